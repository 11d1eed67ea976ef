"""`drsplat synth OUT_DIR --preset NAME --seed S`: a synthetic dataset with exact ground truth."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from drsplat.commands.common import float_range, int_range, seed_int
from drsplat.defaults import ORACLE_LABEL_NAMES, ORACLE_TEXT_EMBEDDINGS
from drsplat.errors import OutputError, UsageError, shown_path

log = logging.getLogger(__name__)

MAX_NOISE = 1000.0  # far past noise that hides the label (norm 1); 1e30 overflowed float32 into all-zero embeddings

MAX_JITTER = 64  # pixels
# what `drsplat synth` writes at the top of its folder (every preset): anything else there is the user's
SYNTH_ENTRIES = frozenset({"scene.ply", "transforms.json", ORACLE_TEXT_EMBEDDINGS, Path(ORACLE_LABEL_NAMES).parts[0], "features", "images"})


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    from drsplat.synthetic import CITY_PRESETS, MASK_SOURCES, MAX_WIDTH, MIN_WIDTH, PRESETS

    p = subparsers.add_parser(
        "synth",
        help="write a synthetic scene with exact ground truth and oracle LangSplat features",
        description="Write a synthetic 3DGS dataset: scene.ply, transforms.json, rendered images, ground-truth "
        "masks and labels, oracle LangSplat feature files and oracle text embeddings (docs/registration.md). "
        "The folder is built beside OUT_DIR and renamed into place at the end, so an interrupted run leaves nothing.",
    )
    p.add_argument("out_dir", type=Path, help="output folder (created; an earlier synthetic dataset there is replaced)")
    p.add_argument("--preset", default="tiny", choices=sorted(PRESETS) + sorted(CITY_PRESETS),
                   help="scene: tiny, small, demo (a table), a hard room hard-* (docs/registration.md), or city (16 small rooms on a grid, "
                        "96 views that each see about one room: the scale path of `drsplat bench scale`) (default: tiny)")
    p.add_argument("--seed", type=seed_int, default=0, help="random seed, 0..2^32-1 (default: 0)")
    p.add_argument("--mislabel", type=float_range(0.0, 1.0), default=None, metavar="FRACTION",
                   help="fraction of masks given a wrong label's embedding (default: the preset's, 0 except hard-noisy)")
    p.add_argument("--noise", type=float_range(0.0, MAX_NOISE), default=0.15,
                   help=f"norm of the random part of each mask embedding, at most {MAX_NOISE:g} (default: 0.15; the label part's norm is 0.8, the part common to all masks 1)")
    p.add_argument("--jitter", type=int_range(0, MAX_JITTER), default=None, metavar="PIXELS",
                   help="mask boundaries wander by up to this many pixels (default: the preset's, 0 except hard-noisy and hard-room)")
    p.add_argument("--merge", type=float_range(0.0, 1.0), default=0.0, metavar="FRACTION",
                   help="under-segmentation: fraction of instance masks swallowed by the neighbour they touch most, the union "
                        "carrying the neighbour's embedding (default: 0)")
    p.add_argument("--split", type=float_range(0.0, 1.0), default=0.0, metavar="FRACTION",
                   help="over-segmentation: fraction of instance masks cut in two across their long axis, each half embedded "
                        "as a part of its object (default: 0)")
    p.add_argument("--mask-source", choices=MASK_SOURCES, default=None,
                   help="oracle masks from the rendered Gaussians' weighted vote (render), ray-cast true silhouettes "
                        "(geometry), or a segmenter's superpixels of each rendered view labelled by the instance under most "
                        "of them (segmenter; no --jitter, --merge or --split) (default: the preset's, render except hard-silhouette)")
    p.add_argument("--width", type=int_range(MIN_WIDTH, MAX_WIDTH), default=None, metavar="PIXELS",
                   help="render the views this many pixels wide: the preset's cameras scaled, same poses (default: the preset's, "
                        "e.g. 320 for hard-room; not for city)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def is_synthetic_dataset(folder: Path) -> bool:
    """Whether `folder` holds an earlier `drsplat synth` output (safe to replace)."""
    return (folder / "scene.ply").is_file() and (folder / ORACLE_LABEL_NAMES).is_file() and (folder / ORACLE_TEXT_EMBEDDINGS).is_file()


def replaceable_dataset(folder: Path) -> bool:
    """`atomic_folder`'s test: whether `folder` holds an earlier synthetic dataset and nothing else.
    OutputError naming the entries synth never writes when it also holds some (a registered PLY,
    notes: the README's own steps put `registered.ply` there), which replacing it would delete."""
    if not is_synthetic_dataset(folder):
        return False
    foreign = sorted(p.name for p in folder.iterdir() if p.name not in SYNTH_ENTRIES)
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
        raise OutputError(folder, f"it holds an earlier synthetic dataset and also {shown}, which synth did not write and would "
                                  "delete with the folder; move them out or choose another folder")
    return True


def run(args: argparse.Namespace) -> int:
    from drsplat.synthetic import CITY_PRESETS, segmenter_corruption_error, write_city, write_dataset
    from drsplat.utils import CancelToken, atomic_folder, cancel_on_signals

    if args.preset in CITY_PRESETS and args.width is not None:
        raise UsageError("--width is for the room and table presets; city views are sized by the city preset")
    refused = segmenter_corruption_error(args.mask_source, args.jitter, args.merge, args.split)
    if refused:
        raise UsageError(f"--mask-source segmenter takes no --jitter, --merge or --split: {refused}")
    token = CancelToken()
    with cancel_on_signals(token, "the current view"), atomic_folder(args.out_dir, replaceable_dataset) as tmp:
        if args.preset in CITY_PRESETS:
            write_city(tmp, args.preset, args.seed, show_progress=not args.no_progress, cancel=token)
        else:
            write_dataset(tmp, args.preset, args.seed, mislabel_fraction=args.mislabel, noise=args.noise, jitter=args.jitter,
                          mask_source=args.mask_source, merge_fraction=args.merge, split_fraction=args.split, width=args.width, show_progress=not args.no_progress,
                          cancel=token)
        token.raise_if_cancelled()
    log.info("synthetic dataset written to %s", shown_path(args.out_dir))
    return 0
