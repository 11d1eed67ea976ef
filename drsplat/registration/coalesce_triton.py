"""A view's coalescing on CUDA in two Triton launches around a sort: `device_sums.coalesce_torch` fused.

`coalesce_torch` is 59 torch ops (on a 16x12 view, k = 6). Here:

1. `_keys_source`, per slot: the key j·N + i of its (Gaussian i, mask j) pair (an empty slot or
   unmasked pixel: M·N + its slot index, after all others, each its own segment), its weight (0
   where not a pair), the contributing slots counted and the masks that hold a pair flagged (an
   atomic add of integers and stores of 1: exact in any order);
2. a stable sort of the keys, so each segment keeps its slots in pixel-then-slot order; the
   segments numbered by a cumulative sum of the key changes; each segment's weights summed by
   `index_add` over the segment numbers (torch: in order on a CPU, with atomics in no fixed order
   on CUDA, as `coalesce_torch`);
3. `_segments_source`, per position: a real segment's first position writes its pair's Gaussian
   and mask at the segment's number; the real segments are counted.

The same outputs as `coalesce_torch` (DevicePairs padded to H·W·k, sorted by (mask, Gaussian)) in
24 torch ops and two launches instead of 59 (tests/test_coalesce_triton.py runs it in Triton's interpreter against
`coalesce_torch`, bit for bit).
"""

from __future__ import annotations

import torch

from drsplat.raster_triton import kernel_ptx, require_cuda, triton_kernel

try:  # triton comes with torch's CUDA builds
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - depends on the torch build
    triton = None
    tl = None

BLOCK = 256  # slots (or sorted positions) per program


