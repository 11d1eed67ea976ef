"""A `-vote` mode's per-view fold as one Triton kernel: `vote._vote_view_kernel` on CUDA.

The torch form (`device_sums.vote_view_torch`) folds a view in rounds, round r taking every
Gaussian's r-th acting pair at once: ~24 ops a round and as many rounds as the most masks one
Gaussian meets in the view, plus a read of that number (which the device sink defers a view). Here
one program per Gaussian walks its own pairs in order, as the numba kernel does per row: the view's
total T_iv first, then each pair's space-saving slot, the Gaussian's S slots held in registers.
The pairs are sorted by Gaussian (stably, so a Gaussian's pairs keep the view's order) and each
program finds its run from the cumulative run starts: a sort, a search and one launch, nothing
read. The same float64 operations in the same order as the numba kernel, FMA contraction off, so
the same bits (tests/test_vote_triton.py runs it in Triton's interpreter against
`vote.vote_view_reference` and the numba kernel).
"""

from __future__ import annotations

import torch

from drsplat.raster_triton import kernel_ptx, require_cuda, row_runs, strict_launch, triton_kernel

try:  # triton comes with torch's CUDA builds
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - depends on the torch build
    triton = None
    tl = None


def _vote_fold_source(clusters_ptr, weights_ptr, starts_ptr, params_ptr, slot_c_ptr, slot_v_ptr, slot_s_ptr, S, SP: tl.constexpr):
    """Program g: Gaussian g's pairs clusters / weights[starts[g]:starts[g + 1]] folded into its
    slots (slot_c [N, S] int32, slot_v / slot_s [N, S] float64), as `vote._vote_view_kernel`:

        T = Σ w (float64, in pair order); for each pair with a cluster c and w > 0:
        v = min(1, w / (T·ρ)) · min(1, T / T₀) (ρ > 0; else v = w)
        slot = the first slot holding c or empty, else the first of fewest votes; V += v, S += w
    params: [ρ, T₀] float64 (a Python float argument would be typed fp32)."""
    g = tl.program_id(0).to(tl.int64)
    lo = tl.load(starts_ptr + g)
    hi = tl.load(starts_ptr + g + 1)
    if lo < hi:
        presence = tl.load(params_ptr)
        full_view = tl.load(params_ptr + 1)
        total = tl.load(weights_ptr + lo).to(tl.float64)
        for i in range(lo + 1, hi):
            total += tl.load(weights_ptr + i).to(tl.float64)
        s = tl.arange(0, SP)
        in_s = s < S
        at = g * S + s
        sc = tl.load(slot_c_ptr + at, mask=in_s, other=0)
        sv = tl.load(slot_v_ptr + at, mask=in_s, other=0.0)
        ss = tl.load(slot_s_ptr + at, mask=in_s, other=0.0)
        for i in range(lo, hi):
            c = tl.load(clusters_ptr + i)
            w = tl.load(weights_ptr + i).to(tl.float64)
            share = tl.minimum(w / (total * presence), 1.0) * tl.minimum(total / full_view, 1.0)
            v = tl.where(presence > 0.0, share, w)
            first = tl.min(tl.where(in_s & ((sc == c) | (sc < 0)), s, SP), axis=0)
            least = tl.min(tl.where(in_s, sv, float("inf")), axis=0)
            fewest = tl.min(tl.where(in_s & (sv == least), s, SP), axis=0)  # the first of the fewest votes
            hit = tl.where(first < SP, first, fewest)
            acting = (c >= 0) & (w > 0.0)
            take = (s == hit) & acting
            sc = tl.where(take, c, sc)
            sv = tl.where(take, sv + v, sv)
            ss = tl.where(take, ss + w, ss)
        tl.store(slot_c_ptr + at, sc, mask=in_s)
        tl.store(slot_v_ptr + at, sv, mask=in_s)
        tl.store(slot_s_ptr + at, ss, mask=in_s)


def vote_fold_triton(rows: torch.Tensor, clusters: torch.Tensor, weights: torch.Tensor, presence: float, full_view: float,
                     slot_c: torch.Tensor, slot_v: torch.Tensor, slot_s: torch.Tensor) -> None:
    """Fold one view's pairs into the vote slots in place, in one launch (`_vote_fold_source`).

    rows: [P] int64 Gaussians, clusters: [P] int (-1 none), weights: [P] float32, in the view's pair
    order; slot_c [N, S] int32, slot_v / slot_s [N, S] float64, contiguous, on a CUDA device (or the
    CPU under the interpreter)."""
    dev = rows.device
    require_cuda(dev, "the fused vote kernel")
    n, slots = slot_c.shape
    if rows.shape[0] == 0 or n == 0:
        return
    order, starts = row_runs(rows, n)
    params = torch.tensor([float(presence), float(full_view)], dtype=torch.float64)
    params = params.pin_memory().to(dev, non_blocking=True) if dev.type == "cuda" else params
    launch = strict_launch()
    triton_kernel(_vote_fold_source)[(n,)](
        clusters[order].to(torch.int32).contiguous(), weights[order].to(torch.float32).contiguous(), starts, params, slot_c, slot_v, slot_s,
        slots, SP=1 << max(0, slots - 1).bit_length(), **launch,
    )  # fmt: skip


def compile_vote_ptx(capability: int = 90, slots: int = 8, ones: bool = False) -> str:
    """The kernel compiled to PTX for sm_`capability` without a GPU (`raster_triton.kernel_ptx`), FMA contraction off as launched."""
    pointers = {"clusters_ptr": "*i32", "weights_ptr": "*fp32", "starts_ptr": "*i64", "params_ptr": "*fp64", "slot_c_ptr": "*i32",
                "slot_v_ptr": "*fp64", "slot_s_ptr": "*fp64", "S": "i32"}
    return kernel_ptx(_vote_fold_source, pointers, {"SP": 1 << max(0, slots - 1).bit_length()}, capability, ones, enable_fp_fusion=False)
