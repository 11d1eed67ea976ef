"""Per-user folders of the viewer and writable default outputs.

- config: $DRSPLAT_CONFIG_DIR, else $XDG_CONFIG_HOME/drsplat (~/.config/drsplat): the imgui layout
  (`imgui.ini`), never the working directory;
- data: $DRSPLAT_DATA_DIR, else $XDG_DATA_HOME/drsplat (~/.local/share/drsplat): where outputs go
  when the scene's own folder (or, for the bundled demo, the working folder) is read-only.
"""

from __future__ import annotations

import os
from pathlib import Path

LAYOUT_FILE = "imgui.ini"
IMAGE_FORMATS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG", ".webp": "WEBP", ".bmp": "BMP", ".tif": "TIFF", ".tiff": "TIFF"}


def image_format(path: str | Path) -> str:
    """The PIL format a screenshot named `path` is written in, from its suffix (any case); PNG for a
    name without one (a FIFO, a device). An unknown suffix is a ValueError naming the known ones:
    the file would otherwise hold data its name does not say."""
    suffix = Path(path).suffix.lower()
    if not suffix:
        return "PNG"
    if suffix not in IMAGE_FORMATS:
        raise ValueError(f"{path}: cannot write a {suffix} image; name it .png, .jpg, .webp, .bmp or .tif")
    return IMAGE_FORMATS[suffix]


def typed_path(text: str | Path) -> Path:
    """The path a user typed into a panel, with a leading `~` or `~user` read as the shell reads it
    (the viewer has no shell: `~/sel.ply` made a folder named `~` in the working folder, round 53), and
    typed text without the spaces around it, as the Scene panel's open field reads it (a pasted
    `sel.ply ` was refused as "a .ply  name", a `Q.npy ` as not found: round 61a)."""
    path = Path(text.strip()) if isinstance(text, str) else Path(text)
    try:
        return path.expanduser()
    except RuntimeError:  # no home folder to be found: the path as typed, which says so where it is used
        return path


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


BUNDLED_ASSETS = Path(__file__).resolve().parents[1] / "assets"  # the demo shipped with the package (viewer.demo)


def is_bundled(path: Path) -> bool:
    """Whether `path` lies in the package's own assets (inside the install tree, not the user's files)."""
    try:
        path.resolve().relative_to(BUNDLED_ASSETS)
    except (ValueError, OSError, RuntimeError):
        return False
    return True


def derived_output(scene_path: Path | None, suffix: str) -> Path:
    """`<scene stem><suffix>.ply` beside the scene; in the current working folder for the bundled demo
    (never inside the package); in the user data dir when that folder is read-only."""
    base = scene_path if scene_path is not None else user_data_dir() / "scene.ply"
    if scene_path is not None and is_bundled(scene_path):
        base = Path.cwd() / scene_path.name
    return writable_output(base.with_name(base.stem + suffix + ".ply"))
