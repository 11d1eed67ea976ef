"""Computing one view of a registration, the same way in every place and with every engine.

`ViewComputer` rasterizes a view with the job's engine (a key of drsplat.raster.ENGINES: "numba"
on the CPU, "torch" on the CPU or a CUDA device) keeping each pixel's top-k (ids, weights); runs
the aggregation mode's per-view hook where the view was rendered
(drsplat.registration.aggregate.ViewHook: reweighting, floater statistics); and coalesces the
pixels into the view's distinct (Gaussian, mask) pairs (drsplat.registration.coalesce). Every
engine computes the same pairs for the same view, so the registered field does not depend on it
(tests/test_registration_matrix.py).
"""

from __future__ import annotations

import os
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drsplat.cameras import Camera
from drsplat.errors import UsageError
from drsplat.memory import peak_rss
from drsplat.defaults import ENGINES
from drsplat.raster import ENGINES as RASTER_ENGINES
from drsplat.raster import NEAR, PreparedScene, RasterOutput, get_engine, prepare_scene, subset_geometry, warn_unrendered
from drsplat.registration.aggregate import ViewHook, mode_stages
from drsplat.registration.coalesce import Coalescer
from drsplat.registration.culling import SpatialIndex, remap_ids
from drsplat.registration.pairlog import ViewPairs
from drsplat.registration.views import load_view_features, used_masks
from drsplat.scene import GaussianScene

CPU_ONLY_ENGINES = ("numba",)
# What the two ways of rendering a view cost beyond what they share (x86_64, 2 threads, measured
# 2026-11-30 on flowers and hard-room, docs/registration.md "Frustum culling"): projecting a Gaussian
# (in view or not), gathering and projecting a visible one (`subset_geometry`), and mapping one
# [H, W, k] slot of the culled render back to scene ids (`remap_ids`). Only the ratios matter.
PROJECT_NS = 15.0
SUBSET_NS = 25.0
REMAP_NS = 0.2


def renders_whole(visible: int, num_gaussians: int, slots: int) -> bool:
    """Whether a view with `visible` of `num_gaussians` Gaussians in view (the culling index's test)
    renders them all instead of the culled subset: when gathering and projecting the visible ones
    and remapping the render's `slots` (H·W·k) ids would cost at least projecting every Gaussian,
    SUBSET_NS·V + REMAP_NS·slots ≥ PROJECT_NS·N. The top-k lists are the same either way (culling
    is exact); a flowers view (N = 542k, 640 x 480 x 40 slots) culls below ~42 % in view, a 27k
    room of 320 x 240 views never (its remap alone costs more than projecting the room)."""
    return SUBSET_NS * visible + REMAP_NS * slots >= PROJECT_NS * num_gaussians


def culling_pays(num_gaussians: int, slots: int) -> bool:
    """Whether a view of `slots` (H·W·k) slots could render a culled subset of a scene of
    `num_gaussians` at all (`renders_whole` with nothing in view is False); when not, the view
    skips the culling index's test."""
    return not renders_whole(0, num_gaussians, slots)


@dataclass(frozen=True)
class ViewJob:
    """What computing a view needs besides the scene; picklable, the same in every place.

    features_dir / level: where the views' LangSplat masks and embeddings are. topk: Gaussians
    kept per pixel. engine / device: the rasterizer (drsplat.raster.ENGINES) and where it runs.
    hook: the aggregation mode's per-view hook, or None (the paper's w = T·α as it is).
    cull: project only the Gaussians the view can see (drsplat.registration.culling; exact, CPU
    engines); False projects all of them.
    device_pairs: coalesce on the torch engine's device and leave the pairs there
    (drsplat.registration.device_sums; the torch engine in this process, any mode).
    group_pairs: hand out host pairs grouped by Gaussian chunk (`ViewPairs.grouped`, the pair log's
    record order), so the process that computed the view sorts them, not the driver that logs it.
    shard_dir / log_params: the views are logged by the Ray workers that compute them, each into a
    shard of its own in this folder (drsplat.registration.pairlog.ShardWriter, with the log's
    parameters), and the driver gets pointers; None: the driver logs them.
    by_gaussian: coalesce each view's pairs grouped by Gaussian (`Coalescer.coalesce`): what a mode
    with a vote or check stage reads them as (`pairs_by_gaussian`); the sums do not change.
    near: the near plane, the camera depth below which Gaussians are not drawn (RegisterOptions.near_plane).
    """

    features_dir: Path
    level: int
    topk: int
    engine: str = "numba"
    device: str = "cpu"
    hook: ViewHook | None = None
    cull: bool = True
    device_pairs: bool = False
    group_pairs: bool = False
    shard_dir: str | None = None
    log_params: dict | None = None
    by_gaussian: bool = False
    near: float = NEAR


