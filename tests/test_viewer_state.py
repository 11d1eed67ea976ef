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


def test_round_86d_viewer_findings(state, tmp_path):
    """Round 86d: an empty oracle label list crashed the first screen (IndexError); an export to an existing name the
    format cannot write asked to be pressed again to replace it, then refused the name; a field of no assigned
    Gaussian loaded without a word and invited queries that pointed to "the warnings above"; a screenshot could replace
    the embedding file of the query shown."""
    from viewer.state import ViewerState, read_oracle_queries

    ds = state.source_dir
    empty = Path(shutil.copytree(ds, tmp_path / "empty"))
    (empty / "gt" / "label_names.json").write_text("[]")
    np.save(empty / "text_embeddings.npy", np.zeros((0, state.field.dim), np.float32))
    problems: list[str] = []
    assert read_oracle_queries(empty, problems) is None and "lists no label" in problems[0], problems
    assert state.load_source(empty) and state.oracle is None and state.next_step().startswith("Next:")
    # the export's name checked before a replacement is asked for
    assert state.run_embedding_query(_save_query(tmp_path, state)) is True
    state.set_threshold(-1.0)
    (tmp_path / "old.splat").write_bytes(b"x" * 64)
    assert state.export_selection(tmp_path / "old.splat", "drsplat") is None
    assert "a drsplat export is a PLY" in state.messages[-1].text and "export again" not in state.messages[-1].text
    assert (tmp_path / "old.splat").read_bytes() == b"x" * 64
    # the query's own embedding file is an input
    query_file = tmp_path / "q.npy"
    assert not state.guard_output(query_file, "the screenshot") and "embedding file of the query shown" in state.messages[-1].text
    # round 95a F2: the CLIP checkpoint and config the viewer was started with (a window screenshot replaced the checkpoint)
    state.clip_checkpoint, state.clip_config = tmp_path / "vitb16", tmp_path / "config.json"
    for given in (state.clip_checkpoint, state.clip_config):
        given.write_bytes(b"weights")
        assert not state.guard_output(given, "the screenshot") and "--clip-c" in state.messages[-1].text, state.messages[-1].text
    state.clip_checkpoint = state.clip_config = None
    # a field whose every Gaussian is unassigned
    none = ViewerState()
    reg = state.scene_path
    from drsplat.scene import load_ply, save_ply

    scene = load_ply(reg)
    extra = {k: (np.zeros_like(v) if k.startswith("lang_") and k != "lang_meta" else v) for k, v in scene.extra.items()}
    save_ply(dataclasses.replace(scene, extra=extra), tmp_path / "unassigned.ply")
    assert none.load_scene(tmp_path / "unassigned.ply")
    assert any(m.level == "warning" and "none of this scene's" in m.text and "warnings above" not in m.text for m in none.messages), \
        [m.text for m in none.messages]
    assert none.next_step().startswith("Queries are off: none of this scene's")


def _save_query(tmp_path: Path, state) -> Path:
    """An embedding file of one assigned Gaussian's feature (a query that selects something)."""
    row = state.field.reconstruct(np.flatnonzero(state.field.assigned())[:1])[0]
    np.save(tmp_path / "q.npy", row.astype(np.float32))
    return tmp_path / "q.npy"


def test_an_export_over_the_output_of_the_registration_running_is_refused(state, tmp_path):
    """An export to the file a running registration writes was accepted ("exported 78 Gaussians")
    and then replaced when the registration ended (a viewer probe, 2026-11-30)."""
    from viewer.registration import RegistrationJob

    assert state.run_oracle_query(0)
    state.set_threshold(-1.0)
    out = tmp_path / "race" / "out.ply"
    state.registration = RegistrationJob(out)  # running: not finished
    assert state.export_selection(out, "standard") is None
    assert "is the same file as the output of the registration running (an input)" in state.messages[-1].text, state.messages[-1].text
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


def test_a_registration_that_replaces_the_file_opened_meanwhile_loads_the_new_one(state, tmp_path):
    """Round 61a: opening out.ply (an earlier registration) while a registration into out.ply ran, then letting it finish,
    said "another scene is open now, so it was not loaded" while the open scene WAS out.ply: the window showed the old
    field as if it were the file on disk. The new file is loaded, and said so."""
    out = tmp_path / "out.ply"
    shutil.copy(state.scene_path, out)
    for book in state.scene_path.parent.glob("registered.codebook.faiss"):
        shutil.copy(book, tmp_path / "out.codebook.faiss")
    assert state.start_registration(out, topk=10, background=True)
    assert state.load_scene(out)
    before = state.num_gaussians
    deadline = time.time() + 120
    while not state.registration.finished and time.time() < deadline:
        time.sleep(0.05)
    assert state.registration.error is None, state.registration.error
    assert state.poll_registration()
    assert any("registration replaced" in m.text and "the new one is loaded" in m.text for m in state.messages)
    from drsplat.lang import read_field
    from drsplat.scene import load_ply

    on_disk = read_field(load_ply(out), out)
    assert state.scene_path == out and np.array_equal(state.field.weights, on_disk.weights)  # the file as it is now
    assert state.num_gaussians <= before


