"""Cross-view mask check: the `check` stage of an aggregation mode (`--aggregate check-vote-reject`, ...).

The vote stage (drsplat.registration.vote) decides per Gaussian, so it needs several views of the
Gaussian to outvote one wrong mask: a Gaussian seen in two views, one of them mislabelled, keeps
both labels. A mislabel, though, is a property of a whole mask: every Gaussian under a mislabelled
mask is seen elsewhere under its true label. The check pools that evidence over the mask's
Gaussians and drops whole masks:

1. while the views arrive, their masks are grouped by embedding (`MaskClusters`, as the vote stage
   does) and every Gaussian collects presence votes V_ic per cluster c in CHECK_SLOTS slots
   (`_fold_votes_kernel`): a view gives cluster c the vote min(1, s_icv / (ρ·T_iv)) · min(1, T_iv / T₀),
   s_icv the Gaussian's weight in the view's masks of c, T_iv its weight in the view (the vote
   stage's rule with ρ = PRESENCE, T₀ = FULL_VIEW, taken per cluster: one view is at most one
   vote); the views' pairs are kept (`PairRecord`);
2. once every view is in, mask j of view v asks the other views what its Gaussians are:

       q_jc = Σ_{i ∈ j} w_ij (V_ic − v_icv) / Σ_{i ∈ j} w_ij

   (v_icv: view v's own vote, so that a mask never supports itself; `view_support`), in units of
   views. Which clusters say the same as the mask is decided by the scene, not by a fixed cosine
   (one object's crops from different views can be farther apart than the clustering's 0.9):

       like = ½ (median_j f̂_j·ĉ_j + median cos(f_j, f_k) over two masks j ≠ k of one view)

   ĉ_j = normalize(Σ_c q_jc μ_c) the consensus of mask j's Gaussians (`_agreement_kernel`; the
   median over masks with at least CHECK_MIN_VIEWS of other votes): halfway between how well a
   mask usually agrees with its Gaussians' other views and how alike two different instances of
   a view are (`like_threshold`). Then (`_own_alt_kernel`)

       own_j = Σ_{c: μ_c·f̂_j ≥ like} q_jc,   alt_j = Σ_{c unlike, μ_c·μ_c* ≥ like} q_jc

   c* the unlike cluster with the largest q: alt is the support of the best other label, its
   clusters that split by noise summed back together. Mask j is dropped when

       alt_j ≥ CHECK_MIN_VIEWS   and   own_j < CHECK_SUPPORT · alt_j

   i.e. at least two views' worth of other evidence agree on another label and the mask's own
   label has almost none there. A small object seen clearly in one view (its Gaussians elsewhere
   faint or spilling into the background: weak, split votes) or a label that a minority of other
   views share (own ≥ CHECK_SUPPORT · alt) is kept (docs/registration.md, "Cross-view mask check");
3. the sums (and the vote stage after it) are made from the kept pairs in the same order. A
   Gaussian all of whose pairs fell in dropped masks keeps them all, so which Gaussians are
   assigned does not change.

Memory: the views' distinct pairs (PAIR_BYTES = 12 per pair) and embeddings while the views arrive,
plus 12·CHECK_SLOTS bytes per Gaussian for the slots (twice the vote's: a label split by
embedding noise takes several clusters; on hard-room with 20% mislabels and noise 0.5, 8 / 16 /
32 / 64 slots gave 0.598 / 0.692 / 0.653 / 0.649 labelled seg mIoU vol); per view of the check a dense [M, K]
float64 support table (M masks, K clusters), made twice (the like cosine needs every view's). The stage needs all Gaussians in one block:
registration refuses it with a --memory-budget that splits the scene into blocks.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass

import numba
import numpy as np

from drsplat.defaults import CHECK_SLOTS
from drsplat.memory import format_size
from drsplat.registration.pairlog import ViewPairs
from drsplat.registration.sink import Block, Sink
from drsplat.registration.vote import FULL_VIEW, PRESENCE, VOTE_PARTS, MaskClusters, _row_aligned_cuts, _rows_order, space_saving_slot

log = logging.getLogger(__name__)

CHECK_MIN_VIEWS = 2.0  # a mask is judged only where its Gaussians' other views hold at least this many views' votes for one label
CHECK_SUPPORT = 0.1  # dropped when its own label's support is below this share of the best other label's
SUPPORT_CACHE_BYTES = 256 << 20  # the views' support tables kept between the check's two passes when they fit in this


@dataclass
class MaskVerdicts:
    """The check's outcome: keep [V] arrays of [M_v] bool per view (True: the mask's pairs are summed),
    and the masks it dropped, judged (with enough evidence to judge) and present (with pairs)."""

    keep: list[np.ndarray]
    dropped: int
    judged: int
    present: int
    like: float | None = None  # the scene's "like" cosine (`like_threshold`), None: too little to judge


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


def check_reference(views: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]], num_gaussians: int,
                    means: np.ndarray, like: float | None = None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Obviously-correct reference of step 2 with unbounded slots (numpy, float64).

    views: per view (gaussians [P], masks [P], weights [P], cluster of each mask [M] (-1 none),
    embeddings [M, D]). means: [K, D] unit cluster means. like: the "like" cosine (None: own and alt
    are 0). Returns per view (mass [M], total [M], agree [M], own [M], alt [M]) as `_agreement_kernel`
    and `_own_alt_kernel` define them (agrees with `check_masks`' kernels whenever no Gaussian meets
    more than CHECK_SLOTS clusters).
    """
    k = means.shape[0]
    means = means.astype(np.float64)
    votes = [view_votes_reference(g, c[m], w, num_gaussians, k) for g, m, w, c, _ in views]
    V = np.sum(votes, axis=0) if votes else np.zeros((num_gaussians, k))
    out = []
    for (g, m, w, c, feats), own_votes in zip(views, votes):
        num_masks = c.shape[0]
        q = np.zeros((num_masks, k))
        np.add.at(q, m, w.astype(np.float64)[:, None] * (V - own_votes)[g])
        mass = np.bincount(m, w.astype(np.float64), num_masks)
        units = unit_rows(feats)
        units[c < 0] = 0.0
        has = mass > 0
        total = np.where(has, np.where(q > 0, q, 0.0).sum(axis=1) / np.where(has, mass, 1.0), 0.0)
        consensus = np.where(q > 0, q, 0.0) @ means
        norm = np.linalg.norm(consensus, axis=1)
        agree = np.where(has & (norm > 0), (consensus * units).sum(axis=1) / np.where(norm > 0, norm, 1.0), 0.0)
        own, alt = np.zeros(num_masks), np.zeros(num_masks)
        for j in np.flatnonzero(has) if like is not None else ():
            present = q[j] > 0
            is_like = present & (means @ units[j] >= like)
            unlike = present & ~is_like
            own[j] = q[j, is_like].sum() / mass[j]
            if unlike.any():
                best = int(np.flatnonzero(unlike)[np.argmax(q[j, unlike])])  # first of equal maxima
                alt[j] = q[j, unlike & (means @ means[best] >= like)].sum() / mass[j]
        out.append((mass, total, agree, own, alt))
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
def _fold_votes_kernel(rows, clusters, weights, order, presence, full_view, slot_c, slot_v):  # pragma: no cover - jitted
    """Step 1 for one view: each Gaussian's votes per cluster (`_group_votes`: one vote per view and
    cluster at most) added to its slots slot_c / slot_v [N, S] with the space-saving rule (a new
    cluster replaces the slot with the fewest votes and inherits them). order: the pairs sorted by
    row (`_rows_order`). A Gaussian's votes touch its own row only, so row-aligned parts of the
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
            for d in range(n_found):
                hit = space_saving_slot(slot_c, slot_v, r, found[d])
                slot_c[r, hit] = found[d]
                slot_v[r, hit] += votes[d]
            start = end


@numba.njit(cache=True)
def _support_kernel(rows, masks, weights, clusters, order, slot_c, slot_v, presence, full_view, q, mass):  # pragma: no cover - jitted
    """q[j, c] += Σ_{pairs (i, j)} w_ij (V_ic − v_icv) over the slots of Gaussian i, mass[j] += w_ij
    (one view, `view_support`, step 2). clusters: [P] the cluster of each pair's mask; order: the
    pairs sorted by row (`_rows_order`), so each Gaussian's pairs of the view are consecutive."""
    num_slots = slot_c.shape[1]
    n = order.shape[0]
    found = np.empty(n, np.int32)
    votes = np.empty(n)
    own = np.zeros(num_slots)
    start = 0
    while start < n:
        r = rows[order[start]]
        end = _run_end(rows, order, start)
        found_n = _group_votes(order, start, end, weights, clusters, presence, full_view, found, votes)
        for s in range(num_slots):  # the view's own votes per slot, so that a mask does not support itself
            own[s] = 0.0
            for d in range(found_n):
                if slot_c[r, s] == found[d]:
                    own[s] = votes[d]
        for i in range(start, end):
            p = order[i]
            w = np.float64(weights[p])
            j = masks[p]
            mass[j] += w
            for s in range(num_slots):
                c = slot_c[r, s]
                if c < 0:
                    break
                other = slot_v[r, s] - own[s]
                if other > 0.0:
                    q[j, c] += w * other
        start = end


