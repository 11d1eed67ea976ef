"""Product-quantisation codebooks (faiss `IndexPQ`, the official `IndexIVFPQ`): load, train, encode, decode, look-up tables."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

from drsplat.defaults import UNIT_TOLERANCE
from drsplat.errors import InputError
from drsplat.utils import CancelToken, progress, write_bytes_atomic

log = logging.getLogger(__name__)

PQ_BITS = 8
PQ_KSUB = 1 << PQ_BITS
SCENE_PQ_M = 128  # sub-vectors of a codebook trained on a scene's own masks (`--codebook scene`, `pq train`'s default): the paper's 128 x 8 bits
PQ_POINTS_PER_CENTROID = 256  # faiss's k-means samples at most this many training points per centroid
PQ_TRAIN_MAX = PQ_POINTS_PER_CENTROID * PQ_KSUB  # so a sub-quantiser never trains on more points than this


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
    _bytes: bytes | None = dataclasses.field(default=None, repr=False, compare=False)
    # files this codebook was written to or found in (`plyformat.write_codebook_beside`), with their
    # stamps then: a registration writes its PLY in chunks, and each would read the file back
    written: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)

    def file_bytes(self) -> bytes:
        """The faiss file of this codebook as it is in memory (serialised once, then kept): what a
        registration writes beside its PLY, never a copy of the file it was read from, which may
        have been replaced since (a probe, 2026-11-30). For a file written by faiss, its bytes."""
        if self._bytes is None:
            self._bytes = bytes(_faiss().serialize_index(self.index))
        return self._bytes

    def __getstate__(self) -> dict:  # a Ray task gets the index, not its serialised copy too
        state = dict(self.__dict__)
        state["_bytes"], state["written"] = None, {}
        return state

    @property
    def dsub(self) -> int:
        return self.dim // self.m

    @property
    def nlist(self) -> int:
        """The coarse lists an ivfpq code's list id counts (the index's, whether or not it encodes residuals: round 59a,
        an IndexIVFPQ with by_residual=False had 0, so every registered row's list id was refused); 0 for pq."""
        if self.coarse is not None:
            return int(self.coarse.shape[0])
        return int(self.index.nlist) if self.kind == "ivfpq" else 0

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
        """Look-up tables LUT[k, m, c] = q_k[m-th sub-vector] · C[m, c]: queries [K, D] -> [K, M, 256].

        Each query's table is made on its own, by einsum's own loop, so a query scores the same bits
        alone and in any batch (round 50: one [K, M, 256] contraction rounded a query's table
        differently for K = 1 and K > 1, by up to 1.9e-9, one ulp in 2/3 of its PQ scores)."""
        q = np.asarray(queries, dtype=np.float32).reshape(-1, self.m, self.dsub)
        out = np.empty((q.shape[0], self.m, self.centroids.shape[1]), np.float32)
        for k in range(q.shape[0]):
            out[k] = np.einsum("md,mcd->mc", q[k], self.centroids)
        return out

    def coarse_table(self, queries: np.ndarray) -> np.ndarray:
        """Coarse table q_k · c_l: queries [K, D] -> [K, nlist] float32 (empty [K, 0] for pq)."""
        if self.coarse is None:
            return np.zeros((queries.shape[0], 0), np.float32)
        # einsum's own loop: a [K, D] x [D, nlist] BLAS call waits on BLAS threads, 10x slower on a busy machine
        return np.ascontiguousarray(np.einsum("kd,ld->kl", np.asarray(queries, np.float32), self.coarse), dtype=np.float32)

    def save(self, path: str | Path) -> None:
        """Write the faiss index atomically. Serialised in memory, then written by Python: faiss's own
        writer raised a RuntimeError (a traceback) on a full disk or /dev/full, not an OSError."""
        write_bytes_atomic(path, _faiss().serialize_index(self.index).tobytes())


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
    _check_finite(centroids, "pq centroids", path)
    if coarse is not None:
        _check_finite(coarse, "coarse centroids", path)
    _check_reconstruction_range(centroids, coarse, path)
    return Codebook(kind=kind, dim=int(index.d), m=int(pq.M), centroids=centroids, coarse=coarse, index=index, path=path, owner=owner)


