"""Volume-aware, count and voxel IoU on cases whose answer is known by hand."""

from __future__ import annotations

import numpy as np
import pytest

from drsplat.eval.metrics import (
    VoxelGrid,
    VoxelSetup,
    evaluate_scene,
    format_reports,
    grid_for,
    localisation_report,
    segmentation_iou,
    segmentation_report,
    significance_weights,
    splat_mass,
    splat_mass_reference,
    threshold_iou_curve,
    voxel_segmentation_report,
    weighted_iou,
)
from drsplat.scene import GaussianScene


def make_scene(means, log_scales, logits, quats=None) -> GaussianScene:
    n = len(means)
    q = np.tile([1.0, 0, 0, 0], (n, 1)) if quats is None else quats
    return GaussianScene(means=np.asarray(means, np.float32), quats=np.asarray(q, np.float32),
                         log_scales=np.asarray(log_scales, np.float32), opacity_logits=np.asarray(logits, np.float32),
                         sh=np.zeros((n, 1, 3), np.float32))


def test_significance_is_scale_product_times_opacity():
    w, bad = significance_weights(np.log([[1.0, 2.0, 3.0], [1.0, 1.0, 1.0]]), np.array([0.0, 30.0]))
    # d = 6 * 0.5 = 3 and ~1 * 1 = 1, normalised by the max
    assert bad == 0
    np.testing.assert_allclose(w, [1.0, 1.0 / 3.0], rtol=1e-6)


def test_significance_survives_huge_and_tiny_scales_and_counts_nonfinite():
    log_scales = np.array([[300.0] * 3, [300.0] * 3, [-300.0] * 3, [np.nan, 0, 0], [np.inf, 0, 0]])
    w, bad = significance_weights(log_scales, np.zeros(5))
    assert bad == 2
    assert np.isfinite(w).all()
    np.testing.assert_allclose(w[:2], [1.0, 1.0])
    assert w[2] == 0.0 and w[3] == 0.0 and w[4] == 0.0
    # an IoU made of two astronomically large Gaussians is still exact
    assert weighted_iou([True, True, False, False, False], [True, False, False, False, False], w) == pytest.approx(0.5)


def test_weighted_iou_by_hand():
    assert weighted_iou([1, 1, 0, 0], [0, 1, 1, 0], [1.0, 2.0, 3.0, 4.0]) == pytest.approx(2.0 / 6.0)
    assert np.isnan(weighted_iou([0, 0], [0, 0], [1.0, 1.0]))


def test_volume_and_count_iou_disagree_as_designed():
    # one big correct Gaussian (volume 8) and three tiny wrong ones (volume 0.001 each)
    scene = make_scene(np.zeros((4, 3)), np.log([[2.0] * 3] + [[0.1] * 3] * 3), np.full(4, 30.0))
    gt = np.array([0, -1, -1, -1])
    scores = np.array([[0.9], [0.8], [0.8], [0.8]])
    rep_v = localisation_report(scores, gt, significance_weights(scene.log_scales, scene.opacity_logits)[0], ["a"], taus=[0.5])
    rep_c = localisation_report(scores, gt, np.ones(4), ["a"], taus=[0.5])
    assert rep_v.iou[0] == pytest.approx(8.0 / (8.0 + 0.003), rel=1e-5)
    assert rep_c.iou[0] == pytest.approx(0.25)


def test_threshold_curve_matches_brute_force():
    rng = np.random.default_rng(0)
    scores = rng.random(500)
    scores[:50] = 0.5  # ties exactly on a grid value
    gt = rng.random(500) < 0.3
    w = rng.random(500)
    taus = np.linspace(0, 1, 21)
    curve = threshold_iou_curve(scores, gt, w, taus)
    brute = [weighted_iou(scores > t, gt, w) for t in taus]
    np.testing.assert_allclose(curve, brute, rtol=1e-9)


