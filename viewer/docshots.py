"""The window screenshots of docs/viewer.md (panels, help overlay, frusta, progressive still frame).

`xvfb-run -a python -m viewer.docshots docs/images` drives the real window (GLFW + the panels)
on the shipped demo scene and saves what the window shows, panels included. Without an X
server `DRSPLAT_VIEWER_PLATFORM=null` renders the same window offscreen (EGL).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np
from viewer.demo import demo_dir
from viewer.state import ViewerState

log = logging.getLogger(__name__)


def window_image(app) -> np.ndarray:
    """[H, W, 3] uint8 of the window's framebuffer (splats and panels), row 0 at the top."""
    import glfw

    w, h = glfw.get_framebuffer_size(app.window)
    data = app.ctx.screen.read(viewport=(0, 0, w, h), components=3, alignment=1)
    return np.frombuffer(data, np.uint8).reshape(h, w, 3)[::-1].copy()


def settle(app, seconds: float = 20.0) -> None:
    """Draw until the sort and the still frame are done."""
    app.hold_still()
    app.draw_until_still(seconds)
    app.run(max_frames=2)


def main(argv: list[str] | None = None) -> int:
    from viewer.app import ViewerApp, save_image  # moderngl, imgui and glfw: GL only when a window or an image is made

    parser = argparse.ArgumentParser(prog="python -m viewer.docshots", description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--width", type=int, default=1100)
    parser.add_argument("--height", type=int, default=660)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s: %(message)s")
    args.out_dir.mkdir(parents=True, exist_ok=True)
    state = ViewerState()
    folder = demo_dir()
    if not (state.load_scene(folder / "registered.ply") and state.load_source(folder)):
        return 1
    app = ViewerApp(state, args.width, args.height, layout_path=None)
    try:
        shots = {}
        app.snap_to_camera(2)
        state.run_oracle_query(state.oracle.names.index("mug"))
        state.settings.export.format = "drsplat"
        settle(app)
        shots["viewer_panel.png"] = window_image(app)

        app.panels.toggle_help()
        settle(app)
        shots["viewer_help.png"] = window_image(app)
        app.panels.close_help()

        state.settings.view.show_frusta = True
        state.settings.view.up_axis = "auto"
        app.reset_view()
        app.view.zoom(-6)
        settle(app)
        shots["viewer_frusta.png"] = window_image(app)
        state.settings.view.show_frusta = False

        state.run_segmentation(None)
        app.panels.open_next.update({"Scene": False, "View": False, "Registration": True, "Messages": True})
        app.snap_to_camera(5)
        settle(app)
        shots["viewer_segmentation.png"] = window_image(app)

        app.panels.open_next.update({"Scene": True, "View": True, "Registration": False, "Messages": False})
        # a still frame in progress: small chunks so the status line shows it part-way
        app._still_chunk = max(1, state.num_gaussians // 5)
        import viewer.app as va  # moderngl, imgui and glfw: GL only when a window or an image is made

        chunk_rule, va.next_still_chunk = va.next_still_chunk, lambda chunk, num, seconds, target=0: chunk
        try:
            app.view.rotate(30, 0)
            app.hold_still()
            settle_sort = time.time() + 10
            while app.renderer.sorter.busy and time.time() < settle_sort:
                app.run(max_frames=1)
            app._drawn_key = None
            app.run(max_frames=3)
            shots["viewer_progressive.png"] = window_image(app)
        finally:
            va.next_still_chunk = chunk_rule
        for name, image in shots.items():
            save_image(image, args.out_dir / name)
            log.info("wrote %s", args.out_dir / name)
    finally:
        app.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
