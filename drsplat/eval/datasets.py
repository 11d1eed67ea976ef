"""Readers (and stand-in writers) for the ground truth of the evaluation datasets.

LERF-OVS (LangSplat's release of LERF scenes with annotations; OpenGaussian uses it too)::

    lerf_ovs/<scene>/images/frame_00001.jpg ...     the training images (+ sparse/0 COLMAP model)
    lerf_ovs/label/<scene>/frame_00041.json          LabelMe-style annotation of one view
    lerf_ovs/label/<scene>/frame_00041.jpg           the annotated image

    frame_XXXXX.json = {"info": {"name": "frame_00041.jpg", "width": W, "height": H},
                        "objects": [{"category": "old camera", "bbox": [x1, y1, x2, y2],
                                     "segmentation": [[x, y], [x, y], ...]}, ...]}

  `segmentation` is one polygon (a list of [x, y]) or a list of polygons (COCO style); an object
  may also appear as several entries with one category. All polygons of a category are united.
  A view is named by the stem of `info.name` (the JSON file's stem when `info.name` is absent; a
  disagreement between the two is warned about) and pairs with the training camera whose image
  stem equals that name. Two files naming the same view are refused.

ScanNet (v2)::

    scans/<scene>/<scene>_vh_clean_2.labels.ply      mesh vertices x, y, z, ..., label (NYU40 id, 0 = none)
    scans/<scene>/pose/<i>.txt                      4 x 4 camera-to-world (OpenCV axes), from the .sens export
    scans/<scene>/intrinsic/intrinsic_color.txt     4 x 4 intrinsics of the colour images
    scans/<scene>/color/<i>.jpg                     colour images
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from pathlib import Path

import numpy as np

from drsplat.cameras import EXIF_ROTATED, FRAMING_TOLERANCE, exif_orientation, header_size, same_aspect
from drsplat.cameras import load_scannet_cameras  # noqa: F401  (the ScanNet camera reader lives with the others)
from drsplat.errors import DrsplatError, InputError, UsageError, hidden_character
from drsplat.eval.polyfill import fill_polygon, truncate_vertices
from drsplat.scene import check_element_sizes, read_ply_header, read_plyfile, trailing_ascii_lines, trailing_bytes
from drsplat.utils import atomic_path, checked_names, clipped, load_npy, read_json, regular_file

log = logging.getLogger(__name__)

NYU40_NAMES = (
    "wall", "floor", "cabinet", "bed", "chair", "sofa", "table", "door", "window", "bookshelf",
    "picture", "counter", "blinds", "desk", "shelves", "curtain", "dresser", "pillow", "mirror", "floor mat",
    "clothes", "ceiling", "books", "refrigerator", "television", "paper", "towel", "shower curtain", "box", "whiteboard",
    "person", "night stand", "toilet", "sink", "lamp", "bathtub", "bag", "otherstructure", "otherfurniture", "otherprop",
)


# ---------------------------------------------------------------------------------------------- LERF-OVS

MAX_ANNOTATION_SIDE = 16384  # pixels per side of an annotated view (larger than any GPU texture); a bool mask is W·H bytes
MAX_ANNOTATION_SCALE = 8.0  # an annotation at most 8x its camera's size (3DGS's -r goes to 8); rendering costs W·H


@dataclass
class AnnotatedView:
    """One annotated view: name (image stem), size, and a boolean mask [H, W] per category.

    path: the annotation file; skipped: category -> why its ground truth is degenerate (such a
    (view, category) pair is left out of every mean, see `rasterise_lerf_document`).
    """

    name: str
    width: int
    height: int
    masks: dict[str, np.ndarray]
    image_path: Path | None = None
    path: Path | None = None
    skipped: dict[str, str] = dataclass_field(default_factory=dict)
    boxes: dict[str, np.ndarray] = dataclass_field(default_factory=dict)  # category -> [B, 4] (x1, y1, x2, y2), one per object
    first_object: dict[str, int] = dataclass_field(default_factory=dict)  # category -> the index of its first entry of 'objects'


@dataclass
class LerfDocument:
    """A parsed LERF-OVS annotation before rasterising: objects are (category, polygons [P, 2] (x, y),
    its box [4] (x1, y1, x2, y2) or None where the object gives no 'bbox')."""

    path: Path
    name: str
    width: int
    height: int
    objects: list[tuple[str, list[np.ndarray], np.ndarray | None]]
    image: Path | None = None  # the annotated image beside it (`annotated_image`)


FAR_VERTEX = 1 << 20  # px: a polygon with a vertex farther outside the frame is clipped before the fill (`clip_polygon`)


def clip_polygon(points: np.ndarray, x_lo: float, y_lo: float, x_hi: float, y_hi: float) -> np.ndarray:
    """[Q, 2] the polygon points [P, 2] clipped to the box x_lo..x_hi, y_lo..y_hi (Sutherland–Hodgman,
    one box side at a time): inside the box it is the same region; a vertex far outside becomes the
    points where its edges cross the box."""
    poly = np.asarray(points, np.float64).reshape(-1, 2)
    for axis, bound, keep_below in ((0, x_lo, False), (0, x_hi, True), (1, y_lo, False), (1, y_hi, True)):
        if poly.shape[0] == 0:
            break
        inside = poly[:, axis] <= bound if keep_below else poly[:, axis] >= bound
        out = []
        for i in range(poly.shape[0]):
            a, b = poly[i - 1], poly[i]
            if inside[i] != inside[i - 1]:  # the edge a -> b crosses the bound: keep the crossing
                # in halves (exact for normal numbers, so the same bits): b − a of two finite vertices ±1.7e308 apart
                # overflowed to inf, and the crossing became NaN (numpy's warnings, then a wrong mask; round 46)
                ha, hb = a * 0.5, b * 0.5
                t = (bound * 0.5 - ha[axis]) / (hb[axis] - ha[axis])
                cross = (ha + t * (hb - ha)) * 2.0
                cross[axis] = bound
                out.append(cross)
            if inside[i]:
                out.append(b)
        poly = np.array(out, np.float64).reshape(-1, 2)
    return poly


def polygon_mask(points: np.ndarray, height: int, width: int) -> np.ndarray:
    """[H, W] bool: the pixels LangSplat's `polygon_to_mask` paints for the polygon ([P, 2] float (x, y)
    pixel coordinates): the vertices truncated toward zero as its int32 cast does, then OpenCV's
    fill, outline included (`drsplat.eval.polyfill.fill_polygon`, the same pixels as cv2.fillPoly).

    A polygon with a vertex more than FAR_VERTEX px outside the frame is first clipped to a box 2 px
    beyond it (`clip_polygon`: the same region inside the frame), so the fixed-point arithmetic stays
    within int64; LangSplat's int32 cast has no meaningful value there either."""
    poly = np.asarray(points, np.float64).reshape(-1, 2)
    if poly.size and (np.abs(poly) > FAR_VERTEX + max(width, height)).any():
        poly = clip_polygon(poly, -2.0, -2.0, width + 2.0, height + 2.0)
    if poly.shape[0] == 0:  # no vertex: OpenCV draws nothing; the caller leaves its (view, category) pair out
        return np.zeros((height, width), np.bool_)
    # one or two vertices are drawn as OpenCV draws them (a point, a line; round 89a F1: a 2-point
    # polygon was said to cover no pixel and its pair left out, the same line with a third vertex scored)
    return fill_polygon(truncate_vertices(poly), height, width)


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)  # JSON true is a Python int


