"""The registration checkpoint: an append-only log of each view's sparse (Gaussian, mask, weight) pairs.

A registration's state after v views is fully described by the distinct (Gaussian, mask) pairs of
those views with their summed weights, plus the views' mask embeddings. The log stores exactly
that, one record per view, appended as each view finishes; nothing is ever rewritten. Replaying
the records in order into `Accumulator.add_pairs` reproduces the running sums bit for bit, and
a budgeted run (LogSink in drsplat.registration.sink) reads them block by block.

Layout (little-endian):

    header:  b"DRSPLOG2" | u64 n | n bytes of JSON parameters | u32 crc32(JSON)
    record:  b"VIEW" | u64 a | u64 b | a bytes of JSON meta | b bytes of payload | u32 crc32(meta + payload)
    payload: feats [M, D] f32 | gaussian [P] i32 | mask [P] i32 | weight [P] f32 | used [U] i32 | starts [C + 1] i64
             [ | stat ids [T] i32 | peak [T] f64 | total [T] f64 | front [T] f64 | stat starts [S + 1] i64 ]   (meta has "T")

A record's pairs are grouped by Gaussian chunk (chunk c = Gaussians c·2^16 .. (c+1)·2^16 - 1,
`CHUNK_SHIFT`), stably: chunk c's pairs are pairs starts[c] .. starts[c+1] - 1, in the order the
view emitted them. Grouping keeps every Gaussian's own pairs in their order, so the sums are the
same bits (they are summed per Gaussian in arrival order, drsplat.registration.sums), and a block
of Gaussians [lo, hi) reads only its chunks' pairs of each record (`read_block`): a budgeted
run's blocks and the reducers of drsplat.registration.reduce read the log's pairs once in all,
not once per block.

Size: 12 bytes per distinct pair plus 4·D per mask and 8 per chunk (flowers, 50 views at 640 x
480: 15.3 M pairs, 184 MB, against 1.1 GB for the old dense F checkpoint that was rewritten every
10 views).
Worker shards (the partitioned reduce on Ray, drsplat.registration.reduce): each view worker
appends its own views' records, with their floater statistics (the optional section, grouped by
chunk like the pairs), to a shard of its own (`ShardWriter`) in a folder beside the log, and the
driver's log holds only a small pointer record per view (meta "shard": the shard file, relative to
the log's folder, and where the record lies; its embeddings and the masks that reached a Gaussian,
"present"). Reading a pointer's pairs (`read_block`) or statistics (`read_stats_block`) follows it
into the shard, so the driver never receives, writes or reads a view's pairs.

A record cut short by a kill, a bad checksum or a file that is not a log (an older .npz
checkpoint, a truncated one) is detected: the valid prefix is kept, or the run starts over with
a warning.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import socket
import struct
import uuid
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drsplat.defaults import NEAR
from drsplat.registration.aggregate import ViewStats
from drsplat.errors import OutputError
from drsplat.utils import TEMP_SUFFIX, os_error_cause

log = logging.getLogger(__name__)

MAGIC = b"DRSPLOG2"  # 2: pairs grouped by Gaussian chunk, with chunk starts (DRSPLOG1 logs start over)
CHUNK_SHIFT = 16  # a record's pairs are grouped by chunks of 2^16 Gaussians
TAG = b"VIEW"
_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")


@dataclass
class ViewPairs:
    """One view's contribution: its distinct (Gaussian, mask) pairs with summed weights.

    feats: [M, D] float32 the view's mask embeddings (non-finite ones zeroed, their pixels dropped).
    gaussians: [P] int32, masks: [P] int32 (rows of feats), weights: [P] float32 w_ij, in the
    order the coalescing emits them (mask by mask, or grouped by Gaussian for a vote or check mode:
    `ViewJob.by_gaussian`); each Gaussian's masks come in increasing order either way, which fixes
    the summation order.
    used: [U] int32 masks that cover at least one pixel (for training a scene codebook).
    num_pairs: contributing (Gaussian, pixel) pairs; num_nonfinite: masks dropped.
    raster_seconds / coalesce_seconds: where the time went (not stored in the log).
    stats: the aggregation mode's per-view statistics (drsplat.registration.aggregate.ViewStats; on
    the torch device path drsplat.registration.device_sums.DeviceViewStats), or None (stored only in
    a worker's shard; the driver's log resumes them from their own snapshot).
    device: the pairs on the torch engine's device (drsplat.registration.device_sums.DevicePairs),
    or None; gaussians / masks / weights are then empty until `on_host` copies them (not logged).
    chunk_starts: [C + 1] int64 when the pairs are grouped by Gaussian chunk (`grouped`), else None.
    present: [M] bool, the masks that reached some Gaussian, or None (then read from `masks`);
    shard: where a worker logged this view's pairs and statistics (`ShardWriter`: the shard file
    relative to the log's folder, the record's offsets and meta), or None; with a shard the host
    pairs are empty and `present` is set.
    stamp: what the view's feature files were when it was logged (drsplat.registration.checkpoint), or None.
    """

    name: str
    feats: np.ndarray
    gaussians: np.ndarray
    masks: np.ndarray
    weights: np.ndarray
    used: np.ndarray
    num_pairs: int
    num_nonfinite: int = 0
    raster_seconds: float = 0.0
    coalesce_seconds: float = 0.0
    stats: object | None = None
    device: object | None = None
    chunk_starts: np.ndarray | None = None
    present: np.ndarray | None = None
    shard: dict | None = None
    stamp: str | None = None

    @property
    def num_distinct(self) -> int:
        if self.shard is not None:
            return int(self.shard["meta"]["P"])
        return self.device.num_distinct if self.device is not None else int(self.gaussians.shape[0])

    def resolved(self) -> ViewPairs:
        """This view with the sizes of its device pairs read (drsplat.registration.device_sums.
        DevicePairs.resolve: a view computed on a device learns them a view late); itself when none
        are pending."""
        if self.device is None or getattr(self.device, "pending", None) is None:
            return self
        return self.device.resolve(self)

    def present_masks(self) -> np.ndarray:
        """[M] bool: the masks that reached some Gaussian in this view (from the device when its pairs
        are there only: M flags copied, not the pairs)."""
        if self.present is not None:
            return self.present
        if self.device is not None and self.gaussians.shape[0] != self.device.num_distinct:
            return self.device.present()
        present = np.zeros(self.feats.shape[0], bool)
        present[self.masks] = True
        return present

    def on_host(self) -> ViewPairs:
        """This view with its pairs on the host: itself, or a copy holding the device pairs' host arrays."""
        if self.device is None or self.gaussians.shape[0] == self.device.num_distinct:
            return self
        g, m, w = self.device.to_host()
        return dataclasses.replace(self, gaussians=g, masks=m, weights=w)

    def grouped(self) -> ViewPairs:
        """This view with its pairs stably grouped by Gaussian chunk and `chunk_starts` set (itself
        when grouped already): the log's record order. Every Gaussian keeps its pairs' order, so
        summing the grouped view gives the same bits. O(P) radix sort on 16-bit chunk keys."""
        if self.chunk_starts is not None:
            return self
        order, starts = chunk_grouping(self.gaussians)
        g, m, w = (self.gaussians, self.masks, self.weights) if order is None else (self.gaussians[order], self.masks[order], self.weights[order])
        return dataclasses.replace(self, gaussians=g, masks=m, weights=w, chunk_starts=starts)

    @property
    def nbytes(self) -> int:
        """Bytes of its host arrays: embeddings, pairs, masks used and statistics (what a kept view holds)."""
        stats = 0 if self.stats is None else sum(int(getattr(self.stats, name).nbytes) for name in ("ids", "peak", "total", "front"))
        return int(self.feats.nbytes + self.gaussians.nbytes + self.masks.nbytes + self.weights.nbytes + self.used.nbytes + stats)


