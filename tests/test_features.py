"""Feature extraction end to end on real fern photos, through the real loading code with
random-weight checkpoints: files, the registration reader, resuming, truncation, manifests,
offline errors; plus the crop recipe and the id layout."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

from drsplat.cameras import Camera, load_cameras, write_transforms_json
from drsplat.cli import main
from drsplat.errors import DrsplatError
from drsplat.features import format as featurefiles
from drsplat.features.clip import ClipEncoder
from drsplat.features.extract import (
    crop_masks,
    extract_features,
    feature_cameras,
    make_manifest,
    segmap_from_levels,
)
from drsplat.features.masks import MaskSet, make_generator
from drsplat.features.masks.postprocess import NmsParams
from drsplat.features.masks.sam import SamGenerator, SamParams, load_sam
from tests.conftest import shared_path
from tests.test_clip import OFFLINE_CLIP_MESSAGE, TINY_CLIP, make_tiny_clip
from tests.test_masks import make_tiny_sam

try:  # imported with the module: importing ray sets RAY_CLIENT_MODE, which the process-state guard would blame on a test
    import ray
except ImportError:
    ray = None

WIDTH = 96  # fern is 504 x 378; features at 96 x 72 keep the tests fast


@pytest.fixture(scope="module")
def weights(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("weights")
    return {"clip": make_tiny_clip(folder), "sam": make_tiny_sam(folder / "tiny_sam.pth")}


@pytest.fixture(scope="module")
def fern3(tmp_path_factory) -> Path:
    """A dataset of three real fern photos (a transforms.json pointing at ../shared/data)."""
    import dataclasses

    cameras = load_cameras(shared_path("fern"))[:3]
    folder = tmp_path_factory.mktemp("fern3")
    (folder / "images").symlink_to(shared_path("fern", "images"), target_is_directory=True)  # paths stay inside the dataset
    cameras = [dataclasses.replace(c, image_path=folder / "images" / c.image_path.name) for c in cameras]
    write_transforms_json(cameras, folder / "transforms.json")
    return folder


def cli(source: Path, out: Path, weights: dict, *extra: str) -> int:
    return main(["-q", "features", "--source", str(source), "--out", str(out), "--clip-model", TINY_CLIP,
                 "--clip-checkpoint", str(weights["clip"]), "--resolution", str(WIDTH), "--device", "cpu", *extra])


def mtimes(folder: Path) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in folder.glob("*.npy")}


def check_pair(out: Path, stem: str, dim: int = 32) -> tuple[np.ndarray, np.ndarray]:
    seg = np.load(featurefiles.seg_path(out, stem))
    feats = np.load(featurefiles.feat_path(out, stem))
    assert seg.shape == (4, 72, WIDTH)
    assert feats.dtype == np.float32 and feats.shape[1] == dim
    np.testing.assert_allclose(np.linalg.norm(feats, axis=1), 1.0, atol=1e-4)
    ranges = [(lvl[lvl >= 0].min(), lvl.max()) for lvl in seg if (lvl >= 0).any()]
    assert all(hi < lo_next for (_, hi), (lo_next, _) in zip(ranges, ranges[1:]))  # cumulative ids
    assert seg.max() == len(feats) - 1
    for level in range(4):
        ids, read = featurefiles.read_features(out, stem, level=level)  # the registration reader
        assert ids.shape == (72, WIDTH) and read.shape == feats.shape
    return seg, feats


def test_cli_slic_end_to_end_resume_and_truncation(fern3, weights, tmp_path):
    out = tmp_path / "features"
    assert cli(fern3, out, weights, "--masks", "slic") == 0
    stems = ["image000", "image001", "image002"]
    assert featurefiles.list_stems(out) == stems
    for stem in stems:
        check_pair(out, stem)
    manifest = featurefiles.read_manifest(out)
    assert manifest["mask_generator"] == "slic" and manifest["levels"] == ["default", "s", "m", "l"]
    assert manifest["clip"]["model"] == TINY_CLIP and manifest["clip"]["pretrained"] == "file:tiny_clip.pt"
    assert manifest["clip_model_id"] == f"{TINY_CLIP}/file:tiny_clip.pt" and manifest["dim"] == 32
    assert manifest["images"] == 3 and manifest["default_level"] == 1
    assert {"torch", "open_clip_torch", "scikit-image", "drsplat"} <= set(manifest["versions"])
    assert manifest["mask_parameters"]["n_segments"] == [32, 64, 16, 6]

    before = mtimes(out)
    assert cli(fern3, out, weights, "--masks", "slic") == 0  # second run: every image skipped
    assert mtimes(out) == before

    f1 = featurefiles.feat_path(out, "image001")
    f1.write_bytes(f1.read_bytes()[:-7])  # an interrupted copy: truncated data
    assert not featurefiles.is_valid_pair(out, "image001")
    assert cli(fern3, out, weights, "--masks", "slic") == 0
    after = mtimes(out)
    assert featurefiles.is_valid_pair(out, "image001")
    assert after["image001_f.npy"] != before["image001_f.npy"]
    assert {k: v for k, v in after.items() if "image001" not in k} == {k: v for k, v in before.items() if "image001" not in k}
    check_pair(out, "image001")
    assert not list(out.glob(".*.tmp"))  # atomic writes leave no temp files


def test_library_report_counts_skips_and_redos(fern3, weights, tmp_path):
    cameras = feature_cameras(fern3, resolution=WIDTH)
    encoder = ClipEncoder(TINY_CLIP, checkpoint=weights["clip"], device="cpu")
    generator = make_generator("felzenszwalb")
    manifest = make_manifest(generator, encoder, NmsParams(), WIDTH, 1080)
    progress_calls = []
    first = extract_features(cameras, tmp_path, generator, encoder, manifest=manifest, show_progress=False,
                             on_progress=lambda done, total: progress_calls.append((done, total)))
    assert first.written == ["image000", "image001", "image002"] and not first.skipped
    assert progress_calls == [(1, 3), (2, 3), (3, 3)]
    assert sum(first.masks_per_level) == sum(len(featurefiles.read_features(tmp_path, s)[1]) for s in first.written)
    assert first.times.masks > 0 and first.times.clip > 0
    featurefiles.seg_path(tmp_path, "image002").unlink()
    second = extract_features(cameras, tmp_path, generator, encoder, manifest=manifest, show_progress=False)
    assert second.skipped == ["image000", "image001"] and second.written == ["image002"] and second.redone == ["image002"]
    for stem in first.written:
        check_pair(tmp_path, stem)


def test_a_library_run_without_a_manifest_folds_its_journal_into_the_folders_own(weights, tmp_path):
    """A folder made with a manifest records each pair's image stamp, so a later `extract_features`
    given no manifest journals its stamps too; it used to leave that journal behind when it
    finished, which `register` then reports as an unfinished run's (review of round 38). It folds
    the journal into the folder's manifest as it is."""
    from PIL import Image

    from drsplat.cameras import load_cameras
    from drsplat.features.format import STAMP_JOURNAL

    src = _one_camera_dataset(tmp_path / "one", Image.fromarray(np.full((48, 64, 3), 40, np.uint8)))
    out = tmp_path / "features"
    assert main(slic_features_argv(src, out, weights, quiet=True)) == 0
    before = featurefiles.read_manifest(out)
    featurefiles.seg_path(out, "view").unlink()
    cameras = load_cameras(src)
    encoder = ClipEncoder(TINY_CLIP, checkpoint=weights["clip"], device="cpu")
    report = extract_features(cameras, out, make_generator("slic"), encoder, show_progress=False)
    assert report.written == ["view"] and not (out / STAMP_JOURNAL).exists()
    after = featurefiles.read_manifest(out)
    assert {k: v for k, v in after.items() if k != "image_stamps"} == {k: v for k, v in before.items() if k != "image_stamps"}
    assert list(after["image_stamps"]) == ["view"]


def test_sam_pipeline_through_checkpoint_loading(fern3, weights, tmp_path):
    out = tmp_path / "sam"
    # the CLI with LangSplat's quality thresholds (a small prompt grid to stay fast): random
    # weights rarely pass them, but the run must complete and write readable pairs
    assert cli(fern3, out, weights, "--masks", "sam", "--sam-checkpoint", str(weights["sam"]), "--sam-points-per-side", "4", "--sam-crop-layers", "0") == 0
    assert featurefiles.list_stems(out) == ["image000", "image001", "image002"]
    assert featurefiles.read_manifest(out)["mask_generator"] == "sam"
    # permissive thresholds so random weights produce masks that flow through every stage
    cameras = feature_cameras(fern3, resolution=WIDTH)[:1]
    encoder = ClipEncoder(TINY_CLIP, checkpoint=weights["clip"], device="cpu")
    generator = SamGenerator(load_sam(weights["sam"]), SamParams(points_per_side=4, pred_iou_thresh=0.0, stability_score_thresh=0.0))
    report = extract_features(cameras, tmp_path / "sam2", generator, encoder, show_progress=False)
    assert sum(report.masks_per_level) > 0
    check_pair(tmp_path / "sam2", "image000")


