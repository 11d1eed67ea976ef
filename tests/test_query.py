"""Query semantics (cosine, relevancy, segmentation, clicks, model ids) and the query/segment/pq CLIs."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from drsplat.cli import main
from drsplat.errors import DrsplatError, InputError
from drsplat.lang import attach_field, build_field, load_codebook, train_codebook
from drsplat.query import (
    check_clip_models,
    click_query,
    cosine,
    first_of_direction,
    first_of_direction_reference,
    load_gaussian_ids,
    load_query_embeddings,
    otsu_threshold,
    relevancy,
    relevancy_from_scores,
    relevancy_reference,
    segment,
    text_embeddings,
)
from drsplat.scene import SH_C0, load_ply, save_ply
from tests.test_index import clip_like, tiny_scene

DIM = 64
NAMES = [f"lbl{i}" for i in range(6)]


class FakeEncoder:
    """Text encoder whose phrase 'lbl<i>' embeds to label direction i (and anything else to a fixed vector)."""

    def __init__(self, dirs: np.ndarray, model_id: str = "oracle-test"):
        self.dirs = dirs
        self.model_id = model_id
        self.other = np.random.default_rng(9).normal(size=dirs.shape[1]).astype(np.float32)

    def encode_text(self, phrases):
        rows = [self.dirs[int(p[3:])] if p.startswith("lbl") else self.other for p in phrases]
        return np.stack(rows).astype(np.float32)


@pytest.fixture(scope="module")
def world():
    x, lab, dirs = clip_like(1200, DIM, labels=6, seed=4)
    w = np.ones(len(x), np.float32)
    w[:4] = 0
    x[:4] = 0
    return x, w, lab, dirs


@pytest.fixture(scope="module")
def fields(world):
    x, w, _, _ = world
    return {"exact": build_field(x, w, "none", clip_model="oracle-test"), "pq": build_field(x, w, train_codebook(x[4:], m=16), clip_model="oracle-test")}


def test_relevancy_matches_the_official_pairwise_softmax():
    rng = np.random.default_rng(0)
    pos = rng.uniform(-1, 1, size=(500, 3)).astype(np.float32)
    neg = rng.uniform(-1, 1, size=(500, 4)).astype(np.float32)
    neg[:50] = pos[:50, :1]  # ties: probability exactly 1/2
    pos[50:60] = 40.0  # saturated
    got = relevancy_from_scores(pos, neg)
    np.testing.assert_allclose(got, relevancy_reference(pos, neg), atol=1e-6)
    np.testing.assert_allclose(got[:50, 0], 0.5, atol=1e-6)
    assert np.all((got >= 0) & (got <= 1))


def test_relevancy_of_many_rows_is_the_same_bits_in_bounded_memory(monkeypatch):
    """Round 61b: relevancy of [N, K] scores made float64 temporaries of the whole [N, K] (5M Gaussians,
    K = 30: 6.5 GB against cosine's 3.0 GB). Now in row blocks, the same bits."""
    import tracemalloc

    import drsplat.query as dq

    rng = np.random.default_rng(3)
    pos = rng.uniform(-1, 1, size=(20_000, 30)).astype(np.float32)
    neg = rng.uniform(-1, 1, size=(20_000, 4)).astype(np.float32)
    whole = (0.5 * (1.0 + np.tanh(0.5 * (10.0 * (pos.astype(np.float64) - neg.max(axis=1, keepdims=True)))))).astype(np.float32)
    np.testing.assert_array_equal(dq.relevancy_from_scores(pos, neg), whole)
    monkeypatch.setattr(dq, "RELEVANCY_ROWS", 1000)
    tracemalloc.start()
    got = dq.relevancy_from_scores(pos, neg)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    np.testing.assert_array_equal(got, whole)
    assert peak < 2 * pos.nbytes, (peak, pos.nbytes)  # the float32 result and a block's temporaries, not 4x the result


@pytest.mark.parametrize("kind", ["exact", "pq"])
def test_relevancy_and_cosine_rank_the_queried_label_first(world, fields, kind):
    x, _, lab, dirs = world
    field = fields[kind]
    rel = relevancy(field, dirs[:2], dirs[2:])
    cos = cosine(field, dirs[:2])
    for k in range(2):
        hit = lab[4:] == k
        assert rel[4:][hit, k].min() > rel[4:][~hit, k].max() - 0.05
        negative = lab[4:] >= 2  # Gaussians of a negative's label
        assert np.mean(rel[4:][hit, k] > 0.5) > 0.95 and np.mean(rel[4:][negative, k] < 0.5) > 0.95
        assert cos[4:][hit, k].mean() > cos[4:][~hit, k].mean() + 0.2
    assert np.all(cos[:4] == 0)
    assert np.all(rel[:4] == 0)  # round 75c F2: ½ (cosine 0 against the query and every negative), as if half a match


def test_segmentation_argmax_background_and_unassigned(world, fields):
    _, _, lab, dirs = world
    seg = segment(fields["exact"], dirs)
    assert seg.labels.dtype == np.int32
    assert np.all(seg.labels[:4] == -1)
    assert np.mean(seg.labels[4:] == lab[4:]) > 0.99
    seg_bg = segment(fields["pq"], dirs[:5], background=dirs[5])
    assert np.mean(seg_bg.labels[4:][lab[4:] == 5] == -1) > 0.97
    assert np.mean(seg_bg.labels[4:][lab[4:] < 5] == lab[4:][lab[4:] < 5]) > 0.97
    high = segment(fields["exact"], dirs, min_score=2.0)
    assert np.all(high.labels == -1)


def test_rows_of_one_direction_are_found_as_every_pair_finds_them():
    """`first_of_direction` (sorted projections) against its reference (every pair): random rows, rows and their
    multiples, bit-equal copies, chains, pairs either side of SAME_DIRECTION, zero-free hard cases."""
    import drsplat.query as dq

    rng = np.random.default_rng(7)
    base = rng.normal(size=(40, 64)).astype(np.float32)
    rows = np.concatenate([base, 3.0 * base[:10], 1e-3 * base[5:15], base[:4], -base[20:24], 1e6 * base[30:32]]).astype(np.float32)
    side = base[0] / np.linalg.norm(base[0])
    bend = rng.normal(size=64)
    bend -= (bend @ side) * side
    bend /= np.linalg.norm(bend)
    for angle in (0.5 * np.sqrt(2 * dq.SAME_DIRECTION), 2.0 * np.sqrt(2 * dq.SAME_DIRECTION), 1e-3):  # 1 - cos = angle²/2: in, out, far out
        rows = np.concatenate([rows, (np.cos(angle) * side + np.sin(angle) * bend)[None].astype(np.float32)])
    rows = rows[rng.permutation(len(rows))]
    units = dq.query_rows(rows)
    got = first_of_direction(units)
    np.testing.assert_array_equal(got, first_of_direction_reference(units))
    assert len(np.unique(got)) < len(rows) - 20 and (got <= np.arange(len(rows))).all()
    # round 86a F2: labels a few degrees apart are never joined through a chain of labels between them
    chain = np.stack([np.cos(t) * side + np.sin(t) * bend for t in np.linspace(0.0, 0.05, 2000)]).astype(np.float32)
    assert len(np.unique(first_of_direction(dq.query_rows(chain)))) > 1900
    for q in (0, 1):
        np.testing.assert_array_equal(first_of_direction(units[:q]), np.arange(q))


@pytest.mark.parametrize("kind", ["exact", "pq"])
def test_a_label_and_its_multiple_are_one_label(world, fields, kind):
    """Round 85c F1: labels and the same labels times 3 (or a background row twice a label's) split the Gaussians
    between the two by float32 rounding, the copies winning most: the first of rows of one direction wins, as of equal
    rows."""
    _, _, _, dirs = world
    field = fields[kind]
    base = segment(field, dirs)
    for c in (3.0, 0.1, 7.3):
        np.testing.assert_array_equal(segment(field, np.concatenate([dirs, c * dirs]).astype(np.float32)).labels, base.labels)
    np.testing.assert_array_equal(segment(field, dirs, background=2.0 * dirs[0]).labels, base.labels)


def test_rows_of_another_width_than_the_fields_are_named(fields):
    """Round 85c F2: a 768-D negative, background or query against a 512-D field met the others in numpy's concatenate,
    whose error named neither."""
    field = fields["exact"]
    good, wide = np.ones((1, field.dim), np.float32), np.ones((2, field.dim + 3), np.float32)
    for call, what in ((lambda: relevancy(field, good, wide), "negative"), (lambda: relevancy(field, wide, good), "query"),
                       (lambda: segment(field, good, background=wide), "background embedding"), (lambda: segment(field, wide), "label embedding")):
        with pytest.raises(DrsplatError, match=f"the {what} rows are {field.dim + 3}-D, but this field holds {field.dim}-D features"):
            call()


@pytest.mark.parametrize("kind", ["exact", "pq"])
def test_segment_scores_a_few_labels_at_a_time_to_the_same_labels(world, fields, monkeypatch, kind):
    """Round 61b: segment held the whole [N, L] scores (200 labels on 5M Gaussians: 6.4 GB, 10M killed at 10 GB).
    Now a few labels a pass, with np.argmax's answer: repeated labels (exact ties) go to the first, as before."""
    import tracemalloc

    import drsplat.query as dq

    _, _, _, dirs = world
    labels = np.concatenate([dirs, dirs[::-1], dirs[:3]] * 4)  # every score tied with another label's
    field = fields[kind]
    whole = dq.segment(field, labels[:-2], background=labels[-2:], min_score=0.1)
    monkeypatch.setattr(dq, "SEGMENT_SCORE_BYTES", 0)
    monkeypatch.setattr(dq, "SEGMENT_MIN_LABELS", 1)
    tracemalloc.start()
    parts = dq.segment(field, labels[:-2], background=labels[-2:], min_score=0.1)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    np.testing.assert_array_equal(parts.labels, whole.labels)
    np.testing.assert_array_equal(parts.scores, whole.scores)
    assert set(np.unique(whole.labels)) <= set(range(len(dirs))) | {-1}  # the first of tied labels
    assert peak < 4 * len(field) * len(labels), (peak, 4 * len(field) * len(labels))  # not the [N, L] float32 scores


def test_segment_passes_count_each_labels_tables_on_a_small_scene(fields, monkeypatch):
    """Round 62a: the labels a pass were counted by their scores alone, so a small scene took every label in one pass,
    whose look-up tables (~128 kB a label) were the memory: 1,001 Gaussians and 20k labels, 3.1 GB."""
    import drsplat.query as dq

    field = fields["pq"]
    sizes = []
    real = type(field).scores

    def counted(self, queries, **kwargs):
        sizes.append(len(queries))
        return real(self, queries, **kwargs)

    monkeypatch.setattr(type(field), "scores", counted)
    labels = np.random.default_rng(0).normal(size=(5000, field.dim)).astype(np.float32)
    dq.segment(field, labels)
    assert sum(sizes) == 5000
    assert max(sizes) * (4 * len(field) + dq.SEGMENT_TABLE_BYTES) <= dq.SEGMENT_SCORE_BYTES + 4 * len(field) + dq.SEGMENT_TABLE_BYTES


def test_click_query_is_the_mean_feature(world, fields):
    x, _, lab, _ = world
    ids = np.flatnonzero(lab == 3)[:5]
    q = click_query(fields["exact"], np.concatenate([ids, [0, 1]]))  # unassigned ids are ignored
    mean = x[ids].mean(0)
    np.testing.assert_allclose(q, mean / np.linalg.norm(mean), atol=2e-3)
    top = np.argsort(-cosine(fields["pq"], click_query(fields["pq"], ids))[:, 0])[:50]
    assert np.all(lab[top] == 3)
    with pytest.raises(DrsplatError, match="unassigned"):
        click_query(fields["exact"], np.array([0, 1]))



def test_click_query_reads_its_ids_as_a_set(world, fields):
    """One set of Gaussians, one query: repeated ids count once and the order does not matter, the
    same bits as its boolean mask (round 50: repeating 5 of 50 ids moved the cosines by 0.0074)."""
    _, _, lab, _ = world
    ids = np.flatnonzero(lab == 3)[:50]
    mask = np.zeros(lab.shape[0], bool)
    mask[ids] = True
    for name in ("exact", "pq"):
        want = click_query(fields[name], np.flatnonzero(mask))
        for given in (ids[::-1], np.concatenate([ids, ids[:5]]), np.repeat(ids, 3)[::-1], mask):  # round 61d: the mask raised IndexError
            np.testing.assert_array_equal(click_query(fields[name], given), want, err_msg=name)
    with pytest.raises(DrsplatError, match="one entry per Gaussian"):
        click_query(fields["exact"], mask[:-1])
    # round 85c F4: -1 read the last Gaussian (so [-1, N-1] counted it twice), N and float ids raised numpy's IndexError
    n = len(fields["exact"])
    for bad, message in (([-1, n - 1], "1 Gaussian ids fall outside 0..1199 (e.g. -1)"), ([n], "fall outside"),
                         (np.array([1.0, 2.0]), "must be integers"), (np.array([], np.int64), "no Gaussian ids given")):
        with pytest.raises(DrsplatError, match=re.escape(message)):
            click_query(fields["exact"], bad)

def test_a_click_query_of_many_gaussians_is_the_same_bits_in_bounded_memory(fields, monkeypatch):
    """Round 61b: a click query reconstructed every selected Gaussian at once, with float64 copies: ~15 kB an id
    (500k ids of a 1M field: 8.4 GB; 1M of 5M killed at 10 GB). Now in chunks, the same bits as the mean
    of all rows at once (numpy's float32 sum down axis 0, a running total taken first)."""
    import tracemalloc

    import drsplat.query as dq
    from drsplat.lang.codebook import unit_rows

    for name in ("exact", "pq"):
        field = fields[name]
        ids = np.flatnonzero(field.assigned())
        rows = unit_rows(field.reconstruct(ids))
        want = unit_rows(rows[np.linalg.norm(rows, axis=1) > 0].mean(axis=0))[0]  # all at once, as before
        np.testing.assert_array_equal(dq.click_query(field, ids), want, err_msg=name)
        monkeypatch.setattr(dq, "CLICK_CHUNK", 7)
        np.testing.assert_array_equal(dq.click_query(field, ids), want, err_msg=name)
        tracemalloc.start()
        dq.click_query(field, ids)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        whole = ids.size * field.dim * 8  # one float64 copy of every selected row
        assert peak < whole / 4, (name, peak, whole)
        monkeypatch.undo()


def test_click_query_on_features_that_cancel_is_one_error_not_a_zero_query():
    """Two selected Gaussians of opposite features have a mean of no direction; the field refuses a
    zero query (round 38), so the click says why in the words a user reads."""
    from drsplat.lang import build_field

    f = np.zeros((3, 8), np.float32)
    f[0, 0], f[1, 0], f[2, 1] = 1.0, -1.0, 1.0
    field = build_field(f, np.ones(3), "none", clip_model="oracle")
    with pytest.raises(DrsplatError, match="the features of the 2 selected Gaussians cancel out"):
        click_query(field, np.array([0, 1]))
    np.testing.assert_array_equal(click_query(field, np.array([0, 2])), np.array([1, 1, 0, 0, 0, 0, 0, 0], np.float32) / np.float32(np.sqrt(2)))


def test_clip_model_mismatch_is_refused(world, fields):
    check_clip_models("ViT-B-16/laion2b_s34b_b88k", "ViT-B-16/laion2b_s34b_b88k")
    check_clip_models("unknown", "ViT-B-16/laion2b_s34b_b88k")
    with pytest.raises(DrsplatError, match="CLIP model mismatch.*ViT-L-14"):
        check_clip_models("ViT-B-16/laion2b_s34b_b88k", "ViT-L-14/openai")
    with pytest.raises(DrsplatError, match="mismatch"):
        check_clip_models("oracle", "ViT-B-16/laion2b_s34b_b88k")
    with pytest.raises(DrsplatError, match="mismatch"):
        text_embeddings(FakeEncoder(world[3], "ViT-B-32/openai"), ["lbl1"], fields["exact"])
    # round 87c F4: an encoder of a given checkpoint is labelled with the field's tag; the message names the file given
    labelled = FakeEncoder(world[3], "ViT-B-32/file:theirs.pt")
    labelled.checkpoint = "/somewhere/mine.pt"
    with pytest.raises(DrsplatError, match=r"the text encoder \(--clip-checkpoint mine.pt\) is ViT-B-32/file:theirs.pt"):
        text_embeddings(labelled, ["lbl1"], fields["exact"])
    emb = text_embeddings(FakeEncoder(world[3]), ["lbl1", "lbl2"], fields["exact"])
    np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1, atol=1e-6)