def _is_point(value: object) -> bool:
    return isinstance(value, list) and len(value) == 2 and all(_is_number(v) for v in value)


def _is_polygon(value: object) -> bool:
    return isinstance(value, list) and all(_is_point(p) for p in value)


def _polygon_array(path: Path, field: str, points: list, what: str = "polygon") -> np.ndarray:
    """[P, 2] float64 of a list of [x, y] points, refusing non-finite coordinates (the error names
    `what` they are: a polygon, or a box's two corners)."""
    try:
        poly = np.array([[float(x), float(y)] for x, y in points], np.float64).reshape(-1, 2)
    except OverflowError:  # a JSON integer beyond float range
        poly = np.full((1, 2), np.inf)
    if not np.isfinite(poly).all():
        raise InputError(path, f"{what} has non-finite coordinates", field=field)
    return poly


def parse_segmentation(path: Path, k: int, segmentation: object) -> list[np.ndarray]:
    """The polygons of `objects[k].segmentation`: a list of [x, y] points is one polygon; a list of
    such lists (COCO style) is several polygons whose union is the object. Anything else (triplets,
    a flat list of numbers, mixed shapes, strings, booleans) is an InputError naming the field."""
    field = f"objects[{k}].segmentation"
    if _is_polygon(segmentation):
        return [_polygon_array(path, field, segmentation)]
    if isinstance(segmentation, list) and segmentation and all(_is_polygon(p) and p for p in segmentation):
        return [_polygon_array(path, field, p) for p in segmentation]
    shown = json.dumps(segmentation)
    shown = shown if len(shown) <= 60 else shown[:57] + "..."
    raise InputError(path, f"expected a list of [x, y] points (one polygon) or a list of such lists (several polygons, "
                           f"united); got {shown}", field=field)


