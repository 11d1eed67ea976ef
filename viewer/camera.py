"""Interactive view cameras: orbit and fly controllers that produce `drsplat.cameras.Camera`s.

Both modes share one pose (eye, target, up): orbit turns the eye around the target, fly turns the
target around the eye. The renderer only ever sees OpenCV cameras (x right, y down, z forward,
x_cam = R x_world + t), the same records the training cameras and drsplat.raster use.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from drsplat.cameras import Camera, look_at

POLE_MARGIN = math.radians(3)  # how close pitch may bring the view direction to the up axis


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """[3, 3] rotation by `angle` radians about `axis` (Rodrigues)."""
    a = np.asarray(axis, np.float64)
    a = a / max(np.linalg.norm(a), 1e-12)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


UP_AXES = {
    "auto": None,  # the training cameras' mean up vector, else a guess from the scene's shape
    "+Y": (0.0, 1.0, 0.0),
    "-Y": (0.0, -1.0, 0.0),
    "+Z": (0.0, 0.0, 1.0),
    "-Z": (0.0, 0.0, -1.0),
    "+X": (1.0, 0.0, 0.0),
    "-X": (-1.0, 0.0, 0.0),
}


def intrinsics_for(width: int, height: int, fov_y_deg: float) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a centred pinhole camera with vertical field of view fov_y_deg."""
    fy = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
    return fy, fy, width / 2, height / 2


NEAR_PLANE = 0.01  # the renderer's near plane for a scene of robust radius 1 or more (gsplat's, drsplat.raster's NEAR)
MIN_RADIUS = 1e-12  # a scene's radius at least this (every Gaussian at one point, with no size)
NEAR_SAMPLE = 1 << 20  # rows `scene_near_plane` reads at most


