"""The prefetch hint (drsplat._prefetch): no change to what a kernel computes, and it reaches the machine code."""

from __future__ import annotations

import platform

import numba
import numpy as np
import pytest

from drsplat._prefetch import prefetch_row


@numba.njit(cache=False)
def _gather_sum(a, ids, ahead):
    """Σ_j a[ids[j], 0], hinting the row of ids[j + ahead] first (the kernels' pattern)."""
    total = 0.0
    for j in range(ids.shape[0]):
        if j + ahead < ids.shape[0]:
            prefetch_row(a, ids[j + ahead])
        total += a[ids[j], 0]
    return total


@pytest.mark.parametrize("layout", ["C", "F", "strided"])
@pytest.mark.parametrize("id_type", [np.int32, np.int64, np.uint32])
def test_a_hinted_gather_sums_what_numpy_does(layout, id_type):
    rng = np.random.default_rng(7)
    base = rng.standard_normal((5_000, 6))
    a = {"C": base, "F": np.asfortranarray(base), "strided": base[::2, ::3]}[layout]
    ids = rng.integers(0, a.shape[0], 20_000).astype(id_type)
    for ahead in (0, 1, 8, 50_000):  # 50,000: past the end, never hinted
        assert _gather_sum(a, ids, ahead) == pytest.approx(float(np.sum(a[ids.astype(np.int64), 0])), rel=1e-12)


def test_the_hint_of_a_one_dimensional_array_and_of_three_dimensions():
    @numba.njit(cache=False)
    def touch(v, cube, i):
        prefetch_row(v, i)
        prefetch_row(cube, i)
        return v[i] + cube[i, 1, 1]

    v = np.arange(10.0)
    cube = np.arange(10 * 3 * 3, dtype=np.float32).reshape(10, 3, 3)
    assert touch(v, cube, 4) == 4.0 + cube[4, 1, 1]


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="checks an x86 prefetch instruction")
def test_the_hint_is_a_prefetch_instruction():
    a = np.zeros((100, 2))
    ids = np.arange(100, dtype=np.int32)
    _gather_sum(a, ids, 4)
    asm = _gather_sum.inspect_asm(_gather_sum.signatures[0])
    assert "prefetcht0" in asm


def test_a_non_integer_row_is_a_typing_error():
    @numba.njit(cache=False)
    def bad(a):
        prefetch_row(a, 1.5)

    with pytest.raises(numba.core.errors.TypingError):
        bad(np.zeros((3, 3)))
