"""Small shared helpers: atomic writes, progress bars, cancellation."""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TypeVar

import numpy as np

log = logging.getLogger("drsplat")

T = TypeVar("T")


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to `path`; rename it over `path` only if the block succeeds.

    Readers never see a half-written file, and an interrupted job leaves the old file intact.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_current_umask())  # mkstemp makes 0600; give the file normal permissions
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def _current_umask() -> int:
    """The process umask, read without changing it where /proc allows (os.umask is not thread-safe)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def save_npy_atomic(path: str | Path, array: np.ndarray) -> None:
    """np.save through a temp file + rename (np.save would append .npy to a temp name)."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, array)


class CancelToken:
    """Cooperative cancellation shared between a worker and a GUI or signal handler."""

    def __init__(self) -> None:
        self._event = threading.Event()

    def cancel(self) -> None:
        self._event.set()

    @property
    def cancelled(self) -> bool:
        return self._event.is_set()

    def raise_if_cancelled(self) -> None:
        from drsplat.errors import Cancelled

        if self._event.is_set():
            raise Cancelled("cancelled by the user")


def progress(iterable: Iterable[T], desc: str, total: int | None = None, enabled: bool = True, unit: str = "it") -> Iterable[T]:
    """Wrap an iterable with a tqdm bar on stderr (disabled when not wanted)."""
    from tqdm.auto import tqdm

    return tqdm(iterable, desc=desc, total=total, disable=not enabled, unit=unit, dynamic_ncols=True, leave=False)


def host_reachable(url: str, timeout: float = 3.0) -> bool:
    """Whether the host of `url` resolves and accepts a TCP connection within `timeout` seconds.

    Download clients retry with back-off for tens of seconds on a closed network; one cheap
    probe lets an offline user get the "how to provide weights" message at once.
    """
    import socket
    from urllib.parse import urlparse

    parsed = urlparse(url)
    port = parsed.port or (443 if parsed.scheme == "https" else 80)
    try:
        with socket.create_connection((parsed.hostname or "", port), timeout=timeout):
            return True
    except OSError:
        return False
