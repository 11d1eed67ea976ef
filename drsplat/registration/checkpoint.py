"""A registration's resumable state beside its output: the pair log and the mode's statistics.

`<dir>/.<out name>.register.log` is the append-only pair log (drsplat.registration.pairlog): every
finished view's distinct (Gaussian, mask, weight) pairs, which is all the running sums depend on.
An aggregation mode with per-Gaussian statistics (floater rejection) snapshots them beside it every
CHECKPOINT_EVERY views (`.register.log.aggregate.npz`); a resume cuts the log back to the views
the snapshot covers. A run whose blocks reducers finish (Ray) has its view workers log the views
into shards (`.register.log.shards/`, drsplat.registration.pairlog.ShardWriter) and keeps only a
pointer per view in the log; the statistics are then in the shards, and a resume keeps the views
whose shard records are all there, checksums included. A checkpoint is resumed only when the scene
(every Gaussian's geometry and opacity), the views (names, intrinsics, poses, order), the feature
folder, top-k, level and mode are the same, and on a GPU the engine (`checkpoint_params`; a restart
names what changed), and a logged view only while its feature files have the size, modification and status-change
times and inode they had when it was logged (`feature_stamp`: features regenerated or edited in place cut the log back to the views
before the first changed one). One registration
at a time holds a checkpoint: `RunLock` (an flock on `.<out>.register.lock`) refuses a second one
writing the same output.
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import json
import logging
import math
import os
import shutil
import tempfile
import zipfile
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from drsplat.cameras import Camera
from drsplat.errors import DrsplatError, OutputError
from drsplat.features import format as featurefiles
from drsplat.memory import format_size
from drsplat.registration.aggregate import Aggregator
from drsplat.registration.pairlog import LogRecord, PairLog, ShardError, ViewPairs, payload_checksum_ok, pointed_record, resuming_from, shard_file, shards_folder
from drsplat.raster import NEAR, sh_in_range
from drsplat.scene import GaussianScene, counted
from drsplat.utils import (TEMP_SUFFIX, atomic_path, file_stamp, is_special_file, odd_entry_kind, os_error_cause, output_target, protected_mode, read_npy_header,
                           temp_prefix, temp_stem, work_folder)

log = logging.getLogger(__name__)

CHECKPOINT_VERSION = 2  # 2: append-only pair log; 1 was a dense F/W .npz
CHECKPOINT_EVERY = 10  # views between fsyncs of the log and snapshots of a mode's statistics


def checkpoint_path_for(out: str | Path) -> Path:
    """The hidden resumable checkpoint (pair log) of a registration that writes `out` (beside it; in the
    temp folder for a device or FIFO output, `drsplat.utils.work_folder`), named after where `out`
    lands: a symlink's target, so that a run into the link and one into the file share one lock
    (named after the link, both ran and wrote the same file; probe round 13); a device's or FIFO's
    with a digest of its path too (two FIFOs named out.ply in two folders shared one; round 14)."""
    target = output_target(out)
    name = target.name
    if is_special_file(target):  # in the temp folder, where outputs of one name from many folders meet
        name = f"{name}.{hashlib.sha1(os.fsencode(os.path.abspath(target))).hexdigest()[:10]}"
    return work_folder(out) / f".{temp_stem(Path(name))}.register.log"  # temp_stem: a long name leaves room for the suffixes


def aggregate_stats_path(checkpoint: Path) -> Path:
    """Where an aggregation mode's statistics are snapshotted beside the pair log `checkpoint`."""
    return checkpoint.with_name(checkpoint.name + ".aggregate.npz")


def lock_path_for(checkpoint: Path) -> Path:
    """The lock file beside a checkpoint (`RunLock`)."""
    return checkpoint.with_name(checkpoint.name.removesuffix(".log") + ".lock")


def lock_run(checkpoint: Path) -> RunLock:
    """The run's lock beside the pair log `checkpoint` (`RunLock`): taken before any work, so that a
    second run into the same output, or an output folder that takes no file, is refused at once.
    Checkpoint(lock=...) takes it over. A pair log there that this user may not rewrite (a run begun
    under another account: root's, then resumed as oneself) is refused too, before any work: it was
    taken for an unreadable log, "starting from scratch", after the fit stage, and then failed."""
    lock = RunLock.acquire(lock_path_for(checkpoint), checkpoint.name[1:].removesuffix(".register.log"))
    if os.path.lexists(checkpoint) and not _may_rewrite(checkpoint):
        lock.release()
        raise OutputError(checkpoint, "the checkpoint of a stopped run here cannot be read and rewritten by this user (permission denied): "
                          "give it this user's permissions to resume, or delete it to start over")
    return lock


