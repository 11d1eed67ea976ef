"""The viewer's settings: every choice the user makes in the panels or on the command line.

One `ViewerSettings`, owned by `viewer.state.ViewerState` (`state.settings`): the panels show
and edit it, the state's actions and the window (viewer.app) read it, and the command line
(viewer.launch) fills it. No GUI code here.

What is not a setting stays with its owner: the query's threshold and the display mode belong
to the query (`ViewerState.set_threshold` / `set_mode`, Otsu's threshold per query); the camera
(orbit / fly, field of view, roll) to `viewer.camera.ViewController`; text typed for a one-shot
action (a query phrase, a file to open) and which sections are open to the panels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from drsplat.defaults import DEFAULT_LEVEL, DEFAULT_TOPK
from viewer.paths import derived_output

FLY_SPEED = 0.4  # scene-distance units per second (times the orbit distance)
FLY_SPEED_RANGE = (0.02, 5.0)
RENDER_SCALE_RANGE = (0.25, 1.0)
CODEBOOK_CHOICES = ("none", "scene", "file")
FOV_RANGE = (20.0, 110.0)  # the View panel's field of view, degrees
ROLL_RANGE = (-180.0, 180.0)  # degrees


def in_range(value: float, lo: float, hi: float, fallback: float) -> float:
    """`value` clamped to [lo, hi]; `fallback` when it is not finite (NaN or ±inf). imgui's ctrl+click lets a
    slider take any typed value: a field of view of 0 divided by zero (the frame loop ended), NaN
    blanked the view, and a NaN fly speed outlived "reset view"."""
    value = float(value)
    return min(max(value, lo), hi) if math.isfinite(value) else fallback


@dataclass
class QuerySettings:
    negatives: str = ""  # comma-separated phrases scored against (relevancy, needs CLIP)
    click_to_query: bool = False  # a plain click queries (ctrl+click always does)


@dataclass
class ExportSettings:
    path: str = ""
    format: str = "standard"  # drsplat.lang.EXPORT_FORMATS


@dataclass
class ViewSettings:
    up_axis: str = "auto"  # viewer.camera.UP_AXES
    show_frusta: bool = False  # the training cameras' frusta over the splats
    camera_index: int = 0  # the training camera last snapped to (N / P step from it)
    fly_speed: float = FLY_SPEED
    render_scale: float = 1.0  # render resolution / window resolution
    screenshot_path: str = ""


@dataclass
class RegistrationSettings:
    output: str = ""
    topk: int = DEFAULT_TOPK
    level: int = DEFAULT_LEVEL
    codebook: str = "none"  # CODEBOOK_CHOICES
    codebook_file: str = ""  # the faiss file when codebook == "file"

    @property
    def codebook_argument(self) -> str:
        """The `codebook` of drsplat.registration.RegisterOptions: none, scene or the file's path."""
        return self.codebook_file if self.codebook == "file" else self.codebook


@dataclass
class ViewerSettings:
    query: QuerySettings = field(default_factory=QuerySettings)
    export: ExportSettings = field(default_factory=ExportSettings)
    view: ViewSettings = field(default_factory=ViewSettings)
    registration: RegistrationSettings = field(default_factory=RegistrationSettings)
    device: str = "cpu"  # auto | cpu | cuda (drsplat.device): where CLIP and registration run, resolved on use
    engine: str | None = None  # registration's compute engine; None = the device's default

    def reset_paths(self, scene_path: Path | None) -> None:
        """Default output paths for a newly opened scene (beside it, or the user data dir when
        that folder is read-only: viewer.paths.derived_output)."""
        self.export.path = str(derived_output(scene_path, "_selection"))
        self.view.screenshot_path = str(derived_output(scene_path, "_screenshot").with_suffix(".png"))
        self.registration.output = str(derived_output(scene_path, "_registered"))
