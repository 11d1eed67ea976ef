"""Helpers of the tests that run Triton kernels on the CPU, in Triton's interpreter, or compile them to PTX.

Triton reads TRITON_INTERPRET when it is imported, so interpreted kernels run in a subprocess with
the variable set; this process's environment is never touched.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_interpreted(worker: str, *argv: str, timeout: int = 900) -> None:
    """Run the Python source `worker` with `argv` in a subprocess under TRITON_INTERPRET=1, from the
    repository root (so it imports drsplat and tests); fail with its last stderr if it fails."""
    env = dict(os.environ, TRITON_INTERPRET="1", PYTHONPATH=str(ROOT))
    done = subprocess.run([sys.executable, "-c", worker, *argv], cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr[-3000:]


def interpreted_outputs(out: Path, worker: str, *argv: str, timeout: int = 900) -> Path:
    """`run_interpreted(worker, *argv, out)`: a worker that writes its results into the folder `out`
    (its last argument); returns `out`."""
    run_interpreted(worker, *argv, str(out), timeout=timeout)
    return out


def compiled_ptx(compile_ptx: Callable[..., str], *args, **kwargs) -> str:
    """`compile_ptx(*args, **kwargs)`, or a skip where Triton's backend API moved (the check cannot
    run there; the kernel may still be fine)."""
    try:
        return compile_ptx(*args, **kwargs)
    except (ImportError, AttributeError) as exc:
        pytest.skip(f"triton's backend API differs from 3.8's ({exc})")
