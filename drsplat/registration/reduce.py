"""The partitioned reduce: a registration's Gaussian blocks finished by Ray tasks, not by the driver.

A run on Ray (`--ray`) in blocks (`--memory-budget`, `RegisterOptions.block_size`) writing a PLY
logs its views where they are computed: each view worker appends its views' records (pairs grouped
by Gaussian chunk, and the floater statistics of a `-reject` mode) to a shard of its own beside the
checkpoint (drsplat.registration.pairlog.ShardWriter), and the driver logs one pointer per view
(the shard, the record's place, its mask embeddings and the masks that reached a Gaussian). The
driver never receives a pair. After the view pass, one reducer task per block (at most `workers`
at once)

    opens the pair log read-only by its path          (storage every node shares: module note below)
    replays it keeping its block's pairs, in view order   LogSink / VoteSink.block_sums; pointers lead into the shards
    folds its block's floater statistics in view order    block_support: SurfaceSupport.add, the driver's fold
    runs the mode's finish step on its block              reject_rows with the block's rejected mask
    normalises, prunes, encodes with the codebook         normalize_rows, output.encode_rows
    writes its rows to a part file, returns its counts    PartResult: rows, non-finite, rejected, W

and the driver assembles header + parts into the output atomically (`assemble_parts`), streaming
each part in chunks. The bytes are the local run's: a Gaussian's pairs reach its row in the log's
order in every block replay (the sums are the same bits), its statistics are folded in view order
(the same bits, so the same rejected mask), the rows are encoded by the same code, and `lang_meta`
(row i holds byte i mod L of the field comment, i the row's index in the whole file) is patched
while streaming: part b's rows are numbered from the prefix sum of the kept rows of blocks
0 .. b-1, known only once every reducer is done (they run at the same time). A file of fewer rows
than L gets its widened columns (`_widen_meta_if_short`) exactly as a single write.

Codebooks: `none` and a faiss file are the same object for every reducer (the codebook file
beside the output is written once, by the driver, after the assembled body and just before its
rename, so that an earlier output of that name keeps its own until then); `--codebook scene`
is trained on the masks' embeddings topped up with a sample of the Gaussians that will be
assigned: the reducers first tell which those are (`candidates_block`, one task per block: weight
received and not rejected), then sum the sampled ones (`BlockReduce.sample`, one task per block
holding sampled ids: the same rows, the same bits as the driver's LogSink.sample), so it gives the
local run's codebook and bytes. Every aggregation mode is supported; the vote stage's mask
clusters (made on the driver in view order from the pointers' embeddings) go to every reducer. A
`check-` mode's masks are judged before any block is summed, since the verdicts need every block's
pairs:
1. each reducer sums its block's part of the support tables (`support_block`, one task per block:
   the block's votes folded, then its pairs' support, in fixed point) into a file in the parts
   folder, a run of a view's masks at a time;
2. the driver adds the parts (integers, exact in any order: the one-block tables), reading a
   file in when it fits its tables' memory cap and from where it lies otherwise, and judges;
3. the job carries the verdicts (`keep`); for `-vote` the driver makes the kept masks' clusters
   (a kept mask keeps every pair, so the masks left with pairs are the kept ones among the masks
   each view reported present);
4. each reducer sums its block's kept pairs (check.KeptPairs). The driver replays no pair.

Shared storage: workers write their shards, reducers open the log and the shards and write their
parts by path, beside the output (the checkpoint's folder). On a local (multi-node) cluster that is
the same file system; a cluster of several machines needs that folder on storage they all mount at
the same path (NFS, ...). A worker that cannot write its shard, or a reducer that cannot read the
log, fails with an error that says so.

Left on the driver: the scene, per view a pointer and its masks' embeddings (the vote's clusters),
and the result's weights [N] float32 (each reducer returns its block's W); nothing of size N x D,
no pair and no per-Gaussian statistic (a `check-` mode's judging keeps every view's support table,
added from the reducers' parts, and its [M] flags per view).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import socket
import tempfile
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drsplat.cluster import TASK_RETRIES, WAIT_SECONDS, ClusterOptions, connect, disconnect, import_ray, set_worker_threads
from drsplat.errors import DrsplatError
from drsplat.lang import META_PROPERTY, Codebook
from drsplat.memory import peak_rss
from drsplat.registration.aggregate import SurfaceSupport, ViewStats, reject_rows
from drsplat.registration.check import CheckSink, KeptPairs, SupportFile, write_block_supports
from drsplat.registration.output import _meta_period, _widen_meta_if_short, encode_rows, write_codebook_of
from drsplat.registration.pairlog import LogRecord, PairLog, ShardError
from drsplat.registration.plan import WRITE_CHUNK
from drsplat.registration.sink import LogSink
from drsplat.registration.sums import RowFates, normalize_rows
from drsplat.registration.vote import CLUSTER_COSINE, MaskClusters, Specificity, VoteSink
from drsplat.scene import GaussianScene, ply_header
from drsplat.utils import TEMP_SUFFIX, CancelToken, atomic_path, temp_prefix, work_folder

log = logging.getLogger(__name__)

COPY_ROWS = WRITE_CHUNK  # rows of a part read, patched and written at a time by the driver


@dataclass(frozen=True)
class ReduceJob:
    """What every reducer of one registration shares (put in the object store once).

    log_path / params / records: the pair log and what its writer knows of it. block: Gaussians
    per block (the last one shorter). clusters: the vote stage's mask clusters, None without it.
    out / clip_model / clip_weights: the output (names the codebook in the field comment), the embedding
    space's id and its weights file's digest (or None). parts_dir: where the parts are written (beside the output). reject: the mode rejects
    floaters and the views' statistics are in the log's shards: each reducer folds its block's.
    keep: a `check-` mode's verdicts, judged by the driver (per view [M] bool: the kept masks), so
    that each reducer sums its block's kept pairs (drsplat.registration.check.KeptPairs); None
    otherwise. check_clusters / check_slots: before the verdicts, a `check-` mode's mask clusters
    (per view [M] int32, and K) and vote slots, from which each reducer sums its block's part of
    the support tables (`support_block`). trim: the vote's θ (drsplat.registration.vote.trim_cosine:
    after a check, from its like cosine). pair_means: with the vote's step 4 (specificity), each
    view's [M] mean pair weights from the driver's judging (MaskVerdicts.pair_means); None otherwise.
    """

    log_path: str
    params: dict
    records: list[LogRecord]
    num_gaussians: int
    dim: int
    block: int
    keep_unassigned: bool
    clusters: MaskClusters | None
    out: str
    clip_model: str
    parts_dir: str
    reject: bool = False
    clip_weights: str | None = None
    keep: list[np.ndarray] | None = None
    check_clusters: list[np.ndarray] | None = None
    check_num_clusters: int = 0
    check_slots: int = 0
    trim: float = CLUSTER_COSINE
    pair_means: list[np.ndarray] | None = None

    @property
    def num_blocks(self) -> int:
        return -(-self.num_gaussians // self.block)

    def bounds(self, index: int) -> tuple[int, int]:
        lo = index * self.block
        return lo, min(self.num_gaussians, lo + self.block)

    def part_path(self, index: int) -> Path:
        return Path(self.parts_dir) / f"block{index:06d}.part"

    def support_path(self, index: int) -> Path:
        """Where block `index`'s part of a `check-` mode's support tables is written."""
        return Path(self.parts_dir) / f"block{index:06d}.support"


@dataclass
class PartResult:
    """One reducer's block: rows kept and written to `path`; header: (vertex dtype, comments) of its
    first chunk; weights [hi - lo] float32 W after finishing (0 = unassigned); fates: what the
    normalisation dropped or found weak (`RowFates`); rejected: Gaussians dropped by the mode; sum_seconds / sum_cpu_seconds: the replay;
    seconds: the whole task; pid / peak_rss: the worker."""

    index: int
    lo: int
    hi: int
    rows: int
    header: tuple
    weights: np.ndarray
    fates: RowFates
    rejected: int
    path: str
    sum_seconds: float
    sum_cpu_seconds: float
    seconds: float
    pid: int
    peak_rss: int


def open_log(job: ReduceJob, index: int) -> PairLog:
    """The job's pair log, opened read-only here (a worker process, maybe on another node);
    DrsplatError naming the block and the path when this process cannot read that log."""
    lo, hi = job.bounds(index)
    try:
        return PairLog.reader(job.log_path, job.params, job.records)
    except (OSError, ValueError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise DrsplatError(
            f"the reducer of block {index} (Gaussians {lo:,}..{hi - 1:,}) on {socket.gethostname()} cannot read the pair log "
            f"{job.log_path} ({why}): the partitioned reduce needs the output's folder on storage every Ray node shares at the same path"
        ) from None


@contextmanager
def shard_errors(index: int | None, lo: int = 0, hi: int = 0):
    """A worker's shard that this reducer (index: its block), or the driver (index None: the mask check, which reads the
    views' pairs from the shards; round 60b: a raw traceback), cannot read becomes one DrsplatError naming who read it,
    the file and the shared storage the partitioned reduce needs."""
    try:
        yield
    except ShardError as exc:
        who = f"the reducer of block {index} (Gaussians {lo:,}..{hi - 1:,})" if index is not None else "the mask check on the driver"
        raise DrsplatError(f"{who} on {socket.gethostname()}: {exc}: the partitioned reduce needs the output's folder on storage every "
                           "Ray node shares at the same path") from None


def block_sink(job: ReduceJob, plog: PairLog) -> LogSink | VoteSink:
    """The driver's kind of sink over `plog` (VoteSink with the driver's clusters for -vote modes),
    summing only the pairs a `check-` mode keeps (the driver's verdicts: job.keep)."""
    source = plog if job.keep is None else KeptPairs(plog, job.keep)
    if job.clusters is not None:
        specific = None if job.pair_means is None else Specificity(source, job.pair_means)
        exact = None if job.keep is None else source  # after a check the vote trims exactly, as the driver's sink does
        return VoteSink(job.num_gaussians, job.dim, source, job.block, clusters=job.clusters, trim=job.trim, specific=specific, exact=exact)
    return LogSink(job.num_gaussians, job.dim, source, job.block)


def reduce_block(job: ReduceJob, scene: GaussianScene, codebook: Codebook | str, index: int) -> PartResult:
    """Finish block `index` of `job` into its part file (module docstring): replay, the mode's
    finish (floater rejection with the block's own statistics, `block_support`, when job.reject),
    normalise, prune, encode. scene: the whole scene (rows lo .. hi-1 are read)."""
    t0 = time.perf_counter()
    lo, hi = job.bounds(index)
    c0 = time.process_time()
    with open_log(job, index) as plog, shard_errors(index, lo, hi):
        block = block_sink(job, plog).block_sums(lo, hi)
        rejected = block_support(plog, lo, hi).rejected() if job.reject else None
    sum_seconds, sum_cpu = time.perf_counter() - t0, time.process_time() - c0
    dropped = reject_rows(block.F, block.W, rejected) if rejected is not None else 0
    _, fates = normalize_rows(block.F, block.W, block.kept)
    keep = np.ones(hi - lo, bool) if job.keep_unassigned else block.W > 0
    path = job.part_path(index)
    rows, header = 0, None
    try:
        with open(path, "wb") as f:  # a retried task rewrites its part from the start
            for vertices, comments in encode_rows(scene, Path(job.out), job.clip_model, codebook, block, keep, 0, job.clip_weights):
                header = header or (vertices.dtype, comments)
                f.write(vertices.tobytes())
                rows += int(vertices.shape[0])
    except OSError as exc:
        raise DrsplatError(f"the reducer of block {index} could not write its part {path} ({exc.strerror or exc})") from None
    return PartResult(index, lo, hi, rows, header, np.array(block.W), fates, dropped, str(path), sum_seconds, sum_cpu,
                      time.perf_counter() - t0, os.getpid(), peak_rss())


def block_support(plog: PairLog, lo: int, hi: int) -> SurfaceSupport:
    """The floater statistics of Gaussians lo .. hi-1 (rows 0 .. hi-lo-1), folded from the log's
    records in view order exactly as the driver folds whole views (SurfaceSupport.add: per Gaussian,
    the same values in the same order, so the same bits and the same rejected mask)."""
    support = SurfaceSupport.zeros(hi - lo)
    for record in plog.records:
        stats = plog.read_stats_block(record, lo, hi)
        support.add(ViewStats(stats.ids - np.int32(lo), stats.peak, stats.total, stats.front))
    return support


def candidates_block(job: ReduceJob, index: int) -> np.ndarray:
    """[hi - lo] bool: the Gaussians of block `index` that some pair gave weight and the mode does
    not reject (the driver's `candidates` when the views were logged in shards)."""
    lo, hi = job.bounds(index)
    positive = np.zeros(hi - lo, bool)
    with open_log(job, index) as plog, shard_errors(index, lo, hi):
        for view in plog.block_views(lo, hi):
            positive[view.gaussians[view.weights > 0] - lo] = True
        if job.reject:
            positive &= ~block_support(plog, lo, hi).rejected()
    return positive


def sample_block(job: ReduceJob, index: int, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F [S, D], W [S]) of the Gaussians `ids` [S] (sorted, distinct, inside block `index`), summed
    from the log as the driver's sink would (a scene codebook's training sample)."""
    with open_log(job, index) as plog, shard_errors(index, *job.bounds(index)):
        return block_sink(job, plog).sample(ids)


def support_block(job: ReduceJob, index: int) -> SupportFile:
    """Block `index`'s part of a `check-` mode's support tables, every view's, written to a file in
    the parts folder (check.write_block_supports: the block's votes folded, then its pairs' support,
    two replays of the block, written a run of masks at a time): the driver adopts every block's
    file, adds the parts exactly, and judges the masks from the sums."""
    lo, hi = job.bounds(index)
    path = job.support_path(index)
    with open_log(job, index) as plog, shard_errors(index, lo, hi):
        try:
            return write_block_supports(path, plog.block_views(lo, hi), plog.block_views(lo, hi), job.check_clusters, job.check_num_clusters, lo,
                                        hi, job.check_slots)
        except OSError as exc:
            raise DrsplatError(f"the reducer of block {index} could not write its support tables {path} ({exc.strerror or exc})") from None


def _support_task(job, index):
    set_worker_threads()
    return support_block(job, index)


def _reduce_task(job, scene, codebook, index):
    """Ray task around `reduce_block` (numba threads = the CPUs Ray gave it)."""
    set_worker_threads()
    return reduce_block(job, scene, codebook, index)


def _sample_task(job, index, ids):
    set_worker_threads()
    return sample_block(job, index, ids)


def _candidates_task(job, index):
    set_worker_threads()
    return candidates_block(job, index)


# ----------------------------------------------------------------------------- the driver's side


def assemble_parts(out: Path, parts: list[PartResult], codebook: Codebook | str = "none") -> int:
    """Header + the parts, in block order, into `out` (atomically): each part streamed COPY_ROWS
    rows at a time with its `lang_meta` rows renumbered from the kept rows before it, so the bytes
    are those of a single write (drsplat.registration.output.PlyTarget). Returns the rows written.
    codebook: written beside `out` after the body, just before the rename (`write_codebook_of`).

    The header is the first block's (its dtype and comments, as PlyTarget takes its first chunk's);
    a file of fewer rows than the field comment's length gets the widened `lang_meta_*` columns.
    """
    if not parts or parts[0].header is None:
        raise DrsplatError(f"the scene has no Gaussians to write to {out}")
    dtype, comments = parts[0].header
    total = sum(p.rows for p in parts)
    period = _meta_period(comments) if META_PROPERTY in dtype.names else None
    if period is not None and total < period.shape[0]:  # a short file: a tiny body, widened as a single write widens it
        with tempfile.TemporaryDirectory(prefix=temp_prefix(out), suffix=TEMP_SUFFIX, dir=work_folder(out)) as tmp:
            body = Path(tmp) / "body"
            with open(body, "wb") as f:
                _copy_parts(f, parts, dtype, period)
            dtype, comments, _ = _widen_meta_if_short(body, (dtype, comments), total)
            with atomic_path(out) as target:
                with open(target, "wb") as f, open(body, "rb") as src:
                    f.write(ply_header(dtype, comments, total))
                    shutil.copyfileobj(src, f)
                write_codebook_of(codebook, out)
        return total
    with atomic_path(out) as target:
        with open(target, "wb") as f:
            f.write(ply_header(dtype, comments, total))
            _copy_parts(f, parts, dtype, period)
        write_codebook_of(codebook, out)
    return total


def _copy_parts(f, parts: list[PartResult], dtype: np.dtype, period: np.ndarray | None) -> None:
    """Append the parts' rows to `f`; `lang_meta` row i of the file = period[i mod L]."""
    first = 0
    buffer = np.empty(COPY_ROWS, dtype)  # one chunk, read into, patched and written in place (no copies)
    for part in parts:
        size = os.path.getsize(part.path)
        if size != part.rows * dtype.itemsize:
            raise DrsplatError(f"the part of block {part.index} ({part.path}) holds {size} bytes, its reducer wrote {part.rows} rows of {dtype.itemsize}")
        with open(part.path, "rb") as src:
            for start in range(0, part.rows, COPY_ROWS):
                rows = buffer[: min(COPY_ROWS, part.rows - start)]
                src.readinto(memoryview(rows).cast("B"))
                if period is not None:
                    rows[META_PROPERTY] = period[(first + start + np.arange(rows.shape[0])) % period.shape[0]]
                f.write(memoryview(rows).cast("B"))
        first += part.rows


