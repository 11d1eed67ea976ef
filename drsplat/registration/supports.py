"""The cross-view mask check's support tables, held under a memory cap (drsplat.registration.check).

The check sums, for every view, a sparse table over the (mask, cluster) pairs its masks meet: per
entry the mask [int32], the cluster [int32], q and the core table r in fixed point [int64 each],
24 bytes (`ENTRY`). The tables grow with views x masks x clusters met, which no header tells
before the views are summed: 1,500 views of 20 random masks held 2.4 GB. So they are summed a
block of Gaussians (and a view) at a time into parts, and `SupportTables` keeps the parts in memory
up to `cap` bytes; past it, every part held is merged per view and appended to a spill file, and
memory starts again from nothing. Reading a view merges its parts from memory and from every spill
file.

Merging adds the parts' integers per (mask, cluster), so any split of the sums into parts, any cap
and any order of spills give the same table: its entries sorted by (mask, cluster), each once,
their sums exact (the kernel's fixed point). The memory plan counts the cap and one view's merge
(`table_bytes`).
"""

from __future__ import annotations

import errno
import logging
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from drsplat.errors import DrsplatError
from drsplat.memory import format_size
from drsplat.utils import TEMP_SUFFIX, os_error_cause, output_target, sweep_stale_temps, temp_prefix, work_folder

log = logging.getLogger(__name__)

ENTRY = np.dtype([("mask", "<i4"), ("cluster", "<i4"), ("fixed", "<i8"), ("core", "<i8")])  # 24 bytes
MERGE_BYTES = 2 * ENTRY.itemsize + 8  # a view's merge: its parts concatenated, the merged table and the sort order, per entry

Entries = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # mask [E] int32, cluster [E] int32, fixed [E] int64, core [E] int64


def no_entries() -> Entries:
    none = np.zeros(0, np.int32)
    return none, none, np.zeros(0, np.int64), np.zeros(0, np.int64)


def merge_entries(parts: Sequence[Entries]) -> Entries:
    """One table from parts of it: the entries of every (mask, cluster) added (integers: exact in any
    order), sorted by (mask, cluster), each pair once. parts: (mask, cluster, fixed, core) [E_p] each."""
    parts = [p for p in parts if p[0].size]
    if not parts:
        return no_entries()
    if len(parts) == 1:
        mask, cluster, fixed, core = parts[0]
    else:
        mask, cluster, fixed, core = (np.concatenate(column) for column in zip(*parts))
    order = np.lexsort((cluster, mask))
    mask, cluster = mask[order], cluster[order]
    first = np.flatnonzero(np.r_[True, (mask[1:] != mask[:-1]) | (cluster[1:] != cluster[:-1])])
    if first.size == order.size:  # each pair once already
        return mask, cluster, fixed[order], core[order]
    return mask[first], cluster[first], np.add.reduceat(fixed[order], first), np.add.reduceat(core[order], first)


def table_bytes(total_masks: int, max_masks: int, cap: int) -> int:
    """What the tables take at most for the memory plan: the parts held (at most `cap`, and at most
    one entry per mask x cluster, K ≤ the masks) and one view's merge while it is read (its masks x
    the clusters, within `cap`: a view's table past the cap is not bounded; docs/hostile.md)."""
    held = min(cap, ENTRY.itemsize * total_masks * total_masks)
    merge = min(cap, MERGE_BYTES * max_masks * total_masks)
    return held + merge