MAX_DIM = 1 << 16  # embedding dimensions; CLIP models use 512-1024


class _FaissHeaderReader:
    """Bounds-checked reader of the little-endian fields faiss writes (index_write.cpp)."""

    def __init__(self, path: Path, data: bytes):
        self.path, self.data, self.pos = path, data, 0

    def take(self, fmt: str, what: str) -> int | float:
        import struct

        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise InputError(self.path, f"faiss file is truncated inside {what} (byte {self.pos})")
        (value,) = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return value

    def skip_array(self, itemsize: int, what: str, expected: int | None = None) -> int:
        """A faiss vector: size_t count then count items; checked against `expected` and the file size."""
        count = int(self.take("Q", what))
        if expected is not None and count != expected:
            raise InputError(self.path, f"faiss {what} holds {count} values, expected {expected}: the file is corrupt", field=what)
        if self.pos + count * itemsize > len(self.data):
            raise InputError(self.path, f"faiss {what} declares {count} values ({count * itemsize} bytes) but only "
                                        f"{len(self.data) - self.pos} bytes remain: the file is truncated or corrupt", field=what)
        self.pos += count * itemsize
        return count

    def fourcc(self) -> bytes:
        if self.pos + 4 > len(self.data):
            raise InputError(self.path, "faiss file is truncated (no index type)")
        code = self.data[self.pos : self.pos + 4]
        self.pos += 4
        return code

    def check_list_sizes(self, nlist: int, code_size: int) -> None:
        """The ArrayInvertedLists sizes ("full": nlist counts, "sprs": (list, count) pairs) fit the file; the lists'
        codes and ids (code_size + 8 bytes an entry, faiss's write_InvertedLists) are then skipped."""
        kind = self.fourcc()
        if kind == b"full":
            count = self.skip_array(8, "inverted list sizes", expected=nlist)
            sizes = np.frombuffer(self.data, "<u8", count, self.pos - 8 * count)
        elif kind == b"sprs":
            count = self.skip_array(8, "inverted list sizes")
            sizes = np.frombuffer(self.data, "<u8", count, self.pos - 8 * count)[1::2]
        else:
            raise InputError(self.path, "faiss inverted lists have an unknown size encoding", field="invlists")
        total = int(sizes.astype(np.float64).sum())
        if total * (code_size + 8) > len(self.data) - self.pos:
            raise InputError(self.path, f"faiss inverted lists declare {total} entries, more than the file holds", field="invlists")
        self.pos += total * (code_size + 8)

    def warn_if_bytes_follow(self) -> None:
        """Warn when bytes follow the index's last field: faiss ignores them, and so does drsplat, but a file joined to
        another, or a corrupt copy, should be said (round 59a: an IndexIVFPQ's were not, an IndexPQ's were)."""
        if self.pos < len(self.data):
            log.warning("%s: %d bytes follow the codebook's last field and are ignored (two files joined, or a corrupt copy?)",
                        self.path, len(self.data) - self.pos)

    def index_header(self, what: str) -> tuple[int, int]:
        """(d, ntotal) of faiss's common index header, with d in 1..MAX_DIM and ntotal >= 0."""
        d = int(self.take("i", f"{what} d"))
        ntotal = int(self.take("q", f"{what} ntotal"))
        self.take("q", "header")
        self.take("q", "header")
        self.take("B", f"{what} is_trained")
        metric = int(self.take("i", f"{what} metric"))
        if metric > 1:
            self.take("f", f"{what} metric_arg")
        if not 1 <= d <= MAX_DIM:
            raise InputError(self.path, f"faiss {what} has dimension d={d}; expected 1..{MAX_DIM}", field="d")
        if ntotal < 0 or ntotal > len(self.data):
            raise InputError(self.path, f"faiss {what} claims {ntotal} vectors, impossible in a {len(self.data)}-byte file", field="ntotal")
        return d, ntotal

    def product_quantizer(self, d: int) -> int:
        """M of a ProductQuantizer block, after checking d, M, nbits and the centroid count."""
        pq_d, m, nbits = int(self.take("Q", "pq d")), int(self.take("Q", "pq M")), int(self.take("Q", "pq nbits"))
        if pq_d != d:
            raise InputError(self.path, f"faiss PQ dimension {pq_d} differs from the index dimension {d}", field="pq d")
        if not 1 <= m <= d or d % m:
            raise InputError(self.path, f"faiss PQ has M={m} sub-vectors, which does not divide d={d}", field="M")
        if nbits != PQ_BITS:
            raise InputError(self.path, f"PQ codes have {nbits} bits; drsplat stores 8-bit codes only", field="nbits")
        self.skip_array(4, "pq centroids", expected=d * PQ_KSUB)
        return m


