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
    aggregate: aggregation mode (drsplat.aggregate.MODES; "paper" is Dr. Splat's weighted mean).
    engine, device: registration's compute engine ("numba" on "cpu", or "torch" on "cpu"/"cuda"; drsplat.device).
    """

    topk: int = DEFAULT_TOPK
    level: int = DEFAULT_LEVEL
    codebook: str = DEFAULT_CODEBOOK
    keep_unassigned: bool = False
    engine: str = "numba"
    device: str = "cpu"
    aggregate: str = DEFAULT_AGGREGATE


@dataclass
class PipelineResult:
    """What `register_to_ply` wrote: the PLY path, the field and the registration's record."""

    path: Path
    field: LanguageField
    registration: RegistrationResult
    num_written: int


def checkpoint_path_for(out: str | Path) -> Path:
    """The hidden resumable checkpoint of a registration that writes `out`."""
    out = Path(out)
    return out.with_name(f".{out.name}.register.npz")


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
) -> PipelineResult:
    """Register `features_dir` onto `scene` and write the registered PLY `out` atomically.

    resumable: keep a checkpoint beside `out` while working (a cancelled or killed run resumes from it);
    it is deleted once `out` is written.
    """
    features_dir, out = Path(features_dir), Path(out)
    clip_model = manifest_model_id(read_manifest(features_dir))
    ckpt = checkpoint_path_for(out) if resumable else None
    result = register_scene(
        scene, cameras, features_dir, topk=options.topk, level=options.level, show_progress=show_progress,
        on_progress=on_progress, cancel=cancel, checkpoint=ckpt, keep_checkpoint=True,
        collect_embeddings=options.codebook == "scene", engine=options.engine, device=options.device,
        aggregate=options.aggregate,
    )
    if result.num_assigned == 0:
        raise DrsplatError(
            f"no Gaussian received a language feature from {result.num_views} views: the cameras do not see the scene "
            f"or every mask of {features_dir} is empty or invalid; nothing was written to {out}"
        )
    keep = np.ones(scene.num_gaussians, bool) if options.keep_unassigned else result.assigned
    field = build_field(result.features[keep], result.weights[keep], codebook=options.codebook, clip_model=clip_model,
                        train_embeddings=result.mask_embeddings)
    if cancel is not None:
        cancel.raise_if_cancelled()
    out_scene = attach_field(scene.subset(keep), field, out)
    save_ply(out_scene, out)
    if ckpt is not None:
        ckpt.unlink(missing_ok=True)
    log.info(
        "%s: %d Gaussians (%d unassigned, %s), %s field, %d views, %.1f s",
        out, out_scene.num_gaussians, scene.num_gaussians - result.num_assigned,
        "kept with lang_weight 0" if options.keep_unassigned else "pruned", field.kind, result.num_views, result.seconds,
    )
    return PipelineResult(out, field, result, out_scene.num_gaussians)