@numba.njit(cache=True)
def _agreement_kernel(q, mass, units, means, agree, total):  # pragma: no cover - jitted
    """Per mask j: total[j] = Σ_c q[j, c] / mass[j] (the other views' votes, in views) and
    agree[j] = f̂_j · ĉ_j, ĉ_j = normalize(Σ_c q[j, c] μ_c) (the cosine between the mask's unit
    embedding and its Gaussians' consensus); 0 for masks without pairs or consensus."""
    num_masks, k = q.shape
    dim = means.shape[1]
    consensus = np.empty(dim)
    for j in range(num_masks):
        agree[j] = 0.0
        total[j] = 0.0
        if not mass[j] > 0.0:
            continue
        for d in range(dim):
            consensus[d] = 0.0
        for c in range(k):
            value = q[j, c]
            if value > 0.0:
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


@numba.njit(cache=True)
def _own_alt_kernel(q, mass, units, means, like, own, alt):  # pragma: no cover - jitted
    """own[j] = Σ_{c like j} q[j, c] / mass[j], "like" μ_c · f̂_j ≥ `like`; alt[j] = Σ_{c in the group
    of c*} q[j, c] / mass[j], c* the unlike cluster of largest q and its group the unlike clusters c
    with μ_c · μ_c* ≥ `like` (0 for masks without pairs). Dotted only where q > 0."""
    num_masks, k = q.shape
    dim = means.shape[1]
    sims = np.empty(k)
    for j in range(num_masks):
        own[j] = 0.0
        alt[j] = 0.0
        if not mass[j] > 0.0:
            continue
        best = -1
        for c in range(k):
            value = q[j, c]
            if not value > 0.0:
                continue
            sim = 0.0
            for d in range(dim):
                sim += np.float64(means[c, d]) * units[j, d]
            sims[c] = sim
            if sim >= like:
                own[j] += value
            elif best < 0 or value > q[j, best]:
                best = c
        if best >= 0:
            for c in range(k):
                if q[j, c] > 0.0 and sims[c] < like:
                    sim = 0.0
                    for d in range(dim):
                        sim += np.float64(means[c, d]) * np.float64(means[best, d])
                    if sim >= like:
                        alt[j] += q[j, c]
        own[j] /= mass[j]
        alt[j] /= mass[j]


