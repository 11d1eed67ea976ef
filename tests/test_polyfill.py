"""OpenCV's polygon fill without OpenCV (drsplat.eval.polyfill): the ground-truth masks of LangSplat's
LERF-OVS evaluation, pixel for pixel."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from drsplat.eval.datasets import mask_to_polygons, polygon_mask
from drsplat.eval.polyfill import (
    fill_polygon,
    line_pixels,
    line_pixels_reference,
    clipped_segments,
    lines_pixels,
    outline_pixels,
    scanline_spans,
    truncate_vertices,
)

FIXTURE = Path(__file__).parent / "data" / "cv2_fillpoly.npz"  # written by tests/data/make_cv2_fillpoly.py with cv2 5.0.0


def stored_cases():
    data = np.load(FIXTURE)
    vertices = np.split(data["vertices"], np.cumsum(data["counts"])[:-1])
    bits = np.split(data["mask_bits"], np.cumsum(data["mask_bytes"])[:-1])
    for v, (h, w), b in zip(vertices, data["shapes"], bits):
        yield v, int(h), int(w), np.unpackbits(b)[: h * w].reshape(h, w).astype(bool)


def test_the_fill_paints_the_pixels_cv2_painted():
    """360 polygons cv2.fillPoly filled (random, inside the image, far outside, on a coarse grid with
    level and upright edges, thin slivers, stars crossing the border; 1 to 16 vertices)."""
    cases = list(stored_cases())
    assert len(cases) == 360
    wrong = [i for i, (v, h, w, expected) in enumerate(cases) if not np.array_equal(fill_polygon(v, h, w), expected)]
    assert wrong == []
    assert sum(int(c[3].sum()) for c in cases) > 50_000  # the cases paint something


def import_cv2():
    """cv2, or a skip; its import sets LD_LIBRARY_PATH for the process, which is put back."""
    before = os.environ.get("LD_LIBRARY_PATH")
    try:
        return pytest.importorskip("cv2", reason="opencv-python is not installed; the stored cv2 masks are checked without it")
    finally:
        if before is None:
            os.environ.pop("LD_LIBRARY_PATH", None)
        else:
            os.environ["LD_LIBRARY_PATH"] = before


def test_the_fill_in_small_pieces_paints_the_same_pixels():
    """At most 7 pixels, crossings or marks at a time: one row per band, one edge per run."""
    for v, h, w, expected in list(stored_cases())[::3]:
        assert np.array_equal(fill_polygon(v, h, w, max_entries=7), expected)


def test_the_fill_agrees_with_cv2_on_new_polygons():
    cv2 = import_cv2()
    rng = np.random.default_rng(7)
    for trial in range(300):
        h, w = (int(v) for v in rng.integers(1, 120, 2))
        p = int(rng.integers(1, 40))
        spread = [20, 400, 100_000][trial % 3]
        v = rng.integers(-spread, max(h, w) + spread, (p, 2))
        expected = np.zeros((h, w), np.uint8)
        cv2.fillPoly(expected, [v.astype(np.int32)], 1)
        assert np.array_equal(fill_polygon(v, h, w), expected.astype(bool)), (h, w, v.tolist())


def test_closed_form_lines_match_the_step_by_step_walk():
    rng = np.random.default_rng(3)
    ends = [((0, 0), (0, 0)), ((0, 0), (9, 0)), ((0, 0), (0, 9)), ((0, 0), (9, 9)), ((9, 0), (0, 9)), ((5, 5), (0, 4)), ((0, 0), (1, 7))]
    ends += [(tuple(int(c) for c in rng.integers(0, 50, 2)), tuple(int(c) for c in rng.integers(0, 50, 2))) for _ in range(3000)]
    for a, b in ends:
        assert np.array_equal(line_pixels(a, b), line_pixels_reference(a, b)), (a, b)
    together = lines_pixels(np.array([[*a, *b] for a, b in ends]))  # many lines in one call: the same pixels, line after line
    assert np.array_equal(together, np.concatenate([line_pixels_reference(a, b) for a, b in ends]))
    # 8-connected: each step moves one pixel along the major axis
    px = line_pixels((3, 40), (47, 2))
    assert len(px) == 45 and (np.abs(np.diff(px, axis=0)).max(axis=1) == 1).all()


@pytest.mark.parametrize("cap", [1, 5, 64])
def test_rows_in_bands_give_the_same_spans(cap):
    rng = np.random.default_rng(cap)
    for _ in range(40):
        v = rng.integers(-30, 130, (int(rng.integers(3, 30)), 2))
        whole = np.concatenate([np.stack(s[2:], 1) for s in scanline_spans(clipped_segments(v, 90, 110), 90, 110)] or [np.zeros((0, 3), np.int64)])
        banded = np.concatenate([np.stack(s[2:], 1) for s in scanline_spans(clipped_segments(v, 90, 110), 90, 110, max_entries=cap)] or [np.zeros((0, 3), np.int64)])
        assert np.array_equal(whole[np.lexsort(whole.T[::-1])], banded[np.lexsort(banded.T[::-1])])


@pytest.mark.parametrize("cap", [1, 50])
def test_outline_in_runs_of_edges_gives_the_same_pixels(cap):
    rng = np.random.default_rng(cap)
    for _ in range(20):
        v = rng.integers(-40, 140, (int(rng.integers(1, 25)), 2))
        whole = np.concatenate(list(outline_pixels(clipped_segments(v, 90, 110))) or [np.zeros((0, 2), np.int64)])
        runs = np.concatenate(list(outline_pixels(clipped_segments(v, 90, 110), max_pixels=cap)) or [np.zeros((0, 2), np.int64)])
        assert np.array_equal(whole, runs)
        assert ((whole >= 0) & (whole < [110, 90])).all()  # clipped to the image


def test_float_vertices_are_truncated_toward_zero_as_langsplat_casts_them():
    poly = np.array([[-0.7, -0.9], [12.9, 0.99], [6.5, 9.999]])
    assert truncate_vertices(poly).tolist() == [[0, 0], [12, 0], [6, 9]]
    assert truncate_vertices(poly).tolist() == np.asarray(poly, np.int32).tolist()  # LangSplat's cast
    assert np.array_equal(polygon_mask(poly, 12, 16), fill_polygon(np.array([[0, 0], [12, 0], [6, 9]]), 12, 16))


def test_the_outline_is_painted_with_its_corners():
    m = polygon_mask(np.array([[2, 2], [6, 2], [6, 6], [2, 6]]), 10, 10)
    assert m.sum() == 25 and m[2:7, 2:7].all()  # cv2 paints the square's edges too: 5 x 5
    line = polygon_mask(np.array([[1, 1], [8, 1]]), 10, 10)  # two vertices: cv2.fillPoly draws the line (round 89a F1: nothing)
    assert line.sum() == 8 and line[1, 1:9].all()


def test_masks_written_as_polygons_come_back():
    """write_lerf_view's polygons run through the mask's boundary pixel centres, so LangSplat's fill
    paints a rectangle, a disk, an L and masks with holes back exactly (round 59b: holes were filled, and concave
    corners cut by a polygon simplified to 0.5 px)."""
    yy, xx = np.mgrid[0:60, 0:80]
    rect = (yy >= 35) & (yy < 55) & (xx >= 50) & (xx < 75)
    disk = (yy - 20) ** 2 + (xx - 25) ** 2 <= 144
    ring = ((yy - 30) ** 2 + (xx - 40) ** 2 <= 400) & ((yy - 30) ** 2 + (xx - 40) ** 2 > 64)
    ell = ((yy >= 10) & (yy < 50) & (xx >= 10) & (xx < 20)) | ((yy >= 40) & (yy < 50) & (xx >= 10) & (xx < 60))
    frame = (yy >= 10) & (yy < 50) & (xx >= 10) & (xx < 70)
    for y0, y1, x0, x1 in ((20, 30, 20, 30), (35, 45, 40, 60), (15, 18, 50, 52)):  # three holes, one in another's column range
        frame &= ~((yy >= y0) & (yy < y1) & (xx >= x0) & (xx < x1))
    checker = ((yy + xx) % 2 == 0) & (yy < 12) & (xx < 12)  # round 60a: components under 4 px were left out
    diagonal = (yy == xx) & (yy < 10)
    pinholes = np.random.default_rng(0).random((60, 80)) >= 0.02
    for mask in (rect, disk, ring, ell, frame, rect | ring, checker, diagonal, pinholes):
        back = np.zeros_like(mask)
        for poly in mask_to_polygons(mask):
            back |= polygon_mask(poly, 60, 80)
        assert (back == mask).all()
    # round 60a: a cut per hole column, recursively, passed Python's recursion limit on a 480x640 mask with 0.5 % pinholes
    big = np.random.default_rng(1).random((480, 640)) >= 0.005
    back = np.zeros_like(big)
    for poly in mask_to_polygons(big):
        back |= polygon_mask(poly, 480, 640)
    assert (back == big).all()
