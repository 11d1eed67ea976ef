"""The torch rasterizer engine against the numba engine (CPU; the same code runs on CUDA)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from drsplat.raster import ENGINES, prepare_for_engine, project_gaussians, rasterize
from drsplat.raster_torch import rasterize as torch_rasterize
from drsplat.raster_torch import TorchScene, composite_torch, project_gaussians_torch, rasterize_torch
from drsplat.testing import assert_agree, check_engine, front_camera, hard_cases, random_case, random_scene, stacked_case


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def torch_engine(*args, **kwargs):
    """The torch ops (the reference: the fused op runs numba's kernels on a CPU, tests/test_raster_ops.py)."""
    return torch_rasterize(*args, fused=False, **kwargs)


def numba_engine(*args, **kwargs):
    return rasterize(*args, engine="numba", **kwargs)


@pytest.mark.parametrize("seed, sh_degree, topk", [(0, 0, 8), (1, 1, 1), (2, 2, 64), (3, 3, 20)])
def test_torch_matches_numba_on_random_scenes(seed, sh_degree, topk):
    case = random_case(seed, sh_degree=sh_degree, topk=topk)
    out = check_engine(torch_engine, numba_engine, case)
    assert (out.ids >= 0).sum() > 0.3 * out.ids[..., 0].size, "the scene should cover the image"


@pytest.mark.parametrize("case", [c for c in hard_cases() if c.name != "stacked"], ids=lambda c: c.name)
def test_torch_matches_numba_on_hard_cases(case):
    check_engine(torch_engine, numba_engine, case)


def test_torch_stacked_gaussians_stop_at_the_transmittance_floor():
    case = stacked_case(2_000)
    out = check_engine(torch_engine, numba_engine, case)
    n = int(np.floor(np.log2(1e4)))
    np.testing.assert_allclose(out.weights[7, 10, :n], 0.5 ** np.arange(1, n + 1), rtol=1e-6)
    np.testing.assert_array_equal(out.ids[7, 10, :n], np.arange(n))


@pytest.mark.parametrize("chunk, max_elements", [(1, 1), (7, 5000), (33, 1 << 16)])
def test_chunking_changes_memory_not_results(chunk, max_elements):
    """Tiny chunks and groups exercise the carried transmittance and the top-k merge across chunks."""
    case = random_case(4, n=300, sh_degree=1, topk=6)
    proj = project_gaussians_torch(case.scene, case.camera, with_colors=True)
    whole = composite_torch(proj, 6, with_rgb=True, with_depth=True, max_elements=1 << 22).numpy()
    parts = composite_torch(proj, 6, with_rgb=True, with_depth=True, chunk=chunk, max_elements=max_elements).numpy()
    np.testing.assert_array_equal(parts.ids, whole.ids)
    np.testing.assert_allclose(parts.weights, whole.weights, atol=1e-7, rtol=0)
    np.testing.assert_allclose(parts.rgb, whole.rgb, atol=1e-6, rtol=0)
    assert_agree(parts, numba_engine(case.scene, case.camera, 6, with_rgb=True, with_depth=True))


def test_projection_matches_numba():
    rng = np.random.default_rng(29)
    scene = random_scene(rng, 500, spread=3.0, log_scale=(-9.0, 4.0))
    scene.means[:20] = [0.0, 0.0, -4.0]
    from drsplat.cameras import look_at_camera

    cam = look_at_camera([0.2, -0.1, -4.0], [0.1, 0.2, 0.0], 50, 20, fov_x_deg=70, cx=12.0, cy=15.0)
    a, b = project_gaussians_torch(scene, cam), project_gaussians(scene, cam)
    valid = a.valid.numpy()
    np.testing.assert_array_equal(valid, b.valid)
    assert 0 < valid.sum() < 500 and a.num_behind == b.num_behind > 0 and a.num_nonfinite == b.num_nonfinite
    np.testing.assert_array_equal(a.tile_rects.numpy()[valid], b.tile_rects[valid])
    np.testing.assert_array_equal(a.radii.numpy()[valid], b.radii[valid])
    # the same float64 operations in the same order, true divisions included: numba's bits
    np.testing.assert_array_equal(a.means2d.numpy()[valid], b.means2d[valid])
    np.testing.assert_array_equal(a.conics.numpy()[valid], b.conics[valid])
    np.testing.assert_array_equal(a.depths.numpy(), b.depths)


def test_mask_and_prepared_scene_keep_scene_ids():
    rng = np.random.default_rng(19)
    scene = random_scene(rng, 250)
    mask = rng.random(250) < 0.4
    cam = front_camera(32, 24)
    prepared = prepare_for_engine(scene, "torch", "cpu")
    assert isinstance(prepared, TorchScene)
    a = rasterize(prepared, cam, 10, mask=mask, with_depth=True, engine="torch")
    assert_agree(a, numba_engine(scene, cam, 10, mask=mask, with_depth=True))
    with pytest.raises(ValueError, match="mask"):
        rasterize_torch(scene, cam, 10, mask=mask[:-1])


def test_engine_registry_and_device_errors():
    assert {"numba", "reference", "torch"} <= set(ENGINES)
    scene, cam = random_scene(np.random.default_rng(0), 10), front_camera(16, 16)
    with pytest.raises(ValueError, match="unknown rasterizer engine 'vulkan'"):
        rasterize(scene, cam, 4, engine="vulkan")
    with pytest.raises(ValueError, match="CPU only"):
        rasterize(scene, cam, 4, engine="numba", device="cuda")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_cuda_fused_projection_equals_numba():
    """The Triton projection compiled for the GPU (FMA off, IEEE division and square roots) gives
    numba's projection; exact on the interpreter, and expected exact here too."""
    from drsplat.raster_torch import project_gaussians_fused

    for case in [random_case(8, n=3000, topk=4), *hard_cases()]:
        with np.errstate(all="ignore"):
            got = project_gaussians_fused(case.scene, case.camera, device="cuda")
            want = project_gaussians(case.scene, case.camera)
        for name in ("means2d", "conics", "depths", "valid", "tile_rects"):
            np.testing.assert_array_equal(getattr(got, name).cpu().numpy(), getattr(want, name), err_msg=f"{case.name}: {name}")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_cuda_matches_cpu():
    case = random_case(5, n=2000, sh_degree=2, topk=20)
    assert_agree(rasterize(case.scene, case.camera, case.topk, engine="torch", device="cuda", **case.kwargs),
                 numba_engine(case.scene, case.camera, case.topk, **case.kwargs))


def _lists(lists, tile: int) -> np.ndarray:
    start, count = int(lists.offsets[tile]), int(lists.counts[tile])
    return lists.ids[start:start + count].numpy()


@pytest.mark.parametrize("case", [random_case(5, n=300, topk=4)] + [c for c in hard_cases() if c.name in ("empty", "behind", "extreme-scales")],
                         ids=lambda c: c.name)
def test_tile_lists_sized_without_a_read_equal_the_exact_ones(case):
    """Lists sized to a capacity at least the entries needed are the exact lists entry for entry (and
    nothing is read from the device: no host sync); a capacity below it is reported as overflowed."""
    from drsplat.bench.opcount import OpCounter
    from drsplat.raster_torch import tile_lists_torch

    proj = project_gaussians_torch(case.scene, case.camera)
    exact = tile_lists_torch(proj)
    needed = int(exact.needed)
    assert exact.ids.shape[0] == needed and not bool(exact.overflowed())
    for capacity in (needed, needed + 1, 2 * needed + 100):
        with OpCounter() as counter:
            sized = tile_lists_torch(proj, capacity)
        assert counter.counts.syncs == 0 and sized.ids.shape[0] == capacity and not bool(sized.overflowed())
        assert int(sized.needed) == needed
        np.testing.assert_array_equal(sized.counts.numpy(), exact.counts.numpy())
        np.testing.assert_array_equal(sized.offsets.numpy(), exact.offsets.numpy())
        for tile in range(exact.counts.shape[0]):
            np.testing.assert_array_equal(_lists(sized, tile), _lists(exact, tile))
    if needed > 1:
        short = tile_lists_torch(proj, needed - 1)
        assert bool(short.overflowed()) and int(short.counts.sum()) == needed - 1


def test_a_render_with_sized_tile_lists_equals_the_exact_one_and_reports_the_entries():
    case = random_case(6, n=300, topk=5)
    exact = rasterize_torch(case.scene, case.camera, 5, with_median=True, fused=False)
    needed = int(exact.tile_entries)
    roomy = rasterize_torch(case.scene, case.camera, 5, with_median=True, tile_capacity=needed + 1000, fused=False)
    assert int(roomy.tile_entries) == needed
    for name in ("ids", "weights", "alpha", "median_ids"):
        np.testing.assert_array_equal(getattr(roomy, name).numpy(), getattr(exact, name).numpy())
    short = rasterize_torch(case.scene, case.camera, 5, tile_capacity=needed // 2, fused=False)
    assert int(short.tile_entries) == needed > needed // 2, "the output says how many entries it needed"
