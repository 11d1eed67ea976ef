"""Robust votes across views: the `-vote` stage of an aggregation mode (`--aggregate vote-reject`, ...).

The paper's mean f_i = normalize(Σ_j w_ij f_j) lets one mislabelled view move a Gaussian, most of
all a close-up one, whose footprint covers many pixels and so carries most of w. The vote stage
keeps the paper's sums and trims them:

1. the views' masks are grouped by embedding: a mask joins the existing cluster whose leader (its
   first mask) is most similar if that cosine is ≥ CLUSTER_COSINE, else founds a new one
   (`MaskClusters`, in view order, so the same views give the same clusters everywhere); μ_c =
   normalize(Σ_{j ∈ c} f_j) is a cluster's mean embedding;
2. per Gaussian i and cluster c, every view votes by presence, not by area:

       V_ic = Σ_views Σ_{j ∈ view, cluster(j) = c} min(1, s_ijv / ρ) · min(1, T_iv / T₀),
       s_ijv = w_ij / T_iv,   T_iv = Σ_{j ∈ view} w_ij

   (one vote per (Gaussian, mask) pair: a Gaussian inside two masks of one cluster in a view, two
   instances of a label, gets up to two votes there; the cross-view check,
   drsplat.registration.check, counts one per view and cluster)

   (ρ = PRESENCE: a mask holding at least that share of the Gaussian's weight in a view gets
   the view's full vote, so a close-up view counts once; T₀ = FULL_VIEW: a view in which the
   Gaussian is faint, far or mostly hidden, T_iv < T₀, votes in proportion, since a small object
   seen from afar has no mask of its own there and lands in its surroundings' mask), together with the paper's weight of the
   cluster S_ic = Σ_views Σ_{j ∈ c} w_ij; both kept in VOTE_SLOTS slots per Gaussian with the
   space-saving rule (the pairs taken in (Gaussian, mask) order, a new cluster replaces the slot
   with the fewest votes, the first of those on a tie, and inherits its votes and its weight S, so
   a cluster voted by more than 1/VOTE_SLOTS of the views is never lost, and a trimmed slot can
   carry an evicted cluster's weight);
3. the votes of each cluster's group, G_ic = Σ_{c' like c} V_ic' (c' like c: μ_c·μ_c' ≥ θ, c
   itself included); the winner c* = argmax_c G_ic (of bit-equal maxima the lowest cluster id); a cluster c is trimmed when it is not like
   the winner (μ_c·μ_c* < θ) and its group is a minority of the views, G_ic < MINORITY·G_ic*:

       F_i = Σ_j w_ij f_j − Σ_{j : cluster(j) trimmed} w_ij f_j   (exact: after the cross-view check)
       F_i = Σ_j w_ij f_j − Σ_{c trimmed} S_ic μ_c                 (at the clusters' means: without it)

   A mislabelled mask is one view's (V small against the views that agree) and is trimmed; a
   silhouette Gaussian whose footprint spills onto the background in every view keeps both
   labels (both are present in every view), exactly as the paper has it. A Gaussian with one
   cluster keeps the paper's sums bit for bit. After the check (a `check-...-vote` mode, the
   default) the check's kept pairs are at hand in every plan and place, and a Gaussian that trims
   a cluster loses that cluster's own pairs (`exact_trimmed_features`: one more replay, read only
   when some Gaussian trims, each trimmed pair subtracted in float32 in the order it was added;
   an evicted cluster's pairs, which no slot names, are kept). Without the
   check (`vote`, `vote-reject`, ...: no record of the pairs in one block) the trimmed part is
   counted at the cluster's mean embedding, not at the Gaussian's own masks': exact when a
   cluster's masks agree; otherwise F_i keeps S_ic (f̄_ic − μ_c), f̄_ic its own masks' weighted
   mean in cluster c, which is small against the kept sums only while the trimmed weight is not
   much larger than the kept one, and a heavy close-up view trimmed against several far ones is
   where it is larger (docs/registration.md, "Robust votes across views"). W_i = Σ w_ij stays the
   paper's, so coverage and floater rejection do not change; an exact trim's block also carries
   the weight F_i still holds (Block.kept), which the normalisation judges |F_i| against.

   After the cross-view check the clusters are made again from the masks the check kept
   (`check.KeptPairs.clusters`) and the pairs are the kept masks' less those of views that abstain
   on a Gaussian (drsplat.registration.check, step 3).

   θ (`trim_cosine`) is CLUSTER_COSINE, or after the cross-view check (a `check-...-vote` mode,
   the default) NO_TRIM where the masks did not group across views (nothing to pool), else the
   lower of that and the check's like cosine, which the scene decides
   (drsplat.registration.check: halfway between how well a mask agrees with its Gaussians' other
   views and how alike two masks of one view are). Masks of one object that a segmenter cut into
   parts are embedded as parts, farther than CLUSTER_COSINE from the whole object's crops and from
   each other yet nearer than two different objects: each part is a cluster of its own with one
   view's vote. Compared one cluster at a time (until 2026-11-30), the object's votes were spread
   over its parts, the background its footprint spills onto won with one cluster, and the object's
   own clusters were trimmed as minorities (docs/evaluation.md, "Over-segmented masks"). When no
   two clusters of a Gaussian are alike, G = V and the rule is the one-cluster rule it was.

4. with sharp footprints (`Stages.specific`: masks that follow the objects' true silhouettes, the
   fit stage's choice) after the cross-view check, also by specificity. A thin or small object's
   Gaussian is an ordinary member of its own small mask and a sliver of the wall its footprint
   spills onto, while the votes of step 3 count both masks alike, and the wall's views, more of
   them, may win. Per Gaussian and cluster, how much of a member of the cluster's masks it is:

       P_ic = Σ_views Σ_{j ∈ view, cluster(j) = c} min(1, w_ij / w̄_j),   w̄_j = (Σ_i' w_i'j) / #{i' : w_i'j > 0}

   (1 per view for a Gaussian holding at least the mask's mean pair weight; capped, because a wall
   Gaussian behind a thin object holds more than the object's small Gaussians wherever a jittered
   object mask spills onto it, and uncapped it took the object's label: −0.06 to −0.11 loc mIoU
   vol on jittered rooms. w̄_j, mask j's mean pair weight over its whole view, comes from the
   check's supports, so every place and plan has the same numbers; P is summed by a replay of the
   kept pairs once the slots are final, `slot_specificity`). When some cluster left by step 3 is
   unlike the winner, the groups' P_g (summed over like clusters as G is) name the most specific
   one, and every cluster left that is unlike it and SPECIFIC times less specific is trimmed too.
   On footprint masks (the paper's weights) a footprint's spill is part of every view's masks and
   this would trim a Gaussian's own label, so it runs only where the fit stage finds the masks
   follow the sharp footprints (docs/evaluation.md, "Specificity").

Memory: the paper's F [N, D] plus VOTE_SLOTS·20 + 8 bytes per Gaussian (slots, a view-total
scratch; step 4: VOTE_SLOTS·8 more while a block is trimmed; the exact trim: 24 more and a sums
buffer (`sums.Accumulator` into F) of max(2²¹, N) pairs and 2 x 16 MB of embeddings at most, defaults.EXACT_TRIM_*), K·D·12 bytes for K clusters in
blocks that are never copied, a view's [M, CLUSTER_BLOCK] cosines at most, and 4 bytes per mask
for the views' cluster ids; the memory plan counts every mask as its own cluster
(`cluster_bytes`). Under a memory budget the slots are summed block by block from the pair log
with the block's F (`VoteSink` with a log), pair by pair in the same order as in memory, so the
bits do not depend on the plan or the place (tests/test_registration_matrix.py).
"""

from __future__ import annotations

import bisect
from collections.abc import Iterator
from dataclasses import dataclass

import numba
import numpy as np

from drsplat.defaults import VOTE_SLOTS
from drsplat.memory import small_page_full, small_page_zeros
from drsplat._sort_kernels import stable_order
from drsplat.registration.pairlog import ViewPairs
from drsplat.registration.sink import Block, PairSource, sample_rows
from drsplat.registration.sums import PAIR_SLOT_BYTES, Accumulator, buffer_bytes, buffered_rows

