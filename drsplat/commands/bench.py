"""`drsplat bench NAME`: speed and memory tables (never run as tests).

Benchmarks live in drsplat/bench/<name>.py and define `add_bench(subparsers)`. Packages that
build on drsplat (the viewer) add theirs through the `drsplat.bench` entry-point group, so
drsplat never imports them directly.
"""

from __future__ import annotations

import argparse
import importlib
from importlib.metadata import entry_points

BENCHES = ("io", "register", "render", "kernel", "features", "query", "registered", "evaluation", "scale", "startup", "budget")


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("bench", help="speed/accuracy benchmarks that print tables")
    benches = parser.add_subparsers(dest="bench", metavar="BENCH", required=True)
    for name in BENCHES:
        importlib.import_module(f"drsplat.bench.{name}").add_bench(benches)
    for ep in entry_points(group="drsplat.bench"):
        try:
            add_bench = ep.load()
        except ImportError:
            continue  # optional GUI dependencies missing: that bench is simply not offered
        add_bench(benches)
    for bench in benches.choices.values():
        func = bench.get_default("func")
        if func is not None:
            bench.set_defaults(func=_guarded(func))


BENCH_OUTPUTS = ("plot", "screenshot", "out", "json", "trace")  # argument names benches write to


def _guarded(func):
    """A bench's run, preceded by the output guard: no bench writes its plot or screenshot over an input."""
    import functools

    @functools.wraps(func)
    def run(args: argparse.Namespace) -> int:
        from drsplat.commands.common import guard_args

        guard_args(args, tuple(name for name in BENCH_OUTPUTS if getattr(args, name, None) is not None))
        return func(args)

    return run
