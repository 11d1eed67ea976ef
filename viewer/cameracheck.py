"""The training cameras' checks against the open scene on a worker thread.

`drsplat.frames.cameras_as_trained` decides the cameras' frame and principal points by rendering
views of the scene: 2-3 s on a 542k-Gaussian scene, longer on bigger ones, during which the
window did not redraw. `ViewerState.load_source(..., background=True)` runs it here and takes the
cameras when it ends (`ViewerState.poll_camera_check`)."""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drsplat.cameras import Camera
from drsplat.frames import cameras_as_trained
from drsplat.scene import GaussianScene
from viewer.messages import LibraryWarnings, MessageLog

log = logging.getLogger(__name__)


@dataclass
class CameraCheck:
    """One check of the cameras of `source` against the scene of `scene_version`: its outcome (cameras or error)."""

    source: Path
    scene_version: int
    given: list[Camera] = field(default_factory=list)  # as read from the dataset: the files they name are inputs meanwhile
    thread: threading.Thread | None = None
    cameras: list[Camera] = field(default_factory=list)
    error: BaseException | None = None
    finished: bool = False
    reported: bool = False


def checked_cameras(scene: GaussianScene, cameras: list[Camera], source: Path, scene_path: Path | None,
                    refinements: np.ndarray | None) -> list[Camera]:
    """The viewer's reading of the training cameras: `cameras_as_trained` with the principal point
    decided by the scene ("auto"), the warnings naming the scene file."""
    what = scene_path.name if scene_path is not None else "the scene"
    return cameras_as_trained(scene, cameras, source, what=what, scene_path=scene_path, refinements=refinements)


def run_camera_check(check: CameraCheck, scene: GaussianScene, cameras: list[Camera], scene_path: Path | None,
                     refinements: np.ndarray | None, messages: MessageLog) -> None:
    """The check's body: its warnings go to `messages` (the window's log); any failure ends up in check.error."""
    try:
        with LibraryWarnings(messages):
            check.cameras = checked_cameras(scene, cameras, check.source, scene_path, refinements)
    except BaseException as exc:  # noqa: BLE001 - reported in the GUI by ViewerState.poll_camera_check
        check.error = exc
        log.debug("camera check failed", exc_info=True)
    finally:
        check.finished = True


def start_camera_check(scene: GaussianScene, cameras: list[Camera], source: Path, scene_path: Path | None,
                       refinements: np.ndarray | None, scene_version: int, messages: MessageLog) -> CameraCheck:
    check = CameraCheck(source=Path(source), scene_version=scene_version, given=list(cameras))
    check.thread = threading.Thread(target=run_camera_check, args=(check, scene, check.given, scene_path, refinements, messages),
                                    name="camera-check", daemon=True)
    check.thread.start()
    return check