def check_faiss_header(path: Path) -> None:
    """Validate a faiss IndexPQ / IndexIVFPQ file's header against its size before faiss reads it.

    faiss trusts every count it reads (a codebook with 3 bytes changed made it allocate 10 GB):
    d, M, nbits, nlist, the centroid, code and inverted-list sizes are checked here first, and
    index types other than IndexPQ and IndexIVFPQ (flat coarse quantiser) are refused.
    """
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(path, f"cannot be read ({exc.strerror or exc})") from None
    r = _FaissHeaderReader(path, data)
    code = r.fourcc()
    if code == b"IxPq":
        d, ntotal = r.index_header("IndexPQ")
        m = r.product_quantizer(d)
        r.skip_array(1, "codes", expected=ntotal * m)
        # IndexPQ's last fields (faiss index_read.cpp): a file cut inside them made faiss throw its C++ text
        r.take("i", "the search type after the codes")
        r.take("B", "encode_signs after the codes")
        r.take("i", "polysemous_ht after the codes")
        r.warn_if_bytes_follow()
        return
    if code == b"IvPQ":  # per-list id vectors before the direct map, which this check does not walk (round 91d F1)
        raise InputError(path, "is a faiss IndexIVFPQ in faiss's pre-2018 layout (type code IvPQ), which drsplat does not read; "
                               "read it and write it again with a current faiss (faiss.read_index, faiss.write_index) to convert it")
    if code != b"IwPQ":
        raise InputError(path, "is not a faiss index file drsplat reads (unknown index type code; drsplat reads IndexPQ and IndexIVFPQ codebooks)")
    d, _ = r.index_header("IndexIVFPQ")
    nlist = int(r.take("Q", "nlist"))
    r.take("Q", "nprobe")
    if not 1 <= nlist <= len(data) // (4 * d):
        raise InputError(path, f"faiss IndexIVFPQ has nlist={nlist} coarse centroids, impossible in a {len(data)}-byte file", field="nlist")
    quantizer = r.fourcc()
    if quantizer not in (b"IxFI", b"IxF2", b"IxFl"):
        raise InputError(path, "faiss IndexIVFPQ has a coarse quantiser that is not a flat index; drsplat reads flat quantisers only", field="quantizer")
    qd, qn = r.index_header("coarse quantiser")
    if qd != d or qn != nlist:
        raise InputError(path, f"faiss coarse quantiser has d={qd}, {qn} centroids; the index has d={d}, nlist={nlist}", field="quantizer")
    r.skip_array(4, "coarse centroids", expected=nlist * d)
    # faiss's DirectMap: 0 none, 1 an array, 2 a hashtable, whose (id, index) pairs follow the array: faiss would
    # otherwise read sizes this check never saw, and allocate them (round 91d F1: a 2.6 MB file took 2.25 GB)
    direct_map = int(r.take("B", "direct map type"))
    if direct_map not in (0, 1, 2):
        raise InputError(path, f"faiss IndexIVFPQ has direct map type {direct_map}; faiss knows 0 (none), 1 (array) and 2 (hashtable): "
                               "the file is corrupt", field="direct map type")
    r.skip_array(8, "direct map")
    if direct_map == 2:
        r.skip_array(16, "direct map hashtable")
    r.take("B", "by_residual")
    code_size = int(r.take("Q", "code_size"))
    m = r.product_quantizer(d)
    if code_size != m:
        raise InputError(path, f"faiss IndexIVFPQ code_size={code_size} differs from M={m}", field="code_size")
    lists_kind = r.fourcc()
    if lists_kind == b"ilar":
        lists, list_code_size = int(r.take("Q", "invlists nlist")), int(r.take("Q", "invlists code_size"))
        if lists != nlist or list_code_size != code_size:
            raise InputError(path, f"faiss inverted lists have nlist={lists}, code_size={list_code_size}; expected {nlist}, {code_size}", field="invlists")
        r.check_list_sizes(nlist, code_size)
    if lists_kind in (b"ilar", b"il00"):  # arrays, or none: the index ends here (other kinds live in files of their own)
        r.warn_if_bytes_follow()


