"""Cross-view mask check: the `check` stage of an aggregation mode (`--aggregate check-vote-reject`, ...).

The vote stage (drsplat.registration.vote) decides per Gaussian, so it needs several views of the
Gaussian to outvote one wrong mask: a Gaussian seen in two views, one of them mislabelled, keeps
both labels. A mislabel, though, is a property of a whole mask: every Gaussian under a mislabelled
mask is seen elsewhere under its true label. The check pools that evidence over the mask's
Gaussians and drops whole masks:

1. while the views arrive, their masks are grouped by embedding (`MaskClusters`, as the vote stage
   does); once every view is in, every Gaussian collects presence votes V_ic per cluster c in
   CHECK_SLOTS slots (`fold_block_votes`, `_fold_votes_kernel`): a view gives cluster c the vote min(1, s_icv / (ρ·T_iv)) · min(1, T_iv / T₀),
   s_icv the Gaussian's weight in the view's masks of c, T_iv its weight in the view (the vote
   stage's rule with ρ = PRESENCE, T₀ = FULL_VIEW, taken per cluster: one view is at most one
   vote);
2. once every view is in, mask j of view v asks the other views what its Gaussians are:

       q_jc = Σ_{i ∈ j} w_ij φ_i (V_ic − v_icv) / Σ_{i ∈ j} w_ij,   φ_i = min(1, n_i / Σ_c (V_ic − v_icv))

   (v_icv: view v's own vote, so that a mask never supports itself; `add_view_support`), in units of
   views; n_i the other views that vote for Gaussian i. A view gives each cluster one vote at most,
   so a Gaussian inside one mask of each view has φ = 1; one spread over several masks in every view
   (faint dust or haze in front of the objects) counts one vote a view over all its clusters
   (`diffuse_share`; since 2026-12-04, round 47 of docs/hostile.md: such dust held 0.85 of an
   object's mask's weight and its votes for the table behind it dropped the mask). Which clusters
   say the same as the mask is decided by the scene, not by a fixed cosine (one object's crops from
   different views can be farther apart than the clustering's 0.9):

       like = min(CLUSTER_COSINE, ½ (median_j f̂_j·ĉ_j + median cos(f_j, f_k) over two masks j ≠ k of one view))

   ĉ_j = normalize(Σ_c q_jc μ_c) the consensus of mask j's Gaussians (`_agreement_kernel`; the
   median over masks with at least CHECK_MIN_VIEWS of other votes): halfway between how well a
   mask usually agrees with its Gaussians' other views and how alike two different instances of
   a view are (`like_threshold`), but never above the clustering's cosine: masks that close are
   one cluster, and where most masks of a view share a label (a shelf of books) the median of two
   masks' cosines is that label's, and the halfway point rose above some masks' cosine to their
   own cluster, whose support then counted against them (round 35: 4-6 of 24 correct masks
   dropped). Then (`_own_alt_kernel`)

       own_j = Σ_{c: μ_c·f̂_j ≥ like} q_jc,   alt_j = Σ_{c unlike, μ_c·μ_c* ≥ like} q_jc

   c* the unlike cluster with the largest q: alt is the support of the best other label, its
   clusters that split by noise summed back together. Mask j is dropped when

       mass_j ≥ CHECK_MIN_MASS,   alt_j ≥ CHECK_MIN_VIEWS   and   own_j < CHECK_SUPPORT · alt_j

   i.e. at least one view's worth of other evidence agrees on another label and the mask's own
   label has almost none there (two views' worth until 2026-11-27: one gave the same verdicts on
   every clean room and more dropped mislabels, docs/registration.md "Design choices, measured").
   A mask of fewer than CHECK_MIN_MASS pixels of weight is not judged (since 2026-11-30): an object
   that small in one view is a speck or absent in the others, where its Gaussians lie inside the
   masks around them, so what the other views say against it is spill. Of the masks the check
   dropped over 126 rooms of the aggregate grid, 276 of the 307 correct ones held under 16 pixels of
   weight, and 146 of the 1,650 mislabelled ones (docs/evaluation.md, "Masks too small to judge").
   A large mask is also dropped when

       judged,   mass_j ≥ CHECK_LARGE_MASK · Σ_k mass_k (its view's masks),
       own_j < CHECK_WEAK_SUPPORT · alt_j   and   core_j < CHECK_CORE,

       core_j = Σ_{c like j} r_jc / Σ_c r_jc,   r_jc = Σ_{i ∈ j: c_i* = c} w_ij

   with c_i* the cluster Gaussian i's other views vote most for (`mask_drops`): its own label
   reaches it only as a leak onto some of its Gaussians (a neighbour's mask spilling over its
   boundary in other views, which gives a mislabelled mask a few tenths of a view of support), and
   almost none of its Gaussians are seen as its label by the other views. Only for large masks:
   core is a share over the mask's Gaussians, and a small object's mask whose other views mostly
   see the wall behind it has the same low numbers (docs/registration.md, "Design choices,
   measured").
   A small object seen clearly in one view (its Gaussians elsewhere faint or spilling into the
   background: weak, split votes, each view's vote scaled by T_iv / T₀) or a label that a minority
   of other views share (own ≥ CHECK_SUPPORT · alt) is kept (docs/registration.md, "Cross-view
   mask check").
   Where the masks form more clusters than CHECK_MAX_CLUSTER_SHARE of their number (`masks_group`),
   one object's masks in different views did not group, so the votes of step 1 are single views and
   nothing is judged; the vote after the check then trims nothing either (`MaskVerdicts.trim`).
   When the masks with a pair (a superset of those with weight) already form that many clusters,
   neither steps 1-2 nor the vote's slots are computed at all (`CheckSink._ungrouped_verdicts`,
   `VoteSink.trims`): the same sums, without three replays of every view's pairs;
3. the sums (and the vote stage after it) are made from the kept pairs in the same order, less
   the views that abstain on a Gaussian: where the dropped masks of view v held at least
   CHECK_ABSTAIN of Gaussian i's weight in v,

       Σ_{j dropped} w_ijv ≥ CHECK_ABSTAIN · Σ_j w_ijv   (sums in fixed point, `abstaining_pairs`),

   v gives i no pair at all. What is left of i in such a view is the spill of its neighbours'
   masks (a thin object's jittered mask is mostly background pixels around it, and the background
   mask covers its footprint's edges), which without the dropped mask outweighs i's own label
   there: on a grazing-view room with 10 % mislabels, a cable's Gaussians went to the wall
   (docs/evaluation.md, "Views that abstain"). A Gaussian all of whose pairs fell in dropped masks
   has no label the other views do not contradict, and is left unassigned (it kept them all until
   2026-11-28: on the mislabelled rooms that painted labels the room does not hold).

Where the pairs come from: the pair log, which registration always keeps for a check mode (its
checkpoint, the log of a plan in blocks, or a temporary one); a CheckSink made without a log keeps
the views' distinct pairs (PAIR_BYTES = 12 per pair) in memory (PairRecord). Steps 1 and 2 run
block by block: a
block's Gaussians take 12·CHECK_SLOTS bytes each for their slots (twice the vote's: a label split
by embedding noise takes several clusters; on hard-room with 20% mislabels and noise 0.5, 8 / 16 /
32 / 64 slots gave 0.598 / 0.692 / 0.653 / 0.649 labelled seg mIoU vol) and 8 for their count of
voting views, and every view has a
sparse support table (`ViewSupport`: 24 bytes per (mask, cluster) pair that occurs; M masks x K
clusters dense until 2026-11-27; one view's [M, K] dense scratch while a view is summed), summed a
block at a time into parts that `SupportTables` (drsplat.registration.supports) holds in memory up
to SUPPORT_TABLE_BYTES and spills to disk beyond, merged when a view is read (`Supports`; twice:
the like cosine's pass, then the verdicts'; all of them held until 2026-11-30). Every term of q[j, c]
and of a mask's mass is added in fixed point (int64 units of 2⁻²⁴, SUPPORT_SCALE; exact up to
q = 2³⁹, pixels x views x VIEW_VOTES), so the sums are the same integers in any order and any partition: one
block, blocks, or on Ray the reducers' parts of their blocks added by the driver
(`write_block_supports`, `Supports.add_file`; since 2026-11-27, sixth session: before, float64
sums in Gaussian order, which only one process could make). The same verdicts, and the same output
bytes, in every plan and place. Step 3 needs the verdicts and each view's [M] present-mask flags only.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

from drsplat.defaults import CHECK_SLOTS, SUPPORT_EXTRA_SCRATCH, SUPPORT_READ_BYTES, SUPPORT_SCRATCH_BYTES, SUPPORT_TABLE_BYTES
from drsplat.errors import DrsplatError
from drsplat.lang.codebook import unit_rows64
from drsplat.memory import format_size, small_page_full, small_page_zeros
from drsplat.registration.pairlog import PairLog, ViewPairs
from drsplat.registration.sink import Block, LogSink, PairSource, Sink
from drsplat._sort_kernels import stable_order
from drsplat.registration.supports import ENTRY, SupportTables, TableWriter, order_by_mask_cluster
from drsplat.registration.vote import (CLUSTER_COSINE, FULL_VIEW, PRESENCE, VOTE_PARTS, MaskClusters, Specificity, VoteSink, _row_aligned_cuts, space_saving_slot,
                                       NO_TRIM, trim_cosine)
from drsplat.utils import CancelToken, progress

log = logging.getLogger(__name__)

CHECK_MIN_VIEWS = 1.0  # a mask is judged only where its Gaussians' other views hold at least this many views' votes for one label
# ... and only when it holds at least this many pixels of weight (mass): an object that small in one view
# is a speck or absent in the others, where its Gaussians lie inside their surroundings' masks, so the
# other views' "evidence" against its mask is spill (module docstring, step 2)
CHECK_MIN_MASS = 16.0
SUPPORT_SCALE = float(1 << 24)  # the support sums' fixed point: units of 2⁻²⁴ in int64, exact up to q = 2³⁹ (pixels x views x VIEW_VOTES)
VIEW_VOTES = 1.0 / PRESENCE  # the most votes one view casts for a Gaussian (its presence votes add up to at most 1/ρ): the most one slot can gain
SUPPORT_ENTRY_BYTES = 17  # a (mask, cluster) of the dense scratch: q and the core table int64, a flag
LIKE_CHUNK = 1 << 22  # cosines between two masks of a view that `like_threshold` holds at a time (32 MB)
MEDIAN_BINS = 1 << 16  # the bins of one of `stream_median`'s passes (1.5 MB of counts and extremes)
CHECK_SUPPORT = 0.1  # dropped when its own label's support is below this share of the best other label's
# a large mask (this share of its view's mass or more) is also dropped when its own label's support is
# below CHECK_WEAK_SUPPORT of the best other label's and under CHECK_CORE of its weight lies on Gaussians
# whose other views vote most for its label (module docstring, step 2)
CHECK_LARGE_MASK = 0.005  # 1 % until 2026-11-30 (docs/evaluation.md, "The second rule at 0.5 %")
CHECK_WEAK_SUPPORT = 0.25
CHECK_CORE = 0.05
# the check judges nothing when the masks with pairs form more clusters than this share of their
# number: almost no mask then reaches the clustering's cosine with a mask of another view, and own /
# alt compare a mask with single noisy masks instead of pooled views (a probe's room with CLIP-like
# correlated labels, round 29: 158 masks, 158 clusters, 48 dropped, accuracy 0.529 against the
# paper's 0.956). A label split by noise while others group is still judged (its clusters summed back
# by the like cosine): docs/registration.md, "Cross-view mask check"
CHECK_MAX_CLUSTER_SHARE = 0.9
# step 3: a view whose dropped masks hold at least this share of a Gaussian's weight in it gives the
# Gaussian no pair at all (what is left of it there is its neighbours' masks spilling onto it)
CHECK_ABSTAIN = 0.5
# a check that drops this share of the masks with pairs or more says so as a warning (`heavy_drop_warning`):
# mislabels on oracle rooms drop about their own share, correct masks ~0-2 %; faint dust before the
# objects made the check drop 24 % of correct masks (round 47)
CHECK_WARN_DROPPED = 0.25


def heavy_drop_warning(dropped: int, present: int, without: str) -> str | None:
    """The warning of a check that dropped `dropped` of the `present` masks with pairs, when that is
    CHECK_WARN_DROPPED of them or more (else None); without: the mode to run without the check."""
    if present <= 0 or dropped < CHECK_WARN_DROPPED * present:
        return None
    return (f"mask check: {dropped:,} of {present:,} masks ({100.0 * dropped / present:.0f} %) dropped as contradicted by the other "
            "views of their Gaussians. So many are dropped when a large share of the masks carry wrong labels, or when right masks "
            "cover Gaussians that the other views put under other labels (faint dust or haze in front of the objects, a scene "
            f"that changed between the photos); if the masks' labels are right, --aggregate {without} registers without the check")


@dataclass
class MaskVerdicts:
    """The check's outcome: keep [V] arrays of [M_v] bool per view (True: the mask's pairs are summed),
    and the masks it dropped, judged (with enough evidence to judge) and present (with pairs)."""

    keep: list[np.ndarray]
    dropped: int
    judged: int
    present: int
    like: float | None = None  # the scene's "like" cosine (`like_threshold`), None: too little to judge
    dropped_large: int = 0  # of the dropped, those only the second rule (large masks) drops
    pair_means: list[np.ndarray] | None = None  # per view [M] float64: each mask's mean pair weight w̄_j (0: no pair), step 4 of the vote
    grouped: bool = True  # the masks grouped into clusters across views (`masks_group`); else nothing was judged

    @property
    def trim(self) -> float:
        """θ of the vote after the check: `vote.trim_cosine` of the like cosine, or NO_TRIM where the
        masks did not group, since the vote pools views by the same clusters (one mask each: with θ
        at the like cosine it trimmed by single noisy masks, with θ at 0.9 it kept one mask of
        every Gaussian whose masks were cut into parts anew in each view; round 29)."""
        return trim_cosine(self.like) if self.grouped else NO_TRIM


def view_votes_reference(rows: np.ndarray, clusters: np.ndarray, weights: np.ndarray, num_rows: int, num_clusters: int,
                         presence: float = PRESENCE, full_view: float = FULL_VIEW) -> np.ndarray:
    """[num_rows, K] float64: one view's presence votes v_icv = min(1, s_icv / (ρ·T_iv)) · min(1, T_iv / T₀),
    s_icv = Σ_{j: cluster(j) = c} w_ij, T_iv = Σ_j w_ij: one vote per view and cluster at most
    (numpy reference; rows [P], clusters [P] (-1: none), weights [P] of the view's pairs)."""
    w = weights.astype(np.float64)
    total = np.bincount(rows, w, num_rows)
    ok = (clusters >= 0) & (w > 0)
    s = np.zeros((num_rows, num_clusters))
    np.add.at(s, (rows[ok], clusters[ok]), w[ok])
    t = np.where(total > 0, total, 1.0)[:, None]
    return np.where(s > 0, np.minimum(1.0, s / (t * presence)) * np.minimum(1.0, t / full_view), 0.0)


def fixed_support(x: np.ndarray) -> np.ndarray:
    """`_fixed` of each x in numpy: round(x · SUPPORT_SCALE) as float64 (integers, exact below 2⁵³,
    so their sums are the same in any order); a NaN, infinite or negative x counts 0."""
    x = np.asarray(x, np.float64)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(x) & (x > 0.0)
    return np.where(ok, np.floor(np.where(ok, x, 0.0) * SUPPORT_SCALE + 0.5), 0.0)


def check_reference(views: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]], num_gaussians: int,
                    means: np.ndarray, like: float | None = None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Obviously-correct reference of step 2 with unbounded slots (numpy, float64), every term and
    weight rounded to the kernels' fixed point (units of 2⁻²⁴, SUPPORT_SCALE) before it is summed.

    views: per view (gaussians [P], masks [P], weights [P], cluster of each mask [M] (-1 none),
    embeddings [M, D]). means: [K, D] unit cluster means. like: the "like" cosine (None: own and alt
    are 0). Returns per view (mass [M], total [M], agree [M], own [M], alt [M], core [M]) as
    `_agreement_kernel` and `_own_alt_kernel` define them (agrees with the kernels of `judge_masks` whenever no Gaussian
    meets more than CHECK_SLOTS clusters).
    """
    k = means.shape[0]
    means = means.astype(np.float64)
    votes = [view_votes_reference(g, c[m], w, num_gaussians, k) for g, m, w, c, _ in views]
    V = np.sum(votes, axis=0) if votes else np.zeros((num_gaussians, k))
    voting_views = np.sum([v.sum(axis=1) > 0 for v in votes], axis=0) if votes else np.zeros(num_gaussians)
    out = []
    for (g, m, w, c, feats), own_votes in zip(views, votes):
        num_masks = c.shape[0]
        q = np.zeros((num_masks, k))
        other_all = np.maximum(V - own_votes, 0.0)  # the kernel adds the positive terms only
        other_views = voting_views - (own_votes.sum(axis=1) > 0)
        other_votes = fixed_support(other_all).sum(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            phi = np.where(other_votes > 0, np.minimum(1.0, other_views / (other_votes / SUPPORT_SCALE)), 1.0)[g]
        other = other_all[g]
        np.add.at(q, m, fixed_support(w.astype(np.float64)[:, None] * other * phi[:, None]))
        q /= SUPPORT_SCALE
        mass = np.bincount(m, fixed_support(w), num_masks) / SUPPORT_SCALE
        units = unit_rows64(feats)
        units[c < 0] = 0.0
        has = mass > 0
        total = np.where(has, np.where(q > 0, q, 0.0).sum(axis=1) / np.where(has, mass, 1.0), 0.0)
        consensus = np.where(q > 0, q, 0.0) @ means
        norm = np.linalg.norm(consensus, axis=1)
        agree = np.where(has & (norm > 0), (consensus * units).sum(axis=1) / np.where(norm > 0, norm, 1.0), 0.0)
        # the core table: each pair's weight on the cluster its Gaussian's other views vote most for
        # (argmax: the lowest cluster id of equal maxima), where some other view votes
        r = np.zeros((num_masks, k))
        voted = other.max(axis=1) > 0 if k else np.zeros(g.shape[0], bool)
        if k:
            np.add.at(r, (m[voted], np.argmax(other, axis=1)[voted]), fixed_support(w[voted].astype(np.float64) * phi[voted]))
        r /= SUPPORT_SCALE
        own, alt, core = np.zeros(num_masks), np.zeros(num_masks), np.zeros(num_masks)
        for j in np.flatnonzero(has) if like is not None else ():
            present = q[j] > 0
            is_like = present & (means @ units[j] >= like)
            unlike = present & ~is_like
            own[j] = q[j, is_like].sum() / mass[j]
            if unlike.any():
                best = int(np.flatnonzero(unlike)[np.argmax(q[j, unlike])])  # first of equal maxima
                alt[j] = q[j, unlike & (means @ means[best] >= like)].sum() / mass[j]
            if r[j].sum() > 0:
                core[j] = r[j, means @ units[j] >= like].sum() / r[j].sum()
        out.append((mass, total, agree, own, alt, core))
    return out


@numba.njit(cache=True, inline="always")
def _group_votes(order, start, end, weights, clusters, presence, full_view, found, votes):  # pragma: no cover - jitted
    """One Gaussian's presence votes in one view, per cluster: pairs order[start:end] (all of the
    Gaussian's pairs in the view, clusters [P] per pair, -1 none). Writes the distinct clusters to
    found[:n] and their votes min(1, s_c / (ρ·T)) · min(1, T / T₀) to votes[:n] (s_c: the
    cluster's weight, T: the Gaussian's weight in the view); returns n. found / votes: scratch of
    at least end - start entries."""
    t = 0.0
    for i in range(start, end):
        t += np.float64(weights[order[i]])
    n = 0
    for i in range(start, end):
        p = order[i]
        c = clusters[p]
        w = np.float64(weights[p])
        if c < 0 or not w > 0.0:
            continue
        hit = -1
        for s in range(n):
            if found[s] == c:
                hit = s
                break
        if hit < 0:
            hit = n
            found[n] = c
            votes[n] = 0.0
            n += 1
        votes[hit] += w
    for s in range(n):
        votes[s] = min(1.0, votes[s] / (t * presence)) * min(1.0, t / full_view)
    return n


@numba.njit(cache=True, inline="always")
def _run_end(rows, order, start):  # pragma: no cover - jitted
    """The end of the run of pairs order[start:end] on the same row as order[start] (pairs sorted by row)."""
    end = start
    while end < order.shape[0] and rows[order[end]] == rows[order[start]]:
        end += 1
    return end


@numba.njit(cache=True, parallel=True)
def _fold_votes_kernel(rows, clusters, weights, order, presence, full_view, slot_c, slot_v, slot_n):  # pragma: no cover - jitted
    """Step 1 for one view: each Gaussian's votes per cluster (`_group_votes`: one vote per view and
    cluster at most) added to its slots slot_c / slot_v [N, S] with the space-saving rule (a new
    cluster replaces the slot with the fewest votes and inherits them), and slot_n [N] += 1 where the
    view votes for the Gaussian at all (its count of voting views). order: the pairs sorted by
    row (`stable_order`). A Gaussian's votes touch its own row only, so row-aligned parts of the
    view are folded in parallel (vote._row_aligned_cuts): the same bits as one pass."""
    cuts = _row_aligned_cuts(rows, order, VOTE_PARTS)
    for part in numba.prange(VOTE_PARTS):
        lo, hi = cuts[part], cuts[part + 1]
        found = np.empty(hi - lo, np.int32)
        votes = np.empty(hi - lo)
        start = lo
        while start < hi:
            r = rows[order[start]]
            end = _run_end(rows, order, start)
            n_found = _group_votes(order, start, end, weights, clusters, presence, full_view, found, votes)
            if n_found > 0:
                slot_n[r] += 1.0
            for d in range(n_found):
                hit = space_saving_slot(slot_c, slot_v, r, found[d])
                slot_c[r, hit] = found[d]
                slot_v[r, hit] += votes[d]
            start = end


@numba.njit(cache=True, inline="always")
def _fixed(x):  # pragma: no cover - jitted
    """x ≥ 0 in units of 2⁻²⁴ (SUPPORT_SCALE), rounded to the nearest; a NaN, infinite or negative x
    is 0, as in `fixed_support` (it cast to int64's smallest value, a mask's mass went negative and
    the mask unjudged; round 35). Registration's weights are finite and ≥ 0."""
    if not (x > 0.0 and x < np.inf):
        return np.int64(0)
    return np.int64(x * SUPPORT_SCALE + 0.5)


