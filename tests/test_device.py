"""Device handling (drsplat.device) and the torch engine end to end through the CLI."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from drsplat.device import resolve_device, resolve_engine
from drsplat.errors import DrsplatError, UsageError

NO_CUDA = not torch.cuda.is_available()


def test_cli_help_does_not_import_torch():
    code = "import sys, contextlib, io\nfrom drsplat.cli import main\n"
    code += "for argv in ([], ['register'], ['query'], ['segment'], ['bench', 'register'], ['bench', 'query']):\n"
    code += "    with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
    code += "        main(argv + ['--help'])\n"
    code += "print('torch' in sys.modules)\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_engine_defaults_and_errors():
    assert resolve_device("cpu") == "cpu"
    assert resolve_engine(None, "cpu") == "numba" and resolve_engine(None, "cuda") == "torch"
    assert resolve_engine("torch", "cpu") == "torch"
    with pytest.raises(DrsplatError, match="CPU only"):
        resolve_engine("numba", "cuda")
    with pytest.raises(DrsplatError, match="unknown device"):
        resolve_device("tpu")
    assert resolve_device("auto") == ("cpu" if NO_CUDA else "cuda")


@pytest.mark.skipif(not NO_CUDA, reason="this machine has a CUDA GPU")
def test_cuda_asked_for_without_a_gpu_is_one_clear_error(tmp_path, capsys):
    from drsplat.cli import main

    with pytest.raises(DrsplatError, match="no CUDA GPU is available"):
        resolve_device("cuda")
    args = ["register", str(tmp_path / "s.ply"), "--source", str(tmp_path), "--features", str(tmp_path), "--out", str(tmp_path / "o.ply"), "--device", "cuda"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "no CUDA GPU is available" in err and "Traceback" not in err


@pytest.mark.skipif(not NO_CUDA, reason="this machine has a CUDA GPU")
def test_kernel_bench_without_a_gpu_says_so_before_reading_the_scene(tmp_path, capsys):
    """`drsplat bench kernel` times Triton kernels that compile for CUDA only: one sentence, exit 1,
    and a bad --configs entry is a usage error (exit 2) that names it."""
    from drsplat.cli import main

    assert main(["bench", "kernel", "--real", str(tmp_path / "absent.ply")]) == 1
    err = capsys.readouterr().err
    assert "run on a CUDA GPU only" in err and "Traceback" not in err
    assert main(["bench", "kernel", "--configs", "16x1,24x1"]) == 2
    assert "'24x1': pixels per program 24 must divide the 256 pixels of a tile" in capsys.readouterr().err
    assert main(["bench", "kernel", "--configs", "1x1x32,1x1x24"]) == 2
    assert "'1x1x24': list entries per step 24 must be 0 (one at a time) or a power of two" in capsys.readouterr().err


def test_kernel_bench_configs_parse_pixels_warps_and_chunk():
    from drsplat.bench.kernel import parse_configs

    assert parse_configs("16x1x0, 1x1x32,8x2") == [(16, 1, 0), (1, 1, 32), (8, 2, None)]
    for bad in ("16x1x", "x1x32", "16x1x32x4", "16", "-1x1x32"):
        with pytest.raises(UsageError, match="is not PIXELSxWARPS"):
            parse_configs(bad)
    for bad, problem in (("16x3x32", "warps per program 3"), ("0x1x32", "pixels per program 0"), ("1x1x2048", "up to 1024")):
        with pytest.raises(UsageError, match=problem):
            parse_configs(bad)


def test_cli_torch_engine_on_cpu_matches_numba(tmp_path, one_torch_thread):
    """register / query / segment with --engine torch --device cpu give what the numba engine gives."""
    from drsplat.cli import main
    from drsplat.lang import read_field
    from drsplat.scene import load_ply

    data = tmp_path / "data"
    assert main(["synth", str(data), "--preset", "tiny", "--seed", "1", "--no-progress"]) == 0
    base = ["register", str(data / "scene.ply"), "--source", str(data), "--features", str(data / "features"), "--topk", "5", "--no-progress"]
    assert main(base + ["--out", str(tmp_path / "numba.ply"), "--engine", "numba"]) == 0
    assert main(base + ["--out", str(tmp_path / "torch.ply"), "--engine", "torch", "--device", "cpu"]) == 0
    fa, fb = (read_field(load_ply(tmp_path / f"{e}.ply"), tmp_path / f"{e}.ply") for e in ("numba", "torch"))
    assert fa.num_gaussians == fb.num_gaussians > 100
    np.testing.assert_allclose(fb.features.astype(np.float32), fa.features.astype(np.float32), atol=2e-3)
    text = data / "text_embeddings.npy"
    for engine in ("numba", "torch"):
        assert main(["query", str(tmp_path / "numba.ply"), "--embedding", str(text), "--scores", str(tmp_path / f"q_{engine}.npy"),
                     "--engine", engine, "--device", "cpu"]) == 0
        assert main(["segment", str(tmp_path / "numba.ply"), "--embeddings", str(text), "--out", str(tmp_path / f"s_{engine}.npy"),
                     "--engine", engine, "--device", "cpu"]) == 0
    np.testing.assert_allclose(np.load(tmp_path / "q_torch.npy"), np.load(tmp_path / "q_numba.npy"), atol=1e-5)
    np.testing.assert_array_equal(np.load(tmp_path / "s_torch.npy"), np.load(tmp_path / "s_numba.npy"))


def test_viewer_device_flags(tmp_path, capsys):
    """`python main.py --device cuda` without a GPU stops in one line; the registration options follow the flags."""
    import torch

    from viewer.launch import build_parser, build_state, main

    if not torch.cuda.is_available():
        assert main(["--device", "cuda", "--screenshot", str(tmp_path / "x.png")]) == 1
        assert "no CUDA GPU is available" in capsys.readouterr().err
        assert not (tmp_path / "x.png").exists()
    state = build_state(build_parser().parse_args(["--device", "cpu", "--engine", "torch"]))
    assert (state.settings.device, state.settings.engine) == ("cpu", "torch")
    state.settings.device, state.settings.engine, state.features_dir = "cuda", "numba", tmp_path
    if not torch.cuda.is_available():
        assert not state.start_registration(tmp_path / "r.ply", background=False)
        assert "no CUDA GPU is available" in state.messages[-1].text
