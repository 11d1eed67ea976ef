"""Training-free registration: lift per-mask embeddings onto Gaussians (Dr. Splat, Sec. 3).

For every training view the rasterizer keeps, per pixel, the top-k Gaussians by blending
weight w = T·α. Pixel p lies in mask j of that view (LangSplat feature files, one level), so
Gaussian i collects w_ij = Σ_{p ∈ mask j} w_i(p). Each Gaussian's feature is

    f_i = normalize(Σ_j w_ij f_j / Σ_j w_ij) = normalize(Σ_j w_ij f_j)

and its weight W_i = Σ_j w_ij (0 = never seen inside a mask: unassigned).

Memory is proportional to N·D: per view, the (Gaussian, mask) pairs are coalesced mask by mask
in a scratch array of N floats into a bounded buffer of distinct pairs, which is folded into the
running sums F [N, D] and W [N] grouped by Gaussian (each F row read and written once per
flush, which keeps the N·D array's memory traffic low). No N x M matrix (Gaussians x masks),
dense or global, is ever formed.
"""

from __future__ import annotations

import hashlib
import logging
import time
import zipfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np

from drsplat.cameras import Camera
from drsplat.defaults import DEFAULT_AGGREGATE, DEFAULT_LEVEL, DEFAULT_TOPK
from drsplat.errors import DrsplatError, InputError
from drsplat.features.format import feat_path, list_stems, read_features_report, resample_nearest
from drsplat.pairlog import PairLog, ViewPairs
from drsplat.scene import GaussianScene
from drsplat.utils import CancelToken, progress

log = logging.getLogger(__name__)
CHECKPOINT_EVERY = 10  # views between snapshots of an aggregation mode's statistics (the pair log itself is per view)

CHECKPOINT_VERSION = 2  # 2: append-only pair log (drsplat.pairlog); 1 was a dense F/W .npz
MAX_BUFFERED_ROWS = 1 << 16  # mask embeddings held between flushes (32 MB at D = 512)


@dataclass
class RegistrationResult:
    """Registered language features of a scene.

    features: [N, D] float32 unit rows (zero rows where unassigned); None when the registration
    streamed Gaussian blocks straight to the PLY (drsplat.streaming), which never holds [N, D].
    weights: [N] float32 total weight Σ_j w_ij (0 = unassigned).
    seconds: wall time; raster_seconds / accumulate_seconds: its two main stages (accumulation
    includes coalescing each view's pairs, coalesce_seconds, done where the view is rendered);
    accumulate_cpu_seconds: CPU time of all threads in accumulation (steadier on a busy machine).
    allocate_seconds: creating the N x D sums (page faults of a large array, once per run).
    num_views: views registered (resumed ones included). num_pairs: contributing
    (Gaussian, pixel) pairs, i.e. top-k entries inside a mask. num_distinct_pairs: distinct
    (Gaussian, mask) pairs summed over views.
    missing_features: camera names without a feature file; unmatched_features: feature stems
    without a camera. num_nonfinite_masks: masks dropped for non-finite embeddings.
    mask_embeddings: [M_total, D] every mask embedding used (only with collect_embeddings).
    aggregate: the aggregation mode (drsplat.aggregate); num_rejected: Gaussians it left unassigned.
    """

    features: np.ndarray | None
    weights: np.ndarray
    num_views: int
    num_pairs: int
    num_distinct_pairs: int
    seconds: float
    raster_seconds: float = 0.0
    accumulate_seconds: float = 0.0
    accumulate_cpu_seconds: float = 0.0
    allocate_seconds: float = 0.0
    coalesce_seconds: float = 0.0
    resumed_views: int = 0
    topk: int = DEFAULT_TOPK
    level: int = DEFAULT_LEVEL
    missing_features: list[str] = field(default_factory=list)
    unmatched_features: list[str] = field(default_factory=list)
    num_nonfinite_masks: int = 0
    num_nonfinite_features: int = 0
    mask_embeddings: np.ndarray | None = None
    aggregate: str = DEFAULT_AGGREGATE
    num_rejected: int = 0

    @property
    def assigned(self) -> np.ndarray:
        """[N] bool, Gaussians that received weight."""
        return self.weights > 0

    @property
    def num_assigned(self) -> int:
        return int(np.count_nonzero(self.weights > 0))


# ----------------------------------------------------------------------------- the kernel


