"""Ray registration on a cluster whose nodes differ from the driver's or fail (round 42 of docs/hostile.md).

A two-node cluster on this machine (ray.cluster_utils.Cluster, one CPU each) stands in for a real
one: a worker slot that never starts (its CPU taken by another job, or its node lost with no room
to restart it) must not hang the run or a Ctrl-C; a node whose feature files are not the driver's
(a stale copy) or that imports another drsplat, numpy or numba must be one error, never a mixed field.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from drsplat.cameras import load_cameras
from drsplat.errors import Cancelled, DrsplatError
from drsplat.registration import RegisterOptions, register_features
from drsplat.scene import load_ply
from drsplat.synthetic import write_dataset
from drsplat.utils import CancelToken
from tests.ray_cluster import two_node_cluster

ray = pytest.importorskip("ray", reason="the Ray backend needs the optional ray package (pip install -e '.[ray]')")

ON_RAY = RegisterOptions(ray="auto", aggregate="paper")


@pytest.fixture(scope="module")
def cluster():
    """A two-node Ray cluster on this machine (tests.ray_cluster); the driver joins it."""
    with two_node_cluster() as c:
        yield c


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("tiny") / "data", "tiny", 0, show_progress=False)


@pytest.fixture(scope="module")
def local(tiny):
    scene, cams = load_ply(tiny / "scene.ply"), load_cameras(tiny)[:8]
    return scene, cams, register_features(scene, cams, tiny / "features", RegisterOptions(aggregate="paper"), show_progress=False)


@pytest.fixture
def busy_cpu(cluster):
    """Another job's actor holding one of the cluster's two CPUs: the run sees two slots, gets one."""

    @ray.remote(num_cpus=1)
    class Hog:
        def ping(self) -> int:
            return 1

    hog = Hog.remote()
    ray.get(hog.ping.remote())
    yield
    ray.kill(hog, no_restart=True)


def test_a_worker_that_never_starts_has_its_views_moved_not_waited_for(local, tiny, busy_cpu, monkeypatch, caplog):
    """Was: the second actor waited forever for a CPU and the run with it (397 s until the other job
    ended; a real node lost before its actor ran hung past 240 s). Now its calls go to the worker
    that runs, the same field."""
    scene, cams, reference = local
    monkeypatch.setattr("drsplat.registration.ray.STALL_SECONDS", 2.0)
    monkeypatch.setattr("drsplat.registration.ray.VIEWS_PER_TASK", 1)
    t0 = time.monotonic()
    with caplog.at_level("WARNING"):
        result = register_features(scene, cams, tiny / "features", ON_RAY, show_progress=False)
    assert time.monotonic() - t0 < 50
    assert "a registration worker was lost" in caplog.text
    np.testing.assert_array_equal(result.features, reference.features)
    np.testing.assert_array_equal(result.weights, reference.weights)


def test_a_cancel_is_seen_while_the_driver_waits_for_a_worker_that_never_starts(local, tiny, busy_cpu, monkeypatch):
    """Was: Ctrl-C (or SIGTERM) said "stopping after the current view" and the process stayed until
    the other job freed its CPU. Now the wait checks the cancel token."""
    import drsplat.registration.ray as rr

    scene, cams, _ = local
    monkeypatch.setattr(rr, "STALL_SECONDS", 1e6)
    monkeypatch.setattr(rr, "VIEWS_PER_TASK", 1)
    token = CancelToken()
    executor_init = rr.RayExecutor.__init__

    def init(self, *args, **kwargs):  # the token the CLI's signal handler sets, set once the workers are asked for
        executor_init(self, *args, **kwargs)
        threading.Timer(3.0, token.cancel).start()

    monkeypatch.setattr(rr.RayExecutor, "__init__", init)
    t0 = time.monotonic()
    with pytest.raises(Cancelled):
        register_features(scene, cams, tiny / "features", ON_RAY, cancel=token, show_progress=False)
    assert time.monotonic() - t0 < 30


def test_a_feature_file_that_differs_on_a_worker_node_is_one_error(cluster, local, tiny, monkeypatch):
    """Was: a node holding a stale copy of the features folder (same sizes, other embeddings) gave
    another field, exit 0. Now the driver sends each view's file marks and the worker compares.
    (The driver's mark of one file is changed here: the worker's copy then differs from it.)"""
    import drsplat.registration.ray as rr

    scene, cams, _ = local
    mark = rr.feature_mark

    def drivers_mark(path):
        size, crc = mark(path)
        return (size, crc ^ 1) if path.name == f"{cams[3].name}_f.npy" else (size, crc)

    monkeypatch.setattr(rr, "feature_mark", drivers_mark)
    with pytest.raises(DrsplatError) as failed:
        register_features(scene, cams, tiny / "features", ON_RAY, show_progress=False)
    message = str(failed.value)
    assert message.startswith(f"{tiny / 'features' / cams[3].name}_f.npy: differs on the Ray worker node ")
    assert "other contents" in message and f"every node needs the driver's {tiny / 'features'} at the same path" in message


def test_a_node_that_imports_other_code_is_refused_before_any_view(cluster, local, tiny, monkeypatch):
    """Was: a node importing another drsplat (`--ray auto` puts the driver's folder on every node's
    PYTHONPATH, which on another host holds another checkout or nothing) computed its views with
    it: another field, exit 0. Now one probe per node compares drsplat's sources, Python, numpy and
    numba with the driver's. (The driver's numpy version is changed here.)"""
    scene, cams, _ = local
    monkeypatch.setattr(np, "__version__", "0.0.0")
    with pytest.raises(DrsplatError, match=r"^the Ray node .* runs other code than this driver \(numpy [0-9.]+ there, 0\.0\.0 here\)"):
        register_features(scene, cams, tiny / "features", ON_RAY, show_progress=False)


def test_a_worker_node_without_the_outputs_folder_fails_at_its_first_view(cluster, local, tiny, tmp_path, monkeypatch):
    """Was: a worker whose node does not share the output's folder created the shard folder on its
    own disk, wrote its shards there, and the run failed only after the whole view pass, when a
    reducer followed a pointer ("the worker's shard holding view orbit_002 cannot be read"). Now a
    worker that does not see the folder the driver made fails at its first view. (The job's shard
    folder is pointed at a folder nobody made here: what such a node sees.)"""
    import dataclasses

    import drsplat.registration.ray as rr
    from drsplat.registration import register

    scene, cams, _ = local
    executor_init = rr.RayExecutor.__init__
    elsewhere = tmp_path / "not-on-this-node" / ".reg.ply.register.log.shards"

    def init(self, geometry, job, *args, **kwargs):
        executor_init(self, geometry, dataclasses.replace(job, shard_dir=str(elsewhere)), *args, **kwargs)

    monkeypatch.setattr(rr.RayExecutor, "__init__", init)
    options = RegisterOptions(ray="auto", aggregate="paper", block_size=1024)
    with pytest.raises(DrsplatError, match=r"cannot write its shard of the log in .*not-on-this-node.* \(the driver made this folder, but "
                                           r"this node does not see it\): the partitioned reduce needs the output's folder"):
        register(scene, cams, tiny / "features", tmp_path / "out" / "reg.ply", options, show_progress=False)
    assert not elsewhere.exists()