def test_localisation_grid_search_finds_the_separating_threshold():
    # label 0 scores 0.7 on its Gaussians and 0.3 elsewhere; label 1 scores 0.65 / 0.2
    gt = np.array([0, 0, 1, 1, -1])
    scores = np.array([[0.7, 0.2], [0.7, 0.2], [0.3, 0.65], [0.3, 0.65], [0.3, 0.2]])
    rep = localisation_report(scores, gt, np.ones(5), ["a", "b"])
    assert rep.miou == pytest.approx(1.0)
    assert 0.3 <= rep.threshold < 0.65
    assert rep.share_above(0.45) == 1.0
    taus = [t for t, _ in rep.curve]
    assert len(taus) == 101 and max(m for _, m in rep.curve) == pytest.approx(1.0)
    # at τ = 0.1 everything is selected: IoU_a = 2/5, IoU_b = 2/5
    assert dict(rep.curve)[0.1] == pytest.approx(0.4)


def test_nonfinite_scores_are_counted_and_never_selected():
    gt = np.array([0, 0, -1])
    scores = np.array([[0.9], [np.nan], [np.inf]])
    rep = localisation_report(scores, gt, np.ones(3), ["a"], taus=[0.5])
    assert rep.nonfinite == 2
    assert rep.iou[0] == pytest.approx(0.5)


def test_segmentation_iou_and_acc_by_hand():
    pred = np.array([0, 0, 1, 1, 1, 2])
    gt = np.array([0, 1, 1, 1, -1, 0])
    w = np.array([1.0, 1.0, 2.0, 1.0, 5.0, 1.0])
    iou, acc = segmentation_iou(pred, gt, w, 3)
    # ignoring the unlabelled one: label 0: inter 1, pred {0,1}=2, gt {0,5}=2 -> 1/3; acc 1/2
    # label 1: inter 3, pred {2,3}=3, gt {1,2,3}=4 -> 3/4; acc 3/4; label 2: no gt -> NaN
    np.testing.assert_allclose(iou[:2], [1 / 3, 3 / 4])
    np.testing.assert_allclose(acc[:2], [1 / 2, 3 / 4])
    assert np.isnan(iou[2]) and np.isnan(acc[2])
    rep = segmentation_report(np.eye(3)[pred], gt, w, ["a", "b", "c"])
    assert rep.miou == pytest.approx((1 / 3 + 3 / 4) / 2)
    assert rep.macc == pytest.approx((1 / 2 + 3 / 4) / 2)
    assert rep.share_above(0.45) == 0.5


# ---------------------------------------------------------------------------------------------- voxel


def random_gaussians(rng, n):
    means = rng.uniform(-1, 1, (n, 3))
    a = rng.normal(size=(n, 3, 3)) * 0.15
    covs = a @ a.transpose(0, 2, 1) + np.eye(3) * 1e-3
    return means, covs, rng.uniform(0.1, 1, n)