def _check_finite(values: np.ndarray, what: str, path: Path | None) -> None:
    """Refuse NaN/inf centroids: every code decoded through them would score NaN (a corrupt file,
    not flipped code bytes, which is what a query would otherwise suspect)."""
    bad = int(np.count_nonzero(~np.isfinite(values)))
    if bad:
        raise InputError(path, f"{bad} of the {values.size} {what} values are not finite (NaN/inf): the codebook is corrupt", field=what)


def largest_reconstruction_norm(centroids: np.ndarray, coarse: np.ndarray | None) -> float:
    """A bound on ‖r‖ of every reconstruction r = [c_list +] concat_m C[m, code_m] (float64):
    sqrt(Σ_m max_c ‖C[m, c]‖²), plus the largest coarse centroid's norm. centroids [M, 256, dsub]."""
    sub = np.square(centroids.astype(np.float64)).sum(axis=2).max(axis=1)  # [M]
    bound = float(np.sqrt(sub.sum()))
    if coarse is not None and coarse.size:
        bound += float(np.linalg.norm(coarse.astype(np.float64), axis=1).max())
    return bound


def _check_reconstruction_range(centroids: np.ndarray, coarse: np.ndarray | None, path: Path | None) -> None:
    """Refuse centroids so large that a reconstruction's norm can pass float32's range: its stored
    norm (lang_norm, float32) would be inf and the row would score 0 (a codebook of 3e37 centroids
    registered every Gaussian with an infinite norm without a word: a probe, round 29a). A codebook of
    unit CLIP embeddings reconstructs norms near 1."""
    bound = largest_reconstruction_norm(centroids, coarse)
    if bound > float(np.finfo(np.float32).max):
        raise InputError(path, f"its centroids reconstruct vectors of norm up to {bound:.3g}, beyond float32's range (+-3.4e38), in which "
                               "a registered PLY stores them: the codebook is corrupt (CLIP codebooks reconstruct norms near 1)", field="pq centroids")


def load_codebook(path: str | Path) -> Codebook:
    """Read a faiss codebook file (IndexPQ from `drsplat pq train`, or the official IndexIVFPQ).

    The header is validated against the file size first (`check_faiss_header`).
    """
    faiss = _faiss()

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "codebook file not found" if not path.exists() else
                         f"is not a regular file ({'a folder' if path.is_dir() else 'a FIFO, device or socket'}); a codebook is a faiss index file")
    check_faiss_header(path)
    try:
        index = faiss.read_index(str(path))
    except RuntimeError as exc:
        raise InputError(path, f"not a faiss index file ({str(exc).splitlines()[0][:200]})") from None
    return codebook_from_index(index, path)


