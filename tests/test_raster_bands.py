"""Views composited in bands of tiles (`raster.tile_bands`): the same bits as one pass, tile lists
that stay under their cap.

A view whose tile lists would hold more than `raster.tile_list_cap` entries (a close-up: every
Gaussian covers most tiles; a view far larger than 640x480) is binned and composited band by band,
so the memory plan's figure for them (drsplat.registration.plan.tile_list_bytes) holds. Each tile's
list is the same list in the same depth order, so nothing a caller sees may change.
"""

from __future__ import annotations

import numpy as np
import pytest

from drsplat import _raster_kernels as kernels
from drsplat import raster
from drsplat.raster import bin_tiles, depth_order, project_gaussians, render_projected, render_topk, tile_bands
from drsplat.registration.plan import estimate_memory, tile_list_bytes
from drsplat.testing import front_camera, hard_cases, random_scene

UNLIMITED = 1 << 62


def _close_up(seed: int = 0, n: int = 400):
    """Gaussians of every size in front of a 70x54 camera (tiles of 16: a 5x4 grid, partial edge
    tiles), the biggest covering every tile: lists of very different lengths."""
    rng = np.random.default_rng(seed)
    scene = random_scene(rng, n, log_scale=(-4.0, 1.5))
    return scene, front_camera(70, 54, cx=33.5, cy=28.0)


def _entries_in_tiles(offsets: np.ndarray, tiles: tuple[int, int]) -> int:
    return int(offsets[tiles[1]] - offsets[tiles[0]])


def test_tile_entry_counts_are_the_lengths_of_the_lists():
    scene, camera = _close_up()
    projected = project_gaussians(scene, camera)
    offsets, ids = bin_tiles(projected)
    counts = kernels.tile_entry_counts(projected.tile_rects, *projected.tile_grid)
    np.testing.assert_array_equal(counts, np.diff(offsets))
    assert kernels.tile_entry_total(projected.tile_rects) == ids.size > 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tile_entry_counts_and_total_are_a_numpy_count_of_random_rectangles(seed):
    """Against the obvious reference (each rectangle's tiles incremented in a numpy grid): random rectangles on grids of
    1x1 to 40x30 tiles, empty and inverted ones (invalid Gaussians), single tiles, the whole grid, none (round 66c:
    the kernels were checked on one scene's lists only)."""
    rng = np.random.default_rng(seed)
    for nx, ny in ((1, 1), (40, 30), (7, 1), (1, 9), (13, 11)):
        x = np.sort(rng.integers(0, nx + 1, size=(300, 2)), axis=1)
        y = np.sort(rng.integers(0, ny + 1, size=(300, 2)), axis=1)
        rects = np.stack([x[:, 0], y[:, 0], x[:, 1], y[:, 1]], axis=1).astype(np.int32)
        rects[:20] = rects[:20][:, [2, 3, 0, 1]]  # inverted: counted as empty
        rects[20] = [0, 0, nx, ny]
        rects[21] = [nx - 1, ny - 1, nx, ny]
        rects[22] = [0, 0, 0, ny]
        grid = np.zeros((ny, nx), np.int64)
        for x0, y0, x1, y1 in rects:
            if x1 > x0 and y1 > y0:
                grid[y0:y1, x0:x1] += 1
        np.testing.assert_array_equal(kernels.tile_entry_counts(rects, nx, ny), grid.ravel())
        assert kernels.tile_entry_total(rects) == grid.sum()
    assert not kernels.tile_entry_counts(np.zeros((0, 4), np.int32), 3, 2).any() and kernels.tile_entry_total(np.zeros((0, 4), np.int32)) == 0


@pytest.mark.parametrize("exact", [False, True])
def test_a_band_lists_its_own_tiles_in_the_full_order_and_no_others(exact):
    scene, camera = _close_up(1)
    projected = project_gaussians(scene, camera)
    full_off, full_ids = bin_tiles(projected, exact=exact)
    n_tiles = full_off.size - 1
    order = depth_order(projected)
    for lo, hi in [(0, n_tiles), (0, 1), (3, 4), (2, 9), (4, 6), (n_tiles - 1, n_tiles), (1, n_tiles - 1)]:
        off, ids = bin_tiles(projected, exact=exact, tiles=(lo, hi), order=order)
        lengths = np.diff(off)
        assert not lengths[:lo].any() and not lengths[hi:].any(), (lo, hi)
        for t in range(lo, hi):
            np.testing.assert_array_equal(ids[off[t] : off[t + 1]], full_ids[full_off[t] : full_off[t + 1]])


