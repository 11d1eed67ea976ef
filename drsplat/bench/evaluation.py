"""`drsplat bench eval`: speed of the evaluation kernels, each against its obviously-correct reference.

- pseudo-labels: the numba grid engine and the KD-tree engine vs every point against every
  Gaussian (on a subset small enough for the reference), then the two engines at full size;
- voxel splatting: numba kernel vs the dense numpy reference;
- localisation grid search: one sort + binary searches vs one weighted IoU per threshold.
Every row reports the accuracy cost next to the speed-up (all three are exact, so it is 0).

A second table gives the voxel IoU's one approximation, its grid (`eval iou --voxel-resolution`):
per resolution its time, the bytes its grid holds and its mIoU, against the finest resolution asked.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from drsplat.bench.common import MAX_BENCH_GAUSSIANS, count_upto, format_table, gaussian_count, int_list, machine_line, median_seconds
from drsplat.commands.common import int_range, positive_int
from drsplat.commands.eval import check_voxel_memory
from drsplat.defaults import VOXEL_EMPTY, VOXEL_RESOLUTION

VOXEL_BENCH_RESOLUTIONS = "32,64,96,192"
VOXEL_BENCH_MISLABEL = 0.1  # the share of labelled Gaussians the scored prediction gets wrong


def add_bench(subparsers: argparse._SubParsersAction) -> None:
    from drsplat.synthetic import PRESETS

    p = subparsers.add_parser("eval", help="evaluation kernels (pseudo-labels, voxel IoU, threshold search) vs their references")
    p.add_argument("--scene", type=Path, default=None, help="a 3DGS PLY to label (default: random Gaussians)")
    p.add_argument("--gaussians", type=gaussian_count, default=200_000, help="random Gaussians when no --scene (e.g. 200k, at most 100M)")
    p.add_argument("--points", type=count_upto(MAX_BENCH_GAUSSIANS, "point count"), default=1_000_000,
                   help="labelled points, sampled around the Gaussians (e.g. 1M, at most 100M)")
    p.add_argument("--repeats", type=positive_int, default=3, help="timed repeats (median reported)")
    p.add_argument("--voxel-resolutions", type=int_list(int_range(1, 512)), default=VOXEL_BENCH_RESOLUTIONS, metavar="LIST",
                   help=f"voxel IoU table: the grid resolutions to compare, the finest the reference (default {VOXEL_BENCH_RESOLUTIONS}; "
                        f"`eval iou` uses {VOXEL_RESOLUTION})")
    p.add_argument("--voxel-preset", choices=sorted(PRESETS), default="hard-room",
                   help="voxel IoU table: the synthetic room whose exact labels are scored (default hard-room)")
    p.set_defaults(func=run)


def random_gaussians(n: int, rng: np.random.Generator):
    from drsplat.scene import quat_to_rotmat

    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    means = rng.uniform(-5, 5, (n, 3))
    scales = np.exp(rng.normal(np.log(0.03), 0.7, (n, 3)))
    return means, quat_to_rotmat(q), scales


def labelled_points(means: np.ndarray, p: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Points scattered around random Gaussians by 0.5% of the scene extent, with 20 classes."""
    src = rng.integers(0, len(means), p)
    extent = float(np.ptp(means, axis=0).max())
    pts = means[src] + rng.normal(0, 0.005 * extent, (p, 3))
    return pts, (src * 7919 % 20).astype(np.int64) - 1  # 20 classes incl. "unannotated"


