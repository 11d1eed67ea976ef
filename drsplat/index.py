"""The language field of a registered scene: storage backends, look-up-table scoring, PLY encoding.

Backends (`LanguageField.kind`):
- `exact`: features [N, D] stored as float16.
- `pq`: faiss product quantiser (`IndexPQ`), M sub-vectors x 8 bits, codes [N, M] uint8.
- `ivfpq`: faiss `IndexIVFPQ` (the official Dr. Splat codebook): a coarse list id per Gaussian plus
  a residual PQ code, reconstruction r = c[list] + Σ_m C[m, code_m].

Every backend scores a unit query q against Gaussian i by the cosine q·r_i / |r_i|, where r_i is
the stored (or reconstructed) feature and |r_i| is computed once. PQ backends never decode the
features to answer a query: a [M, 256] table of sub-vector inner products is gathered and summed
over the codes (`lut_scores` on the [N, M] codes; `lut_scores_blocked` on a blocked copy with
AVX-512 table look-ups, float32 tables or, optionally, 8-bit tables), see docs/index.md.

The registered PLY carries the field in extra vertex properties and a header comment
(docs/ARCHITECTURE.md, "The registered PLY"); the codebook file sits next to the PLY.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote, unquote

import numba
import numpy as np

from drsplat.errors import InputError
from drsplat.scene import GaussianScene
from drsplat.utils import atomic_path

log = logging.getLogger(__name__)

COMMENT_PREFIX = "drsplat.lang"
KINDS = ("exact", "pq", "ivfpq")
PQ_BITS = 8
PQ_KSUB = 1 << PQ_BITS
ENCODE_CHUNK = 65536
EXACT_CHUNK = 32768
SCENE_MIN_TRAIN = 10 * PQ_KSUB
SCENE_FEATURE_SAMPLE = 20000


def _faiss():
    """faiss, imported quietly (its loader logs its SIMD probing at INFO level)."""
    logging.getLogger("faiss.loader").setLevel(logging.WARNING)
    import faiss

    return faiss


# --------------------------------------------------------------------------------------------
# Codebooks


@dataclass
class Codebook:
    """A loaded faiss product quantiser (`IndexPQ`) or `IndexIVFPQ`, as plain arrays.

    centroids: [M, 256, dsub] float32 sub-quantiser centroids (dsub = D / M).
    coarse: [nlist, D] float32 coarse centroids (ivfpq with residual encoding), else None.
    """

    kind: str
    dim: int
    m: int
    centroids: np.ndarray
    coarse: np.ndarray | None
    index: object
    path: Path | None = None
    owner: object = dataclasses.field(default=None, repr=False)  # keeps faiss's owning wrapper alive

    @property
    def dsub(self) -> int:
        return self.dim // self.m

    @property
    def nlist(self) -> int:
        return 0 if self.coarse is None else int(self.coarse.shape[0])

    def encode(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Codes of vectors x: [n, D] -> (codes [n, M] uint8, list_ids [n] int32 or None).

        ivfpq: list = argmax_l (x · c_l) (inner-product coarse quantiser), code = PQ(x − c_list).
        """
        x = np.ascontiguousarray(x, dtype=np.float32)
        if self.kind == "pq":
            return self.index.pq.compute_codes(x), None
        faiss = _faiss()

        _, assign = faiss.downcast_index(self.index.quantizer).search(x, 1)
        list_ids = assign[:, 0].astype(np.int32)
        residual = x - self.coarse[list_ids] if self.index.by_residual else x
        return self.index.pq.compute_codes(np.ascontiguousarray(residual)), list_ids

    def decode(self, codes: np.ndarray, list_ids: np.ndarray | None = None) -> np.ndarray:
        """Reconstructions r = [c[list] +] concat_m C[m, code_m]: codes [n, M] -> [n, D] float32."""
        parts = self.centroids[np.arange(self.m), codes.astype(np.intp)]  # [n, M, dsub]
        recon = parts.reshape(codes.shape[0], self.dim)
        if self.coarse is not None:
            recon = recon + self.coarse[list_ids]
        return recon.astype(np.float32, copy=False)

    def luts(self, queries: np.ndarray) -> np.ndarray:
        """Look-up tables LUT[k, m, c] = q_k[m-th sub-vector] · C[m, c]: queries [K, D] -> [K, M, 256]."""
        q = np.asarray(queries, dtype=np.float32).reshape(-1, self.m, self.dsub)
        return np.ascontiguousarray(np.einsum("kmd,mcd->kmc", q, self.centroids, optimize=True), dtype=np.float32)

    def coarse_table(self, queries: np.ndarray) -> np.ndarray:
        """Coarse table q_k · c_l: queries [K, D] -> [K, nlist] float32 (empty [K, 0] for pq)."""
        if self.coarse is None:
            return np.zeros((queries.shape[0], 0), np.float32)
        # einsum's own loop: a [K, D] x [D, nlist] BLAS call waits on BLAS threads, 10x slower on a busy machine
        return np.ascontiguousarray(np.einsum("kd,ld->kl", np.asarray(queries, np.float32), self.coarse), dtype=np.float32)

    def save(self, path: str | Path) -> None:
        faiss = _faiss()

        with atomic_path(path) as tmp:
            faiss.write_index(self.index, str(tmp))


