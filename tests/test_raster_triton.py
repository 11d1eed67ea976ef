"""The fused Triton top-k kernel (drsplat.raster_triton) against the numba engine, on the CPU.

Triton reads TRITON_INTERPRET when it is imported, so the kernel runs in one subprocess with the
variable set (this process's environment is untouched); that subprocess renders every case through
the fused op's CUDA kernel (`raster_torch.render_topk_triton`) with the interpreter and saves the outputs, which are compared here
with numba's: ids identical except between near-ties (weights within 1e-6 relative), weights within
1e-5 relative, alpha and median ids equal.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("triton")

import torch  # noqa: E402

from drsplat.errors import DrsplatError  # noqa: E402
from drsplat.raster import rasterize  # noqa: E402
from drsplat.testing import hard_cases, random_case, stacked_case, windowed  # noqa: E402
from tests.interpreted import compiled_ptx, interpreted_outputs  # noqa: E402

# small scenes seen through small windows: the interpreter's time grows with the 16x16 tiles (each
# tile's final tl.sort of 256 x k slots, ~10 s at k = 64) and the list entries
CASES = {
    "random-0-k5": lambda: _small(windowed(random_case(0, n=90, topk=5), 8, 8, 24, 20)),
    "random-1-k1": lambda: _small(windowed(random_case(1, n=90, topk=1), 8, 8, 24, 20)),
    "random-2-k16": lambda: _small(windowed(random_case(2, n=120, topk=16), 8, 8, 24, 20)),
    "stacked-k64": lambda: windowed(stacked_case(40), 0, 0, 16, 16),  # T reaches its floor after 14 of the 40
    **{c.name: (lambda c=c: c) for c in hard_cases() if c.name in ("empty", "behind", "camera-inside")},
    "opacity-0-and-1": lambda: windowed(next(c for c in hard_cases() if c.name == "opacity-0-and-1"), 2, 6, 32, 16),
}

def _nonfinite_case():
    """NaN and infinite attributes, an overflowing scale, Gaussians behind the camera and culled by
    opacity: every status the projection kernel writes."""
    case = random_case(4, n=200, topk=4)
    scene = case.scene
    scene.means[0, 1] = np.nan
    scene.quats[1, 2] = np.inf
    scene.log_scales[2, 0] = 200.0  # exp overflows: an infinite covariance
    scene.log_scales[3] = 60.0  # finite but enormous: the screen covariance overflows
    scene.opacity_logits[4:8] = -30.0  # transparent: culled
    scene.means[8:12, 2] = -10.0  # behind the camera
    return case


# the projection kernel alone (cheap in the interpreter: one program per 256 Gaussians)
PROJECT_CASES = {
    **{name: make for name, make in CASES.items()},
    "big-random": lambda: random_case(7, n=3000, topk=4),
    "nonfinite": _nonfinite_case,
    **{c.name: (lambda c=c: c) for c in hard_cases() if c.name in ("extreme-scales", "off-centre-non-square")},
}

# the other kernels and launch shapes, on a few cases: (case, pixels per program, list entries per step; 0 = the per-entry kernel)
VARIANTS = {"per-entry": [("random-0-k5", 16, 0), ("random-2-k16", 16, 0), ("stacked-k64", 64, 0)],
            "chunked-16-pixels-8-entries": [("random-2-k16", 16, 8), ("random-1-k1", 16, 8)]}

# the compositing kernel on tile lists sized with room to spare (drsplat.raster_torch.tile_lists_torch(capacity))
SIZED = ["random-0-k5"]

WORKER = """
import json, sys
import numpy as np
from drsplat.raster_torch import bin_gaussians_torch, project_gaussians_fused, tile_lists_torch
from drsplat.raster_triton import composite_topk_triton
from tests.interpreted import share
from tests.test_raster_triton import CASES, PROJECT_CASES, SIZED, VARIANTS, triton_op_kernel
for name in share(json.loads(sys.argv[1])):
    case = CASES[name]()
    ids, weights, alpha, median = triton_op_kernel(case)[:4]
    np.savez(sys.argv[2] + "/" + name + ".npz", ids=ids.numpy(), weights=weights.numpy(), alpha=alpha.numpy(), median=median.numpy())
for variant, name, block, chunk in share((variant, *run) for variant, runs in VARIANTS.items() for run in runs):
    case = CASES[name]()
    p = project_gaussians_fused(case.scene, case.camera)
    ids, weights, alpha, median = composite_topk_triton(p, bin_gaussians_torch(p), case.topk, with_median=True, block=block, chunk=chunk)
    np.savez(sys.argv[2] + "/" + variant + "-" + name + ".npz", ids=ids.numpy(), weights=weights.numpy(), alpha=alpha.numpy(),
             median=median.numpy())
