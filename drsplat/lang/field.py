"""`LanguageField`: per-Gaussian language features in one storage backend (exact fp16, PQ, IVFPQ), built from registration results."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drsplat.errors import InputError
from drsplat.lang.codebook import PQ_KSUB, Codebook, load_codebook, train_codebook, unit_rows
from drsplat.lang.lut import BLOCKED_MIN_M, blocked_codes, half_scores, lut_scores, lut_scores_blocked, lut_scores_reference, simd_available

log = logging.getLogger(__name__)

KINDS = ("exact", "pq", "ivfpq")
ENCODE_CHUNK = 65536
EXACT_CHUNK = 32768
SCENE_MIN_TRAIN = 10 * PQ_KSUB
SCENE_FEATURE_SAMPLE = 20000



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
    _on_device: object | None = dataclasses.field(default=None, init=False, repr=False, compare=False)

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

    def scores(self, queries: np.ndarray, lut_bits: int = 32, device: str | None = None) -> np.ndarray:
        """Cosine similarity of every Gaussian to each query: queries [K, D] or [D] -> [N, K] float32.

        Queries are L2-normalised; features are compared through their stored norm, so the
        result is cos(q, f_i) for exact fields and cos(q, r_i) for PQ reconstructions r_i.
        Unassigned Gaussians (zero norm) score 0.
        lut_bits: 32 (default) scores PQ fields with float32 tables (exact up to rounding);
        8 uses 8-bit tables (`lut_scores_blocked`, an approximation). Exact fields have no tables
        and ignore it. On AVX-512 CPUs with M ≥ 128 (and always for lut_bits=8) PQ fields are
        scored on a blocked copy of the codes, built by the first call and kept (M more bytes
        per Gaussian).
        device: None = the numba CPU kernels; "cpu" / "cuda" = the torch kernels on that device
        (drsplat.lang.torch_scoring; float32 tables only; the field is copied there on first use and kept).
        """
        if lut_bits not in (8, 32):
            raise ValueError(f"lut_bits must be 8 or 32, got {lut_bits}")
        q = unit_rows(self._check_queries(queries))
        if device is not None:
            return self.scores_torch(q, device, lut_bits).cpu().numpy()
        if self.kind == "exact":
            return half_scores(self.features, self.norms, q)
        if lut_bits == 8 or (self.codebook.m >= BLOCKED_MIN_M and simd_available()):
            return lut_scores_blocked(self.codebook, self.blocked_codes(), self.num_gaussians, self.list_ids, self.norms, q, lut_bits)
        return lut_scores(self.codebook, self.codes, self.list_ids, self.norms, q)

    def scores_torch(self, queries: np.ndarray, device: str, lut_bits: int = 32):
        """`scores` as a torch tensor [N, K] float32 on `device` (unit queries)."""
        from drsplat.lang import torch_scoring

        if lut_bits != 32:
            raise ValueError("8-bit tables are a CPU (AVX-512) kernel; the torch scorer uses float32 tables (lut_bits=32)")
        if self._on_device is None or str(self._on_device.device) != str(torch_scoring.torch.device(device)):
            self._on_device = torch_scoring.to_device(self, device)
        return torch_scoring.field_scores_torch(self, np.asarray(queries, np.float32), self._on_device)

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


