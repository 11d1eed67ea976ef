"""Camera readers: COLMAP binary/text agreement, the OpenCV convention, transforms.json, distortion."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from drsplat.cameras import (
    Camera,
    distort_normalized,
    load_cameras,
    load_image,
    read_colmap_model,
    write_transforms_json,
)
from drsplat.errors import InputError
from tests.conftest import shared_path


def reprojection_errors(model, cameras) -> np.ndarray:
    ids, xyz = model.points_array()
    row = {int(i): k for k, i in enumerate(ids)}
    by_name = {c.name: c for c in cameras}
    errors = []
    for img in model.images.values():
        cam = by_name[img.name.rsplit(".", 1)[0]]
        seen = img.point3D_ids >= 0
        points = xyz[[row[int(i)] for i in img.point3D_ids[seen]]]
        uv, depth = cam.project(points)
        assert (depth > 0).all()
        errors.append(np.linalg.norm(uv - img.xys[seen], axis=1))
    return np.concatenate(errors)


def test_fern_binary_and_text_models_agree():
    b = read_colmap_model(shared_path("fern", "sparse", "0"))
    t = read_colmap_model(shared_path("fern", "sparse", "0_txt"))
    assert b.images.keys() == t.images.keys() and len(b.points) == len(t.points) == 1849
    for k, img in b.images.items():
        assert img.name == t.images[k].name
        np.testing.assert_allclose(img.qvec, t.images[k].qvec, atol=1e-6)
        np.testing.assert_allclose(img.tvec, t.images[k].tvec, atol=1e-6)
        np.testing.assert_allclose(img.xys, t.images[k].xys, atol=1e-6)
    for k, cam in b.cameras.items():
        np.testing.assert_allclose(cam.params, t.cameras[k].params, atol=1e-6)
    for k, p in b.points.items():
        np.testing.assert_allclose(p, t.points[k], atol=1e-6)


def test_fern_points_project_onto_their_observations():
    """The convention test: every 3D point lands on its recorded 2D observation (< 1 px mean)."""
    model = read_colmap_model(shared_path("fern", "sparse", "0"))
    cameras = load_cameras(shared_path("fern"))
    assert len(cameras) == 20 and cameras[0].width == 504
    errors = reprojection_errors(model, cameras)
    assert errors.size > 10000
    assert errors.mean() < 1.0


@pytest.mark.parametrize("mount", ["as given", "through a symlink"])
def test_transforms_json_round_trip_through_opengl(tmp_path, mount):
    fern = shared_path("fern")
    if mount == "through a symlink":  # the dataset seen through a symlinked mount must read the same
        (tmp_path / "mounted").symlink_to(fern.resolve(), target_is_directory=True)
        fern = tmp_path / "mounted"
    model = read_colmap_model(fern / "sparse" / "0")
    cameras = load_cameras(fern)
    out = tmp_path / "out"
    path = out / "transforms.json"
    write_transforms_json(cameras, path)
    meta = json.loads(path.read_text())
    assert np.allclose(np.array(meta["frames"][0]["transform_matrix"])[3], [0, 0, 0, 1])
    again = load_cameras(out)
    for a, b in zip(cameras, again):
        np.testing.assert_allclose(a.R, b.R, atol=1e-9)
        np.testing.assert_allclose(a.t, b.t, atol=1e-9)
        assert (a.fx, a.cy, a.width, a.image_path) == (b.fx, b.cy, b.width, b.image_path)
        assert a.image_path == a.image_path.resolve() and a.image_path.is_file()
    assert reprojection_errors(model, again).mean() < 1.0


def test_nerf_synthetic_camera_angle_x(tmp_path):
    from PIL import Image

    (tmp_path / "train").mkdir()
    Image.new("RGB", (80, 60)).save(tmp_path / "train" / "r_0.png")
    c2w = np.eye(4)
    c2w[:3, 3] = [0, 0, 4]  # OpenGL camera at z=4 looking down -z, at the origin
    meta = {"camera_angle_x": 2 * np.arctan(0.5), "frames": [{"file_path": "./train/r_0", "transform_matrix": c2w.tolist()}]}
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    (cam,) = load_cameras(tmp_path)
    assert (cam.width, cam.height) == (80, 60) and cam.fx == pytest.approx(80.0)
    uv, depth = cam.project(np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]]))
    np.testing.assert_allclose(uv[0], [40, 30])
    assert depth[0] == pytest.approx(4.0)
    assert uv[1, 0] > 40 and uv[1, 1] < 30  # world +x is right, world +y (OpenGL up) is image up


def test_fox_missing_frames_counted_once(caplog):
    with caplog.at_level(logging.WARNING):
        cameras = load_cameras(shared_path("fox"))
    assert len(cameras) == 50
    warnings = [r.getMessage() for r in caplog.records if "missing" in r.getMessage()]
    assert len(warnings) == 1 and "17 frame(s)" in warnings[0]
    assert cameras[0].distortion is not None and cameras[0].distortion[0] == pytest.approx(0.0578421)


def test_resolution_scales_images_and_intrinsics_together():
    full = load_cameras(shared_path("fox"), resolution=1)[0]
    quarter = load_cameras(shared_path("fox"), resolution=4)[0]
    assert (quarter.width, quarter.height) == (270, 480)
    assert quarter.fx == pytest.approx(full.fx / 4) and quarter.cx == pytest.approx(full.cx / 4)
    capped = load_cameras(shared_path("fox"))[0]  # -1: 3DGS caps the width at 1600
    assert capped.width == 1080
    image = load_image(quarter)
    assert image.shape == (480, 270, 3) and image.dtype == np.uint8


def test_undistortion_moves_a_dot_to_its_pinhole_position(tmp_path):
    from PIL import Image

    dist = np.array([0.2, -0.05, 0.01, -0.005])
    cam = Camera(R=np.eye(3), t=np.zeros(3), fx=100.0, fy=100.0, cx=64.0, cy=48.0, width=128, height=96,
                 image_path=tmp_path / "d.png", name="d", distortion=dist)
    target = np.array([100.5, 20.5])  # pinhole pixel centre
    xy = (target - [cam.cx, cam.cy]) / [cam.fx, cam.fy]
    src = distort_normalized(xy, dist) * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    image = np.zeros((96, 128, 3), np.uint8)
    image[int(src[1]) - 1:int(src[1]) + 2, int(src[0]) - 1:int(src[0]) + 2] = 255
    Image.fromarray(image).save(cam.image_path)
    out = load_image(cam)[..., 0].astype(float)
    v, u = np.unravel_index(np.argmax(out), out.shape)
    assert abs(u + 0.5 - target[0]) <= 1.5 and abs(v + 0.5 - target[1]) <= 1.5


def test_distorted_colmap_model_is_refused_with_instructions(tmp_path):
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text("1 OPENCV 100 80 90 90 50 40 0.1 0.01 0 0\n")
    (sparse / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n")
    (tmp_path / "images").mkdir()
    (tmp_path / "images" / "a.png").write_bytes(b"")
    with pytest.raises(InputError, match="image_undistorter"):
        load_cameras(tmp_path)


@pytest.mark.parametrize(
    "files, expected",
    [
        ({"transforms.json": "{not json"}, "is not valid JSON"),
        ({"transforms.json": json.dumps({"frames": 3})}, "field 'frames'"),
        ({"cameras.json": json.dumps({"a": 1})}, "is not a list of cameras"),
        ({}, "has no COLMAP model"),
    ],
)
def test_bad_camera_files_give_clear_errors(tmp_path, files, expected):
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    with pytest.raises(InputError, match=expected):
        load_cameras(tmp_path)


def test_truncated_colmap_binary(tmp_path):
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    src = shared_path("fern", "sparse", "0")
    (sparse / "cameras.bin").write_bytes((src / "cameras.bin").read_bytes())
    (sparse / "images.bin").write_bytes((src / "images.bin").read_bytes()[:5000])
    with pytest.raises(InputError, match="images.bin: is truncated"):
        load_cameras(tmp_path)


def test_3dgs_cameras_json(tmp_path):
    cameras = load_cameras(shared_path("fern"))[:3]
    records = [{"id": i, "img_name": c.name, "width": c.width, "height": c.height, "position": c.center.tolist(),
                "rotation": c.R.T.tolist(), "fx": c.fx, "fy": c.fy} for i, c in enumerate(cameras)]
    (tmp_path / "cameras.json").write_text(json.dumps(records))
    loaded = load_cameras(tmp_path / "cameras.json", require_images=False)
    for a, b in zip(cameras, loaded):
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, atol=1e-9)


def _tiny_colmap(root, image_names=("a.png", "b.png")):
    from PIL import Image

    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (root / "images").mkdir()
    (sparse / "cameras.txt").write_text("1 PINHOLE 64 48 50 50 32 24\n")
    lines = []
    for i, name in enumerate(image_names, start=1):
        Image.new("RGB", (64, 48)).save(root / "images" / name)
        lines += [f"{i} 1 0 0 0 {0.1 * i} 0 4 1 {name}", ""]
    (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    return root


def test_colmap_and_transforms_resolve_image_paths_the_same_through_a_symlink(tmp_path):
    """Issue 13 item 7: both readers give resolved image paths, so a dataset read through a
    symlinked mount equals the dataset read directly, and a round trip through transforms.json
    keeps the paths (no ../shared fixture needed)."""
    real = _tiny_colmap(tmp_path / "real")
    (tmp_path / "mount").symlink_to(real, target_is_directory=True)
    direct, linked = load_cameras(real), load_cameras(tmp_path / "mount")
    assert [c.image_path for c in direct] == [c.image_path for c in linked] == [real.resolve() / "images" / n for n in ("a.png", "b.png")]
    out = tmp_path / "elsewhere"
    write_transforms_json(linked, out / "transforms.json")
    again = load_cameras(out)
    assert [c.image_path for c in again] == [c.image_path for c in direct]
    for a, b in zip(direct, again):
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, atol=1e-12)


def test_dataset_reader_registry_detects_every_format(tmp_path):
    """One registry (DATASET_READERS) detects and reads COLMAP, transforms.json, cameras.json and ScanNet."""
    from PIL import Image

    from drsplat.cameras import DATASET_READERS, detect_dataset

    assert [r.kind for r in DATASET_READERS] == ["colmap", "transforms", "cameras_json", "scannet"]
    colmap = _tiny_colmap(tmp_path / "colmap")
    write_transforms_json(load_cameras(colmap), tmp_path / "tj" / "transforms.json")
    cj = tmp_path / "cj"
    cj.mkdir()
    (cj / "cameras.json").write_text(json.dumps([{"id": 0, "img_name": "a", "width": 64, "height": 48, "position": [0, 0, -4],
                                                  "rotation": np.eye(3).tolist(), "fx": 50, "fy": 50}]))
    scan = tmp_path / "scene0000_00"
    for sub in ("pose", "intrinsic", "color"):
        (scan / sub).mkdir(parents=True)
    K = np.eye(4)
    K[0, 0] = K[1, 1] = 50.0
    K[0, 2], K[1, 2] = 32.0, 24.0
    np.savetxt(scan / "intrinsic" / "intrinsic_color.txt", K)
    np.savetxt(scan / "pose" / "0.txt", np.eye(4))
    Image.new("RGB", (64, 48)).save(scan / "color" / "0.jpg")
    expected = {colmap: "colmap", tmp_path / "tj": "transforms", tmp_path / "tj" / "transforms.json": "transforms", cj: "cameras_json", scan: "scannet"}
    for source, kind in expected.items():
        assert detect_dataset(source)[0] == kind
        cams = load_cameras(source, require_images=False)
        assert cams and all((c.width, c.height, c.fx) == (64, 48, 50.0) for c in cams), kind
