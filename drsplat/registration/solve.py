"""Render-consistent solve: the `solve` stage of an aggregation mode (`--aggregate solve-vote-reject`, ...).

The paper's mean f̄_i = Σ_j w_ij f_j / W_i weighs every pixel of a Gaussian's footprint by w = T·α,
so a silhouette Gaussian whose footprint spills onto the background takes the background's label
even though the background's own Gaussians already explain those pixels. The solve asks instead
for the per-Gaussian features that *re-render* the views' masks best (Splat Feature Solver's
sparse linear inverse problem), Tikhonov-regularised toward the paper's mean:

    min_x  Σ_p ‖Σ_g w_gp x_g − e_{c(p)}‖²  +  λ Σ_g T_g ‖x_g − x̄_g‖²

in a low-dimensional basis: the views' masks grouped by embedding (drsplat.registration.vote.
MaskClusters, cosine ≥ CLUSTER_COSINE), pixel p's target the one-hot e_{c(p)} of its mask's
cluster (pixels without a mask are left out, as the paper leaves them), and x_g restricted to
SOLVE_SLOTS candidate clusters per Gaussian (`slot_sums`: the clusters holding most of its
paper weight S_gc = Σ_{p: c(p)=c} w_gp, space-saving rule in pixel order; then S at the chosen
slots summed exactly in a second pass, `target_sums`). T_g = Σ_s S_gs and
x̄_gs = S_gs / T_g is the paper's mean in that basis. The normal equations

    (WᵀW + λ·diag(T)) x = (1 + λ)·S        ((Wᵀe)_gs = S_gs: no extra pass for the right side)

are solved by conjugate gradients from x̄ (SOLVE_ITERATIONS iterations), Jacobi-preconditioned by
diag(WᵀW) + λ·T (Σ_p w_gp² over the masked pixels, summed in the slot pass). Applying WᵀW re-renders
every view (`apply_view`: y_p = Σ_g w_gp x_g over the pixel's distinct candidate clusters, then
(WᵀW x)_gs += w_gp·y_p[c_gs]); nothing per (pixel, Gaussian) is kept across views. Squared
weights favour the pixels a Gaussian dominates (its core) over the faint tails where another
Gaussian already explains the pixel.

The feature then replaces the slot part of the sums: F_i ← F_i + T_i Σ_s (max(x_is, 0) − x̄_is) μ_{c_is}
(μ_c the cluster's unit mean); a Gaussian whose solve stays at x̄, or whose coefficients are all
≤ 0, keeps F_i bit for bit; W_i is
unchanged, so coverage and floater rejection do not move. Negative coefficients are clipped
(a projection onto non-negative mixtures; the CG itself is unconstrained).

Cost: state 12·SOLVE_SLOTS + 8 bytes per Gaussian for the slots (cluster int32, S float64, Σw²)
plus float64 [N, SOLVE_SLOTS] CG vectors (x, x̄, b, r, z, p, Ap, preconditioner: 8 of them):
76·SOLVE_SLOTS + 8 bytes per Gaussian (616 bytes at 8 slots), K·D·12 bytes for K clusters. Per iteration: one top-k rendering of
every view plus O(P·k·S·U) for P pixels, k slots, S candidates and U distinct candidate clusters
in the pixel; SOLVE_ITERATIONS + 3 render passes in all (slots, exact S, initial residual, iterations).
It needs all Gaussians in one block in memory: registration refuses `--aggregate solve*` with a
`--memory-budget` that splits the scene into blocks.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numba
import numpy as np

from drsplat.defaults import SOLVE_SLOTS
from drsplat.raster import NEAR
from drsplat.registration.compute import ViewComputer, ViewJob
from drsplat.registration.views import load_view_features
from drsplat.registration.vote import MaskClusters
from drsplat.utils import CancelToken

log = logging.getLogger(__name__)

SOLVE_LAMBDA = 0.1  # λ: pull toward the paper's mean, per unit of the Gaussian's weight T_g
SOLVE_ITERATIONS = 10  # conjugate-gradient iterations (docs/evaluation.md, "Render-consistent solve")
SOLVE_SCRATCH_BYTES = 64 << 20  # the gathered cluster means of one chunk of changed rows (`solved_features`)


@dataclass
class SolveView:
    """One view as the solve reads it: ids, weights [P, k] top-k (ids -1 none), labels [P] int32 the
    pixel's mask cluster (-1 no mask)."""

    ids: np.ndarray
    weights: np.ndarray
    labels: np.ndarray


