"""The `drsplat` command line: one subcommand per module in drsplat/commands.

Exit codes follow Python conventions: 0 success, 1 a user-facing error (bad input, missing
weights, cancelled), 2 a usage error (argparse).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from drsplat import __version__
from drsplat.errors import Cancelled, DrsplatError

COMMANDS = ("info", "synth", "features", "register", "pq", "query", "segment", "eval", "bench")

log = logging.getLogger("drsplat")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="drsplat", description="Language search for 3D Gaussian Splatting scenes (Dr. Splat).")
    parser.add_argument("--version", action="version", version=f"drsplat {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        importlib.import_module(f"drsplat.commands.{name}").add_parser(subparsers)
    return parser


def setup_logging(verbose: bool = False, quiet: bool = False) -> None:
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    logging.basicConfig(level=level, format="%(levelname)s: %(message)s", stream=sys.stderr, force=True)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    setup_logging(args.verbose, args.quiet)
    try:
        result = args.func(args)
    except Cancelled as exc:
        log.error("%s; no partial output was written", exc)
        return 1
    except KeyboardInterrupt:
        log.error("interrupted; no partial output was written")
        return 1
    except DrsplatError as exc:
        log.error("%s", exc)
        return 1
    return int(result or 0)


if __name__ == "__main__":
    raise SystemExit(main())
