"""Messages shown by the viewer: a log with levels, the latest one as the status line."""

from __future__ import annotations

import logging
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

    def latest(self) -> Message | None:
        return self[-1] if self else None
