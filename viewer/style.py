"""Per-splat display styles: what each display mode paints, as [N, 4] (r, g, b, mix) for the renderer."""

from __future__ import annotations

import numpy as np

DISPLAY_MODES = ("color", "highlight", "heatmap", "selection", "hide_selection", "segmentation")
DISPLAY_MODE_NAMES = {
    "color": "scene colours",
    "highlight": "highlight above threshold",
    "heatmap": "relevancy heat map",
    "selection": "selection only",
    "hide_selection": "hide selection",
    "segmentation": "segmentation",
}
HIGHLIGHT_RGB = (1.0, 0.1, 0.85)
HIGHLIGHT_MIX = 0.85
SEGMENT_MIX = 0.8
HEATMAP_MIX = 0.9


def heat_colors(t: np.ndarray) -> np.ndarray:
    """[N] values in [0, 1] -> [N, 3] RGB of matplotlib's 'turbo' colour map."""
    from matplotlib import colormaps

    return colormaps["turbo"](np.asarray(t, np.float64))[:, :3].astype(np.float32)


def splat_style(
    n: int,
    mode: str,
    scores: np.ndarray | None = None,
    selected: np.ndarray | None = None,
    score_range: tuple[float, float] = (0.0, 1.0),
    labels: np.ndarray | None = None,
    label_colors: np.ndarray | None = None,
) -> np.ndarray:
    """[N, 4] float32 (r, g, b, mix): colour = mix(sh_colour, rgb, mix); mix < 0 hides a splat.

    highlight: the selection in HIGHLIGHT_RGB; heatmap: turbo over the score range; selection /
    hide_selection: hide the rest / the selection; segmentation: labels [N] (-1 none) in
    label_colors [L, 3]; color (or no query): the scene's own colours.
    """
    style = np.zeros((n, 4), np.float32)
    if n == 0:
        return style
    if mode == "segmentation" and labels is not None:
        labelled = labels >= 0
        style[labelled, :3] = label_colors[labels[labelled]]
        style[labelled, 3] = SEGMENT_MIX
        return style
    if scores is None or mode == "color":
        return style
    if mode == "highlight":
        style[selected, :3] = HIGHLIGHT_RGB
        style[selected, 3] = HIGHLIGHT_MIX
    elif mode == "heatmap":
        lo, hi = score_range
        t = np.clip((np.nan_to_num(scores, nan=lo) - lo) / (hi - lo), 0, 1)
        style[:, :3] = heat_colors(t)
        style[:, 3] = HEATMAP_MIX
    elif mode == "selection":
        style[~selected, 3] = -1.0
    elif mode == "hide_selection":
        style[selected, 3] = -1.0
    return style