def wants_reducers(place: str, reducers: bool, block: int, num_gaussians: int, writes_ply: bool) -> bool:
    """Whether a run finishes its blocks with reducers: on Ray, in blocks, writing a PLY (features
    kept in memory, `register_features`, are finished by the driver), not switched off. In a
    `check-` mode the driver judges the masks first (its verdicts need every block's pairs before
    any block is summed: replays of the pair log, no D-dimensional work) and the reducers sum the
    kept pairs."""
    return place == "ray" and reducers and block < num_gaussians and writes_ply


class ReducePool:
    """The Ray connection of a run whose blocks reducers finish: opened before the view pass (so
    the executor joins it and it outlives the executor), closed after the output is written.

    workers: reducer tasks at once (default: the cluster's CPUs).
    """

    def __init__(self, cluster: ClusterOptions, cancel: CancelToken | None = None):
        """cancel: checked while reducers run (a cancelled run stops them and keeps its checkpoint)."""
        ray = import_ray()
        self.cancel = cancel
        self._owns = connect(cluster.address)
        self.workers = int(cluster.workers or max(1, int(ray.cluster_resources().get("CPU", 1))))
        self.worker_peak_rss: dict[int, int] = {}

    def close(self) -> None:
        disconnect(self._owns)
        self._owns = False

    def reduce(self, job: ReduceJob, scene: GaussianScene, codebook: Codebook | str) -> list[PartResult]:
        """Every block of `job` through a reducer task, at most `workers` at once; the parts in block
        order. A failed reducer (after Ray's retries) is a DrsplatError naming its block; the others
        are cancelled."""
        ray = import_ray()
        task = ray.remote(num_cpus=1, max_retries=TASK_RETRIES)(_reduce_task)
        job_ref, scene_ref, book_ref = ray.put(job), ray.put(scene), ray.put(codebook)

        results = self._run(job, lambda index: task.remote(job_ref, scene_ref, book_ref, index))
        for part in results:
            self.worker_peak_rss[part.pid] = max(part.peak_rss, self.worker_peak_rss.get(part.pid, 0))
        return results

    def sample(self, job: ReduceJob, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F [S, D], W [S]) of the sorted distinct Gaussians `ids` [S]: one task per block holding
        some of them, concatenated in block order (= the order of `ids`)."""
        ray = import_ray()
        task = ray.remote(num_cpus=1, max_retries=TASK_RETRIES)(_sample_task)
        job_ref = ray.put(job)
        cuts = np.searchsorted(ids, np.arange(job.num_blocks + 1) * job.block)
        blocks = [b for b in range(job.num_blocks) if cuts[b + 1] > cuts[b]]
        parts = self._run(job, lambda i: task.remote(job_ref, blocks[i], ids[cuts[blocks[i]] : cuts[blocks[i] + 1]]), len(blocks), blocks)
        if not parts:
            return np.zeros((0, job.dim), np.float32), np.zeros(0, np.float32)
        return np.concatenate([F for F, _ in parts]), np.concatenate([W for _, W in parts])

    def supports(self, job: ReduceJob, add: Callable[[SupportFile], None]) -> None:
        """`support_block` of every block, one task each: each block's file of a `check-` mode's
        support tables handed to `add` as it arrives, in any order (check.Supports adds them as
        integers, reading them in or from where they are), so that neither the reducers nor the
        driver hold every view's part of a block at once."""
        ray = import_ray()
        task = ray.remote(num_cpus=1, max_retries=TASK_RETRIES)(_support_task)
        job_ref = ray.put(job)
        def take(index: int, part: SupportFile) -> None:
            if Path(part.path) != job.support_path(index):  # the driver reads and then removes it: only the file the job names
                raise DrsplatError(f"the reducer of block {index} returned the support file {part.path}, not {job.support_path(index)}")
            add(part)

        self._run(job, lambda i: task.remote(job_ref, i), take=take)

    def candidates(self, job: ReduceJob) -> np.ndarray:
        """[N] bool, `candidates_block` of every block, one task each."""
        ray = import_ray()
        task = ray.remote(num_cpus=1, max_retries=TASK_RETRIES)(_candidates_task)
        job_ref = ray.put(job)
        return np.concatenate(self._run(job, lambda i: task.remote(job_ref, i)))

    def _run(self, job: ReduceJob, submit, count: int | None = None, names: list[int] | None = None,
             take: Callable[[int, object], None] | None = None) -> list:
        """submit(i) for i < count (default: every block), `workers` in flight; results in order, or
        each handed to take(i, result) as it arrives and not kept (the list is then of None)."""
        ray = import_ray()
        count = job.num_blocks if count is None else count
        names = names or list(range(count))
        results: list = [None] * count
        pending: dict = {}
        submitted = 0
        try:
            while submitted < count or pending:
                while submitted < count and len(pending) < self.workers:
                    pending[submit(submitted)] = submitted
                    submitted += 1
                ready, _ = ray.wait(list(pending), num_returns=1, timeout=WAIT_SECONDS)
                if self.cancel is not None:
                    self.cancel.raise_if_cancelled()
                for ref in ready:
                    i = pending.pop(ref)
                    if take is None:
                        results[i] = _get(ref, job, names[i])
                    else:
                        take(i, _get(ref, job, names[i]))
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)
        return results


