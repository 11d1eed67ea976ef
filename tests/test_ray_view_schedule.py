"""The Ray driver's schedule of view calls (`RayExecutor.view_pairs`) against a simulated cluster: calls that take
given times on each worker and a clock that moves with the driver's waits, so a stall of minutes is decided in
milliseconds and no Ray instance is started. What is checked is the order of results and errors and which worker
is taken for lost; the views themselves are names. The same simulation answers the workers' placement and the nodes'
code probe (`drsplat.cluster`)."""

from __future__ import annotations

import logging
import math
from types import SimpleNamespace

import pytest

from drsplat.errors import DrsplatError
from drsplat.registration import ray as ray_executor
from drsplat.registration.compute import WorkerStats

try:  # imported with the module, as tests/test_reduce.py does: importing ray sets RAY_CLIENT_MODE once (the code probe
    import ray  # imports Ray's scheduling strategy; nothing else here needs Ray)
except ImportError:
    ray = None


HUNG_SECONDS = 3600.0  # a run of a few views still waiting after this long (simulated) is hung


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def monotonic(self) -> float:
        return self.now


class Call:
    """A submitted call: its views' names, when it ends on its worker, and the error it raises, if any."""

    def __init__(self, names: list[str], ends: float, error: Exception | None) -> None:
        self.names, self.ends, self.error = names, ends, error


class Worker:
    """Runs its calls one after another: each view takes `seconds[(pid, name)]` or `seconds[name]` (1 s if not named)
    and raises `errors[(pid, name)]` or `errors[name]`; once `lost_after` calls were submitted to it (None: never), its
    node is lost without a word and its later calls never end."""

    def __init__(self, pid: int, clock: Clock, seconds: dict[str, float], errors: dict[str, Exception], lost_after: int | None) -> None:
        self.pid, self.clock, self.seconds, self.errors = pid, clock, seconds, errors
        self.lost_after = lost_after
        self.free_at = 0.0
        self.compute = SimpleNamespace(remote=self._submit)

    def _submit(self, refs, chunk, marks) -> Call:
        names = [c.name for c in chunk]
        start = max(self.clock.now, self.free_at)
        lost = self.lost_after is not None and self.lost_after <= 0
        self.free_at = math.inf if lost else start + sum(self.seconds.get((self.pid, n), self.seconds.get(n, 1.0)) for n in names)
        if self.lost_after is not None:
            self.lost_after -= 1
        raised = [self.errors.get((self.pid, n), self.errors.get(n)) for n in names]
        first = next((i for i, e in enumerate(raised) if e is not None), None)
        call = Call(names, self.free_at, None if first is None else raised[first])
        call.done = names if first is None else names[:first]  # the views computed before the failing one
        return call


class SimulatedRay:
    class RayError(Exception):
        pass

    class RayTaskError(RayError):
        pass

    class ActorUnavailableError(RayError):
        pass

    def __init__(self, clock: Clock) -> None:
        self.exceptions = SimpleNamespace(RayError=self.RayError, RayTaskError=self.RayTaskError, ActorUnavailableError=self.ActorUnavailableError)
        self.clock = clock

    def wait(self, refs: list[Call], num_returns: int = 1, timeout: float = 1.0):
        if self.clock.now > HUNG_SECONDS:
            raise AssertionError(f"the driver still waits after {HUNG_SECONDS:.0f} simulated seconds: hung")
        first = min(refs, key=lambda ref: ref.ends)
        if first.ends <= self.clock.now + timeout:
            self.clock.now = max(self.clock.now, first.ends)
            return [first], [r for r in refs if r is not first]
        self.clock.now += timeout
        return [], refs

    def get(self, ref: Call):
        if isinstance(ref.error, DrsplatError):  # as `_ViewWorker.compute`: a view's DrsplatError comes back in the result,
            return ray_executor._CallResult(list(ref.done), WorkerStats(pid=1), ref.error)  # with the views before it
        if ref.error is not None:
            raise ref.error
        return ray_executor._CallResult(list(ref.names), WorkerStats(pid=1))

    def cancel(self, ref) -> None:
        pass

    def kill(self, actor, no_restart: bool = True) -> None:
        pass


