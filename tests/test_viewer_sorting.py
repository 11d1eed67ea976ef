"""Viewer depth sort (numba kernel vs numpy reference), background sorter and camera controller."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from drsplat.cameras import Camera
from viewer.camera import ViewController, camera_for_size, look_at
from viewer.sorting import BackgroundSorter, back_to_front_order, back_to_front_reference, depth_keys_reference


def _reference_order(means, forward):
    return back_to_front_reference(depth_keys_reference(means, forward))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_counting_sort_matches_reference_on_random_scenes(seed):
    rng = np.random.default_rng(seed)
    means = (rng.normal(size=(5000, 3)) * rng.uniform(0.1, 100)).astype(np.float32)
    forward = rng.normal(size=3).astype(np.float32)
    forward /= np.linalg.norm(forward)
    order = back_to_front_order(means, forward)
    np.testing.assert_array_equal(order, _reference_order(means, forward))
    depth = means.astype(np.float64) @ forward
    assert np.all(np.diff(depth[order]) <= (depth.max() - depth.min()) / 65535 * 1.01), "not back to front"


@pytest.mark.parametrize(
    "means",
    [
        np.zeros((0, 3), np.float32),
        np.ones((1, 3), np.float32),
        np.ones((50, 3), np.float32),  # all at the same depth: stable, id order
        np.array([[0, 0, np.nan], [0, 0, 1], [0, 0, np.inf], [0, 0, -1], [0, 0, 2]], np.float32),
        np.array([[0, 0, 1e30], [0, 0, -1e30], [0, 0, 0]], np.float32),
    ],
    ids=["empty", "one", "ties", "nonfinite", "huge"],
)
def test_counting_sort_matches_reference_on_hard_inputs(means):
    forward = np.array([0, 0, 1], np.float32)
    order = back_to_front_order(means, forward)
    np.testing.assert_array_equal(order, _reference_order(means, forward))
    assert sorted(order.tolist()) == list(range(len(means)))


def test_finite_depths_go_far_to_near_and_nonfinite_come_last():
    means = np.array([[0, 0, np.nan], [0, 0, 1], [0, 0, 3], [0, 0, 2], [0, 0, -0.0], [0, 0, 0], [0, 0, -1e-45]], np.float32)
    order = back_to_front_order(means, np.array([0, 0, 1], np.float32))
    assert order.tolist() == [2, 3, 1, 4, 5, 6, 0]  # -0 and +0 one key, in id order; the subnormal below them


@pytest.mark.parametrize("far", [1e3, 1e6, 1e12, 3e38])
def test_one_far_gaussian_leaves_the_order_of_the_rest_exact(far):
    """Round 71b F1: 16-bit depth keys over [min d, max d] put a scene of 2,763 Gaussians into a few buckets once one of
    them sat at 1e6 (the floor drawn over the table, mean pixel error 6.1 of 255). The keys are the float32 depths'
    whole order now: the rest stay back to front, the far one first."""
    rng = np.random.default_rng(3)
    means = rng.normal(size=(3000, 3)).astype(np.float32)
    means[17] = far
    forward = np.array([0.3, -0.2, 0.93], np.float32)
    forward /= np.linalg.norm(forward)
    order = back_to_front_order(means, forward)
    np.testing.assert_array_equal(order, _reference_order(means, forward))
    depth = (means[:, 0] * forward[0] + means[:, 1] * forward[1] + means[:, 2] * forward[2]).astype(np.float32)
    assert order[0] == 17 and np.all(np.diff(depth[order]) <= 0)


def test_background_sorter_resorts_only_when_the_view_turns():
    rng = np.random.default_rng(0)
    sorter = BackgroundSorter(rng.normal(size=(2000, 3)).astype(np.float32), min_dot=0.998)
    try:
        f0 = np.array([0, 0, 1], np.float32)
        assert sorter.request(f0)
        result = _wait(sorter)
        np.testing.assert_array_equal(result.order, back_to_front_order(sorter.means, f0))
        slight = np.array([0.01, 0, 1], np.float32) / np.linalg.norm([0.01, 0, 1])
        assert not sorter.request(slight), "a 0.6 degree turn must not trigger a sort"
        turned = np.array([0.2, 0, 1], np.float32) / np.linalg.norm([0.2, 0, 1])
        assert sorter.request(turned)
        result = _wait(sorter)
        np.testing.assert_array_equal(result.order, back_to_front_order(sorter.means, turned))
    finally:
        sorter.close()


def test_background_sorter_subsample_keeps_the_order():
    rng = np.random.default_rng(1)
    means = rng.normal(size=(1000, 3)).astype(np.float32)
    rank = rng.permutation(1000).astype(np.uint32)
    sorter = BackgroundSorter(means, rank=rank)
    try:
        result = sorter.sort_now(np.array([0, 1, 0], np.float32))
        positions = np.argsort(result.order)
        for budget in (1, 300, 999):
            sub = result.subsample(budget)
            assert set(sub.tolist()) == set(np.flatnonzero(rank < budget).tolist())
            assert np.all(np.diff(positions[sub]) > 0), "the subsample keeps the back-to-front order"
        assert result.subsample(1000) is result.order
    finally:
        sorter.close()


def _wait(sorter, timeout=10.0):
    deadline = time.time() + timeout
    while time.time() < deadline:
        result = sorter.poll()
        if result is not None:
            return result
        time.sleep(0.005)
    raise AssertionError("the background sort did not finish")


def test_look_at_gives_an_opencv_camera_looking_at_the_target():
    eye, target, up = np.array([3.0, -2.0, 1.5]), np.array([0.1, 0.2, 0.3]), np.array([0.0, 0.0, 1.0])
    R, t = look_at(eye, target, up)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    cam = Camera(R=R, t=t, fx=100, fy=100, cx=50, cy=40, width=100, height=80)
    uv, z = cam.project(np.array([target, target + up]))
    np.testing.assert_allclose(uv[0], [50, 40], atol=1e-9)
    assert z[0] == pytest.approx(np.linalg.norm(target - eye))
    assert uv[1, 1] < 40, "world up must appear above the centre (image y points down)"


def test_home_view_of_a_scene_far_beyond_float_precision_is_a_finite_camera():
    """Gaussians at 1e30 (a units mix-up) round their extent away: eye == target in float64 gave a
    NaN rotation and numpy's warnings (a black frame)."""
    import warnings

    from drsplat.testing import gaussians
    from viewer.camera import ViewController

    scene = gaussians([[1e30, 1e30, 1e30], [1e30, 1e30, 1.0000001e30]], log_scale=[[-2.0, -2.0, -2.0]] * 2, opacity_logit=0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        R, _ = look_at([1e30] * 3, [1e30] * 3, [0.0, -1.0, 0.0])
        camera = ViewController.for_scene(scene.means, [], 64, 48, scene.log_scales).camera()
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.isfinite(camera.R).all() and np.isfinite(camera.t).all()


def test_orbit_keeps_the_distance_and_fly_keeps_the_eye():
    view = ViewController(eye=np.array([0.0, -4.0, 1.0]), target=np.zeros(3), up=np.array([0.0, 0.0, 1.0]))
    d = view.distance
    view.rotate(120, 40)
    assert view.distance == pytest.approx(d)
    np.testing.assert_allclose(view.target, 0)
    view.mode = "fly"
    eye = view.eye.copy()
    view.rotate(-50, 10)
    np.testing.assert_allclose(view.eye, eye)
    view.zoom(1)
    assert not np.allclose(view.eye, eye)
    view.reset()
    np.testing.assert_allclose(view.eye, [0.0, -4.0, 1.0])


def test_pitch_stops_short_of_the_pole():
    view = ViewController(eye=np.array([0.0, -4.0, 0.0]), target=np.zeros(3), up=np.array([0.0, 0.0, 1.0]))
    for _ in range(100):
        view.rotate(0, 50)
    cos_up = abs(view.forward @ view.up)
    assert cos_up < 1.0 and np.isfinite(view.camera().R).all()


def _polar_degrees(view: ViewController) -> float:
    """The angle between the view's turned direction (eye - target orbiting, target - eye flying) and up."""
    offset = view.eye - view.target if view.mode == "orbit" else view.target - view.eye
    return math.degrees(math.acos(np.clip(offset @ view.up / np.linalg.norm(offset), -1.0, 1.0)))


def _from_pole_degrees(view: ViewController) -> float:
    polar = _polar_degrees(view)
    return min(polar, 180.0 - polar)


@pytest.mark.parametrize("mode", ["orbit", "fly"])
def test_a_view_inside_the_pole_margin_drags_out_of_it_one_pixel_at_a_time(mode):
    # a view 1 degree off the up axis (a top-down training camera, or +Z chosen under such a view):
    # slow drags away from the pole used to be refused one by one, as each stayed inside the 3-degree margin
    a = math.radians(1.0)
    view = ViewController(eye=np.array([0.0, -4.0 * math.sin(a), 4.0 * math.cos(a)]), target=np.zeros(3), up=np.array([0.0, 0.0, 1.0]), mode=mode)
    away = 1 if mode == "orbit" else -1  # fly turns the target around the eye: the other way
    start = _from_pole_degrees(view)
    for _ in range(3):
        view.rotate(0, -away)  # toward the pole: held where it is, never over it
    assert _from_pole_degrees(view) == pytest.approx(start, abs=1e-9)
    angles = []
    for _ in range(40):
        view.rotate(0, away)
        angles.append(_from_pole_degrees(view))
    assert np.all(np.diff(angles) > 0.2) and angles[-1] > 10.0
    assert view.distance == pytest.approx(4.0)


def test_a_view_straight_down_the_up_axis_drags_out_of_it():
    view = ViewController(eye=np.array([0.0, 0.0, 4.0]), target=np.zeros(3), up=np.array([0.0, 0.0, 1.0]))
    view.rotate(0, 100)
    assert _from_pole_degrees(view) == pytest.approx(math.degrees(100 * view.rotate_speed))
    assert np.isfinite(view.camera().R).all() and view.distance == pytest.approx(4.0)


@pytest.mark.parametrize("pixels", [400, -400, 1000])
def test_one_fast_drag_stops_at_the_pole_margin_on_its_own_side(pixels):
    view = ViewController(eye=np.array([0.0, -4.0, 0.0]), target=np.zeros(3), up=np.array([0.0, 0.0, 1.0]))
    view.rotate(0, pixels)
    assert _from_pole_degrees(view) == pytest.approx(3.0)
    assert view.eye[1] < 0  # still on the side it started from: not carried over the pole
    assert view.distance == pytest.approx(4.0)


def test_snap_to_a_training_camera_reproduces_its_pose_and_fov():
    R, t = look_at(np.array([2.0, 1.0, 1.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    train = Camera(R=R, t=t, fx=80, fy=80, cx=64, cy=48, width=128, height=96)
    view = ViewController(eye=np.ones(3), target=np.zeros(3), up=np.array([0.0, 0.0, 1.0]), width=128, height=96)
    view.snap_to(train, scene_center=np.zeros(3))
    cam = view.camera()
    np.testing.assert_allclose(cam.R, R, atol=1e-9)
    np.testing.assert_allclose(cam.t, t, atol=1e-9)
    assert cam.fy == pytest.approx(80)
    resized = camera_for_size(train, 256, None)
    assert (resized.width, resized.height, resized.fx, resized.cx) == (256, 192, 160, 128)
