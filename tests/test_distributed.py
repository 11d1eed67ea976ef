"""The Ray backend on a real two-node Ray cluster started on this machine.

A head node and a second node (ray.cluster_utils.Cluster, one CPU each, small object stores)
run registration views and feature images; results must equal the local path, survive a
worker killed mid-run, resume after the driver stops, and an unreachable address must be one
clear error.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from drsplat.cameras import load_cameras
from drsplat.errors import Cancelled, DrsplatError
from drsplat.registration import RegisterOptions, register, register_features
from drsplat.scene import load_ply
from drsplat.synthetic import write_dataset
from drsplat.utils import CancelToken
from tests.ray_cluster import two_node_cluster

ray = pytest.importorskip("ray", reason="the Ray backend needs the optional ray package (pip install -e '.[ray]')")


@pytest.fixture(scope="module")
def cluster():
    """A two-node Ray cluster on this machine (tests.ray_cluster); the driver joins it."""
    with two_node_cluster() as c:
        yield c


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("tiny") / "data", "tiny", 0, show_progress=False)


ON_RAY = RegisterOptions(ray="auto")


def test_ray_registration_equals_local_in_memory_and_streamed(cluster, tiny, tmp_path):
    scene, cams = load_ply(tiny / "scene.ply"), load_cameras(tiny)
    local = register_features(scene, cams, tiny / "features", RegisterOptions(), show_progress=False)
    on_ray = register_features(scene, cams, tiny / "features", RegisterOptions(ray="auto", ray_workers=2), show_progress=False)
    np.testing.assert_array_equal(on_ray.features, local.features)
    np.testing.assert_array_equal(on_ray.weights, local.weights)
    assert (on_ray.num_pairs, on_ray.num_distinct_pairs) == (local.num_pairs, local.num_distinct_pairs)
    # the pipeline with --ray: streamed blocks, the same file as the local in-memory run
    a, b = tmp_path / "local.ply", tmp_path / "ray.ply"
    register(scene, cams, tiny / "features", a, RegisterOptions(), show_progress=False)
    register(scene, cams, tiny / "features", b, RegisterOptions(ray="auto", block_size=1024), show_progress=False)
    assert a.read_bytes() == b.read_bytes()


def test_ray_registration_with_floater_rejection_equals_local(cluster, tmp_path_factory, tmp_path):
    """--aggregate on a cluster: the workers run the mode's hook, the driver folds their per-view
    statistics in view order: the same sums, rejections and file as the local run."""
    data = write_dataset(tmp_path_factory.mktemp("hard") / "data", "hard-tiny", 0, show_progress=False)
    scene, cams = load_ply(data / "scene.ply"), load_cameras(data)
    local = register_features(scene, cams, data / "features", RegisterOptions(aggregate="anchor-reject"), show_progress=False)
    on_ray = register_features(scene, cams, data / "features", RegisterOptions(aggregate="anchor-reject", ray="auto", ray_workers=2), show_progress=False)
    assert on_ray.num_rejected == local.num_rejected > 0
    np.testing.assert_array_equal(on_ray.weights, local.weights)
    np.testing.assert_array_equal(on_ray.features, local.features)
    a, b = tmp_path / "local.ply", tmp_path / "ray.ply"
    register(scene, cams, data / "features", a, RegisterOptions(aggregate="reject"), show_progress=False)
    register(scene, cams, data / "features", b, RegisterOptions(aggregate="reject", ray="auto", block_size=512), show_progress=False)
    assert a.read_bytes() == b.read_bytes()


@pytest.mark.slow
def test_ray_registration_resumes_after_the_driver_stops(cluster, tiny, tmp_path, monkeypatch):
    scene, cams = load_ply(tiny / "scene.ply"), load_cameras(tiny)
    local = register_features(scene, cams, tiny / "features", RegisterOptions(), show_progress=False)
    ckpt = tmp_path / "run.log"
    token = CancelToken()

    def stop(done: int, total: int) -> None:
        if done == 7:
            token.cancel()

    monkeypatch.setattr("drsplat.registration.ray.VIEWS_PER_TASK", 1)
    with pytest.raises(Cancelled):
        register_features(scene, cams, tiny / "features", ON_RAY, checkpoint=ckpt, cancel=token, on_progress=stop, show_progress=False)
    monkeypatch.undo()
    resumed = register_features(scene, cams, tiny / "features", ON_RAY, checkpoint=ckpt, show_progress=False)
    assert resumed.resumed_views == 7
    np.testing.assert_array_equal(resumed.features, local.features)


def test_ray_workers_read_their_features_and_a_missing_file_fails_where_the_local_run_does(cluster, tiny, tmp_path, caplog, monkeypatch):
    """The workers read the feature files (the driver ships cameras): a file missing on a worker is
    one error naming the file and the node and saying every node needs the folder at the same path;
    the views before it are logged as a local run logs them (here view 3, the second of a call), and
    the rerun with the file back resumes from them and writes the local file."""
    import shutil

    import drsplat.registration.driver as driver

    scene, cams = load_ply(tiny / "scene.ply"), load_cameras(tiny)[:8]
    features = tmp_path / "features"
    shutil.copytree(tiny / "features", features)
    missing = features / f"{cams[3].name}_f.npy"
    kept = missing.read_bytes()
    read_headers = driver.read_feature_headers

    def then_gone_from_the_worker(*args, **kwargs):  # the driver saw the pair; the worker's node does not have the file
        headers = read_headers(*args, **kwargs)
        missing.unlink(missing_ok=True)
        return headers

    out, reference = tmp_path / "out" / "reg.ply", tmp_path / "local.ply"
    # not the default's fit stage: it reads its probe views (1, 3, 5, 7 of 8) on the driver first
    register(scene, cams, tiny / "features", reference, RegisterOptions(aggregate="check-vote-reject"), show_progress=False)
    monkeypatch.setattr(driver, "read_feature_headers", then_gone_from_the_worker)
    options = RegisterOptions(ray="auto", ray_workers=2, block_size=1024, aggregate="check-vote-reject")
    with caplog.at_level("WARNING"), pytest.raises(DrsplatError) as failed:
        register(scene, cams, features, out, options, show_progress=False)
    message = str(failed.value)
    assert message.startswith(f"{missing}: embedding file is missing on the Ray worker node ")
    assert f"every node needs {features} at the same path" in message
    assert f"(3 of {len(cams)} views" in caplog.text and not out.exists()
    monkeypatch.setattr(driver, "read_feature_headers", read_headers)
    missing.write_bytes(kept)
    resumed = register(scene, cams, features, out, options, show_progress=False)
    assert resumed.resumed_views == 3
    assert out.read_bytes() == reference.read_bytes()


def test_ray_workers_load_the_kernels_their_node_compiled(cluster, tiny):
    """Kernels are compiled once per node: after this process ran the views (its kernels are in
    numba's on-disk cache beside the package the workers import), every Ray worker loads them from
    the cache and compiles none; each reports its first view apart from the later ones."""
    scene, cams = load_ply(tiny / "scene.ply"), load_cameras(tiny)
    local = register_features(scene, cams, tiny / "features", RegisterOptions(), show_progress=False)
    # the default's fit stage computed its probe views, which the local view pass then did not compute again
    assert [w.pid for w in local.workers] == [os.getpid()] and len(local.workers[0].later_view_seconds) == len(cams) - len(local.fit.views) - 1
    on_ray = register_features(scene, cams, tiny / "features", RegisterOptions(ray="auto", ray_workers=2), show_progress=False)
    assert len(on_ray.workers) == 2 and set(on_ray.worker_peak_rss) == {w.pid for w in on_ray.workers}
    for worker in on_ray.workers:
        assert worker.kernels_compiled == 0 and worker.kernels_cached > 0, worker
        assert worker.first_view_seconds is not None
    assert sum(1 + len(w.later_view_seconds) for w in on_ray.workers) == len(cams)


def test_cuda_on_a_cluster_without_gpus_is_refused_up_front(cluster, tiny):
    scene, cams = load_ply(tiny / "scene.ply"), load_cameras(tiny)
    options = RegisterOptions(ray="auto", engine="torch", device="cuda")
    with pytest.raises(DrsplatError, match=r"^--device cuda on Ray needs workers with a GPU and a CPU on one node, but the cluster at auto has none$"):
        register_features(scene, cams, tiny / "features", options, show_progress=False)


def _task_pids(title: str) -> list[int]:
    """Processes of this machine whose title Ray set to `title` (a worker running that task)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if (entry / "cmdline").read_bytes().split(b"\0")[0].decode(errors="replace").startswith(title):
                    pids.append(int(entry.name))
            except OSError:
                continue
    return pids


def test_killed_worker_is_restarted_its_calls_retried_and_the_result_is_unchanged(cluster, tiny, monkeypatch):
    """A worker actor killed while it computes views (with more calls queued on it) is restarted
    with its geometry, its calls run again, and the field is the local one."""
    data = tiny
    scene, cams = load_ply(data / "scene.ply"), load_cameras(data)
    local = register_features(scene, cams, data / "features", RegisterOptions(), show_progress=False)
    box: dict = {}
    monkeypatch.setattr("drsplat.registration.ray.VIEWS_PER_TASK", 8)  # calls long enough to be caught running

    def run() -> None:
        try:
            box["result"] = register_features(scene, cams, data / "features", ON_RAY, show_progress=False)
        except BaseException as exc:  # noqa: BLE001 - reported by the assertion below
            box["error"] = exc

    thread = threading.Thread(target=run)
    thread.start()
    killed = None
    deadline = time.time() + 60
    while killed is None and thread.is_alive() and time.time() < deadline:
        pids = _task_pids("ray::_ViewWorker.compute")
        if pids:
            killed = pids[0]
            os.kill(killed, signal.SIGKILL)
        time.sleep(0.005)
    thread.join(120)
    assert killed is not None, "no worker was caught running a call"
    assert "error" not in box, box.get("error")
    np.testing.assert_array_equal(box["result"].features, local.features)
    np.testing.assert_array_equal(box["result"].weights, local.weights)


def test_joining_ray_leaves_print_the_sigterm_handler_and_the_environment_alone(cluster, monkeypatch):
    """ray.init replaces the SIGTERM handler (the CLI's clean interrupt) and sets PYTHONBREAKPOINT;
    Ray's progress-bar manager, once created (the first time the driver relays a worker's output or
    death), replaces builtins.print, and numba then cannot compile code calling get_num_threads."""
    import builtins

    import numba
    from ray.experimental import tqdm_ray

    from drsplat.cluster import connect

    ray.shutdown()
    monkeypatch.setenv("PYTHONBREAKPOINT", "pdb.set_trace")
    print_before = builtins.print
    mine = lambda signum, frame: None  # noqa: E731
    previous = signal.signal(signal.SIGTERM, mine)
    try:
        assert connect(cluster.address)
        assert signal.getsignal(signal.SIGTERM) is mine
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert os.environ["PYTHONBREAKPOINT"] == "pdb.set_trace"
    tqdm_ray.instance()  # what a relayed worker message calls: the manager exists already, print stays
    assert builtins.print is print_before

    @numba.njit
    def threads() -> int:
        return numba.get_num_threads()

    assert threads() >= 1


def test_no_address_asks_ray_for_a_new_local_instance(monkeypatch):
    """`--ray` with no address is a local instance of its own (the README's "a local Ray instance"):
    ray.init() with no address joins the cluster a `ray start` left on the machine (RAY_ADDRESS, or
    its session file), whose workers run with another working folder; address="local" never does
    (Ray's API). ray.init itself is replaced here: a second instance started inside the test
    process left later clusters unable to start actors."""
    from ray._private import worker as ray_worker

    from drsplat.cluster import connect

    monkeypatch.setattr(ray_worker, "print_to_stdstream", ray_worker.print_to_stdstream)  # connect relays Ray's errors: put back after
    calls = []
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", lambda **kwargs: calls.append(kwargs))
    monkeypatch.setattr(ray, "nodes", lambda: [])  # `auto` asks for the nodes of other hosts (this test alone has no cluster)
    for address in (None, "", "local"):
        assert connect(address, num_cpus=1)
    assert [c["address"] for c in calls] == ["local"] * 3 and all(c["num_cpus"] == 1 for c in calls)
    assert connect("auto") and calls[-1]["address"] == "auto"


def _init_that_meets_a_sigterm(**kwargs) -> None:
    """What ray.init does when a SIGTERM comes while it connects: its handler, sys.exit(signum)."""
    import sys

    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(signum))
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(1)  # the handler runs at the next bytecode


