"""`drsplat bench register`: registration speed next to its accuracy.

Two tables:
1. a synthetic scene with exact ground truth, registered with top-k in {1, 5, 10, 20, 40} (the
   paper's ablation): ms per view, ms per 1M contributing (Gaussian, pixel) pairs, and the
   volume-weighted segmentation / localisation mIoU;
2. a real scene (default ../shared/data/ply/flowers.ply, 542k Gaussians; or the random blob of
   --gaussians N, on every engine) seen by orbiting
   640x480 views with synthetic masks and 512-D embeddings: first the per-stage ms per view of
   the reference compositor next to the registration's top-k one (`stage_table`), then the
   whole registration: time per view split into rasterization and accumulation, ms per 1M
   pairs, peak RSS.

With --against MODE both tables also time MODE in the same run, the two modes alternating repeat
by repeat (A B, B A, ...), and give the median of the time ratios of the ABBA blocks (`ratios`): the
ratio the default's time bound is stated in (`--against paper`), measured in one run rather than
from two.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drsplat.commands.common import json_output_file, nonneg_int, positive_int, topk_int, unit_fraction
from drsplat.bench.common import format_table, gaussian_count, guard_bench_outputs, int_list, machine_line, peak_rss_mb, scene_file, view_size
from drsplat.device import add_device_arguments, resolve_compute
from drsplat.defaults import AGGREGATE_MODES, DEFAULT_AGGREGATE, DEFAULT_TOPK, MAX_TOPK, ORACLE_LABEL_NAMES, ORACLE_TEXT_EMBEDDINGS
from drsplat.errors import UsageError, shown_path

log = logging.getLogger(__name__)

STREAM_VIEWS = 8  # at least this many views timed back to back (the counted cameras repeated)
DEFAULT_REAL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "ply" / "flowers.ply"
REAL_MASKS = {"voronoi": "random-mask features (every mask its own label)", "regions": "scene-region mask features"}  # --real-masks
REAL_REGIONS = 64  # 3D regions of `region_mask_features`


def add_bench(subparsers: argparse._SubParsersAction) -> None:
    from drsplat.synthetic import MASK_SOURCES, PRESETS

    p = subparsers.add_parser("register", help="registration ms/view, ms per 1M pairs, RSS; mIoU against top-k")
    p.add_argument("--preset", default="small", choices=sorted(PRESETS), help="synthetic preset for the accuracy table (default: small)")
    p.add_argument("--topks", type=int_list(topk_int), default="1,5,10,20,40",
                   help=f"comma-separated top-k values, each 1..{MAX_TOPK} (default: 1,5,10,20,40)")
    p.add_argument("--mislabel", type=unit_fraction, default=0.0, help="fraction of mislabelled synthetic masks, 0..1 (default: 0)")
    p.add_argument("--repeats", type=positive_int, default=3, help="timed repeats per row, median reported (default: 3)")
    p.add_argument("--real", type=Path, default=None,
                   help="real scene for the speed table (default: ../shared/data/ply/flowers.ply, the table skipped when it is absent)")
    p.add_argument("--views", type=positive_int, default=50, help="orbiting views on the real scene (default: 50)")
    p.add_argument("--size", type=view_size, default="640x480", help="real-scene view size WxH (default: 640x480)")
    p.add_argument("--real-topk", type=topk_int, default=DEFAULT_TOPK, help=f"top-k on the real scene, 1..{MAX_TOPK} (default: {DEFAULT_TOPK})")
    p.add_argument("--real-masks", choices=sorted(REAL_MASKS), default="voronoi",
                   help="the real-scene table's masks: random Voronoi cells with a random embedding each, no two alike (voronoi: "
                        "the mask check's and the vote's costliest case), or the scene's 3D regions as each view sees them, a region's "
                        "masks alike from view to view as a segmenter's on a real capture (regions) (default: voronoi)")
    p.add_argument("--skip-synthetic", action="store_true", help="only the real-scene table")
    p.add_argument("--skip-real", action="store_true", help="only the synthetic table")
    p.add_argument("--skip-stages", action="store_true", help="no per-stage split (reference vs top-k compositor) on the real scene")
    p.add_argument("--gaussians", type=gaussian_count, default=None, metavar="N",
                   help="speed table on a random scene of N Gaussians built in memory (e.g. 500k, at most 100M) instead of --real")
    p.add_argument("--agree-views", type=nonneg_int, default=3,
                   help="views rasterized by both engines for the agreement columns (default: 3; 0: not compared)")
    p.add_argument("--count-views", type=positive_int, default=2,
                   help="views whose torch ops and host syncs are counted, after one warm-up view: at most --views minus 1 (default: 2)")
    p.add_argument("--profile-views", type=nonneg_int, default=0, metavar="N",
                   help="torch engine: N more views under torch's profiler, and a table of where their time went, by device "
                        "time on CUDA (default: 0, none)")
    p.add_argument("--trace", type=json_output_file, default=None, metavar="FILE",
                   help="with --profile-views: also write the profiled views' chrome trace to FILE (gzipped for a .gz name; "
                        "open it in Perfetto or chrome://tracing)")
    p.add_argument("--json", type=json_output_file, default=None, metavar="FILE",
                   help="also write the engine's per-view figures (ops_per_view, host_syncs_per_view, ms_per_view, device, engine) as JSON")
    p.add_argument("--aggregate", choices=AGGREGATE_MODES, default=DEFAULT_AGGREGATE,
                   help=f"aggregation mode of every timed registration (default: {DEFAULT_AGGREGATE}; 'paper' is Dr. Splat's)")
    p.add_argument("--against", choices=AGGREGATE_MODES, default=None, metavar="MODE",
                   help="also time MODE (e.g. paper) in the same run, the two modes alternating repeat by repeat (A B, B A, ...), "
                        "and print the time ratio --aggregate / MODE of each ABBA block of two repeats and their median (the "
                        "synthetic and real tables; give an even --repeats)")
    p.add_argument("--mask-source", choices=MASK_SOURCES, default=None,
                   help="the synthetic table's masks: the rendered footprints, the true silhouettes or a segmenter's regions "
                        "(`drsplat synth --mask-source`; default: the preset's)")
    add_device_arguments(p)
    p.set_defaults(func=run)


def _options(topk: int, engine: str, device: str, aggregate: str):
    from drsplat.registration import RegisterOptions

    return RegisterOptions(topk=topk, engine=engine, device=device, aggregate=aggregate)


def _warm_up(scene, cameras, features_dir, options) -> None:
    """One whole registration, not timed: numba compiles (or loads its cache) and the file caches fill. Of the first
    view alone it left the stages that need several views (the fit's probe views, the check's judging, the vote) to
    compile in the first timed repeat when numba's cache was empty: 30.3 s then 0.2 s, 954 ms a view printed for ~12,
    and a time ratio of 119x for ~1.5x with --against (round 101b F1)."""
    from drsplat.registration import register_features

    logger = logging.getLogger("drsplat.registration")
    level = logger.level
    logger.setLevel(logging.ERROR)  # its warnings are the timed runs' to give
    try:
        register_features(scene, cameras, features_dir, options, show_progress=False)
    finally:
        logger.setLevel(level)


def _one_run(scene, cameras, features_dir, options) -> tuple:
    """(result, wall seconds, CPU seconds of all threads) of one whole registration."""
    from drsplat.registration import register_features

    t0, c0 = time.perf_counter(), time.process_time()
    result = register_features(scene, cameras, features_dir, options, show_progress=False)
    return result, time.perf_counter() - t0, time.process_time() - c0


@dataclass
class Timed:
    """One mode's repeats: the last result, median wall and CPU seconds, and each run's timings
    (`runs`: results whose per-Gaussian arrays were let go, so that repeats do not hold an [N, D]
    field each: ten 1.1 GB fields of flowers, 11 GB, in the process whose runs are timed)."""

    result: object
    seconds: float
    cpu_seconds: float
    runs: list
    walls: list[float]

    @classmethod
    def of(cls, runs: list[tuple]) -> Timed:
        results, walls, cpus = (list(column) for column in zip(*runs))
        return cls(results[-1], statistics.median(walls), statistics.median(cpus), results, walls)


def _released(result):
    """`result` without its [N, D] features and [N] weights (the timings and counts stay)."""
    from dataclasses import replace

    return replace(result, features=None, weights=np.zeros(0, np.float32))


def _repeats(scene, cameras, features_dir, options_in_order) -> list[tuple]:
    """`_one_run` of each options in turn; a result loses its field when the next run of the same
    options starts, so each options' newest result keeps it."""
    runs, newest = [], {}
    for options in options_in_order:
        if id(options) in newest:
            i = newest[id(options)]
            result, wall, cpu = runs[i]
            runs[i] = (_released(result), wall, cpu)
        newest[id(options)] = len(runs)
        runs.append(_one_run(scene, cameras, features_dir, options))
    return runs