def test_refuses_to_mix_models_or_generators(fern3, weights, tmp_path):
    out = tmp_path / "features"
    cameras = feature_cameras(fern3, resolution=WIDTH)[:1]
    encoder = ClipEncoder(TINY_CLIP, checkpoint=weights["clip"], device="cpu")
    nms = NmsParams()
    slic = make_generator("slic")
    extract_features(cameras, out, slic, encoder, manifest=make_manifest(slic, encoder, nms, WIDTH, 1080), show_progress=False)
    other = ClipEncoder(TINY_CLIP, pretrained="another-finetune", checkpoint=weights["clip"], device="cpu")
    with pytest.raises(DrsplatError, match=f"CLIP model mismatch: the features already in {out} were made with {TINY_CLIP}/file:tiny_clip.pt but this run's CLIP model is {TINY_CLIP}/another-finetune") as caught:
        extract_features(cameras, out, slic, other, manifest=make_manifest(slic, other, nms, WIDTH, 1080), show_progress=False)
    # round 87c F2: the advice was --clip-model/--pretrained, which a digest check then refused as well
    assert "pass the checkpoint they were made with, tiny_clip.pt, as --clip-checkpoint" in str(caught.value)
    assert "--pretrained" not in str(caught.value)
    felz = make_generator("felzenszwalb")
    with pytest.raises(DrsplatError, match="mask generator 'slic', this run uses 'felzenszwalb'"):
        extract_features(cameras, out, felz, encoder, manifest=make_manifest(felz, encoder, nms, WIDTH, 1080), show_progress=False)


def test_resume_refuses_other_resolution_mask_settings_or_source(fern3, weights, tmp_path):
    """A folder's features were made with one resolution, mask parameters and dataset: a run that
    differs in any of them would leave a mix under one manifest, so it stops before any image."""
    out = tmp_path / "features"
    cameras = feature_cameras(fern3, resolution=WIDTH)[:1]
    encoder = ClipEncoder(TINY_CLIP, checkpoint=weights["clip"], device="cpu")
    slic = make_generator("slic")
    base = make_manifest(slic, encoder, NmsParams(), WIDTH, 1080, {"source": str(fern3.resolve())})
    extract_features(cameras, out, slic, encoder, manifest=base, show_progress=False)
    changes = {
        "resolution": make_manifest(slic, encoder, NmsParams(), 48, 1080, {"source": str(fern3.resolve())}),
        "max_height": make_manifest(slic, encoder, NmsParams(), WIDTH, 720, {"source": str(fern3.resolve())}),
        "postprocess": make_manifest(slic, encoder, NmsParams(iou_thr=0.5), WIDTH, 1080, {"source": str(fern3.resolve())}),
        "source": make_manifest(slic, encoder, NmsParams(), WIDTH, 1080, {"source": str((tmp_path / "other").resolve())}),
    }
    for key, manifest in changes.items():
        with pytest.raises(DrsplatError, match=f"holds features made with {key} .*use a new --out folder"):
            extract_features(cameras, out, slic, encoder, manifest=manifest, show_progress=False)
    report = extract_features(cameras, out, slic, encoder, manifest=dict(base), show_progress=False)  # the same settings resume
    assert report.skipped == [cameras[0].name]
    # other weights in a file of the same name (every download is open_clip_pytorch_model.bin): the manifest
    # recorded the name alone and the two were mixed (a probe, 2026-11-30)
    other = make_tiny_clip(tmp_path / "elsewhere", seed=1)
    assert other.name == weights["clip"].name and other.read_bytes() != weights["clip"].read_bytes()
    retrained = ClipEncoder(TINY_CLIP, checkpoint=other, device="cpu")
    manifest = make_manifest(slic, retrained, NmsParams(), WIDTH, 1080, {"source": str(fern3.resolve())})
    with pytest.raises(DrsplatError, match="holds features made with clip_weights .*--clip-checkpoint: compared by the file's contents, whatever its name"):
        extract_features(cameras, out, slic, retrained, manifest=manifest, show_progress=False)


def test_an_image_edited_after_its_features_were_made_is_redone(tmp_path, weights):
    """A pair was kept on a rerun whatever happened to its image since: a photo fixed (or replaced)
    in place kept its stale masks and embeddings. The manifest records each pair's image stamp."""
    import shutil

    from PIL import Image

    src = tmp_path / "ds"
    shutil.copytree(_one_camera_dataset(tmp_path / "one", Image.fromarray(np.full((48, 64, 3), 40, np.uint8))), src)
    out = tmp_path / "features"
    args = slic_features_argv(src, out, weights, quiet=True)
    assert main(args) == 0
    before = mtimes(out)
    assert main(args) == 0 and mtimes(out) == before  # nothing changed: nothing redone
    image = src / "images" / "view.png"
    Image.fromarray(np.tile(np.linspace(0, 255, 64).astype(np.uint8)[None, :, None], (48, 1, 3))).save(image)
    assert main(args) == 0
    assert mtimes(out) != before  # redone from the edited image
    after = mtimes(out)
    assert main(args) == 0 and mtimes(out) == after


def test_a_pair_made_through_another_lens_is_redone(tmp_path, weights, capsys):
    """Round 85d F1: the camera file's lens distortion corrected (or its undistorted pinhole moved) left every pair of
    the old lens in place, "skipped 50 already complete": the masks are made on the undistorted image, so a pair now
    records its camera's part of that too (`camera_pixels_key`). A pose moved changes no pixel and redoes nothing, nor
    does a folder's stamp from before (the image's part only)."""
    import json
    import shutil

    from PIL import Image

    src = tmp_path / "ds"
    shutil.copytree(_one_camera_dataset(tmp_path / "one", Image.fromarray(np.tile(np.linspace(0, 255, 64).astype(np.uint8)[None, :, None], (48, 1, 3)))), src)
    out = tmp_path / "features"
    args = slic_features_argv(src, out, weights)
    assert main(args) == 0
    doc = json.loads((src / "transforms.json").read_text())
    steps = [("lens", lambda d: d.update(k1=0.08, k2=0.0, p1=0.0, p2=0.0), True), ("nothing", lambda d: None, False),
             ("pose", lambda d: d["frames"][0]["transform_matrix"][0].__setitem__(3, 0.5), False),
             ("centre", lambda d: d["frames"][0].update(cx=30.0) if "cx" in d["frames"][0] else d.update(cx=30.0), True)]
    for what, edit, redone in steps:
        edit(doc)
        (src / "transforms.json").write_text(json.dumps(doc))
        before = mtimes(out)
        capsys.readouterr()
        assert main(args) == 0
        err = capsys.readouterr().err
        assert (mtimes(out) != before) == redone, what
        assert ("the camera (its size, or the lens distortion and the pinhole it is undistorted to) of view changed" in err) == redone, (what, err)
    manifest = featurefiles.read_manifest(out)
    featurefiles.write_manifest(out, {**manifest, "image_stamps": {k: v.partition("|")[0] for k, v in manifest["image_stamps"].items()}})
    before = mtimes(out)
    doc.update(k1=0.02)
    (src / "transforms.json").write_text(json.dumps(doc))
    assert main(args) == 0 and mtimes(out) == before, "a stamp of the image alone (an older folder) does not judge the camera"


def test_sam_flags_given_with_other_masks_are_said(tmp_path, weights, capsys):
    """Round 87c F5: --sam-checkpoint, --sam-model and --sam-points-per-side with --masks slic were taken without a word."""
    import shutil

    from PIL import Image

    src = tmp_path / "ds"
    shutil.copytree(_one_camera_dataset(tmp_path / "one", Image.fromarray(np.full((48, 64, 3), 40, np.uint8))), src)
    args = slic_features_argv(src, tmp_path / "features", weights)
    assert main([*args, "--sam-points-per-side", "8", "--sam-model", "vit_b"]) == 0
    err = capsys.readouterr().err
    assert "--sam-model, --sam-points-per-side apply to --masks sam; --masks slic does not read them" in err, err
    assert main(args) == 0 and "apply to --masks sam" not in capsys.readouterr().err


def test_an_image_edited_after_a_run_that_stopped_is_redone(tmp_path, weights, capsys):
    """Was (a probe, 2026-12-01): the stamps were written when a run finished, so the pairs of a run
    stopped by an unreadable image (or Ctrl-C, or a kill) had none; the next run kept them as complete
    and stamped them with the images as they were then, so an image re-exported in between kept its
    stale features for good. Now each pair's stamp goes to a journal as the pair is written, folded
    into the manifest when a run finishes."""
    from PIL import Image

    from drsplat.cameras import look_at_camera
    from drsplat.features.extract import STAMP_JOURNAL

    src = tmp_path / "ds"
    (src / "images").mkdir(parents=True)
    flat = Image.fromarray(np.full((48, 64, 3), 40, np.uint8))
    flat.save(src / "images" / "a.png")
    (src / "images" / "b.png").write_bytes(b"not a png")  # the run stops here, after a's pair
    import dataclasses

    cams = [dataclasses.replace(look_at_camera([0, 0, -3], [0, 0, 0], 64, 48, name=n), image_path=src / "images" / f"{n}.png") for n in "ab"]
    write_transforms_json(cams, src / "transforms.json")
    out = tmp_path / "features"
    args = slic_features_argv(src, out, weights, quiet=True)
    assert main(args) == 1 and featurefiles.is_valid_pair(out, "a") and (out / STAMP_JOURNAL).exists()
    # round 100c F3: the stop said only the file's error; a Ctrl-C's line says the finished images are kept
    err = capsys.readouterr().err
    assert "b.png" in err and f"the features of 1 other image are kept in {out}, and the same command resumes from them" in err, err
    first = np.load(featurefiles.feat_path(out, "a"))
    gradient = Image.fromarray(np.tile(np.linspace(0, 255, 64).astype(np.uint8)[None, :, None], (48, 1, 3)))
    gradient.save(src / "images" / "a.png")  # re-exported while fixing b
    flat.save(src / "images" / "b.png")
    assert main(args) == 0
    redone = np.load(featurefiles.feat_path(out, "a"))
    assert redone.shape != first.shape or not np.array_equal(redone, first)  # made from the edited image
    assert not (out / STAMP_JOURNAL).exists() and set(featurefiles.read_manifest(out)["image_stamps"]) == {"a", "b"}
    before = mtimes(out)
    assert main(args) == 0 and mtimes(out) == before  # and then kept
    # round 104a F4: every *_f.npy was counted as an image finished before the failing one, its own stale pair too
    capsys.readouterr()
    (src / "images" / "a.png").write_bytes(b"not a png either")  # the first image now, with a whole pair of its old self
    (out / "c_f.npy").write_bytes(b"half")  # and a half pair of no camera
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "a.png" in err and f"the features of 1 other image are kept in {out}" in err, err


