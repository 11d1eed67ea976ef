"""Language field backends: LUT scoring against decode-then-cosine, official codebook, PLY encoding."""

from __future__ import annotations

import logging
import os

import numpy as np
import pytest

from drsplat.errors import InputError, OutputError
from drsplat.lang import (
    Codebook,
    Q8_BLOCK,
    attach_field,
    blocked_codes,
    build_field,
    codebook_path_for,
    load_codebook,
    f32_sums,
    lut_scores,
    lut_scores_blocked,
    lut_scores_q8_reference,
    lut_scores_reference,
    q8_sums,
    quantize_luts,
    read_field,
    simd_available,
    strip_field,
    train_codebook,
    unit_rows,
)
from drsplat.scene import GaussianScene
from tests.conftest import shared_path

TOL = 1e-5


def clip_like(n: int, dim: int, labels: int = 8, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit rows a·c + b·label + noise (all alike, as CLIP embeddings are): ([n, D], [n] labels, [L, D] label vectors)."""
    rng = np.random.default_rng(seed)
    common = rng.normal(size=dim)
    common /= np.linalg.norm(common)
    dirs = rng.normal(size=(labels, dim))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    lab = rng.integers(0, labels, n)
    x = 1.0 * common + 0.8 * dirs[lab] + 0.5 * rng.normal(size=(n, dim)) / np.sqrt(dim)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x.astype(np.float32), lab, dirs.astype(np.float32)


def tiny_scene(n: int, seed: int = 0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    return GaussianScene(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        quats=np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1)),
        log_scales=np.full((n, 3), -3, np.float32),
        opacity_logits=np.zeros(n, np.float32),
        sh=rng.normal(size=(n, 1, 3)).astype(np.float32),
        comments=["trained by someone"],
    )


@pytest.fixture(scope="module")
def data():
    x, lab, dirs = clip_like(1500, 64, seed=1)
    weights = np.ones(len(x), np.float32)
    weights[:5] = 0
    x[:5] = 0
    return x, weights, lab, dirs


@pytest.fixture(scope="module")
def books(data):
    x = data[0][5:]
    return {m: train_codebook(x, m=m, seed=m) for m in (8, 16, 32)}


def hard_queries(dim: int, rng: np.random.Generator) -> np.ndarray:
    """Random, a basis vector, a huge-norm and a tiny-norm vector (normalised inside scores)."""
    q = rng.normal(size=(5, dim)).astype(np.float32)
    q[1] = 0
    q[1, 3] = 1
    q[2] *= 1e4
    q[3] *= 1e-4
    q[4] = -q[0]
    return q


@pytest.mark.parametrize("m", [8, 16, 32])
def test_pq_lut_equals_decode_then_cosine(data, books, m):
    x, w, _, _ = data
    field = build_field(x, w, books[m], clip_model="oracle")
    q = hard_queries(x.shape[1], np.random.default_rng(m))
    lut = field.scores(q)
    ref = field.scores_reference(q)
    assert lut.shape == (len(x), 5) and lut.dtype == np.float32
    np.testing.assert_allclose(lut, ref, atol=TOL, rtol=0)
    assert np.all(lut[:5] == 0), "unassigned Gaussians must score 0"
    np.testing.assert_allclose(lut[:, 4], -lut[:, 0], atol=TOL)


def test_lut_kernel_edge_shapes(books):
    book = books[16]
    rng = np.random.default_rng(3)
    for n, k in [(0, 1), (1, 1), (513, 3), (1025, 17)]:
        codes = rng.integers(0, 256, size=(n, book.m), dtype=np.uint8)
        norms = np.linalg.norm(book.decode(codes), axis=1).astype(np.float32)
        q = rng.normal(size=(k, book.dim)).astype(np.float32)
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        got = lut_scores(book, codes, None, norms, q)
        assert got.shape == (n, k)
        np.testing.assert_allclose(got, lut_scores_reference(book, codes, None, norms, q), atol=TOL, rtol=0)
        if n > 4:  # round 66c F8: rows whose stored norm is no feature's score 0 in both (the reference divided by the decoded norm)
            norms[1:5] = [0.0, 1e-40, np.inf, np.nan]
            got = lut_scores(book, codes, None, norms, q)
            assert not got[1:5].any() and np.array_equal(got[1:5], lut_scores_reference(book, codes, None, norms, q)[1:5])
            np.testing.assert_allclose(got, lut_scores_reference(book, codes, None, norms, q), atol=TOL, rtol=0)



def test_lut_kernel_sums_in_the_order_written():
    """The four-codes-a-load kernel adds each row's table entries in float32 in the order its source
    writes them (four running sums, then (a0 + a1) + (a2 + a3), times 1/norm), so its bits do not
    depend on how the compiler vectorised it. Until round 50 it allowed reassociation: a process that
    compiled it scored other float32 bits (one ulp, 2/3 of the entries) than one that loaded it from
    numba's cache."""
    from drsplat.lang.lut import _lut_scores_kernel_m4

    rng = np.random.default_rng(50)
    n, m, k = 700, 32, 3
    codes = rng.integers(0, 256, (n, m), dtype=np.uint8)
    tables = (rng.normal(size=(k, m, 256)) * 0.01).astype(np.float32)
    norms = (rng.random(n) + 0.5).astype(np.float32)
    got = np.empty((n, k), np.float32)
    _lut_scores_kernel_m4(codes.view(np.uint32), np.zeros(n, np.int32), tables.reshape(k, m * 256), np.zeros((k, 0), np.float32), norms, got)
    sums = np.zeros((4, n, k), np.float32)
    for j in range(m):
        sums[j % 4] += tables[:, j, codes[:, j]].T
    want = ((sums[0] + sums[1]) + (sums[2] + sums[3])) * (np.float32(1.0) / norms)[:, None]
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("m", [127, 6, 1])
def test_the_any_m_lut_kernel_sums_in_the_order_written(m):
    """The kernel for M not a multiple of 4 adds each row's entries in float32 in order, then the coarse term, times
    1/norm. Until round 68 it allowed reassociation: with M = 127 a process that compiled it scored 5,754 of 20,000 rows
    otherwise than one that loaded it from numba's cache, and an AVX-512 target otherwise again."""
    from drsplat.lang.lut import _lut_scores_kernel

    rng = np.random.default_rng(m)
    n, k = 700, 3
    codes = rng.integers(0, 256, (n, m), dtype=np.uint8)
    tables = (rng.normal(size=(k, m, 256)) * 0.01).astype(np.float32)
    inv = (np.float32(1.0) / (rng.random(n) + 0.5)).astype(np.float32)
    got = np.empty((n, k), np.float32)
    _lut_scores_kernel(codes, np.zeros(n, np.int32), tables, np.zeros((k, 0), np.float32), inv, got)
    sums = np.zeros((n, k), np.float32)
    for j in range(m):
        sums += tables[:, j, codes[:, j]].T
    np.testing.assert_array_equal(got, sums * inv[:, None])


@pytest.mark.parametrize("m", [8, 16])
def test_a_query_scores_the_same_bits_alone_and_in_a_batch(data, books, m):
    """A PQ field's scores of a query alone are its column of any batch's, bit for bit: each query's
    tables are made on their own (round 50: one contraction for the batch rounded them otherwise)."""
    x, w, _, _ = data
    field = build_field(x, w, books[m], clip_model="oracle")
    q = hard_queries(x.shape[1], np.random.default_rng(50 + m))
    batch = field.scores(q)
    for k in range(q.shape[0]):
        np.testing.assert_array_equal(field.scores(q[k : k + 1])[:, 0], batch[:, k], err_msg=f"query {k}")
    np.testing.assert_array_equal(field.scores(q[::-1])[:, ::-1], batch)

@pytest.mark.parametrize("m, dim, rows", [(8, 32, 600), (16, 64, 300), (128, 512, 400)])
def test_a_codebook_trained_sub_quantiser_by_sub_quantiser_is_faiss_index_pq_train_bit_for_bit(m, dim, rows):
    """`train_codebook` trains its sub-quantisers one at a time (progress, Ctrl-C between them: round 67b F2) with
    faiss's own k-means: the centroids, the serialised index and the codes are those of one `IndexPQ.train`
    (`train_codebook_reference`), rows without a direction left out of both."""
    import faiss

    from drsplat.lang.codebook import train_codebook_reference

    x, _, _ = clip_like(rows, dim, labels=6, seed=m)
    x[5] = 0.0
    x[7, 1] = np.nan
    got, want = train_codebook(x, m=m, seed=3), train_codebook_reference(x, m=m, seed=3)
    assert got.centroids.tobytes() == want.centroids.tobytes()
    assert np.array_equal(faiss.serialize_index(got.index), faiss.serialize_index(want.index))
    assert np.array_equal(got.index.sa_encode(x[:50] / np.linalg.norm(x[:50], axis=1, keepdims=True)),
                          want.index.sa_encode(x[:50] / np.linalg.norm(x[:50], axis=1, keepdims=True)))


def test_training_a_codebook_stops_between_sub_quantisers_when_cancelled(monkeypatch):
    """Round 67b F2: `register --codebook scene` trained for a minute after a Ctrl-C. The token is read before each
    sub-quantiser."""
    import drsplat.lang.codebook as codebook
    from drsplat.errors import Cancelled
    from drsplat.utils import CancelToken

    x, _, _ = clip_like(600, 32, labels=4, seed=2)
    token, trained = CancelToken(), []
    real = codebook._sub_quantizer_centroids
    monkeypatch.setattr(codebook, "_sub_quantizer_centroids", lambda *a: (trained.append(1), len(trained) == 3 and token.cancel(), real(*a))[2])
    with pytest.raises(Cancelled):
        train_codebook(x, m=8, cancel=token)
    assert len(trained) == 3


def test_training_a_codebook_on_few_distinct_embeddings_warns(caplog):
    """256 copies of 3 embeddings trained without a word into 256 centroids a sub-vector (round 29a):
    a codebook of those 3 directions only. Counted and said; a varied set says nothing."""
    import logging

    x, _, _ = clip_like(600, 32, labels=4, seed=1)
    with caplog.at_level(logging.WARNING, logger="drsplat.lang.codebook"):
        train_codebook(np.repeat(x[:3], 100, axis=0), m=8)
    assert "only 3 of the 300 training embeddings are distinct" in caplog.text and "these 3 directions" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="drsplat.lang.codebook"):  # round 100b F4: "1 ... are distinct ... these 1 directions"
        train_codebook(np.repeat(x[:1], 3000, axis=0), m=8)
    assert "only 1 of the 3,000 training embeddings is distinct" in caplog.text and "reconstructs this one direction" in caplog.text, caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="drsplat.lang.codebook"):
        train_codebook(x, m=8)
    assert "distinct" not in caplog.text
    # round 59a: NaN, inf and zero rows trained as zero rows without a word (256 NaN rows: a codebook of zero centroids)
    bad = x.copy()
    bad[::2] = np.nan
    bad[1] = 0
    bad[3, 0] = np.inf
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="drsplat.lang.codebook"):
        book = train_codebook(bad, m=8)
    assert "302 of the 600 training embeddings are zero or not finite and are left out" in caplog.text
    assert (np.abs(book.centroids).max(axis=2) > 0).all(), "no centroid spent on a zero row"
    with pytest.raises(InputError, match="needs at least 256 embeddings, got 0"):
        train_codebook(np.full((300, 32), np.nan, np.float32), m=8)


