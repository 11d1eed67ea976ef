"""Cameras: the `Camera` record and readers for COLMAP, transforms.json and 3DGS cameras.json.

Every reader converts once, at load time, to the OpenCV convention: x right, y down, z forward,
world-to-camera x_cam = R · x_world + t.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


@dataclass
class Camera:
    """A pinhole camera in the OpenCV convention.

    R: [3, 3] world-to-camera rotation. t: [3] world-to-camera translation.
    fx, fy, cx, cy: intrinsics in pixels of a (width x height) image.
    image_path: the training image, if any. name: the image file stem (pairs with feature files).
    distortion: [4] OpenCV (k1, k2, p1, p2) of the image *file*, or None. The intrinsics always
    describe the undistorted pinhole image that `load_image` returns.
    """

    R: np.ndarray
    t: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    image_path: Path | None = None
    name: str = ""
    distortion: np.ndarray | None = None

    @property
    def K(self) -> np.ndarray:
        """[3, 3] intrinsic matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=np.float64)

    @property
    def viewmat(self) -> np.ndarray:
        """[4, 4] world-to-camera matrix."""
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    @property
    def center(self) -> np.ndarray:
        """[3] camera centre in world coordinates, -Rᵀ t."""
        return -self.R.T @ self.t

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """points: [P, 3] world -> [P, 3] camera coordinates."""
        return points @ self.R.T + self.t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pinhole projection of world points.

        points: [P, 3]. Returns uv: [P, 2] pixel coordinates (pixel centres at +0.5, as COLMAP)
        and depth: [P] camera z.
        """
        pc = self.world_to_camera(np.asarray(points, dtype=np.float64))
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * pc[:, 0] / z + self.cx
            v = self.fy * pc[:, 1] / z + self.cy
        return np.stack([u, v], axis=1), z

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by `factor` (intrinsics and size together)."""
        width = max(1, int(round(self.width * factor)))
        height = max(1, int(round(self.height * factor)))
        sx, sy = width / self.width, height / self.height
        return dataclasses.replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy, width=width, height=height)


# COLMAP camera models: id -> (name, number of parameters)
COLMAP_MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
}
COLMAP_MODEL_IDS = {name: (mid, count) for mid, (name, count) in COLMAP_MODELS.items()}
UNDISTORT_HINT = (
    "3DGS is trained on undistorted images: run `colmap image_undistorter --image_path IMAGES "
    "--input_path sparse/0 --output_path undistorted --output_type COLMAP` (as 3DGS's convert.py does) "
    "and point --source at the undistorted folder"
)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG", ".webp", ".bmp", ".tif", ".tiff")
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


@dataclass
class ColmapCamera:
    """An intrinsics record of a COLMAP model."""

    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapImage:
    """An image record of a COLMAP model: world-to-camera pose and 2D observations.

    qvec: [4] (w, x, y, z). tvec: [3]. xys: [P, 2] observations. point3D_ids: [P] (-1 = none).
    """

    image_id: int
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str
    xys: np.ndarray
    point3D_ids: np.ndarray