class PairRecord:
    """The views' pairs as they arrived (gaussians, masks, weights) with their embeddings and the
    masks' clusters; what the check reads twice (support, then the kept sums)."""

    def __init__(self, dim: int):
        self.clusters = MaskClusters(dim)
        self.views: list[ViewPairs] = []

    def add(self, view: ViewPairs) -> np.ndarray:
        """Keep `view` (its host pairs) and return its masks' clusters [M] int32."""
        self.views.append(ViewPairs(view.name, view.feats, np.ascontiguousarray(view.gaussians, np.int32),
                                    np.ascontiguousarray(view.masks, np.int32), np.ascontiguousarray(view.weights, np.float32),
                                    view.used, view.num_pairs, view.num_nonfinite))
        return self.clusters.add(view.feats, view.present_masks())

    @property
    def nbytes(self) -> int:
        return sum(v.gaussians.nbytes + v.masks.nbytes + v.weights.nbytes + v.feats.nbytes for v in self.views)


def unit_rows(feats: np.ndarray) -> np.ndarray:
    """[M, D] float64 unit rows of feats (zero rows stay zero)."""
    f = np.asarray(feats, np.float64)
    norm = np.linalg.norm(f, axis=1, keepdims=True)
    return np.divide(f, norm, out=np.zeros_like(f), where=norm > 0)


