"""The one registration pipeline: scene -> cameras -> features -> registration -> field -> registered PLY.

`drsplat register`, the viewer's registration panel and the benches all call `register_to_ply`, so the
same inputs give the same file whatever starts the work (a test checks the CLI and the viewer agree).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drsplat.cameras import Camera
from drsplat.errors import DrsplatError
from drsplat.features.format import read_manifest
from drsplat.features.modelid import manifest_model_id
from drsplat.lang import LanguageField, attach_field, build_field
from drsplat.defaults import DEFAULT_AGGREGATE, DEFAULT_CODEBOOK, DEFAULT_LEVEL, DEFAULT_TOPK
from drsplat.registration import RegistrationResult, register_scene
from drsplat.scene import GaussianScene, save_ply
from drsplat.utils import CancelToken

log = logging.getLogger(__name__)


@dataclass
class RegisterOptions:
    """What a user chooses for one registration (the CLI flags and the viewer's panel).

    codebook: "none" (exact float16 field), "scene" (PQ trained on this scene) or a faiss codebook path.
    keep_unassigned: keep Gaussians that got no weight (lang_weight 0) instead of pruning them.
    memory_budget: bytes the registration may use; when the in-memory estimate exceeds it, Gaussians
    are streamed in blocks (drsplat.streaming, same file). None: in memory if it fits the memory
    available, else an error that gives the figure and the budget to pass.
    block_size: stream with blocks of this many Gaussians whatever the estimate (tests, benches).
    ray: a Ray cluster address ("" or "local" starts a local one) computing views on workers
    (drsplat.distributed); ray_workers: how many worker tasks at once (default: the cluster's CPUs).
    aggregate: aggregation mode (drsplat.aggregate.MODES; "paper" is Dr. Splat's weighted mean).
    engine, device: registration's compute engine ("numba" on "cpu", or "torch" on "cpu"/"cuda"; drsplat.device).
    """

    topk: int = DEFAULT_TOPK
    level: int = DEFAULT_LEVEL
    codebook: str = DEFAULT_CODEBOOK
    keep_unassigned: bool = False
    memory_budget: int | None = None
    block_size: int | None = None
    ray: str | None = None
    ray_workers: int | None = None
    engine: str = "numba"
    device: str = "cpu"
    aggregate: str = DEFAULT_AGGREGATE


@dataclass
class PipelineResult:
    """What `register_to_ply` wrote: the PLY path, the field (None when streamed) and the registration's record."""

    path: Path
    field: LanguageField | None
    registration: RegistrationResult
    num_written: int


def checkpoint_path_for(out: str | Path) -> Path:
    """The hidden resumable checkpoint (pair log) of a registration that writes `out`."""
    out = Path(out)
    return out.with_name(f".{out.name}.register.log")


def register_to_ply(
    scene: GaussianScene,
    cameras: Sequence[Camera],
    features_dir: str | Path,
    out: str | Path,
    options: RegisterOptions = RegisterOptions(),
    *,
    show_progress: bool = True,
    on_progress: Callable[[int, int], None] | None = None,
    cancel: CancelToken | None = None,
    resumable: bool = True,
    executor=None,
) -> PipelineResult:
    """Register `features_dir` onto `scene` and write the registered PLY `out` atomically.

    resumable: keep a checkpoint beside `out` while working (a cancelled or killed run resumes from it);
    it is deleted once `out` is written. executor: where views are computed (default: from
    options.ray, else this process); one passed in is not closed here.
    """
    from drsplat.registration import feature_dim, select_views
    from drsplat.streaming import choose_block, estimate_memory, register_streaming

    features_dir, out = Path(features_dir), Path(out)
    clip_model = manifest_model_id(read_manifest(features_dir))
    views = select_views(cameras, features_dir)[0]
    dim = feature_dim(features_dir, views)
    codebook = resolve_codebook(options.codebook, dim)  # a bad codebook fails now, not after registering
    block = options.block_size
    if block is None:
        plan = estimate_memory(scene, views, dim, options.topk, aggregate=options.aggregate)
        block = choose_block(plan, options.memory_budget)
        log.info("estimated peak memory: %.1f GB in memory%s", plan.in_memory / 1e9,
                 "" if block is None else f", {plan.streaming(block) / 1e9:.1f} GB streamed in blocks of {block:,} Gaussians")
    ckpt = checkpoint_path_for(out) if resumable or block is not None else None
    owned = executor is None
    executor = make_executor(options) if owned else executor
    try:
        if block is not None:
            streamed = register_streaming(
                scene, cameras, features_dir, out, block_size=block, checkpoint=ckpt, topk=options.topk, level=options.level,
                codebook=codebook, clip_model=clip_model, keep_unassigned=options.keep_unassigned,
                executor=executor, show_progress=show_progress, on_progress=on_progress, cancel=cancel,
                aggregate=options.aggregate, engine=options.engine, device=options.device,
            )
            _remove_checkpoint(ckpt)
            log.info("%s: %d Gaussians in %d blocks of %d, %s field, %d views, %.1f s", out, streamed.num_written, streamed.num_blocks,
                     block, streamed.field_kind, streamed.registration.num_views, streamed.registration.seconds)
            return PipelineResult(out, None, streamed.registration, streamed.num_written)
        result = register_scene(
            scene, cameras, features_dir, topk=options.topk, level=options.level, show_progress=show_progress,
            on_progress=on_progress, cancel=cancel, checkpoint=ckpt, keep_checkpoint=True,
            collect_embeddings=options.codebook == "scene", executor=executor, engine=options.engine, device=options.device,
            aggregate=options.aggregate,
        )
    finally:
        if owned and executor is not None:
            executor.close()
    if result.num_assigned == 0:
        raise DrsplatError(nothing_assigned(result.num_views, features_dir, out))
    keep = np.ones(scene.num_gaussians, bool) if options.keep_unassigned else result.assigned
    field = build_field(result.features[keep], result.weights[keep], codebook=codebook, clip_model=clip_model,
                        train_embeddings=result.mask_embeddings)
    result.features = None  # the [N, D] sums are not needed for writing: free them first
    if cancel is not None:
        cancel.raise_if_cancelled()
    out_scene = attach_field(scene.subset(keep), field, out)
    save_ply(out_scene, out)
    if ckpt is not None:
        _remove_checkpoint(ckpt)
    log.info(
        "%s: %d Gaussians (%d unassigned, %s), %s field, %d views, %.1f s",
        out, out_scene.num_gaussians, scene.num_gaussians - result.num_assigned,
        "kept with lang_weight 0" if options.keep_unassigned else "pruned", field.kind, result.num_views, result.seconds,
    )
    return PipelineResult(out, field, result, out_scene.num_gaussians)


def nothing_assigned(num_views: int, features_dir: Path, out: Path) -> str:
    """The error when registration gave no Gaussian a feature (nothing is written)."""
    return (f"no Gaussian received a language feature from {num_views} views: the cameras do not see the scene "
            f"or every mask of {features_dir} is empty or invalid; nothing was written to {out}")


def resolve_codebook(codebook: str, dim: int):
    """'none' / 'scene' as given, or the faiss codebook file loaded and checked against the features' D."""
    from drsplat.errors import InputError
    from drsplat.lang import load_codebook

    if codebook in ("none", "scene"):
        return codebook
    book = load_codebook(codebook)
    if book.dim != dim:
        raise InputError(book.path, f"codebook dimension {book.dim} differs from the features' dimension {dim} (a different CLIP model?)")
    return book


def _remove_checkpoint(ckpt: Path) -> None:
    """Delete the pair log and an aggregation mode's statistics beside it (the output is safe)."""
    from drsplat.registration import aggregate_stats_path

    ckpt.unlink(missing_ok=True)
    aggregate_stats_path(ckpt).unlink(missing_ok=True)


def make_executor(options: RegisterOptions):
    """The Ray executor when options.ray is set, else None (views computed in this process)."""
    if options.ray is None:
        return None
    from drsplat.distributed import RayExecutor

    return RayExecutor(options.ray, workers=options.ray_workers)
