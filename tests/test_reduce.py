"""The partitioned reduce (drsplat.registration.reduce): blocks finished by Ray reducer tasks.

On a two-node Ray cluster started inside a fixture (tests/test_distributed.py's), a run on Ray in
blocks must write the local in-memory run's bytes, whatever the mode and codebook; `lang_meta`
must be numbered as in a single write across blocks that keep some, all or no rows, and in a short
file; a failing reducer must name its block and leave the checkpoint that resumes. The assembling
step is also tested without Ray, against PlyTarget on the same blocks.
"""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import numpy as np
import pytest

from drsplat.cameras import load_cameras
from drsplat.errors import DrsplatError
from drsplat.registration import RegisterOptions, register
from drsplat.registration.checkpoint import checkpoint_path_for
from drsplat.registration.output import PlyTarget, _meta_period
from drsplat.registration.aggregate import SurfaceSupport, ViewStats
from drsplat.registration.pairlog import PairLog, ShardWriter, ViewPairs
from drsplat.registration.reduce import ReduceJob, assemble_parts, block_support, reduce_block
from drsplat.registration.sink import LogSink
from drsplat.registration.sums import normalize_rows
from drsplat.scene import GaussianScene, load_ply
from drsplat.synthetic import write_dataset

try:  # imported with the module, as tests/test_distributed.py does: importing ray sets RAY_CLIENT_MODE once
    import ray
except ImportError:  # the tests without Ray still run
    ray = None


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("tiny") / "data", "tiny", 0, show_progress=False)


@pytest.fixture(scope="module")
def general_book(tmp_path_factory) -> Path:
    """A tiny faiss PQ codebook file (512-D, 16 sub-quantisers), as a user's general codebook."""
    from drsplat.lang import train_codebook

    path = tmp_path_factory.mktemp("book") / "general.faiss"
    train_codebook(np.random.default_rng(0).normal(size=(3000, 512)).astype(np.float32), m=16).save(path)
    return path


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _register_both(scene, cams, features, tmp_path: Path, **options) -> tuple[Path, Path, object]:
    local, on_ray = tmp_path / "local" / "reg.ply", tmp_path / "ray" / "reg.ply"
    register(scene, cams, features, local, RegisterOptions(**options), show_progress=False)
    result = register(scene, cams, features, on_ray, RegisterOptions(ray="auto", ray_workers=2, block_size=1024, **options), show_progress=False)
    return local, on_ray, result


# ----------------------------------------------------------------------------- on a Ray cluster


@pytest.fixture(scope="module")
def cluster():
    """A two-node Ray cluster on this machine (tests.ray_cluster); the driver joins it."""
    if ray is None:
        pytest.skip("the partitioned reduce needs the optional ray package (pip install -e '.[ray]')")
    from tests.ray_cluster import two_node_cluster

    with two_node_cluster() as c:
        yield c


