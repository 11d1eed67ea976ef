"""Aggregation modes: kernels vs references, floater rejection, the hook in registration, CLI, and
the recommended mode against the paper's on a tiny hard room."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from drsplat.aggregate import (
    ANCHOR_GAIN,
    MODES,
    WEIGHTINGS,
    Aggregator,
    footprint_area,
    rejected,
    split_mode,
    surface_stats,
    surface_stats_reference,
    view_weights,
    view_weights_reference,
)
from drsplat.cameras import load_cameras, look_at_camera
from drsplat.errors import Cancelled
from drsplat.raster import project_gaussians, rasterize
from drsplat.registration import register_scene
from drsplat.scene import GaussianScene, load_ply
from drsplat.synthetic import write_dataset
from drsplat.utils import CancelToken

RECOMMENDED = "reject"


@pytest.fixture(scope="module")
def hard_tiny(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("agg") / "hard-tiny", "hard-tiny", 0, show_progress=False)


def _random_view(rng, h, w, k, n, case):
    """Top-k lists like the rasterizer's (distinct ids per pixel, -1 padded) plus projections."""
    ids = np.full((h, w, k), -1, np.int32)
    weights = np.zeros((h, w, k), np.float32)
    for y in range(h):
        for x in range(w):
            count = 0 if (case == "all_empty" or rng.random() < 0.2) else int(rng.integers(1, min(k, n) + 1))
            ids[y, x, :count] = rng.choice(n, size=count, replace=False)
            weights[y, x, :count] = np.sort(rng.uniform(1e-4, 0.6, count))[::-1]
    means2d = np.c_[rng.uniform(-5, w + 5, n), rng.uniform(-5, h + 5, n)]
    sig = rng.uniform(0.3, 6.0, (n, 2))
    rho = rng.uniform(-0.9, 0.9, n)
    cov = np.stack([sig[:, 0] ** 2, rho * sig[:, 0] * sig[:, 1], sig[:, 1] ** 2], 1)
    det = cov[:, 0] * cov[:, 2] - cov[:, 1] ** 2
    conics = np.stack([cov[:, 2] / det, -cov[:, 1] / det, cov[:, 0] / det], 1)
    depths = rng.uniform(0.5, 10.0, n).astype(np.float32)
    if case == "hard":
        conics[:3] = [[1e6, 0.0, 1e6], [1e-8, 0.0, 1e-8], [3.3, 0.0, 3.3]]  # needle-thin, huge, blur-only
        means2d[3] = [1e7, -1e7]  # far off-screen
        depths[4:8] = depths[3]  # depth ties
        weights[0, 0, :] = np.where(ids[0, 0] >= 0, 0.0, weights[0, 0])  # zero weights in a pixel
    return ids, weights, means2d, conics, depths


@pytest.mark.parametrize("case", ["random", "hard", "all_empty", "k1"])
@pytest.mark.parametrize("weighting", WEIGHTINGS)
def test_view_weights_kernel_agrees_with_reference(weighting, case):
    rng = np.random.default_rng(abs(hash((weighting, case))) % 2**32)
    k = 1 if case == "k1" else 6
    ids, weights, means2d, conics, _ = _random_view(rng, 9, 13, k, 40, case)
    got = view_weights(weighting, ids, weights, means2d, conics)
    want = view_weights_reference(weighting, ids, weights, means2d, conics)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9)
    bound = {"responsibility": np.ones_like(weights),
             "anchor": weights * (1.0 + ANCHOR_GAIN * footprint_area(conics)[np.maximum(ids, 0)])}.get(weighting, weights)
    assert (got[ids < 0] == 0).all() and (got <= bound * (1 + 1e-6) + 1e-6).all()
    if weighting == "paper":
        np.testing.assert_array_equal(got, np.where(ids >= 0, weights, 0))


@pytest.mark.parametrize("case", ["random", "hard", "all_empty", "k1"])
def test_surface_stats_kernel_agrees_with_reference(case):
    rng = np.random.default_rng(abs(hash(case)) % 2**32)
    k = 1 if case == "k1" else 12  # more slots than the surface depth looks at
    n = 40
    got = [np.zeros(n) for _ in range(3)]
    want = [np.zeros(n) for _ in range(3)]
    for _ in range(3):  # several views accumulate
        ids, weights, _, _, depths = _random_view(rng, 7, 11, k, n, case)
        surface_stats(ids, weights, depths, *got)
        surface_stats_reference(ids, weights, depths, *want)
    for g, w in zip(got, want):
        np.testing.assert_allclose(g, w, rtol=1e-9, atol=1e-12)
    peak, total, front = got
    assert (front <= total + 1e-12).all() and (peak <= total + 1e-12).all()