def test_a_registered_scene_whose_codebook_is_missing_opens_without_its_field(state, tmp_path):
    """Round 61a: a registered PLY whose codebook is missing (or renamed away) could not even be viewed: "cannot open ...:
    codebook file not found". Its splats are intact: it opens without its field, and the panel says why queries are off."""
    from viewer.demo import demo_dir

    lone = Path(shutil.copy(demo_dir() / "registered.ply", tmp_path / "lone.ply"))  # a PQ field, its codebook not beside it
    assert state.load_scene(lone)
    assert state.scene_path == lone and state.field is None and state.num_gaussians > 0
    assert "without its language field" in state.messages[-1].text and "codebook" in state.messages[-1].text
    assert state.encoder_status.startswith("Queries are off: the language field of lone.ply cannot be read")


def test_the_count_above_the_export_says_what_a_hide_selection_export_writes(state, tmp_path):
    """Round 71b F3: in hide-selection mode the panel said "selected: 78 of 2,744" above an export of the 2,666 others."""
    from drsplat.scene import load_ply

    assert state.run_oracle_query(0)
    selected, total = int(state.selection.sum()), state.num_gaussians
    assert state.selection_text() == f"selected: {selected:,} of {total:,}"
    assert state.set_mode("hide_selection")
    shown = int(state.export_mask().sum())
    assert state.selection_text() == f"selected: {selected:,} of {total:,}; an export writes the {shown:,} shown"
    out = tmp_path / "hidden.ply"
    assert state.export_selection(out, "standard") is not None and load_ply(out).num_gaussians == shown


def test_a_one_gaussian_scene_is_said_in_the_singular(tmp_path):
    """Round 71b F5: "loaded one.ply: 1 Gaussians"."""
    from drsplat.scene import GaussianScene, save_ply
    from viewer.state import ViewerState

    one = GaussianScene(means=np.zeros((1, 3), np.float32), quats=np.array([[1, 0, 0, 0]], np.float32), log_scales=np.zeros((1, 3), np.float32),
                        opacity_logits=np.zeros(1, np.float32), sh=np.zeros((1, 1, 3), np.float32))
    save_ply(one, tmp_path / "one.ply")
    st = ViewerState()
    assert st.load_scene(tmp_path / "one.ply") and st.messages[-1].text.startswith("loaded one.ply: 1 Gaussian, SH degree 0")
    save_ply(one.subset(np.zeros(1001, np.int64)), tmp_path / "many.ply")  # and thousands grouped (round 72a F4)
    assert st.load_scene(tmp_path / "many.ply") and st.messages[-1].text.startswith("loaded many.ply: 1,001 Gaussians, SH degree 0")


def test_a_blank_embedding_path_asks_for_one(state):
    """Round 71b F4: a blank Q.npy field became Path("."): "embedding query . failed: .: is not a file"."""
    assert not state.run_embedding_query("  ")
    assert state.messages[-1].text == "type the path of a Q.npy embedding file to query by"


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


def test_a_closing_viewer_waits_for_the_encoder_being_built(state, monkeypatch, caplog):
    """Was: closing the window within seconds of opening a scene of CLIP features ended the process with
    "terminate called without an active exception" and SIGABRT, exit 134 (5 of 6 closes): the
    interpreter ended under the daemon thread building the encoder (round 61a). The closing path now
    waits for it."""
    import viewer.state as vs
    from viewer.launch import wait_for_encoder

    built = []

    class SlowEncoder:
        model_id = "ViT-B-16/laion2b_s34b_b88k"

        def __init__(self, *args, **kwargs):
            time.sleep(1.0)
            built.append(self)

    monkeypatch.setattr(vs, "ClipEncoder", SlowEncoder)
    state.field = dataclasses.replace(state.field, clip_model="ViT-B-16/laion2b_s34b_b88k")
    state.start_text_encoder(background=True)
    assert state.encoder_being_built()
    with caplog.at_level(logging.INFO, logger="viewer"):
        wait_for_encoder(state)
    assert built and not state.encoder_being_built() and state.encoder is built[0]
    assert "waiting for the CLIP text encoder" in caplog.text


def test_an_encoder_of_other_weights_turns_text_queries_off_and_leaves_the_others(state, tmp_path, monkeypatch):
    """Was: `--clip-checkpoint` of other weights than the features' loaded "ready", then every query failed
    with "CLIP weights mismatch", embedding files and clicks too (their relevancy negatives come from the
    encoder's text): nothing could be queried without a restart (round 61a). Now the mismatch is found as
    the encoder loads: text queries are off with the reason, the others score by cosine."""
    import viewer.state as vs

    class OtherWeights:
        model_id = "ViT-B-16/laion2b_s34b_b88k"
        weights_digest = "2:" + "b" * 40

        def __init__(self, *args, **kwargs):
            pass

    monkeypatch.setattr(vs, "ClipEncoder", OtherWeights)
    state.field = dataclasses.replace(state.field, clip_model="ViT-B-16/laion2b_s34b_b88k", clip_weights="1:" + "a" * 40)
    state._load_encoder(state.scene_version)
    assert state.encoder is None
    assert state.encoder_status.startswith("Text queries are off: CLIP weights mismatch") and "by cosine" in state.encoder_status
    query = tmp_path / "q.npy"
    np.save(query, state.oracle.embeddings[:1])
    assert state.run_embedding_query(query) and state.query.metric == "cosine"
    same = type("SameWeights", (OtherWeights,), {"weights_digest": "1:" + "a" * 40})
    monkeypatch.setattr(vs, "ClipEncoder", same)
    state._load_encoder(state.scene_version)
    assert isinstance(state.encoder, same) and "ready" in state.encoder_status


