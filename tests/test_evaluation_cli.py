"""`drsplat eval` end to end on a registered synthetic scene, with LERF-OVS and ScanNet stand-ins."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from drsplat.cli import main
from drsplat.eval.datasets import write_labelled_points, write_lerf_view


@pytest.fixture(scope="module")
def registered(tmp_path_factory) -> dict:
    """A tiny synthetic dataset, its registered PLY (unassigned pruned) and stand-in annotations."""
    from PIL import Image

    from drsplat.synthetic import write_dataset

    root = tmp_path_factory.mktemp("eval")
    ds = write_dataset(root / "ds", "tiny", 0, show_progress=False)
    out = root / "registered.ply"
    assert main(["-q", "register", str(ds / "scene.ply"), "--source", str(ds), "--features", str(ds / "features"), "--out", str(out), "--no-progress"]) == 0
    names = json.loads((ds / "gt" / "label_names.json").read_text())
    label_dir = root / "label" / "tiny"
    for mask_file in sorted((ds / "gt" / "masks").glob("*.npy")):
        seg = np.load(mask_file)
        masks = {names[l]: seg == l for l in np.unique(seg) if l >= 0 and (seg == l).sum() >= 30}
        image = np.asarray(Image.open(ds / "images" / f"{mask_file.stem}.png").convert("RGB"))
        write_lerf_view(label_dir, mask_file.stem, masks, image)
    return {"root": root, "ds": ds, "ply": out, "labels": label_dir, "names": names}


def query_args(r: dict) -> list[str]:
    return ["--text-embeddings", str(r["ds"] / "text_embeddings.npy"), "--label-names", str(r["ds"] / "gt" / "label_names.json")]


def test_eval_iou_matches_the_library(registered, capsys):
    from drsplat.cameras import load_cameras
    from drsplat.eval.metrics import evaluate_scene
    from drsplat.lang import build_field
    from drsplat.registration import RegisterOptions, register_features
    from drsplat.scene import load_ply

    r = registered
    js = r["root"] / "iou.json"
    argv = ["eval", "iou", str(r["ply"]), "--gt-labels", str(r["ds"] / "gt" / "labels.npy"), "--original", str(r["ds"] / "scene.ply"),
            *query_args(r), "--json", str(js)]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "grid search (volume)" in printed and "mAcc" in printed
    doc = json.loads(js.read_text())
    got = {(x["task"], x["weighting"]): x for x in doc["reports"]}
    assert set(got) == {("loc", "volume"), ("seg", "volume"), ("loc", "count"), ("seg", "count")}

    scene = load_ply(r["ds"] / "scene.ply")
    res = register_features(scene, load_cameras(r["ds"]), r["ds"] / "features", RegisterOptions(), show_progress=False)
    scores = build_field(res.features, res.weights).scores(np.load(r["ds"] / "text_embeddings.npy"))
    gt = np.load(r["ds"] / "gt" / "labels.npy")
    expect = {(x.task, x.weighting): x for x in evaluate_scene(scene, scores, gt, r["names"], assigned=res.weights > 0)}
    for key, rep in expect.items():
        assert got[key]["mIoU"] == pytest.approx(rep.miou, abs=1e-6)
    assert got["seg", "volume"]["mIoU"] > 0.6  # oracle features: most labels are found
    assert 0.0 < got["loc", "volume"]["threshold"] < 1.0


def test_eval_iou_synthetic_shorthand(registered, capsys):
    r = registered
    assert main(["eval", "iou", str(r["ply"]), "--synthetic", str(r["ds"]), "--task", "loc", "--weighting", "volume"]) == 0
    out = capsys.readouterr().out
    assert "loc   volume" in out and "<- best" in out
    assert main(["eval", "iou", str(r["ply"]), *query_args(r)]) == 1
    assert "ground truth needed" in capsys.readouterr().err


@pytest.mark.parametrize("flags", [["--classes", "wall"], ["--radius", "2"], ["--classes", "wall", "--vote", "count"]])
def test_eval_iou_pseudo_label_flags_without_a_cloud_are_usage_errors(registered, capsys, flags):
    """--classes, --radius, --vote and --engine act on --gt-points only; with other ground truth they
    were ignored without a word (an unknown class gave exit 0)."""
    r = registered
    assert main(["eval", "iou", str(r["ply"]), "--synthetic", str(r["ds"]), *flags]) == 2
    err = capsys.readouterr().err
    named = [f for f in flags if f.startswith("--")]
    assert all(f in err for f in named) and "--gt-points" in err and "Traceback" not in err


def test_eval_iou_reports_label_count_mismatch(registered, capsys):
    r = registered
    code = main(["eval", "iou", str(r["ply"]), "--gt-labels", str(r["ds"] / "gt" / "labels.npy"), *query_args(r)])
    assert code == 1
    err = capsys.readouterr().err
    assert "labels.npy" in err and "--original" in err


def test_eval_lerf_on_stand_in(registered, capsys):
    r = registered
    js = r["root"] / "lerf.json"
    argv = ["eval", "lerf", str(r["ply"]), "--source", str(r["ds"]), "--annotations", str(r["labels"]), *query_args(r), "--json", str(js)]
    assert main(argv) == 0
    doc = json.loads(js.read_text())
    assert "mAcc@0.25" in capsys.readouterr().out
    assert len(doc["rows"]) >= 8 and not doc["missing_views"]
    assert doc["mIoU"] > 0.5 and doc["mAcc@0.25"] > 0.6


def test_lerf_protocol_with_ground_truth_and_wrong_selections(registered):
    from drsplat.cameras import load_cameras
    from drsplat.eval.datasets import load_lerf_annotations
    from drsplat.eval.lerf import lerf_2d_report
    from drsplat.scene import load_ply

    r = registered
    scene = load_ply(r["ds"] / "scene.ply")
    gt = np.load(r["ds"] / "gt" / "labels.npy")
    views = load_lerf_annotations(r["labels"])
    cams = load_cameras(r["ds"])
    right = {n: gt == l for l, n in enumerate(r["names"])}
    wrong = {n: gt == (l + 1) % len(r["names"]) for l, n in enumerate(r["names"])}
    good = lerf_2d_report(scene, cams, views, right, show_progress=False)
    bad = lerf_2d_report(scene, cams, views, wrong, show_progress=False)
    assert good.miou > 0.6 and good.acc_at(0.25) > 0.8
    assert bad.miou < 0.15


def test_lerf_protocol_single_gaussian_known_disc():
    from drsplat.eval.datasets import AnnotatedView
    from drsplat.eval.lerf import lerf_2d_report
    from drsplat.cameras import look_at_camera
    from drsplat.scene import GaussianScene

    cam = look_at_camera((0, 0, -5.0), (0, 0, 0), 120, 120, fov_x_deg=60.0)
    cam.name = "frame_00001"
    s = 0.4
    scene = GaussianScene(np.zeros((1, 3), np.float32), np.array([[1.0, 0, 0, 0]], np.float32), np.full((1, 3), np.log(s), np.float32),
                          np.array([20.0], np.float32), np.zeros((1, 1, 3), np.float32))
    # alpha = exp(-r²/2σ²) > 0.5 inside r = σ·sqrt(2 ln 2), σ in pixels ≈ fx·s/z
    sigma = np.sqrt((cam.fx * s / 5.0) ** 2 + 0.3)
    yy, xx = np.mgrid[0:120, 0:120] + 0.5
    disc = (xx - cam.cx) ** 2 + (yy - cam.cy) ** 2 <= (sigma * np.sqrt(2 * np.log(2))) ** 2
    view = AnnotatedView("frame_00001", 120, 120, {"blob": disc, "nothing": np.zeros((120, 120), bool)})
    rep = lerf_2d_report(scene, [cam], [view], {"blob": np.array([True]), "nothing": np.array([False])}, show_progress=False)
    ious = {row.category: row.iou for row in rep.rows}
    assert ious["blob"] > 0.95
    assert ious["nothing"] == 1.0  # empty prediction of an empty mask
    half = cam.scaled(0.5)  # annotations at half resolution pair with the same camera
    view2 = AnnotatedView("frame_00001", 60, 60, {"blob": disc[::2, ::2]})
    assert lerf_2d_report(scene, [cam], [view2], {"blob": np.array([True])}, show_progress=False).rows[0].iou > 0.85
    assert half.width == 60


def scannet_stand_in(r: dict) -> Path:
    """A ScanNet-layout scene folder whose labelled vertices are sampled inside the labelled Gaussians."""
    from drsplat.scene import load_ply

    scan = r["root"] / "scans" / "scene0000_00"
    path = scan / "scene0000_00_vh_clean_2.labels.ply"
    if path.exists():
        return scan
    scene = load_ply(r["ds"] / "scene.ply")
    gt = np.load(r["ds"] / "gt" / "labels.npy")
    rng = np.random.default_rng(0)
    labelled = np.flatnonzero(gt >= 0)
    chol = np.linalg.cholesky(scene.covariances()[labelled].astype(np.float64) + 1e-12 * np.eye(3))
    pts = scene.means[labelled, None, :] + 0.5 * np.einsum("nij,nsj->nsi", chol, rng.normal(size=(len(labelled), 3, 3)))
    scan.mkdir(parents=True)
    write_labelled_points(path, pts.reshape(-1, 3), np.repeat(gt[labelled] + 1, 3))
    return scan


def test_eval_scannet_stand_in_and_pseudolabels(registered, capsys):
    r = registered
    scan = scannet_stand_in(r)
    gt = np.load(r["ds"] / "gt" / "labels.npy")
    labelled = np.flatnonzero(gt >= 0)
    names_json = r["ds"] / "gt" / "label_names.json"
    saved = r["root"] / "pseudo.npy"
    argv = ["eval", "scannet", str(r["ply"]), "--scene-dir", str(scan), "--original", str(r["ds"] / "scene.ply"), "--save-labels", str(saved),
            "--label-names", str(names_json), "--text-embeddings", str(r["ds"] / "text_embeddings.npy"), "--weighting", "volume,count,voxel",
            "--voxel-resolution", "32"]
    assert main(argv) == 0
    assert "voxel" in capsys.readouterr().out
    pseudo = np.load(saved)
    assert np.mean(pseudo[labelled] == gt[labelled]) > 0.9
    out = r["root"] / "pl.npy"
    assert main(["eval", "pseudolabels", str(r["ds"] / "scene.ply"), "--points", str(scan / "scene0000_00_vh_clean_2.labels.ply"),
                 "--label-names", str(names_json), "--out", str(out), "--names-out", str(r["root"] / "pl.json")]) == 0
    np.testing.assert_array_equal(np.load(out), pseudo)
    assert json.loads((r["root"] / "pl.json").read_text()) == r["names"]


def test_eval_iou_from_points_with_class_subset(registered, capsys):
    r = registered
    cloud = scannet_stand_in(r) / "scene0000_00_vh_clean_2.labels.ply"
    keep = ["table", "ball"]
    emb = np.load(r["ds"] / "text_embeddings.npy")[[r["names"].index(k) for k in keep]]
    np.save(r["root"] / "two.npy", emb)
    js = r["root"] / "two.json"
    argv = ["eval", "iou", str(r["ply"]), "--gt-points", str(cloud), "--classes", ",".join(keep), "--original", str(r["ds"] / "scene.ply"),
            "--label-names", str(r["ds"] / "gt" / "label_names.json"), "--text-embeddings", str(r["root"] / "two.npy"),
            "--task", "seg", "--weighting", "count", "--json", str(js)]
    assert main(argv) == 0
    doc = json.loads(js.read_text())
    assert doc["labels"] == keep
    (rep,) = doc["reports"]
    assert (rep["task"], rep["weighting"]) == ("seg", "count")
    # two well-separated objects, argmax between just the two: near perfect
    assert rep["mIoU"] > 0.9


def test_eval_cli_rejects_bad_options(registered, capsys):
    r = registered
    base = ["eval", "iou", str(r["ply"]), "--gt-labels", str(r["ds"] / "gt" / "labels.npy"), "--original", str(r["ds"] / "scene.ply"), *query_args(r)]
    assert main(base + ["--taus", "1:0:0.1"]) == 2  # a usage error, as argparse would give
    assert "--taus" in capsys.readouterr().err
    assert main(base + ["--weighting", "volume,mass"]) == 1
    assert "mass" in capsys.readouterr().err
    bad = r["root"] / "bad_labels.npy"
    np.save(bad, np.full(np.load(r["ds"] / "gt" / "labels.npy").shape, 99))
    assert main(["eval", "iou", str(r["ply"]), "--gt-labels", str(bad), "--original", str(r["ds"] / "scene.ply"), *query_args(r)]) == 1
    assert "bad_labels.npy" in capsys.readouterr().err


@pytest.mark.slow
def test_eval_ablate_topk_writes_table_and_plot(registered, tmp_path, capsys):
    (tmp_path / "datasets").mkdir()
    (tmp_path / "datasets" / "tiny-s0-m0-n0.15").symlink_to(registered["ds"], target_is_directory=True)  # the cache: no re-synthesis
    assert main(["-q", "eval", "ablate", "topk", "--values", "1,20", "--out-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| top-k | loc mIoU |" in out
    doc = json.loads((tmp_path / "ablation_topk.json").read_text())
    assert [row[0] for row in doc["rows"]] == [1, 20]
    # more Gaussians per pixel: fewer Gaussians left without weight
    assert doc["rows"][0][3] >= doc["rows"][1][3]
    assert (tmp_path / "ablation_topk.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_eval_ablate_resolution_reports_error_against_time(registered, tmp_path, capsys):
    """Views at 1/r of their size: the table names each size, the first resolution is the speed-up's
    unit, and halving the views changes what is registered (fewer pixels, resampled masks)."""
    (tmp_path / "datasets").mkdir()
    (tmp_path / "datasets" / "tiny-s0-m0-n0.15").symlink_to(registered["ds"], target_is_directory=True)  # the cache: no re-synthesis
    assert main(["-q", "eval", "ablate", "resolution", "--values", "1,2", "--modes", "paper", "--out-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| resolution | mode | views | seg mIoU vol |" in out
    doc = json.loads((tmp_path / "ablation_resolution.json").read_text())
    cols = doc["columns"]
    full, half = doc["rows"]
    assert (full[0], full[2], half[0], half[2]) == (1, "128x96", 2, "64x48")
    assert full[cols.index("speed-up")] == 1.0 and half[cols.index("ms/view")] > 0
    assert 0.0 < half[cols.index("labelled coverage")] <= 1.0
    assert half[3:7] != full[3:7]
    assert (tmp_path / "ablation_resolution.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for values in ("0,2", "3"):  # 3 would be a 3-pixel width to `register --resolution`, not a divisor
        assert main(["-q", "eval", "ablate", "resolution", "--values", values, "--out-dir", str(tmp_path)]) == 1
        assert "not a resolution divisor" in capsys.readouterr().err


@pytest.mark.parametrize("change, index, words", [
    (lambda names: names[:1] + names[:1] + names[2:], 1, "repeats the name"),
    (lambda names: names[:1] + ["a\nb"] + names[2:], 1, "control character"),
    (lambda names: names[:2] + [""] + names[3:], 2, "empty name"),
], ids=["duplicate", "newline", "empty"])
def test_eval_label_names_get_the_names_checks(registered, tmp_path, capsys, change, index, words):
    """--label-names labels the printed tables and the JSON report: a repeated, blank or
    control-character name is one error naming the file and the entry, as segment's --names is."""
    r = registered
    bad = tmp_path / "names.json"
    bad.write_text(json.dumps(change(list(r["names"]))))
    js = tmp_path / "iou.json"
    argv = ["eval", "iou", str(r["ply"]), "--gt-labels", str(r["ds"] / "gt" / "labels.npy"), "--original", str(r["ds"] / "scene.ply"),
            "--text-embeddings", str(r["ds"] / "text_embeddings.npy"), "--label-names", str(bad), "--json", str(js)]
    assert main(argv) == 1 and not js.exists()
    err = capsys.readouterr().err
    assert "names.json" in err and f"entry {index} " in err and words in err, err


