"""User-facing errors: one clear sentence that names the file, the field and the problem."""

from __future__ import annotations

import json
import unicodedata
from pathlib import Path


HIDDEN_CATEGORIES = {"Cc": "control", "Cf": "format", "Cs": "lone surrogate", "Zl": "line separator", "Zp": "paragraph separator"}


def hidden_character(text: str) -> str | None:
    """A description of the first character of `text` that a terminal would not show as itself
    (a control character such as a newline, ESC or NUL; a format character such as U+202E, which
    reverses the text after it; a lone surrogate; the line and paragraph separators U+2028 / U+2029,
    which log viewers break lines at), or None when there is none."""
    for ch in text:
        category = unicodedata.category(ch)
        if category in HIDDEN_CATEGORIES:
            kind = HIDDEN_CATEGORIES[category]
            return f"a {kind} character (U+{ord(ch):04X})"
    return None


def escape_hidden(text: str) -> str:
    """`text` with every character `hidden_character` would name but newline and tab written as a
    backslash-u escape of its code point (U+202E as the six characters \\u202e): a log line that
    quotes an image or file name then shows it as it is spelled instead of letting U+202E reverse,
    or ESC rewrite, the rest of the line."""
    if hidden_character(text) is None:  # the usual case: one scan, no copy
        return text
    return "".join(ch if ch in "\n\t" or unicodedata.category(ch) not in HIDDEN_CATEGORIES else f"\\u{ord(ch):04x}" for ch in text)


def one_line(text: str) -> str:
    """`text` as one line of a terminal or a status bar: `escape_hidden`, and its line breaks written as \\n and \\r
    (a name holding a newline forged a line of its own, round 54)."""
    return escape_hidden(text).replace("\n", "\\n").replace("\r", "\\r")


def shown_path(path: str | Path) -> str:
    """A path as a message prints it: as it is, or JSON-escaped and quoted when it holds a character
    a terminal would not show as itself (`hidden_character`), so a file named with ESC or a newline
    cannot clear the screen or forge a line of output."""
    text = str(path)
    return json.dumps(text) if hidden_character(text) is not None else text


def and_list(items: list[str]) -> str:
    """'a', 'a and b', 'a, b and c'."""
    return items[0] if len(items) == 1 else f"{', '.join(items[:-1])} and {items[-1]}"


class DrsplatError(Exception):
    """An error caused by the user's input or environment; the CLI prints it and exits 1."""


class InputError(DrsplatError):
    """Bad input file. The message names the file, the field and the problem."""

    def __init__(self, path: str | Path | None, problem: str, field: str | None = None):
        self.path = None if path is None else Path(path)
        self.field = field
        self.problem = problem
        where = shown_path(self.path) if self.path is not None else "input"
        if field:
            where += f": field '{field}'"
        super().__init__(f"{where}: {problem}")

    def __reduce__(self):  # rebuilt from its parts when pickled (a Ray worker's error reaching the driver)
        return type(self), (self.path, self.problem, self.field)


class WeightsUnavailableError(DrsplatError):
    """Model weights could not be found or downloaded."""


class Cancelled(DrsplatError):
    """A long job was cancelled by the user (Ctrl-C or a cancel button)."""


# what the command line adds to a Cancelled or an interrupt (drsplat.cli); `features` adds
# RESUMABLE_NOTE when its output folder holds finished images (its parser's `interrupted_note`);
# `register` adds that the same command resumes when a checkpoint is there (its `interrupted_note`; the
# checkpoint's own warning, Checkpoint.leave, names it when this run kept it)
INTERRUPTED_NOTE = "no partial output file was left"
STARTING_NOTE = "drsplat: interrupted while starting; nothing was done\n"  # Ctrl-C before any command ran (drsplat.console)
RESUMABLE_NOTE = f"{INTERRUPTED_NOTE}; what was finished is kept, and the same command resumes from it"


class OutputError(DrsplatError):
    """An output cannot be written (it is an input, a directory, on a full or read-only disk...)."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(f"cannot write {shown_path(self.path) if self.path is not None else 'the output'}: {problem}")

    def __reduce__(self):  # rebuilt from its parts when pickled, as InputError
        return type(self), (self.path, self.problem)


class UsageError(DrsplatError):
    """A command-line value that is out of range; the CLI exits 2 as argparse does."""