def run(args: argparse.Namespace) -> int:
    from drsplat.eval.metrics import VoxelGrid, splat_mass, splat_mass_reference, threshold_iou_curve, weighted_iou
    from drsplat.synthetic import make_synthetic
    from drsplat.eval.pseudolabels import pseudo_labels, pseudo_labels_reference

    voxel_room = make_synthetic(args.voxel_preset, 0)
    # before any work (round 105a F7: 512 on hard-room, 7.2 GiB, ended the run in "out of memory" after the first table)
    check_voxel_memory(max(args.voxel_resolutions), voxel_room.scene, voxel_room.labels >= 0, len(voxel_room.label_names), True,
                       flag="--voxel-resolutions")
    rng = np.random.default_rng(0)
    if args.scene is not None:
        from drsplat.scene import load_ply

        scene = load_ply(args.scene, purpose="benchmark")  # a file of no Gaussians: one error, not numpy's
        g = (scene.means.astype(np.float64), scene.rotations().astype(np.float64), scene.scales().astype(np.float64))
    else:
        g = random_gaussians(args.gaussians, rng)
    n = len(g[0])
    pts, labels = labelled_points(g[0], args.points, rng)
    print(machine_line())
    rows = []

    # pseudo-labels: reference on a small subset, both engines on the same subset and at full size
    sub = rng.choice(n, size=min(n, 200), replace=False)
    gs = tuple(a[sub] for a in g)
    few = rng.choice(len(pts), size=min(len(pts), 20_000), replace=False)
    ref_labels = pseudo_labels_reference(gs, pts[few], labels[few])
    # the references timed as the kernels are, medians of --repeats after a warm-up (round 101b F3: one run each, beside medians)
    t_ref = median_seconds(lambda: pseudo_labels_reference(gs, pts[few], labels[few]), args.repeats)
    labelled = ref_labels >= 0
    for engine in ("grid", "kdtree"):
        t_sub = median_seconds(lambda: pseudo_labels(gs, pts[few], labels[few], engine=engine, show_progress=False), args.repeats)
        got = pseudo_labels(gs, pts[few], labels[few], engine=engine, show_progress=False).labels
        # round 101b F4: most of the subset has no label in either, so the agreement among those the reference labels too
        among = (f"{np.mean(got[labelled] == ref_labels[labelled]):.4f} on the {int(labelled.sum())} the reference labels" if labelled.any()
                 else "the reference labels none")
        rows.append([f"pseudo-labels ({engine}) {len(sub)} G x {len(few)} pts", t_ref, t_sub, t_ref / t_sub,
                     f"{np.mean(got == ref_labels):.4f} agree ({among})"])
    full = {}
    for engine in ("grid", "kdtree"):
        t0 = time.perf_counter()
        full[engine] = pseudo_labels(g, pts, labels, engine=engine, show_progress=False)
        full[engine + "_s"] = time.perf_counter() - t0
    same = float(np.mean(full["grid"].labels == full["kdtree"].labels))
    rows.append([f"pseudo-labels {n} G x {len(pts)} pts: kdtree vs grid (one run each)", full["kdtree_s"], full["grid_s"], full["kdtree_s"] / full["grid_s"],
                 f"{same:.4f} agree, {np.mean(full['grid'].labels >= 0):.3f} labelled, {int(full['grid'].num_points.sum())} points within r"])

    # voxel splatting
    m = 1000
    means = rng.uniform(-1, 1, (m, 3))
    a = rng.normal(size=(m, 3, 3)) * 0.05
    covs = a @ a.transpose(0, 2, 1) + 1e-4 * np.eye(3)
    alpha = rng.uniform(0.1, 1, m)
    ch = rng.integers(0, 4, m)
    grid = VoxelGrid(np.full(3, -1.1), 2.2 / 32, (32, 32, 32))
    t_ref = median_seconds(lambda: splat_mass_reference(means, covs, alpha, ch, 4, grid), args.repeats)
    t_fast = median_seconds(lambda: splat_mass(means, covs, alpha, ch, 4, grid), args.repeats)
    diff = float(np.abs(splat_mass(means, covs, alpha, ch, 4, grid) - splat_mass_reference(means, covs, alpha, ch, 4, grid)).max())
    rows.append([f"voxel splat {m} G, 32^3 voxels", t_ref, t_fast, t_ref / t_fast, f"max |diff| {diff:.1e}"])

    # localisation threshold grid
    k = 1_000_000
    scores = rng.random(k)
    gt = rng.random(k) < 0.1
    w = rng.random(k)
    taus = np.linspace(0, 1, 101)
    t_ref = median_seconds(lambda: [weighted_iou(scores > t, gt, w) for t in taus], args.repeats)
    t_fast = median_seconds(lambda: threshold_iou_curve(scores, gt, w, taus), args.repeats)
    diff = float(np.nanmax(np.abs(threshold_iou_curve(scores, gt, w, taus) - np.array([weighted_iou(scores > t, gt, w) for t in taus]))))
    rows.append([f"loc grid search {k} G x 101 tau", t_ref, t_fast, t_ref / t_fast, f"max |diff| {diff:.1e}"])

    print(format_table(["kernel", "reference s", "drsplat s", "speed-up", "accuracy"], rows))
    print()
    print(voxel_resolution_table(voxel_room, args.voxel_resolutions, args.repeats))
    return 0