def _keys_source(ids_ptr, weights_ptr, masks_ptr, keys_ptr, w_ptr, flags_ptr, counts_ptr, S, k, num_masks, num_gaussians, empty,
                 BLOCK: tl.constexpr):  # fmt: skip
    """Slots b·BLOCK .. +BLOCK: keys [S] int64, w [S] float32, flags [M] (1 where a pair), counts[1] += pairs.

    `empty` = M·N comes from the host: Triton passes an integer argument equal to 1 as a Python
    constant, on which a method such as `.to` does not exist (1 mask failed to compile on an H100)."""
    slot = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    live = slot < S
    g = tl.load(ids_ptr + slot, mask=live, other=-1).to(tl.int64)
    m = tl.load(masks_ptr + slot // k, mask=live, other=-1).to(tl.int64)
    valid = live & (g >= 0) & (m >= 0) & (m < num_masks)
    tl.store(keys_ptr + slot, tl.where(valid, m * num_gaussians + g, empty + slot), mask=live)
    tl.store(w_ptr + slot, tl.where(valid, tl.load(weights_ptr + slot, mask=live, other=0.0), 0.0), mask=live)
    tl.store(flags_ptr + tl.where(valid, m, 0), tl.full([BLOCK], 1, tl.int64), mask=valid)
    tl.atomic_add(counts_ptr + 1, tl.sum(valid.to(tl.int64), axis=0))


def _segments_source(keys_ptr, segment_ptr, out_g_ptr, out_m_ptr, counts_ptr, S, num_gaussians, empty, BLOCK: tl.constexpr):
    """Sorted positions b·BLOCK .. +BLOCK: each real segment's first position writes its pair's
    (Gaussian, mask) at its segment number; counts[0] += real segments."""
    pos = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    live = pos < S
    key = tl.load(keys_ptr + pos, mask=live, other=-1)
    before = tl.load(keys_ptr + pos - 1, mask=live & (pos > 0), other=-1)
    first = live & (key != before) & (key < empty)
    seg = tl.load(segment_ptr + pos, mask=first, other=0)
    tl.store(out_g_ptr + seg, key % num_gaussians, mask=first)
    tl.store(out_m_ptr + seg, key // num_gaussians, mask=first)
    tl.atomic_add(counts_ptr, tl.sum(first.to(tl.int64), axis=0))


def coalesce_triton(ids: torch.Tensor, weights: torch.Tensor, mask_ids: torch.Tensor, num_masks: int, num_gaussians: int):
    """`coalesce_torch`'s (gaussians, masks, weights, counts, mask flags) in two launches around a
    sort: ids [H, W, k] int, weights [H, W, k] float32, mask_ids [H, W] int, on a CUDA device (or the
    CPU under the interpreter). Outputs padded to H·W·k (Gaussian N, mask 0, weight 0 past the
    P distinct pairs); counts [2] = (P, contributing slots)."""
    dev = ids.device
    require_cuda(dev, "the fused coalescing kernel")
    k = int(ids.shape[-1]) if ids.dim() == 3 else 1
    slots = int(ids.numel())
    empty = int(num_masks) * int(num_gaussians)
    out_g = torch.full((slots,), int(num_gaussians), dtype=torch.int64, device=dev)
    out_m = torch.zeros(slots, dtype=torch.int64, device=dev)
    out_w = torch.zeros(slots, dtype=torch.float32, device=dev)
    counts = torch.zeros(2, dtype=torch.int64, device=dev)
    flags = torch.zeros(max(int(num_masks), 1), dtype=torch.int64, device=dev)
    if slots == 0:
        return out_g, out_m, out_w, counts, flags[: int(num_masks)]
    keys = torch.empty(slots, dtype=torch.int64, device=dev)
    w = torch.empty(slots, dtype=torch.float32, device=dev)
    grid = (triton.cdiv(slots, BLOCK),)
    triton_kernel(_keys_source)[grid](ids.reshape(-1).contiguous(), weights.reshape(-1).to(torch.float32).contiguous(),
                                      mask_ids.reshape(-1).to(device=dev).contiguous(), keys, w, flags, counts, slots, k, int(num_masks),
                                      int(num_gaussians), empty, BLOCK=BLOCK)  # fmt: skip
    if empty + slots < 2**31:  # the same order from a radix sort of half the passes (as coalesce_torch)
        keys = keys.to(torch.int32)
    sorted_keys, order = torch.sort(keys, stable=True)
    changes = torch.ones(slots, dtype=torch.int32, device=dev)
    changes[1:] = (sorted_keys[1:] != sorted_keys[:-1]).to(torch.int32)
    segment = torch.cumsum(changes, 0, dtype=torch.int64) - 1
    # each segment's weights added in its slots' order: sequential on a CPU (numba's bits); CUDA's
    # atomics add them in no fixed order, where a walk of each segment in order would serialise a
    # large Gaussian's thousands of slots in one mask on one thread
    out_w.index_add_(0, segment, w[order])
    triton_kernel(_segments_source)[grid](sorted_keys, segment, out_g, out_m, counts, slots, max(int(num_gaussians), 1), empty, BLOCK=BLOCK)
    return out_g, out_m, out_w, counts, flags[: int(num_masks)]


def compile_coalesce_ptx(capability: int = 90, ones: bool = False) -> str:
    """Both kernels compiled to PTX for sm_`capability` without a GPU (`raster_triton.kernel_ptx`),
    one after the other; `ones` as there."""
    keys = {"ids_ptr": "*i32", "weights_ptr": "*fp32", "masks_ptr": "*i32", "keys_ptr": "*i64", "w_ptr": "*fp32", "flags_ptr": "*i64",
            "counts_ptr": "*i64", "S": "i64", "k": "i32", "num_masks": "i32", "num_gaussians": "i32", "empty": "i64"}
    segments = {"keys_ptr": "*i32", "segment_ptr": "*i64", "out_g_ptr": "*i64", "out_m_ptr": "*i64", "counts_ptr": "*i64", "S": "i64",
                "num_gaussians": "i64", "empty": "i64"}
    return (kernel_ptx(_keys_source, keys, {"BLOCK": BLOCK}, capability, ones)
            + kernel_ptx(_segments_source, segments, {"BLOCK": BLOCK}, capability, ones))