@dataclass
class ViewController:
    """The interactive camera: pose (eye, target, up), mode 'orbit' or 'fly', and a viewport.

    Mouse deltas are in pixels; `rotate` turns by `rotate_speed` radians per pixel.
    """

    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray
    width: int = 1280
    height: int = 720
    fov_y_deg: float = 60.0
    mode: str = "orbit"
    rotate_speed: float = 0.005
    roll: float = 0.0  # radians about the view direction, applied after look_at
    auto_up: np.ndarray | None = field(default=None, repr=False)
    home: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    home_fov: float | None = field(default=None, repr=False)
    near: float = NEAR_PLANE  # the renderer's near plane (`scene_near_plane`): orbit zoom stops twice as far from the target

    def __post_init__(self) -> None:
        self.eye = np.asarray(self.eye, np.float64)
        self.target = np.asarray(self.target, np.float64)
        self.up = np.asarray(self.up, np.float64) / max(np.linalg.norm(self.up), 1e-12)
        if self.home is None:
            self.home = (self.eye.copy(), self.target.copy(), self.up.copy())
        if self.home_fov is None:
            self.home_fov = self.fov_y_deg

    @classmethod
    def for_scene(cls, means: np.ndarray, cameras: list[Camera] | None = None, width: int = 1280, height: int = 720,
                  log_scales: np.ndarray | None = None) -> "ViewController":
        """A home view: the first training camera's pose when there are cameras, else the scene from outside.

        means: [N, 3]. Without cameras, up is taken as +z if the scene is flatter along z, else -y
        (the COLMAP habit), and the eye sits at 2.2 robust radii from the centre. log_scales [N, 3]:
        the radius is at least 3 typical Gaussian sizes (one Gaussian, or all at one point, is seen
        whole rather than from inside, in front of the near plane).
        """
        near = scene_near_plane(means, log_scales)
        if cameras:
            view = cls(eye=np.zeros(3), target=np.array([0.0, 0.0, 1.0]), up=np.array([0.0, -1.0, 0.0]), width=width, height=height,
                       near=near)
            view.snap_to(cameras[0], scene_center=_robust_center(means))
            view.up = _mean_up(cameras)
            view.auto_up = view.up.copy()
            view.home = (view.eye.copy(), view.target.copy(), view.up.copy())
            view.home_fov = view.fov_y_deg
            return view
        center = _robust_center(means)
        radius = _robust_radius(means, center, log_scales)
        up = np.array([0.0, 0.0, 1.0])
        if means.shape[0] > 0:
            wide = means.astype(np.float64)  # float32 means near 3e38 overflow the difference
            spread = np.percentile(wide, 95, axis=0) - np.percentile(wide, 5, axis=0)
            up = np.array([0.0, 0.0, 1.0]) if spread[2] < 0.8 * max(spread[0], spread[1]) else np.array([0.0, -1.0, 0.0])
        side = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        offset = (np.cross(up, side) * 0.8 + side * 0.6 + up * 0.7)
        eye = center + 2.2 * radius * offset / np.linalg.norm(offset)
        return cls(eye=eye, target=center, up=up, width=width, height=height, auto_up=up.copy(), near=near)

    @property
    def distance(self) -> float:
        return float(np.linalg.norm(self.target - self.eye))

    @property
    def forward(self) -> np.ndarray:
        return (self.target - self.eye) / max(self.distance, 1e-12)

    def camera(self) -> Camera:
        """The current view as an OpenCV `Camera` of the viewport size."""
        R, t = look_at(self.eye, self.target, self.up)
        if self.roll:
            roll = rotation_about(np.array([0.0, 0.0, 1.0]), self.roll)
            R, t = roll @ R, roll @ t
        fx, fy, cx, cy = intrinsics_for(self.width, self.height, self.fov_y_deg)
        return Camera(R=R, t=t, fx=fx, fy=fy, cx=cx, cy=cy, width=self.width, height=self.height, name="view")

    def set_up_axis(self, name: str, cameras: list[Camera] | None = None) -> None:
        """World up for orbiting and the horizon: one of UP_AXES; "auto" is the training cameras'
        mean up vector (-mean of their y axes) when there are cameras, else the home guess."""
        if name not in UP_AXES:
            raise ValueError(f"unknown up axis {name!r}; expected one of {', '.join(UP_AXES)}")
        if UP_AXES[name] is not None:
            up = np.asarray(UP_AXES[name], np.float64)
        elif cameras:
            up = _mean_up(cameras)
        else:
            up = self.auto_up if self.auto_up is not None else self.up
        self.up = up / np.linalg.norm(up)
        self.roll = 0.0
        if self.home is not None:
            self.home = (self.home[0], self.home[1], self.up.copy())

    def set_roll(self, radians: float) -> None:
        self.roll = float(radians)

    def resize(self, width: int, height: int) -> None:
        self.width, self.height = max(1, int(width)), max(1, int(height))

    def rotate(self, dx: float, dy: float) -> None:
        """Mouse drag: yaw about the world up axis by dx, pitch about the camera right axis by dy.

        Orbit mode moves the eye around the target; fly mode turns the target around the eye.
        Pitch stops POLE_MARGIN short of the poles: the turned direction's angle to the up axis,
        φ ∈ [0, π], moves by the pitch angle toward the nearer pole only as far as φ = POLE_MARGIN
        (or π - POLE_MARGIN), and freely away from it, so a view that starts within the margin (a
        top-down training camera, an up axis changed under the view) can always be dragged out,
        and one fast drag cannot carry the view over the pole. At a pole the right axis is the
        camera's own (`look_at`'s), so a drag there still turns the view.
        """
        yaw = rotation_about(self.up, -dx * self.rotate_speed)
        offset = self.eye - self.target if self.mode == "orbit" else self.target - self.eye
        offset = yaw @ offset
        axis = yaw @ self._pitch_axis()
        pitch_angle = (dy if self.mode == "orbit" else -dy) * self.rotate_speed
        if pitch_angle:
            offset = rotation_about(axis, self._allowed_pitch(offset, axis, pitch_angle)) @ offset
        if self.mode == "orbit":
            self.eye = self.target + offset
        else:
            self.target = self.eye + offset

    def _pitch_axis(self) -> np.ndarray:
        """[3] the horizontal axis pitch turns about: forward × up, or the camera's right axis where
        the view looks along up (their cross product vanishes there)."""
        right = np.cross(self.forward, self.up)
        if np.linalg.norm(right) < 1e-9:
            right = look_at(self.eye, self.target, self.up)[0][0]
        return right

    def _allowed_pitch(self, offset: np.ndarray, axis: np.ndarray, angle: float) -> float:
        """The part of a pitch by `angle` radians about `axis` (horizontal, across `offset`) that
        keeps offset's angle to up, φ, within [POLE_MARGIN, π - POLE_MARGIN] where it moves toward
        a pole: about such an axis φ moves by exactly |angle| until it reaches a pole."""
        polar = self._polar(offset)
        toward = self._polar(rotation_about(axis, math.copysign(1e-6, angle)) @ offset) - polar  # the sign of dφ for this turn
        if polar < 1e-9 or polar > math.pi - 1e-9:  # at a pole every turn moves away from it
            return angle
        step = abs(angle)
        if toward < 0:
            step = min(step, max(polar - POLE_MARGIN, 0.0))
        else:
            step = min(step, max(math.pi - POLE_MARGIN - polar, 0.0))
        return math.copysign(step, angle)

    def _polar(self, v: np.ndarray) -> float:
        """φ: the angle between v [3] and the up axis, in [0, π]."""
        return math.acos(float(np.clip(v @ self.up / max(np.linalg.norm(v), 1e-300), -1.0, 1.0)))

    def pan(self, dx: float, dy: float) -> None:
        """Move eye and target together in the image plane, dx, dy in pixels at the target depth."""
        R = self.camera().R
        per_pixel = self.distance * 2 * math.tan(math.radians(self.fov_y_deg) / 2) / self.height
        shift = (-dx * R[0] - dy * R[1]) * per_pixel
        self.eye = self.eye + shift
        self.target = self.target + shift

    def zoom(self, steps: float) -> None:
        """Scroll: orbit mode scales the distance to the target by 0.9 per step, down to twice the near plane (the target
        stays drawn; a view already nearer is not pushed out); fly mode moves forward."""
        if self.mode == "orbit":
            new_distance = max(self.distance * 0.9**steps, min(self.distance, 2.0 * self.near))
            self.eye = self.target - self.forward * new_distance
        else:
            self.move(np.array([0.0, 0.0, steps * 0.1 * self.distance]))

    def move(self, delta_cam: np.ndarray) -> None:
        """Fly: translate eye and target by delta_cam [3] in camera axes (x right, y down, z forward)."""
        R = self.camera().R
        shift = R.T @ np.asarray(delta_cam, np.float64)
        self.eye = self.eye + shift
        self.target = self.target + shift

    def snap_to(self, camera: Camera, scene_center: np.ndarray | None = None) -> None:
        """Take a training camera's pose (its roll included) and vertical field of view; the orbit target at the scene
        centre's depth, at least twice the near plane (a fixed 1e-3 put it 300 radii behind a scene of 1e-6, which one
        zoom step then left: round 72a F3)."""
        R = np.asarray(camera.R, np.float64)
        center = camera.center
        distance = 1.0
        if scene_center is not None:
            distance = max(float((np.asarray(scene_center) - center) @ R[2]), 2.0 * self.near)
        self.eye = center
        self.target = center + R[2] * distance
        self.up = -R[1]
        self.roll = 0.0
        self.fov_y_deg = math.degrees(2 * math.atan(0.5 * camera.height / camera.fy))

    @property
    def at_home(self) -> bool:
        """True while the view is its home view: nobody has moved it, turned it to fly mode or changed its field of view."""
        assert self.home is not None
        return (self.roll == 0.0 and self.mode == "orbit" and self.fov_y_deg == self.home_fov
                and all(np.array_equal(a, b) for a, b in zip((self.eye, self.target, self.up), self.home)))

    def reset(self) -> None:
        assert self.home is not None
        self.eye, self.target, self.up = (a.copy() for a in self.home)
        self.roll = 0.0


