"""Sizes and this process's memory: '8GB' -> bytes, bytes -> '8.0 GB', /proc readings.

Foundation module (numpy only): the CLI's --memory-budget validator, registration's memory plan,
the Ray workers and the benches all read memory through here; a registration's large one-time
arrays are allocated in small pages here (`small_page_zeros`).
"""

from __future__ import annotations

import math
import mmap
import re
import resource
from pathlib import Path

import numpy as np

_UNITS = {"": 1, "b": 1, "k": 1e3, "kb": 1e3, "m": 1e6, "mb": 1e6, "g": 1e9, "gb": 1e9, "t": 1e12, "tb": 1e12,
          "kib": 1 << 10, "mib": 1 << 20, "gib": 1 << 30, "tib": 1 << 40}


def parse_size(text: str) -> int:
    """'8GB', '8 GiB', '512MB', '1e9', '1E9' -> bytes (GB = 10^9, GiB = 2^30); at least one byte."""
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][0-9]+)?)\s*([a-zA-Z]*)\s*", str(text))
    if not match or match.group(2).lower() not in _UNITS:
        raise ValueError(f"{text!r} is not a size (examples: 8GB, 512MB, 16GiB)")
    value = float(match.group(1)) * _UNITS[match.group(2).lower()]
    if not np.isfinite(value):
        raise ValueError(f"{text!r} is larger than any memory")
    if value < 1:
        raise ValueError(f"{text!r} is less than one byte")
    return int(value)


def format_size(n: float, up: bool = False) -> str:
    """Bytes as '1.3 GB' (from 1 GB up), '512 MB' (from 1 MB up), '34 kB' (from 1 kB up) or '512 bytes';
    up: rounded up at that precision (a minimum a user can type back)."""
    if up:
        step = 1e8 if n >= 1e9 else 1e6 if n >= 1e6 else 1e3 if n >= 1e3 else 1
        n = math.ceil(n / step) * step
    if n >= 1e9:
        return f"{n / 1e9:.1f} GB"
    if n >= 1e6:
        return f"{n / 1e6:.0f} MB"
    if n >= 1e3:
        return f"{n / 1e3:.0f} kB"
    return "1 byte" if n == 1 else f"{n:.0f} bytes"


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
    """MemAvailable of /proc/meminfo in bytes, or less where this process's memory cgroup (a
    container's limit) leaves less (`cgroup_room`); 0 when unknown. /proc/meminfo shows the host's
    memory inside a container, so a plan made from it alone is killed at the container's limit."""
    free = _proc_bytes("/proc/meminfo", "MemAvailable")
    room = cgroup_room()
    return free if room is None else min(free, room) if free else room


def cgroup_room(proc_cgroup: str | Path = "/proc/self/cgroup", fs_root: str | Path = "/sys/fs/cgroup") -> int | None:
    """Bytes this process's memory cgroup still allows: its limit less what it uses, page cache that
    can be dropped (inactive files) not counted as used; None without a limit or cgroup.

    cgroup v2 (a line "0::PATH" of /proc/self/cgroup): memory.max, memory.current, memory.stat's
    inactive_file; v1 (a line "N:...memory...:PATH"): memory.limit_in_bytes, memory.usage_in_bytes,
    memory.stat's total_inactive_file. PATH is looked up under fs_root, then fs_root itself (a
    container sees its own cgroup at the mount's root)."""
    try:
        lines = Path(proc_cgroup).read_text().splitlines()
    except OSError:
        return None
    root = Path(fs_root)
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        if parts[0] == "0" and parts[1] == "":
            candidates, files = [root / parts[2].lstrip("/"), root], ("memory.max", "memory.current", "inactive_file")
        elif "memory" in parts[1].split(","):
            candidates = [root / "memory" / parts[2].lstrip("/"), root / "memory"]
            files = ("memory.limit_in_bytes", "memory.usage_in_bytes", "total_inactive_file")
        else:
            continue
        for folder in candidates:
            room = _cgroup_room_in(folder, *files)
            if room is not None:
                return room
    return None


NO_LIMIT = 1 << 60  # cgroup v1 writes "no limit" as a number near 2^63


