"""Look-up-table scoring kernels: [N, M] codes and blocked AVX-512 layouts, float32 or 8-bit tables (docs/index.md).

Every numba kernel has a numpy reference beside it (`*_reference`), tested equal."""

from __future__ import annotations

import functools
import logging

import numba
import numpy as np

from drsplat import defaults
from drsplat.lang.codebook import PQ_KSUB, Codebook

log = logging.getLogger(__name__)



# --------------------------------------------------------------------------------------------
# Scoring kernels


LUT_BLOCK = 1024
FAST = {"nsz", "arcp", "contract"}  # fastmath without nnan/ninf (non-finite norms are tested) and without reassoc: the sums keep
# their written order, so every compile gives the same bits (with reassoc a process that compiled `_lut_scores_kernel_m4`
# scored one ulp off one that loaded it from numba's cache, round 50), and the gathers stay scalar, which is faster here
# The smallest stored norm a row is scored by: float32's smallest normal number. Below it 1/norm
# overflows float32 (a codebook of subnormal centroids scored every row inf, selected and written
# to --scores without a word: a probe, round 29a), so such a row is read as holding no feature.
MIN_NORM = np.float32(defaults.MIN_NORM)


@numba.njit(cache=True)
def _inverse_norm(norm):  # pragma: no cover - jitted
    """1/norm, 0 for norms that are not finite or below MIN_NORM (zero, negative, subnormal):
    `inverse_norms` for one value."""
    if norm >= MIN_NORM and norm < np.inf:
        return np.float32(1.0) / norm
    return np.float32(0.0)


