"""LangSplat's mask post-processing (`masks_update`): score-weighted NMS over overlapping masks, vectorised.

Every numba kernel has a numpy reference beside it (`*_reference`), tested equal."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numba
import numpy as np

from drsplat.features.masks.base import MaskSet

log = logging.getLogger(__name__)




@dataclass
class NmsParams:
    """LangSplat's masks_update thresholds (preprocess.py: iou 0.8, score 0.7, inner 0.5)."""

    iou_thr: float = 0.8
    score_thr: float = 0.7
    inner_thr: float = 0.5


@numba.njit(cache=True, nogil=True)
def _mask_boxes(masks: np.ndarray) -> np.ndarray:
    """[K, H, W] uint8 -> [K, 4] (y0, y1, x0, x1) half-open boxes; empty masks get y0 = y1 = 0."""
    k_count, h, w = masks.shape
    boxes = np.zeros((k_count, 4), np.int64)
    for k in range(k_count):
        y0, y1, x0, x1 = h, -1, w, -1
        for y in range(h):
            row = masks[k, y]
            for x in range(w):
                if row[x]:
                    if y < y0:
                        y0 = y
                    y1 = y
                    if x < x0:
                        x0 = x
                    if x > x1:
                        x1 = x
        if y1 >= 0:
            boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3] = y0, y1 + 1, x0, x1 + 1
    return boxes


