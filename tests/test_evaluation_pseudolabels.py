"""Pseudo-labels from labelled point clouds: known answers and KD-tree vs brute force."""

from __future__ import annotations

import numpy as np
import pytest

from drsplat.eval.pseudolabels import mahalanobis_sq, pseudo_labels, pseudo_labels_reference
from drsplat.scene import quat_to_rotmat


def one_gaussian(scales, quat=(1.0, 0, 0, 0), mean=(0, 0, 0)):
    q = np.asarray([quat], np.float64)
    q = q / np.linalg.norm(q)
    return np.asarray([mean], np.float64), quat_to_rotmat(q), np.asarray([scales], np.float64)


def test_mahalanobis_matches_explicit_inverse():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(5, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    R = quat_to_rotmat(q)
    s = rng.uniform(0.1, 2, (5, 3))
    mu = rng.normal(size=(5, 3))
    p = rng.normal(size=(5, 3))
    cov = R @ (s[:, :, None] ** 2 * np.eye(3)) @ R.transpose(0, 2, 1)
    expect = np.einsum("pi,pij,pj->p", p - mu, np.linalg.inv(cov), p - mu)
    np.testing.assert_allclose(mahalanobis_sq(p, mu, R, s), expect, rtol=1e-9)


@pytest.fixture(params=["grid", "kdtree"])
def engine(request):
    return request.param


def test_anisotropy_decides_between_equally_distant_points(engine):
    # a needle along x: points at the same Euclidean distance, one along x (label 0), one along y (label 1)
    g = one_gaussian([1.0, 0.1, 0.1])
    pts = np.array([[0.5, 0, 0], [0, 0.5, 0]])
    assert pseudo_labels(g, pts, np.array([0, 1]), engine=engine, show_progress=False).labels.tolist() == [0]
    # rotated by 90 degrees about z, the needle points along y
    g = one_gaussian([1.0, 0.1, 0.1], quat=(np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)))
    assert pseudo_labels(g, pts, np.array([0, 1]), engine=engine, show_progress=False).labels.tolist() == [1]


def test_closeness_not_sum_of_distances(engine):
    # two points of label 0 at the centre, five points of label 1 near the rim (D = 2.8^2 = 7.84)
    g = one_gaussian([1.0, 1.0, 1.0])
    pts = np.array([[0.0, 0, 0], [0.05, 0, 0]] + [[2.8 * np.cos(a), 2.8 * np.sin(a), 0] for a in np.linspace(0, 6, 5)])
    labels = np.array([0, 0, 1, 1, 1, 1, 1])
    res = pseudo_labels(g, pts, labels, engine=engine, show_progress=False)
    assert res.labels.tolist() == [0]  # 2·~1 > 5·exp(-3.92)=0.10
    assert res.num_points.tolist() == [7]
    assert res.support[0] == pytest.approx(1.0 + np.exp(-0.5 * 0.05**2))
    # the literal "argmax of summed distances" and a plain count would both pick label 1
    d2 = mahalanobis_sq(pts, np.zeros((7, 3)), np.tile(np.eye(3), (7, 1, 1)), np.ones((7, 3)))
    assert np.argmax([d2[labels == 0].sum(), d2[labels == 1].sum()]) == 1
    assert pseudo_labels(g, pts, labels, weighting="count", engine=engine, show_progress=False).labels.tolist() == [1]


def test_points_outside_radius_and_unannotated_points(engine):
    g = one_gaussian([0.1, 0.1, 0.1])
    far = pseudo_labels(g, np.array([[1.0, 0, 0]]), np.array([3]), engine=engine, show_progress=False)
    assert far.labels.tolist() == [-1] and far.num_points.tolist() == [0]
    # unannotated points (−1) win the vote: the Gaussian stays unlabelled
    res = pseudo_labels(g, np.array([[0.0, 0, 0], [0.01, 0, 0], [0.2, 0, 0]]), np.array([-1, -1, 5]), engine=engine, show_progress=False)
    assert res.labels.tolist() == [-1]