CLUSTER_COSINE = 0.9  # a mask joins a cluster whose leader is at least this similar
MINORITY = 0.34  # a cluster outside the winner's group is trimmed when its votes are below this x the winner's
FULL_VIEW = 0.5  # a view in which the Gaussian's total weight T_iv reaches this (half an opaque pixel) votes fully
PRESENCE = 0.1  # a view gives a cluster a full vote when it holds this share of the Gaussian's weight there (docs/registration.md)
PARALLEL_MACS = 1 << 21  # `dot_rows` below this many multiply-adds (~0.5 ms on one core) runs on the calling thread
LEADER_RUN = 64  # `dot_rows`: leaders per parallel run
FEW_MASKS = 8  # `dot_rows`: below this many masks a tile's sums run side by side over leaders (`_dot_few_masks`)
MASK_TILE = 256  # `dot_rows`: masks per tile (their [D, 256] float32 columns, 512 KB at D = 512, stay in L2)
CLUSTER_BLOCK = 4096  # mask clusters per block of MaskClusters' storage at most, and per block of a view's cosines with them
FIRST_CLUSTER_BLOCK = 64  # clusters in the first block; each next block holds twice as many, up to CLUSTER_BLOCK
VOTE_PARTS = 32  # row-aligned parts of a view's pairs, folded in parallel (several per thread even out their sizes)
TRIM_COSINE_TABLE_BYTES = 64 << 20  # the trim keeps its clusters' cosines in a [K, K] table up to K = 4,096
TRIM_BUFFER_PAIRS = 1 << 21  # trimmed pairs the exact trim buffers before subtracting them (24 MB, at least one per Gaussian; defaults.EXACT_TRIM_*)
TRIM_BUFFER_FEAT_BYTES = 16 << 20  # the mask embeddings it buffers with them (twice that as its buffer grows; more only for one view's alone)
SPECIFIC = 4.0  # step 4: a group this many times less specific than the most specific one is trimmed (docs/evaluation.md)


@numba.njit(cache=True)
def _row_dot(a, i, b, j):  # pragma: no cover - jitted
    """a[i] · b[j] in float32, the products added in index order d = 0, 1, ..., D-1
    (`ordered_dots_reference`): the one order of the vote's dot products.

    No fastmath: with reassociation the sum was split into as many lanes as the target's vectors
    hold, so an AVX-512 target (skylake-avx512, sapphirerapids) gave other bits than an AVX2 or
    Zen one in 73 % of 60,000 cosines, and a Ray reducer on such a node could trim otherwise than
    the driver's machine where a cosine sits within an ulp of CLUSTER_COSINE (round 66c F6)."""
    s = np.float32(0.0)
    for d in range(a.shape[1]):
        s += a[i, d] * b[j, d]
    return s


@numba.njit(cache=True, inline="always")
def _dot_leaders(feats_t, rows, j0, j1, c0, c1, acc, out):  # pragma: no cover - jitted
    """out[j, c] = Σ_d feats_t[d, j] · rows[c, d] for masks j0 ≤ j < j1 and leaders c0 ≤ c < c1, each
    sum in index order of d as `_row_dot`: the loop over masks is the one that vectorises (each
    lane its own sum), four leaders share each pass over feats_t. acc: [4, ≥ j1 - j0] float32 scratch.
    (The masks are read through a slice of each row of feats_t: indexed from j0, numba's check for
    negative indices kept the loop scalar, 2x slower.)"""
    dim, width = feats_t.shape[0], j1 - j0
    if width < FEW_MASKS:  # whole runs of eight leaders side by side; the rest (fewer than eight) as below
        whole = c0 + (c1 - c0) // 8 * 8
        _dot_few_masks(feats_t, rows, j0, j1, c0, whole, out)
        c0 = whole
    for g in range(c0, c1, 4):
        n = min(4, c1 - g)
        acc[:, :] = 0.0
        if n == 4:
            a0, a1, a2, a3 = acc[0], acc[1], acc[2], acc[3]
            for d in range(dim):
                f = feats_t[d, j0:j1]
                r0, r1, r2, r3 = rows[g, d], rows[g + 1, d], rows[g + 2, d], rows[g + 3, d]
                for j in range(width):
                    x = f[j]
                    a0[j] += x * r0
                    a1[j] += x * r1
                    a2[j] += x * r2
                    a3[j] += x * r3
        else:
            for q in range(n):
                a = acc[q]
                for d in range(dim):
                    f = feats_t[d, j0:j1]
                    r = rows[g + q, d]
                    for j in range(width):
                        a[j] += f[j] * r
        for q in range(n):
            for j in range(width):
                out[j0 + j, g + q] = acc[q, j]


@numba.njit(cache=True, inline="always")
def _dot_few_masks(feats_t, rows, j0, j1, c0, c1, out):  # pragma: no cover - jitted
    """`_dot_leaders` for fewer than FEW_MASKS masks, where a loop over them has too few lanes to vectorise and each
    leader's sum was one serial chain through memory (1.87 against 0.15 ms for one mask x 4,096 leaders with the old
    reassociated sums: round 68a F11): eight leaders' sums kept in registers, each in index order of d as `_row_dot`,
    side by side so that their adds overlap. c1 - c0 is a multiple of eight (the caller sums the rest: one serial chain
    a leader was 1.9x slower than the masks' lanes there, round 72a F2)."""
    dim = feats_t.shape[0]
    for j in range(j0, j1):
        g = c0
        while g + 8 <= c1:
            s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = np.float32(0.0)
            for d in range(dim):
                x = feats_t[d, j]
                s0 += x * rows[g, d]
                s1 += x * rows[g + 1, d]
                s2 += x * rows[g + 2, d]
                s3 += x * rows[g + 3, d]
                s4 += x * rows[g + 4, d]
                s5 += x * rows[g + 5, d]
                s6 += x * rows[g + 6, d]
                s7 += x * rows[g + 7, d]
            out[j, g], out[j, g + 1], out[j, g + 2], out[j, g + 3] = s0, s1, s2, s3
            out[j, g + 4], out[j, g + 5], out[j, g + 6], out[j, g + 7] = s4, s5, s6, s7
            g += 8


@numba.njit(parallel=True, cache=True)
def _dot_rows_kernel(feats_t, rows, out):  # pragma: no cover - jitted
    """out[j, c] = feats[j] · rows[c] (feats_t = featsᵀ [D, M]), parallel over runs of LEADER_RUN
    leaders on numba's own threads, the masks in tiles of MASK_TILE (a tile's [D, MASK_TILE] of
    feats_t stays in L2 while the run's leaders pass over it).

    A BLAS sgemm is a little faster (1.5 vs 2.1 ms for 55 masks x 2,750 leaders x 512), but
    OpenBLAS's threads then busy-wait for a while and take a core from the rasterizer's next
    parallel kernels: on 2 cores binning and projection ran 2-3x slower in every `-vote` mode
    (docs/registration.md); and its order of the sum depends on the CPU."""
    m, c = feats_t.shape[1], rows.shape[0]
    runs = (c + LEADER_RUN - 1) // LEADER_RUN
    for r in numba.prange(runs):
        acc = np.empty((4, min(m, MASK_TILE)), np.float32)
        for j0 in range(0, m, MASK_TILE):
            _dot_leaders(feats_t, rows, j0, min(m, j0 + MASK_TILE), r * LEADER_RUN, min(c, (r + 1) * LEADER_RUN), acc, out)


@numba.njit(cache=True)
def _dot_rows_serial_kernel(feats_t, rows, out):  # pragma: no cover - jitted
    """`_dot_rows_kernel` on the calling thread: the same sums, so the same bits (tested)."""
    m = feats_t.shape[1]
    acc = np.empty((4, min(m, MASK_TILE)), np.float32)
    for j0 in range(0, m, MASK_TILE):
        _dot_leaders(feats_t, rows, j0, min(m, j0 + MASK_TILE), 0, rows.shape[0], acc, out)


