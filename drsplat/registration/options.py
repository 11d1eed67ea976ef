"""What a user chooses for one registration: `RegisterOptions`, checked up front in one sentence each."""

from __future__ import annotations

import math
from dataclasses import dataclass

from drsplat.cluster import ClusterOptions
from drsplat.defaults import AGGREGATE_MODES, DEFAULT_AGGREGATE, DEFAULT_CODEBOOK, DEFAULT_LEVEL, DEFAULT_TOPK, MAX_TOPK
from drsplat.errors import UsageError
from drsplat.defaults import NEAR
from drsplat.registration.compute import check_engine


NEAR_PLANE_COMMENT = "drsplat.near_plane "  # the registered PLY's header line naming a plane other than NEAR


def near_plane_comment(plane: float) -> str | None:
    """The header comment a registration at `plane` writes into its PLY (None at the default NEAR, so
    default files are as they were), which `eval lerf` reads back (`recorded_near_plane`)."""
    return None if plane == NEAR else f"{NEAR_PLANE_COMMENT}{float(plane)!r}"


def recorded_near_plane(comments) -> float | None:
    """The plane a registered PLY's header comments record (`near_plane_comment`), or None: none
    recorded, or one that is no positive finite depth (a header is the file's word, not checked)."""
    for comment in comments:
        if comment.startswith(NEAR_PLANE_COMMENT):
            try:
                plane = float(comment[len(NEAR_PLANE_COMMENT):])
            except ValueError:
                return None
            return plane if math.isfinite(plane) and plane > 0 else None
    return None


@dataclass(frozen=True)
class RegisterOptions:
    """The CLI flags of `drsplat register` and the viewer's registration panel.

    topk: Gaussians kept per pixel. level: the LangSplat mask level. codebook: "none" (exact float16
    field), "scene" (PQ trained on this scene) or a faiss codebook path. keep_unassigned: keep
    Gaussians that got no weight (lang_weight 0) instead of pruning them.
    memory_budget: bytes the registration may use; None: one block if it fits the memory available,
    else an error that gives the budget to pass (drsplat.registration.plan). block_size: Gaussians
    per block whatever the estimate (tests, benches). ray: a Ray cluster address ("" or "local"
    starts a local one) that computes the views; ray_workers: tasks at once (default: the cluster's
    CPUs). engine, device: the rasterizer ("numba" on "cpu", "torch" on "cpu" / "cuda").
    aggregate: the aggregation mode (drsplat.defaults.AGGREGATE_MODES; "paper" is Dr. Splat's, the
    default "fit-check-vote-reject" weights by the footprint the masks follow (drsplat.registration.fit),
    drops the masks the other views contradict, trims its mean by votes across views and rejects floaters).
    cull: each view projects only the Gaussians it can see (exact; drsplat.registration.culling).
    near_plane: the camera depth (scene units) below which a Gaussian is not drawn in a view: NEAR (0.01,
    gsplat's) or INRIA_NEAR (0.2, the rasterizer most scenes were trained with; docs/raster.md).
    near_plane_decided: near_plane was decided from the training images (`register --near-plane auto`), not given:
    an error about it names the decision, not a flag the user never typed (round 67a F10).
    reducers: on Ray and in blocks, each block is summed, finished, encoded and written by a Ray
    task (drsplat.registration.reduce; the same bytes); False: by the driver, block after block.
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
    cull: bool = True
    reducers: bool = True
    near_plane: float = NEAR
    near_plane_decided: bool = False

    @property
    def place(self) -> str:
        """Where the views are computed: "local" or "ray" (drsplat.registration.executor.EXECUTORS)."""
        return "local" if self.ray is None else "ray"

    @property
    def cluster(self) -> ClusterOptions:
        return ClusterOptions(self.ray, self.ray_workers)

    def check(self) -> None:
        """UsageError naming the first option that cannot run (before anything is loaded or computed)."""
        if not 1 <= self.topk <= MAX_TOPK:
            raise UsageError(f"topk must be between 1 and {MAX_TOPK}, got {self.topk}")
        if self.level < 0:
            raise UsageError(f"level must be >= 0, got {self.level}")
        if self.aggregate not in AGGREGATE_MODES:
            raise UsageError(f"unknown aggregation mode {self.aggregate!r}; choose from {', '.join(AGGREGATE_MODES)}")
        for name in ("memory_budget", "block_size", "ray_workers"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise UsageError(f"{name.replace('_', '-')} must be at least 1, got {value}")
        if not (math.isfinite(self.near_plane) and self.near_plane > 0):
            raise UsageError(f"near-plane must be a positive, finite camera depth in scene units, got {self.near_plane!r}")
        check_engine(self.engine, self.device)
