"""Storage backends of a language field: one interface, one class per way of storing features.

Each backend stores N per-Gaussian features and answers cosine queries without decoding them all:

- `exact` (`ExactStorage`): features [N, D] float16 (2·D bytes per Gaussian).
- `pq` / `ivfpq` (`PQStorage`): a faiss product quantiser, codes [N, M] uint8 (M bytes per Gaussian) and, for
  the official Dr. Splat `IndexIVFPQ`, a coarse list id per Gaussian; scored through look-up tables.

Every backend keeps norms [N] float32 of what it stores (0 = unassigned) and scores a unit query q as
q·r_i / |r_i|. A backend class provides:

    kind                         the name written in the registered PLY (`kind=` of its comment)
    encode(features, assigned, codebook) -> storage      from registered unit features [N, D]
    scores(q [K, D], lut_bits) -> [N, K]                  the fast path (numba kernels of drsplat.lang.lut)
    scores_reference(q) -> [N, K]                         decode-then-cosine in float64, for tests
    reconstruct(index) -> [n, D] float32
    take(index) -> storage                                the subset of Gaussians `index` selects
    bytes_per_gaussian() -> int                           stored bytes per Gaussian (a stored norm included)
    columns() -> {PLY property: [N] array}; from_columns(get, n, dim, codebook) -> storage

Adding a backend is one class here plus one line in BACKENDS (drsplat.lang.plyformat and
drsplat.lang.field dispatch through it).
"""

from __future__ import annotations

import copy
import logging
import math
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numba
import numpy as np

from drsplat._scene_kernels import transpose_copy
from drsplat.errors import InputError, shown_path
from drsplat.lang.codebook import Codebook, unit_check, unit_rows
from drsplat.scene import counted
from drsplat.lang.lut import (
    BLOCKED_MIN_M,
    blocked_codes,
    blocked_codes_in_place,
    code_table_sums,
    half_scores,
    has_feature,
    lut_scores,
    lut_scores_blocked,
    lut_scores_reference,
    simd_available,
    unblocked_codes,
)

EXACT_CHUNK = 32768
log = logging.getLogger(__name__)

ENCODE_CHUNK = 65536

ColumnGetter = Callable[[str], np.ndarray]  # PLY property name -> [N] array (raises InputError when missing)


def chunked_row_norms(x: np.ndarray, chunk: int = EXACT_CHUNK) -> np.ndarray:
    """|x_i| of [N, D] rows in float32: [N]. Float16 rows by `_half_norms_kernel` (numpy's bits, 6x
    faster: flowers' 493k x 512 field 0.48 -> 0.08 s, the norms every load of an exact field makes),
    others by `chunked_row_norms_reference`."""
    if x.dtype != np.float16 or x.ndim != 2 or x.shape[0] == 0 or x.shape[1] == 0:
        return chunked_row_norms_reference(x, chunk)
    leaves, order = pairwise_plan(x.shape[1])
    norms = np.empty(x.shape[0], np.float32)
    _half_norms_kernel(np.ascontiguousarray(x).view(np.uint16), leaves, order, norms)
    return norms


def chunked_row_norms_reference(x: np.ndarray, chunk: int = EXACT_CHUNK) -> np.ndarray:
    """`chunked_row_norms` by numpy, chunk by chunk (no [N, D] float32 copy of a float16 array). Each chunk is made
    row-contiguous first: numpy sums a contiguous row pairwise but a column-ordered array column by column, so the
    norms of one field would depend on its memory layout by an ulp (round 66c F4)."""
    norms = np.empty(x.shape[0], np.float32)
    for start in range(0, x.shape[0], chunk):
        norms[start : start + chunk] = np.linalg.norm(np.ascontiguousarray(x[start : start + chunk], np.float32), axis=1)
    return norms


PAIRWISE_BLOCK = 128  # numpy's PW_BLOCKSIZE: runs at most this long are summed with 8 accumulators


