"""Aggregation modes of the registration beyond the paper's (`drsplat register --aggregate MODE`).

The paper sums, for Gaussian i and mask j, w_ij = Σ_{p ∈ mask j} w_i(p) with w = T·α, and sets
f_i = normalize(Σ_j w_ij f_j). Two things go wrong on hard scenes (docs/evaluation.md,
"Aggregation"): a Gaussian on a silhouette spreads much of its footprint over the background's
mask, and faint unlabelled floaters and blobs collect weight like anything else and end up
labelled. A mode changes the per-pixel weight before accumulation (`view_weights`) and/or leaves
unsupported Gaussians unassigned after it (`SurfaceSupport`):

    paper           w                                  (Dr. Splat)
    core            w · exp(-½ d²)                     the Gaussian's own falloff at the pixel relative to
                                                       its peak, d² = dᵀ Σ'⁻¹ d (footprint-core weighting)
    ellipse         w · [d² ≤ 4]                       only pixels inside the Gaussian's 2σ ellipse
    responsibility  w / Σ_k w                          share of the pixel's (top-k) weight it carries
    centre          w · [p = c_i]                      only the pixel c_i = (⌊u_i⌋, ⌊v_i⌋) that holds the
                                                       Gaussian's projected centre (u_i, v_i) (issue 14's
                                                       centre-pixel baseline; occluded centres keep their
                                                       small T·α)
    anchor          w · (1 + c·A_i·[p = c_i])          the paper's w everywhere plus a centre vote worth
                                                       c = ANCHOR_GAIN footprints: A_i = 2π·sqrt(det Σ'_i)
                                                       = 2π / sqrt(a·c - b²) = Σ_p exp(-½ d²), so an
                                                       unoccluded Gaussian's centre pixel weighs about as
                                                       much as its whole footprint, an occluded one little
    reject          w, then floater rejection
    core-reject     core, then floater rejection
    ellipse-reject  ellipse, then floater rejection
    anchor-reject   anchor, then floater rejection

d is the offset of the Gaussian's screen mean from the pixel centre and Σ' its screen covariance,
exactly as the compositor evaluates α = min(0.99, o·exp(-½ d²)); the 2σ ellipse always holds
the pixel centre nearest to the mean (Σ' ⪰ 0.3 I, so that centre is at d² ≤ 0.5/0.3 < 4).
centre and anchor target masks that follow true silhouettes (a SAM mask of a photo; the
`hard-silhouette` preset): a Gaussian straddling a thin object's silhouette puts most of its
footprint on the background's mask, while its centre lies on the object. On masks made by the
Gaussians' own weighted vote (the other hard-* presets) the paper's w is what drew the boundaries,
and both lose (docs/registration.md, "Centre and anchor weightings"). ANCHOR_GAIN c = 1 was
picked over {0.5, 2, 8, 32} on seed 0 of hard-silhouette, -thin, -small and -lowres: larger c moves
anchor towards centre (more gain on hard-silhouette, large losses elsewhere), 0.5 gains less.

Floater rejection (`SurfaceSupport`). In every view, pixel p's surface depth D(p) is the camera
depth at which the pixel's top-k contributions, taken front to back, first reach a summed weight
of ½ (+∞ if they never do): the pixel's median depth. (Using only the 8 heaviest contributions
was measured too: it rejected more labelled Gaussians at silhouettes and grazing views, where
weight is spread over many Gaussians, and cost up to 0.01 mIoU.) A contribution of Gaussian i at p is *in front* when z_i < (1 - τ)·D(p),
τ = 0.05. Over all views Gaussian i collects its peak weight P_i = max_p w_i(p), its total weight
A_i = Σ_p w_i(p) and its in-front weight B_i = Σ_p w_i(p)·[in front]. It is rejected (left
unassigned, W_i = 0) when

    P_i < ½  and  B_i > ½·A_i

i.e. it is never the dominant contribution of any pixel and mostly renders as haze in front of
the visible surface: what a floater or a faint blob in free space does. Faint Gaussians lying on
a surface (D ≈ their depth) and thin opaque structures (P ≥ ½ at their centre pixels) are kept.
Memory: three [N] float arrays; nothing per (Gaussian, mask).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numba
import numpy as np

from drsplat.defaults import AGGREGATE_MODES, DEFAULT_AGGREGATE

log = logging.getLogger(__name__)

WEIGHTINGS = ("paper", "core", "ellipse", "responsibility", "centre", "anchor")
MODES = AGGREGATE_MODES  # names owned by drsplat.defaults (argument parsers read them without numba)
DEFAULT_MODE = DEFAULT_AGGREGATE
ELLIPSE_D2 = 4.0  # squared Mahalanobis radius of the ellipse mode (2σ)
ANCHOR_GAIN = 1.0  # c of the anchor mode: the centre pixel's extra vote, in units of the Gaussian's footprint
FRONT_TOLERANCE = 0.05  # τ: relative depth margin of "in front of the surface"
SURFACE_WEIGHT = 0.5  # summed weight that defines the pixel's surface depth
PEAK_MIN = 0.5  # a Gaussian with P_i ≥ this is never rejected
FRONT_MAX = 0.5  # rejected when more than this share of its weight is in front of the surface

_WEIGHTING_CODE = {"paper": 0, "core": 1, "ellipse": 2, "responsibility": 3, "centre": 4, "anchor": 5}
_PROJECTED = ("core", "ellipse", "centre", "anchor")  # weightings that need the view's screen means / conics


def split_mode(mode: str) -> tuple[str, bool]:
    """(weighting, reject) of a mode name; ValueError for an unknown mode."""
    if mode not in MODES:
        raise ValueError(f"unknown aggregation mode {mode!r} (choose from {', '.join(MODES)})")
    if mode == "reject":
        return "paper", True
    if mode.endswith("-reject"):
        return mode[: -len("-reject")], True
    return mode, False


# ----------------------------------------------------------------------------- per-view weights


def view_weights_reference(weighting: str, ids: np.ndarray, weights: np.ndarray, means2d: np.ndarray, conics: np.ndarray,
                           anchor_gain: float = ANCHOR_GAIN) -> np.ndarray:
    """Per-pixel weights of a weighting (numpy reference; math in the module docstring).

    ids, weights: [H, W, k] top-k ids (-1 none) and w = T·α; means2d: [N, 2] screen means
    (pixel centres at +0.5), conics: [N, 3] (a, b, c) of Σ'⁻¹; anchor_gain: c of "anchor".
    Returns [H, W, k] float32 (0 where ids < 0).
    """
    w = np.where(ids >= 0, weights.astype(np.float64), 0.0)
    if weighting == "paper":
        return w.astype(np.float32)
    if weighting == "responsibility":
        total = w.sum(axis=-1, keepdims=True)
        return np.where(total > 0, w / np.where(total > 0, total, 1.0), 0.0).astype(np.float32)
    h, wd, _ = ids.shape
    g = np.maximum(ids, 0)
    ys, xs = np.mgrid[0:h, 0:wd]
    dx = means2d[g, 0] - (xs[..., None] + 0.5)
    dy = means2d[g, 1] - (ys[..., None] + 0.5)
    a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    if weighting == "core":
        return (w * np.exp(np.minimum(power, 0.0))).astype(np.float32)
    if weighting == "ellipse":
        return np.where(-2.0 * power <= ELLIPSE_D2, w, 0.0).astype(np.float32)
    at_centre = (np.floor(means2d[g, 0]) == xs[..., None]) & (np.floor(means2d[g, 1]) == ys[..., None])
    if weighting == "centre":
        return np.where(at_centre, w, 0.0).astype(np.float32)
    if weighting == "anchor":
        return (w * (1.0 + anchor_gain * footprint_area(conics)[g] * at_centre)).astype(np.float32)
    raise ValueError(f"unknown weighting {weighting!r}")


def footprint_area(conics: np.ndarray) -> np.ndarray:
    """[N] A = 2π·sqrt(det Σ') = 2π / sqrt(a·c - b²) of conics [N, 3]: Σ_p exp(-½ d²) over the
    pixels, the Gaussian's screen footprint in pixels (0 where the conic is degenerate)."""
    det = conics[:, 0] * conics[:, 2] - conics[:, 1] ** 2
    return np.where(det > 0, 2.0 * np.pi / np.sqrt(np.where(det > 0, det, 1.0)), 0.0)


@numba.njit(parallel=True, cache=True)
def _view_weights_kernel(code, ids, weights, means2d, conics, ellipse_d2, anchor_gain, out):  # pragma: no cover - jitted
    """out[y, x, s] = the weighting `code` (see _WEIGHTING_CODE) of slot s of pixel (x, y)."""
    h, wd, k = ids.shape
    for y in numba.prange(h):
        py = y + 0.5
        for x in range(wd):
            px = x + 0.5
            total = 0.0
            if code == 3:
                for s in range(k):
                    if ids[y, x, s] >= 0:
                        total += np.float64(weights[y, x, s])
            for s in range(k):
                g = ids[y, x, s]
                if g < 0:
                    out[y, x, s] = 0.0
                    continue
                w = np.float64(weights[y, x, s])
                if code == 0:
                    out[y, x, s] = w
                elif code == 3:
                    out[y, x, s] = w / total if total > 0.0 else 0.0
                elif code >= 4:
                    at_centre = np.floor(means2d[g, 0]) == x and np.floor(means2d[g, 1]) == y
                    if code == 4:
                        out[y, x, s] = w if at_centre else 0.0
                    elif at_centre:
                        det = conics[g, 0] * conics[g, 2] - conics[g, 1] * conics[g, 1]
                        area = 2.0 * np.pi / np.sqrt(det) if det > 0.0 else 0.0
                        out[y, x, s] = w * (1.0 + anchor_gain * area)
                    else:
                        out[y, x, s] = w
                else:
                    dx = means2d[g, 0] - px
                    dy = means2d[g, 1] - py
                    power = -0.5 * (conics[g, 0] * dx * dx + conics[g, 2] * dy * dy) - conics[g, 1] * dx * dy
                    if code == 1:
                        out[y, x, s] = w * np.exp(min(power, 0.0))
                    else:
                        out[y, x, s] = w if -2.0 * power <= ellipse_d2 else 0.0


def view_weights(weighting: str, ids: np.ndarray, weights: np.ndarray, means2d: np.ndarray, conics: np.ndarray,
                 out: np.ndarray | None = None, anchor_gain: float = ANCHOR_GAIN) -> np.ndarray:
    """`view_weights_reference` with a numba kernel; out: a [H, W, k] float32 buffer to reuse."""
    if weighting not in _WEIGHTING_CODE:
        raise ValueError(f"unknown weighting {weighting!r}")
    if out is None or out.shape != ids.shape:
        out = np.empty(ids.shape, np.float32)
    _view_weights_kernel(_WEIGHTING_CODE[weighting], np.ascontiguousarray(ids, np.int32), np.ascontiguousarray(weights, np.float32),
                         np.ascontiguousarray(means2d, np.float64), np.ascontiguousarray(conics, np.float64), ELLIPSE_D2, float(anchor_gain), out)
    return out


# ----------------------------------------------------------------------------- floater rejection


def surface_stats_reference(ids: np.ndarray, weights: np.ndarray, depths: np.ndarray, peak: np.ndarray, total: np.ndarray,
                            front: np.ndarray, tolerance: float = FRONT_TOLERANCE) -> None:
    """Add one view to the rejection statistics (numpy reference; math in the module docstring).

    ids, weights: [H, W, k] (raw w = T·α); depths: [N] camera z. Updates in place peak [N]
    (max w), total [N] (Σ w) and front [N] (Σ w over contributions in front of the surface).
    """
    k = ids.shape[-1]
    g = ids.reshape(-1, k)
    w = np.where(g >= 0, weights.reshape(-1, k).astype(np.float64), 0.0)
    z = np.where(g >= 0, depths[np.maximum(g, 0)].astype(np.float64), np.inf)
    zs, ws = z, w
    order = np.argsort(zs, axis=1, kind="stable")
    cum = np.cumsum(np.take_along_axis(ws, order, axis=1), axis=1)
    reached = cum >= SURFACE_WEIGHT
    first = np.argmax(reached, axis=1)
    surface = np.where(reached.any(axis=1), np.take_along_axis(np.take_along_axis(zs, order, axis=1), first[:, None], axis=1)[:, 0], np.inf)
    in_front = z < (1.0 - tolerance) * surface[:, None]
    valid = g >= 0
    np.maximum.at(peak, g[valid], w[valid])
    np.add.at(total, g[valid], w[valid])
    np.add.at(front, g[valid], (w * in_front)[valid])


@numba.njit(parallel=True, cache=True)
def _front_limits_kernel(ids, weights, depths, tolerance, surface_weight, limits):  # pragma: no cover - jitted
    """limits[p] = (1 - τ)·D(p), D(p) the depth at which pixel p's contributions, front to back,
    first sum to `surface_weight` (+inf if they never do). Parallel over chunks of pixels.

    The heaviest contribution (slot 0) is the pivot: if the contributions up to its depth already
    reach the sum, only those (usually few: haze in front of the surface) are sorted by depth,
    else only those behind it, starting from the sum in front. Same D as sorting all of them.
    """
    n_pix, k = ids.shape
    n_chunks = 64
    step = (n_pix + n_chunks - 1) // n_chunks
    for c in numba.prange(n_chunks):
        zbuf = np.empty(k, np.float64)  # per chunk, not per pixel: allocation in the loop is slow
        wbuf = np.empty(k, np.float64)
        for p in range(c * step, min(n_pix, (c + 1) * step)):
            limits[p] = np.inf
            if ids[p, 0] < 0:
                continue
            pivot = np.float64(depths[ids[p, 0]])
            total = 0.0
            front = 0.0
            for s in range(k):
                g = ids[p, s]
                if g >= 0:
                    w = np.float64(weights[p, s])
                    total += w
                    if np.float64(depths[g]) <= pivot:
                        front += w
            if total < surface_weight:
                continue
            ahead = front >= surface_weight  # D ≤ pivot: sort the ones up to the pivot, else the ones behind it
            n = 0
            for s in range(k):
                g = ids[p, s]
                if g < 0:
                    continue
                z = np.float64(depths[g])
                if (z <= pivot) != ahead:
                    continue
                w = np.float64(weights[p, s])
                pos = n
                while pos > 0 and zbuf[pos - 1] > z:
                    zbuf[pos] = zbuf[pos - 1]
                    wbuf[pos] = wbuf[pos - 1]
                    pos -= 1
                zbuf[pos] = z
                wbuf[pos] = w
                n += 1
            cum = 0.0 if ahead else front
            for m in range(n):
                cum += wbuf[m]
                if cum >= surface_weight:
                    limits[p] = (1.0 - tolerance) * zbuf[m]
                    break


@numba.njit(cache=True)
def _scatter_stats_kernel(ids, weights, depths, limits, peak, total, front):  # pragma: no cover - jitted
    """Serial scatter of one view's statistics (threads would race on the per-Gaussian sums)."""
    n_pix, k = ids.shape
    for p in range(n_pix):
        limit = limits[p]
        for s in range(k):
            g = ids[p, s]
            if g < 0:
                continue
            w = np.float64(weights[p, s])
            if w > peak[g]:
                peak[g] = w
            total[g] += w
            if np.float64(depths[g]) < limit:
                front[g] += w


def surface_stats(ids: np.ndarray, weights: np.ndarray, depths: np.ndarray, peak: np.ndarray, total: np.ndarray, front: np.ndarray,
                  tolerance: float = FRONT_TOLERANCE) -> None:
    """`surface_stats_reference` with a numba kernel (peak, total, front: float64 [N], in place)."""
    k = ids.shape[-1]
    ids2 = np.ascontiguousarray(ids.reshape(-1, k), np.int32)
    w2 = np.ascontiguousarray(weights.reshape(-1, k), np.float32)
    z = np.ascontiguousarray(depths, np.float32)
    limits = np.empty(ids2.shape[0], np.float64)
    _front_limits_kernel(ids2, w2, z, float(tolerance), SURFACE_WEIGHT, limits)
    _scatter_stats_kernel(ids2, w2, z, limits, peak, total, front)


def rejected(peak: np.ndarray, total: np.ndarray, front: np.ndarray) -> np.ndarray:
    """[N] bool: P_i < PEAK_MIN and B_i > FRONT_MAX·A_i (Gaussians never seen count as not rejected)."""
    return (total > 0) & (peak < PEAK_MIN) & (front > FRONT_MAX * total)


@dataclass
class SurfaceSupport:
    """The rejection statistics of a registration: peak, total, front: [N] float64."""

    peak: np.ndarray
    total: np.ndarray
    front: np.ndarray

    @classmethod
    def zeros(cls, n: int) -> SurfaceSupport:
        return cls(np.zeros(n), np.zeros(n), np.zeros(n))

    def rejected(self) -> np.ndarray:
        return rejected(self.peak, self.total, self.front)


def camera_depths(means: np.ndarray, camera) -> np.ndarray:
    """[N] float32 camera z = R[2]·x + t[2] of means [N, 3] (the rasterizer's depth)."""
    rot, trans = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64)
    return (np.asarray(means, np.float64) @ rot[2] + trans[2]).astype(np.float32)


