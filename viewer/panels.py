"""imgui-bundle panels: drawing only. Every action calls `ViewerState` or `ViewerApp` methods."""

from __future__ import annotations

from typing import TYPE_CHECKING

from imgui_bundle import imgui

from viewer.state import DISPLAY_MODE_NAMES, DISPLAY_MODES, HIGHLIGHT_RGB

if TYPE_CHECKING:
    from viewer.app import ViewerApp

ERROR_COLOR = imgui.ImVec4(1.0, 0.45, 0.4, 1.0)
NOTE_COLOR = imgui.ImVec4(0.95, 0.8, 0.4, 1.0)
CODEBOOKS = ("none", "scene", "file")


def draw_panels(app: "ViewerApp") -> None:
    imgui.set_next_window_pos(imgui.ImVec2(8, 8), imgui.Cond_.first_use_ever.value)
    imgui.set_next_window_size(imgui.ImVec2(380, 640), imgui.Cond_.first_use_ever.value)
    imgui.begin("drsplat")
    if imgui.collapsing_header("Scene", imgui.TreeNodeFlags_.default_open.value):
        scene_panel(app)
    if imgui.collapsing_header("View", imgui.TreeNodeFlags_.default_open.value):
        view_panel(app)
    if imgui.collapsing_header("Query", imgui.TreeNodeFlags_.default_open.value):
        query_panel(app)
    if imgui.collapsing_header("Display", imgui.TreeNodeFlags_.default_open.value):
        display_panel(app)
    if imgui.collapsing_header("Registration"):
        registration_panel(app)
    if imgui.collapsing_header("Messages", imgui.TreeNodeFlags_.default_open.value):
        messages_panel(app)
    imgui.end()


def scene_panel(app: "ViewerApp") -> None:
    state = app.state
    if state.scene is None:
        imgui.text("no scene loaded")
        return
    imgui.text_wrapped(f"file: {state.scene_path}")
    imgui.text(f"Gaussians: {state.num_gaussians:,}   SH degree: {state.scene.sh_degree}")
    lo, hi = state.scene.bounding_box()
    imgui.text(f"bounds: [{lo[0]:.2f}, {lo[1]:.2f}, {lo[2]:.2f}] .. [{hi[0]:.2f}, {hi[1]:.2f}, {hi[2]:.2f}]")
    if state.field is not None:
        f = state.field
        imgui.text_wrapped(f"language field: {f.kind}, {f.dim}-D, {f.clip_model}, {int((f.weights > 0).sum()):,} assigned")
    else:
        imgui.text_colored(NOTE_COLOR, "no language field (see Registration)")
    imgui.text(f"training cameras: {len(state.cameras)}")
    r = app.renderer
    if r is not None:
        t = r.times
        imgui.text(f"frame {app.frame_seconds * 1000:.0f} ms: draw {t.draw * 1000:.0f}, sort {t.sort * 1000:.0f}, upload {t.upload * 1000:.0f} ms")
        imgui.text(f"drawn: {t.drawn:,}" + ("  (moving subsample)" if t.drawn < r.num else ""))


def view_panel(app: "ViewerApp") -> None:
    view = app.view
    if imgui.radio_button("orbit", view.mode == "orbit"):
        view.mode = "orbit"
    imgui.same_line()
    if imgui.radio_button("fly (WASD QE)", view.mode == "fly"):
        view.mode = "fly"
    imgui.same_line()
    if imgui.button("reset view"):
        app.reset_view()
    _, app.render_scale = imgui.slider_float("resolution", app.render_scale, 0.25, 1.0, "%.2fx")
    changed, fov = imgui.slider_float("fov", view.fov_y_deg, 20.0, 110.0, "%.0f deg")
    if changed:
        view.fov_y_deg = fov
        app.camera_changed()
    n = len(app.state.cameras)
    if n:
        changed, app.camera_index = imgui.slider_int("camera", app.camera_index, 0, n - 1)
        imgui.same_line()
        if imgui.button("snap") or changed:
            app.snap_to_camera(app.camera_index)
    _, app.screenshot_path = imgui.input_text("##shot", app.screenshot_path)
    imgui.same_line()
    if imgui.button("screenshot"):
        app.screenshot(app.screenshot_path)
    imgui.text_disabled("drag: rotate, shift/right drag: pan, wheel: zoom, ctrl+click: query")


