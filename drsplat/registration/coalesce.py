"""One view's top-k lists -> its distinct (Gaussian, mask) pairs with summed weights.

Pixel p lies in mask j of its view (-1: none), and its top-k slots hold Gaussians i with weights
w_i(p). The view contributes

    w_ij = Σ_{p ∈ mask j} w_i(p)

for every (i, j) with at least one such slot. Pixels are bucketed by mask (counting sort); per
mask the weights of its pixels' Gaussians are summed in a scratch array of N floats, so a view
costs O(pixels·k) after an O(N) allocation, and never forms anything Gaussians x masks. The masks
are cut into contiguous parts coalesced in parallel, each with its own scratch; the pairs come out
mask by mask, Gaussians in first-seen order, for any number of parts: that order fixes the summation
order downstream (drsplat.registration.sums), so every place that coalesces a view gets the same bits.
"""

from __future__ import annotations

import numba
import numpy as np

from drsplat._sort_kernels import stable_order
from drsplat.memory import small_page_full, small_page_zeros
from drsplat.scene import counted


@numba.njit(cache=True)
def _bucket_pixels(mask_ids, num_masks):  # pragma: no cover - jitted
    """Counting sort of the pixels by mask: (starts [M + 1], order [pixels in a mask]); mask m's
    pixels are order[starts[m] : starts[m + 1]], in pixel order. Pixels with mask -1 are left out, and so are ids
    ≥ num_masks, as `coalesce_reference` leaves them (they were counted past `starts`: round 66c F1)."""
    starts = np.zeros(num_masks + 1, np.int64)
    for p in range(mask_ids.shape[0]):
        m = mask_ids[p]
        if 0 <= m < num_masks:
            starts[m + 1] += 1
    for m in range(num_masks):
        starts[m + 1] += starts[m]
    order = np.empty(starts[num_masks], np.int64)
    fill = starts[:num_masks].copy()
    for p in range(mask_ids.shape[0]):
        m = mask_ids[p]
        if 0 <= m < num_masks:
            order[fill[m]] = p
            fill[m] += 1
    return starts, order


@numba.njit(cache=True, parallel=True)
def _coalesce_parts_kernel(ids, weights, order, starts, part_end, part_next, part_filled, part_pairs, part_bad, seen, acc, touched,
                           out_g, out_row, out_w):  # pragma: no cover - jitted
    """Coalesce the view's masks in parts, one part per thread.

    Part t owns masks part_next[t] .. part_end[t] - 1 (contiguous) and its own scratch seen[t],
    acc[t], touched[t] ([N] each; seen all -1 on entry and exit) and output row out_*[t]. Per mask
    the weights of its pixels' top-k Gaussians are summed in acc[t] in pixel and slot order, and
    the distinct Gaussians are appended in first-seen order: the same bits and order as a serial
    pass over the masks, whatever the number of parts. A part stops before a mask whose pairs
    might not fit its output row (part_next[t] then says where it resumes once the rows grow).
    part_filled[t] / part_pairs[t]: its pairs written / contributing pairs, updated in place; part_bad[t]: the ids
    ≥ N it met and left out (the caller refuses them: they would index past the scratch).
    """
    k = ids.shape[1]
    num_gaussians = seen.shape[1]
    capacity = out_g.shape[1]
    for t in numba.prange(part_end.shape[0]):
        filled = part_filled[t]
        pairs = 0
        m = part_next[t]
        while m < part_end[t]:
            bound = min(num_gaussians, (starts[m + 1] - starts[m]) * k)
            if filled + bound > capacity:
                break
            count = 0
            for o in range(starts[m], starts[m + 1]):
                p = order[o]
                for s in range(k):
                    g = ids[p, s]
                    if g < 0:
                        continue
                    if g >= num_gaussians:
                        part_bad[t] += 1
                        continue
                    if seen[t, g] != m:
                        seen[t, g] = m
                        acc[t, g] = 0.0
                        touched[t, count] = g
                        count += 1
                    acc[t, g] += weights[p, s]
                    pairs += 1
            for c in range(count):
                g = touched[t, c]
                out_g[t, filled] = g
                out_row[t, filled] = m
                out_w[t, filled] = acc[t, g]
                filled += 1
                seen[t, g] = -1
            m += 1
        part_next[t] = m
        part_filled[t] = filled
        part_pairs[t] += pairs


FIRST_RUN_PROBE = _coalesce_parts_kernel  # every engine's sums on the host run it: its place in numba's cache shows a run here before (driver.say_if_kernels_compile)