def test_otsu_threshold_splits_two_modes():
    rng = np.random.default_rng(0)
    s = np.concatenate([rng.normal(0.2, 0.03, 5000), rng.normal(0.7, 0.03, 300)])
    t = otsu_threshold(s)
    assert t == s[5000:].min()  # the lowest score of the upper mode: a value the scores hold
    assert np.sum(s >= t) == 300


def test_otsu_splits_scores_one_ulp_apart():
    """Two groups of float32 scores one ulp apart: the threshold selects the upper one in float32
    (a float64 bin edge between them rounded onto the lower score, selecting both); float64 scores
    one ulp apart made np.histogram refuse (a numerical probe, 2026-11-30)."""
    from drsplat.query import select

    low = np.float32(0.2)
    high = np.nextafter(low, np.float32(1))
    s = np.r_[np.full(900, low), np.full(100, high)].astype(np.float32)
    assert select(s, otsu_threshold(s)).sum() == 100
    d = np.array([0.2, 0.2, np.nextafter(0.2, 1.0)])
    assert otsu_threshold(d) == d[2] and select(d, otsu_threshold(d)).sum() == 1


@pytest.mark.parametrize("scores", [[0.42], [0.42] * 5, [0.42, 0.0, np.nan, 0.42]], ids=["one", "all-equal", "equal-among-unscored"])
def test_auto_threshold_on_scores_of_one_value_says_it_selects_them_all(scores, caplog):
    """A field with one assigned Gaussian (or Gaussians of one score) gave Otsu nothing to split: all
    were selected with only an INFO line; now a warning says so and how to choose."""
    import logging

    from drsplat.commands.common import resolve_threshold

    with caplog.at_level(logging.INFO, logger="drsplat.commands.common"):
        threshold = resolve_threshold("auto", np.array(scores), relevancy=False)
    assert threshold == pytest.approx(0.42)
    (record,) = caplog.records
    assert record.levelno == logging.WARNING and "nothing to split; all of them are selected" in record.getMessage()
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="drsplat.commands.common"):
        resolve_threshold("auto", np.array([0.2, 0.21, 0.7, 0.71]), relevancy=False)
    assert [r.levelno for r in caplog.records] == [logging.INFO]


