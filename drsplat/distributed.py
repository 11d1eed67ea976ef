"""Ray backend: registration views and feature images computed on a Ray cluster.

Ray schedules, retries and moves data; drsplat only says what a task is:

- Registration (`RayExecutor`, plugged into `register_scene` / `register_streaming`): the
  driver puts the scene's prepared geometry in the object store once, reads each view's
  feature files itself (workers need no shared file system) and submits chunks of views as
  tasks. A task rasterizes its views and returns their sparse (Gaussian, mask, weight) pairs
  (drsplat.pairlog.ViewPairs), never anything N x M or N x D. The driver takes the results
  in view order, appends them to the pair log (the checkpoint) and sums them exactly as the
  local path does, so the result is the same bit for bit. A worker that dies is replaced and
  its task retried (`max_retries`); a killed driver resumes from the log.
- Features (`extract_features_ray`): one actor per worker loads the mask generator and CLIP
  once; the driver sends images and writes the returned `<stem>_s.npy` / `<stem>_f.npy`
  atomically itself, so a dead worker (actor restarted, call retried) leaves no half or
  duplicate file, and complete pairs already on disk are skipped.

`ray` is optional (`pip install 'drsplat[ray]'`); without it these entry points raise a
DrsplatError that says so.
"""

from __future__ import annotations

import builtins
import logging
import os
import signal
import socket
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from drsplat.cameras import Camera
from drsplat.errors import DrsplatError
from drsplat.pairlog import ViewPairs
from drsplat.utils import CancelToken, progress

log = logging.getLogger(__name__)

TASK_RETRIES = 3
VIEWS_PER_TASK = 2
LOCAL_ADDRESSES = ("", "local")


def import_ray():
    try:
        import ray
    except ImportError:
        raise DrsplatError("--ray needs the ray package: pip install 'drsplat[ray]' (ray==2.60.0)") from None
    return ray


def _runtime_env(address: str | None) -> dict:
    """Make workers run the driver's drsplat code whatever is installed on their side.

    On this machine (a local instance, or a cluster address on this host) workers import the
    package from the driver's folder (PYTHONPATH), which also reuses numba's on-disk cache of
    compiled kernels; on other hosts Ray ships the package (`py_modules`).
    """
    import drsplat

    package = Path(drsplat.__file__).resolve().parent
    if _on_this_host(address):
        return {"env_vars": {"PYTHONPATH": str(package.parent)}}
    return {"py_modules": [str(package)], "excludes": ["__pycache__", "*.pyc"]}


def _on_this_host(address: str | None) -> bool:
    if address is None or address in LOCAL_ADDRESSES or address == "auto":
        return True
    host = address.split("://", 1)[-1].rpartition(":")[0]
    try:
        ip = socket.gethostbyname(host)
    except OSError:
        return False
    if ip.startswith("127."):
        return True
    try:
        return ip in socket.gethostbyname_ex(socket.gethostname())[2]
    except OSError:
        return False


def _check_reachable(address: str, timeout: float = 3.0) -> None:
    """A clear error at once when host:port accepts no connection (ray.init would wait much longer)."""
    target = address.split("://", 1)[-1]
    host, _, port = target.rpartition(":")
    if not host or not port.isdigit():
        raise DrsplatError(f"--ray {address!r} is not an address: expected HOST:PORT (as printed by `ray start --head`), 'auto', or nothing for a local cluster")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout):
            return
    except OSError as exc:
        raise DrsplatError(
            f"cannot reach a Ray cluster at {address} ({exc.strerror or exc}); start one with `ray start --head` "
            f"and pass the address it prints, or use --ray with no address for a local cluster"
        ) from None


def connect(address: str | None, *, num_cpus: int | None = None, object_store_memory: int | None = None) -> bool:
    """Connect this process to Ray. Returns True when this call started Ray (the caller shuts it down).

    address: None / "" / "local" starts a local Ray instance; "auto" joins the cluster this machine
    belongs to; "HOST:PORT" (or ray://HOST:PORT) joins that cluster, checked first to be reachable.
    An already initialised Ray session is reused.
    """
    ray = import_ray()
    local = address is None or address in LOCAL_ADDRESSES
    if not local and address != "auto":
        _check_reachable(address)
    if ray.is_initialized():
        return False
    kwargs = {"runtime_env": _runtime_env(address), "logging_level": logging.WARNING, "log_to_driver": False}
    if local:
        kwargs.update(include_dashboard=False, num_cpus=num_cpus, object_store_memory=object_store_memory)
    else:
        kwargs["address"] = address
    try:
        with _process_state_kept():
            ray.init(**kwargs)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise DrsplatError(f"could not connect to the Ray cluster at {address or 'a new local instance'}: {exc}") from None
    return True


