"""Registration in Gaussian blocks under a memory budget, the pair-log checkpoint and the memory plan.

A file written in blocks must equal the one-block file byte for byte, for every codebook choice;
logs cut short, damaged or of the old format must be detected; a bad codebook must fail before any
view is registered.
"""

from __future__ import annotations

import logging
import os
import re
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from drsplat.cameras import load_cameras
from drsplat.errors import Cancelled, DrsplatError, InputError
from drsplat.memory import parse_size
from drsplat.registration import RegisterOptions, register, register_features
from drsplat.registration.checkpoint import checkpoint_path_for
from drsplat.registration.coalesce import Coalescer
from drsplat.registration.pairlog import PairLog, ViewPairs
from drsplat.registration.plan import MemoryPlan, choose_block, estimate_memory
from drsplat.registration.sums import (PAIR_CAPACITY, PAIR_SLOT_BYTES, Accumulator, accumulate_view_reference, add_pairs_in_place, buffer_bytes, buffered_rows,
                                      pair_capacity_for)
from drsplat.scene import load_ply
from drsplat.synthetic import write_dataset
from drsplat.utils import CancelToken
from tests.test_registration import _random_view


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("tiny") / "data", "tiny", 0, show_progress=False)


@pytest.fixture(scope="module")
def inputs(tiny):
    return load_ply(tiny / "scene.ply"), load_cameras(tiny)


@pytest.fixture(scope="module")
def in_memory(tiny, inputs, tmp_path_factory) -> dict[bool, bytes]:
    """The in-memory path's files, pruned and with --keep-unassigned."""
    scene, cams = inputs
    folder = tmp_path_factory.mktemp("reference")
    out = {}
    for keep in (False, True):
        path = folder / f"keep{keep}.ply"
        register(scene, cams, tiny / "features", path, RegisterOptions(keep_unassigned=keep), show_progress=False)
        out[keep] = path.read_bytes()
    return out


# ----------------------------------------------------------------------------- kernels


def test_the_sums_hold_no_more_embedding_rows_than_the_plan_counts():
    """Views of many 1024-D masks: the accumulator's embedding rows (the buffer, and the old one while
    it grows) stay within what `buffer_bytes` counts for those mask counts, and the sums are those of
    the pairs added one by one. Until 2026-12-05 the buffer held up to 2¹⁶ rows and doubled past
    them (128,000 rows, 500 MiB, on 40 views of 2,000 masks) and the plan counted none."""
    rng = np.random.default_rng(5)
    n, d, masks, views = 50, 1024, 2_000, 12
    acc = Accumulator(n, d)
    F_ref, W_ref = np.zeros((n, d), np.float32), np.zeros(n, np.float32)
    held = 0
    for _ in range(views):
        feats = rng.normal(size=(masks, d)).astype(np.float32)
        g = rng.integers(0, n, 40).astype(np.int32)
        m = rng.integers(0, masks, 40).astype(np.int32)
        w = rng.random(40).astype(np.float32)
        before = acc._rows.nbytes
        acc.add_pairs(g, m, w, feats)
        held = max(held, acc._rows.nbytes + (before if acc._rows.nbytes != before else 0))  # both buffers while it grew
        add_pairs_in_place(F_ref, W_ref, g, m, w, feats)
    assert views * masks > buffered_rows(d)  # the buffer was flushed for its rows
    assert held <= buffer_bytes(d, views * masks, masks) - PAIR_CAPACITY * PAIR_SLOT_BYTES
    F, W = acc.sums()
    np.testing.assert_array_equal(F, F_ref)
    np.testing.assert_array_equal(W, W_ref)


def test_a_small_scene_buffers_as_many_pairs_as_the_plan_counts(inputs):
    """The pair buffer grows with the scene up to PAIR_CAPACITY (64 pairs a Gaussian, 2²⁰ at the
    least, one a Gaussian at the most), and the memory plan of a scene counts the buffers its sums'
    Accumulator allocates: a scene of 27,354 Gaussians buffers 1.75 M pairs (28 MB), not 8 M (128 MB)."""
    scene, cams = inputs
    plan = estimate_memory(scene, cams, 512, 40, base=0, aggregate="paper", total_masks=100, max_masks=10)
    acc = Accumulator(scene.num_gaussians, 512)
    rows = 2 * 100 * 512 * 4  # every mask's row, and as many while the row buffer grows
    assert acc._pair_g.shape[0] * PAIR_SLOT_BYTES + rows == plan.pair_buffer
    for n in (1, 1_000, 27_354, 200_000):
        assert Accumulator(n, 4)._pair_g.shape[0] == pair_capacity_for(n) >= n
    assert pair_capacity_for(27_354) == 64 * 27_354 < PAIR_CAPACITY
    assert pair_capacity_for(1) == 1 << 20 and pair_capacity_for(200_000) == PAIR_CAPACITY and pair_capacity_for(1 << 24) == 1 << 24


@pytest.mark.parametrize("case", ["random", "tiny_buffer", "empty"])
def test_pair_buffers_of_any_size_give_the_same_bits(case):
    """Coalescer + add_pairs with a 1-pair buffer equal a large buffer bit for bit, and the scipy reference."""
    rng = np.random.default_rng(3)
    n, d = 60, 7
    big, small = Accumulator(n, d), Accumulator(n, d, pair_capacity=1 if case == "tiny_buffer" else 1 << 20)
    coalescer = Coalescer(n, capacity=1)  # grows while coalescing
    F_ref, W_ref = np.zeros((n, d)), np.zeros(n)
    for _ in range(3):
        ids, weights, masks, feats = _random_view(rng, 9, 11, 5, n, 12, empty_fraction=1.0 if case == "empty" else 0.3)
        feats = feats[:, :d]
        g, m, w, contributing = coalescer.coalesce(ids, weights, masks, feats.shape[0])
        assert contributing == accumulate_view_reference(F_ref, W_ref, ids, weights, masks, feats)
        big.add_pairs(g, m, w, feats)
        small.add_pairs(g, m, w, feats)
    (F1, W1), (F2, W2) = big.sums(), small.sums()
    np.testing.assert_array_equal(F1, F2)
    np.testing.assert_array_equal(W1, W2)
    np.testing.assert_allclose(F2, F_ref, rtol=1e-4, atol=1e-5)


# ----------------------------------------------------------------------------- streaming = in memory


@pytest.mark.parametrize("keep", [False, True])
def test_streamed_file_equals_in_memory_byte_for_byte(tiny, inputs, in_memory, tmp_path, keep):
    scene, cams = inputs
    out = tmp_path / "streamed.ply"
    result = register(scene, cams, tiny / "features", out, RegisterOptions(block_size=1024, keep_unassigned=keep), show_progress=False)
    assert result.features is None and result.num_blocks == 3  # never held [N, D]
    assert out.read_bytes() == in_memory[keep]
    assert not list(tmp_path.glob(".*"))  # log and body file removed


