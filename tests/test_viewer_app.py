"""Viewer window code on the GLFW null platform (no X server), and registration from the GUI state."""

from __future__ import annotations

import time

import numpy as np
import pytest

pytestmark = pytest.mark.gl


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from drsplat.synthetic import write_dataset

    return write_dataset(tmp_path_factory.mktemp("tiny"), "tiny", seed=1, show_progress=False)


@pytest.fixture(scope="module")
def registered(dataset, tmp_path_factory):
    from drsplat.cameras import load_cameras
    from drsplat.scene import load_ply
    from drsplat.pipeline import register_to_ply

    out = tmp_path_factory.mktemp("reg") / "registered.ply"
    register_to_ply(load_ply(dataset / "scene.ply"), load_cameras(dataset, require_images=False), dataset / "features", out, show_progress=False)
    return out


@pytest.fixture(scope="module")
def app(registered, dataset):
    """One window for the module: GLFW cannot always re-detect a context after glfwTerminate."""
    from viewer.app import ViewerApp
    from viewer.state import ViewerState

    state = ViewerState()
    assert state.load_scene(registered)
    assert state.load_source(dataset)
    try:
        viewer = ViewerApp(state, 320, 240, platform="null", layout_path=None)
    except Exception as exc:  # noqa: BLE001
        pytest.skip(f"GLFW null platform with an EGL context is unavailable: {exc}")
    yield viewer
    viewer.close()


def _screen(app):
    import glfw

    w, h = glfw.get_framebuffer_size(app.window)
    return np.frombuffer(app.ctx.screen.read(viewport=(0, 0, w, h), components=3, alignment=1), np.uint8).reshape(h, w, 3)[::-1]


def test_window_draws_the_scene_and_the_panels(app, tmp_path):
    app.run(max_frames=3)
    image = _screen(app)
    assert image.shape == (240, 320, 3)
    assert image.std() > 10
    assert app.renderer is not None and app.renderer.times.drawn == app.state.num_gaussians
    # the panels cover the top-left corner, the splats the rest; both change when a query lights the scene
    state = app.state
    assert state.run_oracle_query(state.oracle.names.index("floor"))
    app.run(max_frames=2)
    lit = _screen(app)
    assert np.abs(lit.astype(int) - image.astype(int)).sum(-1).astype(bool).mean() > 0.05
    app.screenshot(tmp_path / "shot.png")
    assert (tmp_path / "shot.png").stat().st_size > 1000
    assert "screenshot 320x240" in state.messages[-1].text


def test_camera_modes_snap_reset_and_resize(app):
    import glfw

    app.reset_view()
    app.run(max_frames=1)
    home = app.view.camera()
    app.view.rotate(40, 10)
    app.camera_changed()
    assert app.moving
    app.run(max_frames=1)
    assert not np.allclose(app.view.camera().R, home.R)
    app.snap_to_camera(3)
    np.testing.assert_allclose(app.view.camera().R, app.state.cameras[3].R, atol=1e-6)
    app.snap_to_camera(999)
    assert "no training camera 999" in app.state.messages[-1].text
    app.reset_view()
    np.testing.assert_allclose(app.view.camera().R, home.R, atol=1e-9)
    app.view.mode = "fly"  # keyboard polling for WASD runs every frame in fly mode
    app.run(max_frames=1)
    np.testing.assert_allclose(app.view.camera().R, home.R, atol=1e-9)
    app.view.mode = "orbit"
    glfw.set_window_size(app.window, 200, 150)
    app.run(max_frames=2)
    assert (app.view.width, app.view.height) == (200, 150)
    assert _screen(app).shape == (150, 200, 3)


def test_registration_runs_in_the_background_and_loads_its_result(dataset, tmp_path):
    from viewer.state import ViewerState

    state = ViewerState()
    assert state.load_scene(dataset / "scene.ply")
    assert state.field is None
    assert not state.run_oracle_query(0)
    assert "register it first" in state.messages[-1].text
    assert state.load_source(dataset)
    out = tmp_path / "reg.ply"
    assert state.start_registration(out, topk=20)
    job = state.registration
    deadline = time.time() + 120
    while not state.poll_registration():
        assert time.time() < deadline, "registration did not finish"
        time.sleep(0.05)
    assert job.error is None and job.done == job.total > 0
    assert out.is_file() and state.field is not None and state.scene_path == out
    assert state.cameras and state.oracle is not None, "cameras and oracle labels survive the reload"
    assert state.run_oracle_query(state.oracle.names.index("ball"))