def frustum_segments(cameras: list[Camera], depth: float) -> np.ndarray:
    """[C * 8, 2, 3] world-space segments drawing each camera's frustum: 4 edges from its centre to
    its image corners at `depth` along the view axis, and the 4 edges of that image rectangle."""
    segments = []
    for cam in cameras:
        R = np.asarray(cam.R, np.float64)
        c = cam.center
        corners = [c + R.T @ (np.array([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0]) * depth)
                   for u, v in ((0, 0), (cam.width, 0), (cam.width, cam.height), (0, cam.height))]
        for k in range(4):
            segments += [(c, corners[k]), (corners[k], corners[(k + 1) % 4])]
    return np.asarray(segments, np.float64).reshape(-1, 2, 3)


def project_segments(camera: Camera, segments: np.ndarray, near: float = 1e-3) -> np.ndarray:
    """[S, 2, 3] world segments -> [K, 2, 2] pixel segments of `camera`, clipped at depth `near`
    (a segment wholly behind the camera is dropped)."""
    R, t = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64)
    p = segments @ R.T + t  # [S, 2, 3] camera coordinates
    z0, z1 = p[:, 0, 2], p[:, 1, 2]
    keep = (z0 > near) | (z1 > near)
    p, z0, z1 = p[keep], z0[keep], z1[keep]
    a = _onto_near_plane(p[:, 0], p[:, 1], near)
    b = _onto_near_plane(p[:, 1], p[:, 0], near)
    ends = np.stack([a, b], axis=1)
    uv = ends[..., :2] / ends[..., 2:3] * np.array([camera.fx, camera.fy]) + np.array([camera.cx, camera.cy])
    return uv


