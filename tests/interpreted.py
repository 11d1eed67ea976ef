"""Helpers of the tests that run Triton kernels on the CPU, in Triton's interpreter, or compile them to PTX.

Triton reads TRITON_INTERPRET when it is imported, so interpreted kernels run in a subprocess with
the variable set; this process's environment is never touched.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


SHARDS = 2  # worker processes an interpreted run is split into: the interpreter is one Python thread, and CI has 2 cores
SHARD_VARIABLE = "DRSPLAT_TEST_SHARD"  # "i/n", set in each worker's environment only


def share(items) -> list:
    """The items this worker process takes: every n-th from its i-th ($DRSPLAT_TEST_SHARD = "i/n"),
    all of them when the variable is not set (a worker run by hand)."""
    items = list(items)
    shard = os.environ.get(SHARD_VARIABLE)
    if not shard:
        return items
    index, count = (int(part) for part in shard.split("/"))
    return items[index::count]


def shard_name() -> str:
    """A name for this worker's own files ("0of2"; "all" when not sharded)."""
    shard = os.environ.get(SHARD_VARIABLE)
    return shard.replace("/", "of") if shard else "all"


def run_interpreted(worker: str, *argv: str, timeout: int = 900, shards: int = SHARDS) -> None:
    """Run the Python source `worker` with `argv` under TRITON_INTERPRET=1 from the repository root
    (so it imports drsplat and tests), in `shards` subprocesses at once, each taking its `share` of
    the worker's items; fail with a failed one's last stderr. Each shard's own stderr and exit code
    are kept apart, so a failure names its shard."""
    procs, logs = [], []
    try:
        for index in range(shards):
            env = dict(os.environ, TRITON_INTERPRET="1", PYTHONPATH=str(ROOT), **{SHARD_VARIABLE: f"{index}/{shards}"})
            logs.append(tempfile.TemporaryFile("w+"))  # a file, not a pipe: a chatty shard never waits on a full pipe
            procs.append(subprocess.Popen([sys.executable, "-c", worker, *argv], cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=logs[-1]))
        deadline = time.monotonic() + timeout
        for proc in procs:
            proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        for index, (proc, log) in enumerate(zip(procs, logs)):
            log.seek(0)
            assert proc.returncode == 0, f"shard {index}/{shards}: " + log.read()[-3000:]
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        for log in logs:
            log.close()


def interpreted_outputs(out: Path, worker: str, *argv: str, timeout: int = 900) -> Path:
    """`run_interpreted(worker, *argv, out)`: a worker that writes its results into the folder `out`
    (its last argument; each shard writes the files of its own items); returns `out`."""
    run_interpreted(worker, *argv, str(out), timeout=timeout)
    return out


def compiled_ptx(compile_ptx: Callable[..., str], *args, **kwargs) -> str:
    """`compile_ptx(*args, **kwargs)`, or a skip where Triton's backend API moved (the check cannot
    run there; the kernel may still be fine)."""
    try:
        return compile_ptx(*args, **kwargs)
    except (ImportError, AttributeError) as exc:
        pytest.skip(f"triton's backend API differs from 3.8's ({exc})")