def test_a_pair_written_just_before_a_kill_is_made_again(tmp_path, weights):
    """A pair whose stamp never reached the journal (a kill between the two writes) in a folder that
    records stamps is made again rather than trusted."""
    import shutil

    from PIL import Image

    from drsplat.features.extract import STAMP_JOURNAL

    src = tmp_path / "ds"
    shutil.copytree(_one_camera_dataset(tmp_path / "one", Image.fromarray(np.full((48, 64, 3), 40, np.uint8))), src)
    out = tmp_path / "features"
    args = slic_features_argv(src, out, weights, quiet=True)
    assert main(args) == 0
    manifest = featurefiles.read_manifest(out)
    featurefiles.write_manifest(out, {**manifest, "image_stamps": {}})  # as a killed run leaves it: the pair, no stamp
    (out / STAMP_JOURNAL).write_text('{"stem": "vi')  # and a torn journal line
    before = mtimes(out)
    assert main(args) == 0 and mtimes(out) != before
    assert featurefiles.read_manifest(out)["image_stamps"].keys() == {"view"}


@pytest.mark.parametrize("kind", ["link to an input", "folder", "fifo"])
def test_a_stamp_journal_that_is_no_plain_file_is_refused_before_any_work(tmp_path, weights, capsys, kind):
    """Was (a probe, 2026-12-01): the journal was opened for appending through a symbolic link, so
    `<out>/.image_stamps.jsonl -> ../ds/transforms.json` appended a line per pair to the dataset's
    own transforms.json (exit 0; the next run could not read it); as a FIFO it blocked the run, as a
    link to /dev/zero it read until memory ran out, and as a folder it failed after the first pair.
    Now anything but a plain file is refused before any pair is made, and the input is untouched."""
    import shutil

    from PIL import Image

    from drsplat.features.extract import STAMP_JOURNAL

    src = tmp_path / "ds"
    shutil.copytree(_one_camera_dataset(tmp_path / "one", Image.fromarray(np.full((48, 64, 3), 40, np.uint8))), src)
    out = tmp_path / "features"
    out.mkdir()
    journal = out / STAMP_JOURNAL
    before = (src / "transforms.json").read_bytes()
    if kind == "link to an input":
        journal.symlink_to(src / "transforms.json")
    elif kind == "folder":
        journal.mkdir()
    else:
        os.mkfifo(journal)
    assert main(slic_features_argv(src, out, weights, quiet=True)) == 1
    err = capsys.readouterr().err
    assert "journal of an unfinished features run" in err and STAMP_JOURNAL in err, err
    assert (src / "transforms.json").read_bytes() == before
    assert not featurefiles.seg_path(out, "view").exists()


def test_a_journal_line_without_end_is_skipped_a_piece_at_a_time(tmp_path):
    """A journal is read a line at a time: a line far longer than any record (a hostile or corrupt
    file) is skipped, the records around it kept, a torn last line dropped."""
    import json

    from drsplat.features.extract import JOURNAL_LINE_CHARS, read_journal

    path = tmp_path / "journal.jsonl"
    path.write_text(json.dumps({"stem": "a", "stamp": "1:2"}) + "\n" + "x" * (3 * JOURNAL_LINE_CHARS + 5) + "\n"
                    + json.dumps({"stem": "b", "stamp": "3:4"}) + "\n" + '{"stem": "c", "sta')
    assert read_journal(path) == {"a": "1:2", "b": "3:4"}
    assert read_journal(tmp_path / "none.jsonl") == {}


def slic_features_argv(src: Path, out: Path, weights: dict[str, Path], quiet: bool = False) -> list[str]:
    """`drsplat features` of dataset `src` into `out` with SLIC masks and the tiny random-weight CLIP on the CPU."""
    return [*(["-q"] if quiet else []), "features", "--source", str(src), "--out", str(out), "--masks", "slic", "--clip-model", TINY_CLIP,
            "--clip-checkpoint", str(weights["clip"]), "--device", "cpu"]


def _one_camera_dataset(folder: Path, image, width: int = 64, height: int = 48, exif=None) -> Path:
    """A transforms.json dataset of one look-at camera whose image file is `image` (a PIL image;
    JPEG with `exif`, TIFF for float and 32-bit pixels, PNG otherwise)."""
    from drsplat.cameras import look_at_camera

    (folder / "images").mkdir(parents=True)
    name = "view.jpg" if exif is not None else "view.tif" if image.mode in ("F", "I") else "view.png"
    image.save(folder / "images" / name, **({"exif": exif} if exif is not None else {}))
    cam = look_at_camera([0, 0, -3], [0, 0, 0], width, height, name="view")
    import dataclasses

    write_transforms_json([dataclasses.replace(cam, image_path=folder / "images" / name)], folder / "transforms.json")
    return folder


def test_load_image_scales_16_bit_and_float_grey_and_refuses_other_ranges(tmp_path):
    """Pillow's convert("RGB") turns 16-bit grey into white and float grey into black: load_image
    scales them, and refuses ranges it cannot read as brightness."""
    from PIL import Image

    from drsplat.cameras import load_image
    from drsplat.errors import InputError

    ramp = np.tile(np.linspace(0, 65535, 64).astype(np.uint16), (48, 1))
    cases = {
        "i16": (Image.fromarray(ramp), np.rint(ramp / 257.0)),
        "float": (Image.fromarray((ramp / 65535.0).astype(np.float32)), np.rint(ramp / 65535.0 * 255)),
    }
    for name, (image, expected) in cases.items():
        cam = load_cameras(_one_camera_dataset(tmp_path / name, image))[0]
        rgb = load_image(cam)
        assert rgb.shape == (48, 64, 3) and np.array_equal(rgb[..., 0], expected.astype(np.uint8)), name
        assert np.array_equal(rgb[..., 0], rgb[..., 2])
    for name, image, words in (("hot", Image.fromarray((ramp / 30000.0).astype(np.float32)), "float pixels outside 0..1"),
                               ("wide", Image.fromarray(ramp.astype(np.int32) * 4), "beyond 0..65535")):
        cam = load_cameras(_one_camera_dataset(tmp_path / name, image))[0]
        with pytest.raises(InputError, match=words) as info:
            load_image(cam)
        assert "view" in str(info.value)


def test_load_image_reads_8_bit_values_stored_as_32_bit_integers_as_8_bit_and_says_so(tmp_path, caplog):
    """A 32-bit integer TIFF of 0..255 (a tool that wrote 8-bit values as int32) was scaled as 16-bit:
    a black image (at most 1 of 255), with no word."""
    from PIL import Image

    from drsplat.cameras import load_image

    ramp = np.tile(np.arange(64, dtype=np.int32) * 4, (48, 1))  # 0..252
    cam = load_cameras(_one_camera_dataset(tmp_path / "i32", Image.fromarray(ramp)))[0]
    with caplog.at_level(logging.WARNING, logger="drsplat.cameras"):
        rgb = load_image(cam)
    assert np.array_equal(rgb[..., 1], ramp.astype(np.uint8))
    assert any("view.tif" in r.getMessage() and "read as 8-bit values" in r.getMessage() for r in caplog.records)
    # round 100c F4: an 8-bit array widened to uint16 and saved as PNG (Pillow's I;16) was read as 0s and 1s, no word
    caplog.clear()
    cam = load_cameras(_one_camera_dataset(tmp_path / "u16", Image.fromarray(ramp.astype(np.uint16))))[0]
    with caplog.at_level(logging.WARNING, logger="drsplat.cameras"):
        rgb = load_image(cam)
    assert np.array_equal(rgb[..., 1], ramp.astype(np.uint8))
    assert any("view.png" in r.getMessage() and "16-bit integer pixels all within 0..255" in r.getMessage() for r in caplog.records)


