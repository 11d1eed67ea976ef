"""Feature extraction on a Ray cluster: `extract_features` with the images spread over actors.

One actor per worker loads the mask generator and CLIP once (on a GPU of its own when the device
is CUDA: one actor per GPU that has a CPU beside it on its node, never more, so none waits forever
for a slot; a cluster without GPUs is refused up front); every actor is checked to have started
before any image is sent, so a worker that cannot load its models (no usable GPU on its node) is
one error, not a wait. The driver sends images and writes the returned `<stem>_s.npy` /
`<stem>_f.npy` atomically itself, so a dead worker (actor restarted, call retried) leaves no half
or duplicate file, and complete pairs already on disk are skipped. A worker whose node is lost
has its image sent to another worker (`_results_as_they_come`). A worker that is never placed (the
cluster's CPUs taken by other work) is still waited for, unlike registration's.
"""

from __future__ import annotations

import logging
import socket
from collections.abc import Callable
from pathlib import Path

import numpy as np

from drsplat.cameras import load_image_sized
from drsplat.cluster import TASK_RETRIES, WAIT_SECONDS, connect, import_ray, set_worker_threads, worker_slots
from drsplat.errors import DrsplatError
from drsplat.features import format as featurefiles
from drsplat.features.extract import (
    IMAGE_STAMPS,
    FeatureReport,
    ImageStamps,
    build_models,
    check_manifest_compatible,
    extract_image,
    make_manifest,
    note_image,
    record_result,
    todo_cameras,
)
from drsplat.utils import CancelToken, file_stamp, progress

log = logging.getLogger(__name__)


def actor_count(nodes: list[dict], gpus_per_actor: int, workers: int | None, address: str | None) -> int:
    """Actors to start: `workers`, or one per worker slot (drsplat.cluster.worker_slots: a CPU, and
    a GPU on the same node when each actor needs one), never more than the slots (the others would
    wait for one forever). nodes: ray.nodes()."""
    slots = worker_slots(nodes, gpus_per_actor)
    if gpus_per_actor and slots == 0:
        raise DrsplatError(f"features on --device cuda need GPUs, but the Ray cluster at {address or 'a local instance'} has none; use --device cpu")
    if workers and workers > slots:
        log.warning("Ray: %d feature workers asked for, but the cluster fits %d%s; using %d", workers, slots,
                    " (one per GPU)" if gpus_per_actor else "", slots)
    return max(1, min(int(workers or slots), slots))


class _FeatureWorker:
    """Ray actor: one model load per worker, then one image per call. A worker that cannot load its
    models keeps the error and reports it (`start_error`) instead of dying, so the driver says why."""

    def __init__(self, spec) -> None:
        set_worker_threads()
        try:
            self.generator, self.encoder = build_models(spec)
        except DrsplatError as exc:
            self.error = f"{exc} (Ray node {socket.gethostname()})"
        else:
            self.error = None
        self.nms = spec.nms

    def start_error(self) -> str | None:
        return self.error

    def manifest(self, resolution: float, max_height: int | None, extra: dict | None) -> dict:
        return make_manifest(self.generator, self.encoder, self.nms, resolution, max_height, extra)

    def extract(self, stem: str, image: np.ndarray):
        seg, feats, times, counts = extract_image(image, self.generator, self.encoder, self.nms)
        return stem, seg, feats, times, counts


def _check_started(actors: list) -> None:
    """One DrsplatError when any actor could not load its models (e.g. a GPU Ray declared that torch cannot use)."""
    ray = import_ray()
    try:
        errors = [e for e in ray.get([a.start_error.remote() for a in actors]) if e is not None]
    except ray.exceptions.RayError as exc:
        raise DrsplatError(f"a Ray feature worker could not start: {exc}") from None
    if errors:
        raise DrsplatError(f"{len(errors)} of {len(actors)} Ray feature workers could not load their models: {errors[0]}")




