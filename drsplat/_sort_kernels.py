"""Stable radix sorts of non-negative integer keys (numba): the depth order of a view and the pairs
grouped by Gaussian. The references are numpy's stable sorts (tests/test_sort_kernels.py)."""

from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

RADIX_BITS = 11  # the widest digit: 2,048 counters per chunk stay in L1 (2¹⁶ buckets scatter to as many places: 1.9-2.6x slower)
CHUNKS_PER_THREAD = 1  # chunks of a pass: each has its own counters, so more only costs their prefix sum


@njit(parallel=True, cache=True)
def radix_pass(keys, ids, out_keys, out_ids, shift, width, n_chunks) -> bool:
    """One stable counting-sort pass of (keys, ids) by the `width`-bit digit of keys at `shift`.

    keys: [M] uint32, ids: [M] int64; out_*: [M], written. The M entries are cut into n_chunks
    contiguous chunks; a chunk's entries of digit d go, in order, after every entry of a smaller
    digit and after the earlier chunks' entries of digit d, so the pass is stable whatever
    n_chunks is. Returns False, writing nothing, when every key has the same digit there (the
    pass would only copy).
    """
    m = keys.shape[0]
    n_chunks = max(1, min(n_chunks, m))
    step = (m + n_chunks - 1) // n_chunks
    mask = np.uint32((1 << width) - 1)
    sh = np.uint32(shift)
    counts = np.zeros((n_chunks, 1 << width), np.int64)
    for c in prange(n_chunks):
        for i in range(c * step, min(m, (c + 1) * step)):
            counts[c, (keys[i] >> sh) & mask] += 1
    total = 0
    for d in range(1 << width):
        in_digit = 0
        for c in range(n_chunks):
            in_digit += counts[c, d]
        if in_digit == m:
            return False
        for c in range(n_chunks):
            start = total
            total += counts[c, d]
            counts[c, d] = start
    for c in prange(n_chunks):
        for i in range(c * step, min(m, (c + 1) * step)):
            d = (keys[i] >> sh) & mask
            slot = counts[c, d]
            out_keys[slot] = keys[i]
            out_ids[slot] = ids[i]
            counts[c, d] = slot + 1
    return True


@njit(parallel=True, cache=True)
def _largest_and_ascending(keys, parts):  # pragma: no cover - jitted
    """(largest key, whether keys never decrease) of keys [M] uint32, M >= 1, in one pass in
    `parts` parallel chunks."""
    m = keys.shape[0]
    parts = max(1, min(parts, m))
    step = (m + parts - 1) // parts
    tops = np.zeros(parts, np.uint32)
    falls = np.zeros(parts, np.bool_)
    for c in prange(parts):
        top = np.uint32(0)
        fall = False
        for i in range(c * step, min(m, (c + 1) * step)):
            top = max(top, keys[i])
            fall = fall or (i > 0 and keys[i] < keys[i - 1])
        tops[c] = top
        falls[c] = fall
    return tops.max(), not falls.any()


def digit_widths(largest: int) -> tuple[int, int]:
    """(passes, bits per pass) of a radix sort of keys up to `largest`: as few digits of at most
    RADIX_BITS bits as cover its bit length, the bits split evenly between them (542k rows: two
    10-bit passes; a 27k-row room: two 8-bit ones; a full 32-bit key: three of 11)."""
    bits = max(1, int(largest).bit_length())
    passes = -(-bits // RADIX_BITS)
    return passes, -(-bits // passes)


def sort_by_key(keys: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """ids [M] int64 reordered by keys [M] uint32, stably (equal keys keep their order in ids):
    `ids[np.argsort(keys, kind="stable")]`, by least-significant-digit radix passes (`radix_pass`,
    in parallel over chunks; a digit every key shares is skipped). Keys already ascending cost one
    scan. Neither input is written; the result is a new array."""
    if keys.shape[0] < 2:
        return ids.copy()
    largest, ascending = _largest_and_ascending(keys, numba.get_num_threads())
    return _radix_sort(keys, ids, int(largest), bool(ascending))


def _radix_sort(keys: np.ndarray, ids: np.ndarray, largest: int, ascending: bool) -> np.ndarray:
    if ascending:
        return ids.copy()
    passes, width = digit_widths(largest)
    n_chunks = CHUNKS_PER_THREAD * numba.get_num_threads()
    m = keys.shape[0]
    buffers = [(np.empty(m, np.uint32), np.empty(m, np.int64)), (np.empty(m, np.uint32), np.empty(m, np.int64))]
    src_keys, src_ids, spare = keys, ids, 0
    for q in range(passes):
        out_keys, out_ids = buffers[spare]
        if radix_pass(src_keys, src_ids, out_keys, out_ids, q * width, width, n_chunks):
            src_keys, src_ids, spare = out_keys, out_ids, 1 - spare
    return src_ids if src_ids is not ids else ids.copy()


def stable_order(rows: np.ndarray) -> np.ndarray:
    """[M] int64 `np.argsort(rows, kind="stable")` of rows [M] int32 >= 0 (`sort_by_key` of the
    indices); ValueError for a negative row."""
    rows = np.ascontiguousarray(rows, np.int32)
    ids = np.arange(rows.shape[0], dtype=np.int64)
    if rows.shape[0] < 2:
        return ids
    keys = rows.view(np.uint32)
    largest, ascending = _largest_and_ascending(keys, numba.get_num_threads())
    if int(largest) > np.iinfo(np.int32).max:
        raise ValueError(f"stable_order sorts rows >= 0, got {int(rows.min())}")
    return ids if ascending else _radix_sort(keys, ids, int(largest), False)
