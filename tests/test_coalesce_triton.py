"""The fused coalescing kernels (drsplat.registration.coalesce_triton) against `coalesce_torch`, bit for bit.

Triton reads TRITON_INTERPRET when it is imported, so the kernels run in one subprocess with the
variable set (this process's environment is untouched), which coalesces every case of
tests/test_device_sums.py and saves the outputs; the test process compares them with
`coalesce_torch`'s (itself held to the numba coalescer there).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("triton")

import torch  # noqa: E402

from drsplat.errors import DrsplatError  # noqa: E402
from drsplat.registration.device_sums import coalesce_torch  # noqa: E402
from tests.interpreted import compiled_ptx, interpreted_outputs  # noqa: E402


def cases():
    """The coalescing cases of tests/test_device_sums.py, plus mask ids past the view's masks and
    keys past 2^31 (20 masks x 2^27 Gaussians: int64 sort keys)."""
    from tests.test_device_sums import CASES, random_view

    out = {name: (ids, weights, masks, m, n) for name, ids, weights, masks, m, n in CASES}
    ids, weights, masks = random_view(21, 12, 10, 5, 70, 6)
    out["mask ids past the masks"] = (ids, weights, np.where(masks == 2, 9, masks).astype(masks.dtype), 6, 70)
    ids, weights, masks = random_view(11, 14, 10, 6, 40, 20)
    out["keys past 2^31"] = (ids, weights, masks, 20, 2**27)
    return out


WORKER = """
import json, sys
import numpy as np
import torch
from drsplat.registration.coalesce_triton import coalesce_triton
from tests.interpreted import share
from tests.test_coalesce_triton import cases
for i, (name, (ids, weights, masks, m, n)) in share(enumerate(cases().items())):
    out = coalesce_triton(torch.from_numpy(ids), torch.from_numpy(weights), torch.from_numpy(masks), m, n)
    np.savez(sys.argv[1] + "/" + str(i) + ".npz", **{key: t.numpy() for key, t in zip(["g", "m", "w", "counts", "flags"], out)})
"""

NAMES = list(cases())


@pytest.fixture(scope="module")
def interpreted(tmp_path_factory) -> Path:
    return interpreted_outputs(tmp_path_factory.mktemp("coalesce"), WORKER, timeout=900)


@pytest.mark.parametrize("name", NAMES)
def test_fused_coalescing_equals_the_torch_ops(interpreted, name):
    """The same padded pairs, counts and mask flags as coalesce_torch, bit for bit (on a CPU its
    index_add adds a pair's slots in pixel order, as the numba coalescer does)."""
    ids, weights, masks, m, n = cases()[name]
    want = coalesce_torch(torch.from_numpy(ids), torch.from_numpy(weights), torch.from_numpy(masks), m, n)
    got = np.load(interpreted / f"{NAMES.index(name)}.npz")
    for key, tensor in zip(["g", "m", "w", "counts", "flags"], (want.gaussians, want.masks, want.weights, want.counts, want.mask_flags)):
        assert got[key].dtype == tensor.numpy().dtype and got[key].tobytes() == tensor.numpy().tobytes(), key


def test_fused_coalescing_is_refused_on_the_cpu():
    from drsplat.registration.coalesce_triton import coalesce_triton

    with pytest.raises(DrsplatError, match="runs on CUDA devices only"):
        coalesce_triton(torch.zeros((2, 2, 1), dtype=torch.int32), torch.ones((2, 2, 1)), torch.zeros((2, 2), dtype=torch.int32), 1, 4)


@pytest.mark.parametrize("ones", [False, True], ids=["scalars", "scalars equal to 1 (Triton passes them as constants)"])
def test_fused_coalescing_compiles_to_ptx(ones):
    from drsplat.registration.coalesce_triton import compile_coalesce_ptx

    ptx = compiled_ptx(compile_coalesce_ptx, 90, ones=ones)
    assert ".entry _keys_source" in ptx and ".entry _segments_source" in ptx and "atom" in ptx


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (the CPU runs the same source in the interpreter above)")
@pytest.mark.parametrize("name", NAMES)
def test_on_cuda_fused_coalescing_equals_the_torch_ops_on_the_cpu(name):
    from drsplat.registration.coalesce_triton import coalesce_triton

    ids, weights, masks, m, n = cases()[name]
    want = coalesce_torch(torch.from_numpy(ids), torch.from_numpy(weights), torch.from_numpy(masks), m, n)
    got = coalesce_triton(*(torch.from_numpy(a).cuda() for a in (ids, weights, masks)), m, n)
    out_g, out_m, out_w, out_counts, out_flags = got
    for a, b in zip((out_g, out_m, out_counts, out_flags), (want.gaussians, want.masks, want.counts, want.mask_flags)):
        assert a.cpu().numpy().tobytes() == b.numpy().tobytes()
    # a pair's weight is a sum of its slots' weights: CUDA's atomics add them in no fixed order
    # (an H100 gave the last bit differently on 3 cases, 2026-11-27)
    np.testing.assert_allclose(out_w.cpu().numpy(), want.weights.numpy(), rtol=1e-5, atol=0)
