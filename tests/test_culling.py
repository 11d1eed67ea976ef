"""Exact frustum culling (drsplat.registration.culling): the same top-k lists and field bytes as
projecting every Gaussian, on views that see all of a scene and views that see a small part of it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from drsplat.cameras import load_cameras, look_at_camera
from drsplat.raster import NEAR, prepare_scene, project_gaussians, rasterize
from drsplat.testing import gaussians
from drsplat.registration import RegisterOptions, register
from drsplat.registration import aggregate
from drsplat.registration.aggregate import RayGeometry, mode_hook
from drsplat.registration.compute import renders_whole, ViewComputer, ViewJob, prepare_geometry
from drsplat.raster import subset_geometry, subset_geometry_reference
from drsplat.registration.culling import (SpatialIndex, largest_eigenvalues, largest_eigenvalues_reference, morton_codes, remap_ids,
                                         remap_ids_reference)
from drsplat.scene import load_ply
from drsplat.synthetic import tile_city, write_dataset


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("tiny") / "data", "tiny", 0, show_progress=False)


@pytest.fixture(scope="module")
def city(tiny):
    """16 copies of the tiny room on a grid; each view looks into one room (sees a small part)."""
    scene, cams = load_ply(tiny / "scene.ply"), load_cameras(tiny)
    city_scene, city_cams, _ = tile_city(scene, cams, 16, 12, 64)
    return city_scene, city_cams


def _hard_cameras(cams):
    """The room's first camera pulled back (sees everything), moved past the room (sees nothing), off-centre."""
    cam = cams[0]
    back = dataclasses.replace(cam, t=np.asarray(cam.t) + np.array([0.0, 0.0, 30.0]), name="far")
    away = dataclasses.replace(cam, t=np.asarray(cam.t) + np.array([0.0, 0.0, -100.0]), name="away")  # all behind it
    shifted = dataclasses.replace(cam, cx=cam.cx + 0.7 * cam.width, name="offcentre")
    return [back, away, shifted]


def _render_both(scene, cams, topk=6):
    prep = prepare_scene(scene)
    index = SpatialIndex.build(prep, block_size=64)
    seen = []
    for cam in cams:
        full = rasterize(prep, cam, topk, with_median=True)
        ids = index.visible(cam)
        mask = np.zeros(prep.num_gaussians, bool)
        mask[ids] = True
        culled = rasterize(prep, cam, topk, with_median=True, mask=mask)
        np.testing.assert_array_equal(culled.ids, full.ids, err_msg=cam.name)
        np.testing.assert_array_equal(culled.weights, full.weights, err_msg=cam.name)
        np.testing.assert_array_equal(culled.median_ids, full.median_ids, err_msg=cam.name)
        seen.append(ids.size / prep.num_gaussians)
    return seen


def test_culled_renders_equal_full_renders_in_the_room(tiny):
    scene, cams = load_ply(tiny / "scene.ply"), load_cameras(tiny)
    seen = _render_both(scene, list(cams) + _hard_cameras(cams))
    assert seen[-3] > 0.9  # pulled back: the whole room is in view
    assert seen[-2] == 0.0  # turned away: nothing


def test_city_views_see_a_small_part_and_render_the_same(city):
    scene, cams = city
    seen = _render_both(scene, cams[:6])
    assert np.mean(seen) < 0.5, seen


