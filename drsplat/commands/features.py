"""`drsplat features --source DATASET --out FEATURES`: per-image masks and CLIP embeddings."""

from __future__ import annotations

import argparse
import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path

from drsplat.commands.common import int_range, nonneg_int, ray_address, resolution_value, text_value
from drsplat.errors import INTERRUPTED_NOTE, RESUMABLE_NOTE, DrsplatError, InputError, OutputError, shown_path
from drsplat.features.masks import GENERATORS
from drsplat.features.modelid import DEFAULT_MODEL, DEFAULT_PRETRAINED
from drsplat.features.weights import SAM_URLS

log = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "features",
        help="make LangSplat-format features (masks + OpenCLIP embeddings) for every training image",
        description=(
            "Segment every training image (SAM, or the weight-free felzenszwalb/slic superpixels), "
            "embed each mask crop with OpenCLIP and write <stem>_s.npy / <stem>_f.npy into --out. "
            "Resumable: complete pairs already in --out are skipped."
        ),
    )
    p.add_argument("--source", type=Path, required=True, metavar="DATASET_DIR", help="dataset folder (COLMAP sparse/0, transforms.json or cameras.json, with images)")
    p.add_argument("--out", type=Path, required=True, metavar="FEATURES_DIR", help="features folder to write (created if needed)")
    p.add_argument("--masks", choices=tuple(GENERATORS), default="sam",
                   help="mask generator: SAM (default, needs weights) or weight-free superpixels (fast on CPU, lower quality)")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto", help="where CLIP and SAM run (fp16 on CUDA, fp32 on CPU)")
    p.add_argument("--clip-model", type=text_value, default=None, metavar="NAME",
                   help=f"open_clip architecture (default {DEFAULT_MODEL}, or the one model --clip-config registers)")
    p.add_argument("--pretrained", type=text_value, default=None, metavar="TAG",
                   help=f"open_clip pretrained tag (default {DEFAULT_PRETRAINED}); with --clip-checkpoint it names the weights the file holds, and so how its crops are normalised")
    p.add_argument("--clip-checkpoint", type=Path, default=None, metavar="PATH", help="local open_clip weights file (no download)")
    p.add_argument("--clip-config", type=Path, default=None, metavar="JSON",
                   help="open_clip model config file, for an architecture open_clip does not ship (named by --clip-model)")
    p.add_argument("--sam-checkpoint", type=Path, default=None, metavar="PATH", help="local SAM checkpoint (vit_b/l/h, read from the file); no download")
    p.add_argument("--sam-model", choices=tuple(SAM_URLS), default=None,
                   help="official SAM weights to download into ~/.cache/drsplat when no --sam-checkpoint is given (default vit_h, as LangSplat)")
    p.add_argument("--sam-points-per-side", type=int_range(1, 256), default=None, metavar="N",
                   help="SAM prompt grid per side (LangSplat 32; fewer is faster on a CPU, with fewer small masks)")
    p.add_argument("--sam-crop-layers", type=int_range(0, 4), default=None, metavar="N",
                   help="SAM crop layers (LangSplat 1: the image plus 4 overlapping crops; 0 is ~5x faster)")
    p.add_argument("--resolution", type=resolution_value, default=-1, metavar="R",
                   help="image scale as 3DGS -r: -1 full size capped at 1600 px wide, 1/2/4/8 divide, other values a target width")
    p.add_argument("--max-height", type=nonneg_int, default=1080, metavar="ROWS", help="LangSplat's cap on image rows (0 = none; default 1080)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (as register and synth; batch logs)")
    p.add_argument("--batch-size", type=int_range(1, 4096), default=64, metavar="N", help="CLIP crops per batch")
    p.add_argument("--ray", nargs="?", type=ray_address, const="local", default=None, metavar="ADDRESS",
                   help="spread images over Ray workers (pip install 'drsplat[ray]'), one model load per worker: ADDRESS of a "
                   "running cluster (host:port or 'auto'), or no value to start a local one. With --device cuda each worker "
                   "requests one GPU. Same files, resumable")
    p.add_argument("--ray-workers", type=int_range(1, 4096), default=None, metavar="N", help="Ray workers (default: the cluster's CPUs)")
    p.set_defaults(func=run, interrupted_note=interrupted_note)


def interrupted_note(args: argparse.Namespace, exc: BaseException | None = None) -> str:
    """What an interrupted run's last line adds: that the same command resumes, when the output
    folder holds finished images (pairs are written atomically: only whole ones are there)."""
    kept = finished_images(args.out) > 0
    return RESUMABLE_NOTE if kept else f"{INTERRUPTED_NOTE}; no image was finished"


def finished_images(out: Path) -> int:
    """How many images' pairs the features folder `out` holds (pairs are written atomically: only whole ones are there)."""
    from drsplat.features.format import FEAT_SUFFIX

    return sum(1 for _ in out.glob(f"*{FEAT_SUFFIX}")) if out.is_dir() else 0


