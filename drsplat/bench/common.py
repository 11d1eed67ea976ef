"""Shared helpers for benchmarks: timing medians, peak memory, table printing."""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

from drsplat.commands.common import MAX_COUNT, MAX_IMAGE_WIDTH, positive_int
from drsplat.errors import DrsplatError
from drsplat.memory import peak_rss

MAX_BENCH_GAUSSIANS = 100_000_000  # a scene built in memory for timing (blob, random Gaussians): ~6 GB at this size


def median_seconds(fn: Callable[[], object], repeats: int = 5, warmup: int = 1) -> float:
    """Median wall time of `fn()` over `repeats` runs after `warmup` untimed runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, in MB."""
    return peak_rss() / 2**20


def machine_line() -> str:
    """The machine a bench ran on, and which AVX-512 look-up-table kernels ran there: without the 8-bit one the 8-bit
    tables score slower than float32 ones, with it ~1.8x faster (round 101b F5: the line did not say; round 103a F1: the
    float32 kernel needs avx512f only, the 8-bit one avx512bw and avx512vbmi too, which Skylake-SP lacks)."""
    import os

    from drsplat.lang.lut import simd_available, simd_q8_available

    kernels = [name for name, there in (("float32", simd_available()), ("8-bit", simd_q8_available())) if there]
    simd = f"AVX-512 table kernels: {' and '.join(kernels)}" if kernels else "no AVX-512 table kernels (portable ones)"
    return f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, {simd}, Python {platform.python_version()}"


