"""Viewer, headless: EGL rendering against drsplat.raster, query highlights, export, screenshots.

The demo scene is the pre-registered one shipped in assets/demo (the tiny synthetic preset, PQ
field, unassigned Gaussians kept so rows match gt/labels.npy): what `python main.py` opens.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytestmark = pytest.mark.gl

moderngl = pytest.importorskip("moderngl")


@pytest.fixture(scope="module")
def gl_context():
    from viewer.renderer import create_offscreen_context

    try:
        ctx = create_offscreen_context()
    except Exception as exc:  # noqa: BLE001
        pytest.skip(f"no EGL OpenGL 4.3 context: {exc}")
    yield ctx
    ctx.release()


@pytest.fixture(scope="module")
def demo():
    from viewer.demo import demo_available, demo_dir

    assert demo_available(), "assets/demo is missing: rebuild it with `python -m viewer.demo`"
    return demo_dir() / "registered.ply", demo_dir()


@pytest.fixture
def state(demo):
    from viewer.state import ViewerState

    registered, dataset = demo
    st = ViewerState()
    assert st.load_scene(registered)
    assert st.load_source(dataset)
    return st


def _camera(state, index=0, width=256):
    from viewer.camera import camera_for_size

    return camera_for_size(state.cameras[index], width, None)


def _label_index(state, name):
    return state.oracle.names.index(name)


def _selected_weight(state, camera, selected):
    """[H, W] summed blending weight of the selected Gaussians per pixel (drsplat.raster, top 64)."""
    from drsplat.raster import rasterize

    out = rasterize(state.scene, camera, topk=64)
    ids = out.ids
    hit = (ids >= 0) & selected[np.maximum(ids, 0)]
    return np.where(hit, out.weights, 0.0).sum(axis=-1)


@pytest.mark.parametrize("index", [0, 4, 9])
def test_render_matches_the_cpu_rasterizer(state, gl_context, index):
    """Same camera, same scene: the GL splats and drsplat.raster's RGB agree pixel by pixel."""
    from drsplat.raster import rasterize
    from viewer.app import render_screenshot

    camera = _camera(state, index)
    image = render_screenshot(state, camera, ctx=gl_context).astype(np.float32) / 255
    reference = rasterize(state.scene, camera, topk=1, with_rgb=True).rgb
    assert image.shape == reference.shape
    diff = np.abs(image - reference)
    assert diff.mean() < 0.01, f"mean abs difference {diff.mean():.4f}"
    assert np.percentile(diff, 99) < 0.05
    assert image.std() > 0.05, "the image is flat: nothing was drawn"


def test_a_scene_in_map_coordinates_renders_as_the_cpu_rasterizer_does(state, gl_context):
    """The demo moved to UTM-like coordinates (5e5, 4e6, 100) with its camera: float32 positions on
    the GPU and in the sort have steps of 0.25-0.5 units there, and splats snapped to a grid and were
    sorted out of order (mean difference 0.060 from the CPU render; a viewer probe, 2026-11-30). The
    GPU now works relative to the scene's centre (`render_origin`)."""
    from drsplat.raster import rasterize
    from viewer.app import render_screenshot
    from viewer.renderer import render_origin
    from viewer.state import ViewerState

    shift = np.array([5e5, 4e6, 100.0])
    camera = _camera(state, 0)
    far = dataclasses.replace(state.scene, means=(np.asarray(state.scene.means, np.float64) + shift).astype(np.float32))
    far_camera = dataclasses.replace(camera, t=np.asarray(camera.t, np.float64) - np.asarray(camera.R, np.float64) @ shift)
    np.testing.assert_allclose(render_origin(far.means), shift, rtol=0, atol=20)
    assert not render_origin(state.scene.means).any()  # a scene about the origin is drawn from its own coordinates
    moved = ViewerState()
    moved.set_scene(far)
    image = render_screenshot(moved, far_camera, ctx=gl_context).astype(np.float32) / 255
    reference = rasterize(far, far_camera, topk=1, with_rgb=True).rgb
    diff = np.abs(image - reference)
    assert diff.mean() < 0.01 and np.percentile(diff, 99) < 0.05, (diff.mean(), np.percentile(diff, 99))
    assert image.std() > 0.05