def test_a_registered_scene_without_its_codebook_says_so_not_register_again(state, tmp_path):
    """Round 79b F1: a PQ PLY copied without its codebook: the load warning named the file, but the first screen, every
    query and a drsplat-format export then said "no language field: register it", minutes of work where putting the
    codebook back is the fix."""
    from viewer.demo import demo_dir

    lone = Path(shutil.copy(demo_dir() / "registered.ply", tmp_path / "lone.ply"))  # a PQ field, its codebook not beside it
    assert state.load_scene(lone) and state.field is None
    assert "codebook" in state.next_step() and "Registration panel" not in state.next_step(), state.next_step()
    q = tmp_path / "q.npy"
    np.save(q, np.ones(4, np.float32))
    assert not state.run_embedding_query(q)
    assert "cannot be read" in state.messages[-1].text and "register it first" not in state.messages[-1].text
    assert state.export_selection(tmp_path / "x.ply", "drsplat") is None
    assert "mend what it names first" in state.messages[-1].text and "codebook" in state.messages[-1].text


@pytest.mark.parametrize("model_id, built", [("ViT-L-14:openai", ("ViT-L-14", "openai")), ("ViT-L-14", None),
                                             ("UNKNOWN", ("ViT-B-16", "laion2b_s34b_b88k"))])  # ids compare case-insensitively (80a F4)
def test_the_text_encoder_is_the_fields_model_whatever_its_ids_separator(state, monkeypatch, model_id, built):
    """Round 79a F3: the viewer split the field's CLIP id at '/' only, so "ViT-L-14:openai" (which the command line reads)
    turned text queries off, and a tagless "ViT-L-14" loaded the default weights tag, after which every query failed
    with a model mismatch. Now the id's architecture and tag; a tagless id without --clip-checkpoint says what to pass."""
    import viewer.state as vs

    made = []

    class Recorder:
        weights_digest = None

        def __init__(self, model, pretrained, checkpoint, device=None):
            made.append((model, pretrained))
            self.model_id = f"{model}/{pretrained}"

    monkeypatch.setattr(vs, "ClipEncoder", Recorder)
    state.field = dataclasses.replace(state.field, clip_model=model_id, clip_weights=None)
    state.clip_checkpoint = None
    state._load_encoder(state.scene_version)
    if built is None:
        assert made == [] and state.encoder is None
        assert "names no weights tag; pass --clip-checkpoint PATH" in state.encoder_status, state.encoder_status
    else:
        assert made == [built] and "ready" in state.encoder_status, state.encoder_status


def test_a_tagless_model_id_matches_its_architecture_with_any_tag(caplog):
    """Round 79a F2: the command line's advice for a field whose id names no weights tag ("pass --pretrained TAG")
    could not work: the model check compared whole ids. A tagless id now matches its architecture with a warning;
    other architectures (and the oracle's space) still do not."""
    from drsplat.errors import DrsplatError
    from drsplat.features.modelid import check_compatible

    with caplog.at_level(logging.WARNING):
        check_compatible("ViT-L-14", "ViT-L-14/openai")
        check_compatible("vit-l-14:OPENAI", "ViT-L-14")
        check_compatible("Unknown", "ViT-B-16/laion2b_s34b_b88k")  # no id at all, in any case: nothing to check
    assert "names no weights tag" in caplog.text and "cannot check they match" in caplog.text
    for a, b in (("ViT-L-14", "ViT-B-16/openai"), ("ViT-L-14/laion2b_s32b_b82k", "ViT-L-14/openai"), ("oracle", "oracle/small-0")):
        with pytest.raises(DrsplatError, match="CLIP model mismatch"):
            check_compatible(a, b)


@pytest.mark.parametrize("names, words", [(["ball", "mug", "ball"], 'repeats the name "ball"'), (["ball", " "], "empty name")])
def test_typed_segmentation_labels_are_checked_like_the_clis(state, names, words):
    assert not state.run_segmentation(names)
    assert words in state.messages[-1].text, state.messages[-1].text


@pytest.mark.parametrize("text, entry", [("mug,,table", "entry 2 of 3"), ("mug,table,", "entry 3 of 3"), (" , mug", "entry 1 of 2")])
def test_the_segment_fields_empty_entries_reach_the_check_instead_of_being_dropped(state, text, entry):
    """Round 39 left as found: the Display panel dropped `mug,,table`'s empty entry before the check,
    and segmented two labels where three were typed. The field goes to the state as typed."""
    assert not state.run_segmentation(text)
    assert f"{entry} is empty" in state.messages[-1].text and state.messages[-1].level == "error", state.messages[-1].text


def test_a_blank_segment_field_segments_by_the_oracles_labels(state):
    assert state.run_segmentation("  ") and state.segment_names == list(state.oracle.names)


