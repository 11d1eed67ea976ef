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
(`table_bytes`). A view whose own table is larger than memory allows (thousands of masks each
meeting thousands of clusters) is summed and judged in runs of its masks, never held whole.
"""

from __future__ import annotations

import errno
import logging
import os
import tempfile
import zlib
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from drsplat.errors import DrsplatError
from drsplat.memory import format_size
from drsplat.utils import TEMP_SUFFIX, os_error_cause, output_target, sweep_stale_temps, temp_prefix, work_folder

log = logging.getLogger(__name__)

ENTRY = np.dtype([("mask", "<i4"), ("cluster", "<i4"), ("fixed", "<i8"), ("core", "<i8")])  # 24 bytes
MERGE_BYTES = 2 * ENTRY.itemsize + 8  # a view's merge: its parts concatenated, the merged table and the sort order, per entry

READ_PIECE = 16 << 20  # bytes of a table file read at a time to check its CRC-32
Entries = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # mask [E] int32, cluster [E] int32, fixed [E] int64, core [E] int64


def no_entries() -> Entries:
    none = np.zeros(0, np.int32)
    return none, none, np.zeros(0, np.int64), np.zeros(0, np.int64)


def merge_entries(parts: Sequence[Entries], consume: bool = False) -> Entries:
    """One table from parts of it: the entries of every (mask, cluster) added (integers: exact in any
    order), sorted by (mask, cluster), each pair once. parts: (mask, cluster, fixed, core) [E_p] each.
    consume: `parts` is a list this call may empty once it has copied them, so that the parts (when
    nothing else holds them) are freed before the sort: a spill of 256 MB of one view's parts then
    peaks at ~40 bytes an entry beyond them, not ~56 on top of them (the columns are gathered in
    sorted order one at a time, each copy freed before the next)."""
    kept = [p for p in parts if p[0].size]
    if consume:
        parts.clear()  # type: ignore[attr-defined]
    if not kept:
        return no_entries()
    if len(kept) == 1:
        columns = list(kept[0])
    else:
        columns = [np.concatenate(column) for column in zip(*kept)]
    del kept
    order = order_by_mask_cluster(columns[0], columns[1])
    for i in range(4):
        columns[i] = columns[i][order]
    del order
    mask, cluster, fixed, core = columns
    first = np.flatnonzero(np.r_[True, (mask[1:] != mask[:-1]) | (cluster[1:] != cluster[:-1])])
    if first.size == mask.size:  # each pair once already
        return mask, cluster, fixed, core
    return mask[first], cluster[first], np.add.reduceat(fixed, first), np.add.reduceat(core, first)


def order_by_mask_cluster(mask: np.ndarray, cluster: np.ndarray) -> np.ndarray:
    """[E] int64: an order of the entries (mask [E], cluster [E] int32) by mask, then cluster, as
    np.lexsort((cluster, mask)) gives up to the order of equal pairs. One int64 key,
    mask·2³² + (cluster + 2³¹), sorted instead of two columns: 5-10x faster (5 M entries: 0.19 s
    against 1.06), for 8 more bytes an entry while it sorts."""
    key = np.left_shift(mask, 32, dtype=np.int64)
    key += np.int64(1) << 31
    key += cluster
    return np.argsort(key)


def table_bytes(total_masks: int, max_masks: int, cap: int) -> int:
    """What the tables take at most for the memory plan: the parts held (at most `cap`, and at most
    one entry per mask x cluster, K ≤ the masks) and one view's merge while it is read (its masks x
    the clusters, within `cap`: a view's table larger than SUPPORT_READ_BYTES is read in runs of its
    masks, `SupportTables.view_ranges`, and summed in runs, `check.add_view_support(emit=...)`)."""
    held = min(cap, ENTRY.itemsize * total_masks * total_masks)
    merge = min(cap, MERGE_BYTES * max_masks * total_masks)
    return held + merge


def write_entries(f, entries: Entries) -> np.ndarray:
    """A table's entries (merged: sorted by (mask, cluster), each once) appended to the open file f as
    ENTRY records, the spill files' format. Returns the records written."""
    mask, cluster, fixed, core = entries
    rec = np.empty(mask.shape[0], ENTRY)
    rec["mask"], rec["cluster"], rec["fixed"], rec["core"] = mask, cluster, fixed, core
    f.write(rec.view(np.uint8))
    return rec


