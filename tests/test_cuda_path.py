"""Registration through the torch ops' CUDA kernels, run on the CPU: the GPU path's glue end to end.

Each per-view op of the torch engine (drsplat.raster_ops.render_topk, and in
drsplat.registration.device_sums the coalescing, weighting, floater statistics, vote and sums ops)
has a CPU kernel (numba) and a CUDA kernel (Triton launches and torch ops). The CUDA kernels are
held to the torch forms one by one under Triton's interpreter (tests/test_raster_triton.py,
tests/test_coalesce_triton.py, ...); here a whole registration runs through them: one subprocess,
with TRITON_INTERPRET=1, registers the ops' CUDA kernels as their CPU kernels (that process only)
and sizes the tile lists from earlier views as on CUDA, registers a small scene in two modes and
saves the fields, which must equal the numba engine's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("triton")

import torch  # noqa: E402

from drsplat.defaults import AGGREGATE_MODES  # noqa: E402
from drsplat.registration import RegisterOptions, register_features  # noqa: E402
from tests.interpreted import interpreted_outputs  # noqa: E402

# between them every op: render, weighting, EM, statistics, coalescing, vote, sums; and a check mode's pairs copied to the host
MODES = ["core-reject", "explain-vote-reject", "check-vote-reject"]


def small_world(folder: Path):
    """A 150-Gaussian blob, 3 orbiting 16x16 views (one tile each: the interpreter's time grows with
    the tiles and their lists) and random mask features written to `folder`."""
    from drsplat.bench.register import blob_scene, orbit_cameras, random_mask_features

    scene = blob_scene(150, seed=3)
    cameras = orbit_cameras(scene.means, 3, 16, 16)
    random_mask_features(folder, cameras, np.random.default_rng(1))
    return scene, cameras


WORKER = """
import sys
from pathlib import Path
import numpy as np
import drsplat.raster_torch as raster_torch
import drsplat.registration.device_sums as device_sums
from drsplat.raster_ops import render_topk
from drsplat.registration import RegisterOptions, register_features
from drsplat.registration.front_triton import front_flags_triton
from tests.interpreted import share, shard_name
from tests.test_cuda_path import MODES, small_world

# the CUDA kernels as the CPU kernels, in this process only
render_topk.register_kernel("cpu")(raster_torch.render_topk_triton)
for op, kernel in [(device_sums.coalesce_pairs_op, device_sums._coalesce_pairs_cuda), (device_sums.view_weights_op, device_sums._view_weights_cuda),
                   (device_sums.explain_weights_op, device_sums._explain_weights_cuda), (device_sums.view_stats_op, device_sums._view_stats_cuda),
                   (device_sums.vote_fold_op, device_sums._vote_fold_cuda), (device_sums.add_pairs_op, device_sums._add_pairs_cuda)]:
    op.register_kernel("cpu")(kernel)
device_sums.triton_available = lambda: True
device_sums.front_flags = lambda rays, camera, ids, median_ids, tolerance=device_sums.FRONT_TOLERANCE: front_flags_triton(
    rays.means, rays.precisions, rays.reach, camera, ids, median_ids, tolerance)
device_sums.TileCapacity.for_device = classmethod(lambda cls, device: cls())  # sized from earlier views, as on CUDA
out = Path(sys.argv[1])
features = out / ("features-" + shard_name())  # each shard writes its own (the same files)
scene, cameras = small_world(features)
for mode in share(MODES):
    got = register_features(scene, cameras, features, RegisterOptions(topk=6, aggregate=mode, engine="torch", device="cpu"),
                            show_progress=False)
    np.savez(out / (mode + ".npz"), features=got.features, weights=got.weights, sums_on=got.sums_on, pairs_on=got.pairs_on, pairs=got.num_pairs)
"""


@pytest.fixture(scope="module")
def cuda_path(tmp_path_factory) -> Path:
    return interpreted_outputs(tmp_path_factory.mktemp("cuda-path"), WORKER, timeout=900)


@pytest.mark.parametrize("mode", MODES)
def test_registration_through_the_cuda_kernels_equals_numba(cuda_path, mode):
    scene, cameras = small_world(cuda_path / "numba-features")
    want = register_features(scene, cameras, cuda_path / "numba-features", RegisterOptions(topk=6, aggregate=mode), show_progress=False)
    got = np.load(cuda_path / f"{mode}.npz")
    assert str(got["pairs_on"]) == str(got["sums_on"]) == "cpu" and int(got["pairs"]) == want.num_pairs > 0
    np.testing.assert_array_equal(got["weights"], want.weights)
    np.testing.assert_array_equal(got["features"], want.features)


# ----------------------------------------------------------------------------- on a real GPU

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (the CPU runs the CUDA kernels in the interpreter above)")


@pytest.fixture(scope="module")
def rooms(tmp_path_factory) -> dict:
    """hard-tiny with 20 % mislabelled masks, its masks rendered from the Gaussians (the fit stage picks
    the paper's footprint) and ray-cast from the geometry (it picks `sharp`), 6 views each."""
    from drsplat.cameras import load_cameras
    from drsplat.scene import load_ply
    from drsplat.synthetic import write_dataset

    found = {}
    for source in ("render", "geometry"):
        data = write_dataset(tmp_path_factory.mktemp(source) / "hard", "hard-tiny", 0, mislabel_fraction=0.2, mask_source=source,
                             show_progress=False)
        found[source] = (load_ply(data / "scene.ply"), load_cameras(data)[:6], data / "features")
    return found


@needs_cuda
@pytest.mark.parametrize("source", ["render", "geometry"])
@pytest.mark.parametrize("mode", AGGREGATE_MODES)
def test_registration_on_cuda_agrees_with_numba(rooms, source, mode):
    """Every mode on the GPU: the same decisions as numba (the fit stage's footprint, the Gaussians
    assigned and rejected), the features and weights to float32 rounding (CUDA's atomics add in no
    fixed order)."""
    scene, cameras, features = rooms[source]
    want = register_features(scene, cameras, features, RegisterOptions(topk=10, aggregate=mode), show_progress=False)
    got = register_features(scene, cameras, features, RegisterOptions(topk=10, aggregate=mode, engine="torch", device="cuda"),
                            show_progress=False)
    assert got.aggregate == want.aggregate and got.num_pairs == want.num_pairs
    assert got.pairs_on.startswith("cuda") and got.sums_on.startswith("cuda")
    assigned, expected = got.weights > 0, want.weights > 0
    assert np.array_equal(assigned, expected), f"{int((assigned != expected).sum())} Gaussians assigned differently"
    np.testing.assert_allclose(got.weights, want.weights, rtol=1e-5, atol=1e-7)
    worst = float(np.abs(got.features - want.features).max())
    assert worst <= 1e-4, f"features differ by up to {worst:.3g}"

