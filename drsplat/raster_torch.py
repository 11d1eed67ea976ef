"""Torch engine of the top-k rasterizer: the math of drsplat.raster in torch ops (CPU or CUDA).

Same conventions and rules as drsplat.raster (module docstring there; docs/raster.md): EWA
projection, 3DGS's getRect tiles, front-to-back compositing with α = min(0.99, o·exp(power)),
α < 1/255 skipped, stop before T·(1 - α) < 1e-4, per-pixel top-k by w = T·α (stable: ties keep
the front one first). Everything is computed in float64 like the numba kernel, so on a CPU the
two agree to rounding (tests: tests/test_raster_torch.py, helpers in drsplat.testing).

How the work is vectorised (no Python loop over pixels or Gaussians):
- projection: elementwise over the N Gaussians;
- binning: every (Gaussian, tile) pair of the getRect rectangles is listed in depth order and
  stably sorted by tile, so each tile's list stays front to back (like gsplat's isect lists);
- compositing: tiles are sorted by list length and taken in groups of B tiles; each group walks
  its lists in chunks of C entries and evaluates α for [B, C, P] (P = pixels of a tile) at once.
  The transmittance before each entry is the running product of (1 - α) along the chunk,
  `cumprod` seeded with the carried T, so an entry contributes iff its T·(1 - α) ≥ 1e-4 (T only
  decreases, so the first failing entry ends the pixel, as the sequential rule does). The chunk's
  weights are merged into the running top-k by a stable sort on (weight desc, list position).
  B·C·P is bounded by `max_elements` (memory, not results). Each group's chunk count is known on
  the host (list lengths are copied once per view), so the loop never waits for the device.
- `rasterize_torch` renders top-k ids / weights / alpha / median with the fused op
  drsplat.raster_ops.render_topk instead (same rules, one dispatcher call: numba's kernels on a
  CPU, Triton's on CUDA), unless RGB or depth is asked for; the torch ops here stay the torch
  reference (fused=False) and the path for RGB and depth.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np
import torch

from drsplat import _raster_kernels as kernels
from drsplat import raster_ops
from drsplat.cameras import Camera
from drsplat.raster import NEAR, TILE_SIZE, PreparedScene, RasterOutput, _check_args, clamp_limits, prepare_scene, sh_basis_xyz, tile_grid
from drsplat.scene import GaussianScene
from drsplat.defaults import DEFAULT_TOPK

log = logging.getLogger(__name__)

CHUNK = 256  # list entries per compositing step
MAX_ELEMENTS_CPU = 1 << 21  # B·C·P per step: ~16 MB per float64 temporary
MAX_ELEMENTS_CUDA = 1 << 25  # ~256 MB per float64 temporary


@dataclass
class TorchScene:
    """`drsplat.raster.PreparedScene` as tensors on one device.

    means: [N, 3] float64. covariances: [N, 3, 3] float64. opacities: [N] float32.
    sh: [N, K, 3] float32. finite: [N] bool. num_nonfinite: Gaussians flagged non-finite.
    """

    means: torch.Tensor
    covariances: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    finite: torch.Tensor
    num_nonfinite: int

    @classmethod
    def geometry(cls, means: torch.Tensor, covariances: torch.Tensor, opacities: torch.Tensor, usable: torch.Tensor) -> TorchScene:
        """The geometry a torch op is handed (no SH; `usable` as `finite`, so nothing more is counted non-finite)."""
        return cls(means, covariances, opacities, means.new_zeros((means.shape[0], 0, 3), dtype=torch.float32), usable, 0)

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])


def prepare_scene_torch(scene: GaussianScene | PreparedScene | TorchScene, device: str | torch.device = "cpu") -> TorchScene:
    """The view-independent arrays of `scene` on `device` (drsplat.raster.prepare_scene, then copied)."""
    device = torch.device(device)
    if isinstance(scene, TorchScene):
        if scene.device == device or (device.index is None and scene.device.type == device.type):
            return scene
        return TorchScene(*(getattr(scene, f).to(device) for f in ("means", "covariances", "opacities", "sh", "finite")), scene.num_nonfinite)
    prep = prepare_scene(scene)
    return TorchScene(
        means=torch.from_numpy(prep.means).to(device),
        covariances=torch.from_numpy(prep.covariances).to(device),
        opacities=torch.from_numpy(prep.opacities).to(device),
        sh=torch.from_numpy(prep.sh).to(device),
        finite=torch.from_numpy(prep.finite).to(device),
        num_nonfinite=prep.num_nonfinite,
    )


@dataclass
class TorchProjected:
    """Screen-space Gaussians of one view (tensors indexed by Gaussian id; see drsplat.raster.Projected).

    means2d: [N, 2] float64. conics: [N, 3] float64. depths: [N] float32 camera z.
    radii: [N] float64 3σ radius. opacities: [N] float32. valid: [N] bool.
    tile_rects: [N, 4] int64 (tx0, ty0, tx1, ty1), end-exclusive. colors: [N, 3] float32 or None.
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    radii: torch.Tensor
    opacities: torch.Tensor
    valid: torch.Tensor
    tile_rects: torch.Tensor
    colors: torch.Tensor | None
    width: int
    height: int
    tile_size: int = TILE_SIZE
    num_nonfinite: int | torch.Tensor = 0  # 0-d tensors as projected (reading them would wait for the device)
    num_behind: int | torch.Tensor = 0

    @property
    def tile_grid(self) -> tuple[int, int]:
        return tile_grid(self.width, self.height, self.tile_size)