def ordered_dots_reference(feats: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """[M, C] float32: Σ_d feats[j, d] · rows[c, d], each product rounded to float32 and added to a
    float32 sum in index order of d: the order of `_row_dot` and `dot_rows`, bit for bit."""
    feats, rows = np.asarray(feats, np.float32), np.asarray(rows, np.float32)
    out = np.zeros((feats.shape[0], rows.shape[0]), np.float32)
    for d in range(feats.shape[1]):
        out += feats[:, d : d + 1] * rows[None, :, d]
    return out


def dot_rows(feats: np.ndarray, rows: np.ndarray, parallel: bool | None = None) -> np.ndarray:
    """[M, C] float32 feats [M, D] · rows [C, D]ᵀ, each sum in index order of d
    (`_dot_rows_kernel`; `ordered_dots_reference` is its reference, bit for bit).

    parallel: None picks by size. Products under PARALLEL_MACS multiply-adds run on the calling
    thread: a mask that founds a cluster is compared with the view's earlier new leaders (1 x a few
    x 512). Waking numba's threads for that cost 2.3 µs a call on an idle 2-core machine against
    1.0 µs on the calling thread, but ~2.4 ms a call with both cores busy, which on flowers (10
    views, random masks: ~1,100 such calls) was 1.3 s of a check-vote-reject run (2026-11-27)."""
    out = np.empty((feats.shape[0], rows.shape[0]), np.float32)
    if out.size:
        if parallel is None:
            parallel = out.size * feats.shape[1] >= PARALLEL_MACS
        kernel = _dot_rows_kernel if parallel else _dot_rows_serial_kernel
        kernel(np.ascontiguousarray(np.asarray(feats, np.float32).T), np.ascontiguousarray(rows, np.float32), out)
    return out


class MaskClusters:
    """Leader clustering of the views' mask embeddings, in view order (module docstring).

    The K clusters are kept in blocks of rows that are never copied (FIRST_CLUSTER_BLOCK rows, then
    twice as many per block up to CLUSTER_BLOCK): leaders, the [rows, D] float32 unit embedding of
    each cluster's first mask; sums, [rows, D] float64 Σ of the member embeddings. per_view: the
    [M] int32 cluster of each mask of every view added (-1 for a zero embedding: a mask dropped for
    non-finite values). A view's masks meet the leaders one block at a time, so a view of M masks
    holds an [M, CLUSTER_BLOCK] float32 scratch at most, whatever K (`cluster_bytes`).
    """

    def __init__(self, dim: int, threshold: float = CLUSTER_COSINE, block: int = CLUSTER_BLOCK):
        self.dim, self.threshold, self.block = dim, float(threshold), max(1, int(block))
        self._leaders: list[np.ndarray] = []
        self._sums: list[np.ndarray] = []
        self._starts: list[int] = []  # the first cluster of each block
        self.count = 0
        self.per_view: list[np.ndarray] = []

    def _leader_rows(self, lo: int, hi: int) -> Iterator[tuple[int, np.ndarray]]:
        """(first cluster, leaders [rows, D]) of clusters lo .. hi-1, block by block (views, no copies)."""
        for start, leaders in zip(self._starts, self._leaders):
            a, b = max(lo, start), min(hi, start + leaders.shape[0])
            if a < b:
                yield a, leaders[a - start : b - start]

    def _best_leaders(self, feats: np.ndarray, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        """(best [M] int64, value [M] float32): per row of feats [M, D], the first of the largest
        `dot_rows` values over the leaders lo .. hi-1 (-1 and -inf when there are none), as
        np.argmax over the whole [M, hi - lo] row would give (a NaN counts as the largest, the first
        one kept), computed one block of leaders at a time."""
        m = feats.shape[0]
        best, value = np.full(m, -1, np.int64), np.full(m, -np.inf, np.float32)
        rows = np.arange(m)
        for start, leaders in self._leader_rows(lo, hi):
            cos = dot_rows(feats, leaders)
            arg = np.argmax(cos, axis=1)
            top = cos[rows, arg]
            better = (top > value) | (np.isnan(top) & ~np.isnan(value))
            best[better], value[better] = start + arg[better], top[better]
        return best, value

    def add(self, feats: np.ndarray, present: np.ndarray | None = None) -> np.ndarray:
        """Assign one view's masks feats [M, D] (in order) and remember the ids; returns them [M] int32.

        present: [M] bool, the masks that reached some Gaussian; the others get -1 and neither found
        nor move a cluster (a mask that covers nothing must not change the field).
        """
        feats = np.asarray(feats, np.float32)
        norms = np.linalg.norm(feats.astype(np.float64), axis=1)
        ids = np.full(feats.shape[0], -1, np.int32)
        known = self.count  # clusters before this view: every mask meets them at once
        best, value = self._best_leaders(feats, 0, known)
        founded = np.empty((feats.shape[0], self.dim), np.float32)  # this view's new leaders, in order (clusters known, known + 1, ...)
        for j in range(feats.shape[0]):
            if not norms[j] > 0 or (present is not None and not present[j]):
                continue
            unit = feats[j] / np.float32(norms[j])
            if best[j] >= 0 and value[j] / norms[j] >= self.threshold:
                ids[j] = best[j]
            else:
                if self.count > known:  # the first of the most similar leaders this view founded (np.argmax: a NaN counts as largest)
                    cos = dot_rows(unit[None, :], founded[: self.count - known])[0]
                    top = int(np.argmax(cos))
                    if cos[top] >= self.threshold:
                        ids[j] = known + top
                if ids[j] < 0:
                    ids[j] = self._found(unit)
                    founded[self.count - known - 1] = unit
            b, r = self._locate(int(ids[j]))
            self._sums[b][r] += feats[j]
        self.per_view.append(ids)
        return ids

    def _locate(self, cluster: int) -> tuple[int, int]:
        """(block, row) of a cluster."""
        b = bisect.bisect_right(self._starts, cluster) - 1
        return b, cluster - self._starts[b]

    def _found(self, unit: np.ndarray) -> int:
        if not self._leaders or self.count == self._starts[-1] + self._leaders[-1].shape[0]:
            rows = min(self.block, FIRST_CLUSTER_BLOCK << len(self._leaders))
            self._starts.append(self.count)
            self._leaders.append(np.zeros((rows, self.dim), np.float32))
            self._sums.append(np.zeros((rows, self.dim), np.float64))
        self._leaders[-1][self.count - self._starts[-1]] = unit
        self.count += 1
        return self.count - 1

    def means(self) -> np.ndarray:
        """[K, D] float32 unit cluster means μ_c = normalize(Σ_{j ∈ c} f_j), block by block."""
        out = np.empty((self.count, self.dim), np.float32)
        for start, sums in zip(self._starts, self._sums):
            rows = sums[: max(0, min(sums.shape[0], self.count - start))]
            norm = np.linalg.norm(rows, axis=1, keepdims=True)
            out[start : start + rows.shape[0]] = rows / np.where(norm > 0, norm, 1.0)
        return out


def cluster_masks_reference(views: list[tuple[np.ndarray, np.ndarray | None]], threshold: float = CLUSTER_COSINE) -> tuple[list[np.ndarray], np.ndarray]:
    """Plain-numpy reference of MaskClusters over `views` [(feats [M, D], present [M] bool or None)],
    in float64: per view, in mask order, a mask joins the cluster of the most similar leader of the
    earlier views if that cosine is ≥ threshold, else the most similar leader founded by this view's
    earlier masks if ≥ threshold, else founds a cluster (its unit embedding the leader); a zero or
    absent mask gets -1. Returns (per view the [M] cluster ids, means [K, D] = normalize(Σ f_j)).
    MaskClusters computes the cosines in float32, so the two agree except on cosines within
    float32 rounding of the threshold."""
    leaders: list[np.ndarray] = []
    sums: list[np.ndarray] = []
    per_view = []
    for feats, present in views:
        rows = np.asarray(feats, np.float64)
        known = len(leaders)
        ids = np.full(rows.shape[0], -1, np.int32)
        for j, row in enumerate(rows):
            norm = np.linalg.norm(row)
            if not norm > 0 or (present is not None and not present[j]):
                continue
            unit = row / norm
            before = [float(unit @ leader) for leader in leaders[:known]]
            mine = [float(unit @ leader) for leader in leaders[known:]]
            if before and max(before) >= threshold:
                ids[j] = int(np.argmax(before))
            elif mine and max(mine) >= threshold:
                ids[j] = known + int(np.argmax(mine))
            else:
                leaders.append(unit)
                sums.append(np.zeros_like(unit))
                ids[j] = len(leaders) - 1
            sums[ids[j]] += row
        per_view.append(ids)
    means = np.array([total / max(np.linalg.norm(total), 1e-300) for total in sums]).reshape(len(sums), rows.shape[1] if views else 0)
    return per_view, means


def cluster_bytes(total_masks: int, max_masks: int, dim: int, block: int = CLUSTER_BLOCK) -> int:
    """The most one MaskClusters holds for views of `total_masks` masks in all, `max_masks` in one:
    every mask its own cluster (12·D bytes each: leader and sum), a partly filled block (its rows
    at most min(K, block)), a view's [M, min(K, block)] cosine scratch and its float64 copy for the
    norms, and 5 bytes per mask (its cluster id, the views' present flags)."""
    rows = min(total_masks, block)
    return (total_masks + rows) * dim * 12 + max_masks * (rows * 4 + dim * 8) + 5 * total_masks


@numba.njit(cache=True, inline="always")
def space_saving_slot(slot_c, slot_v, r, c):  # pragma: no cover - jitted
    """The slot of row r that cluster c goes to (space-saving): its own slot, else the first empty
    one (-1), else the slot with the fewest votes slot_v, whose cluster c replaces and whose counts
    it inherits; so a cluster holding more than 1/S of a row's votes is never lost."""
    low = 0
    for s in range(slot_c.shape[1]):
        if slot_c[r, s] == c or slot_c[r, s] < 0:
            return s
        if slot_v[r, s] < slot_v[r, low]:
            low = s
    return low


def vote_view_reference(rows, clusters, weights, presence, full_view, slot_c, slot_v, slot_s) -> None:
    """Plain-Python reference of `_vote_view_kernel`: fold one view's pairs, one after another in the
    given order, into the slots (in place; module docstring, step 2). The per-Gaussian total
    T_iv = Σ_j w_ij is summed in float64 in pair order first."""
    total = {}
    for r, w in zip(rows.tolist(), weights.tolist()):
        total[r] = total.get(r, 0.0) + w
    for r, c, w in zip(rows.tolist(), clusters.tolist(), weights.tolist()):
        if c < 0 or not w > 0.0:
            continue
        v = min(1.0, w / (total[r] * presence)) * min(1.0, total[r] / full_view) if presence > 0.0 else w
        hit = next((s for s in range(slot_c.shape[1]) if slot_c[r, s] == c or slot_c[r, s] < 0), None)
        if hit is None:
            hit = int(np.argmin(slot_v[r]))  # the first of the fewest votes
        slot_c[r, hit] = c
        slot_v[r, hit] += v
        slot_s[r, hit] += w


@numba.njit(cache=True)
def _row_aligned_cuts(rows, order, parts):  # pragma: no cover - jitted
    """[parts + 1] int64 cuts of `order` (pairs grouped by row) into about equal parts that never
    split a row's run (some may be empty)."""
    n = order.shape[0]
    cuts = np.empty(parts + 1, np.int64)
    cuts[0] = 0
    cuts[parts] = n
    for c in range(1, parts):
        i = max(c * n // parts, cuts[c - 1])
        while 0 < i < n and rows[order[i]] == rows[order[i - 1]]:
            i += 1
        cuts[c] = i
    return cuts


@numba.njit(cache=True, parallel=True)
def _vote_view_kernel(rows, clusters, weights, order, presence, full_view, total, slot_c, slot_v, slot_s):  # pragma: no cover - jitted
    """Fold one view's pairs (rows [P] of the Gaussians in slot_c / slot_v / slot_s, clusters [P],
    weights [P] float32) into the vote slots (module docstring, step 2): slot_v the votes V_ic,
    slot_s the paper's weight S_ic = Σ w_ij of the slot's cluster (what the trimmed mean removes).
    order [P]: the pairs grouped by row, each row's pairs in their given order (`stable_order`).
    total: [rows] float64 scratch, zero on entry and exit.

    A pair reads and writes its own row only, so the view is cut into VOTE_PARTS row-aligned parts
    folded in parallel, each in order: the bits of `vote_view_reference` taking the pairs in that
    order (tested); sorted by row, the [rows, S] slots are walked in order instead of at random."""
    cuts = _row_aligned_cuts(rows, order, VOTE_PARTS)
    for part in numba.prange(VOTE_PARTS):
        lo, hi = cuts[part], cuts[part + 1]
        for i in range(lo, hi):
            p = order[i]
            total[rows[p]] += weights[p]
        for i in range(lo, hi):
            p = order[i]
            r = rows[p]
            c = clusters[p]
            w = np.float64(weights[p])
            if c < 0 or not w > 0.0:
                continue
            v = min(1.0, w / (total[r] * presence)) * min(1.0, total[r] / full_view) if presence > 0.0 else w
            hit = space_saving_slot(slot_c, slot_v, r, c)
            slot_c[r, hit] = c
            slot_v[r, hit] += v
            slot_s[r, hit] += w
        for i in range(lo, hi):
            total[rows[order[i]]] = 0.0


FIRST_RUN_PROBE = _vote_view_kernel  # the stage's kernel whose place in numba's cache shows it ran here before (driver.say_if_kernels_compile)


def fold_view_votes(rows: np.ndarray, clusters: np.ndarray, weights: np.ndarray, presence: float, full_view: float, slot_c: np.ndarray,
                    slot_v: np.ndarray, slot_s: np.ndarray, total: np.ndarray | None = None) -> None:
    """Fold one view's pairs into the vote slots in place (`_vote_view_kernel`: module docstring,
    step 2). rows [P] (Gaussians, rows of the slots), clusters [P] (-1 none), weights [P] float32, in
    the view's pair order; slot_c [N, S] int32, slot_v / slot_s [N, S] float64; total: [N] float64
    zeros (scratch, zero again on return), or None for new ones."""
    rows = np.ascontiguousarray(rows, np.int32)
    total = np.zeros(slot_c.shape[0]) if total is None else total
    _vote_view_kernel(rows, np.ascontiguousarray(clusters, np.int32), np.ascontiguousarray(weights, np.float32), stable_order(rows),
                      float(presence), float(full_view), total, slot_c, slot_v, slot_s)


def trimmed_features_reference(F: np.ndarray, slot_c: np.ndarray, slot_v: np.ndarray, slot_s: np.ndarray, means: np.ndarray,
                     threshold: float = CLUSTER_COSINE, minority: float = MINORITY, slot_p: np.ndarray | None = None,
                     specific: float = SPECIFIC) -> np.ndarray:
    """Numpy reference of `trimmed_features`: in place on the paper's sums F [B, D] float32,
    F_i -= Σ_{c trimmed} S_ic μ_c (module docstring, step 3: group votes G, the winner's group, the
    minorities unlike it; step 4 with slot_p: the groups far less specific than the most specific
    one, row by row in Python); rows with one voted cluster are left bit for bit as they are.

    slot_c: [B, S] int32 clusters (-1 empty), slot_v / slot_s / slot_p: [B, S] float64 votes /
    paper weights / specificities (`slot_specificity`; None: no step 4), means: [K, D] unit μ_c.
    Returns F.
    """
    drop = trimmed_slots_reference(slot_c, slot_v, means, threshold, minority, slot_p, specific)
    mixed = np.flatnonzero(drop.any(axis=1))
    if mixed.size == 0:
        return F
    coef = np.where(drop[mixed], slot_s[mixed], 0.0)
    F[mixed] = (F[mixed].astype(np.float64) - np.einsum("bs,bsd->bd", coef, means[np.maximum(slot_c[mixed], 0)])).astype(np.float32)
    return F


def trimmed_slots_reference(slot_c: np.ndarray, slot_v: np.ndarray, means: np.ndarray, threshold: float = CLUSTER_COSINE,
                            minority: float = MINORITY, slot_p: np.ndarray | None = None, specific: float = SPECIFIC) -> np.ndarray:
    """Numpy reference of the vote's decisions (module docstring, steps 3 and, with slot_p, 4): [B, S]
    bool, the slots each Gaussian trims. slot_c: [B, S] int32 clusters (-1 empty; slots fill in order, as the fold
    fills them: the kernel reads a row whose second slot is empty as one cluster), slot_v / slot_p:
    [B, S] float64 votes / specificities, means: [K, D] unit μ_c."""
    b, num_slots = slot_c.shape
    out = np.zeros((b, num_slots), np.bool_)
    mixed = np.flatnonzero((slot_c[:, 1:] >= 0).any(axis=1)) if num_slots > 1 else np.zeros(0, np.int64)
    if mixed.size == 0 or means.shape[0] == 0 or b == 0:
        return out
    c, v = slot_c[mixed], slot_v[mixed]
    ok = c >= 0
    cw = np.maximum(c, 0)
    mc = means[cw].astype(np.float32)
    sim = np.zeros(c.shape + (num_slots,), np.float32)
    for d in range(means.shape[1]):  # float32, in index order of d: the kernel's dot products (`_row_dot`)
        sim += mc[:, :, None, d] * mc[:, None, :, d]
    like = (sim >= threshold) & ok[:, :, None] & ok[:, None, :]
    group = np.where(ok, v, 0.0)
    for t in range(num_slots):  # G_s = V_s, then + V_t of each other like slot t in slot order: the kernel's order
        group = group + np.where(like[:, :, t] & (np.arange(num_slots) != t)[None, :], v[:, t : t + 1], 0.0)
    group = np.where(ok, group, -np.inf)
    group_or_floor = np.where(np.isnan(group), -np.inf, group)  # a NaN vote never wins, as in the kernel
    top = (group_or_floor == group_or_floor.max(axis=1, keepdims=True)) & ~np.isnan(group)
    best = np.argmin(np.where(top & ok, c.astype(np.int64), np.iinfo(np.int64).max), axis=1)  # of equal maxima, the lowest cluster id
    rows = np.arange(mixed.size)
    won = (top & ok).any(axis=1)  # a row whose every group is NaN has no winner and trims nothing, as in the kernel (round 75a F3)
    drop = ok & won[:, None] & (sim[rows, :, best] < threshold) & (np.arange(num_slots)[None, :] != best[:, None]) & (group < minority * group[rows, best][:, None])
    if slot_p is not None:
        for b_row in np.flatnonzero(won):
            drop[b_row] |= _less_specific_reference(ok[b_row], drop[b_row], sim[b_row], int(best[b_row]), slot_p[mixed[b_row]], threshold, specific)
    out[mixed] = drop
    return out


def exact_trimmed_features_reference(F: np.ndarray, slot_c: np.ndarray, slot_v: np.ndarray, means: np.ndarray,
                                     views: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
                                     threshold: float = CLUSTER_COSINE, minority: float = MINORITY, slot_p: np.ndarray | None = None,
                                     specific: float = SPECIFIC) -> np.ndarray:
    """Plain-Python reference of `exact_trimmed_features`: in place on the paper's sums F [B, D]
    float32, every pair whose cluster sits in a slot its row trims (`trimmed_slots_reference`)
    subtracted, one after another in view and pair order, in float32 as the sums add them
    (drsplat.registration.sums). views: per view (rows [P] of F, clusters [P] (-1 none), masks [P]
    rows of feats, weights [P] float32, feats [M, D] float32). Returns F."""
    drop = trimmed_slots_reference(slot_c, slot_v, means, threshold, minority, slot_p, specific)
    for rows, clusters, masks, weights, feats in views:
        for r, c, m, w in zip(rows.tolist(), clusters.tolist(), masks.tolist(), np.asarray(weights, np.float32)):
            if c >= 0 and bool((drop[r] & (slot_c[r] == c)).any()):
                F[r] -= w * np.asarray(feats[m], np.float32)
    return F


def _less_specific_reference(ok: np.ndarray, trimmed: np.ndarray, sim: np.ndarray, best: int, spec: np.ndarray, threshold: float,
                             specific: float) -> np.ndarray:
    """Step 4 for one Gaussian (module docstring), plain Python: [S] bool, the slots it trims beyond
    step 3's `trimmed`. ok: [S] occupied slots; sim: [S, S] the clusters' cosines; best: the vote's
    winner; spec: [S] P_ic of each slot."""
    num_slots = ok.shape[0]
    alive = [s for s in range(num_slots) if ok[s] and not trimmed[s]]
    out = np.zeros(num_slots, bool)
    if not any(s != best and sim[s, best] < threshold for s in alive):
        return out
    group = list(spec)
    for s in range(num_slots):  # + each other like slot's in slot order, as G
        for t in range(num_slots):
            if t != s and ok[t] and sim[s, t] >= threshold:
                group[s] += spec[t]
    top = alive[0]
    for s in alive:
        if group[s] > group[top]:
            top = s
    for s in alive:
        out[s] = s != top and sim[s, top] < threshold and group[s] * specific < group[top]
    return out


@numba.njit(cache=True, inline="always")
def _less_specific(slot_c, slot_p, i, sim, best, trim, threshold, specific, spec):  # pragma: no cover - jitted
    """Step 4 of row i (`_less_specific_reference`): the bits of the alive slots (occupied, not in
    `trim`) unlike the most specific alive group and `specific` times less specific than it, when
    some alive slot is unlike the winner `best`; spec: [S] float64 scratch."""
    num_slots = slot_c.shape[1]
    unlike = False
    for s in range(num_slots):
        if slot_c[i, s] >= 0 and not (trim >> np.uint64(s)) & np.uint64(1) and s != best and sim[s, best] < threshold:
            unlike = True
    if not unlike:
        return np.uint64(0)
    top = -1
    for s in range(num_slots):
        if slot_c[i, s] < 0:
            continue
        spec[s] = slot_p[i, s]
        for t in range(num_slots):
            if t != s and slot_c[i, t] >= 0 and sim[s, t] >= threshold:
                spec[s] += slot_p[i, t]
        if not (trim >> np.uint64(s)) & np.uint64(1) and (top < 0 or spec[s] > spec[top]):
            top = s
    out = np.uint64(0)
    for s in range(num_slots):
        if slot_c[i, s] >= 0 and not (trim >> np.uint64(s)) & np.uint64(1) and s != top and sim[s, top] < threshold \
                and spec[s] * specific < spec[top]:
            out |= np.uint64(1) << np.uint64(s)
    return out


@numba.njit(parallel=True, cache=True)
def _trim_kernel(F, slot_c, slot_v, slot_s, means, threshold, minority, parts, slot_p, specific, cosines, bits):  # pragma: no cover - jitted
    """`trimmed_features_reference` over `parts` runs of rows in parallel (rows are independent), each
    run with one float64 row buffer and an [S, S] cosine table: per Gaussian, the cosines between its
    slots' clusters and the group votes G_s (V_s, then + V_t of every like slot t in slot order),
    the slots to trim (bits of a uint64; slots ≤ 64), with slot_p [B, S] (not [0, S]) also those of
    step 4 (the specificities' groups, as G's, then the most specific alive slot), then, when there
    are any, F_i ← float32(float64(F_i) − Σ_s S_s μ_{c_s}), the slots subtracted in slot order,
    each over the row in one contiguous (vectorised) loop. cosines: [K, K] float32 all NaN, a table
    shared by the parts that keeps each pair of clusters' cosine once computed (the same call, so the
    same bits; two parts may write one entry, with the same value), or [0, 0] for none. bits: [B]
    uint64, where each row's trimmed slots are written instead of subtracted (F is then not read:
    the exact trim, `exact_trimmed_features`), or [0] to subtract them."""
    b, num_slots = slot_c.shape
    dim = F.shape[1]
    with_p = slot_p.shape[0] == b
    tabled = cosines.shape[0] == means.shape[0]
    decide_only = bits.shape[0] == b
    for part in numba.prange(parts):
        row = np.empty(dim)
        sim = np.empty((num_slots, num_slots), np.float32)
        group = np.empty(num_slots)
        spec = np.empty(num_slots)
        for i in range(part * b // parts, (part + 1) * b // parts):
            if num_slots < 2 or slot_c[i, 1] < 0:  # slots fill in order: one cluster at most
                continue
            for s in range(num_slots):
                group[s] = slot_v[i, s]
            for s in range(num_slots):
                if slot_c[i, s] < 0:
                    continue
                for t in range(s + 1, num_slots):
                    if slot_c[i, t] < 0:
                        continue
                    cs, ct = slot_c[i, s], slot_c[i, t]
                    d = cosines[cs, ct] if tabled else np.float32(np.nan)
                    if d != d:  # not in the table (or no table): the products commute, so (cs, ct) and (ct, cs) are one value
                        d = _row_dot(means, cs, means, ct)
                        if tabled:
                            cosines[cs, ct] = d
                            cosines[ct, cs] = d
                    sim[s, t] = d
                    sim[t, s] = d
            for s in range(num_slots):  # each other like slot's votes in slot order (the reference's order)
                if slot_c[i, s] < 0:
                    continue
                for t in range(num_slots):
                    if t != s and slot_c[i, t] >= 0 and sim[s, t] >= threshold:
                        group[s] += slot_v[i, t]
            best = -1
            for s in range(num_slots):  # a NaN vote never wins (the fold makes none; the reference holds the same rule)
                if slot_c[i, s] < 0 or np.isnan(group[s]):
                    continue
                # equal groups: the lowest cluster id, not the first slot (the slots' order is the order the Gaussian
                # met its clusters, which follows the views' order: round 74a F1)
                if best < 0 or group[s] > group[best] or (group[s] == group[best] and slot_c[i, s] < slot_c[i, best]):
                    best = s
            if best < 0:
                continue
            g_win = group[best]
            trim = np.uint64(0)
            for s in range(num_slots):
                if slot_c[i, s] < 0 or s == best or not group[s] < minority * g_win:
                    continue
                if sim[s, best] < threshold:
                    trim |= np.uint64(1) << np.uint64(s)
            if with_p:
                trim |= _less_specific(slot_c, slot_p, i, sim, best, trim, threshold, specific, spec)
            if decide_only:
                bits[i] = trim
                continue
            if trim == 0:
                continue
            for d in range(dim):
                row[d] = F[i, d]
            for s in range(num_slots):
                if (trim >> np.uint64(s)) & np.uint64(1):
                    c = slot_c[i, s]
                    w = slot_s[i, s]
                    for d in range(dim):
                        row[d] -= w * np.float64(means[c, d])
            for d in range(dim):
                F[i, d] = row[d]


def trimmed_features(F: np.ndarray, slot_c: np.ndarray, slot_v: np.ndarray, slot_s: np.ndarray, means: np.ndarray,
                     threshold: float = CLUSTER_COSINE, minority: float = MINORITY, slot_p: np.ndarray | None = None,
                     specific: float = SPECIFIC) -> np.ndarray:
    """In place on the paper's sums F [B, D] float32: F_i -= Σ_{c trimmed} S_ic μ_c (module
    docstring, steps 3 and, with slot_p, 4; numba, one Gaussian per thread); rows with one voted
    cluster are left bit for bit as they are. slot_c: [B, S] int32 clusters (-1 empty), slot_v /
    slot_s / slot_p: [B, S] float64 votes / paper weights / specificities (`slot_specificity`;
    None: step 3 only), means: [K, D] unit μ_c float32. Returns F."""
    if F.shape[0] == 0 or means.shape[0] == 0:
        return F
    _run_trim_kernel(F, slot_c, slot_v, slot_s, means, threshold, minority, slot_p, specific, np.zeros(0, np.uint64))
    return F


def _run_trim_kernel(F, slot_c, slot_v, slot_s, means, threshold, minority, slot_p, specific, bits) -> None:
    if slot_c.shape[1] > 64:
        raise ValueError(f"the vote's trim takes at most 64 slots per Gaussian, not {slot_c.shape[1]}")
    parts = max(1, min(slot_c.shape[0], 8 * numba.get_num_threads()))
    slot_p = np.zeros((0, slot_c.shape[1])) if slot_p is None else np.ascontiguousarray(slot_p, np.float64)
    k = means.shape[0]
    # the Gaussians' slots meet the same pairs of clusters again and again (flowers: 1,083 clusters, 0.28 s of
    # 512-float dot products a registration, 0.12 s with the table); a table of them when it is small enough
    cosines = np.full((k, k) if k * k * 4 <= TRIM_COSINE_TABLE_BYTES else (0, 0), np.nan, np.float32)
    _trim_kernel(F, slot_c, slot_v, slot_s, np.ascontiguousarray(means, np.float32), np.float32(threshold), float(minority), parts,
                 slot_p, float(specific), cosines, bits)


def trimmed_slots(slot_c: np.ndarray, slot_v: np.ndarray, slot_s: np.ndarray, means: np.ndarray, threshold: float = CLUSTER_COSINE,
                  minority: float = MINORITY, slot_p: np.ndarray | None = None, specific: float = SPECIFIC) -> np.ndarray:
    """[B] uint64, bit s set where Gaussian b trims slot s (module docstring, steps 3 and, with slot_p,
    4; `_trim_kernel` deciding only; reference `trimmed_slots_reference`). Arguments as
    `trimmed_features`."""
    bits = np.zeros(slot_c.shape[0], np.uint64)
    if slot_c.shape[0] and means.shape[0]:
        _run_trim_kernel(np.zeros((slot_c.shape[0], 0), np.float32), slot_c, slot_v, slot_s, means, threshold, minority, slot_p, specific, bits)
    return bits


@numba.njit(cache=True, parallel=True)
def _trimmed_pairs_kernel(rows, clusters, slot_c, bits, out):  # pragma: no cover - jitted
    """out[p] = whether pair p's cluster sits in a slot its row trims (bits [B] uint64); rows,
    clusters [P] int32 (-1: no cluster, never trimmed)."""
    num_slots = slot_c.shape[1]
    for p in numba.prange(rows.shape[0]):
        r, c = rows[p], clusters[p]
        trim = bits[r]
        hit = False
        if trim != 0 and c >= 0:
            for s in range(num_slots):
                if slot_c[r, s] == c:
                    hit = (trim >> np.uint64(s)) & np.uint64(1) != 0
                    break
        out[p] = hit


def trim_buffer_bytes(dim: int, total_masks: int = 0, max_masks: int = 0) -> int:
    """The most the exact trim's buffer holds (`sums.buffer_bytes` of its TRIM_BUFFER_PAIRS pairs and
    TRIM_BUFFER_FEAT_BYTES of rows) for views of `max_masks` `dim`-D masks at most, `total_masks` in all.
    When they are not known (0): its pairs and twice TRIM_BUFFER_FEAT_BYTES of rows (64 MB), what it
    was counted as before the masks were; a small capture's masks fill far less than that, a view of
    thousands of 1024-D masks more."""
    if total_masks <= 0 or max_masks <= 0:
        return TRIM_BUFFER_PAIRS * PAIR_SLOT_BYTES + 2 * TRIM_BUFFER_FEAT_BYTES
    return buffer_bytes(dim, total_masks, max_masks, rows=buffered_rows(dim, TRIM_BUFFER_FEAT_BYTES), pairs=TRIM_BUFFER_PAIRS)


def exact_trimmed_features(F: np.ndarray, slot_c: np.ndarray, slot_v: np.ndarray, slot_s: np.ndarray, means: np.ndarray,
                           views: Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]], threshold: float = CLUSTER_COSINE,
                           minority: float = MINORITY, slot_p: np.ndarray | None = None, specific: float = SPECIFIC,
                           removed: np.ndarray | None = None) -> np.ndarray:
    """In place on the paper's sums F [B, D] float32: every Gaussian that trims a cluster (steps 3 and,
    with slot_p, 4, decided as `trimmed_features` decides) loses that cluster's own pairs,

        F_i = Σ_j w_ij f_j − Σ_{j : cluster(j) trimmed by i} w_ij f_j,

    by one replay of the pairs F was made of (module docstring, step 3: what `trimmed_features`
    approximates by S_ic μ_c), each trimmed pair subtracted in float32 as the sums added it, in
    the same order (so the same bits in every plan and place; the kept sum to float32 rounding of
    the whole). Only the trimmed pairs cost D operations, and rows that trim nothing keep their
    bits. An evicted cluster's pairs, which no slot names, stay. views: the replay, per view (rows
    [P] of F, clusters [P] int32 (-1 none), masks [P] rows of feats, weights [P] float32, feats
    [M, D] float32), read only when some row trims. removed: [B] float32 zeros, or None: gets −Σ w_ij
    of each row's trimmed pairs, added in the same order (so W + removed is the weight F still
    holds). Reference: `exact_trimmed_features_reference`. Returns F."""
    bits = trimmed_slots(slot_c, slot_v, slot_s, means, threshold, minority, slot_p, specific)
    if not bits.any():
        return F
    # the trimmed pairs of several views buffered, then subtracted by the sums' own flush with the weights
    # negated (f + (−w)·x is f − w·x to the bit): each row of F is read and written once per flush, not once
    # per view, and a row's pairs go in their order, so the bits do not depend on where flushes fall
    removed = np.zeros(F.shape[0], np.float32) if removed is None else removed
    out = Accumulator(F.shape[0], F.shape[1], TRIM_BUFFER_PAIRS, buffered_rows(F.shape[1], TRIM_BUFFER_FEAT_BYTES), sums=(F, removed))
    for rows, clusters, masks, weights, feats in views:
        if rows.size:
            rows = np.ascontiguousarray(rows, np.int32)
            hit = np.empty(rows.shape[0], np.bool_)
            _trimmed_pairs_kernel(rows, np.ascontiguousarray(clusters, np.int32), slot_c, bits, hit)
            at = np.flatnonzero(hit)
            if at.size:
                out.add_pairs(rows[at], np.asarray(masks, np.int32)[at], -np.asarray(weights, np.float32)[at], feats)
    out.flush()
    return F


def slot_specificity_reference(views: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], slot_c: np.ndarray) -> np.ndarray:
    """Plain-Python reference of `slot_specificity`: [B, S] float64 P of each slot's cluster,
    P_ic = Σ_views Σ_{pairs (i, j), cluster(j) = c} min(1, w_ij / w̄_j) (module docstring, step 4), the
    pairs added one after another in view and pair order. views: per view (rows [P] of slot_c,
    clusters [P] (-1 none), weights [P] float32, means [P] float64: w̄_j of each pair's mask)."""
    slot_p = np.zeros(slot_c.shape)
    for rows, clusters, weights, means in views:
        for r, c, w, m in zip(rows.tolist(), clusters.tolist(), np.asarray(weights, np.float64).tolist(), means.tolist()):
            if c < 0 or not w > 0.0 or not m > 0.0:
                continue
            for s in range(slot_c.shape[1]):
                if slot_c[r, s] == c:
                    slot_p[r, s] += min(1.0, w / m)
                    break
    return slot_p


@numba.njit(cache=True, parallel=True)
def _specificity_kernel(rows, clusters, weights, means, order, slot_c, slot_p):  # pragma: no cover - jitted
    """Add one view's pairs to slot_p (`slot_specificity_reference`): rows, clusters [P] int32, weights
    [P] float32, means [P] float64 (w̄_j of each pair's mask), order: the pairs grouped by row
    (`stable_order`), cut into VOTE_PARTS row-aligned parts added in parallel, each row's pairs in order."""
    cuts = _row_aligned_cuts(rows, order, VOTE_PARTS)
    for part in numba.prange(VOTE_PARTS):
        for i in range(cuts[part], cuts[part + 1]):
            p = order[i]
            r, c, w, m = rows[p], clusters[p], np.float64(weights[p]), means[p]
            if c < 0 or not w > 0.0 or not m > 0.0:
                continue
            for s in range(slot_c.shape[1]):
                if slot_c[r, s] == c:
                    slot_p[r, s] += min(1.0, w / m)
                    break


def slot_specificity(views: Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], slot_c: np.ndarray) -> np.ndarray:
    """[B, S] float64 P_ic of each slot's cluster (module docstring, step 4) from one replay of the
    views' pairs, each view (rows [P] of slot_c, clusters [P] int32 (-1 none), weights [P] float32,
    means [P] float64: the mean pair weight w̄_j of each pair's mask over its whole view); numba."""
    slot_p = np.zeros(slot_c.shape)
    for rows, clusters, weights, means in views:
        if rows.size:
            rows = np.ascontiguousarray(rows, np.int32)
            _specificity_kernel(rows, np.ascontiguousarray(clusters, np.int32), np.ascontiguousarray(weights, np.float32),
                                np.ascontiguousarray(means, np.float64), stable_order(rows), slot_c, slot_p)
    return slot_p


