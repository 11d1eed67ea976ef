"""The top-k rasterizer: numba kernel against the numpy reference, and 3DGS's physics."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from drsplat import _raster_kernels as kernels
from drsplat import raster
from drsplat.cameras import look_at_camera
from drsplat.raster import (
    SH_C0,
    SH_C1,
    T_MIN,
    Projected,
    balance_tiles,
    depth_order,
    eval_sh,
    prepare_scene,
    project_gaussians,
    project_gaussians_reference,
    rasterize,
    rasterize_reference,
)
from drsplat.scene import GaussianScene, load_ply
from drsplat.testing import (
    assert_agree,
    assert_physical,
    front_camera,
    gaussians,
    hard_cases,
    random_case,
    random_scene,
    windowed,
)
from tests.conftest import shared_path


@pytest.mark.parametrize("seed, sh_degree, topk", [(0, 0, 8), (1, 1, 1), (2, 2, 64), (3, 3, 20)])
def test_kernel_matches_reference_random(seed, sh_degree, topk):
    rng = np.random.default_rng(seed)
    scene = random_scene(rng, 400, sh_degree)
    cam = look_at_camera(rng.normal(size=3) * 0.5 + [0, 0, -4], [0, 0, 0], 48, 34, fov_x_deg=55, cx=20.3, cy=19.1)
    kwargs = dict(with_rgb=True, with_depth=True, background=(0.2, 0.5, 0.9))
    a = rasterize(scene, cam, topk, **kwargs)
    b = rasterize_reference(scene, cam, topk, **kwargs)
    assert_agree(a, b)
    assert_physical(a, topk)
    assert (a.ids >= 0).sum() > 0.3 * a.ids[..., 0].size, "the scene should cover the image"


@pytest.mark.parametrize("case", hard_cases(), ids=lambda c: c.name)
def test_kernel_matches_reference_on_hard_cases(case):
    """numba against the numpy compositor on every hard case (enormous Gaussians included: their
    α ≥ 1/255 box once overflowed an int64 in the kernel and they were dropped)."""
    with np.errstate(all="ignore"):
        a = rasterize(case.scene, case.camera, case.topk, **case.kwargs)
        b = rasterize_reference(case.scene, case.camera, case.topk, **case.kwargs)
    assert_agree(a, b)
    if case.name == "extreme-scales":
        assert np.isin([50, 51], a.ids).all(), "the enormous Gaussians reach the image"


def test_topk_holding_all_contributors_sums_to_alpha():
    rng = np.random.default_rng(5)
    scene = random_scene(rng, 300)
    cam = front_camera(32, 24)
    out = rasterize(scene, cam, 300)
    assert (out.ids[..., -1] == -1).all(), "topk must exceed the contributors for this test"
    np.testing.assert_allclose(out.weights.astype(np.float64).sum(axis=2), out.alpha, atol=1e-5)
    few = rasterize(scene, cam, 3)
    np.testing.assert_array_equal(few.ids, out.ids[..., :3])
    np.testing.assert_array_equal(few.weights, out.weights[..., :3])


def test_empty_scene():
    scene = gaussians(np.zeros((0, 3)))
    cam = front_camera(24, 18)
    for render in (rasterize, rasterize_reference):
        out = render(scene, cam, 5, with_rgb=True, with_depth=True, background=(1.0, 0.0, 0.5))
        assert out.ids.shape == (18, 24, 5)
        assert (out.ids == -1).all() and (out.weights == 0).all() and (out.alpha == 0).all()
        np.testing.assert_array_equal(out.rgb, np.broadcast_to(np.float32([1.0, 0.0, 0.5]), (18, 24, 3)))
        assert (out.depth == 0).all()


def test_all_gaussians_behind_camera():
    rng = np.random.default_rng(7)
    scene = random_scene(rng, 200)
    scene.means[:, 2] = -5.0 - np.abs(scene.means[:, 2])  # camera at z=-4 looks along +z
    cam = front_camera(24, 18)
    proj = project_gaussians(scene, cam)
    assert proj.num_behind == 200 and not proj.valid.any()
    for render in (rasterize, rasterize_reference):
        out = render(scene, cam, 4, with_depth=True)
        assert (out.ids == -1).all() and (out.alpha == 0).all() and (out.depth == 0).all()


def test_near_plane_culls_by_mean_depth():
    cam = front_camera(24, 18)
    scene = gaussians([[0, 0, -4 + 0.005], [0, 0, -4 + 0.02]], log_scale=-6.0)
    proj = project_gaussians(scene, cam)
    assert proj.valid.tolist() == [False, True] and proj.num_behind == 1


def test_kernel_and_reference_agree_on_means_on_the_near_plane_far_from_the_origin():
    """The reference projected the means by a matmul, which rounds otherwise than the kernel's
    r0·x + r1·y + r2·z + t: a mean 1e3-1e6 out that the kernel puts exactly on the near plane was
    behind it in the reference (or the reverse), and the two renders differed over most of the
    image (20 of 192 cameras here, before the mend). Now both round the camera coordinates alike."""
    rng = np.random.default_rng(3)
    on_plane = 0
    for offset in (1e3, 1e5, 1e6):
        means = (offset * np.array([1.0, -0.7, 0.3]) + rng.normal(size=(64, 3)) * 0.3).astype(np.float32)
        prep = raster.prepare_scene(gaussians(means, log_scale=-4.0, opacity_logit=2.0))
        for g in range(64):
            cam = look_at_camera(prep.means[g] - [0.3, 0.2, 1.0], prep.means[g], 40, 30, fov_x_deg=60)
            t = -(np.asarray(cam.R, np.float64) @ prep.means[g])
            t[2] += raster.NEAR  # mean g straight ahead, on the near plane (to rounding)
            cam = dataclasses.replace(cam, t=t)
            kernel, reference = project_gaussians(prep, cam), project_gaussians_reference(prep, cam)
            np.testing.assert_array_equal(kernel.valid, reference.valid)
            assert kernel.num_behind == reference.num_behind
            on_plane += bool(kernel.valid[g])
            if g % 16 == 0:
                assert_agree(rasterize(prep, cam, 4, with_median=True), rasterize_reference(prep, cam, 4, with_median=True))
    assert on_plane > 50  # kept by both as often as not: the cases sit on the boundary


def test_camera_inside_a_gaussian():
    scene = gaussians([[0.0, 0.0, -3.5], [0.0, 0.0, -4.2], [0.3, -0.1, 1.0]], log_scale=[[1.5, 1.0, 2.0], [1.0, 1.0, 1.0], [-2, -2, -2]], opacity_logit=[-1.0, 2.0, 30.0], color=[0.3, 0.6, 0.9])
    cam = front_camera(40, 30, cx=14.0, cy=17.5)
    a = rasterize(scene, cam, 3, with_rgb=True, with_depth=True)
    b = rasterize_reference(scene, cam, 3, with_rgb=True, with_depth=True)
    assert_agree(a, b)
    assert_physical(a, 3)
    assert (a.ids == 0).any(axis=2).all(), "the Gaussian around the camera covers every pixel"
    assert project_gaussians(scene, cam).num_behind == 1


def test_extreme_scales():
    rng = np.random.default_rng(11)
    scene = random_scene(rng, 120)
    scene.log_scales[:40] = np.log(1e-8)
    scene.log_scales[40:45] = np.log(1e4)
    scene.log_scales[45:50, 0] = np.log(1e4)  # needles: huge along one axis only
    scene.opacity_logits[40:50] = -3.0  # keep the giants translucent so others stay visible
    cam = front_camera(40, 30, cx=23.0, cy=11.0)
    a = rasterize(scene, cam, 16, with_rgb=True, with_depth=True)
    b = rasterize_reference(scene, cam, 16, with_rgb=True, with_depth=True)
    assert_agree(a, b)
    assert_physical(a, 16)
    tiny_seen = np.isin(a.ids, np.arange(40)).any()
    assert tiny_seen, "Gaussians of scale 1e-8 still render as 0.3 px² dots"


def test_opacity_zero_and_saturated_logits():
    rng = np.random.default_rng(13)
    scene = random_scene(rng, 200)
    scene.opacity_logits[:50] = -30.0  # opacity ~1e-13: never contributes
    scene.opacity_logits[50:100] = 30.0  # opacity 1: alpha clamps at 0.99
    cam = front_camera(36, 28)
    a = rasterize(scene, cam, 12, with_rgb=True)
    b = rasterize_reference(scene, cam, 12, with_rgb=True)
    assert_agree(a, b)
    assert_physical(a, 12)
    assert not np.isin(a.ids, np.arange(50)).any()
    assert np.isin(a.ids, np.arange(50, 100)).any()
    assert a.weights.max() <= 0.99 + 1e-7, "alpha clamps at 0.99"


def test_ten_thousand_stacked_gaussians_stop_at_transmittance_floor():
    cam = front_camera(24, 18)
    centre = np.linalg.solve(cam.R, np.array([(10.5 - cam.cx) / cam.fx * 4, (7.5 - cam.cy) / cam.fy * 4, 4.0]) - cam.t)
    scene = gaussians(np.tile(centre, (10_000, 1)), log_scale=-9.0, opacity_logit=0.0)  # opacity exactly 0.5
    a = rasterize(scene, cam, 64, with_rgb=True, with_depth=True)
    b = rasterize_reference(scene, cam, 64, with_rgb=True, with_depth=True)
    assert_agree(a, b)
    assert_physical(a, 64)
    # α = 0.5 at the centre: weights 1/2, 1/4, ... until T·(1 - α) would drop below 1e-4.
    n = int(np.floor(np.log2(1 / T_MIN)))
    expected = 0.5 ** np.arange(1, n + 1)
    np.testing.assert_allclose(a.weights[7, 10, :n], expected, rtol=1e-6)
    assert (a.weights[7, 10, n:] == 0).all()
    np.testing.assert_array_equal(a.ids[7, 10, :n], np.arange(n))  # equal depth: id order
    assert a.alpha[7, 10] == pytest.approx(1 - 0.5**n, abs=1e-6)


@pytest.mark.parametrize("seed", [0, 5])
def test_a_window_of_the_image_renders_that_part_of_the_image(seed):
    """drsplat.testing.windowed (the interpreter tests' smaller cases) sees the same rays: a window
    on the tile grid renders the full image's top-k lists, weights and alpha under it, for the
    Gaussians whose direction the EWA Jacobian does not clamp (3DGS clamps at 1.3x the field of
    view: the window's is smaller)."""
    case = random_case(seed, n=600, topk=6)
    part = windowed(case, 16, 16, 27, 18)
    pc = case.scene.means @ case.camera.R.T + case.camera.t
    x_pos, x_neg, y_pos, y_neg = raster.clamp_limits(part.camera)
    tx, ty = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
    unclamped = (pc[:, 2] > 0) & (tx < x_pos) & (-tx < x_neg) & (ty < y_pos) & (-ty < y_neg)
    case.scene = part.scene = case.scene.subset(np.flatnonzero(unclamped))
    full = rasterize(case.scene, case.camera, case.topk, with_median=True)
    win = rasterize(part.scene, part.camera, part.topk, with_median=True)
    assert win.ids.shape == (18, 27, 6) and (win.ids[..., -1] >= 0).any()
    np.testing.assert_array_equal(win.ids, full.ids[16:34, 16:43])
    np.testing.assert_allclose(win.weights, full.weights[16:34, 16:43], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(win.alpha, full.alpha[16:34, 16:43], rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(win.median_ids, full.median_ids[16:34, 16:43])


def test_single_opaque_gaussian_peaks_at_its_projected_pixel():
    cam = front_camera(48, 30, cx=31.0, cy=8.5)  # non-square, principal point off centre
    world = np.linalg.solve(cam.R, np.array([(12.5 - cam.cx) / cam.fx * 5, (20.5 - cam.cy) / cam.fy * 5, 5.0]) - cam.t)
    uv, _ = cam.project(world[None])
    np.testing.assert_allclose(uv[0], [12.5, 20.5], atol=1e-6)
    scene = gaussians([world], log_scale=-1.5, opacity_logit=30.0)
    for render in (rasterize, rasterize_reference):
        out = render(scene, cam, 1)
        assert out.weights[20, 12, 0] == pytest.approx(0.99, abs=1e-6)
        assert np.unravel_index(np.argmax(out.weights[..., 0]), out.alpha.shape) == (20, 12)
        # pixel centres at +0.5: the splat is symmetric about pixel (12, 20)
        assert out.weights[20, 11, 0] == pytest.approx(out.weights[20, 13, 0], abs=1e-5)
        assert out.weights[19, 12, 0] == pytest.approx(out.weights[21, 12, 0], abs=1e-5)
        assert out.weights[20, 11, 0] < 0.99


def test_constant_colour_scene_renders_that_colour():
    rng = np.random.default_rng(17)
    scene = random_scene(rng, 300, sh_degree=0)
    colour = np.float32([0.8, 0.25, 0.6])
    scene.sh[:, 0] = (colour - 0.5) / SH_C0
    bg = np.float32([0.1, 0.9, 0.3])
    cam = front_camera(32, 24)
    out = rasterize(scene, cam, 4, with_rgb=True, background=bg)
    expected = out.alpha[..., None] * colour + (1 - out.alpha[..., None]) * bg
    np.testing.assert_allclose(out.rgb, expected, atol=1e-5)
    assert out.alpha.max() > 0.99


def test_depth_is_the_weighted_mean_of_camera_z():
    cam = front_camera(24, 18)
    scene = gaussians([[0, 0, 0.0], [0, 0, 2.0]], log_scale=-0.5, opacity_logit=0.0)
    out = rasterize(scene, cam, 2, with_depth=True)
    w = out.weights[9, 12].astype(np.float64)
    assert w[0] == pytest.approx(0.5, abs=0.02) and w[1] == pytest.approx(0.25, abs=0.02)
    expected = (w[0] * 4.0 + w[1] * 6.0) / w.sum()
    assert out.depth[9, 12] == pytest.approx(expected, rel=1e-5)


def test_mask_renders_the_subset_with_scene_ids():
    rng = np.random.default_rng(19)
    scene = random_scene(rng, 250)
    mask = rng.random(250) < 0.4
    cam = front_camera(32, 24)
    masked = rasterize(scene, cam, 10, mask=mask, with_depth=True)
    sub = rasterize(scene.subset(mask), cam, 10, with_depth=True)
    ids = np.flatnonzero(mask)
    np.testing.assert_array_equal(masked.ids, np.where(sub.ids >= 0, ids[np.maximum(sub.ids, 0)], -1))
    np.testing.assert_array_equal(masked.weights, sub.weights)
    assert_agree(masked, rasterize_reference(scene, cam, 10, mask=mask, with_depth=True))
    with pytest.raises(ValueError, match="mask"):
        rasterize(scene, cam, 10, mask=mask[:-1])


def test_nonfinite_gaussians_are_dropped_and_counted():
    rng = np.random.default_rng(23)
    scene = random_scene(rng, 150, sh_degree=1)
    bad = GaussianScene(
        means=scene.means.copy(), quats=scene.quats.copy(), log_scales=scene.log_scales.copy(),
        opacity_logits=scene.opacity_logits.copy(), sh=scene.sh.copy(),
    )  # fmt: skip
    bad.means[0, 1] = np.nan
    bad.quats[1, 2] = np.inf
    bad.log_scales[2, 0] = 200.0  # exp overflows: infinite covariance
    bad.opacity_logits[3] = np.nan
    bad.sh[4, 2, 1] = -np.inf
    cam = front_camera(32, 24)
    with np.errstate(all="ignore"):
        out = rasterize(bad, cam, 8, with_rgb=True, with_depth=True)
        ref = rasterize_reference(bad, cam, 8, with_rgb=True, with_depth=True)
    assert out.num_nonfinite == 5
    assert_agree(out, ref)
    clean = rasterize(scene.subset(np.arange(5, 150)), cam, 8, with_rgb=True, with_depth=True)
    np.testing.assert_array_equal(out.weights, clean.weights)
    np.testing.assert_array_equal(out.ids, np.where(clean.ids >= 0, clean.ids + 5, -1))
    np.testing.assert_allclose(out.rgb, clean.rgb, atol=1e-6)


def test_infinite_opacity_logits_render_as_a_loaded_file_reads_them(tmp_path):
    """Round 89d F2: a +inf opacity logit (the most opaque value) was dropped as non-finite by `prepare_scene`, while
    the loader reads it as a logit of +30; the same scene registered 2,601 or 2,650 Gaussians whether given in memory
    or through a file. ±inf now render as opacity 1 and 0 in both; a NaN logit is still not rendered."""
    from drsplat.raster_torch import rasterize as rasterize_torch
    from drsplat.scene import save_ply

    scene = random_scene(np.random.default_rng(5), 150)
    logits = scene.opacity_logits.copy()
    logits[:10], logits[10:15], logits[15] = np.inf, -np.inf, np.nan
    given = dataclasses.replace(scene, opacity_logits=logits)
    save_ply(given, tmp_path / "s.ply")
    loaded = load_ply(tmp_path / "s.ply")  # +-inf clamped to +-30 by the loader (a finding); NaN dropped
    cam = front_camera(32, 24)
    with np.errstate(all="ignore"):
        out = rasterize(given, cam, 8)
        torch_out = rasterize_torch(given, cam, 8)
    assert out.num_nonfinite == 1  # the NaN only
    ref = rasterize(loaded, cam, 8)
    np.testing.assert_array_equal(out.weights, ref.weights)
    np.testing.assert_array_equal(np.where(out.ids > 15, out.ids - 1, out.ids), ref.ids)  # the NaN row (15) is not in the loaded scene
    np.testing.assert_array_equal(out.ids, torch_out.ids)
    assert np.isin(np.arange(10), out.ids).any()  # the fully opaque ones are drawn


def test_colours_and_depths_beyond_float32_are_not_rendered_and_are_counted():
    """Was (a numerical probe, 2026-12-01): SH coefficients of 3e38 (finite) gave inf colours, NaN
    across whole tiles on the torch path, and a mean at 3.4e38 an inf depth, counted nowhere. Now a
    Gaussian with an SH coefficient beyond 1e30 or a mean beyond 1e15 is not rendered by any engine,
    is counted, and the rest render as without it."""
    from drsplat.raster_torch import rasterize as rasterize_torch
    from drsplat.scene import MAX_COORDINATE, MAX_SH_COEFFICIENT

    rng = np.random.default_rng(31)
    scene = random_scene(rng, 120, sh_degree=3)
    bad = scene.subset(np.arange(120))
    bad.sh[0, 5, 1] = 3e38
    bad.sh[1, 0, 0] = -2 * MAX_SH_COEFFICIENT
    bad.means[2] = bad.means[2] * 0 + (0.0, 0.0, 3.3e38)  # straight ahead: its camera z passes float32's range
    bad.means[3, 0] = 2 * MAX_COORDINATE
    bad.sh[4, 1, 2] = MAX_SH_COEFFICIENT / 2  # within the bound: rendered (a colour of ~1e29, finite)
    cam = front_camera(32, 24)
    clean = rasterize(scene.subset(np.arange(4, 120)), cam, 8, with_rgb=True, with_depth=True)
    for render in (rasterize, rasterize_reference, rasterize_torch):
        out = render(bad, cam, 8, with_rgb=True, with_depth=True)
        assert out.num_nonfinite == 4, render
        assert np.isfinite(out.rgb).all() and np.isfinite(out.depth).all(), render
        np.testing.assert_array_equal(out.ids, np.where(clean.ids >= 0, clean.ids + 4, -1))
        np.testing.assert_allclose(out.weights, clean.weights, rtol=1e-6, atol=1e-7)


def test_projection_kernel_matches_reference():
    rng = np.random.default_rng(29)
    scene = random_scene(rng, 500, spread=3.0, log_scale=(-9.0, 4.0))
    scene.means[:20] = [0.0, 0.0, -4.0]  # at the camera centre
    scene.log_scales[20:24] = 60.0  # enormous: a screen radius past 2^63 pixels (it once overflowed an int64 and was culled)
    cam = look_at_camera([0.2, -0.1, -4.0], [0.1, 0.2, 0.0], 50, 20, fov_x_deg=70, cx=12.0, cy=15.0)
    prep = prepare_scene(scene)
    a, b = project_gaussians(prep, cam), project_gaussians_reference(prep, cam)
    np.testing.assert_array_equal(a.valid, b.valid)
    assert b.valid[20:24].any() and (a.radii[20:24][b.valid[20:24]] == 2**30).all()
    assert 0 < a.valid.sum() < 500 and a.num_behind == b.num_behind > 0
    for name in ("radii", "tile_rects"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    for name in ("means2d", "extents", "qlimits", "depths"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-9, atol=1e-12)
    # conics invert 2D covariances of condition up to ~1e8 here (log-scales -9..4, float64 Σ): agreement ~ cond · eps
    np.testing.assert_allclose(a.conics, b.conics, rtol=1e-7, atol=1e-12)
    assert a.num_nonfinite == b.num_nonfinite == 0


def test_screen_covariance_matches_ewa_formula():
    rng = np.random.default_rng(31)
    scene = random_scene(rng, 50, spread=0.5)
    cam = look_at_camera([0.5, 0.3, -3.0], [0.0, 0.0, 0.0], 64, 48, cx=30.0, cy=20.0)
    proj = project_gaussians(scene, cam)
    cov3d = scene.covariances().astype(np.float64)
    for g in np.flatnonzero(proj.valid)[:10]:
        x, y, z = cam.world_to_camera(scene.means[g : g + 1].astype(np.float64))[0]
        jac = np.array([[cam.fx / z, 0, -cam.fx * x / z**2], [0, cam.fy / z, -cam.fy * y / z**2]])
        cov2d = jac @ cam.R @ cov3d[g] @ cam.R.T @ jac.T + 0.3 * np.eye(2)
        a, b, c = proj.conics[g]
        np.testing.assert_allclose(np.array([[a, b], [b, c]]), np.linalg.inv(cov2d), rtol=1e-6)
        np.testing.assert_allclose(proj.means2d[g], cam.project(scene.means[g : g + 1])[0][0], rtol=1e-9)
        assert proj.radii[g] == np.ceil(3 * np.sqrt(np.linalg.eigvalsh(cov2d).max()))


def test_sh_basis_is_orthonormal_with_3dgs_signs():
    nodes, weights = np.polynomial.legendre.leggauss(12)
    phi = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    z, ph = np.meshgrid(nodes, phi, indexing="ij")
    r = np.sqrt(1 - z**2)
    dirs = np.stack([r * np.cos(ph), r * np.sin(ph), z], axis=-1).reshape(-1, 3)
    quad = (weights[:, None] * np.full_like(ph, 2 * np.pi / phi.size)).reshape(-1)
    basis = []
    for i in range(16):
        sh = np.zeros((dirs.shape[0], 16, 3), np.float32)
        sh[:, 0] = 10.0  # keep the result positive so that the clamp at 0 is inactive
        sh[:, i] += 1.0
        basis.append(eval_sh(sh, dirs)[:, 0] - (SH_C0 * 10.0 + 0.5))
    basis = np.array(basis)
    gram = (basis * quad) @ basis.T
    np.testing.assert_allclose(gram, np.eye(16), atol=1e-5)
    x_dir = np.array([[1.0, 0.0, 0.0]])
    sh = np.zeros((1, 4, 3), np.float32)
    sh[0, 3] = 0.5
    np.testing.assert_allclose(eval_sh(sh, x_dir), 0.5 - SH_C1 * 0.5, rtol=1e-6)  # 3DGS: -C1·x·sh[3]
    sh[0, 3] = 5.0
    assert (eval_sh(sh, x_dir) == 0).all(), "colours clamp at 0"


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_the_sh_colour_kernel_matches_eval_sh(degree):
    """The numba `sh_colors` (project_gaussians' colours) against the numpy reference `_add_colors` (eval_sh): random
    coefficients, coefficients of ±1e4 (the clamp at 0 and large sums), a Gaussian at the camera centre (no direction),
    mean directions along each axis, invalid Gaussians (colour 0). float64 sums in one order: equal to float32 rounding."""
    from drsplat.cameras import look_at_camera
    from drsplat.raster import _add_colors, _add_colors_numba, prepare_scene, project_gaussians

    rng = np.random.default_rng(degree)
    cam = look_at_camera(np.array([0.3, -0.2, -4.0]), np.zeros(3), 64, 48)
    means = np.r_[rng.normal(size=(300, 3)), [cam.center], cam.center + np.eye(3), [cam.center - 1e-12]].astype(np.float32)
    scene = gaussians(means, log_scale=-2.0)
    k = (degree + 1) ** 2
    sh = rng.normal(scale=0.5, size=(len(means), k, 3)).astype(np.float32)
    sh[:40] *= 2e4
    scene.sh = sh
    prep = prepare_scene(scene)
    projected = project_gaussians(prep, cam)
    projected.valid[::7] = False
    projected.valid[300:] = True  # the centre itself and points beside it, whether or not the camera sees them
    fast, reference = dataclasses.replace(projected), dataclasses.replace(projected)
    _add_colors_numba(fast, prep, cam)
    _add_colors(reference, prep, cam)
    np.testing.assert_allclose(fast.colors, reference.colors, rtol=1e-6, atol=1e-6)
    assert (fast.colors[~projected.valid] == 0).all() and (fast.colors >= 0).all() and fast.colors.dtype == np.float32
    assert (reference.colors == 0).any() and (reference.colors > 1).any()  # the clamp and large colours both met


@pytest.mark.parametrize("k", [2, 5, 25])
def test_sh_colours_of_no_sh_degree_are_refused_not_read_past_the_basis(k):
    """Round 66c F3: an `sh` of 25 coefficients (set after the scene's own check) read past the kernel's 16-term basis
    and gave inf colours; 2 or 5 gave colours from part of a basis where the reference failed. Now one error, naming the
    count, before the kernel; the GaussianScene refuses such an array when built."""
    from drsplat.cameras import look_at_camera
    from drsplat.raster import _add_colors_numba, prepare_scene, project_gaussians

    cam = look_at_camera(np.array([0.3, -0.2, -4.0]), np.zeros(3), 16, 12)
    scene = gaussians(np.array([[0.1, 0.2, 0.3]], np.float32), log_scale=-2.0)
    scene.sh = np.full((1, k, 3), 0.1, np.float32)
    prep = prepare_scene(scene)
    with pytest.raises(ValueError, match=f"{k} coefficients a colour channel"):
        _add_colors_numba(project_gaussians(prep, cam), prep, cam)
    with pytest.raises(ValueError, match=f"{k} coefficients a colour channel"):
        project_gaussians(prep, cam, with_colors=True)
    with pytest.raises(ValueError, match="K in 1, 4, 9, 16"):
        dataclasses.replace(scene)


@pytest.mark.parametrize("shape", [(3, 4, 3), (5, 4, 1), (5, 4), (5, 4, 3, 1)])
def test_sh_colours_of_another_shape_than_n_k_3_are_refused_not_read_past(shape):
    """Round 67a F7: an `sh` of fewer rows than Gaussians, or of one colour channel, set after the scene's check, was
    read past its end by the colour kernel (colours from other memory, another one each call). One error naming the
    shape, before the kernel."""
    from drsplat.cameras import look_at_camera
    from drsplat.raster import prepare_scene, project_gaussians

    cam = look_at_camera(np.array([0.3, -0.2, -4.0]), np.zeros(3), 16, 12)
    scene = gaussians(np.random.default_rng(0).normal(size=(5, 3)).astype(np.float32) * 0.2, log_scale=-2.0)
    prep = prepare_scene(scene)
    prep.sh = np.full(shape, 0.1, np.float32)
    with pytest.raises(ValueError, match=r"sh has shape .*; expected \[5, K, 3\]"):
        project_gaussians(prep, cam, with_colors=True)


def test_view_dependent_colour_uses_camera_to_mean_direction():
    scene = gaussians([[0.0, 0.0, 0.0]], log_scale=-1.0)
    scene.sh = np.zeros((1, 4, 3), np.float32)
    scene.sh[0, 3] = 0.4  # colour 0.5 - C1·x·0.4 with x the view direction's x
    for eye, sign in (([-4.0, 0.0, 0.0], 1.0), ([4.0, 0.0, 0.0], -1.0)):
        cam = look_at_camera(eye, [0, 0, 0], 24, 18)
        out = rasterize(scene, cam, 1, with_rgb=True)
        expected = (0.5 - SH_C1 * sign * 0.4) * out.alpha[9, 12]
        np.testing.assert_allclose(out.rgb[9, 12], expected, atol=1e-6)


def test_bad_arguments():
    scene = gaussians([[0, 0, 0]])
    cam = front_camera(24, 18)
    with pytest.raises(ValueError, match="topk"):
        rasterize(scene, cam, -1)
    with pytest.raises(ValueError, match="background"):
        rasterize(scene, cam, 2, background=(0, 0))
    out = rasterize(scene, cam, 0, with_rgb=True)
    assert out.ids.shape == (18, 24, 0) and out.alpha.max() > 0.5
    np.testing.assert_array_equal(out.alpha, rasterize(scene, cam, 1).alpha)


def test_reused_buffers_give_the_same_result():
    rng = np.random.default_rng(37)
    scene = prepare_scene(random_scene(rng, 200, sh_degree=1))
    cams = [front_camera(32, 24), look_at_camera([1.0, 0.5, -3.5], [0, 0, 0], 32, 24)]
    first = rasterize(scene, cams[0], 6, with_rgb=True, with_depth=True)
    reused = rasterize(scene, cams[1], 6, with_rgb=True, with_depth=True, out=first)
    assert reused.ids is first.ids and reused.weights is first.weights
    fresh = rasterize(scene, cams[1], 6, with_rgb=True, with_depth=True)
    assert_agree(reused, fresh, tol=0)


PROJECTED_ARRAYS = ("means2d", "conics", "depths", "radii", "valid", "tile_rects", "extents", "qlimits")


def test_reused_projection_buffers_give_a_fresh_projection():
    """project_gaussians(out=previous) overwrites every row: buffers full of NaN and of another view's
    Gaussians (valid ones where this view's are culled, behind or non-finite) give a fresh call's
    arrays bit for bit; a smaller scene takes the first rows of the same memory, a larger one new arrays."""
    rng = np.random.default_rng(41)
    scene = random_scene(rng, 400, spread=3.0, log_scale=(-9.0, 4.0))
    scene.means[:20] = [0.0, 0.0, -4.0]  # at the camera centre: behind the near plane
    scene.opacity_logits[20:30] = -20.0  # transparent: culled
    scene.means[30, 0] = np.nan  # non-finite
    prep = prepare_scene(scene)
    cams = [look_at_camera([0.2, -0.1, -4.0], [0.1, 0.2, 0.0], 50, 20, fov_x_deg=70), front_camera(32, 24)]
    poisoned = project_gaussians(prep, cams[1])
    for name in PROJECTED_ARRAYS:
        arr = getattr(poisoned, name)
        arr[...] = np.nan if arr.dtype.kind == "f" else (True if arr.dtype == bool else 7)
    with np.errstate(invalid="ignore"):
        got = project_gaussians(prep, cams[0], out=poisoned)
        want = project_gaussians(prep, cams[0])
    assert 0 < want.valid.sum() < 400 and want.num_behind > 0 and want.num_nonfinite == 1
    for name in PROJECTED_ARRAYS:
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
        assert np.shares_memory(getattr(got, name), getattr(poisoned, name)), f"{name} was not reused"
    assert (got.num_behind, got.num_nonfinite) == (want.num_behind, want.num_nonfinite)
    small = prepare_scene(scene.subset(np.arange(100, 300)))
    part = project_gaussians(small, cams[1], out=got)
    assert np.shares_memory(part.conics, got.conics) and part.conics.shape == (200, 3)
    for name in PROJECTED_ARRAYS:
        np.testing.assert_array_equal(getattr(part, name), getattr(project_gaussians(small, cams[1]), name), err_msg=name)
    bigger = prepare_scene(random_scene(rng, 900))
    assert not np.shares_memory(project_gaussians(bigger, cams[1], out=part).means2d, part.means2d)


def test_kernel_matches_reference_on_a_real_capture():
    scene = load_ply(shared_path("ply", "guitar.ply"))  # real 3DGS output, with +inf opacities
    scene = prepare_scene(scene.subset(np.arange(0, scene.num_gaussians, 8)))
    lo, hi = np.percentile(scene.means, [2, 98], axis=0)
    centre, radius = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    cam = look_at_camera(centre + [1.2 * radius, 0.0, 0.0], centre, 32, 24, fov_x_deg=50, cx=14.0, cy=13.5, up=(0, 0, 1))
    a = rasterize(scene, cam, 24, with_rgb=True, with_depth=True)
    b = rasterize_reference(scene, cam, 24, with_rgb=True, with_depth=True)
    assert_agree(a, b)
    assert_physical(a, 24)
    assert a.alpha.mean() > 0.3


@pytest.mark.parametrize("k", [1, 3, 8])
def test_topk_buffer_keeps_the_first_k_of_a_stable_sort(k):
    rng = np.random.default_rng(k)
    for trial in range(300):
        n = int(rng.integers(0, 3 * k + 2))
        levels = rng.uniform(0.01, 1.0, size=int(rng.integers(1, 4)))
        w = rng.choice(levels, n) if trial % 2 else rng.uniform(0.0, 1.0, n)  # many exact ties / none
        wbuf, ibuf = np.empty((2, k)), np.empty((2, k), np.int32)
        count, minw, minpos = np.zeros(2, np.int64), np.zeros(2), np.zeros(2, np.int64)
        for g, wg in enumerate(w):
            kernels.push_topk(wbuf, ibuf, count, minw, minpos, 1, wg, g)
        kernels.sort_topk(wbuf, ibuf, count[1], 1)
        best = np.argsort(-w, kind="stable")[:k]
        assert count[1] == best.size
        np.testing.assert_array_equal(ibuf[1, : best.size], best)
        np.testing.assert_array_equal(wbuf[1, : best.size], w[best])


def test_depth_order_is_a_stable_argsort_of_depths():
    rng = np.random.default_rng(41)
    special = np.array([-2.5, -0.0, 0.0, 1e-30, -1e-30, 1.0, 1.0, 3.5, 3e38], np.float32)
    for trial in range(50):
        n = int(rng.integers(0, 400))
        depths = rng.choice(special, n) if trial % 2 else rng.normal(size=n).astype(np.float32)
        projected = Projected(*(None,) * 4, opacities=None, valid=rng.random(n) < 0.8, tile_rects=None, extents=None,
                              qlimits=None, colors=None, width=1, height=1)  # fmt: skip
        projected.depths = depths
        idx = np.flatnonzero(projected.valid)
        np.testing.assert_array_equal(depth_order(projected), idx[np.argsort(depths[idx], kind="stable")])
        np.testing.assert_array_equal(raster.depth_order_reference(projected), idx[np.argsort(depths[idx], kind="stable")])


def _depth_projected(depths: np.ndarray, valid: np.ndarray) -> Projected:
    projected = Projected(*(None,) * 4, opacities=None, valid=valid, tile_rects=None, extents=None,
                          qlimits=None, colors=None, width=1, height=1)  # fmt: skip
    projected.depths = depths
    return projected


@pytest.mark.parametrize("case", ["normal", "one-depth", "few-depths", "wide-range", "negative-and-nan", "close-range"])
def test_radix_depth_order_equals_the_reference_sort(case):
    """The radix sort's three passes (some skipped when every key shares a digit) give numpy's order exactly."""
    rng = np.random.default_rng(len(case))
    n = 20_000
    depths = {
        "normal": rng.normal(3.0, 1.0, n),
        "one-depth": np.full(n, 2.5),
        "few-depths": rng.choice([0.5, 1.0, 1.0 + 2**-20, 7.0], n),
        "wide-range": 10.0 ** rng.uniform(-30, 30, n) * rng.choice([-1.0, 1.0], n),
        "negative-and-nan": np.where(rng.random(n) < 0.01, np.nan, rng.normal(0.0, 1e-3, n)),
        "close-range": 5.0 + rng.integers(0, 64, n) * 2.0**-21,  # keys differ in the low digit only
    }[case].astype(np.float32)
    depths[:7] = [0.0, -0.0, np.inf, -np.inf, 3e38, 1e-45, -1e-45]
    projected = _depth_projected(depths, rng.random(n) < 0.9)
    np.testing.assert_array_equal(depth_order(projected), raster.depth_order_reference(projected))


@pytest.mark.parametrize("n_chunks", [1, 3, 64])
def test_parallel_binning_keeps_depth_order_in_every_tile(n_chunks):
    rng = np.random.default_rng(n_chunks)
    n, tiles_x, tiles_y = 500, 7, 5
    lo = np.stack([rng.integers(0, tiles_x, n), rng.integers(0, tiles_y, n)], axis=1)
    hi = lo + np.stack([rng.integers(0, 4, n), rng.integers(0, 3, n)], axis=1)  # some empty rects
    rects = np.concatenate([lo, np.minimum(hi, [tiles_x, tiles_y])], axis=1).astype(np.int32)
    order = rng.permutation(n)[: n - 40].astype(np.int64)
    offsets, ids = kernels.bin_gaussians(order, rects, tiles_x, tiles_x * tiles_y, n_chunks)
    for ty in range(tiles_y):
        for tx in range(tiles_x):
            t = ty * tiles_x + tx
            inside = (rects[order, 0] <= tx) & (tx < rects[order, 2]) & (rects[order, 1] <= ty) & (ty < rects[order, 3])
            np.testing.assert_array_equal(ids[offsets[t] : offsets[t + 1]], order[inside])


@pytest.mark.parametrize("n_workers, chunks", [(1, 1), (2, 8), (3, 4), (5, 1)])
def test_balance_tiles_gives_every_tile_to_one_worker_and_evens_the_work(n_workers, chunks):
    rng = np.random.default_rng(n_workers * 10 + chunks)
    for entries in (rng.integers(0, 50, 300) * (rng.random(300) < 0.7), np.zeros(7, np.int64), rng.integers(0, 5000, 40)):
        order, starts = balance_tiles(entries, n_workers, chunks)
        assert starts[0] == 0 and starts[-1] == entries.size and (np.diff(starts) >= 0).all()
        np.testing.assert_array_equal(np.sort(order), np.arange(entries.size))
        for w in range(n_workers):
            mine = order[starts[w] : starts[w + 1]]
            assert (np.diff(mine) > 0).all(), "each worker takes its tiles in raster order"
            cost = entries + 1
            assert cost[mine].sum() <= cost.sum() / n_workers + chunks * cost.max()


@pytest.mark.parametrize("n_workers, chunks", [(1, 1), (2, 3), (7, 2), (64, 1)])
def test_any_split_of_the_tiles_gives_bit_identical_images(monkeypatch, n_workers, chunks):
    rng = np.random.default_rng(53)
    scene = prepare_scene(random_scene(rng, 600, sh_degree=1))
    cam = look_at_camera([0.3, -0.2, -3.5], [0, 0, 0], 70, 45, fov_x_deg=55)
    baseline = rasterize(scene, cam, 12, with_rgb=True, with_depth=True)
    split = raster.balance_tiles
    monkeypatch.setattr(raster, "balance_tiles", lambda entries, _threads: split(entries, n_workers, chunks))
    out = rasterize(scene, cam, 12, with_rgb=True, with_depth=True)
    assert_agree(out, rasterize_reference(scene, cam, 12, with_rgb=True, with_depth=True))
    for name in ("ids", "weights", "rgb", "depth", "alpha"):
        np.testing.assert_array_equal(getattr(out, name), getattr(baseline, name))


def _get_rect_3dgs(point_image, max_radius, grid, block):
    """INRIA 3DGS's getRect (auxiliary.h), transcribed statement by statement (C's int cast truncates)."""
    rect_min = [min(grid[i], max(0, int((point_image[i] - max_radius) / block))) for i in range(2)]
    rect_max = [min(grid[i], max(0, int((point_image[i] + max_radius + block - 1) / block))) for i in range(2)]
    return rect_min, rect_max


def test_tile_rect_rule_is_3dgs_getrect_on_any_position():
    rng = np.random.default_rng(43)
    uv = rng.uniform(-60, 140, size=(20000, 2))
    radii = rng.integers(0, 40, 20000).astype(np.float64)
    rects = raster._tile_rects(uv, radii, 83, 45, 16)
    for g in range(uv.shape[0]):
        rmin, rmax = _get_rect_3dgs(uv[g] - 0.5, int(radii[g]), (6, 3), 16)
        assert [rmin[0], rmin[1], rmax[0], rmax[1]] == rects[g].tolist(), g


@pytest.mark.parametrize("engine", ["numba", "reference", "torch"])
def test_tile_rectangles_are_3dgs_getrect(engine):
    """Every projected Gaussian's tiles follow 3DGS's getRect, with 3DGS's point_image = our screen
    mean - 0.5 (its pixel centres are integers); all engines cull the same Gaussians."""
    rng = np.random.default_rng(37)
    scene = random_scene(rng, 3000, spread=2.0, log_scale=(-6.0, 0.5))
    cam = front_camera(83, 45, cx=30.0, cy=25.0, z=-3.0)
    if engine == "torch":
        from drsplat.raster_torch import project_gaussians_torch

        p = project_gaussians_torch(scene, cam)
        valid, rects, uv, radii = p.valid.numpy(), p.tile_rects.numpy(), p.means2d.numpy(), p.radii.numpy()
    else:
        p = (project_gaussians if engine == "numba" else project_gaussians_reference)(scene, cam)
        valid, rects, uv, radii = p.valid, p.tile_rects, p.means2d, p.radii
    grid = (-(-cam.width // 16), -(-cam.height // 16))
    for g in np.flatnonzero(valid):
        rmin, rmax = _get_rect_3dgs((uv[g, 0] - 0.5, uv[g, 1] - 0.5), int(radii[g]), grid, 16)
        assert [rmin[0], rmin[1], rmax[0], rmax[1]] == rects[g].tolist(), g
    assert valid.sum() > 1000
    np.testing.assert_array_equal(valid, project_gaussians_reference(scene, cam).valid)


def test_getrect_differs_from_the_pixel_centre_rule_only_at_tile_borders():
    """The documented difference (docs/raster.md): getRect may add the tile below/left of p - r and drop
    the tile whose first pixel lies in [p + r - 1, p + r]; never anything else."""
    rng = np.random.default_rng(41)
    p = rng.uniform(-40, 200, 20000)
    r = rng.integers(0, 30, 20000).astype(float)
    lo_get = np.clip(np.floor((p - r) / 16), 0, 10)
    hi_get = np.clip(np.floor((p + r + 15) / 16), 0, 10)
    first, last = np.clip(np.ceil(p - r), 0, 160), np.clip(np.floor(p + r), -1, 159)
    nonempty = first <= last
    lo_px, hi_px = first // 16, last // 16 + 1
    both = nonempty & (hi_get > lo_get)
    assert ((lo_get[both] == lo_px[both]) | (lo_get[both] == lo_px[both] - 1)).all()
    assert ((hi_get[both] == hi_px[both]) | (hi_get[both] == hi_px[both] - 1)).all()
    assert (lo_get[both] != lo_px[both]).mean() > 0.01 and (hi_get[both] != hi_px[both]).mean() > 0.01


def _band_cameras(rng: np.random.Generator, count: int) -> list:
    """Cameras around the origin looking at it from 0.3-3 units, plus one whose t puts a mean exactly on each plane."""
    cams = []
    for _ in range(count):
        eye = rng.normal(size=3)
        eye *= rng.uniform(0.3, 3.0) / np.linalg.norm(eye)
        cams.append(look_at_camera(eye, np.zeros(3), int(rng.integers(8, 80)), int(rng.integers(8, 60)), fov_x_deg=float(rng.uniform(30, 120))))
    return cams


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_near_band_is_what_one_plane_draws_and_the_other_does_not(seed):
    """`near_band` (a numba pass over every (camera, Gaussian) depth, then a projection of the few in the band) against
    two plain facts: its ids are those `project_gaussians` keeps at lo and not at hi, and `near_band_reference` (numpy)
    finds the same ids and tiles. Hard cases: means on either plane to the last bit (the planes' own rounding), NaN
    means, Gaussians too faint to draw, ones off to the side of a view, a camera that sees none, an empty scene."""
    rng = np.random.default_rng(seed)
    lo, hi = raster.NEAR, 0.2
    means = rng.normal(size=(3000, 3)) * 0.6
    opacity = np.where(rng.random(3000) < 0.1, -8.0, 2.0)  # a tenth under 1/255: never drawn
    cams = _band_cameras(rng, 12)
    means[2] = np.nan
    means = means.astype(np.float32)
    for row, plane in ((0, lo), (1, hi), (3, lo), (4, hi)):  # cameras that put a mean on a plane, to the last bits of its own sum
        opacity[row] = 2.0
        cam = look_at_camera(means[row] - [0.1, 0.05, 0.5], means[row], 40, 30, fov_x_deg=60)
        t = -(np.asarray(cam.R, np.float64) @ means[row].astype(np.float64))
        t[2] += plane
        cams.append(dataclasses.replace(cam, t=t))
    scene = gaussians(means, log_scale=np.log(rng.uniform(0.002, 0.05, (3000, 3))), opacity_logit=opacity)
    bands = raster.near_band(scene, cams, lo, hi, with_ids=True)
    reference = raster.near_band_reference(scene, cams, lo, hi, with_ids=True)
    assert len(bands) == len(cams) == len(reference)
    nonempty = 0
    for cam, band, ref in zip(cams, bands, reference):
        at_lo = project_gaussians(scene, cam, lo)
        drawn = at_lo.valid & ~project_gaussians(scene, cam, hi).valid
        np.testing.assert_array_equal(band.ids, np.flatnonzero(drawn))
        held = {(tx, ty) for x0, y0, x1, y1 in at_lo.tile_rects[drawn] for tx in range(x0, x1) for ty in range(y0, y1)}
        assert band.tiles == len(held) and band.cover <= 1.0  # distinct tiles (round 65a F2: overlaps summed said "100 %")
        np.testing.assert_array_equal(band.ids, ref.ids)
        assert band.tiles == ref.tiles and band.grid == ref.grid == np.prod(raster.tile_grid(cam.width, cam.height))
        assert band.count == band.ids.size and raster.near_band(scene, [cam], lo, hi)[0] == dataclasses.replace(band, ids=None)
        nonempty += band.ids.size > 0
        assert 2 not in band.ids  # a NaN mean is in no band
    assert nonempty >= 3
    on_plane = [bool(raster.project_gaussians(scene, cam, plane).valid[row]) for cam, (row, plane) in zip(cams[-4:], ((0, lo), (1, hi), (3, lo), (4, hi)))]
    assert any(on_plane)  # some sit on their plane, not a hair in front: the edges are tested, not skirted
    empty = raster.near_band(gaussians(np.zeros((0, 3))), cams[:2], lo, hi)
    assert [b.count for b in empty] == [0, 0] and raster.near_band(scene, [], lo, hi) == []
    from_generator = raster.near_band(scene, (cam for cam in cams), lo, hi, with_ids=True)  # round 67a F6: "generator has no len()"
    assert [b.count for b in from_generator] == [b.count for b in bands]
    with pytest.raises(ValueError, match="0 < lo < hi"):
        raster.near_band(scene, cams, hi, lo)


@pytest.mark.parametrize("seed", [0, 1])
def test_some_view_draws_is_its_reference_on_planes_through_the_scene(seed):
    """`some_view_draws` (a numba scan that stops at the first Gaussian at depth ≥ the plane) against the numpy
    reference, on float32 and float64 means with NaN among them, for planes from in front of every Gaussian to past
    all of them; and at the deepest mean's own depth (the projection's sum) against the projection: drawn there, and
    behind one float further."""
    rng = np.random.default_rng(seed)
    cams = _band_cameras(rng, 5)
    means = (rng.normal(size=(500, 3)) * 0.4).astype(np.float32)
    means[::50] = np.nan
    rot, t = np.asarray(cams[0].R, np.float64), np.asarray(cams[0].t, np.float64)
    m = means.astype(np.float64)
    deepest = float(np.nanmax(rot[2, 0] * m[:, 0] + rot[2, 1] * m[:, 1] + rot[2, 2] * m[:, 2] + t[2]))  # camera 0's, as projected
    beyond = float(np.nextafter(deepest, np.inf))
    for near in (1e-6, 0.01, 0.2, 1.0, 10.0, 1e30, deepest, beyond):
        for values in (means, m):
            assert raster.some_view_draws(values, cams, near) == raster.some_view_draws_reference(values, cams, near), near
    scene = gaussians(means, log_scale=-3.0)
    assert raster.some_view_draws(means, cams[:1], deepest) and project_gaussians(scene, cams[0], deepest).num_behind < 490
    assert not raster.some_view_draws(means, cams[:1], beyond) and project_gaussians(scene, cams[0], beyond).num_behind == 490
    assert not raster.some_view_draws(means, cams, 1e30)
    assert not raster.some_view_draws(means, [], 0.01) and not raster.some_view_draws(np.zeros((0, 3)), cams, 0.01)
    assert raster.some_view_draws(means, iter(cams), 1e-6) == raster.some_view_draws(means, cams, 1e-6)  # cameras read once
    with pytest.raises(ValueError, match=r"shape \(500, 2\); expected \[N, 3\]"):  # 66c F2: read past each row, answered True
        raster.some_view_draws(means[:, :2], cams, 1e30)


@pytest.mark.parametrize("turned", [False, True])
def test_a_gaussian_whose_screen_determinant_overflows_is_counted_non_finite_by_every_engine(turned):
    """Round 98f F1: a Gaussian of log-scale 88 1e-36 in front of the camera (near plane 1e-40) has a finite Σ' whose
    det = ac - b² overflows: mid² - det = inf - inf is NaN, which numba's max(0.1, NaN) made 0.1, so numba (and the
    registration's top-k path) drew it while the reference and the torch engine counted it non-finite; turned 45
    degrees (det itself NaN) numba dropped it without counting it."""
    from drsplat.cameras import Camera

    s = np.sin(np.pi / 8) if turned else 0.0
    scene = GaussianScene(means=np.array([[0, 0, 1e-36], [0, 0, 1]], np.float32),
                          quats=np.array([[np.cos(np.pi / 8) if turned else 1.0, 0, 0, s]] * 2, np.float32),
                          log_scales=np.array([[88, 87 if turned else 88, 88], [-3, -3, -3]], np.float32),
                          opacity_logits=np.full(2, 3.0, np.float32), sh=np.full((2, 1, 3), 0.5, np.float32))
    camera = Camera(R=np.eye(3), t=np.zeros(3), fx=3000.0, fy=3000.0, cx=16.0, cy=12.0, width=32, height=24)
    for project in (raster.project_gaussians, raster.project_gaussians_reference):
        projected = project(scene, camera, 1e-40)
        assert projected.valid.tolist() == [False, True] and projected.num_nonfinite == 1, project.__name__
    outs = [raster.rasterize(scene, camera, 4, near=1e-40, engine=engine, with_rgb=rgb)
            for engine, rgb in (("numba", False), ("reference", False), ("torch", False), ("torch", True))]
    assert all(o.num_nonfinite == 1 and (o.ids == outs[1].ids).all() for o in outs)
    assert raster.rasterize_topk(scene, camera, 4, near=1e-40).num_nonfinite == 1


def test_the_library_refuses_a_near_plane_or_background_it_cannot_render_with():
    """Round 98f F2: rasterize(near=-2) drew a Gaussian behind the camera mirrored through its centre, near=0 counted
    one at z = 0 non-finite, background=(nan, 0, inf) filled the colours with NaN and inf, none of it counted."""
    from drsplat.cameras import Camera

    scene = GaussianScene(means=np.array([[0, 0, -1], [0, 0, 1]], np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (2, 1)),
                          log_scales=np.full((2, 3), -2, np.float32), opacity_logits=np.full(2, 3.0, np.float32),
                          sh=np.full((2, 1, 3), 0.5, np.float32))
    camera = Camera(R=np.eye(3), t=np.zeros(3), fx=30.0, fy=30.0, cx=16.0, cy=12.0, width=32, height=24)
    for engine in ("numba", "reference", "torch"):
        for near in (-2.0, 0.0, float("nan"), float("inf"), True):
            with pytest.raises(ValueError, match="near: expected a positive, finite camera depth"):
                raster.rasterize(scene, camera, 4, near=near, engine=engine)
        with pytest.raises(ValueError, match=r"background must be three finite values, got \[nan, 0.0, inf\]"):
            raster.rasterize(scene, camera, 4, with_rgb=True, background=(float("nan"), 0, float("inf")), engine=engine)
    with pytest.raises(ValueError, match="near: expected a positive"):
        raster.rasterize_topk(scene, camera, 4, near=-2.0)
    assert (raster.rasterize(scene, camera, 4, near=0.5).ids[12, 16] == [1, -1, -1, -1]).all()  # the one in front only


@pytest.mark.parametrize("change, words", [
    ({"width": 0}, "width must be a whole number of pixels, at least 1, got 0"), ({"height": 2.5}, "height must be a whole number"),
    ({"fx": float("nan")}, "the focal length fx must be a positive, finite number of pixels, got nan"),
    ({"fx": 0.0}, "the focal length fx must be a positive"), ({"fy": -10.0}, "the focal length fy must be a positive"),
    ({"cx": float("inf")}, "the principal point cx must be finite, got inf"),
    ({"R": np.full((3, 3), np.nan)}, r"R must be a finite \[3, 3\] rotation"), ({"R": 2 * np.eye(3)}, r"R must be a finite \[3, 3\] rotation"),
    ({"t": np.array([0.0, np.nan, 0.0])}, r"t must be a finite \[3\] translation"),
    ({"R": np.eye(3).tolist()}, "R must be a numpy array, got list"),
], ids=["width 0", "height 2.5", "fx nan", "fx 0", "fy -10", "cx inf", "R nan", "R scaled", "t nan", "R list"])
def test_every_engine_refuses_a_camera_no_view_can_be_rendered_from_in_one_error(change, words):
    """Round 104b F2: a camera built in code with width 0, NaN fx, inf cx or NaN R: torch refused it from 15 frames
    deep, numba and the reference drew an empty view (counting every Gaussian non-finite for NaN fx); fx = 0 was a
    ZeroDivisionError in every engine, fx < 0 a mirrored view without a word."""
    from drsplat.cameras import Camera

    scene = GaussianScene(means=np.array([[0, 0, 1]], np.float32), quats=np.float32([[1, 0, 0, 0]]), log_scales=np.full((1, 3), -2, np.float32),
                          opacity_logits=np.full(1, 3.0, np.float32), sh=np.full((1, 1, 3), 0.5, np.float32))
    good = Camera(R=np.eye(3), t=np.zeros(3), fx=30.0, fy=30.0, cx=16.0, cy=12.0, width=32, height=24, name="v1")
    assert raster.rasterize(scene, good, 4).ids[12, 16, 0] == 0
    whole = dataclasses.replace(good, width=32.0, height=np.int64(24))  # round 105a F3: 32.0 was "not a whole number"
    assert np.array_equal(raster.rasterize(scene, whole, 4).ids, raster.rasterize(scene, good, 4).ids)
    bad = dataclasses.replace(good, **change)
    for engine in ("numba", "reference", "torch"):
        with pytest.raises(ValueError, match=f"camera 'v1': {words}"):
            raster.rasterize(scene, bad, 4, engine=engine)
    with pytest.raises(ValueError, match=f"camera 'v1': {words}"):
        raster.rasterize_topk(scene, bad, 4)
