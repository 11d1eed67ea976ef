"""numba kernels of drsplat.scene: each Gaussian's unit quaternion and R diag(s)² Rᵀ.

Their numpy forms stay beside them in drsplat.scene (`unit_quats64_reference`,
`covariances_reference`, `precisions_reference`), and tests/test_scene.py checks that the two
agree on random and hostile rows. The kernels exist because numpy spends ~0.3 s on these for a
542k-Gaussian scene (nine [N] temporaries for the rotation, then a 3x3 product per Gaussian),
which every registration pays twice (the renderer's covariances, the floater test's precisions).
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(parallel=True, cache=True)
def unit_quats64_kernel(q, out):  # pragma: no cover - jitted
    """out[i] = q[i] / ‖q[i]‖ in float64, (1, 0, 0, 0) where ‖q[i]‖ is not > 0 (zero or NaN).

    q: [N, 4] float32 (or float64) (w, x, y, z); out: [N, 4] float64. The norm is √(((w² + x²) + y²) + z²),
    the order numpy's row reduction adds in, so the rows are numpy's bits.
    """
    for i in numba.prange(q.shape[0]):
        w, x, y, z = np.float64(q[i, 0]), np.float64(q[i, 1]), np.float64(q[i, 2]), np.float64(q[i, 3])
        s = 0.0
        s += w * w
        s += x * x
        s += y * y
        s += z * z
        norm = math.sqrt(s)
        if norm > 0.0:
            out[i, 0], out[i, 1], out[i, 2], out[i, 3] = w / norm, x / norm, y / norm, z / norm
        else:
            out[i, 0], out[i, 1], out[i, 2], out[i, 3] = 1.0, 0.0, 0.0, 0.0


@numba.njit(inline="always")
def _frame_product(q, s, i, zero_nonfinite):  # pragma: no cover - jitted
    """(xx, xy, xz, yy, yz, zz) of M Mᵀ, M = R(q[i]) diag(s[i]) (`scaled_frames_kernel`)."""
    w, x, y, z = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
    s0, s1, s2 = s[i, 0], s[i, 1], s[i, 2]
    m00, m01, m02 = (1 - 2 * (y * y + z * z)) * s0, (2 * (x * y - w * z)) * s1, (2 * (x * z + w * y)) * s2
    m10, m11, m12 = (2 * (x * y + w * z)) * s0, (1 - 2 * (x * x + z * z)) * s1, (2 * (y * z - w * x)) * s2
    m20, m21, m22 = (2 * (x * z - w * y)) * s0, (2 * (y * z + w * x)) * s1, (1 - 2 * (x * x + y * y)) * s2
    e00 = _dot3(m00, m01, m02, m00, m01, m02)
    e01 = _dot3(m00, m01, m02, m10, m11, m12)
    e02 = _dot3(m00, m01, m02, m20, m21, m22)
    e11 = _dot3(m10, m11, m12, m10, m11, m12)
    e12 = _dot3(m10, m11, m12, m20, m21, m22)
    e22 = _dot3(m20, m21, m22, m20, m21, m22)
    if zero_nonfinite and not (math.isfinite(e00) and math.isfinite(e01) and math.isfinite(e02)
                               and math.isfinite(e11) and math.isfinite(e12) and math.isfinite(e22)):
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    return e00, e01, e02, e11, e12, e22


@numba.njit(inline="always")
def _dot3(a0, a1, a2, b0, b1, b2):  # pragma: no cover - jitted
    """((0 + a0 b0) + a1 b1) + a2 b2: the order numpy's small matrix product loop adds in (products
    commute bit for bit, so entry (b, a) is entry (a, b))."""
    acc = 0.0
    acc += a0 * b0
    acc += a1 * b1
    acc += a2 * b2
    return acc


@numba.njit(parallel=True, cache=True)
def scaled_frames_kernel(q, s, zero_nonfinite, out):  # pragma: no cover - jitted
    """out[i] = M Mᵀ with M = R(q[i]) diag(s[i]): Σ for s = the scales, Σ⁻¹ for s = their inverses.

    q: [N, 4] float64 unit quaternions (w, x, y, z); s: [N, 3] float64; out: [N, 3, 3] float64.
    R is `scene.quat_to_rotmat`'s formula, M's column j is R's scaled by s_j, and each entry is
    ((0 + m_a0 m_b0) + m_a1 m_b1) + m_a2 m_b2. zero_nonfinite: a row with any non-finite entry
    becomes 0 (precisions: such Gaussians are not rendered).
    """
    for i in numba.prange(q.shape[0]):
        e00, e01, e02, e11, e12, e22 = _frame_product(q, s, i, zero_nonfinite)
        out[i, 0, 0], out[i, 0, 1], out[i, 0, 2] = e00, e01, e02
        out[i, 1, 0], out[i, 1, 1], out[i, 1, 2] = e01, e11, e12
        out[i, 2, 0], out[i, 2, 1], out[i, 2, 2] = e02, e12, e22


@numba.njit(parallel=True, cache=True)
def packed_frames_kernel(q, s, zero_nonfinite, out):  # pragma: no cover - jitted
    """`scaled_frames_kernel` with out: [N, 6] float64 (xx, xy, xz, yy, yz, zz)."""
    for i in numba.prange(q.shape[0]):
        out[i, 0], out[i, 1], out[i, 2], out[i, 3], out[i, 4], out[i, 5] = _frame_product(q, s, i, zero_nonfinite)


@numba.njit(parallel=True, cache=True)
def bounded_rows_kernel(a, limit, signed, out):  # pragma: no cover - jitted
    """out[i] &= |a[i, j]| ≤ limit (signed: a[i, j] ≤ limit) for every j; NaN never is, and with
    limit = the float64 maximum the test is "every entry finite". a: [N, C] (any float type); out: [N] bool."""
    for i in numba.prange(a.shape[0]):
        ok = out[i]
        for j in range(a.shape[1]):
            v = np.float64(a[i, j])
            ok = ok and (v if signed else abs(v)) <= limit
        out[i] = ok


@numba.njit(parallel=True, cache=True)
def _transpose_kernel(src, out):  # pragma: no cover - jitted
    """out [B, A] = src [A, B] transposed (src of any strides: a run of a PLY record's fields), in
    parallel over blocks of 64 rows of src, whose B entries stay in cache while out's rows are written."""
    rows, cols = src.shape
    for b in numba.prange((rows + 63) // 64):
        for j in range(cols):
            for i in range(b * 64, min(rows, b * 64 + 64)):
                out[j, i] = src[i, j]


def transpose_copy(src: np.ndarray) -> np.ndarray:
    """A C-contiguous copy of src.T for src [A, B] of any strides (`_transpose_kernel`; numpy's
    `np.ascontiguousarray(src.T)` is the reference: the same array)."""
    out = np.empty((src.shape[1], src.shape[0]), src.dtype)
    if out.size:
        _transpose_kernel(src, out)
    return out


@numba.njit(parallel=True, cache=True)
def _gather_rows_kernel(src, ids, out):  # pragma: no cover - jitted
    """out[i] = src[ids[i]] for [N, C] src, in parallel over the rows."""
    for i in numba.prange(ids.shape[0]):
        g = ids[i]
        for c in range(src.shape[1]):
            out[i, c] = src[g, c]


def gather_rows(a: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """a[ids] for a C-contiguous [N, ...] array (no float16: numba has no such type) and [V] ids in
    range, in parallel (`_gather_rows_kernel`). numpy's fancy indexing of short rows took ~50 ns a
    row here: a culled flowers view's 35 % subset 9.4 ms against 1.6, a view's [N, 4] tile
    rectangles in depth order ~12 ms against 0.24."""
    flat = a.reshape(a.shape[0], int(np.prod(a.shape[1:], dtype=np.int64)))  # -1 fails on 0 rows
    out = np.empty((ids.shape[0], flat.shape[1]), a.dtype)
    if out.size:
        _gather_rows_kernel(flat, np.ascontiguousarray(ids, np.int64), out)
    return out.reshape((ids.shape[0],) + a.shape[1:])


BALL_BLOCK = 1 << 16  # rows a partial sum of `ball_sums_kernel` holds: fixed, so the sums do not depend on the threads


@numba.njit(parallel=True, cache=True)
def ball_distances_kernel(means, centre, max_coordinate, out):  # pragma: no cover - jitted
    """out[i] = float32(|means[i] − centre|²), the square summed in float64 as ((dx² + dy²) + dz²); +inf for a row
    not finite or beyond ±max_coordinate (not counted). means: [N, 3] float32 or float64; centre: [3] float64."""
    for i in numba.prange(means.shape[0]):
        x, y, z = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
        if abs(x) <= max_coordinate and abs(y) <= max_coordinate and abs(z) <= max_coordinate:
            dx, dy, dz = x - centre[0], y - centre[1], z - centre[2]
            out[i] = np.float32((dx * dx + dy * dy) + dz * dz)
        else:
            out[i] = np.inf


@numba.njit(parallel=True, cache=True)
def ball_sums_kernel(means, dist, limit, out):  # pragma: no cover - jitted
    """out = (Σx, Σy, Σz, count) over the rows with dist[i] ≤ limit (float32), as float64: a partial sum per block
    of BALL_BLOCK rows (in row order), the blocks then added in order, so the result does not depend on the threads."""
    blocks = (means.shape[0] + BALL_BLOCK - 1) // BALL_BLOCK
    parts = np.zeros((blocks, 4))
    for b in numba.prange(blocks):
        for i in range(b * BALL_BLOCK, min((b + 1) * BALL_BLOCK, means.shape[0])):
            if dist[i] <= limit:
                parts[b, 0] += np.float64(means[i, 0])
                parts[b, 1] += np.float64(means[i, 1])
                parts[b, 2] += np.float64(means[i, 2])
                parts[b, 3] += 1.0
    out[:] = 0.0
    for b in range(blocks):
        for j in range(4):
            out[j] += parts[b, j]