for name in share(SIZED):  # tile lists sized without a read (registration's device path): padding past the lists
    case = CASES[name]()
    p = project_gaussians_fused(case.scene, case.camera)
    lists = tile_lists_torch(p, int(tile_lists_torch(p).needed) + 777)
    ids, weights, alpha, median = composite_topk_triton(p, lists.as_tuple(), case.topk, with_median=True)
    np.savez(sys.argv[2] + "/sized-" + name + ".npz", ids=ids.numpy(), weights=weights.numpy(), alpha=alpha.numpy(), median=median.numpy())
for name in share(PROJECT_CASES):
    case = PROJECT_CASES[name]()
    with np.errstate(all="ignore"):
        p = project_gaussians_fused(case.scene, case.camera)
    np.savez(sys.argv[2] + "/project-" + name + ".npz", means2d=p.means2d.numpy(), conics=p.conics.numpy(), depths=p.depths.numpy(),
             radii=p.radii.numpy(), valid=p.valid.numpy(), tile_rects=p.tile_rects.numpy(), counts=[int(p.num_nonfinite), int(p.num_behind)])
"""


def triton_op_kernel(case):
    """The fused op's CUDA kernel (`render_topk_triton`) on `case`, on the CPU: its 7 outputs."""
    from drsplat.raster import NEAR, TILE_SIZE
    from drsplat.raster_ops import camera_values
    from drsplat.raster_torch import prepare_scene_torch, render_topk_triton

    ts = prepare_scene_torch(case.scene)
    cam = case.camera
    return render_topk_triton(ts.means, ts.covariances, ts.opacities, ts.finite, camera_values(cam), cam.width, cam.height, NEAR, TILE_SIZE,
                              case.topk, True, -1, True)


def _small(case):
    case.scene.opacity_logits[:] = np.abs(case.scene.opacity_logits)  # opaque enough that most pixels reach the T floor early
    return case


@pytest.fixture(scope="module")
def interpreted(tmp_path_factory) -> Path:
    """Folder of <case>.npz written by the fused kernel under Triton's interpreter (one subprocess)."""
    return interpreted_outputs(tmp_path_factory.mktemp("triton"), WORKER, json.dumps(list(CASES)), timeout=900)


def assert_topk_equal(ids, weights, ref_ids, ref_weights) -> None:
    """Weights within 1e-5 relative; ids identical except where the reference weights nearly tie (1e-6 relative)."""
    np.testing.assert_allclose(weights, ref_weights, rtol=1e-5, atol=1e-12)
    differ = ids != ref_ids
    if differ.any():
        w = ref_weights.astype(np.float64)
        gap = np.minimum(np.abs(np.diff(w, axis=2, prepend=np.inf)), np.abs(np.diff(w, axis=2, append=-np.inf)))
        near_tie = gap <= 1e-6 * np.abs(w)
        assert not (differ & ~near_tie).any(), f"{int((differ & ~near_tie).sum())} ids differ where weights do not tie"


