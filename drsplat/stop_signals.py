"""A process's last words on Ctrl-C and SIGTERM: what its entry points (the `drsplat` command, the viewer's main.py)
do once the outcome is settled. Imports nothing heavy: the console script calls it before drsplat.cli is imported."""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator
from typing import NoReturn

from drsplat.errors import STARTING_NOTE


def ignore_stop_signals() -> None:
    """Ctrl-C and SIGTERM ignored from here on, in a process's entry point once its outcome is settled (the work done,
    or the interrupted start said): such a signal while the interpreter shuts down (0.1-0.8 s) killed the process with
    status 130 / 143, or a KeyboardInterrupt traceback from a library's exit hook, after its last line (probe round 14;
    round 92b: the viewer's `--screenshot`, and a second Ctrl-C at start-up). Never from library code: a test or a
    program calling drsplat keeps its handlers. A signal that arrived before and waits for its handler is let go too
    (signal.signal runs a pending handler first, which raises: the outcome is settled all the same)."""
    if threading.current_thread() is not threading.main_thread():
        return
    while True:
        try:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
            return
        except KeyboardInterrupt:
            continue


def interrupted_start(program: str = "drsplat") -> NoReturn:
    """The one line of a Ctrl-C (or SIGTERM) while Python imports `program`, then exit 1; signals ignored first, so a
    second one cannot turn it into a traceback or a death by the signal (round 92b: 7 of 12 double Ctrl-Cs)."""
    ignore_stop_signals()
    sys.stderr.write(STARTING_NOTE if program == "drsplat" else f"{program}: interrupted while starting; nothing was done\n")
    raise SystemExit(1)


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def stop_signals_held() -> Iterator[None]:
    """Ctrl-C and SIGTERM that arrive in the block are held until it ends, then delivered again to the handlers that were
    there (a KeyboardInterrupt, the default death, a cancel token's handler): for a short clean-up that must not stop
    half-way (round 94a F2: a signal in `outputs_together`'s clean-up left the earlier output's hidden copy behind, while
    the command said it left nothing). Blocking the signal in the main thread would not do: the kernel hands it to any
    thread that has it unblocked (numba's, Ray's), and Python then runs the handler in the main thread all the same. Off
    the main thread, where no handler can be set, the block runs as it is."""
    if threading.current_thread() is not threading.main_thread() or None in map(signal.getsignal, STOP_SIGNALS):
        yield  # None: a handler set outside Python, which could not be put back
        return
    held: list[int] = []
    previous = {signum: signal.getsignal(signum) for signum in STOP_SIGNALS}  # read first: a signal between two installs
    try:  # left the first one installed for good (round 96a F2: a caller's Ctrl-C swallowed from then on)
        for signum in STOP_SIGNALS:
            signal.signal(signum, lambda signum, _frame: held.append(signum))
        yield
    finally:
        pending = put_back_handlers(previous)
        for signum in dict.fromkeys(held):
            signal.raise_signal(signum)
        if pending is not None:
            raise pending


def put_back_handlers(handlers: dict) -> KeyboardInterrupt | None:
    """Set every handler of `handlers` (signal -> handler) again, each to the end, though the first one put back raises as
    the next is (round 97a F2: a Ctrl-C then left SIGTERM held for good) or between the two (round 99a F3: the loop's
    back-jump, where Python runs a pending handler, lay outside the try); returns such an interrupt for the caller."""
    pending = None
    left = list(handlers.items())
    while left:
        try:
            while left:  # setting one again is harmless: the loop ends once every call has run uncut
                signum, handler = left[0]
                signal.signal(signum, handler)
                left.pop(0)
        except KeyboardInterrupt as exc:
            pending = exc
    return pending