def png16(path: Path, samples: np.ndarray) -> None:
    """A 16-bit PNG of `samples` [H, W, C] uint16 (C = 2: grey + alpha, 3: RGB, 4: RGBA), written by hand: Pillow writes no 16-bit colour."""
    import struct

    h, w, c = samples.shape
    raw = b"".join(b"\x00" + samples[y].astype(">u2").tobytes() for y in range(h))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, 16, {2: 4, 3: 2, 4: 6}[c], 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def tiff(path: Path, samples: np.ndarray, sample_format: int = 1, byteorder: str = "<", extra: int = 2, planar: bool = False) -> None:
    """A baseline uncompressed TIFF of `samples` [H, W, C], written by hand: Pillow writes no 16-bit colour TIFF.
    sample_format: 1 unsigned integer, 3 float; extra: the ExtraSamples value of a 2nd / 4th sample (0 unspecified, 1
    associated alpha, 2 unassociated alpha); planar: each sample in a plane (strip) of its own (PlanarConfiguration 2),
    else interleaved in one strip."""
    import struct

    h, w, c = samples.shape
    ordered = samples.astype(samples.dtype.newbyteorder(byteorder))
    planes = [ordered[..., i].tobytes() for i in range(c)] if planar else [ordered.tobytes()]
    bits = samples.dtype.itemsize * 8
    strips = len(planes)
    entries = [(256, 3, 1, w), (257, 3, 1, h), (258, 3, c, "bits"), (259, 3, 1, 1), (262, 3, 1, 2 if c >= 3 else 1), (273, 4, strips, "offsets"),
               (277, 3, 1, c), (278, 3, 1, h), (279, 4, strips, "counts"), (284, 3, 1, 2 if planar else 1), (339, 3, c, "formats")]
    if c in (2, 4):
        entries.append((338, 3, 1, extra))
    entries.sort()
    after_ifd = 8 + 2 + 12 * len(entries) + 4
    arrays = {"bits": struct.pack(byteorder + f"{c}H", *[bits] * c), "formats": struct.pack(byteorder + f"{c}H", *[sample_format] * c)}
    inline_arrays = {name: arrays.pop(name) for name in ("bits", "formats") if c <= 2}  # two SHORTs fit in the entry itself
    data_at = after_ifd + sum(len(v) for v in arrays.values()) + (8 * strips if strips > 1 else 0)
    starts = [data_at + sum(len(q) for q in planes[:i]) for i in range(strips)]
    if strips > 1:
        arrays["offsets"] = struct.pack(byteorder + f"{strips}I", *starts)
        arrays["counts"] = struct.pack(byteorder + f"{strips}I", *[len(q) for q in planes])
    where, at = {}, after_ifd
    for name, packed in arrays.items():
        where[name], at = at, at + len(packed)
    ifd = struct.pack(byteorder + "H", len(entries))
    for tag, kind, count, value in entries:
        if value == "offsets" and strips == 1:
            value = starts[0]
        elif value == "counts" and strips == 1:
            value = len(planes[0])
        elif value in inline_arrays:
            ifd += struct.pack(byteorder + "HHI", tag, kind, count) + inline_arrays[value].ljust(4, b"\x00")
            continue
        elif isinstance(value, str):
            value = where[value]
        inline = count * (2 if kind == 3 else 4) <= 4
        ifd += struct.pack(byteorder + "HHI", tag, kind, count) + struct.pack(byteorder + ("H2x" if kind == 3 and inline else "I"), value)
    ifd += struct.pack(byteorder + "I", 0)
    head = (b"II*\x00" if byteorder == "<" else b"MM\x00*") + struct.pack(byteorder + "I", 8)
    path.write_bytes(head + ifd + b"".join(arrays.values()) + b"".join(planes))


@pytest.mark.parametrize("kind", ["rgb", "rgba", "grey alpha", "tiff rgb", "tiff rgb big-endian", "tiff rgbx", "tiff rgba associated"])
def test_load_image_reads_8_bit_values_in_16_bit_colour_as_8_bit_and_says_so(tmp_path, caplog, kind):
    """Round 104a F2, 105b F1 / F2: Pillow opens a 16-bit RGB(A) PNG or TIFF, or a 16-bit grey + alpha PNG, as 8-bit,
    keeping each sample's high byte, so an 8-bit photo widened to uint16 and saved read as a black image, with no word
    (100c F4 mended the plain grey one only). True 16-bit samples are read as before (the high byte, as 3DGS reads
    them through Pillow), and a black file stays black without a word."""
    from PIL import Image

    from drsplat.cameras import load_image

    photo = np.random.default_rng(0).integers(30, 230, (48, 64, 3)).astype(np.uint16)
    if kind == "grey alpha":
        photo = np.repeat(photo[..., :1], 3, axis=2)
    opaque = np.full((48, 64, 1), 255, np.uint16)
    samples = {"rgb": photo, "rgba": np.concatenate([photo, opaque], axis=2), "grey alpha": np.concatenate([photo[..., :1], opaque], axis=2),
               "tiff rgbx": np.concatenate([photo, opaque], axis=2), "tiff rgba associated": np.concatenate([photo, opaque], axis=2)}.get(kind, photo)
    suffix = ".tif" if kind.startswith("tiff") else ".png"
    placeholder = np.zeros((48, 64), np.float32) if suffix == ".tif" else np.zeros((48, 64, 3), np.uint8)  # a float image is saved as TIFF
    cam = load_cameras(_one_camera_dataset(tmp_path / "c", Image.fromarray(placeholder)))[0]
    assert cam.image_path.suffix == suffix

    def write(values: np.ndarray) -> None:
        if suffix == ".png":
            png16(cam.image_path, values)
        else:
            # round 106a F2: an extra sample unspecified (RGBX) or associated alpha (RGBa) read black
            tiff(cam.image_path, values, byteorder=">" if "big" in kind else "<", extra=0 if "rgbx" in kind else 1 if "associated" in kind else 2)

    write(samples)
    with caplog.at_level(logging.WARNING, logger="drsplat.cameras"):
        assert np.array_equal(load_image(cam), photo.astype(np.uint8))
    assert any(f"view{suffix}" in r.getMessage() and "16-bit samples all within 0..255" in r.getMessage() for r in caplog.records), caplog.text
    caplog.clear()
    write(samples * 257)  # true 16-bit: v * 257 has the high byte v
    with caplog.at_level(logging.WARNING, logger="drsplat.cameras"):
        assert np.array_equal(load_image(cam), photo.astype(np.uint8))
    assert not caplog.records
    write(np.zeros_like(samples))  # a black image stays black, without a word
    with caplog.at_level(logging.WARNING, logger="drsplat.cameras"):
        assert not load_image(cam).any()
    assert not caplog.records


def test_load_image_names_a_tiff_pillow_cannot_decode_and_takes_a_transparent_palette_quietly(tmp_path, caplog):
    """Round 105b F3: a palette PNG with transparency logged Pillow's "should be converted to RGBA" once an image
    (its pixels right); F4: a float-colour TIFF failed with Pillow's "cannot identify image file", read as damaged."""
    from PIL import Image

    from drsplat.cameras import load_image
    from drsplat.errors import InputError

    palette = Image.fromarray(np.tile(np.arange(64, dtype=np.uint8)[None, :], (48, 1)), mode="L").convert("P")
    palette.info["transparency"] = 3
    cam = load_cameras(_one_camera_dataset(tmp_path / "p", palette))[0]
    with caplog.at_level(logging.WARNING):
        rgb = load_image(cam)
    assert np.array_equal(rgb, np.asarray(Image.open(cam.image_path).convert("RGB"))) and not caplog.records, caplog.text
    cam = load_cameras(_one_camera_dataset(tmp_path / "f", Image.fromarray(np.zeros((48, 64), np.float32))))[0]
    # round 107a F1: a tRNS chunk longer than the 256 palette entries (libpng ignores the rest) was "palette index out of range"
    import struct

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    indices = np.tile(np.arange(64, dtype=np.uint8), (48, 1))
    colours = np.random.default_rng(1).integers(0, 256, (256, 3), dtype=np.uint8)
    long_trns = load_cameras(_one_camera_dataset(tmp_path / "t", Image.fromarray(np.zeros((48, 64, 3), np.uint8))))[0]
    long_trns.image_path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 64, 48, 8, 3, 0, 0, 0)) + chunk(b"PLTE", colours.tobytes())
                               + chunk(b"tRNS", bytes(range(256)) + b"\x00") + chunk(b"IDAT", zlib.compress(b"".join(b"\x00" + r.tobytes() for r in indices)))
                               + chunk(b"IEND", b""))
    with caplog.at_level(logging.WARNING):
        assert np.array_equal(load_image(long_trns), colours[indices]) and not caplog.records, caplog.text
    tiff(cam.image_path, np.full((48, 64, 3), 0.5, np.float32), sample_format=3)
    with pytest.raises(InputError, match=r"view.tif: is a TIFF of a sample layout Pillow cannot decode .* save it as an 8- or 16-bit RGB image"):
        load_image(cam)
    # round 106a F3: an uncompressed 16-bit TIFF with its colour planes apart, which Pillow reads as 8-bit bands (garbage)
    tiff(cam.image_path, np.full((48, 64, 3), 40000, np.uint16), planar=True)
    with pytest.raises(InputError, match=r"view.tif: is a TIFF of samples wider than 8 bits with its colour planes stored apart"):
        load_image(cam)
    tiff(cam.image_path, np.full((48, 64, 3), 200, np.uint8), planar=True)  # 8-bit planes Pillow reads right
    assert (load_image(cam) == 200).all()


