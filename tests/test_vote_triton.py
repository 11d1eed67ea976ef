"""The fused vote kernel (drsplat.registration.vote_triton) against the plain-loop reference and the
numba kernel, bit for bit.

Triton reads TRITON_INTERPRET when it is imported, so the kernel runs in one subprocess with the
variable set (this process's environment is untouched), which folds every case's views and saves
the slots; the test process folds the same views with `vote.vote_view_reference` and the numba kernel.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("triton")

import torch  # noqa: E402

from drsplat.errors import DrsplatError  # noqa: E402
from drsplat.registration.vote import FULL_VIEW, fold_view_votes, vote_view_reference  # noqa: E402
from tests.interpreted import compiled_ptx, interpreted_outputs  # noqa: E402

# (slots per Gaussian, presence ρ, Gaussians, seed); "ties": votes = weights from {0.25, 0.5}, so
# full slots often tie on the fewest votes (the first of them is replaced)
CASES = {"8-slots": (8, 0.1, 25, 0), "2-slots": (2, 0.1, 25, 1), "3-slots-presence-0": (3, 0.0, 25, 2), "1-slot": (1, 0.3, 10, 3),
         "crowded": (4, 0.1, 3, 4), "ties": (3, 0.0, 6, 5)}


def views(name: str):
    """The case's views: (rows [P] int64, clusters [P] int64, weights [P] float32), some empty, with
    pairs without a cluster, zero weights and Gaussians meeting more clusters than slots."""
    slots, _, n, seed = CASES[name]
    rng = np.random.default_rng(seed)
    out = []
    for v in range(10):
        p = 0 if v == 3 else int(rng.integers(1, 80))
        rows = rng.integers(0, n, p)
        clusters = rng.integers(-1, 3 * slots + 2, p)
        weights = (rng.choice([0.25, 0.5], p) if name == "ties" else rng.uniform(0, 1, p)).astype(np.float32)
        weights[rng.random(p) < 0.1] = 0.0
        out.append((rows, clusters, weights))
    return out


def empty_slots(name: str):
    slots, _, n, _ = CASES[name]
    return np.full((n, slots), -1, np.int32), np.zeros((n, slots)), np.zeros((n, slots))


WORKER = """
import json, sys
import numpy as np
import torch
from drsplat.registration.vote import FULL_VIEW
from drsplat.registration.vote_triton import vote_fold_triton
from tests.interpreted import share
from tests.test_vote_triton import CASES, empty_slots, views
for name in share(json.loads(sys.argv[1])):
    state = [torch.from_numpy(a) for a in empty_slots(name)]
    for rows, clusters, weights in views(name):
        vote_fold_triton(torch.from_numpy(rows), torch.from_numpy(clusters), torch.from_numpy(weights), CASES[name][1], FULL_VIEW, *state)
    np.savez(sys.argv[2] + "/" + name + ".npz", c=state[0].numpy(), v=state[1].numpy(), s=state[2].numpy())
"""


@pytest.fixture(scope="module")
def interpreted(tmp_path_factory) -> Path:
    return interpreted_outputs(tmp_path_factory.mktemp("vote"), WORKER, json.dumps(list(CASES)), timeout=600)


@pytest.mark.parametrize("name", list(CASES))
def test_fused_vote_fold_equals_the_reference_and_the_numba_kernel(interpreted, name):
    presence = CASES[name][1]
    reference, numba = empty_slots(name), empty_slots(name)
    for rows, clusters, weights in views(name):
        vote_view_reference(rows, clusters, weights, presence, FULL_VIEW, *reference)
        fold_view_votes(rows, clusters, weights, presence, FULL_VIEW, *numba)
    got = np.load(interpreted / f"{name}.npz")
    for key, want, walked in zip("cvs", reference, numba):
        assert got[key].tobytes() == want.tobytes(), key
        assert walked.tobytes() == want.tobytes(), key
    assert (reference[0] >= 0).all(axis=1).any(), "some Gaussian filled its slots"
    if name == "8-slots":
        assert (reference[0] < 0).any(), "some slots stay empty"


def test_fused_vote_fold_is_refused_on_the_cpu():
    from drsplat.registration.vote_triton import vote_fold_triton

    slots = [torch.from_numpy(a) for a in empty_slots("1-slot")]
    with pytest.raises(DrsplatError, match="runs on CUDA devices only"):
        vote_fold_triton(torch.zeros(1, dtype=torch.int64), torch.zeros(1, dtype=torch.int64), torch.ones(1), 0.1, FULL_VIEW, *slots)


@pytest.mark.parametrize("ones", [False, True], ids=["scalars", "scalars equal to 1 (Triton passes them as constants)"])
def test_fused_vote_kernel_compiles_to_ptx_without_fma(ones):
    """Typed mode for sm_90, IEEE float64 division and no fused multiply-adds (numba's rounding)."""
    from drsplat.registration.vote_triton import compile_vote_ptx

    ptx = compiled_ptx(compile_vote_ptx, 90, ones=ones)
    assert ".entry _vote_fold_source" in ptx and "div.rn.f64" in ptx and "fma" not in ptx


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (the CPU runs the same source in the interpreter above)")
@pytest.mark.parametrize("name", list(CASES))
def test_on_cuda_fused_vote_fold_equals_the_reference(name):
    from drsplat.registration.vote_triton import vote_fold_triton

    presence = CASES[name][1]
    reference = empty_slots(name)
    state = [torch.from_numpy(a).cuda() for a in empty_slots(name)]
    for rows, clusters, weights in views(name):
        vote_view_reference(rows, clusters, weights, presence, FULL_VIEW, *reference)
        vote_fold_triton(*(torch.from_numpy(a).cuda() for a in (rows, clusters, weights)), presence, FULL_VIEW, *state)
    for got, want in zip(state, reference):
        assert got.cpu().numpy().tobytes() == want.tobytes()
