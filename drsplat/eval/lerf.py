"""The LERF-OVS 2D object-selection protocol (OpenGaussian's), on a registered scene.

For every annotated view and every category annotated in it: select the Gaussians that answer
the category's text query, render the occupancy (accumulated opacity 1 − T) of the selection
alone from the view's camera, binarise it at `alpha_threshold`, and compare with the ground-truth
mask. mIoU is the mean IoU over all (view, category) pairs; mAcc@0.25 is the share of pairs whose
IoU exceeds 0.25. A pair whose ground-truth mask is degenerate (empty, or missing a polygon that
covers no pixel) is left out of both: its IoU would be 0 against any selection and 1.0 against none.
Where the view's camera has lens distortion, the annotation (drawn on the distorted photo) is moved
onto the pinhole camera's pixels that the renders use, and pixels the photo never saw are left out
(`annotation_on_pinhole`).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np

from drsplat.cameras import Camera, lens_corner_shift, source_and_unobserved
from drsplat.defaults import LERF_ALPHA_THRESHOLD
from drsplat.eval.datasets import AnnotatedView, check_annotation_size
from drsplat.utils import CancelToken, progress
from drsplat.query import otsu_threshold, thresholds_as_compared
from drsplat.raster import NEAR, prepare_scene, rasterize

log = logging.getLogger(__name__)


@dataclass
class SelectionRow:
    view: str
    category: str
    iou: float
    selected: int


@dataclass
class Lerf2DReport:
    """rows: one per scored (view, category); missing_views: views with no matching camera;
    skipped: (view, category) pairs left out for degenerate ground truth (not in any mean)."""

    rows: list[SelectionRow]
    alpha_threshold: float
    missing_views: list[str] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)

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
                "skipped_pairs": [{"view": v, "category": c} for v, c in self.skipped],
                "rows": [{"view": r.view, "category": r.category, "iou": r.iou, "selected": r.selected} for r in self.rows]}

    def format(self) -> str:
        lines = [f"{'category':<24} {'mIoU':>6}"]
        lines += [f"{c:<24} {v:6.3f}" for c, v in self.per_category().items()]
        lines.append(f"{'ALL (' + str(len(self.rows)) + ' pairs)':<24} {self.miou:6.3f}   mAcc@0.25 {self.acc_at(0.25):.3f}")
        if self.skipped:
            lines.append(f"({len(self.skipped)} (view, category) pairs with degenerate ground truth left out)")
        return "\n".join(lines)


def mask_iou(pred: np.ndarray, gt: np.ndarray) -> float:
    """|pred ∧ gt| / |pred ∨ gt| of two boolean images (1.0 when both are empty; `lerf_2d_report`
    never scores an empty ground truth)."""
    union = np.count_nonzero(pred | gt)
    return float(np.count_nonzero(pred & gt) / union) if union else 1.0


def camera_for_view(cameras: dict[str, Camera], view: AnnotatedView) -> Camera | None:
    """The camera named like the view, resized to the annotation's resolution (aspect must agree
    within 2%, `check_annotation_size`; the error names the annotation file)."""
    cam = cameras.get(view.name)
    if cam is None:
        return None
    if (cam.width, cam.height) == (view.width, view.height):
        return cam
    check_annotation_size(view.path, view.name, view.width, view.height, cam.width, cam.height)
    # each axis by its own factor, as a training image of another size is stretched to its camera's (round 76b F2: one
    # factor for both, then the height overwritten, left fy and cy for another height: up to 11 px off at the bottom)
    return cam.resized(view.width, view.height)


def annotation_on_pinhole(view: AnnotatedView, cam: Camera) -> tuple[AnnotatedView, np.ndarray | None]:
    """The view's annotation moved from its photo onto the pixels of its pinhole camera `cam` (at the annotation's
    size, `camera_for_view`), with [H, W] bool of the pinhole pixels the photo saw; (view, None) for a camera without
    distortion.

    LERF-OVS polygons are drawn on the photo, which the lens distorted; the renders are pinhole (as 3DGS trains on
    undistorted images, and `drsplat features` undistorts the photos it reads). Pinhole pixel q shows what the photo
    holds at distort(q) (`distorted_source`), so each mask is read there, at the nearest photo pixel; a box becomes
    the bounding box of the pinhole pixels whose source lies in it. Pixels whose source lies outside the photo are
    False in every mask and left out of the comparison by the caller (round 95b F1: a declared k1 = 0.2, 9 px at the
    corners, changed no score: the polygons were compared with pinhole renders as they were drawn)."""
    if cam.distortion is None:
        return view, None
    src_u, src_v, unseen = source_and_unobserved(cam, (view.width, view.height))  # the source once (it was computed twice)
    seen = ~unseen
    iu = np.clip(np.rint(src_u), 0, view.width - 1).astype(np.int64)
    iv = np.clip(np.rint(src_v), 0, view.height - 1).astype(np.int64)
    masks = {c: np.asarray(m, bool)[iv, iu] & seen for c, m in view.masks.items()}
    boxes = {}
    for category, rows in view.boxes.items():
        moved = [box for box in (_box_on_pinhole(row, src_u, src_v, iu, iv, seen) for row in np.asarray(rows, np.float64).reshape(-1, 4))
                 if box is not None]
        if moved:
            boxes[category] = np.stack(moved)
    return dataclasses.replace(view, masks=masks, boxes=boxes), seen


def _box_on_pinhole(box: np.ndarray, src_u: np.ndarray, src_v: np.ndarray, iu: np.ndarray, iv: np.ndarray,
                    seen: np.ndarray) -> np.ndarray | None:
    """[4] (x1, y1, x2, y2): the bounding box of the pinhole pixels whose photo pixel (iu, iv) [H, W] lies in `box` (a
    photo box, bounds included, either corner order, as `peak_in_boxes` reads it); a box too small for any (a lens that
    spreads the photo's pixels: round 96a F7) is the pinhole pixel whose source (src_u, src_v) lies nearest its centre;
    None when the box lies outside what the pinhole camera sees."""
    x1, y1, x2, y2 = box
    inside = seen & (iu >= min(x1, x2)) & (iu <= max(x1, x2)) & (iv >= min(y1, y2)) & (iv <= max(y1, y2))
    ys, xs = np.nonzero(inside)
    if xs.size:
        return np.array([xs.min(), ys.min(), xs.max(), ys.max()], np.float64)
    gap = np.where(seen, np.hypot(src_u - 0.5 * (x1 + x2), src_v - 0.5 * (y1 + y2)), np.inf)  # never a pixel the photo missed (round 97a F3)
    y, x = np.unravel_index(np.argmin(gap), gap.shape)
    return np.array([x, y, x, y], np.float64) if gap[y, x] <= 0.5 * max(abs(x2 - x1), abs(y2 - y1)) + 1.0 else None


def warn_empty_ground_truth(view: AnnotatedView, category: str, photo: AnnotatedView) -> None:
    """The warning for a (view, category) pair left out for an empty ground-truth mask; `photo`: the view as drawn,
    before `annotation_on_pinhole` (a mask the lens moved wholly off the pinhole view was called empty: round 96a F8)."""
    why = ("lies wholly outside what the pinhole camera sees (the lens moves it off the view)" if photo.masks[category].any()
           else "is empty")
    log.warning("%s: view %s, category %r: the ground-truth mask %s; left out of the means", view.path or "annotation", view.name, category, why)


def say_annotations_moved(cameras: list[Camera]) -> None:
    """One INFO line when some camera has lens distortion: the annotations are moved onto the pinhole cameras."""
    shifts = [lens_corner_shift(c) for c in cameras if c.distortion is not None]
    if shifts:
        log.info("%d of %d cameras have lens distortion (up to %.1f px at a corner): each annotation is moved from its photo "
                 "onto the pinhole camera the views are rendered with, and what the photo did not see is left out",
                 len(shifts), len(cameras), max(shifts))


def select_queries(scores: np.ndarray, threshold: float | None = None, assigned: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """[N, L] scores -> ([N, L] bool selections s_il ≥ τ_l, [L] thresholds τ_l).

    threshold: one absolute τ for every query, or None for Otsu's threshold per query (the
    `drsplat query --threshold auto` rule). Non-finite scores are never selected, nor Gaussians
    outside `assigned` [N] bool (`LanguageField.assigned`): one without a feature scores cosine 0
    against the query and every negative, a relevancy of ½, which τ = 0.5 selected (Dr. Splat's
    render_activation.py gives them activation 0; a cross-check, 2026-11-30).
    """
    s = np.asarray(scores, np.float64)
    s = np.where(np.isfinite(s), s, -np.inf)
    if assigned is not None:
        s = np.where(np.asarray(assigned, bool)[:, None], s, -np.inf)
    taus = np.array([threshold if threshold is not None else otsu_threshold(s[:, l]) for l in range(s.shape[1])], np.float64)
    return s >= thresholds_as_compared(taus, scores)[None, :], taus  # float32 scores meet τ in float32


def lerf_2d_report(scene, cameras: list[Camera], views: list[AnnotatedView], selections: dict[str, np.ndarray],
                   alpha_threshold: float = LERF_ALPHA_THRESHOLD, show_progress: bool = True, on_progress=None,
                   cancel: CancelToken | None = None, near: float = NEAR) -> Lerf2DReport:
    """Evaluate selections against LERF-OVS masks.

    scene: GaussianScene (N Gaussians); cameras: the scene's cameras, matched to views by name;
    views: annotated views; selections: category -> [N] bool selected Gaussians.
    Categories without a selection are reported and skipped; views without a camera are listed
    in `missing_views`. Degenerate ground truth is in no mean: the categories of `view.skipped` and
    any empty ground-truth mask become `skipped` pairs (an empty mask would score 1.0 against an
    empty selection and 0 against any other), with a warning for the latter. near: the near plane the
    selections are rendered with (`register --near-plane`; OpenGaussian renders with INRIA's, 0.2).
    """
    by_name = {c.name: c for c in cameras}
    say_annotations_moved(cameras)
    prepared = prepare_scene(scene)
    rows: list[SelectionRow] = []
    missing: list[str] = []
    unselected: set[str] = set()
    skipped: list[tuple[str, str]] = []
    jobs = [(v, c) for v in views for c in v.masks]
    done = 0
    for view in progress(views, "LERF-OVS views", enabled=show_progress, unit="view"):
        cam = camera_for_view(by_name, view)
        if cam is None:
            missing.append(view.name)
            done += len(view.masks)
            continue
        skipped += [(view.name, c) for c in view.skipped]
        photo = view
        view, seen = annotation_on_pinhole(view, cam)
        for category, gt in view.masks.items():
            if cancel is not None:
                cancel.raise_if_cancelled()
            sel = selections.get(category)
            if sel is None:
                unselected.add(category)
                continue
            if not gt.any():
                warn_empty_ground_truth(view, category, photo)
                skipped.append((view.name, category))
                done += 1
                continue
            sel = np.asarray(sel, bool)
            if sel.any():
                alpha = rasterize(prepared, cam, topk=1, mask=sel, near=near).alpha
                pred = alpha > np.float32(alpha_threshold)  # compared in float32, as the official code's tensors
            else:
                pred = np.zeros((view.height, view.width), bool)
            if seen is not None:
                pred &= seen
            rows.append(SelectionRow(view.name, category, mask_iou(pred, gt), int(sel.sum())))
            done += 1
            if on_progress is not None:
                on_progress(done, len(jobs))
    if missing:
        log.warning("%d annotated views have no camera of the same name: %s", len(missing), ", ".join(missing[:5]))
    if unselected:
        log.warning("no selection for categories %s; skipped", sorted(unselected))
    return Lerf2DReport(rows, alpha_threshold, missing, skipped)
