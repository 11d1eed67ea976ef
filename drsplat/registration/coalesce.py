"""One view's top-k lists -> its distinct (Gaussian, mask) pairs with summed weights.

Pixel p lies in mask j of its view (-1: none), and its top-k slots hold Gaussians i with weights
w_i(p). The view contributes

    w_ij = Σ_{p ∈ mask j} w_i(p)

for every (i, j) with at least one such slot. Pixels are bucketed by mask (counting sort); per
mask the weights of its pixels' Gaussians are summed in a scratch array of N floats, so a view
costs O(pixels·k + N) and never forms anything Gaussians x masks. The pairs come out mask by
mask, Gaussians in first-seen order: that order fixes the summation order downstream
(drsplat.registration.sums), so every place that coalesces a view gets the same bits.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def _coalesce_view_kernel(ids, weights, mask_ids, num_masks, first_mask, row_offset, seen, acc, touched, out_g, out_row, out_w, filled):  # pragma: no cover - jitted
    """Append the view's distinct (Gaussian, mask) pairs with summed weights to the out_* buffers.

    Pixels are bucketed by mask (counting sort); per mask the weights of its pixels' top-k
    Gaussians are summed in `acc` (scratch [N], `seen` [N] all -1 on entry and exit). Starts at
    mask `first_mask`; stops before a mask whose pairs might not fit. Mask m is written as row
    row_offset + m. Returns (contributing pairs, distinct pairs, next mask, filled).
    """
    num_pixels, k = ids.shape
    num_gaussians = seen.shape[0]
    capacity = out_g.shape[0]
    starts = np.zeros(num_masks + 1, np.int64)
    for p in range(num_pixels):
        m = mask_ids[p]
        if m >= first_mask:
            starts[m + 1] += 1
    for m in range(num_masks):
        starts[m + 1] += starts[m]
    order = np.empty(starts[num_masks], np.int64)
    fill = starts[:num_masks].copy()
    for p in range(num_pixels):
        m = mask_ids[p]
        if m >= first_mask:
            order[fill[m]] = p
            fill[m] += 1
    num_pairs = 0
    num_distinct = 0
    for m in range(first_mask, num_masks):
        bound = min(num_gaussians, (starts[m + 1] - starts[m]) * k)
        if filled + bound > capacity:
            return num_pairs, num_distinct, m, filled
        count = 0
        for o in range(starts[m], starts[m + 1]):
            p = order[o]
            for s in range(k):
                g = ids[p, s]
                if g < 0:
                    continue
                if seen[g] != m:
                    seen[g] = m
                    acc[g] = 0.0
                    touched[count] = g
                    count += 1
                acc[g] += weights[p, s]
                num_pairs += 1
        for t in range(count):
            g = touched[t]
            out_g[filled] = g
            out_row[filled] = row_offset + m
            out_w[filled] = acc[g]
            filled += 1
            seen[g] = -1
        num_distinct += count
    return num_pairs, num_distinct, num_masks, filled



class Coalescer:
    """Turns one view's top-k lists into its distinct (Gaussian, mask) pairs (numba).

    Owns the kernel's scratch arrays ([N] each, 12 bytes per Gaussian) and a pair buffer that
    grows to the largest view seen, so a view never costs more than its own pairs.
    """

    def __init__(self, num_gaussians: int, capacity: int = 1 << 20):
        self._seen = np.full(num_gaussians, -1, np.int32)
        self._acc = np.zeros(num_gaussians, np.float32)
        self._touched = np.zeros(num_gaussians, np.int32)
        self._g = np.zeros(capacity, np.int32)
        self._m = np.zeros(capacity, np.int32)
        self._w = np.zeros(capacity, np.float32)

    def coalesce(self, ids: np.ndarray, weights: np.ndarray, mask_ids: np.ndarray, num_masks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """ids, weights: [H, W, k]; mask_ids: [H, W] (-1 = none).

        Returns (gaussians [P] int32, masks [P] int32, weights [P] float32, contributing pairs):
        w_ij = Σ_{p ∈ mask j} w_i(p), mask by mask in the kernel's order (arrays are copies).
        """
        k = ids.shape[-1]
        ids2 = np.ascontiguousarray(ids.reshape(-1, k), np.int32)
        w2 = np.ascontiguousarray(weights.reshape(-1, k), np.float32)
        masks = np.ascontiguousarray(mask_ids.reshape(-1), np.int32)
        pairs = filled = first = 0
        while True:
            p, _, first, filled = _coalesce_view_kernel(
                ids2, w2, masks, num_masks, first, 0, self._seen, self._acc, self._touched, self._g, self._m, self._w, filled,
            )
            pairs += p
            if first >= num_masks:
                return self._g[:filled].copy(), self._m[:filled].copy(), self._w[:filled].copy(), int(pairs)
            self._grow()

    def _grow(self) -> None:
        size = 2 * self._g.shape[0]
        for name in ("_g", "_m", "_w"):
            old = getattr(self, name)
            new = np.zeros(size, old.dtype)
            new[: old.shape[0]] = old
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
