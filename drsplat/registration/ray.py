"""Ray registration: a registration's views computed by tasks on a Ray cluster (place "ray").

The driver puts the scene's CPU geometry and the view job (engine, device, top-k, the aggregation
mode's per-view hook) in the object store once, reads each view's feature files itself (workers
need no shared file system) and submits chunks of views as tasks. A task computes its views with
a `ViewComputer` (drsplat.registration.compute), the same code as a local run, with the job's
engine on the job's device (a task asks Ray for one GPU when the device is CUDA), and returns the
views' sparse (Gaussian, mask, weight) pairs, never anything N x M or N x D. The executor yields
them in view order, so the driver logs and sums them exactly as a local run does (bit for bit).
A worker that dies is replaced and its task retried (`TASK_RETRIES`); a killed driver resumes from
its checkpoint.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator, Sequence

from drsplat.cameras import Camera
from drsplat.cluster import TASK_RETRIES, ClusterOptions, connect, import_ray, set_worker_threads
from drsplat.errors import DrsplatError
from drsplat.memory import peak_rss
from drsplat.raster import PreparedScene
from drsplat.registration.compute import ViewComputer, ViewJob
from drsplat.registration.culling import SpatialIndex
from drsplat.registration.pairlog import ViewPairs
from drsplat.registration.views import load_view_features

log = logging.getLogger(__name__)

VIEWS_PER_TASK = 2


def _views_task(geometry: PreparedScene, job: ViewJob, index: SpatialIndex | None, items: list) -> tuple[list[ViewPairs], int, int]:
    """Ray task: the ViewPairs of a chunk of views, this worker's pid and peak RSS (bytes).

    index: the scene's culling index (built once on the driver), or None without culling.
    items: [(camera, mask_ids [H, W], feats [M, D], nonfinite)].
    """
    set_worker_threads()
    computer = ViewComputer(geometry, job, index)
    views = [computer.compute(cam, mask_ids, feats, nonfinite) for cam, mask_ids, feats, nonfinite in items]
    return views, os.getpid(), peak_rss()


class RayExecutor:
    """Computes views on a Ray cluster (see the module docstring); `close()` when done.

    cluster: the address, the number of tasks running at once (default: the cluster's CPUs, or GPUs
    for a CUDA job) and the views a task computes (amortises the task overhead).
    """

    def __init__(self, geometry: PreparedScene, job: ViewJob, cluster: ClusterOptions | None = None):
        cluster = cluster or ClusterOptions()
        ray = import_ray()
        self._owns = connect(cluster.address)
        gpus = 1 if job.device.startswith("cuda") else 0
        resource = "GPU" if gpus else "CPU"
        available = int(ray.cluster_resources().get(resource, 0))
        if gpus and available == 0:
            self.close()
            raise DrsplatError(f"--device {job.device} on Ray needs GPUs, but the cluster at {cluster.address or 'a local instance'} has none")
        self.workers = int(cluster.workers or max(1, available))
        self.views_per_task = max(1, int(cluster.views_per_task or VIEWS_PER_TASK))
        self._task = ray.remote(num_cpus=1, num_gpus=gpus, max_retries=TASK_RETRIES)(_views_task)
        self._geometry = geometry
        self._job = job
        self.worker_peak_rss: dict[int, int] = {}  # pid -> peak resident bytes, as reported by its tasks
        log.info("Ray: %d worker task(s) at once on %s", self.workers, "a local instance" if self._owns and not cluster.address else cluster.address)

    def view_pairs(self, views: Sequence[Camera]) -> Iterator[ViewPairs]:
        """The ViewPairs of `views`, in order (tasks run out of order; results are reordered)."""
        ray = import_ray()
        chunks = [list(views[i : i + self.views_per_task]) for i in range(0, len(views), self.views_per_task)]
        if not chunks:
            return
        geometry, job = ray.put(self._geometry), ray.put(self._job)  # once per run, like the hook's geometry inside the job
        culling = ray.put(SpatialIndex.build(self._geometry) if self._job.cull else None)  # not rebuilt by every task
        pending: dict = {}
        done: dict[int, list[ViewPairs]] = {}
        submitted = 0
        try:
            for index in range(len(chunks)):
                while submitted < len(chunks) and len(pending) < self.workers:
                    items = [(cam, *load_view_features(self._job.features_dir, cam, self._job.level)) for cam in chunks[submitted]]
                    pending[self._task.remote(geometry, job, culling, items)] = submitted
                    submitted += 1
                while index not in done:
                    ready, _ = ray.wait(list(pending), num_returns=1)
                    for ref in ready:
                        views_done, pid, rss = _get(ref)
                        done[pending.pop(ref)] = views_done
                        self.worker_peak_rss[pid] = max(rss, self.worker_peak_rss.get(pid, 0))
                yield from done.pop(index)
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)
            del geometry, job, culling

    def close(self) -> None:
        if self._owns:
            import_ray().shutdown()
            self._owns = False


def _get(ref):
    ray = import_ray()
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as exc:  # a Python error inside the task: show the original one
        raise exc.as_instanceof_cause() from None
    except ray.exceptions.RayError as exc:  # the worker died more than TASK_RETRIES times, node lost, ...
        raise DrsplatError(f"a Ray task failed after {TASK_RETRIES} retries: {exc}") from None