def test_surface_depth_and_rejection_rule_by_hand():
    # pixel 0: floater (id 0, z=1, w=0.1) in front of a wall (id 1, z=5, w=0.85): the wall is the surface
    # pixel 1: a faint Gaussian on the wall (id 2, z=5.02, w=0.1) behind the wall Gaussian: on the surface
    # pixel 2: a thin opaque pole (id 3, z=3, w=0.6) in front of the wall: the pole itself is the surface
    ids = np.array([[[1, 0], [1, 2], [3, 1]]], np.int32)
    weights = np.array([[[0.85, 0.1], [0.85, 0.1], [0.6, 0.35]]], np.float32)
    depths = np.array([1.0, 5.0, 5.02, 3.0], np.float32)
    peak, total, front = np.zeros(4), np.zeros(4), np.zeros(4)
    surface_stats(ids, weights, depths, peak, total, front)
    np.testing.assert_allclose(front, [0.1, 0.0, 0.0, 0.0], atol=1e-7)
    np.testing.assert_array_equal(rejected(peak, total, front), [True, False, False, False])
    # a faint Gaussian in front that is the dominant contribution somewhere (peak ≥ ½) is kept
    assert not rejected(np.array([0.5]), np.array([1.0]), np.array([1.0]))[0]


def test_mode_names():
    assert split_mode("paper") == ("paper", False) and split_mode("reject") == ("paper", True)
    assert split_mode("core-reject") == ("core", True) and set(MODES) >= set(WEIGHTINGS)
    with pytest.raises(ValueError, match="unknown aggregation mode"):
        split_mode("median")


def test_rejection_on_a_rendered_wall():
    """A faint floater in mid-air is rejected; a faint Gaussian lying in the wall is kept."""
    rng = np.random.default_rng(0)
    gx, gy = np.meshgrid(np.linspace(-1, 1, 30), np.linspace(-1, 1, 30))
    wall = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, 3.0)]
    means = np.concatenate([wall, [[0.1, 0.1, 1.5], [0.3, -0.2, 3.0]]]).astype(np.float32)
    n = len(means)
    log_scales = np.log(np.tile([0.05, 0.05, 0.002], (n, 1)))
    log_scales[-2] = np.log(0.05)
    opac = np.full(n, 0.95)
    opac[-2:] = 0.12  # the floater and the faint wall Gaussian
    quats = np.tile([1.0, 0, 0, 0], (n, 1))
    scene = GaussianScene(means=means, quats=quats.astype(np.float32), log_scales=log_scales.astype(np.float32),
                          opacity_logits=np.log(opac / (1 - opac)).astype(np.float32), sh=rng.uniform(0, 1, (n, 1, 3)).astype(np.float32))
    agg = Aggregator("reject", n)
    for eye in ([0, 0, -1.0], [0.6, 0.2, -1.0], [-0.5, -0.4, -0.8]):
        cam = look_at_camera(eye, [0, 0, 3.0], 64, 48)
        out = rasterize(scene, cam, topk=8)
        np.testing.assert_array_equal(agg.view_weights(scene, cam, out), out.weights)  # weights untouched
    drop = agg.support.rejected()
    assert drop[-2] and not drop[-1] and not drop[:-2].any()


def test_core_weights_equal_the_compositor_falloff():
    """For 'core', w·exp(-½ d²) = T·o·exp(-d²) where α = o·exp(-½ d²) < 0.99: check against the rasterizer's own α."""
    scene = GaussianScene(means=np.array([[0.0, 0.0, 4.0]], np.float32), quats=np.array([[1.0, 0, 0, 0]], np.float32),
                          log_scales=np.log(np.array([[0.2, 0.1, 0.1]], np.float32)),
                          opacity_logits=np.array([0.0], np.float32), sh=np.zeros((1, 1, 3), np.float32))
    cam = look_at_camera([0, 0, 0], [0, 0, 4.0], 40, 30)
    out = rasterize(scene, cam, topk=1)
    proj = project_gaussians(scene, cam)
    core = view_weights("core", out.ids, out.weights, proj.means2d, proj.conics)
    hit = out.ids[..., 0] == 0
    alpha = out.weights[..., 0][hit]  # T = 1: w = α = 0.5·exp(-½ d²)
    np.testing.assert_allclose(core[..., 0][hit], alpha * (alpha / 0.5), rtol=1e-5)


def test_paper_mode_is_the_default_and_unchanged(hard_tiny):
    scene, cams = load_ply(hard_tiny / "scene.ply"), load_cameras(hard_tiny)
    a = register_scene(scene, cams, hard_tiny / "features", topk=10, show_progress=False)
    b = register_scene(scene, cams, hard_tiny / "features", topk=10, show_progress=False, aggregate="paper")
    np.testing.assert_array_equal(a.features, b.features)
    assert a.aggregate == "paper" and a.num_rejected == 0


