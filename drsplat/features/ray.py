"""Feature extraction on a Ray cluster: `extract_features` with the images spread over actors.

One actor per worker loads the mask generator and CLIP once (on a GPU of its own when the device
is CUDA: one actor per GPU that has a CPU beside it on its node, never more, so none waits forever
for a slot; a cluster without GPUs is refused up front); every actor is checked to have started
before any image is sent, so a worker that cannot load its models (no usable GPU on its node) is
one error, not a wait; each makes the folder's manifest as it loads (two that differ in what shapes
the features are one error). The driver sends images and writes the returned `<stem>_s.npy` /
`<stem>_f.npy` atomically itself, so a dead worker (actor restarted, call retried) leaves no half
or duplicate file, and complete pairs already on disk are skipped. A worker whose node is lost
has its image sent to another worker (`_results_as_they_come`); so has a worker never placed (the
cluster's CPUs taken by other work) or stalled while the others progress, by registration's rule
(drsplat.cluster.stalled), and a cluster where no worker starts is one error after STALL_SECONDS.
"""

from __future__ import annotations

import dataclasses
import logging
import socket
import time
from collections.abc import Callable
from typing import Any
from pathlib import Path

import numpy as np

from drsplat.cameras import load_image_sized, unobserved_pixels
from drsplat.cluster import (TASK_RETRIES, WAIT_SECONDS, check_nodes_run_this_code, connect, disconnect, import_ray, kill_if_cancelled, placed_actors,
                             set_worker_threads, stalled, worker_slots)
from drsplat.errors import DrsplatError
from drsplat.features import format as featurefiles
from drsplat.features.extract import (
    IMAGE_STAMPS,
    RESUME_KEYS,
    FeatureReport,
    ImageStamps,
    build_models,
    check_manifest_compatible,
    extract_image,
    make_manifest,
    note_image,
    pair_stamp,
    record_result,
    todo_cameras,
)
from drsplat.utils import CancelToken, progress

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
    """Ray actor: one model load per worker (its first `load` or `extract`, so a restarted worker loads
    again), then one image per call. Its constructor is cheap, so `ready` answers as soon as the
    worker is placed: the driver tells a worker never placed from one loading its models. A worker
    that cannot load its models keeps the error and reports it (`load`) instead of dying, so the
    driver says why."""

    def __init__(self, spec) -> None:
        set_worker_threads()
        self.spec = spec
        self.nms = spec.nms
        self.models = None
        self.error: str | None = None

    def ready(self) -> str:
        return socket.gethostname()

    def _models(self):
        if self.models is None and self.error is None:
            try:
                self.models = build_models(self.spec)
            except DrsplatError as exc:
                self.error = f"{exc} (Ray node {socket.gethostname()})"
        if self.error is not None:
            raise DrsplatError(self.error)
        return self.models

    def load(self, resolution: float, max_height: int | None, extra: dict | None) -> tuple[str | None, dict | None]:
        """(None, the features folder's manifest as this worker makes it), or (why its models did not load, None)."""
        try:
            generator, encoder = self._models()
        except DrsplatError:
            return self.error, None
        return None, make_manifest(generator, encoder, self.nms, resolution, max_height, extra)

    def extract(self, stem: str, image: np.ndarray):
        generator, encoder = self._models()
        seg, feats, times, counts = extract_image(image, generator, encoder, self.nms)
        return stem, seg, feats, times, counts