def test_oracle_labels_are_not_offered_for_a_field_of_clip_features(state):
    """Was: a synthetic dataset's features made by a real CLIP pipeline, registered and opened with
    --source, still offered the oracle label buttons (and the first screen's hint recommended them):
    'mug' scored the CLIP field with a ground-truth vector of another space and reported 810
    Gaussians; a blank segmentation field labelled 2,491 of 2,744 'astronaut' (round 61a). Now the
    oracle labels query only an oracle field, and the panel says why they are gone."""
    assert state.usable_oracle is not None and state.run_oracle_query(0)  # an oracle field: offered
    state.field = dataclasses.replace(state.field, clip_model="ViT-B-16/laion2b_s34b_b88k")
    state.query = None
    assert state.usable_oracle is None and "oracle space" in state.oracle_problem()
    assert "click a label" not in state.next_step()
    assert not state.run_oracle_query(0) and "ViT-B-16" in state.messages[-1].text and state.query is None
    assert not state.run_segmentation("  ") and "oracle labels are not offered" in state.messages[-1].text
    assert state.segmentation is None


def test_an_export_replaces_a_file_only_when_pressed_again(state, tmp_path):
    """Was: the export path stays in the panel, so exporting a second query's selection replaced the
    first's export without a word; with an export open, typing the registered scene it came from
    replaced it (2,763 Gaussians) by the 107 selected (round 61a). Now a file is replaced only by a
    second export to it in a row, asked for by name; a file changed in between is asked for again."""
    target = tmp_path / "sel.ply"
    state.run_oracle_query(state.oracle.names.index("mug"))
    first = state.export_selection(target, "drsplat")
    assert first and target.is_file()
    kept = target.read_bytes()
    state.run_oracle_query(state.oracle.names.index("ball"))
    assert state.export_selection(target, "drsplat") is None
    assert "sel.ply (" in state.messages[-1].text and "exists: export again to replace it" in state.messages[-1].text
    assert target.read_bytes() == kept
    target.write_bytes(kept + b"x")  # changed since it was asked about: asked again
    assert state.export_selection(target, "drsplat") is None and "export again" in state.messages[-1].text
    second = state.export_selection(target, "drsplat")
    assert second and second != first and target.read_bytes() != kept + b"x"
    assert state.export_selection(tmp_path / "new.ply", "drsplat") == second  # a new file needs no second press


def test_an_export_while_a_segmentation_is_shown_says_what_it_writes(state, tmp_path):
    """Round 61a: with a segmentation shown, an export said "the selection is empty: run a query" (no query), or wrote the
    query's selection, uncoloured, without a word (a query in hand). Both now say what an export writes."""
    assert state.run_segmentation("  ")
    assert state.export_selection(tmp_path / "a.ply", "standard") is None
    assert "drsplat segment --ply" in state.messages[-1].text
    assert state.run_oracle_query(0) and state.run_segmentation("  ") and state.mode == "segmentation"
    assert state.export_selection(tmp_path / "b.ply", "standard")
    assert "the query's selection, not the segmentation shown" in state.messages[-1].text


def test_an_empty_selections_export_gives_the_best_score_as_the_cli_does(state, tmp_path):
    """Round 95a F8: with a query run and the threshold above every score, the export said "run a query and lower the
    threshold"; `drsplat query --out` gives the best score."""
    assert state.run_oracle_query(0)
    best = float(state.query.scores[state.query.assigned].max())
    state.set_threshold(1.0)
    assert state.export_selection(tmp_path / "a.ply", "standard") is None
    assert f"no Gaussian scores >= 1.0000 (the best score is {best:.4f}): lower the threshold" in state.messages[-1].text
    assert "run a query" not in state.messages[-1].text and not (tmp_path / "a.ply").exists()
    state.set_threshold(best + 1e-6)  # alike at 4 decimals: shown with as many as tell them apart (round 97a F5, as the CLI)
    assert state.export_selection(tmp_path / "a.ply", "standard") is None
    text = state.messages[-1].text
    above, top = text.split("scores >= ")[1].split(" (the best score is ")
    assert above != top.split(")")[0], text


def test_a_non_finite_oracle_vector_is_named_by_its_label(state):
    """Round 95a F9: a NaN row of text_embeddings.npy ("mug", row 3) was reported as "query 0" (the one row given)."""
    state.oracle.embeddings = state.oracle.embeddings.copy()
    state.oracle.embeddings[3] = np.nan
    assert not state.run_oracle_query(3)
    name = state.oracle.names[3]
    assert f"the oracle vector of {name!r} (row 3 of text_embeddings.npy) holds non-finite values" in state.messages[-1].text
    assert state.run_oracle_query(0)


def test_an_exports_confirmation_covers_its_codebook_format_and_query(tmp_path):
    """Round 62b: a drsplat export to a new PLY name replaced the codebook file of that name unasked (only the PLY was
    asked about), and a confirmation outlived the format, scene or query it was asked for."""
    from viewer.demo import demo_dir
    from viewer.state import ViewerState

    state = ViewerState()
    assert state.load_scene(demo_dir() / "registered.ply") and state.load_source(demo_dir())  # a PQ field: a codebook beside
    assert state.run_oracle_query(0)
    book = tmp_path / "A.codebook.faiss"
    book.write_bytes(b"someone's codebook")
    assert state.export_selection(tmp_path / "A.ply", "drsplat") is None
    assert "A.codebook.faiss (18 bytes) exists: export again" in state.messages[-1].text and book.read_bytes() == b"someone's codebook"
    assert state.export_selection(tmp_path / "A.ply", "drsplat") and book.read_bytes() != b"someone's codebook"
    target = tmp_path / "B.ply"
    assert state.export_selection(target, "standard")
    assert state.export_selection(target, "standard") is None  # asked
    assert state.export_selection(target, "drsplat") is None  # another format: asked again, not taken as the answer
    assert state.run_oracle_query(1) and state.export_selection(target, "drsplat") is None  # another query: asked again
    assert state.export_selection(target, "drsplat")


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
    import os

    os.mkfifo(tmp_path / "new" / "fifo.ini")  # round 53: imgui's fopen of a FIFO blocked the first frame for ever
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert usable_layout_path(tmp_path / "new" / "fifo.ini") is None
    assert "fifo.ini is not a regular file" in caplog.text


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


