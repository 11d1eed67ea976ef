"""Messages shown by the viewer: a log with levels, the latest one as the status line."""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

log = logging.getLogger("viewer")

LEVELS = ("info", "warning", "error")


@dataclass
class Message:
    level: str  # "info" | "warning" | "error"
    text: str
    time: float = field(default_factory=time.monotonic)


class MessageLog(list):
    """A list of `Message`s; `add` also logs it (so the terminal has the same record)."""

    def add(self, level: str, text: str) -> Message:
        if level not in LEVELS:
            raise ValueError(f"unknown message level {level!r}")
        log.log({"info": logging.INFO, "warning": logging.WARNING, "error": logging.ERROR}[level], "%s", text)
        message = Message(level, text)
        self.append(message)
        return message

    def record(self, level: str, text: str) -> Message:
        """Add a message that was logged already (a library warning, `LibraryWarnings`): shown, not logged again."""
        message = Message(level, text)
        self.append(message)
        return message

    def latest(self) -> Message | None:
        return self[-1] if self else None


class LibraryWarnings(logging.Handler):
    """The drsplat library's warnings (logger "drsplat") added to a MessageLog while installed (`with`):
    what a load finds (codes that no longer match their codebook, a field with no assigned Gaussian,
    rows dropped for NaN) reached only the terminal, and the GUI then said "0 Gaussians" with no
    reason (a viewer probe, 2026-11-30)."""

    def __init__(self, messages: MessageLog):
        super().__init__(logging.WARNING)
        self.messages = messages
        self.thread: int | None = None

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread != self.thread:  # another thread's work (a camera check, a registration) is not what this block did
            return
        self.messages.record("error" if record.levelno >= logging.ERROR else "warning", record.getMessage())

    def __enter__(self) -> "LibraryWarnings":
        self.thread = threading.get_ident()
        logging.getLogger("drsplat").addHandler(self)
        return self

    def __exit__(self, *exc) -> None:
        logging.getLogger("drsplat").removeHandler(self)
