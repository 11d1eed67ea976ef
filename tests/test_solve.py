"""The render-consistent solve stage (drsplat.registration.solve): kernels against their numpy
references, the conjugate gradients against a dense solve, the silhouette case by hand, and the
stage inside a registration of a tiny hard room."""

from __future__ import annotations

import numpy as np
import pytest

from drsplat.cameras import load_cameras
from drsplat.errors import UsageError
from drsplat.registration import RegisterOptions, register_features
from drsplat.registration.aggregate import Stages, mode_stages
from drsplat.registration.compute import prepare_geometry
from drsplat.registration.solve import (
    SolveView,
    apply_view,
    apply_view_reference,
    residual_reference,
    slot_sums,
    slot_sums_reference,
    solve_coefficients,
    SolveResult,
    solve_registration,
    solved_features,
    target_sums,
    target_view_reference,
)
from drsplat.scene import load_ply
from drsplat.synthetic import write_dataset


def _random_views(rng, count, pixels, k, n, clusters):
    """Top-k lists like the rasterizer's: distinct ids per pixel, -1 padded, some zero weights,
    some pixels without a mask."""
    views = []
    for _ in range(count):
        ids = np.full((pixels, k), -1, np.int32)
        for p in range(pixels):
            m = rng.integers(0, k + 1)
            ids[p, :m] = rng.choice(n, m, replace=False)
        weights = np.where(ids >= 0, rng.random((pixels, k)), 0.0).astype(np.float32)
        weights[rng.random((pixels, k)) < 0.05] = 0.0
        labels = rng.integers(-1, clusters, pixels).astype(np.int32)
        views.append(SolveView(ids, weights, labels))
    return views


@pytest.mark.parametrize("clusters,slots", [(3, 8), (12, 4), (30, 2)])  # fewer clusters than slots, and many more (replacements)
def test_slot_kernel_matches_reference(clusters, slots):
    rng = np.random.default_rng(clusters)
    views = _random_views(rng, 3, 200, 5, 25, clusters)
    c_ref, s_ref, q_ref = slot_sums_reference(views, 25, slots)
    c, s, q = slot_sums(views, 25, slots)
    np.testing.assert_allclose(q, q_ref, rtol=1e-12)
    np.testing.assert_array_equal(c, c_ref)
    np.testing.assert_allclose(s, s_ref, rtol=1e-12)
    assert (c_ref >= 0).sum() > 0


@pytest.mark.parametrize("clusters,slots", [(3, 8), (12, 4)])
def test_operator_kernel_matches_reference(clusters, slots):
    rng = np.random.default_rng(7)
    views = _random_views(rng, 2, 150, 6, 20, clusters)
    slot_c, _, _ = slot_sums(views, 20, slots)
    x = rng.normal(size=slot_c.shape) * (slot_c >= 0)
    for view in views:
        out = np.zeros_like(x)
        apply_view(view, slot_c, x, out)
        np.testing.assert_allclose(out, apply_view_reference(view, slot_c, x, clusters), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(target_sums(views, slot_c), sum(target_view_reference(v, slot_c) for v in views), rtol=1e-12)


def test_solve_kernels_leave_out_weights_the_renderer_never_gives_as_their_references_do():
    """Round 56a: a NaN or infinite weight made the dense reference's whole pixel NaN and the kernel's candidate
    clusters only. Every kernel and reference now reads only finite positive weights, so a view with NaN, ±inf,
    negative and zero weights gives what the same view without those contributions gives; subnormal
    weights (and 1) are kept, and kernels and references agree on them."""
    rng = np.random.default_rng(56)
    n, clusters, slots = 20, 5, 4
    views = _random_views(rng, 2, 150, 6, n, clusters)
    for v in views:
        listed = np.argwhere(v.ids >= 0)
        pick = listed[rng.choice(len(listed), 40, replace=False)]
        v.weights[pick[:8, 0], pick[:8, 1]] = np.nan
        v.weights[pick[8:14, 0], pick[8:14, 1]] = np.inf
        v.weights[pick[14:18, 0], pick[14:18, 1]] = -np.inf
        v.weights[pick[18:26, 0], pick[18:26, 1]] = -0.3
        v.weights[pick[26:32, 0], pick[26:32, 1]] = 1e-45  # float32 subnormal: kept
        v.weights[pick[32:, 0], pick[32:, 1]] = 1.0  # the largest a renderer gives: kept
    clean = [SolveView(np.where((v.weights > 0) & (v.weights < np.inf), v.ids, -1), np.nan_to_num(v.weights), v.labels) for v in views]
    for got, want in ((slot_sums(views, n, slots), slot_sums(clean, n, slots)), (slot_sums_reference(views, n, slots), slot_sums(clean, n, slots))):
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)
    slot_c, _, _ = slot_sums(clean, n, slots)
    x = rng.normal(size=slot_c.shape) * (slot_c >= 0)
    for view, plain in zip(views, clean):
        out, want = np.zeros_like(x), np.zeros_like(x)
        apply_view(view, slot_c, x, out)
        apply_view(plain, slot_c, x, want)
        np.testing.assert_array_equal(out, want)
        np.testing.assert_allclose(out, apply_view_reference(view, slot_c, x, clusters), rtol=1e-10, atol=1e-12)
        assert np.isfinite(apply_view_reference(view, slot_c, x, clusters)).all()
    np.testing.assert_array_equal(target_sums(views, slot_c), target_sums(clean, slot_c))
    np.testing.assert_allclose(target_sums(views, slot_c), sum(target_view_reference(v, slot_c) for v in views), rtol=1e-12)
    assert residual_reference(views, slot_c, x, clusters) == residual_reference(clean, slot_c, x, clusters)


