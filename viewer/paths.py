"""Per-user folders of the viewer and writable default outputs.

- config: $DRSPLAT_CONFIG_DIR, else $XDG_CONFIG_HOME/drsplat (~/.config/drsplat): the imgui layout
  (`imgui.ini`), never the working directory;
- data: $DRSPLAT_DATA_DIR, else $XDG_DATA_HOME/drsplat (~/.local/share/drsplat): where outputs go
  when the scene's own folder is read-only (e.g. the demo of an installed package).
"""

from __future__ import annotations

import os
from pathlib import Path

LAYOUT_FILE = "imgui.ini"


def user_config_dir() -> Path:
    if os.environ.get("DRSPLAT_CONFIG_DIR"):
        return Path(os.environ["DRSPLAT_CONFIG_DIR"])
    return Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config") / "drsplat"


def user_data_dir() -> Path:
    if os.environ.get("DRSPLAT_DATA_DIR"):
        return Path(os.environ["DRSPLAT_DATA_DIR"])
    return Path(os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share") / "drsplat"


def default_layout_path() -> Path:
    return user_config_dir() / LAYOUT_FILE


def writable_output(preferred: Path) -> Path:
    """`preferred` when its folder is writable, else the same file name in the user data dir."""
    folder = preferred.parent
    if folder.is_dir() and os.access(folder, os.W_OK | os.X_OK):
        return preferred
    return user_data_dir() / preferred.name


def derived_output(scene_path: Path | None, suffix: str) -> Path:
    """`<scene stem><suffix>.ply` beside the scene (or in the user data dir when that is read-only)."""
    base = scene_path if scene_path is not None else user_data_dir() / "scene.ply"
    return writable_output(base.with_name(base.stem + suffix + ".ply"))