@pytest.mark.parametrize("log_scale", [16.0, 20.0, 30.0])
def test_a_huge_splat_fills_the_view_evenly_as_the_cpu_rasterizer_draws_it(gl_context, log_scale):
    """A splat of log-scale 16 or more (radii of millions of pixels) drew straight-edged blocks: its
    σ-coordinates were interpolated across a triangle millions of times the screen; from ~19 on it
    vanished (its squared screen covariance passed float32's range: length() gave inf). The
    projection now works in units of the largest entry, and such a splat is drawn on a triangle
    covering the viewport (a viewer probe, round 20)."""
    from drsplat.cameras import Camera
    from drsplat.raster import rasterize
    from drsplat.scene import GaussianScene
    from viewer.camera import look_at
    from viewer.renderer import SplatRenderer, render_offscreen

    R, t = look_at(np.array([0.3, -4.0, 0.5]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    camera = Camera(R=R, t=t, fx=120, fy=110, cx=80, cy=48, width=160, height=96)
    quats = np.array([[1, 0, 0, 0], [0.9, 0.3, 0.2, 0.1]], np.float32)
    scene = GaussianScene(means=np.array([[0.4, 0.2, -0.3], [0.0, 3.0, 0.0]], np.float32), quats=quats / np.linalg.norm(quats, axis=1, keepdims=True),
                          log_scales=np.array([[np.log(0.3)] * 3, [log_scale, log_scale - 1.0, log_scale - 3.0]], np.float32),
                          opacity_logits=np.array([3.0, -1.0], np.float32), sh=np.array([[[1.5, 0.2, 0.2]], [[0.1, 0.1, 1.2]]], np.float32))
    renderer = SplatRenderer(gl_context, scene)
    image = render_offscreen(gl_context, renderer, camera).astype(np.float32) / 255
    reference = rasterize(scene, camera, topk=1, with_rgb=True).rgb
    diff = np.abs(image - reference)
    assert diff.mean() < 0.01 and np.percentile(diff, 99) < 0.05, (diff.mean(), np.percentile(diff, 99))
    assert reference[0, 0, 2] > 0.1 and abs(image[0, 0, 2] - reference[0, 0, 2]) < 0.02  # the huge splat's blue reaches the corners


def test_one_gaussian_lands_where_the_camera_projects_it(gl_context):
    """Pixel convention: a small Gaussian's blob is centred on Camera.project (pixel centres at +0.5)."""
    from drsplat.scene import GaussianScene
    from viewer.camera import look_at
    from viewer.renderer import SplatRenderer, render_offscreen
    from drsplat.cameras import Camera

    R, t = look_at(np.array([0.3, -4.0, 0.5]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    camera = Camera(R=R, t=t, fx=120, fy=110, cx=70, cy=45, width=160, height=96)
    point = np.array([[0.4, 0.2, -0.3]], np.float32)
    scene = GaussianScene(means=point, quats=np.array([[1, 0, 0, 0]], np.float32), log_scales=np.full((1, 3), np.log(0.03), np.float32),
                          opacity_logits=np.array([5.0], np.float32), sh=np.full((1, 1, 3), 1.5, np.float32))
    renderer = SplatRenderer(gl_context, scene)
    try:
        image = render_offscreen(gl_context, renderer, camera).astype(np.float64).sum(-1)
        empty = SplatRenderer(gl_context, scene.subset(np.zeros(1, bool)))
        blank = render_offscreen(gl_context, empty, camera)
        empty.release()
    finally:
        renderer.release()
    assert blank.max() == 0
    ys, xs = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    centroid = np.array([(image * xs).sum(), (image * ys).sum()]) / image.sum()
    uv, _ = camera.project(point.astype(np.float64))
    np.testing.assert_allclose(centroid + 0.5, uv[0], atol=0.15)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_view_dependent_colour_matches_the_rasterizer_for_every_sh_degree(gl_context, degree):
    """Strong random SH of each degree: the GL colours are drsplat.raster's (eval_sh per view)."""
    from drsplat.cameras import Camera
    from drsplat.raster import rasterize
    from drsplat.scene import GaussianScene
    from viewer.camera import look_at
    from viewer.renderer import SplatRenderer, render_offscreen

    rng = np.random.default_rng(degree)
    n = 400
    scene = GaussianScene(
        means=rng.uniform(-1, 1, (n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=np.log(rng.uniform(0.02, 0.12, (n, 3))).astype(np.float32),
        opacity_logits=rng.normal(0.5, 1.5, n).astype(np.float32),
        sh=(rng.normal(size=(n, (degree + 1) ** 2, 3)) * 0.6).astype(np.float32),
    )
    for eye in ([0.5, -3.5, 1.0], [-2.5, 2.0, -1.5]):
        R, t = look_at(np.array(eye), np.zeros(3), np.array([0.0, 0.0, 1.0]))
        camera = Camera(R=R, t=t, fx=150, fy=150, cx=96, cy=64, width=192, height=128)
        renderer = SplatRenderer(gl_context, scene)
        try:
            image = render_offscreen(gl_context, renderer, camera).astype(np.float32) / 255
        finally:
            renderer.release()
        reference = np.clip(rasterize(scene, camera, topk=1, with_rgb=True).rgb, 0, 1)
        diff = np.abs(image - reference)
        assert diff.mean() < 0.01 and np.percentile(diff, 99) < 0.1, (degree, eye, diff.mean())


def _gt_labels(state) -> np.ndarray:
    """Ground-truth labels of the loaded scene: row for row when it kept every Gaussian (the shipped
    demo), else (a pruned registration) matched to the original scene by position."""
    from drsplat.eval.metrics import match_gaussians
    from drsplat.scene import load_ply

    labels = np.load(state.source_dir / "gt" / "labels.npy")
    if labels.shape[0] == state.num_gaussians:
        return labels
    original = load_ply(state.source_dir / "scene.ply")
    return labels[match_gaussians(original.means, state.scene.means)]


def test_highlight_appears_where_the_selection_projects_and_nowhere_else(state, gl_context):
    from viewer.app import render_screenshot
    from viewer.state import HIGHLIGHT_MIX, HIGHLIGHT_RGB

    assert state.run_oracle_query(_label_index(state, "ball"))
    labels = _gt_labels(state)
    selected = state.selection
    assert selected.sum() > 20
    assert (labels[selected] == _label_index(state, "ball")).mean() > 0.9, "the oracle query must select the ball"

    coverage = [(_selected_weight(state, _camera(state, i, 64), selected) > 0.97).sum() for i in range(len(state.cameras))]
    for index in np.argsort(coverage)[::-1][:2]:
        camera = _camera(state, int(index))
        state.set_mode("color")
        plain = render_screenshot(state, camera, ctx=gl_context).astype(np.float32) / 255
        state.set_mode("highlight")
        lit = render_screenshot(state, camera, ctx=gl_context).astype(np.float32) / 255
        weight = _selected_weight(state, camera, selected)
        inside, outside = weight > 0.97, weight < 1e-3
        assert inside.sum() > 30, f"the ball must be visible from camera {index}: {weight.max()} {len(state.cameras)} {state.num_gaussians}"
        # inside: at least HIGHLIGHT_MIX of the colour is the highlight colour
        max_dist = (1 - 0.97 * HIGHLIGHT_MIX) + 0.03
        dist = np.abs(lit[inside] - np.array(HIGHLIGHT_RGB)).max(axis=-1)
        assert np.mean(dist < max_dist) > 0.95
        # outside: unchanged
        assert np.abs(lit[outside] - plain[outside]).max() < 2.5 / 255
        # and the highlight colour is nowhere outside
        far = np.abs(lit[outside] - np.array(HIGHLIGHT_RGB)).max(axis=-1)
        assert np.mean(far < max_dist) < 0.001


def test_selection_only_and_hide_selection_match_the_rasterizer_on_the_subsets(state, gl_context):
    """Selection only = the scene restricted to the selection; hide selection = its complement."""
    from drsplat.raster import rasterize
    from viewer.app import render_screenshot

    assert state.run_oracle_query(_label_index(state, "table"))
    selected = state.selection
    camera = _camera(state, 0)
    for mode, mask in (("selection", selected), ("hide_selection", ~selected)):
        state.set_mode(mode)
        image = render_screenshot(state, camera, ctx=gl_context).astype(np.float32) / 255
        reference = rasterize(state.scene, camera, topk=1, with_rgb=True, mask=mask).rgb
        assert np.abs(image - reference).mean() < 0.01, mode
    full = rasterize(state.scene, camera, topk=1, with_rgb=True).rgb
    assert np.abs(reference - full).mean() > 0.005, "hiding the table must change the picture"


def test_heatmap_and_segmentation_colour_every_labelled_gaussian(state, gl_context):
    from viewer.app import render_screenshot

    assert state.run_oracle_query(_label_index(state, "mug"))
    assert state.set_mode("heatmap")
    style = state.style()
    assert np.all(style[:, 3] > 0)
    assert state.run_segmentation(None)
    style = state.style()
    labels = state.segmentation.labels
    np.testing.assert_allclose(style[labels >= 0, :3], state.segment_colors[labels[labels >= 0]])
    image = render_screenshot(state, _camera(state, 0), ctx=gl_context)
    assert image.std() > 10


def test_click_query_picks_the_object_under_the_cursor(state):
    ball = _label_index(state, "ball")
    labels = _gt_labels(state)
    camera = _camera(state, 0)
    uv, _ = camera.project(state.scene.means[labels == ball])
    u, v = np.median(uv, axis=0)
    picked = state.pick(camera, u, v)
    assert picked.size > 0 and (labels[picked] == ball).mean() >= 0.5
    assert state.click_query(camera, u, v)
    assert state.query.source == "click"
    selected = state.selection
    assert (labels[selected] == ball).mean() > 0.8
    assert not state.click_query(camera, -500, -500)
    assert "outside" in state.messages[-1].text
    away = dataclasses.replace(camera, t=camera.t + np.array([0.0, 0.0, -1e4]))  # everything behind the camera
    assert not state.click_query(away, u, v)
    assert "nothing under the cursor" in state.messages[-1].text


def test_text_query_with_an_encoder_uses_relevancy_and_negatives(state):
    """A stand-in text encoder that returns the oracle vectors (the oracle embedding space)."""

    class OracleTextEncoder:
        model_id = state.field.clip_model

        def encode_text(self, phrases):
            table = dict(zip(state.oracle.names, state.oracle.embeddings))
            rng = np.random.default_rng(0)
            return np.stack([table.get(p, rng.normal(size=state.field.dim)) for p in phrases]).astype(np.float32)

    state.encoder = OracleTextEncoder()
    state.settings.query.negatives = "table"
    assert state.run_text_query("ball")
    assert state.query.metric == "relevancy"
    assert np.all((state.query.scores >= 0) & (state.query.scores <= 1))
    labels = _gt_labels(state)
    assert (labels[state.selection] == _label_index(state, "ball")).mean() > 0.8
    assert not state.run_text_query("   ")


def test_export_writes_a_ply_that_loads_back_with_the_selection(state, tmp_path):
    from drsplat.scene import load_ply

    assert state.export_selection(tmp_path / "none.ply") is None  # standard format by default
    assert "selection is empty" in state.messages[-1].text
    assert state.run_oracle_query(_label_index(state, "crate"))
    selected = state.selection
    count = state.export_selection(tmp_path / "crate.ply")
    assert count == int(selected.sum()) > 0
    back = load_ply(tmp_path / "crate.ply")
    assert back.num_gaussians == count
    np.testing.assert_allclose(back.means, state.scene.means[selected], rtol=0, atol=0)
    np.testing.assert_allclose(back.sh, state.scene.sh[selected], rtol=1e-6)


def test_bad_input_is_reported_not_raised(state, tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nend_header\n")
    assert not state.load_scene(bad)
    assert "bad.ply" in state.messages[-1].text
    assert state.scene is not None, "the old scene stays loaded"
    q = tmp_path / "q.npy"
    np.save(q, np.ones(7, np.float32))
    assert not state.run_embedding_query(q)
    assert "q.npy" in state.messages[-1].text
    assert not state.run_embedding_query(tmp_path / "missing.npy")
    assert not state.set_mode("nonsense")
    assert not state.run_oracle_query(99)


def test_embedding_query_from_file(state, tmp_path):
    q = tmp_path / "mug.npy"
    np.save(q, state.oracle.embeddings[_label_index(state, "mug")])
    assert state.run_embedding_query(q)
    labels = _gt_labels(state)
    assert (labels[state.selection] == _label_index(state, "mug")).mean() > 0.8


def test_weights_message_for_a_clip_field_without_weights(state, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HUB_CACHE", "/nonexistent-drsplat-test-cache")
    state.field = dataclasses.replace(state.field, clip_model="ViT-B-16/laion2b_s34b_b88k")
    state.start_text_encoder(background=False)
    assert state.encoder is None
    assert "--clip-checkpoint" in state.encoder_status
    assert not state.run_text_query("chair")
    assert "--clip-checkpoint" in state.messages[-1].text


def test_screenshot_command_writes_a_png_of_the_scene(demo, tmp_path, monkeypatch):
    from PIL import Image

    from viewer.launch import main

    registered, dataset = demo
    out = tmp_path / "shot.png"
    assert main([str(registered), "--source", str(dataset), "--screenshot", str(out), "--camera", "1", "--width", "160", "--oracle", "ball"]) == 0
    image = np.asarray(Image.open(out))
    assert image.shape == (120, 160, 3)
    assert image.std() > 10
    highlight = (image[..., 0] > 180) & (image[..., 2] > 150) & (image[..., 1] < 90)
    assert highlight.sum() > 5, "the queried ball must be highlighted"
    # the demo path: no SCENE opens the shipped demo at once (nothing generated)
    monkeypatch.setenv("DRSPLAT_CACHE", str(tmp_path / "cache"))
    out2 = tmp_path / "demo.png"
    assert main(["--screenshot", str(out2), "--width", "96", "--height", "64", "--oracle", "mug"]) == 0
    assert not (tmp_path / "cache").exists(), "the shipped demo needs no generation"
    assert np.asarray(Image.open(out2)).shape == (64, 96, 3)


def test_a_screenshot_is_written_in_the_format_its_name_says(demo, tmp_path, capsys):
    """Was: `--screenshot shot.jpg` wrote PNG data under a .jpg name (a viewer probe, 2026-11-30).
    Now the suffix picks the format, and one no format matches is refused before anything renders."""
    from PIL import Image

    from viewer.launch import main

    registered, dataset = demo
    png = None
    for name, fmt in (("s.png", "PNG"), ("s.JPG", "JPEG"), ("s.webp", "WEBP"), ("s.tif", "TIFF")):
        out = tmp_path / name
        assert main([str(registered), "--source", str(dataset), "--screenshot", str(out), "--camera", "1", "--width", "64"]) == 0
        with Image.open(out) as image:
            assert image.format == fmt and image.size == (64, 48), (name, image.format)
            pixels = np.asarray(image.convert("RGB"), np.float64)
        png = pixels if png is None else png
        assert np.abs(pixels - png).mean() < 3.0, name  # the same picture (JPEG and WebP: lossy)
    capsys.readouterr()
    assert main([str(registered), "--screenshot", str(tmp_path / "s.gif")]) == 1
    err = capsys.readouterr().err
    assert "s.gif: cannot write a .gif image" in err and err.count("ERROR") == 1 and "INFO" not in err, err  # before loading anything
    assert not (tmp_path / "s.gif").exists()


def test_a_home_view_screenshot_given_one_side_keeps_the_16_9_aspect(demo, tmp_path):
    """`--width 320` alone drew the home view 320x720 (the other side's default), a portrait strip; one side given now
    keeps the home view's 16:9, as a training camera keeps its own aspect."""
    from PIL import Image

    from viewer.launch import main

    registered, dataset = demo
    for flags, size in ((["--width", "96"], (96, 54)), (["--height", "90"], (160, 90)), (["--width", "40", "--height", "30"], (40, 30))):
        out = tmp_path / "home.png"
        assert main([str(registered), "--source", str(dataset), "--screenshot", str(out), *flags]) == 0
        with Image.open(out) as image:
            assert image.size == size, flags


def test_a_screenshot_threshold_that_selects_nothing_is_said(demo, tmp_path, capsys):
    """`--mode selection --threshold 1` wrote an all-black PNG, exit 0, while the log gave the count
    at the query's own threshold (a viewer probe, 2026-11-30): the count at --threshold is logged,
    and a selection of nothing is a warning."""
    from viewer.launch import main

    registered, dataset = demo
    assert main([str(registered), "--source", str(dataset), "--screenshot", str(tmp_path / "s.png"), "--width", "64",
                 "--oracle", "mug", "--mode", "selection", "--threshold", "1"]) == 0
    err = capsys.readouterr().err
    assert "--threshold 1: 0 Gaussians selected" in err
    assert "no Gaussian scores >= 1.0000: the screenshot shows nothing" in err


def test_a_screenshot_that_shows_nothing_says_why(demo, tmp_path, capsys):
    """Round 79b F2: `--mode hide_selection` with every Gaussian selected, and a camera with the whole scene behind it,
    wrote an all-black image, exit 0, without a word (an empty selection was already said)."""
    from viewer.launch import main

    from drsplat.scene import load_ply, save_ply

    from viewer.state import ViewerState

    registered, dataset = demo
    state = ViewerState()  # the Gaussians with a feature, every one of which a threshold of -1 selects
    assert state.load_scene(registered) and state.load_source(dataset) and state.run_oracle_query(0)
    state.set_threshold(-1.0)
    assigned = tmp_path / "assigned.ply"
    assert state.export_selection(assigned, "drsplat") == state.assigned_count
    assert main([str(assigned), "--source", str(dataset), "--screenshot", str(tmp_path / "a.png"), "--width", "64",
                 "--oracle", "mug", "--mode", "hide_selection", "--threshold", "-1"]) == 0
    err = capsys.readouterr().err
    assert "--mode hide_selection hides them all: the screenshot shows nothing" in err, err
    scene = load_ply(registered)
    from drsplat.cameras import load_cameras

    cam = load_cameras(dataset, require_images=False)[1]
    behind = dataclasses.replace(scene, means=(scene.means - 50.0 * np.asarray(cam.R, np.float32)[2]).astype(np.float32))  # moved behind camera 1
    save_ply(behind, tmp_path / "behind.ply")
    assert main([str(tmp_path / "behind.ply"), "--source", str(dataset), "--screenshot", str(tmp_path / "b.png"), "--width", "64",
                 "--camera", "1"]) == 0
    assert "the screenshot is all background (black): no Gaussian is drawn from this camera" in capsys.readouterr().err
    assert main([str(registered), "--source", str(dataset), "--screenshot", str(tmp_path / "c.png"), "--width", "64", "--camera", "1"]) == 0
    assert "all background" not in capsys.readouterr().err
    from drsplat.scene import SH_C0

    sh = np.zeros_like(scene.sh)
    sh[:, 0] = -0.5 / SH_C0  # every colour 0: a black picture of Gaussians in view is the scene's, not an empty camera
    save_ply(dataclasses.replace(scene, sh=sh), tmp_path / "black.ply")
    assert main([str(tmp_path / "black.ply"), "--source", str(dataset), "--screenshot", str(tmp_path / "d.png"), "--width", "64",
                 "--camera", "1"]) == 0
    assert "all background" not in capsys.readouterr().err
    from PIL import Image

    assert not np.asarray(Image.open(tmp_path / "d.png")).any()  # black indeed


def test_a_black_selection_screenshot_blames_the_selection_not_the_scene(demo, tmp_path, capsys):
    """Round 83a F4: a `--mode selection` picture of a selection off camera (one Gaussian, outside a 64-px home view)
    said the scene lay behind the camera or outside its view, though the scene was in view; and round 83a F5: the count
    read "1 Gaussians selected"."""
    from viewer.launch import main
    from viewer.state import ViewerState

    registered, dataset = demo
    state = ViewerState()
    assert state.load_scene(registered) and state.load_source(dataset) and state.run_oracle_query(0)
    best = float(np.nanmax(state.query.scores))
    assert main([str(registered), "--source", str(dataset), "--screenshot", str(tmp_path / "s.png"), "--width", "64",
                 "--oracle", state.oracle.names[0], "--threshold", repr(best - 1e-7), "--mode", "selection"]) == 0
    err = capsys.readouterr().err
    assert ": 1 Gaussian selected" in err, err
    assert "the selected Gaussians lie outside this camera's view" in err and "the scene lies behind" not in err, err


def test_a_scene_looks_the_same_at_any_scale_at_home_and_zoomed_in(gl_context, demo):
    """Round 71b F2: the renderer's near plane was 0.01 world units and the home radius at least 0.01, so the demo scene
    scaled by 1e-3 (an object 2 cm across, in metres) was cut away after 10 zoom steps and one scaled by 1e-6 was a dot at
    any zoom. The near plane is a share of the scene's radius below radius 1 (`camera.scene_near_plane`), and the
    orbit zoom stops at twice it: the same image at every scale, at home and zoomed in."""
    import dataclasses

    from drsplat.scene import load_ply
    from viewer.app import render_screenshot
    from viewer.camera import ViewController
    from viewer.state import ViewerState

    base = load_ply(demo[0])
    shares = {}
    for scale in (1.0, 1e-3, 1e-6):
        st = ViewerState()
        st.set_scene(dataclasses.replace(base, means=base.means * np.float32(scale), log_scales=base.log_scales + np.float32(np.log(scale))))
        for steps in (0, 10):
            view = ViewController.for_scene(st.scene.means, [], 96, 72, st.scene.log_scales)
            view.zoom(steps)
            image = render_screenshot(st, view.camera(), ctx=gl_context).astype(np.int64)
            shares[scale, steps] = float((np.abs(image - image[0, 0]).sum(-1) > 30).mean())
    for steps in (0, 10):
        assert shares[1.0, steps] > 0.3, shares
        for scale in (1e-3, 1e-6):
            assert abs(shares[scale, steps] - shares[1.0, steps]) < 0.02, shares


def test_a_small_scene_seen_from_its_training_camera_stays_in_view_when_zoomed_and_turned(gl_context, demo):
    """Round 72a F3: the home view from a training camera put the orbit target at least 1e-3 in front of it, 300 radii
    behind a scene scaled by 1e-6: one zoom step or drag lost the scene. The target is the scene centre's depth, at
    least twice the near plane."""
    import dataclasses

    from drsplat.cameras import load_cameras
    from drsplat.scene import load_ply
    from viewer.app import render_screenshot
    from viewer.camera import ViewController
    from viewer.state import ViewerState

    base, cameras = load_ply(demo[0]), load_cameras(demo[1])
    shares = {}
    for scale in (1.0, 1e-6):
        st = ViewerState()
        st.set_scene(dataclasses.replace(base, means=base.means * np.float32(scale), log_scales=base.log_scales + np.float32(np.log(scale))))
        scaled = [dataclasses.replace(c, t=np.asarray(c.t) * scale) for c in cameras]
        for action in ("home", "zoom", "turn"):
            view = ViewController.for_scene(st.scene.means, scaled, 96, 72, st.scene.log_scales)
            if action == "zoom":
                view.zoom(1)
            elif action == "turn":
                view.rotate(40, 0)
            image = render_screenshot(st, view.camera(), ctx=gl_context).astype(np.int64)
            shares[scale, action] = float((np.abs(image - image[0, 0]).sum(-1) > 30).mean())
    for action in ("home", "zoom", "turn"):
        assert shares[1.0, action] > 0.3 and abs(shares[1e-6, action] - shares[1.0, action]) < 0.02, shares


@pytest.mark.parametrize("count", [1, 50])
def test_home_view_of_one_gaussian_or_gaussians_at_one_point_shows_them(gl_context, tmp_path, count):
    """Was: a black screenshot: the home radius (spread of the means) was 1e-3, so the eye sat
    2.2e-3 from the Gaussians, inside them and in front of the renderer's near plane (0.01)."""
    from PIL import Image

    from drsplat.scene import GaussianScene, save_ply
    from viewer.launch import main

    scene = GaussianScene(means=np.full((count, 3), [0.4, -2.0, 1.0], np.float32), quats=np.tile(np.array([1, 0, 0, 0], np.float32), (count, 1)),
                          log_scales=np.full((count, 3), np.log(0.1), np.float32), opacity_logits=np.full(count, 5.0, np.float32),
                          sh=np.full((count, 1, 3), 1.5, np.float32))
    ply, out = tmp_path / "point.ply", tmp_path / "shot.png"
    save_ply(scene, ply)
    assert main([str(ply), "--screenshot", str(out), "--width", "64", "--height", "48"]) == 0
    image = np.asarray(Image.open(out), np.float64).sum(-1)
    assert image.max() > 100 and image[0].max() == 0 and image[-1].max() == 0  # seen whole: lit in the middle, dark at the edges
    ys, xs = np.nonzero(image > 0.5 * image.max())
    assert abs(xs.mean() - 31.5) < 4 and abs(ys.mean() - 23.5) < 4


def test_screenshot_command_errors_name_the_problem(demo, tmp_path, capsys):
    from viewer.launch import main

    registered, dataset = demo
    out = tmp_path / "x.png"
    assert main([str(registered), "--source", str(dataset), "--screenshot", str(out), "--camera", "99"]) == 1
    assert "out of range" in capsys.readouterr().err
    assert main([str(tmp_path / "missing.ply"), "--screenshot", str(out)]) == 1
    err = capsys.readouterr().err
    assert "missing.ply" in err and err.count("ERROR") == 1, "a start-up error is printed once"
    assert main([str(registered), "--source", str(dataset), "--screenshot", str(out), "--oracle", "unicorn"]) == 1
    assert "unicorn" in capsys.readouterr().err
    # round 53: the side that keeps a camera's aspect was never range-checked (a moderngl traceback)
    assert main([str(registered), "--source", str(dataset), "--screenshot", str(out), "--camera", "0", "--height", "16384"]) == 2
    err = capsys.readouterr().err
    assert "--height 16384 keeps camera 0's aspect, a 21845x16384 image, but a side must be 1 to 16384 pixels" in err, err
    assert err.count("ERROR") == 1 and "Traceback" not in err
    # round 85a F2: the home view's 16:9 side was not checked either ("cannot render a 16533x9300 image", exit 1)
    assert main([str(registered), "--screenshot", str(out), "--height", "9300"]) == 2
    err = capsys.readouterr().err
    assert "the home view: --height 9300 keeps the home view's 16:9 aspect, a 16533x9300 image, but a side must be 1 to 16384" in err, err
    assert err.count("ERROR") == 1 and "give --width and --height both" in err
    assert not out.exists()


def test_clip_flags_naming_no_usable_file_are_refused_at_start(demo, tmp_path, capsys):
    """Round 61a: a missing --clip-config or --clip-checkpoint started the viewer; its Query options later said the
    encoder could not be loaded, advising --clip-checkpoint whichever flag was at fault. Now one error at start."""
    from viewer.launch import main

    registered, dataset = demo
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{")
    for flags, words in ((["--clip-checkpoint", str(tmp_path / "nope.pt")], "nope.pt: CLIP checkpoint file does not exist (--clip-checkpoint)"),
                         (["--clip-checkpoint", str(tmp_path)], "is not a file (--clip-checkpoint)"),
                         (["--clip-config", str(tmp_path / "nope.json")], "nope.json: does not exist (--clip-config)"),
                         (["--clip-config", str(bad_json)], "bad.json")):
        assert main([str(registered), "--source", str(dataset), "--screenshot", str(tmp_path / "x.png"), "--query", "a mug", *flags]) == 1
        err = capsys.readouterr().err
        assert words in err and err.count("ERROR") == 1 and "Traceback" not in err, err


def test_screenshot_oracle_flags_refuse_a_field_of_clip_features(demo, tmp_path, capsys):
    """Round 61a: `--oracle` and `--mode segmentation` scored a field of CLIP features with the synthetic
    dataset's ground-truth vectors (another embedding space) and drew the answer. Now one error."""
    import dataclasses

    from drsplat.lang.plyformat import attach_field, read_field
    from drsplat.scene import load_ply, save_ply
    from viewer.launch import main

    registered, dataset = demo
    scene = load_ply(registered)
    field = dataclasses.replace(read_field(scene, registered), clip_model="ViT-B-16/laion2b_s34b_b88k")
    clip_ply = tmp_path / "clip.ply"
    save_ply(attach_field(scene, field, clip_ply), clip_ply)
    out = tmp_path / "x.png"
    for flags in (["--oracle", "mug"], ["--mode", "segmentation"], ["--mode", "segmentation", "--embedding", str(tmp_path / "q.npy")]):
        np.save(tmp_path / "q.npy", np.eye(field.dim, dtype=np.float32)[0])
        assert main([str(clip_ply), "--source", str(dataset), "--screenshot", str(out), *flags]) == 1
        err = capsys.readouterr().err
        assert "oracle labels are not offered" in err and "ViT-B-16" in err and err.count("ERROR") == 1, err
        assert "query" not in err.split("ERROR")[0]  # round 62b: refused before any query ran
    assert "drsplat segment --labels" in err
    assert not out.exists()


def test_a_window_wider_than_the_largest_image_is_drawn_smaller_and_stretched(gl_context):
    """Round 53: a window (or a screenshot) past the driver's largest image (GL_MAX_TEXTURE_SIZE, 16384 on llvmpipe)
    made moderngl fail inside the frame loop, which ended the viewer; the window now renders within it, and an
    offscreen image past it is one error naming the limit."""
    from drsplat.errors import DrsplatError
    from viewer.renderer import OffscreenTarget, fit_within, max_image_side

    side = max_image_side(gl_context)
    assert side >= 1024
    assert fit_within(side + 616, 100, side) == (side, int(100 * side / (side + 616)))
    assert fit_within(0, 5, side) == (1, 5) and fit_within(640, 480, side) == (640, 480)
    with pytest.raises(DrsplatError, match=rf"cannot render a {side + 1}x10 image: the OpenGL driver renders 1 to {side} pixels a side"):
        OffscreenTarget(gl_context, side + 1, 10)


def test_moving_subsample_draws_the_budget_and_resembles_the_full_frame(state, gl_context):
    from viewer.renderer import OffscreenTarget, SplatRenderer

    camera = _camera(state, 0)
    renderer = SplatRenderer(gl_context, state.scene)
    target = OffscreenTarget(gl_context, camera.width, camera.height)
    try:
        target.use()
        renderer.update_order(camera, wait=True)
        renderer.draw(camera)
        full = target.read_rgb().astype(np.float32)
        assert renderer.times.drawn == state.num_gaussians
        renderer.moving_budget = state.num_gaussians // 2
        renderer.draw(camera, moving=True)
        half = target.read_rgb().astype(np.float32)
        assert renderer.times.drawn == state.num_gaussians // 2
    finally:
        target.release()
        renderer.release()
    diff = np.abs(full - half).mean()
    assert 0.5 < diff < 40, diff


def test_moving_subsample_equals_a_full_render_of_the_same_splats(state, gl_context):
    """The compute pass projects only the subsample's splats (by id), strengthened by the thinning
    compensation, and the draw keeps their depth order."""
    from viewer.renderer import OffscreenTarget, SplatRenderer, thinning_compensation

    camera = _camera(state, 0)
    renderer = SplatRenderer(gl_context, state.scene)
    target = OffscreenTarget(gl_context, camera.width, camera.height)
    try:
        target.use()
        renderer.update_order(camera, wait=True)
        renderer.moving_budget = state.num_gaussians // 3
        renderer.draw(camera, moving=True)
        sub = target.read_rgb().astype(np.float32)
        ids = np.flatnonzero(renderer.rank < renderer.moving_budget)
    finally:
        target.release()
        renderer.release()
    assert ids.size == state.num_gaussians // 3
    # the thinning compensation, applied to the subset: opacity 1 - (1 - o)^c, covariance c·Σ
    c = thinning_compensation(state.num_gaussians, ids.size)
    assert c == pytest.approx(np.sqrt(3), rel=1e-3)
    subset = state.scene.subset(ids)
    opacity = 1 - (1 - np.minimum(subset.opacities(), 0.99)) ** c
    subset.opacity_logits = np.log(opacity / (1 - opacity)).astype(np.float32)
    subset.log_scales = (subset.log_scales + 0.5 * np.log(c)).astype(np.float32)
    alone = SplatRenderer(gl_context, subset)
    target = OffscreenTarget(gl_context, camera.width, camera.height)
    try:
        target.use()
        alone.update_order(camera, wait=True)
        alone.draw(camera)
        reference = target.read_rgb().astype(np.float32)
    finally:
        target.release()
        alone.release()
    assert reference.mean() > 5, "the subset is visible"
    assert np.abs(sub - reference).mean() < 0.3


def test_missing_gl_libraries_are_one_error_line(monkeypatch):
    """Round 91b F1: without libEGL (or libGL) glcontext raised a bare Exception, which `--screenshot` showed as a
    20-line traceback; it is a RuntimeError of one line naming the packages now (the launcher logs those, exit 1)."""
    from viewer.renderer import create_offscreen_context, gl_context

    monkeypatch.setenv("GLCONTEXT_LINUX_LIBEGL", "/nonexistent/drsplat-test/libEGL.so.1")
    with pytest.raises(RuntimeError) as raised:
        create_offscreen_context()
    text = str(raised.value)
    assert "\n" not in text and "/nonexistent/drsplat-test/libEGL.so.1" in text and "apt install libegl1 libgl1 libgl1-mesa-dri" in text, text

    def no_display():
        raise RuntimeError("no display")

    with pytest.raises(RuntimeError, match="^no display$"):  # a RuntimeError passes as it was
        gl_context(no_display, "a context")

    def too_old():  # moderngl's version check (round 93a F3: said to be missing libraries)
        raise moderngl.Error("requested OpenGL version 430, got version 410")

    with pytest.raises(RuntimeError, match=r"^cannot create a context: requested OpenGL version 430, got version 410 \(the viewer "
                                           r"needs OpenGL 4\.3\)$"):
        gl_context(too_old, "a context")
