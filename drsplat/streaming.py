"""Registration under a memory budget: Gaussian blocks streamed from the pair log to the PLY.

In-memory registration holds the sums F [N, D] float32 (5M Gaussians x 512 x 4 B = 10 GB) and,
while writing, the field and the PLY rows: about 10·N·D bytes at its peak. Streaming never holds
anything N x D:

1. Views (once each, over the whole scene): rasterize, coalesce the view's distinct
   (Gaussian, mask) pairs and append them to the pair log (drsplat.pairlog, which is also the
   checkpoint). Only [N]-sized scratch is kept (~12 B per Gaussian) next to the scene geometry.
   Rasterizing a view with only a block's Gaussians (`rasterize(mask=...)`) would drop the
   occluders of other blocks and change T·α, so views are rendered whole, exactly once, and the
   pairs are split by block afterwards.
2. Blocks of B consecutive Gaussian ids: replay the log keeping the block's pairs into
   F [B, D], normalise, build the field of the block (fp16 or PQ codes), and append the
   block's PLY rows to a body file. Per Gaussian the pairs are added in exactly the order of
   the in-memory path, so the sums, and the file, are the same bit for bit.
3. The header (its vertex count is known only now) and the body are joined into the output,
   atomically.

Peak memory: the scene + its prepared geometry (~101 B per Gaussian) + one view (projection
~160 B per Gaussian, its top-k buffers and pairs) in step 1; the scene + ~10·B·D bytes in step 2.
`estimate_memory` turns that into a plan and a block size for a budget.
"""

from __future__ import annotations

import logging
import os
import re
import resource
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drsplat.cameras import Camera
from drsplat.defaults import DEFAULT_AGGREGATE
from drsplat.errors import DrsplatError
from drsplat.registration import (
    CHECKPOINT_EVERY,
    Accumulator,
    RegistrationResult,
    ViewTotals,
    checkpoint_params,
    normalize_rows,
    open_checkpoint,
    prepare_geometry,
    run_views,
    select_views,
    start_aggregation,
    track_aggregation,
)
from drsplat.scene import GaussianScene, ply_header, scene_to_vertices
from drsplat.utils import CancelToken, atomic_path, progress

log = logging.getLogger(__name__)

GEOMETRY_BYTES = 101  # prepare_geometry: means, covariances (float64), opacity, finite flag
PROJECTION_BYTES = 160  # one view's Projected arrays, depth order keys and tile lists, per Gaussian
SCRATCH_BYTES = 12  # the coalescer's seen / acc / touched arrays
PAIR_BYTES = 12  # one distinct (Gaussian, mask, weight) pair
OUTPUT_COPIES = 10  # bytes per Gaussian per embedding value while a block (or the whole field) is written
BLOCK_ALIGN = 1024  # block starts keep the in-memory path's row alignment and chunking
OVERHEAD = 256 << 20  # interpreter, numba, faiss, buffers not counted above

_UNITS = {"": 1, "b": 1, "k": 1e3, "kb": 1e3, "m": 1e6, "mb": 1e6, "g": 1e9, "gb": 1e9, "t": 1e12, "tb": 1e12,
          "kib": 1 << 10, "mib": 1 << 20, "gib": 1 << 30, "tib": 1 << 40}


def parse_size(text: str) -> int:
    """'8GB', '8 GiB', '512MB', '1e9' -> bytes (GB = 10^9, GiB = 2^30)."""
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:e[0-9]+)?)\s*([a-zA-Z]*)\s*", str(text))
    if not match or match.group(2).lower() not in _UNITS:
        raise ValueError(f"{text!r} is not a size (examples: 8GB, 512MB, 16GiB)")
    value = float(match.group(1)) * _UNITS[match.group(2).lower()]
    if not np.isfinite(value) or value <= 0:
        raise ValueError(f"{text!r} is not a positive size")
    return int(value)


def format_size(n: float) -> str:
    return f"{n / 1e9:.1f} GB" if n >= 1e9 else f"{n / 1e6:.0f} MB"


def _proc_bytes(path: str, key: str) -> int:
    """The `key:` line of a /proc file (in kB there) in bytes; 0 when unknown."""
    try:
        for line in Path(path).read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def available_memory() -> int:
    """MemAvailable of /proc/meminfo in bytes (0 when unknown)."""
    return _proc_bytes("/proc/meminfo", "MemAvailable")


def current_rss() -> int:
    """Resident memory of this process now (VmRSS), in bytes."""
    return _proc_bytes("/proc/self/status", "VmRSS")


def peak_rss() -> int:
    """Peak resident memory of this process so far (ru_maxrss), in bytes."""
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