@dataclass
class ColmapModel:
    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    points: dict[int, np.ndarray]  # point3D id -> [3] xyz

    def points_array(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids [P] int64, xyz [P, 3] float64) of all 3D points."""
        ids = np.fromiter(self.points.keys(), dtype=np.int64, count=len(self.points))
        xyz = np.array(list(self.points.values()), dtype=np.float64).reshape(-1, 3)
        return ids, xyz


def qvec_to_rotmat(qvec: np.ndarray) -> np.ndarray:
    """[4] (w, x, y, z) -> [3, 3] rotation (normalised first)."""
    from drsplat.scene import quat_to_rotmat

    q = np.asarray(qvec, dtype=np.float64)
    return quat_to_rotmat((q / np.linalg.norm(q))[None])[0]


class _Reader:
    """Bounds-checked little-endian reader for COLMAP binary files."""

    def __init__(self, path: Path):
        from drsplat.errors import InputError

        self.path = path
        try:
            self.buf = path.read_bytes()
        except OSError as exc:
            raise InputError(path, f"cannot be read ({exc.strerror or exc})") from None
        self.pos = 0

    def take(self, dtype: str, count: int = 1) -> np.ndarray:
        from drsplat.errors import InputError

        dt = np.dtype(dtype)
        end = self.pos + dt.itemsize * count
        if end > len(self.buf):
            raise InputError(self.path, f"is truncated at byte {self.pos} (needs {end - self.pos} more bytes)")
        out = np.frombuffer(self.buf, dtype=dt, count=count, offset=self.pos)
        self.pos = end
        return out

    def one(self, dtype: str):
        return self.take(dtype)[0].item()

    def cstring(self) -> str:
        from drsplat.errors import InputError

        end = self.buf.find(b"\x00", self.pos)
        if end < 0:
            raise InputError(self.path, f"is truncated inside an image name at byte {self.pos}")
        text = self.buf[self.pos:end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return text


def read_colmap_cameras_bin(path: Path) -> dict[int, ColmapCamera]:
    from drsplat.errors import InputError

    r = _Reader(path)
    cameras = {}
    for _ in range(r.one("<u8")):
        cam_id, model_id = r.one("<i4"), r.one("<i4")
        if model_id not in COLMAP_MODELS:
            raise InputError(path, f"camera {cam_id} has unknown model id {model_id}", field="model_id")
        name, count = COLMAP_MODELS[model_id]
        width, height = r.one("<u8"), r.one("<u8")
        cameras[cam_id] = ColmapCamera(cam_id, name, int(width), int(height), r.take("<f8", count).copy())
    return cameras


def read_colmap_images_bin(path: Path) -> dict[int, ColmapImage]:
    r = _Reader(path)
    images = {}
    for _ in range(r.one("<u8")):
        image_id = r.one("<u4")
        qvec, tvec = r.take("<f8", 4).copy(), r.take("<f8", 3).copy()
        camera_id = r.one("<u4")
        name = r.cstring()
        num = r.one("<u8")
        obs = r.take([("x", "<f8"), ("y", "<f8"), ("id", "<i8")], num)  # type: ignore[arg-type]
        xys = np.stack([obs["x"], obs["y"]], axis=1) if num else np.zeros((0, 2))
        images[image_id] = ColmapImage(image_id, qvec, tvec, camera_id, name, xys, obs["id"].copy())
    return images


def read_colmap_points_bin(path: Path) -> dict[int, np.ndarray]:
    r = _Reader(path)
    points = {}
    for _ in range(r.one("<u8")):
        pid = r.one("<u8")
        xyz = r.take("<f8", 3).copy()
        r.take("u1", 3)
        r.one("<f8")
        r.take("<i4", 2 * r.one("<u8"))
        points[int(pid)] = xyz
    return points


def _data_lines(path: Path) -> list[str]:
    from drsplat.errors import InputError

    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot be read as text ({exc})") from None
    return [line.strip() for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]


def _parse_fail(path: Path, lineno: int, what: str):
    from drsplat.errors import InputError

    return InputError(path, f"has a malformed {what} line (data line {lineno})")


def read_colmap_cameras_txt(path: Path) -> dict[int, ColmapCamera]:
    from drsplat.errors import InputError

    cameras = {}
    for i, line in enumerate(_data_lines(path), start=1):
        w = line.split()
        try:
            model = w[1]
            if model not in COLMAP_MODEL_IDS:
                raise InputError(path, f"camera line {i} has unknown model {model!r}", field="MODEL")
            cam = ColmapCamera(int(w[0]), model, int(w[2]), int(w[3]), np.array([float(x) for x in w[4:]], dtype=np.float64))
        except (IndexError, ValueError):
            raise _parse_fail(path, i, "camera") from None
        if cam.params.size != COLMAP_MODEL_IDS[model][1]:
            raise InputError(path, f"camera {cam.camera_id} ({model}) has {cam.params.size} parameters, expected {COLMAP_MODEL_IDS[model][1]}", field="PARAMS")
        cameras[cam.camera_id] = cam
    return cameras


def read_colmap_images_txt(path: Path) -> dict[int, ColmapImage]:
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    images = {}
    for i in range(0, len(lines) - 1, 2):
        w, pts = lines[i].split(), lines[i + 1].split()
        if not w:
            continue
        try:
            obs = np.array([float(x) for x in pts], dtype=np.float64).reshape(-1, 3)
            img = ColmapImage(int(w[0]), np.array(w[1:5], float), np.array(w[5:8], float), int(w[8]), " ".join(w[9:]),
                              obs[:, :2].copy(), obs[:, 2].astype(np.int64))
        except (IndexError, ValueError):
            raise _parse_fail(path, i // 2 + 1, "image") from None
        images[img.image_id] = img
    return images


def read_colmap_points_txt(path: Path) -> dict[int, np.ndarray]:
    points = {}
    for i, line in enumerate(_data_lines(path), start=1):
        w = line.split()
        try:
            points[int(w[0])] = np.array([float(w[1]), float(w[2]), float(w[3])])
        except (IndexError, ValueError):
            raise _parse_fail(path, i, "point") from None
    return points


def read_colmap_model(sparse_dir: str | Path) -> ColmapModel:
    """Read a COLMAP sparse model folder (binary `*.bin` preferred, else text `*.txt`)."""
    from drsplat.errors import InputError

    d = Path(sparse_dir)
    if (d / "cameras.bin").exists() and (d / "images.bin").exists():
        cams, imgs = read_colmap_cameras_bin(d / "cameras.bin"), read_colmap_images_bin(d / "images.bin")
        points = read_colmap_points_bin(d / "points3D.bin") if (d / "points3D.bin").exists() else {}
    elif (d / "cameras.txt").exists() and (d / "images.txt").exists():
        cams, imgs = read_colmap_cameras_txt(d / "cameras.txt"), read_colmap_images_txt(d / "images.txt")
        points = read_colmap_points_txt(d / "points3D.txt") if (d / "points3D.txt").exists() else {}
    else:
        raise InputError(d, "is not a COLMAP sparse model (no cameras.bin/images.bin or cameras.txt/images.txt)")
    for img in imgs.values():
        if img.camera_id not in cams:
            raise InputError(d, f"image {img.name!r} refers to camera {img.camera_id}, which the model does not have", field="CAMERA_ID")
    return ColmapModel(cams, imgs, points)


def colmap_intrinsics(cam: ColmapCamera, source: Path) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of an undistorted COLMAP camera; distorted models are refused."""
    from drsplat.errors import InputError

    p = cam.params
    if cam.model == "SIMPLE_PINHOLE":
        return p[0], p[0], p[1], p[2]
    if cam.model == "PINHOLE":
        return p[0], p[1], p[2], p[3]
    if cam.model in ("SIMPLE_RADIAL", "RADIAL") and np.all(p[3:] == 0):
        return p[0], p[0], p[1], p[2]
    if cam.model in ("OPENCV", "FULL_OPENCV") and np.all(p[4:] == 0):
        return p[0], p[1], p[2], p[3]
    raise InputError(source, f"camera {cam.camera_id} uses the distorted model {cam.model}; {UNDISTORT_HINT}", field="MODEL")


