"""Exact frustum culling: which Gaussians a view can possibly rasterize, found through blocks.

`SpatialIndex.build` (once per scene) sorts the finite Gaussians by the Morton code of their means
and cuts them into blocks of `block_size`; each block keeps the bounding box of its means and the
largest trace of its covariances. `SpatialIndex.visible(camera)` returns the ascending ids of the
Gaussians of every block that can meet the view; the view then projects only those (a view's
cost follows what it sees, not the scene's size).

Why it never drops a Gaussian the rasterizer would use (drsplat.raster): a Gaussian contributes
to a pixel only when its camera z ≥ near and its getRect tile rectangle is not empty, i.e. along
x, with screen position u = fx·x/z + cx, integer radius r and G tiles of B pixels,
u + r ≥ 1 and u - r < G·B (similarly along y). The radius is r = ceil(3·sqrt(λ)) with
λ = mid + sqrt(max(0.1, mid² - det)) ≤ λ_max(J Σ Jᵀ) + 0.3 + sqrt(0.1), and since J's rows are
(f/z)·(1, 0, -t) with |t| clamped to the rasterizer's 1.3x field-of-view limit L,

    λ_max(J Σ Jᵀ) ≤ ‖J‖_F² · λ_max(Σ) ≤ (fx²(1 + Lx²) + fy²(1 + Ly²)) / z² · trace(Σ).

So over a block (means in a box, trace(Σ) ≤ s, z ≥ z_lo = max(near, the box's least z)) every
radius is at most R = 3·sqrt((fx²(1+Lx²) + fy²(1+Ly²))·s / z_lo² + 0.3 + sqrt(0.1)) + 1, and a
Gaussian the rasterizer uses satisfies the five linear conditions z ≥ near,
x - z·(-R - 1 - cx)/fx ≥ 0, z·(G·B + R + 1 - cx)/fx - x ≥ 0 (and the two in y, with margins of
2 pixels against rounding). A block is culled only when all eight corners of its box fail one of
them: a linear function's maximum over a box is at a corner, so no point of the box passes.
Gaussians whose mean or covariance is not finite are never projected by the rasterizer either
(PreparedScene.finite), so they are left out of the index.

Keeping the surviving ids ascending keeps the rasterizer's ties (depth order is stable by id,
top-k ties keep the front first) exactly as without culling: tests/test_culling.py compares the
per-view top-k lists and the registered field's bytes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drsplat.cameras import Camera
from drsplat.raster import NEAR, TILE_SIZE, PreparedScene

DEFAULT_BLOCK = 2048
PIXEL_MARGIN = 2.0  # extra pixels on every image side against float rounding in the projection
BLUR_BOUND = 0.3 + np.sqrt(0.1)  # the low-pass blur plus the most the 0.1 floor adds to λ


def morton_codes(points: np.ndarray, bits: int = 21) -> np.ndarray:
    """[N] uint64 Morton (Z-order) codes of points [N, 3], quantised to 2^bits cells per axis of
    their bounding box: interleaving the bits keeps near points near in the code's order."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    scale = (2**bits - 1) / np.maximum(hi - lo, 1e-30)
    cells = np.clip(((points - lo) * scale).astype(np.uint64), 0, 2**bits - 1)
    code = np.zeros(points.shape[0], np.uint64)
    for bit in range(bits):
        for axis in range(3):
            code |= ((cells[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return code


@dataclass(frozen=True)
class SpatialIndex:
    """Blocks of Gaussians with bounding boxes (see the module docstring).

    order: [M] int64 ids of the indexed (finite) Gaussians, block by block. starts: [B + 1] int64
    block b holds order[starts[b]:starts[b + 1]]. lo, hi: [B, 3] float64 boxes of the means.
    max_trace: [B] float64 the largest trace(Σ) in each block. num_gaussians: N of the scene.
    """

    order: np.ndarray
    starts: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    max_trace: np.ndarray
    num_gaussians: int

    @classmethod
    def build(cls, geometry: PreparedScene, block_size: int = DEFAULT_BLOCK) -> SpatialIndex:
        """The index of `geometry` (its means [N, 3] and covariances [N, 3, 3])."""
        if block_size < 1:
            raise ValueError(f"block_size must be at least 1, got {block_size}")
        traces = np.trace(geometry.covariances, axis1=1, axis2=2)
        ok = geometry.finite & np.isfinite(geometry.means).all(axis=1) & np.isfinite(traces)
        ids = np.flatnonzero(ok)
        n = geometry.num_gaussians
        if ids.size == 0:
            empty = np.zeros((0, 3))
            return cls(ids.astype(np.int64), np.zeros(1, np.int64), empty, empty, np.zeros(0), n)
        means = geometry.means[ids]
        order = ids[np.argsort(morton_codes(means), kind="stable")].astype(np.int64)
        starts = np.append(np.arange(0, order.size, block_size), order.size).astype(np.int64)
        sorted_means = geometry.means[order]
        lo = np.minimum.reduceat(sorted_means, starts[:-1], axis=0)
        hi = np.maximum.reduceat(sorted_means, starts[:-1], axis=0)
        max_trace = np.maximum.reduceat(np.maximum(traces[order], 0.0), starts[:-1])
        return cls(order, starts, lo, hi, max_trace, n)

    @property
    def num_blocks(self) -> int:
        return int(self.starts.size - 1)

    def visible_blocks(self, camera: Camera, near: float = NEAR, tile_size: int = TILE_SIZE) -> np.ndarray:
        """[B] bool: blocks that can hold a Gaussian the rasterizer uses in `camera`'s view."""
        if self.num_blocks == 0:
            return np.zeros(0, bool)
        corners = np.stack([np.where(np.array([(c >> a) & 1 for a in range(3)], bool), self.hi, self.lo) for c in range(8)], axis=1)
        cam = corners @ np.asarray(camera.R, np.float64).T + np.asarray(camera.t, np.float64)  # [B, 8, 3]
        x, y, z = cam[..., 0], cam[..., 1], cam[..., 2]
        z_max = z.max(axis=1)
        z_lo = np.maximum(z.min(axis=1), near)
        w, h = camera.width, camera.height
        tan_x, tan_y = 0.5 * w / camera.fx, 0.5 * h / camera.fy
        lim_x = max((w - camera.cx) / camera.fx, camera.cx / camera.fx) + 0.3 * tan_x
        lim_y = max((h - camera.cy) / camera.fy, camera.cy / camera.fy) + 0.3 * tan_y
        gain = camera.fx**2 * (1 + lim_x**2) + camera.fy**2 * (1 + lim_y**2)
        radius = 3.0 * np.sqrt(gain * self.max_trace / (z_lo * z_lo) + BLUR_BOUND) + 1.0 + PIXEL_MARGIN
        radius = radius[:, None]
        grid_w = -(-w // tile_size) * tile_size
        grid_h = -(-h // tile_size) * tile_size
        # u ≥ -radius ⇔ x - z·(-radius - cx)/fx ≥ 0 (z > 0); u ≤ grid_w + radius likewise
        left = (x - z * (-radius - camera.cx) / camera.fx).max(axis=1) >= 0
        right = (z * (grid_w + radius - camera.cx) / camera.fx - x).max(axis=1) >= 0
        top = (y - z * (-radius - camera.cy) / camera.fy).max(axis=1) >= 0
        bottom = (z * (grid_h + radius - camera.cy) / camera.fy - y).max(axis=1) >= 0
        return (z_max >= near) & left & right & top & bottom

    def visible(self, camera: Camera, near: float = NEAR, tile_size: int = TILE_SIZE) -> np.ndarray:
        """[V] int64 ascending ids of the Gaussians in the blocks `camera` can see."""
        blocks = np.flatnonzero(self.visible_blocks(camera, near, tile_size))
        if blocks.size == 0:
            return np.zeros(0, np.int64)
        parts = [self.order[self.starts[b]:self.starts[b + 1]] for b in blocks]
        return np.sort(np.concatenate(parts))


def subset_geometry(geometry: PreparedScene, ids: np.ndarray) -> PreparedScene:
    """The Gaussians `ids` [V] of `geometry` (Gaussian i of the result is ids[i] of the scene)."""
    return PreparedScene(means=geometry.means[ids], covariances=geometry.covariances[ids], opacities=geometry.opacities[ids],
                         sh=geometry.sh[ids], finite=geometry.finite[ids])


def remap_ids(local_ids: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Per-pixel ids of a culled render [H, W, k] (-1 where empty) as scene ids, in place."""
    hit = local_ids >= 0
    local_ids[hit] = ids[local_ids[hit]].astype(local_ids.dtype)
    return local_ids
