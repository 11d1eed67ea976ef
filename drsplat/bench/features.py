"""`drsplat bench features`: seconds per image of each feature-extraction stage, per mask generator.

CLIP (ViT-B-16) and SAM (vit_b by default) run at their real size with *random weights*: no real
weights can be installed here, and the arithmetic, hence the time, of a forward pass does not
depend on the weights. What does depend on them is how many masks SAM keeps: random weights rarely
pass LangSplat's quality thresholds, so the SAM row's later stages see few masks; the per-mask
costs of cropping and CLIP (second table) give the time for any mask count.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from drsplat.bench.common import choice_list, format_table, int_list, machine_line
from drsplat.commands.common import int_range, positive_int, resolution_value
from drsplat.errors import InputError, shown_path

DEFAULT_SOURCE = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "fern"
GENERATORS = ("sam", "felzenszwalb", "slic")
MAX_MASKS = 1000  # masks per NMS timing: k full-image masks and their float64 ellipse tests (12 MB each at 1440x1080) are in memory at once
MAX_POINTS_PER_SIDE = 256  # SAM prompt grid (LangSplat 32): 65,536 prompts per crop
MAX_CROP_LAYERS = 4  # SAM crop layers (LangSplat 1): 4^layers crops at the last
mask_count = int_range(1, MAX_MASKS)


def add_bench(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("features", help="seconds per image for masks, post-processing, cropping and CLIP, per mask generator (CPU)")
    p.add_argument("--source", type=Path, default=DEFAULT_SOURCE, help="dataset (default ../shared/data/fern)")
    p.add_argument("--images", type=positive_int, default=2, help="images timed per generator (median reported)")
    p.add_argument("--generators", type=choice_list(GENERATORS, "mask generator"), default=",".join(GENERATORS),
                   help=f"comma-separated mask generators among {', '.join(GENERATORS)} (default: all)")
    p.add_argument("--sam-model", choices=("vit_b", "vit_l", "vit_h"), default="vit_b", help="SAM size (random weights)")
    p.add_argument("--sam-points-per-side", type=int_range(1, MAX_POINTS_PER_SIDE), default=32,
                   help=f"SAM prompt grid, 1..{MAX_POINTS_PER_SIDE} (LangSplat 32)")
    p.add_argument("--sam-crop-layers", type=int_range(0, MAX_CROP_LAYERS), default=1, help=f"SAM crop layers, 0..{MAX_CROP_LAYERS} (LangSplat 1)")
    p.add_argument("--sam-images", type=positive_int, default=1, help="images timed for SAM (slow on a CPU)")
    p.add_argument("--resolution", type=resolution_value, default=-1, help="image scale as `drsplat features --resolution`")
    p.add_argument("--nms-masks", type=int_list(mask_count), default="50,100,200",
                   help=f"mask counts for the post-processing table, each 1..{MAX_MASKS} (default: 50,100,200)")
    p.add_argument("--loop-masks", type=mask_count, default=40, help=f"mask count at which LangSplat's double loop is timed, 1..{MAX_MASKS} (default: 40)")
    p.set_defaults(func=run)


def _median(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def _stage_rows(args, cameras, encoder) -> tuple[list[list[object]], list[float], list[float]]:
    import torch

    from drsplat.cameras import load_image
    from drsplat.features.extract import extract_image
    from drsplat.features.masks.sam import (
        SAM_ARCHITECTURES,
        SamGenerator,
        SamParams,
        build_sam,
    )
    from drsplat.features.masks.superpixel import FelzenszwalbGenerator, SlicGenerator

    rows, crop_per_mask, clip_per_mask = [], [], []
    for name in args.generators:
        if name == "sam":
            torch.manual_seed(0)
            sam = build_sam(SAM_ARCHITECTURES[args.sam_model])
            generator = SamGenerator(sam, SamParams(points_per_side=args.sam_points_per_side, crop_n_layers=args.sam_crop_layers))
            label = f"sam {args.sam_model} (random weights, {args.sam_points_per_side}² points, {args.sam_crop_layers} crop layer)"
            n_images = args.sam_images
        elif name == "felzenszwalb":
            generator, label, n_images = FelzenszwalbGenerator(), "felzenszwalb", args.images
        else:  # slic (--generators' type admits only GENERATORS)
            generator, label, n_images = SlicGenerator(), "slic", args.images
        _warm_up(generator, name)
        times, counts = [], []
        for cam in cameras[:n_images]:
            _, _, t, per_level = extract_image(load_image(cam), generator, encoder)
            times.append(t)
            counts.append(sum(per_level))
            if sum(per_level):
                crop_per_mask.append(t.crop / sum(per_level))
                clip_per_mask.append(t.clip / sum(per_level))
        print(f"  timed {label}: {len(times)} image(s), {_median(counts):g} masks/img, {_median([t.total for t in times]):.1f} s/img", flush=True)
        rows.append([
            label, len(times), _median(counts),
            _median([t.masks for t in times]), _median([t.postprocess for t in times]),
            _median([t.crop for t in times]), _median([t.clip for t in times]), _median([t.total for t in times]),
        ])
    return rows, crop_per_mask, clip_per_mask


def _warm_up(generator, name: str) -> None:
    """Imports, numba kernel loading and first-call allocations happen outside the timing."""
    from drsplat.features.masks.postprocess import masks_update

    image = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    levels = generator.generate(image) if name != "sam" else None
    if levels is not None:
        masks_update(levels)
    else:
        masks_update([_as_maskset(_overlapping_masks(4, 48, 64, np.random.default_rng(1)))])


def _as_maskset(masks: np.ndarray):
    from drsplat.features.masks import MaskSet

    return MaskSet(masks, np.ones(len(masks), np.float32))


def _overlapping_masks(k: int, height: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """k random ellipses (2-30 % of the image side), nested and overlapping like SAM's levels."""
    yy, xx = np.mgrid[:height, :width]
    cy, cx = rng.uniform(0, height, k), rng.uniform(0, width, k)
    ry, rx = rng.uniform(0.02, 0.3, k) * height, rng.uniform(0.02, 0.3, k) * width
    return ((yy - cy[:, None, None]) / ry[:, None, None]) ** 2 + ((xx - cx[:, None, None]) / rx[:, None, None]) ** 2 < 1