@numba.njit(cache=True, parallel=True)
def _sort_within_masks_kernel(gaussians, masks, weights, bounds):  # pragma: no cover - jitted
    """Each run gaussians[bounds[r]:bounds[r + 1]] (one mask's pairs, distinct Gaussians) sorted by
    Gaussian in place, its masks and weights moved with it; runs in parallel."""
    for r in numba.prange(bounds.shape[0] - 1):
        lo, hi = bounds[r], bounds[r + 1]
        if hi - lo < 2:
            continue
        order = np.argsort(gaussians[lo:hi]) + lo
        g, m, w = gaussians[order], masks[order], weights[order]
        gaussians[lo:hi], masks[lo:hi], weights[lo:hi] = g, m, w


def sort_within_masks(gaussians: np.ndarray, masks: np.ndarray, weights: np.ndarray) -> None:
    """Pairs that come mask by mask (`Coalescer.coalesce`: masks ascending, Gaussians in first-seen
    order) sorted by (mask, Gaussian) in place: gaussians [P], masks [P], weights [P]. The same
    order as `np.lexsort((gaussians, masks))`, each mask sorted on its own (in parallel)."""
    if masks.size == 0:
        return
    bounds = np.flatnonzero(np.diff(masks)) + 1
    _sort_within_masks_kernel(gaussians, masks, weights, np.concatenate([[0], bounds, [masks.size]]).astype(np.int64))


SCRATCH_BYTES = 12  # per Gaussian per part: the seen / acc / touched arrays
EXTRA_SCRATCH_LIMIT = 256 << 20  # scratch of the parts beyond the first (a 50M scene keeps one part: 600 MB each)


def coalesce_parts(num_gaussians: int) -> int:
    """Parts a Coalescer cuts a view's masks into by default: one per numba thread, as long as
    the extra parts' scratch (SCRATCH_BYTES per Gaussian each) stays within EXTRA_SCRATCH_LIMIT.
    The pairs do not depend on it."""
    affordable = 1 + EXTRA_SCRATCH_LIMIT // max(SCRATCH_BYTES * num_gaussians, 1)
    return int(max(1, min(numba.get_num_threads(), affordable)))


def split_masks(starts: np.ndarray, parts: int) -> np.ndarray:
    """[parts + 1] mask boundaries cutting masks 0 .. M-1 into contiguous parts of about equal
    pixel counts: each inner boundary b is the one whose pixel count before it, starts[b], is
    nearest to an equal share (starts: [M + 1] the counting sort's mask starts)."""
    num_masks = starts.shape[0] - 1
    targets = starts[-1] * np.arange(1, parts) / parts
    above = np.minimum(np.searchsorted(starts, targets, side="left"), num_masks)
    below = np.maximum(above - 1, 0)
    inner = np.where(targets - starts[below] <= starts[above] - targets, below, above)
    return np.maximum.accumulate(np.concatenate([[0], inner, [num_masks]]).astype(np.int64))


