"""drsplat viewer: `python main.py [SCENE.ply] [--source DIR] ...` (see viewer/launch.py, docs/viewer.md)."""

import sys

from drsplat.console import prefer_passive_openmp_waits
from drsplat.stop_signals import ignore_stop_signals, interrupted_start

prefer_passive_openmp_waits()  # before the viewer's imports load numba's and torch's OpenMP runtimes
try:
    from viewer.launch import main
except KeyboardInterrupt:  # Ctrl-C while Python imports the viewer: before anything was opened or written
    interrupted_start("drsplat viewer")

if __name__ == "__main__":
    try:
        code = main()
    except KeyboardInterrupt:  # a second signal as the viewer said it was stopped, or one as main returned (round 92b)
        ignore_stop_signals()
        sys.stderr.write("drsplat viewer: interrupted\n")
        code = 1
    ignore_stop_signals()  # the work is done: a signal while torch and numba shut down is not a failure (round 92b F1)
    sys.exit(code)