@pytest.mark.parametrize("program", ["command line", "cancellable job"])
def test_a_sigterm_while_ray_connects_is_the_programs_interrupt(monkeypatch, caplog, program):
    """Was: a SIGTERM during ray.init met Ray's handler: the process ended with status 15 and no line
    (round 60b). Now the program's own handler gets it: the command line's interrupt (exit 1, one
    line), or a cancellable job's cancel (its token set, Cancelled)."""
    from drsplat.cli import sigterm_as_interrupt
    from drsplat.cluster import connect
    from drsplat.utils import CancelToken, cancel_on_signals

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", _init_that_meets_a_sigterm)
    shut = []
    monkeypatch.setattr(ray, "shutdown", lambda: shut.append(True))  # the half-made instance's; not this module's cluster session
    before = signal.getsignal(signal.SIGTERM)
    token = CancelToken()
    handling = sigterm_as_interrupt() if program == "command line" else cancel_on_signals(token, "the views")
    with handling:
        expected = KeyboardInterrupt if program == "command line" else Cancelled
        with pytest.raises(expected):
            connect(None, num_cpus=1)
    assert signal.getsignal(signal.SIGTERM) is before
    assert token.cancelled == (program == "cancellable job")
    assert shut, "the half-made instance is shut down"


def test_rays_error_printer_is_relayed_while_connected_and_given_back_after(monkeypatch):
    """connect() routes Ray's error listener into the log (test_ray_cluster_faults has the relay itself);
    disconnect() of a session it started gives Ray's printer back, and one it did not start is left
    alone. ray.init and ray.shutdown are replaced, as above."""
    from ray._private import worker as ray_worker

    from drsplat.cluster import connect, disconnect

    rays = getattr(ray_worker.print_to_stdstream, "ray_printer", ray_worker.print_to_stdstream)
    monkeypatch.setattr(ray_worker, "print_to_stdstream", rays)  # and as it was, after the test
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", lambda **kwargs: None)
    monkeypatch.setattr(ray, "shutdown", lambda: None)
    assert connect(None, num_cpus=1)
    relay = ray_worker.print_to_stdstream
    assert getattr(relay, "drsplat_relay", False)
    assert connect(None, num_cpus=1) and ray_worker.print_to_stdstream is relay  # never a relay of a relay
    disconnect(False)
    assert ray_worker.print_to_stdstream is relay
    disconnect(True)
    assert ray_worker.print_to_stdstream is rays
    from drsplat.cluster import RELAYED_LINE_CHARS, relayed_line

    assert relayed_line("Raylet is terminated. Last 20 lines of the Raylet logs:") == "Raylet is terminated. Last 20 lines of the Raylet logs"
    cut = relayed_line("x" * 1000)
    assert len(cut) == RELAYED_LINE_CHARS and cut.endswith("...")  # round 62b: cut mid-word without a mark