def query_panel(app: "ViewerApp") -> None:
    state = app.state
    imgui.text_wrapped(state.encoder_status)
    entered, app.query_text = imgui.input_text_with_hint("##text", "text query", app.query_text, imgui.InputTextFlags_.enter_returns_true.value)
    imgui.same_line()
    if imgui.button("search") or entered:
        state.run_text_query(app.query_text)
    _, state.negatives = imgui.input_text_with_hint("negatives", "comma-separated phrases", state.negatives)
    _, app.click_to_query = imgui.checkbox("click to query (or ctrl+click)", app.click_to_query)
    _, app.embedding_path = imgui.input_text_with_hint("##emb", "Q.npy embedding file", app.embedding_path)
    imgui.same_line()
    if imgui.button("query file"):
        state.run_embedding_query(app.embedding_path)
    if state.oracle is not None:
        imgui.text_colored(NOTE_COLOR, "oracle labels (synthetic ground-truth vectors, not CLIP):")
        for i, name in enumerate(state.oracle.names):
            if i % 4:
                imgui.same_line()
            if imgui.small_button(f"{name}##oracle{i}"):
                state.run_oracle_query(i)
    q = state.query
    if q is None:
        return
    imgui.separator()
    imgui.text_wrapped(f"{q.source} query: {q.name} ({q.metric})")
    lo, hi = state.score_range()
    changed, value = imgui.slider_float("threshold", state.threshold, lo, hi, "%.3f")
    if changed:
        state.set_threshold(value)
    imgui.text(f"selected: {int(state.selection.sum()):,} of {state.num_gaussians:,}")
    _, app.export_path = imgui.input_text("##export", app.export_path)
    imgui.same_line()
    if imgui.button("export PLY"):
        state.export_selection(app.export_path)
    if imgui.button("clear query"):
        state.clear_query()


def display_panel(app: "ViewerApp") -> None:
    state = app.state
    for mode in DISPLAY_MODES:
        if imgui.radio_button(DISPLAY_MODE_NAMES[mode], state.mode == mode):
            state.set_mode(mode)
    if state.mode == "highlight":
        imgui.color_button("highlight", imgui.ImVec4(*HIGHLIGHT_RGB, 1.0))
        imgui.same_line()
        imgui.text("above threshold")
    _, app.segment_text = imgui.input_text_with_hint("##seg", "labels, comma-separated" + (" (empty: oracle labels)" if state.oracle else ""), app.segment_text)
    imgui.same_line()
    if imgui.button("segment"):
        names = [s.strip() for s in app.segment_text.split(",") if s.strip()]
        state.run_segmentation(names or None)
    if state.segmentation is not None:
        for name, color in zip(state.segment_names, state.segment_colors):
            imgui.color_button(f"##{name}", imgui.ImVec4(*[float(c) for c in color], 1.0))
            imgui.same_line()
            imgui.text(name)


def registration_panel(app: "ViewerApp") -> None:
    state = app.state
    imgui.text_wrapped(f"dataset: {state.source_dir or '(none: start with --source DIR)'}")
    imgui.text_wrapped(f"features: {state.features_dir or '(none: --features DIR)'}")
    _, app.register_output = imgui.input_text("output", app.register_output)
    _, app.register_topk = imgui.input_int("top-k", app.register_topk)
    app.register_topk = max(1, app.register_topk)
    _, app.register_level = imgui.slider_int("level", app.register_level, 0, 3)
    current = CODEBOOKS.index(app.register_codebook) if app.register_codebook in CODEBOOKS else 2
    changed, current = imgui.combo("codebook", current, ["none (exact fp16)", "scene (PQ trained here)", "faiss file"])
    if changed:
        app.register_codebook = CODEBOOKS[current]
    if app.register_codebook == "file":
        _, app.register_codebook_path = imgui.input_text_with_hint("##codebook", "pq_index.faiss", app.register_codebook_path)
    job = state.registration
    if job is not None and not job.finished:
        imgui.progress_bar(job.fraction, imgui.ImVec2(-1, 0), f"{job.done}/{job.total} views")
        if imgui.button("cancel"):
            state.cancel_registration()
    elif imgui.button("register"):
        codebook = app.register_codebook_path if app.register_codebook == "file" else app.register_codebook
        state.start_registration(app.register_output, app.register_topk, app.register_level, codebook)


def messages_panel(app: "ViewerApp") -> None:
    imgui.push_text_wrap_pos(0.0)
    for message in app.state.messages[-8:]:
        if message.level == "error":
            imgui.text_colored(ERROR_COLOR, message.text)
        elif message.level == "warning":
            imgui.text_colored(NOTE_COLOR, message.text)
        else:
            imgui.text(message.text)
    imgui.pop_text_wrap_pos()
