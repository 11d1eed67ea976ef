"""Small shared helpers: atomic writes, progress bars, cancellation."""

from __future__ import annotations

import contextlib
import contextvars
import errno
import functools
import hashlib
import json
import logging
import math
import os
import shlex
import socket
import stat
import tempfile
import threading
import time
import unicodedata
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TypeVar

import numpy as np

from drsplat.errors import Cancelled, InputError, OutputError, hidden_character, shown_path
from drsplat.stop_signals import stop_signals_held

log = logging.getLogger("drsplat")

T = TypeVar("T")


TEMP_SUFFIX = ".tmp"


TEMP_NAME_BYTES = 200  # longest output name kept whole in its temp names: '.', '.<pid>.<random>.partial' take up to 26 of 255 bytes


def concat_ranges(starts: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """[Σ sizes] int64: the ranges starts[i] .. starts[i] + sizes[i] - 1 one after another, without
    a Python loop (starts, sizes: [G] integers, sizes ≥ 0)."""
    sizes = np.asarray(sizes, np.int64)
    offsets = np.asarray(starts, np.int64) - (np.cumsum(sizes) - sizes)  # each range's start less the items before it
    return np.arange(int(sizes.sum()), dtype=np.int64) + np.repeat(offsets, sizes)


def temp_stem(path: Path) -> str:
    """The part of `path`'s temp names that stands for its name: the name, or for a name too long
    to fit a temp name in a file system's 255 bytes, its start and a hash of all of it (still unique)."""
    data = path.name.encode("utf-8", "surrogateescape")
    if len(data) <= TEMP_NAME_BYTES:
        return path.name
    digest = hashlib.sha1(data).hexdigest()[:12]
    head = data[: TEMP_NAME_BYTES - len(digest) - 1].decode("utf-8", "ignore")  # never half a character
    return f"{head}~{digest}"


def temp_prefix(path: Path) -> str:
    """Prefix of the temp files `atomic_path` makes for `path`: `.<stem>.<pid>@<host>.` (`temp_stem`;
    the pid and `host_tag` find stale ones)."""
    return f".{temp_stem(path)}.{os.getpid()}@{host_tag()}."


@functools.lru_cache(maxsize=1)
def host_tag() -> str:
    """8 hex digits naming this machine, boot and process namespace: a pid means a process only
    there. A temp file of a run on another host or container sharing the folder is never taken for
    a dead run's (it was: a second `synth` removed a live run's folder, a concurrency probe of
    2026-11-30)."""
    def read(how: Callable[[], str]) -> str:
        try:
            return how()
        except OSError:  # not Linux: the host name alone
            return ""

    parts = (socket.gethostname(), read(lambda: Path("/proc/sys/kernel/random/boot_id").read_text().strip()),
             read(lambda: os.readlink("/proc/self/ns/pid")))
    return hashlib.sha1("|".join(parts).encode()).hexdigest()[:8]


def sweep_stale_temps(path: str | Path, suffix: str = TEMP_SUFFIX) -> int:
    """Delete temp files (or folders) of `path` left by writers that are no longer running; returns how many.

    Temp files are named `.<stem>.<pid>@<host>.<random><suffix>` (`temp_prefix`); one of this host
    (`host_tag`; a name without one is an older drsplat's, taken for this host's) whose pid is not a
    live process was left by a killed run (SIGKILL, power loss) and nothing else will ever remove
    it. Another host's are left alone: whether its process lives cannot be told from here.
    """
    import shutil

    path = Path(path)
    stem = temp_stem(path)
    removed = 0
    try:
        candidates = list(path.parent.glob(f".{glob_escape(stem)}.*{suffix}"))
    except OSError:
        return 0
    for tmp in candidates:
        pid_text, _, host = tmp.name[len(stem) + 2 :].split(".", 1)[0].partition("@")
        if not pid_text.isdigit() or (host and host != host_tag()) or _pid_alive(int(pid_text)):
            continue
        folder = tmp.is_dir() and not tmp.is_symlink()
        try:
            if folder:
                shutil.rmtree(tmp)
            else:
                tmp.unlink()
        except OSError:
            continue
        removed += 1
        log.info("removed a stale temporary %s of an interrupted run: %s", "folder" if folder else "file", tmp)
    return removed


def glob_escape(name: str) -> str:
    """`name` with glob metacharacters escaped."""
    import glob

    return glob.escape(name)


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


PARTIAL_SUFFIX = ".partial"


def file_ancestor(path: Path) -> Path | None:
    """The nearest existing ancestor of `path` when it is not a folder (then `path` cannot be created), else None."""
    for ancestor in Path(path).parents:
        if ancestor.exists():
            return None if ancestor.is_dir() else ancestor
    return None


def dangling_ancestor(path: Path) -> Path | None:
    """The nearest ancestor of `path` that is a symbolic link to nothing (no folder can be made there: mkdir says
    "File exists"), when no existing folder comes first; else None."""
    for ancestor in Path(path).parents:
        if ancestor.exists():
            return None
        if ancestor.is_symlink():
            return ancestor
    return None


def ensure_parent(path: Path) -> None:
    """Create the folder of an output (and its parents), saying so at INFO once it is made (a mistyped
    folder is then seen); OutputError when an ancestor is a file or a link to nothing."""
    blocker = file_ancestor(path)
    if blocker is not None:
        raise OutputError(path, f"{blocker} is a file, not a folder")
    dangling = dangling_ancestor(path)
    if dangling is not None:
        raise OutputError(path, f"{dangling} is a link to {os.readlink(dangling)}, which does not exist")
    missing = not path.parent.is_dir()
    path.parent.mkdir(parents=True, exist_ok=True)
    if missing:
        log.info("created the folder %s for %s", path.parent, path.name)


def check_outputs_writable(*paths: str | Path | None) -> None:
    """`check_output_writable` for each output given (None: not given), before any work."""
    for path in paths:
        if path is not None:
            check_output_writable(path)


WRITE_BITS = 0o222  # a file none of whose write bits is set was protected on purpose (round 59a: root replaced the official codebook)


def check_output_writable(path: str | Path) -> None:
    """OutputError now, before long work, when `path` could not be written later.

    Probes with a real temp file in the nearest existing folder of `path` (os.access is wrong for
    root, ACLs and read-only mounts alike); an existing special file (device, FIFO) is left to its writer. An
    existing file without a write bit is refused even for root, who could replace it: it was protected on purpose.
    """
    path = output_target(Path(path))
    if path.is_dir():
        raise OutputError(path, "is a directory; give a file path")
    if is_special_file(path):
        return
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise OutputError(path, f"{folder} is a file, not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=temp_prefix(path), suffix=TEMP_SUFFIX, dir=folder)
    except OSError as exc:
        raise OutputError(path, refused_new_file(folder, exc)) from None
    os.close(fd)
    os.unlink(probe)
    if path.exists() and not os.access(path, os.W_OK):
        raise OutputError(path, "exists and is not writable (permission denied)")
    refuse_write_protected(path)


def protected_mode(path: Path) -> int | None:
    """The permission bits of `path` (links followed) when it is a regular file or a folder without any write bit, else None
    (writable, another kind of node, or nothing there). Root may replace such a file, but its mode says it is to be kept
    (round 59a: `pq train --out` replaced a 0444 codebook in a 0555 folder)."""
    try:
        mode = path.stat().st_mode
    except OSError:
        return None
    if (stat.S_ISREG(mode) or stat.S_ISDIR(mode)) and not mode & WRITE_BITS:
        return mode & 0o777
    return None


def refuse_write_protected(path: Path) -> None:
    """OutputError when `path` (an output's target) is a regular file without any write bit (`protected_mode`)."""
    mode = protected_mode(path)
    if mode is not None and path.is_file():
        raise OutputError(path, f"exists and is write-protected (mode {mode:04o}); make it writable or remove it to have it replaced")


def refuse_write_protected_tree(folder: Path) -> None:
    """`refuse_write_protected` for a folder output about to be replaced whole: the folder, a folder in it, or a regular
    file in it without a write bit (round 60a: `synth` over an earlier dataset deleted a 0444 scene.ply, and replaced a
    0555 folder, as root, without a word; round 60c: a 0555 gt/ in it). Links in it are not followed: its removal deletes
    a link, never what it names."""
    if not folder.is_dir():
        return
    for root, dirs, files in os.walk(folder):  # os.walk lists links to folders among dirs and does not enter them
        for inner in [Path(root)] * (root == str(folder)) + [Path(root) / name for name in dirs + files]:
            mode = None if inner.is_symlink() else protected_mode(inner)
            if mode is not None:
                what = "exists and is write-protected" if inner.is_file() else "is a write-protected folder"
                raise OutputError(inner, f"{what} (mode {mode:04o}); make it writable or remove it to have "
                                         f"{'it' if inner == folder else 'its folder'} replaced")


def refused_new_file(folder: Path, exc: OSError) -> str:
    """Why the existing `folder` did not take a new file, from the OSError of creating one. ENOENT
    there is no missing folder: it is a file system that creates no files on request (/proc, /sys),
    so the cause is said in those words, not as "the parent directory does not exist"."""
    if exc.errno == errno.ENOENT:
        return f"the folder {folder} does not accept new files: its file system creates none on request (a virtual one, such as /proc or /sys)"
    return f"the folder {folder} does not accept new files ({os_error_cause(exc)})"


@contextlib.contextmanager
def atomic_folder(path: str | Path, replaceable: Callable[[Path], bool]) -> Iterator[Path]:
    """Yield an empty temp folder next to `path`; on success it becomes `path` in one rename.

    An existing `path` is replaced only when it is empty or `replaceable(path)` says it is an
    earlier output of the same kind (it is moved aside, the new folder renamed in, the old one
    deleted); otherwise OutputError. On failure or interrupt the temp folder is deleted, and
    temp folders of killed runs are swept first. A link to a folder (or to nothing) is followed: the
    folder it names is replaced and the link stays (renamed over, the link itself became the folder
    and a temp link was left behind; probe round 44).
    """
    import shutil

    path = output_target(Path(path))
    if path.exists() and not path.is_dir():
        raise OutputError(path, "exists and is not a folder")
    if path.is_dir() and any(path.iterdir()) and not replaceable(path):
        raise OutputError(path, "is a non-empty folder that is not an earlier output of this command; choose a new folder")
    refuse_write_protected_tree(path)
    ensure_parent(path)
    sweep_stale_temps(path, PARTIAL_SUFFIX)
    try:
        tmp = Path(tempfile.mkdtemp(prefix=temp_prefix(path), suffix=PARTIAL_SUFFIX, dir=path.parent))
    except OSError as exc:  # a read-only folder: name the output, not the temp folder it never got (round 57c)
        raise OutputError(path, refused_new_file(path.parent, exc)) from None
    os.chmod(tmp, 0o777 & ~_current_umask())
    try:
        yield tmp
        old = None
        # checked again: what the folder holds may have changed while the output was built (another
        # command wrote into it, a user saved a file there), and the old folder is deleted below
        if path.exists() and (not path.is_dir() or (any(path.iterdir()) and not replaceable(path))):
            raise OutputError(path, "changed while this command ran: it is no longer empty or an earlier output of this command "
                                    "(another command wrote into it?); nothing was replaced, choose a new folder or rerun")
        refuse_write_protected_tree(path)
        if path.exists():
            old = Path(tempfile.mkdtemp(prefix=temp_prefix(path), suffix=PARTIAL_SUFFIX, dir=path.parent))
            os.rmdir(old)
            os.replace(path, old)
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def output_target(path: str | Path) -> Path:
    """Where writing `path` lands: a symlink's resolved target (the link itself stays), else `path`.

    A link to a device, FIFO, pipe or socket is returned as it is: such a node is written in place
    through the link, and its resolved name may not be openable at all (`/dev/stdout` on a pipe
    resolves to `/proc/PID/fd/pipe:[N]`, which names no file; probe round 44).
    """
    path = Path(path)
    if path.is_symlink():
        try:
            mode = os.stat(path).st_mode
        except OSError as exc:  # dangling is fine (the target is made); a loop would be replaced by a file (probe round 14)
            if exc.errno == errno.ELOOP:
                raise OutputError(path, "it is a loop of symbolic links (or a chain too long to follow)") from None
        else:
            if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
                return path
        return Path(os.path.realpath(path))
    return path


def is_special_file(path: Path) -> bool:
    """Whether `path` exists and is a character/block device, FIFO or socket (not a regular file or folder).

    Such an output is written in place: a temp file renamed over it would replace the node
    (run as root, `--out /dev/null` would replace /dev/null for the whole system; a FIFO's reader
    would never get the data).
    """
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return False
    return not (stat.S_ISREG(mode) or stat.S_ISDIR(mode))


def file_stamp(path: str | Path | None, *, in_place: bool = False) -> str | None:
    """'size:mtime_ns' of a file (None when it cannot be stat'ed): what rewriting or editing it in
    place changes; a cheap stand-in for its contents when deciding whether earlier work is stale.

    in_place: also its inode and status-change time, 'size:mtime_ns:ino:ctime_ns'. A rewrite that
    keeps the size and puts the old modification time back (`cp -p`, `rsync -a`, `touch -r`) still
    changes these, since no call can set ctime; so does a copy of the folder, so only state that
    never leaves its place (a registration's checkpoint beside its output) should use them."""
    if path is None:
        return None
    try:
        st = os.stat(path)
    except OSError:
        return None
    if in_place:
        return f"{st.st_size}:{st.st_mtime_ns}:{st.st_ino}:{st.st_ctime_ns}"
    return f"{st.st_size}:{st.st_mtime_ns}"


def names_a_folder(path: str | Path) -> bool:
    """Whether a typed output path ends in a path separator: pathlib drops it (Path("newdir/") is
    Path("newdir")), so a file written there would take the folder's name."""
    return str(path).endswith(("/", "\\"))


def work_folder(path: str | Path) -> Path:
    """Where the temp and checkpoint files of an output `path` go: beside its (resolved) target, or the
    system temp folder when it is a device or FIFO (never /dev)."""
    target = output_target(Path(path))
    return Path(tempfile.gettempdir()) if is_special_file(target) else target.parent


def naming_path(exc: OSError, path: Path, *temps: Path) -> OSError:
    """`exc` with `path` as its filename when it names none or only one of our temp files.

    A failed write (ENOSPC, EFBIG) carries no file name; the user needs the output's name, not the
    temp file's. Returns `exc` itself when it already names another file.
    """
    if exc.filename is None or any(str(exc.filename) == str(t) for t in temps):
        renamed = OSError(exc.errno, exc.strerror or str(exc) or exc.__class__.__name__, str(path))
        renamed.__cause__ = exc
        return renamed
    return exc


def _file_identity(path: Path) -> tuple[int, int] | None:
    """(inode, mtime in ns) of a regular file, None for a missing path or one that is no regular file."""
    try:
        st = path.stat()
    except OSError:
        return None
    return (st.st_ino, st.st_mtime_ns) if stat.S_ISREG(st.st_mode) else None


def real_number(value: object) -> float:
    """float(value) for a number a caller gives (a float, an int, a 0-d array, a torch scalar, a Decimal, "0.01"), NaN for
    a bool or anything float() cannot take: what the checks of a near plane or a temperature judge (round 99a F5: a 0-d
    array was refused as not positive)."""
    if isinstance(value, (bool, np.bool_)):
        return math.nan
    try:
        return float(value)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an int past float's range (round 68a F10)
        return math.nan


@contextlib.contextmanager
def outputs_together(paths: Iterable[str | Path | None]) -> Iterator[None]:
    """A command's outputs written as one set: when the block fails after writing some of them, the
    regular files among `paths` that it wrote are undone, so a failed command leaves the set as it was
    instead of half of it (LABELS.npy beside a missing coloured PLY). A new file is removed; a file
    that was there is put back: it is kept under a second name (a hard link, `.<stem>.<pid>@<host>.kept.tmp`,
    which a later write's sweep removes if this process is killed) until the block ends. Until round 61b
    replaced ones were removed too: an interrupted re-export lost the earlier export's codebook, and
    an interrupted `segment` the earlier LABELS.npy. Where no link can be made (another file system
    type), a replaced file is removed as before. Each file is still written atomically on its own; a
    device or FIFO output is left as it is."""
    covered = _COVERED.get()
    given = [Path(p) for p in paths if p is not None]
    targets = [output_target(p) for p in given]  # a link's target holds what is written: the link (the user's) stays
    # an enclosing block keeps and puts back its own outputs: a second kept copy of one (the same name) lost the earlier
    # file when both undid it (round 97a F1: `eval scannet`'s --json, in its own block inside --save-labels')
    given, targets = [g for g, t in zip(given, targets) if _written_key(t) not in covered], [t for t in targets if _written_key(t) not in covered]
    covering = token = None
    before: list[tuple[int, int] | None] = []
    kept: list[Path | None] = []
    settled: list[bool] = []
    written: dict[str, tuple[int, int] | None] = {}
    ended = cleaned = False
    interrupt = None
    try:
        # whole or not at all: a signal half-way left the context variables set for good (later blocks took their
        # outputs as covered: not put back) or a kept copy no clean-up knew of (round 98a F4 / F5)
        with stop_signals_held():
            covering = _COVERED.set(covered | {_written_key(t) for t in targets})
            before = [_file_identity(t) for t in targets]
            kept = [_kept_copy(t) if then is not None else None for t, then in zip(targets, before)]
            settled = [copy is None for copy in kept]  # a kept copy is let go only once its file needs it no more
            token = _WRITTEN.set(written)
        yield
        ended = True  # all the rest under the held signals (round 96a F1: a signal before them left the kept copies)
    except BaseException:
        for i, (target, then, copy) in enumerate(zip(targets, before, kept)):
            now = _file_identity(target)
            # only what this block wrote, as it wrote it: another writer's file there since is left alone (round 62a: put
            # back over a finished command's outputs)
            if now is None or now == then or written.get(_written_key(target)) != now:
                settled[i] = True
                continue
            with contextlib.suppress(OSError):
                if copy is not None:
                    os.replace(copy, target)
                    log.info("put back the earlier %s: the other outputs of this command were not written", shown_path(target))
                else:
                    target.unlink()
                    log.info("removed %s: the other outputs of this command were not written", shown_path(target))
            settled[i] = True
        raise
    finally:
        while not cleaned:  # a signal as the hold began (before its handlers were in) skipped the clean-up (round 98a F7)
            try:
                with stop_signals_held():
                    if ended:
                        settled = [True] * len(kept)
                        _note_settled(given, targets, written)
                    if token is not None:
                        _WRITTEN.reset(token)
                    if covering is not None:
                        _COVERED.reset(covering)
                    outer = _WRITTEN.get()
                    if outer is not None:
                        outer.update(written)
                    for copy, done in zip(kept, settled):
                        if copy is not None and done:  # one not put back yet (a second Ctrl-C in the loop) stays for the user (round 62a)
                            with contextlib.suppress(OSError):
                                copy.unlink()
                    cleaned = True
            except KeyboardInterrupt as exc:  # raised before the clean-up, or by the hold as it ended after it
                interrupt = exc
        if interrupt is not None:
            raise interrupt


_WRITTEN: contextvars.ContextVar[dict | None] = contextvars.ContextVar("drsplat_written_outputs", default=None)
_SETTLED: contextvars.ContextVar[dict | None] = contextvars.ContextVar("drsplat_settled_outputs", default=None)
_COVERED: contextvars.ContextVar[frozenset] = contextvars.ContextVar("drsplat_covered_outputs", default=frozenset())


def _note_settled(given: list[Path], targets: list[Path], written: dict[str, tuple[int, int] | None]) -> None:
    """Record, for an enclosing `settled_outputs`, the outputs of an `outputs_together` block that ended well: each
    given path with the file its block wrote at its target."""
    record = _SETTLED.get()
    if record is not None:
        for path, target in zip(given, targets):
            if _written_key(target) in written:
                record[str(path)] = (target, written[_written_key(target)])


@contextlib.contextmanager
def settled_outputs() -> Iterator[Callable[[], list[str]]]:
    """Yields a function that lists the outputs `outputs_together` blocks wrote and settled since the block began and
    that still hold what they wrote (a later failed block may have put one back): what an interrupted command can say
    it wrote (round 94a F1: a signal after the outputs were in place said only "interrupted; no partial output file
    was left", as if nothing had been written)."""
    record: dict[str, tuple[Path, tuple[int, int] | None]] = {}
    token = _SETTLED.set(record)
    try:
        yield lambda: [path for path, (target, then) in record.items() if _file_identity(target) == then]
    finally:
        _SETTLED.reset(token)


def _written_key(target: Path) -> str:
    return os.path.abspath(target)


def _note_written(target: Path) -> None:
    """Record, for an enclosing `outputs_together`, the file `atomic_path` just put at `target`."""
    written = _WRITTEN.get()
    if written is not None:
        written[_written_key(target)] = _file_identity(target)


def _kept_copy(target: Path) -> Path | None:
    """A second name (hard link) for the file at `target`, beside it, or None where none can be made."""
    copy = target.with_name(f"{temp_prefix(target)}kept{TEMP_SUFFIX}")
    try:
        with contextlib.suppress(FileNotFoundError):
            copy.unlink()
        os.link(target, copy)
    except OSError:
        return None
    return copy


@contextlib.contextmanager
def atomic_path(path: str | Path, cancel: CancelToken | None = None) -> Iterator[Path]:
    """Yield a temporary path next to `path`; rename it over `path` only if the block succeeds.

    Readers never see a half-written file, and an interrupted job leaves the old file intact.
    Temp files of earlier killed runs writing the same path are swept first (`sweep_stale_temps`).
    A symlinked `path` is written (atomically) at its resolved target, so the link stays a link;
    an existing device or FIFO (`is_special_file`) is yielded itself and written in place, a FIFO
    once a process reads it (`fifo_reader`, which checks `cancel` while it waits).
    An OSError in the block that names no file (a full disk) is re-raised naming `path`.
    """
    shown = Path(path)
    target = output_target(shown)
    if is_special_file(target):
        try:
            with fifo_reader(target, shown, cancel):
                yield target
        except OSError as exc:
            raise naming_path(exc, shown) from None
        return
    tmp_path = None
    try:
        with stop_signals_held():  # a signal as the temp file was made (mkstemp to its chmod) left it behind (round 98a F6)
            tmp_path = temp_beside(shown)
        yield tmp_path
        with stop_signals_held():  # a signal between the rename and its record left the new file out of an enclosing
            replace_with_temp(tmp_path, shown)  # `outputs_together`'s undo: one output new, another old (round 96a F3)
            _note_written(target)
    except OSError as exc:
        raise naming_path(exc, shown, *([tmp_path] if tmp_path is not None else [])) from None
    finally:
        with stop_signals_held():  # a second Ctrl-C as the temp file was removed left it behind (round 100a F3)
            if tmp_path is not None and tmp_path.exists():
                tmp_path.unlink()


FIFO_POLL_SECONDS = 0.1  # how often a FIFO output with no reader yet is tried again (and the cancel token read)


@contextlib.contextmanager
def fifo_reader(path: Path, shown: Path | None = None, cancel: CancelToken | None = None, wait: bool = True) -> Iterator[None]:
    """Wait until some process has the FIFO `path` open to read, then hold a write end of it open
    while the block writes (nothing for any other path). shown: the name to log (default `path`).
    wait=False: an OutputError at once when no process reads it (a window's thread must not block;
    probing without holding the write end open would send the reader an end-of-file).

    Opening a FIFO to write blocks until a reader opens it, inside a system call that the signal
    handler of `cancel_on_signals` does not end (it only cancels, and Python retries the call): a
    registration that had finished its work with no reader waited for a second Ctrl-C. The open is
    tried without blocking instead (ENXIO: no reader yet), every FIFO_POLL_SECONDS, with `cancel`
    read in between (Cancelled; a registration keeps its checkpoint). The write end held open keeps
    the reader from seeing end-of-file before the block opens its own."""
    try:
        is_fifo = stat.S_ISFIFO(os.stat(path).st_mode)
    except OSError:
        is_fifo = False
    if not is_fifo:
        yield
        return
    fd, said = None, False
    while fd is None:
        try:
            fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
        except OSError as exc:
            if exc.errno != errno.ENXIO:
                raise
            if not wait:
                raise OutputError(shown or path, "it is a FIFO that no process reads yet; start its reader first (e.g. "
                                                 f"`cat {shlex.quote(str(shown or path))} > FILE`), then write again") from None
            if cancel is not None:
                cancel.raise_if_cancelled()
            if not said:
                log.info("waiting for a process to read the FIFO %s", shown or path)
                said = True
            time.sleep(FIFO_POLL_SECONDS)
    try:
        yield
    finally:
        os.close(fd)


def temp_beside(path: str | Path) -> Path:
    """A new empty temp file beside the regular-file output `path` (a symlink's resolved target),
    with the permissions of the file it replaces (`replaced_mode`), to be renamed over it by `replace_with_temp` (`atomic_path` does
    both). Stale temps of killed writers are swept first; OutputError when `path` is a folder or
    one of its ancestors a file."""
    shown = Path(path)
    target = output_target(shown)
    if target.is_dir():
        raise OutputError(shown, "is a directory")
    ensure_parent(target)
    sweep_stale_temps(target)
    try:
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(target), suffix=TEMP_SUFFIX, dir=target.parent)
    except OSError as exc:  # a read-only folder: name the output, not the temp file it never got
        if exc.errno == errno.ENOENT and target.parent.is_dir():  # the folder is there: its file system makes no files
            raise OutputError(shown, refused_new_file(target.parent, exc)) from None
        raise naming_path(exc, shown, *([Path(exc.filename)] if exc.filename is not None else [])) from None
    os.close(fd)
    os.chmod(tmp, replaced_mode(target))  # mkstemp makes 0600
    return Path(tmp)


def odd_entry_kind(path: Path) -> str | None:
    """What `path` is when it is neither absent nor a regular file ("a symbolic link", "a folder",
    "not a regular file": a FIFO, a device), else None. For the files drsplat keeps for itself
    (checkpoints, journals): writing through a link lands on whatever file it names, a FIFO blocks,
    a device reads without end. Read with lstat, so a link is never followed."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return None
    if stat.S_ISREG(mode):
        return None
    return "a symbolic link" if stat.S_ISLNK(mode) else "a folder" if stat.S_ISDIR(mode) else "not a regular file"


def replaced_mode(target: Path) -> int:
    """The permissions a new output at `target` gets: those of the regular file it replaces (a file a
    user made private with chmod 600 stays private), else a new file's (0666 less the umask)."""
    try:
        st = os.stat(target)
    except OSError:
        return 0o666 & ~_current_umask()
    return stat.S_IMODE(st.st_mode) if stat.S_ISREG(st.st_mode) else 0o666 & ~_current_umask()


def replace_with_temp(tmp: Path, path: str | Path) -> None:
    """Rename the finished temp file `tmp` (from `temp_beside(path)`) over `path`'s target (a
    symlink stays a link); an OSError names `path`. The temp file's data reach the disk before the rename, and the rename
    before this returns: a power loss right after a registration, whose checkpoint is deleted next, could otherwise
    keep the new name over lost data (round 72b F3; ~0.4 ms a file here)."""
    shown = Path(path)
    target = output_target(shown)
    refuse_write_protected(target)
    try:
        _fsync_path(tmp)
        os.replace(tmp, target)
    except OSError as exc:
        raise naming_path(exc, shown, tmp) from None
    with contextlib.suppress(OSError):  # a file system that cannot sync a folder (some network ones): the rename stands as it is
        _fsync_path(target.parent, folder=True)


def _fsync_path(path: Path, folder: bool = False) -> None:
    """fsync a written file (opened for writing: a temp file takes the mode of the output it replaces, which may be
    write-only, 0200: round 73a F1) or a folder. A file this process may not open again is left as written (its data
    were written; only their timing is not forced); an error of the sync itself (EIO) is the write's own and raised."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY) if folder else os.open(path, os.O_WRONLY)
    except PermissionError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _current_umask() -> int:
    """The process umask, read without changing it where /proc allows (os.umask is not thread-safe)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_bytes_atomic(path: str | Path, *parts: bytes, before_replace: Callable[[], object] | None = None) -> None:
    """Write the byte strings one after the other to `path` through `atomic_path` (temp + rename;
    a device or FIFO in place). before_replace: called once they are written, just before the rename."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            for part in parts:
                f.write(part)
        if before_replace is not None:
            before_replace()


def save_npy_atomic(path: str | Path, array: np.ndarray) -> None:
    """np.save through a temp file + rename (np.save would append .npy to a temp name)."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            if is_special_file(tmp):  # a FIFO or device cannot seek, which np.save's fast path asks for
                array = np.ascontiguousarray(array)
                np.lib.format.write_array_header_1_0(f, np.lib.format.header_data_from_array_1_0(array))
                f.write(array.reshape(-1).view(np.uint8))
            else:
                np.save(f, array)


class CancelToken:
    """Cooperative cancellation shared between a worker and a GUI or signal handler."""

    def __init__(self) -> None:
        self._event = threading.Event()

    def cancel(self) -> None:
        self._event.set()

    @property
    def cancelled(self) -> bool:
        return self._event.is_set()

    def raise_if_cancelled(self) -> None:
        if self._event.is_set():
            raise Cancelled("cancelled by the user")


def compiled_here(kernel: object) -> bool:
    """Whether numba's cache holds `kernel` (an `njit(cache=True)` dispatcher) as this process would load it: compiled
    from this source and numba version for this machine's CPU (numba keys its index by both; a cache another CPU type
    filled, or one left by an older drsplat or numba, is compiled again: round 68a F4). True when the cache cannot be
    asked (no cache, or numba's internals moved)."""
    try:
        cache = kernel._cache
        wanted = cache._index_key(None, kernel.targetctx.codegen())[1:]  # (CPU, code's hashes): the key without its signature
        return any(tuple(key[1:]) == wanted for key in cache._cache_file._load_index())
    except Exception:  # noqa: BLE001 - a cache numba cannot read is its own to report; this only decides a note
        return True


def progress(iterable: Iterable[T], desc: str, total: int | None = None, enabled: bool = True, unit: str = "it") -> Iterable[T]:
    """Wrap an iterable with a tqdm bar on stderr (disabled when not wanted)."""
    from tqdm.auto import tqdm

    return tqdm(iterable, desc=desc, total=total, disable=not enabled, unit=unit, dynamic_ncols=True, leave=False)


def host_reachable(url: str, timeout: float = 3.0) -> bool:
    """Whether the host of `url` resolves and accepts a TCP connection within `timeout` seconds.

    Download clients retry with back-off for tens of seconds on a closed network; one cheap
    probe lets an offline user get the "how to provide weights" message at once. Where a proxy
    serves the URL (http_proxy, https_proxy, ... and not no_proxy) the host is only reached through
    it, which the download does and a direct probe cannot: True, the download decides (round 105a
    F6: behind a proxy the SAM weights were "cannot be downloaded" without a try).
    """
    import socket
    import urllib.request
    from urllib.parse import urlparse

    parsed = urlparse(url)
    proxies = urllib.request.getproxies()  # "all": ALL_PROXY, which huggingface_hub's client honours (round 106a F4)
    if (parsed.scheme in proxies or "all" in proxies) and not urllib.request.proxy_bypass(parsed.hostname or ""):
        return True
    port = parsed.port or (443 if parsed.scheme == "https" else 80)
    try:
        with socket.create_connection((parsed.hostname or "", port), timeout=timeout):
            return True
    except OSError:
        return False


# ----------------------------------------------------------------------------- .npy inputs

MAX_NPY_HEADER_BYTES = 1 << 16


def read_npy_header(f) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) from the .npy header at the position of the binary file object `f` (left at
    the data). A bad magic or header is one ValueError naming no byte of it: numpy parses the header
    with ast and tokenize, whose errors quote it (round 89b F4) or are of kinds no caller expects
    (tokenize.TokenError: a snapshot's damaged header was a traceback); OSError passes through."""
    try:
        version = np.lib.format.read_magic(f)
        reader = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, _fortran, dtype = reader(f, max_header_size=MAX_NPY_HEADER_BYTES)
    except OSError:
        raise
    except Exception as exc:
        raise ValueError(f"not a readable .npy header ({type(exc).__name__})") from None
    return shape, dtype


def regular_file(path: str | Path) -> Path:
    """`path` as a Path if it is a regular file; else InputError "file not found" or "is not a file"
    (a FIFO or device would block a read or never end, a folder cannot be read)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "is not a file" if path.exists() else unreachable_cause(path))
    return path


def unreachable_cause(path: Path, missing: str = "file not found") -> str:
    """Why a path that does not resolve to anything is not there: a link loop, a link whose target is
    missing (it exists, so "file not found" would puzzle), or no such file (`missing`)."""
    try:
        os.stat(path)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "is a loop of symbolic links (too many levels to resolve)"
    if path.is_symlink():
        return f"is a symbolic link to {os.readlink(path)}, which does not exist"
    return missing


def spread_rows(rows: np.ndarray, count: int) -> np.ndarray:
    """Every ⌈N / count⌉-th row of rows [N, ...]: at most `count` rows spread over all of them (a
    view, not a copy), the sample the scene-wide estimates take."""
    return rows[:: max(1, -(-len(rows) // count))]


def clipped(text: str, limit: int) -> str:
    """`text` as a message quotes it: cut after `limit` characters, its length said, so a hostile
    value of megabytes cannot flood the terminal."""
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text):,} characters)"


def name_problem(names: list[str]) -> tuple[int, str, object] | None:
    """The first entry of a list of label names that may not label a table or a legend: (index,
    "empty", None) for a blank one, (index, "hidden", description) for one holding a character a
    terminal would not show as itself (`hidden_character`: a newline, ESC, U+202E, a lone
    surrogate), (index, "repeat", earlier index) for one equal to an earlier one apart from spaces
    around it or in how its accents are encoded (Unicode NFC); None when every entry may. The one rule of `checked_names` and `checked_phrases`."""
    seen: dict[str, int] = {}
    for i, name in enumerate(names):
        if not name.strip():
            return i, "empty", None
        hidden = hidden_character(name)
        if hidden is not None:
            return i, "hidden", hidden
        key = unicodedata.normalize("NFC", name.strip())  # "café" composed or as "cafe" + U+0301: one name to the eye
        if key in seen:
            return i, "repeat", seen[key]
        seen[key] = i
    return None


def checked_names(path: Path, names: list) -> list[str]:
    """The names as given, or one error naming the first entry that is not a string or that
    `name_problem` refuses, counted from 1 as the comma-separated flags' entries are (round 100b F5: "entry 1" was the
    first label of --labels and the second name of a --names file) (the names label the printed table and the coloured PLY's legend: a list,
    a blank or a twice-used name would mislabel it)."""
    for i, name in enumerate(names):
        if not isinstance(name, str):
            raise InputError(path, f"entry {i + 1} of {len(names)} is {json.dumps(name)[:60]}, not a string; expected a JSON list of label names")
    problem = name_problem(names)
    if problem is not None:
        i, kind, detail = problem
        shown = json.dumps(names[i])[:60]
        if kind == "empty":
            raise InputError(path, f"entry {i + 1} of {len(names)} is an empty name ({shown})")
        if kind == "hidden":
            raise InputError(path, f"entry {i + 1} of {len(names)} ({shown}) holds {detail}, which a terminal would not show as itself")
        same = "" if names[i] == names[detail] else " (apart from spaces around it or how its accents are encoded)"
        raise InputError(path, f"entry {i + 1} of {len(names)} repeats the name {shown} of entry {detail + 1}{same}")
    return names


def json_text(doc: object, indent: int | None = 2) -> str:
    """`doc` as strict JSON: every non-finite float (NaN, ±inf; Python's or numpy's) written as null.
    json.dumps alone writes NaN / Infinity, which JavaScript's JSON.parse and other strict parsers
    reject; where a value is undefined the document's own fields (findings, counts) say why."""

    def strict(value):
        if isinstance(value, dict):
            return {k: strict(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [strict(v) for v in value]
        if isinstance(value, (float, np.floating)):
            return float(value) if math.isfinite(value) else None
        return value

    return json.dumps(strict(doc), indent=indent, allow_nan=False)


def read_json(path: str | Path, what: str) -> object:
    """The JSON document in `path`, a regular file of UTF-8 text (a leading byte-order mark, which
    Windows editors write, is skipped), or one InputError naming the file and why it is not `what`
    (e.g. "a camera file"): not a file, unreadable, not UTF-8 (the byte offset, never the content),
    bad JSON (line and reason), nested too deeply for the parser, or a number of more digits than
    Python converts (sys.get_int_max_str_digits)."""
    path = regular_file(path)
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except OSError as exc:
        raise InputError(path, f"cannot be read ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise InputError(path, f"is not UTF-8 text (bad byte at offset {exc.start}); expected {what}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(path, f"is not valid JSON (line {exc.lineno}: {exc.msg}); expected {what}") from None
    except RecursionError:
        raise InputError(path, f"is JSON nested too deeply to be {what}") from None
    except ValueError:
        raise InputError(path, f"has a number too long to read; expected {what}") from None


def npy_header(path: str | Path) -> tuple[tuple[int, ...], np.dtype, int]:
    """(shape, dtype, data offset) of an .npy file, read from its header only.

    Raises InputError for a file that is not an .npy array, an object/pickle dtype, or a shape
    whose data would need more bytes than the file holds (a header cannot make us allocate).
    """
    path = regular_file(path)
    try:
        with open(path, "rb") as f:
            shape, dtype = read_npy_header(f)
            offset = f.tell()
        size = path.stat().st_size
    except OSError as exc:
        raise InputError(path, f"cannot be read ({exc.strerror or exc})") from None
    except Exception:  # numpy parses the header with ast/tokenize: any error means a bad header (its text is not echoed)
        raise InputError(path, "is not a readable .npy array (bad magic or header)") from None
    if dtype.hasobject:
        raise InputError(path, "holds Python objects (pickle), which drsplat never loads")
    if any(d < 0 for d in shape):
        raise InputError(path, f"has a negative dimension in its shape {shape}")
    need = dtype.itemsize
    for d in shape:
        need *= int(d)
    if offset + need > size:
        raise InputError(path, f"is truncated: its header declares shape {shape} {dtype} ({need} bytes) but only {max(0, size - offset)} bytes of data follow")
    return tuple(int(d) for d in shape), dtype, offset


def load_npy(path: str | Path, what: str = "array", mmap: bool = False) -> np.ndarray:
    """np.load of a trusted-size .npy: header checked against the file size first, never pickles.

    The one reader of every user-supplied .npy (queries, ids, labels, features, embeddings). mmap: the
    array memory-mapped read-only (read a block at a time, a large file is never held whole).
    """
    path = Path(path)
    npy_header(path)
    try:
        return np.load(path, allow_pickle=False, mmap_mode="r" if mmap else None)
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(path, f"is not a readable .npy {what} ({str(exc).splitlines()[0][:120] if str(exc) else exc.__class__.__name__})") from None


# ----------------------------------------------------------------------------- outputs

def _resolved(path: Path) -> Path:
    try:
        return path.expanduser().resolve()
    except (OSError, RuntimeError):
        return path.absolute()


def _same_file(a: Path, b: Path) -> bool:
    if _resolved(a) == _resolved(b):
        return True
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def guard_outputs(
    inputs: dict[str, str | Path | None],
    outputs: dict[str, str | Path | None],
    protected_folders: dict[str, tuple[str | Path | None, tuple[str, ...]]] | None = None,
    protected_trees: dict[str, str | Path | None] | None = None,
) -> None:
    """Refuse to run when an output would replace an input, another output or a protected file.

    inputs / outputs: flag name -> path (None = not given). Paths are compared resolved (symlinks
    followed) and by inode (hard links). protected_folders: flag -> (folder, glob patterns): an
    output inside that folder matching a pattern (e.g. `*_f.npy` in a features folder) is refused.
    protected_trees: flag -> folder: an output that is an existing file anywhere below that folder
    (a dataset whose files are found by name at read time) is refused, without listing the folder.
    An output that is an existing directory is refused too. Raises OutputError naming both flags.
    """
    given_in = {k: Path(v) for k, v in inputs.items() if v is not None}
    given_out = {k: Path(v) for k, v in outputs.items() if v is not None}
    seen: dict[Path, str] = {}
    for flag, out in given_out.items():
        if out.is_dir():
            raise OutputError(out, f"{flag} names a directory; give a file path")
        blocker = file_ancestor(out)
        if blocker is not None:
            raise OutputError(out, f"{flag} lies under {blocker}, which is a file, not a folder")
        dangling = dangling_ancestor(out)
        if dangling is not None:
            raise OutputError(out, f"{flag} lies under {dangling}, a link to {os.readlink(dangling)}, which does not exist")
        for in_flag, inp in given_in.items():
            if _same_file(out, inp):
                # an input named by a flag or an argument reads "the input --embedding"; one named by a phrase ("the registered
                # PLY's codebook") read "the input the registered PLY's codebook" (round 59a)
                named = f"{in_flag} (an input)" if in_flag.startswith("the ") else f"the input {in_flag}"
                raise OutputError(out, f"{flag} is the same file as {named}; writing it would destroy the input. Choose another output path")
        for tree_flag, tree in (protected_trees or {}).items():
            if tree is not None and out.is_file() and _resolved(out).is_relative_to(_resolved(Path(tree))):
                possessive = "'" if tree_flag.endswith("s") else "'s"
                inside = _resolved(out).relative_to(_resolved(Path(tree)))
                raise OutputError(out, f"{flag} is the same file as the input {tree_flag}{possessive} file {inside}; writing it would destroy "
                                       "the input. Choose another output path")
        key = _resolved(out)
        if key in seen and key != _resolved(Path(os.devnull)):  # outputs all thrown away need not be told apart (round 85c F5)
            raise OutputError(out, f"{flag} and {seen[key]} name the same file")
        seen[key] = flag
        for folder_flag, (folder, patterns) in (protected_folders or {}).items():
            if folder is None:
                continue
            if _resolved(out).parent == _resolved(Path(folder)) and any(_resolved(out).match(p) for p in patterns):
                raise OutputError(out, f"{flag} lies in the {folder_flag} folder and is named like one of its files ({', '.join(patterns)}); choose another output path")


def describe_os_error(exc: OSError) -> str:
    """One sentence for an OSError (usually on an output): the path and the cause in words."""
    where = exc.filename if exc.filename is not None else "an output or input file"
    return f"{where}: {os_error_cause(exc)}"


def os_error_cause(exc: OSError) -> str:
    """An OSError's cause in words ("the disk is full (no space left on the device)")."""
    import errno

    causes = {
        errno.ENOSPC: "the disk is full (no space left on the device)",
        errno.EDQUOT: "the disk quota is exceeded",
        errno.EROFS: "the file system is read-only",
        errno.EACCES: "permission denied",
        errno.EPERM: "operation not permitted",
        errno.EISDIR: "the path is a directory",
        errno.ENOTDIR: "a parent of the path is not a directory",
        errno.ENAMETOOLONG: "the file name is too long",
        errno.EFBIG: "file too large (for this file system or the process's file-size limit)",
        errno.ENXIO: "no reader or device behind this special file",
    }
    if exc.errno == errno.ENOENT:
        return missing_cause(exc)
    cause = causes.get(exc.errno or -1) or exc.strerror or str(exc) or f"{exc.__class__.__name__} (the system gave no cause)"
    if exc.errno is None and "written" in cause:  # numpy's tofile after a short write: the OS error itself is lost
        cause = f"the write stopped short ({cause}): the disk is full or a file-size limit was reached"
    return cause


def missing_cause(exc: OSError) -> str:
    """ENOENT's cause in words: "the parent directory does not exist" only when it does not (an
    existing folder on /proc or /sys refuses new files with ENOENT too; see `refused_new_file`)."""
    name = exc.filename
    if isinstance(name, (str, bytes)) and Path(os.fsdecode(name)).parent.is_dir():
        return f"no such file or directory, though its folder {Path(os.fsdecode(name)).parent} exists"
    return "the parent directory does not exist"


# ----------------------------------------------------------------------------- signals

ABORT_GRACE_SECONDS = 2.0  # after a second Ctrl-C, how long the cancelled job has to end by itself


@contextlib.contextmanager
def cancel_on_signals(token: CancelToken, what: str = "the current step") -> Iterator[None]:
    """Ctrl-C or SIGTERM cancels cleanly (the worker checks `token`); a second one aborts.

    The handler never raises: Python runs it between any two bytecodes of the main thread,
    numba's own dispatch code included, where a KeyboardInterrupt became a chain of SystemError
    tracebacks (probe round 14). The first signal cancels, and the job stops at its next check
    (the view, the block, the check's run of masks) keeping what it finished. Python coalesces the
    signals that arrive while a kernel holds the main thread into one handler call, so the signals
    are also written to a wakeup pipe that a watchdog thread reads (`signal.set_wakeup_fd`): from
    the second on, it gives the cancelled job ABORT_GRACE_SECONDS to end by itself and then ends
    the process with exit code 1 and one line (a third ends it at once). Temp files left beside an
    output are swept by the next run that writes it; a checkpoint stays as of its last snapshot,
    as after a kill. Outside the main thread signal handlers cannot be installed and this does
    nothing.
    """
    import signal

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}

    def handler(signum, frame):
        if token.cancelled:
            return  # the watchdog counts it
        name = "Ctrl-C" if signum == signal.SIGINT else "SIGTERM"
        log.warning("%s: stopping after %s (Ctrl-C again to abort)", name, what)
        token.cancel()

    read_end, write_end = os.pipe()
    os.set_blocking(write_end, False)
    done = threading.Event()
    watchdog = threading.Thread(target=_abort_on_repeated_signals, args=(read_end, {int(sig) for sig in previous}, done),
                                name="drsplat-abort-watchdog", daemon=True)
    previous_wakeup = signal.set_wakeup_fd(write_end, warn_on_full_buffer=False)
    for sig in previous:
        signal.signal(sig, handler)
    watchdog.start()
    try:
        yield
    finally:
        done.set()
        for sig, old in previous.items():
            signal.signal(sig, old)
        signal.set_wakeup_fd(previous_wakeup)
        os.close(write_end)  # the watchdog reads end-of-file and returns
        watchdog.join()
        os.close(read_end)


def _abort_on_repeated_signals(read_end: int, signals: set[int], done: threading.Event) -> None:
    """The watchdog of `cancel_on_signals`: counts the cancelling signals written to the wakeup pipe;
    from the second, ends the process unless the job ends within ABORT_GRACE_SECONDS (at once from
    the third). The pipe's end-of-file (the context left) ends the watch."""
    import select

    count, deadline = 0, None
    while True:
        wait = None if deadline is None else max(0.0, deadline - time.monotonic())
        if not select.select([read_end], [], [], wait)[0]:  # the grace time passed
            _abort(done)
            return
        try:
            data = os.read(read_end, 64)
        except OSError:
            return
        if not data:
            return
        count += sum(1 for byte in data if byte in signals)
        if count >= 3:
            _abort(done)
            return
        if count == 2 and deadline is None:
            deadline = time.monotonic() + ABORT_GRACE_SECONDS


def _abort(done: threading.Event) -> None:
    """End the process now (a repeated Ctrl-C), unless the job ended meanwhile."""
    if done.is_set():
        return
    log.error("aborted by a repeated Ctrl-C; a checkpoint beside the output stays as of its last snapshot and the same command "
              "resumes from it, and temp files left beside the output are removed by the next run that writes it")
    logging.shutdown()
    os._exit(1)
