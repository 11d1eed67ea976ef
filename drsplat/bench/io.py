"""`drsplat bench io`: PLY load/save speed against a bare plyfile read of the same file."""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from drsplat.bench.common import format_table, machine_line, median_seconds
from drsplat.errors import InputError
from drsplat.scene import load_ply, save_ply

DEFAULT_SCENE = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "ply" / "flowers.ply"


def add_bench(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("io", help="PLY load/save time and MB/s, against a bare plyfile read")
    p.add_argument("scene", nargs="?", type=Path, default=DEFAULT_SCENE, help="PLY to time (default: ../shared/data/ply/flowers.ply)")
    p.add_argument("--repeats", type=int, default=5, help="timed repeats (median reported)")
    p.set_defaults(func=run)


def _plyfile_read(path: Path) -> None:
    from plyfile import PlyData

    PlyData.read(str(path))["vertex"].data.copy()


def run(args: argparse.Namespace) -> int:
    path = args.scene
    if not path.exists():
        raise InputError(path, "does not exist (the default needs ../shared/data beside the project; pass a PLY)")
    size_mb = path.stat().st_size / 1e6
    scene = load_ply(path)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out.ply"
        t_load = median_seconds(lambda: load_ply(path), args.repeats)
        t_plyfile = median_seconds(lambda: _plyfile_read(path), args.repeats)
        t_save = median_seconds(lambda: save_ply(scene, out), args.repeats)
        out_mb = out.stat().st_size / 1e6
    rows = [
        ["drsplat load_ply", t_load * 1e3, size_mb / t_load, t_load / t_plyfile],
        ["plyfile read (bare)", t_plyfile * 1e3, size_mb / t_plyfile, 1.0],
        ["drsplat save_ply", t_save * 1e3, out_mb / t_save, t_save / t_plyfile],
    ]
    print(f"{path.name}: {scene.num_gaussians:,} Gaussians, SH degree {scene.sh_degree}, {size_mb:.1f} MB; median of {args.repeats}")
    print(format_table(["operation", "ms", "MB/s", "time / plyfile read"], rows))
    print(machine_line())
    return 0