def test_splat_kernel_matches_reference_random_and_hard():
    rng = np.random.default_rng(1)
    means, covs, alpha = random_gaussians(rng, 40)
    # hard cases: outside the grid, huge, tiny, singular, non-finite
    means[0] = [50.0, 0, 0]
    covs[1] = np.eye(3) * 100.0
    covs[2] = np.eye(3) * 1e-12
    covs[3] = np.zeros((3, 3))
    means[4] = [np.nan, 0, 0]
    alpha[5] = np.inf
    covs[6] = np.eye(3) * 1e60  # enormous: its voxel range once overflowed an int64 in math.floor and it splatted nothing
    channels = rng.integers(-1, 3, 40)
    channels[6], channels[1] = 0, 1  # channel 0 has voxels that only the enormous one reaches (mass ~1e-95 there)
    grid = VoxelGrid(np.array([-1.2, -1.0, -1.1]), 0.1, (24, 21, 23))
    fast = splat_mass(means, covs, alpha, channels, 3, grid)
    ref = splat_mass_reference(means, covs, alpha, channels, 3, grid)
    assert np.isfinite(fast).all()
    np.testing.assert_allclose(fast, ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(fast > 0, ref > 0)  # every voxel a Gaussian reaches, however faintly


def test_splat_mass_is_conserved_for_large_and_subvoxel_gaussians():
    grid = VoxelGrid(np.array([-2.0, -2.0, -2.0]), 0.05, (80, 80, 80))
    # chi-square(3) mass inside 3 sigma is 0.9707; a sub-voxel Gaussian is widened to half a voxel
    for var, rel in ((0.1**2, 0.01), (0.02**2, 0.01), (1e-8, 0.08)):
        for offset in (0.0, 0.01, 0.025):
            m = splat_mass(np.zeros((1, 3)) + offset, np.eye(3)[None] * var, np.array([0.8]), np.array([0]), 1, grid)
            assert m.sum() == pytest.approx(0.8 * 0.9707, rel=rel)


def test_voxel_iou_identical_disjoint_and_half():
    rng = np.random.default_rng(2)
    n = 400
    means = rng.uniform(-1, 1, (n, 3))
    means[:, 0] *= 2.0  # a 4 x 2 x 2 slab, split at x = 0 into labels 0 and 1
    scene = make_scene(means, np.full((n, 3), np.log(0.15)), np.full(n, 3.0))
    gt = (means[:, 0] > 0).astype(int)
    setup = VoxelSetup.from_scene(scene, resolution=48, empty_threshold=1e-3)
    perfect = np.eye(2)[gt]
    rep = voxel_segmentation_report(setup, perfect, gt, ["left", "right"])
    np.testing.assert_allclose(rep.iou, [1.0, 1.0])
    swapped = np.eye(2)[1 - gt]
    assert voxel_segmentation_report(setup, swapped, gt, ["l", "r"]).miou == 0.0
    # predicting everything as "left": IoU_left ≈ 1/2 of the slab, IoU_right = 0
    rep = voxel_segmentation_report(setup, np.tile([1.0, 0.0], (n, 1)), gt, ["l", "r"])
    assert rep.iou[0] == pytest.approx(0.5, abs=0.06)
    assert rep.iou[1] == 0.0


def test_grid_for_leaves_out_means_no_view_can_see():
    """Round 46: two Gaussians at ±3e38 (finite; the loader says no view can see them) spanned the voxel grid: voxels
    ~6e36 wide, the scene in one of them, the voxel IoU of 7 of 8 labels undefined. Means beyond 1e15 (MAX_COORDINATE)
    now lie outside the grid, which is the grid of the others."""
    means = np.random.default_rng(2).uniform(-2, 2, (50, 3))
    far = np.vstack([means, [[-3e38, 0.0, 0.0], [3e38, 0.0, 0.0], [0.0, 2e15, 0.0]]])
    want, got = grid_for(means, resolution=32), grid_for(far, resolution=32)
    assert got.voxel_size == want.voxel_size and got.shape == want.shape
    np.testing.assert_array_equal(got.origin, want.origin)


def test_grid_for_has_requested_resolution():
    g = grid_for(np.array([[0, 0, 0], [4.0, 2.0, 1.0]]), resolution=40, padding=0.0)
    assert max(g.shape) == 40 and g.voxel_size == pytest.approx(0.1)


def test_evaluate_scene_reports_every_task_and_weighting():
    rng = np.random.default_rng(3)
    n = 300
    means = rng.uniform(-1, 1, (n, 3))
    gt = (means[:, 1] > 0).astype(int)
    gt[:10] = -1
    scene = make_scene(means, np.log(rng.uniform(0.05, 0.2, (n, 3))), rng.normal(size=n))
    scores = np.eye(2)[np.maximum(gt, 0)] * 0.5 + 0.25
    reports = evaluate_scene(scene, scores, gt, ["down", "up"], weightings=("volume", "count", "voxel"), voxel_resolution=24)
    kinds = {(r.task, r.weighting) for r in reports}
    assert kinds == {(t, w) for t in ("loc", "seg") for w in ("volume", "count", "voxel")}
    for r in reports:
        if r.weighting != "voxel":
            # unlabelled Gaussians score 0.75 for "down": they are false positives in localisation
            assert r.miou == pytest.approx(1.0) if r.task == "seg" else r.miou < 1.0
    table = format_reports(reports)
    assert "volume" in table and "voxel" in table and "mAcc" in table


def test_match_gaussians_tells_co_located_gaussians_apart_by_what_else_they_store():
    """Round 95c F1: two Gaussians at one position (densification's clones, 49 pairs in biker.ply) were paired in row
    order, so when registration pruned the first and kept the second, the kept one's scores landed on the pruned one's
    row (its volume and label): ball IoU 0.83 for 1.0 on a tiny room with 40 such pairs."""
    from drsplat.eval.metrics import match_gaussians

    means = np.array([[0.0, 0, 0], [0, 0, 0], [1, 1, 1], [0, 0, 0], [2, 2, 2]])
    rest = np.array([[-6.0, 0.1], [-1, 0.2], [-3, 0.3], [-2, 0.4], [-4, 0.5]], np.float32)  # log-scale, opacity
    for kept in ([1, 2], [3], [1, 3, 4], [0, 3], [2, 1, 0], [0, 1, 2, 3, 4]):
        assert match_gaussians(means, means[kept], original_rest=rest, subset_rest=rest[kept]).tolist() == kept, kept
    assert match_gaussians(means, means[[1, 2]]).tolist() == [0, 2], "without the rest: row order, as before"
    quantised = rest + np.float32(1e-3)  # a copy whose rest is not the same bits (a .spz round trip): row order again
    assert match_gaussians(means, means[[1, 3]], original_rest=rest, subset_rest=quantised[[1, 3]]).tolist() == [0, 1]
    twins = np.zeros((4000, 3)), np.repeat(np.float32([[0.5, 0.5]]), 4000, axis=0)  # alike in everything: row order
    assert match_gaussians(twins[0], twins[0][:3000], original_rest=twins[1], subset_rest=twins[1][:3000]).tolist() == list(range(3000))


def test_match_gaussians_and_expand_scores():
    from drsplat.eval.metrics import expand_scores, match_gaussians

    orig = np.arange(30, dtype=np.float64).reshape(10, 3)
    keep = np.array([7, 2, 5])
    idx = match_gaussians(orig, orig[keep].astype(np.float32))
    assert idx.tolist() == [7, 2, 5]
    full = expand_scores(np.array([[0.9], [0.8], [0.7]], np.float32), idx, 10)
    assert full[[7, 2, 5], 0].tolist() == pytest.approx([0.9, 0.8, 0.7])
    assert np.count_nonzero(full) == 3
    with pytest.raises(ValueError, match="no counterpart"):
        match_gaussians(orig, np.array([[100.0, 0, 0]]))
    # round 59b: a scene holding two Gaussians at one position (merged scenes copy some) was refused as "not the scene it
    # was registered from"; they are paired in row order, as registration keeps the original's order
    dup = np.concatenate([orig, orig[[4]], orig[[4, 4]]])  # rows 4, 10, 11, 12 at one position
    assert match_gaussians(dup, dup).tolist() == list(range(13))
    assert match_gaussians(dup, dup[[1, 4, 10, 12]]).tolist() == [1, 4, 10, 11]
    with pytest.raises(ValueError, match=r"the copy holds more Gaussians at the position of its #2 than the original does"):
        match_gaussians(orig, orig[[1, 4, 4, 4]])
    # round 60a: the first in row order within the tolerance took a distinct Gaussian 3e-5 away before the exact copy
    near = np.array([[0.0, 0, 0], [3e-5, 0, 0], [0, 0, 0], [10, 10, 10]])
    assert match_gaussians(near, near[[0, 2, 3]]).tolist() == [0, 2, 3]
    # round 60c: row by row, the first copy took the only original the second could have, and the second was refused
    # ("holds more Gaussians at the position"); a matching of all the shared rows pairs both
    originals = np.array([[0.0, 0, 0], [5e-5, 0, 0], [10, 10, 10]])
    copy = np.array([[0.0, 0, 0], [-6e-5, 0, 0], [10, 10, 10]])
    assert match_gaussians(originals, copy).tolist() == [1, 0, 2]
    many = np.concatenate([np.zeros((3000, 3)), [[10.0, 10, 10]]])  # 3,000 copies of one position (was quadratic, 92 s for 10,000)
    assert match_gaussians(many, many).tolist() == list(range(3001))


def test_argmax_rows_without_finite_scores_predict_nothing():
    from drsplat.eval.metrics import argmax_labels

    s = np.array([[0.1, 0.3], [np.nan, np.nan], [0.5, np.nan]])
    assert argmax_labels(np.where(np.isfinite(s), s, -np.inf)).tolist() == [1, -1, 0]


def test_report_summary_and_json_keep_nan_out():
    rep = segmentation_report(np.eye(2)[[0, 0, 1]], np.array([0, 0, 0]), np.ones(3), ["a", "b"])
    d = rep.to_dict()
    assert d["per_label"]["b"]["iou"] is None  # no ground truth for "b": excluded, not NaN in JSON
    assert d["mIoU"] == pytest.approx(2 / 3) and d["IoU>0.45"] == 1.0


def test_unassigned_gaussians_are_misses_not_label_zero():
    scene = make_scene(np.zeros((4, 3)), np.zeros((4, 3)), np.full(4, 30.0))
    gt = np.array([0, 0, 1, 1])
    scores = np.array([[0.9, 0.1], [0.0, 0.0], [0.1, 0.9], [0.0, 0.0]])  # rows 1 and 3 hold no feature
    assigned = np.array([True, False, True, False])
    reps = {(r.task, r.weighting): r for r in evaluate_scene(scene, scores, gt, ["a", "b"], weightings=("count",), assigned=assigned)}
    # without the mask, row 3 (a zero tie) would be predicted "a": IoU_a = 2/3; with it both labels are 1/2
    np.testing.assert_allclose(reps["seg", "count"].iou, [0.5, 0.5])
    np.testing.assert_allclose(reps["loc", "count"].iou, [0.5, 0.5])
    assert reps["seg", "count"].nonfinite == 0
    plain = {(r.task, r.weighting): r for r in evaluate_scene(scene, scores, gt, ["a", "b"], weightings=("count",))}
    assert plain["seg", "count"].iou[0] == pytest.approx(2 / 3)


def test_float32_scores_meet_tau_in_float32_through_evaluate_scene_and_the_voxel_report():
    """`evaluate_scene(assigned=...)` (what `drsplat eval iou` always calls) cast float32 scores to float64
    before the grid search, and the voxel report compared in float64: a score of float32(0.3) counted as
    above τ = 0.3 there, undoing round 19's mend (an independent re-implementation, round 40)."""
    from drsplat.eval.metrics import evaluate_scene
    from drsplat.scene import GaussianScene

    n = 5
    scene = GaussianScene(means=np.array([[5, 5, 5], [3, 3, 3], [7, 7, 7], [0, 0, 0], [10, 10, 10]], np.float32),
                          quats=np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32), log_scales=np.full((n, 3), -3, np.float32),
                          opacity_logits=np.full(n, 3, np.float32), sh=np.zeros((n, 1, 3), np.float32))
    scores = np.array([[0.3], [0.3], [0.3], [0.9], [0.9]], np.float32)
    gt = np.array([-1, -1, -1, 0, 0])
    for assigned in (None, np.ones(n, bool)):
        reports = evaluate_scene(scene, scores, gt, ["a"], tasks=("loc",), weightings=("volume", "count", "voxel"),
                                 taus=np.array([0.3]), assigned=assigned)
        assert [r.miou for r in reports] == pytest.approx([1.0, 1.0, 1.0])