def pairwise_plan(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The order in which numpy's pairwise summation adds n contiguous float32 values (what
    `np.add.reduce` and so `np.linalg.norm` do along a contiguous axis): the leaf runs [(start,
    length)] it sums directly (`_leaf_sum`), and a postfix program over them (leaf index, or -1:
    add the top two partial sums), from its recursion n -> (n2, n - n2), n2 = n/2 rounded down to a
    multiple of 8. tests/test_index.py checks the bits against numpy for many lengths."""
    leaves: list[tuple[int, int]] = []
    program: list[int] = []
    stack = [(0, n, False)]
    while stack:  # the recursion's post-order, without recursion
        start, length, expanded = stack.pop()
        if length <= PAIRWISE_BLOCK:
            program.append(len(leaves))
            leaves.append((start, length))
        elif expanded:
            program.append(-1)
        else:
            half = length // 2
            half -= half % 8
            stack += [(start, length, True), (start + half, length - half, False), (start, half, False)]
    return np.array(leaves, np.int64).reshape(-1, 2), np.array(program, np.int64)


@numba.njit(inline="always")
def _leaf_sum(a, start, n):  # pragma: no cover - jitted
    """numpy's sum of the float32 run a[start:start+n], n ≤ PAIRWISE_BLOCK: below 8 one by one;
    else 8 accumulators over the multiple-of-8 part, combined ((0+1)+(2+3))+((4+5)+(6+7)), then the rest."""
    if n < 8:
        total = np.float32(0.0)
        for i in range(n):
            total += a[start + i]
        return total
    r0, r1, r2, r3 = a[start], a[start + 1], a[start + 2], a[start + 3]
    r4, r5, r6, r7 = a[start + 4], a[start + 5], a[start + 6], a[start + 7]
    i = 8
    while i < n - n % 8:
        r0 += a[start + i]
        r1 += a[start + i + 1]
        r2 += a[start + i + 2]
        r3 += a[start + i + 3]
        r4 += a[start + i + 4]
        r5 += a[start + i + 5]
        r6 += a[start + i + 6]
        r7 += a[start + i + 7]
        i += 8
    total = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        total += a[start + i]
        i += 1
    return total


@numba.njit(inline="always")
def _float_bits_of_half(h):  # pragma: no cover - jitted
    """The float32 bits of the float16 whose bits are h: exact (every half is a float32), subnormals
    normalised, inf and NaN kept (the same as numpy's cast for all 65,536 halves: tested)."""
    h = np.uint32(h)
    sign = (h & np.uint32(0x8000)) << np.uint32(16)
    exp = h & np.uint32(0x7C00)
    sig = h & np.uint32(0x03FF)
    if exp == np.uint32(0x7C00):
        return sign | np.uint32(0x7F800000) | (sig << np.uint32(13))
    if exp != 0:
        return sign | (((exp >> np.uint32(10)) + np.uint32(112)) << np.uint32(23)) | (sig << np.uint32(13))
    if sig == 0:
        return sign
    e = np.uint32(113)
    while (sig & np.uint32(0x0400)) == 0:
        sig <<= np.uint32(1)
        e -= np.uint32(1)
    return sign | (e << np.uint32(23)) | ((sig & np.uint32(0x03FF)) << np.uint32(13))


@numba.njit(parallel=True, cache=True)
def _half_norms_kernel(bits, leaves, program, out):  # pragma: no cover - jitted
    """out[i] = ‖row i‖ of float16 rows (bits [N, D] uint16) as np.linalg.norm computes it in float32:
    the squares in float32, summed in numpy's pairwise order (`pairwise_plan`), then the sqrt; in
    parallel over runs of 256 rows."""
    n, d = bits.shape
    for run in numba.prange((n + 255) // 256):
        words = np.empty(d, np.uint32)
        values = words.view(np.float32)
        squares = np.empty(d, np.float32)
        sums = np.empty(leaves.shape[0], np.float32)
        stack = np.empty(program.shape[0] + 1, np.float32)
        for i in range(run * 256, min(n, run * 256 + 256)):
            for j in range(d):
                words[j] = _float_bits_of_half(bits[i, j])
            for j in range(d):
                squares[j] = values[j] * values[j]
            for leaf in range(leaves.shape[0]):
                sums[leaf] = _leaf_sum(squares, leaves[leaf, 0], leaves[leaf, 1])
            top = 0
            for step in program:
                if step >= 0:
                    stack[top] = sums[step]
                    top += 1
                else:
                    stack[top - 2] = stack[top - 2] + stack[top - 1]
                    top -= 1
            out[i] = np.sqrt(stack[0])


@numba.njit(inline="always")
def _half_bits(f):  # pragma: no cover - jitted
    """The float16 bits of the float32 whose bits are f (uint32), rounded to nearest, ties to even:
    from 65520 up inf, below half's smallest subnormal a signed zero, NaN kept a NaN with the top of
    its payload. Every case is computed and one selected, without a branch, so the row loop
    vectorises. The same bits as numpy's `astype(np.float16)` for all 2³² inputs (checked
    exhaustively once, 2026-11-30; tests/test_query.py checks the edges)."""
    sign = (f >> np.uint32(16)) & np.uint32(0x8000)
    exp = f & np.uint32(0x7F800000)
    sig = f & np.uint32(0x007FFFFF)
    # a normal half: the significand's top 10 bits, +1 from the bit below unless an exact tie onto an even half
    # (a carry into the exponent is right, up to inf)
    up = sig + (np.uint32(0) if (sig & np.uint32(0x3FFF)) == np.uint32(0x1000) else np.uint32(0x1000))
    normal = ((exp - np.uint32(0x38000000)) >> np.uint32(13)) + (up >> np.uint32(13))
    # a subnormal half: the significand with its leading 1, shifted by 1 to 11 bits more; the tie
    # test also looks at the bits the shift dropped
    shift = min(np.uint32(113) - min(exp >> np.uint32(23), np.uint32(113)), np.uint32(31))
    small = (np.uint32(0x00800000) + sig) >> shift
    tie = (small & np.uint32(0x3FFF)) == np.uint32(0x1000) and (f & np.uint32(0x7FF)) == np.uint32(0)
    subnormal = (small + (np.uint32(0) if tie else np.uint32(0x1000))) >> np.uint32(13)
    nan = np.uint32(0x7C00) + (sig >> np.uint32(13))
    nan = nan + (np.uint32(1) if nan == np.uint32(0x7C00) else np.uint32(0))  # a payload below half's bits: still a NaN
    beyond = nan if (exp == np.uint32(0x7F800000) and sig != np.uint32(0)) else np.uint32(0x7C00)
    below = np.uint32(0) if exp < np.uint32(0x33000000) else subnormal
    inside = below if exp <= np.uint32(0x38000000) else normal
    return sign + (beyond if exp >= np.uint32(0x47800000) else inside)


@numba.njit(parallel=True, cache=True)
def _float16_rows_kernel(bits, keep, out):  # pragma: no cover - jitted
    """out[i] = the float16 bits of rows bits [N, D] (float32 bits) where keep[i], else zeros; in parallel."""
    for i in numba.prange(bits.shape[0]):
        if keep[i]:
            for j in range(bits.shape[1]):
                out[i, j] = np.uint16(_half_bits(bits[i, j]))
        else:
            for j in range(bits.shape[1]):
                out[i, j] = 0


def float16_rows(f: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """[N, D] float16 of f [N, D] float32, rows where keep [N] is False zero (`_float16_rows_kernel`;
    numpy's astype of flowers' 542k x 512 features takes 0.45 s, this 0.05 s on 2 threads).
    `float16_rows_reference` is the numpy form, the same bits."""
    f = np.ascontiguousarray(f, np.float32)
    out = np.empty(f.shape, np.uint16)
    if out.size:
        _float16_rows_kernel(f.view(np.uint32), np.ascontiguousarray(keep, np.bool_), out)
    return out.view(np.float16)


def float16_rows_reference(f: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """`float16_rows` in numpy."""
    with np.errstate(over="ignore", invalid="ignore"):
        f16 = np.asarray(f, np.float32).astype(np.float16)
    f16[~np.asarray(keep, bool)] = 0
    return f16


@numba.njit(parallel=True, cache=True)
def _reconstruction_norms_kernel(codes, list_ids, centroids, coarse, out):  # pragma: no cover - jitted
    """out[i] = ‖r_i‖ of r_i = [coarse[list_ids[i]] +] concat_m centroids[m, codes[i, m]], each entry
    of r_i the float32 sum `Codebook.decode` makes, the squares summed in float64; in parallel."""
    m, dsub = centroids.shape[0], centroids.shape[2]
    has_coarse = coarse.shape[0] > 0
    for i in numba.prange(codes.shape[0]):
        s = 0.0
        for j in range(m):
            c = codes[i, j]
            for d in range(dsub):
                v = centroids[j, c, d]
                if has_coarse:
                    v = v + coarse[list_ids[i], j * dsub + d]
                s += np.float64(v) * np.float64(v)
        out[i] = math.sqrt(s)


def reconstruction_norms(codebook: Codebook, codes: np.ndarray, list_ids: np.ndarray | None, dtype=np.float32) -> np.ndarray:
    """[n] ‖decode(codes)‖ of codes [n, M] (and list ids [n] for ivfpq) without decoding them
    (`_reconstruction_norms_kernel`; `reconstruction_norms_reference` decodes, within 1e-6), as
    `dtype` (float32 to store; float64 to check stored norms, `norm_mismatches`)."""
    out = np.empty(codes.shape[0], dtype)
    if out.size:
        coarse = np.zeros((0, 0), np.float32) if codebook.coarse is None else np.ascontiguousarray(codebook.coarse, np.float32)
        ids = np.zeros(0, np.int32) if list_ids is None else np.ascontiguousarray(list_ids, np.int32)
        _reconstruction_norms_kernel(np.ascontiguousarray(codes, np.uint8), ids, np.ascontiguousarray(codebook.centroids, np.float32), coarse, out)
    return out


def reconstruction_norms_reference(codebook: Codebook, codes: np.ndarray, list_ids: np.ndarray | None) -> np.ndarray:
    """`reconstruction_norms` by decoding (float64 norms)."""
    return np.linalg.norm(codebook.decode(codes, list_ids).astype(np.float64), axis=1).astype(np.float32)


@dataclass
class ExactStorage:
    """features: [N, D] float16; norms: [N] float32 (0 = unassigned), computed from the features when
    first asked for (a field that is only written to a PLY never needs them: 1.9 s of writing
    flowers' 490 k registered rows went to them)."""

    features: np.ndarray
    known_norms: np.ndarray | None = field(default=None, repr=False)
    kind = "exact"

    def detached(self) -> "ExactStorage":
        """This storage with features of its own (a copy): none of its arrays is another's view."""
        return ExactStorage(self.features.copy(), self.known_norms)

    @property
    def norms(self) -> np.ndarray:
        if self.known_norms is None:
            self.known_norms = chunked_row_norms(self.features)
        return self.known_norms

    @classmethod
    def encode(cls, features: np.ndarray, assigned: np.ndarray, codebook: Codebook | None = None,
               checked: tuple[np.ndarray, np.ndarray] | None = None) -> "ExactStorage":
        """Float16 rows (0 where not assigned); a row whose norm is not ~1 is normalised first (unit
        rows, as registration writes, are stored as given), so no direction underflows to zero or
        overflows in float16 (a row of 1e-8 did, while a PQ field kept it). checked: `unit_check`
        of the features when the caller made it (`build_field`), else made here."""
        f = np.asarray(features, np.float32)
        _, off = unit_check(f) if checked is None else checked
        if off.any():
            f = f.copy()
            f[off] = unit_rows(f[off])
        return cls(float16_rows(f, assigned))

    def scores(self, q: np.ndarray, lut_bits: int = 32) -> np.ndarray:
        return half_scores(self.features, self.norms, q)

    def scores_reference(self, q: np.ndarray) -> np.ndarray:
        f = self.features.astype(np.float64)
        norm = np.linalg.norm(f, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (f @ q.astype(np.float64).T) / norm[:, None]
        return np.where((np.isfinite(norm) & (norm > 0))[:, None], s, 0.0).astype(np.float32)  # a non-finite row scores 0

    def reconstruct(self, index: np.ndarray | slice) -> np.ndarray:
        return self.features[index].astype(np.float32)

    def take(self, index: np.ndarray | slice) -> "ExactStorage":
        return ExactStorage(self.features[index], None if self.known_norms is None else self.known_norms[index])

    def bytes_per_gaussian(self) -> int:
        return 2 * self.features.shape[1]  # lang_0 .. lang_{D-1}: the norm is computed on load, not stored

    def columns(self) -> dict[str, np.ndarray]:
        """`lang_0 .. lang_{D-1}`: IEEE float16 bit patterns as ushort (PLY has no half type)."""
        bits = np.asarray(self.features, np.float16).view(np.uint16)
        # column views of one [N, D] array, not copies: scene_to_vertices writes such a run of columns as one block
        return {f"lang_{j}": bits[:, j] for j in range(bits.shape[1])}

    @classmethod
    def from_columns(cls, get: ColumnGetter, n: int, dim: int, codebook: Codebook | None = None) -> "ExactStorage":
        features = stack_columns([get(f"lang_{j}") for j in range(dim)], np.uint16, n, dim).view(np.float16)
        return cls(features)


NORM_RTOL = 2e-6  # stored vs recomputed reconstruction norm: intact rows of the demo are <= 1.3e-7 apart (float32 rounding)


def _other_code(codes: np.ndarray, list_ids: np.ndarray | None, code: np.ndarray, list_id: int | None) -> bool:
    """Whether any of the rows' PQ codes [n, M] (with their inverted lists [n], ivfpq) differs from `code` (`list_id`)."""
    return bool((codes != code).any()) or (list_ids is not None and bool((list_ids != list_id).any()))


def _tells_directions_apart(codebook: Codebook, probes: int = 16) -> bool:
    """Whether `codebook` gives `probes` random unit directions more than one code: a codebook of usable scale always
    does (with M sub-quantisers of 256 centroids each); one whose centroids overflow or vanish in faiss's float32
    distances gives them all the first code."""
    rows = unit_rows(np.random.default_rng(0).standard_normal((probes, codebook.dim)).astype(np.float32))
    codes, list_ids = codebook.encode(rows)
    return _other_code(codes, list_ids, codes[0], None if list_ids is None else list_ids[0])


def row_ids(index: np.ndarray | slice | int, n: int) -> np.ndarray:
    """The rows 0..n-1 an index of [n] rows names, as numpy would take them: a slice, an [n] bool mask, or integers
    (negative from the end). IndexError for an integer outside -n..n-1 or a mask of another length."""
    if isinstance(index, slice):
        return np.arange(n)[index]
    index = np.asarray(index)
    if index.dtype == bool:
        if index.shape != (n,):
            raise IndexError(f"a boolean index of shape {index.shape} for {n} rows")
        return np.flatnonzero(index)
    if index.size and (index.min() < -n or index.max() >= n):
        raise IndexError(f"index {int(index.min() if index.min() < -n else index.max())} is out of bounds for {n} rows")
    return np.where(index < 0, index + n, index).astype(np.int64)


class PQStorage:
    """codes: [N, M] uint8; list_ids: [N] int32 coarse lists (ivfpq) or None; norms: [N] float32 of the
    reconstructions (0 = unassigned); codebook: the faiss quantiser the codes belong to.

    Where every score is made by the blocked kernels (`blocked_scoring`: an AVX-512 CPU, M ≥ 128), the
    first score lays the codes out blocked and keeps them in that layout only: `codes` is then
    rebuilt on each read (a copy; `code_rows` for a few rows). Until 2026-12-06 both layouts were
    held, M more bytes a Gaussian while a field was queried (2.5 GB of a 20M-Gaussian query)."""

    def __init__(self, codes: np.ndarray, list_ids: np.ndarray | None, norms: np.ndarray, codebook: Codebook):
        self._codes: np.ndarray | None = codes
        self._blocked: np.ndarray | None = None
        self._lock = threading.Lock()  # the layout changes once, under it (`blocked_codes`)
        self._n = int(codes.shape[0])
        self.list_ids = list_ids
        self.norms = norms
        self.codebook = codebook

    def __repr__(self) -> str:
        return f"PQStorage({self.codebook.kind}, {self._n:,} x {self.codebook.m} codes{', blocked' if self._codes is None else ''})"

    @property
    def codes(self) -> np.ndarray:
        """[N, M] uint8: the codes as given, or rebuilt from the blocked layout (a new array) once they are held blocked only."""
        with self._lock:
            return self._codes if self._codes is not None else unblocked_codes(self._blocked, self._n)

    def with_norms(self, norms: np.ndarray) -> "PQStorage":
        """The same codes (in the layout they are held in) with other norms [N]."""
        out = copy.copy(self)
        out.norms = norms
        return out

    def code_rows(self, index: np.ndarray | slice) -> np.ndarray:
        """codes[index] without rebuilding all N rows from the blocked layout."""
        with self._lock:
            if self._codes is not None:
                return self._codes[index]
        rows = row_ids(index, self._n)
        return unblocked_codes(self._blocked, self._n, rows.reshape(-1)).reshape(*rows.shape, self.codebook.m)

    def detached(self) -> "PQStorage":
        """This storage with codes of its own (a copy): none of its arrays is another's view."""
        return PQStorage(self.codes.copy(), self.list_ids, self.norms, self.codebook)

    def blocked_scoring(self, lut_bits: int = 32) -> bool:
        """Whether scores with `lut_bits` tables are made by the blocked kernels."""
        return lut_bits == 8 or (self.codebook.m >= BLOCKED_MIN_M and simd_available())

    @property
    def kind(self) -> str:
        return self.codebook.kind

    @classmethod
    def encode(cls, features: np.ndarray, assigned: np.ndarray, codebook: Codebook | None = None,
               checked: tuple[np.ndarray, np.ndarray] | None = None) -> "PQStorage":
        """Encode [N, D] features in chunks; norms are the reconstruction norms |r_i| (0 where not
        assigned). checked: `unit_check` of the features when the caller made it, else made per chunk."""
        if codebook is None:
            raise ValueError("a PQ field needs a codebook")
        n = features.shape[0]
        codes = np.zeros((n, codebook.m), np.uint8)
        list_ids = np.zeros(n, np.int32) if codebook.kind == "ivfpq" else None
        norms = np.zeros(n, np.float32)
        first = None  # (row, code, list) of the first encoded row, while every code equals its code
        encoded, rows_differ, codes_differ = 0, False, False
        for start in range(0, n, ENCODE_CHUNK):
            stop = min(n, start + ENCODE_CHUNK)
            x = np.asarray(features[start:stop], np.float32)
            ok, off = unit_check(x) if checked is None else (checked[0][start:stop], checked[1][start:stop])
            rows = np.flatnonzero(np.asarray(assigned[start:stop], bool) & ok)  # unassigned rows keep code 0, list 0, norm 0
            if not rows.size:
                continue
            x = x[rows]
            if off[rows].any():  # as the exact backend: rows within codebook.UNIT_TOLERANCE of unit are encoded as given
                x[off[rows]] = unit_rows(x[off[rows]])
            c, ids = codebook.encode(x)
            codes[start + rows] = c
            if list_ids is not None:
                list_ids[start + rows] = ids
            norms[start + rows] = reconstruction_norms(codebook, c, ids)
            encoded += rows.size
            if not codes_differ:  # for a usable codebook settled within the first chunk: nothing more is compared after it
                first = first or (x[0].copy(), c[0].copy(), None if ids is None else ids[0])
                codes_differ = _other_code(c, ids, first[1], first[2])
                rows_differ = rows_differ or bool((x != first[0]).any())
        if rows_differ and not codes_differ and not _tells_directions_apart(codebook):  # not merely features too alike for it
            # faiss assigns codes by float32 squared distances: centroids of 1e20 overflow them to inf, of 1e18 or 1e-20 swamp or
            # vanish beside a unit row's sub-vectors, and every row gets the first code (a codebook scaled by a corrupt or
            # hand-made file; round 46): every Gaussian would score alike, without a word
            scale = float(np.abs(codebook.centroids).max())
            log.warning("%s: the codebook gives all %s features the same code, though they differ: its centroids (largest "
                        "magnitude %.3g) cannot tell unit features apart in faiss's float32 distances (CLIP codebooks' centroids "
                        "are near unit scale), so every Gaussian scores alike", "codebook" if codebook.path is None else shown_path(codebook.path),
                        f"{encoded:,}", scale)
        return cls(codes, list_ids, norms, codebook)

    def norm_mismatches(self, rtol: float = NORM_RTOL) -> np.ndarray:
        """[N] bool: assigned rows whose codes do not reproduce their stored norm (altered codes or norms).

        The stored norm is |r_i| of the reconstruction r_i = decode(codes_i) (`encode`), so it is a
        checksum of the codes that costs no extra bytes. pq: |r_i|² = Σ_m |c_{m, code_im}|² (sub-
        vectors are concatenated), M table look-ups per row; ivfpq: `reconstruction_norms` from the codes
        (the coarse centroid adds cross terms). A flipped code byte is caught unless the two
        centroids of that sub-quantiser have norms within `rtol` (rare: measured in the tests).
        Unassigned rows (norm 0) are not checked; a negative norm, which no encoder writes, counts as altered.
        """
        codes = self.codes
        if self.list_ids is None:
            table = np.square(self.codebook.centroids.astype(np.float64)).sum(axis=2)  # [M, 256]
            recomputed = np.sqrt(code_table_sums(codes, table))
        else:
            recomputed = reconstruction_norms(self.codebook, codes, self.list_ids, np.float64)
        stored = self.norms.astype(np.float64)
        with np.errstate(invalid="ignore"):
            return (stored != 0) & ~(np.abs(recomputed - stored) <= rtol * np.maximum(stored, 1e-12))

    def scores(self, q: np.ndarray, lut_bits: int = 32) -> np.ndarray:
        """On AVX-512 CPUs with M ≥ 128 (and always for lut_bits=8) the codes are scored in their blocked
        layout (`blocked_codes`)."""
        if self.blocked_scoring(lut_bits):
            return lut_scores_blocked(self.codebook, self.blocked_codes(), self._n, self.list_ids, self.norms, q, lut_bits)
        return lut_scores(self.codebook, self.codes, self.list_ids, self.norms, q)

    def blocked_codes(self) -> np.ndarray:
        """The codes in the layout of the blocked kernels, [ceil(N/64), M, 64] uint8, built on first use.
        Where the blocked kernels make every score (`blocked_scoring`), the [N, M] codes are let go then."""
        with self._lock:
            if self._blocked is not None:
                return self._blocked
            if not self.blocked_scoring():
                self._blocked = blocked_codes(self._codes)
            elif self._sole_owner():  # laid out where they lie: never both layouts at once
                codes, self._codes = self._codes, None
                self._blocked = blocked_codes_in_place(codes)
            else:  # a view of the codes is held elsewhere (a scene's columns): copied, then let go
                self._blocked = blocked_codes(self._codes)
                self._codes = None
            return self._blocked

    def _sole_owner(self) -> bool:
        """Whether this storage alone refers to its codes' memory (the array owns it and no view or other
        name refers to the array: CPython's reference count, numpy's own `resize` check), so it can be reused."""
        codes = self._codes
        owner = codes.flags.owndata and codes.flags.c_contiguous and codes.dtype == np.uint8
        del codes
        return bool(owner) and sys.getrefcount(self._codes) == 2  # the attribute and getrefcount's argument

    def scores_reference(self, q: np.ndarray) -> np.ndarray:
        scores = lut_scores_reference(self.codebook, self.codes, self.list_ids, self.norms, q)
        return np.where(has_feature(self.norms)[:, None], scores, 0.0).astype(np.float32)

    def reconstruct(self, index: np.ndarray | slice) -> np.ndarray:
        return self.codebook.decode(self.code_rows(index), None if self.list_ids is None else self.list_ids[index])

    def take(self, index: np.ndarray | slice) -> "PQStorage":
        return PQStorage(self.code_rows(index), None if self.list_ids is None else self.list_ids[index], self.norms[index], self.codebook)

    def bytes_per_gaussian(self) -> int:
        return self.codebook.m + 4 + (4 if self.list_ids is not None else 0)

    def columns(self) -> dict[str, np.ndarray]:
        """`lang_code_0 .. lang_code_{M-1}` uchar, `lang_norm` float, and `lang_list` int for ivfpq."""
        codes = self.codes
        cols = {f"lang_code_{j}": np.ascontiguousarray(codes[:, j], np.uint8) for j in range(codes.shape[1])}
        cols["lang_norm"] = np.ascontiguousarray(self.norms, np.float32)
        if self.list_ids is not None:
            cols["lang_list"] = np.ascontiguousarray(self.list_ids, np.int32)
        return cols

    @classmethod
    def from_columns(cls, get: ColumnGetter, n: int, dim: int, codebook: Codebook | None = None) -> "PQStorage":
        if codebook is None:
            raise ValueError("a PQ field needs its codebook")
        codes = stack_columns([get(f"lang_code_{j}") for j in range(codebook.m)], np.uint8, n, codebook.m)
        norms = get("lang_norm").astype(np.float32)
        list_ids = None
        if codebook.kind == "ivfpq":
            list_ids = get("lang_list").astype(np.int32)
            bad = (list_ids < 0) | (list_ids >= codebook.nlist)
            if np.any(bad):
                raise InputError(None, f"{counted(int(bad.sum()), 'coarse list id falls', 'coarse list ids fall')} outside 0..{codebook.nlist - 1}", field="lang_list")
        return cls(codes, list_ids, norms, codebook)


Storage = ExactStorage | PQStorage

# kind -> backend class. `needs_codebook`: which kinds store codes of a faiss codebook file.
BACKENDS: dict[str, type] = {
    "exact": ExactStorage,
    "pq": PQStorage,
    "ivfpq": PQStorage,
}
KINDS = tuple(BACKENDS)


def needs_codebook(kind: str) -> bool:
    return BACKENDS[kind] is PQStorage


def stack_columns(cols: list[np.ndarray], dtype: type, n: int, width: int) -> np.ndarray:
    """Per-property columns [N] -> one [N, width] array of `dtype`. Columns that are consecutive
    column views of one [N, L] array (what the PLY loader makes of properties side by side in the
    file, `scene.extra_columns_of`, and what a storage's `columns` gives) are that array's slice,
    not copied when it is all of it and of `dtype`; other columns are stacked and transposed in one
    pass (`transpose_copy`: writing each column into the [N, width] array straight took 1.35 s for
    the 512 float16 columns of flowers' exact field). `stack_columns_reference` is the
    column-by-column form."""
    if n == 0 or width == 0:
        return np.empty((n, width), dtype)
    block = _columns_of_one_block(cols, n)
    if block is not None:
        return np.ascontiguousarray(block.astype(dtype, copy=False))
    return transpose_copy(np.stack([np.asarray(col) for col in cols]).astype(dtype, copy=False))


def _columns_of_one_block(cols: list[np.ndarray], n: int) -> np.ndarray | None:
    """The [N, len(cols)] slice of one C-contiguous [N, L] array whose consecutive columns the
    columns [N] are (in order), or None."""
    base = cols[0].base
    if not (isinstance(base, np.ndarray) and base.ndim == 2 and base.flags.c_contiguous and base.shape[0] == n):
        return None
    origin, step = base.__array_interface__["data"][0], base.strides[1]
    first, rest = divmod(cols[0].__array_interface__["data"][0] - origin, step)
    if rest or first < 0 or first + len(cols) > base.shape[1]:
        return None
    for j, col in enumerate(cols):  # each a whole column of base, of its dtype, in order
        if (col.base is not base or col.shape != (n,) or col.dtype != base.dtype or col.strides != base.strides[:1]
                or col.__array_interface__["data"][0] != origin + (first + j) * step):
            return None
    return base if first == 0 and len(cols) == base.shape[1] else base[:, first:first + len(cols)]


def stack_columns_reference(cols: list[np.ndarray], dtype: type, n: int, width: int) -> np.ndarray:
    """`stack_columns` one column at a time."""
    out = np.empty((n, width), dtype)
    for j, col in enumerate(cols):
        out[:, j] = col.astype(dtype, copy=False)
    return out