def _results_as_they_come(ray, actors: list, cameras: list, send: Callable, cancel: CancelToken | None):
    """Each camera's extract result, in the order they finish: one call queued per actor (`send(actor,
    camera)` reads the image and submits it). A call whose actor became unavailable (its node lost:
    Ray does not retry those, and an actor restarted with no CPU to run on would be waited for
    forever) goes to another actor, at most TASK_RETRIES times, and the lost actor is given up; a
    cancel is seen within WAIT_SECONDS."""
    todo = list(cameras)
    live = list(actors)
    busy: dict = {}  # ref -> (camera, actor)
    tries: dict[str, int] = {}
    while todo or busy:
        for a in [a for a in live if all(owner is not a for _, owner in busy.values())]:
            if not todo:
                break
            cam = todo.pop(0)
            busy[send(a, cam)] = (cam, a)
        ready, _ = ray.wait(list(busy), num_returns=1, timeout=WAIT_SECONDS)
        if cancel is not None and cancel.cancelled:
            for a in live:
                ray.kill(a)
            cancel.raise_if_cancelled()
        for ref in ready:
            cam, actor = busy.pop(ref)
            try:
                result = ray.get(ref)
            except ray.exceptions.RayTaskError as exc:
                raise exc.as_instanceof_cause() from None
            except ray.exceptions.ActorUnavailableError:
                tries[cam.name] = tries.get(cam.name, 0) + 1
                if tries[cam.name] > TASK_RETRIES:
                    raise DrsplatError(f"image {cam.name} found no available Ray feature worker in {TASK_RETRIES + 1} tries") from None
                todo.insert(0, cam)
                if actor in live:
                    live.remove(actor)
                    ray.kill(actor, no_restart=True)
                if not live:
                    raise DrsplatError("every Ray feature worker was lost (their nodes became unavailable); the images written so "
                                       "far are kept: rerun to skip them") from None
                log.warning("Ray: a feature worker was lost (its node became unavailable); its image goes to the %d other worker(s)", len(live))
                continue
            except ray.exceptions.RayError as exc:
                raise DrsplatError(f"a Ray feature worker failed after {TASK_RETRIES} retries: {exc}") from None
            yield result


def extract_features_ray(
    cameras: list,
    out_dir: str | Path,
    spec,
    *,
    address: str | None = None,
    workers: int | None = None,
    resolution: float = -1,
    max_height: int | None = None,
    manifest_extra: dict | None = None,
    show_progress: bool = True,
    on_progress: Callable[[int, int], None] | None = None,
    cancel: CancelToken | None = None,
):
    """`extract_features` with the images spread over Ray actors (same files; see the module docstring).

    spec: drsplat.features.extract.ModelSpec (how each worker builds its models). Returns the
    FeatureReport. GPU workers (spec.device == "cuda") each request one GPU.
    """
    ray = import_ray()
    out = Path(out_dir)
    owns = connect(address)
    actors: list = []
    try:
        gpus = 1 if spec.device == "cuda" else 0
        count = actor_count(ray.nodes(), gpus, workers, address)
        actor = ray.remote(num_cpus=1, num_gpus=gpus, max_restarts=-1, max_task_retries=TASK_RETRIES)(_FeatureWorker)
        actors = [actor.remote(spec) for _ in range(count)]
        log.info("features on %d Ray actor(s)%s", count, " (one per GPU)" if gpus else "")
        _check_started(actors)
        manifest = ray.get(actors[0].manifest.remote(resolution, max_height, manifest_extra))
        stamps = ImageStamps.read(out)
        check_manifest_compatible(out, manifest)
        out.mkdir(parents=True, exist_ok=True)
        featurefiles.write_manifest(out, {**manifest, IMAGE_STAMPS: stamps.known})
        stamps.tracked = True
        report = FeatureReport()
        todo = todo_cameras(cameras, out, report, stamps)
        read_at: dict[str, str | None] = {}  # each image as it was read, not as it may be when its pair comes back

        def send(a, c):
            read_at[c.name] = file_stamp(c.image_path)
            rgb, file_size = load_image_sized(c)
            note_image(report, c, rgb, file_size)
            return a.extract.remote(c.name, rgb)

        results = _results_as_they_come(ray, actors, todo, send, cancel)
        finished = len(report.skipped)
        if on_progress is not None:
            on_progress(finished, len(cameras))
        for _ in progress(range(len(todo)), desc="features", total=len(todo), enabled=show_progress, unit="img"):
            stem, seg, feats, times, counts = next(results)
            record_result(out, stem, seg, feats, times, counts, report)
            stamps.add(stem, read_at.get(stem))
            finished += 1
            if on_progress is not None:
                on_progress(finished, len(cameras))
        stamps.finish(manifest, len(report.written) + len(report.skipped))
        report.workers = count
        return report
    finally:
        for a in actors:  # their models and GPUs go back to the cluster now, not when this driver exits
            ray.kill(a, no_restart=True)
        if owns:
            ray.shutdown()