def test_corruption_costs_compare_each_corruption_with_its_reference_room():
    """mislabel10 against jitter2 (the same masks without the mislabels), the others against clean;
    mean over presets and the worst one; nothing without a reference in the rows."""
    from drsplat.eval.ablations import AGGREGATE_COLUMNS, AblationResult, corruption_costs

    seg = AGGREGATE_COLUMNS.index("seg mIoU vol")

    def row(name, mode, value):
        r = [name, mode, 40] + [0.0] * (len(AGGREGATE_COLUMNS) - 3)
        r[seg] = value
        return r

    values = {("a", "clean"): 0.9, ("a", "jitter2"): 0.8, ("a", "mislabel10"): 0.7, ("b", "clean"): 0.6, ("b", "jitter2"): 0.5,
              ("b", "mislabel10"): 0.1}
    rows = [row(f"{p} render {c}", m, v - (0.05 if m == "other" else 0.0)) for (p, c), v in values.items() for m in ("paper", "other")]
    table = corruption_costs(AblationResult("aggregate", list(AGGREGATE_COLUMNS), rows), 40)
    lines = table.splitlines()
    assert "render mislabel10 (vs jitter2)" in lines[2] and "render jitter2 (vs clean)" in lines[2]
    assert lines[4].startswith("| paper | 0.250 (0.400 b) | 0.100 (0.100 a) |"), lines[4]
    assert corruption_costs(AblationResult("aggregate", list(AGGREGATE_COLUMNS), [row("a render mislabel10", "paper", 0.5)]), 40) == ""
