"""The interactive viewer window (GLFW + moderngl + imgui-bundle) and the offscreen screenshot path.

imgui_bundle is imported before glfw so that pyGLFW binds the GLFW library imgui-bundle ships.
Window code runs on any GLFW platform, including the null platform used by the tests
(`DRSPLAT_VIEWER_PLATFORM=null`, EGL context).
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from imgui_bundle import imgui  # noqa: I001 - must precede glfw

import glfw
import moderngl

from drsplat.cameras import Camera
from drsplat.errors import OutputError
from drsplat.splat_formats import SCENE_SUFFIXES, spz_fractional_bits
from drsplat.utils import atomic_path, describe_os_error, fifo_reader
from viewer.camera import ViewController, camera_for_size, frustum_segments, project_segments
from viewer.panels import Panels
from viewer.paths import default_layout_path, image_format, typed_path
from viewer.renderer import (GL_REQUIRE, Blitter, gl_context, OffscreenTarget, SplatRenderer, create_offscreen_context, fit_within, max_image_side, preload_torch,
                             render_offscreen)
from viewer.settings import FLY_SPEED_RANGE, RENDER_SCALE_RANGE
from viewer.state import CAMERAS_BEING_CHECKED, ViewerState, resolved_folder

log = logging.getLogger(__name__)

MOVING_SECONDS = 0.25
MOVING_SCALE = 0.5  # render resolution factor while the camera moves
MOVING_FRAME_SECONDS = 0.1  # the moving subsample adapts towards this draw time
MIN_MOVING_SPLATS = 20_000
STILL_CHUNK_SECONDS = 0.05  # a still frame is drawn in chunks of about this much draw time per GUI frame
MIN_STILL_CHUNK = 5_000
IDLE_WAIT_SECONDS = 0.5  # nothing to do: sleep in glfw.wait_events_timeout at most this long
JOB_WAIT_SECONDS = 0.1  # a background job (registration, CLIP loading, sort) runs: poll it this often
ACTIVE_FRAMES = 3  # frames drawn after an input event (imgui settles hover / release states)
USE_LAYOUT_DEFAULT = object()
DIALOG_HELPERS = ("zenity", "kdialog", "matedialog", "qarma")  # what portable_file_dialogs runs on Linux


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


def still_chunk_target(frame_overhead: float) -> float:
    """Draw seconds per GUI frame for a progressive still frame: STILL_CHUNK_SECONDS, or twice the
    rest of a GUI frame (panels, copy, swap) when that is larger, so that drawing in chunks takes
    at most ~1.5x the time of one whole draw (total = D + (D / c) * overhead)."""
    return max(STILL_CHUNK_SECONDS, 2.0 * frame_overhead)


def next_still_chunk(chunk: int, num: int, seconds: float, target: float = STILL_CHUNK_SECONDS) -> int:
    """Splats per GUI frame of a progressive still frame, given that `chunk` took `seconds`:
    proportional towards `target` seconds (x0.5-x2 per step), within [MIN_STILL_CHUNK, num]."""
    factor = float(np.clip(target / max(seconds, 1e-4), 0.5, 2.0))
    return int(np.clip(chunk * factor, min(num, MIN_STILL_CHUNK), max(num, 1)))


def idle_timeout(animating: bool, events_pending: int, jobs_running: bool) -> float | None:
    """How long the main loop may sleep in glfw.wait_events_timeout before the next frame:
    None (do not wait: draw now) while the camera moves, a still frame is being drawn or input
    arrived in the last ACTIVE_FRAMES frames; JOB_WAIT_SECONDS while a background job runs (its
    progress shows); IDLE_WAIT_SECONDS otherwise (any input event wakes the loop at once)."""
    if animating or events_pending > 0:
        return None
    return JOB_WAIT_SECONDS if jobs_running else IDLE_WAIT_SECONDS


def save_image(image: np.ndarray, path: str | Path) -> Path:
    """Write [H, W, 3] uint8 in the format its name says (`image_format`: PNG, JPEG or WebP at quality 95,
    BMP or TIFF; PNG without a suffix), atomically (a FIFO or device: in place, atomic_path)."""
    import io

    from PIL import Image

    path = Path(path)
    fmt = image_format(path)
    data = io.BytesIO()  # encoded first: PIL seeks in the file it writes, which a FIFO cannot
    Image.fromarray(image).save(data, format=fmt, **({"quality": 95} if fmt in ("JPEG", "WEBP") else {}))
    with atomic_path(path) as tmp:
        tmp.write_bytes(data.getvalue())
    return path


def render_screenshot(state: ViewerState, camera: Camera, path: str | Path | None = None, ctx: moderngl.Context | None = None) -> np.ndarray:
    """Render one frame of the state's scene and style from `camera` on an EGL standalone context
    (no window, no X server); save it when `path` is given (`save_image`). Returns [H, W, 3] uint8."""
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
        save_image(image, path)
    return image


@dataclass
class InputState:
    last_change: float = 0.0  # the camera's
    last_style_change: float = 0.0  # the highlight's, on a scene too large to draw in one frame (ViewerApp.sync_scene)
    last_time: float = 0.0
    drag_distance: float = 0.0
    events: int = 0  # frames still to draw after input events (see idle_timeout)


@dataclass
class StillFrame:
    """A still frame drawn progressively: the view it is of, and how far the draw got."""

    key: tuple
    camera: Camera
    drawn: int = 0
    total: int = 0
    seconds: float = 0.0  # summed draw time

    @property
    def fraction(self) -> float:
        return self.drawn / self.total if self.total else 1.0


class ViewerApp:
    """The window: camera input, hotkeys, splat drawing (progressive when still), the panels
    (viewer.panels, called through `Panels`' methods only), file open / drop, and screenshots.
    What the user chose (speeds, resolution, paths...) is read from `state.settings`.

    layout_path: the imgui layout file (default: viewer.paths.default_layout_path(), in the
    per-user config dir); None keeps no layout file (tests).
    """

    def __init__(self, state: ViewerState, width: int = 1280, height: int = 720, title: str = "drsplat viewer", platform: str | None = None, layout_path=USE_LAYOUT_DEFAULT):
        self.state = state
        self.platform = platform or os.environ.get("DRSPLAT_VIEWER_PLATFORM")
        self.window = self._create_window(width, height, title)
        self.ctx = gl_context(lambda: moderngl.create_context(require=GL_REQUIRE), "the window's OpenGL context")
        self.input = InputState(last_time=time.perf_counter())
        self._dropped: list[str] = []
        self._install_event_callbacks()
        imgui.create_context()
        io = imgui.get_io()
        io.config_flags |= imgui.ConfigFlags_.nav_enable_keyboard.value | imgui.ConfigFlags_.docking_enable.value
        self.layout_path = default_layout_path() if layout_path is USE_LAYOUT_DEFAULT else layout_path
        self.layout_path = usable_layout_path(self.layout_path)
        io.set_ini_filename(None if self.layout_path is None else str(self.layout_path))
        imgui.backends.glfw_init_for_opengl(ctypes.cast(self.window, ctypes.c_void_p).value, True)
        imgui.backends.opengl3_init("#version 330")
        fb_w, fb_h = glfw.get_framebuffer_size(self.window)
        means = state.scene.means if state.scene is not None else np.zeros((0, 3), np.float32)
        log_scales = state.scene.log_scales if state.scene is not None else None
        self.view = ViewController.for_scene(means, state.cameras, fb_w, fb_h, log_scales)
        self.renderer: SplatRenderer | None = None
        self.blitter = Blitter(self.ctx)
        self.max_side = max_image_side(self.ctx)  # a window wider than the largest image is drawn smaller and stretched
        self._target: OffscreenTarget | None = None
        self._pending: OffscreenTarget | None = None
        self._still: StillFrame | None = None
        self._still_chunk = 0
        self._frame_overhead = 0.0  # seconds of a GUI frame besides drawing splats (EMA)
        self._drawn_key: tuple | None = None
        self.moving_scale = MOVING_SCALE
        self.progressive = True  # draw still frames in chunks (benches and tests turn it off)
        self.background_checks = True  # the training cameras' checks on a worker thread (tests that read them at once turn it off)
        self._scene_version = -1
        self._budget_calibrated = False
        self._style_version = -1
        self._style_digest: bytes | None = None  # of the style the renderer holds
        self._file_dialog = None
        self.panels = Panels()
        state.settings.reset_paths(state.scene_path)
        self.frame_seconds = 0.0
        self.frames = 0

    def _create_window(self, width: int, height: int, title: str):
        preload_torch()
        if self.platform == "null":
            glfw.init_hint(glfw.PLATFORM, glfw.PLATFORM_NULL)
        glfw.ERROR_REPORTING = "ignore"  # pyGLFW would print raw warnings; errors reach _glfw_error
        glfw.set_error_callback(_glfw_error)
        if not glfw.init():
            raise RuntimeError(no_display_message())
        if self.platform == "null":
            glfw.window_hint(glfw.CONTEXT_CREATION_API, glfw.EGL_CONTEXT_API)
        glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 4)
        glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 3)
        glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
        glfw.window_hint(glfw.OPENGL_FORWARD_COMPAT, True)
        window = glfw.create_window(width, height, title, None, None)
        if not window:
            glfw.terminate()
            raise RuntimeError("could not open an OpenGL 4.3 window (the viewer needs compute shaders); use --screenshot for offscreen rendering")
        glfw.make_context_current(window)
        glfw.swap_interval(1)
        return window

    def _install_event_callbacks(self) -> None:
        """Callbacks that wake the render loop (imgui's backend, installed after, chains to them)
        and collect dropped files."""

        def wake(*_args) -> None:
            self.input.events = ACTIVE_FRAMES

        for setter in (glfw.set_cursor_pos_callback, glfw.set_mouse_button_callback, glfw.set_scroll_callback, glfw.set_key_callback,
                       glfw.set_char_callback, glfw.set_window_size_callback, glfw.set_window_focus_callback, glfw.set_window_refresh_callback):
            setter(self.window, wake)

        def drop(_window, paths) -> None:
            self._dropped.extend(paths)
            wake()

        glfw.set_drop_callback(self.window, drop)

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
                if not (state.same_place and self.view is not None):  # a registration of the scene in view keeps the view (round 61a)
                    fb_w, fb_h = glfw.get_framebuffer_size(self.window)
                    self.view = ViewController.for_scene(state.scene.means, state.cameras, fb_w, fb_h, state.scene.log_scales)
                    state.settings.view.up_axis = "auto"
            state.same_place = False
            self._scene_version = state.scene_version
            self._budget_calibrated = False
            self._style_version = -1
            self._style_digest = None
            self._drawn_key = None
            self._still = None
        if self.renderer is not None and state.style_version != self._style_version:
            self._style_version = state.style_version
            style = state.style()
            digest = hashlib.blake2b(np.ascontiguousarray(style), digest_size=16).digest()
            if digest == self._style_digest:  # the mode clicked again, a threshold moved in colour mode: nothing to draw (round 84a F4)
                return
            self._style_digest = digest
            self.renderer.set_style(style)
            self._drawn_key = None
            self._still = None  # its projection holds the old style: a still frame in progress starts again
            if self._budget_calibrated and self.renderer.moving_budget < self.renderer.num:
                # A still frame of this scene takes several GUI frames, and a threshold dragged over it restarted the
                # frame at every step, so nothing new showed until the drag ended (round 83 / 79b F4): the new
                # highlight is drawn on the moving subsample first, as a camera move is.
                self.input.last_style_change = time.perf_counter()

    def camera_changed(self) -> None:
        self.input.last_change = time.perf_counter()

    @property
    def moving(self) -> bool:
        """The camera or, on a scene too large for one frame, the highlight changed in the last MOVING_SECONDS."""
        return time.perf_counter() - max(self.input.last_change, self.input.last_style_change) < MOVING_SECONDS

    def hold_still(self) -> None:
        """Draw still frames from now on, as if the last change were long ago (benches, tests, screenshots)."""
        self.input.last_change = self.input.last_style_change = 0.0

    def draw_until_still(self, seconds: float = 20.0) -> bool:
        """Draw GUI frames until the background sort, the moving frames of the last change and the still frame after
        them are done (benches, tests, screenshots); False when `seconds` pass first."""
        deadline = time.perf_counter() + seconds
        self.run(max_frames=1)
        while self.renderer is not None and (self.renderer.sorter.busy or self._still is not None or self.moving
                                             or self._drawn_key is None or self._drawn_key[-1]):  # [-1]: drawn moving
            if time.perf_counter() > deadline:
                return False
            time.sleep(0.01)
            self.run(max_frames=1)
        return True

    def handle_input(self) -> None:
        io = imgui.get_io()
        now = time.perf_counter()
        dt, self.input.last_time = now - self.input.last_time, now
        if not io.want_capture_mouse:
            self._handle_mouse(io)
        if keyboard_to_scene(io.want_text_input):
            self.handle_hotkeys(io)
            if self.view.mode == "fly":
                self._fly(io, dt)
        if imgui.is_key_pressed(imgui.Key.escape, False):
            self.release_focus()
            self.panels.close_help()

    def _handle_mouse(self, io) -> None:
        delta = io.mouse_delta
        if imgui.is_mouse_clicked(imgui.MouseButton_.left) or imgui.is_mouse_clicked(imgui.MouseButton_.right):
            self.input.drag_distance = 0.0
            self.release_focus()  # a click on the scene gives the keys back to the scene (WASD)
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
            if self.view.mode == "fly":
                settings = self.state.settings.view
                settings.fly_speed = float(np.clip(settings.fly_speed * 1.2 ** io.mouse_wheel, *FLY_SPEED_RANGE))
                self.state.info(f"fly speed {settings.fly_speed:.2f}")
            else:
                self.view.zoom(io.mouse_wheel)
                self.camera_changed()
        if imgui.is_mouse_released(imgui.MouseButton_.left) and self.input.drag_distance < 3 and (self.state.settings.query.click_to_query or io.key_ctrl):
            scale = self._framebuffer_scale()
            self.state.click_query(self.view.camera(), io.mouse_pos.x * scale[0], io.mouse_pos.y * scale[1])

    def _fly(self, io, dt: float) -> None:
        step = self.state.settings.view.fly_speed * max(self.view.distance, 1e-3) * dt * (3.0 if io.key_shift else 1.0)
        move = np.zeros(3)
        for key, axis, sign in ((imgui.Key.w, 2, 1), (imgui.Key.s, 2, -1), (imgui.Key.d, 0, 1), (imgui.Key.a, 0, -1), (imgui.Key.e, 1, -1), (imgui.Key.q, 1, 1)):
            if imgui.is_key_down(key) and not io.key_ctrl:
                move[axis] += sign * step
        if move.any():
            self.view.move(move)
            self.camera_changed()

    def handle_hotkeys(self, io) -> None:
        """The hotkeys of viewer.panels.HOTKEYS (only when imgui does not want text input)."""
        pressed = lambda key: imgui.is_key_pressed(key, False)  # noqa: E731
        ctrl = io.key_ctrl
        if pressed(imgui.Key.f1) or (pressed(imgui.Key.slash) and io.key_shift):
            self.panels.toggle_help()
        elif pressed(imgui.Key.slash) or (ctrl and pressed(imgui.Key.f)):
            self.panels.focus_query()
        elif ctrl and pressed(imgui.Key.e):
            self.state.export_selection()
        elif ctrl and pressed(imgui.Key.o):
            self.open_file_dialog()
        elif ctrl:
            return
        elif pressed(imgui.Key.h):
            self.toggle_highlight()
        elif pressed(imgui.Key.r):
            self.reset_view()
        elif pressed(imgui.Key.n):
            self.step_camera(1)
        elif pressed(imgui.Key.p):
            self.step_camera(-1)
        elif pressed(imgui.Key.f):
            self.view.mode = "orbit" if self.view.mode == "fly" else "fly"
            self.state.info(f"{self.view.mode} mode")

    def release_focus(self) -> None:
        """Take keyboard focus from imgui's widgets (the keys then move the camera)."""
        imgui.set_window_focus(None)

    def toggle_highlight(self) -> None:
        state = self.state
        if state.query is None:
            state.error("nothing to highlight: run a query first")
            return
        state.set_mode("color" if state.mode == "highlight" else "highlight")

    def _framebuffer_scale(self) -> tuple[float, float]:
        win_w, win_h = glfw.get_window_size(self.window)
        fb_w, fb_h = glfw.get_framebuffer_size(self.window)
        return fb_w / max(win_w, 1), fb_h / max(win_h, 1)

    def _target_for(self, target: OffscreenTarget | None, camera: Camera) -> OffscreenTarget:
        if target is None or (target.width, target.height) != (camera.width, camera.height):
            if target is not None:
                target.release()
            target = OffscreenTarget(self.ctx, camera.width, camera.height)
        return target

    def draw_scene(self) -> None:
        """Splats are rendered on demand into an offscreen image, then copied (or stretched) over
        the window; a frame where nothing changed only redraws the panels.

        Moving: MOVING_SCALE resolution and the moving subsample, one frame at once. Still: the
        exact full frame, drawn progressively (`progressive`) in chunks of about
        STILL_CHUNK_SECONDS per GUI frame into a second image, which replaces the shown one
        when complete; input is handled between chunks, and a camera change abandons it.
        """
        fb_w, fb_h = glfw.get_framebuffer_size(self.window)
        if (fb_w, fb_h) != (self.view.width, self.view.height) and fb_w > 0 and fb_h > 0:
            self.view.resize(fb_w, fb_h)
        if self.renderer is not None and fb_w > 0 and fb_h > 0:
            moving = self.moving
            scale = clamped_render_scale(self.state.settings.view.render_scale) * (self.moving_scale if moving else 1.0)
            camera = camera_for_size(self.view.camera(), *fit_within(int(fb_w * scale), int(fb_h * scale), self.max_side))
            if self.renderer.update_order(camera):
                self._drawn_key = None
                self._still = None
            key = (camera.R.tobytes(), camera.t.tobytes(), camera.fx, camera.width, camera.height, moving)
            if moving:
                self._still = None
                if key != self._drawn_key:
                    self._target = self._target_for(self._target, camera)
                    self._target.use()
                    self.renderer.draw(camera, moving=True)
                    self._drawn_key = key
                    self.adapt_moving_budget(self.renderer.times.draw)
            elif key != self._drawn_key:
                self._draw_still_chunk(key, camera)
        self.ctx.screen.use()
        self.ctx.viewport = (0, 0, fb_w, fb_h)
        self.ctx.clear(0.0, 0.0, 0.0, 1.0)
        if self.renderer is not None and self._target is not None:
            if (self._target.width, self._target.height) == (fb_w, fb_h):
                self.ctx.copy_framebuffer(self.ctx.screen, self._target.fbo)  # a plain copy: ~100x cheaper
            else:
                self.blitter.draw(self._target.texture)

    def _draw_still_chunk(self, key: tuple, camera: Camera) -> None:
        r = self.renderer
        still = self._still
        whole = not self.progressive or self._target is None or not self._budget_calibrated
        if still is None or still.key != key:
            self._pending = self._target_for(self._pending, camera)
            self._pending.use()
            self.ctx.clear(*r.background, 0.0)
            start = time.perf_counter()
            total = r.project(camera)
            r.ctx.finish()
            still = self._still = StillFrame(key, camera, total=total, seconds=time.perf_counter() - start)
            if not self._still_chunk:
                self._still_chunk = r.num
        self._pending.use()
        count = still.total - still.drawn if whole else min(self._still_chunk, still.total - still.drawn)
        start = time.perf_counter()
        r.draw_range(still.drawn, count)
        seconds = time.perf_counter() - start
        still.drawn += count
        still.seconds += seconds
        if count and not whole:
            self._still_chunk = next_still_chunk(count, r.num, seconds, still_chunk_target(self._frame_overhead))
        if still.drawn < still.total:
            return
        self._target, self._pending = self._pending, self._target
        self._drawn_key = key
        self._still = None
        r.times.draw, r.times.drawn = still.seconds, still.total
        if not self._budget_calibrated:
            r.moving_budget = calibrated_moving_budget(r.num, still.seconds)
            self._still_chunk = max(MIN_STILL_CHUNK, int(r.num * STILL_CHUNK_SECONDS / max(still.seconds, 1e-4)))
            self._budget_calibrated = True

    def still_progress(self) -> float | None:
        """The progressive still frame's completed fraction, None when none is being drawn."""
        return None if self._still is None else self._still.fraction

    def adapt_moving_budget(self, seconds: float) -> None:
        """Scale the moving subsample so that moving frames take about MOVING_FRAME_SECONDS."""
        r = self.renderer
        r.moving_budget = next_moving_budget(r.moving_budget, r.num, seconds)

    def draw_overlays(self) -> None:
        """Training-camera frusta (View panel), in imgui's background draw list (over the splats,
        under the panels)."""
        if not self.state.settings.view.show_frusta or not self.state.cameras or self.state.scene is None:
            return
        lo, hi = self.state.scene.bounding_box()
        depth = 0.03 * float(np.linalg.norm(hi - lo))
        camera = self.view.camera()
        segments = project_segments(camera, frustum_segments(self.state.cameras, depth))
        sx, sy = self._framebuffer_scale()
        draw = imgui.get_background_draw_list()
        color = imgui.get_color_u32(imgui.ImVec4(1.0, 0.85, 0.2, 0.9))
        for (u0, v0), (u1, v1) in segments:
            draw.add_line(imgui.ImVec2(u0 / sx, v0 / sy), imgui.ImVec2(u1 / sx, v1 / sy), color, 1.5)

    def frame(self) -> None:
        """One iteration of the main loop (events are polled or waited for by `run`)."""
        start = time.perf_counter()
        self.state.poll_registration()
        self._poll_camera_check()
        self._poll_file_inputs()
        self.sync_scene()
        imgui.backends.opengl3_new_frame()
        imgui.backends.glfw_new_frame()
        imgui.new_frame()
        self.handle_input()
        self.panels.draw(self)
        self.draw_overlays()
        imgui.render()
        self.sync_scene()
        scene_start = time.perf_counter()
        self.draw_scene()
        scene_seconds = time.perf_counter() - scene_start
        imgui.backends.opengl3_render_draw_data(imgui.get_draw_data())
        glfw.swap_buffers(self.window)
        self.frame_seconds = time.perf_counter() - start
        overhead = max(0.0, self.frame_seconds - scene_seconds)
        self._frame_overhead = overhead if self.frames == 0 else 0.8 * self._frame_overhead + 0.2 * overhead
        self.frames += 1
        self.input.events = max(0, self.input.events - 1)

    def wait_timeout(self) -> float | None:
        """idle_timeout of the current state."""
        r = self.renderer
        animating = self.moving or self._still is not None or (self.view.mode == "fly" and self._fly_keys_down())
        sort_pending = r is not None and r.sorter.busy
        job = self.state.registration
        jobs = ((job is not None and not job.finished) or sort_pending or self._file_dialog is not None or self.state.encoder_loading
                or self.state.cameras_pending)
        return idle_timeout(animating, self.input.events, jobs)

    def _fly_keys_down(self) -> bool:
        return any(glfw.get_key(self.window, k) == glfw.PRESS for k in (glfw.KEY_W, glfw.KEY_A, glfw.KEY_S, glfw.KEY_D, glfw.KEY_Q, glfw.KEY_E))

    def wait_for_events(self) -> float | None:
        """Poll (something animates) or sleep until an event or the timeout; returns the timeout used."""
        timeout = self.wait_timeout()
        if timeout is None:
            glfw.poll_events()
        else:
            glfw.wait_events_timeout(timeout)
        return timeout

    def run(self, max_frames: int | None = None) -> None:
        frames = 0
        while not glfw.window_should_close(self.window) and (max_frames is None or frames < max_frames):
            self.wait_for_events() if max_frames is None else glfw.poll_events()
            self.frame()
            frames += 1

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.release()
        for target in (self._target, self._pending):
            if target is not None:
                target.release()
        self.blitter.release()
        imgui.backends.opengl3_shutdown()
        imgui.backends.glfw_shutdown()
        imgui.destroy_context()
        glfw.destroy_window(self.window)
        glfw.terminate()

    # ---------------------------------------------------------------- actions used by the panels

    def frame_stats(self) -> str:
        r = self.renderer
        if r is None:
            return "no splats"
        t = r.times
        return f"frame {self.frame_seconds * 1000:.0f} ms, draw {t.draw * 1000:.0f} ms, {t.drawn:,} splats" + (" (moving subsample)" if t.drawn < r.num else "")

    def _poll_camera_check(self) -> None:
        """Cameras checked in the background arrived: an untouched view goes to its home with them (the first
        training camera, as when the cameras are there at once)."""
        state = self.state
        if state.poll_camera_check() and state.cameras and state.scene is not None and self.view.at_home:
            fb_w, fb_h = glfw.get_framebuffer_size(self.window)
            self.view = ViewController.for_scene(state.scene.means, state.cameras, fb_w, fb_h, state.scene.log_scales)
            self.camera_changed()

    def snap_to_camera(self, index: int) -> None:
        cams = self.state.cameras
        if self.state.cameras_pending:
            self.state.error(f"{CAMERAS_BEING_CHECKED}; snap to one when they are in")
            return
        if not 0 <= index < len(cams):
            self.state.error(f"no training camera {index} (there are {len(cams)})")
            return
        center = np.median(self.state.scene.means, axis=0) if self.state.scene is not None and self.state.num_gaussians else None
        self.view.snap_to(cams[index], center)
        self.state.settings.view.camera_index = index
        self.camera_changed()

    def step_camera(self, step: int) -> None:
        """Snap to the training camera `step` after the current one (N / P), wrapping around."""
        n = len(self.state.cameras)
        if self.state.cameras_pending:
            self.snap_to_camera(0)  # which says they are being checked
            return
        if n == 0:
            self.state.error("no training cameras to snap to (start with --source DATASET)")
            return
        self.snap_to_camera((self.state.settings.view.camera_index + step) % n)

    def reset_view(self) -> None:
        self.view.reset()
        self.camera_changed()

    def open_scene(self, path: str | Path) -> bool:
        """Open another PLY (Scene panel, file dialog, drop). The training cameras and oracle
        labels are kept when it lies in the same folder as the current scene or in the dataset's and is
        that scene, an export or registration of it, or the scene it came from (`derived_from`), else
        dropped, saying so;
        kept, they are read again for the new scene, whose frame and trainer's camera refinements
        (drsplat.frames) may not be the old one's."""
        if not str(path).strip():  # Path("") is ".", which would then be "not a file"
            self.state.error("type the path of a PLY to open")
            return False
        path = typed_path(str(path).strip())
        source = self.state.source_dir
        # the dataset's own folder and those of the scenes shown with it: its scene.ply is the scene the cameras were made for,
        # and the registered scene beside which it was given may be reopened (round 86d F2, 87b F3: dropped)
        folders = {resolved_folder(self.state.scene_path)} if self.state.scene_path is not None else set()
        if source is not None:
            folders |= {resolved_folder(Path(source) / "scene.ply"), *self.state.dataset_scene_folders}
        same_folder = resolved_folder(path) in folders  # no resolve() of a link loop here: load_scene names it (round 87b F1)
        previous = self.state.scene
        if not self.state.load_scene(path):
            return False
        if same_folder and previous is not None and not (derived_from(self.state.scene.means, previous.means) or derived_from(previous.means, self.state.scene.means)):
            if source is not None:  # round 87b F2: said with no dataset to drop
                self.state.info(f"{path.name} is not the previous scene, an export or registration of it, nor the scene it came from: "
                                "its training cameras and oracle labels were dropped (start with --source to give its own)")
            same_folder = False
        elif not same_folder and source is not None:  # round 86d F2: dropped without a word
            self.state.info(f"{path.name} lies in neither the previous scene's folder nor the dataset's ({source}): the dataset's "
                            "training cameras and oracle labels were dropped (start with --source to give its own)")
        if not same_folder:
            self.state.forget_source()
        elif self.state.source_dir is not None and not self.state.load_source(self.state.source_dir, background=self.background_checks):
            self.state.forget_source()
        self.state.start_text_encoder()
        self.state.settings.reset_paths(self.state.scene_path)
        return True

    def open_file_dialog(self) -> None:
        """A native file-open dialog (imgui-bundle's portable_file_dialogs), polled each frame."""
        from imgui_bundle import portable_file_dialogs as pfd

        if self._file_dialog is not None:
            return
        if sys.platform.startswith("linux") and not any(shutil.which(tool) for tool in DIALOG_HELPERS):
            self.state.error(f"no file dialog on this machine (portable_file_dialogs needs one of {', '.join(DIALOG_HELPERS)}); "
                             "type the path in the Scene section or drop the PLY on the window")
            return
        folder = str(self.state.scene_path.parent) if self.state.scene_path is not None else os.getcwd()
        try:
            patterns = " ".join(f"*{s}" for s in SCENE_SUFFIXES)
            self._file_dialog = pfd.open_file("Open a 3DGS scene", folder, [f"3DGS scenes ({patterns})", patterns, "All files", "*"])
        except Exception as exc:  # noqa: BLE001 - no dialog helper (zenity/kdialog) on this machine
            self.state.error(f"no file dialog available ({exc}); type the path in the Scene panel or drop the file on the window")

    def _poll_file_inputs(self) -> None:
        dropped, self._dropped = self._dropped, []
        plys = [p for p in dropped if p.lower().endswith(SCENE_SUFFIXES)]
        if dropped and not plys:
            self.state.error(f"dropped {len(dropped)} file(s), none a 3DGS scene ({', '.join(SCENE_SUFFIXES)}): drop one to open it")
        if plys:
            self.open_scene(plys[0])
            ignored = [Path(p).name for p in dropped if p != plys[0]]
            if ignored:  # one scene at a time: the rest were dropped without a word (round 61a)
                self.state.warning(f"opened {Path(plys[0]).name}; ignored {', '.join(ignored[:5])}{' ...' if len(ignored) > 5 else ''} "
                                   "(one scene at a time)")
        dialog = self._file_dialog
        if dialog is not None and dialog.ready(0):
            self._file_dialog = None
            chosen = dialog.result()
            if chosen:
                self.open_scene(chosen[0])

    def screenshot(self, path: str | Path) -> None:
        """Save the splats of the current view (without the panels) as an image (`save_image`); never over a file the
        viewer read (`ViewerState.guard_output`)."""
        if self.renderer is None:
            self.state.error("no scene to take a screenshot of")
            return
        if not self.state.guard_output(path, "the screenshot"):
            return
        path = typed_path(path)
        try:
            camera = self.view.camera()  # fitted within the driver's largest image, as the window draws it (round 79b F3)
            camera = camera_for_size(camera, *fit_within(camera.width, camera.height, self.max_side))
            image = render_offscreen(self.ctx, self.renderer, camera)
            with fifo_reader(path, wait=False):  # the window's thread: a FIFO nobody reads is refused, not waited on
                save_image(image, path)
            self._drawn_key = None
            self._still = None
        except Exception as exc:  # noqa: BLE001 - reported in the GUI
            self.state.error(f"screenshot to {path} failed: {exc}")
            return
        self.state.info(f"screenshot {image.shape[1]}x{image.shape[0]} saved to {path}")


def derived_from(means: np.ndarray, previous: np.ndarray, tolerance: float = 1e-3) -> bool:
    """Whether every Gaussian of `means` [M, 3] lies where one of `previous` [N, 3] does: an export or
    a registration of that scene (a subset of its rows), not another scene that happens to share its
    folder. Within `tolerance` x the scene's extent (a compressed PLY quantises positions relative to
    its chunks' boxes) or one .spz step, whichever is larger (.spz stores 24-bit fixed point, steps of
    2⁻¹² units, coarser past ±2048: a small or far-from-origin scene moves by more than its extent's
    1e-3; `splat_formats.spz_fractional_bits`)."""
    from scipy.spatial import cKDTree  # scipy's KD-tree only when a scene is opened beside another

    new, old = np.asarray(means, np.float64), np.asarray(previous, np.float64)
    new, old = new[np.isfinite(new).all(axis=1)], old[np.isfinite(old).all(axis=1)]
    if new.shape[0] == 0 or old.shape[0] == 0 or new.shape[0] > old.shape[0]:
        return new.shape[0] == 0
    extent = max(float(np.ptp(old, axis=0).max()), 1e-12)
    try:
        step = 2.0 ** -spz_fractional_bits(old)  # a rounding of half a step per axis: √3/2 steps at most
    except OutputError:  # beyond what .spz can store: no .spz export of it exists
        step = 0.0
    dist, _ = cKDTree(old).query(new, distance_upper_bound=max(tolerance * extent, step))
    return bool(np.isfinite(dist).all())


def clamped_render_scale(value: float) -> float:
    """The render scale within RENDER_SCALE_RANGE (1 when not a number): imgui's ctrl+click lets a
    slider take any typed value, and NaN ended the frame loop (int(NaN)); 4 rendered 16x the pixels."""
    lo, hi = RENDER_SCALE_RANGE
    return min(max(float(value), lo), hi) if math.isfinite(value) else 1.0


def usable_layout_path(path: str | Path | None) -> Path | None:
    """`path` (the imgui layout file) once its folder exists, or None, with a warning, when the
    folder cannot be made (a file in the way, a read-only parent) or `path` is there but not a
    regular file (imgui's fopen of a FIFO blocked the first frame for ever, round 53): the layout is
    a convenience and must not stop the viewer from starting."""
    if path is None:
        return None
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        log.warning("the panel layout will not be saved: %s (set DRSPLAT_CONFIG_DIR to a writable folder)", describe_os_error(exc))
        return None
    if os.path.lexists(path) and not path.is_file():
        log.warning("the panel layout is neither read nor saved: %s is not a regular file (set DRSPLAT_CONFIG_DIR to another folder)", path)
        return None
    return path


def keyboard_to_scene(want_text_input: bool) -> bool:
    """Keys move the camera and trigger hotkeys unless a text field is being edited (imgui's
    want_capture_keyboard is also true when a panel merely has focus, which blocked WASD)."""
    return not want_text_input


def no_display_message() -> str:
    return ("no display: the viewer window needs an X11/Wayland display (DISPLAY or WAYLAND_DISPLAY); "
            "on a headless machine use `python main.py SCENE --screenshot OUT.png` or run it under xvfb-run")


def _glfw_error(code: int, description: bytes | str) -> None:
    """GLFW errors go to the log once, as one line (not GLFW's raw warnings)."""
    text = description.decode(errors="replace") if isinstance(description, bytes) else str(description)
    log.debug("GLFW error %#x: %s", code, text)