def test_both_engines_match_brute_force_with_small_chunks():
    rng = np.random.default_rng(4)
    n, p = 150, 2000
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    g = (rng.uniform(-1, 1, (n, 3)), quat_to_rotmat(q), rng.uniform(0.02, 0.3, (n, 3)))
    g[2][0] = [np.nan, 0.1, 0.1]  # non-finite: skipped
    g[2][1] = [5.0, 5.0, 5.0]  # huge: sees every point
    g[2][2] = [1e30, 1e30, 1e30]  # enormous: its cell range once overflowed an int64 and it saw no point
    pts = rng.uniform(-1.2, 1.2, (p, 3))
    labels = rng.integers(-1, 6, p)
    for weighting in ("gaussian", "count"):
        ref = pseudo_labels_reference(g, pts, labels, weighting=weighting)
        grid = pseudo_labels(g, pts, labels, weighting=weighting, chunk=40, max_cells=64, show_progress=False)
        tree = pseudo_labels(g, pts, labels, weighting=weighting, engine="kdtree", chunk=40, max_pairs=500, show_progress=False)
        np.testing.assert_array_equal(grid.labels, ref)
        np.testing.assert_array_equal(pseudo_labels(g, pts, labels, weighting=weighting, show_progress=False).labels, ref)  # fine cells
        np.testing.assert_array_equal(tree.labels, ref)
        np.testing.assert_array_equal(grid.num_points, tree.num_points)
        np.testing.assert_allclose(grid.support, tree.support, rtol=1e-9)
        assert grid.nonfinite == tree.nonfinite == 1


@pytest.mark.parametrize("engine", ["grid", "kdtree"])
def test_votes_that_all_underflow_give_a_label_of_the_points_there(engine):
    """Round 69c F1: a Gaussian whose only points within --radius 40 lie at D > ~1490 gets votes exp(−D/2) of exactly 0,
    and the argmax over every class gave it the cloud's first label (3), which no point near it has. Both engines now
    choose among the classes of its voters, as the reference does (label 7), and still give -1 to a Gaussian with none."""
    g = (np.array([[0.0, 0, 0], [100.0, 0, 0]]), np.repeat(np.eye(3)[None], 2, axis=0), np.ones((2, 3)))
    points, labels = np.array([[39.0, 0, 0], [100.0, 0, 0]]), np.array([7, 3])
    for radius, want in ((40.0, [7, 3]), (3.0, [-1, 3])):
        assert pseudo_labels_reference(g, points, labels, radius=radius).tolist() == want
        assert pseudo_labels(g, points, labels, radius=radius, engine=engine, show_progress=False).labels.tolist() == want


def test_bad_weighting_or_engine_is_rejected():
    with pytest.raises(ValueError, match="weighting"):
        pseudo_labels(one_gaussian([1, 1, 1]), np.zeros((1, 3)), np.zeros(1, int), weighting="sum")
    with pytest.raises(ValueError, match="engine"):
        pseudo_labels(one_gaussian([1, 1, 1]), np.zeros((1, 3)), np.zeros(1, int), engine="octree")


def test_cancel_stops_between_batches(engine):
    from drsplat.errors import Cancelled
    from drsplat.utils import CancelToken

    token = CancelToken()
    token.cancel()
    with pytest.raises(Cancelled):
        pseudo_labels(one_gaussian([1, 1, 1]), np.zeros((3, 3)), np.zeros(3, int), engine=engine, cancel=token, show_progress=False)


def test_radius_batches_bound_the_overfetch():
    from drsplat.eval.pseudolabels import radius_batches

    radii = np.array([0.1, 0.12, 0.2, 1.0, 1.3, 0.11, 5.0])
    batches = radius_batches(radii, np.arange(7), chunk=2)
    assert sorted(np.concatenate(batches).tolist()) == list(range(7))
    assert all(len(b) <= 2 for b in batches)
    for b in batches:
        assert radii[b].max() / radii[b].min() < 2**0.5


@pytest.mark.parametrize("ratio", [1e-6, 1e-8, 1e-9])
def test_flat_gaussians_measure_distances_in_their_own_frame(ratio):
    """A rotated Gaussian of scales ratio : 1 : 1 and points at 1.5, 2.9 and 3.1 σ along a long axis:
    D = 2.25, 8.41, 9.61, so only the first two are within r = 3 and the first one's label wins. The
    expanded quadratic form with Σ⁻¹'s entries (~1/ratio²) put them at 3 / 8 / 8 at 1e-8 (the third
    counted) and at 0 / 0 / 0 at 1e-9, where the grid engine then gave another label (a numerical
    probe, 2026-11-30); both engines now whiten, as the reference does."""
    axis, angle = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0), 0.7
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    scales = np.array([[ratio, 1.0, 1.0]])
    pts = np.array([1.5, 2.9, 3.1])[:, None] * rot[:, 1][None]
    labels = np.array([1, 2, 2])
    gaussians = (np.zeros((1, 3)), rot[None], scales)
    np.testing.assert_allclose(mahalanobis_sq(pts, np.zeros((3, 3)), np.repeat(rot[None], 3, 0), np.repeat(scales, 3, 0)), [2.25, 8.41, 9.61], rtol=1e-6)
    for engine in ("grid", "kdtree"):
        got = pseudo_labels(gaussians, pts, labels, engine=engine, show_progress=False)
        assert got.labels.tolist() == [1] and got.num_points.tolist() == [2], engine
    assert pseudo_labels_reference(gaussians, pts, labels).tolist() == [1]


