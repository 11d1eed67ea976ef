"""The fit stage (`--aggregate fit...`): do the masks follow the Gaussians' filtered footprints or
their sharp ones?

Whether a view's masks follow the footprints the rasterizer draws (3DGS's 0.3 px² screen-space
low-pass filter included: the `paper` weights w) or the objects' true silhouettes (the surface
patches themselves, sampled at the pixel centres: the `sharp` weights w̃ of
drsplat.registration.aggregate) depends on the scene, its training and its segmenter, which a user
cannot know, and it decides which weighting is right: on thin and small objects each loses where
the other wins (docs/evaluation.md, "The fit stage"). The fit stage asks the data. In P probe views
(`ProbeOrder`: the camera poses in farthest-point order, passing over views that cannot score) and
for each footprint u ∈ {paper, sharp}:

    ℓ_u(g) = argmax_j Σ_{p : m(p) = j} u_g(p)         the view's own labelling of its Gaussians
    r_u(p) = argmax_j Σ_s u_s(p)·[ℓ_u(g_s) = j]         that labelling re-rendered (s: p's top-k slots)
    S_u    = mean over the masks j of the view of IoU({p : m(p) = j}, {p : r_u(p) = j})

with m(p) the view's mask ids (-1 none; masks with the very same embedding are one label,
`same_embedding`); ties go to the lower mask id, a Gaussian with no weight on
any mask takes no label, a pixel with no labelled weight renders none. S_u asks whether a view's own
labelling re-renders its masks; it can prefer the filtered footprint although the sharp one labels
the Gaussians better (an independent generator's exact silhouettes, docs/evaluation.md, "The fit
stage's held-out score"). So each labelling is also scored on the later probe views, whose masks
did not make it: for probe views a < b,

    τ(j)      = argmax_{g in b's masks} cos(f_a(j), f_b(g))        a's mask j as b's most alike mask
    H_u(a, b) = S of b with ℓ_u of view a mapped through τ, re-rendered with b's weights u

(`translate_labels`; the labellings are kept sparse, `HeldOut`). The registration
then runs with the sharp weights when the probe views' mean of S_sharp - S_paper is above zero or the
pairs' mean of H_sharp - H_paper is above HELD_OUT_MIN_MARGIN (on masks drawn from the footprints
H's margin stayed at or below +0.0009 over 126 rooms, though it goes far below zero, to -0.10; round
36 measured -0.078 on a merged room), and with the paper's otherwise (`FitChoice.decide`); a probe
view with no mask over a Gaussian it sees is left out of both means (`scores_footprints`):
"fit-vote-reject" becomes "sharp-vote-reject" or "vote-reject" (`resolve_mode`), and everything
downstream (places, blocks, the pair log's header) sees that mode. The probe renders on the CPU
with the numba engine, so every CPU engine and place decides alike, bit for bit; a pass of the torch
engine on a GPU in this process renders its probe views there (`probe_engine`), whose top-k lists
equal numba's but for near-ties and the weights' last float32 bit.

A mode that rejects floaters (`...-reject`, the default) leaves out of every labelling it scores
in probe view b the Gaussians its rejection would leave unassigned on the probe views up to b (their
floater statistics folded in probe order, `probe_floaters`): the registration gives them no label,
and their labels are noise to the scores. Faint dust over a table of small objects labels each
grain with whatever lies behind it in one view, which lies elsewhere in the next: it moved H's
margin from +0.094 to -0.021 on an independent generator's room, whose silhouette masks the sharp
footprint labels 0.929 right against the paper's 0.853 (docs/evaluation.md, "Floaters left out of
the fit's scores"). A mode without rejection keeps its floaters labelled, so its fit scores them.

Cost: per probe view one top-k render (culled as the view pass culls, on the registration's
geometry without its SH), the sharp weights, two coalescings and two re-render passes, O(H·W·k):
each pass re-renders the view's own labelling and every earlier probe view's translated one
(`rerender_scores`: 2P passes over the slots for P probe views, where one labelling a pass took P(P + 1);
the figures below are of 4 probe views, before round 41 made them 8).
Measured on flowers at 640x480 (region masks, 2 threads, alternated, two sessions' hours): the stage
2.68-2.74 -> 2.33-2.36 s and 2.38-2.50 -> 2.18-2.23 s; on a 320x240 room 0.18-0.19 s either way. When
the view pass computes views as the probe does (numba, in this process), the chosen footprint's
pairs are kept (`FitStage.pairs`) and the pass uses them instead of rendering those views again,
so the stage's own cost is the sharp weights, one coalescing and the re-renders.

A view whose mask map is coarser than the view is probed at the map's resolution (`probe_view`: the
camera scaled to it), since which footprint masks follow shows at their own resolution; the view
pass renders it again at the view's. A map finer than the view is resampled to it (nearest), as the
view pass reads it: at 2x, a noisy room's margin fell from +0.029 to -0.030 (round 22; probing at the
map's resolution gave +0.035, but a probe render of 4x the pixels is not in the memory plan).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numba
import numpy as np

from drsplat.cameras import Camera
from drsplat.raster import NEAR, PreparedScene
from drsplat.registration.aggregate import RayGeometry, SurfaceSupport, mode_hook, mode_stages
from drsplat.registration.coalesce import Coalescer
from drsplat.registration.compute import ViewComputer, ViewJob, pairs_by_gaussian, prepare_geometry
from drsplat.registration.culling import SpatialIndex
from drsplat.registration.pairlog import ViewPairs
from drsplat.registration.plan import PAIR_BYTES, view_pairs_bound
from drsplat.features.format import read_features_report, resample_nearest, seg_path
from drsplat.lang.codebook import unit_rows64
from drsplat.registration.views import check_aspect, read_feature_headers
from drsplat.scene import GaussianScene, scene_ball
from drsplat.utils import CancelToken

log = logging.getLogger(__name__)

FIT_PROBES = 8  # probe views of the fit stage that score (`ProbeOrder`; all views when there are fewer); as many more may be passed over
FOOTPRINTS = ("paper", "sharp")
# the re-render's per-part tables: per label and labelling its float64 sum and int32 mark, and per
# mask its int32 counts (`rerender_scores`; 64 MB: a 2-million-mask view re-renders one labelling a
# pass in one part, ~40 MB, where a table per labelling and thread asked 160 MB per thread)
RERENDER_LABEL_BYTES = 20
RERENDER_TABLE_BYTES = 1 << 26
# H_sharp - H_paper that takes the sharp footprint where S does not: over 126 rooms of footprint masks
# (7 presets x clean, jittered, 10 / 20 % mislabels, merged, split; seeds 0-2) H's margin reached
# +0.0009, and the sharp footprint there cost up to 0.105 (docs/evaluation.md, "The fit stage's
# held-out score"); on an independent generator's silhouettes it was +0.0024 to +0.020 where S chose wrong
HELD_OUT_MIN_MARGIN = 0.002
TRANSLATION_BLOCK_BYTES = 1 << 26  # the held-out score's cosines [rows, G] float64 made at once (`mask_translation`)
# What the probe holds beyond what the view pass's own plan counts (drsplat.registration.plan: the
# geometry, the culling index and the rays it makes are the pass's, and counted there per Gaussian):
# the kernels and libraries its first views load; the probe views' pairs it keeps for the pass, at
# most `probe_keep_bytes` (a view past it is rendered again by the pass: the same pairs); and while a
# probe view is scored, its dense labellings [N, 1 + E] int32 (E earlier probe views) and its own
# labels [N]. Until 2026-12-03 this was 512 bytes per Gaussian measured on rooms of ≤ 295k
# Gaussians, the geometry and rays counted twice: a 20M-Gaussian city was refused at 20.9 GB for
# one view, and peaked at 9.8 GB in its view pass.
PROBE_LOAD_BYTES = 96 << 20
PROBE_KEEP_BYTES = 256 << 20
# below PROBE_KEEP_BYTES, the probe keeps this much per Gaussian of the scene (`probe_keep_bytes`): both
# footprints' pairs of the 8 probe views took 133-188 bytes per Gaussian on the hard rooms and the demo
PROBE_KEEP_PER_GAUSSIAN = 1024
PROBE_KEEP_MIN = 32 << 20
PROBE_LABEL_BYTES = 4 * (FIT_PROBES + 2)
PROBE_STATS_BYTES = 28  # a probe view's floater statistics of one Gaussian it saw (id, peak, total, in front)
# a rejecting mode's probe (`probe_folds_floaters`): the probe views' statistics folded (SurfaceSupport,
# 32 bytes a Gaussian), the last view's rejected set (1) and what `rejected` makes while it runs (a
# float64 and some bool temporaries: 10 measured); tests/test_fit.py measures the peak
PROBE_SUPPORT_BYTES = 48
HELD_OUT_BYTES = 8  # a probe view's sparse labelling kept for the later ones (`HeldOut`): id and mask per Gaussian it labels


def probe_memory(num_gaussians: int, embedding_bytes: int = 0, rejects: bool = False, max_masks: int = 0) -> int:
    """Bytes the fit stage's probe adds to the process's resident memory beyond the view pass's plan
    (PROBE_LOAD_BYTES and the constants below it; an estimate, on the safe side where a view's masks
    are few next to its pixels, as they are from a segmenter). embedding_bytes: the largest view's
    mask embeddings (M·D·4), which no term of the view pass's plan counts (its vote and check count
    clusters, `fit` and `fit-reject` nothing): the probe holds every probe view's (`HeldOut`), and
    while a view is scored its own unit rows and an earlier view's, float64 (`probe_embedding_bytes`).
    rejects: the probe folds its views' floater statistics (`probe_folds_floaters`: PROBE_SUPPORT_BYTES).
    max_masks: the masks of the largest view (0: not known), which bound the translation's cosines."""
    per_gaussian = PROBE_LABEL_BYTES + (PROBE_SUPPORT_BYTES if rejects else 0)
    return PROBE_LOAD_BYTES + probe_keep_bytes(num_gaussians) + per_gaussian * num_gaussians + probe_embedding_bytes(embedding_bytes, max_masks)