def test_conjugate_gradients_solve_the_normal_equations():
    """With enough iterations CG reaches the dense solution of (WᵀW + λ·diag(T)) x = (1 + λ)·S."""
    rng = np.random.default_rng(3)
    n, clusters, lam = 12, 4, 0.1
    views = _random_views(rng, 2, 80, 4, n, clusters)
    result = solve_coefficients(lambda: views, n, lam=lam, iterations=200, slots=4)
    slot_c = result.slot_c
    live = np.flatnonzero(slot_c.reshape(-1) >= 0)
    size = slot_c.size
    A = np.zeros((size, size))
    for col in live:  # the operator column by column through the numpy reference
        e = np.zeros(size)
        e[col] = 1.0
        A[:, col] = sum(apply_view_reference(v, slot_c, e.reshape(slot_c.shape), clusters) for v in views).reshape(-1)
    A += np.diag(lam * np.repeat(result.total, 4) * (slot_c.reshape(-1) >= 0))
    S = result.prior * result.total[:, None]
    expected = np.linalg.solve(A[np.ix_(live, live)], (1 + lam) * S.reshape(-1)[live])
    np.testing.assert_allclose(result.x.reshape(-1)[live], expected, rtol=1e-6, atol=1e-8)


def _silhouette_case():
    """A row of 20 pixels: an opaque background Gaussian (id 1) behind everything, a wide silhouette
    Gaussian (id 0, σ = 4 px) centred on a 4-pixel object mask (cluster 0; elsewhere the background's
    cluster 1): most of its footprint lies on the background's mask."""
    x = np.arange(20) + 0.5
    alpha = 0.9 * np.exp(-0.5 * ((x - 10.0) / 4.0) ** 2)
    ids = np.tile(np.array([0, 1], np.int32), (20, 1))
    weights = np.stack([alpha, (1 - alpha) * 0.99], 1).astype(np.float32)
    labels = np.where(np.abs(x - 10.0) < 2.0, 0, 1).astype(np.int32)
    return SolveView(ids, weights, labels)


def test_a_spilling_silhouette_gaussian_keeps_its_objects_label():
    view = _silhouette_case()
    result = solve_coefficients(lambda: [view], 2, iterations=20)

    def label(coeffs, g):
        return int(result.slot_c[g, np.argmax(np.where(result.slot_c[g] >= 0, coeffs[g], -np.inf))])

    assert label(result.prior, 0) == 1  # the paper's mean: the background's label
    assert label(result.x, 0) == 0  # the solve: the object's, since the background Gaussian explains the background
    assert label(result.x, 1) == 1
    before = residual_reference([view], result.slot_c, result.prior, 2)
    after = residual_reference([view], result.slot_c, result.x, 2)
    assert after < 0.8 * before