def resuming_from(count: int) -> str:
    """What a resume that keeps the first `count` logged views does: "resuming from the N views before it", or
    "starting from scratch" when it keeps none (round 89b F2: "resuming from the 0 views before it")."""
    return f"resuming from the {count} view{'' if count == 1 else 's'} before it" if count else "starting from scratch"


def chunk_grouping(ids: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """(order, starts): the stable order that groups `ids` [P] int32 by Gaussian chunk (None when
    they are grouped already) and the [C + 1] int64 chunk starts of the grouped ids. O(P) radix sort
    on 16-bit chunk keys."""
    chunks = (ids >> CHUNK_SHIFT).astype(np.uint16)  # int32 ids: chunk < 2^15, and numpy's stable sort of 16-bit keys is a radix sort
    count = int(chunks.max()) + 1 if ids.size else 0
    starts = np.zeros(count + 1, np.int64)
    np.cumsum(np.bincount(chunks, minlength=count), out=starts[1:])
    order = np.argsort(chunks, kind="stable") if count > 1 and np.any(chunks[1:] < chunks[:-1]) else None
    return order, starts


def _stats_arrays(stats) -> tuple[dict, list[np.ndarray]]:
    """The optional statistics section of a record (a view's ViewStats grouped by Gaussian chunk):
    its meta entries and arrays. A view's statistics hold each Gaussian once, so any order folds to
    the same bits (drsplat.registration.aggregate.SurfaceSupport.add)."""
    order, starts = chunk_grouping(np.asarray(stats.ids, np.int32))
    columns = [np.asarray(stats.ids, np.int32), np.asarray(stats.peak, np.float64), np.asarray(stats.total, np.float64),
               np.asarray(stats.front, np.float64)]
    if order is not None:
        columns = [c[order] for c in columns]
    dtypes = ("<i4", "<f8", "<f8", "<f8")
    return ({"T": int(columns[0].shape[0]), "S": int(starts.shape[0] - 1)},
            [np.ascontiguousarray(c, t) for c, t in zip(columns, dtypes)] + [np.ascontiguousarray(starts, "<i8")])


def _encode(view: ViewPairs, with_stats: bool = False) -> tuple[bytes, list[np.ndarray]]:
    """A record's meta and payload arrays: the view's pairs (grouped by chunk), with its statistics
    when `with_stats` (a worker's shard); a view logged in a shard gets a pointer record (no pairs)."""
    view = view.grouped()  # done by the worker that computed it when the job asked (ViewJob.group_pairs)
    meta = {
        "name": view.name, "M": int(view.feats.shape[0]), "D": int(view.feats.shape[1]), "P": int(view.gaussians.shape[0]),
        "U": int(view.used.shape[0]), "C": int(view.chunk_starts.shape[0] - 1), "pairs": int(view.num_pairs),
        "nonfinite": int(view.num_nonfinite),
    }
    if view.shard is not None:
        meta["shard"] = view.shard
        meta["present"] = np.flatnonzero(view.present_masks()).tolist()
    if view.stamp is not None:
        meta["stamp"] = view.stamp
    arrays = [
        np.ascontiguousarray(view.feats, "<f4"), np.ascontiguousarray(view.gaussians, "<i4"),
        np.ascontiguousarray(view.masks, "<i4"), np.ascontiguousarray(view.weights, "<f4"), np.ascontiguousarray(view.used, "<i4"),
        np.ascontiguousarray(view.chunk_starts, "<i8"),
    ]
    if with_stats:
        if view.stats is None:
            raise ValueError(f"view {view.name}: no statistics to log")
        extra, stats = _stats_arrays(view.stats)
        meta.update(extra)
        arrays += stats
    return json.dumps(meta).encode(), arrays


def _decode(meta: dict, payload: memoryview | bytes) -> ViewPairs:
    m, d, p, u = meta["M"], meta["D"], meta["P"], meta["U"]
    buf = np.frombuffer(payload, np.uint8)
    pos = 0

    def take(count: int, dtype: str, shape: tuple[int, ...]) -> np.ndarray:
        nonlocal pos
        size = count * np.dtype(dtype).itemsize
        arr = buf[pos : pos + size].view(dtype).reshape(shape)
        pos += size
        return arr

    feats = take(m * d, "<f4", (m, d))
    g, mk, w, used = take(p, "<i4", (p,)), take(p, "<i4", (p,)), take(p, "<f4", (p,)), take(u, "<i4", (u,))
    starts = take(meta["C"] + 1, "<i8", (meta["C"] + 1,))
    stats = None
    if "T" in meta:
        t = meta["T"]
        stats = ViewStats(take(t, "<i4", (t,)), take(t, "<f8", (t,)), take(t, "<f8", (t,)), take(t, "<f8", (t,)))
    present = None
    if "present" in meta:
        present = np.zeros(m, bool)
        present[np.asarray(meta["present"], np.int64)] = True
    return ViewPairs(meta["name"], feats, g, mk, w, used, int(meta["pairs"]), int(meta["nonfinite"]), stats=stats, chunk_starts=starts,
                     present=present, shard=meta.get("shard"))


def meta_problem(meta) -> str | None:
    """Why a log record's meta (JSON read back from disk) cannot be a record `_encode` wrote, or None:
    a dict whose name is a string, whose counts and pair numbers are non-negative integers, whose
    stamp is a string and whose present masks are rows of its embeddings. A record that passes its
    checksum but not this (a log edited by hand or by another tool) is damaged like one that fails
    it: replaying it raised KeyError or IndexError from deep inside the resume (round 30), and a
    kept checkpoint then failed every rerun the same way."""
    if not isinstance(meta, dict):
        return "its meta is not a JSON object"
    if not isinstance(meta.get("name"), str):
        return "it names no view"
    keys = _SIZE_KEYS + ("pairs", "nonfinite") + (("T", "S") if "T" in meta else ())
    if not all(type(meta.get(k)) is int and 0 <= meta[k] < 1 << 62 for k in keys):
        return "its counts are not non-negative integers"
    if "stamp" in meta and not isinstance(meta["stamp"], str):
        return "its feature stamp is not a string"
    present = meta.get("present", [])
    if not (isinstance(present, list) and all(type(i) is int and 0 <= i < meta["M"] for i in present)):
        return "its present masks are not rows of its embeddings"
    if "shard" in meta and not isinstance(meta["shard"], dict):
        return "its shard pointer is not a JSON object"
    return None


def _pairs_section_size(meta: dict) -> int:
    """Bytes of a record's payload before its optional statistics section (embeddings, pairs, used
    masks, chunk starts)."""
    return 4 * (meta["M"] * meta["D"] + 3 * meta["P"] + meta["U"]) + 8 * (meta["C"] + 1)


def payload_size(meta: dict) -> int:
    """The bytes of a record's payload, from its meta (the statistics section included)."""
    size = _pairs_section_size(meta)
    if "T" in meta:
        size += 28 * meta["T"] + 8 * (meta["S"] + 1)
    return size


def chunk_span(starts: np.ndarray, lo: int, hi: int) -> tuple[int, int]:
    """The pairs (s0, s1) of a record whose chunks meet Gaussians lo .. hi-1; starts: its [C + 1]
    chunk starts. Empty (s0 == s1) when the range is empty or past the record's last chunk."""
    c = starts.shape[0] - 1
    first = min(lo >> CHUNK_SHIFT, c)
    last = min(((hi - 1) >> CHUNK_SHIFT) + 1, c) if hi > lo else first
    return int(starts[first]), int(starts[max(last, first)])


class ShardError(ValueError):
    """A pointer record's shard is missing, is not that log's, or lies outside its folder: the
    message names the file; `reason` is the message without it."""

    def __init__(self, path, reason: str):
        super().__init__(f"{path}: {reason}")
        self.path, self.reason = path, reason


def shards_folder(log_path: Path) -> Path:
    """The folder of the view workers' shards beside the log `log_path` (a temporary log's is a temp
    folder too, `.<out>.<pid>.<random>.shards.tmp`, so a killed run's is swept with it)."""
    name = log_path.name
    if name.endswith(TEMP_SUFFIX):
        return log_path.with_name(name[: -len(TEMP_SUFFIX)] + ".shards" + TEMP_SUFFIX)
    return log_path.with_name(name + ".shards")


def shard_file(log_path: Path, ref: dict) -> Path:
    """The shard a pointer record `ref` of the log `log_path` names, which must be a plain file name
    in the log's shards folder (`<folder>/<name>`): a log read back from disk never leads a reader
    to another path. ShardError otherwise."""
    name = ref.get("file") if isinstance(ref, dict) else None
    folder = shards_folder(log_path)
    parts = name.split("/") if isinstance(name, str) else []
    if len(parts) != 2 or parts[0] != folder.name or parts[1] in ("", ".", "..") or "\\" in parts[1] or "\0" in parts[1]:
        raise ShardError(log_path, f"a view's pointer names {name!r}, not a shard in {folder.name}")
    return folder / parts[1]


_SIZE_KEYS = ("M", "D", "P", "U", "C")  # a record's counts (with "T", "S" when it holds statistics)


def pointed_record(path: Path, ref: dict, f) -> LogRecord:
    """The record of shard `path` (open as `f`, binary) that the pointer `ref` names, checked
    before anything is read by its sizes: its start and offset non-negative integers, its counts
    non-negative integers, a record header at `start` whose meta is the pointer's, whose lengths
    are that meta's and whose payload and checksum fit in the file. A pointer comes from a log on
    disk, so nothing in it is trusted. ShardError (naming the file) otherwise."""
    meta = ref.get("meta")
    start, offset = ref.get("start"), ref.get("offset")
    counts = [meta.get(k) for k in _SIZE_KEYS + (("T", "S") if "T" in meta else ())] if isinstance(meta, dict) else [None]
    if not all(type(v) is int and 0 <= v < 1 << 62 for v in [start, offset, *counts]):
        raise ShardError(path, "the pointer to it is malformed (offsets and counts must be non-negative integers)")
    meta_bytes = json.dumps(meta).encode()
    size = payload_size(meta)
    f.seek(start)
    head = f.read(20 + len(meta_bytes))
    if (len(head) != 20 + len(meta_bytes) or head[:4] != TAG or _U64.unpack(head[4:12])[0] != len(meta_bytes)
            or _U64.unpack(head[12:20])[0] != size or head[20:] != meta_bytes or offset != start + 20 + len(meta_bytes)
            or os.fstat(f.fileno()).st_size < offset + size + 4):
        raise ShardError(path, "the record is not there (the shard was cut short or replaced)")
    return LogRecord(str(meta.get("name")), offset, meta, start)


@dataclass
class LogRecord:
    """Where a view's record lies in the log (for re-reading it without a scan)."""

    name: str
    offset: int  # of the payload
    meta: dict
    start: int = 0  # of the record


class PairLog:
    """An append-only registration log at `path` for the parameters `params`.

    `PairLog.open(path, params)` keeps a valid prefix of an existing log with the same parameters
    (`records`), truncates a torn last record, and starts a new log otherwise (with a warning
    that says why). `append(view)` adds a record; `read(record)` returns a stored view.
    """

    def __init__(self, path: Path, params: dict, records: list[LogRecord], file) -> None:
        self.path = path
        self.params = params
        self.records = records
        self._file = file
        self._shards: dict[str, PairLog] = {}  # shard file -> its reader (pointer records lead there)
        self._pointed: dict[tuple[str, int], LogRecord] = {}  # (shard file, pointer's start) -> its checked record

    # --------------------------------------------------------------------- opening

    @classmethod
    def open(cls, path: str | Path, params: dict) -> "PairLog":
        path = Path(path)
        records = _valid_records(path, params) if path.exists() else None
        if records is None:
            path.parent.mkdir(parents=True, exist_ok=True)
            with open(path, "wb") as f:
                body = json.dumps(params, sort_keys=True).encode()
                f.write(MAGIC + _U64.pack(len(body)) + body + _U32.pack(zlib.crc32(body)))
            records = []
        return cls(path, params, records, open(path, "r+b"))

    @classmethod
    def reader(cls, path: str | Path, params: dict, records: list[LogRecord]) -> "PairLog":
        """The log at `path`, opened read-only with the `records` its writer knows (a reducer on
        another process or node replaying it; nothing is scanned or truncated).

        OSError when the file cannot be opened; ValueError when it is not that log: another header,
        other parameters, or shorter than its records (another file at the same path on this node)."""
        path = Path(path)
        f = open(path, "rb")
        try:
            head = f.read(len(MAGIC) + 8)
            if len(head) < len(MAGIC) + 8 or head[: len(MAGIC)] != MAGIC:
                raise ValueError("not a drsplat registration log")
            (n,) = _U64.unpack(head[len(MAGIC) :])
            body = f.read(min(n, 1 << 20))
            if len(body) != n or json.loads(body) != json.loads(json.dumps(params, sort_keys=True)):
                raise ValueError("a log of other parameters or inputs")
            end = records[-1].offset + payload_size(records[-1].meta) + 4 if records else 0
            size = os.fstat(f.fileno()).st_size
            if size < end:
                raise ValueError(f"{size} bytes, its {len(records)} views need {end}")
        except BaseException:
            f.close()
            raise
        return cls(path, params, list(records), f)

    def sync(self) -> None:
        """Flush and fsync the log (before other processes or nodes read it)."""
        self._file.flush()
        os.fsync(self._file.fileno())

    def close(self) -> None:
        for shard in self._shards.values():
            shard.close()
        self._shards.clear()
        if self._file is not None and not self._file.closed:
            self._file.close()

    def __enter__(self) -> "PairLog":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def delete(self) -> None:
        self.close()
        self.path.unlink(missing_ok=True)

    # --------------------------------------------------------------------- writing / reading

    def append(self, view: ViewPairs, sync: bool = False, with_stats: bool = False) -> None:
        """Append one view's record (flushed to the OS; fsync'd when `sync`); with its statistics when
        `with_stats` (a worker's shard), a pointer record when the view lies in a shard."""
        meta_bytes, arrays = _encode(view, with_stats)
        size = sum(a.nbytes for a in arrays)
        f = self._file
        f.seek(0, os.SEEK_END)
        start = f.tell()
        f.write(TAG + _U64.pack(len(meta_bytes)) + _U64.pack(size) + meta_bytes)
        crc = zlib.crc32(meta_bytes)
        for a in arrays:
            raw = a.reshape(-1).view(np.uint8)  # flat bytes; memoryview.cast refuses a zero-size [0, D] array (a view with no masks)
            f.write(raw)
            crc = zlib.crc32(raw, crc)
        f.write(_U32.pack(crc))
        f.flush()
        if sync:
            os.fsync(f.fileno())
        self.records.append(LogRecord(view.name, start + 4 + 16 + len(meta_bytes), json.loads(meta_bytes), start))

    def truncate(self, count: int) -> None:
        """Keep only the first `count` records (the views a companion snapshot covers)."""
        if count < len(self.records):
            self._file.flush()
            self._file.truncate(self.records[count].start)
            del self.records[count:]

    def read(self, record: LogRecord) -> ViewPairs:
        """The view stored in `record` (checked when the log was opened)."""
        f = self._file
        f.flush()
        f.seek(record.offset)
        return _decode(record.meta, f.read(payload_size(record.meta)))

    def _reader_at(self, record: LogRecord):
        """read_at(pos, count, dtype): `count` items of `dtype` at byte `pos` of the record's payload."""
        f = self._file  # one handle, one reader: a reducer opens its own
        f.flush()

        def read_at(pos: int, count: int, dtype: str) -> np.ndarray:
            f.seek(record.offset + pos)
            size = count * np.dtype(dtype).itemsize
            raw = f.read(size)
            if len(raw) != size:
                raise ValueError(f"{self.path}: the record of view {record.name} is cut short")
            return np.frombuffer(raw, dtype)

        return read_at

    def _in_shard(self, record: LogRecord) -> tuple[PairLog, LogRecord] | None:
        """(the shard's reader, the view's record there) for a pointer record, else None."""
        ref = record.meta.get("shard")
        if ref is None:
            return None
        path = shard_file(self.path, ref)
        shard = self._shards.get(path.name)
        if shard is None:
            try:
                shard = self._shards[path.name] = PairLog.reader(path, self.params, [])
            except (OSError, ValueError) as exc:
                why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
                raise ShardError(path, f"the worker's shard holding view {record.name} cannot be read ({why})") from None
        key = (path.name, record.start)
        if key not in self._pointed:  # checked once per reader: a reducer reads a record once per block
            self._pointed[key] = pointed_record(path, ref, shard._file)
        return shard, self._pointed[key]

    def read_block(self, record: LogRecord, lo: int, hi: int) -> ViewPairs:
        """The view stored in `record` with only the pairs of Gaussians lo .. hi-1 (in record order):
        its embeddings, its chunk starts and the pairs of the chunks that meet [lo, hi), read with
        one seek each, then filtered exactly. A pointer record's pairs are read from its shard."""
        shard = self._in_shard(record)
        if shard is not None:
            return shard[0].read_block(shard[1], lo, hi)
        meta = record.meta
        m, d, p, u, c = meta["M"], meta["D"], meta["P"], meta["U"], meta["C"]
        read_at = self._reader_at(record)
        feats = read_at(0, m * d, "<f4").reshape(m, d)
        pairs_at = 4 * m * d
        starts = read_at(pairs_at + 12 * p + 4 * u, c + 1, "<i8")
        s0, s1 = chunk_span(starts, lo, hi)
        g = read_at(pairs_at + 4 * s0, s1 - s0, "<i4")
        mk = read_at(pairs_at + 4 * (p + s0), s1 - s0, "<i4")
        w = read_at(pairs_at + 4 * (2 * p + s0), s1 - s0, "<f4")
        used = read_at(pairs_at + 12 * p, u, "<i4")
        keep = (g >= lo) & (g < hi)
        if not keep.all():
            g, mk, w = g[keep], mk[keep], w[keep]
        return ViewPairs(record.name, feats, g, mk, w, used, int(meta["pairs"]), int(meta["nonfinite"]))

    def read_stats_block(self, record: LogRecord, lo: int, hi: int) -> ViewStats:
        """The statistics of Gaussians lo .. hi-1 in `record` (a shard's record, or a pointer to one;
        ids are scene ids), read from the chunks that meet [lo, hi). ValueError for a record
        without statistics."""
        shard = self._in_shard(record)
        if shard is not None:
            return shard[0].read_stats_block(shard[1], lo, hi)
        meta = record.meta
        if "T" not in meta:
            raise ValueError(f"{self.path}: the record of view {record.name} holds no floater statistics")
        t = meta["T"]
        at = _pairs_section_size(meta)
        read_at = self._reader_at(record)
        starts = read_at(at + 28 * t, meta["S"] + 1, "<i8")
        s0, s1 = chunk_span(starts, lo, hi)
        ids = read_at(at + 4 * s0, s1 - s0, "<i4")
        columns = [read_at(at + 4 * t + 8 * (j * t + s0), s1 - s0, "<f8") for j in range(3)]
        keep = (ids >= lo) & (ids < hi)
        if not keep.all():
            ids, columns = ids[keep], [c[keep] for c in columns]
        return ViewStats(ids, *columns)

    def __iter__(self) -> Iterator[ViewPairs]:
        for record in list(self.records):
            yield self.read(record)

    def block_views(self, lo: int, hi: int) -> Iterator[ViewPairs]:
        """Every record in order, holding only the pairs of Gaussians lo .. hi-1 (`read_block`)."""
        for record in list(self.records):
            yield self.read_block(record, lo, hi)

    @property
    def nbytes(self) -> int:
        self._file.flush()
        return os.path.getsize(self.path)


def _valid_records(path: Path, params: dict) -> list[LogRecord] | None:
    """The records of a readable log made with `params` (torn tail truncated), or None to start over."""
    try:
        size = path.stat().st_size
        with open(path, "r+b") as f:
            head = f.read(len(MAGIC) + 8)
            if head[: len(MAGIC)] != MAGIC or len(head) < len(MAGIC) + 8:
                log.warning("%s is not a drsplat registration log (an older or truncated checkpoint); starting from scratch", path)
                return None
            (n,) = _U64.unpack(head[len(MAGIC) :])
            body = f.read(n) if n <= size else b""
            crc = f.read(4)
            if len(body) != n or len(crc) != 4 or _U32.unpack(crc)[0] != zlib.crc32(body):
                log.warning("%s has a damaged header (truncated checkpoint); starting from scratch", path)
                return None
            saved = json.loads(body)
            wanted = json.loads(json.dumps(params, sort_keys=True))
            if saved != wanted:
                log.warning("%s was made with other parameters or inputs (%s); starting over", path, changed_params(saved, wanted))
                return None
            records, end = _scan(f, size)
            if end < size:
                log.warning("%s: %s; %s", path,
                            "the last view's record is incomplete (the run stopped while writing it: killed, or its disk full)" if _is_torn_tail(f, end, size)
                            else f"record {len(records) + 1} is damaged (its checksum, length or meta does not match)", resuming_from(len(records)))
                f.truncate(end)
            return records
    except OSError as exc:  # not the log's contents: starting over would truncate a log that may be whole
        raise OutputError(path, f"the checkpoint of a stopped run cannot be read to resume ({os_error_cause(exc)}); make it readable and "
                          "writable to resume, or delete it to start over") from None
    except (ValueError, json.JSONDecodeError) as exc:
        log.warning("%s is not a readable checkpoint (%s); starting from scratch", path, exc)
        return None


PARAM_MEANINGS = {  # checkpoint_params' keys, as a restart names them
    "scene": "the scene's Gaussians", "num_gaussians": "the scene's size", "views": "the views (names, intrinsics, poses, order)",
    "features_dir": "the feature folder", "topk": "--topk", "level": "--level",
    "aggregate": "--aggregate", "shards": "Ray in blocks (--ray with --memory-budget)", "version": "the checkpoint format",
    "engine": "the engine (--engine / --device: the GPU's agrees with the CPU's to float32 rounding only)",
}


def changed_params(saved: dict, wanted: dict) -> str:
    """What differs between a log's parameters and this run's, in words ("--topk, the feature files"). The near plane
    names both values: the same command decides it from the training images (`--near-plane auto`), so it changes
    with them and not only with the flag (round 66a F1)."""
    keys = sorted(k for k in set(saved) | set(wanted) if saved.get(k) != wanted.get(k))
    return ", ".join(_near_plane_change(saved, wanted) if k == "near_plane" else PARAM_MEANINGS.get(k, k) for k in keys) + " changed"


def _near_plane_change(saved: dict, wanted: dict) -> str:
    """'the near plane (0.2 in the checkpoint, 0.01 now: ...)'; checkpoint_params records it only where it is not NEAR."""
    def shown(params: dict) -> str:
        return f"{params.get('near_plane', NEAR):g}"

    return (f"the near plane ({shown(saved)} in the checkpoint, {shown(wanted)} now: --near-plane, or the plane that "
            "--near-plane auto, the default, decides from the training images when they changed)")


def _is_torn_tail(f, end: int, size: int) -> bool:
    """Whether the bytes after the last valid record are one record cut short (a killed write), not a
    damaged record with more after it."""
    f.seek(end)
    head = f.read(20)
    if len(head) < 20 or head[:4] != TAG:
        return len(head) < 20
    (a,), (b,) = _U64.unpack(head[4:12]), _U64.unpack(head[12:20])
    return end + 20 + a + b + 4 > size


def payload_checksum_ok(f, record: LogRecord) -> bool:
    """Whether record's stored crc32 matches its meta and payload as they are in the file `f`
    (binary; record from `pointed_record`, whose sizes were checked against the file)."""
    meta_bytes = json.dumps(record.meta).encode()
    size = payload_size(record.meta)
    f.seek(record.offset)
    crc, remaining = zlib.crc32(meta_bytes), size
    while remaining:
        chunk = f.read(min(remaining, 1 << 24))
        if not chunk:
            return False
        crc = zlib.crc32(chunk, crc)
        remaining -= len(chunk)
    stored = f.read(4)
    return len(stored) == 4 and _U32.unpack(stored)[0] == crc


def _scan(f, size: int) -> tuple[list[LogRecord], int]:
    """Records with valid length, checksum and meta (`meta_problem`) from the current position; (records, end of the last)."""
    records: list[LogRecord] = []
    end = f.tell()
    while True:
        head = f.read(20)
        if len(head) < 20 or head[:4] != TAG:
            return records, end
        (a,), (b,) = _U64.unpack(head[4:12]), _U64.unpack(head[12:20])
        if end + 20 + a + b + 4 > size:
            return records, end
        meta_bytes = f.read(a)
        crc = zlib.crc32(meta_bytes)
        remaining = b
        while remaining:
            chunk = f.read(min(remaining, 1 << 24))
            crc = zlib.crc32(chunk, crc)
            remaining -= len(chunk)
        stored = f.read(4)
        try:
            meta = json.loads(meta_bytes)
            ok = _U32.unpack(stored)[0] == crc and meta_problem(meta) is None and payload_size(meta) == b
        except (ValueError, KeyError, TypeError, struct.error):
            ok = False
        if not ok:
            return records, end
        records.append(LogRecord(meta["name"], end + 20 + a, meta, end))
        end = f.tell()


class ShardWriter:
    """A view worker's own log (module docstring): the records of the views it computes, with their
    statistics, appended to a new file `<host>-<pid>-<random>.log` in `folder` (a restarted worker
    starts another file, so no two processes ever write one shard). `write(view)` returns the view
    as the driver gets it: no pairs, no statistics, `shard` pointing at its record, `present` set.
    """

    def __init__(self, folder: str | Path, params: dict):
        folder = Path(folder)
        host = socket.gethostname().replace("/", "_")
        self.file = f"{folder.name}/{host}-{os.getpid()}-{uuid.uuid4().hex[:12]}.log"
        self.log = PairLog.open(folder.parent / self.file, params)

    def write(self, view: ViewPairs) -> ViewPairs:
        self.log.append(view, with_stats=view.stats is not None)
        record = self.log.records[-1]
        del self.log.records[-1]  # the driver keeps the places; a worker's list would only grow
        none = np.zeros(0, np.int32)
        return dataclasses.replace(view, gaussians=none, masks=none, weights=np.zeros(0, np.float32), stats=None, chunk_starts=None,
                                   present=view.present_masks(), shard={"file": self.file, "offset": record.offset, "start": record.start,
                                                                        "meta": record.meta})

    def sync(self) -> None:
        """fsync the shard: the driver logs pointers to its records only after this."""
        self.log.sync()

    def close(self) -> None:
        self.log.close()
