"""The torch engine's top-k rasterizer as one torch op, `drsplat::render_topk`, with a kernel per device.

    render_topk(means [N, 3] f64, covariances [N, 3, 3] f64, opacities [N] f32, usable [N] bool,
                camera [16] (R row-major, t, fx, fy, cx, cy), width, height, near, tile_size, topk,
                with_median, capacity, ranked)
      -> ids [H, W, k] int32, weights [H, W, k] f32, alpha [H, W] f32, median [H, W] int32 ([0, 0]
         without with_median), tile_entries, num_nonfinite, num_behind (0-d int64)

The same rules as every engine (drsplat.raster's module docstring): EWA projection, getRect tiles,
front-to-back compositing, each pixel's top-k by w = T·α, ranked by weight (ranked=False: the
same entries in no particular order, padding still last, where the kernel can skip the sort:
registration sums a pixel's slots whatever their order; the CUDA kernel always ranks).

Kernels:
- cpu: the numba kernels (`drsplat.raster.project_gaussians`, `bin_tiles`, `composite_topk`,
  ranked), on the tensors' memory (no copy). The tile lists are sized exactly on the host, which
  costs no synchronisation there, so `capacity` is not needed (tile_entries still says how many
  entries the view needed).
- cuda: the fused Triton projection and compositing (drsplat.raster_triton) around the torch
  tile lists, sized to `capacity` entries without reading the device (capacity < 0: exactly, one
  read): `raster_torch.render_topk_triton`, registered by drsplat.raster_torch, which owns the
  tile lists (the torch engine imports it before it calls the op).

Why an op: a torch engine run is then the same few dispatcher calls on either device (the
per-view count `drsplat bench register --engine torch` prints), and on a CPU it runs at the numba
engine's speed instead of the dense torch compositor's (~20x slower; that compositor,
`raster_torch.composite_torch`, stays as the torch reference the tests compare with). Both kernels
give numba's lists (tests/test_raster_ops.py; the Triton one in the interpreter,
tests/test_raster_triton.py).
"""

from __future__ import annotations

import numpy as np
import torch

from drsplat import raster
from drsplat.cameras import Camera

CAMERA_VALUES = 16  # R (9, row-major), t (3), fx, fy, cx, cy


def host_array(tensor: torch.Tensor) -> np.ndarray:
    """A CPU tensor's memory as a numpy array (shared, writable), through DLPack: no copy and no
    dispatcher call, where `Tensor.numpy()` inside an op's kernel makes four (detach, to,
    resolve_conj, resolve_neg: views, which a per-view op count would otherwise carry)."""
    return np.from_dlpack(tensor.detach() if tensor.requires_grad else tensor)


def host_tensor(array: np.ndarray) -> torch.Tensor:
    """A numpy array as a CPU tensor sharing its memory (DLPack: no dispatcher call, where
    `torch.from_numpy` makes one)."""
    return torch.from_dlpack(array)


def host_scene(means: torch.Tensor, covariances: torch.Tensor, opacities: torch.Tensor, usable: torch.Tensor) -> raster.PreparedScene:
    """The numba kernels' PreparedScene on CPU tensors' memory (no SH; `finite` = usable [N] bool)."""
    usable_np = np.ascontiguousarray(host_array(usable))
    return raster.PreparedScene(means=np.ascontiguousarray(host_array(means)), covariances=np.ascontiguousarray(host_array(covariances)),
                                opacities=np.ascontiguousarray(host_array(opacities)), sh=np.zeros((usable_np.size, 0, 3), np.float32),
                                finite=usable_np)


def camera_values(camera: Camera) -> list[float]:
    """The op's `camera` argument: [R row-major (9), t (3), fx, fy, cx, cy] as floats."""
    rot, trans = np.asarray(camera.R, np.float64).reshape(-1), np.asarray(camera.t, np.float64).reshape(-1)
    return [float(v) for v in (*rot, *trans, camera.fx, camera.fy, camera.cx, camera.cy)]


def camera_from_values(values: list[float], width: int, height: int) -> Camera:
    """The Camera that `camera_values` flattened (no image, no name)."""
    if len(values) != CAMERA_VALUES:
        raise ValueError(f"render_topk's camera holds {CAMERA_VALUES} values (R, t, fx, fy, cx, cy), got {len(values)}")
    v = np.asarray(values, np.float64)
    if not np.isfinite(v).all() or not (width >= 1 and height >= 1):
        # a camera loaded from a file passed cameras.validate_camera; this guards the op's own arguments
        raise ValueError(f"render_topk's camera must have finite values and an image of at least 1x1 pixels, got {int((~np.isfinite(v)).sum())} "
                         f"non-finite values and {width}x{height}")
    return Camera(R=v[:9].reshape(3, 3), t=v[9:12].copy(), fx=v[12], fy=v[13], cx=v[14], cy=v[15], width=int(width), height=int(height))


@torch.library.custom_op("drsplat::render_topk", mutates_args=(), device_types="cpu")
def render_topk(means: torch.Tensor, covariances: torch.Tensor, opacities: torch.Tensor, usable: torch.Tensor, camera: list[float], width: int,
                height: int, near: float, tile_size: int, topk: int, with_median: bool, capacity: int,
                ranked: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """See the module docstring. This body is the CPU kernel (numba); drsplat.raster_torch registers the CUDA one."""
    prep = host_scene(means, covariances, opacities, usable)
    projected = raster.project_gaussians(prep, camera_from_values(camera, width, height), near, tile_size=tile_size)
    out = raster.render_topk(projected, topk, with_median=with_median, ranked=ranked)
    median = out.median_ids if with_median else np.zeros((0, 0), np.int32)
    counts = [out.tile_entries, projected.num_nonfinite - prep.num_nonfinite, projected.num_behind]  # the kernel's own non-finite count
    return tuple(host_tensor(a) for a in (out.ids, out.weights, out.alpha, median, *(np.array(c, np.int64) for c in counts)))


@render_topk.register_fake
def _render_topk_fake(means, covariances, opacities, usable, camera, width, height, near, tile_size, topk, with_median, capacity, ranked):
    def new(shape, dtype):
        return means.new_empty(shape, dtype=dtype)

    scalar = [new((), torch.int64) for _ in range(3)]
    return (new((height, width, topk), torch.int32), new((height, width, topk), torch.float32), new((height, width), torch.float32),
            new((height, width) if with_median else (0, 0), torch.int32), *scalar)