def test_a_short_threshold_grid_is_printed_whole_and_a_long_one_every_fifth_point():
    """Round 57c: `eval iou --taus 0.1:0.3:0.05` printed one row of its five thresholds (every 5th point, the
    default grid's step), so the search looked as if it had tried one."""
    from drsplat.eval.metrics import IoUReport, format_curve

    short = [(0.1 + 0.05 * k, 0.5 + 0.01 * k) for k in range(5)]
    report = IoUReport("loc", "volume", ["a"], np.array([0.6]), threshold=short[-1][0], curve=short)
    rows = format_curve(report).splitlines()[1:]
    assert [float(r.split()[0]) for r in rows] == pytest.approx([t for t, _ in short]) and rows[-1].endswith("<- best")
    long = [(0.02 * k, 0.5) for k in range(50)]
    rows = format_curve(IoUReport("loc", "volume", ["a"], np.array([0.6]), threshold=long[7][0], curve=long)).splitlines()[1:]
    assert [float(r.split()[0]) for r in rows] == pytest.approx(sorted([0.02 * k for k in range(0, 50, 5)] + [0.14]))


def test_the_voxel_row_uses_the_volume_tau_whatever_the_order_of_the_weightings():
    """Round 59b: the voxel localisation took the τ of whichever weighting came first: `--weighting count,volume,voxel`
    gave another voxel row than `volume,count,voxel` or `voxel` alone (0.770 against 0.754 on tiny). It takes the
    volume-aware grid search's τ always (made for it when volume is not asked), as its docstring and the docs say."""
    from drsplat.eval.metrics import evaluate_scene

    # one large labelled Gaussian scored 0.5, three small unlabelled ones 0.6 and a small labelled one 0.8: the count IoU
    # is best at τ = 0.7 (only the small labelled one), the volume IoU at 0.4 (the large one dominates)
    n = 5
    scene = GaussianScene(means=np.array([[0, 0, 0], [3, 0, 0], [0, 3, 0], [0, 0, 3], [3, 3, 3]], np.float32),
                          quats=np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32),
                          log_scales=np.array([[0.0] * 3] + [[-4.0] * 3] * 4, np.float32),
                          opacity_logits=np.full(n, 3, np.float32), sh=np.zeros((n, 1, 3), np.float32))
    scores = np.array([[0.5], [0.6], [0.6], [0.6], [0.8]], np.float32)
    gt = np.array([0, -1, -1, -1, 0])
    taus = np.array([0.4, 0.55, 0.7])

    def rows(weightings):
        return {r.weighting: r for r in evaluate_scene(scene, scores, gt, ["a"], tasks=("loc",), weightings=weightings, taus=taus)}

    first = rows(("volume", "count", "voxel"))
    assert first["count"].threshold == pytest.approx(0.7) and first["volume"].threshold == pytest.approx(0.4)
    for weightings in (("count", "volume", "voxel"), ("count", "voxel"), ("voxel",)):
        voxel = rows(weightings)["voxel"]
        assert voxel.threshold == pytest.approx(0.4) and voxel.miou == pytest.approx(first["voxel"].miou), weightings


