"""A `-reject` mode's in-front test as one Triton kernel: `device_sums.front_flags_torch` fused.

The torch form gathers each slot's Gaussian (6 precisions, 3 means, reach) as [H·W, k] float64
tensors and runs ~40 elementwise ops over them: on an H100, ~50 gathers of ~175 µs and as many
products per flowers view (640x480, k = 40, 12 M slots); with this kernel the view's gathers went
from 9.5 to 1.7 ms and its device time from 32.6 to 18.5 ms (vote-reject, 2026-11-27). It reads each
slot's Gaussian once and keeps the arithmetic in registers: the same float64 operations in the
same order, FMA contraction off, so the same bits (tests/test_front_triton.py runs it in Triton's
interpreter against the torch form on the CPU).
"""

from __future__ import annotations

import numpy as np
import torch

from drsplat.cameras import Camera
from drsplat.registration.aggregate import FRONT_REACH_SHARE
from drsplat.raster_triton import kernel_ptx, require_cuda, strict_launch, triton_kernel

try:  # triton comes with torch's CUDA builds
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - depends on the torch build
    triton = None
    tl = None

BLOCK = 2  # pixels per program (x the k slots rounded up to a power of two): 62 registers a thread at k = 40


def _ray_depth_source(g, live, dx, dy, dz, ox, oy, oz, r20, r21, r22, tz, means_ptr, prec_ptr, reach_ptr):
    """(t*, reach) of Gaussians g on the rays o + t·d (`aggregate._ray_depth`; math in
    `aggregate.ray_depths_reference`), in `ray_depths_torch`'s order of operations:

        pd = Σ⁻¹ d, zc = (R m)_z + t_z, den = dᵀ pd, t = pdᵀ (m - o) / den,
        t* = clamp(t, zc - reach, zc + reach) where den > 0, else zc (NaN stays NaN)

    reach is returned for the in-front test's second limit, so a slot's ten values are each read once."""
    p0 = tl.load(prec_ptr + 6 * g, mask=live, other=0.0)
    p1 = tl.load(prec_ptr + 6 * g + 1, mask=live, other=0.0)
    p2 = tl.load(prec_ptr + 6 * g + 2, mask=live, other=0.0)
    p3 = tl.load(prec_ptr + 6 * g + 3, mask=live, other=0.0)
    p4 = tl.load(prec_ptr + 6 * g + 4, mask=live, other=0.0)
    p5 = tl.load(prec_ptr + 6 * g + 5, mask=live, other=0.0)
    pdx = p0 * dx + p1 * dy + p2 * dz
    pdy = p1 * dx + p3 * dy + p4 * dz
    pdz = p2 * dx + p4 * dy + p5 * dz
    mx = tl.load(means_ptr + 3 * g, mask=live, other=0.0)
    my = tl.load(means_ptr + 3 * g + 1, mask=live, other=0.0)
    mz = tl.load(means_ptr + 3 * g + 2, mask=live, other=0.0)
    zc = r20 * mx + r21 * my + r22 * mz + tz
    den = pdx * dx + pdy * dy + pdz * dz
    t = (pdx * (mx - ox) + pdy * (my - oy) + pdz * (mz - oz)) / den
    reach = tl.load(reach_ptr + g, mask=live, other=0.0)
    nearest = tl.maximum(t, zc - reach, propagate_nan=tl.PropagateNan.ALL)
    return tl.where(den > 0.0, tl.minimum(nearest, zc + reach, propagate_nan=tl.PropagateNan.ALL), zc), reach