def test_embedding_and_id_files_are_validated(tmp_path):
    np.save(tmp_path / "q.npy", np.ones(DIM + 1, np.float32))
    with pytest.raises(InputError, match=r"q.npy.*expected shape \(64,\)"):
        load_query_embeddings(tmp_path / "q.npy", DIM)
    bad = np.ones((2, DIM), np.float32)
    bad[1, 0] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    with pytest.raises(InputError, match=r"rows \[1\]"):
        load_query_embeddings(tmp_path / "nan.npy", DIM)
    np.save(tmp_path / "ids.npy", np.array([1, 99]))
    with pytest.raises(InputError, match="outside 0..9"):
        load_gaussian_ids(tmp_path / "ids.npy", 10)
    np.save(tmp_path / "mask.npy", np.arange(10) > 6)
    assert load_gaussian_ids(tmp_path / "mask.npy", 10).tolist() == [7, 8, 9]
    with pytest.raises(InputError, match="file not found"):
        load_query_embeddings(tmp_path / "missing.npy", DIM)


def test_query_rows_of_subnormal_norm_are_refused_and_a_smallest_normal_one_is_read(tmp_path):
    """Round 46: a query row scaled to float32 subnormals (entries of 1.4e-45 .. 3e-45) was normalised and scored without a
    word, though its few bits kept cosine ~0.9 to the direction it was saved from; now refused by name, as the feature
    reader ignores such mask embeddings; a float64 row of 1e-300 was called "zero or non-finite", which its file does not
    hold. A row just above float32's smallest normal reads as its direction."""
    rows = np.random.default_rng(3).normal(size=(3, DIM))
    rows /= np.abs(rows).max(axis=1, keepdims=True)
    tiny = rows.copy()
    tiny[1] *= 3e-45
    np.save(tmp_path / "tiny.npy", tiny.astype(np.float32))
    with pytest.raises(InputError, match=r"tiny\.npy: rows \[1\] have a norm of .* below float32's smallest normal number"):
        load_query_embeddings(tmp_path / "tiny.npy", DIM)
    np.save(tmp_path / "under.npy", rows * np.r_[1.0, 1e-300, 1.0][:, None])  # float64 rows that the float32 cast makes zero rows
    with pytest.raises(InputError, match=r"under\.npy: rows \[1\] have a norm of .* below float32's smallest normal number"):
        load_query_embeddings(tmp_path / "under.npy", DIM)
    small = rows.copy()
    small[1] *= 1e-37
    np.save(tmp_path / "small.npy", small.astype(np.float32))
    np.testing.assert_allclose(load_query_embeddings(tmp_path / "small.npy", DIM)[1], rows[1] / np.linalg.norm(rows[1]), atol=1e-5)


# ---------------------------------------------------------------------------------------------
# CLI


@pytest.fixture(scope="module")
def registered(tmp_path_factory, world, fields):
    out = {}
    root = tmp_path_factory.mktemp("reg")
    for kind, field in fields.items():
        ply = root / f"{kind}.ply"
        save_ply(attach_field(tiny_scene(len(field)), field, ply), ply)
        out[kind] = ply
    return out


def test_an_embedding_file_of_no_rows_says_so(tmp_path):
    """Round 61b: a (0, 512) query file was refused as "expected shape (512,) or (K, 512), got (0, 512)": a shape it has."""
    from drsplat.errors import InputError
    from drsplat.query import load_query_embeddings

    np.save(tmp_path / "q0.npy", np.zeros((0, 16), np.float32))
    with pytest.raises(InputError, match=r"holds no query rows \(shape \(0, 16\)\)"):
        load_query_embeddings(tmp_path / "q0.npy", 16)


def test_an_empty_negative_or_label_file_and_a_string_array_are_named_for_what_they_are(tmp_path, registered, fields, capsys):
    """Round 98c F3: an empty --negative-embeddings or segment --embeddings file was refused as holding "no query rows";
    a string array of the wrong length as of the wrong shape, not as no numbers at all."""
    kind = next(iter(registered))
    ply, dim = registered[kind], fields[kind].dim
    np.save(tmp_path / "empty.npy", np.zeros((0, dim), np.float32))
    np.save(tmp_path / "q.npy", np.ones(dim, np.float32))
    np.save(tmp_path / "words.npy", np.array(["a red apple"] * 3))
    runs = {
        "negative": ["query", str(ply), "--embedding", str(tmp_path / "q.npy"), "--relevancy", "--negative-embeddings", str(tmp_path / "empty.npy")],
        "label": ["segment", str(ply), "--embeddings", str(tmp_path / "empty.npy"), "--out", str(tmp_path / "l.npy")],
    }
    for rows, command in runs.items():
        assert main(command) == 1
        assert f"empty.npy: holds no {rows} rows (shape (0, {dim}))" in capsys.readouterr().err
    assert main(["query", str(ply), "--embedding", str(tmp_path / "words.npy")]) == 1
    assert "words.npy: expected a float array, got dtype <U11" in capsys.readouterr().err


def test_top_ids_are_the_full_stable_sorts_first_rows():
    """Round 61b: `query --top` sorted all N scores (3 s of a 10M query); now only those at least the top-th, the same ids."""
    from drsplat.commands.query import top_ids

    rng = np.random.default_rng(5)
    best = rng.integers(0, 20, 5000).astype(np.float32) / 7  # many exact ties
    ids = np.flatnonzero(rng.uniform(size=5000) < 0.8)
    for top in (0, 1, 3, 10, 57, len(ids) - 1, len(ids), len(ids) + 5):
        want = ids[np.argsort(-best[ids], kind="stable")[:top]]
        np.testing.assert_array_equal(top_ids(best, ids, top), want)


@pytest.mark.parametrize("kind", ["exact", "pq"])
def test_a_registered_scene_is_held_once_for_queries(registered, fields, kind):
    """Round 61b: query, segment and eval held the language columns twice (the scene's PLY columns and the field
    built from them), 130 B a Gaussian more for PQ, 1 kB for exact float16. The commands' scene has none of them."""
    from drsplat.commands.common import load_registered

    scene, field = load_registered(registered[kind])
    assert not [name for name in scene.extra if name.startswith("lang_")]
    assert not [c for c in scene.comments if c.startswith("drsplat.lang")]
    np.testing.assert_array_equal(field.scores(np.eye(field.dim, dtype=np.float32)[:2]),
                                  fields[kind].scores(np.eye(field.dim, dtype=np.float32)[:2]))


@pytest.mark.parametrize("kind", ["exact", "pq"])
def test_query_cli_embedding_scores_and_selection(tmp_path, registered, fields, world, kind):
    _, _, lab, dirs = world
    np.save(tmp_path / "q1.npy", dirs[2])
    np.save(tmp_path / "qk.npy", dirs[:3])
    assert main(["query", str(registered[kind]), "--embedding", str(tmp_path / "q1.npy"), "--scores", str(tmp_path / "s1.npy"), "--threshold", "0.45", "--out", str(tmp_path / "sel.ply")]) == 0
    s1 = np.load(tmp_path / "s1.npy")
    assert s1.shape == (len(lab),) and s1.dtype == np.float32
    np.testing.assert_allclose(s1, fields[kind].scores(dirs[2:3])[:, 0], atol=1e-6)
    sel = load_ply(tmp_path / "sel.ply")
    assert sel.num_gaussians == int(np.sum(s1 >= 0.45)) > 0
    assert not any(k.startswith("lang") for k in sel.extra) and not any("drsplat.lang" in c for c in sel.comments)
    assert main(["query", str(registered[kind]), "--embedding", str(tmp_path / "qk.npy"), "--scores", str(tmp_path / "sk.npy")]) == 0
    assert np.load(tmp_path / "sk.npy").shape == (len(lab), 3)


def test_query_cli_click_text_and_relevancy(tmp_path, registered, world, monkeypatch, capsys):
    from drsplat.commands import common as common_cmd

    _, _, lab, dirs = world
    monkeypatch.setattr(common_cmd, "load_encoder", lambda args, field, **_: FakeEncoder(dirs))
    ids = np.flatnonzero(lab == 4)[:3]
    np.save(tmp_path / "ids.npy", ids)
    assert main(["query", str(registered["pq"]), "--gaussians", str(tmp_path / "ids.npy"), "--scores", str(tmp_path / "c.npy")]) == 0
    c = np.load(tmp_path / "c.npy")
    assert c.shape == (len(lab),) and np.all(lab[np.argsort(-c)[:50]] == 4)
    assert main(["query", str(registered["exact"]), "--text", "lbl1", "--relevancy", "--negatives", "lbl2", "--scores", str(tmp_path / "r.npy")]) == 0
    r = np.load(tmp_path / "r.npy")
    assert r.shape == (len(lab),) and np.mean(r[lab == 1] > 0.5) > 0.95 and np.mean(r[lab == 2] < 0.5) > 0.95
    assert main(["query", str(registered["exact"]), "--text", "lbl0", "--top", "3"]) == 0
    printed = capsys.readouterr().out.split("\n")
    top_ids = [int(line.split()[0]) for line in printed[1:4]]
    assert all(lab[i] == 0 for i in top_ids)