def _check_started(actors: list, manifest_args: tuple, cancel: CancelToken | None = None) -> tuple[list, dict]:
    """The actors that started, each with its models loaded, and the features folder's manifest they
    made as they loaded (manifest_args: resolution, max_height, extra of make_manifest). The placed
    ones first (drsplat.cluster.placed_actors: a worker not placed while others are is given up with a
    warning, none placed in STALL_SECONDS is one DrsplatError, not a wait). One DrsplatError when any
    placed worker could not load its models (e.g. a GPU Ray declared that torch cannot use), or when
    two workers' manifests differ in what shapes the features (`_check_same_manifests`: another
    weights file on a node, whose features would be mixed in one folder); a cancel is seen within WAIT_SECONDS.

    The manifest comes with the load, not from a later call: a node lost once its worker loaded
    (Ray: unavailable) stopped the run there, whoever was left to take its images."""
    ray = import_ray()
    loads: dict[int, Any] = {}

    def load_once_placed(actor) -> None:  # queued behind `ready`: a worker loads as soon as it is placed
        loads[id(actor)] = actor.load.remote(*manifest_args)

    placed = placed_actors(actors, "feature", "images", cancel, queue_after_ready=load_once_placed)
    try:
        loading = {loads[id(a)]: a for a in placed}
        started, errors, manifests = [], [], []
        while loading:  # no bound: a placed worker loading its models is progressing
            ready, _ = ray.wait(list(loading), num_returns=len(loading), timeout=WAIT_SECONDS)
            kill_if_cancelled(ray, actors, cancel)
            for ref in ready:
                a = loading.pop(ref)
                try:
                    error, manifest = ray.get(ref)
                except ray.exceptions.ActorUnavailableError:  # its node lost while it loaded
                    log.warning("Ray: a feature worker was lost while it loaded its models (its node became unavailable)")
                    ray.kill(a, no_restart=True)
                    continue
                if error is None:
                    started.append(a)
                    manifests.append(manifest)
                else:
                    errors.append(error)
    except ray.exceptions.RayError as exc:
        raise DrsplatError(f"a Ray feature worker could not start: {exc}") from None
    if errors:
        raise DrsplatError(f"{len(errors)} of {len(placed)} Ray feature workers could not load their models: {errors[0]}")
    if not started:
        raise DrsplatError("every Ray feature worker was lost while it loaded its models (their nodes became unavailable)")
    _check_same_manifests(manifests)
    return started, manifests[0]


FEATURE_MODULES = ("torch", "open_clip")  # besides drsplat, Python, numpy and numba: what makes a worker's embeddings (`check_nodes_run_this_code`)
SHAPING_KEYS = ("mask_generator", "clip_model_id", "dim", "crop_size", *RESUME_KEYS)  # manifest entries two workers must share


def _check_same_manifests(manifests: list[dict]) -> None:
    """One DrsplatError naming the first entry that shapes the features (the models, their weights'
    digests, the mask and resize settings: RESUME_KEYS and the model identity) on which two workers'
    manifests differ, e.g. clip_weights: a node's weights file of the same name holds other weights.
    Other library versions or CLIP precisions (`--device auto` on a cluster of GPU and CPU nodes) are
    a warning (the features may differ in their last bits); paths are not compared, since each host
    has its own hub cache."""
    first = manifests[0]
    for other in manifests[1:]:
        differ = [k for k in SHAPING_KEYS if first.get(k) != other.get(k)]
        if differ:
            key = differ[0]
            raise DrsplatError(f"two Ray feature workers would make other features: their manifests differ in {key!r} ({first.get(key)!r} "
                               f"on one node, {other.get(key)!r} on another); every node needs the same weights files and settings")
    for key, what in (("versions", "library versions"), ("clip_precision", "CLIP precisions (float16 on a CUDA device)")):
        other = next((m for m in manifests[1:] if m.get(key) != first.get(key)), None)
        if other is not None:  # once per kind, not once per worker
            log.warning("Ray: the feature workers' nodes run other %s (%s on one, %s on another): their features may differ in "
                        "their last bits", what, first.get(key), other.get(key))