@contextmanager
def _process_state_kept():
    """Keep what belongs to the program using drsplat, not to Ray, as it was across ray.init.

    ray.init replaces the SIGTERM handler (with sys.exit: the CLI's own handler, which turns
    SIGTERM into a clean interrupt, would be lost) and sets PYTHONBREAKPOINT to Ray's debugger.
    And the first worker output or worker-death error that Ray's driver relays (log_to_driver
    or not) replaces builtins.print with ray.experimental.tqdm_ray.safe_print, from a background
    thread; numba then cannot compile jitted code that calls numba.get_num_threads() (its
    implementation prints). Creating Ray's progress-bar manager now, print put back, means Ray
    never replaces print later (the manager replaces it only when it is created).
    """
    from ray.experimental import tqdm_ray

    keep_print = builtins.print
    tqdm_ray.instance()
    builtins.print = keep_print
    in_main_thread = threading.current_thread() is threading.main_thread()  # signal handlers are the main thread's
    keep_sigterm = signal.getsignal(signal.SIGTERM) if in_main_thread else None
    keep_breakpoint = os.environ.get("PYTHONBREAKPOINT")
    try:
        yield
    finally:
        if keep_sigterm is not None:
            signal.signal(signal.SIGTERM, keep_sigterm)
        if keep_breakpoint is None:
            os.environ.pop("PYTHONBREAKPOINT", None)
        else:
            os.environ["PYTHONBREAKPOINT"] = keep_breakpoint


def _set_threads() -> None:
    """numba threads = the CPUs Ray gave this task (workers otherwise oversubscribe the node)."""
    import numba
    import ray

    cpus = ray.get_runtime_context().get_assigned_resources().get("CPU", 1)
    numba.set_num_threads(max(1, min(numba.config.NUMBA_NUM_THREADS, int(round(cpus)))))


# ----------------------------------------------------------------------------- registration


def _views_task(prepared, items: list, topk: int, hook=None) -> tuple[list[ViewPairs], int, int]:
    """Ray task: the ViewPairs of a chunk of views, this worker's pid and peak RSS (bytes).

    items: [(camera, mask_ids [H, W], feats [M, D], nonfinite)]. hook: an aggregation mode's
    per-view hook (drsplat.aggregate.ViewHook) or None; its statistics travel in ViewPairs.stats.
    """
    import os

    from drsplat.registration import Coalescer, compute_view_pairs
    from drsplat.streaming import peak_rss

    _set_threads()
    coalescer = Coalescer(prepared.num_gaussians)
    out = None
    results = []
    for cam, mask_ids, feats, nonfinite in items:
        view, out = compute_view_pairs(prepared, cam, mask_ids, feats, topk, coalescer, out, weights=hook)
        view.num_nonfinite = nonfinite
        results.append(view)
    return results, os.getpid(), peak_rss()