def train_codebook(embeddings: np.ndarray, m: int = SCENE_PQ_M, seed: int = 0, cancel: CancelToken | None = None,
                   show_progress: bool = False) -> Codebook:
    """Train a faiss IndexPQ (inner product, M sub-vectors x 8 bits) on embeddings [n, D].

    Each sub-quantiser is a 256-centroid k-means over its D/M-dimensional slice. Rows are
    L2-normalised first (CLIP embeddings are compared by cosine); rows without a direction (zero, NaN, inf:
    `has_direction`) are left out with a warning before the count is checked (round 59a: they trained as
    zero rows, and 256 NaN rows made a codebook of zero centroids without a word).
    The sub-quantisers are trained one at a time (`_sub_quantizer_centroids`, faiss's own k-means with the
    parameters `IndexPQ.train` gives it, so the same centroids bit for bit, tested), so that a long training
    shows its progress and stops at a Ctrl-C (`cancel`): 20,244 x 512 rows took 64 s on 2 loaded cores, and
    `register --codebook scene` neither said so nor could be stopped (round 67b F2).
    """
    faiss = _faiss()

    raw = np.atleast_2d(np.asarray(embeddings, np.float32))
    usable = has_direction(raw)
    if not usable.all():
        log.warning("%d of the %d training embeddings are zero or not finite and are left out", int((~usable).sum()), raw.shape[0])
    x = unit_rows(raw[usable])
    n, d = x.shape
    if m <= 0 or d % m:
        raise InputError(None, f"M={m} sub-vectors do not divide the embedding dimension {d}")
    if n < PQ_KSUB:
        raise InputError(None, f"training a PQ codebook needs at least {PQ_KSUB} embeddings, got {n}")
    distinct = distinct_rows(x)
    if distinct < PQ_KSUB:  # k-means then spreads its centroids over copies: a codebook of this set only
        log.warning("only %s of the %s training embeddings %s distinct (a PQ sub-quantiser has %d centroids): the codebook "
                    "reconstructs %s and little else; train it on many images' masks", f"{distinct:,}", f"{n:,}", "is" if distinct == 1 else "are",
                    PQ_KSUB, "this one direction" if distinct == 1 else f"these {distinct:,} directions")
    index = _untrained_pq(faiss, d, m, seed)
    dsub = d // m
    centroids = np.empty((m, PQ_KSUB, dsub), np.float32)
    with _one_faiss_thread(faiss):
        for j in progress(range(m), desc="train the scene codebook", enabled=show_progress, unit="sub-quantiser"):
            if cancel is not None:
                cancel.raise_if_cancelled()
            centroids[j] = _sub_quantizer_centroids(faiss, x[:, j * dsub : (j + 1) * dsub], index.pq.cp)
    faiss.copy_array_to_vector(centroids.ravel(), index.pq.centroids)
    index.is_trained = True
    return codebook_from_index(index)


def _sub_quantizer_centroids(faiss, x_sub: np.ndarray, params) -> np.ndarray:
    """[PQ_KSUB, dsub] float32: one sub-quantiser's k-means over x_sub [n, dsub], as faiss's ProductQuantizer.train
    makes it for each sub-vector (Clustering with the index's parameters, assigned by an exact L2 index)."""
    clustering = faiss.Clustering(x_sub.shape[1], PQ_KSUB, params)
    clustering.train(np.ascontiguousarray(x_sub), faiss.IndexFlatL2(x_sub.shape[1]))
    return faiss.vector_to_array(clustering.centroids).reshape(PQ_KSUB, x_sub.shape[1])


def train_codebook_reference(embeddings: np.ndarray, m: int = SCENE_PQ_M, seed: int = 0) -> Codebook:
    """`train_codebook` as one faiss `IndexPQ.train` call (the same rows, parameters and one thread): its reference."""
    faiss = _faiss()
    raw = np.atleast_2d(np.asarray(embeddings, np.float32))
    x = unit_rows(raw[has_direction(raw)])
    index = _untrained_pq(faiss, x.shape[1], m, seed)
    with _one_faiss_thread(faiss):
        index.train(np.ascontiguousarray(x))
    return codebook_from_index(index)