@numba.njit(parallel=True, cache=True)
def _slots_by_id_kernel(ids, weights):  # pragma: no cover - jitted
    """Each row's slots in increasing id, equal ids in the order they came (an insertion sort), in place."""
    for p in numba.prange(ids.shape[0]):
        for i in range(1, ids.shape[1]):
            g, w = ids[p, i], weights[p, i]
            j = i
            while j > 0 and ids[p, j - 1] > g:
                ids[p, j] = ids[p, j - 1]
                weights[p, j] = weights[p, j - 1]
                j -= 1
            ids[p, j] = g
            weights[p, j] = w


def slots_by_id(ids: np.ndarray, weights: np.ndarray) -> None:
    """Sort each pixel's slots by Gaussian id, stably, in place: ids [P, k] int32 (-1 first), weights [P, k] with
    them (`_slots_by_id_kernel`; `slots_by_id_reference` is numpy's stable argsort and gathers)."""
    if ids.size:
        _slots_by_id_kernel(ids, weights)


def slots_by_id_reference(ids: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`slots_by_id` by a stable argsort: (ids, weights) sorted, new arrays."""
    order = np.argsort(ids, axis=1, kind="stable")
    return np.take_along_axis(ids, order, 1), np.take_along_axis(weights, order, 1)


def counted(view: SolveView) -> np.ndarray:
    """[P, k] bool: the contributions the solve reads, a Gaussian (id ≥ 0) with a finite positive weight. The
    renderer gives nothing else; a zero, negative, NaN or infinite weight is left out everywhere alike, kernels and
    references (a NaN would otherwise spoil a reference's whole pixel and the kernel's candidates only)."""
    w = view.weights
    return (view.ids >= 0) & (w > 0) & (w < np.inf)


# ----------------------------------------------------------------------------- candidate slots


def slot_sums_reference(views: Iterable[SolveView], n: int, slots: int = SOLVE_SLOTS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(slot_c [n, slots] int32 cluster (-1 empty), slot_s [n, slots] float64 S, square [n] float64
    Σ_p w_gp² over the masked pixels: the diagonal of WᵀW, CG's Jacobi preconditioner) by the
    space-saving rule, pixel by pixel and slot by slot (numpy/python reference of `_slot_kernel`):
    a cluster already in a slot adds w; else it takes the first empty slot; else it replaces the
    slot with the smallest S (first of ties) and inherits S."""
    slot_c = np.full((n, slots), -1, np.int32)
    slot_s = np.zeros((n, slots), np.float64)
    square = np.zeros(n)
    for v in views:
        for p in range(v.ids.shape[0]):
            c = int(v.labels[p])
            if c < 0:
                continue
            for j in range(v.ids.shape[1]):
                g, w = int(v.ids[p, j]), float(v.weights[p, j])
                if g < 0 or not 0 < w < math.inf:
                    continue
                square[g] += w * w
                hit = np.flatnonzero(slot_c[g] == c)
                if hit.size:
                    slot_s[g, hit[0]] += w
                    continue
                empty = np.flatnonzero(slot_c[g] < 0)
                s = int(empty[0]) if empty.size else int(np.argmin(slot_s[g]))
                slot_c[g, s] = c
                slot_s[g, s] += w
    return slot_c, slot_s, square


@numba.njit(cache=True)
def _slot_kernel(ids, weights, labels, slot_c, slot_s, square):  # pragma: no cover - jitted
    """Fold one view into the slots (`slot_sums_reference`'s rule, same order) and Σ w² into square."""
    npx, k = ids.shape
    slots = slot_c.shape[1]
    for p in range(npx):
        c = labels[p]
        if c < 0:
            continue
        for j in range(k):
            g = ids[p, j]
            w = np.float64(weights[p, j])
            if g < 0 or not 0.0 < w < np.inf:
                continue
            square[g] += w * w
            found = -1
            empty = -1
            low = 0
            for s in range(slots):
                if slot_c[g, s] == c:
                    found = s
                    break
                if slot_c[g, s] < 0 and empty < 0:
                    empty = s
                if slot_s[g, s] < slot_s[g, low]:
                    low = s
            if found < 0:
                found = empty if empty >= 0 else low
                slot_c[g, found] = c
            slot_s[g, found] += w


FIRST_RUN_PROBE = _slot_kernel  # the stage's kernel whose place in numba's cache shows it ran here before (driver.say_if_kernels_compile)


def slot_sums(views: Iterable[SolveView], n: int, slots: int = SOLVE_SLOTS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`slot_sums_reference` with the numba kernel."""
    slot_c = np.full((n, slots), -1, np.int32)
    slot_s = np.zeros((n, slots), np.float64)
    square = np.zeros(n)
    for v in views:
        _slot_kernel(v.ids, v.weights, v.labels, slot_c, slot_s, square)
    return slot_c, slot_s, square


# ----------------------------------------------------------------------------- the operator WᵀW


def apply_view_reference(view: SolveView, slot_c: np.ndarray, x: np.ndarray, num_clusters: int) -> np.ndarray:
    """(WᵀW x) restricted to one view's pixels with a mask: [n, slots] float64 (dense numpy reference:
    X [n, K] from the slots, Y = W X per pixel, back-projected and read at the slots)."""
    n, slots = slot_c.shape
    dense = np.zeros((n, num_clusters))
    rows = np.repeat(np.arange(n), slots)
    ok = slot_c.reshape(-1) >= 0
    dense[rows[ok], slot_c.reshape(-1)[ok]] = x.reshape(-1)[ok]
    keep = (view.labels >= 0)[:, None] & counted(view)
    g = np.where(keep, view.ids, 0)
    w = np.where(keep, view.weights.astype(np.float64), 0.0)
    y = np.einsum("pk,pkc->pc", w, dense[g])  # [P, K] rendered coefficients
    back = np.zeros((n, num_clusters))
    np.add.at(back, g.reshape(-1), (w[..., None] * y[:, None, :]).reshape(-1, num_clusters))
    out = np.zeros((n, slots))
    out[ok.reshape(n, slots)] = back[rows[ok], slot_c.reshape(-1)[ok]]
    return out


@numba.njit(cache=True)
def _apply_kernel(ids, weights, labels, slot_c, x, out, uc, uy):  # pragma: no cover - jitted
    """out += WᵀW x over one view (`apply_view_reference`); uc/uy: [k·slots] scratch of the pixel's
    distinct candidate clusters and their rendered coefficient y_p[c]."""
    npx, k = ids.shape
    slots = slot_c.shape[1]
    for p in range(npx):
        if labels[p] < 0:
            continue
        u = 0
        for j in range(k):
            g = ids[p, j]
            w = np.float64(weights[p, j])
            if g < 0 or not 0.0 < w < np.inf:
                continue
            for s in range(slots):
                c = slot_c[g, s]
                if c < 0:
                    continue
                at = -1
                for q in range(u):
                    if uc[q] == c:
                        at = q
                        break
                if at < 0:
                    at = u
                    uc[u] = c
                    uy[u] = 0.0
                    u += 1
                uy[at] += w * x[g, s]
        for j in range(k):
            g = ids[p, j]
            w = np.float64(weights[p, j])
            if g < 0 or not 0.0 < w < np.inf:
                continue
            for s in range(slots):
                c = slot_c[g, s]
                if c < 0:
                    continue
                for q in range(u):
                    if uc[q] == c:
                        out[g, s] += w * uy[q]
                        break


def apply_view(view: SolveView, slot_c: np.ndarray, x: np.ndarray, out: np.ndarray) -> None:
    """out [n, slots] += (WᵀW x) over one view's pixels, with the numba kernel."""
    scratch = view.ids.shape[1] * slot_c.shape[1]
    _apply_kernel(view.ids, view.weights, view.labels, slot_c, x, out, np.empty(scratch, np.int32), np.empty(scratch))


def target_view_reference(view: SolveView, slot_c: np.ndarray) -> np.ndarray:
    """(Wᵀe) at the slots over one view: [n, slots] float64 Σ_p w_gp·[c(p) = c_gs] (numpy reference)."""
    out = np.zeros(slot_c.shape)
    keep = (view.labels >= 0)[:, None] & counted(view)
    p, j = np.nonzero(keep)
    g = view.ids[p, j]
    hit = slot_c[g] == view.labels[p][:, None]  # [pairs, slots]
    rows, s = np.nonzero(hit)
    np.add.at(out, (g[rows], s), view.weights[p[rows], j[rows]].astype(np.float64))
    return out


@numba.njit(cache=True)
def _target_kernel(ids, weights, labels, slot_c, out):  # pragma: no cover - jitted
    """out += Wᵀe at the slots over one view (`target_view_reference`)."""
    npx, k = ids.shape
    slots = slot_c.shape[1]
    for p in range(npx):
        c = labels[p]
        if c < 0:
            continue
        for j in range(k):
            g = ids[p, j]
            w = np.float64(weights[p, j])
            if g < 0 or not 0.0 < w < np.inf:
                continue
            for s in range(slots):
                if slot_c[g, s] == c:
                    out[g, s] += w
                    break


def target_sums(views: Iterable[SolveView], slot_c: np.ndarray) -> np.ndarray:
    """[n, slots] S_gs = (Wᵀe)_gs = Σ_p w_gp·[c(p) = c_gs], exactly (the slots' space-saving counts
    can hold a replaced cluster's weight), with the numba kernel."""
    out = np.zeros(slot_c.shape)
    for v in views:
        _target_kernel(v.ids, v.weights, v.labels, slot_c, out)
    return out


def residual_reference(views: Iterable[SolveView], slot_c: np.ndarray, x: np.ndarray, num_clusters: int) -> float:
    """Σ_p ‖Σ_g w_gp x_g − e_{c(p)}‖² over the pixels with a mask (the re-render residual; numpy)."""
    n, slots = slot_c.shape
    dense = np.zeros((n, num_clusters))
    rows = np.repeat(np.arange(n), slots)
    ok = slot_c.reshape(-1) >= 0
    dense[rows[ok], slot_c.reshape(-1)[ok]] = x.reshape(-1)[ok]
    total = 0.0
    for v in views:
        keep = v.labels >= 0
        g = np.where(counted(v)[keep], v.ids[keep], 0)
        w = np.where(counted(v)[keep], v.weights[keep].astype(np.float64), 0.0)
        y = np.einsum("pk,pkc->pc", w, dense[g])
        y[np.arange(y.shape[0]), v.labels[keep]] -= 1.0
        total += float(np.sum(y * y))
    return total


# ----------------------------------------------------------------------------- conjugate gradients


@dataclass
class SolveResult:
    """slot_c [n, S] clusters, x̄ / x [n, S] float64 the paper's and the solved coefficients,
    T [n] the slots' total weight, iterations run, the residual norms ‖b − Ax‖ per iteration and
    the re-render residual before and after."""

    slot_c: np.ndarray
    prior: np.ndarray
    x: np.ndarray
    total: np.ndarray
    iterations: int
    residuals: list[float]
    rerender: tuple[float, float]  # Σ_p ‖Σ_g w_gp x_g − e_c(p)‖² at x̄ and at x (masked pixels of every view)


def solve_coefficients(render: Callable[[], Iterable[SolveView]], n: int, lam: float = SOLVE_LAMBDA,
                       iterations: int = SOLVE_ITERATIONS, slots: int = SOLVE_SLOTS) -> SolveResult:
    """Conjugate gradients on (WᵀW + λ·diag(T)) x = (1 + λ)·S from x̄ (module docstring).

    render: called once per pass, yields every view's SolveView (re-rendered: nothing per pixel
    is kept across views); n: Gaussians."""
    masked = [0]

    def counted() -> Iterable[SolveView]:
        for view in render():
            masked[0] += int(np.count_nonzero(view.labels >= 0))
            yield view

    slot_c, _, square = slot_sums(counted(), n, slots)
    slot_s = target_sums(render(), slot_c)
    total = slot_s.sum(axis=1)
    live = total > 0
    prior = np.divide(slot_s, total[:, None], out=np.zeros_like(slot_s), where=live[:, None])
    reg = lam * total[:, None] * (slot_c >= 0)

    def apply(v: np.ndarray) -> np.ndarray:
        out = reg * v
        for view in render():
            apply_view(view, slot_c, v, out)
        return out

    x = prior.copy()
    b = (1.0 + lam) * slot_s
    ax = apply(x)
    r = b - ax
    diag = np.where(slot_c >= 0, square[:, None] + reg, 1.0)  # Jacobi preconditioner: diag(WᵀW) = Σ_p w_gp² (masked pixels)
    z = r / diag
    # Σ_p ‖W x − e‖² = xᵀWᵀWx − 2 xᵀS + (masked pixels); WᵀWx = Ax − reg·x (at the end Ax = b − r)
    before = float(np.sum(x * (ax - reg * x)) - 2.0 * np.sum(x * slot_s)) + masked[0]
    p = z.copy()
    rz = float(np.sum(r * z))
    residuals = [float(np.linalg.norm(r))]
    done = 0
    for _ in range(iterations):
        if not rz > 0:
            break
        ap = apply(p)
        alpha = rz / float(np.sum(p * ap))
        x += alpha * p
        r -= alpha * ap
        z = r / diag
        rz_new = float(np.sum(r * z))
        p = z + (rz_new / rz) * p
        rz = rz_new
        residuals.append(float(np.linalg.norm(r)))
        done += 1
    after = float(np.sum(x * (b - r - reg * x)) - 2.0 * np.sum(x * slot_s)) + masked[0]
    log.info("solve: %d CG iterations, normal-equation residual %.3g -> %.3g, re-render residual %.6g -> %.6g over %d masked pixels",
             done, residuals[0], residuals[-1], before, after, masked[0])
    return SolveResult(slot_c, prior, x, total, done, residuals, (before, after))


def solved_features(F: np.ndarray, result: SolveResult, means: np.ndarray, scratch_bytes: int = SOLVE_SCRATCH_BYTES) -> int:
    """F [n, D] ← F + T Σ_s (max(x_s, 0) − x̄_s) μ_{c_s} in place (module docstring); means [K, D]
    the clusters' unit means. Returns how many Gaussians changed. The changed rows are updated in
    chunks whose gathered means ([chunk, S, D], float32 then float64: 12 B a value) stay within
    scratch_bytes; each row's sum is the same whatever the chunk (tested)."""
    kept = np.where(result.slot_c >= 0, np.maximum(result.x, 0.0), 0.0)
    delta = (kept - np.where(result.slot_c >= 0, result.prior, 0.0)) * result.total[:, None]
    delta[kept.sum(axis=1) <= 0] = 0.0  # nothing positive left: keep the paper's sums (the rest would be rounding noise's direction)
    changed = np.flatnonzero(np.any(delta != 0.0, axis=1))
    chunk = max(1, int(scratch_bytes) // (12 * max(result.slot_c.shape[1], 1) * max(means.shape[1], 1)))
    for start in range(0, changed.size, chunk):
        rows = changed[start:start + chunk]
        c = np.maximum(result.slot_c[rows], 0)
        F[rows] += np.einsum("rs,rsd->rd", delta[rows], means[c].astype(np.float64)).astype(F.dtype)
    return int(changed.size)


# ----------------------------------------------------------------------------- registration's use


def solve_registration(geometry, cameras, features_dir, level: int, topk: int, engine: str, device: str,
                       F: np.ndarray, lam: float = SOLVE_LAMBDA, iterations: int = SOLVE_ITERATIONS,
                       cancel: CancelToken | None = None, near: float = NEAR) -> SolveResult:
    """The solve stage on a whole scene's sums F [N, D] (in place): clusters the views' masks,
    re-renders the views with the registration's engine on every pass (drsplat.registration.compute.
    ViewComputer) and moves F toward the solved mixtures. geometry: the scene's PreparedScene.
    cancel: checked before each view of each pass (the passes are most of a `solve` run's time). near:
    the registration's near plane (`ViewJob.near`)."""
    computer = ViewComputer(geometry, ViewJob(features_dir, level, topk, engine, device, near=near))
    clusters = MaskClusters(F.shape[1])
    for cam in cameras:
        mask_ids, feats, _ = load_view_features(features_dir, cam, level)
        flat = mask_ids.reshape(-1)
        present = np.zeros(feats.shape[0], bool)
        present[np.unique(flat[flat >= 0])] = True
        clusters.add(feats, present)  # a mask that covers no pixel founds no cluster

    def render() -> Iterable[SolveView]:
        # each pass reads the view's masks again rather than keeping [views, H·W] labels in memory
        # (one view's labels is what the memory plan counts; the read costs far less than the render)
        for cam, cluster_of_mask in zip(cameras, clusters.per_view):
            if cancel is not None:
                cancel.raise_if_cancelled()
            flat = load_view_features(features_dir, cam, level)[0].reshape(-1)
            labels = np.where(flat >= 0, cluster_of_mask[np.maximum(flat, 0)] if cluster_of_mask.size else -1, -1).astype(np.int32)
            out = computer.rasterize(cam)
            k = out.ids.shape[-1]
            # engines may order a pixel's slots differently: sums in id order. Sorted where they lie (the computer's
            # buffers, overwritten by the next view, when this one is done): an argsort's int64 order and sorted copies
            # took 24 more bytes a slot, 1 GB past the memory plan on 1600x1200 views (round 63b)
            ids = np.ascontiguousarray(out.ids.reshape(-1, k), np.int32)
            weights = np.ascontiguousarray(out.weights.reshape(-1, k), np.float32)
            slots_by_id(ids, weights)
            yield SolveView(ids, weights, labels)

    result = solve_coefficients(render, geometry.num_gaussians, lam, iterations)
    changed = solved_features(F, result, clusters.means())
    log.info("solve: %d Gaussians moved toward the render-consistent mixture over %d mask clusters", changed, clusters.count)
    return result