def probe_keep_bytes(num_gaussians: int) -> int:
    """The most the probe keeps of its views' pairs for the view pass (views past it are rendered
    again by the pass, to the same pairs): PROBE_KEEP_PER_GAUSSIAN bytes per Gaussian of the scene
    within [PROBE_KEEP_MIN, PROBE_KEEP_BYTES]. Until 2026-12-05 every scene was charged 256 MB for
    it; hard-room (27,354 Gaussians) keeps ~7 MB."""
    return int(min(PROBE_KEEP_BYTES, max(PROBE_KEEP_MIN, PROBE_KEEP_PER_GAUSSIAN * num_gaussians)))


def probe_embedding_bytes(embedding_bytes: int, max_masks: int = 0) -> int:
    """What the probe's embeddings hold at most, views of `embedding_bytes` (M·D·4) each: the probe
    views' float32 rows kept for the held-out scores (`HeldOut`, FIT_PROBES views) and, while one is
    scored, its float64 unit rows and those of the earlier view being translated (2 x 2 x its bytes)
    with the translation's cosine block (`translation_block_bytes`). 0 when there are none. Until
    2026-12-03 `probe_memory` did not count them: `--aggregate fit` on 8 views of 20,000 masks of
    1024-D (82 MB a view) was accepted at 1.17 GB and peaked at 1.53 GB (VmHWM) in its probe."""
    if embedding_bytes <= 0:
        return 0
    return (FIT_PROBES + 4) * embedding_bytes + translation_block_bytes(max_masks)


def translation_block_bytes(max_masks: int = 0) -> int:
    """The most `mask_translation`'s cosines [rows, G] float64 hold at once for views of `max_masks`
    masks at most (rows ≤ max_masks, G ≤ max_masks; one row at the least): TRANSLATION_BLOCK_BYTES
    when that is not known (0)."""
    if max_masks <= 0:
        return TRANSLATION_BLOCK_BYTES
    return max(min(TRANSLATION_BLOCK_BYTES, 8 * max_masks * max_masks), 8 * max_masks)


def probe_memory_bound(num_gaussians: int, pixels: int, topk: int, embedding_bytes: int = 0, max_masks: int = 0, rejects: bool = False) -> int:
    """`probe_memory` with a probe view's pairs and statistics at their most: a pair per top-k slot of
    every pixel (thousands of masks a view split a Gaussian's pixels into as many pairs), but no more
    than every Gaussian in every mask (`plan.view_pairs_bound`), and statistics for every Gaussian
    they name: the view being scored holds them under both footprints, the kept views at most
    `probe_keep_bytes`. Then the earlier probe views' sparse labellings and embeddings (`HeldOut`) and
    the re-render's tables of one probe view scored (`rerender_table_bytes`: its own and the earlier
    views' labellings, labels below its masks). What a refusal's named budget is made from, so that
    the budget typed back is not refused once the probe has run. pixels: the largest view's;
    embedding_bytes: the largest view's mask embeddings (M·D·4), which its pairs hold too;
    max_masks: its masks (0: not known, then one per pixel); rejects: as `probe_memory`'s."""
    slots = pixels * topk
    seen = min(num_gaussians, slots)
    scored = view_pairs_bound(num_gaussians, pixels, topk, max_masks) * PAIR_BYTES + seen * PROBE_STATS_BYTES + embedding_bytes
    held_out = FIT_PROBES * len(FOOTPRINTS) * seen * HELD_OUT_BYTES  # each footprint keeps its own labellings (their embeddings: probe_memory)
    tables = rerender_table_bytes(FIT_PROBES, max_masks if max_masks > 0 else pixels, max(1, numba.get_num_threads()))
    return probe_memory(num_gaussians, embedding_bytes, rejects, max_masks) + len(FOOTPRINTS) * scored + held_out + tables