def _untrained_pq(faiss, d: int, m: int, seed: int):
    """The faiss IndexPQ (inner product, M sub-vectors x 8 bits) a codebook is trained into, with its k-means parameters."""
    index = faiss.IndexPQ(d, m, PQ_BITS, faiss.METRIC_INNER_PRODUCT)
    index.pq.cp.seed = seed
    index.pq.cp.max_points_per_centroid = PQ_POINTS_PER_CENTROID
    index.pq.cp.min_points_per_centroid = 1  # small scene sets are fine; faiss would warn per sub-quantiser
    return index


@contextlib.contextmanager
def _one_faiss_thread(faiss):
    """faiss on one OpenMP thread while the block runs. Each sub-quantiser's k-means is too small to share between
    threads: OpenMP barriers made training 8x slower on a busy 2-core machine, one thread is as fast on an idle one."""
    previous = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(1)
    try:
        yield
    finally:
        faiss.omp_set_num_threads(previous)


def distinct_rows(x: np.ndarray) -> int:
    """How many distinct rows x [n, D] holds, counted by a random projection of each row (float64):
    rows that differ project apart but for a chance of ~1e-16 per pair, and no [n, D] sort is made."""
    keys = np.asarray(x, np.float64) @ np.random.default_rng(0).standard_normal(x.shape[1])
    return int(np.unique(keys).size)


def has_direction(x: np.ndarray) -> np.ndarray:
    """[K] bool: the rows of x [K, D] (or one [D] row) that are finite and not all zero, the rows
    `unit_rows` normalises (the others it makes zero rows)."""
    x = np.atleast_2d(np.asarray(x))
    with np.errstate(invalid="ignore"):
        return np.isfinite(x).all(axis=1) & (x != 0).any(axis=1)


def undirected_rows_problem(x: np.ndarray, what: str = "query") -> str | None:
    """Why rows of x [K, D] cannot be queried, naming the first such row (non-finite rows before
    all-zero ones, and how many there are), or None when every row `has_direction`: `unit_rows`
    would make such a row a zero row, whose scores look like an unassigned Gaussian's."""
    x = np.atleast_2d(np.asarray(x))
    with np.errstate(invalid="ignore"):
        finite = np.isfinite(x).all(axis=1)
    for bad, why in ((~finite, "holds non-finite values"), (finite & ~has_direction(x), "is all zeros")):
        if bad.any():
            count = int(bad.sum())
            return f"{what} {int(np.flatnonzero(bad)[0])} {why}: it has no direction to score by" + (f" ({count} such rows)" if count > 1 else "")
    return None


@numba.njit(parallel=True, cache=True)
def _unit_check_kernel(f, tol, ok, off):  # pragma: no cover - jitted
    """Per row of f [N, D] float32, in parallel, one pass: ok = finite and not all zero
    (`has_direction`); off = ok and |‖f‖ - 1| > tol. The squares are summed in float64, whose range
    holds the square of every finite float32 (3.4e38² and 1e-45²): no scaling needed against
    overflow or underflow."""
    for i in numba.prange(f.shape[0]):
        finite = True
        nonzero = False
        s = 0.0
        for j in range(f.shape[1]):
            v = np.float64(f[i, j])
            finite = finite and math.isfinite(v)
            nonzero = nonzero or v != 0.0
            s += v * v
        ok[i] = finite and nonzero
        off[i] = ok[i] and abs(math.sqrt(s) - 1.0) > tol


