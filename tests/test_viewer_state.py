"""The viewer's state across actions (no window): what a later action may not undo or overwrite.

Found by a probe of the viewer on 2026-11-29 (docs/hostile.md, "The viewer, round 5"): the GUI's
registration, export and screenshot wrote over the dataset's files and the opened PLY, a
registration that finished loaded over a scene opened after it started, and a new scene kept the
previous one's display mode and CLIP encoder.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import tiny_registered


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory):
    return tiny_registered(tmp_path_factory.mktemp("viewer-state"), seed=2)


@pytest.fixture
def state(scene_files, tmp_path):
    """A state on copies (a test that fails must not damage the module's files)."""
    from viewer.state import ViewerState

    dataset, registered = scene_files
    ds = Path(shutil.copytree(dataset, tmp_path / "ds"))
    reg = Path(shutil.copy(registered, tmp_path / "registered.ply"))
    for book in registered.parent.glob("*.faiss"):  # an exact field has none; a PQ one its codebook beside the PLY
        shutil.copy(book, tmp_path)
    s = ViewerState()
    assert s.load_scene(reg)
    assert s.load_source(ds)
    return s


def digests(folder: Path) -> dict[Path, str]:
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_export_and_screenshot_never_write_over_what_the_viewer_read(state):
    ds = state.source_dir
    before = digests(ds) | digests(state.scene_path.parent)
    assert state.run_oracle_query(0)
    state.set_threshold(-1.0)  # every Gaussian selected: the export would go ahead
    image = next((ds / "images").iterdir())
    feature = next((ds / "features").glob("*_f.npy"))
    for target in (ds / "transforms.json", ds / "text_embeddings.npy", ds / "gt" / "label_names.json", image, feature, state.scene_path,
                   ds / "features" / "new_f.npy"):
        assert state.export_selection(target, "standard") is None, target
        assert "cannot write" in state.messages[-1].text, state.messages[-1].text
        assert not state.guard_output(target, "the screenshot")
    assert not state.guard_output("", "the screenshot") and "type the path of the screenshot" in state.messages[-1].text
    assert digests(ds) | digests(state.scene_path.parent) == before


def test_an_export_over_the_output_of_the_registration_running_is_refused(state, tmp_path):
    """An export to the file a running registration writes was accepted ("exported 78 Gaussians")
    and then replaced when the registration ended (a viewer probe, 2026-11-30)."""
    from viewer.registration import RegistrationJob

    assert state.run_oracle_query(0)
    state.set_threshold(-1.0)
    out = tmp_path / "race" / "out.ply"
    state.registration = RegistrationJob(out)  # running: not finished
    assert state.export_selection(out, "standard") is None
    assert "cannot write" in state.messages[-1].text and "registration running" in state.messages[-1].text, state.messages[-1].text
    assert not out.exists()
    state.registration.finished = True  # once it has ended, the file is the user's to replace
    assert state.export_selection(out, "standard") is not None and out.exists()


def test_gui_registration_refuses_its_inputs_as_output(state, tmp_path):
    ds = state.source_dir
    before = digests(ds) | digests(state.scene_path.parent)
    for target in (state.scene_path, ds / "transforms.json", next((ds / "images").iterdir())):
        assert not state.start_registration(target, background=False), target
        assert "same file as the input" in state.messages[-1].text, state.messages[-1].text
    assert state.registration is None
    assert digests(ds) | digests(state.scene_path.parent) == before


def test_a_registration_that_ends_after_another_scene_opened_does_not_replace_it(state, tmp_path):
    other = Path(shutil.copy(state.scene_path, tmp_path / "other.ply"))
    for book in state.scene_path.parent.glob("registered.codebook.faiss"):
        shutil.copy(book, tmp_path / "other.codebook.faiss")
    assert state.start_registration(tmp_path / "out.ply", background=True)
    assert state.load_scene(other)
    assert state.run_oracle_query(1)
    deadline = time.time() + 120
    while not state.registration.finished and time.time() < deadline:
        time.sleep(0.05)
    assert state.registration.finished and state.registration.error is None, state.registration.error
    assert state.poll_registration()
    assert state.scene_path == other and state.query is not None  # the scene opened later stays, with its query
    assert "another scene is open now" in state.messages[-1].text and (tmp_path / "out.ply").is_file()


def test_a_new_scene_starts_without_the_last_ones_mode_segmentation_or_encoder(state):
    assert state.run_oracle_query(0) and state.set_mode("hide_selection")
    state.encoder = object()  # a CLIP encoder of the previous scene's model
    assert state.load_scene(state.scene_path)
    assert state.mode == "color" and state.query is None and state.encoder is None
    assert state.segment_names == [] and state.segment_colors.shape == (0, 3)
    assert state.export_selection(state.scene_path.with_name("all.ply"), "standard") is None  # nothing selected, nothing shown hidden
    assert not state.set_mode("hide_selection") and "run a query first" in state.messages[-1].text
    assert state.run_segmentation(None) and state.mode == "segmentation"
    assert state.load_scene(state.scene_path) and state.mode == "color" and state.segmentation is None


def test_an_encoder_that_loads_for_a_scene_no_longer_open_is_dropped(state, monkeypatch):
    import viewer.state as vs

    class FakeEncoder:
        model_id = "ViT-B-16/laion2b_s34b_b88k"

        def __init__(self, *args, **kwargs):
            state.load_scene(state.scene_path)  # the user opens another scene while the weights load

    monkeypatch.setattr(vs, "ClipEncoder", FakeEncoder)
    state._load_encoder(state.scene_version)
    assert state.encoder is None


@pytest.mark.parametrize("names, words", [(["ball", "mug", "ball"], 'repeats the name "ball"'), (["ball", " "], "empty name")])
def test_typed_segmentation_labels_are_checked_like_the_clis(state, names, words):
    assert not state.run_segmentation(names)
    assert words in state.messages[-1].text, state.messages[-1].text


def test_a_config_folder_that_cannot_be_made_only_loses_the_layout(tmp_path, caplog):
    from viewer.app import usable_layout_path

    blocker = tmp_path / "cfg"
    blocker.write_text("a file where the config folder should be")
    with caplog.at_level(logging.WARNING):
        assert usable_layout_path(blocker / "imgui.ini") is None
    assert "the panel layout will not be saved" in caplog.text
    assert usable_layout_path(tmp_path / "new" / "imgui.ini") == tmp_path / "new" / "imgui.ini" and (tmp_path / "new").is_dir()
    assert usable_layout_path(None) is None
    np.testing.assert_equal(blocker.read_text(), "a file where the config folder should be")


@pytest.mark.parametrize("value, expected", [(float("nan"), 1.0), (4.0, 1.0), (0.0, 0.25), (0.5, 0.5), (float("inf"), 1.0)])
def test_render_scale_is_kept_in_its_range(value, expected):
    """A typed render scale of NaN ended the frame loop (int(NaN)); 4 rendered 16x the window's pixels."""
    from viewer.app import clamped_render_scale

    assert clamped_render_scale(value) == expected


def test_an_export_into_a_read_only_folder_names_the_export_not_its_temp_file(tmp_path, monkeypatch):
    """The error named `.a.ply.<pid>.<random>.tmp`, a file the user never asked for."""
    import errno
    import tempfile

    from drsplat.utils import atomic_path

    def refuse(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(tmp_path / ".a.ply.123.xyz.tmp"))

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    with pytest.raises(OSError) as info:
        with atomic_path(tmp_path / "a.ply"):
            pass
    assert info.value.filename == str(tmp_path / "a.ply") and info.value.errno == errno.EACCES



def test_what_a_load_warns_of_is_shown_and_a_field_with_nothing_assigned_is_said(tmp_path):
    """A load's warnings (rows dropped for NaN, codes that no longer match their codebook) reached
    only the terminal, and a query of a field with no assigned Gaussian said "0 Gaussians at
    threshold 0.000" where `drsplat query` refuses it (a viewer probe, 2026-11-30)."""
    from drsplat.lang import attach_field, build_field
    from drsplat.scene import save_ply
    from tests.test_index import tiny_scene
    from viewer.state import ViewerState

    scene = tiny_scene(6)
    field = build_field(np.eye(6, 8, dtype=np.float32), np.zeros(6, np.float32), "none", clip_model="oracle")
    path = tmp_path / "unassigned.ply"
    save_ply(attach_field(scene, field, path), path)
    s = ViewerState()
    assert s.load_scene(path)
    np.save(tmp_path / "q.npy", np.eye(1, 8, dtype=np.float32)[0])
    assert not s.run_embedding_query(tmp_path / "q.npy")
    assert "none of this scene's 6 Gaussians has a language feature" in s.messages[-1].text
    broken = tmp_path / "nan.ply"
    means = np.asarray(scene.means, np.float32).copy()
    means[2] = np.nan
    save_ply(dataclasses.replace(scene, means=means), broken)
    s = ViewerState()
    assert s.load_scene(broken)
    assert any(m.level == "warning" and "NaN" in m.text for m in s.messages), [m.text for m in s.messages]


def test_a_threshold_that_is_not_a_number_is_refused_and_the_last_kept(state):
    """Round 29a: imgui's ctrl+click lets the threshold slider take a typed "nan", which selected
    nothing while the slider showed "nan" (and "inf" the same); the threshold is kept instead."""
    assert state.run_oracle_query(0)
    before, selected = state.threshold, int(state.selection.sum())
    for value in (float("nan"), float("inf"), -float("inf")):
        assert not state.set_threshold(value)
        assert state.threshold == before and int(state.selection.sum()) == selected
        assert state.messages[-1].level == "error" and "must be a finite number" in state.messages[-1].text
    assert state.set_threshold(-1.0) and state.selection.sum() == state.field.assigned().sum()


def test_an_export_or_screenshot_path_ending_in_a_separator_is_refused(state, tmp_path):
    """Round 29a: the export path `sel/` wrote a file named `sel` (pathlib drops the separator),
    which the CLI refuses for its outputs (`output_file`); the viewer's export, screenshot and
    registration paths now refuse it too."""
    assert state.run_oracle_query(0) and state.set_threshold(-1.0)
    for typed in (f"{tmp_path}/sel/", f"{tmp_path}/sel\\"):
        assert state.export_selection(typed) is None
        assert "ends with a separator" in state.messages[-1].text, state.messages[-1].text
        assert not state.guard_output(typed, "the screenshot")
    assert not (tmp_path / "sel").exists() and not (tmp_path / "sel\\").exists()
    assert state.export_selection(tmp_path / "sel.ply") == int(state.selection.sum())


def test_an_embedding_file_of_several_rows_says_the_viewer_queries_by_the_first(state, tmp_path):
    """Round 29a: a Q.npy of K rows (which `drsplat query` scores one by one) was queried by its
    first row without a word."""
    emb = state.oracle.embeddings
    np.save(tmp_path / "k.npy", emb[:3])
    assert state.run_embedding_query(tmp_path / "k.npy")
    assert any(m.level == "warning" and "holds 3 embeddings; the viewer queries by the first" in m.text for m in state.messages)
    np.save(tmp_path / "one.npy", emb[0])
    count = len(state.messages)
    assert state.run_embedding_query(tmp_path / "one.npy")
    assert not any("embeddings; the viewer" in m.text for m in state.messages[count:])
