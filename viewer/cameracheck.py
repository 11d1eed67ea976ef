"""The training cameras' checks against the open scene on a worker thread.

`drsplat.frames.cameras_and_plane_as_trained` decides the cameras' frame, the near plane registration renders at and
the principal points, by rendering views of the scene: 2-3 s on a 542k-Gaussian scene, longer on bigger ones, during which the window did not redraw. `ViewerState.load_source(..., background=True)` runs it here and takes the
cameras when it ends (`ViewerState.poll_camera_check`).

One check renders at a time: a check that replaces another cancels it (it stops at its next
step) and waits for it to end. A check's warnings are kept with it and shown only when its
cameras are taken, so a replaced check says nothing (round 56c: six quick opens of one folder
rendered six checks at once and logged six warnings, and a check of a closed scene warned about
it after the next scene opened).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np

from drsplat._scene_kernels import bounded_rows_kernel
from drsplat.cameras import Camera
from drsplat.errors import Cancelled
from drsplat.defaults import NEAR
from drsplat.frames import cameras_and_plane_as_trained
from drsplat.scene import GaussianScene
from drsplat.utils import CancelToken
from viewer.messages import LibraryWarnings, MessageLog

log = logging.getLogger(__name__)


@dataclass
class CameraCheck:
    """One check of the cameras of `source` against the scene of `scene_version`: its outcome (cameras or
    error) and the warnings it gave (`messages`, shown when its cameras are taken)."""

    source: Path
    scene_version: int
    given: list[Camera] = field(default_factory=list)  # as read from the dataset: the files they name are inputs meanwhile
    thread: threading.Thread | None = None
    cancel: CancelToken = field(default_factory=CancelToken)
    messages: MessageLog = field(default_factory=MessageLog)
    cameras: list[Camera] = field(default_factory=list)
    near_plane: float = NEAR  # the plane the scene was drawn at while training, for the cameras (`near_plane_as_trained`)
    error: BaseException | None = None
    finished: bool = False
    reported: bool = False

    def stop(self) -> None:
        """Cancel the check: it ends at its next step, its cameras and warnings unused."""
        self.cancel.cancel()


def concurrent_kernels_safe() -> bool:
    """Whether numba's threading layer lets a worker thread run parallel kernels while the window's thread runs
    others (omp and tbb do; workqueue, numba's fallback where neither is installed, ends the process on
    "Concurrent access": round 56c). Asked after one parallel kernel has run, which makes numba pick its layer."""
    bounded_rows_kernel(np.zeros((1, 1)), 1.0, False, np.ones(1, bool))
    return numba.threading_layer() in ("omp", "tbb")


@dataclass(frozen=True)
class TrainedCameras:
    """The training cameras as their scene was trained with them, and the near plane it was drawn at (`checked_cameras`)."""

    cameras: list[Camera]
    near_plane: float


def checked_cameras(scene: GaussianScene, cameras: list[Camera], source: Path, scene_path: Path | None,
                    refinements: np.ndarray | None, cancel: CancelToken | None = None) -> TrainedCameras:
    """The viewer's reading of the training cameras, as `register` reads them by default: the principal points and
    the near plane decided by the scene and its images (`cameras_and_plane_as_trained`, "auto" for both), the warnings
    naming the scene file."""
    what = scene_path.name if scene_path is not None else "the scene"
    cameras, plane = cameras_and_plane_as_trained(scene, cameras, source, what=what, scene_path=scene_path, refinements=refinements,
                                                  cancel=cancel)
    return TrainedCameras(cameras, plane)


def run_camera_check(check: CameraCheck, scene: GaussianScene, scene_path: Path | None, refinements: np.ndarray | None,
                     previous: CameraCheck | None) -> None:
    """The check's body, after `previous` (stopped by its caller) has ended: its warnings go to check.messages; a
    failure ends up in check.error, a cancellation in neither."""
    try:
        if previous is not None and previous.thread is not None:
            previous.thread.join()
        check.cancel.raise_if_cancelled()
        with LibraryWarnings(check.messages):
            trained = checked_cameras(scene, check.given, check.source, scene_path, refinements, check.cancel)
            check.cameras, check.near_plane = trained.cameras, trained.near_plane
    except Cancelled:
        pass
    except BaseException as exc:  # noqa: BLE001 - reported in the GUI by ViewerState.poll_camera_check
        check.error = exc
        log.debug("camera check failed", exc_info=True)
    finally:
        check.finished = True


def start_camera_check(scene: GaussianScene, cameras: list[Camera], source: Path, scene_path: Path | None,
                       refinements: np.ndarray | None, scene_version: int, previous: CameraCheck | None = None) -> CameraCheck:
    """A check of `cameras` on a worker thread; `previous`, a check it replaces, is stopped and waited for first."""
    if previous is not None:
        previous.stop()
    check = CameraCheck(source=Path(source), scene_version=scene_version, given=list(cameras))
    check.thread = threading.Thread(target=run_camera_check, args=(check, scene, scene_path, refinements, previous),
                                    name="camera-check", daemon=True)
    check.thread.start()
    return check