def test_a_fine_threshold_grid_is_printed_with_its_own_decimals():
    """Round 59b: `--taus 0.104:0.116:0.002` printed its curve as five rows of 0.11 and the table's τ as 0.11, while the
    JSON said 0.114. A threshold is printed with as many decimals as it has (2 to 6); the default grid keeps two."""
    from drsplat.eval.metrics import IoUReport, format_curve, format_reports

    fine = [(round(0.104 + 0.002 * k, 6), 0.5 + 0.01 * k) for k in range(7)]
    report = IoUReport("loc", "count", ["a"], np.array([0.6]), threshold=fine[5][0], curve=fine)
    rows = format_curve(report).splitlines()[1:]
    assert [r.split()[0] for r in rows] == ["0.104", "0.106", "0.108", "0.110", "0.112", "0.114", "0.116"]
    assert rows[5].endswith("<- best")
    assert format_reports([report]).splitlines()[-1].split()[-2] == "0.114"
    # round 60a: the voxel row has no grid of its own and printed the same τ as 0.11; and 6 decimals overflowed the column
    voxel = IoUReport("loc", "voxel", ["a"], np.array([0.6]), threshold=0.11)
    table = format_reports([report, voxel]).splitlines()
    assert [row.split()[-2] for row in table[2:]] == ["0.114", "0.110"]
    finest = IoUReport("loc", "count", ["a"], np.array([0.6]), threshold=0.123456, curve=[(0.123456, 0.5)])
    table = format_reports([finest, voxel]).splitlines()
    assert [row.split()[-2] for row in table[2:]] == ["0.123456", "0.110000"] and len({len(row) for row in table[2:]}) == 1
    coarse = [(k / 100, 0.5) for k in range(0, 101)]  # the default grid, 0.07 held as 0.07000000000000001
    report = IoUReport("loc", "volume", ["a"], np.array([0.6]), threshold=coarse[7][0], curve=coarse)
    assert format_reports([report]).splitlines()[-1].split()[-2] == "0.07"
    assert "  0.07   0.500  <- best" in format_curve(report)