def assert_matches_numba(got, name: str):
    """The saved outputs `got` (ids, weights, alpha, median) of case `name` against numba's render; returns numba's."""
    case = CASES[name]()
    ref = rasterize(case.scene, case.camera, case.topk, with_median=True, engine="numba")
    assert_topk_equal(got["ids"], got["weights"], ref.ids, ref.weights)
    np.testing.assert_allclose(got["alpha"], ref.alpha, rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(got["median"], ref.median_ids)
    return ref


@pytest.mark.parametrize("name", list(CASES))
def test_fused_kernel_topk_equals_numba(interpreted, name):
    got = np.load(interpreted / f"{name}.npz")
    ref = assert_matches_numba(got, name)
    assert got["ids"].shape == ref.ids.shape and got["ids"].dtype == np.int32 and got["weights"].dtype == np.float32
    if name.startswith(("random", "stacked")):
        assert (ref.ids[..., 0] >= 0).any(), "the case should have contributions"
    if name.startswith("random"):
        assert (ref.ids[..., -1] >= 0).any(), "the top-k lists should fill (so the kernel's eviction runs) on some pixels"


@pytest.mark.parametrize("variant, name", [(v, run[0]) for v, runs in VARIANTS.items() for run in runs])
def test_other_kernels_and_launch_shapes_equal_numba(interpreted, variant, name):
    """The per-entry kernel (the bench's before) and the chunked one with several pixels per program
    (which fill their slots at different chunks) give numba's lists too."""
    assert_matches_numba(np.load(interpreted / f"{variant}-{name}.npz"), name)


@pytest.mark.parametrize("name", SIZED)
def test_fused_kernel_on_lists_sized_with_room_to_spare_equals_numba(interpreted, name):
    """Lists sized to a capacity past the entries needed (registration's device path sizes them from
    the views before) leave padding after the last list; the kernel reads only the lists."""
    assert_matches_numba(np.load(interpreted / f"sized-{name}.npz"), name)


@pytest.mark.parametrize("name", list(PROJECT_CASES))
def test_fused_projection_equals_numba_bit_for_bit(interpreted, name):
    """The projection kernel (one launch instead of ~186 torch ops) gives numba's projection bit for
    bit: the same float64 operations in the same order, FMA contraction off."""
    from drsplat.raster import prepare_scene, project_gaussians

    case = PROJECT_CASES[name]()
    got = np.load(interpreted / f"project-{name}.npz")
    with np.errstate(all="ignore"):
        ref = project_gaussians(prepare_scene(case.scene), case.camera)
    for field in ("means2d", "conics", "depths", "valid", "tile_rects"):
        np.testing.assert_array_equal(got[field], getattr(ref, field), err_msg=field)
    np.testing.assert_array_equal(np.minimum(got["radii"], 2.0**30), ref.radii.astype(np.float64))  # numba stores int32, capped
    assert got["counts"].tolist() == [ref.num_nonfinite, ref.num_behind]
    if name == "nonfinite":
        assert ref.num_nonfinite >= 3 and ref.num_behind >= 4 and ref.valid.sum() > 100


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (the CPU runs the same source in the interpreter above)")
@pytest.mark.parametrize("block, chunk", [(None, None), (16, 0), (8, 16)], ids=["default", "per-entry", "chunked-8-pixels"])
def test_on_cuda_fused_kernel_topk_equals_numba(block, chunk):
    """The kernel compiled for the GPU against numba on every interpreter case, the hard cases and
    a 20k-Gaussian scene with full top-40 lists (the eviction guard, the fill and the chunks at scale)."""
    from drsplat.raster_torch import bin_gaussians_torch, project_gaussians_fused
    from drsplat.raster_triton import composite_topk_triton

    cases = [make() for make in CASES.values()] + list(hard_cases()) + [random_case(9, n=20000, topk=40)]
    for case in cases:
        with np.errstate(all="ignore"):
            projected = project_gaussians_fused(case.scene, case.camera, device="cuda")
            ids, weights, alpha, median = composite_topk_triton(projected, bin_gaussians_torch(projected), case.topk, with_median=True,
                                                                block=block, chunk=chunk)
            ref = rasterize(case.scene, case.camera, case.topk, with_median=True, engine="numba")
        assert_topk_equal(ids.cpu().numpy(), weights.cpu().numpy(), ref.ids, ref.weights)
        np.testing.assert_allclose(alpha.cpu().numpy(), ref.alpha, rtol=1e-5, atol=1e-7, err_msg=case.name)
        np.testing.assert_array_equal(median.cpu().numpy(), ref.median_ids, err_msg=case.name)


@pytest.mark.parametrize("launch, problem", [({"chunk": 3}, "list entries per step 3"), ({"block": 24}, "pixels per program 24"),
                                             ({"num_warps": 3}, "warps per program 3"), ({"chunk": 4096}, "up to 1024")])
def test_bad_launch_shapes_are_named_before_any_launch(launch, problem):
    """A launch Triton cannot compile (a chunk or warp count that is no power of two, pixels that do
    not divide a tile) is one ValueError naming it, not an error from inside Triton's compiler."""
    from drsplat.raster_torch import bin_gaussians_torch, project_gaussians_torch
    from drsplat.raster_triton import composite_topk_triton

    case = random_case(0, n=20, topk=3)
    projected = project_gaussians_torch(case.scene, case.camera)
    with pytest.raises(ValueError, match=problem):
        composite_topk_triton(projected, bin_gaussians_torch(projected), 3, **launch)


def test_fused_kernel_is_refused_on_the_cpu():
    """Outside the interpreter the kernel compiles for CUDA only: one sentence saying so."""
    case = random_case(0, n=20, topk=3)
    with pytest.raises(DrsplatError, match="runs on CUDA devices only"):
        triton_op_kernel(case)


@pytest.mark.parametrize("ones", [False, True], ids=["scalars", "scalars equal to 1 (Triton passes them as constants)"])
@pytest.mark.parametrize("chunk, entry", [(None, "_composite_topk_chunked_source"), (0, "_composite_topk_source")])
def test_fused_kernel_compiles_to_ptx_for_an_h100(chunk, entry, ones):
    """Triton's typed compiler (stricter than the interpreter, and the one that refuses some layouts
    inside loops) accepts the sources: PTX for sm_90, no GPU needed."""
    from drsplat.raster_triton import CUDA_CHUNK, compile_ptx

    ptx = compiled_ptx(compile_ptx, 90, chunk=CUDA_CHUNK if chunk is None else chunk, ones=ones)
    assert ".target sm_90" in ptx and f".entry {entry}" in ptx


@pytest.mark.parametrize("ones", [False, True], ids=["scalars", "scalars equal to 1 (Triton passes them as constants)"])
def test_fused_projection_compiles_to_ptx_without_fma(ones):
    """The projection kernel compiles in Triton's typed mode for sm_90, with IEEE float64 division and
    square roots and no fused multiply-adds (they would round differently from numba's)."""
    from drsplat.raster_triton import compile_project_ptx

    ptx = compiled_ptx(compile_project_ptx, 90, ones=ones)
    assert ".entry _project_source" in ptx and "div.rn.f64" in ptx and "sqrt.rn.f64" in ptx
    assert "fma" not in ptx