def run_views(monkeypatch, tmp_path, workers: int, views: int, seconds: dict, errors: dict | None = None,
              lost: dict[int, int] | None = None, stall: float = 3.0, per_task: int = 1):
    """(the names view_pairs yielded, the error it raised or None, the simulated seconds it took)."""
    clock = Clock()
    fake = SimulatedRay(clock)
    monkeypatch.setattr(ray_executor, "import_ray", lambda: fake)
    monkeypatch.setattr(ray_executor, "time", SimpleNamespace(monotonic=clock.monotonic))
    monkeypatch.setattr("drsplat.cluster.STALL_SECONDS", stall)
    executor = object.__new__(ray_executor.RayExecutor)
    executor._placed, executor._refs, executor._features_dir = True, [], tmp_path
    executor._actors = [Worker(i, clock, seconds, errors or {}, (lost or {}).get(i)) for i in range(workers)]
    executor.views_per_task, executor.cancel, executor.worker_stats = per_task, None, {}
    got: list[str] = []
    try:
        for name in executor.view_pairs([SimpleNamespace(name=f"v{i}") for i in range(views)]):
            got.append(name)
    except Exception as exc:  # noqa: BLE001 - returned to the test
        return got, exc, clock.now
    return got, None, clock.now


def test_a_slow_call_of_the_only_worker_is_waited_for_not_taken_for_a_stall(monkeypatch, tmp_path):
    """Round 74d F2: the stall rule read the worker's own finished call (each worker has IN_FLIGHT queued) as the
    others' progress, so one call slower than STALL_SECONDS plus 10x the slowest killed the only worker and the run
    ended with "every Ray registration worker was lost" where the local run finishes."""
    got, error, _ = run_views(monkeypatch, tmp_path, workers=1, views=4, seconds={"v1": 30.0})
    assert error is None and got == ["v0", "v1", "v2", "v3"]


def test_a_worker_that_hangs_while_the_other_progresses_has_its_calls_done_elsewhere(monkeypatch, tmp_path, caplog):
    """The rule still does what it is for: a call that never ends (its node lost, Ray saying nothing) is sent to the
    other worker once that one is idle."""
    with caplog.at_level(logging.WARNING, logger="drsplat"):
        got, error, took = run_views(monkeypatch, tmp_path, workers=2, views=6, seconds={}, lost={1: 0})
    assert error is None and got == [f"v{i}" for i in range(6)] and took < 60
    assert [r for r in caplog.records if "sent to another as well" in r.getMessage()]


@pytest.mark.parametrize("case", ["slow first calls, one worker idle", "the idle worker's node lost", "a slow worker beside a lost one"])
def test_a_slow_live_worker_is_never_stopped_and_a_lost_one_never_waited_for(monkeypatch, tmp_path, caplog, case):
    """Round 76a F1-F3: taking the stalled worker for lost (and moving its calls) stopped live workers whose first calls
    outlasted the bound while another had no call (a cold compile, slow views), moved a live worker's call onto an idle
    worker whose node was lost, then waited for ever on it, and stopped a slow live worker while keeping a lost one.
    A stalled call is now sent as well to an idle worker and the first answer taken: every run ends with every view."""
    if case == "slow first calls, one worker idle":
        run = dict(workers=2, views=1, seconds={"v0": 130.0})
    elif case == "the idle worker's node lost":
        run = dict(workers=2, views=1, seconds={"v0": 130.0}, lost={1: 0})
    else:
        run = dict(workers=2, views=8, seconds={"v3": 300.0}, lost={0: 4})
    with caplog.at_level(logging.WARNING, logger="drsplat"):
        got, error, took = run_views(monkeypatch, tmp_path, stall=120.0, **run)
    assert error is None and got == [f"v{i}" for i in range(run["views"])] and took < HUNG_SECONDS
    assert not [r for r in caplog.records if "worker was lost" in r.getMessage()]  # no worker stopped for a stall