def test_match_gaussians_pairs_each_copy_with_its_own_position_and_rest_in_a_cluster_of_positions():
    """Round 98a F1: four positions within one matching radius of one another, two Gaussians at each (their rests
    differ), one pruned: rows at different positions shared a group, ranked by the distance to its first row, so one
    position's copy took another's originals and a copy then one of another rest ([0, 4, 1, 2, 5, 6, 3]). Each copy is
    paired with its original (the identity), and in random dense clusters no row with another rest."""
    from drsplat.eval.metrics import match_gaussians

    radius = 1e-4  # tolerance 1e-5 x the extent 10
    spots = {"A": (0.1477, 0.1982), "B": (0.3785, 0.7784), "C": (1.0537, 1.2348), "D": (1.1259, 0.1407)}
    at = ["A", "B", "C", "D", "C", "A", "B", "D"]
    means = np.array([[spots[a][0] * radius, spots[a][1] * radius, 0.0] for a in at] + [[10.0, 10.0, 10.0]])
    rest = np.array([[1], [1], [0], [1], [1], [0], [0], [1], [9]], np.float32)
    keep = [0, 1, 3, 4, 5, 6, 7, 8]
    assert match_gaussians(means, means[keep], original_rest=rest, subset_rest=rest[keep]).tolist() == keep
    rng = np.random.default_rng(7)
    wrong = 0
    for _ in range(300):
        places = np.zeros((rng.integers(3, 9), 3))
        places[:, :2] = rng.uniform(0, 1.6 * radius, (len(places), 2))
        which = np.concatenate([np.arange(len(places)), rng.integers(0, len(places), rng.integers(0, 2 * len(places) + 1))])
        means = np.vstack([places[which], [[10.0, 10.0, 10.0]]])
        rest = np.vstack([rng.integers(0, 3, (len(which), 2)), [[9, 9]]]).astype(np.float32)
        keep = np.sort(rng.choice(len(which), rng.integers(1, len(which) + 1), replace=False)).tolist() + [len(which)]
        idx = match_gaussians(means, means[keep], original_rest=rest, subset_rest=rest[keep])
        assert sorted(set(idx.tolist())) == sorted(idx.tolist())  # one to one
        wrong += int((rest[idx] != rest[keep]).any(axis=1).sum() + (means[idx] != means[keep]).any(axis=1).sum())
    assert wrong == 0


