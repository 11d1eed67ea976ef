"""The `drsplat` console script's entry: imports nothing heavy before it can answer Ctrl-C.

The console script (pyproject's `drsplat = "drsplat.console:entry"`) and `python -m drsplat` both
start here. Importing `drsplat.cli` takes seconds on a busy machine (numpy and every command's module);
a Ctrl-C or SIGTERM then printed a KeyboardInterrupt traceback of 16-41 lines (exit 130) when the
console script imported `drsplat.cli` itself (round 54).
"""

import os
import signal
import sys
from collections.abc import MutableMapping

from drsplat.defaults import C_BLANKS, OPENMP_WAIT_POLICY, openmp_wait_policy
from drsplat.stop_signals import interrupted_start


def prefer_passive_openmp_waits(environ: MutableMapping[str, str] = os.environ) -> None:
    """OMP_WAIT_POLICY = OPENMP_WAIT_POLICY unless the user set it: the drsplat and viewer processes' own setting, made
    before numba or torch loads an OpenMP runtime (each reads it once, at load). Library callers keep theirs. An empty
    value counts as unset (`OMP_WAIT_POLICY= drsplat ...` and `docker -e OMP_WAIT_POLICY=` clear it so); a value the
    runtimes would call invalid ("pasive") is replaced too, with one line that says so: they would spin (round 68a F15)."""
    given = environ.get("OMP_WAIT_POLICY", "")
    if openmp_wait_policy(given) is None:
        if given.strip(C_BLANKS):
            sys.stderr.write(f"drsplat: OMP_WAIT_POLICY={given!r} is neither 'active' nor 'passive'; "
                             f"using {OPENMP_WAIT_POLICY!r}\n")
        environ["OMP_WAIT_POLICY"] = OPENMP_WAIT_POLICY


def entry() -> None:
    """SIGTERM while Python imports the command line is Ctrl-C there: one line, exit 1. Python's own
    handler, not drsplat.cli's context manager: that is the import it guards; `drsplat.cli.main`
    takes over with it before it builds the parser."""
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    prefer_passive_openmp_waits()
    try:
        from drsplat.cli import entry as cli_entry  # the slow import this handler guards
    except KeyboardInterrupt:  # Ctrl-C while Python imports the command line: before any command ran
        interrupted_start()
    cli_entry()