def test_a_path_with_a_line_break_fails_in_one_line(tmp_path, caplog):
    """Round 54: the viewer's "cannot open ..." message quoted a typed path with its newline raw, forging a line of the log
    (the CLI escapes them since round 54); every failure message is now one line, the break written as \\n."""
    from viewer.state import ViewerState

    s = ViewerState()
    with caplog.at_level(logging.ERROR):
        assert not s.load_scene(tmp_path / "a\nERROR: forged.ply")
        assert not s.load_source(tmp_path / "b\rdata")
    texts = [m.text for m in s.messages if m.level == "error"]
    assert len(texts) == 2 and all("\n" not in t and "\r" not in t for t in texts), texts
    assert "a\\nERROR: forged.ply" in texts[0] and "b\\rdata" in texts[1], texts
    assert not any(line.startswith("ERROR: forged") for line in caplog.text.splitlines())


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


@pytest.mark.parametrize("value, expected", [(0.0, 20.0), (float("nan"), 60.0), (1e6, 110.0), (-30.0, 20.0), (75.0, 75.0)])
def test_a_typed_field_of_view_is_kept_in_the_sliders_range(value, expected):
    """Round 39: a typed fov of 0 divided by zero and closed the window, NaN blanked the view, 1e6 gave a negative
    focal length; roll and fly speed took NaN (`viewer.settings.in_range`, which the View panel applies)."""
    from viewer.camera import intrinsics_for
    from viewer.settings import FOV_RANGE, in_range

    fov = in_range(value, *FOV_RANGE, 60.0)
    assert fov == expected
    fx, fy, _, _ = intrinsics_for(640, 480, fov)
    assert np.isfinite([fx, fy]).all() and fx > 0 and fy > 0


class _OracleEncoder:
    """A stand-in CLIP text encoder: the dataset's oracle vectors for its label names (tests/test_viewer_render.py)."""

    def __init__(self, state):
        self.model_id = state.field.clip_model
        self._vectors = dict(zip(state.oracle.names, state.oracle.embeddings))

    def encode_text(self, phrases):
        rng = np.random.default_rng(0)  # LERF's canonical negatives ("object", "things", ...): fixed random directions
        dim = next(iter(self._vectors.values())).shape[0]
        return np.stack([self._vectors[p] if p in self._vectors else rng.normal(size=dim) for p in phrases]).astype(np.float32)


def test_a_relevancy_query_starts_at_the_clis_threshold_of_one_half(state):
    """Round 39: with an encoder loaded every text query is scored by relevancy, and the GUI started it at Otsu's
    split (selecting ~78 % of a scene with negatives) where `drsplat query --relevancy` and the evaluation use 0.5."""
    from drsplat.query import select

    names = state.oracle.names
    state.encoder = _OracleEncoder(state)
    state.settings.query.negatives = f"{names[0]}, {names[1]}"
    assert state.run_text_query(names[2]) and state.query.metric == "relevancy"
    assert state.threshold == 0.5
    expected = select(state.query.scores, 0.5) & state.query.assigned
    np.testing.assert_array_equal(state.selection, expected)
    # the colour scale spans the Gaussians with a feature (the others' relevancy is 0: round 76a F4)
    assigned = state.query.assigned.copy()
    assigned[:10] = False
    scores = np.where(assigned, state.query.scores, np.float32(0))
    state.query = dataclasses.replace(state.query, scores=scores, assigned=assigned)
    assert state.score_range() == (float(scores[assigned].min()), float(scores[assigned].max())) and scores[assigned].min() > 0


def test_the_viewers_scores_are_the_clis_bit_for_bit(state, tmp_path):
    """Round 53: the viewer made the query a unit row and the library made it one again; float32 normalising is not
    idempotent, so every viewer score was up to 6e-8 off `drsplat query`'s, and a Gaussian at the threshold was selected
    and exported by one and not the other. Embedding files and text queries (cosine and relevancy) now score as the CLI's."""
    from drsplat.cli import build_parser
    from drsplat.commands.query import build_queries, compute_scores

    names = state.oracle.names
    path = tmp_path / "q.npy"
    np.save(path, (state.oracle.embeddings[2] * 3.7).astype(np.float32))  # not a unit row: normalised once, where both do it
    cases = [(["--embedding", str(path)], lambda: state.run_embedding_query(path))]
    encoder = _OracleEncoder(state)
    cases.append((["--text", names[2], "--relevancy"], lambda: state.run_text_query(names[2])))
    for argv, run_in_viewer in cases:
        args = build_parser().parse_args(["query", str(state.scene_path), *argv])
        queries, _, used = build_queries(args, state.field, encoder_factory=lambda *_: encoder)
        expected = compute_scores(args, state.field, queries, used, encoder_factory=lambda *_: encoder)[:, 0]
        state.encoder = encoder if "--text" in argv else None
        assert run_in_viewer()
        assert state.query.metric == ("relevancy" if "--relevancy" in argv else "cosine")
        np.testing.assert_array_equal(state.query.scores, expected, err_msg=" ".join(argv))