def _may_rewrite(path: Path) -> bool:
    """Whether this process may read and rewrite `path` (its permissions, as the kernel judges them for this user)."""
    return os.access(path, os.R_OK | os.W_OK)


def _scene_digest(scene: GaussianScene) -> str:
    """sha1 of every Gaussian's mean, scales, opacity and rotation (what registration reads; ~1 GB/s,
    so a 50M-Gaussian scene's 2.8 GB take a few seconds against hours of registration), and of which
    Gaussians the SH leave unrendered: the SH themselves are not read (a recoloured scene resumes),
    but a coefficient past MAX_SH_COEFFICIENT keeps its Gaussian out of every view (`prepare_scene`),
    so a log begun before such an edit holds views that saw it. Hashed only when some are (the
    digest of a scene whose Gaussians all render is the one earlier logs hold)."""
    h = hashlib.sha1()
    n = scene.num_gaussians
    h.update(str(n).encode())
    for arr in (scene.means, scene.log_scales, scene.opacity_logits, scene.quats):
        h.update(memoryview(np.ascontiguousarray(arr)).cast("B"))
    renders = sh_in_range(scene)
    if not renders.all():
        h.update(b"unrendered by their SH:" + np.packbits(renders).tobytes())
    return h.hexdigest()


def feature_stamp(features_dir: Path, name: str) -> str:
    """The stamps (`utils.file_stamp`, in place) of view `name`'s feature pair: a view is resumed from
    the log only while its files are as they were when it was logged (a file the driver does not
    hold, on Ray, is absent both times). The status-change time counts too: a file rewritten at its
    old size with its old modification time put back (`cp -p`) is a changed file."""
    pair = (featurefiles.seg_path(features_dir, name), featurefiles.feat_path(features_dir, name))
    return hashlib.sha1("|".join(f"{p.name}={file_stamp(p, in_place=True)}" for p in pair).encode()).hexdigest()[:16]


def feature_stamps(features_dir: Path, views: Sequence[Camera]) -> dict[str, str]:
    """Every view's `feature_stamp`, taken before a registration reads any view."""
    return {cam.name: feature_stamp(features_dir, cam.name) for cam in views}


def changed_features(features_dir: Path, stamps: dict[str, str]) -> list[str]:
    """The views whose feature files are not as `stamps` (`feature_stamps`) found them."""
    return [name for name, stamp in stamps.items() if feature_stamp(features_dir, name) != stamp]


def _views_digest(cameras: Sequence[Camera]) -> str:
    """The cameras' names, sizes, intrinsics and poses, every float by its exact float64 bits: a pose
    or focal length that moved at all is another set of views (printed to 6 digits, cameras differing
    by 3.5e-7 relative resumed each other's log, round 22)."""
    h = hashlib.sha1()
    for c in cameras:
        h.update(f"{c.name}|{c.width}x{c.height}|".encode())
        h.update(c.geometry_bits())
    return h.hexdigest()


def checkpoint_params(scene: GaussianScene, cameras: Sequence[Camera], features_dir: Path, topk: int, level: int, aggregate: str,
                      shards: bool = False, engine: str = "numba", device: str = "cpu", near_plane: float = NEAR) -> dict:
    """What a checkpoint (pair log) must match to be resumed. shards: the views are logged by the
    workers into shards (a log of pointers resumes only as one). engine, device: the rasterizer;
    only a GPU's is recorded, since the CPU engines log the same bits (numba = torch on a CPU) and
    the torch engine on CUDA agrees with them to float32 rounding only: a log it began resumed on
    the CPU (or the reverse) would give a field equal to neither run's. near_plane: recorded where
    it is not the default (so a log made before the option resumes as it was)."""
    extra = {"shards": True} if shards else {}
    if near_plane != NEAR:
        extra["near_plane"] = float(near_plane)
    kind = device.split(":")[0]  # which GPU of a kind does not matter
    if kind != "cpu":
        extra["engine"] = f"{engine} on {kind}"
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


