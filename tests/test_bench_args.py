"""Bad input to `drsplat bench ...`: one error line naming the flag or file, never a traceback;
exit 2 for a bad flag (before any work), exit 1 for bad data; no bench writes over a file it
reads (the ones its command line does not name too: a default scene, a cached codebook, the
negatives beside --official, a --room's files); an unwritable output is found before the work."""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from drsplat.cli import main


def run_cli(argv: list, capsys) -> tuple[int, str, str]:
    """(exit code, stderr, stdout) of `drsplat argv`; argparse's SystemExit becomes its code."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:
        code = exc.code
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err, captured.err
    return code, captured.err, captured.out


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("ERROR") or ": error:" in line]


def digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@pytest.fixture(autouse=True)
def in_tmp(tmp_path, monkeypatch):
    """Each test in its own folder: a default output (bench_query.png) and its writability probe land there."""
    monkeypatch.chdir(tmp_path)


@pytest.fixture
def no_work(monkeypatch):
    """Every bench's first piece of real work fails the test: a refusal must come before it."""
    import drsplat.bench.budget as budget
    import drsplat.bench.query as query
    import drsplat.bench.register as register
    import drsplat.bench.scale as scale

    def forbidden(*args, **kwargs):
        raise AssertionError("the bench started its work before refusing its input")

    monkeypatch.setattr(query.EmbeddingModel, "create", classmethod(forbidden))
    monkeypatch.setattr(query, "train_books", forbidden)
    monkeypatch.setattr(register, "synthetic_table", forbidden)
    monkeypatch.setattr(register, "blob_scene", forbidden)
    monkeypatch.setattr(budget, "run_case", forbidden)
    for part in ("_compare", "_rss", "_big", "_replay"):
        monkeypatch.setattr(scale, part, forbidden)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> dict[int, Path]:
    """PLY files of 0, 1 and 2 Gaussians."""
    from drsplat.scene import save_ply
    from drsplat.testing import gaussians

    folder = tmp_path_factory.mktemp("scenes")
    scene = gaussians(np.random.default_rng(0).normal(size=(2, 3)), log_scale=-1.5, opacity_logit=5.0)  # large enough to cover pixels
    out = {}
    for n in (0, 1, 2):
        out[n] = folder / f"g{n}.ply"
        save_ply(scene.subset(slice(0, n)), out[n])
    return out


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    """A written `tiny` synthetic dataset (scene.ply, transforms.json, features/)."""
    from drsplat.synthetic import write_dataset

    return write_dataset(tmp_path_factory.mktemp("room") / "tiny", "tiny", 0, show_progress=False)


@pytest.fixture(scope="module")
def codebook64(tmp_path_factory) -> Path:
    """A 64-D PQ codebook (M=8) alone in its folder, as an --official would be."""
    from drsplat.lang import train_codebook

    path = tmp_path_factory.mktemp("official") / "pq.faiss"
    train_codebook(np.random.default_rng(0).normal(size=(300, 64)).astype(np.float32), m=8).save(path)
    return path


# ----------------------------------------------------------------------------- flags refused by argparse (exit 2)

BAD_FLAGS = [
    # --repeats 0 ran StatisticsError tracebacks; inf / 1e400 in a count an OverflowError
    (["io", "--repeats", "0"], "--repeats"), (["eval", "--repeats", "-1"], "--repeats"),
    (["query", "--repeats", "0"], "--repeats"), (["register", "--repeats", "0"], "--repeats"),
    (["query", "--sizes", "inf"], "--sizes"), (["query", "--sizes", "1e400"], "--sizes"), (["query", "--sizes", "nan"], "--sizes"),
    (["query", "--max-float32", "inf"], "--max-float32"),
    (["register", "--gaussians", "inf"], "--gaussians"), (["register", "--gaussians", "1e12"], "--gaussians"),
    (["eval", "--gaussians", "0"], "--gaussians"), (["eval", "--gaussians", "-5"], "--gaussians"),
    (["eval", "--points", "0"], "--points"), (["eval", "--points", "-1"], "--points"),
    (["eval", "--voxel-resolutions", "0"], "--voxel-resolutions"), (["eval", "--voxel-resolutions", "32,abc"], "--voxel-resolutions"),
    (["eval", "--voxel-preset", "bogus"], "--voxel-preset"),
    # register: ValueError tracebacks from the synthetic dataset, slices of negative views
    (["register", "--mislabel", "nan"], "--mislabel"), (["register", "--mislabel", "2"], "--mislabel"), (["register", "--mislabel", "-1"], "--mislabel"),
    (["register", "--preset", "bogus"], "--preset"), (["register", "--real-topk", "0"], "--real-topk"), (["register", "--topks", "5,2000"], "--topks"),
    (["register", "--agree-views", "-1"], "--agree-views"), (["register", "--count-views", "-1"], "--count-views"),
    (["register", "--count-views", "0"], "--count-views"), (["register", "--size", "100000x10"], "--size"),
    # features: slices and NaN rows; an unknown generator was found after CLIP was built
    (["features", "--images", "-3"], "--images"), (["features", "--images", "0"], "--images"), (["features", "--sam-images", "0"], "--sam-images"),
    (["features", "--nms-masks", "abc"], "--nms-masks"), (["features", "--nms-masks", "50,0"], "--nms-masks"),
    (["features", "--loop-masks", "-1"], "--loop-masks"), (["features", "--resolution", "0"], "--resolution"),
    (["features", "--resolution", "nan"], "--resolution"), (["features", "--sam-points-per-side", "0"], "--sam-points-per-side"),
    (["features", "--sam-crop-layers", "-1"], "--sam-crop-layers"), (["features", "--generators", "bogus"], "--generators"),
    # query
    (["query", "--dim", "0"], "--dim"), (["query", "--dim", "-3"], "--dim"), (["query", "--labels", "0"], "--labels"),
    (["query", "--labels", "1"], "--labels"), (["query", "--queries", "0"], "--queries"), (["query", "--queries", "-2"], "--queries"),
    (["query", "--seed", "-1"], "--seed"), (["query", "--backends", ","], "--backends"), (["query", "--backends", "float32,bogus"], "--backends"),
    # scale
    (["scale", "--workers", "abc"], "--workers"), (["scale", "--workers", "0"], "--workers"), (["scale", "--workers", "-1"], "--workers"),
    (["scale", "--budget", "abc"], "--budget"), (["scale", "--rss-tiles", "abc"], "--rss-tiles"), (["scale", "--rss-tiles", "0"], "--rss-tiles"),
    (["scale", "--big-tiles", "-1"], "--big-tiles"), (["scale", "--gpu-speedup", "0"], "--gpu-speedup"),
    (["scale", "--model-images", "0"], "--model-images"), (["scale", "--nodes", "abc"], "--nodes"), (["scale", "--width", "0"], "--width"),
    # startup showed `drsplat synth`'s usage; budget found an unknown case in its run
    (["startup", "--preset", "bogus"], "bench startup: error: argument --preset"), (["budget", "--cases", "bogus"], "--cases"),
    # an output ending in "/" names a folder: the file would have taken its name
    (["register", "--engine", "torch", "--device", "cpu", "--json", "out/"], "--json"),
    (["register", "--engine", "torch", "--device", "cpu", "--profile-views", "1", "--trace", "out/"], "--trace"), (["budget", "--json", "out/"], "--json"),
    (["query", "--plot", "out/"], "--plot"), (["scale", "--json", "out/"], "--json"),
]


