"""Torch query scoring (exact fp16 cosine, PQ LUT) against the CPU kernels of drsplat.lang.lut."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from drsplat.lang import LanguageField, build_field, train_codebook
from drsplat.lang.backends import PQStorage
from tests.test_index import clip_like, hard_queries


@pytest.fixture(scope="module")
def data():
    x, _, _ = clip_like(1200, 64, seed=3)
    w = np.ones(len(x), np.float32)
    x[:4], w[:4] = 0, 0  # unassigned: score 0
    return x, w


@pytest.mark.parametrize("codebook", ["none", "pq8", "pq16", "ivf"])
def test_torch_scores_equal_cpu_kernels(data, codebook):
    x, w = data
    if codebook == "none":
        book = "none"
    else:
        book = train_codebook(x[4:], m=16 if codebook == "ivf" else int(codebook[2:]), seed=1)
    field = build_field(x, w, book, clip_model="oracle")
    if codebook == "ivf":  # coarse lists: the tables gain the term q · c_list (as an IVFPQ codebook's)
        rng = np.random.default_rng(2)
        coarse = rng.normal(size=(8, x.shape[1])).astype(np.float32) * 0.1
        storage = PQStorage(field.codes, rng.integers(0, 8, len(x)).astype(np.int32), field.norms,
                            dataclasses.replace(book, kind="ivfpq", coarse=coarse))
        field = LanguageField(field.dim, field.clip_model, field.weights, storage)
        assert field.kind == "ivfpq"
    q = hard_queries(x.shape[1], np.random.default_rng(5))
    cpu = field.scores(q)
    on_torch = field.scores(q, device="cpu")
    assert on_torch.shape == cpu.shape and on_torch.dtype == np.float32
    np.testing.assert_allclose(on_torch, cpu, atol=1e-5, rtol=0)
    assert (on_torch[:4] == 0).all()
    np.testing.assert_allclose(field.scores(q[:1], device="cpu"), cpu[:, :1], atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="float32 tables"):
        field.scores(q, lut_bits=8, device="cpu")


def test_torch_scores_a_non_finite_row_0_as_the_cpu_kernel_does():
    """Round 56a: with norms given rather than made from the rows, the CPU kernel read inf and NaN halves as finite
    numbers; it scores such a row 0 now, and so does the torch scorer (it gave inf and NaN)."""
    from drsplat.lang.backends import ExactStorage

    rng = np.random.default_rng(0)
    f = rng.normal(size=(6, 16)).astype(np.float16)
    f[2, 3], f[4, 0] = np.inf, np.nan
    field = LanguageField(16, "oracle", np.ones(6, np.float32), ExactStorage(f, np.ones(6, np.float32)))
    q = hard_queries(16, np.random.default_rng(1))
    cpu, on_torch = field.scores(q), field.scores(q, device="cpu")
    assert (cpu[[2, 4]] == 0).all() and np.isfinite(on_torch).all()
    np.testing.assert_allclose(on_torch, cpu, atol=1e-5, rtol=0)


def test_device_copy_is_made_once(data):
    x, w = data
    field = build_field(x, w, "none", clip_model="oracle")
    queries = x[np.linalg.norm(x, axis=1) > 0]  # assigned rows: a zero query is refused
    field.scores(queries[:2], device="cpu")
    first = field._on_device
    field.scores(queries[2:4], device="cpu")
    assert field._on_device is first and isinstance(field.scores_torch(queries[:2], "cpu"), torch.Tensor)


@pytest.mark.parametrize("kind", ["none", "pq"])
def test_scores_torch_makes_its_queries_unit_as_scores_does(data, kind):
    """Round 75c F4: `scores_torch` took its queries as given, so a raw CLIP embedding of norm 3 scored 3x what `scores`
    gave for it."""
    x, w = data
    field = build_field(x, w, "none" if kind == "none" else train_codebook(x[4:], m=8, seed=1), clip_model="oracle")
    queries = x[np.linalg.norm(x, axis=1) > 0][:2]
    on_torch = field.scores_torch(3.0 * queries, "cpu").numpy()
    np.testing.assert_allclose(on_torch, field.scores(queries), atol=1e-5, rtol=0)