def pairs_by_gaussian(mode: str) -> bool:
    """Whether `mode`'s views are best coalesced grouped by Gaussian (`ViewJob.by_gaussian`): its vote
    and check stages read a view's pairs Gaussian by Gaussian, which otherwise costs them a sort each."""
    stages = mode_stages(mode)
    return stages.vote or stages.check


def check_engine(engine: str, device: str) -> None:
    """UsageError in one sentence when registration cannot run `engine` on `device`."""
    if engine not in ENGINES or engine not in RASTER_ENGINES:  # the numpy reference rasterizer is for tests
        raise UsageError(f"unknown registration engine {engine!r}; choose {' or '.join(ENGINES)}")
    if engine in CPU_ONLY_ENGINES and device != "cpu":
        raise UsageError(f"the {engine} engine runs on the CPU only, not on {device!r}; use --engine torch with --device {device}")


def prepare_geometry(scene: GaussianScene, chunk: int = 1 << 20, warn: bool = True) -> PreparedScene:
    """`raster.prepare_scene` without the SH coefficients (registration renders no colour).

    Prepared chunk by chunk: ~101 bytes per Gaussian (means and covariances float64, opacity,
    finite flag), the SH checked but never copied. Gaussians with non-finite SH are still flagged
    non-finite, exactly as prepare_scene does. warn: say the unusable ones (`raster.warn_unrendered`) once,
    not per chunk; off for a second preparation of a scene already said (the solve's: round 90b F1).
    """
    n = scene.num_gaussians
    means = np.empty((n, 3), np.float64)
    covs = np.empty((n, 3, 3), np.float64)
    opacities = np.empty(n, np.float32)
    finite = np.empty(n, bool)
    for start in range(0, n, chunk):
        part = prepare_scene(scene.subset(slice(start, start + chunk)), with_sh=False, warn=False)
        stop = start + part.num_gaussians
        means[start:stop], covs[start:stop] = part.means, part.covariances
        opacities[start:stop], finite[start:stop] = part.opacities, part.finite
    prepared = PreparedScene(means=means, covariances=covs, opacities=opacities, sh=np.zeros((n, 0, 3), np.float32), finite=finite)
    if warn:
        warn_unrendered(prepared)  # once for the scene, not once a chunk
    return prepared