def test_stage_names():
    assert mode_stages("solve-vote-reject") == Stages("paper", True, True, solve=True)
    assert mode_stages("solve") == Stages("paper", False, False, solve=True)
    assert not mode_stages("vote-reject").solve


@pytest.fixture(scope="module")
def hard_tiny(tmp_path_factory):
    data = write_dataset(tmp_path_factory.mktemp("solve") / "hard-tiny", "hard-tiny", 0, show_progress=False)
    return load_ply(data / "scene.ply"), load_cameras(data)[:6], data / "features"


def test_solve_reduces_the_rerender_residual_on_a_hard_room(hard_tiny):
    """On a synthetic hard room: CG converges and the solve lowers Σ_p ‖Σ_g w_gp x_g − e_c(p)‖²
    against the paper's mean (the figures the solve logs, checked against the numpy reference in
    test_the_logged_residual_is_the_reference_residual)."""
    scene, cams, features = hard_tiny
    paper = register_features(scene, cams, features, RegisterOptions(topk=10, aggregate="paper"), show_progress=False)
    sums = paper.features * paper.weights[:, None]
    result = solve_registration(prepare_geometry(scene), cams, features, 0, 10, "numba", "cpu", sums)
    before, after = result.rerender
    assert after < 0.95 * before
    assert result.residuals[-1] < 0.05 * result.residuals[0]


def test_the_logged_residual_is_the_reference_residual():
    rng = np.random.default_rng(5)
    views = _random_views(rng, 2, 120, 4, 15, 5)
    result = solve_coefficients(lambda: views, 15, iterations=30, slots=4)
    np.testing.assert_allclose(result.rerender[0], residual_reference(views, result.slot_c, result.prior, 5), rtol=1e-9)
    np.testing.assert_allclose(result.rerender[1], residual_reference(views, result.slot_c, result.x, 5), rtol=1e-6)
    assert result.rerender[1] < result.rerender[0]


def test_solve_modes_register_and_are_refused_in_blocks(hard_tiny, tmp_path):
    scene, cams, features = hard_tiny
    paper = register_features(scene, cams, features, RegisterOptions(topk=10, aggregate="paper"), show_progress=False)
    solved = register_features(scene, cams, features, RegisterOptions(topk=10, aggregate="solve"), show_progress=False)
    np.testing.assert_array_equal(solved.weights, paper.weights)  # W (coverage) is the paper's
    moved = np.linalg.norm(solved.features - paper.features, axis=1) > 1e-3
    assert moved.sum() > 0
    with pytest.raises(UsageError, match="cannot run under a --memory-budget"):
        register_features(scene, cams, features, RegisterOptions(topk=10, aggregate="solve-vote-reject", block_size=100), show_progress=False)


def test_a_solve_run_stops_when_cancelled_during_its_passes(hard_tiny):
    """Was (a probe, 2026-12-01): Ctrl-C or SIGTERM during the solve stage, most of a `solve` run's
    time, printed "stopping after the current view" and then ran every pass to the end (181 s) and
    wrote the output. The solve's passes check the token before each view now."""
    import sys

    from drsplat.errors import Cancelled
    from drsplat.utils import CancelToken

    class CancelledInTheSolve(CancelToken):
        """Cancelled the first time the solve stage asks (the view pass before it is left to finish)."""

        def raise_if_cancelled(self) -> None:
            if sys._getframe(1).f_globals.get("__name__") == "drsplat.registration.solve":
                self.cancel()
            super().raise_if_cancelled()

    scene, cams, features = hard_tiny
    with pytest.raises(Cancelled):
        register_features(scene, cams, features, RegisterOptions(topk=10, aggregate="solve"), show_progress=False,
                          cancel=CancelledInTheSolve())


