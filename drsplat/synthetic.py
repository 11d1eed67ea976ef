"""Synthetic scenes with exact ground truth, and oracle LangSplat features (`drsplat synth`).

A scene is a room of labelled objects (boxes, spheres, cylinders, thin plates, and panels
textured with photos shipped in scikit-image) whose surfaces are covered by flat Gaussians, as a
trained 3DGS scene would be. It also contains the cases that make registration hard:
low-opacity floaters, a few huge background Gaussians, a small object hidden behind a larger one
and thin objects. Cameras orbit the scene and some stand inside it.

Ground truth per view comes from one of two sources (`OracleParams.mask_source`, a preset's
`mask_source`; a third, "segmenter", takes the masks themselves from a segmenter, below):

    render    the same rasterizer the registration uses: a pixel belongs to the object instance
              with the largest summed contribution w = T·α among the pixel's top-k Gaussians (the
              unlabelled floaters and background Gaussians vote for "none"); more stable at
              silhouettes than the single top-1 Gaussian. Mask boundaries follow the Gaussians'
              blurry footprints, so they agree with the registration's own weights.
    geometry  analytic ray casting of the objects' true surfaces (`ray_cast_instances`): the ray
              through the pixel centre hits the nearest box, sphere, closed cylinder or panel.
              Mask boundaries are the true silhouettes, as a SAM mask of a real photo follows the
              image's edges, and a Gaussian straddling a silhouette spreads part of its footprint
              over the neighbour's mask (the `hard-silhouette` preset).
    segmenter geometry's instances as ground truth, but the masks are not the instances: a
              segmenter's regions of the rendered view (Felzenszwalb superpixels at LangSplat's four
              levels, drsplat.features.masks.superpixel), each embedded as the oracle embeds the
              instance covering most of it (`segmenter_masks_and_embeddings`). Its errors are a
              real segmenter's, not a corruption model's: regions follow colour edges, so textured
              walls come in many pieces, a small object is often part of the region around it
              and a region straddling two objects carries one label. What the oracle's
              corruptions model one at a time (jitter, merges, splits) it makes together.

Oracle features stand in for SAM + CLIP: one mask per visible object instance, and for the
mask of label l the embedding normalize(a·c + b·v_l + noise), where v_l is the label's fixed
unit vector and c is a component common to every image embedding (CLIP image embeddings are
all alike to some degree). The label's "text" vector is normalize(a_t·c_t + b_t·v_l) with a
different common component c_t ⟂ c: text and image vectors differ (the modality gap), yet the
text vector of l is closest to the image embeddings of l.

Corruptions of the oracle (`OracleParams`): boundary jitter, mislabelled masks (another label's
embedding), under-segmentation (`merge_fraction`: an instance's mask swallowed by the
neighbour it touches most, the union carrying the neighbour's label, as a segmenter that takes a
cup and the table under it for one region does) and over-segmentation (`split_fraction`: an
instance's mask cut in two across its long axis, each half embedded as a part of its object,
normalize(a·c + b·(PART_SHARE·v_l + √(1 − PART_SHARE²)·p) + noise) with p a random unit direction
of its own, as a segmenter that returns a chair's back and its seat, whose crops CLIP sees as
parts, does). Each draws from its own random stream, so a
corrupted room has the masks, jitter and noise of the same room without that corruption wherever
the corruption does not reach.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drsplat.cameras import Camera, load_cameras, look_at_camera, write_transforms_json
from drsplat.defaults import ORACLE_LABEL_NAMES, ORACLE_TEXT_EMBEDDINGS
from drsplat.features.masks.base import LEVELS
from drsplat.features.masks.superpixel import FelzenszwalbGenerator
from drsplat.features.modelid import ORACLE_MODEL_ID, manifest_clip_entry
from drsplat.scene import SH_C0, GaussianScene, load_ply, save_ply
from drsplat.features.format import write_features, write_manifest
from drsplat.raster import NEAR, rasterize
from drsplat.utils import atomic_path, progress, save_npy_atomic

log = logging.getLogger(__name__)

LIGHT = np.array([0.4, -0.3, 0.866]) / np.linalg.norm([0.4, -0.3, 0.866])


@dataclass
class ObjectSpec:
    """One labelled object: `kind` in box, sphere, cylinder, plate, panel; geometry in `params`."""

    name: str
    kind: str
    params: dict
    color: tuple[float, float, float] = (0.6, 0.6, 0.6)
    texture: str | None = None


@dataclass
class RoomParams:
    """Knobs of the hard "room" layout (`_build_room`); geometry is drawn from the seed.

    Counts are per scene. half_size: range of the room's half-extent (m). thin_radius: range of
    pole/cable/stem radii. faint_fraction: share of object Gaussians made semi-transparent
    (opacity 0.1-0.6, as trained 3DGS scenes have many). floater_fraction: unlabelled small faint
    Gaussians as a share of all. num_blobs: huge faint unlabelled Gaussians inside the room.
    grazing_views / far_views / low_views: cameras looking along a wall, from the far side of the
    room at a small object, and from near the floor.
    """

    half_size: tuple[float, float] = (1.8, 2.4)
    num_poles: int = 2
    num_cables: int = 2
    num_stems: int = 2
    num_small: int = 4
    num_wall_items: int = 2
    num_boxes: int = 2
    thin_radius: tuple[float, float] = (0.006, 0.02)
    faint_fraction: float = 0.08
    floater_fraction: float = 0.01
    num_blobs: int = 4
    grazing_views: int = 3
    far_views: int = 3
    low_views: int = 2


@dataclass
class Preset:
    """Size of a synthetic dataset."""

    name: str
    objects: tuple[str, ...]
    num_gaussians: int
    num_orbit_views: int
    num_inside_views: int
    width: int
    height: int
    dim: int = 512
    num_floaters: int = 30
    num_background: int = 6
    sh_degree: int = 3
    layout: str = "table"  # key of LAYOUTS: how the Gaussians and cameras are made
    room: RoomParams | None = None  # the "room" layout's knobs
    jitter: int = 0  # default oracle mask boundary jitter (pixels) of this preset
    mislabel: float = 0.0  # default oracle mislabelled-mask fraction of this preset
    mask_source: str = "render"  # where the oracle's instance maps come from (MASK_SOURCES)


@dataclass
class OracleParams:
    """Oracle embedding model: image embedding normalize(a·c + b·v_l + noise·n/√D).

    mask_source: "render" (weighted vote of the rendered Gaussians), "geometry" (ray-cast true
    silhouettes) or "segmenter" (superpixels of the rendered view over geometry's instances); see
    the module docstring.
    """

    a: float = 1.0
    b: float = 0.8
    noise: float = 0.15
    text_a: float = 0.8
    text_b: float = 0.6
    mislabel_fraction: float = 0.0
    jitter: int = 0
    merge_fraction: float = 0.0  # under-segmentation: share of instance masks swallowed by a neighbour's (`merged_instances`)
    split_fraction: float = 0.0  # over-segmentation: share of instance masks cut in two parts (`split_instances`)
    min_mask_pixels: int = 4
    mask_source: str = "render"


@dataclass
class SyntheticScene:
    """A synthetic scene with exact ground truth.

    scene: the Gaussians ([N] of them). cameras: the views.
    labels: [N] int32 label per Gaussian, -1 for floaters and background Gaussians.
    instances: [N] int32 object instance per Gaussian, -1 none; instance_labels: [I] its label.
    label_names: [L] names, index = label id.
    label_vectors: [L, D] unit vectors v_l. common_vector: [D] image component c.
    text_vectors: [L, D] oracle text embeddings (with a modality gap).
    instance_specs: [I] the geometry of each object instance (what "geometry" masks ray-cast).
    """

    preset: str
    seed: int
    scene: GaussianScene
    cameras: list[Camera]
    labels: np.ndarray
    instances: np.ndarray
    instance_labels: np.ndarray
    label_names: list[str]
    label_vectors: np.ndarray
    common_vector: np.ndarray
    text_common_vector: np.ndarray
    text_vectors: np.ndarray
    oracle: OracleParams = field(default_factory=OracleParams)
    instance_specs: list[ObjectSpec] = field(default_factory=list)

    def image_prototypes(self) -> np.ndarray:
        """[L, D] noise-free image embeddings normalize(a·c + b·v_l)."""
        return _normalize(self.oracle.a * self.common_vector + self.oracle.b * self.label_vectors)

    def localisation_threshold(self) -> float:
        """One global cosine threshold for text queries, from the oracle model alone.

        Midway between the score of a noise-free image embedding of the queried label and of
        any other label (every label is alike to the others, so one number serves all).
        """
        scores = self.text_vectors @ self.image_prototypes().T
        own = float(np.mean(np.diag(scores)))
        other = float(np.mean(scores[~np.eye(len(scores), dtype=bool)])) if len(scores) > 1 else 0.0
        return 0.5 * (own + other)


# ----------------------------------------------------------------------------- scene content

OBJECTS: dict[str, ObjectSpec] = {
    spec.name: spec
    for spec in (
        ObjectSpec("floor", "plate", {"center": (0, 0, -0.01), "size": (7.0, 7.0, 0.02), "top_only": True}, (0.55, 0.5, 0.45)),
        ObjectSpec("table", "box", {"center": (0, 0, 0.275), "size": (1.2, 0.8, 0.55)}, (0.55, 0.33, 0.18)),
        ObjectSpec("ball", "sphere", {"center": (-0.3, 0.1, 0.73), "radius": 0.18}, (0.85, 0.15, 0.12)),
        ObjectSpec("mug", "cylinder", {"center": (0.3, -0.15, 0.66), "radius": 0.09, "height": 0.22, "axis": 2}, (0.2, 0.45, 0.85)),
        ObjectSpec("book", "plate", {"center": (0.25, 0.22, 0.565), "size": (0.32, 0.24, 0.03)}, (0.15, 0.6, 0.25)),
        ObjectSpec("pencil", "cylinder", {"center": (-0.2, -0.28, 0.562), "radius": 0.015, "height": 0.36, "axis": 0}, (0.95, 0.8, 0.1)),
        ObjectSpec("crate", "box", {"center": (1.0, 0.9, 0.225), "size": (0.45, 0.45, 0.45)}, (0.75, 0.6, 0.35)),
        ObjectSpec("marble", "sphere", {"center": (0.74, 0.5, 0.07), "radius": 0.07}, (0.6, 0.2, 0.8)),
        ObjectSpec("pole", "cylinder", {"center": (-1.3, -1.2, 0.8), "radius": 0.03, "height": 1.6, "axis": 2}, (0.8, 0.8, 0.85)),
        ObjectSpec("astronaut", "panel", {"center": (-3.0, 0.0, 1.0), "size": (1.4, 1.4), "facing": (1, 0, 0)}, texture="astronaut"),
        ObjectSpec("cat", "panel", {"center": (0.0, 3.0, 0.95), "size": (1.6, 1.07), "facing": (0, -1, 0)}, texture="chelsea"),
        ObjectSpec("coffee", "panel", {"center": (3.0, -0.4, 0.9), "size": (1.5, 1.0), "facing": (-1, 0, 0)}, texture="coffee"),
        ObjectSpec("rocket", "panel", {"center": (0.3, -3.0, 1.0), "size": (1.5, 1.0), "facing": (0, 1, 0)}, texture="rocket"),
    )
}

_TINY = ("floor", "table", "ball", "mug", "pencil", "crate", "marble", "astronaut")
PRESETS: dict[str, Preset] = {
    "tiny": Preset("tiny", _TINY, 3000, 14, 2, 128, 96, num_floaters=20, num_background=4),
    "small": Preset("small", tuple(OBJECTS), 20000, 12, 4, 160, 120, num_floaters=60),
    "demo": Preset("demo", tuple(OBJECTS), 80000, 24, 6, 320, 240, num_floaters=150, num_background=8),
}


MASK_SOURCES = ("render", "geometry", "segmenter")
# the wrong labels of mislabelled oracle masks come from their own random stream, [seed, 3], so that
# a mislabelled room has the masks, jitter and noise of the same room without mislabels (since
# 2026-11-28; before, they came from the masks' stream and every later draw moved). Written to a
# mislabelled dataset's manifest, which is how a cached dataset made before is told apart.
WRONG_LABEL_STREAM = 3
WRONG_LABELS = f"own stream [seed, {WRONG_LABEL_STREAM}]"
MERGE_STREAM = 4  # which instance masks are merged into a neighbour's (`merged_instances`), [seed, 4]
SPLIT_STREAM = 5  # which instance masks are cut in two, and the parts' directions and noise (`split_instances`), [seed, 5]
PART_SHARE = 0.7  # cosine between a part's label direction and its object's (module docstring)


def _room_preset(name: str, num_gaussians: int, views: int, width: int, height: int, *, jitter: int = 0, mislabel: float = 0.0,
                 mask_source: str = "render", **room) -> Preset:
    return Preset(name, (), num_gaussians, views, 0, width, height, num_floaters=0, num_background=0, layout="room",
                  room=RoomParams(**room), jitter=jitter, mislabel=mislabel, mask_source=mask_source)


# Hard rooms (docs/evaluation.md, "Aggregation"): each stresses one thing registration gets wrong;
# all have ~1% unlabelled floaters, huge faint blobs and 8% semi-transparent object Gaussians.
HARD_PRESETS: dict[str, Preset] = {
    p.name: p
    for p in (
        _room_preset("hard-thin", 12000, 12, 160, 120, num_poles=4, num_cables=3, num_stems=3, num_small=2),
        _room_preset("hard-small", 12000, 10, 160, 120, num_small=10, far_views=5, num_poles=1, num_cables=1, num_stems=1),
        _room_preset("hard-grazing", 12000, 6, 160, 120, grazing_views=7, low_views=4, far_views=1),
        _room_preset("hard-lowres", 12000, 12, 80, 60),
        _room_preset("hard-noisy", 12000, 12, 160, 120, jitter=2, mislabel=0.1, floater_fraction=0.03, num_blobs=8, faint_fraction=0.15),
        _room_preset("hard-room", 30000, 14, 320, 240, num_poles=3, num_cables=2, num_stems=2, num_small=6, num_wall_items=3, jitter=1),
        _room_preset("hard-tiny", 4000, 8, 96, 72, num_poles=2, num_cables=1, num_stems=1, num_small=3, grazing_views=2, far_views=2, low_views=1),
        # true-silhouette masks (ray cast), thin and small things against the walls, Gaussians about
        # as wide as the thin objects: the silhouette case of issue 14 (docs/registration.md)
        _room_preset("hard-silhouette", 20000, 12, 320, 240, mask_source="geometry", num_poles=4, num_cables=3, num_stems=3, num_small=8,
                     num_wall_items=3, far_views=4),
    )
}
PRESETS.update(HARD_PRESETS)


def _normalize(x: np.ndarray, axis: int = -1) -> np.ndarray:
    norm = np.linalg.norm(x, axis=axis, keepdims=True)
    return x / np.where(norm > 0, norm, 1.0)


def rotmat_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) of rotation matrices. r: [N, 3, 3] -> [N, 4]."""
    m = r.astype(np.float64)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    q = np.empty((len(m), 4))
    cand = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    case = np.argmax(cand, axis=1)
    for c in range(4):
        s = case == c
        if not s.any():
            continue
        a = m[s]
        if c == 0:
            t = np.sqrt(1 + tr[s]) * 2
            q[s] = np.stack([0.25 * t, (a[:, 2, 1] - a[:, 1, 2]) / t, (a[:, 0, 2] - a[:, 2, 0]) / t, (a[:, 1, 0] - a[:, 0, 1]) / t], 1)
        elif c == 1:
            t = np.sqrt(1 + a[:, 0, 0] - a[:, 1, 1] - a[:, 2, 2]) * 2
            q[s] = np.stack([(a[:, 2, 1] - a[:, 1, 2]) / t, 0.25 * t, (a[:, 0, 1] + a[:, 1, 0]) / t, (a[:, 0, 2] + a[:, 2, 0]) / t], 1)
        elif c == 2:
            t = np.sqrt(1 + a[:, 1, 1] - a[:, 0, 0] - a[:, 2, 2]) * 2
            q[s] = np.stack([(a[:, 0, 2] - a[:, 2, 0]) / t, (a[:, 0, 1] + a[:, 1, 0]) / t, 0.25 * t, (a[:, 1, 2] + a[:, 2, 1]) / t], 1)
        else:
            t = np.sqrt(1 + a[:, 2, 2] - a[:, 0, 0] - a[:, 1, 1]) * 2
            q[s] = np.stack([(a[:, 1, 0] - a[:, 0, 1]) / t, (a[:, 0, 2] + a[:, 2, 0]) / t, (a[:, 1, 2] + a[:, 2, 1]) / t, 0.25 * t], 1)
    return _normalize(q).astype(np.float32)


def _frame_from_normals(normals: np.ndarray) -> np.ndarray:
    """[P, 3, 3] rotations whose third column is the unit normal (first two span the tangent plane)."""
    n = _normalize(normals)
    helper = np.where(np.abs(n[:, 2:3]) < 0.9, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    t1 = _normalize(np.cross(helper, n))
    t2 = np.cross(n, t1)
    return np.stack([t1, t2, n], axis=2)


def _grid_on_rect(count: int, w: float, h: float, rng: np.random.Generator) -> np.ndarray:
    """~count jittered-grid points in [0, w] x [0, h] (even coverage without holes). -> [P, 2]."""
    count = max(count, 1)
    nx = max(1, int(round(np.sqrt(count * w / max(h, 1e-9)))))
    ny = max(1, int(round(count / nx)))
    gx, gy = np.meshgrid((np.arange(nx) + 0.5) / nx, (np.arange(ny) + 0.5) / ny, indexing="xy")
    uv = np.stack([gx.ravel(), gy.ravel()], 1)
    uv += rng.uniform(-0.35, 0.35, uv.shape) / np.array([nx, ny])
    return np.clip(uv, 0, 1) * np.array([w, h])


def _box_faces(center, size, top_only: bool = False, faces_kept=None):
    """(origin, u_axis, v_axis, normal) per face; u, v are edge vectors of the face.

    top_only keeps the +z face; faces_kept, a list of (axis, sign), keeps those faces only.
    """
    c, s = np.asarray(center, float), np.asarray(size, float) / 2
    faces = []
    for axis in ((2,) if top_only else (0, 1, 2)):
        a1, a2 = [i for i in range(3) if i != axis]
        for sign in (1.0, -1.0):
            if top_only and sign < 0:
                continue
            if faces_kept is not None and (axis, sign) not in [tuple(f) for f in faces_kept]:
                continue
            normal = np.zeros(3)
            normal[axis] = sign
            u, v = np.zeros(3), np.zeros(3)
            u[a1], v[a2] = 2 * s[a1], 2 * s[a2]
            origin = c + normal * s[axis] - u / 2 - v / 2
            faces.append((origin, u, v, normal))
    return faces


def object_area(spec: ObjectSpec) -> float:
    p = spec.params
    if spec.kind in ("box", "plate"):
        return float(sum(np.linalg.norm(u) * np.linalg.norm(v) for _, u, v, _ in _box_faces(p["center"], p["size"], p.get("top_only", False), p.get("faces"))))
    if spec.kind == "sphere":
        return float(4 * np.pi * p["radius"] ** 2)
    if spec.kind == "cylinder":
        return float(2 * np.pi * p["radius"] * p["height"] + 2 * np.pi * p["radius"] ** 2)
    if spec.kind == "panel":
        return float(p["size"][0] * p["size"][1])
    raise ValueError(f"unknown object kind {spec.kind}")


def sample_surface(spec: ObjectSpec, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Evenly spread surface points of an object.

    Returns points: [P, 3], normals: [P, 3] and, for panels, uv: [P, 2] in [0, 1] (else None).
    """
    p = spec.params
    if spec.kind in ("box", "plate"):
        faces = _box_faces(p["center"], p["size"], p.get("top_only", False), p.get("faces"))
        areas = np.array([np.linalg.norm(u) * np.linalg.norm(v) for _, u, v, _ in faces])
        pts, nrm = [], []
        for (origin, u, v, normal), area in zip(faces, areas):
            lu, lv = np.linalg.norm(u), np.linalg.norm(v)
            st = _grid_on_rect(int(round(count * area / areas.sum())), lu, lv, rng)
            pts.append(origin + st[:, :1] * (u / lu) + st[:, 1:] * (v / lv))
            nrm.append(np.broadcast_to(normal, (len(st), 3)))
        return np.concatenate(pts), np.concatenate(nrm), None
    if spec.kind == "sphere":
        i = np.arange(count) + 0.5
        phi = np.arccos(1 - 2 * i / count)
        theta = np.pi * (1 + 5**0.5) * i + rng.uniform(0, 2 * np.pi)
        n = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)
        return np.asarray(p["center"]) + p["radius"] * n, n, None
    if spec.kind == "cylinder":
        r, h, axis = p["radius"], p["height"], p["axis"]
        side, cap = 2 * np.pi * r * h, np.pi * r * r
        n_side = int(round(count * side / (side + 2 * cap)))
        st = _grid_on_rect(n_side, 2 * np.pi * r, h, rng)
        ang = st[:, 0] / r
        local_pts = [np.stack([r * np.cos(ang), r * np.sin(ang), st[:, 1] - h / 2], 1)]
        local_nrm = [np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1)]
        n_cap = max(1, (count - n_side) // 2)
        for sign in (1.0, -1.0):
            rad = r * np.sqrt((np.arange(n_cap) + 0.5) / n_cap)
            a = np.pi * (1 + 5**0.5) * np.arange(n_cap)
            local_pts.append(np.stack([rad * np.cos(a), rad * np.sin(a), np.full(n_cap, sign * h / 2)], 1))
            local_nrm.append(np.broadcast_to([0.0, 0.0, sign], (n_cap, 3)))
        lp, ln = np.concatenate(local_pts), np.concatenate(local_nrm)
        perm = {2: [0, 1, 2], 0: [2, 0, 1], 1: [1, 2, 0]}[axis]
        return np.asarray(p["center"]) + lp[:, perm], ln[:, perm], None
    if spec.kind == "panel":
        w, h = p["size"]
        facing = _normalize(np.asarray(p["facing"], float))
        right = _normalize(np.cross(np.array([0.0, 0.0, 1.0]), facing))  # image x axis seen from the front
        up = np.cross(facing, right)
        st = _grid_on_rect(count, w, h, rng)
        pts = np.asarray(p["center"]) + (st[:, :1] - w / 2) * right + (st[:, 1:] - h / 2) * up
        uv = np.stack([st[:, 0] / w, 1 - st[:, 1] / h], 1)
        return pts, np.broadcast_to(facing, (len(st), 3)).copy(), uv
    raise ValueError(f"unknown object kind {spec.kind}")


def inside_object(spec: ObjectSpec, points: np.ndarray, margin: float) -> np.ndarray:
    """[P] bool: points inside the solid of `spec` grown by `margin` (panels have no inside)."""
    p = spec.params
    c = np.asarray(p.get("center", (0, 0, 0)), float)
    if spec.kind in ("box", "plate"):
        return np.all(np.abs(points - c) <= np.asarray(p["size"]) / 2 + margin, axis=1)
    if spec.kind == "sphere":
        return np.linalg.norm(points - c, axis=1) <= p["radius"] + margin
    if spec.kind == "cylinder":
        d = points - c
        axis = p["axis"]
        radial = np.linalg.norm(np.delete(d, axis, axis=1), axis=1)
        return (radial <= p["radius"] + margin) & (np.abs(d[:, axis]) <= p["height"] / 2 + margin)
    return np.zeros(len(points), bool)


def _texture(name: str) -> np.ndarray:
    import skimage.data

    img = getattr(skimage.data, name)()
    if img.ndim == 2:
        img = np.stack([img] * 3, -1)
    return img[..., :3].astype(np.float32) / 255.0


def _sample_texture(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w = img.shape[:2]
    x = np.clip((uv[:, 0] * w).astype(int), 0, w - 1)
    y = np.clip((uv[:, 1] * h).astype(int), 0, h - 1)
    return img[y, x]


def _rgb_to_sh(rgb: np.ndarray, degree: int, rng: np.random.Generator, view_dependence: float) -> np.ndarray:
    """[P, K, 3] SH coefficients whose DC term gives `rgb`, with a little view dependence."""
    k = (degree + 1) ** 2
    sh = np.zeros((len(rgb), k, 3), np.float32)
    sh[:, 0] = (rgb - 0.5) / SH_C0
    if k > 1:
        sh[:, 1:] = rng.normal(0, view_dependence, (len(rgb), k - 1, 3))
    return sh


def _build_gaussians(preset: Preset, rng: np.random.Generator):
    """All Gaussians of the preset: (scene, labels [N], instances [N], instance labels, names)."""
    specs = [OBJECTS[name] for name in preset.objects]
    areas = np.array([object_area(s) for s in specs])
    budget = preset.num_gaussians - preset.num_floaters - preset.num_background
    # ∝ √area: small and thin objects get finer Gaussians (3DGS densifies detail the same way)
    share = np.sqrt(areas) / np.sqrt(areas).sum()
    counts = np.maximum(60, np.round(budget * share)).astype(int)
    means, quats, scales, colors, labels = [], [], [], [], []
    for label, (spec, count) in enumerate(zip(specs, counts)):
        pts, nrm, uv = sample_surface(spec, int(count), rng)
        spacing = np.sqrt(object_area(spec) / len(pts))
        # surfaces inside or facing another object closely (a box's bottom on the floor, the
        # table top under the mug) are never seen; a trained 3DGS scene has no Gaussians there
        hidden = np.zeros(len(pts), bool)
        for other in specs:
            if other is not spec:
                hidden |= inside_object(other, pts, margin=0.01) | inside_object(other, pts + 0.04 * nrm, margin=0.01)
        pts, nrm = pts[~hidden], nrm[~hidden]
        uv = None if uv is None else uv[~hidden]
        tangent = spacing * rng.uniform(0.55, 0.75, (len(pts), 2))
        normal = np.full((len(pts), 1), spacing * 0.05)
        if spec.texture is not None:
            rgb = _sample_texture(_texture(spec.texture), uv)
        else:
            rgb = np.asarray(spec.color) + rng.normal(0, 0.03, (len(pts), 3))
            if spec.name == "floor":  # tiles, so that motion and depth read well in the viewer
                tiles = (np.floor(pts[:, 0] / 0.5) + np.floor(pts[:, 1] / 0.5)) % 2
                rgb = rgb * (0.85 + 0.2 * tiles[:, None])
            rgb = np.clip(rgb * (0.7 + 0.3 * np.clip(nrm @ LIGHT, 0, 1))[:, None], 0, 1)  # baked diffuse light
        means.append(pts)
        quats.append(rotmat_to_quat(_frame_from_normals(nrm)))
        scales.append(np.concatenate([tangent, normal], 1))
        colors.append(rgb)
        labels.append(np.full(len(pts), label, np.int32))
    n_obj = sum(len(m) for m in means)
    opacity = rng.uniform(0.85, 0.98, n_obj)

    # floaters: small, faint, unlabelled, inside the room
    nf = preset.num_floaters
    f_means = np.c_[rng.uniform(-2, 2, (nf, 2)), rng.uniform(0.2, 2.0, nf)]
    f_scales = np.exp(rng.uniform(np.log(0.02), np.log(0.08), (nf, 3)))
    f_opacity = rng.uniform(0.02, 0.15, nf)
    # huge background Gaussians: a far sky / wall of a few enormous splats
    nb = preset.num_background
    ang = 2 * np.pi * (np.arange(nb) + rng.uniform(0, 1)) / max(nb, 1)
    b_means = np.c_[12 * np.cos(ang), 12 * np.sin(ang), rng.uniform(2, 5, nb)]
    b_scales = np.exp(rng.uniform(np.log(3.0), np.log(5.0), (nb, 3)))
    b_opacity = rng.uniform(0.5, 0.8, nb)
    extra_rgb = np.concatenate([rng.uniform(0.3, 0.9, (nf, 3)), np.clip([0.55, 0.7, 0.9] + rng.normal(0, 0.03, (nb, 3)), 0, 1)])
    extra_quats = _normalize(rng.normal(size=(nf + nb, 4))).astype(np.float32)

    all_rgb = np.concatenate(colors + [extra_rgb])
    opac = np.clip(np.concatenate([opacity, f_opacity, b_opacity]), 1e-4, 1 - 1e-4)
    scene = GaussianScene(
        means=np.concatenate(means + [f_means, b_means]).astype(np.float32),
        quats=np.concatenate(quats + [extra_quats]).astype(np.float32),
        log_scales=np.log(np.concatenate(scales + [f_scales, b_scales])).astype(np.float32),
        opacity_logits=np.log(opac / (1 - opac)).astype(np.float32),
        sh=_rgb_to_sh(all_rgb, preset.sh_degree, rng, 0.01),
        comments=[f"drsplat.synthetic preset={preset.name}"],
    )
    obj_labels = np.concatenate(labels)
    labels_all = np.concatenate([obj_labels, np.full(nf + nb, -1, np.int32)])
    return scene, labels_all, labels_all.copy(), np.arange(len(specs), dtype=np.int32), [s.name for s in specs], specs


def look_at(eye, target, width: int, height: int, fov_x_deg: float = 62.0, name: str = "") -> Camera:
    """An OpenCV camera at `eye` looking at `target` with world z up (y up when looking almost straight down)."""
    forward = _normalize(np.asarray(target, float) - np.asarray(eye, float))
    up = (0.0, 0.0, 1.0) if abs(forward[2]) < 0.99 else (0.0, 1.0, 0.0)
    return look_at_camera(eye, target, width, height, fov_x_deg, up=up, name=name)


def make_cameras(preset: Preset, rng: np.random.Generator) -> list[Camera]:
    """Orbiting views of the table plus views from inside the scene looking outwards."""
    cams = []
    w, h = preset.width, preset.height
    for i in range(preset.num_orbit_views):
        ang = 2 * np.pi * (i + 0.5) / preset.num_orbit_views + rng.uniform(-0.1, 0.1)
        radius = rng.uniform(2.1, 2.5)
        eye = (radius * np.cos(ang), radius * np.sin(ang), rng.uniform(1.2, 1.9))
        cams.append(look_at(eye, (0, 0, 0.45), w, h, name=f"orbit_{i:03d}"))
    for i in range(preset.num_inside_views):
        ang = 2 * np.pi * i / max(preset.num_inside_views, 1) + rng.uniform(0, 0.5)
        eye = (0.25 * np.cos(ang), 0.25 * np.sin(ang), rng.uniform(0.9, 1.3))
        target = (3.0 * np.cos(ang), 3.0 * np.sin(ang), rng.uniform(0.3, 0.8))
        cams.append(look_at(eye, target, w, h, fov_x_deg=75.0, name=f"inside_{i:03d}"))
    return cams


# ----------------------------------------------------------------------------- the hard "room" layout

ROOM_HEIGHT = 2.4
WALL_THICKNESS = 0.04


@dataclass
class RoomObject:
    """One object instance of a room: its geometry and its (category) label name."""

    spec: ObjectSpec
    label: str


def _wall_frame(wall: int, hx: float, hy: float):
    """(point on the wall's inner face at floor height, unit direction along it, inward normal, length)
    of wall 0..3 (-x, +x, -y, +y)."""
    if wall < 2:
        sign = -1.0 if wall == 0 else 1.0
        return np.array([sign * hx, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), np.array([-sign, 0.0, 0.0]), 2 * hy
    sign = -1.0 if wall == 2 else 1.0
    return np.array([0.0, sign * hy, 0.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, -sign, 0.0]), 2 * hx


def _room_objects(room: RoomParams, rng: np.random.Generator) -> tuple[list[RoomObject], float, float]:
    """Random objects of a room (walls, floor, thin, small and wall-mounted things), and (hx, hy).

    Objects stand against the walls (a pole or a cabinet a few cm from a wall, a cable along it, a
    frame on it), small things sit on the floor or on a cabinet; footprints do not overlap.
    """
    hx, hy = rng.uniform(*room.half_size, 2)
    objs: list[RoomObject] = [
        RoomObject(ObjectSpec("floor", "plate", {"center": (0, 0, -0.01), "size": (2 * hx, 2 * hy, 0.02), "top_only": True},
                              tuple(rng.uniform(0.4, 0.6, 3))), "floor")
    ]
    wall_rgb = rng.uniform(0.55, 0.8, 3)
    for wall in range(4):
        base, along, inward, length = _wall_frame(wall, hx, hy)
        axis = 0 if wall < 2 else 1
        size = [0.0, 0.0, ROOM_HEIGHT]
        size[axis] = WALL_THICKNESS
        size[1 - axis] = length
        centre = base - inward * WALL_THICKNESS / 2 + np.array([0, 0, ROOM_HEIGHT / 2])
        spec = ObjectSpec(f"wall_{wall}", "plate", {"center": tuple(centre), "size": tuple(size), "faces": [(axis, float(inward[axis]))]},
                          tuple(np.clip(wall_rgb + rng.normal(0, 0.04, 3), 0, 1)))
        objs.append(RoomObject(spec, "wall"))
    taken: list[tuple[np.ndarray, float]] = []  # footprint (centre xy, radius) of each object

    def place(radius: float, gap: tuple[float, float], tries: int = 60):
        """A free spot against a random wall: (wall, base, along, inward, xy) or None."""
        for _ in range(tries):
            wall = int(rng.integers(4))
            base, along, inward, length = _wall_frame(wall, hx, hy)
            t = rng.uniform(-length / 2 + 0.3, length / 2 - 0.3)
            xy = (base + along * t + inward * (rng.uniform(*gap) + radius))[:2]
            if all(np.linalg.norm(xy - c) > radius + r + 0.05 for c, r in taken):
                taken.append((xy, radius))
                return wall, base, along, inward, xy
        return None

    def color():
        return tuple(rng.uniform(0.1, 0.95, 3))

    for i in range(room.num_boxes):
        size = rng.uniform(0.3, 0.6, 3)
        spot = place(0.5 * float(np.hypot(size[0], size[1])), (0.0, 0.02))
        if spot:
            xy = spot[4]
            objs.append(RoomObject(ObjectSpec(f"cabinet_{i}", "box", {"center": (xy[0], xy[1], size[2] / 2), "size": tuple(size)}, color()), "cabinet"))
    for i in range(room.num_poles):
        r, h = rng.uniform(*room.thin_radius), rng.uniform(0.8, 2.0)
        spot = place(r, (0.03, 0.25))
        if spot:
            xy = spot[4]
            objs.append(RoomObject(ObjectSpec(f"pole_{i}", "cylinder", {"center": (xy[0], xy[1], h / 2), "radius": r, "height": h, "axis": 2}, color()), "pole"))
    for i in range(room.num_cables):
        wall = int(rng.integers(4))
        base, along, inward, length = _wall_frame(wall, hx, hy)
        r = rng.uniform(*room.thin_radius) * 0.6
        cable_len = rng.uniform(0.8, min(2.0, length - 0.4))
        t = rng.uniform(-length / 2 + cable_len / 2 + 0.1, length / 2 - cable_len / 2 - 0.1)
        centre = base + along * t + inward * (r + rng.uniform(0.01, 0.08)) + np.array([0, 0, rng.uniform(0.3, 2.0)])
        objs.append(RoomObject(ObjectSpec(f"cable_{i}", "cylinder", {"center": tuple(centre), "radius": r, "height": cable_len,
                                                                     "axis": 1 if wall < 2 else 0}, color()), "cable"))
    for i in range(room.num_stems):
        pot_r, pot_h = rng.uniform(0.07, 0.12), rng.uniform(0.12, 0.25)
        spot = place(pot_r, (0.02, 0.3))
        if spot:
            xy = spot[4]
            stem_r, stem_h = rng.uniform(*room.thin_radius) * 0.5, rng.uniform(0.3, 0.7)
            objs.append(RoomObject(ObjectSpec(f"pot_{i}", "cylinder", {"center": (xy[0], xy[1], pot_h / 2), "radius": pot_r, "height": pot_h, "axis": 2},
                                              color()), "pot"))
            objs.append(RoomObject(ObjectSpec(f"stem_{i}", "cylinder", {"center": (xy[0], xy[1], pot_h + stem_h / 2), "radius": stem_r,
                                                                        "height": stem_h, "axis": 2}, (0.2, 0.6, 0.2)), "stem"))
    for i in range(room.num_wall_items):
        wall = int(rng.integers(4))
        base, along, inward, length = _wall_frame(wall, hx, hy)
        w, h = rng.uniform(0.2, 0.6), rng.uniform(0.15, 0.45)
        centre = base + along * rng.uniform(-length / 2 + 0.4, length / 2 - 0.4) + inward * 0.012 + np.array([0, 0, rng.uniform(0.9, 1.8)])
        axis = 0 if wall < 2 else 1
        size = [0.0, 0.0, h]
        size[axis], size[1 - axis] = 0.02, w
        objs.append(RoomObject(ObjectSpec(f"frame_{i}", "plate", {"center": tuple(centre), "size": tuple(size)}, color()), "frame"))
    cabinets = [o.spec for o in objs if o.label == "cabinet"]
    for i in range(room.num_small):
        kind = "sphere" if rng.random() < 0.5 else "box"
        r = rng.uniform(0.03, 0.07)
        if cabinets and rng.random() < 0.4:  # on a cabinet, else on the floor against a wall
            cab = cabinets[int(rng.integers(len(cabinets)))].params
            half = np.asarray(cab["size"]) / 2
            xy = np.asarray(cab["center"][:2]) + rng.uniform(-1, 1, 2) * np.maximum(half[:2] - r, 0)
            z0 = cab["center"][2] + half[2]
        else:
            spot = place(r, (0.0, 0.4))
            if not spot:
                continue
            xy, z0 = spot[4], 0.0
        if kind == "sphere":
            spec = ObjectSpec(f"ball_{i}", "sphere", {"center": (xy[0], xy[1], z0 + r), "radius": r}, color())
        else:
            spec = ObjectSpec(f"cube_{i}", "box", {"center": (xy[0], xy[1], z0 + r), "size": (2 * r, 2 * r, 2 * r)}, color())
        objs.append(RoomObject(spec, "ball" if kind == "sphere" else "cube"))
    return objs, float(hx), float(hy)


def _thin_cylinder_surface(spec: ObjectSpec, spacing: float, rng: np.random.Generator):
    """Gaussians of a thin cylinder, elongated along its axis as 3DGS fits thin structures.

    8 Gaussians around the circumference, spaced `along` = max(spacing, 2.5x the circumferential
    spacing) along the axis (no caps). Returns points [P, 3], rotations [P, 3, 3] (columns:
    circumferential tangent, axis, outward normal) and scales [P, 3].
    """
    p = spec.params
    r, h, axis = p["radius"], p["height"], p["axis"]
    around = 2 * np.pi * r / 8
    along = max(spacing, 2.5 * around)
    n_along = max(2, int(round(h / along)))
    ang = (np.arange(8)[None, :] + 0.5 * (np.arange(n_along)[:, None] % 2) + rng.uniform(-0.15, 0.15, (n_along, 8))) * (2 * np.pi / 8)
    z = ((np.arange(n_along) + 0.5) / n_along * h - h / 2)[:, None] + np.zeros_like(ang)
    ang, z = ang.ravel(), z.ravel()
    perm = {2: [0, 1, 2], 0: [2, 0, 1], 1: [1, 2, 0]}[axis]
    normal = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1)[:, perm]
    tangent = np.stack([-np.sin(ang), np.cos(ang), np.zeros_like(ang)], 1)[:, perm]
    axis_dir = np.broadcast_to(np.eye(3)[axis], normal.shape)
    pts = np.asarray(p["center"]) + (r * np.stack([np.cos(ang), np.sin(ang), z / r], 1))[:, perm]
    rot = np.stack([tangent, axis_dir, normal], axis=2)
    scales = np.stack([np.full(len(pts), 0.6 * around), np.full(len(pts), 0.6 * h / n_along), np.full(len(pts), 0.05 * around)], 1)
    return pts, rot, scales


def _build_room(preset: Preset, rng: np.random.Generator):
    """All Gaussians of a hard room (see RoomParams): (scene, labels [N], instances [N], instance labels, names)."""
    room = preset.room or RoomParams()
    objs, hx, hy = _room_objects(room, rng)
    names = sorted({o.label for o in objs}, key=[o.label for o in objs].index)
    specs = [o.spec for o in objs]
    thin = [o.spec.kind == "cylinder" and o.spec.params["radius"] < 0.03 for o in objs]
    num_floaters = int(round(room.floater_fraction * preset.num_gaussians))
    budget = preset.num_gaussians - num_floaters - room.num_blobs
    area = sum(object_area(s) for s, t in zip(specs, thin) if not t)
    thin_count = sum(8 * max(2, int(round(s.params["height"] / (2.5 * 2 * np.pi * s.params["radius"] / 8)))) for s, t in zip(specs, thin) if t)
    spacing = np.sqrt(area / max(budget - thin_count, 100))
    means, rots, scales, colors, inst = [], [], [], [], []
    for k, (spec, is_thin) in enumerate(zip(specs, thin)):
        if is_thin:
            pts, rot, sc = _thin_cylinder_surface(spec, spacing, rng)
            nrm = rot[:, :, 2]
        else:
            # small objects get at least ~40 Gaussians (3DGS densifies detail)
            count = max(40, int(round(object_area(spec) / spacing**2)))
            pts, nrm, _ = sample_surface(spec, count, rng)
            rot = _frame_from_normals(nrm)
            local = np.sqrt(object_area(spec) / max(len(pts), 1))
            sc = np.concatenate([local * rng.uniform(0.55, 0.75, (len(pts), 2)), np.full((len(pts), 1), local * 0.05)], 1)
        hidden = np.zeros(len(pts), bool)
        for other in specs:
            if other is not spec:
                hidden |= inside_object(other, pts, margin=0.005) | inside_object(other, pts + 0.02 * nrm, margin=0.005)
        rgb = np.asarray(spec.color) + rng.normal(0, 0.03, (len(pts), 3))
        rgb = np.clip(rgb * (0.7 + 0.3 * np.clip(nrm @ LIGHT, 0, 1))[:, None], 0, 1)
        means.append(pts[~hidden])
        rots.append(rot[~hidden])
        scales.append(sc[~hidden])
        colors.append(rgb[~hidden])
        inst.append(np.full(int((~hidden).sum()), k, np.int32))
    n_obj = sum(len(m) for m in means)
    opacity = rng.uniform(0.85, 0.98, n_obj)
    faint = rng.random(n_obj) < room.faint_fraction
    opacity[faint] = rng.uniform(0.1, 0.6, int(faint.sum()))
    nf, nb = num_floaters, room.num_blobs
    f_means = np.c_[rng.uniform(-hx + 0.1, hx - 0.1, nf), rng.uniform(-hy + 0.1, hy - 0.1, nf), rng.uniform(0.1, ROOM_HEIGHT - 0.2, nf)]
    f_scales = np.exp(rng.uniform(np.log(0.01), np.log(0.06), (nf, 3)))
    f_opacity = rng.uniform(0.03, 0.3, nf)
    b_means = np.c_[rng.uniform(-hx, hx, nb) * 0.6, rng.uniform(-hy, hy, nb) * 0.6, rng.uniform(0.4, 1.6, nb)]
    b_scales = np.exp(rng.uniform(np.log(0.3), np.log(1.0), (nb, 3)))
    b_opacity = rng.uniform(0.03, 0.12, nb)
    extra_rgb = rng.uniform(0.3, 0.9, (nf + nb, 3))
    extra_quats = _normalize(rng.normal(size=(nf + nb, 4))).astype(np.float32)
    opac = np.clip(np.concatenate([opacity, f_opacity, b_opacity]), 1e-4, 1 - 1e-4)
    scene = GaussianScene(
        means=np.concatenate(means + [f_means, b_means]).astype(np.float32),
        quats=np.concatenate([rotmat_to_quat(np.concatenate(rots)), extra_quats]).astype(np.float32),
        log_scales=np.log(np.concatenate(scales + [f_scales, b_scales])).astype(np.float32),
        opacity_logits=np.log(opac / (1 - opac)).astype(np.float32),
        sh=_rgb_to_sh(np.concatenate(colors + [extra_rgb]), preset.sh_degree, rng, 0.01),
        comments=[f"drsplat.synthetic preset={preset.name}"],
    )
    instances = np.concatenate(inst + [np.full(nf + nb, -1, np.int32)])
    instance_labels = np.array([names.index(o.label) for o in objs], np.int32)
    labels = np.where(instances >= 0, instance_labels[np.maximum(instances, 0)], -1).astype(np.int32)
    return scene, labels, instances, instance_labels, names, specs


def _room_bounds(scene: GaussianScene, labels: np.ndarray) -> tuple[float, float]:
    """(hx, hy) of a room from its wall Gaussians' extent."""
    pts = scene.means[labels >= 0]
    return float(np.abs(pts[:, 0]).max()), float(np.abs(pts[:, 1]).max())


def make_room_cameras(preset: Preset, syn_scene: GaussianScene, labels: np.ndarray, instances: np.ndarray, names: list[str],
                      rng: np.random.Generator) -> list[Camera]:
    """Views of a room from inside it: overviews across the room, grazing views along a wall,
    far views of a small or thin object from the opposite side, and views from near the floor."""
    room = preset.room or RoomParams()
    hx, hy = _room_bounds(syn_scene, labels)
    w, h = preset.width, preset.height
    cams = []
    for i in range(preset.num_orbit_views):
        ang = 2 * np.pi * (i + 0.5) / max(preset.num_orbit_views, 1) + rng.uniform(-0.2, 0.2)
        eye = (0.55 * hx * np.cos(ang), 0.55 * hy * np.sin(ang), rng.uniform(1.3, 1.9))
        target = (-0.9 * hx * np.cos(ang + rng.uniform(-0.6, 0.6)), -0.9 * hy * np.sin(ang + rng.uniform(-0.6, 0.6)), rng.uniform(0.3, 1.0))
        cams.append(look_at(eye, target, w, h, fov_x_deg=70.0, name=f"orbit_{i:03d}"))
    for i in range(room.grazing_views):
        wall = int(rng.integers(4))
        base, along, inward, length = _wall_frame(wall, hx, hy)
        sign = 1.0 if rng.random() < 0.5 else -1.0
        eye = base + along * sign * (length / 2 - 0.2) + inward * rng.uniform(0.25, 0.6) + np.array([0, 0, rng.uniform(0.5, 1.6)])
        target = base - along * sign * (length / 2) + inward * rng.uniform(0.0, 0.3) + np.array([0, 0, rng.uniform(0.3, 1.2)])
        cams.append(look_at(eye, target, w, h, fov_x_deg=60.0, name=f"grazing_{i:03d}"))
    small = [k for k, n in enumerate(names) if n in ("ball", "cube", "pole", "stem", "cable")]
    for i in range(room.far_views):
        pick = np.isin(labels, small) if small else labels >= 0
        centre = syn_scene.means[rng.choice(np.flatnonzero(pick))].astype(np.float64)
        eye = np.array([-np.sign(centre[0]) * 0.8 * hx, -np.sign(centre[1]) * 0.8 * hy, rng.uniform(1.0, 1.8)]) + rng.uniform(-0.2, 0.2, 3)
        cams.append(look_at(eye, centre, w, h, fov_x_deg=55.0, name=f"far_{i:03d}"))
    for i in range(room.low_views):
        ang = rng.uniform(0, 2 * np.pi)
        eye = (0.5 * hx * np.cos(ang), 0.5 * hy * np.sin(ang), rng.uniform(0.12, 0.3))
        target = (-hx * np.cos(ang), -hy * np.sin(ang), rng.uniform(0.1, 0.4))
        cams.append(look_at(eye, target, w, h, fov_x_deg=75.0, name=f"low_{i:03d}"))
    return cams


def make_embedding_basis(num_labels: int, dim: int, rng: np.random.Generator):
    """(c [D], c_t [D], v [L, D]): mutually orthogonal unit vectors."""
    if num_labels + 2 > dim:
        raise ValueError(f"dim={dim} is too small for {num_labels} labels")
    q, _ = np.linalg.qr(rng.normal(size=(dim, num_labels + 2)))
    q = q.T.astype(np.float32)
    return q[0], q[1], q[2:]


MIN_WIDTH, MAX_WIDTH = 8, 4096  # the image widths a synthetic dataset may be rendered at


def make_synthetic(preset: str = "tiny", seed: int = 0, *, oracle: OracleParams | None = None, width: int | None = None) -> SyntheticScene:
    """Build the scene, cameras and oracle vectors of a preset (nothing is rendered or written).

    width: render the views `width` pixels wide (the preset's cameras scaled, intrinsics and height
    with them: the same poses, scene and oracle vectors); None keeps the preset's size."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset '{preset}' (choose from {', '.join(PRESETS)})")
    if width is not None and not MIN_WIDTH <= width <= MAX_WIDTH:
        raise ValueError(f"width must be {MIN_WIDTH} to {MAX_WIDTH} pixels, got {width}")
    p = PRESETS[preset]
    oracle = oracle or OracleParams(jitter=p.jitter, mislabel_fraction=p.mislabel, mask_source=p.mask_source)
    if oracle.mask_source not in MASK_SOURCES:
        raise ValueError(f"unknown mask source {oracle.mask_source!r} (choose from {', '.join(MASK_SOURCES)})")
    rng = np.random.default_rng(seed)
    if p.layout == "room":
        scene, labels, instances, instance_labels, names, specs = _build_room(p, rng)
        cameras = make_room_cameras(p, scene, labels, instances, names, rng)
    else:
        scene, labels, instances, instance_labels, names, specs = _build_gaussians(p, rng)
        cameras = make_cameras(p, rng)
    if width is not None:
        cameras = [cam.scaled(width / cam.width) for cam in cameras]
    c, c_t, v = make_embedding_basis(len(names), p.dim, np.random.default_rng([seed, 1]))
    text = _normalize(oracle.text_a * c_t + oracle.text_b * v).astype(np.float32)
    return SyntheticScene(preset, seed, scene, cameras, labels, instances, instance_labels, names, v, c, c_t, text, oracle, list(specs))


# ----------------------------------------------------------------------------- rendering & oracle features


def instance_map(ids: np.ndarray, weights: np.ndarray, instances: np.ndarray, num_instances: int) -> np.ndarray:
    """Per-pixel object instance by weighted vote.

    ids, weights: [H, W, k] top-k Gaussians of each pixel (-1 padded) and their w = T·α.
    instances: [N] instance per Gaussian (-1 none). Returns [H, W] int32: argmax over
    {none, 0..I-1} of Σ_s w_s·[instance(id_s) = i]; -1 when "none" wins or nothing was hit.
    """
    inst = np.where(ids >= 0, instances[np.maximum(ids, 0)], -1)
    w = np.where(ids >= 0, weights, 0.0)
    votes = np.stack([np.sum(w * (inst == i), axis=-1) for i in range(-1, num_instances)], axis=-1)
    best = np.argmax(votes, axis=-1) - 1
    return np.where(votes.max(axis=-1) > 0, best, -1).astype(np.int32)


def ray_hit_depth(spec: ObjectSpec, origin: np.ndarray, dirs: np.ndarray, near: float | None = None) -> np.ndarray:
    """[R] ray parameter t ≥ near (default: the rasterizer's near plane) of the first hit of each ray origin + t·dirs with the solid of
    `spec` (+inf on a miss). Boxes and plates: the axis-aligned slab test on the whole box;
    spheres: |o + t·d - c| = r; cylinders (axis-aligned, closed): side |radial| = r within the
    height, caps within the radius; panels: the two-sided rectangle."""
    near = NEAR if near is None else near
    p = spec.params
    c = np.asarray(p["center"], np.float64)
    o = origin - c
    inf = np.full(len(dirs), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        if spec.kind in ("box", "plate"):
            half = np.asarray(p["size"], np.float64) / 2
            safe = np.where(dirs == 0, 1e-300, dirs)
            t1, t2 = (-half - o) / safe, (half - o) / safe
            t_in = np.minimum(t1, t2).max(axis=1)
            t_out = np.maximum(t1, t2).min(axis=1)
            return np.where((t_out >= t_in) & (t_in >= near), t_in, inf)
        if spec.kind == "sphere":
            return _first_root(np.sum(dirs * dirs, 1), 2 * dirs @ o, float(o @ o) - p["radius"] ** 2, near)
        if spec.kind == "cylinder":
            axis, r, h = p["axis"], p["radius"], p["height"]
            rad = [i for i in range(3) if i != axis]
            d2, o2 = dirs[:, rad], o[rad]
            t_side = _first_root(np.sum(d2 * d2, 1), 2 * d2 @ o2, float(o2 @ o2) - r * r, near)
            t_side = np.where(np.abs(o[axis] + t_side * dirs[:, axis]) <= h / 2, t_side, np.inf)
            best = t_side
            for cap in (-h / 2, h / 2):
                t_cap = (cap - o[axis]) / dirs[:, axis]
                radial = o2 + t_cap[:, None] * d2
                ok = (t_cap >= near) & (np.sum(radial * radial, 1) <= r * r)
                best = np.minimum(best, np.where(ok, t_cap, np.inf))
            return best
        if spec.kind == "panel":
            w, h = p["size"]
            facing = _normalize(np.asarray(p["facing"], np.float64))
            right = _normalize(np.cross(np.array([0.0, 0.0, 1.0]), facing))
            up = np.cross(facing, right)
            t = -(o @ facing) / (dirs @ facing)
            q = o + t[:, None] * dirs
            ok = (t >= near) & (np.abs(q @ right) <= w / 2) & (np.abs(q @ up) <= h / 2)
            return np.where(ok, t, inf)
    raise ValueError(f"unknown object kind {spec.kind}")


def _first_root(a: np.ndarray, b: np.ndarray, c: float, near: float) -> np.ndarray:
    """Smallest root t ≥ near of a·t² + b·t + c = 0 per ray (+inf if none): the entry point, or the
    exit point when the ray starts inside."""
    disc = b * b - 4 * a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    t0, t1 = (-b - sq) / (2 * a), (-b + sq) / (2 * a)
    t = np.where(t0 >= near, t0, np.where(t1 >= near, t1, np.inf))
    return np.where(disc >= 0, t, np.inf)


def ray_cast_instances(specs: list[ObjectSpec], camera: Camera) -> np.ndarray:
    """[H, W] int32 instance whose true surface the ray through the pixel centre hits first (index
    into `specs`), -1 where it hits none: the objects' exact silhouettes ("geometry" masks)."""
    origin, dirs = camera.pixel_rays()
    best_t = np.full(len(dirs), np.inf)
    best = np.full(len(dirs), -1, np.int32)
    for k, spec in enumerate(specs):
        t = ray_hit_depth(spec, origin, dirs)
        closer = t < best_t
        best_t[closer] = t[closer]
        best[closer] = k
    return best.reshape(camera.height, camera.width)


def jitter_boundaries(ids: np.ndarray, jitter: int, rng: np.random.Generator) -> np.ndarray:
    """Mask map whose boundaries wander by up to `jitter` pixels (every pixel copies a random
    neighbour within the window); interiors are unchanged. ids: [H, W] -> [H, W]."""
    if jitter <= 0:
        return ids
    h, w = ids.shape
    ys, xs = np.mgrid[0:h, 0:w]
    dy = rng.integers(-jitter, jitter + 1, (h, w))
    dx = rng.integers(-jitter, jitter + 1, (h, w))
    return ids[np.clip(ys + dy, 0, h - 1), np.clip(xs + dx, 0, w - 1)]


def merged_instances(ids: np.ndarray, present: np.ndarray, fraction: float, rng: np.random.Generator) -> dict[int, int]:
    """Under-segmentation of one mask level: {instance: the instance whose mask swallows it}.

    ids: [H, W] instance per pixel (-1 none); present: the instances that get a mask. Each present
    instance is, with probability `fraction` (one draw of rng each, in order), merged into the
    present instance it shares the most 4-neighbour pixel edges with, unless it touches none or
    that one is merged itself (a union is one level deep: absorbers keep their own mask).
    """
    if fraction <= 0 or present.size < 2:
        return {}
    chosen = [int(i) for i, u in zip(present, rng.random(present.size)) if u < fraction]
    pairs = [np.stack([ids[:, :-1].ravel(), ids[:, 1:].ravel()]), np.stack([ids[:-1].ravel(), ids[1:].ravel()])]
    a, b = np.concatenate(pairs, axis=1)
    ok = (a != b) & (a >= 0) & (b >= 0) & np.isin(a, present) & np.isin(b, present)
    a, b = np.concatenate([a[ok], b[ok]]), np.concatenate([b[ok], a[ok]])  # both directions
    merged: dict[int, int] = {}
    for i in chosen:
        if i in merged.values():  # it swallows another already: keeps its own mask
            continue
        touching = b[a == i]
        touching = touching[~np.isin(touching, list(merged))]  # never into a mask merged away
        if touching.size:
            into, counts = np.unique(touching, return_counts=True)
            merged[i] = int(into[np.argmax(counts)])
    return merged


def split_instances(ids: np.ndarray, present: np.ndarray, fraction: float, rng: np.random.Generator, min_pixels: int) -> dict[int, np.ndarray]:
    """Over-segmentation of one mask level: {instance: [H, W] bool, the pixels of its second part}.

    ids: [H, W] instance per pixel (-1 none); present: the instances that may be cut. Each is, with
    probability `fraction` (one draw of rng each, in order), cut by the line through its pixels'
    centroid across their principal (long) axis: the pixels on the positive side form the second
    part. An instance whose parts would not both hold `min_pixels` pixels stays whole.
    """
    if fraction <= 0 or present.size == 0:
        return {}
    parts: dict[int, np.ndarray] = {}
    for instance, u in zip(present, rng.random(present.size)):
        if u >= fraction:
            continue
        inside = ids == instance
        ys, xs = np.nonzero(inside)
        coords = np.stack([xs, ys], axis=1).astype(np.float64)
        centred = coords - coords.mean(axis=0)
        axis = np.linalg.eigh(centred.T @ centred)[1][:, -1]  # the long axis: largest eigenvalue
        second = centred @ axis > 0
        if min_pixels <= second.sum() <= second.size - min_pixels:
            part = np.zeros_like(inside)
            part[ys[second], xs[second]] = True
            parts[int(instance)] = part
    return parts


def oracle_masks_and_embeddings(
    inst: np.ndarray, syn: SyntheticScene, rng: np.random.Generator, label_rng: np.random.Generator | None = None,
    merge_rng: np.random.Generator | None = None, split_rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """LangSplat-style feature pair for one view from its instance map.

    inst: [H, W] instance per pixel. Returns seg: [4, H, W] int32 with ids cumulative across the
    four levels (each level: one mask per visible instance, independently jittered), feats:
    [M, D] float32 unit embeddings, and mask_labels: [M] the label each embedding encodes
    (differs from the true label for mislabelled masks).

    rng draws the jitter, the noise and, for every mask, whether it is mislabelled; label_rng
    (None: rng) the wrong labels. With a label_rng of its own, rng's draws do not depend on the
    mislabel fraction: a room's masks, jitter and noise are those of the same room without
    mislabels, and its mislabelled embeddings are the only difference (what a mislabel costs is
    then measured on the same masks).
    """
    label_rng = rng if label_rng is None else label_rng
    merge_rng = rng if merge_rng is None else merge_rng
    split_rng = rng if split_rng is None else split_rng
    o = syn.oracle
    dim = syn.label_vectors.shape[1]
    seg = np.full((len(LEVELS),) + inst.shape, -1, np.int32)
    feats, mask_labels = [], []
    for level in range(len(LEVELS)):
        ids = jitter_boundaries(inst, o.jitter, rng)
        present, counts = np.unique(ids[ids >= 0], return_counts=True)
        present = present[counts >= o.min_mask_pixels]
        merged = merged_instances(ids, present, o.merge_fraction, merge_rng)
        whole = present[~np.isin(present, list(merged) + list(merged.values()))]  # a union is never cut
        split = split_instances(ids, whole, o.split_fraction, split_rng, o.min_mask_pixels)
        mask_of = {}
        for instance in present:
            label = _drawn_label(int(syn.instance_labels[instance]), syn, rng, label_rng)
            noise = _embedding_noise(syn, rng)  # drawn for a merged instance too: the later masks' draws stay
            if instance in merged:
                continue
            mask_of[instance] = len(feats)
            seg[level][ids == instance] = len(feats)
            if instance not in split:
                feats.append(_image_embedding(syn, syn.label_vectors[label], noise))
                mask_labels.append(label)
                continue
            seg[level][split[instance]] = len(feats) + 1
            for part_noise in (noise, _embedding_noise(syn, split_rng)):  # the second part's noise from the split stream
                direction = split_rng.normal(size=dim)
                part = PART_SHARE * syn.label_vectors[label] + np.sqrt(1 - PART_SHARE**2) * direction / np.linalg.norm(direction)
                feats.append(_image_embedding(syn, part, part_noise))
                mask_labels.append(label)
        for instance, into in merged.items():
            seg[level][ids == instance] = mask_of[into]
    return seg, _unit_embeddings(feats, dim), np.array(mask_labels, np.int32)


def _drawn_label(label: int, syn: SyntheticScene, rng: np.random.Generator, label_rng: np.random.Generator) -> int:
    """The label a mask's embedding encodes: its true `label`, or with probability
    oracle.mislabel_fraction another one (rng draws whether, label_rng which)."""
    num_labels = len(syn.label_names)
    if num_labels > 1 and rng.random() < syn.oracle.mislabel_fraction:
        return int(label_rng.choice([l for l in range(num_labels) if l != label]))
    return label


def _embedding_noise(syn: SyntheticScene, rng: np.random.Generator) -> np.ndarray:
    """[D] one mask's embedding noise: normal, oracle.noise/√D per component."""
    dim = syn.label_vectors.shape[1]
    return rng.normal(0, syn.oracle.noise / np.sqrt(dim), dim)


def _image_embedding(syn: SyntheticScene, direction: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """[D] a·c + b·direction + noise, before normalisation (direction: a label's vector, or a part's)."""
    return syn.oracle.a * syn.common_vector + syn.oracle.b * direction + noise


def _unit_embeddings(feats: list[np.ndarray], dim: int) -> np.ndarray:
    """[M, D] float32 a view's mask embeddings, each normalised."""
    return _normalize(np.array(feats, np.float32).reshape(-1, dim)).astype(np.float32)


@dataclass
class RenderedView:
    rgb: np.ndarray  # [H, W, 3] float32
    label_mask: np.ndarray  # [H, W] int32
    instance_mask: np.ndarray  # [H, W] int32


SEGMENTER_MASKS = "felzenszwalb superpixels of the rendered view, each with the oracle embedding of the instance covering most of it"


def segmenter_masks_and_embeddings(rgb: np.ndarray, inst: np.ndarray, syn: SyntheticScene, rng: np.random.Generator,
                                   label_rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A segmenter's masks of one view with oracle embeddings ("segmenter" masks, module docstring).

    rgb: [H, W, 3] uint8 the rendered view; inst: [H, W] int32 the ray-cast instance per pixel (-1
    none). The masks are `FelzenszwalbGenerator`'s regions at the four levels (its default
    parameters; ids cumulative across levels, as `oracle_masks_and_embeddings`'). A region's
    label is that of the instance covering most of its pixels (pixels of no instance not
    counted; a region over none gets no mask, its pixels -1), its embedding normalize(a·c + b·v_l +
    noise), and with probability mislabel_fraction another label's, drawn as for oracle masks
    (rng: whether, and the noise; label_rng, None for rng: which label). Returns seg [4, H, W]
    int32, feats [M, D] float32 unit rows, mask_labels [M] int32 (the label each embedding encodes).
    """
    label_rng = rng if label_rng is None else label_rng
    seg = np.full((len(LEVELS),) + inst.shape, -1, np.int32)
    feats, mask_labels = [], []
    for level, masks in enumerate(FelzenszwalbGenerator().generate(rgb)):
        for region in masks.masks:
            under = inst[region]
            under = under[under >= 0]
            if under.size == 0:
                continue
            label = _drawn_label(int(syn.instance_labels[np.bincount(under).argmax()]), syn, rng, label_rng)
            seg[level][region] = len(feats)
            feats.append(_image_embedding(syn, syn.label_vectors[label], _embedding_noise(syn, rng)))
            mask_labels.append(label)
    return seg, _unit_embeddings(feats, syn.label_vectors.shape[1]), np.array(mask_labels, np.int32)


def segmenter_corruption_error(mask_source: str | None, jitter: int | None, merge: float, split: float) -> str | None:
    """Why segmenter masks refuse these corruptions (None: they do not, or the masks are the
    oracle's): jitter, merges and splits are the oracle's models of a segmenter's errors, which
    segmenter masks have of their own. The one rule `write_dataset`, `drsplat synth` and `eval
    ablate` apply."""
    if mask_source != "segmenter" or not (jitter or merge or split):
        return None
    return ("jitter, merges and splits corrupt the oracle's instance masks; segmenter masks have a segmenter's own errors "
            f"(got jitter {jitter or 0}, merge {merge:g}, split {split:g})")


def render_view(syn: SyntheticScene, camera: Camera, topk: int = 16) -> RenderedView:
    """RGB and ground-truth masks of one view: one rasterizer pass, and the instance map from it
    ("render" masks) or from ray casting the objects ("geometry" and "segmenter" masks)."""
    out = rasterize(syn.scene, camera, topk=topk, with_rgb=True, background=np.array([1.0, 1.0, 1.0], np.float32))
    if syn.oracle.mask_source in ("geometry", "segmenter"):
        inst = ray_cast_instances(syn.instance_specs, camera)
    else:
        inst = instance_map(out.ids, out.weights, syn.instances, len(syn.instance_labels))
    labels = np.where(inst >= 0, syn.instance_labels[np.maximum(inst, 0)], -1).astype(np.int32)
    return RenderedView(np.asarray(out.rgb, np.float32), labels, inst)


def write_dataset(
    out_dir: str | Path,
    preset: str = "tiny",
    seed: int = 0,
    *,
    mislabel_fraction: float | None = None,
    noise: float = 0.15,
    jitter: int | None = None,
    mask_source: str | None = None,
    merge_fraction: float = 0.0,
    split_fraction: float = 0.0,
    width: int | None = None,
    show_progress: bool = True,
    cancel=None,
) -> Path:
    """Render a synthetic dataset into `out_dir` (layout in docs/ARCHITECTURE.md) and return it.

    mislabel_fraction, jitter, merge_fraction, split_fraction: oracle mask corruption; mask_source: "render",
    "geometry" or "segmenter" (module docstring; segmenter masks take mislabels, but jitter, merges and
    splits are the oracle's models of a segmenter's errors, so a preset's jitter is not applied to
    them and a nonzero one given is refused); None takes the preset's default. width: the views' width in
    pixels (`make_synthetic`; None: the preset's).

    Every file is written atomically; the manifest and scene.ply come last, so an interrupted
    run leaves no scene.ply claiming a complete dataset.
    """
    from PIL import Image

    if preset not in PRESETS:
        raise ValueError(f"unknown preset '{preset}' (choose from {', '.join(PRESETS)})")
    mislabel_fraction = PRESETS[preset].mislabel if mislabel_fraction is None else mislabel_fraction
    mask_source = PRESETS[preset].mask_source if mask_source is None else mask_source
    jitter = (0 if mask_source == "segmenter" else PRESETS[preset].jitter) if jitter is None else jitter
    refused = segmenter_corruption_error(mask_source, jitter, merge_fraction, split_fraction)
    if refused:
        raise ValueError(refused)
    if not 0.0 <= mislabel_fraction <= 1.0:
        raise ValueError("mislabel_fraction must be in [0, 1]")
    for name, value in (("merge_fraction", merge_fraction), ("split_fraction", split_fraction)):
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"{name} must be in [0, 1]")
    out = Path(out_dir)
    oracle = OracleParams(noise=noise, mislabel_fraction=mislabel_fraction, jitter=jitter, mask_source=mask_source, merge_fraction=merge_fraction,
                          split_fraction=split_fraction)
    syn = make_synthetic(preset, seed, oracle=oracle, width=width)
    for sub in ("images", "gt/masks", "features"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([seed, 2])
    label_rng = np.random.default_rng([seed, WRONG_LABEL_STREAM])
    merge_rng = np.random.default_rng([seed, MERGE_STREAM])
    split_rng = np.random.default_rng([seed, SPLIT_STREAM])
    mislabelled = total_masks = 0
    for cam in progress(syn.cameras, desc=f"synth {preset}", enabled=show_progress, unit="view"):
        if cancel is not None:
            cancel.raise_if_cancelled()
        view = render_view(syn, cam)
        rgb8 = (np.clip(view.rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
        with atomic_path(out / "images" / f"{cam.name}.png") as tmp:
            Image.fromarray(rgb8).save(tmp, format="PNG")
        save_npy_atomic(out / "gt" / "masks" / f"{cam.name}.npy", view.label_mask)
        if mask_source == "segmenter":
            seg, feats, mask_labels = segmenter_masks_and_embeddings(rgb8, view.instance_mask, syn, rng, label_rng)
        else:
            seg, feats, mask_labels = oracle_masks_and_embeddings(view.instance_mask, syn, rng, label_rng, merge_rng, split_rng)
        true_labels = _true_mask_labels(seg, view.instance_mask, syn.instance_labels, len(feats))
        mislabelled += int(np.count_nonzero(mask_labels != true_labels))
        total_masks += len(feats)
        write_features(out / "features", cam.name, seg, feats)
    save_npy_atomic(out / "gt" / "labels.npy", syn.labels.astype(np.int32))
    save_npy_atomic(out / ORACLE_TEXT_EMBEDDINGS, syn.text_vectors.astype(np.float32))
    with atomic_path(out / ORACLE_LABEL_NAMES) as tmp:
        tmp.write_text(json.dumps(syn.label_names) + "\n")
    write_transforms_json(syn.cameras, out / "transforms.json")
    write_manifest(
        out / "features",
        {
            "format": "langsplat",
            "mask_generator": (SEGMENTER_MASKS if mask_source == "segmenter" else "oracle (drsplat.synthetic: one mask per visible object instance)"),
            **manifest_clip_entry(ORACLE_MODEL_ID, None),
            "synthetic": {"preset": preset, "seed": seed, **({"width": width} if width is not None else {})},
            "levels": list(LEVELS),
            "default_level": 1,
            "dim": int(syn.label_vectors.shape[1]),
            # mask_source only when not the default, so that datasets of the "render" presets stay byte-identical
            "params": {"a": oracle.a, "b": oracle.b, "noise": noise, "mislabel_fraction": mislabel_fraction, "jitter": jitter,
                       **({"mask_source": mask_source} if mask_source != "render" else {}),
                       **({"wrong_labels": WRONG_LABELS} if mislabel_fraction > 0 else {}),
                       **({"merge_fraction": merge_fraction} if merge_fraction > 0 else {}),
                       **({"split_fraction": split_fraction, "part_share": PART_SHARE} if split_fraction > 0 else {})},
            "counts": {"views": len(syn.cameras), "masks": total_masks, "mislabelled_masks": mislabelled},
        },
    )
    with atomic_path(out / "gt" / "synthetic.json") as tmp:
        tmp.write_text(
            json.dumps(
                {"preset": preset, "seed": seed, "localisation_threshold": syn.localisation_threshold(), "num_gaussians": syn.scene.num_gaussians},
                indent=2,
            )
            + "\n"
        )
    save_ply(syn.scene, out / "scene.ply")
    log.debug("wrote %s: %d Gaussians, %d views, %d masks (%d mislabelled)", out, syn.scene.num_gaussians, len(syn.cameras), total_masks, mislabelled)
    return out


def _true_mask_labels(seg: np.ndarray, inst: np.ndarray, instance_labels: np.ndarray, num_masks: int) -> np.ndarray:
    """[M] true label of each mask: the majority instance label under the mask."""
    out = np.full(num_masks, -1, np.int32)
    for level in seg:
        for m in np.unique(level[level >= 0]):
            under = inst[level == m]
            under = under[under >= 0]
            if len(under):
                out[m] = instance_labels[np.bincount(under).argmax()]
    return out


# ============================================================================= city (scale benchmark)
# A "city" for `drsplat bench scale`: copies of one written synthetic room on a grid. Owned by the
# scale work (drsplat/registration: plan, sink, ray); kept apart from the room generator above.


def tile_city(room: SyntheticScene | GaussianScene, cameras: list[Camera], tiles: int, views: int, width: int,
              spacing: float | None = None, sh_degree: int = 0) -> tuple[GaussianScene, list[Camera], list[str]]:
    """A city of `tiles` copies of a room on a square-ish grid, and `views` cameras spread over them.

    room: the room's scene (or its SyntheticScene); cameras: the room's cameras. Tile i is the
    room shifted by o_i = spacing·(col, row, 0) (spacing: the room's labelled extent + 10 %).
    View j is room camera j mod C of tile j mod tiles, shifted the same way (t' = t - R·o_i),
    at `width` pixels wide; it keeps the room camera's name as its features' source: returns
    (scene, cameras named t<tile>_<name>, the room view name of each camera). SH are cut to
    `sh_degree` (registration renders no colour; a degree-0 city is 4x smaller).
    """
    import dataclasses

    scene = room.scene if isinstance(room, SyntheticScene) else room
    if spacing is None:
        lo, hi = np.percentile(scene.means[:, :2], [2, 98], axis=0)
        spacing = float(1.1 * np.max(hi - lo))
    cols = int(np.ceil(np.sqrt(tiles)))
    offsets = np.array([[spacing * (i % cols), spacing * (i // cols), 0.0] for i in range(tiles)], np.float32)
    k = (sh_degree + 1) ** 2
    city = GaussianScene(
        means=(scene.means[None] + offsets[:, None]).reshape(-1, 3),
        quats=np.tile(scene.quats, (tiles, 1)),
        log_scales=np.tile(scene.log_scales, (tiles, 1)),
        opacity_logits=np.tile(scene.opacity_logits, tiles),
        sh=np.tile(scene.sh[:, :k], (tiles, 1, 1)),
    )
    out, sources = [], []
    for j in range(views):
        tile, cam = j % tiles, cameras[(j // tiles + j) % len(cameras)]
        cam = cam.scaled(width / cam.width)
        shift = offsets[tile].astype(np.float64)
        out.append(dataclasses.replace(cam, t=np.asarray(cam.t, np.float64) - np.asarray(cam.R, np.float64) @ shift,
                                       name=f"t{tile:05d}_{cam.name}", image_path=None))
        sources.append(cameras[(j // tiles + j) % len(cameras)].name)
    return city, out, sources


@dataclass(frozen=True)
class CityPreset:
    """`drsplat synth --preset city`: `tiles` copies of the `room` preset on a grid and `views` cameras
    spread over them at `width` pixels (each view sees about one room: the culled, scale path)."""

    room: str = "small"
    tiles: int = 16
    views: int = 96
    width: int = 64


CITY_PRESETS: dict[str, CityPreset] = {"city": CityPreset()}


def write_city(out_dir: str | Path, preset: str | CityPreset = "city", seed: int = 0, *, show_progress: bool = True, cancel=None) -> Path:
    """Write the city `preset` (a CITY_PRESETS name or a CityPreset) into `out_dir`: the room is written once (in
    out_dir/room, removed at the end), tiled by `tile_city` (the same city `drsplat bench scale`
    registers), and each city view's feature files are copies of its source room view's, its image
    the room view's image resized."""
    import shutil

    city = CITY_PRESETS[preset] if isinstance(preset, str) else preset
    out = Path(out_dir)
    room = write_dataset(out / "room", city.room, seed, show_progress=show_progress, cancel=cancel)
    scene, cams, sources = tile_city(load_ply(room / "scene.ply"), load_cameras(room, require_images=False), city.tiles, city.views, city.width)
    from PIL import Image

    for sub in ("features", "gt", "images"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    for cam, src in zip(cams, sources):
        for suffix in ("_s.npy", "_f.npy"):
            shutil.copyfile(room / "features" / f"{src}{suffix}", out / "features" / f"{cam.name}{suffix}")
        # the room view's picture at the city view's size (a city view is its room view, shifted)
        with Image.open(room / "images" / f"{src}.png") as image:
            image.resize((cam.width, cam.height), Image.BILINEAR).save(out / "images" / f"{cam.name}.png", format="PNG")
    manifest = json.loads((room / "features" / "manifest.json").read_text())
    manifest["synthetic"] = {"preset": "city", "seed": seed, "room": city.room, "tiles": city.tiles, "views": city.views, "width": city.width}
    manifest.setdefault("counts", {})["views"] = len(cams)
    write_manifest(out / "features", manifest)
    for name in (ORACLE_TEXT_EMBEDDINGS, ORACLE_LABEL_NAMES):
        shutil.copyfile(room / name, out / name)
    save_npy_atomic(out / "gt" / "labels.npy", np.tile(np.load(room / "gt" / "labels.npy"), city.tiles))  # tile-major, as tile_city
    write_transforms_json(cams, out / "transforms.json")
    save_ply(scene, out / "scene.ply")
    shutil.rmtree(room)
    log.debug("wrote city %s: %d Gaussians, %d views", out, scene.num_gaussians, len(cams))
    return out
