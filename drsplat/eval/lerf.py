"""The LERF-OVS 2D object-selection protocol (OpenGaussian's), on a registered scene.

For every annotated view and every category annotated in it: select the Gaussians that answer
the category's text query, render the occupancy (accumulated opacity 1 − T) of the selection
alone from the view's camera, binarise it at `alpha_threshold`, and compare with the ground-truth
mask. mIoU is the mean IoU over all (view, category) pairs; mAcc@0.25 is the share of pairs whose
IoU exceeds 0.25.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np

from drsplat.cameras import Camera
from drsplat.eval.datasets import AnnotatedView
from drsplat.errors import InputError
from drsplat.utils import CancelToken, progress
from drsplat.query import otsu_threshold
from drsplat.raster import prepare_scene, rasterize

log = logging.getLogger(__name__)


@dataclass
class SelectionRow:
    view: str
    category: str
    iou: float
    selected: int


@dataclass
class Lerf2DReport:
    """rows: one per (view, category); missing_views: views with no matching camera."""

    rows: list[SelectionRow]
    alpha_threshold: float
    missing_views: list[str] = field(default_factory=list)

    @property
    def miou(self) -> float:
        return float(np.mean([r.iou for r in self.rows])) if self.rows else float("nan")

    def acc_at(self, threshold: float = 0.25) -> float:
        return float(np.mean([r.iou > threshold for r in self.rows])) if self.rows else float("nan")

    def per_category(self) -> dict[str, float]:
        cats: dict[str, list[float]] = {}
        for r in self.rows:
            cats.setdefault(r.category, []).append(r.iou)
        return {c: float(np.mean(v)) for c, v in sorted(cats.items())}

    def to_dict(self) -> dict:
        return {"mIoU": self.miou, "mAcc@0.25": self.acc_at(0.25), "alpha_threshold": self.alpha_threshold,
                "per_category": self.per_category(), "missing_views": self.missing_views,
                "rows": [{"view": r.view, "category": r.category, "iou": r.iou, "selected": r.selected} for r in self.rows]}

    def format(self) -> str:
        lines = [f"{'category':<24} {'mIoU':>6}"]
        lines += [f"{c:<24} {v:6.3f}" for c, v in self.per_category().items()]
        lines.append(f"{'ALL (' + str(len(self.rows)) + ' pairs)':<24} {self.miou:6.3f}   mAcc@0.25 {self.acc_at(0.25):.3f}")
        return "\n".join(lines)


def mask_iou(pred: np.ndarray, gt: np.ndarray) -> float:
    """|pred ∧ gt| / |pred ∨ gt| of two boolean images (1.0 when both are empty)."""
    union = np.count_nonzero(pred | gt)
    return float(np.count_nonzero(pred & gt) / union) if union else 1.0


def camera_for_view(cameras: dict[str, Camera], view: AnnotatedView) -> Camera | None:
    """The camera named like the view, resized to the annotation's resolution (aspect must agree)."""
    cam = cameras.get(view.name)
    if cam is None:
        return None
    if (cam.width, cam.height) == (view.width, view.height):
        return cam
    sx, sy = view.width / cam.width, view.height / cam.height
    if abs(sx - sy) > 0.02 * max(sx, sy):
        raise InputError(None, f"view {view.name} is annotated at {view.width}x{view.height} but its camera is {cam.width}x{cam.height} (different aspect)")
    scaled = cam.scaled(sx)
    if (scaled.width, scaled.height) != (view.width, view.height):
        scaled = dataclasses.replace(scaled, width=view.width, height=view.height)
    return scaled


def select_queries(scores: np.ndarray, threshold: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """[N, L] scores -> ([N, L] bool selections s_il ≥ τ_l, [L] thresholds τ_l).

    threshold: one absolute τ for every query, or None for Otsu's threshold per query (the
    `drsplat query --threshold auto` rule). Non-finite scores are never selected.
    """
    s = np.asarray(scores, np.float64)
    s = np.where(np.isfinite(s), s, -np.inf)
    taus = np.array([threshold if threshold is not None else otsu_threshold(s[:, l]) for l in range(s.shape[1])], np.float64)
    return s >= taus[None, :], taus


def lerf_2d_report(scene, cameras: list[Camera], views: list[AnnotatedView], selections: dict[str, np.ndarray],
                   alpha_threshold: float = 0.5, show_progress: bool = True, on_progress=None,
                   cancel: CancelToken | None = None) -> Lerf2DReport:
    """Evaluate selections against LERF-OVS masks.

    scene: GaussianScene (N Gaussians); cameras: the scene's cameras, matched to views by name;
    views: annotated views; selections: category -> [N] bool selected Gaussians.
    Categories without a selection are reported and skipped; views without a camera are listed
    in `missing_views`.
    """
    by_name = {c.name: c for c in cameras}
    prepared = prepare_scene(scene)
    rows: list[SelectionRow] = []
    missing: list[str] = []
    unselected: set[str] = set()
    jobs = [(v, c) for v in views for c in v.masks]
    done = 0
    for view in progress(views, "LERF-OVS views", enabled=show_progress, unit="view"):
        cam = camera_for_view(by_name, view)
        if cam is None:
            missing.append(view.name)
            done += len(view.masks)
            continue
        for category, gt in view.masks.items():
            if cancel is not None:
                cancel.raise_if_cancelled()
            sel = selections.get(category)
            if sel is None:
                unselected.add(category)
                continue
            sel = np.asarray(sel, bool)
            if sel.any():
                alpha = rasterize(prepared, cam, topk=1, mask=sel).alpha
                pred = alpha > alpha_threshold
            else:
                pred = np.zeros((view.height, view.width), bool)
            rows.append(SelectionRow(view.name, category, mask_iou(pred, gt), int(sel.sum())))
            done += 1
            if on_progress is not None:
                on_progress(done, len(jobs))
    if missing:
        log.warning("%d annotated views have no camera of the same name: %s", len(missing), ", ".join(missing[:5]))
    if unselected:
        log.warning("no selection for categories %s; skipped", sorted(unselected))
    return Lerf2DReport(rows, alpha_threshold, missing)
