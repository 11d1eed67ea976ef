"""A registration's resumable state beside its output: the pair log and the mode's statistics.

`<dir>/.<out name>.register.log` is the append-only pair log (drsplat.registration.pairlog): every
finished view's distinct (Gaussian, mask, weight) pairs, which is all the running sums depend on.
An aggregation mode with per-Gaussian statistics (floater rejection) snapshots them beside it every
CHECKPOINT_EVERY views (`.register.log.aggregate.npz`); a resume cuts the log back to the views
the snapshot covers. A run whose blocks reducers finish (Ray) has its view workers log the views
into shards (`.register.log.shards/`, drsplat.registration.pairlog.ShardWriter) and keeps only a
pointer per view in the log; the statistics are then in the shards, and a resume keeps the views
whose shard records are all there. A checkpoint is resumed only when the scene, the views (names, intrinsics,
poses, order), the feature folder, top-k, level and mode are the same (`checkpoint_params`).
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import tempfile
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from drsplat.cameras import Camera
from drsplat.memory import format_size
from drsplat.registration.aggregate import Aggregator
from drsplat.registration.pairlog import PairLog, ShardError, ViewPairs, pointed_record, shard_file, shards_folder
from drsplat.scene import GaussianScene
from drsplat.utils import TEMP_SUFFIX, atomic_path, read_npy_header, temp_prefix, work_folder

log = logging.getLogger(__name__)

CHECKPOINT_VERSION = 2  # 2: append-only pair log; 1 was a dense F/W .npz
CHECKPOINT_EVERY = 10  # views between fsyncs of the log and snapshots of a mode's statistics


def checkpoint_path_for(out: str | Path) -> Path:
    """The hidden resumable checkpoint (pair log) of a registration that writes `out` (beside it; in the
    temp folder for a device or FIFO output, `drsplat.utils.work_folder`)."""
    out = Path(out)
    return work_folder(out) / f".{out.name}.register.log"


def aggregate_stats_path(checkpoint: Path) -> Path:
    """Where an aggregation mode's statistics are snapshotted beside the pair log `checkpoint`."""
    return checkpoint.with_name(checkpoint.name + ".aggregate.npz")