def _image_side(path: Path, info: dict, key: str) -> int:
    """info[key] as a whole number of pixels in 1..MAX_ANNOTATION_SIDE (128.0 is accepted, 128.9 and true are not)."""
    field = f"info.{key}"
    value = info.get(key)
    if value is None:
        raise InputError(path, f"missing: the annotated image's {key} in pixels", field=field)
    if not _is_number(value):
        raise InputError(path, f"is {json.dumps(value)[:40]}, not a number of pixels", field=field)
    if isinstance(value, float) and not (math.isfinite(value) and value.is_integer()):
        raise InputError(path, f"is {value!r}, not a whole number of pixels", field=field)
    shown = f"{value:.6g}" if isinstance(value, float) else (str(value) if abs(value) < 10**12 else f"{str(value)[:6]}... ({len(str(value))} digits)")
    if value < 1:
        raise InputError(path, f"is {shown}: an image is at least 1 pixel on each side", field=field)
    if value > MAX_ANNOTATION_SIDE:
        raise InputError(path, f"is {shown} pixels; at most {MAX_ANNOTATION_SIDE} are supported", field=field)
    return int(value)


def _view_name(path: Path, info: dict) -> str:
    """The view's name: the stem of info.name, or the file's stem without one; a disagreement is warned."""
    given = info.get("name")
    if given is None:
        return path.stem
    if not isinstance(given, str) or not Path(given).stem:
        raise InputError(path, f"is {json.dumps(given)[:40]}; expected the annotated image's file name", field="info.name")
    name = Path(given).stem
    if name != path.stem:
        log.warning("%s: info.name %r names view %r but the file is named %r; the view is matched to a camera by info.name (%r)",
                    path, given, name, path.stem, name)
    return name


def _category(path: Path, k: int, value: object) -> str:
    """objects[k].category as given, or one InputError: str() would turn null, 5 or a list into a
    category of its own ("None"), and a blank one names nothing a query could embed."""
    if isinstance(value, str) and value.strip():
        hidden = hidden_character(value)
        if hidden is not None:  # printed in `eval lerf`'s table and embedded as a query, which `--text` refuses alike
            raise InputError(path, f"{clipped(json.dumps(value), 60)} holds {hidden}, which a terminal would not show as itself",
                             field=f"objects[{k}].category")
        return value
    kind = ("null" if value is None else "an empty string" if isinstance(value, str) else json.dumps(value)[:40])
    raise InputError(path, f"is {kind}, not a non-empty string", field=f"objects[{k}].category")


def _box(path: Path, k: int, value: object) -> np.ndarray | None:
    """objects[k].bbox as [4] float64 (x1, y1, x2, y2), None when absent; anything but four finite
    numbers is an InputError naming the field."""
    if value is None:
        return None
    if not (isinstance(value, list) and len(value) == 4 and all(_is_number(v) for v in value)):
        raise InputError(path, "is not a list of four numbers [x1, y1, x2, y2]", field=f"objects[{k}].bbox")
    return _polygon_array(path, f"objects[{k}].bbox", [value[:2], value[2:]], "box").reshape(4)


def read_lerf_document(path: str | Path) -> LerfDocument:
    """Parse one LERF-OVS `frame_<n>.json` and check its sizes, allocating no image."""
    path = Path(path)
    data = read_json(path, "a LERF-OVS annotation")
    info = data.get("info") if isinstance(data, dict) else None
    if not isinstance(info, dict):
        raise InputError(path, "missing the 'info' object with width and height", field="info")
    width, height = _image_side(path, info, "width"), _image_side(path, info, "height")
    objects = data.get("objects")
    if not isinstance(objects, list):
        raise InputError(path, "missing the 'objects' list", field="objects")
    parsed = []
    for k, obj in enumerate(objects):
        if not isinstance(obj, dict) or "category" not in obj or "segmentation" not in obj:
            raise InputError(path, "object without a category or a segmentation", field=f"objects[{k}]")
        parsed.append((_category(path, k, obj["category"]), parse_segmentation(path, k, obj["segmentation"]), _box(path, k, obj.get("bbox"))))
    return LerfDocument(path, _view_name(path, info), width, height, parsed, annotated_image(path, width, height))


