"""Coalescing and per-Gaussian sums on the torch engine's device (drsplat.registration.device_sums),
held to the numba coalescer and the host accumulator, and registration through them."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest
import torch

from drsplat.bench.opcount import OpCounter
from drsplat.defaults import VOTE_SLOT_BYTES
from drsplat.errors import InputError
from drsplat.registration import RegisterOptions, register, register_features
from drsplat.registration.coalesce import Coalescer, coalesce_reference
from drsplat.registration.device_sums import DeviceSink, coalesce_pairs, coalesce_pairs_op, coalesce_torch, slot_sums
from drsplat.registration.pairlog import ViewPairs
from drsplat.registration.sink import MemorySink

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def random_view(seed: int, h: int, w: int, k: int, n: int, m: int, empty: float = 0.2, unmasked: float = 0.2):
    """ids [h, w, k] (distinct per pixel, -1 for a share `empty`), weights (0, 1], masks [h, w] (-1 for a share `unmasked`)."""
    rng = np.random.default_rng(seed)
    ids = np.stack([rng.permutation(n)[:k] for _ in range(h * w)]).reshape(h, w, k).astype(np.int32) if h * w else np.zeros((h, w, k), np.int32)
    ids[rng.random(ids.shape) < empty] = -1
    weights = rng.uniform(1e-4, 1.0, ids.shape).astype(np.float32)
    masks = rng.integers(0, m, (h, w)).astype(np.int32)
    masks[rng.random((h, w)) < unmasked] = -1
    return ids, weights, masks


def hard_views():
    """(name, ids, weights, masks, num_masks, num_gaussians): the cases a coalescer gets wrong first."""
    ids, weights, masks = random_view(7, 6, 5, 4, 30, 3)
    yield "empty view", np.zeros((0, 0, 4), np.int32), np.zeros((0, 0, 4), np.float32), np.zeros((0, 0), np.int32), 3, 30
    yield "one mask", ids, weights, np.zeros_like(masks), 1, 30
    yield "k = 1", *random_view(8, 9, 7, 1, 40, 4), 4, 40
    yield "all pixels masked out", ids, weights, np.full_like(masks, -1), 3, 30
    yield "every id -1", np.full_like(ids, -1), weights, masks, 3, 30
    yield "one Gaussian everywhere", np.where(ids >= 0, 0, -1).astype(np.int32), weights, masks, 3, 30
    yield "unused masks", ids, weights, masks, 50, 30
    yield "one pixel", ids[:1, :1], weights[:1, :1], masks[:1, :1], 3, 30


def random_views():
    for seed, (h, w, k, n, m) in enumerate([(12, 10, 5, 80, 6), (20, 16, 16, 400, 12), (8, 8, 40, 60, 2), (30, 20, 3, 5000, 30)]):
        yield f"random {h}x{w} k={k}", *random_view(seed, h, w, k, n, m), m, n


CASES = list(random_views()) + list(hard_views())


def torch_pairs(ids, weights, masks, num_masks, num_gaussians, coalesce=coalesce_torch):
    """`coalesce`'s pairs on the host, trimmed to the count it reports, and its counts."""
    pairs = coalesce(torch.from_numpy(ids), torch.from_numpy(weights), torch.from_numpy(masks), num_masks, num_gaussians)
    distinct, contributing = (int(c) for c in pairs.counts)
    return (*pairs.trimmed(distinct).to_host(), distinct, contributing)


@pytest.mark.parametrize("coalesce", [coalesce_torch, coalesce_pairs], ids=["torch ops", "op"])
@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_device_pairs_equal_numba_pairs(case, coalesce):
    """The same pairs as the numba coalescer with the same float32 weights (sums in the same order);
    sorted by (mask, Gaussian), so each Gaussian meets its masks in numba's order. Both the torch
    ops and the op (the numba coalescer behind it on a CPU)."""
    _, ids, weights, masks, num_masks, n = case
    g, m, w, pairs = Coalescer(n).coalesce(ids, weights, masks, num_masks)
    tg, tm, tw, distinct, contributing = torch_pairs(ids, weights, masks, num_masks, n, coalesce)
    assert (distinct, contributing) == (g.shape[0], pairs)
    order = np.lexsort((tg, tm))
    np.testing.assert_array_equal(order, np.arange(distinct), err_msg="pairs sorted by (mask, Gaussian)")
    by_gaussian, numba_by_gaussian = np.argsort(tg, kind="stable"), np.argsort(g, kind="stable")
    np.testing.assert_array_equal(tg[by_gaussian], g[numba_by_gaussian])
    np.testing.assert_array_equal(tm[by_gaussian], m[numba_by_gaussian], err_msg="a Gaussian's masks in numba's order")
    np.testing.assert_array_equal(tw[by_gaussian], w[numba_by_gaussian])
    rg, rm, rw, rpairs = coalesce_reference(ids, weights, masks, num_masks)
    assert rpairs == contributing
    np.testing.assert_array_equal(np.stack([tm, tg]), np.stack([rm, rg]))
    np.testing.assert_allclose(tw, rw, rtol=1e-5)


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_the_coalescing_op_equals_the_torch_ops(case):
    """Pairs, counts and mask flags of the op (numba behind it on a CPU) equal coalesce_torch's, bit
    for bit, also with mask ids past the view's masks (no pair, as for -1); the op is one dispatcher
    call without a host sync."""
    _, ids, weights, masks, num_masks, n = case
    masks = np.where(masks == 1, num_masks + 3, masks).astype(masks.dtype)
    args = (torch.from_numpy(ids), torch.from_numpy(weights), torch.from_numpy(masks), num_masks, n)
    want = coalesce_torch(*args)
    with OpCounter() as counter:
        got = coalesce_pairs(*args)
    assert counter.counts.by_name["drsplat::coalesce_pairs"] == 1 and counter.counts.syncs == 0
    assert torch.equal(got.counts, want.counts) and torch.equal(got.mask_flags, want.mask_flags)
    distinct = int(want.counts[0])
    assert got.gaussians.shape[0] == distinct, "on a CPU exactly the distinct pairs"
    for a, b in zip(got.trimmed(distinct).to_host(), want.trimmed(distinct).to_host()):
        assert a.tobytes() == b.tobytes()


def test_the_coalescing_op_names_mismatched_shapes():
    ids, weights, masks = (torch.from_numpy(a) for a in random_view(5, 9, 7, 4, 60, 5))
    with pytest.raises(ValueError, match=r"mask ids \(7, 9\) \[H, W\]"):
        coalesce_pairs(ids, weights, masks.t(), 5, 60)
    with pytest.raises(ValueError, match=r"must be \[H, W, k\]"):
        coalesce_pairs(ids, weights[..., :2], masks, 5, 60)


def test_the_coalescing_op_passes_torch_opcheck():
    ids, weights, masks = (torch.from_numpy(a) for a in random_view(5, 9, 7, 4, 60, 5))
    torch.library.opcheck(coalesce_pairs_op, (ids, weights, masks, 5, 60), test_utils=("test_schema", "test_faketensor"))