def _scene_digest(scene: GaussianScene) -> str:
    h = hashlib.sha1()
    h.update(str(scene.num_gaussians).encode())
    step = max(1, scene.num_gaussians // 4096)
    for arr in (scene.means, scene.log_scales, scene.opacity_logits, scene.quats):
        h.update(np.ascontiguousarray(arr[::step]).tobytes())
    return h.hexdigest()


def _views_digest(cameras: Sequence[Camera]) -> str:
    h = hashlib.sha1()
    for c in cameras:
        h.update(f"{c.name}|{c.width}x{c.height}|{c.fx:.6g},{c.fy:.6g},{c.cx:.6g},{c.cy:.6g}|".encode())
        h.update(np.asarray(c.R, np.float64).round(9).tobytes() + np.asarray(c.t, np.float64).round(9).tobytes())
    return h.hexdigest()


def checkpoint_params(scene: GaussianScene, cameras: Sequence[Camera], features_dir: Path, topk: int, level: int, aggregate: str,
                      shards: bool = False) -> dict:
    """What a checkpoint (pair log) must match to be resumed. shards: the views are logged by the
    workers into shards (a log of pointers resumes only as one)."""
    extra = {"shards": True} if shards else {}
    return {**extra,
        "aggregate": aggregate,
        "version": CHECKPOINT_VERSION,
        "num_gaussians": scene.num_gaussians,
        "scene": _scene_digest(scene),
        "views": _views_digest(cameras),
        "features_dir": str(Path(features_dir).resolve()),
        "topk": int(topk),
        "level": int(level),
    }


class Checkpoint:
    """The pair log at `path` (resumed when it matches `params` and its views are a prefix of
    `views`) and the statistics snapshot of `aggregator`'s mode beside it.

    temporary: the log only backs a run in blocks that is not resumable: it is removed whatever
    happens. every: views between fsyncs and statistics snapshots. `resumed`: views replayed from the log (their statistics are already in the snapshot).
    shards: the views are logged by the workers (`shards_dir`, made empty for a fresh log) and the
    log holds pointers (params has "shards").
    """

    def __init__(self, path: Path, params: dict, views: Sequence[Camera], aggregator: Aggregator, temporary: bool = False,
                 every: int = CHECKPOINT_EVERY):
        self.path = Path(path)
        self.temporary = temporary
        self.every = max(1, int(every))
        self.total = len(views)
        self.shards_dir = shards_folder(self.path) if params.get("shards") else None
        self.log = PairLog.open(self.path, params)
        names = [r.name for r in self.log.records]
        if names != [c.name for c in views[: len(names)]]:
            log.warning("%s does not match the order of the views; starting over", self.path)
            self.log.delete()
            self.log = PairLog.open(self.path, params)
        self.aggregator = aggregator
        self.stats_path = aggregate_stats_path(self.path) if aggregator.state() else None
        if self.stats_path is not None:
            self._resume_stats()
        if self.shards_dir is not None:
            self._resume_shards()
        self.resumed = len(self.log.records)

    @classmethod
    def temporary_beside(cls, out: Path, params: dict, views: Sequence[Camera], aggregator: Aggregator) -> "Checkpoint":
        """A fresh log in `out`'s folder for a run in blocks that keeps no checkpoint."""
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(prefix=temp_prefix(out), suffix=TEMP_SUFFIX, dir=out.parent, delete=False) as f:
            path = Path(f.name)
        path.unlink()
        return cls(path, params, views, aggregator, temporary=True)

    @property
    def done(self) -> int:
        return len(self.log.records)

    @property
    def nbytes(self) -> int:
        """The log's bytes and its shards'."""
        size = os.path.getsize(self.path)
        if self.shards_dir is not None and self.shards_dir.is_dir():
            size += sum(p.stat().st_size for p in self.shards_dir.iterdir() if p.is_file())
        return size

    def replay(self):
        """The logged views, in order (ViewPairs without statistics)."""
        return iter(self.log)

    def append(self, view: ViewPairs) -> None:
        """Log one newly computed view (fsync'd every `self.every` views). Called before the view's
        statistics are folded, so a failed append leaves them covering exactly the logged views."""
        done = self.done + 1
        try:
            self.log.append(view, sync=done % self.every == 0 and not self.temporary)
        except OSError as exc:  # name the file: a bare ENOSPC from write() carries none
            raise OSError(exc.errno, exc.strerror, str(self.path)) from None

    def folded(self) -> None:
        """The last logged view's statistics are folded in: snapshot them at the fsync points."""
        if self.done % self.every == 0 and self.stats_path is not None and not self.temporary:
            self._snapshot(self.done)

    def _snapshot(self, views: int) -> None:
        """Write the mode's statistics as covering the first `views` logged views."""
        with atomic_path(self.stats_path) as tmp, open(tmp, "wb") as f:
            np.savez(f, views=np.int64(views), **self.aggregator.state())

    def close(self) -> None:
        self.log.close()

    def remove(self) -> None:
        """Delete the log, its shards and the statistics snapshot (the output is safe, or the run is abandoned)."""
        self.log.delete()
        if self.stats_path is not None:
            self.stats_path.unlink(missing_ok=True)
        if self.shards_dir is not None:
            shutil.rmtree(self.shards_dir, ignore_errors=True)

    def describe(self) -> str:
        """'PATH (N of M views, S)': what a stopped run leaves behind."""
        size = self.nbytes if self.path.exists() else 0
        shards = f", with the workers' shards in {self.shards_dir.name}" if self.shards_dir is not None else ""
        return f"{self.path} ({self.done} of {self.total} views, {format_size(size)}{shards})"

    def leave(self, why: str) -> None:
        """A run ended early (`why`): keep a log that holds views, with one message saying what it is;
        remove a temporary one or one that holds nothing."""
        self.close()
        if self.temporary or self.done == 0:
            self.remove()
            return
        if self.stats_path is not None and self.aggregator.views_folded == self.done:
            try:  # the statistics cover exactly the logged views: the rerun resumes from all of them
                self._snapshot(self.done)
            except OSError as exc:  # a full disk: the last periodic snapshot still stands
                log.debug("no statistics snapshot at the stop (%s)", exc)
        log.warning("%s: kept the registration checkpoint %s; the same command resumes from it, delete it to start over",
                    why, self.describe())

    # ------------------------------------------------------------------ the workers' shards

    def _resume_shards(self) -> None:
        """Keep the logged views whose shard records are all there (a shard lost or cut short: the
        log is cut back to the views before it, with a warning); a fresh log gets an empty folder."""
        files: dict[str, object] = {}
        try:
            for i, record in enumerate(self.log.records):
                problem = _shard_record_problem(self.path, record.meta.get("shard"), files)
                if problem is not None:
                    log.warning("%s: view %s %s; resuming from the %d views before it", self.path, record.name, problem, i)
                    self.log.truncate(i)
                    break
        finally:
            for f in files.values():
                if f is not None:
                    f.close()
        if not self.log.records:  # nothing to resume: the old shards are of no use
            shutil.rmtree(self.shards_dir, ignore_errors=True)
        self.shards_dir.mkdir(parents=True, exist_ok=True)

    # ------------------------------------------------------------------ the mode's statistics

    def _resume_stats(self) -> None:
        """Load the statistics snapshot and cut the log back to the views it covers (or start over)."""
        if not self.log.records:
            self.stats_path.unlink(missing_ok=True)
            return
        try:
            views, arrays = _load_snapshot(self.stats_path, self.aggregator.state())
        except (OSError, ValueError, KeyError, EOFError, SyntaxError, zipfile.BadZipFile) as exc:
            log.warning("%s is missing or unreadable (%s); the aggregation statistics restart with the views", self.stats_path, exc)
            views, arrays = 0, {}
        if views > len(self.log.records):  # the log was cut shorter than the snapshot: start over
            views, arrays = 0, {}
        self.log.truncate(views)
        self.aggregator.load_state(arrays)
        self.aggregator.views_folded = views


def _shard_record_problem(log_path: Path, ref: dict | None, files: dict) -> str | None:
    """Why the shard record a pointer `ref` of the log `log_path` names cannot be resumed from, or
    None when it is there (`pairlog.shard_file`, `pairlog.pointed_record`: the payload itself is read
    by the reducers). files: shard path -> open file (or None when it cannot be opened), shared
    between calls."""
    if ref is None:
        return "holds no shard pointer"
    try:
        path = shard_file(log_path, ref)
    except ShardError:
        return f"names {ref.get('file') if isinstance(ref, dict) else ref!r}, which is not a file of {shards_folder(log_path).name}"
    if path not in files:
        try:
            files[path] = open(path, "rb")
        except OSError:
            files[path] = None
    f = files[path]
    if f is None:
        return f"needs {path}, which is missing or unreadable"
    try:
        pointed_record(path, ref, f)
    except ShardError as exc:
        return f"needs a record of {path}, but {exc.reason}"
    return None


def _load_snapshot(path: Path, expected: dict[str, np.ndarray]) -> tuple[int, dict[str, np.ndarray]]:
    """(views, arrays) of a statistics snapshot. Its members must be `views` (a number) and exactly
    the arrays of `expected`, with their shapes and numeric dtypes: checked from the .npy headers
    inside the zip before anything is read (a damaged or foreign file cannot make us allocate)."""
    with zipfile.ZipFile(path) as archive:
        members = {name.removesuffix(".npy"): name for name in archive.namelist()}
        if set(members) != set(expected) | {"views"}:
            raise ValueError(f"holds {sorted(members)}, expected {sorted(set(expected) | {'views'})}")
        for name, member in members.items():
            with archive.open(member) as f:
                shape, dtype = read_npy_header(f)
            want = () if name == "views" else expected[name].shape
            if shape != want or dtype.kind not in "iuf":
                raise ValueError(f"{name} has shape {shape} {dtype}, expected {want} numbers")
    with np.load(path, allow_pickle=False) as data:
        views = int(data["views"])
        if views < 0:
            raise ValueError(f"covers {views} views")
        return views, {name: data[name] for name in expected}