def _cgroup_room_in(folder: Path, limit_file: str, usage_file: str, inactive_key: str) -> int | None:
    try:
        limit_text = (folder / limit_file).read_text().strip()
        usage = int((folder / usage_file).read_text().strip())
    except (OSError, ValueError):
        return None
    if limit_text == "max":
        return None
    try:
        limit = int(limit_text)
    except ValueError:
        return None
    if limit >= NO_LIMIT:
        return None
    inactive = 0
    try:
        for line in (folder / "memory.stat").read_text().splitlines():
            key, _, value = line.partition(" ")
            if key == inactive_key:
                inactive = int(value)
                break
    except (OSError, ValueError):
        pass
    return max(0, limit - max(0, usage - inactive))


def current_rss() -> int:
    """Resident memory of this process now (VmRSS), in bytes."""
    return _proc_bytes("/proc/self/status", "VmRSS")


def trim_heap() -> None:
    """Hand the heap's free memory back to the system (glibc's malloc_trim; nothing elsewhere), so
    that `current_rss` then counts what the process holds, not what it held: after a fit stage's
    probe views, 200 of a process's 539 MB were freed arrays the allocator had kept (4 views x
    4,000 scattered masks), and the plan took them for memory in use, refusing the budget its own
    refusal had named a moment before (probe round 12)."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        trim = getattr(libc, "malloc_trim", None)
    except OSError:
        trim = None
    if trim is not None:
        trim(0)


def peak_rss() -> int:
    """Peak resident memory of this process so far, in bytes: VmHWM, the high-water mark of the
    memory map its program runs in, where the system has one; ru_maxrss otherwise. ru_maxrss alone
    would not do in a child started by fork and exec: Linux carries the forking parent's resident
    size over exec into it (a bench's child of a 1.2 GB process "peaked" at 1.2 GB)."""
    return _proc_bytes("/proc/self/status", "VmHWM") or int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


SMALL_PAGES_FROM = 4 << 20  # numpy advises huge pages from this many bytes on


def small_page_zeros(shape: int | tuple[int, ...], dtype=np.float32) -> np.ndarray:
    """A zero array in ordinary 4 kB pages: anonymous memory that numpy has not advised the kernel
    to back with transparent huge pages (numpy does for every array of 4 MB or more).

    For the large arrays a registration makes once (the accumulator's sums F [N, D], the in-memory
    field of a run in blocks). Where the kernel compacts memory before it hands out a huge
    page (/sys/kernel/mm/transparent_hugepage/defrag = madvise, common) and memory is fragmented,
    faulting such an array in stalls: flowers' 1.1 GB of sums took 2.59 s instead of 0.39 s
    (docs/registration.md, "Huge pages"). Arrays made and freed every view keep numpy's advice:
    there huge pages freed by the last view are handed out again at once, and small pages were
    measured slower (the torch engine's per-view outputs: 264 -> 377 ms of rendering per view).
    """
    shape = (int(shape),) if np.isscalar(shape) else tuple(int(n) for n in shape)
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if nbytes < SMALL_PAGES_FROM:  # numpy gives these small pages anyway
        return np.zeros(shape, dtype)
    buf = mmap.mmap(-1, nbytes)  # anonymous: zero pages, faulted in on first touch
    if hasattr(mmap, "MADV_NOHUGEPAGE"):  # also where THP is "always"
        buf.madvise(mmap.MADV_NOHUGEPAGE)
    return np.frombuffer(buf, dtype, count=nbytes // dtype.itemsize).reshape(shape)


def small_page_full(shape: int | tuple[int, ...], value, dtype) -> np.ndarray:
    """`np.full(shape, value, dtype)` in small pages (`small_page_zeros`, which zero tables use
    directly), for the per-Gaussian tables
    a registration makes once per block and then touches a few rows a view at a time (the check's
    and the vote's slots, the floater statistics' scratch, the coalescer's): with numpy's huge-page
    advice their first touches stalled on the kernel's compaction (flowers, the check's 104 MB of
    slots: 465 ms in the first view's fold, 3-5 ms in the later ones; docs/registration.md, "Huge
    pages")."""
    out = small_page_zeros(shape, dtype)
    if value != 0:
        out.fill(value)
    return out