class RayExecutor:
    """Computes views' pairs on a Ray cluster (see the module docstring); `close()` when done.

    address: as for `connect`. workers: tasks running at once (default: the cluster's CPUs). views_per_task: views a task renders (amortises the task overhead).
    """

    def __init__(self, address: str | None = None, *, workers: int | None = None, views_per_task: int = VIEWS_PER_TASK, cpus_per_task: float = 1.0):
        ray = import_ray()
        self._owns = connect(address)
        self.workers = int(workers or max(1, int(ray.cluster_resources().get("CPU", 1) // cpus_per_task)))
        self.views_per_task = max(1, int(views_per_task))
        self._task = ray.remote(num_cpus=cpus_per_task, max_retries=TASK_RETRIES)(_views_task)
        self.worker_peak_rss: dict[int, int] = {}  # pid -> peak resident bytes, as reported by its tasks
        self._hook = None
        log.info("Ray: %d worker task(s) at once on %s", self.workers, "a local instance" if self._owns and not address else address)

    def set_hook(self, hook) -> None:
        """Run an aggregation mode's per-view hook (drsplat.aggregate.ViewHook) on the workers."""
        self._hook = hook

    def view_pairs(self, prepared, views: Sequence[Camera], features_dir: Path, level: int, topk: int) -> Iterator[ViewPairs]:
        """The ViewPairs of `views`, in order (tasks run out of order; results are reordered)."""
        import ray

        from drsplat.registration import load_view_features

        chunks = [list(views[i : i + self.views_per_task]) for i in range(0, len(views), self.views_per_task)]
        if not chunks:
            return
        geometry = ray.put(prepared)
        hook = ray.put(self._hook)  # the mode's RayGeometry goes to the object store once, like the scene
        pending: dict = {}
        done: dict[int, list[ViewPairs]] = {}
        submitted = 0
        try:
            for index in range(len(chunks)):
                while submitted < len(chunks) and len(pending) < self.workers:
                    items = [(cam, *load_view_features(features_dir, cam, level)) for cam in chunks[submitted]]
                    pending[self._task.remote(geometry, items, topk, hook)] = submitted
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
            del geometry, hook

    def close(self) -> None:
        if self._owns:
            import ray

            ray.shutdown()
            self._owns = False


def _get(ref):
    import ray

    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as exc:  # a Python error inside the task: show the original one
        raise exc.as_instanceof_cause() from None
    except ray.exceptions.RayError as exc:  # the worker died more than TASK_RETRIES times, node lost, ...
        raise DrsplatError(f"a Ray task failed after {TASK_RETRIES} retries: {exc}") from None


# ----------------------------------------------------------------------------- features


class _FeatureWorker:
    """Ray actor: one model load per worker, then one image per call."""

    def __init__(self, spec) -> None:
        from drsplat.features.extract import build_models

        _set_threads()
        self.generator, self.encoder = build_models(spec)
        self.nms = spec.nms

    def manifest(self, resolution: float, max_height: int | None, extra: dict | None) -> dict:
        from drsplat.features.extract import make_manifest

        return make_manifest(self.generator, self.encoder, self.nms, resolution, max_height, extra)

    def extract(self, stem: str, image: np.ndarray):
        from drsplat.features.extract import extract_image

        seg, feats, times, counts = extract_image(image, self.generator, self.encoder, self.nms)
        return stem, seg, feats, times, counts


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
    from drsplat.cameras import load_image
    from drsplat.features import format as featurefiles
    from drsplat.features.extract import FeatureReport, check_manifest_compatible, record_result, todo_cameras

    ray = import_ray()
    from ray.util import ActorPool

    out = Path(out_dir)
    owns = connect(address)
    try:
        gpus = 1 if spec.device == "cuda" else 0
        count = int(workers or max(1, int(ray.cluster_resources().get("CPU", 1))))
        actor = ray.remote(num_cpus=1, num_gpus=gpus, max_restarts=-1, max_task_retries=TASK_RETRIES)(_FeatureWorker)
        actors = [actor.remote(spec) for _ in range(count)]
        manifest = ray.get(actors[0].manifest.remote(resolution, max_height, manifest_extra))
        check_manifest_compatible(out, manifest)
        out.mkdir(parents=True, exist_ok=True)
        featurefiles.write_manifest(out, manifest)
        report = FeatureReport()
        todo = todo_cameras(cameras, out, report)
        pool = ActorPool(actors)
        for cam in todo:
            pool.submit(lambda a, c: a.extract.remote(c.name, load_image(c)), cam)
        finished = len(report.skipped)
        if on_progress is not None:
            on_progress(finished, len(cameras))
        for _ in progress(range(len(todo)), desc="features", total=len(todo), enabled=show_progress, unit="img"):
            if cancel is not None and cancel.cancelled:
                for a in actors:
                    ray.kill(a)
                cancel.raise_if_cancelled()
            try:
                stem, seg, feats, times, counts = pool.get_next_unordered()
            except ray.exceptions.RayTaskError as exc:
                raise exc.as_instanceof_cause() from None
            except ray.exceptions.RayError as exc:
                raise DrsplatError(f"a Ray feature worker failed after {TASK_RETRIES} retries: {exc}") from None
            record_result(out, stem, seg, feats, times, counts, report)
            finished += 1
            if on_progress is not None:
                on_progress(finished, len(cameras))
        featurefiles.write_manifest(out, {**manifest, "images": len(report.written) + len(report.skipped)})
        return report
    finally:
        if owns:
            ray.shutdown()