@dataclass
class ViewSupport:
    """One view's masks as the check sees them: q [M, K] the other views' votes per cluster (divided
    by mass in own / alt / total), mass [M] = Σ_i w_ij, units [M, D] the unit embeddings."""

    q: np.ndarray
    mass: np.ndarray
    units: np.ndarray


def view_support(view: ViewPairs, clusters: np.ndarray, slot_c: np.ndarray, slot_v: np.ndarray, num_clusters: int,
                 presence: float = PRESENCE, full_view: float = FULL_VIEW) -> ViewSupport:
    """Step 2's q for one recorded view (`_support_kernel`). clusters: [M] the view's mask clusters;
    slot_c / slot_v: [N, S] the Gaussians' clusters and votes folded over all views (step 1)."""
    num_masks = clusters.shape[0]
    q = np.zeros((num_masks, num_clusters))
    mass = np.zeros(num_masks)
    if view.gaussians.size and num_clusters:
        _support_kernel(view.gaussians, view.masks, view.weights, np.ascontiguousarray(clusters[view.masks], np.int32),
                        _rows_order(view.gaussians), slot_c, slot_v, presence, full_view, q, mass)
    elif view.gaussians.size:
        np.add.at(mass, view.masks, view.weights.astype(np.float64))
    units = unit_rows(view.feats)
    units[clusters < 0] = 0.0  # a mask without a cluster (dropped for non-finite values) is never judged
    return ViewSupport(q, mass, units)


def like_threshold(agreements: np.ndarray, view_units: list[np.ndarray]) -> float | None:
    """The scene's "like" cosine, halfway between what a mask's consensus usually is and what two
    different things are: ½ (median agreement of the judged masks + median cosine between two
    masks of one view, which show different instances). None when either is missing (then nothing
    is dropped). agreements: [J]; view_units: per view [M, D] the unit embeddings of its masks with pairs."""
    between = []
    for units in view_units:
        units = units[np.linalg.norm(units, axis=1) > 0]
        if units.shape[0] > 1:
            cos = units @ units.T
            between.append(cos[np.triu_indices(units.shape[0], 1)])
    if agreements.size == 0 or not between:
        return None
    return 0.5 * (float(np.median(agreements)) + float(np.median(np.concatenate(between))))


