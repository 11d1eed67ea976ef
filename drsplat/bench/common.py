"""Shared helpers for benchmarks: timing medians, peak memory, table printing."""

from __future__ import annotations

import platform
import statistics
import time
from collections.abc import Callable, Sequence

from drsplat.commands.common import positive_int
from drsplat.memory import peak_rss


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
    import os

    return f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"


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
    """'100k' -> 100000, '1.5M' -> 1500000, '42' -> 42; ValueError for anything else."""
    text = text.strip().lower().replace("_", "")
    scale = {"k": 1_000, "m": 1_000_000}.get(text[-1:], 1)
    return int(float(text[:-1] if scale > 1 else text) * scale)


def count_list(text: str) -> list[int]:
    """argparse type: comma-separated counts >= 1 ('100k,1M'), refused at parse time (not after minutes of work)."""
    import argparse

    items = [s for s in text.split(",") if s.strip()]
    if not items:
        raise argparse.ArgumentTypeError("give at least one size, e.g. 100k,1M")
    values = []
    for item in items:
        try:
            value = parse_count(item)
        except ValueError:
            raise argparse.ArgumentTypeError(f"cannot read the size '{item.strip()}' (use e.g. 100k, 1M, 5M)") from None
        if value < 1:
            raise argparse.ArgumentTypeError(f"sizes must be at least 1, got '{item.strip()}'")
        values.append(value)
    return values


def positive_int_list(text: str) -> list[int]:
    """argparse type: comma-separated integers >= 1 ('1,5,10')."""
    import argparse

    items = [s for s in text.split(",") if s.strip()]
    if not items:
        raise argparse.ArgumentTypeError("give at least one value, e.g. 1,5,10")
    try:
        return [positive_int(s.strip()) for s in items]
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"in '{text}': {exc}") from None


def count_arg(text: str) -> int:
    """argparse type: one count >= 1 ('500k')."""
    import argparse

    values = count_list(text)
    if len(values) != 1:
        raise argparse.ArgumentTypeError(f"give one size, not '{text}'")
    return values[0]


def whole_pair(text: str) -> tuple[int, int] | None:
    """'AxB' with two whole numbers >= 1 -> (A, B); None for anything else."""
    a, sep, b = text.strip().lower().partition("x")
    if not (sep and a.strip().isdigit() and b.strip().isdigit() and int(a) > 0 and int(b) > 0):
        return None
    return int(a), int(b)


def view_size(text: str) -> tuple[int, int]:
    """argparse type: a view size 'WxH' of two integers >= 1 ('640x480') -> (640, 480)."""
    import argparse

    size = whole_pair(text)
    if size is None:
        raise argparse.ArgumentTypeError(f"'{text}' is not WxH with two whole numbers >= 1, e.g. 640x480")
    return size
