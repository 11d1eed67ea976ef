"""Faults during registration: the disk fills up, the process is killed. Nothing half-written under
the output's name, one message naming the file and what was kept, and the rerun resumes to the bytes
of an uninterrupted run."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from drsplat.cli import main
from drsplat.registration.checkpoint import aggregate_stats_path, checkpoint_path_for
from drsplat.registration.output import PlyTarget
from drsplat.registration.pairlog import PairLog
from drsplat.synthetic import write_dataset

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("faults") / "tiny", "tiny", 0, show_progress=False)


@pytest.fixture(scope="module")
def uninterrupted(tiny, tmp_path_factory) -> bytes:
    out = tmp_path_factory.mktemp("reference") / "reg.ply"
    assert main(_args(tiny, out)) == 0
    return out.read_bytes()


def _args(tiny: Path, out: Path, *extra: str) -> list[str]:
    return ["register", str(tiny / "scene.ply"), "--source", str(tiny), "--features", str(tiny / "features"), "--out", str(out),
            "--no-progress", *extra]


class _FullDisk:
    """A binary file whose writes fail with ENOSPC from the `calls`-th on, as on a full disk."""

    def __init__(self, file, calls: int):
        self._file, self._left = file, calls

    def write(self, data) -> int:
        self._left -= 1
        if self._left <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return self._file.write(data)

    def __getattr__(self, name):
        return getattr(self._file, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self._file.close()


class _CtrlC(_FullDisk):
    """A binary file whose `calls`-th write is where Ctrl-C arrives."""

    def write(self, data) -> int:
        self._left -= 1
        if self._left <= 0:
            raise KeyboardInterrupt
        return self._file.write(data)


def _fill_disk_in(cls, attribute: str, opener: str, calls: int, monkeypatch, failing=_FullDisk) -> None:
    """Make the file `attribute` that `cls.opener` opens fail like a full disk (or as `failing` does) from its `calls`-th write."""
    original = getattr(cls, opener)

    def opened(self, *args, **kwargs):
        result = original(self, *args, **kwargs)
        setattr(self, attribute, failing(getattr(self, attribute), calls))
        return result

    monkeypatch.setattr(cls, opener, opened)


def test_disk_full_while_writing_the_output_keeps_the_checkpoint_and_the_rerun_resumes(tiny, uninterrupted, tmp_path, monkeypatch, capsys):
    out = tmp_path / "reg.ply"
    monkeypatch.setattr("drsplat.registration.output.WRITE_CHUNK", 512)  # rows are written in several chunks
    _fill_disk_in(PlyTarget, "_body", "open", 3, monkeypatch)
    assert main(_args(tiny, out, "--memory-budget", "16GB")) == 1
    err = capsys.readouterr().err
    assert f"{out}: the disk is full" in err
    left = sorted(p.name for p in tmp_path.iterdir())  # no half file, no temp body: the log and the mode's statistics snapshot
    assert not out.exists() and left == sorted([checkpoint_path_for(out).name, aggregate_stats_path(checkpoint_path_for(out)).name])
    assert f"kept the registration checkpoint {checkpoint_path_for(out)} (16 of 16 views" in err and "resumes from it" in err
    monkeypatch.undo()  # space freed
    assert main(_args(tiny, out)) == 0
    assert "16 of 16 views already registered" in capsys.readouterr().err
    assert out.read_bytes() == uninterrupted and sorted(p.name for p in tmp_path.iterdir()) == ["reg.ply"]


def test_ctrl_c_during_the_views_says_the_kept_checkpoint_once(tiny, uninterrupted, tmp_path, monkeypatch, capsys):
    """Round 54's leftover: a registration stopped during its views said the kept checkpoint twice, in its warning
    (with the views it holds) and again in the last line. The last line now says only what the warning does not."""
    out = tmp_path / "reg.ply"
    _fill_disk_in(PairLog, "_file", "__init__", 5 * 8 + 1, monkeypatch, _CtrlC)  # the 6th view's first write
    assert main(_args(tiny, out)) == 1
    monkeypatch.undo()
    err = capsys.readouterr().err
    assert err.count(str(checkpoint_path_for(out))) == 1 and f"kept the registration checkpoint {checkpoint_path_for(out)} (5 of 16 views" in err, err
    assert err.rstrip().splitlines()[-1] == "ERROR: interrupted; no partial output file was left", err
    assert main(_args(tiny, out)) == 0
    assert "5 of 16 views already registered" in capsys.readouterr().err
    assert out.read_bytes() == uninterrupted


def test_disk_full_while_logging_views_names_the_log(tiny, uninterrupted, tmp_path, monkeypatch, capsys):
    out = tmp_path / "reg.ply"
    _fill_disk_in(PairLog, "_file", "__init__", 5 * 8 + 1, monkeypatch)  # a record is 8 writes: the 6th view's first fails
    assert main(_args(tiny, out)) == 1
    err = capsys.readouterr().err
    assert f"{checkpoint_path_for(out)}: the disk is full" in err and "(5 of 16 views" in err
    monkeypatch.undo()
    assert main(_args(tiny, out)) == 0
    assert "5 of 16 views already registered" in capsys.readouterr().err
    assert out.read_bytes() == uninterrupted


def test_a_stop_whose_statistics_cannot_be_saved_keeps_no_checkpoint_it_could_not_resume(tiny, uninterrupted, tmp_path, monkeypatch,
                                                                                         capsys):
    """Round 72b F2: a run stopped on a full disk before the mode's first statistics snapshot said "kept the registration
    checkpoint (5 of 16 views) ... resumes from it", and the rerun redid every view. With no statistics saved the log
    could resume nothing: it is removed, and the message says why."""
    from drsplat.registration.checkpoint import Checkpoint

    def no_room(self, views):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self.stats_path))

    out = tmp_path / "reg.ply"
    monkeypatch.setattr(Checkpoint, "_snapshot", no_room)
    _fill_disk_in(PairLog, "_file", "__init__", 5 * 8 + 1, monkeypatch)
    assert main(_args(tiny, out)) == 1
    err = capsys.readouterr().err
    assert "the registration checkpoint was removed: the aggregation statistics of its 5 views could not be saved" in err, err
    assert "kept the registration checkpoint" not in err and not checkpoint_path_for(out).exists()
    monkeypatch.undo()
    assert main(_args(tiny, out)) == 0
    assert "already registered" not in capsys.readouterr().err and out.read_bytes() == uninterrupted


def test_disk_full_while_the_check_spills_its_tables_names_the_spill_and_the_rerun_resumes(tiny, uninterrupted, tmp_path, monkeypatch, capsys):
    """The default mode's check with its support tables capped at nothing, on a full disk: one error
    naming the spill file and what to do, no spill folder left, the checkpoint kept; the rerun
    (space freed) resumes to the uninterrupted bytes."""
    import builtins

    import drsplat.registration.check as check
    import drsplat.registration.supports as supports

    out = tmp_path / "reg.ply"
    monkeypatch.setattr(check, "SUPPORT_TABLE_BYTES", 0)
    monkeypatch.setattr(supports, "open", lambda path, mode="r", *a, **k: _FullDisk(builtins.open(path, mode, *a, **k), 2) if "w" in mode
                        else builtins.open(path, mode, *a, **k), raising=False)
    assert main(_args(tiny, out)) == 1
    err = capsys.readouterr().err
    assert "support-0.bin: the mask check could not spill its support tables to disk (the disk is full" in err and "free space there" in err
    assert "Traceback" not in err and f"kept the registration checkpoint {checkpoint_path_for(out)}" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([checkpoint_path_for(out).name, aggregate_stats_path(checkpoint_path_for(out)).name])
    monkeypatch.undo()
    assert main(_args(tiny, out)) == 0
    assert "16 of 16 views already registered" in capsys.readouterr().err
    assert out.read_bytes() == uninterrupted and sorted(p.name for p in tmp_path.iterdir()) == ["reg.ply"]


def test_a_killed_run_reruns_to_the_same_bytes(tiny, uninterrupted, tmp_path):
    """SIGKILL in the middle of the views (no handler runs): the rerun resumes from the torn log."""
    out = tmp_path / "reg.ply"
    log = checkpoint_path_for(out)
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen([sys.executable, "-m", "drsplat", *_args(tiny, out)], cwd=tmp_path, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 120
        while proc.poll() is None and time.time() < deadline and not (log.exists() and log.stat().st_size > 4096):
            time.sleep(0.002)
        killed = proc.poll() is None
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait()
    assert killed, "the run finished before it could be killed"
    assert not out.exists() and log.exists()
    assert main(_args(tiny, out)) == 0
    assert out.read_bytes() == uninterrupted and not log.exists()


# ---------------------------------------------------------------------------------------------- round 6: what a resume trusts


def _stopped_after_five_views(dataset: Path, out: Path, monkeypatch, *extra: str) -> None:
    """A registration that stops (a full disk) after logging five views, keeping its checkpoint."""
    with monkeypatch.context() as m:
        _fill_disk_in(PairLog, "_file", "__init__", 5 * 8 + 1, m)
        assert main(_args(dataset, out, *extra)) == 1


def _copy(tiny: Path, tmp_path: Path) -> Path:
    import shutil

    return Path(shutil.copytree(tiny, tmp_path / "ds", symlinks=True))


def test_features_edited_between_runs_restart_the_checkpoint(tiny, tmp_path, monkeypatch, capsys):
    """The log holds the logged views' masks and embeddings: features regenerated or edited in the
    same folder between the stop and the rerun must not be mixed with them (the rerun equals a fresh
    run on the new features; it resumed with the old ones before)."""
    import numpy as np

    ds = _copy(tiny, tmp_path)
    out = tmp_path / "reg.ply"
    _stopped_after_five_views(ds, out, monkeypatch)
    feats = ds / "features" / "orbit_000_f.npy"
    np.save(feats, np.load(feats)[::-1].copy())  # one logged view's embeddings, rows reversed
    capsys.readouterr()
    assert main(_args(ds, out)) == 0
    err = capsys.readouterr().err
    assert "the feature files of view orbit_000 changed since it was logged; starting from scratch" in err  # round 89b F2: "the 0 views before it"
    fresh = tmp_path / "fresh" / "reg.ply"
    assert main(_args(ds, fresh)) == 0
    assert out.read_bytes() == fresh.read_bytes()


def test_features_rewritten_with_their_old_size_and_mtime_restart_the_checkpoint(tiny, tmp_path, monkeypatch, capsys):
    """`cp -p` / `rsync -a` of edited features puts the old modification time back, and rows reversed
    keep the size: the stamp was size:mtime only, so the resume mixed the old views' logged masks
    with the new files (round 28). The status-change time, which no call can set back, tells them apart."""
    import os

    import numpy as np

    ds = _copy(tiny, tmp_path)
    out = tmp_path / "reg.ply"
    _stopped_after_five_views(ds, out, monkeypatch)
    feats = ds / "features" / "orbit_001_f.npy"
    before = feats.stat()
    np.save(feats, np.load(feats)[::-1].copy())
    os.utime(feats, ns=(before.st_atime_ns, before.st_mtime_ns))
    assert (feats.stat().st_size, feats.stat().st_mtime_ns) == (before.st_size, before.st_mtime_ns)
    capsys.readouterr()
    assert main(_args(ds, out)) == 0
    err = capsys.readouterr().err
    assert "the feature files of view orbit_001 changed since it was logged; resuming from the 1 view before it" in err
    # the default mode's statistics cover the 5 views logged: they restart, and it is said (round 72b F1: "resuming from ...",
    # then nothing resumed and no word)
    assert "its statistics snapshot covers 5 views, more than the 1 it keeps now; the aggregation statistics restart" in err, err
    assert not aggregate_stats_path(checkpoint_path_for(out)).exists()
    fresh = tmp_path / "fresh" / "reg.ply"
    assert main(_args(ds, fresh)) == 0
    assert out.read_bytes() == fresh.read_bytes()


def _zero_some_opacities(scene) -> None:
    scene.opacity_logits[1::7] = -20.0  # floaters removed, N kept; not on the old digest's sampled rows alone


def _sh_past_the_render_limit(scene) -> None:
    scene.sh[::5, 0, 0] = 1e35  # finite float32: the loader keeps the row, the rasterizer skips it


@pytest.mark.parametrize("edit", [_zero_some_opacities, _sh_past_the_render_limit], ids=["opacities", "sh_past_render_limit"])
def test_a_scene_edited_without_changing_its_size_restarts_the_checkpoint(tiny, tmp_path, monkeypatch, capsys, edit):
    """Floaters removed by zeroing their opacity keep N: the scene digest covers every Gaussian. The SH
    are not in the digest (a recoloured scene resumes), but an SH coefficient past MAX_SH_COEFFICIENT
    keeps its Gaussian out of every view: a log begun before such an edit held views that saw it, and
    the resume wrote a field neither scene gives (probe round 40). Either way: a fresh run's bytes."""
    from drsplat.scene import load_ply, save_ply

    ds = _copy(tiny, tmp_path)
    out = tmp_path / "reg.ply"
    _stopped_after_five_views(ds, out, monkeypatch)
    scene = load_ply(ds / "scene.ply")
    edit(scene)
    (ds / "scene.ply").unlink()
    save_ply(scene, ds / "scene.ply")
    capsys.readouterr()
    assert main(_args(ds, out)) == 0
    assert "(the scene's Gaussians changed); starting over" in capsys.readouterr().err
    fresh = tmp_path / "fresh" / "reg.ply"
    assert main(_args(ds, fresh)) == 0
    assert out.read_bytes() == fresh.read_bytes()