def test_an_address_that_refuses_the_driver_names_ray_token_authentication(monkeypatch):
    from drsplat.cluster import auth_hint

    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)
    assert "RAY_AUTH_MODE=token" in auth_hint() and "ray get-auth-token" in auth_hint()
    monkeypatch.setenv("RAY_AUTH_MODE", "token")
    assert "check the token" in auth_hint()


def _frame(kind: int, flags: int, stream: int, payload: bytes = b"") -> bytes:
    return len(payload).to_bytes(3, "big") + bytes([kind, flags]) + stream.to_bytes(4, "big") + payload


GCS_REPLY = bytes([0x0A, 0x00, 0x12, 28]) + bytes(range(28))  # GetClusterIdReply: an empty status, a 28-byte cluster id
SERVER_SETTINGS = _frame(4, 0, 0, bytes([0, 3, 0, 0, 0, 100]))  # MAX_CONCURRENT_STREAMS 100
ANSWERS = {  # what a server sends once the probe's bytes came
    "http": b"HTTP/1.1 400 Bad Request\r\n\r\n",
    "silent": b"",
    "garbage with a 4th byte of 4": b"ABC\x04garbage-garbage",  # round 91a F3: passed a probe that read one byte
    "SETTINGS, then nothing": SERVER_SETTINGS,  # an HTTP/2 server that is not gRPC (round 91a F3: ray.init hung)
    "a gRPC error (a raylet's port)": SERVER_SETTINGS + _frame(1, 0x5, 1, b"\x88"),  # trailers only: the call failed
    "a reply that is no cluster id": SERVER_SETTINGS + _frame(1, 0x4, 1, b"\x88") + _frame(0, 0, 1, bytes([0, 0, 0, 0, 2, 0x0A, 0])),
}


