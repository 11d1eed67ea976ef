"""`drsplat synth OUT_DIR --preset NAME --seed S`: a synthetic dataset with exact ground truth."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from drsplat.errors import DrsplatError

log = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    from drsplat.synthetic import PRESETS

    p = subparsers.add_parser(
        "synth",
        help="write a synthetic scene with exact ground truth and oracle LangSplat features",
        description="Write a synthetic 3DGS dataset: scene.ply, transforms.json, rendered images, ground-truth "
        "masks and labels, oracle LangSplat feature files and oracle text embeddings (docs/registration.md).",
    )
    p.add_argument("out_dir", type=Path, help="output folder (created)")
    p.add_argument("--preset", default="tiny", choices=sorted(PRESETS), help="scene: tiny, small, demo (a table), or a hard room hard-* (docs/evaluation.md) (default: tiny)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    p.add_argument("--mislabel", type=float, default=None, metavar="FRACTION",
                   help="fraction of masks given a wrong label's embedding (default: the preset's, 0 except hard-noisy)")
    p.add_argument("--noise", type=float, default=0.15, help="norm of the random part of each mask embedding (default: 0.15)")
    p.add_argument("--jitter", type=int, default=None, metavar="PIXELS",
                   help="mask boundaries wander by up to this many pixels (default: the preset's, 0 except hard-noisy/hard-room)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from drsplat.synthetic import write_dataset

    if args.mislabel is not None and not 0.0 <= args.mislabel <= 1.0:
        raise DrsplatError(f"--mislabel must be between 0 and 1, got {args.mislabel}")
    if args.noise < 0 or (args.jitter is not None and args.jitter < 0):
        raise DrsplatError("--noise and --jitter must not be negative")
    out = write_dataset(args.out_dir, args.preset, args.seed, mislabel_fraction=args.mislabel, noise=args.noise,
                        jitter=args.jitter, show_progress=not args.no_progress)
    log.info("synthetic dataset written to %s", out)
    return 0
