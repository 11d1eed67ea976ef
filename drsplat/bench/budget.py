"""`drsplat bench budget`: whether `register --memory-budget` holds on inputs that stress one memory term.

Each case writes a dataset (a blob scene of `drsplat.bench.register.blob_scene`, orbiting views,
a grid of masks per view with random or shared-label unit embeddings: random ones make every mask
its own cluster, the worst case for the vote and check stages) and runs `drsplat register` on it
in a fresh process under the case's budget. A run that refuses the budget names the one it needs;
that one is then run too. Peak RSS is the child's own (its VmHWM), the whole command.
The cases are the memory probe's (docs/hostile.md, "Round 10"); `tiny` is the tests' smoke case.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from drsplat.bench.common import choice_list, format_table, guard_bench_outputs, machine_line
from drsplat.commands.common import json_output_file
from drsplat.memory import parse_size
from drsplat.utils import write_bytes_atomic


@dataclass(frozen=True)
class BudgetCase:
    """One probe input: a blob of `gaussians`, `views` orbiting views of width x height, `masks`
    grid masks per view with `dim`-D embeddings (random, or around `labels` shared labels when > 0),
    registered with `--aggregate mode` under `budget`."""

    gaussians: int
    views: int
    masks: int
    dim: int
    mode: str
    budget: str
    labels: int = 0
    width: int = 320
    height: int = 240
    note: str = ""
    scattered: bool = False  # each pixel in a random mask (a view's masks then meet thousands of clusters each)


CASES = {
    "vote-clusters": BudgetCase(20_000, 8, 3_000, 1024, "vote-reject", "1GB", note="the vote's mask clusters (24,000 of 1024-D)"),
    "check-scratch": BudgetCase(50_000, 4, 4_000, 512, "fit-check-vote-reject", "1GB", note="the check's support scratch (4,000 masks a view)"),
    "check-tables": BudgetCase(20_000, 300, 20, 512, "fit-check-vote-reject", "1GB", note="the check's support tables over many views"),
    "check-spill": BudgetCase(20_000, 1_500, 20, 512, "fit-check-vote-reject", "1GB",
                              note="the check's support tables over 1,500 views: past SUPPORT_TABLE_BYTES they spill to disk"),
    "check-one-view": BudgetCase(50_000, 4, 4_000, 512, "fit-check-vote-reject", "1GB", scattered=True,
                                 note="one view's own support table past the cap (~360 MB a view): summed and judged in runs of masks"),
    "shared-labels": BudgetCase(20_000, 8, 3_000, 1024, "fit-check-vote-reject", "2GB", labels=50, note="3,000 masks of 50 labels a view"),
    "paper-control": BudgetCase(20_000, 8, 3_000, 1024, "paper", "1GB", note="the vote-clusters input, paper's mean"),
    "embedding-rows": BudgetCase(20_000, 40, 2_000, 1024, "paper", "800MB",
                                 note="the sums' buffer of mask embeddings: 80,000 rows of 1024-D over the views (a block replays them all)"),
    "tiny": BudgetCase(2_000, 2, 40, 64, "vote-reject", "1GB", width=64, height=48, note="smoke case"),
}
DEFAULT_CASES = ("vote-clusters", "check-scratch", "shared-labels", "paper-control")
NAMED_BUDGET = re.compile(r"give at least ([0-9.]+ ?[kMGT]?B)")


def add_bench(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("budget", help="peak RSS of `register --memory-budget` on inputs that stress one memory term (subprocesses)")
    p.add_argument("--cases", type=choice_list(CASES, "budget case"), default=",".join(DEFAULT_CASES), help=f"comma-separated cases from {', '.join(CASES)}")
    p.add_argument("--json", type=json_output_file, default=None, help="also write the rows as JSON")
    p.set_defaults(func=run)


def write_case(case: BudgetCase, out: Path, seed: int = 0) -> Path:
    """The case's dataset in `out` (scene.ply, transforms.json, images/, features/); returns `out`.

    Masks: a g x g grid of cells (g = ceil(√M)) over the view, cell c in mask c mod M (`scattered`:
    each pixel's mask random), 10 % of the pixels unmasked; embeddings unit rows, random or a unit
    label's plus noise of norm ~0.15."""
    from PIL import Image

    from drsplat.bench.register import blob_scene, orbit_cameras
    from drsplat.cameras import write_transforms_json
    from drsplat.features.format import write_features
    from drsplat.scene import save_ply

    rng = np.random.default_rng(seed)
    scene = blob_scene(case.gaussians, seed=seed)
    (out / "features").mkdir(parents=True, exist_ok=True)
    (out / "images").mkdir(exist_ok=True)
    save_ply(scene, out / "scene.ply")
    cameras = orbit_cameras(scene.means, case.views, case.width, case.height)
    write_transforms_json(cameras, out / "transforms.json")
    labels = None
    if case.labels:
        labels = rng.normal(size=(case.labels, case.dim))
        labels /= np.linalg.norm(labels, axis=1, keepdims=True)
    grid = int(np.ceil(np.sqrt(case.masks)))
    ys, xs = np.mgrid[0 : case.height, 0 : case.width]
    cells = (ys * grid // case.height) * grid + (xs * grid // case.width)
    for cam in cameras:
        Image.new("RGB", (cam.width, cam.height)).save(out / "images" / f"{cam.name}.png")
        ids = (rng.integers(0, case.masks, cells.shape) if case.scattered else cells % case.masks).astype(np.int32)
        ids[rng.random(ids.shape) < 0.1] = -1
        if labels is None:
            feats = rng.normal(size=(case.masks, case.dim))
        else:
            feats = labels[rng.integers(0, case.labels, case.masks)] + 0.15 * rng.normal(size=(case.masks, case.dim)) / np.sqrt(case.dim)
        feats = (feats / np.linalg.norm(feats, axis=1, keepdims=True)).astype(np.float32)
        write_features(out / "features", cam.name, ids, feats)
    return out


@dataclass
class BudgetRun:
    """One `register` process: its budget, exit code, the budget a refusal named, peak RSS bytes and seconds."""

    case: str
    mode: str
    budget: int
    code: int
    named: int | None
    peak: int
    seconds: float

    @property
    def verdict(self) -> str:
        if self.code != 0:
            return f"refused (names {self.named / 2**20:,.0f} MiB)" if self.named else f"failed (exit {self.code})"
        return "held" if self.peak <= self.budget else "OVER"


# The child reports its own peak (`memory.peak_rss`: VmHWM; wait4's ru_maxrss would include the
# bench's own size, which Linux carries over exec into a forked child).
CHILD = """
import sys
from drsplat.cli import main
from drsplat.memory import peak_rss
try:
    code = main(sys.argv[1:])
except SystemExit as stop:
    code = stop.code
finally:
    sys.stderr.write("\\nBUDGET-PEAK %d\\n" % peak_rss())
sys.exit(code)
"""
PEAK_LINE = re.compile(r"BUDGET-PEAK (-?[0-9]+)")


def register_under(data: Path, out: Path, mode: str, budget: int) -> tuple[int, str, int, float]:
    """(exit code, stderr, peak RSS bytes, seconds) of `drsplat register` on `data` in a fresh
    process (the peak: its own `memory.peak_rss`; wait4's ru_maxrss if it died before saying)."""
    argv = [sys.executable, "-c", CHILD, "-q", "register", str(data / "scene.ply"), "--source", str(data), "--features", str(data / "features"),
            "--out", str(out), "--no-progress", "--aggregate", mode, "--memory-budget", str(budget)]
    with tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)
        seconds = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait again
        err.seek(0)
        text = err.read().decode(errors="replace")
    found = PEAK_LINE.findall(text)
    peak = int(found[-1]) if found and int(found[-1]) > 0 else int(usage.ru_maxrss) * 1024
    return proc.returncode, text, peak, seconds


def run_case(name: str, case: BudgetCase, work: Path) -> list[BudgetRun]:
    """The case under its budget and, when refused with a named budget, under that one."""
    data = write_case(case, work / name)
    runs, budget = [], parse_size(case.budget)
    for _ in range(2):
        code, text, peak, seconds = register_under(data, work / name / "out.ply", case.mode, budget)
        match = NAMED_BUDGET.search(text)
        named = parse_size(match.group(1)) if match else None
        runs.append(BudgetRun(name, case.mode, budget, code, named, peak, seconds))
        if code == 0 or named is None:
            break
        budget = named
    return runs


def budget_rows(runs: list[BudgetRun]) -> list[list]:
    return [[r.case, r.mode, f"{r.budget / 2**20:,.0f}", r.code, f"{r.peak / 2**20:,.0f}", f"{r.peak / r.budget:.2f}", f"{r.seconds:.1f}", r.verdict]
            for r in runs]


def run(args: argparse.Namespace) -> int:
    names = args.cases
    guard_bench_outputs({}, {"--json": args.json})  # an unwritable --json found now, not after the cases' minutes
    runs: list[BudgetRun] = []
    with tempfile.TemporaryDirectory(prefix="drsplat-bench-budget-") as tmp:
        for name in names:
            runs += run_case(name, CASES[name], Path(tmp))
    print(machine_line())
    for name in names:
        c = CASES[name]
        print(f"{name}: blob {c.gaussians:,}, {c.views} views {c.width}x{c.height}, {c.masks:,} masks a view, {c.dim}-D "
              f"{'random' if not c.labels else f'around {c.labels} labels'}; {c.note}")
    print(format_table(["case", "--aggregate", "budget MiB", "exit", "peak RSS MiB", "peak / budget", "s", "verdict"], budget_rows(runs)))
    if args.json is not None:
        write_bytes_atomic(args.json, json.dumps([asdict(r) | {"verdict": r.verdict} for r in runs], indent=1).encode())
    return 0