def _serve_once(answer: bytes):
    """A listener on 127.0.0.1 that sends `answer` to its first connection once the probe's bytes came, then waits."""
    import socket

    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)
    served = threading.Event()

    def serve():
        conn, _ = listener.accept()
        with conn:
            if answer:
                conn.recv(1024)
                conn.sendall(answer)
            served.wait(10)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    return f"127.0.0.1:{listener.getsockname()[1]}", served, thread, listener


@pytest.mark.parametrize("kind", list(ANSWERS))
def test_an_address_that_is_not_a_ray_cluster_is_one_clear_error_at_once(kind, monkeypatch):
    """Round 90c F1: `--ray HOST:PORT` of a server that accepts connections but is not Ray's GCS (an HTTP server, a
    port that never answers) hung `register` in ray.init (over 420 s, a first Ctrl-C unheard). Round 91a F3: a probe
    that asked only for an HTTP/2 SETTINGS frame (by one byte of it) was passed by garbage, by an HTTP/2 server that
    is not gRPC (ray.init hung) and by a raylet's port (25 s of Ray's errors, then a token hint). The address is now
    asked the GCS's cluster id, and refused within the probe's timeout. The positive case, a real GCS, is every test
    that connects to a `ray.cluster_utils.Cluster` by its address, and the fake GCS below."""
    from drsplat.cluster import check_reachable

    monkeypatch.delenv("RAY_USE_TLS", raising=False)
    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)
    address, served, thread, listener = _serve_once(ANSWERS[kind])
    try:
        started = time.monotonic()
        with pytest.raises(DrsplatError, match=rf"^{address} (accepts a connection but does not answer as a Ray cluster does|"
                                               rf"answers HTTP/2 but not the cluster-id call|answers gRPC but refused the cluster-id call every Ray GCS answers: a "
                                               rf"raylet's or another service's port, or a cluster that asks for a token; if the cluster "
                                               rf"uses Ray's token authentication)"):
            check_reachable(address, timeout=1.0)
        assert time.monotonic() - started < 5.0  # the timeout bounds the whole probe, not each read
    finally:
        served.set()
        thread.join(5)
        listener.close()


