"""Pseudo ground truth for Gaussians from a labelled point cloud (ScanNet-like).

The Dr. Splat supplement labels Gaussian G_i from the labelled points near it, measuring nearness
by the Mahalanobis distance D(p, G_i) = (p − μ_i)ᵀ Σ_i⁻¹ (p − μ_i) under the Gaussian's covariance.
Its equation, as printed, takes argmax_l Σ_{p ∈ P_l} D(p, G_i): a *sum of distances*, which would
pick the label whose points are farthest (and most numerous) — the opposite of the intent. We read
it as a sum of *closeness* and implement

    label_i = argmax_l Σ_{p ∈ P_l, D(p, G_i) ≤ r²} exp(−½ D(p, G_i))            (weighting="gaussian")

i.e. every point within Mahalanobis radius r (default 3, the usual 3σ support) votes with the
Gaussian's own (unnormalised) density at that point. Points deep inside the ellipsoid dominate,
points at its rim barely count, and the result does not hinge on the exact radius. The plain count
of points within the radius (weighting="count") is available for comparison.

Points labelled −1 (unannotated; ScanNet's label 0 maps there) vote for "no label": a Gaussian
whose strongest vote is "no label", or that has no point within its radius, gets −1.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial import cKDTree

from drsplat.utils import CancelToken, progress

log = logging.getLogger(__name__)

WEIGHTINGS = ("gaussian", "count")


@dataclass
class PseudoLabels:
    """labels: [N] int32 (−1 none); support: [N] float winning vote; num_points: [N] points within the radius.

    nonfinite: Gaussians skipped for non-finite means/scales/rotations (label −1).
    """

    labels: np.ndarray
    support: np.ndarray
    num_points: np.ndarray
    nonfinite: int = 0


def _gaussian_frames(scene_or_arrays) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if isinstance(scene_or_arrays, tuple):
        means, rotations, scales = scene_or_arrays
    else:
        means, rotations, scales = scene_or_arrays.means, scene_or_arrays.rotations(), scene_or_arrays.scales()
    return np.asarray(means, np.float64), np.asarray(rotations, np.float64), np.asarray(scales, np.float64)


def mahalanobis_sq(points: np.ndarray, means: np.ndarray, rotations: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """D = (p − μ)ᵀ Σ⁻¹ (p − μ) with Σ = R S² Rᵀ, computed as Σ_k ((Rᵀ(p − μ))_k / s_k)².

    points, means: [P, 3]; rotations: [P, 3, 3]; scales: [P, 3] (row-aligned pairs). Returns [P].
    """
    local = np.einsum("pk,pkj->pj", points - means, rotations)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        return np.sum((local / scales) ** 2, axis=1)


def _votes(d2: np.ndarray, weighting: str) -> np.ndarray:
    if weighting == "gaussian":
        return np.exp(-0.5 * d2)
    if weighting == "count":
        return np.ones_like(d2)
    raise ValueError(f"unknown weighting {weighting!r}; expected one of {WEIGHTINGS}")


def _decide(gauss_idx: np.ndarray, point_class: np.ndarray, votes: np.ndarray, n: int, num_classes: int):
    """Per Gaussian: the class with the largest vote sum among the classes of its voters (the first on a tie), that sum,
    and the number of voters. Among its voters' classes only: votes exp(−D/2) are all 0.0 past D ≈ 1490 (a --radius near
    40), and argmax over every class then gave the cloud's first label, which no point near it had (round 69c F1)."""
    key = gauss_idx * num_classes + point_class
    sums = np.bincount(key, weights=votes, minlength=n * num_classes).reshape(n, num_classes)
    voted = np.bincount(key, minlength=n * num_classes).reshape(n, num_classes) > 0
    counts = np.bincount(gauss_idx, minlength=n)
    best = np.argmax(np.where(voted, sums, -1.0), axis=1)
    return best, sums[np.arange(n), best], counts


