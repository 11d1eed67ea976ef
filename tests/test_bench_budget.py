"""`drsplat bench budget`: its datasets are what the cases say, and a run under a budget reports
the child's own peak, a refusal the budget it names, which is then run and held."""

from __future__ import annotations

import numpy as np

from drsplat.bench.budget import BudgetCase, run_case, write_case
from drsplat.cameras import load_cameras
from drsplat.memory import parse_size
from drsplat.registration.views import load_view_features
from drsplat.registration.vote import MaskClusters
from drsplat.scene import load_ply

TINY = dict(gaussians=2_000, views=2, masks=40, dim=64, mode="vote-reject", width=64, height=48)


def test_a_case_writes_its_scene_views_and_masks(tmp_path):
    data = write_case(BudgetCase(**TINY, budget="1GB", labels=3), tmp_path / "d")
    scene, cams = load_ply(data / "scene.ply"), load_cameras(data)
    assert scene.num_gaussians == 2_000 and len(cams) == 2 and (cams[0].width, cams[0].height) == (64, 48)
    clusters = MaskClusters(64)
    for cam in cams:
        mask_ids, feats, _ = load_view_features(data / "features", cam, 0)
        assert feats.shape == (40, 64) and set(np.unique(mask_ids)) == set(range(-1, 40))  # every mask used, some pixels unmasked
        np.testing.assert_allclose(np.linalg.norm(feats, axis=1), 1.0, rtol=1e-5)
        clusters.add(feats)
    assert clusters.count <= 3  # masks around 3 labels: at most 3 clusters
    random = write_case(BudgetCase(**TINY, budget="1GB"), tmp_path / "r")
    clusters = MaskClusters(64)
    for cam in cams:
        clusters.add(load_view_features(random / "features", cam, 0)[1])
    assert clusters.count == 80  # random embeddings: every mask its own cluster


def test_a_refused_budget_is_run_again_at_the_budget_it_names(tmp_path):
    runs = run_case("tiny-refused", BudgetCase(**TINY, budget="100MB"), tmp_path)
    assert len(runs) == 2
    refused, named = runs
    assert refused.code != 0 and refused.named is not None and refused.named > parse_size("100MB")
    assert refused.verdict.startswith("refused")
    assert named.budget == refused.named and named.code == 0 and 0 < named.peak <= named.budget and named.verdict == "held"


def test_the_peak_is_the_childs_own_not_the_parents(tmp_path):
    """Linux carries a forking parent's resident size over exec into the child's ru_maxrss: the
    bench reads the child's own high-water mark, so a large parent does not inflate it."""
    from drsplat.memory import current_rss

    ballast = np.ones(60_000_000)  # 480 MB held by this process while the child runs
    assert current_rss() > 450 << 20
    (run,) = run_case("tiny", BudgetCase(**TINY, budget="1GB"), tmp_path)
    assert run.code == 0 and 0 < run.peak < 400 << 20, run
    del ballast


def test_a_small_capture_registers_under_a_budget_of_its_own_size(tmp_path):
    """A capture of 30,000 Gaussians and 480 masks (the default mode, its fit probe included) is
    accepted under 1 GB and holds it. Until 2026-12-05 the plan charged every scene the large ones'
    reserves (the sums' 8 M-pair buffer, the probe's 256 MB of kept views, the check's 128 MB of
    support scratch, the trim's and the translation's buffers at their caps): such a room was refused
    below ~1.5 GB and peaked at ~0.4 GB."""
    (run,) = run_case("small", BudgetCase(30_000, 8, 60, 512, "fit-check-vote-reject", "1GB"), tmp_path)
    assert run.code == 0 and 0 < run.peak <= run.budget, run
