"""A view's per-Gaussian sums on CUDA in one Triton launch: `sums._flush_pairs_kernel`'s order, run-to-run exact.

`device_sums.add_pairs_torch` adds a view's pairs with `index_add`, whose CUDA atomics add a
Gaussian's pairs in no fixed order (the sums agree with numba's to float32 rounding and may differ
between runs). Here the pairs are sorted by Gaussian (stably, so each Gaussian keeps the view's
pair order) and one program per Gaussian reads its row of F once, adds its pairs' w·f one after
another and writes the row once, as the numba kernel of the host accumulator does:

    F_g += w·f_m (the product rounded to float32, then the add: FMA contraction off),  W_g += w

so the bits are numba's on any device (tests/test_sums_triton.py runs it in Triton's interpreter
against `sums.add_pairs_in_place`). Padding pairs (Gaussian = N, the device coalescer's) sort
after every run and are never read.
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


def _add_pairs_source(masks_ptr, weights_ptr, starts_ptr, feats_ptr, F_ptr, W_ptr, D, BLOCK_D: tl.constexpr):
    """Program g: F[g, :D] += Σ w·feats[m] and W[g] += Σ w over Gaussian g's pairs
    masks / weights[starts[g]:starts[g + 1]], in order; F's row held in registers."""
    g = tl.program_id(0).to(tl.int64)
    lo = tl.load(starts_ptr + g)
    hi = tl.load(starts_ptr + g + 1)
    if lo < hi:
        d = tl.arange(0, BLOCK_D)
        inside = d < D
        row = g * D + d
        f = tl.load(F_ptr + row, mask=inside, other=0.0)
        total = tl.load(W_ptr + g)
        for i in range(lo, hi):
            m = tl.load(masks_ptr + i).to(tl.int64)
            w = tl.load(weights_ptr + i)
            f += w * tl.load(feats_ptr + m * D + d, mask=inside, other=0.0)
            total += w
        tl.store(F_ptr + row, f, mask=inside)
        tl.store(W_ptr + g, total)


def add_pairs_triton(F: torch.Tensor, W: torch.Tensor, gaussians: torch.Tensor, masks: torch.Tensor, weights: torch.Tensor,
                     feats: torch.Tensor) -> None:
    """`device_sums.add_pairs_op`'s sums in one launch after a sort, in place: F [N, D], W [N]
    float32 contiguous; gaussians [P] int64 (N: padding), masks [P] int64, weights [P] float32;
    feats [M, D] float32. On a CUDA device (or the CPU under the interpreter)."""
    dev = F.device
    require_cuda(dev, "the fused sums kernel")
    n, dim = F.shape
    if gaussians.shape[0] == 0 or n == 0:
        return
    order, starts = row_runs(gaussians, n)
    launch = strict_launch()
    triton_kernel(_add_pairs_source)[(n,)](
        masks[order].contiguous(), weights[order].to(torch.float32).contiguous(), starts, feats.to(torch.float32).contiguous(), F, W, dim,
        BLOCK_D=triton.next_power_of_2(max(dim, 1)), **launch,
    )  # fmt: skip


def compile_sums_ptx(capability: int = 90, dim: int = 512, ones: bool = False) -> str:
    """The kernel compiled to PTX for sm_`capability` without a GPU (`raster_triton.kernel_ptx`), FMA contraction off as launched."""
    pointers = {"masks_ptr": "*i64", "weights_ptr": "*fp32", "starts_ptr": "*i64", "feats_ptr": "*fp32", "F_ptr": "*fp32", "W_ptr": "*fp32",
                "D": "i32"}
    return kernel_ptx(_add_pairs_source, pointers, {"BLOCK_D": 1 << max(0, dim - 1).bit_length()}, capability, ones, enable_fp_fusion=False)