@numba.njit(cache=True)
def _coalesce_view_kernel(ids, weights, mask_ids, num_masks, first_mask, row_offset, seen, acc, touched, out_g, out_row, out_w, filled):  # pragma: no cover - jitted
    """Append the view's distinct (Gaussian, mask) pairs with summed weights to the out_* buffers.

    Pixels are bucketed by mask (counting sort); per mask the weights of its pixels' top-k
    Gaussians are summed in `acc` (scratch [N], `seen` [N] all -1 on entry and exit). Starts at
    mask `first_mask`; stops before a mask whose pairs might not fit. Mask m is written as row
    row_offset + m. Returns (contributing pairs, distinct pairs, next mask, filled).
    """
    num_pixels, k = ids.shape
    num_gaussians = seen.shape[0]
    capacity = out_g.shape[0]
    starts = np.zeros(num_masks + 1, np.int64)
    for p in range(num_pixels):
        m = mask_ids[p]
        if m >= first_mask:
            starts[m + 1] += 1
    for m in range(num_masks):
        starts[m + 1] += starts[m]
    order = np.empty(starts[num_masks], np.int64)
    fill = starts[:num_masks].copy()
    for p in range(num_pixels):
        m = mask_ids[p]
        if m >= first_mask:
            order[fill[m]] = p
            fill[m] += 1
    num_pairs = 0
    num_distinct = 0
    for m in range(first_mask, num_masks):
        bound = min(num_gaussians, (starts[m + 1] - starts[m]) * k)
        if filled + bound > capacity:
            return num_pairs, num_distinct, m, filled
        count = 0
        for o in range(starts[m], starts[m + 1]):
            p = order[o]
            for s in range(k):
                g = ids[p, s]
                if g < 0:
                    continue
                if seen[g] != m:
                    seen[g] = m
                    acc[g] = 0.0
                    touched[count] = g
                    count += 1
                acc[g] += weights[p, s]
                num_pairs += 1
        for t in range(count):
            g = touched[t]
            out_g[filled] = g
            out_row[filled] = row_offset + m
            out_w[filled] = acc[g]
            filled += 1
            seen[g] = -1
        num_distinct += count
    return num_pairs, num_distinct, num_masks, filled


@numba.njit(parallel=True, cache=True)
def _flush_pairs_kernel(pair_g, pair_row, pair_w, filled, rows, F, W):  # pragma: no cover - jitted
    """F[g] += Σ w·rows[row] and W[g] += Σ w over the buffered pairs, one Gaussian per thread
    at a time (pairs grouped by Gaussian with a counting sort), so each F row is read and
    written once per flush."""
    num_gaussians, dim = F.shape
    starts = np.zeros(num_gaussians + 1, np.int64)
    for i in range(filled):
        starts[pair_g[i] + 1] += 1
    for g in range(num_gaussians):
        starts[g + 1] += starts[g]
    order = np.empty(filled, np.int32)
    fill = starts[:num_gaussians].copy()
    for i in range(filled):
        g = pair_g[i]
        order[fill[g]] = i
        fill[g] += 1
    for g in numba.prange(num_gaussians):
        if starts[g] == starts[g + 1]:
            continue
        f = F[g]
        for o in range(starts[g], starts[g + 1]):
            i = order[o]
            w = pair_w[i]
            row = rows[pair_row[i]]
            W[g] += w  # pair by pair in view order: the sums do not depend on when flushes happen
            for d in range(dim):  # row views, not F[g, d]: this loop must vectorise
                f[d] += w * row[d]


