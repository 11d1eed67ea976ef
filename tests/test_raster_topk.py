"""The registration's top-k rasterizer (`raster.render_topk` / `rasterize_topk`) against the reference kernel.

The reference is `render_projected` (the float64 compositor every engine agrees with), itself
held to the numpy per-pixel `composite_reference` in tests/test_raster.py. The top-k path runs the
same float64 arithmetic, so ranked output must be identical bit for bit; unranked output must
hold the same (id, weight) entries per pixel; the exact tile sets must not change anything.
"""

from __future__ import annotations

import numpy as np
import pytest

from drsplat import _raster_kernels as kernels
from drsplat import raster
from drsplat.cameras import look_at_camera
from drsplat.raster import bin_tiles, project_gaussians, render_projected, render_topk, rasterize_reference, rasterize_topk
from drsplat.registration.sums import normalize_rows, normalize_rows_reference
from drsplat.scene import load_ply
from drsplat.testing import RasterCase, assert_agree, assert_physical, front_camera, gaussians, hard_cases, random_case, random_scene
from tests.conftest import shared_path


def _near_threshold_case() -> RasterCase:
    """Opacities within a hair of 1/255 (α ≥ 1/255 only right at the centre, or nowhere), big and tiny
    Gaussians, and pairs of equal Gaussians (exact weight ties at the k-th slot)."""
    rng = np.random.default_rng(5)
    scene = random_scene(rng, 300, log_scale=(-6.0, 0.5))
    logit = np.log((1 / 255) / (1 - 1 / 255))
    scene.opacity_logits[:80] = logit + rng.uniform(-1e-4, 1e-3, 80).astype(np.float32)
    scene.means[150:200] = scene.means[100:150]  # identical twins: ties in every pixel they cover
    scene.quats[150:200], scene.log_scales[150:200] = scene.quats[100:150], scene.log_scales[100:150]
    scene.opacity_logits[150:200] = scene.opacity_logits[100:150]
    return RasterCase("near-1/255-and-ties", scene, front_camera(48, 40, cx=21.0, cy=22.5), 6, dict(with_median=True))


def _cases() -> list[RasterCase]:
    return [random_case(s, topk=k) for s, k in ((0, 8), (1, 3), (2, 40))] + hard_cases() + [_near_threshold_case()]


