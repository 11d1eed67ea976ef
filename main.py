"""drsplat viewer: `python main.py [SCENE.ply] [--source DIR] ...` (see viewer/launch.py, docs/viewer.md)."""

import sys

from drsplat.console import prefer_passive_openmp_waits

prefer_passive_openmp_waits()  # before the viewer's imports load numba's and torch's OpenMP runtimes
try:
    from viewer.launch import main
except KeyboardInterrupt:  # Ctrl-C while Python imports the viewer: before anything was opened or written
    sys.stderr.write("drsplat viewer: interrupted while starting; nothing was done\n")
    raise SystemExit(1) from None

if __name__ == "__main__":
    sys.exit(main())
