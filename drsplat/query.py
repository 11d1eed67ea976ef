"""Language queries on a registered field: cosine, LERF relevancy, thresholds, segmentation, clicks.

Every function takes a `drsplat.lang.LanguageField` and unit-normalised query embeddings [K, D]
(text through an encoder with `encode_text(list[str]) -> [K, D]` and `model_id`, an embedding
file, or the mean feature of clicked Gaussians) and returns per-Gaussian arrays in file order.

CLIP model ids: a field records the model that made its features (`clip_model`); text queries
must come from the same model. "unknown" (features without a manifest) is compared with anything,
with a warning; "oracle" (synthetic scenes) is a space of its own and only matches "oracle".
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from drsplat.defaults import MIN_NORM
from drsplat.errors import DrsplatError, InputError
from drsplat.features.modelid import CANONICAL_PHRASES, check_clip_weights, check_compatible
from drsplat.lang import LanguageField, has_direction, undirected_rows_problem, unit_rows, unit_rows64
from drsplat.utils import load_npy, real_number

log = logging.getLogger(__name__)

RELEVANCY_TEMPERATURE = 10.0
BACKGROUND_PHRASE = "background"


class TextEncoder(Protocol):
    model_id: str

    def encode_text(self, phrases: list[str]) -> np.ndarray: ...


# ---------------------------------------------------------------------------------------------
# Model ids


def check_clip_models(field_model: str | None, query_model: str | None, what: str = "the text encoder") -> None:
    """Refuse to compare embeddings of two different CLIP models (see drsplat.features.modelid)."""
    check_compatible(field_model, query_model, "the registered features", what)


# ---------------------------------------------------------------------------------------------
# Queries


def query_rows(x: np.ndarray, what: str = "query") -> np.ndarray:
    """Query-like embeddings as unit rows [K, D] float32; DrsplatError naming the first row that is
    not finite or is zero (`unit_rows` would make it a zero row, whose scores look like an
    unassigned Gaussian's, or a negative that never wins: a numerical probe, 2026-11-30)."""
    with np.errstate(over="ignore"):  # judged as `unit_rows` reads them: in float32 1e-50 is 0 and 1e39 is inf
        x = np.atleast_2d(np.asarray(x, np.float32))
    problem = undirected_rows_problem(x, what)
    if problem is not None:
        raise DrsplatError(problem)
    return unit_rows(x)


def field_rows(field: LanguageField, x: np.ndarray, what: str = "query") -> np.ndarray:
    """`query_rows` of x, DrsplatError when their width is not the field's D (round 85c F2: a 768-D negative met the
    512-D queries in numpy's concatenate, whose message named neither)."""
    rows = query_rows(x, what)
    if rows.shape[1] != field.dim:
        raise DrsplatError(f"the {what} rows are {rows.shape[1]}-D, but this field holds {field.dim}-D features")
    return rows


# 1 - cos below which two unit rows are one direction: a copy scaled by 1e-20 to 1e20 is within 2.1e-15 of its row after
# float32 rounding, so 1e-12 keeps a margin; a wider one joined distinct labels through chains of near ones (round 86a F2:
# at 1e-9, two labels 3° apart became one through 1,232 between them)
SAME_DIRECTION = 1e-12


def first_of_direction(units: np.ndarray) -> np.ndarray:
    """[Q] int64: for each of the unit rows units [Q, D], the lowest index of a row with its direction,
    1 - cos ≤ SAME_DIRECTION (itself where none is earlier; groups joined through any chain of such pairs). A row and
    its multiple c·x normalise to unit rows that differ in their last bits, so their scores differ by float32 noise in
    either direction (round 85c F1: eight labels and the same eight times 3, the copies won 1,590 of 2,757 Gaussians).
    Bit-identical rows are one row first; the others are compared only with rows whose projection on a fixed direction
    r lies within √(2·SAME_DIRECTION)·|r| of theirs (|a - b|² = 2(1 - cos) for unit a, b), after sorting by it:
    O(Q log Q) and a few dot products where the Q² of them would take minutes for 20,000 labels.
    `first_of_direction_reference` compares every pair."""
    q = units.shape[0]
    if q < 2:
        return np.arange(q, dtype=np.int64)
    _, rep, inverse = np.unique(units, axis=0, return_index=True, return_inverse=True)
    u = unit_rows64(units[rep])
    parent = np.arange(rep.size)

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    r = np.linspace(1.0, 2.0, u.shape[1])  # any fixed direction
    key = u @ r
    reach = math.sqrt(2.0 * SAME_DIRECTION) * float(np.linalg.norm(r))
    order = np.argsort(key, kind="stable")
    for a in range(order.size):
        b = a + 1
        while b < order.size and key[order[b]] - key[order[a]] <= reach:
            i, j = int(order[a]), int(order[b])
            if 1.0 - float(u[i] @ u[j]) <= SAME_DIRECTION and (ri := root(i)) != (rj := root(j)):
                parent[max(ri, rj)] = min(ri, rj)
            b += 1
    roots = np.array([root(i) for i in range(rep.size)])
    lowest = np.full(rep.size, q, np.int64)
    np.minimum.at(lowest, roots, rep)
    return lowest[roots][inverse.reshape(-1)]


def first_of_direction_reference(units: np.ndarray) -> np.ndarray:
    """`first_of_direction` by every pair: the groups are the connected parts of the graph 1 - cos ≤ SAME_DIRECTION."""
    q = units.shape[0]
    u = unit_rows64(units)
    near = 1.0 - u @ u.T <= SAME_DIRECTION
    first = np.arange(q, dtype=np.int64)
    for i in range(q):  # a breadth-first search from each row not yet in an earlier group
        if first[i] != i:
            continue
        group, frontier = {i}, [i]
        while frontier:
            frontier = [int(j) for f in frontier for j in np.flatnonzero(near[f]) if j not in group]
            group.update(frontier)
        first[sorted(group)] = i
    return first


def text_embeddings(encoder: TextEncoder, phrases: list[str], field: LanguageField | None = None) -> np.ndarray:
    """Unit text embeddings [K, D] of phrases, after checking the encoder matches the field's model."""
    if field is not None:  # the checkpoint given named: its label may be the field's tag (round 87c F4: a file never passed)
        given = getattr(encoder, "checkpoint", None)
        check_clip_models(field.clip_model, getattr(encoder, "model_id", None),
                          "the text encoder" + (f" (--clip-checkpoint {Path(given).name})" if given is not None else ""))
        if field.clip_weights is not None:  # the encoder's file is read only when there is something to compare it with
            check_clip_weights(field.clip_weights, getattr(encoder, "weights_digest", None), getattr(encoder, "checkpoint", None))
    emb = query_rows(encoder.encode_text(list(phrases)), "the text encoder's embedding of phrase")
    if field is not None and emb.shape[1] != field.dim:
        raise DrsplatError(f"the text encoder gives {emb.shape[1]}-D embeddings but the field holds {field.dim}-D features")
    return emb


def click_query(field: LanguageField, ids: np.ndarray) -> np.ndarray:
    """The paper's self-referencing query: normalize(mean of the unit features of Gaussians `ids`): [D].

    ids: [n] Gaussian indices (or an [N] bool mask), read as a set: an id given twice counts once, and the mean is taken
    in id order, so one set of Gaussians gives one query, the same bits in any order and as a
    boolean mask (round 50: 5 of 50 ids repeated moved the cosines by up to 0.0074). PQ fields use
    the reconstructions of those Gaussians. Gaussians without a feature (`LanguageField.assigned`:
    a PQ row's codes decode to a vector even then) are ignored.
    """
    given = np.asarray(ids).reshape(-1)
    if given.dtype == bool:  # a boolean [N] mask: its True rows (np.unique of the mask read [False, True] as ids 0 and 1)
        if given.shape[0] != len(field):
            raise DrsplatError(f"a boolean mask of Gaussians needs one entry per Gaussian ({len(field):,}), got {given.shape[0]:,}")
        given = np.flatnonzero(given)
    elif not np.issubdtype(given.dtype, np.integer):  # round 85c F4: float ids raised numpy's IndexError
        raise DrsplatError(f"Gaussian ids must be integers (or a boolean mask), got dtype {given.dtype}")
    if given.size == 0:  # it was told "all unassigned", though nothing was selected
        raise DrsplatError("no Gaussian ids given: a click query needs at least one Gaussian")
    outside = (given < 0) | (given >= len(field))  # -1 read the last Gaussian, so [-1, N-1] counted it twice (round 85c F4)
    if outside.any():
        raise DrsplatError(f"{int(outside.sum()):,} Gaussian ids fall outside 0..{len(field) - 1} (e.g. {int(given[outside][0])})")
    ids = np.unique(given)
    if ids.size < given.size:
        log.info("%d repeated Gaussian ids counted once", given.size - ids.size)
    ids = ids[field.assigned()[ids]] if ids.size else ids
    total, count = np.zeros(field.dim, np.float32), 0
    for lo in range(0, ids.size, CLICK_CHUNK):  # memory of one chunk, whatever the selection (round 61b: 15 kB an id at once)
        feats = unit_rows(field.reconstruct(ids[lo : lo + CLICK_CHUNK]))
        feats = feats[np.linalg.norm(feats, axis=1) > 0]
        # the running total first, then the chunk's rows one by one: numpy's float32 sum down axis 0, the bits of one mean of all rows
        total = np.concatenate((total[None], feats)).sum(axis=0)
        count += feats.shape[0]
    if count == 0:
        raise DrsplatError("none of the selected Gaussians has a language feature (all unassigned)")
    mean = total / count
    if not has_direction(mean)[0]:  # opposite features cancel: a zero query would be refused by the field
        raise DrsplatError(f"the features of the {count} selected Gaussians cancel out: their mean has no direction to query by")
    return unit_rows(mean)[0]


CLICK_CHUNK = 16_384  # Gaussians a click query reconstructs at a time (~64 MB of float64 unit rows at D = 512)


@dataclass
class EmbeddingRowProblems:
    """Rows of an embedding file [K, D] that float32 cannot use, each judged as stored (a float64 row
    of 1e-300 has a direction in its file; its float32 cast has none), one [K] mask per kind; a row
    is in the first kind it meets, in this order. norms: [K] float64, as stored."""

    beyond_float32: np.ndarray  # a finite value past ±3.4e38: the float32 cast is inf
    no_direction: np.ndarray  # zero, NaN or infinite
    huge_norm: np.ndarray  # finite values whose sum of squares overflows float32: not an embedding (CLIP's are near 1)
    tiny_norm: np.ndarray  # a norm below float32's smallest normal: subnormal entries keep a few bits each
    norms: np.ndarray

    def any(self) -> np.ndarray:
        return self.beyond_float32 | self.no_direction | self.huge_norm | self.tiny_norm

    def counts(self) -> str:
        """'2 beyond float32's range, 1 zero or non-finite' (the kinds that occur)."""
        kinds = (("beyond float32's range", self.beyond_float32), ("zero or non-finite", self.no_direction),
                 ("of a norm beyond float32's range", self.huge_norm), ("of a norm below float32's smallest normal", self.tiny_norm))
        return ", ".join(f"{int(m.sum())} {what}" for what, m in kinds if m.any())


def embedding_row_problems(arr: np.ndarray) -> EmbeddingRowProblems:
    """The rows of arr [K, D] (any float or integer dtype) that no float32 unit row can stand for
    (EmbeddingRowProblems). The norm is taken scaled by each row's largest entry, so that 1e-300
    squared is not 0 even in float64: norm = peak · ‖row / peak‖."""
    with np.errstate(invalid="ignore"):
        big = np.isfinite(arr) & (np.abs(arr) > np.finfo(np.float32).max) if arr.dtype.itemsize > 4 else np.zeros(arr.shape, bool)
    beyond = big.any(axis=1)
    wide = arr.astype(np.float64)
    no_direction = ~has_direction(wide) & ~beyond
    norms = np.zeros(len(arr))
    ok = ~(beyond | no_direction)
    peak = np.abs(wide[ok]).max(axis=1)
    norms[ok] = peak * np.linalg.norm(wide[ok] / peak[:, None], axis=1)
    huge = ok & (norms > np.finfo(np.float32).max)
    tiny = ok & (norms < MIN_NORM)
    return EmbeddingRowProblems(beyond, no_direction, huge, tiny, norms)


def load_query_embeddings(path: str | Path, dim: int, kind: str = "query") -> np.ndarray:
    """Read Q.npy, (D,) or (K, D), as unit rows [K, D] (InputError for bad shape or values). kind: what the rows are to
    the caller ("query", "negative", "label"), as an empty file's message says it (round 98c F3: "no query rows" for an
    empty --negative-embeddings)."""
    arr = _load_npy(path)
    shape = arr.shape  # as stored, for the message
    if not np.issubdtype(arr.dtype, np.floating) and not np.issubdtype(arr.dtype, np.integer):  # first: a string array's shape
        raise InputError(path, f"expected a float array, got dtype {arr.dtype}")  # is not its problem (round 98c F3)
    if arr.ndim == 1:
        arr = arr[None]
    if arr.ndim == 2 and arr.shape[1] == dim and arr.shape[0] == 0:  # the shape is one of those named, K = 0 (round 61b)
        raise InputError(path, f"holds no {kind} rows (shape {shape}); expected ({dim},) or (K, {dim}) with K >= 1")
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise InputError(path, f"expected shape ({dim},) or (K, {dim}), got {shape}")
    bad = embedding_row_problems(arr)
    if bad.beyond_float32.any():  # the float32 cast would make them inf (with numpy's overflow warning)
        raise InputError(path, f"rows {np.flatnonzero(bad.beyond_float32)[:10].tolist()} hold values beyond float32's range (±3.4e38); "
                               "embeddings are stored as float32")
    if bad.no_direction.any():
        raise InputError(path, f"rows {np.flatnonzero(bad.no_direction)[:10].tolist()} are zero or non-finite")
    if bad.huge_norm.any():
        raise InputError(path, f"rows {np.flatnonzero(bad.huge_norm)[:10].tolist()} have a norm of {bad.norms[bad.huge_norm].max():.3g}, beyond "
                               "float32's range (the sum of squares overflows); this is not an embedding: rescale it")
    if bad.tiny_norm.any():
        raise InputError(path, f"rows {np.flatnonzero(bad.tiny_norm)[:10].tolist()} have a norm of {bad.norms[bad.tiny_norm].min():.3g}, below "
                               f"float32's smallest normal number ({MIN_NORM:.3g}): too few bits to hold a direction; this is not an "
                               "embedding: rescale it")
    return unit_rows(arr.astype(np.float32))


def load_gaussian_ids(path: str | Path, n: int) -> np.ndarray:
    """Read IDS.npy: integer indices [k] into 0..n-1, or a boolean mask [n]."""
    arr = _load_npy(path)
    if arr.ndim > 1:
        raise InputError(path, f"expected a 1-D array of Gaussian indices or a boolean mask, got shape {arr.shape}")
    arr = arr.reshape(-1)
    if arr.dtype == bool:
        if arr.shape[0] != n:
            raise InputError(path, f"boolean mask has {arr.shape[0]} entries, the scene has {n} Gaussians")
        if not arr.any():
            raise InputError(path, f"the boolean mask selects none of the {n} Gaussians")
        return np.flatnonzero(arr)
    if not np.issubdtype(arr.dtype, np.integer):
        raise InputError(path, f"expected integer Gaussian indices, got dtype {arr.dtype}")
    if arr.size == 0:
        raise InputError(path, "no Gaussian indices given")
    out = (arr < 0) | (arr >= n)
    if out.any():
        raise InputError(path, f"{int(out.sum())} indices fall outside 0..{n - 1} (e.g. {int(arr[out][0])})")
    if n > 2 and arr.shape[0] == n and arr.min() >= 0 and arr.max() <= 1:  # a mask saved as 0/1 integers reads as ids 0 and 1
        log.warning("%s: %d integer entries, one per Gaussian, all 0 or 1: read as the Gaussian ids 0 and 1; save a boolean mask "
                    "(dtype bool) to select by mask", path, n)
    return arr.astype(np.int64)


def _load_npy(path: str | Path) -> np.ndarray:
    return load_npy(path)


# ---------------------------------------------------------------------------------------------
# Scores


def cosine(field: LanguageField, queries: np.ndarray, lut_bits: int = 32, device: str | None = None) -> np.ndarray:
    """cos(q_k, f_i) of every Gaussian and query: queries [K, D] -> [N, K] float32 (0 if unassigned).

    lut_bits: 32 exact look-up tables, 8 the faster 8-bit tables (PQ fields; see LanguageField.scores).
    """
    return field.scores(query_rows(queries), lut_bits=lut_bits, device=device)


def relevancy_from_scores(positive: np.ndarray, negative: np.ndarray, temperature: float = RELEVANCY_TEMPERATURE) -> np.ndarray:
    """LERF relevancy from cosines: positive [N, K], negative [N, C] -> [N, K].

    rel = min_c softmax(t·[p, n_c])[0] = min_c σ(t(p − n_c)) = σ(t(p − max_c n_c)),
    the probability of the query against its hardest canonical phrase (t = 10 as LERF/LangSplat).
    In float64, RELEVANCY_ROWS rows at a time: whole, its temporaries took 4x the [N, K] float32 result
    (5M Gaussians, K = 30: 6.5 GB against cosine's 3.0; round 61b). t must be finite and positive: NaN scored every
    Gaussian NaN, a negative t turned the ranking over, t = 0 gave every Gaussian ½ (round 98c F2).
    """
    t = real_number(temperature)  # used as the check read it: a Decimal or "10" passed the check, then failed numpy's multiply (round 100a F4)
    if not (math.isfinite(t) and t > 0):
        raise DrsplatError(f"the relevancy temperature must be a finite positive number (LERF's is {RELEVANCY_TEMPERATURE}), got {temperature!r}")
    out = np.empty(positive.shape, np.float32)
    for lo in range(0, positive.shape[0], RELEVANCY_ROWS):
        rows = slice(lo, lo + RELEVANCY_ROWS)
        p = positive[rows]
        hardest = negative[rows].max(axis=1, keepdims=True) if negative.shape[1] else np.full((p.shape[0], 1), -np.inf, np.float32)
        z = t * (p.astype(np.float64) - hardest)
        out[rows] = 0.5 * (1.0 + np.tanh(0.5 * z))
    return out


RELEVANCY_ROWS = 1 << 16  # Gaussians whose relevancy is computed at a time


def relevancy_reference(positive: np.ndarray, negative: np.ndarray, temperature: float = RELEVANCY_TEMPERATURE) -> np.ndarray:
    """The official LangSplat formulation, literally: pairwise softmax per negative, min over negatives."""
    n, k = positive.shape
    out = np.empty((n, k), np.float64)
    for j in range(k):
        sims = np.stack([np.repeat(positive[:, j : j + 1], negative.shape[1], 1), negative], axis=-1) * temperature
        sims = sims - sims.max(axis=-1, keepdims=True)
        soft = np.exp(sims) / np.exp(sims).sum(axis=-1, keepdims=True)
        out[:, j] = soft[..., 0].min(axis=1)
    return out.astype(np.float32)


def relevancy(field: LanguageField, queries: np.ndarray, negatives: np.ndarray, temperature: float = RELEVANCY_TEMPERATURE, lut_bits: int = 32,
              device: str | None = None) -> np.ndarray:
    """LERF relevancy of every Gaussian: queries [K, D], negatives [C, D] -> [N, K] in [0, 1]; 0 for a Gaussian without a
    feature (`LanguageField.assigned`), as Dr. Splat's render_activation.py gives it (its cosines against the query and
    every negative are 0, a relevancy of ½ that a file of scores thresholded at 0.5 selected: round 75c F2).

    negatives are the canonical phrases' embeddings ("object", "things", "stuff", "texture"),
    optionally followed by user negatives. One LUT pass scores queries and negatives together.
    The relevancy is LERF's and LangSplat's: of cosines, the reconstruction r_i normalised on a PQ field. Dr. Splat's
    render_activation.py takes the raw dot products of `sa_decode`'s r_i (|r_i| 0.57-1.0 with its codebook), which
    scales t = 10 by |r_i| per Gaussian: the same selection at τ = 0.5, other scores elsewhere.
    """
    if len(negatives) == 0:
        raise DrsplatError("relevancy needs at least one negative embedding")
    q, neg = field_rows(field, queries), field_rows(field, negatives, "negative")
    scores = field.scores(np.concatenate([q, neg]), lut_bits=lut_bits, device=device)
    out = relevancy_from_scores(scores[:, : q.shape[0]], scores[:, q.shape[0] :], temperature)
    out[~field.assigned()] = 0.0
    return out


def negative_embeddings(encoder: TextEncoder | None, field: LanguageField, user_phrases: list[str] = (), extra: np.ndarray | None = None) -> np.ndarray:
    """Canonical + user negative embeddings [C, D]: text through `encoder`, plus rows of `extra`."""
    parts = []
    if encoder is not None:
        parts.append(text_embeddings(encoder, list(CANONICAL_PHRASES) + list(user_phrases), field))
    elif user_phrases:
        raise DrsplatError("negative phrases need a CLIP text encoder")
    if extra is not None:
        parts.append(query_rows(extra, "negative embedding"))
    if not parts:
        raise DrsplatError("relevancy needs negatives: a CLIP text encoder for the canonical phrases, or negative embeddings")
    return np.concatenate(parts)


# ---------------------------------------------------------------------------------------------
# Thresholds and segmentation


def thresholds_as_compared(thresholds, scores: np.ndarray) -> np.ndarray:
    """The thresholds τ (float64, any shape) as `scores` meet them: rounded to float32 when the
    scores are float32, as the official code's tensors compare. A score of float32(0.7) lies below
    the float64 0.7 but equals float32(0.7): "score ≥ 0.7" then selects it, as the user meant."""
    taus = np.asarray(thresholds, np.float64)
    if np.asarray(scores).dtype != np.float32:
        return taus
    with np.errstate(over="ignore"):  # a threshold past float32's range is ±inf there, and compares as it should
        return taus.astype(np.float32).astype(np.float64)


def select(scores: np.ndarray, threshold: float, assigned: np.ndarray | None = None) -> np.ndarray:
    """Boolean selection scores >= threshold: [N] -> [N] (NaN never selected), among the Gaussians
    `assigned` [N] bool (`LanguageField.assigned`) when given: one without a feature scores 0 as a
    cosine and as a relevancy, which a threshold at or below it would otherwise select. Float32
    scores meet the threshold in float32 (`thresholds_as_compared`). A NaN threshold is refused: it would select
    nothing without a word (round 91d F4); ±inf select none / all."""
    if np.isnan(np.asarray(threshold, np.float64)).any():
        raise ValueError(f"the threshold is {threshold!r}, which selects nothing: give a number (-inf selects every Gaussian)")
    picked = np.asarray(scores) >= thresholds_as_compared(threshold, scores)
    return picked if assigned is None else picked & assigned


def threshold_digits(threshold: float, best: float) -> int:
    """The decimals a message shows `threshold` and the best score with: 4, or more where 4 show two different values
    alike ("no Gaussian scores >= 0.3763 (the best score is 0.3763)": round 78b F1), at most 17."""
    return next(d for d in range(4, 18) if f"{threshold:.{d}f}" != f"{best:.{d}f}" or d == 17)


def otsu_scores(scores: np.ndarray) -> np.ndarray:
    """The scores Otsu splits: the finite, nonzero ones, float64. An unassigned Gaussian's cosine and relevancy are 0
    and drop out (`drsplat query` and the viewer pass the assigned rows only all the same)."""
    s = np.asarray(scores, np.float64)
    return s[np.isfinite(s) & (s != 0)]


OTSU_NOISE_SPREAD = 1e-5  # scores spanning less than this are float32 rounding of one value (a query unlike every feature: ~1e-8)


def otsu_split_problem(scores: np.ndarray, threshold: float) -> str | None:
    """Why Otsu's `threshold` of `scores` is no real split, in words, or None when it is one: no
    score but 0, one value only, or a span under OTSU_NOISE_SPREAD (float32 rounding of one value).
    `drsplat query` and the viewer each say it in their own terms."""
    scored = otsu_scores(scores)
    if scored.size == 0:
        return f"no Gaussian scores anything but 0, so there is nothing to split; every assigned Gaussian scores {threshold:.4f} and is selected"
    if scored.min() == scored.max():  # Otsu splits two groups; one value has none to split
        return f"every one of the {scored.size:,} scored Gaussians scores {threshold:.4f}, so there is nothing to split; all of them are selected"
    if scored.max() - scored.min() < OTSU_NOISE_SPREAD:
        return (f"the {scored.size:,} scored Gaussians' scores span only {scored.max() - scored.min():.2g}, so the split ({threshold:.4g}) "
                "is rounding noise, not a match")
    return None


def otsu_threshold(scores: np.ndarray, bins: int = 256) -> float:
    """Threshold maximising the between-class variance of `otsu_scores` (Otsu); with one value
    among them (nothing to split), that value, which selects them all.

    The classes are the scores' distinct values when there are at most `bins` of them (exact,
    however close: scores one float64 ulp apart made np.histogram refuse), else a histogram of
    `bins` bins. The threshold returned is the lowest score of the upper class, a value the scores
    hold, so `scores >= threshold` selects that class in the scores' own dtype (a float64 bin edge
    between two float32 scores one ulp apart rounded onto the lower one, which was then selected
    too: a numerical probe, 2026-11-30)."""
    s = otsu_scores(scores)
    if s.size == 0 or s.min() == s.max():
        return float(s.max()) if s.size else 0.0
    values, counts = np.unique(s, return_counts=True)
    if values.size <= bins:
        centers, hist = values, counts
    else:
        hist, edges = np.histogram(s, bins=bins)
        centers = 0.5 * (edges[:-1] + edges[1:])
    p = hist / hist.sum()
    w0 = np.cumsum(p)
    mu = np.cumsum(p * centers)
    w1 = 1 - w0
    with np.errstate(divide="ignore", invalid="ignore"):
        between = (mu[-1] * w0 - mu) ** 2 / (w0 * w1)
    between = np.nan_to_num(between, nan=-1.0, posinf=-1.0)
    split = int(np.argmax(between))  # the lower class is bins 0 .. split
    if values.size <= bins:
        return float(values[split + 1])
    upper = s[s >= edges[split + 1]]
    return float(upper.min()) if upper.size else float(edges[split + 1])


@dataclass
class Segmentation:
    """Argmax segmentation. labels: [N] int32 label index, -1 for background / unassigned / low score.
    scores: [N] float32 cosine of the winning label (of background where it won)."""

    labels: np.ndarray
    scores: np.ndarray


def segment(field: LanguageField, label_embeddings: np.ndarray, background: np.ndarray | None = None, min_score: float | None = None, lut_bits: int = 32,
            device: str | None = None) -> Segmentation:
    """Label every Gaussian with argmax_l cos(e_l, f_i) over labels [L, D]; of labels of one direction
    (`first_of_direction`: a row and its multiple) the first takes every Gaussian, as of equal rows.

    background: [D] or [B, D] embeddings of background phrases; Gaussians they win get -1.
    min_score: Gaussians whose best cosine is below it get -1 (a finite number: ValueError for NaN,
    which would cut nothing, and ±inf). Unassigned Gaussians get -1.
    """
    if min_score is not None and not math.isfinite(min_score):
        raise ValueError(f"min_score must be a finite cosine, got {min_score!r}")
    labels_emb = field_rows(field, label_embeddings, "label embedding")
    n_labels = labels_emb.shape[0]
    if n_labels == 0:  # every Gaussian was labelled background with a best score of -inf (round 98c F1)
        raise DrsplatError("segmentation needs at least one label embedding")
    queries = labels_emb if background is None else np.concatenate([labels_emb, field_rows(field, background, "background embedding")])
    queries = queries[first_of_direction(queries)]  # rows of one direction are one label: the first wins their ties, as documented
    best, best_score = _argmax_scores(field, queries, lut_bits, device)
    labels = np.where(best < n_labels, best, -1).astype(np.int32)
    labels[~field.assigned()] = -1  # unassigned (0) and non-finite features (they score 0; read_field warns)
    if min_score is not None:  # met as `select` meets a threshold, whatever min_score's type (round 91d F3: NumPy 2 compared a
        labels[best_score < thresholds_as_compared(min_score, best_score)] = -1  # float in float32, an np.float64 in float64)
    return Segmentation(labels=labels, scores=best_score.astype(np.float32))


SEGMENT_SCORE_BYTES = 256 << 20  # the [N, L'] scores `segment` holds at a time: L' labels a pass (at least SEGMENT_MIN_LABELS)
SEGMENT_MIN_LABELS = 8
SEGMENT_TABLE_BYTES = 128 * 256 * 4  # a query's look-up tables at M = 128 (an exact field's query row is less)


def _argmax_scores(field: LanguageField, queries: np.ndarray, lut_bits: int, device: str | None) -> tuple[np.ndarray, np.ndarray]:
    """(argmax over queries [Q, D] of each Gaussian's score [N] int64, that score [N] float32), the first of equal scores
    as np.argmax picks it, scoring a few queries at a time: a query's scores are the same bits alone and in a batch, and
    the whole [N, Q] took 6.4 GB for 200 labels on 5M Gaussians (round 61b)."""
    n = len(field)
    # each query's look-up tables too (a PQ field's M x 256 floats): on a small scene they, not the scores, were the memory
    # (1,001 Gaussians, 20k labels in one pass: 3.1 GB; round 62a)
    per = max(SEGMENT_MIN_LABELS, SEGMENT_SCORE_BYTES // (4 * max(n, 1) + SEGMENT_TABLE_BYTES))
    best, best_score = np.zeros(n, np.int64), np.full(n, -np.inf, np.float32)
    for lo in range(0, queries.shape[0], per):
        scores = field.scores(queries[lo : lo + per], lut_bits=lut_bits, device=device)
        here = np.argmax(scores, axis=1)
        score = scores[np.arange(n), here]
        # strictly better; NaN wins as it does in np.argmax (the first NaN), and keeps its place
        take = (score > best_score) | (np.isnan(score) & ~np.isnan(best_score))
        best[take], best_score[take] = here[take] + lo, score[take]
    return best, best_score


def label_colors(count: int) -> np.ndarray:
    """[count, 3] distinct RGB colours in [0, 1] (golden-ratio hues)."""
    import colorsys

    return np.array([colorsys.hsv_to_rgb((0.13 + i * 0.618033988749895) % 1.0, 0.75, 0.95) for i in range(count)], np.float32).reshape(count, 3)
