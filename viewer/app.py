"""The interactive viewer window (GLFW + moderngl + imgui-bundle) and the offscreen screenshot path.

imgui_bundle is imported before glfw so that pyGLFW binds the GLFW library imgui-bundle ships.
Window code runs on any GLFW platform, including the null platform used by the tests
(`DRSPLAT_VIEWER_PLATFORM=null`, EGL context).
"""

from __future__ import annotations

import ctypes
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from imgui_bundle import imgui  # noqa: I001 - must precede glfw

import glfw
import moderngl

from drsplat.cameras import Camera
from drsplat.utils import atomic_path
from viewer.camera import ViewController, camera_for_size
from viewer.renderer import GL_REQUIRE, Blitter, OffscreenTarget, SplatRenderer, create_offscreen_context, preload_torch, render_offscreen
from viewer.state import ViewerState

log = logging.getLogger(__name__)

MOVING_SECONDS = 0.25
MOVING_SCALE = 0.5  # render resolution factor while the camera moves
MOVING_FRAME_SECONDS = 0.1  # the moving subsample adapts towards this draw time
MIN_MOVING_SPLATS = 20_000
FLY_SPEED = 0.4  # scene-distance units per second (times the orbit distance)


def next_moving_budget(budget: int, num: int, seconds: float) -> int:
    """The moving subsample for the next moving frame, given that `budget` splats took `seconds`.

    The draw time is linear in the splats drawn (per-triangle setup dominates on llvmpipe), so
    the step is proportional, budget · MOVING_FRAME_SECONDS / seconds, limited to ×0.5–×1.5 per
    frame against timing noise, and kept within [MIN_MOVING_SPLATS, num].
    """
    factor = float(np.clip(MOVING_FRAME_SECONDS / max(seconds, 1e-4), 0.5, 1.5))
    return int(np.clip(budget * factor, min(num, MIN_MOVING_SPLATS), num))