class TableWriter:
    """Tables written to one file in the spill files' format, view after view, each a run of its
    masks at a time (`add`: runs of one view in increasing masks, views in increasing order), so
    that the writer holds one run, never a view's table nor every view's (a Ray reducer's part of
    the tables: drsplat.registration.reduce). `offsets` [V + 1]: each view's first entry; `crc32`:
    the CRC-32 of the bytes written, which the reader checks (`SupportTables.adopt`)."""

    def __init__(self, f, num_views: int):
        self.f = f
        self.offsets = np.zeros(num_views + 1, np.int64)
        self.crc32 = 0
        self._view = 0
        self._last_mask = -1  # the last mask written of the current view

    def add(self, view: int, entries: Entries) -> None:
        if view < self._view:
            raise ValueError(f"view {view} after view {self._view}: a table file is written in view order")
        if view > self._view:
            self._last_mask = -1
        if entries[0].size and int(entries[0].min()) <= self._last_mask:
            raise ValueError(f"a run of view {view}'s masks from mask {int(entries[0].min())}, after its mask {self._last_mask}: "
                             "a view's runs are written in increasing masks")
        self.offsets[self._view + 1 : view + 2] = self.offsets[self._view + 1]
        self._view = view
        rec = write_entries(self.f, merge_entries([entries]))
        if rec.shape[0]:
            self._last_mask = int(rec["mask"][-1])
        self.crc32 = zlib.crc32(rec.view(np.uint8), self.crc32)
        self.offsets[view + 1] += rec.shape[0]

    def close(self) -> np.ndarray:
        """The offsets once every view is written (the views after the last one added hold nothing)."""
        self.offsets[self._view + 1 :] = self.offsets[self._view + 1]
        return self.offsets


def _changed(file, what: str) -> DrsplatError:
    """The one error of a table file (a spill, or a Ray reducer's part) that is not what was written."""
    return DrsplatError(f"{file.name}: the check's support table file{what} was changed while the registration ran (cut "
                        "short, reordered or overwritten)")


def _open_table(path: Path):
    """A table file opened for reading; one error naming it when it is gone."""
    try:
        return open(path, "rb")
    except FileNotFoundError:
        raise DrsplatError(f"{path}: the check's support table file was removed while the registration ran") from None


def _check_file(path: Path, offsets: np.ndarray, crc32: int | None) -> None:
    """`_changed` unless the file at `path` holds offsets[-1] records exactly (and, given crc32, bytes
    of that CRC-32: read once in pieces of READ_PIECE bytes)."""
    with _open_table(path) as f:
        size = os.fstat(f.fileno()).st_size
        if size != int(offsets[-1]) * ENTRY.itemsize:
            raise _changed(f, f" (it holds {size:,} bytes, its writer wrote {int(offsets[-1]) * ENTRY.itemsize:,})")
        if crc32 is None:
            return
        crc = 0
        while piece := f.read(READ_PIECE):
            crc = zlib.crc32(piece, crc)
        if crc != crc32:
            raise _changed(f, " (its CRC-32 is not its writer's)")


def _read_entries(file, start: int, count: int, what: str) -> np.ndarray:
    """[count] ENTRY records from entry `start` of an open spill file; `_changed` when it holds fewer,
    or when the count, from positions read in it, is negative."""
    if count < 0:
        raise _changed(file, what)
    file.seek(start * ENTRY.itemsize)
    rec = np.fromfile(file, ENTRY, count)
    if rec.shape[0] != count:
        raise _changed(file, what)
    return rec


