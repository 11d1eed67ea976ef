"""Counting the torch ops and host synchronisations of a piece of work (a TorchDispatchMode).

An op is one aten call that reaches the dispatcher (one kernel launch on a GPU, roughly). A host
sync is an op that makes the host wait for the device on CUDA: reading a scalar
(`aten::_local_scalar_dense`, behind `.item()`, `int(t)`, `bool(t)`), ops whose output size
depends on the data (`nonzero`, boolean-mask indexing and `masked_select`, `unique`,
`repeat_interleave` without an output size), copies from a device to the CPU (except with
non_blocking into pinned memory, which the host reads later, after an event: a read a view late,
drsplat.registration.device_sums.DeviceRead), and copies from
the CPU to a device that are blocking or from pageable memory (CUDA waits for the stream's queued
work before it copies pageable memory; only a pinned source with non_blocking runs ahead). The same ops are
counted on a CPU, where they cost no synchronisation but show what a GPU run would wait for.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import torch
from torch.utils._python_dispatch import TorchDispatchMode

_DATA_DEPENDENT = {"aten::_local_scalar_dense", "aten::nonzero", "aten::masked_select", "aten::unique", "aten::_unique2", "aten::unique_dim",
                   "aten::unique_consecutive", "aten::nonzero_static"}


@dataclass
class OpCounts:
    """ops: aten calls; views: those that only make a view (no kernel launch on a GPU); syncs: the
    host-syncing ones; by_name: calls per op name."""

    ops: int = 0
    views: int = 0
    syncs: int = 0
    by_name: Counter = field(default_factory=Counter)
    syncs_by_name: Counter = field(default_factory=Counter)


def is_host_sync(name: str, args: tuple, kwargs: dict) -> bool:
    """Whether aten op `name` called with (args, kwargs) makes the host wait for a device (module docstring)."""
    if name in _DATA_DEPENDENT:
        return name != "aten::nonzero_static"  # a fixed-size output: no wait
    if name in ("aten::index.Tensor", "aten::index_put_", "aten::index_put", "aten::_index_put_impl_"):
        indices = args[1] if len(args) > 1 else kwargs.get("indices", ())
        return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in indices or ())
    if name == "aten::repeat_interleave.Tensor" or name == "aten::repeat_interleave.self_Tensor":
        return kwargs.get("output_size") is None
    if name in ("aten::_to_copy", "aten::copy_"):
        src = args[1] if name == "aten::copy_" else args[0]
        dst_device = args[0].device if name == "aten::copy_" else kwargs.get("device")
        if not isinstance(src, torch.Tensor) or dst_device is None:
            return False
        dst = torch.device(dst_device).type
        non_blocking = args[2] if name == "aten::copy_" and len(args) > 2 else kwargs.get("non_blocking", False)
        if src.device.type != "cpu":  # into pinned memory with non_blocking: queued, the host reads it after an event
            return dst == "cpu" and not (name == "aten::copy_" and non_blocking and _pinned(args[0]))
        return dst != "cpu" and not (non_blocking and _pinned(src))
    return False


def _pinned(tensor: torch.Tensor) -> bool:
    """Whether a CPU tensor is in pinned memory (False where this torch has no accelerator to pin for)."""
    try:
        return bool(tensor.is_pinned())
    except RuntimeError:
        return False


class OpCounter(TorchDispatchMode):
    """`with OpCounter() as c: work()`, then c.counts (OpCounts)."""

    def __init__(self):
        super().__init__()
        self.counts = OpCounts()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = f"aten::{func._schema.name.split('::')[-1]}" + (f".{func._overloadname}" if func._overloadname != "default" else "")
        self.counts.ops += 1
        self.counts.views += bool(func.is_view)
        self.counts.by_name[name] += 1
        if is_host_sync(name, args, kwargs):
            self.counts.syncs += 1
            self.counts.syncs_by_name[name] += 1
        return func(*args, **kwargs)
