"""Sizes and this process's memory: '8GB' -> bytes, bytes -> '8.0 GB', /proc readings.

Foundation module (numpy only): the CLI's --memory-budget validator, registration's memory plan,
the Ray workers and the benches all read memory through here; the CLI and the viewer run with
numpy's huge-page advice off (`small_pages`).
"""

from __future__ import annotations

import contextlib
import os
import re
import resource
from collections.abc import Iterator
from pathlib import Path

import numpy as np

_UNITS = {"": 1, "b": 1, "k": 1e3, "kb": 1e3, "m": 1e6, "mb": 1e6, "g": 1e9, "gb": 1e9, "t": 1e12, "tb": 1e12,
          "kib": 1 << 10, "mib": 1 << 20, "gib": 1 << 30, "tib": 1 << 40}


def parse_size(text: str) -> int:
    """'8GB', '8 GiB', '512MB', '1e9' -> bytes (GB = 10^9, GiB = 2^30)."""
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:e[0-9]+)?)\s*([a-zA-Z]*)\s*", str(text))
    if not match or match.group(2).lower() not in _UNITS:
        raise ValueError(f"{text!r} is not a size (examples: 8GB, 512MB, 16GiB)")
    value = float(match.group(1)) * _UNITS[match.group(2).lower()]
    if not np.isfinite(value) or value <= 0:
        raise ValueError(f"{text!r} is not a positive size")
    return int(value)


def format_size(n: float) -> str:
    """Bytes as '1.3 GB' (from 1 GB up), '512 MB' (from 1 MB up) or '34 kB'."""
    if n >= 1e9:
        return f"{n / 1e9:.1f} GB"
    return f"{n / 1e6:.0f} MB" if n >= 1e6 else f"{n / 1e3:.0f} kB"


def _proc_bytes(path: str, key: str) -> int:
    """The `key:` line of a /proc file (in kB there) in bytes; 0 when unknown."""
    try:
        for line in Path(path).read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def available_memory() -> int:
    """MemAvailable of /proc/meminfo in bytes (0 when unknown)."""
    return _proc_bytes("/proc/meminfo", "MemAvailable")


def current_rss() -> int:
    """Resident memory of this process now (VmRSS), in bytes."""
    return _proc_bytes("/proc/self/status", "VmRSS")


def peak_rss() -> int:
    """Peak resident memory of this process so far (ru_maxrss), in bytes."""
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


HUGEPAGE_ENV = "NUMPY_MADVISE_HUGEPAGE"  # numpy's own switch for its huge-page advice, read when numpy is imported


def _hugepage_setter():
    """numpy's switch behind NUMPY_MADVISE_HUGEPAGE (a private function; None where this numpy has none)."""
    core = getattr(np, "_core", None) or getattr(np, "core", None)
    return getattr(getattr(core, "multiarray", None), "_set_madvise_hugepage", None)


@contextlib.contextmanager
def small_pages() -> Iterator[None]:
    """Run the block with numpy's arrays in ordinary 4 kB pages; numpy's setting is put back after.

    numpy advises Linux to back every array of 4 MB or more with transparent huge pages
    (madvise). Where the kernel compacts memory before it hands out a huge page
    (/sys/kernel/mm/transparent_hugepage/defrag = madvise, the default of common distributions)
    and the machine's memory is fragmented, every fresh array stalls while it is faulted in:
    flowers' 1.1 GB of sums took 2.6 s to allocate instead of 0.39 s, and a 12-view registration
    ran 762 instead of 532 ms per view (docs/registration.md, "Huge pages"). A user's own
    NUMPY_MADVISE_HUGEPAGE decides instead when it is set.
    """
    setter = _hugepage_setter()
    if setter is None or HUGEPAGE_ENV in os.environ:
        yield
        return
    previous = setter(False)
    try:
        yield
    finally:
        setter(bool(previous))


def worker_hugepage_env() -> dict[str, str]:
    """The environment that gives a worker process (Ray) the same huge-page choice as `small_pages`."""
    return {HUGEPAGE_ENV: os.environ.get(HUGEPAGE_ENV, "0")}