def cameras_from_colmap(model: ColmapModel, images_dir: Path, source: Path) -> list[Camera]:
    """Cameras in image-name order (as 3DGS sorts them)."""
    out = []
    for img in sorted(model.images.values(), key=lambda im: im.name):
        cam = model.cameras[img.camera_id]
        fx, fy, cx, cy = (float(v) for v in colmap_intrinsics(cam, source))
        out.append(Camera(R=qvec_to_rotmat(img.qvec), t=img.tvec.astype(np.float64), fx=fx, fy=fy, cx=cx, cy=cy,
                          width=cam.width, height=cam.height, image_path=images_dir / img.name, name=Path(img.name).stem))
    return out


def _json(path: Path) -> dict:
    import json

    from drsplat.errors import InputError

    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot be read ({exc})") from None
    except json.JSONDecodeError as exc:
        raise InputError(path, f"is not valid JSON (line {exc.lineno}: {exc.msg})") from None


def _number(path: Path, record: dict, key: str, default: float | None = None, where: str = "") -> float:
    from drsplat.errors import InputError

    value = record.get(key, default)
    if value is None:
        raise InputError(path, f"is missing{where}", field=key)
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InputError(path, f"has a non-numeric value{where}: {value!r}", field=key) from None
    if not np.isfinite(value):
        raise InputError(path, f"has a non-finite value{where}", field=key)
    return value


def _resolve_image(root: Path, file_path: str) -> Path | None:
    """The image a transforms.json frame names (NeRF-synthetic omits the extension)."""
    p = (root / file_path).resolve() if not Path(file_path).is_absolute() else Path(file_path)
    if p.is_file():
        return p
    for suffix in IMAGE_SUFFIXES:
        q = p.with_name(p.name + suffix)
        if q.is_file():
            return q
    return None


def _image_size(path: Path) -> tuple[int, int]:
    from PIL import Image

    from drsplat.errors import InputError

    try:
        with Image.open(path) as im:
            return im.size
    except Exception as exc:
        raise InputError(path, f"is not a readable image ({exc.__class__.__name__})") from None