def test_query_cli_errors(tmp_path, registered, capsys):
    plain = tmp_path / "plain.ply"
    save_ply(tiny_scene(5), plain)
    np.save(tmp_path / "q.npy", np.ones(DIM, np.float32))
    assert main(["query", str(plain), "--embedding", str(tmp_path / "q.npy")]) == 1
    assert "no language field" in capsys.readouterr().err
    np.save(tmp_path / "bad.npy", np.ones(7, np.float32))
    assert main(["query", str(registered["exact"]), "--embedding", str(tmp_path / "bad.npy")]) == 1
    assert "bad.npy" in capsys.readouterr().err
    # oracle features cannot be queried by text; clear message instead of a CLIP error
    field = build_field(np.eye(4, DIM, dtype=np.float32), np.ones(4, np.float32), "none", clip_model="oracle")
    oracle = tmp_path / "oracle.ply"
    save_ply(attach_field(tiny_scene(4), field, oracle), oracle)
    assert main(["query", str(oracle), "--text", "chair"]) == 1
    assert "pass --embedding (" in capsys.readouterr().err
    assert main(["segment", str(oracle), "--labels", "chair,table", "--out", str(tmp_path / "s.npy")]) == 1
    assert "pass --embeddings (" in capsys.readouterr().err  # segment's flag, not query's
    assert main(["query", str(registered["exact"]), "--embedding", str(tmp_path / "q.npy"), "--relevancy"]) == 1
    capsys.readouterr()
    # relevancy on oracle features needs negatives no text encoder can give: the flag that does (it said "use --embedding")
    assert main(["query", str(oracle), "--embedding", str(tmp_path / "q.npy"), "--relevancy"]) == 1
    err = capsys.readouterr().err
    assert "--negative-embeddings N.npy" in err and "instead of text" not in err, err
    np.save(tmp_path / "neg.npy", np.eye(2, DIM, dtype=np.float32)[::-1].copy())
    assert main(["query", str(oracle), "--embedding", str(tmp_path / "q.npy"), "--relevancy", "--negative-embeddings",
                 str(tmp_path / "neg.npy"), "--scores", str(tmp_path / "rel.npy")]) == 0
    assert np.load(tmp_path / "rel.npy").shape == (4,)


def test_segment_cli_labels_and_coloured_ply(tmp_path, registered, world, monkeypatch, capsys):
    from drsplat.commands import common as common_cmd

    _, _, lab, dirs = world
    np.save(tmp_path / "L.npy", dirs)
    assert main(["segment", str(registered["exact"]), "--embeddings", str(tmp_path / "L.npy"), "--out", str(tmp_path / "lab.npy"), "--ply", str(tmp_path / "col.ply")]) == 0
    got = np.load(tmp_path / "lab.npy")
    assert got.dtype == np.int32 and got.shape == (len(lab),)
    assert np.all(got[:4] == -1) and np.mean(got[4:] == lab[4:]) > 0.99
    col = load_ply(tmp_path / "col.ply")
    rgb = 0.5 + SH_C0 * col.sh[:, 0]
    same = got == got[10]
    np.testing.assert_allclose(rgb[same], np.broadcast_to(rgb[10], rgb[same].shape), atol=1e-5)
    assert not np.allclose(rgb[got == 0][0], rgb[got == 1][0])
    # round 60a: a write-protected --ply was refused after LABELS.npy was written, which then went with it: the earlier
    # labels file was lost, nothing left. Refused before any work now, both files kept
    before = (tmp_path / "lab.npy").read_bytes()
    (tmp_path / "col.ply").chmod(0o444)
    try:
        assert main(["segment", str(registered["exact"]), "--embeddings", str(tmp_path / "L.npy"), "--out", str(tmp_path / "lab.npy"),
                     "--ply", str(tmp_path / "col.ply")]) == 1
    finally:
        (tmp_path / "col.ply").chmod(0o644)
    assert "col.ply: exists and is write-protected" in capsys.readouterr().err
    assert (tmp_path / "lab.npy").read_bytes() == before
    monkeypatch.setattr(common_cmd, "load_encoder", lambda args, field, **_: FakeEncoder(dirs))
    assert main(["segment", str(registered["pq"]), "--labels", "lbl0,lbl1,lbl2,lbl3", "--out", str(tmp_path / "t.npy")]) == 0
    t = np.load(tmp_path / "t.npy")
    assert np.mean(t[4:][lab[4:] < 4] == lab[4:][lab[4:] < 4]) > 0.97
    assert "lbl3" in capsys.readouterr().out
    # round 57c: "background" typed in --labels beside --background became an ordinary label, its Gaussians k, not -1
    assert main(["segment", str(registered["pq"]), "--labels", "lbl0,Background", "--background", "--out", str(tmp_path / "b.npy")]) == 2
    assert "--labels: entry 2 is 'background', which --background adds as the background (label -1)" in capsys.readouterr().err
    assert not (tmp_path / "b.npy").exists()


def test_pq_train_cli(tmp_path, world, capsys):
    x = world[0][4:]
    np.save(tmp_path / "a.npy", x[:700])
    feats = tmp_path / "feats"
    feats.mkdir()
    np.save(feats / "img0_f.npy", x[700:])
    np.save(feats / "img0_s.npy", np.zeros((1, 4, 4), np.int32))
    out = tmp_path / "general.codebook.faiss"
    assert main(["pq", "train", "--embeddings", str(tmp_path / "a.npy"), "--features", str(feats), "--out", str(out), "--m", "16"]) == 0
    book = load_codebook(out)
    assert book.kind == "pq" and book.m == 16 and book.dim == DIM
    assert main(["pq", "train", "--embeddings", str(tmp_path / "a.npy"), "--out", str(out), "--m", "7"]) == 2  # a usage error (round 5)
    assert "does not divide" in capsys.readouterr().err
    assert main(["pq", "info", str(out)]) == 0
    assert "M=16" in capsys.readouterr().out


def test_relevancy_with_the_real_canonical_negatives_and_official_codebook(tmp_path):
    """text_negative.npy (4, 512) float16 as --negative-embeddings on an official-IVFPQ registered PLY."""
    from tests.conftest import shared_path

    negatives_path = shared_path("drsplat", "text_negative.npy")
    official = load_codebook(shared_path("drsplat", "pq_index.faiss"))
    negatives = np.load(negatives_path)
    assert negatives.shape == (4, 512) and negatives.dtype == np.float16
    x, lab, dirs = clip_like(800, 512, labels=5, seed=11)
    field = build_field(x, np.ones(len(x), np.float32), official, clip_model="ViT-B-16/laion2b_s34b_b88k")
    ply = tmp_path / "official.ply"
    save_ply(attach_field(tiny_scene(len(x)), field, ply), ply)
    np.save(tmp_path / "q.npy", dirs[1])
    assert main(["query", str(ply), "--embedding", str(tmp_path / "q.npy"), "--relevancy", "--negative-embeddings", str(negatives_path), "--scores", str(tmp_path / "r.npy")]) == 0
    got = np.load(tmp_path / "r.npy")
    neg = negatives.astype(np.float32)
    neg /= np.linalg.norm(neg, axis=1, keepdims=True)
    decoded = field.scores_reference(np.concatenate([dirs[1:2], neg]))
    np.testing.assert_allclose(got, relevancy_reference(decoded[:, :1], decoded[:, 1:])[:, 0], atol=1e-5)


def test_cli_eight_bit_tables_match_exact_tables_closely(tmp_path, registered, world):
    """--lut-bits 8 is the opt-in fast path: same selection as exact tables up to the documented bound."""
    _, _, lab, dirs = world
    np.save(tmp_path / "q.npy", dirs[:2])
    outs = {}
    for bits in ("32", "8"):
        assert main(["query", str(registered["pq"]), "--embedding", str(tmp_path / "q.npy"), "--lut-bits", bits, "--scores", str(tmp_path / f"s{bits}.npy")]) == 0
        outs[bits] = np.load(tmp_path / f"s{bits}.npy")
    assert outs["8"].shape == outs["32"].shape == (len(lab), 2)
    assert 0 < np.abs(outs["8"] - outs["32"]).max() < 0.02
    assert main(["segment", str(registered["pq"]), "--embeddings", str(tmp_path / "q.npy"), "--lut-bits", "8", "--out", str(tmp_path / "l8.npy")]) == 0
    assert main(["segment", str(registered["pq"]), "--embeddings", str(tmp_path / "q.npy"), "--out", str(tmp_path / "l32.npy")]) == 0
    assert np.mean(np.load(tmp_path / "l8.npy") == np.load(tmp_path / "l32.npy")) > 0.99


def test_exact_norms_are_computed_only_when_scored(tmp_path):
    """Writing an exact field needs no norms (the registered PLY never stores them): the encoded
    storage computes them on first use, equal to the row norms of its float16 rows, and the field
    read back from the file scores as the one in memory."""
    from drsplat.lang.backends import ExactStorage, chunked_row_norms
    from drsplat.lang.field import LanguageField
    from drsplat.lang.plyformat import attach_field, read_field
    from drsplat.scene import GaussianScene, load_ply, save_ply

    rng = np.random.default_rng(0)
    n, dim = 40, 16
    feats = rng.normal(size=(n, dim)).astype(np.float32)
    assigned = rng.random(n) > 0.2
    storage = ExactStorage.encode(feats, assigned)
    assert storage.known_norms is None
    scene = GaussianScene(means=rng.normal(size=(n, 3)).astype(np.float32), quats=np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32),
                          log_scales=np.full((n, 3), -3, np.float32), opacity_logits=np.zeros(n, np.float32), sh=np.zeros((n, 1, 3), np.float32))
    field = LanguageField(dim, "test/model", assigned.astype(np.float32), storage)
    path = tmp_path / "exact.ply"
    save_ply(attach_field(scene, field, path), path)
    assert storage.known_norms is None  # written without them
    np.testing.assert_array_equal(storage.norms, chunked_row_norms(storage.features))
    assert (storage.norms[~assigned] == 0).all() and (storage.norms[assigned] > 0).all()
    q = rng.normal(size=(2, dim)).astype(np.float32)
    np.testing.assert_array_equal(read_field(load_ply(path), path).scores(q), field.scores(q))
    half = storage.take(np.arange(0, n, 2))
    np.testing.assert_array_equal(half.norms, storage.norms[::2])


