"""`drsplat bench viewer`: frame time of the splat renderer split into sort, upload and draw.

Registered through the `drsplat.bench` entry point (drsplat never imports the viewer). Scenes:
100k and 1M splats are drawn from flowers.ply (1M: two copies, the second jittered by 1 cm)
or, without it, random Gaussians; 542k is flowers.ply itself (skipped when absent). Each
repeat turns the view by 3 degrees so that every frame needs a new sort.

Approximations are reported with their cost: the 16-bit counting sort against an exact float
argsort (speed and the image difference it makes), and the moving-camera frame (the GUI's
adaptive subsample at MOVING_SCALE resolution) against the full frame.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from drsplat.scene import GaussianScene

FLOWERS = Path(__file__).resolve().parents[2] / "shared" / "data" / "ply" / "flowers.ply"
SIZES = {"100k": 100_000, "542k": 542_104, "1M": 1_000_000}
MOVING_FRAMES = 8  # moving frames the budget adapts over
SETTLED_FRAMES = 3  # of which the last ones are reported


def screenshot_file(text: str) -> Path:
    """argparse type of --screenshot: a file name (`output_file`) whose suffix names an image format
    (`viewer.paths.image_format`), refused before any frame is drawn."""
    from drsplat.commands.common import output_file
    from viewer.paths import image_format

    path = output_file(text)
    try:
        image_format(path)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return path


def add_bench(subparsers: argparse._SubParsersAction) -> None:
    from drsplat.bench.common import choice_list
    from drsplat.commands.common import MAX_IMAGE_WIDTH, int_range, positive_int

    side = int_range(1, MAX_IMAGE_WIDTH)
    p = subparsers.add_parser("viewer", help="viewer frame time (sort, upload, draw) on the EGL OpenGL renderer")
    p.add_argument("--sizes", type=choice_list(SIZES, "size"), default="100k,542k,1M", help="comma-separated scene sizes among 100k, 542k, 1M")
    p.add_argument("--ply", type=Path, default=None,
                   help="the real scene for 542k (and the source of the others) (default: ../shared/data/ply/flowers.ply, random Gaussians when absent)")
    p.add_argument("--width", type=side, default=1280, help=f"frame width, 1..{MAX_IMAGE_WIDTH} (default: 1280)")
    p.add_argument("--height", type=side, default=720, help=f"frame height, 1..{MAX_IMAGE_WIDTH} (default: 720)")
    p.add_argument("--repeats", type=positive_int, default=5, help="frames per measurement (median reported)")
    p.add_argument("--screenshot", type=screenshot_file, help="also save the 542k (or first) frame to this PNG")
    p.add_argument("--progressive", action="store_true",
                   help="instead: the GUI's still frame drawn whole vs progressively (the window on GLFW's null platform)")
    p.set_defaults(func=run)


def progressive_timings(app, scene: GaussianScene, repeats: int) -> dict[str, float]:
    """Seconds of the window's (`app`, a viewer.app.ViewerApp) still frame of `scene` drawn whole
    (one GUI frame) and progressively (GUI frames: count, median, longest, until complete),
    medians over `repeats` new still views (a 1-degree turn each, so no re-sort)."""
    import statistics

    app.state.set_scene(scene)
    app.hold_still()
    app.run(max_frames=1)
    while app.renderer.sorter.busy or app.still_progress() is not None:
        app.run(max_frames=1)
    rows: dict[str, list[float]] = {"whole": [], "frames": [], "median": [], "longest": [], "complete": []}
    for _ in range(repeats):
        app.progressive = False
        app.view.rotate(1, 0)
        app.hold_still()
        start = time.perf_counter()
        app.run(max_frames=1)
        rows["whole"].append(time.perf_counter() - start)
        app.progressive = True
        app.view.rotate(1, 0)
        app.hold_still()
        frames, start = [], time.perf_counter()
        while not frames or app.still_progress() is not None:
            t = time.perf_counter()
            app.run(max_frames=1)
            frames.append(time.perf_counter() - t)
        rows["complete"].append(time.perf_counter() - start)
        rows["frames"].append(len(frames))
        rows["median"].append(statistics.median(frames))
        rows["longest"].append(max(frames))
    return {k: statistics.median(v) for k, v in rows.items()}


def random_scene(n: int, seed: int = 0) -> GaussianScene:
    """n flat-ish coloured Gaussians in a 2 m ball (a stand-in when flowers.ply is absent)."""
    rng = np.random.default_rng(seed)
    means = (rng.normal(size=(n, 3)) * [1.0, 0.4, 1.0]).astype(np.float32)
    sh = np.zeros((n, 1, 3), np.float32)
    sh[:, 0] = (rng.random((n, 3)) - 0.5) / 0.2821
    return GaussianScene(
        means=means,
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=(np.log(0.01) + rng.normal(size=(n, 3)) * 0.5).astype(np.float32),
        opacity_logits=rng.normal(1.0, 1.0, n).astype(np.float32),
        sh=sh,
    )


def bench_scene(name: str, base: GaussianScene | None, seed: int = 0, stem: str = "flowers") -> tuple[GaussianScene | None, str]:
    """The scene of size `name` and where it comes from; (None, "") for 542k without flowers.ply.
    A size larger than `base` (the scene file `stem`) is drawn from jittered copies of it: two of flowers.ply for 1M."""
    n = SIZES[name]
    if base is None:
        return (None, "") if name == "542k" else (random_scene(n, seed), "random")
    rng = np.random.default_rng(seed)
    if name == "542k":
        return base, f"{stem}.ply"
    if n <= base.num_gaussians:
        return base.subset(np.sort(rng.choice(base.num_gaussians, n, replace=False))), f"{stem} subset"
    copies = -(-n // base.num_gaussians)  # enough copies to draw n distinct Gaussians from (a small scene needs many)
    jitter = rng.normal(scale=0.01, size=((copies - 1) * base.num_gaussians, 3)).astype(np.float32)
    means = np.tile(base.means, (copies, 1))
    means[base.num_gaussians :] += jitter  # every copy after the first moved by ~1 cm
    many = GaussianScene(
        means=means,
        quats=np.tile(base.quats, (copies, 1)),
        log_scales=np.tile(base.log_scales, (copies, 1)),
        opacity_logits=np.tile(base.opacity_logits, copies),
        sh=np.tile(base.sh, (copies, 1, 1)),
    )
    return many.subset(np.sort(rng.choice(many.num_gaussians, n, replace=False))), f"{stem} x{copies}, jittered"


def measure(ctx, scene: GaussianScene, width: int, height: int, repeats: int):
    """Median seconds of sort / exact sort / upload / projection / draw / moving draw, and the
    approximation costs. The moving frame is the GUI's: the subsample starts from
    `calibrated_moving_budget` and adapts with `next_moving_budget` for MOVING_FRAMES frames;
    the budget it settles on, the median time of the last frames and their error are reported."""
    from viewer.app import MOVING_SCALE, calibrated_moving_budget, next_moving_budget  # moderngl, imgui and glfw: GL only when a window or an image is made
    from viewer.camera import ViewController, camera_for_size
    from viewer.renderer import OffscreenTarget, SplatRenderer
    from viewer.sorting import SortResult

    renderer = SplatRenderer(ctx, scene)
    renderer.profile = True
    view = ViewController.for_scene(scene.means, None, width, height)
    target = OffscreenTarget(ctx, width, height)
    small = OffscreenTarget(ctx, max(1, int(width * MOVING_SCALE)), max(1, int(height * MOVING_SCALE)))
    screen = OffscreenTarget(ctx, width, height)
    rows = {k: [] for k in ("sort", "exact_sort", "upload", "project", "draw", "moving", "still")}
    try:
        target.use()
        renderer.update_order(view.camera(), wait=True)
        renderer.draw(view.camera())  # warm-up: shader compilation, first upload
        for _ in range(repeats):
            view.rotate(0.05 / view.rotate_speed, 0)
            camera = view.camera()
            forward = np.asarray(camera.R, np.float32)[2]
            result = renderer.sorter.sort_now(forward)
            rows["sort"].append(result.seconds)
            start = time.perf_counter()
            depth = scene.means @ forward
            np.argsort(-depth, kind="stable")
            rows["exact_sort"].append(time.perf_counter() - start)
            renderer.upload_order(result)
            rows["upload"].append(renderer.times.upload)
            target.use()
            renderer.draw(camera)
            rows["draw"].append(renderer.times.draw)
            rows["project"].append(renderer.times.project)
            screen.use()
            start = time.perf_counter()
            ctx.copy_framebuffer(screen.fbo, target.fbo)
            ctx.finish()
            rows["still"].append(time.perf_counter() - start)
        camera = view.camera()
        small_camera = camera_for_size(camera, small.width, small.height)
        renderer.moving_budget = calibrated_moving_budget(renderer.num, float(np.median(rows["draw"])))
        small.use()
        budgets = []
        for _ in range(MOVING_FRAMES):
            budgets.append(renderer.moving_budget)
            renderer.draw(small_camera, moving=True)
            rows["moving"].append(renderer.times.draw)
            renderer.moving_budget = next_moving_budget(renderer.moving_budget, renderer.num, renderer.times.draw)
        rows["moving"] = rows["moving"][-SETTLED_FRAMES:]
        budget = int(np.median(budgets[-SETTLED_FRAMES:]))
        target.use()
        renderer.draw(camera)
        full = target.read_rgb().astype(np.float32)
        depth = scene.means.astype(np.float64) @ np.asarray(camera.R, np.float64)[2]
        exact = np.argsort(-depth, kind="stable").astype(np.uint32)
        renderer.upload_order(SortResult(exact, renderer.rank[exact], np.asarray(camera.R[2], np.float32), 0.0, -1))
        renderer.draw(camera)
        exact_image = target.read_rgb().astype(np.float32)
        small.use()
        renderer.moving_budget = budget
        renderer.draw(small_camera, moving=True)
        from PIL import Image

        moving_image = np.asarray(Image.fromarray(small.read_rgb()).resize((width, height), Image.BILINEAR), np.float32)
        costs = {"sort_diff": float(np.abs(full - exact_image).mean()), "moving_diff": float(np.abs(moving_image - exact_image).mean())}
        return {k: float(np.median(v)) for k, v in rows.items()}, costs, full.astype(np.uint8), budget
    finally:
        screen.release()
        target.release()
        small.release()
        renderer.release()


def base_scene(args: argparse.Namespace) -> GaussianScene | None:
    """The scene the sizes are drawn from, read before any work: a --ply the user gave must be a file of
    Gaussians (one error otherwise); the default flowers.ply is skipped (random Gaussians) when absent.
    Sets args.ply to the file read (the default resolved), for the lines that name it."""
    from drsplat.bench.common import guard_bench_outputs, scene_file
    from drsplat.scene import load_ply

    given = args.ply is not None
    args.ply = scene_file(args.ply, "--ply") if given else FLOWERS
    # the default scene is an input too: it is resolved here, after the command line's own guard
    guard_bench_outputs({"--ply" if given else "--ply (its default)": args.ply}, {"--screenshot": args.screenshot})
    return load_ply(args.ply, purpose="benchmark") if args.ply.is_file() else None


def run(args: argparse.Namespace) -> int:
    from viewer.app import MOVING_FRAME_SECONDS, MOVING_SCALE, save_image  # moderngl, imgui and glfw: GL only when a window or an image is made
    from viewer.renderer import create_offscreen_context

    names = args.sizes
    base = base_scene(args)
    if args.progressive:
        return run_progressive(args, names, base)
    ctx = create_offscreen_context()
    print(f"viewer frame time, {args.width}x{args.height}, {ctx.info['GL_RENDERER']}, median of {args.repeats} frames, load average {os.getloadavg()[0]:.1f}")
    print(f"{'splats':>9} {'scene':<22} {'sort':>6} {'exact':>6} {'upload':>6} {'project':>7} {'draw':>6} {'fps idle-sort':>13} {'fps sort/frame':>14} "
          f"{'moving splats':>13} {'moving':>6} {'fps moving':>10} {'sort err':>8} {'moving err':>10} {'still':>6}")
    shot = None
    for name in names:
        scene, origin = bench_scene(name, base, stem=args.ply.stem)
        if scene is None:
            print(f"{name:>9} skipped: {args.ply} is absent")
            continue
        t, costs, image, budget = measure(ctx, scene, args.width, args.height, args.repeats)
        ms = {k: v * 1000 for k, v in t.items()}
        print(
            f"{scene.num_gaussians:>9,} {origin:<22} {ms['sort']:>5.0f}m {ms['exact_sort']:>5.0f}m {ms['upload']:>5.1f}m {ms['project']:>6.0f}m {ms['draw']:>5.0f}m "
            f"{1000 / (ms['upload'] + ms['draw']):>13.1f} {1000 / (ms['sort'] + ms['upload'] + ms['draw']):>14.1f} "
            f"{budget:>13,} {ms['moving']:>5.0f}m {1000 / ms['moving']:>10.1f} {costs['sort_diff']:>8.2f} {costs['moving_diff']:>10.2f} {ms['still']:>5.1f}m"
        )
        if shot is None or name == "542k":
            shot = image
    print("columns (ms): sort = 16-bit counting sort (background thread), exact = float argsort, upload = order buffer, "
          "project = the compute pass alone, draw = compute projection + blend at full resolution (ctx.finish); "
          "fps idle-sort = 1/(upload + draw), the background sort off the frame; moving = the GUI's moving frame: "
          f"{MOVING_SCALE:g}x resolution, a random subsample adapted over {MOVING_FRAMES} frames towards {MOVING_FRAME_SECONDS * 1000:.0f} ms "
          f"(moving splats = the budget it settled on; median of the last {SETTLED_FRAMES}); errors = mean |difference| in 8-bit levels "
          "against the exact-order full frame; still = a GUI frame while the camera is still (the last image is reused, not re-rendered)")
    if args.screenshot is not None and shot is not None:
        save_image(shot, args.screenshot)
        print(f"screenshot: {args.screenshot}")
    ctx.release()
    return 0


def run_progressive(args: argparse.Namespace, names: list[str], base: GaussianScene | None) -> int:
    print(f"still frame in the window, {args.width}x{args.height}, whole vs progressive, median of {args.repeats} still views, load average {os.getloadavg()[0]:.1f}")
    from viewer.app import ViewerApp  # moderngl, imgui and glfw: GL only when a window or an image is made
    from viewer.state import ViewerState

    print(f"{'splats':>9} {'scene':<22} {'whole':>7} {'GUI frames':>10} {'median frame':>12} {'longest frame':>13} {'complete':>8}")
    app = ViewerApp(ViewerState(), args.width, args.height, platform="null", layout_path=None)  # one window: GLFW cannot re-detect a context after glfwTerminate
    for name in names:
        scene, origin = bench_scene(name, base, stem=args.ply.stem)
        if scene is None:
            print(f"{name:>9} skipped: {args.ply} is absent")
            continue
        t = progressive_timings(app, scene, args.repeats)
        print(f"{scene.num_gaussians:>9,} {origin:<22} {t['whole'] * 1000:>6.0f}m {t['frames']:>10.0f} {t['median'] * 1000:>11.0f}m "
              f"{t['longest'] * 1000:>12.0f}m {t['complete'] * 1000:>7.0f}m")
    print("columns (ms): whole = the GUI frame that draws the still frame at once (input blocked meanwhile); progressive: "
          "GUI frames until the still frame is complete, their median and longest time (the longest holds the compute "
          "projection), and the time until complete")
    app.close()
    return 0
