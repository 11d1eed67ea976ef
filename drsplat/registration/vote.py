"""Robust votes across views: the `-vote` stage of an aggregation mode (`--aggregate vote`, ...).

The paper's mean f_i = normalize(Σ_j w_ij f_j) lets one mislabelled view flip a Gaussian, and a
close-up view, whose footprint covers many pixels, carries most of w. The vote stage instead:

1. groups the views' masks by embedding: a mask joins the existing cluster whose leader (its
   first mask) is most similar if that cosine is ≥ CLUSTER_COSINE, else founds a new one
   (`MaskClusters`, in view order, so the same views give the same clusters everywhere);
2. per Gaussian i and cluster c sums the votes

       V_ic = Σ_views Σ_{j ∈ view, cluster(j) = c} w_ij / T_iv^γ,     T_iv = Σ_{j ∈ view} w_ij

   (γ = VIEW_POWER: 0 is the paper's weight, 1 gives every view that sees the Gaussian one vote
   split between its masks), kept in VOTE_SLOTS slots per Gaussian with the space-saving rule
   (a new cluster replaces the smallest slot and inherits its count, so a cluster holding more
   than 1/VOTE_SLOTS of the votes is never lost);
3. keeps the winning cluster c* = argmax_c V_ic and the slots whose cluster means have cosine
   ≥ CLUSTER_COSINE with c*'s, and sets

       f_i = normalize(Σ_{c ∈ group} V_ic μ_c),   μ_c = normalize(Σ_{j ∈ c} f_j)

   so a minority of mislabelled views is outvoted, and the feature is the consensus embedding of
   the masks of the winning group (mean over the whole scene's masks of those clusters, not only
   the Gaussian's own). The Gaussian's weight W_i = Σ w_ij stays the paper's, so coverage and
   floater rejection do not change.

Memory: VOTE_SLOTS·12 + 12 bytes per Gaussian (slots, W, a view-total scratch) instead of the
paper's F [N, D] (4·D bytes), plus K·D·12 bytes for K clusters and 4 bytes per mask for the
views' cluster ids. Under a memory budget the per-Gaussian slots are summed block by block from
the pair log (`VoteSink` with a log), pair by pair in the same order as in memory, so the bits do
not depend on the plan or the place.
"""

from __future__ import annotations

from collections.abc import Iterator

import numba
import numpy as np

from drsplat.registration.pairlog import PairLog, ViewPairs
from drsplat.registration.sink import Block

VOTE_SLOTS = 8  # candidate clusters kept per Gaussian
CLUSTER_COSINE = 0.9  # a mask joins a cluster whose leader is at least this similar
VIEW_POWER = 0.5  # γ: each view's votes are w_ij / T_iv^γ (docs/registration.md, "Design choices, measured")


class MaskClusters:
    """Leader clustering of the views' mask embeddings, in view order (module docstring).

    leaders: [K, D] float32 unit embeddings of each cluster's first mask; sums: [K, D] float64
    Σ of the member embeddings; per_view: the [M] int32 cluster of each mask of every view added
    (-1 for a zero embedding: a mask dropped for non-finite values).
    """

    def __init__(self, dim: int, threshold: float = CLUSTER_COSINE):
        self.dim, self.threshold = dim, float(threshold)
        self._leaders = np.zeros((64, dim), np.float32)
        self._sums = np.zeros((64, dim), np.float64)
        self.count = 0
        self.per_view: list[np.ndarray] = []

    @property
    def leaders(self) -> np.ndarray:
        return self._leaders[: self.count]

    def add(self, feats: np.ndarray) -> np.ndarray:
        """Assign one view's masks feats [M, D] (in order) and remember the ids; returns them [M] int32."""
        feats = np.asarray(feats, np.float32)
        norms = np.linalg.norm(feats.astype(np.float64), axis=1)
        ids = np.full(feats.shape[0], -1, np.int32)
        cos = feats @ self.leaders.T if self.count else np.zeros((feats.shape[0], 0), np.float32)
        for j in range(feats.shape[0]):
            if not norms[j] > 0:
                continue
            unit = feats[j] / np.float32(norms[j])
            best = int(np.argmax(cos[j])) if cos.shape[1] else -1
            if best >= 0 and cos[j, best] / norms[j] >= self.threshold:
                ids[j] = best
            else:
                if self.count > cos.shape[1]:  # leaders founded by this view's earlier masks
                    new = self._leaders[cos.shape[1] : self.count] @ unit
                    k = int(np.argmax(new))
                    if new[k] >= self.threshold:
                        ids[j] = cos.shape[1] + k
                if ids[j] < 0:
                    ids[j] = self._found(unit)
            self._sums[ids[j]] += feats[j]
        self.per_view.append(ids)
        return ids

    def _found(self, unit: np.ndarray) -> int:
        if self.count == self._leaders.shape[0]:
            grow = self._leaders.shape[0]
            self._leaders = np.concatenate([self._leaders, np.zeros((grow, self.dim), np.float32)])
            self._sums = np.concatenate([self._sums, np.zeros((grow, self.dim), np.float64)])
        self._leaders[self.count] = unit
        self.count += 1
        return self.count - 1

    def means(self) -> np.ndarray:
        """[K, D] float32 unit cluster means μ_c = normalize(Σ_{j ∈ c} f_j)."""
        sums = self._sums[: self.count]
        norm = np.linalg.norm(sums, axis=1, keepdims=True)
        return (sums / np.where(norm > 0, norm, 1.0)).astype(np.float32)