@pytest.mark.parametrize("argv, words", BAD_FLAGS, ids=[" ".join(a) for a, _ in BAD_FLAGS])
def test_a_bad_bench_flag_is_a_usage_error_naming_it(argv, words, capsys, no_work):
    code, err, out = run_cli(["bench", *argv], capsys)
    assert code == 2 and words in err, err
    assert len(error_lines(err)) == 1 and not out


def test_count_flags_read_suffixes_and_refuse_what_is_not_a_finite_count():
    from drsplat.bench.common import count_arg, count_list, gaussian_count, parse_count

    assert count_list("100k,1.5M, 42") == [100_000, 1_500_000, 42] and count_arg("2M") == 2_000_000
    for text in ("inf", "-inf", "nan", "1e400", "1e400k"):
        with pytest.raises(ValueError):
            parse_count(text)
        with pytest.raises(argparse.ArgumentTypeError, match="finite"):
            count_list(text)
    with pytest.raises(argparse.ArgumentTypeError, match="at most"):
        gaussian_count("1e12")


FLAGS_WRONG_TOGETHER = [
    (["query", "--queries", "50", "--labels", "40"], "--queries 50 is more than --labels 40"),
    (["query", "--dim", "100", "--backends", "pq32"], "--dim 100"),
    (["query", "--train", "100", "--backends", "pq32"], "--train 100"),
    (["query", "--backends", "faiss"], "--backends faiss"),
    (["register", "--skip-synthetic", "--gaussians", "100", "--engine", "numba", "--device", "cpu", "--profile-views", "3"], "--profile-views"),
    (["register", "--skip-synthetic", "--gaussians", "100", "--engine", "torch", "--device", "cpu", "--views", "1"], "--views 1"),
    (["scale", "--part", "rss", "--json", "x.json"], "--json"),
    (["register", "--against", "paper", "--engine", "torch", "--device", "cpu"], "--against times two aggregation modes on the numba engine"),
    (["register", "--aggregate", "paper", "--against", "paper"], "--against paper names the mode --aggregate times already"),
    (["register", "--skip-synthetic", "--mask-source", "geometry"], "--mask-source sets the synthetic table's masks"),
    (["register", "--against", "nosuch"], "--against"),
    (["register", "--mask-source", "nosuch"], "--mask-source"),
]


@pytest.mark.parametrize("argv, words", FLAGS_WRONG_TOGETHER, ids=[" ".join(a) for a, _ in FLAGS_WRONG_TOGETHER])
def test_flags_wrong_together_are_usage_errors_before_any_work(argv, words, capsys, no_work, tmp_path):
    code, err, _ = run_cli(["bench", *argv], capsys)
    assert code == 2 and words in err, err
    assert not list(tmp_path.iterdir())  # nothing written


# ----------------------------------------------------------------------------- no output over an input (exit 1, input unchanged)


def test_query_plot_may_not_replace_a_cached_codebook_or_the_negatives(tmp_path, capsys, no_work, codebook64):
    cache = tmp_path / "cache"
    cache.mkdir()
    cached = cache / "v2_pq32_d512_l40_n5000_s0.faiss"  # what --backends pq32 reads with the other flags' defaults
    cached.write_bytes(b"a codebook trained by an earlier run")
    before = digest(cached)
    code, err, _ = run_cli(["bench", "query", "--backends", "pq32", "--cache-dir", cache, "--plot", cached], capsys)
    assert code == 1 and "cannot write" in err and "--cache-dir's pq32 codebook" in err, err
    assert digest(cached) == before

    negatives = codebook64.parent / "text_negative.npy"
    np.save(negatives, np.ones((2, 64), np.float32))
    before = digest(negatives)
    code, err, _ = run_cli(["bench", "query", "--backends", "official", "--dim", "64", "--official", codebook64, "--plot", negatives], capsys)
    assert code == 1 and "cannot write" in err and "text_negative.npy" in err, err
    assert digest(negatives) == before
    negatives.unlink()