@dataclass
class FitChoice:
    """The fit stage's decision: footprint "paper" or "sharp"; views: the probe views' names; paper,
    sharp: [P] the scores S_u of the P probe views scored (those with a mask over a Gaussian they see,
    `scores_footprints`; `scored` names them); held_paper, held_sharp: [P(P-1)/2] their held-out
    scores H_u, one per pair of them (module docstring)."""

    footprint: str
    views: list[str]
    paper: np.ndarray
    sharp: np.ndarray
    held_paper: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    held_sharp: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    scored: list[str] | None = None  # the probe views scored; None: all of them
    floaters: int = 0  # Gaussians left out of the last probe view's labellings as floaters (a rejecting mode's; module docstring)

    def __post_init__(self) -> None:
        if self.scored is None:
            self.scored = list(self.views)

    @property
    def margin(self) -> float:
        """mean(S_sharp - S_paper) over the probe views (0 without any)."""
        return mean_or_zero(self.sharp - self.paper)

    @property
    def held_margin(self) -> float:
        """mean(H_sharp - H_paper) over the pairs of probe views (0 without any)."""
        return mean_or_zero(self.held_sharp - self.held_paper)

    def decide(self) -> str:
        """"sharp" when either score says the masks follow the sharp footprints (margin > 0 or
        held_margin > HELD_OUT_MIN_MARGIN), else "paper" (module docstring)."""
        return "sharp" if self.margin > 0.0 or self.held_margin > HELD_OUT_MIN_MARGIN else "paper"


def mean_or_zero(values: np.ndarray) -> float:
    """The mean of a fit score's values [P], 0 when there are none (no probe view, or no pair of them)."""
    return float(np.mean(values)) if len(values) else 0.0


def probe_engine(engine: str, device: str, place: str) -> tuple[str, str]:
    """(engine, device) the fit stage renders its probe views with, for a view pass of `engine` on
    `device` at `place`: the pass's own when it is the torch engine on a GPU in this process, else
    numba on the CPU (which culls, and is what a CPU or Ray pass decides with). On an H200 the probe
    rendered by numba on the host took 3.3 s of a 4.3 s registration of 10 flowers views, whose
    view pass takes 0.66 s (2026-12-04, docs/gpu.md); a Ray driver may have no GPU of its own."""
    if engine == "torch" and place == "local" and device != "cpu":
        return engine, device
    return "numba", "cpu"


def probe_folds_floaters(mode: str) -> bool:
    """Whether the fit stage of `mode` folds its probe views' floater statistics and scores its
    labellings without what they reject: exactly when the mode rejects floaters (module docstring)."""
    return mode_stages(mode).reject


def probe_floaters(support: SurfaceSupport | None, stats) -> np.ndarray | None:
    """[N] bool: the Gaussians floater rejection would leave unassigned on the probe views so far
    (`SurfaceSupport.rejected` after folding this view's statistics `stats` into `support`, the
    probe's running statistics), or None for a mode that rejects nothing (support None; a rejecting
    mode's hook always gives statistics)."""
    if support is None:
        return None
    support.add(stats)
    return support.rejected()


def scores_footprints(pair_weights: np.ndarray) -> bool:
    """Whether a probe view can score the footprints, from its pairs' weights [P] under the paper's
    footprint: some pair of weight > 0, i.e. some slot of weight > 0 in a pixel of a mask (pairs are
    summed over masked pixels only). A view without (no mask file's masks, or masks only over pixels
    it renders nothing in) would score 0 under both footprints: that leaves S's sign as it is, but
    its zeros would dilute H's mean toward 0, so that H could only keep the paper's footprint (round
    36). The sharp weights are w·max(·, SHARP_FLOOR) > 0 exactly where w > 0: one test serves both."""
    return bool(pair_weights.size and np.max(pair_weights) > 0)


@dataclass(frozen=True)
class ProbeSpace:
    """Where the fit stage measures the views' poses: the scene's ball (`scene.scene_ball`), its centre, from which the
    views are ranked (`ProbeOrder`), and its diameter `scale`, the length that weighs a view's direction against its
    position (`pose_points`). The scene's, not the cameras': a view added or left out then moves no other view's point.
    Both move with the world, so a rotated, moved or scaled copy of a capture (COLMAP's frame is arbitrary) probes
    the same views (round 83b F1: the first probe was the view of the lowest world coordinates)."""

    centre: np.ndarray  # [3]
    scale: float = 1.0

    @classmethod
    def unit(cls) -> ProbeSpace:
        return cls(np.zeros(3), 1.0)


def probe_space(scene: GaussianScene) -> ProbeSpace:
    """The scene's `ProbeSpace`; a scale of 1 for a scene without an extent."""
    centre, radius = scene_ball(scene.means)
    return ProbeSpace(centre, 2.0 * radius if np.isfinite(radius) and radius > 0.0 else 1.0)


def pose_points(views: Sequence[Camera], scale: float = 1.0) -> np.ndarray:
    """[V, 6] float64 each view's pose as a point: its camera centre c and its viewing direction d
    (the camera's +z in the world, R's last row) times `scale` (`ProbeSpace`):

        x_v = (c_v, scale·d_v)

    so that two views far apart and two views at one place looking different ways are both far
    apart, in the scene's units. Non-finite entries count as 0."""
    if not len(views):
        return np.zeros((0, 6))
    with np.errstate(over="ignore", invalid="ignore"):  # a hostile pose's overflow is the 0 below, not a numpy warning
        centres = np.array([v.ray_origin() for v in views], np.float64).reshape(-1, 3)
        ahead = np.array([np.asarray(v.R, np.float64)[2] for v in views]).reshape(-1, 3)
        points = np.concatenate([centres, scale * ahead], axis=1)
    return np.nan_to_num(points, nan=0.0, posinf=0.0, neginf=0.0)


PROBE_TIE = 1e-6  # `ProbeOrder` rounds distances (in diameters) and cosines to this step, and equal ones tie: the world's rounding, and the centre's float32 distances, decide nothing (two values either side of a step's edge do not tie, however close)


