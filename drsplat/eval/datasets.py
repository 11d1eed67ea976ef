"""Readers (and stand-in writers) for the ground truth of the evaluation datasets.

LERF-OVS (LangSplat's release of LERF scenes with annotations; OpenGaussian uses it too)::

    lerf_ovs/<scene>/images/frame_00001.jpg ...     the training images (+ sparse/0 COLMAP model)
    lerf_ovs/label/<scene>/frame_00041.json          LabelMe-style annotation of one view
    lerf_ovs/label/<scene>/frame_00041.jpg           the annotated image

    frame_XXXXX.json = {"info": {"name": "frame_00041.jpg", "width": W, "height": H},
                        "objects": [{"category": "old camera", "bbox": [x1, y1, x2, y2],
                                     "segmentation": [[x, y], [x, y], ...]}, ...]}

  An object may appear as several polygons (several entries with one category); they are
  united. A view pairs with the training camera whose image stem equals the JSON stem.

ScanNet (v2)::

    scans/<scene>/<scene>_vh_clean_2.labels.ply      mesh vertices x, y, z, ..., label (NYU40 id, 0 = none)
    scans/<scene>/pose/<i>.txt                      4 x 4 camera-to-world (OpenCV axes), from the .sens export
    scans/<scene>/intrinsic/intrinsic_color.txt     4 x 4 intrinsics of the colour images
    scans/<scene>/color/<i>.jpg                     colour images
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drsplat.cameras import load_scannet_cameras  # noqa: F401  (the ScanNet camera reader lives with the others)
from drsplat.errors import DrsplatError, InputError
from drsplat.scene import check_element_sizes, read_ply_header
from drsplat.utils import atomic_path, load_npy, read_json

log = logging.getLogger(__name__)

NYU40_NAMES = (
    "wall", "floor", "cabinet", "bed", "chair", "sofa", "table", "door", "window", "bookshelf",
    "picture", "counter", "blinds", "desk", "shelves", "curtain", "dresser", "pillow", "mirror", "floor mat",
    "clothes", "ceiling", "books", "refrigerator", "television", "paper", "towel", "shower curtain", "box", "whiteboard",
    "person", "night stand", "toilet", "sink", "lamp", "bathtub", "bag", "otherstructure", "otherfurniture", "otherprop",
)


# ---------------------------------------------------------------------------------------------- LERF-OVS


@dataclass
class AnnotatedView:
    """One annotated view: name (image stem), size, and a boolean mask [H, W] per category."""

    name: str
    width: int
    height: int
    masks: dict[str, np.ndarray]
    image_path: Path | None = None


def polygon_mask(points: np.ndarray, height: int, width: int) -> np.ndarray:
    """[H, W] bool: pixels inside the polygon ([P, 2] (x, y) pixel coordinates), as a fill rule would paint."""
    from PIL import Image, ImageDraw

    img = Image.new("L", (width, height), 0)
    pts = [(float(x), float(y)) for x, y in np.asarray(points, np.float64).reshape(-1, 2)]
    if len(pts) >= 3:
        ImageDraw.Draw(img).polygon(pts, fill=1, outline=1)
    return np.asarray(img, dtype=bool)


def load_lerf_view(path: str | Path) -> AnnotatedView:
    """Read one LERF-OVS `frame_XXXXX.json` (LabelMe-style polygons) into masks per category."""
    path = Path(path)
    data = read_json(path, "a LERF-OVS annotation")
    info = data.get("info") if isinstance(data, dict) else None
    if not isinstance(info, dict):
        raise InputError(path, "missing the 'info' object with width and height", field="info")
    try:
        width, height = int(info["width"]), int(info["height"])
    except (KeyError, TypeError, ValueError):
        raise InputError(path, "info.width / info.height missing or not integers", field="info") from None
    objects = data.get("objects")
    if not isinstance(objects, list):
        raise InputError(path, "missing the 'objects' list", field="objects")
    masks: dict[str, np.ndarray] = {}
    for k, obj in enumerate(objects):
        try:
            category = str(obj["category"])
            poly = np.asarray(obj["segmentation"], np.float64).reshape(-1, 2)
        except (KeyError, TypeError, ValueError):
            raise InputError(path, "object without a category or with a malformed polygon", field=f"objects[{k}]") from None
        if not np.isfinite(poly).all():
            raise InputError(path, "polygon has non-finite coordinates", field=f"objects[{k}].segmentation")
        m = polygon_mask(poly, height, width)
        masks[category] = masks[category] | m if category in masks else m
    stem = Path(str(info.get("name", path.stem))).stem or path.stem
    image = path.with_suffix(".jpg")
    return AnnotatedView(stem, width, height, masks, image if image.exists() else None)


def load_lerf_annotations(label_dir: str | Path) -> list[AnnotatedView]:
    """All annotated views of one LERF-OVS scene (`label/<scene>/frame_*.json`), sorted by name."""
    label_dir = Path(label_dir)
    if not label_dir.is_dir():
        raise InputError(label_dir, "annotation folder not found (expected lerf_ovs/label/<scene>/ with frame_*.json)")
    files = sorted(label_dir.glob("*.json"))
    if not files:
        raise InputError(label_dir, "no *.json annotations in this folder (expected frame_XXXXX.json, LabelMe-style)")
    return [load_lerf_view(f) for f in files]


def mask_to_polygons(mask: np.ndarray, tolerance: float = 0.5, min_pixels: int = 4) -> list[np.ndarray]:
    """Outer boundaries of a boolean mask as polygons [P, 2] (x, y), one per connected component."""
    from skimage import measure

    labelled = measure.label(mask, connectivity=1)
    polys = []
    for region in measure.regionprops(labelled):
        if region.area < min_pixels:
            continue
        comp = np.pad(labelled == region.label, 1)
        contours = measure.find_contours(comp.astype(np.float32), 0.5)
        if not contours:
            continue
        outer = max(contours, key=len)
        outer = measure.approximate_polygon(outer, tolerance) - 1.0  # undo the padding
        # contour coordinates run through pixel centres; +0.5 moves them to PIL's pixel-corner grid
        polys.append(np.stack([outer[:, 1] + 0.5, outer[:, 0] + 0.5], axis=1))
    return polys


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


POINT_CLOUD_SUFFIXES = (".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")  # read through open3d


def load_labelled_points(path: str | Path, raw_names: tuple[str, ...] | list[str] = NYU40_NAMES,
                         classes: list[str] | None = None, label_field: str = "label") -> LabelledPoints:
    """Read a labelled point cloud: ScanNet's `<scene>_vh_clean_2.labels.ply`, or any point cloud open3d reads
    (.pcd, .xyz, .xyzn, .xyzrgb, .pts) with its raw labels beside it in `<file>.labels.npy` ([P] integers).

    The raw label r (PLY vertex property `label_field`, or the sidecar's entries) names raw_names[r − 1];
    r = 0 is unannotated. With `classes`, only those names are kept (in that order) and every other point
    becomes −1, e.g. the subsets of NYU40 classes used in published ScanNet tables.
    """
    path = Path(path)
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
    from plyfile import PlyData, PlyHeaderParseError

    check_element_sizes(path, read_ply_header(path), path.stat().st_size)  # no allocation from a lying header
    try:
        ply = PlyData.read(str(path))
        vertex = ply["vertex"]
    except (OSError, KeyError, PlyHeaderParseError, ValueError) as exc:
        raise InputError(path, f"not a readable PLY point cloud with a vertex element ({exc})") from None
    names = vertex.data.dtype.names
    for f in ("x", "y", "z", label_field):
        if f not in names:
            raise InputError(path, "vertex property missing (a labelled cloud needs x, y, z and a label)", field=f)
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
                           "on Debian/Ubuntu run `apt install libusb-1.0-0`, or convert the cloud to a labelled PLY") from None

    if not path.is_file():
        raise InputError(path, "point cloud file does not exist")
    cloud = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(cloud.points, np.float64)
    if pts.size == 0:
        raise InputError(path, "open3d read no points from this file (empty, or not a point cloud of its suffix's format)")
    sidecar = labels_sidecar(path)
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
    """The `*_vh_clean_2.labels.ply` of a ScanNet scene folder (or the file itself)."""
    scene_dir = Path(scene_dir)
    if scene_dir.is_file():
        return scene_dir
    found = sorted(scene_dir.glob("*_vh_clean_2.labels.ply"))
    if not found:
        raise InputError(scene_dir, "no *_vh_clean_2.labels.ply in this ScanNet scene folder")
    return found[0]
