"""Registration's per-view coalescing and per-Gaussian sums in torch, on the device a view was rendered on.

The torch engine renders a view's top-k lists on its device (CPU or CUDA). Instead of copying the
lists [H, W, k] to the host for the numba coalescer and sums (drsplat.registration.coalesce,
drsplat.registration.sums), this module keeps them there:

    coalesce_torch   ids, weights [H, W, k], mask ids [H, W] -> the view's distinct (Gaussian, mask)
                     pairs with summed weights, fixed-size ops only (no host synchronisation);
    coalesce_pairs   the same as one torch op (`coalesce_pairs_op`: the numba coalescer on a CPU,
                     coalesce_torch on CUDA), what registration calls
    view_weights_torch, explain_weights_torch
                     every mode's per-view weighting (the explain EM included) on the device
    DeviceSink       F [N, D], W [N] on the device, each view's pairs added in view order
                     (index_add), copied to the host once, when the sink gives its one block
    DeviceVoteSink   a `-vote` mode's sink on the device: the paper's sums (DeviceSink) and the vote
                     slots (`vote_view_torch`), trimmed on the host once, at the end
    view_stats_torch a `-reject` mode's per-view floater statistics (the in-front test of every
                     slot against the pixel's median Gaussian, per-Gaussian max / sums), and
    DeviceSupport    their fold over the views, kept on the device (copied to the host for a
                     checkpoint snapshot and once at the end, for the rejected mask)

Each per-view stage is also one torch op (torch.library) with a kernel per device, and
registration calls the ops: `coalesce_pairs_op`, `view_stats_op` (front flags and statistics),
`explain_weights_op`, `vote_fold_op`, beside drsplat.raster_ops.render_topk. On a CPU their kernels
are the host path's numba kernels (the same bits: each op is tested against its torch form here),
so a CPU view is a few dozen dispatcher calls; on CUDA they are the torch forms here (and Triton
kernels), whose torch ops the bench's counter counts inside the op.

A view's sizes are read one view late: its tile lists are sized from the views before it
(`TileCapacity`, nothing read), and its distinct and contributing pair counts and the tile
entries it needed travel to the host in one small copy that does not wait (`DeviceRead`). The
driver takes each view only once the next one is computed (drsplat.registration.executor.
one_view_behind), so by the time it reads a view's sizes the device has long finished them and is
busy with the next view; a view whose tile lists fell short is computed again with exact lists
(`DevicePairs.resolve`) before anything of it is summed, so every view is summed whole and in
order. The M flags of the masks that reached a Gaussian (for a `-vote` mode's mask clusters, made
on the host) travel in the same read, and the vote's rounds are folded one view late too
(`DeviceVoteSink`), so no mode reads the device inside a view. The pairs themselves reach the
host only when a pair log is kept (a checkpoint, or a run in Gaussian blocks), through
`DevicePairs.to_host`. torch is imported here: the driver imports this module
only for the torch engine.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np
import torch

from drsplat.cameras import Camera
from drsplat.raster import NEAR, project_gaussians
from drsplat import raster_ops, raster_torch
from drsplat.raster_ops import host_array, host_tensor
from drsplat.raster_torch import TorchScene, triton_available, project_gaussians_torch, rasterize_torch
from drsplat._raster_kernels import BLUR
from drsplat.registration.aggregate import (ANCHOR_GAIN, ELLIPSE_D2, SHARP_BLUR, SHARP_EXP_SQUARINGS, SHARP_EXP_TERMS, SHARP_FLOOR, SHARP_LOG_FLOOR, EXPLAIN_ITERATIONS, FRONT_MAX, FRONT_REACH_SHARE, FRONT_TOLERANCE, PROJECTED_WEIGHTINGS, WEIGHTINGS,
                                            STATS_SCALE, RayGeometry, SurfaceSupport, explain_weights, surface_stats, view_weights)
from drsplat.defaults import VOTE_SLOTS
from drsplat.registration.coalesce import Coalescer, sort_within_masks
from drsplat.registration.pairlog import ViewPairs
from drsplat.registration.sink import Block, PairSource, sample_rows
from drsplat.registration.sums import add_pairs_in_place
from drsplat.registration.vote import CLUSTER_COSINE, FULL_VIEW, PRESENCE, MaskClusters, Specificity, fold_view_votes, kept_weights, trim_sums

PAIR_CHUNK = 1 << 15  # pairs per F update: a [PAIR_CHUNK, D] product (64 MB at D = 512), like the host accumulator's pair buffer
DEVICE_HEADROOM = 1.25  # free device memory wanted per byte of the sums (the chunk products, the allocator's slack)
TILE_HEADROOM = 1.25  # tile-list entries allocated per entry the recent views needed
TILE_WINDOW = 8  # recent views whose tile-list sizes set the next view's
TILE_ROUND = 1 << 16  # tile-list sizes are multiples of this (fewer distinct sizes for the caching allocator)
STAGE_BYTES = 64 << 20  # bytes per pinned buffer when large sums are copied to the host (`to_host`)


class DeviceRead:
    """A few int64 values of the device that the host reads later without waiting for the work
    queued after them: on CUDA copied with non_blocking into pinned memory and marked by an event,
    so `values` waits only for the work up to the copy (a view late, long done); on a CPU the
    tensor itself.

    values: [K] int64 on the device.
    """

    def __init__(self, values: torch.Tensor):
        self._event = None
        self._host = values
        if values.device.type == "cuda":
            self._host = torch.empty(values.shape, dtype=values.dtype, pin_memory=True)
            self._host.copy_(values, non_blocking=True)
            self._event = torch.cuda.Event()
            self._event.record()
        self._values: list[int] | None = None

    @property
    def event(self):
        """The torch.cuda.Event recorded after the values were made (None on a CPU)."""
        return self._event

    def values(self) -> list[int]:
        if self._values is None:
            if self._event is not None:
                self._event.synchronize()
            self._values = [int(x) for x in self._host.tolist()]
        return self._values


@dataclass
class TileCapacity:
    """How many tile-list entries to allocate for a view without reading the device: TILE_HEADROOM x
    the most any of the last TILE_WINDOW views read needed, rounded up to a multiple of TILE_ROUND;
    None (size exactly, one read) before any view was read. A view that needs more is computed again
    (`DevicePairs.resolve`), and its size joins the window."""

    recent: list[int] = field(default_factory=list)
    exact: bool = False  # size every view exactly (`for_device`)

    def capacity(self) -> int | None:
        if self.exact or not self.recent:
            return None
        want = max(1, int(np.ceil(TILE_HEADROOM * max(self.recent))))
        return -(-want // TILE_ROUND) * TILE_ROUND

    @classmethod
    def for_device(cls, device: torch.device) -> TileCapacity:
        """The policy for views rendered on `device`: exact on a CPU when the fused op renders
        there (its numba kernels size the lists on the host, reading no device), learned otherwise."""
        return cls(exact=device.type == "cpu" and raster_torch.has_fused_kernel(device))

    def saw(self, needed: int) -> None:
        self.recent = (self.recent + [int(needed)])[-TILE_WINDOW:]

    def pending(self, read: DeviceRead, capacity: int | None, redo: Callable[[], ViewPairs]) -> PendingSizes:
        """The PendingSizes of a view rendered with lists of `capacity` entries: its read tells this
        policy the entries needed."""
        return PendingSizes(read, capacity, self.saw, redo)


@dataclass
class PendingSizes:
    """What a view computed on the device still has to learn from it (`DevicePairs.resolve`).

    read: (distinct pairs, contributing slots, tile-list entries needed); tile_capacity: the entries
    its tile lists held (None: sized exactly); on_read: told the entries needed (`TileCapacity.saw`);
    redo: the view computed again with exact tile lists (a new, pending ViewPairs)."""

    read: DeviceRead
    tile_capacity: int | None
    on_read: Callable[[int], None]
    redo: Callable[[], ViewPairs]


@dataclass
class DevicePairs:
    """One view's distinct (Gaussian, mask) pairs on the device.

    gaussians: [P] int64, masks: [P] int64 (rows of the view's embeddings), weights: [P] float32
    w_ij, sorted by (mask, Gaussian). When `coalesce_torch` (or `coalesce_pairs` on CUDA; on a CPU
    it returns the P pairs exactly) returns them they are padded to the view's H·W·k slots (padding: Gaussian = num_gaussians, mask 0, weight 0, after the real pairs)
    and `counts` [2] int64 holds (distinct pairs P, contributing slots); `trimmed` cuts them to P.
    mask_flags: [M] int64, 1 for the masks some pair holds (or None). pending: the sizes not read yet
    (`resolve`), or None. ready: on CUDA, the event after which the pairs are made (`to_host`).
    """

    gaussians: torch.Tensor
    masks: torch.Tensor
    weights: torch.Tensor
    counts: torch.Tensor
    mask_flags: torch.Tensor | None = None
    pending: PendingSizes | None = None
    ready: object | None = None  # a torch.cuda.Event recorded once the pairs were made (CUDA), else None

    @property
    def num_distinct(self) -> int:
        if self.pending is not None:
            raise RuntimeError("the view's sizes are not read yet: take ViewPairs.resolved() first")
        return int(self.gaussians.shape[0])

    def trimmed(self, distinct: int) -> DevicePairs:
        """The first `distinct` pairs (views of the tensors; `distinct` read from `counts` by the caller)."""
        return DevicePairs(self.gaussians[:distinct], self.masks[:distinct], self.weights[:distinct], self.counts, self.mask_flags)

    def resolve(self, view: ViewPairs) -> ViewPairs:
        """`view` (whose pairs these are) with its sizes read: the pairs trimmed, num_pairs and the
        present masks set, or, when its tile lists fell short, the view computed again with exact
        lists and resolved."""
        distinct, contributing, needed, *present = self.pending.read.values()
        self.pending.on_read(needed)
        if self.pending.tile_capacity is not None and needed > self.pending.tile_capacity:
            return self.pending.redo().resolved()
        pairs = dataclasses.replace(self.trimmed(distinct), ready=self.pending.read.event)
        return dataclasses.replace(view, num_pairs=contributing, device=pairs, present=np.array(present, bool))

    def present(self) -> np.ndarray:
        """[M] bool on the host: the masks some pair holds (`mask_flags` copied, not the pairs)."""
        return self.mask_flags.cpu().numpy().astype(bool)

    def to_host(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(gaussians [P] int32, masks [P] int32, weights [P] float32) on the host, in one copy.

        On CUDA, when the pairs' DeviceRead marked where they were done (`ready`), the packing and
        the copy run on a side stream that waits for that mark only, so the host waits for this
        copy, not for the next view's render queued after it (the driver takes a view while the
        next one renders). Unmeasured on a GPU."""

        def packed() -> torch.Tensor:
            return torch.stack([self.gaussians.to(torch.int32), self.masks.to(torch.int32), self.weights.view(torch.int32)])

        if self.ready is None:
            host = packed().cpu().numpy()
        else:
            side = torch.cuda.Stream(device=self.gaussians.device)
            side.wait_event(self.ready)
            with torch.cuda.stream(side):
                pinned = torch.empty((3, self.gaussians.shape[0]), dtype=torch.int32, pin_memory=True)
                pinned.copy_(packed(), non_blocking=True)
            side.synchronize()
            host = pinned.numpy()
        return host[0].copy(), host[1].copy(), host[2].view(np.float32).copy()


def to_device(array: np.ndarray, device: torch.device) -> torch.Tensor:
    """`array` (a writable host array) on `device` without the host waiting for queued device work:
    a copy from pageable memory to CUDA waits for the stream, so the array is staged in pinned
    memory and copied with non_blocking (the caching host allocator keeps the pinned copy until the
    copy is done). On the CPU: a tensor sharing the array.

    The array is copied into the pinned buffer by numpy, on one thread: `tensor.pin_memory()` copies
    with torch's thread pool, and for a view's mask ids (1.2 MB) or embeddings that took 1-5 ms of
    the H100 machine's host per view (2026-11-27), while the GPU waited for the next launch."""
    tensor = host_tensor(array)
    if device.type != "cuda":
        return tensor
    pinned = torch.empty(tensor.shape, dtype=tensor.dtype, pin_memory=True)
    pinned.numpy()[...] = array
    return pinned.to(device, non_blocking=True)


def to_host(tensor: torch.Tensor, staged: bool | None = None, chunk_bytes: int = STAGE_BYTES) -> np.ndarray:
    """`tensor` [R, ...] as a host array: on a CPU the tensor's own memory (no copy), on CUDA a new
    array filled `chunk_bytes` of rows at a time through two pinned buffers (`staged`, default on
    CUDA; on a CPU too when asked, with unpinned buffers, as the tests do).

    A plain `.cpu()` copies a large tensor into pageable memory through the driver's own staging:
    F of flowers (542k x 512 float32, 1.1 GB) took 783 ms on an H100 (1.4 GB/s, 2026-11-27). Here
    the device copies rows into one pinned buffer while the host moves the other's rows into the
    array, so the bus runs at pinned speed and the host's copy overlaps it.
    """
    staged = tensor.device.type == "cuda" if staged is None else staged
    if not staged:
        return tensor.cpu().numpy()
    out = np.empty(tuple(tensor.shape), dtype=torch.empty(0, dtype=tensor.dtype).numpy().dtype)
    if tensor.numel() == 0:
        return out
    flat = tensor.contiguous().reshape(tensor.shape[0] if tensor.dim() else 1, -1)
    host = out.reshape(flat.shape)
    step = max(1, int(chunk_bytes) // (flat.shape[1] * flat.element_size()))
    pinned = tensor.device.type == "cuda"
    buffers = [torch.empty((min(step, flat.shape[0]), flat.shape[1]), dtype=flat.dtype, pin_memory=pinned) for _ in range(2)]
    queued: list[tuple[int, int, torch.Tensor, object]] = []  # (first row, rows, buffer, event) in flight

    def drain() -> None:
        start, rows, buffer, event = queued.pop(0)
        if event is not None:
            event.synchronize()
        host[start : start + rows] = buffer[:rows].numpy()

    for i, start in enumerate(range(0, flat.shape[0], step)):
        rows, buffer = min(step, flat.shape[0] - start), buffers[i % 2]
        buffer[:rows].copy_(flat[start : start + rows], non_blocking=pinned)
        event = None
        if pinned:
            event = torch.cuda.Event()
            event.record()
        queued.append((start, rows, buffer, event))
        if len(queued) == 2:  # the other buffer's copy was queued earlier: empty it while this one fills
            drain()
    while queued:
        drain()
    return out


def spread_rows(used: torch.Tensor, rows: torch.Tensor, num_rows: int) -> torch.Tensor:
    """[S] int64: `rows` where `used`, else the entry's index mod `num_rows`.

    For the targets of an index_add / amax whose unused entries add zeros: sent to one spare row,
    millions of them serialise on one address under CUDA's atomics (4 ms of a flowers view in the
    coalescing, 12 ms in the floater statistics, on an H100); spread, each adds its zero where it
    changes no bit (sums start at +0.0 and add values >= 0)."""
    return torch.where(used, rows, torch.arange(rows.shape[0], device=rows.device) % num_rows)


def slot_sums(values: torch.Tensor) -> torch.Tensor:
    """Σ over the last axis, added one slot after the other as the numba kernels do: [..., k] -> [..., 1].

    A cumulative sum along the slots laid out as the outer axis ([k, rest], one copy): torch's CUDA
    scan of an outer axis runs one thread per column, adding in order, where its innermost-axis
    scan (the slots' own layout) is a parallel scan, which took 2 ms a call on a flowers view's
    [H·W, 40] float64 weights on an H100 (the explain EM's largest cost there, 2026-11-27; this
    form's GPU time is unmeasured). The CPU adds in order either way.
    """
    k = values.shape[-1]
    if k == 0:
        return values.new_zeros(*values.shape[:-1], 1)
    rows = values.reshape(-1, k).t().contiguous()
    return torch.cumsum(rows, 0)[-1].reshape(*values.shape[:-1], 1)


def coalesce_torch(ids: torch.Tensor, weights: torch.Tensor, mask_ids: torch.Tensor, num_masks: int, num_gaussians: int) -> DevicePairs:
    """A view's distinct (Gaussian, mask) pairs with summed weights, on the tensors' device.

    ids: [H, W, k] int (-1 = empty slot); weights: [H, W, k] float32; mask_ids: [H, W] int (-1 =
    no mask). The view contributes, for every (i, j) with at least one slot,

        w_ij = Σ_{p ∈ mask j} Σ_s [id_s(p) = i] w_s(p)

    Every slot gets the key j·N + i (N = num_gaussians; an empty slot or unmasked pixel the key
    M·N + its slot index, after all others and each its own group, so that the segment sum below
    does not pile millions of zeros onto one address: on CUDA those atomics serialise, 4 ms of a
    flowers view); a stable sort groups equal keys in pixel-then-slot order, and a
    segment sum (index_add over the segment numbers, a cumulative sum of the key changes) adds
    each group's weights in that order, as the numba coalescer does (drsplat.registration.coalesce).
    All shapes are fixed by H·W·k, so nothing waits for the device.

    Order rule: pairs come out sorted by (mask, Gaussian); numba's come mask by mask with the
    Gaussians in first-seen order. Both give each Gaussian its masks in increasing order, which is
    the only order the per-Gaussian sums depend on. Returns `DevicePairs` padded to H·W·k entries,
    counts = (distinct pairs, contributing slots).
    """
    device = ids.device
    k = int(ids.shape[-1]) if ids.dim() == 3 else 1
    g = ids.reshape(-1).to(torch.int64)
    pixel_masks = mask_ids.reshape(-1).to(device=device, dtype=torch.int64)
    m = pixel_masks[:, None].expand(-1, k).reshape(-1)
    valid = (g >= 0) & (m >= 0) & (m < num_masks)
    empty_key = num_masks * num_gaussians
    keys = torch.where(valid, m * num_gaussians + g, empty_key + torch.arange(g.shape[0], device=device))
    if empty_key + g.shape[0] < 2**31:  # the same order from a radix sort of half the passes (0.6 ms of a flowers view on an H100)
        keys = keys.to(torch.int32)
    sorted_keys, order = torch.sort(keys, stable=True)
    w = torch.where(valid, weights.reshape(-1).to(torch.float32), torch.zeros((), dtype=torch.float32, device=device))[order]
    starts = torch.ones_like(sorted_keys, dtype=torch.bool)
    starts[1:] = sorted_keys[1:] != sorted_keys[:-1]
    segment = torch.cumsum(starts, 0) - 1
    sums = torch.zeros_like(w).index_add_(0, segment, w)
    first_key = torch.full_like(sorted_keys, empty_key).scatter_(0, segment, sorted_keys)  # a segment's keys are all equal
    real = first_key < empty_key
    gaussians = torch.where(real, first_key % max(num_gaussians, 1), torch.full_like(first_key, num_gaussians)).to(torch.int64)
    masks = torch.where(real, first_key // max(num_gaussians, 1), torch.zeros_like(first_key)).to(torch.int64)
    counts = torch.stack([(starts & (sorted_keys < empty_key)).sum(), valid.sum()])
    # a mask holds a pair iff one of its pixels has a valid slot: flagged per pixel, not per slot
    reached = torch.where(valid.view(-1, k).any(1), pixel_masks, num_masks)
    flags = torch.zeros(num_masks + 1, dtype=torch.int64, device=device).index_fill_(0, reached, 1)[:num_masks]
    return DevicePairs(gaussians, masks, torch.where(real, sums, torch.zeros_like(sums)), counts, flags)


def check_view_shapes(ids: torch.Tensor, weights: torch.Tensor, mask_ids: torch.Tensor) -> None:
    """ValueError in one sentence unless ids and weights are [H, W, k] and mask_ids [H, W]."""
    if ids.dim() != 3 or weights.shape != ids.shape or tuple(mask_ids.shape) != tuple(ids.shape[:2]):
        raise ValueError(f"a view's top-k ids {tuple(ids.shape)} and weights {tuple(weights.shape)} must be [H, W, k] and its mask ids "
                         f"{tuple(mask_ids.shape)} [H, W]")


@torch.library.custom_op("drsplat::coalesce_pairs", mutates_args=(), device_types="cpu")
def coalesce_pairs_op(ids: torch.Tensor, weights: torch.Tensor, mask_ids: torch.Tensor, num_masks: int,
                      num_gaussians: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """`coalesce_torch` as one op: (gaussians, masks, weights, counts, mask flags) of its DevicePairs.

    Kernels: cpu, the numba coalescer (drsplat.registration.coalesce.Coalescer, the same float32
    sums in the same order) with each mask's pairs sorted by Gaussian, exactly the P distinct pairs
    (no padding: the host knows P at once); cuda, two Triton launches around a sort and an
    index_add (drsplat.registration.coalesce_triton: 24 torch ops), or without Triton `coalesce_torch`
    itself (both padded to H·W·k, nothing read; their float32 atomics add a pair's slots in no
    fixed order there).
    """
    check_view_shapes(ids, weights, mask_ids)
    k = int(ids.shape[-1]) if ids.dim() == 3 else 1
    masks = host_array(mask_ids).astype(np.int32).reshape(ids.shape[:2])
    masks = np.where(masks < num_masks, masks, -1)  # as coalesce_torch: a mask id past the view's masks holds no pair
    g, m, w, contributing = Coalescer(num_gaussians, capacity=1 << 16).coalesce(host_array(ids).reshape(*masks.shape, k), host_array(weights),
                                                                                masks, num_masks)
    sort_within_masks(g, m, w)
    flags = np.zeros(num_masks, np.int64)
    flags[m] = 1
    counts = np.array([g.size, contributing], np.int64)
    return tuple(host_tensor(a) for a in (g.astype(np.int64), m.astype(np.int64), w, counts, flags))


@coalesce_pairs_op.register_kernel("cuda")
def _coalesce_pairs_cuda(ids, weights, mask_ids, num_masks, num_gaussians):
    check_view_shapes(ids, weights, mask_ids)
    if triton_available():
        from drsplat.registration.coalesce_triton import coalesce_triton  # imports triton

        return coalesce_triton(ids, weights, mask_ids, num_masks, num_gaussians)
    pairs = coalesce_torch(ids, weights, mask_ids, num_masks, num_gaussians)
    return pairs.gaussians, pairs.masks, pairs.weights, pairs.counts, pairs.mask_flags


@coalesce_pairs_op.register_fake
def _coalesce_pairs_fake(ids, weights, mask_ids, num_masks, num_gaussians):
    size = torch.library.get_ctx().new_dynamic_size()  # P on a CPU, H·W·k on CUDA
    return (ids.new_empty(size, dtype=torch.int64), ids.new_empty(size, dtype=torch.int64), weights.new_empty(size, dtype=torch.float32),
            ids.new_empty(2, dtype=torch.int64), ids.new_empty(num_masks, dtype=torch.int64))


def coalesce_pairs(ids: torch.Tensor, weights: torch.Tensor, mask_ids: torch.Tensor, num_masks: int, num_gaussians: int) -> DevicePairs:
    """The view's DevicePairs through `coalesce_pairs_op` (one dispatcher call): `coalesce_torch`'s
    pairs, counts and flags; on a CPU exactly the P pairs, on CUDA padded to H·W·k."""
    return DevicePairs(*coalesce_pairs_op(ids, weights.to(torch.float32), mask_ids, int(num_masks), int(num_gaussians)))


def view_weights_torch(weighting: str, ids: torch.Tensor, weights: torch.Tensor, means2d: torch.Tensor | None = None,
                       conics: torch.Tensor | None = None, anchor_gain: float = ANCHOR_GAIN) -> torch.Tensor:
    """A weighting's per-slot weights on the device: drsplat.registration.aggregate.view_weights in torch
    (the math in that module's docstring; float64 like its kernel, the pixel's total summed slot by slot).

    ids, weights: [H, W, k] (-1 = empty); means2d: [N, 2], conics: [N, 3] (a, b, c) of the view's
    projection (float64; needed by core, ellipse, centre, anchor). Returns [H, W, k] float32, 0 where ids < 0.
    """
    if weighting not in WEIGHTINGS:
        raise ValueError(f"unknown weighting {weighting!r}")
    valid = ids >= 0
    zero = torch.zeros((), dtype=torch.float64, device=ids.device)
    w = torch.where(valid, weights.to(torch.float64), zero)
    if weighting == "paper":
        return w.to(torch.float32)
    if weighting == "responsibility":
        total = slot_sums(w)  # slot by slot, as the kernel adds them
        return torch.where(total > 0, w / torch.where(total > 0, total, torch.ones_like(total)), zero).to(torch.float32)
    h, wd, _ = ids.shape
    g = ids.clamp(min=0).to(torch.int64)
    xs = torch.arange(wd, dtype=torch.float64, device=ids.device)[None, :, None]
    ys = torch.arange(h, dtype=torch.float64, device=ids.device)[:, None, None]
    mx, my = means2d[g, 0], means2d[g, 1]
    a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
    if weighting in ("core", "ellipse"):
        dx, dy = mx - (xs + 0.5), my - (ys + 0.5)
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        out = w * torch.exp(torch.clamp(power, max=0.0)) if weighting == "core" else torch.where(-2.0 * power <= ELLIPSE_D2, w, zero)
    elif weighting == "sharp":
        q = torch.clamp(_sharp_exponent(mx - (xs + 0.5), my - (ys + 0.5), a, b, c), min=SHARP_LOG_FLOOR, max=0.0)
        out = w * torch.clamp(sharp_exp_torch(q), min=SHARP_FLOOR)
    else:
        at_centre = (torch.floor(mx) == xs) & (torch.floor(my) == ys)
        if weighting == "centre":
            out = torch.where(at_centre, w, zero)
        else:
            det = a * c - b * b
            area = torch.where(det > 0, torch.full_like(det, 2.0 * torch.pi) / torch.sqrt(torch.where(det > 0, det, torch.ones_like(det))), zero)
            area = torch.clamp(area, max=float(h * wd))  # capped at the view's pixels, as the kernel's
            out = torch.where(at_centre, w * (1.0 + anchor_gain * area), w)
    return torch.where(valid, out, zero).to(torch.float32)


def _sharp_exponent(dx: torch.Tensor, dy: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """-½ dᵀ Δ d of the sharp weighting per slot, in the numba kernel's order of operations
    (Δ = Σ₀⁻¹ - Σ'⁻¹: drsplat.registration.aggregate.sharpening; 0 where the conic or Σ₀ is not
    positive definite)."""
    one = torch.ones_like(a)
    det = a * c - b * b
    safe = torch.where(det > 0, det, one)
    shift = BLUR - SHARP_BLUR
    sxx, sxy, syy = c / safe - shift, -b / safe, a / safe - shift
    det0 = sxx * syy - sxy * sxy
    ok = (det > 0) & (det0 > 0) & (sxx > 0)
    safe0 = torch.where(ok, det0, one)
    q = -0.5 * ((syy / safe0 - a) * dx * dx + (sxx / safe0 - c) * dy * dy) - (-sxy / safe0 - b) * dx * dy
    return torch.where(ok, q, torch.zeros_like(q))


def sharp_exp_torch(q: torch.Tensor) -> torch.Tensor:
    """exp(q) for SHARP_LOG_FLOOR ≤ q ≤ 0 in the operations of the numba kernel's
    `aggregate.sharp_exp` (Horner over SHARP_EXP_TERMS in q / 2^SHARP_EXP_SQUARINGS, then as many
    squarings): the same bits."""
    t = q * (1.0 / (1 << SHARP_EXP_SQUARINGS))
    p = torch.zeros_like(q)
    for c in SHARP_EXP_TERMS:
        p = p * t + c
    for _ in range(SHARP_EXP_SQUARINGS):
        p = p * p
    return p


def explain_weights_torch(ids: torch.Tensor, weights: torch.Tensor, mask_ids: torch.Tensor, num_gaussians: int,
                          iterations: int = EXPLAIN_ITERATIONS) -> torch.Tensor:
    """The "explain" weighting of one view on the device (`aggregate.explain_weights`; its EM and math there).

    ids, weights: [H, W, k] (-1 = empty slot; ids < num_gaussians); mask_ids: [H, W] (-1 = no mask).
    Returns [H, W, k] float32, 0 where ids < 0 or the pixel has no mask. Fixed-size ops only (the
    pairs live in arrays of H·W·k + 1 rows, the last a spare for empty slots), `iterations` rounds
    of ~12 ops, no host synchronisation. Empty slots and unused pairs add their zeros to spread
    rows (`spread_rows`; unmeasured on a GPU here). Every sum is taken in the kernel's order, so the
    same bits on a CPU:
    - a slot's pair (i, j) is its segment in a stable sort by the key j·N + i; the per-pair sums
      v_ij and c_ij run over the slots in pixel-then-slot order (index_add in slot order);
    - a pixel's denominator adds its slots one by one (`slot_sums`);
    - the per-Gaussian sums T_i and Σ_j c_ij add the Gaussian's pairs newest first, as the kernel's
      linked lists do: the pairs ordered by their first slot, descending, before the index_add.
    """
    dev = ids.device
    shape, k = ids.shape, int(ids.shape[-1])
    g = ids.reshape(-1).to(torch.int64)
    slots = g.shape[0]
    n = max(int(num_gaussians), 1)
    m = mask_ids.reshape(-1, 1).to(device=dev, dtype=torch.int64).expand(-1, k).reshape(-1)
    valid = (g >= 0) & (m >= 0)
    zero = torch.zeros((), dtype=torch.float64, device=dev)
    keys = torch.where(valid, m * n + g, torch.full_like(g, torch.iinfo(torch.int64).max))
    sorted_keys, order = torch.sort(keys, stable=True)
    starts = torch.ones_like(sorted_keys, dtype=torch.bool)
    starts[1:] = sorted_keys[1:] != sorted_keys[:-1]
    pair = torch.empty_like(g).scatter_(0, order, torch.cumsum(starts, 0) - 1)
    del keys, sorted_keys, order, starts  # [S] int64 each: ~100 MB apiece on a 640x480 view at k = 40
    index = torch.arange(slots, device=dev)
    adds_to = spread_rows(valid, pair, slots)  # [S] where the slot's values add
    pair = torch.where(valid, pair, slots)  # [S] the slot's pair; empty slots: the spare row
    pair_g = torch.full((slots + 1,), n, dtype=torch.int64, device=dev).scatter_(0, pair, torch.where(valid, g, n))
    first = torch.full((slots + 1,), slots, dtype=torch.int64, device=dev).scatter_reduce_(
        0, adds_to, torch.where(valid, index, slots), "amin")  # an empty slot offers `slots`, which lowers no row
    newest_first = torch.sort(first, descending=True, stable=True).indices
    del first, g, m
    by_gaussian = pair_g[newest_first]
    by_gaussian = spread_rows(by_gaussian < n, by_gaussian, n + 1)  # unused pairs add 0

    def per_gaussian(values: torch.Tensor) -> torch.Tensor:  # Σ over the pair's Gaussian's pairs, newest first, per pair
        return torch.zeros(n + 1, dtype=torch.float64, device=dev).index_add_(0, by_gaussian, values[newest_first])[pair_g]

    w = torch.where(valid, weights.reshape(-1).to(torch.float64), zero)
    v = torch.zeros(slots + 1, dtype=torch.float64, device=dev).index_add_(0, adds_to, w)
    total = per_gaussian(v)
    q = torch.where(total > 0.0, v / torch.where(total > 0.0, total, 1.0), zero)
    for _ in range(int(iterations)):
        share = torch.where(valid, w * q[pair], zero).reshape(-1, k)
        denom = slot_sums(share)
        r = torch.where(denom > 0.0, share / torch.where(denom > 0.0, denom, 1.0), zero).reshape(-1)
        c = torch.zeros(slots + 1, dtype=torch.float64, device=dev).index_add_(0, adds_to, torch.where(valid, r, zero))
        rs = per_gaussian(c)
        q = torch.where(rs > 0.0, c / torch.where(rs > 0.0, rs, 1.0), q)
    scale = torch.where(v > 0.0, total * q / torch.where(v > 0.0, v, 1.0), zero)
    return torch.where(valid, w * scale[pair], zero).to(torch.float32).reshape(shape)


@torch.library.custom_op("drsplat::view_weights", mutates_args=(), device_types="cpu")
def view_weights_op(weighting: str, ids: torch.Tensor, weights: torch.Tensor, means: torch.Tensor, covariances: torch.Tensor,
                    opacities: torch.Tensor, usable: torch.Tensor, camera: list[float], near: float, anchor_gain: float) -> torch.Tensor:
    """A per-pixel weighting's [H, W, k] float32 weights as one op (`view_weights_torch`), the view
    projected first for the weightings that read screen means and conics (PROJECTED_WEIGHTINGS;
    means [N, 3], covariances [N, 3, 3], opacities [N], usable [N]: the TorchScene; camera:
    `raster_ops.camera_values`). Kernels: cpu, numba's projection and `aggregate.view_weights` (the
    host hook's kernels: the same bits); cuda, `project_gaussians_torch` and `view_weights_torch`."""
    h, w, _ = ids.shape
    screen = np.zeros((0, 2)), np.zeros((0, 3))
    if weighting in PROJECTED_WEIGHTINGS:
        projected = project_gaussians(raster_ops.host_scene(means, covariances, opacities, usable), raster_ops.camera_from_values(camera, w, h), near)
        screen = projected.means2d, projected.conics
    return host_tensor(view_weights(weighting, host_array(ids), host_array(weights), *screen, anchor_gain=anchor_gain))


@view_weights_op.register_kernel("cuda")
def _view_weights_cuda(weighting, ids, weights, means, covariances, opacities, usable, camera, near, anchor_gain):
    h, w, _ = ids.shape
    screen = ()
    if weighting in PROJECTED_WEIGHTINGS:
        projected = project_gaussians_torch(TorchScene.geometry(means, covariances, opacities, usable), raster_ops.camera_from_values(camera, w, h), near,
                                            device=means.device)
        screen = projected.means2d, projected.conics
    return view_weights_torch(weighting, ids, weights, *screen, anchor_gain=anchor_gain)


@view_weights_op.register_fake
def _view_weights_fake(weighting, ids, weights, means, covariances, opacities, usable, camera, near, anchor_gain):
    return weights.new_empty(ids.shape, dtype=torch.float32)


@torch.library.custom_op("drsplat::explain_weights", mutates_args=(), device_types="cpu")
def explain_weights_op(ids: torch.Tensor, weights: torch.Tensor, mask_ids: torch.Tensor, num_gaussians: int, iterations: int) -> torch.Tensor:
    """`explain_weights_torch` as one op ([H, W, k] float32). Kernels: cpu, the host hook's numba EM
    (`aggregate.explain_weights`: the same bits); cuda, `explain_weights_torch`."""
    return host_tensor(explain_weights(host_array(ids), host_array(weights), host_array(mask_ids), num_gaussians, iterations))


@explain_weights_op.register_kernel("cuda")
def _explain_weights_cuda(ids, weights, mask_ids, num_gaussians, iterations):
    return explain_weights_torch(ids, weights, mask_ids, num_gaussians, iterations)


@explain_weights_op.register_fake
def _explain_weights_fake(ids, weights, mask_ids, num_gaussians, iterations):
    return weights.new_empty(ids.shape, dtype=torch.float32)


@dataclass
class DeviceRays:
    """drsplat.registration.aggregate.RayGeometry on a device: means [N, 3], precisions [N, 6]
    (xx, xy, xz, yy, yz, zz) and reach [N], float64."""

    means: torch.Tensor
    precisions: torch.Tensor
    reach: torch.Tensor

    @classmethod
    def from_host(cls, rays: RayGeometry, device: torch.device) -> DeviceRays:
        return cls(*(to_device(np.array(a, np.float64), device) for a in (rays.means, rays.precisions, rays.reach)))


def ray_depths_torch(rays: DeviceRays, g: torch.Tensor, dx, dy, dz, origin: np.ndarray, rot: np.ndarray, tz: float) -> torch.Tensor:
    """t* of Gaussians g [P, S] (ids ≥ 0) on the pixels' rays o + t·d, d = (dx, dy, dz) [P, 1]:
    `aggregate._ray_depth` (math in `ray_depths_reference`) in float64 tensors, each sum in the
    kernel's order, so the same bits on a CPU."""
    p = rays.precisions[g]  # [P, S, 6]
    pdx = p[..., 0] * dx + p[..., 1] * dy + p[..., 2] * dz
    pdy = p[..., 1] * dx + p[..., 3] * dy + p[..., 4] * dz
    pdz = p[..., 2] * dx + p[..., 4] * dy + p[..., 5] * dz
    m = rays.means[g]
    mx, my, mz = m[..., 0], m[..., 1], m[..., 2]
    zc = float(rot[2, 0]) * mx + float(rot[2, 1]) * my + float(rot[2, 2]) * mz + tz
    den = pdx * dx + pdy * dy + pdz * dz
    t = (pdx * (mx - float(origin[0])) + pdy * (my - float(origin[1])) + pdz * (mz - float(origin[2]))) / den
    reach = rays.reach[g]
    return torch.where(den > 0.0, torch.minimum(torch.maximum(t, zc - reach), zc + reach), zc)


def front_flags_torch(rays: DeviceRays, camera: Camera, ids: torch.Tensor, median_ids: torch.Tensor,
                      tolerance: float = FRONT_TOLERANCE) -> torch.Tensor:
    """[H·W, k] bool: slot (p, s) is in front of the pixel's surface, t*_{ids[p, s]}(p) < (1 - τ)·D(p) and
    t* < D(p) - κ·s (`aggregate.in_front_reference`), D(p) the median Gaussian's t* (+inf where
    median_ids[p] < 0); False for empty slots.
    `aggregate.surface_stats`' in-front test in torch. ids: [H, W, k], median_ids: [H, W]."""
    h, w, k = ids.shape
    dev = ids.device
    rot, trans = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64)
    origin, tz = camera.ray_origin(), float(trans[2])
    pix = torch.arange(h * w, device=dev)
    rx = ((pix % w).to(torch.float64) + 0.5 - float(camera.cx)) / float(camera.fx)
    ry = ((pix // w).to(torch.float64) + 0.5 - float(camera.cy)) / float(camera.fy)
    dx = (float(rot[0, 0]) * rx + float(rot[1, 0]) * ry + float(rot[2, 0]))[:, None]  # d = Rᵀ (rx, ry, 1)
    dy = (float(rot[0, 1]) * rx + float(rot[1, 1]) * ry + float(rot[2, 1]))[:, None]
    dz = (float(rot[0, 2]) * rx + float(rot[1, 2]) * ry + float(rot[2, 2]))[:, None]
    g = ids.reshape(-1, k).to(torch.int64)
    med = median_ids.reshape(-1, 1).to(torch.int64)
    surface = ray_depths_torch(rays, med.clamp(min=0), dx, dy, dz, origin, rot, tz)
    surface = torch.where(med >= 0, surface, torch.inf)
    limit = (1.0 - tolerance) * surface
    depth = ray_depths_torch(rays, g.clamp(min=0), dx, dy, dz, origin, rot, tz)
    beyond = surface - FRONT_REACH_SHARE * rays.reach[g.clamp(min=0)]
    return (g >= 0) & (depth < limit) & (depth < beyond)


def front_flags(rays: DeviceRays, camera: Camera, ids: torch.Tensor, median_ids: torch.Tensor, tolerance: float = FRONT_TOLERANCE) -> torch.Tensor:
    """`front_flags_torch`'s flags: on CUDA with Triton one fused launch (drsplat.registration.front_triton: the
    same bits without the ~50 [H·W, k] gathers and products: the view's gathers 9.5 -> 1.7 ms on an H100), else the torch ops."""
    if ids.device.type == "cuda" and triton_available():
        from drsplat.registration.front_triton import front_flags_triton  # imports triton

        return front_flags_triton(rays.means, rays.precisions, rays.reach, camera, ids, median_ids, tolerance)
    return front_flags_torch(rays, camera, ids, median_ids, tolerance)


@dataclass
class DeviceViewStats:
    """One view's floater statistics on the device, [N] each: peak (max w), total (Σ w), front
    (Σ w in front of the surface) float64, touched bool (the view sees the Gaussian). The dense
    form of aggregate.ViewStats: fixed sizes, so nothing waits for the device."""

    peak: torch.Tensor
    total: torch.Tensor
    front: torch.Tensor
    touched: torch.Tensor

    def support_for(self, support: SurfaceSupport | DeviceSupport) -> DeviceSupport:
        """The running support to fold this view into: `support`, moved to this view's device once."""
        return support if isinstance(support, DeviceSupport) else DeviceSupport.from_host(support, self.peak.device)


def scatter_max(rows: torch.Tensor, values: torch.Tensor, num_rows: int, lanes: torch.Tensor | None = None, replicas: int = 1) -> torch.Tensor:
    """[num_rows] float64: max over the entries of each row, 0 where a row has none (values ≥ 0).

    rows: [P] int64 in [0, num_rows); values: [P] float64; lanes: [P] int64 ≥ 0 (an entry's pixel).
    With `replicas` R > 1 the entries go to R copies of the table, entry e to copy lanes_e mod R,
    and the copies' maxima are taken at the end:

        peak_r = max { values_e : rows_e = r },  = max_c max { values_e : rows_e = r, lanes_e ≡ c (mod R) }

    A max is exact in any grouping, so every R gives the same bits. Why: CUDA serialises the
    atomics that meet on one address, and a large Gaussian's pixels (thousands in a view) all meet on
    its row; spread by pixel, neighbouring pixels' entries go to different copies."""
    if replicas <= 1 or lanes is None:
        return torch.zeros(num_rows, dtype=torch.float64, device=rows.device).scatter_reduce_(0, rows, values, "amax")
    spread = rows * replicas + lanes.remainder(replicas)
    table = torch.zeros(num_rows * replicas, dtype=torch.float64, device=rows.device).scatter_reduce_(0, spread, values, "amax")
    return table.view(num_rows, replicas).amax(1)


# Copies of the per-Gaussian max table on CUDA (`scatter_max`), while they fit PEAK_TABLE_BYTES; 1 on a CPU, where
# nothing contends. Measured on an H200 (2026-11-29, flowers, 640x480, k = 40): a view's max 3.47 -> 1.19 ms where
# large Gaussians cover many pixels, 0.86 -> 0.95 ms where none does; 64 was the fastest of 1, 2, 4, ..., 128.
PEAK_REPLICAS = 64
PEAK_TABLE_BYTES = 512 * 2**20  # the copies' float64 table at most this: fewer copies for larger scenes (8 at 5 M Gaussians, one past 33.5 M)


def peak_replicas(num_rows: int, device: torch.device) -> int:
    """The copies of a max table of `num_rows` rows on `device`: PEAK_REPLICAS on CUDA, halved until the
    table fits PEAK_TABLE_BYTES (at least 1); 1 elsewhere."""
    if device.type != "cuda":
        return 1
    replicas = PEAK_REPLICAS
    while replicas > 1 and 8 * replicas * max(int(num_rows), 1) > PEAK_TABLE_BYTES:
        replicas //= 2
    return replicas


def view_stats_torch(ids: torch.Tensor, weights: torch.Tensor, flags: torch.Tensor, num_gaussians: int,
                     replicas: int | None = None) -> DeviceViewStats:
    """A view's per-Gaussian max w, Σ w and Σ w·flags over its slots (`aggregate.surface_stats`).

    ids, weights: [H, W, k] (-1 empty; raw w = T·α); flags: [H·W, k] (`front_flags`). An
    empty slot adds w = 0 to a spread row (`spread_rows`; its maximum too, which changes no row:
    they hold maxima of weights ≥ 0) and marks the spare row N touched. The sums add each w in the
    host's fixed point (`aggregate.fixed_weights`: int64, exact in any order), so index_add gives
    the host kernel's bits on a CPU and with CUDA's atomics alike; the max is taken over `replicas`
    copies of its table, spread by pixel (`scatter_max`; default `peak_replicas`): the same bits
    for every count."""
    n = num_gaussians
    if replicas is None:
        replicas = peak_replicas(n + 1, ids.device)
    g = ids.reshape(-1).to(torch.int64)
    valid = g >= 0
    row = spread_rows(valid, g, n + 1)
    zero = torch.zeros((), dtype=torch.float64, device=g.device)
    w = torch.where(valid, weights.reshape(-1).to(torch.float64), zero)
    fixed = torch.floor(torch.nan_to_num(w.clamp(0.0, 1.0), nan=0.0) * STATS_SCALE + 0.5).to(torch.int64)
    i64 = {"dtype": torch.int64, "device": g.device}
    pixel = torch.arange(ids.shape[0] * ids.shape[1], device=g.device).repeat_interleave(ids.shape[2]) if replicas > 1 else None
    peak = scatter_max(row, w, n + 1, pixel, replicas)
    total = torch.zeros(n + 1, **i64).index_add_(0, row, fixed)
    front = torch.zeros(n + 1, **i64).index_add_(0, row, torch.where(flags.reshape(-1), fixed, torch.zeros_like(fixed)))
    touched = torch.zeros(n + 1, dtype=torch.bool, device=g.device).index_fill_(0, torch.where(valid, g, n), True)
    return DeviceViewStats(peak[:n], total[:n].to(torch.float64) / STATS_SCALE, front[:n].to(torch.float64) / STATS_SCALE, touched[:n])


@torch.library.custom_op("drsplat::view_stats", mutates_args=(), device_types="cpu")
def view_stats_op(ids: torch.Tensor, weights: torch.Tensor, median_ids: torch.Tensor, means: torch.Tensor, precisions: torch.Tensor,
                  reach: torch.Tensor, camera: list[float], tolerance: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A `-reject` mode's per-view floater statistics as one op: (peak, total, front [N] float64,
    touched [N] bool) of `view_stats_torch` over `front_flags`' in-front test.

    ids, weights: [H, W, k]; median_ids: [H, W]; means [N, 3], precisions [N, 6], reach [N]: the
    scene's DeviceRays; camera: `raster_ops.camera_values`. Kernels: cpu, the numba kernels of the
    host hook (`aggregate.surface_stats`: the same bits), its compact statistics laid out dense;
    cuda, `front_flags` (one Triton launch) and `view_stats_torch`.
    """
    h, w, _ = ids.shape
    cam = raster_ops.camera_from_values(camera, w, h)
    rays = RayGeometry(*(np.ascontiguousarray(host_array(t)) for t in (means, precisions, reach)))
    stats, _ = surface_stats(rays, cam, host_array(ids), host_array(weights), host_array(median_ids), tolerance)
    n = reach.shape[0]
    dense = [np.zeros(n) for _ in range(3)]
    for out, values in zip(dense, (stats.peak, stats.total, stats.front)):
        out[stats.ids] = values
    touched = np.zeros(n, bool)
    touched[stats.ids] = True
    return tuple(host_tensor(a) for a in (*dense, touched))


@view_stats_op.register_kernel("cuda")
def _view_stats_cuda(ids, weights, median_ids, means, precisions, reach, camera, tolerance):
    h, w, _ = ids.shape
    cam = raster_ops.camera_from_values(camera, w, h)
    flags = front_flags(DeviceRays(means, precisions, reach), cam, ids, median_ids, tolerance)
    stats = view_stats_torch(ids, weights, flags, int(reach.shape[0]))
    return stats.peak, stats.total, stats.front, stats.touched


@view_stats_op.register_fake
def _view_stats_fake(ids, weights, median_ids, means, precisions, reach, camera, tolerance):
    n = reach.shape[0]
    return (*(reach.new_empty(n, dtype=torch.float64) for _ in range(3)), reach.new_empty(n, dtype=torch.bool))


def view_stats(rays: DeviceRays, camera: Camera, ids: torch.Tensor, weights: torch.Tensor, median_ids: torch.Tensor,
               tolerance: float = FRONT_TOLERANCE) -> DeviceViewStats:
    """The view's DeviceViewStats through `view_stats_op` (one dispatcher call)."""
    return DeviceViewStats(*view_stats_op(ids, weights, median_ids, rays.means, rays.precisions, rays.reach, raster_ops.camera_values(camera),
                                          float(tolerance)))


class DeviceSupport:
    """aggregate.SurfaceSupport kept on a device: the views' statistics folded in view order,

        P_i = max(P_i, p_i),  A_i += a_i,  B_i += b_i,  views_seen_i += 1,  views_front_i += [b_i > FRONT_MAX·a_i]

    for the Gaussians each view touches (an untouched one adds p = a = b = 0, which changes no bit:
    P ≥ 0, x + 0.0 = x), so the same bits as the host fold. `arrays()` copies it to the host (a
    checkpoint snapshot), `rejected()` too."""

    def __init__(self, peak: torch.Tensor, total: torch.Tensor, front: torch.Tensor, views_seen: torch.Tensor, views_front: torch.Tensor):
        self.peak, self.total, self.front, self.views_seen, self.views_front = peak, total, front, views_seen, views_front

    @classmethod
    def from_host(cls, support: SurfaceSupport, device: torch.device) -> DeviceSupport:
        return cls(*(to_device(np.array(a), device) for a in support.arrays().values()))

    def add(self, view: DeviceViewStats) -> None:
        if not isinstance(view, DeviceViewStats):
            raise TypeError("the device's floater statistics fold only views computed on the device")
        self.peak = torch.maximum(self.peak, view.peak)  # NaN propagates, as the host fold's max
        self.total += view.total
        self.front += view.front
        self.views_seen += view.touched.to(torch.int32)
        self.views_front += (view.touched & (view.front > FRONT_MAX * view.total)).to(torch.int32)

    def host(self) -> SurfaceSupport:
        return SurfaceSupport(*(t.cpu().numpy().copy() for t in (self.peak, self.total, self.front, self.views_seen, self.views_front)))

    def arrays(self) -> dict[str, np.ndarray]:
        return self.host().arrays()

    def rejected(self) -> np.ndarray:
        return self.host().rejected()


def render_pairs(scene: TorchScene, camera: Camera, topk: int, mask_ids: np.ndarray, num_masks: int, weighting: str = "paper",
                 rays: DeviceRays | None = None, tile_capacity: int | None = None, near: float = NEAR) -> tuple[DevicePairs, DeviceRead, float, DeviceViewStats | None]:
    """Render `camera` on the scene's device, weight its slots (`view_weights_torch`) and coalesce its
    pairs there (`coalesce_pairs`).

    mask_ids: [H, W] the view's masks (-1 none; copied to the device). weighting: the aggregation
    mode's per-view weighting (core, ellipse, centre, anchor project the scene once more; explain
    runs its EM on the view's slots and masks, `explain_weights_torch`). rays:
    the scene's ray geometry on the device for a `-reject` mode (the view is rendered with its
    median Gaussians and its floater statistics computed there), else None. tile_capacity: the
    tile lists' size (`TileCapacity`; None: exact, the one read of the device inside a view). near:
    the near plane (`ViewJob.near`). Returns (the view's DevicePairs padded to H·W·k, the DeviceRead of (distinct pairs P,
    contributing slots, tile-list entries needed, the M present-mask flags), seconds until the render's ops were issued, its
    DeviceViewStats or None): nothing is read here. The pairs are right when the entries needed fit
    tile_capacity. On CUDA the render runs on after it was issued, so the seconds then split the
    view where the host waited, not where the device worked.
    """
    t0 = time.perf_counter()
    out = rasterize_torch(scene, camera, topk, with_median=rays is not None, device=scene.device, tile_capacity=tile_capacity, ranked=False,
                          near=near)
    raster_seconds = time.perf_counter() - t0
    stats = None
    if rays is not None:
        stats = view_stats(rays, camera, out.ids, out.weights, out.median_ids)
    weights = out.weights
    masks = to_device(np.array(mask_ids, np.int32), scene.device)
    if weighting == "explain":
        weights = explain_weights_op(out.ids, out.weights, masks, scene.num_gaussians, EXPLAIN_ITERATIONS)
    elif weighting != "paper":
        weights = view_weights_op(weighting, out.ids, out.weights, scene.means, scene.covariances, scene.opacities, scene.finite,
                                  raster_ops.camera_values(camera), near, ANCHOR_GAIN)
    pairs = coalesce_pairs(out.ids, weights, masks, num_masks, scene.num_gaussians)
    read = DeviceRead(torch.cat([pairs.counts, out.tile_entries.reshape(1).to(pairs.counts.device), pairs.mask_flags]))
    return pairs, read, raster_seconds, stats


def sums_fit_device(num_gaussians: int, dim: int, device: str, extra_per_gaussian: int = 0) -> bool:
    """Whether F [N, D] and W [N] (float32), plus `extra_per_gaussian` bytes per Gaussian (a vote's
    slots), fit the free memory of a CUDA `device`; always True for the CPU, whose memory the
    registration's plan budgets (drsplat.registration.plan). Free counts the blocks torch's caching
    allocator holds unused (reserved less allocated), which it releases when an allocation needs
    them: the fit stage's probe views, rendered on the device before the sums are made, leave such
    blocks (a flowers view at 640x480 peaks at 2.5 GB on the device), which `mem_get_info` counts as taken."""
    dev = torch.device(device)
    if dev.type != "cuda":
        return True
    free, _ = torch.cuda.mem_get_info(dev)
    free += torch.cuda.memory_reserved(dev) - torch.cuda.memory_allocated(dev)
    return DEVICE_HEADROOM * num_gaussians * (4 * (dim + 1) + extra_per_gaussian) + 8 * PAIR_CHUNK * dim <= free


@torch.library.custom_op("drsplat::add_pairs", mutates_args=("F", "W"), device_types="cpu")
def add_pairs_op(F: torch.Tensor, W: torch.Tensor, gaussians: torch.Tensor, masks: torch.Tensor, weights: torch.Tensor, feats: torch.Tensor,
                 chunk: int) -> None:
    """F[g] += w·feats[m], W[g] += w for one view's pairs (g, m, w), in place; a Gaussian's pairs in
    pair order, the product rounded to float32 before the add. F [N, D], W [N] float32; gaussians,
    masks [P] int64; weights [P] float32; feats [M, D] float32. Kernels: cpu, the host
    accumulator's numba kernel (`sums.add_pairs_in_place`: the same bits, in parallel over
    Gaussians); cuda, one Triton launch after a sort by Gaussian (drsplat.registration.sums_triton:
    each F row read and written once, the pairs added in order, so numba's bits and the same in
    every run), or without Triton `add_pairs_torch` (index_add of F in chunks of `chunk` pairs)."""
    add_pairs_in_place(host_array(F), host_array(W), *(host_array(t) for t in (gaussians, masks, weights, feats)))


def add_pairs_torch(F: torch.Tensor, W: torch.Tensor, gaussians: torch.Tensor, masks: torch.Tensor, weights: torch.Tensor, feats: torch.Tensor,
                    chunk: int = PAIR_CHUNK) -> None:
    """`add_pairs_op` in torch ops, its CUDA kernel (index_add adds a row's pairs in pair order on a
    CPU; with atomics in no fixed order on CUDA)."""
    W.index_add_(0, gaussians, weights)
    for start in range(0, int(gaussians.shape[0]), chunk):
        part = slice(start, start + chunk)
        F.index_add_(0, gaussians[part], weights[part, None] * feats[masks[part]])


@add_pairs_op.register_kernel("cuda")
def _add_pairs_cuda(F, W, gaussians, masks, weights, feats, chunk):
    if triton_available():
        from drsplat.registration.sums_triton import add_pairs_triton  # imports triton

        add_pairs_triton(F, W, gaussians, masks, weights, feats)
    else:
        add_pairs_torch(F, W, gaussians, masks, weights, feats, chunk)


class DeviceSink:
    """The one block of all N Gaussians, summed on `device` as the views arrive (drsplat.registration.sink).

    F [N, D] = Σ w_ij f_j and W [N] = Σ w_ij (float32) stay on the device; each view's pairs are
    added with index_add in the order given (views in view order, a view's pairs sorted by (mask,
    Gaussian)), its embeddings copied to the device once. Views replayed from a pair log (host
    arrays) are added the same way. `blocks` copies the sums to the host once.

    On a CPU index_add adds a row's pairs one after another, so the sums are the host
    accumulator's bits; on CUDA it adds with atomics in no fixed order, so sums agree to float32
    rounding and may differ between runs in the last bits.
    """

    num_blocks = 1

    def __init__(self, num_gaussians: int, dim: int, device: str, chunk: int = PAIR_CHUNK):
        self.device = torch.device(device)
        self.place = str(self.device)
        self.F = torch.zeros((num_gaussians, dim), dtype=torch.float32, device=self.device)
        self.W = torch.zeros(num_gaussians, dtype=torch.float32, device=self.device)
        self.chunk = int(chunk)

    def add(self, view: ViewPairs) -> None:
        pairs = view.device
        if pairs is None:  # a view replayed from the log (read-only arrays: copied)
            g = to_device(view.gaussians.astype(np.int64), self.device)
            m = to_device(view.masks.astype(np.int64), self.device)
            w = to_device(np.array(view.weights, np.float32), self.device)
        else:
            g, m, w = pairs.gaussians, pairs.masks, pairs.weights
        total = int(g.shape[0])
        if total == 0:
            return
        feats = to_device(np.array(view.feats, np.float32), self.device)  # [M, D], once per view
        add_pairs_op(self.F, self.W, g, m, w, feats, self.chunk)

    def positive(self) -> np.ndarray:
        """[N] bool: Gaussians some pair gave weight > 0 (W_i > 0: a float32 sum of non-negative
        weights is positive exactly when one of them is)."""
        return (self.W > 0).cpu().numpy()

    def blocks(self, reuse: bool = False) -> Iterator[Block]:
        F, W = to_host(self.F), self.W.cpu().numpy()
        yield Block(0, F.shape[0], F, W)

    def sample(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F [S, D], W [S]) of the Gaussians `ids` [S] (host copies)."""
        index = to_device(np.array(ids, np.int64), self.device)
        return self.F[index].cpu().numpy().copy(), self.W[index].cpu().numpy().copy()


@dataclass
class VoteRounds:
    """One view's pairs laid out for the vote's rounds (`vote_rounds_torch`), on the device.

    g / c: [P] int64 Gaussians and clusters, w / v: [P] float64 weights and votes, in the pairs'
    order sorted by Gaussian (stable); by_round: [P] positions of the pairs by (round, order);
    read: (rounds, then the end of each of up to M rounds in by_round), read by `fold_vote_rounds`."""

    g: torch.Tensor
    c: torch.Tensor
    w: torch.Tensor
    v: torch.Tensor
    by_round: torch.Tensor
    read: DeviceRead


def vote_rounds_torch(rows: torch.Tensor, clusters: torch.Tensor, weights: torch.Tensor, presence: float, full_view: float,
                      num_masks: int, num_gaussians: int) -> VoteRounds:
    """The first half of `vote_view_torch`: the votes and the rounds of one view's P > 0 pairs, without
    reading the device (its sizes travel in a DeviceRead). A Gaussian has at most one pair per mask,
    so at most `num_masks` rounds."""
    dev, n, p = rows.device, max(int(num_gaussians), 1), int(rows.shape[0])
    w = weights.to(torch.float64)
    total = torch.zeros(n, dtype=torch.float64, device=dev).index_add_(0, rows, w)[rows]
    order = torch.sort(rows, stable=True).indices
    g, c, w, total = rows[order], clusters[order], w[order], total[order]
    one = torch.ones((), dtype=torch.float64, device=dev)
    v = torch.minimum(one, w / (total * presence)) * torch.minimum(one, total / full_view) if presence > 0.0 else w
    acting = ((c >= 0) & (w > 0.0)).to(torch.int64)
    before = torch.cumsum(acting, 0) - acting  # acting pairs before each pair, over all Gaussians
    steps = torch.arange(p, device=dev)
    first = torch.ones(p, dtype=torch.bool, device=dev)
    first[1:] = g[1:] != g[:-1]
    group_start = torch.cummax(torch.where(first, steps, 0), 0).values
    rank = torch.where(acting > 0, before - before[group_start], p)  # p: not acting, after every round
    rank, by_round = torch.sort(rank, stable=True)
    rounds = torch.where(rank < p, rank, -1).max().reshape(1) + 1
    ends = torch.searchsorted(rank, torch.arange(1, max(int(num_masks), 1) + 1, device=dev))
    return VoteRounds(g, c, w, v, by_round, DeviceRead(torch.cat([rounds, ends])))


def fold_vote_rounds(rounds: VoteRounds, slot_c: torch.Tensor, slot_v: torch.Tensor, slot_s: torch.Tensor) -> None:
    """The second half of `vote_view_torch`: fold the view's rounds into the slots, in place (reads
    its DeviceRead: a view late in DeviceVoteSink, when the device is done with it)."""
    count, *ends = rounds.read.values()
    g, c, w, v = rounds.g, rounds.c, rounds.w, rounds.v
    begin = 0
    for end in ends[:count]:
        pick = rounds.by_round[begin:end]
        begin = end
        row, cl = g[pick], c[pick].to(torch.int32)
        sc = slot_c[row]
        match = (sc == cl[:, None]) | (sc < 0)
        slot = torch.where(match.any(1), torch.argmax(match.to(torch.int8), 1), torch.argmin(slot_v[row], 1))
        slot_c[row, slot] = cl
        slot_v[row, slot] = slot_v[row, slot] + v[pick]
        slot_s[row, slot] = slot_s[row, slot] + w[pick]


def vote_view_torch(rows: torch.Tensor, clusters: torch.Tensor, weights: torch.Tensor, presence: float, full_view: float,
                    slot_c: torch.Tensor, slot_v: torch.Tensor, slot_s: torch.Tensor, num_masks: int | None = None) -> None:
    """`vote._vote_view_kernel` on the device: fold one view's pairs into the vote slots, in place.

    rows: [P] int64 Gaussians, clusters: [P] int64 (-1 none), weights: [P] float32, in the view's
    pair order; slot_c [N, S] int32 (-1 empty), slot_v / slot_s [N, S] float64. A Gaussian's pairs
    act one after another (the space-saving rule depends on its slots as earlier pairs left them),
    so the acting pairs (a cluster and w > 0) are numbered within their Gaussian, in pair order, and
    round r folds every Gaussian's r-th acting pair at once: a contiguous run of the pairs sorted by
    that number, one pair per Gaussian, so no two writes of a round meet:

        T_iv = Σ_{j ∈ view} w_ij (float64, in pair order), v = min(1, w / (T·ρ)) · min(1, T / T₀)
        slot = the cluster's slot, else the first empty one, else the one of fewest votes (first of
        equal), which the cluster takes over with its counts; V += v, S += w

    num_masks: the view's masks (bounds the rounds; None: P). `vote_rounds_torch` then
    `fold_vote_rounds`, which reads the rounds' ends (DeviceVoteSink reads them a view late). Equal
    to the kernel bit for bit on the CPU (one addition per slot and round, in its order), and on
    CUDA too as long as T_iv is: its index_add adds in no fixed order there, but a float64 sum of
    float32 weights is exact in any order unless they span more than 2^29.
    """
    if rows.shape[0] == 0:
        return
    limit = int(rows.shape[0]) if num_masks is None else num_masks
    fold_vote_rounds(vote_rounds_torch(rows, clusters, weights, presence, full_view, limit, slot_c.shape[0]), slot_c, slot_v, slot_s)


@torch.library.custom_op("drsplat::vote_fold", mutates_args=("slot_c", "slot_v", "slot_s"), device_types="cpu")
def vote_fold_op(rows: torch.Tensor, clusters: torch.Tensor, weights: torch.Tensor, presence: float, full_view: float, num_masks: int,
                 slot_c: torch.Tensor, slot_v: torch.Tensor, slot_s: torch.Tensor) -> None:
    """`vote_view_torch` as one op: fold one view's pairs into the vote slots, in place (arguments
    as there). Kernels: cpu, the numba kernel of the host VoteSink (`vote.fold_view_votes`: the
    same bits); cuda, one Triton launch after a sort (drsplat.registration.vote_triton: a program
    per Gaussian, nothing read), or without Triton `vote_view_torch` (which reads the view's number
    of rounds: DeviceVoteSink then lays the rounds out and folds them a view late instead)."""
    fold_view_votes(*(host_array(t) for t in (rows, clusters, weights)), presence, full_view, *(host_array(t) for t in (slot_c, slot_v, slot_s)))


@vote_fold_op.register_kernel("cuda")
def _vote_fold_cuda(rows, clusters, weights, presence, full_view, num_masks, slot_c, slot_v, slot_s):
    if triton_available():
        from drsplat.registration.vote_triton import vote_fold_triton  # imports triton

        vote_fold_triton(rows, clusters, weights, presence, full_view, slot_c, slot_v, slot_s)
    else:
        vote_view_torch(rows, clusters, weights, presence, full_view, slot_c, slot_v, slot_s, num_masks)


class DeviceVoteSink:
    """The `-vote` stage's sink on the device (drsplat.registration.vote.VoteSink's one-block form):
    the paper's sums in a DeviceSink, the vote slots [N, S] on the device, each view folded by the
    vote op (`vote_fold_op`: numba on a CPU, one Triton launch on CUDA), or where that op would
    read the device (CUDA without Triton: `lagged`) as `vote_view_torch` does but a view late: `add`
    lays out a view's rounds (`vote_rounds_torch`) and folds the view before it
    (`fold_vote_rounds`), whose rounds the device finished long ago, so reading their number does
    not wait. The views' mask clusters are made on the host (a view's embeddings, in view order).
    `blocks` folds the last view, copies F, W and the slots to the host once and trims there
    (`vote.trim_sums`, exactly by a replay of the pairs after a check), so the result is the host
    VoteSink's bits on a CPU.
    """

    num_blocks = 1

    def __init__(self, num_gaussians: int, dim: int, device: str, slots: int = VOTE_SLOTS, presence: float = PRESENCE,
                 full_view: float = FULL_VIEW):
        self._sums = DeviceSink(num_gaussians, dim, device)
        self.device, self.place = self._sums.device, self._sums.place
        self.presence, self.full_view = float(presence), float(full_view)
        self.trim = CLUSTER_COSINE  # θ of the trim (VoteSink.trim; a check sets it once it has judged the masks)
        self.specific: Specificity | None = None  # the vote's step 4 (VoteSink.specific; set with trim)
        self.exact: PairSource | None = None  # the pairs replayed for exact trims (VoteSink.exact; set with trim)
        self.clusters = MaskClusters(dim)
        rows = (num_gaussians, int(slots))
        self.slot_c = torch.full(rows, -1, dtype=torch.int32, device=self.device)
        self.slot_v = torch.zeros(rows, dtype=torch.float64, device=self.device)
        self.slot_s = torch.zeros(rows, dtype=torch.float64, device=self.device)
        self._unfolded: VoteRounds | None = None  # the last view's rounds, folded when the next view arrives
        self._trimmed_sums: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None  # (F, W, kept) once trimmed (on a CPU in place: trimmed once)
        # the vote op folds a view without reading the device on a CPU (numba) and on CUDA with Triton;
        # otherwise its rounds are laid out now and folded a view late
        self.lagged = not (self.device.type == "cpu" or triton_available())

    def add(self, view: ViewPairs) -> None:
        pairs = view.device
        if pairs is None:  # a view replayed from the log
            rows = to_device(view.gaussians.astype(np.int64), self.device)
            masks = to_device(view.masks.astype(np.int64), self.device)
            weights = to_device(np.array(view.weights, np.float32), self.device)
        else:
            rows, masks, weights = pairs.gaussians, pairs.masks, pairs.weights
        cluster_of_mask = to_device(self.clusters.add(view.feats, view.present_masks()).astype(np.int64), self.device)
        self._sums.add(view)
        self._fold()
        if rows.shape[0] == 0:
            return
        if not self.lagged:
            vote_fold_op(rows, cluster_of_mask[masks], weights, self.presence, self.full_view, view.feats.shape[0], self.slot_c, self.slot_v,
                         self.slot_s)
        else:
            self._unfolded = vote_rounds_torch(rows, cluster_of_mask[masks], weights, self.presence, self.full_view, view.feats.shape[0],
                                               self.slot_c.shape[0])

    def _fold(self) -> None:
        if self._unfolded is not None:
            fold_vote_rounds(self._unfolded, self.slot_c, self.slot_v, self.slot_s)
            self._unfolded = None

    def positive(self) -> np.ndarray:
        return self._sums.positive()

    def _trimmed(self, index: torch.Tensor | None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        self._fold()
        F, W = self._sums.F, self._sums.W
        c, v, s = self.slot_c, self.slot_v, self.slot_s
        if index is not None:
            F, W, c, v, s = F[index], W[index], c[index], v[index], s[index]
        # a fresh host array except the whole of F on a CPU, which is then trimmed in place (as VoteSink's
        # blocks do): a copy of F there (1.1 GB on flowers) cost 2 s of page faults
        F = to_host(F)
        n = self.slot_c.shape[0]
        row, lo, hi = (None, 0, n) if index is None else sample_rows(index.cpu().numpy(), n)
        # step 4's specificities and the exact trim's sums are replayed on the host, as VoteSink does
        F, removed = trim_sums(F, c.cpu().numpy(), v.cpu().numpy(), s.cpu().numpy(), self.clusters, self.trim, self.specific, self.exact, lo, hi, row)
        W = W.cpu().numpy().copy()
        return F, W, kept_weights(W, removed)

    def blocks(self, reuse: bool = False) -> Iterator[Block]:
        """The trimmed sums as one block (on a CPU F is trimmed in place, so once: a second call gets the same sums)."""
        if self._trimmed_sums is None:
            self._trimmed_sums = self._trimmed(None)
            self.specific = self.exact = None  # their replays are done: the pairs they hold (a check's record) can go
        F, W, kept = self._trimmed_sums
        yield Block(0, F.shape[0], F, W, kept)

    def sample(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F [S, D], W [S]) of the Gaussians `ids` [S], trimmed (host copies)."""
        if self._trimmed_sums is not None:
            F, W, _ = self._trimmed_sums
            return F[ids], W[ids].copy()
        return self._trimmed(to_device(np.array(ids, np.int64), self.device))[:2]