def test_query_plot_named_other_than_png_and_flags_no_backend_reads(tmp_path, capsys, no_work):
    """Round 54: `bench query --plot x.npy` wrote a PNG under an array's name; --cache-dir and --official, with backends that
    read neither, were taken without a word. The name is refused before any work; the flags get one warning each."""
    code, err, _ = run_cli(["bench", "query", "--backends", "float32", "--plot", tmp_path / "x.npy"], capsys)
    assert code == 2 and "--plot " in err and "the plot is a PNG image; name it .png" in err, err
    assert not (tmp_path / "x.npy").exists()
    with pytest.raises(AssertionError, match="started its work"):  # the flags pass, with their warnings, and the work begins
        main(["bench", "query", "--backends", "float16", "--cache-dir", str(tmp_path / "c"), "--official", str(tmp_path / "o.faiss"),
              "--plot", str(tmp_path / "q.PNG")])
    err = capsys.readouterr().err
    assert "--cache-dir holds trained PQ codebooks; --backends float16 trains none, so it is not used" in err, err
    assert "--official is read by the 'official' backend, which --backends float16 leaves out; it is not used" in err, err


def test_register_outputs_may_not_replace_the_default_real_scene(tmp_path, capsys, no_work, monkeypatch):
    """The default --real is resolved in the bench, after the command line's own guard: it is guarded there."""
    import drsplat.bench.register as register

    default = tmp_path / "flowers.ply"
    default.write_bytes(b"ply\nthe default real scene")
    monkeypatch.setattr(register, "DEFAULT_REAL", default)
    before = digest(default)
    torch = ["bench", "register", "--skip-synthetic", "--engine", "torch", "--device", "cpu"]
    for flags in (["--profile-views", "1", "--trace", default], ["--json", default]):  # JSON outputs named .ply: refused by name (round 89c F4, 90a F1)
        code, err, _ = run_cli(torch + flags, capsys)
        assert code == 2 and "this output is JSON text; a .ply name would hold it" in err, err
        assert digest(default) == before
    copy = tmp_path / "flowers.json"  # a default --real of another name is still guarded by the bench itself
    copy.write_bytes(b"{}")
    monkeypatch.setattr(register, "DEFAULT_REAL", copy)
    code, err, _ = run_cli(torch + ["--json", copy], capsys)
    assert code == 1 and "cannot write" in err and "--real (its default)" in err, err
    assert copy.read_bytes() == b"{}"


def test_scale_json_may_not_replace_a_file_of_the_room(tmp_path, capsys, no_work):
    room = tmp_path / "room"
    (room / "features").mkdir(parents=True)
    for name in ("scene.ply", "transforms.json", "features/manifest.json"):
        (room / name).write_text(name)
    for target, words in (("transforms.json", "--room's transforms.json"), ("features/manifest.json", "features folder")):
        code, err, _ = run_cli(["bench", "scale", "--room", room, "--part", "compare", "--json", room / target], capsys)
        assert code == 1 and "cannot write" in err and words in err, (target, err)
    for target in ("scene.ply", "features/view_000_f.npy"):  # JSON under these names is refused by the name first (round 89c F4)
        code, err, _ = run_cli(["bench", "scale", "--room", room, "--part", "compare", "--json", room / target], capsys)
        assert code == 2 and "this output is JSON text" in err, (target, err)
    assert all((room / name).read_text() == name for name in ("scene.ply", "transforms.json", "features/manifest.json"))
    code, err, _ = run_cli(["bench", "scale", "--room", tmp_path / "nothing", "--part", "rss"], capsys)
    assert code == 1 and "is not a written synthetic dataset" in err, err


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc, a folder that accepts no new file")
@pytest.mark.parametrize("argv", [
    ["register", "--skip-synthetic", "--gaussians", "100", "--engine", "torch", "--device", "cpu", "--json", "/proc/self/x.json"],
    ["budget", "--cases", "tiny", "--json", "/proc/self/x.json"],
    ["query", "--sizes", "1k", "--backends", "float16", "--plot", "/proc/self/x.png"],
    ["scale", "--part", "compare", "--json", "/proc/self/x.json"],
], ids=["register", "budget", "query", "scale"])
def test_an_unwritable_output_is_found_before_the_work(argv, capsys, no_work):
    code, err, out = run_cli(["bench", *argv], capsys)
    assert code == 1 and "cannot write /proc/self/x." in err, err
    assert len(error_lines(err)) == 1 and "|" not in out


def test_a_real_scene_that_is_no_file_says_so(tmp_path, capsys, no_work):
    folder = tmp_path / "emptyd"
    folder.mkdir()
    argv = ["bench", "register", "--skip-synthetic", "--engine", "numba", "--device", "cpu", "--real"]
    code, err, _ = run_cli(argv + [folder], capsys)
    assert code == 1 and f"{folder}: is not a file but a folder (--real)" in err, err
    code, err, _ = run_cli(argv + [tmp_path / "missing.ply"], capsys)
    assert code == 1 and "no such scene file (--real)" in err, err
    if hasattr(os, "mkfifo"):
        fifo = tmp_path / "fifo.ply"
        os.mkfifo(fifo)
        code, err, _ = run_cli(argv + [fifo], capsys)
        assert code == 1 and "is not a file but a FIFO" in err, err


# ----------------------------------------------------------------------------- scenes of few Gaussians


