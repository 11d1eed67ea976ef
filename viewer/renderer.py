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
from drsplat.scene import GaussianScene
from viewer.sorting import BackgroundSorter, SortResult

log = logging.getLogger(__name__)

GL_REQUIRE = 430
LOCAL_SIZE = 256

PROJECT_SHADER = """
#version 430
layout(local_size_x = %(local)d) in;
layout(std430, binding = 0) readonly buffer Geometry { vec4 geometry[]; };
layout(std430, binding = 1) readonly buffer Harmonics { float harmonics[]; };
layout(std430, binding = 2) readonly buffer Style { vec4 style[]; };
layout(std430, binding = 3) readonly buffer Ids { uint ids[]; };
layout(std430, binding = 4) writeonly buffer Projected { vec4 projected[]; };

uniform mat3 rotation;
uniform vec3 translation;
uniform vec3 cam_pos;
uniform vec2 focal;
uniform vec2 principal;
uniform vec2 viewport;
uniform vec2 tan_limit_neg;
uniform vec2 tan_limit_pos;
uniform float near_plane;
uniform int coeffs;
uniform uint count;
uniform bool use_ids;
uniform float thin_alpha;
uniform float thin_cov;

const float C0 = 0.28209479177387814;
const float C1 = 0.4886025119029199;
const float C2[5] = float[](1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396);
const float C3[7] = float[](-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658, 1.445305721320277, -0.5900435899266435);

vec3 sh(uint id, int k) {
    uint base = (id * uint(coeffs) + uint(k)) * 3u;
    return vec3(harmonics[base], harmonics[base + 1u], harmonics[base + 2u]);
}

vec3 sh_color(uint id, vec3 d) {
    vec3 c = C0 * sh(id, 0);
    if (coeffs > 1) {
        float x = d.x, y = d.y, z = d.z;
        c += -C1 * y * sh(id, 1) + C1 * z * sh(id, 2) - C1 * x * sh(id, 3);
        if (coeffs > 4) {
            float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
            c += C2[0] * xy * sh(id, 4) + C2[1] * yz * sh(id, 5) + C2[2] * (2.0 * zz - xx - yy) * sh(id, 6)
               + C2[3] * xz * sh(id, 7) + C2[4] * (xx - yy) * sh(id, 8);
            if (coeffs > 9) {
                c += C3[0] * y * (3.0 * xx - yy) * sh(id, 9) + C3[1] * xy * z * sh(id, 10)
                   + C3[2] * y * (4.0 * zz - xx - yy) * sh(id, 11) + C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh(id, 12)
                   + C3[4] * x * (4.0 * zz - xx - yy) * sh(id, 13) + C3[5] * z * (xx - yy) * sh(id, 14)
                   + C3[6] * x * (xx - 3.0 * yy) * sh(id, 15);
            }
        }
    }
    return max(c + 0.5, vec3(0.0));
}

void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= count) return;
    uint id = use_ids ? ids[i] : i;
    vec4 g0 = geometry[3u * id], g1 = geometry[3u * id + 1u], g2 = geometry[3u * id + 2u];
    vec4 st = style[id];
    // a thinned (moving) subsample keeps 1/f of the splats: 1 - (1 - o)^thin_alpha, thin_alpha = sqrt(f)
    if (thin_alpha != 1.0) g0.w = 1.0 - pow(1.0 - min(g0.w, 0.99), thin_alpha);
    vec3 p = rotation * g0.xyz + translation;
    projected[3u * id] = vec4(0.0);
    if (p.z <= near_plane || st.a < 0.0) return;
    mat3 cov3 = mat3(g1.x, g1.y, g1.z, g1.y, g1.w, g2.x, g1.z, g2.x, g2.y);
    vec2 txy = clamp(p.xy / p.z, -tan_limit_neg, tan_limit_pos) * p.z;
    float iz = 1.0 / p.z;
    mat3 J = mat3(focal.x * iz, 0.0, 0.0,
                  0.0, focal.y * iz, 0.0,
                  -focal.x * txy.x * iz * iz, -focal.y * txy.y * iz * iz, 0.0);
    mat3 T = J * rotation;
    mat3 cov2 = thin_cov * (T * cov3 * transpose(T));
    float a = cov2[0][0] + 0.3, b = cov2[0][1], c = cov2[1][1] + 0.3;
    float mid = 0.5 * (a + c);
    float radius = length(vec2(0.5 * (a - c), b));
    float l1 = mid + radius, l2 = mid - radius;
    if (l2 <= 0.0) return;
    vec2 dir = abs(b) > 1e-12 ? normalize(vec2(b, l1 - a)) : (a >= c ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
    vec2 uv = focal * p.xy * iz + principal;
    // alpha = o exp(-d²/2) >= 1/255 only within d <= sqrt(2 ln(255 o)) standard deviations
    float reach = min(3.0, sqrt(2.0 * log(max(255.0 * g0.w, 1.0))));
    if (reach <= 0.0) return;
    float extent = reach * sqrt(l1);
    if (uv.x + extent < 0.0 || uv.y + extent < 0.0 || uv.x - extent > viewport.x || uv.y - extent > viewport.y) return;
    vec2 major = reach * sqrt(l1) * dir;
    vec2 minor = reach * sqrt(l2) * vec2(-dir.y, dir.x);
    vec2 to_ndc = vec2(2.0, -2.0) / viewport;
    vec3 rgb = sh_color(id, normalize(g0.xyz - cam_pos));
    rgb = mix(rgb, st.rgb, st.a);
    projected[3u * id] = vec4(uv * to_ndc + vec2(-1.0, 1.0), p.z, reach);
    projected[3u * id + 1u] = vec4(major * to_ndc, minor * to_ndc);
    projected[3u * id + 2u] = vec4(rgb, g0.w);
}
"""

