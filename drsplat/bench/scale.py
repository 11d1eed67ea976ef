"""`drsplat bench scale`: registration of a synthetic city, local vs streamed vs Ray, and a projection.

The city (drsplat.synthetic.tile_city) is copies of the `small` room on a grid, built in memory
in each run (not written: 5M Gaussians), with low-resolution views whose feature files link to
the room's oracle features. Every configuration runs in its own process so that peak RSS is
that run's: `memory.peak_rss` (VmHWM) of the driver and, for Ray, of each worker process (reported by its
tasks). Agreement: the SHA-256 of the registered PLY against the local in-memory run's.

Parts: `replay` (block replays of a pair log: chunked reads vs whole records), `compare` (a small city: local in memory with and without frustum culling, local
streamed, Ray on local clusters of 1 and 2 one-CPU nodes, the 2-node one also with an empty kernel cache; `--json FILE` writes its records), `rss` (peak RSS vs N, streamed under the budget, in memory where it fits)
and `big` (the done-means run: >= 5M Gaussians, >= 500 views streamed under --budget). The
projection for 8/64 GPU nodes multiplies per-task costs measured here by task counts; it is a
model, not a measurement.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from drsplat.bench.common import child_env, format_table, guard_bench_outputs, last_error_line, machine_line, positive_int_list
from drsplat.commands.common import MAX_IMAGE_WIDTH, int_range, json_output_file, nonneg_float, positive_float, positive_int, size_value
from drsplat.errors import DrsplatError, InputError, UsageError
from drsplat.memory import parse_size, peak_rss

log = logging.getLogger(__name__)

ROOM_PRESET = "small"
ROOM_FILES = ("scene.ply", "transforms.json")  # what the runs read of --room besides its features folder


def budget_text(text: str) -> str:
    """argparse type of --budget: a size ('8GB'), checked now and kept as written (it is printed and passed to the child runs)."""
    size_value(text)
    return text.strip()


budget_text.__name__ = "size"


class ChildRunFailed(DrsplatError):
    """A configuration's own process failed; the message is its last error line."""