@numba.njit(cache=True, nogil=True)
def _intersections_kernel(masks: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    k_count, h, w = masks.shape
    n_words = (k_count + 63) // 64
    inter = np.zeros((k_count, k_count), np.int64)
    words = np.zeros((w + 1, n_words), np.uint64)
    members = np.empty(k_count, np.int64)
    for y in range(h):
        words[:] = 0
        for k in range(k_count):
            if boxes[k, 0] <= y < boxes[k, 1]:
                bit = np.uint64(1) << np.uint64(k & 63)
                wi = k >> 6
                row = masks[k, y]
                for x in range(boxes[k, 2], boxes[k, 3]):
                    if row[x]:
                        words[x, wi] |= bit
        start = 0
        for x in range(1, w + 1):
            same = x < w
            if same:
                for wi in range(n_words):
                    if words[x, wi] != words[start, wi]:
                        same = False
                        break
            if same:
                continue
            run = x - start
            n = 0
            for wi in range(n_words):
                word = words[start, wi]
                b = 0
                while word != 0:
                    if word & np.uint64(1):
                        members[n] = wi * 64 + b
                        n += 1
                    word >>= np.uint64(1)
                    b += 1
            for i in range(n):
                for j in range(n):
                    inter[members[i], members[j]] += run
            start = x
    return inter


def intersections(masks: np.ndarray) -> np.ndarray:
    """Pairwise pixel intersections I[i, j] = |m_i ∧ m_j|: masks [K, H, W] bool -> [K, K] int64.

    Numba kernel: per image row, each mask ORs its bit into a per-pixel bitset (only inside its
    bounding box); runs of equal bitsets add their length to every pair of member masks. Cost
    ∝ Σ box areas + Σ_runs (members)², never a dense K·P product.
    """
    m = np.ascontiguousarray(masks, dtype=bool).view(np.uint8)
    if m.shape[0] == 0:
        return np.zeros((0, 0), np.int64)
    return _intersections_kernel(m, _mask_boxes(m))


def intersections_reference(masks: np.ndarray) -> np.ndarray:
    """Obviously-correct reference of `intersections`: a float64 matrix product of flat masks."""
    flat = masks.reshape(masks.shape[0], int(np.prod(masks.shape[1:]))).astype(np.float64)  # -1 cannot be told for 0 masks (round 86b F3)
    return np.rint(flat @ flat.T).astype(np.int64)


def _nms_from_overlaps(inter: np.ndarray, area: np.ndarray, scores: np.ndarray, p: NmsParams) -> np.ndarray:
    """Kept positions, given the overlaps of masks already sorted by descending score."""
    k = len(scores)
    with np.errstate(divide="ignore", invalid="ignore"):
        frac_i = inter / area[:, None]  # share of mask i (row) covered by mask j
        frac_j = inter / area[None, :]
        iou = inter / (area[:, None] + area[None, :] - inter)
    upper = np.triu(np.ones((k, k), bool), 1)
    iou_max = np.where(upper, iou, 0.0).max(axis=0, initial=0.0)
    inner_val = 1.0 - frac_i * frac_j
    j_in_i = (frac_i < 0.5) & (frac_j >= 0.85)  # mask j lies mostly inside the larger mask i
    i_in_j = (frac_i >= 0.85) & (frac_j < 0.5)
    inner = np.where(upper & j_in_i, inner_val, 0.0)
    inner = np.maximum(inner, np.where(upper & i_in_j, inner_val, 0.0).T)
    band_l = np.tril(np.ones((k, k), bool), 1)  # torch.tril(diagonal=1) as in LangSplat
    inner_u = np.where(upper, inner, 0.0).max(axis=0, initial=0.0)
    inner_l = np.where(band_l, inner, 0.0).max(axis=0, initial=0.0)
    return _combine_keeps(iou_max, inner_u, inner_l, scores, p)


def _combine_keeps(iou_max: np.ndarray, inner_u: np.ndarray, inner_l: np.ndarray, scores: np.ndarray, p: NmsParams) -> np.ndarray:
    keep = iou_max <= p.iou_thr
    conds = [scores > p.score_thr, inner_u <= 1 - p.inner_thr, inner_l <= 1 - p.inner_thr]
    for cond in conds:
        if not cond.any():  # LangSplat's fallback: the three best-scored masks pass this test
            cond[: min(3, len(cond))] = True
        keep &= cond
    return np.flatnonzero(keep)


def _sorted_by_score(masks: np.ndarray, scores: np.ndarray) -> np.ndarray:
    if masks.ndim != 3 or len(scores) != masks.shape[0]:
        raise ValueError(f"masks must be [K, H, W] with K scores, got {masks.shape} and {len(scores)}")
    if masks.shape[0] and not masks.reshape(masks.shape[0], -1).any(axis=1).all():
        raise ValueError("masks must be non-empty")
    return np.argsort(-np.asarray(scores, np.float64), kind="stable")


def mask_nms(masks: np.ndarray, scores: np.ndarray, params: NmsParams = NmsParams()) -> np.ndarray:
    """LangSplat's mask NMS, vectorised. masks: [K, H, W] bool (non-empty), scores: [K].

    Masks are sorted by descending score (stable). With I = |m_i ∧ m_j|, a_i = |m_i|, for i < j:
    IoU_ij = I / (a_i + a_j - I); mask j is dropped if max_{i<j} IoU_ij > iou_thr, or its score
    <= score_thr, or it is in an "inner" relation 1 - (I/a_i)(I/a_j) > 1 - inner_thr with a mask
    where one covers >= 85 % of the other and the other < 50 % of it. The inner maxima are taken
    as LangSplat does: over rows above the diagonal (upper) and over rows >= j - 1 (its
    torch.tril(diagonal=1), which includes the first superdiagonal). If a test would drop every
    mask, the three best-scored masks pass it. Returns kept indices into `masks`, in score order.
    """
    order = _sorted_by_score(masks, scores)
    if len(order) == 0:
        return order
    ordered = masks[order]
    inter = intersections(ordered).astype(np.float64)
    area = np.diag(inter).copy()
    return order[_nms_from_overlaps(inter, area, np.asarray(scores, np.float64)[order], params)]


def mask_nms_reference(masks: np.ndarray, scores: np.ndarray, params: NmsParams = NmsParams()) -> np.ndarray:
    """Straightforward double loop over mask pairs, as LangSplat's preprocess.py (for tests)."""
    order = _sorted_by_score(masks, scores)
    k = len(order)
    if k == 0:
        return order
    m = masks[order].reshape(k, -1)
    s = np.asarray(scores, np.float64)[order]
    area = m.sum(axis=1).astype(np.float64)
    iou = np.zeros((k, k))
    inner = np.zeros((k, k))
    for i in range(k):
        for j in range(i, k):
            inter = float(np.logical_and(m[i], m[j]).sum())
            union = float(np.logical_or(m[i], m[j]).sum())
            iou[i, j] = inter / union
            a, b = inter / area[i], inter / area[j]
            if a < 0.5 and b >= 0.85:
                inner[i, j] = 1 - b * a
            if a >= 0.85 and b < 0.5:
                inner[j, i] = 1 - b * a
    iou_max = np.triu(iou, 1).max(axis=0)
    inner_u = np.triu(inner, 1).max(axis=0)
    inner_l = np.tril(inner, 1).max(axis=0)
    return order[_combine_keeps(iou_max, inner_u, inner_l, s, params)]


def masks_update(levels: list[MaskSet], params: NmsParams = NmsParams()) -> list[MaskSet]:
    """Remove redundant masks of each level (LangSplat's masks_update); kept masks keep their order.

    Empty masks are dropped first (they carry no pixels to register).
    """
    out = []
    for level in levels:
        nonempty = np.flatnonzero(level.masks.reshape(len(level), -1).any(axis=1)) if len(level) else np.zeros(0, np.int64)
        level = level.subset(nonempty)
        keep = np.sort(mask_nms(level.masks, level.scores, params))
        out.append(level.subset(keep))
    return out