def test_query_functions_refuse_rows_with_no_direction():
    """A NaN or all-zero query, negative, label or text embedding was made a zero row: cosine gave
    0 everywhere (as for unassigned Gaussians), relevancy plausible values, segment gave the NaN
    label wherever the others scored below 0 (a numerical probe, 2026-11-30). Now one error naming
    the row."""
    from drsplat.lang import unit_rows
    from drsplat.query import cosine, relevancy, segment, text_embeddings

    rng = np.random.default_rng(5)
    feats = unit_rows(rng.normal(size=(6, 8)))
    field = build_field(feats, np.ones(6, np.float32))
    nan, zero = np.full(8, np.nan, np.float32), np.zeros(8, np.float32)
    with pytest.raises(DrsplatError, match="query 0 holds non-finite values"):
        cosine(field, nan)
    with pytest.raises(DrsplatError, match="query 1 is all zeros"):
        cosine(field, np.vstack([feats[0], zero]))
    with pytest.raises(DrsplatError, match="query 0 holds non-finite"):
        relevancy(field, nan, feats[1:2])
    with pytest.raises(DrsplatError, match="negative 1 holds non-finite"):
        relevancy(field, feats[0], np.vstack([feats[1], nan]))
    with pytest.raises(DrsplatError, match="label embedding 1 holds non-finite"):
        segment(field, np.vstack([feats[0], nan]))
    with pytest.raises(DrsplatError, match="background embedding 0 is all zeros"):
        segment(field, feats[:2], background=zero)

    class Encoder:
        model_id = "unknown"

        def encode_text(self, phrases):
            return np.vstack([feats[0], nan])

    with pytest.raises(DrsplatError, match="the text encoder's embedding of phrase 1 holds non-finite"):
        text_embeddings(Encoder(), ["chair", "table"], field)
    # finite rows of any scale are still directions
    np.testing.assert_allclose(cosine(field, 1e30 * feats[0]), cosine(field, feats[0]), atol=1e-6)


@pytest.mark.parametrize("dim", [1, 2, 7, 16, 512, 768])
def test_unit_check_kernel_flags_the_rows_numpy_flags(dim):
    """The exact backend's check of which rows are unit (`unit_check`, a parallel kernel) flags the
    same rows as its numpy form: unit rows, rows off by 2e-3 either way, scales 1e-40 to 1e30, zero,
    NaN and infinite rows, and a row of float32's largest values."""
    from drsplat.lang.codebook import unit_check, unit_check_reference
    from drsplat.lang import unit_rows

    rng = np.random.default_rng(dim)
    base = unit_rows(rng.normal(size=(40, dim)))
    rows = np.concatenate([base, base[:6] * np.float32(1.002), base[:6] * np.float32(0.998),
                           base[:6] * np.array([1e-40, 1e-20, 1e-8, 1e5, 1e20, 1e30], np.float32)[:, None],
                           np.zeros((1, dim), np.float32), np.full((1, dim), np.float32(3.4e38))]).astype(np.float32)
    bad = rows[:3].copy()
    bad[0, 0], bad[1, -1], bad[2, 0] = np.nan, np.inf, -np.inf
    rows = np.concatenate([rows, bad])
    ok, off = unit_check(rows)
    want_ok, want_off = unit_check_reference(rows)
    np.testing.assert_array_equal(ok, want_ok)
    np.testing.assert_array_equal(off, want_off)
    assert not off[:40].any() and off[40:58].all() and ok[:-5].all() and ok[-4] and not ok[-5] and not ok[-3:].any()


def test_float16_rows_are_numpys_bits_at_every_edge():
    """The exact backend's float32 -> float16 kernel gives numpy's bits (an exhaustive run over all
    2³² patterns agreed once; here the edges): every exponent with the significands around a
    rounding tie, odd and even, the subnormal and overflow boundaries (65504, 65519.99, 65520), signed
    zeros, infinities, NaNs with payloads, and a million random patterns; unkept rows are zero."""
    from drsplat.lang.backends import float16_rows, float16_rows_reference

    rng = np.random.default_rng(16)
    exps = np.arange(256, dtype=np.uint32) << np.uint32(23)
    sigs = np.array([0, 1, 0x0FFF, 0x1000, 0x1001, 0x1FFF, 0x2000, 0x2FFF, 0x3000, 0x3001, 0x7FF, 0x800, 0x7FFFFF, 0x7FE000,
                     0x7FF000, 0x400000, 0x401000, 0x403000], np.uint32)
    edges = (exps[:, None] | sigs[None, :]).reshape(-1)
    edges = np.concatenate([edges, edges | np.uint32(0x80000000)])
    specials = np.array([65504.0, 65519.99, 65520.0, 6.1e-5, 5.96e-8, 2.98e-8, 2.99e-8, 1e-8, -0.0, 0.0], np.float32).view(np.uint32)
    bits = np.concatenate([edges, specials, rng.integers(0, 2**32, 1_000_000, dtype=np.uint64).astype(np.uint32)])
    pad = (-bits.size) % 64
    rows = np.concatenate([bits, np.zeros(pad, np.uint32)]).view(np.float32).reshape(-1, 64)
    keep = rng.random(rows.shape[0]) > 0.05
    got, want = float16_rows(rows, keep), float16_rows_reference(rows, keep)
    assert got.dtype == np.float16 and got.shape == rows.shape
    np.testing.assert_array_equal(got.view(np.uint16), want.view(np.uint16))
    assert not got[~keep].view(np.uint16).any()


@pytest.mark.parametrize("codebook", ["none", "pq"])
def test_every_backend_stores_the_same_rows_as_features(codebook):
    """Rows with weight that are zero or not finite are unassigned by every backend (a PQ code of a
    zero row decoded to some vector, cosine 0.051), and rows of any finite scale (1e-8, 1e-40, 1e5)
    keep their direction in every backend (float16 underflowed 1e-8 to zero: a numerical probe,
    2026-11-30); unit rows are stored as given."""
    from drsplat.lang import unit_rows

    rng = np.random.default_rng(2)
    base = unit_rows(rng.normal(size=(300, 16)))
    rows = base.copy()
    rows[1], rows[2] = 0.0, np.nan
    rows[3], rows[4], rows[5] = base[3] * 1e-8, base[4] * 1e-40, base[5] * 1e5
    book = train_codebook(base, m=4) if codebook == "pq" else "none"
    field = build_field(rows, np.ones(len(rows), np.float32), book, clip_model="oracle-test")
    assigned = field.assigned()
    assert not assigned[1] and not assigned[2] and assigned[[0, 3, 4, 5]].all()
    assert field.weights[1] == field.weights[2] == 0
    scores = field.scores(base[[0, 3, 4, 5]])  # each row scored against its own direction
    assert np.all(np.diag(scores[[0, 3, 4, 5]]) > (0.999 if codebook == "none" else 0.5))
    if codebook == "none":  # unit rows stored as given
        np.testing.assert_array_equal(field.storage.features[0], base[0].astype(np.float16))


@pytest.mark.parametrize("value, expected", [("-1e-3", -1e-3), ("-.5e-1", -0.05), ("-0.25", -0.25), ("-1", -1.0),
                                             ("-0_0.25", -0.25), ("-0.000_5", -5e-4), ("-1_0e-1_0", -1e-9)])  # grouped as 1_000 is read
def test_a_negative_threshold_in_any_float_spelling_is_read_as_the_value(value, expected):
    from drsplat.cli import build_parser
    from viewer.launch import build_parser as viewer_parser

    args = build_parser().parse_args(["query", "r.ply", "--embedding", "q.npy", "--threshold", value])
    assert float(args.threshold) == expected
    assert viewer_parser().parse_args(["s.ply", "--threshold", value]).threshold == expected


@pytest.mark.parametrize("value", ["-inf", "-Infinity", "-nan"])
def test_a_negative_infinite_threshold_is_refused_as_not_finite_not_as_a_missing_value(value, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["query", "r.ply", "--embedding", "q.npy", "--threshold", value])
    err = capsys.readouterr().err
    assert exit_.value.code == 2
    assert "finite" in err and "expected one argument" not in err


def test_a_query_row_is_normalised_to_the_same_bits_wherever_it_sits_in_its_batch():
    """Round 37: numpy's float32 norm of a row depended on the array's layout (a Fortran-ordered batch
    sums each row in another order), so a query normalised alone and as the third of three (an
    embedding file saved from a transposed array) differed in all 512 components; its scores
    then depended on the other queries of the call, and `segment` split Gaussians tied between
    equal label and background rows by that noise. The norm is summed in float64 now."""
    from drsplat.lang import unit_rows

    rng = np.random.default_rng(3)
    rows = rng.normal(size=(9, 512)).astype(np.float32)
    alone = unit_rows(rows[:1])[0]
    for k in range(1, 9):
        for batch in (np.vstack([rows[1:k + 1], rows[:1]]), np.vstack([rows[:1], rows[1:k + 1]])):
            got = unit_rows(np.asfortranarray(batch))  # as a text embedding file saved from a transposed array loads
            assert np.array_equal(got[(batch == rows[0]).all(axis=1)][0].view(np.int32), alone.view(np.int32)), k
    np.testing.assert_allclose(np.linalg.norm(unit_rows(rows).astype(np.float64), axis=1), 1.0, atol=1e-6)