def timed_register(scene, cameras, features_dir, topk: int, repeats: int, engine: str = "numba", device: str = "cpu",
                   aggregate: str = DEFAULT_AGGREGATE) -> Timed:
    """One mode's registration, warmed up, then timed `repeats` times."""
    options = _options(topk, engine, device, aggregate)
    _warm_up(scene, cameras, features_dir, options)
    return Timed.of(_repeats(scene, cameras, features_dir, [options] * max(1, repeats)))


def timed_pair(scene, cameras, features_dir, topk: int, repeats: int, modes: tuple[str, str]) -> tuple[Timed, Timed]:
    """Both modes timed in one run, alternating: repeat r runs modes[0] then modes[1] when r is even,
    the other way round when odd (A B, B A, A B, ...), so that a drift of the machine and whatever
    the first run of a pair pays for the other's leftovers fall on both alike (`ratios`)."""
    options = [_options(topk, "numba", "cpu", mode) for mode in modes]
    for o in options:
        _warm_up(scene, cameras, features_dir, o)
    order = [m for r in range(max(1, repeats)) for m in ((0, 1) if r % 2 == 0 else (1, 0))]
    runs = _repeats(scene, cameras, features_dir, [options[m] for m in order])
    mine = ([run for run, m in zip(runs, order) if m == 0], [run for run, m in zip(runs, order) if m == 1])
    return Timed.of(mine[0]), Timed.of(mine[1])


def ratios(first: Timed, second: Timed) -> list[float]:
    """first's time over second's per ABBA block: repeats 2i (first ran first) and 2i + 1 (second ran
    first) summed, (a_2i + a_2i+1) / (b_2i + b_2i+1), so that running first or second in a pair
    cancels out (on hard-room, ~0.6 s a run, it moved single repeats' ratios by 10 %); a last odd
    repeat is left out. One repeat: its own ratio."""
    a, b = first.walls, second.walls
    if len(a) < 2:
        return [a[0] / b[0]]
    return [(a[i] + a[i + 1]) / (b[i] + b[i + 1]) for i in range(0, len(a) - 1, 2)]


def ratio_line(mode: str, against: str, values: list[float]) -> str:
    """'time per view, --aggregate MODE / AGAINST: 1.47x (median of the n ABBA blocks' ratios: 1.45, 1.47, 1.52)'."""
    listed = ", ".join(f"{v:.2f}" for v in values)
    return (f"time per view, --aggregate {mode} / {against}: {statistics.median(values):.2f}x (median of the {len(values)} ABBA blocks' "
            f"ratios, each of two repeats with the modes' order swapped: {listed})")


def synthetic_table(preset: str, topks: list[int], mislabel: float, repeats: int, aggregate: str = DEFAULT_AGGREGATE,
                    against: str | None = None, mask_source: str | None = None) -> str:
    """The preset's room (seed 0) registered at each top-k: speed next to mIoU. With `against`, that
    mode is timed in the same run, alternating (`timed_pair`), in five more columns: its ms per view, the
    median of the ABBA blocks' time ratios (`ratios`), and its assigned Gaussians, seg and loc mIoU."""
    from drsplat.cameras import load_cameras
    from drsplat.eval.metrics import significance_weights
    from drsplat.scene import load_ply
    from drsplat.synthetic import write_dataset

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        data = write_dataset(Path(tmp) / preset, preset, 0, mislabel_fraction=mislabel, mask_source=mask_source, show_progress=False)
        scene = load_ply(data / "scene.ply")
        cameras = load_cameras(data)
        gt = np.load(data / "gt" / "labels.npy")
        names = json.loads((data / ORACLE_LABEL_NAMES).read_text())
        text = np.load(data / ORACLE_TEXT_EMBEDDINGS)
        d, _ = significance_weights(scene.log_scales, scene.opacity_logits)
        for k in topks:
            if against is None:
                timed, other = timed_register(scene, cameras, data / "features", k, repeats, aggregate=aggregate), None
            else:
                timed, other = timed_pair(scene, cameras, data / "features", k, repeats, (aggregate, against))
            result, seconds, runs = timed.result, timed.seconds, timed.runs
            acc_s = statistics.median(r.accumulate_seconds for r in runs)
            seg, loc = accuracy(result.features @ text.T, gt, d, names)
            row = [
                k, 1e3 * seconds / result.num_views, result.num_pairs / 1e6, 1e3 * seconds / (result.num_pairs / 1e6),
                1e3 * acc_s / (result.num_pairs / 1e6), result.num_assigned, float(np.nanmean(seg.iou)), float(np.nanmean(loc.iou)), loc.threshold,
            ]
            if other is not None:  # the other mode's accuracy beside its time (round 78d F3: its time alone was shown)
                other_seg, other_loc = accuracy(other.result.features @ text.T, gt, d, names)
                row += [1e3 * other.seconds / other.result.num_views, statistics.median(ratios(timed, other)), other.result.num_assigned,
                        float(np.nanmean(other_seg.iou)), float(np.nanmean(other_loc.iou))]
            rows.append(row)
    source = "" if mask_source is None else f", {mask_source} masks"
    head = (f"synthetic '{preset}': {scene.num_gaussians:,} Gaussians, {len(cameras)} views "
            f"{cameras[0].width}x{cameras[0].height}, {text.shape[1]}-D{source}, mislabelled masks {mislabel:.0%}; --aggregate {aggregate}; "
            f"median of {repeats}")
    columns = ["top-k", "ms/view", "M pairs", "ms/1M pairs (total)", "ms/1M pairs (accumulate)", "assigned", "seg mIoU", "loc mIoU", "loc τ"]
    if against is not None:
        head += f"; --against {against}, alternating"
        columns += [f"ms/view ({against})", "time ratio (median)", f"assigned ({against})", f"seg mIoU ({against})", f"loc mIoU ({against})"]
    return head + "\n" + format_table(columns, rows)