def test_the_nearest_free_original_is_found_without_ranking_the_group_for_each_position(monkeypatch):
    """Round 100a F1: thousands of positions in one matching radius, two copies each with their rests rounded (none
    alike, as in a .spz copy) took 25.5 s for 5,000 rows: every position ranked all the group's originals and walked
    them in Python. A position of few rows now searches the free ones in numpy (no ranking made), and each copy still
    takes an original at its own position."""
    from drsplat.eval import metrics

    rng = np.random.default_rng(11)
    spots = rng.normal(size=(300, 3)) * 1e-7
    means = np.vstack([np.repeat(spots, 2, axis=0), [[10.0, 10, 10]]])
    rest = rng.normal(size=(len(means), 3)).astype(np.float32)
    keep = np.sort(rng.choice(len(means) - 1, 450, replace=False)).tolist() + [len(means) - 1]
    rankings = []
    real_lexsort = np.lexsort
    monkeypatch.setattr(metrics.np, "lexsort", lambda keys, *a, **k: (rankings.append(1), real_lexsort(keys, *a, **k))[1])
    idx = metrics.match_gaussians(means, means[keep], original_rest=rest, subset_rest=np.round(rest[keep], 1))
    monkeypatch.setattr(metrics.np, "lexsort", real_lexsort)
    assert len(set(idx.tolist())) == len(idx) and (means[idx] == means[keep]).all() and not rankings, len(rankings)