def test_streamed_pq_file_equals_in_memory(tiny, inputs, tmp_path):
    from drsplat.lang import train_codebook

    scene, cams = inputs
    book = train_codebook(np.random.default_rng(0).normal(size=(3000, 512)).astype(np.float32), m=16)
    book.save(tmp_path / "general.faiss")
    a, b = tmp_path / "a" / "mem.ply", tmp_path / "b" / "mem.ply"
    register(scene, cams, tiny / "features", a, RegisterOptions(codebook=str(tmp_path / "general.faiss")), show_progress=False)
    register(scene, cams, tiny / "features", b, RegisterOptions(codebook=str(tmp_path / "general.faiss"), block_size=1024), show_progress=False)
    assert a.read_bytes() == b.read_bytes()
    assert (a.parent / "mem.codebook.faiss").read_bytes() == (b.parent / "mem.codebook.faiss").read_bytes()


def test_streaming_resumes_after_cancel_and_equals_in_memory(tiny, inputs, in_memory, tmp_path):
    scene, cams = inputs
    out = tmp_path / "out.ply"
    token = CancelToken()

    def stop_after_six(done: int, total: int) -> None:
        if done == 6:
            token.cancel()

    options = RegisterOptions(block_size=1024)
    with pytest.raises(Cancelled):
        register(scene, cams, tiny / "features", out, options, show_progress=False, cancel=token, on_progress=stop_after_six)
    assert not out.exists() and checkpoint_path_for(out).is_file()
    seen = []
    result = register(scene, cams, tiny / "features", out, options, show_progress=False, on_progress=lambda d, t: seen.append(d))
    assert result.resumed_views == 6 and seen[0] == 6
    assert out.read_bytes() == in_memory[False]
    assert not checkpoint_path_for(out).exists()


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_a_fifo_output_with_no_reader_waits_cancellably_and_a_reader_gets_the_file(tiny, inputs, in_memory, tmp_path, caplog):
    """Was (round 27): `register --out FIFO` with no reader blocked in the FIFO's open once its work
    was done, and one Ctrl-C (which only cancels) did not end it. Now it waits for a reader while
    reading the cancel token: cancelled there, it keeps its checkpoint, and the rerun's reader gets
    the bytes of a regular-file run."""
    scene, cams = inputs
    fifo = tmp_path / "pipe.ply"
    os.mkfifo(fifo)
    token = CancelToken()
    raised: list[BaseException] = []

    def run() -> None:
        try:
            register(scene, cams, tiny / "features", fifo, RegisterOptions(), show_progress=False, cancel=token)
        except BaseException as exc:  # noqa: BLE001 - handed to the test's thread
            raised.append(exc)

    with caplog.at_level(logging.INFO, logger="drsplat"):
        worker = threading.Thread(target=run, daemon=True)
        worker.start()
        deadline = time.monotonic() + 120
        while worker.is_alive() and time.monotonic() < deadline and not any("FIFO" in r.getMessage() for r in caplog.records):
            time.sleep(0.05)  # the work done, the output waits for its reader
        token.cancel()
        worker.join(timeout=30)
        if worker.is_alive():  # blocked in the FIFO's open: a reader that opens and goes releases it, and the test fails
            os.close(os.open(fifo, os.O_RDONLY | os.O_NONBLOCK))
            worker.join(timeout=30)
    assert raised and isinstance(raised[0], Cancelled), raised
    assert any("waiting for a process to read the FIFO" in r.getMessage() and str(fifo) in r.getMessage() for r in caplog.records)
    assert fifo.is_fifo() and checkpoint_path_for(fifo).is_file()
    got: list[bytes] = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_bytes()), daemon=True)
    reader.start()
    result = register(scene, cams, tiny / "features", fifo, RegisterOptions(), show_progress=False)
    reader.join(timeout=60)
    assert result.resumed_views == len(cams) and got == [in_memory[False]]
    assert fifo.is_fifo() and not checkpoint_path_for(fifo).exists()


def test_scene_codebook_in_blocks_writes_the_same_bytes_as_one_block(tiny, inputs, tmp_path):
    """The scene codebook is trained once, the same way in every plan (masks topped up with a sample of
    Gaussians the sink sums), so `--codebook scene` gives the same file and codebook with and without blocks."""
    scene, cams = inputs
    a, b = tmp_path / "one" / "reg.ply", tmp_path / "blocks" / "reg.ply"
    one = register(scene, cams, tiny / "features", a, RegisterOptions(codebook="scene"), show_progress=False)
    many = register(scene, cams, tiny / "features", b, RegisterOptions(codebook="scene", block_size=1024), show_progress=False)
    assert one.num_blocks == 1 and many.num_blocks > 1 and one.field_kind == "pq"
    assert a.read_bytes() == b.read_bytes()
    assert (a.parent / "reg.codebook.faiss").read_bytes() == (b.parent / "reg.codebook.faiss").read_bytes()


# ----------------------------------------------------------------------------- checkpoints


# The damage tests below are about the pair log itself, so they register with `paper`, which keeps no
# statistics: a mode with statistics restarts when a damaged log no longer holds the views its
# snapshot covers (tests/test_aggregate.py, the snapshot tests).
LOG_ONLY = RegisterOptions(aggregate="paper")


def _cancelled_log(tiny, inputs, path: Path, views: int, options: RegisterOptions = LOG_ONLY) -> None:
    scene, cams = inputs
    token = CancelToken()

    def stop(done: int, total: int) -> None:
        if done == views:
            token.cancel()

    with pytest.raises(Cancelled):
        register_features(scene, cams, tiny / "features", options, checkpoint=path, cancel=token, on_progress=stop, show_progress=False)


def test_torn_last_record_is_dropped_and_redone(tiny, inputs, tmp_path, caplog):
    scene, cams = inputs
    full = register_features(scene, cams, tiny / "features", LOG_ONLY, show_progress=False)
    ckpt = tmp_path / "run.log"
    _cancelled_log(tiny, inputs, ckpt, 5)
    ckpt.write_bytes(ckpt.read_bytes()[:-100])  # killed while appending view 5
    with caplog.at_level(logging.WARNING):
        resumed = register_features(scene, cams, tiny / "features", LOG_ONLY, checkpoint=ckpt, show_progress=False)
    assert "incomplete" in caplog.text and resumed.resumed_views == 4
    np.testing.assert_array_equal(resumed.features, full.features)
    np.testing.assert_array_equal(resumed.weights, full.weights)


def test_damaged_record_checksum_is_detected(tiny, inputs, tmp_path):
    scene, cams = inputs
    ckpt = tmp_path / "run.log"
    _cancelled_log(tiny, inputs, ckpt, 3)
    data = bytearray(ckpt.read_bytes())
    data[-50] ^= 0xFF  # a flipped byte inside the last record's pairs
    ckpt.write_bytes(bytes(data))
    resumed = register_features(scene, cams, tiny / "features", LOG_ONLY, checkpoint=ckpt, show_progress=False)
    assert resumed.resumed_views == 2


