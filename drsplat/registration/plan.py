"""The memory plan of a registration: one block of Gaussians (sums held in memory while the views
are computed) or many (sums per block, replayed from the pair log), chosen for a budget.

A registration holds the scene, its prepared geometry (~101 B per Gaussian), the culling index (40 B)
and one view in flight
(projection ~128 B per Gaussian, tile lists of at most `drsplat.raster.tile_list_cap` entries, its
top-k buffers and pairs) while views are computed, and the
sums F [B, D] float32 + W [B] of a block of B Gaussians. With one block (B = N) the sums are kept
as the views arrive; with several, views' pairs go to the pair log and each block replays it
(drsplat.registration.sink). Rows are encoded and written in chunks of at most WRITE_CHUNK
Gaussians either way, so the output costs ~10·D bytes per Gaussian of one chunk, not of the scene.
The vote, check and solve stages each keep the views' mask clusters until the sums are finished,
counted from the feature headers' mask counts as if every mask were its own cluster
(drsplat.registration.vote.cluster_bytes), and the check its views' unit embeddings
(drsplat.registration.check.check_units_bytes) and its support tables, held up to
SUPPORT_TABLE_BYTES and spilled to disk beyond (drsplat.registration.supports.table_bytes).
Rasterizing a view with only a block's Gaussians would drop the occluders of other blocks and
change T·α, so views are always rendered whole, exactly once.

`estimate_memory` turns that into a `MemoryPlan`, and `choose_block` into a block size for a budget.
The torch engine's device sums (drsplat.registration.device_sums.DeviceSink) are the one-block
plan's F and W on its device: on the CPU the same bytes as the host accumulator's (its chunked
update stands in for the pair buffer); on CUDA they are checked against the device's free memory
instead, and a plan of several blocks always sums on the host from the pair log.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

from drsplat.cameras import Camera
from drsplat.defaults import DEFAULT_AGGREGATE, SUPPORT_TABLE_BYTES
from drsplat.errors import DrsplatError
from drsplat.memory import available_memory, current_rss, format_size
from drsplat.raster import TILE_ENTRY_BYTES, tile_list_cap
from drsplat.registration.aggregate import Aggregator, mode_stages
from drsplat.registration.check import check_units_bytes, support_scratch_bytes
from drsplat.registration.coalesce import SCRATCH_BYTES, coalesce_parts
from drsplat.registration.sums import FLUSH_BYTES, PAIR_CAPACITY, PAIR_SLOT_BYTES, buffer_bytes, pair_capacity_for
from drsplat.registration.supports import table_bytes
from drsplat.registration.vote import cluster_bytes, trim_buffer_bytes
from drsplat.scene import GaussianScene

log = logging.getLogger(__name__)

GEOMETRY_BYTES = 101  # prepare_geometry: means, covariances (float64), opacity, finite flag
INDEX_BYTES = 40  # the culling index (drsplat.registration.culling.SpatialIndex): Morton order (int64), spread (float64), mean (3 float64)
PROJECTION_BYTES = 128  # one view's Projected arrays and depth order keys, per Gaussian (its tile lists: `tile_list_bytes`)
PAIR_BYTES = 12  # one distinct (Gaussian, mask, weight) pair
SUM_BYTES = 4 + FLUSH_BYTES  # per Gaussian of a block besides F's 4·D: W, and the counting sort of the accumulator's flush
OUTPUT_COPIES = 10  # bytes per Gaussian per embedding value while a chunk of rows is encoded and written
WRITE_CHUNK = 1 << 15  # Gaussians encoded and written at a time
BLOCK_ALIGN = 1024  # block sizes are multiples of this
OVERHEAD = 256 << 20  # interpreter, numba, faiss, buffers not counted above
# The process's resident memory, which the estimate starts from, differs by a few MB from run to
# run: the minimum a refusal names has this much room, so that typing it back is accepted.
NAMED_MINIMUM_ROOM = 16 << 20


@dataclass
class MemoryPlan:
    """Estimated peak resident memory of a registration, in bytes.

    base: what the process holds already (the loaded scene, libraries, the aggregation mode's
    statistics). views: the peak of the view pass without sums (geometry + one view + scratch).
    sum_bytes: per Gaussian of a block's sums (F row, W, sorting, the mode's slots). write_bytes: per Gaussian of
    a chunk being encoded and written. pair_buffer: the accumulator's buffers of pairs and mask embeddings (`sums.buffer_bytes`).
    """

    num_gaussians: int
    dim: int
    base: int
    views: int
    sum_bytes: int
    write_bytes: int
    pair_buffer: int

    def peak(self, block: int) -> int:
        """Peak with blocks of `block` Gaussians (block >= N: one block, summed while views run)."""
        n = self.num_gaussians
        write = min(block, n, WRITE_CHUNK) * self.write_bytes
        if block >= n:
            sums = n * self.sum_bytes + self.pair_buffer
            return max(self.views + sums, self.base + OVERHEAD + sums + write)
        return max(self.views, self.base + OVERHEAD + block * self.sum_bytes + self.pair_buffer + write)

    @property
    def in_memory(self) -> int:
        return self.peak(self.num_gaussians)

    def minimum_budget(self) -> int:
        """The smallest budget `block_for` gives a block (of BLOCK_ALIGN Gaussians) under."""
        blocks = self.base + OVERHEAD + self.pair_buffer + min(self.num_gaussians, WRITE_CHUNK) * self.write_bytes + BLOCK_ALIGN * self.sum_bytes
        return max(self.views, blocks)

    def block_for(self, budget: int) -> int:
        """The largest aligned block that fits `budget` (0 when even the view pass does not). A block
        as large as the scene is the in-memory run, which holds the sums while the views run: when
        that does not fit, the largest aligned block below N (N itself when N <= BLOCK_ALIGN)."""
        if self.views > budget:
            return 0
        n = self.num_gaussians
        room = budget - self.base - OVERHEAD - self.pair_buffer - min(n, WRITE_CHUNK) * self.write_bytes
        block = int(min(max(room // self.sum_bytes // BLOCK_ALIGN * BLOCK_ALIGN, 0), -(-n // BLOCK_ALIGN) * BLOCK_ALIGN))
        if block >= n and self.in_memory > budget:
            block = (n - 1) // BLOCK_ALIGN * BLOCK_ALIGN or n
        return block


def view_pairs_bound(num_gaussians: int, pixels: int, topk: int, max_masks: int = 0) -> int:
    """The most distinct (Gaussian, mask) pairs one view can give: one per top-k slot of its pixels,
    and no more than every Gaussian in every mask of the view (N·M; max_masks 0: not known). A view
    of 1920x1080 at k = 40 has 83 M slots, but 20,000 Gaussians in 102 masks give at most 2 M
    pairs: counting the slots put a default registration that peaked at 1.2 GB at 8 GB (a probe on
    real photos, 2026-11-30)."""
    slots = pixels * topk
    return min(slots, num_gaussians * max_masks) if max_masks > 0 else slots


def tile_list_bytes(num_gaussians: int) -> int:
    """The most a view's tile lists hold at once: views that need more are composited in bands
    (drsplat.raster.tile_bands), so a close-up or a view far larger than 640x480 stays within it."""
    return tile_list_cap(num_gaussians) * TILE_ENTRY_BYTES


def estimate_memory(scene: GaussianScene, views: Sequence[Camera], dim: int, topk: int, base: int | None = None,
                    aggregate: str = DEFAULT_AGGREGATE, total_masks: int = 0, max_masks: int = 0) -> MemoryPlan:
    """Estimate the peak memory of registering `views` onto `scene` with `dim`-D embeddings
    (and the statistics of aggregation mode `aggregate`, kept until the sums are finished).
    base: bytes already held (default: this process's resident memory now). total_masks,
    max_masks: the views' masks in all and in one view (drsplat.registration.views.FeatureHeaders;
    0: the mask clusters of the vote, check and solve stages are not counted)."""
    n = scene.num_gaussians
    pixels = max((c.width * c.height for c in views), default=0)
    mode_views, mode_kept, mode_block = Aggregator.memory_bytes(aggregate, n, pixels, topk, support_scratch_bytes(total_masks, max_masks),
                                                                trim_buffer_bytes(dim, total_masks, max_masks))
    stages = mode_stages(aggregate)  # the vote, check and solve stages each keep the views' mask clusters until the sums are finished
    clusters = (stages.vote + stages.check + stages.solve) * cluster_bytes(total_masks, max_masks, dim) if total_masks else 0
    if stages.check and total_masks:  # and the check's unit embeddings and support tables
        clusters += check_units_bytes(total_masks, max_masks, dim) + table_bytes(total_masks, max_masks, SUPPORT_TABLE_BYTES)
    mode_views, mode_kept = mode_views + clusters, mode_kept + clusters
    base = (current_rss() if base is None else base) + mode_kept
    view = (n * (PROJECTION_BYTES + SCRATCH_BYTES * coalesce_parts(n)) + tile_list_bytes(n) + pixels * topk * 8
            + 2 * PAIR_BYTES * view_pairs_bound(n, pixels, topk, max_masks) + mode_views - mode_kept)
    views_peak = base + OVERHEAD + n * (GEOMETRY_BYTES + INDEX_BYTES) + view
    row_bytes = scene.sh.shape[1] * 12 + 64
    buffered = PAIR_SLOT_BYTES if n > PAIR_CAPACITY else 0  # a block past PAIR_CAPACITY buffers a pair per Gaussian
    return MemoryPlan(n, dim, base, views_peak, sum_bytes=4 * dim + SUM_BYTES + buffered + mode_block,
                      write_bytes=OUTPUT_COPIES * dim + 2 * row_bytes + 32,
                      pair_buffer=buffer_bytes(dim, total_masks, max_masks, pairs=min(pair_capacity_for(n), PAIR_CAPACITY)))


EARLY_REFUSAL_BYTES = 256 << 20  # a scene file whose reading holds less is read before a budget is judged: cheaply, and then the plan's refusal names a budget that fits


def refuse_below_scene_floor(budget: int, rows: int, values: int, what: str, base: int | None = None) -> None:
    """Refuse a --memory-budget that reading the scene file alone would exceed, before it is read (round 67b F3: 300 MB
    was refused for a 3M-Gaussian scene only after loading it to 1.02 GB resident).

    floor = base + 4 · rows · values: the float32 values its loading makes of every row of the file at once
    (`splat_formats.declared_scene_size`), before it drops any (non-finite rows) and before the plan counts the
    geometry, views and masks. Rows the loading then drops are held too, so a budget below it is exceeded whatever the
    plan says (round 70a F1: a floor of the plan's per-Gaussian bytes refused a file of mostly non-finite rows a budget
    its kept rows fit). Only a scene whose reading holds EARLY_REFUSAL_BYTES or more is refused so: a smaller one costs
    little to read, and the plan's refusal then names a budget that fits, which this one cannot (it knows neither the
    views nor the masks). base: this process's resident memory (None: now)."""
    held = 4 * rows * values
    floor = (current_rss() if base is None else base) + held
    if held >= EARLY_REFUSAL_BYTES and budget < floor:
        raise DrsplatError(f"--memory-budget {format_size(budget)} is too small for this scene ({what}): reading its "
                           f"{rows:,} rows of {values} values holds more than {format_size(floor)}, before its geometry, views and "
                           "masks are counted; a budget above that is planned once the scene is read, and a refusal then names the "
                           "budget that fits")