def _front_flags_source(ids_ptr, median_ptr, means_ptr, prec_ptr, reach_ptr, camera_ptr, flags_ptr, n_pixels, width, k,
                        BLOCK: tl.constexpr, KP: tl.constexpr):  # fmt: skip
    """Program b: pixels b·BLOCK .. +BLOCK. flags [P, k] int8 = slot (p, s) holds a Gaussian whose
    t* on the pixel's ray is < (1 - τ)·D(p) and < D(p) - κ·s (`aggregate.in_front_reference`), D the
    median Gaussian's t* (+inf without one)."""
    r00, r01, r02 = tl.load(camera_ptr), tl.load(camera_ptr + 1), tl.load(camera_ptr + 2)
    r10, r11, r12 = tl.load(camera_ptr + 3), tl.load(camera_ptr + 4), tl.load(camera_ptr + 5)
    r20, r21, r22 = tl.load(camera_ptr + 6), tl.load(camera_ptr + 7), tl.load(camera_ptr + 8)
    ox, oy, oz, tz = tl.load(camera_ptr + 9), tl.load(camera_ptr + 10), tl.load(camera_ptr + 11), tl.load(camera_ptr + 12)
    fx, fy, cx, cy = tl.load(camera_ptr + 13), tl.load(camera_ptr + 14), tl.load(camera_ptr + 15), tl.load(camera_ptr + 16)
    keep = tl.load(camera_ptr + 17)  # 1 - τ
    share = tl.load(camera_ptr + 18)  # κ / 3 (aggregate.FRONT_REACH_SHARE)
    pix = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    live = pix < n_pixels
    rx = ((pix % width).to(tl.float64) + 0.5 - cx) / fx
    ry = ((pix // width).to(tl.float64) + 0.5 - cy) / fy
    dx = r00 * rx + r10 * ry + r20  # d = Rᵀ (rx, ry, 1)
    dy = r01 * rx + r11 * ry + r21
    dz = r02 * rx + r12 * ry + r22
    med = tl.load(median_ptr + pix, mask=live, other=-1).to(tl.int64)
    has = med >= 0
    surface, _ = _ray_depth(tl.maximum(med, 0), has, dx, dy, dz, ox, oy, oz, r20, r21, r22, tz, means_ptr, prec_ptr, reach_ptr)
    surface = tl.where(has, surface, float("inf"))
    limit = keep * surface
    slots = tl.arange(0, KP)
    at = pix[:, None] * k + slots[None, :]
    inside = live[:, None] & (slots < k)[None, :]
    g = tl.load(ids_ptr + at, mask=inside, other=-1).to(tl.int64)
    some = g >= 0
    depth, reach = _ray_depth(tl.maximum(g, 0), some, dx[:, None], dy[:, None], dz[:, None], ox, oy, oz, r20, r21, r22, tz, means_ptr,
                              prec_ptr, reach_ptr)  # fmt: skip
    beyond = surface[:, None] - share * reach
    tl.store(flags_ptr + at, (some & (depth < limit[:, None]) & (depth < beyond)).to(tl.int8), mask=inside)


if triton is not None:  # a kernel's helper is itself a Triton function
    _ray_depth = triton.jit(_ray_depth_source)


def front_flags_triton(means: torch.Tensor, precisions: torch.Tensor, reach: torch.Tensor, camera: Camera, ids: torch.Tensor,
                       median_ids: torch.Tensor, tolerance: float) -> torch.Tensor:
    """`device_sums.front_flags_torch` in one launch: [H·W, k] bool, slot (p, s) in front of the
    pixel's surface. means [N, 3], precisions [N, 6], reach [N] float64 (the scene's DeviceRays);
    ids [H, W, k], median_ids [H, W] int32, on a CUDA device (or the CPU under the interpreter)."""
    h, w, k = ids.shape
    dev = ids.device
    require_cuda(dev, "the fused in-front kernel")
    rot, trans = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64)
    values = [*rot.reshape(-1), *camera.ray_origin(), trans[2], camera.fx, camera.fy, camera.cx, camera.cy, 1.0 - tolerance,
              FRONT_REACH_SHARE]
    params = torch.tensor([float(v) for v in values], dtype=torch.float64)
    params = params.pin_memory().to(dev, non_blocking=True) if dev.type == "cuda" else params
    flags = torch.empty((h * w, k), dtype=torch.int8, device=dev)
    n_pixels = h * w
    if n_pixels == 0 or k == 0:
        return flags.view(torch.bool)
    kp = 1 << max(0, k - 1).bit_length()
    launch = strict_launch()
    triton_kernel(_front_flags_source)[(triton.cdiv(n_pixels, BLOCK),)](
        ids.contiguous(), median_ids.contiguous(), means.contiguous(), precisions.contiguous(), reach.contiguous(), params, flags,
        n_pixels, w, k, BLOCK=BLOCK, KP=kp, **launch,
    )  # fmt: skip
    return flags.view(torch.bool)


def compile_front_ptx(capability: int = 90, k: int = 40, ones: bool = False) -> str:
    """The kernel compiled to PTX for sm_`capability` without a GPU (`raster_triton.kernel_ptx`), FMA contraction off as launched."""
    pointers = {"ids_ptr": "*i32", "median_ptr": "*i32", "means_ptr": "*fp64", "prec_ptr": "*fp64", "reach_ptr": "*fp64", "camera_ptr": "*fp64",
                "flags_ptr": "*i8", "n_pixels": "i32", "width": "i32", "k": "i32"}
    return kernel_ptx(_front_flags_source, pointers, {"BLOCK": BLOCK, "KP": 1 << max(0, k - 1).bit_length()}, capability, ones, enable_fp_fusion=False)
