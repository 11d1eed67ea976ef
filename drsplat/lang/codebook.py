"""Product-quantisation codebooks (faiss `IndexPQ`, the official `IndexIVFPQ`): load, train, encode, decode, look-up tables."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drsplat.errors import InputError
from drsplat.utils import atomic_path

log = logging.getLogger(__name__)

PQ_BITS = 8
PQ_KSUB = 1 << PQ_BITS


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