def vote_reference(views: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], num_gaussians: int, means: np.ndarray,
                   presence: float = PRESENCE, threshold: float = CLUSTER_COSINE, minority: float = MINORITY,
                   full_view: float = FULL_VIEW) -> np.ndarray:
    """Obviously-correct reference of the vote stage with unbounded slots (numpy, float64).

    views: per view (gaussians [P], clusters [P], weights [P], embeddings [P, D] of the pairs'
    masks). Returns F [N, D] float64 before normalisation: the paper's Σ w_ij f_j less the pairs
    of the clusters outside each Gaussian's winning group, each counted as S_ic μ_c (agrees with the
    kernel whenever no Gaussian meets more than VOTE_SLOTS clusters).
    """
    k = means.shape[0]
    V = np.zeros((num_gaussians, k))
    S = np.zeros((num_gaussians, k))
    F = np.zeros((num_gaussians, means.shape[1]))
    for g, c, w, f in views:
        w = w.astype(np.float64)
        np.add.at(F, g, w[:, None] * f)
        total = np.bincount(g, w, num_gaussians)
        ok = (c >= 0) & (w > 0)
        t = total[g[ok]]
        v = np.minimum(1.0, w[ok] / (t * presence)) * np.minimum(1.0, t / full_view) if presence else w[ok]
        np.add.at(V, (g[ok], c[ok]), v)
        np.add.at(S, (g[ok], c[ok]), w[ok])
    for i in np.flatnonzero((V > 0).sum(axis=1) > 1):
        voted = np.flatnonzero(V[i] > 0)
        like = means[voted] @ means[voted].T >= threshold
        group = like.astype(np.float64) @ V[i, voted]  # G_c: the votes of every voted cluster like c, itself included
        win = int(np.argmax(group))
        drop = (means[voted] @ means[voted[win]] < threshold) & (group < minority * group[win])
        drop[win] = False
        F[i] -= S[i, voted[drop]] @ means[voted[drop]]
    return F