class RunLock:
    """An exclusive flock on `path` while one registration works on a checkpoint: a second run
    aiming at the same output fails at once instead of rewriting the log under the first. The file
    is removed on release; a run that dies releases the lock with its process (the file stays, and
    the next run takes it)."""

    def __init__(self, path: Path, fd: int):
        self.path, self._fd = path, fd

    @classmethod
    def acquire(cls, path: Path, what: str) -> "RunLock":
        """DrsplatError naming `what` when another process holds the lock; OutputError naming the
        folder when it cannot hold the run's files (`_check_folder`)."""
        refuse_odd_entry(path)
        if not path.parent.is_dir() and not os.path.lexists(path.parent):  # the output's folder, made here first (utils.ensure_parent's words)
            log.info("created the folder %s for %s", path.parent, what)
        while True:
            problem = "the folder cannot be made"
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                problem = f"its file {path.name} cannot be opened for writing" if path.exists() else "the folder takes no new file"
                fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            except OSError as exc:
                raise OutputError(path.parent, f"{problem} ({os_error_cause(exc)}), and a registration keeps its checkpoint and "
                                  f"lock there, beside {what}; write the output to another folder") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise DrsplatError(f"another registration is writing {what} (it holds {path}); wait for it to end, or write "
                                   "another output") from None
            try:  # the holder we waited for may have removed the file: then lock the new one
                if os.stat(path).st_ino == os.fstat(fd).st_ino:
                    lock = cls(path, fd)
                    break
            except FileNotFoundError:
                pass
            os.close(fd)
        try:
            lock._check_folder(what)
        except BaseException:
            lock.release()
            raise
        return lock

    def _check_folder(self, what: str) -> None:
        """OutputError unless the lock's folder takes a new file and lets it be removed: a lock file
        left by a killed run opens in a folder that takes no new file (`chattr +i`), and an
        append-only folder (`chattr +a`) takes files but never lets the output's temp file be renamed
        into place; either way the run failed only after its work (probe round 13)."""
        probe = self.path.with_name(self.path.name + ".probe")
        problem = "the folder takes no new file"
        try:
            os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644))
            problem = "files made in the folder cannot be removed or renamed, as in an append-only folder"
            os.unlink(probe)
        except OSError as exc:
            raise OutputError(self.path.parent, f"{problem} ({os_error_cause(exc)}), and a registration keeps its checkpoint and "
                              f"lock there and renames its output into place, beside {what}; write the output to another "
                              "folder") from None

    def release(self) -> None:
        """Unlock and remove the lock file (a lock file that cannot be removed stays: the next run takes
        it; the error that ended the run, if any, is the one worth reporting)."""
        if self._fd < 0:
            return
        try:
            self.path.unlink(missing_ok=True)
        except OSError as exc:
            log.debug("%s was not removed (%s)", self.path, os_error_cause(exc))
        finally:
            os.close(self._fd)
            self._fd = -1

    def __del__(self) -> None:  # a Checkpoint dropped without close(): its process must not keep the lock
        if getattr(self, "_fd", -1) >= 0:
            os.close(self._fd)
            self._fd = -1


def refuse_odd_entry(path: Path) -> None:
    """DrsplatError when drsplat's own hidden file `path` is a link, folder, FIFO, device or a write-protected file:
    writing there would follow the link (over a user's file), fail, block, or (as root) truncate a protected file."""
    kind = odd_entry_kind(path)
    mode = protected_mode(path) if kind is None else None
    if mode is not None:  # root would truncate it (round 60c)
        kind = f"a write-protected file (mode {mode:04o})"
    if kind is not None:
        raise DrsplatError(f"{path} is where drsplat keeps this registration's checkpoint, but it is {kind}; move it away and rerun")