@numba.njit(parallel=True, fastmath=FAST, cache=True, boundscheck=False)
def _lut_scores_kernel(codes, list_ids, luts, coarse, inv_norms, out):  # pragma: no cover - jitted
    """out[i, k] = (coarse[k, list_ids[i]] + Σ_m luts[k, m, codes[i, m]]) · inv_norms[i], any M, the sum in the
    order written (FAST: no reassociation; with it, M = 127 scored 5,754 of 20,000 rows otherwise in a process that
    compiled the kernel than in one that loaded it from the cache, and otherwise on an AVX-512 target: round 68b F2).

    codes: [N, M] uint8; list_ids: [N] int32 (or [0] when coarse is [K, 0]); luts: [K, M, 256].
    """
    n, m = codes.shape
    k_count = luts.shape[0]
    has_coarse = coarse.shape[1] > 0
    for b in numba.prange((n + LUT_BLOCK - 1) // LUT_BLOCK):
        for i in range(b * LUT_BLOCK, min(n, (b + 1) * LUT_BLOCK)):
            row = codes[i]
            for k in range(k_count):
                lut = luts[k]
                acc = np.float32(0.0)
                for j in range(m):
                    acc += lut[j, row[j]]
                if has_coarse:
                    acc += coarse[k, list_ids[i]]
                out[i, k] = acc * inv_norms[i]


@numba.njit(parallel=True, fastmath=FAST, cache=True, boundscheck=False)
def _lut_scores_kernel_m4(words, list_ids, flat_luts, coarse, norms, out):  # pragma: no cover - jitted
    """`_lut_scores_kernel` for M % 4 == 0, reading four codes per 32-bit load.

    words: [N, M/4] uint32 view of the codes (little-endian: code 4w+b is byte b of word w);
    flat_luts: [K, M·256] float32; norms: [N] float32 (1/|r_i| is taken here, 0 for zero or
    non-finite norms: one pass over N fewer than a separate `inverse_norms`).
    Per block of rows, one query's table at a time: the table
    (M KB) stays in L1/L2 and the block's codes (M KB) in L2 while all K queries pass over them;
    four independent accumulators keep the gathers from waiting on one another.
    """
    n, m4 = words.shape
    k_count = flat_luts.shape[0]
    has_coarse = coarse.shape[1] > 0
    for b in numba.prange((n + LUT_BLOCK - 1) // LUT_BLOCK):
        for k in range(k_count):
            lut = flat_luts[k]
            for i in range(b * LUT_BLOCK, min(n, (b + 1) * LUT_BLOCK)):
                row = words[i]
                a0 = np.float32(0.0)
                a1 = np.float32(0.0)
                a2 = np.float32(0.0)
                a3 = np.float32(0.0)
                for j in range(m4):
                    w = row[j]
                    base = j * 1024
                    a0 += lut[base + (w & 255)]
                    a1 += lut[base + 256 + ((w >> 8) & 255)]
                    a2 += lut[base + 512 + ((w >> 16) & 255)]
                    a3 += lut[base + 768 + (w >> 24)]
                acc = (a0 + a1) + (a2 + a3)
                if has_coarse:
                    acc += coarse[k, list_ids[i]]
                out[i, k] = acc * _inverse_norm(norms[i])


HALF_TO_FLOAT_SCALE = np.float32(2.0**112)


@numba.njit(parallel=True, fastmath=True, cache=True, boundscheck=False)
def _half_scores_kernel(bits, q_scaled, inv_norms, out):  # pragma: no cover - jitted
    """out[i, k] = Σ_d half(bits[i, d]) · q[k, d] · inv_norms[i] for float16 features; 0 for a row
    holding an inf or NaN half, whatever its norm.

    bits: [N, D] uint16 float16 bit patterns; q_scaled: [K, D] = q · 2^112.
    half -> float: the sign moves to bit 31 and exponent+mantissa are shifted left by 13 into a
    float32, which is then the half's value times 2^-112 (exact for zero, subnormal and normal
    halves: the float32 exponent range covers them all); the 2^112 is folded into the query.
    An inf or NaN half (exponent bits all set) would read as a finite float32 so: such rows are
    found by their exponent bits (round 56a: with a norm given, not made from the row, they scored
    65536).
    """
    n, d = bits.shape
    k_count = q_scaled.shape[0]
    block = 256
    for b in numba.prange((n + block - 1) // block):
        buf = np.empty(d, np.uint32)
        values = buf.view(np.float32)
        for i in range(b * block, min(n, (b + 1) * block)):
            row = bits[i]
            largest = np.uint32(0)  # of the magnitudes' bits: inf and NaN are the patterns from 0x7C00 up
            for j in range(d):
                h = np.uint32(row[j])
                magnitude = h & np.uint32(0x7FFF)
                buf[j] = (magnitude << np.uint32(13)) | ((h & np.uint32(0x8000)) << np.uint32(16))
                largest = max(largest, magnitude)
            if largest >= np.uint32(0x7C00):
                for k in range(k_count):
                    out[i, k] = 0.0
                continue
            for k in range(k_count):
                qk = q_scaled[k]
                acc = np.float32(0.0)
                for j in range(d):
                    acc += values[j] * qk[j]
                out[i, k] = acc * inv_norms[i]


def half_scores(features: np.ndarray, norms: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Cosine of unit queries [K, D] against float16 features [N, D] with norms [N]: [N, K] float32.

    Zero-norm (unassigned) and non-finite rows score 0.
    """
    queries = np.atleast_2d(np.asarray(queries, np.float32))
    out = np.empty((features.shape[0], queries.shape[0]), np.float32)
    if features.shape[0]:
        bits = np.ascontiguousarray(features, np.float16).view(np.uint16)
        _half_scores_kernel(bits, np.ascontiguousarray(queries * HALF_TO_FLOAT_SCALE), inverse_norms(norms), out)
    return out


def lut_scores(codebook: Codebook, codes: np.ndarray, list_ids: np.ndarray | None, norms: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Cosine of unit queries against PQ reconstructions, by look-up tables.

    cos(q, r_i) = ([q·c_{list_i}] + Σ_m LUT[m, code_im]) / |r_i|, LUT[m, c] = q_m · C[m, c].
    Gaussians with |r_i| = 0 (unassigned) score 0.

    codes: [N, M] uint8, list_ids: [N] int32 or None, norms: [N] float32, queries: [K, D] unit rows.
    Returns [N, K] float32.
    """
    queries = np.atleast_2d(np.asarray(queries, np.float32))
    luts = codebook.luts(queries)
    coarse = codebook.coarse_table(queries)
    ids = np.zeros(0, np.int32) if list_ids is None or codebook.coarse is None else np.ascontiguousarray(list_ids, np.int32)
    out = np.empty((codes.shape[0], queries.shape[0]), np.float32)
    codes = np.ascontiguousarray(codes, np.uint8)
    m = codes.shape[1]
    if m % 4 == 0 and np.little_endian and codes.shape[0] > 0:
        words = codes.view(np.uint32)
        _lut_scores_kernel_m4(words, ids, luts.reshape(luts.shape[0], m * PQ_KSUB), coarse, np.ascontiguousarray(norms, np.float32), out)
    else:
        _lut_scores_kernel(codes, ids, luts, coarse, inverse_norms(norms), out)
    return out


def lut_scores_reference(codebook: Codebook, codes: np.ndarray, list_ids: np.ndarray | None, norms: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Decode-then-cosine reference of `lut_scores` (float64): [N, K] (r_i · q) / |r_i| with the stored |r_i| (`norms`),
    0 for the rows `has_feature` refuses (unassigned: 0; subnormal or non-finite), as the kernel scores them (round 66c F8:
    the decoded rows' own norms gave those rows a full cosine)."""
    recon = codebook.decode(codes, list_ids).astype(np.float64)
    q = np.atleast_2d(np.asarray(queries, np.float64))
    norms = np.asarray(norms, np.float32)
    ok = has_feature(norms)
    inverse = np.where(ok, 1.0 / np.where(ok, norms.astype(np.float64), 1.0), 0.0)
    return ((recon @ q.T) * inverse[:, None]).astype(np.float32)


@numba.njit(parallel=True, cache=True, boundscheck=False)
def _code_table_sums_kernel(codes, table, out):  # pragma: no cover - jitted
    n, m = codes.shape
    for i in numba.prange(n):
        total = 0.0
        for j in range(m):
            total += table[j, codes[i, j]]
        out[i] = total


def code_table_sums(codes: np.ndarray, table: np.ndarray) -> np.ndarray:
    """[N] float64 s_i = Σ_m table[m, codes[i, m]] (codes: [N, M] uint8, table: [M, 256] float64).

    With table[m, k] = |c_{m,k}|² this is |r_i|², the squared norm of a PQ reconstruction (the
    sub-vectors are concatenated). Summed in m order, exactly as `code_table_sums_reference`."""
    codes = np.ascontiguousarray(codes, np.uint8)
    out = np.zeros(codes.shape[0], np.float64)
    if codes.shape[0] and codes.shape[1]:
        _code_table_sums_kernel(codes, np.ascontiguousarray(table, np.float64), out)
    return out


def code_table_sums_reference(codes: np.ndarray, table: np.ndarray) -> np.ndarray:
    """numpy reference of `code_table_sums`: one gather per sub-quantiser."""
    out = np.zeros(codes.shape[0], np.float64)
    for j in range(codes.shape[1]):
        out += table[j, codes[:, j]]
    return out


def has_feature(norms: np.ndarray) -> np.ndarray:
    """[N] bool: the rows whose stored norm [N] is finite and at least MIN_NORM, the rows that hold
    a feature (the others, unassigned, found damaged or too small to score in float32, score 0 and
    are never selected)."""
    norms = np.asarray(norms)
    return np.isfinite(norms) & (norms >= MIN_NORM)


def subnormal_norms(norms: np.ndarray) -> np.ndarray:
    """[N] bool: the rows with a positive stored norm below MIN_NORM, which `has_feature` leaves out
    (their reciprocal overflows float32): a codebook of subnormal centroids, or an altered file."""
    norms = np.asarray(norms)
    return (norms > 0) & (norms < MIN_NORM)


def inverse_norms(norms: np.ndarray) -> np.ndarray:
    """1/|r| with 0 for the norms `has_feature` refuses (zero, subnormal, non-finite): [N] float32."""
    norms = np.asarray(norms, np.float32)
    ok = has_feature(norms)
    return np.where(ok, 1.0 / np.where(ok, norms, 1.0), 0.0).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Blocked kernels: float32 tables (exact) and 8-bit tables (approximate, `lut_bits=8`)


Q8_BLOCK = 64
BLOCKED_MIN_M = 128  # below, the [N, M] kernel is as fast as the float32 blocked one (docs/index.md)
Q8_MAX_M = 257  # M·255 must fit the uint16 sums
Q8_EXACT_SPAN = 4.0  # a sub-table this many times wider than the median one stays float32 (`quantize_luts`)
Q8_EXACT_MAX = 8  # at most this many per query


def blocked_codes(codes: np.ndarray) -> np.ndarray:
    """Codes [N, M] uint8 -> [ceil(N/64), M, 64] uint8: 64 Gaussians' codes of one sub-vector are contiguous.

    Rows past N are zero (their sums are discarded). Built once per field, M bytes per Gaussian.
    """
    codes = np.asarray(codes, np.uint8)
    n, m = codes.shape
    nb = -(-n // Q8_BLOCK)
    out = np.zeros((nb, m, Q8_BLOCK), np.uint8)
    full = n // Q8_BLOCK
    out[:full] = codes[: full * Q8_BLOCK].reshape(full, Q8_BLOCK, m).transpose(0, 2, 1)
    if full < nb:
        out[full, :, : n - full * Q8_BLOCK] = codes[full * Q8_BLOCK :].T
    return out


@numba.njit(parallel=True, cache=True)
def _transpose_blocks_in_place(flat, m, nb):  # pragma: no cover - jitted
    """Each block b of 64 rows x m codes, flat[b·64·m : (b+1)·64·m], rewritten as its m x 64 transpose."""
    size = Q8_BLOCK * m
    for b in numba.prange(nb):
        rows = flat[b * size:(b + 1) * size].copy()
        for r in range(Q8_BLOCK):
            for j in range(m):
                flat[b * size + j * Q8_BLOCK + r] = rows[r * m + j]


def blocked_codes_in_place(codes: np.ndarray) -> np.ndarray:
    """`blocked_codes(codes)` made in the codes' own memory: the array grown to whole blocks (a realloc,
    at most 63 zero rows more) and each block of 64 rows transposed where it lies, so the codes and
    their blocked copy are never held together (2.5 GB of a 20M-Gaussian field). codes: [N, M] uint8,
    C-contiguous, owning its memory, referred to by nothing else (the caller makes sure: a view of it
    would read freed memory after the realloc); it is the blocked array's memory afterwards."""
    n, m = codes.shape
    nb = -(-n // Q8_BLOCK)
    codes.resize((nb * Q8_BLOCK, m), refcheck=False)
    if nb:
        _transpose_blocks_in_place(codes.reshape(-1), m, nb)
    return codes.reshape(nb, m, Q8_BLOCK)


def unblocked_codes(blocked: np.ndarray, n: int, rows: np.ndarray | None = None) -> np.ndarray:
    """The [N, M] codes of `blocked_codes`' layout [ceil(N/64), M, 64] (a copy); rows: [R] ids to take
    only those, [R, M]. `blocked_codes` of the result is `blocked` again (its reference)."""
    if rows is None:
        return np.ascontiguousarray(blocked.transpose(0, 2, 1).reshape(-1, blocked.shape[1])[:n])
    rows = np.asarray(rows, np.int64)
    return np.ascontiguousarray(blocked[rows // Q8_BLOCK, :, rows % Q8_BLOCK])


def quantize_luts(luts: np.ndarray, exact_span: float = Q8_EXACT_SPAN) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """8-bit tables as faiss fast-scan makes them, but for outlying sub-tables:
    luts [K, M, 256] -> (q [K, M, 256] uint8, scale [K], offset [K], exact [K, M] bool).

    LUT[k, m, c] ≈ lo[k, m] + scale[k] · q[k, m, c] with lo[k, m] = min_c LUT[k, m, c] and one
    scale per query, scale[k] = max_m (max_c − min_c LUT[k, m, c]) / 255 over the quantised
    sub-tables, so that Σ_m LUT[k, m, code_m] ≈ offset[k] + scale[k] · Σ_m q[k, m, code_m] +
    Σ_{m exact} LUT[k, m, code_m], offset[k] = Σ_{m not exact} lo[k, m]. Each quantised entry is
    off by at most scale/2, a sum by at most M·scale/2.

    exact: the sub-tables kept in float32 (q = 0 there), those whose span passes `exact_span` times
    the median span (at most Q8_EXACT_MAX, widest first; inf: none, faiss's one scale). A CLIP text embedding has one component
    of 0.6-0.75, which makes one sub-table 12-18x wider than the median: with it in the one scale,
    8-bit scores of the official codebook were 8e-5 to 3e-4 off the float32 tables' on average and
    selected 0.88-0.94 of their top 1 % (a numerical probe, 2026-11-30).
    """
    luts = np.asarray(luts, np.float64)
    lo = luts.min(axis=2)
    spans = luts.max(axis=2) - lo  # [K, M]
    exact = np.zeros(spans.shape, bool)
    if spans.shape[1] > 1:
        median = np.median(spans, axis=1, keepdims=True)
        widest = np.argsort(-spans, axis=1, kind="stable")[:, :Q8_EXACT_MAX]
        outlying = np.take_along_axis(spans, widest, axis=1) > exact_span * median
        np.put_along_axis(exact, widest, outlying, axis=1)
    span = np.where(exact, 0.0, spans).max(axis=1)
    scale = np.where(span > 0, span / 255.0, 1.0)
    q = np.clip(np.rint((luts - lo[:, :, None]) / scale[:, None, None]), 0, 255).astype(np.uint8)
    q[exact] = 0
    return q, scale.astype(np.float32), np.where(exact, 0.0, lo).sum(axis=1).astype(np.float32), exact


@numba.njit(parallel=True, cache=True, boundscheck=False)
def _exact_tables_kernel(blocked, columns, tables, n, norms, out, k):  # pragma: no cover - jitted
    """out[i, k] += Σ_j tables[j, blocked[i // 64, columns[j], i % 64]] / |r_i| (float64 sums, added
    to the 8-bit scores: the sub-tables `quantize_luts` kept in float32; 0 where |r_i| is not a norm)."""
    for b in numba.prange(blocked.shape[0]):
        for t in range(min(Q8_BLOCK, n - b * Q8_BLOCK)):
            i = b * Q8_BLOCK + t
            r = norms[i]
            if not (r >= MIN_NORM and r < np.inf):
                continue
            total = 0.0  # in a register: the block's few rows of codes stay in cache across its 64 Gaussians
            for j in range(columns.shape[0]):
                total += tables[j, blocked[b, columns[j], t]]
            out[i, k] = np.float32(out[i, k] + total / r)


@numba.njit(parallel=True, fastmath=FAST, cache=True, boundscheck=False)
def _table_sums_kernel(blocked, table, out):  # pragma: no cover - jitted
    """out[64·b + t] = Σ_m table[m, blocked[b, m, t]], accumulated in out's dtype, in m order.

    blocked: [NB, M, 64] uint8; table: [M, 256] uint8 (8-bit tables, exact integer sums in
    out: uint16) or float32 (out: float32). Portable twin of the AVX-512 kernels.
    """
    nb, m, width = blocked.shape
    for b in numba.prange(nb):
        acc = np.zeros(width, out.dtype)
        for j in range(m):
            row = blocked[b, j]
            lut = table[j]
            for t in range(width):
                acc[t] += lut[row[t]]
        out[b * width : (b + 1) * width] = acc


_VBMI_IR = r"""
declare <64 x i8> @llvm.x86.avx512.vpermi2var.qi.512(<64 x i8>, <64 x i8>, <64 x i8>)

define void @q8_sums(i8* %codes, i8* %lut, i16* %out, i64 %b0, i64 %b1, i64 %m) {
entry:
  br label %bloop
bloop:
  %b = phi i64 [%b0, %entry], [%bn, %mend]
  %bdone = icmp sge i64 %b, %b1
  br i1 %bdone, label %exit, label %bbody
bbody:
  %boff = mul i64 %b, %m
  %boff64 = mul i64 %boff, 64
  br label %mloop
mloop:
  %j = phi i64 [0, %bbody], [%jn, %mloop]
  %acc0 = phi <32 x i16> [zeroinitializer, %bbody], [%acc0n, %mloop]
  %acc1 = phi <32 x i16> [zeroinitializer, %bbody], [%acc1n, %mloop]
  %coff = mul i64 %j, 64
  %cidx = add i64 %boff64, %coff
  %cp = getelementptr i8, i8* %codes, i64 %cidx
  %cpv = bitcast i8* %cp to <64 x i8>*
  %idx = load <64 x i8>, <64 x i8>* %cpv, align 1
  %loff = mul i64 %j, 256
  %lp = getelementptr i8, i8* %lut, i64 %loff
  %lp0 = bitcast i8* %lp to <64 x i8>*
  %lp1 = getelementptr <64 x i8>, <64 x i8>* %lp0, i64 1
  %lp2 = getelementptr <64 x i8>, <64 x i8>* %lp0, i64 2
  %lp3 = getelementptr <64 x i8>, <64 x i8>* %lp0, i64 3
  %t0 = load <64 x i8>, <64 x i8>* %lp0, align 1
  %t1 = load <64 x i8>, <64 x i8>* %lp1, align 1
  %t2 = load <64 x i8>, <64 x i8>* %lp2, align 1
  %t3 = load <64 x i8>, <64 x i8>* %lp3, align 1
  %lo = call <64 x i8> @llvm.x86.avx512.vpermi2var.qi.512(<64 x i8> %t0, <64 x i8> %idx, <64 x i8> %t1)
  %hi = call <64 x i8> @llvm.x86.avx512.vpermi2var.qi.512(<64 x i8> %t2, <64 x i8> %idx, <64 x i8> %t3)
  %neg = icmp slt <64 x i8> %idx, zeroinitializer
  %v = select <64 x i1> %neg, <64 x i8> %hi, <64 x i8> %lo
  %vl = shufflevector <64 x i8> %v, <64 x i8> undef, <32 x i32> <LOW>
  %vh = shufflevector <64 x i8> %v, <64 x i8> undef, <32 x i32> <HIGH>
  %wl = zext <32 x i8> %vl to <32 x i16>
  %wh = zext <32 x i8> %vh to <32 x i16>
  %acc0n = add <32 x i16> %acc0, %wl
  %acc1n = add <32 x i16> %acc1, %wh
  %jn = add i64 %j, 1
  %jdone = icmp eq i64 %jn, %m
  br i1 %jdone, label %mend, label %mloop
mend:
  %ooff = mul i64 %b, 64
  %op = getelementptr i16, i16* %out, i64 %ooff
  %op0 = bitcast i16* %op to <32 x i16>*
  %op1 = getelementptr <32 x i16>, <32 x i16>* %op0, i64 1
  store <32 x i16> %acc0n, <32 x i16>* %op0, align 2
  store <32 x i16> %acc1n, <32 x i16>* %op1, align 2
  %bn = add i64 %b, 1
  br label %bloop
exit:
  ret void
}
""".replace("<LOW>", "<" + ", ".join(f"i32 {i}" for i in range(32)) + ">").replace(
    "<HIGH>", "<" + ", ".join(f"i32 {i}" for i in range(32, 64)) + ">"
)


def _f32_sums_ir() -> str:
    """LLVM IR of `f32_sums(codes, lut, out, b0, b1, m)`: out[64·b + t] = Σ_j lut[j, codes[b, j, t]] for
    blocks b0 ≤ b < b1, float32 tables [M, 256], AVX-512F.

    A sub-vector's 256-float table sits in sixteen 16-float registers; `vpermi2ps` looks up 16 codes
    in a pair of them (code bits 0–4), and bits 5, 6, 7 pick among the eight pairs by three rounds
    of selects. Four groups of 16 Gaussians (a block of 64) share the loaded table.
    """
    lines = [
        "declare <16 x float> @llvm.x86.avx512.vpermi2var.ps.512(<16 x float>, <16 x i32>, <16 x float>)",
        "define void @f32_sums(i8* %codes, float* %lut, float* %out, i64 %b0, i64 %b1, i64 %m) {",
        "entry:\n  br label %bloop",
        "bloop:\n  %b = phi i64 [%b0, %entry], [%bn, %mend]\n  %bdone = icmp sge i64 %b, %b1\n  br i1 %bdone, label %exit, label %bbody",
        "bbody:\n  %boff = mul i64 %b, %m\n  %boff64 = mul i64 %boff, 64\n  br label %mloop",
        "mloop:\n  %j = phi i64 [0, %bbody], [%jn, %mloop]",
    ]
    add = lines.append
    for g in range(4):
        add(f"  %acc{g} = phi <16 x float> [zeroinitializer, %bbody], [%accn{g}, %mloop]")
    add("  %coff = mul i64 %j, 64\n  %cidx = add i64 %boff64, %coff\n  %cp = getelementptr i8, i8* %codes, i64 %cidx")
    add("  %loff = mul i64 %j, 256\n  %lp = getelementptr float, float* %lut, i64 %loff\n  %lpv = bitcast float* %lp to <16 x float>*")
    for t in range(16):
        add(f"  %tp{t} = getelementptr <16 x float>, <16 x float>* %lpv, i64 {t}\n  %t{t} = load <16 x float>, <16 x float>* %tp{t}, align 4")
    for g in range(4):
        add(f"  %ip{g} = getelementptr i8, i8* %cp, i64 {16 * g}\n  %ipv{g} = bitcast i8* %ip{g} to <16 x i8>*")
        add(f"  %i8_{g} = load <16 x i8>, <16 x i8>* %ipv{g}, align 1\n  %ix{g} = zext <16 x i8> %i8_{g} to <16 x i32>")
        for p in range(8):
            add(f"  %r{g}_{p} = call <16 x float> @llvm.x86.avx512.vpermi2var.ps.512(<16 x float> %t{2 * p}, <16 x i32> %ix{g}, <16 x float> %t{2 * p + 1})")
        for bit, name in ((32, "b5"), (64, "b6"), (128, "b7")):
            mask = ", ".join([f"i32 {bit}"] * 16)
            add(f"  %{name}a{g} = and <16 x i32> %ix{g}, <{mask}>\n  %{name}{g} = icmp ne <16 x i32> %{name}a{g}, zeroinitializer")
        for q in range(4):
            add(f"  %s{g}_{q} = select <16 x i1> %b5{g}, <16 x float> %r{g}_{2 * q + 1}, <16 x float> %r{g}_{2 * q}")
        for q in range(2):
            add(f"  %u{g}_{q} = select <16 x i1> %b6{g}, <16 x float> %s{g}_{2 * q + 1}, <16 x float> %s{g}_{2 * q}")
        add(f"  %v{g} = select <16 x i1> %b7{g}, <16 x float> %u{g}_1, <16 x float> %u{g}_0")
        add(f"  %accn{g} = fadd <16 x float> %acc{g}, %v{g}")
    add("  %jn = add i64 %j, 1\n  %jdone = icmp eq i64 %jn, %m\n  br i1 %jdone, label %mend, label %mloop")
    add("mend:\n  %ooff = mul i64 %b, 64\n  %op = getelementptr float, float* %out, i64 %ooff\n  %opv = bitcast float* %op to <16 x float>*")
    for g in range(4):
        add(f"  %o{g} = getelementptr <16 x float>, <16 x float>* %opv, i64 {g}\n  store <16 x float> %accn{g}, <16 x float>* %o{g}, align 4")
    add("  %bn = add i64 %b, 1\n  br label %bloop\nexit:\n  ret void\n}")
    return "\n".join(lines)


SIMD_KERNELS = {"q8_sums": (("avx512bw", "avx512vbmi"), lambda: _VBMI_IR), "f32_sums": (("avx512f",), _f32_sums_ir)}


@functools.lru_cache(maxsize=None)
def _simd_kernel(name: str):
    """The AVX-512 kernel `name` of `SIMD_KERNELS` as a parallel numba function (blocked, table, out),
    or None when the CPU lacks the instructions.

    q8_sums: `_table_sums_kernel` with VBMI byte shuffles: each sub-vector's 256-entry uint8 table
    sits in four 64-byte registers, two `vpermi2b` look up its low and high halves for 64
    Gaussians at once and bit 7 of the code picks between them (faiss fast-scan does the same
    with 16-entry tables and 4-bit codes). f32_sums: see `_f32_sums_ir`.
    Compiled once from LLVM IR by llvmlite (which numba ships); numba's `prange` calls it over
    chunks of blocks.
    """
    import ctypes

    import llvmlite.binding as llvm

    needs, make_ir = SIMD_KERNELS[name]
    features = llvm.get_host_cpu_features()
    if not all(features.get(f) for f in needs):
        return None
    llvm.initialize_native_target()
    llvm.initialize_native_asmprinter()
    module = llvm.parse_assembly(make_ir())
    module.verify()
    machine = llvm.Target.from_default_triple().create_target_machine(cpu=llvm.get_host_cpu_name(), features=features.flatten(), opt=3)
    engine = llvm.create_mcjit_compiler(module, machine)
    engine.finalize_object()
    c_int64, c_void_p = ctypes.c_int64, ctypes.c_void_p
    scan = ctypes.CFUNCTYPE(None, c_void_p, c_void_p, c_void_p, c_int64, c_int64, c_int64)(engine.get_function_address(name))

    @numba.njit(parallel=True)
    def run_blocks(blocked, table, sums, scale, offset, coarse_k, list_ids, norms, out, k):  # pragma: no cover - jitted
        """sums [NB·64] of every block, then out[:, k] rescaled chunk by chunk (one parallel region)."""
        nb, m = blocked.shape[0], blocked.shape[1]
        n = out.shape[0]
        chunks = min(nb, 8 * numba.get_num_threads())
        for c in numba.prange(chunks):
            b0, b1 = c * nb // chunks, (c + 1) * nb // chunks
            scan(blocked.ctypes.data, table.ctypes.data, sums.ctypes.data, b0, b1, m)
            _rescale_range(sums, scale, offset, coarse_k, list_ids, norms, out, k, b0 * 64, min(n, b1 * 64))

    run_blocks.engine = engine  # the machine code lives as long as the engine
    return run_blocks


def simd_available() -> bool:
    """Whether the AVX-512 float32 blocked kernel runs on this CPU."""
    return _simd_kernel("f32_sums") is not None


def simd_q8_available() -> bool:
    """Whether the AVX-512 VBMI 8-bit blocked kernel runs on this CPU (avx512bw and avx512vbmi: not on Skylake-SP or
    Cascade Lake, whose float32 kernel runs all the same)."""
    return _simd_kernel("q8_sums") is not None


def q8_sums(blocked: np.ndarray, qlut: np.ndarray, use_simd: bool = True) -> np.ndarray:
    """Σ_m qlut[m, code_im] for every Gaussian of blocked codes [NB, M, 64]: [NB·64] uint16.

    Uses the VBMI kernel when the CPU has it (and `use_simd`), else the portable numba kernel;
    both give the same integers.
    """
    m = blocked.shape[1]
    if not 1 <= m <= Q8_MAX_M:
        raise ValueError(f"8-bit look-up tables need 1 ≤ M ≤ {Q8_MAX_M}, got M = {m}")
    return _table_sums("q8_sums", blocked, np.ascontiguousarray(qlut, np.uint8), np.uint16, use_simd)


def f32_sums(blocked: np.ndarray, lut: np.ndarray, use_simd: bool = True) -> np.ndarray:
    """Σ_m lut[m, code_im] for every Gaussian of blocked codes [NB, M, 64], float32 tables [M, 256]: [NB·64] float32.

    Uses the AVX-512 kernel when the CPU has it (and `use_simd`), else the portable numba kernel.
    """
    if blocked.shape[1] < 1:
        raise ValueError("look-up tables need M ≥ 1 sub-vectors")
    return _table_sums("f32_sums", blocked, np.ascontiguousarray(lut, np.float32), np.float32, use_simd)


def _table_sums(kernel: str, blocked: np.ndarray, table: np.ndarray, dtype, use_simd: bool) -> np.ndarray:
    """Run the SIMD kernel `kernel` of `SIMD_KERNELS` when available, else `_table_sums_kernel`."""
    blocked = np.ascontiguousarray(blocked, np.uint8)
    out = np.empty(blocked.shape[0] * Q8_BLOCK, dtype)
    if blocked.shape[0] == 0:
        return out
    simd = _simd_kernel(kernel) if use_simd else None
    if simd is None:
        _table_sums_kernel(blocked, table, out)
    else:
        none = np.zeros(0, np.int32)
        simd(blocked, table, out, np.float32(1), np.float32(0), np.zeros(0, np.float32), none, np.zeros(0, np.float32), np.zeros((0, 1), np.float32), 0)
    return out


@numba.njit(cache=True, boundscheck=False)
def _rescale_range(sums, scale, offset, coarse_k, list_ids, norms, out, k, i0, i1):  # pragma: no cover - jitted
    """out[i, k] = (offset + scale · sums[i] [+ coarse_k[list_ids[i]]]) / norms[i] for i0 ≤ i < i1 (0 for zero or non-finite norms)."""
    has_coarse = coarse_k.shape[0] > 0
    for i in range(i0, i1):
        acc = offset + scale * np.float32(sums[i])
        if has_coarse:
            acc += coarse_k[list_ids[i]]
        out[i, k] = acc * _inverse_norm(norms[i])


@numba.njit(parallel=True, cache=True, boundscheck=False)
def _q8_rescale_kernel(sums, scale, offset, coarse_k, list_ids, norms, out, k):  # pragma: no cover - jitted
    """`_rescale_range` over all N, parallel over chunks of 4,096."""
    n = out.shape[0]
    for c in numba.prange((n + 4095) // 4096):
        _rescale_range(sums, scale, offset, coarse_k, list_ids, norms, out, k, c * 4096, min(n, (c + 1) * 4096))


def lut_scores_blocked(
    codebook: Codebook,
    blocked: np.ndarray,
    n: int,
    list_ids: np.ndarray | None,
    norms: np.ndarray,
    queries: np.ndarray,
    lut_bits: int = 32,
    use_simd: bool = True,
    exact_span: float = Q8_EXACT_SPAN,
) -> np.ndarray:
    """`lut_scores` on blocked codes, with float32 tables (lut_bits=32, exact up to float32 rounding)
    or 8-bit tables (lut_bits=8, `quantize_luts` with `exact_span`: an approximation, off by at most
    M·scale/2 / |r_i|).

    blocked: [ceil(N/64), M, 64] from `blocked_codes`; n: N; list_ids: [N] int32 or None;
    norms: [N]; queries: [K, D] unit rows. Returns [N, K] float32.
    """
    if lut_bits not in (8, 32):
        raise ValueError(f"lut_bits must be 8 or 32, got {lut_bits}")
    queries = np.atleast_2d(np.asarray(queries, np.float32))
    luts = codebook.luts(queries)
    if lut_bits == 8:
        tables, scale, offset, exact = quantize_luts(luts, exact_span)
    else:
        tables, scale, offset = luts, np.ones(len(queries), np.float32), np.zeros(len(queries), np.float32)
        exact = np.zeros(luts.shape[:2], bool)
    coarse = codebook.coarse_table(queries)
    ids = np.zeros(0, np.int32) if list_ids is None or codebook.coarse is None else np.ascontiguousarray(list_ids, np.int32)
    norms = np.ascontiguousarray(norms, np.float32)
    if blocked.shape[0] != -(-n // Q8_BLOCK) or norms.shape[0] != n:
        raise ValueError(f"blocked codes {blocked.shape} and norms {norms.shape} do not hold N = {n} Gaussians")
    out = np.empty((n, queries.shape[0]), np.float32)
    simd = _simd_kernel("q8_sums" if lut_bits == 8 else "f32_sums") if use_simd and blocked.shape[0] else None
    if lut_bits == 8 and not 1 <= blocked.shape[1] <= Q8_MAX_M:
        raise ValueError(f"8-bit look-up tables need 1 ≤ M ≤ {Q8_MAX_M}, got M = {blocked.shape[1]}")
    blocked = np.ascontiguousarray(blocked, np.uint8)
    sums = np.empty(blocked.shape[0] * Q8_BLOCK, np.uint16 if lut_bits == 8 else np.float32)
    for k in range(queries.shape[0]):
        table = np.ascontiguousarray(tables[k], np.uint8 if lut_bits == 8 else np.float32)
        coarse_k = np.ascontiguousarray(coarse[k]) if ids.shape[0] else np.zeros(0, np.float32)
        if simd is not None:
            simd(blocked, table, sums, scale[k], offset[k], coarse_k, ids, norms, out, k)
        else:
            sums = q8_sums(blocked, table, False) if lut_bits == 8 else f32_sums(blocked, table, False)
            _q8_rescale_kernel(sums, scale[k], offset[k], coarse_k, ids, norms, out, k)
        if exact[k].any():
            columns = np.flatnonzero(exact[k]).astype(np.int64)
            _exact_tables_kernel(blocked, columns, np.ascontiguousarray(luts[k, columns], np.float64), n, norms, out, k)
    return out


def lut_scores_q8_reference(codebook: Codebook, codes: np.ndarray, list_ids: np.ndarray | None, norms: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Numpy reference of `lut_scores_blocked(..., lut_bits=8)` from codes [N, M]: gather the 8-bit tables, rescale (float64)."""
    queries = np.atleast_2d(np.asarray(queries, np.float32))
    luts = codebook.luts(queries)
    qluts, scale, offset, exact = quantize_luts(luts)
    codes = np.asarray(codes, np.intp)
    m = codes.shape[1]
    sums = qluts[:, np.arange(m)[None, :], codes].astype(np.int64).sum(axis=2).T  # [N, K]
    kept = np.where(exact[:, None, :], luts[:, np.arange(m)[None, :], codes].astype(np.float64), 0.0).sum(axis=2).T  # [N, K]
    dots = offset.astype(np.float64) + scale.astype(np.float64) * sums + kept
    if list_ids is not None and codebook.coarse is not None:
        dots = dots + codebook.coarse_table(queries).T[np.asarray(list_ids, np.intp)]
    return (dots * inverse_norms(norms)[:, None]).astype(np.float32)


