"""`drsplat bench render`: RGB rendering's SH colours (numba kernel against the numpy reference) and what
`--principal-point auto` and `--near-plane auto` cost on a scene (drsplat.frames.cameras_with_principal_point,
near_plane_as_trained).

Rows, each measured in this run (medians over --repeats):
- SH colours of every Gaussian for one view: the numpy reference (`raster._add_colors`, eval_sh) and the
  numba kernel (`raster._add_colors_numba`), with the largest colour difference between them;
- one RGB render of a --width x --height view (projection, colours, compositing);
- the principal-point decision over --views orbit views whose images are the scene's own renders and whose
  principal points are moved --offset of the width off the centre (a scene trained about the centres): its
  time and whether it took the centres;
- the near band (`raster.near_band`: the Gaussians 0.01-0.2 in front of each of the --views cameras) of the scene
  with 20 floaters before each of 2 views (`testing.with_floaters`), its numba pass against the numpy reference
  (`near_band_reference`), and whether they found the same bands;
- the near-plane decision on that scene, whose images are its renders at INRIA's plane (0.2): its time and
  whether it took 0.2.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import tempfile
from pathlib import Path

import numpy as np

from drsplat.bench.common import format_table, machine_line, median_seconds
from drsplat.commands.common import float_range, int_range, positive_int


def add_bench(subparsers: argparse._SubParsersAction) -> None:
    from drsplat.bench.register import DEFAULT_REAL

    p = subparsers.add_parser("render", help="RGB render: SH colours (numba vs numpy), the --principal-point auto and --near-plane auto decisions' cost")
    p.add_argument("--scene", type=Path, default=None,
                   help=f"a 3DGS scene (default: {DEFAULT_REAL.name} from ../shared/data when present, else the synthetic 'small' room)")
    p.add_argument("--width", type=int_range(16, 4096), default=640, help="view width in pixels (default 640)")
    p.add_argument("--height", type=int_range(16, 4096), default=480, help="view height in pixels (default 480)")
    p.add_argument("--views", type=int_range(1, 256), default=24, help="orbit views the principal-point decision may pick from (default 24)")
    p.add_argument("--offset", type=float_range(0.0, 0.5), default=0.01, help="principal-point offset, a share of the width (default 0.01)")
    p.add_argument("--repeats", type=positive_int, default=3, help="timed repeats (median reported; default 3)")
    p.set_defaults(func=run)


def bench_scene(path: Path | None):
    """(name, GaussianScene) the bench renders: `path`, else the default real scene, else the synthetic 'small' room."""
    from drsplat.bench.register import DEFAULT_REAL
    from drsplat.splat_formats import load_scene
    from drsplat.synthetic import make_synthetic

    if path is None and DEFAULT_REAL.is_file():
        path = DEFAULT_REAL
    if path is None:
        return "synthetic small", make_synthetic("small", 0).scene
    return path.name, load_scene(path)


def decision_cameras(cameras, offset: float):
    """`cameras` (with images of their own renders) with their principal points moved `offset` of the width right and
    0.6 of that up: a scene trained about the centres, read from an off-centre calibration."""
    out = []
    for camera in cameras:
        shift = offset * camera.width
        out.append(dataclasses.replace(camera, cx=camera.cx + shift, cy=camera.cy - 0.6 * shift))
    return out


def run(args: argparse.Namespace) -> int:
    from drsplat.bench.register import orbit_cameras
    from drsplat.defaults import INRIA_NEAR, NEAR
    from drsplat.frames import cameras_with_principal_point, near_plane_as_trained
    from drsplat.raster import _add_colors, _add_colors_numba, near_band, near_band_reference, prepare_scene, project_gaussians, rasterize
    from drsplat.testing import cameras_with_own_images, with_floaters

    name, scene = bench_scene(args.scene)
    prepared = prepare_scene(scene)
    cameras = orbit_cameras(scene.means, args.views, args.width, args.height)
    camera = cameras[0]
    projected = project_gaussians(prepared, camera)
    reference, kernel = dataclasses.replace(projected), dataclasses.replace(projected)
    t_reference = median_seconds(lambda: _add_colors(reference, prepared, camera), args.repeats)
    t_kernel = median_seconds(lambda: _add_colors_numba(kernel, prepared, camera), args.repeats)
    difference = float(np.abs(kernel.colors.astype(np.float64) - reference.colors).max())
    t_render = median_seconds(lambda: rasterize(prepared, camera, 1, with_rgb=True), args.repeats)
    frames_log = logging.getLogger("drsplat.frames")
    level = frames_log.level
    with tempfile.TemporaryDirectory(prefix="drsplat-bench-render-") as folder:
        shifted = decision_cameras(cameras_with_own_images(prepared, cameras, Path(folder)), args.offset)
        chosen = []
        frames_log.setLevel(logging.ERROR)  # its warning once per repeat is no table row
        try:
            t_decision = median_seconds(lambda: chosen.append(cameras_with_principal_point(scene, shifted)), args.repeats)
        finally:
            frames_log.setLevel(level)
        floaty = with_floaters(scene, cameras[:2])
        # prepared once, so a scene's unusable Gaussians are said once, not once a repeat (round 90b F3)
        floaty_prepared = prepare_scene(floaty)
        t_band_reference = median_seconds(lambda: near_band_reference(floaty_prepared, cameras, NEAR, INRIA_NEAR), args.repeats)
        t_band = median_seconds(lambda: near_band(floaty_prepared, cameras, NEAR, INRIA_NEAR), args.repeats)
        same = all(np.array_equal(a.ids, b.ids) and a.tiles == b.tiles
                   for a, b in zip(near_band(floaty_prepared, cameras, NEAR, INRIA_NEAR, with_ids=True),
                                   near_band_reference(floaty_prepared, cameras, NEAR, INRIA_NEAR, with_ids=True)))
        (Path(folder) / "inria").mkdir()
        inria = cameras_with_own_images(floaty_prepared, cameras, Path(folder) / "inria", INRIA_NEAR)
        planes = []
        frames_log.setLevel(logging.ERROR)
        try:
            t_plane = median_seconds(lambda: planes.append(near_plane_as_trained(floaty, inria)), args.repeats)
        finally:
            frames_log.setLevel(level)
    took = "the centres" if chosen and chosen[-1][0].cx == camera.width / 2 else "the file's"
    print(f"{name}: {scene.num_gaussians:,} Gaussians, SH degree {scene.sh_degree}, views {args.width}x{args.height}")
    print(format_table(["step", "reference s", "kernel s", "speed-up", "max |Δ colour|"],
                       [[f"SH colours, one view ({int(projected.valid.sum()):,} visible)", t_reference, t_kernel, t_reference / t_kernel,
                         f"{difference:.2e}"]]))
    print(format_table(["step", "seconds", "result"],
                       [["RGB render, one view", t_render, ""],
                        [f"--principal-point auto, {args.views} views {100 * args.offset:g} % off", t_decision, f"took {took} (truth: the centres)"],
                        [f"--near-plane auto, 20 floaters before 2 of {args.views} views, images at {INRIA_NEAR:g}", t_plane,
                         f"took {planes[-1]:g} (truth: {INRIA_NEAR:g})"]]))
    print(format_table(["step", "reference s", "kernel s", "speed-up", "same bands"],
                       [[f"near band {NEAR:g}-{INRIA_NEAR:g}, {args.views} views ({floaty.num_gaussians:,} Gaussians)", t_band_reference,
                         t_band, t_band_reference / t_band, "yes" if same else "NO"]]))
    print(machine_line())
    return 0
