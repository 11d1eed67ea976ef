"""`drsplat register SCENE --source DATASET --features FEATURES --out REGISTERED.ply` (SCENE: PLY, .splat or .spz)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from drsplat.commands.common import add_principal_point_argument, guard_args, mask_level, add_near_plane_argument, output_file, positive_int, protected_feature_folders, ray_address, resolution_value, size_value, text_value, topk_int
from drsplat.defaults import AGGREGATE_MODES, DEFAULT_AGGREGATE, DEFAULT_CODEBOOK, DEFAULT_LEVEL, DEFAULT_TOPK, NEAR
from drsplat.device import add_device_arguments, resolve_compute
from drsplat.utils import CancelToken, cancel_on_signals, output_target, refuse_write_protected

if TYPE_CHECKING:  # the command's modules load when it runs, not when the parser is built
    from drsplat.cameras import Camera
    from drsplat.registration import RegisterOptions
    from drsplat.registration.checkpoint import RunLock

log = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "register",
        help="lift per-mask language embeddings onto the Gaussians (training-free registration)",
        description="Rasterize every training view, keep the top-k Gaussians of each pixel, accumulate their "
        "weights into (Gaussian, mask) pairs and give each Gaussian the weight-averaged mask embedding. "
        "Writes an INRIA-layout PLY with the language field as extra properties (docs/registration.md). "
        "Ctrl-C stops at the end of the current step (a view, or a sub-quantiser of --codebook scene) and keeps a checkpoint; the same command resumes.",
    )
    p.add_argument("scene", type=Path, metavar="SCENE", help="trained 3DGS scene (PLY, INRIA or compressed; .splat; .spz)")
    p.add_argument("--source", type=Path, required=True, help="dataset folder: COLMAP (sparse/0), transforms.json or 3DGS cameras.json")
    p.add_argument("--features", type=Path, required=True, help="LangSplat feature folder (<stem>_s.npy, <stem>_f.npy)")
    p.add_argument("--level", type=mask_level, default=DEFAULT_LEVEL, help=f"mask level of the feature files: an index or LangSplat's name, default, s, m or l (default: {DEFAULT_LEVEL}, 's')")
    p.add_argument("--topk", type=topk_int, default=DEFAULT_TOPK, help=f"Gaussians kept per pixel (default: {DEFAULT_TOPK})")
    p.add_argument("--codebook", type=text_value, default=DEFAULT_CODEBOOK,
                   help="'none' (exact float16 features, the default), 'scene' (PQ trained on this scene) or a faiss codebook file")
    p.add_argument("--aggregate", choices=AGGREGATE_MODES, default=DEFAULT_AGGREGATE,
                   help="how pixel weights become Gaussian features: paper (Dr. Splat's weighted mean), core / ellipse "
                   "(weight by the Gaussian's own falloff / only its 2-sigma ellipse), responsibility (w / pixel sum), "
                   "centre / anchor (only / also a vote at the pixel of its projected centre), explain (per-view EM: "
                   "who explains each pixel's mask), sharp (the Gaussian's footprint before 3DGS's 0.3 px2 screen filter: "
                   "masks that follow true silhouettes), fit (paper or sharp, whichever re-renders a few probe views' masks "
                   "better), *-check (drop the masks the other views contradict), *-vote (the mean trimmed of masks a minority of views vote for: "
                   "mislabelled masks), *-reject (also leave floaters unassigned); stages combine as "
                   "WEIGHTING[-check][-vote][-reject]; see docs/registration.md (default: %(default)s)")
    p.add_argument("--keep-unassigned", action="store_true",
                   help="keep Gaussians that got no weight (lang_weight 0) instead of pruning them")
    p.add_argument("--resolution", type=resolution_value, default=-1,
                   help="camera resolution as 3DGS's -r: 1, 2, 4, 8 divide, another number is a width in pixels; "
                   "default -1: full size, capped at 1600 px wide. Smaller views register faster and less exactly: 2 measured "
                   "1.7x (flowers) to 2.6x (a 640x480 room) faster per view and -0.013 seg mIoU on that room (docs/evaluation.md, "
                   "\"Resolution\"; `drsplat eval ablate resolution`)")
    add_principal_point_argument(p)
    add_near_plane_argument(p, "a view is rendered with; 'inria' (0.2) is the plane of the INRIA rasterizer that trained LangSplat's and "
                               "Dr. Splat's scenes, which never drew nearer Gaussians in that view", auto=True)
    p.add_argument("--out", type=output_file, required=True, metavar="REGISTERED.ply", help="registered PLY to write")
    p.add_argument("--memory-budget", type=size_value, default=None, metavar="SIZE",
                   help="memory the registration may use (e.g. 8GB); when the in-memory estimate exceeds it, Gaussians are "
                   "streamed in blocks through a pair log on disk, with the same output. Default: in memory if it fits the "
                   "memory available, else stop and say which budget fits")
    p.add_argument("--ray", nargs="?", type=ray_address, const="local", default=None, metavar="ADDRESS",
                   help="compute views on a Ray cluster (pip install 'drsplat[ray]'): ADDRESS of a running cluster "
                   "(host:port or 'auto'), or no value to start a local one; same output as without")
    p.add_argument("--ray-workers", type=positive_int, default=None, metavar="N", help="Ray tasks at once (default: the cluster's CPUs)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_device_arguments(p)
    p.set_defaults(func=run, interrupted_note=interrupted_note)


def interrupted_note(args: argparse.Namespace, exc: BaseException | None = None) -> str:
    """What a stopped registration's last line adds: that the same command resumes, when a checkpoint is
    there (kept by an earlier run that this one was stopped before resuming from). One kept by this
    run was said by its own warning just above (`Checkpoint.leave`: `exc.checkpoint_said`), with its
    views: not twice."""
    from drsplat.errors import INTERRUPTED_NOTE, shown_path
    from drsplat.registration.checkpoint import checkpoint_path_for

    checkpoint = checkpoint_path_for(args.out)
    if getattr(exc, "checkpoint_said", False) or not checkpoint.is_file():
        return INTERRUPTED_NOTE
    return f"{INTERRUPTED_NOTE}; the registration checkpoint {shown_path(checkpoint)} is kept, and the same command resumes from it"


def run(args: argparse.Namespace) -> int:
    from drsplat.cameras import dataset_inputs, load_cameras
    from drsplat.cluster import LOCAL_ADDRESSES, check_reachable
    from drsplat.errors import InputError, UsageError
    from drsplat.lang import REGISTERED_IS_PLY, codebook_name_for, header_text_problem, other_data_name, written_codebook_path
    from drsplat.registration import RegisterOptions
    from drsplat.registration.checkpoint import checkpoint_path_for, lock_run
    from drsplat.splat_formats import written_format

    if written_format(args.out) != "ply":
        raise UsageError(f"--out {args.out.name}: {REGISTERED_IS_PLY}; name it .ply")
    device, engine = resolve_compute(args)  # before any loading: a missing GPU is the first thing to say
    if args.ray_workers is not None and args.ray is None:
        log.warning("--ray-workers %d applies to a run on Ray (--ray); without it the views are computed here", args.ray_workers)
    if args.ray not in (None, "auto", *LOCAL_ADDRESSES):  # before the scene is read and the probe views rendered (round 90c F2)
        check_reachable(args.ray)
    decided = args.near_plane == "auto"  # decided from the scene and its images once they are read
    options = RegisterOptions(topk=args.topk, level=args.level, codebook=args.codebook, keep_unassigned=args.keep_unassigned,
                              memory_budget=args.memory_budget, ray=args.ray, ray_workers=args.ray_workers, engine=engine, device=device,
                              aggregate=args.aggregate, near_plane=NEAR if decided else args.near_plane)
    options.check()
    codebook_file = Path(args.codebook) if args.codebook not in ("none", "scene") else None
    if codebook_file is not None and not codebook_file.exists():  # round 57c: a misspelt keyword was only "codebook file not found"
        raise InputError(codebook_file, "codebook file not found (--codebook takes 'none', 'scene' or a faiss codebook file)")
    written_codebook = written_codebook_path(args.out) if args.codebook != "none" else None
    if codebook_file is not None and written_codebook is not None and written_codebook.resolve() == codebook_file.resolve():
        written_codebook = None  # the codebook already sits where the registered PLY names it
    named = codebook_name_for(args.out) if args.codebook != "none" else None
    problem = header_text_problem("", named)  # said now, not after the whole registration (the manifest's CLIP id is checked as it is read)
    if problem is not None:
        raise UsageError(f"--out {json.dumps(str(args.out))[:80]}: {problem}")
    # the cameras come first: the files they were read from and the images they name are inputs too
    cameras = load_cameras(args.source, resolution=args.resolution, require_images=False)
    guard_args(args, ("out",), extra_inputs={"--codebook": codebook_file, **dataset_inputs(args.source, cameras)},
               extra_outputs={"the codebook written beside --out": written_codebook},
               protected_folders=protected_feature_folders("--features", [args.features]))
    # before the views: a write-protected --out or codebook beside it was refused after the whole registration (round 60a);
    # a folder that takes no file is said when the run's lock is taken, naming the folder
    for written in (args.out, written_codebook):
        if written is not None:
            refuse_write_protected(output_target(written))
    other = other_data_name(args.out)
    if other is not None:  # after the input guard, whose message names the input it would hit
        raise UsageError(f"--out {other}")
    # a second run into --out is refused before the scene is read (round 67b F1: after 21 s and 1.5 GB of a 3M scene and the
    # near plane's decision), and the lock is held from here to the registration's end (round 68a F1: taken and released, it
    # let a second run through while the first read its scene); no folder, no run in it: the registration makes the folder
    # once the inputs are read (round 68b F1: a run whose scene was missing left it empty)
    checkpoint = checkpoint_path_for(args.out)
    lock = lock_run(checkpoint) if checkpoint.parent.is_dir() else None
    try:
        return _register_holding(args, lock, cameras, options, decided)
    finally:
        if lock is not None:  # the registration's own once it began (released there); here when the run stopped before it
            lock.release()


def _register_holding(args: argparse.Namespace, lock: RunLock | None, cameras: list[Camera], options: RegisterOptions, decided: bool) -> int:
    """`run` from the scene on, `lock` (the run's lock, or None) held: reads the scene, decides the cameras' frame, near plane
    and principal points, and registers."""
    from drsplat.errors import DrsplatError, shown_path
    from drsplat.features.format import list_stems
    from drsplat.frames import DECISION_HELD_BYTES, FIRST_COMPILE_HELD_BYTES, cameras_and_plane_as_trained, refinement_comment
    from drsplat.raster import kernels_cached
    from drsplat.memory import trim_heap
    from drsplat.registration import register
    from drsplat.registration.driver import prepare_run, refuse_if_over_budget, say_if_kernels_compile
    from drsplat.registration.plan import refuse_below_scene_floor
    from drsplat.splat_formats import declared_scene_size, load_scene_report

    size = declared_scene_size(args.scene) if options.memory_budget is not None else None
    if size is not None:  # a budget its reading would exceed is refused before the scene is loaded over it
        refuse_below_scene_floor(options.memory_budget, *size, shown_path(args.scene))
    scene, report = load_scene_report(args.scene, purpose="register")  # refuses a file with no usable row; ~1 s of compiling at first
    if args.features.is_dir() and list_stems(args.features):  # before the near plane's decision and the views, which compile (round
        say_if_kernels_compile(options)  # 68a F4), after what refuses a run at once: a scene or feature folder unread (70a F7, 71a F4)
    dropped = report.dropped_nan_rows + report.dropped_inf_rows
    if args.keep_unassigned and dropped:  # the option's promise is row-for-row with the scene file
        log.warning("--keep-unassigned: %d of the %d rows of %s were dropped on loading (non-finite values), so the registered "
                    "PLY has %d rows and its row i is not always the file's row i; drop those rows from the scene file first "
                    "to keep the two files row for row", dropped, report.rows_in_file, args.scene, report.rows_in_file - dropped)
    def refuse_before_deciding(framed: list) -> None:  # a run the plan refuses is refused before the plane's evidence is rendered
        if decided:
            # the run says its warnings; the decision's kernels and image readers stay resident, and a first run's compiler
            held = DECISION_HELD_BYTES + (FIRST_COMPILE_HELD_BYTES if options.engine == "numba" and not kernels_cached() else 0)
            try:
                refuse_if_over_budget(prepare_run(scene, framed, args.features, options, quiet=True), held_later=held)
            except DrsplatError:  # its warnings explain the refusal (feature files that match no camera): said once, then it
                prepare_run(scene, framed, args.features, options)  # (round 68a F7: a fixed plane's run said them, auto's did not)
                raise

    # trainers' own worlds, cameras, near planes and principal points
    cameras, plane = cameras_and_plane_as_trained(scene, cameras, args.source, args.principal_point, args.near_plane, what=str(args.scene),
                                                  scene_path=args.scene, refinements=report.camera_refinements,
                                                  before_deciding=refuse_before_deciding)
    options = dataclasses.replace(options, near_plane=plane, near_plane_decided=decided)
    if decided:  # the decision's images and renders are freed, and the memory plan starts from this process's resident memory
        trim_heap()  # (round 66a F4: a --memory-budget a fixed plane accepts was refused after `auto`, or ran in more blocks)
    comment = refinement_comment(args.scene) if report.camera_refinements is not None else None
    if comment is not None:  # `eval lerf` of the registered scene then takes its cameras as registration did
        scene = dataclasses.replace(scene, comments=[*scene.comments, comment])
    token = CancelToken()
    with cancel_on_signals(token, "the current step (a view, the fit stage's probe view, a run of the check's masks or a sub-quantiser "
                                  "of the scene codebook)"):
        register(scene, cameras, args.features, args.out, options, show_progress=not args.no_progress, cancel=token, lock=lock,
                 say_first_run=False)
    if token.cancelled:  # the interrupt came while the output was being finished: it was completed, not left half done
        log.warning("the interrupt came after the last view; the output was finished and written to %s", shown_path(args.out))
    return 0