def test_a_server_that_gives_a_cluster_id_passes_the_probe(monkeypatch):
    """The probe's positive case without Ray: SETTINGS, then the reply's HEADERS and a DATA frame holding a
    GetClusterIdReply with a cluster id, as Ray's GCS answers (checked by hand against a real GCS: 1 ms)."""
    from drsplat.cluster import check_reachable

    monkeypatch.delenv("RAY_USE_TLS", raising=False)
    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)
    message = bytes([0]) + len(GCS_REPLY).to_bytes(4, "big") + GCS_REPLY
    address, served, thread, listener = _serve_once(SERVER_SETTINGS + _frame(1, 0x4, 1, b"\x88") + _frame(0, 0, 1, message))
    try:
        check_reachable(address, timeout=2.0)
    finally:
        served.set()
        thread.join(5)
        listener.close()


@pytest.mark.parametrize("host", ["..", "a" * 64 + ".example"])
def test_a_host_name_that_cannot_be_encoded_is_one_clear_error(host):
    """Round 91a F4: `--ray '..:6379'` or a label over 63 letters ended in a UnicodeError traceback (IDNA's). Round 92a:
    a port of superscript digits ('6379²', digits to str.isdigit) was a bare ValueError from int()."""
    from drsplat.cluster import check_reachable, gcs_probe_request

    with pytest.raises(DrsplatError, match=rf"^cannot reach a Ray cluster at {host}:6379 \("):
        check_reachable(f"{host}:6379", timeout=1.0)
    with pytest.raises(DrsplatError, match=r"'localhost:6379²' is not an address"):
        check_reachable("localhost:6379\u00b2", timeout=1.0)
    # a host of fullwidth digits connects (IDNA maps them to ASCII); the request's authority must not end the probe
    assert b"/ray.rpc.NodeInfoGcsService/GetClusterId" in gcs_probe_request("\uff11\uff12\uff17.\uff10.\uff10.\uff11:6379")