def test_lut_kernel_for_m_not_multiple_of_4():
    x, _, dirs = clip_like(600, 30, labels=4, seed=7)
    book = train_codebook(x, m=6)
    field = build_field(x, np.ones(len(x), np.float32), book)
    q = np.concatenate([dirs, hard_queries(30, np.random.default_rng(2))])
    np.testing.assert_allclose(field.scores(q), field.scores_reference(q), atol=TOL, rtol=0)


# ---------------------------------------------------------------------------------------------
# Blocked kernels: float32 tables (exact) and 8-bit tables (approximate), AVX-512 and portable

EDGE_NS = [0, 1, 63, 64, 65, 200]


@pytest.mark.parametrize("n", EDGE_NS)
def test_blocked_codes_layout(n):
    codes = np.random.default_rng(n).integers(0, 256, size=(n, 12), dtype=np.uint8)
    blocked = blocked_codes(codes)
    assert blocked.shape == (-(-n // Q8_BLOCK), 12, Q8_BLOCK) and blocked.dtype == np.uint8
    i = np.arange(n)
    np.testing.assert_array_equal(blocked[i // Q8_BLOCK, :, i % Q8_BLOCK], codes)
    assert blocked.size == 0 or blocked.reshape(-1, 12, Q8_BLOCK).transpose(0, 2, 1).reshape(-1, 12)[n:].sum() == 0


def extreme_tables(m: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Random, huge, tiny, signed-zero and constant float32 tables [M, 256]."""
    base = rng.normal(size=(m, 256)).astype(np.float32)
    huge = (base * 1e30).astype(np.float32)
    tiny = (base * 1e-30).astype(np.float32)
    zeros = np.zeros((m, 256), np.float32)
    zeros[:, ::2] = -0.0
    return [base, huge, tiny, zeros, np.full((m, 256), 3.5, np.float32)]


@pytest.mark.parametrize("use_simd", [True, False])
@pytest.mark.parametrize("n", EDGE_NS)
def test_f32_sums_equal_numpy_gather(n, use_simd):
    rng = np.random.default_rng(n + 7)
    for m in (1, 5, 128):
        codes = rng.integers(0, 256, size=(n, m), dtype=np.uint8)
        codes[:1] = 255  # the highest entry of every table
        for lut in extreme_tables(m, rng):
            got = f32_sums(blocked_codes(codes), lut, use_simd)
            assert got.shape == (-(-n // Q8_BLOCK) * Q8_BLOCK,) and got.dtype == np.float32
            ref = lut.astype(np.float64)[np.arange(m)[None, :], codes].sum(axis=1)
            scale = np.abs(lut.astype(np.float64)[np.arange(m)[None, :], codes]).sum(axis=1)
            assert np.all(np.abs(got[:n] - ref) <= 1e-6 * scale + 1e-45), (m, float(np.abs(lut).max()))


@pytest.mark.parametrize("use_simd", [True, False])
@pytest.mark.parametrize("n", EDGE_NS)
def test_q8_sums_are_exact_integers(n, use_simd):
    rng = np.random.default_rng(n + 11)
    for m in (1, 3, 128, 257):
        codes = rng.integers(0, 256, size=(n, m), dtype=np.uint8)
        codes[:1] = 255
        for qlut in (rng.integers(0, 256, size=(m, 256)).astype(np.uint8), np.full((m, 256), 255, np.uint8)):
            got = q8_sums(blocked_codes(codes), qlut, use_simd)
            ref = qlut.astype(np.int64)[np.arange(m)[None, :], codes].sum(axis=1)
            np.testing.assert_array_equal(got[:n].astype(np.int64), ref)
    if n:
        assert q8_sums(blocked_codes(np.full((n, 257), 255, np.uint8)), np.full((257, 256), 255, np.uint8), use_simd)[0] == 65535


def test_q8_sums_refuse_m_that_overflows_uint16():
    with pytest.raises(ValueError, match="M ≤ 257"):
        q8_sums(blocked_codes(np.zeros((3, 258), np.uint8)), np.zeros((258, 256), np.uint8))


def test_quantize_luts_error_bound():
    rng = np.random.default_rng(4)
    luts = np.stack([rng.normal(size=(16, 256)), rng.normal(size=(16, 256)) * 1e6, np.full((16, 256), -2.0)]).astype(np.float32)
    luts[0, 3] += 5.0  # one sub-table with a much larger range sets the scale
    q, scale, offset, exact = quantize_luts(luts)
    assert q.dtype == np.uint8 and scale.shape == offset.shape == (3,) and not exact.any()
    lo = luts.astype(np.float64).min(axis=2)
    approx = lo[:, :, None] + scale[:, None, None].astype(np.float64) * q
    assert np.all(np.abs(approx - luts) <= scale[:, None, None] * 0.5 * (1 + 1e-5) + 1e-6 * np.abs(luts))
    np.testing.assert_allclose(offset, lo.sum(axis=1), rtol=1e-6)
    assert np.all(q[2] == 0) and offset[2] == -32.0, "a constant table is represented exactly"


def test_an_outlying_sub_table_stays_float32_and_the_rest_get_a_finer_scale():
    """One sub-table 12-18x wider than the others (a CLIP text embedding's outlier component) set
    the one 8-bit scale; it is now kept in float32 (`exact`, q = 0, out of the offset) and the scale
    comes from the others, so every quantised entry is within their scale / 2 and a sum of the
    kept float table and the 8-bit ones is the float sum within M·scale/2."""
    rng = np.random.default_rng(7)
    luts = rng.normal(size=(2, 32, 256))
    luts[0, 5] *= 15.0  # query 0: one wide table; query 1: none
    q, scale, offset, exact = quantize_luts(luts)
    assert exact[0].tolist() == [m == 5 for m in range(32)] and not exact[1].any()
    assert np.all(q[0, 5] == 0)
    spans = luts.max(axis=2) - luts.min(axis=2)
    np.testing.assert_allclose(scale[0], np.delete(spans[0], 5).max() / 255, rtol=1e-6)
    lo = luts.min(axis=2)
    approx = np.where(exact[:, :, None], luts, lo[:, :, None] + scale[:, None, None].astype(np.float64) * q)
    assert np.all(np.abs(approx - luts) <= scale[:, None, None] * 0.5 * (1 + 1e-5))
    np.testing.assert_allclose(offset, np.where(exact, 0.0, lo).sum(axis=1), rtol=1e-6)


@pytest.mark.parametrize("use_simd", [True, False])
def test_8bit_scores_of_a_query_with_an_outlying_component_follow_the_float_tables(data, books, use_simd):
    """A unit query with one component of 0.7 (as CLIP text embeddings have): the 8-bit scores
    equal the reference's (the same kept float table) and stay within the float32 tables' scores
    by the bound of the finer scale."""
    x, w, _, _ = data
    field = build_field(x, w, books[16], clip_model="oracle")
    rng = np.random.default_rng(11)
    q = rng.normal(size=(3, x.shape[1])) * 0.05
    q[:, 3] = 0.7
    qn = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)
    _, scale, _, exact = quantize_luts(field.codebook.luts(qn))
    assert exact.any(axis=1).all(), "the component's sub-table is kept in float32"
    got = lut_scores_blocked(field.codebook, blocked_codes(field.codes), len(x), None, field.norms, qn, 8, use_simd)
    np.testing.assert_allclose(got, lut_scores_q8_reference(field.codebook, field.codes, None, field.norms, qn), atol=TOL, rtol=0)
    f32 = lut_scores(field.codebook, field.codes, None, field.norms, qn)
    bound = 16 * scale[None, :] / 2 / np.where(field.norms > 0, field.norms, 1)[:, None]
    assert np.all(np.abs(got - f32) <= bound + TOL)


BLOCKED_PATHS = [(32, True), (32, False), (8, True), (8, False)]


@pytest.mark.parametrize("bits,use_simd", BLOCKED_PATHS)
@pytest.mark.parametrize("m", [8, 16, 32])
def test_blocked_lut_scores_agree_with_references(data, books, m, bits, use_simd):
    x, w, _, _ = data
    field = build_field(x, w, books[m], clip_model="oracle")
    q = hard_queries(x.shape[1], np.random.default_rng(m))
    qn = q / np.linalg.norm(q, axis=1, keepdims=True)
    got = lut_scores_blocked(field.codebook, blocked_codes(field.codes), len(x), None, field.norms, qn, bits, use_simd)
    exact = field.scores_reference(q)
    assert got.shape == (len(x), 5) and np.all(got[:5] == 0)
    if bits == 32:
        np.testing.assert_allclose(got, exact, atol=TOL, rtol=0)
        np.testing.assert_allclose(got, lut_scores(field.codebook, field.codes, None, field.norms, qn), atol=TOL, rtol=0)
    else:
        np.testing.assert_allclose(got, lut_scores_q8_reference(field.codebook, field.codes, None, field.norms, qn), atol=TOL, rtol=0)
        _, scale, _, _ = quantize_luts(field.codebook.luts(qn))
        bound = m * scale[None, :] / 2 / np.where(field.norms > 0, field.norms, 1)[:, None]
        assert np.all(np.abs(got - exact) <= bound + TOL)
        assert np.abs(got - exact).mean() < 0.5 * bound.mean(), "rounding errors should partly cancel"


@pytest.mark.parametrize("bits,use_simd", BLOCKED_PATHS)
def test_blocked_lut_scores_edge_shapes_and_bad_norms(books, bits, use_simd):
    book = books[16]
    rng = np.random.default_rng(5)
    for n, k in [(0, 1), (1, 1), (65, 3), (130, 17)]:
        codes = rng.integers(0, 256, size=(n, book.m), dtype=np.uint8)
        norms = np.linalg.norm(book.decode(codes), axis=1).astype(np.float32)
        norms[1:4] = [np.inf, np.nan, 0.0][: max(0, min(3, n - 1))]
        q = rng.normal(size=(k, book.dim)).astype(np.float32)
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        got = lut_scores_blocked(book, blocked_codes(codes), n, None, norms, q, bits, use_simd)
        assert got.shape == (n, k) and np.all(np.isfinite(got))
        ref = lut_scores_reference(book, codes, None, norms, q) if bits == 32 else lut_scores_q8_reference(book, codes, None, norms, q)
        np.testing.assert_allclose(got, ref, atol=TOL, rtol=0)
        if bits == 32:
            np.testing.assert_allclose(lut_scores(book, codes, None, norms, q), ref, atol=TOL, rtol=0)
    with pytest.raises(ValueError, match="N = 5"):
        lut_scores_blocked(book, blocked_codes(np.zeros((70, book.m), np.uint8)), 5, None, np.ones(5, np.float32), q)


def test_field_lut_bits_option(data, books):
    x, w, _, dirs = data
    field = build_field(x, w, books[32], clip_model="oracle")
    exact = field.scores_reference(dirs)
    np.testing.assert_allclose(field.scores(dirs), exact, atol=TOL, rtol=0)
    approx = field.scores(dirs, lut_bits=8)
    assert approx.shape == exact.shape and np.all(approx[:5] == 0)
    assert 0 < np.abs(approx - exact).max() < 0.02
    sub = field.subset(np.arange(10, 300))
    np.testing.assert_allclose(sub.scores(dirs, lut_bits=8), approx[10:300], atol=TOL, rtol=0)
    with pytest.raises(ValueError, match="lut_bits"):
        field.scores(dirs, lut_bits=4)


def test_simd_kernels_are_used_when_the_cpu_has_them():
    import llvmlite.binding as llvm

    assert simd_available() == bool(llvm.get_host_cpu_features().get("avx512f"))


def test_codebook_decode_matches_faiss(books, data):
    book = books[32]
    codes, _ = book.encode(data[0][5:50])
    np.testing.assert_array_equal(codes, book.index.sa_encode(data[0][5:50]))
    np.testing.assert_allclose(book.decode(codes), book.index.sa_decode(codes), atol=1e-6)


@pytest.mark.parametrize("n,width", [(0, 3), (1, 1), (63, 5), (64, 128), (1000, 130), (4097, 7)])
def test_stack_columns_equals_the_column_by_column_copy(n, width):
    """A field's PLY columns stacked into [N, width] (`stack_columns`, stacked then transposed by a
    blocked kernel) are the column-by-column copy, for row counts around its 64-row blocks, uint8
    codes from wider integer columns and float16 bits."""
    from drsplat.lang.backends import stack_columns, stack_columns_reference

    rng = np.random.default_rng(n + width)
    for dtype, source in ((np.uint8, np.int32), (np.uint16, np.uint16)):
        cols = [rng.integers(0, 256 if dtype == np.uint8 else 65536, n).astype(source) for _ in range(width)]
        block = np.empty((width + 2, n), source)  # the loader's layout: the columns as rows of one array
        block[1:-1] = cols
        for given in (cols, list(block[1:-1]), list(block[1:-1])[::-1]):
            got = stack_columns(given, dtype, n, width)
            assert got.dtype == dtype and got.shape == (n, width)
            np.testing.assert_array_equal(got, stack_columns_reference(given, dtype, n, width))
    m = max(n, 2)
    square = np.arange(m * m, dtype=np.int32).reshape(m, m).copy()  # its first column starts where row 0 does
    for given in ([square[:, 0]], [square[:, 0], square[:, 1]], [square[0].view(np.uint32)]):
        np.testing.assert_array_equal(stack_columns(given, np.int64, m, len(given)), stack_columns_reference(given, np.int64, m, len(given)))


@pytest.mark.parametrize("dim", [1, 2, 7, 8, 9, 16, 17, 127, 128, 129, 130, 256, 257, 300, 512, 513, 768, 1024, 1100])
def test_float16_row_norms_are_numpys_bits(dim):
    """An exact field's norms (`chunked_row_norms`: float16 rows, numpy's pairwise order) are
    np.linalg.norm's float32 bits, for lengths around its 8-wide accumulators and 128-long blocks,
    rows of 1e-3 to 100, zero rows, the largest and smallest halves, infinities and NaN; the same bits for the rows
    held column-ordered or strided, and as float32."""
    from drsplat.lang.backends import chunked_row_norms, chunked_row_norms_reference

    rng = np.random.default_rng(dim)
    x = (rng.normal(size=(700, dim)) * rng.choice([1e-3, 1.0, 100.0], size=(700, 1))).astype(np.float16)
    x[0] = 0
    x[1, 0] = np.float16(6e-8)
    x[2] = np.float16(65504)
    x[3, -1], x[4, 0] = np.inf, np.nan
    got, want = chunked_row_norms(x), chunked_row_norms_reference(x)
    np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))
    for layout in (np.asfortranarray(x), x[:, ::-1][:, ::-1], np.asfortranarray(x.astype(np.float32))):  # 66c F4: not by layout
        np.testing.assert_array_equal(chunked_row_norms(layout).view(np.uint32), want.view(np.uint32))
        np.testing.assert_array_equal(chunked_row_norms_reference(layout).view(np.uint32), want.view(np.uint32))


def test_half_to_float_bits_for_every_half():
    """The norms kernel's float16 -> float32 conversion gives numpy's cast bits for all 65,536 halves
    (signs, subnormals, infinities and NaN payloads included)."""
    import numba

    from drsplat.lang.backends import _float_bits_of_half

    @numba.njit
    def convert(bits, out):
        for i in range(bits.shape[0]):
            out[i] = _float_bits_of_half(bits[i])

    halves = np.arange(65536, dtype=np.uint16)
    got = np.empty(65536, np.uint32)
    convert(halves, got)
    np.testing.assert_array_equal(got, halves.view(np.float16).astype(np.float32).view(np.uint32))


def test_reconstruction_norms_kernel_equals_decoding(books, data):
    """The PQ backend's norms, summed from the codes without decoding (`reconstruction_norms`), are
    the decoded rows' norms: random and hard codes (all 0, all 255) of every test codebook, and no
    rows (the ivfpq case, coarse lists included: `test_official_codebook_norms_without_decoding`)."""
    from drsplat.lang.backends import reconstruction_norms, reconstruction_norms_reference

    rng = np.random.default_rng(4)
    for book in books.values():
        codes = rng.integers(0, 256, (300, book.m)).astype(np.uint8)
        codes[0], codes[1] = 0, 255
        np.testing.assert_allclose(reconstruction_norms(book, codes, None), reconstruction_norms_reference(book, codes, None), rtol=1e-6)
        assert reconstruction_norms(book, codes[:0], None).shape == (0,)


def test_exact_field_is_float16_cosine(data):
    x, w, _, _ = data
    field = build_field(x, w, "none", clip_model="oracle")
    assert field.kind == "exact" and field.features.dtype == np.float16
    q = hard_queries(x.shape[1], np.random.default_rng(0))
    s = field.scores(q)
    np.testing.assert_allclose(s, field.scores_reference(q), atol=TOL, rtol=0)
    qn = q / np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(s, x @ qn.T, atol=2e-3)
    assert np.all(s[:5] == 0)


def test_half_kernel_on_hard_values():
    """float16 bit tricks: zeros, -0, subnormals, the largest half, and non-finite rows (score 0)."""
    from drsplat.lang import half_scores

    rng = np.random.default_rng(4)
    f = rng.normal(size=(300, 40)).astype(np.float16)
    f[0] = 0
    f[1, :] = np.float16(-0.0)
    f[1, 0] = np.float16(1e-7)  # subnormal
    f[2] = np.float16(6e-8) * rng.integers(1, 20, 40)  # all subnormal
    f[3, :3] = np.float16(65504)
    f[4, 5] = np.inf
    f[5, 7] = np.nan
    norms = np.linalg.norm(f.astype(np.float64), axis=1).astype(np.float32)
    q = hard_queries(40, rng)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    got = half_scores(f, norms, q)
    with np.errstate(invalid="ignore", divide="ignore"):
        ref = (f.astype(np.float64) @ q.T.astype(np.float64)) / norms[:, None].astype(np.float64)
    finite = np.isfinite(norms) & (norms > 0)
    np.testing.assert_allclose(got[finite], ref[finite], atol=TOL, rtol=0)
    assert np.all(got[~finite] == 0) and (~finite).sum() == 3
    assert abs(got[2, 0] - ref[2, 0]) < TOL and abs(got[1, 1] - ref[1, 1]) < TOL
    # round 56a: with norms given rather than made from the rows (ExactStorage's known_norms), a row holding inf or NaN read as
    # finite halves (65536, 98304) and scored; it scores 0 as the docstring says, and so does the float64 reference
    from drsplat.lang.backends import ExactStorage

    given = np.where(np.isfinite(norms), norms, 1.0).astype(np.float32)
    assert np.all(half_scores(f, given, q)[4:6] == 0)
    np.testing.assert_array_equal(half_scores(f, given, q)[finite], got[finite])
    storage = ExactStorage(f, given)
    assert np.all(storage.scores(q)[4:6] == 0) and np.all(storage.scores_reference(q)[4:6] == 0)
    assert np.isfinite(storage.scores_reference(q)).all()


def test_backends_agree_on_selection(data, books):
    """Every backend selects (nearly) the same Gaussians for a label query as the exact field."""
    x, w, lab, dirs = data
    exact = build_field(x, w, "none").scores(dirs)
    for m, book in books.items():
        pq = build_field(x, w, book).scores(dirs)
        assert np.mean(np.abs(pq - exact)) < 0.03, m
        assert np.mean(np.argmax(pq[5:], 1) == np.argmax(exact[5:], 1)) > 0.97, m
    assert np.mean(np.argmax(exact[5:], 1) == lab[5:]) > 0.99


def test_scene_codebook_trains_on_mask_embeddings(data):
    x, w, _, dirs = data
    field = build_field(x, w, "scene", train_embeddings=x[5:400], m=16)
    assert field.kind == "pq" and field.codes.shape == (len(x), 16)
    np.testing.assert_allclose(field.scores(dirs), field.scores_reference(dirs), atol=TOL, rtol=0)
    with pytest.raises(InputError, match="at least 256"):
        build_field(x[:100], w[:100], "scene", train_embeddings=x[5:50], m=16)


def test_the_scene_sample_is_the_same_gaussians_in_the_same_order_whatever_the_rows_order():
    """Round 49 left as found: the top-up sample of a scene codebook was drawn by id, so permuting the
    scene's Gaussians moved the codebook. Now it is the rows of lowest hash, in hash order."""
    from drsplat.lang.field import row_hashes, scene_sample_ids

    rng = np.random.default_rng(3)
    rows = rng.normal(size=(5000, 11)).astype(np.float32)
    rows[4000:4010] = rows[7]  # rows of the same bytes: alike keys, ties to the lower id
    candidates = np.flatnonzero(rng.random(5000) < 0.7)
    perm = rng.permutation(5000)  # new row i holds old row perm[i]
    inverse = np.argsort(perm)
    for count in (1, 300, 5000):
        old = scene_sample_ids(candidates, lambda ids: rows[ids], count=count)
        new = scene_sample_ids(np.sort(inverse[candidates]), lambda ids: rows[perm][ids], count=count)
        assert len(old) == min(count, len(candidates))
        np.testing.assert_array_equal(rows[old], rows[perm][new])  # the same rows, in the same order
    keys = row_hashes(rows)
    old = scene_sample_ids(candidates, lambda ids: rows[ids], count=300)
    assert np.all(np.diff(keys[old].astype(np.float64)) >= 0) and set(old) <= set(candidates)
    assert keys[old].max() <= np.sort(keys[candidates])[299]  # the lowest keys (the chunked running best is exact)
    assert len(np.unique(keys)) == 5000 - 10 and keys[4000] == keys[7]


def test_row_hashes_equal_a_plain_loop_of_their_formula():
    from drsplat.lang.field import row_hashes

    rows = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)
    mask = (1 << 64) - 1
    for seed in (0, 5):
        expected = []
        for row in rows.view(np.uint32):
            h = 14695981039346656037 ^ seed
            for word in row:
                h = ((h ^ int(word)) * 1099511628211) & mask
            h = ((h ^ (h >> 30)) * 0xBF58476D1CE4E5B9) & mask
            h = ((h ^ (h >> 27)) * 0x94D049BB133111EB) & mask
            expected.append(h ^ (h >> 31))
        np.testing.assert_array_equal(row_hashes(rows, seed), np.array(expected, np.uint64))
    with pytest.raises(ValueError, match="whole 32-bit words"):
        row_hashes(np.zeros((3, 3), np.uint8))
    assert row_hashes(np.zeros((0, 11), np.float32)).shape == (0,)  # no rows: no keys (a reshape of 0 rows to (0, -1) raised)
    np.testing.assert_array_equal(row_hashes(rows[:, 0]), row_hashes(rows[:, :1]))  # a 1-D row is one word


def test_a_scene_codebook_topped_up_with_features_is_the_same_for_permuted_rows(data):
    x, w, _, dirs = data
    perm = np.random.default_rng(2).permutation(len(x))
    a = build_field(x, w, "scene", train_embeddings=x[:100], m=16)  # 100 masks: topped up with features
    b = build_field(x[perm], w[perm], "scene", train_embeddings=x[:100], m=16)
    np.testing.assert_array_equal(a.codes[perm], b.codes)
    np.testing.assert_array_equal(a.scores(dirs)[perm], b.scores(dirs))


def test_subset_keeps_scores(data, books):
    x, w, _, dirs = data
    field = build_field(x, w, books[8])
    ids = np.array([7, 3, 1000, 3])
    np.testing.assert_array_equal(field.subset(ids).scores(dirs), field.scores(dirs)[ids])
    np.testing.assert_array_equal(field.subset(ids).reconstruct(), field.reconstruct(ids))


@pytest.mark.parametrize("backend", ["none", "pq", "scene"])
def test_ply_encoding_round_trip(tmp_path, data, books, backend):
    x, w, _, dirs = data
    codebook = books[16] if backend == "pq" else backend
    field = build_field(x, w, codebook, clip_model="ViT-B-16/laion2b_s34b_b88k", train_embeddings=x[5:], m=8)
    ply = tmp_path / "reg.ply"
    scene = attach_field(tiny_scene(len(x)), field, ply)
    assert scene.comments[0] == "trained by someone"
    comment = scene.comments[-1]
    assert comment.startswith("drsplat.lang kind=") and "clip=ViT-B-16/laion2b_s34b_b88k" in comment
    assert scene.extra["lang_weight"].dtype == np.float32
    if field.kind == "exact":
        assert scene.extra["lang_0"].dtype == np.uint16 and f"lang_{x.shape[1] - 1}" in scene.extra
        assert not codebook_path_for(ply).exists()
    else:
        assert scene.extra["lang_code_0"].dtype == np.uint8 and scene.extra["lang_norm"].dtype == np.float32
        assert "codebook=reg.codebook.faiss" in comment and codebook_path_for(ply).is_file()
    back = read_field(scene, ply)
    assert back.kind == field.kind and back.dim == field.dim and back.clip_model == field.clip_model
    np.testing.assert_array_equal(back.scores(dirs), field.scores(dirs))
    np.testing.assert_array_equal(back.weights, w)
    # attaching again replaces the field instead of adding a second one
    again = attach_field(scene, field, ply)
    assert sum(c.startswith("drsplat.lang") for c in again.comments) == 1
    assert strip_field(again).extra == {} and strip_field(again).comments == ["trained by someone"]


def test_ply_round_trip_through_save_and_load(tmp_path, data, books):
    from drsplat.scene import load_ply, save_ply

    x, w, _, dirs = data
    for codebook in ("none", books[8]):
        field = build_field(x, w, codebook, clip_model="oracle")
        ply = tmp_path / f"reg_{field.kind}.ply"
        save_ply(attach_field(tiny_scene(len(x)), field, ply), ply)
        back = read_field(load_ply(ply), ply)
        assert back.kind == field.kind
        np.testing.assert_array_equal(back.scores(dirs), field.scores(dirs))


def test_a_pq_ply_exported_through_a_link_keeps_its_codebook_beside_the_target(tmp_path, data, books, caplog):
    """Round 44: written through links/reg.ply -> real/target.ply, the codebook went beside the link as
    reg.codebook.faiss while the target's header named that file in real/, where it was not: the file
    read directly was refused. Now it lies beside the target under the target's name, and the PLY
    reads back through the link and directly. Into a FIFO nothing is written beside it, and one warning
    names the codebook its reader would need."""
    import threading

    from drsplat.lang import export_scene
    from drsplat.scene import load_ply

    x, w, _, dirs = data
    field = build_field(x, w, books[16], clip_model="oracle")
    (tmp_path / "real").mkdir()
    (tmp_path / "links").mkdir()
    target, link = tmp_path / "real" / "target.ply", tmp_path / "links" / "reg.ply"
    link.symlink_to(target)
    export_scene(tiny_scene(len(x)), field, link, "drsplat")
    assert sorted(p.name for p in (tmp_path / "links").iterdir()) == ["reg.ply"] and link.is_symlink()
    assert sorted(p.name for p in (tmp_path / "real").iterdir()) == ["target.codebook.faiss", "target.ply"]
    for opened in (target, link):
        np.testing.assert_array_equal(read_field(load_ply(opened), opened).scores(dirs), field.scores(dirs))
    fifo = tmp_path / "pipe.ply"
    os.mkfifo(fifo)
    got: list[bytes] = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_bytes()), daemon=True)
    reader.start()
    with caplog.at_level(logging.WARNING, logger="drsplat"):
        export_scene(tiny_scene(len(x)), field, fifo, "drsplat")
    reader.join(timeout=30)
    assert got and got[0].startswith(b"ply\n") and b"codebook=pipe.codebook.faiss" in got[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["links", "pipe.ply", "real"]
    assert any("pipe.codebook.faiss) was not written" in r.getMessage() for r in caplog.records)


def test_read_field_errors_name_the_problem(tmp_path, data, books):
    x, w, _, _ = data
    ply = tmp_path / "reg.ply"
    assert read_field(tiny_scene(3), ply) is None
    scene = attach_field(tiny_scene(len(x)), build_field(x, w, books[8]), ply)
    broken = GaussianScene(**{**scene.__dict__, "extra": {k: v for k, v in scene.extra.items() if k != "lang_code_3"}})
    with pytest.raises(InputError, match="lang_code_3"):
        read_field(broken, ply)
    # round 59a: an empty codebook= entry read as the PLY's own folder: "is not a regular file (a folder)"
    empty = GaussianScene(**{**scene.__dict__, "comments": [c.replace("codebook=reg.codebook.faiss", "codebook=") for c in scene.comments]})
    assert "codebook= " in empty.comments[-1] or empty.comments[-1].endswith("codebook=")
    with pytest.raises(InputError, match="reg.ply: .*a quantised language field names no codebook file"):
        read_field(empty, ply)
    codebook_path_for(ply).unlink()
    with pytest.raises(InputError, match="codebook file not found"):
        read_field(scene, ply)
    from drsplat.commands.info import field_summary  # round 59a: info's finding did not say which codebook is missing

    assert field_summary(scene, ply)[1] == [f"language field: {codebook_path_for(ply)}: codebook file not found (the codebook reg.ply's header names)"]
    bad_kind = GaussianScene(**{**scene.__dict__, "comments": ["drsplat.lang kind=zip dim=64 clip=x"]})
    with pytest.raises(InputError, match="unknown language field kind"):
        read_field(bad_kind, ply)
    (tmp_path / "junk.faiss").write_bytes(b"not faiss")
    with pytest.raises(InputError, match="not a faiss index"):
        load_codebook(tmp_path / "junk.faiss")


@pytest.mark.parametrize("cut", [1, 4, 9])
def test_codebook_cut_inside_its_last_fields_says_truncated(books, tmp_path, cut, caplog):
    """IndexPQ ends with 9 bytes of fields after the codes: a copy missing some of them made faiss
    throw its C++ text ("read error in ..."). Bytes appended after them are a warning."""
    books[8].save(tmp_path / "cb.faiss")
    whole = (tmp_path / "cb.faiss").read_bytes()
    (tmp_path / "cut.faiss").write_bytes(whole[:-cut])
    with pytest.raises(InputError, match=r"cut\.faiss: faiss file is truncated inside .* after the codes"):
        load_codebook(tmp_path / "cut.faiss")
    (tmp_path / "joined.faiss").write_bytes(whole + b"\0" * cut)
    with caplog.at_level(logging.WARNING):
        book = load_codebook(tmp_path / "joined.faiss")
    assert f"{cut} bytes follow the codebook's last field" in caplog.text
    np.testing.assert_array_equal(book.centroids, books[8].centroids)


@pytest.mark.parametrize("entries", [0, 300])
def test_bytes_after_an_ivfpq_codebook_are_a_warning_too(data, tmp_path, caplog, entries):
    """Round 59a: 5 MB appended to the official IndexIVFPQ were read without a word, while an IndexPQ's were a warning.
    The inverted lists' codes and ids (code_size + 8 bytes an entry) are skipped, and what follows is said; an index
    with filled lists, or none, warns of nothing."""
    import faiss

    x = np.ascontiguousarray(data[0][5:])
    index = faiss.IndexIVFPQ(faiss.IndexFlatIP(x.shape[1]), x.shape[1], 4, 8, 8, faiss.METRIC_INNER_PRODUCT)
    index.train(x)
    index.add(x[:entries])
    whole = faiss.serialize_index(index).tobytes()
    (tmp_path / "cb.faiss").write_bytes(whole)
    with caplog.at_level(logging.WARNING):
        load_codebook(tmp_path / "cb.faiss")
    assert "follow the codebook's last field" not in caplog.text
    (tmp_path / "joined.faiss").write_bytes(whole + b"\0" * 5)
    with caplog.at_level(logging.WARNING):
        load_codebook(tmp_path / "joined.faiss")
    assert "joined.faiss: 5 bytes follow the codebook's last field and are ignored" in caplog.text


def _direct_map_type_at(whole: bytes, d: int, nlist: int) -> int:
    """The offset of an IwPQ file's direct map type byte: fourcc, index header (d int32, ntotal, two dummies, is_trained,
    metric), nlist, nprobe, the flat quantiser's fourcc and header, its centroid vector."""
    header = 4 + 4 + 8 + 8 + 8 + 1 + 4
    at = header + 8 + 8 + header  # the IVF's header, nlist, nprobe, then the quantiser's
    assert whole[:4] == b"IwPQ" and int.from_bytes(whole[at:at + 8], "little") == nlist * d
    return at + 8 + 4 * nlist * d


def test_an_ivfpq_codebook_with_a_hashtable_direct_map_is_read_whole(data, tmp_path):
    """Round 91d F1: the direct map's type byte was read and not checked, and a hashtable's (id, index) pairs, which
    follow its array, were not skipped: a 2.6 MB file whose type byte said "hashtable" led faiss to sizes the check
    never saw (2.25 GB allocated). A real hashtable map is walked now (and loads), an unknown type is refused, and
    a corrupt file's sizes behind the pairs are checked against the file."""
    import faiss

    x = np.ascontiguousarray(data[0][5:])
    index = faiss.IndexIVFPQ(faiss.IndexFlatIP(x.shape[1]), x.shape[1], 4, 8, 8, faiss.METRIC_INNER_PRODUCT)
    index.train(x)
    index.set_direct_map_type(faiss.DirectMap.Hashtable)
    index.add(x[:50])
    whole = faiss.serialize_index(index).tobytes()
    (tmp_path / "hash.faiss").write_bytes(whole)
    book = load_codebook(tmp_path / "hash.faiss")
    assert book.m == 8 and book.centroids.shape == (8, 256, x.shape[1] // 8)
    at = _direct_map_type_at(whole, x.shape[1], 4)
    assert whole[at] == 2
    (tmp_path / "three.faiss").write_bytes(whole[:at] + b"\x03" + whole[at + 1:])
    with pytest.raises(InputError, match=r"direct map type 3; faiss knows 0 \(none\), 1 \(array\) and 2 \(hashtable\)"):
        load_codebook(tmp_path / "three.faiss")
    pairs_at = at + 1 + 8 + 8 * int.from_bytes(whole[at + 1:at + 9], "little")
    huge = whole[:pairs_at] + (1 << 40).to_bytes(8, "little") + whole[pairs_at + 8:]  # pairs a terabyte long
    (tmp_path / "huge.faiss").write_bytes(huge)
    with pytest.raises(InputError, match=r"direct map hashtable declares 1099511627776 values .* the file is truncated or corrupt"):
        load_codebook(tmp_path / "huge.faiss")
    (tmp_path / "legacy.faiss").write_bytes(b"IvPQ" + whole[4:])
    with pytest.raises(InputError, match=r"pre-2018 layout \(type code IvPQ\), which drsplat does not read"):
        load_codebook(tmp_path / "legacy.faiss")


def test_codebook_dimension_mismatch_is_an_input_error(data, tmp_path):
    book = train_codebook(data[0][5:], m=8)
    book.save(tmp_path / "cb.faiss")
    x = np.random.default_rng(0).normal(size=(10, 32)).astype(np.float32)
    with pytest.raises(InputError, match="dimension 64 differs"):
        build_field(x, np.ones(10, np.float32), tmp_path / "cb.faiss")


# ---------------------------------------------------------------------------------------------
# The official Dr. Splat codebook (../shared/data/drsplat/pq_index.faiss)


@pytest.fixture(scope="module")
def official() -> Codebook:
    return load_codebook(shared_path("drsplat", "pq_index.faiss"))


def test_official_codebook_norms_without_decoding(official):
    """`reconstruction_norms` on the official IndexIVFPQ (coarse list + residual codes) equals
    decoding the rows and taking their norms."""
    from drsplat.lang.backends import reconstruction_norms, reconstruction_norms_reference

    rng = np.random.default_rng(5)
    codes = rng.integers(0, 256, (500, official.m)).astype(np.uint8)
    ids = rng.integers(0, official.nlist, 500).astype(np.int32)
    np.testing.assert_allclose(reconstruction_norms(official, codes, ids), reconstruction_norms_reference(official, codes, ids), rtol=1e-6)


def test_official_codebook_is_ivfpq_128x8(official):
    assert official.kind == "ivfpq" and official.dim == 512 and official.m == 128
    assert official.nlist == 1024 and official.index.by_residual
    assert official.index.sa_code_size() == 130


def test_official_codebook_lut_equals_decode_then_cosine(official):
    x, _, dirs = clip_like(3000, 512, labels=6, seed=5)
    w = np.ones(len(x), np.float32)
    w[-3:] = 0
    field = build_field(x, w, official, clip_model="ViT-B-16/laion2b_s34b_b88k")
    # our (list id, codes) are faiss's own 130-byte codes: 2-byte little-endian list id + 128 PQ bytes
    raw = official.index.sa_encode(x[:200])
    np.testing.assert_array_equal(raw[:, 0].astype(np.int32) + 256 * raw[:, 1].astype(np.int32), field.list_ids[:200])
    np.testing.assert_array_equal(raw[:, 2:], field.codes[:200])
    np.testing.assert_allclose(field.reconstruct(np.arange(200)), official.index.sa_decode(raw), atol=1e-6)
    q = np.concatenate([dirs, hard_queries(512, np.random.default_rng(1))])
    ref = field.scores_reference(q)
    np.testing.assert_allclose(field.scores(q), ref, atol=TOL, rtol=0)
    assert np.all(field.scores(q)[-3:] == 0)
    qn = q / np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(lut_scores(official, field.codes, field.list_ids, field.norms, qn), ref, atol=TOL, rtol=0)
    blocked = blocked_codes(field.codes)
    for use_simd in (True, False):
        got = lut_scores_blocked(official, blocked, len(x), field.list_ids, field.norms, qn, 32, use_simd)
        np.testing.assert_allclose(got, ref, atol=TOL, rtol=0)
        got8 = lut_scores_blocked(official, blocked, len(x), field.list_ids, field.norms, qn, 8, use_simd)
        np.testing.assert_allclose(got8, lut_scores_q8_reference(official, field.codes, field.list_ids, field.norms, qn), atol=TOL, rtol=0)


def test_official_codebook_round_trips_through_ply_encoding(official, tmp_path):
    x, _, dirs = clip_like(300, 512, seed=2)
    field = build_field(x, np.ones(len(x), np.float32), official.path)
    ply = tmp_path / "scene.ply"
    scene = attach_field(tiny_scene(len(x)), field, ply)
    assert scene.extra["lang_list"].dtype == np.int32
    assert codebook_path_for(ply).read_bytes() == official.path.read_bytes()
    np.testing.assert_array_equal(read_field(scene, ply).scores(dirs), field.scores(dirs))


def test_8bit_scores_of_real_clip_text_queries_follow_the_float_tables(official):
    """The official codebook and the real CLIP text embeddings shipped with it (one component of
    0.6-0.75 each): with the wide sub-tables kept in float32, the 8-bit scores of random unit
    features are several times closer to the float32 tables' than with faiss's one scale, and
    their top 1 % is nearly the float32 tables' (a numerical probe, 2026-11-30: 0.877-0.937)."""
    rng = np.random.default_rng(3)
    n = 20_000
    feats = unit_rows(rng.normal(size=(n, 512)).astype(np.float32))
    field = build_field(feats, np.ones(n, np.float32), codebook=official)
    queries = unit_rows(np.load(shared_path("drsplat", "text_negative.npy")).astype(np.float32))
    store = field.storage
    blocked = blocked_codes(store.codes)
    f32 = lut_scores_blocked(official, blocked, n, store.list_ids, store.norms, queries, 32)
    one_scale = lut_scores_blocked(official, blocked, n, store.list_ids, store.norms, queries, 8, exact_span=np.inf)
    kept = lut_scores_blocked(official, blocked, n, store.list_ids, store.norms, queries, 8)
    assert np.abs(kept - f32).mean() < 0.4 * np.abs(one_scale - f32).mean()
    top = np.quantile(f32, 0.99, axis=0)
    for k in range(len(queries)):
        a, b = kept[:, k] >= top[k], f32[:, k] >= top[k]
        assert (a & b).sum() / (a | b).sum() > 0.95


def test_a_codebook_replaced_after_registration_is_refused_and_one_replaced_during_it_is_not_copied(data, tmp_path):
    """The codebook beside a registered PLY is written from the codebook in memory, not copied from
    the --codebook file (replaced by a `pq train` while `register` ran, the copy did not decode the
    codes: exit 0, every score off), and the PLY records its CRC-32: a codebook replaced later (a
    registration into `a.PLY` beside `a.ply`, or one that failed after writing its codebook) is one
    error naming it, not wrong scores (a probe, 2026-11-30)."""
    from drsplat.lang import read_field
    from drsplat.scene import load_ply, save_ply

    x, w, _, _ = data
    source = tmp_path / "general.faiss"
    train_codebook(x, m=8, seed=0).save(source)
    book = load_codebook(source)
    field = build_field(x, w, book, clip_model="oracle")
    queries = x[np.linalg.norm(x, axis=1) > 0][:3]  # assigned rows: a zero query is refused
    want = field.scores(queries)
    train_codebook(x, m=8, seed=1).save(source)  # replaced while the registration runs
    ply = tmp_path / "a.ply"
    save_ply(attach_field(tiny_scene(len(x)), field, ply), ply)
    got = read_field(load_ply(ply), ply)
    np.testing.assert_allclose(got.scores(queries), want, atol=1e-6)
    codebook_path_for(ply).write_bytes(source.read_bytes())  # replaced after it
    with pytest.raises(InputError, match=r"a\.codebook\.faiss: is not the codebook a\.ply was registered with \(its CRC-32 is [0-9a-f]{8}"):
        read_field(load_ply(ply), ply)
    # round 85c F3: replaced by a codebook of another width, it was told only "codebook is pq d=32, but a.ply declares pq dim=..."
    train_codebook(np.random.default_rng(2).normal(size=(512, 32)).astype(np.float32), m=8, seed=0).save(codebook_path_for(ply))
    with pytest.raises(InputError, match=r"is not the codebook a\.ply was registered with .*it was replaced after that registration"):
        read_field(load_ply(ply), ply)


def test_backends_store_the_same_rows_with_the_callers_unit_check(books, data):
    """`build_field` hands its `unit_check` to the backend (one pass over the features, not two): the
    stored rows are those the backend makes checking the features itself, rows off unit length,
    zero and non-finite rows included."""
    from drsplat.lang.backends import ExactStorage, PQStorage
    from drsplat.lang.codebook import unit_check

    x = data[0][:300].copy()
    x[5:10] *= 3.0  # off unit length: normalised first
    x[10] = np.nan
    assigned = np.ones(len(x), bool)
    assigned[:5] = False
    ok, _ = unit_check(x)
    assigned &= ok  # what build_field hands on
    mine, given = ExactStorage.encode(x, assigned), ExactStorage.encode(x, assigned, checked=unit_check(x))
    np.testing.assert_array_equal(mine.features.view(np.uint16), given.features.view(np.uint16))
    mine, given = PQStorage.encode(x, assigned, books[16]), PQStorage.encode(x, assigned, books[16], checked=unit_check(x))
    np.testing.assert_array_equal(mine.codes, given.codes)
    np.testing.assert_array_equal(mine.norms, given.norms)
    assert (mine.norms[5:10] > 0).all() and mine.norms[10] == 0


def _with_comment(scene: GaussianScene, comment: str) -> GaussianScene:
    """The scene with its drsplat.lang comment replaced by `comment` (a hand-edited header)."""
    kept = [c for c in scene.comments if not c.startswith("drsplat.lang")]
    return GaussianScene(**{**scene.__dict__, "comments": kept + [comment]})


def test_header_dim_takes_ascii_digits_only_and_an_error_echoes_a_capped_value(tmp_path, data):
    """Was: dim=５１２ (full-width digits, percent-encoded) was read as 512, since int() takes any
    Unicode digit, and a 5,000-digit dim was echoed whole in the error."""
    x, w, _, dirs = data
    ply = tmp_path / "reg.ply"
    scene = attach_field(tiny_scene(len(x)), build_field(x, w, "none"), ply)
    comment = scene.comments[-1]
    assert " dim=64 " in comment
    np.testing.assert_array_equal(read_field(scene, ply).scores(dirs), build_field(x, w, "none").scores(dirs))
    with pytest.raises(InputError, match=r"reg\.ply: field 'comment drsplat\.lang': dim='６４' is not an integer \(ASCII digits\)"):
        read_field(_with_comment(scene, comment.replace("dim=64", "dim=%EF%BC%96%EF%BC%94")), ply)
    with pytest.raises(InputError) as caught:
        read_field(_with_comment(scene, comment.replace("dim=64", "dim=" + "9" * 5000)), ply)
    assert "(5,000 characters) is not a feature dimension" in str(caught.value) and len(str(caught.value)) < 300
    for bad in ("-64", "0", "+64", "6 4"):
        with pytest.raises(InputError, match="field 'comment drsplat.lang': dim="):
            read_field(_with_comment(scene, comment.replace("dim=64", f"dim={bad}".replace(" ", "%20"))), ply)


def test_header_codebook_crc_is_exactly_8_hex_digits(tmp_path, data, books):
    """Was: codebook_crc=-0x0 was taken as a CRC (int(x, 16) takes a sign, a 0x prefix, spaces and
    underscores) and reported as "the PLY records 00000000"."""
    import re

    x, w, _, dirs = data
    ply = tmp_path / "reg.ply"
    scene = attach_field(tiny_scene(len(x)), build_field(x, w, books[8]), ply)
    comment = scene.comments[-1]
    crc = re.search(r"codebook_crc=([0-9a-f]{8})", comment).group(1)
    upper = read_field(_with_comment(scene, comment.replace(crc, crc.upper())), ply)
    np.testing.assert_array_equal(upper.scores(dirs), read_field(scene, ply).scores(dirs))
    for bad in ("-0x0", "0x" + crc[2:], "%20" + crc[1:], crc[:4] + "_" + crc[5:], crc + "0", "0x0"):
        with pytest.raises(InputError, match=r"reg\.ply: field 'comment drsplat\.lang': codebook_crc='.*' is not a CRC-32 \(8 hex digits\)"):
            read_field(_with_comment(scene, comment.replace(f"codebook_crc={crc}", f"codebook_crc={bad}")), ply)


@pytest.mark.parametrize("clip_model, name, field", [("x\x1b[2J\nERROR: forged", "reg.ply", "clip"),
                                                     ("ViT-B-16/laion2b_s34b_b88k", "re\u202eg.ply", "codebook")])
def test_the_writer_refuses_header_text_its_reader_would_refuse(tmp_path, data, books, clip_model, name, field):
    """Was: a CLIP model id holding ESC or a newline (from a hand-edited manifest) or an output name
    holding U+202E went into the header comment, percent-escaped; every reader then refused the
    written PLY as altered. Now the writer refuses first, naming the field, and writes nothing."""
    x, w, _, _ = data
    ply = tmp_path / name
    field_obj = build_field(x, w, books[8], clip_model=clip_model)
    with pytest.raises(OutputError, match=rf"cannot write .*: field '{field}' of the 'drsplat\.lang' header comment: .* holds a "):
        attach_field(tiny_scene(len(x)), field_obj, ply)
    assert list(tmp_path.iterdir()) == []  # not even the codebook beside it


def test_an_ivfpq_codebook_without_residual_encoding_registers_a_readable_field(tmp_path, data):
    """Round 59a: an IndexIVFPQ with by_residual=False was accepted, but its Codebook counted 0 coarse lists, so the
    registered PLY's every list id was refused on reading ("outside 0..-1"). Its lists are the index's; the codes
    hold no coarse term, and the scores are decode-then-cosine."""
    import faiss

    x, w, _, dirs = data
    index = faiss.IndexIVFPQ(faiss.IndexFlatIP(x.shape[1]), x.shape[1], 4, 8, 8, faiss.METRIC_INNER_PRODUCT)
    index.by_residual = False
    index.train(np.ascontiguousarray(x[5:]))
    faiss.write_index(index, str(tmp_path / "nores.faiss"))
    book = load_codebook(tmp_path / "nores.faiss")
    assert book.kind == "ivfpq" and book.coarse is None and book.nlist == 4
    field = build_field(x, w, book, clip_model="oracle")
    ply = tmp_path / "reg.ply"
    back = read_field(attach_field(tiny_scene(len(x)), field, ply), ply)
    scores = back.scores(dirs)
    np.testing.assert_array_equal(scores, field.scores(dirs))
    recon = book.decode(back.storage.codes, back.storage.list_ids)
    np.testing.assert_array_equal(recon, index.pq.decode(np.ascontiguousarray(back.storage.codes)))  # no coarse term
    keep = w > 0
    expected = unit_rows(recon[keep].astype(np.float64)) @ unit_rows(dirs.astype(np.float64)).T
    np.testing.assert_allclose(scores[keep], expected, atol=1e-5)


def test_a_dangling_link_where_an_exports_codebook_goes_is_refused(tmp_path, data, books):
    """Round 59a: `query --out sel.ply --format drsplat` beside a dangling link sel.codebook.faiss -> /elsewhere/dir/x.faiss
    (a name the user never typed) wrote the codebook at the link's target and made its missing folders, exit 0. It is
    one error naming the link now, and nothing is written."""
    from drsplat.lang.plyformat import export_scene

    x, w, _, _ = data
    field = build_field(x, w, books[8])
    (tmp_path / "sel.codebook.faiss").symlink_to(tmp_path / "elsewhere" / "dir" / "x.faiss")
    with pytest.raises(OutputError, match=r"sel.codebook.faiss: is a link to .*x.faiss, which does not exist: the codebook sel.ply needs"):
        export_scene(tiny_scene(len(x)), field, tmp_path / "sel.ply", "drsplat")
    assert not (tmp_path / "elsewhere").exists() and not (tmp_path / "sel.ply").exists()


def test_an_export_over_a_write_protected_ply_leaves_its_codebook_alone(tmp_path, data, books):
    """Round 60a: an export onto a write-protected drsplat PLY was refused at the PLY's rename, after its codebook beside it
    had been replaced: the protected PLY then named a codebook it no longer matched (CRC refused). The PLY is checked
    before its codebook is written, in the library and in the viewer's export alike."""
    from drsplat.lang.plyformat import export_scene
    from drsplat.scene import load_ply

    x, w, _, _ = data
    ply = tmp_path / "sel.ply"
    export_scene(tiny_scene(len(x)), build_field(x, w, books[8]), ply, "drsplat")
    kept = {p.name: p.read_bytes() for p in (ply, codebook_path_for(ply))}
    ply.chmod(0o444)
    try:
        with pytest.raises(OutputError, match=r"sel.ply: exists and is write-protected \(mode 0444\)"):
            export_scene(tiny_scene(len(x)), build_field(x, w, books[16]), ply, "drsplat")
        assert {p.name: p.read_bytes() for p in (ply, codebook_path_for(ply))} == kept
    finally:
        ply.chmod(0o644)
    assert len(read_field(load_ply(ply), ply).scores(data[3])) == len(x)


def test_an_export_named_without_a_suffix_is_refused_unless_it_is_a_device(tmp_path):
    """Round 61a: an export to `sel` was written as a PLY that no drop or scene dialog opens (only `.txt` and such were
    refused); a name without a suffix is for a device or pipe (/dev/stdout) only."""
    from drsplat.lang.plyformat import export_problem

    for fmt in ("standard", "drsplat"):
        assert "name it sel.ply" in export_problem(tmp_path / "sel", fmt)
        assert export_problem(tmp_path / "sel.ply", fmt) is None
        assert export_problem(os.devnull, fmt) is None


def test_an_export_stopped_over_an_earlier_one_of_another_codebook_leaves_it_readable(data, books, tmp_path, monkeypatch):
    """Round 61b: `query --out sel.ply --format drsplat` over an earlier export of another codebook wrote the codebook
    first: stopped while the PLY was written (a Ctrl-C; a kill, the out-of-memory killer), the earlier sel.ply sat
    beside a codebook it no longer matched. The codebook is written last now, just before the PLY's rename; stopped
    before it, the earlier pair is untouched."""
    import drsplat.scene as sc
    from drsplat.lang.plyformat import export_scene
    from drsplat.scene import load_ply

    x, w, _, _ = data
    ply = tmp_path / "sel.ply"
    export_scene(tiny_scene(len(x)), build_field(x, w, books[8]), ply, "drsplat")
    kept = {p.name: p.read_bytes() for p in (ply, codebook_path_for(ply))}

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(sc, "ply_header", stopped)  # stopped while the PLY is made
    with pytest.raises(KeyboardInterrupt):
        export_scene(tiny_scene(len(x)), build_field(x, w, books[16]), ply, "drsplat")
    assert {p.name: p.read_bytes() for p in (ply, codebook_path_for(ply))} == kept
    monkeypatch.undo()
    import drsplat.utils as ut

    real = ut.replace_with_temp

    def ply_rename_fails(tmp, path):  # round 62a: the codebook put in place, then the PLY's rename refused (EPERM, EIO)
        if str(path).endswith(".ply"):
            raise PermissionError(1, "Operation not permitted", str(path))
        return real(tmp, path)

    monkeypatch.setattr(ut, "replace_with_temp", ply_rename_fails)
    with pytest.raises(PermissionError):
        export_scene(tiny_scene(len(x)), build_field(x, w, books[16]), ply, "drsplat")
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in (ply, codebook_path_for(ply))} == kept
    assert len(read_field(load_ply(ply), ply).scores(data[3])) == len(x)


@pytest.mark.parametrize("n", [1, 63, 64, 1000])
def test_unblocked_codes_undo_the_blocked_layout(n):
    """`unblocked_codes` (all rows, or some) is the inverse of `blocked_codes`, padding rows past N included."""
    from drsplat.lang.lut import unblocked_codes

    codes = np.random.default_rng(n).integers(0, 256, (n, 24)).astype(np.uint8)
    blocked = blocked_codes(codes)
    np.testing.assert_array_equal(unblocked_codes(blocked, n), codes)
    np.testing.assert_array_equal(blocked_codes(unblocked_codes(blocked, n)), blocked)
    rows = np.random.default_rng(1).integers(0, n, 50)
    np.testing.assert_array_equal(unblocked_codes(blocked, n, rows), codes[rows])


@pytest.mark.parametrize("n", [0, 1, 63, 64, 65, 1000])
@pytest.mark.parametrize("m", [1, 8, 128])
def test_codes_blocked_in_their_own_memory_are_blocked_codes(n, m):
    """`blocked_codes_in_place` (a realloc, each block transposed where it lies) against `blocked_codes` (a new array)."""
    from drsplat.lang.lut import blocked_codes_in_place

    codes = np.random.default_rng(n + m).integers(0, 256, (n, m), np.uint8)
    want = blocked_codes(codes)
    got = blocked_codes_in_place(codes)
    assert got.shape == want.shape and got.dtype == np.uint8
    np.testing.assert_array_equal(got, want)


def test_codes_scored_blocked_are_held_in_one_layout(monkeypatch):
    """Where the blocked kernels make every score (AVX-512, M ≥ 128), a field held its [N, M] codes and their blocked
    copy: M more bytes a Gaussian while queried (2.5 GB of a 20M query). Now the blocked layout replaces the codes in
    their own memory, and every way of reading them (all, some rows by ids, a slice or a mask, a subset, reconstructions, the PLY
    columns) gives what the codes gave."""
    import tracemalloc

    from drsplat.lang.backends import PQStorage

    x, _, _ = clip_like(600, 32, seed=3)
    field = build_field(x, np.ones(len(x), np.float32), train_codebook(x, m=8), clip_model="oracle-test")
    storage = field.storage
    want = storage.codes.copy()
    ids = np.array([5, 0, 599, 64, 5])
    mask = np.arange(len(x)) % 3 == 0
    before = {"rows": storage.code_rows(ids), "slice": storage.code_rows(slice(10, 200, 7)), "mask": storage.code_rows(mask),
              "take": storage.take(ids).codes, "recon": storage.reconstruct(ids), "columns": storage.columns()}
    monkeypatch.setattr(PQStorage, "blocked_scoring", lambda self, lut_bits=32: True)
    tracemalloc.start()  # before the codes are made: a block freed that was allocated untraced would not count
    try:
        big = PQStorage(np.random.default_rng(0).integers(0, 256, (200_000, 8), np.uint8), None, np.ones(200_000, np.float32),
                        storage.codebook)
        held = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        big.blocked_codes()
        grown = tracemalloc.get_traced_memory()[1] - held
    finally:
        tracemalloc.stop()
    assert grown < 200_000 * 8 // 10  # never both layouts, even for a moment (both: +1.6 MB)
    storage.blocked_codes()
    np.testing.assert_array_equal(storage.codes, want)
    np.testing.assert_array_equal(storage.code_rows(ids), before["rows"])
    np.testing.assert_array_equal(storage.code_rows(slice(10, 200, 7)), before["slice"])
    np.testing.assert_array_equal(storage.code_rows(mask), before["mask"])
    np.testing.assert_array_equal(storage.take(ids).codes, before["take"])
    np.testing.assert_array_equal(storage.reconstruct(ids), before["recon"])
    after = storage.columns()
    assert list(after) == list(before["columns"])
    for name, column in after.items():
        np.testing.assert_array_equal(column, before["columns"][name])
    assert not storage.norm_mismatches().any()
    shared = PQStorage(want.copy(), None, storage.norms, storage.codebook)
    view = shared.codes[:7]  # a view held elsewhere (a scene's columns): the codes are copied, never moved under it
    shared.blocked_codes()
    np.testing.assert_array_equal(view, want[:7])
    np.testing.assert_array_equal(shared.codes, want)



def test_rows_of_codes_held_blocked_are_indexed_as_numpy_indexes(monkeypatch):
    """Round 63c: with the codes held blocked only, a negative index read the last block's zero padding (`take([-1])`
    all zeros, its score 0.0047 against -0.0100) and an index past N up to the padding's end returned padding instead of
    an IndexError. Now every index reads the rows numpy would, or raises as numpy does."""
    from drsplat.lang.backends import PQStorage

    x, _, _ = clip_like(300, 32, seed=4)
    x = x[:130]  # 130 rows: the last block holds 2 rows and 62 of padding
    field = build_field(x, np.ones(len(x), np.float32), train_codebook(clip_like(300, 32, seed=4)[0], m=8), clip_model="oracle-test")
    storage = field.storage
    want = storage.codes.copy()
    monkeypatch.setattr(PQStorage, "blocked_scoring", lambda self, lut_bits=32: True)
    storage.blocked_codes()
    for index in ([-1], [-130, 129, 0], np.array([-2, 5]), slice(-3, None), slice(None, None, -7)):
        np.testing.assert_array_equal(storage.code_rows(index), want[index])
        np.testing.assert_array_equal(storage.take(index).codes, want[index])
    for index in ([130], [200], [-131], np.ones(129, bool)):
        with pytest.raises(IndexError):
            storage.code_rows(index)
        with pytest.raises(IndexError):
            want[index]


@pytest.mark.parametrize("kind", ["exact", "pq"])
def test_a_field_read_from_a_scene_is_its_own_unless_shared(tmp_path, kind):
    """Round 63c: a field read by `read_field` kept the scene's language columns' memory, so editing the scene's
    `lang_0` (or `lang_code_0`) changed the field's scores. Now it holds a copy unless the caller says it shares them
    (`shared=True`: the commands, which drop the scene's columns, and the viewer, which never edits them)."""
    from drsplat.scene import load_ply, save_ply

    x, _, _ = clip_like(300, 32, seed=6)
    field = build_field(x, np.ones(len(x), np.float32), "none" if kind == "exact" else train_codebook(x, m=8), clip_model="oracle-test")
    ply = tmp_path / "r.ply"
    save_ply(attach_field(tiny_scene(len(x)), field, ply), ply)
    scene = load_ply(ply)
    own, shared = read_field(scene, ply), read_field(scene, ply, shared=True)
    before = own.scores(x[:2])
    np.testing.assert_array_equal(shared.scores(x[:2]), before)
    column = scene.extra["lang_0" if kind == "exact" else "lang_code_0"]
    column[:] = column[::-1].copy()
    np.testing.assert_array_equal(own.scores(x[:2]), before)
    assert not np.array_equal(shared.scores(x[:2]), before)  # the shared one is the scene's memory, as documented