@pytest.mark.parametrize("argv", [
    ["io", "{ply}", "--views", "1", "--repeats", "1"],
    ["eval", "--scene", "{ply}", "--points", "10", "--repeats", "1"],
    ["register", "--skip-synthetic", "--engine", "numba", "--device", "cpu", "--real", "{ply}", "--views", "2", "--size", "32x24"],
    ["register", "--skip-synthetic", "--engine", "torch", "--device", "cpu", "--real", "{ply}", "--views", "2", "--size", "32x24"],
], ids=["io", "eval", "register-numba", "register-torch"])
def test_a_scene_of_no_gaussians_is_one_error_naming_it(argv, scenes, capsys, monkeypatch):
    import drsplat.bench.register as register

    monkeypatch.setattr(register, "synthetic_table", lambda *a, **k: pytest.fail("the scene was read after the synthetic table"))
    code, err, _ = run_cli(["bench", *(str(scenes[0]) if a == "{ply}" else a for a in argv)], capsys)
    assert code == 1 and f"{scenes[0]}: holds no Gaussians" in err, err
    assert len(error_lines(err)) == 1


def test_orbit_cameras_see_scenes_of_one_two_or_three_gaussians():
    """orbit_cameras' SVD needed three points inside the 5-95 % box, and a nonzero extent (IndexError, NaN poses)."""
    from drsplat.bench.register import orbit_cameras

    rng = np.random.default_rng(0)
    for means in (rng.normal(size=(1, 3)), rng.normal(size=(2, 3)), rng.normal(size=(3, 3)), np.zeros((4, 3))):
        cams = orbit_cameras(means, 3, 32, 24)
        assert len(cams) == 3
        assert all(np.isfinite(c.R).all() and np.isfinite(c.t).all() for c in cams)
    big = rng.normal(size=(500, 3))  # a scene with a 5-95 % box to take its axes from: unchanged
    assert np.isfinite(orbit_cameras(big, 2, 32, 24)[0].R).all()


def test_orbit_cameras_take_the_scenes_axes_without_a_square_matrix_of_its_points():
    """Was: the axes came from an SVD with full_matrices=True on up to 20,000 points, which also built a
    20000 x 20000 U (3.2 GB) that the bench's peak RSS then counted. 6,000 points would take 288 MB."""
    import tracemalloc

    from drsplat.bench.register import orbit_cameras

    means = np.random.default_rng(1).normal(size=(6000, 3)) * [4.0, 2.0, 0.5]
    tracemalloc.start()
    try:
        cams = orbit_cameras(means, 4, 32, 24)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 20e6, f"{peak / 1e6:.0f} MB traced to place 4 cameras around 6,000 points"
    up = np.array([0.0, 0.0, 1.0])  # the flattest axis: the orbit's plane is the two widest
    for cam in cams:
        down = cam.R[1]
        assert abs(abs(down @ up) - 1) < 0.2


def test_benches_run_on_scenes_of_one_and_two_gaussians(scenes, capsys):
    code, err, out = run_cli(["bench", "io", scenes[2], "--views", "1", "--repeats", "1"], capsys)
    assert code == 0 and "2 Gaussians" in out, err
    code, err, out = run_cli(["bench", "register", "--skip-synthetic", "--skip-stages", "--engine", "numba", "--device", "cpu", "--real", scenes[1],
                              "--views", "2", "--size", "32x24", "--repeats", "1"], capsys)
    assert code == 0 and "1 Gaussians, 2 orbiting views" in out, err


def test_bench_io_on_a_scene_spz_cannot_hold_says_so_in_its_table(tmp_path, capsys):
    """Was (round 46, left as found): `bench io` on a scene with a mean past .spz's 24-bit fixed point
    stopped with "cannot write /tmp/tmpqpknpi30/scene.spz: positions reach 1e+07 units", naming a temp
    file the user never gave. Now the .spz rows say "not written" and why, and the other types are timed."""
    from drsplat.scene import save_ply
    from drsplat.testing import gaussians

    far = tmp_path / "far.ply"
    save_ply(gaussians(np.array([[0.0, 0.0, 0.0], [1e7, 0.0, 0.0], [0.0, 1.0, 0.0]]), log_scale=-1.5, opacity_logit=5.0), far)
    code, err, out = run_cli(["bench", "io", str(far), "--views", "0", "--repeats", "1"], capsys)
    assert code == 0, err
    assert out.count("| not written |") == 2 and "tmp" not in out.replace(str(tmp_path), "")
    assert ".spz v3 (gzip): not written: positions reach 1e+07 units; .spz stores 24-bit fixed point" in out
    assert "| .splat " in out and "| compressed PLY " in out


def test_bench_tables_show_a_scene_named_with_escape_as_its_escaped_name(scenes, tmp_path, capsys):
    """Round 42 (left as found then): the bench commands printed a scene's file name raw, so a name
    holding ESC could rewrite the terminal's line; it is shown JSON-escaped, as every message shows it."""
    import shutil

    hostile = tmp_path / "scene\x1b[2Kx.ply"
    shutil.copy(scenes[2], hostile)
    code, err, out = run_cli(["bench", "io", str(hostile), "--views", "1", "--repeats", "1"], capsys)
    assert code == 0 and "\x1b" not in out and '"scene\\u001b[2Kx.ply": 2 Gaussians' in out, out
    code, err, out = run_cli(["bench", "register", "--skip-synthetic", "--skip-stages", "--engine", "numba", "--device", "cpu", "--real", str(hostile),
                              "--views", "2", "--size", "32x24", "--repeats", "1"], capsys)
    assert code == 0 and "\x1b" not in out and '"scene\\u001b[2Kx.ply": 2 Gaussians' in out, out


# ----------------------------------------------------------------------------- bench register


def test_register_gaussians_is_the_scene_of_the_numba_tables_too(capsys):
    """--gaussians N was ignored on the numba engine, which timed flowers.ply instead."""
    code, err, out = run_cli(["bench", "register", "--skip-synthetic", "--gaussians", "300", "--engine", "numba", "--device", "cpu",
                              "--views", "2", "--size", "32x24", "--repeats", "1"], capsys)
    assert code == 0, err
    assert "random blob scene 300: per-stage ms per view" in out and "random blob scene 300: 300 Gaussians" in out
    assert "flowers" not in out