@pytest.mark.parametrize("case", ["noise", "zeros", "one value", "real"])
def test_an_automatic_threshold_says_when_the_scores_have_nothing_to_split(case, caplog):
    """Round 37: a query orthogonal to every feature scores float32 rounding (~1e-8), and Otsu split
    that noise without a word, selecting 170 of 269 Gaussians; all-zero scores selected every
    assigned Gaussian with 'threshold 0.0000'. Each now gets a warning; real scores do not."""
    import logging

    from drsplat.commands.common import resolve_threshold

    rng = np.random.default_rng(0)
    scores = {"noise": rng.normal(scale=1e-8, size=300), "zeros": np.zeros(300), "one value": np.full(300, 0.25),
              "real": np.concatenate([rng.normal(0.1, 0.02, 250), rng.normal(0.3, 0.02, 50)])}[case].astype(np.float32)
    with caplog.at_level(logging.INFO):
        resolve_threshold("auto", scores, relevancy=False)
    warned = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    expected = {"noise": "rounding noise", "zeros": "no Gaussian scores anything but 0", "one value": "nothing to split", "real": None}[case]
    assert (warned == []) if expected is None else (len(warned) == 1 and expected in warned[0]), warned


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_segment_refuses_a_min_score_that_is_not_a_finite_cosine(bad):
    """Round 37: segment(min_score=nan) cut nothing without a word (every comparison with NaN is false),
    where the CLI refuses `--min-score nan`."""
    from drsplat.query import segment

    field = build_field(np.eye(4, dtype=np.float32)[[0, 1, 2]], np.ones(3, np.float32), "none")
    with pytest.raises(ValueError, match="min_score must be a finite cosine"):
        segment(field, np.eye(4, dtype=np.float32)[:2], min_score=bad)