@pytest.mark.parametrize("stop", ["after_encoding", "copying_the_body"])
def test_an_earlier_output_keeps_its_codebook_until_the_new_ply_is_in_place(tiny, tmp_path, monkeypatch, stop):
    """The codebook beside --out was written at the first encoded chunk: a run stopped in the rest of
    the write left the earlier output naming a codebook it no longer matched (probe round 40). Stopped
    once every block is encoded, or while the body is copied behind a header of another length (the
    path of a FIFO output or a widened header; the review of round 40 found the codebook written
    before that copy), the earlier output and its codebook are as they were."""
    from drsplat.lang import codebook_path_for
    from drsplat.registration import output

    out = tmp_path / "reg.ply"
    assert main(_args(tiny, out, "--codebook", "scene", "--topk", "20")) == 0
    book, ply = codebook_path_for(out).read_bytes(), out.read_bytes()
    seen = []

    def full_disk(*args):
        seen.append(codebook_path_for(out).read_bytes() == book)
        raise OSError(errno.ENOSPC, "No space left on device", str(out))

    if stop == "after_encoding":
        monkeypatch.setattr(output.PlyTarget, "close", full_disk)
    else:
        opened = output.PlyTarget.open
        monkeypatch.setattr(output.PlyTarget, "open", lambda self, codebook, rows_hint=None: opened(self, codebook, None))
        monkeypatch.setattr(output.shutil, "copyfileobj", full_disk)
    assert main(_args(tiny, out, "--codebook", "scene", "--topk", "10")) == 1
    assert seen == [True] and out.read_bytes() == ply and codebook_path_for(out).read_bytes() == book