def codebook_from_index(index: object, path: Path | None = None) -> Codebook:
    """Wrap a faiss IndexPQ / IndexIVFPQ (8-bit codes) as a Codebook; InputError otherwise."""
    faiss = _faiss()

    owner = index
    index = faiss.downcast_index(index)
    if isinstance(index, faiss.IndexIVFPQ):
        kind = "ivfpq"
    elif isinstance(index, faiss.IndexPQ):
        kind = "pq"
    else:
        raise InputError(path, f"unsupported faiss index type {type(index).__name__}; expected IndexPQ or IndexIVFPQ")
    if not index.is_trained:
        raise InputError(path, "the faiss index is not trained")
    pq = index.pq
    if pq.nbits != PQ_BITS:
        raise InputError(path, f"PQ codes have {pq.nbits} bits; drsplat stores 8-bit codes only")
    centroids = faiss.vector_to_array(pq.centroids).reshape(pq.M, pq.ksub, pq.dsub).astype(np.float32)
    coarse = None
    if kind == "ivfpq":
        quantizer = faiss.downcast_index(index.quantizer)
        coarse = quantizer.reconstruct_n(0, quantizer.ntotal).astype(np.float32)
        if not index.by_residual:
            coarse = None
    return Codebook(kind=kind, dim=int(index.d), m=int(pq.M), centroids=centroids, coarse=coarse, index=index, path=path, owner=owner)


def load_codebook(path: str | Path) -> Codebook:
    """Read a faiss codebook file (IndexPQ from `drsplat pq train`, or the official IndexIVFPQ)."""
    faiss = _faiss()

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "codebook file not found")
    try:
        index = faiss.read_index(str(path))
    except RuntimeError as exc:
        raise InputError(path, f"not a faiss index file ({str(exc).splitlines()[0][:200]})") from None
    return codebook_from_index(index, path)


def train_codebook(embeddings: np.ndarray, m: int = 128, seed: int = 0) -> Codebook:
    """Train a faiss IndexPQ (inner product, M sub-vectors x 8 bits) on embeddings [n, D].

    Each sub-quantiser is a 256-centroid k-means over its D/M-dimensional slice. Rows are
    L2-normalised first (CLIP embeddings are compared by cosine).
    """
    faiss = _faiss()

    x = unit_rows(np.asarray(embeddings, np.float32))
    n, d = x.shape
    if m <= 0 or d % m:
        raise InputError(None, f"M={m} sub-vectors do not divide the embedding dimension {d}")
    if n < PQ_KSUB:
        raise InputError(None, f"training a PQ codebook needs at least {PQ_KSUB} embeddings, got {n}")
    index = faiss.IndexPQ(d, m, PQ_BITS, faiss.METRIC_INNER_PRODUCT)
    index.pq.cp.seed = seed
    index.pq.cp.max_points_per_centroid = 256
    index.pq.cp.min_points_per_centroid = 1  # small scene sets are fine; faiss would warn per sub-quantiser
    # Each sub-quantiser's k-means is too small to share between threads: OpenMP barriers made
    # training 8x slower on a busy 2-core machine, one thread is as fast on an idle one.
    previous = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(1)
    try:
        index.train(np.ascontiguousarray(x))
    finally:
        faiss.omp_set_num_threads(previous)
    return codebook_from_index(index)