def _rewrite_record_meta(path: Path, index: int, edit) -> None:
    """Replace record `index`'s meta of the pair log `path` by edit(meta), with a checksum that matches
    (a log edited by hand or by another tool: the checksum cannot tell)."""
    import json
    import struct
    import zlib

    data = path.read_bytes()
    pos = 16 + struct.unpack("<Q", data[8:16])[0] + 4
    for _ in range(index):
        a, b = struct.unpack("<QQ", data[pos + 4 : pos + 20])
        pos += 20 + a + b + 4
    a, b = struct.unpack("<QQ", data[pos + 4 : pos + 20])
    meta, payload = json.loads(data[pos + 20 : pos + 20 + a]), data[pos + 20 + a : pos + 20 + a + b]
    meta_bytes = json.dumps(edit(meta)).encode()
    record = b"VIEW" + struct.pack("<QQ", len(meta_bytes), b) + meta_bytes + payload
    path.write_bytes(data[:pos] + record + struct.pack("<I", zlib.crc32(payload, zlib.crc32(meta_bytes))) + data[pos + 20 + a + b + 4 :])


@pytest.mark.parametrize("edit", [lambda m: {k: v for k, v in m.items() if k != "name"}, lambda m: {**m, "pairs": "many"},
                                  lambda m: {**m, "present": [10**6]}, lambda m: {**m, "stamp": [1]}, lambda m: [m]],
                         ids=["no_name", "pairs_a_string", "present_beyond_the_masks", "stamp_a_list", "meta_a_list"])
def test_a_record_whose_meta_is_not_a_records_is_damaged_though_its_checksum_matches(tiny, inputs, tmp_path, caplog, edit):
    """Round 30: a record whose checksum matches but whose meta `_encode` never writes (no name, a
    count that is a string, present masks beyond its embeddings) raised KeyError, ValueError or
    IndexError from inside the resume, and the kept checkpoint failed every rerun the same way. It is
    a damaged record: the log resumes from the views before it, to the same features."""
    scene, cams = inputs
    full = register_features(scene, cams, tiny / "features", LOG_ONLY, show_progress=False)
    ckpt = tmp_path / "run.log"
    _cancelled_log(tiny, inputs, ckpt, 4)
    _rewrite_record_meta(ckpt, 2, edit)
    with caplog.at_level(logging.WARNING):
        resumed = register_features(scene, cams, tiny / "features", LOG_ONLY, checkpoint=ckpt, show_progress=False)
    assert "record 3 is damaged (its checksum, length or meta does not match)" in caplog.text and resumed.resumed_views == 2
    np.testing.assert_array_equal(resumed.features, full.features)
    np.testing.assert_array_equal(resumed.weights, full.weights)


@pytest.mark.parametrize("content", ["truncated_zip", "empty", "junk"])
def test_old_or_truncated_checkpoints_restart_from_scratch(tiny, inputs, tmp_path, caplog, content):
    """An old .npz checkpoint cut short (BadZipFile) no longer blocks every later run."""
    scene, cams = inputs
    ckpt = tmp_path / "run.log"
    if content == "truncated_zip":
        with zipfile.ZipFile(ckpt, "w") as z:
            z.writestr("F.npy", b"x" * 5000)
        ckpt.write_bytes(ckpt.read_bytes()[:3000])
    else:
        ckpt.write_bytes(b"" if content == "empty" else b"not a log at all")
    with caplog.at_level(logging.WARNING):
        result = register_features(scene, cams, tiny / "features", RegisterOptions(), checkpoint=ckpt, show_progress=False)
    assert result.resumed_views == 0 and result.num_views == 16
    assert "starting from scratch" in caplog.text and not ckpt.exists()


def test_log_is_smaller_than_dense_sums_and_round_trips(tmp_path):
    rng = np.random.default_rng(0)
    view = ViewPairs("v0", rng.normal(size=(5, 8)).astype(np.float32), rng.integers(0, 1000, 40).astype(np.int32),
                     rng.integers(0, 5, 40).astype(np.int32), rng.random(40).astype(np.float32), np.arange(5, dtype=np.int32), 123, 1)
    params = {"version": 2, "n": 1000}
    with PairLog.open(tmp_path / "l.log", params) as plog:
        plog.append(view)
        plog.append(view)
    with PairLog.open(tmp_path / "l.log", params) as plog:
        back = list(plog)
    assert [v.name for v in back] == ["v0", "v0"] and back[1].num_pairs == 123 and back[1].num_nonfinite == 1
    for a in ("feats", "gaussians", "masks", "weights", "used"):
        np.testing.assert_array_equal(getattr(back[1], a), getattr(view, a))
    with PairLog.open(tmp_path / "l.log", {"version": 2, "n": 999}) as plog:  # other parameters
        assert plog.records == []