@dataclass
class MemoryPlan:
    """Estimated peak resident memory of a registration (bytes), in memory and streamed.

    base: what the process holds already (the loaded scene, libraries). views: the view pass
    (geometry + one view + scratch). in_memory: the peak of the in-memory path. per_gaussian:
    bytes per Gaussian of a streamed block (its sums and output rows).
    """

    num_gaussians: int
    dim: int
    base: int
    views: int
    in_memory: int
    per_gaussian: int

    def streaming(self, block: int) -> int:
        """Peak of the streamed path with blocks of `block` Gaussians."""
        return max(self.views, self.base + OVERHEAD + block * self.per_gaussian)

    def block_for(self, budget: int) -> int:
        """The largest aligned block that fits `budget` (0 when even the view pass does not)."""
        if self.views > budget:
            return 0
        room = budget - self.base - OVERHEAD
        block = room // self.per_gaussian // BLOCK_ALIGN * BLOCK_ALIGN
        return int(min(max(block, 0), -(-self.num_gaussians // BLOCK_ALIGN) * BLOCK_ALIGN))


def estimate_memory(scene: GaussianScene, views: Sequence[Camera], dim: int, topk: int, base: int | None = None,
                    aggregate: str = DEFAULT_AGGREGATE) -> MemoryPlan:
    """Estimate the peak memory of registering `views` onto `scene` with `dim`-D embeddings
    (and the statistics of aggregation mode `aggregate`, kept until the sums are finished)."""
    from drsplat.aggregate import Aggregator

    n = scene.num_gaussians
    pixels = max((c.width * c.height for c in views), default=0)
    mode_views, mode_kept = Aggregator.memory_bytes(aggregate, n, pixels, topk)
    base = (current_rss() if base is None else base) + mode_kept
    view = n * (PROJECTION_BYTES + SCRATCH_BYTES) + pixels * topk * (8 + 2 * PAIR_BYTES) + mode_views - mode_kept
    views_peak = base + OVERHEAD + n * GEOMETRY_BYTES + view
    accumulate = n * (4 * dim + 16) + max(1 << 23, n) * PAIR_BYTES
    row_bytes = scene.sh.shape[1] * 12 + 64
    in_memory = max(views_peak + accumulate, base + OVERHEAD + n * (OUTPUT_COPIES * dim + 2 * row_bytes))
    per_gaussian = OUTPUT_COPIES * dim + 2 * row_bytes + 32
    return MemoryPlan(n, dim, base, views_peak, in_memory, per_gaussian)


def choose_block(plan: MemoryPlan, budget: int | None, available: int | None = None) -> int | None:
    """None to register in memory, else the block size to stream with.

    budget None: in memory when the estimate fits the memory available now, otherwise a
    DrsplatError with the figure and the --memory-budget that fits. With a budget: in memory
    when it fits the budget, else streamed blocks; an error when even one view does not fit.
    """
    if budget is None:
        free = (available_memory() if available is None else available) + current_rss()
        if free == 0 or plan.in_memory <= 0.9 * free:
            return None
        fits = int(0.8 * free)
        hint = (f"rerun with --memory-budget {fits / 1e9:.0f}GB to stream Gaussians in blocks (same result)"
                if plan.block_for(fits) > 0 else
                f"even streamed, one view needs about {format_size(plan.views)}; use a machine with more memory or fewer, smaller views")
        raise DrsplatError(
            f"registering {plan.num_gaussians:,} Gaussians with {plan.dim}-D features in memory needs about "
            f"{format_size(plan.in_memory)}, but only {format_size(free)} is available: {hint}"
        )
    if plan.in_memory <= budget:
        return None
    block = plan.block_for(budget)
    if block <= 0:
        raise DrsplatError(
            f"--memory-budget {format_size(budget)} is too small for this scene: the view pass alone (scene, geometry, "
            f"one view) needs about {format_size(plan.views)}; give at least {format_size(plan.views + plan.per_gaussian * BLOCK_ALIGN)}"
        )
    return block


# ----------------------------------------------------------------------------- the streamed path


@dataclass
class StreamResult:
    """What `register_streaming` wrote and how."""

    registration: RegistrationResult
    num_written: int
    num_blocks: int
    block_size: int
    log_bytes: int
    field_kind: str
    view_seconds: float
    block_seconds: float


def register_streaming(
    scene: GaussianScene,
    cameras: Sequence[Camera],
    features_dir: str | Path,
    out: str | Path,
    *,
    block_size: int,
    checkpoint: str | Path,
    topk: int,
    level: int,
    codebook="none",
    clip_model: str = "unknown",
    keep_unassigned: bool = False,
    executor=None,
    show_progress: bool = True,
    on_progress: Callable[[int, int], None] | None = None,
    cancel: CancelToken | None = None,
    aggregate: str = DEFAULT_AGGREGATE,
    engine: str = "numba",
    device: str = "cpu",
) -> StreamResult:
    """Register and write the registered PLY `out` in Gaussian blocks of `block_size` (module docstring).

    executor: None (views rasterized in this process with `engine` on `device`) or a RayExecutor
    (which runs the mode's per-view hook on its workers). aggregate: the aggregation mode (drsplat.aggregate); its per-Gaussian
    statistics stay in memory and are snapshotted beside the pair log.

    codebook: "none", "scene" (trained on the scene's mask embeddings) or a loaded
    drsplat.lang.Codebook. checkpoint: the pair log; it is kept (the caller deletes it after
    the output is safe) and a rerun resumes from it.
    The file equals `drsplat.pipeline.register_to_ply`'s in-memory output byte for byte.
    """
    t_start = time.perf_counter()
    features_dir, out, checkpoint = Path(features_dir), Path(out), Path(checkpoint)
    if block_size < 1:
        raise ValueError("block_size must be >= 1")
    views, missing, unmatched = select_views(cameras, features_dir)
    plog = open_checkpoint(checkpoint, checkpoint_params(scene, views, features_dir, topk, level, aggregate), views)
    totals = ViewTotals()
    stats_path = None
    try:
        aggregator, stats_path, executor = start_aggregation(aggregate, scene, plog, checkpoint, executor, engine, device)
        resumed = len(plog.records)

        def consume(view) -> None:
            totals.add(view, features_dir, codebook == "scene")
            track_aggregation(aggregator, view, totals.done, resumed, stats_path, CHECKPOINT_EVERY)

        prepared = executor.prepare(scene) if hasattr(executor, "prepare") else prepare_geometry(scene)
        run_views(prepared, views, features_dir, level, topk, consume, plog=plog, executor=executor, checkpoint_every=CHECKPOINT_EVERY,
                  show_progress=show_progress, on_progress=on_progress, cancel=cancel)
        del prepared
        view_seconds = time.perf_counter() - t_start
        book = _codebook_for(codebook, totals)
        totals.embeddings = []
        weights, written, blocks, nonfinite = _write_blocks(scene, plog, features_dir, out, block_size, totals.dim or 1, book, clip_model, keep_unassigned,
                                                            show_progress, cancel, aggregator)
        aggregator.log_rejected()
        log_bytes = plog.nbytes
    finally:
        plog.close()
    seconds = time.perf_counter() - t_start
    result = RegistrationResult(
        features=None, weights=weights, num_views=totals.done, num_pairs=totals.num_pairs, num_distinct_pairs=totals.num_distinct,
        seconds=seconds, raster_seconds=totals.raster_seconds, accumulate_seconds=totals.coalesce_seconds,
        coalesce_seconds=totals.coalesce_seconds, resumed_views=resumed,
        topk=topk, level=level, missing_features=missing, unmatched_features=unmatched, num_nonfinite_masks=totals.num_nonfinite_masks,
        num_nonfinite_features=nonfinite, aggregate=aggregate, num_rejected=aggregator.num_rejected,
    )
    kind = "exact" if book == "none" else book.kind
    return StreamResult(result, written, blocks, block_size, log_bytes, kind, view_seconds, seconds - view_seconds)


def _codebook_for(codebook, totals: ViewTotals):
    """'none', or a Codebook (loaded by the caller, or trained here on the scene's mask embeddings)."""
    from drsplat.lang import train_codebook
    from drsplat.lang.field import SCENE_MIN_TRAIN

    if not (isinstance(codebook, str) and codebook == "scene"):
        return codebook
    train = np.concatenate(totals.embeddings) if totals.embeddings else np.zeros((0, totals.dim or 1), np.float32)
    if train.shape[0] < SCENE_MIN_TRAIN:
        raise DrsplatError(
            f"a scene codebook trained while streaming needs at least {SCENE_MIN_TRAIN} mask embeddings, the scene has "
            f"{train.shape[0]}; register in memory (no --memory-budget), or use --codebook none or a general codebook"
        )
    return train_codebook(train, m=128, seed=0)


def _write_blocks(scene, plog, features_dir: Path, out: Path, block_size: int, dim: int, book, clip_model: str, keep_unassigned: bool, show_progress: bool, cancel,
                  aggregator=None):
    """Sum, (reject: drop the aggregator's rejected Gaussians,) normalise, encode and write each
    block; then header + body -> `out` (atomic).

    Returns (weights [N] float32, Gaussians written, blocks, Gaussians dropped for non-finite sums).
    """
    from drsplat.lang import attach_field, build_field

    n = scene.num_gaussians
    weights = np.zeros(n, np.float32)
    starts = list(range(0, n, block_size))
    written = nonfinite = 0
    header = None
    fd, body_name = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".body.tmp", dir=out.parent)
    body_path = Path(body_name)
    try:
        with os.fdopen(fd, "wb") as body:
            for lo in progress(starts, desc="blocks", total=len(starts), enabled=show_progress, unit="block"):
                if cancel is not None:
                    cancel.raise_if_cancelled()
                hi = min(n, lo + block_size)
                F, W = _block_sums(plog, lo, hi, dim)
                if aggregator is not None:
                    aggregator.finish(F, W, lo)
                F, bad = normalize_rows(F, W)
                nonfinite += bad
                weights[lo:hi] = W
                keep = np.ones(hi - lo, bool) if keep_unassigned else W > 0
                field = build_field(F[keep], W[keep], codebook=book, clip_model=clip_model)
                del F
                part = _with_meta_rows(attach_field(scene.subset(slice(lo, hi)).subset(keep), field, out), written)
                vertices = scene_to_vertices(part)
                header = header or (vertices.dtype, part.comments)
                body.write(vertices.tobytes())
                written += int(vertices.shape[0])
                del field, part, vertices
        if header is None:
            raise DrsplatError("the scene has no Gaussians to register")
        if not np.any(weights > 0):
            from drsplat.pipeline import nothing_assigned

            raise DrsplatError(nothing_assigned(len(plog.records), features_dir, out))
        header = _drop_meta_if_short(body_path, header, written)
        with atomic_path(out) as tmp:
            with open(tmp, "wb") as f, open(body_path, "rb") as src:
                f.write(ply_header(header[0], header[1], written))
                shutil.copyfileobj(src, f, 1 << 24)
    finally:
        body_path.unlink(missing_ok=True)
    if nonfinite:
        log.warning("%d Gaussians got non-finite feature sums and are left unassigned", nonfinite)
    return weights, written, len(starts), nonfinite


def _meta_period(comments: list[str]) -> np.ndarray | None:
    """One period of the `lang_meta` column of the field comment (None when it is not carried)."""
    from drsplat.lang import COMMENT_PREFIX, encode_meta_column

    comment = next((c for c in reversed(comments) if c.startswith(COMMENT_PREFIX)), "")
    text = comment[len(COMMENT_PREFIX):].strip()
    return encode_meta_column(text, len(text.encode("utf-8")))


def _with_meta_rows(part: GaussianScene, first_row: int) -> GaussianScene:
    """The block with its `lang_meta` rows numbered from `first_row`, as in the whole file.

    The column's row i holds byte i mod L of the field comment, so a block written alone would
    restart at 0 (and a block shorter than L would not carry the column at all).
    """
    import dataclasses

    from drsplat.lang import META_PROPERTY

    period = _meta_period(part.comments)
    if period is None:
        return part
    column = period[(first_row + np.arange(part.num_gaussians)) % period.shape[0]]
    extra = {}
    for name, values in part.extra.items():
        if name != META_PROPERTY:
            extra[name] = values
        if name == "lang_weight":
            extra[META_PROPERTY] = column
    return dataclasses.replace(part, extra=extra)


def _drop_meta_if_short(body_path: Path, header: tuple, written: int) -> tuple:
    """A file of fewer rows than the comment's length carries no `lang_meta` column (as in
    memory): rewrite the (then tiny) body without it. Returns the header's (dtype, comments)."""
    from drsplat.lang import META_PROPERTY

    dtype, comments = header
    period = _meta_period(comments)
    if META_PROPERTY not in dtype.names or period is None or written >= period.shape[0]:
        return header
    rows = np.fromfile(body_path, dtype)
    names = [n for n in dtype.names if n != META_PROPERTY]
    kept = np.empty(rows.shape[0], np.dtype([(n, dtype[n]) for n in names]))
    for n in names:
        kept[n] = rows[n]
    body_path.write_bytes(kept.tobytes())
    return kept.dtype, comments


def _block_sums(plog, lo: int, hi: int, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """F [hi - lo, D], W [hi - lo]: the log's pairs of Gaussians lo..hi-1, added in log order."""
    acc = Accumulator(hi - lo, dim)
    for record in plog.records:
        view = plog.read(record)
        sel = (view.gaussians >= lo) & (view.gaussians < hi)
        if sel.any():
            acc.add_pairs(view.gaussians[sel] - lo, view.masks[sel], view.weights[sel], view.feats)
    return acc.sums()