class _SortedRun:
    """One view's merged table in a spill file (`count` entries from entry `start`, sorted by mask),
    read in pieces: `position(m)`, the first entry of a mask ≥ m (a binary search that reads one
    record per step, remembered), and `read(a, b)`, entries a .. b-1. limits: (the view's masks, the
    clusters) that every entry read must lie under, its (mask, cluster) pairs increasing (else
    `_changed`: an id past a table would be read out of bounds by the judging's kernels)."""

    def __init__(self, file, start: int, count: int, view: int, limits: tuple[int, int] | None = None):
        self.file, self.start, self.count, self.what = file, start, count, f" of view {view}"
        self.limits = limits
        self._positions: dict[int, int] = {}

    def position(self, mask: int) -> int:
        if mask not in self._positions:
            a, b = 0, self.count
            while a < b:
                mid = (a + b) // 2
                if int(_read_entries(self.file, self.start + mid, 1, self.what)["mask"][0]) < mask:
                    a = mid + 1
                else:
                    b = mid
            self._positions[mask] = a
        return self._positions[mask]

    def read(self, a: int, b: int, masks: tuple[int, int] | None = None) -> Entries:
        """Entries a .. b-1; masks: the (lo, hi) their masks must lie in (else the file is not the
        sorted table written: `_changed`)."""
        rec = _read_entries(self.file, self.start + a, b - a, self.what)
        if masks is not None and rec.shape[0] and not (rec["mask"].min() >= masks[0] and rec["mask"].max() < masks[1]):
            raise _changed(self.file, self.what)
        mask, cluster = rec["mask"].copy(), rec["cluster"].copy()
        if self.limits is not None and mask.size:
            num_masks, num_clusters = self.limits
            key = mask.astype(np.int64) * max(num_clusters, 1) + cluster
            if not (mask.min() >= 0 and mask.max() < num_masks and cluster.min() >= 0 and cluster.max() < num_clusters
                    and np.all(key[1:] > key[:-1])):
                raise _changed(self.file, self.what)
        return mask, cluster, rec["fixed"].copy(), rec["core"].copy()


def _largest_end(runs: Sequence[_SortedRun], lo: int, num_masks: int, max_entries: int) -> int:
    """The largest hi ≤ num_masks (lo + 1 at least) whose masks lo .. hi-1 hold at most `max_entries`
    entries over the runs: doubling, then bisection (the count grows with hi)."""
    def entries(hi: int) -> int:
        return sum(run.position(hi) - run.position(lo) for run in runs)

    good, step = lo + 1, 1
    while good < num_masks and entries(min(num_masks, good + step)) <= max_entries:
        good, step = min(num_masks, good + step), 2 * step
    if good >= num_masks:
        return num_masks
    bad = min(num_masks, good + step)  # holds more than max_entries
    while bad - good > 1:
        mid = (good + bad) // 2
        if entries(mid) <= max_entries:
            good = mid
        else:
            bad = mid
    return good


