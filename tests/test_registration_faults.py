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


def _fill_disk_in(cls, attribute: str, opener: str, calls: int, monkeypatch) -> None:
    """Make the file `attribute` that `cls.opener` opens fail like a full disk from its `calls`-th write."""
    original = getattr(cls, opener)

    def opened(self, *args, **kwargs):
        result = original(self, *args, **kwargs)
        setattr(self, attribute, _FullDisk(getattr(self, attribute), calls))
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