def test_registration_can_be_cancelled_without_output(dataset, tmp_path):
    from viewer.state import ViewerState

    state = ViewerState()
    assert state.load_scene(dataset / "scene.ply")
    assert state.load_source(dataset)
    out = tmp_path / "cancelled.ply"
    assert state.start_registration(out)
    state.cancel_registration()
    deadline = time.time() + 120
    while not state.poll_registration():
        assert time.time() < deadline
        time.sleep(0.05)
    assert state.registration.error is not None and "cancel" in state.registration.error
    assert "registration did not finish" in state.messages[-1].text
    assert not out.exists()
    from drsplat.pipeline import checkpoint_path_for

    left = set(tmp_path.glob(".cancelled.ply*"))
    assert left <= {checkpoint_path_for(out)}, f"only the resumable checkpoint may stay, found {left}"


def test_registration_refuses_without_cameras(dataset, tmp_path):
    from viewer.state import ViewerState

    state = ViewerState()
    assert state.load_scene(dataset / "scene.ply")
    assert not state.start_registration(tmp_path / "x.ply")
    assert "training cameras" in state.messages[-1].text


def _draw_in_frame(app):
    from imgui_bundle import imgui

    imgui.backends.opengl3_new_frame()
    imgui.backends.glfw_new_frame()
    imgui.new_frame()
    app.panels.show_help = True
    app.panels.view.show_frusta = True
    app.panels.draw(app)
    app.draw_overlays()
    imgui.render()
    imgui.backends.opengl3_render_draw_data(imgui.get_draw_data())


def test_every_panel_draws_in_every_state(app, tmp_path):
    """Each panel's imgui calls run with a query, a segmentation, a running registration, errors."""
    from viewer.state import RegistrationJob

    state = app.state
    app.panels.expand |= {"Query options", "Registration", "Messages"}
    _draw_in_frame(app)
    assert state.run_oracle_query(0)
    for mode in ("highlight", "heatmap", "selection", "hide_selection"):
        assert state.set_mode(mode)
        _draw_in_frame(app)
    assert state.run_segmentation(None)
    app.panels.registration.codebook = "file"
    state.error("a long error message " * 10)
    state.registration = RegistrationJob(output=tmp_path / "r.ply", done=3, total=10)
    _draw_in_frame(app)
    state.registration.finished = state.registration.reported = True
    assert not state.start_registration(tmp_path / "r.ply", codebook="")
    assert "codebook file" in state.messages[-1].text
    app.panels.show_help = False
    app.panels.view.show_frusta = False
    app.run(max_frames=1)


def test_moving_budget_adapts_to_the_frame_time(app, monkeypatch):
    import viewer.app

    monkeypatch.setattr(viewer.app, "MIN_MOVING_SPLATS", 100)
    app.run(max_frames=1)
    r = app.renderer
    n = r.num
    r.moving_budget = n
    app.adapt_moving_budget(10.0)  # far too slow: halve
    assert r.moving_budget == n // 2
    for _ in range(30):
        app.adapt_moving_budget(10.0)
    assert r.moving_budget == 100, "never below the minimum"
    app.adapt_moving_budget(viewer.app.MOVING_FRAME_SECONDS)
    assert r.moving_budget == 100, "on target: unchanged"
    for _ in range(30):
        app.adapt_moving_budget(1e-3)
    assert r.moving_budget == n, "fast frames grow back to the whole scene"


def test_first_still_frame_calibrates_the_moving_budget(app, monkeypatch):
    import viewer.app

    monkeypatch.setattr(viewer.app, "MIN_MOVING_SPLATS", 100)
    num = 10_000
    assert viewer.app.calibrated_moving_budget(num, 4 * viewer.app.MOVING_FRAME_SECONDS) == num // 4
    assert viewer.app.calibrated_moving_budget(num, 0.5 * viewer.app.MOVING_FRAME_SECONDS) == num, "a fast scene is drawn whole"
    assert viewer.app.calibrated_moving_budget(num, 1e3) == 100, "never below the minimum"
    app.run(max_frames=1)
    r = app.renderer
    assert r.times.drawn == r.num, "the first frame is a full still frame"
    assert r.moving_budget == viewer.app.calibrated_moving_budget(r.num, r.times.draw)


def test_viewer_and_cli_registration_write_the_same_ply(dataset, tmp_path):
    """One pipeline: the viewer's registration and `drsplat register` give byte-identical files."""
    from drsplat.cli import main
    from drsplat.lang import read_field
    from drsplat.scene import load_ply
    from viewer.state import ViewerState

    cli_out, gui_out = tmp_path / "cli.ply", tmp_path / "gui.ply"
    assert main(["register", str(dataset / "scene.ply"), "--source", str(dataset), "--features", str(dataset / "features"),
                 "--out", str(cli_out), "--no-progress"]) == 0
    state = ViewerState()
    assert state.load_scene(dataset / "scene.ply") and state.load_source(dataset)
    assert state.start_registration(gui_out, background=False)
    assert state.registration.error is None
    assert cli_out.read_bytes() == gui_out.read_bytes()
    field = read_field(load_ply(cli_out), cli_out)
    assert field.clip_model == "oracle"