def test_register_says_when_the_engines_were_not_compared_and_clamps_the_counted_views(capsys):
    code, err, out = run_cli(["bench", "register", "--skip-synthetic", "--gaussians", "300", "--engine", "torch", "--device", "cpu",
                              "--views", "2", "--size", "32x24", "--repeats", "1", "--agree-views", "0", "--count-views", "5"], capsys)
    assert code == 0, err
    assert "not compared (--agree-views 0)" in out and "max |Δw|" not in out
    assert "--count-views 5: only 1 of the 2 --views come after the warm-up view; using 1" in err
    assert "median of 1 views after a warm-up" in out and "median of 0 views" not in out


def test_register_against_times_both_modes_in_abba_blocks(capsys, monkeypatch):
    """--against: the two modes in one run, in the order A B, B A, A B, B A; each ABBA block's ratio
    sums both positions, so whatever the first run of a pair pays cancels."""
    import drsplat.bench.register as register

    order, walls = [], iter([3.0, 2.0, 1.0, 2.0, 6.0, 2.0, 3.0, 4.0])  # A B | B A | A B | B A: A's 3, 2, 6, 4; B's 2, 1, 2, 3
    real_one_run = register._one_run

    def one_run(scene, cameras, features_dir, options):
        result, _, cpu = real_one_run(scene, cameras, features_dir, options)
        order.append(options.aggregate)
        return result, next(walls), cpu

    monkeypatch.setattr(register, "_one_run", one_run)
    code, err, out = run_cli(["bench", "register", "--skip-synthetic", "--skip-stages", "--gaussians", "300", "--views", "2", "--size", "32x24",
                              "--repeats", "4", "--aggregate", "vote-reject", "--against", "paper"], capsys)
    assert code == 0, err
    assert order == ["vote-reject", "paper", "paper", "vote-reject", "vote-reject", "paper", "paper", "vote-reject"]
    assert "--aggregate vote-reject; median of 4" in out and "--aggregate paper; median of 4" in out
    # blocks (3 + 2) / (2 + 1) = 1.67 and (6 + 4) / (2 + 3) = 2.00: their median, not a ratio of single runs or of medians
    assert "time per view, --aggregate vote-reject / paper: 1.83x (median of the 2 ABBA blocks' ratios" in out
    assert "1.67, 2.00" in out


@pytest.mark.parametrize("repeats", [1, 2, 3])
def test_timed_pair_keeps_the_field_of_each_modes_newest_run_only(repeats):
    """Ten results of flowers held 1.1 GB each (11 GB) in the process being timed; each mode's
    newest keeps its field (the synthetic table scores it), whichever mode ran last."""
    from drsplat.bench.register import blob_scene, orbit_cameras, random_mask_features, timed_pair

    scene = blob_scene(200)
    cameras = orbit_cameras(scene.means, 2, 32, 24)
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        random_mask_features(Path(tmp), cameras, np.random.default_rng(0), dim=8)
        first, second = timed_pair(scene, cameras, Path(tmp), 10, repeats, ("vote-reject", "paper"))
    for timed in (first, second):
        assert len(timed.runs) == len(timed.walls) == repeats
        assert timed.result is timed.runs[-1] and timed.result.features is not None and timed.result.features.shape == (200, 8)
        assert all(r.features is None and r.weights.size == 0 for r in timed.runs[:-1])
        assert all(r.num_views == 2 for r in timed.runs)


def test_the_register_benchs_warm_up_registers_every_view(monkeypatch):
    """Round 101b F1: the warm-up registered the first view alone, so the stages that need several views (the fit's probe
    views, the check, the vote) compiled in the first timed repeat on an empty numba cache: 954 ms a view printed for ~12,
    a time ratio of 119x for ~1.5x. Each mode's warm-up is a whole registration, not timed."""
    import drsplat.registration as registration
    from drsplat.bench.register import blob_scene, orbit_cameras, random_mask_features, timed_pair, timed_register

    scene = blob_scene(100)
    cameras = orbit_cameras(scene.means, 3, 32, 24)
    real, calls = registration.register_features, []
    monkeypatch.setattr(registration, "register_features", lambda s, cams, *a, **k: (calls.append(len(cams)), real(s, cams, *a, **k))[1])
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        random_mask_features(Path(tmp), cameras, np.random.default_rng(0), dim=8)
        timed_register(scene, cameras, Path(tmp), 10, 1, aggregate="paper")
        assert calls == [3, 3]  # the warm-up, then the timed repeat
        calls.clear()
        timed_pair(scene, cameras, Path(tmp), 10, 2, ("vote-reject", "paper"))
        assert calls == [3] * 6  # a warm-up of each mode, then two repeats of each


def test_the_text_query_tables_header_names_the_queries_file():
    """Round 101b F2: a loop variable took the queries' file name's place, so the header read "(8-bit, wide tables
    float32, 4 rows)" for "(text_negative.npy, 4 rows)"."""
    from drsplat.bench.query import text_query_table
    from drsplat.lang.codebook import train_codebook

    rng = np.random.default_rng(0)
    book = train_codebook(rng.normal(size=(600, 32)).astype(np.float32), m=8)
    table = text_query_table(book, rng.normal(size=(4, 32)).astype(np.float32), "text_negative.npy", 500, 0, 1)
    assert table.splitlines()[0].startswith("8-bit tables on CLIP text queries (text_negative.npy, 4 rows) over 500 random"), table


@pytest.mark.parametrize("f32, q8, words", [(True, True, "AVX-512 table kernels: float32 and 8-bit"),
                                             (True, False, "AVX-512 table kernels: float32,"),
                                             (False, False, "no AVX-512 table kernels (portable ones)")])
