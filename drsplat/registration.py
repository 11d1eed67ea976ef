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
import json
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np

from drsplat.cameras import Camera
from drsplat.defaults import DEFAULT_AGGREGATE, DEFAULT_LEVEL, DEFAULT_TOPK
from drsplat.errors import InputError
from drsplat.features.format import list_stems, read_features_report, resample_nearest
from drsplat.scene import GaussianScene
from drsplat.utils import CancelToken, atomic_path, progress

log = logging.getLogger(__name__)

CHECKPOINT_VERSION = 1


@dataclass
class RegistrationResult:
    """Registered language features of a scene.

    features: [N, D] float32 unit rows (zero rows where unassigned).
    weights: [N] float32 total weight Σ_j w_ij (0 = unassigned).
    seconds: wall time; raster_seconds / accumulate_seconds: its two main stages;
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

    features: np.ndarray
    weights: np.ndarray
    num_views: int
    num_pairs: int
    num_distinct_pairs: int
    seconds: float
    raster_seconds: float = 0.0
    accumulate_seconds: float = 0.0
    accumulate_cpu_seconds: float = 0.0
    allocate_seconds: float = 0.0
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


def checkpoint_params(scene: GaussianScene, cameras: Sequence[Camera], features_dir: Path, topk: int, level: int, collect: bool,
                      aggregate: str = DEFAULT_AGGREGATE) -> dict:
    """What a checkpoint must match to be resumed."""
    return {
        "aggregate": aggregate,
        "version": CHECKPOINT_VERSION,
        "num_gaussians": scene.num_gaussians,
        "scene": _scene_digest(scene),
        "views": _views_digest(cameras),
        "features_dir": str(Path(features_dir).resolve()),
        "topk": int(topk),
        "level": int(level),
        "collect_embeddings": bool(collect),
    }


@dataclass
class _State:
    acc: Accumulator | None = None
    done: list[str] = field(default_factory=list)
    num_pairs: int = 0
    num_distinct: int = 0
    num_nonfinite_masks: int = 0
    embeddings: list[np.ndarray] = field(default_factory=list)
    aggregate: dict[str, np.ndarray] = field(default_factory=dict)  # drsplat.aggregate statistics


def save_checkpoint(path: Path, params: dict, state: _State) -> None:
    """Atomic .npz of the accumulators, the views done and the parameters they belong to."""
    meta = dict(params, done=state.done, num_pairs=state.num_pairs, num_distinct=state.num_distinct, num_nonfinite_masks=state.num_nonfinite_masks)
    arrays = {"meta": np.array(json.dumps(meta))}
    if state.acc is not None:
        arrays["F"], arrays["W"] = state.acc.sums()
    if state.embeddings:
        arrays["embeddings"] = np.concatenate(state.embeddings)
    arrays.update({f"aggregate_{k}": v for k, v in state.aggregate.items()})
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
    log.debug("checkpoint %s: %d views", path, len(state.done))


def load_checkpoint(path: Path, params: dict) -> _State | None:
    """The saved state if `path` holds a checkpoint made with the same `params`, else None."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            if any(meta.get(k) != v for k, v in params.items()):
                log.warning("%s was made with other parameters or inputs; starting over", path)
                return None
            state = _State(done=list(meta["done"]), num_pairs=int(meta["num_pairs"]), num_distinct=int(meta["num_distinct"]),
                           num_nonfinite_masks=int(meta["num_nonfinite_masks"]))
            if "F" in data:
                state.acc = Accumulator(params["num_gaussians"], data["F"].shape[1])
                state.acc.F[:] = data["F"]
                state.acc.W[:] = data["W"]
            if "embeddings" in data:
                state.embeddings = [data["embeddings"]]
            state.aggregate = {k[len("aggregate_"):]: data[k] for k in data.files if k.startswith("aggregate_")}
    except (OSError, ValueError, KeyError, json.JSONDecodeError) as exc:
        log.warning("%s is not a readable checkpoint (%s); starting over", path, exc)
        return None
    return state


