"""Shared helpers: atomic writes and the network probe that keeps offline errors instant."""

from __future__ import annotations

import socket

import numpy as np
import pytest

from drsplat.utils import atomic_path, host_reachable, save_npy_atomic


def test_host_reachable_on_loopback():
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    port = server.getsockname()[1]
    try:
        assert host_reachable(f"http://127.0.0.1:{port}/weights.bin", timeout=2)
    finally:
        server.close()
    assert not host_reachable(f"http://127.0.0.1:{port}/weights.bin", timeout=2)
    assert not host_reachable("https://no-such-host.invalid/x", timeout=2)


def test_atomic_path_leaves_old_file_on_failure(tmp_path):
    target = tmp_path / "a.npy"
    save_npy_atomic(target, np.arange(3))
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"partial")
            raise RuntimeError("interrupted")
    np.testing.assert_array_equal(np.load(target), np.arange(3))
    assert [p.name for p in tmp_path.iterdir()] == ["a.npy"]