def format_table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A plain Markdown table (pastes into the README as is: a "|" inside a header or cell, as in
    "max |Δ|", is written "\\|", which a Markdown table shows as "|")."""
    def cell(v: object) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v).replace("|", "\\|")

    headers = [cell(h) for h in headers]
    body = [[cell(v) for v in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in body)) if body else len(h) for i, h in enumerate(headers)]
    line = lambda cells: "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"  # noqa: E731
    return "\n".join([line(headers), "|" + "|".join("-" * (w + 2) for w in widths) + "|", *(line(r) for r in body)])


# ----------------------------------------------------------------------------- argparse types (checked before any work)


def parse_count(text: str) -> int:
    """'100k' -> 100000, '1.5M' -> 1500000, '42' -> 42; ValueError for anything else (inf and nan too)."""
    text = text.strip().lower().replace("_", "")
    scale = {"k": 1_000, "m": 1_000_000}.get(text[-1:], 1)
    value = float(text[:-1] if scale > 1 else text) * scale
    if not math.isfinite(value):  # int(inf) raises OverflowError, which argparse would show as a traceback
        raise ValueError(f"{text!r} is not a finite count")
    return int(value)


def count_list_upto(hi: int = MAX_COUNT, what: str = "size") -> Callable[[str], list[int]]:
    """argparse type: comma-separated counts in 1..hi ('100k,1M'), refused at parse time (not after minutes of work)."""

    def parse(text: str) -> list[int]:
        items = [s for s in text.split(",") if s.strip()]
        if not items:
            raise argparse.ArgumentTypeError(f"give at least one {what}, e.g. 100k,1M")
        values = []
        for item in items:
            try:
                value = parse_count(item)
            except ValueError:
                raise argparse.ArgumentTypeError(f"cannot read the {what} '{item.strip()}' as a finite count (use e.g. 100k, 1M, 5M)") from None
            if value < 1:
                raise argparse.ArgumentTypeError(f"{what}s must be at least 1, got '{item.strip()}'")
            if value > hi:
                raise argparse.ArgumentTypeError(f"{what}s must be at most {hi:,}, got '{item.strip()}'")
            values.append(value)
        return values

    parse.__name__ = f"{what} list"
    return parse


def count_upto(hi: int = MAX_COUNT, what: str = "size") -> Callable[[str], int]:
    """argparse type: one count in 1..hi ('500k')."""
    many = count_list_upto(hi, what)

    def parse(text: str) -> int:
        values = many(text)
        if len(values) != 1:
            raise argparse.ArgumentTypeError(f"give one {what}, not '{text}'")
        return values[0]

    parse.__name__ = what
    return parse


count_list = count_list_upto()
count_arg = count_upto()
gaussian_count = count_upto(MAX_BENCH_GAUSSIANS, "Gaussian count")


def int_list(item: Callable[[str], int]) -> Callable[[str], list[int]]:
    """argparse type: comma-separated integers, each checked by the argparse type `item` ('1,5,10')."""

    def parse(text: str) -> list[int]:
        items = [s for s in text.split(",") if s.strip()]
        if not items:
            raise argparse.ArgumentTypeError("give at least one value, e.g. 1,5,10")
        try:
            return [item(s.strip()) for s in items]
        except argparse.ArgumentTypeError as exc:
            raise argparse.ArgumentTypeError(f"in {text!r}: {exc}") from None

    parse.__name__ = "integer list"
    return parse


positive_int_list = int_list(positive_int)


def choice_list(choices: Iterable[str], what: str) -> Callable[[str], list[str]]:
    """argparse type: comma-separated names among `choices`, in the order given, each once ('float32,pq64');
    an unknown name or none at all is a usage error before any work."""
    allowed = tuple(choices)

    def parse(text: str) -> list[str]:
        names = list(dict.fromkeys(s.strip() for s in text.split(",") if s.strip()))
        if not names:
            raise argparse.ArgumentTypeError(f"give at least one {what} among {', '.join(allowed)}")
        unknown = [n for n in names if n not in allowed]
        if unknown:
            raise argparse.ArgumentTypeError(f"unknown {what}{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))}; "
                                             f"choose from {', '.join(allowed)}")
        return names

    parse.__name__ = f"{what} list"
    return parse


def child_env(**extra: str) -> dict[str, str]:
    """The environment of a bench's child process: this one's, with this drsplat first on PYTHONPATH (the copy being
    benched, not an installed one), and `extra` variables."""
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.update(extra)
    return env


def last_error_line(stderr: str) -> str:
    """The last line of a child's stderr (its exception), without the exception's class name."""
    lines = [line for line in stderr.splitlines() if line.strip()]
    return lines[-1].split("Error: ", 1)[-1].strip()[:300] if lines else "no message (killed?)"


def whole_pair(text: str) -> tuple[int, int] | None:
    """'AxB' with two whole numbers >= 1 -> (A, B); None for anything else."""
    a, sep, b = text.strip().lower().partition("x")
    if not (sep and a.strip().isdigit() and b.strip().isdigit() and int(a) > 0 and int(b) > 0):
        return None
    return int(a), int(b)


def view_size(text: str) -> tuple[int, int]:
    """argparse type: a view size 'WxH' of two integers in 1..MAX_IMAGE_WIDTH ('640x480') -> (640, 480)."""
    size = whole_pair(text)
    if size is None:
        raise argparse.ArgumentTypeError(f"'{text}' is not WxH with two whole numbers >= 1, e.g. 640x480")
    if max(size) > MAX_IMAGE_WIDTH:  # larger than any GPU texture; the top-k buffers alone would not fit
        raise argparse.ArgumentTypeError(f"'{text}': each side may be at most {MAX_IMAGE_WIDTH} pixels")
    return size


# ----------------------------------------------------------------------------- inputs and outputs (checked before any work)


def scene_file(path: Path, flag: str) -> Path:
    """`path` when it is a regular file, else one error naming it and `flag` (exit 1): a folder or a
    FIFO is not a scene a bench can read, nor is a missing path."""
    if not path.exists():
        raise DrsplatError(f"{path}: no such scene file ({flag})")
    if not path.is_file():
        kind = "a folder" if path.is_dir() else "a FIFO, device or socket"
        raise DrsplatError(f"{path}: is not a file but {kind} ({flag}); give a scene file (.ply)")
    return path


def guard_bench_outputs(inputs: dict[str, Path | None], outputs: dict[str, Path | None],
                        protected_folders: dict[str, tuple[Path | None, tuple[str, ...]]] | None = None) -> None:
    """Before any work: no output over an input the bench reads (`utils.guard_outputs`: also the inputs
    the command line does not name, such as a default scene or a cache file), and every output
    writable (`utils.check_output_writable`), so that neither is found only after minutes of work."""
    from drsplat.utils import check_outputs_writable, guard_outputs

    guard_outputs(inputs, outputs, protected_folders)
    check_outputs_writable(*outputs.values())