def budget_hint(plan: MemoryPlan, fits: int) -> str:
    """A --memory-budget to suggest, as typed ("1.2GB", "800MB"): `fits` rounded down to 0.1 GB (1 MB
    below 1 GB), or the plan's smallest budget rounded up when that rounding would fall below it."""
    step = 10**8 if fits >= 10**9 else 10**6
    low = plan.minimum_budget() + NAMED_MINIMUM_ROOM
    value = fits // step * step
    if value < low:
        value = -(-low // step) * step
    return f"{value / 1e9:.1f}GB" if value >= 10**9 else f"{value // 10**6}MB"


def warn_beyond_free(plan: MemoryPlan, budget: int, available: int | None = None) -> None:
    """One warning when a --memory-budget lets the run use more than the machine has free now (its available memory and
    this process's own): the budget is followed as given, so such a run may be killed midway (round 63b: 1e300 was
    taken without a word, where no budget is refused with the figure that fits)."""
    free = (available_memory() if available is None else available) + current_rss()
    use = min(plan.in_memory, budget)
    if free and use > 0.9 * free:
        log.warning("--memory-budget %s lets this run use about %s, more than the %s this machine has free now: it may be killed "
                    "before it ends; a smaller budget registers in blocks (the same result)", format_size(budget), format_size(use),
                    format_size(free))


def choose_block(plan: MemoryPlan, budget: int | None, available: int | None = None, whole: bool = False) -> int:
    """The block size to register with: N (one block, in memory) or fewer Gaussians per block.

    budget None: one block when the estimate fits the memory available now, otherwise a
    DrsplatError with the figure and the --memory-budget that fits. With a budget: one block
    when it fits the budget, else the largest blocks that do; an error when even one view does not.
    whole: the mode needs every Gaussian in one block (the solve stage): a budget or memory
    below the in-memory peak is refused, naming that peak rather than a budget for blocks.
    """
    n = plan.num_gaussians
    if whole:
        limit = budget if budget is not None else (available_memory() if available is None else available) + current_rss()
        if budget is None and limit == 0:  # nothing known about the machine's memory
            return n
        if plan.in_memory > (limit if budget is not None else 0.9 * limit):
            need = f"it needs about {format_size(plan.in_memory)}"
            if budget is None:
                raise DrsplatError(f"this scene with a mode that solves over all Gaussians in one block in memory (blocks cannot be used) "
                                   f"does not fit the {format_size(limit)} available: {need}; free memory or use a mode without the solve stage")
            raise DrsplatError(f"--memory-budget {format_size(budget)} is too small for this scene with a mode that solves over all "
                               f"Gaussians in one block in memory (blocks cannot be used): {need}; give at least "
                               f"{format_size(plan.in_memory + NAMED_MINIMUM_ROOM, up=True)} (an estimate, on the safe side), "
                               "or use a mode without the solve stage")
        return n
    if budget is None:
        free = (available_memory() if available is None else available) + current_rss()
        if free == 0 or plan.in_memory <= 0.9 * free:
            return n
        fits = int(0.8 * free)
        if plan.block_for(fits) > 0:
            hint = f"rerun with --memory-budget {budget_hint(plan, fits)} to register Gaussians in blocks (same result)"
        elif plan.views > fits:
            hint = f"even in blocks, one view needs about {format_size(plan.views)}; use a machine with more memory or fewer, smaller views"
        else:  # the view fits; the process's own memory with the smallest blocks does not
            hint = (f"even in blocks, the smallest blocks with this process's own memory need about {format_size(plan.minimum_budget())}; "
                    "use a machine with more memory")
        raise DrsplatError(
            f"registering {n:,} Gaussians with {plan.dim}-D features in memory needs about "
            f"{format_size(plan.in_memory)}, but only {format_size(free)} is available: {hint}"
        )
    warn_beyond_free(plan, budget, available)
    if plan.in_memory <= budget:
        return n
    block = plan.block_for(budget)
    if block <= 0:
        blocks = f"the smallest blocks ({BLOCK_ALIGN:,} Gaussians) with the process's own memory need about {format_size(plan.minimum_budget())}"
        why = blocks
        if plan.views > budget:  # the named budget is the larger of the two terms: say both when the blocks' is larger
            why = f"the view pass alone (scene, geometry, one view) needs about {format_size(plan.views)}"
            why += f", and {blocks}" if plan.minimum_budget() > plan.views else ""
        raise DrsplatError(f"--memory-budget {format_size(budget)} is too small for this scene: {why}; give at least "
                           f"{format_size(plan.minimum_budget() + NAMED_MINIMUM_ROOM, up=True)} (an estimate, on the safe side)")
    return block