def test_an_export_to_a_fifo_nobody_reads_is_refused_at_once_and_one_that_is_read_is_written_whole(state, tmp_path):
    """Round 53: an export (or screenshot) to a FIFO with no reader waited for one on the window's thread: no frame
    drawn, no message, the window could not be closed. It is now refused at once, naming the FIFO and the way out; with
    a reader, the PLY arrives whole (the write end is held open, so the reader sees no end-of-file before it)."""
    import os
    import threading

    from drsplat.scene import load_ply

    assert state.run_oracle_query(0)
    fifo = tmp_path / "sel.ply"
    os.mkfifo(fifo)
    done: list = []
    worker = threading.Thread(target=lambda: done.append(state.export_selection(fifo, "standard")), daemon=True)
    worker.start()
    worker.join(10)
    if worker.is_alive():  # let the blocked export end, so the test fails instead of hanging
        with open(fifo, "rb") as drain:
            drain.read()
        worker.join(10)
        pytest.fail("the export waited for a reader of the FIFO")
    assert done == [None]
    assert "it is a FIFO that no process reads yet; start its reader first" in state.messages[-1].text, state.messages[-1].text
    received: list[bytes] = []
    reader = threading.Thread(target=lambda: received.append(fifo.read_bytes()), daemon=True)
    reader.start()
    for _ in range(200):  # refused until the reader has the FIFO open (a probe that opened and closed it would end its read)
        count = state.export_selection(fifo, "standard")
        if count is not None:
            break
        time.sleep(0.02)
    reader.join(10)
    assert count == int(state.selection.sum()) and received
    (tmp_path / "got.ply").write_bytes(received[0])
    assert load_ply(tmp_path / "got.ply").num_gaussians == count


def test_a_typed_tilde_is_the_home_folder_as_in_a_shell(state, tmp_path, monkeypatch):
    """Round 53: `~/sel.ply` typed as an export path said "exported ... to ~/sel.ply" and made a folder named `~` in the
    working folder, nothing in the home folder; opening `~/scene.ply` said it did not exist."""
    home, work = tmp_path / "home", tmp_path / "work"
    home.mkdir()
    work.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(work)
    assert state.run_oracle_query(0)
    assert state.export_selection("~/sel.ply", "standard") == int(state.selection.sum())
    assert (home / "sel.ply").is_file() and not (work / "~").exists()
    assert f"to {home / 'sel.ply'}" in state.messages[-1].text
    state.set_threshold(float(state.query.scores[state.query.assigned].max()))  # the best Gaussian alone (no two tie here)
    assert state.export_selection(tmp_path / "one.ply", "standard") == 1
    assert state.messages[-1].text.startswith("exported 1 Gaussian to "), state.messages[-1].text  # not "1 Gaussians"
    assert state.load_scene("~/sel.ply") and state.scene_path == home / "sel.ply"


def test_a_typed_path_is_read_without_the_spaces_around_it(state, tmp_path):
    """Round 61a: a pasted `sel.ply ` was refused as "a .ply  name would hold a PLY" and a `Q.npy ` as not found, where
    the Scene panel's open field strips the spaces; every typed path does now."""
    assert state.run_oracle_query(0)
    assert state.export_selection(f"  {tmp_path / 'sel.ply'} ", "standard") and (tmp_path / "sel.ply").is_file()
    np.save(tmp_path / "q.npy", state.oracle.embeddings[:1])
    assert state.run_embedding_query(f"{tmp_path / 'q.npy'}  ") and state.query.name == "q.npy"


def test_the_scene_panels_assigned_count_is_the_set_queries_use(state, tmp_path):
    """Round 53: the Scene panel counted rows with a registration weight; queries, exports and `drsplat info` count rows
    with a stored feature. A file whose 100 features were zeroed (weights kept) was warned of on loading, then shown
    with those 100 counted as assigned."""
    from plyfile import PlyData

    from viewer.state import ViewerState

    ply = PlyData.read(str(state.scene_path))
    rows = ply["vertex"].data
    names = [name for name in rows.dtype.names if name.startswith("lang_") and name[5:].isdigit()]
    zeroed = np.flatnonzero(rows["lang_weight"] > 0)[:100]
    for name in names:
        rows[name][zeroed] = 0
    ply.write(str(tmp_path / "zeroed.ply"))
    other = ViewerState()
    assert other.load_scene(tmp_path / "zeroed.ply")
    weighted = int((other.field.weights > 0).sum())
    assert other.assigned_count == int(other.field.assigned().sum()) == weighted - 100