def check_masks(record: PairRecord, slot_c: np.ndarray, slot_v: np.ndarray, min_views: float = CHECK_MIN_VIEWS,
                min_share: float = CHECK_SUPPORT) -> MaskVerdicts:
    """Steps 2 (module docstring) on the record and the folded slots: the verdict on every mask.
    Two passes over the views; each view's support ([M, K] q, its masses and unit embeddings) is
    kept between them when all of them fit in SUPPORT_CACHE_BYTES, else computed again (the same bits)."""
    means = np.ascontiguousarray(record.clusters.means(), np.float32)
    k = means.shape[0]
    agreements, units_with_pairs = [], []
    size = sum(c.shape[0] * (k + 1 + means.shape[1]) * 8 for c in record.clusters.per_view)
    kept = [] if size <= SUPPORT_CACHE_BYTES else None  # q, mass and units of every view, for the second pass
    for view, clusters in zip(record.views, record.clusters.per_view):
        sup = view_support(view, clusters, slot_c, slot_v, k)
        if kept is not None:
            kept.append(sup)
        agree, total = np.zeros(clusters.shape[0]), np.zeros(clusters.shape[0])
        _agreement_kernel(sup.q, sup.mass, sup.units, means, agree, total)
        agreements.append(agree[(total >= min_views) & (np.linalg.norm(sup.units, axis=1) > 0)])
        units_with_pairs.append(sup.units[sup.mass > 0])
    like = like_threshold(np.concatenate(agreements) if agreements else np.zeros(0), units_with_pairs)
    keep, dropped, judged, present = [], 0, 0, 0
    for index, (view, clusters) in enumerate(zip(record.views, record.clusters.per_view)):
        sup = kept[index] if kept is not None else view_support(view, clusters, slot_c, slot_v, k)
        own, alt = np.zeros(clusters.shape[0]), np.zeros(clusters.shape[0])
        if like is not None:
            _own_alt_kernel(sup.q, sup.mass, sup.units, means, like, own, alt)
        judge = (sup.mass > 0) & (alt >= min_views)
        drop = judge & (own < min_share * alt)
        keep.append(~drop)
        dropped += int(drop.sum())
        judged += int(judge.sum())
        present += int((sup.mass > 0).sum())
    return MaskVerdicts(keep, dropped, judged, present, like)


def kept_pairs(record: PairRecord, keep: list[np.ndarray], num_gaussians: int) -> list[np.ndarray]:
    """Per view, [P] bool: the pairs of kept masks, and every pair of a Gaussian that would keep none
    (step 3: which Gaussians are assigned does not change)."""
    kept = [k[v.masks] for v, k in zip(record.views, keep)]
    any_kept = np.zeros(num_gaussians, bool)
    for view, k in zip(record.views, kept):
        any_kept[view.gaussians[k & (view.weights > 0)]] = True
    return [k | ~any_kept[v.gaussians] for v, k in zip(record.views, kept)]


class CheckSink:
    """A sink (drsplat.registration.sink) whose blocks are `inner`'s sums of the pairs the check keeps.

    `add` records each view and folds its presence votes into the slots (step 1); the first call of
    `blocks` or `sample` judges the masks (step 2), replays the kept pairs into `inner` in view
    order (step 3) and frees the record. One block of all N Gaussians, on the host."""

    place = "host"
    num_blocks = 1

    def __init__(self, num_gaussians: int, dim: int, inner: Sink, slots: int = CHECK_SLOTS):
        self.num_gaussians = num_gaussians
        self.inner = inner
        self.record = PairRecord(dim)
        self._slot_c = np.full((num_gaussians, slots), -1, np.int32)
        self._slot_v = np.zeros((num_gaussians, slots))
        self.verdicts: MaskVerdicts | None = None

    def add(self, view: ViewPairs) -> None:
        clusters = self.record.add(view)
        kept = self.record.views[-1]
        if kept.gaussians.size:
            _fold_votes_kernel(kept.gaussians, np.ascontiguousarray(clusters[kept.masks], np.int32), kept.weights, _rows_order(kept.gaussians),
                               PRESENCE, FULL_VIEW, self._slot_c, self._slot_v)

    def _judge(self) -> None:
        if self.verdicts is not None:
            return
        record = self.record
        self.verdicts = check_masks(record, self._slot_c, self._slot_v)
        like = "none" if self.verdicts.like is None else f"{self.verdicts.like:.3f}"
        log.info("mask check: %d of %d masks dropped (%d had enough other views to judge; like cosine %s; record of the pairs %s)",
                 self.verdicts.dropped, self.verdicts.present, self.verdicts.judged, like, format_size(record.nbytes))
        self._slot_c = self._slot_v = None  # the inner sink's sums take their place
        for view, keep in zip(record.views, kept_pairs(record, self.verdicts.keep, self.num_gaussians)):
            self.inner.add(ViewPairs(view.name, view.feats, view.gaussians[keep], view.masks[keep], view.weights[keep], view.used,
                                     view.num_pairs, view.num_nonfinite))
        self.record = None

    def blocks(self) -> Iterator[Block]:
        self._judge()
        yield from self.inner.blocks()

    def sample(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self._judge()
        return self.inner.sample(ids)
