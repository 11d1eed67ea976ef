"""LangSplat's 2D protocol on LERF-OVS (its eval/evaluate_iou_loc.py, d70edb8), on a registered scene.

Where OpenGaussian's protocol (`drsplat.eval.lerf`) renders the Gaussians a query selects, LangSplat's
scores a rendered feature map. For each annotated view:

1. The language feature of pixel p is the blend of its Gaussians' features, F(p) = Σ_s w_s f_{g_s}
   over its top-k contributions (w = T·α, the registration's rasterizer), normalised. Gaussians
   without a feature add nothing (they still take their weight from those behind them).
2. The relevancy map of a query t against the canonical negatives c_j (LERF's):
   R(p) = min_j σ(10·(cos(F(p), t) − cos(F(p), c_j)))  (`drsplat.query.relevancy_from_scores`).
3. Segmentation: V = ½(B(R) + R), B the mean over a 30 x 30 box (`box_filter`: cv2.filter2D's
   window and border); V is scaled to [−1, 1] by its own minimum and maximum,
   M = clip(2(V − min V)/(max(V − min V) + 1e-9) − 1, 0, 1) > 0.4, and M goes through LangSplat's
   majority filter (`majority_filter`). The pair's IoU is |M ∧ G| / |M ∨ G| with G the annotated
   mask.
4. Localisation: the pair is a hit when a pixel where B(R) reaches its maximum lies inside one of
   the category's annotated boxes (bounds included; x is the column, y the row).

mIoU is the mean IoU over (view, category) pairs, localisation accuracy the share of hits. LangSplat
keeps three feature levels and takes, per query, the level whose V peaks highest; a registered
scene holds one level, so there is no choice to make. LangSplat renders its features with every
Gaussian; here the blend is over each pixel's k heaviest, and `coverage` reports what share of the
pixel's weight (its α) they hold.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numba
import numpy as np

from drsplat.cameras import Camera
from drsplat.defaults import DEFAULT_TOPK, LANGSPLAT_MASK_THRESHOLD
from drsplat.eval.datasets import AnnotatedView
from drsplat.errors import DrsplatError
from drsplat.eval.lerf import annotation_on_pinhole, camera_for_view, mask_iou, say_annotations_moved, warn_empty_ground_truth
from drsplat.memory import available_memory, format_size
from drsplat.query import query_rows, relevancy_from_scores
from drsplat.raster import NEAR, prepare_scene, rasterize_topk
from drsplat.utils import CancelToken, progress

log = logging.getLogger(__name__)

BOX_SIZE = 30  # LangSplat's `scale`: the side of the mean filter
MAJORITY_REACH = 3  # LangSplat's `smooth`: a 7 x 7 window (truncated at the far edges, as there)
NORM_EPS = 1e-9


def _reflect_101(index: np.ndarray, size: int) -> np.ndarray:
    """cv2's BORDER_REFLECT_101 (gfedcb|abcdefgh|gfedcba) of integer positions on an axis of `size`."""
    if size == 1:
        return np.zeros_like(index)
    period = 2 * (size - 1)
    i = np.mod(index, period)
    return np.where(i < size, i, period - i)


def box_filter(image: np.ndarray, size: int = BOX_SIZE) -> np.ndarray:
    """[H, W] -> [H, W] float64: cv2.filter2D(image, -1, ones((size, size)) / size²), the default
    anchor (size // 2) and border (BORDER_REFLECT_101):

        out[y, x] = Σ_{a, b = -size//2}^{size - 1 - size//2} image[r(y + a), r(x + b)] / size²,

    r reflecting without repeating the edge pixel. Summed in float64 through a summed-area table of
    the padded image (cv2 sums float32 maps in float32, so the two agree to float32 rounding)."""
    img = np.asarray(image, np.float64)
    h, w = img.shape
    before, after = size // 2, size - 1 - size // 2
    rows = _reflect_101(np.arange(-before, h + after), h)
    cols = _reflect_101(np.arange(-before, w + after), w)
    padded = img[rows][:, cols]
    table = np.zeros((padded.shape[0] + 1, padded.shape[1] + 1))
    table[1:, 1:] = padded.cumsum(0).cumsum(1)
    window = table[size:, size:] - table[:-size, size:] - table[size:, :-size] + table[:-size, :-size]
    return window / (size * size)


