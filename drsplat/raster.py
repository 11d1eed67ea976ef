"""Tile rasterizer of 3DGS scenes that keeps, per pixel, the top-k Gaussians by blending weight.

Conventions (shared with `drsplat.cameras.Camera.project`):
- OpenCV camera, x right, y down, z forward; world-to-camera x_c = R·x_w + t.
- Pixel (i, j) covers [i, i+1) x [j, j+1); its centre is (i + 0.5, j + 0.5) and a Gaussian's
  screen mean is (fx·x/z + cx, fy·y/z + cy). With cx = W/2 this is exactly 3DGS's ndc2Pix
  convention (3DGS evaluates at integer pixel coordinates with means shifted by -0.5) and
  gsplat's.
- 16 x 16 tiles. A Gaussian is binned into the tiles of 3DGS's getRect rectangle of its 3σ
  square (`_tile_rects`); like 3DGS, it contributes nothing to pixels of other tiles.
- Compositing is 3DGS's, front to back in increasing camera z (ties by Gaussian id):
  α = min(0.99, o·exp(-½ dᵀ Σ'⁻¹ d)), skipped when α < 1/255; with test_T = T·(1 - α), the pixel
  stops before adding a Gaussian that would make test_T < 1e-4. The weight of a contribution is
  w = T·α, so Σ w = 1 - T_final ≤ 1 - 1e-4.

Engines (`ENGINES`, chosen by `rasterize(..., engine=...)`): "numba" (`rasterize_numba`, the CPU
default), "reference" (`rasterize_reference`, numpy, per pixel) and "torch" (drsplat.raster_torch,
CPU or CUDA). All return the same `RasterOutput`; tests check that they agree (drsplat.testing).
"""

from __future__ import annotations

import dataclasses

import importlib
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numba
import numpy as np

from drsplat import _raster_kernels as kernels
from drsplat._scene_kernels import bounded_rows_kernel, gather_rows
from drsplat._sort_kernels import sort_by_key
from drsplat.cameras import Camera, render_camera_problem
from drsplat.scene import MAX_COORDINATE, MAX_LOG_SCALE, MAX_OPACITY_LOGIT, MAX_SH_COEFFICIENT, SH_C0, SH_COEFFICIENTS, GaussianScene
from drsplat.defaults import DEFAULT_TOPK, NEAR
from drsplat.utils import compiled_here, real_number, spread_rows

log = logging.getLogger(__name__)

TILE_SIZE = 16
BIN_CHUNKS_PER_THREAD = 8  # chunks of the depth order binned in parallel (load balance)
TILE_CHUNKS_PER_WORKER = 16  # runs of neighbouring tiles per compositing thread (`balance_tiles`; 8 left 4-6 % imbalance on flowers)
# A view's tile lists hold at most this many entries per Gaussian (with a floor for small scenes):
# a view that needs more (close-ups, views far larger than 640x480) is binned and composited in
# bands of tiles (`tile_bands`), so its lists stay within what drsplat.registration.plan counts.
TILE_ENTRIES_PER_GAUSSIAN = 8
MIN_TILE_ENTRIES = 1 << 22
TILE_ENTRY_BYTES = 4  # one int32 id
BLUR = kernels.BLUR
ALPHA_MIN = kernels.ALPHA_MIN
ALPHA_MAX = kernels.ALPHA_MAX
T_MIN = kernels.T_MIN
MEDIAN_T = kernels.MEDIAN_T

SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


@dataclass
class RasterOutput:
    """Per-pixel results of one view.

    ids: [H, W, k] int32 Gaussian ids, -1 where empty, sorted by descending weight (ties: front first).
    weights: [H, W, k] float32 blending weights w = T·α, 0 where empty.
    rgb: [H, W, 3] float32 Σ w·colour + T_final·background, or None.
    depth: [H, W] float32 expected camera z, Σ w·z / Σ w (0 where nothing contributes), or None.
    alpha: [H, W] float32 accumulated opacity 1 - T_final (= Σ of all weights, not only the top k).
    num_nonfinite: Gaussians dropped because an attribute or their projection was not finite.
    median_ids: [H, W] int32 the median Gaussian: the one whose contribution takes T from above ½
    to ≤ ½, i.e. where the summed weight of all contributions (not only the top k), front to
    back, reaches ½; -1 where it never does. depths[median_ids] is the median depth. Or None.
    """

    ids: np.ndarray
    weights: np.ndarray
    rgb: np.ndarray | None
    depth: np.ndarray | None
    alpha: np.ndarray
    num_nonfinite: int = 0
    median_ids: np.ndarray | None = None
    projected: Projected | None = None  # the view's projection (rasterize_topk), its arrays reused by a later call with out=
    # the scene ids of projected's rows when the renderer was handed a subset of the scene (registration's
    # culling, which remaps ids and median_ids to scene ids but not the projection); None: row i is Gaussian i
    projected_ids: np.ndarray | None = None
    tile_entries: int = 0  # entries of the view's tile lists, over all its bands (numba engine)


@dataclass
class PreparedScene:
    """View-independent arrays of a scene, computed once and reused for every view.

    means: [N, 3] float64. covariances: [N, 3, 3] float64 world Σ = R S Sᵀ Rᵀ.
    opacities: [N] float32 sigmoid(logit). sh: [N, K, 3] float32.
    finite: [N] bool, False where any attribute (or Σ) is not finite.
    """

    means: np.ndarray
    covariances: np.ndarray
    opacities: np.ndarray
    sh: np.ndarray
    finite: np.ndarray

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    @property
    def num_nonfinite(self) -> int:
        return int(self.finite.size - np.count_nonzero(self.finite))


def subset_geometry(geometry: PreparedScene, ids: np.ndarray) -> PreparedScene:
    """The Gaussians `ids` [V] of `geometry` (Gaussian i of the result is ids[i] of the scene), gathered
    in parallel (`gather_rows`; `subset_geometry_reference` is the numpy form, the same arrays)."""
    rows = (geometry.means, geometry.covariances, geometry.opacities, geometry.sh, geometry.finite)
    if not all(a.flags.c_contiguous for a in rows):
        return subset_geometry_reference(geometry, ids)
    means, covariances, opacities, sh, finite = (gather_rows(a, ids) for a in rows)
    return PreparedScene(means=means, covariances=covariances, opacities=opacities, sh=sh, finite=finite)


def subset_geometry_reference(geometry: PreparedScene, ids: np.ndarray) -> PreparedScene:
    """`subset_geometry` by numpy's fancy indexing."""
    return PreparedScene(means=geometry.means[ids], covariances=geometry.covariances[ids], opacities=geometry.opacities[ids],
                         sh=geometry.sh[ids], finite=geometry.finite[ids])