class ViewComputer:
    """Computes views with one engine on one device (see the module docstring).

    geometry: the scene's CPU geometry (`prepare_geometry`); the engine prepares its own form of it
    once (tensors on the device for torch). Holds the coalescer's [N] scratch and the previous
    view's raster buffers, reused from view to view. index: the scene's culling index when built
    already (a Ray task gets the driver's from the object store instead of building it per task).
    """

    def __init__(self, geometry: PreparedScene, job: ViewJob, index: SpatialIndex | None = None):
        check_engine(job.engine, job.device)
        engine = get_engine(job.engine)
        self.job = job
        self._render = engine.topk_fn()  # ids and weights only: registration sums a pixel's slots whatever their order
        self._prepared = engine.prepare_fn()(geometry, job.device)
        hook = job.hook
        self._geometry = geometry if hook is not None and hook.needs_projection else None  # the hook projects on the CPU
        self._with_median = hook is not None and hook.needs_median
        self._coalescer = Coalescer(geometry.num_gaussians)
        self._out = None
        # culling subsets the CPU geometry per view; the torch engine keeps its tensors on the device
        culls = job.cull and isinstance(self._prepared, PreparedScene)
        self._index = (index or SpatialIndex.build(geometry)) if culls else None
        self.projected = 0  # Gaussians handed to the rasterizer, summed over this computer's views
        self._render_pairs = None
        self._rays = None
        self._tiles = None  # the device path's TileCapacity: tile lists sized from the views read before
        if job.device_pairs:
            if job.engine != "torch":
                raise ValueError("pairs are coalesced on the device with the torch engine only")
            # imports torch: only the torch engine's device path needs it
            from drsplat.registration.device_sums import DeviceRays, TileCapacity, render_pairs

            self._render_pairs = render_pairs
            self._tiles = TileCapacity.for_device(self._prepared.device)
            if hook is not None and hook.reject:  # the floater statistics are computed on the device too
                self._rays = DeviceRays.from_host(hook.rays, self._prepared.device)

    def compute(self, cam: Camera, mask_ids: np.ndarray, feats: np.ndarray, nonfinite: int = 0) -> ViewPairs:
        """The ViewPairs of view `cam` with its mask ids [H, W] and embeddings feats [M, D]."""
        if self._render_pairs is not None:
            return self._compute_on_device(cam, mask_ids, feats, nonfinite)
        t0 = time.perf_counter()
        self._out = self._rasterize(cam)
        raster_seconds = time.perf_counter() - t0
        hook = self.job.hook
        weights, stats = (self._out.weights, None) if hook is None else hook(self._geometry, cam, self._out, mask_ids, near=self.job.near)
        view = self.pairs(cam, self._out.ids, weights, stats, mask_ids, feats, nonfinite, raster_seconds)
        return view.grouped() if self.job.group_pairs else view

    def pairs(self, cam: Camera, ids: np.ndarray, weights: np.ndarray, stats, mask_ids: np.ndarray, feats: np.ndarray, nonfinite: int = 0,
              raster_seconds: float = 0.0) -> ViewPairs:
        """The ViewPairs of view `cam` from its top-k ids [H, W, k] (scene ids), the weights [H, W, k]
        to accumulate and the hook's stats: its distinct (Gaussian, mask) pairs (not grouped; the
        coalescing's seconds are counted from the call)."""
        t0 = time.perf_counter()
        g, m, w, pairs = self._coalescer.coalesce(ids, weights, mask_ids, feats.shape[0], by_gaussian=self.job.by_gaussian)
        view = ViewPairs(cam.name, feats, g, m, w, used_masks(mask_ids), pairs, num_nonfinite=nonfinite, stats=stats)
        view.raster_seconds, view.coalesce_seconds = raster_seconds, time.perf_counter() - t0
        return view

    def _compute_on_device(self, cam: Camera, mask_ids: np.ndarray, feats: np.ndarray, nonfinite: int, exact: bool = False) -> ViewPairs:
        """`compute` with the pairs coalesced and left on the device (ViewPairs.device; host arrays
        empty) and its sizes pending (`ViewPairs.resolved` reads them; nothing is read here unless
        the tile lists are sized exactly: `exact`, or no view was read yet)."""
        t0 = time.perf_counter()
        weighting = self.job.hook.weighting if self.job.hook is not None else "paper"
        capacity = None if exact else self._tiles.capacity()
        pairs, read, raster_seconds, stats = self._render_pairs(self._prepared, cam, self.job.topk, mask_ids, feats.shape[0], weighting,
                                                                self._rays, capacity, near=self.job.near)
        pairs.pending = self._tiles.pending(read, capacity, lambda: self._compute_on_device(cam, mask_ids, feats, nonfinite, exact=True))
        used = used_masks(mask_ids)
        none = np.zeros(0, np.int32)
        return ViewPairs(cam.name, feats, none, none, np.zeros(0, np.float32), used, 0, num_nonfinite=nonfinite,
                         raster_seconds=raster_seconds, coalesce_seconds=time.perf_counter() - t0 - raster_seconds, stats=stats, device=pairs)

    @property
    def index(self) -> SpatialIndex | None:
        """The culling index this computer culls with (None when it renders every Gaussian)."""
        return self._index

    def rasterize(self, cam: Camera):
        """The view's top-k RasterOutput (ids, weights [H, W, k], scene ids) with this computer's engine
        and culling; no hook (the fit and solve stages render with it). Its arrays are the previous
        view's buffers, reused (fresh ones cost page faults), so the next call overwrites them."""
        self._out = self._rasterize(cam)
        return self._out

    def _rasterize(self, cam: Camera):
        """The view's RasterOutput with scene ids, rendering only the visible Gaussians when culling
        and that costs less than rendering every one (`renders_whole`)."""
        def render(prepared):
            return self._render(prepared, cam, self.job.topk, with_median=self._with_median, out=self._out, device=self.job.device, near=self.job.near)

        slots = cam.width * cam.height * self.job.topk
        if self._index is None or not culling_pays(self._prepared.num_gaussians, slots):
            self.projected += self._prepared.num_gaussians if isinstance(self._prepared, PreparedScene) else 0
            return _whole(render(self._prepared))
        ids = self._index.visible(cam, self.job.near)
        if renders_whole(ids.size, self._prepared.num_gaussians, slots):
            self.projected += self._prepared.num_gaussians
            return _whole(render(self._prepared))
        self.projected += int(ids.size)
        out = render(subset_geometry(self._prepared, ids))
        remap_ids(out.ids, ids)
        if out.median_ids is not None:
            remap_ids(out.median_ids, ids)
        if isinstance(out, RasterOutput):
            out.projected_ids = ids
        return out

    def load_and_compute(self, cam: Camera) -> ViewPairs:
        """`compute` with the view's features read from the job's feature folder."""
        return self.compute(cam, *load_view_features(self.job.features_dir, cam, self.job.level))