def unit_rows(x: np.ndarray) -> np.ndarray:
    """Rows divided by their L2 norm (zero rows stay zero): [K, D] float32."""
    x = np.atleast_2d(np.asarray(x, np.float32))
    norm = np.linalg.norm(x, axis=1, keepdims=True)
    return np.where(norm > 0, x / np.where(norm > 0, norm, 1), 0).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Scoring kernels


LUT_BLOCK = 1024
FAST = {"reassoc", "nsz", "arcp", "contract"}  # fastmath without nnan/ninf: non-finite norms are tested


@numba.njit(cache=True)
def _inverse_norm(norm):  # pragma: no cover - jitted
    """1/norm, 0 for zero, negative or non-finite norms (`inverse_norms` for one value)."""
    if norm > 0 and norm < np.inf:
        return np.float32(1.0) / norm
    return np.float32(0.0)


@numba.njit(parallel=True, fastmath=True, cache=True, boundscheck=False)
def _lut_scores_kernel(codes, list_ids, luts, coarse, inv_norms, out):  # pragma: no cover - jitted
    """out[i, k] = (coarse[k, list_ids[i]] + Σ_m luts[k, m, codes[i, m]]) · inv_norms[i], any M.

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
    """out[i, k] = Σ_d half(bits[i, d]) · q[k, d] · inv_norms[i] for float16 features.

    bits: [N, D] uint16 float16 bit patterns; q_scaled: [K, D] = q · 2^112.
    half -> float: the sign moves to bit 31 and exponent+mantissa are shifted left by 13 into a
    float32, which is then the half's value times 2^-112 (exact for zero, subnormal and normal
    halves: the float32 exponent range covers them all); the 2^112 is folded into the query.
    """
    n, d = bits.shape
    k_count = q_scaled.shape[0]
    block = 256
    for b in numba.prange((n + block - 1) // block):
        buf = np.empty(d, np.uint32)
        values = buf.view(np.float32)
        for i in range(b * block, min(n, (b + 1) * block)):
            row = bits[i]
            for j in range(d):
                h = np.uint32(row[j])
                buf[j] = ((h & np.uint32(0x7FFF)) << np.uint32(13)) | ((h & np.uint32(0x8000)) << np.uint32(16))
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
    """Decode-then-cosine reference of `lut_scores` (float64): [N, K]."""
    recon = codebook.decode(codes, list_ids).astype(np.float64)
    q = np.atleast_2d(np.asarray(queries, np.float64))
    norm = np.linalg.norm(recon, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        scores = (recon @ q.T) / norm[:, None]
    return np.where(norm[:, None] > 0, scores, 0.0).astype(np.float32)


def inverse_norms(norms: np.ndarray) -> np.ndarray:
    """1/|r| with 0 for zero (or non-finite) norms: [N] float32."""
    norms = np.asarray(norms, np.float32)
    ok = np.isfinite(norms) & (norms > 0)
    return np.where(ok, 1.0 / np.where(ok, norms, 1.0), 0.0).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Blocked kernels: float32 tables (exact) and 8-bit tables (approximate, `lut_bits=8`)


Q8_BLOCK = 64
BLOCKED_MIN_M = 128  # below, the [N, M] kernel is as fast as the float32 blocked one (docs/index.md)
Q8_MAX_M = 257  # M·255 must fit the uint16 sums


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


def quantize_luts(luts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """8-bit tables as faiss fast-scan makes them: luts [K, M, 256] -> (q [K, M, 256] uint8, scale [K], offset [K]).

    LUT[k, m, c] ≈ lo[k, m] + scale[k] · q[k, m, c] with lo[k, m] = min_c LUT[k, m, c] and one
    scale per query, scale[k] = max_m (max_c − min_c LUT[k, m, c]) / 255, so that
    Σ_m LUT[k, m, code_m] ≈ offset[k] + scale[k] · Σ_m q[k, m, code_m], offset[k] = Σ_m lo[k, m].
    Each entry is off by at most scale/2, a sum of M entries by at most M·scale/2.
    """
    luts = np.asarray(luts, np.float64)
    lo = luts.min(axis=2)
    span = (luts.max(axis=2) - lo).max(axis=1)
    scale = np.where(span > 0, span / 255.0, 1.0)
    q = np.clip(np.rint((luts - lo[:, :, None]) / scale[:, None, None]), 0, 255).astype(np.uint8)
    return q, scale.astype(np.float32), lo.sum(axis=1).astype(np.float32)


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
) -> np.ndarray:
    """`lut_scores` on blocked codes, with float32 tables (lut_bits=32, exact up to float32 rounding)
    or 8-bit tables (lut_bits=8, `quantize_luts`: an approximation, off by at most M·scale/2 / |r_i|).

    blocked: [ceil(N/64), M, 64] from `blocked_codes`; n: N; list_ids: [N] int32 or None;
    norms: [N]; queries: [K, D] unit rows. Returns [N, K] float32.
    """
    if lut_bits not in (8, 32):
        raise ValueError(f"lut_bits must be 8 or 32, got {lut_bits}")
    queries = np.atleast_2d(np.asarray(queries, np.float32))
    luts = codebook.luts(queries)
    if lut_bits == 8:
        tables, scale, offset = quantize_luts(luts)
    else:
        tables, scale, offset = luts, np.ones(len(queries), np.float32), np.zeros(len(queries), np.float32)
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
            continue
        sums = q8_sums(blocked, table, False) if lut_bits == 8 else f32_sums(blocked, table, False)
        _q8_rescale_kernel(sums, scale[k], offset[k], coarse_k, ids, norms, out, k)
    return out


def lut_scores_q8_reference(codebook: Codebook, codes: np.ndarray, list_ids: np.ndarray | None, norms: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Numpy reference of `lut_scores_blocked(..., lut_bits=8)` from codes [N, M]: gather the 8-bit tables, rescale (float64)."""
    queries = np.atleast_2d(np.asarray(queries, np.float32))
    qluts, scale, offset = quantize_luts(codebook.luts(queries))
    codes = np.asarray(codes, np.intp)
    m = codes.shape[1]
    sums = qluts[:, np.arange(m)[None, :], codes].astype(np.int64).sum(axis=2).T  # [N, K]
    dots = offset.astype(np.float64) + scale.astype(np.float64) * sums
    if list_ids is not None and codebook.coarse is not None:
        dots = dots + codebook.coarse_table(queries).T[np.asarray(list_ids, np.intp)]
    return (dots * inverse_norms(norms)[:, None]).astype(np.float32)