def test_resume_keeps_rejection_statistics(hard_tiny, tmp_path):
    scene, cams = load_ply(hard_tiny / "scene.ply"), load_cameras(hard_tiny)
    full = register_scene(scene, cams, hard_tiny / "features", topk=10, show_progress=False, aggregate=RECOMMENDED)
    ckpt = tmp_path / "run.npz"
    token = CancelToken()

    def stop(done: int, total: int) -> None:
        if done == 4:
            token.cancel()

    with pytest.raises(Cancelled):
        register_scene(scene, cams, hard_tiny / "features", topk=10, checkpoint=ckpt, checkpoint_every=2, cancel=token,
                       on_progress=stop, show_progress=False, aggregate=RECOMMENDED)
    resumed = register_scene(scene, cams, hard_tiny / "features", topk=10, checkpoint=ckpt, show_progress=False, aggregate=RECOMMENDED)
    assert resumed.resumed_views == 4 and resumed.num_rejected == full.num_rejected > 0
    np.testing.assert_array_equal(resumed.weights, full.weights)
    np.testing.assert_allclose(resumed.features, full.features, atol=1e-6)


def test_recommended_mode_beats_paper_and_rejects_floaters(hard_tiny):
    """On hard-tiny seed 0, top-k 40 (measured, paper -> reject): seg mIoU vol with unlabelled as false
    positives 0.852 -> 0.889, loc mIoU vol 0.876 -> 0.928, labelled-only seg 0.890 -> 0.889, floaters
    kept 1.00 -> 0.09, labelled coverage 1.000 -> 0.996. Asserted with slack."""
    from drsplat.eval.ablations import AGGREGATE_COLUMNS, Dataset, aggregate_metrics

    ds = Dataset(hard_tiny, load_ply(hard_tiny / "scene.ply"), load_cameras(hard_tiny), np.load(hard_tiny / "gt" / "labels.npy").astype(np.int64),
                 json.loads((hard_tiny / "gt" / "label_names.json").read_text()), np.load(hard_tiny / "text_embeddings.npy"))
    col = {c: i - 3 for i, c in enumerate(AGGREGATE_COLUMNS)}
    paper = aggregate_metrics(ds, register_scene(ds.scene, ds.cameras, hard_tiny / "features", show_progress=False))
    best = aggregate_metrics(ds, register_scene(ds.scene, ds.cameras, hard_tiny / "features", show_progress=False, aggregate=RECOMMENDED))
    assert best[col["seg mIoU vol +unl"]] >= paper[col["seg mIoU vol +unl"]] + 0.02
    assert best[col["loc mIoU vol"]] >= paper[col["loc mIoU vol"]] + 0.02
    assert best[col["seg mIoU vol"]] >= paper[col["seg mIoU vol"]] - 0.01  # labelled-only: about the same
    assert paper[col["floaters kept"]] > 0.9 and best[col["floaters kept"]] < 0.3
    assert best[col["labelled coverage"]] >= 0.99


def test_cli_lists_modes_and_rejects_unknown(hard_tiny, tmp_path):
    help_text = subprocess.run([sys.executable, "-m", "drsplat", "register", "--help"], capture_output=True, text=True, check=False).stdout
    assert all(m in help_text for m in MODES)
    bad = subprocess.run([sys.executable, "-m", "drsplat", "register", str(hard_tiny / "scene.ply"), "--source", str(hard_tiny),
                          "--features", str(hard_tiny / "features"), "--out", str(tmp_path / "x.ply"), "--aggregate", "median"],
                         capture_output=True, text=True, check=False)
    assert bad.returncode == 2 and "median" in bad.stderr and not (tmp_path / "x.ply").exists()
    torch_engine = subprocess.run([sys.executable, "-m", "drsplat", "register", str(hard_tiny / "scene.ply"), "--source", str(hard_tiny),
                                   "--features", str(hard_tiny / "features"), "--out", str(tmp_path / "x.ply"), "--aggregate", "reject",
                                   "--engine", "torch"], capture_output=True, text=True, check=False)
    assert torch_engine.returncode == 1 and "numba engine only" in torch_engine.stderr and not (tmp_path / "x.ply").exists()


def test_pipeline_writes_fewer_gaussians_with_rejection(hard_tiny, tmp_path):
    from drsplat.pipeline import RegisterOptions, register_to_ply

    scene, cams = load_ply(hard_tiny / "scene.ply"), load_cameras(hard_tiny)
    paper = register_to_ply(scene, cams, hard_tiny / "features", tmp_path / "paper.ply", RegisterOptions(topk=10), show_progress=False)
    rej = register_to_ply(scene, cams, hard_tiny / "features", tmp_path / "rej.ply", RegisterOptions(topk=10, aggregate="reject"),
                          show_progress=False)
    assert rej.registration.num_rejected > 0
    assert rej.num_written == paper.num_written - rej.registration.num_rejected
