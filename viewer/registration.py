"""Registration started from the viewer: a job on a worker thread running drsplat.registration.register
(the same pipeline as `drsplat register`), with progress, cancel and its outcome."""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path

from drsplat.cameras import Camera
from drsplat.registration import RegisterOptions, register
from drsplat.scene import GaussianScene
from drsplat.utils import CancelToken
from viewer.messages import LibraryWarnings, MessageLog

log = logging.getLogger(__name__)


@dataclass
class RegistrationJob:
    """A registration running on a worker thread: progress (done, total), cancel, outcome."""

    output: Path
    thread: threading.Thread | None = None
    cancel: CancelToken | None = None
    done: int = 0
    total: int = 0
    finished: bool = False
    reported: bool = False
    error: str | None = None
    scene_version: int | None = None  # ViewerState.scene_version when it started: its output opens only over that scene
    messages: MessageLog = field(default_factory=MessageLog)  # the library's warnings on the job's thread, shown when it ends

    @property
    def fraction(self) -> float:
        return self.done / self.total if self.total else 0.0

    @property
    def running(self) -> bool:
        return not self.finished


def run_registration(job: RegistrationJob, scene: GaussianScene, cameras: list[Camera], features_dir: Path, options: RegisterOptions) -> None:
    """The job's body: register, write job.output atomically; errors and cancellation end up in job.error."""
    try:
        # what the run warns of (a checkpoint kept or started over, images unlike the scene) reached only the terminal (round 61a)
        with LibraryWarnings(job.messages):
            register(scene, cameras, features_dir, job.output, options, show_progress=False, on_progress=lambda d, t: _progress(job, d, t),
                     cancel=job.cancel)
    except BaseException as exc:  # noqa: BLE001 - reported in the GUI
        job.error = str(exc) or type(exc).__name__
        log.debug("registration failed", exc_info=True)
    finally:
        job.finished = True


def start_job(output: Path, scene: GaussianScene, cameras: list[Camera], features_dir: Path, options: RegisterOptions, background: bool = True) -> RegistrationJob:
    job = RegistrationJob(output=Path(output), cancel=CancelToken())
    args = (job, scene, list(cameras), Path(features_dir), options)
    if background:
        job.thread = threading.Thread(target=run_registration, args=args, name="registration", daemon=True)
        job.thread.start()
    else:
        run_registration(*args)
    return job


def _progress(job: RegistrationJob, done: int, total: int) -> None:
    job.done, job.total = done, total