def test_a_second_registration_into_the_same_output_is_refused_at_once(tiny, tmp_path, capsys):
    """Two runs writing one output shared its checkpoint: the second rewrote the log under the first
    (a mixed field written over a good one, false errors, tracebacks). Now it fails before any work."""
    from drsplat.registration.checkpoint import RunLock, lock_path_for

    out = tmp_path / "reg.ply"
    holder = RunLock.acquire(lock_path_for(checkpoint_path_for(out)), "reg.ply")  # a run in progress (flock: per open file)
    try:
        assert main(_args(tiny, out)) == 1
        err = capsys.readouterr().err
        assert "another registration is writing reg.ply" in err and "Traceback" not in err
        assert not out.exists() and not checkpoint_path_for(out).exists()
    finally:
        holder.release()
    assert main(_args(tiny, out)) == 0 and sorted(p.name for p in tmp_path.iterdir()) == ["reg.ply"]


def test_an_output_folder_that_takes_no_file_is_one_error_naming_the_folder(tiny, tmp_path, monkeypatch, capsys):
    """Probe round 12: a read-only output folder was refused naming the lock file the run tried to make
    (`.reg.ply.register.lock: permission denied`), which the user never asked for. Now the folder."""
    from drsplat.registration import checkpoint

    folder = tmp_path / "locked"
    folder.mkdir()
    real_open = os.open

    def refuse_in_folder(path, *args, **kwargs):
        if Path(path).parent == folder:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(checkpoint.os, "open", refuse_in_folder)
    assert main(_args(tiny, folder / "reg.ply")) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert f"cannot write {folder}: the folder takes no new file (permission denied)" in err and "another folder" in err
    assert ".lock" not in err and list(folder.iterdir()) == []