@dataclass
class ProbeOrder:
    """The order the fit stage probes the views in: farthest-point order of their poses
    (`pose_points`) over the views that score. The first is the view whose camera lies farthest from
    the scene's centre (`ProbeSpace`); each next one the pose farthest from the nearest of the views
    probed so far that scored (`scores_footprints`); a view that did not score is passed over and
    moves no distance. Distances and cosines are rounded to PROBE_TIE (of the diameter) and equal
    ones tie; ties go to the view farther from the centre, then to the one looking more toward it
    (the cosine between its direction and the centre's: a rig's views share one camera centre), then to
    the lower pose (compared coordinate by coordinate), the name and `Camera.exact_key`: never the
    list's order. Only an exactly symmetric capture (a ring of cameras around the centre, a rig's
    mirror-image views) or a rig whose camera centre is the scene's centre to the last bit (it has no
    direction to it: round 86a F3) gets to the pose, where nothing but the world's frame, the names or
    the list can tell its views apart. So the views probed depend on the cameras and the scene alone: not on the order
    a file lists them in (round 41: a shuffled transforms.json took other probe views and flipped
    the footprint, seg mIoU vol 0.594 -> 0.426), nor on their names, nor on views that see nothing
    (round 49: a room's views renamed, then one blind camera added, flipped the footprint twice,
    0.642 -> 0.498 -> 0.642, when the probes were evenly spaced in name order), nor on the world's
    frame (round 83b F1: the first probe was the lowest pose, compared coordinate by coordinate,
    and four of six rotations of that room flipped it again)."""

    points: np.ndarray  # [V, 6] pose_points
    rank: np.ndarray  # [V] each view's place in the tie order
    gap: np.ndarray  # [V] distance to the nearest probed view that scored (+inf before one has)
    open: np.ndarray  # [V] bool: not probed yet

    @classmethod
    def of(cls, views: Sequence[Camera], space: ProbeSpace | None = None) -> ProbeOrder:
        space = ProbeSpace.unit() if space is None else space
        points = pose_points(views, space.scale)
        digits = -round(math.log10(PROBE_TIE))
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            to_centre = space.centre - points[:, :3]
            distance = np.linalg.norm(to_centre, axis=1)
            away = np.nan_to_num(np.round(distance / space.scale, digits), nan=np.inf)
            # a rig's views share one camera centre (cube faces, a tripod panorama): the one looking most toward the scene's
            # centre first, an angle that turns with the world, where the pose's coordinates do not (round 85a F1)
            toward = np.round((points[:, 3:] / space.scale * to_centre).sum(axis=1) / distance, digits)
        toward = np.nan_to_num(toward, nan=0.0, posinf=0.0, neginf=0.0)
        ties = sorted(range(len(views)), key=lambda j: (-away[j], -toward[j], tuple(points[j].tolist()), views[j].name, views[j].exact_key()))
        rank = np.empty(len(views), np.int64)
        rank[ties] = np.arange(len(views))
        return cls(points, rank, np.full(len(views), np.inf), np.ones(len(views), bool))

    def next(self) -> int | None:
        """The next view to probe (an index into the views), or None when every view was probed."""
        candidates = np.flatnonzero(self.open)
        if candidates.size == 0:
            return None
        gaps = self.gap[candidates]
        far = candidates[gaps >= gaps.max() * (1.0 - PROBE_TIE)]
        return int(far[np.argmin(self.rank[far])])

    def probed(self, view: int, scored: bool) -> None:
        """Record that `view` was probed, and whether it scored (only a view that scored moves the distances)."""
        self.open[view] = False
        if scored:
            with np.errstate(over="ignore"):  # poses 1e308 apart are +inf apart: the farthest, as they are
                self.gap = np.minimum(self.gap, np.linalg.norm(self.points - self.points[view], axis=1))


def probe_picks(views: Sequence[Camera], count: int = FIT_PROBES, space: ProbeSpace | None = None) -> np.ndarray:
    """[min(count, V)] indices into `views` of the probe views, in the order they are scored, when
    every view probed scores (`ProbeOrder`; space: `probe_space` of the scene)."""
    order = ProbeOrder.of(views, space)
    picks = []
    while len(picks) < count and (view := order.next()) is not None:
        order.probed(view, True)
        picks.append(view)
    return np.array(picks, np.int64)


def is_fit_mode(mode: str) -> bool:
    """Whether `mode` starts with the fit stage ("fit" or "fit-...")."""
    return mode == "fit" or mode.startswith("fit-")


def resolve_mode(mode: str, footprint: str) -> str:
    """The concrete mode of a fit mode: "fit[-vote][-reject]" -> "[vote][-reject]" (paper; bare
    "fit" -> "paper") or "sharp[-vote][-reject]"; other modes are returned as they are."""
    if footprint not in FOOTPRINTS:
        raise ValueError(f"unknown footprint {footprint!r} (choose from {', '.join(FOOTPRINTS)})")
    if not is_fit_mode(mode):
        return mode
    rest = mode[len("fit"):]
    if footprint == "sharp":
        return "sharp" + rest
    return rest[1:] if rest else "paper"


# ----------------------------------------------------------------------------- the score of one footprint


def view_labels_reference(ids: np.ndarray, weights: np.ndarray, mask_ids: np.ndarray, num_gaussians: int) -> np.ndarray:
    """[N] int32 ℓ(g) = argmax_j Σ_{p ∈ mask j} u_g(p) (ties: the lower j; -1: no weight on any mask).
    ids, weights: [H, W, k]; mask_ids: [H, W]. numpy reference of `view_labels`."""
    k = ids.shape[-1]
    g = ids.reshape(-1, k)
    m = np.broadcast_to(mask_ids.reshape(-1, 1), g.shape)
    ok = (g >= 0) & (m >= 0)
    keys, inverse = np.unique(np.stack([g[ok], m[ok]], 1), axis=0, return_inverse=True)
    sums = np.zeros(len(keys), np.float32)  # float32, added in pixel then slot order: the coalesced pairs' sums
    np.add.at(sums, inverse.ravel(), weights.reshape(-1, k)[ok].astype(np.float32))
    labels = np.full(num_gaussians, -1, np.int32)
    best = np.zeros(num_gaussians, np.float32)
    for (gi, mj), s in zip(keys, sums):  # keys ascend by (g, m): a later mask wins only when strictly heavier
        if s > best[gi]:
            best[gi], labels[gi] = s, mj
    return labels


@numba.njit(cache=True)
def _labels_kernel(g, m, w, best, labels):  # pragma: no cover - jitted
    """labels[g] = the mask of g's heaviest pair (ties: the lower mask); best, labels [N]: 0, -1 on entry."""
    for t in range(g.shape[0]):
        i, j, s = g[t], m[t], w[t]
        if s > best[i] or (s == best[i] and s > 0.0 and j < labels[i]):
            best[i] = s
            labels[i] = j


