"""Ray registration: a registration's views computed by stateful actors on a Ray cluster (place "ray").

One actor per worker slot (`_ViewWorker`: one CPU, plus one GPU when the job's device is CUDA)
holds for its life:

- the scene's CPU geometry, put in the object store once by the driver: the workers of a node
  read the node's one copy (numpy arrays come out of Ray's shared memory without a copy);
- the culling index (drsplat.registration.culling), built once on the driver, shipped the same way;
- one `ViewComputer` (drsplat.registration.compute) with the job's engine on the job's device:
  the same code as a local run, its buffers reused from view to view.

With a log in shards (ViewJob.shard_dir: a run whose blocks reducers finish), each worker also
appends its views' records, pairs and floater statistics, to a shard of its own in the shared
checkpoint folder (drsplat.registration.pairlog.ShardWriter), fsyncs it at the end of each call and
returns the views without their pairs: the driver logs a pointer per view and never receives a
pair (drsplat.registration.reduce reads them back per block).

The driver ships cameras only. A worker reads its views' feature files itself from the job's
features folder (`load_view_features`), so every node needs that folder at the same path (a
shared file system, or a copy): a file missing on a worker is an error that names the node.
Each actor has `IN_FLIGHT` calls of `views_per_task` views queued (submitted ahead), so it never
waits for the driver; results come back out of order and are yielded in view order, so the
driver logs and sums them exactly as a local run does (bit for bit). A view that fails (bad
feature file) fails where the local run would: the views before it are yielded first.

Kernels are compiled once per node: every numba kernel is `cache=True`, and a node's workers
import the package from one folder (the driver's on its host, the package Ray unpacks once per
node elsewhere), so the first worker to compile a kernel stores it beside the source and the
node's other workers (and restarted ones) load it. Each worker reports its first view's seconds
(kernel loading included), its later views' and its kernel cache hits and misses (`WorkerStats`).

A worker that dies is restarted with the same geometry and its queued calls retried
(`TASK_RETRIES` times each); a killed driver resumes from its checkpoint.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
import socket
import time
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from drsplat.cameras import Camera
from drsplat.cluster import (TASK_RETRIES, WAIT_SECONDS, ClusterOptions, check_nodes_run_this_code, connect, disconnect, import_ray, placed_actors,
                             set_worker_threads, stalled,
                             worker_slots)
from drsplat.errors import DrsplatError, InputError
from drsplat.raster import PreparedScene
from drsplat.registration.compute import ViewComputer, ViewJob, WorkerStats
from drsplat.registration.culling import SpatialIndex
from drsplat.registration.pairlog import ShardWriter, ViewPairs
from drsplat.features.format import feat_path, seg_path
from drsplat.registration.views import load_view_features
from drsplat.utils import CancelToken

log = logging.getLogger(__name__)

VIEWS_PER_TASK = 2  # views per actor call: a call's overhead is small next to a view's
IN_FLIGHT = 2  # calls queued on each actor at once, so it starts its next views while the driver sums
MARK_BYTES = 8192  # a feature file's first and last bytes compared between the driver and a worker (feature_mark)


def feature_mark(path: Path) -> tuple[int, int] | None:
    """(size, CRC-32 of the first and last MARK_BYTES) of a feature file, or None when it cannot be read:
    what a worker's copy must match (a stale or foreign copy on a node reads as the driver's file otherwise)."""
    try:
        with open(path, "rb") as f:
            size = f.seek(0, 2)
            f.seek(0)
            head = f.read(MARK_BYTES)
            f.seek(max(0, size - MARK_BYTES))
            tail = f.read(MARK_BYTES)
    except OSError:
        return None
    return size, zlib.crc32(tail, zlib.crc32(head))


@dataclass
class _CallResult:
    """One actor call: the views computed (in order), the worker's report, and the error that
    stopped the call at the next view, if any (raised by the driver in view order)."""

    views: list[ViewPairs]
    stats: WorkerStats | None  # None: the call itself failed (`error`)
    error: Exception | None = None


class _ViewWorker:
    """Ray actor: the geometry, the culling index and one ViewComputer for its life (module docstring).

    The shared objects come with every call as object-store references ([geometry, job, index],
    nested so that Ray does not fetch them per call) and are fetched by the first call only; a
    restarted worker fetches them again with its first retried call. (Constructor arguments in the
    object store would make Ray warn that a restart could lose them.)
    """

    def __init__(self) -> None:
        set_worker_threads()
        self._job: ViewJob | None = None
        self._computer: ViewComputer | None = None
        self._error: Exception | None = None
        self._views = 0
        self._shard: ShardWriter | None = None

    def ready(self) -> bool:
        """Answers once Ray placed this worker (`drsplat.cluster.placed_actors`); its constructor is cheap."""
        return True

    def compute(self, shared: list, cameras: list[Camera], marks: list | None = None) -> _CallResult:
        """The ViewPairs of `cameras`, their features read here; stops at the first view that fails.

        shared: [geometry, job, index] references (see the class docstring).
        marks: per camera, the driver's `feature_mark` of its (mask, embedding) files.
        """
        stats, views = WorkerStats(), []
        error = None
        try:
            for i, cam in enumerate(cameras):
                t0 = time.perf_counter()
                computer = self._computer or self._start(shared)
                if marks is not None:
                    self._check_marks(cam, marks[i])
                view = computer.compute(cam, *self._read(cam))
                if self._shard is not None:
                    t1 = time.perf_counter()
                    view = self._shard.write(view)
                    stats.log_seconds += time.perf_counter() - t1
                views.append(view)
                seconds = time.perf_counter() - t0
                if self._views == 0:
                    stats.first_view_seconds = seconds
                else:
                    stats.later_view_seconds.append(seconds)
                self._views += 1
        except DrsplatError as exc:
            error = exc
        if self._shard is not None and views:
            t1 = time.perf_counter()
            self._shard.sync()  # before the driver logs pointers to these records
            stats.log_seconds += time.perf_counter() - t1
        return _CallResult(views, stats.refresh(), error)

    def _start(self, shared: list) -> ViewComputer:
        """This worker's ViewComputer on the shared geometry and index (first call only); a worker that
        cannot start its engine (no usable GPU, ...) keeps the reason and gives it for every call."""
        if self._error is not None:
            raise self._error
        geometry, job, index = import_ray().get(shared)
        try:
            self._computer = ViewComputer(geometry, job, index)
        except Exception as exc:  # noqa: BLE001 - reported as one sentence instead of a dead worker's traceback
            self._error = DrsplatError(f"a Ray registration worker on node {socket.gethostname()} could not start the {job.engine} engine "
                                       f"on {job.device}: {exc}")
            raise self._error from None
        self._job = job
        if job.shard_dir is not None:
            try:
                if not Path(job.shard_dir).is_dir():  # the driver made it before any view: this node does not share its storage
                    raise FileNotFoundError(errno.ENOENT, "the driver made this folder, but this node does not see it")
                self._shard = ShardWriter(job.shard_dir, job.log_params)
            except OSError as exc:
                self._computer = None
                self._error = DrsplatError(f"a Ray registration worker on node {socket.gethostname()} cannot write its shard of the log in "
                                           f"{job.shard_dir} ({exc.strerror or exc}): the partitioned reduce needs the output's folder on "
                                           "storage every Ray node shares at the same path")
                raise self._error from None
        return self._computer

    def _check_marks(self, cam: Camera, marks: tuple) -> None:
        """The driver's marks of the view's files against this node's copies: a copy that differs is one error."""
        for path, mark in zip((seg_path(self._job.features_dir, cam.name), feat_path(self._job.features_dir, cam.name)), marks):
            here = feature_mark(path)
            if mark is not None and here is not None and here != mark:
                raise InputError(path, f"differs on the Ray worker node {socket.gethostname()} from the driver's copy ({here[0]:,} bytes "
                                 f"here, {mark[0]:,} on the driver{'' if here[0] != mark[0] else ', other contents'}): Ray workers read "
                                 f"the feature files themselves, so every node needs the driver's {self._job.features_dir} at the same "
                                 "path (a shared file system or an up-to-date copy)")

    def _read(self, cam: Camera):
        try:
            return load_view_features(self._job.features_dir, cam, self._job.level)
        except InputError as exc:
            if exc.path is None or exc.path.exists():
                raise
            raise InputError(exc.path, f"{exc.problem} on the Ray worker node {socket.gethostname()}: Ray workers read the feature "
                             f"files themselves, so every node needs {self._job.features_dir} at the same path (a shared file system "
                             "or a copy)", exc.field) from None


