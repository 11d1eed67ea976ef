"""Torch twin of `drsplat.registration.Accumulator`: sparse (Gaussian, mask) sums on the device.

Per view, the top-k entries (Gaussian i, pixel p, weight w) whose pixel lies in a mask j are
reduced to distinct pairs with summed weights w_ij = Σ_{p ∈ j} w_i(p) (`torch.unique` on the key
i·M + j, then `index_add_`), and folded into the running sums

    F [N, D] += w_ij · f_j,   W [N] += w_ij

with `index_add_` in blocks of pairs (memory: N·D + one view's pairs, never N x M). The views
stream through; nothing of a view is kept once it is added. Same interface as `Accumulator`
(add_view, add_pairs, flush, sums): registration sums the views' pairs with either
(`register_scene(..., engine=...)`, through `torch_compute_engine`).
"""

from __future__ import annotations

import numpy as np
import torch

PAIR_BLOCK = 1 << 16  # pairs folded into F per index_add_ (bounds the [block, D] temporary)


def _as_tensor(x, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(device=device, dtype=dtype)
    return torch.as_tensor(np.asarray(x), device=device).to(dtype)


class TorchAccumulator:
    """Running sums F [N, D] = Σ_j w_ij f_j and W [N] = Σ_j w_ij as float32 tensors on `device`."""

    def __init__(self, num_gaussians: int, dim: int, device: str | torch.device = "cpu", pair_block: int = PAIR_BLOCK):
        self.device = torch.device(device)
        self.F = torch.zeros((num_gaussians, dim), dtype=torch.float32, device=self.device)
        self.W = torch.zeros(num_gaussians, dtype=torch.float32, device=self.device)
        self.pair_block = max(1, int(pair_block))

    @property
    def dim(self) -> int:
        return int(self.F.shape[1])

    def view_pairs(self, ids, weights, mask_ids, num_masks: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int]:
        """The view's distinct (Gaussian, mask) pairs: (gaussian [U] int64, mask [U] int64, w_ij [U] float32, contributing entries).

        ids, weights: [H, W, k] (numpy or tensors; -1 = no Gaussian). mask_ids: [H, W] (-1 = no mask).
        """
        k = ids.shape[-1]
        g = _as_tensor(ids, self.device, torch.int64).reshape(-1)
        w = _as_tensor(weights, self.device, torch.float32).reshape(-1)
        m = _as_tensor(mask_ids, self.device, torch.int64).reshape(-1).repeat_interleave(k)
        keep = (g >= 0) & (m >= 0) & (m < num_masks)
        g, m, w = g[keep], m[keep], w[keep]
        keys, inverse = torch.unique(g * max(num_masks, 1) + m, return_inverse=True)
        summed = torch.zeros(keys.numel(), dtype=torch.float32, device=self.device).index_add_(0, inverse, w)
        return keys // max(num_masks, 1), keys % max(num_masks, 1), summed, int(g.numel())

    def add_view(self, ids, weights, mask_ids, feats) -> tuple[int, int]:
        """Add one view. Returns (contributing pairs, distinct (Gaussian, mask) pairs).

        ids, weights: [H, W, k]; mask_ids: [H, W]; feats: [M, D] mask embeddings (numpy or tensors).
        """
        rows = _as_tensor(feats, self.device, torch.float32)
        gauss, mask, w, entries = self.view_pairs(ids, weights, mask_ids, rows.shape[0])
        self._fold(gauss, mask, w, rows)
        return entries, int(gauss.numel())

    def add_pairs(self, gaussians, masks, weights, feats) -> None:
        """Add one view's distinct pairs (gaussians [P], masks [P] rows of feats [M, D], weights [P]), as
        registration's executors produce them (`drsplat.registration.Coalescer`)."""
        self._fold(_as_tensor(gaussians, self.device, torch.int64), _as_tensor(masks, self.device, torch.int64),
                   _as_tensor(weights, self.device, torch.float32), _as_tensor(feats, self.device, torch.float32))

    def _fold(self, gauss: torch.Tensor, mask: torch.Tensor, w: torch.Tensor, rows: torch.Tensor) -> None:
        """F[g] += w · rows[m] and W[g] += w, in blocks of pairs (bounds the [block, D] temporary)."""
        for start in range(0, gauss.numel(), self.pair_block):
            sl = slice(start, start + self.pair_block)
            self.F.index_add_(0, gauss[sl], w[sl, None] * rows[mask[sl]])
        self.W.index_add_(0, gauss, w)

    def flush(self, keep_last: int = 0) -> None:
        """Nothing is buffered: views are folded in as they are added."""

    def sums(self) -> tuple[np.ndarray, np.ndarray]:
        """(F [N, D], W [N]) as float32 numpy arrays."""
        return self.F.cpu().numpy(), self.W.cpu().numpy()


def torch_compute_engine(device: str | torch.device, record):
    """registration's ComputeEngine (`record`) for the torch rasterizer + TorchAccumulator on `device`:
    rasterized views stay on the device from the rasterizer to the sums."""
    from drsplat.raster_torch import prepare_scene_torch, rasterize_torch

    device = torch.device(device)

    def render(prepared, camera, topk, _previous):
        out = rasterize_torch(prepared, camera, topk, device=device)
        if device.type == "cuda":
            torch.cuda.synchronize(device)  # honest per-stage timings
        return out

    return record(
        prepare=lambda scene: prepare_scene_torch(scene, device),
        render=render,
        accumulator=lambda n, dim: TorchAccumulator(n, dim, device),
    )
