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
import logging
import socket
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

from drsplat.cameras import Camera
from drsplat.cluster import TASK_RETRIES, ClusterOptions, connect, import_ray, set_worker_threads, worker_slots
from drsplat.errors import DrsplatError, InputError
from drsplat.raster import PreparedScene
from drsplat.registration.compute import ViewComputer, ViewJob, WorkerStats
from drsplat.registration.culling import SpatialIndex
from drsplat.registration.pairlog import ShardWriter, ViewPairs
from drsplat.registration.views import load_view_features

log = logging.getLogger(__name__)

VIEWS_PER_TASK = 2  # views per actor call: a call's overhead is small next to a view's
IN_FLIGHT = 2  # calls queued on each actor at once, so it starts its next views while the driver sums


@dataclass
class _CallResult:
    """One actor call: the views computed (in order), the worker's report, and the error that
    stopped the call at the next view, if any (raised by the driver in view order)."""

    views: list[ViewPairs]
    stats: WorkerStats
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

    def compute(self, shared: list, cameras: list[Camera]) -> _CallResult:
        """The ViewPairs of `cameras`, their features read here; stops at the first view that fails.

        shared: [geometry, job, index] references (see the class docstring).
        """
        stats, views = WorkerStats(), []
        error = None
        try:
            for cam in cameras:
                t0 = time.perf_counter()
                computer = self._computer or self._start(shared)
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
                self._shard = ShardWriter(job.shard_dir, job.log_params)
            except OSError as exc:
                self._computer = None
                self._error = DrsplatError(f"a Ray registration worker on node {socket.gethostname()} cannot write its shard of the log in "
                                           f"{job.shard_dir} ({exc.strerror or exc}): the partitioned reduce needs the output's folder on "
                                           "storage every Ray node shares at the same path")
                raise self._error from None
        return self._computer

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

    def __init__(self, geometry: PreparedScene, job: ViewJob, cluster: ClusterOptions | None = None, index: SpatialIndex | None = None):
        """index: the scene's culling index when built already (the fit stage's); else built here."""
        cluster = cluster or ClusterOptions()
        ray = import_ray()
        self._owns = connect(cluster.address)
        self._actors: list = []
        self._refs: list = []  # [geometry, job, culling index] in the object store
        self.worker_stats: dict[int, WorkerStats] = {}
        where = "a local instance" if self._owns and not cluster.address else cluster.address
        try:
            gpus = 1 if job.device.startswith("cuda") else 0
            slots = worker_slots(ray.nodes(), gpus)
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

        Calls go to the actor with the fewest queued, at most IN_FLIGHT each, and never more than
        2 x IN_FLIGHT x workers chunks ahead of the next one to yield (bounds what waits here).
        """
        ray = import_ray()
        chunks = [list(views[i : i + self.views_per_task]) for i in range(0, len(views), self.views_per_task)]
        window = 2 * IN_FLIGHT * len(self._actors)
        queued: dict = {}  # ref -> (chunk index, actor index)
        load = [0] * len(self._actors)  # calls queued per actor
        finished: dict[int, _CallResult] = {}
        submitted = 0

        def top_up(first_unyielded: int) -> None:
            nonlocal submitted
            while submitted < min(len(chunks), first_unyielded + window):
                actor = min(range(len(load)), key=load.__getitem__)
                if load[actor] >= IN_FLIGHT:
                    return
                queued[self._actors[actor].compute.remote(self._refs, chunks[submitted])] = (submitted, actor)
                load[actor] += 1
                submitted += 1

        try:
            for index in range(len(chunks)):
                top_up(index)
                while index not in finished:
                    ready, _ = ray.wait(list(queued), num_returns=1)
                    for ref in ready:
                        chunk, actor = queued.pop(ref)
                        load[actor] -= 1
                        finished[chunk] = self._collect(ref)
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
        if self._owns:
            import_ray().shutdown()
            self._owns = False


def _get(ref) -> _CallResult:
    ray = import_ray()
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as exc:  # a Python error inside the call: show the original one
        raise exc.as_instanceof_cause() from None
    except ray.exceptions.RayError as exc:  # the worker died more than TASK_RETRIES times, node lost, ...
        raise DrsplatError(f"a Ray registration worker failed after {TASK_RETRIES} restarts: {exc}") from None
