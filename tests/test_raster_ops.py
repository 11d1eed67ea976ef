"""The fused top-k op (drsplat.raster_ops.render_topk) on the CPU: numba's kernels behind one torch op.

Held to the torch reference (the torch ops of drsplat.raster_torch, fused=False) and to the numba
engine on random and hard cases; counted as one dispatcher call with no host sync; checked by
torch's own op checker (schema, fake kernel, no aliasing). Its CUDA kernel runs in Triton's
interpreter in tests/test_raster_triton.py.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from drsplat.bench.opcount import OpCounter
from drsplat.raster import NEAR, TILE_SIZE, rasterize
from drsplat.raster_ops import camera_from_values, camera_values, render_topk
from drsplat.raster_torch import prepare_scene_torch, rasterize_torch
from drsplat.testing import assert_agree, hard_cases, random_case, stacked_case

pytestmark = pytest.mark.usefixtures("one_torch_thread")

CASES = [random_case(0, topk=8), random_case(1, n=900, topk=1), random_case(2, topk=64), stacked_case(600),
         *[c for c in hard_cases() if c.name != "stacked"]]


def _op_args(case, with_median=True, capacity=-1, ranked=True):
    ts = prepare_scene_torch(case.scene)
    cam = case.camera
    return (ts.means, ts.covariances, ts.opacities, ts.finite, camera_values(cam), cam.width, cam.height, NEAR, TILE_SIZE, case.topk,
            with_median, capacity, ranked)


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_op_equals_numba_bit_for_bit_and_the_torch_reference_to_rounding(case):
    fused = rasterize_torch(case.scene, case.camera, case.topk, with_median=True).numpy()
    ref = rasterize(case.scene, case.camera, case.topk, with_median=True, engine="numba")
    for name in ("ids", "weights", "alpha", "median_ids"):
        np.testing.assert_array_equal(getattr(fused, name), getattr(ref, name), err_msg=name)
    assert fused.num_nonfinite == ref.num_nonfinite
    torch_ref = rasterize_torch(case.scene, case.camera, case.topk, with_median=True, fused=False).numpy()
    assert_agree(fused, torch_ref)
    np.testing.assert_array_equal(fused.median_ids, torch_ref.median_ids)


@pytest.mark.parametrize("case", [c for c in hard_cases() if c.name in ("empty", "behind", "extreme-scales")], ids=lambda c: c.name)
def test_op_reports_the_tile_entries_and_counts_of_the_torch_reference(case):
    """tile_entries, non-finite and behind counts equal the torch projection's and lists' (the
    registration's device path learns its tile-list sizes from them)."""
    from drsplat.raster_torch import project_gaussians_torch, tile_lists_torch

    with np.errstate(all="ignore"):
        out = render_topk(*_op_args(case))
        projected = project_gaussians_torch(case.scene, case.camera)
    assert int(out[4]) == int(tile_lists_torch(projected).needed)
    assert int(out[5]) + prepare_scene_torch(case.scene).num_nonfinite == int(projected.num_nonfinite)
    assert int(out[6]) == int(projected.num_behind)


def test_unranked_slots_hold_the_same_entries_padding_last():
    """ranked=False (registration's render): each pixel's slots are the ranked ones in some order,
    the -1 / 0 padding still after them (the in-front test stops at the first empty slot)."""
    case = random_case(8, topk=6)
    ranked = render_topk(*_op_args(case))
    unranked = render_topk(*_op_args(case, ranked=False))
    for a, b in zip(ranked[2:], unranked[2:]):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    ids, weights = unranked[0].numpy(), unranked[1].numpy()
    order = np.lexsort((ids, -weights.astype(np.float64)), axis=-1)
    np.testing.assert_array_equal(np.take_along_axis(ids, order, -1), np.take_along_axis(ranked[0].numpy(), np.lexsort(
        (ranked[0].numpy(), -ranked[1].numpy().astype(np.float64)), axis=-1), -1))
    filled = ids >= 0
    assert not (~filled[..., :-1] & filled[..., 1:]).any(), "padding last"
    assert (ids != ranked[0].numpy()).any(), "the case should leave some pixel's slots unranked"


def test_op_ignores_a_short_capacity_on_the_cpu():
    """Its lists are sized exactly on the host, so a capacity below the entries needed changes nothing."""
    case = random_case(3, topk=6)
    exact = render_topk(*_op_args(case))
    short = render_topk(*_op_args(case, capacity=1))
    assert int(exact[4]) > 1
    for a, b in zip(exact, short):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_op_is_one_dispatcher_call_without_a_host_sync():
    case = random_case(4, topk=6)
    ts = prepare_scene_torch(case.scene)
    with OpCounter() as counter:
        rasterize_torch(ts, case.camera, case.topk, with_median=True)
    assert counter.counts.by_name["drsplat::render_topk"] == 1, dict(counter.counts.by_name)
    assert counter.counts.syncs == 0
    # besides the op, the non-finite count's add; the rest are views (the tensors read as arrays)
    assert counter.counts.ops - counter.counts.views == 2, dict(counter.counts.by_name)


def test_op_passes_torch_opcheck():
    """Schema, fake (meta) kernel shapes and dtypes, and outputs that alias no input."""
    case = random_case(5, n=200, topk=4)
    torch.library.opcheck(render_topk, _op_args(case), test_utils=("test_schema", "test_faketensor"))
    torch.library.opcheck(render_topk, _op_args(case, with_median=False), test_utils=("test_schema", "test_faketensor"))


def test_camera_values_round_trip_and_a_wrong_length_is_named():
    case = random_case(6)
    cam = camera_from_values(camera_values(case.camera), case.camera.width, case.camera.height)
    np.testing.assert_array_equal(cam.R, case.camera.R)
    np.testing.assert_array_equal(cam.t, case.camera.t)
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (case.camera.fx, case.camera.fy, case.camera.cx, case.camera.cy,
                                                                      case.camera.width, case.camera.height)
    with pytest.raises(ValueError, match="camera holds 16 values"):
        camera_from_values([1.0] * 15, 4, 4)
    with pytest.raises(ValueError, match="1 non-finite values and 4x4"):
        camera_from_values([1.0] * 15 + [float("nan")], 4, 4)
    with pytest.raises(ValueError, match="0 non-finite values and -1x4"):
        camera_from_values([1.0] * 16, -1, 4)


def test_rgb_or_depth_take_the_torch_ops_and_fused_refuses_them():
    case = random_case(7, n=200, topk=3)
    out = rasterize_torch(case.scene, case.camera, case.topk, with_depth=True)
    assert out.depth is not None
    with pytest.raises(ValueError, match="fused=False for RGB or depth"):
        rasterize_torch(case.scene, case.camera, case.topk, with_rgb=True, fused=True)
