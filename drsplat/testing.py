"""Reusable test helpers: random and hard-case scenes, and agreement checks between rasterizer engines.

Used by tests/test_raster*.py and by anyone adding a rasterizer engine (`drsplat.raster.ENGINES`):
an engine is right when `assert_agree(engine_output, reference_output)` holds on `random_case`
and on every `hard_cases()` entry, and `assert_physical` holds on its output.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from drsplat.cameras import Camera
from drsplat.cameras import look_at_camera
from drsplat.raster import NEAR, T_MIN, RasterOutput, rasterize
from drsplat.scene import SH_C0, GaussianScene


def random_scene(rng: np.random.Generator, n: int, sh_degree: int = 0, spread: float = 1.0, log_scale=(-3.5, -1.0)) -> GaussianScene:
    """n Gaussians with normal means (· spread), random rotations, uniform log-scales and logits ~ N(0, 2)."""
    return GaussianScene(
        means=(rng.normal(size=(n, 3)) * spread).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=rng.uniform(*log_scale, size=(n, 3)).astype(np.float32),
        opacity_logits=rng.normal(0.0, 2.0, size=n).astype(np.float32),
        sh=(rng.normal(size=(n, (sh_degree + 1) ** 2, 3)) * 0.6).astype(np.float32),
    )


def gaussians(means, log_scale=-2.0, opacity_logit=30.0, color=None) -> GaussianScene:
    """Axis-aligned Gaussians at `means` [N, 3] with one scale (or [N, 3] scales), opacity and DC colour."""
    means = np.asarray(means, np.float32).reshape(-1, 3)
    n = means.shape[0]
    sh = np.zeros((n, 1, 3), np.float32)
    if color is not None:
        sh[:, 0] = (np.asarray(color, np.float32) - 0.5) / SH_C0
    return GaussianScene(
        means=means,
        quats=np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1)),
        log_scales=np.broadcast_to(np.asarray(log_scale, np.float32), (n, 3)).copy() if np.ndim(log_scale) < 2 else np.asarray(log_scale, np.float32),
        opacity_logits=np.broadcast_to(np.asarray(opacity_logit, np.float32), (n,)).copy(),
        sh=sh,
    )


def with_floaters(scene: GaussianScene, cameras, per_camera: int = 20, seed: int = 0) -> GaussianScene:
    """`scene` plus `per_camera` opaque, coloured Gaussians 0.03-0.15 units in front of each of `cameras`, inside
    its view: the floaters a trainer leaves before a camera, which INRIA's rasterizer (near plane 0.2) never drew
    there (`drsplat.frames.near_plane_as_trained`'s tests and bench)."""
    rng = np.random.default_rng(seed)
    placed = []
    for c in cameras:
        z = rng.uniform(0.03, 0.15, per_camera)
        u, v = rng.uniform(0.1, 0.9, per_camera) * c.width, rng.uniform(0.1, 0.9, per_camera) * c.height
        in_camera = np.stack([(u - c.cx) / c.fx * z, (v - c.cy) / c.fy * z, z], axis=1)
        placed.append((in_camera - np.asarray(c.t)) @ np.asarray(c.R))  # x_w = Rᵀ (x_c − t)
    means = np.concatenate(placed).astype(np.float32) if placed else np.zeros((0, 3), np.float32)
    k = len(means)
    quats = rng.normal(size=(k, 4)).astype(np.float32)
    sh = np.zeros((k, *scene.sh.shape[1:]), np.float32)
    sh[:, 0] = rng.normal(size=(k, 3)) * 1.5
    return GaussianScene(means=np.concatenate([scene.means, means]),
                         quats=np.concatenate([scene.quats, quats / np.linalg.norm(quats, axis=1, keepdims=True)]),
                         log_scales=np.concatenate([scene.log_scales, np.log(rng.uniform(0.002, 0.01, (k, 3))).astype(np.float32)]),
                         opacity_logits=np.concatenate([scene.opacity_logits, np.full(k, 3.0, np.float32)]),
                         sh=np.concatenate([scene.sh, sh]))


def cameras_with_own_images(prepared, cameras, folder: Path, near: float = NEAR) -> list:
    """`cameras` with images of the scene's renders (`prepared`, near plane `near`) saved as
    `folder`/<name>.png: the images a scene trained by a rasterizer of that plane was fitted to."""
    from PIL import Image  # Pillow only where images are written

    out = []
    for camera in cameras:
        rgb = rasterize(prepared, camera, 1, with_rgb=True, near=near).rgb
        path = Path(folder) / f"{camera.name}.png"
        Image.fromarray(np.clip(np.rint(rgb * 255), 0, 255).astype(np.uint8)).save(path)
        out.append(replace(camera, image_path=path))
    return out


def front_camera(width: int = 40, height: int = 30, cx: float | None = None, cy: float | None = None, z: float = -4.0) -> Camera:
    """Camera at (0, 0, z) looking along +z, OpenCV axes aligned with the world's."""
    return look_at_camera([0.0, 0.0, z], [0.0, 0.0, 0.0], width, height, fov_x_deg=50.0, cx=cx, cy=cy)


@dataclass
class RasterCase:
    """One scene + camera an engine must render like the reference (kwargs go to the engine)."""

    name: str
    scene: GaussianScene
    camera: Camera
    topk: int
    kwargs: dict = field(default_factory=dict)


def random_case(seed: int, n: int = 400, sh_degree: int = 0, topk: int = 8) -> RasterCase:
    """A random scene seen off-centre (48 x 34 px, principal point not at the centre)."""
    rng = np.random.default_rng(seed)
    scene = random_scene(rng, n, sh_degree)
    cam = look_at_camera(rng.normal(size=3) * 0.5 + [0, 0, -4], [0, 0, 0], 48, 34, fov_x_deg=55, cx=20.3, cy=19.1)
    return RasterCase(f"random-{seed}", scene, cam, topk, dict(with_rgb=True, with_depth=True, with_median=True, background=(0.2, 0.5, 0.9)))


def windowed(case: RasterCase, x0: int, y0: int, width: int, height: int) -> RasterCase:
    """The case seen through pixels x0 .. x0 + width, y0 .. y0 + height of its image: the same rays
    (the principal point moved by the window's corner) on fewer pixels and tiles. Its render is the
    full image's under the window where the corner is on the 16-px tile grid (3DGS's tile
    rectangles cut some footprints at tile borders: off the grid, pixels near those borders can
    differ slightly) and no Gaussian's direction lies past the window's EWA clamp (1.3x its field
    of view)."""
    cam = case.camera
    window = replace(cam, cx=cam.cx - x0, cy=cam.cy - y0, width=width, height=height)
    return replace(case, name=f"{case.name}-window", camera=window)


def stacked_case(count: int = 10_000) -> RasterCase:
    """`count` identical Gaussians (opacity 0.5) on one pixel: T halves until the 1e-4 floor."""
    cam = front_camera(24, 18)
    centre = np.linalg.solve(cam.R, np.array([(10.5 - cam.cx) / cam.fx * 4, (7.5 - cam.cy) / cam.fy * 4, 4.0]) - cam.t)
    scene = gaussians(np.tile(centre, (count, 1)), log_scale=-9.0, opacity_logit=0.0)
    return RasterCase("stacked", scene, cam, 64, dict(with_rgb=True, with_depth=True, with_median=True))


def hard_cases() -> list[RasterCase]:
    """The scenes that broke rasterizers before: empty, all behind, camera inside a Gaussian,
    extreme scales (1e-8 to e^60, rotated needles), opacity 0 / saturated, stacked Gaussians at the T floor, off-centre non-square."""
    rng = np.random.default_rng(7)
    cases = [RasterCase("empty", gaussians(np.zeros((0, 3))), front_camera(24, 18), 5, dict(with_rgb=True, with_depth=True, with_median=True, background=(1.0, 0.0, 0.5)))]
    behind = random_scene(rng, 200)
    behind.means[:, 2] = -5.0 - np.abs(behind.means[:, 2])
    cases.append(RasterCase("behind", behind, front_camera(24, 18), 4, dict(with_depth=True, with_median=True)))
    inside = gaussians(
        [[0.0, 0.0, -3.5], [0.0, 0.0, -4.2], [0.3, -0.1, 1.0]], log_scale=[[1.5, 1.0, 2.0], [1.0, 1.0, 1.0], [-2, -2, -2]],
        opacity_logit=[-1.0, 2.0, 30.0], color=[0.3, 0.6, 0.9],
    )  # fmt: skip
    cases.append(RasterCase("camera-inside", inside, front_camera(40, 30, cx=14.0, cy=17.5), 3, dict(with_rgb=True, with_depth=True, with_median=True)))
    extreme = random_scene(np.random.default_rng(11), 120)
    extreme.log_scales[:40] = np.log(1e-8)
    extreme.log_scales[40:45] = np.log(1e4)
    extreme.log_scales[45:50, 0] = np.log(1e4)
    extreme.opacity_logits[40:50] = -3.0
    extreme.log_scales[50:52] = 60.0  # enormous: a screen radius and α ≥ 1/255 box past 2^63 pixels (int64 overflow once dropped them)
    extreme.opacity_logits[50:52] = -2.0
    # rotated needles, 3e5 times longer than wide, across the view: the screen conic is the inverse of a
    # nearly singular Σ', whose determinant loses ~1e-16·L² of itself (L: the screen length in pixels)
    extreme.log_scales[52:60] = np.log([30.0, 1e-4, 1e-4])
    extreme.opacity_logits[52:60] = 2.0
    cases.append(RasterCase("extreme-scales", extreme, front_camera(40, 30, cx=23.0, cy=11.0), 16, dict(with_rgb=True, with_depth=True, with_median=True)))
    opacity = random_scene(np.random.default_rng(13), 200)
    opacity.opacity_logits[:50] = -30.0
    opacity.opacity_logits[50:100] = 30.0
    cases.append(RasterCase("opacity-0-and-1", opacity, front_camera(36, 28), 12, dict(with_rgb=True)))
    cases.append(stacked_case())
    offc = random_scene(np.random.default_rng(31), 300, sh_degree=1)
    cam = look_at_camera([0.3, -0.2, -4.0], [0.0, 0.1, 0.0], 53, 21, fov_x_deg=70, cx=40.0, cy=3.5)
    cases.append(RasterCase("off-centre-non-square", offc, cam, 10, dict(with_rgb=True, with_depth=True, with_median=True)))
    return cases


def assert_agree(a: RasterOutput, b: RasterOutput, tol: float = 1e-5) -> None:
    """Output `a` equals reference output `b`: weights/rgb/depth/alpha within tol, ids identical
    except between entries whose weights tie (then their order is arbitrary)."""
    assert a.ids.shape == b.ids.shape and a.ids.dtype == np.int32 and a.weights.dtype == np.float32
    np.testing.assert_allclose(a.weights, b.weights, atol=tol, rtol=0)
    np.testing.assert_allclose(a.alpha, b.alpha, atol=tol, rtol=0)
    for name in ("rgb", "depth"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_allclose(x, y, atol=tol, rtol=0)
    assert (a.median_ids is None) == (b.median_ids is None)
    if a.median_ids is not None:
        np.testing.assert_array_equal(a.median_ids, b.median_ids)
    differ = a.ids != b.ids
    if differ.any():
        w = b.weights.astype(np.float64)
        gap_prev = np.abs(np.diff(w, axis=2, prepend=np.inf))
        gap_next = np.abs(np.diff(w, axis=2, append=-np.inf))
        tie = np.minimum(gap_prev, gap_next) < 1e-7
        assert not (differ & ~tie).any(), f"{int((differ & ~tie).sum())} ids differ where weights do not tie"
    assert a.num_nonfinite == b.num_nonfinite


def agreement(a: RasterOutput, b: RasterOutput) -> tuple[float, float]:
    """(max |weight difference|, fraction of top-k slots whose ids differ) of two outputs."""
    if a.weights.size == 0:
        return 0.0, 0.0
    wdiff = float(np.abs(a.weights.astype(np.float64) - b.weights).max())
    return wdiff, float(np.count_nonzero(a.ids != b.ids) / a.ids.size)


def assert_physical(out: RasterOutput, topk: int) -> None:
    """Invariants of any 3DGS top-k output."""
    for arr in (out.weights, out.alpha, out.rgb, out.depth):
        if arr is not None:
            assert np.isfinite(arr).all()
    w = out.weights.astype(np.float64)
    assert out.ids.shape[-1] == topk
    assert (w >= 0).all()
    assert (np.diff(w, axis=2) <= 0).all(), "weights must be sorted in descending order"
    assert ((out.ids >= 0) == (w > 0)).all(), "ids are -1 exactly where weights are 0"
    assert (w.sum(axis=2) <= 1.0 - T_MIN + 1e-6).all()
    assert (w.sum(axis=2) <= out.alpha + 1e-5).all()
    assert ((0 <= out.alpha) & (out.alpha <= 1.0 - T_MIN + 1e-6)).all()
    if out.median_ids is not None:  # set exactly where the accumulated opacity reached ½
        assert out.median_ids.dtype == np.int32
        assert (out.median_ids[out.alpha >= 0.5 + 1e-6] >= 0).all()
        assert (out.median_ids[out.alpha < 0.5 - 1e-6] == -1).all()
    ids = np.sort(out.ids, axis=2)
    assert not ((ids[..., 1:] == ids[..., :-1]) & (ids[..., 1:] >= 0)).any(), "a Gaussian appears twice in one pixel"


def check_engine(render: Callable[..., RasterOutput], reference: Callable[..., RasterOutput], case: RasterCase, tol: float = 1e-5) -> RasterOutput:
    """Render `case` with both callables (signature of drsplat.raster.rasterize), assert they agree; returns render's output."""
    a = render(case.scene, case.camera, case.topk, **case.kwargs)
    b = reference(case.scene, case.camera, case.topk, **case.kwargs)
    assert_agree(a, b, tol)
    assert_physical(a, case.topk)
    return a
