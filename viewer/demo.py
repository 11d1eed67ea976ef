"""The pre-registered demo scene shipped in assets/demo/, and the command that rebuilds it.

`python -m viewer.demo [OUT_DIR]` (default assets/demo) writes the `tiny` synthetic preset
(drsplat.synthetic, seed 0), registers it with the one pipeline (drsplat.registration.register,
a PQ codebook trained on the scene, unassigned Gaussians kept so the scene looks whole and its
rows match gt/labels.npy) and keeps only what the viewer needs:

    registered.ply, registered.codebook.faiss   the scene with its language field
    transforms.json, images/*.png               the training cameras and their images (128x96)
    gt/label_names.json, gt/labels.npy          the labels (oracle queries, tests)
    text_embeddings.npy                         the oracle "text" vectors, one per label

about 1.9 MB. `python main.py` opens it at once.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import sys
import tempfile
from pathlib import Path

from drsplat.cameras import load_cameras
from drsplat.defaults import ORACLE_LABEL_NAMES, ORACLE_TEXT_EMBEDDINGS
from drsplat.registration import RegisterOptions, register
from drsplat.scene import load_ply
from drsplat.synthetic import write_dataset
from viewer.assets import asset_path

log = logging.getLogger(__name__)

DEMO_PRESET = "tiny"
DEMO_SEED = 0
DEMO_FILES = ("registered.ply", "registered.codebook.faiss", "transforms.json", ORACLE_LABEL_NAMES, "gt/labels.npy", ORACLE_TEXT_EMBEDDINGS)


def demo_dir() -> Path:
    return asset_path("demo")


def demo_available(folder: Path | None = None) -> bool:
    folder = folder or demo_dir()
    return all((folder / name).is_file() for name in DEMO_FILES)


def build_demo(out_dir: Path, preset: str = DEMO_PRESET, seed: int = DEMO_SEED, show_progress: bool = True) -> Path:
    """Write the demo files (DEMO_FILES) into `out_dir`; returns its registered PLY.

    Built in a temporary folder next to `out_dir` and moved in file by file, so a failed build
    leaves the previous demo untouched.
    """

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out_dir.parent, prefix=".demo-build-") as tmp:
        dataset = write_dataset(Path(tmp) / "dataset", preset, seed=seed, show_progress=show_progress)
        built = Path(tmp) / "out"
        built.mkdir()
        options = RegisterOptions(codebook="scene", keep_unassigned=True)
        register(load_ply(dataset / "scene.ply"), load_cameras(dataset, require_images=False), dataset / "features", built / "registered.ply", options, show_progress=show_progress)
        names = list(DEMO_FILES) + [f"images/{p.name}" for p in sorted((dataset / "images").glob("*.png"))]
        for name in names[2:]:
            (built / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(dataset / name, built / name)
        for name in names:
            (out_dir / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.move(str(built / name), out_dir / name)
    return out_dir / "registered.ply"


def demo_size(folder: Path) -> int:
    """Bytes of the demo's files."""
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m viewer.demo", description="Rebuild the pre-registered demo scene (assets/demo).")
    parser.add_argument("out_dir", nargs="?", type=Path, default=None, help="output folder (default: assets/demo)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s: %(message)s")
    out = build_demo(args.out_dir or demo_dir())
    total = demo_size(out.parent)
    log.info("demo scene written to %s (%.1f MB)", out.parent, total / 1e6)
    return 0


if __name__ == "__main__":
    sys.exit(main())