def annotated_image(path: Path, width: int, height: int) -> Path | None:
    """The annotated image beside annotation `path` (frame_00041.json's frame_00041.jpg), or None. Its size from its header (with its EXIF
    orientation, as LabelMe shows it) must be info's width x height, the pixels the polygons are drawn in: a size
    that says otherwise put the polygons at another scale without a word (round 59b: info doubled, the polygons
    covering a quarter of the frame, mIoU 0.843 -> 0.774, exit 0). A file no image reader opens is not compared
    (the metric reads only the polygons)."""
    image = path.with_suffix(".jpg")
    if not image.is_file():
        return None
    size = header_size(image)
    if size is None:
        return image
    turn = exif_orientation(image)
    w, h = size[::-1] if turn in EXIF_ROTATED else size
    if (w, h) != (width, height):
        shown = f"{w}x{h} as shown ({size[0]}x{size[1]} stored, EXIF orientation {turn})" if turn in EXIF_ROTATED else f"{w}x{h}"
        raise InputError(path, f"says the annotated image is {width}x{height}, but {image.name} beside it is {shown}: the polygons "
                               "would be read at another scale; give info.width and info.height of the image they were drawn on",
                         field="info.width")
    return image


def check_annotation_size(path: Path | None, name: str, width: int, height: int, camera_width: int, camera_height: int) -> tuple[float, float]:
    """(sx, sy) = annotation size / camera size. The aspect must agree (`cameras.same_aspect`
    within FRAMING_TOLERANCE, as a training image must) and the annotation may be at most MAX_ANNOTATION_SCALE times the
    camera's size (rendering happens at the annotation's size); InputError naming `path` otherwise."""
    sx, sy = width / camera_width, height / camera_height
    if not same_aspect(width, height, camera_width, camera_height, FRAMING_TOLERANCE):
        raise InputError(path, f"view {name} is annotated at {width}x{height} but its camera is {camera_width}x{camera_height} "
                               "(different aspect)", field="info.width")
    # half a camera pixel of rounding: 986x728 trained at -r 8 is 123x91, 8.016x (round 76b F3: refused)
    if width > MAX_ANNOTATION_SCALE * (camera_width + 0.5) or height > MAX_ANNOTATION_SCALE * (camera_height + 0.5):
        raise InputError(path, f"view {name} is annotated at {width}x{height}, more than {MAX_ANNOTATION_SCALE:g} times its "
                               f"camera's {camera_width}x{camera_height}", field="info.width")
    return sx, sy


def rasterise_lerf_document(doc: LerfDocument) -> AnnotatedView:
    """Masks per category: the union of the category's polygons.

    Degenerate ground truth: a polygon that paints no pixel (no point, or wholly outside the image)
    means the category's mask lacks part of what was annotated, so its IoU would be wrong either way
    (0 against any selection, or 1.0 when nothing is selected and the whole mask is empty). Such a
    (view, category) pair is warned about (file, object index, category) and moved to `skipped`,
    which every mean leaves out. A polygon of one or two points paints its point or line, as
    LangSplat's cv2.fillPoly does, and is scored, with a warning.
    """
    masks: dict[str, np.ndarray] = {}
    skipped: dict[str, str] = {}
    boxes: dict[str, list[np.ndarray]] = {}
    first_object: dict[str, int] = {}
    for k, (category, polygons, box) in enumerate(doc.objects):
        if box is None and any(len(p) for p in polygons):  # no 'bbox': the extent of its polygons
            points = np.concatenate([p for p in polygons if len(p)])
            box = np.concatenate([points.min(axis=0), points.max(axis=0)])
        if box is not None:
            boxes.setdefault(category, []).append(box)
        first_object.setdefault(category, k)
        for j, poly in enumerate(polygons):
            m = polygon_mask(poly, doc.height, doc.width)
            which = f"objects[{k}]" if len(polygons) == 1 else f"objects[{k}] polygon {j}"
            if 0 < len(poly) < 3 and m.any():
                log.warning("%s: %s (category %r) has %d point%s, not an area; scored as OpenCV's fill draws it (%s, %d px), "
                            "as LangSplat's ground truth is", doc.path, which, category, len(poly), "" if len(poly) == 1 else "s",
                            "a point" if len(poly) == 1 else "a line", int(m.sum()))
            if not m.any():
                why = "has no point" if len(poly) == 0 else f"lies wholly outside the {doc.width}x{doc.height} image"
                log.warning("%s: %s (category %r) %s and covers no pixel; the (view %s, %r) pair is left out of the means",
                            doc.path, which, category, why, doc.name, category)
                skipped.setdefault(category, f"{which} {why}")
            masks[category] = masks[category] | m if category in masks else m
    for category in skipped:
        masks.pop(category, None)
    return AnnotatedView(doc.name, doc.width, doc.height, masks, doc.image, doc.path, skipped,
                         {c: np.stack(b) for c, b in boxes.items() if c in masks}, first_object)