@dataclass
class TorchRasterOutput:
    """`drsplat.raster.RasterOutput` as tensors on the device (ids [H, W, k] int32, weights float32, ...)."""

    ids: torch.Tensor
    weights: torch.Tensor
    rgb: torch.Tensor | None
    depth: torch.Tensor | None
    alpha: torch.Tensor
    num_nonfinite: int | torch.Tensor = 0  # a 0-d tensor until the output is copied to the host
    median_ids: torch.Tensor | None = None
    tile_entries: torch.Tensor | None = None  # 0-d int64: the tile-list entries the view needed (TileLists.needed)

    def numpy(self) -> RasterOutput:
        """The same output as numpy arrays (a RasterOutput)."""

        def host(t):
            return t.cpu().numpy() if isinstance(t, torch.Tensor) else t

        host_names = {f.name for f in dataclasses.fields(RasterOutput)}
        fields = {f.name: host(getattr(self, f.name)) for f in dataclasses.fields(self) if f.name in host_names}  # the same fields by name
        fields["num_nonfinite"] = int(fields["num_nonfinite"])
        return RasterOutput(**fields)


def _screen_space(ts: TorchScene, camera: Camera):
    """Camera-space depth and EWA screen covariance of every Gaussian, in the numba kernel's order of operations.

    Returns (pz [N], u [N], v [N], a, b, c [N]: Σ' = [[a, b], [b, c]]) as float64; the math is
    drsplat.raster._screen_covariances (Σ' = J W Σ Wᵀ Jᵀ + 0.3·I, J clamped at 1.3x the field of view).
    """
    rot = [[float(x) for x in row] for row in np.asarray(camera.R, np.float64)]  # host floats: no device scalars, same double math
    t = [float(x) for x in np.asarray(camera.t, np.float64)]
    m = ts.means
    mx, my, mz = m.unbind(1)
    px, py, pz = (rot[i][0] * mx + rot[i][1] * my + rot[i][2] * mz + t[i] for i in range(3))
    fx, fy, cx, cy = float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)
    lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg = clamp_limits(camera)
    tx = pz * torch.clamp(px / pz, -lim_x_neg, lim_x_pos)
    ty = pz * torch.clamp(py / pz, -lim_y_neg, lim_y_pos)
    jx, jy = torch.full_like(pz, fx) / pz, torch.full_like(pz, fy) / pz  # a true division: scalar / tensor is reciprocal · scalar in torch
    jxz, jyz = -fx * tx / (pz * pz), -fy * ty / (pz * pz)
    # rows of J·W, [N, 2, 3]: jac[:, 0, i] = jx·R[0, i] + jxz·R[2, i], jac[:, 1, i] = jy·R[1, i] + jyz·R[2, i]
    r0, r1, r2 = (torch.tensor(rot[i], dtype=torch.float64, device=m.device) for i in range(3))
    jac = torch.stack([jx[:, None] * r0 + jxz[:, None] * r2, jy[:, None] * r1 + jyz[:, None] * r2], 1)
    cv = ts.covariances
    # s[:, r, i] = Σ_j cv[:, i, j]·jac[:, r, j], summed j = 0, 1, 2 in that order (the numba kernel's rounding)
    s = cv[:, None, :, 0] * jac[:, :, 0, None] + cv[:, None, :, 1] * jac[:, :, 1, None] + cv[:, None, :, 2] * jac[:, :, 2, None]
    ab = jac[:, :, None, 0] * s[:, None, :, 0] + jac[:, :, None, 1] * s[:, None, :, 1] + jac[:, :, None, 2] * s[:, None, :, 2]  # [N, 2, 2]
    a = ab[:, 0, 0] + kernels.BLUR
    b = ab[:, 1, 0]
    c = ab[:, 1, 1] + kernels.BLUR
    u = fx * px / pz + cx
    v = fy * py / pz + cy
    return pz, u, v, a, b, c