@numba.njit(cache=True)
def _vote_view_kernel(rows, clusters, weights, gamma, total, slot_c, slot_v, W):  # pragma: no cover - jitted
    """Fold one view's pairs (rows [P] of the Gaussians in slot_c / slot_v / W, clusters [P],
    weights [P] float32) into the vote slots (module docstring, step 2), pair by pair in order.
    total: [rows] float64 scratch, zero on entry and exit."""
    num_slots = slot_c.shape[1]
    for p in range(rows.shape[0]):
        total[rows[p]] += weights[p]
    for p in range(rows.shape[0]):
        r = rows[p]
        c = clusters[p]
        w = np.float64(weights[p])
        W[r] += weights[p]
        if c < 0 or not w > 0.0:
            continue
        v = w if gamma == 0.0 else w / total[r] ** gamma
        hit = -1
        low = 0
        for s in range(num_slots):
            if slot_c[r, s] == c or slot_c[r, s] < 0:
                hit = s
                break
            if slot_v[r, s] < slot_v[r, low]:
                low = s
        if hit >= 0:
            slot_c[r, hit] = c
            slot_v[r, hit] += v
        else:  # space-saving: the smallest slot's cluster is replaced, its count inherited
            slot_c[r, low] = c
            slot_v[r, low] += v
    for p in range(rows.shape[0]):
        total[rows[p]] = 0.0


def vote_features(slot_c: np.ndarray, slot_v: np.ndarray, means: np.ndarray, threshold: float = CLUSTER_COSINE) -> np.ndarray:
    """F [B, D] float32 = Σ_{c ∈ group_i} V_ic μ_c (module docstring, step 3; zero rows where no vote).

    slot_c: [B, S] int32 clusters (-1 empty), slot_v: [B, S] float64 votes, means: [K, D] unit μ_c.
    """
    b, _ = slot_c.shape
    F = np.zeros((b, means.shape[1]), np.float32)
    has = slot_c[:, 0] >= 0
    if not has.any() or means.shape[0] == 0:
        return F
    votes = np.where(slot_c >= 0, slot_v, -np.inf)
    win = slot_c[np.arange(b), np.argmax(votes, axis=1)]  # first of equal maxima
    cw = np.maximum(slot_c, 0)
    sim = np.einsum("bsd,bd->bs", means[cw], means[np.maximum(win, 0)])
    keep = (slot_c >= 0) & (sim >= threshold) & has[:, None]
    keep |= (slot_c == win[:, None]) & has[:, None]
    coef = np.where(keep, slot_v, 0.0)
    F[:] = np.einsum("bs,bsd->bd", coef, means[cw]).astype(np.float32)
    return F