def calibrated_moving_budget(num: int, full_seconds: float) -> int:
    """A first moving subsample from the time of a full frame: the share of the scene a full-
    resolution frame draws in MOVING_FRAME_SECONDS. Moving frames (MOVING_SCALE resolution) are
    cheaper per splat, so this starts a little low and next_moving_budget grows it."""
    share = MOVING_FRAME_SECONDS / max(full_seconds, 1e-4)
    return int(np.clip(num * share, min(num, MIN_MOVING_SPLATS), num))


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write [H, W, 3] uint8 as PNG, atomically."""
    from PIL import Image

    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format="PNG")
    return path


def render_screenshot(state: ViewerState, camera: Camera, path: str | Path | None = None, ctx: moderngl.Context | None = None) -> np.ndarray:
    """Render one frame of the state's scene and style from `camera` on an EGL standalone context
    (no window, no X server); save it as PNG when `path` is given. Returns [H, W, 3] uint8."""
    own = ctx is None
    ctx = ctx or create_offscreen_context()
    renderer = SplatRenderer(ctx, state.scene)
    try:
        renderer.set_style(state.style())
        image = render_offscreen(ctx, renderer, camera)
    finally:
        renderer.release()
        if own:
            ctx.release()
    if path is not None:
        save_png(image, path)
    return image


@dataclass
class InputState:
    last_change: float = 0.0
    last_time: float = 0.0
    drag_distance: float = 0.0


class ViewerApp:
    """The window: camera input, splat drawing, the panels (viewer.panels) and screenshots."""

    def __init__(self, state: ViewerState, width: int = 1280, height: int = 720, title: str = "drsplat viewer", platform: str | None = None):
        self.state = state
        self.platform = platform or os.environ.get("DRSPLAT_VIEWER_PLATFORM")
        self.window = self._create_window(width, height, title)
        self.ctx = moderngl.create_context(require=GL_REQUIRE)
        imgui.create_context()
        imgui.get_io().config_flags |= imgui.ConfigFlags_.nav_enable_keyboard.value
        imgui.backends.glfw_init_for_opengl(ctypes.cast(self.window, ctypes.c_void_p).value, True)
        imgui.backends.opengl3_init("#version 330")
        fb_w, fb_h = glfw.get_framebuffer_size(self.window)
        means = state.scene.means if state.scene is not None else np.zeros((0, 3), np.float32)
        self.view = ViewController.for_scene(means, state.cameras, fb_w, fb_h)
        self.renderer: SplatRenderer | None = None
        self.blitter = Blitter(self.ctx)
        self._target: OffscreenTarget | None = None
        self._drawn_key: tuple | None = None
        self.moving_scale = MOVING_SCALE
        self.render_scale = 1.0
        self._scene_version = -1
        self._budget_calibrated = False
        self._style_version = -1
        self.input = InputState(last_time=time.perf_counter())
        self.click_to_query = False
        self.camera_index = 0
        self.export_path = str(default_export_path(state))
        self.screenshot_path = "screenshot.png"
        self.register_output = str(default_registered_path(state))
        self.register_topk = 40
        self.register_level = 1
        self.register_codebook = "none"
        self.register_codebook_path = ""
        self.query_text = ""
        self.embedding_path = ""
        self.segment_text = ""
        self.frame_seconds = 0.0

    def _create_window(self, width: int, height: int, title: str):
        preload_torch()
        if self.platform == "null":
            glfw.init_hint(glfw.PLATFORM, glfw.PLATFORM_NULL)
        if not glfw.init():
            raise RuntimeError("GLFW could not be initialised (no display? use --screenshot for offscreen rendering)")
        if self.platform == "null":
            glfw.window_hint(glfw.CONTEXT_CREATION_API, glfw.EGL_CONTEXT_API)
        glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 4)
        glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 3)
        glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
        glfw.window_hint(glfw.OPENGL_FORWARD_COMPAT, True)
        window = glfw.create_window(width, height, title, None, None)
        if not window:
            glfw.terminate()
            raise RuntimeError("could not open an OpenGL 4.3 window (the viewer needs compute shaders)")
        glfw.make_context_current(window)
        glfw.swap_interval(1)
        return window

    # ---------------------------------------------------------------- per frame

    def sync_scene(self) -> None:
        """Recreate GPU state when the scene changed, re-upload the style when it changed."""
        state = self.state
        if state.scene_version != self._scene_version:
            if self.renderer is not None:
                self.renderer.release()
                self.renderer = None
            if state.scene is not None:
                self.renderer = SplatRenderer(self.ctx, state.scene)
                fb_w, fb_h = glfw.get_framebuffer_size(self.window)
                self.view = ViewController.for_scene(state.scene.means, state.cameras, fb_w, fb_h)
            self._scene_version = state.scene_version
            self._budget_calibrated = False
            self._style_version = -1
            self._drawn_key = None
        if self.renderer is not None and state.style_version != self._style_version:
            self.renderer.set_style(state.style())
            self._style_version = state.style_version
            self._drawn_key = None

    def camera_changed(self) -> None:
        self.input.last_change = time.perf_counter()

    @property
    def moving(self) -> bool:
        return time.perf_counter() - self.input.last_change < MOVING_SECONDS

    def handle_input(self) -> None:
        io = imgui.get_io()
        now = time.perf_counter()
        dt, self.input.last_time = now - self.input.last_time, now
        if not io.want_capture_mouse:
            delta = io.mouse_delta
            if imgui.is_mouse_clicked(imgui.MouseButton_.left):
                self.input.drag_distance = 0.0
            if imgui.is_mouse_down(imgui.MouseButton_.left) and (delta.x or delta.y):
                self.input.drag_distance += abs(delta.x) + abs(delta.y)
                if io.key_shift:
                    self.view.pan(delta.x, delta.y)
                else:
                    self.view.rotate(delta.x, delta.y)
                self.camera_changed()
            if imgui.is_mouse_down(imgui.MouseButton_.right) and (delta.x or delta.y):
                self.view.pan(delta.x, delta.y)
                self.camera_changed()
            if io.mouse_wheel:
                self.view.zoom(io.mouse_wheel)
                self.camera_changed()
            if imgui.is_mouse_released(imgui.MouseButton_.left) and self.input.drag_distance < 3 and (self.click_to_query or io.key_ctrl):
                scale = self._framebuffer_scale()
                self.state.click_query(self.view.camera(), io.mouse_pos.x * scale[0], io.mouse_pos.y * scale[1])
        if not io.want_capture_keyboard and self.view.mode == "fly":
            step = FLY_SPEED * max(self.view.distance, 1e-3) * dt * (3.0 if io.key_shift else 1.0)
            move = np.zeros(3)
            for key, axis, sign in ((imgui.Key.w, 2, 1), (imgui.Key.s, 2, -1), (imgui.Key.d, 0, 1), (imgui.Key.a, 0, -1), (imgui.Key.e, 1, -1), (imgui.Key.q, 1, 1)):
                if imgui.is_key_down(key):
                    move[axis] += sign * step
            if move.any():
                self.view.move(move)
                self.camera_changed()

    def _framebuffer_scale(self) -> tuple[float, float]:
        win_w, win_h = glfw.get_window_size(self.window)
        fb_w, fb_h = glfw.get_framebuffer_size(self.window)
        return fb_w / max(win_w, 1), fb_h / max(win_h, 1)

    def draw_scene(self) -> None:
        """Splats are rendered on demand into an offscreen image (at MOVING_SCALE resolution and
        with the moving subsample while the camera moves), then stretched over the window; a
        frame where nothing changed only redraws the panels."""
        fb_w, fb_h = glfw.get_framebuffer_size(self.window)
        if (fb_w, fb_h) != (self.view.width, self.view.height) and fb_w > 0 and fb_h > 0:
            self.view.resize(fb_w, fb_h)
        if self.renderer is not None and fb_w > 0 and fb_h > 0:
            moving = self.moving
            scale = self.render_scale * (self.moving_scale if moving else 1.0)
            camera = camera_for_size(self.view.camera(), max(1, int(fb_w * scale)), max(1, int(fb_h * scale)))
            if self.renderer.update_order(camera):
                self._drawn_key = None
            key = (camera.R.tobytes(), camera.t.tobytes(), camera.fx, camera.width, camera.height, moving)
            if key != self._drawn_key:
                if self._target is None or (self._target.width, self._target.height) != (camera.width, camera.height):
                    if self._target is not None:
                        self._target.release()
                    self._target = OffscreenTarget(self.ctx, camera.width, camera.height)
                self._target.use()
                self.renderer.draw(camera, moving=moving)
                self._drawn_key = key
                if moving:
                    self.adapt_moving_budget(self.renderer.times.draw)
                elif not self._budget_calibrated:
                    self.renderer.moving_budget = calibrated_moving_budget(self.renderer.num, self.renderer.times.draw)
                    self._budget_calibrated = True
        self.ctx.screen.use()
        self.ctx.viewport = (0, 0, fb_w, fb_h)
        self.ctx.clear(0.0, 0.0, 0.0, 1.0)
        if self.renderer is not None and self._target is not None:
            if (self._target.width, self._target.height) == (fb_w, fb_h):
                self.ctx.copy_framebuffer(self.ctx.screen, self._target.fbo)  # a plain copy: ~100x cheaper
            else:
                self.blitter.draw(self._target.texture)

    def adapt_moving_budget(self, seconds: float) -> None:
        """Scale the moving subsample so that moving frames take about MOVING_FRAME_SECONDS."""
        r = self.renderer
        r.moving_budget = next_moving_budget(r.moving_budget, r.num, seconds)

    def frame(self) -> None:
        """One iteration of the main loop."""
        from viewer.panels import draw_panels

        start = time.perf_counter()
        glfw.poll_events()
        self.state.poll_registration()
        self.sync_scene()
        imgui.backends.opengl3_new_frame()
        imgui.backends.glfw_new_frame()
        imgui.new_frame()
        self.handle_input()
        draw_panels(self)
        imgui.render()
        self.sync_scene()
        self.draw_scene()
        imgui.backends.opengl3_render_draw_data(imgui.get_draw_data())
        glfw.swap_buffers(self.window)
        self.frame_seconds = time.perf_counter() - start

    def run(self, max_frames: int | None = None) -> None:
        frames = 0
        while not glfw.window_should_close(self.window) and (max_frames is None or frames < max_frames):
            self.frame()
            frames += 1

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.release()
        if self._target is not None:
            self._target.release()
        self.blitter.release()
        imgui.backends.opengl3_shutdown()
        imgui.backends.glfw_shutdown()
        imgui.destroy_context()
        glfw.destroy_window(self.window)
        glfw.terminate()

    # ---------------------------------------------------------------- actions used by the panels

    def snap_to_camera(self, index: int) -> None:
        cams = self.state.cameras
        if not 0 <= index < len(cams):
            self.state.error(f"no training camera {index} (there are {len(cams)})")
            return
        center = np.median(self.state.scene.means, axis=0) if self.state.scene is not None and self.state.num_gaussians else None
        self.view.snap_to(cams[index], center)
        self.camera_changed()

    def reset_view(self) -> None:
        self.view.reset()
        self.camera_changed()

    def screenshot(self, path: str | Path) -> None:
        """Save the splats of the current view (without the panels) as PNG."""
        if self.renderer is None:
            self.state.error("no scene to take a screenshot of")
            return
        try:
            image = render_offscreen(self.ctx, self.renderer, self.view.camera())
            save_png(image, path)
            self._drawn_key = None
        except Exception as exc:  # noqa: BLE001 - reported in the GUI
            self.state.error(f"screenshot to {path} failed: {exc}")
            return
        self.state.info(f"screenshot {image.shape[1]}x{image.shape[0]} saved to {path}")


def default_export_path(state: ViewerState) -> Path:
    base = state.scene_path if state.scene_path is not None else Path("scene.ply")
    return base.with_name(base.stem + "_selection.ply")


def default_registered_path(state: ViewerState) -> Path:
    base = state.scene_path if state.scene_path is not None else Path("scene.ply")
    return base.with_name(base.stem + "_registered.ply")