def _nms_rows(args) -> list[list[object]]:
    from drsplat.features.masks.postprocess import mask_nms, mask_nms_reference

    rng = np.random.default_rng(0)
    rows = []
    counts = args.nms_masks
    for height, width in ((378, 504), (1080, 1440)):
        loop_masks = _overlapping_masks(args.loop_masks, height, width, rng)
        scores = rng.uniform(0.6, 1.0, args.loop_masks)
        mask_nms(loop_masks[:2], scores[:2])  # compile / load the kernel outside the timing
        t0 = time.perf_counter()
        fast_kept = mask_nms(loop_masks, scores)
        t_fast = time.perf_counter() - t0
        t0 = time.perf_counter()
        loop_kept = mask_nms_reference(loop_masks, scores)
        t_loop = time.perf_counter() - t0
        same = "yes" if np.array_equal(fast_kept, loop_kept) else "NO"
        rows.append([f"{width}x{height}", args.loop_masks, t_fast, t_loop, t_loop / t_fast, same])
        for k in counts:
            masks = _overlapping_masks(k, height, width, rng)
            s = rng.uniform(0.6, 1.0, k)
            t0 = time.perf_counter()
            mask_nms(masks, s)
            rows.append([f"{width}x{height}", k, time.perf_counter() - t0, "", "", ""])
    return rows


def run(args: argparse.Namespace) -> int:
    from drsplat.features.clip import ClipEncoder
    from drsplat.features.extract import feature_cameras

    if not args.source.exists():
        raise InputError(args.source, "does not exist (the default needs ../shared/data beside the project; pass --source)")
    cameras = feature_cameras(args.source, args.resolution)
    encoder = ClipEncoder.random("ViT-B-16", device="cpu")
    cam = cameras[0]
    print(f"{shown_path(args.source.name)}: {len(cameras)} images, features at {cam.width}x{cam.height}; CPU; CLIP ViT-B-16 and SAM with random weights")
    rows, crop_pm, clip_pm = _stage_rows(args, cameras, encoder)
    print("\nseconds per image (median over the images timed)")
    print(format_table(["mask generator", "images", "masks/img", "mask generation", "post-processing", "cropping", "CLIP", "total"], rows))
    print("\nper-mask cost (median over the images above): multiply by the mask count (LangSplat/SAM: ~100-300 over 4 levels)")
    print(format_table(["stage", "ms per mask"], [["cropping (224 px)", _median(crop_pm) * 1e3], ["CLIP ViT-B-16 image", _median(clip_pm) * 1e3]]))
    print("\nLangSplat post-processing (masks_update): vectorised numba kernel vs LangSplat's double loop, same kept masks")
    print(format_table(["image", "masks", "vectorised s", "loop s", "loop / vectorised", "same result"], _nms_rows(args)))
    print(machine_line())
    return 0
