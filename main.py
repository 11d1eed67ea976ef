"""drsplat viewer: `python main.py [SCENE.ply] [--source DIR] ...` (see viewer/launch.py, docs/viewer.md)."""

import sys

from viewer.launch import main

if __name__ == "__main__":
    sys.exit(main())