class SupportTables:
    """Every view's support entries, added in parts (`add`), held in memory up to `cap` bytes and
    spilled beyond it to files in a temporary folder, removed by `close` (or when the object is
    collected). The folder is named after where the output `beside` lands (a symlink's target) and
    lies in its work folder (`.<stem>.<pid>.<random>.tmp`: a later run writing the same output, or
    spilling for it, sweeps it if this one is killed); None: in the system's temp folder.
    `view(v)` gives view v's merged table (`merge_entries`)."""

    def __init__(self, num_views: int, cap: int, beside: str | Path | None = None):
        self.num_views, self.cap, self.beside = num_views, int(cap), beside
        self._held: list[list[Entries]] = [[] for _ in range(num_views)]
        self._held_bytes = 0
        self._merged: set[int] = set()  # views whose one part held is their merged table
        self._spills: list[tuple[Path, np.ndarray]] = []  # (file, [V + 1] entry offsets of each view in it)
        self._tmp: tempfile.TemporaryDirectory | None = None
        self.spilled_bytes = 0

    def add(self, view: int, entries: Entries) -> None:
        """Part of view `view`'s table (entries from one block of Gaussians, or one run of its masks)."""
        if entries[0].size:
            self._merged.discard(view)
            self._held[view].append(entries)
            self._held_bytes += ENTRY.itemsize * entries[0].size
            if self._held_bytes > self.cap:
                self._spill()

    def view(self, view: int) -> Entries:
        """View `view`'s table: its parts held and spilled, merged."""
        if view in self._merged:
            return self._held[view][0]
        parts = list(self._held[view])
        for path, offsets in self._spills:
            count = int(offsets[view + 1] - offsets[view])
            if count:
                with open(path, "rb") as f:
                    f.seek(int(offsets[view]) * ENTRY.itemsize)
                    rec = np.fromfile(f, ENTRY, count)
                if rec.shape[0] != count:
                    raise DrsplatError(f"{path}: the check's spilled support table of view {view} is cut short (its file was changed "
                                       "while the registration ran)")
                parts.append((rec["mask"], rec["cluster"], rec["fixed"], rec["core"]))
        merged = merge_entries(parts)
        if not self._spills and merged[0].size:  # read twice by the judging: keep it merged (never more entries than its parts)
            self._held[view] = [merged]
            self._merged.add(view)
            self._held_bytes += ENTRY.itemsize * merged[0].size - sum(ENTRY.itemsize * p[0].size for p in parts)
        return merged

    @property
    def held_bytes(self) -> int:
        return self._held_bytes

    def _spill(self) -> None:
        """Every view's held parts, merged, appended to a new spill file; memory held drops to nothing."""
        if self.beside is None:
            prefix, folder = "drsplat-check-", Path(tempfile.gettempdir())
        else:  # named after where the output lands (a symlink's target), in its work folder (the temp folder for a FIFO)
            folder = work_folder(self.beside)
            named = folder / output_target(self.beside).name
            prefix = temp_prefix(named)
            if self._tmp is None:
                sweep_stale_temps(named)  # a killed run's spill folder, also where no write of the output would look (a FIFO's)
        path = folder
        offsets = np.zeros(self.num_views + 1, np.int64)
        try:
            if self._tmp is None:
                self._tmp = tempfile.TemporaryDirectory(prefix=prefix, suffix=TEMP_SUFFIX, dir=os.fspath(folder))
            path = Path(self._tmp.name) / f"support-{len(self._spills)}.bin"
            with open(path, "wb") as f:
                for v in range(self.num_views):
                    mask, cluster, fixed, core = merge_entries(self._held[v])
                    rec = np.empty(mask.shape[0], ENTRY)
                    rec["mask"], rec["cluster"], rec["fixed"], rec["core"] = mask, cluster, fixed, core
                    f.write(rec.view(np.uint8))
                    offsets[v + 1] = offsets[v] + rec.shape[0]
                    self._held[v] = []
        except OSError as exc:
            self.close()
            full = exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
            raise DrsplatError(f"{path}: the mask check could not spill its support tables to disk ({os_error_cause(exc)}); it holds "
                               f"{format_size(self.cap)} of them in memory and writes the rest beside the output: "
                               + ("free space there" if full else f"let it write in {folder}")) from None
        self._merged.clear()
        self._spills.append((path, offsets))
        self.spilled_bytes += int(offsets[-1]) * ENTRY.itemsize
        log.debug("mask check: %s of support tables spilled to %s", format_size(int(offsets[-1]) * ENTRY.itemsize), path)
        self._held_bytes = 0

    def close(self) -> None:
        """Remove the spill files."""
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None
        self._spills = []