def c2w_opengl_to_w2c_opencv(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-to-world in OpenGL axes (x right, y up, z back) -> world-to-camera (R, t) in OpenCV axes.

    R = (R_c2w · diag(1, -1, -1))ᵀ, t = -R · c.
    """
    rot = c2w[:3, :3] @ OPENGL_TO_OPENCV
    R = rot.T
    return R, -R @ c2w[:3, 3]


def w2c_opencv_to_c2w_opengl(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Inverse of `c2w_opengl_to_w2c_opencv`: [4, 4] camera-to-world in OpenGL axes."""
    c2w = np.eye(4)
    c2w[:3, :3] = R.T @ OPENGL_TO_OPENCV
    c2w[:3, 3] = -R.T @ t
    return c2w


def read_transforms_json(path: Path) -> tuple[list[Camera], int]:
    """Cameras of a NeRF-synthetic or instant-ngp/nerfstudio transforms.json.

    Returns (cameras, number of frames skipped because their image is missing). Per-frame
    intrinsics override the shared ones. OpenCV distortion (k1, k2, p1, p2) is kept on the
    camera and removed by `load_image`; fisheye models are refused.
    """
    from drsplat.errors import InputError

    meta = _json(path)
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise InputError(path, "has no 'frames' list", field="frames")
    if meta.get("camera_model", "OPENCV") not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        raise InputError(path, f"uses camera_model {meta['camera_model']!r}; only pinhole and OpenCV (k1, k2, p1, p2) are supported; {UNDISTORT_HINT}", field="camera_model")
    root = path.parent
    cameras, missing = [], 0
    for i, frame in enumerate(frames):
        rec = {**meta, **frame}
        where = f" in frame {i}"
        if "file_path" not in frame:
            raise InputError(path, f"frame {i} has no image path", field="file_path")
        image = _resolve_image(root, str(frame["file_path"]))
        if image is None:
            missing += 1
            continue
        try:
            c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
        except (KeyError, TypeError, ValueError):
            raise InputError(path, f"frame {i} has no valid 4x4 matrix", field="transform_matrix") from None
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise InputError(path, f"frame {i} has a transform_matrix of shape {c2w.shape} or with non-finite values", field="transform_matrix")
        if "w" in rec and "h" in rec:
            width, height = int(_number(path, rec, "w", where=where)), int(_number(path, rec, "h", where=where))
        else:
            width, height = _image_size(image)
        if "fl_x" in rec:
            fx = _number(path, rec, "fl_x", where=where)
            fy = _number(path, rec, "fl_y", fx, where=where)
        elif "camera_angle_x" in rec:
            fx = 0.5 * width / np.tan(0.5 * _number(path, rec, "camera_angle_x", where=where))
            fy = 0.5 * height / np.tan(0.5 * rec["camera_angle_y"]) if "camera_angle_y" in rec else fx
        else:
            raise InputError(path, f"gives no focal length{where} (fl_x or camera_angle_x)", field="fl_x")
        cx = _number(path, rec, "cx", width / 2, where=where)
        cy = _number(path, rec, "cy", height / 2, where=where)
        dist = np.array([_number(path, rec, k, 0.0, where=where) for k in ("k1", "k2", "p1", "p2")])
        if any(abs(float(rec.get(k, 0.0) or 0.0)) > 0 for k in ("k3", "k4")):
            raise InputError(path, f"has k3/k4 distortion{where}, which drsplat does not undistort; {UNDISTORT_HINT}", field="k3")
        R, t = c2w_opengl_to_w2c_opencv(c2w)
        cameras.append(Camera(R=R, t=t, fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height, image_path=image,
                              name=image.stem, distortion=dist if np.any(dist != 0) else None))
    return cameras, missing


def read_3dgs_cameras_json(path: Path, images_dir: Path | None) -> tuple[list[Camera], int]:
    """Cameras of a 3DGS `cameras.json` (c2w rotation and position, OpenCV axes, centred principal point)."""
    from drsplat.errors import InputError

    records = _json(path)
    if not isinstance(records, list):
        raise InputError(path, "is not a list of cameras as 3DGS writes it")
    cameras, missing = [], 0
    for i, rec in enumerate(records):
        where = f" in camera {i}"
        try:
            rot = np.asarray(rec["rotation"], dtype=np.float64)
            pos = np.asarray(rec["position"], dtype=np.float64)
            name = str(rec["img_name"])
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(path, f"camera {i} lacks a valid {exc}", field=str(exc).strip("'")) from None
        if rot.shape != (3, 3) or pos.shape != (3,):
            raise InputError(path, f"camera {i} has rotation {rot.shape} / position {pos.shape}", field="rotation")
        width, height = int(_number(path, rec, "width", where=where)), int(_number(path, rec, "height", where=where))
        image = _resolve_image(images_dir, name) if images_dir is not None else None
        if images_dir is not None and image is None:
            missing += 1
            continue
        R = rot.T
        cameras.append(Camera(R=R, t=-R @ pos, fx=_number(path, rec, "fx", where=where), fy=_number(path, rec, "fy", where=where),
                              cx=width / 2, cy=height / 2, width=width, height=height, image_path=image, name=Path(name).stem))
    return cameras, missing


def detect_dataset(source: str | Path) -> tuple[str, Path]:
    """Find the camera description of a dataset folder, as 3DGS's `-s` does.

    Returns (kind, path) with kind in colmap, transforms, cameras_json.
    """
    from drsplat.errors import InputError

    src = Path(source)
    if src.is_file():
        if src.suffix == ".json":
            return ("cameras_json" if src.name == "cameras.json" else "transforms"), src
        raise InputError(src, "is not a dataset folder, transforms.json or cameras.json")
    if not src.is_dir():
        raise InputError(src, "does not exist")
    for sparse in (src / "sparse" / "0", src / "sparse"):
        if (sparse / "cameras.bin").exists() or (sparse / "cameras.txt").exists():
            return "colmap", sparse
    for name in ("transforms_train.json", "transforms.json"):
        if (src / name).exists():
            return "transforms", src / name
    if (src / "cameras.json").exists():
        return "cameras_json", src / "cameras.json"
    raise InputError(src, "has no COLMAP model (sparse/0), transforms.json or cameras.json")


def resolution_scale(width: int, resolution: float) -> float:
    """Image scale factor from a 3DGS-style `-r` value.

    -1: full size, capped at 1600 px wide (3DGS's rule); 1, 2, 4, 8: divide by it;
    any other positive value: the target width in pixels.
    """
    if resolution == -1:
        return min(1.0, 1600.0 / width)
    if resolution in (1, 2, 4, 8):
        return 1.0 / resolution
    if resolution > 0:
        return float(resolution) / width
    raise ValueError(f"resolution must be -1, 1, 2, 4, 8 or a target width, got {resolution}")


def load_cameras(source: str | Path, resolution: float = -1, require_images: bool = True) -> list[Camera]:
    """Training cameras of a dataset (COLMAP, transforms.json or 3DGS cameras.json), OpenCV convention.

    Frames whose image is missing are skipped with one warning that counts them. With
    `resolution` images and intrinsics are scaled together (see `resolution_scale`).
    """
    from drsplat.errors import InputError

    kind, path = detect_dataset(source)
    missing = 0
    if kind == "colmap":
        root = path.parent.parent if path.name == "0" else path.parent
        cameras = cameras_from_colmap(read_colmap_model(path), root / "images", path)
        if require_images:
            present = [c for c in cameras if c.image_path is not None and c.image_path.is_file()]
            missing, cameras = len(cameras) - len(present), present
    elif kind == "transforms":
        cameras, missing = read_transforms_json(path)
        if path.name == "transforms_train.json" and (path.parent / "transforms_test.json").exists():
            log.info("using the training split %s (transforms_test.json is not used for registration)", path)
    else:
        images_dir = path.parent / "images"
        cameras, missing = read_3dgs_cameras_json(path, images_dir if images_dir.is_dir() else None)
    if missing:
        log.warning("%s: %d frame(s) skipped because their image file is missing (%d cameras kept)", path, missing, len(cameras))
    if not cameras:
        raise InputError(path, "yields no usable camera")
    return [c.scaled(resolution_scale(c.width, resolution)) if resolution_scale(c.width, resolution) != 1.0 else c for c in cameras]


def write_transforms_json(cameras: list[Camera], path: str | Path, image_root: str | Path | None = None) -> None:
    """Write cameras as a nerfstudio-style transforms.json (OpenGL c2w, per-frame intrinsics), atomically."""
    import json
    import os

    from drsplat.utils import atomic_path

    path = Path(path)
    root = Path(image_root) if image_root is not None else path.parent
    frames = []
    for cam in cameras:
        frame = {
            "file_path": os.path.relpath(cam.image_path, root) if cam.image_path is not None else f"images/{cam.name}.png",
            "transform_matrix": w2c_opencv_to_c2w_opengl(cam.R, cam.t).tolist(),
            "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy, "w": cam.width, "h": cam.height,
        }
        if cam.distortion is not None:
            frame.update(dict(zip(("k1", "k2", "p1", "p2"), map(float, cam.distortion))))
        frames.append(frame)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps({"camera_model": "OPENCV", "frames": frames}, indent=1))


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """OpenCV radial-tangential distortion of normalised image coordinates.

    xy: [P, 2] undistorted (x/z, y/z); dist: (k1, k2, p1, p2).
    x_d = x·(1 + k1 r² + k2 r⁴) + 2 p1 x y + p2 (r² + 2x²),  y_d = y·(…) + p1 (r² + 2y²) + 2 p2 x y.
    """
    k1, k2, p1, p2 = dist
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def undistort_image(image: np.ndarray, camera: Camera, file_size: tuple[int, int]) -> np.ndarray:
    """Resample a distorted image file onto the camera's pinhole grid (bilinear).

    image: [h, w, C] as stored in the file (size `file_size` = (w, h) at full resolution).
    Each output pixel centre is unprojected with the pinhole intrinsics, distorted, and looked
    up in the file image (intrinsics rescaled to the file's size). Returns [H, W, C].
    """
    from scipy.ndimage import map_coordinates

    fw, fh = file_size
    sx, sy = image.shape[1] / camera.width, image.shape[0] / camera.height
    u, v = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    xy = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy], axis=-1)
    d = distort_normalized(xy, camera.distortion)
    src_u = (d[..., 0] * camera.fx + camera.cx) * sx - 0.5
    src_v = (d[..., 1] * camera.fy + camera.cy) * sy - 0.5
    out = np.empty((camera.height, camera.width, image.shape[2]), dtype=np.float32)
    for c in range(image.shape[2]):
        out[..., c] = map_coordinates(image[..., c].astype(np.float32), [src_v, src_u], order=1, mode="nearest")
    return np.clip(np.rint(out), 0, 255).astype(np.uint8) if image.dtype == np.uint8 else out