def test_solved_features_move_the_slot_part_and_keep_gaussians_with_nothing_positive():
    means = np.eye(3, dtype=np.float32)  # three clusters, unit means
    slot_c = np.array([[0, 1], [0, 1], [2, -1]], np.int32)
    prior = np.array([[0.25, 0.75], [0.5, 0.5], [1.0, 0.0]])
    x = np.array([[0.9, 0.1], [-0.2, -0.1], [1.0, 0.0]])
    total = np.array([4.0, 2.0, 1.0])
    F = (prior[:, :, None] * means[np.maximum(slot_c, 0)]).sum(1).astype(np.float32) * total[:, None].astype(np.float32)
    F[0] += np.float32(0.5) * means[2]  # weight on a mask outside the slots: kept
    before = F.copy()
    changed = solved_features(F, SolveResult(slot_c, prior, x, total, 1, [1.0], (1.0, 0.5)), means)
    assert changed == 1
    np.testing.assert_allclose(F[0], [3.6, 0.4, 0.5], rtol=1e-6)  # T·x on the slots, the rest as it was
    np.testing.assert_array_equal(F[1:], before[1:])  # all ≤ 0: the paper's; at x̄: bit for bit


@pytest.mark.parametrize("rows_per_chunk", [1, 7, 10_000])
def test_solved_features_are_the_same_bits_in_chunks_of_bounded_scratch(rows_per_chunk):
    """The changed rows are updated in chunks whose gathered means stay within the scratch bound
    (12 B per value of [chunk, S, D]: the 3.2 GB a 65,536-row chunk took at 512-D is gone); every
    chunk size gives the same sums."""
    rng = np.random.default_rng(3)
    n, slots, dim, clusters = 300, 8, 16, 40
    means = rng.normal(size=(clusters, dim)).astype(np.float32)
    slot_c = rng.integers(-1, clusters, (n, slots)).astype(np.int32)
    prior = rng.random((n, slots))
    x = rng.normal(size=(n, slots))
    total = rng.random(n) * 5
    F0 = rng.normal(size=(n, dim)).astype(np.float32)
    result = SolveResult(slot_c, prior, x, total, 1, [1.0], (1.0, 0.5))
    whole = F0.copy()
    assert solved_features(whole, result, means, scratch_bytes=1 << 40) > 100
    chunked = F0.copy()
    solved_features(chunked, result, means, scratch_bytes=rows_per_chunk * 12 * slots * dim)
    np.testing.assert_array_equal(chunked, whole)


@pytest.mark.parametrize("k", [1, 2, 40])
def test_slots_sorted_by_id_in_place_are_a_stable_argsorts(k):
    """`slots_by_id` (an insertion sort where the slots lie) against numpy's stable argsort and gathers: random ids
    with -1 padding, equal ids (their weights keep their order), rows already sorted or reversed, no rows."""
    from drsplat.registration.solve import slots_by_id, slots_by_id_reference

    rng = np.random.default_rng(k)
    ids = rng.integers(-1, 6, (500, k)).astype(np.int32)
    ids[:50] = np.sort(ids[:50], axis=1)
    ids[50:100] = -np.sort(-ids[50:100], axis=1)
    weights = rng.random((500, k)).astype(np.float32)
    want_ids, want_weights = slots_by_id_reference(ids, weights)
    slots_by_id(ids, weights)
    np.testing.assert_array_equal(ids, want_ids)
    np.testing.assert_array_equal(weights, want_weights)
    slots_by_id(np.zeros((0, k), np.int32), np.zeros((0, k), np.float32))


def test_the_solve_holds_no_copy_of_a_views_slots(hard_tiny):
    """Round 63b: each re-rendered view's slots were sorted into new arrays through an int64 argsort (24 more bytes
    a slot), so a `solve` on 1600x1200 views peaked at 2.8 GB under the 1.9 GB its own refusal named. Now they are
    sorted where the renderer left them: the solve's peak is the renderer's buffers (~10 bytes a slot) and the
    N-sized arrays, the same bits."""
    import tracemalloc

    scene, cams, features = hard_tiny
    cams = [c.scaled(5.0) for c in cams[:2]]  # 480x360: the slots outweigh everything N-sized
    paper = register_features(scene, cams, features, RegisterOptions(topk=40, aggregate="paper"), show_progress=False)
    sums = paper.features * paper.weights[:, None]
    geometry = prepare_geometry(scene)
    solve_registration(geometry, cams, features, 0, 40, "numba", "cpu", sums.copy())  # kernels compiled and loaded
    tracemalloc.start()
    try:
        solve_registration(geometry, cams, features, 0, 40, "numba", "cpu", sums)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    slots = cams[0].width * cams[0].height * 40
    assert peak < 24 * slots  # 19 bytes a slot; with the sorted copies 36
