"""`LanguageField`: per-Gaussian language features in one storage backend (exact fp16, PQ, IVFPQ), built from registration results."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drsplat.errors import InputError
from drsplat.lang.codebook import PQ_KSUB, Codebook, load_codebook, train_codebook, undirected_rows_problem, unit_check, unit_rows
from drsplat.lang.backends import BACKENDS, ExactStorage, Storage
from drsplat.lang.lut import has_feature

log = logging.getLogger(__name__)

SCENE_MIN_TRAIN = 10 * PQ_KSUB
SCENE_FEATURE_SAMPLE = 20000



# --------------------------------------------------------------------------------------------
# The field


@dataclass
class LanguageField:
    """Per-Gaussian language features of a registered scene, in one storage backend (drsplat.lang.backends).

    dim: D, the embedding size. clip_model: the id of the embedding space (drsplat.features.modelid).
    weights: [N] float32 total registration weight Σ_j w_ij (0 where unassigned; `assigned` reads the stored norms).
    storage: an ExactStorage (features [N, D] float16) or a PQStorage (codes [N, M] uint8, list ids, codebook),
    both with norms [N] float32 of what they store (0 = unassigned).
    """

    dim: int
    clip_model: str
    weights: np.ndarray
    storage: Storage
    clip_weights: str | None = None  # 'size:sha1' of the CLIP weights file the features were made with (None: not recorded)
    _on_device: object | None = dataclasses.field(default=None, init=False, repr=False, compare=False)  # torch_scoring.DeviceField

    @property
    def kind(self) -> str:
        return self.storage.kind

    # The backends' arrays, for readers that need one directly (None where the backend has no such array).
    @property
    def norms(self) -> np.ndarray:
        return self.storage.norms

    def assigned(self) -> np.ndarray:
        """[N] bool: the Gaussians with a language feature (a finite, positive stored norm). The
        others (unassigned, or a row whose stored values were found damaged and zeroed) score 0 and
        are never selected, labelled or averaged into a query; a PQ row's codes decode to some
        vector whatever its norm, so this, not a reconstruction, says which rows hold a feature."""
        return has_feature(self.norms)

    @property
    def features(self) -> np.ndarray | None:
        return getattr(self.storage, "features", None)

    @property
    def codes(self) -> np.ndarray | None:
        return getattr(self.storage, "codes", None)

    @property
    def list_ids(self) -> np.ndarray | None:
        return getattr(self.storage, "list_ids", None)

    @property
    def codebook(self) -> Codebook | None:
        return getattr(self.storage, "codebook", None)

    @property
    def codebook_path(self) -> Path | None:
        """The codebook file this field was read with (a PQ field's; None for an exact one or a
        codebook never saved): an input that no output may be written over."""
        return getattr(self.codebook, "path", None)

    @property
    def num_gaussians(self) -> int:
        return int(self.weights.shape[0])

    def __len__(self) -> int:
        return self.num_gaussians

    def bytes_per_gaussian(self) -> int:
        """Stored bytes per Gaussian of the field in the PLY (weight and norm included; not the uint16
        `lang_meta` columns that carry its description, as many as the file's rows need)."""
        return self.storage.bytes_per_gaussian() + 4

    def scores(self, queries: np.ndarray, lut_bits: int = 32, device: str | None = None) -> np.ndarray:
        """Cosine similarity of every Gaussian to each query: queries [K, D] or [D] -> [N, K] float32.

        Queries are L2-normalised; features are compared through their stored norm, so the
        result is cos(q, f_i) for exact fields and cos(q, r_i) for PQ reconstructions r_i.
        Unassigned Gaussians (zero norm) score 0.
        lut_bits: 32 (default) scores PQ fields with float32 tables (exact up to rounding);
        8 uses 8-bit tables (`lut_scores_blocked`, an approximation). Exact fields have no tables
        and ignore it.
        device: None = the numba CPU kernels; "cpu" / "cuda" = the torch kernels on that device
        (drsplat.lang.torch_scoring; float32 tables only; the field is copied there on first use and kept).
        """
        if lut_bits not in (8, 32):
            raise ValueError(f"lut_bits must be 8 or 32, got {lut_bits}")
        q = unit_rows(self._check_queries(queries))
        if device is not None:
            return self._scores_on_device(q, device, lut_bits).cpu().numpy()
        return self.storage.scores(q, lut_bits)

    def scores_torch(self, queries: np.ndarray, device: str, lut_bits: int = 32):
        """`scores` as a torch tensor [N, K] float32 on `device`: the queries checked and made unit as `scores` does (round
        75c F4: taken as given, a query of norm 3 scored 3x)."""
        return self._scores_on_device(unit_rows(self._check_queries(queries)), device, lut_bits)

    def _scores_on_device(self, queries: np.ndarray, device: str, lut_bits: int):
        """`scores_torch` of queries checked already."""
        from drsplat.lang import torch_scoring  # imports torch: only when a torch device is asked for

        if lut_bits != 32:
            raise ValueError("8-bit tables are a CPU (AVX-512) kernel; the torch scorer uses float32 tables (lut_bits=32)")
        if self._on_device is None or str(self._on_device.device) != str(torch_scoring.torch.device(device)):
            self._on_device = torch_scoring.to_device(self, device)
        return torch_scoring.field_scores_torch(self, np.asarray(queries, np.float32), self._on_device)

    def scores_reference(self, queries: np.ndarray) -> np.ndarray:
        """Decode-then-cosine reference of `scores` (float64 math): [N, K]."""
        return self.storage.scores_reference(unit_rows(self._check_queries(queries)))

    def reconstruct(self, index: np.ndarray | slice | None = None) -> np.ndarray:
        """Stored features (exact) or PQ reconstructions of the selected Gaussians: [n, D] float32."""
        return self.storage.reconstruct(slice(None) if index is None else index)

    def subset(self, index: np.ndarray | slice) -> "LanguageField":
        """The field of the Gaussians selected by a boolean mask [N] or an index array."""
        return LanguageField(self.dim, self.clip_model, self.weights[index], self.storage.take(index), self.clip_weights)

    def _check_queries(self, queries: np.ndarray) -> np.ndarray:
        q = np.atleast_2d(np.asarray(queries, np.float32))
        if q.ndim != 2 or q.shape[1] != self.dim:
            raise ValueError(f"queries have shape {np.shape(queries)}; this field holds {self.dim}-D features")
        problem = undirected_rows_problem(q)
        if problem is not None:  # as a zero row it would score 0 everywhere, like an unassigned Gaussian (round 37)
            raise ValueError(problem)
        return q


def build_field(
    features: np.ndarray,
    weights: np.ndarray,
    codebook: str | Path | Codebook = "none",
    clip_model: str = "unknown",
    train_embeddings: np.ndarray | None = None,
    m: int = 128,
    seed: int = 0,
    clip_weights: str | None = None,
) -> LanguageField:
    """Store registered features [N, D] (unit rows, zero rows for unassigned) in a backend.

    codebook: "none" (exact float16), "scene" (PQ with `m` sub-vectors trained on
    `train_embeddings`, the scene's mask embeddings, topped up with a sample of the features when
    they are fewer than 2,560), a path to a faiss codebook file, or a loaded Codebook.
    weights: [N] total registration weight; Gaussians with weight 0 get norm 0 (score 0).
    clip_weights: the CLIP weights file's 'size:sha1' the features were made with, carried into the PLY.
    """
    features = np.asarray(features)
    weights = np.asarray(weights, np.float32).reshape(-1)
    if features.ndim != 2 or features.shape[0] != weights.shape[0]:
        raise ValueError(f"features {features.shape} and weights {weights.shape} disagree")
    n, dim = features.shape
    exact = isinstance(codebook, str) and codebook == "none"
    assigned = weights > 0
    checked = unit_check(features)  # (rows with a direction, those not of unit length): one parallel pass the backends reuse
    lost = assigned & ~checked[0]
    if lost.any():  # every backend leaves them unassigned (a PQ code of a zero row decodes to some vector)
        log.warning("%d of %d Gaussians with weight have a feature that is zero or not finite: left unassigned", int(lost.sum()), n)
        assigned &= ~lost
        weights = np.where(lost, np.float32(0), weights)
    if exact:
        return LanguageField(dim, clip_model, weights, ExactStorage.encode(features, assigned, checked=checked), clip_weights)
    if isinstance(codebook, Codebook):
        book = codebook
    elif isinstance(codebook, str) and codebook == "scene":
        book = train_codebook(_scene_training_set(features, assigned, train_embeddings, seed), m=m, seed=seed)
    else:
        book = load_codebook(codebook)
    if book.dim != dim:
        raise InputError(book.path, f"codebook dimension {book.dim} differs from the features' dimension {dim} (a different CLIP model?)")
    return LanguageField(dim, clip_model, weights, BACKENDS[book.kind].encode(features, assigned, book, checked=checked), clip_weights)


def row_hashes(rows: np.ndarray, seed: int = 0) -> np.ndarray:
    """[n] uint64: a 64-bit hash of each row's bytes (rows [n, ...], each row a whole number of
    32-bit words): FNV-1a over the words, seeded, then splitmix64's finaliser so that every bit of
    the key depends on every word,

        h ← (h ⊕ word) · 1099511628211  (mod 2⁶⁴),  h₀ = 14695981039346656037 ⊕ seed

    Two rows of the same bytes hash alike wherever they sit, which is what makes a sample drawn by
    these keys independent of the rows' order."""
    rows = np.ascontiguousarray(rows)
    n = rows.shape[0]
    row_bytes = rows.itemsize * int(np.prod(rows.shape[1:], dtype=np.int64))
    if row_bytes % 4:
        raise ValueError(f"rows of {row_bytes} bytes are not whole 32-bit words")
    words = rows.reshape(n, row_bytes // rows.itemsize).view(np.uint8).view(np.uint32).astype(np.uint64)
    h = np.full(n, np.uint64(14695981039346656037) ^ np.uint64(seed & (2**64 - 1)), np.uint64)
    with np.errstate(over="ignore"):  # arithmetic mod 2⁶⁴ is the hash
        for column in words.T:
            h = (h ^ column) * np.uint64(1099511628211)
        h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return h ^ (h >> np.uint64(31))


SAMPLE_HASH_ROWS = 1 << 15  # rows hashed at once by `scene_sample_ids` (32,768 features of 512-D: 64 MB)


def scene_sample_ids(candidates: np.ndarray, rows_of: Callable[[np.ndarray], np.ndarray], seed: int = 0,
                     count: int = SCENE_FEATURE_SAMPLE) -> np.ndarray:
    """[min(n, count)] ids, in sample order, of the Gaussians among `candidates` [n] whose features
    top up a scene codebook's training set when the masks are too few: those whose rows
    `rows_of(ids)` ([len(ids), ...], the bytes that identify a Gaussian: its parameters, or its
    feature) have the `count` lowest `row_hashes` (ties, i.e. rows of the same bytes: the lower id),
    ordered by that key. So the sample and its order, and with them the codebook, do not depend on
    the order the scene file lists its Gaussians in (round 49: permuted, the sample drawn by id
    moved scores by up to 0.034). Hashed SAMPLE_HASH_ROWS rows at a time, keeping the best so far:
    O(n) time, O(count) memory beyond one chunk."""
    candidates = np.asarray(candidates, np.int64).reshape(-1)
    best_keys, best_ids = np.zeros(0, np.uint64), np.zeros(0, np.int64)
    for start in range(0, candidates.size, SAMPLE_HASH_ROWS):
        ids = candidates[start:start + SAMPLE_HASH_ROWS]
        keys = np.concatenate([best_keys, row_hashes(rows_of(ids), seed)])
        ids = np.concatenate([best_ids, ids])
        best_keys, best_ids = _lowest(keys, ids, count)
    order = np.lexsort((best_ids, best_keys))
    return best_ids[order]


def _lowest(keys: np.ndarray, ids: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """The `count` entries of lowest (key, id), in no particular order (all of them when fewer)."""
    if keys.size <= count:
        return keys, ids
    kth = np.partition(keys, count - 1)[count - 1]
    below = keys < kth
    tied = np.flatnonzero(keys == kth)
    tied = tied[np.argsort(ids[tied], kind="stable")[: count - int(below.sum())]]
    keep = np.concatenate([np.flatnonzero(below), tied])
    return keys[keep], ids[keep]


def scene_training_set(train: np.ndarray | None, sample_features: Callable[[], np.ndarray], dim: int) -> np.ndarray:
    """A scene codebook's training set [n, D]: the scene's mask embeddings `train`, topped up with
    `sample_features()` (unit features of sampled Gaussians, `scene_sample_ids`) when they are
    fewer than SCENE_MIN_TRAIN. InputError when even that is fewer than PQ_KSUB rows."""
    parts = [] if train is None else [np.asarray(train, np.float32)]
    have = sum(p.shape[0] for p in parts)
    if have < SCENE_MIN_TRAIN:
        extra = np.asarray(sample_features(), np.float32)
        parts.append(extra)
        log.info("scene codebook: %d mask embeddings topped up with %d Gaussian features", have, extra.shape[0])
    x = np.concatenate(parts) if parts else np.zeros((0, dim), np.float32)
    if x.shape[0] < PQ_KSUB:
        raise InputError(None, f"a scene codebook needs at least {PQ_KSUB} embeddings to train, the scene has {x.shape[0]}; use --codebook none or a general codebook")
    return x


def _scene_training_set(features: np.ndarray, assigned: np.ndarray, train: np.ndarray | None, seed: int) -> np.ndarray:
    return scene_training_set(train, lambda: features[scene_sample_ids(np.flatnonzero(assigned), lambda ids: features[ids], seed)],
                              features.shape[1])