def test_a_cosine_query_whose_scores_are_one_value_says_otsu_has_nothing_to_split(state, tmp_path):
    """Round 39: 500 copies of one Gaussian scored one value; the GUI selected them all without the warning
    `drsplat query --threshold auto` gives."""
    from drsplat.lang import export_scene
    from viewer.state import ViewerState

    one = np.flatnonzero(state.field.assigned())[0]
    rows = np.full(500, one)
    out = tmp_path / "same.ply"
    export_scene(state.scene.subset(rows), state.field.subset(rows), out, "drsplat")
    same = ViewerState()
    assert same.load_scene(out) and same.load_source(state.source_dir)
    assert same.run_oracle_query(0) and same.query.metric == "cosine"
    warned = [m.text for m in same.messages if m.level == "warning"]
    assert any("automatic threshold: every one of the 500 scored Gaussians scores" in t for t in warned), warned
    assert same.selection.sum() == 500


def test_a_click_in_hide_selection_mode_picks_what_is_drawn_not_the_hidden_selection(state):
    """Round 39: ctrl+click rasterized the whole scene, so in *hide selection* the click queried the hidden object
    behind which the user clicked; now only the Gaussians drawn are picked (and in *selection only* the same)."""
    from drsplat.raster import rasterize
    from viewer.camera import camera_for_size
    from viewer.state import ViewerState

    state.run_oracle_query(0)
    state.set_mode("hide_selection")
    hidden = state.selection.copy()
    assert 0 < hidden.sum() < hidden.size
    cam = camera_for_size(state.cameras[0], 96, None)
    front = rasterize(state.scene, cam, topk=1).ids[..., 0]
    vs, us = np.nonzero((front >= 0) & hidden[np.maximum(front, 0)])
    assert vs.size, "the hidden label is in front somewhere in this view"
    picks = [state.pick(cam, u + 0.5, v + 0.5) for v, u in zip(vs[:: max(1, vs.size // 8)], us[:: max(1, vs.size // 8)])]
    assert any(p.size for p in picks)
    assert not any(hidden[p].any() for p in picks if p.size), "no hidden Gaussian is picked"
    # the pick among the shown Gaussians (the whole scene's prepared arrays, masked: no per-click preparation) is the
    # pick of a scene made of them alone
    shown_ids = np.flatnonzero(~hidden)
    alone = ViewerState()
    alone.scene = state.scene.subset(~hidden)
    for v, u, picked in zip(vs[:: max(1, vs.size // 8)], us[:: max(1, vs.size // 8)], picks):
        np.testing.assert_array_equal(picked, shown_ids[alone.pick(cam, u + 0.5, v + 0.5)])
    state.set_mode("selection")
    shown = [state.pick(cam, u + 0.5, v + 0.5) for v, u in zip(vs[:4], us[:4])]
    assert all(hidden[p].all() for p in shown if p.size) and any(p.size for p in shown)


def test_an_oracle_label_file_that_is_refused_is_said_in_the_gui(state, tmp_path):
    """Round 39: a repeated label name made the oracle buttons vanish with the reason in the terminal only."""
    import json

    from drsplat.defaults import ORACLE_LABEL_NAMES

    ds = Path(shutil.copytree(state.source_dir, tmp_path / "labels"))
    names = json.loads((ds / ORACLE_LABEL_NAMES).read_text())
    names[1] = names[0]
    (ds / ORACLE_LABEL_NAMES).write_text(json.dumps(names))
    assert state.load_source(ds) and state.oracle is None
    assert state.messages[-1].level == "warning" and "no oracle labels" in state.messages[-1].text
    assert "repeats" in state.messages[-1].text


def test_a_scene_opened_beside_the_current_one_keeps_its_cameras_only_when_it_is_derived_from_it(state, tmp_path):
    """Round 39: every PLY opened from the current scene's folder kept its cameras and oracle, so registering an
    unrelated scene there used the other scene's cameras and features, silently wrong."""
    import types

    from drsplat.lang import export_scene
    from viewer.app import ViewerApp, derived_from

    scene, field = state.scene, state.field
    extent = float(np.ptp(scene.means, axis=0).max())
    half = np.arange(0, scene.num_gaussians, 2)
    assert derived_from(scene.means[half], scene.means) and not derived_from(scene.means, scene.means[half])
    assert derived_from(scene.means + 1e-4 * extent, scene.means), "quantised positions (.spz, compressed PLY) still match"
    assert not derived_from(scene.means + 0.05 * extent, scene.means)
    # a small scene far from the origin written as .spz: positions rounded to its fixed-point steps (the review of round 39)
    far = scene.means.astype(np.float64) * (0.2 / extent) + 5000.0
    step = 2.0 ** -10  # 24-bit fixed point with the coordinates near 5000: 10 fractional bits
    assert derived_from(np.round(far / step) * step, far) and not derived_from(far + 0.01, far)
    folder = state.scene_path.parent
    export_scene(scene.subset(half), field.subset(half), folder / "export.ply", "drsplat")
    host = types.SimpleNamespace(state=state, background_checks=False)
    assert ViewerApp.open_scene(host, folder / "export.ply") and len(state.cameras) and state.oracle is not None
    other = scene.subset(half)
    other.means = other.means + np.array([0.3 * extent, 0.0, 0.0], other.means.dtype)
    export_scene(other, field.subset(half), folder / "other.ply", "drsplat")
    assert ViewerApp.open_scene(host, folder / "other.ply")
    assert state.cameras == [] and state.oracle is None and state.source_dir is None
    assert "is not the previous scene" in " ".join(m.text for m in state.messages[-3:])


def test_an_export_of_nothing_shown_in_hide_selection_says_so(state, tmp_path):
    """Round 39: with every Gaussian selected and hidden, the export said "the selection is empty"."""
    state.run_oracle_query(0)
    state.set_threshold(-1.0)  # every assigned Gaussian selected
    state.set_mode("hide_selection")
    assert state.selection.all() and not state.export_mask().any(), "a registered PLY holds assigned Gaussians only"
    assert state.export_selection(tmp_path / "shown.ply", "standard") is None
    assert "nothing is shown to export" in state.messages[-1].text and not (tmp_path / "shown.ply").exists()


@pytest.mark.parametrize("text, negatives, words", [
    ("ball\x1b[2J", "", "holds"), ("ball", "mug,,table", "entry 2 of 3 is empty"), ("ball", "mug, mug", "repeats the phrase 'mug'"),
    ("ball", "mug\u202e", "which a terminal would not show as itself")])
def test_typed_queries_and_negatives_are_checked_like_the_clis(state, text, negatives, words):
    """Round 39: the GUI embedded what `drsplat query --text / --negatives` refuses: hidden characters, empty and
    repeated negative phrases."""
    state.encoder = _OracleEncoder(state)
    state.settings.query.negatives = negatives
    assert not state.run_text_query(text)
    assert words in state.messages[-1].text and state.messages[-1].level == "error", state.messages[-1].text


def test_library_warnings_take_only_their_own_threads_records():
    """A camera check on a worker thread records its warnings into the window's log while the window's thread loads a
    scene under its own `LibraryWarnings`: each block shows what its thread's work warned of, once, not the other's."""
    import threading

    from viewer.messages import LibraryWarnings, MessageLog

    messages = MessageLog()
    library = logging.getLogger("drsplat.test")
    with LibraryWarnings(messages):
        library.warning("this thread's warning")
        worker = threading.Thread(target=library.warning, args=("another thread's warning",))
        worker.start()
        worker.join()
    assert [m.text for m in messages] == ["this thread's warning"]


def test_a_query_waits_for_a_registration_where_numba_cannot_run_two_threads(state, tmp_path, monkeypatch):
    """Round 56e: under numba's workqueue threading layer a query (or a click) during the viewer's registration ran
    kernels beside the registration's and the process ended ("Concurrent access has been detected"). There they are
    refused while it runs, saying why; with omp or tbb they run."""
    import viewer.state
    from viewer.registration import RegistrationJob

    monkeypatch.setattr(viewer.state, "concurrent_kernels_safe", lambda: False)
    state._kernels_safe = None
    assert not state.kernels_safe()
    state.registration = RegistrationJob(output=tmp_path / "r.ply")  # running
    assert not state.run_oracle_query(0)
    assert "waits for the registration running" in state.messages[-1].text
    camera = state.cameras[0]
    assert state.pick(camera, camera.cx, camera.cy).size == 0 and "picking a splat waits" in state.messages[-1].text
    state.registration.finished = True
    assert state.run_oracle_query(0)
    state._kernels_safe, state.registration = True, RegistrationJob(output=tmp_path / "r.ply")
    assert state.run_oracle_query(0)


@pytest.mark.parametrize("rows", [1, 4, 5, 7, 8, 9, 31, 33])
def test_the_near_plane_reads_at_most_its_sample_of_rows(rows, monkeypatch):
    """Round 74c F2: the stride was rows // NEAR_SAMPLE, rounded down, so a scene of up to twice NEAR_SAMPLE rows was read
    whole and larger ones up to twice the sample: the stride is rounded up."""
    from viewer import camera

    read: list[int] = []
    robust_radius = camera._robust_radius
    monkeypatch.setattr(camera, "NEAR_SAMPLE", 4)
    monkeypatch.setattr(camera, "_robust_radius", lambda means, *rest: read.append(means.shape[0]) or robust_radius(means, *rest))
    means = np.random.default_rng(rows).normal(size=(rows, 3)).astype(np.float32)
    camera.scene_near_plane(means, np.zeros((rows, 3), np.float32))
    assert len(read) == 1 and read[0] <= 4 and read[0] == (rows if rows <= 4 else -(-rows // -(-rows // 4)))



def test_a_black_screenshot_is_judged_by_the_gaussians_its_mode_draws(state):
    """Round 81a F1: the black-screenshot check counted every centre in view, also the ones `--mode selection` does not
    draw, so a selection entirely off camera gave a black picture and no word. The check reads the drawn rows only."""
    from viewer.launch import centres_in_view, drawn_means

    assert state.run_oracle_query(0)
    cam = state.cameras[1]
    selected = state.selection.copy()
    assert centres_in_view(drawn_means(state, "selection"), cam)  # the demo's selection is in view of camera 1
    means = state.scene.means.copy()
    means[selected] -= 50.0 * np.asarray(cam.R, np.float32)[2]  # the selection moved behind the camera
    state.scene = dataclasses.replace(state.scene, means=means)
    assert not centres_in_view(drawn_means(state, "selection"), cam)
    assert centres_in_view(drawn_means(state, "hide_selection"), cam) and centres_in_view(drawn_means(state, "highlight"), cam)
