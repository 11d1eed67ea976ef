"""The `drsplat` command line: one subcommand per module in drsplat/commands.

Exit codes follow Python conventions: 0 success, 1 a user-facing error (bad input, missing
weights, cancelled, an output that cannot be written), 2 a usage error (argparse, or a
`drsplat.errors.UsageError` raised by a command). SIGTERM is handled like Ctrl-C; a closed
stdout (`drsplat ... | head`) ends the command quietly.
"""

from __future__ import annotations

import argparse
import importlib
import contextlib
import logging
import os
import signal
import sys
import threading

from drsplat import __version__
from drsplat.commands.common import ArgumentParser
from drsplat.stop_signals import ignore_stop_signals, put_back_handlers
from drsplat.errors import INTERRUPTED_NOTE, STARTING_NOTE, Cancelled, DrsplatError, UsageError, and_list, escape_hidden, shown_path
from drsplat.utils import describe_os_error, settled_outputs

COMMANDS = ("info", "synth", "features", "register", "pq", "query", "segment", "eval", "bench")

log = logging.getLogger("drsplat")


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="drsplat", description="Language search for 3D Gaussian Splatting scenes (Dr. Splat).")
    parser.add_argument("--version", action="version", version=f"drsplat {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only (no progress bars)")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        importlib.import_module(f"drsplat.commands.{name}").add_parser(subparsers)
    for sub in subparsers.choices.values():
        _add_verbosity(sub)
    return parser


def _add_verbosity(sub: argparse.ArgumentParser) -> None:
    """-v / -q after the subcommand too (`drsplat register ... -q`), and after a nested one (`drsplat
    pq train ... -q`, `eval iou`, `bench ...`); SUPPRESS keeps the global flag's value."""
    sub.set_defaults(_usage_parser=sub)  # a UsageError prints this command's usage, not the top level's
    group = sub.add_argument_group("logging")
    for flags, dest, text in ((("-v", "--verbose"), "verbose", "debug logging"), (("-q", "--quiet"), "quiet", "warnings and errors only (no progress bars)")):
        if not any(f in sub._option_string_actions for f in flags):
            group.add_argument(*flags, dest=dest, action="store_true", default=argparse.SUPPRESS, help=text)
    for action in sub._actions:
        if isinstance(action, argparse._SubParsersAction):
            for nested in action.choices.values():
                _add_verbosity(nested)


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever `sys.stderr` is when a record is emitted, not the stream of the first call (a
    caller that swapped stderr, such as a test capture, never leaves the log pointing at a closed stream),
    with the characters a terminal would not show as itself escaped (`errors.escape_hidden`)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass

    def format(self, record: logging.LogRecord) -> str:
        return escape_hidden(super().format(record))  # names from files (image stems, paths) reach many messages


# PIL says two DEBUG lines for every PNG chunk it reads: noise among drsplat's own lines even with -v (round 94b F3)
CHATTY_LOGGERS = ("PIL",)
LIBRARY_LOGGERS = ("torch",)  # others' INFO lines (torch's "FakeTensor cache stats" at exit) are not this program's: -v shows them


def setup_logging(verbose: bool = False, quiet: bool = False) -> None:
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    logging.basicConfig(level=level, format="%(levelname)s: %(message)s", handlers=[_StderrHandler()], force=True)
    for name in LIBRARY_LOGGERS:
        logging.getLogger(name).setLevel(logging.NOTSET if verbose else max(level, logging.WARNING))
    for name in CHATTY_LOGGERS:
        logging.getLogger(name).setLevel(max(level, logging.WARNING))


def interrupted_note(args: argparse.Namespace, exc: BaseException | None = None) -> str:
    """What an interrupted command's last line adds: its parser's `interrupted_note`, a text or a
    function of the arguments and the exception that stopped it (what the stopped run kept), else
    INTERRUPTED_NOTE."""
    note = getattr(args, "interrupted_note", INTERRUPTED_NOTE)
    return note(args, exc) if callable(note) else note


def after_writing(paths: list[str]) -> str:
    """' after writing a.npy and b.ply (complete)' for an interrupted command's line, '' when it wrote none."""
    return f" after writing {and_list([shown_path(p) for p in paths])} (complete)" if paths else ""


NOT_RETURNED = object()  # a command's result before its function returned (a command may return None)