@contextlib.contextmanager
def finished_images_said(out: Path, cameras) -> Iterator[None]:
    """An image that stops the extraction (unreadable, or not its camera's aspect) says, as an interrupt's line does,
    that the images finished before it are kept and the same command resumes from them (round 100c F3: only the
    file's error was said, though with SAM on a CPU each finished image is minutes of work). Other errors (a folder
    of another model's features, which no rerun resumes) are left as they are."""
    images = {cam.image_path for cam in cameras if cam.image_path is not None}
    try:
        yield
    except InputError as exc:
        kept = other_images_kept(out, cameras, exc.path) if exc.path in images else 0
        if not kept:
            raise
        raise DrsplatError(f"{exc}; the features of {kept:,} other image{'s' if kept != 1 else ''} are kept in {shown_path(out)}, and "
                           "the same command resumes from them") from exc


def other_images_kept(out: Path, cameras, failed: Path) -> int:
    """The images of `cameras`, other than the one at `failed`, whose pairs in `out` are whole (round 104a F4: every
    *_f.npy was counted as an image "finished before" the failing one, its own stale pair, half-written ones and
    those of other runs' images too)."""
    from drsplat.features.format import is_valid_pair

    if not out.is_dir():
        return 0
    return sum(1 for cam in cameras if cam.image_path is not None and cam.image_path != failed and is_valid_pair(out, cam.name))


def refuse_image_folder(out: Path, cameras) -> None:
    """OutputError when `out` is a folder holding the cameras' images: feature files and a manifest
    among the photographs would mix outputs into an input folder (checked before any model loads)."""
    target = out.resolve()
    folders = {cam.image_path.resolve().parent for cam in cameras if cam.image_path is not None}
    if target in folders:
        raise OutputError(out, "--out is the folder of the training images; write the features to a folder of their own "
                          "(e.g. SOURCE/language_features)")


SAM_TUNING = ("sam_model", "sam_points_per_side", "sam_crop_layers")  # flags whose defaults (LangSplat's) are ModelSpec's


def given_sam_tuning(args: argparse.Namespace) -> dict:
    """The SAM flags given (their defaults are `ModelSpec`'s, so they are said once), after one warning naming those given
    with another --masks (round 87c F5: taken without a word)."""
    given = {name: getattr(args, name) for name in SAM_TUNING if getattr(args, name) is not None}
    flags = [f"--{name.replace('_', '-')}" for name in ("sam_checkpoint", *given) if getattr(args, name) is not None]
    if flags and args.masks != "sam":
        log.warning("%s %s to --masks sam; --masks %s does not read %s", ", ".join(flags), "applies" if len(flags) == 1 else "apply",
                    args.masks, "it" if len(flags) == 1 else "them")
    return given


def run(args: argparse.Namespace) -> int:
    from drsplat.features.clip import model_for_config
    from drsplat.features.extract import ModelSpec, build_models, extract_features, feature_cameras, make_manifest

    if args.out.exists() and not args.out.is_dir():
        raise OutputError(args.out, "--out must be a features folder, but a file has that name")

    cameras = feature_cameras(args.source, args.resolution, args.max_height or None)
    refuse_image_folder(args.out, cameras)
    spec = ModelSpec(
        masks=args.masks, clip_model=model_for_config(args.clip_model, args.clip_config), pretrained=args.pretrained, clip_checkpoint=args.clip_checkpoint,
        sam_checkpoint=args.sam_checkpoint, **given_sam_tuning(args), device=args.device, batch_size=args.batch_size, clip_config=args.clip_config,
    )
    extra = {"source": str(args.source.resolve()), "sam_checkpoint": str(Path(args.sam_checkpoint).resolve()) if args.masks == "sam" and args.sam_checkpoint else
             ("" if args.masks == "sam" else None)}
    if args.ray is not None:
        from drsplat.features.ray import extract_features_ray

        log.info("%d images from %s; masks %s; CLIP %s on Ray workers", len(cameras), args.source, args.masks, spec.clip_model)
        with finished_images_said(args.out, cameras):
            report = extract_features_ray(cameras, args.out, spec, address=args.ray, workers=args.ray_workers, resolution=args.resolution,
                                          max_height=args.max_height or None, manifest_extra=extra, show_progress=not args.no_progress)
    else:
        generator, encoder = build_models(spec)
        manifest = make_manifest(generator, encoder, spec.nms, args.resolution, args.max_height or None, extra)
        log.info("%d images from %s; masks %s; CLIP %s on %s", len(cameras), args.source, args.masks, encoder.model_id, encoder.device)
        with finished_images_said(args.out, cameras):
            report = extract_features(cameras, args.out, generator, encoder, spec.nms, manifest, show_progress=not args.no_progress)
    n = len(report.written)
    per = report.times
    log.info(  # the masks counted are those of the images written now (round 57c: a complete folder's rerun read as "no masks")
        "wrote %d image(s), skipped %d already complete, redid %d incomplete%s",
        n, len(report.skipped), len(report.redone), f"; masks per level (default/s/m/l) of the images written: {report.masks_per_level}" if n else "",
    )
    if n:
        log.info("seconds per image: masks %.2f, post-processing %.2f, cropping %.2f, CLIP %.2f (total %.2f)",
                 per.masks / n, per.postprocess / n, per.crop / n, per.clip / n, per.total / n)
    if report.nonfinite_embeddings:
        log.warning("%d non-finite embeddings were dropped", report.nonfinite_embeddings)
    for note in report.notes():
        log.warning("%s", note)
    return 0