def load_lerf_view(path: str | Path) -> AnnotatedView:
    """Read one LERF-OVS `frame_<n>.json` (LabelMe-style polygons) into masks per category
    (`read_lerf_document`, then `rasterise_lerf_document`)."""
    return rasterise_lerf_document(read_lerf_document(path))


def lerf_annotation_files(label_dir: str | Path) -> list[Path]:
    """The annotation files of one LERF-OVS scene folder: every `*.json` in it, sorted."""
    label_dir = Path(label_dir)
    if not label_dir.is_dir():
        found = "is not a folder" if label_dir.exists() else "annotation folder not found"
        raise InputError(label_dir, f"{found} (expected lerf_ovs/label/<scene>/ with frame_*.json)")
    files = sorted(label_dir.glob("*.json"))
    if not files:
        raise InputError(label_dir, "no *.json annotations in this folder (expected frame_XXXXX.json, LabelMe-style)")
    return files


def load_lerf_annotations(label_dir: str | Path, camera_sizes: dict[str, tuple[int, int]] | None = None) -> list[AnnotatedView]:
    """All annotated views of one LERF-OVS scene (`label/<scene>/frame_*.json`), sorted by file name.

    Every file is parsed and checked before any mask is drawn: two files naming one view are refused,
    and with camera_sizes (view name -> camera (width, height)) a view's size must fit its camera
    (`check_annotation_size`), so a lying size allocates nothing.
    """
    docs = [read_lerf_document(f) for f in lerf_annotation_files(label_dir)]
    first: dict[str, Path] = {}
    for doc in docs:
        if doc.name in first:
            raise InputError(doc.path, f"annotates view {doc.name!r}, as {first[doc.name].name} does; each view may be annotated "
                                       "once (its pairs would be counted twice)", field="info.name")
        first[doc.name] = doc.path
        if camera_sizes is not None and doc.name in camera_sizes:
            check_annotation_size(doc.path, doc.name, doc.width, doc.height, *camera_sizes[doc.name])
    return [rasterise_lerf_document(doc) for doc in docs]


def mask_to_polygons(mask: np.ndarray, tolerance: float = 0.0, min_pixels: int = 1) -> list[np.ndarray]:
    """Outer boundaries of a boolean mask as polygons [P, 2] (x, y), one per piece without holes (`hole_free_pieces`) of
    each connected component: an annotation is the union of its polygons, so a hole cannot be written as one, and the
    outer boundary alone filled it (round 59b: the tiny room's floor annotation covered the objects standing on it,
    +26-37 % in 9 of 16 views). tolerance: skimage's `approximate_polygon`; 0, the default, keeps every boundary
    vertex, so that LangSplat's fill paints each piece back exactly (0.5 cut concave corners: 14 extra pixels on an L
    of 800). Components of fewer than `min_pixels` pixels are left out; with the default, 1, none is, and every mask
    fills back exactly (a single pixel's contour gives four vertices at its centre, which the fill paints; with 4, a
    checkerboard or a one-pixel diagonal wrote nothing: round 60a)."""
    from skimage import measure

    labelled = measure.label(mask, connectivity=1)
    polys = []
    for region in measure.regionprops(labelled):
        if region.area < min_pixels:
            continue
        rows, cols = region.slice
        for piece, (r0, c0) in hole_free_pieces(labelled[rows, cols] == region.label):
            comp = np.pad(piece, 1)
            contours = measure.find_contours(comp.astype(np.float32), 0.5)
            if not contours:
                continue
            outer = measure.approximate_polygon(max(contours, key=len), tolerance)
            # - 1 undoes the padding; the piece's and the region's offsets place it in the mask
            polys.append(_inside_pixel_centres(comp, outer) - 1.0 + np.array([c0 + cols.start, r0 + rows.start], np.float64))
    return polys


def hole_free_pieces(component: np.ndarray) -> list[tuple[np.ndarray, tuple[int, int]]]:
    """A 4-connected boolean mask [H, W] cut into 4-connected pieces without holes whose union is the mask: (the piece
    cropped to its box, (row, column) of the box in `component`). Cut at the first column of every hole at once: each
    hole then touches a column outside its strip, so it opens to the outside (a hole is 4-connected, so its columns are
    one interval and every strip it crosses holds one of its ends' columns); a piece still holding a hole, which the
    argument rules out, is cut again. Without holes: [(component, (0, 0))]. Iterative and one labelling per pass: cutting
    one column at a time, recursively, passed Python's recursion limit on masks with many pinholes (round 60a: a 480x640
    mask with 0.5 % of its pixels holes, after 21 s)."""
    from scipy import ndimage

    done: list[tuple[np.ndarray, tuple[int, int]]] = []
    work = [(np.asarray(component, bool), (0, 0))]
    while work:
        comp, (r0, c0) = work.pop()
        holes = ndimage.binary_fill_holes(comp) & ~comp
        if not holes.any():
            done.append((comp, (r0, c0)))
            continue
        hole_labels, count = ndimage.label(holes)
        firsts = [box[1].start for box in ndimage.find_objects(hole_labels) if box is not None]
        cuts = np.unique(np.asarray(firsts, np.int64))
        # a blank column before each cut keeps the strips apart in one labelling; dropping them maps the labels back
        spread = np.insert(comp, cuts, False, axis=1)
        labels, _ = ndimage.label(spread)
        labels = np.delete(labels, cuts + np.arange(cuts.size), axis=1)
        for k, box in enumerate(ndimage.find_objects(labels), start=1):
            if box is not None:
                work.append((labels[box] == k, (r0 + box[0].start, c0 + box[1].start)))
    return done