def test_a_second_run_into_the_same_output_is_refused_before_the_scene_is_read(tiny, tmp_path, capsys, monkeypatch):
    """Round 67b F1: the lock was taken inside the registration, after the scene was loaded and the near plane decided
    (21 s and 1.5 GB on a 3M-Gaussian scene) before "another registration is writing"."""
    import drsplat.splat_formats as formats
    from drsplat.registration.checkpoint import RunLock, lock_path_for

    out = tmp_path / "reg.ply"
    holder = RunLock.acquire(lock_path_for(checkpoint_path_for(out)), "reg.ply")
    try:
        with monkeypatch.context() as patched:
            patched.setattr(formats, "load_scene_report", lambda *a, **k: pytest.fail("the scene was read"))
            assert main(_args(tiny, out)) == 1
        assert "another registration is writing reg.ply" in capsys.readouterr().err
    finally:
        holder.release()
    assert main(_args(tiny, out)) == 0 and out.is_file()


def test_the_run_lock_is_held_from_before_the_scene_is_read_to_the_end(tiny, tmp_path, monkeypatch):
    """Round 68a F1: the early check took the lock and released it, so a second run started while the first read its
    scene passed it, read its own scene and decided its own plane before the registration's lock refused it. The lock
    is held from before the scene is read; the run ends with it released and its file gone."""
    import drsplat.splat_formats as formats
    from drsplat.errors import DrsplatError
    from drsplat.registration.checkpoint import lock_path_for, lock_run

    out = tmp_path / "reg.ply"
    real, seen = formats.load_scene_report, []

    def reading(*args, **kwargs):
        with pytest.raises(DrsplatError, match="another registration is writing reg.ply"):
            lock_run(checkpoint_path_for(out))
        seen.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(formats, "load_scene_report", reading)
    assert main(_args(tiny, out)) == 0 and seen == [1] and out.is_file()
    assert not lock_path_for(checkpoint_path_for(out)).exists()
    lock_run(checkpoint_path_for(out)).release()  # free again


