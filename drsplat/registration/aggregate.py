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
                                                       much as its whole footprint, an occluded one little;
                                                       A_i is capped at the view's H·W pixels (no footprint
                                                       covers more of it; uncapped, a Gaussian of log scale
                                                       ≥ ~50 made the centre's weight overflow float32)
    sharp           w · max(exp(-½ dᵀ (Σ₀⁻¹ - Σ'⁻¹) d), SHARP_FLOOR)
                                                       the Gaussian's own footprint before 3DGS's screen-space
                                                       low-pass filter: Σ' = Σ₂ + 0.3·I is what the rasterizer
                                                       evaluates (Σ₂ = J W Σ Wᵀ Jᵀ), Σ₀ = Σ₂ + SHARP_BLUR·I
                                                       keeps 0.001 px² of it (positive definite for a point-
                                                       like Gaussian too); so w̃ = T·o·exp(-½ dᵀ Σ₀⁻¹ d) where
                                                       α is not clamped: the pixel centre sampled through the
                                                       surface patch's true extent, as a ray-cast silhouette
                                                       is. Σ₀ ⪯ Σ' makes the factor ≤ 1; it is ~1 over a
                                                       Gaussian many pixels wide and falls off fast around a
                                                       thin or small one. The floor (1e-4) keeps every
                                                       Gaussian the paper assigns assigned (one that never
                                                       covers a pixel centre keeps the paper's proportions)
    fit             per registration, paper or sharp: the footprint whose labelling re-renders a few
                    probe views' masks better (drsplat.registration.fit)
    reject          w, then floater rejection
    core-reject     core, then floater rejection
    ellipse-reject  ellipse, then floater rejection
    anchor-reject   anchor, then floater rejection
    sharp-reject, sharp-vote, sharp-vote-reject, fit-reject, fit-vote, fit-vote-reject   the stages in that order
    explain         w redistributed between the view's masks by who explains each pixel's mask
                    (per-view EM, `explain_weights`: a label-space stand-in for a render-consistent
                    solve); the Gaussian's total weight in the view is kept
    vote            w, then the mean trimmed of clusters of masks that a minority of views vote
                    for (drsplat.registration.vote: mislabelled masks outvoted)
    explain-reject, explain-vote, vote-reject, explain-vote-reject   the stages in that order
    solve           w, then the render-consistent solve on the sums (drsplat.registration.solve:
                    features that re-render the views' masks best, Tikhonov toward the paper's
                    mean, conjugate gradients; one block in memory only)
    solve-reject, solve-vote, solve-vote-reject   the solve on the (vote-trimmed) sums, then rejection
    check           w, with the masks that the other views contradict dropped before the sums
                    (drsplat.registration.check: a mislabelled mask judged over all its Gaussians;
                    one block in memory only)
    check-reject, check-vote, check-vote-reject   the check, then the vote and / or rejection
    sharp-check-vote-reject, fit-check-vote-reject   the check on the sharp / the fit stage's weights
    sharp-check-vote, fit-check-vote   the same without floater rejection, which also drops Gaussians of
                    a semi-transparent object (glass) that never reach ½ of a pixel's weight: the
                    default's counterpart for scenes that hold such objects

A mode's name lists its stages, "[WEIGHTING][-check][-vote][-reject]" (`mode_stages`); WEIGHTING
"solve" means the paper's w in the views and the solve stage on the sums; "check" alone, the
paper's w and the check stage before the sums.

d is the offset of the Gaussian's screen mean from the pixel centre and Σ' its screen covariance,
exactly as the compositor evaluates α = min(0.99, o·exp(-½ d²)); the 2σ ellipse always holds
the pixel centre nearest to the mean (Σ' ⪰ 0.3 I, so that centre is at d² ≤ 0.5/0.3 < 4).
centre and anchor target masks that follow true silhouettes (a SAM mask of a photo; the
`hard-silhouette` preset): a Gaussian straddling a thin object's silhouette puts most of its
footprint on the background's mask, while its centre lies on the object. On masks made by the
Gaussians' own weighted vote (the other hard-* presets) the paper's w is what drew the boundaries,
and both lose (docs/registration.md, "Centre and anchor weightings"; how c = ANCHOR_GAIN was chosen:
"Design choices, measured").

Floater rejection (`SurfaceSupport`). Depths are taken where the pixel's ray meets a Gaussian,
not at its mean: t*_i(p) = dᵀ Σ_i⁻¹ (μ_i - o) / dᵀ Σ_i⁻¹ d, the point of largest density along the
ray o + t·d (camera z = t), clamped to the mean's depth ± 3 max scale (`ray_depths_reference`;
the mean's depth itself where dᵀ Σ_i⁻¹ d is not positive or not a number). For a flat Gaussian that is the plane it lies in, so a large floor or wall Gaussian seen at a
grazing angle is not "in front" of its own surface over the far half of its footprint. In every view, pixel p's surface depth D(p) = t* of the pixel's median Gaussian, the
one whose contribution takes the transmittance T from above ½ to ≤ ½ (the rasterizer returns it:
`rasterize(..., with_median=True)`; D = +∞ where the opacity never reaches ½). A contribution of
Gaussian i at p is *in front* when

    t*_i(p) < (1 - τ)·D(p)  and  t*_i(p) < D(p) - κ·s_i,   τ = 0.05, κ = 1,

s_i its largest scale (reach_i / 3): in front of the surface by a share of its depth and by more
than its own extent, so haze that touches the surface it hangs over is not a floater (real splats,
docs/hostile.md "Round 31b": biker's clean rooms -0.005 -> -0.002 against `paper`, the hard rooms'
floaters kept unchanged). Over all views Gaussian i
collects its peak weight P_i = max_p w_i(p), its total weight A_i = Σ_p w_i(p), its in-front
weight B_i = Σ_p w_i(p)·[in front], the number of views that see it V_i and the number of those
in which more than half of its weight is in front, F_i. It is rejected (left unassigned, W_i = 0)
when

    P_i < ½  and  B_i > ½·A_i  and  F_i > ½·V_i

i.e. it is never the dominant contribution of any pixel and mostly renders as haze in front of
the visible surface, by weight and in most views: what a floater or a faint blob in free space
does. Faint Gaussians lying on a surface (D ≈ their depth) and thin opaque structures (P ≥ ½ at
their centre pixels) are kept. The view vote keeps surface Gaussians whose weight is dominated
by one close-up view in which a box edge puts them in front of a neighbour's plane (what each of
these choices changed on the hard rooms: docs/registration.md, "Design choices, measured").
A view's sums add each w in fixed point (int64 units of 2⁻³², STATS_SCALE; exact up to 2³¹ pixels of
weight 1), so they are the same integers in any order: the view's pixels are cut into parts summed
in parallel, on the host, and the torch engine's atomics on a GPU give the same bits.
Memory: five [N] arrays for the statistics (32 bytes per Gaussian), per-view scratch (8 bytes, and
28 per part of the view's pixels: `stats_parts`) and the scene's means, Σ⁻¹ and reach (80 bytes,
`RayGeometry`); nothing per (Gaussian, mask).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numba
import numpy as np

from drsplat.defaults import AGGREGATE_MODES, CHECK_SLOTS, EXACT_TRIM_SLOT_BYTES, GAUSSIAN_TERM_BYTES, SOLVE_SLOTS, SPECIFICITY_SLOT_BYTES, VOTE_SLOT_BYTES
from drsplat.memory import small_page_zeros
from drsplat._raster_kernels import BLUR
from drsplat.raster import NEAR, PreparedScene, project_gaussians
from drsplat.scene import counted

log = logging.getLogger(__name__)

WEIGHTINGS = ("paper", "core", "ellipse", "responsibility", "centre", "anchor", "sharp")  # per-pixel (`view_weights`)
MASK_WEIGHTINGS = ("explain",)  # also read the view's masks (`explain_weights`)
ELLIPSE_D2 = 4.0  # squared Mahalanobis radius of the ellipse mode (2σ)
EXPLAIN_ITERATIONS = 3  # EM iterations of the explain weighting per view (docs/registration.md, "Design choices, measured")
ANCHOR_GAIN = 1.0  # c of the anchor mode: the centre pixel's extra vote, in units of the Gaussian's footprint
SHARP_BLUR = 0.001  # px² of 3DGS's 0.3 px² low-pass filter the sharp weighting keeps (module docstring)
SHARP_FLOOR = 1e-4  # the sharp factor's floor: a Gaussian the paper assigns stays assigned (module docstring)
SHARP_LOG_FLOOR = float(np.log(SHARP_FLOOR))  # below this exponent the factor is the floor
# `sharp_exp`: exp(q) = exp(q / 2^s)^(2^s), s = SHARP_EXP_SQUARINGS, with 1/n!, n = 9 .. 0, the Taylor terms of exp(q / 2^s)
SHARP_EXP_SQUARINGS = 5
SHARP_EXP_TERMS = tuple(1.0 / math.factorial(n) for n in range(9, -1, -1))
FRONT_TOLERANCE = 0.05  # τ: relative depth margin of "in front of the surface"
FRONT_SCALES = 1.0  # κ: "in front" also by more than this many of the Gaussian's largest scale
FRONT_REACH_SHARE = FRONT_SCALES / 3.0  # κ·s_i = FRONT_REACH_SHARE·reach_i (RayGeometry.reach = 3·largest scale)
PEAK_MIN = 0.5  # a Gaussian with P_i ≥ this is never rejected
FRONT_MAX = 0.5  # rejected when more than this share of its weight is in front of the surface

_WEIGHTING_CODE = {"paper": 0, "core": 1, "ellipse": 2, "responsibility": 3, "centre": 4, "anchor": 5, "sharp": 6}
PROJECTED_WEIGHTINGS = ("core", "ellipse", "centre", "anchor", "sharp")  # weightings that need the view's screen means / conics


@dataclass(frozen=True)
class Stages:
    """A mode as its stages: the per-view weighting, then (vote) the weighted mean trimmed by robust
    votes across views (drsplat.registration.vote), then (reject) floater rejection."""

    weighting: str
    vote: bool
    reject: bool
    solve: bool = False  # the render-consistent solve on the sums (weighting "paper" in the views)
    check: bool = False  # masks dropped by the cross-view check before the sums (drsplat.registration.check)

    @property
    def specific(self) -> bool:
        """Whether the vote also trims by specificity (drsplat.registration.vote, step 4): on sharp
        footprints (masks that follow true silhouettes), after the cross-view check, whose supports
        give the masks' mean pair weights."""
        return self.weighting == "sharp" and self.check and self.vote


def mode_stages(mode: str) -> Stages:
    """The stages of a mode name "[WEIGHTING][-check][-vote][-reject]" ("vote" or "check" alone:
    paper weights; "solve" is a stage on the paper's weights); ValueError for an unknown mode."""
    if mode not in AGGREGATE_MODES:
        raise ValueError(f"unknown aggregation mode {mode!r} (choose from {', '.join(AGGREGATE_MODES)})")
    parts = mode.split("-")
    reject = parts[-1] == "reject"
    parts = parts[:-1] if reject else parts
    vote = bool(parts) and parts[-1] == "vote"
    parts = parts[:-1] if vote else parts
    if parts and parts[0] == "solve":
        return Stages("paper", vote, reject, solve=True)
    check = bool(parts) and parts[-1] == "check"
    parts = parts[:-1] if check else parts
    return Stages(parts[0] if parts else "paper", vote, reject, check=check)


def without_rejection(mode: str) -> str:
    """`mode` without its floater rejection: "fit-check-vote-reject" -> "fit-check-vote", "reject" ->
    "paper"; a mode that rejects nothing is returned as it is."""
    if not mode_stages(mode).reject:
        return mode
    return mode[: -len("-reject")] if mode != "reject" else "paper"


def keep_all_remedy(asked: str | None, mode: str) -> str:
    """The `--aggregate` that keeps what the rejection of `mode` (the concrete mode the run used)
    dropped: `mode` without its rejection, so the footprint a fit mode chose stays; `asked` (the mode
    as the user named it) without its rejection fits again, scoring the floaters it keeps, and can
    choose the other footprint (round 100e F2: `fit-check-vote` went back to the filtered footprint
    and lost a thin pole, 0.833 -> 0.276 IoU, to keep a glass box), so it is named as the other way."""
    kept = without_rejection(mode)
    refit = without_rejection(asked) if asked is not None else kept
    if refit == kept:
        return f"--aggregate {kept} keeps all"
    return f"--aggregate {kept} keeps all with this run's footprint ({refit} fits it again)"


def without_check(mode: str) -> str:
    """`mode` without its cross-view mask check: "fit-check-vote-reject" -> "fit-vote-reject",
    "check" -> "paper", "check-reject" -> "reject"; a mode without the check is returned as it is."""
    if not mode_stages(mode).check:
        return mode
    return "-".join(part for part in mode.split("-") if part != "check") or "paper"


def split_mode(mode: str) -> tuple[str, bool]:
    """(weighting, reject) of a mode name; ValueError for an unknown mode."""
    stages = mode_stages(mode)
    return stages.weighting, stages.reject


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
        area = np.minimum(footprint_area(conics), float(h * wd))[g]
        return (w * (1.0 + anchor_gain * area * at_centre)).astype(np.float32)
    if weighting == "sharp":
        da, db, dc = sharpening(conics).T
        q = -0.5 * (da[g] * dx * dx + dc[g] * dy * dy) - db[g] * dx * dy
        return (w * np.maximum(np.exp(np.minimum(q, 0.0)), SHARP_FLOOR)).astype(np.float32)
    raise ValueError(f"unknown weighting {weighting!r}")


def sharpening(conics: np.ndarray) -> np.ndarray:
    """[N, 3] (a, b, c) of Δ = Σ₀⁻¹ - Σ'⁻¹ for conics [N, 3] = Σ'⁻¹ (the sharp weighting's
    exponent is -½ dᵀ Δ d): Σ' = conic⁻¹, Σ₀ = Σ' - (BLUR - SHARP_BLUR)·I. Rows whose conic or Σ₀
    is not positive definite (not rendered, or rounding) get Δ = 0: the paper's weight."""
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
    det = a * c - b * b
    ok = det > 0
    safe = np.where(ok, det, 1.0)
    sxx = c / safe - (BLUR - SHARP_BLUR)
    sxy = -b / safe
    syy = a / safe - (BLUR - SHARP_BLUR)
    det0 = sxx * syy - sxy * sxy
    ok &= (det0 > 0) & (sxx > 0)
    safe0 = np.where(ok, det0, 1.0)
    delta = np.stack([syy / safe0 - a, -sxy / safe0 - b, sxx / safe0 - c], axis=1)
    return np.where(ok[:, None], delta, 0.0)


def footprint_area(conics: np.ndarray) -> np.ndarray:
    """[N] A = 2π·sqrt(det Σ') = 2π / sqrt(a·c - b²) of conics [N, 3]: Σ_p exp(-½ d²) over the
    pixels, the Gaussian's screen footprint in pixels (0 where the conic is degenerate)."""
    det = conics[:, 0] * conics[:, 2] - conics[:, 1] ** 2
    return np.where(det > 0, 2.0 * np.pi / np.sqrt(np.where(det > 0, det, 1.0)), 0.0)


@numba.njit(parallel=True, cache=True)
def _view_weights_kernel(code, ids, weights, means2d, conics, ellipse_d2, anchor_gain, out):  # pragma: no cover - jitted
    """out[y, x, s] = the weighting `code` (see _WEIGHTING_CODE) of slot s of pixel (x, y)."""
    h, wd, k = ids.shape
    view_pixels = np.float64(h * wd)  # the anchor's footprint cap
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
                        area = min(2.0 * np.pi / np.sqrt(det), view_pixels) if det > 0.0 else 0.0
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
    if weighting == "sharp":
        return sharp_weights(ids, weights, means2d, conics, out=out)[0]
    if out is None or out.shape != ids.shape:
        out = np.empty(ids.shape, np.float32)
    ids, weights = np.ascontiguousarray(ids, np.int32), np.ascontiguousarray(weights, np.float32)
    means2d, conics = np.ascontiguousarray(means2d, np.float64), np.ascontiguousarray(conics, np.float64)
    _view_weights_kernel(_WEIGHTING_CODE[weighting], ids, weights, means2d, conics, ELLIPSE_D2, float(anchor_gain), out)
    return out


def sharp_weights(ids: np.ndarray, weights: np.ndarray, means2d: np.ndarray, conics: np.ndarray, rows: np.ndarray | None = None,
                  num_gaussians: int | None = None, screen: np.ndarray | None = None, out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """`view_weights("sharp", ...)` from a projection of some of the scene's Gaussians: means2d [V, 2]
    and conics [V, 3] float64 of the Gaussians rows [V] (scene ids; None: row i is Gaussian i). ids,
    weights: [H, W, k] (every id among rows). Only those V rows of the [N, 5] screen table
    (`_sharp_screen_kernel`) are made, so a culled view costs O(V + slots), not O(N) (num_gaussians:
    N, default V). screen: an [N, 5] buffer to reuse; out: a [H, W, k] float32 one. Returns (out,
    screen). The same bits as one formula per slot."""
    ids, weights = np.ascontiguousarray(ids, np.int32), np.ascontiguousarray(weights, np.float32)
    means2d, conics = np.ascontiguousarray(means2d, np.float64), np.ascontiguousarray(conics, np.float64)
    n = conics.shape[0] if num_gaussians is None else int(num_gaussians)
    if screen is None or screen.shape != (n, 5):
        screen = np.empty((n, 5))
    if out is None or out.shape != ids.shape:
        out = np.empty(ids.shape, np.float32)
    rows = np.arange(conics.shape[0], dtype=np.int32) if rows is None else np.ascontiguousarray(rows, np.int32)
    if rows.shape[0] != conics.shape[0] or (rows.size and (rows.min() < 0 or rows.max() >= n)):  # the kernel writes screen[rows]: no row outside it
        raise ValueError(f"rows must name one of the scene's {n:,} Gaussians for each of the {conics.shape[0]:,} projected")
    _sharp_screen_kernel(means2d, conics, BLUR - SHARP_BLUR, rows, screen)
    parts = max(1, min(ids.shape[0], 4 * numba.get_num_threads()))  # runs of rows, each with one row buffer
    _sharp_weights_kernel(ids, weights, screen, SHARP_LOG_FLOOR, SHARP_FLOOR, parts, out)
    return out, screen

@numba.njit(inline="always")
def sharp_exp(q):  # pragma: no cover - jitted
    """exp(q) for SHARP_LOG_FLOOR ≤ q ≤ 0 as (Σ_{n ≤ 9} (q/32)ⁿ / n!)³²: Horner, then five squarings
    (relative error 4.5e-11 at most there, 1/1,300 of a float32 weight's half ulp: tests/test_fit.py).
    No library call, so a loop of it vectorises; the torch engine evaluates the same operations
    (`device_sums.sharp_exp_torch`). Degree 9 and five squarings cost what degree 10 and four do
    (14 multiplications) at 1/35 of the error; degree 14 and four squarings (until 2026-12-01,
    error 9e-15) made `view_weights("sharp")` take 3.4 ms per hard-room view and 17.7-18.2 ms per
    flowers view against 2.8-2.9 and 16.2-16.4, for the same float32 weights in all but 4 of 12.2 M
    and 251 of 52.7 M slots (one ulp each; docs/registration.md)."""
    t = q * (1.0 / (1 << SHARP_EXP_SQUARINGS))
    p = 0.0
    for c in SHARP_EXP_TERMS:
        p = p * t + c
    for _ in range(SHARP_EXP_SQUARINGS):
        p = p * p
    return p


@numba.njit(parallel=True, cache=True)
def _sharp_screen_kernel(means2d, conics, shift, rows, out):  # pragma: no cover - jitted
    """out[g] = (u, v, Δa, Δb, Δc): the screen mean means2d[i] beside `sharpening`(conics)[i] (the
    same operations) of the Gaussian g = rows[i], in parallel over the rows:
    what `_sharp_weights_kernel` reads per slot, in one 40-byte row instead of rows of two arrays."""
    for i in numba.prange(conics.shape[0]):
        g = rows[i]
        a, b, c = conics[i, 0], conics[i, 1], conics[i, 2]
        out[g, 0] = means2d[i, 0]
        out[g, 1] = means2d[i, 1]
        out[g, 2] = out[g, 3] = out[g, 4] = 0.0
        det = a * c - b * b
        if det > 0.0:
            sxx, sxy, syy = c / det - shift, -b / det, a / det - shift
            det0 = sxx * syy - sxy * sxy
            if det0 > 0.0 and sxx > 0.0:
                out[g, 2] = syy / det0 - a
                out[g, 3] = -sxy / det0 - b
                out[g, 4] = sxx / det0 - c


@numba.njit(parallel=True, cache=True)
def _sharp_weights_kernel(ids, weights, screen, log_floor, floor, parts, out):  # pragma: no cover - jitted
    """out = the sharp weighting of each slot (screen: [N, 5] rows of `_sharp_screen_kernel`), over
    `parts` runs of rows in parallel: per pixel, first
    the exponents q = -½ dᵀ Δ d of its slots up to the first empty one (gathers), then w ·
    max(sharp_exp(clamp(q, log_floor, 0)), floor) over those slots in one branch-free loop
    (vectorised); the slots from the first empty one on (the padding: every engine puts it last)
    one by one, 0 where empty. The same bits as one formula per slot."""
    h, wd, k = ids.shape
    for part in numba.prange(parts):
        q = np.empty(k)  # one pixel's exponents
        for y in range(part * h // parts, (part + 1) * h // parts):
            py = y + 0.5
            for x in range(wd):
                px = x + 0.5
                n = 0
                while n < k and ids[y, x, n] >= 0:
                    g = ids[y, x, n]
                    dx = screen[g, 0] - px
                    dy = screen[g, 1] - py
                    q[n] = -0.5 * (screen[g, 2] * dx * dx + screen[g, 4] * dy * dy) - screen[g, 3] * dx * dy
                    n += 1
                for s in range(n):
                    out[y, x, s] = np.float64(weights[y, x, s]) * max(sharp_exp(min(max(q[s], log_floor), 0.0)), floor)
                for s in range(n, k):
                    g = ids[y, x, s]
                    if g < 0:
                        out[y, x, s] = 0.0
                        continue
                    dx = screen[g, 0] - px
                    dy = screen[g, 1] - py
                    qs = -0.5 * (screen[g, 2] * dx * dx + screen[g, 4] * dy * dy) - screen[g, 3] * dx * dy
                    out[y, x, s] = np.float64(weights[y, x, s]) * max(sharp_exp(min(max(qs, log_floor), 0.0)), floor)


SHARP_FIRST_RUN_PROBE = _sharp_weights_kernel  # the sharp footprint's kernel whose place in numba's cache shows it ran here before (driver.say_if_kernels_compile)


# ----------------------------------------------------------------------------- per-view explanation (EM)


def explain_weights_reference(ids: np.ndarray, weights: np.ndarray, mask_ids: np.ndarray, iterations: int = EXPLAIN_ITERATIONS) -> np.ndarray:
    """Per-pixel weights of the "explain" weighting (numpy reference; math in `explain_weights`).

    ids, weights: [H, W, k] top-k ids (-1 none) and w = T·α; mask_ids: [H, W] the view's mask
    per pixel (-1 none). Returns [H, W, k] float32 (0 where ids < 0 or the pixel has no mask).
    """
    k = ids.shape[-1]
    g = ids.reshape(-1, k).astype(np.int64)
    m = np.broadcast_to(mask_ids.reshape(-1, 1), g.shape).astype(np.int64)
    w = weights.reshape(-1, k).astype(np.float64)
    valid = (g >= 0) & (m >= 0)
    out = np.zeros(g.shape, np.float64)
    if not valid.any():
        return out.reshape(ids.shape).astype(np.float32)
    base = int(m[valid].max()) + 1
    keys, pair = np.unique(g[valid] * base + m[valid], return_inverse=True)
    pair_g = keys // base
    gauss, owner = np.unique(pair_g, return_inverse=True)
    wv = w[valid]
    v = np.bincount(pair, wv, keys.size)  # w_ij of the view (the paper's pair weights)
    total = np.bincount(owner, v, gauss.size)  # T_i
    t = total[owner]
    q = np.where(t > 0, v / np.where(t > 0, t, 1.0), 0.0)
    slot_pair = np.full(g.shape, -1, np.int64)
    slot_pair[valid] = pair
    for _ in range(iterations):
        share = np.where(valid, w * q[np.maximum(slot_pair, 0)], 0.0)
        denom = share.sum(axis=1, keepdims=True)
        r = np.where(denom > 0, share / np.where(denom > 0, denom, 1.0), 0.0)
        c = np.bincount(pair, r[valid], keys.size)
        rsum = np.bincount(owner, c, gauss.size)
        q = np.where(rsum[owner] > 0, c / np.where(rsum[owner] > 0, rsum[owner], 1.0), q)
    scale = np.where(v > 0, total[owner] * q / np.where(v > 0, v, 1.0), 0.0)
    out[valid] = wv * scale[pair]
    return out.reshape(ids.shape).astype(np.float32)


@numba.njit(cache=True)
def _explain_kernel(ids, weights, mask_ids, iterations, seen, slot_pair, out):  # pragma: no cover - jitted
    """out[p, s] = the "explain" weight of slot s of pixel p (`explain_weights`); serial, float64 sums.

    seen [N] int32 (-1 on entry and exit), slot_pair [P, k] int32 scratch.
    """
    n_pix, k = ids.shape
    n_pairs = 0
    # pair index of every slot: (Gaussian, mask) pairs in first-seen order of the slots
    pair_g = np.empty(n_pix * k, np.int32)
    pair_m = np.empty(n_pix * k, np.int32)
    head = np.empty(n_pix * k, np.int32)  # per pair: next pair of the same Gaussian (linked lists per Gaussian)
    for p in range(n_pix):
        m = mask_ids[p]
        for s in range(k):
            g = ids[p, s]
            if g < 0 or m < 0:
                slot_pair[p, s] = -1
                continue
            # walk Gaussian g's pairs (few: the masks it touches in this view)
            j = seen[g]
            found = -1
            while j >= 0:
                if pair_m[j] == m:
                    found = j
                    break
                j = head[j]
            if found < 0:
                found = n_pairs
                pair_g[found] = g
                pair_m[found] = m
                head[found] = seen[g]
                seen[g] = found
                n_pairs += 1
            slot_pair[p, s] = found
    v = np.zeros(n_pairs)
    for p in range(n_pix):
        for s in range(k):
            j = slot_pair[p, s]
            if j >= 0:
                v[j] += weights[p, s]
    q = np.empty(n_pairs)
    total = np.zeros(n_pairs)  # T_i of the pair's Gaussian, stored per pair
    c = np.zeros(n_pairs)
    for j in range(n_pairs):  # per Gaussian (at its newest pair, the head of its list): T_i and q_ij
        g = pair_g[j]
        if seen[g] != j:
            continue
        t = 0.0
        i = j
        while i >= 0:
            t += v[i]
            i = head[i]
        i = j
        while i >= 0:
            total[i] = t
            q[i] = v[i] / t if t > 0.0 else 0.0
            i = head[i]
    for _ in range(iterations):
        c[:] = 0.0
        for p in range(n_pix):
            denom = 0.0
            for s in range(k):
                j = slot_pair[p, s]
                if j >= 0:
                    denom += np.float64(weights[p, s]) * q[j]
            if denom > 0.0:
                for s in range(k):
                    j = slot_pair[p, s]
                    if j >= 0:
                        c[j] += np.float64(weights[p, s]) * q[j] / denom
        for j in range(n_pairs):
            g = pair_g[j]
            if seen[g] != j:
                continue
            rs = 0.0
            i = j
            while i >= 0:
                rs += c[i]
                i = head[i]
            if rs > 0.0:
                i = j
                while i >= 0:
                    q[i] = c[i] / rs
                    i = head[i]
    for p in range(n_pix):
        for s in range(k):
            j = slot_pair[p, s]
            if j < 0:
                out[p, s] = 0.0
            elif v[j] > 0.0:
                out[p, s] = np.float64(weights[p, s]) * (total[j] * q[j] / v[j])
            else:
                out[p, s] = 0.0
    for j in range(n_pairs):
        seen[pair_g[j]] = -1
    return n_pairs


def explain_weights(ids: np.ndarray, weights: np.ndarray, mask_ids: np.ndarray, num_gaussians: int, iterations: int = EXPLAIN_ITERATIONS,
                    out: np.ndarray | None = None, seen: np.ndarray | None = None) -> np.ndarray:
    """The "explain" weighting of one view: which of a pixel's Gaussians explain its mask (EM).

    ids, weights: [H, W, k] top-k ids (-1 none) and w = T·α; mask_ids: [H, W] (-1 none); out: a
    [H, W, k] float32 buffer to reuse. Returns [H, W, k] float32.

    Model: pixel p's mask m(p) was emitted by one of its Gaussians, Gaussian i chosen with
    probability ∝ w_i(p), and Gaussian i emits mask j of this view with probability q_ij. EM from
    the paper's shares q_ij = w_ij / T_i (w_ij = Σ_{p ∈ j} w_i(p), T_i = Σ_j w_ij):

        E: r_i(p) = w_i(p)·q_{i,m(p)} / Σ_s w_s(p)·q_{s,m(p)}     (who explains pixel p's mask)
        M: q_ij = Σ_{p ∈ j} r_i(p) / Σ_p r_i(p)

    `iterations` times, then the view contributes T_i·q_ij to pair (i, j) (each slot's share
    proportional to its w): a Gaussian's total weight in the view stays the paper's (so coverage
    and floater statistics do not change), only its split between masks does. A silhouette
    Gaussian whose footprint spills onto the background keeps its object's mask, because the
    background's own Gaussians explain the background pixels (r small there) while on the
    object's pixels only the object's Gaussians compete. This is a per-view, label-space stand-in
    for the render-consistent least-squares solve (it never mixes views, so it costs one pass over
    the view's slots per iteration and no memory beyond the view: slot → pair indices [H·W·k]
    int32 and per-pair float64 arrays).
    """
    h, w, k = ids.shape
    ids2 = np.ascontiguousarray(ids.reshape(-1, k), np.int32)
    if out is None or out.shape != ids.shape:
        out = np.empty(ids.shape, np.float32)
    if seen is None or seen.shape[0] != num_gaussians:
        seen = np.full(num_gaussians, -1, np.int32)
    slot_pair = np.empty(ids2.shape, np.int32)
    _explain_kernel(ids2, np.ascontiguousarray(weights.reshape(-1, k), np.float32), np.ascontiguousarray(mask_ids.reshape(-1), np.int32),
                    int(iterations), seen, slot_pair, out.reshape(-1, k))
    return out


# ----------------------------------------------------------------------------- floater rejection


@dataclass
class RayGeometry:
    """What the depth at which a pixel's ray meets a Gaussian needs (one scene, every view).

    means: [N, 3] float64; precisions: [N, 6] float64 Σ⁻¹ = R S⁻² Rᵀ as (xx, xy, xz, yy, yz, zz);
    reach: [N] float64 3·(largest scale), the clamp of the ray depth around the mean's depth.
    """

    means: np.ndarray
    precisions: np.ndarray
    reach: np.ndarray

    @classmethod
    def from_scene(cls, scene, chunk: int = 1 << 20) -> RayGeometry:
        """From a GaussianScene (Σ⁻¹ built from quaternions and scales, `GaussianScene.packed_precisions`:
        exact for flat Gaussians), `chunk` Gaussians at a time, so the float64 temporaries (~100 bytes
        per Gaussian: 5 GB at 50M in one go) stay ~100 MB; every row is the same as in one go."""
        n = scene.num_gaussians
        out = cls(np.empty((n, 3)), np.empty((n, 6)), np.empty(n))
        for start in range(0, n, chunk):
            part = scene.subset(slice(start, start + chunk))
            stop = start + part.num_gaussians
            part.packed_precisions(out=out.precisions[start:stop])
            with np.errstate(over="ignore", invalid="ignore"):
                reach = 3.0 * np.exp(part.log_scales.astype(np.float64)).max(axis=1)
            means = np.asarray(part.means, np.float64)
            bad = ~(np.isfinite(reach) & np.isfinite(means).all(axis=1))
            out.means[start:stop] = np.where(bad[:, None], 0.0, means)
            out.reach[start:stop] = np.where(bad, 0.0, reach)
        return out


def ray_depths_reference(geometry: RayGeometry, camera, ids: np.ndarray) -> np.ndarray:
    """Camera depth at which pixel p's ray meets Gaussian ids[p, s] (numpy reference).

    ids: [H, W, k] (-1 none). The ray o + t·d (d = Rᵀ((x + ½ - cx)/fx, (y + ½ - cy)/fy, 1), so
    camera z = t) meets Gaussian i where its density is largest along the ray:

        t* = dᵀ Σ⁻¹ (μ - o) / dᵀ Σ⁻¹ d

    (the plane a flat Gaussian lies in; the mean's projection onto the ray for a round one),
    clamped to z_i ± 3·max scale (z_i the mean's camera depth; z_i itself where dᵀΣ⁻¹d ≤ 0).
    Returns [H, W, k] float64, +inf where ids < 0.
    """
    h, w, k = ids.shape
    if (h, w) != (camera.height, camera.width):
        raise ValueError(f"top-k lists of {w}x{h} pixels do not match the {camera.width}x{camera.height} camera")
    origin = camera.ray_origin()
    ys, xs = np.mgrid[0:h, 0:w]
    rx, ry = (xs.ravel() + 0.5 - camera.cx) / camera.fx, (ys.ravel() + 0.5 - camera.cy) / camera.fy
    rm = np.asarray(camera.R, np.float64)
    # d and z summed left to right, as the kernel sums them: `pixel_rays`' matrix product rounds as the BLAS does, and a
    # depth a few ulps from the in-front limit then fell on the other side of it (round 86b F1)
    dirs = np.stack([rm[0, j] * rx + rm[1, j] * ry + rm[2, j] for j in range(3)], axis=1)
    g = np.maximum(ids.reshape(-1, k), 0)
    p = geometry.precisions[g]  # [P, k, 6]
    d = dirs[:, None, :]
    v = geometry.means[g] - origin
    rot, trans = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64)
    m = geometry.means[g]
    zc = rot[2, 0] * m[..., 0] + rot[2, 1] * m[..., 1] + rot[2, 2] * m[..., 2] + trans[2]  # the kernel's order, not BLAS's
    reach = geometry.reach[g]
    # precisions of ±inf (hostile geometry) give inf - inf = NaN here, as in the kernel: no numpy warning for it
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        pd = np.stack([p[..., 0] * d[..., 0] + p[..., 1] * d[..., 1] + p[..., 2] * d[..., 2],
                       p[..., 1] * d[..., 0] + p[..., 3] * d[..., 1] + p[..., 4] * d[..., 2],
                       p[..., 2] * d[..., 0] + p[..., 4] * d[..., 1] + p[..., 5] * d[..., 2]], axis=-1)
        num = (pd * v).sum(-1)
        den = (pd * d).sum(-1)
        t = np.where(den > 0, np.clip(num / np.where(den > 0, den, 1.0), zc - reach, zc + reach), zc)
    return np.where(ids.reshape(-1, k) >= 0, t, np.inf).reshape(h, w, k)


@dataclass
class ViewStats:
    """One view's rejection statistics of the Gaussians it sees (each id once): ids [T] int32;
    peak (max w), total (Σ w) and front (Σ w in front of the surface) [T] float64."""

    ids: np.ndarray
    peak: np.ndarray
    total: np.ndarray
    front: np.ndarray


@numba.njit(cache=True)
def _fold_stats_kernel(ids, peak_v, total_v, front_v, front_max, peak, total, front, views_seen, views_front):  # pragma: no cover - jitted
    """SurfaceSupport.add's fold in one pass over the view's (distinct) ids; NaN propagates through
    the max as np.maximum's does."""
    for j in range(ids.shape[0]):
        i = ids[j]
        p, v = peak[i], peak_v[j]
        if v > p or v != v:
            peak[i] = v
        total[i] += total_v[j]
        front[i] += front_v[j]
        views_seen[i] += 1
        if front_v[j] > front_max * total_v[j]:
            views_front[i] += 1


REJECT_FIRST_RUN_PROBE = _fold_stats_kernel  # the floater rejection's kernel whose place in numba's cache shows it ran here before (driver.say_if_kernels_compile)


@dataclass
class SurfaceSupport:
    """The rejection statistics of a registration, [N] each: peak (max w), total (A = Σ w),
    front (B = Σ w in front of the surface) as float64; views_seen (views that see the Gaussian) and
    views_front (views in which more than FRONT_MAX of its weight is in front) as int32."""

    peak: np.ndarray
    total: np.ndarray
    front: np.ndarray
    views_seen: np.ndarray
    views_front: np.ndarray

    @classmethod
    def zeros(cls, n: int) -> SurfaceSupport:
        zeros = small_page_zeros  # made once a registration, touched a view's Gaussians at a time: small pages
        return cls(zeros(n, np.float64), zeros(n, np.float64), zeros(n, np.float64), zeros(n, np.int32), zeros(n, np.int32))

    def rejected(self) -> np.ndarray:
        """[N] bool: P < PEAK_MIN, B > FRONT_MAX·A and views_front > FRONT_MAX·views_seen (never seen: kept)."""
        return ((self.total > 0) & (self.peak < PEAK_MIN) & (self.front > FRONT_MAX * self.total)
                & (self.views_front > FRONT_MAX * self.views_seen))

    def arrays(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def add(self, view: ViewStats) -> None:
        """Fold one view's statistics in (views are folded in view order, so the sums do not depend
        on where the views were computed): for each Gaussian i the view sees,

            P_i = max(P_i, p_i),  A_i += a_i,  B_i += b_i,  views_seen_i += 1,  views_front_i += [b_i > FRONT_MAX·a_i]

        in one pass (`_fold_stats_kernel`; `add_reference` is the numpy form, the same bits). It
        runs on the driver for every view of a `-reject` mode."""
        _fold_stats_kernel(np.ascontiguousarray(view.ids, np.int32), np.ascontiguousarray(view.peak, np.float64),
                           np.ascontiguousarray(view.total, np.float64), np.ascontiguousarray(view.front, np.float64), FRONT_MAX,
                           self.peak, self.total, self.front, self.views_seen, self.views_front)

    def add_reference(self, view: ViewStats) -> None:
        """`add` in numpy (the view's ids are distinct)."""
        ids = view.ids
        self.peak[ids] = np.maximum(self.peak[ids], view.peak)
        self.total[ids] += view.total
        self.front[ids] += view.front
        self.views_seen[ids] += 1
        self.views_front[ids] += view.front > FRONT_MAX * view.total

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> SurfaceSupport:
        """The statistics from `arrays()` output (KeyError naming a missing one)."""
        return cls(*(np.array(arrays[f.name], dtype=np.int32 if f.name.startswith("views") else np.float64) for f in dataclasses.fields(cls)))


STATS_SCALE = float(1 << 32)  # the per-view sums' fixed point: units of 2⁻³² in int64 (exact up to 2³¹ pixels of weight 1)
STATS_SCRATCH_BYTES = 28  # per Gaussian per part of `surface_stats`: its peak, total, front and view stamps
RAY_GEOMETRY_BYTES = 80  # per Gaussian of RayGeometry: mean (3 float64), precision (6 float64), reach (float64)
STATS_EXTRA_SCRATCH = 256 << 20  # scratch of the parts beyond the first (a 50M scene keeps one part: 1.4 GB each)


def fixed_weights(weights: np.ndarray) -> np.ndarray:
    """Each slot's w as the per-view sums add it: round(w · STATS_SCALE) in int64, w clipped to
    [0, 1] (the rasterizer's w = T·α lies in it) and NaN as 0. [...] float32 or float64 -> int64."""
    w = np.nan_to_num(np.clip(np.asarray(weights, np.float64), 0.0, 1.0), nan=0.0)
    return np.floor(w * STATS_SCALE + 0.5).astype(np.int64)


def in_front_reference(depth: np.ndarray, surface: np.ndarray, reach: np.ndarray, tolerance: float = FRONT_TOLERANCE) -> np.ndarray:
    """[...] bool: t* = depth in front of the pixel's surface D = surface (broadcast; +inf: none), by a
    share τ = tolerance of D and by more than κ·s = FRONT_REACH_SHARE·reach (reach: the Gaussian's
    3·largest scale):

        t* < (1 - τ)·D  and  t* < D - κ·s

    Two comparisons, not a min of the limits, so a NaN anywhere is "not in front" in every engine."""
    with np.errstate(invalid="ignore"):
        return (depth < (1.0 - tolerance) * surface) & (depth < surface - FRONT_REACH_SHARE * reach)


def surface_stats_reference(geometry: RayGeometry, camera, ids: np.ndarray, weights: np.ndarray, median_ids: np.ndarray,
                            tolerance: float = FRONT_TOLERANCE) -> ViewStats:
    """One view's rejection statistics (numpy reference; math in the module docstring).

    ids, weights: [H, W, k] (raw w = T·α); median_ids: [H, W] the rasterizer's median Gaussian
    (-1 where the pixel's opacity never reaches ½: D(p) = +inf). A contribution is in front
    when t*_i(p) < (1 - τ)·D(p) and t*_i(p) < D(p) - κ·s_i (`in_front_reference`), D(p) = t* of
    the median Gaussian at p. The sums add each w in
    fixed point (`fixed_weights`), so they are the same integers in any order; the peak is the
    largest w (NaN ignored).
    """
    k = ids.shape[-1]
    depth = ray_depths_reference(geometry, camera, ids).reshape(-1, k)
    surface = ray_depths_reference(geometry, camera, median_ids[..., None]).reshape(-1, 1)  # +inf where -1
    g = ids.reshape(-1, k)
    valid = g >= 0
    w = np.where(valid, weights.reshape(-1, k).astype(np.float64), 0.0)
    fixed = np.where(valid, fixed_weights(w), 0)
    in_front = in_front_reference(depth, surface, geometry.reach[np.maximum(g, 0)], tolerance)
    seen, inverse = np.unique(g[valid], return_inverse=True)
    peak, total, front = np.zeros(seen.size), np.zeros(seen.size, np.int64), np.zeros(seen.size, np.int64)
    np.fmax.at(peak, inverse, w[valid])
    np.add.at(total, inverse, fixed[valid])
    np.add.at(front, inverse, np.where(in_front, fixed, 0)[valid])
    return ViewStats(seen.astype(np.int32), peak, total / STATS_SCALE, front / STATS_SCALE)


@numba.njit(inline="always")
def _ray_depth(g, dx, dy, dz, ox, oy, oz, means, prec, reach, r2x, r2y, r2z, tz):  # pragma: no cover - jitted
    """t* of Gaussian g on the ray o + t·d (`ray_depths_reference`)."""
    p = prec[g]
    pdx = p[0] * dx + p[1] * dy + p[2] * dz
    pdy = p[1] * dx + p[3] * dy + p[4] * dz
    pdz = p[2] * dx + p[4] * dy + p[5] * dz
    mx, my, mz = means[g, 0], means[g, 1], means[g, 2]
    zc = r2x * mx + r2y * my + r2z * mz + tz
    den = pdx * dx + pdy * dy + pdz * dz
    if not den > 0.0:
        return zc
    t = (pdx * (mx - ox) + pdy * (my - oy) + pdz * (mz - oz)) / den
    return min(max(t, zc - reach[g]), zc + reach[g])


@numba.njit(inline="always")
def _fixed_weight(w, scale):  # pragma: no cover - jitted
    """`fixed_weights` of one slot: round(clip(w, 0, 1) · scale), 0 for NaN."""
    if not w > 0.0:
        return np.int64(0)
    return np.int64(math.floor(min(w, 1.0) * scale + 0.5))


@numba.njit(parallel=True, cache=True)
def _surface_stats_kernel(ids, weights, median_ids, width, means, prec, reach, rot, origin, tz, fx, fy, cx, cy, tolerance, scale,
                          candidates, near, sums, peaks, seen, stamp, flags, part_seen):  # pragma: no cover - jitted
    """The in-front test and the per-Gaussian sums of one view in one pass, in parallel over
    P = sums.shape[0] parts, part t taking the pixel rows t, t + P, t + 2P, ... with its own [N]
    scratch (rows interleaved: every part gets a share of the busy rows).

    Per slot (p, s), g = ids[p, s]: in front when t*_g(p) < (1 - τ)·D(p) and t*_g(p) < D(p) -
    κ·s_g (`in_front_reference`; D = +inf where median_ids[p] < 0); near [N] float64, each Gaussian's nearest clamp zc - reach, is computed
    first and settles most slots without Σ⁻¹ (t* is clamped to [zc - reach, zc + reach]; NaN is
    never < the limit), for the Gaussians `candidates` [V] int32 names: the view's cost follows
    what it sees, not the scene's size. Part t keeps, in one record per Gaussian (sums [P, N, 3] int64; peaks: the
    same memory as float64), peaks[t, g, 0] = max w, sums[t, g, 1] = Σ fixed w and sums[t, g, 2] =
    Σ fixed w·[in front] (`_fixed_weight`: exact in any order); seen[t, g] == stamp marks the
    Gaussians it saw, whose first slot sets the three values instead of adding to them, so nothing
    is cleared between views (stamp: a number no earlier view of these buffers used). One record,
    not three arrays: a slot touches two cache lines instead of four, and three arrays whose
    addresses fall on the same cache sets cannot evict one another (docs/registration.md).
    flags: [H·W, k] bool to receive the in-front test, or [0, k] for none. part_seen [P] int64:
    how many Gaussians each part saw (what the merge must find again, `surface_stats`).
    """
    for i in numba.prange(candidates.shape[0]):
        g = candidates[i]
        near[g] = rot[2, 0] * means[g, 0] + rot[2, 1] * means[g, 1] + rot[2, 2] * means[g, 2] + tz - reach[g]
    n_pix, k = ids.shape
    height = n_pix // width if width > 0 else 0
    parts = sums.shape[0]
    keep_flags = flags.shape[0] == n_pix
    for part in numba.prange(parts):
        part_count = np.int64(0)
        for y in range(part, height, parts):
            for p in range(y * width, (y + 1) * width):
                rx = (p % width + 0.5 - cx) / fx
                ry = (p // width + 0.5 - cy) / fy
                dx = rot[0, 0] * rx + rot[1, 0] * ry + rot[2, 0]  # d = Rᵀ (rx, ry, 1)
                dy = rot[0, 1] * rx + rot[1, 1] * ry + rot[2, 1]
                dz = rot[0, 2] * rx + rot[1, 2] * ry + rot[2, 2]
                m = median_ids[p]
                surface = np.inf
                if m >= 0:
                    surface = _ray_depth(m, dx, dy, dz, origin[0], origin[1], origin[2], means, prec, reach, rot[2, 0], rot[2, 1], rot[2, 2], tz)
                limit = (1.0 - tolerance) * surface
                for s in range(k):
                    g = ids[p, s]
                    if g < 0:  # slots are filled first, -1 padded at the end (every engine)
                        if keep_flags:
                            for r in range(s, k):
                                flags[p, r] = False
                        break
                    in_front = False
                    if near[g] < limit:
                        t = _ray_depth(g, dx, dy, dz, origin[0], origin[1], origin[2], means, prec, reach, rot[2, 0], rot[2, 1], rot[2, 2], tz)
                        in_front = t < limit and t < surface - FRONT_REACH_SHARE * reach[g]
                    if keep_flags:
                        flags[p, s] = in_front
                    w = np.float64(weights[p, s])
                    fixed = _fixed_weight(w, scale)
                    if seen[part, g] != stamp:
                        seen[part, g] = stamp
                        part_count += 1
                        peaks[part, g, 0] = w if w > 0.0 else 0.0
                        sums[part, g, 1] = fixed
                        sums[part, g, 2] = fixed if in_front else 0
                        continue
                    # selects, not branches: the flags and the running maxima follow no pattern a branch predictor learns
                    pk = peaks[part, g, 0]
                    peaks[part, g, 0] = w if w > pk else pk
                    sums[part, g, 1] += fixed
                    sums[part, g, 2] += fixed if in_front else 0
        part_seen[part] = part_count


@numba.njit(parallel=True, cache=True)
def _merge_stats_kernel(seen, stamp, sums, peaks, scale, candidates, chunks):  # pragma: no cover - jitted
    """The parts of `_surface_stats_kernel` (its records sums / peaks) as one view's (ids [T], peak [T], total [T], front [T]):
    every Gaussian some part saw (seen[t, g] == stamp) in id order, its largest peak and the exact
    sums of its parts as float64 (÷ scale). Looks at the ascending ids `candidates` [V] only. Two passes in parallel over `chunks` runs of them: count, then
    write at each run's offset. Also returns how many (part, Gaussian) marks it found (int64),
    which equals Σ part_seen of `_surface_stats_kernel` exactly when no Gaussian seen is left out."""
    parts = seen.shape[0]
    n = candidates.shape[0]
    found = np.zeros(chunks + 1, np.int64)
    for c in numba.prange(chunks):
        count = 0
        for i in range(c * n // chunks, (c + 1) * n // chunks):
            g = candidates[i]
            hit = False
            for part in range(parts):
                hit = hit or seen[part, g] == stamp
            count += 1 if hit else 0
        found[c + 1] = count
    for c in range(chunks):
        found[c + 1] += found[c]
    out_ids = np.empty(found[chunks], np.int32)
    out_peak = np.empty(found[chunks])
    out_total = np.empty(found[chunks])
    out_front = np.empty(found[chunks])
    chunk_marks = np.zeros(chunks, np.int64)
    for c in numba.prange(chunks):
        o = found[c]
        marks = np.int64(0)
        for i in range(c * n // chunks, (c + 1) * n // chunks):
            g = candidates[i]
            hit = False
            pk = 0.0
            t = np.int64(0)
            f = np.int64(0)
            for part in range(parts):
                if seen[part, g] == stamp:
                    hit = True
                    marks += 1
                    v = peaks[part, g, 0]
                    pk = v if v > pk else pk
                    t += sums[part, g, 1]
                    f += sums[part, g, 2]
            if hit:
                out_ids[o] = g
                out_peak[o] = pk
                out_total[o] = t / scale
                out_front[o] = f / scale
                o += 1
        chunk_marks[c] = marks
    return out_ids, out_peak, out_total, out_front, chunk_marks.sum()


def stats_parts(num_gaussians: int) -> int:
    """Parts `surface_stats` cuts a view's pixels into: one per numba thread, as long as the extra
    parts' scratch (STATS_SCRATCH_BYTES per Gaussian each) stays within STATS_EXTRA_SCRATCH. The
    statistics do not depend on it."""
    affordable = 1 + STATS_EXTRA_SCRATCH // max(STATS_SCRATCH_BYTES * num_gaussians, 1)
    return int(max(1, min(numba.get_num_threads(), affordable)))


@dataclass
class StatsScratch:
    """Reusable buffers of `surface_stats`: per part [P, N, 3] records (peak as float64 bits, total,
    front), view stamps [P, N] (`seen`), [N] nearest clamps, flags [H·W, k] bool (or [0, k] without)
    and the last view's stamp."""

    near: np.ndarray
    sums: np.ndarray
    seen: np.ndarray
    flags: np.ndarray
    stamp: int = 0

    @classmethod
    def new(cls, n: int, parts: int, k: int, flag_pixels: int = 0) -> StatsScratch:
        # made once a registration, touched a view's Gaussians at a time: small pages (drsplat.memory.small_page_zeros)
        return cls(np.empty(n), small_page_zeros((parts, n, 3), np.int64), small_page_zeros((parts, n), np.int32), np.empty((flag_pixels, k), np.bool_))

    @property
    def peaks(self) -> np.ndarray:
        """The records as float64 (the same memory): [..., 0] is each part's peak."""
        return self.sums.view(np.float64)

    def fits(self, n: int, parts: int, k: int, flag_pixels: int) -> bool:
        return self.seen.shape == (parts, n) and self.flags.shape == (flag_pixels, k)

    def next_stamp(self) -> int:
        """A stamp no earlier view of these buffers used (they start at 0: the first is 1)."""
        if self.stamp >= np.iinfo(np.int32).max:
            self.seen[:] = 0
            self.stamp = 0
        self.stamp += 1
        return self.stamp


def surface_stats(geometry: RayGeometry, camera, ids: np.ndarray, weights: np.ndarray, median_ids: np.ndarray,
                  tolerance: float = FRONT_TOLERANCE, scratch: StatsScratch | None = None, parts: int | None = None,
                  keep_flags: bool = False, candidates: np.ndarray | None = None) -> tuple[ViewStats, StatsScratch]:
    """`surface_stats_reference` with numba kernels: the in-front test and the sums in one pass,
    in parallel over `parts` sets of pixel rows (default `stats_parts`; the same statistics for
    any), then their merge, Gaussians in id order. scratch: buffers of a previous call to reuse; keep_flags: also keep the
    in-front test of every slot in scratch.flags [H·W, k]. candidates: [V] the ascending ids of
    every Gaussian `ids` can name (a culled view's projected ids, `RasterOutput.projected_ids`), so
    that the per-Gaussian work is O(V), not O(N): a 50M-Gaussian scene's view that sees 200,000
    of them would otherwise scan 50M clamps and 2 x 50M stamps (None: every Gaussian). A Gaussian
    of `ids` that is not among them is an error (the merge counts the parts' marks again).
    Returns (stats, the buffers used)."""
    h, w, k = ids.shape
    ids2 = np.ascontiguousarray(ids.reshape(-1, k), np.int32)
    n = geometry.reach.shape[0]
    parts = stats_parts(n) if parts is None else max(1, int(parts))
    flag_pixels = ids2.shape[0] if keep_flags else 0
    if scratch is None or not scratch.fits(n, parts, k, flag_pixels):
        scratch = StatsScratch.new(n, parts, k, flag_pixels)
    if candidates is None:  # a view rendered whole: every id, ascending by construction (no O(N) check per view)
        candidates = np.arange(n, dtype=np.int32)
    else:
        candidates = np.ascontiguousarray(candidates, np.int32)
        if candidates.size and (candidates[0] < 0 or candidates[-1] >= n or np.any(candidates[1:] <= candidates[:-1])):
            raise ValueError(f"candidates must be ascending ids of the scene's {n:,} Gaussians")
    rot, trans = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64)
    stamp = scratch.next_stamp()
    part_seen = np.zeros(parts, np.int64)
    _surface_stats_kernel(ids2, np.ascontiguousarray(weights.reshape(-1, k), np.float32), np.ascontiguousarray(median_ids.reshape(-1), np.int32), w,
                          geometry.means, geometry.precisions, geometry.reach, np.ascontiguousarray(rot), camera.ray_origin(), float(trans[2]),
                          float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy), float(tolerance), STATS_SCALE,
                          candidates, scratch.near, scratch.sums, scratch.peaks, scratch.seen, stamp, scratch.flags, part_seen)
    chunks = max(1, min(candidates.size, 8 * numba.get_num_threads()))
    *merged, found = _merge_stats_kernel(scratch.seen, stamp, scratch.sums, scratch.peaks, STATS_SCALE, candidates, chunks)
    if found != part_seen.sum():
        raise ValueError("the view's top-k lists name Gaussians that are not among its candidates")
    return ViewStats(*merged), scratch


# ----------------------------------------------------------------------------- the registration hook


@dataclass
class ViewHook:
    """The per-view part of a mode: runs where a view is rasterized (this process or a Ray worker,
    so it is picklable and holds no running sums). Called as hook(geometry, camera, out) with the
    view's RasterOutput, it returns ([H, W, k] weights to accumulate, the view's ViewStats or None).

    rays: the scene's RayGeometry (floater rejection), else None.
    """

    mode: str
    rays: RayGeometry | None = None
    _buffer: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    _scratch: StatsScratch | None = dataclasses.field(default=None, repr=False, compare=False)
    _seen: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    _means2d: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    _conics: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    _screen: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.weighting, self.reject = split_mode(self.mode)

    def __getstate__(self) -> dict:  # buffers are rebuilt where the hook runs
        return {"mode": self.mode, "rays": self.rays}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["mode"], state["rays"])

    @property
    def needs_projection(self) -> bool:
        """Whether the hook projects the scene (its weighting reads screen means and conics)."""
        return self.weighting in PROJECTED_WEIGHTINGS

    @property
    def needs_median(self) -> bool:
        """Whether the views must be rasterized with_median (floater rejection's surface)."""
        return self.reject

    def __call__(self, geometry: PreparedScene | None, camera, out, mask_ids: np.ndarray | None = None,
                 near: float = NEAR) -> tuple[np.ndarray, ViewStats | None]:
        """(`weights`, `stats`) of one view: what a view pass accumulates and folds (near: the plane it was rendered with)."""
        stats = self.stats(camera, out)
        return self.weights(geometry, camera, out, mask_ids, near), stats

    def stats(self, camera, out) -> ViewStats | None:
        """The view's floater statistics (`surface_stats`, from the paper's weights whatever the
        weighting), or None without floater rejection. out: its RasterOutput, with median_ids."""
        if not self.reject:
            return None
        if out.median_ids is None:
            raise ValueError(f"--aggregate {self.mode} needs the rasterizer's median Gaussians (rasterize(..., with_median=True))")
        stats, self._scratch = surface_stats(self.rays, camera, out.ids, out.weights, out.median_ids, scratch=self._scratch,
                                             candidates=getattr(out, "projected_ids", None))
        return stats

    def weights(self, geometry: PreparedScene | None, camera, out, mask_ids: np.ndarray | None = None, near: float = NEAR) -> np.ndarray:
        """[H, W, k] the weighting's per-slot weights (out.weights itself for "paper"; else this
        hook's buffer, overwritten by its next call). geometry: the scene's CPU geometry (means
        [N, 3] float64, covariances), needed when `needs_projection` (the render's own projection,
        `out.projected`, is reused when it covers every Gaussian). out: the view's RasterOutput (ids,
        weights [H, W, k]). mask_ids: [H, W] the view's masks (-1 none), read by the explain weighting."""
        if self.weighting == "paper":
            return out.weights
        if self.weighting == "explain":
            if mask_ids is None:
                raise ValueError(f"--aggregate {self.mode} needs the view's mask ids")
            n = self.rays.reach.shape[0] if self.rays is not None else int(out.ids.max()) + 1
            if self._seen is None or self._seen.shape[0] < n:
                self._seen = np.full(max(n, 1), -1, np.int32)
            self._buffer = explain_weights(out.ids, out.weights, mask_ids, self._seen.shape[0], out=self._buffer, seen=self._seen)
            return self._buffer
        if self.weighting == "sharp":
            means2d, conics, rows = self._projection(geometry, camera, out, near)
            if self._screen is None or self._screen.shape[0] != geometry.num_gaussians:
                self._screen = small_page_zeros((geometry.num_gaussians, 5), np.float64)  # made once, a view's rows written at a time
            self._buffer, self._screen = sharp_weights(out.ids, out.weights, means2d, conics, rows, geometry.num_gaussians, self._screen, self._buffer)
            return self._buffer
        means2d, conics = self._scene_projection(geometry, camera, out, near) if self.needs_projection else (np.zeros((0, 2)), np.zeros((0, 3)))
        self._buffer = view_weights(self.weighting, out.ids, out.weights, means2d, conics, self._buffer)
        return self._buffer

    def _projection(self, geometry: PreparedScene, camera, out, near: float = NEAR) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(means2d [V, 2], conics [V, 3] float64, rows [V] their scene ids or None for V = N in id
        order), right for every Gaussian out.ids names: the render's own projection (of a culled
        subset: out.projected_ids), or projected here when the render kept none."""
        projected = getattr(out, "projected", None)
        rows = getattr(out, "projected_ids", None)
        if projected is not None and rows is None and projected.means2d.shape[0] == geometry.num_gaussians:
            return projected.means2d, projected.conics, None
        if projected is None or rows is None or rows.shape[0] != projected.means2d.shape[0]:
            projected = project_gaussians(geometry, camera, near)
            return projected.means2d, projected.conics, None
        return projected.means2d, projected.conics, rows

    def _scene_projection(self, geometry: PreparedScene, camera, out, near: float = NEAR) -> tuple[np.ndarray, np.ndarray]:
        """(means2d [N, 2], conics [N, 3]) float64 by scene id (`_projection`'s rows scattered into this
        hook's buffers when it covers a culled subset; a Gaussian's projection does not depend on the
        others, so these are the same bits)."""
        means2d, conics, rows = self._projection(geometry, camera, out, near)
        if rows is None:
            return means2d, conics
        n = geometry.num_gaussians
        if self._means2d is None or self._means2d.shape[0] != n:
            self._means2d, self._conics = small_page_zeros((n, 2), np.float64), small_page_zeros((n, 3), np.float64)
        self._means2d[rows] = means2d
        self._conics[rows] = conics
        return self._means2d, self._conics


def mode_hook(mode: str, rays: RayGeometry | None) -> ViewHook | None:
    """The per-view hook of `mode`, or None when its views are summed as rendered (the paper's
    weights, no floater rejection). rays: the scene's RayGeometry (`RayGeometry.from_scene`), read
    by floater rejection only."""
    stages = mode_stages(mode)
    if stages.weighting == "paper" and not stages.reject:
        return None
    return ViewHook(mode, rays if stages.reject else None)


def reject_rows(F: np.ndarray, W: np.ndarray, rejected: np.ndarray) -> int:
    """In place: rows with rejected [B] bool and W > 0 get W = 0 and F = 0 (unassigned); F [B, D],
    W [B]. Returns how many rows were dropped (the finish step of floater rejection on a block,
    run by the driver or by a reducer with its block's slice of the rejected mask)."""
    drop = rejected & (W > 0)
    F[drop] = 0.0
    W[drop] = 0.0
    return int(np.count_nonzero(drop))


class Aggregator:
    """A mode's state in one registration: its per-view `hook` (None for "paper": the view's w is
    used as it is), the folded statistics (`add` per view, in view order) and `finish` on the sums."""

    def __init__(self, mode: str, scene, stats_on_reducers: bool = False, rays: RayGeometry | None = None):
        """scene: the GaussianScene being registered (rejection reads its shapes: `RayGeometry`;
        rays: that RayGeometry when made already, by the fit stage).
        stats_on_reducers: the views' statistics are logged by the workers and folded per block by
        the reducers (drsplat.registration.reduce): nothing is folded here, `rejected()` is None
        and the reducers' counts come in through `num_rejected`."""
        self.mode = mode
        stages = mode_stages(mode)
        self.reject, self.vote, self.solve, self.check, self.specific = stages.reject, stages.vote, stages.solve, stages.check, stages.specific
        self.support = SurfaceSupport.zeros(scene.num_gaussians) if self.reject and not stats_on_reducers else None
        if self.reject and rays is None:
            rays = RayGeometry.from_scene(scene)
        self.hook = mode_hook(mode, rays)
        self.num_rejected = 0
        self.views_folded = 0  # views whose statistics are in `support` (a checkpoint snapshots only a consistent state)
        self._rejected: np.ndarray | None = None

    def end_views(self) -> None:
        """Let go of what only the view pass uses: the hook and its RayGeometry (RAY_GEOMETRY_BYTES a
        Gaussian), which the memory plan counts for the view pass and not for the blocks after it."""
        self.hook = None

    def add(self, stats: ViewStats | None) -> None:
        """Fold one view's statistics (from the hook's second output) into the running support."""
        if self.support is not None:
            if stats is None:
                raise ValueError(f"--aggregate {self.mode}: a view came without its rejection statistics")
            on_device = getattr(stats, "support_for", None)  # a view computed on the torch engine's device (device_sums.DeviceViewStats)
            if on_device is not None:
                self.support = on_device(self.support)
            self.support.add(stats)
            self.views_folded += 1

    def finish(self, F: np.ndarray, W: np.ndarray, start: int = 0) -> int:
        """Post-step on the sums of Gaussians start .. start + B (all of them, or a block when
        streaming), F [B, D], W [B], once every view is in: rejected Gaussians get W = 0 and F = 0
        (unassigned). Returns how many of them were rejected that had weight (also added to
        `num_rejected`)."""
        if self.support is None:
            return 0
        count = reject_rows(F, W, self.rejected()[start:start + W.shape[0]])
        self.num_rejected += count
        return count

    def rejected(self) -> np.ndarray | None:
        """[N] bool, the Gaussians the mode leaves unassigned (computed once every view is in), or
        None for modes that reject nothing and when the reducers fold the statistics."""
        if self.support is None:
            return None
        if self._rejected is None:
            self._rejected = self.support.rejected()
        return self._rejected

    def log_rejected(self, asked: str | None = None) -> None:
        """One line: how many Gaussians the rejection dropped, and the mode without it (of `asked`, the
        mode as the user named it, when a fit mode resolved to this one)."""
        if self.reject:
            log.info("%s: %s rejected as unsupported (floaters / haze in front of the surface; a semi-transparent object such "
                     "as glass would go with them if it stayed under %g of every pixel's weight: %s)", self.mode,
                     counted(self.num_rejected, "Gaussian", "Gaussians"), PEAK_MIN, keep_all_remedy(asked, self.mode))

    @staticmethod
    def memory_bytes(mode: str, num_gaussians: int, pixels: int, topk: int, support_scratch: int, trim_buffer: int) -> tuple[int, int, int]:
        """(bytes held while views are rasterized, bytes held until the sums are finished, bytes per
        Gaussian of a block of sums) by `mode` for a scene of `num_gaussians` and views of at most
        `pixels` pixels (registration's memory plan). support_scratch, trim_buffer: the check's support
        scratch and the exact trim's buffer (`check.support_scratch_bytes`, `vote.trim_buffer_bytes`:
        from the views' mask counts, or their caps where those are not known)."""
        stages = mode_stages(mode)
        weighting, reject = stages.weighting, stages.reject
        views = pixels * topk * 4 if weighting != "paper" else 0  # the reweighted [H, W, k] buffer
        if weighting == "explain":  # slot -> pair indices and the per-pair arrays (at most one pair per slot)
            views += pixels * topk * (4 + 12 + 32) + 4 * num_gaussians
        kept = per_block = 0
        if reject:  # statistics, per-view scratch and RayGeometry per Gaussian; one flag per slot
            kept = 32 * num_gaussians
            views += (8 + STATS_SCRATCH_BYTES * stats_parts(num_gaussians) + RAY_GEOMETRY_BYTES) * num_gaussians + pixels * 4  # StatsScratch, RayGeometry, median ids
        if stages.vote:  # vote slots, W and a scratch per Gaussian of a block (the weighted mean's F is counted by the plan anyway)
            per_block += VOTE_SLOT_BYTES + 8 + (SPECIFICITY_SLOT_BYTES if stages.specific else 0)  # step 4's specificities
        if stages.check:  # the check's slots per Gaussian of a block and its dense support scratch, bounded whatever a view's masks
            # (drsplat.registration.check; its mask clusters, unit embeddings and support tables, held up to SUPPORT_TABLE_BYTES and
            # spilled to disk beyond, are counted by the plan, `plan.estimate_memory`; registration always gives it a pair log)
            per_block += 12 * CHECK_SLOTS + 8  # and its count of voting views
            per_block += GAUSSIAN_TERM_BYTES  # a view's Gaussians' support terms (check.gaussian_terms), at most the block's
            kept += support_scratch
            if stages.vote:  # after the check the vote trims exactly (drsplat.registration.vote.exact_trimmed_features)
                per_block += EXACT_TRIM_SLOT_BYTES
                kept += trim_buffer
        if stages.solve:  # slots, CG vectors and a re-rendered view (drsplat.registration.solve)
            kept += (76 * SOLVE_SLOTS + 8) * num_gaussians + pixels * (topk * 8 + 4)
        return views + kept, kept, per_block

    def state(self) -> dict[str, np.ndarray]:
        """Arrays to checkpoint (empty for modes without statistics)."""
        return {} if self.support is None else self.support.arrays()

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        if self.support is not None and arrays:
            self.support = SurfaceSupport.from_arrays(arrays)