def _inside_pixel_centres(mask: np.ndarray, contour: np.ndarray) -> np.ndarray:
    """[P, 2] (x, y): each vertex of a level-½ contour of `mask` ([P, 2] (row, col), one coordinate
    half-way between two pixel centres) moved to the centre of the one of the two pixels inside the
    mask, so that LangSplat's fill (vertices truncated, the outline painted through them) paints
    the mask's own boundary pixels."""
    rows, cols = contour[:, 0], contour[:, 1]
    lo_r, lo_c = np.floor(rows).astype(np.int64), np.floor(cols).astype(np.int64)
    hi_r, hi_c = np.ceil(rows).astype(np.int64), np.ceil(cols).astype(np.int64)
    r = np.where(mask[lo_r, lo_c], lo_r, hi_r)
    c = np.where(mask[lo_r, lo_c], lo_c, hi_c)
    return np.stack([c, r], axis=1).astype(np.float64)


def write_lerf_view(out_dir: str | Path, name: str, masks: dict[str, np.ndarray], image: np.ndarray | None = None) -> Path:
    """Write a view in the LERF-OVS layout (`<name>.json` polygons + `<name>.jpg`). Returns the JSON path."""
    from PIL import Image

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    height, width = next(iter(masks.values())).shape if masks else (image.shape[0], image.shape[1])
    objects = []
    for category, mask in masks.items():
        for poly in mask_to_polygons(mask):
            x1, y1 = poly.min(axis=0)
            x2, y2 = poly.max(axis=0)
            objects.append({"category": category, "bbox": [float(x1), float(y1), float(x2), float(y2)],
                            "segmentation": [[round(float(x), 2), round(float(y), 2)] for x, y in poly]})
    doc = {"info": {"name": f"{name}.jpg", "width": int(width), "height": int(height)}, "objects": objects}
    path = out_dir / f"{name}.json"
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(doc))
    if image is not None:
        with atomic_path(out_dir / f"{name}.jpg") as tmp:
            Image.fromarray(np.asarray(image, np.uint8)).save(tmp, format="JPEG", quality=90)
    return path


# ---------------------------------------------------------------------------------------------- ScanNet


@dataclass
class LabelledPoints:
    """points: [P, 3] float64; labels: [P] int (index into names, −1 = unannotated); names: label names."""

    points: np.ndarray
    labels: np.ndarray
    names: list[str]


SCANNET_LABELS_PATTERN = "*_vh_clean_2.labels.ply"  # the labelled mesh of a ScanNet scene folder
POINT_CLOUD_SUFFIXES = (".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")  # read through open3d


def load_labelled_points(path: str | Path, raw_names: tuple[str, ...] | list[str] = NYU40_NAMES,
                         classes: list[str] | None = None, label_field: str = "label") -> LabelledPoints:
    """Read a labelled point cloud: ScanNet's `<scene>_vh_clean_2.labels.ply`, or any point cloud open3d reads
    (.pcd, .xyz, .xyzn, .xyzrgb, .pts) with its raw labels beside it in `<file>.labels.npy` ([P] integers).

    The raw label r (PLY vertex property `label_field`, or the sidecar's entries) names raw_names[r − 1];
    r = 0 is unannotated. With `classes`, only those names are kept (in that order) and every other point
    becomes −1, e.g. the subsets of NYU40 classes used in published ScanNet tables.
    """
    path = regular_file(path)  # a FIFO or device would block the read forever
    if path.suffix.lower() in POINT_CLOUD_SUFFIXES:
        pts, raw, where = _read_open3d_cloud(path)
    else:
        pts, raw = _read_labelled_ply(path, label_field)
        where = label_field
    if raw.size and (raw.min() < 0 or raw.max() > len(raw_names)):
        raise InputError(path, f"labels range {raw.min()}..{raw.max()}, outside 0..{len(raw_names)} of the label names", field=where)
    labels = raw - 1
    out_names = list(raw_names)
    if classes is not None:
        unknown = [c for c in classes if c not in raw_names]
        if unknown:
            raise InputError(None, f"classes {unknown} are not among the dataset's label names")
        remap = np.full(len(raw_names) + 1, -1, np.int64)
        for k, c in enumerate(classes):
            remap[list(raw_names).index(c)] = k
        labels = np.where(labels >= 0, remap[np.maximum(labels, 0)], -1)
        out_names = list(classes)
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():
        log.warning("%s: %d points with non-finite coordinates dropped", path, int(bad.sum()))
        pts, labels = pts[~bad], labels[~bad]
    return LabelledPoints(pts, labels, out_names)