def _results_as_they_come(ray, actors: list, cameras: list, send: Callable, cancel: CancelToken | None):
    """Each camera's extract result, in the order they finish: one call queued per actor (`send(actor,
    camera)` reads the image and submits it). A call whose actor became unavailable (its node lost:
    Ray does not retry those, and an actor restarted with no CPU to run on would be waited for
    forever) goes to another actor, at most TASK_RETRIES times, and the lost actor is given up; so
    does the call of an actor stalled while others finished calls (drsplat.cluster.stalled: its node
    lost with no room to restart it, or its CPU taken). A cancel is seen within WAIT_SECONDS."""
    todo = list(cameras)
    live = list(actors)
    busy: dict = {}  # ref -> (camera, actor, submitted at)
    tries: dict[str, int] = {}
    slowest = 0.0
    last_done = time.monotonic()

    def lose(actor, cam, why: str) -> None:
        todo.insert(0, cam)
        if actor in live:
            live.remove(actor)
            ray.kill(actor, no_restart=True)
        if not live:
            raise DrsplatError(f"every Ray feature worker was lost ({why}); the images written so far are kept: rerun to skip them")
        log.warning("Ray: a feature worker was lost (%s); its image goes to the %d other worker(s)", why, len(live))

    while todo or busy:
        for a in [a for a in live if all(owner is not a for _, owner, _ in busy.values())]:
            if not todo:
                break
            cam = todo.pop(0)
            busy[send(a, cam)] = (cam, a, time.monotonic())
        ready, _ = ray.wait(list(busy), num_returns=1, timeout=WAIT_SECONDS)
        kill_if_cancelled(ray, live, cancel)
        for ref in ready:
            cam, actor, at = busy.pop(ref)
            try:
                result = ray.get(ref)
            except ray.exceptions.RayTaskError as exc:
                raise exc.as_instanceof_cause() from None
            except ray.exceptions.ActorUnavailableError:
                tries[cam.name] = tries.get(cam.name, 0) + 1
                if tries[cam.name] > TASK_RETRIES:
                    raise DrsplatError(f"image {cam.name} found no available Ray feature worker in {TASK_RETRIES + 1} tries") from None
                lose(actor, cam, "its node became unavailable")
                continue
            except ray.exceptions.RayError as exc:
                raise DrsplatError(f"a Ray feature worker failed after {TASK_RETRIES} retries: {exc}") from None
            slowest = max(slowest, time.monotonic() - at)
            last_done = time.monotonic()
            yield result
        now = time.monotonic()
        for ref, (cam, actor, at) in list(busy.items()):
            if now - last_done < now - at and stalled(now - at, slowest):
                del busy[ref]
                try:
                    ray.cancel(ref)
                except Exception:  # noqa: BLE001 - the call of a killed actor
                    pass
                lose(actor, cam, f"no image finished on it for {now - at:.0f} s while the others progressed: its node lost or "
                                 "the cluster's CPUs taken by other work")


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
    # the files a worker reads, as the driver's working folder names them: a worker's own is the one its
    # node was started in (`ray start`'s), where a relative --clip-checkpoint is another file or none
    spec = dataclasses.replace(spec, **{k: Path(v).absolute() for k in ("clip_checkpoint", "clip_config", "sam_checkpoint")
                                        if (v := getattr(spec, k)) is not None})
    owns = connect(address)
    actors: list = []
    try:
        gpus = 1 if spec.device == "cuda" else 0
        # before any image, as registration checks its nodes: a node of other code wrote 9 of 16 feature files of another
        # norm into one folder, exit 0 (round 60b); torch and open_clip make the embeddings too
        nodes = check_nodes_run_this_code(ray, FEATURE_MODULES, "its feature files", cancel)
        count = actor_count(nodes, gpus, workers, address)
        actor = ray.remote(num_cpus=1, num_gpus=gpus, max_restarts=-1, max_task_retries=TASK_RETRIES)(_FeatureWorker)
        actors = [actor.remote(spec) for _ in range(count)]
        log.info("features on %d Ray actor(s)%s", count, " (one per GPU)" if gpus else "")
        started, manifest = _check_started(actors, (resolution, max_height, manifest_extra), cancel)
        stamps = ImageStamps.read(out)
        check_manifest_compatible(out, manifest)
        out.mkdir(parents=True, exist_ok=True)
        featurefiles.write_manifest(out, {**manifest, IMAGE_STAMPS: stamps.known})
        stamps.tracked = True
        report = FeatureReport()
        todo = todo_cameras(cameras, out, report, stamps)
        read_at: dict[str, str | None] = {}  # each image as it was read, not as it may be when its pair comes back
        unseen: dict[str, np.ndarray | None] = {}  # its pixels the photo never saw (`unobserved_pixels`), by stem

        def send(a, c):
            again = c.name in read_at  # sent again (its worker lost): counted once in the report
            read_at[c.name] = pair_stamp(c)
            rgb, file_size = load_image_sized(c)
            unseen[c.name] = unobserved_pixels(c, file_size)
            if not again:
                note_image(report, c, rgb, file_size)
            return a.extract.remote(c.name, rgb)

        results = _results_as_they_come(ray, started, todo, send, cancel)
        finished = len(report.skipped)
        if on_progress is not None:
            on_progress(finished, len(cameras))
        for _ in progress(range(len(todo)), desc="features", total=len(todo), enabled=show_progress, unit="img"):
            stem, seg, feats, times, counts = next(results)
            record_result(out, stem, seg, feats, times, counts, report, unseen.pop(stem, None))
            stamps.add(stem, read_at.get(stem))
            finished += 1
            if on_progress is not None:
                on_progress(finished, len(cameras))
        stamps.finish(manifest, len(report.written) + len(report.skipped))
        report.workers = len(started)
        return report
    finally:
        for a in actors:  # their models and GPUs go back to the cluster now, not when this driver exits
            ray.kill(a, no_restart=True)
        disconnect(owns)