def _whole(out):
    """out, its projection (if any) marked as the whole scene's: a buffer reused from a culled view keeps no stale subset ids."""
    if isinstance(out, RasterOutput):
        out.projected_ids = None
    return out


@dataclass
class WorkerStats:
    """What one process computing views did (this process for a local run, a Ray worker's otherwise).

    first_view_seconds: its first view, from reading the features to the pairs, which includes
    loading its numba kernels from the on-disk cache or compiling them; later_view_seconds: each
    later view's. kernels_cached / kernels_compiled: numba kernels this process loaded from the
    cache / compiled (`kernel_cache_counts`). peak_rss: its peak resident bytes. log_seconds: time
    writing its shard of the log (included in the views' seconds; 0 when the driver logs).
    """

    pid: int = field(default_factory=os.getpid)
    first_view_seconds: float | None = None
    later_view_seconds: list[float] = field(default_factory=list)
    kernels_cached: int = 0
    kernels_compiled: int = 0
    peak_rss: int = 0
    log_seconds: float = 0.0

    def add_view(self, seconds: float) -> None:
        if self.first_view_seconds is None:
            self.first_view_seconds = seconds
        else:
            self.later_view_seconds.append(seconds)

    def merge(self, other: "WorkerStats") -> None:
        """Fold in a later report of the same process (a Ray worker reports per call, in any order;
        its counts and peak only grow)."""
        if other.first_view_seconds is not None:
            self.first_view_seconds = other.first_view_seconds
        self.later_view_seconds.extend(other.later_view_seconds)
        self.kernels_cached = max(self.kernels_cached, other.kernels_cached)
        self.kernels_compiled = max(self.kernels_compiled, other.kernels_compiled)
        self.peak_rss = max(self.peak_rss, other.peak_rss)
        self.log_seconds += other.log_seconds

    def refresh(self) -> "WorkerStats":
        """Read this process's kernel counts and peak RSS now; returns self."""
        self.kernels_cached, self.kernels_compiled = kernel_cache_counts()
        self.peak_rss = peak_rss()
        return self

    @property
    def median_later_view_seconds(self) -> float | None:
        return statistics.median(self.later_view_seconds) if self.later_view_seconds else None


def kernel_cache_counts() -> tuple[int, int]:
    """(kernels loaded from numba's on-disk cache, kernels compiled) by this process so far.

    Counted over the numba dispatchers of drsplat's loaded modules (`Dispatcher.stats`: a cache
    lookup that finds the kernel is a hit, one that does not compiles it and is a miss); every
    kernel is `cache=True`, so a process whose node compiled them already compiles none.
    """
    hits = misses = 0
    seen: set[int] = set()
    for name, module in list(sys.modules.items()):
        if module is None or not (name == "drsplat" or name.startswith("drsplat.")):
            continue
        for value in list(vars(module).values()):
            stats = getattr(value, "stats", None)
            if id(value) in seen or not hasattr(stats, "cache_hits"):
                continue
            seen.add(id(value))
            hits += sum(stats.cache_hits.values())
            misses += sum(stats.cache_misses.values())
    return hits, misses