def majority_filter(mask: np.ndarray, reach: int = MAJORITY_REACH) -> np.ndarray:
    """[H, W] bool: LangSplat's `smooth`. Pixel (i, j) becomes the majority value of the window rows
    max(0, i − reach) .. min(i + reach + 1, H − 1) − 1 and columns likewise (its upper bound H − 1,
    not H, leaves the last row and column out of every window, as there); a tie gives False
    (`argmax(bincount)` takes the smaller value). An empty window (H or W of 1), where LangSplat's
    code fails, gives False."""
    m = np.asarray(mask, bool)
    h, w = m.shape
    table = np.zeros((h + 1, w + 1), np.int64)
    table[1:, 1:] = m.astype(np.int64).cumsum(0).cumsum(1)
    r0 = np.maximum(np.arange(h) - reach, 0)
    r1 = np.minimum(np.arange(h) + reach + 1, h - 1)
    c0 = np.maximum(np.arange(w) - reach, 0)
    c1 = np.minimum(np.arange(w) + reach + 1, w - 1)
    r1, c1 = np.maximum(r1, r0), np.maximum(c1, c0)
    ones = table[r1][:, c1] - table[r0][:, c1] - table[r1][:, c0] + table[r0][:, c0]
    size = (r1 - r0)[:, None] * (c1 - c0)[None, :]
    return 2 * ones > size


def langsplat_mask(relevancy_map: np.ndarray, threshold: float = LANGSPLAT_MASK_THRESHOLD) -> np.ndarray:
    """[H, W] relevancy -> [H, W] bool predicted mask (step 3 of the module docstring)."""
    r = np.asarray(relevancy_map, np.float64)
    valid = 0.5 * (box_filter(r) + r)
    shifted = valid - valid.min()
    scaled = np.clip(2.0 * shifted / (shifted.max() + NORM_EPS) - 1.0, 0.0, 1.0)
    return majority_filter(scaled > threshold)


def peak_in_boxes(relevancy_map: np.ndarray, boxes: np.ndarray) -> bool:
    """Whether a pixel where the box-filtered relevancy peaks lies in one of boxes [B, 4] (x1, y1,
    x2, y2 in pixels, either corner order; bounds included) (step 4)."""
    smooth = box_filter(relevancy_map)
    ys, xs = np.nonzero(smooth == smooth.max())
    for x1, y1, x2, y2 in np.asarray(boxes, np.float64).reshape(-1, 4):
        inside = (xs >= min(x1, x2)) & (xs <= max(x1, x2)) & (ys >= min(y1, y2)) & (ys <= max(y1, y2))
        if inside.any():
            return True
    return False