def test_pairs_sorted_within_masks_equal_a_lexsort():
    from drsplat.registration.coalesce import sort_within_masks

    rng = np.random.default_rng(3)
    masks = np.sort(rng.integers(0, 7, 500)).astype(np.int32)
    gaussians = np.concatenate([rng.permutation(1000)[: int((masks == j).sum())] for j in range(7)]).astype(np.int32)
    weights = rng.random(500).astype(np.float32)
    order = np.lexsort((gaussians, masks))
    want = gaussians[order], masks[order], weights[order]
    sort_within_masks(gaussians, masks, weights)
    for a, b in zip((gaussians, masks, weights), want):
        np.testing.assert_array_equal(a, b)
    empty = np.zeros(0, np.int32)
    sort_within_masks(empty, empty, np.zeros(0, np.float32))


def test_coalescing_sorts_keys_past_int32_the_same_way():
    """Keys mask·N + Gaussian below 2^31 are sorted as int32 (half a radix sort's passes); a scene whose
    keys pass 2^31 (here 20 masks x 2^27 Gaussians) sorts them as int64, with the same pairs."""
    ids, weights, masks = random_view(11, 14, 10, 6, 40, 20)
    small = torch_pairs(ids, weights, masks, 20, 40)
    large = torch_pairs(ids, weights, masks, 20, 2**27)
    assert 20 * 2**27 > 2**31 and small[3] > 10
    for a, b in zip(small, large):
        np.testing.assert_array_equal(a, b)


def test_coalescing_never_waits_for_the_device():
    ids, weights, masks = (torch.from_numpy(a) for a in random_view(3, 16, 12, 8, 300, 9))
    with OpCounter() as counter:
        coalesce_torch(ids, weights, masks, 9, 300)
    assert counter.counts.syncs == 0, dict(counter.counts.syncs_by_name)
    assert counter.counts.ops < 60


WEIGHTINGS = ("paper", "responsibility", "core", "ellipse", "centre", "anchor", "sharp")