class Checkpoint:
    """The pair log at `path` (resumed when it matches `params` and its views are a prefix of
    `views`) and the statistics snapshot of `aggregator`'s mode beside it.

    temporary: the log only backs a run in blocks that is not resumable: it is removed whatever
    happens. every: views between fsyncs and statistics snapshots. `resumed`: views replayed from the log (their statistics are already in the snapshot).
    shards: the views are logged by the workers (`shards_dir`, made empty for a fresh log) and the
    log holds pointers (params has "shards"). lock: the run's lock when taken already (`lock_run`).
    """

    def __init__(self, path: Path, params: dict, views: Sequence[Camera], aggregator: Aggregator, temporary: bool = False,
                 every: int = CHECKPOINT_EVERY, features_dir: Path | None = None, lock: "RunLock | None" = None,
                 stamps: dict[str, str] | None = None):
        self.path = Path(path)
        # each view's feature stamp taken before the run read anything (`feature_stamps`): what a view is logged with, so that
        # files changed between their read and the view's logging are not taken for the files the view was computed from
        self.stamps = stamps or {}
        self.temporary = temporary
        self.every = max(1, int(every))
        self.total = len(views)
        self.shards_dir = shards_folder(self.path) if params.get("shards") else None
        self.features_dir = None if features_dir is None else Path(features_dir)
        self._lock = None if temporary else lock if lock is not None else lock_run(self.path)
        try:
            for entry in (self.path, aggregate_stats_path(self.path)):
                refuse_odd_entry(entry)
            self.log = PairLog.open(self.path, params)
            names = [r.name for r in self.log.records]
            if names != [c.name for c in views[: len(names)]]:
                log.warning("%s does not match the order of the views; starting over", self.path)
                self.log.delete()
                self.log = PairLog.open(self.path, params)
            self._check_feature_stamps()
            if not self.log.records:  # a fresh log: an earlier run's snapshot or shards would only mislead
                aggregate_stats_path(self.path).unlink(missing_ok=True)
                shutil.rmtree(shards_folder(self.path), ignore_errors=True)
            self.aggregator = aggregator
            self._key_at = (0, params_key(self.log.params))  # (views, log_key of them): where `_log_key` goes on from
            self.stats_path = aggregate_stats_path(self.path) if aggregator.state() else None
            self.covered = None if self.stats_path is None else 0  # the views the statistics snapshot on disk covers (None: no statistics)
            if self.stats_path is not None:
                self._resume_stats()
            if self.shards_dir is not None:
                self._resume_shards()
        except BaseException:
            self._release()
            raise
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
        """The log's bytes and its shards' (what is there: a figure for the report, never an error)."""
        try:
            size = os.path.getsize(self.path)
            if self.shards_dir is not None and self.shards_dir.is_dir():
                size += sum(p.stat().st_size for p in self.shards_dir.iterdir() if p.is_file())
        except OSError:
            return 0
        return size

    def replay(self):
        """The logged views, in order (ViewPairs without statistics)."""
        return iter(self.log)

    def append(self, view: ViewPairs) -> None:
        """Log one newly computed view (fsync'd every `self.every` views), with its feature files'
        stamp. Called before the view's statistics are folded, so a failed append leaves them
        covering exactly the logged views."""
        if self.features_dir is not None:
            view = dataclasses.replace(view, stamp=self.stamps.get(view.name) or feature_stamp(self.features_dir, view.name))
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
        """Write the mode's statistics as covering the first `views` logged views, with the key of those views' records."""
        with atomic_path(self.stats_path) as tmp, open(tmp, "wb") as f:
            np.savez(f, views=np.int64(views), log_key=np.int64(self._log_key(views)), **self.aggregator.state())
        self.covered = views

    def _log_key(self, views: int) -> int:
        """`log_key` of the log's parameters and its first `views` records, going on from the last one asked (the
        snapshots' views only grow; the log is cut back only before the first)."""
        count, key = self._key_at
        if count > views:
            count, key = 0, params_key(self.log.params)
        key = chained_key(key, self.log.records[count:views])
        self._key_at = (views, key)
        return key

    def close(self) -> None:
        """Close the log and release the run's lock (a later Checkpoint at this path may open it)."""
        try:
            self.log.close()
        finally:
            self._release()

    def remove(self) -> None:
        """Delete the log, its shards and the statistics snapshot (the output is safe, or the run is
        abandoned), and release the run's lock."""
        try:
            self.log.delete()
            if self.stats_path is not None:
                self.stats_path.unlink(missing_ok=True)
            if self.shards_dir is not None:
                shutil.rmtree(self.shards_dir, ignore_errors=True)
        finally:
            self._release()

    def _release(self) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def describe(self) -> str:
        """'PATH (N of M views, S)': what a stopped run leaves behind."""
        size = self.nbytes if self.path.exists() else 0
        shards = f", with the workers' shards in {self.shards_dir.name}" if self.shards_dir is not None else ""
        snapshot = f", its statistics in {self.stats_path.name}" if self.stats_path is not None and self.stats_path.exists() else ""
        return f"{self.path} ({self.done} of {self.total} views, {format_size(size)}{shards}{snapshot})"

    def leave(self, why: str) -> bool:
        """A run ended early (`why`): keep a log that holds views, with one message saying what it is;
        remove a temporary one or one that holds nothing. True when it was kept and said."""
        try:
            self.log.close()
        except OSError as exc:  # a full disk fails the buffered tail's flush too: the rerun cuts that record off
            log.debug("the checkpoint's last record was not flushed (%s)", exc)
        if self.temporary or self.done == 0:
            self.remove()
            return False
        try:
            if self.stats_path is not None and self.aggregator.views_folded == self.done:
                try:  # the statistics cover exactly the logged views: the rerun resumes from all of them
                    self._snapshot(self.done)
                except OSError as exc:  # a full disk: the last periodic snapshot still stands
                    log.debug("no statistics snapshot at the stop (%s)", exc)
            resumable = self.done if self.covered is None else min(self.covered, self.done)
            if resumable == 0:  # the mode's statistics were never saved: a rerun would redo every view (round 72b F2)
                self.remove()
                log.warning("%s: the registration checkpoint was removed: the aggregation statistics of its %s could not be "
                            "saved, so a rerun would compute them again anyway", why, counted(self.done, "view", "views"))
                return False
            # the same words for `drsplat register` and the viewer's Register button (round 71b F5: "the same command" there)
            part = "" if resumable == self.done else f" (its first {resumable}: the aggregation statistics were last saved there)"
            beside = self.shards_dir is not None or (self.stats_path is not None and self.stats_path.exists())
            log.warning("%s: kept the registration checkpoint %s; a registration into the same output with the same settings "
                        "resumes from it%s, delete %s to start over", why, self.describe(), part, "it and the files it names" if beside else "it")
            return True
        finally:
            self._release()

    def _check_feature_stamps(self) -> None:
        """Cut the log back to the views before the first whose feature files changed since it was logged."""
        if self.features_dir is None:
            return
        for i, record in enumerate(self.log.records):
            if record.meta.get("stamp") != feature_stamp(self.features_dir, record.name):
                log.warning("%s: the feature files of view %s changed since it was logged; %s", self.path, record.name, resuming_from(i))
                self.log.truncate(i)
                return

    # ------------------------------------------------------------------ the workers' shards

    def _resume_shards(self) -> None:
        """Keep the logged views whose shard records are all there (a shard lost or cut short: the
        log is cut back to the views before it, with a warning); a fresh log gets an empty folder."""
        files: dict[str, object] = {}
        try:
            for i, record in enumerate(self.log.records):
                problem = _shard_record_problem(self.path, record.meta.get("shard"), files)
                if problem is not None:
                    log.warning("%s: view %s %s; %s", self.path, record.name, problem, resuming_from(i))
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
        if not self.log.records:  # a fresh log: __init__ removed any earlier snapshot
            return
        try:
            views, key, arrays = _load_snapshot(self.stats_path, self.aggregator.state())
            if views <= len(self.log.records) and key != self._log_key(views):
                # round 100d F1: another run's snapshot (a --topk 20 run's, copied over this one's) was folded in without a word
                log.warning("%s belongs to another run's log (its key does not match the first %d views of %s); the aggregation "
                            "statistics restart with the views", self.stats_path, views, self.path.name)
                views, arrays = 0, {}
        except SnapshotWithoutKey:
            log.warning("%s was written by an earlier drsplat, which did not tie it to its log; the aggregation statistics restart "
                        "with the views", self.stats_path)
            views, arrays = 0, {}
        except FileNotFoundError:  # stopped before the first snapshot: the normal case of an early kill
            if len(self.log.records) <= self.every:  # a kill while the first snapshot was written, too (round 90a F3)
                log.info("%s: its %d views predate the first statistics snapshot (every %d views); they are redone", self.path,
                         len(self.log.records), self.every)
            else:  # a snapshot was due, so it went (round 89b F3: blamed on timing)
                log.warning("%s: its statistics snapshot %s is missing; its %s are redone", self.path, self.stats_path.name,
                            counted(len(self.log.records), "view", "views"))
            views, arrays = 0, {}
        # NotImplementedError, RuntimeError: zipfile's for a compression method it lacks, an encrypted member (round 91a F5)
        except (OSError, ValueError, KeyError, EOFError, SyntaxError, zipfile.BadZipFile, NotImplementedError, RuntimeError) as exc:
            # the reader's own words quote the damaged bytes (round 89b F4): the cause is named, never the contents
            why = os_error_cause(exc) if isinstance(exc, OSError) else "its contents are damaged"
            log.warning("%s is unreadable (%s); the aggregation statistics restart with the views", self.stats_path, why)
            views, arrays = 0, {}
        if views > len(self.log.records):  # the log was cut shorter than the snapshot: start over, and say so (round 72b F1:
            log.warning("%s: its statistics snapshot covers %d views, more than the %d it keeps now; the aggregation statistics "  # "resuming
                        "restart, so those views are redone too", self.path, views, len(self.log.records))  # from N views", then none)
            self.stats_path.unlink(missing_ok=True)
            views, arrays = 0, {}
        self.log.truncate(views)
        self.covered = views
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
        record = pointed_record(path, ref, f)
    except ShardError as exc:
        return f"needs a record of {path}, but {exc.reason}"
    if not payload_checksum_ok(f, record):
        return f"needs a record of {path} whose checksum does not match (the shard was damaged)"
    return None