def test_segment_cuts_at_a_min_score_by_its_value_not_its_type(fields, world):
    """Round 91d F3: a min_score just above a float32 score k (float32(t) == k) cut k's Gaussians when given as an
    np.float64 and kept them as a Python float (NumPy 2 compares a float in float32, an np.float64 in float64). Both
    now meet the scores as `select` meets a threshold: in float32, so a score equal to float32(t) is kept."""
    field = fields["exact"]
    _, _, _, dirs = world
    labels = dirs[:3]
    plain = segment(field, labels)
    k = float(np.sort(plain.scores[plain.labels >= 0])[len(plain.scores) // 2])
    t = float(np.nextafter(np.float64(k), 2.0))  # above k in float64, k in float32
    assert np.float32(t) == np.float32(k) and t > k
    as_float, as_numpy = segment(field, labels, min_score=t), segment(field, labels, min_score=np.float64(t))
    np.testing.assert_array_equal(as_float.labels, as_numpy.labels)
    assert np.all(as_numpy.labels[plain.scores == np.float32(k)] >= 0)  # k meets float32(t)


def test_select_refuses_a_nan_threshold():
    """Round 91d F4: select(scores, nan) selected nothing without a word; ±inf still select none / all."""
    from drsplat.query import select

    scores = np.array([0.1, 0.5, np.nan], np.float32)
    with pytest.raises(ValueError, match="the threshold is nan, which selects nothing"):
        select(scores, float("nan"))
    assert select(scores, -np.inf).tolist() == [True, True, False] and not select(scores, np.inf).any()


def test_a_threshold_just_outside_the_range_is_shown_as_given(capsys):
    """Round 91d F5: `--threshold 1.0000001` was refused as "1 is outside [-1, 1]", a value that is inside."""
    from drsplat.cli import build_parser

    for argv, said in ((["query", "x.ply", "--embedding", "e.npy", "--threshold", "1.0000001"], "1.0000001 is outside [-1, 1]"),
                       (["segment", "x.ply", "--min-score", "1.0000001"], "1.0000001 is out of range"),
                       (["register", "x.ply", "--resolution", "640.0000001"], "640.0000001: a width is a whole number"),  # round 92a F1
                       (["register", "x.ply", "--resolution", "0.99999999"], "0.99999999: expected -1")):
        with pytest.raises(SystemExit):
            build_parser().parse_args(argv)
        err = capsys.readouterr().err
        assert said in err, err


@pytest.mark.parametrize("bad", [0.0, np.nan, np.inf])
def test_a_field_refuses_a_query_row_without_a_direction_naming_it(bad):
    """Round 37 left it as found: `LanguageField.scores` made a zero or NaN query row a zero row,
    whose column scored 0 for every Gaussian, as if none were assigned (the refusals were in
    `cosine`, `relevancy` and `segment` only). The field refuses it, naming the row, as they do."""
    from drsplat.lang import build_field, unit_rows

    rng = np.random.default_rng(0)
    field = build_field(unit_rows(rng.normal(size=(50, 16))), np.ones(50))
    queries = rng.normal(size=(3, 16)).astype(np.float32)
    good = field.scores(queries)
    assert good.shape == (50, 3) and np.abs(good).max() > 0.1
    queries[1] = 0.0 if bad == 0.0 else rng.normal(size=16)
    if bad != 0.0:
        queries[1, 5] = bad
    why = "is all zeros" if bad == 0.0 else "holds non-finite values"
    for score in (field.scores, field.scores_reference):
        with pytest.raises(ValueError, match=f"query 1 {why}: it has no direction to score by"):
            score(queries)


@pytest.mark.parametrize("value,why", [(1e-50, "is all zeros"), (1e39, "holds non-finite values")])
def test_query_rows_judges_a_row_as_the_float32_it_becomes(value, why):
    """Review of round 38: `query_rows` judged rows in their own dtype, then `unit_rows` read them as
    float32, so a float64 row of 1e-50 (0 in float32) or 1e39 (inf) passed it and reached the
    field as a zero or infinite row, refused there with the field's ValueError about "query 0"
    whatever the row was. It judges the float32 row, naming it as the caller's."""
    from drsplat.query import query_rows

    rows = np.ones((2, 8))
    rows[1] = value
    with pytest.raises(DrsplatError, match=f"label embedding 1 {why}: it has no direction to score by"):
        query_rows(rows, "label embedding")


def test_float32_scores_meet_a_typed_threshold_in_float32():
    """Round 40: float32(0.7) lies below the float64 0.7, so `--threshold 0.7` left out a Gaussian scoring exactly
    0.7 in float32 (`query.select`, `eval lerf`'s `select_queries`); the evaluation's grid already compared in float32."""
    from drsplat.eval.lerf import select_queries
    from drsplat.query import select

    scores = np.array([0.7, 0.6999999, 0.71], np.float32)
    assert select(scores, 0.7).tolist() == [True, False, True]
    assert select(scores.astype(np.float64), 0.7).tolist() == [False, False, True]  # float64 scores: float64 compare
    chosen, taus = select_queries(scores[:, None], 0.7)
    assert chosen[:, 0].tolist() == [True, False, True] and taus.tolist() == [0.7]
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a threshold past float32's range (typed into the viewer): no overflow warning
        assert not select(scores, 1e39).any() and select(scores, -1e39).all()


def test_segment_names_a_background_row_from_the_datasets_own_list(tmp_path, caplog):
    """Round 49: with --background the last row of a synthetic dataset's text_embeddings.npy is the
    background, and its gt/label_names.json names all the rows; the names were ignored ("does not
    name the 7 label rows") and the table showed label_0 .. label_6. Now the first names are the
    labels'. A list of another length is still ignored with a message that says what it should hold,
    and a --names file of the wrong length is refused naming both lengths."""
    import json

    from drsplat.commands.segment import embedding_names

    (tmp_path / "gt").mkdir()
    names = ["wall", "floor", "mug", "background"]
    (tmp_path / "gt" / "label_names.json").write_text(json.dumps(names))
    assert embedding_names(tmp_path / "text_embeddings.npy", None, 3, background=True) == names[:3]
    assert embedding_names(tmp_path / "text_embeddings.npy", None, 4) == names
    with caplog.at_level("INFO"):
        assert embedding_names(tmp_path / "text_embeddings.npy", None, 3) == ["label_0", "label_1", "label_2"]
    assert "is not a list of 3 names" in caplog.text
    explicit = tmp_path / "names.json"
    explicit.write_text(json.dumps(names + ["extra"]))
    with pytest.raises(InputError, match=r"3 names .*or 4, the last the background row"):
        embedding_names(tmp_path / "text_embeddings.npy", explicit, 3, background=True)
    # round 59a: any file of as many rows beside the dataset's names took them (its rows reversed, or random vectors: the
    # table named every label wrongly); only the dataset's own text_embeddings.npy is named by them, --names names any
    caplog.clear()
    with caplog.at_level("INFO"):
        assert embedding_names(tmp_path / "reversed.npy", None, 4) == ["label_0", "label_1", "label_2", "label_3"]
    assert "not naming the rows of" in caplog.text and "reversed.npy" in caplog.text
    assert embedding_names(tmp_path / "reversed.npy", tmp_path / "gt" / "label_names.json", 4) == names
    link = tmp_path / "linked" / "text_embeddings.npy"  # round 60c: a link of the dataset's name to other rows took them too
    (tmp_path / "linked" / "gt").mkdir(parents=True)
    (tmp_path / "linked" / "gt" / "label_names.json").write_text(json.dumps(names))
    link.symlink_to(tmp_path / "reversed.npy")
    assert embedding_names(link, None, 4) == ["label_0", "label_1", "label_2", "label_3"]


@pytest.mark.parametrize("dim", [2, 16, 512])
def test_a_phrase_given_as_query_and_as_negative_has_relevancy_one_half_exactly(dim, tmp_path):
    """Round 59a: the same embedding as a query and as a negative scored 0.5 ± 1e-7 (the CLI normalised the negatives once
    more than the queries, and `unit_rows` re-rounded a unit row), so `--threshold 0.5` selected 371 of 2,744 Gaussians by
    rounding noise. `unit_rows` is idempotent now (its own rows, at every scale), and the relevancy is 0.5 everywhere."""
    from drsplat.lang import unit_rows

    rng = np.random.default_rng(dim)
    for scale in (1e-30, 1e-3, 1.0, 7.0, 1e30):
        x = (scale * rng.standard_normal((500, dim))).astype(np.float32)
        once = unit_rows(x)
        np.testing.assert_array_equal(unit_rows(once), once)
        assert np.abs(np.linalg.norm(once.astype(np.float64), axis=1) - 1).max() <= 2.0**-23
    feats = unit_rows(rng.normal(size=(300, dim)))
    field = build_field(feats, np.ones(300, np.float32))
    q = (3 * rng.normal(size=dim)).astype(np.float32)
    assert (relevancy(field, q, unit_rows(unit_rows(q[None]))) == np.float32(0.5)).all()
    ply = tmp_path / "r.ply"
    save_ply(attach_field(tiny_scene(300), field, ply), ply)
    np.save(tmp_path / "q.npy", q)
    np.save(tmp_path / "neg.npy", q[None])
    assert main(["-q", "query", str(ply), "--embedding", str(tmp_path / "q.npy"), "--relevancy", "--negative-embeddings",
                 str(tmp_path / "neg.npy"), "--threshold", "0.5", "--scores", str(tmp_path / "s.npy")]) == 0
    assert (np.load(tmp_path / "s.npy") == np.float32(0.5)).all()


@pytest.mark.parametrize("kind", ["exact", "pq"])
def test_a_registered_scene_loads_without_holding_its_rows_or_a_second_field(tmp_path, world, fields, kind, monkeypatch):
    """Round 61b: loading a registered PLY held the file's rows whole, the language columns copied out of them
    ([L, N]) and the field's [N, L] transpose at once: 2.1x the file for an exact field (a 5M-Gaussian one was
    killed at 10 GB). Now the rows are read a block at a time and the field is the block the columns were copied
    into: the load's peak is the field and the geometry, not the file on top."""
    import tracemalloc

    import drsplat.scene as ds
    from drsplat.commands.common import load_registered

    x, w, _, _ = world
    rows = 12_000  # 24 MB of exact float16 rows at D = 1024: far above the geometry and the blocks
    big = np.tile(x, (rows // len(x), 2))
    big /= np.linalg.norm(big, axis=1, keepdims=True).clip(1e-12)
    field = build_field(big, np.tile(w, rows // len(x)), "none" if kind == "exact" else train_codebook(big[4:2000], m=16),
                        clip_model="oracle-test")
    ply = tmp_path / f"{kind}.ply"
    save_ply(attach_field(tiny_scene(len(field)), field, ply), ply)
    monkeypatch.setattr(ds, "READ_BLOCK_BYTES", 1 << 16)
    tracemalloc.start()
    try:
        _, loaded = load_registered(ply)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    held = field.storage.bytes_per_gaussian() * len(field) if kind == "pq" else big.shape[0] * big.shape[1] * 2
    geometry = len(field) * (14 + 4) * 4  # means, quats, scales, opacity, DC colour, weight (float32)
    assert peak < held + geometry + 4 * (1 << 16) + (2 << 20)
    np.testing.assert_array_equal(loaded.scores(big[100:103]), field.scores(big[100:103]))


def _sh3_registered(tmp_path, world, fields, kind: str, rows: int = 40_000):
    """A registered PLY of `rows` Gaussians of SH degree 3 (192 B of colour each) carrying the `kind` field's rows, tiled."""
    field = fields[kind].subset(np.arange(rows) % len(fields[kind]))
    scene = tiny_scene(rows)
    scene = dataclasses.replace(scene, sh=np.random.default_rng(2).normal(size=(rows, 16, 3)).astype(np.float32))
    ply = tmp_path / f"{kind}_sh3.ply"
    save_ply(attach_field(scene, field, ply), ply)
    return ply, field


@pytest.mark.parametrize("kind", ["exact", "pq"])
def test_a_query_that_writes_no_scene_never_holds_the_gaussians(tmp_path, world, fields, kind, monkeypatch):
    """A query or segmentation writing no scene read every Gaussian's geometry with the field (a 3M-Gaussian SH degree 3
    PQ scene: 3.0 GB peak against 1.1 GB; 236 B a Gaussian beside PQ's 138). Now the rows are checked block by
    block and their geometry let go: the load's peak is the field's, the scores the same."""
    import tracemalloc

    import drsplat.scene as ds
    from drsplat.commands.common import load_registered

    ply, field = _sh3_registered(tmp_path, world, fields, kind)
    monkeypatch.setattr(ds, "READ_BLOCK_BYTES", 1 << 16)
    tracemalloc.start()
    try:
        scene, loaded = load_registered(ply, geometry=False)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert scene is None
    geometry = len(field) * (3 + 4 + 3 + 1 + 48) * 4  # 9.4 MB, against the field's 1.1 MB (PQ) or 5.4 MB (exact)
    # beside the field: 8 bytes a Gaussian, and the geometry findings' 4 (a largest scale) and 12 (its mean, sampled for the
    # extent: every mean of a scene under EXTENT_SAMPLE)
    assert peak < field.num_gaussians * (field.storage.bytes_per_gaussian() + 8 + 16) + 6 * (1 << 16) + (2 << 20) < geometry
    q = world[0][100:102]
    np.testing.assert_array_equal(loaded.scores(q), field.scores(q))
    np.testing.assert_array_equal(loaded.scores(q), load_registered(ply)[1].scores(q))


@pytest.mark.parametrize("kind", ["exact", "pq"])
def test_a_query_writing_its_selection_holds_the_selections_gaussians_only(tmp_path, world, fields, kind, monkeypatch):
    """`query --out` read every Gaussian's geometry to write the few it selects (a 20M-Gaussian SH degree 3 scene: 4.7 GB
    for a selection of thousands). Now the selection is made from the field alone and its own rows are read after: the
    query holds about what it holds without --out, and writes the same Gaussians as the whole load's subset."""
    import tracemalloc

    import drsplat.scene as ds
    from drsplat.commands.common import load_registered

    ply, field = _sh3_registered(tmp_path, world, fields, kind)
    monkeypatch.setattr(ds, "READ_BLOCK_BYTES", 1 << 16)
    np.save(tmp_path / "q.npy", world[3][2])
    scores = field.scores(world[3][2][None])[:, 0]
    threshold = float(np.quantile(scores, 0.99))
    peaks = {}
    args = ["query", str(ply), "--embedding", str(tmp_path / "q.npy"), "--threshold", f"{threshold:.6f}", "--scores", str(tmp_path / "s.npy")]
    assert main(args) == 0  # what a first query makes once (kernels, caches) is not the selection's
    for out in (None, tmp_path / "sel.ply"):
        tracemalloc.start()
        try:
            assert main(args + (["--out", str(out)] if out else [])) == 0
            peaks[out is not None] = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    geometry = len(field) * (3 + 4 + 3 + 1 + 48) * 4  # 9.4 MB
    assert peaks[True] - peaks[False] < geometry / 4, peaks
    mask = np.load(tmp_path / "s.npy") >= np.float32(f"{threshold:.6f}")
    got, want = load_ply(tmp_path / "sel.ply"), load_registered(ply)[0].subset(mask)
    assert 0 < len(got) == int(mask.sum()) < len(field) // 50
    for attr in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(got, attr), getattr(want, attr))


def test_a_query_whose_file_is_rewritten_before_its_selection_is_read_writes_nothing(tmp_path, world, fields, monkeypatch, capsys):
    """Round 64b F3: the registered PLY rewritten, as many finite rows, between the field's read and the selection's: the
    selection made on the old field was written from the new geometry, exit 0. Now one error naming the file, exit 1,
    no --out written."""
    import drsplat.commands.query as query_command
    from drsplat.commands.common import load_registered

    ply, field = _sh3_registered(tmp_path, world, fields, "pq")
    np.save(tmp_path / "q.npy", world[3][2])

    def load_then_rewritten(path, geometry=True):
        loaded = load_registered(path, geometry)
        scene = load_ply(path)
        save_ply(dataclasses.replace(scene, means=scene.means + 1.0), path)  # another program's new version, the same rows
        return loaded

    monkeypatch.setattr(query_command, "load_registered", load_then_rewritten)
    out = tmp_path / "sel.ply"
    assert main(["query", str(ply), "--embedding", str(tmp_path / "q.npy"), "--threshold", "0.0", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "changed while it was read: its size, modification time or inode differ" in err and ply.name in err, err
    assert not out.exists()


def test_a_query_of_a_text_ply_parses_it_once(tmp_path, world, fields, monkeypatch):
    """Round 64b F4: `query --out` of an ASCII registered PLY parsed the text twice (the field, then the selection's
    rows: 73k rows, 14.4 -> 27.2 s), though a text file is held whole either way. It is read once now, with its
    Gaussians, and writes the same selection as the binary file's."""
    from plyfile import PlyData

    import drsplat.scene as ds

    ply, field = _sh3_registered(tmp_path, world, fields, "pq")
    text = PlyData.read(str(ply))
    text.text = True
    text.write(str(tmp_path / "text.ply"))
    np.save(tmp_path / "q.npy", world[3][2])
    threshold = float(np.quantile(field.scores(world[3][2][None])[:, 0], 0.98))
    for name in ("text", "binary"):
        source = tmp_path / "text.ply" if name == "text" else ply
        parsed = []
        real = ds.read_plyfile
        monkeypatch.setattr(ds, "read_plyfile", lambda *a, **k: (parsed.append(1), real(*a, **k))[1])
        assert main(["query", str(source), "--embedding", str(tmp_path / "q.npy"), "--threshold", f"{threshold:.6f}",
                     "--out", str(tmp_path / f"{name}-sel.ply")]) == 0
        monkeypatch.undo()
        if name == "text":
            assert len(parsed) == 1, parsed
    got, want = load_ply(tmp_path / "text-sel.ply"), load_ply(tmp_path / "binary-sel.ply")
    assert len(got) == len(want) > 0
    for attr in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_allclose(getattr(got, attr), getattr(want, attr), rtol=1e-6, atol=1e-7)


def test_a_query_that_writes_no_scene_refuses_rows_the_load_would_drop(tmp_path, world, fields):
    """Without the geometry held, a row with a NaN position or an infinite scale is still found, and the query is
    refused as with the whole load: its scores could not follow the file order."""
    from drsplat.commands.common import load_registered
    from drsplat.errors import InputError

    field = fields["pq"]
    scene = tiny_scene(len(field))
    scene.means[7, 1] = np.nan
    scene.log_scales[9, 2] = np.inf
    scene.opacity_logits[11] = np.inf  # clamped, not dropped
    ply = tmp_path / "bad.ply"
    save_ply(attach_field(scene, field, ply), ply)
    for geometry in (True, False):
        with pytest.raises(InputError, match=r"bad\.ply: 2 rows have non-finite values and would be dropped"):
            load_registered(ply, geometry=geometry)


def test_a_query_that_writes_no_scene_still_says_what_the_load_found(tmp_path, fields, caplog):
    """Round 63c: reading the extras only dropped the load's findings that need no geometry held: a NaN lang_weight
    ("non-finite values in extra properties"), an infinite opacity clamped, a zero quaternion. They are said as the
    whole load says them."""
    from drsplat.commands.common import load_registered

    field = fields["pq"]
    scene = tiny_scene(len(field))
    scene.opacity_logits[3] = np.inf
    scene.quats[5] = 0
    reg = attach_field(scene, field, tmp_path / "f.ply")
    reg.extra["lang_weight"][8] = np.nan
    save_ply(reg, tmp_path / "f.ply")
    said = {}
    for geometry in (True, False):
        caplog.clear()
        with caplog.at_level("WARNING", logger="drsplat.scene"):
            load_registered(tmp_path / "f.ply", geometry=geometry)
        said[geometry] = [r.getMessage() for r in caplog.records]
    for note in ("1 non-finite value in extra properties", "1 infinite opacity logit clamped", "1 zero quaternion replaced"):
        assert any(note in line for line in said[False]), (note, said[False])
        assert any(note in line for line in said[True]), (note, said[True])


def test_a_second_embedding_file_is_a_usage_error_not_a_silent_replacement(tmp_path, registered, capsys):
    """Round 78b F3: `query --embedding a.npy --embedding b.npy` (and segment's --embeddings) kept b alone, exit 0, while
    --text repeats to add queries. Now exit 2 naming both files."""
    np.save(tmp_path / "a.npy", np.ones(DIM, np.float32))
    np.save(tmp_path / "b.npy", -np.ones(DIM, np.float32))
    argv = ["query", str(registered["exact"]), "--embedding", str(tmp_path / "a.npy"), "--embedding", str(tmp_path / "b.npy"),
            "--scores", str(tmp_path / "s.npy")]
    with pytest.raises(SystemExit) as exit_:  # argparse's usage error
        main(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "--embedding is given twice" in err and "a.npy" in err and "b.npy" in err
    assert not (tmp_path / "s.npy").exists()
    with pytest.raises(SystemExit) as exit_:
        main(["segment", str(registered["exact"]), "--embeddings", str(tmp_path / "a.npy"), "--embeddings", str(tmp_path / "b.npy"),
              "--out", str(tmp_path / "t.npy")])
    assert exit_.value.code == 2 and "--embeddings is given twice" in capsys.readouterr().err
    np.save(tmp_path / "ids_a.npy", np.array([0, 1]))
    np.save(tmp_path / "ids_b.npy", np.array([2]))
    with pytest.raises(SystemExit) as exit_:  # round 83a F1: --gaussians kept the last set too
        main(["query", str(registered["exact"]), "--gaussians", str(tmp_path / "ids_a.npy"), "--gaussians", str(tmp_path / "ids_b.npy"),
              "--scores", str(tmp_path / "s.npy")])
    assert exit_.value.code == 2 and "--gaussians is given twice" in capsys.readouterr().err
    from viewer.launch import build_parser

    for flag in ("--query", "--embedding", "--oracle"):  # the viewer's screenshot query (round 83a F1)
        with pytest.raises(SystemExit) as exit_:
            build_parser().parse_args(["s.ply", flag, "a", flag, "b"])
        assert exit_.value.code == 2 and f"{flag} is given twice" in capsys.readouterr().err


@pytest.mark.parametrize("model_id, expected", [
    ("ViT-B-16/laion2b_s34b_b88k", ("ViT-B-16", "laion2b_s34b_b88k")),
    ("ViT-L-14:openai", ("ViT-L-14", "openai")),
    ("ViT-B-16/file:ckpt.pt", ("ViT-B-16", "file:ckpt.pt")),
    ("ViT-L-14", ("ViT-L-14", None)),
    ("hf-hub:laion/CLIP-ViT-g-14", ("hf-hub:laion/CLIP-ViT-g-14", None)),
])
def test_a_model_id_splits_after_its_architecture_at_either_separator(model_id, expected):
    from drsplat.features.modelid import canonical_model_id, split_model_id

    assert split_model_id(model_id) == expected
    model, tag = expected
    if tag is not None and not model.startswith("hf-hub:"):  # the split agrees with the ids' comparison
        assert canonical_model_id(model_id) == canonical_model_id(f"{model}/{tag}")


def test_a_scene_of_another_clip_model_asks_for_that_models_weights(tmp_path, capsys, monkeypatch):
    """Round 78b F2: a field whose model id had no "/" ("ViT-L-14:openai", or no tag at all) asked for the default
    ViT-B-16's weights, a model the scene was never made with. Now the field's architecture and tag, and an id with no
    tag is one error asking for --pretrained or --clip-checkpoint."""
    from drsplat.features import clip as clip_module

    made = []

    class Recorder:
        def __init__(self, model, pretrained, checkpoint, device):
            made.append((model, pretrained))
            raise DrsplatError(f"no weights for {model} ({pretrained}) here")

    monkeypatch.setattr(clip_module, "ClipEncoder", Recorder)
    np.save(tmp_path / "q.npy", np.ones(DIM, np.float32))
    for model_id, asked in (("ViT-L-14:openai", ("ViT-L-14", "openai")), ("ViT-L-14", None)):
        field = build_field(np.eye(4, DIM, dtype=np.float32), np.ones(4, np.float32), "none", clip_model=model_id)
        path = tmp_path / f"{model_id.replace(':', '_')}.ply"
        save_ply(attach_field(tiny_scene(4), field, path), path)
        made.clear()
        assert main(["query", str(path), "--text", "chair"]) == 1
        err = capsys.readouterr().err
        if asked is None:
            assert made == [] and "CLIP model id 'ViT-L-14' names no weights tag: pass --pretrained TAG" in err, err
        else:
            assert made == [asked] and "ViT-L-14 (openai)" in err, err


def test_an_empty_selection_names_a_threshold_and_best_score_that_differ(tmp_path, registered, capsys):
    """Round 78b F1: both were rounded to 4 decimals, so a threshold just above the best score read as
    "no Gaussian scores >= 0.7773 (the best score is 0.7773)"."""
    np.save(tmp_path / "q.npy", np.ones(DIM, np.float32))
    assert main(["query", str(registered["exact"]), "--embedding", str(tmp_path / "q.npy"), "--scores", str(tmp_path / "s.npy")]) == 0
    best = float(np.load(tmp_path / "s.npy").max())
    assert main(["query", str(registered["exact"]), "--embedding", str(tmp_path / "q.npy"), "--threshold", repr(best + 2e-6),
                 "--out", str(tmp_path / "sel.ply")]) == 1
    out, err = capsys.readouterr()
    said = re.search(r"no Gaussian scores >= (\S+) \(the best score is (\S+)\)", err)
    assert said and said.group(1) != said.group(2) and float(said.group(2).rstrip("):")) <= best + 1e-9, err
    assert f"Gaussians score >= {said.group(1)}" in out + err  # the count's line too (round 79a F4: 4 decimals there)


def test_segment_without_labels_and_relevancy_at_a_bad_temperature_are_refused():
    """Round 98c F1 / F2: segment() with no label embeddings labelled every Gaussian background at a best score of -inf;
    relevancy() at temperature NaN scored every Gaussian NaN (nothing selected), at -10 turned the ranking over, at 0
    gave every Gaussian ½."""
    from drsplat.query import relevancy, segment

    field = build_field(np.eye(4, dtype=np.float32)[[0, 1, 2]], np.ones(3, np.float32), "none")
    with pytest.raises(DrsplatError, match="segmentation needs at least one label embedding"):
        segment(field, np.zeros((0, 4), np.float32))
    query, negatives = np.eye(4, dtype=np.float32)[:1], np.eye(4, dtype=np.float32)[3:]
    for bad in (float("nan"), -10.0, 0.0, float("inf")):
        with pytest.raises(DrsplatError, match=r"relevancy temperature must be a finite positive number \(LERF's is 10.0\)"):
            relevancy(field, query, negatives, temperature=bad)
    np.testing.assert_allclose(relevancy(field, query, negatives, temperature=10.0)[:, 0], [1 / (1 + np.exp(-10)), 0.5, 0.5], rtol=1e-6)
    from decimal import Decimal  # round 100a F4: passed the check, then numpy's multiply raised UFuncTypeError / TypeError

    for given in (Decimal("10"), "10", np.float32(10), np.array(10.0)):
        assert np.array_equal(relevancy(field, query, negatives, temperature=given), relevancy(field, query, negatives, temperature=10.0))
