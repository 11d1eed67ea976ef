"""`drsplat register SCENE.ply --source DATASET --features FEATURES --out REGISTERED.ply`."""

from __future__ import annotations

import argparse
import contextlib
import logging
import signal
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np

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
    p.add_argument("--level", type=int, default=1, help="mask level of the feature files (default: 1, LangSplat's 's')")
    p.add_argument("--topk", type=int, default=40, help="Gaussians kept per pixel (default: 40)")
    p.add_argument("--codebook", default="none",
                   help="'none' (exact float16 features), 'scene' (PQ trained on this scene) or a faiss codebook file")
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


def clip_model_name(manifest: dict) -> str:
    """The features' CLIP model id from manifest.json: `clip_model_id`, else 'model/pretrained'
    from `clip`; 'unknown' without a manifest (e.g. features made by LangSplat)."""
    model_id = manifest.get("clip_model_id")
    if isinstance(model_id, str) and model_id:
        return model_id
    clip = manifest.get("clip")
    if isinstance(clip, dict):
        model, tag = clip.get("model"), clip.get("pretrained")
        if model:
            return f"{model}/{tag}" if tag else str(model)
    if isinstance(clip, str) and clip:
        return clip
    return "unknown"


def checkpoint_path_for(out: Path) -> Path:
    return out.with_name(f".{out.name}.register.npz")


def run(args: argparse.Namespace) -> int:
    from drsplat.cameras import load_cameras
    from drsplat.featurefiles import read_manifest
    from drsplat.index import attach_field, build_field
    from drsplat.registration import register_scene
    from drsplat.scene import load_ply, save_ply

    from drsplat.cameras import resolution_scale
    from drsplat.errors import DrsplatError

    if args.topk < 1:
        raise DrsplatError(f"--topk must be at least 1, got {args.topk}")
    try:
        resolution_scale(1000, args.resolution)
    except ValueError as exc:
        raise DrsplatError(f"--resolution: {exc}") from exc
    scene = load_ply(args.scene)
    cameras = load_cameras(args.source, resolution=args.resolution, require_images=False)
    manifest = read_manifest(args.features)
    clip_model = clip_model_name(manifest)
    ckpt = checkpoint_path_for(args.out)
    token = CancelToken()
    with cancel_on_sigint(token):
        result = register_scene(
            scene, cameras, args.features, topk=args.topk, level=args.level, show_progress=not args.no_progress,
            cancel=token, checkpoint=ckpt, keep_checkpoint=True, collect_embeddings=args.codebook == "scene",
        )
        keep = np.ones(scene.num_gaussians, bool) if args.keep_unassigned else result.assigned
        field = build_field(result.features[keep], result.weights[keep], codebook=args.codebook, clip_model=clip_model,
                            train_embeddings=result.mask_embeddings)
        out_scene = attach_field(scene.subset(keep), field, args.out)
        save_ply(out_scene, args.out)
    ckpt.unlink(missing_ok=True)
    unassigned = scene.num_gaussians - result.num_assigned
    log.info(
        "%s: %d Gaussians (%d unassigned, %s), %s field, %d views, %.1f s",
        args.out, out_scene.num_gaussians, unassigned, "kept with lang_weight 0" if args.keep_unassigned else "pruned",
        field.kind, result.num_views, result.seconds,
    )
    return 0