def trim_sums(F: np.ndarray, slot_c: np.ndarray, slot_v: np.ndarray, slot_s: np.ndarray, clusters: MaskClusters, trim: float,
              specific: Specificity | None, exact: PairSource | None, lo: int, hi: int, row: np.ndarray | None = None,
              ) -> tuple[np.ndarray, np.ndarray | None]:
    """The vote's trim of the sums F [B, D] of Gaussians lo .. hi-1 (or of `row` [N], a sample), in
    place, as a VoteSink or its device form has them: nothing at θ = NO_TRIM; step 4 when `specific`
    (its replay); exact (`exact_trimmed_features`, a replay of `exact`) or at the clusters' means
    (`trimmed_features`). slot_*: [B, S] the slots; clusters: the views' mask clusters. Returns (F,
    removed: [B] float32 −Σ w of each row's trimmed pairs for an exact trim, else None)."""
    if trim == NO_TRIM:
        return F, None
    slot_p = None if specific is None else slot_specificity(specific.views(clusters.per_view, lo, hi, row), slot_c)
    if exact is None:
        return trimmed_features(F, slot_c, slot_v, slot_s, clusters.means(), trim, slot_p=slot_p), None
    removed = np.zeros(F.shape[0], np.float32)
    exact_trimmed_features(F, slot_c, slot_v, slot_s, clusters.means(), untrimmed_replay(exact, clusters.per_view, lo, hi, row), trim,
                           slot_p=slot_p, removed=removed)
    return F, removed


