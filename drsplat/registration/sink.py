"""Sinks: where views' pairs are summed per Gaussian block, one per memory plan.

    plan          sink        how the sums of a block [lo, hi) come to be
    one block     MemorySink  F [N, D], W [N] kept while the views arrive (drsplat.registration.sums)
    many blocks   LogSink     after the views, each block replays the pair log keeping its pairs

A Gaussian's pairs reach its row in the same order in both (view order, then the order of the
view's pairs), so a block's sums are the same bits whichever sink made them. `sample` sums a few
chosen Gaussians the same way (a scene codebook's training sample).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from drsplat.registration.pairlog import ViewPairs
from drsplat.registration.sums import Accumulator, zero_in_parallel


@dataclass
class Block:
    """The sums of Gaussians lo .. hi-1: F [hi - lo, D] = Σ w_ij f_j and W [hi - lo] = Σ w_ij (float32).
    kept: [hi - lo] float32, the weight of the pairs F still holds where the vote removed some
    exactly (W less the trimmed pairs'; what F's norm is judged against, `sums.normalize_rows`),
    None where F holds all of W."""

    lo: int
    hi: int
    F: np.ndarray
    W: np.ndarray
    kept: np.ndarray | None = None


class PairSource(Protocol):
    """Views' pairs that can be read again block by block, every view in order with only the pairs of
    Gaussians lo .. hi-1: a PairLog, the check's PairRecord and KeptPairs (drsplat.registration.check)."""

    def block_views(self, lo: int, hi: int) -> Iterator[ViewPairs]: ...


class Sink(Protocol):
    """Receives every view's pairs in view order (`add`), then gives the sums block by block.
    place: where `add` takes the views' pairs and keeps the sums, "host" or a torch device
    (drsplat.registration.device_sums.DeviceSink, which also tells which Gaussians got weight:
    `positive`); a sink that takes them on the host and sums elsewhere says so in `sums_on`
    (`sums_place`)."""

    num_blocks: int
    place: str

    def add(self, view: ViewPairs) -> None: ...

    def blocks(self, reuse: bool = False) -> Iterator[Block]:
        """The sums block by block. reuse: a block's arrays hold the next block's sums (their pages
        touched already: a fresh 4 GB block cost 3.2 s of page faults at 5M Gaussians, reused 0.2 s),
        so the caller drops or copies each block before it asks for the next; one-block sinks ignore it."""
        ...

    def sample(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...



def sample_rows(ids: np.ndarray, num_gaussians: int) -> tuple[np.ndarray, int, int]:
    """(row [N] int32: each sampled Gaussian's row, -1 elsewhere; lo, hi: the span of the views'
    blocks that holds them) of a sample `ids` [S] (sorted, distinct): what a sink's `sample` replays."""
    row = np.full(num_gaussians, -1, np.int32)
    row[ids] = np.arange(ids.shape[0], dtype=np.int32)
    return row, *((int(ids[0]), int(ids[-1]) + 1) if ids.size else (0, 0))


def reused_sums(spare: tuple[np.ndarray, np.ndarray] | None, rows: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The first `rows` rows of an earlier block's (F [R, D], W [R]), zeroed, to sum a block of
    rows ≤ R in (None without them, or when they are too few: the Accumulator then makes new ones)."""
    if spare is None or spare[0].shape[0] < rows:
        return None
    F, W = spare[0][:rows], spare[1][:rows]
    zero_in_parallel(F)
    W.fill(0)
    return F, W


def sums_place(sink: Sink) -> str:
    """Where `sink` keeps its sums: its `place`, or its `sums_on` where the two differ (the cross-view
    check takes the views' pairs on the host and, in one block, sums the kept ones on the torch
    device: drsplat.registration.check.CheckSink)."""
    return getattr(sink, "sums_on", sink.place)


class MemorySink:
    """One block of all N Gaussians, summed as the views arrive."""

    num_blocks = 1
    place = "host"

    def __init__(self, num_gaussians: int, dim: int):
        self._acc = Accumulator(num_gaussians, dim)

    def add(self, view: ViewPairs) -> None:
        self._acc.add_pairs(view.gaussians, view.masks, view.weights, view.feats)

    def blocks(self, reuse: bool = False) -> Iterator[Block]:
        F, W = self._acc.sums()
        yield Block(0, F.shape[0], F, W)

    def sample(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F [S, D], W [S]) of the Gaussians `ids` [S] (copies)."""
        F, W = self._acc.sums()
        return F[ids], W[ids]


class LogSink:
    """Blocks of `block` consecutive Gaussians, each summed by replaying the pair log `plog`
    (the views are logged by the driver, so `add` keeps nothing). A block reads only its Gaussian
    chunks' pairs of each record (PairLog.block_views)."""

    place = "host"

    def __init__(self, num_gaussians: int, dim: int, plog: PairSource, block: int):
        if block < 1:
            raise ValueError("block must be >= 1")
        self.num_gaussians, self.dim, self.block = num_gaussians, dim, int(block)
        self._log = plog

    @property
    def num_blocks(self) -> int:
        return -(-self.num_gaussians // self.block)

    def add(self, view: ViewPairs) -> None:
        pass

    def blocks(self, reuse: bool = False) -> Iterator[Block]:
        spare = None
        for lo in range(0, self.num_gaussians, self.block):
            hi = min(self.num_gaussians, lo + self.block)
            if not reuse:  # no local keeps the block across the yield: the next block's sums are allocated only after the caller drops this one
                yield self.block_sums(lo, hi)
                continue
            block = self.block_sums(lo, hi, spare)
            spare = block.F, block.W
            yield block
            del block

    def block_sums(self, lo: int, hi: int, spare: tuple[np.ndarray, np.ndarray] | None = None) -> Block:
        """The sums of Gaussians lo .. hi-1 from one replay of the log (a reducer's block,
        drsplat.registration.reduce); spare: an earlier block's (F, W) to make them in (`reused_sums`)."""
        acc = Accumulator(hi - lo, self.dim, sums=reused_sums(spare, hi - lo))
        for view in self._log.block_views(lo, hi):  # only the chunks of [lo, hi) are read
            if view.gaussians.size:
                acc.add_pairs(view.gaussians - np.int32(lo), view.masks, view.weights, view.feats)
        return Block(lo, hi, *acc.sums())

    def sample(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F [S, D], W [S]) of the Gaussians `ids` [S] (sorted, distinct), from one replay."""
        row, lo, hi = sample_rows(ids, self.num_gaussians)
        acc = Accumulator(ids.shape[0], self.dim)
        for view in self._log.block_views(lo, hi) if ids.size else ():
            keep = row[view.gaussians] >= 0
            if keep.any():
                acc.add_pairs(row[view.gaussians[keep]], view.masks[keep], view.weights[keep], view.feats)
        return acc.sums()