def accuracy(scores: np.ndarray, gt: np.ndarray, significance: np.ndarray, names: list[str]):
    """(segmentation report, localisation report) of a registered field's scores [N, labels] against the labels gt [N]."""
    from drsplat.eval.metrics import localisation_report, segmentation_report

    return segmentation_report(scores, gt, significance, names), localisation_report(scores, gt, significance, names)


def orbit_cameras(means: np.ndarray, count: int, width: int, height: int):
    """`count` cameras on a circle around the scene's robust centre, in the plane of its two
    main axes, looking at the centre (the third axis is 'up')."""
    from drsplat.synthetic import look_at

    lo, hi = np.percentile(means, [5, 95], axis=0)
    inner = means[np.all((means >= lo) & (means <= hi), axis=1)]
    if len(inner) < 3:  # a scene of a few Gaussians: the 5-95 % box of each axis may hold none of them
        inner = means
    centre = np.median(inner, axis=0)
    sample = inner[:: max(1, len(inner) // 20000)] - centre
    # full_matrices only under three points, for three axes (any completion of the ones they span):
    # on 20,000 points it would also build a 20000 x 20000 U, 3.2 GB the bench's peak RSS counted
    _, _, vt = np.linalg.svd(sample, full_matrices=len(sample) < 3)
    a, b, up = vt[0], vt[1], vt[2]
    radius = 0.6 * np.linalg.norm(hi - lo)
    if not radius > 0:  # every Gaussian at one point: no extent to scale the orbit by
        radius = 1.0
    cams = []
    for i in range(count):
        ang = 2 * np.pi * i / count
        eye = centre + radius * (np.cos(ang) * a + np.sin(ang) * b) + 0.35 * radius * up
        cam = look_at(eye, centre, width, height, fov_x_deg=60.0, name=f"view_{i:03d}")
        cams.append(_with_up(cam, eye, centre, up))
    return cams


def _with_up(cam, eye, target, up):
    """look_at assumes z up; rebuild the rotation with the scene's own up axis."""
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    r = np.stack([right, down, forward])
    cam.R, cam.t = r, -r @ eye
    return cam


def random_mask_features(features_dir: Path, cameras, rng: np.random.Generator, dim: int = 512) -> None:
    """Voronoi-like random masks (30-80 per view, some pixels unmasked) and random unit embeddings."""
    from drsplat.features.format import write_features

    for cam in cameras:
        count = int(rng.integers(30, 81))
        seeds = rng.uniform([0, 0], [cam.width, cam.height], (count, 2))
        ys, xs = np.mgrid[0 : cam.height : 4, 0 : cam.width : 4]
        d2 = (xs[..., None] - seeds[:, 0]) ** 2 + (ys[..., None] - seeds[:, 1]) ** 2
        low = np.argmin(d2, axis=-1).astype(np.int32)
        low[rng.random(low.shape) < 0.1] = -1
        ids = np.repeat(np.repeat(low, 4, 0), 4, 1)[: cam.height, : cam.width]
        feats = rng.normal(size=(count, dim)).astype(np.float32)
        feats /= np.linalg.norm(feats, axis=1, keepdims=True)
        write_features(features_dir, cam.name, ids, feats)


def region_mask_features(features_dir: Path, cameras, scene, rng: np.random.Generator, regions: int = REAL_REGIONS,
                         noise: float | None = None, dim: int = 512) -> None:
    """Masks that follow the scene, as a segmenter and CLIP give them on a real capture: the Gaussians
    cut into `regions` 3D regions (each the Gaussians nearest one of `regions` centres drawn among
    them), a view's pixel labelled by the region of its heaviest Gaussian (a top-1 render), one mask
    per region in view, embedded as the region's unit vector plus a random part of length `noise`
    (default: the length of `drsplat synth`'s mask noise, `OracleParams.noise`), normalised. So a
    region's masks agree from view to view, unlike
    `random_mask_features`, where every mask is a label of its own (the mask check's and the vote's
    most expensive case: as many clusters as masks)."""
    from scipy.spatial import cKDTree

    from drsplat.features.format import write_features
    from drsplat.raster import prepare_scene, rasterize_topk
    from drsplat.synthetic import OracleParams

    noise = OracleParams().noise if noise is None else noise
    means = np.asarray(scene.means, np.float64)
    finite = np.flatnonzero(np.isfinite(means).all(axis=1))
    centres = means[rng.choice(finite, size=min(regions, finite.size), replace=False)]
    region = np.full(len(means), -1, np.int64)
    region[finite] = cKDTree(centres).query(means[finite], workers=-1)[1]
    labels = rng.normal(size=(len(centres), dim))
    labels /= np.linalg.norm(labels, axis=1, keepdims=True)
    prepared = prepare_scene(scene, with_sh=False)
    for cam in cameras:
        top = rasterize_topk(prepared, cam, 1).ids[..., 0]
        seen = np.where(top >= 0, region[np.maximum(top, 0)], -1)
        present, ids = np.unique(seen, return_inverse=True)
        ids = ids.reshape(seen.shape).astype(np.int32) - int(present[0] < 0)  # -1 stays where no Gaussian is
        present = present[present >= 0]
        jitter = rng.normal(size=(len(present), dim))
        feats = labels[present] + noise * jitter / np.linalg.norm(jitter, axis=1, keepdims=True)
        feats /= np.linalg.norm(feats, axis=1, keepdims=True)
        write_features(features_dir, cam.name, ids, feats.astype(np.float32))


def write_real_masks(kind: str, features_dir: Path, cameras, scene) -> None:
    """The real-scene table's mask features (REAL_MASKS): "voronoi" (`random_mask_features`) or "regions" (`region_mask_features`)."""
    if kind == "regions":
        region_mask_features(features_dir, cameras, scene, np.random.default_rng(0))
    else:
        random_mask_features(features_dir, cameras, np.random.default_rng(0))


def real_table(scene, name: str, views: int, width: int, height: int, topk: int, repeats: int, aggregate: str = DEFAULT_AGGREGATE,
               against: str | None = None, masks: str = "voronoi") -> str:
    """The whole registration of `scene` (called `name`) seen by orbiting views: time per view by stage, ms per 1M pairs.
    With `against`, that mode is timed in the same run, alternating (`timed_pair`): its table, then the ratio line.
    masks: the views' mask features (`write_real_masks`)."""
    cameras = orbit_cameras(scene.means, views, width, height)
    with tempfile.TemporaryDirectory() as tmp:
        features_dir = Path(tmp)
        write_real_masks(masks, features_dir, cameras, scene)
        if against is None:
            timed, other = timed_register(scene, cameras, features_dir, topk, repeats, aggregate=aggregate), None
        else:
            timed, other = timed_pair(scene, cameras, features_dir, topk, repeats, (aggregate, against))
    text = _stage_rows(scene, name, width, height, topk, repeats, aggregate, timed, masks)
    if other is None:
        return text
    return "\n".join([text, "", _stage_rows(scene, name, width, height, topk, repeats, against, other, masks), "",
                      ratio_line(aggregate, against, ratios(timed, other))])


def _stage_rows(scene, name: str, width: int, height: int, topk: int, repeats: int, aggregate: str, timed: Timed, masks: str = "voronoi") -> str:
    """`real_table`'s table of one mode's timed registrations."""
    runs, result, seconds, cpu_seconds = timed.runs, timed.result, timed.seconds, timed.cpu_seconds
    raster_s = statistics.median(r.raster_seconds for r in runs)
    acc_s = statistics.median(r.accumulate_seconds for r in runs)
    acc_cpu = statistics.median(r.accumulate_cpu_seconds for r in runs)
    mpairs = result.num_pairs / 1e6
    views = result.num_views
    rows = [
        ["total (incl. feature I/O, normalise)", 1e3 * seconds, 1e3 * seconds / views, 1e3 * seconds / mpairs],
        ["  rasterize top-k", 1e3 * raster_s, 1e3 * raster_s / views, 1e3 * raster_s / mpairs],
        ["  coalesce, per-view hook and sums (wall)", 1e3 * acc_s, 1e3 * acc_s / views, 1e3 * acc_s / mpairs],
        ["  sums only, CPU time of all threads", 1e3 * acc_cpu, 1e3 * acc_cpu / views, 1e3 * acc_cpu / mpairs],
        ["total CPU time, all threads", 1e3 * cpu_seconds, 1e3 * cpu_seconds / views, 1e3 * cpu_seconds / mpairs],
    ]
    head = (f"{name}: {scene.num_gaussians:,} Gaussians, {views} orbiting views {width}x{height}, top-{topk}, "
            f"512-D {REAL_MASKS[masks]}; {mpairs:.1f} M contributing pairs, {result.num_distinct_pairs / 1e6:.2f} M distinct "
            f"(Gaussian, mask) pairs, {result.num_assigned:,} Gaussians assigned; --aggregate {aggregate}; median of {repeats}")
    return head + "\n" + format_table(["stage", "ms (wall)", "ms/view", "ms/1M pairs"], rows)


def _canonical_lists(ids: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's (id, weight) slots ordered by id: the same lists compare equal whatever their slot order."""
    order = np.argsort(np.where(ids < 0, np.iinfo(np.int32).max, ids), axis=-1, kind="stable")
    return np.take_along_axis(ids, order, -1), np.take_along_axis(weights, order, -1)


def stage_table(scene, scene_name: str, views: int, width: int, height: int, topk: int, dim: int = 512) -> str:
    """Per-stage ms per view of one registration view, the reference compositor next to the top-k one.

    Both paths run on every view, interleaved (reference first), so machine load hits both alike;
    medians over the views. reference: `render_projected` (getRect tiles, the colour/depth
    kernel, sorted slots), `normalize_rows_reference` and the scene's Σ and Σ⁻¹ in numpy
    (`covariances_reference`, `precisions_reference`); top-k: what registration runs (`render_topk`:
    the ids-and-weights kernel, unordered slots), `normalize_rows` and the Σ, Σ⁻¹ kernels. The exact
    tile sets (`bin_tiles(exact=True)`) are timed as a third binning. Stages shared by both
    (projection, depth sort, binning, coalescing, summing) are the same code: one median over
    both paths' samples. The
    last line counts the pixels whose top-k list (as a set of (id, weight)) differs between them.
    """
    import numba

    from drsplat import raster
    from drsplat.registration.coalesce import Coalescer
    from drsplat.registration.compute import prepare_geometry
    from drsplat.registration.sums import Accumulator, normalize_rows, normalize_rows_reference

    geometry = prepare_geometry(scene)
    cameras = orbit_cameras(scene.means, views, width, height)
    rng = np.random.default_rng(0)
    coalescer = Coalescer(geometry.num_gaussians)
    acc = Accumulator(geometry.num_gaussians, dim)
    times: dict[tuple[str, str], list[float]] = {}
    outs: dict[str, raster.RasterOutput | None] = {"reference": None, "top-k": None}
    # each path projects into its previous view's arrays, as registration's ViewComputer does: fresh
    # arrays every view cost ~4 ms more on flowers in page faults (10.8 against 14.8 ms, 2 threads)
    projections: dict[str, raster.Projected | None] = {"reference": None, "top-k": None}
    changed_pixels = changed_views = 0
    n_tiles_x, n_tiles_y = raster.tile_grid(width, height)
    chunks = raster.BIN_CHUNKS_PER_THREAD * numba.get_num_threads()

    cpu: dict[str, list[float]] = {"reference": [], "top-k": []}

    def timed(path_name: str, stage: str, fn):
        t0, c0 = time.perf_counter(), time.process_time()
        result = fn()
        times.setdefault((path_name, stage), []).append(time.perf_counter() - t0)
        if stage == "composite":
            cpu[path_name].append(time.process_time() - c0)
        return result

    entries = {"reference": [], "top-k": [], "exact": []}
    for i, cam in enumerate([cameras[0]] + cameras):  # the first view twice: compile / warm up, not counted
        masks = rng.integers(-1, 60, (height // 8 + 1, width // 8 + 1)).astype(np.int32).repeat(8, 0).repeat(8, 1)[:height, :width]
        feats = rng.normal(size=(60, dim)).astype(np.float32)
        for name in ("reference", "top-k"):
            projected = timed(name, "project", lambda: raster.project_gaussians(geometry, cam, out=projections[name]))
            projections[name] = projected
            order = timed(name, "depth sort", lambda: raster.depth_order(projected))
            offsets, tile_ids = timed(name, "bin (getRect tiles)", lambda: kernels_bin(projected, order, n_tiles_x, n_tiles_y, chunks))
            if name == "reference":
                out = timed(name, "composite", lambda: raster.composite_projected(projected, offsets, tile_ids, topk, out=outs[name]))
            else:
                out = timed(name, "composite", lambda: raster.composite_topk(projected, offsets, tile_ids, topk, ranked=False, out=outs[name]))
                exact = timed(name, "bin (exact tiles, not used)", lambda: raster.bin_tiles(projected, exact=True))
                entries["exact"].append(exact[1].size)
            entries[name].append(tile_ids.size)
            outs[name] = out
            g, m, w, _ = timed(name, "coalesce", lambda: coalescer.coalesce(out.ids, out.weights, masks, feats.shape[0]))
            if name == "top-k":
                timed(name, "buffer pairs", lambda: acc.add_pairs(g, m, w, feats))
        if i == 0:
            times.clear()
            cpu["reference"].clear()
            cpu["top-k"].clear()
            continue
        ref, new = outs["reference"], outs["top-k"]
        a, b = _canonical_lists(ref.ids, ref.weights), _canonical_lists(new.ids, new.weights)
        differ = np.any((a[0] != b[0]) | (a[1] != b[1]), axis=-1)
        changed_pixels += int(differ.sum())
        changed_views += int(differ.any())
    scene.covariances(), scene.packed_precisions()  # compile / warm up, not counted
    ref_cov, ref_prec = timed("reference", "Σ and Σ⁻¹ from quaternions (per run / views)",
                              lambda: (scene.covariances_reference(), scene.precisions_reference()))
    cov, packed = timed("top-k", "Σ and Σ⁻¹ from quaternions (per run / views)", lambda: (scene.covariances(), scene.packed_precisions()))
    # registration's forms: Σ [N, 3, 3] for the renderer, Σ⁻¹ packed [N, 6] for the floater statistics
    frames_gap = max(_largest_relative_gap(cov, ref_cov), _largest_relative_gap(packed, ref_prec.reshape(-1, 9)[:, [0, 1, 2, 4, 5, 8]]))
    del ref_cov, ref_prec, cov, packed
    F, W = timed("top-k", "sum pairs (per run / views)", acc.sums)  # flushes every buffered pair, as registration does when its buffer fills
    F2, W2 = F.copy(), W.copy()
    normalize_rows(F2[:2].copy(), W2[:2].copy())  # compile / load the kernel, not counted
    timed("reference", "normalize (per run / views)", lambda: normalize_rows_reference(F2, W2))
    timed("top-k", "normalize (per run / views)", lambda: normalize_rows(F, W))
    n = len(cameras)
    stages = ["Σ and Σ⁻¹ from quaternions (per run / views)", "project", "depth sort", "bin (getRect tiles)", "composite", "coalesce",
              "buffer pairs", "sum pairs (per run / views)", "normalize (per run / views)"]
    rows, totals = [], {"reference": 0.0, "top-k": 0.0}
    shared = ("project", "depth sort", "bin (getRect tiles)", "coalesce", "buffer pairs", "sum pairs (per run / views)")
    for stage in stages:
        vals = {}
        for name in ("reference", "top-k"):
            if stage in shared:  # one code for both paths: one median over both paths' samples
                got = times.get(("reference", stage), []) + times.get(("top-k", stage), [])
            else:
                got = times[(name, stage)]
            vals[name] = 1e3 * (got[0] / n if "per run" in stage else statistics.median(got))
            totals[name] += vals[name]
        label = stage + (" (same code)" if stage in shared else "")
        rows.append([label, vals["reference"], vals["top-k"], vals["reference"] / vals["top-k"] if vals["top-k"] else float("nan")])
    rows.append(["total per view", totals["reference"], totals["top-k"], totals["reference"] / totals["top-k"]])
    exact_ms = 1e3 * statistics.median(times[("top-k", "bin (exact tiles, not used)")])
    ratios = [a / b for a, b in zip(times[("reference", "composite")], times[("top-k", "composite")])]
    head = (f"{scene_name}: per-stage ms per view (median of {n} views {width}x{height}, top-{topk}, {numba.get_num_threads()} threads), "
            f"reference compositor vs the registration's top-k compositor, interleaved per view")
    foot = (f"composite speed-up, median of the {n} per-view ratios (each pair run back to back): {statistics.median(ratios):.2f} "
            f"(range {min(ratios):.2f}-{max(ratios):.2f}); CPU seconds of all threads, median per view: "
            f"{1e3 * statistics.median(cpu['reference']):.0f} vs {1e3 * statistics.median(cpu['top-k']):.0f} ms "
            f"({statistics.median(cpu['reference']) / statistics.median(cpu['top-k']):.2f}x; less sensitive to other jobs than wall time)\n"
            f"tile-list entries per view: getRect {statistics.median(entries['top-k']) / 1e6:.2f} M, exact α ≥ 1/255 tiles "
            f"{statistics.median(entries['exact']) / 1e6:.2f} M (binning them: {exact_ms:.1f} ms/view, not used)\n"
            f"top-k lists that differ from the reference (as sets of (id, weight)): {changed_pixels} pixels in {changed_views} of {n} views "
            f"(both float64; a float32 compositor is not implemented)\n"
            f"Σ and Σ⁻¹: numpy (3x3 products through BLAS) vs the numba kernels, largest difference {frames_gap:.1e} of a matrix's "
            f"largest entry (the default mode makes both once per run, `paper` Σ only)")
    return head + "\n" + format_table(["stage", "reference ms/view", "top-k ms/view", "speed-up"], rows) + "\n" + foot


def _largest_relative_gap(got: np.ndarray, ref: np.ndarray) -> float:
    """max |got - ref| / max |ref| per row over the rows (matrices [N, 3, 3] or packed [N, 6]) both hold finite."""
    got, ref = got.reshape(len(got), -1), ref.reshape(len(ref), -1)
    ok = np.isfinite(got).all(axis=1) & np.isfinite(ref).all(axis=1)
    scale = np.maximum(np.abs(ref[ok]).max(axis=1), np.finfo(np.float64).tiny)
    return float((np.abs(got[ok] - ref[ok]).max(axis=1) / scale).max()) if ok.any() else 0.0


def kernels_bin(projected, order, n_tiles_x: int, n_tiles_y: int, chunks: int):
    """3DGS getRect binning of a depth order (the part of raster.bin_tiles after the sort)."""
    from drsplat import _raster_kernels

    return _raster_kernels.bin_gaussians(order, projected.tile_rects, n_tiles_x, n_tiles_x * n_tiles_y, chunks)


def blob_scene(n: int, seed: int = 0):
    """A random scene of n Gaussians in a unit-ish blob (sizes and opacities like a trained scene's), for timing."""
    from drsplat.testing import random_scene

    scene = random_scene(np.random.default_rng(seed), n, sh_degree=0, spread=1.0, log_scale=(-5.5, -3.0))
    scene.opacity_logits[:] = np.random.default_rng(seed + 1).normal(1.0, 2.0, n).astype(np.float32)
    return scene


def engine_table(scene, name: str, views: int, width: int, height: int, topk: int, repeats: int, engine: str, device: str, agree_views: int,
                 count_views: int = 2, aggregate: str = "paper", profile_views: int = 0, trace: Path | None = None) -> tuple[str, dict]:
    """The same registration with numba (CPU) and with `engine` on `device`: times as ratios, and agreement;
    then `engine`'s per-view ops and host syncs (`per_view_counts`). Returns (text, the counts record)."""
    from drsplat.raster import prepare_for_engine, rasterize
    from drsplat.testing import agreement

    cameras = orbit_cameras(scene.means, views, width, height)
    with tempfile.TemporaryDirectory() as tmp:
        features_dir = Path(tmp)
        random_mask_features(features_dir, cameras, np.random.default_rng(0))
        first = timed_register(scene, cameras, features_dir, topk, repeats, aggregate=aggregate)
        second = timed_register(scene, cameras, features_dir, topk, repeats, engine, device, aggregate=aggregate)
        base, base_s, base_runs = first.result, first.seconds, first.runs
        other, other_s, other_runs = second.result, second.seconds, second.runs
        per_view = base.aggregate  # a fit mode's views run the mode its fit stage resolved to
        counts = per_view_counts(scene, cameras[: count_views + 1], features_dir, topk, engine, device, per_view)
        profile = profile_table(scene, cameras[: profile_views + 1], features_dir, topk, device, per_view, trace=trace) if profile_views > 0 else ""
    wdiff, mismatch = 0.0, 0.0
    prep_n, prep_o = prepare_for_engine(scene, "numba"), prepare_for_engine(scene, engine, device)
    for cam in cameras[:agree_views]:
        a = rasterize(prep_n, cam, topk)
        b = rasterize(prep_o, cam, topk, engine=engine, device=device)
        w, m = agreement(b, a)
        wdiff, mismatch = max(wdiff, w), max(mismatch, m)
    feat_diff = float(np.abs(other.features - base.features).max()) if base.features.size else 0.0

    def stage(runs, attr):
        return statistics.median(getattr(r, attr) for r in runs)

    rows = []
    for label, runs, total in (("numba (cpu)", base_runs, base_s), (f"{engine} ({device})", other_runs, other_s)):
        raster, acc = stage(runs, "raster_seconds"), stage(runs, "accumulate_seconds")
        rows.append([label, 1e3 * total / views, 1e3 * raster / views, 1e3 * acc / views, base_s / total,
                     stage(base_runs, "raster_seconds") / raster if raster else float("nan")])
    agreed = min(agree_views, views)
    agreement = (f"Agreement on {agreed} views: max |Δw| {wdiff:.2e}, id mismatch {mismatch:.2e} of top-k slots" if agreed else
                 "Agreement of the rasterizers: not compared (--agree-views 0)")  # a 0 there would read as "they agree"
    head = (f"{name}: {scene.num_gaussians:,} Gaussians, {views} orbiting views {width}x{height}, top-{topk}, 512-D random masks, "
            f"--aggregate {aggregate}; "
            f"median of {repeats}. {agreement}; features max |Δ| {feat_diff:.2e}, assigned {base.num_assigned:,} vs {other.num_assigned:,}")
    table = format_table(["engine", "ms/view", "raster ms/view", "accumulate ms/view", "speed-up (total)", "speed-up (raster)"], rows)
    return head + "\n" + table + "\n\n" + counts_table(counts) + (f"\n\n{profile}" if profile else ""), counts


def per_view_counts(scene, cameras, features_dir: Path, topk: int, engine: str, device: str, aggregate: str = "paper") -> dict:
    """What computing and summing one view costs `engine` on `device` with the `aggregate` mode:
    drsplat.registration.compute.ViewComputer.compute (rasterize, the mode's per-view hook,
    coalesce), the fold of the mode's statistics and the sink's `add` (a `check-` mode's: the view's
    pairs copied to the host and recorded; its judging and sums after the views are the record's
    `blocks_ms`). Torch ops and host syncs per
    view (drsplat.bench.opcount), the median wall ms per view (timed without the counter) and peak
    device memory (CUDA); and the same views (repeated to `STREAM_VIEWS`) computed back to back,
    synchronised only before and after them (`streamed_ms_per_view`: a registration's rate).
    Each way first runs two views twice and its hand-over once, untimed: a check mode's judging compiles
    its numba kernels on its first call, which took 13 s of the hand-over on an H200's host
    (2026-11-29) and is not the hand-over's cost.

    For the torch engine both ways are measured, interleaved view
    by view: pairs coalesced and summed on the device (drsplat.registration.device_sums, what
    registration does in that mode: the record's top-level figures) and the lists copied to the host
    for the numba hook, coalescer and sums (`host_sums`). The first camera is a warm-up
    (compilation, caches) and is not counted.
    """
    ways = [True, False] if engine == "torch" else [False]
    for way in ways:  # the hand-over's first calls compile its numba kernels: done here, so that `blocks_ms` times the work
        warm = _ViewCounter(scene, features_dir, topk, engine, device, way, aggregate)
        # two views seen twice: their masks then group, so a check mode judges (compiling its kernels) as the
        # counted views, also seen twice, make it; two views seen once were skipped as ungroupable, and
        # 8.05 s of the H200's timed hand-over was the judging's compilation (2026-12-04)
        for cam in cameras[:2] * 2:
            warm.view(cam, counted=False)
        warm.record()
        del warm
    counters = [_ViewCounter(scene, features_dir, topk, engine, device, way, aggregate) for way in ways]
    for i, cam in enumerate(cameras):
        for counter in counters:
            counter.view(cam, counted=i > 0)
    loaded = _loaded_views(features_dir, cameras[1:])
    for counter in counters:
        counter.stream(loaded * -(-STREAM_VIEWS // max(len(loaded), 1)))
    record = counters[0].record()
    if len(counters) > 1:
        record["host_sums"] = counters[1].record()
    return record


@dataclass
class DeviceTimeline:
    """How busy the device was over a profiled stretch: span_ms from its first kernel's start to its
    last one's end, busy_ms covered by at least one kernel, copy or memset, gaps_ms the idle
    stretches longer than the threshold (in time order)."""

    span_ms: float
    busy_ms: float
    gaps_ms: list[float]

    def line(self, views: int, threshold_ms: float) -> str:
        idle = sum(self.gaps_ms)
        return (f"device timeline over {views} views back to back: busy {self.busy_ms:.1f} of {self.span_ms:.1f} ms "
                f"({self.busy_ms / max(views, 1):.2f} ms a view); {len(self.gaps_ms)} idle gaps over {threshold_ms:g} ms, "
                f"{idle:.1f} ms in all" + (f" (longest {max(self.gaps_ms):.2f} ms: the device waited for the host)" if self.gaps_ms else ""))


DEVICE_EVENT_KINDS = ("kernel", "gpu_memcpy", "gpu_memset")  # chrome-trace categories of work on the device


def device_timeline(trace: dict, threshold_ms: float = 0.3) -> DeviceTimeline | None:
    """The DeviceTimeline of a torch.profiler chrome trace (`export_chrome_trace`'s JSON), or None
    when it holds no device work (a CPU run). Overlapping kernels count once."""
    spans = sorted((float(e["ts"]), float(e["ts"]) + float(e.get("dur", 0.0))) for e in trace.get("traceEvents", [])
                   if e.get("ph") == "X" and e.get("cat") in DEVICE_EVENT_KINDS)
    if not spans:
        return None
    busy, gaps, end = 0.0, [], spans[0][0]
    for start, stop in spans:
        if start - end > 1e3 * threshold_ms:
            gaps.append((start - end) / 1e3)
        if stop > end:
            busy += stop - max(start, end)
            end = stop
    return DeviceTimeline((end - spans[0][0]) / 1e3, busy / 1e3, gaps)


def profile_table(scene, cameras, features_dir: Path, topk: int, device: str, aggregate: str = "paper", rows: int = 25,
                  trace: Path | None = None) -> str:
    """Where the torch engine's time goes on `device`: the views after the first (a warm-up) computed
    and summed back to back as registration does (pairs on the device, `_ViewCounter.stream`) under
    torch.profiler; its table of the `rows` costliest ops and kernels, by self device time on CUDA,
    by self CPU time on a CPU. On CUDA also the device's timeline (`device_timeline`): how long it
    sat idle waiting for the host. trace: where to write the chrome trace (gzipped when the name
    ends in .gz), for chrome://tracing or Perfetto."""
    import torch

    counter = _ViewCounter(scene, features_dir, topk, "torch", device, True, aggregate)
    counter.view(cameras[0], counted=False)
    loaded = _loaded_views(features_dir, cameras[1:])
    cuda = device.startswith("cuda")
    activities = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA] if cuda else [])
    with torch.profiler.profile(activities=activities) as prof:
        counter.stream(loaded)
    timeline = _write_trace(prof, trace) if cuda or trace is not None else None  # a CPU trace has no device timeline
    averages = prof.key_averages()
    key = "self_cpu_time_total"
    if cuda:  # the name of the device column changed between torch versions
        key = "self_device_time_total" if hasattr(averages[0], "self_device_time_total") else "self_cuda_time_total"
    table = (f"where {len(cameras) - 1} views' time went (torch.profiler, --aggregate {aggregate}, sorted by {key}):\n"
             + averages.table(sort_by=key, row_limit=rows, max_name_column_width=70))
    return table + (f"\n{timeline.line(len(loaded), TIMELINE_GAP_MS)}" if timeline is not None else "")


TIMELINE_GAP_MS = 0.3  # idle stretches of the device longer than this are counted as gaps


def _write_trace(prof, trace: Path | None) -> DeviceTimeline | None:
    """The profile's DeviceTimeline (read from its chrome trace), the trace kept at `trace` if given
    (written atomically; gzipped for a .gz name)."""
    import gzip

    from drsplat.utils import atomic_path

    with tempfile.TemporaryDirectory() as tmp:
        raw = Path(tmp) / "trace.json"
        prof.export_chrome_trace(str(raw))
        text = raw.read_bytes()
    if trace is not None:
        with atomic_path(trace) as out:
            out.write_bytes(gzip.compress(text) if trace.name.endswith(".gz") else text)
    return device_timeline(json.loads(text), TIMELINE_GAP_MS)


def _loaded_views(features_dir: Path, cameras) -> list[tuple]:
    """[(camera, mask ids [H, W], embeddings [M, D])] of `cameras`, read once before views are timed back to back."""
    from drsplat.registration.views import load_view_features

    return [(cam, *load_view_features(features_dir, cam, 0)[:2]) for cam in cameras]


class _ViewCounter:
    """One way of computing and summing views (`per_view_counts`), with its per-view figures."""

    def __init__(self, scene, features_dir: Path, topk: int, engine: str, device: str, on_device: bool, aggregate: str = "paper"):
        from drsplat.registration.aggregate import Aggregator
        from drsplat.registration.compute import ViewComputer, ViewJob, pairs_by_gaussian, prepare_geometry

        self.scene, self.features_dir, self.engine, self.device, self.on_device = scene, features_dir, engine, device, on_device
        self.aggregator = Aggregator(aggregate, scene)
        job = ViewJob(features_dir, 0, topk, engine, device, self.aggregator.hook, device_pairs=on_device, by_gaussian=pairs_by_gaussian(aggregate))
        self.computer = ViewComputer(prepare_geometry(scene), job)
        self.sink = None
        self._pending = None  # the view computed last, handed to the sink once the next one is computed (as the driver does)
        self.ops, self.views_only, self.syncs, self.ms, self.sync_names, self.peak_mb = [], [], [], [], None, None
        self.after_raster_ms = []  # coalescing and summing (on CUDA: from the render's issue to the sums' end)
        self.streamed_ms = None  # ms per view computed back to back (`stream`)

    def view(self, cam, counted: bool) -> None:
        import torch

        from drsplat.bench.opcount import OpCounter
        from drsplat.registration.driver import one_block_sink
        from drsplat.registration.views import load_view_features

        mask_ids, feats, *_ = load_view_features(self.features_dir, cam, 0)
        if self.sink is None:
            n, dim, vote = self.scene.num_gaussians, feats.shape[1], self.aggregator.vote
            # a check mode: the views recorded in memory, judged and summed after them (the driver logs them instead: a log's
            # writes are left out of this count in every mode)
            if self.aggregator.check:
                from drsplat.registration.check import CheckSink

                self.sink = CheckSink(n, dim, vote, inner=one_block_sink(n, dim, vote, self.device if self.on_device else None))
            else:
                self.sink = one_block_sink(n, dim, vote, self.device if self.on_device else None)
        cuda = self.device.startswith("cuda")
        if cuda:
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        t0 = time.perf_counter()
        self._step(cam, mask_ids, feats)
        if not counted:  # a warm-up: its sizes read now, so that the counted views size their tile lists from it
            self._flush()
        if cuda:
            torch.cuda.synchronize()
            self.peak_mb = max(self.peak_mb or 0.0, torch.cuda.max_memory_allocated() / 2**20)
        if not counted:
            return
        self.ms.append(1e3 * (time.perf_counter() - t0))
        self.after_raster_ms.append(self.ms[-1] - 1e3 * self._raster_seconds)
        with OpCounter() as counter:
            self._step(cam, mask_ids, feats)
        self.ops.append(counter.counts.ops)
        self.views_only.append(counter.counts.views)
        self.syncs.append(counter.counts.syncs)
        self.sync_names = counter.counts.syncs_by_name

    def stream(self, views: list) -> None:
        """`views` [(camera, mask ids, embeddings)] computed and summed back to back as the driver
        does (each view added once the next is computed), the device synchronised only before and
        after them: the rate of a registration's views, where `view` times one view alone (on CUDA
        the host then waits for each view's last kernel, and the device for the host's first launches)."""
        import torch

        if not views:
            return
        cuda = self.device.startswith("cuda")
        if cuda:
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        for cam, mask_ids, feats in views:
            self._step(cam, mask_ids, feats)
        self._flush()
        if cuda:
            torch.cuda.synchronize()
        self.streamed_ms = 1e3 * (time.perf_counter() - t0) / len(views)

    def _step(self, cam, mask_ids, feats) -> None:
        """One view's work in the driver's order (drsplat.registration.executor.one_view_behind):
        compute this view, then read the sizes of the one before and sum it."""
        view = self.computer.compute(cam, mask_ids, feats)
        self._raster_seconds = view.raster_seconds
        self._flush()
        self._pending = view

    def _flush(self) -> None:
        if self._pending is not None:
            self._add(self._pending.resolved())
            self._pending = None

    def _add(self, view) -> None:
        """The driver's part of a view: its pairs copied to a host sink, the mode's statistics folded,
        the pairs summed (or recorded, in a `check-` mode)."""
        if self.sink.place == "host":
            view = view.on_host()
        self.aggregator.add(view.stats)
        self.sink.add(view)

    def record(self) -> dict:
        """The per-view medians, and the sums' hand-over after the views (`blocks`: the device sink's
        copy to the host, the host sink's last flush of its buffered pairs into F)."""
        from drsplat.registration.sink import sums_place

        views = len(self.ms)
        self._flush()
        t0 = time.perf_counter()
        for _ in self.sink.blocks() if self.sink is not None else ():
            pass
        blocks_ms = 1e3 * (time.perf_counter() - t0)

        def median(values):
            return statistics.median(values) if views else None

        return {
            "engine": self.engine, "device": self.device, "aggregate": self.aggregator.mode, "views": views,
            "pairs": self.device if self.on_device else "host",
            "sums": sums_place(self.sink) if self.sink is not None else "host",
            "ops_per_view": median(self.ops), "view_ops_per_view": median(self.views_only), "host_syncs_per_view": median(self.syncs),
            "ms_per_view": median(self.ms), "streamed_ms_per_view": self.streamed_ms, "coalesce_sum_ms_per_view": median(self.after_raster_ms),
            "blocks_ms": blocks_ms,
            "peak_device_mb": self.peak_mb,
            "host_syncs_by_op": dict(self.sync_names.most_common()) if self.sync_names else {},
        }


def counts_table(counts: dict) -> str:
    """The per-view records of `per_view_counts` as a table (device sums, then host sums when measured)."""
    records = [counts] + ([counts["host_sums"]] if "host_sums" in counts else [])
    syncs = "; ".join(f"pairs on {r['pairs']}, sums on {r['sums']}: " + (", ".join(f"{k} x{v}" for k, v in r["host_syncs_by_op"].items()) or "none") for r in records)
    head = (f"per-view work of {counts['engine']} ({counts['device']}), --aggregate {counts['aggregate']}, compute + statistics + sink add, "
            f"median of {counts['views']} "
            f"views after a warm-up, each alone (synchronised before and after it; back to back: {STREAM_VIEWS} or more views in a row, "
            f"synchronised at the ends) (ops: dispatcher calls, a drsplat:: op counted with the torch ops its kernel issues; host syncs: {syncs})")
    rows = [[r["engine"], r["device"], r["pairs"], r["sums"], r["ops_per_view"], r["view_ops_per_view"], r["host_syncs_per_view"], r["ms_per_view"],
             r["streamed_ms_per_view"], r["coalesce_sum_ms_per_view"], r["blocks_ms"],
             "n/a (cpu)" if r["peak_device_mb"] is None else r["peak_device_mb"]] for r in records]
    return head + "\n" + format_table(["engine", "device", "pairs on", "sums on", "ops/view", "of them views (no launch)", "host syncs/view", "ms/view",
                                       "back to back ms/view", "coalesce + sum ms/view", "sums to host ms (once)", "peak device MB"], rows)


def write_json(path: Path, record: dict) -> None:
    """`record` as JSON at `path`, written atomically."""
    from drsplat.utils import atomic_path, json_text

    with atomic_path(path) as tmp:
        tmp.write_text(json_text(record) + "\n")


def _check_outputs(args: argparse.Namespace, engine: str) -> None:
    """--json, --trace and --profile-views record the torch engine's views: refused up front (before any table) where none are measured."""
    if args.json is not None and (engine == "numba" or args.skip_real):
        raise UsageError("--json records the torch engine's per-view figures: add --engine torch (and leave out --skip-real)")
    if args.trace is not None and (engine == "numba" or args.skip_real or args.profile_views == 0):
        raise UsageError("--trace keeps the trace of the torch engine's profiled views: add --engine torch and --profile-views N")
    if args.profile_views and (engine == "numba" or args.skip_real):
        raise UsageError("--profile-views profiles the torch engine's views: add --engine torch (and leave out --skip-real)")
    if args.against is not None and engine != "numba":
        raise UsageError(f"--against times two aggregation modes on the numba engine; --engine {engine} compares engines instead: leave one out")
    if args.against is not None and args.against == args.aggregate:
        raise UsageError(f"--against {args.against} names the mode --aggregate times already: give another mode (e.g. --against paper)")
    if args.mask_source is not None and args.skip_synthetic:
        raise UsageError("--mask-source sets the synthetic table's masks, which --skip-synthetic leaves out: leave one out")


def _views_after_warmup(args: argparse.Namespace, engine: str) -> tuple[int, int]:
    """(--count-views, --profile-views) as the torch engine's table can honour them: both take the
    views after one warm-up view, so at most --views - 1 (fewer are used, with a warning)."""
    if engine == "numba" or args.skip_real:
        return args.count_views, args.profile_views
    after = args.views - 1
    if after < 1:
        raise UsageError(f"--views {args.views}: the torch engine's per-view counts take the views after one warm-up view; give --views 2 or more")
    kept = []
    for flag, wanted in (("--count-views", args.count_views), ("--profile-views", args.profile_views)):
        if wanted > after:
            log.warning("%s %d: only %d of the %d --views come after the warm-up view; using %d", flag, wanted, after, args.views, after)
        kept.append(min(wanted, after))
    return kept[0], kept[1]


def _real_scene(args: argparse.Namespace) -> Path:
    """The real scene: --real, refused before any table when it is not a file (exit 1), or the default
    flowers.ply, whose table is skipped with a line when it is absent (a machine without the data)."""
    if args.real is None:
        return DEFAULT_REAL
    return scene_file(args.real, "--real")


def _speed_scene(args: argparse.Namespace):
    """(scene, name) of the speed tables: the blob of --gaussians, else the real scene; (None, why) when
    the default real scene is absent. Read before any table, so that an empty scene is found at once."""
    if args.gaussians:
        return blob_scene(args.gaussians), f"random blob scene {args.gaussians}"
    if args.real == DEFAULT_REAL and not DEFAULT_REAL.is_file():
        return None, f"{shown_path(args.real)} is absent"
    from drsplat.scene import load_ply

    return load_ply(args.real, purpose="benchmark"), shown_path(args.real.name)


def run(args: argparse.Namespace) -> int:
    topks = args.topks
    width, height = args.size
    device, engine = resolve_compute(args)
    _check_outputs(args, engine)
    args.real = _real_scene(args) if not args.skip_real and not args.gaussians else (args.real or DEFAULT_REAL)
    count_views, profile_views = _views_after_warmup(args, engine)
    # the default scene too: it is resolved here, after the command line's own guard
    real_flag = "--real" if args.real != DEFAULT_REAL else "--real (its default)"
    guard_bench_outputs({real_flag: args.real}, {"--json": args.json, "--trace": args.trace})
    scene, name = _speed_scene(args) if not args.skip_real else (None, "")
    if not args.skip_synthetic:
        print(synthetic_table(args.preset, topks, args.mislabel, args.repeats, args.aggregate, args.against, args.mask_source))
        print()
    if engine != "numba" and not args.skip_real:
        if scene is None:
            print(f"skipped the engine table: {name} (pass --real SCENE.ply or --gaussians N)")
        else:
            text, counts = engine_table(scene, name, args.views, width, height, args.real_topk, args.repeats, engine, device,
                                        args.agree_views, count_views, args.aggregate, profile_views, args.trace)
            print(text)
            if args.json is not None:
                write_json(args.json, {**counts, "scene": name, "gaussians": scene.num_gaussians, "size": f"{width}x{height}", "topk": args.real_topk})
                print(f"wrote {shown_path(args.json)}")
    elif not args.skip_real:
        if scene is None:
            print(f"skipped the real-scene table: {name} (pass --real SCENE.ply or --gaussians N)")
        else:
            if not args.skip_stages:
                print(stage_table(scene, name, args.views, width, height, args.real_topk))
                print()
            print(real_table(scene, name, args.views, width, height, args.real_topk, args.repeats, args.aggregate, args.against, args.real_masks))
    print(f"peak RSS {peak_rss_mb():.0f} MB")
    print(machine_line())
    return 0
