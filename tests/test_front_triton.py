"""The fused in-front kernel (drsplat.registration.front_triton) against `front_flags_torch`, bit for bit.

Triton reads TRITON_INTERPRET when it is imported, so the kernel runs in one subprocess with the
variable set (this process's environment is untouched), which saves its flags; the test process
compares them with the torch form's (itself held to the numba kernel's bits in tests/test_device_sums.py).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("triton")

import torch  # noqa: E402

from drsplat.raster import rasterize  # noqa: E402
from drsplat.registration.aggregate import FRONT_TOLERANCE, RayGeometry  # noqa: E402
from drsplat.registration.device_sums import DeviceRays, front_flags_torch  # noqa: E402
from drsplat.testing import random_case, windowed  # noqa: E402
from tests.interpreted import compiled_ptx, interpreted_outputs  # noqa: E402


def _inputs(name: str):
    """(rays, camera, ids [H, W, k] int32, median ids [H, W] int32) of a named case."""
    seed, topk = {"random-k8": (0, 8), "random-k1": (1, 1), "random-k40": (2, 40), "hostile": (3, 8), "no-median": (4, 8),
                  "all-empty": (5, 4)}[name]
    case = windowed(random_case(seed, n=300, topk=topk), 12, 8, 24, 20)  # the interpreter runs a program per 2 pixels
    out = rasterize(case.scene, case.camera, case.topk, with_median=True, engine="numba")
    geometry = RayGeometry.from_scene(case.scene)
    ids, median = out.ids.copy(), out.median_ids.copy()
    if name == "hostile":  # non-finite and degenerate precisions: den <= 0, NaN, inf, a zero matrix
        geometry.precisions[:20] = 0.0
        geometry.precisions[20:40, 0] = np.nan
        geometry.precisions[40:60, 5] = np.inf
        geometry.precisions[60:80] *= -1.0
        geometry.reach[80:100] = np.inf
    if name == "no-median":
        median[::2] = -1
    if name == "all-empty":
        ids[:] = -1
    return DeviceRays.from_host(geometry, torch.device("cpu")), case.camera, torch.from_numpy(ids), torch.from_numpy(median)


CASES = ["random-k8", "random-k1", "random-k40", "hostile", "no-median", "all-empty"]

WORKER = """
import json, sys
import numpy as np
from drsplat.registration.aggregate import FRONT_TOLERANCE
from drsplat.registration.front_triton import front_flags_triton
from tests.interpreted import share
from tests.test_front_triton import _inputs
for name in share(json.loads(sys.argv[1])):
    rays, camera, ids, median = _inputs(name)
    with np.errstate(all="ignore"):
        flags = front_flags_triton(rays.means, rays.precisions, rays.reach, camera, ids, median, FRONT_TOLERANCE)
    np.save(sys.argv[2] + "/" + name + ".npy", flags.numpy())
"""


@pytest.fixture(scope="module")
def interpreted(tmp_path_factory) -> Path:
    return interpreted_outputs(tmp_path_factory.mktemp("front"), WORKER, json.dumps(CASES), timeout=600)


@pytest.mark.parametrize("name", CASES)
def test_fused_front_flags_equal_the_torch_form(interpreted, name):
    rays, camera, ids, median = _inputs(name)
    with np.errstate(all="ignore"):
        ref = front_flags_torch(rays, camera, ids, median, FRONT_TOLERANCE).numpy()
    got = np.load(interpreted / f"{name}.npy")
    assert got.shape == ref.shape and got.dtype == np.bool_
    np.testing.assert_array_equal(got, ref)
    if name.startswith("random"):
        assert 0 < ref.sum() < (ids.numpy() >= 0).sum(), "the case should have slots in front and behind"
    if name == "all-empty":
        assert not got.any()


@pytest.mark.parametrize("ones", [False, True], ids=["scalars", "scalars equal to 1 (Triton passes them as constants)"])
def test_fused_front_kernel_compiles_to_ptx_without_fma(ones):
    """Typed mode for sm_90, IEEE float64 division and no fused multiply-adds (numba's and torch's rounding)."""
    from drsplat.registration.front_triton import compile_front_ptx

    ptx = compiled_ptx(compile_front_ptx, 90, ones=ones)
    assert ".entry _front_flags_source" in ptx and "div.rn.f64" in ptx and "fma" not in ptx


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (the CPU runs the same source in the interpreter above)")
@pytest.mark.parametrize("name", CASES)
def test_on_cuda_fused_front_flags_equal_the_torch_form(name):
    from drsplat.registration.front_triton import front_flags_triton

    rays, camera, ids, median = _inputs(name)
    cuda = DeviceRays(*(t.cuda() for t in (rays.means, rays.precisions, rays.reach)))
    with np.errstate(all="ignore"):
        ref = front_flags_torch(cuda, camera, ids.cuda(), median.cuda(), FRONT_TOLERANCE).cpu().numpy()
        got = front_flags_triton(cuda.means, cuda.precisions, cuda.reach, camera, ids.cuda(), median.cuda(), FRONT_TOLERANCE).cpu().numpy()
    np.testing.assert_array_equal(got, ref)