def test_load_image_refuses_an_image_of_another_aspect_and_names_exif_rotation(tmp_path):
    from PIL import Image

    from drsplat.cameras import load_image, scale_cameras
    from drsplat.errors import InputError

    upright = Image.fromarray(np.zeros((64, 48, 3), np.uint8))  # 48 x 64 for a 64 x 48 camera
    cam = load_cameras(_one_camera_dataset(tmp_path / "t", upright))[0]
    with pytest.raises(InputError, match=r"is 48x64 but camera 'view' is 64x48: the aspect ratios .* would be stretched"):
        load_image(cam)
    exif = Image.Exif()
    exif[0x0112] = 6  # what a phone writes for a portrait shot stored sideways
    cam = load_cameras(_one_camera_dataset(tmp_path / "e", upright, exif=exif))[0]
    with pytest.raises(InputError, match="EXIF orientation says to rotate it"):
        load_image(cam)
    # at --resolution 4 the refusal still quotes the size the camera file gives, then the scaled one
    with pytest.raises(InputError, match=r"camera 'view' is 64x48 \(16x12 at the resolution chosen\): the aspect ratios 0\.75 and 1\.333"):
        load_image(scale_cameras([cam], 4)[0])
    same_aspect = Image.fromarray(np.full((96, 128, 3), 7, np.uint8))  # twice the camera's size: resized, as before
    cam = load_cameras(_one_camera_dataset(tmp_path / "s", same_aspect))[0]
    assert load_image(cam).shape == (48, 64, 3) and load_image(cam).max() == 7


def test_load_image_of_a_decompression_bomb_is_one_error(tmp_path):
    import struct
    import zlib

    from drsplat.cameras import load_image
    from drsplat.errors import InputError

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    folder = _one_camera_dataset(tmp_path / "b", __import__("PIL.Image", fromlist=["Image"]).fromarray(np.zeros((48, 48, 3), np.uint8)),
                                 width=48, height=48)
    side = 30000  # 900 M pixels in a 429-byte file: Pillow refuses to decode it
    bomb = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0)) + \
        chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")
    (folder / "images" / "view.png").write_bytes(bomb)
    cam = load_cameras(folder, require_images=False)[0]
    with pytest.raises(InputError, match="is not a readable image: Image size .* exceeds limit"):
        load_image(cam)


def test_missing_and_irregular_images_are_named(tmp_path, caplog):
    """Frames whose image is missing, a folder or a FIFO are skipped with one warning naming them."""
    import logging

    from PIL import Image

    folder = _one_camera_dataset(tmp_path / "m", Image.fromarray(np.zeros((48, 64, 3), np.uint8)))
    meta = __import__("json").loads((folder / "transforms.json").read_text())
    frame = meta["frames"][0]
    meta["frames"] = [frame] + [{**frame, "file_path": f"images/{n}"} for n in ("gone.png", "dir.png", "fifo.png")]
    (folder / "transforms.json").write_text(__import__("json").dumps(meta))
    (folder / "images" / "dir.png").mkdir()
    os.mkfifo(folder / "images" / "fifo.png")
    with caplog.at_level(logging.WARNING):
        assert len(load_cameras(folder)) == 1
    assert "3 frames skipped because their images are missing or not a regular file (images/gone.png, images/dir.png, images/fifo.png" in caplog.text


@pytest.mark.parametrize("masks", ["sam", "slic", "sam checkpoint missing"])
def test_offline_cli_prints_one_sentence(fern3, tmp_path, masks):
    """Round 104c F1: without either weight file (SAM's default masks) only CLIP's absence was said, SAM's a run
    later; one sentence names both flags. With masks that need no weights, CLIP's alone."""
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HOME": str(tmp_path / "hf"), "DRSPLAT_CACHE": str(tmp_path / "cache")}
    env.pop("HF_HUB_CACHE", None)
    flags = ["--masks", "slic"] if masks == "slic" else ["--sam-checkpoint", str(tmp_path / "none.pth")] if "missing" in masks else []
    proc = subprocess.run([sys.executable, "-m", "drsplat", "features", "--source", str(fern3), "--out", str(tmp_path / "f"), *flags],
                          capture_output=True, text=True, env=env, cwd=Path(__file__).resolve().parents[1], timeout=300)
    assert proc.returncode == 1
    sam = {"sam": (f"; and SAM weights (vit_h) are not in the cache {tmp_path / 'cache'} and cannot be downloaded; pass --sam-checkpoint "
                   "PATH to a local SAM checkpoint, or run once with internet access."),
           "sam checkpoint missing": f"; and {tmp_path / 'none.pth'}: SAM checkpoint file does not exist (--sam-checkpoint)",  # round 105a F2
           "slic": ""}[masks]
    assert proc.stderr == (f"ERROR: {OFFLINE_CLIP_MESSAGE.rstrip('.')}{sam}\n" if sam else f"ERROR: {OFFLINE_CLIP_MESSAGE}\n"), proc.stderr
    assert not (tmp_path / "f").exists()