def _read_labelled_ply(path: Path, label_field: str) -> tuple[np.ndarray, np.ndarray]:
    """([P, 3] float64 points, [P] int64 raw labels) from a PLY's vertex element."""
    from plyfile import PlyElementParseError, PlyParseError

    header = read_ply_header(path)
    check_element_sizes(path, header, path.stat().st_size)  # no allocation from a lying header
    try:
        ply = read_plyfile(path)
        vertex = ply["vertex"]
    except PlyElementParseError as exc:  # a malformed row of an ASCII PLY, a value its property type cannot hold
        raise InputError(path, f"{_where_in_ply(exc)}{exc.message}", field=exc.prop.name if exc.prop else None) from None
    except (OSError, KeyError, PlyParseError, ValueError, OverflowError) as exc:
        raise InputError(path, f"not a readable PLY point cloud with a vertex element ({str(exc)[:200]})") from None
    names = vertex.data.dtype.names
    for f in ("x", "y", "z", label_field):
        if f not in names:
            raise InputError(path, "vertex property missing (a labelled cloud needs x, y, z and a label)", field=f)
    for k in "xyz":
        if vertex.data.dtype[k].kind not in "iuf":  # a list property: plyfile gives an object column of arrays
            raise InputError(path, f"property {k} is a {'list' if vertex.data.dtype[k].kind == 'O' else vertex.data.dtype[k]}; "
                                   "a point's coordinates are numbers", field=k)
    extra_lines, extra_bytes = trailing_ascii_lines(path, header), trailing_bytes(header, path.stat().st_size)
    if extra_lines or extra_bytes:  # a header whose count is smaller than the data: the points after it would go unscored
        log.warning("%s: %s follow the %s points the header declares; they are ignored (is the header's vertex count wrong?)", path,
                    f"{extra_lines:,} more data lines" if extra_lines else f"{extra_bytes:,} bytes", f"{len(vertex.data):,}")
    pts = np.stack([np.asarray(vertex[k], np.float64) for k in "xyz"], axis=1)
    column = np.asarray(vertex[label_field])
    if column.dtype.kind == "f":  # astype(int64) would turn 1.5 into class 1 and NaN into garbage, without a word
        with np.errstate(invalid="ignore"):
            bad = np.flatnonzero(~np.isfinite(column) | (column != np.round(column)))
        if bad.size:
            raise InputError(path, f"the {column.dtype} label property holds {bad.size} values that are not whole numbers (vertex "
                                   f"{bad[0]}: {float(column[bad[0]])!r}); labels are integer class ids", field=label_field)
    elif column.dtype.kind not in "iu":
        raise InputError(path, f"the label property has type {column.dtype}; labels are integer class ids", field=label_field)
    return pts, column.astype(np.int64)


def _where_in_ply(exc) -> str:
    """'element 'vertex' row 12: ' of a plyfile parse error, as far as it says."""
    parts = ([f"element {exc.element.name!r}"] if exc.element is not None else []) + ([f"row {exc.row}"] if exc.row is not None else [])
    return " ".join(parts) + ": " if parts else ""


def labels_sidecar(path: str | Path) -> Path:
    """Where the raw labels of a point cloud without a label property live: `<file>.labels.npy`."""
    path = Path(path)
    return path.with_name(path.name + ".labels.npy")