def _tile_rects(u: torch.Tensor, v: torch.Tensor, radius: torch.Tensor, width: int, height: int, tile_size: int) -> torch.Tensor:
    """[N, 4] int64: 3DGS's getRect (the rule of drsplat.raster._tile_rects)."""
    cols = []
    for lo in (True, False):
        for mean, size in ((u, width), (v, height)):
            grid = float(-(-size // tile_size))
            p = mean - 0.5
            edge = torch.floor((p - radius) / tile_size) if lo else torch.floor((p + radius + tile_size - 1) / tile_size)
            cols.append(torch.clamp(torch.nan_to_num(edge, nan=0.0), 0.0, grid))
    return torch.stack(cols, dim=1).to(torch.int64)


def project_gaussians_torch(
    scene: GaussianScene | PreparedScene | TorchScene,
    camera: Camera,
    near: float = NEAR,
    *,
    mask: np.ndarray | torch.Tensor | None = None,
    with_colors: bool = False,
    tile_size: int = TILE_SIZE,
    device: str | torch.device = "cpu",
) -> TorchProjected:
    """Project every Gaussian (drsplat.raster.project_gaussians_reference's rules, as tensors on the device)."""
    ts = prepare_scene_torch(scene, device)
    usable = _usable(ts, mask)
    pz, u, v, a, b, c = _screen_space(ts, camera)
    in_front = usable & (pz >= near)
    behind = usable & ~in_front
    det = a * c - b * b
    mid = 0.5 * (a + c)
    radius = torch.ceil(3.0 * torch.sqrt(mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))))
    considered = in_front & (ts.opacities.double() >= kernels.ALPHA_MIN)
    finite = torch.isfinite(torch.stack([a, b, c, u, v, radius])).all(dim=0)
    rects = _tile_rects(u, v, radius, camera.width, camera.height, tile_size)
    nonempty = (rects[:, 2] > rects[:, 0]) & (rects[:, 3] > rects[:, 1])
    valid = considered & finite & (det > 0) & nonempty
    zero = torch.zeros((), dtype=torch.float64, device=ts.device)
    out = TorchProjected(
        means2d=torch.where(valid[:, None], torch.stack([u, v], 1), zero),
        conics=torch.where(valid[:, None], torch.stack([c / det, -b / det, a / det], 1), zero),
        depths=torch.where(usable, pz, zero).float(),
        radii=torch.where(valid, radius, zero),
        opacities=ts.opacities,
        valid=valid,
        tile_rects=torch.where(valid[:, None], rects, 0),
        colors=None,
        width=int(camera.width),
        height=int(camera.height),
        tile_size=tile_size,
        num_nonfinite=ts.num_nonfinite + (considered & ~finite).sum(),  # 0-d tensors: read when the output reaches the host
        num_behind=behind.sum(),
    )
    if with_colors:
        out.colors = _colors(ts, camera, valid)
    return out


def _usable(ts: TorchScene, mask: np.ndarray | torch.Tensor | None) -> torch.Tensor:
    """[N] bool: the Gaussians with finite attributes that `mask` ([N] bool, if given) selects."""
    if mask is None:
        return ts.finite
    n = ts.num_gaussians
    mask_t = torch.as_tensor(np.asarray(mask) if not isinstance(mask, torch.Tensor) else mask, device=ts.device)
    if mask_t.shape != (n,) or mask_t.dtype != torch.bool:
        raise ValueError(f"mask must be a bool array of shape ({n},), got {mask_t.dtype} {tuple(mask_t.shape)}")
    return ts.finite & mask_t