def mislabelled_scores(gt: np.ndarray, num_labels: int, share: float, rng: np.random.Generator) -> np.ndarray:
    """[N, L] one-hot scores of the labels `gt` [N] with `share` of the labelled Gaussians given another label (a
    prediction with known errors: its IoU is below 1 by an amount every weighting should see)."""
    pred = np.asarray(gt, np.int64).copy()
    wrong = (pred >= 0) & (rng.random(len(pred)) < share)
    if num_labels > 1:
        pred[wrong] = (pred[wrong] + rng.integers(1, num_labels, int(wrong.sum()))) % num_labels
    scores = np.zeros((len(pred), num_labels), np.float32)
    scores[np.flatnonzero(pred >= 0), pred[pred >= 0]] = 1.0
    return scores


def voxel_resolution_table(syn, resolutions: list[int], repeats: int) -> str:
    """Speed against error of the voxel IoU's grid: on a synthetic room's exact labels, a prediction with
    VOXEL_BENCH_MISLABEL of them wrong, scored at each resolution (the segmentation and the localisation at the τ
    of the volume-aware search, as `eval iou --weighting voxel` does); the error column is each resolution's
    |ΔmIoU| against the finest one asked. The empty threshold is a mass per voxel (VOXEL_EMPTY), so the occupied
    set itself changes with the resolution: the finest grid is a reference, not the exact continuum. syn: the room
    (`synthetic.make_synthetic`)."""
    from drsplat.eval.metrics import (VoxelSetup, localisation_report, scene_weights, segmentation_report, voxel_iou_bytes, voxel_localisation_report,
                                      voxel_segmentation_report)
    gt = syn.labels.astype(np.int64)
    names = list(syn.label_names)
    scores = mislabelled_scores(gt, len(names), VOXEL_BENCH_MISLABEL, np.random.default_rng(1))
    w, bad = scene_weights(syn.scene, "volume")
    loc_volume = localisation_report(scores, gt, w, names, None, "volume", bad)
    seg_volume = segmentation_report(scores, gt, w, names, "volume", bad)

    def voxel_ious(resolution: int) -> tuple[float, float, int]:
        setup = VoxelSetup.from_scene(syn.scene, resolution, VOXEL_EMPTY, focus=gt >= 0)
        seg = voxel_segmentation_report(setup, scores, gt, names)
        loc = voxel_localisation_report(setup, scores, gt, loc_volume.threshold, names)
        return float(np.nanmean(seg.iou)), float(np.nanmean(loc.iou)), voxel_iou_bytes(setup.grid, len(names))

    measured = {r: (median_seconds(lambda r=r: voxel_ious(r), repeats), *voxel_ious(r)) for r in sorted(set(resolutions))}
    finest = max(measured)
    _, seg_ref, loc_ref, _ = measured[finest]
    rows = [[r, t, f"{grid_bytes / 2**20:.1f}", f"{seg:.4f}", f"{abs(seg - seg_ref):.4f}", f"{loc:.4f}", f"{abs(loc - loc_ref):.4f}"]
            for r, (t, seg, loc, grid_bytes) in measured.items()]
    title = (f"voxel IoU against its grid: {syn.preset} seed {syn.seed}, {syn.scene.num_gaussians} Gaussians, {len(names)} labels, the exact labels with "
             f"{VOXEL_BENCH_MISLABEL:.0%} wrong (volume-aware: seg mIoU {float(np.nanmean(seg_volume.iou)):.4f}, loc {float(np.nanmean(loc_volume.iou)):.4f}); "
             f"|Δ| against {finest}, empty below {VOXEL_EMPTY} a voxel")
    return title + "\n" + format_table(["resolution", "s (seg + loc)", "grid MiB", "seg mIoU voxel", "|Δ| seg", "loc mIoU voxel", "|Δ| loc"], rows)