def test_a_run_whose_inputs_fail_leaves_no_output_folder(tiny, tmp_path, capsys):
    """Round 68b F1: the early lock check made --out's folders before the inputs were read, so a run with a missing
    scene said "created the folder" and left it empty."""
    out = tmp_path / "new" / "deeper" / "reg.ply"
    args = _args(tiny, out)
    args[1] = str(tmp_path / "missing.ply")
    assert main(args) == 1
    assert "created the folder" not in capsys.readouterr().err and not (tmp_path / "new").exists()


def test_a_run_into_a_symlink_and_one_into_its_target_share_one_lock(tiny, tmp_path, capsys):
    """Probe round 13: the lock was named after the link, so a run into `link.ply -> out/reg.ply` and
    one into `out/reg.ply` took two locks and both wrote the same file."""
    from drsplat.registration.checkpoint import RunLock, lock_path_for

    (tmp_path / "out").mkdir()
    (tmp_path / "links").mkdir()
    target = tmp_path / "out" / "reg.ply"
    link = tmp_path / "links" / "link.ply"
    link.symlink_to(target)
    assert checkpoint_path_for(link) == checkpoint_path_for(target)
    holder = RunLock.acquire(lock_path_for(checkpoint_path_for(target)), "reg.ply")
    try:
        assert main(_args(tiny, link)) == 1
        assert "another registration is writing reg.ply" in capsys.readouterr().err
    finally:
        holder.release()
    assert main(_args(tiny, link)) == 0 and link.is_symlink() and target.is_file()