def _get(ref, job: ReduceJob, index: int):
    ray = import_ray()
    lo, hi = job.bounds(index)
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as exc:
        cause = exc.cause if isinstance(getattr(exc, "cause", None), BaseException) else exc
        if isinstance(cause, DrsplatError):
            raise DrsplatError(str(cause)) from None
        raise DrsplatError(f"the reducer of block {index} (Gaussians {lo:,}..{hi - 1:,}) failed: {type(cause).__name__}: {cause}") from None
    except ray.exceptions.RayError as exc:  # the worker died more than TASK_RETRIES times, node lost, ...
        raise DrsplatError(f"the reducer of block {index} (Gaussians {lo:,}..{hi - 1:,}) failed after {TASK_RETRIES} retries: {exc}") from None


def make_job(plog: PairLog, num_gaussians: int, dim: int, block: int, keep_unassigned: bool, clusters: MaskClusters | None, out: Path,
             clip_model: str, reject: bool = False, check: CheckSink | None = None, clip_weights: str | None = None) -> ReduceJob:
    """The job of a run whose view pass is done: the log synced to storage, a parts folder beside
    `out` (a temp folder named after `out`, swept if a killed run leaves it). reject: the reducers
    fold the floater statistics from the log's shards. check: a `check-` mode's sink, whose mask
    clusters and slots let the reducers sum the support tables (`judged` then adds the verdicts)."""
    plog.sync()
    parts = tempfile.mkdtemp(prefix=temp_prefix(out), suffix=TEMP_SUFFIX, dir=work_folder(out))
    job = ReduceJob(str(Path(plog.path).resolve()), plog.params, list(plog.records), num_gaussians, dim, block, keep_unassigned,
                    clusters, str(out), clip_model, parts, reject, clip_weights)
    if check is not None:
        job = dataclasses.replace(job, check_clusters=list(check.clusters.per_view), check_num_clusters=check.clusters.count,
                                  check_slots=check.slots)
    return job


