"""Numba kernels of the tile rasterizer (see drsplat.raster for the math and the reference)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from numba.cpython.unsafe.numbers import trailing_zeros

from drsplat._prefetch import prefetch_row
from drsplat.defaults import T_MIN

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
MEDIAN_T = 0.5  # the median Gaussian is the one that takes the transmittance T down to this
T_STOP = float(np.nextafter(T_MIN, 0.0))  # test_t <= T_STOP exactly when test_t < T_MIN (composite_topk's one test)
BLUR = 0.3
EXTENT_SCALE = 1.001  # safety margins of the α ≥ 1/255 ellipse (it only limits the pixels visited)
EXTENT_PAD = 1e-3
VALID, BEHIND, NONFINITE, CULLED = 0, 1, 2, 3


@njit(parallel=True, cache=True, error_model="numpy")
def bin_gaussians(order: np.ndarray, tile_rects: np.ndarray, n_tiles_x: int, n_tiles: int, n_chunks: int = 1, t_lo: int = 0,
                  t_hi: int = -1, rects_in_order: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Per-tile lists of Gaussian ids in the order given (front to back).

    order: [M] int64 Gaussian ids sorted by depth. tile_rects: [N, 4] int32 (tx0, ty0, tx1, ty1),
    end-exclusive. Returns offsets [n_tiles + 1] int64 and ids [offsets[-1]] int32; tile t owns
    ids[offsets[t]:offsets[t + 1]]. Only tiles t_lo <= t < t_hi (row-major; t_hi -1: n_tiles) get
    entries, the others empty lists: a band of the view (`band_row_span`). rects_in_order: tile_rects
    is [M, 4], row i the rectangle of Gaussian order[i] (gathered once for a view binned in many
    bands, which then reads it in sequence instead of gathering it again per band).

    Parallel over n_chunks contiguous chunks of `order`: each chunk counts its entries per tile, an
    exclusive prefix sum over (tile, chunk) gives every chunk its own start in every tile, and
    the chunks fill their slots; so each tile's list keeps the order of `order`.
    """
    t_hi = n_tiles if t_hi < 0 else t_hi
    m = order.shape[0]
    n_chunks = max(1, min(m, n_chunks))
    step = -(-m // n_chunks) if m > 0 else 1
    counts = np.zeros((n_chunks, n_tiles), np.int64)
    for c in prange(n_chunks):
        for i in range(c * step, min(m, (c + 1) * step)):
            g = order[i]
            r = i if rects_in_order else g
            for ty in range(max(tile_rects[r, 1], t_lo // n_tiles_x), min(tile_rects[r, 3], (t_hi - 1) // n_tiles_x + 1)):
                tx0, tx1 = band_row_span(ty, tile_rects[r, 0], tile_rects[r, 2], t_lo, t_hi, n_tiles_x)
                for tx in range(tx0, tx1):
                    counts[c, ty * n_tiles_x + tx] += 1
    offsets = np.zeros(n_tiles + 1, np.int64)
    total = 0
    for t in range(n_tiles):
        offsets[t] = total
        for c in range(n_chunks):
            here = counts[c, t]
            counts[c, t] = total
            total += here
    offsets[n_tiles] = total
    ids = np.empty(total, np.int32)
    for c in prange(n_chunks):
        fill = counts[c]
        for i in range(c * step, min(m, (c + 1) * step)):
            g = order[i]
            r = i if rects_in_order else g
            for ty in range(max(tile_rects[r, 1], t_lo // n_tiles_x), min(tile_rects[r, 3], (t_hi - 1) // n_tiles_x + 1)):
                tx0, tx1 = band_row_span(ty, tile_rects[r, 0], tile_rects[r, 2], t_lo, t_hi, n_tiles_x)
                for tx in range(tx0, tx1):
                    t = ty * n_tiles_x + tx
                    ids[fill[t]] = g
                    fill[t] += 1
    return offsets, ids


@njit(parallel=True, cache=True)
def depth_keys(idx: np.ndarray, depth_bits: np.ndarray) -> np.ndarray:
    """[M] uint32 keys that order as the float32 depths of Gaussians idx do.

    depth_bits: [N] uint32, the float32 depths' bits. -0 becomes +0; a positive float gets its sign
    bit set, a negative one all its bits flipped, so unsigned order is float order (NaN with the sign
    bit clear after +inf, as `drsplat.raster.depth_order_reference` orders them).
    """
    keys = np.empty(idx.shape[0], np.uint32)
    for i in prange(idx.shape[0]):
        b = depth_bits[idx[i]]
        if b == np.uint32(0x80000000):
            b = np.uint32(0)
        keys[i] = ~b if b >> np.uint32(31) else b | np.uint32(0x80000000)
    return keys


@njit(cache=True, inline="always")
def band_row_span(ty, tx0, tx1, t_lo, t_hi, n_tiles_x):
    """[tx0, tx1) of tile row ty cut to the band of row-major tiles t_lo <= t < t_hi (the band's first
    and last rows may be partial)."""
    if ty == t_lo // n_tiles_x:
        tx0 = max(tx0, t_lo - ty * n_tiles_x)
    if ty == (t_hi - 1) // n_tiles_x:
        tx1 = min(tx1, t_hi - ty * n_tiles_x)
    return tx0, tx1


@njit(parallel=True, cache=True)
def tile_entry_total(tile_rects: np.ndarray) -> int:
    """Σ of the getRect rectangles' tiles: the entries of a view's whole tile lists, in parallel
    (tile_rects: [N, 4] int32, empty rectangles count 0)."""
    total = 0
    for g in prange(tile_rects.shape[0]):
        total += max(tile_rects[g, 2] - tile_rects[g, 0], 0) * max(tile_rects[g, 3] - tile_rects[g, 1], 0)
    return total


@njit(cache=True)
def tile_entry_counts(tile_rects: np.ndarray, n_tiles_x: int, n_tiles_y: int) -> np.ndarray:
    """[n_tiles] int64: how many Gaussians' getRect rectangles hold each tile (the lengths of
    `bin_gaussians`' lists), from a 2-D difference array: O(N + tiles), no list built.
    tile_rects: [N, 4] int32 (tx0, ty0, tx1, ty1), end-exclusive, empty for invalid Gaussians."""
    diff = np.zeros((n_tiles_y + 1, n_tiles_x + 1), np.int64)
    for g in range(tile_rects.shape[0]):
        x0, y0, x1, y1 = tile_rects[g, 0], tile_rects[g, 1], tile_rects[g, 2], tile_rects[g, 3]
        if x1 <= x0 or y1 <= y0:
            continue
        diff[y0, x0] += 1
        diff[y0, x1] -= 1
        diff[y1, x0] -= 1
        diff[y1, x1] += 1
    counts = np.empty(n_tiles_y * n_tiles_x, np.int64)
    above = np.zeros(n_tiles_x + 1, np.int64)
    for ty in range(n_tiles_y):
        run = np.int64(0)
        for tx in range(n_tiles_x):
            run += diff[ty, tx]
            above[tx] += run
            counts[ty * n_tiles_x + tx] = above[tx]
    return counts


@njit(cache=True, error_model="numpy", inline="always")
def rescan_min(wbuf, minw, minpos, p) -> None:
    """minw[p], minpos[p] = the smallest weight of pixel p's full buffer and its last slot.

    Slots are in arrival order, so among equal smallest weights the last slot is the one a
    stable sort by descending weight puts last: the one to evict first.
    """
    k = wbuf.shape[1]
    mn = wbuf[p, 0]
    mp = 0
    for m in range(1, k):
        if wbuf[p, m] <= mn:
            mn = wbuf[p, m]
            mp = m
    minw[p] = mn
    minpos[p] = mp


@njit(cache=True, error_model="numpy", inline="always")
def push_topk(wbuf, ibuf, count, minw, minpos, p, w, g) -> None:
    """Offer contribution (w, g) to pixel p's buffer of its k best (k = wbuf.shape[1]).

    The buffer is unsorted and in arrival order. Until it holds k entries a newcomer is appended;
    then it replaces the evictable minimum (`rescan_min`) only if w is strictly larger (a newcomer
    of equal weight sorts after the entries that arrived earlier), shifting the later slots down
    to keep arrival order. `sort_topk` at the end then yields exactly the first k entries of a
    stable sort of all contributions by descending weight. Most contributions of a full buffer
    lose the single comparison with minw[p].
    """
    k = wbuf.shape[1]
    n = count[p]
    if n < k:
        wbuf[p, n] = w
        ibuf[p, n] = g
        count[p] = n + 1
        if n + 1 == k:
            rescan_min(wbuf, minw, minpos, p)
    elif w > minw[p]:
        for m in range(minpos[p], k - 1):
            wbuf[p, m] = wbuf[p, m + 1]
            ibuf[p, m] = ibuf[p, m + 1]
        wbuf[p, k - 1] = w
        ibuf[p, k - 1] = g
        rescan_min(wbuf, minw, minpos, p)


@njit(cache=True, error_model="numpy", inline="always")
def sort_topk(wbuf, ibuf, n, p) -> None:
    """Stable insertion sort of pixel p's first n entries by descending weight."""
    for i in range(1, n):
        w = wbuf[p, i]
        g = ibuf[p, i]
        pos = i
        while pos > 0 and wbuf[p, pos - 1] < w:
            wbuf[p, pos] = wbuf[p, pos - 1]
            ibuf[p, pos] = ibuf[p, pos - 1]
            pos -= 1
        wbuf[p, pos] = w
        ibuf[p, pos] = g


@njit(parallel=True, cache=True, error_model="numpy")
def composite_tiles(
    tile_order: np.ndarray,
    worker_starts: np.ndarray,
    offsets: np.ndarray,
    tile_ids: np.ndarray,
    means2d: np.ndarray,
    conics: np.ndarray,
    opacities: np.ndarray,
    extents: np.ndarray,
    qlimits: np.ndarray,
    depths: np.ndarray,
    colors: np.ndarray,
    width: int,
    height: int,
    tile_size: int,
    n_tiles_x: int,
    with_rgb: bool,
    with_depth: bool,
    with_median: bool,
    background: np.ndarray,
    out_ids: np.ndarray,
    out_weights: np.ndarray,
    out_rgb: np.ndarray,
    out_depth: np.ndarray,
    out_alpha: np.ndarray,
    out_median: np.ndarray,
) -> None:
    """Front-to-back compositing of every tile, Gaussian-outer like 3DGS's shared-memory loop.

    Worker w (one prange iteration, one thread each) processes the tiles
    tile_order[worker_starts[w]:worker_starts[w + 1]] in that order, reusing its scratch arrays
    from tile to tile; the caller balances the work (`balance_tiles`). For each Gaussian of
    a tile (depth order) only the pixels inside its ellipse dᵀ Σ'⁻¹ d ≤ qlimits (where α ≥ 1/255
    is possible; `extents` is its bounding box) are visited, with a one-pixel margin; the
    per-pixel test is the exact 3DGS rule, so the ellipse changes speed, not results. Rows and
    tiles whose pixels all reached the transmittance floor are skipped. Writes every element of out_ids [H, W, k], out_weights [H, W, k],
    out_rgb [H, W, 3] = Σ w·c + T·background, out_depth [H, W] = Σ w·z / Σ w (0 where Σ w = 0)
    out_alpha [H, W] = 1 - T and out_median [H, W] = the median Gaussian: the id of the
    contribution that takes T from above ½ to ≤ ½ (-1 where T stays above ½).
    """
    k = out_ids.shape[2]
    n_px = tile_size * tile_size
    for worker in prange(worker_starts.shape[0] - 1):
        trans = np.empty(n_px, np.float64)
        done = np.empty(n_px, np.bool_)
        count = np.empty(n_px, np.int64)
        minw = np.zeros(n_px, np.float64)  # minw, minpos, wbuf, ibuf: read only once count[p] says they are set
        minpos = np.zeros(n_px, np.int64)
        wbuf = np.empty((n_px, max(k, 1)), np.float64)
        ibuf = np.empty((n_px, max(k, 1)), np.int32)
        rgb = np.empty((n_px, 3), np.float64)
        dep = np.empty(n_px, np.float64)
        med = np.empty(n_px, np.int32)
        row_active = np.empty(tile_size, np.int64)
        for slot in range(worker_starts[worker], worker_starts[worker + 1]):
            t = tile_order[slot]
            x0 = (t % n_tiles_x) * tile_size
            y0 = (t // n_tiles_x) * tile_size
            x1 = min(x0 + tile_size, width)
            y1 = min(y0 + tile_size, height)
            tw = x1 - x0
            th = y1 - y0
            for p in range(th * tw):
                trans[p] = 1.0
                done[p] = False
                count[p] = 0
                dep[p] = 0.0
                med[p] = -1
                rgb[p, 0] = 0.0
                rgb[p, 1] = 0.0
                rgb[p, 2] = 0.0
            n_active = tw * th
            for ly in range(th):
                row_active[ly] = tw
            for j in range(offsets[t], offsets[t + 1]):
                g = tile_ids[j]
                u = means2d[g, 0]
                v = means2d[g, 1]
                ex = extents[g, 0]
                ey = extents[g, 1]
                fx0 = max(float(x0), np.ceil(u - 0.5 - ex))
                fx1 = min(float(x1 - 1), np.floor(u - 0.5 + ex))
                fy0 = max(float(y0), np.ceil(v - 0.5 - ey))
                fy1 = min(float(y1 - 1), np.floor(v - 0.5 + ey))
                if fx0 > fx1 or fy0 > fy1:
                    continue
                ca = conics[g, 0]
                cb = conics[g, 1]
                cc = conics[g, 2]
                qmax = qlimits[g]
                # below this power α < 1/255 for sure (qmax ≥ 2·ln(255·o) with a margin), so exp is skipped
                power_min = -0.5 * qmax
                o = np.float64(opacities[g])
                z = np.float64(depths[g])
                for py in range(int(fy0), int(fy1) + 1):
                    ly = py - y0
                    if row_active[ly] == 0:
                        continue
                    dy = v - (py + 0.5)
                    # pixels of this row inside the ellipse a·dx² + 2b·dx·dy + c·dy² ≤ qmax, ±1 px
                    disc = cb * cb * dy * dy - ca * (cc * dy * dy - qmax)
                    if disc < 0.0:
                        continue
                    root = math.sqrt(disc)
                    rx0 = max(fx0, np.floor(u - 0.5 - (root - cb * dy) / ca) - 1.0)
                    rx1 = min(fx1, np.ceil(u - 0.5 + (root + cb * dy) / ca) + 1.0)
                    row = ly * tw - x0
                    for px in range(int(rx0), int(rx1) + 1):
                        pix = row + px
                        if done[pix]:
                            continue
                        dx = u - (px + 0.5)
                        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                        if power > 0.0 or power < power_min:
                            continue
                        alpha = min(ALPHA_MAX, o * math.exp(power))
                        if alpha < ALPHA_MIN:
                            continue
                        t_now = trans[pix]
                        test_t = t_now * (1.0 - alpha)
                        if test_t < T_MIN:
                            done[pix] = True
                            n_active -= 1
                            row_active[ly] -= 1
                            continue
                        w = alpha * t_now
                        if k > 0:
                            push_topk(wbuf, ibuf, count, minw, minpos, pix, w, g)
                        if with_rgb:
                            rgb[pix, 0] += w * colors[g, 0]
                            rgb[pix, 1] += w * colors[g, 1]
                            rgb[pix, 2] += w * colors[g, 2]
                        if with_depth:
                            dep[pix] += w * z
                        if with_median and test_t <= MEDIAN_T < t_now:
                            med[pix] = g
                        trans[pix] = test_t
                if n_active == 0:
                    break
            for ly in range(th):
                for lx in range(tw):
                    py = y0 + ly
                    px = x0 + lx
                    p = ly * tw + lx
                    if k > 0:
                        sort_topk(wbuf, ibuf, count[p], p)
                    n = count[p]
                    for m in range(n):
                        out_ids[py, px, m] = ibuf[p, m]
                        out_weights[py, px, m] = wbuf[p, m]
                    for m in range(n, k):
                        out_ids[py, px, m] = -1
                        out_weights[py, px, m] = 0.0
                    acc = 1.0 - trans[p]
                    out_alpha[py, px] = acc
                    if with_rgb:
                        for ch in range(3):
                            out_rgb[py, px, ch] = rgb[p, ch] + trans[p] * background[ch]
                    if with_depth:
                        out_depth[py, px] = dep[p] / acc if acc > 0.0 else 0.0
                    if with_median:
                        out_median[py, px] = med[p]


@njit(parallel=True, cache=True, error_model="numpy")
def project_points(
    means: np.ndarray,
    covariances: np.ndarray,
    opacities: np.ndarray,
    usable: np.ndarray,
    rot: np.ndarray,
    trans: np.ndarray,
    intrinsics: np.ndarray,
    width: int,
    height: int,
    near: float,
    tile_size: int,
    out_means2d: np.ndarray,
    out_conics: np.ndarray,
    out_depths: np.ndarray,
    out_radii: np.ndarray,
    out_rects: np.ndarray,
    out_extents: np.ndarray,
    out_qlimits: np.ndarray,
    out_status: np.ndarray,
) -> None:
    """Per-Gaussian EWA projection; the same math as drsplat.raster.project_gaussians_reference.

    intrinsics: [8] (fx, fy, cx, cy, then the clamp tangents of drsplat.raster.clamp_limits:
    x/z max, -(x/z) max, y/z max, -(y/z) max). out_status: [N] int8, VALID, BEHIND (z < near), NONFINITE
    (projection not finite), or CULLED (unusable, transparent, degenerate or off-screen).
    Every output row is written: a non-valid Gaussian gets zeros (its depth: the camera z, 0
    when unusable), so the outputs may be reused buffers holding a previous view.
    """
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg = intrinsics[4], intrinsics[5], intrinsics[6], intrinsics[7]
    for g in prange(means.shape[0]):
        out_status[g] = CULLED
        out_means2d[g, 0] = out_means2d[g, 1] = 0.0
        out_conics[g, 0] = out_conics[g, 1] = out_conics[g, 2] = 0.0
        out_radii[g] = 0
        out_rects[g, 0] = out_rects[g, 1] = out_rects[g, 2] = out_rects[g, 3] = 0
        out_extents[g, 0] = out_extents[g, 1] = 0.0
        out_qlimits[g] = 0.0
        if not usable[g]:
            out_depths[g] = 0.0
            continue
        px = rot[0, 0] * means[g, 0] + rot[0, 1] * means[g, 1] + rot[0, 2] * means[g, 2] + trans[0]
        py = rot[1, 0] * means[g, 0] + rot[1, 1] * means[g, 1] + rot[1, 2] * means[g, 2] + trans[1]
        pz = rot[2, 0] * means[g, 0] + rot[2, 1] * means[g, 1] + rot[2, 2] * means[g, 2] + trans[2]
        out_depths[g] = pz
        if not pz >= near:
            out_status[g] = BEHIND
            continue
        o = np.float64(opacities[g])
        if o < ALPHA_MIN:
            continue
        tx = pz * min(max(px / pz, -lim_x_neg), lim_x_pos)
        ty = pz * min(max(py / pz, -lim_y_neg), lim_y_pos)
        # rows of J·W: the screen-space Jacobian of the world position
        jx = fx / pz
        jxz = -fx * tx / (pz * pz)
        jy = fy / pz
        jyz = -fy * ty / (pz * pz)
        a00 = jx * rot[0, 0] + jxz * rot[2, 0]
        a01 = jx * rot[0, 1] + jxz * rot[2, 1]
        a02 = jx * rot[0, 2] + jxz * rot[2, 2]
        a10 = jy * rot[1, 0] + jyz * rot[2, 0]
        a11 = jy * rot[1, 1] + jyz * rot[2, 1]
        a12 = jy * rot[1, 2] + jyz * rot[2, 2]
        cv = covariances[g]
        s00 = cv[0, 0] * a00 + cv[0, 1] * a01 + cv[0, 2] * a02
        s01 = cv[1, 0] * a00 + cv[1, 1] * a01 + cv[1, 2] * a02
        s02 = cv[2, 0] * a00 + cv[2, 1] * a01 + cv[2, 2] * a02
        s10 = cv[0, 0] * a10 + cv[0, 1] * a11 + cv[0, 2] * a12
        s11 = cv[1, 0] * a10 + cv[1, 1] * a11 + cv[1, 2] * a12
        s12 = cv[2, 0] * a10 + cv[2, 1] * a11 + cv[2, 2] * a12
        a = a00 * s00 + a01 * s01 + a02 * s02
        b = a10 * s00 + a11 * s01 + a12 * s02
        c = a10 * s10 + a11 * s11 + a12 * s12
        a += BLUR
        c += BLUR
        u = fx * px / pz + cx
        v = fy * py / pz + cy
        det = a * c - b * b
        mid = 0.5 * (a + c)
        spread = mid * mid - det
        if spread < 0.1:  # np.maximum(0.1, ·) as the reference takes it: a NaN (inf - inf, where det overflows) stays NaN
            spread = 0.1  # and the Gaussian is counted non-finite (round 98f F1: max() made it 0.1, and it was drawn)
        radius = np.ceil(3.0 * math.sqrt(mid + math.sqrt(spread)))
        if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(c) and math.isfinite(u) and math.isfinite(v) and math.isfinite(radius)):
            out_status[g] = NONFINITE
            continue
        if not det > 0.0:
            continue
        # 3DGS's getRect (drsplat.raster._tile_rects), p = mean - 0.5
        grid_x = float(-(-width // tile_size))
        grid_y = float(-(-height // tile_size))
        rx0 = min(max(np.floor((u - 0.5 - radius) / tile_size), 0.0), grid_x)
        rx1 = min(max(np.floor((u - 0.5 + radius + tile_size - 1) / tile_size), 0.0), grid_x)
        ry0 = min(max(np.floor((v - 0.5 - radius) / tile_size), 0.0), grid_y)
        ry1 = min(max(np.floor((v - 0.5 + radius + tile_size - 1) / tile_size), 0.0), grid_y)
        if rx1 <= rx0 or ry1 <= ry0:
            continue
        q = 2.0 * math.log(o * 255.0)
        out_status[g] = VALID
        out_means2d[g, 0] = u
        out_means2d[g, 1] = v
        out_conics[g, 0] = c / det
        out_conics[g, 1] = -b / det
        out_conics[g, 2] = a / det
        out_radii[g] = np.int32(min(radius, 2.0**30))
        out_rects[g, 0] = np.int32(rx0)
        out_rects[g, 1] = np.int32(ry0)
        out_rects[g, 2] = np.int32(rx1)
        out_rects[g, 3] = np.int32(ry1)
        out_extents[g, 0] = math.sqrt(max(q, 0.0) * a) * EXTENT_SCALE + EXTENT_PAD
        out_extents[g, 1] = math.sqrt(max(q, 0.0) * c) * EXTENT_SCALE + EXTENT_PAD
        out_qlimits[g] = max(q, 0.0) * EXTENT_SCALE + EXTENT_PAD


# ----------------------------------------------------------------------------- the registration path
# Ids and weights only (plus the median Gaussian when asked), exact opacity-aware tile sets, and an
# unordered top-k buffer that knows its slot to evict. drsplat.raster.render_topk drives these; the
# kernels above (composite_tiles, bin_gaussians) stay the reference they must agree with.

ACCUTILE_PAD = 0.01  # pixels added around the α ≥ 1/255 ellipse's span of a tile row (rounding)
MAX_TILE_LANES = 64  # composite_topk keeps a tile row's pixels as the bits of one uint64: tiles at most this wide
LANE_BLOCK = 16  # composite_topk evaluates a tile row's powers in blocks of this many lanes (MAX_TILE_LANES is a multiple)
BLOCK_BITS = np.uint64((1 << LANE_BLOCK) - 1)
NARROW_BOX = 10.0  # boxes narrower than this (pixels) are visited row by row whole: cheaper than the ellipse's span (-6% measured)
PREFETCH_ENTRIES = 8  # composite_topk asks for the rows of the Gaussian this many tile entries ahead (4: 0.90x, 8: 0.85x, 16: 0.91x)


@njit(cache=True, error_model="numpy", inline="always")
def ellipse_tile_span(u, v, ca, cb, cc, q, ty, tile_size, height, rx0, rx1):
    """(tx0, tx1), end-exclusive, of the tiles of tile row ty that the ellipse
    a·dx² + 2b·dx·dy + c·dy² ≤ q (dx = u - X, dy = v - Y, conic (a, b, c)) meets at a pixel centre
    (X, Y) = (px + 0.5, py + 0.5), clipped to [rx0, rx1); empty (tx0 ≥ tx1) when it meets none.

    On a horizontal line dy the ellipse spans dx ∈ (-b·dy ± sqrt(a·q - det·dy²)) / a, det = ac - b²,
    for dy² ≤ a·q / det. The right end is concave in dy, its maximum sqrt(q·c/det) at
    dy = -(b/c)·sqrt(q·c/det); so over the band of the row's pixel centres its largest value is
    at that dy clamped into the band (the left end likewise, mirrored), padded by ACCUTILE_PAD.
    """
    det = ca * cc - cb * cb
    y_lo = ty * tile_size + 0.5
    y_hi = min(ty * tile_size + tile_size, height) - 0.5
    reach_y = math.sqrt(max(ca * q / det, 0.0)) + ACCUTILE_PAD
    d_lo = max(v - y_hi, -reach_y)  # the band in dy = v - Y
    d_hi = min(v - y_lo, reach_y)
    if d_lo > d_hi:
        return 0, 0
    reach_x = math.sqrt(max(q * cc / det, 0.0))
    dy_right = min(max(-(cb / cc) * reach_x, d_lo), d_hi)
    dy_left = min(max((cb / cc) * reach_x, d_lo), d_hi)
    dx_max = (-cb * dy_right + math.sqrt(max(ca * q - det * dy_right * dy_right, 0.0))) / ca + ACCUTILE_PAD
    dx_min = (-cb * dy_left - math.sqrt(max(ca * q - det * dy_left * dy_left, 0.0))) / ca - ACCUTILE_PAD
    # pixels whose centre X = px + 0.5 lies in [u - dx_max, u - dx_min]
    px0 = np.ceil(u - dx_max - 0.5)
    px1 = np.floor(u - dx_min - 0.5)
    tx0 = max(float(rx0), np.floor(px0 / tile_size))
    tx1 = min(float(rx1), np.floor(px1 / tile_size) + 1.0)
    if tx0 >= tx1:
        return 0, 0
    return int(tx0), int(tx1)


@njit(cache=True, error_model="numpy", inline="always")
def snug_rect(g, tile_rects, means2d, extents, tile_size):
    """(tx0, ty0, tx1, ty1), end-exclusive: the tiles of Gaussian g's getRect rectangle that its
    α ≥ 1/255 bounding box (±extents around the mean, Speedy-Splat's SnugBox) meets at a pixel centre."""
    u = means2d[g, 0] - 0.5
    v = means2d[g, 1] - 0.5
    ex = extents[g, 0] + ACCUTILE_PAD
    ey = extents[g, 1] + ACCUTILE_PAD
    tx0 = max(float(tile_rects[g, 0]), np.floor(np.ceil(u - ex) / tile_size))
    tx1 = min(float(tile_rects[g, 2]), np.floor(np.floor(u + ex) / tile_size) + 1.0)
    ty0 = max(float(tile_rects[g, 1]), np.floor(np.ceil(v - ey) / tile_size))
    ty1 = min(float(tile_rects[g, 3]), np.floor(np.floor(v + ey) / tile_size) + 1.0)
    if tx0 >= tx1 or ty0 >= ty1:
        return 0, 0, 0, 0
    return int(tx0), int(ty0), int(tx1), int(ty1)


@njit(cache=True, error_model="numpy", inline="always")
def row_tiles(g, ty, rect, means2d, conics, qlimits, tile_size, height):
    """The tiles of row ty of `rect` (snug_rect) that Gaussian g's α ≥ 1/255 ellipse meets: the
    whole row when the rectangle is one tile wide or tall (the box is then exact enough), else
    `ellipse_tile_span` (AccuTile)."""
    if rect[2] - rect[0] <= 1 or rect[3] - rect[1] <= 1:
        return rect[0], rect[2]
    return ellipse_tile_span(means2d[g, 0], means2d[g, 1], conics[g, 0], conics[g, 1], conics[g, 2], qlimits[g], ty, tile_size, height,
                             rect[0], rect[2])


@njit(parallel=True, cache=True, error_model="numpy")
def bin_gaussians_exact(order, tile_rects, means2d, conics, extents, qlimits, tile_size, height, n_tiles_x, n_tiles, n_chunks=1, t_lo=0,
                        t_hi=-1):
    """`bin_gaussians` restricted to the tiles the α ≥ 1/255 ellipse meets (Speedy-Splat's SnugBox
    and AccuTile).

    A Gaussian goes into tile (tx, ty) of its getRect rectangle `tile_rects` only when its
    α ≥ 1/255 box meets a pixel centre of the tile (`snug_rect`) and, for rectangles at least
    two tiles wide and tall, its ellipse dᵀ Σ'⁻¹ d ≤ qlimits does too (`row_tiles`). Both hold
    every pixel where α ≥ 1/255, so every tile dropped is one where the Gaussian contributes
    nothing: compositing gives the same result with fewer tile visits. Same outputs and order as
    bin_gaussians: offsets [n_tiles + 1] int64 and ids [offsets[-1]] int32, front to back per tile,
    entries only in the band of tiles t_lo <= t < t_hi (t_hi -1: n_tiles).
    """
    t_hi = n_tiles if t_hi < 0 else t_hi
    m = order.shape[0]
    n_chunks = max(1, min(m, n_chunks))
    step = -(-m // n_chunks) if m > 0 else 1
    counts = np.zeros((n_chunks, n_tiles), np.int64)
    for c in prange(n_chunks):
        for i in range(c * step, min(m, (c + 1) * step)):
            g = order[i]
            rect = snug_rect(g, tile_rects, means2d, extents, tile_size)
            for ty in range(max(rect[1], t_lo // n_tiles_x), min(rect[3], (t_hi - 1) // n_tiles_x + 1)):
                tx0, tx1 = row_tiles(g, ty, rect, means2d, conics, qlimits, tile_size, height)
                tx0, tx1 = band_row_span(ty, tx0, tx1, t_lo, t_hi, n_tiles_x)
                for tx in range(tx0, tx1):
                    counts[c, ty * n_tiles_x + tx] += 1
    offsets = np.zeros(n_tiles + 1, np.int64)
    total = 0
    for t in range(n_tiles):
        offsets[t] = total
        for c in range(n_chunks):
            here = counts[c, t]
            counts[c, t] = total
            total += here
    offsets[n_tiles] = total
    ids = np.empty(total, np.int32)
    for c in prange(n_chunks):
        fill = counts[c]
        for i in range(c * step, min(m, (c + 1) * step)):
            g = order[i]
            rect = snug_rect(g, tile_rects, means2d, extents, tile_size)
            for ty in range(max(rect[1], t_lo // n_tiles_x), min(rect[3], (t_hi - 1) // n_tiles_x + 1)):
                tx0, tx1 = row_tiles(g, ty, rect, means2d, conics, qlimits, tile_size, height)
                tx0, tx1 = band_row_span(ty, tx0, tx1, t_lo, t_hi, n_tiles_x)
                for tx in range(tx0, tx1):
                    t = ty * n_tiles_x + tx
                    ids[fill[t]] = g
                    fill[t] += 1
    return offsets, ids


@njit(cache=True, error_model="numpy", inline="always")
def lightest_slot(wbits, sbuf, p, k):
    """The slot of pixel p's full buffer to evict first: the lightest, and among equal weights the
    latest arrival (the one a stable sort by descending weight puts last).

    wbits: the weight buffer's float64 bits read as int64 (`wbuf.view(np.int64)`). Weights are
    positive (w = T·α, α ≥ 1/255), and the bits of positive floats order as the floats do, so the
    minimum is an integer reduction, which numba vectorises (a float one it does not: NaN rules).
    The slots holding it are then the bits of a 64-bit mask per 64 slots, usually a single bit.
    """
    m = wbits[p, 0]
    for i in range(1, k):
        v = wbits[p, i]
        m = v if v < m else m
    pos = -1
    for base in range(0, k, 64):
        ties = np.uint64(0)
        for i in range(min(64, k - base)):
            ties |= np.uint64(wbits[p, base + i] == m) << np.uint64(i)
        while ties != 0:
            i = base + np.int64(trailing_zeros(ties))
            ties &= ties - np.uint64(1)
            if pos < 0 or sbuf[p, i] > sbuf[p, pos]:
                pos = i
    return pos


@njit(cache=True, error_model="numpy", inline="always")
def offer_topk(wbuf, wbits, sbuf, count, evict, p, w, seq) -> None:
    """Offer weight w, arrival number seq (increasing; the entry's place in its tile list), to pixel p's k best.

    wbuf: [P, k] float64 weights (wbits: the same memory as int64, `lightest_slot`), sbuf: [P, k]
    int32 arrival numbers, count: [P] slots used, evict: [P] the slot to evict next (set once full).
    Until k entries are held a newcomer is appended; the k-th finds the slot to evict first
    (`lightest_slot`). Then a newcomer replaces that slot only if strictly heavier (one of equal
    weight would sort after it), and the next one to evict is found by a vectorised rescan. So
    the buffer always holds the first k entries of a stable sort of the contributions so far by
    descending weight, unordered (`write_ranked` sorts them). The Gaussian id is not stored: it
    is the tile list's entry at seq. (A min-heap did the same in O(log k) per replacement; the
    rescan, k = 40, is faster: docs/raster.md.)
    """
    k = wbuf.shape[1]
    n = count[p]
    if n < k:
        wbuf[p, n] = w
        sbuf[p, n] = seq
        count[p] = n + 1
        if n + 1 == k:
            evict[p] = lightest_slot(wbits, sbuf, p, k)
    else:
        pos = evict[p]
        if w > wbuf[p, pos]:
            wbuf[p, pos] = w
            sbuf[p, pos] = seq
            evict[p] = lightest_slot(wbits, sbuf, p, k)


@njit(cache=True, error_model="numpy", inline="always")
def write_ranked(wbuf, sbuf, n, p, tile_list, out_ids, out_weights, py, px, ranked) -> None:
    """Write pixel p's n entries to out_* at (py, px), -1 / 0 in the k - n slots after them.

    tile_list: the tile's Gaussian ids in arrival order (an entry's id is tile_list[seq]).
    ranked=False writes the n entries as they lie in the buffer (no particular order). ranked=True sorts
    them first (insertion sort on (weight desc, arrival)), for the order every engine promises.
    """
    for i in range(1, n if ranked else 0):
        w = wbuf[p, i]
        s = sbuf[p, i]
        pos = i
        while pos > 0 and (wbuf[p, pos - 1] < w or (wbuf[p, pos - 1] == w and sbuf[p, pos - 1] > s)):
            wbuf[p, pos] = wbuf[p, pos - 1]
            sbuf[p, pos] = sbuf[p, pos - 1]
            pos -= 1
        wbuf[p, pos] = w
        sbuf[p, pos] = s
    ids_row = out_ids[py, px]
    weights_row = out_weights[py, px]
    for m in range(n):
        ids_row[m] = tile_list[sbuf[p, m]]
        weights_row[m] = wbuf[p, m]
    # slices, not out_*[py, px, m] for m in range(n, k): numba cannot prove such an m non-negative,
    # and the wrap-around it then allows made the padding a loop of scatters
    ids_row[n:] = -1
    weights_row[n:] = 0.0


@njit(cache=True, error_model="numpy", inline="always")
def lane_span(lo, hi):
    """The uint64 bit mask of lanes lo..hi (0 <= lo, hi <= 63; empty when lo > hi: no bit is both >= lo and <= hi)."""
    return ((np.uint64(2) << np.uint64(hi)) - np.uint64(1)) & ~((np.uint64(1) << np.uint64(lo)) - np.uint64(1))


@njit(parallel=True, cache=True, error_model="numpy")
def composite_topk(
    tile_order: np.ndarray,
    worker_starts: np.ndarray,
    offsets: np.ndarray,
    tile_ids: np.ndarray,
    means2d: np.ndarray,
    conics: np.ndarray,
    opacities: np.ndarray,
    extents: np.ndarray,
    qlimits: np.ndarray,
    width: int,
    height: int,
    tile_size: int,
    n_tiles_x: int,
    with_median: bool,
    ranked: bool,
    out_ids: np.ndarray,
    out_weights: np.ndarray,
    out_alpha: np.ndarray,
    out_median: np.ndarray,
) -> None:
    """`composite_tiles` for registration: ids, weights, alpha (and the median Gaussian), nothing else.

    The same per-pixel 3DGS rules in float64, so the same contributions bit for bit; faster by:
    - each tile row's pixels still compositing are the bits of one uint64 (`active`; tile_size
      <= 64), so a Gaussian's row visits only those (trailing-zero count), and a row with none
      costs one AND;
    - a row is done in two passes: the power of every lane of the row's span, without a branch,
      giving the bits of the lanes inside the α window; then the exp, transmittance and top-k of
      those lanes only (the window test, taken in the middle of the loop, mispredicted at every
      ellipse edge);
    - a top-k buffer that, once full, knows the slot to evict next (`offer_topk`: a vectorised
      rescan per replacement), holding (float64 weight, int32 place in the tile list): the id is
      read from the list at write time;
    - the ellipse's row span only for boxes at least NARROW_BOX wide, no colour or depth work,
      and, with ranked=False, no per-pixel sort: the k slots then hold the same entries in
      arrival-and-replacement order (`write_ranked`).
    The tile lists may be bin_gaussians' or bin_gaussians_exact's.
    out_ids [H, W, k] int32, out_weights [H, W, k] float32, out_alpha [H, W], out_median [H, W]
    (only with_median) are all written.
    """
    k = out_ids.shape[2]
    n_px = tile_size * tile_size
    for worker in prange(worker_starts.shape[0] - 1):
        trans = np.empty(n_px, np.float64)
        count = np.empty(n_px, np.int64)
        wbuf = np.empty((n_px, max(k, 1)), np.float64)
        sbuf = np.empty((n_px, max(k, 1)), np.int32)  # arrival numbers: places in the tile's list
        wbits = wbuf.view(np.int64)
        evict = np.empty(n_px, np.int64)
        med = np.empty(n_px, np.int32)
        next_t = np.empty(n_px, np.float64)  # the T at or below which the pixel's next event happens
        active = np.empty(tile_size, np.uint64)
        power_of = np.empty(MAX_TILE_LANES, np.float64)
        for slot in range(worker_starts[worker], worker_starts[worker + 1]):
            t = tile_order[slot]
            x0 = (t % n_tiles_x) * tile_size
            y0 = (t // n_tiles_x) * tile_size
            x1 = min(x0 + tile_size, width)
            y1 = min(y0 + tile_size, height)
            tw = x1 - x0
            th = y1 - y0
            for p in range(th * tw):
                trans[p] = 1.0
                count[p] = 0
                med[p] = -1
                next_t[p] = MEDIAN_T if with_median else T_STOP
            n_active = tw * th
            for ly in range(th):
                active[ly] = lane_span(0, tw - 1)
            first = offsets[t]
            last = offsets[t + 1]
            for j in range(first, last):
                if j + PREFETCH_ENTRIES < last:
                    ahead = tile_ids[j + PREFETCH_ENTRIES]
                    prefetch_row(means2d, ahead)
                    prefetch_row(extents, ahead)
                    prefetch_row(conics, ahead)
                    prefetch_row(qlimits, ahead)
                    prefetch_row(opacities, ahead)
                g = tile_ids[j]
                u = means2d[g, 0]
                v = means2d[g, 1]
                ex = extents[g, 0]
                ey = extents[g, 1]
                fx0 = max(float(x0), np.ceil(u - 0.5 - ex))
                fx1 = min(float(x1 - 1), np.floor(u - 0.5 + ex))
                fy0 = max(float(y0), np.ceil(v - 0.5 - ey))
                fy1 = min(float(y1 - 1), np.floor(v - 0.5 + ey))
                if fx0 > fx1 or fy0 > fy1:
                    continue
                ca = conics[g, 0]
                cb = conics[g, 1]
                cc = conics[g, 2]
                qmax = qlimits[g]
                power_min = -0.5 * qmax
                o = np.float64(opacities[g])
                narrow = fx1 - fx0 < NARROW_BOX
                box = lane_span(int(fx0) - x0, int(fx1) - x0)
                seq = np.int32(j - first)
                for py in range(int(fy0), int(fy1) + 1):
                    ly = py - y0
                    lanes = active[ly] & box
                    if lanes == 0:
                        continue
                    dy = v - (py + 0.5)
                    if not narrow:  # a narrow box's row: the ellipse's span costs more than the pixels it skips
                        disc = cb * cb * dy * dy - ca * (cc * dy * dy - qmax)
                        if disc < 0.0:
                            continue
                        root = math.sqrt(disc)
                        rx0 = max(fx0, np.floor(u - 0.5 - (root - cb * dy) / ca) - 1.0)
                        rx1 = min(fx1, np.ceil(u - 0.5 + (root + cb * dy) / ca) + 1.0)
                        if not rx0 <= rx1:
                            continue
                        lanes &= lane_span(int(rx0) - x0, int(rx1) - x0)
                        if lanes == 0:
                            continue
                    inside = np.uint64(0)
                    for base in range(0, tw, LANE_BLOCK):
                        if (lanes >> np.uint64(base)) & BLOCK_BITS == 0:
                            continue
                        block = np.uint64(0)
                        # indexed by the loop's own lane, the stores are contiguous; power_of[base + lane]
                        # (an index numba cannot prove non-negative) compiled to two 8-lane scatters
                        block_powers = power_of[base:base + LANE_BLOCK]
                        for lane in range(LANE_BLOCK):  # a constant trip count: numba vectorises it
                            dx = u - (x0 + base + lane + 0.5)
                            power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                            block_powers[lane] = power
                            block |= np.uint64(not (power > 0.0 or power < power_min)) << np.uint64(lane)
                        inside |= block << np.uint64(base)
                    inside &= lanes
                    row = ly * tw
                    while inside != 0:
                        lx = np.int64(trailing_zeros(inside))
                        inside &= inside - np.uint64(1)
                        alpha = min(ALPHA_MAX, o * math.exp(power_of[lx]))
                        if alpha < ALPHA_MIN:
                            continue
                        pix = row + lx
                        t_now = trans[pix]
                        test_t = t_now * (1.0 - alpha)
                        # one test for both rare events: T falls below T_MIN (the pixel is done), or,
                        # with the median, to MEDIAN_T or below for the first time (T only falls, so
                        # t_now > MEDIAN_T until then); next_t then drops to T_STOP
                        if test_t <= next_t[pix]:
                            if test_t < T_MIN:
                                active[ly] &= ~(np.uint64(1) << np.uint64(lx))
                                n_active -= 1
                                continue
                            med[pix] = g
                            next_t[pix] = T_STOP
                        if k > 0:
                            offer_topk(wbuf, wbits, sbuf, count, evict, pix, alpha * t_now, seq)
                        trans[pix] = test_t
                if n_active == 0:
                    break
            tile_list = tile_ids[first:last]
            for ly in range(th):
                py = y0 + ly
                for lx in range(tw):
                    px = x0 + lx
                    p = ly * tw + lx
                    write_ranked(wbuf, sbuf, count[p], p, tile_list, out_ids, out_weights, py, px, ranked)
                    out_alpha[py, px] = 1.0 - trans[p]
                    if with_median:
                        out_median[py, px] = med[p]


@njit(parallel=True, cache=True, error_model="numpy")
def sh_colors(sh, means, centre, valid, c1, c2, c3, out):  # pragma: no cover - numba
    """out[i] = max(0, 0.5 + Σ_k sh[i, k]·Y_k(d_i)) for valid Gaussians, d_i = normalize(means[i] − centre)
    (d_i = 0 at the centre itself), 0 elsewhere: raster.eval_sh per Gaussian, its basis in 3DGS's order and
    signs and its sum in the same order (k = 0, 1, ...), in float64.

    sh: [N, K, 3] float32, K = 1, 4, 9 or 16. means: [N, 3] float64. centre: [3] float64. valid: [N] bool.
    c1: float; c2: [5]; c3: [7] float64 (raster.SH_C1, SH_C2, SH_C3). out: [N, 3] float32, overwritten.
    """
    n, num_coeffs = sh.shape[0], sh.shape[1]
    c0 = 0.28209479177387814
    for i in prange(n):
        if not valid[i]:
            out[i, 0] = 0.0
            out[i, 1] = 0.0
            out[i, 2] = 0.0
            continue
        dx, dy, dz = means[i, 0] - centre[0], means[i, 1] - centre[1], means[i, 2] - centre[2]
        norm = math.sqrt(dx * dx + dy * dy + dz * dz)
        if norm > 0:
            dx, dy, dz = dx / norm, dy / norm, dz / norm
        basis = np.empty(16)
        basis[0] = c0
        if num_coeffs > 1:
            basis[1], basis[2], basis[3] = -c1 * dy, c1 * dz, -c1 * dx
        if num_coeffs > 4:
            xx, yy, zz = dx * dx, dy * dy, dz * dz
            basis[4] = c2[0] * dx * dy
            basis[5] = c2[1] * dy * dz
            basis[6] = c2[2] * (2 * zz - xx - yy)
            basis[7] = c2[3] * dx * dz
            basis[8] = c2[4] * (xx - yy)
            if num_coeffs > 9:
                basis[9] = c3[0] * dy * (3 * xx - yy)
                basis[10] = c3[1] * dx * dy * dz
                basis[11] = c3[2] * dy * (4 * zz - xx - yy)
                basis[12] = c3[3] * dz * (2 * zz - 3 * xx - 3 * yy)
                basis[13] = c3[4] * dx * (4 * zz - xx - yy)
                basis[14] = c3[5] * dz * (xx - yy)
                basis[15] = c3[6] * dx * (xx - 3 * yy)
        for ch in range(3):
            value = 0.5
            for k in range(num_coeffs):
                value += basis[k] * np.float64(sh[i, k, ch])
            out[i, ch] = max(value, 0.0)


# ----------------------------------------------------------------------------- the near plane's band
# Which Gaussians one near plane draws and a deeper one does not (drsplat.raster.near_band): their camera depth z is
# summed exactly as project_points sums its pz, so the band's edges are the projection's own.


@njit(parallel=True, cache=True)
def depth_band_counts(means: np.ndarray, rot_z: np.ndarray, trans_z: np.ndarray, lo: float, hi: float, counts: np.ndarray) -> None:
    """counts[c] = #{g : lo ≤ z_cg < hi}, z_cg = rot_z[c, 0]·x_g + rot_z[c, 1]·y_g + rot_z[c, 2]·z_g + trans_z[c].

    means: [N, 3] float64; rot_z: [C, 3] the cameras' third rotation rows; trans_z: [C]; counts: [C] int64.
    A NaN depth is in no band."""
    for c in prange(rot_z.shape[0]):
        r0, r1, r2, t = rot_z[c, 0], rot_z[c, 1], rot_z[c, 2], trans_z[c]
        n = 0
        for g in range(means.shape[0]):
            z = r0 * means[g, 0] + r1 * means[g, 1] + r2 * means[g, 2] + t
            if lo <= z < hi:
                n += 1
        counts[c] = n


@njit(parallel=True, cache=True)
def depth_band_fill(means: np.ndarray, rot_z: np.ndarray, trans_z: np.ndarray, lo: float, hi: float, starts: np.ndarray,
                    out_ids: np.ndarray) -> None:
    """out_ids[starts[c]:starts[c + 1]] = the g of `depth_band_counts`' band of camera c, in increasing order."""
    for c in prange(rot_z.shape[0]):
        r0, r1, r2, t = rot_z[c, 0], rot_z[c, 1], rot_z[c, 2], trans_z[c]
        k = starts[c]
        for g in range(means.shape[0]):
            z = r0 * means[g, 0] + r1 * means[g, 1] + r2 * means[g, 2] + t
            if lo <= z < hi:
                out_ids[k] = g
                k += 1


@njit(cache=True)
def any_at_depth(means: np.ndarray, rot_z: np.ndarray, trans_z: np.ndarray, near: float) -> bool:
    """Whether some camera c has some Gaussian g at z_cg ≥ near, z_cg summed as `depth_band_counts` sums it (means
    float32 or float64: a float32 is widened exactly, so the sums are the same bits). Stops at the first such pair,
    which a scene its cameras see finds at once; only a scene no camera can draw costs every pair."""
    for g in range(means.shape[0]):
        x, y, z = np.float64(means[g, 0]), np.float64(means[g, 1]), np.float64(means[g, 2])
        for c in range(rot_z.shape[0]):
            if rot_z[c, 0] * x + rot_z[c, 1] * y + rot_z[c, 2] * z + trans_z[c] >= near:
                return True
    return False