def test_the_machine_line_says_which_avx512_table_kernels_ran(monkeypatch, f32, q8, words):
    """Round 101b F5: "machine: x86_64, 2 cores" hid whether the AVX-512 look-up-table kernels ran, which turns the 8-bit
    tables from ~1.8x faster than float32 ones (the docs' machine) to slower (this one); round 103a F1: the float32
    kernel needs avx512f only, the 8-bit one VBMI too (not on Skylake-SP), so the line names each."""
    import drsplat.lang.lut as lut
    from drsplat.bench.common import machine_line

    monkeypatch.setattr(lut, "simd_available", lambda: f32)
    monkeypatch.setattr(lut, "simd_q8_available", lambda: q8)
    assert words in machine_line(), machine_line()


def test_bench_query_reports_what_a_training_sample_costs(tmp_path, capsys):
    """Round 101b: training a codebook on a sample (`pq train --max-train`, the scene codebook's rows) is an approximation
    no bench measured. `--train-sizes` trains one on each size and gives its time beside its scores' error; the row of the
    size the main table's codebook was trained on gives that table's error, and fewer embeddings cost accuracy here."""
    argv = ["bench", "query", "--sizes", "20k", "--backends", "pq32", "--dim", "64", "--train", "1000", "--train-sizes", "256,1k,4k",
            "--repeats", "1", "--plot", tmp_path / "q.png", "--cache-dir", tmp_path / "cache"]
    code, err, out = run_cli(argv, capsys)
    assert code == 0, err
    lines = out.splitlines()
    main_row = next(line for line in lines if line.startswith("| PQ M=32 (LUT) "))
    at = next(i for i, line in enumerate(lines) if line.startswith("PQ M=32 trained on a sample of embeddings"))
    sample = {row.split("|")[1].strip(): [c.strip() for c in row.strip("|").split("|")] for row in lines[at + 3:at + 6]}
    assert list(sample) == ["256", "1,000", "4,000"], sample
    assert sample["1,000"][2:] == [c.strip() for c in main_row.strip("|").split("|")][6:9], (sample["1,000"], main_row)
    assert float(sample["256"][2]) > float(sample["4,000"][2]) > 0  # mean |Δcos|: a smaller sample, a larger error
    assert run_cli([*argv[:-4], "--train-sizes", "100", *argv[-4:]], capsys)[0] == 2  # fewer than a sub-quantiser's 256 centroids


def test_register_synthetic_table_with_against_and_a_mask_source(capsys):
    code, err, out = run_cli(["bench", "register", "--skip-real", "--preset", "tiny", "--topks", "5", "--repeats", "2",
                              "--against", "paper", "--mask-source", "geometry"], capsys)
    assert code == 0, err
    head, columns, _, row = out.splitlines()[:4]
    assert "geometry masks" in head and "--against paper, alternating" in head
    cells = [c.strip() for c in columns.strip("|").split("|")]
    assert cells[-5:] == ["ms/view (paper)", "time ratio (median)", "assigned (paper)", "seg mIoU (paper)", "loc mIoU (paper)"]
    against = dict(zip(cells, (c.strip() for c in row.strip("|").split("|"))))
    assert float(against["ms/view (paper)"]) > 0 and 0 < float(against["time ratio (median)"]) < 100
    # round 78d F3: the other mode's accuracy was not shown; it is the one `--aggregate paper` alone measures
    code, err, out = run_cli(["bench", "register", "--skip-real", "--preset", "tiny", "--topks", "5", "--repeats", "1",
                              "--aggregate", "paper", "--mask-source", "geometry"], capsys)
    assert code == 0, err
    _, columns, _, row = out.splitlines()[:4]
    alone = dict(zip((c.strip() for c in columns.strip("|").split("|")), (c.strip() for c in row.strip("|").split("|"))))
    assert [against[f"{c} (paper)"] for c in ("assigned", "seg mIoU", "loc mIoU")] == [alone[c] for c in ("assigned", "seg mIoU", "loc mIoU")]


# ----------------------------------------------------------------------------- bench query


def test_query_with_float32_alone_draws_its_plot(tmp_path, capsys):
    """The plot's log axes had no positive value to draw: a ValueError after all the work."""
    plot = tmp_path / "q.png"
    code, err, out = run_cli(["bench", "query", "--sizes", "1k", "--backends", "float32", "--repeats", "1", "--plot", plot], capsys)
    assert code == 0 and plot.stat().st_size > 0, err
    assert "float32 matmul" in out


def test_the_faiss_search_rows_show_their_error_as_not_measured_not_as_exact(tmp_path, capsys):
    """Round 78d F2: faiss's top-k search rows printed mean |Δcos| 0, Spearman 1 and IoU 1, the record's defaults (no
    all-N scores are compared for them), as if the search over PQ codes were exact; the LUT rows of the same codes
    measure 0.006 at M=128. Now "–"; float32 is the reference (0 / 1 / 1) and the LUT rows keep their errors."""
    argv = ["bench", "query", "--sizes", "1k", "--backends", "float32,pq128,faiss", "--dim", "128", "--labels", "5", "--queries", "2",
            "--train", "300", "--cache-dir", tmp_path, "--repeats", "1", "--plot", tmp_path / "q.png"]
    code, err, out = run_cli(argv, capsys)
    assert code == 0, err
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[-4:-1]] for line in out.splitlines() if line.startswith("| ")}
    faiss_rows = [r for name, r in rows.items() if "faiss search" in name]
    assert faiss_rows and all(r == ["–", "–", "–"] for r in faiss_rows), rows
    assert [float(v) for v in rows["float32 matmul"]] == [0.0, 1.0, 1.0]
    assert float(rows["PQ M=128 (LUT)"][0]) > 0


