"""`drsplat bench startup`: what each main command costs before and around its work, with default flags.

Every row runs in a fresh interpreter (a subprocess), so imports are not shared between rows:
import s = time to import drsplat.cli and build its parser (every command pays it), run s = the
command itself, peak RSS = the child's VmHWM (ru_maxrss would include the bench's own peak, which
a forked child inherits across exec), heavy = which of torch / ray / open_clip /
moderngl the command left in sys.modules. The row marked "torch imported first" runs `query` after
importing torch, which is what `--device auto` cost on a machine without a GPU before it asked the
driver first (drsplat.device.nvidia_driver_present).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from drsplat.bench.common import format_table, machine_line, positive_int
from drsplat.defaults import ORACLE_TEXT_EMBEDDINGS
from drsplat.errors import DrsplatError

HEAVY = ("torch", "ray", "open_clip", "moderngl")

CHILD = """
import json, sys, time
t0 = time.perf_counter()
if sys.argv[1] == "torch-first":
    import torch  # noqa: F401  (the row that shows what importing torch for --device auto cost)
from drsplat.cli import build_parser, main
build_parser()
t1 = time.perf_counter()
import contextlib, io
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    try:
        code = main(sys.argv[2:])
    except SystemExit as exc:
        code = exc.code
t2 = time.perf_counter()
heavy = [m for m in {heavy!r} if m in sys.modules]
from drsplat.memory import peak_rss  # this image's peak (VmHWM), not the forking parent's
print(json.dumps({{"code": code, "import_s": t1 - t0, "run_s": t2 - t1, "peak_mb": peak_rss() / 2**20, "heavy": heavy}}))
"""


def add_bench(subparsers: argparse._SubParsersAction) -> None:
    from drsplat.synthetic import CITY_PRESETS, PRESETS

    p = subparsers.add_parser("startup", help="import time and peak memory of each main command with default flags (subprocesses)")
    p.add_argument("--repeats", type=positive_int, default=3, help="runs per command (medians reported)")
    p.add_argument("--preset", default="tiny", choices=sorted(PRESETS) + sorted(CITY_PRESETS),  # `drsplat synth --preset`'s choices
                   help="synthetic scene the commands run on (made once in a temp folder; default: tiny)")
    p.set_defaults(func=run)


def command_rows(data: Path, work: Path) -> list[tuple[str, str, list[str]]]:
    """(label, mode, argv) of each measured command; mode "torch-first" imports torch before it."""
    reg = work / "reg.ply"
    query = ["query", str(reg), "--embedding", str(work / "q.npy"), "--scores", str(work / "s.npy")]
    return [
        ("drsplat --help", "plain", ["--help"]),
        ("info REGISTERED.ply", "plain", ["info", str(reg)]),
        ("query --embedding --scores", "plain", query),
        ("query, torch imported first (old --device auto)", "torch-first", query),
        ("segment --embeddings", "plain", ["segment", str(reg), "--embeddings", str(work / "L.npy"), "--out", str(work / "seg.npy")]),
        ("register (tiny scene)", "plain", ["register", str(data / "scene.ply"), "--source", str(data), "--features", str(data / "features"),
                                            "--out", str(work / "again.ply"), "--no-progress"]),
    ]


def measure(mode: str, argv: list[str]) -> dict:
    """One fresh interpreter running `drsplat argv`; its timings, peak RSS and heavy modules."""
    script = CHILD.format(heavy=HEAVY)
    proc = subprocess.run([sys.executable, "-c", script, mode, *argv], capture_output=True, text=True)
    if proc.returncode != 0 or not proc.stdout.strip():
        raise DrsplatError(f"bench startup: `drsplat {' '.join(argv)}` failed in its subprocess: {proc.stderr.strip()[-400:]}")
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    if result["code"] not in (0, None):
        raise DrsplatError(f"bench startup: `drsplat {' '.join(argv)}` exited {result['code']}")
    return result


def prepare(work: Path, preset: str) -> Path:
    """A synthetic dataset, its registered PLY and query embeddings in `work` (made in-process, not timed)."""
    import numpy as np

    from drsplat.cli import main

    data = work / "data"
    if main(["-q", "synth", str(data), "--preset", preset, "--seed", "0", "--no-progress"]) != 0:
        raise DrsplatError(f"bench startup: could not make the synthetic '{preset}' scene")
    if main(["-q", "register", str(data / "scene.ply"), "--source", str(data), "--features", str(data / "features"),
             "--out", str(work / "reg.ply"), "--no-progress"]) != 0:
        raise DrsplatError("bench startup: could not register the synthetic scene")
    emb = np.load(data / ORACLE_TEXT_EMBEDDINGS)
    np.save(work / "q.npy", emb[0])
    np.save(work / "L.npy", emb)
    return data


def run(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory(prefix="drsplat-bench-startup-") as tmp:
        work = Path(tmp)
        data = prepare(work, args.preset)
        measure("plain", ["info", str(work / "reg.ply")])  # warm the OS file cache and numba's on-disk cache once
        rows = []
        for label, mode, argv in command_rows(data, work):
            runs = [measure(mode, argv) for _ in range(args.repeats)]
            med = lambda key: statistics.median(r[key] for r in runs)  # noqa: E731
            rows.append([label, med("import_s"), med("run_s"), med("peak_mb"), ", ".join(runs[-1]["heavy"]) or "none"])
    print(machine_line())
    print(f"each row: a fresh interpreter, default flags, median of {args.repeats}")
    print(format_table(["command", "import s", "run s", "peak RSS MB", "heavy modules loaded"], rows))
    return 0