def vote_reference(views: list[tuple[np.ndarray, np.ndarray, np.ndarray]], num_gaussians: int, means: np.ndarray,
                   gamma: float = VIEW_POWER, threshold: float = CLUSTER_COSINE) -> tuple[np.ndarray, np.ndarray]:
    """Obviously-correct reference of the vote stage with unbounded slots (numpy, float64).

    views: per view (gaussians [P], clusters [P], weights [P]). Returns (F [N, D] float64 before
    normalisation, W [N]): V_ic summed exactly; agrees with the kernel whenever no Gaussian meets
    more than VOTE_SLOTS clusters.
    """
    k = means.shape[0]
    V = np.zeros((num_gaussians, k))
    W = np.zeros(num_gaussians)
    for g, c, w in views:
        w = w.astype(np.float64)
        W += np.bincount(g, w, num_gaussians)
        total = np.bincount(g, w, num_gaussians)
        ok = (c >= 0) & (w > 0)
        v = w[ok] / total[g[ok]] ** gamma if gamma else w[ok]
        np.add.at(V, (g[ok], c[ok]), v)
    F = np.zeros((num_gaussians, means.shape[1]))
    for i in np.flatnonzero(V.max(axis=1) > 0):
        win = int(np.argmax(V[i]))
        group = (V[i] > 0) & (means @ means[win] >= threshold)
        group[win] = True
        F[i] = V[i, group] @ means[group]
    return F, W


class VoteSink:
    """A sink (drsplat.registration.sink) whose blocks hold the vote stage's features.

    Without a log, the vote slots of all N Gaussians are kept while the views arrive; with one
    (a plan of several blocks), each block replays the log keeping its Gaussians' pairs. Either
    way `add` assigns the view's masks to clusters (every view, replayed ones included, in order).
    """

    def __init__(self, num_gaussians: int, dim: int, plog: PairLog | None = None, block: int | None = None,
                 slots: int = VOTE_SLOTS, gamma: float = VIEW_POWER):
        self.num_gaussians, self.dim, self.slots, self.gamma = num_gaussians, dim, int(slots), float(gamma)
        self.clusters = MaskClusters(dim)
        self._log = plog
        self.block = num_gaussians if plog is None else int(block)
        if self.block < 1:
            raise ValueError("block must be >= 1")
        self._state = None if plog is not None else self._empty(num_gaussians)

    def _empty(self, rows: int):
        return (np.full((rows, self.slots), -1, np.int32), np.zeros((rows, self.slots)), np.zeros(rows, np.float32), np.zeros(rows))

    @property
    def num_blocks(self) -> int:
        return max(1, -(-self.num_gaussians // self.block))

    def add(self, view: ViewPairs) -> None:
        ids = self.clusters.add(view.feats)
        if self._state is not None:
            self._fold(self._state, view.gaussians, ids[view.masks], view.weights)

    def _fold(self, state, rows: np.ndarray, clusters: np.ndarray, weights: np.ndarray) -> None:
        slot_c, slot_v, W, total = state
        _vote_view_kernel(np.ascontiguousarray(rows, np.int32), np.ascontiguousarray(clusters, np.int32),
                          np.ascontiguousarray(weights, np.float32), self.gamma, total, slot_c, slot_v, W)

    def blocks(self) -> Iterator[Block]:
        means = self.clusters.means()
        for lo in range(0, self.num_gaussians, self.block):
            hi = min(self.num_gaussians, lo + self.block)
            if self._state is not None:
                slot_c, slot_v, W, _ = self._state
            else:
                slot_c, slot_v, W, _ = self._replay(lambda g: (g >= lo) & (g < hi), lambda g: g - lo, hi - lo)
            yield Block(lo, hi, vote_features(slot_c, slot_v, means), W)

    def sample(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F [S, D], W [S]) of the Gaussians `ids` [S] (sorted, distinct)."""
        means = self.clusters.means()
        if self._state is not None:
            slot_c, slot_v, W, _ = self._state
            return vote_features(slot_c[ids], slot_v[ids], means), W[ids].copy()
        row = np.full(self.num_gaussians, -1, np.int32)
        row[ids] = np.arange(ids.shape[0], dtype=np.int32)
        slot_c, slot_v, W, _ = self._replay(lambda g: row[g] >= 0, lambda g: row[g], ids.shape[0])
        return vote_features(slot_c, slot_v, means), W

    def _replay(self, select, to_row, rows: int):
        state = self._empty(rows)
        for index, view in enumerate(self._log):
            keep = select(view.gaussians)
            if keep.any():
                self._fold(state, to_row(view.gaussians[keep]), self.clusters.per_view[index][view.masks[keep]], view.weights[keep])
        return state
