"""The fused sums kernel (drsplat.registration.sums_triton) against the host accumulator's numba
kernel (`sums.add_pairs_in_place`) and the torch form, bit for bit.

Triton reads TRITON_INTERPRET when it is imported, so the kernel runs in one subprocess with the
variable set (this process's environment is untouched), which adds every case's views and saves
F and W; the test process adds the same views with numba and with `add_pairs_torch` (index_add,
which on a CPU adds a Gaussian's pairs in order).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("triton")

import torch  # noqa: E402

from drsplat.errors import DrsplatError  # noqa: E402
from drsplat.registration.device_sums import add_pairs_torch  # noqa: E402
from drsplat.registration.sums import add_pairs_in_place  # noqa: E402
from tests.interpreted import compiled_ptx, interpreted_outputs  # noqa: E402

# (Gaussians, embedding dimension, seed); "crowded": 2 Gaussians take every pair
CASES = {"d7": (30, 7, 0), "d1": (12, 1, 1), "d64-padded": (40, 64, 2), "crowded": (2, 5, 3)}


def views(name: str):
    """The case's views: (gaussians [P] int64, masks [P] int64, weights [P] float32, feats [M, D]);
    an empty view, zero weights, and for "d64-padded" the device coalescer's padding (Gaussian N,
    mask 0, weight 0) after the real pairs."""
    n, dim, seed = CASES[name]
    rng = np.random.default_rng(seed)
    out = []
    for v in range(6):
        p, m = (0 if v == 2 else int(rng.integers(1, 90))), int(rng.integers(1, 7))
        gaussians = rng.integers(0, n, p)
        masks = rng.integers(0, m, p)
        weights = np.where(rng.random(p) < 0.1, 0.0, rng.uniform(0, 2, p)).astype(np.float32)
        if name == "d64-padded":
            pad = int(rng.integers(1, 20))
            gaussians, masks = np.concatenate([gaussians, np.full(pad, n)]), np.concatenate([masks, np.zeros(pad, np.int64)])
            weights = np.concatenate([weights, np.zeros(pad, np.float32)])
        out.append((gaussians, masks, weights, rng.normal(size=(m, dim)).astype(np.float32)))
    return out


WORKER = """
import json, sys
import numpy as np
import torch
from drsplat.registration.sums_triton import add_pairs_triton
from tests.interpreted import share
from tests.test_sums_triton import CASES, views
for name in share(json.loads(sys.argv[1])):
    n, dim, _ = CASES[name]
    F, W = torch.zeros((n, dim)), torch.zeros(n)
    for view in views(name):
        add_pairs_triton(F, W, *(torch.from_numpy(a) for a in view))
    np.savez(sys.argv[2] + "/" + name + ".npz", F=F.numpy(), W=W.numpy())
"""


@pytest.fixture(scope="module")
def interpreted(tmp_path_factory) -> Path:
    return interpreted_outputs(tmp_path_factory.mktemp("sums"), WORKER, json.dumps(list(CASES)), timeout=600)


@pytest.mark.parametrize("name", list(CASES))
def test_fused_sums_equal_numba_and_the_torch_form(interpreted, name):
    n, dim, _ = CASES[name]
    F, W = np.zeros((n, dim), np.float32), np.zeros(n, np.float32)
    Ft, Wt = torch.zeros((n, dim)), torch.zeros(n)
    for gaussians, masks, weights, feats in views(name):
        real = gaussians < n  # numba's accumulator is given the real pairs only
        add_pairs_in_place(F, W, gaussians[real], masks[real], weights[real], feats)
        add_pairs_torch(Ft, Wt, *(torch.from_numpy(a[real]) for a in (gaussians, masks, weights)), torch.from_numpy(feats), chunk=16)
    got = np.load(interpreted / f"{name}.npz")
    assert got["F"].tobytes() == F.tobytes() == Ft.numpy().tobytes()
    assert got["W"].tobytes() == W.tobytes() == Wt.numpy().tobytes()
    assert (W > 0).sum() >= min(n, 10) // 2


def test_fused_sums_are_refused_on_the_cpu():
    from drsplat.registration.sums_triton import add_pairs_triton

    with pytest.raises(DrsplatError, match="runs on CUDA devices only"):
        add_pairs_triton(torch.zeros((2, 3)), torch.zeros(2), torch.zeros(1, dtype=torch.int64), torch.zeros(1, dtype=torch.int64), torch.ones(1),
                         torch.ones((1, 3)))


@pytest.mark.parametrize("ones", [False, True], ids=["scalars", "scalars equal to 1 (Triton passes them as constants)"])
def test_fused_sums_kernel_compiles_to_ptx_without_fma(ones):
    """Typed mode for sm_90 and no fused multiply-adds: w·f rounds to float32 before the add, as numba's."""
    from drsplat.registration.sums_triton import compile_sums_ptx

    ptx = compiled_ptx(compile_sums_ptx, 90, ones=ones)
    assert ".entry _add_pairs_source" in ptx and "mul.rn.f32" in ptx and "add.rn.f32" in ptx and "fma" not in ptx


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (the CPU runs the same source in the interpreter above)")
@pytest.mark.parametrize("name", list(CASES))
def test_on_cuda_fused_sums_equal_numba(name):
    from drsplat.registration.sums_triton import add_pairs_triton

    n, dim, _ = CASES[name]
    F, W = np.zeros((n, dim), np.float32), np.zeros(n, np.float32)
    Fc, Wc = torch.zeros((n, dim), device="cuda"), torch.zeros(n, device="cuda")
    for gaussians, masks, weights, feats in views(name):
        real = gaussians < n
        add_pairs_in_place(F, W, gaussians[real], masks[real], weights[real], feats)
        add_pairs_triton(Fc, Wc, *(torch.from_numpy(a).cuda() for a in (gaussians, masks, weights, feats)))
    assert Fc.cpu().numpy().tobytes() == F.tobytes() and Wc.cpu().numpy().tobytes() == W.tobytes()