def project_gaussians_fused(scene: GaussianScene | PreparedScene | TorchScene, camera: Camera, near: float = NEAR, *,
                            mask: np.ndarray | torch.Tensor | None = None, tile_size: int = TILE_SIZE,
                            device: str | torch.device = "cpu") -> TorchProjected:
    """`project_gaussians_torch` (no colours) in one Triton kernel launch instead of ~186 torch ops
    (drsplat.raster_triton.project_triton: the same float64 math in the same order, so the same
    bits). Runs on CUDA devices (and on the CPU under Triton's interpreter: the tests)."""
    from drsplat import raster_triton  # imports triton: only when the fused kernels are asked for

    ts = prepare_scene_torch(scene, device)
    means2d, conics, depths, radii, rects, status = raster_triton.project_triton(ts.means, ts.covariances, ts.opacities, _usable(ts, mask),
                                                                                 camera, near, tile_size)
    return TorchProjected(means2d=means2d, conics=conics, depths=depths, radii=radii, opacities=ts.opacities, valid=status == kernels.VALID,
                          tile_rects=rects, colors=None, width=int(camera.width), height=int(camera.height), tile_size=tile_size,
                          num_nonfinite=ts.num_nonfinite + (status == kernels.NONFINITE).sum(), num_behind=(status == kernels.BEHIND).sum())


def _colors(ts: TorchScene, camera: Camera, valid: torch.Tensor) -> torch.Tensor:
    """[N, 3] float32 SH colours for the direction camera centre -> mean (0 where not valid); drsplat.raster.eval_sh."""
    centre = torch.as_tensor(np.asarray(camera.center, np.float64), device=ts.device)
    dirs = ts.means - centre
    norm = torch.linalg.norm(dirs, dim=1, keepdim=True)
    dirs = dirs / torch.where(norm > 0, norm, torch.ones_like(norm))
    sh = ts.sh.double()
    rgb = torch.full((ts.num_gaussians, 3), 0.5, dtype=torch.float64, device=ts.device)
    for i, y_i in enumerate(sh_basis_xyz(dirs[:, 0], dirs[:, 1], dirs[:, 2], sh.shape[1])):
        rgb = rgb + y_i[:, None] * sh[:, i]
    return torch.where(valid[:, None], torch.clamp(rgb, min=0.0), 0.0).float()


