"""Splat rendering with moderngl: a compute pass projects every Gaussian, an instanced draw blends them.

Per view, the compute shader does what the 3DGS rasterizer's preprocessing does, once per
splat: view transform, EWA projection of the 3D covariance to a 2D one, SH colour for the
viewing direction, the per-splat style (highlight colour, hidden), and writes the ellipse's
centre, its two axes and its colour. The compute pass walks the splats in storage order (or
the moving subsample's ids, ascending) so that its reads of geometry and SH are sequential; a
walk in depth order was 3x slower on llvmpipe. The draw pass is one triangle per splat in
back-to-front order (the order comes from `viewer.sorting`), each fragment evaluating the
Gaussian and blending with premultiplied alpha, i.e. C = Σ_i c_i α_i Π_{j<i} (1 - α_j) + T·bg.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import moderngl
import numpy as np

from drsplat.cameras import Camera
from drsplat.errors import DrsplatError
from drsplat.raster import in_render_range
from drsplat.scene import GaussianScene
from viewer.assets import load_shader
from viewer.camera import scene_near_plane
from viewer.sorting import BackgroundSorter, SortResult

log = logging.getLogger(__name__)

GL_REQUIRE = 430
LOCAL_SIZE = 256

@dataclass
class FrameTimes:
    """Seconds spent on the last frame: sort (0 when skipped), order upload, project + draw, and
    of the draw the compute projection alone (only measured when SplatRenderer.profile is set)."""

    sort: float = 0.0
    upload: float = 0.0
    draw: float = 0.0
    project: float = 0.0
    drawn: int = 0


FAR_FACTOR = 100.0  # a scene whose box centre lies farther from the origin than this many box sizes is drawn about its centre


def render_origin(means: np.ndarray) -> np.ndarray:
    """[3] float64: the point the GPU's float32 positions are taken relative to, the centre of the
    finite means' box when it lies farther than FAR_FACTOR box sizes from the world origin (the
    origin itself otherwise, so that a scene near it is drawn from its own coordinates). A scene
    in map coordinates (UTM: 5e5, 4e6) has float32 steps of 0.25-0.5 units there: splats snapped
    to a grid and sorted out of order (a viewer probe, 2026-11-30)."""
    finite = np.asarray(means, np.float64)
    finite = finite[np.isfinite(finite).all(axis=1)] if finite.size else finite
    if finite.shape[0] == 0:
        return np.zeros(3)
    lo, hi = finite.min(axis=0), finite.max(axis=0)
    centre, size = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))
    return centre if np.linalg.norm(centre) > FAR_FACTOR * max(size, 1e-6) else np.zeros(3)


def splat_geometry(scene: GaussianScene, origin: np.ndarray | None = None) -> np.ndarray:
    """Per-splat shader input: [N, 3, 4] float32 rows (mean − origin, opacity), (Σxx, Σxy, Σxz, Σyy), (Σyz, Σzz, 0, 0).

    Σ = R S Sᵀ Rᵀ is the world covariance (GaussianScene.covariances), opacity = sigmoid(logit);
    origin: [3] `render_origin` (None: the world origin), subtracted in float64.
    """
    n = scene.num_gaussians
    geometry = np.zeros((n, 3, 4), np.float32)
    if n == 0:
        return geometry
    # A scale past float32 (the load warns of it) or a Σ past float32 (scale ~1e19) is an inf/NaN Σ,
    # which the projection shader drops: no numpy overflow warnings on the way.
    with np.errstate(over="ignore", invalid="ignore"):
        cov = scene.covariances()
        geometry[:, 0, :3] = np.asarray(scene.means, np.float64) - (0.0 if origin is None else np.asarray(origin, np.float64))
        geometry[:, 0, 3] = scene.opacities()
        geometry[:, 1] = np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 1]], axis=1)
        geometry[:, 2, 0] = cov[:, 1, 2]
        geometry[:, 2, 1] = cov[:, 2, 2]
    # Σ finite in float64 but not in float32 (scales ~1e19 to 1.8e19·e^69, e.g. a raw scale of 1e30 stored
    # where 3DGS stores its log): the CPU rasterizer draws these splats, the shader cannot; the load's own
    # warning covers scales that overflow float32 themselves
    beyond = ~np.isfinite(geometry[:, 1:]).all(axis=(1, 2))
    lost = int(np.isfinite(cov[beyond]).all(axis=(1, 2)).sum()) if beyond.any() else 0
    if lost:
        log.warning("%d of %d Gaussians have a covariance beyond float32 (a scale above ~1e19: are raw scales stored where "
                    "3DGS stores their logs?); the viewer does not draw them", lost, n)
    # what `drsplat.raster` renders not, the shader draws not either (a NaN Σ): the load says they are not rendered, and a
    # click (picked by drsplat.raster) found nothing on them (round 95a F1: a scene scaled by 1e30 drawn, never picked)
    geometry[~in_render_range(scene), 1:] = np.nan
    return geometry


def thinning_compensation(num: int, drawn: int) -> float:
    """How much a random subsample of `drawn` of `num` splats strengthens each splat while moving.

    With f = num / drawn, a kept splat gets opacity 1 - (1 - o)^c and a screen covariance c·Σ',
    c = sqrt(f): a thinned surface keeps most of its coverage instead of turning see-through.
    (c = f for either alone would restore the expected transmittance or the covered area; the
    square root of both was measured best on flowers.ply: 11 instead of 15 grey levels mean error
    at 60k of 542k splats, for ~10 % more draw time.) Returns 1 when nothing is left out.
    """
    if drawn <= 0 or drawn >= num:
        return 1.0
    return float(np.sqrt(num / drawn))


def preload_torch() -> None:
    """Import torchvision before the first OpenGL context exists.

    With Mesa's llvmpipe loaded, a later first `import torchvision` (which the CLIP encoder
    needs) crashes the process with a segmentation fault; importing it first is safe.
    """
    try:
        import torchvision  # noqa: F401
    except ImportError:
        pass


GL_LIBRARIES_HINT = "on Debian/Ubuntu: apt install libegl1 libgl1 libgl1-mesa-dri"


def gl_context(create, what: str) -> moderngl.Context:
    """`create()`'s OpenGL context, or a RuntimeError of one line: glcontext raises a bare Exception when it cannot load
    libEGL or libGL (round 91b F1: a 20-line traceback where `--screenshot` promises one error line), moderngl its own
    Error or a ValueError when the context is older than GL_REQUIRE, glcontext a bare Exception when EGL makes none
    (round 93a F3: both were said to be a missing library too)."""
    try:
        return create()
    except RuntimeError:
        raise
    except Exception as exc:  # noqa: BLE001 - glcontext's and moderngl's classes
        if type(exc) is Exception and "not loaded" in str(exc):  # glcontext's words for a library it could not load
            raise RuntimeError(f"cannot create {what} ({exc}): the system's OpenGL libraries are missing or unusable; "
                               f"{GL_LIBRARIES_HINT}") from None
        raise RuntimeError(f"cannot create {what}: {exc} (the viewer needs OpenGL {GL_REQUIRE // 100}.{GL_REQUIRE % 100 // 10})") from None


def create_offscreen_context() -> moderngl.Context:
    """A standalone EGL context (no window, no X server); needs GL 4.3 for the compute pass."""
    preload_torch()
    return gl_context(lambda: moderngl.create_standalone_context(backend="egl", require=GL_REQUIRE), "a headless OpenGL context (EGL)")


class SplatRenderer:
    """GPU state of one scene: geometry, SH, per-splat style and the current back-to-front order.

    moving_budget: while the camera moves, draw only this many splats (a random subsample, the
    splats of lowest random rank, so that any budget is a fixed subset); the app adapts it to
    the frame time.
    """

    def __init__(self, ctx: moderngl.Context, scene: GaussianScene, moving_budget: int = 250_000, seed: int = 0):
        self.ctx = ctx
        self.num = scene.num_gaussians
        self.background = (0.0, 0.0, 0.0)
        self.times = FrameTimes()
        self.rank = np.random.default_rng(seed).permutation(self.num).astype(np.uint32)
        self.moving_budget = min(self.num, moving_budget)
        self.origin = render_origin(scene.means)  # float32 positions on the GPU and in the sort are taken relative to it
        self.near_plane = scene_near_plane(scene.means, scene.log_scales)
        self.sorter = BackgroundSorter(np.asarray(scene.means, np.float64) - self.origin, self.rank)
        self._result: SortResult | None = None
        self._sub_key: tuple[int, int] | None = None
        self.coeffs = scene.sh.shape[1]
        self._geometry = self._buffer(splat_geometry(scene, self.origin))
        self._harmonics = self._buffer(np.ascontiguousarray(scene.sh, np.float32))
        self._style = self._buffer(np.zeros((self.num, 4), np.float32))
        self._projected = ctx.buffer(reserve=max(16, self.num * 48))
        self._order = ctx.buffer(reserve=max(16, self.num * 4))
        self._order_sub = ctx.buffer(reserve=max(16, self.num * 4))
        self._ids_sub = ctx.buffer(reserve=max(16, self.num * 4))
        self._ids_sub_budget = -1
        self._order_len = 0
        self._order_sub_len = 0
        self._project = ctx.compute_shader(load_shader("project.comp.glsl", {"LOCAL_SIZE": LOCAL_SIZE}))
        self._program = ctx.program(vertex_shader=load_shader("splat.vert.glsl"), fragment_shader=load_shader("splat.frag.glsl"))
        self._vao = ctx.vertex_array(self._program, [])
        self.last_forward: np.ndarray | None = None
        self.profile = False

    def _buffer(self, array: np.ndarray) -> moderngl.Buffer:
        data = np.ascontiguousarray(array).tobytes()
        return self.ctx.buffer(data if data else bytes(16))

    def release(self) -> None:
        self.sorter.close()
        for obj in (self._vao, self._program, self._project, self._geometry, self._harmonics, self._style, self._projected, self._order, self._order_sub, self._ids_sub):
            obj.release()

    def set_style(self, style: np.ndarray) -> None:
        """style: [N, 4] float32 (r, g, b, mix): colour = mix(sh_colour, rgb, mix); mix < 0 hides the splat."""
        style = np.ascontiguousarray(style, np.float32)
        if style.shape != (self.num, 4):
            raise ValueError(f"style has shape {style.shape}, expected ({self.num}, 4)")
        if self.num:
            self._style.write(style.tobytes())

    def upload_order(self, result: SortResult) -> None:
        start = time.perf_counter()
        if self.num:
            self._order.write(result.order.tobytes())
        self._order_len = len(result.order)
        self._result = result
        self._sub_key = None
        self.times.upload = time.perf_counter() - start

    def _upload_subsample(self, budget: int) -> int:
        if budget != self._ids_sub_budget:
            ids = np.flatnonzero(self.rank < budget).astype(np.uint32)
            if ids.size:
                self._ids_sub.write(ids.tobytes())
            self._ids_sub_budget = budget
        key = (self._result.generation, budget)
        if key != self._sub_key:
            sub = self._result.subsample(budget)
            if sub.size:
                self._order_sub.write(sub.tobytes())
            self._order_sub_len = int(sub.size)
            self._sub_key = key
        return self._order_sub_len

    def update_order(self, camera: Camera, wait: bool = False) -> bool:
        """Ask the background sorter for this view and upload a finished order; True if uploaded.

        wait=True (screenshots) sorts on the calling thread when the current order is stale.
        """
        forward = np.asarray(camera.R, np.float32)[2]
        self.times.sort = 0.0
        self.times.upload = 0.0
        if wait or (self._order_len == 0 and self.num):
            if self._order_len and self.last_forward is not None and np.array_equal(self.last_forward, forward):
                return False
            result = self.sorter.sort_now(forward)
            self.times.sort = result.seconds
            self.upload_order(result)
            self.last_forward = forward
            return True
        self.sorter.request(forward)
        result = self.sorter.poll()
        if result is None:
            return False
        self.times.sort = result.seconds
        self.upload_order(result)
        self.last_forward = result.forward
        return True

    def draw(self, camera: Camera, moving: bool = False, clear: bool = True) -> None:
        """Project and draw all splats (or the moving subsample) into the bound framebuffer."""
        start = time.perf_counter()
        if clear:
            self.ctx.clear(*self.background, 0.0)
        count = self.project(camera, moving)
        self.draw_range(0, count, moving)
        self.times.draw = time.perf_counter() - start
        self.times.drawn = count

    def project(self, camera: Camera, moving: bool = False) -> int:
        """The compute pass for `camera`: every splat (or the moving subsample); returns how many
        splats the draw then has (0 when there is nothing to draw)."""
        start = time.perf_counter()
        if self.num == 0 or self._order_len == 0:
            return 0
        use_sub = moving and self.moving_budget < self.num
        count = self._upload_subsample(self.moving_budget) if use_sub else self.num
        self._bind_uniforms(camera, count)
        self._project["use_ids"].value = use_sub
        thin = thinning_compensation(self.num, count) if use_sub else 1.0
        self._project["thin_alpha"].value = thin
        self._project["thin_cov"].value = thin
        self._geometry.bind_to_storage_buffer(0)
        self._harmonics.bind_to_storage_buffer(1)
        self._style.bind_to_storage_buffer(2)
        self._ids_sub.bind_to_storage_buffer(3)
        self._projected.bind_to_storage_buffer(4)
        self._project.run(group_x=(count + LOCAL_SIZE - 1) // LOCAL_SIZE)
        self.ctx.memory_barrier()
        if self.profile:
            self.ctx.finish()
            self.times.project = time.perf_counter() - start
        return count

    def draw_range(self, first: int, count: int, moving: bool = False) -> None:
        """Blend splats first .. first + count - 1 of the back-to-front order (of the moving
        subsample when `moving`) over the bound framebuffer, after `project`. Consecutive ranges
        drawn in order give the same image as one draw of their union (blending is in order)."""
        if count <= 0:
            return
        ctx = self.ctx
        use_sub = moving and self.moving_budget < self.num
        order = self._order_sub if use_sub else self._order
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.enable(moderngl.BLEND)
        ctx.blend_func = moderngl.ONE, moderngl.ONE_MINUS_SRC_ALPHA
        ctx.blend_equation = moderngl.FUNC_ADD
        order.bind_to_storage_buffer(5)
        self._projected.bind_to_storage_buffer(4)
        self._vao.render(moderngl.TRIANGLES, vertices=3 * count, first=3 * first)
        ctx.disable(moderngl.BLEND)
        ctx.finish()

    def _bind_uniforms(self, camera: Camera, count: int) -> None:
        cs = self._project
        R = np.asarray(camera.R, np.float64)
        cs["rotation"].write(np.ascontiguousarray(R.T, np.float32).tobytes())
        # positions are relative to self.origin: R (x − o) + (t + R o) = R x + t, the sum taken in float64
        cs["translation"].value = tuple(float(v) for v in np.asarray(camera.t, np.float64) + R @ self.origin)
        cs["cam_pos"].value = tuple(float(v) for v in np.asarray(camera.center, np.float64) - self.origin)
        cs["focal"].value = (float(camera.fx), float(camera.fy))
        cs["principal"].value = (float(camera.cx), float(camera.cy))
        cs["viewport"].value = (float(camera.width), float(camera.height))
        # the clamp of drsplat.raster._screen_covariances (3DGS, in gsplat's off-centre form)
        margin_x, margin_y = 0.15 * camera.width / camera.fx, 0.15 * camera.height / camera.fy
        cs["tan_limit_neg"].value = (camera.cx / camera.fx + margin_x, camera.cy / camera.fy + margin_y)
        cs["tan_limit_pos"].value = ((camera.width - camera.cx) / camera.fx + margin_x, (camera.height - camera.cy) / camera.fy + margin_y)
        cs["near_plane"].value = self.near_plane
        cs["coeffs"].value = self.coeffs
        cs["count"].value = count


def max_image_side(ctx: moderngl.Context) -> int:
    """The largest side, in pixels, of an image this context can render into: the least of its
    driver's texture, renderbuffer and viewport limits (16384 on llvmpipe; less on some GPUs)."""
    info = ctx.info
    limits = [int(info.get("GL_MAX_TEXTURE_SIZE", 0)), int(info.get("GL_MAX_RENDERBUFFER_SIZE", 0))]
    dims = info.get("GL_MAX_VIEWPORT_DIMS")
    limits += [int(d) for d in dims] if isinstance(dims, (tuple, list)) else []
    return min(limit for limit in limits if limit > 0)