@numba.njit(cache=True, inline="always")
def diffuse_share(other_views, other_votes):  # pragma: no cover - jitted
    """φ = min(1, n / V): a Gaussian's weight in the check's support, from the n other views that vote
    for it and the votes V (fixed point, `_fixed`) they cast over all clusters. A view gives each cluster
    one vote at most, so a Gaussian inside one mask a view has V ≤ n and φ = 1; one spread over several
    masks in every view (faint haze or dust in front of the objects, a large blurred Gaussian) has
    V > n, and φ scales it to one vote a view. Without it such Gaussians outvoted the objects behind
    them: their masks' own Gaussians held 0.2 of the weight, and the haze's votes for the table it
    also hangs over dropped the objects' correct masks (an independent generator's dusty clutter:
    490 of 2,054 masks, docs/hostile.md round 47)."""
    if other_votes <= 0:
        return 1.0
    return min(1.0, other_views / (other_votes / SUPPORT_SCALE))


@numba.njit(cache=True, parallel=True)
def _gaussian_terms_kernel(rows, weights, clusters, order, starts, slot_c, slot_v, slot_n, presence, full_view, other, phi, win):  # pragma: no cover - jitted
    """What each Gaussian of one view adds to the support per unit of its pairs' weight (step 2,
    `_support_kernel`'s terms), from all of its pairs of the view: the Gaussian g holds the pairs
    order[starts[g]:starts[g + 1]] (sorted by row, `stable_order`), row r = rows[order[starts[g]]].

    other[g, s] = V_is − v_isv: the votes of slot s's cluster from the other views (v_isv this
    view's own, `_group_votes`, so that a mask does not support itself); φ_i = phi[g] =
    min(1, n_i / Σ_c (V_ic − v_icv)) with n_i the other views that vote for i (slot_n less this
    view): a Gaussian whose other views vote for more than one cluster each on average (faint haze
    or dust spread over several masks in every view) weighs as one vote per view, `diffuse_share`;
    win[g] = c_i*, the slot cluster of largest V_ic − v_icv > 0, the lowest cluster id of equal
    maxima (-1 when no other view votes). Gaussians are independent: parts in parallel."""
    num_gaussians = starts.shape[0] - 1
    num_slots = slot_c.shape[1]
    parts = min(VOTE_PARTS, max(num_gaussians, 1))
    for part in numba.prange(parts):
        g_lo, g_hi = part * num_gaussians // parts, (part + 1) * num_gaussians // parts
        longest = 0
        for g in range(g_lo, g_hi):
            longest = max(longest, starts[g + 1] - starts[g])
        found = np.empty(longest, np.int32)
        votes = np.empty(longest)
        for g in range(g_lo, g_hi):
            start, end = starts[g], starts[g + 1]
            r = rows[order[start]]
            found_n = _group_votes(order, start, end, weights, clusters, presence, full_view, found, votes)
            best = -1
            best_votes = 0.0
            other_votes = np.int64(0)  # Σ_c (V_ic − v_icv) in fixed point: the same bits in any slot order
            for s in range(num_slots):
                own = 0.0
                for d in range(found_n):
                    if slot_c[r, s] == found[d]:
                        own = votes[d]
                c = slot_c[r, s]
                other[g, s] = slot_v[r, s] - own
                if c >= 0:
                    other_votes += _fixed(other[g, s])
                    if other[g, s] > best_votes or (other[g, s] == best_votes and other[g, s] > 0.0 and c < best):
                        best, best_votes = c, other[g, s]
            win[g] = best
            phi[g] = diffuse_share(slot_n[r] - (1.0 if found_n > 0 else 0.0), other_votes)


