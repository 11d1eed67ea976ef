"""Query scoring in torch (CPU or CUDA): exact fp16 cosine and PQ look-up-table scoring.

The same math as the CPU kernels of drsplat.lang.lut (`half_scores`, `lut_scores`), tested equal
within 1e-5: for exact fields cos(q, f_i) = (f_i · q) / |f_i| with f_i the stored float16 row
(converted exactly to float32); for PQ fields cos(q, r_i) = ([q·c_{list_i}] + Σ_m LUT[m, code_im]) / |r_i|
with LUT[m, c] = q_m · C[m, c] (built on the CPU by the codebook, K·M·256 floats, then copied).
Zero-norm (unassigned) and non-finite rows score 0. The field's arrays are copied to the device once
(`DeviceField`) and reused by every query.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from drsplat.lang.lut import inverse_norms

ROWS_PER_STEP = 1 << 16  # Gaussians per step: bounds the [K, rows, M] gather of the LUT scorer


@dataclass
class DeviceField:
    """A LanguageField's arrays on one device: features [N, D] float16 (exact) or codes [N, M] int64
    offsets into the flattened tables (m·256 + code) and list_ids [N] int64 (ivfpq); inv_norms [N] float32."""

    device: torch.device
    inv_norms: torch.Tensor
    features: torch.Tensor | None = None
    lut_index: torch.Tensor | None = None
    list_ids: torch.Tensor | None = None


def to_device(field, device: str | torch.device) -> DeviceField:
    """Copy what scoring needs of `field` (a drsplat.lang.LanguageField) to `device`."""
    device = torch.device(device)
    inv = torch.from_numpy(inverse_norms(field.norms)).to(device)
    if field.kind == "exact":
        return DeviceField(device, inv, features=torch.from_numpy(np.ascontiguousarray(field.features, np.float16)).to(device))
    codes = field.codes  # read once: held blocked only, each read rebuilds [N, M] (`PQStorage.codes`)
    offsets = torch.arange(codes.shape[1], dtype=torch.int64, device=device) * 256
    lut_index = torch.from_numpy(np.ascontiguousarray(codes, np.uint8)).to(device).to(torch.int64) + offsets
    ids = None
    if field.list_ids is not None and field.codebook.coarse is not None:
        ids = torch.from_numpy(np.asarray(field.list_ids, np.int64)).to(device)
    return DeviceField(device, inv, lut_index=lut_index, list_ids=ids)


def half_scores_torch(dev: DeviceField, queries: np.ndarray, rows_per_step: int = ROWS_PER_STEP) -> torch.Tensor:
    """Cosine of unit queries [K, D] against the float16 features: [N, K] float32 on the device; 0 for an
    unassigned row and for one holding inf or NaN, whatever its norm (`lut.half_scores`: with finite
    queries such a row's products are never finite)."""
    q = torch.from_numpy(np.ascontiguousarray(queries, np.float32)).to(dev.device)
    n = dev.features.shape[0]
    out = torch.empty((n, q.shape[0]), dtype=torch.float32, device=dev.device)
    for s in range(0, n, rows_per_step):
        rows = dev.features[s : s + rows_per_step].float()
        out[s : s + rows_per_step] = (rows @ q.T) * dev.inv_norms[s : s + rows_per_step, None]
    return torch.where((dev.inv_norms[:, None] > 0) & torch.isfinite(out), out, 0.0)


def lut_scores_torch(dev: DeviceField, luts: np.ndarray, coarse: np.ndarray, rows_per_step: int = ROWS_PER_STEP) -> torch.Tensor:
    """PQ scores from tables luts [K, M, 256] and coarse [K, nlist] (or [K, 0]): [N, K] float32 on the device."""
    k_count = luts.shape[0]
    flat = torch.from_numpy(np.ascontiguousarray(luts.reshape(k_count, -1), np.float32)).to(dev.device)
    table = torch.from_numpy(np.ascontiguousarray(coarse, np.float32)).to(dev.device) if dev.list_ids is not None and coarse.shape[1] else None
    n = dev.lut_index.shape[0]
    out = torch.empty((n, k_count), dtype=torch.float32, device=dev.device)
    step = max(1, rows_per_step // max(1, k_count))
    for s in range(0, n, step):
        idx = dev.lut_index[s : s + step]
        acc = flat[:, idx].sum(dim=2)  # [K, rows]
        if table is not None:
            acc = acc + table[:, dev.list_ids[s : s + step]]
        out[s : s + step] = acc.T * dev.inv_norms[s : s + step, None]
    return out


def field_scores_torch(field, queries: np.ndarray, dev: DeviceField) -> torch.Tensor:
    """`LanguageField.scores` (float32 tables) computed on `dev.device`: unit queries [K, D] -> [N, K] tensor."""
    if field.kind == "exact":
        return half_scores_torch(dev, queries)
    return lut_scores_torch(dev, field.codebook.luts(queries), field.codebook.coarse_table(queries))