@pytest.mark.parametrize("scale", [1e200, 1e308, 1e-160, 1e-300])
def test_scales_at_the_ends_of_float64_label_like_the_reference(scale):
    """One Gaussian of scale 1e200 made the grid engine read out of bounds (a segmentation fault:
    0 · inf = NaN in its box, then NaN cast to a cell index); 1e-160 overflowed Σ⁻¹, so a point
    exactly on the centre was not counted. Both engines give the reference's label: a huge Gaussian
    holds every point (a tie of equal votes: the smaller label), a tiny one the point on its centre."""
    gaussians = (np.zeros((1, 3)), np.eye(3)[None], np.full((1, 3), scale))
    pts, labels = np.array([[0.0, 0.0, 0.0], [1e150, 0.0, 0.0]]), np.array([3, 4])
    want = pseudo_labels_reference(gaussians, pts, labels)
    assert want.tolist() == [3]
    for engine in ("grid", "kdtree"):
        with np.errstate(invalid="raise"):  # no NaN made on the way (the old cell indices)
            got = pseudo_labels(gaussians, pts, labels, engine=engine, show_progress=False)
        assert got.labels.tolist() == want.tolist() and got.num_points.tolist() == [2 if scale > 1 else 1], engine


def test_coordinates_too_large_for_the_kdtree_engine_are_one_error_and_the_grid_labels_them():
    """Round 40: points near 1e199 made scipy's sparse_distance_matrix stop with "Encountering floating point
    overflow" inside the kdtree engine; it now refuses them in one sentence, and the grid engine labels them
    as the brute-force reference does."""
    rng = np.random.default_rng(5)
    n, p = 20, 200
    g = (rng.uniform(-1, 1, (n, 3)) * 1e199, np.tile(np.eye(3), (n, 1, 1)), np.full((n, 3), 0.3e199))
    pts = rng.uniform(-1.2, 1.2, (p, 3)) * 1e199
    labels = rng.integers(0, 3, p)
    with pytest.raises(ValueError, match="the kdtree engine cannot label coordinates this large .*use the grid engine"):
        pseudo_labels(g, pts, labels, engine="kdtree", show_progress=False)
    grid = pseudo_labels(g, pts, labels, show_progress=False)
    np.testing.assert_array_equal(grid.labels, pseudo_labels_reference(g, pts, labels))


def test_two_points_the_whole_float64_range_apart_leave_the_grid_labels_as_they_were():
    """Round 46: a good labelled cloud plus two points at ±1.7e308 (finite; a double-precision cloud) made the grid's
    extent hi - lo overflow to inf: inf / inf cell counts and indices (numpy's warnings), and `eval pseudolabels`
    labelled none of 2,763 Gaussians, exit 0. The grid is now one cell there, and the labels are those of the cloud
    without the two points."""
    import warnings

    rng = np.random.default_rng(7)
    n, p = 30, 300
    g = (rng.uniform(-1, 1, (n, 3)), np.tile(np.eye(3), (n, 1, 1)), np.full((n, 3), 0.3))
    pts = rng.uniform(-1.2, 1.2, (p, 3))
    labels = rng.integers(0, 3, p)
    far = np.vstack([pts, [[-1.7e308, -1.7e308, 0.0], [1.7e308, 1.7e308, 0.0]]])
    want = pseudo_labels(g, pts, labels, show_progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = pseudo_labels(g, far, np.r_[labels, 1, 2], show_progress=False)
    assert (want.labels >= 0).sum() > n // 2
    np.testing.assert_array_equal(got.labels, want.labels)
    np.testing.assert_array_equal(got.num_points, want.num_points)
