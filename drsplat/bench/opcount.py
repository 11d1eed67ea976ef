"""Counting the torch ops and host synchronisations of a piece of work (a TorchDispatchMode).

An op is one call that reaches the dispatcher (one kernel launch on a GPU, roughly): an aten op,
or a custom op such as drsplat::render_topk (drsplat.raster_ops), which counts once plus every
torch op its kernel issues in turn: on CUDA the torch ops around a Triton launch (the launches of
a Triton kernel itself are not torch ops and are not counted), on a CPU the few a numba kernel's
wrapper makes. Counters do not nest across a custom op: the innermost counts it. A host
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

# aten::item reaches a mode as itself only inside a custom op's kernel (below autograd, where it is
# not yet decomposed into _local_scalar_dense, which the mode then does not see)
_DATA_DEPENDENT = {"aten::_local_scalar_dense", "aten::item", "aten::nonzero", "aten::masked_select", "aten::unique", "aten::_unique2", "aten::unique_dim",
                   "aten::unique_consecutive", "aten::nonzero_static"}


@dataclass
class OpCounts:
    """ops: dispatcher calls (aten ops, and custom ops with the torch ops their kernels issue);
    views: those that only make a view (no kernel launch on a GPU); syncs: the host-syncing ones;
    by_name: calls per op name."""

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


def _custom_kernel(name: str, args: tuple):
    """The Python kernel that custom op `name` (torch.library.custom_op) runs on its tensor
    arguments' device, or None (an op defined otherwise, or a torch without this registry)."""
    from torch._library import custom_ops

    opdef = getattr(custom_ops, "OPDEFS", {}).get(name)
    device = next((a.device.type for a in args if isinstance(a, torch.Tensor)), None)
    return None if opdef is None or device is None else getattr(opdef, "_backend_fns", {}).get(device)


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
        name = func._schema.name + (f".{func._overloadname}" if func._overloadname != "default" else "")
        self.counts.ops += 1
        self.counts.views += bool(func.is_view)
        self.counts.by_name[name] += 1
        if is_host_sync(name, args, kwargs):
            self.counts.syncs += 1
            self.counts.syncs_by_name[name] += 1
        if name.startswith("aten::"):
            return func(*args, **kwargs)
        # a custom op (drsplat::...): the torch ops its kernel issues count too (on CUDA the fused
        # op's tile lists are torch ops around its Triton launches; numba's CPU kernel issues few)
        kernel = _custom_kernel(func._schema.name, args)
        if kernel is None:
            return func(*args, **kwargs)
        with OpCounter() as inner:  # the kernel called directly: through the dispatcher it would come back here
            out = kernel(*args, **kwargs)
        self._fold(inner.counts)
        return out

    def _fold(self, inner: OpCounts) -> None:
        self.counts.ops += inner.ops
        self.counts.views += inner.views
        self.counts.syncs += inner.syncs
        self.counts.by_name.update(inner.by_name)
        self.counts.syncs_by_name.update(inner.syncs_by_name)
