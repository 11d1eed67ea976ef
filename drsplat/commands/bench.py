"""`drsplat bench NAME`: speed and memory tables (never run as tests).

Benchmarks live in drsplat/bench/<name>.py and define `add_bench(subparsers)`. Packages that
build on drsplat (the viewer) add theirs through the `drsplat.bench` entry-point group, so
drsplat never imports them directly.
"""

from __future__ import annotations

import argparse
import importlib
from importlib.metadata import entry_points

BENCHES = ("io", "register", "features", "query", "evaluation", "scale")


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