def load_image(camera: Camera) -> np.ndarray:
    """[H, W, 3] uint8 RGB training image at the camera's resolution, undistorted if needed."""
    from PIL import Image

    from drsplat.errors import InputError

    if camera.image_path is None:
        raise InputError(None, f"camera {camera.name!r} has no image file")
    try:
        with Image.open(camera.image_path) as im:
            im = im.convert("RGB")
            file_size = im.size
            if camera.distortion is None:
                if im.size != (camera.width, camera.height):
                    im = im.resize((camera.width, camera.height), Image.BICUBIC)
                return np.asarray(im)
            work = np.asarray(im)
    except OSError as exc:
        raise InputError(camera.image_path, f"is not a readable image ({exc})") from None
    return undistort_image(work, camera, file_size)


# ----------------------------------------------------------------------------- look-at cameras


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R [3, 3], t [3]) of a camera at `eye` looking at `target`, OpenCV axes.

    z = (target - eye)/|.|, x = z × up /|.| (right), y = z × x (down); R has rows x, y, z; t = -R eye.
    """
    eye = np.asarray(eye, np.float64)
    z = np.asarray(target, np.float64) - eye
    z /= max(np.linalg.norm(z), 1e-12)
    x = np.cross(z, np.asarray(up, np.float64))
    if np.linalg.norm(x) < 1e-9:  # up parallel to the view direction: pick any perpendicular
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


def look_at_camera(
    eye, target, width: int, height: int, fov_x_deg: float = 60.0, up=(0.0, -1.0, 0.0),
    cx: float | None = None, cy: float | None = None, name: str = "",
) -> Camera:
    """An OpenCV pinhole camera at `eye` looking at `target` (pose from `look_at`; image y points along -up).

    fx = fy = (width / 2) / tan(fov_x / 2); the principal point defaults to the image centre.
    """
    R, t = look_at(eye, target, up)
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    return Camera(
        R=R, t=t, fx=fx, fy=fx, cx=width / 2 if cx is None else cx, cy=height / 2 if cy is None else cy,
        width=width, height=height, name=name,
    )