def judged(job: ReduceJob, keep: list[np.ndarray]) -> ReduceJob:
    """The job once a `check-` mode's masks are judged: the reducers get the verdicts `keep` (per
    view [M] bool; each reducer finds its own block's Gaussians with a kept pair); the clusters
    for the support are dropped. A `-vote` mode then adds the kept masks' clusters (`clusters`)."""
    return dataclasses.replace(job, keep=keep, check_clusters=None, check_num_clusters=0, check_slots=0)


class BlockReduce:
    """One run's reduce on `pool`: the scene codebook's sample (`sample`, what the driver's sink
    would give) and the blocks (`finish`)."""

    def __init__(self, pool: ReducePool, job: ReduceJob):
        self.pool, self.job = pool, job

    def sample(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.pool.sample(self.job, ids)

    def candidates(self) -> np.ndarray:
        """[N] bool: the Gaussians that will be assigned (a scene codebook samples them)."""
        return self.pool.candidates(self.job)

    def finish(self, scene: GaussianScene, codebook: Codebook | str, aggregator) -> tuple[list[PartResult], np.ndarray]:
        """Every block finished by a reducer (`aggregator`: the run's Aggregator, whose num_rejected
        gets the reducers' counts: each reducer folds its own block's floater statistics). Returns
        (the parts in block order, weights [N] float32: the result's W)."""
        t0 = time.perf_counter()
        parts = self.pool.reduce(self.job, scene, codebook)  # the driver writes its file when it assembles the parts
        log.info("%d blocks finished by reducer tasks (%d at once) in %.1f s", len(parts), self.pool.workers, time.perf_counter() - t0)
        weights = np.zeros(self.job.num_gaussians, np.float32)
        for part in parts:
            weights[part.lo : part.hi] = part.weights
            part.weights = None  # the result's copy is enough
            aggregator.num_rejected += part.rejected
        return parts, weights

    def close(self) -> None:
        """Remove the parts folder (written or not)."""
        shutil.rmtree(self.job.parts_dir, ignore_errors=True)