def fit_within(width: int, height: int, side: int) -> tuple[int, int]:
    """width x height scaled down, keeping its aspect, until neither side passes `side` (at least 1
    pixel each): a window wider than the GPU's largest image is drawn smaller and stretched over it."""
    width, height = max(1, width), max(1, height)
    if max(width, height) <= side:
        return width, height
    factor = side / max(width, height)
    return max(1, min(side, int(width * factor))), max(1, min(side, int(height * factor)))


class OffscreenTarget:
    """An RGBA8 framebuffer of a fixed size to render into and read back."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int):
        side = max_image_side(ctx)
        if not (1 <= width <= side and 1 <= height <= side):
            raise DrsplatError(f"cannot render a {width}x{height} image: the OpenGL driver renders 1 to {side} pixels a side")
        self.ctx = ctx
        self.width, self.height = width, height
        self.texture = ctx.texture((width, height), 4)
        self.texture.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self.fbo = ctx.framebuffer(color_attachments=[self.texture])

    def use(self) -> None:
        self.fbo.use()
        self.ctx.viewport = (0, 0, self.width, self.height)

    def read_rgb(self) -> np.ndarray:
        """[H, W, 3] uint8, row 0 at the top (as images are stored)."""
        data = self.fbo.read(components=3, alignment=1)
        return np.frombuffer(data, np.uint8).reshape(self.height, self.width, 3)[::-1].copy()

    def release(self) -> None:
        self.fbo.release()
        self.texture.release()


class Blitter:
    """Draws a texture over the whole bound viewport (one triangle), scaling with linear filtering."""

    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self.program = ctx.program(vertex_shader=load_shader("blit.vert.glsl"), fragment_shader=load_shader("blit.frag.glsl"))
        self.vao = ctx.vertex_array(self.program, [])

    def draw(self, texture: moderngl.Texture) -> None:
        texture.use(0)
        self.program["image"].value = 0
        self.ctx.disable(moderngl.BLEND)
        self.vao.render(moderngl.TRIANGLES, vertices=3)

    def release(self) -> None:
        self.vao.release()
        self.program.release()


def render_offscreen(ctx: moderngl.Context, renderer: SplatRenderer, camera: Camera) -> np.ndarray:
    """One frame of `camera` (sorted first, synchronously) as [H, W, 3] uint8."""
    target = OffscreenTarget(ctx, camera.width, camera.height)
    try:
        target.use()
        renderer.update_order(camera, wait=True)
        renderer.draw(camera)
        return target.read_rgb()
    finally:
        target.release()