def params_key(params: dict) -> int:
    """crc32 of a log's parameters (JSON, sorted keys): where a snapshot's `log_key` starts."""
    return zlib.crc32(json.dumps(params, sort_keys=True, default=str).encode())


def chained_key(key: int, records: Sequence[LogRecord]) -> int:
    """`key` chained (crc32) over the records' metadata (JSON, sorted keys: a view's name, its feature stamp, its counts):
    a snapshot's `log_key` ties it to the log whose first views it covers."""
    for record in records:
        key = zlib.crc32(json.dumps(record.meta, sort_keys=True, default=str).encode(), key)
    return key


SNAPSHOT_SCALARS = ("views", "log_key")  # a snapshot's members beside the mode's arrays


class SnapshotWithoutKey(ValueError):
    """A statistics snapshot of an earlier drsplat, which kept no `log_key`: what it covers cannot be told."""


def _load_snapshot(path: Path, expected: dict[str, np.ndarray]) -> tuple[int, int, dict[str, np.ndarray]]:
    """(views, log_key, arrays) of a statistics snapshot. Its members must be `views` and `log_key` (numbers) and
    exactly the arrays of `expected`, with their shapes and numeric dtypes: checked from the .npy headers inside the
    zip before anything is read (a damaged or foreign file cannot make us allocate)."""
    with zipfile.ZipFile(path) as archive:
        members = {name.removesuffix(".npy"): name for name in archive.namelist()}
        if set(members) == set(expected) | {"views"}:  # all but the key: written before it was kept (round 102a F3)
            raise SnapshotWithoutKey()
        if set(members) != set(expected) | set(SNAPSHOT_SCALARS):
            raise ValueError(f"holds {sorted(members)}, expected {sorted(set(expected) | set(SNAPSHOT_SCALARS))}")
        for name, member in members.items():
            with archive.open(member) as f:
                shape, dtype = read_npy_header(f)
            if name in SNAPSHOT_SCALARS:
                if shape != () or dtype.kind not in "iuf":
                    raise ValueError(f"{name} has shape {shape} {dtype}, expected one number")
            elif shape != expected[name].shape or dtype != expected[name].dtype:  # the dtypes the statistics are kept in
                raise ValueError(f"{name} has shape {shape} {dtype}, expected {expected[name].shape} {expected[name].dtype}")
    with np.load(path, allow_pickle=False) as data:
        views, key = (_whole_number(data[name], name) for name in SNAPSHOT_SCALARS)
        if views < 0:
            raise ValueError(f"covers {views} views")
        arrays = {name: data[name] for name in expected}
    for name, values in arrays.items():
        problem = _statistic_problem(values, views)
        if problem is not None:
            raise ValueError(f"{name} {problem}")
    return views, key, arrays