def _read_open3d_cloud(path: Path) -> tuple[np.ndarray, np.ndarray, str]:
    """([P, 3] float64 points, [P] int64 raw labels from the sidecar, the sidecar's name) via open3d."""
    try:
        import open3d as o3d
    except ImportError as exc:  # most often the system library open3d links against
        raise DrsplatError(f"reading {path.suffix} point clouds needs open3d, which failed to import ({exc}); "
                           "on Debian/Ubuntu run `apt install libusb-1.0-0 libgl1`, or convert the cloud to a labelled PLY") from None

    regular_file(path)
    cloud = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(cloud.points, np.float64)
    if pts.size == 0:
        raise InputError(path, "open3d read no points from this file (empty, or not a point cloud of its suffix's format)")
    sidecar = labels_sidecar(path)
    if sidecar.exists() and not sidecar.is_file():
        raise InputError(sidecar, "is not a file (a folder, FIFO or device); a cloud's raw labels are an .npy array beside it")
    if not sidecar.is_file():
        raise InputError(sidecar, f"missing: a {path.suffix} cloud has no label property, so its raw labels must be in this file ([P] integers)")

    raw = load_npy(sidecar, "label array")
    if raw.ndim != 1 or raw.shape[0] != len(pts) or not np.issubdtype(raw.dtype, np.integer):
        skipped = (f"; open3d skips the lines of {path.name} it cannot read, so check that file too"
                   if raw.ndim == 1 and raw.shape[0] > len(pts) else "")
        raise InputError(sidecar, f"expected {len(pts)} integer labels (one per point open3d read from {path.name}), got {raw.dtype} "
                                  f"of shape {raw.shape}{skipped}")
    return pts, raw.astype(np.int64), sidecar.name


def write_labelled_points(path: str | Path, points: np.ndarray, raw_labels: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Write a ScanNet-style labelled cloud (x, y, z, red, green, blue, alpha, label ushort)."""
    from plyfile import PlyData, PlyElement

    n = len(points)
    rgb = np.full((n, 3), 128, np.uint8) if colors is None else np.asarray(colors, np.uint8)
    data = np.empty(n, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1"), ("label", "u2")])
    for k, c in enumerate("xyz"):
        data[c] = points[:, k]
    data["red"], data["green"], data["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    data["alpha"] = 255
    data["label"] = raw_labels
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(data, "vertex")], text=False).write(str(tmp))


def find_scannet_labels(scene_dir: str | Path) -> Path:
    """The `*_vh_clean_2.labels.ply` of a ScanNet scene folder (or the file itself).

    A folder must hold exactly one: with two, which is the scene's ground truth is a guess.
    """
    scene_dir = Path(scene_dir)
    if scene_dir.is_file():
        return scene_dir
    if not scene_dir.is_dir():
        raise InputError(scene_dir, "does not exist" if not scene_dir.exists() else "is neither a folder nor a file")
    found = sorted(scene_dir.glob(SCANNET_LABELS_PATTERN))
    if not found:
        raise InputError(scene_dir, f"no {SCANNET_LABELS_PATTERN} in this ScanNet scene folder")
    if len(found) > 1:
        raise InputError(scene_dir, f"holds {len(found)} {SCANNET_LABELS_PATTERN} files ({', '.join(f.name for f in found)}); "
                                    "pass the one to use as --scene-dir")
    return found[0]


def load_label_names(path: Path | None, default: list[str] | None = None) -> list[str]:
    """The label names of a JSON list at `path` (`checked_names`: non-empty strings, no hidden
    characters, none twice), or `default` when no path is given (an error when there is none)."""
    if path is None:
        if default is None:
            raise UsageError("label names are needed: pass --label-names NAMES.json")  # a flag left out: exit 2 (round 100f F2)
        return list(default)
    names = read_json(path, "a JSON list of label names")
    if not isinstance(names, list) or not names:
        raise InputError(path, "expected a non-empty JSON list of label names")
    return checked_names(path, names)


def load_gt_labels(path: Path, n: int, num_labels: int, original: Path | None = None) -> np.ndarray:
    """(n,) int64 labels, -1..num_labels-1; `original`: the --original scene given, whose size the hint names."""
    from drsplat.query import _load_npy  # here: query loads the language-field stack, which evaluating ground truth alone does not need

    arr = _load_npy(path)
    if arr.ndim != 1 or arr.shape[0] != n:
        hint = ""
        if arr.ndim == 1 and arr.shape[0] > n:
            hint = (" (labels of the unregistered scene? pass that scene with --original SCENE.ply)" if original is None else
                    f" (--original {original.name} has {n} Gaussians: are these the labels of another scene?)")
        raise InputError(path, f"expected ({n},) labels, one per Gaussian, got shape {arr.shape}{hint}")
    if not np.issubdtype(arr.dtype, np.integer):
        raise InputError(path, f"expected integer labels, got dtype {arr.dtype}")
    bad = (arr < -1) | (arr >= num_labels)
    if bad.any():
        raise InputError(path, f"{int(bad.sum())} labels fall outside -1..{num_labels - 1} (the label names list has {num_labels})")
    return arr.astype(np.int64)
