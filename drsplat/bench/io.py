"""`drsplat bench io`: scene file load/save speed against a bare plyfile read of the same PLY, and
for each file type drsplat writes (PLY, compressed PLY, `.splat`, `.spz` v3 and v4) its size, write and read time
and what its quantisation costs: the PSNR of renders of the written file against the PLY's."""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from drsplat.bench.common import format_table, machine_line, median_seconds
from drsplat.commands.common import nonneg_int, positive_int
from drsplat.errors import InputError, OutputError, shown_path
from drsplat.raster import prepare_scene, rasterize
from drsplat.scene import GaussianScene, load_ply, morton_order, save_ply
from drsplat.splat_formats import load_scene, save_scene, written_format

DEFAULT_SCENE = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "ply" / "flowers.ply"
WRITTEN_FILES = (("PLY", "scene.ply", 3), ("compressed PLY", "scene.compressed.ply", 3), (".splat", "scene.splat", 3),
                 (".spz v3 (gzip)", "scene.spz", 3), (".spz v4 (zstd)", "v4.spz", 4))


def add_bench(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("io", help="scene file load/save time, size and render error per file type (PLY, compressed PLY, .splat, .spz)")
    p.add_argument("scene", nargs="?", type=Path, default=DEFAULT_SCENE, help="PLY to time (default: ../shared/data/ply/flowers.ply)")
    p.add_argument("--repeats", type=positive_int, default=5, help="timed repeats (median reported)")
    p.add_argument("--views", type=nonneg_int, default=4,
                   help="orbiting 640x480 views rendered from each written file against the PLY (0: no render error)")
    p.set_defaults(func=run)


def _plyfile_read(path: Path) -> None:
    from plyfile import PlyData

    PlyData.read(str(path))["vertex"].data.copy()


def psnr(image: np.ndarray, reference: np.ndarray) -> float:
    """PSNR in dB of image against reference, both [H, W, 3] in [0, 1] (inf when equal)."""
    mse = float(np.mean((np.clip(image, 0, 1) - np.clip(reference, 0, 1)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


def renders(scene: GaussianScene, cameras) -> list[np.ndarray]:
    """[H, W, 3] colour renders of the scene in each camera (numba engine, black background)."""
    prepared = prepare_scene(scene)
    return [rasterize(prepared, cam, 1, with_rgb=True).rgb for cam in cameras]


def file_type_table(scene: GaussianScene, folder: Path, views: int, repeats: int) -> str:
    """Per file type: MB, size against the PLY, write and read ms (medians), the largest position
    error and the median PSNR of `views` renders against the PLY's; a type that cannot hold the
    scene (.spz's fixed point past ±8.4M units) is a row "not written" and a line saying why."""
    from drsplat.bench.register import orbit_cameras

    cameras = orbit_cameras(scene.means, views, 640, 480) if views else []
    reference = renders(scene, cameras)
    rows, notes, ply_mb = [], [], None
    for name, file, version in WRITTEN_FILES:
        path = folder / file
        try:
            t_write = median_seconds(lambda: save_scene(scene, path, spz_version=version), repeats)
        except OutputError as exc:  # the type cannot hold this scene (e.g. .spz's fixed point): a row, not an error naming a temp file
            if exc.path != path:
                raise
            rows.append([name, "not written", "", "", "", "", ""])
            notes.append(f"{name}: not written: {exc.problem}")
            continue
        mb = path.stat().st_size / 1e6
        ply_mb = mb if ply_mb is None else ply_mb
        t_read = median_seconds(lambda: load_scene(path), repeats)
        back = load_scene(path)
        order = morton_order(scene.means) if written_format(path) == "compressed.ply" else slice(None)  # which stores them in Morton order
        error = float(np.abs(back.means.astype(np.float64) - scene.means[order]).max())
        quality = float(np.median([psnr(a, b) for a, b in zip(renders(back, cameras), reference)])) if views else float("nan")
        rows.append([name, mb, mb / ply_mb, t_write * 1e3, t_read * 1e3, error, quality])
    table = format_table(["file", "MB", "size / PLY", "write ms", "read ms", "max |Δ position|", f"PSNR dB vs PLY (median of {views} views)"], rows)
    return "\n".join([table, *notes])


def run(args: argparse.Namespace) -> int:
    path = args.scene
    if not path.exists():
        raise InputError(path, "does not exist (the default needs ../shared/data beside the project; pass a PLY)")
    size_mb = path.stat().st_size / 1e6
    scene = load_ply(path, purpose="benchmark")  # a file of no Gaussians is one error here, not a numpy one in the tables
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out.ply"
        t_load = median_seconds(lambda: load_ply(path), args.repeats)
        t_plyfile = median_seconds(lambda: _plyfile_read(path), args.repeats)
        t_save = median_seconds(lambda: save_ply(scene, out), args.repeats)
        out_mb = out.stat().st_size / 1e6
        types = file_type_table(scene, Path(tmp), args.views, args.repeats)
    rows = [
        ["drsplat load_ply", t_load * 1e3, size_mb / t_load, t_load / t_plyfile],
        ["plyfile read (bare)", t_plyfile * 1e3, size_mb / t_plyfile, 1.0],
        ["drsplat save_ply", t_save * 1e3, out_mb / t_save, t_save / t_plyfile],
    ]
    print(f"{shown_path(path.name)}: {scene.num_gaussians:,} Gaussians, SH degree {scene.sh_degree}, {size_mb:.1f} MB; median of {args.repeats}")
    print(format_table(["operation", "ms", "MB/s", "time / plyfile read"], rows))
    print("\nFile types drsplat writes (`save_scene`: by the name), read back by `load_scene`:")
    print(types)
    print(machine_line())
    return 0