@pytest.mark.parametrize("fault", ["create", "remove"])
def test_a_folder_that_keeps_or_refuses_files_is_refused_before_any_work(tiny, tmp_path, monkeypatch, capsys, fault):
    """Probe round 13: a folder that takes no new file but holds a killed run's lock file (chattr +i)
    let the lock open and failed after the fit stage, naming the lock; an append-only folder
    (chattr +a) ran the whole registration and then failed to rename the output into place, again
    naming the lock. Both are now refused when the lock is taken, naming the folder."""
    from drsplat.registration import checkpoint

    folder = tmp_path / "odd"
    folder.mkdir()
    lock = checkpoint.lock_path_for(checkpoint_path_for(folder / "reg.ply"))
    lock.touch()  # a killed run's
    real_open, real_unlink = os.open, os.unlink

    def open_(path, flags, *args, **kwargs):
        if fault == "create" and Path(path).parent == folder and not Path(path).exists():
            raise PermissionError(errno.EPERM, os.strerror(errno.EPERM), str(path))
        return real_open(path, flags, *args, **kwargs)

    def unlink(path, *args, **kwargs):
        if fault == "remove" and Path(path).parent == folder:
            raise PermissionError(errno.EPERM, os.strerror(errno.EPERM), str(path))
        return real_unlink(path, *args, **kwargs)

    def no_fit(*args, **kwargs):
        raise AssertionError("the fit stage ran before the folder was checked")

    monkeypatch.setattr(checkpoint.os, "open", open_)
    monkeypatch.setattr(checkpoint.os, "unlink", unlink)
    import drsplat.registration.driver as driver

    monkeypatch.setattr(driver, "_fit_stage", no_fit)
    assert main(_args(tiny, folder / "reg.ply")) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    words = "the folder takes no new file" if fault == "create" else "files made in the folder cannot be removed or renamed"
    assert f"cannot write {folder}: {words}" in err and "operation not permitted" in err and "another folder" in err