def projection(seed: int, n: int, h: int, w: int):
    """Screen means [n, 2] (some exactly on pixel edges, some off screen) and conics [n, 3] (some degenerate)."""
    rng = np.random.default_rng(seed)
    means2d = np.stack([rng.uniform(-2, w + 2, n), rng.uniform(-2, h + 2, n)], 1)
    means2d[: n // 4] = np.floor(means2d[: n // 4])  # centres on pixel corners: floor decides the centre pixel
    a, c = rng.uniform(0.05, 2.0, n), rng.uniform(0.05, 2.0, n)
    b = rng.uniform(-1, 1, n) * np.sqrt(a * c)
    b[n // 4 : n // 3] = np.sqrt(a * c)[n // 4 : n // 3] * 1.5  # det < 0: no footprint area
    return means2d, np.stack([a, b, c], 1)


@pytest.mark.parametrize("weighting", WEIGHTINGS)
@pytest.mark.parametrize("case", ["random", "all empty", "k = 1"])
def test_device_weightings_equal_numba(weighting, case):
    """Each per-view weighting ported to torch gives the numba kernel's float32 weights (and the reference's)."""
    from drsplat.registration.aggregate import view_weights, view_weights_reference
    from drsplat.registration.device_sums import view_weights_torch

    h, w, n = 14, 11, 60
    ids, weights, _ = random_view(5, h, w, 1 if case == "k = 1" else 6, n, 3)
    if case == "all empty":
        ids[:] = -1
    means2d, conics = projection(6, n, h, w)
    want = view_weights(weighting, ids, weights, means2d, conics)
    got = view_weights_torch(weighting, *(torch.from_numpy(a) for a in (ids, weights, means2d, conics))).numpy()
    np.testing.assert_array_equal(got, want)
    np.testing.assert_allclose(got, view_weights_reference(weighting, ids, weights, means2d, conics), rtol=1e-6)
    if weighting != "paper" and case == "random":
        assert not np.array_equal(got, weights * (ids >= 0)), "the weighting changed something"


EXPLAIN_CASES = [
    ("random", *random_view(11, 14, 11, 6, 60, 4)),
    ("k = 1", *random_view(12, 9, 7, 1, 40, 3)),
    ("k = 40, few Gaussians", *random_view(13, 6, 5, 40, 45, 2, empty=0.5)),
    ("every id -1", np.full((5, 4, 3), -1, np.int32), np.ones((5, 4, 3), np.float32), np.zeros((5, 4), np.int32)),
    ("no masks", *random_view(14, 7, 6, 4, 30, 3, unmasked=1.0)),
    ("one Gaussian everywhere", np.zeros((6, 5, 1), np.int32), np.full((6, 5, 1), 0.5, np.float32), np.arange(30).reshape(6, 5).astype(np.int32) % 3),
    ("zero weights", random_view(15, 8, 8, 5, 50, 4)[0], np.zeros((8, 8, 5), np.float32), random_view(15, 8, 8, 5, 50, 4)[2]),
    ("empty view", np.zeros((0, 0, 4), np.int32), np.zeros((0, 0, 4), np.float32), np.zeros((0, 0), np.int32)),
]


@pytest.mark.parametrize("case,ids,weights,masks", EXPLAIN_CASES, ids=[c[0] for c in EXPLAIN_CASES])
def test_device_explain_equals_the_numba_em(case, ids, weights, masks):
    """The explain EM on the device gives the numba kernel's float32 weights bit for bit (its sums in the
    kernel's order), for 0, 1 and 3 iterations, without waiting for the device."""
    from drsplat.registration.aggregate import explain_weights
    from drsplat.registration.device_sums import explain_weights_torch

    n = int(max(ids.max(initial=-1) + 1, 1))
    for iterations in (0, 1, 3):
        want = explain_weights(ids, weights, masks, n, iterations=iterations)
        with OpCounter() as counter:
            got = explain_weights_torch(*(torch.from_numpy(a) for a in (ids, weights, masks)), n, iterations).numpy()
        assert got.tobytes() == want.tobytes(), f"{iterations} iterations: max |Δ| {np.abs(got - want).max(initial=0):.3e}"
        assert counter.counts.syncs == 0, dict(counter.counts.syncs_by_name)
    if case == "random":
        assert not np.array_equal(got, np.where((ids >= 0) & (masks[..., None] >= 0), weights, 0)), "the EM moved some weight"


def views_of(seed: int, count: int, n: int, dim: int):
    """`count` views' (DevicePairs, feats, host arrays) of random top-k lists over n Gaussians."""
    rng = np.random.default_rng(seed)
    for v in range(count):
        m = int(rng.integers(1, 9))
        ids, weights, masks = random_view(seed * 100 + v, 10, 9, 6, n, m)
        feats = rng.normal(size=(m, dim)).astype(np.float32)
        pairs = coalesce_torch(torch.from_numpy(ids), torch.from_numpy(weights), torch.from_numpy(masks), m, n)
        distinct, contributing = (int(c) for c in pairs.counts)
        g, mk, w, _ = Coalescer(n).coalesce(ids, weights, masks, m)
        none = np.zeros(0, np.int32)
        device_view = ViewPairs(f"v{v}", feats, none, none, np.zeros(0, np.float32), none, contributing, device=pairs.trimmed(distinct))
        host_view = ViewPairs(f"v{v}", feats, g, mk, w, none, contributing)
        yield device_view, host_view


def test_device_sink_sums_equal_the_host_accumulator():
    """Device pairs and replayed host pairs, mixed, give the host sums' bits (on the CPU); the sums
    reach the host as one block; `positive` and `sample` agree with the host sink."""
    n, dim = 3000, 16
    device_sink, host_sink = DeviceSink(n, dim, "cpu", chunk=7), MemorySink(n, dim)
    for v, (device_view, host_view) in enumerate(views_of(1, 6, n, dim)):
        device_sink.add(host_view if v % 3 == 2 else device_view)  # every third view as a log replay gives it
        host_sink.add(host_view)
    ids = np.array([0, 5, 17, 2999])
    for got, want in zip(device_sink.sample(ids), host_sink.sample(ids)):
        np.testing.assert_array_equal(got, want)
    (block,), (want,) = list(device_sink.blocks()), list(host_sink.blocks())
    assert (block.lo, block.hi) == (0, n)
    np.testing.assert_array_equal(block.F, want.F)
    np.testing.assert_array_equal(block.W, want.W)
    assert block.W.any() and not block.W.all()
    np.testing.assert_array_equal(device_sink.positive(), want.W > 0)


CUDA = pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU"))


@pytest.mark.parametrize("device", ["cpu", CUDA])
@pytest.mark.parametrize("slots,presence", [(8, 0.1), (2, 0.1), (3, 0.0)])
def test_vote_slots_fold_on_the_device_as_the_kernel(slots, presence, device):
    """vote_view_torch against the plain-loop reference and the numba kernel (pairs walked row by row,
    what VoteSink does): the same slots bit for bit, over views whose Gaussians meet more clusters
    than slots (space-saving replacements), pairs without a cluster, zero weights, and presence 0
    (votes = weights). Bit for bit on CUDA too: a round writes each slot once, with no atomics."""
    from drsplat.registration.device_sums import vote_view_torch
    from drsplat._sort_kernels import stable_order
    from drsplat.registration.vote import FULL_VIEW, _vote_view_kernel, vote_view_reference

    n, rng = 25, np.random.default_rng(slots)
    host = (np.full((n, slots), -1, np.int32), np.zeros((n, slots)), np.zeros((n, slots)))
    by_row = tuple(a.copy() for a in host)  # the kernel: pairs walked row by row, in parallel over row-aligned parts
    dev = (torch.full((n, slots), -1, dtype=torch.int32, device=device), torch.zeros((n, slots), dtype=torch.float64, device=device),
           torch.zeros((n, slots), dtype=torch.float64, device=device))
    scratch = np.zeros(n)
    for _ in range(12):
        p = int(rng.integers(0, 60))
        rows = rng.integers(0, n, p).astype(np.int32)
        clusters = rng.integers(-1, 9, p).astype(np.int32)
        weights = rng.uniform(0, 1, p).astype(np.float32)
        weights[rng.random(p) < 0.1] = 0.0
        vote_view_reference(rows, clusters, weights, presence, FULL_VIEW, *host)
        _vote_view_kernel(rows, clusters, weights, stable_order(rows), presence, FULL_VIEW, scratch, *by_row)
        vote_view_torch(torch.from_numpy(rows.astype(np.int64)).to(device), torch.from_numpy(clusters.astype(np.int64)).to(device),
                        torch.from_numpy(weights).to(device), presence, FULL_VIEW, *dev)
    for want, got, walked in zip(host, dev, by_row):
        np.testing.assert_array_equal(got.cpu().numpy(), want)
        np.testing.assert_array_equal(walked, want)
    assert (host[0] >= 0).all(axis=1).any(), "some Gaussian filled its slots"


def mislabelled_views(seed: int, count: int, n: int, dim: int):
    """views_of's pairs, but every mask of a view shows one object (its embedding near A), except
    in two views, where a third of the masks carry other embeddings (mislabels the vote trims)."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=dim)
    for v in range(count):
        m = 3
        ids, weights, masks = random_view(seed * 100 + v, 10, 9, 6, n, m)
        feats = (a + 0.01 * rng.normal(size=(m, dim))).astype(np.float32)
        if v in (1, 5):
            feats[2] = rng.normal(size=dim)
        pairs = coalesce_torch(torch.from_numpy(ids), torch.from_numpy(weights), torch.from_numpy(masks), m, n)
        distinct, contributing = (int(c) for c in pairs.counts)
        g, mk, w, _ = Coalescer(n).coalesce(ids, weights, masks, m)
        none = np.zeros(0, np.int32)
        yield (ViewPairs(f"v{v}", feats, none, none, np.zeros(0, np.float32), none, contributing, device=pairs.trimmed(distinct)),
               ViewPairs(f"v{v}", feats, g, mk, w, none, contributing))


@pytest.mark.parametrize("lagged", [False, True], ids=["folded now (the op)", "folded a view late (CUDA without Triton)"])
def test_device_vote_sink_equals_the_host_vote_sink(lagged):
    """DeviceVoteSink (device pairs and replayed host pairs, mixed) gives VoteSink's trimmed sums,
    W and samples bit for bit; with two slots per Gaussian, so clusters are replaced. Both ways of
    folding: each view by the vote op, or its rounds laid out and folded when the next view comes."""
    from drsplat.registration.device_sums import DeviceVoteSink
    from drsplat.registration.vote import VoteSink

    n, dim = 40, 8
    device_sink, host_sink, paper = DeviceVoteSink(n, dim, "cpu", slots=2), VoteSink(n, dim, slots=2), MemorySink(n, dim)
    device_sink.lagged = lagged
    for v, (device_view, host_view) in enumerate(mislabelled_views(6, 9, n, dim)):
        device_sink.add(host_view if v % 3 == 2 else device_view)
        host_sink.add(host_view)
        paper.add(host_view)
    assert device_sink.clusters.count == host_sink.clusters.count > 2
    ids = np.array([0, 3, 39])  # sampled before the blocks, as the driver does (the host sink trims its sums in place)
    for a, b in zip(device_sink.sample(ids), host_sink.sample(ids)):
        np.testing.assert_array_equal(a, b)
    (got,), (want,) = list(device_sink.blocks()), list(host_sink.blocks())
    np.testing.assert_array_equal(got.F, want.F)
    np.testing.assert_array_equal(got.W, want.W)
    assert not np.array_equal(got.F, next(paper.blocks()).F), "the vote trimmed something"


def test_device_pairs_reach_the_host_for_the_log():
    n, dim = 50, 4
    for device_view, host_view in views_of(2, 3, n, dim):
        copied = device_view.on_host()
        assert copied.num_distinct == host_view.num_distinct == device_view.num_distinct
        order, want = np.lexsort((copied.gaussians, copied.masks)), np.lexsort((host_view.gaussians, host_view.masks))
        for a, b in ((copied.gaussians, host_view.gaussians), (copied.masks, host_view.masks), (copied.weights, host_view.weights)):
            np.testing.assert_array_equal(a[order], b[want])
        assert host_view.on_host() is host_view


def stats_view(seed: int, h: int, w: int, k: int, n: int, case: str = "random"):
    """(RayGeometry, camera, ids [h, w, k] with -1 padding last, weights, median ids [h, w]) of
    random Gaussians in front of a random camera; the cases: flat and round Gaussians, zero
    precisions (dᵀΣ⁻¹d = 0: the mean's depth), a share of pixels without a median."""
    from drsplat.cameras import Camera
    from drsplat.registration.aggregate import RayGeometry

    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    cam = Camera(q * np.sign(np.linalg.det(q)), rng.normal(size=3) * 0.3, 0.9 * w, 0.9 * w, w / 2 + 0.3, h / 2 - 0.2, w, h)
    means = (rng.normal(size=(n, 3)) * 0.5 + np.array([0.0, 0.0, 4.0]) - cam.t) @ cam.R  # world points that land in front
    axes = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]
    scales = rng.uniform(0.02, 0.4, (n, 3))
    scales[: n // 3, 2] = 1e-6  # flat
    prec = np.einsum("nij,nj,nkj->nik", axes, 1.0 / scales**2, axes)
    packed = np.stack([prec[:, 0, 0], prec[:, 0, 1], prec[:, 0, 2], prec[:, 1, 1], prec[:, 1, 2], prec[:, 2, 2]], 1)
    packed[n // 3 : n // 3 + n // 10] = 0.0  # no precision: the ray depth is the mean's depth
    rays = RayGeometry(means, np.ascontiguousarray(packed), 3.0 * scales.max(1))
    ids, weights, _ = random_view(seed, h, w, k, n, 2)
    order = np.argsort(ids < 0, axis=-1, kind="stable")  # the rasterizer's rule: -1 padding after the entries
    ids, weights = np.take_along_axis(ids, order, -1), np.take_along_axis(weights, order, -1)
    weights[ids < 0] = 0.0
    median = np.where(rng.random((h, w)) < 0.2, -1, ids[..., 0]).astype(np.int32)
    if case == "no median":
        median[:] = -1
    elif case == "every slot empty":
        ids[:], weights[:], median[:] = -1, 0.0, -1
    return rays, cam, ids, weights, median


STATS_CASES = [("random", 14, 11, 6, 90), ("random", 9, 13, 1, 40), ("random", 1, 1, 40, 60), ("no median", 8, 8, 5, 30),
               ("every slot empty", 6, 5, 4, 20)]


@pytest.mark.parametrize("case,h,w,k,n", STATS_CASES, ids=[f"{c[0]} {c[1]}x{c[2]} k={c[3]}" for c in STATS_CASES])
def test_device_floater_statistics_equal_numba(case, h, w, k, n):
    """The in-front flags and the per-view max / sums of a `-reject` mode, computed in torch, are
    the numba kernels' bits (and the numpy reference's statistics)."""
    from drsplat.registration.aggregate import surface_stats, surface_stats_reference
    from drsplat.registration.device_sums import DeviceRays, front_flags_torch, view_stats_torch

    rays, cam, ids, weights, median = stats_view(3 + h, h, w, k, n, case)
    want, scratch = surface_stats(rays, cam, ids, weights, median, keep_flags=True)
    flags = front_flags_torch(DeviceRays.from_host(rays, torch.device("cpu")), cam, torch.from_numpy(ids), torch.from_numpy(median))
    np.testing.assert_array_equal(flags.numpy(), scratch.flags)
    if case == "random" and k > 1:
        assert 0 < flags.sum() < (ids >= 0).sum(), "some slots in front, some not"
    got = view_stats_torch(torch.from_numpy(ids), torch.from_numpy(weights), flags, n)
    np.testing.assert_array_equal(np.flatnonzero(got.touched.numpy()), np.sort(want.ids))
    for name in ("peak", "total", "front"):
        dense = np.zeros(n)
        dense[want.ids] = getattr(want, name)
        np.testing.assert_array_equal(getattr(got, name).numpy(), dense)
    reference = surface_stats_reference(rays, cam, ids, weights, median)
    np.testing.assert_array_equal(reference.ids, np.flatnonzero(got.touched.numpy()))
    np.testing.assert_allclose(got.front.numpy()[reference.ids], reference.front, rtol=1e-12)


@pytest.mark.parametrize("case,h,w,k,n", STATS_CASES, ids=[f"{c[0]} {c[1]}x{c[2]} k={c[3]}" for c in STATS_CASES])
def test_the_peak_over_copies_of_its_table_is_the_same_bits(case, h, w, k, n):
    """The per-Gaussian max taken over R copies of its table (spread by pixel, as on CUDA) is the
    one-table max bit for bit, for every R."""
    from drsplat.registration.device_sums import DeviceRays, front_flags_torch, view_stats_torch

    rays, cam, ids, weights, median = stats_view(3 + h, h, w, k, n, case)
    flags = front_flags_torch(DeviceRays.from_host(rays, torch.device("cpu")), cam, torch.from_numpy(ids), torch.from_numpy(median))
    want = view_stats_torch(torch.from_numpy(ids), torch.from_numpy(weights), flags, n, replicas=1)
    for replicas in (2, 3, 16, 64):
        got = view_stats_torch(torch.from_numpy(ids), torch.from_numpy(weights), flags, n, replicas=replicas)
        for name in ("peak", "total", "front", "touched"):
            assert getattr(got, name).numpy().tobytes() == getattr(want, name).numpy().tobytes(), (replicas, name)


def test_scatter_max_over_copies_on_hard_rows():
    """One row hit by every entry, rows never hit, zeros, ties, a value past float32, NaN: R copies
    give the one-table maxima for every R (NaN where a row holds one)."""
    from drsplat.registration.device_sums import scatter_max

    rng = np.random.default_rng(11)
    rows = np.concatenate([np.zeros(500, np.int64), rng.integers(2, 9, 300)])  # row 1 and rows 9.. never hit
    values = np.concatenate([rng.uniform(0, 1, 500), rng.choice([0.0, 0.5, 0.5, 1e300], 300)])
    values[700] = np.nan
    lanes = np.arange(rows.size, dtype=np.int64) // 3
    want = scatter_max(torch.from_numpy(rows), torch.from_numpy(values), 12)
    expected = np.zeros(12)
    for r in range(12):
        hit = values[rows == r]
        expected[r] = np.max(hit) if hit.size and not np.isnan(hit).any() else (np.nan if hit.size else 0.0)
    np.testing.assert_array_equal(want.numpy(), expected)
    for replicas in (2, 5, 32):
        got = scatter_max(torch.from_numpy(rows), torch.from_numpy(values), 12, torch.from_numpy(lanes), replicas)
        assert got.numpy().tobytes() == want.numpy().tobytes(), replicas


def test_the_peak_table_copies_stay_within_their_bytes():
    """As many copies as PEAK_REPLICAS on CUDA while the table fits PEAK_TABLE_BYTES, fewer for larger
    scenes, never fewer than one; one on a CPU."""
    from drsplat.registration.device_sums import PEAK_REPLICAS, PEAK_TABLE_BYTES, peak_replicas

    cuda = torch.device("cuda")
    assert peak_replicas(1000, cuda) == PEAK_REPLICAS and peak_replicas(1000, torch.device("cpu")) == 1
    assert peak_replicas(0, cuda) == PEAK_REPLICAS
    for rows in (542_105, 5_000_000, 20_000_000, 50_000_000, 10**9):
        replicas = peak_replicas(rows, cuda)
        assert replicas == 1 or 8 * replicas * rows <= PEAK_TABLE_BYTES, rows  # within the bytes
        assert replicas == PEAK_REPLICAS or 16 * replicas * rows > PEAK_TABLE_BYTES, rows  # and no fewer copies than fit
    assert peak_replicas(50_000_000, cuda) == 1 and 1 < peak_replicas(5_000_000, cuda) < PEAK_REPLICAS


def test_device_support_folds_to_the_host_bits():
    """Views folded on the device, after a host snapshot of earlier ones (a resume), give the host
    fold's arrays bit for bit, and the same rejected mask."""
    from drsplat.registration.aggregate import SurfaceSupport, surface_stats
    from drsplat.registration.device_sums import DeviceRays, front_flags_torch, view_stats_torch

    n = 70
    host, device = SurfaceSupport.zeros(n), None
    for v in range(8):
        rays, cam, ids, weights, median = stats_view(40 + v, 10, 12, 5, n)
        stats, _ = surface_stats(rays, cam, ids, weights, median)
        host.add(stats)
        flags = front_flags_torch(DeviceRays.from_host(rays, torch.device("cpu")), cam, torch.from_numpy(ids), torch.from_numpy(median))
        view = view_stats_torch(torch.from_numpy(ids), torch.from_numpy(weights), flags, n)
        if v == 3:  # the first views as a snapshot on the host, as a resumed run gets them
            device = SurfaceSupport.from_arrays(device.arrays())
        device = view.support_for(device if device is not None else SurfaceSupport.zeros(n))
        device.add(view)
    for name, values in host.arrays().items():
        np.testing.assert_array_equal(device.arrays()[name], values)
    np.testing.assert_array_equal(device.rejected(), host.rejected())
    assert host.views_front.any() and (host.views_seen > 1).any()


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    from drsplat.cameras import load_cameras
    from drsplat.scene import load_ply
    from drsplat.synthetic import write_dataset

    data = write_dataset(tmp_path_factory.mktemp("devsum") / "hard", "hard-tiny", 0, show_progress=False)
    return load_ply(data / "scene.ply"), load_cameras(data)[:4], data / "features"


def test_registration_sums_on_the_device_and_equals_numba(room):
    """--engine torch with the paper and core modes keeps its sums on the device (no pair log here) and gives numba's field."""
    scene, cams, features = room
    want = register_features(scene, cams, features, RegisterOptions(topk=8, aggregate="paper"), show_progress=False)
    got = register_features(scene, cams, features, RegisterOptions(topk=8, aggregate="paper", engine="torch", device="cpu"), show_progress=False)
    assert (got.sums_on, want.sums_on) == ("cpu", "host")
    assert (got.num_pairs, got.num_distinct_pairs, got.num_assigned) == (want.num_pairs, want.num_distinct_pairs, want.num_assigned)
    assert got.num_assigned > 0
    np.testing.assert_array_equal(got.weights, want.weights)
    np.testing.assert_array_equal(got.features, want.features)
    core = RegisterOptions(topk=8, aggregate="core")
    want = register_features(scene, cams, features, core, show_progress=False)
    got = register_features(scene, cams, features, dataclasses.replace(core, engine="torch", device="cpu"), show_progress=False)
    assert got.sums_on == "cpu", "a weighting ported to torch runs on the device too"
    np.testing.assert_array_equal(got.features, want.features)
    for mode in ("core-reject", "vote-reject", "explain-vote-reject"):  # floater statistics, the vote's slots and the EM on the device
        want = register_features(scene, cams, features, RegisterOptions(topk=8, aggregate=mode), show_progress=False)
        got = register_features(scene, cams, features, RegisterOptions(topk=8, aggregate=mode, engine="torch", device="cpu"),
                                show_progress=False)
        assert got.sums_on == "cpu" and got.num_rejected == want.num_rejected > 0
        np.testing.assert_array_equal(got.features, want.features)


@pytest.fixture
def torch_ops_render(monkeypatch):
    """Registration's torch engine rendering with the torch ops (the CUDA path's sized tile lists)
    instead of the fused op, whose numba kernels size the lists on the host on a CPU."""
    import drsplat.raster_torch

    monkeypatch.setattr(drsplat.raster_torch, "has_fused_kernel", lambda device: False)


def test_on_a_cpu_the_fused_op_sizes_every_view_exactly(room, monkeypatch):
    """No view is sized from earlier ones or computed twice: the op reads no device to size its lists."""
    import drsplat.registration.device_sums as device_sums

    scene, cams, features = room
    asked = []
    render_pairs = device_sums.render_pairs
    monkeypatch.setattr(device_sums, "render_pairs", lambda *args, **kwargs: asked.append(args[7]) or render_pairs(*args, **kwargs))
    want = register_features(scene, cams, features, RegisterOptions(topk=8, aggregate="paper"), show_progress=False)
    got = register_features(scene, cams, features, RegisterOptions(topk=8, aggregate="paper", engine="torch", device="cpu"), show_progress=False)
    assert asked == [None] * len(cams)
    np.testing.assert_array_equal(got.features, want.features)


@pytest.mark.parametrize("mode", ["paper", "vote-reject"])
@pytest.mark.parametrize("policy", ["learned", "always short"])
def test_tile_lists_sized_a_view_late_give_numbas_field(room, monkeypatch, torch_ops_render, mode, policy):
    """The first view sizes its tile lists exactly and later ones from the views read before them
    (nothing read inside a view); a view whose lists fell short ("always short": capacity 1) is
    computed again with exact lists before any of it is summed. Either way: numba's field, bit for bit."""
    import drsplat.registration.device_sums as device_sums

    scene, cams, features = room
    asked = []
    render_pairs = device_sums.render_pairs

    def spy(*args, **kwargs):
        asked.append(args[7])  # tile_capacity
        return render_pairs(*args, **kwargs)

    monkeypatch.setattr(device_sums, "render_pairs", spy)
    if policy == "always short":
        monkeypatch.setattr(device_sums.TileCapacity, "capacity", lambda self: 1 if self.recent else None)
    want = register_features(scene, cams, features, RegisterOptions(topk=8, aggregate=mode), show_progress=False)
    got = register_features(scene, cams, features, RegisterOptions(topk=8, aggregate=mode, engine="torch", device="cpu"), show_progress=False)
    assert got.sums_on == "cpu" and (got.num_pairs, got.num_distinct_pairs) == (want.num_pairs, want.num_distinct_pairs)
    np.testing.assert_array_equal(got.features, want.features)
    np.testing.assert_array_equal(got.weights, want.weights)
    if policy == "learned":  # view 2 is computed before view 1's sizes are read: both exact, the rest sized
        assert asked[:2] == [None, None] and len(asked) == len(cams) and all(c is not None and c % device_sums.TILE_ROUND == 0 for c in asked[2:])
    else:  # every sized view fell short and was computed again, exactly (the redo comes after the next view's render)
        assert asked[:2] == [None, None] and asked.count(1) == len(cams) - 2 and asked.count(None) == 2 + len(cams) - 2


def test_views_that_see_nothing_then_more_than_learned_give_numbas_field(room, monkeypatch, torch_ops_render):
    """The tile lists' size swings: a view turned away from the scene (no tile entries, no pairs), then
    views needing more entries than any view read before them (their lists fall short, sized
    tightly here, and they are computed again); the device path still writes numba's field."""
    import drsplat.registration.device_sums as device_sums

    scene, cams, features = room
    monkeypatch.setattr(device_sums, "TILE_ROUND", 1)
    monkeypatch.setattr(device_sums, "TILE_HEADROOM", 1.0)
    seen, asked = [], []
    saw, render_pairs = device_sums.TileCapacity.saw, device_sums.render_pairs
    monkeypatch.setattr(device_sums.TileCapacity, "saw", lambda self, needed: seen.append(needed) or saw(self, needed))
    monkeypatch.setattr(device_sums, "render_pairs", lambda *args, **kwargs: asked.append(args[7]) or render_pairs(*args, **kwargs))
    flip = np.diag([-1.0, 1.0, -1.0])  # half a turn about the camera's y axis: it looks away from the scene
    centre = scene.means.mean(axis=0)
    eye = -cams[0].R.T @ cams[0].t
    far = centre + 1e3 * (eye - centre) / np.linalg.norm(eye - centre)
    away = dataclasses.replace(cams[0], R=flip @ cams[0].R, t=-(flip @ cams[0].R) @ far)
    views = [away, cams[1], cams[0], cams[3]]
    want = register_features(scene, views, features, RegisterOptions(topk=8, aggregate="vote-reject"), show_progress=False)
    got = register_features(scene, views, features, RegisterOptions(topk=8, aggregate="vote-reject", engine="torch", device="cpu"),
                            show_progress=False)
    assert got.sums_on == "cpu" and got.num_assigned == want.num_assigned > 0
    np.testing.assert_array_equal(got.features, want.features)
    assert seen[0] == 0, "the first view sees nothing"
    assert asked[2] == 1 and asked.count(None) > 2, "a view sized from the empty one fell short and was computed again"


def test_one_view_behind_hands_on_each_view_after_the_next_is_computed():
    """The same views in order, each resolved only once the next one was computed; when computing a view
    fails, the one before it is still handed on, then the error."""
    from drsplat.registration.executor import one_view_behind

    events = []

    class View:
        def __init__(self, i):
            self.i = i

        def resolved(self):
            events.append(("resolved", self.i))
            return self

    def computed(count, fail_at=None):
        for i in range(count):
            if i == fail_at:
                raise InputError("view.npy", "truncated")
            events.append(("computed", i))
            yield View(i)

    assert [v.i for v in one_view_behind(computed(3))] == [0, 1, 2]
    assert events == [("computed", 0), ("computed", 1), ("resolved", 0), ("computed", 2), ("resolved", 1), ("resolved", 2)]
    events.clear()
    got = []
    with pytest.raises(InputError, match="truncated"):
        for view in one_view_behind(computed(3, fail_at=2)):
            got.append(view.i)
    assert got == [0, 1] and events[-1] == ("resolved", 1)
    assert list(one_view_behind(iter(()))) == []


def test_sums_that_do_not_fit_the_device_go_to_the_host(room, monkeypatch, caplog):
    """When F and W do not fit the device's free memory, the views' pairs are copied to the host sums instead."""
    import drsplat.registration.device_sums as device_sums

    scene, cams, features = room
    asked = []
    monkeypatch.setattr(device_sums, "sums_fit_device", lambda n, dim, device, extra=0: asked.append(extra) or False)
    for mode in ("paper", "vote-reject"):  # the vote's slots are asked for too, and go to the host VoteSink
        options = RegisterOptions(topk=8, aggregate=mode)
        want = register_features(scene, cams, features, options, show_progress=False)
        with caplog.at_level("INFO"):
            got = register_features(scene, cams, features, dataclasses.replace(options, engine="torch", device="cpu"), show_progress=False)
        assert got.sums_on == "host" and "do not fit the free memory of cpu: summing on the host" in caplog.text
        np.testing.assert_array_equal(got.features, want.features)
    assert asked == [0, VOTE_SLOT_BYTES]


def test_the_caching_allocators_unused_blocks_count_as_free_device_memory(monkeypatch):
    """The fit stage's probe views are rendered on the GPU (2026-12-04) before the sums are made,
    and torch's caching allocator keeps their blocks reserved; `mem_get_info` counts them as taken,
    though the allocator releases them when F needs the room. Sums that fit only with them go to the
    device; with none cached, to the host."""
    import drsplat.registration.device_sums as device_sums

    gib, dim = 1 << 30, 512
    need_per_gaussian = device_sums.DEVICE_HEADROOM * 4 * (dim + 1)
    n = int((2.5 * gib - 8 * device_sums.PAIR_CHUNK * dim) / need_per_gaussian)  # F and W take 2.5 GiB with the headroom
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (1 * gib, 80 * gib))
    monkeypatch.setattr(torch.cuda, "memory_allocated", lambda device=None: 1 * gib)
    monkeypatch.setattr(torch.cuda, "memory_reserved", lambda device=None: 4 * gib)  # 3 GiB held unused by the allocator
    assert device_sums.sums_fit_device(n, dim, "cuda")
    assert not device_sums.sums_fit_device(2 * n, dim, "cuda")  # 5 GiB: more than the 4 GiB free with the cache
    monkeypatch.setattr(torch.cuda, "memory_reserved", lambda device=None: 1 * gib)  # nothing cached: 1 GiB free
    assert not device_sums.sums_fit_device(n, dim, "cuda")
    assert device_sums.sums_fit_device(n, dim, "cpu")


@pytest.mark.parametrize("mode,sums_on", [("paper", "cpu"), ("vote-reject", "cpu")])
def test_a_device_run_resumes_from_its_pair_log(room, tmp_path, mode, sums_on):
    """The device path logs every view's pairs: a run that fails at view 2 resumes and writes numba's
    file (vote-reject: the device's floater statistics snapshotted on the host at the failure, and
    folded on the device again after the resume)."""
    scene, cams, features = room
    reference = tmp_path / "numba.ply"
    register(scene, cams, features, reference, RegisterOptions(topk=8, aggregate=mode), show_progress=False)
    copy = tmp_path / "features"
    shutil.copytree(features, copy)
    bad = copy / f"{cams[2].name}_s.npy"
    good = bad.read_bytes()
    ids = np.load(bad)
    ids[..., 0, 0] = 10_000  # past the view's embeddings: found when the view is read (its headers are fine)
    np.save(bad, ids)
    out = tmp_path / "out" / "reg.ply"
    options = RegisterOptions(topk=8, aggregate=mode, engine="torch", device="cpu")
    with pytest.raises(InputError, match=bad.name):
        register(scene, cams, copy, out, options, show_progress=False)
    bad.write_bytes(good)
    result = register(scene, cams, copy, out, options, show_progress=False)
    assert result.resumed_views == 2 and result.sums_on == sums_on
    assert out.read_bytes() == reference.read_bytes()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (the CPU runs the same code above)")
def test_on_cuda_pairs_and_sums_equal_numba_to_float32_rounding():
    """On CUDA index_add adds with atomics in no fixed order: the same pairs, weights and sums to float32 rounding."""
    n, dim = 3000, 16
    device_sink, host_sink = DeviceSink(n, dim, "cuda"), MemorySink(n, dim)
    for _, ids, weights, masks, num_masks, num_gaussians in CASES:
        pairs = coalesce_torch(*(torch.from_numpy(a).cuda() for a in (ids, weights, masks)), num_masks, num_gaussians)
        distinct, contributing = (int(c) for c in pairs.counts)
        tg, tm, tw = pairs.trimmed(distinct).to_host()
        g, m, w, want_pairs = Coalescer(num_gaussians).coalesce(ids, weights, masks, num_masks)
        assert (distinct, contributing) == (g.shape[0], want_pairs)
        got, want = np.lexsort((tg, tm)), np.lexsort((g, m))
        np.testing.assert_array_equal(np.stack([tg, tm])[:, got], np.stack([g, m])[:, want])
        np.testing.assert_allclose(tw[got], w[want], rtol=1e-6)
    for device_view, host_view in views_of(1, 6, n, dim):
        device_view.device = type(device_view.device)(*(t.cuda() for t in (device_view.device.gaussians, device_view.device.masks,
                                                                            device_view.device.weights, device_view.device.counts)))
        device_sink.add(device_view)
        host_sink.add(host_view)
    (block,), (want,) = list(device_sink.blocks()), list(host_sink.blocks())
    np.testing.assert_allclose(block.W, want.W, rtol=1e-5)
    np.testing.assert_allclose(block.F, want.F, rtol=1e-5, atol=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (the CPU runs the same code above)")
@pytest.mark.parametrize("case,ids,weights,masks", EXPLAIN_CASES, ids=[c[0] for c in EXPLAIN_CASES])
def test_on_cuda_explain_equals_the_numba_em_to_float32_rounding(case, ids, weights, masks):
    """On CUDA the EM's index_add sums in no fixed order: numba's weights to float32 rounding."""
    from drsplat.registration.aggregate import explain_weights
    from drsplat.registration.device_sums import explain_weights_torch

    n = int(max(ids.max(initial=-1) + 1, 1))
    want = explain_weights(ids, weights, masks, n)
    got = explain_weights_torch(*(torch.from_numpy(a).cuda() for a in (ids, weights, masks)), n).cpu().numpy()
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)



@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU"))])
def test_slot_sums_add_slot_after_slot(device):
    """A pixel's total is its slots added in order (the numba kernels' order), bit for bit: values
    whose sum depends on the order (1e16 next to ones), k = 1 and 40, and no slots at all."""
    rng = np.random.default_rng(5)
    x = rng.uniform(0.0, 1.0, (6, 9, 40))
    x[..., ::7] *= 1e16  # an order-dependent sum: the ones vanish or not
    for values in (x, x[..., :1], x[..., :0]):
        got = slot_sums(torch.from_numpy(values).to(device)).cpu().numpy()
        ref = np.zeros(values.shape[:-1] + (1,))
        for s in range(values.shape[-1]):
            ref[..., 0] = ref[..., 0] + values[..., s]
        assert got.shape == ref.shape
        np.testing.assert_array_equal(got, ref)
    tree = torch.from_numpy(x).sum(-1, keepdim=True).numpy()
    assert (tree != slot_sums(torch.from_numpy(x)).numpy()).any(), "the case should tell a pairwise sum from a sequential one"


@pytest.mark.parametrize("case,h,w,k,n", STATS_CASES, ids=[f"{c[0]} {c[1]}x{c[2]} k={c[3]}" for c in STATS_CASES])
def test_the_floater_statistics_op_equals_the_torch_ops(case, h, w, k, n):
    """drsplat::view_stats (numba behind it on a CPU) against front_flags_torch + view_stats_torch,
    bit for bit; one dispatcher call, no host sync; torch's op checks (schema, fake kernel)."""
    from drsplat.raster_ops import camera_values
    from drsplat.registration.device_sums import DeviceRays, front_flags_torch, view_stats, view_stats_op, view_stats_torch

    rays, cam, ids, weights, median = stats_view(3 + h, h, w, k, n, case)
    device_rays = DeviceRays.from_host(rays, torch.device("cpu"))
    tensors = [torch.from_numpy(a) for a in (ids, weights, median)]
    want = view_stats_torch(tensors[0], tensors[1], front_flags_torch(device_rays, cam, tensors[0], tensors[2]), n)
    with OpCounter() as counter:
        got = view_stats(device_rays, cam, *tensors)
    assert counter.counts.by_name["drsplat::view_stats"] == 1 and counter.counts.syncs == 0
    for name in ("peak", "total", "front", "touched"):
        assert getattr(got, name).numpy().tobytes() == getattr(want, name).numpy().tobytes(), name
    args = (*tensors, device_rays.means, device_rays.precisions, device_rays.reach, camera_values(cam), 0.05)
    torch.library.opcheck(view_stats_op, args, test_utils=("test_schema", "test_faketensor"))


@pytest.mark.parametrize("case,ids,weights,masks", EXPLAIN_CASES, ids=[c[0] for c in EXPLAIN_CASES])
def test_the_explain_op_equals_the_torch_ops(case, ids, weights, masks):
    from drsplat.registration.device_sums import explain_weights_op, explain_weights_torch

    n = int(max(ids.max(initial=-1) + 1, 1))
    args = tuple(torch.from_numpy(a) for a in (ids, weights, masks))
    for iterations in (0, 3):
        want = explain_weights_torch(*args, n, iterations)
        with OpCounter() as counter:
            got = explain_weights_op(*args, n, iterations)
        assert counter.counts.by_name["drsplat::explain_weights"] == 1 and counter.counts.syncs == 0
        assert got.numpy().tobytes() == want.numpy().tobytes(), f"{iterations} iterations"
    if ids.size:
        torch.library.opcheck(explain_weights_op, (*args, n, 2), test_utils=("test_schema", "test_faketensor"))


@pytest.mark.parametrize("slots,presence", [(8, 0.1), (2, 0.1), (3, 0.0)])
def test_the_vote_op_folds_as_the_torch_ops(slots, presence):
    """drsplat::vote_fold (numba behind it on a CPU) folds views into the slots as vote_view_torch
    does, bit for bit, in place (pairs given in the views' (mask, Gaussian) order, not by row)."""
    from drsplat.registration.device_sums import vote_fold_op, vote_view_torch
    from drsplat.registration.vote import FULL_VIEW

    n, rng = 25, np.random.default_rng(slots + 40)

    def slots_():
        return (torch.full((n, slots), -1, dtype=torch.int32), torch.zeros((n, slots), dtype=torch.float64),
                torch.zeros((n, slots), dtype=torch.float64))

    want, got = slots_(), slots_()
    for _ in range(12):
        p = int(rng.integers(0, 60))
        rows = torch.from_numpy(rng.integers(0, n, p))
        clusters = torch.from_numpy(rng.integers(-1, 9, p))
        weights = torch.from_numpy(np.where(rng.random(p) < 0.1, 0.0, rng.uniform(0, 1, p)).astype(np.float32))
        vote_view_torch(rows, clusters, weights, presence, FULL_VIEW, *want)
        with OpCounter() as counter:
            vote_fold_op(rows, clusters, weights, presence, FULL_VIEW, 9, *got)
        assert counter.counts.by_name["drsplat::vote_fold"] == 1 and counter.counts.syncs == 0
    for a, b in zip(got, want):
        assert a.numpy().tobytes() == b.numpy().tobytes()
    assert (want[0] >= 0).all(axis=1).any(), "some Gaussian filled its slots"


def test_the_sums_op_adds_as_the_torch_ops():
    """drsplat::add_pairs (the host accumulator's numba kernel behind it on a CPU) gives index_add's
    bits: a Gaussian's pairs in pair order over several views, pairs spread over chunks, repeated
    Gaussians and masks, zero weights, a view without pairs; one dispatcher call, in place."""
    from drsplat.registration.device_sums import add_pairs_op, add_pairs_torch

    rng = np.random.default_rng(8)
    n, dim = 40, 7
    want = (torch.zeros((n, dim)), torch.zeros(n))
    got = (torch.zeros((n, dim)), torch.zeros(n))
    for p in (50, 0, 200, 3):
        m = 6
        g = torch.from_numpy(rng.integers(0, n, p))
        masks = torch.from_numpy(rng.integers(0, m, p))
        w = torch.from_numpy(np.where(rng.random(p) < 0.1, 0.0, rng.uniform(0, 2, p)).astype(np.float32))
        feats = torch.from_numpy(rng.normal(size=(m, dim)).astype(np.float32))
        add_pairs_torch(*want, g, masks, w, feats, chunk=16)
        with OpCounter() as counter:
            add_pairs_op(*got, g, masks, w, feats, 16)
        assert counter.counts.ops == 1 and counter.counts.by_name["drsplat::add_pairs"] == 1
    for a, b in zip(got, want):
        assert a.numpy().tobytes() == b.numpy().tobytes()
    assert (want[1] > 0).sum() > n // 2


@pytest.mark.parametrize("weighting", [w for w in WEIGHTINGS if w != "paper"])
def test_the_weighting_op_equals_the_torch_ops(weighting):
    """drsplat::view_weights (numba's projection and weighting behind it on a CPU) gives the torch
    projection + view_weights_torch's bits on a rendered view; one dispatcher call."""
    from drsplat.raster import NEAR
    from drsplat.raster_ops import camera_values
    from drsplat.raster_torch import prepare_scene_torch, project_gaussians_torch, rasterize_torch
    from drsplat.registration.device_sums import view_weights_op, view_weights_torch
    from drsplat.testing import random_case

    case = random_case(9, n=400, topk=6)
    ts = prepare_scene_torch(case.scene)
    out = rasterize_torch(ts, case.camera, case.topk)
    projected = project_gaussians_torch(ts, case.camera)
    want = view_weights_torch(weighting, out.ids, out.weights, projected.means2d, projected.conics, anchor_gain=2.5)
    args = (weighting, out.ids, out.weights, ts.means, ts.covariances, ts.opacities, ts.finite, camera_values(case.camera), NEAR, 2.5)
    with OpCounter() as counter:
        got = view_weights_op(*args)
    assert counter.counts.ops == 1 and counter.counts.syncs == 0
    assert got.numpy().tobytes() == want.numpy().tobytes()
    assert not torch.equal(got, out.weights), "the weighting changed something"
    torch.library.opcheck(view_weights_op, args, test_utils=("test_schema", "test_faketensor"))


@pytest.mark.parametrize("device", ["cpu", CUDA])
@pytest.mark.parametrize(
    "shape, dtype, chunk_bytes",
    [((13, 5), torch.float32, 40), ((13, 5), torch.float32, 1), ((1000, 7), torch.float32, 4096), ((7,), torch.int64, 16),
     ((4, 2, 3), torch.int32, 24), ((0, 5), torch.float32, 64), ((3,), torch.float64, 1 << 30)],
    ids=["two rows a chunk", "a chunk under one row", "many chunks, last one short", "1-D", "3-D", "empty", "one chunk"],
)
def test_sums_staged_to_the_host_chunk_by_chunk_equal_the_tensor(device, shape, dtype, chunk_bytes):
    """`to_host` through two staging buffers (pinned on CUDA, where F's hand-over uses it): every
    row once, in place, in a new array of the tensor's dtype and shape."""
    from drsplat.registration.device_sums import to_host

    want = (torch.rand(shape, generator=torch.Generator().manual_seed(3)) * 1e4).to(dtype)
    tensor = want.to(device)
    got = to_host(tensor, staged=True, chunk_bytes=chunk_bytes)
    assert got.dtype == want.numpy().dtype and got.shape == tuple(shape)
    assert got.tobytes() == want.numpy().tobytes()
    assert not np.shares_memory(got, tensor.cpu().numpy())
