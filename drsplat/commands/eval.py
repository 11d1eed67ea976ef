"""`drsplat eval`: the paper's evaluation protocols on a registered scene, and its ablations.

    drsplat eval iou REGISTERED.ply --gt-labels labels.npy --label-names names.json --text-embeddings T.npy
    drsplat eval iou REGISTERED.ply --gt-points cloud.labels.ply ...        (pseudo ground truth on the fly)
    drsplat eval scannet REGISTERED.ply --scene-dir scans/scene0000_00 [--classes wall,floor,...]
    drsplat eval pseudolabels SCENE.ply --points cloud.labels.ply --out labels.npy
    drsplat eval lerf REGISTERED.ply --source lerf_ovs/figurines --annotations lerf_ovs/label/figurines
    drsplat eval ablate topk|pq|robustness|metrics|aggregate [--preset tiny] --out-dir DIR
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path

import numpy as np

from drsplat.cameras import folded_name, spelling_difference
from drsplat.commands.common import (add_near_plane_argument, add_principal_point_argument, check_npy_name, float_range, guard_args, guard_field_codebook, int_range, json_output_file,
                                     output_file, refuse_repeats, shown_number, table_stream, threshold_value)
from drsplat.defaults import (DEFAULT_TOPK, LANGSPLAT_MASK_THRESHOLD, LERF_ALPHA_LIMIT, LERF_ALPHA_THRESHOLD, NEAR, ORACLE_LABEL_NAMES,
                              ORACLE_TEXT_EMBEDDINGS, VOXEL_EMPTY, VOXEL_RESOLUTION)
from drsplat.errors import DrsplatError, InputError, UsageError, shown_path
from drsplat.eval.datasets import load_gt_labels, load_label_names
from drsplat.scene import counted
from drsplat.utils import CancelToken, cancel_on_signals, check_outputs_writable, json_text, outputs_together

log = logging.getLogger(__name__)

WEIGHTINGS = ("volume", "count", "voxel")
# the Mahalanobis radius of a vote: a point at r = 40 weighs exp(-800) = 0 in float64, so a larger radius adds no
# Gaussian vote's weight, only neighbour-search work (every point near every Gaussian at 1e308); such a point still
# counts as a voter, whose label a Gaussian with no nearer one takes (round 69c F1)
MAX_RADIUS = 40.0
MIN_TAU_STEP = 1e-6  # the grid is printed and compared rounded to 6 decimals: a finer step would repeat thresholds


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "eval",
        help="evaluate a registered scene: volume-aware / count / voxel 3D IoU, pseudo-labels, LERF-OVS 2D, ablations",
        description="Evaluation protocols of Dr. Splat (volume-aware 3D IoU) and OpenGaussian (count IoU, LERF-OVS 2D "
                    "object selection), a voxel IoU, ScanNet pseudo ground truth, and the paper's ablations on synthetic scenes.",
    )
    sub = parser.add_subparsers(dest="eval_command", metavar="PROTOCOL", required=True)
    _add_iou(sub)
    _add_scannet(sub)
    _add_pseudolabels(sub)
    _add_lerf(sub)
    from drsplat.eval.ablations import add_ablate_parser

    add_ablate_parser(sub)


# ---------------------------------------------------------------------------------------------- arguments


def _add_query_arguments(parser: argparse.ArgumentParser, names_help: str) -> None:
    from drsplat.commands.common import add_clip_arguments

    q = parser.add_argument_group("label queries")
    q.add_argument("--label-names", type=Path, metavar="NAMES.json", help=names_help)
    q.add_argument("--text-embeddings", type=Path, metavar="T.npy", help="(L, D) query embedding per label, in label order (else the labels' names go through CLIP)")
    q.add_argument("--relevancy", action="store_true", help="score by LERF relevancy instead of cosine")
    q.add_argument("--negative-embeddings", type=Path, metavar="N.npy", help="(C, D) negatives for --relevancy without a text encoder")
    add_clip_arguments(parser)


def _add_task_arguments(parser: argparse.ArgumentParser) -> None:
    t = parser.add_argument_group("metrics")
    t.add_argument("--task", choices=("loc", "seg", "both"), default="both", help="localisation (global threshold), segmentation (argmax), or both")
    t.add_argument("--argmax-over", choices=("queried", "present"), default=None,
                   help="segmentation's argmax over every queried label (default; OpenGaussian's protocol: a label absent from "
                        "the ground truth can win a Gaussian, a miss) or only over the labels the ground truth holds (easier; "
                        "drsplat's rule until 2026-12-07); the means are over the present labels either way")
    t.add_argument("--weighting", default="volume,count", metavar="LIST",
                   help="comma-separated subset of volume (Dr. Splat), count (OpenGaussian), voxel; default volume,count")
    t.add_argument("--taus", default="0:1:0.01", metavar="START:STOP:STEP", help="localisation threshold grid (inclusive)")
    t.add_argument("--voxel-resolution", type=int_range(1, 2048), default=None,
                   help=f"voxels along the longest side of the labelled region (default {VOXEL_RESOLUTION}; --weighting voxel)")
    t.add_argument("--voxel-empty", type=float_range(0.0, None), default=None,
                   help=f"α-mass below which a voxel is empty (default {VOXEL_EMPTY}; --weighting voxel)")
    t.add_argument("--curve", action="store_true", help="print the whole localisation grid search")
    t.add_argument("--json", type=json_output_file, metavar="OUT.json", help="also write the full report (per label, curves) as JSON")
    t.add_argument("--original", type=Path, metavar="SCENE.ply",
                   help="the unregistered scene: evaluate on all its Gaussians (those pruned by registration score 0) "
                        "instead of only the registered ones; ground-truth labels then index the original scene")


def _add_iou(sub) -> None:
    p = sub.add_parser("iou", help="3D IoU (volume-aware, count, voxel) for localisation and segmentation",
                       description="3D IoU of the language field's answers against per-Gaussian ground truth labels, or "
                                   "against a labelled point cloud turned into pseudo-labels.")
    p.add_argument("registered", type=Path, metavar="REGISTERED.ply")
    gt = p.add_mutually_exclusive_group()
    gt.add_argument("--synthetic", type=Path, metavar="DATASET",
                    help="a `drsplat synth` dataset: shorthand for its gt/labels.npy, gt/label_names.json, text_embeddings.npy and scene.ply (--original)")
    gt.add_argument("--gt-labels", type=Path, metavar="LABELS.npy", help="(N,) int label per Gaussian, -1 none")
    gt.add_argument("--gt-points", type=Path, metavar="CLOUD", help="labelled point cloud: a PLY with a label property (ScanNet *_vh_clean_2.labels.ply), or .pcd/.xyz/.pts with labels in CLOUD.labels.npy")
    _add_pseudo_arguments(p)
    _add_query_arguments(p, "JSON list of label names (label id = index); with --gt-points, the names of the cloud's raw labels 1..K (default NYU40)")
    _add_task_arguments(p)
    _add_no_progress(p)  # --gt-points runs the pseudo-label vote, whose bar went into redirected stderr (round 59b)
    p.set_defaults(func=run_iou)


PSEUDO_DEFAULTS = {"classes": None, "radius": 3.0, "vote": "gaussian", "engine": "grid", "min_opacity": 0.0}  # the pseudo-label flags (`pseudo_flags_given`)


def _add_pseudo_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("pseudo-labels from a labelled point cloud")
    d = PSEUDO_DEFAULTS
    g.add_argument("--classes", type=class_list, default=d["classes"], metavar="A,B,...",
                   help="keep only these label names, each once (the others' points become unannotated and vote for 'no label')")
    g.add_argument("--radius", type=float_range(0.0, MAX_RADIUS, lo_open=True), default=d["radius"],
                   help=f"Mahalanobis radius r (points with D <= r^2 vote), at most {MAX_RADIUS:g}")
    g.add_argument("--vote", choices=("gaussian", "count"), default=d["vote"], help="vote weight exp(-D/2) (default) or 1")
    g.add_argument("--engine", choices=("grid", "kdtree"), default=d["engine"], help="neighbour search: numba point grid (default) or scipy KD-trees")
    g.add_argument("--min-opacity", type=float_range(0.0, 1.0), default=d["min_opacity"], metavar="P",
                   help="Gaussians of opacity below P get no pseudo-label, as OpenGaussian's ScanNet evaluation drops them at 0.1 "
                        "(default 0: every Gaussian is labelled; the volume-aware IoU weighs them by their opacity instead)")


def class_list(text: str) -> list[str]:
    """argparse type for --classes: comma-separated label names, none blank or given twice (the k-th
    name is the k-th query, so a repeat would score a label with another label's embedding row)."""
    items = [c.strip() for c in text.split(",")]
    seen: set[str] = set()
    for k, name in enumerate(items):
        if not name:
            raise argparse.ArgumentTypeError(f"entry {k + 1} of {text!r} is empty")
        if name in seen:
            raise argparse.ArgumentTypeError(f"{name!r} is given twice")
        seen.add(name)
    return items


class_list.__name__ = "class list"


def pseudo_flags_given(args: argparse.Namespace) -> list[str]:
    """The pseudo-label flags set to something other than their default, as "--name"."""
    return [f"--{name.replace('_', '-')}" for name, default in PSEUDO_DEFAULTS.items() if getattr(args, name) != default]


def _add_scannet(sub) -> None:
    p = sub.add_parser("scannet", help="3D IoU on a ScanNet scene: pseudo ground truth from *_vh_clean_2.labels.ply (NYU40)")
    p.add_argument("registered", type=Path, metavar="REGISTERED.ply")
    p.add_argument("--scene-dir", type=Path, required=True, metavar="DIR", help="ScanNet scene folder (or the labels.ply itself)")
    p.add_argument("--save-labels", type=output_file, metavar="OUT.npy", help="also save the pseudo-labels")
    _add_pseudo_arguments(p)
    _add_query_arguments(p, "JSON list of the raw label names 1..K (default: the 40 NYU40 classes)")
    _add_task_arguments(p)
    _add_no_progress(p)
    p.set_defaults(func=run_scannet)


def _add_pseudolabels(sub) -> None:
    p = sub.add_parser("pseudolabels", help="label every Gaussian from a labelled point cloud (Mahalanobis vote)")
    p.add_argument("scene", type=Path, metavar="SCENE.ply")
    p.add_argument("--points", type=Path, required=True, metavar="CLOUD", help="labelled cloud: PLY with x, y, z, label (ScanNet layout), or .pcd/.xyz/.pts with labels in CLOUD.labels.npy")
    p.add_argument("--out", type=output_file, required=True, metavar="LABELS.npy", help="(N,) int32 labels, -1 none")
    p.add_argument("--names-out", type=json_output_file, metavar="NAMES.json", help="write the label names (index = label id)")
    p.add_argument("--label-names", type=Path, metavar="NAMES.json", help="names of the cloud's raw labels 1..K (default NYU40)")
    _add_pseudo_arguments(p)
    _add_no_progress(p)
    p.set_defaults(func=run_pseudolabels)


def _add_no_progress(p) -> None:
    """--no-progress, as register, features and synth have it (round 57c: the eval commands drew their bars into pipes and logs)."""
    p.add_argument("--no-progress", action="store_true", help="no progress bar (-q hides it too)")


def progress_shown(args: argparse.Namespace) -> bool:
    """Whether a progress bar is drawn: not with -q or --no-progress."""
    return not (getattr(args, "quiet", False) or getattr(args, "no_progress", False))


def _add_lerf(sub) -> None:
    p = sub.add_parser("lerf", help="LERF-OVS 2D object selection (OpenGaussian's protocol): mIoU and mAcc@0.25")
    _add_no_progress(p)
    p.add_argument("registered", type=Path, metavar="REGISTERED.ply")
    p.add_argument("--source", type=Path, required=True, metavar="DATASET", help="the scene's dataset folder (COLMAP / transforms.json cameras)")
    p.add_argument("--annotations", type=Path, required=True, metavar="DIR", help="lerf_ovs/label/<scene>/ with frame_XXXXX.json")
    p.add_argument("--threshold", type=threshold_value, default=None, metavar="T|auto", help="selection threshold on the score (default: 0.5 for relevancy, per-query Otsu for cosine)")
    # a pixel is selected strictly above it, and the occupancy never exceeds LERF_ALPHA_LIMIT, nor the rescaled map 1 (round 59b:
    # 1 was taken and scored 0 by construction, exit 0)
    p.add_argument("--alpha-threshold", type=float_range(0.0, LERF_ALPHA_LIMIT, hi_open=True), default=None,
                   help=f"rendered occupancy above which a pixel is selected, 0 <= value < {LERF_ALPHA_LIMIT} (a pixel's occupancy "
                        f"never reaches it) (default: {LERF_ALPHA_THRESHOLD}, OpenGaussian's)")
    p.add_argument("--json", type=json_output_file, metavar="OUT.json", help="also write per-view results as JSON")
    add_principal_point_argument(p)
    add_near_plane_argument(p, "the views are rendered with (OpenGaussian's and LangSplat's renderer: INRIA's, 'inria')",
                            default="the plane the registered PLY records, else 0.01, gsplat's")
    p.add_argument("--protocol", choices=("opengaussian", "langsplat"), default="opengaussian",
                   help="opengaussian: render the Gaussians each query selects (mIoU, mAcc@0.25; the default); langsplat: "
                        "LangSplat's relevancy maps of the rendered features (mIoU, localization accuracy; always relevancy, "
                        "so it needs negatives; --threshold and --alpha-threshold do not apply)")
    p.add_argument("--mask-threshold", type=float_range(0.0, 1.0, hi_open=True), default=None,
                   help=f"--protocol langsplat: threshold of the rescaled relevancy map, 0 <= value < 1 (default: {LANGSPLAT_MASK_THRESHOLD}, LangSplat's)")
    p.add_argument("--topk", type=int_range(1, 1024), default=None,
                   help=f"--protocol langsplat: Gaussians blended per pixel for its feature (default: {DEFAULT_TOPK})")
    _add_query_arguments(p, "JSON list of names, one per --text-embeddings row (needed with it); with a text encoder, the phrases to "
                            "query (default: the annotated categories, in sorted order)")
    p.set_defaults(func=run_lerf)


# ---------------------------------------------------------------------------------------------- helpers


def label_embeddings(args: argparse.Namespace, field, names: list[str], negatives: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """([L, D] the labels' query embeddings, [C, D] the relevancy's negatives or None): from
    --text-embeddings / --negative-embeddings, else through the CLIP text encoder."""
    from drsplat.commands.common import load_encoder, oracle_flag, warn_unused_clip_flags
    from drsplat.query import load_query_embeddings, negative_embeddings, text_embeddings

    encoder = None
    if args.text_embeddings is not None:
        queries = load_query_embeddings(args.text_embeddings, field.dim, "label")
        if queries.shape[0] != len(names):
            raise InputError(args.text_embeddings, f"{queries.shape[0]} embeddings for {len(names)} label names")
    else:
        encoder = load_encoder(args, field, oracle_flag("--text-embeddings"))
        queries = text_embeddings(encoder, names, field)
    if not negatives:
        warn_unused_clip_flags(args, encoder)
        return queries, None
    extra = None if args.negative_embeddings is None else load_query_embeddings(args.negative_embeddings, field.dim, "negative")
    if encoder is None and extra is None:
        encoder = load_encoder(args, field, "--negative-embeddings ((C, D) rows standing for the canonical phrases, which "
                                            "relevancy needs)")
    warn_unused_clip_flags(args, encoder)
    return queries, negative_embeddings(encoder, field, [], extra)


def label_scores(args: argparse.Namespace, field, names: list[str]) -> np.ndarray:
    """[N, L] scores of every Gaussian for every label: cosine, or relevancy with --relevancy."""
    from drsplat.query import cosine, relevancy

    queries, negatives = label_embeddings(args, field, names, args.relevancy)
    return cosine(field, queries) if negatives is None else relevancy(field, queries, negatives)


MAX_TAUS = 10_001  # localisation thresholds searched; each costs one pass over the scores


def parse_taus(text: str) -> np.ndarray:
    """START:STOP:STEP -> the inclusive grid; at most MAX_TAUS finite values, STEP at least MIN_TAU_STEP
    (the thresholds are rounded to 6 decimals: a finer step would repeat them) (UsageError otherwise)."""
    try:
        start, stop, step = (float(x) for x in text.split(":"))
    except ValueError:
        raise UsageError(f"--taus must be START:STOP:STEP, got {text!r}") from None
    if not all(np.isfinite([start, stop, step])):
        raise UsageError(f"--taus {text!r}: START, STOP and STEP must be finite numbers")
    if step <= 0 or stop < start:
        raise UsageError(f"--taus {text!r}: need STEP > 0 and STOP >= START")
    if step < MIN_TAU_STEP:
        raise UsageError(f"--taus {text!r}: STEP {shown_number(step)} is below {MIN_TAU_STEP:g}; thresholds are compared to 6 decimals")
    with np.errstate(over="ignore", invalid="ignore"):
        count = np.floor((stop - start) / step + 0.5) + 1
    if not np.isfinite(count) or count > MAX_TAUS:
        raise UsageError(f"--taus {text!r} is a grid of {count:.3g} thresholds; at most {MAX_TAUS} (use a larger STEP)")
    with np.errstate(over="ignore", invalid="ignore"):
        end = stop + 0.5 * step
        grid = np.round(np.arange(start, end, step), 6) if np.isfinite(end) else None  # numpy's arange raises on an infinite end
    if grid is None or not np.isfinite(grid).all():  # STOP + STEP/2 beyond float range (round 54: a traceback)
        raise UsageError(f"--taus {text!r}: the grid reaches beyond the range of floating-point numbers")
    return grid


def parse_weightings(text: str | tuple[str, ...]) -> tuple[str, ...]:
    """--weighting as a tuple of WEIGHTINGS (a tuple passes through: the command parsed it up front)."""
    if isinstance(text, tuple):
        return text
    items = tuple(w.strip() for w in text.split(",") if w.strip())
    unknown = [w for w in items if w not in WEIGHTINGS]
    if unknown or not items:
        raise UsageError(f"--weighting: unknown {', '.join(map(repr, unknown)) if unknown else repr(text)}; choose from {', '.join(WEIGHTINGS)}")
    refuse_repeats("--weighting", items)  # each weighting is one row of the table
    return items


def check_metric_flags(args: argparse.Namespace) -> None:
    """--taus and --weighting checked before any file is read (the grid and the list are parsed once here)."""
    parse_taus(args.taus)
    args.weighting = parse_weightings(args.weighting)
    check_negatives_flag(args, args.relevancy)
    given = [flag for flag, name in (("--voxel-resolution", "voxel_resolution"), ("--voxel-empty", "voxel_empty"))
             if getattr(args, name) is not None]
    if given and "voxel" not in args.weighting:  # they were ignored without a word (round 54)
        raise UsageError(f"{', '.join(given)} {'applies' if len(given) == 1 else 'apply'} to the voxel IoU only: add voxel to "
                         f"--weighting (now {','.join(args.weighting)}) or drop {'it' if len(given) == 1 else 'them'}")
    if args.argmax_over is not None and args.task == "loc":  # it changes the segmentation only (round 85a F3: ignored without a word)
        raise UsageError(f"--argmax-over applies to the segmentation's argmax: use --task seg or both, or drop --argmax-over {args.argmax_over}")
    args.argmax_over = "queried" if args.argmax_over is None else args.argmax_over
    args.voxel_resolution = VOXEL_RESOLUTION if args.voxel_resolution is None else args.voxel_resolution
    args.voxel_empty = VOXEL_EMPTY if args.voxel_empty is None else args.voxel_empty


def check_negatives_flag(args: argparse.Namespace, relevancy: bool) -> None:
    """UsageError for --negative-embeddings where the scores are cosine (it was ignored without a word,
    round 54; `drsplat query` refuses it so)."""
    if args.negative_embeddings is not None and not relevancy:
        raise UsageError("--negative-embeddings applies to relevancy scores only (cosine scores have no negatives): add "
                         "--relevancy or drop it")


def cloud_inputs(flag: str, cloud: Path | None) -> dict[str, Path]:
    """The file a labelled cloud's raw labels are read from when it is not the cloud itself: the
    `<cloud>.labels.npy` beside a .xyz/.pcd/.pts cloud (an input that guard_args cannot see)."""
    from drsplat.eval.datasets import POINT_CLOUD_SUFFIXES, labels_sidecar

    if cloud is None or cloud.suffix.lower() not in POINT_CLOUD_SUFFIXES:
        return {}
    return {f"{flag}'s labels file": labels_sidecar(cloud)}


def check_folder(flag: str, folder: Path) -> None:
    """InputError unless `folder` is a folder: said before anything inside it is looked for."""
    if not folder.is_dir():
        raise InputError(folder, f"{flag}: " + ("does not exist" if not folder.exists() else "is not a folder"))


def assigned_rows(path: Path, field) -> np.ndarray:
    """[N] bool: the Gaussians that hold a language feature (`LanguageField.assigned`, a finite positive
    norm; registration weights do not say this). InputError when there is none: every score would be 0
    and every IoU 0 by construction, which reads like a result."""
    assigned = np.asarray(field.assigned(), bool)
    if not assigned.any():
        raise InputError(path, f"none of its {assigned.size} Gaussians holds a language feature (every stored norm is 0 or "
                               "non-finite): nothing to evaluate; register the scene again")
    if not assigned.all():
        log.info("%s: %d of %d Gaussians hold a language feature; the others are never selected", shown_path(path), int(assigned.sum()), assigned.size)
    return assigned


def check_defined(reports, names: list[str]) -> None:
    """Every label queried has ground truth, so an undefined (NaN) IoU means the weighting could not
    measure it (a voxel IoU with no occupied voxel): warn naming the labels left out of the mean,
    and refuse a report that measured none (its mIoU would be NaN, exit 0)."""
    for r in reports:
        dropped = [names[i] for i in np.flatnonzero(~r.valid)]
        if not dropped:
            continue
        what = f"{r.task} IoU ({r.weighting})"
        if len(dropped) == len(names):
            hint = " (is --voxel-empty above every voxel's mass, or --voxel-resolution too coarse?)" if r.weighting == "voxel" else ""
            raise DrsplatError(f"{what}: no label's IoU is defined{hint}; nothing to average")
        shown = ", ".join(dropped[:10]) + (f" and {len(dropped) - 10} more" if len(dropped) > 10 else "")
        log.warning("%s: averaged over %d of %d labels; undefined for %s (left out of the mean)", what, len(names) - len(dropped),
                    len(names), shown)


def write_json(path: Path | None, doc: dict) -> None:
    if path is None:
        return
    from drsplat.utils import atomic_path

    with outputs_together([path]), atomic_path(path) as tmp:  # settled: an interrupt after it names it (round 96a F6)
        tmp.write_text(json_text(doc) + "\n")
    log.info("wrote %s", shown_path(path))


def check_classes(args: argparse.Namespace, raw_names: list[str]) -> None:
    """UsageError naming --classes and where the names came from when a class is not one of them."""
    unknown = [c for c in args.classes or () if c not in raw_names]
    if unknown:
        source = args.label_names if args.label_names is not None else "NYU40 (the default; pass --label-names for others)"
        raise UsageError(f"--classes: {', '.join(map(repr, unknown))} {'is' if len(unknown) == 1 else 'are'} not among the label names of {source}")


def pseudo_from_cloud(args: argparse.Namespace, scene, cloud: Path, raw_names: list[str]):
    """(labels [N], names) of a scene from a labelled cloud, with the --classes/--radius/--vote options.
    Ctrl-C stops the vote at its next chunk (`cancel_on_signals`): the grid engine's kernel holds the
    main thread for minutes on a large scene."""
    from drsplat.eval.datasets import load_labelled_points
    from drsplat.eval.pseudolabels import KDTREE_MAX_COORDINATE, pseudo_labels

    check_classes(args, raw_names)
    pts = load_labelled_points(cloud, raw_names, args.classes)
    if args.engine == "kdtree":  # a double-precision cloud can hold what scipy's KD-tree cannot square (the library's ValueError)
        largest = float(np.abs(pts.points).max(initial=0.0))
        if largest > KDTREE_MAX_COORDINATE:
            raise InputError(cloud, f"holds point coordinates up to {largest:.3g}: the kdtree engine's squared distances overflow past "
                                    f"{KDTREE_MAX_COORDINATE:.0e}; use --engine grid (the default)")
    token = CancelToken()
    with cancel_on_signals(token, "the current chunk of Gaussians"):
        res = pseudo_labels(scene, pts.points, pts.labels, radius=args.radius, weighting=args.vote, engine=args.engine,
                            show_progress=progress_shown(args), cancel=token)
        token.raise_if_cancelled()
    faint = np.zeros(len(res.labels), bool)
    if args.min_opacity > 0:  # OpenGaussian's scripts/eval_scannet.py drops Gaussians of sigmoid(opacity) < 0.1 from its ground truth
        faint = ~(scene.opacities() >= args.min_opacity)
        res.labels[faint] = -1
        log.info("pseudo-labels: %d Gaussians of opacity below %g left unlabelled (--min-opacity)", int(faint.sum()), args.min_opacity)
    labelled = int(np.count_nonzero(res.labels >= 0))
    log.info("pseudo-labels: %d of %d Gaussians labelled from %d points (%d non-finite Gaussians)", labelled, len(res.labels), len(pts.points), res.nonfinite)
    if labelled == 0:
        why = (f"every Gaussian's opacity is below --min-opacity {args.min_opacity:g}" if args.min_opacity > 0 and faint.all() else
               why_nothing_labelled(scene.means, pts.points, pts.labels, res.nonfinite, args.radius))
        log.warning("the pseudo-labels from %s label none of the scene's %d Gaussians: %s", cloud, len(res.labels), why)
    return res.labels.astype(np.int64), pts.names


def why_nothing_labelled(means: np.ndarray, points: np.ndarray, labels: np.ndarray, nonfinite: int, radius: float) -> str:
    """The likeliest reason a labelled cloud labelled no Gaussian, checked in this order: no Gaussian
    with a finite mean, no point, no labelled point, disjoint bounding boxes of the labelled points
    and the means (the cloud in another frame or unit), else points near but outside every radius."""
    labelled = np.asarray(points)[np.asarray(labels) >= 0]
    means = np.asarray(means, np.float64)
    means = means[np.isfinite(means).all(axis=1)]
    if len(means) == 0:
        return "the scene holds no Gaussian" + (" with finite parameters" if nonfinite else "")
    if len(points) == 0:
        return "the cloud holds no point with finite coordinates (empty, or every point is NaN/inf)"
    if len(labelled) == 0:
        return "no point of the cloud has a label among the names kept (every raw label is 0, or outside --classes)"
    lo_c, hi_c, lo_s, hi_s = labelled.min(axis=0), labelled.max(axis=0), means.min(axis=0), means.max(axis=0)
    if (lo_c > hi_s).any() or (hi_c < lo_s).any():
        return (f"the labelled points' bounding box {_box(lo_c, hi_c)} does not overlap the Gaussians' {_box(lo_s, hi_s)}: "
                "is the cloud in the scene's coordinate frame (same axes and units)?")
    return (f"no labelled point lies within the Mahalanobis radius {radius:g} of any Gaussian: is the cloud in the scene's "
            "coordinate frame (same axes and units), or is --radius too small?")


def _box(lo: np.ndarray, hi: np.ndarray) -> str:
    """An axis-aligned box as "[x0..x1, y0..y1, z0..z1]"."""
    return "[" + ", ".join(f"{a:.3g}..{b:.3g}" for a, b in zip(lo, hi)) + "]"


def load_row_aligned_scene(path: Path, rows_of: str):
    """A user scene (any splat format) whose Gaussians must be the file's rows: refused when loading
    drops rows with non-finite values, since `rows_of` (labels, indices) follow the file's rows and
    would shift by one after every dropped row."""
    from drsplat.splat_formats import load_scene_report

    scene, report = load_scene_report(path)
    dropped = report.dropped_nan_rows + report.dropped_inf_rows
    if dropped:
        raise InputError(path, f"{counted(dropped, 'row has', 'rows have')} non-finite values and would be dropped, so {rows_of} could not follow "
                               "the file's rows; repair or remove those rows first")
    return scene


def load_eval_scene(args: argparse.Namespace):
    """(scene to evaluate on, registered field, index of registered Gaussians in that scene or None)."""
    from drsplat.commands.common import load_registered
    from drsplat.eval.metrics import match_gaussians

    scene, field = load_registered(args.registered)
    if args.original is None:
        return scene, field, None
    original = load_row_aligned_scene(args.original, "ground-truth labels of the original scene")
    try:
        index = match_gaussians(original.means, scene.means, original_rest=original.identity_rows(slice(None))[:, 3:],
                                subset_rest=scene.identity_rows(slice(None))[:, 3:])
    except ValueError as exc:
        raise InputError(args.original, f"is not the scene {args.registered.name} was registered from: {exc}; if it was registered "
                                        "from a .spz or .splat copy of this scene, pass that copy as --original (.spz stores "
                                        "positions in steps of 1/4096)") from None
    log.info("evaluating on the %d Gaussians of %s (%d registered)", original.num_gaussians, shown_path(args.original), scene.num_gaussians)
    return original, field, index


def in_report_order(reports: list, weightings: tuple[str, ...]) -> list:
    """Reports in `evaluate_scene`'s order: each weighting's localisation then segmentation, the voxel ones last."""
    place = {w: (w == "voxel", k) for k, w in enumerate(weightings)}
    return sorted(reports, key=lambda r: (place[r.weighting], r.task != "loc"))


def _evaluate_and_write(args, scene, field, gt: np.ndarray, names: list[str], index: np.ndarray | None = None) -> list[str]:
    """The evaluation's reports written to --json, and the lines of its table, which the caller prints
    once its outputs are settled: a table reader that goes (`| head`) ends the command quietly, and
    must not take the files with it (round 89c F1: `eval scannet` printed inside its outputs' set,
    whose rollback removed the --json and --save-labels it had just written, exit 0)."""
    from drsplat.eval.metrics import evaluate_scene, expand_scores, format_curve, format_reports

    present = sorted(set(int(x) for x in np.unique(gt) if x >= 0))
    if not present:
        raise DrsplatError("no Gaussian has a ground-truth label; nothing to evaluate")
    # only labels present in the ground truth are averaged (NYU40 has 40 names, a scene a few)
    keep = np.array(present)
    sub_names = [names[i] for i in keep]
    remap = np.full(len(names) + 1, -1, np.int64)
    remap[keep] = np.arange(len(keep))
    gt_sub = np.where(gt >= 0, remap[np.maximum(gt, 0)], -1)
    assigned = assigned_rows(args.registered, field)
    tasks = ("loc", "seg") if args.task == "both" else (args.task,)
    every = "seg" in tasks and args.argmax_over == "queried" and len(present) < len(names)
    absent = sorted(set(range(len(names))) - set(present)) if every else []
    over_names = every or args.text_embeddings is not None  # every queried label, in the names' order: a tie goes to the lower label
    scores = label_scores(args, field, names if over_names else sub_names)
    if index is not None:
        scores = expand_scores(scores, index, scene.num_gaussians)
        registered, assigned = assigned, np.zeros(scene.num_gaussians, bool)
        assigned[index] = registered
    present_scores = scores[:, keep] if over_names else scores
    weightings, taus = parse_weightings(args.weighting), parse_taus(args.taus)
    rest = tuple(t for t in tasks if not (every and t == "seg"))
    if "voxel" in weightings:
        check_voxel_memory(args.voxel_resolution, scene, gt_sub >= 0, len(names) if every else len(sub_names), "seg" in tasks)
    reports = evaluate_scene(scene, present_scores, gt_sub, sub_names, rest, weightings, taus, args.voxel_resolution, args.voxel_empty,
                             assigned=assigned) if rest else []
    if every:  # OpenGaussian's protocol: the argmax over every queried label, the means over the present ones (round 76b F1)
        segmentation = evaluate_scene(scene, scores, gt, names, ("seg",), weightings, taus, args.voxel_resolution, args.voxel_empty,
                                      assigned=assigned)
        reports = in_report_order(reports + [r.restricted(keep) for r in segmentation], weightings)
    check_defined(reports, sub_names)
    absent_names = [names[i] for i in absent]
    write_json(args.json, {"scene": str(args.registered), "labels": sub_names, "absent_labels_in_argmax": absent_names,
                           "reports": [r.to_dict() for r in reports]})
    # evaluated on the original scene's rows when the registered file holds fewer (round 91b F4: its count was the original's)
    on = (f": {scene.num_gaussians} Gaussians" if index is None else
          f" on the {scene.num_gaussians} Gaussians of {shown_path(Path(args.original).name)} ({len(index)} registered)")
    lines = [f"{shown_path(args.registered.name)}{on}, {len(sub_names)} labels, "
             f"{int(np.count_nonzero(gt_sub >= 0))} labelled, score = {'relevancy' if args.relevancy else 'cosine'}"
             + (f"; the segmentation's argmax also over {counted(len(absent), 'label', 'labels')} absent from the ground truth" if absent else ""),
             format_reports(reports)]
    lines += [format_curve(r, every=1 if args.curve else 10) for r in reports
              if r.curve and (args.curve or r is next(x for x in reports if x.curve))]
    return lines


VOXEL_FREE_SHARE = 0.9  # of the free memory, the most a voxel grid may need (the process holds the scene and scores besides)


def check_voxel_memory(resolution: int, scene, focus: np.ndarray, num_labels: int, segmentation: bool, flag: str = "--voxel-resolution") -> None:
    """A usage error naming --voxel-resolution when the voxel IoU's grid (`VoxelSetup.grid_of`, over the labelled
    Gaussians `focus` [N] bool) would not fit in the free memory (`voxel_iou_bytes`), with the largest resolution that
    does (round 89c F3: 2048, within the flag's range, grew to 20 GB on a room of 2,763 Gaussians and ended in "out of
    memory: the input is larger than this machine can hold")."""
    from drsplat.eval.metrics import VoxelSetup, voxel_iou_bytes
    from drsplat.memory import available_memory, format_size

    grid = VoxelSetup.grid_of(scene, resolution, focus)
    need, free = voxel_iou_bytes(grid, num_labels, segmentation), available_memory()
    if free <= 0 or need <= VOXEL_FREE_SHARE * free:  # the estimate ran ~4 % under the measured peak (round 90b F4)
        return
    fits, room = resolution, free // 2  # half: the scene, the scores and the process hold the rest
    while fits > 1 and (held := voxel_iou_bytes(VoxelSetup.grid_of(scene, fits, focus), num_labels, segmentation)) > room:
        fits = max(1, min(fits - 1, int(fits * (room / held) ** (1 / 3))))
    nx, ny, nz = grid.shape
    labels = counted(num_labels, "label", "labels") if segmentation else "one label at a time"
    raise UsageError(f"{flag} {resolution}: the voxel IoU's grid of {nx}x{ny}x{nz} voxels for {labels} "
                     f"needs about {format_size(need)}, more than {VOXEL_FREE_SHARE:.0%} of the {format_size(free)} of memory free; "
                     f"{flag} {fits} needs at most half of that")


def print_lines(lines: list[str], stream) -> int:
    """The table's lines printed to `stream`; exit code 0."""
    for line in lines:
        print(line, file=stream)
    return 0


# ---------------------------------------------------------------------------------------------- commands


def run_iou(args: argparse.Namespace) -> int:
    from drsplat.eval.datasets import NYU40_NAMES

    if args.gt_points is None:  # the pseudo-label options act on a labelled cloud only: silently ignoring them would mislead
        given = pseudo_flags_given(args)
        if given:
            raise UsageError(f"{', '.join(given)} {'applies' if len(given) == 1 else 'apply'} to pseudo-labels from --gt-points CLOUD.ply only")
    check_metric_flags(args)
    if args.synthetic is None and args.gt_labels is None and args.gt_points is None:
        raise UsageError("ground truth needed: --gt-labels LABELS.npy, --gt-points CLOUD.ply or --synthetic DATASET")
    if args.synthetic is not None:
        ds = args.synthetic
        check_folder("--synthetic", ds)
        args.gt_labels = ds / "gt" / "labels.npy"
        args.label_names = args.label_names or ds / ORACLE_LABEL_NAMES
        args.text_embeddings = args.text_embeddings or ds / ORACLE_TEXT_EMBEDDINGS
        args.original = args.original or (ds / "scene.ply" if (ds / "scene.ply").exists() else None)  # the bundled demo ships none: its PLY keeps every Gaussian
    guard_args(args, ("json",), extra_inputs=cloud_inputs("--gt-points", args.gt_points),
               protected_trees={"--synthetic": args.synthetic})  # an output over any file of the dataset would damage it
    check_outputs_writable(args.json)
    scene, field, index = load_eval_scene(args)
    guard_field_codebook(args.registered, field, {"--json": args.json})
    if args.gt_labels is not None:
        names = load_label_names(args.label_names)
        gt = load_gt_labels(args.gt_labels, scene.num_gaussians, len(names), args.original)
    else:
        raw = load_label_names(args.label_names, list(NYU40_NAMES))
        gt, names = pseudo_from_cloud(args, scene, args.gt_points, raw)
    stream = table_stream(args.json)  # before the file is written (a rename would make it another file than a redirected stdout)
    return print_lines(_evaluate_and_write(args, scene, field, gt, names, index), stream)


def run_scannet(args: argparse.Namespace) -> int:
    from drsplat.eval.datasets import NYU40_NAMES, SCANNET_LABELS_PATTERN, find_scannet_labels
    from drsplat.utils import save_npy_atomic

    check_metric_flags(args)
    cloud = find_scannet_labels(args.scene_dir)
    # the labels PLY is found inside --scene-dir, so guard_args does not know it; an output named
    # like one beside it would make the folder ambiguous for the next run
    folder = {"--scene-dir": (args.scene_dir, (SCANNET_LABELS_PATTERN,))} if args.scene_dir.is_dir() else None
    guard_args(args, ("json", "save_labels"), extra_inputs={"--scene-dir's labels PLY": cloud, **cloud_inputs("--scene-dir", cloud)},
               protected_folders=folder)
    check_outputs_writable(args.json, args.save_labels)
    scene, field, index = load_eval_scene(args)
    guard_field_codebook(args.registered, field, {"--json": args.json, "--save-labels": args.save_labels})
    check_npy_name("--save-labels", args.save_labels)
    raw = load_label_names(args.label_names, list(NYU40_NAMES))
    gt, names = pseudo_from_cloud(args, scene, cloud, raw)
    stream = table_stream(args.json, args.save_labels)
    with outputs_together([args.save_labels, args.json]):  # labels without the evaluation they were saved for would be half a run
        if args.save_labels is not None:
            save_npy_atomic(args.save_labels, gt.astype(np.int32))
        lines = _evaluate_and_write(args, scene, field, gt, names, index)
    return print_lines(lines, stream)


def run_pseudolabels(args: argparse.Namespace) -> int:
    from drsplat.eval.datasets import NYU40_NAMES
    from drsplat.utils import atomic_path, save_npy_atomic

    guard_args(args, ("out", "names_out"), extra_inputs=cloud_inputs("--points", args.points))
    check_npy_name("--out", args.out)
    check_outputs_writable(args.out, args.names_out)
    scene = load_row_aligned_scene(args.scene, "the labels written (one per row)")
    raw = load_label_names(args.label_names, list(NYU40_NAMES))
    labels, names = pseudo_from_cloud(args, scene, args.points, raw)
    with outputs_together([args.out, args.names_out]):
        save_npy_atomic(args.out, labels.astype(np.int32))
        if args.names_out is not None:
            with atomic_path(args.names_out) as tmp:
                tmp.write_text(json.dumps(names) + "\n")
    counts = np.bincount(labels[labels >= 0], minlength=len(names))
    stream = table_stream(args.out, args.names_out)
    print(f"{int((labels >= 0).sum())} of {len(labels)} Gaussians labelled; wrote {shown_path(args.out)}", file=stream)
    for k in np.flatnonzero(counts):
        print(f"  {names[k]:<20} {int(counts[k]):>9}", file=stream)
    return 0


def refuse_if_no_annotated_view_draws(registered: Path, scene, cameras, views, near_plane: float, given: bool) -> None:
    """One error when no annotated view's camera has a Gaussian at depth ≥ the near plane (`raster.some_view_draws`):
    every view would render nothing and score IoU 0, a table that looks like an evaluation (round 89c F2:
    --near-plane 50 on a room 0.37 units from its cameras printed mIoU 0.000, exit 0; `register` refuses such a
    plane). A plane given with --near-plane is a usage error naming the flag; the one the header records is named as such."""
    from drsplat.raster import median_nearest_depth, plane_below, some_view_draws

    annotated = {v.name for v in views}
    shown = [c for c in cameras if c.name in annotated] or list(cameras)
    if some_view_draws(scene.means, shown, near_plane):
        return
    depth = median_nearest_depth(scene.means, shown)
    cams = f"any of the {counted(len(shown), 'annotated view', 'annotated views')}' cameras"
    if not math.isfinite(depth):
        raise DrsplatError(f"no Gaussian of {shown_path(registered)} lies in front of {cams}, so every view would render nothing: the "
                           "cameras face away from the scene, or --source holds the cameras of another scene, frame or unit")
    smaller = min(plane_below(depth), NEAR) if 1e-300 < depth < math.inf else NEAR
    why = (f"no Gaussian of {shown_path(registered)} lies {near_plane:g} scene units or more in front of {cams} (the near plane), so every "
           f"view would render nothing and score IoU 0: the Gaussians lie a median {depth:.2g} units from these cameras; pass a smaller "
           f"--near-plane (such as {smaller:g})")
    if given:
        raise UsageError(f"--near-plane {near_plane:g}: {why}")
    raise DrsplatError(f"{why}; {near_plane:g} is the plane the registered scene's header records")


def registered_near_plane(given: float | None, scene) -> float:
    """The plane `eval lerf` renders at: --near-plane when given, else the one the registered scene's header records
    (`registration.options.recorded_near_plane`, said in one line), else NEAR."""
    from drsplat.defaults import NEAR
    from drsplat.registration.options import recorded_near_plane

    if given is not None:
        return given
    recorded = recorded_near_plane(scene.comments)
    if recorded is None:
        return NEAR
    log.info("rendering at the near plane the registered scene was registered at, %g (its header; --near-plane chooses another)", recorded)
    return recorded


def trained_cameras(scene, registered: Path) -> dict:
    """`cameras_in_scene_frame`'s scene_path and refinements for a registered scene whose
    registration took a gsplat checkpoint's camera refinements (`frames.refined_by` its header):
    that checkpoint's refinements alone, read again (`splat_formats.checkpoint_refinements`); {} for
    any other scene, or, with a warning, when the file its header names is not there or is no
    readable gsplat checkpoint (a header is the registered file's word, not the user's)."""
    from drsplat.errors import InputError
    from drsplat.frames import refined_by
    from drsplat.splat_formats import checkpoint_refinements

    checkpoint = refined_by(scene.comments)
    if checkpoint is None:
        return {}
    try:
        if not checkpoint.is_file():
            raise InputError(checkpoint, "is not a file here")
        refinements = checkpoint_refinements(checkpoint)
    except InputError as exc:
        log.warning("%s was registered with the camera refinements of the gsplat checkpoint its header names, which cannot be read (%s): "
                    "evaluated with the dataset's cameras as they are", registered, exc)
        return {}
    return {"scene_path": checkpoint, "refinements": refinements}


def check_categories_named(views, categories: list[str], names: list[str], names_path: Path) -> None:
    """Every annotated category must have a label name (and so a query embedding). The error names
    the first annotation file and object holding a missing category, the names file, and a spelling
    of it that the names hold up to blanks or case (round 89a F2: only the names file was named)."""
    missing = [c for c in categories if c not in names]
    if not missing:
        return
    first = missing[0]
    view = next(v for v in views if first in v.masks or first in v.skipped)
    k = view.first_object.get(first)
    # up to blanks around it and what `cameras.folded_name` folds (case, composed accents): said as the cameras' names are
    near = [n for n in names if folded_name(n.strip()) == folded_name(first.strip())]
    hint = ""
    if near:
        ways = (["in blanks around it"] if near[0].strip() != near[0] or first.strip() != first else []) + \
               ([spelling_difference(near[0].strip(), first.strip())] if near[0].strip() != first.strip() else [])
        # escaped: spellings that differ in composed accents print alike (round 91a F6)
        hint = f" (the names hold {ascii(near[0])}, this is {ascii(first)}: the spellings differ {' and '.join(ways)})"
    more = f"; {len(missing) - 1} more annotated categor{'y' if len(missing) == 2 else 'ies'} lack one too: {missing[1:6]}" if len(missing) > 1 else ""
    raise InputError(view.path, f"category {first!r} is not among the {len(names)} names of {shown_path(names_path)}, so it has no "
                                f"query embedding{hint}{more}",
                     field=f"objects[{k}].category" if k is not None else "objects")


def run_lerf(args: argparse.Namespace) -> int:
    from drsplat.cameras import dataset_inputs, load_cameras
    from drsplat.commands.common import load_registered
    from drsplat.frames import cameras_as_trained
    from drsplat.eval.datasets import lerf_annotation_files, load_lerf_annotations
    from drsplat.eval.lerf import lerf_2d_report, select_queries

    check_protocol_flags(args)
    cameras = load_cameras(args.source)
    # the camera file and the annotations are found inside --source and --annotations; any *.json
    # written into --annotations would be read as an annotation by the next run
    lerf_annotation_files(args.annotations)  # a missing folder or one without annotations, said before anything else
    guard_args(args, ("json",), extra_inputs=dataset_inputs(args.source, cameras), protected_folders={"--annotations": (args.annotations, ("*.json",))},
               protected_trees={"--annotations": args.annotations})
    check_outputs_writable(args.json)
    views = load_lerf_annotations(args.annotations, {c.name: (c.width, c.height) for c in cameras})
    if not any(v.masks or v.skipped for v in views):
        raise InputError(args.annotations, f"the annotations hold no objects (the 'objects' list of each of its {len(views)} "
                                           "file(s) is empty): nothing to evaluate")
    scene, field = load_registered(args.registered)
    given_plane = args.near_plane is not None
    args.near_plane = registered_near_plane(args.near_plane, scene)
    cameras = cameras_as_trained(scene, cameras, args.source, args.principal_point, what=str(args.registered),
                                 **trained_cameras(scene, args.registered), near=args.near_plane)
    guard_field_codebook(args.registered, field, {"--json": args.json})
    refuse_if_no_annotated_view_draws(args.registered, scene, cameras, views, args.near_plane, given_plane)
    assigned = assigned_rows(args.registered, field)
    categories = sorted({c for v in views for c in (*v.masks, *v.skipped)})
    if args.text_embeddings is not None and args.label_names is None:  # round 57c: rows paired with sorted categories, mIoU 0.013 against 0.811
        raise UsageError(f"--text-embeddings needs --label-names NAMES.json (one name per row, in the rows' order): an embedding file "
                         f"holds no names, so its rows cannot be matched to the {len(categories)} annotated categories")
    names = load_label_names(args.label_names, categories)
    check_categories_named(views, categories, names, args.label_names)
    if args.protocol == "langsplat":
        return _run_lerf_langsplat(args, scene, field, cameras, views, names, categories, assigned)
    scores = label_scores(args, field, names)
    threshold = None
    if args.threshold is None and args.relevancy:
        threshold = 0.5
    elif args.threshold not in (None, "auto"):
        try:
            threshold = float(args.threshold)
        except ValueError:
            raise DrsplatError(f"--threshold must be a number or 'auto', got {args.threshold!r}") from None
    selected, taus = select_queries(scores, threshold, assigned)
    selections = {n: selected[:, k] for k, n in enumerate(names) if n in categories}
    alpha_threshold = LERF_ALPHA_THRESHOLD if args.alpha_threshold is None else args.alpha_threshold
    report = lerf_2d_report(scene, cameras, views, selections, alpha_threshold, show_progress=progress_shown(args), near=args.near_plane)
    require_scored_pairs(args, report)
    stream = table_stream(args.json)
    doc = report.to_dict()
    doc["thresholds"] = {n: float(t) for n, t in zip(names, taus)}
    write_json(args.json, doc)  # before the table, as in `eval iou`
    print(f"{shown_path(args.registered.name)}: {len(report.rows)} (view, category) pairs over {len(views) - len(report.missing_views)} views; "
          f"thresholds {'per-query Otsu' if threshold is None else threshold}", file=stream)
    print(report.format(), file=stream)
    return 0


PROTOCOL_FLAGS = {"opengaussian": (("threshold", "--threshold"), ("alpha_threshold", "--alpha-threshold")),
                  "langsplat": (("mask_threshold", "--mask-threshold"), ("topk", "--topk"))}


def check_protocol_flags(args: argparse.Namespace) -> None:
    """UsageError for a flag of the other `eval lerf` protocol (it would be ignored without a word), and
    for --negative-embeddings with cosine scores (LangSplat's protocol always scores relevancy)."""
    for protocol, flags in PROTOCOL_FLAGS.items():
        given = [flag for name, flag in flags if getattr(args, name) is not None]
        if given and protocol != args.protocol:
            raise UsageError(f"{', '.join(given)} belong{'s' if len(given) == 1 else ''} to --protocol {protocol}, not "
                             f"{args.protocol} (OpenGaussian's protocol thresholds the Gaussians' scores and their rendered "
                             "occupancy; LangSplat's the relevancy map of the rendered features)")
    check_negatives_flag(args, args.relevancy or args.protocol == "langsplat")


def require_scored_pairs(args: argparse.Namespace, report) -> None:
    """DrsplatError when an `eval lerf` report (either protocol) scored no (view, category) pair, saying why."""
    if not report.rows and report.skipped:
        raise DrsplatError(f"every (view, category) pair of {args.annotations} that matches a camera has degenerate ground truth "
                           "(see the warnings above): nothing to score")
    if not report.rows:
        raise DrsplatError(f"no annotated view of {args.annotations} matches a camera of {args.source} by image name")


def _run_lerf_langsplat(args: argparse.Namespace, scene, field, cameras, views, names: list[str], categories: list[str],
                        assigned: np.ndarray) -> int:
    """`eval lerf --protocol langsplat`: LangSplat's relevancy-map protocol (drsplat.eval.langsplat).
    Ctrl-C stops it at the next view (a view takes seconds at LERF-OVS's size)."""
    from drsplat.eval.langsplat import langsplat_report

    queries, negatives = label_embeddings(args, field, names, negatives=True)
    by_name = {n: queries[k] for k, n in enumerate(names) if n in categories}
    topk = DEFAULT_TOPK if args.topk is None else args.topk
    mask_threshold = LANGSPLAT_MASK_THRESHOLD if args.mask_threshold is None else args.mask_threshold
    token = CancelToken()
    with cancel_on_signals(token, "the current view"):
        report = langsplat_report(scene, field, cameras, views, by_name, negatives, topk, mask_threshold, show_progress=progress_shown(args),
                                  cancel=token, assigned=assigned, near=args.near_plane)
        token.raise_if_cancelled()  # a Ctrl-C during the last view: it said "stopping", so no report and no exit 0
    require_scored_pairs(args, report)
    stream = table_stream(args.json)
    write_json(args.json, report.to_dict())  # before the table, as in `eval iou`
    print(f"{shown_path(args.registered.name)}: {len(report.rows)} (view, category) pairs over {len(views) - len(report.missing_views)} views",
          file=stream)
    print(report.format(), file=stream)
    return 0