def kept_weights(W: np.ndarray, removed: np.ndarray | None) -> np.ndarray | None:
    """[B] float32 W + removed, the weight of the pairs an exactly trimmed F still holds (Block.kept),
    or None when nothing was removed exactly."""
    return None if removed is None else W + removed


NO_TRIM = -2.0  # a θ below any cosine, so every cluster is like every other: step 3 trims nothing, nor does step 4 (no cluster is unlike the winner)


def trim_cosine(like: float | None) -> float:
    """θ of step 3 (module docstring): CLUSTER_COSINE, or the cross-view check's like cosine when
    there is one and it is lower (a cluster that is like the winner is never trimmed)."""
    return CLUSTER_COSINE if like is None else float(min(CLUSTER_COSINE, like))


@dataclass
class Specificity:
    """What step 4 of the vote replays (module docstring): `source`, the views' pairs the sums were
    made of, read block by block (the check's KeptPairs), and pair_means, per view [M] float64 each
    mask's mean pair weight w̄_j over the whole view (the check's supports: the same numbers in every
    place and plan; 0 where a mask has no pair)."""

    source: PairSource
    pair_means: list[np.ndarray]

    def views(self, per_view: list[np.ndarray], lo: int, hi: int, row: np.ndarray | None = None,
              ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """Every view's pairs of Gaussians lo .. hi-1 for `slot_specificity`: (rows, clusters,
        weights, w̄ of each pair's mask), rows = gaussians - lo, or row[gaussians] keeping those ≥ 0
        when row [N] int32 is given. per_view: each view's [M] mask clusters."""
        for index, rows, m, w, _ in block_pairs(self.source, lo, hi, row):
            yield rows, per_view[index][m], w, self.pair_means[index][m]


def block_pairs(source: PairSource, lo: int, hi: int, row: np.ndarray | None = None,
                ) -> Iterator[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Every view's pairs of Gaussians lo .. hi-1 in `source`, in order: (view index, rows, masks,
    weights, feats), rows = gaussians - lo, or row[gaussians] keeping those ≥ 0 when row [N] int32
    is given (a sample's rows)."""
    for index, view in enumerate(source.block_views(lo, hi)):
        g, m, w = view.gaussians, view.masks, view.weights
        if row is None:
            rows = g - np.int32(lo)
        else:
            keep = row[g] >= 0
            rows, m, w = row[g[keep]], m[keep], w[keep]
        yield index, rows, m, w, view.feats


def untrimmed_replay(source: PairSource, per_view: list[np.ndarray], lo: int, hi: int, row: np.ndarray | None = None,
                     ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """The replay `exact_trimmed_features` reads: every view's pairs of Gaussians lo .. hi-1 (or of
    `row`, as `block_pairs`) as (rows, clusters, masks, weights, feats); per_view: each view's [M]
    mask clusters."""
    for index, rows, m, w, feats in block_pairs(source, lo, hi, row):
        yield rows, per_view[index][m], m, w, feats


class VoteSink:
    """A sink (drsplat.registration.sink) whose blocks hold the paper's sums trimmed by the vote.

    Without a log, the paper's sums (an Accumulator) and the vote slots of all N Gaussians are kept
    while the views arrive; with one (a plan of several blocks), each block replays the log keeping
    its Gaussians' pairs into both. Either way `add` assigns the view's masks to clusters (every
    view, replayed ones included, in order), and a Gaussian's pairs reach its row in the same order.
    With `specific` (a Specificity) step 4 trims too: a second replay of the block's pairs gives its
    slots' specificities once the slots are final. With `exact` (the pairs the sums are made of: a
    cross-view check's kept pairs) the trimmed clusters' own pairs are subtracted
    (`exact_trimmed_features`), else the trim is counted at the clusters' means (`trimmed_features`).
    """

    place = "host"

    def __init__(self, num_gaussians: int, dim: int, plog: PairSource | None = None, block: int | None = None,
                 slots: int = VOTE_SLOTS, presence: float = PRESENCE, full_view: float = FULL_VIEW, clusters: MaskClusters | None = None,
                 trim: float = CLUSTER_COSINE, specific: Specificity | None = None, exact: PairSource | None = None):
        """clusters: the views' clusters made already (a reducer replaying a block of a finished view
        pass gets the driver's); None: made by `add`. trim: θ of step 3 (`trim_cosine`; a check
        sets it once it has judged the masks, before the sums are finished); specific: step 4's
        replay (None: no step 4; a check sets it with `trim`); exact: the pairs the sums are made
        of, replayed for exact trims (None: trims at the clusters' means; a check sets it with `trim`)."""
        self.trim = float(trim)
        self.specific = specific
        self.exact = exact
        self.num_gaussians, self.dim, self.slots, self.presence, self.full_view = num_gaussians, dim, int(slots), float(presence), float(full_view)
        self.clusters = MaskClusters(dim) if clusters is None else clusters
        self._log = plog
        self.block = num_gaussians if plog is None else int(block)
        if self.block < 1:
            raise ValueError("block must be >= 1")
        self._state = None if plog is not None else self._empty(num_gaussians)
        self._trimmed_sums: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None  # in one block: (F, W, kept) once trimmed, in place

    def _empty(self, rows: int, spare: tuple | None = None):
        """A block's state for `rows` Gaussians: its Accumulator and the vote's slots (candidates, votes,
        specificities) and totals; in an earlier block's state `spare` when given (`Accumulator.reused`)."""
        if spare is not None and spare[1].shape[0] >= rows:
            acc, slot_c, slot_v, slot_s, total = spare
            slot_c, slot_v, slot_s, total = slot_c[:rows], slot_v[:rows], slot_s[:rows], total[:rows]
            slot_c.fill(-1)
            for table in (slot_v, slot_s, total):
                table.fill(0.0)
            return acc.reused(rows), slot_c, slot_v, slot_s, total
        # made once a block, touched a few rows a view: small pages (drsplat.memory.small_page_full)
        return (Accumulator(rows, self.dim), small_page_full((rows, self.slots), -1, np.int32), small_page_zeros((rows, self.slots), np.float64),
                small_page_zeros((rows, self.slots), np.float64), small_page_zeros(rows, np.float64))

    @property
    def num_blocks(self) -> int:
        return max(1, -(-self.num_gaussians // self.block))

    def add(self, view: ViewPairs) -> None:
        ids = self.clusters.add(view.feats, view.present_masks())
        if self._state is not None:
            self._fold(self._state, view.gaussians, view.masks, ids, view.weights, view.feats)

    def _fold(self, state, rows: np.ndarray, masks: np.ndarray, cluster_of_mask: np.ndarray, weights: np.ndarray, feats: np.ndarray) -> None:
        acc, slot_c, slot_v, slot_s, total = state
        rows = np.ascontiguousarray(rows, np.int32)
        acc.add_pairs(rows, masks, weights, feats)
        if self.trims:
            fold_view_votes(rows, cluster_of_mask[masks], weights, self.presence, self.full_view, slot_c, slot_v, slot_s, total)

    @property
    def trims(self) -> bool:
        """Whether the vote can trim anything: not at θ = NO_TRIM (a check whose masks did not group),
        where neither step 3 nor step 4 trims a slot, so the slots are not folded and the sums are
        the paper's as they are."""
        return self.trim != NO_TRIM

    def _finish(self, state, lo: int, hi: int, row: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The trimmed sums of the state's rows, (F, W, kept: Block.kept): Gaussians lo .. hi-1, or those `row` [N] maps to rows."""
        acc, slot_c, slot_v, slot_s, _ = state
        F, W = acc.sums()
        F, removed = self._trimmed(F, slot_c, slot_v, slot_s, lo, hi, row)
        return F, W, kept_weights(W, removed)

    def _trimmed(self, F: np.ndarray, slot_c: np.ndarray, slot_v: np.ndarray, slot_s: np.ndarray, lo: int, hi: int,
                 row: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        return trim_sums(F, slot_c, slot_v, slot_s, self.clusters, self.trim, self.specific, self.exact, lo, hi, row)

    def blocks(self, reuse: bool = False) -> Iterator[Block]:
        if self._state is not None:
            if self._trimmed_sums is None:  # F is trimmed in place: once, whoever asks again gets the same sums
                self._trimmed_sums = self._finish(self._state, 0, self.num_gaussians)
                self.specific = self.exact = None  # their replays are done: the pairs they hold (a check's record) can go
            yield Block(0, self.num_gaussians, *self._trimmed_sums)
            return
        spare = None
        for lo in range(0, self.num_gaussians, self.block):
            hi = min(self.num_gaussians, lo + self.block)
            if not reuse:  # as LogSink.blocks: nothing here holds a block across the yield
                yield self.block_sums(lo, hi)
                continue
            state = self._block_state(lo, hi, spare)
            spare = state
            yield Block(lo, hi, *self._finish(state, lo, hi))

    def block_sums(self, lo: int, hi: int) -> Block:
        """The trimmed sums of Gaussians lo .. hi-1 from one replay of the log (needs the log; a
        reducer's block, drsplat.registration.reduce)."""
        state = self._block_state(lo, hi)
        return Block(lo, hi, *self._finish(state, lo, hi))

    def _block_state(self, lo: int, hi: int, spare: tuple | None = None):
        """The state of Gaussians lo .. hi-1 with every logged view folded in (in `spare`'s arrays, `_empty`)."""
        state = self._empty(hi - lo, spare)
        for index, view in enumerate(self._log.block_views(lo, hi)):  # only the chunks of [lo, hi) are read
            if view.gaussians.size:
                self._fold(state, view.gaussians - np.int32(lo), view.masks, self.clusters.per_view[index], view.weights, view.feats)
        return state

    def sample(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F [S, D], W [S]) of the Gaussians `ids` [S] (sorted, distinct)."""
        row, lo, hi = sample_rows(ids, self.num_gaussians)
        if self._trimmed_sums is not None:
            F, W, _ = self._trimmed_sums
            return F[ids], W[ids].copy()
        if self._state is not None:
            acc, slot_c, slot_v, slot_s, _ = self._state
            F, W = acc.sums()
            return self._trimmed(F[ids], slot_c[ids], slot_v[ids], slot_s[ids], lo, hi, row)[0], W[ids].copy()
        state = self._empty(ids.shape[0])
        for index, view in enumerate(self._log.block_views(lo, hi) if ids.size else ()):
            keep = row[view.gaussians] >= 0
            if keep.any():
                self._fold(state, row[view.gaussians[keep]], view.masks[keep], self.clusters.per_view[index], view.weights[keep], view.feats)
        return self._finish(state, lo, hi, row)[:2]
