"""`drsplat bench registered`: peak memory and time of `query`, `segment` and `info` on registered PLYs.

For each field kind (exact float16, PQ with a codebook trained here, IVFPQ with the official Dr. Splat
codebook when ../shared/data has it) and each size N, a registered PLY of N Gaussians of SH degree
--sh-degree is written (random unit directions: exact rows, or random codes with their true
reconstruction norms), then each command runs in a fresh process and reports its own peak resident
memory (`memory.peak_rss`, VmHWM) and wall time. The table gives the bytes a Gaussian adds (the
peak's growth between sizes) beside the file's, so the figures of docs/index.md ("Holding a
registered scene") can be measured again.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from drsplat.bench.common import child_env, choice_list, count_list, format_table, last_error_line, machine_line
from drsplat.commands.common import int_range
from drsplat.errors import DrsplatError

KINDS = ("exact", "pq", "ivfpq")
COMMANDS = ("query", "segment", "info")
PQ_M = 128  # sub-vectors of the trained codebook, as the official one
DIM = 512


def add_bench(subparsers: argparse._SubParsersAction) -> None:
    from drsplat.bench.query import DEFAULT_OFFICIAL

    p = subparsers.add_parser("registered", help="peak memory and time of query, segment and info on registered PLYs of N Gaussians")
    p.add_argument("--sizes", type=count_list, default="500k,2M", help="comma-separated Gaussian counts, two or more for the "
                   "per-Gaussian column (default: 500k,2M)")
    p.add_argument("--kinds", type=choice_list(KINDS, "field kind"), default=",".join(KINDS), help=f"field kinds, a subset of {','.join(KINDS)} (ivfpq needs the official codebook)")
    p.add_argument("--sh-degree", type=int_range(0, 3), default=0, help="SH degree of the scenes written, 0..3 (default: 0)")
    p.add_argument("--official", type=Path, default=DEFAULT_OFFICIAL,
                   help="the official Dr. Splat IVFPQ codebook for the ivfpq rows (default: ../shared/data/drsplat/pq_index.faiss)")
    p.set_defaults(func=run)


def _field(kind: str, n: int, rng: np.random.Generator, book):
    """A LanguageField of n random unit directions (exact) or random codes with their reconstruction norms (pq, ivfpq)."""
    from drsplat.lang import LanguageField
    from drsplat.lang.backends import ExactStorage, PQStorage, reconstruction_norms

    weights = np.ones(n, np.float32)
    if kind == "exact":
        rows = rng.standard_normal((n, DIM), dtype=np.float32)
        rows /= np.linalg.norm(rows, axis=1, keepdims=True)
        return LanguageField(DIM, "ViT-B-16/laion2b_s34b_b88k", weights, ExactStorage(rows.astype(np.float16)))
    codes = rng.integers(0, 256, (n, book.m), np.uint8)
    ids = rng.integers(0, book.nlist, n).astype(np.int32) if book.kind == "ivfpq" else None
    return LanguageField(book.dim, "ViT-B-16/laion2b_s34b_b88k", weights, PQStorage(codes, ids, reconstruction_norms(book, codes, ids), book))


def _scene(n: int, degree: int, rng: np.random.Generator):
    from drsplat.scene import GaussianScene

    return GaussianScene(means=rng.standard_normal((n, 3), dtype=np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                         log_scales=np.full((n, 3), -4.0, np.float32), opacity_logits=np.zeros(n, np.float32),
                         sh=0.1 * rng.standard_normal((n, (degree + 1) ** 2, 3), dtype=np.float32))


def _codebook(kind: str, official: Path, rng: np.random.Generator):
    from drsplat.lang import load_codebook, train_codebook

    if kind == "exact":
        return None
    if kind == "ivfpq":
        return load_codebook(official)
    train = rng.standard_normal((20 * 256, DIM), dtype=np.float32)
    return train_codebook(train / np.linalg.norm(train, axis=1, keepdims=True), m=PQ_M)


def _write(kind: str, n: int, degree: int, folder: Path, book) -> Path:
    from drsplat.lang import attach_field
    from drsplat.scene import save_ply

    rng = np.random.default_rng(n)
    path = folder / f"{kind}_{n}.ply"
    save_ply(attach_field(_scene(n, degree, rng), _field(kind, n, rng, book), path), path)
    return path


def _child(argv: list[str]) -> tuple[float, int]:
    """(wall seconds, peak resident bytes) of `drsplat argv` run in a fresh process; no argv: the program loaded, nothing run."""
    run_it = "rc = main(sys.argv[1:])" if argv else "rc = 0"
    code = (f"import sys; from drsplat.cli import main; from drsplat.memory import peak_rss; {run_it}; "
            "print('PEAK', peak_rss(), file=sys.stderr); sys.exit(rc)")
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", code, *argv], env=child_env(), capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    peak = [line for line in proc.stderr.splitlines() if line.startswith("PEAK ")]
    if proc.returncode != 0 or not peak:
        raise DrsplatError(f"bench run 'drsplat {' '.join(argv[:1])}' failed: {last_error_line(proc.stderr)}")
    return seconds, int(peak[-1].split()[1])


def _commands(path: Path, folder: Path) -> dict[str, list[str]]:
    rng = np.random.default_rng(0)
    queries = rng.standard_normal((2, DIM)).astype(np.float32)
    np.save(folder / "q.npy", queries[0] / np.linalg.norm(queries[0]))
    np.save(folder / "labels.npy", queries / np.linalg.norm(queries, axis=1, keepdims=True))
    return {"query": ["query", str(path), "--embedding", str(folder / "q.npy"), "--top", "3", "-q"],
            "segment": ["segment", str(path), "--embeddings", str(folder / "labels.npy"), "--out", str(folder / "labels_out.npy"), "-q"],
            "info": ["info", str(path), "-q"]}


def run(args: argparse.Namespace) -> int:
    kinds = list(args.kinds)
    if "ivfpq" in kinds and not args.official.is_file():
        print(f"ivfpq left out: the official codebook {args.official} is not there")
        kinds.remove("ivfpq")
    _, baseline = _child([])
    rows, before = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for kind in kinds:
            book = _codebook(kind, args.official, np.random.default_rng(1))
            for n in sorted(args.sizes):
                path = _write(kind, n, args.sh_degree, folder, book)
                size = path.stat().st_size
                for name, argv in _commands(path, folder).items():
                    seconds, peak = _child(argv)
                    last = before.get((kind, name))
                    slope = "-" if last is None or last[0] == n else f"{(peak - last[1]) / (n - last[0]):,.0f}"
                    before[(kind, name)] = (n, peak)
                    rows.append([kind, f"{n:,}", f"{size / n:,.0f}", name, f"{peak / 1e6:,.0f}", slope, f"{seconds:.2f}"])
                path.unlink()
    print(f"registered PLYs of SH degree {args.sh_degree}, {DIM}-D fields; each command a fresh process, its own peak resident memory "
          f"(VmHWM); the program alone (drsplat.cli imported): {baseline / 1e6:,.0f} MB. B/Gaussian: the peak's growth from the "
          "previous size over the Gaussians added (what a Gaussian costs, the fixed costs left out)")
    print(format_table(["field", "Gaussians", "file B/Gaussian", "command", "peak MB", "B/Gaussian", "s"], rows))
    print(machine_line())
    return 0
