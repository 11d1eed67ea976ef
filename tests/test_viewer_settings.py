"""The viewer's settings have one owner (state.settings): the panels edit it, the window and the
state's actions read it, and the window never reaches into a panel's fields."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# what the panels may keep themselves: text typed for a one-shot action, open sections, the help overlay
WIDGET_STATE = {"text", "embedding_path", "focus_requested", "open_path", "segment_text", "show_help", "open_next"}
SUB_PANELS = {"query", "scene", "view", "display", "registration"}  # Panels' fields holding the panels


def _panels_uses(tree: ast.AST) -> list[ast.Attribute]:
    """Every `self.panels.<name>` in the tree."""
    return [node for node in ast.walk(tree)
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Attribute) and node.value.attr == "panels"
            and isinstance(node.value.value, ast.Name) and node.value.value.id == "self"]


def test_the_window_calls_panels_methods_and_never_reads_their_fields():
    from viewer.panels import Panels

    tree = ast.parse((ROOT / "viewer" / "app.py").read_text())
    called = {id(node.func) for node in ast.walk(tree) if isinstance(node, ast.Call)}
    fields = {f.name for f in dataclasses.fields(Panels)}
    uses = _panels_uses(tree)
    assert uses, "app.py draws the panels through self.panels"
    bad = [f"line {node.lineno}: self.panels.{node.attr}" for node in uses
           if node.attr in fields or node.attr.startswith("_") or id(node) not in called or not callable(getattr(Panels, node.attr, None))]
    assert bad == [], f"app.py must talk to the panels through Panels' public methods (settings: state.settings): {bad}"


def test_panels_keep_no_settings_of_their_own():
    from viewer import panels

    for cls in (panels.QueryPanel, panels.ScenePanel, panels.ViewPanel, panels.DisplayPanel, panels.RegistrationPanel, panels.Panels):
        own = {f.name for f in dataclasses.fields(cls)} - WIDGET_STATE - (SUB_PANELS if cls is panels.Panels else set())
        assert own == set(), f"{cls.__name__} keeps {own}: a setting belongs in viewer.settings.ViewerSettings"


def test_new_scene_paths_and_the_codebook_choice(tmp_path):
    from viewer.settings import ViewerSettings

    settings = ViewerSettings()
    settings.reset_paths(tmp_path / "garden.ply")
    assert Path(settings.export.path) == tmp_path / "garden_selection.ply"
    assert Path(settings.view.screenshot_path) == tmp_path / "garden_screenshot.png"
    assert Path(settings.registration.output) == tmp_path / "garden_registered.ply"
    settings.registration.codebook_file = "pq_index.faiss"
    assert settings.registration.codebook_argument == "none", "the file is used only when chosen"
    settings.registration.codebook = "file"
    assert settings.registration.codebook_argument == "pq_index.faiss"


def test_export_writes_what_the_settings_say(tmp_path):
    from drsplat.lang import read_field
    from drsplat.scene import load_ply
    from viewer.demo import demo_available, demo_dir
    from viewer.state import ViewerState

    if not demo_available():
        pytest.skip("the shipped demo scene (assets/demo) is absent")
    state = ViewerState()
    assert state.load_scene(demo_dir() / "registered.ply") and state.load_source(demo_dir())
    assert state.run_oracle_query(state.oracle.names.index("mug"))
    state.settings.export.path, state.settings.export.format = str(tmp_path / "mug.ply"), "drsplat"
    count = state.export_selection()
    out = tmp_path / "mug.ply"
    assert count == int(state.selection.sum()) > 0
    assert load_ply(out).num_gaussians == count and read_field(load_ply(out), out) is not None, "the drsplat format carries the field"
    state.settings.export.path, state.settings.export.format = str(tmp_path / "plain.ply"), "standard"
    assert state.export_selection() == count
    assert read_field(load_ply(tmp_path / "plain.ply"), tmp_path / "plain.ply") is None, "the standard format has no field"