@pytest.mark.parametrize("fails", [False, True])
def test_a_worker_lost_after_the_others_last_call_is_still_taken_for_lost(monkeypatch, tmp_path, fails):
    """Round 75a F1 (a regression of the mend above): worker 0 finishes its share at t = 4 and is idle; worker 1 ends
    its slow first view at t = 5 and its node is lost with its next call queued. That call could begin only at 5, after
    worker 0's last call, so "another worker progressed since" never held: the run waited for ever (and a failure of
    v4, stored for view order behind it, was never raised). An idle worker counts as one that could take the call."""
    errors = {"v4": ValueError("view v4 is bad")} if fails else None
    got, error, took = run_views(monkeypatch, tmp_path, workers=2, views=6, seconds={"v1": 5.0}, errors=errors, lost={1: 1})
    assert took < HUNG_SECONDS
    if fails:
        assert got == ["v0", "v1", "v2", "v3"] and isinstance(error, ValueError)
    else:
        assert error is None and got == [f"v{i}" for i in range(6)]


def test_a_failed_call_is_raised_in_view_order_after_the_views_before_it(monkeypatch, tmp_path):
    """Round 74d F1: an error in a worker's call left the loop as soon as it arrived, so views before it still running
    elsewhere were never yielded (never logged, so the rerun could not resume from them); the local run fails after
    logging them."""
    got, error, _ = run_views(monkeypatch, tmp_path, workers=2, views=4, seconds={"v0": 5.0}, errors={"v1": ValueError("view v1 is bad")})
    assert got == ["v0"]
    assert isinstance(error, ValueError) and "v1 is bad" in str(error)


class Placement(SimulatedRay):
    """Ray as `placed_actors` and the nodes' code probe see it: every `ready` answers at once (or raises the actor's
    error); the probe's tasks never answer."""

    def __init__(self, clock: Clock, errors: dict[int, Exception] | None = None) -> None:
        super().__init__(clock)
        self.errors = errors or {}
        self.killed: list[int] = []
        self.timeouts: list[float] = []

    def wait(self, refs, num_returns: int = 1, timeout: float = 1.0):
        self.timeouts.append(timeout)
        if all(isinstance(ref, tuple) for ref in refs):  # `ready` calls
            return list(refs), []
        self.clock.now += timeout
        return [], refs

    def get(self, ref):
        if ref[1] in self.errors:
            raise self.errors[ref[1]]
        return True

    def kill(self, actor, no_restart: bool = True) -> None:
        self.killed.append(actor.pid)

    def nodes(self) -> list[dict]:
        return [{"Alive": True, "NodeID": "ab" * 28, "NodeManagerHostname": "silent"}]

    def remote(self, **options):
        task = SimpleNamespace(remote=lambda *args: object())
        return lambda function: SimpleNamespace(options=lambda **kw: task)


def placement_workers(count: int) -> list:
    return [SimpleNamespace(pid=i, ready=SimpleNamespace(remote=lambda i=i: ("ready", i))) for i in range(count)]


def test_a_worker_whose_node_is_lost_as_it_starts_is_left_out_not_the_end_of_the_run(monkeypatch, caplog):
    """Round 74d F3: an ActorUnavailableError answering one worker's `ready` (its node lost once its process started)
    ended the registration or feature run with "a Ray worker could not start", other workers placed; now that worker
    is given up, and only none placed is one error."""
    from drsplat import cluster
    from drsplat.errors import DrsplatError

    fake = Placement(Clock(), {0: SimulatedRay.ActorUnavailableError("the actor is temporarily unavailable")})
    monkeypatch.setattr(cluster, "import_ray", lambda: fake)
    workers = placement_workers(2)
    with caplog.at_level(logging.WARNING, logger="drsplat"):
        placed = cluster.placed_actors(workers, "registration", "views")
    assert [w.pid for w in placed] == [1] and fake.killed == [0]
    assert any("1 of 2 registration workers became unavailable" in r.getMessage() for r in caplog.records)
    fake.errors[1] = fake.errors[0]
    with pytest.raises(DrsplatError, match="no Ray feature worker started"):
        cluster.placed_actors(placement_workers(2), "feature", "images")


