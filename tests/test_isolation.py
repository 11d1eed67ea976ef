"""The suite's own guarantees: files can run in any order (--reverse-files), and in two processes at
once (pytest-xdist) with the Ray cluster files on one of them; a test that leaves process-wide state
changed is reported (tests/process_state.py, checked by conftest)."""

from __future__ import annotations

import builtins
import os
import re
import signal
from pathlib import Path
from types import SimpleNamespace

import pytest

from tests.conftest import RAY_CLUSTER_FILES, pytest_xdist_make_scheduler, reversed_by_file
from tests.process_state import ProcessState


def test_reverse_files_reverses_the_files_and_keeps_each_files_order():
    items = [SimpleNamespace(path=Path(f), name=n) for f, n in [("a.py", 1), ("a.py", 2), ("b.py", 3), ("c.py", 4), ("c.py", 5)]]
    assert [i.name for i in reversed_by_file(items)] == [4, 5, 3, 1, 2]


def test_the_guard_names_what_a_test_changed(monkeypatch, tmp_path):
    before = ProcessState.capture()
    assert before.changes(ProcessState.capture()) == []
    monkeypatch.setattr(builtins, "print", lambda *args, **kwargs: None)  # what Ray's driver did
    monkeypatch.setenv("DRSPLAT_ISOLATION_PROBE", "1")
    monkeypatch.chdir(tmp_path)
    previous = signal.signal(signal.SIGUSR1, lambda signum, frame: None)
    try:
        changes = before.changes(ProcessState.capture())
    finally:
        signal.signal(signal.SIGUSR1, previous)
    assert "builtins.print" in changes and "os.environ['DRSPLAT_ISOLATION_PROBE']" in changes and "the SIGUSR1 handler" in changes
    assert any(c.startswith("the working directory") and str(tmp_path) in c for c in changes)
    monkeypatch.undo()
    assert before.changes(ProcessState.capture()) == [] and os.getcwd() == before.cwd


def test_an_environment_variable_a_library_sets_on_import_may_appear_but_not_change(monkeypatch):
    monkeypatch.delenv("TCM_ENABLE", raising=False)
    before = ProcessState.capture()
    monkeypatch.setenv("TCM_ENABLE", "1")  # open3d's import
    assert before.changes(ProcessState.capture()) == []
    after_import = ProcessState.capture()
    monkeypatch.setenv("TCM_ENABLE", "0")
    assert after_import.changes(ProcessState.capture()) == ["os.environ['TCM_ENABLE']"]


def test_every_file_that_starts_a_ray_cluster_is_one_the_scheduler_keeps_together():
    """A new test file that starts a cluster (ray.cluster_utils, tests.ray_cluster, a local Ray run) must join
    RAY_CLUSTER_FILES, or under xdist it could run beside another cluster on this machine."""
    here = Path(__file__).parent
    starting = {p.name for p in here.glob("test_*.py") if p.name != Path(__file__).name and re.search(r'cluster_utils|two_node_cluster|ray\.init\(|ray start|ray="local"|"--ray"', p.read_text())}
    assert starting and starting <= RAY_CLUSTER_FILES, sorted(starting - RAY_CLUSTER_FILES)
    assert all((here / name).exists() for name in RAY_CLUSTER_FILES)


def test_the_scheduler_gives_the_ray_cluster_files_to_one_process_and_every_other_file_its_own_unit():
    pytest.importorskip("xdist", reason="the parallel run needs pytest-xdist (pip install -e '.[test]')")
    scheduler = pytest_xdist_make_scheduler(SimpleNamespace(getvalue={"dist": "loadfile", "tx": ["2*popen"]}.get), None)
    scope = scheduler._split_scope
    assert scope("tests/test_reduce.py::test_a[x]") == scope("tests/test_distributed.py::test_b") == scope("tests/test_features.py::test_c")
    assert scope("tests/test_scene.py::test_d") == "tests/test_scene.py" != scope("tests/test_reduce.py::test_a[x]")
    assert pytest_xdist_make_scheduler(SimpleNamespace(getvalue={"dist": "load"}.get), None) is None  # other modes: xdist's own