def _spread_view(rng, name: str, n: int, masks: int = 6, pairs: int = 3000, dim: int = 8) -> ViewPairs:
    """A view's pairs as the coalescer emits them (mask by mask, Gaussians in first-seen order), with
    Gaussian ids spread over several 2^16 chunks and many Gaussians in several masks."""
    g, m = [], []
    for j in range(masks):
        ids = rng.choice(n, size=pairs // masks, replace=False)
        g.append(ids)
        m.append(np.full(ids.size, j))
    g = np.concatenate(g).astype(np.int32) if masks else np.zeros(0, np.int32)
    m = np.concatenate(m).astype(np.int32) if masks else np.zeros(0, np.int32)
    w = rng.uniform(1e-6, 2.0, g.size).astype(np.float32)
    return ViewPairs(name, rng.normal(size=(masks, dim)).astype(np.float32), g, m, w, np.arange(masks, dtype=np.int32), int(g.size) * 3)


def test_grouped_pairs_keep_each_gaussians_order_and_sum_to_the_same_bits():
    rng = np.random.default_rng(3)
    n = 5 * 65536 + 77
    view = _spread_view(rng, "v", n, masks=9, pairs=20000)
    view.gaussians[:50] = 5 * 65536 + 5  # one Gaussian many times: its order must survive
    grouped = view.grouped()
    chunks = grouped.gaussians >> 16
    assert np.all(np.diff(chunks) >= 0) and grouped.chunk_starts.tolist() == [int(np.sum(chunks < c)) for c in range(chunks.max() + 2)]
    for gid in np.unique(view.gaussians)[:: 97]:
        before, after = view.gaussians == gid, grouped.gaussians == gid
        np.testing.assert_array_equal(view.masks[before], grouped.masks[after])
        np.testing.assert_array_equal(view.weights[before], grouped.weights[after])
    sums = []
    for v in (view, grouped):
        acc = Accumulator(n, view.feats.shape[1], pair_capacity=4096)
        acc.add_pairs(v.gaussians, v.masks, v.weights, v.feats)
        sums.append(acc.sums())
    assert np.array_equal(sums[0][0], sums[1][0]) and np.array_equal(sums[0][1], sums[1][1])


def test_read_block_reads_exactly_the_blocks_pairs_in_record_order(tmp_path):
    rng = np.random.default_rng(4)
    n = 4 * 65536 + 1000
    views = [_spread_view(rng, f"v{i}", n) for i in range(4)]
    views.append(_spread_view(rng, "no masks", n, masks=0))
    low = _spread_view(rng, "first chunk only", 60000)
    views.append(low)
    with PairLog.open(tmp_path / "l.log", {"n": n}) as plog:
        for v in views:
            plog.append(v)
        full = list(plog)
        spans = [(0, n), (0, 1), (65535, 65537), (70000, 200000), (3 * 65536, n), (n - 1, n), (5, 5), (65536, 2 * 65536)]
        spans += [tuple(sorted(rng.integers(0, n, 2))) for _ in range(6)]
        for lo, hi in spans:
            for record, whole in zip(plog.records, full):
                part = plog.read_block(record, lo, hi)
                keep = (whole.gaussians >= lo) & (whole.gaussians < hi)
                for a in ("gaussians", "masks", "weights"):
                    np.testing.assert_array_equal(getattr(part, a), getattr(whole, a)[keep])
                np.testing.assert_array_equal(part.feats, whole.feats)
                assert part.num_pairs == whole.num_pairs and part.name == whole.name


@pytest.mark.parametrize("sink", ["log", "vote"])
def test_block_replays_over_many_chunks_equal_the_in_memory_sums(tmp_path, sink):
    """Blocks that start and end inside 2^16-Gaussian chunks, replayed from the log, give the bits
    of summing every view in memory (the log's records are grouped by chunk), and so do blocks made
    in the previous block's arrays (`blocks(reuse=True)`, what the driver asks for), the last one smaller."""
    from drsplat.registration.sink import LogSink, MemorySink
    from drsplat.registration.vote import VoteSink

    rng = np.random.default_rng(5)
    n, dim = 3 * 65536 + 513, 8
    views = [_spread_view(rng, f"v{i}", n, dim=dim) for i in range(5)]
    memory = MemorySink(n, dim) if sink == "log" else VoteSink(n, dim)
    with PairLog.open(tmp_path / "l.log", {"n": n}) as plog:
        streamed = LogSink(n, dim, plog, 50_000) if sink == "log" else VoteSink(n, dim, plog, 50_000)
        for v in views:
            plog.append(v)
            memory.add(v)
            streamed.add(v)
        (whole,) = list(memory.blocks())
        blocks = list(streamed.blocks())
        # reused: each block in the last one's arrays (copied here as they come, as the driver encodes them)
        reused, previous = [], None
        for b in streamed.blocks(reuse=True):
            assert previous is None or np.shares_memory(previous, b.F)
            previous = b.F
            reused.append((b.lo, b.hi, b.F.copy(), b.W.copy()))
    assert len(blocks) == 4 == len(reused)
    for b, (lo, hi, F, W) in zip(blocks, reused):
        assert np.array_equal(b.F, whole.F[b.lo : b.hi]) and np.array_equal(b.W, whole.W[b.lo : b.hi])
        assert (lo, hi) == (b.lo, b.hi) and np.array_equal(F, b.F) and np.array_equal(W, b.W)
    assert np.count_nonzero(whole.W) > 10_000


def test_bad_codebook_fails_before_registering(tiny, inputs, tmp_path):
    scene, cams = inputs
    calls = []
    junk = tmp_path / "junk.faiss"
    junk.write_bytes(b"\0" * 64)
    with pytest.raises(InputError):
        register(scene, cams, tiny / "features", tmp_path / "o.ply", RegisterOptions(codebook=str(junk)),
                        show_progress=False, on_progress=lambda d, t: calls.append(d))
    from drsplat.lang import train_codebook

    small = train_codebook(np.random.default_rng(0).normal(size=(600, 16)).astype(np.float32), m=4)
    small.save(tmp_path / "d16.faiss")
    with pytest.raises(InputError, match="dimension 16 differs from the features' dimension 512"):
        register(scene, cams, tiny / "features", tmp_path / "o.ply", RegisterOptions(codebook=str(tmp_path / "d16.faiss")),
                        show_progress=False, on_progress=lambda d, t: calls.append(d))
    assert calls == [] and not checkpoint_path_for(tmp_path / "o.ply").exists()


def test_a_scene_codebook_that_cannot_split_the_features_fails_before_registering(tiny, inputs, tmp_path):
    """Was: `--codebook scene` on 64-D features (a small CLIP model) registered every view, then failed with
    "M=128 sub-vectors do not divide the embedding dimension 64", keeping a checkpoint whose resume failed
    the same way (round 61a). Now before the first view, naming what to use instead."""
    import json
    import shutil

    scene, cams = inputs
    features = Path(shutil.copytree(tiny / "features", tmp_path / "features64"))
    for f in features.glob("*_f.npy"):
        rows = np.load(f)[:, :64]
        np.save(f, (rows / np.maximum(np.linalg.norm(rows, axis=1, keepdims=True), 1e-12)).astype(np.float32))
    manifest = features / "manifest.json"
    if manifest.exists():
        manifest.write_text(json.dumps({**json.loads(manifest.read_text()), "dim": 64}))
    calls = []
    with pytest.raises(InputError, match="--codebook scene trains a codebook of 128 sub-vectors, which do not divide these features' 64-D"):
        register(scene, cams, features, tmp_path / "o.ply", RegisterOptions(codebook="scene"),
                 show_progress=False, on_progress=lambda d, t: calls.append(d))
    assert calls == [] and not checkpoint_path_for(tmp_path / "o.ply").exists()


# ----------------------------------------------------------------------------- memory plan


def test_parse_size():
    assert parse_size("8GB") == 8_000_000_000 and parse_size("1.5 GiB") == 3 << 29 and parse_size("512mb") == 512_000_000
    for bad in ("", "8XB", "-1GB", "0", "nan"):
        with pytest.raises(ValueError):
            parse_size(bad)


def test_plan_streams_a_5m_scene_in_8gb_and_refuses_what_cannot_fit(inputs):
    """The done-means case as a plan: 5M Gaussians x 512-D hold 10 GB of sums in one block (more than 8 GB)."""
    scene, cams = inputs

    class Big:  # the planner only reads the Gaussian count and the SH width
        num_gaussians = 5_000_000
        sh = np.zeros((1, 1, 3))

    plan = estimate_memory(Big(), cams, 512, 40, base=400 << 20)
    assert plan.in_memory > 5_000_000 * 512 * 4
    block = choose_block(plan, 8 * 10**9)
    assert 0 < block < 5_000_000 and block % 1024 == 0
    assert plan.peak(block) <= 8e9
    assert choose_block(plan, 64 * 10**9) == 5_000_000  # fits: one block
    with pytest.raises(DrsplatError, match="too small for this scene"):
        choose_block(plan, 10**9)
    with pytest.raises(DrsplatError, match=r"needs about .* GB.*--memory-budget [0-9.]+GB") as hinted:
        choose_block(plan, None, available=12 * 10**9)
    hint = parse_size(str(hinted.value).split("--memory-budget ")[1].split()[0])
    assert choose_block(plan, hint) > 0 and hint <= 0.8 * (12 * 10**9 + 10**10)  # the hint is accepted as typed


def test_the_hint_without_a_budget_is_never_below_the_smallest_budget(inputs):
    """Rounding the suggested budget down to 0.1 GB must not fall below what the plan accepts (probe
    round 11: 1.85 GB free, minimum 1.1 GB, hint "1GB", refused when typed back)."""
    from drsplat.registration.plan import NAMED_MINIMUM_ROOM, budget_hint

    scene, cams = inputs

    class Big:
        num_gaussians = 1_000_000
        sh = np.zeros((1, 1, 3))

    plan = estimate_memory(Big(), cams, 512, 40, base=400 << 20)
    low = plan.minimum_budget() + NAMED_MINIMUM_ROOM
    for fits in (low, low + 1, low + 10**8 - 1, low + 3 * 10**8, 10 * low):
        hint = budget_hint(plan, fits)
        assert " " not in hint and choose_block(plan, parse_size(hint)) > 0, (fits, hint)
        assert parse_size(hint) <= max(fits, -(-low // 10**8) * 10**8)


def test_a_budget_below_the_in_memory_peak_streams_even_when_blocks_of_the_whole_scene_fit(inputs):
    """In memory the sums are held while the views run (peak: both); in blocks, one after the other.
    A budget between the two used to get one block, i.e. the in-memory run it does not fit."""
    scene, cams = inputs

    class Big:
        num_gaussians = 1_000_000
        sh = np.zeros((1, 1, 3))

    plan = estimate_memory(Big(), cams, 512, 40, base=400 << 20)
    from drsplat.registration.plan import OVERHEAD, WRITE_CHUNK

    whole = -(-plan.num_gaussians // 1024) * 1024  # an aligned block holding every Gaussian, summed after the views
    blocks_peak = max(plan.views, plan.base + OVERHEAD + whole * plan.sum_bytes + plan.pair_buffer + WRITE_CHUNK * plan.write_bytes)
    budget = (blocks_peak + plan.in_memory) // 2
    assert blocks_peak <= budget < plan.in_memory
    block = choose_block(plan, budget)
    assert plan.block_for(budget) == block
    assert block == (plan.num_gaussians - 1) // 1024 * 1024 and plan.peak(block) <= budget


def test_a_solve_mode_is_refused_below_its_in_memory_peak_naming_that_peak(inputs):
    """The solve stage needs every Gaussian in one block: a budget that would give blocks is refused
    up front, naming a budget for the one block (a refusal used to name the blocks' minimum, which
    the run then refused as blocks: probe round 11); that budget gives one block."""
    from drsplat.memory import parse_size as size

    scene, cams = inputs

    class Big:
        num_gaussians = 1_000_000
        sh = np.zeros((1, 1, 3))

    plan = estimate_memory(Big(), cams, 512, 40, base=400 << 20, aggregate="solve")
    budget = plan.in_memory - 1
    assert 0 < choose_block(plan, budget) < plan.num_gaussians  # a mode that streams would get blocks
    with pytest.raises(DrsplatError, match=r"solves over all Gaussians in one block.*give at least ([0-9.]+ [MG]B)") as refused:
        choose_block(plan, budget, whole=True)
    named = size(str(refused.value).split("give at least ")[1].split(" (")[0])
    assert named >= plan.in_memory and choose_block(plan, named, whole=True) == plan.num_gaussians
    with pytest.raises(DrsplatError, match="solves over all Gaussians in one block .* does not fit the .* available"):
        choose_block(plan, None, available=plan.in_memory // 2, whole=True)
    assert choose_block(plan, None, available=2 * plan.in_memory, whole=True) == plan.num_gaussians


def test_refusals_say_which_term_the_budget_they_name_is_for():
    """A refusal's reason names the term behind the budget it names (probe round 11: "the view pass
    alone needs about 852 MB; give at least 1.1 GB", the 1.1 GB being the blocks' minimum; and
    without a budget "even in blocks, one view needs ..." where the process's own memory, not the
    view, ruled blocks out)."""
    gb = 10**9
    plan = MemoryPlan(1_000_000, 512, base=int(0.9 * gb), views=int(0.5 * gb), sum_bytes=4_200, write_bytes=5_000, pair_buffer=100 << 20)
    assert plan.minimum_budget() > plan.views
    with pytest.raises(DrsplatError, match=r"the view pass alone .* needs about 500 MB, and the smallest blocks .* need about 1\.\d GB; "
                                           r"give at least 1\.\d GB") as refused:
        choose_block(plan, int(0.4 * gb))
    named = parse_size(str(refused.value).split("give at least ")[1].split(" (")[0])
    assert choose_block(plan, named) > 0
    heavy = MemoryPlan(1_000_000, 512, base=50 * gb, views=1 * gb, sum_bytes=4_200, write_bytes=5_000, pair_buffer=100 << 20)
    with pytest.raises(DrsplatError, match=r"even in blocks, the smallest blocks with this process's own memory need about 5\d\.\d GB"):
        choose_block(heavy, None, available=10 * gb)
    wide = MemoryPlan(1_000_000, 512, base=0, views=20 * gb, sum_bytes=4_200, write_bytes=5_000, pair_buffer=100 << 20)
    with pytest.raises(DrsplatError, match=r"even in blocks, one view needs about 20\.0 GB"):
        choose_block(wide, None, available=10 * gb)


def test_plan_keeps_small_scenes_in_memory(inputs):
    scene, cams = inputs
    plan = estimate_memory(scene, cams, 512, 40)
    assert isinstance(plan, MemoryPlan) and choose_block(plan, None) == scene.num_gaussians


def test_cli_memory_budget_errors(tiny, tmp_path):
    from drsplat.cli import main

    base = ["register", str(tiny / "scene.ply"), "--source", str(tiny), "--features", str(tiny / "features"), "--out", str(tmp_path / "o.ply"), "--no-progress"]
    with pytest.raises(SystemExit) as usage:  # not a size: argparse's usage error
        main(base + ["--memory-budget", "lots"])
    assert usage.value.code == 2
    assert main(base + ["--memory-budget", "1KB"]) == 1  # a size, too small for this scene
    assert not (tmp_path / "o.ply").exists()


def test_a_budget_too_small_is_refused_before_the_fit_stage_renders(tiny, tmp_path, monkeypatch, capsys):
    """The default (fit) mode used to render its probe views first and refuse the budget after; now
    the budget is checked against both modes the probe may pick before any view is rendered."""
    from drsplat import splat_formats
    from drsplat.cli import main
    from drsplat.registration import driver

    def no_probe(*args, **kwargs):
        raise AssertionError("the fit stage ran before the budget was refused")

    monkeypatch.setattr(driver, "fit_stage", no_probe)
    monkeypatch.setattr(splat_formats, "declared_scene_size", lambda path: None)  # past the check before the scene is read
    base = ["register", str(tiny / "scene.ply"), "--source", str(tiny), "--features", str(tiny / "features"), "--out", str(tmp_path / "o.ply"), "--no-progress"]
    assert main(base + ["--memory-budget", "1KB"]) == 1
    assert "too small for this scene" in capsys.readouterr().err and not (tmp_path / "o.ply").exists()


@pytest.mark.parametrize("mode", ["fit-check-vote-reject", "paper", "solve"])
def test_a_budget_too_small_is_refused_before_the_near_plane_is_decided(tiny, tmp_path, monkeypatch, capsys, mode):
    """Round 65a F5: `--near-plane auto` (the default) rendered its evidence, and warned, before the plan refused the
    budget. The plan is checked first, for a fit mode, a plain one and one that solves in one block; with a budget that
    fits, the decision is made and the run registers."""
    from drsplat import frames, splat_formats
    from drsplat.cli import main

    decided = []

    def no_decision(*args, **kwargs):
        raise AssertionError("the near plane was decided before the budget was refused")

    monkeypatch.setattr(frames, "near_plane_as_trained", no_decision)
    monkeypatch.setattr(splat_formats, "declared_scene_size", lambda path: None)  # past the check before the scene is read
    base = ["register", str(tiny / "scene.ply"), "--source", str(tiny), "--features", str(tiny / "features"),
            "--out", str(tmp_path / "o.ply"), "--no-progress", "--aggregate", mode]
    assert main(base + ["--memory-budget", "1KB"]) == 1
    assert "too small for this scene" in capsys.readouterr().err and not (tmp_path / "o.ply").exists()
    monkeypatch.setattr(frames, "near_plane_as_trained", lambda *args, **kwargs: decided.append(1) or frames.NEAR)
    assert main(base + ["--memory-budget", "8GB"]) == 0 and decided == [1] and (tmp_path / "o.ply").exists()


def test_a_budget_its_reading_would_exceed_is_refused_before_the_scene_is_read(tiny, inputs, tmp_path, monkeypatch, capsys):
    """Round 67b F3: --memory-budget 300MB for a 3M-Gaussian scene was refused only after loading it (1.02 GB resident,
    5-9 s). What reading the file holds (4 bytes for each value of every row, `splat_formats.declared_scene_size`) bounds
    any run from below before it is read, rows the loading drops included (round 70a F1: a floor counted in the plan's
    bytes per kept Gaussian refused a file of mostly non-finite rows a budget its kept rows fit)."""
    from drsplat import splat_formats
    from drsplat.cli import main
    from drsplat.registration.plan import refuse_below_scene_floor
    from drsplat.scene import load_ply_report

    with pytest.raises(DrsplatError, match=r"too small for this scene \(s\): reading its 3,000,000 rows of 59 values holds more than 708 MB"):
        refuse_below_scene_floor(700 * 10**6, 3_000_000, 59, "s", base=0)
    refuse_below_scene_floor(709 * 10**6, 3_000_000, 59, "s", base=0)
    # a scene cheap to read is read: the plan's refusal then names a budget that fits (`test_the_budget_a_refusal_names_*`)
    refuse_below_scene_floor(1, 1_000_000, 59, "s", base=0)

    def not_read(*args, **kwargs):
        raise AssertionError("the scene was read before the budget was refused")

    with monkeypatch.context() as patched:
        patched.setattr(splat_formats, "load_scene_report", not_read)
        patched.setattr(splat_formats, "declared_scene_size", lambda path: (3_000_000, 59))
        base = ["register", str(tiny / "scene.ply"), "--source", str(tiny), "--features", str(tiny / "features"), "--out", str(tmp_path / "o.ply"),
                "--no-progress"]
        assert main(base + ["--memory-budget", "300MB"]) == 1
    err = capsys.readouterr().err
    assert "--memory-budget 300 MB is too small for this scene" in err and "3,000,000 rows" in err and not (tmp_path / "o.ply").exists()
    # a file of mostly non-finite rows: the floor counts them (its loading holds them), the plan only the kept ones
    scene, _ = inputs
    nan_rows = 20 * scene.num_gaussians
    bad = scene.subset(np.r_[np.arange(scene.num_gaussians), np.zeros(nan_rows, np.int64)])
    bad.means[scene.num_gaussians:] = np.nan
    from drsplat.scene import save_ply

    save_ply(bad, tmp_path / "nan.ply")
    rows, values = splat_formats.declared_scene_size(tmp_path / "nan.ply")
    assert rows == bad.num_gaussians and load_ply_report(tmp_path / "nan.ply")[1].dropped_nan_rows == nan_rows


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_a_fifo_given_as_the_scene_with_a_budget_is_refused_not_waited_on(tiny, tmp_path, capsys):
    """Round 74c F1: with --memory-budget the early size check opened the scene before anything had checked it is a
    regular file, and the open of a FIFO no one writes to blocked for good (without a budget: "is not a file" at once)."""
    from drsplat.cli import main

    fifo = tmp_path / "scene.ply"
    os.mkfifo(fifo)
    codes: list[int] = []
    args = ["register", str(fifo), "--source", str(tiny), "--features", str(tiny / "features"), "--out", str(tmp_path / "o.ply"),
            "--no-progress", "--memory-budget", "1GB"]
    worker = threading.Thread(target=lambda: codes.append(main(args)), daemon=True)
    worker.start()
    worker.join(timeout=60)
    blocked = worker.is_alive()
    if blocked:  # in the FIFO's open: a writer that opens and goes releases it
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        worker.join(timeout=30)
    assert not blocked and codes == [1]
    assert f"{fifo}: is not a file" in capsys.readouterr().err


def test_declared_scene_size_reads_a_scene_file_s_rows_and_values_without_loading_it(tiny, inputs, tmp_path):
    """A PLY's vertex count and its values (14, and its higher SH), a .splat's records, an spz header's points; None where
    the file has a problem its loading names (a header declaring more rows than the file holds is not taken at its
    word) or the count is in no header."""
    from drsplat.splat_formats import declared_scene_size, save_compressed_ply, save_scene

    scene, _ = inputs
    n, rest = scene.num_gaussians, 3 * (scene.sh.shape[1] - 1)
    save_scene(scene, tmp_path / "s.splat")
    save_scene(scene, tmp_path / "s.spz")
    save_compressed_ply(scene, tmp_path / "s.compressed.ply")
    assert declared_scene_size(tiny / "scene.ply") == (n, 14 + rest)
    assert declared_scene_size(tmp_path / "s.splat") == (n, 14) and declared_scene_size(tmp_path / "s.spz") == (n, 14 + rest)
    (tmp_path / "cut.splat").write_bytes((tmp_path / "s.splat").read_bytes() + b"12345")  # no whole number of records: not a size to trust
    assert declared_scene_size(tmp_path / "cut.splat") is None
    assert declared_scene_size(tmp_path / "s.compressed.ply") == (n, 14 + rest)
    data = (tiny / "scene.ply").read_bytes()
    (tmp_path / "lying.ply").write_bytes(data.replace(f"element vertex {n}\n".encode(), f"element vertex {n * 1000}\n".encode(), 1))
    (tmp_path / "cut.ply").write_bytes(data[: len(data) // 2])
    assert declared_scene_size(tmp_path / "lying.ply") is None and declared_scene_size(tmp_path / "cut.ply") is None
    assert declared_scene_size(tmp_path / "missing.ply") is None
    spz = (tmp_path / "s.spz").read_bytes()
    (tmp_path / "big.spz").write_bytes(spz[:8] + (10**9).to_bytes(4, "little") + spz[12:])  # an NGSP v4 header declaring 1e9 points
    assert declared_scene_size(tmp_path / "big.spz") is None


@pytest.mark.parametrize("mode", ["fit-check-vote-reject", "paper"])
def test_the_early_budget_check_plans_with_the_rendering_engine_loaded(tiny, inputs, monkeypatch, mode):
    """Round 67a F2: the check before `--near-plane auto`'s decision planned from this process's memory before the
    engine that renders the views was loaded, so with `--engine torch` it named 515 MB as enough and the run was then
    refused under 1.1 GB after the decision. The engine is loaded first, as the registration's own plan does."""
    from drsplat.registration import driver
    from drsplat.registration.options import RegisterOptions

    events = []

    class Engine:
        def topk_fn(self):
            events.append("engine")

    monkeypatch.setattr(driver, "get_engine", lambda name: Engine())
    planned = driver._memory_plan
    monkeypatch.setattr(driver, "_memory_plan", lambda *args, **kwargs: events.append("plan") or planned(*args, **kwargs))
    scene, cameras = inputs
    run = driver.prepare_run(scene, cameras, tiny / "features", RegisterOptions(aggregate=mode, memory_budget=8 << 30, engine="torch"))
    driver.refuse_if_over_budget(run)
    assert events[0] == "engine" and "plan" in events


@pytest.mark.parametrize("mode", ["fit-check-vote-reject", "paper"])
def test_the_early_budget_check_counts_what_the_decision_leaves_resident(tiny, inputs, tmp_path, monkeypatch, mode):
    """Round 67a F2: after the early check the decision left its render kernels and image readers resident (13 MB), so a
    budget within that of the minimum was accepted, the plane decided and warned about, and then refused. The check
    counts what is held later (the command gives it `frames.DECISION_HELD_BYTES`): a budget it accepts without is refused
    with more held."""
    from drsplat import frames
    from drsplat.cli import main
    from drsplat.memory import current_rss
    from drsplat.registration import driver
    from drsplat.registration.options import RegisterOptions

    scene, cameras = inputs
    run = driver.prepare_run(scene, cameras, tiny / "features", RegisterOptions(aggregate=mode))
    budget = driver._memory_plan(run, current_rss()).minimum_budget() + (600 << 20)  # room for the fit stage's probe and noise
    run = driver.prepare_run(scene, cameras, tiny / "features", RegisterOptions(aggregate=mode, memory_budget=budget))
    driver.refuse_if_over_budget(run)
    with pytest.raises(DrsplatError, match="too small for this scene"):
        driver.refuse_if_over_budget(run, held_later=4 << 30)
    held = []
    monkeypatch.setattr(driver, "refuse_if_over_budget", lambda run, held_later=0: held.append(held_later))
    monkeypatch.setattr(frames, "near_plane_as_trained", lambda *args, **kwargs: frames.NEAR)
    assert main(["register", str(tiny / "scene.ply"), "--source", str(tiny), "--features", str(tiny / "features"), "--out",
                 str(tmp_path / "o.ply"), "--no-progress", "--aggregate", mode, "--memory-budget", "8GB"]) == 0
    assert held == [frames.DECISION_HELD_BYTES]
    # a first run (no kernel in numba's cache) holds its compiler's memory too (round 68a F3: 560 MB passed, 697 asked after)
    import drsplat.raster as raster

    monkeypatch.setattr(raster, "kernels_cached", lambda: False)
    assert main(["register", str(tiny / "scene.ply"), "--source", str(tiny), "--features", str(tiny / "features"), "--out",
                 str(tmp_path / "o2.ply"), "--no-progress", "--aggregate", mode, "--memory-budget", "8GB"]) == 0
    assert held[-1] == frames.DECISION_HELD_BYTES + frames.FIRST_COMPILE_HELD_BYTES


@pytest.mark.parametrize("refused", [False, True])
def test_each_warning_about_the_feature_files_is_said_once_when_the_plane_is_decided(tiny, tmp_path, capsys, monkeypatch, refused):
    """Round 67a F1: under `--near-plane auto` (the default) the budget check before the decision paired the cameras
    with the feature files as the run does after it, and every warning of that pairing came twice. Round 68a F7: when
    that quiet check refused the run, its warnings (which can explain the refusal) were not said at all; now once."""
    import shutil

    from drsplat import splat_formats
    from drsplat.cli import main

    budget = []
    if refused:  # a budget the plan refuses, past the check before the scene is read
        monkeypatch.setattr(splat_formats, "declared_scene_size", lambda path: None)
        budget = ["--memory-budget", "1KB"]

    features = tmp_path / "features"
    shutil.copytree(tiny / "features", features)
    stem = sorted(features.glob("*_s.npy"))[0].name[: -len("_s.npy")]
    for suffix in ("_s.npy", "_f.npy"):  # a pair that matches no camera
        shutil.copy(features / f"{stem}{suffix}", features / f"stray{suffix}")
    assert main(["register", str(tiny / "scene.ply"), "--source", str(tiny), "--features", str(features),
                 "--out", str(tmp_path / "o.ply"), "--no-progress", "--aggregate", "paper", *budget]) == (1 if refused else 0)
    err = capsys.readouterr().err
    assert err.count("1 feature file in") == 1, err  # "... matches no camera and is ignored", once
    assert ("too small for this scene" in err) == refused, err


@pytest.mark.parametrize("n", [30, 300])
def test_block_rows_carry_the_whole_files_meta_column(tmp_path, n):
    """lang_meta row i holds byte i mod L of the comment: blocks are numbered as in the whole
    file, and a file shorter than L carries the text in ceil(L / n) columns (as in memory)."""
    from drsplat.lang import attach_field, build_field
    from drsplat.scene import GaussianScene, ply_header, save_ply, scene_to_vertices
    from drsplat.registration.output import _widen_meta_if_short, _with_meta_rows

    rng = np.random.default_rng(n)
    scene = GaussianScene(means=rng.normal(size=(n, 3)).astype(np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                          log_scales=np.full((n, 3), -3, np.float32), opacity_logits=np.zeros(n, np.float32), sh=np.zeros((n, 1, 3), np.float32))
    feats = rng.normal(size=(n, 16)).astype(np.float32)
    feats /= np.linalg.norm(feats, axis=1, keepdims=True)
    weights = rng.random(n).astype(np.float32) + 0.1
    whole = tmp_path / "whole.ply"
    save_ply(attach_field(scene, build_field(feats, weights, clip_model="oracle"), whole), whole)
    body = tmp_path / "body"
    header, written = None, 0
    with open(body, "wb") as f:
        for lo in range(0, n, 8):
            sl = slice(lo, lo + 8)
            part = _with_meta_rows(attach_field(scene.subset(sl), build_field(feats[sl], weights[sl], clip_model="oracle"), whole), written)
            rows = scene_to_vertices(part)
            header = header or (rows.dtype, part.comments)
            f.write(rows.tobytes())
            written += rows.shape[0]
    dtype, comments, _ = _widen_meta_if_short(body, header, written)
    assert ply_header(dtype, comments, written) + body.read_bytes() == whole.read_bytes()


class _BlockWatcher:
    """A registration target that keeps weak references to each block's sums; `alive()` counts the
    blocks whose F still exists (the plan counts one block of sums at a time)."""

    def __init__(self):
        self.refs: list = []

    def alive(self, sums=None) -> int:
        """Blocks whose F is alive, but for one whose memory holds `sums` (F, W): the next block made
        in the last one's arrays (`blocks(reuse=True)`) is one block's memory."""
        import gc

        gc.collect()
        return sum(ref() is not None and (sums is None or not np.shares_memory(ref(), sums[0])) for ref in self.refs)

    def open(self, codebook, rows_hint=None) -> None:
        pass

    def add(self, block, keep) -> None:
        import weakref

        self.refs.append(weakref.ref(block.F))

    def close(self) -> int:
        return 0

    def abort(self) -> None:
        pass


@pytest.mark.parametrize("aggregate", ["paper", "vote-reject"])
def test_one_block_of_sums_is_alive_at_a_time(tiny, inputs, tmp_path, monkeypatch, aggregate):
    """Was: the driver held block b's sums while block b+1's were summed, so a 5M-Gaussian run in
    two blocks peaked at 10.8 GB under --memory-budget 8GB. Checked where a block's sums are made."""
    from drsplat.registration import sink, vote
    from drsplat.registration.driver import prepare_run, run_registration
    from drsplat.registration.sums import Accumulator

    watcher = _BlockWatcher()
    alive_when_summing: list[int] = []

    class Watched(Accumulator):
        def __init__(self, *args, **kwargs):
            alive_when_summing.append(watcher.alive(kwargs.get("sums")))
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(sink, "Accumulator", Watched)
    monkeypatch.setattr(vote, "Accumulator", Watched)
    scene, cams = inputs
    options = RegisterOptions(block_size=1024, aggregate=aggregate)
    run_registration(prepare_run(scene, cams, tiny / "features", options), watcher, checkpoint=tmp_path / "log", show_progress=False)
    assert len(watcher.refs) == -(-scene.num_gaussians // 1024) > 1
    assert alive_when_summing and max(alive_when_summing) == 0, alive_when_summing


def test_a_scene_codebook_keeps_a_bounded_share_of_the_masks_the_same_in_every_plan(tiny, inputs, tmp_path, monkeypatch):
    """Every used mask's embedding was kept for `--codebook scene` (40 views x 4,000 masks: 1.1 GB over
    the plan), though faiss trains on 65,536 at most; now every k-th used mask in view order, at most
    SCENE_TRAIN_MAX, chosen the same way in one block and in blocks (same file, same codebook)."""
    from drsplat.registration import driver
    from drsplat.registration.views import read_feature_headers

    scene, cams = inputs
    total = read_feature_headers(tiny / "features", cams, 1).total_masks
    cap = max(1, total // 3)
    monkeypatch.setattr(driver, "SCENE_TRAIN_MAX", cap)
    seen = []
    training_set = driver.scene_training_set

    def spy(masks, sample, dim):
        seen.append(masks.shape[0])
        return training_set(masks, sample, dim)

    monkeypatch.setattr(driver, "scene_training_set", spy)
    a, b = tmp_path / "one" / "reg.ply", tmp_path / "blocks" / "reg.ply"
    register(scene, cams, tiny / "features", a, RegisterOptions(codebook="scene"), show_progress=False)
    register(scene, cams, tiny / "features", b, RegisterOptions(codebook="scene", block_size=1024), show_progress=False)
    assert seen[0] == seen[1] and 0 < seen[0] <= cap < total
    assert a.read_bytes() == b.read_bytes()
    assert (a.parent / "reg.codebook.faiss").read_bytes() == (b.parent / "reg.codebook.faiss").read_bytes()


def test_a_budget_beyond_the_free_memory_is_followed_with_one_warning(inputs, caplog):
    """Round 63b: `--memory-budget 1e300` was taken without a word (the run may be killed midway), where no budget is
    refused with the figure that fits. The budget is still followed; one warning names what is free."""
    from drsplat.memory import current_rss

    scene, cams = inputs

    class Big:
        num_gaussians = 5_000_000
        sh = np.zeros((1, 1, 3))

    plan = estimate_memory(Big(), cams, 512, 40, base=400 << 20)
    free = 6 * 10**9 - current_rss()
    with caplog.at_level("WARNING", logger="drsplat.registration.plan"):
        assert choose_block(plan, 64 * 10**9, available=free) == 5_000_000
        assert choose_block(plan, 5 * 10**9, available=free) > 0  # within what is free: blocks, no warning
    warned = [r.getMessage() for r in caplog.records]
    assert len(warned) == 1 and "lets this run use about" in warned[0] and "more than the 6.0 GB this machine has free now" in warned[0]


def test_a_run_in_one_block_logs_its_estimate_too(tiny, inputs, caplog):
    """Round 63b: the estimate was logged only for runs in blocks; a run in one block said nothing of its memory."""
    scene, cams = inputs
    with caplog.at_level("INFO", logger="drsplat.registration.driver"):
        register_features(scene, cams, tiny / "features", RegisterOptions(topk=5, aggregate="paper"), show_progress=False)
    said = [r.getMessage() for r in caplog.records if r.getMessage().startswith("estimated peak memory")]
    assert len(said) == 1 and re.fullmatch(r"estimated peak memory: [0-9.]+ [kMG]B, in one block", said[0]), said  # the size: the process's


def test_a_damaged_first_record_is_said_to_start_from_scratch(tiny, inputs, tmp_path, caplog):
    """Round 89b F2: a damaged first record was said as "resuming from the 0 views before it"; the run starts over,
    and says so, to the same features."""
    scene, cams = inputs
    full = register_features(scene, cams, tiny / "features", LOG_ONLY, show_progress=False)
    ckpt = tmp_path / "run.log"
    _cancelled_log(tiny, inputs, ckpt, 3)
    _rewrite_record_meta(ckpt, 0, lambda m: {**m, "pairs": "many"})
    with caplog.at_level(logging.WARNING):
        resumed = register_features(scene, cams, tiny / "features", LOG_ONLY, checkpoint=ckpt, show_progress=False)
    assert "record 1 is damaged (its checksum, length or meta does not match); starting from scratch" in caplog.text, caplog.text
    assert "0 views" not in caplog.text and resumed.resumed_views == 0
    np.testing.assert_array_equal(resumed.features, full.features)


@pytest.mark.parametrize("aggregate", [None, "solve-reject"], ids=["default", "solve"])
def test_gaussians_left_unrendered_are_said_once_a_registration_with_their_cause(tiny, inputs, tmp_path, capsys, aggregate):
    """Round 89d F4: ten Gaussians whose log scale overflows float32 were said three times by `register` (the frame
    check's sample, the fit stage's geometry, once per chunk of it), as "non-finite attributes" without that cause;
    a solve mode said it once more, preparing the scene again for its re-renders (round 90b F1)."""
    import dataclasses

    from drsplat.cli import main
    from drsplat.scene import save_ply

    scene, _ = inputs
    log_scales = scene.log_scales.copy()
    log_scales[:10, 0] = 100.0
    save_ply(dataclasses.replace(scene, log_scales=log_scales), tmp_path / "big.ply")
    assert main(["register", str(tmp_path / "big.ply"), "--source", str(tiny), "--features", str(tiny / "features"), "--out",
                 str(tmp_path / "reg.ply"), "--topk", "10", "--no-progress", *(["--aggregate", aggregate] if aggregate else [])]) == 0
    said = [line for line in capsys.readouterr().err.splitlines() if "are not rendered" in line]
    assert len(said) == 1 and f"10 of {scene.num_gaussians} Gaussians have non-finite attributes" in said[0], said
    assert "a log scale above 88.7 whose scale overflows float32" in said[0]
    registered = load_ply(tmp_path / "reg.ply")
    assert registered.num_gaussians < scene.num_gaussians  # the ten, never rendered, are pruned with the other unseen ones