def test_rays_advice_names_drsplats_flag(monkeypatch):
    """Round 90c F3: `--ray auto` with no cluster running passed on Ray's advice to set "the `--address` flag", which
    drsplat does not have; its option is --ray."""
    import ray

    from drsplat.cluster import connect

    def no_cluster(**kwargs):
        raise ConnectionError("Could not find any running Ray instance. Please specify the one to connect to by setting "
                              "`--address` flag or `RAY_ADDRESS` environment variable.")

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", no_cluster)
    with pytest.raises(DrsplatError) as raised:
        connect("auto")
    assert "--address" not in str(raised.value) and "by setting --ray or `RAY_ADDRESS`" in str(raised.value), raised.value


def test_unreachable_address_is_one_clear_error(tiny, tmp_path, capsys):
    from drsplat.cli import main
    from drsplat.cluster import connect

    with pytest.raises(DrsplatError, match=r"cannot reach a Ray cluster at 127\.0\.0\.1:9.*ray start --head"):
        connect("127.0.0.1:9")
    with pytest.raises(DrsplatError, match="is not an address"):
        connect("nowhere")
    # round 60b: a dashboard's address got Ray's advice about a RAY_ADDRESS variable and a token hint, and a malformed one
    # was refused only after the scene was loaded and the fit stage had run: the CLI refuses both as it parses
    with pytest.raises(DrsplatError, match=r"--ray 'http://127.0.0.1:8265' is a web address \(a dashboard's\?\), not a cluster's"):
        connect("http://127.0.0.1:8265")
    # round 60c: an IPv6 host kept its brackets for the socket ("Name or service not known"), '::1' read as host '::' port 1
    with pytest.raises(DrsplatError, match=r"cannot reach a Ray cluster at \[::1\]:9 \((Connection refused|Cannot assign)"):
        connect("[::1]:9")
    for bad, why in (("http://127.0.0.1:8265", "is a web address"), ("foo", "is not an address"), ("h:99999", "is not an address"),
                     ("ftp://h:1", "ray:// is the only scheme"), ("::1", "an IPv6 host goes in brackets"), (" h:6379", "spaces")):
        for command in (["register", str(tiny / "scene.ply"), "--source", str(tiny), "--features", str(tiny / "features"), "--out",
                         str(tmp_path / "o.ply")], ["features", "--source", str(tiny), "--out", str(tmp_path / "f")]):
            with pytest.raises(SystemExit) as exited:
                main([*command, f"--ray={bad}"])
            assert exited.value.code == 2, (bad, command[0])
    capsys.readouterr()
    code = main(["register", str(tiny / "scene.ply"), "--source", str(tiny), "--features", str(tiny / "features"),
                 "--out", str(tmp_path / "o.ply"), "--ray", "127.0.0.1:9", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 1 and not (tmp_path / "o.ply").exists() and "cannot reach a Ray cluster at 127.0.0.1:9" in err
    # round 90c F2: said before the scene is read (it came after the fit stage's probe views were rendered)
    assert "fit:" not in err and "estimated peak memory" not in err, err


@pytest.mark.slow
def test_ray_features_equal_local_and_skip_done_images(cluster, tiny, tmp_path):
    from drsplat.cli import main
    from drsplat.features import format as featurefiles
    from tests.test_clip import TINY_CLIP, make_tiny_clip

    from drsplat.cameras import write_transforms_json

    clip = make_tiny_clip(tmp_path)
    four = tmp_path / "four"
    four.mkdir()
    write_transforms_json(load_cameras(tiny)[:4], four / "transforms.json")
    args = ["-q", "features", "--source", str(four), "--masks", "slic", "--clip-model", TINY_CLIP, "--clip-checkpoint", str(clip),
            "--clip-config", str(tmp_path / f"{TINY_CLIP}.json"),
            "--device", "cpu", "--resolution", "64"]
    local, remote = tmp_path / "local", tmp_path / "ray"
    assert main(args + ["--out", str(local)]) == 0
    remote.mkdir()
    stems = featurefiles.list_stems(local)
    first = stems[0]
    for name in (f"{first}_s.npy", f"{first}_f.npy", "manifest.json"):  # one image done already: skipped, not redone
        (remote / name).write_bytes((local / name).read_bytes())
    before = (remote / f"{first}_f.npy").stat().st_mtime_ns
    assert main(args + ["--out", str(remote), "--ray", "auto", "--ray-workers", "2"]) == 0
    assert featurefiles.list_stems(remote) == stems and (remote / f"{first}_f.npy").stat().st_mtime_ns == before
    for stem in stems:
        np.testing.assert_array_equal(np.load(local / f"{stem}_s.npy"), np.load(remote / f"{stem}_s.npy"))
        np.testing.assert_allclose(np.load(local / f"{stem}_f.npy"), np.load(remote / f"{stem}_f.npy"), atol=1e-5)
    assert featurefiles.read_manifest(remote)["images"] == len(stems)
    assert not list(remote.glob(".*"))  # no temp or half files


# The numba engine runs on Ray five modes that between them take every branch the Ray path has (each
# Ray registration costs seconds of worker start-up, so no more than that): the per-view weightings
# that read only the top-k lists (paper), the projection (sharp), the masks (explain) and the fit
# stage's probe (fit, the default); the vote's slots, clusters and specificity, floater rejection, the
# check's support tables and kept pairs with a vote, and the one-block solve. The torch engine runs
# one mode for each kind of per-view input its device computes: the projection (centre), the masks
# (explain), the top-k lists (with the solve and a vote); the driver's and reducers' work does not
# depend on the engine. Every mode's agreement with the reference, engine by engine and
# plan by plan, is the local matrix's (tests/test_registration_matrix.py): a mode's weighting is the
# same function on a Ray worker.
NUMBA_ON_RAY_MODES = ("paper", "explain-reject", "fit-check-vote-reject", "sharp-check-vote-reject", "solve-vote-reject")
TORCH_ON_RAY_MODES = ("centre", "explain-reject", "solve-vote-reject")


def _branches(mode: str) -> set[tuple[str, object]]:
    """The branches of the Ray path a mode takes: its weighting's inputs and each stage on or off."""
    from drsplat.registration.aggregate import MASK_WEIGHTINGS, PROJECTED_WEIGHTINGS, mode_stages

    stages = mode_stages(mode)
    inputs = ("fit probe" if stages.weighting == "fit" else "masks" if stages.weighting in MASK_WEIGHTINGS
              else "projection" if stages.weighting in PROJECTED_WEIGHTINGS else "top-k lists")
    stage_flags = {("vote", stages.vote), ("reject", stages.reject), ("check", stages.check), ("solve", stages.solve),
                   ("vote by specificity", stages.specific)}
    return {("weights from", inputs), ("check with vote", stages.check and stages.vote)} | stage_flags


def test_the_modes_run_on_ray_take_every_branch_a_mode_can():
    """A mode added later with a new stage or a new kind of weighting must join NUMBA_ON_RAY_MODES."""
    from drsplat.defaults import AGGREGATE_MODES

    every = set().union(*map(_branches, AGGREGATE_MODES))
    assert set().union(*map(_branches, NUMBA_ON_RAY_MODES)) == every
    assert ("check with vote", True) in every and ("weights from", "fit probe") in every


@pytest.mark.parametrize("engine", ["numba", "torch"])
def test_every_mode_on_ray_writes_the_local_file(cluster, tmp_path_factory, engine):
    """The Ray place of the engine x place x mode matrix (tests/test_registration_matrix.py covers the
    local place): the modes of NUMBA_ON_RAY_MODES / TORCH_ON_RAY_MODES, computed by tasks with
    `engine`, in Gaussian blocks, write the bytes of the local numba one-block run."""
    from drsplat.registration.aggregate import mode_stages

    data = tmp_path_factory.getbasetemp() / "matrix-hard-mislabelled"
    if not (data / "scene.ply").exists():  # mislabelled masks: the check modes drop some (on clean ones they write their base modes' files)
        write_dataset(data, "hard-tiny", 0, mislabel_fraction=0.2, show_progress=False)
    scene, cams = load_ply(data / "scene.ply"), load_cameras(data)[:4]
    tmp_path = tmp_path_factory.mktemp(f"modes-{engine}")
    for mode in NUMBA_ON_RAY_MODES if engine == "numba" else TORCH_ON_RAY_MODES:
        local, on_ray = data / "local" / mode / "reg.ply", tmp_path / mode / "reg.ply"
        if not local.exists():  # the local reference, shared by both engines' runs
            register(scene, cams, data / "features", local, RegisterOptions(topk=10, aggregate=mode), show_progress=False)
        stages = mode_stages(mode)  # the solve runs in one block only (refused in blocks: tests/test_registration_matrix.py)
        options = RegisterOptions(topk=10, aggregate=mode, engine=engine, ray="auto", ray_workers=2, block_size=None if stages.solve else 1024)
        result = register(scene, cams, data / "features", on_ray, options, show_progress=False)
        assert result.num_blocks == (1 if stages.solve else 3) and result.worker_peak_rss, mode
        assert result.reducers == (not stages.solve), mode  # a check's masks are judged by the driver, its kept pairs summed by reducers
        assert on_ray.read_bytes() == local.read_bytes(), mode


def test_a_first_ctrl_c_while_ray_connects_ends_the_connect(monkeypatch):
    """Round 90c (left as found then): ray.init waits in Ray's own loops for a GCS slow to answer, and a command's first
    Ctrl-C only cancelled its token, which ray.init never reads: still waiting 30 s later. The connect now ends at the
    first Ctrl-C with Cancelled, the half-made connection shut down, and the command's own handler back in place."""
    import signal

    import ray

    from drsplat.cluster import connect
    from drsplat.utils import CancelToken, cancel_on_signals

    shut = []

    def slow_init(**kwargs):
        for _ in range(400):  # 20 s of Ray's polling
            time.sleep(0.05)

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", slow_init)
    monkeypatch.setattr(ray, "shutdown", lambda: shut.append(True))
    token = CancelToken()
    with cancel_on_signals(token):
        handler = signal.getsignal(signal.SIGINT)
        timer = threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT))
        timer.start()
        started = time.monotonic()
        try:
            with pytest.raises(Cancelled, match=r"Ctrl-C while connecting to Ray \(a new local instance\)"):
                connect(None)
        finally:
            timer.cancel()
        assert time.monotonic() - started < 5.0 and shut == [True]
        assert signal.getsignal(signal.SIGINT) is handler and not token.cancelled