@dataclass
class TileLists:
    """Per-tile lists of Gaussian ids, front to back (`tile_lists_torch`).

    offsets [n_tiles] int64, counts [n_tiles] int64, ids [L] int64: tile t owns
    ids[offsets[t]:offsets[t] + counts[t]], in increasing depth (ties by id, as drsplat.raster.depth_order);
    entries past the lists are padding. needed: 0-d int64, the entries the view's lists need; the
    lists are whole iff needed <= L (a list sized without reading the device can fall short: `overflowed`).
    """

    offsets: torch.Tensor
    counts: torch.Tensor
    ids: torch.Tensor
    needed: torch.Tensor

    def overflowed(self) -> torch.Tensor:
        """0-d bool: the lists were cut short (more entries needed than they hold)."""
        return self.needed > self.ids.shape[0]

    def as_tuple(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return self.offsets, self.counts, self.ids


def tile_lists_torch(projected: TorchProjected, capacity: int | None = None) -> TileLists:
    """The view's tile lists, sized exactly (capacity None: the host reads the entries' number from
    the device, one synchronisation) or with `capacity` entries (nothing read; lists cut short past
    it, which `TileLists.overflowed` says).

    Every Gaussian of the depth order owns the entries [end_g - n_g, end_g) of the flat list
    (n_g = its getRect rectangle's tiles, end = the inclusive cumulative sum), so entry e belongs to
    the first Gaussian with end_g > e (a binary search) and is that Gaussian's (e - end_g + n_g)-th
    tile in row order; a stable sort by tile keeps each list in depth order. Entries past the last
    end get the tile n_tiles and sort after every list, so the lists of a capacity at least the
    needed number are the exact ones, entry for entry.
    """
    dev = projected.valid.device
    n_tiles_x, n_tiles_y = projected.tile_grid
    n_tiles = n_tiles_x * n_tiles_y
    # all N ids by depth, invalid ones last (their rects are empty: they add no entries); a stable
    # sort of the valid depths alone gives the same order of the valid ids, without a nonzero()
    depth = torch.where(projected.valid, projected.depths + 0.0, torch.inf)  # -0 sorts as +0
    order = torch.sort(depth, stable=True).indices
    r = projected.tile_rects[order]
    span_x = r[:, 2] - r[:, 0]
    per = span_x * (r[:, 3] - r[:, 1])
    ends = torch.cumsum(per, 0)
    needed = ends[-1] if ends.numel() else torch.zeros((), dtype=torch.int64, device=dev)
    size = (int(needed) if ends.numel() else 0) if capacity is None else int(capacity)
    if size == 0 or ends.numel() == 0:
        empty = torch.zeros(n_tiles, dtype=torch.int64, device=dev)
        return TileLists(empty, empty.clone(), torch.zeros(max(size, 0), dtype=torch.int64, device=dev), needed)
    entry = torch.arange(size, device=dev)
    rank = torch.searchsorted(ends, entry, right=True)
    listed = rank < ends.numel()
    rank = torch.clamp(rank, max=ends.numel() - 1)
    local = entry - (ends[rank] - per[rank])
    width = torch.clamp(span_x[rank], min=1)  # padding entries may land on an empty rectangle
    tile = (r[rank, 1] + local // width) * n_tiles_x + r[rank, 0] + local % width
    tile_sorted, perm = torch.sort(torch.where(listed, tile, n_tiles), stable=True)
    counts = torch.bincount(tile_sorted, minlength=n_tiles + 1)[:n_tiles]
    offsets = torch.cumsum(counts, 0) - counts
    return TileLists(offsets, counts, order[rank[perm]], needed)


def bin_gaussians_torch(projected: TorchProjected) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(offsets [n_tiles], counts [n_tiles], ids [E]) int64 of the exact tile lists (`tile_lists_torch`)."""
    return tile_lists_torch(projected).as_tuple()


def _merge_topk(best_w: torch.Tensor, best_pos: torch.Tensor, w: torch.Tensor, pos: torch.Tensor, k: int):
    """The k largest of both candidate sets ([..., k_i]), weight descending.

    best_* come from earlier (smaller) list positions and, being sorted, a stable descending
    sort of [best, new] keeps the earlier entry first among equal weights, as the sequential rule does.
    """
    cand_w = torch.cat([best_w, w], dim=-1)
    cand_pos = torch.cat([best_pos, pos], dim=-1)
    by_w = torch.sort(cand_w, dim=-1, descending=True, stable=True).indices[..., :k]
    return torch.gather(cand_w, -1, by_w), torch.gather(cand_pos, -1, by_w)


@dataclass
class _Buffers:
    """Tile-major outputs: ids / weights [n_tiles, P, k], trans [n_tiles, P], rgb [n_tiles, P, 3] | None, dep [n_tiles, P] | None,
    med [n_tiles, P] | None (median Gaussian, as a position in the tile's list)."""

    ids: torch.Tensor
    weights: torch.Tensor
    trans: torch.Tensor
    rgb: torch.Tensor | None
    dep: torch.Tensor | None
    med: torch.Tensor | None = None


@dataclass
class _TileGroup:
    """Compositing state of the B active tiles of a group (P pixels each): tiles [B], starts / lengths [B]
    of their lists, pixel centres cx / cy [B, P], T [B, P], done [B, P], rgb [B, P, 3], dep [B, P],
    best_w / best_pos [B, P, k'] running top-k weights and list positions."""

    tiles: torch.Tensor
    starts: torch.Tensor
    lengths: torch.Tensor
    cx: torch.Tensor
    cy: torch.Tensor
    trans: torch.Tensor
    done: torch.Tensor
    rgb: torch.Tensor
    dep: torch.Tensor
    med: torch.Tensor
    best_w: torch.Tensor
    best_pos: torch.Tensor


def _new_group(projected: TorchProjected, tiles, starts, lengths) -> _TileGroup:
    """Fresh state of `tiles`; pixels outside the image start done (they never count)."""
    dev = tiles.device
    ts = projected.tile_size
    n_tiles_x, _ = projected.tile_grid
    b_count, p_count = tiles.numel(), ts * ts
    local = torch.arange(p_count, device=dev)
    pix_x = ((tiles % n_tiles_x) * ts)[:, None] + local[None] % ts
    pix_y = ((tiles // n_tiles_x) * ts)[:, None] + local[None] // ts
    f64 = {"dtype": torch.float64, "device": dev}
    return _TileGroup(
        tiles=tiles, starts=starts, lengths=lengths, cx=pix_x.double() + 0.5, cy=pix_y.double() + 0.5,
        trans=torch.ones((b_count, p_count), **f64),
        done=(pix_x >= projected.width) | (pix_y >= projected.height),
        rgb=torch.zeros((b_count, p_count, 3), **f64), dep=torch.zeros((b_count, p_count), **f64),
        med=torch.full((b_count, p_count), -1, dtype=torch.int64, device=dev),
        best_w=torch.zeros((b_count, p_count, 0), **f64), best_pos=torch.zeros((b_count, p_count, 0), dtype=torch.int64, device=dev),
    )  # fmt: skip


def _store(state: _TileGroup, tile_list: torch.Tensor, out: _Buffers) -> None:
    """Write the finished tiles of `state` into the tile-major outputs."""
    tiles = state.tiles
    out.trans[tiles] = state.trans
    if out.rgb is not None:
        out.rgb[tiles] = state.rgb
    if out.dep is not None:
        out.dep[tiles] = state.dep
    if out.med is not None:
        picked = state.med >= 0
        gid = tile_list[state.starts[:, None] + torch.where(picked, state.med, 0)]
        out.med[tiles] = torch.where(picked, gid, -1)
    kept = state.best_w.shape[-1]
    if kept:
        hit = state.best_w > 0
        gid = tile_list[state.starts[:, None, None] + torch.where(hit, state.best_pos, 0)]
        out.ids[tiles, :, :kept] = torch.where(hit, gid, -1).to(torch.int32)
        out.weights[tiles, :, :kept] = state.best_w.float()


def _composite_group(projected: TorchProjected, state: _TileGroup, tile_list, topk, chunk, longest: int, out: _Buffers) -> None:
    """Composite the tiles of `state` (lists tile_list[starts[b]:starts[b] + lengths[b]]) into `out`.

    For each chunk of C entries: d = mean2d - pixel centre, power = -½(a·dx² + c·dy²) - b·dx·dy,
    α = min(0.99, o·exp(power)), hit = power ≤ 0 and α ≥ 1/255; T_after = cumprod of (1 - α)
    (1 where not hit) seeded with the carried T (0 once a pixel is done); an entry contributes
    w = α·T_before iff hit and T_after ≥ 1e-4; the median Gaussian is the contributing entry
    with T_before > ½ ≥ T_after (one per pixel at most: T only falls). longest: the group's longest
    list, known on the host, so the chunk loop has a fixed trip count and never waits for the device
    (pixels that are done and tiles whose lists are exhausted contribute nothing in later chunks).
    """
    dev = tile_list.device
    with_rgb, with_depth, with_median = out.rgb is not None, out.dep is not None, out.med is not None
    steps = torch.arange(chunk, device=dev)
    for c0 in range(0, longest, chunk):
        pos = c0 + steps[: min(chunk, longest - c0)]
        in_range = pos[None, :] < state.lengths[:, None]  # [B, C]
        g = tile_list[torch.where(in_range, state.starts[:, None] + pos[None, :], 0)]
        u, v = projected.means2d[g, 0][..., None], projected.means2d[g, 1][..., None]
        ca, cb, cc = (projected.conics[g, i][..., None] for i in range(3))
        dx = u - state.cx[:, None, :]
        dy = v - state.cy[:, None, :]
        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy  # [B, C, P]
        alpha = torch.clamp(projected.opacities[g].double()[..., None] * torch.exp(power), max=kernels.ALPHA_MAX)
        hit = in_range[..., None] & (power <= 0.0) & (alpha >= kernels.ALPHA_MIN)
        seed = torch.where(state.done, 0.0, state.trans)
        cum = torch.cumprod(torch.cat([seed[:, None, :], torch.where(hit, 1.0 - alpha, 1.0)], dim=1), dim=1)
        t_after = cum[:, 1:]
        ok = hit & (t_after >= kernels.T_MIN)
        w = torch.where(ok, alpha * cum[:, :-1], 0.0)
        state.trans = torch.minimum(state.trans, torch.where(ok, t_after, torch.inf).amin(dim=1))
        state.done |= (hit & (t_after < kernels.T_MIN)).any(dim=1)
        if with_rgb:
            state.rgb += torch.einsum("bcp,bcd->bpd", w, projected.colors[g].double())
        if with_depth:
            state.dep += torch.einsum("bcp,bc->bp", w, projected.depths[g].double())
        if with_median:
            cross = ok & (t_after <= kernels.MEDIAN_T) & (cum[:, :-1] > kernels.MEDIAN_T)  # [B, C, P]
            at = torch.where(cross, pos[None, :, None], 0).sum(dim=1)  # the crossing entry's position in the list
            state.med = torch.where(cross.any(dim=1), at, state.med)
        if topk > 0:
            cw, ci = torch.topk(w.transpose(1, 2), min(topk, w.shape[1]), dim=-1)
            state.best_w, state.best_pos = _merge_topk(state.best_w, state.best_pos, cw, pos[ci], topk)
    _store(state, tile_list, out)


def composite_torch(
    projected: TorchProjected,
    topk: int = DEFAULT_TOPK,
    *,
    with_rgb: bool = False,
    with_depth: bool = False,
    with_median: bool = False,
    background=(0.0, 0.0, 0.0),
    chunk: int = CHUNK,
    max_elements: int | None = None,
    lists: TileLists | None = None,
) -> TorchRasterOutput:
    """Bin and composite `projected` (module docstring); outputs stay on its device.

    lists: its tile lists (`tile_lists_torch`), else made here exactly."""
    bg = _check_args(topk, background)
    if with_rgb and projected.colors is None:
        raise ValueError("with_rgb needs TorchProjected.colors (project_gaussians_torch(..., with_colors=True))")
    dev = projected.valid.device
    if max_elements is None:
        max_elements = MAX_ELEMENTS_CUDA if dev.type == "cuda" else MAX_ELEMENTS_CPU
    ts = projected.tile_size
    p_count = ts * ts
    n_tiles_x, n_tiles_y = projected.tile_grid
    n_tiles = n_tiles_x * n_tiles_y
    lists = tile_lists_torch(projected) if lists is None else lists
    offsets, counts, tile_list = lists.as_tuple()
    out = _Buffers(
        ids=torch.full((n_tiles, p_count, topk), -1, dtype=torch.int32, device=dev),
        weights=torch.zeros((n_tiles, p_count, topk), dtype=torch.float32, device=dev),
        trans=torch.ones((n_tiles, p_count), dtype=torch.float64, device=dev),
        rgb=torch.zeros((n_tiles, p_count, 3), dtype=torch.float64, device=dev) if with_rgb else None,
        dep=torch.zeros((n_tiles, p_count), dtype=torch.float64, device=dev) if with_depth else None,
        med=torch.full((n_tiles, p_count), -1, dtype=torch.int64, device=dev) if with_median else None,
    )
    by_length = torch.sort(counts, descending=True, stable=True).indices
    lengths_host = counts[by_length].cpu().numpy()
    n_busy = int(np.count_nonzero(lengths_host))
    i = 0
    while i < n_busy:
        b = max(1, max_elements // (int(min(lengths_host[i], chunk)) * p_count))
        tiles = by_length[i : min(i + b, n_busy)]
        _composite_group(projected, _new_group(projected, tiles, offsets[tiles], counts[tiles]), tile_list, topk, chunk, int(lengths_host[i]), out)
        i += b
    ids, weights, trans, rgb, dep = out.ids, out.weights, out.trans, out.rgb, out.dep
    acc = 1.0 - trans
    out_rgb = None
    if with_rgb:
        out_rgb = (rgb + trans[..., None] * torch.as_tensor(bg, dtype=torch.float64, device=dev)).float()
    out_depth = None
    if with_depth:
        out_depth = torch.where(acc > 0, dep / torch.where(acc > 0, acc, 1.0), 0.0).float()
    h, w = projected.height, projected.width

    def image(t: torch.Tensor | None) -> torch.Tensor | None:
        if t is None:
            return None
        rest = t.shape[2:]
        t = t.reshape(n_tiles_y, n_tiles_x, ts, ts, *rest).transpose(1, 2).reshape(n_tiles_y * ts, n_tiles_x * ts, *rest)
        return t[:h, :w].contiguous()

    median = image(out.med.to(torch.int32)) if with_median else None
    return TorchRasterOutput(image(ids), image(weights), image(out_rgb), image(out_depth), image(acc.float()), projected.num_nonfinite, median,
                             lists.needed)


def rasterize_torch(
    scene: GaussianScene | PreparedScene | TorchScene,
    camera: Camera,
    topk: int = DEFAULT_TOPK,
    *,
    with_rgb: bool = False,
    with_depth: bool = False,
    with_median: bool = False,
    background=(0.0, 0.0, 0.0),
    mask: np.ndarray | torch.Tensor | None = None,
    near: float = NEAR,
    device: str | torch.device | None = None,
    max_elements: int | None = None,
    fused: bool | None = None,
    tile_capacity: int | None = None,
    ranked: bool = True,
) -> TorchRasterOutput:
    """Render one view with the torch engine; the output stays on the device (tensors).

    tile_capacity: size the view's tile lists to this many entries without reading the device
    (`tile_lists_torch`); the output is then right only if `tile_entries` (the entries needed, a
    0-d tensor in the output) is at most it, which the caller checks when it reads the device
    anyway. None: sized exactly (one read of the device).
    device: where to run; None = the device of a TorchScene, else the CPU.
    fused: render with the fused top-k op (drsplat.raster_ops.render_topk: numba's kernels on a CPU,
    Triton's on CUDA; one dispatcher call) instead of the torch ops below (the torch reference);
    None = wherever the op has a kernel (`has_fused_kernel`) and no RGB / depth is asked for (the
    op keeps ids, weights, alpha and the median).
    ranked: each pixel's slots by weight, as every engine; False lets the fused op's CPU kernel
    skip that sort (the same entries, padding last: what registration needs). The torch ops rank always.
    """
    _check_args(topk, background)
    if device is None:
        device = scene.device if isinstance(scene, TorchScene) else "cpu"
    ts = prepare_scene_torch(scene, device)
    if fused is None:
        fused = not (with_rgb or with_depth) and has_fused_kernel(ts.device)
    if fused:
        if with_rgb or with_depth:
            raise ValueError("the fused top-k op keeps ids, weights, alpha and the median only; use fused=False for RGB or depth")
        ids, weights, alpha, median, entries, nonfinite, _ = raster_ops.render_topk(
            ts.means, ts.covariances, ts.opacities, _usable(ts, mask), raster_ops.camera_values(camera), int(camera.width), int(camera.height),
            float(near), TILE_SIZE, topk, with_median, -1 if tile_capacity is None else int(tile_capacity), ranked,
        )  # fmt: skip
        return TorchRasterOutput(ids, weights, None, None, alpha, nonfinite + ts.num_nonfinite, median if with_median else None, entries)
    projected = project_gaussians_torch(ts, camera, near, mask=mask, with_colors=with_rgb, device=ts.device)
    return composite_torch(projected, topk, with_rgb=with_rgb, with_depth=with_depth, with_median=with_median, background=background,
                           max_elements=max_elements, lists=tile_lists_torch(projected, tile_capacity))


def render_topk_triton(means: torch.Tensor, covariances: torch.Tensor, opacities: torch.Tensor, usable: torch.Tensor, camera: list[float],
                       width: int, height: int, near: float, tile_size: int, topk: int, with_median: bool, capacity: int, ranked: bool = True):
    """The CUDA kernel of `drsplat::render_topk` (drsplat.raster_ops, its arguments and outputs):
    Triton's projection (`project_gaussians_fused`), the tile lists (`tile_lists_torch`, `capacity`
    entries; < 0: exact, one read) and Triton's compositing, whose slots are always ranked (by
    float32 weight). Runs on the CPU under Triton's interpreter (the tests)."""
    from drsplat import raster_triton  # imports triton: only when the fused kernels are asked for

    cam = raster_ops.camera_from_values(camera, width, height)
    projected = project_gaussians_fused(TorchScene.geometry(means, covariances, opacities, usable), cam, near, tile_size=tile_size, device=means.device)
    lists = tile_lists_torch(projected, None if capacity < 0 else capacity)
    ids, weights, alpha, median = raster_triton.composite_topk_triton(projected, lists.as_tuple(), topk, with_median=with_median)
    if median is None:
        median = torch.zeros((0, 0), dtype=torch.int32, device=means.device)
    return ids, weights, alpha, median, lists.needed.reshape(()).clone(), torch.as_tensor(projected.num_nonfinite, device=means.device).clone(), \
        projected.num_behind.clone()


raster_ops.render_topk.register_kernel("cuda")(render_topk_triton)


def has_fused_kernel(device: torch.device) -> bool:
    """Whether the fused top-k op (`raster_ops.render_topk`) has a kernel for `device`: the CPU
    always (numba), CUDA when Triton is installed."""
    return device.type == "cpu" or (device.type == "cuda" and triton_available())


def triton_available() -> bool:
    """Whether the fused Triton kernel can be compiled (triton installed)."""
    import importlib.util

    return importlib.util.find_spec("triton") is not None


def rasterize(
    scene: GaussianScene | PreparedScene | TorchScene,
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
    device: str | None = "cpu",
    fused: bool | None = None,
) -> RasterOutput:
    """The torch engine behind `drsplat.raster.rasterize(..., engine="torch")`: numpy RasterOutput
    (`out` unused; `fused` as in `rasterize_torch`)."""
    if isinstance(scene, TorchScene) and device in (None, "cpu") and scene.device.type != "cpu":
        device = scene.device
    return rasterize_torch(
        scene, camera, topk, with_rgb=with_rgb, with_depth=with_depth, with_median=with_median, background=background, mask=mask,
        near=near, device=device, fused=fused,
    ).numpy()
