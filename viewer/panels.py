"""imgui-bundle panels. They show and edit the viewer's settings (`state.settings`,
viewer.settings.ViewerSettings: paths, choices, speeds), call `ViewerState` actions or the
host's (`PanelHost`: the window) for everything else, and own only widget state (text typed for
a one-shot action, which sections are open, the help overlay). The window talks to them through
`Panels`' public methods, never their fields.

Layout: one resizable, dockable window "drsplat" whose top part (query, threshold, export) is
always visible, the rest (scene, view, display, registration, messages) in collapsible sections
that scroll below it; a status line at the bottom of the window (the latest message, the
progressive frame's progress); a help overlay (F1 or ?) listing the hotkeys (HOTKEYS).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from imgui_bundle import imgui

from drsplat.lang import EXPORT_FORMAT_HELP, EXPORT_FORMATS
from viewer.camera import UP_AXES, ViewController
from viewer.settings import CODEBOOK_CHOICES, FLY_SPEED_RANGE, FOV_RANGE, RENDER_SCALE_RANGE, ROLL_RANGE, in_range
from viewer.state import ViewerState
from viewer.style import DISPLAY_MODE_NAMES, DISPLAY_MODES, HIGHLIGHT_RGB

ERROR_COLOR = imgui.ImVec4(1.0, 0.45, 0.4, 1.0)
NOTE_COLOR = imgui.ImVec4(0.95, 0.8, 0.4, 1.0)
CODEBOOK_NAMES = ["none (exact fp16)", "scene (PQ trained here)", "faiss file"]
EXPORT_NAMES = ["standard (.ply, .compressed.ply, .splat, .spz)", "drsplat PLY (+ field)"]
MAIN_WINDOW = "drsplat"
PANEL_WIDTH = 400
STATUS_HEIGHT = 26

# (keys, action) shown in the help overlay; viewer.app.ViewerApp.handle_hotkeys implements them
HOTKEYS = (
    ("F1 / ?", "show or hide this help"),
    ("/ or Ctrl+F", "focus the text query"),
    ("H", "toggle the highlight of the selection"),
    ("Ctrl+E", "export the selection (the format chosen in the panel)"),
    ("R", "reset the view"),
    ("N / P", "snap to the next / previous training camera"),
    ("F", "switch between orbit and fly"),
    ("Ctrl+O", "open a PLY (file dialog); or drop a PLY on the window"),
    ("Esc", "leave a text field (keys go back to the scene); close this help"),
    ("WASD, Q/E", "fly: move, down/up (Shift: faster); wheel: zoom (fly: speed)"),
    ("drag / right drag", "rotate / pan; Ctrl+click: query what is under the cursor"),
)


class PanelHost(Protocol):
    """What the panels need from the window (viewer.app.ViewerApp implements it)."""

    state: ViewerState
    view: ViewController

    def snap_to_camera(self, index: int) -> None: ...
    def reset_view(self) -> None: ...
    def camera_changed(self) -> None: ...
    def screenshot(self, path: str | Path) -> None: ...
    def open_scene(self, path: str | Path) -> bool: ...
    def open_file_dialog(self) -> None: ...
    def frame_stats(self) -> str: ...
    def still_progress(self) -> float | None: ...


# ---------------------------------------------------------------- panels


@dataclass
class QueryPanel:
    """Query text, Q.npy file, and the query and export settings."""

    text: str = ""
    embedding_path: str = ""
    focus_requested: bool = False

    def request_focus(self) -> None:
        self.focus_requested = True

    def draw_essentials(self, host: PanelHost) -> None:
        """Always visible: the text query, the threshold, the selection count and the export."""
        state = host.state
        if self.focus_requested:
            imgui.set_keyboard_focus_here()
            self.focus_requested = False
        self.text, submitted = submit_field("##text", "text query (/ to focus)", self.text, "search", -70)
        if submitted:
            state.run_text_query(self.text)
        if (problem := state.oracle_problem()) is not None:
            imgui.push_text_wrap_pos(0.0)
            imgui.text_colored(NOTE_COLOR, problem)
            imgui.pop_text_wrap_pos()
        elif state.oracle is not None:
            imgui.text_colored(NOTE_COLOR, "oracle labels (ground-truth vectors, not CLIP):")
            for i, name in enumerate(state.oracle.names):
                if i % 5:
                    imgui.same_line()
                if imgui.small_button(f"{name}##oracle{i}"):
                    state.run_oracle_query(i)
        q = state.query
        if q is None:
            imgui.push_text_wrap_pos(0.0)
            imgui.text_colored(NOTE_COLOR, state.next_step())  # the first screen says what to do next
            imgui.pop_text_wrap_pos()
            return
        imgui.text_wrapped(f"{q.source} query: {q.name} ({q.metric})")
        lo, hi = state.score_range()
        imgui.set_next_item_width(-70)
        changed, value = imgui.slider_float("threshold", state.threshold, lo, hi, "%.3f")
        if changed:
            state.set_threshold(value)
        imgui.text(state.selection_text())
        imgui.same_line()
        if imgui.small_button("clear query"):
            state.clear_query()
        export = state.settings.export
        imgui.set_next_item_width(-70)
        changed, current = imgui.combo("format", EXPORT_FORMATS.index(export.format), EXPORT_NAMES)
        if changed:
            export.format = EXPORT_FORMATS[current]
        if imgui.is_item_hovered():
            imgui.set_tooltip(EXPORT_FORMAT_HELP[export.format])
        imgui.set_next_item_width(-70)
        _, export.path = imgui.input_text("##export", export.path)
        imgui.same_line()
        if imgui.button("export"):
            state.export_selection()

    def draw_more(self, host: PanelHost) -> None:
        state = host.state
        settings = state.settings.query
        imgui.text_wrapped(state.encoder_status)
        _, settings.negatives = imgui.input_text_with_hint("negatives", "comma-separated phrases", settings.negatives)
        _, settings.click_to_query = imgui.checkbox("click to query (or ctrl+click)", settings.click_to_query)
        self.embedding_path, submitted = submit_field("##emb", "Q.npy embedding file", self.embedding_path, "query file", -90)
        if submitted:
            state.run_embedding_query(self.embedding_path)


@dataclass
class ScenePanel:
    open_path: str = ""

    def draw(self, host: PanelHost) -> None:
        state = host.state
        self.open_path, submitted = submit_field("##open", "scene.ply (or drop a scene file)", self.open_path, "open", -110)
        if submitted:
            host.open_scene(self.open_path)
        imgui.same_line()
        if imgui.button("..."):
            host.open_file_dialog()
        if state.scene is None:
            imgui.text("no scene loaded")
            return
        imgui.text_wrapped(f"file: {state.scene_path}")
        imgui.text(f"Gaussians: {state.num_gaussians:,}   SH degree: {state.scene.sh_degree}")
        lo, hi = state.scene.bounding_box()
        imgui.text(f"bounds: [{lo[0]:.2f}, {lo[1]:.2f}, {lo[2]:.2f}] .. [{hi[0]:.2f}, {hi[1]:.2f}, {hi[2]:.2f}]")
        if state.field is not None:
            f = state.field
            imgui.text_wrapped(f"language field: {f.kind}, {f.dim}-D, {f.clip_model}, {state.assigned_count:,} assigned")  # as queries and `drsplat info` count them
        else:
            imgui.text_colored(NOTE_COLOR, "language field unreadable (see the messages)" if state.field_problem else "no language field (see Registration)")
        imgui.text("training cameras: being checked against the scene..." if state.cameras_pending else f"training cameras: {len(state.cameras)}")
        imgui.text(host.frame_stats())


@dataclass
class ViewPanel:
    """Camera mode, up axis, roll, speeds, resolution, training cameras, screenshot."""

    def draw(self, host: PanelHost) -> None:
        view, settings = host.view, host.state.settings.view
        if imgui.radio_button("orbit", view.mode == "orbit"):
            view.mode = "orbit"
        imgui.same_line()
        if imgui.radio_button("fly (WASD QE)", view.mode == "fly"):
            view.mode = "fly"
        imgui.same_line()
        if imgui.button("reset view (R)"):
            host.reset_view()
        names = list(UP_AXES)
        changed, current = imgui.combo("up axis", names.index(settings.up_axis), names)
        if changed:
            settings.up_axis = names[current]
            view.set_up_axis(settings.up_axis, host.state.cameras)
            host.camera_changed()
        changed, roll = imgui.slider_float("roll", math.degrees(view.roll), *ROLL_RANGE, "%.0f deg")
        if changed:
            view.set_roll(math.radians(in_range(roll, *ROLL_RANGE, math.degrees(view.roll))))
            host.camera_changed()
        changed, speed = imgui.slider_float("fly speed", settings.fly_speed, *FLY_SPEED_RANGE, "%.2f", imgui.SliderFlags_.logarithmic.value)
        if changed:
            settings.fly_speed = in_range(speed, *FLY_SPEED_RANGE, settings.fly_speed)
        _, settings.render_scale = imgui.slider_float("resolution", settings.render_scale, *RENDER_SCALE_RANGE, "%.2fx")
        changed, fov = imgui.slider_float("fov", view.fov_y_deg, *FOV_RANGE, "%.0f deg")
        if changed:
            view.fov_y_deg = in_range(fov, *FOV_RANGE, view.fov_y_deg)
            host.camera_changed()
        n = len(host.state.cameras)
        if n:
            settings.camera_index = min(max(settings.camera_index, 0), n - 1)
            changed, typed = imgui.slider_int("camera (N/P)", settings.camera_index, 0, n - 1)
            # ctrl+click takes any integer: kept in range, as the float sliders are (-5 was kept, and N went to camera n - 4)
            settings.camera_index = int(in_range(typed, 0, n - 1, settings.camera_index))
            imgui.same_line()
            if imgui.button("snap") or changed:
                host.snap_to_camera(settings.camera_index)
            changed, settings.show_frusta = imgui.checkbox("training-camera frusta", settings.show_frusta)
            if changed:
                host.camera_changed()
        imgui.set_next_item_width(-90)
        _, settings.screenshot_path = imgui.input_text("##shot", settings.screenshot_path)
        imgui.same_line()
        if imgui.button("screenshot"):
            host.screenshot(settings.screenshot_path)


@dataclass
class DisplayPanel:
    segment_text: str = ""

    def draw(self, host: PanelHost) -> None:
        state = host.state
        for mode in DISPLAY_MODES:
            if imgui.radio_button(DISPLAY_MODE_NAMES[mode], state.mode == mode):
                state.set_mode(mode)
        if state.mode == "highlight":
            imgui.color_button("highlight", imgui.ImVec4(*HIGHLIGHT_RGB, 1.0))
            imgui.same_line()
            imgui.text("above threshold (H toggles)")
        self.segment_text, submitted = submit_field("##seg", "labels, comma-separated" + (" (empty: oracle labels)" if state.usable_oracle else ""), self.segment_text, "segment", -80)
        if submitted:
            state.run_segmentation(self.segment_text)
        if state.segmentation is not None:
            for name, color in zip(state.segment_names, state.segment_colors):
                imgui.color_button(f"##{name}", imgui.ImVec4(*[float(c) for c in color], 1.0))
                imgui.same_line()
                imgui.text(name)


@dataclass
class RegistrationPanel:
    """The registration settings, its progress and cancel button."""

    def draw(self, host: PanelHost) -> None:
        state, settings = host.state, host.state.settings.registration
        imgui.text_wrapped(f"dataset: {state.source_dir or '(none: start with --source DIR)'}")
        imgui.text_wrapped(f"features: {state.features_dir or '(none: --features DIR)'}")
        _, settings.output = imgui.input_text("output", settings.output)
        _, settings.topk = imgui.input_int("top-k", settings.topk)
        settings.topk = max(1, settings.topk)
        _, settings.level = imgui.slider_int("level", settings.level, 0, 3)
        changed, current = imgui.combo("codebook", CODEBOOK_CHOICES.index(settings.codebook), CODEBOOK_NAMES)
        if changed:
            settings.codebook = CODEBOOK_CHOICES[current]
        if settings.codebook == "file":
            _, settings.codebook_file = imgui.input_text_with_hint("##codebook", "pq_index.faiss", settings.codebook_file)
        job = state.registration
        if job is not None and not job.finished:
            imgui.progress_bar(job.fraction, imgui.ImVec2(-1, 0), f"{job.done}/{job.total} views")
            if imgui.button("cancel"):
                state.cancel_registration()
        elif imgui.button("register"):
            state.start_registration(settings.output, settings.topk, settings.level, settings.codebook_argument)


def submit_field(widget_id: str, hint: str, value: str, button: str, width: float) -> tuple[str, bool]:
    """A text field (`width` as imgui's set_next_item_width) and a button beside it: (the edited
    text, whether it was submitted by the button or by Enter in the field)."""
    imgui.set_next_item_width(width)
    entered, value = imgui.input_text_with_hint(widget_id, hint, value, imgui.InputTextFlags_.enter_returns_true.value)
    imgui.same_line()
    clicked = imgui.button(button)
    return value, bool(clicked or entered)


def draw_message(level: str, text: str) -> None:
    if level == "error":
        imgui.text_colored(ERROR_COLOR, text)
    elif level == "warning":
        imgui.text_colored(NOTE_COLOR, text)
    else:
        imgui.text(text)


def messages_panel(host: PanelHost) -> None:
    imgui.push_text_wrap_pos(0.0)
    for message in host.state.messages[-12:]:
        draw_message(message.level, message.text)
    imgui.pop_text_wrap_pos()


# ---------------------------------------------------------------- the window


@dataclass
class Panels:
    """All panels, their widget state, the status line and the help overlay (what the window
    calls: `draw`, `focus_query`, `toggle_help`, `close_help`)."""

    query: QueryPanel = field(default_factory=QueryPanel)
    scene: ScenePanel = field(default_factory=ScenePanel)
    view: ViewPanel = field(default_factory=ViewPanel)
    display: DisplayPanel = field(default_factory=DisplayPanel)
    registration: RegistrationPanel = field(default_factory=RegistrationPanel)
    show_help: bool = False
    open_next: dict[str, bool] = field(default_factory=dict)  # sections to open (True) / close on the next frame

    def _section(self, name: str, default_open: bool = False) -> bool:
        if name in self.open_next:
            imgui.set_next_item_open(self.open_next.pop(name))
        return imgui.collapsing_header(name, imgui.TreeNodeFlags_.default_open.value if default_open else 0)

    def focus_query(self) -> None:
        """Put the keyboard focus in the text query on the next frame."""
        self.query.request_focus()

    def toggle_help(self) -> None:
        self.show_help = not self.show_help

    def close_help(self) -> None:
        self.show_help = False

    def draw(self, host: PanelHost) -> None:
        viewport = imgui.get_main_viewport()
        imgui.dock_space_over_viewport(0, viewport, imgui.DockNodeFlags_.passthru_central_node.value)
        imgui.set_next_window_pos(imgui.ImVec2(viewport.work_pos.x + 8, viewport.work_pos.y + 8), imgui.Cond_.first_use_ever.value)
        height = max(200.0, viewport.work_size.y - 16)
        imgui.set_next_window_size(imgui.ImVec2(min(PANEL_WIDTH, viewport.work_size.x - 16), height), imgui.Cond_.first_use_ever.value)
        imgui.begin(MAIN_WINDOW)
        self.query.draw_essentials(host)
        imgui.separator()
        imgui.begin_child("sections", imgui.ImVec2(0, -self.status_height(host)))
        if self._section("Query options"):
            self.query.draw_more(host)
        if self._section("Scene", default_open=True):
            self.scene.draw(host)
        if self._section("View", default_open=True):
            self.view.draw(host)
        if self._section("Display", default_open=True):
            self.display.draw(host)
        if self._section("Registration"):
            self.registration.draw(host)
        if self._section("Messages"):
            messages_panel(host)
        imgui.end_child()
        self.draw_status(host)
        imgui.end()
        if self.show_help:
            self.draw_help()

    def status_height(self, host: PanelHost) -> float:
        """Pixels the status line needs at the bottom: its message wrapped to the panel's width (at least one line)."""
        if host.still_progress() is not None:
            return STATUS_HEIGHT
        text = self.status_message(host)[1]
        wrapped = imgui.calc_text_size(text, False, max(1.0, imgui.get_content_region_avail().x)).y
        return max(STATUS_HEIGHT, wrapped + STATUS_HEIGHT - imgui.get_text_line_height())

    @staticmethod
    def status_message(host: PanelHost) -> tuple[str, str]:
        """(level, text) of the status line: the latest message, else the help hint."""
        latest = host.state.messages.latest()
        if latest is None:
            return "info", "F1: help"
        return latest.level, status_text(latest.text)

    def draw_status(self, host: PanelHost) -> None:
        """The status line: the still frame's progress, else the latest message (F1: help), wrapped."""
        imgui.separator()
        progress = host.still_progress()
        if progress is not None:
            imgui.progress_bar(progress, imgui.ImVec2(-1, 0), f"drawing the still frame {100 * progress:.0f}%")
            return
        level, text = self.status_message(host)
        imgui.push_text_wrap_pos(0.0)  # wrapped at the panel's edge: an error is read in full, not cut at the width
        draw_message(level, text)
        imgui.pop_text_wrap_pos()

    def draw_help(self) -> None:
        viewport = imgui.get_main_viewport()
        center = imgui.ImVec2(viewport.work_pos.x + viewport.work_size.x / 2, viewport.work_pos.y + viewport.work_size.y / 2)
        imgui.set_next_window_pos(center, imgui.Cond_.always.value, imgui.ImVec2(0.5, 0.5))
        imgui.set_next_window_bg_alpha(0.92)
        flags = imgui.WindowFlags_.always_auto_resize.value | imgui.WindowFlags_.no_docking.value | imgui.WindowFlags_.no_saved_settings.value | imgui.WindowFlags_.no_collapse.value
        opened, self.show_help = imgui.begin("Hotkeys", self.show_help, flags)
        if opened:
            if imgui.begin_table("hotkeys", 2):
                for keys, action in HOTKEYS:
                    imgui.table_next_row()
                    imgui.table_next_column()
                    imgui.text_colored(NOTE_COLOR, keys)
                    imgui.table_next_column()
                    imgui.text(action)
                imgui.end_table()
        imgui.end()


STATUS_MAX_CHARS = 600  # a few wrapped lines at most; the Messages section keeps the full text


def status_text(text: str, limit: int = STATUS_MAX_CHARS) -> str:
    """The status line's text: the whole message (wrapped when drawn), lines joined, cut only past `limit`."""
    joined = " ".join(line.strip() for line in text.splitlines() if line.strip())
    return joined if len(joined) <= limit else joined[: limit - 1] + "…"