@pytest.mark.skipif(ray is None, reason="the probe names its node through Ray's scheduling strategy")
def test_a_cancel_is_seen_while_the_nodes_code_probe_waits_for_a_silent_node(monkeypatch):
    """Round 74d F4: the probe of the nodes' code was one wait of PROBE_SECONDS (60 s), so a Ctrl-C on a cluster with
    one silent node waited up to a minute; the wait is now in steps of WAIT_SECONDS, reading the cancel token."""
    from drsplat import cluster
    from drsplat.errors import Cancelled
    from drsplat.utils import CancelToken

    clock = Clock()
    fake = Placement(clock)
    monkeypatch.setattr(cluster, "time", SimpleNamespace(monotonic=clock.monotonic))
    cancel = CancelToken()
    cancel.cancel()
    with pytest.raises(Cancelled):
        cluster.check_nodes_run_this_code(fake, cancel=cancel)
    assert fake.timeouts and max(fake.timeouts) <= cluster.WAIT_SECONDS


def test_a_call_stalled_on_a_lost_node_gets_one_new_copy_per_stall(monkeypatch, tmp_path):
    """Round 77a F1: the stall was timed from the original call (on a lost node it never ends), so every worker that
    went idle got one more copy of the same views, each computed in full (with --memory-budget, each written to a
    shard). A chunk now gets one new copy per stall period, timed from its last copy."""
    sent: list[tuple[int, str]] = []
    submit = Worker._submit

    def recorded(self, refs, chunk, marks):
        sent.extend((self.pid, c.name) for c in chunk)
        return submit(self, refs, chunk, marks)

    monkeypatch.setattr(Worker, "_submit", recorded)
    got, error, _ = run_views(monkeypatch, tmp_path, workers=4, views=8, seconds={f"v{i}": 20.0 for i in range(8)}, lost={0: 0})
    assert error is None and got == [f"v{i}" for i in range(8)]
    for name in ("v0", "v4"):  # the lost worker's two calls: each sent there and copied once
        assert len([pid for pid, n in sent if n == name]) == 2, sent


@pytest.mark.parametrize("kind", [ValueError, DrsplatError], ids=["raised", "returned"])
@pytest.mark.parametrize("failing", ["the copy", "the original"])
def test_a_copy_that_fails_on_its_worker_does_not_undo_the_views_another_worker_computes(monkeypatch, tmp_path, failing, kind):
    """Round 78a F1: of a stalled call and its copy, the first error was taken as the views' answer while the other
    call still ran and would answer: a copy on a node whose worker died (or whose features folder is not mounted) failed
    a registration whose views worker 0 computed 10 s later. An error is now raised only once no copy of the call is
    left to answer. (v0 takes 130 s on worker 0, past the 120 s bound: it is copied to the idle worker 1 at ~120 s.)
    Round 79c F1: a worker returns a view's DrsplatError in its result rather than raising it; that kind was still taken
    at once on a real cluster (the simulation had only raised errors)."""
    seconds = {(0, "v0"): 130.0, (1, "v0"): 5.0 if failing == "the copy" else 20.0}  # the failure comes first
    errors = {(1 if failing == "the copy" else 0, "v0"): kind("features folder not visible on this node")}
    got, error, _ = run_views(monkeypatch, tmp_path, workers=2, views=1, seconds=seconds, errors=errors, stall=120.0)
    assert error is None and got == ["v0"]


def test_a_call_that_fails_on_every_copy_raises_the_first_error(monkeypatch, tmp_path):
    """The other side of the mend above: when each copy fails, the view's error is raised (the first to arrive)."""
    seconds = {(0, "v0"): 130.0, (1, "v0"): 20.0}
    errors = {(0, "v0"): ValueError("worker 0's error"), (1, "v0"): ValueError("worker 1's error")}
    got, error, took = run_views(monkeypatch, tmp_path, workers=2, views=2, seconds=seconds, errors=errors, stall=120.0)
    assert got == [] and isinstance(error, ValueError) and "worker 0's error" in str(error) and took < HUNG_SECONDS