def unit_check(f: np.ndarray, tol: float = UNIT_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
    """([N] ok, [N] off) of rows f [N, D] float32: rows with a direction (`has_direction`), and those
    of them whose norm is not within tol of 1 (`_unit_check_kernel`; `unit_check_reference` is the
    numpy form: the same flags but for norms within float32 rounding of 1 ± tol)."""
    f = np.ascontiguousarray(f, np.float32)
    ok, off = np.empty(f.shape[0], bool), np.empty(f.shape[0], bool)
    if f.shape[0]:
        _unit_check_kernel(f, float(tol), ok, off)
    return ok, off


def unit_check_reference(f: np.ndarray, tol: float = UNIT_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
    """`unit_check` in numpy (float32 norms of the rows scaled by their peak)."""
    f = np.asarray(f, np.float32)
    ok = has_direction(f)
    with np.errstate(invalid="ignore", over="ignore"):
        peak = np.abs(f).max(axis=1) if f.shape[1] else np.zeros(f.shape[0], np.float32)
        norm = peak * np.linalg.norm(f / np.where(ok, peak, 1)[:, None], axis=1)  # no underflow for rows of 1e-40
    return ok, ok & (np.abs(norm - 1.0) > tol)


def unit_rows64(rows: np.ndarray) -> np.ndarray:
    """[M, D] float64 unit rows of rows, divided by their float64 norms (zero rows stay zero): where `unit_rows`' float32
    rows would do, a row within 2⁻²² of unit is left as it is, and the cosine of its own copy times 3 was 1 - 4e-8."""
    f = np.asarray(rows, np.float64)
    norm = np.linalg.norm(f, axis=1, keepdims=True)
    return np.divide(f, norm, out=np.zeros_like(f), where=norm > 0)


def unit_rows(x: np.ndarray) -> np.ndarray:
    """Rows divided by their L2 norm: [K, D] float32; rows without a direction (`has_direction`) become zero.

    Each row is first divided by its largest magnitude (y = x / max|x|, then y / ||y||), so a
    huge finite row (1e30) normalises correctly instead of overflowing the norm to inf. ||y|| is
    summed in float64 and rounded once: numpy's float32 norm of a row took other bits in another
    layout (a Fortran-ordered batch, as an embedding file saved from a transposed array loads, sums
    each row in another order: a query alone and as the third of three differed in all 512
    components, and `segment` split Gaussians tied between equal label and background rows by that
    noise; round 37); a float64 sum's order moves its float32 rounding only at a boundary.

    Idempotent: a row whose float64 norm is within UNIT_ROW_SLACK of 1 is returned as it is, and every row this
    function makes is (each of its components is rounded once, relative error ≤ 2⁻²⁴, and the norm it divides by
    once more, so its norm lies within 2⁻²³ of 1). A second pass re-rounded them: the same phrase given as a query
    and as a negative, normalised two and three times on their ways, scored 0.5 ± 1e-7 and `--threshold 0.5`
    selected by that noise (round 59a).
    """
    x = np.atleast_2d(np.asarray(x, np.float32))
    with np.errstate(invalid="ignore", over="ignore"):
        norms = np.sqrt(np.einsum("ij,ij->i", x, x, dtype=np.float64))  # float64 squares: no float32 input overflows them
        unit = np.abs(norms - 1.0) <= UNIT_ROW_SLACK  # False for NaN; a finite row of norm ~1 has a direction
        if unit.all():
            return x.copy()
        out = x.copy()
        rest = x[~unit]
        scale = np.abs(rest).max(axis=1, keepdims=True) if rest.shape[1] else np.zeros((rest.shape[0], 1), np.float32)
        ok = has_direction(rest)[:, None]
        y = np.where(ok, rest / np.where(ok, scale, 1), 0)
        y64 = y.astype(np.float64)
        norm = np.sqrt(np.einsum("ij,ij->i", y64, y64))[:, None].astype(np.float32)
        out[~unit] = np.where(ok, y / np.where(ok, norm, 1), 0)
        return out


# |‖x‖ − 1| of a row `unit_rows` takes as unit already: twice the most its own rows are off (not defaults.UNIT_TOLERANCE,
# the 1e-3 within which a stored row counts as unit)
UNIT_ROW_SLACK = 2.0**-22
