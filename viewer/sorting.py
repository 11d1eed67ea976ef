"""Back-to-front depth ordering of splats, and the background thread that keeps it current.

The order is by view-space depth z = f · x + t_z, so it depends only on the view direction f
(the translation adds the same t_z to every splat). As in antimatter15's splat viewer, the
background thread re-sorts only when f has turned by more than a small angle since the last
sort, and the sort itself is a radix sort of the float32 depths: two 16-bit counting passes, O(N), no comparison
(antimatter15's is one pass over 16-bit depths quantised over their range, which one far Gaussian collapses).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numba
import numpy as np

RADIX_BITS = 16  # bits of the depth keys sorted per counting pass (two passes: the whole float32 key)


@numba.njit(cache=True, nogil=True)
def _depth_keys(means: np.ndarray, forward: np.ndarray) -> np.ndarray:
    n = means.shape[0]
    keys = np.zeros(n, np.uint32)
    for i in range(n):
        d = np.float32(means[i, 0] * forward[0] + means[i, 1] * forward[1] + means[i, 2] * forward[2])
        if np.isfinite(d):
            b = np.float32(d + np.float32(0.0)).view(np.uint32)  # -0 + 0 is +0: one key for both zeros
            keys[i] = ~b if b >> np.uint32(31) else b | np.uint32(0x80000000)
    return keys


@numba.njit(cache=True, nogil=True)
def _counting_pass_descending(keys: np.ndarray, order: np.ndarray, shift: int) -> np.ndarray:
    """`order` stably re-ordered by the RADIX_BITS-bit digit (keys >> shift), largest first."""
    bins = 1 << RADIX_BITS
    mask = np.uint32(bins - 1)
    counts = np.zeros(bins, np.int64)
    for i in order:
        counts[(keys[i] >> np.uint32(shift)) & mask] += 1
    start = np.empty(bins, np.int64)
    running = 0
    for k in range(bins - 1, -1, -1):
        start[k] = running
        running += counts[k]
    out = np.empty(order.shape[0], np.uint32)
    for i in order:
        k = (keys[i] >> np.uint32(shift)) & mask
        out[start[k]] = i
        start[k] += 1
    return out


def depth_keys_reference(means: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """Keys whose unsigned order is the order of the float32 depths d = means · forward: d's bits with the sign bit set
    (d ≥ 0) or all bits flipped (d < 0), -0 as +0. Non-finite depths get key 0, below every finite one: drawn last (the
    loader drops such Gaussians; here they only must not break the sort).

    means: [N, 3], forward: [3]. Returns keys: [N] uint32. The whole float32 order, not depths quantised over their
    range: one Gaussian far from the scene (a floater, a units slip) stretched 16-bit buckets until the whole scene
    shared a few, drawn in storage order (round 71b F1)."""
    m, f = means.astype(np.float32), forward.astype(np.float32)
    depth = (m[:, 0] * f[0] + m[:, 1] * f[1] + m[:, 2] * f[2]).astype(np.float32) + np.float32(0.0)
    finite = np.isfinite(depth)
    bits = depth.view(np.uint32)
    keys = np.where(bits >> 31 == 1, ~bits, bits | np.uint32(0x80000000)).astype(np.uint32)
    return np.where(finite, keys, np.uint32(0))


def back_to_front_reference(keys: np.ndarray) -> np.ndarray:
    """Stable order by key, largest (farthest) first. keys: [N] -> order: [N] uint32."""
    return np.argsort(-keys.astype(np.int64), kind="stable").astype(np.uint32)


def back_to_front_order(means: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """Indices of `means` [N, 3] from farthest to nearest along `forward` [3]: the float32 depths' keys
    (`depth_keys_reference`) in two stable counting passes of RADIX_BITS bits, low digit first."""
    means = np.ascontiguousarray(means, np.float32)
    keys = _depth_keys(means, np.ascontiguousarray(forward, np.float32))
    order = _counting_pass_descending(keys, np.arange(keys.shape[0], dtype=np.uint32), 0)
    return _counting_pass_descending(keys, order, RADIX_BITS)


@dataclass
class SortResult:
    """A finished sort: `order` [N] back to front; `ranks` [N] the random rank of each entry of
    `order` (for subsampling), or None; the view direction it was made for; the time it took."""

    order: np.ndarray
    ranks: np.ndarray | None
    forward: np.ndarray
    seconds: float
    generation: int

    def subsample(self, budget: int) -> np.ndarray:
        """The same back-to-front order restricted to the `budget` splats of lowest random rank."""
        if self.ranks is None or budget >= self.order.shape[0]:
            return self.order
        return self.order[self.ranks < budget]


class BackgroundSorter:
    """Keeps a back-to-front order for the latest view direction, sorting on its own thread.

    `request(forward)` never blocks; `poll()` returns a result not yet handed out, if any.
    A new sort starts only when the direction has turned so that dot(f, f_last) < min_dot.
    """

    def __init__(self, means: np.ndarray, rank: np.ndarray | None = None, min_dot: float = 0.998):
        """means: [N, 3]; rank: [N] a random permutation of 0..N-1 ordering splats for subsampling."""
        self.means = np.ascontiguousarray(means, np.float32)
        self.rank = rank
        self.min_dot = min_dot
        self._lock = threading.Condition()
        self._wanted: np.ndarray | None = None
        self._last_sorted: np.ndarray | None = None
        self._result: SortResult | None = None
        self._generation = 0
        self._closed = False
        self._running = False
        self._thread = threading.Thread(target=self._run, name="splat-sorter", daemon=True)
        self._thread.start()

    def needs_sort(self, forward: np.ndarray) -> bool:
        last = self._last_sorted if self._wanted is None else self._wanted
        return last is None or float(np.dot(last, forward)) < self.min_dot

    def request(self, forward: np.ndarray, force: bool = False) -> bool:
        """Ask for a sort for view direction `forward` [3] (unit); True when one was queued."""
        forward = np.asarray(forward, np.float32)
        with self._lock:
            if not force and not self.needs_sort(forward):
                return False
            self._wanted = forward.copy()
            self._lock.notify()
            return True

    @property
    def busy(self) -> bool:
        """A sort is queued, running, or done but not yet polled (the GUI must keep polling)."""
        with self._lock:
            return self._wanted is not None or self._running or self._result is not None

    def poll(self) -> SortResult | None:
        with self._lock:
            result, self._result = self._result, None
            return result

    def sort_now(self, forward: np.ndarray) -> SortResult:
        """Sort synchronously on the calling thread (screenshots, benchmarks)."""
        forward = np.asarray(forward, np.float32)
        result = self._sort(forward)
        with self._lock:
            self._last_sorted = forward.copy()
        return result

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._lock.notify()
        self._thread.join(timeout=5)

    def _sort(self, forward: np.ndarray) -> SortResult:
        start = time.perf_counter()
        order = back_to_front_order(self.means, forward)
        ranks = None if self.rank is None else self.rank[order]
        with self._lock:
            self._generation += 1
            generation = self._generation
        return SortResult(order, ranks, forward, time.perf_counter() - start, generation)

    def _run(self) -> None:
        while True:
            with self._lock:
                while self._wanted is None and not self._closed:
                    self._lock.wait()
                if self._closed:
                    return
                forward, self._wanted = self._wanted, None
                self._running = True
            result = self._sort(forward)
            with self._lock:
                self._last_sorted = forward
                self._result = result
                self._running = False