@pytest.mark.parametrize("weighting", [None, "sharp", "anchor", "sharp-reject"])
def test_view_computer_pairs_equal_with_and_without_culling(city, weighting, monkeypatch):
    """The same pairs, bit for bit, whether a view renders its culled subset or the whole scene; a
    weighting that reads the projection (sharp, anchor) reads the culled render's own, by scene id,
    instead of projecting the whole scene again; floater statistics (`-reject`) are the same too,
    a culled view's made over its projected Gaussians only."""
    projections = []
    monkeypatch.setattr(aggregate, "project_gaussians", lambda *args: projections.append(args) or project_gaussians(*args))
    scene, cams = city
    geometry = prepare_geometry(scene)
    rng = np.random.default_rng(3)
    rays = RayGeometry.from_scene(scene) if weighting and weighting.endswith("-reject") else None
    hooks = [mode_hook(weighting, rays) if weighting else None for _ in range(2)]
    culled = ViewComputer(geometry, ViewJob(Path("."), 0, 5, cull=True, hook=hooks[0]))
    full = ViewComputer(geometry, ViewJob(Path("."), 0, 5, cull=False, hook=hooks[1]))
    n = geometry.num_gaussians
    overview = dataclasses.replace(cams[0], t=np.asarray(cams[0].t) + np.array([0.0, 0.0, 60.0]), name="overview")  # the whole city in view
    projected = []
    for cam in cams[:4] + [overview]:
        masks = rng.integers(-1, 7, (cam.height, cam.width)).astype(np.int32)
        feats = rng.normal(size=(7, 8)).astype(np.float32)
        before = culled.projected
        a, b = culled.compute(cam, masks, feats), full.compute(cam, masks, feats)
        projected.append(culled.projected - before)
        for field in ("gaussians", "masks", "weights", "used"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=f"{cam.name} {field}")
        assert a.num_pairs == b.num_pairs > 0
        if rays is not None:
            for field in ("ids", "peak", "total", "front"):
                np.testing.assert_array_equal(getattr(a.stats, field), getattr(b.stats, field), err_msg=f"{cam.name} stats {field}")
            assert 0 < a.stats.ids.size
    assert max(projected[:4]) < 0.35 * n  # room views render their culled subset
    slots = overview.width * overview.height * 5
    assert projected[4] == n and renders_whole(culled._index.visible(overview).size, n, slots)  # most of the city in view: rendered whole
    assert projections == []  # the hooks read the renders' own projections, never the scene's projected again
    if weighting == "anchor":  # the culled views' projections were scattered by scene id
        assert hooks[0]._means2d is not None and hooks[1]._means2d is None
    if weighting and weighting.startswith("sharp"):  # their sharp table rows were made from the culled rows themselves
        assert hooks[0]._means2d is None and hooks[0]._screen is not None


def test_registered_field_bytes_equal_with_and_without_culling(tiny, tmp_path):
    scene, cams = load_ply(tiny / "scene.ply"), load_cameras(tiny)
    paths = []
    for cull in (True, False):
        path = tmp_path / f"cull{cull}.ply"
        register(scene, cams, tiny / "features", path, RegisterOptions(cull=cull), show_progress=False)
        paths.append(path.read_bytes())
    assert paths[0] == paths[1]


def test_nonfinite_gaussians_are_left_out_of_the_index(tiny):
    prep = prepare_scene(load_ply(tiny / "scene.ply"))
    prep.means[5] = np.nan
    prep.finite[5] = False
    index = SpatialIndex.build(prep, block_size=100)
    assert 5 not in index.order
    assert index.order.size == prep.num_gaussians - 1
    assert np.isfinite(index.lo).all()


def test_morton_codes_order_nearby_points_together():
    pts = np.array([[0.0, 0, 0], [1, 1, 1], [0.01, 0, 0], [0.99, 1, 1]])
    order = np.argsort(morton_codes(pts))
    assert {int(order[0]), int(order[1])} == {0, 2}


def test_synth_city_is_the_bench_city_and_registers(tmp_path):
    from drsplat.synthetic import CityPreset, write_city

    preset = CityPreset(room="tiny", tiles=4, views=8, width=48)
    out = write_city(tmp_path / "city", preset, show_progress=False)
    assert not (out / "room").exists()
    scene, cams = load_ply(out / "scene.ply"), load_cameras(out, require_images=False)
    room = write_dataset(tmp_path / "room", "tiny", 0, show_progress=False)
    expect, expect_cams, _ = tile_city(load_ply(room / "scene.ply"), load_cameras(room), 4, 8, 48)
    np.testing.assert_array_equal(scene.means, expect.means)
    assert [c.name for c in cams] == [c.name for c in expect_cams]
    assert np.load(out / "gt" / "labels.npy").shape == (scene.num_gaussians,)
    reg = register(scene, cams, out / "features", tmp_path / "field.ply", RegisterOptions(), show_progress=False)
    assert reg.num_views == 8 and reg.num_pairs > 0


