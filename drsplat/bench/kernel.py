"""`drsplat bench kernel`: the fused Triton top-k kernel on a CUDA GPU, per launch configuration.

For a real scene seen by orbiting views: the projection and the tile binning (ms per view), then
for each (pixels, warps, list entries per step) of a program the compositing with its slot sort and
id lookup
(`raster_triton.composite_topk_triton`, median ms per view over repeats, after one compiling
call), with its agreement against the numba engine on the first view (top-k ids, weights,
median ids). The default configuration is `raster_triton.CUDA_BLOCK` x `CUDA_WARPS` x `CUDA_CHUNK`
(chunk 0: the per-entry kernel, one list entry per step); the table is what chose it. Needs a CUDA GPU (Triton compiles for CUDA only).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from drsplat.bench.common import format_table, machine_line, scene_file, view_size
from drsplat.bench.register import DEFAULT_REAL, orbit_cameras
from drsplat.commands.common import positive_int
from drsplat.defaults import DEFAULT_TOPK
from drsplat.errors import DrsplatError, UsageError, shown_path

DEFAULT_CONFIGS = "16x1x0,8x1x16,2x1x32,1x1x32,1x1x64"
TILE_PIXELS = 256  # a 16 x 16 tile


def add_bench(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("kernel", help="the fused Triton top-k kernel on a CUDA GPU: ms per view per launch configuration")
    p.add_argument("--real", type=Path, default=DEFAULT_REAL, help="scene to render (default: ../shared/data/ply/flowers.ply)")
    p.add_argument("--views", type=positive_int, default=2, help="orbiting views timed (default: 2)")
    p.add_argument("--size", type=view_size, default="640x480", help="view size WxH (default: 640x480)")
    p.add_argument("--topk", type=positive_int, default=DEFAULT_TOPK, help=f"top-k per pixel (default: {DEFAULT_TOPK})")
    p.add_argument("--configs", default=DEFAULT_CONFIGS,
                   help=f"comma-separated PIXELSxWARPS[xCHUNK] per program (CHUNK: list entries per step, 0 = the per-entry kernel, "
                        f"default the library's); PIXELS must divide a tile's {TILE_PIXELS} (default: {DEFAULT_CONFIGS})")
    p.add_argument("--repeats", type=positive_int, default=7, help="timed calls per view and configuration, median reported (default: 7)")
    p.set_defaults(func=run)


def parse_configs(text: str) -> list[tuple[int, int, int | None]]:
    """'16x1,32x4x16,16x1x0' -> [(16, 1, None), (32, 4, 16), (16, 1, 0)]: (pixels, warps, list entries per step;
    None: the library's default, 0: one at a time), each checked by `raster_triton.launch_problem`; UsageError naming the bad entry."""
    from drsplat.raster_triton import launch_problem  # imports torch and triton: only once the bench runs

    configs = []
    for item in text.split(","):
        parts = item.strip().lower().split("x")
        numbers = [int(p) for p in parts if p.strip().isdigit()]
        if len(parts) not in (2, 3) or len(numbers) != len(parts):
            raise UsageError(f"--configs: {item.strip()!r} is not PIXELSxWARPS[xCHUNK] (whole numbers)")
        pixels, warps, chunk = numbers[0], numbers[1], numbers[2] if len(numbers) == 3 else None
        problem = launch_problem(pixels, warps, 0 if chunk is None else chunk, TILE_PIXELS)
        if problem:
            raise UsageError(f"--configs: {item.strip()!r}: {problem}")
        configs.append((pixels, warps, chunk))
    return configs


def _timed(fn, repeats: int):
    """(median ms of `repeats` calls, the last result), each call timed with CUDA events."""
    import torch

    times, result = [], None
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        result = fn()
        end.record()
        torch.cuda.synchronize()
        times.append(start.elapsed_time(end))
    return statistics.median(times), result


def run(args: argparse.Namespace) -> int:
    configs = parse_configs(args.configs)
    width, height = args.size
    from drsplat.device import cuda_available

    if not cuda_available():  # before the scene is read
        raise DrsplatError("drsplat bench kernel times the fused Triton kernels, which run on a CUDA GPU only, and none is available")
    scene_file(args.real, "--real")
    from drsplat import raster_triton
    from drsplat.raster import rasterize
    from drsplat.raster_torch import bin_gaussians_torch, prepare_scene_torch, project_gaussians_fused
    from drsplat.registration.compute import prepare_geometry
    from drsplat.scene import load_ply

    scene = load_ply(args.real, purpose="benchmark")
    cameras = orbit_cameras(scene.means, args.views, width, height)
    geometry = prepare_geometry(scene)
    prepared = prepare_scene_torch(geometry, "cuda")
    rows, stages = [], []
    for index, cam in enumerate(cameras):
        project_ms, projected = _timed(lambda: project_gaussians_fused(prepared, cam, device=prepared.device), args.repeats)
        bin_ms, bins = _timed(lambda: bin_gaussians_torch(projected), args.repeats)
        stages.append([cam.name, project_ms, bin_ms, int(bins[2].numel())])
        reference = rasterize(geometry, cam, args.topk, with_median=True, engine="numba") if index == 0 else None
        for block, warps, chunk in configs:
            def composite():
                return raster_triton.composite_topk_triton(projected, bins, args.topk, with_median=True, block=block, num_warps=warps,
                                                           chunk=chunk)

            t0 = time.perf_counter()
            composite()  # compiles this configuration once
            ms, (ids, weights, _, median) = _timed(composite, args.repeats)
            agree = ["", "", ""]
            if reference is not None:
                agree = [float((ids.cpu().numpy() != reference.ids).mean()), float(np.abs(weights.cpu().numpy() - reference.weights).max()),
                         float((median.cpu().numpy() != reference.median_ids).mean())]
            shown = raster_triton.CUDA_CHUNK if chunk is None else chunk
            rows.append([cam.name, f"{block}x{warps}x{shown}", 1e3 * (time.perf_counter() - t0) if index == 0 else "", ms, *agree])
    import torch

    print(f"{shown_path(args.real.name)}: {scene.num_gaussians:,} Gaussians, {len(cameras)} orbiting views {width}x{height}, top-{args.topk}, "
          f"{torch.cuda.get_device_name(0)}; median of {args.repeats} calls")
    print(format_table(["view", "project ms", "bin ms", "tile-list entries"], stages))
    print()
    print(format_table(["view", "pixels x warps x chunk", "first call ms (compile)", "composite ms", "id mismatch vs numba", "max |Δw|",
                        "median-id mismatch"], rows))
    print(f"defaults: {raster_triton.CUDA_BLOCK}x{raster_triton.CUDA_WARPS}x{raster_triton.CUDA_CHUNK} (chunk 0: one list entry per step)")
    print(machine_line())
    return 0