def camera_for_size(camera: Camera, width: int | None, height: int | None) -> Camera:
    """A training camera resized to width x height (keeping its aspect if only one is given)."""
    if width is None and height is None:
        return camera
    if width is None:
        width = int(round(camera.width * height / camera.height))
    if height is None:
        height = int(round(camera.height * width / camera.width))
    sx, sy = width / camera.width, height / camera.height
    return dataclasses.replace(camera, fx=camera.fx * sx, fy=camera.fy * sy, cx=camera.cx * sx, cy=camera.cy * sy, width=width, height=height)


def _onto_near_plane(p: np.ndarray, other: np.ndarray, near: float) -> np.ndarray:
    """[S, 3] endpoints p, those behind depth `near` moved along the segment to it (other in front)."""
    behind = p[:, 2] < near
    dz = other[:, 2] - p[:, 2]
    s = np.clip((near - p[:, 2]) / np.where(behind, dz, 1.0), 0.0, 1.0)[:, None]
    return np.where(behind[:, None], p + s * (other - p), p)


def _robust_center(means: np.ndarray) -> np.ndarray:
    if means.shape[0] == 0:
        return np.zeros(3)
    return np.median(means.astype(np.float64), axis=0)


def scene_near_plane(means: np.ndarray, log_scales: np.ndarray | None = None) -> float:
    """The renderer's near plane for a scene: NEAR_PLANE, or that share of its robust radius below radius 1. A fixed
    0.01 cut a scene 2 cm across (in metres) as soon as it was looked at closely, and hid one of 1e-6 whatever the zoom
    (round 71b F2). means: [N, 3]; log_scales: [N, 3] or None (`_robust_radius`), read at every k-th row, at most NEAR_SAMPLE
    rows (a scale, not a boundary: the sort of 50M distances took seconds)."""
    step = max(1, -(-means.shape[0] // NEAR_SAMPLE))  # rounded up: at most NEAR_SAMPLE rows (round 74c F2)
    sample = means[::step]
    return NEAR_PLANE * min(1.0, _robust_radius(sample, _robust_center(sample), None if log_scales is None else log_scales[::step]))


def _robust_radius(means: np.ndarray, center: np.ndarray, log_scales: np.ndarray | None = None) -> float:
    if means.shape[0] == 0:
        return 1.0
    d = np.linalg.norm(means - center, axis=1)
    radius = float(np.percentile(d, 90))
    if log_scales is not None and len(log_scales):
        largest = np.asarray(log_scales, np.float64).max(axis=1)
        largest = largest[np.isfinite(largest)]
        if largest.size:  # 3 sigma of the median Gaussian (exp capped: no float overflow)
            radius = max(radius, 3.0 * float(np.exp(min(float(np.median(largest)), 80.0))))
    return max(radius, MIN_RADIUS)


def _mean_up(cameras: list[Camera]) -> np.ndarray:
    up = -np.mean([np.asarray(c.R)[1] for c in cameras], axis=0)
    norm = np.linalg.norm(up)
    return up / norm if norm > 1e-6 else -np.asarray(cameras[0].R)[1]