@pytest.mark.parametrize("rows_at_a_position", [1, 3, 40])
def test_nearest_free_agrees_with_a_brute_force_search(rows_at_a_position):
    """`_NearestFree` (a search for positions of few rows, a ranking walked once for those of many) against a brute
    force: the nearest free original to the position (of the asked rest), ties to the lower index, each taken once."""
    from drsplat.eval.metrics import _NearestFree

    rng = np.random.default_rng(rows_at_a_position)
    for _ in range(30):
        k = int(rng.integers(5, 80))
        candidates = np.sort(rng.choice(200, k, replace=False))
        grid = rng.integers(0, 4, (k, 3)).astype(np.float64)  # a coarse grid: many equal distances, ties by index
        originals = np.zeros((200, 2), np.float32)
        originals[candidates] = rng.integers(0, 3, (k, 2))
        positions = rng.integers(0, 4, (5, 3)).astype(np.float64)
        at = {j: list(range(rows_at_a_position)) for j in range(5)}
        picker, free = _NearestFree(grid, candidates, positions, at), set(candidates.tolist())
        for _ in range(min(k, 5 * rows_at_a_position)):
            j = int(rng.integers(0, 5))
            key = rng.integers(0, 3, 2).astype(np.float32) if rng.random() < 0.5 else None
            pool = [c for c in sorted(free) if key is None or (originals[c] == key).all()]
            d = [float(np.square(grid[np.searchsorted(candidates, c)] - positions[j]).sum()) for c in pool]
            want = pool[int(np.argmin(d))] if pool else None
            got = picker.take(j) if key is None else picker.take_alike(j, key.tobytes(), originals)
            assert got == want, (j, key, got, want)
            free.discard(want)


def test_positions_asked_once_give_every_row_its_own_answer():
    """Round 96a F5: the k-d tree was asked once for each of K copies of one position (its leaf of K identical points
    scanned whole each time) and the copies' group key, a K-tuple, hashed for each: 64,000 copies took 21-28 s (0.6 s
    now, measured, not asserted). `_once_per_position` hands the tree each position once; every row gets its own."""
    from drsplat.eval.metrics import _once_per_position, match_gaussians

    rng = np.random.default_rng(3)
    spread = rng.normal(size=(500, 3))
    assert np.array_equal(_once_per_position(spread)[0], spread)  # none alike: as they are
    points = np.vstack([spread, spread[:40], np.zeros((300, 3)), [[np.nan, 0, 0], [-0.0, 0, 0]]])
    distinct, back = _once_per_position(points)
    assert len(distinct) < len(points) and np.array_equal(distinct[back], points, equal_nan=True)
    assert len(_once_per_position(points[:1])[0]) == 1 and len(_once_per_position(points[:0])[0]) == 0
    means = np.vstack([np.zeros((3000, 3)), rng.uniform(-1, 1, (200, 3))])
    rest = rng.integers(0, 3, (len(means), 2)).astype(np.float32)
    keep = np.sort(rng.choice(len(means), len(means) - 700, replace=False))
    idx = match_gaussians(means, means[keep], original_rest=rest, subset_rest=rest[keep])
    assert len(set(idx.tolist())) == len(idx) and (rest[idx] == rest[keep]).all() and (means[idx] == means[keep]).all()