class Coalescer:
    """Turns one view's top-k lists into its distinct (Gaussian, mask) pairs (numba, in parallel over
    contiguous parts of the masks).

    Owns the kernel's scratch arrays (SCRATCH_BYTES per Gaussian per part: `parts`, default
    `coalesce_parts`) and per part a pair buffer that grows to the largest share of a view seen, so a view
    never costs more than its own pairs. The pairs are the same, in the same order, for any number
    of parts.
    """

    def __init__(self, num_gaussians: int, capacity: int = 1 << 20, parts: int | None = None):
        self.parts = max(1, int(parts or coalesce_parts(num_gaussians)))
        # made once a registration, touched a view's Gaussians at a time: small pages (drsplat.memory.small_page_full)
        self._seen = small_page_full((self.parts, num_gaussians), -1, np.int32)
        self._acc = small_page_zeros((self.parts, num_gaussians), np.float32)
        self._touched = small_page_zeros((self.parts, num_gaussians), np.int32)
        self._alloc(max(1, capacity // self.parts))

    @property
    def num_gaussians(self) -> int:
        """N: the Gaussians a view's ids index."""
        return self._seen.shape[1]

    def coalesce(self, ids: np.ndarray, weights: np.ndarray, mask_ids: np.ndarray, num_masks: int,
                 by_gaussian: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """ids, weights: [H, W, k]; mask_ids: [H, W] (-1 = none, else < num_masks).

        Returns (gaussians [P] int32, masks [P] int32, weights [P] float32, contributing pairs):
        w_ij = Σ_{p ∈ mask j} w_i(p), mask by mask, Gaussians in first-seen order (arrays are copies).
        by_gaussian: then stably grouped by Gaussian (`stable_order`): each Gaussian's masks stay in
        increasing order, the only order a per-Gaussian sum depends on, and the vote and check
        kernels, which read a view's pairs Gaussian by Gaussian, skip their own sorts (three per view).
        """
        if num_masks < 0:
            raise ValueError(f"coalesce: num_masks is {num_masks}; expected 0 or more")
        k = ids.shape[-1]
        masks = mask_ids.reshape(-1)
        if masks.dtype != np.int32:  # ids outside int32 would wrap into range (round 67a F8): out of range, none
            masks = np.where((masks >= 0) & (masks < num_masks), masks, -1)
        masks = np.ascontiguousarray(masks, np.int32)
        if ids.dtype != np.int32 and ids.size:  # int64 ids past int32 would wrap into range (round 68b F4): refused as past N
            past = int(np.count_nonzero(ids >= self.num_gaussians))
            if past:
                raise self._ids_past_n(past)
            ids = np.where(ids < 0, -1, ids)
        ids2 = np.ascontiguousarray(ids.reshape(masks.shape[0], k), np.int32)  # by the pixel count: k = 0 has no -1 to infer
        w2 = np.ascontiguousarray(weights.reshape(masks.shape[0], k), np.float32)
        starts, order = _bucket_pixels(masks, num_masks)
        bounds = split_masks(starts, self.parts)
        nxt, end = bounds[:-1].copy(), bounds[1:].copy()
        filled = np.zeros(self.parts, np.int64)
        pairs = np.zeros(self.parts, np.int64)
        bad = np.zeros(self.parts, np.int64)
        while True:
            _coalesce_parts_kernel(ids2, w2, order, starts, end, nxt, filled, pairs, bad, self._seen, self._acc, self._touched,
                                   self._g, self._m, self._w)
            if bad.any():  # an API caller's ids (a render's are < N): refused, not written past the scratch (round 67a F8)
                raise self._ids_past_n(int(bad.sum()))
            if np.all(nxt >= end):
                break
            self._alloc(2 * self._g.shape[1])
        rows = [slice(0, int(f)) for f in filled]
        g = np.concatenate([self._g[t, r] for t, r in enumerate(rows)])
        m = np.concatenate([self._m[t, r] for t, r in enumerate(rows)])
        w = np.concatenate([self._w[t, r] for t, r in enumerate(rows)])
        if by_gaussian:
            order = stable_order(g)
            g, m, w = g[order], m[order], w[order]
        return g, m, w, int(pairs.sum())

    def _ids_past_n(self, count: int) -> ValueError:
        """The error of a view holding `count` Gaussian ids ≥ N."""
        return ValueError(f"coalesce: {counted(count, 'Gaussian id of the view is', 'Gaussian ids of the view are')} {self.num_gaussians} "
                          f"or more; expected ids below the scene's {self.num_gaussians} Gaussians (or -1)")

    def _alloc(self, size: int) -> None:
        """Pair rows of `size` per part, keeping what the old rows hold."""
        for name, dtype in (("_g", np.int32), ("_m", np.int32), ("_w", np.float32)):
            new = np.zeros((self.parts, size), dtype)
            old = getattr(self, name, None)
            if old is not None:
                new[:, : old.shape[1]] = old
            setattr(self, name, new)


def coalesce_reference(ids: np.ndarray, weights: np.ndarray, mask_ids: np.ndarray, num_masks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Obviously-correct reference of `Coalescer.coalesce` (numpy, float64 sums).

    ids, weights: [H, W, k]; mask_ids: [H, W]. Returns (gaussians [P], masks [P], w_ij [P] float64,
    contributing pairs), sorted by (mask, Gaussian): the same set of pairs as the kernel, whose
    order within a mask is first-seen.
    """
    k = ids.shape[-1]
    g = ids.reshape(-1).astype(np.int64)
    m = np.repeat(mask_ids.reshape(-1).astype(np.int64), k)
    w = weights.reshape(-1).astype(np.float64)
    keep = (g >= 0) & (m >= 0) & (m < num_masks)
    base = int(g[keep].max()) + 1 if keep.any() else 1
    keys, inverse = np.unique(m[keep] * base + g[keep], return_inverse=True)
    sums = np.zeros(keys.size)
    np.add.at(sums, inverse, w[keep])
    return keys % base, keys // base, sums, int(np.count_nonzero(keep))