VERTEX_SHADER = """
#version 430
layout(std430, binding = 4) readonly buffer Projected { vec4 projected[]; };
layout(std430, binding = 5) readonly buffer Order { uint order[]; };
out vec4 v_color;
out vec2 v_sigma;
void main() {
    // one triangle per splat, circumscribing the ellipse's unit circle; splats back to front
    uint splat_id = order[uint(gl_VertexID) / 3u];
    int k = gl_VertexID % 3;
    vec2 corner = k == 0 ? vec2(0.0, 2.0) : vec2(k == 1 ? -1.7320508 : 1.7320508, -1.0);
    vec4 center = projected[3u * splat_id];
    if (center.w == 0.0) {
        gl_Position = vec4(2.0, 2.0, 2.0, 1.0);
        v_color = vec4(0.0);
        v_sigma = vec2(10.0);
        return;
    }
    vec4 axes = projected[3u * splat_id + 1u];
    v_color = projected[3u * splat_id + 2u];
    v_sigma = center.w * corner;
    gl_Position = vec4(center.xy + corner.x * axes.xy + corner.y * axes.zw, 0.0, 1.0);
}
"""

FRAGMENT_SHADER = """
#version 430
in vec4 v_color;
in vec2 v_sigma;
out vec4 frag;
void main() {
    float alpha = min(0.99, v_color.a * exp(-0.5 * dot(v_sigma, v_sigma)));
    if (alpha < 1.0 / 255.0) discard;
    frag = vec4(v_color.rgb * alpha, alpha);
}
"""


@dataclass
class FrameTimes:
    """Seconds spent on the last frame: sort (0 when skipped), order upload, project + draw, and
    of the draw the compute projection alone (only measured when SplatRenderer.profile is set)."""

    sort: float = 0.0
    upload: float = 0.0
    draw: float = 0.0
    project: float = 0.0
    drawn: int = 0


def splat_geometry(scene: GaussianScene) -> np.ndarray:
    """Per-splat shader input: [N, 3, 4] float32 rows (mean, opacity), (Σxx, Σxy, Σxz, Σyy), (Σyz, Σzz, 0, 0).

    Σ = R S Sᵀ Rᵀ is the world covariance (GaussianScene.covariances), opacity = sigmoid(logit).
    """
    n = scene.num_gaussians
    geometry = np.zeros((n, 3, 4), np.float32)
    if n == 0:
        return geometry
    cov = scene.covariances()
    geometry[:, 0, :3] = scene.means
    geometry[:, 0, 3] = scene.opacities()
    geometry[:, 1] = np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 1]], axis=1)
    geometry[:, 2, 0] = cov[:, 1, 2]
    geometry[:, 2, 1] = cov[:, 2, 2]
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