class RayExecutor:
    """Computes views on stateful Ray actors (see the module docstring); `close()` when done.

    cluster: the address, the number of actors (default and most: one per CPU of the cluster, or
    one per GPU for a CUDA job; more would wait forever for a slot) and the views per actor call.
    worker_stats: pid -> WorkerStats of every worker process (a restarted worker is a new pid);
    worker_peak_rss: pid -> peak resident bytes.
    """

    def __init__(self, geometry: PreparedScene, job: ViewJob, cluster: ClusterOptions | None = None, index: SpatialIndex | None = None,
                 cancel: CancelToken | None = None):
        """index: the scene's culling index when built already (the fit stage's); else built here. cancel: checked while
        the driver waits for the nodes' code probe and for its workers (a Ctrl-C never waits for a worker)."""
        cluster = cluster or ClusterOptions()
        ray = import_ray()
        self._owns = connect(cluster.address)
        self._actors: list = []
        self._placed = False  # the actors' placement waited for (`view_pairs`, where the cancel token is set)
        self._refs: list = []  # [geometry, job, culling index] in the object store
        self.cancel = cancel
        self.worker_stats: dict[int, WorkerStats] = {}
        where = "a local instance" if self._owns and not cluster.address else cluster.address
        try:
            gpus = 1 if job.device.startswith("cuda") else 0
            nodes = check_nodes_run_this_code(ray, cancel=cancel)  # before any view; and the nodes still there, a node just lost left out
            slots = worker_slots(nodes, gpus)
            if slots == 0:
                need = "a GPU and a CPU on one node" if gpus else "a CPU"
                raise DrsplatError(f"--device {job.device} on Ray needs workers with {need}, but the cluster at {where} has none")
            self.workers = min(int(cluster.workers or slots), slots)
            if cluster.workers and cluster.workers > slots:
                log.warning("Ray: %d workers asked for, but the cluster fits %d; using %d", cluster.workers, slots, slots)
            self.views_per_task = max(1, int(cluster.views_per_task or VIEWS_PER_TASK))
            if gpus:  # Ray shows each actor its own GPU only, as device 0
                job = dataclasses.replace(job, device="cuda")
            culling = (index or SpatialIndex.build(geometry)) if job.cull else None  # built once, not by every worker
            self._refs = [ray.put(geometry), ray.put(job), ray.put(culling)]
            self._features_dir = job.features_dir
            actor = ray.remote(num_cpus=1, num_gpus=gpus, max_restarts=TASK_RETRIES, max_task_retries=TASK_RETRIES)(_ViewWorker)
            self._actors = [actor.remote() for _ in range(self.workers)]
        except BaseException:
            self.close()
            raise
        log.info("Ray: %d worker actor(s) on %s", self.workers, where)

    @property
    def worker_peak_rss(self) -> dict[int, int]:
        return {pid: stats.peak_rss for pid, stats in self.worker_stats.items()}

    def view_pairs(self, views: Sequence[Camera]) -> Iterator[ViewPairs]:
        """The ViewPairs of `views`, in order (calls finish out of order; results are reordered).

        Before the first call, the actors Ray placed are waited for (drsplat.cluster.placed_actors): one
        not placed while others are is stopped, none placed in STALL_SECONDS is one DrsplatError.
        Calls go to the live actor with the fewest queued, at most IN_FLIGHT each, and never more than
        2 x IN_FLIGHT x workers chunks ahead of the next one to yield (bounds what waits here). A call
        whose actor became unavailable (its node lost) goes to another actor, and a call that waits past
        drsplat.cluster.stalled's bound is sent as well to an actor with nothing queued, the first answer taken
        (`copy_stalled_calls`; the views are the same bits wherever they are computed).
        """
        ray = import_ray()
        if not self._placed:  # a cluster with no room for any worker is one error, not a wait for the first call
            self._actors = placed_actors(self._actors, "registration", "views", self.cancel)
            self._placed = True
        chunks = [list(views[i : i + self.views_per_task]) for i in range(0, len(views), self.views_per_task)]
        actors = list(self._actors)
        window = 2 * IN_FLIGHT * len(actors)
        queued: dict = {}  # ref -> (chunk index, actor, submitted at)
        load = {id(a): 0 for a in actors}  # calls queued per actor
        finished: dict[int, _CallResult] = {}
        todo: list[int] = []  # chunks to submit again (their actor was lost), before new ones
        attempts: dict[int, int] = {}
        submitted = 0
        slowest = 0.0
        done_at: dict[int, float] = {}  # id(actor) -> when its last call finished
        settled: set[int] = set()  # chunks whose result (or error) is taken
        copied_at: dict[int, float] = {}  # chunk -> when its last copy was sent (`copy_stalled_calls`)
        waiting_said: list[float | None] = [None]  # when a stalled call's wait with no worker free was last logged
        failed: dict[int, tuple[_CallResult, float]] = {}  # chunk -> its first failed call's result and when it came

        def marks_of(chunk: list[Camera]) -> list:
            return [(feature_mark(seg_path(self._features_dir, c.name)), feature_mark(feat_path(self._features_dir, c.name))) for c in chunk]

        def send(chunk: int, actor) -> None:
            queued[actor.compute.remote(self._refs, chunks[chunk], marks_of(chunks[chunk]))] = (chunk, actor, time.monotonic())
            load[id(actor)] += 1

        def submit(chunk: int) -> bool:
            live = [a for a in actors if load[id(a)] < IN_FLIGHT]
            if not live:
                return False
            send(chunk, min(live, key=lambda a: load[id(a)]))
            return True

        def top_up(first_unyielded: int) -> None:
            nonlocal submitted
            while todo and submit(todo[0]):
                todo.pop(0)
            while submitted < min(len(chunks), first_unyielded + window) and submit(submitted):
                submitted += 1

        def copies(chunk: int) -> list:
            """The actors a call of `chunk` is queued on."""
            return [owner for c, owner, _ in queued.values() if c == chunk]

        def lose(actor, why: str) -> None:
            """Stop `actor` and queue its calls again on the others (those no other actor holds a copy of)."""
            if actor not in actors:
                return
            actors.remove(actor)
            if not actors:
                raise DrsplatError(f"every Ray registration worker was lost ({why}); the views logged so far are kept: rerun to resume")
            log.warning("Ray: a registration worker was lost (%s); its views go to the %d other worker(s)", why, len(actors))
            for ref, (chunk, owner, _) in list(queued.items()):
                if owner is actor:
                    del queued[ref]
                    if chunk not in settled and not copies(chunk):
                        todo.append(chunk)
                    try:
                        ray.cancel(ref)
                    except Exception:  # noqa: BLE001 - the call of a dead actor
                        pass
            try:
                ray.kill(actor, no_restart=True)
            except Exception as exc:  # noqa: BLE001 - an actor already gone
                log.debug("a lost worker was not killed (%s)", exc)
            todo.sort()

        def take(ref) -> None:
            """A finished call: its chunk's result, unless a copy's came first (then dropped: the same bits)."""
            nonlocal slowest
            chunk, actor, at = queued.pop(ref)
            load[id(actor)] -= 1
            began = max(at, done_at.get(id(actor), at))  # the call's own time, not its wait behind the one before
            done_at[id(actor)] = time.monotonic()
            if chunk in settled:  # a copy's answer after the first (a begun call is not stopped: Ray answers its cancel at
                return            # once while it runs on, so copies are left to answer and keep their worker's load true)
            try:
                result = self._collect(ref)
                if result.error is not None:  # a view's error, returned with the views before it (round 79c F1: only a
                    keep_failure(chunk, result)  # raised error had waited for another copy; a worker returns its views' errors)
                    return
                finished[chunk] = result
            except ray.exceptions.ActorUnavailableError:  # its node lost: the call may not have run; run it elsewhere
                if not copies(chunk):
                    attempts[chunk] = attempts.get(chunk, 0) + 1
                    if attempts[chunk] > TASK_RETRIES:
                        raise DrsplatError(f"views {chunks[chunk][0].name}.. found no available Ray worker in {TASK_RETRIES + 1} "
                                           "tries; the views logged so far are kept: rerun to resume") from None
                    todo.append(chunk)  # this call, then the others queued on the lost actor
                lose(actor, "it became unavailable, its node lost")
                todo.sort()
                return
            except Exception as exc:  # noqa: BLE001 - raised in view order, once the chunks before it are logged
                keep_failure(chunk, _CallResult([], None, error=exc))  # (round 74d F1: it had left them unlogged)
                return
            settled.add(chunk)
            slowest = max(slowest, done_at[id(actor)] - began)

        def keep_failure(chunk: int, result: _CallResult) -> None:
            """A call of `chunk` that failed: its result (the views before the failing one, and the error) is the chunk's
            once no copy is left to answer; while one runs its answer may come (round 78a F1: an error of one worker's
            node, as a features folder not mounted there, had been taken over the views another worker was computing),
            until `give_up_on_failed` says it waited long enough."""
            kept = failed.setdefault(chunk, (result, time.monotonic()))
            if len(result.views) > len(kept[0].views):  # the copy that got furthest: fewer views to compute again (round 81a F2)
                failed[chunk] = (result, kept[1])
            if not copies(chunk):
                finished[chunk] = failed[chunk][0]
                settled.add(chunk)

        def give_up_on_failed(now: float) -> None:
            """A chunk one of whose calls failed while a copy still ran takes that error once every copy left has waited
            the stall bound since the failure and since it could begin as far as the driver knows (its submission, or its
            worker's last finished call's end: a copy sent again after its node was lost gets its own time, round 79a F1;
            one queued behind a call still running is timed from its submission, so a worker that answers nothing for
            the bound is taken for lost, as the copies' rule takes it, round 80a F1). Waiting for the call ahead instead
            would wait for ever on a node lost where Ray says nothing."""
            for chunk, (result, failed_at) in failed.items():
                if chunk in settled or chunk in todo:
                    continue
                left = [max(failed_at, at, done_at.get(id(owner), at)) for c, owner, at in queued.values() if c == chunk]
                if all(stalled(now - began, slowest) for began in left):
                    finished[chunk] = result
                    settled.add(chunk)

        def copy_stalled_calls(now: float) -> None:
            """A call waiting STALL_SECONDS + 10x the slowest call since it could begin (its submission, or its worker's
            previous call's end) is sent as well to a worker with nothing queued (none: it waits). The first answer is
            taken, so a worker is never stopped for being slow: a live one's answer counts whichever comes first, and a
            lost node's calls (never placed, or lost with no room to restart it, where Ray reports nothing) are done
            elsewhere. (Rounds 74d F2, 75a F1, 76a F1-F3: stopping the stalled worker stopped the only worker, hung the
            run on a node lost after the others' last call, or stopped a live worker and left a lost one.)"""
            idle = [a for a in actors if load[id(a)] == 0]
            for chunk, actor, at in list(queued.values()):
                began = max(at, done_at.get(id(actor), at), copied_at.get(chunk, at))  # one new copy per stall (round 77a F1)
                if chunk in settled or chunk in failed or not stalled(now - began, slowest):
                    continue
                if not idle:  # every worker busy or stuck: said once a stall period, not waited on in silence (round 79c F2)
                    if waiting_said[0] is None or stalled(now - waiting_said[0], slowest):
                        waiting_said[0] = now
                        why = ("one worker and no other worker is free to take them (each is busy or stalled too: a hung node or a "
                               "shared folder that stopped answering)") if len(actors) > 1 else "the only worker (slow, or its node hung)"
                        log.warning("Ray: views %s.. waited %.0f s on %s; waiting on (Ctrl-C stops; the views logged so far are "
                                    "kept)", chunks[chunk][0].name, now - began, why)  # round 81a F3: one worker has no other
                    continue
                holders = [id(a) for a in copies(chunk)]
                spare = next((a for a in idle if id(a) not in holders), None)
                if spare is None:
                    continue
                idle.remove(spare)
                copied_at[chunk] = now
                log.warning("Ray: views %s.. waited %.0f s on one worker (its node lost, or the worker slow): sent to another "
                            "as well; the first answer is taken (the same bits)", chunks[chunk][0].name, now - began)
                send(chunk, spare)

        try:
            for index in range(len(chunks)):
                top_up(index)
                while index not in finished:
                    ready, _ = ray.wait(list(queued), num_returns=1, timeout=WAIT_SECONDS)
                    if self.cancel is not None:
                        self.cancel.raise_if_cancelled()
                    for ref in ready:
                        take(ref)
                    give_up_on_failed(time.monotonic())
                    copy_stalled_calls(time.monotonic())
                    top_up(index)
                result = finished.pop(index)
                yield from result.views
                if result.error is not None:
                    raise result.error
        finally:
            for ref in queued:  # a stop: cancelled, the calls still queued end quietly (killed with the actors, Ray
                try:            # logged "Task _ViewWorker.compute failed ... will be retried" for each)
                    ray.cancel(ref)
                except Exception as exc:  # noqa: BLE001 - a call that just finished, or a Ray without actor-task cancel
                    log.debug("a queued view call was not cancelled (%s)", exc)
            queued.clear()

    def _collect(self, ref) -> _CallResult:
        result = _get(ref)
        stats = self.worker_stats.setdefault(result.stats.pid, WorkerStats(result.stats.pid))
        stats.merge(result.stats)
        return result

    def close(self) -> None:
        """Stop the actors (their geometry leaves the object store) and a Ray instance this executor started."""
        if self._actors or self._refs:
            ray = import_ray()
            for actor in self._actors:
                ray.kill(actor, no_restart=True)
            self._actors, self._refs = [], []
        disconnect(self._owns)
        self._owns = False


def _get(ref) -> _CallResult:
    ray = import_ray()
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as exc:  # a Python error inside the call: show the original one
        raise exc.as_instanceof_cause() from None
    except ray.exceptions.ActorUnavailableError:  # its node lost: view_pairs runs the call on another worker
        raise
    except ray.exceptions.RayError as exc:  # the worker died more than TASK_RETRIES times, ...
        raise DrsplatError(f"a Ray registration worker failed after {TASK_RETRIES} restarts: {exc}") from None