FIRST_RUN_PROBE = _labels_kernel  # the stage's kernel whose place in numba's cache shows it ran here before (driver.say_if_kernels_compile)


def pairs_labels(gaussians: np.ndarray, masks: np.ndarray, weights: np.ndarray, num_gaussians: int) -> np.ndarray:
    """[N] int32 ℓ(g) from a view's coalesced pairs gaussians, masks [P] int32, weights [P] float32
    (`Coalescer.coalesce`'s order): the mask of each Gaussian's heaviest pair (ties: the lower mask)."""
    best, labels = np.zeros(num_gaussians, np.float32), np.full(num_gaussians, -1, np.int32)
    _labels_kernel(gaussians, masks, weights, best, labels)
    return labels


def view_labels(ids: np.ndarray, weights: np.ndarray, mask_ids: np.ndarray, num_masks: int, coalescer: Coalescer) -> np.ndarray:
    """`view_labels_reference` from the view's coalesced pairs (drsplat.registration.coalesce)."""
    g, m, w, _ = coalescer.coalesce(ids, weights, mask_ids, num_masks)
    return pairs_labels(g, m, w, coalescer.num_gaussians)


def rerender_reference(ids: np.ndarray, weights: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """[H, W] int32 r(p) = argmax_j Σ_s u_s(p)·[ℓ(g_s) = j] (ties: the lower j; -1 where no slot
    has a labelled Gaussian with weight > 0). numpy reference of the re-render in `footprint_score`.
    It reads every slot; the kernel (`rerender_scores`) stops at a pixel's first -1, as every engine
    pads after the filled slots, so a -1 between filled slots (no render gives one) scores apart."""
    lab = np.where(ids >= 0, labels[np.maximum(ids, 0)], -1)
    u = np.where(lab >= 0, weights.astype(np.float64), 0.0)
    top = int(labels.max()) + 1 if labels.size else 0
    out = np.full(ids.shape[:2], -1, np.int32)
    best = np.zeros(ids.shape[:2])
    for j in range(top):
        s = np.where(lab == j, u, 0.0).sum(axis=-1)
        win = s > best
        out[win], best[win] = j, s[win]
    return out


def mask_iou_score(mask_ids: np.ndarray, rendered: np.ndarray) -> float:
    """S = mean over the masks j present in mask_ids [H, W] of IoU(mask_ids = j, rendered = j)."""
    present = np.unique(mask_ids[mask_ids >= 0])
    if present.size == 0:
        return 0.0
    ious = [np.count_nonzero((mask_ids == j) & (rendered == j)) / np.count_nonzero((mask_ids == j) | (rendered == j)) for j in present]
    return float(np.mean(ious))


@numba.njit(parallel=True, cache=True)
def _rerender_counts_kernel(ids, weights, labels, mask_ids, num_masks, num_labels, parts, inter, area_r):  # pragma: no cover - jitted
    """Per part t of the pixels and labelling l (labels [N, L], one row per Gaussian): inter[t, l, j] =
    #{p : r_l(p) = m(p) = j}, area_r[t, l, j] = #{p : r_l(p) = j} (r_l: the re-render of
    `rerender_reference` under labelling l; a label's sum over the pixel's slots in slot order,
    float64). Each label's sum sits at its own place of a [L, num_labels] table, marked by the pixel
    that touched it last, and the pixel's touched labels are listed in first-touch order for the
    argmax: no search of the labels seen so far, whose compares followed no pattern a branch
    predictor learns (per part RERENDER_LABEL_BYTES per label and labelling, with the counts). The L
    labellings of one view are re-rendered in one pass over its slots. A
    pixel's slots are read up to its first -1: every engine writes the -1 padding last, ranked or not
    (a pixel of a registration view fills ~half of its 40 slots)."""
    n_pix, k = ids.shape
    count = labels.shape[1]
    for t in numba.prange(parts):
        sums = np.zeros((count, num_labels))
        touched_by = np.full((count, num_labels), -1, np.int32)  # a pixel index: views hold < 2³¹ pixels
        touched = np.empty((count, k), np.int32)
        used = np.zeros(count, np.int64)
        for p in range(t * n_pix // parts, (t + 1) * n_pix // parts):
            used[:] = 0
            for s in range(k):
                g = ids[p, s]
                if g < 0:
                    break
                u = np.float64(weights[p, s])
                for l in range(count):
                    j = labels[g, l]
                    if j < 0:
                        continue
                    if touched_by[l, j] != p:
                        touched_by[l, j] = p
                        sums[l, j] = u
                        touched[l, used[l]] = j
                        used[l] += 1
                    else:
                        sums[l, j] += u
            m = mask_ids[p]
            for l in range(count):
                r = -1
                top = 0.0
                for e in range(used[l]):
                    j = touched[l, e]
                    a = sums[l, j]
                    if a > top or (a == top and top > 0.0 and j < r):
                        top = a
                        r = j
                if 0 <= r < num_masks:
                    area_r[t, l, r] += 1
                    if m == r:
                        inter[t, l, r] += 1


def footprint_score(ids: np.ndarray, weights: np.ndarray, mask_ids: np.ndarray, num_masks: int, coalescer: Coalescer) -> float:
    """S_u of one view for the per-slot weights u = `weights` [H, W, k] (module docstring): the view's
    labelling re-rendered and compared with its masks mask_ids [H, W], mask by mask."""
    return rerender_score(ids, weights, view_labels(ids, weights, mask_ids, num_masks, coalescer), mask_ids, num_masks)


def rerender_score(ids: np.ndarray, weights: np.ndarray, labels: np.ndarray, mask_ids: np.ndarray, num_masks: int) -> float:
    """S_u of one view from its labelling ℓ = labels [N] (`view_labels`; `rerender_scores` of one labelling)."""
    return float(rerender_scores(ids, weights, labels[:, None], mask_ids, num_masks)[0])


def rerender_scores(ids: np.ndarray, weights: np.ndarray, labellings: np.ndarray, mask_ids: np.ndarray, num_masks: int) -> np.ndarray:
    """[L] float64: S of each labelling of labellings [N, L] int32 (-1: no label), re-rendered from
    ids, weights [H, W, k] (each pixel's -1 padding after its filled slots, as the rasterizers write
    them), then the mean per-mask IoU against mask_ids [H, W] (0 where no mask holds a pixel): what
    `rerender_score` gives each, in one pass over the view's slots. The kernel's per-part tables
    (RERENDER_LABEL_BYTES per label and labelling) are held to RERENDER_TABLE_BYTES by re-rendering
    fewer labellings a pass, then in fewer parts, as views of hundreds of thousands of masks need."""
    k = ids.shape[-1]
    count = labellings.shape[1]
    masks = np.ascontiguousarray(mask_ids.reshape(-1), np.int32)
    labellings, num_labels = compact_labels(labellings, num_masks)
    ids2, w2 = np.ascontiguousarray(ids.reshape(-1, k), np.int32), np.ascontiguousarray(weights.reshape(-1, k), np.float32)
    group, parts = rerender_plan(count, num_labels, max(1, numba.get_num_threads()))
    area_m = np.bincount(masks[masks >= 0], minlength=num_masks)[:num_masks]
    present = area_m > 0
    if not present.any():
        return np.zeros(count)
    scores = np.empty(count)
    for start in range(0, count, group):
        stop = min(count, start + group)
        inter = np.zeros((parts, stop - start, num_masks), np.int32)  # a part's pixels: < 2³¹
        area_r = np.zeros((parts, stop - start, num_masks), np.int32)
        _rerender_counts_kernel(ids2, w2, np.ascontiguousarray(labellings[:, start:stop]), masks, num_masks, num_labels, parts, inter, area_r)
        i, r = inter.sum(0, dtype=np.int64)[:, present], area_r.sum(0, dtype=np.int64)[:, present]
        for l in range(stop - start):  # each a 1-D mean: one labelling's bits
            scores[start + l] = np.mean(i[l] / (area_m[present] + r[l] - i[l]))
    return scores


def rerender_plan(count: int, num_labels: int, threads: int) -> tuple[int, int]:
    """(labellings re-rendered a pass, parts of the pixels) of `rerender_scores` for `count` labellings
    of `num_labels` labels on `threads` threads: as many of both as keep the per-part tables
    (RERENDER_LABEL_BYTES per label and labelling) within RERENDER_TABLE_BYTES, the labellings first;
    one labelling in one part at the least."""
    per_labelling = RERENDER_LABEL_BYTES * max(1, num_labels)
    group = max(1, min(count, RERENDER_TABLE_BYTES // (per_labelling * threads)))
    parts = max(1, min(threads, RERENDER_TABLE_BYTES // (per_labelling * group)))
    return group, parts


def rerender_table_bytes(count: int, num_labels: int, threads: int) -> int:
    """Bytes of the tables `rerender_scores` holds at once for `count` labellings of `num_labels`
    labels (`rerender_plan`): at most RERENDER_TABLE_BYTES, or one labelling's table in one part
    where that alone is larger."""
    group, parts = rerender_plan(count, num_labels, threads)
    return RERENDER_LABEL_BYTES * max(1, num_labels) * group * parts


def compact_labels(labellings: np.ndarray, num_masks: int) -> tuple[np.ndarray, int]:
    """(labellings [N, L] as int32, the labels' count): labels < 0 become -1 (no label); labels of no
    mask (≥ num_masks) can win a pixel's argmax but count for no mask, so only their being distinct
    and above every mask matters: they are renumbered num_masks, num_masks + 1, ... in their order,
    so the re-render's label table holds the masks and the distinct labels past them, whatever their
    values (a label of 2³⁰ asked a [L, 2³⁰] table per part, a probe)."""
    labellings = np.asarray(labellings)
    if labellings.size == 0:
        return np.ascontiguousarray(labellings, np.int32), max(num_masks, 1)
    if labellings.dtype == np.int32 and labellings.min() >= -1 and labellings.max() < num_masks:  # the fit's own labellings
        return np.ascontiguousarray(labellings), max(num_masks, 1)
    labellings = np.where(labellings < 0, -1, labellings).astype(np.int64)  # a new array, wide enough for the new numbers
    past = labellings >= num_masks
    if past.any():
        _, rank = np.unique(labellings[past], return_inverse=True)
        labellings[past] = num_masks + rank.reshape(-1)
    out = np.ascontiguousarray(labellings, np.int32)
    return out, max(num_masks, int(out.max()) + 1, 1)


def translate_labels(labels: np.ndarray, feats_from: np.ndarray, feats_to: np.ndarray, groups_to: np.ndarray) -> np.ndarray:
    """[N] int32: one view's labelling ℓ (labels [N], mask ids of feats_from [M_a, D], -1 none) in
    another view's masks: mask j goes to the mask g of groups_to [H, W] (that view's grouped mask map,
    feats_to [M_b, D]) whose embedding is most alike,

        τ(j) = argmax_{g present in groups_to} cos(f_a[j], f_b[g])      (ties: the lower g)

    so the labelling can be re-rendered in that view and scored against its masks. -1 stays -1; all
    -1 when that view holds no mask. A zero row has cosine 0 with every mask. The dense form, the
    reference of the fit stage's sparse `HeldOut`."""
    trans = mask_translation(unit_rows64(feats_from), unit_rows64(feats_to), present_masks(groups_to, feats_to.shape[0]))
    return np.where(labels >= 0, trans[np.maximum(labels, 0)], -1).astype(np.int32)


def present_masks(groups: np.ndarray, num_masks: int) -> np.ndarray:
    """[G] int32 ascending: the masks (groups) of a grouped mask map groups [H, W] that hold a pixel."""
    return np.flatnonzero(np.bincount(groups[groups >= 0].ravel(), minlength=num_masks)).astype(np.int32)


def mask_translation(units_from: np.ndarray, units_to: np.ndarray, present: np.ndarray) -> np.ndarray:
    """[M_a + 1] int32 τ of `translate_labels` from unit rows (`lang.unit_rows64`) [M_a, D] and [M_b, D] and
    the other view's present masks [G]; entry M_a (and all of τ when G = 0) is -1. The cosines are
    made TRANSLATION_BLOCK_BYTES of rows at a time: at once, [M_a, G] float64 asked 703 GiB of views
    of 640x480 one-pixel masks (a probe, round 31); one block up to ~2,900 masks a view."""
    trans = np.full(units_from.shape[0] + 1, -1, np.int32)
    if present.size and units_from.shape[0]:
        to = units_to[present].T
        rows = max(1, TRANSLATION_BLOCK_BYTES // (8 * present.size))
        m = units_from.shape[0]
        for start in range(0, m, rows):
            stop = min(start + rows, m)
            trans[start:stop] = present[np.argmax(units_from[start:stop] @ to, axis=1)]
    return trans


@dataclass
class HeldOut:
    """The probe views' labellings kept for the held-out scores, sparse (a probe view labels the
    Gaussians it sees: ids [S] int32 and their masks [S] int32) with their masks' embeddings [M, D] as
    read (float32: what `probe_memory_bound` counts per probe view; their float64 unit rows, twice
    that, are made per pair)."""

    earlier: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = dataclasses.field(default_factory=list)

    def labellings(self, labels: np.ndarray, groups: np.ndarray, units: np.ndarray) -> np.ndarray:
        """[N, 1 + E] int32: this view's own labelling labels [N] and each of the E earlier probe views'
        translated into this view's grouped masks groups [H, W] (their unit rows units [M, D];
        `translate_labels`, the table made once per pair), -1 where none: what `rerender_scores`
        re-renders in one pass for S_u and the view's H_u."""
        present = present_masks(groups, units.shape[0])
        out = np.full((labels.shape[0], 1 + len(self.earlier)), -1, np.int32)
        out[:, 0] = labels
        for column, (seen, masks, feats_from) in enumerate(self.earlier, 1):
            out[seen, column] = mask_translation(unit_rows64(feats_from), units, present)[masks]
        return out

    def keep(self, labels: np.ndarray, feats: np.ndarray) -> None:
        """Keep this view's labelling [N] (-1 none) and its mask embeddings [M, D] for the later probe views."""
        seen = np.flatnonzero(labels >= 0).astype(np.int32)
        self.earlier.append((seen, labels[seen], feats))


def footprint_score_reference(ids: np.ndarray, weights: np.ndarray, mask_ids: np.ndarray, num_gaussians: int) -> float:
    """`footprint_score` in numpy."""
    return mask_iou_score(mask_ids, rerender_reference(ids, weights, view_labels_reference(ids, weights, mask_ids, num_gaussians)))


# ----------------------------------------------------------------------------- the probe


@dataclass
class FitStage:
    """What the fit stage hands the registration driver.

    mode: the concrete mode (`resolve_mode`); choice: the decision. geometry: the scene's
    `prepare_geometry`, which the view pass renders too. index: the culling index the probe built,
    which the view pass culls with (None without culling). rays: the RayGeometry the
    probe built for floater rejection (None when it built none). pairs: view index -> that probe
    view's ViewPairs for the chosen footprint, computed as the view pass computes them (the same
    render, hook and coalescing), so the pass does not render it again (empty unless asked for).
    """

    mode: str
    choice: FitChoice
    geometry: PreparedScene
    index: SpatialIndex | None
    rays: RayGeometry | None
    pairs: dict[int, ViewPairs]

    @property
    def pass_bytes(self) -> int:
        """Bytes of the arrays the view pass takes over (geometry, culling index, rays), which the
        pass's memory plan counts per Gaussian itself (drsplat.registration.plan)."""
        held = [self.geometry, self.index, self.rays]
        return sum(int(value.nbytes) for part in held if part is not None for value in vars(part).values() if isinstance(value, np.ndarray))


def fit_stage(mode: str, scene: GaussianScene, views: Sequence[Camera], features_dir: Path, level: int, topk: int, *,
              geometry: PreparedScene | None = None, cull: bool = True, keep_pairs: bool = False, count: int = FIT_PROBES,
              cancel: CancelToken | None = None, keep_bytes: int | None = None, engine: str = "numba", device: str = "cpu",
              near: float = NEAR) -> FitStage:
    """The fit stage of `mode` (a fit mode; module docstring) on `count` probe views of `views`.

    Each probe view is rendered once, by a ViewComputer of `engine` on `device` (`probe_engine`;
    numba culls, `cull`) that takes the median as the view pass does, its top-k lists on the host,
    and coalesced under each footprint; a footprint's score is read
    from its pairs (ℓ) and the render (r). A mode that rejects floaters has each view's floater
    statistics computed and folded, and scores its labellings without what they reject (module
    docstring). keep_pairs: keep the chosen footprint's ViewPairs (statistics included) for a view pass that computes
    views the same way (numba, in this process), as many probe views as keep both footprints' pairs
    within `keep_bytes` (default `probe_keep_bytes(N)`; the pass renders the others again: the same pairs). geometry:
    `prepare_geometry(scene)` when made already. cancel: checked before each probe view. near: the
    view pass's near plane (`ViewJob.near`).
    """
    geometry = geometry if geometry is not None else prepare_geometry(scene)
    candidates = {footprint: resolve_mode(mode, footprint) for footprint in FOOTPRINTS}
    # a mode that rejects floaters has them left out of the labellings, so the probe computes the floater
    # statistics whatever the place and engine of the view pass (every place decides alike)
    rejects = probe_folds_floaters(mode)
    rays = RayGeometry.from_scene(scene) if rejects else None
    # the sharp candidate's hook gives the sharp weights, and renders with the median exactly when the view pass will
    hook = mode_hook(candidates["sharp"], rays)
    support = SurfaceSupport.zeros(geometry.num_gaussians) if rejects else None  # the probe views' statistics, folded in probe order
    computer = ViewComputer(geometry, ViewJob(features_dir, level, topk, engine, device, hook=hook, cull=cull,
                                              by_gaussian=keep_pairs and pairs_by_gaussian(mode), near=near))
    order = ProbeOrder.of(views, probe_space(scene))
    picks: list[int] = []  # the views probed, in probe order
    scores: dict[str, list[float]] = {footprint: [] for footprint in FOOTPRINTS}
    held: dict[str, list[float]] = {footprint: [] for footprint in FOOTPRINTS}
    kept_labels = {footprint: HeldOut() for footprint in FOOTPRINTS}
    kept: dict[str, dict[int, ViewPairs]] = {footprint: {} for footprint in FOOTPRINTS}
    names: list[str] = []  # the probe views scored
    kept_bytes, keep_bytes = 0, probe_keep_bytes(geometry.num_gaussians) if keep_bytes is None else keep_bytes
    floating = None
    while len(names) < count and len(picks) - len(names) < count and (i := order.next()) is not None:
        if cancel is not None:
            cancel.raise_if_cancelled()
        picks.append(i)
        # one embedding size over the probe views (a held-out score compares two views' embeddings), each file's
        # layout the format's: `register` checked every view's headers already; this guards a direct call
        read_feature_headers(features_dir, [views[picks[0]], views[i]], level)
        cam, mask_ids, feats, nonfinite = probe_view(features_dir, views[i], level)
        t0 = time.perf_counter()
        out = computer.rasterize(cam)
        raster_seconds = time.perf_counter() - t0
        stats = hook.stats(cam, out)
        floating = probe_floaters(support, stats)
        same = same_embedding(feats)
        groups = mask_groups(mask_ids, same)
        units = unit_rows64(feats)
        scored = None
        both: dict[str, ViewPairs] = {}
        for footprint in FOOTPRINTS:  # the paper's first: its pairs decide whether the view scores
            weights = hook.weights(geometry, cam, out, mask_ids, near) if footprint == "sharp" else out.weights
            view = both[footprint] = computer.pairs(cam, out.ids, weights, stats, mask_ids, feats, nonfinite, raster_seconds)
            if scored is None:
                scored = scores_footprints(view.weights)
                order.probed(i, scored)
                if scored:
                    names.append(views[i].name)
            if not scored:
                continue
            labels = pairs_labels(*grouped_pairs(view.gaussians, view.masks, view.weights, same), geometry.num_gaussians)
            labellings = kept_labels[footprint].labellings(labels, groups, units)
            if floating is not None:  # what the rejection would leave unassigned labels nothing (module docstring)
                labellings[floating] = -1
            s_and_h = rerender_scores(out.ids, weights, labellings, groups, feats.shape[0])
            scores[footprint].append(float(s_and_h[0]))
            held[footprint] += s_and_h[1:].tolist()
            kept_labels[footprint].keep(labels, feats)
        # the footprints' views share the embeddings and the statistics
        view_bytes = both["paper"].nbytes + sum(v.gaussians.nbytes + v.masks.nbytes + v.weights.nbytes + v.used.nbytes for f, v in both.items() if f != "paper")
        # a view probed at its masks' coarser resolution is rendered again by the pass
        if keep_pairs and cam is views[i] and kept_bytes + view_bytes <= keep_bytes:
            kept_bytes += view_bytes
            for footprint, view in both.items():
                kept[footprint][int(i)] = view
    choice = FitChoice("paper", [views[i].name for i in picks], np.array(scores["paper"]), np.array(scores["sharp"]), np.array(held["paper"]),
                       np.array(held["sharp"]), scored=names, floaters=int(np.count_nonzero(floating)) if floating is not None else 0)
    choice.footprint = choice.decide()
    if len(names) < len(picks):
        log.info("fit: %d of the %d views probed have no mask over a Gaussian they see, and are not scored", len(picks) - len(names), len(picks))
    if names:
        log.info("fit: the masks of %d probe views follow the %s footprints (mean per-mask IoU of their re-rendered labels: paper %.3f, "
                 "sharp %.3f; of the labels of another probe view: paper %.3f, sharp %.3f%s)", len(names),
                 "sharp" if choice.footprint == "sharp" else "rasterized (filtered)",
                 mean_or_zero(choice.paper), mean_or_zero(choice.sharp), mean_or_zero(choice.held_paper), mean_or_zero(choice.held_sharp),
                 f"; {choice.floaters:,} Gaussians the floater rejection drops left unlabelled" if rejects else "")
    else:
        log.info("fit: no probe view to score: the rasterized (filtered) footprints")
    return FitStage(resolve_mode(mode, choice.footprint), choice, geometry, computer.index, rays, kept[choice.footprint])


def same_embedding(feats: np.ndarray) -> np.ndarray:
    """[M] int32: each mask's id, or the lowest id of a mask with the very same embedding row. The fit
    scores labels, and one label's mask cut into pieces (or painted per instance from one text
    embedding) is one label: scored piece by piece, the pieces' boundaries, which follow no object,
    moved the margin of a hard-tiny room from +0.029 to -0.006 (round 22). Rows are compared by
    their bits with -0.0 read as 0.0 (equal numbers), so NaN rows of the same bits are one label too
    (the feature reader zeroes non-finite rows and gives their masks no pixels before the fit)."""
    if feats.shape[0] == 0 or feats.shape[1] == 0:  # 0-wide rows are all the same (empty) embedding
        return np.zeros(feats.shape[0], np.int32)
    feats = np.ascontiguousarray(feats) + np.zeros((), np.asarray(feats).dtype)  # -0.0 + 0.0 = 0.0: one bit pattern per number
    _, first, inverse = np.unique(feats.view(np.dtype((np.void, feats.dtype.itemsize * feats.shape[1]))),
                                  return_index=True, return_inverse=True)
    return first[inverse.reshape(-1)].astype(np.int32)


def mask_groups(mask_ids: np.ndarray, same: np.ndarray) -> np.ndarray:
    """[H, W] int32: each pixel's mask replaced by its group (`same_embedding`), -1 where it has none;
    all -1 for a view without masks (whose `same` is empty: a view a segmenter found nothing in)."""
    if same.shape[0] == 0:
        return np.full(mask_ids.shape, -1, np.int32)
    return np.where(mask_ids >= 0, same[np.maximum(mask_ids, 0)], -1).astype(np.int32)


def grouped_pairs(gaussians: np.ndarray, masks: np.ndarray, weights: np.ndarray, same: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A view's pairs (gaussians, masks [P] int32, weights [P] float32) with each mask replaced by
    `same`'s (`same_embedding`) and the weights of a Gaussian's pairs in one group summed (float64,
    then float32), in (Gaussian, group) order; the pairs as they are when no two masks share an
    embedding (every mask its own group)."""
    if np.array_equal(same, np.arange(same.shape[0])):
        return gaussians, masks, weights
    n = max(1, same.shape[0])
    unique, inverse = np.unique(gaussians.astype(np.int64) * n + same[masks], return_inverse=True)
    sums = np.bincount(inverse.reshape(-1), weights.astype(np.float64), minlength=unique.shape[0]).astype(np.float32)
    return (unique // n).astype(np.int32), (unique % n).astype(np.int32), sums


def probe_view(features_dir: Path, cam: Camera, level: int) -> tuple[Camera, np.ndarray, np.ndarray, int]:
    """(camera, mask ids [h, w], feats [M, D], masks dropped as non-finite) of one probe view: `cam`
    itself and its masks resampled to it, unless the mask map is coarser than the view; then `cam`
    scaled to the map's width and the map at that size (`Camera.scaled`, which may round the height).
    Which footprint masks follow is a question at their own resolution: a map at half the view's,
    upsampled, has 2-pixel steps at every boundary, which hide the filter's 0.3 px² blur, and the fit
    took the filtered footprint for true silhouettes on 9 of 9 rooms (round 22; the sharp one then
    labels them better at the view's resolution too)."""
    mask_ids, feats, nonfinite = read_features_report(features_dir, cam.name, level, drop_nonfinite=True)
    check_aspect(seg_path(features_dir, cam.name), mask_ids.shape[1], mask_ids.shape[0], cam)
    if mask_ids.shape[1] < cam.width:
        cam = cam.scaled(mask_ids.shape[1] / cam.width)
    return cam, resample_nearest(mask_ids, cam.width, cam.height), feats, nonfinite


def choose_footprint(scene: GaussianScene, views: Sequence[Camera], features_dir: Path, level: int, topk: int, count: int = FIT_PROBES,
                     cancel: CancelToken | None = None) -> FitChoice:
    """The fit stage's decision for a registration of `views` (`fit_stage`'s choice, nothing kept)."""
    return fit_stage("fit", scene, views, features_dir, level, topk, count=count, cancel=cancel).choice