# --------------------------------------------------------------------------------------------
# The field


@dataclass
class LanguageField:
    """Per-Gaussian language features in one storage backend.

    kind: "exact" | "pq" | "ivfpq".
    weights: [N] float32 total registration weight Σ_j w_ij (0 = unassigned).
    features: [N, D] float16 (exact).
    codes: [N, M] uint8 (pq, ivfpq).
    list_ids: [N] int32 coarse list ids (ivfpq).
    norms: [N] float32 norms of the stored / reconstructed features (0 = unassigned).
    codebook: the loaded faiss quantiser (pq, ivfpq).
    """

    kind: str
    dim: int
    clip_model: str
    weights: np.ndarray
    features: np.ndarray | None = None
    codes: np.ndarray | None = None
    list_ids: np.ndarray | None = None
    norms: np.ndarray | None = None
    codebook: Codebook | None = None
    _blocked: np.ndarray | None = dataclasses.field(default=None, init=False, repr=False, compare=False)

    @property
    def num_gaussians(self) -> int:
        return int(self.weights.shape[0])

    def __len__(self) -> int:
        return self.num_gaussians

    def bytes_per_gaussian(self) -> int:
        """Stored bytes per Gaussian in the PLY (weight and norm included)."""
        if self.kind == "exact":
            return 2 * self.dim + 4
        return self.codebook.m + 8 + (4 if self.kind == "ivfpq" else 0)

    def scores(self, queries: np.ndarray, lut_bits: int = 32) -> np.ndarray:
        """Cosine similarity of every Gaussian to each query: queries [K, D] or [D] -> [N, K] float32.

        Queries are L2-normalised; features are compared through their stored norm, so the
        result is cos(q, f_i) for exact fields and cos(q, r_i) for PQ reconstructions r_i.
        Unassigned Gaussians (zero norm) score 0.
        lut_bits: 32 (default) scores PQ fields with float32 tables (exact up to rounding);
        8 uses 8-bit tables (`lut_scores_blocked`, an approximation). Exact fields have no tables
        and ignore it. On AVX-512 CPUs with M ≥ 128 (and always for lut_bits=8) PQ fields are
        scored on a blocked copy of the codes, built by the first call and kept (M more bytes
        per Gaussian).
        """
        if lut_bits not in (8, 32):
            raise ValueError(f"lut_bits must be 8 or 32, got {lut_bits}")
        q = unit_rows(self._check_queries(queries))
        if self.kind == "exact":
            return half_scores(self.features, self.norms, q)
        if lut_bits == 8 or (self.codebook.m >= BLOCKED_MIN_M and simd_available()):
            return lut_scores_blocked(self.codebook, self.blocked_codes(), self.num_gaussians, self.list_ids, self.norms, q, lut_bits)
        return lut_scores(self.codebook, self.codes, self.list_ids, self.norms, q)

    def blocked_codes(self) -> np.ndarray:
        """The codes in the layout of the 8-bit kernel, built on first use: [ceil(N/64), M, 64] uint8."""
        if self._blocked is None:
            self._blocked = blocked_codes(self.codes)
        return self._blocked

    def scores_reference(self, queries: np.ndarray) -> np.ndarray:
        """Decode-then-cosine reference of `scores` (float64 math): [N, K]."""
        q = unit_rows(self._check_queries(queries))
        if self.kind == "exact":
            f = self.features.astype(np.float64)
            norm = np.linalg.norm(f, axis=1)
            with np.errstate(divide="ignore", invalid="ignore"):
                s = (f @ q.astype(np.float64).T) / norm[:, None]
            return np.where(norm[:, None] > 0, s, 0.0).astype(np.float32)
        scores = lut_scores_reference(self.codebook, self.codes, self.list_ids, self.norms, q)
        return np.where(self.norms[:, None] > 0, scores, 0.0).astype(np.float32)

    def reconstruct(self, index: np.ndarray | slice | None = None) -> np.ndarray:
        """Stored features (exact) or PQ reconstructions of the selected Gaussians: [n, D] float32."""
        sel = slice(None) if index is None else index
        if self.kind == "exact":
            return self.features[sel].astype(np.float32)
        ids = None if self.list_ids is None else self.list_ids[sel]
        return self.codebook.decode(self.codes[sel], ids)

    def subset(self, index: np.ndarray | slice) -> "LanguageField":
        """The field of the Gaussians selected by a boolean mask [N] or an index array."""

        def take(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[index]

        return dataclasses.replace(
            self,
            weights=self.weights[index],
            features=take(self.features),
            codes=take(self.codes),
            list_ids=take(self.list_ids),
            norms=take(self.norms),
        )

    def _check_queries(self, queries: np.ndarray) -> np.ndarray:
        q = np.atleast_2d(np.asarray(queries, np.float32))
        if q.ndim != 2 or q.shape[1] != self.dim:
            raise ValueError(f"queries have shape {np.shape(queries)}; this field holds {self.dim}-D features")
        return q



def build_field(
    features: np.ndarray,
    weights: np.ndarray,
    codebook: str | Path | Codebook = "none",
    clip_model: str = "unknown",
    train_embeddings: np.ndarray | None = None,
    m: int = 128,
    seed: int = 0,
) -> LanguageField:
    """Store registered features [N, D] (unit rows, zero rows for unassigned) in a backend.

    codebook: "none" (exact float16), "scene" (PQ with `m` sub-vectors trained on
    `train_embeddings`, the scene's mask embeddings, topped up with a sample of the features when
    they are fewer than 2,560), a path to a faiss codebook file, or a loaded Codebook.
    weights: [N] total registration weight; Gaussians with weight 0 get norm 0 (score 0).
    """
    features = np.asarray(features)
    weights = np.asarray(weights, np.float32).reshape(-1)
    if features.ndim != 2 or features.shape[0] != weights.shape[0]:
        raise ValueError(f"features {features.shape} and weights {weights.shape} disagree")
    n, dim = features.shape
    assigned = weights > 0
    if isinstance(codebook, str) and codebook == "none":
        f16 = features.astype(np.float16)
        f16[~assigned] = 0
        norms = np.empty(n, np.float32)
        for start in range(0, n, EXACT_CHUNK):
            norms[start : start + EXACT_CHUNK] = np.linalg.norm(f16[start : start + EXACT_CHUNK].astype(np.float32), axis=1)
        return LanguageField("exact", dim, clip_model, weights, features=f16, norms=norms)
    if isinstance(codebook, Codebook):
        book = codebook
    elif isinstance(codebook, str) and codebook == "scene":
        book = train_codebook(_scene_training_set(features, assigned, train_embeddings, seed), m=m, seed=seed)
    else:
        book = load_codebook(codebook)
    if book.dim != dim:
        raise InputError(book.path, f"codebook dimension {book.dim} differs from the features' dimension {dim} (a different CLIP model?)")
    codes, list_ids, norms = encode_features(book, features, assigned)
    return LanguageField(book.kind, dim, clip_model, weights, codes=codes, list_ids=list_ids, norms=norms, codebook=book)


def encode_features(book: Codebook, features: np.ndarray, assigned: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Encode [N, D] features in chunks: (codes [N, M] uint8, list_ids [N] int32 | None, norms [N]).

    norms are the reconstruction norms |r_i| (0 where not assigned).
    """
    n = features.shape[0]
    codes = np.zeros((n, book.m), np.uint8)
    list_ids = np.zeros(n, np.int32) if book.kind == "ivfpq" else None
    norms = np.zeros(n, np.float32)
    for start in range(0, n, ENCODE_CHUNK):
        stop = min(n, start + ENCODE_CHUNK)
        x = unit_rows(np.asarray(features[start:stop], np.float32))
        c, ids = book.encode(x)
        codes[start:stop] = c
        if list_ids is not None:
            list_ids[start:stop] = ids
        norms[start:stop] = np.linalg.norm(book.decode(c, ids), axis=1)
    norms[~assigned] = 0
    return codes, list_ids, norms


def _scene_training_set(features: np.ndarray, assigned: np.ndarray, train: np.ndarray | None, seed: int) -> np.ndarray:
    parts = [] if train is None else [np.asarray(train, np.float32)]
    have = sum(p.shape[0] for p in parts)
    if have < SCENE_MIN_TRAIN:
        rng = np.random.default_rng(seed)
        ids = np.flatnonzero(assigned)
        take = rng.choice(ids, size=min(ids.size, SCENE_FEATURE_SAMPLE), replace=False) if ids.size else ids
        parts.append(np.asarray(features[np.sort(take)], np.float32))
        log.info("scene codebook: %d mask embeddings topped up with %d Gaussian features", have, take.size)
    x = np.concatenate(parts) if parts else np.zeros((0, features.shape[1]), np.float32)
    if x.shape[0] < PQ_KSUB:
        raise InputError(None, f"a scene codebook needs at least {PQ_KSUB} embeddings to train, the scene has {x.shape[0]}; use --codebook none or a general codebook")
    return x


# --------------------------------------------------------------------------------------------
# PLY encoding


def codebook_path_for(ply_path: str | Path) -> Path:
    """The codebook file next to a registered PLY: `<stem>.codebook.faiss`."""
    ply_path = Path(ply_path)
    return ply_path.with_name(f"{ply_path.stem}.codebook.faiss")


def field_comment(field: LanguageField, codebook_name: str | None) -> str:
    """`drsplat.lang kind=<kind> dim=<D> clip=<model> [codebook=<file>]` (values URL-quoted)."""
    parts = [COMMENT_PREFIX, f"kind={field.kind}", f"dim={field.dim}", f"clip={quote(field.clip_model, safe='/:-_.+')}"]
    if codebook_name:
        parts.append(f"codebook={quote(codebook_name, safe='/:-_.+')}")
    return " ".join(parts)


def field_extras(field: LanguageField) -> dict[str, np.ndarray]:
    """Extra vertex properties of the field, name -> [N] array (dtype = PLY type)."""
    extras: dict[str, np.ndarray] = {"lang_weight": np.ascontiguousarray(field.weights, np.float32)}
    if field.kind == "exact":
        bits = field.features.astype(np.float16).view(np.uint16)
        for j in range(field.dim):
            extras[f"lang_{j}"] = np.ascontiguousarray(bits[:, j])
        return extras
    for j in range(field.codes.shape[1]):
        extras[f"lang_code_{j}"] = np.ascontiguousarray(field.codes[:, j], np.uint8)
    extras["lang_norm"] = np.ascontiguousarray(field.norms, np.float32)
    if field.kind == "ivfpq":
        extras["lang_list"] = np.ascontiguousarray(field.list_ids, np.int32)
    return extras


def is_lang_property(name: str) -> bool:
    return name == "lang_weight" or name == "lang_norm" or name == "lang_list" or re.fullmatch(r"lang_(code_)?\d+", name) is not None


def strip_field(scene: GaussianScene) -> GaussianScene:
    """The scene without language properties and drsplat.lang comments (a plain 3DGS scene)."""
    return dataclasses.replace(
        scene,
        extra={k: v for k, v in scene.extra.items() if not is_lang_property(k)},
        comments=[c for c in scene.comments if not c.startswith(COMMENT_PREFIX)],
    )


def attach_field(scene: GaussianScene, field: LanguageField, ply_path: str | Path) -> GaussianScene:
    """The scene with the field's extra properties and header comment; writes the codebook.

    The codebook (pq, ivfpq) is written next to `ply_path` as `<stem>.codebook.faiss`; save the
    returned scene to `ply_path` with `drsplat.scene.save_ply`.
    """
    if field.num_gaussians != scene.num_gaussians:
        raise ValueError(f"field has {field.num_gaussians} Gaussians, scene has {scene.num_gaussians}")
    base = strip_field(scene)
    name = None
    if field.kind != "exact":
        target = codebook_path_for(ply_path)
        name = target.name
        source = field.codebook.path
        if source is not None and source.is_file() and source.resolve() != target.resolve():
            with atomic_path(target) as tmp:
                shutil.copyfile(source, tmp)
        elif source is None or source.resolve() != target.resolve():
            field.codebook.save(target)
    extra = dict(base.extra)
    extra.update(field_extras(field))
    return dataclasses.replace(base, extra=extra, comments=base.comments + [field_comment(field, name)])


def parse_field_comment(comments: list[str]) -> dict[str, str] | None:
    """The key=value pairs of the `drsplat.lang` header comment, or None when there is none."""
    for comment in comments:
        tokens = comment.split()
        if tokens and tokens[0] == COMMENT_PREFIX:
            return {k: unquote(v) for k, _, v in (t.partition("=") for t in tokens[1:])}
    return None


def read_field(scene: GaussianScene, ply_path: str | Path) -> LanguageField | None:
    """The language field of a scene loaded from `ply_path` (None if it has no drsplat.lang comment).

    Raises InputError naming the PLY (or codebook) file and the field for missing properties,
    an unknown kind, a missing codebook, or codes that do not fit the codebook.
    """
    ply_path = Path(ply_path)
    meta = parse_field_comment(scene.comments)
    if meta is None:
        return None
    kind = meta.get("kind")
    if kind not in KINDS:
        raise InputError(ply_path, f"unknown language field kind {kind!r}; expected one of {', '.join(KINDS)}", field="comment drsplat.lang")
    try:
        dim = int(meta.get("dim", ""))
    except ValueError:
        raise InputError(ply_path, f"dim={meta.get('dim')!r} is not an integer", field="comment drsplat.lang") from None
    clip_model = meta.get("clip", "unknown")
    weights = _extra(scene, ply_path, "lang_weight").astype(np.float32)
    if kind == "exact":
        cols = [_extra(scene, ply_path, f"lang_{j}") for j in range(dim)]
        features = _stack_columns(cols, np.uint16, scene.num_gaussians, dim).view(np.float16)
        norms = np.empty(scene.num_gaussians, np.float32)
        for start in range(0, scene.num_gaussians, EXACT_CHUNK):
            norms[start : start + EXACT_CHUNK] = np.linalg.norm(features[start : start + EXACT_CHUNK].astype(np.float32), axis=1)
        nonfinite = int(np.count_nonzero(~np.isfinite(norms)))
        if nonfinite:
            log.warning("%s: %d Gaussians have non-finite language features; they score 0", ply_path, nonfinite)
        return LanguageField(kind, dim, clip_model, weights, features=features, norms=norms)
    if "codebook" not in meta:
        raise InputError(ply_path, "a quantised language field names no codebook file", field="comment drsplat.lang")
    book = load_codebook(ply_path.parent / meta["codebook"])
    if book.kind != kind or book.dim != dim:
        raise InputError(book.path, f"codebook is {book.kind} d={book.dim}, but {ply_path.name} declares {kind} dim={dim}")
    cols = [_extra(scene, ply_path, f"lang_code_{j}") for j in range(book.m)]
    if f"lang_code_{book.m}" in scene.extra:
        raise InputError(ply_path, f"more PQ code columns than the codebook's M={book.m}", field=f"lang_code_{book.m}")
    codes = _stack_columns(cols, np.uint8, scene.num_gaussians, book.m)
    norms = _extra(scene, ply_path, "lang_norm").astype(np.float32)
    list_ids = None
    if kind == "ivfpq":
        list_ids = _extra(scene, ply_path, "lang_list").astype(np.int32)
        nlist = int(book.index.nlist)
        bad = (list_ids < 0) | (list_ids >= nlist)
        if np.any(bad):
            raise InputError(ply_path, f"{int(bad.sum())} coarse list ids fall outside 0..{nlist - 1}", field="lang_list")
    return LanguageField(kind, dim, clip_model, weights, codes=codes, list_ids=list_ids, norms=norms, codebook=book)


def _extra(scene: GaussianScene, ply_path: Path, name: str) -> np.ndarray:
    if name not in scene.extra:
        raise InputError(ply_path, "missing vertex property of the language field", field=name)
    return np.asarray(scene.extra[name])


def _stack_columns(cols: list[np.ndarray], dtype: type, n: int, width: int) -> np.ndarray:
    out = np.empty((n, width), dtype)
    for j, col in enumerate(cols):
        out[:, j] = col.astype(dtype, copy=False)
    return out
