"""Fused per-tile top-k compositing in Triton: the torch engine's compositing on a CUDA device.

Projection, tile binning and the depth sort stay in torch on the device (drsplat.raster_torch:
`project_gaussians_torch`, `bin_gaussians_torch`); one Triton program then composites a block of
BLOCK pixels of one 16x16 tile (by default one pixel), walking the tile's depth-sorted list front
to back, CHUNK entries per step (`_composite_topk_chunked_source`; one entry per step:
`_composite_topk_source`, the first design), and keeping each pixel's top-k in registers. The
rules are the numba kernel's
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

Each kernel source is one function (with jitted helpers); under TRITON_INTERPRET=1 (read by triton
when it is imported, so the tests set it in a subprocess) Triton runs it with numpy on the CPU, which is how the tests
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

# pixels, warps and list entries per step of a program on a GPU (chunk 0: the per-entry kernel): on an H100, flowers
# 640x480, top-40, the per-entry kernel composites a view in 18.6 ms at 16 x 1; the chunked one in 8.3 ms at 8 x 1 x 16
# and 4.8 ms at 1 x 1 x 32, with the empty slots filled through memory (`drsplat bench kernel`; docs/gpu.md)
CUDA_BLOCK = 1
CUDA_WARPS = 1
CUDA_CHUNK = 32
INTERPRET_BLOCK = 256  # a whole tile per program in the interpreter (fewer, larger numpy steps)


MAX_CHUNK = 1024  # list entries per step: a bound on the [pixels, entries] block, far past the measured best (32-64)


def launch_problem(block: int, num_warps: int, chunk: int, tile_pixels: int) -> str | None:
    """What is wrong with a compositing launch of `block` pixels, `num_warps` warps and `chunk` list
    entries per step (0: the per-entry kernel) on tiles of `tile_pixels`, or None: Triton needs
    powers of two, and a program's pixels must divide its tile's."""
    if block < 1 or tile_pixels % block:
        return f"pixels per program {block} must divide the {tile_pixels} pixels of a tile"
    if num_warps not in (1, 2, 4, 8, 16):
        return f"warps per program {num_warps} must be 1, 2, 4, 8 or 16"
    if chunk < 0 or chunk > MAX_CHUNK or chunk & (chunk - 1):
        return f"list entries per step {chunk} must be 0 (one at a time) or a power of two up to {MAX_CHUNK}"
    return None


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
    tile, local, cx, cy, done, start, count = _program_pixels(offsets_ptr, counts_ptr, width, height, n_tiles_x, TILE, BLOCK)
    n_active = tl.sum((~done).to(tl.int32), axis=0)
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


def _composite_topk_chunked_source(
    offsets_ptr, counts_ptr, list_ptr, means_ptr, conics_ptr, opacities_ptr,
    out_key_ptr, out_trans_ptr, out_med_ptr, fill_pos_ptr,
    width, height, n_tiles_x, topk,
    TILE: tl.constexpr, BLOCK: tl.constexpr, KP: tl.constexpr, CHUNK: tl.constexpr,
    ALPHA_MIN: tl.constexpr, ALPHA_MAX: tl.constexpr, T_MIN: tl.constexpr, MEDIAN_T: tl.constexpr,
):  # fmt: skip
    """`_composite_topk_source`'s program and outputs, walking the list CHUNK entries at a time
    (`_chunk_weights`: every entry's α, T and w at once) in two phases.

    Filling: while every pixel of the block has empty slots, each chunk's ok entries go to the
    next empty slots in one step: written to the pixel's out_key row (as float64 bits) and
    fill_pos row, not to registers (a gather of them into the [BLOCK, KP] slots inside the loop
    does not compile in Triton 3.6-3.8). This is what the eviction rule does with empty slots (an
    empty slot is the smallest, the empties are taken in slot order).
    Evicting: once some pixel's slots are full, the slots are read back, the chunk's remaining ok
    entries and every later chunk's that beat a pixel's smallest slot enter one at a time, in
    list order, by the per-entry kernel's eviction rule (so the slots are the same): a loop whose
    trips are the most entries any pixel of the block takes from a chunk, which once the slots are
    full is mostly none.
    """
    tile, local, cx, cy, done, start, count = _program_pixels(offsets_ptr, counts_ptr, width, height, n_tiles_x, TILE, BLOCK)
    n_active = tl.sum((~done).to(tl.int32), axis=0)
    slots = tl.arange(0, KP)
    cols = tl.arange(0, CHUNK)
    base = tile * TILE * TILE + local
    row = base.to(tl.int64)[:, None] * KP  # [BLOCK, 1]: the pixel's KP slots in out_key / fill_pos
    trans = tl.full([BLOCK], 1.0, tl.float64)
    med = tl.full([BLOCK], -1, tl.int32)
    n_filled = tl.zeros([BLOCK], tl.int32)
    take = tl.zeros([BLOCK, CHUNK], tl.int1)  # the last filling chunk's entries left for the eviction
    w = tl.zeros([BLOCK, CHUNK], tl.float64)
    j = tl.zeros([], dtype=tl.int32)  # a typed loop-carried counter (list positions are int32)
    filling = n_active > 0
    while (j < count) & filling:
        ok, w, trans, med, done = _chunk_weights(j, cols, start, count, list_ptr, means_ptr, conics_ptr, opacities_ptr, cx, cy,
                                                 trans, med, done, ALPHA_MIN, ALPHA_MAX, T_MIN, MEDIAN_T)
        n_active = tl.sum((~done).to(tl.int32), axis=0)
        rank = tl.cumsum(ok.to(tl.int32), axis=1) - 1
        fill = ok & (rank < (topk - n_filled)[:, None])
        at = row + (n_filled[:, None] + rank)
        tl.store(out_key_ptr + at, w.to(tl.int64, bitcast=True), mask=fill)
        tl.store(fill_pos_ptr + at, (j + cols)[None, :] + tl.zeros([BLOCK, CHUNK], tl.int32), mask=fill)
        n_filled += tl.sum(fill.to(tl.int32), axis=1)
        take = ok & ~fill
        j += CHUNK
        filling = (n_active > 0) & (tl.max(n_filled, axis=0) < topk)
    tl.debug_barrier()  # the filled slots, written by other threads of the program, are read back
    real = (slots < topk)[None, :] & (local >= 0)[:, None]  # [BLOCK, KP]
    stored = slots[None, :] < n_filled[:, None]
    buf_w = tl.where(real, -1.0, 2.0).to(tl.float64)  # empty: -1; padding: 2 > any weight, never evicted
    buf_w = tl.where(stored, tl.load(out_key_ptr + row + slots[None, :], mask=stored, other=0).to(tl.float64, bitcast=True), buf_w)
    buf_pos = (-1 - slots[None, :] + tl.zeros([BLOCK, KP], tl.int32)).to(tl.int32)  # empty slots: distinct negatives
    buf_pos = tl.where(stored, tl.load(fill_pos_ptr + row + slots[None, :], mask=stored, other=0), buf_pos)
    min_w = tl.min(buf_w, axis=1)
    j -= CHUNK  # the last filling chunk's leftover entries first
    take = take & (w > min_w[:, None])
    evicting = True
    while evicting:
        while tl.sum(take.to(tl.int32)) > 0:
            c = tl.min(tl.where(take, cols[None, :], CHUNK), axis=1)  # each pixel's first entry to take
            better = c < CHUNK
            w_in = tl.max(tl.where(cols[None, :] == c[:, None], w, -1.0), axis=1)
            # evict the smallest slot, the latest-arrived among equal smallest
            tie = buf_w == min_w[:, None]
            last = tl.max(tl.where(tie, buf_pos, -KP - 1), axis=1)
            replace = tie & (buf_pos == last[:, None]) & better[:, None]
            buf_w = tl.where(replace, w_in[:, None], buf_w)
            buf_pos = tl.where(replace, (j + c)[:, None], buf_pos)
            min_w = tl.min(buf_w, axis=1)
            take = take & (cols[None, :] > c[:, None]) & (w > min_w[:, None])
        j += CHUNK
        evicting = (j < count) & (n_active > 0)
        if evicting:
            ok, w, trans, med, done = _chunk_weights(j, cols, start, count, list_ptr, means_ptr, conics_ptr, opacities_ptr, cx, cy,
                                                     trans, med, done, ALPHA_MIN, ALPHA_MAX, T_MIN, MEDIAN_T)
            n_active = tl.sum((~done).to(tl.int32), axis=0)
            take = ok & (w > min_w[:, None])
    tl.store(out_trans_ptr + base, trans)
    tl.store(out_med_ptr + base, med)
    filled = real & (buf_w > 0.0)
    bits = buf_w.to(tl.float32).to(tl.int32, bitcast=True).to(tl.int64)
    key = tl.where(filled, (bits << 31) | (0x7FFFFFFF - buf_pos.to(tl.int64)), -1)
    tl.debug_barrier()  # every thread has read the filled slots before any key overwrites them
    tl.store(out_key_ptr + row + slots[None, :], tl.sort(key, dim=1, descending=True))


def _chunk_weights(j, cols, start, count, list_ptr, means_ptr, conics_ptr, opacities_ptr, cx, cy, trans, med, done,
                   ALPHA_MIN: tl.constexpr, ALPHA_MAX: tl.constexpr, T_MIN: tl.constexpr, MEDIAN_T: tl.constexpr):  # fmt: skip
    """List entries j .. j+CHUNK of a tile for BLOCK pixels at once: (ok [BLOCK, CHUNK], w [BLOCK,
    CHUNK], and the pixels' new T, median list position and done flags [BLOCK]).

        before_c = T · Π_{i<c} f_i,  after_c = T · Π_{i≤c} f_i,  f_i = 1 - α_i on a hit, else 1
        (one associative scan of (before, after) pairs: (b, a) ∘ (b', a') = (a·b', a·a'))
        ok_c = hit_c and after_c ≥ T_MIN;  w_c = α_c · before_c

    The products are the per-entry kernel's T ← T·(1 - α) (a compiled scan may associate them
    differently: the last bits of T can differ). Since after_c never grows, the entries after a
    pixel's stopping one are not ok, its new T is the smallest ok after_c, and its median entry
    is the one ok entry with after_c ≤ ½ < before_c.
    """
    pos = j + cols
    inside = pos < count
    g = tl.load(list_ptr + start + pos, mask=inside, other=0)
    u = tl.load(means_ptr + 2 * g, mask=inside, other=0.0)[None, :]
    v = tl.load(means_ptr + 2 * g + 1, mask=inside, other=0.0)[None, :]
    ca = tl.load(conics_ptr + 3 * g, mask=inside, other=0.0)[None, :]
    cb = tl.load(conics_ptr + 3 * g + 1, mask=inside, other=0.0)[None, :]
    cc = tl.load(conics_ptr + 3 * g + 2, mask=inside, other=0.0)[None, :]
    o = tl.load(opacities_ptr + g, mask=inside, other=0.0).to(tl.float64)[None, :]
    dx = u - cx[:, None]
    dy = v - cy[:, None]
    power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
    alpha = tl.minimum(o * tl.exp(tl.minimum(power, 0.0)), ALPHA_MAX)
    hit = (~done)[:, None] & inside[None, :] & (power <= 0.0) & (alpha >= ALPHA_MIN)
    factor = tl.where(hit, 1.0 - alpha, 1.0)
    first = (cols == 0)[None, :]
    lead = tl.where(first, trans[:, None], 1.0)
    before, after = tl.associative_scan((lead, tl.where(first, trans[:, None] * factor, factor)), 1, _transmittance_products)
    ok = hit & (after >= T_MIN)
    crossing = ok & (after <= MEDIAN_T) & (before > MEDIAN_T)
    med = tl.maximum(med, tl.max(tl.where(crossing, pos[None, :], -1), axis=1))
    trans = tl.minimum(trans, tl.min(tl.where(ok, after, 2.0), axis=1))
    done = done | (tl.max((hit & (after < T_MIN)).to(tl.int32), axis=1) > 0)
    return ok, alpha * before, trans, med, done


def _program_pixels(offsets_ptr, counts_ptr, width, height, n_tiles_x, TILE: tl.constexpr, BLOCK: tl.constexpr):
    """Program (tile, block)'s pixels: (tile, local index in the tile [BLOCK], pixel centres cx, cy
    [BLOCK] float64, done [BLOCK]: outside the image, the tile's list start and length)."""
    tile = tl.program_id(0)
    local = tl.program_id(1) * BLOCK + tl.arange(0, BLOCK)
    px = (tile % n_tiles_x) * TILE + local % TILE
    py = (tile // n_tiles_x) * TILE + local // TILE
    done = (px >= width) | (py >= height)
    return tile, local, px.to(tl.float64) + 0.5, py.to(tl.float64) + 0.5, done, tl.load(offsets_ptr + tile), tl.load(counts_ptr + tile)


def _transmittance_products(before_left, after_left, before_right, after_right):
    """The scan's combine for (T before the segment's last entry, T after it): (b, a) ∘ (b', a') = (a·b', a·a')."""
    return after_left * before_right, after_left * after_right


if triton is not None:  # a scan's combine and a kernel's helpers are themselves Triton functions
    _transmittance_products = triton.jit(_transmittance_products)
    _chunk_weights = triton.jit(_chunk_weights)
    _program_pixels = triton.jit(_program_pixels)


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
    spread = mid * mid - det
    radius = tl.ceil(3.0 * tl.sqrt(mid + tl.sqrt(tl.where(spread < 0.1, 0.1, spread))))  # a NaN stays NaN, as np.maximum's
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
def triton_kernel(source):
    """A kernel source as a Triton kernel, once per source: compiled for CUDA, or interpreted under
    TRITON_INTERPRET=1 (triton.jit decides)."""
    if triton is None:
        raise DrsplatError("the fused top-k kernel needs triton (it comes with torch's CUDA builds: pip install triton)")
    return triton.jit(source)


def require_cuda(dev: torch.device, kernel: str) -> None:
    """DrsplatError in one sentence unless `kernel` (a name, "the fused ... kernel") can run on
    `dev`: a CUDA device, or any device under Triton's interpreter (the tests)."""
    if dev.type != "cuda" and not interpreting():
        raise DrsplatError(f"{kernel} runs on CUDA devices only, not on {dev.type!r}")


def strict_launch(**options) -> dict:
    """A launch's options with FMA contraction off (products round as numba's and torch's do), plus
    `options`; none under the interpreter, which takes no compiler options."""
    return {} if interpreting() else {"enable_fp_fusion": False, **options}


def row_runs(rows: torch.Tensor, num_rows: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(order [P], starts [num_rows + 1]): `rows` [P] int64 stably sorted (each row's entries keep
    their order), row r's entries at order[starts[r]:starts[r + 1]]; for kernels that run one
    program per row (entries of rows ≥ num_rows, padding, sort after every run). Nothing is read."""
    by_row, order = torch.sort(rows, stable=True)
    return order, torch.searchsorted(by_row, torch.arange(num_rows + 1, device=rows.device, dtype=by_row.dtype))


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
    require_cuda(dev, "the fused Triton projection kernel")
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
    launch = strict_launch()
    triton_kernel(_project_source)[(triton.cdiv(n, PROJECT_BLOCK),)](
        means.contiguous(), covariances.contiguous(), opacities.contiguous(), usable.to(torch.int8), *out,
        values.pin_memory().to(dev, non_blocking=True) if dev.type == "cuda" else values, n,
        TILE=tile_size, BLOCK=PROJECT_BLOCK, **_project_constants(), **launch,
    )  # fmt: skip
    return out


def composite_topk_triton(projected, bins, topk: int = DEFAULT_TOPK, *, with_median: bool = False, block: int | None = None,
                          num_warps: int | None = None, chunk: int | None = None):
    """Top-k ids [H, W, k] int32 and weights [H, W, k] float32, alpha [H, W] float32 (and median ids [H, W] int32 or None).

    projected: a drsplat.raster_torch.TorchProjected on a CUDA device (or on the CPU under TRITON_INTERPRET=1: the tests).
    bins: the tile lists (offsets [T], counts [T], tile_list [L]) of drsplat.raster_torch.bin_gaussians_torch,
    passed in so that this module does not import its caller. block / num_warps: pixels and warps
    per program (default CUDA_BLOCK, CUDA_WARPS); chunk: list entries per step (default CUDA_CHUNK; 0: the per-entry
    kernel, `_composite_topk_source`). The rest is one kernel launch plus `_finish`'s
    gathers (no host synchronisation).
    """

    _check_args(topk, (0.0, 0.0, 0.0))
    dev = projected.valid.device
    interpret = interpreting()
    ts = projected.tile_size
    p_count = ts * ts
    block = (INTERPRET_BLOCK if interpret else CUDA_BLOCK) if block is None else block
    num_warps = CUDA_WARPS if num_warps is None else num_warps
    chunk = CUDA_CHUNK if chunk is None else chunk
    problem = launch_problem(block, num_warps, chunk, p_count)
    if problem:
        raise ValueError(problem)
    require_cuda(dev, "the fused Triton top-k kernel")
    n_tiles_x, n_tiles_y = projected.tile_grid
    n_tiles = n_tiles_x * n_tiles_y
    offsets, counts, tile_list = bins
    if tile_list.numel() == 0:  # nothing visible: a one-entry list keeps the gathers in range (every count is 0)
        tile_list = torch.zeros(1, dtype=torch.int64, device=dev)
    kp = max(1, 1 << max(0, topk - 1).bit_length())
    out_key = torch.empty((n_tiles, p_count, kp), dtype=torch.int64, device=dev)
    out_trans = torch.empty((n_tiles, p_count), dtype=torch.float64, device=dev)
    out_med = torch.empty((n_tiles, p_count), dtype=torch.int32, device=dev)
    launch = strict_launch(num_warps=num_warps)
    scratch = ()
    if chunk:
        kernel, launch = triton_kernel(_composite_topk_chunked_source), {**launch, "CHUNK": chunk}
        scratch = (torch.empty((n_tiles, p_count, kp), dtype=torch.int32, device=dev),)
    else:
        kernel = triton_kernel(_composite_topk_source)
    kernel[(n_tiles, p_count // block)](
        offsets, counts, tile_list, projected.means2d.contiguous(), projected.conics.contiguous(), projected.opacities.contiguous(),
        out_key, out_trans, out_med, *scratch, projected.width, projected.height, n_tiles_x, topk,
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


def compile_ptx(capability: int = 90, block: int = CUDA_BLOCK, kp: int = 64, tile: int = 16, chunk: int = CUDA_CHUNK,
                num_warps: int = CUDA_WARPS, ones: bool = False) -> str:
    """The compositing kernel compiled to PTX for CUDA compute capability `capability` (90: H100), without a GPU.

    Runs Triton's front end and NVIDIA backend stages (ttir -> ttgir -> llir -> ptx), not ptxas, so
    it checks that the source compiles in Triton's typed mode (the interpreter is looser) but says
    nothing about registers or speed. Uses Triton's backend API (checked with triton 3.8).
    """
    pointers = {"offsets_ptr": "*i64", "counts_ptr": "*i64", "list_ptr": "*i64", "means_ptr": "*fp64", "conics_ptr": "*fp64",
                "opacities_ptr": "*fp32", "out_key_ptr": "*i64", "out_trans_ptr": "*fp64", "out_med_ptr": "*i32"}
    consts = {"TILE": tile, "BLOCK": block, "KP": kp, "ALPHA_MIN": kernels.ALPHA_MIN, "ALPHA_MAX": kernels.ALPHA_MAX, "T_MIN": kernels.T_MIN,
              "MEDIAN_T": kernels.MEDIAN_T}
    source = _composite_topk_source
    if chunk:
        source, consts = _composite_topk_chunked_source, {**consts, "CHUNK": chunk}
        pointers = {**pointers, "fill_pos_ptr": "*i32"}  # after out_med_ptr, as in the source
    return kernel_ptx(source, {**pointers, **dict.fromkeys(("width", "height", "n_tiles_x", "topk"), "i32")}, consts, capability, ones,
                enable_fp_fusion=False, num_warps=num_warps)


def compile_project_ptx(capability: int = 90, tile: int = 16, ones: bool = False) -> str:
    """The projection kernel compiled to PTX (as `compile_ptx`), with FMA contraction off as launched."""
    pointers = {"means_ptr": "*fp64", "cov_ptr": "*fp64", "opacities_ptr": "*fp32", "usable_ptr": "*i8", "out_means_ptr": "*fp64",
                "out_conics_ptr": "*fp64", "out_depths_ptr": "*fp32", "out_radii_ptr": "*fp64", "out_rects_ptr": "*i64",
                "out_status_ptr": "*i8", "camera_ptr": "*fp64", "n": "i32"}
    consts = {"TILE": tile, "BLOCK": PROJECT_BLOCK, **_project_constants()}
    return kernel_ptx(_project_source, pointers, consts, capability, ones, enable_fp_fusion=False)


def kernel_ptx(source, signature: dict, consts: dict, capability: int, ones: bool = False, **options) -> str:
    """PTX of one kernel source for sm_`capability` (Triton's stages up to ptx, no GPU).

    `ones`: every integer scalar argument 1, passed as a constant, as Triton specialises an integer
    argument equal to 1 at launch (one mask, k = 1, a one-pixel-wide view): the source must compile
    with a Python int there too (`.to` on one does not; found on an H100, 2026-11-27)."""
    if ones:
        scalars = [name for name, kind in signature.items() if not kind.startswith("*")]
        signature = {name: kind for name, kind in signature.items() if name not in scalars}
        consts = {**dict.fromkeys(scalars, 1), **consts}
    from triton._C.libtriton import ir  # Triton internals, only for this offline check
    from triton.backends.compiler import GPUTarget
    from triton.backends.nvidia.compiler import CUDABackend
    from triton.compiler import ASTSource

    fn = triton_kernel(source)
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