def test_sam_weights_out_of_reach_are_said_without_a_downloading_line(tmp_path, monkeypatch, caplog):
    """Round 104c F1: with no network (not declared offline) "downloading SAM vit_h weights from ..." was logged just
    before the error saying they cannot be downloaded."""
    import logging

    from drsplat.errors import WeightsUnavailableError
    from drsplat.features import weights as weights_module

    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    monkeypatch.delenv("DRSPLAT_OFFLINE", raising=False)
    monkeypatch.setenv("DRSPLAT_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(weights_module, "host_reachable", lambda url, timeout=3.0: False)
    with caplog.at_level(logging.INFO), pytest.raises(WeightsUnavailableError, match=r"SAM weights \(vit_b\) are not in the cache .* --sam-checkpoint"):
        weights_module.resolve_sam_checkpoint("vit_b")
    assert "downloading" not in caplog.text and not (tmp_path / "cache").exists()
    (tmp_path / "cache").mkdir()
    (tmp_path / "cache" / "sam_vit_b_01ec64.pth").write_bytes(b"cached")  # a cached file needs no network
    assert weights_module.resolve_sam_checkpoint("vit_b") == tmp_path / "cache" / "sam_vit_b_01ec64.pth"


def test_offline_sam_cli_names_the_flag(fern3, weights, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("DRSPLAT_CACHE", str(tmp_path / "cache"))
    assert cli(fern3, tmp_path / "f", weights, "--masks", "sam") == 1
    assert capsys.readouterr().err == (
        f"ERROR: SAM weights (vit_h) are not in the cache {tmp_path / 'cache'} and cannot be downloaded; "
        "pass --sam-checkpoint PATH to a local SAM checkpoint, or run once with internet access.\n"
    )


def test_crop_recipe():
    image = np.zeros((40, 60, 3), np.uint8)
    image[...] = (10, 20, 30)
    image[10:20, 5:45] = (200, 100, 50)
    masks = np.zeros((2, 40, 60), bool)
    masks[0, 10:20, 5:45] = True  # a 10 x 40 box: padded to 40 x 40, content in rows 15..24
    masks[1, 0, 0] = True  # a single pixel
    crops = crop_masks(image, masks, size=80)
    assert crops.shape == (2, 3, 80, 80) and crops.dtype == np.float32
    np.testing.assert_allclose(crops[0, :, 40, 40], np.array([200, 100, 50]) / 255, atol=1e-6)
    np.testing.assert_allclose(crops[0, :, 5, 40], 0.0)  # black padding above
    np.testing.assert_allclose(crops[0, :, 75, 40], 0.0)  # and below
    rows_with_content = np.flatnonzero(crops[0, 0].max(axis=1) > 0)
    assert rows_with_content[0] in (29, 30) and rows_with_content[-1] in (49, 50)  # 20 rows of 80, centred
    np.testing.assert_allclose(crops[1], np.broadcast_to((np.array([10, 20, 30]) / 255)[:, None, None], (3, 80, 80)), atol=1e-6)
    outside = np.zeros((1, 40, 60), bool)
    outside[0, 5:15, 0:10] = True
    outside[0, 5, 9] = False  # a pixel outside the mask inside its box becomes black
    crop = crop_masks(image, outside, size=10)
    assert crop[0, :, 0, 9].sum() == 0 and crop[0, 0, 5, 5] > 0


def test_segmap_ids_are_cumulative_and_painted_in_order():
    a = np.zeros((3, 2, 3), bool)
    a[0, 0, :] = True
    a[1, :, 0] = True  # overlaps a[0] at (0, 0): painted later, wins
    b = np.zeros((1, 2, 3), bool)
    b[0, 1, 2] = True
    levels = [MaskSet(a[:2], np.ones(2)), MaskSet(a[:0], np.ones(0)), MaskSet(b, np.ones(1)), MaskSet(a[2:], np.ones(1))]
    seg = segmap_from_levels(levels)
    np.testing.assert_array_equal(seg[0], [[1, 0, 0], [1, -1, -1]])
    np.testing.assert_array_equal(seg[1], np.full((2, 3), -1))
    np.testing.assert_array_equal(seg[2], [[-1, -1, -1], [-1, -1, 2]])
    np.testing.assert_array_equal(seg[3], np.full((2, 3), -1))  # an empty mask paints nothing


class InterruptingGenerator:
    """Slic that raises (Ctrl-C or a cancel) while working on the second image."""

    name = "slic"

    def __init__(self, exc: BaseException | None = None, token=None):
        from drsplat.features.masks.superpixel import SlicGenerator

        self.inner, self.calls, self.exc, self.token = SlicGenerator(), 0, exc, token

    def parameters(self) -> dict:
        return self.inner.parameters()

    def generate(self, image):
        self.calls += 1
        if self.calls == 2:
            if self.token is not None:
                self.token.cancel()
            else:
                raise self.exc
        return self.inner.generate(image)


def test_interrupt_and_cancel_leave_only_complete_pairs(fern3, weights, tmp_path):
    from drsplat.errors import Cancelled
    from drsplat.utils import CancelToken

    cameras = feature_cameras(fern3, resolution=WIDTH)
    encoder = ClipEncoder(TINY_CLIP, checkpoint=weights["clip"], device="cpu")
    out = tmp_path / "ctrl-c"
    with pytest.raises(KeyboardInterrupt):
        extract_features(cameras, out, InterruptingGenerator(KeyboardInterrupt()), encoder, show_progress=False)
    assert sorted(p.name for p in out.iterdir()) == ["image000_f.npy", "image000_s.npy"]
    check_pair(out, "image000")
    token = CancelToken()
    out2 = tmp_path / "cancel"
    with pytest.raises(Cancelled):
        extract_features(cameras, out2, InterruptingGenerator(token=token), encoder, show_progress=False, cancel=token)
    assert featurefiles.list_stems(out2) == ["image000", "image001"]  # the image in progress completes, then it stops
    assert not list(out2.glob(".*.tmp"))


# ----------------------------------------------------------------------------- Ray, --device cuda


def test_ray_cuda_actor_count_is_one_per_gpu_with_a_cpu_beside_it():
    """One feature actor per worker slot: a GPU with a CPU on its node; a cluster without GPUs is refused."""
    from drsplat.features.ray import actor_count

    def node(cpus: float, gpus: float = 0, alive: bool = True) -> dict:
        return {"Alive": alive, "Resources": {"CPU": cpus, **({"GPU": gpus} if gpus else {})}}

    nodes = [node(8, 2), node(0, 4), node(1, 4), node(16, 8, alive=False)]  # 2 + 0 (no CPU) + 1 (one CPU) + dead
    assert actor_count(nodes, 1, None, "h:1") == 3
    assert actor_count(nodes, 1, 10, "h:1") == 3  # more would wait forever
    assert actor_count(nodes, 1, 2, "h:1") == 2
    assert actor_count(nodes, 0, None, "h:1") == 9  # CPU workers: one per CPU
    with pytest.raises(DrsplatError, match=r"need GPUs, but the Ray cluster at h:1 has none; use --device cpu"):
        actor_count([node(8), node(4)], 1, None, "h:1")


def test_ray_feature_workers_whose_manifests_differ_are_one_error_naming_the_entry(caplog):
    """Each feature worker makes the manifest as it loads its models (a lost node cannot stop the run
    at a later manifest call, CI of stop 82); two that differ in what shapes the features (a node's
    weights file of the same name holding other weights) would mix two models' features in one
    folder, and are refused. Each host's own hub cache path is not a difference; other library
    versions are said."""
    from drsplat.features.ray import _check_same_manifests

    one = {"format": "langsplat", "clip_weights": "600:aa", "dim": 512, "clip": {"checkpoint": "/home/a/.cache/x.bin"},
           "versions": {"torch": "2.14.1"}}
    with caplog.at_level("WARNING"):
        _check_same_manifests([one, dict(one), {**one, "clip": {"checkpoint": "/root/.cache/x.bin"}}])
    assert not caplog.text
    with pytest.raises(DrsplatError, match=r"manifests differ in 'clip_weights' \('600:aa' on one node, '600:bb' on another\); every node needs the "
                                           r"same weights files"):
        _check_same_manifests([one, dict(one), {**one, "clip_weights": "600:bb"}])
    with pytest.raises(DrsplatError, match=r"differ in 'sam_weights' \(None on one node, '1:cc' on another\)"):
        _check_same_manifests([one, {**one, "sam_weights": "1:cc"}])
    with pytest.raises(DrsplatError, match=r"differ in 'dim'"):  # a third worker's difference is seen past a second's other versions
        _check_same_manifests([one, {**one, "versions": {"torch": "2.14.0"}}, {**one, "dim": 768}])
    with caplog.at_level("WARNING"):
        _check_same_manifests([one, {**one, "versions": {"torch": "2.14.0"}}])
    assert "other library versions ({'torch': '2.14.1'} on one, {'torch': '2.14.0'} on another)" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING"):
        _check_same_manifests([{**one, "clip_precision": "float16"}, {**one, "clip_precision": "float32"}])
    assert "other CLIP precisions (float16 on a CUDA device) (float16 on one, float32 on another)" in caplog.text


def test_a_folder_resumed_in_another_clip_precision_is_said(tmp_path, caplog):
    """Was (a probe of `features --ray`, left as found then fixed): CLIP embeds in float16 on a CUDA
    device and float32 on the CPU, and nothing recorded which; a folder begun on a GPU and finished on
    CPUs mixed the two without a word. The manifest records it, and a resume in the other is warned
    about (not refused: the two differ in their last bits, as other library versions do)."""
    from drsplat.features import format as featurefiles
    from drsplat.features.extract import check_manifest_compatible, clip_precision

    class Encoder:
        dtype = "torch.float16"

    assert clip_precision(Encoder()) == "float16" and clip_precision(object()) is None
    made = {"format": "langsplat", "mask_generator": "slic", "clip_model_id": "m/p", "clip_precision": "float16"}
    featurefiles.write_manifest(tmp_path, made)
    with caplog.at_level("WARNING"):
        check_manifest_compatible(tmp_path, dict(made))
        assert not caplog.text
        check_manifest_compatible(tmp_path, {**made, "clip_precision": "float32"})
    assert "holds features CLIP made in float16, this run's are in float32" in caplog.text
    caplog.clear()
    featurefiles.write_manifest(tmp_path, {**made, "clip_precision": "float16\nERROR forged"})  # an edited manifest cannot forge a log line
    with caplog.at_level("WARNING"):
        check_manifest_compatible(tmp_path, {**made, "clip_precision": "float32"})
    assert len(caplog.records) == 1 and "\n" not in caplog.records[0].getMessage() and '"float16\\nERROR forged"' in caplog.text


@pytest.fixture
def fake_gpu_cluster():
    """A local two-node Ray cluster that declares three GPUs Ray cannot use: two on a head node with
    three CPUs, one on a node without a CPU (no actor fits there)."""
    if ray is None:
        pytest.skip("Ray features need the optional ray package (pip install -e '.[ray]')")
    import signal

    from ray.cluster_utils import Cluster

    from drsplat.device import cuda_available

    if cuda_available():
        pytest.skip("this machine has a CUDA GPU: the declared fake GPUs would map onto real ones")
    sigterm = signal.getsignal(signal.SIGTERM)
    store = 80 * 1024 * 1024
    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 3, "num_gpus": 2, "object_store_memory": store, "include_dashboard": False})
    try:
        c.add_node(num_cpus=0, num_gpus=1, object_store_memory=store)
        c.wait_for_nodes()
        yield c
    finally:
        ray.shutdown()
        c.shutdown()
        signal.signal(signal.SIGTERM, sigterm)


def test_ray_features_on_cuda_start_one_actor_per_usable_gpu_and_never_hang(fern3, weights, tmp_path, fake_gpu_cluster, caplog):
    """--ray --device cuda on a cluster whose declared GPUs torch cannot see (this machine has none):
    two actors (the GPU without a CPU beside it gets none, more were asked for), and the run ends at
    once with one error that says why, instead of waiting for a GPU or restarting workers forever."""
    import time

    from drsplat.features.extract import ModelSpec
    from drsplat.features.ray import extract_features_ray

    spec = ModelSpec(masks="slic", clip_model=TINY_CLIP, clip_checkpoint=weights["clip"], device="cuda",
                     clip_config=weights["clip"].parent / f"{TINY_CLIP}.json")
    t0 = time.monotonic()
    with caplog.at_level("INFO", logger="drsplat.features.ray"), pytest.raises(
            DrsplatError, match=r"^2 of 2 Ray feature workers could not load their models: --device cuda was requested but no CUDA GPU"):
        extract_features_ray(load_cameras(fern3), tmp_path / "out", spec, address=fake_gpu_cluster.address, workers=4, show_progress=False)
    assert time.monotonic() - t0 < 120  # a hang would be stopped here, not a timing claim
    assert "features on 2 Ray actor(s) (one per GPU)" in caplog.text
    assert "4 feature workers asked for, but the cluster fits 2 (one per GPU)" in caplog.text
    assert not (tmp_path / "out").exists()


def test_a_png_with_a_malformed_chunk_is_one_error_naming_the_file(tmp_path):
    """Was (a probe, 2026-12-01): Pillow reports some malformed PNG chunks with ValueError or
    SyntaxError, not OSError, and `features` ended in a traceback (a third of 1,500 chunk-level
    mutations)."""
    from PIL import Image

    from drsplat.cameras import load_cameras, load_image
    from drsplat.errors import InputError

    src = _one_camera_dataset(tmp_path / "ds", Image.fromarray(np.full((48, 64, 3), 90, np.uint8)))
    path = src / "images" / "view.png"
    data = bytearray(path.read_bytes())
    data[11] = 4  # IHDR's length 13 -> 4: "Truncated IHDR chunk"
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"view\.png: is not a readable image \(ValueError: Truncated IHDR chunk\)"):
        load_image(load_cameras(src)[0])