def pseudo_labels_reference(gaussians, points: np.ndarray, point_labels: np.ndarray, radius: float = 3.0,
                            weighting: str = "gaussian") -> np.ndarray:
    """Obviously-correct dense version of `pseudo_labels` (every point against every Gaussian). [N] int."""
    means, rots, scales = _gaussian_frames(gaussians)
    pts = np.asarray(points, np.float64)
    labels = np.asarray(point_labels, np.int64)
    out = np.full(means.shape[0], -1, np.int64)
    for i in range(means.shape[0]):
        d2 = mahalanobis_sq(pts, np.broadcast_to(means[i], pts.shape), np.broadcast_to(rots[i], (len(pts), 3, 3)), np.broadcast_to(scales[i], pts.shape))
        near = d2 <= radius * radius
        if not near.any():
            continue
        score: dict[int, float] = {}
        for lab, v in zip(labels[near], _votes(d2[near], weighting)):
            score[int(lab)] = score.get(int(lab), 0.0) + float(v)
        best = max(sorted(score), key=lambda k: score[k])
        out[i] = best if best >= 0 else -1
    return out


def whitening(rotations: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """W = S⁻¹ Rᵀ per Gaussian: [N, 3, 3] float64, so that D = |W (p − μ)|² = dᵀ Σ⁻¹ d.

    The whitened form sums three squares, as `mahalanobis_sq` does; the expanded quadratic form
    with Σ⁻¹'s entries (~1/s_min²) cancels for flat Gaussians: at scales 1e-8 : 1 : 1 it put
    distances 2.25 / 8.41 / 9.61 at 3 / 8 / 8 (a numerical probe, 2026-11-30)."""
    with np.errstate(divide="ignore", over="ignore"):
        return np.ascontiguousarray(rotations.transpose(0, 2, 1) / scales[:, :, None])


def _whitened_sq(d: np.ndarray, w: np.ndarray) -> np.ndarray:
    """|W d|² from difference vectors d: [P, 3] and the gathered W: [P, 3, 3] (`whitening`)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return np.sum(np.einsum("pkj,pj->pk", w, d) ** 2, axis=1)


def radius_batches(eu_radius: np.ndarray, todo: np.ndarray, chunk: int, ratio: float = 2.0**0.5) -> list[np.ndarray]:
    """Gaussian indices grouped by search radius (bins a factor `ratio` wide), at most `chunk` per group.

    One fixed-radius KD-tree join per group fetches every point within the group's largest radius;
    with narrow bins no Gaussian over-fetches more than ratio³ ≈ 2.8 times its own ball.
    """
    if len(todo) == 0:
        return []
    key = np.floor(np.log(eu_radius[todo]) / np.log(ratio)).astype(np.int64)
    order = np.argsort(key, kind="stable")
    todo, key = todo[order], key[order]
    cuts = np.flatnonzero(np.diff(key)) + 1
    out = []
    for group in np.split(todo, cuts):
        out.extend(group[i : i + chunk] for i in range(0, len(group), chunk))
    return out


def _vote_batch(batch, pairs, pts, point_class, classes, means, white, eu_radius, radius, weighting, labels, support, num_points) -> None:
    """Decide the Gaussians of one batch from their candidate (Gaussian, point) pairs, in place."""
    local, pj, dist = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64), pairs["v"]
    inside = dist <= eu_radius[batch][local]
    local, pj = local[inside], pj[inside]
    gi = batch[local]
    d2 = _whitened_sq(pts[pj] - means[gi], white[gi])
    near = d2 <= radius * radius
    best, sup, cnt = _decide(local[near], point_class[pj[near]], _votes(d2[near], weighting), len(batch), len(classes))
    has = cnt > 0
    labels[batch[has]] = np.maximum(classes[best[has]], -1)
    support[batch[has]] = sup[has]
    num_points[batch] = cnt


ENGINES = ("grid", "kdtree")


@numba.njit(parallel=True, cache=True)
def _grid_vote_kernel(todo, means, white, half, pts, cls, cell_start, origin, h, nx, ny, nz, r2, gaussian_votes, num_classes,
                      out_best, out_support, out_count):  # pragma: no cover - jitted
    """Per Gaussian of `todo`, the vote of the points in the grid cells of its box μ ± half (cells
    clamped to the grid; an infinite half-extent, from a scale near the float64 range, takes every
    cell), D = |W (p − μ)|² (`whitening`)."""
    for t in numba.prange(todo.shape[0]):
        i = todo[t]
        votes = np.zeros(num_classes)
        voted = np.zeros(num_classes, np.bool_)  # the classes of its voters: the only ones that can win (`_decide`)
        count = 0
        lo = np.empty(3, np.int64)
        hi = np.empty(3, np.int64)
        dims = (nx, ny, nz)
        for k in range(3):
            # NaN-free before the cast: ±inf compare and clamp, inf / inf would not
            a = (means[i, k] - half[i, k] - origin[k]) / h
            b = (means[i, k] + half[i, k] - origin[k]) / h
            lo[k] = int(np.floor(a)) if a > 0.0 and a < dims[k] else (0 if not a >= dims[k] else dims[k])
            hi[k] = int(np.floor(b)) if b >= 0.0 and b < dims[k] - 1.0 else (dims[k] - 1 if b >= dims[k] - 1.0 else -1)
        for cx in range(lo[0], hi[0] + 1):
            for cy in range(lo[1], hi[1] + 1):
                base = (cx * ny + cy) * nz
                for p in range(cell_start[base + lo[2]], cell_start[base + hi[2] + 1] if hi[2] >= lo[2] else cell_start[base + lo[2]]):
                    x = pts[p, 0] - means[i, 0]
                    y = pts[p, 1] - means[i, 1]
                    z = pts[p, 2] - means[i, 2]
                    m2 = 0.0
                    for k in range(3):
                        u = white[i, k, 0] * x + white[i, k, 1] * y + white[i, k, 2] * z
                        m2 += u * u
                    if m2 <= r2:
                        votes[cls[p]] += math.exp(-0.5 * m2) if gaussian_votes else 1.0
                        voted[cls[p]] = True
                        count += 1
        out_count[i] = count
        if count > 0:
            best = -1
            for c in range(num_classes):
                if voted[c] and (best < 0 or votes[c] > votes[best]):
                    best = c
            out_best[i] = best
            out_support[i] = votes[best]


@dataclass
class _Prepared:
    means: np.ndarray
    white: np.ndarray  # [N, 3, 3] W = S⁻¹ Rᵀ (`whitening`)
    half: np.ndarray  # [N, 3] half-extents of the ellipsoid D ≤ r² along x, y, z (inf past float64)
    eu_radius: np.ndarray  # [N] r · max_k s_k, at most the distance to the farthest point
    todo: np.ndarray  # indices of valid Gaussians
    pts: np.ndarray
    point_class: np.ndarray  # [P] index into classes
    classes: np.ndarray  # sorted distinct point labels
    nonfinite: int


def _prepare(gaussians, points, point_labels, radius: float) -> _Prepared:
    means, rots, scales = _gaussian_frames(gaussians)
    pts = np.asarray(points, np.float64)
    plab = np.asarray(point_labels, np.int64)
    if pts.ndim != 2 or pts.shape[1] != 3 or plab.shape != (pts.shape[0],):
        raise ValueError(f"points must be [P, 3] with labels [P]; got {pts.shape} and {plab.shape}")
    ok_pts = np.isfinite(pts).all(axis=1)
    if not ok_pts.all():
        log.warning("%d labelled points have non-finite coordinates; ignored", int((~ok_pts).sum()))
        pts, plab = pts[ok_pts], plab[ok_pts]
    n = means.shape[0]
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(means).all(axis=1) & np.isfinite(scales).all(axis=1) & (scales > 0).all(axis=1) & np.isfinite(rots).all(axis=(1, 2))
    nonfinite = int(n - valid.sum())
    if nonfinite:
        log.warning("%d Gaussians have non-finite or zero scales/means; they get no pseudo-label", nonfinite)
    todo = np.flatnonzero(valid)
    white = np.zeros((n, 3, 3))
    half = np.zeros((n, 3))
    eu_radius = np.zeros(n)
    if len(todo):
        white[todo] = whitening(rots[todo], scales[todo])
        largest = scales[todo].max(axis=1)
        with np.errstate(over="ignore"):  # past the float64 range: inf, a box over every point
            # the ellipsoid's axis-aligned box: r·sqrt(Σ_kk), Σ_kk = Σ_j R_kj² s_j², with s_j / max s
            # inside the root so that no square overflows (0 · inf would be NaN)
            unit = scales[todo] / largest[:, None]
            half[todo] = radius * largest[:, None] * np.sqrt(np.einsum("nkj,nj->nk", rots[todo] ** 2, unit**2))
            eu_radius[todo] = radius * largest
        if len(pts):  # no point lies farther from μ than |μ − c| + the points' half-diagonal (c: their box's centre)
            lo, hi = pts.min(axis=0), pts.max(axis=0)
            with np.errstate(over="ignore"):  # past the float64 range the reach is inf, which leaves the radius as it is
                reach = np.linalg.norm(means[todo] - 0.5 * (lo + hi), axis=1) + 0.5 * np.linalg.norm(hi - lo)
            eu_radius[todo] = np.minimum(eu_radius[todo], np.nextafter(reach * (1 + 1e-9), np.inf))
    classes, point_class = np.unique(plab, return_inverse=True)
    return _Prepared(means, white, half, eu_radius, todo, pts, point_class.astype(np.int64), classes, nonfinite)


def _point_grid(pts: np.ndarray, half: np.ndarray, max_cells: int):
    """Points bucketed in a uniform grid: (sorted order, cell_start [C+1], origin, h, (nx, ny, nz)).

    The cell edge is the median Gaussian half-extent (so a typical Gaussian visits a few cells),
    enlarged when needed to keep at most `max_cells` cells.
    """
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    with np.errstate(over="ignore"):  # points ±1.7e308 apart: an extent past the float64 range is inf (one cell, below)
        extent = np.maximum(hi - lo, 1e-9)
    # a half-extent beyond the points' extent (or infinite) visits every cell whatever the cell size
    typical = float(np.median(np.minimum(half.max(axis=1), extent.max()))) if len(half) else 1.0
    with np.errstate(over="ignore"):  # a volume past the float64 range is inf: then one cell holds every point (right, only slower)
        h = max(typical, float(np.prod(extent) / max_cells) ** (1 / 3), float(extent.max()) / 4096, 1e-12)
    if math.isfinite(h):
        dims = np.minimum(np.floor(extent / h).astype(np.int64) + 1, 1 << 20)
        cell = np.minimum(((pts - lo) / h).astype(np.int64), dims - 1)
    else:  # one cell, said without inf / inf: an infinite extent made NaN cell counts and indices, cast to int64's
        # smallest value, and no Gaussian found a point (two points at ±1.7e308 beside a good cloud labelled nothing; round 46)
        dims, cell = np.ones(3, np.int64), np.zeros((len(pts), 3), np.int64)
    flat = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = np.argsort(flat, kind="stable")
    start = np.searchsorted(flat[order], np.arange(int(np.prod(dims)) + 1))
    return order, start, lo, h, tuple(int(d) for d in dims)


def _labels_grid(prep: _Prepared, radius: float, weighting: str, chunk: int, max_cells: int, out, show_progress, on_progress, cancel) -> None:
    labels, support, num_points = out
    order, start, origin, h, (nx, ny, nz) = _point_grid(prep.pts, prep.half[prep.todo], max_cells)
    pts_sorted = np.ascontiguousarray(prep.pts[order])
    cls_sorted = np.ascontiguousarray(prep.point_class[order])
    n = len(prep.means)
    best = np.zeros(n, np.int64)
    for k, s in enumerate(progress(range(0, len(prep.todo), chunk), "pseudo-labels", enabled=show_progress, unit="chunk")):
        if cancel is not None:
            cancel.raise_if_cancelled()
        part = prep.todo[s : s + chunk]
        _grid_vote_kernel(part, prep.means, prep.white, prep.half, pts_sorted, cls_sorted, start, origin, h, nx, ny, nz, radius * radius,
                          weighting == "gaussian", len(prep.classes), best, support, num_points)
        if on_progress is not None:
            on_progress(min(s + chunk, len(prep.todo)), len(prep.todo))
    has = num_points > 0
    labels[has] = np.maximum(prep.classes[best[has]], -1)


def _labels_kdtree(prep: _Prepared, radius: float, weighting: str, chunk: int, max_pairs: int, out, show_progress, on_progress, cancel) -> None:
    labels, support, num_points = out
    point_tree = cKDTree(prep.pts)
    batches = radius_batches(prep.eu_radius, prep.todo, chunk)
    bar = progress(None, "pseudo-labels", total=len(prep.todo), enabled=show_progress, unit="G")
    done = 0
    try:
        while batches:
            if cancel is not None:
                cancel.raise_if_cancelled()
            batch = batches.pop()
            r_max = float(prep.eu_radius[batch].max())
            batch_tree = cKDTree(prep.means[batch])
            if len(batch) > 1 and batch_tree.count_neighbors(point_tree, r_max) > max_pairs:
                batches.extend(np.array_split(batch, 2))
                continue
            pairs = batch_tree.sparse_distance_matrix(point_tree, r_max, output_type="ndarray")
            _vote_batch(batch, pairs, prep.pts, prep.point_class, prep.classes, prep.means, prep.white, prep.eu_radius, radius, weighting,
                        labels, support, num_points)
            done += len(batch)
            bar.update(len(batch))
            if on_progress is not None:
                on_progress(done, len(prep.todo))
    finally:
        bar.close()


def pseudo_labels(gaussians, points: np.ndarray, point_labels: np.ndarray, radius: float = 3.0, weighting: str = "gaussian",
                  engine: str = "grid", chunk: int = 50_000, max_pairs: int = 2_000_000, max_cells: int = 1 << 22,
                  show_progress: bool = True, on_progress=None, cancel: CancelToken | None = None) -> PseudoLabels:
    """Label each Gaussian by the Mahalanobis-weighted vote of the labelled points near it.

    gaussians: a GaussianScene, or a tuple (means [N,3], rotations [N,3,3], scales [N,3]).
    points: [P, 3]; point_labels: [P] int, −1 for unannotated. radius r: Mahalanobis cut-off.
    Returns `PseudoLabels` (see the module docstring for the rule). Both engines give the labels
    of `pseudo_labels_reference` (every point against every Gaussian), except at two knife edges of exact arithmetic,
    where each computes D in its own order (the engines through the whitening W, the grid's kernel and the kdtree's
    `_whitened_sq` each in their own order, the reference through `mahalanobis_sq`), so rounding decides them either
    way: two labels' votes that tie (two points mirrored about a mean; round 71a F5: 4 of 300 random cases built around
    ties), and a point at D = r² exactly, inside by one formula and outside by another (round 86b F2: 14-18 of 300
    Gaussians each with a point placed there; a point must lie within ~1e-15 of the cut-off):

    - "grid" (default): the points are bucketed in a uniform grid; a parallel numba kernel visits,
      per Gaussian, the cells of the ellipsoid's axis-aligned box (half-extent r·sqrt(Σ_kk), tight
      for flat Gaussians), and filters and votes point by point. No candidate pairs are stored, so
      memory is O(N + P) and time O(candidates) in compiled code.
    - "kdtree": the ellipsoid lies in the ball of radius r·max_k s_k. Gaussians are grouped by that
      radius (`radius_batches`); per group a KD-tree over the group's means is joined with one over
      the points (scipy `sparse_distance_matrix`, pairs as arrays); the Mahalanobis filter and the
      votes run vectorised in numpy. A dual-tree count splits any group with more than `max_pairs`
      candidates first, so memory stays bounded (≈ 150 bytes per pair).
    """
    if weighting not in WEIGHTINGS:
        raise ValueError(f"unknown weighting {weighting!r}; expected one of {WEIGHTINGS}")
    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r}; expected one of {ENGINES}")
    prep = _prepare(gaussians, points, point_labels, radius)
    n = len(prep.means)
    out = (np.full(n, -1, np.int32), np.zeros(n, np.float64), np.zeros(n, np.int64))
    if len(prep.todo) and len(prep.pts):
        if engine == "grid":
            _labels_grid(prep, radius, weighting, chunk, max_cells, out, show_progress, on_progress, cancel)
        else:
            _check_kdtree_range(prep)
            _labels_kdtree(prep, radius, weighting, chunk, max_pairs, out, show_progress, on_progress, cancel)
    return PseudoLabels(*out, nonfinite=prep.nonfinite)


KDTREE_MAX_COORDINATE = 1e150  # squared distances between coordinates past this overflow float64 inside scipy's KD-tree


def _check_kdtree_range(prep: _Prepared) -> None:
    """ValueError when a finite coordinate of the points or Gaussians is too large for the kdtree
    engine: scipy's `sparse_distance_matrix` then stops with "Encountering floating point overflow"
    (a round-40 probe, coordinates near 1e199); the grid engine labels them."""
    largest = max(float(np.abs(prep.pts).max(initial=0.0)), float(np.abs(prep.means[prep.todo]).max(initial=0.0)))
    if largest > KDTREE_MAX_COORDINATE:
        raise ValueError(f"the kdtree engine cannot label coordinates this large (up to {largest:.3g}; its squared distances "
                         f"overflow past {KDTREE_MAX_COORDINATE:.0e}); use the grid engine (the default)")
