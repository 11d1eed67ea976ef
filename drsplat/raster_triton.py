"""Fused per-tile top-k compositing in Triton: the torch engine's compositing on a CUDA device.

Projection, tile binning and the depth sort stay in torch on the device (drsplat.raster_torch:
`project_gaussians_torch`, `bin_gaussians_torch`); one Triton program then composites a block of
BLOCK pixels of one 16x16 tile, walking the tile's depth-sorted list front to back and keeping
each pixel's top-k in registers (local memory when they spill). The rules are the numba kernel's
(drsplat._raster_kernels.composite_tiles), in float64 like it:

    d = mean2d - pixel centre, power = -½(a·dx² + c·dy²) - b·dx·dy
    α = min(0.99, o·exp(power)); the entry is skipped when power > 0 or α < 1/255
    the pixel stops (and the entry does not count) when T·(1 - α) < 1e-4
    otherwise w = T·α, T ← T·(1 - α)

Top-k without sorting inside the loop: each pixel holds k unsorted slots (weight, list position);
a newcomer replaces the slot with the smallest weight — the latest-arrived among equal smallest —
when its weight is strictly larger. So the slots end up holding exactly the first k entries of a
stable sort of all the pixel's contributions by descending weight (a later equal weight never
displaces an earlier one), which is what the numba kernel keeps; at the end the kernel sorts
each pixel's k slots by (float32 weight descending, list position ascending) with tl.sort, and
`_finish` turns positions into Gaussian ids.

The kernel source is one function; under TRITON_INTERPRET=1 (read by triton when it is imported,
so the tests set it in a subprocess) Triton runs it with numpy on the CPU, which is how the tests
check the same source against numba (tests/test_raster_triton.py). Otherwise it is compiled for
CUDA and refused on any other device.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from drsplat import _raster_kernels as kernels
from drsplat.defaults import DEFAULT_TOPK
from drsplat.errors import DrsplatError
from drsplat.raster import _check_args, clamp_limits, tile_grid

try:  # triton comes with torch's CUDA builds; without it only the pure-torch compositing exists
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - depends on the torch build
    triton = None
    tl = None

# pixels and warps per program on a GPU: on an H100, flowers 640x480, top-40, this kernel composites a
# view in 18.8 ms at 16 x 1, 22.3 at 16 x 2, 22.5 at 32 x 4, 23.6 at 32 x 2 (`drsplat bench kernel`;
# the sweeps of its earlier versions, up to 256 pixels, are in docs/gpu.md)
CUDA_BLOCK = 16
CUDA_WARPS = 1
INTERPRET_BLOCK = 256  # a whole tile per program in the interpreter (fewer, larger numpy steps)


def available() -> bool:
    """Whether Triton is importable (the fused kernel can run at all)."""
    return triton is not None


def _composite_topk_source(
    offsets_ptr, counts_ptr, list_ptr, means_ptr, conics_ptr, opacities_ptr,
    out_key_ptr, out_trans_ptr, out_med_ptr,
    width, height, n_tiles_x, topk,
    TILE: tl.constexpr, BLOCK: tl.constexpr, KP: tl.constexpr,
    ALPHA_MIN: tl.constexpr, ALPHA_MAX: tl.constexpr, T_MIN: tl.constexpr, MEDIAN_T: tl.constexpr,
):  # fmt: skip
    """Program (tile, block): pixels block·BLOCK .. +BLOCK of the tile (row-major inside the tile).

    Writes out_key [n_tiles, TILE², KP] int64, each pixel's slots sorted descending by the key

        (bits of float32(w)) · 2³¹ + (2³¹ - 1 - list position)     (-1: no Gaussian)

    (a positive float's bits order as the float does: weight descending, then list position
    ascending), out_trans [n_tiles, TILE²] final T and out_med [n_tiles, TILE²] the list position
    of the median Gaussian (-1: none). KP is topk rounded up to a power of two (tl.sort's need).

    The eviction (a min / max over the KP slots of every pixel) runs only for an entry that beats
    some pixel's smallest slot, which each pixel keeps (min_w): once the slots are full, the
    weights T·α mostly fall along the list and few entries do (on an H100, flowers: 88.6 -> 32.7 ms
    a view at 64 pixels x 4 warps). An entry that no pixel of the block takes skips the rest of
    its step.
    """
    tile = tl.program_id(0)
    local = tl.program_id(1) * BLOCK + tl.arange(0, BLOCK)
    px = (tile % n_tiles_x) * TILE + local % TILE
    py = (tile // n_tiles_x) * TILE + local // TILE
    cx = px.to(tl.float64) + 0.5
    cy = py.to(tl.float64) + 0.5
    done = (px >= width) | (py >= height)
    n_active = tl.sum((~done).to(tl.int32), axis=0)
    start = tl.load(offsets_ptr + tile)
    count = tl.load(counts_ptr + tile)
    slots = tl.arange(0, KP)
    real = (slots < topk)[None, :] & (local >= 0)[:, None]  # [BLOCK, KP]
    buf_w = tl.where(real, -1.0, 2.0).to(tl.float64)  # empty: -1; padding: 2 > any weight, never evicted
    buf_pos = (-1 - slots[None, :] + tl.zeros([BLOCK, KP], tl.int32)).to(tl.int32)  # empty slots: distinct negatives
    min_w = tl.min(buf_w, axis=1)
    trans = tl.full([BLOCK], 1.0, tl.float64)
    med = tl.full([BLOCK], -1, tl.int32)
    j = tl.zeros([], dtype=tl.int32)  # a typed loop-carried counter (list positions are int32)
    while (j < count) & (n_active > 0):
        g = tl.load(list_ptr + start + j)
        u = tl.load(means_ptr + 2 * g)
        v = tl.load(means_ptr + 2 * g + 1)
        ca = tl.load(conics_ptr + 3 * g)
        cb = tl.load(conics_ptr + 3 * g + 1)
        cc = tl.load(conics_ptr + 3 * g + 2)
        o = tl.load(opacities_ptr + g).to(tl.float64)
        dx = u - cx
        dy = v - cy
        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
        alpha = tl.minimum(o * tl.exp(tl.minimum(power, 0.0)), ALPHA_MAX)
        hit = (~done) & (power <= 0.0) & (alpha >= ALPHA_MIN)
        if tl.sum(hit.to(tl.int32), axis=0) > 0:
            test_t = trans * (1.0 - alpha)
            stop = hit & (test_t < T_MIN)
            ok = hit & (test_t >= T_MIN)
            w = alpha * trans
            med = tl.where(ok & (test_t <= MEDIAN_T) & (trans > MEDIAN_T), j, med)
            # evict the smallest slot, the latest-arrived among equal smallest, if w beats it strictly
            better = ok & (w > min_w)
            if tl.sum(better.to(tl.int32), axis=0) > 0:
                tie = buf_w == min_w[:, None]
                last = tl.max(tl.where(tie, buf_pos, -KP - 1), axis=1)
                replace = tie & (buf_pos == last[:, None]) & better[:, None]
                buf_w = tl.where(replace, w[:, None], buf_w)
                buf_pos = tl.where(replace, j, buf_pos)
                min_w = tl.min(buf_w, axis=1)
            trans = tl.where(ok, test_t, trans)
            done = done | stop
            n_active -= tl.sum(stop.to(tl.int32), axis=0)
        j += 1
    base = tile * TILE * TILE + local
    tl.store(out_trans_ptr + base, trans)
    tl.store(out_med_ptr + base, med)
    filled = real & (buf_w > 0.0)
    bits = buf_w.to(tl.float32).to(tl.int32, bitcast=True).to(tl.int64)
    key = tl.where(filled, (bits << 31) | (0x7FFFFFFF - buf_pos.to(tl.int64)), -1)
    tl.store(out_key_ptr + base.to(tl.int64)[:, None] * KP + slots[None, :], tl.sort(key, dim=1, descending=True))


def _project_source(
    means_ptr, cov_ptr, opacities_ptr, usable_ptr,
    out_means_ptr, out_conics_ptr, out_depths_ptr, out_radii_ptr, out_rects_ptr, out_status_ptr, camera_ptr, n,
    TILE: tl.constexpr, BLOCK: tl.constexpr, BLUR: tl.constexpr, ALPHA_MIN: tl.constexpr,
    VALID: tl.constexpr, BEHIND: tl.constexpr, NONFINITE: tl.constexpr, CULLED: tl.constexpr,
):  # fmt: skip
    """Program b: Gaussians b·BLOCK .. +BLOCK, drsplat._raster_kernels.project_points's EWA math in
    float64 with the torch engine's order of operations (drsplat.raster_torch._screen_space).

    Writes depths [N] float32 (camera z; 0 where not usable) and status [N] int8 (the numba
    kernel's VALID, BEHIND the near plane, NONFINITE projection or CULLED), and for every Gaussian means2d
    [N, 2], conics [N, 3], radii [N] float64 and tile rectangles [N, 4] int64 (getRect), zeros
    where not valid.
    """
    # the camera as float64 values in memory: a Python float argument would be typed fp32
    r00, r01, r02 = tl.load(camera_ptr), tl.load(camera_ptr + 1), tl.load(camera_ptr + 2)
    r10, r11, r12 = tl.load(camera_ptr + 3), tl.load(camera_ptr + 4), tl.load(camera_ptr + 5)
    r20, r21, r22 = tl.load(camera_ptr + 6), tl.load(camera_ptr + 7), tl.load(camera_ptr + 8)
    t0, t1, t2 = tl.load(camera_ptr + 9), tl.load(camera_ptr + 10), tl.load(camera_ptr + 11)
    fx, fy, cx, cy = tl.load(camera_ptr + 12), tl.load(camera_ptr + 13), tl.load(camera_ptr + 14), tl.load(camera_ptr + 15)
    lim_x_pos, lim_x_neg = tl.load(camera_ptr + 16), tl.load(camera_ptr + 17)
    lim_y_pos, lim_y_neg = tl.load(camera_ptr + 18), tl.load(camera_ptr + 19)
    near, grid_x, grid_y = tl.load(camera_ptr + 20), tl.load(camera_ptr + 21), tl.load(camera_ptr + 22)
    g = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)  # int64: 9·g passes 2^31 past 238 M Gaussians
    live = g < n
    mx = tl.load(means_ptr + 3 * g, mask=live, other=0.0)
    my = tl.load(means_ptr + 3 * g + 1, mask=live, other=0.0)
    mz = tl.load(means_ptr + 3 * g + 2, mask=live, other=0.0)
    usable = tl.load(usable_ptr + g, mask=live, other=0) != 0
    px = r00 * mx + r01 * my + r02 * mz + t0
    py = r10 * mx + r11 * my + r12 * mz + t1
    pz = r20 * mx + r21 * my + r22 * mz + t2
    in_front = usable & (pz >= near)
    considered = in_front & (tl.load(opacities_ptr + g, mask=live, other=0.0).to(tl.float64) >= ALPHA_MIN)
    tx = pz * tl.minimum(tl.maximum(px / pz, -lim_x_neg), lim_x_pos)
    ty = pz * tl.minimum(tl.maximum(py / pz, -lim_y_neg), lim_y_pos)
    jx = fx / pz
    jy = fy / pz
    jxz = -fx * tx / (pz * pz)
    jyz = -fy * ty / (pz * pz)
    a00 = jx * r00 + jxz * r20
    a01 = jx * r01 + jxz * r21
    a02 = jx * r02 + jxz * r22
    a10 = jy * r10 + jyz * r20
    a11 = jy * r11 + jyz * r21
    a12 = jy * r12 + jyz * r22
    c00 = tl.load(cov_ptr + 9 * g, mask=live, other=0.0)
    c01 = tl.load(cov_ptr + 9 * g + 1, mask=live, other=0.0)
    c02 = tl.load(cov_ptr + 9 * g + 2, mask=live, other=0.0)
    c10 = tl.load(cov_ptr + 9 * g + 3, mask=live, other=0.0)
    c11 = tl.load(cov_ptr + 9 * g + 4, mask=live, other=0.0)
    c12 = tl.load(cov_ptr + 9 * g + 5, mask=live, other=0.0)
    c20 = tl.load(cov_ptr + 9 * g + 6, mask=live, other=0.0)
    c21 = tl.load(cov_ptr + 9 * g + 7, mask=live, other=0.0)
    c22 = tl.load(cov_ptr + 9 * g + 8, mask=live, other=0.0)
    s00 = c00 * a00 + c01 * a01 + c02 * a02
    s01 = c10 * a00 + c11 * a01 + c12 * a02
    s02 = c20 * a00 + c21 * a01 + c22 * a02
    s10 = c00 * a10 + c01 * a11 + c02 * a12
    s11 = c10 * a10 + c11 * a11 + c12 * a12
    s12 = c20 * a10 + c21 * a11 + c22 * a12
    a = a00 * s00 + a01 * s01 + a02 * s02 + BLUR
    b = a10 * s00 + a11 * s01 + a12 * s02
    c = a10 * s10 + a11 * s11 + a12 * s12 + BLUR
    u = fx * px / pz + cx
    v = fy * py / pz + cy
    det = a * c - b * b
    mid = 0.5 * (a + c)
    radius = tl.ceil(3.0 * tl.sqrt(mid + tl.sqrt(tl.maximum(mid * mid - det, 0.1))))
    # x - x is 0 exactly when x is finite (NaN for ±inf and NaN)
    finite = (a - a == 0.0) & (b - b == 0.0) & (c - c == 0.0) & (u - u == 0.0) & (v - v == 0.0) & (radius - radius == 0.0)
    x0 = tl.floor((u - 0.5 - radius) / TILE)
    y0 = tl.floor((v - 0.5 - radius) / TILE)
    x1 = tl.floor((u - 0.5 + radius + TILE - 1) / TILE)
    y1 = tl.floor((v - 0.5 + radius + TILE - 1) / TILE)
    x0 = tl.minimum(tl.maximum(tl.where(x0 == x0, x0, 0.0), 0.0), grid_x)
    y0 = tl.minimum(tl.maximum(tl.where(y0 == y0, y0, 0.0), 0.0), grid_y)
    x1 = tl.minimum(tl.maximum(tl.where(x1 == x1, x1, 0.0), 0.0), grid_x)
    y1 = tl.minimum(tl.maximum(tl.where(y1 == y1, y1, 0.0), 0.0), grid_y)
    valid = considered & finite & (det > 0.0) & (x1 > x0) & (y1 > y0)
    status = tl.where(valid, VALID, tl.where(usable & ~in_front, BEHIND, tl.where(considered & ~finite, NONFINITE, CULLED))).to(tl.int8)
    tl.store(out_status_ptr + g, status, mask=live)
    tl.store(out_depths_ptr + g, tl.where(usable, pz, 0.0).to(tl.float32), mask=live)
    tl.store(out_means_ptr + 2 * g, tl.where(valid, u, 0.0), mask=live)
    tl.store(out_means_ptr + 2 * g + 1, tl.where(valid, v, 0.0), mask=live)
    tl.store(out_conics_ptr + 3 * g, tl.where(valid, c / det, 0.0), mask=live)
    tl.store(out_conics_ptr + 3 * g + 1, tl.where(valid, -b / det, 0.0), mask=live)
    tl.store(out_conics_ptr + 3 * g + 2, tl.where(valid, a / det, 0.0), mask=live)
    tl.store(out_radii_ptr + g, tl.where(valid, radius, 0.0), mask=live)
    tl.store(out_rects_ptr + 4 * g, tl.where(valid, x0, 0.0).to(tl.int64), mask=live)
    tl.store(out_rects_ptr + 4 * g + 1, tl.where(valid, y0, 0.0).to(tl.int64), mask=live)
    tl.store(out_rects_ptr + 4 * g + 2, tl.where(valid, x1, 0.0).to(tl.int64), mask=live)
    tl.store(out_rects_ptr + 4 * g + 3, tl.where(valid, y1, 0.0).to(tl.int64), mask=live)


def interpreting() -> bool:
    """Whether Triton runs kernels in its CPU interpreter (TRITON_INTERPRET=1, read when triton is imported)."""
    return triton is not None and bool(triton.knobs.runtime.interpret)


@functools.cache
def _kernel(source=_composite_topk_source):
    """A kernel (default: the top-k compositing): compiled for CUDA, or interpreted under
    TRITON_INTERPRET=1 (triton.jit decides)."""
    if triton is None:
        raise DrsplatError("the fused top-k kernel needs triton (it comes with torch's CUDA builds: pip install triton)")
    return triton.jit(source)


def _check_device(dev: torch.device) -> None:
    if dev.type != "cuda" and not interpreting():
        raise DrsplatError(f"the fused Triton top-k kernel runs on CUDA devices only, not on {dev.type!r}; use the torch compositing there")


PROJECT_BLOCK = 256  # Gaussians per projection program


def _project_constants() -> dict:
    """The numba kernels' constants the projection kernel takes as constexprs (one definition: drsplat._raster_kernels)."""
    return {"BLUR": kernels.BLUR, "ALPHA_MIN": kernels.ALPHA_MIN, "VALID": kernels.VALID, "BEHIND": kernels.BEHIND,
            "NONFINITE": kernels.NONFINITE, "CULLED": kernels.CULLED}


def project_triton(means: torch.Tensor, covariances: torch.Tensor, opacities: torch.Tensor, usable: torch.Tensor, camera, near: float,
                   tile_size: int) -> tuple[torch.Tensor, ...]:
    """Project every Gaussian in one kernel launch (`_project_source`): the torch engine's
    `project_gaussians_torch` (186 ops per view) fused, the same float64 math in the same order.

    means: [N, 3] float64, covariances: [N, 3, 3] float64, opacities: [N] float32, usable: [N]
    bool, on a CUDA device (or the CPU under the interpreter). Returns (means2d [N, 2], conics
    [N, 3], depths [N] float32, radii [N] float64, tile_rects [N, 4] int64, status [N] int8:
    drsplat._raster_kernels' VALID / BEHIND / NONFINITE / CULLED). FMA contraction is off, so the
    products round as the numba and torch engines' do.
    """
    dev = means.device
    _check_device(dev)
    n = int(means.shape[0])
    f64 = {"dtype": torch.float64, "device": dev}
    out = (torch.empty((n, 2), **f64), torch.empty((n, 3), **f64), torch.empty(n, dtype=torch.float32, device=dev), torch.empty(n, **f64),
           torch.empty((n, 4), dtype=torch.int64, device=dev), torch.empty(n, dtype=torch.int8, device=dev))
    if n == 0:
        return out
    rot = [float(x) for x in np.asarray(camera.R, np.float64).reshape(-1)]
    t = [float(x) for x in np.asarray(camera.t, np.float64)]
    intrinsics = (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy))
    grids = [float(g) for g in tile_grid(camera.width, camera.height, tile_size)]
    values = torch.tensor([*rot, *t, *intrinsics, *clamp_limits(camera), float(near), *grids], dtype=torch.float64)
    launch = {} if interpreting() else {"enable_fp_fusion": False}
    _kernel(_project_source)[(triton.cdiv(n, PROJECT_BLOCK),)](
        means.contiguous(), covariances.contiguous(), opacities.contiguous(), usable.to(torch.int8), *out,
        values.pin_memory().to(dev, non_blocking=True) if dev.type == "cuda" else values, n,
        TILE=tile_size, BLOCK=PROJECT_BLOCK, **_project_constants(), **launch,
    )  # fmt: skip
    return out


def composite_topk_triton(projected, bins, topk: int = DEFAULT_TOPK, *, with_median: bool = False, block: int | None = None,
                          num_warps: int | None = None):
    """Top-k ids [H, W, k] int32 and weights [H, W, k] float32, alpha [H, W] float32 (and median ids [H, W] int32 or None).

    projected: a drsplat.raster_torch.TorchProjected on a CUDA device (or on the CPU under TRITON_INTERPRET=1: the tests).
    bins: the tile lists (offsets [T], counts [T], tile_list [L]) of drsplat.raster_torch.bin_gaussians_torch,
    passed in so that this module does not import its caller. block / num_warps: pixels and warps
    per program (default CUDA_BLOCK, CUDA_WARPS). The rest is one kernel launch plus `_finish`'s
    gathers (no host synchronisation).
    """

    _check_args(topk, (0.0, 0.0, 0.0))
    dev = projected.valid.device
    interpret = interpreting()
    _check_device(dev)
    ts = projected.tile_size
    p_count = ts * ts
    block = block or (INTERPRET_BLOCK if interpret else CUDA_BLOCK)
    if p_count % block:
        raise ValueError(f"block {block} must divide the {p_count} pixels of a tile")
    n_tiles_x, n_tiles_y = projected.tile_grid
    n_tiles = n_tiles_x * n_tiles_y
    offsets, counts, tile_list = bins
    if tile_list.numel() == 0:  # nothing visible: a one-entry list keeps the gathers in range (every count is 0)
        tile_list = torch.zeros(1, dtype=torch.int64, device=dev)
    kp = max(1, 1 << max(0, topk - 1).bit_length())
    out_key = torch.empty((n_tiles, p_count, kp), dtype=torch.int64, device=dev)
    out_trans = torch.empty((n_tiles, p_count), dtype=torch.float64, device=dev)
    out_med = torch.empty((n_tiles, p_count), dtype=torch.int32, device=dev)
    launch = {} if interpret else {"enable_fp_fusion": False, "num_warps": num_warps or CUDA_WARPS}
    _kernel()[(n_tiles, p_count // block)](
        offsets, counts, tile_list, projected.means2d.contiguous(), projected.conics.contiguous(), projected.opacities.contiguous(),
        out_key, out_trans, out_med, projected.width, projected.height, n_tiles_x, topk,
        TILE=ts, BLOCK=block, KP=kp, ALPHA_MIN=kernels.ALPHA_MIN, ALPHA_MAX=kernels.ALPHA_MAX, T_MIN=kernels.T_MIN, MEDIAN_T=kernels.MEDIAN_T,
        **launch,
    )  # fmt: skip
    return _finish(projected, out_key[..., :topk], out_trans, out_med if with_median else None, offsets, tile_list)


def _finish(projected, key, trans, med, offsets, tile_list):
    """Each pixel's sorted slot keys [n_tiles, P, k] (the kernel's) as Gaussian ids and float32
    weights, tiles laid out as the image (ids -1 / weights 0 in empty slots).

    The kernel orders a pixel's slots by float32 weight; numba by the float64 weight, so two slots
    whose float64 weights round to the same float32 may come in the other order, with equal output
    weights. (Sorting here instead, two stable sorts by position then weight, took 5.5 ms of a
    flowers view on an H100.)
    """
    filled = key >= 0
    pos = 0x7FFFFFFF - (key & 0x7FFFFFFF)
    first = offsets[:, None, None]
    ids = torch.where(filled, tile_list[torch.where(filled, first + pos, 0)], -1).to(torch.int32)
    weights = torch.where(filled, (key >> 31).to(torch.int32).view(torch.float32), 0.0)
    median = None
    if med is not None:
        has = med >= 0
        median = torch.where(has, tile_list[torch.where(has, offsets[:, None] + med, 0)], -1).to(torch.int32)
    ts = projected.tile_size
    n_tiles_x, n_tiles_y = projected.tile_grid
    h, w = projected.height, projected.width

    def image(t):
        rest = t.shape[2:]
        t = t.reshape(n_tiles_y, n_tiles_x, ts, ts, *rest).transpose(1, 2).reshape(n_tiles_y * ts, n_tiles_x * ts, *rest)
        return t[:h, :w].contiguous()

    return image(ids), image(weights), image((1.0 - trans).float()), None if median is None else image(median)


def compile_ptx(capability: int = 90, block: int = CUDA_BLOCK, kp: int = 64, tile: int = 16) -> str:
    """The compositing kernel compiled to PTX for CUDA compute capability `capability` (90: H100), without a GPU.

    Runs Triton's front end and NVIDIA backend stages (ttir -> ttgir -> llir -> ptx), not ptxas, so
    it checks that the source compiles in Triton's typed mode (the interpreter is looser) but says
    nothing about registers or speed. Uses Triton's backend API (checked with triton 3.8).
    """
    pointers = {"offsets_ptr": "*i64", "counts_ptr": "*i64", "list_ptr": "*i64", "means_ptr": "*fp64", "conics_ptr": "*fp64",
                "opacities_ptr": "*fp32", "out_key_ptr": "*i64", "out_trans_ptr": "*fp64", "out_med_ptr": "*i32"}
    consts = {"TILE": tile, "BLOCK": block, "KP": kp, "ALPHA_MIN": kernels.ALPHA_MIN, "ALPHA_MAX": kernels.ALPHA_MAX, "T_MIN": kernels.T_MIN,
              "MEDIAN_T": kernels.MEDIAN_T}
    return _ptx(_composite_topk_source, {**pointers, **dict.fromkeys(("width", "height", "n_tiles_x", "topk"), "i32")}, consts, capability,
                enable_fp_fusion=False)


def compile_project_ptx(capability: int = 90, tile: int = 16) -> str:
    """The projection kernel compiled to PTX (as `compile_ptx`), with FMA contraction off as launched."""
    pointers = {"means_ptr": "*fp64", "cov_ptr": "*fp64", "opacities_ptr": "*fp32", "usable_ptr": "*i8", "out_means_ptr": "*fp64",
                "out_conics_ptr": "*fp64", "out_depths_ptr": "*fp32", "out_radii_ptr": "*fp64", "out_rects_ptr": "*i64",
                "out_status_ptr": "*i8", "camera_ptr": "*fp64", "n": "i32"}
    consts = {"TILE": tile, "BLOCK": PROJECT_BLOCK, **_project_constants()}
    return _ptx(_project_source, pointers, consts, capability, enable_fp_fusion=False)


def _ptx(source, signature: dict, consts: dict, capability: int, **options) -> str:
    """PTX of one kernel source for sm_`capability` (Triton's stages up to ptx, no GPU)."""
    from triton._C.libtriton import ir  # Triton internals, only for this offline check
    from triton.backends.compiler import GPUTarget
    from triton.backends.nvidia.compiler import CUDABackend
    from triton.compiler import ASTSource

    fn = _kernel(source)
    signature = {**signature, **dict.fromkeys(consts, "constexpr")}
    ast = ASTSource(fn=fn, signature=signature, constexprs={(fn.arg_names.index(k),): v for k, v in consts.items()})
    target = GPUTarget("cuda", capability, 32)
    backend = CUDABackend(target)
    parsed = backend.parse_options(options)
    context = ir.context()
    ir.load_dialects(context)
    backend.load_dialects(context)
    module = ast.make_ir(target, parsed, backend.get_codegen_implementation(parsed), backend.get_module_map(), context)
    stages: dict = {}
    backend.add_stages(stages, parsed, ast.language)
    metadata: dict = {}
    for name in ("ttir", "ttgir", "llir", "ptx"):
        module = stages[name](module, metadata)
    return module