def test_fifo_outputs_of_one_name_in_two_folders_get_their_own_checkpoints(tmp_path):
    """Probe round 14: a FIFO's (or device's) checkpoint and lock lie in the temp folder, named after
    the FIFO alone: two runs into `a/out.ply` and `b/out.ply` refused each other, and one threw the
    other's interrupted checkpoint away. The name now carries a digest of the path."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    os.mkfifo(tmp_path / "a" / "out.ply")
    os.mkfifo(tmp_path / "b" / "out.ply")
    a, b = checkpoint_path_for(tmp_path / "a" / "out.ply"), checkpoint_path_for(tmp_path / "b" / "out.ply")
    assert a != b and a.parent == b.parent and a.name.startswith(".out.ply.") and a.name.endswith(".register.log")
    assert checkpoint_path_for(tmp_path / "a" / "out.ply") == a  # the same FIFO resumes from its own
    assert checkpoint_path_for(tmp_path / "a" / "reg.ply") == tmp_path / "a" / ".reg.ply.register.log"  # a file's: beside it, as before


def test_a_loop_of_symbolic_links_as_the_output_is_refused_and_kept(tiny, tmp_path, capsys):
    """Probe round 14: `x.ply -> y.ply -> x.ply` as --out was replaced by a regular file."""
    (tmp_path / "x.ply").symlink_to(tmp_path / "y.ply")
    (tmp_path / "y.ply").symlink_to(tmp_path / "x.ply")
    assert main(_args(tiny, tmp_path / "x.ply")) == 1
    err = capsys.readouterr().err
    assert "loop of symbolic links" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert (tmp_path / "x.ply").is_symlink() and (tmp_path / "y.ply").is_symlink()


def test_a_restart_names_what_changed_and_leaves_no_stale_statistics(tiny, tmp_path, monkeypatch, capsys):
    out = tmp_path / "reg.ply"
    _stopped_after_five_views(tiny, out, monkeypatch)  # the default mode: a statistics snapshot may be beside the log
    capsys.readouterr()
    assert main(_args(tiny, out, "--aggregate", "paper", "--topk", "20")) == 0
    assert "(--aggregate, --topk changed); starting over" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["reg.ply"]


def test_a_log_begun_on_a_gpu_is_not_resumed_on_the_cpu_but_the_cpu_engines_share_theirs(tiny):
    """Probe round 26: the engine was no checkpoint parameter, so a log the torch engine began on CUDA
    (float32 rounding away from the CPU's) was resumed by numba without a word, into a field equal to
    neither run's. The CPU engines log the same bits, so they still resume each other's logs."""
    from drsplat.cameras import load_cameras
    from drsplat.registration.checkpoint import checkpoint_params
    from drsplat.registration.pairlog import changed_params
    from drsplat.scene import load_ply

    scene, cameras = load_ply(tiny / "scene.ply"), load_cameras(tiny)

    def params(engine, device):
        return checkpoint_params(scene, cameras, tiny / "features", 40, 1, "paper", engine=engine, device=device)

    assert params("numba", "cpu") == params("torch", "cpu")
    assert params("torch", "cuda") == params("torch", "cuda:1")
    gpu, cpu = params("torch", "cuda"), params("numba", "cpu")
    assert gpu != cpu and changed_params(gpu, cpu).startswith("the engine (--engine / --device")


def test_output_names_up_to_the_file_system_limit_register(tiny, tmp_path):
    """A 250-byte output name: the checkpoint, its snapshot and lock used to add their suffixes to it
    and pass 255 bytes ('file name is too long', naming a file the user never asked for)."""
    out = tmp_path / ("a" * 246 + ".ply")
    assert main(_args(tiny, out)) == 0 and out.is_file() and sorted(p.name for p in tmp_path.iterdir()) == [out.name]


def test_a_checkpoint_path_that_is_a_link_or_folder_is_refused_and_its_target_kept(tiny, tmp_path, capsys):
    out = tmp_path / "reg.ply"
    precious = tmp_path / "notes.txt"
    precious.write_text("mine")
    checkpoint_path_for(out).symlink_to(precious)
    assert main(_args(tiny, out)) == 1
    assert "is where drsplat keeps this registration's checkpoint, but it is a symbolic link" in capsys.readouterr().err
    assert precious.read_text() == "mine" and not out.exists()
    checkpoint_path_for(out).unlink()  # round 60c: a write-protected file there was truncated and deleted (root ignores the mode)
    checkpoint_path_for(out).write_text("kept")
    checkpoint_path_for(out).chmod(0o444)
    try:
        assert main(_args(tiny, out)) == 1
        assert "but it is a write-protected file (mode 0444); move it away" in capsys.readouterr().err
        assert checkpoint_path_for(out).read_text() == "kept" and not out.exists()
    finally:
        checkpoint_path_for(out).chmod(0o644)
    checkpoint_path_for(out).unlink()
    checkpoint_path_for(out).mkdir()
    assert main(_args(tiny, out)) == 1
    assert "but it is a folder" in capsys.readouterr().err


def test_ray_workers_without_ray_is_said(tiny, uninterrupted, tmp_path, capsys):
    out = tmp_path / "reg.ply"
    assert main(_args(tiny, out, "--ray-workers", "3")) == 0
    assert "--ray-workers 3 applies to a run on Ray (--ray)" in capsys.readouterr().err and out.read_bytes() == uninterrupted


def test_features_rewritten_while_the_registration_reads_them_are_one_error_and_the_rerun_resumes(tiny, uninterrupted, tmp_path,
                                                                                                     monkeypatch, capsys):
    """Another `drsplat features` rewriting the folder while `register` read it gave a field mixing
    two sets of features, exit 0 (a concurrency probe, 2026-11-30). The views' stamps are taken
    before any is read and checked after the last: one error, nothing written, and the rerun (the
    files now final) resumes the views whose files did not change and gives the bytes of a run on
    the final files."""
    import shutil

    import drsplat.registration.compute as compute

    data = tmp_path / "data"
    shutil.copytree(tiny, data)
    feats = sorted((data / "features").glob("*_f.npy"))
    read = compute.load_view_features
    calls = []

    def and_features_rewrite_a_file(*args, **kwargs):
        calls.append(1)
        if len(calls) == 6:  # a later view's file rewritten (same content, new mtime) after five views were read
            st = os.stat(feats[-1])
            os.utime(feats[-1], ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
        return read(*args, **kwargs)

    monkeypatch.setattr(compute, "load_view_features", and_features_rewrite_a_file)
    out = tmp_path / "reg.ply"
    assert main(_args(data, out)) == 1
    err = capsys.readouterr().err
    assert "changed while the registration read them" in err and feats[-1].name[: -len("_f.npy")] in err, err
    assert not out.exists() and checkpoint_path_for(out).exists()
    monkeypatch.setattr(compute, "load_view_features", read)
    assert main(_args(data, out)) == 0
    assert out.read_bytes() == uninterrupted and not checkpoint_path_for(out).exists()


def test_cameras_that_moved_by_an_ulp_do_not_resume_the_old_log(tiny, tmp_path):
    """Round 22: the log's header printed the intrinsics to 6 digits and rounded the poses to 9
    decimals, so cameras 3.5e-7 apart resumed each other's views and the result was neither run's.
    Any change of a camera's bits starts over; the same cameras still resume."""
    from dataclasses import replace

    import numpy as np

    from drsplat.cameras import load_cameras
    from drsplat.registration import RegisterOptions, register_features
    from drsplat.registration.checkpoint import _views_digest
    from drsplat.scene import load_ply
    from drsplat.utils import Cancelled, CancelToken

    scene, cams, features = load_ply(tiny / "scene.ply"), load_cameras(tiny), tiny / "features"
    assert _views_digest(cams) == _views_digest(load_cameras(tiny))
    for field in ("fx", "fy", "cx", "cy"):
        moved = [replace(cams[0], **{field: np.nextafter(getattr(cams[0], field), np.inf)}), *cams[1:]]
        assert _views_digest(moved) != _views_digest(cams), field
    turned = np.array(cams[0].R, np.float64)
    turned[0, 0] = np.nextafter(turned[0, 0], np.inf)
    assert _views_digest([replace(cams[0], R=turned), *cams[1:]]) != _views_digest(cams)

    new = [replace(c, fx=c.fx * (1 + 3e-7), cx=c.cx * (1 + 3e-7)) for c in cams]
    options, log_path, token = RegisterOptions(topk=10, aggregate="paper"), tmp_path / "run.log", CancelToken()
    with pytest.raises(Cancelled):
        register_features(scene, cams, features, options, checkpoint=log_path, cancel=token, show_progress=False,
                          on_progress=lambda done, total: token.cancel() if done == 5 else None)
    resumed = register_features(scene, new, features, options, checkpoint=log_path, show_progress=False)
    fresh = register_features(scene, new, features, options, show_progress=False)
    assert resumed.resumed_views == 0
    assert np.array_equal(resumed.weights, fresh.weights) and np.array_equal(resumed.features, fresh.features)


def test_a_checkpoint_this_user_may_not_rewrite_is_refused_before_any_work(tiny, tmp_path, monkeypatch, capsys):
    """Round 40: a run begun under another account left a log its owner alone may write; the rerun took it for an
    unreadable log ("starting from scratch") after the fit stage, then failed; a read error (EIO) would have
    truncated a log that may be whole. Both are now one error naming the log, before any work, the log kept."""
    from drsplat.registration import checkpoint as ck
    from drsplat.registration import pairlog

    out = tmp_path / "reg.ply"
    _stopped_after_five_views(tiny, out, monkeypatch)
    log_path = ck.checkpoint_path_for(out)
    kept = log_path.read_bytes()
    monkeypatch.setattr(ck, "_may_rewrite", lambda path: False)
    rendered = []
    monkeypatch.setattr(ck, "_scene_digest", lambda scene: rendered.append(1) or "x")  # any work on the scene
    capsys.readouterr()
    assert main(_args(tiny, out)) == 1
    err = capsys.readouterr().err
    assert "cannot be read and rewritten by this user" in err and str(log_path) in err and "starting from scratch" not in err
    assert log_path.read_bytes() == kept and not out.exists() and rendered == []
    monkeypatch.undo()

    def io_error(path, mode="r", *args, **kwargs):
        raise OSError(errno.EIO, "Input/output error", str(path))

    monkeypatch.setattr(pairlog, "open", io_error, raising=False)  # the log's own open in _valid_records
    capsys.readouterr()
    assert main(_args(tiny, out)) == 1
    assert "cannot be read to resume" in capsys.readouterr().err and log_path.read_bytes() == kept