class SupportTables:
    """Every view's support entries, added in parts (`add`), held in memory up to `cap` bytes and
    spilled beyond it to files in a temporary folder, removed by `close` (or when the object is
    collected). The folder is named after where the output `beside` lands (a symlink's target) and
    lies in its work folder (`.<stem>.<pid>.<random>.tmp`: a later run writing the same output, or
    spilling for it, sweeps it if this one is killed); None: in the system's temp folder.
    `view(v)` gives view v's merged table (`merge_entries`)."""

    def __init__(self, num_views: int, cap: int, beside: str | Path | None = None, mask_counts: Sequence[int] | None = None,
                 num_clusters: int | None = None):
        self.num_views, self.cap, self.beside = num_views, int(cap), beside
        # each view's masks and the clusters, that the entries read from files must lie under (None: unchecked)
        self._limits = None if mask_counts is None or num_clusters is None else [(int(m), int(num_clusters)) for m in mask_counts]
        self._held: list[list[Entries]] = [[] for _ in range(num_views)]
        self._held_bytes = 0
        self._merged: set[int] = set()  # views whose one part held is their merged table
        self._spills: list[tuple[Path, np.ndarray]] = []  # (file, [V + 1] entry offsets of each view in it)
        self._adopted: list[Path] = []  # spill files written elsewhere (`adopt`), removed by `close` too
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

    def adopt(self, path: Path, offsets: np.ndarray, crc32: int | None = None) -> None:
        """Parts of every view written elsewhere in the spill files' format (`TableWriter`: a Ray
        reducer's block), offsets [V + 1]: its size (and, given, its CRC-32) checked first
        (`_check_file`), then read into memory when they fit beside what is held (the file is then
        removed), else read from the file as a spill file of this object's own (removed by
        `close`). The same tables either way."""
        _check_file(path, offsets, crc32)
        total = int(offsets[-1])
        if self._held_bytes + ENTRY.itemsize * total <= self.cap:
            with _open_table(path) as f:
                for v in range(self.num_views):
                    count = int(offsets[v + 1] - offsets[v])
                    if count:
                        self.add(v, self._run(f, int(offsets[v]), count, v).read(0, count))
            path.unlink()
            return
        self._merged.clear()  # a view's merged table held no longer covers the new file's part
        self._adopted.append(path)
        self._spills.append((path, np.asarray(offsets, np.int64)))
        self.spilled_bytes += ENTRY.itemsize * total

    def view(self, view: int) -> Entries:
        """View `view`'s table: its parts held and spilled, merged."""
        if view in self._merged:
            return self._held[view][0]
        parts = list(self._held[view])
        for path, offsets in self._spills:
            count = int(offsets[view + 1] - offsets[view])
            if count:
                with _open_table(path) as f:
                    parts.append(self._run(f, int(offsets[view]), count, view).read(0, count))
        merged = merge_entries(parts)
        if not self._spills and merged[0].size:  # read twice by the judging: keep it merged (never more entries than its parts)
            self._held[view] = [merged]
            self._merged.add(view)
            self._held_bytes += ENTRY.itemsize * merged[0].size - sum(ENTRY.itemsize * p[0].size for p in parts)
        return merged

    def view_ranges(self, view: int, num_masks: int, max_entries: int) -> Iterator[tuple[int, int, Entries]]:
        """View `view`'s table in runs of its masks: (lo, hi, the merged entries of masks lo .. hi-1),
        each run holding at most `max_entries` entries before the merge (one mask at least), so a view
        whose own table is larger than memory allows is read a part at a time (probe round 12: 4
        views of 4,000 scattered masks, ~360 MB of table each, went to 1.23-1.55x the budget). A
        mask's entries all fall in one run and are merged as `view` merges them: the same numbers.
        A table within `max_entries` is one run (`view`); a larger one is first spilled with the
        rest, so that every run is read from the spill files' sorted tables, found by binary search
        on their mask column."""
        held = sum(part[0].shape[0] for part in self._held[view])
        spilled = sum(int(offsets[view + 1] - offsets[view]) for _, offsets in self._spills)
        if held + spilled <= max_entries or num_masks <= 1:
            yield 0, num_masks, self.view(view)
            return
        if held:
            self._spill()
        files = [(_open_table(path), int(offsets[view]), int(offsets[view + 1] - offsets[view]))
                 for path, offsets in self._spills if offsets[view + 1] > offsets[view]]
        try:
            runs = [self._run(*file, view) for file in files]
            lo = 0
            while lo < num_masks:
                hi = _largest_end(runs, lo, num_masks, max_entries)
                parts = [run.read(run.position(lo), run.position(hi), (lo, hi)) for run in runs]
                yield lo, hi, merge_entries(parts)
                lo = hi
        finally:
            for file, _, _ in files:
                file.close()

    def _run(self, file, start: int, count: int, view: int) -> _SortedRun:
        return _SortedRun(file, start, count, view, None if self._limits is None else self._limits[view])

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
                    offsets[v + 1] = offsets[v] + write_entries(f, merge_entries(self._held[v], consume=True)).shape[0]  # the view's parts freed as merged
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
        for path in self._adopted:
            path.unlink(missing_ok=True)
        self._adopted = []
        self._spills = []
