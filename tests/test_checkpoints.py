"""Trainer checkpoints as scenes: gsplat's simple_trainer `.pt` (which writes no PLY unless asked)
and nerfstudio's splatfacto `.ckpt`, read with torch.load's weights_only."""

from __future__ import annotations

import dataclasses

import logging
import pickle
import re

import numpy as np
import pytest
import torch

from drsplat.cli import main
from drsplat.errors import InputError
from drsplat.scene import GaussianScene, dc_from_rgb, save_ply
from drsplat.splat_formats import load_scene, load_scene_report


def random_scene(n: int = 50, degree: int = 3, seed: int = 0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    return GaussianScene(means=rng.normal(size=(n, 3)).astype(np.float32), quats=rng.normal(size=(n, 4)).astype(np.float32),
                         log_scales=rng.normal(-3, 1, size=(n, 3)).astype(np.float32), opacity_logits=rng.normal(size=n).astype(np.float32),
                         sh=rng.normal(size=(n, k, 3)).astype(np.float32), extra={}, comments=[])


def gsplat_checkpoint(scene: GaussianScene) -> dict:
    """What gsplat's simple_trainer saves (`{"step", "splats": state_dict}`, plus optimizer state)."""
    t = torch.from_numpy
    splats = {"means": t(scene.means), "scales": t(scene.log_scales), "quats": t(scene.quats), "opacities": t(scene.opacity_logits),
              "sh0": t(scene.sh[:, :1].copy()), "shN": t(scene.sh[:, 1:].copy())}
    return {"step": 29999, "splats": splats, "optimizers": {"means": {"state": {}, "param_groups": [{"lr": 1.6e-4, "eps": 1e-15}]}}}


def nerfstudio_checkpoint(scene: GaussianScene) -> dict:
    """What nerfstudio's splatfacto saves: the pipeline's state dict, Gaussians under _model.gauss_params."""
    t, p = torch.from_numpy, "_model.gauss_params."
    pipeline = {p + "means": t(scene.means), p + "scales": t(scene.log_scales), p + "quats": t(scene.quats),
                p + "opacities": t(scene.opacity_logits[:, None].copy()), p + "features_dc": t(scene.sh[:, 0].copy()),
                p + "features_rest": t(scene.sh[:, 1:].copy()), "_model.camera_optimizer.pose_adjustment": torch.zeros(3, 6)}
    return {"step": 29999, "pipeline": pipeline, "optimizers": {}, "scalers": {}}


def nerfstudio_1_0_checkpoint(scene: GaussianScene) -> dict:
    """Splatfacto before its gauss_params (nerfstudio 1.0): the Gaussians as _model.means, ... (round 87a F4: called a NeRF)."""
    ckpt = nerfstudio_checkpoint(scene)
    ckpt["pipeline"] = {k.replace("_model.gauss_params.", "_model."): v for k, v in ckpt["pipeline"].items()}
    return ckpt


@pytest.mark.parametrize("make, name, layout", [(gsplat_checkpoint, "ckpt_29999_rank0.pt", "gsplat checkpoint"),
                                                (nerfstudio_checkpoint, "step-000029999.ckpt", "nerfstudio checkpoint"),
                                                (nerfstudio_1_0_checkpoint, "step-000029999.ckpt", "nerfstudio 1.0 checkpoint")])
@pytest.mark.parametrize("degree", [0, 3])
def test_a_trainer_checkpoint_reads_as_the_scene_it_holds(tmp_path, make, name, layout, degree):
    """Every attribute comes back bit for bit, and the scene writes the same PLY bytes as the scene
    itself: what gsplat's export_splats or ns-export would have written."""
    scene = random_scene(degree=degree)
    torch.save(make(scene), tmp_path / name)
    loaded, report = load_scene_report(tmp_path / name)
    assert report.layout == layout and report.sh_degree == degree
    if degree == 0 and layout != "gsplat checkpoint":
        # round 87b F6: splatfacto at SH degree 0 keeps colour logits (nerfstudio draws their sigmoid), not SH
        from drsplat.scene import dc_from_rgb

        want = dc_from_rgb(1.0 / (1.0 + np.exp(-scene.sh[:, 0].astype(np.float64))))[:, None, :].astype(np.float32)
        np.testing.assert_array_equal(loaded.sh, want)
        scene = dataclasses.replace(scene, sh=want)
    for field in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert np.array_equal(getattr(loaded, field), getattr(scene, field)), field
    save_ply(scene, tmp_path / "a.ply")
    save_ply(loaded, tmp_path / "b.ply")
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()


def test_half_precision_and_non_finite_rows_follow_the_ply_rules(tmp_path):
    """A bfloat16 / float16 checkpoint is widened to float32; a row with NaN is dropped and counted,
    as a PLY's would be."""
    scene = random_scene()
    ckpt = gsplat_checkpoint(scene)
    ckpt["splats"]["means"] = ckpt["splats"]["means"].to(torch.bfloat16)
    ckpt["splats"]["sh0"] = ckpt["splats"]["sh0"].half()
    ckpt["splats"]["scales"][7, 1] = float("nan")
    torch.save(ckpt, tmp_path / "c.pt")
    loaded, report = load_scene_report(tmp_path / "c.pt")
    assert report.dropped_nan_rows == 1 and loaded.num_gaussians == 49
    keep = np.arange(50) != 7
    assert np.array_equal(loaded.means, torch.from_numpy(scene.means).to(torch.bfloat16).float().numpy()[keep])
    assert np.array_equal(loaded.sh[:, 0], torch.from_numpy(scene.sh[:, 0]).half().float().numpy()[keep])


def test_gsplats_appearance_model_reads_its_base_colour(tmp_path, caplog):
    """With app_opt gsplat keeps colors (logits) and features instead of SH: the base colour
    sigmoid(colors) becomes the DC term, with one warning that the view-dependent part is not read."""
    scene = random_scene(degree=0)
    ckpt = gsplat_checkpoint(scene)
    del ckpt["splats"]["sh0"], ckpt["splats"]["shN"]
    colors = np.random.default_rng(1).normal(size=(50, 3)).astype(np.float32)
    ckpt["splats"]["colors"], ckpt["splats"]["features"] = torch.from_numpy(colors), torch.zeros(50, 32)
    torch.save(ckpt, tmp_path / "app.pt")
    with caplog.at_level(logging.WARNING, logger="drsplat.splat_formats"):
        loaded = load_scene(tmp_path / "app.pt")
    assert "appearance model" in caplog.text
    np.testing.assert_allclose(loaded.sh[:, 0], dc_from_rgb(1 / (1 + np.exp(-colors.astype(np.float64)))), rtol=1e-6)


class NotATensor:  # a class only a full unpickler would build: weights_only refuses it
    pass


def _bad(case: str, tmp_path):
    scene = random_scene()
    ckpt = gsplat_checkpoint(scene)
    s = ckpt["splats"]
    if case == "code":
        ckpt["hook"] = NotATensor()
    elif case == "missing":
        del s["quats"]
    elif case == "shape":
        s["means"] = s["means"][:, :2].clone()
    elif case == "rows":
        s["scales"] = s["scales"][:40].clone()
    elif case == "degree":
        s["shN"] = s["shN"][:, :5].clone()
    elif case == "integer":
        s["opacities"] = torch.zeros(50, dtype=torch.int64)
    elif case == "other":
        ckpt = {"state_dict": {"weight": torch.zeros(3)}}
    elif case == "no means":  # round 85b F9: told it held no 'splats', its entries then listing splats
        del s["means"]
    elif case == "1.0 no means":  # round 87b F7: named the other layout's key
        ckpt = {"pipeline": {k.replace("_model.gauss_params.", "_model."): v for k, v in nerfstudio_checkpoint(scene)["pipeline"].items()
                             if not k.endswith("means")}}
    elif case == "nerfacto":  # round 86c F4: a NeRF's checkpoint was told it lacked its Gaussians' means, as if damaged
        ckpt = {"pipeline": {"_model.field.mlp_base.params": torch.zeros(3)}, "step": 1}
    path = tmp_path / f"{case}.pt"
    torch.save(ckpt, path)
    return path


@pytest.mark.parametrize("case, words", [
    ("code", r"holds something other than tensors and plain values, which is not read \(a reference to tests.test_checkpoints.NotATensor\)"),
    ("missing", r"field 'quats': has no such entry"),
    ("shape", r"field 'means': has shape \[50, 2\], expected \[N, 3\]"),
    ("rows", r"field 'scales': has 40 rows but means has 50"),
    ("degree", r"field 'shN': has 5 higher SH coefficients"),
    ("integer", r"field 'opacities': is a Tensor of torch.int64, not a floating-point tensor"),
    ("other", "holds neither a gsplat checkpoint's 'splats' nor a nerfstudio one's"),
    ("no means", r"field 'splats.means': is a gsplat checkpoint whose 'splats' has no 'means' \(it holds opacities, quats, scales, sh0, shN\)"),
    ("1.0 no means", r"field 'pipeline._model.means': is a nerfstudio 1.0 checkpoint whose 'pipeline' has no '_model.means'"),
    ("nerfacto", r"is a nerfstudio checkpoint of a model without Gaussians \(its 'pipeline' holds no '_model.gauss_params.\*': "
                 r"_model.field.mlp_base.params\): a NeRF such as nerfacto, not splatfacto"),
])
def test_a_bad_checkpoint_is_one_error_naming_the_file_and_field(tmp_path, case, words):
    path = _bad(case, tmp_path)
    with pytest.raises(InputError, match=words) as err:
        load_scene(path)
    assert str(path) in str(err.value)


def test_a_file_named_like_a_checkpoint_that_is_not_one(tmp_path):
    """Not a zip archive (a legacy pickle, text): one error naming it; nothing is unpickled."""
    legacy = tmp_path / "legacy.pt"
    legacy.write_bytes(pickle.dumps({"splats": {}}))
    with pytest.raises(InputError, match="not a torch checkpoint archive"):
        load_scene(legacy)
    cut = tmp_path / "cut.pt"
    torch.save(gsplat_checkpoint(random_scene()), cut)
    cut.write_bytes(cut.read_bytes()[:600])
    with pytest.raises(InputError, match="cannot be read as a torch checkpoint"):
        load_scene(cut)


def test_drsplat_info_reads_a_gsplat_checkpoint(tmp_path, capsys):
    torch.save(gsplat_checkpoint(random_scene(n=20, degree=1)), tmp_path / "ckpt_6999_rank0.pt")
    assert main(["info", str(tmp_path / "ckpt_6999_rank0.pt")]) == 0
    out = capsys.readouterr().out
    assert "(gsplat checkpoint layout)" in out and re.search(r"gaussians\s+20 \(rows in file 20\)", out) and re.search(r"SH degree\s+1\b", out)


def test_a_checkpoint_given_where_a_registered_scene_is_needed_is_named_as_one(tmp_path, capsys):
    torch.save(gsplat_checkpoint(random_scene(n=20)), tmp_path / "ckpt.pt")
    assert main(["query", str(tmp_path / "ckpt.pt"), "--text", "a chair"]) == 1
    assert "is a trainer checkpoint, not a registered scene" in capsys.readouterr().err


def test_an_empty_checkpoint_says_there_is_nothing_to_register(tmp_path):
    torch.save(gsplat_checkpoint(random_scene(n=0)), tmp_path / "empty.pt")
    with pytest.raises(InputError, match="holds no Gaussians"):
        load_scene_report(tmp_path / "empty.pt", purpose="register")
    for name in ("a_folder.pt", "another.ckpt"):
        (tmp_path / name).mkdir()
        with pytest.raises(InputError, match="is not a file"):
            load_scene(tmp_path / name)


def _rewritten(path, name: str, data: bytes | None):
    """The torch archive at `path` with its member ending in `name` replaced by `data` (None: cut to 8 bytes)."""
    import zipfile

    with zipfile.ZipFile(path) as z:
        members = {i.filename: z.read(i.filename) for i in z.infolist()}
    member = next(m for m in members if m.endswith(name))
    members[member] = members[member][:8] if data is None else data
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        for m, content in members.items():
            z.writestr(m, content)


@pytest.mark.parametrize("case, words", [
    ("short record", r"cannot be read as a torch checkpoint \(RuntimeError: record size \(8 bytes\)"),
    ("bad persistent id", r"cannot be read as a torch checkpoint \(AssertionError"),
])
def test_a_damaged_archive_is_refused_not_read_from_its_neighbours_bytes(tmp_path, case, words):
    """Round 23: read memory-mapped, torch checked no record's size, so a tensor record cut short
    read the bytes after it as its values and loaded with exit 0. Read whole, a short record is
    refused; torch's other failures on a damaged pickle (an assertion, a KeyError) are one error too."""
    path = tmp_path / "c.pt"
    torch.save(gsplat_checkpoint(random_scene()), path)
    if case == "short record":
        _rewritten(path, "data/0", None)
    else:
        _rewritten(path, "data.pkl", b"\x80\x02K\x05Q.")  # a persistent id that is an int, not the tuple torch writes
    with pytest.raises(InputError, match=words):
        load_scene(path)


def test_a_tensor_expanded_over_one_row_cannot_declare_a_billion(tmp_path):
    """Round 23: an expanded tensor is a few bytes on disk and declares any N; made dense it asked
    for 11 GB. Refused before any copy, naming the field."""
    ckpt = gsplat_checkpoint(random_scene(n=1))
    for key in ("means", "scales", "quats", "opacities", "sh0", "shN"):
        ckpt["splats"][key] = ckpt["splats"][key].expand(1_000_000_000, *ckpt["splats"][key].shape[1:])
    torch.save(ckpt, tmp_path / "bomb.pt")
    assert (tmp_path / "bomb.pt").stat().st_size < 10_000
    with pytest.raises(InputError, match=r"field 'means': declares 3,000,000,000 values but stores 12 bytes"):
        load_scene(tmp_path / "bomb.pt")


def test_sparse_meta_none_and_negative_views(tmp_path):
    """A sparse or meta tensor is one error naming the field; None is named as what it is (not as a
    missing entry); a negative view reads as its values."""
    scene = random_scene()
    cases = {"sparse": lambda t: t.to_sparse(), "meta": lambda t: torch.empty_like(t, device="meta"), "none": lambda t: None}
    words = {"sparse": "is a torch.sparse_coo tensor on cpu, not a dense one", "meta": "is a torch.strided tensor on meta, not a dense one",
             "none": "is a NoneType, not a floating-point tensor"}
    import warnings

    for name, change in cases.items():
        ckpt = gsplat_checkpoint(scene)
        ckpt["splats"]["means"] = change(ckpt["splats"]["means"])
        torch.save(ckpt, tmp_path / f"{name}.pt")
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # round 41: torch's own UserWarning on the sparse tensor came before the error
            with pytest.raises(InputError, match=f"field 'means': {words[name]}"):
                load_scene(tmp_path / f"{name}.pt")
    ckpt = gsplat_checkpoint(scene)
    ckpt["splats"]["means"] = torch._neg_view(-ckpt["splats"]["means"])
    torch.save(ckpt, tmp_path / "neg.pt")
    assert np.array_equal(load_scene(tmp_path / "neg.pt").means, scene.means)


def test_intact_archives_are_read_mapped_and_a_compressed_one_whole(tmp_path):
    """What torch.save writes has its records stored and sized as its storages, so it is read
    memory-mapped (a checkpoint with its optimiser's state is not read whole); an archive rewritten
    with compressed records, which the mapped read took as raw values, is read whole and right."""
    import zipfile

    from drsplat.splat_formats import _archive_records, _records_intact

    scene = random_scene()
    for name, ckpt in (("g.pt", gsplat_checkpoint(scene)), ("n.ckpt", nerfstudio_checkpoint(scene))):
        torch.save(ckpt, tmp_path / name)
        assert _records_intact(_archive_records(tmp_path / name), torch.load(tmp_path / name, weights_only=True, mmap=True))
    with zipfile.ZipFile(tmp_path / "g.pt") as z:
        members = {i.filename: z.read(i.filename) for i in z.infolist()}
    with zipfile.ZipFile(tmp_path / "deflated.pt", "w", zipfile.ZIP_DEFLATED) as z:
        for member, content in members.items():
            z.writestr(member, content)
    assert not _records_intact(_archive_records(tmp_path / "deflated.pt"), torch.load(tmp_path / "deflated.pt", weights_only=True, mmap=True))
    assert np.array_equal(load_scene(tmp_path / "deflated.pt").means, scene.means)


def test_a_flipped_byte_is_caught_by_the_records_crc(tmp_path):
    """Round 23: torch reads records without their CRC-32, so one flipped byte in a tensor's record
    (a copy damaged in transfer) loaded as a wrong value with exit 0. Every record's CRC is checked
    first; a damaged record header (its name) is named as such too."""
    import zipfile

    torch.save(gsplat_checkpoint(random_scene()), tmp_path / "c.pt")
    data = bytearray((tmp_path / "c.pt").read_bytes())
    with zipfile.ZipFile(tmp_path / "c.pt") as z:
        record = next(i for i in z.infolist() if i.filename.endswith("data/0"))
    start = record.header_offset + 30 + len(record.filename.encode()) + int.from_bytes(data[record.header_offset + 28:record.header_offset + 30], "little")
    flipped = bytearray(data)
    flipped[start + 5] ^= 0x40
    (tmp_path / "flipped.pt").write_bytes(bytes(flipped))
    with pytest.raises(InputError, match=r"its record \S+/data/0 fails its CRC-32 check"):
        load_scene(tmp_path / "flipped.pt")
    renamed = bytearray(data)
    renamed[record.header_offset + 31] = 0x82  # not UTF-8: the local header's name cannot be read
    (tmp_path / "renamed.pt").write_bytes(bytes(renamed))
    with pytest.raises(InputError, match="has a damaged record header"):
        load_scene(tmp_path / "renamed.pt")


def test_a_gsplat_run_on_several_gpus_is_read_whole_from_its_rank_shares(tmp_path, caplog):
    """gsplat on W GPUs gives rank r the Gaussians [r::W] and saves ckpt_<step>_rank<r>.pt each; any
    one of them given as the scene reads every rank's share, joined in rank order (as gsplat's own
    viewer joins them). A missing rank is one error naming it; other steps' files are not mixed in."""
    scene = random_scene(n=30, degree=2)
    shares = [np.arange(30)[r::3] for r in range(3)]
    for r, rows in enumerate(shares):
        part = GaussianScene(means=scene.means[rows], quats=scene.quats[rows], log_scales=scene.log_scales[rows],
                             opacity_logits=scene.opacity_logits[rows], sh=scene.sh[rows], extra={}, comments=[])
        torch.save(gsplat_checkpoint(part), tmp_path / f"ckpt_29999_rank{r}.pt")
    torch.save(gsplat_checkpoint(random_scene(n=7)), tmp_path / "ckpt_6999_rank0.pt")  # another step of the run
    order = np.concatenate(shares)
    with caplog.at_level(logging.INFO, logger="drsplat.splat_formats"):
        loaded, report = load_scene_report(tmp_path / "ckpt_29999_rank1.pt")
    assert report.layout == "gsplat checkpoint (3 ranks)" and "3 per-GPU shares" in caplog.text
    for field in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert np.array_equal(getattr(loaded, field), getattr(scene, field)[order]), field
    assert load_scene(tmp_path / "ckpt_6999_rank0.pt").num_gaussians == 7
    (tmp_path / "ckpt_29999_rank1.pt").unlink()
    with pytest.raises(InputError, match=r"the share of rank 1 \(ckpt_29999_rank1.pt\) is not beside it"):
        load_scene(tmp_path / "ckpt_29999_rank2.pt")


def test_a_deflated_record_of_zeros_cannot_ask_for_what_the_file_does_not_hold(tmp_path):
    """Review of round 23: a whole read inflates compressed records, and deflate packs zeros ~1000:1,
    so a 30 KB file could have torch allocate 32 MB (a 1 GB file, 1 TB). Records that would inflate
    past MAX_CHECKPOINT_INFLATION times the file are refused before torch reads any."""
    import zipfile

    from drsplat.splat_formats import MAX_CHECKPOINT_INFLATION

    ckpt = gsplat_checkpoint(random_scene(n=1))
    ckpt["splats"]["padding"] = torch.zeros(8_000_000)
    torch.save(ckpt, tmp_path / "plain.pt")
    with zipfile.ZipFile(tmp_path / "plain.pt") as z:
        members = {i.filename: z.read(i.filename) for i in z.infolist()}
    with zipfile.ZipFile(tmp_path / "bomb.pt", "w", zipfile.ZIP_DEFLATED) as z:
        for member, content in members.items():
            z.writestr(member, content)
    size = (tmp_path / "bomb.pt").stat().st_size
    assert 32_000_000 > MAX_CHECKPOINT_INFLATION * size
    with pytest.raises(InputError, match=rf"declares [\d,]+ bytes of records in a {size:,}-byte file, more than {MAX_CHECKPOINT_INFLATION}:1"):
        load_scene(tmp_path / "bomb.pt")
    assert load_scene(tmp_path / "plain.pt").num_gaussians == 1  # stored, the same content reads


def test_a_rank_number_in_a_file_name_sizes_nothing(tmp_path):
    """Review of round 23: the missing ranks were found as range(highest + 1) minus those present, so
    a file named rank 99999999999 beside rank 0 asked for a set of 1e11 numbers (out of memory).
    The first gap is named instead."""
    torch.save(gsplat_checkpoint(random_scene(n=5)), tmp_path / "ckpt_1_rank0.pt")
    (tmp_path / "ckpt_1_rank99999999999.pt").write_bytes((tmp_path / "ckpt_1_rank0.pt").read_bytes())
    with pytest.raises(InputError, match=r"the share of rank 1 \(ckpt_1_rank1.pt\) is not beside it"):
        load_scene(tmp_path / "ckpt_1_rank0.pt")
