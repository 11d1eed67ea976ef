"""The radix sorts (drsplat._sort_kernels) against numpy's stable sorts."""

from __future__ import annotations

import numpy as np
import pytest

from drsplat import _sort_kernels as sorts


@pytest.mark.parametrize("high", [1, 2, 255, 256, 2047, 2048, 2049, 70_000, 2**22, 2**22 + 1, 2**31 - 1])
def test_stable_order_is_numpys_stable_argsort(high):
    """Largest rows on either side of a digit count's boundary (2¹¹, 2²², 2³¹ - 1: one, two, three
    passes), many repeats, one row, none; rows already grouped take the scan's early answer."""
    rng = np.random.default_rng(high % 97)
    for size in (0, 1, 7, 5000):
        rows = rng.integers(0, high, size).astype(np.int32)
        if size > 2:
            rows[: size // 3] = rows[0]  # repeats
            rows[-1] = high - 1  # the largest row decides the passes
        before = rows.copy()
        np.testing.assert_array_equal(sorts.stable_order(rows), np.argsort(rows, kind="stable"))
        np.testing.assert_array_equal(rows, before)  # the input is not written
        ordered = np.sort(rows)
        np.testing.assert_array_equal(sorts.stable_order(ordered), np.arange(size))


def test_stable_order_refuses_a_negative_row():
    with pytest.raises(ValueError, match="rows >= 0, got -3"):
        sorts.stable_order(np.array([4, -3, 2], np.int32))


@pytest.mark.parametrize("keys", ["full-range", "top-bit", "one-key", "low-digit-only", "descending"])
def test_sort_by_key_is_a_stable_sort_of_the_ids(keys):
    rng = np.random.default_rng(len(keys))
    n = 30_000
    k = {
        "full-range": rng.integers(0, 2**32, n, dtype=np.uint64),
        "top-bit": 2**31 + rng.integers(0, 2**12, n) * 2**19,  # only the top digit varies: two passes skipped
        "one-key": np.full(n, 2**32 - 1),
        "low-digit-only": 7 * 2**25 + rng.integers(0, 16, n),
        "descending": np.arange(n)[::-1] * 1000,
    }[keys].astype(np.uint32)
    ids = rng.permutation(10 * n)[:n].astype(np.int64)
    k_before, ids_before = k.copy(), ids.copy()
    np.testing.assert_array_equal(sorts.sort_by_key(k, ids), ids[np.argsort(k, kind="stable")])
    np.testing.assert_array_equal(k, k_before)
    np.testing.assert_array_equal(ids, ids_before)


@pytest.mark.parametrize("n_chunks", [1, 2, 3, 64, 5000])
@pytest.mark.parametrize("width", [1, 8, 11])
def test_radix_pass_is_stable_for_any_chunking(n_chunks, width):
    rng = np.random.default_rng(n_chunks + width)
    keys = rng.integers(0, 2**32, 3000, dtype=np.uint64).astype(np.uint32)
    keys[::3] = keys[1]  # many exact ties
    ids = np.arange(keys.size, dtype=np.int64)
    out_keys, out_ids = np.empty_like(keys), np.empty_like(ids)
    for shift in (0, width, 32 - width):
        assert sorts.radix_pass(keys, ids, out_keys, out_ids, shift, width, n_chunks)
        digit = (keys >> np.uint32(shift)) & np.uint32((1 << width) - 1)
        order = np.argsort(digit, kind="stable")
        np.testing.assert_array_equal(out_keys, keys[order])
        np.testing.assert_array_equal(out_ids, ids[order])
    same = np.full(10, 77 << 11, np.uint32)
    before = out_keys[:10].copy()
    assert not sorts.radix_pass(same, ids[:10], out_keys[:10], out_ids[:10], 11, width, n_chunks)
    np.testing.assert_array_equal(out_keys[:10], before)  # a skipped pass writes nothing


@pytest.mark.parametrize("largest,passes,width", [(0, 1, 1), (1, 1, 1), (2047, 1, 11), (2048, 2, 6), (542_103, 2, 10),
                                                  (2**22 - 1, 2, 11), (2**22, 3, 8), (2**32 - 1, 3, 11)])
def test_digit_widths(largest, passes, width):
    assert sorts.digit_widths(largest) == (passes, width)