# ----------------------------------------------------------------------------- compute engine hook


@dataclass
class ComputeEngine:
    """How registration rasterizes and accumulates: prepare(scene) once, render(prepared, camera,
    topk, previous output) per view (an output with .ids / .weights [H, W, k]), accumulator(N, D)
    and adopt(accumulator) (converts one loaded from a checkpoint)."""

    prepare: Callable
    render: Callable
    accumulator: Callable[[int, int], object]
    adopt: Callable[[object], object]


def compute_engine(engine: str = "numba", device: str = "cpu") -> ComputeEngine:
    """numba: drsplat.raster + `Accumulator` (CPU). torch: drsplat.raster_torch + drsplat.accumulate_torch on `device`."""
    if engine == "numba":
        from drsplat.raster import _check_cpu, prepare_scene, rasterize_numba

        _check_cpu("numba", device)
        return ComputeEngine(prepare_scene, lambda prep, cam, topk, out: rasterize_numba(prep, cam, topk, out=out), Accumulator, lambda acc: acc)
    if engine == "torch":
        from drsplat.accumulate_torch import torch_compute_engine

        return torch_compute_engine(device, ComputeEngine)
    raise ValueError(f"unknown registration engine {engine!r}; choose numba or torch")


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
    checkpoint_every: int = 10,
    keep_checkpoint: bool = False,
    collect_embeddings: bool = False,
    engine: str = "numba",
    device: str = "cpu",
    aggregate: str = DEFAULT_AGGREGATE,
) -> RegistrationResult:
    """Register the mask embeddings of `features_dir` onto the Gaussians of `scene`.

    cameras: the training views; each pairs with `<name>_s.npy` / `<name>_f.npy` by image stem
    (cameras without features and features without a camera are skipped with a warning).
    Feature maps are resampled to the camera size by nearest neighbour.
    checkpoint: an .npz path; the sums are saved there every `checkpoint_every` views (and on
    cancel), and a run with the same inputs resumes from it. It is deleted at the end unless
    keep_checkpoint (the caller then deletes it once its own output is safely written).
    engine, device: "numba" (CPU) or "torch" (CPU or CUDA) rasterizer + accumulator (`compute_engine`).
    aggregate: how pixel weights are turned into Gaussian features (drsplat.aggregate.MODES; "paper" = Dr. Splat;
    the other modes run on the numba engine).
    Returns a RegistrationResult with f_i = normalize(Σ_j w_ij f_j) (math in the module docstring).
    """
    from drsplat.aggregate import Aggregator

    if aggregate != "paper" and engine != "numba":
        raise ValueError(f"--aggregate {aggregate} needs the numba engine (its kernels take numpy arrays), not {engine}")
    compute = compute_engine(engine, device)
    t_start = time.perf_counter()
    features_dir = Path(features_dir)
    if topk < 1:
        raise ValueError("topk must be >= 1")
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

    ckpt = Path(checkpoint) if checkpoint is not None else None
    params = checkpoint_params(scene, views, features_dir, topk, level, collect_embeddings, aggregate)
    state = (load_checkpoint(ckpt, params) if ckpt is not None else None) or _State()
    aggregator = Aggregator(aggregate, scene.num_gaussians)  # --aggregate hook: per-view weights + a post-step
    resumed = len(state.done)
    if state.done != [c.name for c in views[:resumed]]:  # views run in order: done is a prefix
        log.warning("%s does not match the order of the views; starting over", ckpt)
        state, resumed = _State(), 0
    if resumed:
        log.info("resuming from %s: %d of %d views already registered", ckpt, resumed, len(views))
        aggregator.load_state(state.aggregate)
    state.aggregate = aggregator.state()
    prepared = compute.prepare(scene)
    out = None  # the rasterizer's [H, W, k] buffers, reused from view to view
    raster_s = accumulate_s = accumulate_cpu = allocate_s = 0.0
    since_checkpoint = 0
    total = len(views)
    if on_progress is not None:
        on_progress(resumed, total)
    for cam in progress(views[resumed:], desc="register", total=total - resumed, enabled=show_progress, unit="view"):
        if cancel is not None and cancel.cancelled:
            if ckpt is not None:
                save_checkpoint(ckpt, params, state)
            cancel.raise_if_cancelled()
        mask_ids, feats, nonfinite = read_features_report(features_dir, cam.name, level, drop_nonfinite=True)
        state.num_nonfinite_masks += nonfinite
        if state.acc is None:
            t0 = time.perf_counter()
            state.acc = compute.accumulator(scene.num_gaussians, feats.shape[1])
            allocate_s = time.perf_counter() - t0
        if feats.shape[1] != state.acc.dim:
            raise InputError(features_dir / f"{cam.name}_f.npy", f"embeddings are {feats.shape[1]}-D but earlier views' are {state.acc.dim}-D")
        mask_ids = resample_nearest(mask_ids, cam.width, cam.height)
        t0 = time.perf_counter()
        state.acc = compute.adopt(state.acc)
        out = compute.render(prepared, cam, topk, out)
        t1, c1 = time.perf_counter(), time.process_time()
        pairs, distinct = state.acc.add_view(out.ids, aggregator.view_weights(prepared, cam, out), mask_ids, feats)
        accumulate_s += time.perf_counter() - t1
        accumulate_cpu += time.process_time() - c1
        raster_s += t1 - t0
        state.num_pairs += int(pairs)
        state.num_distinct += int(distinct)
        if collect_embeddings:
            used = np.unique(mask_ids[mask_ids >= 0])
            state.embeddings.append(feats[used])
        state.done.append(cam.name)
        since_checkpoint += 1
        if ckpt is not None and since_checkpoint >= checkpoint_every and len(state.done) < total:
            save_checkpoint(ckpt, params, state)
            since_checkpoint = 0
        if on_progress is not None:
            on_progress(len(state.done), total)

    if state.acc is None:  # only a checkpoint saved before the first view could get here
        state.acc = Accumulator(scene.num_gaussians, 1)
    t0, c0 = time.perf_counter(), time.process_time()
    sums = state.acc.sums()
    num_rejected = aggregator.finish(*sums)
    accumulate_s += time.perf_counter() - t0
    accumulate_cpu += time.process_time() - c0
    features, nonfinite = normalize_rows(*sums)
    if nonfinite:
        log.warning("%d Gaussians got non-finite feature sums and are left unassigned", nonfinite)
    result = RegistrationResult(
        features=features,
        weights=sums[1],
        num_views=len(state.done),
        num_pairs=state.num_pairs,
        num_distinct_pairs=state.num_distinct,
        seconds=time.perf_counter() - t_start,
        raster_seconds=raster_s,
        accumulate_seconds=accumulate_s,
        accumulate_cpu_seconds=accumulate_cpu,
        allocate_seconds=allocate_s,
        resumed_views=resumed,
        topk=topk,
        level=level,
        missing_features=missing,
        unmatched_features=unmatched,
        num_nonfinite_masks=state.num_nonfinite_masks,
        num_nonfinite_features=nonfinite,
        mask_embeddings=np.concatenate(state.embeddings) if collect_embeddings and state.embeddings else None,
        aggregate=aggregate,
        num_rejected=num_rejected,
    )
    if ckpt is not None and not keep_checkpoint:
        ckpt.unlink(missing_ok=True)
    log.info(
        "registered %d views: %d of %d Gaussians assigned, %.1f M contributing pairs, %.1f s",
        result.num_views, result.num_assigned, scene.num_gaussians, result.num_pairs / 1e6, result.seconds,
    )
    return result