def test_a_corrupt_cached_codebook_is_trained_again(tmp_path, capsys):
    from drsplat.lang import load_codebook

    cache = tmp_path / "cache"
    cache.mkdir()
    cached = cache / "v2_pq32_d64_l5_n300_s0.faiss"
    cached.write_bytes(b"\x00" * 100)  # a run killed while writing it (or a disk error)
    argv = ["bench", "query", "--sizes", "1k", "--backends", "pq32", "--dim", "64", "--labels", "5", "--queries", "2", "--train", "300",
            "--cache-dir", cache, "--repeats", "1", "--plot", tmp_path / "q.png"]
    code, err, out = run_cli(argv, capsys)
    assert code == 0, err
    assert str(cached) in err and "training it again" in err and "trained PQ M=32" in out
    assert load_codebook(cached).m == 32  # replaced: the next run reads it
    code, err, out = run_cli(argv, capsys)
    assert code == 0 and "trained" not in out and "training it again" not in err


def test_official_codebook_of_another_width_is_one_error_naming_it(codebook64, capsys, no_work):
    code, err, _ = run_cli(["bench", "query", "--sizes", "1k", "--backends", "float16,official", "--official", codebook64], capsys)
    assert code == 1 and f"{codebook64}: is a 64-D codebook but --dim is 512" in err, err
    code, err, _ = run_cli(["bench", "query", "--sizes", "1k", "--backends", "official", "--official", codebook64.parent / "absent.faiss"], capsys)
    assert code == 1 and "absent.faiss: does not exist (--official)" in err, err


@pytest.mark.parametrize("content, words", [
    (b"not an npy file", "is not a readable .npy"),
    (np.ones((3, 32), np.float32), "expected [K, 64]"),
    (np.ones(64, np.float32), "expected [K, 64]"),
    (np.full((2, 64), np.nan, np.float32), "none of its 2 rows is usable"),
], ids=["garbage", "wrong-width", "one-dimensional", "all-nan"])
def test_bad_negatives_beside_the_official_codebook_are_one_error_before_the_work(content, words, codebook64, capsys, no_work):
    negatives = codebook64.parent / "text_negative.npy"
    if isinstance(content, bytes):
        negatives.write_bytes(content)
    else:
        np.save(negatives, content)
    try:
        code, err, _ = run_cli(["bench", "query", "--sizes", "1k", "--backends", "official", "--dim", "64", "--official", codebook64], capsys)
    finally:
        negatives.unlink()
    assert code == 1 and f"{negatives}: " in err and words in err, err


def test_negatives_rows_with_nan_are_counted_and_left_out(tmp_path, caplog):
    from drsplat.bench.query import text_negatives

    rows = np.random.default_rng(0).normal(size=(5, 8)).astype(np.float32)
    rows[1, 3], rows[4] = np.nan, 0.0
    np.save(tmp_path / "n.npy", rows)
    kept = text_negatives(tmp_path / "n.npy", 8)
    assert np.array_equal(kept, rows[[0, 2, 3]])
    assert "2 of its 5 rows are no float32 embedding (2 zero or non-finite)" in caplog.text
    assert text_negatives(tmp_path / "absent.npy", 8) is None


def test_negatives_rows_float32_cannot_hold_are_counted_by_kind(tmp_path, caplog):
    """Was (round 46, left as found): a float64 row beyond float32's range was counted among the rows
    holding "NaN or infinite values" (its float32 cast), and a row of subnormal norm was kept. Each kind
    is now judged as stored, by the query loader's owner (drsplat.query.embedding_row_problems)."""
    from drsplat.bench.query import text_negatives

    rows = np.random.default_rng(0).normal(size=(6, 8))
    rows[1, 2] = 1e39  # beyond float32
    rows[2] = 1e-44  # a float32 cast keeps a few bits of a direction
    rows[3] = 3e38  # finite in float32, its norm is not
    rows[5, 0] = np.inf
    np.save(tmp_path / "n.npy", rows)
    with caplog.at_level("WARNING"):
        kept = text_negatives(tmp_path / "n.npy", 8)
    np.testing.assert_array_equal(kept, rows[[0, 4]].astype(np.float32))
    assert ("4 of its 6 rows are no float32 embedding (1 beyond float32's range, 1 zero or non-finite, 1 of a norm beyond float32's range, "
            "1 of a norm below float32's smallest normal)") in caplog.text


# ----------------------------------------------------------------------------- bench scale


def test_scale_run_of_a_local_configuration_has_no_worker_first_view(room, tmp_path):
    """`run_config` took max() over no workers (a local run): --part rss printed 'stops: max() arg is an
    empty sequence' rows and exited 0, --part big a traceback."""
    from drsplat.bench.scale import _prepare, run_config, write_records

    config = _prepare(argparse.Namespace(room=room, width=16), tmp_path, 1, 2, "t")
    result = run_config(config)
    assert result["first_view"] is None and result["views"] == 2 and result["gaussians"] > 0
    write_records(tmp_path / "r.json", [{**result, "label": "local"}])
    assert '"first_view_s": null' in (tmp_path / "r.json").read_text()


def test_a_scale_part_that_measured_nothing_exits_1(room, capsys, monkeypatch):
    import drsplat.bench.scale as scale

    def fails(config):
        raise scale.ChildRunFailed(f"bench run '{config['label']}' failed: out of memory")

    monkeypatch.setattr(scale, "_child", fails)
    code, err, out = run_cli(["bench", "scale", "--room", room, "--part", "rss", "--rss-tiles", "1", "--rss-views", "2", "--width", "16"], capsys)
    assert code == 1 and "--part rss measured nothing" in err, err
    assert "stops: out of memory" in out
    code, err, out = run_cli(["bench", "scale", "--room", room, "--part", "big", "--big-tiles", "1", "--big-views", "2", "--width", "16"], capsys)
    assert code == 1 and error_lines(err) == ["ERROR: bench run 'big' failed: out of memory"], err