class Accumulator:
    """Running sums F [N, D] = Σ_j w_ij f_j and W [N] = Σ_j w_ij.

    Views are coalesced into a buffer of distinct (Gaussian, mask) pairs plus the embeddings of
    the buffered masks; a flush folds the buffer into F grouped by Gaussian, so memory is
    N·D + the buffer (`pair_capacity` pairs, at least N), never Gaussians x masks.
    """

    def __init__(self, num_gaussians: int, dim: int, pair_capacity: int = 1 << 23):
        self.F = np.empty((num_gaussians, dim), np.float32)
        self.F.fill(0.0)  # touch every page now, not inside the first flush
        self.W = np.zeros(num_gaussians, np.float32)
        self._seen = np.full(num_gaussians, -1, np.int32)
        self._acc = np.zeros(num_gaussians, np.float32)
        self._touched = np.zeros(num_gaussians, np.int32)
        capacity = max(pair_capacity, num_gaussians, 1)
        self._pair_g = np.zeros(capacity, np.int32)
        self._pair_row = np.zeros(capacity, np.int32)
        self._pair_w = np.zeros(capacity, np.float32)
        self._filled = 0
        self._rows = np.zeros((256, dim), np.float32)
        self._num_rows = 0

    @property
    def dim(self) -> int:
        return self.F.shape[1]

    def add_view(self, ids: np.ndarray, weights: np.ndarray, mask_ids: np.ndarray, feats: np.ndarray) -> tuple[int, int]:
        """Add one view (numba). Returns (contributing pairs, distinct (Gaussian, mask) pairs).

        ids, weights: [H, W, k] top-k Gaussian ids (-1 = none) and w = T·α per pixel.
        mask_ids: [H, W] mask of each pixel (-1 = none), rows of feats: [M, D].
        """
        k = ids.shape[-1]
        ids2 = np.ascontiguousarray(ids.reshape(-1, k), np.int32)
        w2 = np.ascontiguousarray(weights.reshape(-1, k), np.float32)
        masks = np.ascontiguousarray(mask_ids.reshape(-1), np.int32)
        offset = self._push_rows(np.asarray(feats, np.float32))
        num_masks = feats.shape[0]
        pairs = distinct = 0
        first = 0
        while True:
            p, d, first, self._filled = _coalesce_view_kernel(
                ids2, w2, masks, num_masks, first, offset, self._seen, self._acc, self._touched,
                self._pair_g, self._pair_row, self._pair_w, self._filled,
            )
            pairs += p
            distinct += d
            if first >= num_masks:
                return pairs, distinct
            self.flush(keep_last=num_masks)
            offset = 0

    def add_pairs(self, gaussians: np.ndarray, masks: np.ndarray, weights: np.ndarray, feats: np.ndarray) -> None:
        """Add one view's distinct pairs (as `Coalescer.coalesce` returns them) to the buffer.

        gaussians: [P] int32 ids (rows of F), masks: [P] int32 rows of feats [M, D], weights: [P]
        float32. Pairs keep their order, so the sums equal `add_view`'s bit for bit.
        """
        num_masks = feats.shape[0]
        if self._num_rows > MAX_BUFFERED_ROWS:  # bound the embedding buffer of sparse views too
            self.flush()
        offset = self._push_rows(np.asarray(feats, np.float32))
        start, total = 0, gaussians.shape[0]
        capacity = self._pair_g.shape[0]
        while start < total:
            if self._filled == capacity:
                self.flush(keep_last=num_masks)
                offset = 0
            take = min(capacity - self._filled, total - start)
            dst = slice(self._filled, self._filled + take)
            self._pair_g[dst] = gaussians[start : start + take]
            self._pair_row[dst] = masks[start : start + take] + offset
            self._pair_w[dst] = weights[start : start + take]
            self._filled += take
            start += take

    def _push_rows(self, feats: np.ndarray) -> int:
        """Store a view's embeddings after the buffered ones; returns their first row."""
        need = self._num_rows + feats.shape[0]
        if need > self._rows.shape[0]:
            grown = np.zeros((max(need, 2 * self._rows.shape[0]), self.dim), np.float32)
            grown[: self._num_rows] = self._rows[: self._num_rows]
            self._rows = grown
        self._rows[self._num_rows : need] = feats
        offset, self._num_rows = self._num_rows, need
        return offset

    def flush(self, keep_last: int = 0) -> None:
        """Fold the buffered pairs into F and W; keep the last `keep_last` embedding rows (the
        view being added) as rows 0..keep_last-1."""
        if self._filled:
            _flush_pairs_kernel(self._pair_g, self._pair_row, self._pair_w, self._filled, self._rows, self.F, self.W)
        self._filled = 0
        if keep_last:
            self._rows[:keep_last] = self._rows[self._num_rows - keep_last : self._num_rows].copy()
        self._num_rows = keep_last

    def sums(self) -> tuple[np.ndarray, np.ndarray]:
        """(F [N, D], W [N]) with every added view folded in."""
        self.flush()
        return self.F, self.W


def accumulate_view_reference(F: np.ndarray, W: np.ndarray, ids: np.ndarray, weights: np.ndarray, mask_ids: np.ndarray, feats: np.ndarray) -> int:
    """Obviously-correct reference of Accumulator.add_view (scipy sparse, float64).

    A = sparse [N, M] with A_ij = Σ_p [mask(p) = j] Σ_s [id_s(p) = i] w_s(p); then F += A·feats
    and W += A·1. Returns the number of contributing pairs.
    """
    import scipy.sparse

    k = ids.shape[-1]
    g = ids.reshape(-1).astype(np.int64)
    m = np.repeat(mask_ids.reshape(-1).astype(np.int64), k)
    w = weights.reshape(-1).astype(np.float64)
    keep = (g >= 0) & (m >= 0)
    a = scipy.sparse.coo_matrix((w[keep], (g[keep], m[keep])), shape=(F.shape[0], feats.shape[0])).tocsr()
    F += (a @ feats.astype(np.float64)).astype(F.dtype)
    W += np.asarray(a.sum(axis=1)).reshape(-1).astype(W.dtype)
    return int(np.count_nonzero(keep))


def normalize_rows(F: np.ndarray, W: np.ndarray, chunk: int = 65536) -> tuple[np.ndarray, int]:
    """In place: F_i <- F_i / |F_i| where W_i > 0 and F_i is finite and non-zero; other rows -> 0
    (and their W_i -> 0). Returns (F, count of rows dropped for non-finite values)."""
    bad_total = 0
    for start in range(0, F.shape[0], chunk):
        f, w = F[start : start + chunk], W[start : start + chunk]
        norm = np.sqrt(np.einsum("nd,nd->n", f, f, dtype=np.float64))
        finite = np.isfinite(norm) & np.isfinite(w)
        bad_total += int(np.count_nonzero(~finite & (w != 0)))
        ok = finite & (w > 0) & (norm > 0)
        f[ok] /= norm[ok, None].astype(np.float32)
        f[~ok] = 0.0
        w[~ok] = 0.0
    return F, bad_total



