"""`drsplat register SCENE.ply --source DATASET --features FEATURES --out REGISTERED.ply`."""

from __future__ import annotations

import argparse
import contextlib
import logging
import signal
import threading
from collections.abc import Iterator
from pathlib import Path

from drsplat.defaults import AGGREGATE_MODES, DEFAULT_AGGREGATE, DEFAULT_CODEBOOK, DEFAULT_LEVEL, DEFAULT_TOPK
from drsplat.utils import CancelToken

log = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "register",
        help="lift per-mask language embeddings onto the Gaussians (training-free registration)",
        description="Rasterize every training view, keep the top-k Gaussians of each pixel, accumulate their "
        "weights into (Gaussian, mask) pairs and give each Gaussian the weight-averaged mask embedding. "
        "Writes an INRIA-layout PLY with the language field as extra properties (docs/registration.md). "
        "Ctrl-C stops at the end of the current view and keeps a checkpoint; the same command resumes.",
    )
    p.add_argument("scene", type=Path, metavar="SCENE.ply", help="trained 3DGS scene (PLY)")
    p.add_argument("--source", type=Path, required=True, help="dataset folder: COLMAP (sparse/0) or transforms.json")
    p.add_argument("--features", type=Path, required=True, help="LangSplat feature folder (<stem>_s.npy, <stem>_f.npy)")
    p.add_argument("--level", type=int, default=DEFAULT_LEVEL, help=f"mask level of the feature files (default: {DEFAULT_LEVEL}, LangSplat's 's')")
    p.add_argument("--topk", type=int, default=DEFAULT_TOPK, help=f"Gaussians kept per pixel (default: {DEFAULT_TOPK})")
    p.add_argument("--codebook", default=DEFAULT_CODEBOOK,
                   help="'none' (exact float16 features), 'scene' (PQ trained on this scene) or a faiss codebook file")
    p.add_argument("--aggregate", choices=AGGREGATE_MODES, default=DEFAULT_AGGREGATE,
                   help="how pixel weights become Gaussian features: paper (Dr. Splat's weighted mean), core / ellipse "
                   "(weight by the Gaussian's own falloff / only its 2-sigma ellipse), responsibility (w / pixel sum), "
                   "*-reject (also leave floaters unassigned); see docs/registration.md (default: %(default)s)")
    p.add_argument("--keep-unassigned", action="store_true",
                   help="keep Gaussians that got no weight (lang_weight 0) instead of pruning them")
    p.add_argument("--resolution", type=float, default=-1,
                   help="camera resolution as 3DGS's -r: 1, 2, 4, 8 divide, another number is a width in pixels; "
                   "default -1: full size, capped at 1600 px wide")
    p.add_argument("--out", type=Path, required=True, metavar="REGISTERED.ply", help="registered PLY to write")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


@contextlib.contextmanager
def cancel_on_sigint(token: CancelToken) -> Iterator[None]:
    """First Ctrl-C cancels cleanly at the end of the current view; a second one interrupts."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGINT)

    def handler(signum, frame):
        if token.cancelled:
            raise KeyboardInterrupt
        log.warning("stopping after the current view (Ctrl-C again to abort at once)")
        token.cancel()

    signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)



def run(args: argparse.Namespace) -> int:
    from drsplat.cameras import load_cameras, resolution_scale
    from drsplat.errors import DrsplatError
    from drsplat.pipeline import RegisterOptions, register_to_ply
    from drsplat.scene import load_ply

    if args.topk < 1:
        raise DrsplatError(f"--topk must be at least 1, got {args.topk}")
    try:
        resolution_scale(1000, args.resolution)
    except ValueError as exc:
        raise DrsplatError(f"--resolution: {exc}") from exc
    scene = load_ply(args.scene)
    cameras = load_cameras(args.source, resolution=args.resolution, require_images=False)
    options = RegisterOptions(topk=args.topk, level=args.level, codebook=args.codebook, keep_unassigned=args.keep_unassigned,
                              aggregate=args.aggregate)
    token = CancelToken()
    with cancel_on_sigint(token):
        register_to_ply(scene, cameras, args.features, args.out, options, show_progress=not args.no_progress, cancel=token)
    return 0