def _statistic_problem(values: np.ndarray, views: int) -> str | None:
    """What no registration writes into a snapshot's statistics array of `views` views, or None: a NaN or infinity, a
    negative value (each is a max, a sum of weights w = T·α ≥ 0 or a count of views), a count past `views`. Round 104a
    F1: with its key intact, a NaN peak or views_seen of -5 was folded in without a word (18,402 Gaussians for 18,347)."""
    if values.dtype.kind == "f" and not np.isfinite(values).all():
        return f"holds {int(np.count_nonzero(~np.isfinite(values)))} NaN or infinite values"
    if values.size and values.min() < 0:
        return f"holds {int(np.count_nonzero(values < 0))} negative values"
    if values.dtype.kind in "iu" and values.size and values.max() > views:
        return f"counts up to {int(values.max())} views, more than the {views} the snapshot covers"
    return None


def _whole_number(value: np.ndarray, name: str) -> int:
    """A snapshot's 0-d `views` or `log_key` as an int; ValueError for a float that is not a whole number (int() of an
    inf raised OverflowError, which no caller took for a damaged file: a traceback)."""
    number = value.item()
    if isinstance(number, float) and not (math.isfinite(number) and number.is_integer()):
        raise ValueError(f"{name} is {number}, not a whole number")
    return int(number)