@numba.njit(parallel=True, cache=True)
def _blend_kernel(local, weights, feats, out, norms):  # pragma: no cover - jitted
    """out[p] = Σ_s weights[p, s] feats[local[p, s]] summed in float64, stored float32, and norms[p]
    = its float64 norm. local [P, k] int32 (-1: empty slot), weights [P, k] float32, feats [U, D]
    float32, out [P, D] float32, norms [P] float64."""
    n_pix, k = local.shape
    dim = feats.shape[1]
    chunk = 256
    for c in numba.prange((n_pix + chunk - 1) // chunk):
        acc = np.empty(dim)  # one per run of pixels: an allocation per pixel cost more than its blend
        sq = np.empty(8)  # eight running sums of squares (lanes d mod 8): one is a serial chain of adds
        for p in range(c * chunk, min(n_pix, (c + 1) * chunk)):
            acc[:] = 0.0
            for s in range(k):
                u = local[p, s]
                if u >= 0:
                    w = np.float64(weights[p, s])
                    for d in range(dim):
                        acc[d] += w * feats[u, d]
            sq[:] = 0.0
            for d in range(dim):
                out[p, d] = acc[d]
                sq[d % 8] += acc[d] * acc[d]
            norms[p] = np.sqrt(((sq[0] + sq[4]) + (sq[1] + sq[5])) + ((sq[2] + sq[6]) + (sq[3] + sq[7])))


BLEND_BLOCK = 1 << 15  # pixels blended at a time: their [P, D] float32 features (64 MB at D = 512)


def blend_cosines(ids: np.ndarray, weights: np.ndarray, features: np.ndarray, embeddings: np.ndarray) -> np.ndarray:
    """[E, H, W] float32 cosines of each pixel's blended feature with each embedding (steps 1-2).

    ids, weights: [H, W, k] top-k lists (-1 / 0 padding); features: [U, D] the features of the
    Gaussians ids names, row u for the u-th smallest id present (`np.unique` order), zero rows for
    Gaussians without one; embeddings: [E, D] unit rows (`blend_local_cosines`)."""
    h, w, k = ids.shape
    return blend_local_cosines(local_ids(ids.reshape(-1, k))[1], weights, features, embeddings).reshape(-1, h, w)


def blend_local_cosines(local: np.ndarray, weights: np.ndarray, features: np.ndarray, embeddings: np.ndarray) -> np.ndarray:
    """[E, P] float32 `blend_cosines` of pixels whose slots are rows of `features` already: local
    [P, k] int32 (-1 empty, `local_ids`), weights [P, k]. A block of pixels at a time: the blend
    (`_blend_kernel`), then its norms and its product with each embedding (BLAS, one matrix-vector
    product an embedding, so an embedding's cosines are the same bits whatever the others: round 50
    found one [P, D] x [D, E] product rounding the query's column otherwise when a negative was
    repeated, which moved LangSplat's localization peak); 0 where a pixel's blend is zero."""
    n_pix, k = local.shape
    wts = np.ascontiguousarray(weights.reshape(-1, k), np.float32)
    feats = np.ascontiguousarray(features, np.float32)
    emb = np.ascontiguousarray(embeddings, np.float32).reshape(-1, feats.shape[1])
    out = np.empty((emb.shape[0], n_pix), np.float32)
    block = np.empty((min(BLEND_BLOCK, n_pix), feats.shape[1]), np.float32)
    norms = np.empty(block.shape[0])
    for lo in range(0, n_pix, BLEND_BLOCK):
        hi = min(lo + BLEND_BLOCK, n_pix)
        blend, norm = block[: hi - lo], norms[: hi - lo]
        _blend_kernel(local[lo:hi], wts[lo:hi], feats, blend, norm)
        dots = np.empty((emb.shape[0], hi - lo))
        for e in range(emb.shape[0]):
            dots[e] = blend @ emb[e]
        out[:, lo:hi] = np.divide(dots, norm, out=np.zeros_like(dots), where=norm > 0)
    return out


def present_ids(ids: np.ndarray) -> np.ndarray:
    """The distinct ids >= 0 of ids (any shape), increasing: `np.unique(ids[ids >= 0])` by a mark per id."""
    valid = ids[ids >= 0]
    if valid.size == 0:
        return np.zeros(0, np.int64)
    marks = np.zeros(int(valid.max()) + 1, bool)
    marks[valid] = True
    return np.flatnonzero(marks)


def local_ids(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(`present_ids(ids)`, ids (any shape, -1 empty) as int32 rows of it, -1 staying -1)."""
    present = present_ids(ids)
    lookup = np.full(int(present[-1]) + 2 if present.size else 1, -1, np.int32)
    lookup[present] = np.arange(present.size, dtype=np.int32)
    return present, lookup[np.where(ids >= 0, ids, -1)]


def blend_cosines_reference(ids: np.ndarray, weights: np.ndarray, features: np.ndarray, embeddings: np.ndarray) -> np.ndarray:
    """Reference of `blend_cosines` (numpy, float64)."""
    h, w, k = ids.shape
    flat = ids.reshape(-1, k)
    present = np.unique(flat[flat >= 0])
    local = np.searchsorted(present, np.maximum(flat, 0))
    wts = np.where(flat >= 0, weights.reshape(-1, k).astype(np.float64), 0.0)
    feats = np.asarray(features, np.float64)
    blend = np.einsum("pk,pkd->pd", wts, feats[local] if feats.shape[0] else np.zeros((*local.shape, feats.shape[1])))
    norm = np.linalg.norm(blend, axis=1, keepdims=True)
    unit = np.divide(blend, norm, out=np.zeros_like(blend), where=norm > 0)
    return (unit @ np.asarray(embeddings, np.float64).T).T.reshape(-1, h, w).astype(np.float32)


@dataclass
class LangSplatRow:
    """One (view, category) pair: its IoU, whether the relevancy peak fell in a box, and the share
    of the pixels' weight (α) inside the top-k blend over the view."""

    view: str
    category: str
    iou: float
    hit: bool
    coverage: float


@dataclass
class LangSplatReport:
    """rows: one per scored (view, category); missing_views and skipped as in `lerf.Lerf2DReport`."""

    rows: list[LangSplatRow]
    topk: int
    mask_threshold: float
    missing_views: list[str] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)

    @property
    def miou(self) -> float:
        return float(np.mean([r.iou for r in self.rows])) if self.rows else float("nan")

    @property
    def localization(self) -> float:
        return float(np.mean([r.hit for r in self.rows])) if self.rows else float("nan")

    def per_category(self) -> dict[str, tuple[float, float]]:
        """category -> (mean IoU, localisation accuracy) over its views."""
        names = sorted({r.category for r in self.rows})
        return {n: (float(np.mean([r.iou for r in self.rows if r.category == n])), float(np.mean([r.hit for r in self.rows if r.category == n])))
                for n in names}

    def to_dict(self) -> dict:
        return {"protocol": "langsplat", "mIoU": self.miou, "localization_accuracy": self.localization, "topk": self.topk,
                "mask_threshold": self.mask_threshold, "rows": [r.__dict__ for r in self.rows], "missing_views": self.missing_views,
                "skipped_pairs": [{"view": v, "category": c} for v, c in self.skipped],
                "per_category": {n: {"IoU": i, "localization": a} for n, (i, a) in self.per_category().items()}}

    def format(self) -> str:
        lines = [f"LangSplat protocol: mIoU {self.miou:.4f}  localization accuracy {self.localization:.4f}  "
                 f"({len(self.rows)} pairs, mask threshold {self.mask_threshold:g}, top-{self.topk} blend)"]
        for name, (iou, acc) in self.per_category().items():
            lines.append(f"  {name:24s} IoU {iou:.4f}  loc {acc:.2f}")
        coverage = [r.coverage for r in self.rows]
        if coverage:
            lines.append(f"  the top-{self.topk} blend holds {100 * min(coverage):.2f}-{100 * max(coverage):.2f} % of the views' rendered weight")
        if self.skipped:
            lines.append(f"  ({len(self.skipped)} (view, category) pairs with degenerate ground truth left out)")
        return "\n".join(lines)


def view_feature_blend(prepared, camera: Camera, field, assigned: np.ndarray, embeddings: np.ndarray, topk: int,
                       near: float = NEAR) -> tuple[np.ndarray, float]:
    """([E, H, W] cosines of the view's blended features with `embeddings`, the share of the pixels'
    α the top-k slots hold). assigned: [N] bool `field.assigned()`: the others blend as zeros."""
    out = rasterize_topk(prepared, camera, topk, near=near)
    h, w, k = out.ids.shape
    present, local = local_ids(out.ids.reshape(-1, k))  # numbered once: the features are fetched, then blended, by it
    feats = field.reconstruct(present).astype(np.float32) if present.size else np.zeros((0, field.dim), np.float32)
    feats[~assigned[present]] = 0.0
    held = float(np.where(out.ids >= 0, out.weights, 0.0).sum(dtype=np.float64))
    rendered = float(out.alpha.sum(dtype=np.float64))
    cosines = blend_local_cosines(local, out.weights, feats, embeddings).reshape(-1, h, w)
    return cosines, (held / rendered if rendered > 0 else 1.0)


def view_bytes(width: int, height: int, topk: int, embeddings: int) -> int:
    """Memory one view of the protocol needs at most: the top-k lists (ids, weights and their local
    ids: 12 bytes a slot), the cosines and the maps (float32 and float64, ~8·E + 64 bytes a pixel)."""
    return width * height * (12 * topk + 8 * embeddings + 64)


def check_view_memory(view: AnnotatedView, topk: int, embeddings: int) -> None:
    """DrsplatError naming the view before it is rendered when its lists would not fit in memory (an
    annotation may be up to 8x its camera's size: 8000x6000 pixels at k = 40 is 23 GB)."""
    need, free = view_bytes(view.width, view.height, topk, embeddings), available_memory()
    if need > free:
        raise DrsplatError(f"{view.path or view.name}: view {view.name} is annotated at {view.width}x{view.height}; its top-{topk} "
                           f"feature blend needs {format_size(need, up=True)} and {format_size(free)} is free: pass a smaller --topk "
                           "or annotations at the camera's size")


def langsplat_report(scene, field, cameras: list[Camera], views: list[AnnotatedView], queries: dict[str, np.ndarray], negatives: np.ndarray,
                     topk: int = DEFAULT_TOPK, mask_threshold: float = LANGSPLAT_MASK_THRESHOLD, show_progress: bool = True,
                     cancel: CancelToken | None = None, assigned: np.ndarray | None = None, near: float = NEAR) -> LangSplatReport:
    """Evaluate a registered field with LangSplat's 2D protocol (module docstring).

    scene: the registered GaussianScene; field: its LanguageField; cameras: matched to views by name
    (`lerf.camera_for_view`); queries: category -> [D] text embedding; negatives: [C, D] canonical
    (+ user) negative embeddings (both normalised here); assigned: [N] bool `field.assigned()` when the
    caller has it. Pairs of categories without a query are skipped with a warning; degenerate ground
    truth is left out as in `lerf.lerf_2d_report`. near: the near plane the views are rendered with.
    """
    by_name = {c.name: c for c in cameras}
    say_annotations_moved(cameras)
    prepared = prepare_scene(scene)
    assigned = np.asarray(field.assigned() if assigned is None else assigned, bool)
    rows: list[LangSplatRow] = []
    missing: list[str] = []
    skipped: list[tuple[str, str]] = []
    unqueried: set[str] = set()
    for view in progress(views, "LERF-OVS views", enabled=show_progress, unit="view"):
        cam = camera_for_view(by_name, view)
        if cam is None:
            missing.append(view.name)
            continue
        skipped += [(view.name, c) for c in view.skipped]
        photo = view
        view, seen = annotation_on_pinhole(view, cam)
        names = [c for c in view.masks if c in queries]
        unqueried |= {c for c in view.masks if c not in queries}
        if not names:
            continue
        if cancel is not None:
            cancel.raise_if_cancelled()
        check_view_memory(view, topk, len(names) + len(negatives))
        embeddings = query_rows(np.stack([queries[c] for c in names] + list(negatives)))  # unit rows: the cosines' other side
        cosines, coverage = view_feature_blend(prepared, cam, field, assigned, embeddings, topk, near)
        pos = cosines[: len(names)].reshape(len(names), -1).T
        neg = cosines[len(names):].reshape(len(negatives), -1).T
        relevancy = relevancy_from_scores(pos, neg).T.reshape(len(names), view.height, view.width)
        for q, category in enumerate(names):
            gt = view.masks[category]
            if not gt.any():
                warn_empty_ground_truth(view, category, photo)
                skipped.append((view.name, category))
                continue
            relevant = relevancy[q] if seen is None or not seen.any() else np.where(seen, relevancy[q], relevancy[q][seen].min())  # no peak off the photo
            pred = langsplat_mask(relevant, mask_threshold)
            if seen is not None:
                pred &= seen
            hit = peak_in_boxes(relevant, view.boxes.get(category, np.zeros((0, 4))))
            rows.append(LangSplatRow(view.name, category, mask_iou(pred, gt), bool(hit), coverage))
    if missing:
        log.warning("%d annotated views have no camera of the same name: %s", len(missing), ", ".join(missing[:5]))
    if unqueried:
        log.warning("no query for categories %s; skipped", sorted(unqueried))
    return LangSplatReport(rows, topk, mask_threshold, missing, skipped)