def test_a_call_that_failed_beside_a_copy_on_a_lost_node_raises_its_error_not_waits(monkeypatch, tmp_path):
    """The mend above must not wait for ever on a copy that never answers: worker 0's node is lost holding v0 (Ray says
    nothing), its copy fails on worker 1. The error is raised once the lost call has not answered in one more stall
    bound (it had been copied again and again, each copy failing, for ever)."""
    got, error, took = run_views(monkeypatch, tmp_path, workers=2, views=2, seconds={}, errors={(1, "v0"): ValueError("v0 is bad")},
                                 lost={0: 0}, stall=120.0)
    assert got == [] and isinstance(error, ValueError) and took < HUNG_SECONDS


def test_a_kept_error_waits_for_a_copy_from_when_that_copy_could_begin(monkeypatch, tmp_path):
    """Round 79a F1: a kept error was raised one stall bound after the failure, although the copy left was queued behind
    its worker's slow call and had not begun: worker 0 holds v0 (200 s) and v2 (100 s) behind it; v2's copy fails on
    worker 1 at ~133 s; worker 0 answers v2 at 300 s, within the bound counted from when v2 could begin (v0's end, 200 s)
    though not from the failure (~263 s)."""
    seconds = {(0, "v0"): 200.0, (0, "v2"): 100.0}
    got, error, took = run_views(monkeypatch, tmp_path, workers=2, views=3, seconds=seconds, errors={(1, "v2"): ValueError("worker 1's error")},
                                 stall=120.0)
    assert error is None and got == ["v0", "v1", "v2"], (got, error, took)


def test_a_stalled_call_with_no_worker_free_to_take_it_is_said_not_waited_on_in_silence(monkeypatch, tmp_path, caplog):
    """Round 79c F2: with every worker's call stalled (a hung node, a shared folder that stopped answering) no copy can
    be sent, and the run waited with nothing said. Now a warning once a stall period; the run still ends when the calls do."""
    with caplog.at_level(logging.WARNING, logger="drsplat"):
        got, error, took = run_views(monkeypatch, tmp_path, workers=2, views=2, seconds={"v0": 700.0, "v1": 700.0}, stall=120.0)
    assert error is None and got == ["v0", "v1"]
    said = [r for r in caplog.records if "waited" in r.getMessage() and "s on one worker and no other worker is free to take them"
            in r.getMessage()]  # the whole phrase (round 82a F1: "waited 120 s on no other worker is free")
    assert 2 <= len(said) <= 6, [r.getMessage() for r in said]  # ~700 s of waiting, one line a ~130 s period
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="drsplat"):  # one worker has no other (round 81a F3)
        got, error, _ = run_views(monkeypatch, tmp_path, workers=1, views=2, seconds={"v0": 300.0}, stall=120.0)
    assert error is None and got == ["v0", "v1"]
    said = [r.getMessage() for r in caplog.records if "waited" in r.getMessage()]
    assert said and all("the only worker (slow, or its node hung)" in m and "other worker" not in m for m in said), said


def test_of_two_failed_copies_the_one_that_got_furthest_gives_its_views(monkeypatch, tmp_path):
    """Round 81a F2: when both copies of a chunk failed, the first to answer was kept: a copy on a node without the
    features failed at its first view, the original returned v0-v2 and the real error at v3; nothing was yielded and
    the error named the node. Now the failed result with the most views: v0-v2 yielded (logged), then v3's error."""
    seconds = {(0, f"v{i}"): 40.0 for i in range(4)}  # 160 s on worker 0: copied at ~130 s to worker 1
    errors = {(1, "v0"): DrsplatError("features folder not visible on node 1"), (0, "v3"): DrsplatError("v3 is bad")}
    got, error, took = run_views(monkeypatch, tmp_path, workers=2, views=4, seconds=seconds, errors=errors, stall=120.0, per_task=4)
    assert got == ["v0", "v1", "v2"] and isinstance(error, DrsplatError) and "v3 is bad" in str(error), (got, error)
