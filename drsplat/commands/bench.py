"""`drsplat bench NAME`: speed and memory tables (never run as tests).

Benchmarks live in drsplat/bench/<name>.py and define `add_bench(subparsers)`. Packages that
build on drsplat (the viewer) add theirs through the `drsplat.bench` entry-point group, so
drsplat never imports them directly.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
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
    """A bench's run, preceded by the output guard (no bench writes its plot or screenshot over an input), its
    warnings said once each (`warnings_said_once`)."""
    import functools

    @functools.wraps(func)
    def run(args: argparse.Namespace) -> int:
        from drsplat.commands.common import guard_args

        guard_args(args, tuple(name for name in BENCH_OUTPUTS if getattr(args, name, None) is not None))
        with warnings_said_once():
            return func(args)

    return run


class _OnceFilter(logging.Filter):
    """Passes a warning the first time its logger, text and arguments are seen, and every record below WARNING."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: set[tuple] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING:
            return True
        key = (record.name, record.levelno, str(record.msg), repr(record.args))
        if key in self.seen:
            return False
        self.seen.add(key)
        return True


@contextlib.contextmanager
def warnings_said_once():
    """Within the block, a warning the root logger's handlers already showed is not shown again: a bench repeats the
    same work (each timed repeat loads, prepares and registers again), and a scene's warning once a repeat is no row
    of its table (round 90b F3: `bench render` said a scene's unusable Gaussians 8 times, `bench register` 3)."""
    # a filter per handler: one shared filter would let the first handler show a warning and hide it from the others
    filters = [(handler, _OnceFilter()) for handler in logging.getLogger().handlers]
    for handler, once in filters:
        handler.addFilter(once)
    try:
        yield
    finally:
        for handler, once in filters:
            handler.removeFilter(once)