def tile_grid(width: int, height: int, tile_size: int = TILE_SIZE) -> tuple[int, int]:
    """(tiles in x, tiles in y) covering a width x height image: ceil(width / tile), ceil(height / tile)."""
    return -(-width // tile_size), -(-height // tile_size)


@dataclass
class Projected:
    """Screen-space Gaussians of one view (all arrays indexed by Gaussian id).

    means2d: [N, 2] float64 pixel coordinates (pixel centres at +0.5).
    conics: [N, 3] float64 (a, b, c) of Σ'⁻¹ = [[a, b], [b, c]].
    depths: [N] float32 camera z. radii: [N] int32 3σ screen radius (0 where invalid).
    opacities: [N] float32. valid: [N] bool, True for Gaussians that reach the image.
    tile_rects: [N, 4] int32 (tx0, ty0, tx1, ty1), end-exclusive tiles of each Gaussian.
    extents: [N, 2] float64 half-sizes of the box outside which α < 1/255, and qlimits: [N]
    float64 the bound on dᵀ Σ'⁻¹ d inside which α ≥ 1/255 is possible (kernel speed-up only).
    num_nonfinite: Gaussians dropped for non-finite attributes or projection; num_behind: z < near.
    colors: [N, 3] float32 SH colours for this view, or None.
    """

    means2d: np.ndarray
    conics: np.ndarray
    depths: np.ndarray
    radii: np.ndarray
    opacities: np.ndarray
    valid: np.ndarray
    tile_rects: np.ndarray
    extents: np.ndarray
    qlimits: np.ndarray
    colors: np.ndarray | None
    width: int
    height: int
    tile_size: int = TILE_SIZE
    num_nonfinite: int = 0
    num_behind: int = 0

    @property
    def tile_grid(self) -> tuple[int, int]:
        return tile_grid(self.width, self.height, self.tile_size)


def share_within_near_plane(means: np.ndarray, cameras: Sequence[Camera], sample: int = 100_000, near: float = NEAR) -> float:
    """The share of Gaussians that no view renders because their mean is nearer than `near` to every
    camera it lies in front of: 0 < z < near in some view and z < near in all (z the camera-space
    depth, `Camera.world_to_camera`; the projection culls z < near), estimated on every ⌈N / sample⌉-th
    Gaussian. A scene in other units than its cameras, or scaled down, has most of them there.

    means: [N, 3] world means; cameras: the views. Returns a share in [0, 1] (0 without Gaussians).
    """
    means = spread_rows(np.asarray(means, np.float64), sample)
    if len(means) == 0 or not cameras:
        return 0.0
    rendered, within = np.zeros(len(means), bool), np.zeros(len(means), bool)
    for cam in cameras:
        z = cam.world_to_camera(means)[:, 2]
        rendered |= z >= near
        within |= (z > 0) & (z < near)
    return float(np.mean(within & ~rendered))


def median_nearest_depth(means: np.ndarray, cameras: Sequence[Camera], sample: int = 100_000) -> float:
    """The median over Gaussians in front of some camera of their smallest camera-space depth z > 0
    over the views (`Camera.world_to_camera`), estimated on every ⌈N / sample⌉-th Gaussian: how far
    the capture's Gaussians lie from its cameras, in scene units; NaN when none lies in front.

    means: [N, 3] world means; cameras: the views."""
    means = spread_rows(np.asarray(means, np.float64), sample)
    nearest = np.full(len(means), np.inf)
    for cam in cameras:
        z = cam.world_to_camera(means)[:, 2]
        nearest = np.where(z > 0, np.minimum(nearest, z), nearest)
    nearest = nearest[np.isfinite(nearest)]
    return float(np.median(nearest)) if nearest.size else float("nan")


def plane_below(depth: float) -> float:
    """A near plane that draws Gaussians lying a median `depth` scene units from the cameras (`median_nearest_depth`):
    the power of ten at most a tenth of it, 10^⌊log₁₀(depth / 10)⌋ (depth in (1e-300, inf); below 1e-300 the power
    would pass float64's range)."""
    return 10.0 ** math.floor(math.log10(depth / 10.0))


def median_seen_depth(means: np.ndarray, cameras: Sequence[Camera], sample: int = 100_000) -> float:
    """The median over Gaussians some view sees (z > 0, the projection inside the image) of their smallest depth z over
    the views that see them, estimated on every ⌈N / sample⌉-th Gaussian: how far a capture's Gaussians lie from the
    cameras that look at them, in scene units; NaN when no view sees any. Unlike `median_nearest_depth`, a camera that
    does not look at a Gaussian (a ring of cameras inside a room, looking out: each Gaussian beside the cameras behind
    it) does not count (round 84b F1: 0.049 against 0.573 seen)."""
    means = spread_rows(np.asarray(means, np.float64), sample)
    nearest = np.full(len(means), np.inf)
    for cam in cameras:
        inside, z = cam.image_hits(means)
        nearest = np.where(inside & (z > 0), np.minimum(nearest, z), nearest)
    nearest = nearest[np.isfinite(nearest)]
    return float(np.median(nearest)) if nearest.size else float("nan")


def share_in_some_view(means: np.ndarray, cameras: Sequence[Camera], sample: int = 100_000, near: float = NEAR) -> float:
    """The share of Gaussians whose mean some view sees: z ≥ near and its projection inside the image
    (0 ≤ u < W, 0 ≤ v < H), estimated on every ⌈N / sample⌉-th Gaussian. A trained scene's training
    views see most of it; a scene in another frame than its cameras (a trainer's normalised world)
    has few seen, or none.

    means: [N, 3] world means; cameras: the views. Returns a share in [0, 1] (0 without Gaussians)."""
    means = spread_rows(np.asarray(means, np.float64), sample)
    if len(means) == 0 or not cameras:
        return 0.0
    seen = np.zeros(len(means), bool)
    for cam in cameras:
        inside, z = cam.image_hits(means)
        seen |= inside & (z >= near)
    return float(np.mean(seen))


@dataclass(frozen=True)
class NearBand:
    """The Gaussians of one view that a render with near plane `lo` draws and one with a deeper plane
    `hi` does not (`near_band`): count of them; tiles: the view's tiles that some of their getRect rectangles
    hold at lo (each counted once); grid: the view's tile count; ids: [count] int64, increasing, of the scene it
    was taken of, when asked for (`with_ids`), else None."""

    count: int
    tiles: int
    grid: int
    ids: np.ndarray | None = None

    @property
    def cover(self) -> float:
        """tiles / grid: the share of the view the band's Gaussians may draw on."""
        return self.tiles / self.grid if self.grid else 0.0


def _band_of(prep: PreparedScene, camera: Camera, ids: np.ndarray, lo: float, project, with_ids: bool) -> NearBand:
    """NearBand of `camera` from the candidates ids (lo ≤ z < hi), keeping those `project` (a projection function
    with project_gaussians' signature) draws at lo."""
    grid_x, grid_y = tile_grid(camera.width, camera.height)
    if ids.size == 0:
        return NearBand(0, 0, grid_x * grid_y, ids.astype(np.int64) if with_ids else None)
    projected = project(subset_geometry_reference(prep, ids), camera, lo)
    drawn = projected.valid
    per_tile = kernels.tile_entry_counts(np.ascontiguousarray(projected.tile_rects[drawn], np.int32), grid_x, grid_y)
    tiles = int(np.count_nonzero(per_tile))
    return NearBand(int(np.count_nonzero(drawn)), tiles, grid_x * grid_y, ids[drawn].astype(np.int64) if with_ids else None)


def _depth_rows(cameras: Sequence[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """([C, 3] the cameras' third rotation rows, [C] their third translations): a camera depth is z = R₂·x + t₂."""
    rot_z = np.ascontiguousarray([np.asarray(c.R, np.float64)[2] for c in cameras]).reshape(len(cameras), 3)
    return rot_z, np.array([float(np.asarray(c.t, np.float64)[2]) for c in cameras])


def near_band(scene: GaussianScene | PreparedScene, cameras: Sequence[Camera], lo: float, hi: float, with_ids: bool = False) -> list[NearBand]:
    """Per camera, the Gaussians a render at near plane lo draws and one at hi > lo does not: those of camera
    depth lo ≤ z < hi that the projection at lo keeps (`project_gaussians`' valid: usable, opacity ≥ 1/255,
    a finite footprint whose tile rectangle meets the image). z is the projection's own float64 sum
    (`kernels.depth_band_counts`), so the band's edges are exactly the planes': at hi every Gaussian of
    the band is behind. A numba pass over every (camera, Gaussian) pair counts the depths; then, one camera at a
    time, its candidates are listed and projected, so memory holds one camera's band (a scene in the band of every
    camera, one shrunk toward its cameras, would hold N x C ids at once). `near_band_reference` is the numpy form (the
    same bands).

    cameras: C views; with_ids: keep each band's ids (NearBand.ids). Returns C NearBands, in camera order."""
    if not 0 < lo < hi:
        raise ValueError(f"near_band: expected 0 < lo < hi, got {lo!r}, {hi!r}")
    cameras = list(cameras)  # read once (round 67a F6: a generator was used up by `_depth_rows`, as in `some_view_draws`)
    if not cameras:
        return []
    prep = prepare_scene(scene)
    rot_z, trans_z = _depth_rows(cameras)
    counts = np.zeros(len(cameras), np.int64)
    kernels.depth_band_counts(prep.means, rot_z, trans_z, float(lo), float(hi), counts)
    bands = []
    for c, cam in enumerate(cameras):
        ids = np.empty(int(counts[c]), np.int64)
        if ids.size:
            kernels.depth_band_fill(prep.means, rot_z[c:c + 1], trans_z[c:c + 1], float(lo), float(hi), np.array([0, ids.size]), ids)
        bands.append(_band_of(prep, cam, ids, lo, project_gaussians, with_ids))
    return bands


def near_band_reference(scene: GaussianScene | PreparedScene, cameras: Sequence[Camera], lo: float, hi: float,
                        with_ids: bool = False) -> list[NearBand]:
    """`near_band` in numpy: per camera, z = R₂₀·x + R₂₁·y + R₂₂·z + t₂ summed elementwise in that order,
    the candidates lo ≤ z < hi projected by `project_gaussians_reference` at lo."""
    prep = prepare_scene(scene)
    out = []
    for cam in cameras:
        rot, t = np.asarray(cam.R, np.float64), np.asarray(cam.t, np.float64)
        m = prep.means
        z = rot[2, 0] * m[:, 0] + rot[2, 1] * m[:, 1] + rot[2, 2] * m[:, 2] + t[2]
        out.append(_band_of(prep, cam, np.flatnonzero((z >= lo) & (z < hi)), lo, project_gaussians_reference, with_ids))
    return out


def some_view_draws(means: np.ndarray, cameras: Sequence[Camera], near: float = NEAR) -> bool:
    """Whether some camera has some mean at camera depth z ≥ near, the projection's own sum (`kernels.any_at_depth`):
    when not, no view can draw a Gaussian (every one is behind every camera or nearer than the plane), whatever the
    masks. means: [N, 3] (float32 or float64); `some_view_draws_reference` is the numpy form."""
    means = np.asarray(means)
    if means.ndim != 2 or means.shape[1] != 3:  # the kernel reads column 2 of every row unchecked (round 66c F2)
        raise ValueError(f"some_view_draws: means has shape {means.shape}; expected [N, 3]")
    cameras = list(cameras)  # read twice by _depth_rows: a generator would give no translations
    if len(means) == 0 or not cameras:
        return False
    rot_z, trans_z = _depth_rows(cameras)
    means = np.ascontiguousarray(means)
    if means.dtype not in (np.float32, np.float64):
        means = means.astype(np.float64)
    return bool(kernels.any_at_depth(means, rot_z, trans_z, float(near)))


def some_view_draws_reference(means: np.ndarray, cameras: Sequence[Camera], near: float = NEAR) -> bool:
    """`some_view_draws` in numpy: z = R₂₀·x + R₂₁·y + R₂₂·z + t₂ elementwise, in that order, for every camera."""
    m = np.asarray(means, np.float64)
    for cam in cameras:
        rot, t = np.asarray(cam.R, np.float64), np.asarray(cam.t, np.float64)
        if np.any(rot[2, 0] * m[:, 0] + rot[2, 1] * m[:, 1] + rot[2, 2] * m[:, 2] + t[2] >= near):
            return True
    return False


def sh_in_range(scene: GaussianScene) -> np.ndarray:
    """[N] bool: the Gaussians whose SH coefficients are all finite and within MAX_SH_COEFFICIENT;
    `prepare_scene` renders no other (a colour past float32's range would be infinite)."""
    n = scene.num_gaussians
    ok = np.ones(n, bool)
    bounded_rows_kernel(np.ascontiguousarray(scene.sh.reshape(n, 3 * scene.sh.shape[1])), MAX_SH_COEFFICIENT, False, ok)
    return ok


def in_render_range(scene: GaussianScene) -> np.ndarray:
    """[N] bool: the Gaussians whose SH coefficients pass `sh_in_range` and whose mean is finite and within
    MAX_COORDINATE on every axis; `prepare_scene` renders no other, nor the viewer's shader (its `splat_geometry`)."""
    ok = sh_in_range(scene)
    bounded_rows_kernel(np.ascontiguousarray(scene.means), MAX_COORDINATE, False, ok)
    return ok


SCENE_ARRAYS = ("means", "quats", "log_scales", "opacity_logits", "sh")


def widened_scene(scene: GaussianScene) -> GaussianScene:
    """`scene`, or a copy whose float16 arrays are float32 (the same values): numba loads no float16, and numpy
    would compute its exponentials and products in float16 (round 56a: a scene built with float16 SH raised
    NotImplementedError from the kernels)."""
    narrow = [name for name in SCENE_ARRAYS if np.asarray(getattr(scene, name)).dtype == np.float16]
    if not narrow:
        return scene
    return dataclasses.replace(scene, **{name: np.asarray(getattr(scene, name), np.float32) for name in narrow})


def faint_share(scene: GaussianScene) -> float:
    """The share of `scene`'s Gaussians with an opacity under ALPHA_MIN (1/255), which the rasterizer skips at every
    pixel as 3DGS's does: seen or not, they draw nothing and get no weight. 0 for a scene without Gaussians."""
    return float(np.mean(scene.opacities() < ALPHA_MIN)) if scene.num_gaussians else 0.0


def warn_unrendered(prepared: PreparedScene) -> None:
    """The one warning that `prepared` flags Gaussians it does not render, with what makes a Gaussian unusable."""
    if prepared.num_nonfinite:
        log.warning("%d of %d Gaussians have non-finite attributes (a NaN or infinite value, a log scale above %.1f whose scale "
                    "overflows float32, a mean beyond %.0e, or an SH coefficient beyond %.0e) and are not rendered",
                    prepared.num_nonfinite, prepared.num_gaussians, MAX_LOG_SCALE, MAX_COORDINATE, MAX_SH_COEFFICIENT)


def prepare_scene(scene: GaussianScene | PreparedScene, with_sh: bool = True, warn: bool = True) -> PreparedScene:
    """The view-independent arrays of `scene`; unusable Gaussians are flagged (`finite`) and counted.

    A Gaussian is usable when its mean, quaternion, log scales, opacity logit, SH coefficients and
    covariance are finite, its mean lies within MAX_COORDINATE of the origin on every axis (no
    camera is farther out, and a camera z past float32's range would be an infinite depth) and its
    SH coefficients within MAX_SH_COEFFICIENT (a colour past float32's range would be infinite).
    with_sh=False: the SH are still checked, not copied (sh becomes [N, 0, 3]: a registration
    renders no colour). warn: say how many are flagged (`warn_unrendered`); a caller that prepares a
    scene in parts, or a sample of it, says it once itself (round 89d F4: three times a registration).
    """
    if isinstance(scene, PreparedScene):
        return scene
    scene = widened_scene(scene)
    n = scene.num_gaussians
    finite = in_render_range(scene)
    everything = float(np.finfo(np.float64).max)
    # an infinite opacity logit is an opacity of 0 or 1, as the loader reads it (clamped to ±MAX_OPACITY_LOGIT): a scene
    # given in memory renders it as one loaded from a file does (round 89d F2: +inf was dropped here, the most opaque value)
    logits = np.clip(scene.opacity_logits, -MAX_OPACITY_LOGIT, MAX_OPACITY_LOGIT)
    for rows, limit in ((scene.quats, everything), (scene.log_scales, everything), (logits.reshape(n, 1), everything)):
        bounded_rows_kernel(np.ascontiguousarray(rows), limit, False, finite)
    cov = scene.covariances()
    bounded_rows_kernel(cov.reshape(n, 9), everything, False, finite)
    cov[~finite] = 0.0
    means = np.where(finite[:, None], scene.means, 0.0).astype(np.float64)
    opacities = np.where(finite, scene.opacities(), 0.0).astype(np.float32)
    sh = np.where(finite[:, None, None], scene.sh, 0.0).astype(np.float32) if with_sh else np.zeros((n, 0, 3), np.float32)
    prepared = PreparedScene(means=means, covariances=cov, opacities=opacities, sh=sh, finite=finite)
    if warn:
        warn_unrendered(prepared)
    return prepared


def sh_basis(dirs: np.ndarray, num_coeffs: int) -> list[np.ndarray]:
    """The first `num_coeffs` (1, 4, 9 or 16) real SH basis functions in 3DGS's order and signs.

    dirs: [N, 3] unit vectors. Returns a list of [N] float64 arrays (`sh_basis_xyz`).
    """
    x, y, z = (dirs[:, i].astype(np.float64) for i in range(3))
    return sh_basis_xyz(x, y, z, num_coeffs)


def sh_basis_xyz(x, y, z, num_coeffs: int) -> list:
    """`sh_basis` of the direction components x, y, z: [N] arrays of any array library (numpy, torch).

    C0; -C1·y, C1·z, -C1·x; C2·(xy, yz, 2z² - x² - y², xz, x² - y²); C3·(y(3x² - y²), xyz,
    y(4z² - x² - y²), z(2z² - 3x² - 3y²), x(4z² - x² - y²), z(x² - y²), x(x² - 3y²)).
    """
    basis = [x * 0.0 + SH_C0]
    if num_coeffs > 1:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if num_coeffs > 4:
        xx, yy, zz = x * x, y * y, z * z
        basis += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * x * z, SH_C2[4] * (xx - yy)]
    if num_coeffs > 9:
        basis += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return basis


def eval_sh(sh: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """RGB of spherical harmonics as 3DGS evaluates them (degree 0-3).

    sh: [N, K, 3] coefficients, K = (degree + 1)^2. dirs: [N, 3] unit view directions (camera
    centre -> Gaussian mean). Returns [N, 3] float64 max(0, Σ_i sh_i·Y_i(dir) + 0.5) with the
    basis Y of `sh_basis`.
    """
    result = np.full((sh.shape[0], 3), 0.5)
    for i, y_i in enumerate(sh_basis(dirs, sh.shape[1])):
        result += y_i[:, None] * sh[:, i]
    return np.maximum(result, 0.0)


def clamp_limits(camera: Camera) -> tuple[float, float, float, float]:
    """(x/z max, -(x/z) max, y/z max, -(y/z) max): the tangents at which the EWA Jacobian clamps a
    mean's direction, 1.3x the field of view around the principal point as 3DGS does (every
    engine's projection takes them from here, the numba and Triton kernels as arguments)."""
    w, h, fx, fy, cx, cy = camera.width, camera.height, float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)
    tan_x, tan_y = 0.5 * w / fx, 0.5 * h / fy
    return (w - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x, (h - cy) / fy + 0.3 * tan_y, cy / fy + 0.3 * tan_y


def _screen_covariances(cov3d: np.ndarray, pc: np.ndarray, camera: Camera) -> np.ndarray:
    """EWA splatting: Σ' = J W Σ Wᵀ Jᵀ + 0.3·I.

    cov3d: [M, 3, 3] world covariances. pc: [M, 3] camera-space means (z > 0). Returns [M, 3]
    (a, b, c) of Σ' = [[a, b], [b, c]]. W = camera R; J is the Jacobian of the pinhole projection
    at the mean, J = [[fx/z, 0, -fx·x/z²], [0, fy/z, -fy·y/z²]], with x/z and y/z clamped to
    1.3x the field of view as 3DGS does (gsplat's off-centre form), so that Gaussians far outside
    the image do not blow up. The 0.3 px² blur is 3DGS's low-pass filter.
    """
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg = clamp_limits(camera)
    tx = z * np.clip(x / z, -lim_x_neg, lim_x_pos)
    ty = z * np.clip(y / z, -lim_y_neg, lim_y_pos)
    rot = np.asarray(camera.R, np.float64)
    a0 = (camera.fx / z)[:, None] * rot[0] - (camera.fx * tx / (z * z))[:, None] * rot[2]
    a1 = (camera.fy / z)[:, None] * rot[1] - (camera.fy * ty / (z * z))[:, None] * rot[2]
    s0 = np.einsum("nij,nj->ni", cov3d, a0)
    s1 = np.einsum("nij,nj->ni", cov3d, a1)
    a = np.einsum("ni,ni->n", a0, s0) + BLUR
    b = np.einsum("ni,ni->n", a1, s0)
    c = np.einsum("ni,ni->n", a1, s1) + BLUR
    return np.stack([a, b, c], axis=1)


def _tile_rects(means2d: np.ndarray, radii: np.ndarray, width: int, height: int, tile_size: int) -> np.ndarray:
    """[M, 4] int32 (tx0, ty0, tx1, ty1), end-exclusive: 3DGS's getRect.

    With p = mean - 0.5 (3DGS's pixel coordinates, whose pixel centres are integers), r the
    integer radius, B the tile size and G the tile count along the axis:
    tx0 = clamp(floor((p - r) / B), 0, G), tx1 = clamp(floor((p + r + B - 1) / B), 0, G).
    (3DGS truncates with an int cast; after the clamp to ≥ 0 that is the floor.) A Gaussian whose
    rectangle is empty is culled.
    """
    rects = np.zeros((means2d.shape[0], 4), np.int32)
    for axis, size in ((0, width), (1, height)):
        grid = -(-size // tile_size)
        p = means2d[:, axis] - 0.5
        rects[:, axis] = np.clip(np.floor((p - radii) / tile_size), 0, grid)
        rects[:, axis + 2] = np.clip(np.floor((p + radii + tile_size - 1) / tile_size), 0, grid)
    return rects


def _usable(prep: PreparedScene, mask: np.ndarray | None) -> np.ndarray:
    if mask is None:
        return prep.finite
    mask = np.asarray(mask)
    if mask.shape != (prep.num_gaussians,) or mask.dtype != bool:
        raise ValueError(f"mask must be a bool array of shape ({prep.num_gaussians},), got {mask.dtype} {mask.shape}")
    return prep.finite & mask


def _empty_projected(n: int, camera: Camera, tile_size: int) -> Projected:
    return Projected(
        means2d=np.zeros((n, 2)),
        conics=np.zeros((n, 3)),
        depths=np.zeros(n, np.float32),
        radii=np.zeros(n, np.int32),
        opacities=np.zeros(n, np.float32),
        valid=np.zeros(n, bool),
        tile_rects=np.zeros((n, 4), np.int32),
        extents=np.zeros((n, 2)),
        qlimits=np.zeros(n),
        colors=None,
        width=int(camera.width),
        height=int(camera.height),
        tile_size=tile_size,
    )


def _projected_buffers(previous: Projected | None, n: int, camera: Camera, tile_size: int) -> Projected:
    """A Projected for n Gaussians on `previous`'s arrays where they can hold them (`_buffer`),
    new ones otherwise; the contents are left for project_points to overwrite."""
    if previous is None:
        return _empty_projected(n, camera, tile_size)
    return Projected(
        means2d=_buffer(previous.means2d, (n, 2), np.float64),
        conics=_buffer(previous.conics, (n, 3), np.float64),
        depths=_buffer(previous.depths, (n,), np.float32),
        radii=_buffer(previous.radii, (n,), np.int32),
        opacities=previous.opacities,
        valid=_buffer(previous.valid, (n,), np.bool_),
        tile_rects=_buffer(previous.tile_rects, (n, 4), np.int32),
        extents=_buffer(previous.extents, (n, 2), np.float64),
        qlimits=_buffer(previous.qlimits, (n,), np.float64),
        colors=None,
        width=int(camera.width),
        height=int(camera.height),
        tile_size=tile_size,
    )


def _add_colors(out: Projected, prep: PreparedScene, camera: Camera) -> None:
    """Projected.colors [N, 3]: SH evaluated for the direction camera centre -> mean (0 if not valid)."""
    idx = np.flatnonzero(out.valid)
    out.colors = np.zeros((prep.num_gaussians, 3), np.float32)
    dirs = prep.means[idx] - camera.center[None, :]
    norm = np.linalg.norm(dirs, axis=1, keepdims=True)
    out.colors[idx] = eval_sh(prep.sh[idx], dirs / np.where(norm > 0, norm, 1.0))


def _add_colors_numba(out: Projected, prep: PreparedScene, camera: Camera) -> None:
    """`_add_colors` by the numba kernel `sh_colors` (the same sums in the same order; 542k Gaussians of
    SH degree 2: 0.53 s a view in numpy)."""
    if prep.sh.shape[1] not in SH_COEFFICIENTS:  # the kernel's basis holds 16 terms, unchecked (round 66c F3: 25 read past it)
        raise ValueError(f"SH colours: {prep.sh.shape[1]} coefficients a colour channel; expected one of {SH_COEFFICIENTS} (degree 0-3)")
    if prep.sh.ndim != 3 or prep.sh.shape[0] != prep.num_gaussians or prep.sh.shape[2] != 3:  # read unchecked too (round 67a F7)
        raise ValueError(f"SH colours: sh has shape {prep.sh.shape}; expected [{prep.num_gaussians}, K, 3]")
    out.colors = np.empty((prep.num_gaussians, 3), np.float32)
    kernels.sh_colors(prep.sh, prep.means, np.asarray(camera.center, np.float64), out.valid, SH_C1, np.asarray(SH_C2), np.asarray(SH_C3),
                      out.colors)


def project_gaussians(
    scene: GaussianScene | PreparedScene,
    camera: Camera,
    near: float = NEAR,
    *,
    mask: np.ndarray | None = None,
    with_colors: bool = False,
    tile_size: int = TILE_SIZE,
    out: Projected | None = None,
) -> Projected:
    """Project every Gaussian into `camera` (numba; the math is `project_gaussians_reference`'s).

    out: a previous call's Projected whose arrays are reused (overwritten) when they can hold
    this scene: a view's projection writes ~70 bytes per Gaussian, and fresh arrays every view
    cost more in page faults than the projection itself (flowers, 542k Gaussians: 50 vs 11-18 ms
    per view, docs/raster.md).
    """
    prep = prepare_scene(scene)
    usable = _usable(prep, mask)
    n = prep.num_gaussians
    out = _projected_buffers(out, n, camera, tile_size)
    out.opacities = prep.opacities
    status = np.empty(n, np.int8)
    intrinsics = np.array([camera.fx, camera.fy, camera.cx, camera.cy, *clamp_limits(camera)], np.float64)
    kernels.project_points(
        prep.means, prep.covariances, prep.opacities, usable, np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64),
        intrinsics, out.width, out.height, float(near), tile_size,
        out.means2d, out.conics, out.depths, out.radii, out.tile_rects, out.extents, out.qlimits, status,
    )  # fmt: skip
    np.equal(status, kernels.VALID, out=out.valid)
    out.num_behind = int(np.count_nonzero(status == kernels.BEHIND))
    out.num_nonfinite = prep.num_nonfinite + int(np.count_nonzero(status == kernels.NONFINITE))
    if with_colors:
        _add_colors_numba(out, prep, camera)
    return out


def project_gaussians_reference(
    scene: GaussianScene | PreparedScene,
    camera: Camera,
    near: float = NEAR,
    *,
    mask: np.ndarray | None = None,
    with_colors: bool = False,
    tile_size: int = TILE_SIZE,
) -> Projected:
    """Project every Gaussian into `camera` (EWA splatting, as 3DGS's preprocess step; numpy).

    A Gaussian is valid when its attributes are finite, `mask` (if given, [N] bool) selects it,
    its camera z ≥ near, o ≥ 1/255 (otherwise α < 1/255 everywhere), Σ' is finite and positive
    definite, and its getRect tile rectangle (`_tile_rects`) is not empty. radius = ceil(3·sqrt(λ_max(Σ'))) with 3DGS's
    λ_max = mid + sqrt(max(0.1, mid² - det)). conic = Σ'⁻¹. qlimits and extents bound the
    ellipse dᵀ Σ'⁻¹ d ≤ q = 2·ln(255·o) outside which α < 1/255 (half-width sqrt(q·Σ'_xx)),
    slightly enlarged; they only tell the kernel which pixels to visit.
    """
    prep = prepare_scene(scene)
    usable = _usable(prep, mask)
    n = prep.num_gaussians
    rot, trans = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64)
    # the kernel's order of operations (r0·x + r1·y + r2·z + t, left to right): a matmul rounds otherwise, and a mean the
    # kernel puts on the near plane exactly (1e3 or more from the origin) was behind it here, or the reverse
    m = prep.means
    pc = np.stack([rot[i, 0] * m[:, 0] + rot[i, 1] * m[:, 1] + rot[i, 2] * m[:, 2] + trans[i] for i in range(3)], axis=1)
    depths = np.where(usable, pc[:, 2], 0.0)
    in_front = usable & (depths >= near)
    idx = np.flatnonzero(in_front & (prep.opacities >= ALPHA_MIN))
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        cov2d = _screen_covariances(prep.covariances[idx], pc[idx], camera)
        uv = np.stack([camera.fx * pc[idx, 0] / depths[idx] + camera.cx, camera.fy * pc[idx, 1] / depths[idx] + camera.cy], axis=1)
        a, b, c = cov2d[:, 0], cov2d[:, 1], cov2d[:, 2]
        det = a * c - b * b
        mid = 0.5 * (a + c)
        radius = np.ceil(3.0 * np.sqrt(mid + np.sqrt(np.maximum(0.1, mid * mid - det))))
        finite = np.isfinite(cov2d).all(axis=1) & np.isfinite(uv).all(axis=1) & np.isfinite(radius)
        conics = np.stack([c / det, -b / det, a / det], axis=1)
        q = np.maximum(2.0 * np.log(prep.opacities[idx].astype(np.float64) * 255.0), 0.0)
        extents = np.sqrt(q[:, None] * np.stack([a, c], axis=1)) * kernels.EXTENT_SCALE + kernels.EXTENT_PAD
    ok = finite & (det > 0)
    rects = np.zeros((idx.size, 4), np.int32)
    rects[ok] = _tile_rects(uv[ok], radius[ok], camera.width, camera.height, tile_size)
    ok &= (rects[:, 2] > rects[:, 0]) & (rects[:, 3] > rects[:, 1])

    out = _empty_projected(n, camera, tile_size)
    out.opacities = prep.opacities
    with np.errstate(over="ignore"):  # a depth past float32 (a mean near 3e38) is inf there, as the kernel's cast makes it
        out.depths = depths.astype(np.float32)
    out.num_nonfinite = prep.num_nonfinite + int(np.count_nonzero(~finite))
    out.num_behind = int(np.count_nonzero(usable & ~in_front))
    keep = idx[ok]
    out.valid[keep] = True
    out.means2d[keep] = uv[ok]
    out.conics[keep] = conics[ok]
    out.radii[keep] = np.minimum(radius[ok], 2**30).astype(np.int32)
    out.tile_rects[keep] = rects[ok]
    out.extents[keep] = extents[ok]
    out.qlimits[keep] = q[ok] * kernels.EXTENT_SCALE + kernels.EXTENT_PAD
    if with_colors:
        _add_colors(out, prep, camera)
    return out


def depth_order(projected: Projected) -> np.ndarray:
    """[M] int64 ids of the valid Gaussians, front to back (stable: ties keep id order).

    The float32 depths are mapped to uint32 keys that order as the floats do (`kernels.depth_keys`)
    and sorted with their ids by a least-significant-digit radix sort (`_sort_kernels.sort_by_key`:
    three stable passes of 11 bits, in parallel over chunks; a digit every key shares is skipped).
    The ids start in increasing order and every pass is stable, so ties keep it: the result is
    exactly `depth_order_reference`'s, without a comparison sort (numpy's sort of 440k keys took
    2 ms on one CPU of these machines and 21 ms on another).
    """
    idx = np.flatnonzero(projected.valid)
    keys = kernels.depth_keys(idx, np.asarray(projected.depths, np.float32).view(np.uint32))
    return sort_by_key(keys, idx.astype(np.int64))


def depth_order_reference(projected: Projected) -> np.ndarray:
    """Reference of `depth_order`: numpy's sort of the unique uint64 keys (depth bits << 32 | id),
    the depth bits mapped as in `kernels.depth_keys` (-0 counts as +0); the result equals a stable
    argsort of the float32 depths of the valid Gaussians."""
    idx = np.flatnonzero(projected.valid)
    depths = np.asarray(projected.depths[idx], np.float32) + np.float32(0.0)
    bits = depths.view(np.uint32)
    ordered = np.where(bits >> np.uint32(31), ~bits, bits | np.uint32(0x80000000))
    keys = (ordered.astype(np.uint64) << np.uint64(32)) | idx.astype(np.uint64)
    keys.sort()
    return (keys & np.uint64(0xFFFFFFFF)).astype(np.int64)


def _check_args(topk: int, background) -> np.ndarray:
    if topk < 0:
        raise ValueError(f"topk must be >= 0, got {topk}")
    bg = np.asarray(background, np.float64).reshape(-1)
    if bg.shape != (3,):
        raise ValueError(f"background must have 3 values, got {bg.shape[0]}")
    if not np.isfinite(bg).all():  # it filled the colours with NaN / inf, uncounted (round 98f F2)
        raise ValueError(f"background must be three finite values, got {bg.tolist()}")
    return bg


def _buffer(previous: np.ndarray | None, shape: tuple[int, ...], dtype) -> np.ndarray:
    """An array of `shape` and `dtype` on `previous`'s memory when it can hold it, else a new one:
    `previous` itself when it has that shape, else the first shape[0] rows of the array it is a view
    of (or is) when that has at least as many rows of shape[1:] (a smaller culled subset reuses a
    larger view's buffers). It must be writable and contiguous; the contents are whatever was there."""
    full = previous if previous is None or previous.base is None else previous.base
    if previous is not None and previous.shape == shape:
        full = previous
    if (isinstance(full, np.ndarray) and full.shape[1:] == tuple(shape[1:]) and full.ndim == len(shape) and full.shape[0] >= shape[0]
            and full.dtype == dtype and full.flags.c_contiguous and full.flags.writeable):
        return full if full.shape[0] == shape[0] else full[: shape[0]]
    return np.empty(shape, dtype)


def balance_tiles(entries: np.ndarray, n_workers: int, chunks_per_worker: int = TILE_CHUNKS_PER_WORKER) -> tuple[np.ndarray, np.ndarray]:
    """Split the tiles among `n_workers` threads so that each gets about the same work.

    entries: [n_tiles] tile list lengths. Returns tile_order [n_tiles] int64 and worker_starts
    [n_workers + 1] int64: worker w composites tile_order[worker_starts[w]:worker_starts[w + 1]].
    The tiles, in raster order, are cut into n_workers·chunks_per_worker runs of equal estimated
    cost (list length + 1, so that empty tiles are shared out too) and run c goes to worker
    c mod n_workers: runs keep neighbouring tiles (which share Gaussians, so cache lines) on one
    thread, and several runs per worker even out the error of the estimate across the image.
    numba's prange splits its range into equal contiguous blocks, so this split is the schedule.
    """
    n_workers = max(1, int(n_workers))
    n_chunks = n_workers * max(1, int(chunks_per_worker))
    cost = entries.astype(np.float64) + 1.0
    before = np.cumsum(cost) - cost
    chunk = np.minimum((before * (n_chunks / max(cost.sum(), 1.0))).astype(np.int64), n_chunks - 1)
    worker = chunk % n_workers
    tile_order = np.argsort(worker, kind="stable")
    worker_starts = np.zeros(n_workers + 1, np.int64)
    np.cumsum(np.bincount(worker, minlength=n_workers), out=worker_starts[1:])
    return tile_order, worker_starts


def render_projected(
    projected: Projected,
    topk: int = DEFAULT_TOPK,
    *,
    with_rgb: bool = False,
    with_depth: bool = False,
    with_median: bool = False,
    background=(0.0, 0.0, 0.0),
    out: RasterOutput | None = None,
    max_tile_entries: int | None = None,
) -> RasterOutput:
    """Bin projected Gaussians into tiles and composite them with the numba kernel.

    Lower-level entry of `rasterize` for callers that project once (or mask) themselves.
    out: a previous RasterOutput whose arrays are overwritten when their shapes match (saves
    allocating ~100 MB per 640x480 view at k = 40 when rendering many views); the returned
    RasterOutput then shares them. max_tile_entries: the most entries one band's tile lists may
    hold (default `tile_list_cap`); the output does not depend on it.
    """
    _check_args(topk, background)
    if with_rgb and projected.colors is None:
        raise ValueError("with_rgb needs Projected.colors (project_gaussians(..., with_colors=True))")
    return _composite_in_bands(projected, max_tile_entries, False, out, lambda offsets, tile_ids, band, out: composite_projected(
        projected, offsets, tile_ids, topk, with_rgb=with_rgb, with_depth=with_depth, with_median=with_median, background=background,
        out=out, tiles=band))


def composite_projected(
    projected: Projected,
    offsets: np.ndarray,
    tile_ids: np.ndarray,
    topk: int = DEFAULT_TOPK,
    *,
    with_rgb: bool = False,
    with_depth: bool = False,
    with_median: bool = False,
    background=(0.0, 0.0, 0.0),
    out: RasterOutput | None = None,
    tiles: tuple[int, int] | None = None,
) -> RasterOutput:
    """The compositing half of `render_projected`, on tile lists from `bin_tiles` (kernels.composite_tiles).
    tiles: (t_lo, t_hi), composite only those row-major tiles (a band's); the other pixels of `out` are left as they are."""
    bg = _check_args(topk, background)
    if with_rgb and projected.colors is None:
        raise ValueError("with_rgb needs Projected.colors (project_gaussians(..., with_colors=True))")
    h, w = projected.height, projected.width
    n_tiles_x = projected.tile_grid[0]
    ids = _buffer(None if out is None else out.ids, (h, w, topk), np.int32)
    weights = _buffer(None if out is None else out.weights, (h, w, topk), np.float32)
    rgb = _buffer(None if out is None else out.rgb, (h, w, 3) if with_rgb else (0, 0, 3), np.float32)
    depth = _buffer(None if out is None else out.depth, (h, w) if with_depth else (0, 0), np.float32)
    alpha = _buffer(None if out is None else out.alpha, (h, w), np.float32)
    median = _buffer(None if out is None else out.median_ids, (h, w) if with_median else (0, 0), np.int32)
    colors = projected.colors if with_rgb else np.zeros((0, 3), np.float32)
    tile_order, worker_starts = _band_schedule(offsets, tiles)
    kernels.composite_tiles(
        tile_order, worker_starts, offsets, tile_ids, projected.means2d, projected.conics, projected.opacities, projected.extents,
        projected.qlimits, projected.depths, colors, w, h, projected.tile_size, n_tiles_x, with_rgb, with_depth, with_median, bg,
        ids, weights, rgb, depth, alpha, median,
    )  # fmt: skip
    return RasterOutput(
        ids=ids,
        weights=weights,
        rgb=rgb if with_rgb else None,
        depth=depth if with_depth else None,
        alpha=alpha,
        num_nonfinite=projected.num_nonfinite,
        median_ids=median if with_median else None,
    )


def bin_tiles(projected: Projected, exact: bool = False, tiles: tuple[int, int] | None = None,
              order: np.ndarray | None = None, rects_in_order: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-tile lists of Gaussian ids, front to back: offsets [n_tiles + 1] int64, ids [offsets[-1]] int32.

    exact=False: every tile of each Gaussian's getRect rectangle (3DGS's rule, `render_projected`).
    exact=True: only those of its tiles that the α ≥ 1/255 ellipse meets (`bin_gaussians_exact`,
    Speedy-Splat's AccuTile); compositing then gives the same result, with fewer tile visits.
    tiles: (t_lo, t_hi), lists for those row-major tiles only (a band, `tile_bands`), the others empty.
    order: the view's `depth_order`, when the caller bins several bands (computed here when None);
    rects_in_order: projected.tile_rects[order], likewise (getRect tiles only; gathered here when None).
    """
    n_tiles_x, n_tiles_y = projected.tile_grid
    n_tiles = n_tiles_x * n_tiles_y
    t_lo, t_hi = (0, n_tiles) if tiles is None else tiles
    order = depth_order(projected) if order is None else order
    n_chunks = BIN_CHUNKS_PER_THREAD * numba.get_num_threads()
    if not exact:
        rects = gather_rows(projected.tile_rects, order) if rects_in_order is None else rects_in_order
        return kernels.bin_gaussians(order, rects, n_tiles_x, n_tiles, n_chunks, t_lo, t_hi, True)
    return kernels.bin_gaussians_exact(order, projected.tile_rects, projected.means2d, projected.conics, projected.extents, projected.qlimits,
                                       projected.tile_size, projected.height, n_tiles_x, n_tiles, n_chunks, t_lo, t_hi)


def tile_list_cap(num_gaussians: int) -> int:
    """The most entries one band's tile lists hold for a scene of `num_gaussians` Gaussians:
    TILE_ENTRIES_PER_GAUSSIAN per Gaussian, at least MIN_TILE_ENTRIES."""
    return max(MIN_TILE_ENTRIES, TILE_ENTRIES_PER_GAUSSIAN * int(num_gaussians))


def tile_bands(projected: Projected, max_entries: int | None = None) -> list[tuple[int, int]]:
    """The view's tiles cut into bands whose lists each hold at most `max_entries` entries
    (default `tile_list_cap` of the projection's Gaussians): [(t_lo, t_hi)], contiguous runs of
    row-major tiles covering every tile, cut greedily; one band (0, n_tiles) when the whole view fits.

    The lengths come from the getRect rectangles (`kernels.tile_entry_counts`, O(N), no list built);
    AccuTile's exact lists are no longer. A single tile whose list is longer than max_entries makes
    a band of its own (it cannot be cut: a tile's Gaussians blend in one depth order); with the
    default cap that never happens, since a tile holds each Gaussian at most once.
    """
    n_tiles_x, n_tiles_y = projected.tile_grid
    n_tiles = n_tiles_x * n_tiles_y
    cap = tile_list_cap(projected.means2d.shape[0]) if max_entries is None else int(max_entries)
    if cap < 1:
        raise ValueError(f"max_entries must be at least 1, got {cap}")
    if n_tiles == 0 or kernels.tile_entry_total(projected.tile_rects) <= cap:
        return [(0, n_tiles)]
    counts = kernels.tile_entry_counts(projected.tile_rects, n_tiles_x, n_tiles_y)
    bands, start, held = [], 0, 0
    for t, c in enumerate(counts.tolist()):
        if t > start and held + c > cap:
            bands.append((start, t))
            start, held = t, 0
        held += c
    bands.append((start, n_tiles))
    return bands


def _composite_in_bands(projected: Projected, max_tile_entries: int | None, exact: bool, out: RasterOutput | None,
                        composite: Callable[[np.ndarray, np.ndarray, tuple[int, int], RasterOutput | None], RasterOutput]) -> RasterOutput:
    """Bin and composite the view band by band (`tile_bands`): composite(offsets, tile_ids, band, out)
    fills the band's pixels of `out` (made by the first band when None) and returns it; the result
    says how many list entries all the bands held."""
    entries, bands = 0, tile_bands(projected, max_tile_entries)
    order, rects = _band_inputs(projected, bands, exact)
    for band in bands:
        offsets, tile_ids = bin_tiles(projected, exact=exact, tiles=band, order=order, rects_in_order=rects)
        out = composite(offsets, tile_ids, band, out)
        entries += tile_ids.shape[0]
    out.tile_entries = entries
    return out


def _band_inputs(projected: Projected, bands: list[tuple[int, int]], exact: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """The view's depth order and, for getRect tiles, its rectangles gathered in that order, made
    once for all its bands (each band then reads them in sequence; `gather_rows`, in parallel)."""
    order = depth_order(projected)
    if exact:
        return order, None
    return order, gather_rows(projected.tile_rects, order)


def _band_schedule(offsets: np.ndarray, tiles: tuple[int, int] | None) -> tuple[np.ndarray, np.ndarray]:
    """`balance_tiles` over the tiles of a band (all tiles when None): (tile_order, worker_starts)."""
    lengths = np.diff(offsets)
    if tiles is None:
        return balance_tiles(lengths, numba.get_num_threads())
    t_lo, t_hi = tiles
    order, starts = balance_tiles(lengths[t_lo:t_hi], numba.get_num_threads())
    return order + t_lo, starts


def composite_topk(
    projected: Projected,
    offsets: np.ndarray,
    tile_ids: np.ndarray,
    topk: int = DEFAULT_TOPK,
    *,
    with_median: bool = False,
    ranked: bool = True,
    out: RasterOutput | None = None,
    tiles: tuple[int, int] | None = None,
) -> RasterOutput:
    """Composite binned tiles (`bin_tiles`) keeping only ids, weights, alpha and (with_median) the median.

    The registration's compositor (kernels.composite_topk): float64, the same per-pixel rules
    as `render_projected`, without colour or depth. ranked=True: the same ids, weights, alpha and
    median bit for bit. ranked=False: each pixel's slots hold the same (id, weight) entries, in no
    particular order (the -1 / 0 padding still last); what registration needs, since it sums
    a pixel's entries per (Gaussian, mask) whatever their order, and it skips a sort per pixel.
    out: buffers to reuse, as in `render_projected`. tiles: (t_lo, t_hi), composite only those
    row-major tiles (a band's, `tile_bands`); the other pixels of `out` are left as they are.
    """
    _check_args(topk, (0.0, 0.0, 0.0))
    if projected.tile_size > kernels.MAX_TILE_LANES:
        raise ValueError(f"composite_topk keeps a tile row's pixels in one 64-bit mask: tile_size {projected.tile_size} "
                         f"is over {kernels.MAX_TILE_LANES}; use render_projected")
    h, w = projected.height, projected.width
    ids = _buffer(None if out is None else out.ids, (h, w, topk), np.int32)
    weights = _buffer(None if out is None else out.weights, (h, w, topk), np.float32)
    alpha = _buffer(None if out is None else out.alpha, (h, w), np.float32)
    median = _buffer(None if out is None else out.median_ids, (h, w) if with_median else (0, 0), np.int32)
    tile_order, worker_starts = _band_schedule(offsets, tiles)
    kernels.composite_topk(
        tile_order, worker_starts, offsets, tile_ids, projected.means2d, projected.conics, projected.opacities, projected.extents,
        projected.qlimits, w, h, projected.tile_size, projected.tile_grid[0], with_median, ranked, ids, weights, alpha, median,
    )  # fmt: skip
    return RasterOutput(ids=ids, weights=weights, rgb=None, depth=None, alpha=alpha, num_nonfinite=projected.num_nonfinite,
                        median_ids=median if with_median else None)


def render_topk(
    projected: Projected,
    topk: int = DEFAULT_TOPK,
    *,
    with_median: bool = False,
    ranked: bool = True,
    exact_tiles: bool = False,
    out: RasterOutput | None = None,
    max_tile_entries: int | None = None,
) -> RasterOutput:
    """`render_projected` for callers that need only the top-k ids and weights (registration):
    `bin_tiles(exact=exact_tiles)` then `composite_topk` (see there for `ranked`), band by band
    (`tile_bands`; max_tile_entries as in `render_projected`)."""
    return _composite_in_bands(projected, max_tile_entries, exact_tiles, out, lambda offsets, tile_ids, band, out: composite_topk(
        projected, offsets, tile_ids, topk, with_median=with_median, ranked=ranked, out=out, tiles=band))


def rasterize_topk(
    scene: GaussianScene | PreparedScene,
    camera: Camera,
    topk: int = DEFAULT_TOPK,
    *,
    with_rgb: bool = False,
    with_depth: bool = False,
    with_median: bool = False,
    background=(0.0, 0.0, 0.0),
    mask: np.ndarray | None = None,
    near: float = NEAR,
    out: RasterOutput | None = None,
    device: str = "cpu",
    ranked: bool = False,
) -> RasterOutput:
    """The registration's CPU rasterizer: `rasterize_numba` for the top-k lists only (`render_topk`).

    Same signature as rasterize, plus `ranked`; with_rgb / with_depth must be False (this path
    computes neither) and background is unused. By default (ranked=False) a pixel's k slots
    are the top-k entries in no particular order (`composite_topk`); ranked=True sorts them as
    every other engine does.
    """
    if with_rgb or with_depth:
        raise ValueError("rasterize_topk computes ids, weights, alpha and the median only; use rasterize for rgb or depth")
    _check_args(topk, background)
    check_near(near)
    check_camera(camera)
    _check_cpu("numba", device)
    projected = project_gaussians(scene, camera, near, mask=mask, out=None if out is None else out.projected)
    result = render_topk(projected, topk, with_median=with_median, ranked=ranked, out=out)
    result.projected = projected
    return result


def rasterize_numba(
    scene: GaussianScene | PreparedScene,
    camera: Camera,
    topk: int = DEFAULT_TOPK,
    *,
    with_rgb: bool = False,
    with_depth: bool = False,
    with_median: bool = False,
    background=(0.0, 0.0, 0.0),
    mask: np.ndarray | None = None,
    near: float = NEAR,
    out: RasterOutput | None = None,
    device: str = "cpu",
) -> RasterOutput:
    """Render one view and keep the top-k Gaussians of every pixel (numba engine).

    scene: a GaussianScene or, to skip per-scene work on every view, `prepare_scene(scene)`.
    mask: [N] bool restricts rendering to a subset of Gaussians (ids stay scene ids).
    out: buffers of a previous call to reuse (see `render_projected`).
    Returns a RasterOutput of camera.height x camera.width pixels (see the module docstring for
    the compositing rules).
    """
    _check_args(topk, background)
    _check_cpu("numba", device)
    projected = project_gaussians(scene, camera, near, mask=mask, with_colors=with_rgb)
    return render_projected(projected, topk, with_rgb=with_rgb, with_depth=with_depth, with_median=with_median,
                            background=background, out=out)


def composite_reference(
    projected: Projected,
    topk: int = DEFAULT_TOPK,
    *,
    with_rgb: bool = False,
    with_depth: bool = False,
    with_median: bool = False,
    background=(0.0, 0.0, 0.0),
) -> RasterOutput:
    """Plain numpy compositing, one pixel at a time (slow; the reference for the kernel).

    For pixel (i, j) with centre p = (i + 0.5, j + 0.5): the candidates are the valid Gaussians
    whose tile rectangle holds the pixel's tile, in depth order. For each, d = mean2d - p,
    α = min(0.99, o·exp(-½ dᵀ Σ'⁻¹ d)); those with power > 0 or α < 1/255 are skipped; then
    front to back, test_T = T·(1 - α), stop if test_T < 1e-4, else w = T·α and T = test_T.
    The median Gaussian is the contribution after which T ≤ ½ for the first time.
    """
    bg = _check_args(topk, background)
    if with_rgb and projected.colors is None:
        raise ValueError("with_rgb needs Projected.colors (project_gaussians(..., with_colors=True))")
    h, w, ts = projected.height, projected.width, projected.tile_size
    order = depth_order(projected)
    rects = projected.tile_rects[order]
    out = RasterOutput(
        ids=np.full((h, w, topk), -1, np.int32),
        weights=np.zeros((h, w, topk), np.float32),
        rgb=np.zeros((h, w, 3), np.float32) if with_rgb else None,
        depth=np.zeros((h, w), np.float32) if with_depth else None,
        alpha=np.zeros((h, w), np.float32),
        num_nonfinite=projected.num_nonfinite,
        median_ids=np.full((h, w), -1, np.int32) if with_median else None,
    )
    tiles_x, tiles_y = projected.tile_grid
    for ty in range(tiles_y):
        for tx in range(tiles_x):
            cand = order[(rects[:, 0] <= tx) & (tx < rects[:, 2]) & (rects[:, 1] <= ty) & (ty < rects[:, 3])]
            for py in range(ty * ts, min((ty + 1) * ts, h)):
                for px in range(tx * ts, min((tx + 1) * ts, w)):
                    _composite_pixel(projected, cand, px, py, bg, out)
    return out


def _composite_pixel(projected: Projected, cand: np.ndarray, px: int, py: int, bg: np.ndarray, out: RasterOutput) -> None:
    """3DGS's compositing of pixel (px, py) over the candidates `cand` (ids in depth order)."""
    d = projected.means2d[cand] - np.array([px + 0.5, py + 0.5])
    a, b, c = projected.conics[cand].T
    power = -0.5 * (a * d[:, 0] * d[:, 0] + c * d[:, 1] * d[:, 1]) - b * d[:, 0] * d[:, 1]
    alphas = np.minimum(ALPHA_MAX, projected.opacities[cand].astype(np.float64) * np.exp(power))
    hit = (power <= 0) & (alphas >= ALPHA_MIN)
    t = 1.0
    median = -1
    contrib, contrib_w = [], []
    for g, al in zip(cand[hit], alphas[hit]):
        test_t = t * (1.0 - al)
        if test_t < T_MIN:
            break
        if test_t <= MEDIAN_T < t:
            median = int(g)
        contrib.append(g)
        contrib_w.append(al * t)
        t = test_t
    gs, ws = np.array(contrib, np.int64), np.array(contrib_w, np.float64)
    best = np.argsort(-ws, kind="stable")[: out.ids.shape[2]]
    out.ids[py, px, : best.size] = gs[best]
    out.weights[py, px, : best.size] = ws[best]
    out.alpha[py, px] = 1.0 - t
    if out.rgb is not None:
        out.rgb[py, px] = ws @ projected.colors[gs].astype(np.float64) + t * bg
    if out.depth is not None and 1.0 - t > 0:
        out.depth[py, px] = ws @ projected.depths[gs].astype(np.float64) / (1.0 - t)
    if out.median_ids is not None:
        out.median_ids[py, px] = median


def rasterize_reference(
    scene: GaussianScene | PreparedScene,
    camera: Camera,
    topk: int = DEFAULT_TOPK,
    *,
    with_rgb: bool = False,
    with_depth: bool = False,
    with_median: bool = False,
    background=(0.0, 0.0, 0.0),
    mask: np.ndarray | None = None,
    near: float = NEAR,
    out: RasterOutput | None = None,
    device: str = "cpu",
) -> RasterOutput:
    """`rasterize` with the plain numpy per-pixel compositor (for tests on tiny images; `out` is unused)."""
    _check_args(topk, background)
    _check_cpu("reference", device)
    projected = project_gaussians_reference(scene, camera, near, mask=mask, with_colors=with_rgb)
    return composite_reference(projected, topk, with_rgb=with_rgb, with_depth=with_depth, with_median=with_median,
                               background=background)


def _check_cpu(engine: str, device: str | None) -> None:
    if device not in (None, "cpu"):
        raise ValueError(f"the {engine} rasterizer runs on the CPU only, not on {device!r} (use engine='torch')")


@dataclass(frozen=True)
class Engine:
    """A rasterizer engine: `render` has `rasterize`'s signature (without `engine`); `prepare(scene,
    device)` returns what `render` takes as its scene fastest (done once per scene, reused per view).
    Both are "module:function" entry points imported on first use (torch loads only when asked for).
    topk: optionally, a faster `render` for ids, weights and the median only (registration)."""

    render: str
    prepare: str
    topk: str | None = None

    @staticmethod
    def _load(entry: str) -> Callable:
        module, name = entry.split(":")
        return getattr(importlib.import_module(module), name)

    def render_fn(self) -> Callable[..., RasterOutput]:
        return self._load(self.render)

    def prepare_fn(self) -> Callable:
        return self._load(self.prepare)

    def topk_fn(self) -> Callable[..., RasterOutput]:
        """The engine's renderer for callers that need only ids, weights and the median
        (registration): `topk` if the engine has one (numba: `rasterize_topk`, whose slots are
        unordered), else `render`."""
        return self._load(self.topk or self.render)


# The registry: a new engine is one module plus one line here.
ENGINES: dict[str, Engine] = {
    "numba": Engine("drsplat.raster:rasterize_numba", "drsplat.raster:_prepare_cpu", topk="drsplat.raster:rasterize_topk"),
    "reference": Engine("drsplat.raster:rasterize_reference", "drsplat.raster:_prepare_cpu"),
    "torch": Engine("drsplat.raster_torch:rasterize", "drsplat.raster_torch:prepare_scene_torch"),
}


def kernels_cached() -> bool:
    """Whether numba's cache already holds the compositor (`composite_topk`) for this machine (`utils.compiled_here`):
    False on a first run, which compiles the rasterizer's and registration's kernels (81 s of a 20-view registration on
    2 loaded cores, then 3.9 s: round 67c F6)."""
    return compiled_here(kernels.composite_topk)


def get_engine(name: str) -> Engine:
    """The registered engine `name` (ValueError naming the choices otherwise)."""
    try:
        return ENGINES[name]
    except KeyError:
        raise ValueError(f"unknown rasterizer engine {name!r}; choose one of {', '.join(ENGINES)}") from None


def _prepare_cpu(scene: GaussianScene | PreparedScene, device: str = "cpu") -> PreparedScene:
    _check_cpu("numba", device)
    return prepare_scene(scene)


def prepare_for_engine(scene, engine: str = "numba", device: str = "cpu"):
    """`scene` made ready for many `rasterize(..., engine=engine, device=device)` calls
    (a PreparedScene for the CPU engines, tensors on `device` for torch)."""
    return get_engine(engine).prepare_fn()(scene, device)


def check_near(near) -> None:
    """ValueError unless `near` is a positive, finite camera depth (round 98f F2: near = -2 drew a Gaussian behind the
    camera mirrored through its centre, near = 0 counted one at z = 0 non-finite; the command line and RegisterOptions
    refuse them, the library took them)."""
    plane = real_number(near)
    if not (math.isfinite(plane) and plane > 0):
        raise ValueError(f"near: expected a positive, finite camera depth in scene units, got {near!r}")


def check_camera(camera: Camera) -> None:
    """ValueError naming the camera and what is wrong with it (`cameras.render_camera_problem`), the same for every engine."""
    problem = render_camera_problem(camera)
    if problem is not None:
        raise ValueError(f"camera{' ' + repr(camera.name) if camera.name else ''}: {problem}")


def rasterize(
    scene,
    camera: Camera,
    topk: int = DEFAULT_TOPK,
    *,
    with_rgb: bool = False,
    with_depth: bool = False,
    with_median: bool = False,
    background=(0.0, 0.0, 0.0),
    mask: np.ndarray | None = None,
    near: float = NEAR,
    out: RasterOutput | None = None,
    engine: str = "numba",
    device: str = "cpu",
) -> RasterOutput:
    """Render one view and keep the top-k Gaussians of every pixel, with the engine `engine`.

    scene: a GaussianScene or, to skip per-scene work on every view, `prepare_for_engine(scene,
    engine, device)` (for numba: `prepare_scene(scene)`).
    mask: [N] bool restricts rendering to a subset of Gaussians (ids stay scene ids).
    out: buffers of a previous call to reuse (see `render_projected`; numba only).
    engine: a key of ENGINES ("numba", "reference", "torch"); device: "cpu" or a torch device
    ("cuda", "cuda:1") for the torch engine. Every engine returns the same RasterOutput (numpy) of
    camera.height x camera.width pixels; tests hold them to the reference (drsplat.testing).
    """
    check_near(near)
    check_camera(camera)
    render = rasterize_numba if engine == "numba" else get_engine(engine).render_fn()
    return render(
        scene, camera, topk, with_rgb=with_rgb, with_depth=with_depth, with_median=with_median, background=background, mask=mask,
        near=near, out=out, device=device,
    )