# ----------------------------------------------------------------------------- the registration hook


class Aggregator:
    """What registration calls for a mode: `view_weights` per view, `finish` on the sums.

    For "paper" both are no-ops (the view's w is used as it is) and no projection is done.
    """

    def __init__(self, mode: str, num_gaussians: int):
        self.mode = mode
        self.weighting, self.reject = split_mode(mode)
        self.support = SurfaceSupport.zeros(num_gaussians) if self.reject else None
        self.num_rejected = 0
        self._buffer: np.ndarray | None = None

    @property
    def needs_projection(self) -> bool:
        return self.weighting in _PROJECTED

    def view_weights(self, prepared, camera, out) -> np.ndarray:
        """[H, W, k] weights to accumulate for one rasterized view (`out`, a RasterOutput).

        prepared: the scene (drsplat.raster.PreparedScene, means [N, 3] float64).
        """
        if self.weighting == "paper" and not self.reject:
            return out.weights
        projected = None
        if self.needs_projection:
            from drsplat.raster import project_gaussians

            projected = project_gaussians(prepared, camera)
        if self.reject:
            # camera z of every mean, as the rasterizer sorts by (a projection is not needed for it)
            depths = projected.depths if projected is not None else camera_depths(prepared.means, camera)
            surface_stats(out.ids, out.weights, depths, self.support.peak, self.support.total, self.support.front)
        if self.weighting == "paper":
            return out.weights
        means2d = projected.means2d if projected is not None else np.zeros((0, 2))
        conics = projected.conics if projected is not None else np.zeros((0, 3))
        self._buffer = view_weights(self.weighting, out.ids, out.weights, means2d, conics, self._buffer)
        return self._buffer

    def finish(self, F: np.ndarray, W: np.ndarray) -> int:
        """Post-step on the sums F [N, D], W [N]: rejected Gaussians get W = 0 and F = 0 (unassigned).
        Returns the number of Gaussians rejected that had weight."""
        if not self.reject:
            return 0
        drop = self.support.rejected() & (W > 0)
        F[drop] = 0.0
        W[drop] = 0.0
        self.num_rejected = int(np.count_nonzero(drop))
        log.info("%s: %d Gaussians rejected as unsupported (floaters / haze in front of the surface)", self.mode, self.num_rejected)
        return self.num_rejected

    def state(self) -> dict[str, np.ndarray]:
        """Arrays to checkpoint (empty for modes without statistics)."""
        if self.support is None:
            return {}
        return {"peak": self.support.peak, "total": self.support.total, "front": self.support.front}

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        if self.support is not None and arrays:
            self.support = SurfaceSupport(*(np.asarray(arrays[k], np.float64).copy() for k in ("peak", "total", "front")))