def test_an_image_name_with_a_control_character_is_refused_and_paths_print_escaped(tmp_path):
    """Was (a probe, 2026-12-01): an image named with ESC or a newline was accepted, became feature
    file names, and its error line printed the raw bytes (escape codes ran; a newline forged a line)."""
    import json

    from drsplat.cameras import load_cameras
    from drsplat.errors import InputError

    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 50.0, "w": 64, "h": 48, "frames": [
        {"file_path": "a\u001b[2Jb.png", "transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(InputError, match=r"frame 0 has an image name with a control character \(U\+001B at character 1\)"):
        load_cameras(tmp_path, require_images=False)
    message = str(InputError(tmp_path / "x\nERROR: forged.png", "is not a readable image"))
    assert "\n" not in message and '"' in message and "\\nERROR: forged.png" in message


def test_an_image_a_power_of_two_of_its_cameras_size_is_not_taken_for_an_undistorted_pairs_photo():
    """Round 100c F2: a photo of exactly twice its camera's size (full-resolution photos beside the cameras of an
    images_2 copy) was said to be "neither its camera's size nor a power-of-two fraction of it", the signature of the
    photos from before `colmap image_undistorter`, which differ from their cameras by a few percent."""
    from drsplat.features.extract import off_power_of_two

    cam = Camera(R=np.eye(3), t=np.zeros(3), fx=50.0, fy=50.0, cx=32.0, cy=24.0, width=64, height=48, name="view")
    for size in [(64, 48), (32, 24), (16, 12), (2, 1), (128, 96), (256, 192), (129, 97), (2048, 1536)]:
        assert not off_power_of_two(size, cam), size
    for size in [(66, 49), (130, 99), (96, 72), (4096, 3072), (60, 48)]:
        assert off_power_of_two(size, cam), size


def test_features_says_which_images_gave_nothing_useful(tmp_path, weights, capsys):
    """Was (a probe, 2026-12-01): a blank image, an image with no mask and a 16x12 file for a 64x48
    camera all ended in exit 0 without a word. Now one warning each at the end, naming the images."""
    from PIL import Image

    src = _one_camera_dataset(tmp_path / "ds", Image.fromarray(np.full((12, 16, 3), 200, np.uint8)))
    out = tmp_path / "features"
    args = slic_features_argv(src, out, weights)
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "1 image(s) are one flat colour (view)" in err, err
    assert "1 image file(s) are over 1.5x narrower than their cameras and were upsampled (the most: view, 16x12 to 64x48, 4x)" in err
    assert "power-of-two fraction" not in err  # 16x12 is 64x48 over 4, as an images_4 copy
    # round 57b: a file a few percent off its camera (the photos from before `colmap image_undistorter`, beside its
    # cameras) was resized to it without a word
    rng = np.random.default_rng(0)
    src = _one_camera_dataset(tmp_path / "off", Image.fromarray(rng.integers(0, 255, (49, 66, 3), dtype=np.uint8)))
    assert main(slic_features_argv(src, tmp_path / "features_off", weights)) == 0
    err = capsys.readouterr().err
    # round 104a F5: "nor a power-of-two fraction of it" since multiples are accepted too (100c F2)
    assert ("1 image file(s) are neither their camera's size nor a power-of-two fraction or multiple of it (as images_2, _4, _8 are, "
            "or full-size photos beside their cameras) and were resized to it (the first: view, 66x49 for camera 64x48)") in err, err


def test_a_foreign_manifest_in_the_output_folder_is_named_as_such(tmp_path, weights, capsys):
    """Was (a probe, 2026-12-01): an --out folder holding another tool's manifest.json was refused as
    holding "features made with mask generator None"."""
    from PIL import Image

    src = _one_camera_dataset(tmp_path / "ds", Image.fromarray(np.full((48, 64, 3), 90, np.uint8)))
    out = tmp_path / "out"
    out.mkdir()
    (out / "manifest.json").write_text('{"my": "own dataset manifest"}')
    args = slic_features_argv(src, out, weights)
    assert main(args) == 1
    assert "manifest.json is not a drsplat features manifest" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json"]


def test_resuming_with_other_sam_weights_is_refused_and_a_manifest_alone_says_what_to_do(weights, tmp_path):
    """Round 40: a resume with other SAM weights (another --sam-checkpoint, or another --sam-model downloaded, whose
    path the manifest kept as "") was accepted, mixing SAM models in one folder; and a folder holding only the manifest
    of a run stopped before its first pair (SAM takes minutes an image on a CPU) refused every other setting without
    saying that deleting the manifest is safe when no run is writing there."""
    from PIL import Image

    src = _one_camera_dataset(tmp_path / "one", Image.fromarray(np.full((48, 64, 3), 40, np.uint8)))
    cameras = load_cameras(src)
    encoder = ClipEncoder(TINY_CLIP, checkpoint=weights["clip"], device="cpu")
    params = SamParams(points_per_side=2, crop_n_layers=0)
    other = make_tiny_sam(tmp_path / "other_sam.pth", seed=1)
    made = {}
    for name, path in (("a", weights["sam"]), ("b", other)):
        gen = SamGenerator(load_sam(path), params, path)
        made[name] = (gen, make_manifest(gen, encoder, NmsParams(), 64, 1080))
    out = tmp_path / "features"
    extract_features(cameras, out, made["a"][0], encoder, manifest=made["a"][1], show_progress=False)
    assert featurefiles.read_manifest(out)["sam_weights"].startswith(f"{weights['sam'].stat().st_size}:")
    with pytest.raises(DrsplatError, match="holds features made with sam_weights .* SAM weights"):
        extract_features(cameras, out, made["b"][0], encoder, manifest=made["b"][1], show_progress=False)
    stopped = tmp_path / "stopped"
    stopped.mkdir()
    slic = make_generator("slic")
    featurefiles.write_manifest(stopped, make_manifest(slic, encoder, NmsParams(), 64, 1080))  # the first run wrote no pair
    felz = make_generator("felzenszwalb")
    # still refused (another run may be writing there now: the manifest is all that tells them apart), saying what to do
    with pytest.raises(DrsplatError, match="holds no feature file yet, only the manifest of a run stopped before its first: if no "
                                           "`drsplat features` is writing there now, delete manifest.json"):
        extract_features(cameras, stopped, felz, encoder, manifest=make_manifest(felz, encoder, NmsParams(), 64, 1080), show_progress=False)
    (stopped / featurefiles.MANIFEST_NAME).unlink()
    report = extract_features(cameras, stopped, felz, encoder, manifest=make_manifest(felz, encoder, NmsParams(), 64, 1080), show_progress=False)
    assert report.written == ["view"] and featurefiles.read_manifest(stopped)["mask_generator"] == "felzenszwalb"


def test_resuming_with_the_same_clip_weights_renamed_is_accepted(tmp_path, weights, capsys):
    """Round 61c: the same CLIP weights under another file name changed the features' model label (`file:NAME`) and a
    resume was refused, though `query` accepted the file (the digest, not the name, says what the weights are). Other
    weights of the same name are still refused (`clip_weights`)."""
    import shutil

    from PIL import Image

    src = _one_camera_dataset(tmp_path / "ds", Image.fromarray(np.full((48, 64, 3), 90, np.uint8)))
    out = tmp_path / "out"
    assert main(slic_features_argv(src, out, weights)) == 0
    renamed = Path(shutil.copy(weights["clip"], tmp_path / "renamed_clip.pt"))
    assert main(slic_features_argv(src, out, {**weights, "clip": renamed})) == 0, capsys.readouterr().err
    assert featurefiles.list_stems(out) == ["view"]


def test_a_result_in_read_only_arrays_is_recorded_as_any_other(tmp_path):
    """Round 62b: `features --ray` on a dataset with lens distortion ended at its first image in "assignment destination is
    read-only" (a Ray worker's arrays come from the object store) and wrote no pair, every run. Read-only arrays are
    changed in copies."""
    from drsplat.features.extract import FeatureReport, StageTimes, record_result

    seg = np.zeros((4, 6, 8), np.int16)
    feats = np.ones((2, 16), np.float32)
    feats[1, 0] = np.nan
    seg[:, :, :4], seg[:, :, 4:] = 0, 1
    seg.flags.writeable = False
    feats.flags.writeable = False
    unseen = np.zeros((6, 8), bool)
    unseen[0] = True
    report = FeatureReport()
    record_result(tmp_path, "view", seg, feats, StageTimes(), [2, 0, 0, 0], report, unseen)
    got_seg, got_feats = featurefiles.read_features(tmp_path, "view", level=0)
    assert report.written == ["view"] and np.all(got_seg[0] == -1) and np.all(got_seg[1:, 4:] == -1)  # unseen; the NaN row's mask
    assert np.all(got_seg[1:, :4] == 0) and np.isfinite(got_feats).all()


def test_a_resume_in_another_crop_normalisation_is_refused_also_where_the_folder_predates_recording_it(weights, tmp_path):
    """Round 62b: a folder begun before the crop normalisation followed the checkpoint's model (OpenAI's mean and std for
    every file then) was resumed by a run normalising with 0/1 (a MobileCLIP checkpoint), without a word: the folder held
    views of two embeddings (cosine 0.81 between them). The manifest records the normalisation; a resume in another is
    refused, and so is one other than OpenAI's into a folder whose manifest does not say."""
    import json

    from PIL import Image

    src = _one_camera_dataset(tmp_path / "one", Image.fromarray(np.full((48, 64, 3), 40, np.uint8)))
    cameras = load_cameras(src)
    openai = ClipEncoder(TINY_CLIP, checkpoint=weights["clip"], device="cpu")
    other = ClipEncoder(TINY_CLIP, checkpoint=weights["clip"], device="cpu")
    other.mean, other.std = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    slic = make_generator("slic")
    out = tmp_path / "features"
    extract_features(cameras, out, slic, openai, manifest=make_manifest(slic, openai, NmsParams(), 64, 1080), show_progress=False)
    assert featurefiles.read_manifest(out)["crop_normalisation"]["std"] == [0.26862954, 0.26130258, 0.27577711]
    with pytest.raises(DrsplatError, match="crop_normalisation"):
        extract_features(cameras, out, slic, other, manifest=make_manifest(slic, other, NmsParams(), 64, 1080), show_progress=False)
    manifest = out / featurefiles.MANIFEST_NAME  # as written before it was recorded
    manifest.write_text(json.dumps({k: v for k, v in json.loads(manifest.read_text()).items() if k != "crop_normalisation"}))
    with pytest.raises(DrsplatError, match="made before drsplat recorded how crops are normalised"):
        extract_features(cameras, out, slic, other, manifest=make_manifest(slic, other, NmsParams(), 64, 1080), show_progress=False)
    report = extract_features(cameras, out, slic, openai, manifest=make_manifest(slic, openai, NmsParams(), 64, 1080), show_progress=False)
    assert report.skipped == ["view"]


def test_resuming_with_the_same_sam_weights_moved_is_accepted(weights, tmp_path):
    """Round 61c: a resume whose --sam-checkpoint was the same file moved (~/Downloads -> ~/models) was refused on its
    path though the manifest's sam_weights (size:sha1) matched: SAM takes minutes an image on a CPU, and the remedy
    offered (a new --out) threw them away. The weights' digest decides, as for CLIP; other weights are still refused."""
    import shutil

    from PIL import Image

    src = _one_camera_dataset(tmp_path / "one", Image.fromarray(np.full((48, 64, 3), 40, np.uint8)))
    cameras = load_cameras(src)
    encoder = ClipEncoder(TINY_CLIP, checkpoint=weights["clip"], device="cpu")
    params = SamParams(points_per_side=2, crop_n_layers=0)
    moved = Path(shutil.copy(weights["sam"], (tmp_path / "models").mkdir() or tmp_path / "models" / weights["sam"].name))
    out = tmp_path / "features"
    runs = []
    for path in (weights["sam"], moved, make_tiny_sam(tmp_path / "other_sam.pth", seed=1)):
        gen = SamGenerator(load_sam(path), params, path)
        runs.append((gen, make_manifest(gen, encoder, NmsParams(), 64, 1080, {"sam_checkpoint": str(path.resolve())})))
    extract_features(cameras, out, runs[0][0], encoder, manifest=runs[0][1], show_progress=False)
    report = extract_features(cameras, out, runs[1][0], encoder, manifest=runs[1][1], show_progress=False)
    assert report.skipped == ["view"]
    with pytest.raises(DrsplatError, match="sam_weights"):
        extract_features(cameras, out, runs[2][0], encoder, manifest=runs[2][1], show_progress=False)


def test_features_on_a_3dgs_model_folder_without_images_is_refused_before_any_model_loads(tmp_path, weights, capsys, monkeypatch):
    """Round 51 (F5): `features --source output/run1` (3DGS's model folder: cameras.json, no images/) built SAM and CLIP
    (minutes and gigabytes with the real models), then stopped with "input: camera 'DSC0001' has no image file". Now one
    error before any model loads, naming cameras.json, the folder looked in and where --source should point."""
    import json

    import drsplat.features.extract as extract

    def no_models(*args, **kwargs):
        raise AssertionError("a model was built")

    monkeypatch.setattr(extract, "build_models", no_models)
    run = tmp_path / "output" / "run1"
    run.mkdir(parents=True)
    (run / "cameras.json").write_text(json.dumps([{"id": 0, "img_name": "DSC0001", "width": 64, "height": 48, "position": [0, 0, -4],
                                                   "rotation": np.eye(3).tolist(), "fx": 50.0, "fy": 50.0}]))
    out = tmp_path / "features"
    assert main(slic_features_argv(run, out, weights)) == 1
    err = capsys.readouterr().err
    assert (f"{run / 'cameras.json'}: field 'img_name': none of its 1 cameras has an image (e.g. 'DSC0001'): the images are looked for "
            f"in {run / 'images'}, which does not exist") in err, err
    assert "give --source the dataset folder 3DGS trained from" in err
    assert not out.exists()


def test_pixels_an_undistorted_photo_never_saw_get_no_mask(tmp_path, weights, capsys):
    """Round 57b: undistorting a pincushion lens's photo fills the pinhole view's corners, which the photo never saw,
    with its edge pixels (fox: 1.6 % of every view); they were segmented and lifted like the scene. They get no mask
    now, on every level, and the run says how many views had such pixels."""
    import dataclasses
    import json

    from PIL import Image

    from drsplat.cameras import load_cameras, unobserved_pixels

    rng = np.random.default_rng(1)
    src = _one_camera_dataset(tmp_path / "ds", Image.fromarray(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)))
    meta = json.loads((src / "transforms.json").read_text())
    meta["frames"][0]["k1"] = 0.1
    (src / "transforms.json").write_text(json.dumps(meta))
    cam = load_cameras(src)[0]
    unseen = unobserved_pixels(cam, (64, 48))
    assert unseen[0, 0] and unseen[-1, -1] and not unseen[24, 32] and 0 < unseen.mean() < 0.5
    assert not unobserved_pixels(dataclasses.replace(cam, distortion=np.array([-0.1, 0, 0, 0])), (64, 48)).any()  # barrel: all seen
    assert unobserved_pixels(dataclasses.replace(cam, distortion=None), (64, 48)) is None
    assert main(slic_features_argv(src, tmp_path / "features", weights)) == 0
    seg = np.load(tmp_path / "features" / "view_s.npy")
    assert (seg[:, unseen] == -1).all() and (seg[:, ~unseen] >= 0).any()
    assert f"1 undistorted view(s) hold pixels their photo never saw (the lens maps them outside the file; the most: view, " \
           f"{100 * unseen.mean():.3g} %)" in capsys.readouterr().err


def test_a_resumed_folder_takes_its_dataset_named_another_way_and_refuses_another_dataset(tmp_path):
    """Round 57c: features made with `--source DATA/transforms.json` and resumed with `--source DATA` (one camera file)
    were refused as "made with source .../transforms.json, this run's is ...: resuming would mix the two". The camera
    files are compared now; another dataset is still refused."""
    from PIL import Image

    from drsplat.errors import DrsplatError
    from drsplat.features.extract import check_same_path

    data = _one_camera_dataset(tmp_path / "a", Image.new("RGB", (64, 48)))
    other = _one_camera_dataset(tmp_path / "b", Image.new("RGB", (64, 48)))
    check_same_path(tmp_path / "f", "source", "--source", str((data / "transforms.json").resolve()), str(data.resolve()))
    with pytest.raises(DrsplatError, match=r"holds features made with source .*a/transforms.json, this run's is .*b: resuming would mix"):
        check_same_path(tmp_path / "f", "source", "--source", str((data / "transforms.json").resolve()), str(other.resolve()))


@pytest.mark.parametrize("value", ["600:aa", 600, ["600:" + "ab" * 20], "600:" + "AB" * 20])
def test_a_manifests_clip_weights_that_is_not_a_digest_is_said_not_dropped(tmp_path, caplog, value):
    """A `clip_weights` that is not the 'size:sha1' `drsplat features` writes (hand-edited, damaged) used to be dropped without
    a word: the registered PLY then records no digest and queries check the text encoder by its name alone. It is a warning
    naming the file and field now; null (hub weights, no file) and a real digest are read without one."""
    import json

    path = tmp_path / featurefiles.MANIFEST_NAME
    for quiet in (None, "1234:" + "ab" * 20):
        path.write_text(json.dumps({"dim": 512, "clip_weights": quiet}))
        with caplog.at_level(logging.WARNING, logger="drsplat"):
            featurefiles.read_manifest(tmp_path)
        assert "clip_weights" not in caplog.text
    path.write_text(json.dumps({"dim": 512, "clip_weights": value}))
    with caplog.at_level(logging.WARNING, logger="drsplat"):
        featurefiles.read_manifest(tmp_path)
    assert f"{path}: field 'clip_weights' is {json.dumps(value)}, not the 'size:sha1' digest" in caplog.text
    assert "queries check the text encoder by its model name alone" in caplog.text


def test_images_without_a_mask_are_said_to_be_unreadable_by_langsplat():
    """Round 96b F1: an image that gave no mask is written as a feature file of no row beside a map of -1, which
    LangSplat's training cannot index (IndexError); the run said only that registration gets nothing from it."""
    from drsplat.features.extract import FeatureReport

    report = FeatureReport()
    report.without_masks.append("frame_0001")
    (note,) = report.notes()
    assert "1 image(s) gave no mask at all (frame_0001)" in note and "which LangSplat's own training cannot read" in note


def test_a_resumed_run_still_names_the_finished_images_that_gave_no_mask(tmp_path):
    """Round 96b F3: after Ctrl-C and a resume, the images finished before the interrupt were never named as mask-less."""
    from drsplat.cameras import Camera
    from drsplat.features import format as featurefiles
    from drsplat.features.extract import FeatureReport, todo_cameras

    out = tmp_path / "features"
    out.mkdir()
    cams = [Camera(R=np.eye(3), t=np.zeros(3), fx=10.0, fy=10.0, cx=4.0, cy=3.0, width=8, height=6, name=n) for n in ("a", "b")]
    featurefiles.write_features(out, "a", np.full((4, 6, 8), -1, np.int32), np.zeros((0, 512), np.float16))
    featurefiles.write_features(out, "b", np.zeros((4, 6, 8), np.int32), np.ones((1, 512), np.float16))
    report = FeatureReport()
    assert todo_cameras(cams, out, report) == [] and report.skipped == ["a", "b"]
    assert report.without_masks == ["a"] and "1 image(s) gave no mask at all (a)" in report.notes()[0]

