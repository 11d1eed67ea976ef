"""The process-wide state a test must leave as it found it (the project's test standard).

tests/conftest.py captures it around every test and every test module and fails the test (or
the module's last test) that changed it, naming what changed: a test that replaces
builtins.print, sets an environment variable or changes the thread count makes later tests
depend on the order the files run in. The root logger is the one exception: it is put back
(root_logger_kept), not checked.
"""

from __future__ import annotations

import builtins
import logging
import os
import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass


# Set once, to the same value, when a library is first imported (whichever test imports it
# first adds them, in any order): only their appearance is allowed, never a change.
SET_ON_IMPORT = {
    "TOKENIZERS_PARALLELISM": "open_clip",
    "TORCHINDUCTOR_CACHE_DIR": "open_clip (through torch._inductor)",
    "TCM_ENABLE": "open3d",
    "PYGLFW_LIBRARY": "imgui_bundle (the GLFW library it ships)",
}


@dataclass(frozen=True)
class ProcessState:
    builtins: dict[str, object]
    environ: dict[str, str]
    cwd: str
    signal_handlers: dict[str, object]
    thread_counts: dict[str, int]  # numba, torch, faiss: only those already imported

    @classmethod
    def capture(cls) -> ProcessState:
        return cls(
            builtins=dict(vars(builtins)),
            environ={k: v for k, v in os.environ.items() if k != "PYTEST_CURRENT_TEST"},  # pytest's, set per phase
            cwd=os.getcwd(),
            signal_handlers={sig.name: signal.getsignal(sig) for sig in signal.valid_signals() if isinstance(sig, signal.Signals)},
            thread_counts=_thread_counts(),
        )

    def changes(self, after: ProcessState) -> list[str]:
        """What differs in `after`, one line each (empty when nothing does)."""
        found = [f"builtins.{name}" for name in _changed_keys(self.builtins, after.builtins, same=lambda a, b: a is b)]
        found += [f"os.environ[{name!r}]" for name in _changed_keys(self.environ, after.environ)
                  if not (name in SET_ON_IMPORT and name not in self.environ)]
        if self.cwd != after.cwd:
            found.append(f"the working directory ({self.cwd} -> {after.cwd})")
        found += [f"the {name} handler" for name in _changed_keys(self.signal_handlers, after.signal_handlers)]
        # a library imported during the test had no count before: only a changed count counts
        found += [f"{name}'s thread count ({self.thread_counts[name]} -> {after.thread_counts[name]})"
                  for name in self.thread_counts.keys() & after.thread_counts.keys() if self.thread_counts[name] != after.thread_counts[name]]
        return found


@contextmanager
def root_logger_kept() -> Iterator[None]:
    """Put the root logger's level and handlers back afterwards.

    Tests run the CLI's main() in-process, and main() configures logging the way the real
    program must (drsplat.cli.setup_logging replaces the root handlers); restoring it here keeps
    those tests independent without each one restoring it. pytest's own capture handlers change
    per test phase and are left to pytest.
    """
    root = logging.getLogger()
    level, handlers = root.level, [h for h in root.handlers if not type(h).__module__.startswith("_pytest")]
    try:
        yield
    finally:
        ours = [h for h in root.handlers if not type(h).__module__.startswith("_pytest")]
        for handler in ours:
            if handler not in handlers:
                root.removeHandler(handler)
        for handler in handlers:
            if handler not in root.handlers:
                root.addHandler(handler)
        root.setLevel(level)


def _changed_keys(before: dict, after: dict, same=lambda a, b: a == b) -> list[str]:
    return sorted(k for k in before.keys() | after.keys() if k not in before or k not in after or not same(before[k], after[k]))


def _thread_counts() -> dict[str, int]:
    counts = {}
    parallel = sys.modules.get("numba.np.ufunc.parallel")
    if parallel is not None and parallel._is_initialized:  # asking earlier would start numba's threads
        counts["numba"] = parallel.get_num_threads()
    if "torch" in sys.modules:
        counts["torch"] = sys.modules["torch"].get_num_threads()
    if "faiss" in sys.modules:
        counts["faiss"] = sys.modules["faiss"].omp_get_max_threads()
    return counts