@pytest.mark.parametrize("cap", [1, 50, 400, 1000])
def test_bands_cover_every_tile_once_and_hold_at_most_the_cap(cap):
    scene, camera = _close_up(2)
    projected = project_gaussians(scene, camera)
    offsets, _ = bin_tiles(projected)
    bands = tile_bands(projected, cap)
    n_tiles = offsets.size - 1
    assert bands[0][0] == 0 and bands[-1][1] == n_tiles
    assert all(a[1] == b[0] for a, b in zip(bands, bands[1:])) and all(lo < hi for lo, hi in bands)
    for band in bands:
        held = _entries_in_tiles(offsets, band)
        assert held <= cap or band[1] - band[0] == 1, (band, held, cap)
    if cap < offsets[-1]:
        assert len(bands) > 1
    # greedy: no two neighbouring bands would fit the cap together
    for a, b in zip(bands, bands[1:]):
        assert _entries_in_tiles(offsets, (a[0], b[1])) > cap


def test_a_view_that_fits_is_one_band():
    scene, camera = _close_up(3)
    projected = project_gaussians(scene, camera)
    assert tile_bands(projected) == [(0, int(np.prod(projected.tile_grid)))]
    with pytest.raises(ValueError, match="max_entries"):
        tile_bands(projected, 0)


def _same(a, b, fields):
    for name in fields:
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=name)


@pytest.mark.parametrize("cap", [1, 30, 700])
@pytest.mark.parametrize("seed", [0, 4])
def test_composited_in_bands_the_view_is_the_same_bits(cap, seed):
    scene, camera = _close_up(seed)
    projected = project_gaussians(scene, camera, with_colors=True)
    assert len(tile_bands(projected, cap)) > 1
    for ranked in (False, True):
        one = render_topk(projected, 7, with_median=True, ranked=ranked, max_tile_entries=UNLIMITED)
        banded = render_topk(projected, 7, with_median=True, ranked=ranked, max_tile_entries=cap)
        _same(one, banded, ("ids", "weights", "alpha", "median_ids"))
        assert banded.tile_entries == one.tile_entries > 0
    one = render_projected(projected, 5, with_rgb=True, with_depth=True, with_median=True, max_tile_entries=UNLIMITED)
    banded = render_projected(projected, 5, with_rgb=True, with_depth=True, with_median=True, max_tile_entries=cap)
    _same(one, banded, ("ids", "weights", "rgb", "depth", "alpha", "median_ids"))
    exact = render_topk(projected, 7, with_median=True, ranked=True, exact_tiles=True, max_tile_entries=cap)
    _same(render_topk(projected, 7, with_median=True, ranked=True, max_tile_entries=UNLIMITED), exact, ("ids", "weights", "alpha", "median_ids"))


@pytest.mark.parametrize("case", hard_cases(), ids=lambda c: c.name)
def test_hard_cases_in_bands_are_the_same_bits(case):
    projected = project_gaussians(case.scene, case.camera)
    one = render_topk(projected, case.topk, with_median=True, ranked=True, max_tile_entries=UNLIMITED)
    banded = render_topk(projected, case.topk, with_median=True, ranked=True, max_tile_entries=3)
    _same(one, banded, ("ids", "weights", "alpha", "median_ids"))


def test_the_default_cap_bands_a_close_up_and_no_list_passes_it(monkeypatch):
    """With the floor lowered to what a 400-Gaussian scene would get without it, a close-up whose
    lists need more than 8 entries per Gaussian is composited in bands, none of whose lists is
    longer than the cap, and the registration's rasterizer returns the one-pass bits."""
    scene, camera = _close_up(5)
    projected = project_gaussians(scene, camera)
    needed = kernels.tile_entry_total(projected.tile_rects)
    monkeypatch.setattr(raster, "MIN_TILE_ENTRIES", 1)
    cap = raster.tile_list_cap(scene.num_gaussians)
    assert cap == raster.TILE_ENTRIES_PER_GAUSSIAN * scene.num_gaussians < needed
    seen = []
    bin_tiles_before = raster.bin_tiles

    def spy(*args, **kwargs):
        offsets, ids = bin_tiles_before(*args, **kwargs)
        seen.append(ids.size)
        return offsets, ids

    monkeypatch.setattr(raster, "bin_tiles", spy)
    banded = raster.rasterize_topk(scene, camera, 9, with_median=True, ranked=True)
    assert len(seen) > 1 and max(seen) <= cap and sum(seen) == needed == banded.tile_entries
    monkeypatch.setattr(raster, "MIN_TILE_ENTRIES", UNLIMITED)
    one = raster.rasterize_topk(scene, camera, 9, with_median=True, ranked=True)
    _same(one, banded, ("ids", "weights", "alpha", "median_ids"))


def test_the_memory_plan_counts_the_capped_lists():
    scene, camera = _close_up(6, n=50)
    plan = estimate_memory(scene, [camera], 16, 8, base=0)
    assert tile_list_bytes(scene.num_gaussians) == raster.MIN_TILE_ENTRIES * raster.TILE_ENTRY_BYTES
    assert plan.views >= tile_list_bytes(scene.num_gaussians)
    many = 10_000_000
    assert tile_list_bytes(many) == raster.TILE_ENTRIES_PER_GAUSSIAN * many * raster.TILE_ENTRY_BYTES
