"""The one registration driver, for every engine, place, aggregation mode and memory plan.

    plan       choose_block: one block of N Gaussians, or blocks that fit --memory-budget
    views      an executor (engine x place) yields each view's pairs in view order; the mode's
               hook ran where the view was rendered; the driver folds the mode's statistics,
               logs the view (checkpoint) and hands it to the sink
    sums       the sink gives each block's sums F, W (MemorySink: kept live; LogSink: replayed)
    finish     the mode's step on the sums (floater rejection), normalise, prune
    reduce     on Ray in blocks, writing a PLY: the workers log the views in shards (the driver
               logs pointers and folds nothing); sums, the statistics' fold, finish and encoding
               of each block run in a reducer task that writes a part; the driver assembles the
               parts (registration.reduce)
    codebook   one step: none, a loaded file, or trained on the scene's masks (+ a sample of
               Gaussians summed by the sink), the same whatever the plan
    target     PlyTarget writes the registered PLY (one writer), ArrayTarget keeps [N, D]

`register` writes the registered PLY (drsplat register, the viewer, the benches); `register_features`
returns the features in memory (evaluation, tests). Both run `run_registration`. Since every block's
sums are the same bits whatever the plan and the place, so is the output (tested byte for byte).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drsplat.cameras import Camera
from drsplat.defaults import VOTE_SLOT_BYTES
from drsplat.errors import Cancelled, DrsplatError, InputError, UsageError
from drsplat.features.format import check_manifest_dim, feat_path, read_manifest, seg_path
from drsplat.features.modelid import manifest_model_id, manifest_weights
from drsplat.frames import frame_hint, warn_if_scene_misses_its_images
from drsplat.lang import Codebook, load_codebook, train_codebook
from drsplat.lang.codebook import PQ_TRAIN_MAX, SCENE_PQ_M
from drsplat.lang.field import scene_sample_ids, scene_training_set
from drsplat.memory import current_rss, format_size, trim_heap
from drsplat.raster import NEAR, faint_share, get_engine, kernels_cached, median_nearest_depth, plane_below, share_within_near_plane, some_view_draws, widened_scene
from drsplat.registration.aggregate import PEAK_MIN, REJECT_FIRST_RUN_PROBE, SHARP_FIRST_RUN_PROBE, Aggregator, mode_stages, without_check, without_rejection
from drsplat.registration.fit import (FIRST_RUN_PROBE as FIT_PROBE, FOOTPRINTS, FitChoice, FitStage, fit_stage, is_fit_mode, probe_engine,
                                      probe_folds_floaters, probe_memory, probe_memory_bound, resolve_mode)
from drsplat.registration.check import FIRST_RUN_PROBE as CHECK_PROBE, CheckSink, fixed_point_fits, heavy_drop_warning
from drsplat.registration.checkpoint import (CHECKPOINT_EVERY, Checkpoint, RunLock, changed_features, checkpoint_params, checkpoint_path_for,
                                             feature_stamps, lock_run)
from drsplat.registration.coalesce import FIRST_RUN_PROBE as COALESCE_PROBE
from drsplat.registration.compute import ViewJob, WorkerStats, pairs_by_gaussian, prepare_geometry
from drsplat.registration.executor import one_view_behind, open_executor
from drsplat.registration.options import NEAR_PLANE_COMMENT, RegisterOptions, near_plane_comment
from drsplat.registration.output import ArrayTarget, PlyTarget, Target
from drsplat.registration.pairlog import ViewPairs
from drsplat.registration.plan import MemoryPlan, choose_block, estimate_memory
from drsplat.registration.reduce import BlockReduce, ReducePool, assemble_parts, judged, make_job, shard_errors, wants_reducers
from drsplat.registration.solve import FIRST_RUN_PROBE as SOLVE_PROBE, solve_registration
from drsplat.registration.sink import LogSink, MemorySink, Sink, sums_place
from drsplat.registration.sums import CANCEL_RATIO, WEAK_RESULTANT, RowFates, normalize_rows
from drsplat.registration.views import (FeatureHeaders, ViewSelection, far_coarser_note, level_count_note, read_feature_headers, select_views, single_level_note, warn_if_distorted_without_manifest,
                                        warn_if_turned_without_manifest)
from drsplat.registration.vote import FIRST_RUN_PROBE as VOTE_PROBE, VoteSink
from drsplat.scene import GaussianScene, counted
from drsplat.utils import CancelToken, compiled_here, describe_os_error, progress

log = logging.getLogger(__name__)

SCENE_CODEBOOK_M = 128  # sub-vectors of a scene codebook (the paper's general codebook has 128 x 8 bits)
# Mask embeddings a scene codebook trains on at most: faiss's k-means would never use more, so a
# run with more masks keeps every k-th one.
SCENE_TRAIN_MAX = PQ_TRAIN_MAX


@dataclass
class RegistrationResult:
    """What a registration computed and, for `register`, wrote.

    features: [N, D] float32 unit rows, zero where unassigned (`register_features`); None when a
    PLY was written instead. weights: [N] float32 total weight W_i = Σ_j w_ij (0 = unassigned).
    path / num_written: the registered PLY and its rows (`register`).
    seconds: wall time; view_seconds: the view pass (raster_seconds rendering and coalesce_seconds
    coalescing, where the views were computed, plus logging and summing here); accumulate_seconds:
    coalescing + summing (live, or the blocks' replays); accumulate_cpu_seconds: CPU time of all
    threads in summing. num_views: views registered (resumed ones included); num_pairs:
    contributing (Gaussian, pixel) pairs; num_distinct_pairs: (Gaussian, mask) pairs summed.
    missing_features: camera names without a feature file; unmatched_features: feature stems
    without a camera. num_nonfinite_masks: masks dropped for non-finite embeddings;
    num_nonfinite_features: Gaussians left unassigned for non-finite or cancelled sums (`normalize_rows`);
    num_weak_features: Gaussians kept whose sums are under WEAK_RESULTANT of their weight (`RowFates`). mask_embeddings:
    [M, D] the masks' embeddings (a scene codebook's training set; only when asked for).
    num_rejected: Gaussians the aggregation mode left unassigned. block_size / num_blocks: the
    memory plan. log_bytes: size of the pair log (0 without one). worker_peak_rss: pid -> peak
    resident bytes of the Ray workers (reducers included). sums_on: where the per-Gaussian sums were
    kept ("host", or the torch device: drsplat.registration.device_sums). pairs_on: where each view
    was coalesced into its (Gaussian, mask) pairs ("host", or the torch device; a `check-` mode
    copies them to the host for its judging, then sums the kept ones where sums_on says).
    finish_cpu_seconds: this
    process's CPU time after the view pass; reducers: the blocks were finished by reducer tasks.
    workers: the WorkerStats of the processes that computed views (this one for a local run): first
    and later views' seconds, numba kernels cached/compiled. reducer_seconds / reducer_sum_seconds:
    the reducer tasks' seconds summed over the blocks, whole tasks / their replays of the log (0
    without reducers). driver_view_cpu_seconds: this process's CPU time (all threads) on the
    computed views' results as they arrived (logging, the mode's statistics, the sink), the
    driver's per-view work apart from waiting for the views and its fixed costs. aggregate: the mode
    that ran (a `fit` mode resolved to its footprint's); fit: the fit stage's decision, or None.
    """

    features: np.ndarray | None
    weights: np.ndarray
    num_views: int = 0
    num_pairs: int = 0
    num_distinct_pairs: int = 0
    seconds: float = 0.0
    view_seconds: float = 0.0
    raster_seconds: float = 0.0
    coalesce_seconds: float = 0.0
    accumulate_seconds: float = 0.0
    accumulate_cpu_seconds: float = 0.0
    resumed_views: int = 0
    topk: int = 0
    level: int = 0
    missing_features: list[str] = field(default_factory=list)
    unmatched_features: list[str] = field(default_factory=list)
    num_nonfinite_masks: int = 0
    num_nonfinite_features: int = 0
    num_weak_features: int = 0
    mask_embeddings: np.ndarray | None = None
    aggregate: str = ""
    num_rejected: int = 0
    block_size: int = 0
    num_blocks: int = 0
    log_bytes: int = 0
    path: Path | None = None
    num_written: int = 0
    field_kind: str = ""
    worker_peak_rss: dict[int, int] = field(default_factory=dict)
    sums_on: str = "host"
    pairs_on: str = "host"
    finish_cpu_seconds: float = 0.0
    reducers: bool = False
    workers: list[WorkerStats] = field(default_factory=list)
    reducer_seconds: float = 0.0
    reducer_sum_seconds: float = 0.0
    driver_view_cpu_seconds: float = 0.0
    fit: FitChoice | None = None

    @property
    def assigned(self) -> np.ndarray:
        """[N] bool, Gaussians that received weight."""
        return self.weights > 0

    @property
    def num_assigned(self) -> int:
        return int(np.count_nonzero(self.weights > 0))


@dataclass
class ViewTotals:
    """Counts and timings summed over the registered views, and what the codebook step needs."""

    dim: int
    features_dir: Path
    collect: bool
    done: int = 0
    num_pairs: int = 0
    num_distinct: int = 0
    num_nonfinite_masks: int = 0
    raster_seconds: float = 0.0
    coalesce_seconds: float = 0.0
    sum_seconds: float = 0.0
    sum_cpu_seconds: float = 0.0
    driver_view_cpu_seconds: float = 0.0  # this process's CPU on computed views' results: log, fold, sums
    embeddings: list[np.ndarray] = field(default_factory=list)
    positive: np.ndarray | None = None  # [N] bool: some pair gave the Gaussian weight > 0 (None: the reducers know)
    stride: int = 1  # every stride-th used mask's embedding is collected, counted over the views in order
    used_seen: int = 0

    def add(self, view: ViewPairs) -> None:
        if view.feats.shape[1] != self.dim:
            raise InputError(feat_path(self.features_dir, view.name), f"embeddings are {view.feats.shape[1]}-D but earlier views' are {self.dim}-D")
        self.done += 1
        self.num_pairs += view.num_pairs
        self.num_distinct += view.num_distinct
        self.num_nonfinite_masks += view.num_nonfinite
        self.raster_seconds += view.raster_seconds
        self.coalesce_seconds += view.coalesce_seconds
        if self.positive is not None:
            self.positive[view.gaussians[view.weights > 0]] = True
        if self.collect:
            used = view.used
            if self.stride > 1:  # which masks are kept depends on their place in the run only, not on the plan
                used = used[(self.used_seen + np.arange(used.shape[0])) % self.stride == 0]
            self.used_seen += view.used.shape[0]
            self.embeddings.append(np.array(view.feats[used]))

    def mask_embeddings(self) -> np.ndarray | None:
        return np.concatenate(self.embeddings) if self.embeddings else None


@dataclass
class Run:
    """One registration's inputs, after checking: the scene, its views, D and the options."""

    scene: GaussianScene
    selection: ViewSelection
    features_dir: Path
    headers: FeatureHeaders
    options: RegisterOptions

    @property
    def dim(self) -> int:
        return self.headers.dim

    @property
    def views(self) -> list[Camera]:
        return self.selection.views


def prepare_run(scene: GaussianScene, cameras: Sequence[Camera], features_dir: str | Path, options: RegisterOptions,
                quiet: bool = False) -> Run:
    """Check the options, pair the cameras with the feature files and check those files' headers (nothing heavy is loaded).
    quiet: the warnings and notes left unsaid, for a check made again by the run itself (`refuse_if_over_budget`'s caller:
    round 67a F1, every warning about the feature files came twice under `register --near-plane auto`)."""
    options.check()
    if scene.num_gaussians == 0:
        raise DrsplatError("the scene holds no Gaussians: there is nothing to register")
    features_dir = Path(features_dir)
    selection = select_views(cameras, features_dir, quiet=quiet)
    refuse_if_no_view_draws(scene, selection.views, options.near_plane, options.near_plane_decided)
    headers = read_feature_headers(features_dir, selection.views, options.level, missing_ok=options.place == "ray")
    for note in (single_level_note(headers.levels, options.level), level_count_note(headers.levels, options.level),
                 far_coarser_note(headers.coarse, len(selection.views))):
        if note is not None and not quiet:  # here, once: the fit stage reads its probe views' headers again
            log.warning("%s", note)
    return Run(scene, selection, features_dir, headers, options)


def refuse_if_no_view_draws(scene: GaussianScene, cameras: Sequence[Camera], near_plane: float, decided: bool = False) -> None:
    """One error before any view when no camera has a Gaussian at depth ≥ the near plane (`raster.some_view_draws`):
    every view would render nothing, and the run would fail after them with a checkpoint that could only fail again
    (round 64c F3: --near-plane 1e30). No Gaussian in front of any camera at all: the cameras face away (or another
    frame). Some in front, all nearer than a plane the user chose: a usage error naming the flag; nearer than one
    `--near-plane auto` decided (`decided`), an error naming the decision (round 67a F10: a usage error told the user to
    leave out the flag they had left out); at the default the scene and cameras disagree in units (`near_plane_remedy`
    says how)."""
    if some_view_draws(scene.means, cameras, near_plane):
        return
    depth = median_nearest_depth(scene.means, cameras)
    if not math.isfinite(depth):  # none in front of any camera at all: the plane is not what hides them
        raise DrsplatError(f"no Gaussian of the scene lies in front of any of the {counted(len(cameras), 'camera', 'cameras')}, so no view can draw one: "
                           "the cameras face away from it, or the scene and its cameras are in different frames or units")
    why = (f"no Gaussian of the scene lies {near_plane:g} scene units or more in front of any of the {counted(len(cameras), 'camera', 'cameras')} "
           f"(the near plane), so no view can draw one: " + near_plane_remedy(depth, near_plane, decided))
    if near_plane != NEAR and not decided:  # Gaussians in front, all nearer than a plane the user chose: the flag is the cause
        raise UsageError(f"--near-plane {near_plane:g}: {why}")
    raise DrsplatError(why)


def resolve_codebook(codebook: str, dim: int) -> Codebook | str:
    """'none' / 'scene' as given, or the faiss codebook file loaded and checked against the features' D; 'scene' is
    checked to split D into SCENE_PQ_M sub-vectors (a 64-D model was refused only after every view, round 61a)."""
    if codebook == "scene" and (dim <= 0 or dim % SCENE_PQ_M):
        raise InputError(None, f"--codebook scene trains a codebook of {SCENE_PQ_M} sub-vectors, which do not divide these features' "
                               f"{dim}-D embeddings; use --codebook none (exact features) or a codebook file of {dim}-D")
    if codebook in ("none", "scene"):
        return codebook
    book = load_codebook(codebook)
    if book.dim != dim:
        raise InputError(book.path, f"codebook dimension {book.dim} differs from the features' dimension {dim} (a different CLIP model?)")
    return book


class NothingAssigned(DrsplatError):
    """Registration ran every view and gave no Gaussian a feature (`nothing_assigned` says why)."""


def nothing_assigned(num_views: int, features_dir: Path, out: Path | None, hint: str = "", unusable: RowFates | None = None,
                     rejected: int = 0, mode: str = "") -> str:
    """The error when registration gave no Gaussian a feature (nothing is written); hint: `unassigned_hint`'s;
    unusable: Gaussians whose sums were dropped by `normalize_rows`, rejected: Gaussians with weight
    that `mode`'s floater rejection dropped (either is then the likely cause)."""
    written = f"; nothing was written to {out}" if out is not None else ""
    if unusable is not None and unusable.dropped:
        return f"no Gaussian kept a language feature from {counted(num_views, 'view', 'views')}: {unusable_sums(unusable)}{written}"
    if rejected:
        return (f"no Gaussian kept a language feature from {counted(num_views, 'view', 'views')}: floater rejection (--aggregate {mode}) left all "
                f"{rejected} Gaussians that the masks gave weight unassigned, since each stays under {PEAK_MIN:g} of every pixel's "
                "weight and lies mostly in front of the surface the views see: a scene without an opaque surface (or with "
                f"opacities far below a trained scene's); --aggregate {without_rejection(mode)} registers without the rejection{written}")
    return (f"no Gaussian received a language feature from {counted(num_views, 'view', 'views')}: the cameras do not see the scene "
            f"or every mask of {features_dir} is empty or invalid{hint}{written}")


def empty_level_hint(features_dir: Path, views: Sequence[Camera], level: int) -> str:
    """'; level L of every view's mask map holds no mask ...' when the mask maps hold masks at other
    levels only (a LangSplat file whose --level is empty), "" otherwise or when a file cannot be read.
    Read on the error path only: it stops at the first view with a mask at `level`."""
    others: set[int] = set()
    try:
        for cam in views:
            seg = np.load(seg_path(features_dir, cam.name), mmap_mode="r", allow_pickle=False)
            if seg.ndim != 3 or seg.shape[0] <= level:
                return ""
            if (np.asarray(seg[level]) >= 0).any():
                return ""
            others.update(i for i in range(seg.shape[0]) if i != level and (np.asarray(seg[i]) >= 0).any())
    except (OSError, ValueError):
        return ""
    if not others:
        return ""
    return (f"; level {level} of every view's mask map holds no mask (-1 everywhere), while level(s) "
            f"{', '.join(map(str, sorted(others)))} hold some: choose one with --level")


def failure_hint(run: Run, level: int) -> str:
    """'; <the likely cause>' of a registration that assigned nothing: an empty mask level
    (`empty_level_hint`), else what `unassigned_hint` finds in the scene and cameras."""
    return empty_level_hint(run.features_dir, run.views, level) or unassigned_hint(run.scene, run.views, run.options.near_plane, run.options.near_plane_decided)


def weak_sums(count: int) -> str:
    """`RowFates.weak` in words."""
    return (f"{count} Gaussians got feature sums under {WEAK_RESULTANT:g} of their weight (|Σ w f| < {WEAK_RESULTANT:g} Σ w): the "
            "embeddings of the masks they lie in point many or opposite ways, so their features are a guess (CLIP's crops "
            "of one capture never disagree that much: were some feature files made with another model, or negated?)")


def unusable_sums(fates: RowFates) -> str:
    """What `normalize_rows` dropped, in words: the non-finite sums and the cancelled ones apart, since
    their causes differ (a weight past float32's range, a Gaussian of absurd size; masks' embeddings
    pointing opposite ways)."""
    parts = []
    cancelled = fates.dropped - fates.nonfinite
    if fates.nonfinite:
        parts.append(f"{fates.nonfinite} Gaussians got a non-finite feature sum or weight (a weight beyond float32's range: a Gaussian "
                     "of absurd size or opacity; or non-finite embeddings)")
    if cancelled:
        parts.append(f"{cancelled} Gaussians got feature sums that cancel out (|Σ w f| ≤ {CANCEL_RATIO:g} Σ w: their masks' "
                     "embeddings point opposite ways)")
    return "; ".join(parts) + "; they are left unassigned"


def run_registration(
    run: Run,
    target: Target,
    *,
    checkpoint: Path | None = None,
    checkpoint_every: int = CHECKPOINT_EVERY,
    out: Path | None = None,
    collect_embeddings: bool = False,
    show_progress: bool = True,
    on_progress: Callable[[int, int], None] | None = None,
    cancel: CancelToken | None = None,
    lock: RunLock | None = None,
    say_first_run: bool = True,
) -> RegistrationResult:
    """Register `run` into `target` (module docstring).

    checkpoint: the pair log to resume from and keep while working (None: no checkpoint; a run in
    blocks then logs into a temporary file beside `out`). It is removed once the target is closed;
    a run that stops early keeps it when it holds views and says so; checkpoint_every: views between
    its fsyncs and the mode's statistics snapshots. collect_embeddings: keep the
    masks' embeddings in the result (always collected for a scene codebook). lock: `checkpoint`'s lock when the caller
    took it before reading the run's inputs (`drsplat register`: round 68a F1, a second run started while the first read
    its scene passed a lock taken and released), used instead of taking it here; released here as the run's own.
    say_first_run: note a first run's compiling (`say_if_kernels_compile`); False where the caller said it before its own
    work (`drsplat register`, whose scene loading and near-plane decision compile kernels first).
    """
    t_start = time.perf_counter()
    codebook = resolve_codebook(run.options.codebook, run.dim)  # a bad codebook fails now, not after registering
    if lock is None and checkpoint is not None:  # a second run, or a folder that takes no file: refused before any work
        lock = lock_run(checkpoint)
    try:
        return _register_locked(run, target, codebook, lock, t_start, checkpoint=checkpoint, checkpoint_every=checkpoint_every, out=out,
                                collect_embeddings=collect_embeddings, show_progress=show_progress, on_progress=on_progress, cancel=cancel,
                                say_first_run=say_first_run)
    finally:
        if lock is not None:  # released by the checkpoint that took it over; here only when the run stopped before making it
            lock.release()


def say_if_kernels_compile(options: RegisterOptions) -> None:
    """One note when this process's registration will compile numba's kernels rather than load them from its cache: a first
    run on a machine spent 81 s of 92 compiling without a word (round 67c F6). Asked, for this CPU and code
    (`utils.compiled_here`: a cache another CPU type filled, or an older drsplat's, is compiled again), of a kernel of each
    part the run uses: the compositor (the numba engine), the pairs' coalescing (every engine's sums on the host: round 68a
    F4, `--engine torch` compiled for 70 s unsaid) and each stage of the mode (round 70a F5: a cache an `--aggregate paper`
    run filled left the default's stages 25 s of compiling unsaid). On Ray, the compositor only: this process loads the
    scene and decides the near plane with it, the workers compile theirs (round 70a F6)."""
    if options.place == "ray":
        cached = kernels_cached()
    else:
        stages = mode_stages(options.aggregate)
        parts = ((True, COALESCE_PROBE), (stages.vote, VOTE_PROBE), (stages.check, CHECK_PROBE), (stages.solve, SOLVE_PROBE),
                 (stages.reject, REJECT_FIRST_RUN_PROBE), (stages.weighting == "fit", FIT_PROBE),
                 (stages.weighting in ("sharp", "fit"), SHARP_FIRST_RUN_PROBE))
        cached = (options.engine != "numba" or kernels_cached()) and all(compiled_here(kernel) for used, kernel in parts if used)
    if not cached:
        log.info("first run of this drsplat on this machine: numba compiles the kernels as they are first used (a minute or two; "
                 "later runs load them from its cache)")


def _register_locked(run: Run, target: Target, codebook, lock: RunLock | None, t_start: float, *, checkpoint: Path | None,
                     checkpoint_every: int, out: Path | None, collect_embeddings: bool, show_progress: bool,
                     on_progress: Callable[[int, int], None] | None, cancel: CancelToken | None,
                     say_first_run: bool) -> RegistrationResult:
    """`run_registration` once the run's lock is held (`lock`, None without a checkpoint)."""
    load_rendering_engine(run)
    if say_first_run:
        say_if_kernels_compile(run.options)
    stamps = feature_stamps(run.features_dir, run.views)  # before any view is read: a file changed during the run is caught
    memory_base = _check_memory_before_probe(run)
    probe = _fit_stage(run, cancel)
    asked = run.options.aggregate  # the mode as the user named it (a fit mode resolves to a concrete one here)
    if probe is not None:
        run = dataclasses.replace(run, options=dataclasses.replace(run.options, aggregate=probe.mode))
    scene, options = run.scene, run.options
    n = scene.num_gaussians
    if mode_stages(options.aggregate).check:  # a view's paper weights sum to at most its pixels: refused if the exact sums could overflow
        fixed_point_fits(max((cam.width * cam.height for cam in run.views), default=0), len(run.views), options.aggregate)
    block = options.block_size or _plan_block(run, memory_base, probe.pass_bytes if probe is not None else 0)
    # the partitioned reduce (Ray, blocks, a PLY): the workers log the views in shards and the reducers fold the statistics
    reducers = wants_reducers(options.place, options.reducers, block, n, isinstance(target, PlyTarget))
    aggregator = Aggregator(options.aggregate, scene, stats_on_reducers=reducers, rays=probe.rays if probe is not None else None)
    if aggregator.solve and block < n:
        raise UsageError(f"--aggregate {options.aggregate} solves over all Gaussians in one block in memory and cannot run under a "
                         f"--memory-budget (or a block_size) that splits the scene into blocks of {block:,}")
    params = checkpoint_params(scene, run.views, run.features_dir, options.topk, options.level, options.aggregate, shards=reducers,
                               engine=options.engine, device=options.device, near_plane=options.near_plane)
    if checkpoint is not None:
        ckpt = Checkpoint(checkpoint, params, run.views, aggregator, every=checkpoint_every, features_dir=run.features_dir, lock=lock,
                          stamps=stamps)
    elif block < n or aggregator.check:  # blocks replay a log; so does a check, rather than keep every view's pairs in memory
        ckpt = Checkpoint.temporary_beside(out or Path(tempfile.gettempdir()) / "drsplat-registration", params, run.views, aggregator)
    else:
        ckpt = None
    pool: ReducePool | None = None
    reduce: BlockReduce | None = None
    reducer_seconds = (0.0, 0.0)
    try:  # from here on the checkpoint is left (kept or removed) whatever happens: it holds the run's lock
        totals = ViewTotals(run.dim, run.features_dir, collect_embeddings or options.codebook == "scene", positive=None if reducers else np.zeros(n, bool),
                            stride=1 if collect_embeddings else max(1, -(-run.headers.total_masks // SCENE_TRAIN_MAX)))
        pool = ReducePool(options.cluster, cancel) if reducers else None  # its Ray connection outlives the view pass's executor
        sink, device_pairs = _open_sink(run, aggregator, ckpt, block, cancel, show_progress, out)
        workers, worker_rss = _view_pass(run, aggregator, ckpt, sink, totals, device_pairs, show_progress, on_progress, cancel, probe)
        # the blocks' plan counts neither the geometry, culling index and rays the view pass took over nor the probe's kept views
        aggregator.end_views()
        fit_choice, probe = (probe.choice if probe is not None else None), None
        changed = changed_features(run.features_dir, stamps)
        if changed:  # some views were read before the change, some maybe after: the sums mix two sets of features
            raise DrsplatError(f"{run.features_dir}: the feature files of {len(changed)} view(s) changed while the registration read them "
                               f"(e.g. {', '.join(changed[:3])}; another `drsplat features` writing there?); nothing was written: rerun "
                               "when they are final (views whose files did not change are resumed from the checkpoint)")
        if sink.place != "host":  # the views' pairs stayed on the device: which Gaussians got weight is in the sums
            totals.positive |= sink.positive()
        view_seconds, finish_cpu0 = time.perf_counter() - t_start, time.process_time()
        if pool is None:
            candidates = totals.positive if aggregator.rejected() is None else totals.positive & ~aggregator.rejected()
        else:  # the pairs and statistics are in the workers' shards: the reducers know the candidates
            # a check mode: the reducers sum their blocks' parts of the support tables, the driver adds them (exactly)
            # and judges the masks, then the reducers sum the pairs it keeps
            check = sink if aggregator.check else None
            reduce = BlockReduce(pool, make_job(ckpt.log, n, run.dim, block, options.keep_unassigned,
                                                None if check is not None else getattr(sink, "clusters", None), target.out,
                                                target.clip_model, reject=aggregator.reject, check=check, clip_weights=target.clip_weights))
            if check is not None:
                with shard_errors(None):
                    kept = check.kept_pairs(partial_supports=lambda add: pool.supports(reduce.job, add))
                reduce.job = judged(reduce.job, kept.keep)
                if aggregator.vote:  # the clusters of the kept masks with pairs, trimmed by the check's like cosine
                    reduce.job = dataclasses.replace(reduce.job, clusters=kept.clusters(run.dim), trim=check.verdicts.trim,
                                                     pair_means=check.verdicts.pair_means if check.specific else None)
            candidates = reduce.candidates() if codebook == "scene" else None
        if candidates is not None and not candidates.any():
            dropped = aggregator.rejected()
            rejected = int(np.count_nonzero(totals.positive & dropped)) if pool is None and dropped is not None else 0
            raise NothingAssigned(nothing_assigned(totals.done, run.features_dir, out, failure_hint(run, options.level), rejected=rejected, mode=asked))
        if codebook == "scene":
            codebook = _train_scene_codebook(totals, sink if reduce is None else reduce, candidates, run.scene, cancel, show_progress)
        if reduce is None:
            # the kept rows as far as known now (the header's room; drsplat.registration.output.PlyTarget)
            target.open(codebook, rows_hint=n if options.keep_unassigned else int(np.count_nonzero(candidates)))
            weights, fates, blocks, sum_seconds, sum_cpu = _finish_blocks(run, aggregator, sink, target, show_progress, cancel)
            if not np.any(weights > 0):
                raise NothingAssigned(nothing_assigned(totals.done, run.features_dir, out, failure_hint(run, options.level), fates,
                                                    aggregator.num_rejected, asked))
            written = target.close()
        else:
            weights, fates, blocks, sum_seconds, sum_cpu, written, task_seconds = _reduce_blocks(reduce, run, aggregator, codebook, totals, out, asked)
            reducer_seconds = (task_seconds, sum_seconds)
    except BaseException as exc:
        target.abort()
        if ckpt is not None and isinstance(exc, NothingAssigned):
            ckpt.remove()  # every view is logged: a rerun with the same settings would end in this error again (round 91c F2)
        elif ckpt is not None and ckpt.leave(_why(exc)):
            exc.checkpoint_said = True  # the command's last line need not say it again (drsplat.commands.register.interrupted_note)
        raise
    finally:
        if reduce is not None:
            reduce.close()
        if pool is not None:
            pool.close()
    if pool is not None:  # the reducers' workers too
        worker_rss = {pid: max(rss, worker_rss.get(pid, 0)) for pid, rss in {**worker_rss, **pool.worker_peak_rss}.items()}
    log_bytes = ckpt.nbytes if ckpt is not None else 0
    if ckpt is not None:
        ckpt.remove()
    aggregator.log_rejected(asked)
    verdicts = sink.verdicts if aggregator.check else None  # a check mode's sink is its CheckSink, judged by now
    heavy = heavy_drop_warning(verdicts.dropped, verdicts.present, without_check(asked)) if verdicts is not None else None
    if heavy:
        log.warning("%s", heavy)
    if fates.dropped:
        log.warning("%s", unusable_sums(fates))
    if fates.weak:
        log.warning("%s", weak_sums(fates.weak))
    return RegistrationResult(
        features=getattr(target, "features", None), weights=weights, num_views=totals.done, num_pairs=totals.num_pairs,
        num_distinct_pairs=totals.num_distinct, seconds=time.perf_counter() - t_start, view_seconds=view_seconds,
        raster_seconds=totals.raster_seconds, coalesce_seconds=totals.coalesce_seconds,
        accumulate_seconds=totals.coalesce_seconds + totals.sum_seconds + sum_seconds, accumulate_cpu_seconds=totals.sum_cpu_seconds + sum_cpu,
        resumed_views=ckpt.resumed if ckpt is not None else 0, topk=options.topk, level=options.level,
        missing_features=run.selection.missing, unmatched_features=run.selection.unmatched, num_nonfinite_masks=totals.num_nonfinite_masks,
        num_nonfinite_features=fates.dropped, num_weak_features=fates.weak, mask_embeddings=totals.mask_embeddings() if collect_embeddings else None, aggregate=options.aggregate,
        num_rejected=aggregator.num_rejected, block_size=min(block, n), num_blocks=blocks, log_bytes=log_bytes, path=out, num_written=written,
        field_kind="exact" if isinstance(codebook, str) else codebook.kind, worker_peak_rss=worker_rss, workers=workers,
        sums_on=sums_place(sink), pairs_on=options.device if device_pairs else "host",
        finish_cpu_seconds=time.process_time() - finish_cpu0, reducers=reduce is not None,
        reducer_seconds=reducer_seconds[0], reducer_sum_seconds=reducer_seconds[1], driver_view_cpu_seconds=totals.driver_view_cpu_seconds,
        fit=fit_choice,
    )


def _fit_stage(run: Run, cancel: CancelToken | None) -> FitStage | None:
    """A fit mode's stage (drsplat.registration.fit), or None for other modes: the footprint picked on
    its probe views before any view is summed, on the geometry the view pass then uses. When the
    pass computes views as the probe does (numba, in this process) the probe views' pairs are kept
    for it, so they are rendered once; a torch pass on a GPU renders the probe views there (`probe_engine`)."""
    options = run.options
    if not is_fit_mode(options.aggregate):
        return None
    same_views = options.place == "local" and options.engine == "numba"
    engine, device = probe_engine(options.engine, options.device, options.place)
    return fit_stage(options.aggregate, run.scene, run.views, run.features_dir, options.level, options.topk,
                     geometry=prepare_geometry(run.scene), cull=options.cull, keep_pairs=same_views, cancel=cancel, engine=engine, device=device,
                     near=options.near_plane)


def device_pairs_apply(options: RegisterOptions) -> bool:
    """Whether views are coalesced on the torch engine's device (drsplat.registration.device_sums):
    the torch engine in this process, with any mode (every per-view weighting has a torch form);
    floater statistics are then computed and folded on the device too, and a `-vote` mode's slots
    are folded there (device_sums.DeviceVoteSink). Ray workers return host pairs. A `check-` mode
    coalesces on the device too; the driver copies each view's distinct pairs to the host for its
    record or log, where it judges the masks, and in one block sums the kept pairs on the device
    (drsplat.registration.check)."""
    return options.engine == "torch" and options.place == "local"


def _open_sink(run: Run, aggregator: Aggregator, ckpt: Checkpoint | None, block: int, cancel: CancelToken | None = None,
               show_progress: bool = False, out: Path | None = None) -> tuple[Sink, bool]:
    """The sink of the plan and whether views keep their pairs on the device.

    One block with device pairs: a DeviceSink, or a DeviceVoteSink for a `-vote` mode (F, W and the
    vote slots on the device; on CUDA when they fit its free memory, else the host MemorySink /
    VoteSink). Blocks: the pairs are logged and each block replays the log on the host (LogSink,
    VoteSink), whatever the engine. A `check-` mode: CheckSink, in one block or many (`cancel` and
    `show_progress` for its judging of the masks; its support tables spill beside `out`, if any).
    """
    n, dim = run.scene.num_gaussians, run.dim
    on_device = device_pairs_apply(run.options)
    if aggregator.check:  # the masks judged over every view's pairs, replayed from the log (run_registration always keeps one), then the kept pairs summed
        inner = one_block_sink(n, dim, aggregator.vote, run.options.device if on_device else None) if block >= n else None
        if on_device:
            log.info("coalescing on %s; the mask check judges on the host and sums the kept pairs on %s (torch engine, --aggregate %s)",
                     run.options.device, "the host" if inner is None or inner.place == "host" else run.options.device, run.options.aggregate)
        return CheckSink(n, dim, aggregator.vote, ckpt.log, block, inner, cancel=cancel,
                         show_progress=show_progress, spill_beside=out, specific=aggregator.specific), on_device
    if block < n:
        return (VoteSink(n, dim, ckpt.log, block) if aggregator.vote else LogSink(n, dim, ckpt.log, block)), on_device
    sink = one_block_sink(n, dim, aggregator.vote, run.options.device if on_device else None)
    if sink.place != "host":
        log.info("coalescing and summing on %s (torch engine, --aggregate %s)", run.options.device, run.options.aggregate)
    return sink, on_device


def one_block_sink(num_gaussians: int, dim: int, vote: bool, device: str | None = None) -> Sink:
    """The sink of all N Gaussians in one block: on the torch `device` (DeviceSink, or DeviceVoteSink
    for a `-vote` mode) when its sums (and a vote's slots) fit the device's free memory, else, or
    when device is None, on the host (MemorySink, VoteSink)."""
    if device is not None:
        # imports torch: only the torch engine keeps its sums on the device
        from drsplat.registration.device_sums import DeviceSink, DeviceVoteSink, sums_fit_device

        if sums_fit_device(num_gaussians, dim, device, VOTE_SLOT_BYTES if vote else 0):
            return (DeviceVoteSink if vote else DeviceSink)(num_gaussians, dim, device)
        log.info("the sums of %s Gaussians do not fit the free memory of %s: summing on the host", f"{num_gaussians:,}", device)
    return VoteSink(num_gaussians, dim) if vote else MemorySink(num_gaussians, dim)


def _check_memory_before_probe(run: Run, held_later: int = 0) -> int | None:
    """A fit mode's memory (the budget, or what is free) checked before its probe views are rendered:
    the DrsplatError of `choose_block` when a mode the probe may pick does not fit, so that a budget
    too small is refused at once rather than after the probe, and the minimum it names works for
    whichever footprint the probe picks. Returns the resident memory the plan starts from (this
    process's now plus what the probe adds, `probe_memory`), which `_plan_block` keeps after the
    probe; None for other modes (the plan measures it then). held_later: bytes this process will hold besides by then
    (`refuse_if_over_budget`)."""
    options = run.options
    if options.block_size or not is_fit_mode(options.aggregate):
        return None
    rss = current_rss() + held_later
    rejects = probe_folds_floaters(options.aggregate)
    base = rss + probe_memory(run.scene.num_gaussians, run.headers.max_masks * run.dim * 4, rejects, max_masks=run.headers.max_masks)
    if _refusal_for_footprints(run, base) is not None:  # refused: the budget it names allows for the most the probe can hold
        pixels = max((cam.width * cam.height for cam in run.views), default=0)
        raise _refusal_for_footprints(run, rss + probe_memory_bound(run.scene.num_gaussians, pixels, options.topk,
                                                                     run.headers.max_masks * run.dim * 4, run.headers.max_masks, rejects))
    return base


def refuse_if_over_budget(run: Run, held_later: int = 0) -> None:
    """The memory plan's refusal (`choose_block`'s DrsplatError) said before work that precedes the registration
    (`register --near-plane auto` renders its plane's evidence first; round 65a F5: a --memory-budget too small
    was refused only after that decision and its warning). Nothing is logged when the run fits; the registration
    plans again from the memory held then (this process may hold more by then, so it can still refuse). held_later: what the
    work before the registration leaves resident, counted now (`frames.DECISION_HELD_BYTES`: round 67a F2, a budget this
    check accepted was refused after the decision by the 13 MB its render kernels and image readers stay)."""
    options = run.options
    if options.block_size:
        return
    load_rendering_engine(run)  # round 67a F2: planned without it, --engine torch was told 515 MB and then refused under 1.1 GB
    if is_fit_mode(options.aggregate):
        _check_memory_before_probe(run, held_later)
        return
    choose_block(_memory_plan(run, current_rss() + held_later), options.memory_budget, whole=mode_stages(options.aggregate).solve)


def load_rendering_engine(run: Run) -> None:
    """The engine that renders the views, loaded when this process renders them (not on Ray), so that a memory plan
    made after it counts it in this process's resident memory (torch: ~0.4 GB, probe round 11)."""
    if run.options.place != "ray":
        get_engine(run.options.engine).topk_fn()


def _memory_plan(run: Run, base: int | None = None, aggregate: str | None = None) -> MemoryPlan:
    """`estimate_memory` of `run` in its mode (or `aggregate`), from `base` resident bytes (None: this process's now)."""
    return estimate_memory(run.scene, run.views, run.dim, run.options.topk, base=base, aggregate=aggregate or run.options.aggregate,
                           total_masks=run.headers.total_masks, max_masks=run.headers.max_masks)


def _refusal_for_footprints(run: Run, base: int) -> DrsplatError | None:
    """`choose_block`'s refusal of the mode either footprint makes from a fit mode, starting from `base`
    (the one naming the larger budget), or None when both fit."""
    refusals = []
    for footprint in FOOTPRINTS:
        plan = _memory_plan(run, base, resolve_mode(run.options.aggregate, footprint))
        try:
            choose_block(plan, run.options.memory_budget)
        except DrsplatError as exc:
            refusals.append((plan.minimum_budget(), plan.in_memory, exc))
    return max(refusals, key=lambda refusal: refusal[:2])[2] if refusals else None


def _plan_block(run: Run, base: int | None = None, taken_over: int = 0) -> int:
    """The block to register with (`choose_block`). base: the resident memory the plan starts from,
    as checked before a fit mode's probe (the larger of it and the process's now is used, so that a
    budget accepted then is accepted now unless the probe held more than was allowed for).
    taken_over: bytes the process holds now that the plan counts per Gaussian itself (the probe's
    geometry, culling index and rays, `FitStage.pass_bytes`), not counted twice."""
    if base is not None:
        trim_heap()  # the probe's freed arrays are not memory in use
        base = max(base, current_rss() - taken_over)
    plan = _memory_plan(run, base)
    block = choose_block(plan, run.options.memory_budget, whole=mode_stages(run.options.aggregate).solve)
    if block < run.scene.num_gaussians:
        log.info("estimated peak memory: %s in one block, %s in blocks of %s Gaussians", format_size(plan.in_memory),
                 format_size(plan.peak(block)), f"{block:,}")
    else:  # said for every run (round 63b: a run in one block said nothing), as an estimate: small scenes peak at 0.3-0.7 of it
        log.info("estimated peak memory: %s, in one block", format_size(plan.in_memory))
    return block


def _why(exc: BaseException) -> str:
    """How a registration ended early, for the message about what it left behind."""
    if isinstance(exc, (Cancelled, KeyboardInterrupt)):
        return "registration stopped"
    if isinstance(exc, OSError):
        return f"registration stopped ({describe_os_error(exc)})"
    return "registration failed"


def _view_pass(run: Run, aggregator: Aggregator, ckpt: Checkpoint | None, sink: Sink, totals: ViewTotals, device_pairs: bool,
               show_progress: bool, on_progress, cancel, probe: FitStage | None = None) -> tuple[list[WorkerStats], dict[int, int]]:
    """Replay the checkpoint's views, then compute the others with the executor, in view order:
    fold the mode's statistics, log the view, add it to the sink. device_pairs: views keep their
    pairs on the torch engine's device (copied to the host only to be logged). probe: the fit
    stage, whose geometry and culling index the executor takes and whose probe views' pairs
    (`FitStage.pairs`) are used where they fall instead of computing those views again. Returns the
    WorkerStats of the processes that computed views and the Ray workers' peak RSS (pid -> bytes)."""

    def consume(view: ViewPairs) -> None:
        totals.add(view)
        t0, c0 = time.perf_counter(), time.process_time()
        sink.add(view)
        totals.sum_seconds += time.perf_counter() - t0
        totals.sum_cpu_seconds += time.process_time() - c0

    total = len(run.views)
    if ckpt is not None:
        for view in ckpt.replay():
            consume(view)
        if ckpt.done:
            log.info("resuming from %s: %d of %d views already registered", ckpt.path, ckpt.done, total)
    if on_progress is not None:
        on_progress(totals.done, total)
    if cancel is not None:
        cancel.raise_if_cancelled()
    if totals.done == total:
        return [], {}
    options = run.options
    shards = ckpt is not None and ckpt.shards_dir is not None
    job = ViewJob(run.features_dir, options.level, options.topk, options.engine, options.device, aggregator.hook, options.cull,
                  device_pairs=device_pairs, group_pairs=ckpt is not None, shard_dir=str(ckpt.shards_dir.resolve()) if shards else None,
                  log_params=ckpt.log.params if shards else None, by_gaussian=pairs_by_gaussian(options.aggregate), near=options.near_plane)
    ready = {i: view for i, view in (probe.pairs if probe is not None else {}).items() if i >= totals.done}
    geometry = probe.geometry if probe is not None else prepare_geometry(run.scene)
    executor = open_executor(options.place, geometry, job, options.cluster, index=probe.index if probe is not None else None, cancel=cancel)
    stream = executor.view_pairs([cam for i, cam in enumerate(run.views) if i >= totals.done and i not in ready])
    views = one_view_behind(stream) if device_pairs else stream  # a device view's sizes are read while the next one renders
    if ready:
        views = in_view_order(range(totals.done, total), ready, views, grouped=job.group_pairs)
    try:
        for view in progress(views, desc="register", total=total - totals.done, enabled=show_progress, unit="view"):
            c0 = time.process_time()
            if ckpt is not None or sink.place == "host":
                view = view.on_host()  # for the log or the host sums: one copy of the view's pairs
            if ckpt is not None:
                ckpt.append(view)
            aggregator.add(view.stats)
            if ckpt is not None:
                ckpt.folded()
            consume(view)
            totals.driver_view_cpu_seconds += time.process_time() - c0
            if on_progress is not None:
                on_progress(totals.done, total)
            if cancel is not None and totals.done < total:
                cancel.raise_if_cancelled()
    finally:
        stream.close()
        executor.close()
    return list(executor.worker_stats.values()), dict(getattr(executor, "worker_peak_rss", {}))


def in_view_order(indices: range, ready: dict[int, ViewPairs], computed: Iterator[ViewPairs], grouped: bool = False) -> Iterator[ViewPairs]:
    """The views of `indices` in order: ready[i] where computed already (grouped by Gaussian chunk
    when `grouped`, as the executor's are), else the next of `computed` (the other views, in order)."""
    for i in indices:
        view = ready.pop(i, None)
        if view is None:
            yield next(computed)
        else:
            yield view.grouped() if grouped else view


def _train_scene_codebook(totals: ViewTotals, sink: Sink, candidates: np.ndarray, scene: GaussianScene, cancel: CancelToken | None = None,
                          show_progress: bool = False) -> Codebook:
    """The scene codebook: PQ trained on the masks' embeddings, topped up with the unit features of a
    sample of the Gaussians that will be assigned (summed by the sink, so the same in every plan),
    drawn and ordered by their parameters' hashes (`scene_sample_ids`, `GaussianScene.identity_rows`),
    so the same in any order of the scene file's Gaussians."""

    def sample_features() -> np.ndarray:
        ids = scene_sample_ids(np.flatnonzero(candidates), scene.identity_rows)
        ascending = np.sort(ids)  # what a sink replays
        F, W = sink.sample(ascending)
        F, _ = normalize_rows(F, W)
        at = np.searchsorted(ascending, ids)  # back in sample order: the codebook's k-means sees its rows in it
        return F[at][W[at] > 0]

    train = scene_training_set(totals.mask_embeddings(), sample_features, totals.dim)
    totals.embeddings = []
    return train_codebook(train, m=SCENE_CODEBOOK_M, seed=0, cancel=cancel, show_progress=show_progress)


def _finish_blocks(run: Run, aggregator: Aggregator, sink: Sink, target: Target, show_progress: bool, cancel):
    """Per block: the mode's step on the sums, normalise, prune, hand to the target.
    Returns (weights [N], RowFates of the normalisation, blocks, seconds summing, CPU seconds summing)."""
    n = run.scene.num_gaussians
    weights = np.zeros(n, np.float32)
    fates = RowFates()
    blocks = 0
    sum_seconds = sum_cpu = 0.0
    count = sink.num_blocks
    stream = sink.blocks(reuse=True)  # each block is dropped (its rows encoded or copied) before the next is asked for
    bar = progress(range(count), desc="blocks", total=count, enabled=show_progress and count > 1, unit="block")
    for _ in bar:
        if cancel is not None:
            cancel.raise_if_cancelled()
        t0, c0 = time.perf_counter(), time.process_time()
        block = next(stream)
        sum_seconds += time.perf_counter() - t0
        sum_cpu += time.process_time() - c0
        if aggregator.solve:  # the solve stage (one block: refused up front otherwise), before floater rejection
            _solve_block(run, block, cancel)
        aggregator.finish(block.F, block.W, block.lo)
        _, block_fates = normalize_rows(block.F, block.W, block.kept)
        fates += block_fates
        weights[block.lo : block.hi] = block.W
        keep = np.ones(block.hi - block.lo, bool) if run.options.keep_unassigned else block.W > 0
        target.add(block, keep)
        blocks += 1
        del block, keep  # the next block's sums must not be allocated while this one's are alive (the plan counts one)
    return weights, fates, blocks, sum_seconds, sum_cpu


def _reduce_blocks(reduce: BlockReduce, run: Run, aggregator: Aggregator, codebook, totals: ViewTotals, out: Path | None, asked: str):
    """The blocks finished by reducer tasks, then the parts assembled into `out` (drsplat.registration.reduce); asked: the
    mode as the user named it (for the error when nothing is assigned).
    Returns what `_finish_blocks` does, the rows written and the reducer tasks' seconds (summed)."""
    parts, weights = reduce.finish(run.scene, codebook, aggregator)
    if not np.any(weights > 0):
        raise NothingAssigned(nothing_assigned(totals.done, run.features_dir, out, unassigned_hint(run.scene, run.views, run.options.near_plane, run.options.near_plane_decided),
                                            sum((p.fates for p in parts), RowFates()), sum(p.rejected for p in parts), asked))
    written = assemble_parts(Path(reduce.job.out), parts, codebook)  # the codebook written after the body, before the rename
    return (weights, sum((p.fates for p in parts), RowFates()), len(parts), sum(p.sum_seconds for p in parts), sum(p.sum_cpu_seconds for p in parts),
            written, sum(p.seconds for p in parts))


def _solve_block(run: Run, block, cancel) -> None:
    """The render-consistent solve on the whole scene's sums (drsplat.registration.solve), re-rendering
    the views with the registration's engine in this process; cancel: checked before each view it renders."""
    options = run.options
    solve_registration(prepare_geometry(run.scene, warn=False), run.views, run.features_dir, options.level, options.topk, options.engine, options.device,
                       block.F, cancel=cancel, near=options.near_plane)


def register(
    scene: GaussianScene,
    cameras: Sequence[Camera],
    features_dir: str | Path,
    out: str | Path,
    options: RegisterOptions = RegisterOptions(),
    *,
    resumable: bool = True,
    checkpoint_every: int = CHECKPOINT_EVERY,
    show_progress: bool = True,
    on_progress: Callable[[int, int], None] | None = None,
    cancel: CancelToken | None = None,
    lock: RunLock | None = None,
    say_first_run: bool = True,
) -> RegistrationResult:
    """Register `features_dir` onto `scene` and write the registered PLY `out` atomically.

    resumable: keep a checkpoint beside `out` while working (`checkpoint_path_for(out)`): a cancelled
    or killed run resumes from it; it is deleted once `out` is written. checkpoint_every: views
    between the checkpoint's fsyncs and the mode's statistics snapshots. lock: the checkpoint's lock, already
    taken by the caller (`run_registration`). say_first_run: as `run_registration`'s.
    """
    out = Path(out)
    scene = widened_scene(scene)  # float16 arrays as float32: numba loads no float16
    # the file says at which plane it was registered (`eval lerf` renders it there); an input's own such line does not carry over
    plane = near_plane_comment(options.near_plane)
    if plane is not None or any(c.startswith(NEAR_PLANE_COMMENT) for c in scene.comments):
        scene = dataclasses.replace(scene, comments=[*(c for c in scene.comments if not c.startswith(NEAR_PLANE_COMMENT)), *([plane] if plane else [])])
    run = prepare_run(scene, cameras, features_dir, options)
    manifest = read_manifest(run.features_dir)
    check_manifest_dim(run.features_dir, manifest, run.dim)
    warn_if_distorted_without_manifest(run.selection.views, manifest, run.features_dir)
    warn_if_turned_without_manifest(run.selection.views, manifest, run.features_dir)
    warn_if_scene_misses_its_images(scene, run.selection.views, options.near_plane)
    target = PlyTarget(scene, out, manifest_model_id(manifest), cancel, clip_weights=manifest_weights(manifest))
    result = run_registration(run, target, checkpoint=checkpoint_path_for(out) if resumable else None, checkpoint_every=checkpoint_every, out=out,
                              show_progress=show_progress, on_progress=on_progress, cancel=cancel, lock=lock if resumable else None,
                              say_first_run=say_first_run)
    log.info("%s: %s (%d unassigned, %s), %s field, %s in %s, %.1f s", out, counted(result.num_written, "Gaussian", "Gaussians"),
             n_unassigned(result), "kept with lang_weight 0" if options.keep_unassigned else "pruned", result.field_kind,
             counted(result.num_views, "view", "views"), counted(result.num_blocks, "block", "blocks"), result.seconds)
    # the registered views' causes, not those of cameras without features (round 68a F6: the plane hid 91 % in the one view)
    warn_if_mostly_unassigned(result, scene, run.views, options.near_plane, options.near_plane_decided)
    return result


LOW_ASSIGNED_FRACTION = 0.5  # below this share of Gaussians with a feature, a run is most likely misconfigured


def warn_if_mostly_unassigned(result: RegistrationResult, scene: GaussianScene, cameras, near: float = NEAR, decided: bool = False) -> None:
    """One warning when fewer than LOW_ASSIGNED_FRACTION of the Gaussians got a feature, with the likely cause.

    A trained scene seen by its own training views assigns most Gaussians; a small share means tiny
    views (`--resolution 0.001` rendered 1-pixel views), a scene nearer to its cameras than the
    near plane (in other units, or scaled down), cameras that miss the scene, or masks that cover
    little. The run still succeeds: the user decides.
    """
    total = int(result.weights.shape[0])
    if total == 0 or result.num_assigned >= LOW_ASSIGNED_FRACTION * total:
        return
    log.warning("only %d of %d Gaussians (%.0f%%) were seen inside a mask and got a language feature; %d got nothing%s",
                result.num_assigned, total, 100.0 * result.num_assigned / total, total - result.num_assigned,
                unassigned_hint(scene, cameras, near, decided))


def unassigned_hint(scene: GaussianScene, cameras: Sequence[Camera], near_plane: float = NEAR, decided: bool = False) -> str:
    """'; <the likely cause>' of a registration that assigned few or no Gaussians, "" when none shows:
    views under 64 px wide, Gaussians too faint for any pixel (opacity < 1/255), Gaussians nearer to every camera than the near plane (a scene in other
    units than its cameras: the projection culls them), else `frame_hint`'s scene in another frame. decided: the plane was
    decided by `--near-plane auto` (`near_plane_remedy`)."""
    sizes = sorted({(c.width, c.height) for c in cameras})
    small = bool(sizes) and sizes[0][0] < 64
    why = f"; the views are only {sizes[0][0]}x{sizes[0][1]} px (check --resolution)" if small else ""
    faint = faint_share(scene)
    if faint >= 0.1:  # every pixel skips them (α < 1/255, as 3DGS's rasterizer does): seen or not, they get no weight
        why += f"; {int(100 * faint)}% of the Gaussians have an opacity under 1/255, which the rasterizer skips at every pixel"
    near = share_within_near_plane(scene.means, cameras, near=near_plane)
    if near >= 0.1:
        return why + (f"; {int(100 * near)}% of the Gaussians are nearer to every camera than the near plane ({near_plane:g} scene units), "
                      "which culls them: " + near_plane_remedy(median_nearest_depth(scene.means, cameras), near_plane, decided))
    if small:  # a few pixels hold few centres whatever the frame: "another frame" would mislead
        return why
    return why + frame_hint(scene.means, cameras, near_plane)


def near_plane_remedy(depth: float, near_plane: float = NEAR, decided: bool = False) -> str:
    """What to do about a scene the near plane culls, given how far its Gaussians lie from the cameras
    (`median_nearest_depth`, scene units). A plane the user chose (`near_plane` not NEAR) deeper than
    that is the cause itself: a smaller one is named (the default where it fits, else a power of ten
    at most a tenth of the depth; round 64c: a plane of 5 on a room 0.24 units away was told to scale
    the scene). At the default plane, a capture whose Gaussians lie a median under 1 unit from its
    cameras is a whole capture at a tiny scale (scene and cameras in kilometres, say; both scaled
    together, they stay in one unit system), so scaling both up by the power of ten that brings that
    median to 1 or more renders it, as does such a smaller plane; otherwise the scene and cameras
    disagree on units. decided: the plane was decided by `--near-plane auto`, and the remedy names a plane to pass."""
    if not 1e-300 < depth < math.inf:  # NaN too; under 1e-300 the factor would pass float64's range
        return "are the scene and its cameras in the same units?"
    plane = plane_below(depth)
    if near_plane != NEAR and decided:
        return (f"the Gaussians lie a median {depth:.2g} scene units from these cameras, nearer than the near plane of {near_plane:g} "
                f"that --near-plane auto decided from the training images: register with --near-plane {min(plane, NEAR):g}")
    if near_plane != NEAR:
        smaller = f"--near-plane {min(plane, NEAR):g}"  # not "leave it out": `auto` may decide the same plane again (round 68a F5)
        return (f"the Gaussians lie a median {depth:.2g} scene units from the cameras, nearer than the --near-plane of "
                f"{near_plane:g}: register with a smaller plane ({smaller})")
    if depth >= 1.0:
        return "are the scene and its cameras in the same units?"
    factor = 10.0 ** math.ceil(-math.log10(depth))
    or_plane = f", or register with --near-plane {plane:g}" if plane < NEAR else ""
    return (f"the Gaussians lie a median {depth:.2g} scene units from the cameras, so the whole capture is at a scale the near plane "
            f"does not fit: scale the scene and its cameras up together (by {factor:g}, say) and register again{or_plane}")


def n_unassigned(result: RegistrationResult) -> int:
    return int(result.weights.shape[0]) - result.num_assigned


def register_features(
    scene: GaussianScene,
    cameras: Sequence[Camera],
    features_dir: str | Path,
    options: RegisterOptions = RegisterOptions(),
    *,
    checkpoint: str | Path | None = None,
    checkpoint_every: int = CHECKPOINT_EVERY,
    collect_embeddings: bool = False,
    show_progress: bool = True,
    on_progress: Callable[[int, int], None] | None = None,
    cancel: CancelToken | None = None,
) -> RegistrationResult:
    """Register `features_dir` onto `scene` and return the features [N, D] in memory (result.features:
    unit rows, zero where unassigned). checkpoint: a pair log to resume from (removed at the end)."""
    scene = widened_scene(scene)  # float16 arrays as float32: numba loads no float16
    run = prepare_run(scene, cameras, features_dir, options)
    target = ArrayTarget(scene.num_gaussians, run.dim)
    result = run_registration(run, target, checkpoint=Path(checkpoint) if checkpoint is not None else None, checkpoint_every=checkpoint_every,
                              collect_embeddings=collect_embeddings,
                              show_progress=show_progress, on_progress=on_progress, cancel=cancel)
    log.info("registered %d views: %d of %d Gaussians assigned, %.1f M contributing pairs, %.1f s",
             result.num_views, result.num_assigned, scene.num_gaussians, result.num_pairs / 1e6, result.seconds)
    return result
