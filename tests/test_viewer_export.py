"""Exports that round-trip: the registered-PLY metadata column (drsplat.lang.plyformat), the
standard and drsplat export formats of `drsplat query --out` / `drsplat segment --ply` and of the
viewer, and a PLY whose header comments were dropped by another tool (splat-transform does)."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drsplat.lang import (
    META_PROPERTY,
    decode_meta_column,
    encode_meta_column,
    export_scene,
    field_metadata,
    read_field,
)
from drsplat.errors import InputError
from drsplat.lang.plyformat import META_LONG_MAX_BYTES
from drsplat.splat_formats import load_scene
from drsplat.scene import load_ply, save_ply
from tests.conftest import splat_transform_command


@pytest.fixture(scope="module")
def demo():
    from viewer.demo import demo_available, demo_dir

    assert demo_available(), "assets/demo is missing: rebuild it with `python -m viewer.demo`"
    return demo_dir() / "registered.ply", demo_dir()


@pytest.fixture(scope="module")
def query(demo):
    """(Q.npy path, oracle vector) of the demo's 'mug' label."""
    _, folder = demo
    names = json.loads((folder / "gt" / "label_names.json").read_text())
    return np.load(folder / "text_embeddings.npy")[names.index("mug")]


@given(st.text(alphabet=st.characters(min_codepoint=33, max_codepoint=0x2FF, blacklist_categories=("Cc", "Cf", "Cs", "Zl", "Zp")), min_size=1, max_size=300), st.integers(0, 400), st.randoms(use_true_random=False))
@settings(max_examples=60, deadline=None)
def test_meta_column_survives_reordering_and_subsets_keeping_each_position(text, extra_rows, rnd):
    data = text.encode()
    column = encode_meta_column(text, len(data) + extra_rows)
    assert column.dtype == (np.uint16 if len(data) <= 255 else np.uint32) and column.shape == (len(data) + extra_rows,)
    rows = list(range(column.size))
    rnd.shuffle(rows)
    assert decode_meta_column(column[rows]) == text
    # any subset keeping one row per position decodes: the first len(data) rows of a permutation of positions
    keep = sorted(rows[: column.size // 2], key=lambda i: i % len(data))
    positions = {i % len(data) for i in keep}
    if len(positions) == len(data):
        assert decode_meta_column(column[keep]) == text


def test_meta_column_refuses_what_it_cannot_carry():
    assert encode_meta_column("kind=pq", 3) is None, "fewer rows than bytes"
    assert encode_meta_column("x" * (META_LONG_MAX_BYTES + 1), META_LONG_MAX_BYTES + 10) is None
    longest = encode_meta_column("x" * META_LONG_MAX_BYTES, META_LONG_MAX_BYTES)
    assert longest.dtype == np.uint32 and longest.max() < 1 << 23, "a float32 copy of the column keeps every cell"
    assert decode_meta_column(longest.astype(np.float32)) == "x" * META_LONG_MAX_BYTES
    assert encode_meta_column("", 10) is None
    column = encode_meta_column("kind=pq dim=512", 100)
    assert decode_meta_column(column[column >> 8 != 3]) is None, "a lost position does not decode"


def test_majority_vote_outvotes_a_few_altered_rows():
    column = encode_meta_column("kind=exact dim=4", 1600)
    column[:5] = (column[:5] & 0xFF00) | ord("#")
    assert decode_meta_column(column) == "kind=exact dim=4"


def _strip_comments(src: Path, dst: Path, permute_seed: int | None = None) -> None:
    """What splat-transform's ply -> ply does to a drsplat PLY: properties and rows kept, header comments dropped
    (optionally rows reordered, as its --morton-order does)."""
    scene = load_ply(src)
    if permute_seed is not None:
        scene = scene.subset(np.random.default_rng(permute_seed).permutation(scene.num_gaussians))
    scene.comments.clear()
    save_ply(scene, dst)


def test_field_survives_a_tool_that_drops_header_comments(demo, query, tmp_path):
    registered, _ = demo
    scene = load_ply(registered)
    field = read_field(scene, registered)
    assert META_PROPERTY in scene.extra, "the shipped demo carries the metadata column"
    out = tmp_path / "no_comments.ply"
    _strip_comments(registered, out, permute_seed=3)
    shutil.copyfile(field.codebook.path, tmp_path / field.codebook.path.name)
    back_scene = load_ply(out)
    assert not any(c.startswith("drsplat.lang") for c in back_scene.comments)
    assert field_metadata(back_scene, out) == field_metadata(scene, registered)
    back = read_field(back_scene, out)
    assert back is not None and (back.kind, back.dim, back.clip_model) == (field.kind, field.dim, field.clip_model)
    order = np.random.default_rng(3).permutation(scene.num_gaussians)
    np.testing.assert_array_equal(back.scores(query[None])[:, 0], field.scores(query[None])[order, 0])


def test_a_long_codebook_name_keeps_its_field_through_a_tool_that_drops_comments(demo, query, tmp_path):
    """Round 56d: metadata over 255 bytes (a codebook name of 35 "é", 6 bytes each once URL-quoted) got no `lang_meta`
    column, without a word, so after splat-transform the file "has no language field ... run drsplat register first".
    Such metadata is carried in uint cells now (plain metadata keeps its ushort column, byte for byte)."""
    registered, _ = demo
    scene = load_ply(registered)
    field = read_field(scene, registered)
    name = tmp_path / ("é" * 40 + ".ply")
    export_scene(scene, field, name, "drsplat")
    written = load_ply(name)
    assert written.extra[META_PROPERTY].dtype == np.uint32 and scene.extra[META_PROPERTY].dtype == np.uint16
    from drsplat.commands.info import field_summary  # round 56e: `info` counted the uint column as 2 bytes a Gaussian

    assert field_summary(written, name)[0]["bytes_per_gaussian"] == field_summary(scene, registered)[0]["bytes_per_gaussian"] + 2
    out = tmp_path / "no_comments.ply"  # beside the export, whose codebook the metadata names
    _strip_comments(name, out, permute_seed=5)
    back = read_field(load_ply(out), out)
    # round 56e: a tool that narrows the uint column to ushort keeps each cell's low 16 bits: the text does not decode,
    # said so, not named as a made-up metadata entry
    narrowed = load_ply(out)
    narrowed.extra[META_PROPERTY] = narrowed.extra[META_PROPERTY].astype(np.uint16)
    save_ply(narrowed, tmp_path / "narrowed.ply")
    with pytest.raises(InputError, match=r"the language field's metadata column does not decode"):
        read_field(load_ply(tmp_path / "narrowed.ply"), tmp_path / "narrowed.ply")
    order = np.random.default_rng(5).permutation(scene.num_gaussians)
    np.testing.assert_array_equal(back.scores(query[None])[:, 0], field.scores(query[None])[order, 0])


def test_files_with_the_comment_only_still_read(demo, tmp_path):
    """PLYs written before the metadata column existed: the comment alone names the field."""
    registered, _ = demo
    scene = load_ply(registered)
    old = tmp_path / "old.ply"
    scene.extra.pop(META_PROPERTY)
    save_ply(scene, old)
    shutil.copyfile(registered.with_name("registered.codebook.faiss"), tmp_path / "registered.codebook.faiss")
    assert read_field(load_ply(old), old).kind == "pq"


def test_export_formats_standard_and_drsplat(demo, query, tmp_path):
    registered, _ = demo
    scene = load_ply(registered)
    field = read_field(scene, registered)
    mask = field.scores(query[None])[:, 0] > 0.2
    assert 0 < mask.sum() < scene.num_gaussians
    other = tmp_path / "elsewhere"
    other.mkdir()
    export_scene(scene.subset(mask), field.subset(mask), other / "std.ply", "standard")
    std = load_ply(other / "std.ply")
    # round 56d: SIBR reads the count from the third header line, where the demo's "drsplat.synthetic" comment was carried
    assert (other / "std.ply").read_bytes().split(b"\n")[2] == f"element vertex {int(mask.sum())}".encode() and not std.comments
    assert std.extra == {} and read_field(std, other / "std.ply") is None, "standard: INRIA layout only"
    export_scene(scene.subset(mask), field.subset(mask), other / "sel.ply", "drsplat")
    assert (other / "sel.codebook.faiss").is_file(), "the codebook is copied beside the export"
    back = read_field(load_ply(other / "sel.ply"), other / "sel.ply")
    np.testing.assert_array_equal(back.scores(query[None]), field.subset(mask).scores(query[None]))
    with pytest.raises(ValueError, match="format"):
        export_scene(scene, field, other / "x.ply", "splat")


def test_cli_query_can_query_its_own_drsplat_export(demo, query, tmp_path, capsys):
    from drsplat.cli import main

    registered, _ = demo
    q = tmp_path / "q.npy"
    np.save(q, query)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    assert main(["query", str(registered), "--embedding", str(q), "--out", str(out_dir / "mug.ply"), "--format", "drsplat"]) == 0
    first = capsys.readouterr().out
    count = int(first.split()[0])
    assert main(["query", str(out_dir / "mug.ply"), "--embedding", str(q), "--threshold", "-1"]) == 0
    assert f"{count} of {count} Gaussians" in capsys.readouterr().out
    assert main(["query", str(registered), "--embedding", str(q), "--out", str(out_dir / "std.ply")]) == 0
    assert main(["query", str(out_dir / "std.ply"), "--embedding", str(q)]) == 1, "the standard export has no field"


def test_cli_segment_prints_the_dataset_label_names_and_exports(demo, tmp_path, capsys):
    from drsplat.cli import main

    registered, folder = demo
    names = json.loads((folder / "gt" / "label_names.json").read_text())
    assert main(["segment", str(registered), "--embeddings", str(folder / "text_embeddings.npy"), "--out", str(tmp_path / "l.npy"),
                 "--ply", str(tmp_path / "seg.ply"), "--format", "drsplat"]) == 0
    printed = capsys.readouterr().out
    assert all(name in printed for name in names) and "label_0" not in printed
    assert read_field(load_ply(tmp_path / "seg.ply"), tmp_path / "seg.ply") is not None
    # round 56d: the coloured scene keeps its SH degree (3), the rest zero: INRIA's loader asserts 45 f_rest columns
    coloured = load_ply(tmp_path / "seg.ply")
    assert coloured.sh.shape[1] == load_ply(registered).sh.shape[1] == 16 and not coloured.sh[:, 1:].any()
    # round 56e: a .compressed.ply stores no exact 0 (its rest read back 0.0156 and tinted every label): degree 0 there
    assert main(["segment", str(registered), "--embeddings", str(folder / "text_embeddings.npy"), "--out", str(tmp_path / "l3.npy"),
                 "--ply", str(tmp_path / "seg.compressed.ply")]) == 0
    compressed = load_scene(tmp_path / "seg.compressed.ply")  # its rows in the format's own order: each a label's colour
    assert compressed.sh.shape[1] == 1
    palette = np.unique(coloured.sh[:, 0], axis=0)
    assert np.abs(compressed.sh[:, 0][:, None, :] - palette[None]).max(axis=2).min(axis=1).max() < 0.02
    bad = tmp_path / "names.json"
    bad.write_text(json.dumps(["a", "b"]))
    assert main(["segment", str(registered), "--embeddings", str(folder / "text_embeddings.npy"), "--names", str(bad), "--out", str(tmp_path / "l2.npy")]) == 1
    assert "names.json" in capsys.readouterr().err


def test_viewer_exports_both_formats(demo, query, tmp_path):
    from viewer.state import ViewerState

    registered, folder = demo
    state = ViewerState()
    assert state.load_scene(registered) and state.load_source(folder)
    assert state.run_oracle_query(state.oracle.names.index("mug"))
    (tmp_path / "a" / "dir.ply").mkdir(parents=True)
    assert state.export_selection(tmp_path / "a" / "dir.ply", "drsplat") is None
    assert "export to" in state.messages[-1].text, "a write failure is a reported error, not a traceback"
    n = state.export_selection(tmp_path / "a" / "mug.ply", "drsplat")
    assert n == int(state.selection.sum()) > 0
    back = read_field(load_ply(tmp_path / "a" / "mug.ply"), tmp_path / "a" / "mug.ply")
    np.testing.assert_array_equal(back.scores(query[None]), state.field.subset(state.selection).scores(query[None]))
    assert state.export_selection(tmp_path / "a" / "std.ply", "standard") == n
    assert load_ply(tmp_path / "a" / "std.ply").extra == {}
    assert state.export_selection(registered, "standard") is None, "never over the loaded scene"
    assert registered.with_name("registered.codebook.faiss").is_file()
    # round 60a: onto a write-protected export, the PLY was refused at its rename after its codebook had been replaced
    book = tmp_path / "a" / "mug.codebook.faiss"
    book.write_bytes(b"another codebook")
    (tmp_path / "a" / "mug.ply").chmod(0o444)
    try:
        assert state.export_selection(tmp_path / "a" / "mug.ply", "drsplat") is None
        assert "exists and is write-protected" in state.messages[-1].text and book.read_bytes() == b"another codebook"
    finally:
        (tmp_path / "a" / "mug.ply").chmod(0o644)


def test_cli_exports_splat_and_spz_by_the_name(demo, query, tmp_path, capsys):
    """`query --out` and `segment --ply` write .splat / .spz when the name ends so (the selection, in
    its order); a drsplat export named .spz is a usage error before anything is read or written."""
    from drsplat.cli import main
    from drsplat.splat_formats import load_scene, scene_format

    registered, folder = demo
    q = tmp_path / "q.npy"
    np.save(q, query)
    assert main(["query", str(registered), "--embedding", str(q), "--out", str(tmp_path / "mug.ply")]) == 0
    count = int(capsys.readouterr().out.split()[0])
    reference = load_ply(tmp_path / "mug.ply")
    for name in ("mug.spz", "mug.splat", "mug.compressed.ply"):
        assert main(["query", str(registered), "--embedding", str(q), "--out", str(tmp_path / name)]) == 0
        assert f"({'.' + name.split('.', 1)[1]})" in capsys.readouterr().err
        back = load_scene(tmp_path / name)
        assert scene_format(tmp_path / name) == name.split(".")[-1] and back.num_gaussians == count
        if not name.endswith(".compressed.ply"):  # which keeps the splats in Morton order
            assert np.abs(back.means - reference.means).max() <= (0 if name.endswith(".splat") else 2.0 ** -13)
    assert main(["query", str(registered), "--embedding", str(q), "--out", str(tmp_path / "f.spz"), "--format", "drsplat"]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "f.spz" in err and "drsplat export is a PLY" in err and not (tmp_path / "f.spz").exists()
    for name in ("sel.codebook.faiss", "sel.npy"):  # round 41, left as found then: a PLY was written under such a name
        assert main(["query", str(registered), "--embedding", str(q), "--out", str(tmp_path / name)]) == 2
        assert f"a {Path(name).suffix} name would hold a PLY" in capsys.readouterr().err and not (tmp_path / name).exists()
    assert main(["segment", str(registered), "--embeddings", str(folder / "text_embeddings.npy"), "--out", str(tmp_path / "l.npy"),
                 "--ply", str(tmp_path / "seg.spz")]) == 0
    assert load_scene(tmp_path / "seg.spz").num_gaussians == load_ply(registered).num_gaussians


def test_viewer_exports_spz_and_refuses_a_drsplat_spz(demo, tmp_path):
    from drsplat.splat_formats import load_scene
    from viewer.state import ViewerState

    registered, folder = demo
    state = ViewerState()
    assert state.load_scene(registered) and state.load_source(folder)
    assert state.run_oracle_query(state.oracle.names.index("mug"))
    n = state.export_selection(tmp_path / "mug.spz", "standard")
    assert n == int(state.selection.sum()) > 0 and load_scene(tmp_path / "mug.spz").num_gaussians == n
    assert "(.spz)" in state.messages[-1].text
    assert state.export_selection(tmp_path / "f.spz", "drsplat") is None
    assert "drsplat export is a PLY" in state.messages[-1].text and not (tmp_path / "f.spz").exists()


@pytest.fixture
def demo_copy(demo, tmp_path):
    """The demo's registered PLY and codebook copied, with the ids of its unassigned Gaussians."""
    registered, folder = demo
    shutil.copy(registered, tmp_path / "reg.ply")
    shutil.copy(registered.with_name("registered.codebook.faiss"), tmp_path / "reg.codebook.faiss")
    scene = load_ply(tmp_path / "reg.ply")
    scene.comments = [c.replace("registered.codebook.faiss", "reg.codebook.faiss") for c in scene.comments]
    save_ply(scene, tmp_path / "reg.ply")
    unassigned = np.flatnonzero(scene.extra["lang_norm"] == 0)
    assert read_field(scene, tmp_path / "reg.ply").kind == "pq" and 0 < unassigned.size < scene.num_gaussians
    return tmp_path / "reg.ply", unassigned


def test_query_never_selects_ranks_or_averages_gaussians_without_a_feature(demo_copy, query, tmp_path, capsys):
    """A PQ row's codes decode to some vector even when the Gaussian is unassigned (norm 0), and such a
    Gaussian scores 0 as a cosine and scored exactly ½ as a relevancy (0 since round 75c): `--gaussians` of unassigned
    ids made a query of them, and the default relevancy threshold (0.5) exported them, exit 0."""
    from drsplat.cli import main

    reg, unassigned = demo_copy
    np.save(tmp_path / "u.npy", unassigned)
    assert main(["query", str(reg), "--gaussians", str(tmp_path / "u.npy"), "--top", "3"]) == 1
    assert "none of the selected Gaussians has a language feature" in capsys.readouterr().err
    q, neg = tmp_path / "q.npy", tmp_path / "neg.npy"
    np.save(q, query)
    np.save(neg, -query[None])
    assert main(["query", str(reg), "--embedding", str(q), "--relevancy", "--negative-embeddings", str(neg), "--scores",
                 str(tmp_path / "rel.npy"), "--out", str(tmp_path / "sel.ply")]) == 0
    printed = capsys.readouterr().out
    rel = np.load(tmp_path / "rel.npy")
    assert np.all(rel[unassigned] == 0)
    picked = np.count_nonzero(rel >= 0.5)
    assert load_ply(tmp_path / "sel.ply").num_gaussians == picked and f"{unassigned.size} Gaussians without a language feature left out" in printed
    assert main(["query", str(reg), "--embedding", str(q), "--threshold", "-1", "--top", "5"]) == 0
    assert f"{load_ply(reg).num_gaussians - unassigned.size} of" in capsys.readouterr().out


def test_query_of_a_field_with_no_feature_at_all_is_one_error(demo_copy, query, tmp_path, capsys):
    """Every Gaussian unassigned: the automatic threshold was 0 and every Gaussian was written, exit 0."""
    from drsplat.cli import main

    reg, _ = demo_copy
    scene = load_ply(reg)
    scene.extra["lang_norm"][:] = 0
    scene.extra["lang_weight"][:] = 0
    save_ply(scene, reg)
    np.save(tmp_path / "q.npy", query)
    for extra in (["--out", str(tmp_path / "sel.ply")], ["--top", "3"]):
        assert main(["query", str(reg), "--embedding", str(tmp_path / "q.npy"), *extra]) == 1
        assert "none of its 2,763 Gaussians has a language feature" in capsys.readouterr().err
    assert not (tmp_path / "sel.ply").exists()


def test_viewer_selection_leaves_gaussians_without_a_feature_out(demo, tmp_path):
    from viewer.state import ViewerState

    registered, folder = demo
    state = ViewerState()
    assert state.load_scene(registered) and state.load_source(folder)
    assert state.run_oracle_query(state.oracle.names.index("mug"))
    unassigned = ~state.field.assigned()
    assert unassigned.any()
    state.set_threshold(float(state.query.scores.min()) - 1.0)
    assert state.selection.sum() == (~unassigned).sum() and not state.selection[unassigned].any()
    assert state.export_selection(tmp_path / "all.ply", "standard") == int((~unassigned).sum())


def test_lut_bits_8_where_it_cannot_apply_scores_exactly_with_a_warning(demo, query, tmp_path, capsys):
    """8-bit tables are a CPU kernel for at most 257 sub-vectors: with the torch engine (the default on
    a CUDA machine), an exact field or a codebook of M = 512 it was a ValueError traceback."""
    import argparse
    import types

    from drsplat.cli import main
    from drsplat.commands.common import lut_bits_for

    registered, _ = demo
    np.save(tmp_path / "q.npy", query)
    base = ["query", str(registered), "--embedding", str(tmp_path / "q.npy")]
    assert main(base + ["--scores", str(tmp_path / "exact.npy"), "--engine", "torch", "--device", "cpu"]) == 0
    assert main(base + ["--scores", str(tmp_path / "torch8.npy"), "--lut-bits", "8", "--engine", "torch", "--device", "cpu"]) == 0
    assert "--lut-bits 8: the torch engine scores with float32 tables" in capsys.readouterr().err
    np.testing.assert_array_equal(np.load(tmp_path / "torch8.npy"), np.load(tmp_path / "exact.npy"))
    args = argparse.Namespace(lut_bits=8)
    wide = types.SimpleNamespace(codebook=types.SimpleNamespace(m=512))
    assert lut_bits_for(args, wide, None) == 32 and "codebook has 512" in capsys.readouterr().err
    assert lut_bits_for(args, types.SimpleNamespace(codebook=None), None) == 32 and "exact features" in capsys.readouterr().err
    assert lut_bits_for(args, types.SimpleNamespace(codebook=types.SimpleNamespace(m=128)), None) == 8


@pytest.mark.parametrize("entry", ["codebook=x%0AERROR:%20forged%20line%0A", "codebook=%1B[2J%1B[31mred", "clip=bad%0Amodel/x",
                                   "codebook=reg.codebook.faiss%00", "clip=a%E2%80%AEb"])
def test_hidden_characters_in_the_field_metadata_are_one_error(demo_copy, query, tmp_path, capsys, entry):
    """The header's URL-quoted values reached the terminal raw: a %0A forged an extra 'ERROR:' line,
    %1B sent escape codes, U+202E reversed the text after it."""
    from drsplat.cli import main

    reg, _ = demo_copy
    scene = load_ply(reg)
    key = entry.split("=")[0]
    (i,) = [j for j, c in enumerate(scene.comments) if c.startswith("drsplat.lang ")]
    words = [w for w in scene.comments[i].split() if not w.startswith(key + "=")]
    scene.comments[i] = " ".join(words + [entry])
    save_ply(scene, reg)
    np.save(tmp_path / "q.npy", query)
    assert main(["query", str(reg), "--embedding", str(tmp_path / "q.npy")]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "\x1b" not in err and "\u202e" not in err
    assert "reg.ply" in err and "holds a" in err and "(the file was altered)" in err


def test_a_ply_property_name_with_a_control_character_is_one_error(tmp_path, capsys):
    from drsplat.cli import main

    path = tmp_path / "esc.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\x1b[2J\nend_header\n")
    assert main(["info", str(path)]) == 1
    err = capsys.readouterr().err
    assert "\x1b" not in err and "header line 4 (property) holds a control character (U+001B)" in err


def test_field_survives_a_real_splat_transform_round_trip(demo, query, tmp_path):
    """PlayCanvas splat-transform (npm) ply -> ply, plain and Morton-reordered: the field is read back."""
    command = splat_transform_command()
    registered, _ = demo
    field = read_field(load_ply(registered), registered)
    src = tmp_path / "mug.ply"
    export_scene(load_ply(registered), field, src, "drsplat")
    for name, flags in (("plain.ply", []), ("morton.ply", ["-M"])):
        subprocess.run([*command, "-q", "-w", str(src), *flags, str(tmp_path / name)], check=True, timeout=120, capture_output=True)
        converted = load_ply(tmp_path / name)
        assert not any(c.startswith("drsplat.lang") for c in converted.comments), "splat-transform drops comments"
        back = read_field(converted, tmp_path / name)
        assert back is not None and back.kind == field.kind
        assert np.allclose(np.sort(back.scores(query[None])[:, 0]), np.sort(field.scores(query[None])[:, 0]))