def _sorted_by_id(ids: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's slots ordered by id (-1 last): a canonical form of an unordered top-k list."""
    key = np.where(ids < 0, np.iinfo(np.int32).max, ids)
    order = np.argsort(key, axis=-1, kind="stable")
    return np.take_along_axis(ids, order, -1), np.take_along_axis(weights, order, -1)


@pytest.mark.parametrize("case", _cases(), ids=lambda c: c.name)
def test_topk_path_gives_the_reference_kernels_lists_bit_for_bit(case):
    with_median = bool(case.kwargs.get("with_median", False))
    projected = project_gaussians(case.scene, case.camera)
    ref = render_projected(projected, case.topk, with_median=with_median)
    for exact_tiles in (False, True):
        ranked = render_topk(projected, case.topk, with_median=with_median, ranked=True, exact_tiles=exact_tiles)
        np.testing.assert_array_equal(ranked.ids, ref.ids)
        np.testing.assert_array_equal(ranked.weights, ref.weights)
        np.testing.assert_array_equal(ranked.alpha, ref.alpha)
        if with_median:
            np.testing.assert_array_equal(ranked.median_ids, ref.median_ids)
        assert_physical(ranked, case.topk)
        loose = render_topk(projected, case.topk, with_median=with_median, ranked=False, exact_tiles=exact_tiles)
        for a, b in zip(_sorted_by_id(loose.ids, loose.weights), _sorted_by_id(ref.ids, ref.weights)):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(loose.alpha, ref.alpha)
        # unordered slots keep their -1 padding after the filled ones (the fit's re-render stops at the first -1)
        assert not ((loose.ids[..., 1:] >= 0) & (loose.ids[..., :-1] < 0)).any()


@pytest.mark.parametrize("case", [random_case(3, topk=8), _near_threshold_case()], ids=lambda c: c.name)
def test_topk_path_agrees_with_the_numpy_reference(case):
    """Against the per-pixel numpy compositor: ids identical except between weights that tie, weights within 1e-5."""
    a = rasterize_topk(case.scene, case.camera, case.topk, with_median=True, ranked=True)
    b = rasterize_reference(case.scene, case.camera, case.topk, with_median=True)
    b.rgb = b.depth = None
    assert_agree(a, b)


@pytest.mark.parametrize("tile_size", [1, 5, 37, 64])
def test_any_tile_size_up_to_64_gives_the_reference_lists(tile_size):
    """Tile rows are 64-bit lane masks: rows of 1 to 64 pixels (64: every bit, the mask's edge case)."""
    scene = random_scene(np.random.default_rng(6), 600)
    cam = look_at_camera([0.3, -0.2, -4.0], [0.0, 0.0, 0.0], 140, 70, fov_x_deg=55, cx=66.2, cy=30.7)  # full 64-pixel rows and a ragged edge
    projected = project_gaussians(scene, cam, tile_size=tile_size)
    ref = render_projected(projected, 6, with_median=True)
    ranked = render_topk(projected, 6, with_median=True, ranked=True)
    assert (ref.ids >= 0).any()
    for name in ("ids", "weights", "alpha", "median_ids"):
        np.testing.assert_array_equal(getattr(ranked, name), getattr(ref, name))


@pytest.mark.parametrize("k", [65, 70])
def test_buffers_over_64_slots_replace_their_lightest_entries_as_the_reference_does(k):
    """k > 64: the slots of equal smallest weight span two 64-bit tie masks (`lightest_slot`).
    Faint, wide, overlapping Gaussians give pixels more than k contributions, with ties."""
    rng = np.random.default_rng(k)
    scene = random_scene(rng, 900, log_scale=(-1.5, -0.5))
    scene.opacity_logits[:] = rng.normal(-3.5, 0.5, scene.num_gaussians).astype(np.float32)  # faint: T stays high
    scene.means[450:], scene.quats[450:], scene.log_scales[450:] = scene.means[:450], scene.quats[:450], scene.log_scales[:450]
    scene.opacity_logits[450:] = scene.opacity_logits[:450]  # identical twins: exact ties
    cam = look_at_camera([0.0, 0.0, -5.0], [0.0, 0.0, 0.0], 40, 30, fov_x_deg=50)
    projected = project_gaussians(scene, cam)
    wide = render_projected(projected, 4 * k)
    assert ((wide.ids >= 0).sum(-1) > k).mean() > 0.3  # many pixels replace entries
    ref = render_projected(projected, k, with_median=True)
    for ranked in (True, False):
        got = render_topk(projected, k, with_median=True, ranked=ranked)
        for a, b in zip(_sorted_by_id(got.ids, got.weights), _sorted_by_id(ref.ids, ref.weights)):
            np.testing.assert_array_equal(a, b)
        if ranked:
            np.testing.assert_array_equal(got.ids, ref.ids)
        np.testing.assert_array_equal(got.alpha, ref.alpha)
        np.testing.assert_array_equal(got.median_ids, ref.median_ids)


def test_topk_path_refuses_tiles_wider_than_its_masks():
    case = random_case(6, topk=6)
    projected = project_gaussians(case.scene, case.camera, tile_size=65)
    with pytest.raises(ValueError, match="tile_size 65 is over 64"):
        render_topk(projected, case.topk)


def test_exact_tile_sets_are_subsets_of_getrect_and_smaller():
    rng = np.random.default_rng(9)
    scene = random_scene(rng, 3000, log_scale=(-4.0, -1.0))
    scene.opacity_logits[:] = rng.normal(-3.0, 2.0, scene.num_gaussians).astype(np.float32)  # many faint ones: small α ellipses
    cam = look_at_camera([0.2, -0.1, -4.0], [0.0, 0.0, 0.0], 160, 120, fov_x_deg=55)
    projected = project_gaussians(scene, cam)
    full_off, full_ids = bin_tiles(projected, exact=False)
    off, ids = bin_tiles(projected, exact=True)
    assert 0 < ids.size < 0.9 * full_ids.size
    for t in range(off.size - 1):
        kept, every = ids[off[t] : off[t + 1]], full_ids[full_off[t] : full_off[t + 1]]
        assert np.isin(kept, every).all()
        np.testing.assert_array_equal(kept, every[np.isin(every, kept)])  # same front-to-back order


def test_views_that_see_nothing():
    scene = gaussians([[0.0, 0.0, -9.0], [5.0, 5.0, 0.0]])  # behind the camera, and far off-screen
    out = rasterize_topk(scene, front_camera(20, 16), 5, with_median=True)
    assert (out.ids == -1).all() and (out.weights == 0).all() and (out.alpha == 0).all() and (out.median_ids == -1).all()


def test_rasterize_topk_refuses_colour_and_depth():
    with pytest.raises(ValueError, match="ids, weights, alpha and the median only"):
        rasterize_topk(gaussians([[0.0, 0.0, 0.0]]), front_camera(), 4, with_rgb=True)


def test_registration_uses_the_topk_path_for_numba_only():
    assert raster.get_engine("numba").topk_fn() is rasterize_topk
    assert raster.get_engine("reference").topk_fn() is raster.rasterize_reference


@pytest.mark.parametrize("k", [1, 3, 8, 40, 64, 65, 130])
def test_topk_buffer_keeps_the_first_k_of_a_stable_sort_with_ties(k):
    rng = np.random.default_rng(k)
    out_ids, out_w = np.empty((1, 1, k), np.int32), np.empty((1, 1, k), np.float32)
    for trial in range(300):
        n = int(rng.integers(0, 4 * k + 2))
        levels = rng.uniform(0.01, 1.0, size=int(rng.integers(1, 4)))
        w = rng.choice(levels, n) if trial % 2 else rng.uniform(0.0, 1.0, n)  # many exact ties / none
        wbuf, sbuf = np.empty((2, k)), np.empty((2, k), np.int32)
        count, evict = np.zeros(2, np.int64), np.zeros(2, np.int64)
        for g, wg in enumerate(w):
            kernels.offer_topk(wbuf, wbuf.view(np.int64), sbuf, count, evict, 1, wg, g)
        best = np.argsort(-w, kind="stable")[:k]
        assert count[1] == best.size
        kernels.write_ranked(wbuf, sbuf, count[1], 1, np.arange(n, dtype=np.int32), out_ids, out_w, 0, 0, True)
        np.testing.assert_array_equal(out_ids[0, 0, : best.size], best)
        np.testing.assert_array_equal(out_w[0, 0, : best.size], w[best].astype(np.float32))
        assert (out_ids[0, 0, best.size :] == -1).all()


def test_topk_path_on_real_flowers_views():
    scene = load_ply(shared_path("ply", "flowers.ply"))
    from drsplat.bench.register import orbit_cameras  # the bench's views of a real scene

    prepared = raster.prepare_scene(scene)
    for cam in orbit_cameras(scene.means, 12, 96, 72)[::4]:
        projected = project_gaussians(prepared, cam)
        ref = render_projected(projected, 40, with_median=True)
        ranked = render_topk(projected, 40, with_median=True, ranked=True, exact_tiles=True)
        assert (ref.ids >= 0).mean() > 0.3  # the view sees the scene
        np.testing.assert_array_equal(ranked.ids, ref.ids)
        np.testing.assert_array_equal(ranked.weights, ref.weights)
        np.testing.assert_array_equal(ranked.median_ids, ref.median_ids)


def test_normalize_rows_matches_its_reference():
    rng = np.random.default_rng(4)
    F = rng.normal(size=(500, 37)).astype(np.float32) * rng.uniform(1e-3, 1e6, (500, 1)).astype(np.float32)
    W = rng.uniform(0.0, 2.0, 500).astype(np.float32)
    W[:20] = 0.0
    F[20:30] = 0.0  # a sum that cancelled exactly: dropped and counted
    F[55:60] = F[55:60] / np.linalg.norm(F[55:60], axis=1, keepdims=True) * (W[55:60, None] * 0.99e-4)  # cancelled to rounding
    F[60:65] = F[60:65] / np.linalg.norm(F[60:65], axis=1, keepdims=True) * (W[60:65, None] * 1.01e-4)  # kept
    F[65:70] = F[65:70] / np.linalg.norm(F[65:70], axis=1, keepdims=True) * (W[65:70, None] * 0.049)  # kept, counted weak
    F[70:74] = F[70:74] / np.linalg.norm(F[70:74], axis=1, keepdims=True) * (W[70:74, None] * 0.051)  # kept, not weak
    F[30:35, 3] = np.nan
    F[35:40, 0] = np.inf
    W[40:45] = np.nan
    F[45:50] = 1e36  # squares overflow float32, not the float64 sum
    F[50:55] = 1e38  # the norm itself passes float32's range (6e38): divided in float64, not zeroed (round 22)
    F[74:79] = rng.choice([1e-44, 3e-44, 7e-44], (5, 37))  # subnormal sums: a float32 norm of a few bits gave length 0.88-0.98 (round 56a)
    W[74:79] = 1e-42
    a, wa = F.copy(), W.copy()
    b, wb = F.copy(), W.copy()
    _, bad_a = normalize_rows(a, wa)
    _, bad_b = normalize_rows_reference(b, wb)
    assert bad_a == bad_b
    assert bad_a.dropped == 30 and bad_a.weak == 10  # rows 60-69: the five kept at 1.01e-4 of their weight and the five at 0.049
    assert bad_a.nonfinite == 15  # rows 30-44 (NaN, inf, NaN weight) of the 30; the other 15 cancelled
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(wa, wb)
    ok = wa > 0
    np.testing.assert_allclose(np.linalg.norm(a[ok].astype(np.float64), axis=1), 1.0, rtol=1e-6)
    assert ok[50:55].all() and np.allclose(a[50:55], 1 / np.sqrt(37), rtol=1e-6) and ok[74:79].all()
    assert not ok[20:30].any() and not ok[55:60].any() and ok[60:65].all()


def test_dropped_sums_are_said_by_their_cause():
    """Was (round 45, left as found): Gaussians whose weight overflowed float32 (`--aggregate anchor`
    on log scales past ~50) were dropped and counted, but the warning said their masks' embeddings
    point opposite ways. Non-finite and cancelled sums are now counted and said apart."""
    from drsplat.registration.driver import unusable_sums
    from drsplat.registration.sums import RowFates

    both = unusable_sums(RowFates(dropped=5, nonfinite=2))
    assert both.startswith("2 Gaussians got a non-finite feature sum or weight (a weight beyond float32's range")
    assert "; 3 Gaussians got feature sums that cancel out" in both and both.endswith("; they are left unassigned")
    assert "cancel" not in unusable_sums(RowFates(dropped=2, nonfinite=2))
    assert "non-finite" not in unusable_sums(RowFates(dropped=2))
    assert RowFates(3, 1, 2) + RowFates(1, 0, 1) == RowFates(4, 1, 3)


def test_normalize_rows_judges_a_trimmed_sum_against_the_weight_it_still_holds():
    """Block.kept (the weight an exactly trimmed sum still holds) is what a norm is judged against:
    a row holding 1.8 of weight 20,001.8 after the vote removed a close-up view (|F| = 1.8) is kept
    and not counted weak, while judged against W it would be dropped as cancelled; the same row
    without `kept` is; a row whose kept sum did cancel is still dropped; kernel and reference agree,
    and NaN in kept drops the row as a non-finite weight does."""
    rng = np.random.default_rng(5)
    F = rng.normal(size=(6, 16)).astype(np.float32)
    F /= np.linalg.norm(F, axis=1, keepdims=True)
    W = np.full(6, 20001.8, np.float32)
    kept = np.full(6, 1.8, np.float32)
    F[:4] *= 1.8  # the far views' clean sums
    F[4] *= 1e-5  # a kept sum that cancelled
    kept[5] = np.nan
    for kernel in (normalize_rows, normalize_rows_reference):
        f, w = F.copy(), W.copy()
        _, fates = kernel(f, w, kept=kept)
        assert (w[:4] > 0).all() and w[4] == 0 and w[5] == 0
        assert fates.dropped == 2 and fates.weak == 0 and fates.nonfinite == 1
        np.testing.assert_allclose(f[:4], F[:4] / 1.8, rtol=1e-6)
        f, w = F.copy(), W.copy()
        _, fates = kernel(f, w)
        assert fates.dropped == 6 and not (w > 0).any()  # against W every one looks cancelled
    with pytest.raises(ValueError, match="kept has shape"):
        normalize_rows(F.copy(), W.copy(), kept=kept[:5])


def test_a_scene_of_float16_arrays_renders_as_its_values_in_float32():
    """Round 56a: a GaussianScene built with float16 arrays (its SH, quaternions, ...) raised NotImplementedError from
    numba, which loads no float16. Each array is read as float32 now: the same top-k lists, bit for bit, as the scene
    whose arrays hold the same values in float32."""
    import dataclasses

    scene = random_scene(np.random.default_rng(0), 60)
    names = ("means", "quats", "log_scales", "opacity_logits", "sh")
    half = dataclasses.replace(scene, **{name: getattr(scene, name).astype(np.float16) for name in names})
    widened = dataclasses.replace(scene, **{name: getattr(half, name).astype(np.float32) for name in names})
    got, want = rasterize_topk(half, front_camera(), 6), rasterize_topk(widened, front_camera(), 6)
    np.testing.assert_array_equal(got.ids, want.ids)
    np.testing.assert_array_equal(got.weights, want.weights)
    assert (got.ids >= 0).any()
