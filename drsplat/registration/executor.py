"""Executors: the place where a registration's views are computed (local or Ray), with any engine.

An executor runs `ViewComputer`s (drsplat.registration.compute) and yields the views' ViewPairs
in view order:

    place   executor                                             registered in
    local   LocalExecutor: this process, view by view            EXECUTORS
    ray     RayExecutor: actors on a Ray cluster (registration.ray) EXECUTORS

Every (engine, place) pair gives the same pairs, hence the same field (tests/test_registration_matrix.py).
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator, Sequence
from typing import Protocol

from drsplat.cameras import Camera
from drsplat.cluster import ClusterOptions
from drsplat.errors import UsageError
from drsplat.raster import PreparedScene
from drsplat.registration.compute import ViewComputer, ViewJob, WorkerStats
from drsplat.registration.culling import SpatialIndex
from drsplat.registration.pairlog import ViewPairs
from drsplat.registration.ray import RayExecutor
from drsplat.utils import CancelToken


class Executor(Protocol):
    """A place that computes views: their ViewPairs in view order, then `close()`; worker_stats:
    pid -> WorkerStats of the processes that computed them."""

    worker_stats: dict[int, WorkerStats]

    def view_pairs(self, views: Sequence[Camera]) -> Iterator[ViewPairs]: ...

    def close(self) -> None: ...


class LocalExecutor:
    """Computes views in this process, one after another (the default place).

    worker_stats: {this pid: WorkerStats} (first view, later views, kernels), as a Ray worker reports.
    """

    def __init__(self, geometry: PreparedScene, job: ViewJob, cluster: ClusterOptions | None = None, index: SpatialIndex | None = None,
                 cancel: CancelToken | None = None):
        """cluster, cancel: unused here (every place takes them; the driver reads the cancel token between views); index:
        the scene's culling index when built already (the fit stage's)."""
        self._computer = ViewComputer(geometry, job, index)
        self._stats = WorkerStats()
        self.worker_stats = {self._stats.pid: self._stats}

    def view_pairs(self, views: Sequence[Camera]) -> Iterator[ViewPairs]:
        for cam in views:
            t0 = time.perf_counter()
            view = self._computer.load_and_compute(cam)
            self._stats.add_view(time.perf_counter() - t0)
            yield view
        self._stats.refresh()

    def close(self) -> None:
        self._computer = None


def one_view_behind(views: Iterable[ViewPairs]) -> Iterator[ViewPairs]:
    """`views` in order, each resolved (`ViewPairs.resolved`) and handed on only once the next one
    was computed: a view computed on a device has its sizes read while the device works on the next
    one, so reading them does not leave the device idle. The same views, in the same order; when
    computing a view fails, the view before it is still handed on first (a checkpoint keeps it)."""
    pending = None
    stream = iter(views)
    while True:
        try:
            view = next(stream)
        except StopIteration:
            break
        except BaseException:
            if pending is not None:
                yield pending.resolved()
            raise
        if pending is not None:
            yield pending.resolved()
        pending = view
    if pending is not None:
        yield pending.resolved()


# The places: a new one is a class taking (geometry, job, cluster, index, cancel) with view_pairs / close, and one line here.
EXECUTORS = {"local": LocalExecutor, "ray": RayExecutor}


def open_executor(place: str, geometry: PreparedScene, job: ViewJob, cluster: ClusterOptions | None = None,
                  index: SpatialIndex | None = None, cancel: CancelToken | None = None) -> Executor:
    """The executor of `place` ("local" or "ray") computing `job`'s views of `geometry`; index: the
    scene's culling index when built already (None: the executor builds it if the job culls); cancel: read while a
    Ray executor waits for its cluster (a Ctrl-C never waits for a worker or node)."""
    try:
        factory = EXECUTORS[place]
    except KeyError:
        raise UsageError(f"unknown place {place!r}; choose {' or '.join(EXECUTORS)}") from None
    return factory(geometry, job, cluster, index, cancel)