class Coalescer:
    """Turns one view's top-k lists into its distinct (Gaussian, mask) pairs (numba).

    Owns the kernel's scratch arrays ([N] each, 12 bytes per Gaussian) and a pair buffer that
    grows to the largest view seen, so a view never costs more than its own pairs.
    """

    def __init__(self, num_gaussians: int, capacity: int = 1 << 20):
        self._seen = np.full(num_gaussians, -1, np.int32)
        self._acc = np.zeros(num_gaussians, np.float32)
        self._touched = np.zeros(num_gaussians, np.int32)
        self._g = np.zeros(capacity, np.int32)
        self._m = np.zeros(capacity, np.int32)
        self._w = np.zeros(capacity, np.float32)

    def coalesce(self, ids: np.ndarray, weights: np.ndarray, mask_ids: np.ndarray, num_masks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """ids, weights: [H, W, k]; mask_ids: [H, W] (-1 = none).

        Returns (gaussians [P] int32, masks [P] int32, weights [P] float32, contributing pairs):
        w_ij = Σ_{p ∈ mask j} w_i(p), mask by mask in the kernel's order (arrays are copies).
        """
        k = ids.shape[-1]
        ids2 = np.ascontiguousarray(ids.reshape(-1, k), np.int32)
        w2 = np.ascontiguousarray(weights.reshape(-1, k), np.float32)
        masks = np.ascontiguousarray(mask_ids.reshape(-1), np.int32)
        pairs = filled = first = 0
        while True:
            p, _, first, filled = _coalesce_view_kernel(
                ids2, w2, masks, num_masks, first, 0, self._seen, self._acc, self._touched, self._g, self._m, self._w, filled,
            )
            pairs += p
            if first >= num_masks:
                return self._g[:filled].copy(), self._m[:filled].copy(), self._w[:filled].copy(), int(pairs)
            self._grow()

    def _grow(self) -> None:
        size = 2 * self._g.shape[0]
        for name in ("_g", "_m", "_w"):
            old = getattr(self, name)
            new = np.zeros(size, old.dtype)
            new[: old.shape[0]] = old
            setattr(self, name, new)


def prepare_geometry(scene: GaussianScene, chunk: int = 1 << 20):
    """`raster.prepare_scene` without the SH coefficients (registration renders no colour).

    Prepared chunk by chunk, so the float64 copies of the SH never exist at once: ~101 bytes per
    Gaussian (means and covariances float64, opacity, finite flag). Gaussians with non-finite SH
    are still flagged non-finite, exactly as prepare_scene does.
    """
    from drsplat.raster import PreparedScene, prepare_scene

    n = scene.num_gaussians
    means = np.empty((n, 3), np.float64)
    covs = np.empty((n, 3, 3), np.float64)
    opacities = np.empty(n, np.float32)
    finite = np.empty(n, bool)
    for start in range(0, n, chunk):
        part = prepare_scene(scene.subset(slice(start, start + chunk)))
        stop = start + part.num_gaussians
        means[start:stop], covs[start:stop] = part.means, part.covariances
        opacities[start:stop], finite[start:stop] = part.opacities, part.finite
    return PreparedScene(means=means, covariances=covs, opacities=opacities, sh=np.zeros((n, 0, 3), np.float32), finite=finite)


def load_view_features(features_dir: Path, cam: Camera, level: int) -> tuple[np.ndarray, np.ndarray, int]:
    """(mask ids [H, W] resampled to the camera size, feats [M, D] float32, masks dropped as non-finite)."""
    mask_ids, feats, nonfinite = read_features_report(features_dir, cam.name, level, drop_nonfinite=True)
    return resample_nearest(mask_ids, cam.width, cam.height), feats, nonfinite


def compute_view_pairs(prepared, cam: Camera, mask_ids: np.ndarray, feats: np.ndarray, topk: int, coalescer: Coalescer, out=None,
                       render: Callable | None = None, weights: Callable | None = None):
    """Rasterize one view (numba, or `render(prepared, cam, topk, out)`) and coalesce its pairs.
    weights: the --aggregate hook (drsplat.aggregate.ViewHook) or None; the numba rasterizer also
    returns each pixel's median Gaussian when the hook `needs_median`.
    Returns (ViewPairs, the raster buffers to reuse)."""
    from drsplat.raster import rasterize

    t0 = time.perf_counter()
    if render is None:
        out = rasterize(prepared, cam, topk=topk, out=out, with_median=getattr(weights, "needs_median", False))
    else:
        out = render(prepared, cam, topk, out)
        out = out.numpy() if hasattr(out, "numpy") else out  # a torch engine's output comes back to the host
    t1 = time.perf_counter()
    view_weights, stats = (out.weights, None) if weights is None else weights(prepared, cam, out)
    g, m, w, pairs = coalescer.coalesce(out.ids, view_weights, mask_ids, feats.shape[0])
    used = np.unique(mask_ids[mask_ids >= 0]).astype(np.int32)
    t2 = time.perf_counter()
    return ViewPairs(cam.name, feats, g, m, w, used, pairs, raster_seconds=t1 - t0, coalesce_seconds=t2 - t1, stats=stats), out


class LocalExecutor:
    """Computes views' pairs in this process, one view after another (the default).

    render: (prepared, camera, topk, previous output) -> output with .ids / .weights [H, W, k]
    (default: the numba rasterizer); prepare: scene -> what render takes (default: prepare_geometry);
    weights: (prepared, camera, output) -> ([H, W, k] weights to accumulate, per-view statistics or
    None): the --aggregate hook (drsplat.aggregate.ViewHook; default: the rasterizer's w = T·α).
    """

    def __init__(self, render: Callable | None = None, prepare: Callable | None = None, weights: Callable | None = None):
        self._render = render
        self._weights = weights
        self.prepare = prepare or prepare_geometry

    def view_pairs(self, prepared, views: Sequence[Camera], features_dir: Path, level: int, topk: int) -> Iterator[ViewPairs]:
        coalescer = Coalescer(int(prepared.num_gaussians))
        out = None
        for cam in views:
            mask_ids, feats, nonfinite = load_view_features(features_dir, cam, level)
            view, out = compute_view_pairs(prepared, cam, mask_ids, feats, topk, coalescer, out, render=self._render, weights=self._weights)
            view.num_nonfinite = nonfinite
            yield view


def local_executor(engine: str = "numba", device: str = "cpu", weights: Callable | None = None) -> LocalExecutor:
    """The in-process executor rendering with `engine` on `device` (see `compute_engine`)."""
    if engine == "numba":
        compute_engine(engine, device)  # checks the device
        return LocalExecutor(weights=weights)
    compute = compute_engine(engine, device)
    return LocalExecutor(render=compute.render, prepare=compute.prepare, weights=weights)


# ----------------------------------------------------------------------------- pairing & checkpoints


def pair_views(cameras: Sequence[Camera], stems: Sequence[str]) -> tuple[list[Camera], list[str], list[str]]:
    """Match cameras to feature files by image stem.

    Returns (cameras with features, in camera order; camera names without features;
    feature stems without a camera).
    """
    available = set(stems)
    names = {c.name for c in cameras}
    matched = [c for c in cameras if c.name in available]
    missing = [c.name for c in cameras if c.name not in available]
    unmatched = sorted(s for s in stems if s not in names)
    return matched, missing, unmatched


def select_views(cameras: Sequence[Camera], features_dir: Path) -> tuple[list[Camera], list[str], list[str]]:
    """`pair_views` on the feature folder, with the warnings and the error when nothing matches."""
    stems = list_stems(features_dir)
    if not stems:
        raise InputError(features_dir, "no LangSplat feature files (<stem>_s.npy + <stem>_f.npy) in this folder")
    views, missing, unmatched = pair_views(cameras, stems)
    if missing:
        log.warning("%d of %d cameras have no feature file in %s and are skipped (e.g. %s)", len(missing), len(cameras), features_dir, ", ".join(missing[:3]))
    if unmatched:
        log.warning("%d feature files in %s match no camera and are ignored (e.g. %s)", len(unmatched), features_dir, ", ".join(unmatched[:3]))
    duplicates = len(views) - len({c.name for c in views})
    if duplicates:
        log.warning("%d cameras share an image name with another camera; each uses that image's features", duplicates)
    if not views:
        raise InputError(
            features_dir,
            f"no feature file matches a camera image stem (cameras: {', '.join(c.name for c in cameras[:3])}...; "
            f"features: {', '.join(stems[:3])}...)",
        )
    return views, missing, unmatched


def feature_dim(features_dir: Path, views: Sequence[Camera]) -> int:
    """D of the embeddings, from the first view's `_f.npy` header (nothing loaded)."""
    path = feat_path(features_dir, views[0].name)
    try:
        shape = np.load(path, mmap_mode="r").shape
    except (OSError, ValueError) as exc:
        raise InputError(path, f"not a readable .npy file ({exc})") from None
    if len(shape) != 2 or shape[1] == 0:
        raise InputError(path, f"embeddings have shape {shape}, expected (M, D) with D > 0")
    return int(shape[1])


def _scene_digest(scene: GaussianScene) -> str:
    h = hashlib.sha1()
    h.update(str(scene.num_gaussians).encode())
    step = max(1, scene.num_gaussians // 4096)
    for arr in (scene.means, scene.log_scales, scene.opacity_logits, scene.quats):
        h.update(np.ascontiguousarray(arr[::step]).tobytes())
    return h.hexdigest()


def _views_digest(cameras: Sequence[Camera]) -> str:
    h = hashlib.sha1()
    for c in cameras:
        h.update(f"{c.name}|{c.width}x{c.height}|{c.fx:.6g},{c.fy:.6g},{c.cx:.6g},{c.cy:.6g}|".encode())
        h.update(np.asarray(c.R, np.float64).round(9).tobytes() + np.asarray(c.t, np.float64).round(9).tobytes())
    return h.hexdigest()


def checkpoint_params(scene: GaussianScene, cameras: Sequence[Camera], features_dir: Path, topk: int, level: int,
                      aggregate: str = DEFAULT_AGGREGATE) -> dict:
    """What a checkpoint (pair log) must match to be resumed."""
    return {
        "aggregate": aggregate,
        "version": CHECKPOINT_VERSION,
        "num_gaussians": scene.num_gaussians,
        "scene": _scene_digest(scene),
        "views": _views_digest(cameras),
        "features_dir": str(Path(features_dir).resolve()),
        "topk": int(topk),
        "level": int(level),
    }


def open_checkpoint(path: Path, params: dict, views: Sequence[Camera]) -> PairLog:
    """The pair log at `path`, restarted when its views are not a prefix of `views` in order."""
    plog = PairLog.open(path, params)
    names = [r.name for r in plog.records]
    if names != [c.name for c in views[: len(names)]]:
        log.warning("%s does not match the order of the views; starting over", path)
        plog.delete()
        plog = PairLog.open(path, params)
    return plog


@dataclass
class ViewTotals:
    """Counts and timings summed over registered views."""

    done: int = 0
    num_pairs: int = 0
    num_distinct: int = 0
    num_nonfinite_masks: int = 0
    raster_seconds: float = 0.0
    coalesce_seconds: float = 0.0
    dim: int | None = None
    embeddings: list[np.ndarray] = field(default_factory=list)

    def add(self, view: ViewPairs, features_dir: Path, collect: bool) -> None:
        if self.dim is None:
            self.dim = int(view.feats.shape[1])
        elif view.feats.shape[1] != self.dim:
            raise InputError(feat_path(features_dir, view.name), f"embeddings are {view.feats.shape[1]}-D but earlier views' are {self.dim}-D")
        self.done += 1
        self.num_pairs += view.num_pairs
        self.num_distinct += view.num_distinct
        self.num_nonfinite_masks += view.num_nonfinite
        self.raster_seconds += view.raster_seconds
        self.coalesce_seconds += view.coalesce_seconds
        if collect:
            self.embeddings.append(np.array(view.feats[view.used]))


def run_views(
    prepared,
    views: Sequence[Camera],
    features_dir: Path,
    level: int,
    topk: int,
    consume: Callable[[ViewPairs], None],
    *,
    plog: PairLog | None,
    executor=None,
    checkpoint_every: int = CHECKPOINT_EVERY,
    show_progress: bool = True,
    on_progress: Callable[[int, int], None] | None = None,
    cancel: CancelToken | None = None,
) -> None:
    """Compute the pairs of the views not yet in `plog`, in view order: append each to the log
    (the checkpoint) and hand it to `consume`. Views already logged are replayed into `consume` first."""
    done = 0
    if plog is not None:
        for view in plog:
            consume(view)
            done += 1
    if done:
        log.info("resuming from %s: %d of %d views already registered", plog.path, done, len(views))
    total = len(views)
    if on_progress is not None:
        on_progress(done, total)
    if cancel is not None:
        cancel.raise_if_cancelled()
    executor = executor or LocalExecutor()
    stream = executor.view_pairs(prepared, views[done:], features_dir, level, topk)
    bar = progress(stream, desc="register", total=total - done, enabled=show_progress, unit="view")
    try:
        for view in bar:
            if plog is not None:
                plog.append(view, sync=(done + 1) % max(1, checkpoint_every) == 0)
            consume(view)
            done += 1
            if on_progress is not None:
                on_progress(done, total)
            if cancel is not None and done < total:
                cancel.raise_if_cancelled()
    finally:
        close = getattr(stream, "close", None)
        if close is not None:
            close()


# ----------------------------------------------------------------------------- compute engine hook


@dataclass
class ComputeEngine:
    """How registration rasterizes and sums: prepare(scene) once, render(prepared, camera, topk,
    previous output) per view (an output with .ids / .weights [H, W, k]), and accumulator(N, D), the
    running sums the views' pairs are added to (`add_pairs`, `sums`)."""

    prepare: Callable
    render: Callable
    accumulator: Callable[[int, int], object]


def compute_engine(engine: str = "numba", device: str = "cpu") -> ComputeEngine:
    """numba: drsplat.raster + `Accumulator` (CPU). torch: drsplat.raster_torch + drsplat.accumulate_torch on `device`."""
    if engine == "numba":
        from drsplat.raster import _check_cpu, prepare_scene, rasterize_numba

        _check_cpu("numba", device)
        return ComputeEngine(prepare_scene, lambda prep, cam, topk, out: rasterize_numba(prep, cam, topk, out=out), Accumulator)
    if engine == "torch":
        from drsplat.accumulate_torch import torch_compute_engine

        return torch_compute_engine(device, ComputeEngine)
    raise ValueError(f"unknown registration engine {engine!r}; choose numba or torch")


def aggregate_stats_path(checkpoint: Path) -> Path:
    """Where an aggregation mode's statistics are snapshotted beside the pair log `checkpoint`."""
    return checkpoint.with_name(checkpoint.name + ".aggregate.npz")


def start_aggregation(aggregate: str, scene: GaussianScene, plog: PairLog | None, checkpoint: Path | None, executor=None,
                      engine: str = "numba", device: str = "cpu"):
    """(Aggregator, path of its statistics snapshot or None, executor) for a registration run with
    `--aggregate aggregate` (in memory or streamed): the mode's statistics resumed beside the pair
    log (which is cut back to the views they cover), and the in-process executor carrying its
    per-view hook when `executor` is None."""
    from drsplat.aggregate import Aggregator

    if aggregate != "paper" and engine != "numba":
        raise ValueError(f"--aggregate {aggregate} needs the numba engine (its kernels take numpy arrays), not {engine}")
    aggregator = Aggregator(aggregate, scene)
    if aggregator.hook is not None and executor is not None:  # views computed elsewhere run the mode's hook there
        if not hasattr(executor, "set_hook"):
            raise DrsplatError(f"--aggregate {aggregate} needs an executor that runs its per-view hook ({type(executor).__name__} does not)")
        executor.set_hook(aggregator.hook)
    stats_path = aggregate_stats_path(checkpoint) if checkpoint is not None and aggregator.state() else None
    if stats_path is not None:
        _resume_aggregate(plog, stats_path, aggregator)
    if executor is None:
        executor = local_executor(engine, device, weights=aggregator.hook)
    return aggregator, stats_path, executor


def track_aggregation(aggregator, view: ViewPairs, done: int, resumed: int, stats_path: Path | None, every: int) -> None:
    """After the `done`-th view: fold a newly computed view's statistics (the first `resumed`
    views are replayed from the log and already in the resumed snapshot), and snapshot them every
    `every` new views beside the pair log, which holds the sums."""
    if done <= resumed:
        return
    aggregator.add(view.stats)
    if stats_path is not None and done % max(1, every) == 0:
        _save_aggregate(stats_path, done, aggregator)


def _save_aggregate(path: Path, views: int, aggregator) -> None:
    """Snapshot of an aggregation mode's per-view statistics after `views` views (atomic)."""
    from drsplat.utils import atomic_path

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, views=np.int64(views), **aggregator.state())


def _resume_aggregate(plog: PairLog | None, path: Path, aggregator) -> None:
    """Load the statistics snapshot and cut the log back to the views it covers (or start over)."""
    if plog is None or not plog.records:
        path.unlink(missing_ok=True)
        return
    try:
        views, arrays = _load_snapshot(path, aggregator.state())
    except (OSError, ValueError, KeyError, EOFError, SyntaxError, zipfile.BadZipFile) as exc:
        log.warning("%s is missing or unreadable (%s); the aggregation statistics restart with the views", path, exc)
        views, arrays = 0, {}
    if views > len(plog.records):  # the log was cut shorter than the snapshot: start over
        views, arrays = 0, {}
    plog.truncate(views)
    aggregator.load_state(arrays)


def _load_snapshot(path: Path, expected: dict[str, np.ndarray]) -> tuple[int, dict[str, np.ndarray]]:
    """(views, arrays) of a statistics snapshot. Its members must be `views` (a number) and exactly
    the arrays of `expected`, with their shapes and numeric dtypes: checked from the .npy headers
    inside the zip before anything is read (a damaged or foreign file cannot make us allocate)."""
    from drsplat.utils import read_npy_header

    with zipfile.ZipFile(path) as archive:
        members = {name.removesuffix(".npy"): name for name in archive.namelist()}
        if set(members) != set(expected) | {"views"}:
            raise ValueError(f"holds {sorted(members)}, expected {sorted(set(expected) | {'views'})}")
        for name, member in members.items():
            with archive.open(member) as f:
                shape, dtype = read_npy_header(f)
            want = () if name == "views" else expected[name].shape
            if shape != want or dtype.kind not in "iuf":
                raise ValueError(f"{name} has shape {shape} {dtype}, expected {want} numbers")
    with np.load(path, allow_pickle=False) as data:
        views = int(data["views"])
        if views < 0:
            raise ValueError(f"covers {views} views")
        return views, {name: data[name] for name in expected}


# ----------------------------------------------------------------------------- registration


def register_scene(
    scene: GaussianScene,
    cameras: Sequence[Camera],
    features_dir: str | Path,
    *,
    topk: int = DEFAULT_TOPK,
    level: int = DEFAULT_LEVEL,
    show_progress: bool = True,
    on_progress: Callable[[int, int], None] | None = None,
    cancel: CancelToken | None = None,
    checkpoint: str | Path | None = None,
    checkpoint_every: int = CHECKPOINT_EVERY,
    keep_checkpoint: bool = False,
    collect_embeddings: bool = False,
    executor=None,
    engine: str = "numba",
    device: str = "cpu",
    aggregate: str = DEFAULT_AGGREGATE,
) -> RegistrationResult:
    """Register the mask embeddings of `features_dir` onto the Gaussians of `scene` (in memory).

    cameras: the training views; each pairs with `<name>_s.npy` / `<name>_f.npy` by image stem
    (cameras without features and features without a camera are skipped with a warning).
    Feature maps are resampled to the camera size by nearest neighbour.
    checkpoint: path of the pair log (drsplat.pairlog): every finished view's pairs are appended
    (fsync'd every `checkpoint_every` views), and a run with the same inputs replays it and goes
    on from there. Deleted at the end unless keep_checkpoint (the caller then deletes it once its
    own output is safely written).
    executor: where views' pairs are computed: LocalExecutor (default) or
    drsplat.distributed.RayExecutor; the result is the same bit for bit.
    engine, device: "numba" (CPU) or "torch" (CPU or CUDA) rasterizer (`compute_engine`); views are
    coalesced and summed by the numba kernels whatever renders them, so the pair log, streaming
    and Ray work with either engine.
    aggregate: how pixel weights are turned into Gaussian features (drsplat.defaults.AGGREGATE_MODES; "paper" = Dr. Splat;
    the other modes run locally on the numba engine, in memory; the statistics of floater
    rejection are snapshotted beside the log every `checkpoint_every` views).
    Returns a RegistrationResult with f_i = normalize(Σ_j w_ij f_j) (math in the module docstring).
    """
    t_start = time.perf_counter()
    features_dir = Path(features_dir)
    if topk < 1:
        raise ValueError("topk must be >= 1")
    views, missing, unmatched = select_views(cameras, features_dir)
    ckpt = Path(checkpoint) if checkpoint is not None else None
    plog = open_checkpoint(ckpt, checkpoint_params(scene, views, features_dir, topk, level, aggregate), views) if ckpt is not None else None
    aggregator, stats_path, executor = start_aggregation(aggregate, scene, plog, ckpt, executor, engine, device)
    resumed = len(plog.records) if plog is not None else 0
    prepared = executor.prepare(scene) if hasattr(executor, "prepare") else prepare_geometry(scene)
    totals = ViewTotals()
    new_accumulator = compute_engine(engine, device).accumulator  # numba's on the CPU, torch's on `device`
    acc = None
    accumulate_s = accumulate_cpu = allocate_s = 0.0

    def consume(view: ViewPairs) -> None:
        nonlocal acc, accumulate_s, accumulate_cpu, allocate_s
        totals.add(view, features_dir, collect_embeddings)
        track_aggregation(aggregator, view, totals.done, resumed, stats_path, checkpoint_every)
        if acc is None:
            t0 = time.perf_counter()
            acc = new_accumulator(scene.num_gaussians, totals.dim)
            allocate_s = time.perf_counter() - t0
        t0, c0 = time.perf_counter(), time.process_time()
        acc.add_pairs(view.gaussians, view.masks, view.weights, view.feats)
        accumulate_s += time.perf_counter() - t0
        accumulate_cpu += time.process_time() - c0

    try:
        run_views(prepared, views, features_dir, level, topk, consume, plog=plog, executor=executor, checkpoint_every=checkpoint_every,
                  show_progress=show_progress, on_progress=on_progress, cancel=cancel)
    finally:
        if plog is not None:
            plog.close()
    del prepared
    if acc is None:  # no view had any data
        acc = new_accumulator(scene.num_gaussians, totals.dim or 1)
    t0, c0 = time.perf_counter(), time.process_time()
    sums = acc.sums()
    num_rejected = aggregator.finish(*sums)
    aggregator.log_rejected()
    accumulate_s += time.perf_counter() - t0
    accumulate_cpu += time.process_time() - c0
    features, nonfinite = normalize_rows(*sums)
    if nonfinite:
        log.warning("%d Gaussians got non-finite feature sums and are left unassigned", nonfinite)
    result = RegistrationResult(
        features=features,
        weights=acc.W,
        num_views=totals.done,
        num_pairs=totals.num_pairs,
        num_distinct_pairs=totals.num_distinct,
        seconds=time.perf_counter() - t_start,
        raster_seconds=totals.raster_seconds,
        accumulate_seconds=accumulate_s + totals.coalesce_seconds,
        accumulate_cpu_seconds=accumulate_cpu,
        allocate_seconds=allocate_s,
        coalesce_seconds=totals.coalesce_seconds,
        resumed_views=resumed,
        topk=topk,
        level=level,
        missing_features=missing,
        unmatched_features=unmatched,
        num_nonfinite_masks=totals.num_nonfinite_masks,
        num_nonfinite_features=nonfinite,
        mask_embeddings=np.concatenate(totals.embeddings) if collect_embeddings and totals.embeddings else None,
        aggregate=aggregate,
        num_rejected=num_rejected,
    )
    if plog is not None and not keep_checkpoint:
        plog.delete()
    if stats_path is not None and not keep_checkpoint:
        stats_path.unlink(missing_ok=True)
    log.info(
        "registered %d views: %d of %d Gaussians assigned, %.1f M contributing pairs, %.1f s",
        result.num_views, result.num_assigned, scene.num_gaussians, result.num_pairs / 1e6, result.seconds,
    )
    return result
