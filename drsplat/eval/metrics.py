"""3D evaluation of language fields on Gaussian scenes: the Dr. Splat protocol and its relatives.

Three ways to weigh a Gaussian when measuring the overlap of a predicted and a ground-truth set:

- volume-aware IoU (Dr. Splat, supplement): weight d_i = s_x·s_y·s_z·α_i, so that a large opaque
  Gaussian counts more than a tiny transparent one;
- count IoU (OpenGaussian): every Gaussian weighs 1;
- voxel IoU: the sets are splatted into a voxel grid (`voxel_iou_*`), and voxels are compared.

Two tasks:

- localisation: each label is selected by one global threshold τ on its similarity; τ is found by
  a grid search and the whole curve mIoU(τ) is reported;
- segmentation: each Gaussian takes the argmax label; mIoU and mAcc.

Ground-truth labels are integers per Gaussian, -1 meaning "no label". In segmentation the
unlabelled Gaussians are ignored (argmax always assigns some label, so they could only add
noise); in localisation they count as false positives when selected.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numba
import numpy as np

from drsplat.defaults import VOXEL_EMPTY, VOXEL_RESOLUTION
from drsplat.query import thresholds_as_compared
from drsplat.scene import MAX_COORDINATE

log = logging.getLogger(__name__)

IOU_THRESHOLDS = (0.15, 0.3, 0.45)
DEFAULT_TAU_GRID = tuple(np.round(np.linspace(0.0, 1.0, 101), 4))


@dataclass
class IoUReport:
    """Per-label results of one task under one weighting.

    iou: [L] IoU per label (NaN where the label has no ground truth: excluded from the means).
    acc: [L] accuracy per label (segmentation; weighted recall inter / gt), or None.
    threshold: the global similarity threshold (localisation), or None.
    curve: [(τ, mIoU)] the grid search behind `threshold` (localisation), else empty.
    nonfinite: number of non-finite scores/weights met (treated as "not selected"/weight 0).
    """

    task: str
    weighting: str
    label_names: list[str]
    iou: np.ndarray
    acc: np.ndarray | None = None
    threshold: float | None = None
    curve: list[tuple[float, float]] = field(default_factory=list)
    nonfinite: int = 0

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.iou)

    def restricted(self, labels: Sequence[int]) -> IoUReport:
        """This report of `labels` (indices into label_names) alone: their IoU and accuracy as measured, the means over
        them. A segmentation's argmax over more labels than the ground truth holds is averaged over the present ones
        so (OpenGaussian's `eval_scannet.py`); a localisation's curve is of all its labels, so only a segmentation's."""
        if self.curve:
            raise ValueError("a localisation report's curve averages all its labels: restrict the labels it is made of instead")
        keep = list(labels)
        return dataclasses.replace(self, label_names=[self.label_names[i] for i in keep], iou=self.iou[keep],
                                   acc=None if self.acc is None else self.acc[keep])

    @property
    def miou(self) -> float:
        return float(np.mean(self.iou[self.valid])) if self.valid.any() else float("nan")

    @property
    def macc(self) -> float:
        if self.acc is None:
            return float("nan")
        ok = np.isfinite(self.acc)
        return float(np.mean(self.acc[ok])) if ok.any() else float("nan")

    def share_above(self, threshold: float) -> float:
        """Share of (ground-truth-present) labels whose IoU exceeds `threshold`."""
        if not self.valid.any():
            return float("nan")
        return float(np.mean(self.iou[self.valid] > threshold))

    def summary(self) -> dict:
        out = {"task": self.task, "weighting": self.weighting, "mIoU": self.miou}
        for t in IOU_THRESHOLDS:
            out[f"IoU>{t}"] = self.share_above(t)
        if self.acc is not None:
            out["mAcc"] = self.macc
        if self.threshold is not None:
            out["threshold"] = self.threshold
        out["nonfinite"] = self.nonfinite
        return out

    def to_dict(self) -> dict:
        out = self.summary()
        out["per_label"] = {
            name: {"iou": _none_if_nan(self.iou[i]), **({"acc": _none_if_nan(self.acc[i])} if self.acc is not None else {})}
            for i, name in enumerate(self.label_names)
        }
        if self.curve:
            out["curve"] = [[t, _none_if_nan(m)] for t, m in self.curve]
        return out


def _none_if_nan(x: float) -> float | None:
    x = float(x)
    return None if not math.isfinite(x) else x


def significance_weights(log_scales: np.ndarray, opacity_logits: np.ndarray) -> tuple[np.ndarray, int]:
    """Dr. Splat's significance d_i = s_x·s_y·s_z·α_i, normalised so that max d = 1.

    log_scales: [N, 3], opacity_logits: [N]. Returns (weights [N] float64, nonfinite count).

    Computed in log space, log d_i = Σ_k log s_k + log σ(logit_i) with log σ(x) = −log(1 + e^−x),
    then shifted by max_i log d_i before exponentiating: IoU is a ratio of weighted sums, so a
    common factor cancels, and neither huge (e^300) nor tiny (e^−300) volumes overflow. Gaussians
    with a non-finite log d get weight 0 and are counted.
    """
    ls = np.asarray(log_scales, dtype=np.float64)
    lo = np.asarray(opacity_logits, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        log_d = ls.sum(axis=1) - np.logaddexp(0.0, -lo)
    finite = np.isfinite(log_d)
    nonfinite = int(np.count_nonzero(~finite))
    weights = np.zeros(log_d.shape[0], dtype=np.float64)
    if finite.any():
        weights[finite] = np.exp(log_d[finite] - log_d[finite].max())
    if nonfinite:
        log.warning("%d Gaussians have a non-finite significance (scale or opacity); they weigh 0", nonfinite)
    return weights, nonfinite


def scene_weights(scene, weighting: str) -> tuple[np.ndarray, int]:
    """Per-Gaussian weights [N] for `weighting` in {"volume", "count"} and the non-finite count."""
    if weighting == "volume":
        return significance_weights(scene.log_scales, scene.opacity_logits)
    if weighting == "count":
        return np.ones(scene.num_gaussians, dtype=np.float64), 0
    raise ValueError(f"unknown weighting {weighting!r} (volume, count)")


def weighted_iou(pred: np.ndarray, gt: np.ndarray, weights: np.ndarray) -> float:
    """IoU = d·(p ⊙ g) / d·(p + g − p ⊙ g) for boolean sets p, g: [N] and weights d: [N].

    NaN when the union has zero weight.
    """
    p = np.asarray(pred, bool)
    g = np.asarray(gt, bool)
    w = np.asarray(weights, np.float64)
    inter = float(w[p & g].sum())
    union = float(w[p | g].sum())
    return inter / union if union > 0 else float("nan")


def segmentation_iou(pred_labels: np.ndarray, gt_labels: np.ndarray, weights: np.ndarray, num_labels: int,
                     ignore_unlabelled: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Per-label weighted IoU and accuracy of a hard labelling.

    pred_labels, gt_labels: [N] int (−1 = none). weights: [N]. Returns (iou [L], acc [L]) with
        I_l = Σ_i d_i [pred_i = l ∧ gt_i = l],  P_l = Σ_i d_i [pred_i = l],  G_l = Σ_i d_i [gt_i = l],
        IoU_l = I_l / (P_l + G_l − I_l),  Acc_l = I_l / G_l,
    NaN for labels without ground truth. With `ignore_unlabelled`, Gaussians with gt −1 are dropped.
    """
    pred = np.asarray(pred_labels, np.int64)
    gt = np.asarray(gt_labels, np.int64)
    w = np.asarray(weights, np.float64)
    if ignore_unlabelled:
        keep = gt >= 0
        pred, gt, w = pred[keep], gt[keep], w[keep]
    hit = (pred == gt) & (gt >= 0)
    inter = np.bincount(gt[hit], weights=w[hit], minlength=num_labels)[:num_labels]
    pm = (pred >= 0) & (pred < num_labels)
    p_area = np.bincount(pred[pm], weights=w[pm], minlength=num_labels)[:num_labels]
    gm = (gt >= 0) & (gt < num_labels)
    g_area = np.bincount(gt[gm], weights=w[gm], minlength=num_labels)[:num_labels]
    union = p_area + g_area - inter
    present = g_area > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(present, inter / np.where(union > 0, union, 1.0), np.nan)
        acc = np.where(present, inter / np.where(g_area > 0, g_area, 1.0), np.nan)
    return iou, acc


def _clean_scores(scores: np.ndarray) -> tuple[np.ndarray, int]:
    """Scores as float64 with NaN and +inf replaced by −inf (never selected), and their count.

    −inf itself is the deliberate "never selected" value (unassigned Gaussians), not counted.
    """
    s = np.asarray(scores, dtype=np.float64)
    bad = np.isnan(s) | (s == np.inf)
    nonfinite = int(np.count_nonzero(bad))
    if nonfinite:
        log.warning("%d non-finite similarity scores; they never select a Gaussian", nonfinite)
        s = np.where(bad, -np.inf, s)
    return s, nonfinite


def threshold_iou_curve(scores: np.ndarray, gt: np.ndarray, weights: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """IoU of the set {i : score_i > τ} against the set gt, for every τ at once.

    scores: [N], gt: [N] bool, weights: [N], taus: [T]. Returns [T] (NaN where the union is empty).
    Sort once by descending score; cumulative sums give P(τ) and I(τ) for any τ by a binary search,
    so the grid costs O(N log N + T log N) instead of O(N T).
    """
    order = np.argsort(-scores, kind="stable")
    s_sorted = scores[order]
    w_sorted = np.asarray(weights, np.float64)[order]
    g_sorted = np.asarray(gt, bool)[order]
    cum_p = np.concatenate([[0.0], np.cumsum(w_sorted)])
    cum_i = np.concatenate([[0.0], np.cumsum(np.where(g_sorted, w_sorted, 0.0))])
    g_total = cum_i[-1]
    # number of scores strictly greater than τ: the descending array negated is ascending
    count = np.searchsorted(-s_sorted, -np.asarray(taus, np.float64), side="left")
    inter = cum_i[count]
    union = cum_p[count] + g_total - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(union > 0, inter / np.where(union > 0, union, 1.0), np.nan)


def localisation_report(scores: np.ndarray, gt_labels: np.ndarray, weights: np.ndarray, label_names: list[str],
                        taus: np.ndarray | None = None, weighting: str = "volume", nonfinite_weights: int = 0) -> IoUReport:
    """Localisation: label l selects {i : score_il > τ}; one global τ maximises the mIoU.

    scores: [N, L] similarity of every Gaussian to every label query; gt_labels: [N] int (−1 none);
    weights: [N]; taus: [T] grid (default 0, 0.01, …, 1). The report keeps the curve mIoU(τ) and the
    per-label IoU at the best τ. Labels without ground truth are excluded from the means.
    """
    s, nonfinite = _clean_scores(scores)
    num_labels = s.shape[1]
    taus = np.asarray(DEFAULT_TAU_GRID if taus is None else taus, dtype=np.float64)
    # float32 scores meet τ in float32, as the official code's tensors do: a score of float32(0.3) is not > 0.3 there, and
    # was here (the float64 0.3 lies below it; a cross-check, 2026-11-30)
    compared = thresholds_as_compared(taus, scores)
    gt = np.asarray(gt_labels, np.int64)
    curves = np.stack([threshold_iou_curve(s[:, l], gt == l, weights, compared) for l in range(num_labels)], axis=1)
    present = np.array([(gt == l).any() and float(np.asarray(weights)[gt == l].sum()) > 0 for l in range(num_labels)])
    curves[:, ~present] = np.nan
    with np.errstate(invalid="ignore"):
        miou = np.array([np.mean(np.nan_to_num(row[present], nan=0.0)) if present.any() else np.nan for row in curves])
    best = int(np.nanargmax(miou)) if np.isfinite(miou).any() else 0
    iou = np.where(present, np.nan_to_num(curves[best], nan=0.0), np.nan)
    return IoUReport(task="loc", weighting=weighting, label_names=list(label_names), iou=iou, threshold=float(taus[best]),
                     curve=[(float(t), float(m)) for t, m in zip(taus, miou)], nonfinite=nonfinite + nonfinite_weights)


def segmentation_report(scores: np.ndarray, gt_labels: np.ndarray, weights: np.ndarray, label_names: list[str],
                        weighting: str = "volume", nonfinite_weights: int = 0) -> IoUReport:
    """Segmentation: every Gaussian takes argmax_l score_il; mIoU and mAcc (`segmentation_iou`).

    scores: [N, L]; gt_labels: [N] int (−1 none, ignored); weights: [N]. A row with no finite
    score predicts −1 (counts against the label of that Gaussian).
    """
    s, nonfinite = _clean_scores(scores)
    pred = argmax_labels(s)
    iou, acc = segmentation_iou(pred, gt_labels, weights, s.shape[1])
    return IoUReport(task="seg", weighting=weighting, label_names=list(label_names), iou=iou, acc=acc,
                     nonfinite=nonfinite + nonfinite_weights)


def argmax_labels(scores: np.ndarray) -> np.ndarray:
    """[N, L] scores -> [N] argmax label, −1 where no score is finite (or L = 0)."""
    if scores.shape[1] == 0:
        return np.full(scores.shape[0], -1, np.int64)
    pred = np.argmax(scores, axis=1).astype(np.int64)
    pred[~np.isfinite(scores).any(axis=1)] = -1
    return pred


# ----------------------------------------------------------------------------------------------
# Voxel IoU


@dataclass
class VoxelGrid:
    """An axis-aligned grid of cubic voxels. origin: [3] corner; voxel_size h; shape (nx, ny, nz)."""

    origin: np.ndarray
    voxel_size: float
    shape: tuple[int, int, int]

    @property
    def num_voxels(self) -> int:
        return int(np.prod(self.shape))

    def centers(self) -> np.ndarray:
        """[V, 3] voxel centres, x fastest-varying last (C order over (nx, ny, nz))."""
        axes = [self.origin[k] + (np.arange(self.shape[k]) + 0.5) * self.voxel_size for k in range(3)]
        g = np.meshgrid(*axes, indexing="ij")
        return np.stack([a.ravel() for a in g], axis=1)


def grid_for(means: np.ndarray, resolution: int = VOXEL_RESOLUTION, padding: float = 0.02) -> VoxelGrid:
    """A grid around `means` ([N, 3], finite rows within MAX_COORDINATE only) with `resolution` voxels on the longest side.

    A mean beyond MAX_COORDINATE (1e15) is one no view can see (the scene loader says so; the rasterizer skips it):
    in the box, two such Gaussians at ±3e38 made every voxel ~6e36 wide, so the whole scene fell in one voxel and the
    voxel IoU of 7 of 8 labels was undefined (round 46). Such a Gaussian lies outside the grid, as its mass does."""
    m = np.asarray(means, np.float64)
    with np.errstate(invalid="ignore"):
        m = m[np.isfinite(m).all(axis=1) & (np.abs(m) <= MAX_COORDINATE).all(axis=1)]
    if m.shape[0] == 0:
        return VoxelGrid(np.zeros(3), 1.0, (1, 1, 1))
    lo, hi = m.min(axis=0), m.max(axis=0)
    extent = float(max((hi - lo).max(), 1e-9))
    lo = lo - padding * extent
    hi = hi + padding * extent
    h = float((hi - lo).max()) / resolution
    shape = tuple(int(max(1, math.ceil((hi[k] - lo[k]) / h))) for k in range(3))
    return VoxelGrid(lo, h, shape)


def _voxel_precompute(means, covs, opacities, grid: VoxelGrid):
    """Per Gaussian: Σ' = Σ + (h/2)²·I, Σ'⁻¹ [N,3,3], α·h³/√((2π)³|Σ'|), valid."""
    h = grid.voxel_size
    c = np.asarray(covs, np.float64) + np.eye(3) * (0.25 * h * h)
    det = np.linalg.det(c)
    valid = np.isfinite(det) & (det > 0) & np.isfinite(np.asarray(means, np.float64)).all(axis=1) & np.isfinite(opacities)
    c_safe = np.where(valid[:, None, None], c, np.eye(3))
    inv = np.linalg.inv(c_safe)
    amp = np.where(valid, np.asarray(opacities, np.float64) * h**3 / np.sqrt((2 * np.pi) ** 3 * np.where(valid, det, 1.0)), 0.0)
    return c_safe, inv, amp, valid


def splat_mass_reference(means, covs, opacities, channels, num_channels: int, grid: VoxelGrid, cutoff: float = 3.0) -> np.ndarray:
    """Obviously-correct dense version of `splat_mass` (every voxel against every Gaussian)."""
    c, inv, amp, valid = _voxel_precompute(means, covs, opacities, grid)
    centers = grid.centers()
    out = np.zeros((num_channels, grid.num_voxels), np.float64)
    for i in range(len(amp)):
        ch = int(channels[i])
        if not valid[i] or ch < 0:
            continue
        d = centers - np.asarray(means[i], np.float64)
        m2 = np.einsum("vi,ij,vj->v", d, inv[i], d)
        out[ch] += np.where(m2 <= cutoff * cutoff, amp[i] * np.exp(-0.5 * m2), 0.0)
    return out


@numba.njit(cache=True)
def _splat_kernel(means, inv, sig, amp, channels, out, origin, h, nx, ny, nz, cutoff2):
    n = means.shape[0]
    cut = math.sqrt(cutoff2)
    for i in range(n):
        ch = channels[i]
        if ch < 0 or amp[i] == 0.0:
            continue
        r0 = cut * sig[i, 0]
        r1 = cut * sig[i, 1]
        r2 = cut * sig[i, 2]
        x0 = int(min(nx * 1.0, max(0.0, np.floor((means[i, 0] - r0 - origin[0]) / h - 0.5))))
        x1 = int(max(-1.0, min(nx - 1.0, np.ceil((means[i, 0] + r0 - origin[0]) / h - 0.5))))
        y0 = int(min(ny * 1.0, max(0.0, np.floor((means[i, 1] - r1 - origin[1]) / h - 0.5))))
        y1 = int(max(-1.0, min(ny - 1.0, np.ceil((means[i, 1] + r1 - origin[1]) / h - 0.5))))
        z0 = int(min(nz * 1.0, max(0.0, np.floor((means[i, 2] - r2 - origin[2]) / h - 0.5))))
        z1 = int(max(-1.0, min(nz - 1.0, np.ceil((means[i, 2] + r2 - origin[2]) / h - 0.5))))
        a00 = inv[i, 0, 0]
        a11 = inv[i, 1, 1]
        a22 = inv[i, 2, 2]
        a01 = inv[i, 0, 1]
        a02 = inv[i, 0, 2]
        a12 = inv[i, 1, 2]
        for x in range(x0, x1 + 1):
            dx = origin[0] + (x + 0.5) * h - means[i, 0]
            for y in range(y0, y1 + 1):
                dy = origin[1] + (y + 0.5) * h - means[i, 1]
                for z in range(z0, z1 + 1):
                    dz = origin[2] + (z + 0.5) * h - means[i, 2]
                    m2 = a00 * dx * dx + a11 * dy * dy + a22 * dz * dz + 2.0 * (a01 * dx * dy + a02 * dx * dz + a12 * dy * dz)
                    if m2 <= cutoff2:
                        out[ch, (x * ny + y) * nz + z] += amp[i] * math.exp(-0.5 * m2)


def splat_mass(means: np.ndarray, covs: np.ndarray, opacities: np.ndarray, channels: np.ndarray, num_channels: int,
               grid: VoxelGrid, cutoff: float = 3.0) -> np.ndarray:
    """α-weighted Gaussian mass per voxel and channel.

    means: [N, 3], covs: [N, 3, 3], opacities: [N], channels: [N] int (−1 = skip). Returns [C, V]:
        M_c(v) = h³ Σ_{i: ch_i = c} α_i N(v | μ_i, Σ_i + (h/2)²·I)   for (v−μ)ᵀΣ'⁻¹(v−μ) ≤ cutoff²,
    i.e. Σ α_i N(v | μ_i, Σ_i) sampled at voxel centres, with every Gaussian widened to a standard
    deviation of at least half a voxel: sampling a Gaussian narrower than that is not a faithful
    quadrature (sub-voxel Gaussians would fall between sample points and lose or gain mass); with
    the widening Σ_v M(v) ≈ α·0.971 (the χ²₃ mass within 3σ) for every size.
    Gaussians with non-finite or singular parameters are skipped.
    """
    c, inv, amp, valid = _voxel_precompute(means, covs, opacities, grid)
    sig = np.sqrt(np.einsum("nii->ni", c))
    ch = np.where(valid, np.asarray(channels, np.int64), -1)
    out = np.zeros((num_channels, grid.num_voxels), np.float64)
    if len(amp):
        _splat_kernel(np.ascontiguousarray(means, np.float64), np.ascontiguousarray(inv), np.ascontiguousarray(sig), amp, ch, out,
                      np.asarray(grid.origin, np.float64), float(grid.voxel_size), *grid.shape, float(cutoff) ** 2)
    return out


def voxel_labels(mass: np.ndarray, empty_threshold: float) -> np.ndarray:
    """[C, V] mass -> [V] label: argmax channel where the total mass exceeds `empty_threshold`, else −1."""
    total = mass.sum(axis=0)
    lab = np.argmax(mass, axis=0).astype(np.int64) if mass.shape[0] else np.full(mass.shape[1], -1, np.int64)
    lab[total <= empty_threshold] = -1
    return lab


@dataclass
class VoxelSetup:
    """Everything the voxel IoU needs about the scene: means [N,3], covs [N,3,3], opacities [N], grid."""

    means: np.ndarray
    covs: np.ndarray
    opacities: np.ndarray
    grid: VoxelGrid
    empty_threshold: float = VOXEL_EMPTY

    @classmethod
    def from_scene(cls, scene, resolution: int = VOXEL_RESOLUTION, empty_threshold: float = VOXEL_EMPTY, focus: np.ndarray | None = None) -> "VoxelSetup":
        """Grid over the Gaussians in `focus` ([N] bool, e.g. labelled or selected ones; all by default)."""
        grid = cls.grid_of(scene, resolution, focus)
        return cls(scene.means.astype(np.float64), scene.covariances().astype(np.float64), scene.opacities().astype(np.float64), grid,
                   empty_threshold)

    @staticmethod
    def grid_of(scene, resolution: int = VOXEL_RESOLUTION, focus: np.ndarray | None = None) -> VoxelGrid:
        """The grid `from_scene` makes: `resolution` voxels on the longest side of the box of the Gaussians in `focus`."""
        return grid_for(scene.means if focus is None else scene.means[focus], resolution)  # grid_for reads them in float64


    def occupancy(self, selected: np.ndarray) -> np.ndarray:
        """[V] bool: voxels whose mass from the selected Gaussians ([N] bool) exceeds the threshold."""
        ch = np.where(np.asarray(selected, bool), 0, -1)
        return splat_mass(self.means, self.covs, self.opacities, ch, 1, self.grid)[0] > self.empty_threshold

    def label_field(self, labels: np.ndarray, num_labels: int) -> np.ndarray:
        """[V] voxel labels (−1 empty) from per-Gaussian labels [N] (−1 skipped)."""
        return voxel_labels(splat_mass(self.means, self.covs, self.opacities, labels, num_labels, self.grid), self.empty_threshold)


def voxel_iou_bytes(grid: VoxelGrid, num_labels: int, segmentation: bool = True) -> int:
    """Bytes the voxel IoU holds at its peak on `grid` for `num_labels` labels. The segmentation: the [C, V] float64
    mass of every label (`splat_mass`), its [V] total and argmax (`voxel_labels`), and the two [V] label fields
    compared. The localisation (segmentation=False) takes one label at a time: its [V] mass and a few [V] masks, 16
    bytes a voxel (round 90a F2: charged the segmentation's, a run of 2.6 GB was refused as needing 26 GB)."""
    return grid.num_voxels * (8 * (max(1, num_labels) + 4) if segmentation else 16)


def voxel_localisation_report(setup: VoxelSetup, scores: np.ndarray, gt_labels: np.ndarray, threshold: float,
                              label_names: list[str]) -> IoUReport:
    """Localisation IoU on voxels at a given τ: occupancy of {score_l > τ} vs occupancy of {gt = l}; undefined (NaN)
    for a label whose ground truth occupies no voxel, as in `voxel_segmentation_report` (round 59b: it scored 0 here
    and counted in the mean, while the segmentation row left it out)."""
    s, nonfinite = _clean_scores(scores)
    compared = float(thresholds_as_compared(threshold, scores))  # the selection `localisation_report` judged at this τ
    gt = np.asarray(gt_labels, np.int64)
    iou = np.full(s.shape[1], np.nan)
    for l in range(s.shape[1]):
        g = gt == l
        if not g.any():
            continue
        gv = setup.occupancy(g)
        if not gv.any():
            continue
        pv = setup.occupancy(s[:, l] > compared)
        iou[l] = np.count_nonzero(gv & pv) / np.count_nonzero(gv | pv)
    return IoUReport(task="loc", weighting="voxel", label_names=list(label_names), iou=iou, threshold=float(threshold), nonfinite=nonfinite)


def voxel_segmentation_report(setup: VoxelSetup, scores: np.ndarray, gt_labels: np.ndarray, label_names: list[str]) -> IoUReport:
    """Segmentation IoU/Acc on voxels: the voxel label fields of argmax predictions and of the ground truth.

    Only Gaussians with a ground-truth label take part (as in `segmentation_report`), so both
    fields cover the same occupied voxels and differ only in their labels.
    """
    s, nonfinite = _clean_scores(scores)
    gt = np.asarray(gt_labels, np.int64)
    num_labels = s.shape[1]
    pred = np.where(gt >= 0, argmax_labels(s), -1)
    gv = setup.label_field(np.where(gt < num_labels, gt, -1), num_labels)
    pv = setup.label_field(pred, num_labels)
    iou, acc = segmentation_iou(pv, gv, np.ones(gv.shape[0]), num_labels)
    return IoUReport(task="seg", weighting="voxel", label_names=list(label_names), iou=iou, acc=acc, nonfinite=nonfinite)


def match_gaussians(original_means: np.ndarray, subset_means: np.ndarray, tolerance: float = 1e-5,
                    original_rest: np.ndarray | None = None, subset_rest: np.ndarray | None = None) -> np.ndarray:
    """Index into the original scene of every Gaussian of a pruned copy, matched by position.

    original_means: [N, 3]; subset_means: [M, 3] (M ≤ N, e.g. a registered PLY written without
    --keep-unassigned). Returns [M] int64. Gaussians at one position (merged scenes hold exact
    copies, densification leaves clones; round 59b: refused) are told apart by the rest of what
    each row stores, `original_rest` [N, D] and `subset_rest` [M, D] (rotation, log-scales,
    opacity: `GaussianScene.identity_rows`, which registration copies as they are): a copy's
    Gaussian takes the original there whose rest is the same bits (round 95c F1: by row order
    alone, a kept Gaussian whose co-located first copy was pruned took that copy's place, its
    volume and label), then the ones left pair in row order, as registration keeps the original's
    order, each the nearest original there not taken yet (`_pair_in_row_order`). Raises ValueError
    when a Gaussian has no original within `tolerance` × the scene extent, or the copy holds more
    Gaussians at a position than the original.
    """
    from scipy.spatial import cKDTree

    orig = np.asarray(original_means, np.float64)
    sub = np.asarray(subset_means, np.float64)
    if sub.shape[0] == 0:
        return np.zeros(0, np.int64)
    finite = np.isfinite(orig).all(axis=1)
    extent = float(np.ptp(orig[finite], axis=0).max()) if finite.any() else 1.0
    tree = cKDTree(np.where(finite[:, None], orig, 1e30))
    distinct, back = _once_per_position(sub)
    dist, idx = (result[back] for result in tree.query(distinct))
    bad = ~(dist <= tolerance * max(extent, 1e-12))
    if bad.any():
        raise ValueError(f"{int(bad.sum())} Gaussians have no counterpart in the original scene (e.g. #{int(np.flatnonzero(bad)[0])})")
    idx = idx.astype(np.int64)
    radius = tolerance * max(extent, 1e-12)
    rest = _rest_keys(original_rest, subset_rest)
    repair = _rows_to_repair(tree, sub, idx, radius, rest)
    if repair.size:
        _pair_in_row_order(tree, sub, idx, radius, rest, repair)
    return idx


def _rows_to_repair(tree, sub: np.ndarray, idx: np.ndarray, radius: float, rest: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """The rows of `idx` [M] (each row's nearest original) that `_pair_in_row_order` pairs again: those whose nearest
    original another row has too, and (with `rest`) those whose nearest original stores another rest while an original
    within `radius` of the row stores its own (a pruned clone's place taken, round 95c F1). A row whose nearest original
    is its own, or that no original nearby matches (a .spz copy's rounded rest), keeps it (round 96a F4: re-pairing
    every row near another original swapped two drifted clones alike in everything)."""
    values, counts = np.unique(idx, return_counts=True)
    repair = np.isin(idx, values[counts > 1])
    if rest is not None:
        originals, copies = rest
        differs = ~repair & (originals[idx].view(np.uint32) != copies.view(np.uint32)).any(axis=1)
        rows = np.flatnonzero(differs)
        rows = rows[_shares_a_position(tree, idx[rows], radius)]
        distinct, back = _once_per_position(sub[rows])
        balls = tree.query_ball_point(distinct, r=radius) if rows.size else []  # a ball for each position (96a F5)
        for row, near in zip(rows.tolist(), (balls[j] for j in back.tolist())):
            key = copies[row].tobytes()
            repair[row] = any(originals[c].tobytes() == key for c in near)
    return np.flatnonzero(repair)


def _rest_keys(original_rest: np.ndarray | None, subset_rest: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
    """The rests (`match_gaussians`) as float32 rows, whose bytes `_pair_alike` compares (those of the co-located
    groups only: a key for each of 5M rows took seconds); None when either is not given."""
    if original_rest is None or subset_rest is None:
        return None
    return np.ascontiguousarray(original_rest, np.float32), np.ascontiguousarray(subset_rest, np.float32)


def _shares_a_position(tree, idx: np.ndarray, radius: float) -> np.ndarray:
    """[R] bool: whether the originals `idx` [R] have another original within `radius`."""
    if tree.n < 2 or idx.size == 0:
        return np.zeros(idx.size, bool)
    distinct, back = _once_per_position(tree.data[idx])
    return (tree.query(distinct, k=2)[0][:, 1] <= radius)[back]


def _once_per_position(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the distinct rows of points [P, 3], [P] each row's among them) for k-d tree queries asked once for each position:
    the tree keeps K identical points in one leaf and scans it whole for each query there, so K copies asking were
    quadratic (round 96a F5: 64,000 copies of one position, 28 s). Rows are sorted by a hash of their bits (one argsort
    of P integers); only the rows whose hash another row shares are compared bit for bit (np.unique over every row took
    1-4 s for 2M, and real scenes hold a few exact clones, so a check for none alike before it seldom saved it: round
    99a F1). Rows alike are those of the same bits (-0.0 and 0.0 are two positions, each asked once)."""
    points = np.ascontiguousarray(points, np.float64)
    if len(points) < 2:
        return points, np.arange(len(points))
    rows = points.view(np.dtype((np.void, points.dtype.itemsize * points.shape[1]))).reshape(-1)
    hashed = _row_hash(points)
    order = np.argsort(hashed, kind="stable")
    hashes = hashed[order]
    starts = np.ones(len(points), bool)
    starts[1:] = hashes[1:] != hashes[:-1]
    if starts.all():
        return points, np.arange(len(points))
    run = np.cumsum(starts) - 1
    hash_shared = np.zeros(len(points), bool)  # rows whose hash another row has: alike, or (seldom) a collision
    hash_shared[order[np.bincount(run)[run] > 1]] = True
    shared, alone = np.flatnonzero(hash_shared), np.flatnonzero(~hash_shared)
    kinds, kind_of = np.unique(rows[shared], return_index=False, return_inverse=True)
    back = np.empty(len(points), np.int64)
    back[alone] = np.arange(len(alone))
    back[shared] = len(alone) + kind_of.reshape(-1)
    return np.concatenate([points[alone], kinds.view(np.float64).reshape(-1, points.shape[1])]), back


def _row_hash(points: np.ndarray) -> np.ndarray:
    """[P] uint64: a hash of the bits of each float64 row of points [P, 3], each column mixed in by an odd multiply and a shift (float32 values
    widened to float64 leave the low 29 bits zero, which a multiply alone kept zero: 58 collisions in 2M rows)."""
    bits = points.view(np.uint64)
    mix = np.zeros(len(points), np.uint64)
    for column, odd in zip(bits.T, (0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9)):
        mix = (mix ^ column) * np.uint64(odd)  # uint64 arithmetic wraps: a hash, not a number
        mix ^= mix >> np.uint64(29)
    return mix


def _pair_in_row_order(tree, sub: np.ndarray, idx: np.ndarray, radius: float, rest_keys: tuple[np.ndarray, np.ndarray] | None,
                       shared: np.ndarray) -> None:
    """Re-pair, in place, the rows `shared` of `idx` [M] (`_rows_to_repair`). Rows with the same originals within
    `radius` (a group: the copies of one position, or of positions nearer than `radius`) take first the originals whose
    rest is theirs (`rest_keys`: originals', copy's; `_pair_alike`), then the others in row order, each row the nearest
    free one to its own position, then in row order (round 60a: the first in row order took a distinct Gaussian 3e-5 away
    before the exact copy; round 98a F1: ranked by the distance to the group's first row, a row at another position of
    the group took that position's originals, and a copy then one of another rest); each group's nearest free originals
    by `_NearestFree` (O(K) a row in numpy, or one O(K log K) ranking for a position of many rows), its ball found once
    for each (round 60c: row by row, 10,000 copies of one position took 92 s;
    round 96a F5: a ball and its sort for each of K copies, quadratic). When a group finds too few free originals, a
    maximum bipartite matching of every shared row decides (row by row, one valid pairing was refused); ValueError when
    even that leaves a row without one."""
    fixed = set(np.delete(idx, shared).tolist())  # the originals of the rows not paired again
    taken = set(fixed)
    positions, where = _once_per_position(sub[shared])
    where = where.tolist()
    balls = tree.query_ball_point(positions, r=radius)
    nears = [balls[j] for j in where]  # a row's ball: the list of its position's, not a copy
    group_of: dict[tuple[int, ...], int] = {}  # a ball's group, its tuple hashed once for each position, not each row (a
    group = [group_of.setdefault(tuple(sorted(ball)), len(group_of)) for ball in balls]  # tuple's hash is not kept)
    groups: list[list[int]] = [[] for _ in group_of]
    for k, j in enumerate(where):
        groups[group[j]].append(k)
    for near, members in zip(group_of, groups):
        free = [c for c in near if c not in taken]
        if len(free) < len(members):
            _pair_by_matching(shared, nears, fixed, idx)
            return
        at: dict[int, list[int]] = {}  # the group's rows by position, each in row order
        for k in members:
            at.setdefault(where[k], []).append(k)
        candidates = np.asarray(sorted(free), np.int64)
        points = np.ascontiguousarray(tree.data[candidates], np.float64)  # gathered once: for `there` and the picker
        places: dict[bytes, list[int]] = {}  # the free originals by their very position, in index order
        for c, place in zip(candidates.tolist(), points):
            places.setdefault(place.tobytes(), []).append(c)
        there = {j: places.get(np.ascontiguousarray(positions[j], np.float64).tobytes(), []) for j in at}
        picker = _NearestFree(points, candidates, positions, at)
        left = _pair_alike(at, picker, there, shared, idx, rest_keys)
        for j, rows in left.items():
            for k in rows:
                idx[shared[k]] = picker.take(j)
        taken.update(picker.used)


NEAREST_SORT_ROWS = 32  # a position with this many rows to pair ranks its group's originals once (O(K log K)) instead of
# searching them for each row (O(K) each, in numpy)


class _NearestFree:
    """The free originals of one co-located group (`candidates` [K], ascending, at `points` [K, 3]) for its rows at
    `positions` [P, 3] (`at`: position -> its rows): `take(j)` / `take_alike(j, key, originals)` give the nearest free
    one to position j (of the rest bits `key`), ties to the lower index, and mark it used. A position of few rows
    searches the free ones (O(K) a row, in numpy); one of many ranks them once (squared distances, then index:
    `np.lexsort`) and walks that ranking (O(K) in all: an original once taken stays taken). Round 100a F1: a ranking
    walked in Python for each position made thousands of positions in one group quadratic in Python steps (5,000
    rows 25.5 s; 4.4 s before round 98a's mend)."""

    def __init__(self, points: np.ndarray, candidates: np.ndarray, positions: np.ndarray, at: dict[int, list[int]]):
        self.points, self.candidates, self.positions = points, candidates, positions
        self.many = {j for j, rows in at.items() if len(rows) >= NEAREST_SORT_ROWS}
        self.free = np.ones(len(candidates), bool)
        self.slot = {c: i for i, c in enumerate(candidates.tolist())}
        self.used: set[int] = set()
        self._ranked: dict[int, np.ndarray] = {}  # position -> slots nearest first (the positions in `many`)
        self._rank_of: dict[int, np.ndarray] = {}  # position -> each slot's place in its ranking
        self._walks: dict[tuple[int, int | None], Iterator[int]] = {}  # (position, rest id) -> where its ranking is walked to
        self._rest: dict[bytes, int] | None = None  # rest bits -> rest id
        self._members: list[np.ndarray] = []  # rest id -> the slots of that rest, ascending
        self._rest_of = np.zeros(0, np.int64)  # slot -> rest id

    def _mark(self, slot: int) -> int:
        self.free[slot] = False
        original = int(self.candidates[slot])
        self.used.add(original)
        return original

    def _nearest(self, j: int, rest: int | None) -> int | None:
        """The nearest free slot to position j (of the rest id `rest`; None: any), or None when none is free."""
        if j in self.many:
            walk = self._walks.get((j, rest))
            if walk is None:
                walk = self._walks[(j, rest)] = iter(self._ranking(j, rest))
            return next((i for i in walk if self.free[i]), None)
        pool = np.flatnonzero(self.free) if rest is None else self._members[rest][self.free[self._members[rest]]]
        if pool.size == 0:
            return None
        return int(pool[np.argmin(np.square(self.points[pool] - self.positions[j]).sum(axis=1))])

    def _ranking(self, j: int, rest: int | None) -> list[int]:
        """Position j's slots nearest first (of the rest id `rest`; None: all). The whole ranking is made once for the
        position; a rest's slots are put in its order by their ranks there (round 102a F1: filtered from the whole
        ranking in Python for each rest asked, K rests at one position were quadratic)."""
        ranked = self._ranked.get(j)
        if ranked is None:
            distances = np.square(self.points - self.positions[j]).sum(axis=1)
            ranked = self._ranked[j] = np.lexsort((self.candidates, distances))
        if rest is None:
            return ranked.tolist()
        rank_of = self._rank_of.get(j)
        if rank_of is None:
            rank_of = self._rank_of[j] = np.empty(len(ranked), np.int64)
            rank_of[ranked] = np.arange(len(ranked))
        members = self._members[rest]
        return members[np.argsort(rank_of[members])].tolist()

    def take(self, j: int) -> int:
        """The nearest free original to position j (there is one: the group has at least as many as rows)."""
        return self._mark(self._nearest(j, None))

    def take_alike(self, j: int, key: bytes, originals: np.ndarray) -> int | None:
        """The nearest free original to position j whose rest (its row of `originals`) has the bits `key`, or None."""
        if self._rest is None:
            self._rest = {}
            self._rest_of = np.asarray([self._rest.setdefault(originals[c].tobytes(), len(self._rest)) for c in self.candidates.tolist()], np.int64)
            order = np.argsort(self._rest_of, kind="stable")
            self._members = np.split(order, np.flatnonzero(np.diff(self._rest_of[order])) + 1) if order.size else []
        rest = self._rest.get(key)
        slot = None if rest is None else self._nearest(j, rest)
        return None if slot is None else self._mark(slot)

    def take_at(self, c: int) -> None:
        """Mark the original c used (an exact copy's own original, at its very position)."""
        self._mark(self.slot[c])


def _pair_alike(at: dict[int, list[int]], picker: _NearestFree, there: dict[int, list[int]], shared: np.ndarray, idx: np.ndarray,
                rest_keys: tuple[np.ndarray, np.ndarray] | None) -> dict[int, list[int]]:
    """Pair, in place in `idx`, the rows of a co-located group (`at`: position -> rows) with free originals whose rest is
    the same bits: first those at the row's very position (`there`: an exact copy's own original, whichever position of
    the group comes first), then the nearest to the row's position (`picker`, which marks the originals taken); returns
    the rows left (position -> rows) to pair in row order."""
    if rest_keys is None:
        return at
    originals, copies = rest_keys
    still: dict[int, list[int]] = {}
    for j, rows in at.items():
        alike: dict[bytes, list[int]] = {}
        for c in reversed(there[j]):  # index order reversed, so pop() takes the lowest index
            alike.setdefault(originals[c].tobytes(), []).append(c)
        for k in rows:
            same = alike.get(copies[shared[k]].tobytes())
            while same and same[-1] in picker.used:
                same.pop()
            if same:
                idx[shared[k]] = same.pop()
                picker.take_at(int(idx[shared[k]]))
            else:
                still.setdefault(j, []).append(k)
    left: dict[int, list[int]] = {}
    for j, rows in still.items():
        for k in rows:
            original = picker.take_alike(j, copies[shared[k]].tobytes(), originals)
            if original is None:
                left.setdefault(j, []).append(k)
            else:
                idx[shared[k]] = original
    return left


def _pair_by_matching(shared: np.ndarray, nears: list, taken: set, idx: np.ndarray) -> None:
    """`_pair_in_row_order`'s fallback: a maximum matching of the shared rows to the free originals within reach
    (scipy's Hopcroft-Karp); ValueError naming a row left without one."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import maximum_bipartite_matching

    free = sorted({c for near in nears for c in near} - taken)
    column = {c: j for j, c in enumerate(free)}
    rows = [k for k, near in enumerate(nears) for c in near if c in column]
    cols = [column[c] for near in nears for c in near if c in column]
    graph = csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(nears), max(len(free), 1)))
    match = maximum_bipartite_matching(graph, perm_type="column")
    for k, j in enumerate(match):
        if j < 0:
            raise ValueError(f"the copy holds more Gaussians at the position of its #{int(shared[k])} than the original does")
        idx[shared[k]] = free[j]


def expand_scores(scores: np.ndarray, index: np.ndarray, num_original: int, fill: float = 0.0) -> np.ndarray:
    """[M, L] scores of a pruned copy -> [N, L] on the original scene; pruned Gaussians score `fill`
    (0 = the score of an unassigned Gaussian in `LanguageField.scores`)."""
    out = np.full((num_original, scores.shape[1]), fill, dtype=np.float32)
    out[index] = scores
    return out


# ----------------------------------------------------------------------------------------------
# Whole-scene entry point


def evaluate_scene(scene, scores: np.ndarray, gt_labels: np.ndarray, label_names: list[str], tasks: tuple[str, ...] = ("loc", "seg"),
                   weightings: tuple[str, ...] = ("volume", "count"), taus: np.ndarray | None = None,
                   voxel_resolution: int = VOXEL_RESOLUTION, voxel_empty_threshold: float = VOXEL_EMPTY, assigned: np.ndarray | None = None) -> list[IoUReport]:
    """Every requested (task, weighting) report for one scene.

    scene: GaussianScene with N Gaussians; scores: [N, L]; gt_labels: [N] int (−1 none).
    weightings ⊂ {volume, count, voxel}. The voxel localisation uses the τ found by the
    volume-aware grid search (made for it when volume is not asked), so its row is the same whichever
    other weightings are asked and in whatever order (round 59b: the first one's τ was taken).
    assigned: [N] bool, Gaussians that hold a language feature; the others (unassigned or pruned
    by registration) are never selected and predict no label (not label 0 by a tie of zeros).
    """
    scores = np.asarray(scores)
    gt = np.asarray(gt_labels, np.int64)
    if scores.shape[0] != scene.num_gaussians or gt.shape[0] != scene.num_gaussians:
        raise ValueError(f"scores {scores.shape} / labels {gt.shape} do not match the scene's {scene.num_gaussians} Gaussians")
    if assigned is not None:  # keep float32 scores float32: localisation compares them with τ in float32 (round 19)
        dtype = scores.dtype if scores.dtype in (np.float32, np.float64) else np.dtype(np.float64)
        scores = np.where(np.asarray(assigned, bool)[:, None], scores.astype(dtype, copy=False), dtype.type(-np.inf))
    reports: list[IoUReport] = []
    loc_tau: float | None = None  # the volume-aware grid search's, for the voxel row
    for weighting in [w for w in weightings if w != "voxel"]:
        w, bad = scene_weights(scene, weighting)
        if "loc" in tasks:
            rep = localisation_report(scores, gt, w, label_names, taus, weighting, bad)
            loc_tau = rep.threshold if weighting == "volume" else loc_tau
            reports.append(rep)
        if "seg" in tasks:
            reports.append(segmentation_report(scores, gt, w, label_names, weighting, bad))
    if "voxel" in weightings:
        setup = VoxelSetup.from_scene(scene, voxel_resolution, voxel_empty_threshold, focus=gt >= 0)
        if "loc" in tasks:
            if loc_tau is None:
                loc_tau = localisation_report(scores, gt, significance_weights(scene.log_scales, scene.opacity_logits)[0], label_names, taus).threshold
            reports.append(voxel_localisation_report(setup, scores, gt, loc_tau, label_names))
        if "seg" in tasks:
            reports.append(voxel_segmentation_report(setup, scores, gt, label_names))
    return reports


TAU_DECIMALS = 6  # `drsplat eval`'s thresholds are compared to this many decimals (commands.eval.parse_taus)


def tau_decimals(taus) -> int:
    """The decimals (2 to TAU_DECIMALS) that print every threshold of `taus` as it is: a grid of step 0.002 printed to
    2 decimals showed five rows of 0.11 and a best τ the JSON gave as 0.114 (round 59b)."""
    exact = [round(float(t), TAU_DECIMALS) for t in taus]
    return next(d for d in range(2, TAU_DECIMALS + 1) if all(round(t, d) == t for t in exact) or d == TAU_DECIMALS)


def tau_text(tau: float, decimals: int | None = None) -> str:
    """A threshold printed with `decimals` (default: its own, `tau_decimals`)."""
    return f"{round(float(tau), TAU_DECIMALS):.{tau_decimals([tau]) if decimals is None else decimals}f}"


def format_reports(reports: list[IoUReport]) -> str:
    """A plain-text table (one row per report) like the paper's: mIoU, IoU>0.15/0.3/0.45, mAcc, τ. Every τ is printed with
    the decimals of all the grids searched (`tau_decimals`; round 60a: the voxel row, which has no grid of its own, printed
    the volume row's 0.110 as 0.11), in a column as wide as they need."""
    decimals = tau_decimals([t for r in reports for t, _ in r.curve] + [r.threshold for r in reports if r.threshold is not None])
    taus = [tau_text(r.threshold, decimals) if r.threshold is not None else "-" for r in reports]
    width = max([6, *map(len, taus)])
    head = (f"{'task':<5} {'weighting':<8} {'mIoU':>7} " + " ".join(f"{'>' + str(t):>7}" for t in IOU_THRESHOLDS)
            + f" {'mAcc':>7} {'tau':>{width}} {'nonfin':>6}")
    lines = [head, "-" * len(head)]
    for r, tau in zip(reports, taus):
        shares = " ".join(f"{r.share_above(t):7.3f}" for t in IOU_THRESHOLDS)
        macc = f"{r.macc:7.3f}" if r.acc is not None else f"{'-':>7}"
        lines.append(f"{r.task:<5} {r.weighting:<8} {r.miou:7.3f} {shares} {macc} {tau:>{width}} {r.nonfinite:6d}")
    return "\n".join(lines)


CURVE_WHOLE_POINTS = 20  # a grid search of this many thresholds or fewer is printed whole (`format_curve`)


def format_curve(report: IoUReport, every: int = 5, whole_up_to: int = CURVE_WHOLE_POINTS) -> str:
    """The localisation grid search as a table: τ and mIoU (every `every`-th grid point, best marked; every point of a
    grid of at most `whole_up_to`, so a short --taus grid is shown whole: round 57c, 5 points showed as 1)."""
    lines = [f"grid search ({report.weighting}): tau  mIoU"]
    every = 1 if len(report.curve) <= whole_up_to else every
    decimals = tau_decimals(t for t, _ in report.curve)
    for k, (t, m) in enumerate(report.curve):
        mark = "  <- best" if report.threshold is not None and t == report.threshold else ""
        if k % every == 0 or mark:
            lines.append(f"  {tau_text(t, decimals):>5}  {m:6.3f}{mark}")
    return "\n".join(lines)


__all__ = [
    "IOU_THRESHOLDS", "IoUReport", "expand_scores", "tau_text", "match_gaussians", "VoxelGrid", "VoxelSetup", "argmax_labels", "evaluate_scene", "format_curve",
    "format_reports", "grid_for", "localisation_report", "scene_weights", "segmentation_iou", "segmentation_report",
    "significance_weights", "splat_mass", "splat_mass_reference", "threshold_iou_curve", "voxel_iou_bytes", "voxel_labels",
    "voxel_localisation_report", "voxel_segmentation_report", "weighted_iou",
]
