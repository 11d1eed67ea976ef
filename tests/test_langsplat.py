"""LangSplat's 2D protocol (drsplat.eval.langsplat) against literal ports of its evaluation code."""

from __future__ import annotations

import numpy as np
import pytest

from drsplat.eval import langsplat as ls


def _reflect_101_literal(i: int, n: int) -> int:
    """cv2.borderInterpolate(i, n, BORDER_REFLECT_101), written as the reflection it is."""
    if n == 1:
        return 0
    while i < 0 or i >= n:
        i = -i if i < 0 else 2 * (n - 1) - i
    return i


def _filter2d_literal(img: np.ndarray, size: int) -> np.ndarray:
    """cv2.filter2D(img, -1, ones((size, size)) / size**2): the anchor at size // 2, reflect-101 border."""
    h, w = img.shape
    out = np.zeros((h, w))
    a = size // 2
    for y in range(h):
        for x in range(w):
            total = 0.0
            for ky in range(size):
                for kx in range(size):
                    total += img[_reflect_101_literal(y + ky - a, h), _reflect_101_literal(x + kx - a, w)]
            out[y, x] = total / size**2
    return out


def _smooth_literal(mask: np.ndarray) -> np.ndarray:
    """LangSplat's eval/utils.py `smooth`, line for line (windows never empty for H, W >= 2)."""
    h, w = mask.shape[:2]
    im_smooth = mask.copy()
    scale = 3
    for i in range(h):
        for j in range(w):
            square = mask[max(0, i - scale) : min(i + scale + 1, h - 1), max(0, j - scale) : min(j + scale + 1, w - 1)]
            im_smooth[i, j] = np.argmax(np.bincount(square.reshape(-1)))
    return im_smooth


@pytest.mark.parametrize("shape,size", [((9, 13), 4), ((6, 5), 7), ((3, 40), 30), ((1, 7), 3), ((31, 2), 30), ((20, 20), 5)])
def test_box_filter_is_cv2_filter2d_with_a_reflect_101_border(shape, size):
    """Even and odd kernels, and kernels larger than the image (the border reflects more than once)."""
    img = np.random.default_rng(size).random(shape)
    np.testing.assert_allclose(ls.box_filter(img, size), _filter2d_literal(img, size), rtol=0, atol=1e-12)


@pytest.mark.parametrize("shape,density", [((12, 17), 0.5), ((2, 2), 0.5), ((30, 9), 0.2), ((8, 8), 0.9), ((5, 40), 0.5)])
def test_majority_filter_is_langsplats_smooth(shape, density):
    """Ties (even windows) go to 0, and the last row and column are left out of every window, as there."""
    rng = np.random.default_rng(shape[0] * 100 + shape[1])
    mask = (rng.random(shape) < density).astype(np.uint8)
    np.testing.assert_array_equal(ls.majority_filter(mask.astype(bool)), _smooth_literal(mask).astype(bool))


def test_majority_filter_of_one_row_is_empty():
    """A 1-pixel-high map has empty windows (LangSplat's code fails there): nothing is kept."""
    assert not ls.majority_filter(np.ones((1, 9), bool)).any()


@pytest.mark.parametrize("case", ["random", "padding", "zero-features", "nothing"])
def test_blend_cosines_kernel_equals_the_reference(case):
    rng = np.random.default_rng(len(case))
    h, w, k, d = 7, 9, 5, 32
    ids = rng.integers(0, 50, (h, w, k)).astype(np.int32)
    weights = rng.random((h, w, k)).astype(np.float32)
    if case == "padding":
        ids[..., 3:] = -1
        weights[..., 3:] = 0.0
        ids[0, 0] = -1  # a pixel no Gaussian reaches
    if case == "nothing":
        ids[:] = -1
    present = np.unique(ids[ids >= 0])
    feats = rng.normal(size=(present.size, d)).astype(np.float32)
    if case == "zero-features":
        feats[::2] = 0.0
    emb = rng.normal(size=(3, d)).astype(np.float32)
    emb /= np.linalg.norm(emb, axis=1, keepdims=True)
    got = ls.blend_cosines(ids, weights, feats, emb)
    want = ls.blend_cosines_reference(ids, weights, feats, emb)
    assert got.shape == (3, h, w)
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)
    if case in ("padding", "nothing"):
        assert (got[:, 0, 0] == 0).all()  # no feature: cosine 0, not NaN
    assert np.isfinite(got).all() and np.abs(got).max() <= 1 + 1e-6



def test_an_embeddings_cosines_are_the_same_bits_whatever_the_others():
    """The query's cosine map alone, beside the negatives, and beside them repeated are the same bits
    (round 50: repeating two negatives rounded the query's map otherwise, by up to 4.8e-7, and moved
    the box-filtered peak out of its box: localization 0.5517 -> 0.5172)."""
    rng = np.random.default_rng(50)
    h, w, k, d = 40, 60, 8, 512
    ids = rng.integers(0, 300, (h, w, k)).astype(np.int32)
    weights = rng.random((h, w, k)).astype(np.float32)
    feats = rng.normal(size=(np.unique(ids).size, d)).astype(np.float32)
    emb = rng.normal(size=(6, d)).astype(np.float32)
    emb /= np.linalg.norm(emb, axis=1, keepdims=True)
    alone = ls.blend_cosines(ids, weights, feats, emb[:1])
    for others in (emb, np.concatenate([emb, emb[1:3]]), emb[[0, 5, 4, 3, 2, 1, 1]]):
        np.testing.assert_array_equal(ls.blend_cosines(ids, weights, feats, others)[0], alone[0])

def test_langsplat_mask_finds_a_bright_disc_and_the_peak_its_box():
    yy, xx = np.mgrid[:120, :160]
    disc = (yy - 60) ** 2 + (xx - 100) ** 2 <= 25**2
    rel = np.where(disc, 0.9, 0.4) + 0.01 * np.random.default_rng(0).random((120, 160))
    pred = ls.langsplat_mask(rel)
    iou = (pred & disc).sum() / (pred | disc).sum()
    assert iou > 0.7  # the mean filter widens the map; the threshold on its rescaled values takes the core
    assert ls.peak_in_boxes(rel, np.array([[75, 35, 125, 85]]))
    assert ls.peak_in_boxes(rel, np.array([[125, 85, 75, 35]]))  # corners in either order
    assert not ls.peak_in_boxes(rel, np.array([[0, 0, 40, 40], [130, 90, 159, 119]]))
    assert not ls.peak_in_boxes(rel, np.zeros((0, 4)))


def test_a_view_too_large_for_memory_is_one_error_naming_it(monkeypatch):
    """An annotation may be 8x its camera's size; its top-k lists are refused before any allocation."""
    from pathlib import Path

    from drsplat.errors import DrsplatError
    from drsplat.eval.datasets import AnnotatedView

    view = AnnotatedView("frame_00001", 8000, 6000, {}, path=Path("label/frame_00001.json"))
    assert ls.view_bytes(8000, 6000, 40, 12) > 20e9
    monkeypatch.setattr(ls, "available_memory", lambda: 4 << 30)
    with pytest.raises(DrsplatError, match=r"frame_00001.json: view frame_00001 is annotated at 8000x6000.*--topk"):
        ls.check_view_memory(view, 40, 12)
    ls.check_view_memory(AnnotatedView("v", 986, 728, {}), 40, 12)  # a LERF-OVS view fits