def _rotations(rng, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


@pytest.mark.parametrize("case", ["random", "needles_and_discs", "isotropic", "double_root", "zero_and_tiny", "huge"])
def test_closed_form_largest_eigenvalue_bounds_lapacks_tightly(case):
    """The index's λ_max (closed form) is never below LAPACK's and above it by at most the pad: culling
    stays exact (never drops a Gaussian a view can see) without loosening the bound."""
    rng = np.random.default_rng(len(case))
    n = 20_000
    log_scales = {"random": rng.uniform(-6, 2, (n, 3)), "needles_and_discs": rng.choice([-12.0, -6.0, 1.0], (n, 3)),
                  "isotropic": np.repeat(rng.uniform(-5, 1, (n, 1)), 3, 1), "double_root": np.c_[rng.uniform(-3, 0, (n, 1)).repeat(2, 1), rng.uniform(-3, 0, (n, 1))],
                  "zero_and_tiny": rng.choice([-700.0, -200.0, -30.0], (n, 3)), "huge": rng.uniform(30, 60, (n, 3))}[case]
    rot = _rotations(rng, n)
    cov = rot @ (np.exp(log_scales)[:, :, None] ** 2 * np.transpose(rot, (0, 2, 1)))
    if case == "zero_and_tiny":
        cov[: n // 4] = 0.0
    ids = np.arange(n)
    got, ref = largest_eigenvalues(cov, ids), largest_eigenvalues_reference(cov, ids)
    scale = np.abs(cov).max(axis=(1, 2))
    assert np.all(got >= ref) and np.all(np.isfinite(got))
    assert np.all(got - np.maximum(ref, 0) <= 2e-6 * scale + 1e-299)


@pytest.mark.parametrize("case", ["random", "all_empty", "none_empty", "one_visible", "strided"])
def test_remap_kernel_matches_the_numpy_remap(case):
    """The parallel remap of a culled view's local ids to scene ids equals the numpy form on random
    and hard inputs (every slot empty, none, one visible Gaussian, a non-contiguous array)."""
    rng = np.random.default_rng(len(case))
    ids = np.sort(rng.choice(2_000_000_000, 5000, replace=False)).astype(np.int64)  # scene ids near the int32 limit
    local = rng.integers(-1, ids.size, size=(17, 23, 8)).astype(np.int32)
    if case == "all_empty":
        local[:] = -1
    if case == "none_empty":
        local = np.abs(local)
    if case == "one_visible":
        ids, local = ids[:1], np.where(local >= 0, 0, -1).astype(np.int32)
    if case == "strided":
        local = local[:, ::2]
    want = remap_ids_reference(local.copy(), ids)
    got = local.copy() if case != "strided" else local
    assert remap_ids(got, ids) is got
    np.testing.assert_array_equal(got, want)
    assert got.dtype == np.int32


def test_a_view_culls_only_where_the_subset_costs_less_than_the_whole_scene():
    """The cost rule: a flowers-sized scene at 640 x 480 x 40 culls a view that sees 30 % and renders
    one that sees 60 % whole; a 27k-Gaussian room at 320 x 240 x 40 never culls (remapping the
    view's ids costs more than projecting the room), at k = 5 it does; nothing in view culls
    whenever culling can pay at all."""
    from drsplat.registration.compute import culling_pays

    flowers, slots = 542_104, 640 * 480 * 40
    assert culling_pays(flowers, slots)
    assert not renders_whole(int(0.30 * flowers), flowers, slots) and renders_whole(int(0.60 * flowers), flowers, slots)
    room = 27_354
    assert not culling_pays(room, 320 * 240 * 40) and renders_whole(0, room, 320 * 240 * 40)
    assert culling_pays(room, 320 * 240 * 5) and not renders_whole(int(0.3 * room), room, 320 * 240 * 5)
    assert all(culling_pays(n, s) == (not renders_whole(0, n, s)) for n in (1, 1000, 10**7) for s in (0, 10**4, 10**8))


@pytest.mark.parametrize("case", ["random", "none", "all", "repeated", "sh", "non_contiguous"])
def test_subset_gather_matches_numpy_indexing(case):
    """The parallel gather of a culled view's Gaussians equals numpy's fancy indexing, array by array
    and bit for bit (NaN rows and non-finite flags included): random ids, none, all, repeated ids, SH
    of degree 2, and a scene whose arrays are views (the numpy path)."""
    from drsplat.raster import PreparedScene

    rng = np.random.default_rng(7)
    n = 3000
    sh = rng.normal(size=(n, 9 if case == "sh" else 0, 3)).astype(np.float32)
    means = rng.normal(size=(n, 3))
    means[::97] = np.nan
    cov = rng.normal(size=(n, 3, 3))
    geometry = PreparedScene(means=means, covariances=cov, opacities=rng.random(n, dtype=np.float32), sh=sh, finite=np.isfinite(means).all(1))
    if case == "non_contiguous":
        geometry = PreparedScene(means=np.asfortranarray(means), covariances=cov, opacities=geometry.opacities, sh=sh, finite=geometry.finite)
    ids = {"random": np.sort(rng.choice(n, 700, replace=False)), "none": np.zeros(0, np.int64), "all": np.arange(n),
           "repeated": rng.integers(0, n, 900)}.get(case, np.sort(rng.choice(n, 1200, replace=False))).astype(np.int64)
    got, want = subset_geometry(geometry, ids), subset_geometry_reference(geometry, ids)
    for name in ("means", "covariances", "opacities", "sh", "finite"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), name


@pytest.mark.parametrize("block_size", [1, 64, 4096])
def test_visible_kernel_matches_the_numpy_test(city, tiny, block_size):
    """The parallel per-Gaussian test returns exactly the numpy reference's ids: city views (a
    small part), the room's hard cameras (everything, nothing, off-centre), near-plane and huge
    Gaussians, and an index with one Gaussian per block or one block for all."""
    scene, cams = city
    prep = prepare_scene(scene)
    rng = np.random.default_rng(block_size)
    cam = cams[0]
    near_plane = (np.asarray(cam.R).T @ (np.array([0.0, 0.0, 0.01]) - np.asarray(cam.t)))  # a mean on the near plane
    prep.means[:3] = near_plane
    prep.covariances[3:6] *= 1e6  # huge Gaussians
    index = SpatialIndex.build(prep, block_size=block_size)
    room_cams = _hard_cameras(load_cameras(tiny))
    jittered = [dataclasses.replace(c, t=np.asarray(c.t) + rng.normal(scale=0.5, size=3), name=f"j{i}") for i, c in enumerate(cams[:4])]
    sizes = []
    for c in list(cams) + room_cams + jittered:
        got, want = index.visible(c), index.visible_reference(c)
        np.testing.assert_array_equal(got, want, err_msg=c.name)
        assert got.dtype == np.int64
        sizes.append(got.size)
    assert min(sizes) == 0 and max(sizes) > 0  # the "away" camera sees nothing


def test_a_gaussian_on_the_near_plane_far_from_the_origin_is_never_culled_when_the_rasterizer_keeps_it():
    """The block test computed the boxes' camera z by a matmul, which rounds otherwise than the
    rasterizer's r0·x + r1·y + r2·z + t: a Gaussian 1e5-1e6 out whose z the rasterizer rounds to
    the near plane exactly had its one-Gaussian block's z a few ulps below it, and was culled
    though the full render uses it (4 of the 111 kept here, before the mend)."""
    rng = np.random.default_rng(3)
    kept = culled = 0
    for offset in (1e5, 1e6):
        n = 64
        means = (offset * np.array([1.0, -0.7, 0.3]) + rng.normal(size=(n, 3)) * 0.3).astype(np.float32)
        scene = gaussians(means, log_scale=-4.0, opacity_logit=2.0)
        prep = prepare_scene(scene)
        index = SpatialIndex.build(prep, block_size=1)
        for g in range(n):
            cam = look_at_camera(prep.means[g] - [0.3, 0.2, 1.0], prep.means[g], 40, 30, fov_x_deg=60)
            rot = np.asarray(cam.R, np.float64)
            t = -(rot @ prep.means[g])
            t[2] += NEAR  # the mean straight ahead, on the near plane (to rounding)
            cam = dataclasses.replace(cam, t=t)
            if project_gaussians(prep, cam).valid[g]:
                kept += 1
                culled += g not in index.visible(cam)
    assert kept > 20 and culled == 0