def test_scale_keeps_the_budget_as_written():
    from drsplat.bench.scale import budget_text

    assert budget_text(" 8GB") == "8GB"
    with pytest.raises(argparse.ArgumentTypeError):
        budget_text("lots")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))


def test_viewer_bench_refuses_a_typed_scene_that_is_missing_or_a_folder(tmp_path, capsys):
    """Round 21: `bench viewer --ply` that does not exist (or is a folder) silently benchmarked a
    random scene instead; only the default scene may be skipped when it is absent."""
    for ply, problem in ((tmp_path / "missing.ply", "no such scene file"), (tmp_path, "is not a file but a folder")):
        code, err, _ = run_cli(["bench", "viewer", "--ply", ply, "--sizes", "100k", "--width", "64", "--height", "48", "--repeats", "1"], capsys)
        (line,) = error_lines(err)
        assert code == 1 and problem in line and "--ply" in line, err
    for flag, value in (("--width", "0"), ("--height", "100000"), ("--repeats", "0"), ("--sizes", "5"), ("--screenshot", str(tmp_path / "shots") + os.sep)):
        code, err, _ = run_cli(["bench", "viewer", flag, value], capsys)
        assert code == 2 and flag in err, (flag, err)


def test_region_masks_follow_the_scene_from_view_to_view(tmp_path):
    """`--real-masks regions`: a view's pixel is in the mask of its heaviest Gaussian's region, and a
    region's masks in different views carry alike embeddings (cosine > 0.95 at noise 0.15), while
    different regions' are far apart; pixels no Gaussian covers are in no mask."""
    from drsplat.bench.register import blob_scene, orbit_cameras, region_mask_features
    from drsplat.features.format import read_features
    from drsplat.raster import rasterize_topk

    scene = blob_scene(3000, seed=2)
    cameras = orbit_cameras(scene.means, 3, 48, 36)
    region_mask_features(tmp_path, cameras, scene, np.random.default_rng(0), regions=6, dim=64)
    for cam in cameras:
        ids, feats = read_features(tmp_path, cam.name)
        top = rasterize_topk(scene, cam, 1).ids[..., 0]
        assert ((ids >= 0) == (top >= 0)).all() and len(feats) >= 2
        assert np.array_equal(np.unique(ids[ids >= 0]), np.arange(len(feats)))  # every mask has pixels
        np.testing.assert_allclose(np.linalg.norm(feats, axis=1), 1.0, rtol=1e-5)
    # across views, the masks' embeddings fall into tight groups, one per region, far from one another
    allf = np.concatenate([read_features(tmp_path, c.name)[1] for c in cameras])
    cos = allf @ allf.T
    close = cos > 0.95
    assert (np.diag(close)).all()
    groups = {tuple(np.flatnonzero(row)) for row in close}
    assert 2 <= len(groups) <= 6 and sum(len(g) for g in groups) == len(allf)  # a partition: each mask in one region's group
    assert cos[~close].max() < 0.6


def test_render_bench_times_the_sh_kernel_against_its_reference_and_the_principal_point_decision(tmp_path, capsys):
    """`drsplat bench render` on a small scene: its SH colour row agrees with the reference to float32 rounding, the
    decision over views whose images are the scene's own renders, read 5 % off-centre, takes the centres, and the near
    plane's takes 0.2 for floaters the images (drawn at 0.2) do not show, its band the reference's. A scene file that is
    not there is one error naming it, before any work."""
    from drsplat.scene import save_ply
    from drsplat.synthetic import make_synthetic

    save_ply(make_synthetic("tiny", 0).scene, tmp_path / "tiny.ply")
    code, err, out = run_cli(["bench", "render", "--scene", tmp_path / "tiny.ply", "--width", "96", "--height", "72", "--views", "4",
                              "--offset", "0.05", "--repeats", "1"], capsys)
    assert code == 0, err
    sh_row = next(line for line in out.splitlines() if line.startswith("| SH colours"))
    assert float(sh_row.split("|")[-2]) < 1e-5, sh_row
    assert "took the centres (truth: the centres)" in out, out
    assert "took 0.2 (truth: 0.2)" in out, out  # the near plane decided on floaters INRIA's rasterizer never drew
    band_row = next(line for line in out.splitlines() if line.startswith("| near band"))
    assert band_row.rstrip(" |").endswith("yes"), band_row  # the numba pass found the reference's bands
    code, err, _ = run_cli(["bench", "render", "--scene", tmp_path / "missing.ply"], capsys)
    assert code == 1 and "missing.ply" in err, err


def test_a_bench_says_each_warning_once_however_often_its_repeats_raise_it(caplog):
    """Each timed repeat prepares and registers again: a scene's warning once a repeat is no row of the table (round
    90b F3: `bench render` said a scene's unusable Gaussians 8 times). Other warnings, and info lines, still show."""
    import logging

    from drsplat.commands.bench import _guarded

    log = logging.getLogger("drsplat.raster")

    def repeats(args) -> int:
        for _ in range(3):
            log.warning("%d of %d Gaussians are not rendered", 3, 2760)
            log.info("repeat done")
        log.warning("%d of %d Gaussians are not rendered", 3, 2800)  # another scene: said too
        return 0

    with caplog.at_level(logging.INFO):
        assert _guarded(repeats)(argparse.Namespace()) == 0
        log.warning("%d of %d Gaussians are not rendered", 3, 2760)  # after the bench: the filter is gone
    texts = [(r.levelname, r.getMessage()) for r in caplog.records]
    assert texts.count(("WARNING", "3 of 2760 Gaussians are not rendered")) == 2
    assert texts.count(("WARNING", "3 of 2800 Gaussians are not rendered")) == 1
    assert texts.count(("INFO", "repeat done")) == 3