def add_bench(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("scale", help="city-scale registration: local vs streamed vs Ray, peak RSS, projection to GPU nodes")
    p.add_argument("--part", choices=("all", "compare", "rss", "big", "replay"), default="all")
    p.add_argument("--room", type=Path, default=None, help="a written `small` synthetic dataset (default: written to a temp folder)")
    p.add_argument("--width", type=int_range(1, MAX_IMAGE_WIDTH), default=64, help="view width in pixels (height follows the room's 4:3)")
    p.add_argument("--compare-tiles", type=positive_int, default=16, help="rooms in the comparison city (~18.4k Gaussians each)")
    p.add_argument("--compare-views", type=positive_int, default=96)
    p.add_argument("--workers", type=positive_int_list, default="1,2", help="Ray worker counts to compare")
    p.add_argument("--rss-tiles", type=positive_int_list, default="55,272", help="cities for peak RSS vs N (55 ~ 1M, 272 ~ 5M, 1087 ~ 20M Gaussians)")
    p.add_argument("--rss-views", type=positive_int, default=20)
    p.add_argument("--big-tiles", type=positive_int, default=272, help="the done-means city: 272 rooms = 5.0M Gaussians")
    p.add_argument("--big-views", type=positive_int, default=544)
    p.add_argument("--budget", type=budget_text, default="8GB", help="memory budget of the streamed runs")
    p.add_argument("--model-images", type=positive_int, default=10_000)
    p.add_argument("--model-gaussians", type=positive_float, default=50e6)
    p.add_argument("--model-pixels", type=positive_float, default=1.0e6, help="pixels per image of the projected city")
    p.add_argument("--pixel-cost-us", type=nonneg_float, default=0.68, help="rasterizer cost per pixel per view (flowers, docs/raster.md)")
    p.add_argument("--pairs-per-mp", type=positive_float, default=1.0e6, help="distinct pairs per megapixel of a view (flowers: 306k at 640x480)")
    p.add_argument("--gpu-speedup", type=positive_float, default=40.0,
                   help="assumed speed-up of one GPU node over this machine's per-view rasterization (an assumption, stated in the table)")
    p.add_argument("--replay-gaussians", type=positive_int, default=2_000_000, help="replay part: Gaussians of the synthetic pair log")
    p.add_argument("--replay-views", type=positive_int, default=60)
    p.add_argument("--replay-pairs", type=positive_int, default=300_000, help="replay part: distinct pairs per view")
    p.add_argument("--replay-blocks", type=positive_int, default=4)
    p.add_argument("--nodes", type=positive_int_list, default="1,8,64", help="GPU node counts of the projection")
    p.add_argument("--reducers-per-node", type=positive_int, default=1, help="reducer tasks per node in the projection (each holds one block)")
    p.add_argument("--json", type=json_output_file, default=None, help="also write the compare runs as JSON records to this file (--part compare or all)")
    p.set_defaults(func=run)


# ----------------------------------------------------------------------------- one configuration (child process)


def _city(config: dict):
    from drsplat.cameras import load_cameras
    from drsplat.scene import load_ply
    from drsplat.synthetic import tile_city

    room = Path(config["room"])
    scene, cameras = load_ply(room / "scene.ply"), load_cameras(room, require_images=False)
    return tile_city(scene, cameras, config["tiles"], config["views"], config["width"])


def link_features(room: Path, folder: Path, cameras, sources) -> None:
    """Feature files of the city's views: symbolic links to the room's (no copy)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "manifest.json").write_bytes((room / "features" / "manifest.json").read_bytes())
    for cam, src in zip(cameras, sources):
        for suffix in ("_s.npy", "_f.npy"):
            link = folder / f"{cam.name}{suffix}"
            if not link.exists():
                link.symlink_to((room / "features" / f"{src}{suffix}").resolve())


def run_config(config: dict) -> dict:
    """One registration as `config` says; returns its figures (run inside a fresh process).

    config["nodes"] > 0 runs the views on a Ray cluster of that many nodes of one CPU each, started
    here on this machine (ray.cluster_utils) and stopped after the run: the first views are the
    first after the cluster started.
    """
    from drsplat.registration import RegisterOptions, register

    t0 = time.perf_counter()
    scene, cameras, _ = _city(config)
    build_s = time.perf_counter() - t0
    out = Path(config["out"])
    cull = config.get("cull", True)
    with _ray_cluster(config.get("nodes", 0)) as address:
        options = RegisterOptions(keep_unassigned=True, memory_budget=parse_size(config["budget"]) if config.get("budget") else None,
                                  block_size=config.get("block"), ray=address, ray_workers=config.get("workers"), cull=cull,
                                  reducers=config.get("reducers", True))
        views_done: list[float] = []  # (wall, driver CPU) when the last view was summed: the view pass apart from finishing
        first_done: list[float] = []  # driver CPU when the first view was summed: the run's fixed costs before any pair

        def on_progress(done: int, total: int) -> None:
            if done >= 1 and not first_done:
                first_done.append(_cpu_seconds() - cpu0)
            if done == total and not views_done:
                views_done.extend([time.perf_counter() - t0, _cpu_seconds() - cpu0])

        t0, cpu0 = time.perf_counter(), _cpu_seconds()
        reg = register(scene, cameras, config["features"], out, options, show_progress=False, on_progress=on_progress)
        wall, driver_cpu = time.perf_counter() - t0, _cpu_seconds() - cpu0
    digest = hashlib.sha256()
    with open(out, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 24), b""):
            digest.update(chunk)
    size = out.stat().st_size
    out.unlink()
    workers = sorted(reg.worker_peak_rss.values())
    later = [s for w in reg.workers for s in w.later_view_seconds]
    return {
        "gaussians": scene.num_gaussians, "views": reg.num_views, "wall": wall, "build": build_s, "raster": reg.raster_seconds,
        "coalesce": reg.coalesce_seconds, "accumulate": reg.accumulate_seconds,
        "pairs": reg.num_pairs, "distinct": reg.num_distinct_pairs, "streamed": reg.num_blocks > 1, "peak_rss": peak_rss(),
        "worker_rss": workers, "sha": digest.hexdigest(), "ply_bytes": size, "driver_cpu": driver_cpu, "cull": cull,
        "projected_per_view": _projected_per_view(scene, cameras, options.topk) if cull else float(scene.num_gaussians),
        "reduce": {"reducers": reg.reducers, "tail_wall_s": round(reg.seconds - reg.view_seconds, 3), "tail_driver_cpu_s": round(reg.finish_cpu_seconds, 3)},
        # a local run has no workers: no first view of one (None, shown as '-')
        "first_view": max((w.first_view_seconds for w in reg.workers if w.first_view_seconds is not None), default=None),
        "later_view": statistics.median(later) if later else None,
        "kernels_compiled": sum(w.kernels_compiled for w in reg.workers), "kernels_cached": sum(w.kernels_cached for w in reg.workers),
        "views_wall": views_done[0], "views_driver_cpu": views_done[1], "first_view_driver_cpu": first_done[0] if first_done else 0.0,
        "reducer_seconds": reg.reducer_seconds, "reducer_sum_seconds": reg.reducer_sum_seconds, "driver_view_cpu": reg.driver_view_cpu_seconds,
        "worker_log_seconds": sum(w.log_seconds for w in reg.workers), "log_bytes": reg.log_bytes,
    }


@contextmanager
def _ray_cluster(nodes: int) -> Iterator[str | None]:
    """The address of a Ray cluster of `nodes` one-CPU nodes on this machine, or None for no Ray."""
    if not nodes:
        yield None
        return
    from ray.cluster_utils import Cluster

    store = 256 * 1024 * 1024
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "object_store_memory": store, "include_dashboard": False})
    try:
        for _ in range(nodes - 1):
            cluster.add_node(num_cpus=1, object_store_memory=store)
        cluster.wait_for_nodes()
        yield cluster.address
    finally:
        cluster.shutdown()


def _cpu_seconds() -> float:
    """User + system CPU seconds of this process (all its threads), the driver's busy time."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _projected_per_view(scene, cameras, topk: int) -> float:
    """Mean Gaussians a culled view projects: the same index, test and cost rule the registration's
    views use (`ViewComputer`)."""
    from drsplat.registration.compute import culling_pays, prepare_geometry, renders_whole
    from drsplat.registration.culling import SpatialIndex

    n = scene.num_gaussians
    index = SpatialIndex.build(prepare_geometry(scene))
    projected = []
    for cam in cameras:
        slots = cam.width * cam.height * topk
        size = index.visible(cam).size if culling_pays(n, slots) else n
        projected.append(n if renders_whole(size, n, slots) else size)
    return float(sum(projected) / max(len(cameras), 1))


# ----------------------------------------------------------------------------- the bench (parent process)


def _child(config: dict) -> dict:
    """Run `config` in a fresh process; config["numba_cache"] names an (empty) NUMBA_CACHE_DIR for it
    and the workers it starts: every kernel is compiled in that run."""
    env = child_env(**({"NUMBA_CACHE_DIR": config["numba_cache"]} if config.get("numba_cache") else {}))
    proc = subprocess.run([sys.executable, "-m", "drsplat.bench.scale", json.dumps(config)], env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        log.debug("bench run %s failed:\n%s", config.get("label"), proc.stderr[-3000:])
        raise ChildRunFailed(f"bench run '{config.get('label')}' failed: {last_error_line(proc.stderr)}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _mb(n: float) -> str:
    return f"{n / 1e6:,.0f}"


def _prepare(args, work: Path, tiles: int, views: int, tag: str) -> dict:
    from drsplat.cameras import load_cameras
    from drsplat.synthetic import tile_city

    room = args.room
    cams = load_cameras(room, require_images=False)
    from drsplat.scene import load_ply

    _, city_cams, sources = tile_city(load_ply(room / "scene.ply"), cams, tiles, views, args.width)
    feats = work / f"features_{tag}"
    link_features(room, feats, city_cams, sources)
    return {"room": str(room), "tiles": tiles, "views": views, "width": args.width, "features": str(feats), "out": str(work / f"{tag}.ply")}


def check_flags_and_files(args: argparse.Namespace) -> None:
    """Before any work: --json only where the compare part writes it, a given --room a written dataset,
    and --json over none of the room's files the runs read (nor named like a feature file in its features folder)."""
    from drsplat.commands.common import protected_feature_folders

    if args.json is not None and args.part not in ("all", "compare"):
        raise UsageError(f"--json records the compare part's runs, and --part {args.part} has none: use --part compare or all")
    room = args.room
    inputs: dict[str, Path | None] = {}
    protected = {}
    if room is not None:
        missing = [name for name in (*ROOM_FILES, "features") if not (room / name).exists()]
        if missing:
            raise InputError(room, f"is not a written synthetic dataset (--room): it has no {', '.join(missing)}; "
                                   f"make one with drsplat synth DIR --preset {ROOM_PRESET}")
        inputs = {f"--room's {name}": room / name for name in ROOM_FILES}
        protected = protected_feature_folders("--room's features", [room / "features"])
    guard_bench_outputs(inputs, {"--json": args.json}, protected)


def run(args: argparse.Namespace) -> int:
    from drsplat.synthetic import write_dataset

    check_flags_and_files(args)
    with tempfile.TemporaryDirectory(prefix="drsplat-scale-") as tmp:
        work = Path(tmp)
        if args.room is None:
            args.room = write_dataset(work / "room", ROOM_PRESET, 0, show_progress=False)
        print(machine_line() + " (shared with other jobs; absolute times are noisy)")
        compare, empty = None, []
        if args.part in ("all", "compare"):
            compare = _compare(args, work)
        if args.part in ("all", "rss") and not _rss(args, work):
            empty.append("rss")
        if args.part in ("all", "big"):
            _big(args, work)
        if args.part in ("all", "replay"):
            _replay(args, work)
        if compare:
            _projection(args, compare)
    if empty:  # the table says why each run stopped; a part of no measurement is not a result
        raise DrsplatError(f"--part {', '.join(empty)} measured nothing: every run stopped (see the table above)")
    return 0


def _compare(args, work: Path) -> list[dict]:
    base = _prepare(args, work, args.compare_tiles, args.compare_views, "compare")
    configs = [("local, in memory", {}), ("local, in memory, no culling", {"cull": False}), ("local, streamed (4 blocks)", {"block": -(-args.compare_tiles * 18413 // 4 // 1024) * 1024})]
    counts = args.workers
    configs += [(f"Ray, {w} node{'s' if w > 1 else ''} x 1 worker", {"nodes": w, "workers": w}) for w in counts]
    configs.append((f"Ray, {counts[-1]} nodes, empty kernel cache", {"nodes": counts[-1], "workers": counts[-1], "numba_cache": str(work / "numba-cold")}))
    configs += _reduce_configs(args, configs[2][1]["block"])
    # the reducers run again with views of 4x the width: more pairs per view, the projection's source
    wide = _prepare(argparse.Namespace(**{**vars(args), "width": 4 * args.width}), work, args.compare_tiles, args.compare_views, "compare-wide")
    configs.append((f"{configs[-1][0]}, {4 * args.width} px views", {**configs[-1][1], "wide": True}))
    rows, results = [], []
    reference = None
    for label, extra in configs:
        r = _child({**(wide if extra.get("wide") else base), **extra, "label": label})
        results.append({**r, "label": label, **extra})
        if extra.get("wide"):  # other views, another file: compared with nothing
            verdict = "(other views)"
        else:
            reference = reference or r["sha"]
            verdict = "identical" if r["sha"] == reference else "DIFFERENT"
        per_worker = "/".join(_mb(x) for x in r["worker_rss"]) or "-"
        later = f"{r['later_view']:.3f}" if r["later_view"] is not None else "-"
        rows.append([label, f"{r['gaussians']:,}", r["views"], f"{r['projected_per_view']:,.0f}", f"{r['wall']:.1f}", f"{r['raster']:.1f}",
                     f"{r['driver_cpu']:.1f}", f"{100 * r['driver_cpu'] / r['wall']:.0f}%",
                     f"{r['views_wall']:.1f}", f"{100 * r['views_driver_cpu'] / r['views_wall']:.0f}%", _seconds(r["first_view"], 2), later,
                     f"{r['kernels_compiled']}/{r['kernels_cached']}", _mb(r["peak_rss"]), per_worker, verdict])
    print(f"\nCity of {args.compare_tiles} rooms, {args.compare_views} views at {args.width} px, top-40, every Gaussian written (--keep-unassigned);"
          " Ray nodes are one-CPU nodes on this machine, started per run:")
    print(format_table(["run", "Gaussians", "views", "projected / view", "wall s", "raster s", "driver CPU s", "driver busy", "view pass s",
                        "driver busy in view pass", "first view s",
                        "later views s (median)", "kernels compiled/cached", "driver peak RSS MB", "worker peak RSS MB", "PLY vs local"], rows))
    print("first view: the slowest worker's first view (feature read, kernels loaded from numba's cache or compiled, render, pairs); "
          "driver busy: driver CPU / wall;\nview pass: from the start to the last view summed (the rest is finishing: normalise, encode, write the PLY).")
    _print_reduce(results)
    if args.json:
        write_records(args.json, results)
    return results


def _seconds(value: float | None, digits: int) -> str:
    """A table cell of seconds: '-' where there is none (a local run's first view on a worker)."""
    return "-" if value is None else f"{value:.{digits}f}"


def _reduce_configs(args, block: int) -> list[tuple[str, dict]]:
    """Ray in 4 blocks, most workers: the blocks finished by the driver, then by reducer tasks (the partitioned reduce)."""
    workers = max(args.workers)
    ray = {"nodes": workers, "workers": workers, "block": block}
    return [(f"Ray, {workers} workers, 4 blocks, driver finishes", {**ray, "reducers": False}),
            (f"Ray, {workers} workers, 4 blocks, reducers", {**ray, "reducers": True})]


def _print_reduce(results: list[dict]) -> None:
    """The finishing tail (after the view pass: sums, finish, encode, write) of the runs that have one."""
    rows = [[r["label"], "yes" if r["reduce"]["reducers"] else "no", f"{r['reduce']['tail_wall_s']:.2f}", f"{r['reduce']['tail_driver_cpu_s']:.2f}",
             f"{r['wall']:.1f}", f"{r['driver_cpu']:.1f}"] for r in results if r.get("block")]
    print("\nFinishing tail (after the view pass) of the runs in blocks:")
    print(format_table(["run", "reducers", "tail wall s", "tail driver CPU s", "wall s", "driver CPU s"], rows))


def write_records(path: Path, results: list[dict]) -> None:
    """The compare runs as JSON records (place, nodes, workers, wall_s, driver_busy_s, sha256, ...).

    nodes: Ray nodes (one-CPU nodes started on this machine). driver_busy_s: the driver process's
    CPU seconds during `register` (its threads included, so for a local run it is the whole
    computation). first_view_s: the slowest worker's first view after the cluster started
    (kernels loaded from numba's cache, or compiled with numba_cache "empty"); later_view_s: the
    median of the other views; kernels_compiled / kernels_cached: summed over the workers.
    view_pass_s / view_pass_driver_busy_s: wall and driver CPU from the start to the last view summed;
    view_pass_first_view_driver_busy_s: driver CPU until the first view was summed (fixed costs);
    view_results_driver_busy_s: driver CPU on the views' results (logging, folding, sums).
    worker_log_s: the workers' seconds writing their shards of the log (runs with reducers);
    log_bytes: the pair log's bytes, shards included.
    reduce: tail (after the view pass) wall and driver CPU, and the reducer tasks' seconds summed over
    blocks (whole tasks, and their log replays).
    """
    from drsplat.utils import atomic_path

    records = []
    for r in results:
        place = "ray" if r.get("nodes") else "streamed" if r["streamed"] else "local"
        records.append({
            "label": r["label"], "place": place, "nodes": r.get("nodes") or 1, "workers": r.get("workers", 1), "cull": r["cull"],
            "wall_s": round(r["wall"], 3), "driver_busy_s": round(r["driver_cpu"], 3), "raster_s": round(r["raster"], 3), "sha256": r["sha"],
            "gaussians": r["gaussians"], "views": r["views"], "projected_per_view": r["projected_per_view"], "driver_peak_rss": r["peak_rss"],
            "worker_peak_rss": r["worker_rss"], "first_view_s": None if r["first_view"] is None else round(r["first_view"], 4),
            "later_view_s": None if r["later_view"] is None else round(r["later_view"], 4), "kernels_compiled": r["kernels_compiled"],
            "kernels_cached": r["kernels_cached"], "numba_cache": "empty" if r.get("numba_cache") else "warm",
            "view_pass_s": round(r["views_wall"], 3), "view_pass_driver_busy_s": round(r["views_driver_cpu"], 3),
            "view_pass_first_view_driver_busy_s": round(r["first_view_driver_cpu"], 3), "view_results_driver_busy_s": round(r["driver_view_cpu"], 3),
            "reduce": {**r["reduce"], "reducer_seconds": round(r["reducer_seconds"], 3), "reducer_replay_seconds": round(r["reducer_sum_seconds"], 3)},
            "worker_log_s": round(r["worker_log_seconds"], 3), "log_bytes": r["log_bytes"],
        })
    with atomic_path(Path(path)) as tmp:
        Path(tmp).write_text(json.dumps(records, indent=1))


def _rss(args, work: Path) -> list[dict]:
    """Peak RSS vs N: each city streamed under --budget and in memory; a run that stops (in memory
    past what fits) is a row saying why. Returns the runs that finished."""
    rows, results = [], []
    budget = parse_size(args.budget)
    for tiles in args.rss_tiles:
        base = _prepare(args, work, tiles, args.rss_views, f"rss{tiles}")
        for label, extra in (("streamed", {"budget": args.budget}), ("in memory", {})):
            try:
                r = _child({**base, **extra, "label": label})
            except ChildRunFailed as exc:
                rows.append([f"{tiles * 18413 / 1e6:.1f} M", label, "-", "-", "-", "stops: " + str(exc).split(" failed: ", 1)[-1][:100]])
                continue
            results.append(r)
            rows.append([f"{r['gaussians'] / 1e6:.2f} M", label + (" (blocks)" if r["streamed"] else " (fits: in memory)" if extra else ""), _mb(r["peak_rss"]),
                         f"{r['wall']:.0f}", f"{r['wall'] / r['views']:.2f}", "fits" if r["peak_rss"] <= budget else "over budget"])
    print(f"\nPeak RSS vs N ({args.rss_views} views, budget {args.budget}; 'in memory' runs without a budget stop when they do not fit):")
    print(format_table(["N", "run", "peak RSS MB", "wall s", "wall s / view", "vs budget"], rows))
    return results


def _big(args, work: Path) -> list[dict]:
    base = _prepare(args, work, args.big_tiles, args.big_views, "big")
    r = _child({**base, "budget": args.budget, "label": "big"})
    print(f"\nDone-means run: {r['gaussians']:,} Gaussians, {r['views']} views at {args.width} px, budget {args.budget}, every Gaussian written:")
    print(format_table(["wall s", "views/s", "peak RSS MB", "streamed", "pairs (M)", "distinct (M)", "PLY GB"],
                       [[f"{r['wall']:.0f}", f"{r['views'] / r['wall']:.2f}", _mb(r["peak_rss"]), r["streamed"], f"{r['pairs'] / 1e6:.1f}",
                         f"{r['distinct'] / 1e6:.1f}", f"{r['ply_bytes'] / 1e9:.2f}"]]))
    replay = max(r["accumulate"] - r["coalesce"], 0.0)
    tail = r["wall"] - r["views_wall"]
    stages = [("city built in memory (before register)", r["build"]), ("view pass", r["views_wall"]),
              ("  rasterize (culled, top-k)", r["raster"]), ("  coalesce + group pairs", r["coalesce"]),
              ("  log, statistics, the rest of the view pass", r["views_wall"] - r["raster"] - r["coalesce"]),
              ("blocks: replay the log's chunks", replay), ("blocks: finish, encode, write the PLY", tail - replay)]
    print("Per stage (wall s; the view pass's parts are summed per view):")
    print(format_table(["stage", "s", "share of register"], [[name, f"{sec:.1f}", "-" if "built" in name else f"{100 * sec / r['wall']:.0f}%"]
                                                               for name, sec in stages]))
    return [r]


def _replay(args, work: Path, dim: int = 512, masks: int = 200, repeats: int = 5) -> None:
    """Block replays of one pair log: reading only each block's Gaussian chunks of every record
    (`PairLog.block_views`, what LogSink and the reducers do) vs reading every record whole and
    filtering (the layout before chunks). The same sums are asserted; times are medians over
    repeats that alternate which replay runs first (the 512-D sums dominate and are noisy)."""
    import numpy as np

    from drsplat.registration.pairlog import PairLog, ViewPairs
    from drsplat.registration.sink import LogSink
    from drsplat.registration.sums import Accumulator

    rng = np.random.default_rng(0)
    n, per_mask = args.replay_gaussians, max(args.replay_pairs // masks, 1)
    path = work / "replay.log"
    with PairLog.open(path, {"bench": "replay"}) as plog:
        for v in range(args.replay_views):  # each view sees a window of the scene, mask by mask
            centre = int(rng.integers(0, n))
            g = np.concatenate([(centre + rng.integers(-n // 7, n // 7, per_mask)) % n for _ in range(masks)]).astype(np.int32)
            plog.append(ViewPairs(f"v{v}", rng.normal(size=(masks, dim)).astype(np.float32), g, np.repeat(np.arange(masks, dtype=np.int32), per_mask),
                                  rng.random(g.size).astype(np.float32), np.arange(masks, dtype=np.int32), g.size))
    block = -(-n // args.replay_blocks)

    def whole_records(plog: PairLog, lo: int, hi: int):
        acc = Accumulator(hi - lo, dim)
        for view in plog:
            keep = (view.gaussians >= lo) & (view.gaussians < hi)
            if keep.any():
                acc.add_pairs(view.gaussians[keep] - np.int32(lo), view.masks[keep], view.weights[keep], view.feats)
        return acc.sums()

    times: dict[str, list[float]] = {"whole records": [], "chunks only": []}
    read: dict[str, int] = {}
    with PairLog.open(path, {"bench": "replay"}) as plog:
        size = plog.nbytes
        sink = LogSink(n, dim, plog, block)
        for rep in range(repeats):
            spent = {k: 0.0 for k in times}
            for lo in range(0, n, block):
                hi = min(n, lo + block)
                sums = {}
                for name in (("whole records", "chunks only") if rep % 2 == 0 else ("chunks only", "whole records")):
                    t0 = time.perf_counter()
                    sums[name] = whole_records(plog, lo, hi) if name == "whole records" else _block_arrays(sink.block_sums(lo, hi))
                    spent[name] += time.perf_counter() - t0
                (F, W), (F2, W2) = sums["whole records"], sums["chunks only"]
                if not (np.array_equal(F, F2) and np.array_equal(W, W2)):
                    raise RuntimeError(f"block {lo}..{hi}: chunked replay differs from the whole-record replay")
                del sums, F, W, F2, W2
            for k, v in spent.items():
                times[k].append(v)
        read["whole records"] = size * -(-n // block)
        read["chunks only"] = sum(_chunk_bytes(plog, r, lo, min(n, lo + block)) for r in plog.records for lo in range(0, n, block))
    base = statistics.median(times["whole records"])
    print(f"\nBlock replays of a pair log ({size / 1e6:,.0f} MB: {args.replay_views} views x {args.replay_pairs:,} pairs, N = {n:,}, "
          f"{-(-n // block)} blocks, D = {dim}, page cache warm; median of {repeats}, alternating which runs first; the same sums asserted):")
    print(format_table(["replay", "all blocks s", "speed-up", "bytes read MB"],
                       [[k, f"{statistics.median(v):.2f}", f"{base / statistics.median(v):.2f}x", f"{read[k] / 1e6:,.0f}"] for k, v in times.items()]))


def _block_arrays(block) -> tuple:
    return block.F, block.W


def _chunk_bytes(plog, record, lo: int, hi: int) -> int:
    """Bytes `PairLog.read_block` reads of `record` for Gaussians lo .. hi-1 (embeddings, used masks, chunk starts, the chunks' pairs)."""
    from drsplat.registration.pairlog import chunk_span

    meta = record.meta
    s0, s1 = chunk_span(plog.read(record).chunk_starts, lo, hi)
    return 4 * meta["M"] * meta["D"] + 4 * meta["U"] + 8 * (meta["C"] + 1) + 12 * (s1 - s0)


def _projection(args, results: list[dict]) -> None:
    """Wall time on 1 / 8 / 64 GPU nodes from per-task costs measured in the compare runs x task counts (a model).

    Views: t = a·N + b·P per view on a worker (projection ~ Gaussians, compositing ~ pixels); a from
    the local run after removing b·P, b (--pixel-cost-us) from the flowers rasterizer table; plus the
    worker's writes of its shard of the log per distinct pair; workers run in parallel on nodes x
    --gpu-speedup. The other costs come from the Ray reducers run with the widest views (the most
    pairs per view): the driver's CPU per view after the first (Ray calls, a pointer logged, the
    vote's mask clusters: the workers log the pairs, so none of it grows with them); the reducers'
    replay of the shards per pair (sums and floater statistics) and the rest of their task time
    (allocation, finish, encoding) per Gaussian, `--reducers-per-node` reducers per node; the
    driver's CPU after the view pass (assembly) per Gaussian. With V views, D distinct pairs, N
    Gaussians and k nodes:

        wall = max(V · ((a·N + b·P) / gpu_speedup + D/V · log_per_pair) / k, V · driver_per_view)
               + (D · replay_per_pair + N · reducer_per_gaussian) / (k · reducers_per_node) + N · assemble_per_gaussian
    """
    local = results[0]
    runs = [r for r in results if r.get("reducers") and r["reduce"]["reducers"]]
    if not runs:
        print("\nProjection: needs the compare part's Ray run with reducers (--part compare or all)")
        return
    ray = max(runs, key=lambda r: r["distinct"])
    pixels = args.width * args.width * 3 / 4
    per_view = (local["raster"] + local["coalesce"]) / local["views"]
    b = args.pixel_cost_us * 1e-6
    a = max(per_view - b * pixels, 0.0) / local["gaussians"]
    log_per_pair = ray["worker_log_seconds"] / max(ray["distinct"], 1)
    driver_per_view = max(ray["views_driver_cpu"] - ray["first_view_driver_cpu"], 0.0) / max(ray["views"] - 1, 1)
    replay_per_pair = ray["reducer_sum_seconds"] / max(ray["distinct"], 1)
    reducer_per_gaussian = max(ray["reducer_seconds"] - ray["reducer_sum_seconds"], 0.0) / ray["gaussians"]
    assemble_per_gaussian = ray["reduce"]["tail_driver_cpu_s"] / ray["gaussians"]
    pairs = args.model_images * args.pairs_per_mp * args.model_pixels / 1e6
    view_cost = (a * args.model_gaussians + b * args.model_pixels) / args.gpu_speedup + log_per_pair * pairs / args.model_images
    rows, walls = [], {}
    for nodes in args.nodes:
        views_s = args.model_images * view_cost / nodes
        log_s = args.model_images * driver_per_view
        reduce_s = (pairs * replay_per_pair + args.model_gaussians * reducer_per_gaussian) / (nodes * args.reducers_per_node)
        assemble_s = args.model_gaussians * assemble_per_gaussian
        walls[nodes] = max(views_s, log_s) + reduce_s + assemble_s
        rows.append([nodes, f"{views_s / 60:.1f}", f"{log_s / 60:.1f}", f"{reduce_s / 60:.1f}", f"{assemble_s / 60:.1f}", f"{walls[nodes] / 60:.1f}",
                     "driver" if log_s > views_s else "workers"])
    print(f"\nProjection (a model, not a measurement): {args.model_images:,} images of {args.model_pixels / 1e6:.1f} MP, "
          f"{args.model_gaussians / 1e6:.0f}M Gaussians, {pairs / 1e9:.1f} G distinct pairs. Measured here: {a * 1e9:.0f} ns per Gaussian per "
          f"view ({local['gaussians'] / 1e6:.2f}M Gaussians, culled); from '{ray['label']}' ({ray['distinct'] / ray['views'] / 1e3:.1f}k pairs per "
          f"view): workers {log_per_pair * 1e9:.0f} ns per pair written to their shards, driver {driver_per_view * 1e3:.1f} ms per view "
          f"(Ray calls, pointers, mask clusters), reducers {replay_per_pair * 1e9:.0f} ns per pair replayed (sums and statistics) + "
          f"{reducer_per_gaussian * 1e6:.1f} us per Gaussian, driver {assemble_per_gaussian * 1e6:.2f} us per Gaussian assembled. Assumed: "
          f"{args.pixel_cost_us:g} us per pixel per view, {args.pairs_per_mp / 1e6:g} M distinct pairs per megapixel (flowers), one GPU node = "
          f"{args.gpu_speedup:g}x this machine per view (not the shard writes), {args.reducers_per_node} reducer(s) per node.")
    print(format_table(["GPU nodes", "views on workers (min)", "driver per view (min)", "reducers (min)", "driver assembles (min)",
                        "wall (min)", "view pass bound by"], rows))
    counts = sorted(walls)
    if len(counts) > 1:
        lo, hi = counts[-2], counts[-1]
        print(f"speed-up {lo} -> {hi} nodes: {walls[lo] / walls[hi]:.1f}x")


if __name__ == "__main__":  # a child run: python -m drsplat.bench.scale CONFIG_JSON
    logging.basicConfig(level=logging.WARNING)
    print(json.dumps(run_config(json.loads(sys.argv[1]))))
