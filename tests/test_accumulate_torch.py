"""Torch accumulation and torch registration against the numba Accumulator and registration."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from drsplat.accumulate_torch import TorchAccumulator
from drsplat.registration import Accumulator, accumulate_view_reference


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def random_views(rng, n, dim, views=4, h=20, w=24, k=5, masks=7):
    for _ in range(views):
        ids = rng.integers(-1, n, size=(h, w, k)).astype(np.int32)
        ids[rng.random((h, w, k)) < 0.2] = -1
        weights = np.where(ids >= 0, rng.random((h, w, k)), 0).astype(np.float32)
        mask_ids = rng.integers(-1, masks, size=(h, w)).astype(np.int32)
        feats = rng.normal(size=(masks, dim)).astype(np.float32)
        yield ids, weights, mask_ids, feats


def test_torch_accumulator_equals_numba_and_reference():
    rng = np.random.default_rng(0)
    n, dim = 300, 16
    numba_acc, torch_acc = Accumulator(n, dim, pair_capacity=512), TorchAccumulator(n, dim, pair_block=37)
    F, W = np.zeros((n, dim)), np.zeros(n)
    for ids, weights, mask_ids, feats in random_views(rng, n, dim):
        a = numba_acc.add_view(ids, weights, mask_ids, feats)
        b = torch_acc.add_view(torch.from_numpy(ids), torch.from_numpy(weights), mask_ids, feats)
        assert a == b
        accumulate_view_reference(F, W, ids, weights, mask_ids, feats)
    (f1, w1), (f2, w2) = numba_acc.sums(), torch_acc.sums()
    assert w2.dtype == np.float32 and f2.shape == (n, dim)
    np.testing.assert_allclose(f2, f1, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(w2, w1, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(f2, F, rtol=1e-4, atol=1e-4)
    assert (w1 > 0).sum() > 0.9 * n


def test_add_pairs_equals_numba_and_is_what_the_torch_engine_sums_with():
    """Registration sums coalesced pairs (`add_pairs`): the torch accumulator gives numba's sums."""
    from drsplat.registration import Coalescer, compute_engine

    rng = np.random.default_rng(1)
    n, dim = 200, 8
    numba_acc = Accumulator(n, dim, pair_capacity=64)
    torch_acc = compute_engine("torch", "cpu").accumulator(n, dim)
    assert isinstance(torch_acc, TorchAccumulator)
    coalescer = Coalescer(n)
    for ids, weights, mask_ids, feats in random_views(rng, n, dim, views=5):
        g, m, w, _ = coalescer.coalesce(ids, weights, mask_ids, feats.shape[0])
        numba_acc.add_pairs(g, m, w, feats)
        torch_acc.add_pairs(g, m, w, feats)
    (f1, w1), (f2, w2) = numba_acc.sums(), torch_acc.sums()
    np.testing.assert_allclose(f2, f1, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(w2, w1, rtol=1e-5, atol=1e-6)
    assert (w1 > 0).sum() > 0.5 * n


def test_torch_registration_equals_numba_registration(tmp_path):
    """End to end on a synthetic scene: same assigned Gaussians, features equal within fp16 rounding."""
    from drsplat.cameras import load_cameras
    from drsplat.registration import register_scene
    from drsplat.scene import load_ply
    from drsplat.synthetic import write_dataset

    root = tmp_path / "syn"
    write_dataset(root, "tiny", 0, show_progress=False)
    scene, cams = load_ply(root / "scene.ply"), load_cameras(root)[:4]
    a = register_scene(scene, cams, root / "features", topk=8, show_progress=False)
    b = register_scene(scene, cams, root / "features", topk=8, show_progress=False, engine="torch", device="cpu")
    np.testing.assert_array_equal(a.assigned, b.assigned)
    np.testing.assert_allclose(b.weights, a.weights, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(b.features, a.features, atol=1e-3)  # fp16 rounding of a unit vector's entries
    assert a.num_pairs == b.num_pairs and a.num_distinct_pairs == b.num_distinct_pairs
    assert a.num_assigned > 100