def create_offscreen_context() -> moderngl.Context:
    """A standalone EGL context (no window, no X server); needs GL 4.3 for the compute pass."""
    preload_torch()
    return moderngl.create_standalone_context(backend="egl", require=GL_REQUIRE)


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
        self.sorter = BackgroundSorter(scene.means, self.rank)
        self._result: SortResult | None = None
        self._sub_key: tuple[int, int] | None = None
        self.coeffs = scene.sh.shape[1]
        self._geometry = self._buffer(splat_geometry(scene))
        self._harmonics = self._buffer(np.ascontiguousarray(scene.sh, np.float32))
        self._style = self._buffer(np.zeros((self.num, 4), np.float32))
        self._projected = ctx.buffer(reserve=max(16, self.num * 48))
        self._order = ctx.buffer(reserve=max(16, self.num * 4))
        self._order_sub = ctx.buffer(reserve=max(16, self.num * 4))
        self._ids_sub = ctx.buffer(reserve=max(16, self.num * 4))
        self._ids_sub_budget = -1
        self._order_len = 0
        self._order_sub_len = 0
        self._project = ctx.compute_shader(PROJECT_SHADER % {"local": LOCAL_SIZE})
        self._program = ctx.program(vertex_shader=VERTEX_SHADER, fragment_shader=FRAGMENT_SHADER)
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
        ctx = self.ctx
        if clear:
            ctx.clear(*self.background, 0.0)
        if self.num == 0 or self._order_len == 0:
            self.times.draw = time.perf_counter() - start
            self.times.drawn = 0
            return
        use_sub = moving and self.moving_budget < self.num
        count = self._upload_subsample(self.moving_budget) if use_sub else self.num
        order = self._order_sub if use_sub else self._order
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
        ctx.memory_barrier()
        if self.profile:
            ctx.finish()
            self.times.project = time.perf_counter() - start
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.enable(moderngl.BLEND)
        ctx.blend_func = moderngl.ONE, moderngl.ONE_MINUS_SRC_ALPHA
        ctx.blend_equation = moderngl.FUNC_ADD
        order.bind_to_storage_buffer(5)
        self._vao.render(moderngl.TRIANGLES, vertices=3 * count)
        ctx.disable(moderngl.BLEND)
        ctx.finish()
        self.times.draw = time.perf_counter() - start
        self.times.drawn = count

    def _bind_uniforms(self, camera: Camera, count: int) -> None:
        cs = self._project
        R = np.asarray(camera.R, np.float64)
        cs["rotation"].write(np.ascontiguousarray(R.T, np.float32).tobytes())
        cs["translation"].value = tuple(float(v) for v in camera.t)
        cs["cam_pos"].value = tuple(float(v) for v in camera.center)
        cs["focal"].value = (float(camera.fx), float(camera.fy))
        cs["principal"].value = (float(camera.cx), float(camera.cy))
        cs["viewport"].value = (float(camera.width), float(camera.height))
        # the clamp of drsplat.raster._screen_covariances (3DGS, in gsplat's off-centre form)
        margin_x, margin_y = 0.15 * camera.width / camera.fx, 0.15 * camera.height / camera.fy
        cs["tan_limit_neg"].value = (camera.cx / camera.fx + margin_x, camera.cy / camera.fy + margin_y)
        cs["tan_limit_pos"].value = ((camera.width - camera.cx) / camera.fx + margin_x, (camera.height - camera.cy) / camera.fy + margin_y)
        cs["near_plane"].value = 0.01
        cs["coeffs"].value = self.coeffs
        cs["count"].value = count


class OffscreenTarget:
    """An RGBA8 framebuffer of a fixed size to render into and read back."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int):
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


BLIT_VERTEX = """
#version 330
out vec2 uv;
void main() {
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    uv = p;
    gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
"""

BLIT_FRAGMENT = """
#version 330
uniform sampler2D image;
in vec2 uv;
out vec4 frag;
void main() { frag = vec4(texture(image, uv).rgb, 1.0); }
"""


class Blitter:
    """Draws a texture over the whole bound viewport (one triangle), scaling with linear filtering."""

    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self.program = ctx.program(vertex_shader=BLIT_VERTEX, fragment_shader=BLIT_FRAGMENT)
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