@numba.njit(cache=True, parallel=True)
def _support_kernel(pairs, rows, masks, weights, pair_gaussian, slot_c, other, phi, win, entry_mask, entry_cluster, entry_value,
                    entry_core, scratch, core, touched, mass, j_lo):  # pragma: no cover - jitted
    """q[j, c] += Σ_{pairs (i, j)} w_ij (V_ic − v_icv) φ_i over the slots of Gaussian i, mass[j] += w_ij
    (one view, `add_view_support`, step 2), the Gaussians' terms from `_gaussian_terms_kernel`
    (other, phi, win [G] of the view's Gaussians; pair_gaussian [P]: each pair's). pairs: the
    pair indices to add, those of masks j_lo .. j_lo + M' - 1 (others are skipped).

    Every term is added in fixed point (`_fixed`: int64 units of 2⁻²⁴), so the sums are exact and
    the same in any order and any partition of the Gaussians: one block, blocks in any order,
    reducers' partial tables summed by the driver (`Supports.add_file`), or the parts of the pairs
    this kernel sums in parallel, one per scratch layer, then adds into layer 0.

    Beside q, the core table: r[j, c] += w_ij for the pairs whose Gaussian's other views vote
    most for c (win, c_i*), whose share of mask j's like clusters is core_j (`_own_alt_kernel`).
    Its entries are q's: c_i* has a positive term in q[j, c_i*].

    q and r arrive and leave as entries (entry_mask, entry_cluster [E] int32, entry_value,
    entry_core [E] int64: the pairs (j, c) met so far); returns the new entries (the old ones first;
    every (j, c) once, in an order that depends on the parts: readers sort them, `ViewSupport.rows`).
    They are summed in scratch and core [L, M', K] int64 (zero) with touched [L, M', K] bool (False), L
    parts, all left as they came: the masks j_lo .. j_lo + M' - 1 only (the entries passed in are
    theirs), so a view of many masks is summed a run of masks at a time in bounded scratch, each
    run reading its own pairs only (`add_view_support`). mass: [M] int64, fixed point too."""
    num_slots = slot_c.shape[1]
    layers, num_masks = scratch.shape[0], scratch.shape[1]
    count = entry_mask.shape[0]
    num_pairs = pairs.shape[0]
    room = np.empty(layers + 1, np.int64)  # each part's own stretch of the met lists: every (j, c) at most once
    room[0] = count
    for part in range(layers):
        room[part + 1] = room[part] + min(scratch.shape[1] * scratch.shape[2], ((part + 1) * num_pairs // layers - part * num_pairs // layers) * num_slots)
    met_j = np.empty(room[layers], np.int32)
    met_c = np.empty(room[layers], np.int32)
    met_n = np.zeros(layers, np.int64)
    part_mass = np.zeros((layers, num_masks), np.int64)
    for e in range(count):
        j, c = entry_mask[e] - j_lo, entry_cluster[e]
        scratch[0, j, c] = entry_value[e]
        core[0, j, c] = entry_core[e]
        touched[0, j, c] = True
        met_j[e] = j
        met_c[e] = c
    for part in numba.prange(layers):
        at = room[part]
        for i in range(part * num_pairs // layers, (part + 1) * num_pairs // layers):
            p = pairs[i]
            j = masks[p] - j_lo
            if j < 0 or j >= num_masks:
                continue
            w = np.float64(weights[p])
            r, g = rows[p], pair_gaussian[p]
            part_mass[part, j] += _fixed(w)
            for s in range(num_slots):
                c = slot_c[r, s]
                if c < 0:
                    break
                if other[g, s] > 0.0:
                    if not touched[part, j, c]:
                        touched[part, j, c] = True
                        met_j[at] = j
                        met_c[at] = c
                        at += 1
                    scratch[part, j, c] += _fixed(w * other[g, s] * phi[g])
            if win[g] >= 0:
                core[part, j, win[g]] += _fixed(w * phi[g])
        met_n[part] = at - room[part]
    for j in range(num_masks):
        for part in range(layers):
            mass[j_lo + j] += part_mass[part, j]
    out_j = np.empty(count + met_n.sum(), np.int32)
    out_c = np.empty(out_j.shape[0], np.int32)
    out_n = 0
    for e in range(count + met_n[0]):  # layer 0: the old entries, then its new ones
        out_j[out_n] = met_j[e]
        out_c[out_n] = met_c[e]
        out_n += 1
    for part in range(1, layers):  # the other layers added into layer 0
        for e in range(room[part], room[part] + met_n[part]):
            j, c = met_j[e], met_c[e]
            if not touched[0, j, c]:
                touched[0, j, c] = True
                out_j[out_n] = j
                out_c[out_n] = c
                out_n += 1
            scratch[0, j, c] += scratch[part, j, c]
            core[0, j, c] += core[part, j, c]
            scratch[part, j, c] = 0
            core[part, j, c] = 0
            touched[part, j, c] = False
    out_value = np.empty(out_n, np.int64)
    out_core = np.empty(out_n, np.int64)
    for e in range(out_n):
        j, c = out_j[e], out_c[e]
        out_value[e] = scratch[0, j, c]
        out_core[e] = core[0, j, c]
        scratch[0, j, c] = 0
        core[0, j, c] = 0
        touched[0, j, c] = False
    return out_j[:out_n] + np.int32(j_lo), out_c[:out_n].copy(), out_value, out_core


FIRST_RUN_PROBE = _support_kernel  # the stage's kernel whose place in numba's cache shows it ran here before (driver.say_if_kernels_compile)


@numba.njit(cache=True, parallel=True)
def _agreement_kernel(starts, clusters, values, mass, units, means, agree, total):  # pragma: no cover - jitted
    """Per mask j: total[j] = Σ_c q[j, c] / mass[j] (the other views' votes, in views) and
    agree[j] = f̂_j · ĉ_j, ĉ_j = normalize(Σ_c q[j, c] μ_c) (the cosine between the mask's unit
    embedding and its Gaussians' consensus); 0 for masks without pairs or consensus. q as
    compressed rows (`ViewSupport.rows`: mask j's entries at starts[j] .. starts[j + 1] - 1, in
    cluster order). Masks in parallel: each one's sums in the same order as alone."""
    num_masks = mass.shape[0]
    dim = means.shape[1]
    for j in numba.prange(num_masks):
        consensus = np.empty(dim)
        agree[j] = 0.0
        total[j] = 0.0
        if not mass[j] > 0.0:
            continue
        for d in range(dim):
            consensus[d] = 0.0
        for e in range(starts[j], starts[j + 1]):
            value = values[e]
            if value > 0.0:
                c = clusters[e]
                total[j] += value
                for d in range(dim):
                    consensus[d] += value * means[c, d]
        total[j] /= mass[j]
        norm = 0.0
        dot = 0.0
        for d in range(dim):
            norm += consensus[d] * consensus[d]
            dot += consensus[d] * units[j, d]
        if norm > 0.0:
            agree[j] = dot / np.sqrt(norm)


@numba.njit(cache=True, inline="always")
def _dots(means, rows, n, vec, out):  # pragma: no cover - jitted
    """out[k] = Σ_d float64(means[rows[k], d]) · vec[d] for k < n, each sum in d order (the bits of
    one dot product after another), four rows at a time so that their chains of adds overlap
    (2.4x faster on 1 thread than one at a time: each add waits for the last one)."""
    dim = means.shape[1]
    k = 0
    while k + 4 <= n:
        r0, r1, r2, r3 = rows[k], rows[k + 1], rows[k + 2], rows[k + 3]
        s0 = s1 = s2 = s3 = 0.0
        for d in range(dim):
            v = vec[d]
            s0 += np.float64(means[r0, d]) * v
            s1 += np.float64(means[r1, d]) * v
            s2 += np.float64(means[r2, d]) * v
            s3 += np.float64(means[r3, d]) * v
        out[k], out[k + 1], out[k + 2], out[k + 3] = s0, s1, s2, s3
        k += 4
    while k < n:
        s = 0.0
        for d in range(dim):
            s += np.float64(means[rows[k], d]) * vec[d]
        out[k] = s
        k += 1


@numba.njit(cache=True, parallel=True)
def _own_alt_kernel(starts, clusters, values, core_values, mass, units, means, like, own, alt, core):  # pragma: no cover - jitted
    """own[j] = Σ_{c like j} q[j, c] / mass[j], "like" μ_c · f̂_j ≥ `like`; alt[j] = Σ_{c in the group
    of c*} q[j, c] / mass[j], c* the unlike cluster of largest q (the first in cluster order of
    equal ones) and its group the unlike clusters c with μ_c · μ_c* ≥ `like`; core[j] = Σ_{c like j}
    r[j, c] / Σ_c r[j, c], the share of the mask's weight on Gaussians whose other views vote most
    for its own label (0 for masks without pairs or without such votes). Dotted only where q > 0
    or r > 0. q and r (core_values) as compressed rows (`_agreement_kernel`). Masks in parallel (each
    writes its own entries of the similarity scratch): the same bits as one after the other. The
    cosines are taken four at a time (`_dots`), each summed in d order: the bits of one at a time."""
    num_masks = mass.shape[0]
    dim = means.shape[1]
    sims = np.empty(values.shape[0])
    for j in numba.prange(num_masks):
        own[j] = 0.0
        alt[j] = 0.0
        core[j] = 0.0
        if not mass[j] > 0.0:
            continue
        lo, hi = starts[j], starts[j + 1]
        rows = np.empty(hi - lo, np.int64)  # the clusters to dot, at entries `where`
        where = np.empty(hi - lo, np.int64)
        dots = np.empty(hi - lo)
        n = 0
        for e in range(lo, hi):
            if values[e] > 0.0 or core_values[e] > 0.0:
                rows[n] = clusters[e]
                where[n] = e
                n += 1
        _dots(means, rows, n, units[j], dots)
        best = -1
        core_all = 0.0
        for i in range(n):
            e = where[i]
            value = values[e]
            sims[e] = dots[i]
            core_all += core_values[e]
            if dots[i] >= like:
                core[j] += core_values[e]
            if not value > 0.0:
                continue
            if dots[i] >= like:
                own[j] += value
            elif best < 0 or value > values[best]:
                best = e
        if best >= 0:
            leader = np.empty(dim)
            for d in range(dim):
                leader[d] = np.float64(means[clusters[best], d])
            n = 0
            for e in range(lo, hi):
                if values[e] > 0.0 and sims[e] < like:
                    rows[n] = clusters[e]
                    where[n] = e
                    n += 1
            _dots(means, rows, n, leader, dots)
            for i in range(n):
                if dots[i] >= like:
                    alt[j] += values[where[i]]
        own[j] /= mass[j]
        alt[j] /= mass[j]
        core[j] = core[j] / core_all if core_all > 0.0 else 0.0


class PairRecord:
    """The views' pairs kept in memory in arrival order: what the check replays in one block without
    a pair log (in blocks it replays the log). `block_views` reads it as PairLog.block_views does."""

    def __init__(self, num_gaussians: int):
        self.num_gaussians = num_gaussians
        self.views: list[ViewPairs] = []

    def add(self, view: ViewPairs) -> None:
        """Keep `view`'s host pairs (copies: the caller may reuse its buffers for the next view)."""
        self.views.append(ViewPairs(view.name, view.feats, np.ascontiguousarray(view.gaussians, np.int32),
                                    np.ascontiguousarray(view.masks, np.int32), np.ascontiguousarray(view.weights, np.float32),
                                    view.used, view.num_pairs, view.num_nonfinite))

    def block_views(self, lo: int, hi: int) -> Iterator[ViewPairs]:
        """Every view in order, holding only the pairs of Gaussians lo .. hi-1 (in record order)."""
        for view in self.views:
            if lo <= 0 and hi >= self.num_gaussians:
                yield view
                continue
            keep = (view.gaussians >= lo) & (view.gaussians < hi)
            yield ViewPairs(view.name, view.feats, view.gaussians[keep], view.masks[keep], view.weights[keep], view.used,
                            view.num_pairs, view.num_nonfinite)


@dataclass
class ViewSupport:
    """One view's masks as the check sees them: the other views' votes per (mask, cluster) pair that
    occurs, q[j, c] (divided by mass in own / alt / total), mass [M] = Σ_i w_ij and units [M, D] the
    unit embeddings.

    q is sparse: entries (mask [E] int32, cluster [E] int32, fixed [E] int64: q · SUPPORT_SCALE)
    for the pairs (j, c) with c in a slot of one of mask j's Gaussians, in the order they were met;
    `rows()` gives them per mask in cluster order, as float64. A view's masks meet a few clusters
    each, so the tables hold ~(masks) x (clusters per mask) entries where dense [M, K] tables held
    every mask x every cluster (200 k masks x 5 k clusters: 8 GB dense). mass_fixed: [M] int64,
    `mass` its float64 values."""

    entry_mask: np.ndarray
    entry_cluster: np.ndarray
    entry_fixed: np.ndarray
    entry_core: np.ndarray
    num_clusters: int
    mass_fixed: np.ndarray
    units: np.ndarray
    is_sorted: bool = False  # entries in (mask, cluster) order already (SupportTables' merged tables)

    @classmethod
    def empty(cls, feats: np.ndarray, clusters: np.ndarray, num_clusters: int) -> ViewSupport:
        """Zero sums for a view's masks: feats [M, D], clusters [M] (-1: never judged)."""
        units = unit_rows64(feats)
        units[clusters < 0] = 0.0  # a mask without a cluster (dropped for non-finite values) is never judged
        none = np.zeros(0, np.int32)
        return cls(none, none, np.zeros(0, np.int64), np.zeros(0, np.int64), int(num_clusters), np.zeros(clusters.shape[0], np.int64), units)

    @property
    def entry_value(self) -> np.ndarray:
        """[E] float64 q of the entries."""
        return self.entry_fixed / SUPPORT_SCALE

    @property
    def mass(self) -> np.ndarray:
        """[M] float64 Σ_i w_ij of each mask."""
        return self.mass_fixed / SUPPORT_SCALE

    @property
    def num_entries(self) -> int:
        return int(self.entry_value.shape[0])

    def rows(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """q and the core table r as compressed rows: (starts [M + 1] int64, clusters [E] int32,
        q values [E] float64, r values [E] float64), the entries of mask j at starts[j] ..
        starts[j + 1] - 1 in increasing cluster order."""
        if self.is_sorted:
            mask, cluster, fixed, core = self.entry_mask, self.entry_cluster, self.entry_fixed, self.entry_core
        else:
            order = order_by_mask_cluster(self.entry_mask, self.entry_cluster)
            mask, cluster, fixed, core = self.entry_mask[order], self.entry_cluster[order], self.entry_fixed[order], self.entry_core[order]
        starts = np.searchsorted(mask, np.arange(self.mass_fixed.shape[0] + 1), side="left").astype(np.int64)
        return starts, np.ascontiguousarray(cluster), fixed / SUPPORT_SCALE, core / SUPPORT_SCALE

    def dense(self) -> np.ndarray:
        """q as a dense [M, K] table (tests)."""
        q = np.zeros((self.mass_fixed.shape[0], self.num_clusters))
        q[self.entry_mask, self.entry_cluster] = self.entry_value
        return q


class SupportScratch:
    """The dense scratch `_support_kernel` sums one view in: [L, M', K] int64 zeros (q, the core
    table) and bool flags for a run of M' of the view's masks, one layer per part of the view
    summed in parallel, sized for the largest run and reused (left zero by every call). A run
    holds as many masks as keep one layer within SUPPORT_SCRATCH_BYTES (at least one), so a view
    of thousands of masks against thousands of clusters is summed in runs instead of one
    [M, K] table (4,000 masks x 16,000 clusters: 1.1 GB a layer). L: one per numba thread, as long
    as the layers beyond the first stay within SUPPORT_EXTRA_SCRATCH (the sums do not depend on
    it); `layers` fixes L, `run_bytes` the bound of a layer."""

    def __init__(self, num_clusters: int, layers: int | None = None, run_bytes: int = SUPPORT_SCRATCH_BYTES):
        self.num_clusters = num_clusters
        self.layers = layers
        self.run_bytes = run_bytes
        self._values = np.zeros(0, np.int64)
        self._core = np.zeros(0, np.int64)
        self._touched = np.zeros(0, bool)

    def masks_per_run(self, num_masks: int) -> int:
        """How many of a view's `num_masks` masks one call sums (all of them when a layer fits)."""
        return int(max(1, min(num_masks, self.run_bytes // max(SUPPORT_ENTRY_BYTES * self.num_clusters, 1))))

    def take(self, num_masks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q's, the core table's and the flags' [L, M', K] layers for a run of `num_masks` masks."""
        table = num_masks * self.num_clusters
        layers = self.layers or int(max(1, min(numba.get_num_threads(), 1 + SUPPORT_EXTRA_SCRATCH // max(SUPPORT_ENTRY_BYTES * table, 1))))
        size = layers * table
        if size > self._values.shape[0]:
            self._values, self._core, self._touched = np.zeros(size, np.int64), np.zeros(size, np.int64), np.zeros(size, bool)
        shape = (layers, num_masks, self.num_clusters)
        return self._values[:size].reshape(shape), self._core[:size].reshape(shape), self._touched[:size].reshape(shape)


def support_scratch_bytes(total_masks: int = 0, max_masks: int = 0) -> int:
    """The most a `SupportScratch` holds for views of `max_masks` masks at most against at most
    `total_masks` clusters (every mask its own cluster): one layer of a run of masks, L·K·E bytes
    (E = SUPPORT_ENTRY_BYTES) for a run of L ≤ max_masks masks within SUPPORT_SCRATCH_BYTES (one mask
    at the least, so K·E when that alone is more), and the further layers, each as large, within
    SUPPORT_EXTRA_SCRATCH, one per numba thread. SUPPORT_SCRATCH_BYTES + SUPPORT_EXTRA_SCRATCH when
    the counts are not known (0). A capture of a few thousand masks needs ~1 MB of the 128."""
    if total_masks <= 0 or max_masks <= 0:
        return SUPPORT_SCRATCH_BYTES + SUPPORT_EXTRA_SCRATCH
    per_mask = SUPPORT_ENTRY_BYTES * total_masks
    layer = max(per_mask, min(max_masks * per_mask, SUPPORT_SCRATCH_BYTES))
    # the most threads numba may be set to, not today's count: `take` reads the count when it runs
    return layer + min((numba.config.NUMBA_NUM_THREADS - 1) * layer, SUPPORT_EXTRA_SCRATCH)


def fold_block_votes(views: Iterator[ViewPairs], per_view: list[np.ndarray], lo: int, hi: int,
                     slots: int = CHECK_SLOTS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 1 for Gaussians lo .. hi-1: their presence votes over `views` (every view in order, with
    those Gaussians' pairs) folded into slots (slot_c [hi - lo, S] int32 clusters, -1 free; slot_v
    [hi - lo, S] float64 votes) and the count of views that vote for each (slot_n [hi - lo] float64).
    per_view: each view's [M] mask clusters. A Gaussian's slots depend on its own pairs only, so they
    are the same bits whatever block holds it."""
    slot_c = small_page_full((hi - lo, slots), -1, np.int32)  # made once a block, touched a few rows a view: small pages
    slot_v = small_page_zeros((hi - lo, slots), np.float64)
    slot_n = small_page_zeros(hi - lo, np.float64)
    for view, clusters in zip(views, per_view):
        if view.gaussians.size:
            rows = np.ascontiguousarray(view.gaussians - np.int32(lo), np.int32)
            _fold_votes_kernel(rows, np.ascontiguousarray(clusters[view.masks], np.int32), np.ascontiguousarray(view.weights, np.float32),
                               stable_order(rows), PRESENCE, FULL_VIEW, slot_c, slot_v, slot_n)
    return slot_c, slot_v, slot_n


def add_view_support(view: ViewPairs, lo: int, clusters: np.ndarray, slot_c: np.ndarray, slot_v: np.ndarray, slot_n: np.ndarray,
                     support: ViewSupport | PartialSupport, scratch: SupportScratch | None = None,
                     emit: Callable[[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], None] | None = None) -> None:
    """Step 2's sums of one view's pairs of Gaussians lo .. lo + len(slot_c) - 1 added to support's q
    and mass (`_support_kernel`). clusters: [M] the view's mask clusters; slot_c / slot_v / slot_n: those
    Gaussians' slots and voting views folded over all views (`fold_block_votes`); scratch: reused between calls (None: a new one). The
    terms of q[j, c] are added in Gaussian order, so blocks taken in increasing `lo` give one
    block's bits. emit: receives each run of masks' entries (mask, cluster, fixed, core) as it is
    summed, instead of support keeping them (support, empty of entries, then gets the masses only):
    a view whose table is larger than memory allows is never held whole (`view_supports`)."""
    if not view.gaussians.size:
        return
    rows = np.ascontiguousarray(view.gaussians - np.int32(lo), np.int32)
    if scratch is None:  # only a ViewSupport knows its cluster count; a PartialSupport comes with its block's scratch
        scratch = SupportScratch(support.num_clusters)
    masks, weights = np.ascontiguousarray(view.masks, np.int32), np.ascontiguousarray(view.weights, np.float32)
    order = stable_order(rows)
    terms = gaussian_terms(rows, weights, np.ascontiguousarray(clusters[view.masks], np.int32), order, slot_c, slot_v, slot_n)
    num_masks = support.mass_fixed.shape[0]
    step = scratch.masks_per_run(num_masks)  # ≥ 1; a view with pairs has masks
    by_run, run_starts = (order, np.array([0, order.shape[0]])) if step >= num_masks else pairs_by_run(order, masks, step, num_masks)
    del order
    entries = (support.entry_mask, support.entry_cluster, support.entry_fixed, support.entry_core)
    runs = []
    for k, j_lo in enumerate(range(0, num_masks, step)):
        j_hi = min(num_masks, j_lo + step)
        inside = entries if step >= num_masks else tuple(e[(entries[0] >= j_lo) & (entries[0] < j_hi)] for e in entries)
        run = _support_kernel(by_run[run_starts[k] : run_starts[k + 1]], rows, masks, weights, terms.pair_gaussian, slot_c, terms.other,
                              terms.phi, terms.win, *inside, *scratch.take(j_hi - j_lo), support.mass_fixed, j_lo)
        if emit is not None:
            emit(run)
        else:
            runs.append(run)
    if emit is not None:
        return
    support.entry_mask, support.entry_cluster, support.entry_fixed, support.entry_core = (
        runs[0] if len(runs) == 1 else tuple(np.concatenate(column) for column in zip(*runs)))


@dataclass
class GaussianTerms:
    """Each Gaussian of one view's part in its pairs' support terms (`_gaussian_terms_kernel`):
    other [G, S] float64, phi [G] float64, win [G] int32, for the view's G Gaussians in row
    order, and pair_gaussian [P] int32, each pair's Gaussian among them."""

    other: np.ndarray
    phi: np.ndarray
    win: np.ndarray
    pair_gaussian: np.ndarray


def gaussian_terms(rows: np.ndarray, weights: np.ndarray, pair_clusters: np.ndarray, order: np.ndarray, slot_c: np.ndarray,
                   slot_v: np.ndarray, slot_n: np.ndarray) -> GaussianTerms:
    """The terms of the Gaussians of one view's pairs (rows [P] int32 in slot_c's rows, weights
    [P] float32, pair_clusters [P] int32, order [P]: the pairs sorted by row), each Gaussian's once
    for all the runs of masks its pairs are summed in (`add_view_support`)."""
    sorted_rows = rows[order]
    starts = np.flatnonzero(np.r_[True, sorted_rows[1:] != sorted_rows[:-1], True]).astype(np.int64)
    del sorted_rows
    num_gaussians = starts.shape[0] - 1
    pair_gaussian = np.empty(rows.shape[0], np.int32)
    pair_gaussian[order] = np.repeat(np.arange(num_gaussians, dtype=np.int32), np.diff(starts))
    other = np.empty((num_gaussians, slot_c.shape[1]))
    phi, win = np.empty(num_gaussians), np.empty(num_gaussians, np.int32)
    _gaussian_terms_kernel(rows, weights, pair_clusters, order, starts, slot_c, slot_v, slot_n, PRESENCE, FULL_VIEW, other, phi, win)
    return GaussianTerms(other, phi, win, pair_gaussian)


def pairs_by_run(order: np.ndarray, masks: np.ndarray, step: int, num_masks: int) -> tuple[np.ndarray, np.ndarray]:
    """(the pairs of `order` [P] stably sorted by their run of masks, ⌊mask / step⌋, [P] int64; each
    run's first place in it [R + 1] int64, R = ⌈num_masks / step⌉): a run of masks reads its own
    pairs, not the view's (a view of 19,200 masks was summed in 26 runs, each reading all of its pairs)."""
    run_of = masks[order] // np.int32(step)
    starts = np.r_[0, np.cumsum(np.bincount(run_of, minlength=-(-num_masks // step)))]
    return order[stable_order(run_of)], starts


def fixed_point_fits(max_pixels: int, num_views: int, mode: str = "check") -> None:
    """DrsplatError when the support sums could leave the fixed point's range, checked before any
    view is rendered: q[j, c] = Σ_i w_ij (V_ic − v_icv) ≤ mass_j · max V, a mask's mass is at most its
    view's pixels (the check's paper weights sum to ≤ 1 a pixel), and a slot's count V is at most
    the votes cast into its Gaussian's slots, VIEW_VOTES a view (space-saving's evictions hand a
    slot's count on, so one slot can hold them all), so max_pixels · num_views · VIEW_VOTES must stay
    under 2³⁹ (2⁶³ units of 2⁻²⁴): 1,650 views of 8K images, 26,500 of 1920x1080."""
    if not float(max_pixels) * max(num_views, 1) * VIEW_VOTES < 2.0**63 / SUPPORT_SCALE:
        raise DrsplatError(f"--aggregate {mode}: the mask check cannot judge {num_views:,} views of up to {max_pixels:,} pixels: "
                           f"views x pixels x {VIEW_VOTES:g} votes pass the range of its exact sums ({2.0**63 / SUPPORT_SCALE:.3g}); register without the check "
                           f"(--aggregate vote-reject) or with fewer or smaller views")


@dataclass
class PartialSupport:
    """One view's support from one block of Gaussians, as `add_view_support` sums it: entries (mask
    [E] int32, cluster [E] int32, fixed and core [E] int64; none when its runs are handed on as they
    are summed) and mass_fixed [M] int64, in the kernel's fixed point, so the parts of every block
    add up exactly (`block_supports`)."""

    entry_mask: np.ndarray
    entry_cluster: np.ndarray
    entry_fixed: np.ndarray
    entry_core: np.ndarray
    mass_fixed: np.ndarray

    @classmethod
    def empty(cls, num_masks: int) -> PartialSupport:
        none = np.zeros(0, np.int32)
        return cls(none, none, np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(num_masks, np.int64))


def block_supports(views: Iterator[ViewPairs], pair_views: Iterator[ViewPairs], per_view: list[np.ndarray], lo: int, hi: int, slots: int,
                   scratch: SupportScratch, emit: Callable[[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], None],
                   ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Steps 1 and 2 for Gaussians lo .. hi-1 alone: their votes folded over `views` (every view in
    order, with those Gaussians' pairs), then each view's support from those Gaussians' pairs
    (`pair_views`: a second replay of the same views), handed to emit(v, entries) a run of view v's
    masks at a time (views in order, a view's runs in increasing masks: `add_view_support`), so that
    no view's part is held whole. per_view: each view's [M] mask clusters. Returns each view's
    masses [M] int64 and pair counts [M] int64 (the Gaussians with a pair in each mask) from these
    Gaussians."""
    slot_c, slot_v, slot_n = fold_block_votes(views, per_view, lo, hi, slots)
    masses, counts = [], []
    for v, (view, clusters) in enumerate(zip(pair_views, per_view)):
        part = PartialSupport.empty(clusters.shape[0])
        add_view_support(view, lo, clusters, slot_c, slot_v, slot_n, part, scratch, emit=lambda run, v=v: emit(v, run))
        masses.append(part.mass_fixed)
        counts.append(np.bincount(view.masks[view.weights > 0], minlength=clusters.shape[0])[: clusters.shape[0]].astype(np.int64))
    return masses, counts


@dataclass
class SupportFile:
    """One block's part of every view's support table, written by a reducer (`write_block_supports`):
    path, offsets [V + 1] (each view's first entry in it, the spill files' format), the views'
    masses and pair counts [M] int64 from the block's Gaussians and the file's CRC-32 (checked when
    adopted)."""

    path: str
    offsets: np.ndarray
    mass_fixed: list[np.ndarray]
    crc32: int
    pair_counts: list[np.ndarray]


def write_block_supports(path: Path, views: Iterator[ViewPairs], pair_views: Iterator[ViewPairs], per_view: list[np.ndarray],
                         num_clusters: int, lo: int, hi: int, slots: int = CHECK_SLOTS) -> SupportFile:
    """`block_supports` written to `path` a run of masks at a time (`TableWriter`), so that a reducer
    holds one run of a view's table, never the block's part of every view (the driver adopts the
    file: `Supports.add_file`). A retried task rewrites the file from the start."""
    with open(path, "wb") as f:
        writer = TableWriter(f, len(per_view))
        masses, counts = block_supports(views, pair_views, per_view, lo, hi, slots, SupportScratch(num_clusters), writer.add)
        offsets = writer.close()
    return SupportFile(str(path), offsets, masses, writer.crc32, counts)


class Supports(Sequence):
    """Every view's ViewSupport (`supports[v]`, merged when read), their parts held by SupportTables
    under a memory cap and spilled beyond it; the masses and pair counts [M] int64 and unit
    embeddings [M, D] of each view kept in memory. `close` removes the spill files."""

    def __init__(self, tables: SupportTables, mass_fixed: list[np.ndarray], units: list[np.ndarray], num_clusters: int,
                 read_bytes: int | None = None):
        self.tables, self.mass_fixed, self.units, self.num_clusters = tables, mass_fixed, units, num_clusters
        self.pair_counts = [np.zeros(m.shape[0], np.int64) for m in mass_fixed]
        # a view's table larger than this is judged in runs of its masks (`runs`)
        self.read_bytes = SUPPORT_READ_BYTES if read_bytes is None else read_bytes

    @classmethod
    def empty(cls, feats: list[np.ndarray], per_view: list[np.ndarray], num_clusters: int, cap: int | None = None,
              beside: str | Path | None = None) -> Supports:
        """Zero sums for every view's masks: feats [M, D] and clusters [M] of each view. cap: the
        tables' bytes held in memory (None: SUPPORT_TABLE_BYTES, what the memory plan counts)."""
        views = [ViewSupport.empty(f, c, num_clusters) for f, c in zip(feats, per_view)]
        tables = SupportTables(len(views), SUPPORT_TABLE_BYTES if cap is None else cap, beside, [c.shape[0] for c in per_view], num_clusters)
        return cls(tables, [v.mass_fixed for v in views], [v.units for v in views], num_clusters)

    def add_file(self, part: SupportFile) -> None:
        """One block's parts written to a file by a reducer (`write_block_supports`): its masses and
        pair counts added, the file adopted by the tables (`SupportTables.adopt`: read in, or read
        from where it is)."""
        for view, (mass, count) in enumerate(zip(part.mass_fixed, part.pair_counts)):
            self.mass_fixed[view] += mass
            self.pair_counts[view] += count
        self.tables.adopt(Path(part.path), part.offsets, part.crc32)

    def __len__(self) -> int:
        return len(self.units)

    def __getitem__(self, view: int) -> ViewSupport:
        if not -len(self) <= view < len(self):
            raise IndexError(view)
        view %= len(self)
        return ViewSupport(*self.tables.view(view), self.num_clusters, self.mass_fixed[view], self.units[view], is_sorted=True)

    def runs(self, view: int) -> Iterator[tuple[int, ViewSupport]]:
        """View `view`'s support in runs of its masks: (lo, the ViewSupport of masks lo .. lo + m - 1,
        numbered from 0), each table within `read_bytes` (`SupportTables.view_ranges`; one run when the
        whole table is). Every mask's entries and sums are those of `supports[view]`."""
        mass, units = self.mass_fixed[view], self.units[view]
        for lo, hi, (mask, cluster, fixed, core) in self.tables.view_ranges(view, mass.shape[0], max(1, self.read_bytes // ENTRY.itemsize)):
            yield lo, ViewSupport(mask - np.int32(lo), cluster, fixed, core, self.num_clusters, mass[lo:hi], units[lo:hi], is_sorted=True)

    def close(self) -> None:
        self.tables.close()


def check_units_bytes(total_masks: int, max_masks: int, dim: int) -> int:
    """What the check holds besides its support tables and its clusters (memory plan): every view's
    [M, D] float64 unit embeddings (`ViewSupport.units`, 8·D bytes a mask), the clusters' means
    while judging ([K, D] float32, K ≤ the masks), one view's [M, D] float64 temporaries (two at
    most: a norm, the like cosine's gathered rows) and the like cosines' pieces (LIKE_CHUNK values)."""
    return total_masks * dim * 12 + 2 * max_masks * dim * 8 + 8 * LIKE_CHUNK


def like_threshold(agreements: np.ndarray, view_units: list[np.ndarray], chunk: int = LIKE_CHUNK,
                   rows: list[np.ndarray] | None = None) -> float | None:
    """The scene's "like" cosine, halfway between what a mask's consensus usually is and what two
    different things are: ½ (median agreement of the judged masks + median cosine between two
    masks of one view, which show different instances), at most CLUSTER_COSINE (the module
    docstring). None when either is missing (then nothing is dropped). agreements: [J]; view_units:
    per view [M, D] the unit embeddings of its masks;
    rows: per view [M] bool, the masks to take (None: all); zero rows are never taken.

    The cosines between two masks of one view are Σ_v M_v(M_v - 1)/2 values (4,000 masks: 8 M per
    view); their median is found exactly without holding them (`stream_median`), about `chunk` at a
    time, and the views' taken rows are gathered one view at a time, not all at once."""
    taken = [(np.linalg.norm(u, axis=1) > 0) & (True if r is None else r) for u, r in zip(view_units, rows or [None] * len(view_units))]
    if agreements.size == 0 or not any(t.sum() > 1 for t in taken):
        return None
    between = stream_median(lambda: _pair_cosines((u[t] for u, t in zip(view_units, taken)), chunk), chunk)
    return min(CLUSTER_COSINE, 0.5 * (float(np.median(agreements)) + between))


def _pair_cosines(view_units: Iterable[np.ndarray], chunk: int) -> Iterator[np.ndarray]:
    """Each view's cosines u_i · u_j (i < j) between its unit rows [M, D], in pieces of rows of the
    upper triangle holding about `chunk` values (at least one row)."""
    for units in view_units:
        m = units.shape[0]
        rows = max(1, chunk // max(m, 1))
        for i0 in range(0, m - 1, rows):
            i1 = min(m - 1, i0 + rows)
            cos = units[i0:i1] @ units[i0 + 1 :].T  # row r: cosines with masks i0 + 1 ..; keep j > i0 + r
            yield np.concatenate([cos[r, r:] for r in range(i1 - i0)])


def stream_median(pieces: Callable[[], Iterator[np.ndarray]], chunk: int = LIKE_CHUNK, bins: int = MEDIAN_BINS) -> float:
    """np.median of the concatenation of `pieces()` (a fresh iterator of float64 arrays on each
    call, at least one value in all), holding about `chunk` values at most besides one piece.

    Exact, in a few passes: the values are counted into `bins` bins of equal width between their
    extremes (`_bin_stats`), the range narrowed to the smallest and largest value of the bin
    holding the wanted rank, and so on until that bin's values fit `chunk`; those are gathered and
    the rank and the next one picked (np.partition; the next one, when the bin ends at the rank,
    is the smallest value of the next bin holding any). The two middle values of an even count are
    averaged as np.median does; NaN anywhere gives NaN, as there, and infinities rank below and above
    every finite value (counted, never binned). A view of 19,200 masks (184 M
    cosines) takes three passes over them (the median used to take ~20, each value's bin found by a
    binary search)."""
    n, below, above, low, high = 0, 0, 0, np.inf, -np.inf  # the count, the infinities below and above, the finite extremes
    for piece in pieces():
        if np.isnan(piece).any():
            return float("nan")
        n += piece.size
        infinite = np.isinf(piece)
        if infinite.any():
            below += int(np.count_nonzero(piece == -np.inf))
            above += int(np.count_nonzero(piece == np.inf))
            piece = piece[~infinite]
        if piece.size:
            low, high = min(low, float(piece.min())), max(high, float(piece.max()))
    finite = n - below - above

    def value_at(rank: int) -> float:
        return -np.inf if rank < below else np.inf if rank >= below + finite else _values_at_rank(pieces, rank - below, finite, low, high, chunk, bins)[0]

    middle = (n - 1) // 2
    if n % 2:
        middles = [value_at(middle)]  # as np.median: the one middle value through a mean (-0.0 gives 0.0)
    elif below <= middle and middle + 1 < below + finite:
        middles = list(_values_at_rank(pieces, middle - below, finite, low, high, chunk, bins))
    else:
        middles = [value_at(middle), value_at(middle + 1)]
    with np.errstate(over="ignore", invalid="ignore"):  # two huge middles overflow to inf, -inf and inf give NaN: np.median's values
        return float(np.mean(middles))


@numba.njit(cache=True)
def _bin_stats(values, low, high, scale, counts, mins, maxs):  # pragma: no cover - jitted
    """Each value v of [low, high] counted into bin b = min(B - 1, ⌊(v/2 − low/2)·scale⌋) of counts [B]
    int64, with the bin's smallest and largest value in mins / maxs [B] float64. b never decreases as
    v grows (halving, subtracting, scaling by scale > 0 and truncating are each monotone in floating
    point), so a bin holds a contiguous stretch of the sorted values: exactly those of [mins[b],
    maxs[b]]. Halving keeps v − low finite for any finite pair."""
    bins = counts.shape[0]
    half_low = 0.5 * low
    for v in values:
        if v >= low and v <= high:
            x = (0.5 * v - half_low) * scale
            b = 0 if not x > 0.0 else bins - 1 if x >= bins else int(x)  # x is finite and >= 0 for finite v, low, scale
            counts[b] += 1
            if v < mins[b]:
                mins[b] = v
            if v > maxs[b]:
                maxs[b] = v


def _values_at_rank(pieces: Callable[[], Iterator[np.ndarray]], rank: int, count: int, low: float, high: float, chunk: int,
                    bins: int) -> tuple[float, float]:
    """The values of 0-based `rank` and of rank + 1 (inf when there is none) among the `count`
    finite values of `pieces()` (none NaN; the finite ones within [low, high], infinities left out). The next rank's value is the next one
    in the gathered bin, or the smallest value of the next bin that holds any (`after`)."""

    def within(v: np.ndarray) -> np.ndarray:
        return v[(v >= low) & (v <= high)]

    after = np.inf  # the smallest value above the range: where rank + 1 lies when rank is the range's last
    while low < high:
        width = 0.5 * high - 0.5 * low
        with np.errstate(over="ignore", divide="ignore"):
            scale = float(np.float64(bins) / np.float64(width))
        if not (width > 0.0 and np.isfinite(scale)):
            break  # a range a few floats wide (subnormal halves may not differ at all): counted by value below
        counts, mins, maxs = np.zeros(bins, np.int64), np.full(bins, np.inf), np.full(bins, -np.inf)
        for p in pieces():
            _bin_stats(np.ascontiguousarray(p, np.float64), low, high, scale, counts, mins, maxs)
        ends = np.cumsum(counts)
        b = int(np.searchsorted(ends, rank, side="right"))
        rank -= int(ends[b] - counts[b])
        later = np.flatnonzero(counts[b + 1 :])
        after = float(mins[b + 1 + later[0]]) if later.size else after
        narrowed, count = (float(mins[b]), float(maxs[b])), int(counts[b])
        if count <= chunk:
            low, high = narrowed
            values = np.concatenate([within(p) for p in pieces()])
            if rank + 1 < count:
                values = np.partition(values, (rank, rank + 1))
                return float(values[rank]), float(values[rank + 1])
            return float(np.partition(values, rank)[rank]), after
        if narrowed == (low, high):
            break  # every value in one bin: counted by value below
        low, high = narrowed
    if low == high:
        return low, (low if rank + 1 < count else after)
    values = np.unique(np.concatenate([np.unique(within(p)) for p in pieces()]))
    counts = np.zeros(values.size, np.int64)
    for p in pieces():
        counts += np.bincount(np.searchsorted(values, within(p)), minlength=values.size)
    ends = np.cumsum(counts)
    at, next_at = (int(np.searchsorted(ends, r, side="right")) for r in (rank, rank + 1))
    return float(values[at]), (float(values[next_at]) if next_at < values.size else after)


def judge_masks(source: PairSource, clusters: MaskClusters, num_gaussians: int, block: int, slots: int = CHECK_SLOTS,
                min_views: float = CHECK_MIN_VIEWS, min_share: float = CHECK_SUPPORT, cancel: CancelToken | None = None,
                show_progress: bool = False, supports: Supports | None = None, cap: int | None = None,
                beside: str | Path | None = None, min_mass: float = CHECK_MIN_MASS) -> MaskVerdicts:
    """Steps 1 and 2 (module docstring): the verdict on every mask of `source`'s views, from their
    support (`view_supports`, its tables under `cap` bytes, spilled beside `beside` beyond) in blocks of
    `block` Gaussians, or from `supports` when they were summed elsewhere (reducers' parts,
    `Supports.add_file`: the same numbers). The tables' spill files are removed after."""
    means = np.ascontiguousarray(clusters.means(), np.float32)
    if supports is None:
        supports = view_supports(source, clusters, num_gaussians, block, slots, cancel, show_progress, cap, beside)
    try:
        return _verdicts(supports, means, min_views, min_share, supports.tables.spilled_bytes, cancel, min_mass)
    finally:
        supports.close()


def _blocks(num_gaussians: int, block: int, cancel: CancelToken | None, show_progress: bool = False) -> Iterator[tuple[int, int]]:
    """(lo, hi) of each block in order; cancel is checked before each, a bar shown for several."""
    count = -(-num_gaussians // block)
    for lo in progress(range(0, num_gaussians, block), desc="mask check", total=count, enabled=show_progress and count > 1, unit="block"):
        if cancel is not None:
            cancel.raise_if_cancelled()
        yield lo, min(num_gaussians, lo + block)


def view_supports(source: PairSource, clusters: MaskClusters, num_gaussians: int, block: int, slots: int = CHECK_SLOTS,
                  cancel: CancelToken | None = None, show_progress: bool = False, cap: int | None = None,
                  beside: str | Path | None = None) -> Supports:
    """Every view's support: per block of `block` Gaussians, one replay of `source` folds the block's
    votes into slots (`fold_block_votes`, [block, S]) and a second sums its pairs' support per view
    (`add_view_support`), a part that SupportTables keeps under `cap` bytes (spilled beyond, in a
    temporary folder named after the output `beside`). The parts' sums are integers, so every plan gives the same bits.

    clusters: the views' mask clusters (MaskClusters of every view, in order). cancel: checked
    before each block (Cancelled); show_progress: a bar over the blocks.
    """
    k = clusters.count
    supports = Supports.empty([view.feats for view in source.block_views(0, 0)], clusters.per_view, k, cap, beside)
    scratch = SupportScratch(k)
    for lo, hi in _blocks(num_gaussians, block, cancel, show_progress):
        masses, counts = block_supports(source.block_views(lo, hi), source.block_views(lo, hi), clusters.per_view, lo, hi, slots, scratch,
                                        supports.tables.add)
        for v, (mass, count) in enumerate(zip(masses, counts)):
            supports.mass_fixed[v] += mass
            supports.pair_counts[v] += count
    return supports


def _log_supports(masks: int, present: int, num_clusters: int, entries: int, spilled: int) -> None:
    """masks: the views' feature-file rows (every level); present: those with pairs (the registered level's), which the
    verdict's line counts (round 57c: the two lines gave 400 and 100 masks without saying why)."""
    spill = f", {format_size(spilled)} of parts spilled to disk" if spilled else ""
    log.info("mask check: %d masks with pairs (of %d rows in the views' feature files, every level) x %d clusters, %d support "
             "entries (%s%s; dense tables would take %s)", present, masks, num_clusters, entries,
             format_size(ENTRY.itemsize * entries), spill, format_size(8 * num_clusters * masks))


def masks_group(present: int, num_clusters: int, views: int = 2) -> bool:
    """Whether the views' `present` masks with pairs group into few enough clusters for the check to
    pool views (at most CHECK_MAX_CLUSTER_SHARE of them); else one line says why nothing is judged.
    views: how many views hold masks with pairs; with one, its masks are apart by design (one mask a
    label), so the line says there is no other view rather than blaming the masks' likeness."""
    if num_clusters <= CHECK_MAX_CLUSTER_SHARE * present:
        return True
    if views < 2:
        log.info("mask check: skipped, since only %d view holds masks with pairs: no other view can judge its %d masks, and the "
                 "vote trims nothing", views, present)
        return False
    log.info("mask check: skipped, since the %d masks with pairs form %d clusters (more than %g of them): one object's masks in "
             "different views are not alike enough to group, so no mask can be judged by the other views, and the vote trims nothing",
             present, num_clusters, CHECK_MAX_CLUSTER_SHARE)
    return False


def judged_masks(mass: np.ndarray, alt: np.ndarray, min_views: float = CHECK_MIN_VIEWS, min_mass: float = CHECK_MIN_MASS) -> np.ndarray:
    """[M] bool: the masks of one view the check judges: some weight and at least min_mass pixels of
    it (mass [M]), and at least min_views of other views' votes for one other label (alt [M])."""
    return (mass > 0) & (mass >= min_mass) & (alt >= min_views)


def mask_drops(mass: np.ndarray, own: np.ndarray, alt: np.ndarray, core: np.ndarray, min_views: float = CHECK_MIN_VIEWS,
               min_share: float = CHECK_SUPPORT, min_mass: float = CHECK_MIN_MASS) -> tuple[np.ndarray, np.ndarray]:
    """([M] bool the masks of one view the check drops, [M] bool those only the second rule drops)
    (module docstring, step 2): judged (`judged_masks`) and own < min_share · alt, or large (mass ≥
    CHECK_LARGE_MASK of the view's mass over its masks), own < CHECK_WEAK_SUPPORT · alt and core <
    CHECK_CORE. mass, own, alt, core: [M]."""
    judge = judged_masks(mass, alt, min_views, min_mass)
    first = judge & (own < min_share * alt)
    large = mass >= CHECK_LARGE_MASK * mass.sum()
    second = judge & ~first & large & (own < CHECK_WEAK_SUPPORT * alt) & (core < CHECK_CORE)
    return first | second, second


def _verdicts(supports: Supports, means: np.ndarray, min_views: float, min_share: float, spilled: int = 0,
              cancel: CancelToken | None = None, min_mass: float = CHECK_MIN_MASS) -> MaskVerdicts:
    """Step 2's decision from every view's support: the like cosine, then own / alt per mask. Two
    passes over the views, one view's table at a time (Supports merges it when read; a table past
    its `read_bytes` a run of masks at a time, each mask's numbers the same; `cancel` checked before
    each run: a Ctrl-C after the last view waited for the whole judging, probe round 13). spilled:
    bytes of the tables' parts spilled to disk (logged)."""
    agreements, masses, units, entries = [], [], [], 0
    for v in range(len(supports)):
        mass, unit = supports.mass_fixed[v] / SUPPORT_SCALE, supports.units[v]  # no table read (ViewSupport.mass)
        agree, total = np.zeros(mass.shape[0]), np.zeros(mass.shape[0])
        for lo, sup in supports.runs(v):
            if cancel is not None:
                cancel.raise_if_cancelled()
            hi = lo + sup.mass_fixed.shape[0]
            _agreement_kernel(*sup.rows()[:3], sup.mass, sup.units, means, agree[lo:hi], total[lo:hi])
            entries += sup.num_entries
        agreements.append(agree[(total >= min_views) & (np.linalg.norm(unit, axis=1) > 0)])
        masses.append(mass)
        units.append(unit)
    _log_supports(sum(m.shape[0] for m in masses), sum(int((m > 0).sum()) for m in masses), means.shape[0], entries, spilled)
    like = like_threshold(np.concatenate(agreements) if agreements else np.zeros(0), units, rows=[m > 0 for m in masses])
    grouped = masks_group(sum(int((m > 0).sum()) for m in masses), means.shape[0], sum(bool((m > 0).any()) for m in masses))
    judging = like is not None and grouped
    keep, dropped, judged, present, dropped_large = [], 0, 0, 0, 0
    for v, mass in enumerate(masses):
        own, alt, core = np.zeros(mass.shape[0]), np.zeros(mass.shape[0]), np.zeros(mass.shape[0])
        if judging:
            for lo, sup in supports.runs(v):
                if cancel is not None:
                    cancel.raise_if_cancelled()
                hi = lo + sup.mass_fixed.shape[0]
                _own_alt_kernel(*sup.rows(), sup.mass, sup.units, means, like, own[lo:hi], alt[lo:hi], core[lo:hi])
        drop, large_only = mask_drops(mass, own, alt, core, min_views, min_share, min_mass)
        judge = judged_masks(mass, alt, min_views, min_mass)
        keep.append(~drop)
        dropped += int(drop.sum())
        dropped_large += int(large_only.sum())
        judged += int(judge.sum())
        present += int((mass > 0).sum())
    return MaskVerdicts(keep, dropped, judged, present, like, dropped_large, pair_means(masses, supports.pair_counts), grouped)


def pair_means(masses: list[np.ndarray], counts: list[np.ndarray]) -> list[np.ndarray]:
    """Per view [M] float64 w̄_j = mass_j / #pairs_j, each mask's mean pair weight over its view
    (0 where it has no pair): step 4 of the vote (drsplat.registration.vote). masses: [M] float64
    pixels of weight, counts: [M] int64 pairs with weight, from the supports (exact integers)."""
    return [np.where(c > 0, m / np.maximum(c, 1), 0.0) for m, c in zip(masses, counts)]


def abstaining_pairs(gaussians: np.ndarray, weights: np.ndarray, kept: np.ndarray, lo: int, hi: int,
                     share: float = CHECK_ABSTAIN) -> np.ndarray:
    """[P] bool: the pairs of one view (gaussians [P] in lo .. hi-1, weights [P] float32, kept [P]
    bool: in a kept mask) of Gaussians whose dropped pairs hold at least `share` of their weight in
    the view (module docstring, step 3). The weights are summed as integers (`fixed_support`: exact
    in float64 below 2⁵³, i.e. ~5e8 pixels of weight per Gaussian and view), so the verdict does not
    depend on the pairs' order."""
    if gaussians.size == 0 or kept.all():
        return np.zeros(gaussians.shape[0], bool)
    local = np.asarray(gaussians, np.int64) - lo
    fixed = fixed_support(weights)
    total = np.bincount(local, fixed, minlength=hi - lo)
    dropped = np.bincount(local[~kept], fixed[~kept], minlength=hi - lo)
    return ((dropped > 0) & (dropped >= share * total))[local]


class KeptPairs:
    """The pairs the check keeps, read block by block like a pair log (step 3): a view's pairs in
    kept masks. A Gaussian all of whose pairs are in dropped masks keeps none and is left
    unassigned: every label it was given is one the other views contradict (it kept them until
    2026-11-28; docs/evaluation.md, "Gaussians whose every mask is dropped").

    present: per view [M] bool, the masks with a pair and an embedding (the clustered ones,
    `MaskClusters.per_view` ≥ 0, the driver's record of every view), which `clusters` needs; None
    where only pairs are read (a reducer).
    """

    def __init__(self, source: PairSource, keep: list[np.ndarray], present: list[np.ndarray] | None = None):
        self.source, self.keep, self._present = source, keep, present

    def block_views(self, lo: int, hi: int) -> Iterator[ViewPairs]:
        """Every view in order with the kept pairs of Gaussians lo .. hi-1: those in kept masks, less
        those of Gaussians the view abstains on (`abstaining_pairs`). A Gaussian's pairs of a view
        all lie in one block, so every partition into blocks keeps the same pairs. With the views'
        present masks known, a yielded view's `present` is its kept present masks whatever
        pairs are left, as `present` says (the one-block path clusters from it, the blocks path from
        `present`: the same clusters)."""
        for v, (view, k) in enumerate(zip(self.source.block_views(lo, hi), self.keep)):
            kept = k[view.masks]
            if kept.all():
                yield view
                continue
            kept &= ~abstaining_pairs(view.gaussians, view.weights, kept, lo, hi)
            present = None if self._present is None or v >= len(self._present) else k & self._present[v]
            yield ViewPairs(view.name, view.feats, view.gaussians[kept], view.masks[kept], view.weights[kept], view.used, view.num_pairs,
                            view.num_nonfinite, present=present)

    def present(self) -> list[np.ndarray]:
        """Per view [M] bool: the kept masks among those with a pair. Not quite "the masks with a kept pair": a kept
        mask whose every Gaussian abstains in the view (`abstaining_pairs`: a small right mask inside a large dropped
        one) keeps no pair and is still present, so it can found or lead a cluster (round 69a F1; not seen on the
        generator's rooms). Telling it apart needs the view's kept pairs of every block, one more replay of the pair
        log in a plan of blocks; one plan and another still give the same clusters."""
        if self._present is None or len(self._present) != len(self.keep):
            raise RuntimeError(f"KeptPairs needs every view's present masks to tell which kept masks have pairs "
                               f"({0 if self._present is None else len(self._present)} for {len(self.keep)} views)")
        return [k & p for k, p in zip(self.keep, self._present)]

    def clusters(self, dim: int) -> MaskClusters:
        """The views' mask clusters made from the `present` masks: what the vote stage makes of the kept views when they
        are added to it one by one."""
        clusters = MaskClusters(dim)
        for view, flags in zip(self.source.block_views(0, 0), self.present()):
            clusters.add(view.feats, flags)
        return clusters


def dropped_masks_text(names: list[str], keep: list[np.ndarray], present: list[np.ndarray]) -> str:
    """The masks the check dropped, view by view: "view v003 rows 4, 17 of its _f.npy; view v011 row 2" (rows of the
    view's embeddings file, which its mask-id file's ids name; round 104d: `-v` could not tell which masks went)."""
    parts = []
    for name, kept, there in zip(names, keep, present):
        rows = np.flatnonzero(there & ~kept)
        if rows.size:
            parts.append(f"view {name} row{'s' if rows.size > 1 else ''} {', '.join(str(int(r)) for r in rows)} of its _f.npy")
    return "; ".join(parts) or "no mask"


class CheckSink:
    """A sink (drsplat.registration.sink) whose blocks are the mode's sums of the pairs the check keeps.

    `add` clusters each view's masks and, without a pair log, records its pairs (PairRecord); with
    one (`plog`: a checkpoint, or the log of a plan in blocks of `block` Gaussians) the driver has
    logged them and the check replays the log. The first call of `blocks` or `sample` judges the
    masks (`judge_masks`), then the mode's own sink (`inner` in one block; VoteSink for a `-vote`
    mode, else LogSink, in blocks) sums the kept pairs (KeptPairs), on the host. Every plan gives
    the same bits.
    """

    place = "host"

    def __init__(self, num_gaussians: int, dim: int, vote: bool, plog: PairLog | None = None, block: int | None = None,
                 inner: Sink | None = None, slots: int = CHECK_SLOTS, cancel: CancelToken | None = None, show_progress: bool = False,
                 spill_beside: Path | None = None, specific: bool = False):
        """block: Gaussians per block (None: one block). inner: in one block, the mode's own sink of
        all N Gaussians, made by the caller before the views as without the check (the kept views are
        added to it); in blocks None, the kept pairs are replayed into a VoteSink / LogSink. cancel:
        checked before each block of the judging (Cancelled); show_progress: a bar over its blocks.
        spill_beside: the output the support tables' spill folder is named after (SupportTables;
        None: the system's temp folder). specific: the vote also trims by specificity (its step 4,
        `Stages.specific`), from the kept pairs and the masks' mean pair weights judged here."""
        self.num_gaussians, self.dim, self.vote, self.slots = num_gaussians, dim, vote, int(slots)
        self.specific = bool(specific) and vote
        self.cancel, self.show_progress = cancel, show_progress
        self.block = num_gaussians if block is None else int(block)
        if self.block < 1 and num_gaussians:
            raise ValueError("block must be >= 1")
        if (inner is None) != (self.block < num_gaussians):
            raise ValueError("a check in one block sums into `inner`; in blocks it makes its own sink (inner None)")
        if plog is None and self.block < num_gaussians:
            raise ValueError("a check in blocks replays the pair log: plog is needed")
        self.record = PairRecord(num_gaussians) if plog is None else None
        self.spill_beside = spill_beside
        self._source: PairSource | None = plog if plog is not None else self.record
        self.clusters = MaskClusters(dim)
        self.verdicts: MaskVerdicts | None = None
        self._inner = inner
        self._kept: KeptPairs | None = None
        self._summed = False
        self._with_pairs = 0  # masks with a pair, over the views added (`_ungrouped_verdicts`)
        self._views_with_pairs = 0
        self._largest_view_weight = 0.0  # the most pair weight one view added (`_check_range`)
        self._views_added = 0
        self._view_names: list[str] = []  # in the order added, for the debug line naming the masks dropped

    @property
    def num_blocks(self) -> int:
        return max(1, -(-self.num_gaussians // max(self.block, 1)))

    @property
    def sums_on(self) -> str:
        """Where the kept pairs are summed: in one block the caller's sink's place (the torch device,
        when the views were coalesced there), in blocks the host. The views themselves come to the
        host (`place`), for the record or the log the judging replays."""
        return self._inner.place if self._inner is not None else "host"

    def add(self, view: ViewPairs) -> None:
        """Cluster the view's masks and keep its pairs (ValueError when a pair weight is NaN, infinite or
        negative: registration gives none, and the supports' fixed point has no value for them)."""
        w = view.weights
        if w.size and not (w.min() >= 0 and np.isfinite(w.max())):  # two reductions a view (NaN fails the first); counted only when bad
            with np.errstate(invalid="ignore"):
                bad = int(w.size - np.count_nonzero(np.isfinite(w) & (w >= 0)))
            if bad:
                raise ValueError(f"view {view.name!r}: {bad} of its {view.weights.size} pair weights are NaN, infinite or negative; "
                                 "the check takes finite weights >= 0 (w = T·alpha summed per mask)")
        self._check_range(view)
        self._view_names.append(view.name)
        present = view.present_masks()
        self.clusters.add(view.feats, present)
        self._with_pairs += int(np.count_nonzero(present))
        self._views_with_pairs += bool(present.any())
        if self.record is not None:
            self.record.add(view)

    def _check_range(self, view: ViewPairs) -> None:
        """ValueError, naming the view, once the views added could take a support sum past its fixed
        point's range, the bound `fixed_point_fits` puts on pixels x views before a registration with
        a mask's mass in place of its pixels: (the most pair weight of one view) x (views) x VIEW_VOTES
        under 2³⁹. Registration's weights sum to ≤ 1 a pixel, so only a caller's own pair weights can
        pass it (round 35: over ~5.5e11 they wrapped). A view refused is not counted."""
        total = float(view.weights.sum(dtype=np.float64)) if view.weights.size else 0.0
        largest, views = max(self._largest_view_weight, total), self._views_added + 1
        if not largest * views * VIEW_VOTES < 2.0**63 / SUPPORT_SCALE:
            raise ValueError(f"view {view.name!r}: {views:,} view{'s' if views != 1 else ''} of up to {largest:.4g} pair weight each, "
                             f"x {VIEW_VOTES:g} votes, pass the range of the check's exact sums ({2.0**63 / SUPPORT_SCALE:.3g}); "
                             "registration's weights sum to at most 1 a pixel")
        self._largest_view_weight, self._views_added = largest, views

    def kept_pairs(self, partial_supports: Callable[[Callable[[SupportFile], None]], None] | None = None) -> KeptPairs:
        """The masks judged (once: `judge_masks`) and the pairs they keep: what the mode's sums are
        made of, here or by reducers (drsplat.registration.reduce, given the verdicts `keep`).
        partial_supports(add): hands each block's part of the support tables, summed elsewhere and
        written to a file, to `add` (reducers, one block each, in any order:
        drsplat.registration.reduce.ReducePool.supports); None: summed here by replays."""
        if self._kept is None:
            if self._summed:
                raise RuntimeError("the kept pairs of a check in one block are summed already")
            self.verdicts = self._ungrouped_verdicts()
            if self.verdicts is None:
                self.verdicts = self._judge(partial_supports)
            like = "none" if self.verdicts.like is None else f"{self.verdicts.like:.3f}"
            log.info("mask check: %d of %d masks dropped (%d judged: of %g pixels of weight or more, with enough other views; %d dropped as large masks whose label "
                     "the other views give only to their boundary; like cosine %s)",
                     self.verdicts.dropped, self.verdicts.present, self.verdicts.judged, CHECK_MIN_MASS, self.verdicts.dropped_large, like)
            present = [ids >= 0 for ids in self.clusters.per_view]
            if self.verdicts.dropped and log.isEnabledFor(logging.DEBUG):
                log.debug("mask check: dropped %s", dropped_masks_text(self._view_names, self.verdicts.keep, present))
            self._kept = KeptPairs(self._source, self.verdicts.keep, present)
        return self._kept

    def _ungrouped_verdicts(self) -> MaskVerdicts | None:
        """The verdicts without a support table, when the clusters are already too many for the masks
        with a pair to group (`masks_group`): the judging counts the masks with weight, which are
        among those (with an embedding or not: a zero row has pairs but no cluster), so it would find
        them ungrouped too and keep every mask, and the vote would trim nothing (NO_TRIM; nor step
        4). Nothing is replayed: on random masks of a flowers view, no two alike, the supports' two
        replays were ~45 ms a view. None where the masks may group (then `_judge`)."""
        if self._with_pairs == 0 or masks_group(self._with_pairs, self.clusters.count, self._views_with_pairs):
            return None
        return MaskVerdicts([np.ones(ids.shape[0], np.bool_) for ids in self.clusters.per_view], 0, 0, self._with_pairs, grouped=False)

    def _judge(self, partial_supports: Callable[[Callable[[SupportFile], None]], None] | None) -> MaskVerdicts:
        """`judge_masks` on the supports summed here by replays, or handed in by `partial_supports`."""
        n, block = self.num_gaussians, max(self.block, 1)
        supports = None
        if partial_supports is not None:
            feats = [view.feats for view in self._source.block_views(0, 0)]
            supports = Supports.empty(feats, self.clusters.per_view, self.clusters.count, beside=self.spill_beside)
            try:
                partial_supports(supports.add_file)
            except BaseException:  # a reducer failed or the run was cancelled: the files adopted so far go too
                supports.close()
                raise
        return judge_masks(self._source, self.clusters, n, block, self.slots, cancel=self.cancel, show_progress=self.show_progress,
                           supports=supports, beside=self.spill_beside)

    def _judged(self) -> Sink:
        """The sink of the kept pairs, the masks judged first."""
        if not self._summed:
            n, kept = self.num_gaussians, self.kept_pairs()
            trim = self.verdicts.trim  # the vote trims what is unlike by the scene's own measure (vote.trim_cosine)
            # the vote's step 4 (none where the masks did not group: at NO_TRIM it trims nothing, and there are no pair means)
            specific = Specificity(kept, self.verdicts.pair_means) if self.specific and self.verdicts.grouped else None
            if self.block >= n:  # one block: the kept views fed in order to the caller's sink
                if self.vote:  # before the views: at NO_TRIM the vote folds no slots (VoteSink.trims)
                    # the exact trim replays the kept pairs (the record) once more, as step 4 does
                    self._inner.trim, self._inner.specific, self._inner.exact = trim, specific, kept
                for view in kept.block_views(0, n):
                    self._inner.add(view)
                # the sums hold what the record did (the vote's step 4 and exact trim replay it once more)
                self.record = self._source = self._kept = None
            else:
                self._inner = (VoteSink(n, self.dim, kept, self.block, clusters=kept.clusters(self.dim), trim=trim, specific=specific, exact=kept)
                               if self.vote else LogSink(n, self.dim, kept, self.block))
            self._summed = True
        return self._inner

    def blocks(self, reuse: bool = False) -> Iterator[Block]:
        yield from self._judged().blocks(reuse)

    def sample(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._judged().sample(ids)