# pairwise, not the full product: each codebook and each mode once (every mode on Ray: tests/test_distributed.py)
@pytest.mark.parametrize(("book", "aggregate"), [("none", "paper"), ("faiss", "vote-reject")])
def test_reducers_write_the_local_in_memory_bytes(cluster, tiny, general_book, tmp_path, aggregate, book):
    scene, cams = load_ply(tiny / "scene.ply"), load_cameras(tiny)
    codebook = str(general_book) if book == "faiss" else "none"
    local, on_ray, result = _register_both(scene, cams, tiny / "features", tmp_path, aggregate=aggregate, codebook=codebook)
    assert result.reducers and result.num_blocks == -(-scene.num_gaussians // 1024) >= 3
    assert sha(on_ray) == sha(local)
    if book == "faiss":
        assert (on_ray.parent / "reg.codebook.faiss").read_bytes() == (local.parent / "reg.codebook.faiss").read_bytes()
    assert result.worker_peak_rss  # the reducers' workers reported
    assert not [p.name for p in on_ray.parent.iterdir() if p.name != "reg.ply" and not p.name.endswith(".faiss")]  # no parts, no log left


def test_scene_codebook_from_the_reducers_sample_gives_the_local_bytes(cluster, tiny, tmp_path):
    """--codebook scene: the reducers sum the training sample (one task per block), the same rows as the driver's sink."""
    scene, cams = load_ply(tiny / "scene.ply"), load_cameras(tiny)
    local, on_ray, result = _register_both(scene, cams, tiny / "features", tmp_path, codebook="scene")
    assert result.reducers
    assert (on_ray.parent / "reg.codebook.faiss").read_bytes() == (local.parent / "reg.codebook.faiss").read_bytes()
    assert sha(on_ray) == sha(local)


def test_a_check_mode_judged_from_the_reducers_support_gives_the_local_bytes(cluster, tmp_path_factory, tmp_path, monkeypatch):
    """--aggregate check-vote-reject with --codebook scene on mislabelled masks: the reducers sum
    their blocks' parts of the support tables, the driver adds them, judges the masks and makes the
    kept masks' clusters from the masks each view reported present (its own replays of the log are
    made to fail here), the reducers sum the kept pairs, the codebook's sample included: the local run's
    bytes, with the driver's support tables spilled to disk (capped at nothing) as well."""
    import drsplat.registration.check as check

    data = write_dataset(tmp_path_factory.mktemp("mislabelled") / "data", "tiny", 0, mislabel_fraction=0.3, show_progress=False)
    scene, cams = load_ply(data / "scene.ply"), load_cameras(data)
    local, on_ray = tmp_path / "local" / "reg.ply", tmp_path / "ray" / "reg.ply"
    options = dict(codebook="scene", aggregate="check-vote-reject")
    register(scene, cams, data / "features", local, RegisterOptions(**options), show_progress=False)

    def replayed_on_the_driver(*args, **kwargs):
        raise AssertionError("the driver replayed the log")

    monkeypatch.setattr(check, "view_supports", replayed_on_the_driver)  # the support tables
    monkeypatch.setattr(check, "SUPPORT_TABLE_BYTES", 0)  # the reducers' files are read where they lie, not read in
    monkeypatch.setattr(check.KeptPairs, "block_views", replayed_on_the_driver)  # the kept pairs (the reducers' processes read them)
    result = register(scene, cams, data / "features", on_ray, RegisterOptions(ray="auto", ray_workers=2, block_size=1024, **options),
                      show_progress=False)
    monkeypatch.undo()
    plain = tmp_path / "plain" / "reg.ply"  # the check drops masks here: without it the file differs
    register(scene, cams, data / "features", plain, RegisterOptions(codebook="scene", aggregate="vote-reject"), show_progress=False)
    assert result.reducers and sha(plain) != sha(local)
    assert (on_ray.parent / "reg.codebook.faiss").read_bytes() == (local.parent / "reg.codebook.faiss").read_bytes()
    assert sha(on_ray) == sha(local)


def _with_unseen_block(scene: GaussianScene) -> GaussianScene:
    """The scene with 1024 copies of its first Gaussians far behind every camera inserted as rows
    1024 .. 2047: with blocks of 1024 the second block keeps no row."""
    order = np.concatenate([np.arange(1024), np.arange(1024), np.arange(1024, scene.num_gaussians)])
    out = scene.subset(order)
    means = np.array(out.means)
    means[1024:2048] += np.float32(1e6)
    return dataclasses.replace(out, means=means)


def test_meta_column_across_blocks_with_an_empty_one(cluster, tiny, tmp_path):
    scene, cams = _with_unseen_block(load_ply(tiny / "scene.ply")), load_cameras(tiny)
    local, on_ray, result = _register_both(scene, cams, tiny / "features", tmp_path)
    assert result.reducers and not result.weights[1024:2048].any() and result.weights[:1024].any() and result.weights[2048:].any()
    assert sha(on_ray) == sha(local)
    written = load_ply(on_ray)
    assert written.num_gaussians == result.num_written == result.num_assigned
    period = _meta_period(written.comments)
    np.testing.assert_array_equal(written.extra["lang_meta"], period[np.arange(written.num_gaussians) % period.shape[0]])


def test_short_file_gets_the_widened_meta_columns(cluster, tiny, tmp_path):
    """Fewer kept rows than the field comment's bytes, spread over blocks: the widened columns of a single write."""
    scene, cams = load_ply(tiny / "scene.ply"), load_cameras(tiny)
    full = register(scene, cams, tiny / "features", tmp_path / "all.ply", RegisterOptions(), show_progress=False)
    assigned = np.flatnonzero(full.weights > 0)
    kept = np.r_[assigned[assigned < 1024][:8], assigned[assigned >= 2048][:8]]  # blocks 0 and 2; the rest moved out of sight
    means = np.array(scene.means)
    far = np.ones(scene.num_gaussians, bool)
    far[kept] = False
    means[far] += np.float32(1e6)
    few = dataclasses.replace(scene, means=means)
    local, on_ray, result = _register_both(few, cams, tiny / "features", tmp_path)
    written = load_ply(on_ray)
    assert result.reducers and 0 < result.num_written < _meta_period(written.comments).shape[0]
    assert "lang_meta_1" in written.extra
    assert sha(on_ray) == sha(local)


def _failing_reduce_task(job, scene, codebook, index):
    """A reducer whose block 1 fails (runs on a worker: imported there by reference)."""
    if index == 1:
        raise RuntimeError("the disk under block 1 is gone")
    from drsplat.registration.reduce import _reduce_task

    return _reduce_task(job, scene, codebook, index)


def test_a_failing_reducer_names_its_block_and_the_checkpoint_resumes(cluster, tiny, tmp_path, monkeypatch):
    scene, cams = load_ply(tiny / "scene.ply"), load_cameras(tiny)
    local = tmp_path / "local.ply"
    register(scene, cams, tiny / "features", local, RegisterOptions(), show_progress=False)
    out = tmp_path / "ray" / "reg.ply"
    options = RegisterOptions(ray="auto", ray_workers=2, block_size=1024)
    monkeypatch.setattr("drsplat.registration.reduce._reduce_task", _failing_reduce_task)
    with pytest.raises(DrsplatError, match=r"reducer of block 1 \(Gaussians 1,024\.\.2,047\) failed: RuntimeError: the disk under block 1"):
        register(scene, cams, tiny / "features", out, options, show_progress=False)
    monkeypatch.undo()
    assert not out.exists() and checkpoint_path_for(out).exists()
    # the parts folder is gone; the workers' shards of the log stay with the checkpoint
    assert [p.name for p in out.parent.iterdir() if p.is_dir()] == [checkpoint_path_for(out).name + ".shards"]
    resumed = register(scene, cams, tiny / "features", out, options, show_progress=False)
    assert resumed.resumed_views == len(cams) and resumed.reducers
    assert sha(out) == sha(local) and not checkpoint_path_for(out).exists()


def test_a_run_cancelled_while_reducers_run_keeps_its_checkpoint(cluster, tiny, tmp_path):
    from drsplat.errors import Cancelled
    from drsplat.utils import CancelToken

    scene, cams = load_ply(tiny / "scene.ply"), load_cameras(tiny)
    out = tmp_path / "reg.ply"
    options = RegisterOptions(ray="auto", ray_workers=2, block_size=1024)
    token = CancelToken()

    def cancel_after_the_views(done: int, total: int) -> None:
        if done == total:
            token.cancel()

    with pytest.raises(Cancelled):
        register(scene, cams, tiny / "features", out, options, on_progress=cancel_after_the_views, cancel=token, show_progress=False)
    assert not out.exists() and checkpoint_path_for(out).exists()
    # the workers logged the views' pairs in their shards; the driver's log holds a pointer per view and no pair
    records = _logged_records(checkpoint_path_for(out))
    assert [r.name for r in records] == [c.name for c in cams]
    assert all(r.meta["P"] == 0 and r.meta["shard"]["file"].startswith(".reg.ply.register.log.shards/") for r in records)
    assert sum(r.meta["shard"]["meta"]["P"] for r in records) > 0 and all("T" in r.meta["shard"]["meta"] for r in records)
    assert register(scene, cams, tiny / "features", out, options, show_progress=False).resumed_views == len(cams)
    assert not checkpoint_path_for(out).exists() and not [p for p in tmp_path.iterdir() if p.name != "reg.ply"]


def _logged_records(path: Path) -> list:
    """The records of the pair log at `path`, opened with the parameters in its own header."""
    import json
    import struct

    with open(path, "rb") as f:
        f.read(8)
        (n,) = struct.unpack("<Q", f.read(8))
        params = json.loads(f.read(n))
    with PairLog.open(path, params) as plog:
        return list(plog.records)


def test_without_reducers_the_driver_finishes_the_same_bytes(cluster, tiny, tmp_path):
    scene, cams = load_ply(tiny / "scene.ply"), load_cameras(tiny)
    local, on_ray, result = _register_both(scene, cams, tiny / "features", tmp_path, reducers=False)
    assert not result.reducers and sha(on_ray) == sha(local)


# ----------------------------------------------------------------------------- without Ray


def _random_log(path: Path, n: int, dim: int, views: int, seed: int, seen: np.ndarray) -> PairLog:
    """A pair log of random views whose pairs touch only the Gaussians `seen` [n] bool."""
    rng = np.random.default_rng(seed)
    plog = PairLog.open(path, {"test": seed})
    ids = np.flatnonzero(seen)
    for v in range(views):
        m = int(rng.integers(1, 6))
        p = int(rng.integers(0, 3 * ids.size + 1))
        g = rng.choice(ids, size=p).astype(np.int32)
        feats = rng.normal(size=(m, dim)).astype(np.float32)
        plog.append(ViewPairs(f"v{v}", feats, g, rng.integers(0, m, p).astype(np.int32), rng.uniform(1e-3, 1, p).astype(np.float32),
                              np.arange(m, dtype=np.int32), p))
    return plog


@pytest.mark.parametrize("case", ["empty_middle_block", "short_file"])
def test_assembled_parts_equal_a_single_write(tmp_path, case):
    """reduce_block per block + assemble_parts = PlyTarget fed by LogSink, byte for byte: lang_meta
    renumbered across parts (one keeps no row), and a file shorter than the comment widened."""
    n, dim, block = 300, 16, 100
    rng = np.random.default_rng(1)
    scene = GaussianScene(means=rng.normal(size=(n, 3)).astype(np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                          log_scales=np.full((n, 3), -3, np.float32), opacity_logits=np.zeros(n, np.float32), sh=np.zeros((n, 1, 3), np.float32))
    seen = np.ones(n, bool)
    if case == "empty_middle_block":
        seen[100:200] = False
    else:
        seen[:] = False
        seen[[3, 7, 150, 151, 290]] = True
    plog = _random_log(tmp_path / "pairs.log", n, dim, 5, 2, seen)
    plog.sync()
    expected = tmp_path / "single" / "reg.ply"
    expected.parent.mkdir()
    target = PlyTarget(scene, expected, "oracle")
    target.open("none")
    for b in LogSink(n, dim, plog, block).blocks():
        normalize_rows(b.F, b.W)
        target.add(b, b.W > 0)
    written = target.close()
    out = tmp_path / "parts" / "reg.ply"
    out.parent.mkdir()
    parts_dir = tmp_path / "parts" / "p"
    parts_dir.mkdir()
    job = ReduceJob(str(plog.path), plog.params, list(plog.records), n, dim, block, False, None, str(out), "oracle", str(parts_dir))
    parts = [reduce_block(job, scene, "none", i) for i in range(job.num_blocks)]
    rows = [p.rows for p in parts]
    assert sum(rows) == written and (rows[1] == 0 < rows[0] if case == "empty_middle_block" else 0 < written < 60)
    assert assemble_parts(out, parts) == written
    assert out.read_bytes() == expected.read_bytes()
    if case == "short_file":
        assert "lang_meta_1" in load_ply(out).extra
    # the codebook beside the output is written after the body, just before the rename (round 40): a copy that fails
    # leaves it, and the earlier output, as they were
    from drsplat.registration import reduce as reduce_module

    written_books = []
    with pytest.MonkeyPatch.context() as m:
        m.setattr(reduce_module, "write_codebook_of", lambda book, path: written_books.append((book, path)))
        assert assemble_parts(out, parts, "BOOK") == written and written_books == [("BOOK", out)]

        def full_disk(*args):
            raise OSError(28, "No space left on device")

        m.setattr(reduce_module, "_copy_parts", full_disk)
        m.setattr(reduce_module.shutil, "copyfileobj", full_disk)
        with pytest.raises(OSError):
            assemble_parts(out, parts, "BOOK")
    assert written_books == [("BOOK", out)] and out.read_bytes() == expected.read_bytes()


def test_a_log_the_reducer_cannot_read_is_one_clear_error(tmp_path):
    job = ReduceJob(str(tmp_path / "elsewhere" / "pairs.log"), {}, [], 10, 4, 5, False, None, str(tmp_path / "o.ply"), "oracle", str(tmp_path))
    with pytest.raises(DrsplatError, match=r"reducer of block 1 \(Gaussians 5\.\.9\).*cannot read the pair log .*elsewhere/pairs\.log.*storage every Ray node shares"):
        reduce_block(job, None, "none", 1)
    other = PairLog.open(tmp_path / "other.log", {"a": 1})
    other.close()
    job = dataclasses.replace(job, log_path=str(tmp_path / "other.log"), params={"a": 2})
    with pytest.raises(DrsplatError, match="other parameters"):
        reduce_block(job, None, "none", 0)


# ----------------------------------------------------------------------------- the workers' shards (without Ray)


def _view_with_stats(rng, name: str, n: int, dim: int) -> ViewPairs:
    """A random view over Gaussians 0 .. n-1 (several 2^16 chunks) with floater statistics: each seen
    Gaussian once, a third of them faint and mostly in front (rejected once every view agrees)."""
    m = int(rng.integers(1, 5))
    p = int(rng.integers(0, 4000))
    g = rng.integers(0, n, p).astype(np.int32)
    seen = rng.permutation(np.unique(np.r_[g, rng.integers(0, n, 500)]).astype(np.int32))  # any order, as the hook's first-seen order
    total = rng.uniform(0.01, 2.0, seen.size)
    faint = (seen % 3) == 0
    peak = np.where(faint, 0.1, rng.uniform(0.0, 1.0, seen.size))
    front = np.where(faint, 0.9, rng.uniform(0.0, 1.0, seen.size)) * total
    return ViewPairs(name, rng.normal(size=(m, dim)).astype(np.float32), g, rng.integers(0, m, p).astype(np.int32),
                     rng.uniform(1e-3, 1, p).astype(np.float32), np.arange(m, dtype=np.int32), p,
                     stats=ViewStats(seen, peak, total, front))


def test_shard_pointers_give_the_workers_pairs_and_the_driver_statistics(tmp_path):
    """Two workers log views in shards, the driver logs pointers: every block reads the pairs a
    whole log holds, and the statistics folded per block are the driver's fold of the whole views,
    bit for bit, so the rejected mask is the same."""
    n, dim = 200_000, 8
    rng = np.random.default_rng(3)
    params = {"test": "shards"}
    folder = tmp_path / "reg.log.shards"
    writers = [ShardWriter(folder, params) for _ in range(2)]
    pointers, whole = PairLog.open(tmp_path / "reg.log", params), PairLog.open(tmp_path / "whole.log", params)
    support = SurfaceSupport.zeros(n)
    for v in range(7):
        view = _view_with_stats(rng, f"v{v}", n, dim)
        whole.append(view)
        support.add(view.stats)
        pointer = writers[v % 2].write(view)
        assert pointer.gaussians.size == 0 and pointer.stats is None and pointer.num_distinct == view.num_distinct
        np.testing.assert_array_equal(pointer.present, np.isin(np.arange(view.feats.shape[0]), view.masks))
        pointers.append(pointer)
    for w in writers:
        w.sync()
    assert len({p.name for p in folder.iterdir()}) == 2
    assert all(r.meta["P"] == 0 and "shard" in r.meta for r in pointers.records)  # the driver's log holds no pair
    assert support.rejected().any() and not support.rejected().all()
    reader = PairLog.reader(pointers.path, params, pointers.records)  # a reducer's view of it
    for lo, hi in [(0, n), (70_000, 140_000), (65_535, 65_537), (n - 10, n)]:
        for a, b in zip(reader.block_views(lo, hi), whole.block_views(lo, hi)):
            for name in ("gaussians", "masks", "weights", "feats"):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        got = block_support(reader, lo, hi)
        for name, values in support.arrays().items():
            np.testing.assert_array_equal(getattr(got, name), values[lo:hi])
        np.testing.assert_array_equal(got.rejected(), support.rejected()[lo:hi])
    replayed = list(reader)  # a resumed driver's replay: pointers with the masks that reached a Gaussian
    assert [v.num_distinct for v in replayed] == [r.meta["shard"]["meta"]["P"] for r in pointers.records]
    assert all(v.present is not None and v.gaussians.size == 0 for v in replayed)
    reader.close()
    with pytest.raises(ValueError, match="holds no floater statistics"):
        block_support(whole, 0, n)
    # a reducer on a node that does not see a shard: one error naming the block, the file and the storage it needs
    (tmp_path / writers[1].file).unlink()
    job = ReduceJob(str(pointers.path), params, list(pointers.records), n, dim, n // 2, False, None, str(tmp_path / "o.ply"), "oracle",
                    str(tmp_path), reject=True)
    with pytest.raises(DrsplatError, match=rf"reducer of block 1 \(Gaussians 100,000\.\.199,999\).*{writers[1].file}: the worker's shard "
                                           r"holding view v1 cannot be read \(No such file or directory\).*storage every Ray node shares"):
        reduce_block(job, None, "none", 1)


def test_a_resume_keeps_the_views_whose_shard_records_are_there(tmp_path, caplog):
    from drsplat.registration.aggregate import Aggregator
    from drsplat.registration.checkpoint import Checkpoint
    from drsplat.registration.pairlog import shards_folder as shards_path
    from drsplat.cameras import Camera

    n, dim = 1000, 4
    rng = np.random.default_rng(4)
    scene = GaussianScene(means=rng.normal(size=(n, 3)).astype(np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                          log_scales=np.full((n, 3), -3, np.float32), opacity_logits=np.zeros(n, np.float32), sh=np.zeros((n, 1, 3), np.float32))
    cams = [Camera(np.eye(3), np.zeros(3), 8.0, 8.0, 4.0, 4.0, 8, 8, name=f"v{i}") for i in range(6)]
    params = {"shards": True, "test": 1}
    path = tmp_path / "reg.log"

    def checkpoint() -> Checkpoint:
        return Checkpoint(path, params, cams, Aggregator("vote-reject", scene, stats_on_reducers=True))

    ckpt = checkpoint()
    assert ckpt.shards_dir == shards_path(path) and ckpt.shards_dir.is_dir() and ckpt.resumed == 0
    writers = [ShardWriter(ckpt.shards_dir, params) for _ in range(2)]
    for i, cam in enumerate(cams):
        ckpt.append(writers[i % 2].write(_view_with_stats(rng, cam.name, n, dim)))
    for w in writers:
        w.sync()
        w.close()
    ckpt.close()
    assert checkpoint().resumed == 6
    cut = tmp_path / writers[1].file  # views 1, 3, 5: the shard loses its last record's tail
    with open(cut, "r+b") as f:
        f.truncate(cut.stat().st_size - 10)
    again = checkpoint()
    assert again.resumed == 5 and "view v5 needs" in caplog.text
    again.close()
    replaced = tmp_path / writers[0].file  # views 0, 2, 4: another file of the same size at that path
    replaced.write_bytes(bytes(replaced.stat().st_size))
    assert checkpoint().resumed == 0 and "view v0 needs a record of" in caplog.text
    assert not list(shards_path(path).iterdir())  # a fresh log starts with an empty folder


def test_a_pointer_that_leads_out_of_the_shards_folder_is_refused(tmp_path, caplog):
    """A log whose pointer names a path outside its shards folder (edited by hand, or hostile:
    '../', an absolute path, a nested folder): a resume reads nothing there and starts over, and a
    reducer's read is one ShardError naming the pointer; the file outside is never opened."""
    from drsplat.registration.pairlog import ShardError

    n, dim = 1000, 4
    params = {"test": "hostile"}
    outside = tmp_path / "secret.log"
    outside.write_bytes(b"DRSPLOG2 not yours")
    writer = ShardWriter(tmp_path / "reg.log.shards", params)
    good = writer.write(_view_with_stats(np.random.default_rng(5), "v0", n, dim))
    writer.sync()
    for name in ("../secret.log", str(outside), "reg.log.shards/sub/x.log", "other.shards/x.log", "reg.log.shards/.."):
        plog = PairLog.open(tmp_path / "reg.log", params)
        plog.truncate(0)
        plog.append(dataclasses.replace(good, shard={**good.shard, "file": name}))
        with pytest.raises(ShardError, match=r"pointer names .* not a shard in reg\.log\.shards"):
            plog.read_block(plog.records[0], 0, n)
        plog.close()
        from drsplat.registration.checkpoint import _shard_record_problem

        assert "which is not a file of reg.log.shards" in _shard_record_problem(tmp_path / "reg.log", plog.records[0].meta["shard"], {})
    writer.close()


@pytest.mark.parametrize("bad", [{"start": -5}, {"start": "12"}, {"offset": 10**30}, {"start": 10**30}, {"meta": None}, {"meta": {"M": 1}},
                                 {"offset": 3}, "meta-counts"], ids=str)
def test_a_malformed_pointer_is_refused_before_any_read(tmp_path, bad):
    """A pointer's offsets and counts come from a file: negative, non-integer, huge or inconsistent
    ones (a log edited by hand or hostile) give one ShardError naming the shard on a reducer's read,
    and a resume starts over with a warning, instead of a seek error or a read of 10^30 bytes."""
    from drsplat.registration.checkpoint import _shard_record_problem
    from drsplat.registration.pairlog import ShardError

    n, dim, params = 1000, 4, {"test": "malformed"}
    writer = ShardWriter(tmp_path / "reg.log.shards", params)
    good = writer.write(_view_with_stats(np.random.default_rng(6), "v0", n, dim))
    writer.sync()
    if bad == "meta-counts":  # the shard's own counts, grown: they no longer match its record
        ref = {**good.shard, "meta": {**good.shard["meta"], "P": 10**12}}
    else:
        ref = {**good.shard, **bad}
    plog = PairLog.open(tmp_path / "reg.log", params)
    plog.append(dataclasses.replace(good, shard=ref))
    shard = tmp_path / writer.file
    with pytest.raises(ShardError, match=rf"{shard.name}: the (pointer to it is malformed|record is not there)"):
        plog.read_block(plog.records[0], 0, n)
    problem = _shard_record_problem(tmp_path / "reg.log", ref, {})
    assert problem.startswith(f"needs a record of {shard}, but the ")
    plog.truncate(0)  # the unaltered pointer reads the view
    plog.append(good)
    assert plog.read_block(plog.records[0], 0, n).gaussians.size == good.num_distinct
    assert _shard_record_problem(tmp_path / "reg.log", good.shard, {}) is None
    plog.close()
    writer.close()


def test_a_killed_temporary_runs_shards_are_swept(tmp_path):
    """A run in blocks without a checkpoint logs into a temp file; its shards' folder is a temp folder of
    the output too, so the next run writing that output removes a killed run's."""
    from drsplat.registration.pairlog import shards_folder as shards_path
    from drsplat.utils import sweep_stale_temps

    dead = 2**22 + 12345  # above Linux's default pid_max: no live process has it
    folder = shards_path(tmp_path / f".reg.ply.{dead}.ab12cd.tmp")
    assert folder.name == f".reg.ply.{dead}.ab12cd.shards.tmp"
    folder.mkdir()
    (folder / "host-1-abc.log").write_bytes(b"x")
    assert sweep_stale_temps(tmp_path / "reg.ply") == 1 and not folder.exists()


def test_a_worker_that_cannot_write_its_shard_names_its_node(tmp_path, monkeypatch):
    """A view worker whose node does not see the checkpoint's folder (here: the shard folder lies
    under a file) reports it in one sentence for every call, naming the node and the folder,
    instead of a dead worker's traceback. The actor class runs in this process: the object store
    is replaced by the objects themselves."""
    import socket
    from types import SimpleNamespace

    import drsplat.registration.ray as ray_module
    from drsplat.registration.compute import ViewJob, prepare_geometry

    data = write_dataset(tmp_path / "data", "tiny", 0, show_progress=False)
    scene, cams = load_ply(data / "scene.ply"), load_cameras(data)
    blocked = tmp_path / "a-file"
    blocked.write_text("not a folder")
    job = ViewJob(data / "features", 0, 8, shard_dir=str(blocked / "reg.ply.register.log.shards"), log_params={"test": 1})
    monkeypatch.setattr(ray_module, "import_ray", lambda: SimpleNamespace(get=lambda refs: refs))
    monkeypatch.setattr(ray_module, "set_worker_threads", lambda: None)  # a Ray worker's thread count: not this process's
    worker = ray_module._ViewWorker()
    for _ in range(2):  # the reason is kept: every later call gives it again
        result = worker.compute([prepare_geometry(scene), job, None], cams[:1])
        assert result.views == [] and isinstance(result.error, DrsplatError)
        assert f"worker on node {socket.gethostname()} cannot write its shard of the log in {blocked}" in str(result.error)
        assert "storage every Ray node shares at the same path" in str(result.error)


def test_a_damaged_shard_record_is_cut_back_on_resume(tmp_path, caplog):
    """A flipped byte inside a shard record's payload (its length intact): a resume used to keep the
    view and feed the reducers the damaged weights (a changed output, exit 0). The record's checksum
    is now checked, and the log cut back to the views before it."""
    from drsplat.cameras import Camera
    from drsplat.registration.aggregate import Aggregator
    from drsplat.registration.checkpoint import Checkpoint

    n, dim = 1000, 4
    rng = np.random.default_rng(8)
    scene = GaussianScene(means=rng.normal(size=(n, 3)).astype(np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                          log_scales=np.full((n, 3), -3, np.float32), opacity_logits=np.zeros(n, np.float32), sh=np.zeros((n, 1, 3), np.float32))
    cams = [Camera(np.eye(3), np.zeros(3), 8.0, 8.0, 4.0, 4.0, 8, 8, name=f"v{i}") for i in range(4)]
    params = {"shards": True, "test": "crc"}
    path = tmp_path / "reg.log"

    def checkpoint() -> Checkpoint:
        return Checkpoint(path, params, cams, Aggregator("vote-reject", scene, stats_on_reducers=True))

    ckpt = checkpoint()
    writer = ShardWriter(ckpt.shards_dir, params)
    for cam in cams:
        ckpt.append(writer.write(_view_with_stats(rng, cam.name, n, dim)))
    writer.sync()
    writer.close()
    pointer = ckpt.log.records[2].meta["shard"]
    ckpt.close()
    shard = tmp_path / writer.file
    with open(shard, "r+b") as f:
        f.seek(pointer["offset"] + 7)
        byte = f.read(1)
        f.seek(pointer["offset"] + 7)
        f.write(bytes([byte[0] ^ 0x40]))
    again = checkpoint()
    assert again.resumed == 2 and "view v2 needs a record of" in caplog.text and "checksum does not match" in caplog.text
    again.close()
