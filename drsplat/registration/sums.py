"""Running per-Gaussian sums of registration, and their normalisation.

With w_ij the summed weight of Gaussian i in mask j of one view (drsplat.registration.coalesce) and
f_j that mask's embedding, registration keeps

    F_i = Σ_views Σ_j w_ij f_j   [N, D] float32,     W_i = Σ_views Σ_j w_ij   [N] float32

and each Gaussian's feature is f_i = F_i / |F_i| = normalize(Σ_j w_ij f_j / W_i) (W_i > 0), its
weight W_i (0 = unassigned). Pairs are buffered and folded into F grouped by Gaussian (each F row
read and written once per flush, which keeps the N·D array's memory traffic low); a Gaussian's
pairs are added one by one in the order they arrive, so the sums do not depend on when flushes
happen, on block boundaries or on where the views were computed: the same views in the same
order give the same bits. Memory: N·D + the buffer, never Gaussians x masks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from drsplat.memory import small_page_zeros

ROW_BUFFER_BYTES = 64 << 20  # mask embeddings held between flushes: 32,768 rows at D = 512, 16,384 at D = 1024 (`buffered_rows`)
PAIR_CAPACITY = 1 << 23  # pairs buffered between flushes at most (`pair_capacity`; at least one per Gaussian summed)
PAIRS_PER_GAUSSIAN = 64  # below PAIR_CAPACITY, pairs buffered per Gaussian summed: a flush's O(N) sort is spread over 64·N pairs
MIN_PAIR_CAPACITY = 1 << 20
PAIR_SLOT_BYTES = 16  # a buffered pair: Gaussian, row and weight (12), and its place in the flush's counting sort (4)
FLUSH_BYTES = 16  # per Gaussian summed, the flush's counting sort: its starts and fill pointers (int64 each)
CANCEL_RATIO = 1e-4  # |Σ w f| ≤ this · Σ w: the sum cancelled (`normalize_rows`); float32 sums leave ~1e-7 of the weight, CLIP crops far more
WEAK_RESULTANT = 0.05  # |Σ w f| < this · Σ w: kept, but counted as a guess (`RowFates.weak`); CLIP's crops embed far closer than that
FLOAT32_TINY = np.float32(np.finfo(np.float32).tiny)  # the smallest normal float32: a norm under it holds too few bits to divide by


@dataclass(frozen=True)
class RowFates:
    """What `normalize_rows` did with the rows it did not simply normalise. dropped: rows left
    unassigned (non-finite or cancelled sums), of which nonfinite: those whose sum, weight or kept
    weight is not finite (a weight past float32's range, NaN features); weak: rows kept whose sum is under WEAK_RESULTANT of
    its weight, |Σ w f| < 0.05 Σ w: the masks' embeddings point so many ways (or opposite ways) that
    the direction is decided by a small remainder of them. With CLIP's embeddings, whose pairwise
    cosines are well above 0, no sum comes near that; 400 equally weighted random unit vectors do."""

    dropped: int = 0
    weak: int = 0
    nonfinite: int = 0

    def __add__(self, other: RowFates) -> RowFates:
        return RowFates(self.dropped + other.dropped, self.weak + other.weak, self.nonfinite + other.nonfinite)


@numba.njit(parallel=True, cache=True)
def _flush_pairs_kernel(pair_g, pair_row, pair_w, filled, rows, F, W):  # pragma: no cover - jitted
    """F[g] += Σ w·rows[row] and W[g] += Σ w over the buffered pairs, one Gaussian per thread
    at a time (pairs grouped by Gaussian with a counting sort), so each F row is read and
    written once per flush."""
    num_gaussians, dim = F.shape
    starts = np.zeros(num_gaussians + 1, np.int64)
    for i in range(filled):
        starts[pair_g[i] + 1] += 1
    for g in range(num_gaussians):
        starts[g + 1] += starts[g]
    order = np.empty(filled, np.int32)
    fill = starts[:num_gaussians].copy()
    for i in range(filled):
        g = pair_g[i]
        order[fill[g]] = i
        fill[g] += 1
    for g in numba.prange(num_gaussians):
        if starts[g] == starts[g + 1]:
            continue
        f = F[g]
        for o in range(starts[g], starts[g + 1]):
            i = order[o]
            w = pair_w[i]
            row = rows[pair_row[i]]
            W[g] += w  # pair by pair in view order: the sums do not depend on when flushes happen
            for d in range(dim):  # row views, not F[g, d]: this loop must vectorise
                f[d] += w * row[d]


def add_pairs_in_place(F: np.ndarray, W: np.ndarray, gaussians: np.ndarray, masks: np.ndarray, weights: np.ndarray, feats: np.ndarray) -> None:
    """F[g] += w·feats[m] and W[g] += w for every pair (g, m, w), a Gaussian's pairs in the order
    given (`_flush_pairs_kernel`, unbuffered): F [N, D] / W [N] float32, in place; gaussians,
    masks [P] (rows of F and of feats [M, D]), weights [P] float32."""
    if gaussians.shape[0] == 0:
        return
    _flush_pairs_kernel(np.ascontiguousarray(gaussians, np.int32), np.ascontiguousarray(masks, np.int32),
                        np.ascontiguousarray(weights, np.float32), int(gaussians.shape[0]), np.ascontiguousarray(feats, np.float32), F, W)


@numba.njit(parallel=True, cache=True)
def _zero_kernel(flat):  # pragma: no cover - jitted
    """flat[:] = 0 on numba's threads."""
    for i in numba.prange(flat.shape[0]):
        flat[i] = 0


def zero_in_parallel(array: np.ndarray) -> np.ndarray:
    """`array.fill(0)` (its reference) on numba's threads, in place; array: any contiguous array.

    For the first touch of a large fresh array in small pages: the page faults then run on every
    thread. Flowers' sums F (542k x 512 float32, 1.1 GB) took 0.36 s against 0.59 s for `fill` on
    2 cores (2026-11-27)."""
    if not array.flags.c_contiguous:
        raise ValueError("zero_in_parallel needs a C-contiguous array (a flat view of it)")
    if array.size:
        _zero_kernel(array.reshape(-1))
    return array


class Accumulator:
    """Running sums F [N, D] = Σ_j w_ij f_j and W [N] = Σ_j w_ij.

    Views' distinct (Gaussian, mask) pairs and the embeddings of their masks are buffered; a flush
    folds the buffer into F grouped by Gaussian, so memory is N·D + the buffer (`pair_capacity`, default `pair_capacity_for(N)`
    pairs, at least N, and `max_rows` embeddings plus one view's, default `buffered_rows(D)`; the most
    it holds: `buffer_bytes`), never Gaussians x masks. sums: (F [N, D],
    W [N]) float32 to add into in place instead of new zeros (the vote's exact trim subtracts its
    trimmed pairs from a block's sums, weights negated).
    """

    def __init__(self, num_gaussians: int, dim: int, pair_capacity: int | None = None, max_rows: int | None = None,
                 sums: tuple[np.ndarray, np.ndarray] | None = None):
        if sums is None:
            self.F = small_page_zeros((num_gaussians, dim), np.float32)  # made once: no huge pages (drsplat.memory)
            zero_in_parallel(self.F)  # touch every page now, not inside the first flush
            self.W = np.zeros(num_gaussians, np.float32)
        else:
            self.F, self.W = sums
        self._max_rows = buffered_rows(dim) if max_rows is None else int(max_rows)
        capacity = pair_capacity_for(num_gaussians) if pair_capacity is None else max(pair_capacity, num_gaussians, 1)
        self._pair_g = np.zeros(capacity, np.int32)
        self._pair_row = np.zeros(capacity, np.int32)
        self._pair_w = np.zeros(capacity, np.float32)
        self._filled = 0
        self._rows = np.zeros((256, dim), np.float32)
        self._num_rows = 0

    def reused(self, rows: int) -> Accumulator:
        """An empty Accumulator of `rows` ≤ N Gaussians in this one's first rows of F and W (zeroed:
        their pages are touched already) and its pair buffers; this one is not to be used after."""
        if rows > self.F.shape[0]:
            raise ValueError(f"an Accumulator of {self.F.shape[0]} rows cannot hold {rows}")
        F, W = self.F[:rows], self.W[:rows]
        zero_in_parallel(F)
        W.fill(0)
        other = object.__new__(Accumulator)
        other.__dict__.update(self.__dict__, F=F, W=W, _filled=0, _num_rows=0)
        return other

    @property
    def dim(self) -> int:
        return self.F.shape[1]

    def add_pairs(self, gaussians: np.ndarray, masks: np.ndarray, weights: np.ndarray, feats: np.ndarray) -> None:
        """Add one view's distinct pairs (as `Coalescer.coalesce` returns them) to the buffer.

        gaussians: [P] int32 ids (rows of F), masks: [P] int32 rows of feats [M, D], weights: [P]
        float32. Pairs are summed in the order given, so the same pairs in the same order give the
        same bits wherever they were computed.
        """
        num_masks = feats.shape[0]
        if self._num_rows > self._max_rows:  # bound the embedding buffer of sparse views too
            self.flush()
        offset = self._push_rows(np.asarray(feats, np.float32))
        start, total = 0, gaussians.shape[0]
        capacity = self._pair_g.shape[0]
        while start < total:
            if self._filled == capacity:
                self.flush(keep_last=num_masks)
                offset = 0
            take = min(capacity - self._filled, total - start)
            dst = slice(self._filled, self._filled + take)
            self._pair_g[dst] = gaussians[start : start + take]
            self._pair_row[dst] = masks[start : start + take] + offset
            self._pair_w[dst] = weights[start : start + take]
            self._filled += take
            start += take

    def _push_rows(self, feats: np.ndarray) -> int:
        """Store a view's embeddings after the buffered ones; returns their first row. The buffer
        doubles as it grows, but never past max_rows + the view's rows, what it can need (its rows
        are flushed once there are more than max_rows before a view is pushed)."""
        need = self._num_rows + feats.shape[0]
        if need > self._rows.shape[0]:
            grown = np.zeros((max(need, min(2 * self._rows.shape[0], self._max_rows + feats.shape[0])), self.dim), np.float32)
            grown[: self._num_rows] = self._rows[: self._num_rows]
            self._rows = grown
        self._rows[self._num_rows : need] = feats
        offset, self._num_rows = self._num_rows, need
        return offset

    def flush(self, keep_last: int = 0) -> None:
        """Fold the buffered pairs into F and W; keep the last `keep_last` embedding rows (the
        view being added) as rows 0..keep_last-1."""
        if self._filled:
            _flush_pairs_kernel(self._pair_g, self._pair_row, self._pair_w, self._filled, self._rows, self.F, self.W)
        self._filled = 0
        if keep_last:
            self._rows[:keep_last] = self._rows[self._num_rows - keep_last : self._num_rows].copy()
        self._num_rows = keep_last

    def sums(self) -> tuple[np.ndarray, np.ndarray]:
        """(F [N, D], W [N]) with every added view folded in."""
        self.flush()
        return self.F, self.W


def pair_capacity_for(num_gaussians: int) -> int:
    """The pairs an Accumulator of `num_gaussians` buffers by default: PAIRS_PER_GAUSSIAN per Gaussian
    within [MIN_PAIR_CAPACITY, PAIR_CAPACITY], and at least one per Gaussian. A flush costs O(N) for
    its counting sort besides its pairs, so a small scene flushes as cheaply with a small buffer;
    8 M pairs (128 MB) for a scene of 27,000 Gaussians were memory its views never filled."""
    return int(max(min(max(PAIRS_PER_GAUSSIAN * num_gaussians, MIN_PAIR_CAPACITY), PAIR_CAPACITY), num_gaussians, 1))


def buffered_rows(dim: int, row_bytes: int = ROW_BUFFER_BYTES) -> int:
    """The mask embeddings of `dim`-D an Accumulator holds between flushes within `row_bytes` (one at the least)."""
    return max(1, row_bytes // (4 * max(dim, 1)))


def buffer_bytes(dim: int, total_masks: int = 0, max_masks: int = 0, rows: int | None = None, pairs: int = PAIR_CAPACITY) -> int:
    """The most an Accumulator of `dim`-D rows holds in its buffers beyond F, W and the flush's
    per-Gaussian scratch (FLUSH_BYTES), for views of `max_masks` masks at most and `total_masks` in
    all (0: not known): `pairs` pairs of PAIR_SLOT_BYTES (its pair_capacity; a block of B > pairs
    Gaussians buffers B pairs: PAIR_SLOT_BYTES more per Gaussian), and the embedding rows. Those are
    at most R = min(rows + max_masks, total_masks) (rows: its max_rows, default buffered_rows(D)),
    and twice that while the buffer grows (the old rows and the new buffer both held): 2 · R · 4D.
    Unknown mask counts take a view of `rows` masks. Until 2026-12-05 the plan counted no rows: a `paper` registration of
    40 views of 2,000 1024-D masks, which grew the buffer to 128,000 rows (500 MiB), was accepted
    under 800 MB and peaked at 833 MiB."""
    cap = buffered_rows(dim) if rows is None else rows
    held = cap + (max_masks if max_masks > 0 else cap)
    if total_masks > 0:
        held = min(held, total_masks)
    return pairs * PAIR_SLOT_BYTES + 2 * held * 4 * max(dim, 1)


def accumulate_view_reference(F: np.ndarray, W: np.ndarray, ids: np.ndarray, weights: np.ndarray, mask_ids: np.ndarray, feats: np.ndarray) -> int:
    """Obviously-correct reference of coalescing one view and adding its pairs (scipy sparse, float64).

    A = sparse [N, M] with A_ij = Σ_p [mask(p) = j] Σ_s [id_s(p) = i] w_s(p); then F += A·feats
    and W += A·1. Returns the number of contributing pairs.
    """
    import scipy.sparse  # only the tests' reference needs scipy.sparse

    k = ids.shape[-1]
    g = ids.reshape(-1).astype(np.int64)
    m = np.repeat(mask_ids.reshape(-1).astype(np.int64), k)
    w = weights.reshape(-1).astype(np.float64)
    keep = (g >= 0) & (m >= 0)
    a = scipy.sparse.coo_matrix((w[keep], (g[keep], m[keep])), shape=(F.shape[0], feats.shape[0])).tocsr()
    F += (a @ feats.astype(np.float64)).astype(F.dtype)
    W += np.asarray(a.sum(axis=1)).reshape(-1).astype(W.dtype)
    return int(np.count_nonzero(keep))


@numba.njit(parallel=True, cache=True)
def _normalize_rows_kernel(F, W, R, cancel_ratio, weak_ratio):  # pragma: no cover - jitted
    """`normalize_rows` row by row in parallel, each norm judged against R (W, or the kept weight);
    returns the counts of rows dropped for non-finite or cancelled sums, of rows kept under
    weak_ratio of their weight, and of the dropped rows that were non-finite."""
    n, dim = F.shape
    bad = np.zeros(n, np.int64)  # 1: cancelled, 2: non-finite (one array: the block's scratch is counted per Gaussian)
    weak = np.zeros(n, np.int64)
    whole = dim - dim % 8
    for i in numba.prange(n):
        f = F[i]
        # eight running sums (lanes d mod 8), so the loop vectorises; one sum is a serial chain of adds
        s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
        for d in range(0, whole, 8):
            x0, x1, x2, x3 = np.float64(f[d]), np.float64(f[d + 1]), np.float64(f[d + 2]), np.float64(f[d + 3])
            x4, x5, x6, x7 = np.float64(f[d + 4]), np.float64(f[d + 5]), np.float64(f[d + 6]), np.float64(f[d + 7])
            s0 += x0 * x0
            s1 += x1 * x1
            s2 += x2 * x2
            s3 += x3 * x3
            s4 += x4 * x4
            s5 += x5 * x5
            s6 += x6 * x6
            s7 += x7 * x7
        total = ((s0 + s4) + (s1 + s5)) + ((s2 + s6) + (s3 + s7))
        for d in range(whole, dim):
            x = np.float64(f[d])
            total += x * x
        norm = np.sqrt(total)
        w = W[i]
        r = R[i]
        finite = np.isfinite(norm) and np.isfinite(w) and np.isfinite(r)
        if not finite and w != 0:
            bad[i] = 2
        if finite and w > 0 and not norm > cancel_ratio * r:
            bad[i] = 1
        if finite and w > 0 and norm > cancel_ratio * r:
            if norm < weak_ratio * r:
                weak[i] = 1
            scale = np.float32(norm)
            if np.isfinite(scale) and scale >= FLOAT32_TINY:
                for d in range(dim):
                    f[d] /= scale
            else:  # |F_i| past float32's range (zeroed by inf) or subnormal there (a few bits): divided in float64
                for d in range(dim):
                    f[d] = np.float32(np.float64(f[d]) / norm)
        else:
            for d in range(dim):
                f[d] = 0.0
            W[i] = 0.0
    dropped = nonfinite = 0
    for i in range(n):
        if bad[i]:
            dropped += 1
            if bad[i] == 2:
                nonfinite += 1
    return dropped, weak.sum(), nonfinite


def normalize_rows(F: np.ndarray, W: np.ndarray, kept: np.ndarray | None = None) -> tuple[np.ndarray, RowFates]:
    """In place: F_i <- F_i / |F_i| where W_i > 0, F_i is finite and |F_i| > CANCEL_RATIO·K_i; other
    rows -> 0 (and their W_i -> 0). F: [N, D] float32 sums Σ_j w_ij f_j of unit embeddings, W: [N]
    float32 their weights Σ_j w_ij, so |F_i| ≤ W_i; K = kept ([N] float32, the weight of the pairs F
    still holds after an exact vote trim: Block.kept) or W when None. A sum under CANCEL_RATIO of its
    weight has cancelled (its masks' embeddings point opposite ways): what is left is float32
    rounding, whose direction means nothing, so the Gaussian is left unassigned instead of given it.
    A sum the vote trimmed is judged against what it still holds: a wall Gaussian whose heavy
    close-up view was trimmed keeps its few far views' clean sum, which W (the close-up's weight
    included) would call cancelled.

    |F_i| is summed in float64 and rounded to float32 before the division, as in
    `normalize_rows_reference` (a norm beyond float32's range divides in float64: the float32 norm
    is inf, and dividing by it zeroed a row that kept its weight, round 22; so does a norm that is subnormal in float32,
    whose few bits gave rows of length 0.88-0.98, round 56a); one pass over F in parallel (the reference makes several
    passes and a float64 copy of each chunk). The float64 sums may round differently in the last
    bit, so a row can differ from the reference's by one float32 ulp where its norm lies on a
    float32 rounding boundary. Returns (F, RowFates: the rows with weight dropped for non-finite or
    cancelled sums, and the rows kept whose |F_i| < WEAK_RESULTANT·W_i).
    """
    if kept is not None and kept.shape != W.shape:  # the kernel reads kept[i] for every row, unchecked
        raise ValueError(f"normalize_rows: kept has shape {kept.shape}, W {W.shape}: one weight per row of F")
    if F.shape[0] == 0:
        return F, RowFates()
    if not (F.flags.c_contiguous and F.dtype == np.float32 and W.dtype == np.float32 and (kept is None or kept.dtype == np.float32)):
        return normalize_rows_reference(F, W, kept=kept)
    dropped, weak, nonfinite = _normalize_rows_kernel(F, W, W if kept is None else np.ascontiguousarray(kept), CANCEL_RATIO, WEAK_RESULTANT)
    return F, RowFates(int(dropped), int(weak), int(nonfinite))


def normalize_rows_reference(F: np.ndarray, W: np.ndarray, chunk: int = 65536, kept: np.ndarray | None = None) -> tuple[np.ndarray, RowFates]:
    """Reference of `normalize_rows` (numpy, chunk by chunk): in place F_i <- F_i / |F_i| where
    W_i > 0, F_i is finite and |F_i| > CANCEL_RATIO·K_i (K: kept, or W when None); other rows -> 0
    (and their W_i -> 0).

    Returns (F, RowFates).
    """
    bad_total = weak_total = nonfinite_total = 0
    for start in range(0, F.shape[0], chunk):
        f, w = F[start : start + chunk], W[start : start + chunk]
        k = (w if kept is None else kept[start : start + chunk]).astype(np.float64)
        norm = np.sqrt(np.einsum("nd,nd->n", f, f, dtype=np.float64))
        finite = np.isfinite(norm) & np.isfinite(w) & np.isfinite(k)
        cancelled = finite & (w > 0) & ~(norm > CANCEL_RATIO * k)
        nonfinite = int(np.count_nonzero(~finite & (w != 0)))
        nonfinite_total += nonfinite
        bad_total += nonfinite + int(np.count_nonzero(cancelled))
        ok = finite & (w > 0) & ~cancelled
        weak_total += int(np.count_nonzero(ok & (norm < WEAK_RESULTANT * k)))
        with np.errstate(over="ignore"):
            scale = norm.astype(np.float32)
        big = ok & ~(np.isfinite(scale) & (scale >= FLOAT32_TINY))  # |F_i| past float32's range or subnormal there: in float64
        f[big] = (f[big].astype(np.float64) / norm[big, None]).astype(np.float32)
        usual = ok & ~big
        f[usual] /= scale[usual, None]
        f[~ok] = 0.0
        w[~ok] = 0.0
    return F, RowFates(bad_total, weak_total, nonfinite_total)