def main(argv: list[str] | None = None, as_program: bool = False) -> int:
    """Run the command line `argv` (default: sys.argv) and return its exit code. as_program: this is the process's
    own entry (`entry`), whose interrupted start-up may ignore further signals; a program calling main keeps its own."""
    try:
        # imports every command's module: the slow part of start-up (seconds on a busy machine), where
        # SIGTERM killed the process by the signal with no message (probe round 26)
        with sigterm_as_interrupt():
            parser = build_parser()
    except KeyboardInterrupt:
        if as_program:  # a second Ctrl-C must not cut the line (round 92b); a caller of main keeps its handlers (round 93a F5)
            ignore_stop_signals()
        sys.stderr.write(STARTING_NOTE)
        return 1
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # argparse's own parse_args would print the top level's usage for them
        getattr(args, "_usage_parser", parser).error(f"unrecognized arguments: {' '.join(unknown)}")
    setup_logging(args.verbose, args.quiet)
    if args.quiet and hasattr(args, "no_progress"):  # a progress bar is info-level output (round 51: -q still drew bars)
        args.no_progress = True
    result = NOT_RETURNED
    written_so_far = list  # what settled_outputs yields, for a signal before it began
    try:
        with settled_outputs() as written_so_far, sigterm_as_interrupt():
            result = args.func(args)
    except KeyboardInterrupt as exc:
        if result is NOT_RETURNED:
            log.error("interrupted%s; %s", after_writing(written_so_far()), interrupted_note(args, exc))
            return stopped(as_program)
        # a signal as the command's handler block ended, its work done (round 93a F4: "interrupted ..." and exit 1 after
        # the outputs were written): the command's own outcome stands
    except Cancelled as exc:
        log.error("%s; %s", exc, interrupted_note(args, exc))
        return stopped(as_program)
    except UsageError as exc:
        getattr(args, "_usage_parser", parser).print_usage(sys.stderr)
        log.error("%s", exc)
        return 2
    except DrsplatError as exc:
        log.error("%s", exc)
        return 1
    except BrokenPipeError as exc:
        if exc.filename is not None:  # an output file's reader went (a FIFO): the output is not written
            log.error("%s", describe_os_error(exc))
            return 1
        _silence_stdout()  # stdout's reader went (`drsplat ... | head`): nothing is wrong
        return 0
    except MemoryError:
        log.error("out of memory: the input is larger than this machine can hold (see the command's --help for options that use less)")
        return 1
    except OSError as exc:
        log.error("%s", describe_os_error(exc))
        return 1
    try:
        sys.stdout.flush()
    except BrokenPipeError:
        _silence_stdout()
    return int(result or 0)


def stopped(as_program: bool) -> int:
    """Exit code 1 of a command stopped by a signal, once its line is written. The process's own entry ignores further
    signals from here: the stopped command's frames (a run's lock, its checkpoint) are let go as `main` returns, and a
    second Ctrl-C then printed "Exception ignored in: RunLock.__del__ ... KeyboardInterrupt" (round 98d F1)."""
    if as_program:
        ignore_stop_signals()
    return 1


def entry() -> None:
    """The `drsplat` command (console script and `python -m drsplat`): `main`, then its exit code.
    Ctrl-C or SIGTERM while the interpreter then shuts down (0.1-0.8 s) is ignored: the command's
    work is done, and such a signal killed the process with status 130 / 143 and no message, after
    a successful run too (probe round 14)."""
    code = None
    try:
        code = main(as_program=True)
    except KeyboardInterrupt:  # a second signal while main said it was stopped (round 92b), or one as it returned
        ignore_stop_signals()
        if code is None:
            sys.stderr.write("drsplat: interrupted\n")
            code = 1
    ignore_stop_signals()
    sys.exit(code)


@contextlib.contextmanager
def sigterm_as_interrupt():
    """SIGTERM raises KeyboardInterrupt like Ctrl-C, so atomic writes clean up their temp files (the
    command line's and the viewer's one way of it; the previous handler is put back after).

    Commands with a cancellable long job replace this with `drsplat.utils.cancel_on_signals`.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGTERM)
    try:  # installed inside: a SIGTERM just after the install raised before the restore was armed (round 99a F4)
        signal.signal(signal.SIGTERM, signal.default_int_handler)
        yield
    finally:
        # to the end though a Ctrl-C lands as it is put back: it was left raising KeyboardInterrupt after main returned
        pending = put_back_handlers({signal.SIGTERM: previous})  # (round 96a F11)
        if pending is not None:
            raise pending


def _silence_stdout() -> None:
    """After a closed pipe, point stdout at /dev/null so the interpreter's final flush is silent."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


if __name__ == "__main__":
    raise SystemExit(main())
