"""Camera readers: COLMAP binary/text agreement, the OpenCV convention, transforms.json, distortion."""

from __future__ import annotations

import dataclasses
import json
import re
import logging
import warnings
from pathlib import Path

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
    assert len(warnings) == 1 and "17 frames skipped" in warnings[0]
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


@pytest.mark.parametrize("model, words", [
    ("opencv", 'has camera_model "opencv": write it "OPENCV"'),
    ("OPENCV_FISHEYE", 'has camera_model "OPENCV_FISHEYE", which drsplat does not read; it reads OPENCV (k1, k2, p1, p2), PINHOLE and '
                       "SIMPLE_PINHOLE; 3DGS is trained on undistorted images: undistort them with the tool that made this file"),
    ("EQUIRECTANGULAR", "no pinhole camera shows a whole panorama"),
    ("equirectangular", "no pinhole camera shows a whole panorama"),
    (7, "has camera_model 7, which drsplat does not read"),
])
def test_a_transforms_camera_model_refused_is_named_with_a_way_out_that_fits_it(tmp_path, model, words):
    """Round 95b F3: every refused camera_model was told "only pinhole and OpenCV are supported" ("opencv" too) and sent
    to `colmap image_undistorter --input_path sparse/0`, which a transforms.json dataset seldom has."""
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_model": model, "frames": []}))
    with pytest.raises(InputError, match="camera_model") as exc:
        load_cameras(tmp_path, require_images=False)
    assert words in str(exc.value) and "sparse/0" not in str(exc.value)


def test_distorted_colmap_model_is_refused_with_instructions(tmp_path):
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text("1 OPENCV 100 80 90 90 50 40 0.1 0.01 0 0\n")
    (sparse / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n")
    (tmp_path / "images").mkdir()
    (tmp_path / "images" / "a.png").write_bytes(b"")
    with pytest.raises(InputError, match="image_undistorter"):
        load_cameras(tmp_path)
    # round 57b: the refusal named the sparse folder, not cameras.txt, and neither the image nor the coefficients
    with pytest.raises(InputError, match=re.escape(f"{sparse / 'cameras.txt'}: field 'MODEL': camera 1 (used by image 1 ('a.png')) uses "
                                                   "the distorted model OPENCV, its coefficients after the focal length and principal "
                                                   "point are 0.1 0.01 0 0; 3DGS is trained on undistorted images")):
        load_cameras(tmp_path)
    # round 57b: COLMAP 3.10's models (ids 11-17) were 'unknown model id 14', as if the file were damaged
    for line in ("1 SIMPLE_FISHEYE 100 80 90 50 40", "1 EUCM 100 80 90 90 50 40 0.5 1.0", "1 DIVISION 100 80 90 90 50 40 0.2"):
        (sparse / "cameras.txt").write_text(line + "\n")
        with pytest.raises(InputError, match=rf"camera 1 \(used by image 1 \('a.png'\)\) uses the distorted model {line.split()[1]}.*image_undistorter"):
            load_cameras(tmp_path)
    (sparse / "cameras.txt").write_text("1 DIVISION 100 80 90 90 50 40 0\n")  # k = 0: a pinhole camera
    (tmp_path / "images" / "a.png").unlink()
    from PIL import Image

    Image.new("RGB", (100, 80)).save(tmp_path / "images" / "a.png")
    assert [(c.fx, c.cx) for c in load_cameras(tmp_path)] == [(90.0, 50.0)]
    import struct

    (sparse / "cameras.txt").unlink()  # the binary model: an id of COLMAP 3.10 with its parameter count, so the record is read
    (sparse / "cameras.bin").write_bytes(struct.pack("<QIiQQ", 1, 1, 14, 100, 80) + struct.pack("<3d", 90, 50, 40))
    (sparse / "images.txt").unlink()
    (sparse / "images.bin").write_bytes(struct.pack("<QI7dI", 1, 1, 1, 0, 0, 0, 0, 0, 0, 1) + b"a.png\0" + struct.pack("<Q", 0))
    with pytest.raises(InputError, match=r"cameras.bin: field 'MODEL': camera 1 .* uses the distorted model SIMPLE_FISHEYE, a fisheye"):
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


def test_a_device_or_a_pipe_given_as_a_dataset_or_annotations_is_called_no_folder(tmp_path):
    """Round 54: `--source /dev/null` was told it "has no COLMAP model (sparse/0), no transforms.json, ..." and
    `eval lerf --annotations /dev/null` "annotation folder not found", as if each were an empty folder or absent."""
    import os

    from drsplat.eval.datasets import lerf_annotation_files

    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)
    for path in (Path("/dev/null"), pipe):
        with pytest.raises(InputError, match=r"is not a dataset folder, transforms.json or cameras.json \(it is no regular file or folder\)"):
            load_cameras(path)
        with pytest.raises(InputError, match=r": is not a folder \(expected lerf_ovs/label/<scene>/ with frame_\*.json\)"):
            lerf_annotation_files(path)
    with pytest.raises(InputError, match="annotation folder not found"):
        lerf_annotation_files(tmp_path / "absent")


def test_truncated_colmap_binary(tmp_path):
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    src = shared_path("fern", "sparse", "0")
    (sparse / "cameras.bin").write_bytes((src / "cameras.bin").read_bytes())
    (sparse / "images.bin").write_bytes((src / "images.bin").read_bytes()[:5000])
    with pytest.raises(InputError, match=r"images.bin: field 'NUM_POINTS2D': image \d+ declares \d+ points \(\d+ bytes\), but only \d+ bytes "
                                         "follow: the count is wrong, or the file was cut short"):
        load_cameras(tmp_path)


def _points3d_bin(records: list[tuple[int, tuple[float, float, float], int]], declared: int | None = None) -> bytes:
    """A points3D.bin of (id, xyz, track length) records (colour, error and track filled in)."""
    import struct

    out = struct.pack("<Q", len(records) if declared is None else declared)
    for pid, xyz, track in records:
        out += struct.pack("<Q3d3BdQ", pid, *xyz, 10, 20, 30, 0.25, track) + np.arange(2 * track, dtype="<i4").tobytes()
    return out


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
def test_a_colmap_binary_count_beyond_its_file_is_called_a_wrong_count(tmp_path, name):
    """Round 54: a count of 2⁶³ in a COLMAP binary header was called "truncated at byte N" at the first record short of
    it, which reads as a cut file. It is refused before any record is read, naming the count's field and what the
    file can hold."""
    import struct

    from drsplat.cameras import read_colmap_cameras_bin, read_colmap_images_bin, read_colmap_points_bin

    record = {"cameras.bin": struct.pack("<IiQQ3d", 1, 0, 64, 48, 50.0, 32.0, 24.0),
              "images.bin": struct.pack("<I7dI", 1, 1, 0, 0, 0, 0, 0, 0, 1) + b"a.png\x00" + struct.pack("<Q", 0),
              "points3D.bin": _points3d_bin([(1, (0.0, 0.0, 0.0), 0)])[8:]}[name]
    field = {"cameras.bin": "num_cameras", "images.bin": "num_reg_images", "points3D.bin": "num_points3D"}[name]
    read = {"cameras.bin": read_colmap_cameras_bin, "images.bin": read_colmap_images_bin, "points3D.bin": read_colmap_points_bin}[name]
    path = tmp_path / name
    path.write_bytes(struct.pack("<Q", 1) + record)
    assert len(read(path)) == 1
    path.write_bytes(struct.pack("<Q", 1 << 63) + record)
    with pytest.raises(InputError, match=rf"{name}: field '{field}': declares {1 << 63} \w+, but the {len(record)} bytes after the count "
                                         r"hold at most 1 \(a record takes at least \d+ bytes\): the count is wrong"):
        read(path)
    # round 85d F4: a record's own count (an image's points, a point's track) was "truncated at byte 93 (needs
    # 27670116110564327424 more bytes)", no field named
    if name != "cameras.bin":
        inner = {"images.bin": "NUM_POINTS2D': image 1 declares 1152921504606846976 points", "points3D.bin": "TRACK_LENGTH': point record 0 declares "
                 "1152921504606846976 track elements"}[name]
        path.write_bytes(struct.pack("<Q", 1) + record[:-8] + struct.pack("<Q", 1 << 60))
        with pytest.raises(InputError, match=rf"{name}: field '{inner} \(\d+ bytes\), but only 0 bytes follow: the count is wrong"):
            read(path)


def test_points3d_bin_reads_every_record_and_refuses_truncation_and_trailing_bytes(tmp_path):
    """points3D.bin is read by finding each record's start from the track lengths, then gathering the
    positions at once: ids and positions as written, tracks of any length skipped; a file cut inside a
    record's head or its track, or with bytes after the declared records, is one InputError."""
    from drsplat.cameras import read_colmap_points_bin

    records = [(7, (1.5, -2.0, 3.25), 0), (3, (1e30, -0.0, 5e-300), 5), (1 << 40, (0.1, 0.2, 0.3), 1)]
    path = tmp_path / "points3D.bin"
    data = _points3d_bin(records)
    path.write_bytes(data)
    points = read_colmap_points_bin(path)
    assert list(points) == [7, 3, 1 << 40]
    for pid, xyz, _ in records:
        assert points[pid].tolist() == list(xyz)
    for cut, words in ((8 + 20, "field .num_points3D.: declares 3 points, but the 20 bytes after the count hold at most 0"),  # in the first head
                       (len(data) - 4, r"field 'TRACK_LENGTH': point record 2 declares 1 track elements \(8 bytes\), but only 4 bytes "
                                       "follow: the count is wrong, or the file was cut short")):  # inside the last track
        path.write_bytes(data[:cut])
        with pytest.raises(InputError, match=f"points3D.bin: {words}"):
            read_colmap_points_bin(path)
    path.write_bytes(_points3d_bin(records, declared=2))
    with pytest.raises(InputError, match="declares 2 points but"):
        read_colmap_points_bin(path)
    path.write_bytes(_points3d_bin([*records, (3, (9.0, 9.0, 9.0), 2)]))  # round 23: the last of two records kept silently
    with pytest.raises(InputError, match=r"field 'POINT3D_ID': point record 3 repeats POINT3D_ID 3 of an earlier record"):
        read_colmap_points_bin(path)
    from drsplat.cameras import read_colmap_points_txt

    text = tmp_path / "points3D.txt"
    text.write_text("1 0 0 0 1 1 1 0.5\n2 1 1 1 1 1 1 0.5\n1 2 2 2 1 1 1 0.5\n")
    with pytest.raises(InputError, match=r"field 'POINT3D_ID': point line 3 repeats POINT3D_ID 1"):
        read_colmap_points_txt(text)


def test_points3d_bin_of_a_real_model_reads_as_its_text_twin():
    """fern's points3D.bin through the one-pass reader against the same model's points3D.txt
    (kept apart from the hostile cases above, which then run where the real fixture is absent)."""
    from drsplat.cameras import read_colmap_points_bin, read_colmap_points_txt

    fern = read_colmap_points_bin(shared_path("fern", "sparse", "0") / "points3D.bin")
    text = read_colmap_points_txt(shared_path("fern", "sparse", "0_txt") / "points3D.txt")
    assert len(fern) == 1849 and sorted(fern) == sorted(text) and all(np.allclose(fern[k], text[k], rtol=1e-6) for k in text)


def test_3dgs_cameras_json(tmp_path):
    cameras = load_cameras(shared_path("fern"))[:3]
    records = [{"id": i, "img_name": c.name, "width": c.width, "height": c.height, "position": c.center.tolist(),
                "rotation": c.R.T.tolist(), "fx": c.fx, "fy": c.fy} for i, c in enumerate(cameras)]
    (tmp_path / "cameras.json").write_text(json.dumps(records))
    loaded = load_cameras(tmp_path / "cameras.json", require_images=False)
    for a, b in zip(cameras, loaded):
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, atol=1e-9)


def test_3dgs_cameras_json_names_with_dots_keep_them(tmp_path):
    """Round 95b F2: 3DGS writes img_name "inside.000" for inside.000.png; the reader cut it to "inside", so two such
    views were refused as one name (and blamed on a camera rig's folders)."""
    from PIL import Image

    (tmp_path / "images").mkdir()
    records = []
    for i, name in enumerate(("inside.000", "inside.001", "frame.png")):
        Image.new("RGB", (64, 48)).save(tmp_path / "images" / (name if name.endswith(".png") else name + ".png"))
        records.append({"id": i, "img_name": name, "width": 64, "height": 48, "position": [0.1 * i, 0, -4],
                        "rotation": np.eye(3).tolist(), "fx": 50.0, "fy": 50.0})
    (tmp_path / "cameras.json").write_text(json.dumps(records))
    loaded = load_cameras(tmp_path)
    assert [c.name for c in loaded] == ["inside.000", "inside.001", "frame"]
    assert [c.image_path.name for c in loaded] == ["inside.000.png", "inside.001.png", "frame.png"]


def _tiny_colmap(root, image_names=("a.png", "b.png")):
    from PIL import Image

    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (root / "images").mkdir()
    (sparse / "cameras.txt").write_text("1 PINHOLE 64 48 50 50 32 24\n")
    lines = []
    for i, name in enumerate(image_names, start=1):
        (root / "images" / name).parent.mkdir(parents=True, exist_ok=True)
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


# ---------------------------------------------------------------------------------------------- round 3: COLMAP records


def colmap_text_lines(cameras, blank_lines: int = 0, last_points_line: bool = True) -> tuple[str, str]:
    """(cameras.txt, images.txt) of `cameras` (one PINHOLE camera each, empty POINTS2D lines);
    `blank_lines` extra blank lines after each record, the last POINTS2D line dropped when asked."""
    from drsplat.synthetic import rotmat_to_quat

    cams, imgs = [], ["# Image list with two lines of data per image:", f"# Number of images: {len(cameras)}, mean observations per image: 0"]
    for i, c in enumerate(cameras, start=1):
        cams.append(f"{i} PINHOLE {c.width} {c.height} {c.fx!r} {c.fy!r} {c.cx!r} {c.cy!r}")
        q = rotmat_to_quat(np.asarray(c.R, np.float64)[None])[0]
        imgs += [f"{i} {' '.join(repr(float(v)) for v in q)} {' '.join(repr(float(v)) for v in c.t)} {i} {c.image_path.name}", ""]
        imgs += [""] * blank_lines
    if not last_points_line:
        imgs = imgs[: len(imgs) - 1 - blank_lines]
    return "\n".join(cams) + "\n", "\n".join(imgs) + "\n"


def _colmap_bin(cameras, declared_images: int | None = None, duplicate: str | None = None) -> tuple[bytes, bytes]:
    """(cameras.bin, images.bin) of `cameras`, with another declared image count or a repeated id."""
    import struct

    from drsplat.synthetic import rotmat_to_quat

    cam_ids = [1 if duplicate == "camera" else i for i in range(1, len(cameras) + 1)]
    img_ids = [1 if duplicate == "image" else i for i in range(1, len(cameras) + 1)]
    cams = struct.pack("<Q", len(cameras)) + b"".join(
        struct.pack("<iiQQ4d", k, 1, c.width, c.height, c.fx, c.fy, c.cx, c.cy) for k, c in zip(cam_ids, cameras))
    imgs = struct.pack("<Q", len(cameras) if declared_images is None else declared_images) + b"".join(
        struct.pack("<I4d3dI", k, *rotmat_to_quat(np.asarray(c.R, np.float64)[None])[0], *c.t, i) + c.image_path.name.encode() + b"\0" + struct.pack("<Q", 0)
        for i, (k, c) in enumerate(zip(img_ids, cameras), start=1))
    return cams, imgs


def _write_model(root, files: dict[str, str | bytes]):
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    for name, data in files.items():
        (sparse / name).write_bytes(data.encode() if isinstance(data, str) else data)
    return root


@pytest.fixture
def four_cameras(tmp_path):
    return load_cameras(_tiny_colmap(tmp_path / "src", ("a.png", "b.png", "c.png", "d.png")))


@pytest.mark.parametrize("blank_lines, last_points_line", [(1, True), (2, True), (0, False), (1, False)])
def test_colmap_images_txt_keeps_every_record_despite_blank_lines(tmp_path, four_cameras, blank_lines, last_points_line):
    """Round 3 C1: images.txt was read as fixed line pairs: one extra blank line dropped every later
    image (3 of 16 views, exit 0) and a last record without its POINTS2D line was dropped. Now
    every record is kept, with the same poses as the well-formed file."""
    cams, imgs = colmap_text_lines(four_cameras, blank_lines, last_points_line)
    loaded = load_cameras(_write_model(tmp_path / "m", {"cameras.txt": cams, "images.txt": imgs}), require_images=False)
    assert [c.name for c in loaded] == ["a", "b", "c", "d"]
    for a, b in zip(four_cameras, loaded):
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, atol=1e-12)


def test_colmap_text_files_with_a_byte_order_mark_read_like_without(tmp_path, four_cameras):
    """Notepad saves UTF-8 with a byte-order mark: cameras.txt was "a malformed camera line" and
    images.txt "not an image line" (round 5). The mark is skipped, as in JSON files."""
    cams, imgs = colmap_text_lines(four_cameras)
    model = {"cameras.txt": "\ufeff" + cams, "images.txt": "\ufeff" + imgs}
    loaded = load_cameras(_write_model(tmp_path / "m", model), require_images=False)
    assert [c.name for c in loaded] == ["a", "b", "c", "d"]
    for a, b in zip(four_cameras, loaded):
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        assert (a.fx, a.width) == (b.fx, b.width)


def test_colmap_images_txt_count_comment_that_disagrees_is_a_warning(tmp_path, four_cameras, caplog):
    """Round 3 C1: records read against the "# Number of images" comment COLMAP writes."""
    cams, imgs = colmap_text_lines(four_cameras)
    imgs = imgs.replace("Number of images: 4", "Number of images: 5")
    with caplog.at_level(logging.WARNING):
        assert len(load_cameras(_write_model(tmp_path / "m", {"cameras.txt": cams, "images.txt": imgs}), require_images=False)) == 4
    assert "images.txt: line 2 declares 5 images but 4 image records were read" in caplog.text


@pytest.mark.parametrize("case, expected", [
    ("count_smaller", r"images\.bin: field 'num_reg_images': declares 1 images but \d+ bytes follow the last of them"),
    ("duplicate_image", r"images\.bin: field 'IMAGE_ID': image record 1 repeats IMAGE_ID 1"),
    ("duplicate_camera", r"cameras\.bin: field 'CAMERA_ID': camera record 1 repeats CAMERA_ID 1"),
    ("trailing_camera_bytes", r"cameras\.bin: field 'num_cameras': declares 4 cameras but 7 bytes follow"),
])
def test_colmap_binary_counts_and_ids(tmp_path, four_cameras, case, expected):
    """Round 3 C2/C3: a declared count smaller than the records present (the rest ignored) and
    repeated ids (last one won) were silent; now one error naming the file, the field and the numbers."""
    cams, imgs = _colmap_bin(four_cameras, declared_images=1 if case == "count_smaller" else None,
                             duplicate={"duplicate_image": "image", "duplicate_camera": "camera"}.get(case))
    if case == "trailing_camera_bytes":
        cams += b"\0" * 7
    root = _write_model(tmp_path / "m", {"cameras.bin": cams, "images.bin": imgs})
    with pytest.raises(InputError, match=expected):
        load_cameras(root, require_images=False)


def test_colmap_binary_model_reads_like_the_text_model(tmp_path, four_cameras):
    """The binary writer of these tests is a valid model: the same cameras as the text one."""
    cams, imgs = _colmap_bin(four_cameras)
    loaded = load_cameras(_write_model(tmp_path / "m", {"cameras.bin": cams, "images.bin": imgs}), require_images=False)
    assert [c.name for c in loaded] == ["a", "b", "c", "d"]
    for a, b in zip(four_cameras, loaded):
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)


def test_a_resolution_above_the_views_width_warns_once(tmp_path, four_cameras, caplog):
    """`--resolution 16384` on 128-px views upscaled them 128x without a word (then ran out of memory)."""
    from drsplat.cameras import scale_cameras

    width = four_cameras[0].width
    with caplog.at_level(logging.WARNING):
        same = scale_cameras(four_cameras, width // 2)
    assert not caplog.records and same[0].width == width // 2
    with caplog.at_level(logging.WARNING):
        big = scale_cameras(four_cameras, 4 * width)
    (record,) = caplog.records
    assert big[0].width == 4 * width and "upscales 4 of 4 views" in record.getMessage() and "4x" in record.getMessage()



def test_cameras_whose_images_all_have_another_extension_say_where_they_looked(tmp_path):
    """Images re-saved as .jpg where the camera file names .png: "yields no usable camera (every image
    file is missing)" named neither the folder searched nor the files of the same names that are
    there (a probe on real photos, 2026-11-30)."""
    from PIL import Image

    from drsplat.cameras import load_cameras

    frames = [{"file_path": f"images/r_{i}.png", "transform_matrix": np.eye(4).tolist()} for i in range(2)]
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.8, "w": 8, "h": 6, "frames": frames}))
    (tmp_path / "images").mkdir()
    for i in range(2):
        Image.new("RGB", (8, 6)).save(tmp_path / "images" / f"r_{i}.jpg")
    with pytest.raises(InputError, match=r"every image file is missing: e\.g\. .*images/r_0\.png; r_0\.jpg in that folder has its name but "
                                         r"another extension: the cameras name '\.png' files"):
        load_cameras(tmp_path)


def test_images_named_without_a_suffix_are_found_in_any_case_of_theirs(tmp_path):
    """Round 85d F2: a camera file that names its images without a suffix (NeRF's file_path, 3DGS's cameras.json) found
    NAME.png or NAME.JPG but not NAME.BMP, NAME.Tif or NAME.Jpg, and then called those extensions unreadable."""
    from PIL import Image

    from drsplat.cameras import load_cameras

    frames = [{"file_path": f"images/r_{i}", "transform_matrix": np.eye(4).tolist()} for i in range(4)]
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.8, "w": 8, "h": 6, "frames": frames}))
    (tmp_path / "images").mkdir()
    for i, (suffix, kind) in enumerate(((".BMP", "BMP"), (".Tif", "TIFF"), (".Jpg", "JPEG"), (".Png", "PNG"))):
        Image.new("RGB", (8, 6)).save(tmp_path / "images" / f"r_{i}{suffix}", format=kind)
    (tmp_path / "images" / "r_3.JPG").mkdir()  # round 87a F2: a folder sorting first hid the image after it
    cams = load_cameras(tmp_path)
    assert [c.image_path.name for c in cams] == ["r_0.BMP", "r_1.Tif", "r_2.Jpg", "r_3.Png"] and [c.name for c in cams] == ["r_0", "r_1", "r_2", "r_3"]


def test_a_folder_is_listed_once_for_the_suffixes_of_many_names(tmp_path, monkeypatch):
    """Round 86c F1: each name without a suffix listed and sorted its whole folder again (12,000 .TIF images: 92 s)."""
    import drsplat.cameras as dc

    (tmp_path / "images").mkdir()
    for i in range(40):
        (tmp_path / "images" / f"v_{i}.TIF").write_bytes(b"x")
    listed = []
    real = dc.os.listdir
    monkeypatch.setattr(dc.os, "listdir", lambda folder: listed.append(folder) or real(folder))
    paths = dc.DatasetPaths(tmp_path, tmp_path / "transforms.json")
    assert [paths.find(f"images/v_{i}").name for i in range(40)] == [f"v_{i}.TIF" for i in range(40)]
    assert len(listed) <= 2, listed  # `may_hold`'s listing and the suffixes' table, once each


@pytest.mark.parametrize("spelling", ["case", "unicode", "unsuffixed", "folding"])
def test_an_image_named_in_another_case_or_unicode_form_is_said_so(tmp_path, spelling):
    """Round 85d F3: an image whose name differs from the camera file's only in letter case, or in composed against
    decomposed accents (a zip made on macOS), was "missing", the path shown looking like the file `ls` lists."""
    import unicodedata

    from PIL import Image

    from drsplat.cameras import load_cameras

    named, stored = {"case": ("Orbit_0.png", "orbit_0.png"),
                     "unicode": (unicodedata.normalize("NFD", "\u00e9t\u00e9.png"), unicodedata.normalize("NFC", "\u00e9t\u00e9.png")),
                     "unsuffixed": ("img", "IMG.png"),  # round 86c F2: a name without a suffix was not said
                     "folding": ("Strasse.png", "Stra\u00dfe.png")}[spelling]  # round 86c F6: called "letter case"
    frames = [{"file_path": f"images/{named}", "transform_matrix": np.eye(4).tolist()}]
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.8, "w": 8, "h": 6, "frames": frames}))
    (tmp_path / "images").mkdir()
    Image.new("RGB", (8, 6)).save(tmp_path / "images" / stored)
    if spelling == "unsuffixed":  # round 87a F3: a folder of an alike name was called an accent's encoding
        (tmp_path / "images" / "IMG.PNG").mkdir()  # sorts before IMG.png
    how = {"case": "in letter case", "unicode": "in how its accented letters are encoded (Unicode NFC against NFD",
           "unsuffixed": "in letter case (and it has an image suffix the cameras leave out)",
           "folding": "in letter case as Unicode compares it (ß and ss"}[spelling]
    with pytest.raises(InputError, match=re.escape(f"; {stored!r} in that folder differs from the name the cameras give only {how}")):
        load_cameras(tmp_path)


def _similarity(seed: int = 3):
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_euler("zyx", [50.0, -20.0, 110.0], degrees=True)
    return rot, rot.as_matrix(), np.array([0.4, -1.3, 2.2]), 0.37


def test_a_camera_in_the_trained_frame_sees_every_point_at_the_same_pixel():
    from drsplat.cameras import in_trained_frame, look_at_camera

    _, rotation, translation, scale = _similarity()
    cam = look_at_camera((3.0, 1.0, -4.0), (0.0, 0.2, 0.0), 64, 48)
    moved = in_trained_frame(cam, rotation, translation, scale)
    points = np.random.default_rng(0).normal(size=(50, 3))
    uv, z = cam.project(points)
    uv2, z2 = moved.project(scale * (points @ rotation.T + translation))
    np.testing.assert_allclose(uv2, uv, atol=1e-9)
    np.testing.assert_allclose(z2, scale * z, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(moved.R) @ np.asarray(moved.R).T, np.eye(3), atol=1e-12)


def test_a_splatfacto_scene_registers_with_its_datasets_cameras_and_dataparser_transforms(tmp_path, caplog):
    """nerfstudio trains (and ns-export writes a splatfacto PLY) in the frame x' = s·(R x + t) of its
    dataparser_transforms.json, not in its dataset's frame. Copied beside the dataset's cameras, the
    file moves them into that frame: the transformed scene registers as the original one did."""
    import dataclasses
    import shutil

    from drsplat.registration import RegisterOptions, register_features
    from drsplat.scene import load_ply
    from drsplat.synthetic import write_dataset

    data = write_dataset(tmp_path / "room", "tiny", 0, show_progress=False)
    scene, cams = load_ply(data / "scene.ply"), load_cameras(data)
    rot, rotation, translation, scale = _similarity()
    quats = scene.quats[:, [1, 2, 3, 0]].astype(np.float64)  # (w, x, y, z) -> scipy's (x, y, z, w)
    from scipy.spatial.transform import Rotation

    turned = (rot * Rotation.from_quat(quats)).as_quat()[:, [3, 0, 1, 2]]
    trained = dataclasses.replace(scene, means=(scale * (scene.means.astype(np.float64) @ rotation.T + translation)).astype(np.float32),
                                  quats=turned.astype(np.float32), log_scales=scene.log_scales + np.float32(np.log(scale)))
    moved = tmp_path / "moved"
    shutil.copytree(data, moved)
    (moved / "dataparser_transforms.json").write_text(json.dumps(
        {"transform": np.c_[rotation, translation].tolist(), "scale": scale}))
    with caplog.at_level(logging.INFO):
        moved_cams = load_cameras(moved)
    assert "cameras moved into the frame nerfstudio trained in" in caplog.text
    options = RegisterOptions(topk=10, aggregate="paper")
    ref = register_features(scene, cams, data / "features", options, show_progress=False)
    got = register_features(trained, moved_cams, moved / "features", options, show_progress=False)
    assigned = ref.weights > 0
    assert abs(int((got.weights > 0).sum()) - int(assigned.sum())) <= 3
    rel = np.abs(got.weights[assigned] - ref.weights[assigned]) / ref.weights[assigned]
    assert np.mean(rel < 1e-3) > 0.995 and rel.max() < 0.05  # the float32 rounding of the moved scene moves a few depth ties
    cos = np.einsum("nd,nd->n", got.features[assigned].astype(np.float64), ref.features[assigned].astype(np.float64))
    assert np.quantile(cos, 0.01) > 0.999


@pytest.mark.parametrize("case", ["applied_transform", "colmap_folder", "applied_scale", "checkpoint_run"])
def test_a_nerfstudio_applied_transform_is_undone_before_its_dataparser_transform(tmp_path, caplog, case):
    """Round 54: ns-process-data writes every pose as A·c2w with `applied_transform`: A, and ns-train saves
    dataparser_transforms.json as T·A (a move from the frame before A). drsplat applied T·A to poses already moved by A:
    a splatfacto scene registered off by A (seg mIoU 0.135 against 0.950), with a frame warning that asked for the file
    already there. Round 55 (nerfstudio_dataparser.py read again): without the key, beside a colmap/sparse/0 folder,
    nerfstudio takes A = [[0,1,0],[1,0,0],[0,0,-1]] itself; `applied_scale` a is multiplied into the saved scale and never
    into the poses (the scale was a times too large); a checkpoint's run file is read the same way. Each dataset gives
    the cameras of the one without A and a, with the file T·A and scale s; a bad applied_transform is one error."""
    import shutil

    from drsplat.frames import cameras_in_scene_frame
    from drsplat.synthetic import write_dataset

    data = write_dataset(tmp_path / "room", "tiny", 0, show_progress=False)
    _, rotation, translation, scale = _similarity()
    plain, applied = tmp_path / "plain", tmp_path / "applied"
    shutil.copytree(data, plain)
    shutil.copytree(data, applied)
    move = np.eye(4)
    if case != "applied_scale":
        move = np.eye(4)[[1, 0, 2, 3]]  # nerfstudio's rows (1, 0, 2), the third negated; as a key, a translation too
        move[2, :3] *= -1
        move[:3, 3] = (0.1, -0.2, 0.3) if case != "colmap_folder" else 0.0
    meta = json.loads((data / "transforms.json").read_text())
    for frame in meta["frames"]:
        frame["transform_matrix"] = (move @ np.asarray(frame["transform_matrix"])).tolist()
    if case == "colmap_folder":
        (applied / "colmap" / "sparse" / "0").mkdir(parents=True)
    else:
        meta["applied_transform"] = move[:3].tolist()
    a = 2.5 if case == "applied_scale" else 1.0
    if a != 1.0:
        meta["applied_scale"] = a
    (applied / "transforms.json").write_text(json.dumps(meta))
    saved = np.r_[np.c_[rotation, translation], [[0, 0, 0, 1]]] @ move  # what ns-train writes: T·A, from the frame before A
    (plain / "dataparser_transforms.json").write_text(json.dumps({"transform": saved[:3].tolist(), "scale": scale}))
    run = tmp_path / "outputs" / "room" / "splatfacto" / "2026-12-05_120000"
    (run / "nerfstudio_models").mkdir(parents=True)
    (run if case == "checkpoint_run" else applied).joinpath("dataparser_transforms.json").write_text(
        json.dumps({"transform": saved[:3].tolist(), "scale": scale * a}))
    want = load_cameras(plain)
    with caplog.at_level(logging.INFO):
        got = load_cameras(applied)
        if case == "checkpoint_run":
            got = cameras_in_scene_frame(np.zeros((0, 3)), got, applied, scene_path=run / "nerfstudio_models" / "step-000029999.ckpt")
    assert {"applied_transform": "after undoing transforms.json's applied_transform, which the file includes",
            "colmap_folder": "after undoing the applied_transform nerfstudio takes for a transforms.json without one beside a colmap",
            "applied_scale": "after undoing transforms.json's applied_transform and transforms.json's applied_scale 2.5",
            "checkpoint_run": "after undoing transforms.json's applied_transform, which the run's file includes"}[case] in caplog.text
    for a_cam, b_cam in zip(want, got):
        np.testing.assert_allclose(b_cam.R, a_cam.R, atol=1e-12)
        np.testing.assert_allclose(b_cam.t, a_cam.t, atol=1e-9)
    if case == "applied_transform":
        meta["applied_transform"] = [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]
        (applied / "transforms.json").write_text(json.dumps(meta))
        with pytest.raises(InputError, match=r"transforms.json: field 'applied_transform': has a 3x3 part that is not a rotation "
                                             r"\(ns-process-data's applied_transform is a rigid move of the poses\)"):
            load_cameras(applied)
        meta["applied_transform"], meta["applied_scale"] = move[:3].tolist(), 0.0
        (applied / "transforms.json").write_text(json.dumps(meta))
        with pytest.raises(InputError, match=r"transforms.json: field 'applied_scale': has applied_scale 0; it must lie in"):
            load_cameras(applied)
        # round 56b: each within its bounds, their quotient not: cameras at 1e30 (an error quoting a scale in neither file) or
        # all at the origin (exit 0); one error now, naming both values and the dataparser file's field
        for a, s in ((1e-15, 1e15), (1e15, 1e-15)):
            meta["applied_scale"] = a
            (applied / "transforms.json").write_text(json.dumps(meta))
            (applied / "dataparser_transforms.json").write_text(json.dumps({**json.loads((applied / "dataparser_transforms.json").read_text()), "scale": s}))
            with pytest.raises(InputError, match=re.escape(f"dataparser_transforms.json: field 'scale': has scale {s:g}, which over the "
                                                           f"transforms.json's applied_scale {a:g} (ns-train multiplies that into it) "
                                                           f"gives {s / a:g}, outside")):
                load_cameras(applied)


@pytest.mark.parametrize("content, words", [
    ({"transform": [[1, 0, 0, 0], [0, 1, 0, 0]], "scale": 1}, "'transform': is not 3 (or 4) rows of 4 numbers"),
    ({"transform": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "scale": 1}, "is not a rotation"),
    ({"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0]], "scale": 1}, "is not a rotation"),
    ({"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "scale": 0}, "'scale': has scale 0"),
    ({"transform": [[1, 0, 0, "x"], [0, 1, 0, 0], [0, 0, 1, 0]], "scale": 1}, "'transform': has a non-numeric value in row 0"),
    ({"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1e400]], "scale": 1}, "'transform': has a non-finite value in row 2"),
    ({"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 2]], "scale": 1}, "fourth row that is not 0 0 0 1"),
    ({"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}, "'scale': is missing"),
    ({"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "scale": None}, "'scale': is null (a JSON null, expected a number)"),  # was "missing"
    ([1, 2], "is not a JSON object"),
])
def test_a_bad_dataparser_transforms_file_is_one_error_naming_it(tmp_path, content, words):
    from drsplat.synthetic import write_dataset

    data = write_dataset(tmp_path / "room", "tiny", 0, show_progress=False)
    (data / "dataparser_transforms.json").write_text(json.dumps(content))
    with pytest.raises(InputError, match="dataparser_transforms.json") as info:
        load_cameras(data)
    assert words in str(info.value)


# ---------------------------------------------------------------------------------------------- probe fuzz1: camera readers

QUATERNION = np.array([0.7, -0.2, 0.5, 0.4]) / np.linalg.norm([0.7, -0.2, 0.5, 0.4])  # (w, x, y, z), a turn about no axis


def _one_image_model(root, qvec, fmt: str, name: bytes = b"a.png"):
    """A COLMAP model of one PINHOLE 64x48 camera and one image `name` with quaternion `qvec`, as text or binary."""
    import struct

    if fmt == "txt":
        images = f"1 {' '.join(repr(float(v)) for v in qvec)} 0.0 0.0 4.0 1 {name.decode()}\n\n"
        return _write_model(root, {"cameras.txt": "1 PINHOLE 64 48 50 50 32 24\n", "images.txt": images})
    cameras = struct.pack("<QiiQQ4d", 1, 1, 1, 64, 48, 50.0, 50.0, 32.0, 24.0)
    images = struct.pack("<QI4d3dI", 1, 1, *qvec, 0.0, 0.0, 4.0, 1) + name + b"\0" + struct.pack("<Q", 0)
    return _write_model(root, {"cameras.bin": cameras, "images.bin": images})


@pytest.mark.parametrize("fmt", ["txt", "bin"])
@pytest.mark.parametrize("scale", [1e300, 2.0**600, 1e-310])
def test_a_colmap_quaternion_at_any_finite_scale_gives_its_rotation(tmp_path, fmt, scale):
    """Probe fuzz1 finding 1: a quaternion x 1e300 squared to inf in |q|, q/inf = 0 became the identity
    (a wrong pose, exit 0, numpy's overflow warning); one of subnormal components (1e-310) squared to
    0 and was refused as zero. Now q is scaled by a power of two before its norm: the rotation COLMAP
    means, with no warning; an exact power-of-two scale changes no bit."""
    from scipy.spatial.transform import Rotation

    from drsplat.cameras import qvec_to_rotmat

    root = _one_image_model(tmp_path / "m", QUATERNION * scale, fmt)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        (camera,) = load_cameras(root, require_images=False)
    expected = Rotation.from_quat(QUATERNION[[1, 2, 3, 0]]).as_matrix()
    np.testing.assert_allclose(camera.R, expected, atol=1e-12)
    assert not np.allclose(camera.R, np.eye(3), atol=0.1)
    if scale == 2.0**600:
        assert np.array_equal(camera.R, qvec_to_rotmat(QUATERNION))


@pytest.mark.parametrize("fmt", ["txt", "bin"])
@pytest.mark.parametrize("qvec, shown, problem", [
    ((np.inf, 0.0, 0.0, 1e300), "inf 0 0 1e+300", "a component that is not finite"),
    ((0.0, np.nan, 0.0, 0.0), "0 nan 0 0", "a component that is not finite"),
    ((0.0, 0.0, 0.0, 0.0), "0 0 0 0", "all components zero, which is no rotation"),
])
def test_a_colmap_quaternion_that_is_no_rotation_is_one_error_naming_the_image(tmp_path, fmt, qvec, shown, problem):
    """A quaternion with a non-finite component, or all zeros, has no rotation: one error naming the
    images file, the image, the field and the values as written (it said only "zero or non-finite");
    `qvec_to_rotmat` itself (also read by frames.py) gives NaN there without numpy's warning."""
    from drsplat.cameras import qvec_to_rotmat

    root = _one_image_model(tmp_path / "m", qvec, fmt)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(InputError) as info:
            load_cameras(root, require_images=False)
        assert np.isnan(qvec_to_rotmat(np.array(qvec))).all()
    assert str(info.value) == (f"{root / 'sparse' / '0' / f'images.{fmt}'}: field 'QW QX QY QZ': image 1 ('a.png') has the rotation "
                               f"quaternion {shown}, with {problem}")


def _transforms_dataset(root, **meta):
    """A transforms.json folder with one 64x48 image, the frame's keys and matrix from `meta`."""
    from PIL import Image

    (root / "images").mkdir(parents=True)
    Image.new("RGB", (64, 48)).save(root / "images" / "v.png")
    frame = {"file_path": "images/v.png", "transform_matrix": meta.pop("matrix", np.eye(4).tolist()), "w": 64, "h": 48}
    frame.update(meta.pop("frame", {}))
    (root / "transforms.json").write_text(json.dumps({**meta, "frames": [frame]}))
    return root


def _scannet_scene(root, pose: np.ndarray):
    """A ScanNet export of one 64x48 frame with camera-to-world `pose`."""
    from PIL import Image

    for sub in ("pose", "intrinsic", "color"):
        (root / sub).mkdir(parents=True)
    np.savetxt(root / "intrinsic" / "intrinsic_color.txt", np.array([[50, 0, 32, 0], [0, 50, 24, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]))
    np.savetxt(root / "pose" / "0.txt", pose)
    Image.new("RGB", (64, 48)).save(root / "color" / "0.jpg")
    return root


def _turned(scale: float = 1.0, centre=(0.0, 0.0, 4.0)) -> list[list[float]]:
    """A 4x4 camera-to-world matrix turned 45 degrees about z, its 3x3 part times `scale`."""
    m = np.eye(4)
    m[:2, :2] = np.sqrt(0.5) * np.array([[1.0, -1.0], [1.0, 1.0]])
    m[:3, :3] *= scale
    m[:3, 3] = centre
    return m.tolist()


@pytest.mark.parametrize("case, expected", [
    ("transforms_rotation_1e300", r"transforms\.json: field 'transform_matrix': frame 0 has a rotation that is not orthonormal"),
    ("transforms_rotation_1e308", r"transforms\.json: field 'transform_matrix': frame 0 has a rotation that is not orthonormal"),
    ("transforms_centre_1e308", r"transforms\.json: field 'transform_matrix': frame 0 has a camera position of 1\.5e\+308, beyond any scene"),
    ("cameras_json_rotation_1e300", r"cameras\.json: field 'rotation': camera 0 has a rotation that is not orthonormal"),
    ("cameras_json_position_1e308", r"cameras\.json: field 'position': camera 0 has a camera position of 1\.5e\+308, beyond any scene"),
    ("scannet_rotation_1e308", r"pose/0\.txt: field 'rotation': frame 0 has a rotation that is not orthonormal"),
])
def test_huge_rotations_and_positions_in_camera_files_are_refused_without_numpy_warnings(tmp_path, case, expected):
    """Probe fuzz1 finding 4: a transform_matrix rotation x 1e300 printed numpy's "overflow encountered
    in matmul" before its (right) error; near 1e308, or with a camera position near it, -R c overflowed
    to a "non-finite translation" the file does not hold. The same in cameras.json and ScanNet poses.
    Now one error naming the file and field."""
    if case.startswith("scannet"):
        source = _scannet_scene(tmp_path / "scene0000_00", np.array(_turned(1e308)))
    elif case.startswith("transforms"):
        matrix = _turned(1e308 if case.endswith("1e308") and "rotation" in case else 1e300 if "rotation" in case else 1.0,
                         (1.5e308, 1.5e308, 0.0) if "centre" in case else (0.0, 0.0, 4.0))
        source = _transforms_dataset(tmp_path / "t", matrix=matrix, frame={"fl_x": 50.0})
    else:
        c2w = np.array(_turned(1e300 if "rotation" in case else 1.0))
        position = [1.5e308, 1.5e308, 0.0] if "position" in case else [0.0, 0.0, 4.0]
        (tmp_path / "cameras.json").write_text(json.dumps([{"id": 0, "img_name": "v", "width": 64, "height": 48, "fx": 50, "fy": 50,
                                                            "rotation": c2w[:3, :3].tolist(), "position": position}]))
        source = tmp_path / "cameras.json"
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(InputError, match=expected):
            load_cameras(source, require_images=False)


def test_a_dataparser_rotation_with_huge_entries_is_refused_without_numpy_warnings(tmp_path):
    """The same rule for nerfstudio's dataparser_transforms.json: R Rᵀ of entries near 1e300 overflowed."""
    from drsplat.cameras import read_dataparser_transform

    path = tmp_path / "dataparser_transforms.json"
    path.write_text(json.dumps({"transform": [row[:4] for row in _turned(1e300)[:3]], "scale": 1.0}))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(InputError, match=r"dataparser_transforms\.json: field 'transform': has a 3x3 part that is not a rotation"):
            read_dataparser_transform(path)


@pytest.mark.parametrize("angle, shown", [(1e-320, "9.99989e-321"), (1e-7, "1e-07")])
def test_a_field_of_view_too_narrow_for_any_lens_names_camera_angle_x(tmp_path, angle, shown):
    """Probe fuzz1 finding 4: camera_angle_x 1e-320 printed numpy's "overflow encountered in scalar
    divide", then "fx=np.float64(inf)" (a field the file does not have, in a numpy repr); 1e-7 named
    fx too. Now one error naming camera_angle_x and the angle as a plain number."""
    source = _transforms_dataset(tmp_path / "t", camera_angle_x=angle)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(InputError) as info:
            load_cameras(source, require_images=False)
    message = str(info.value)
    assert message.startswith(f"{source / 'transforms.json'}: field 'camera_angle_x': has a field of view of {shown} rad in frame 0; "
                              "it must be at least 1e-06 rad")
    assert "np." not in message and "inf" not in message


def test_a_field_of_view_at_the_narrowest_allowed_is_a_valid_camera(tmp_path):
    """The narrowest field of view accepted gives a focal length within the intrinsics' range (of a
    square image: fy = fx is bounded by the height too)."""
    from drsplat.cameras import MAX_INTRINSIC_RATIO, MIN_FIELD_OF_VIEW

    source = _transforms_dataset(tmp_path / "t", camera_angle_x=MIN_FIELD_OF_VIEW * (1 + 1e-9), frame={"h": 64})
    (camera,) = load_cameras(source, require_images=False)
    assert camera.fx == pytest.approx(MAX_INTRINSIC_RATIO * 64, rel=1e-6) and type(camera.fx) is float


def test_an_images_bin_name_that_is_not_utf8_is_refused_like_the_text_models(tmp_path):
    """Probe fuzz1 finding 10: images.bin names were decoded with replacement characters ("orbit_\\ufffd\\ufffd0"),
    so the camera was skipped as missing, where images.txt refuses the same bytes. Now both refuse,
    naming the file, the image and the byte."""
    root = _one_image_model(tmp_path / "m", QUATERNION, "bin", name=b"orbit_\xff\xfe0.png")
    with pytest.raises(InputError, match=r"images\.bin: field 'NAME': image 1 has a name that is not UTF-8 text \(invalid byte at offset 78\)"):
        load_cameras(root, require_images=False)
    text = _write_model(tmp_path / "t", {"cameras.txt": "1 PINHOLE 64 48 50 50 32 24\n", "images.txt": b"1 1 0 0 0 0 0 4 1 orbit_\xff\xfe0.png\n\n"})
    with pytest.raises(InputError, match=r"images\.txt: is not UTF-8 text"):
        load_cameras(text, require_images=False)


def test_a_folder_with_both_a_binary_and_a_text_model_says_which_it_used(tmp_path, caplog):
    """Probe fuzz1 finding 10: with cameras/images .bin and .txt side by side (the text one edited to
    another focal length), the binary one was used without a word. It still is, as COLMAP does,
    with one warning naming the folder and the model ignored; one model alone gives no warning."""
    root = _one_image_model(tmp_path / "m", QUATERNION, "bin")
    sparse = root / "sparse" / "0"
    with caplog.at_level(logging.WARNING):
        (alone,) = load_cameras(root, require_images=False)
    assert not caplog.records
    (sparse / "cameras.txt").write_text("1 PINHOLE 64 48 70 70 32 24\n")
    (sparse / "images.txt").write_text(f"1 {' '.join(map(repr, QUATERNION.tolist()))} 0 0 4 1 a.png\n\n")
    with caplog.at_level(logging.WARNING):
        (both,) = load_cameras(root, require_images=False)
    (record,) = caplog.records
    assert both.fx == alone.fx == 50.0
    assert record.getMessage().startswith(f"{sparse} holds both a binary (cameras.bin, images.bin) and a text (cameras.txt, images.txt) "
                                          "COLMAP model; the binary one is used, as COLMAP does, and the text one is ignored")


# ---------------------------------------------------------------------------------------------- probe: camera readers, a second pass


def _dataparser(folder, transform=None, scale: float = 1.0):
    """A dataparser_transforms.json in `folder`: the identity rotation with `transform`'s last column, and `scale`."""
    matrix = np.c_[np.eye(3), np.zeros(3) if transform is None else transform]
    (folder / "dataparser_transforms.json").write_text(json.dumps({"transform": matrix.tolist(), "scale": scale}))


@pytest.mark.parametrize("translation, scale, centre, expected", [
    (None, 1e300, 4.0, r"field 'scale': has scale 1e\+300; it must lie in \[1e-15, 1e\+15\]"),
    (None, 1e-300, 4.0, r"field 'scale': has scale 1e-300; it must lie in \[1e-15, 1e\+15\]"),
    ((0.0, 1e300, 0.0), 1.0, 4.0, r"field 'transform': has the translation 0 1e\+300 0 in its last column, beyond any scene"),
    ((0.0, 1e16, 0.0), 1.0, 4.0, r"field 'transform': has the translation 0 1e\+16 0 in its last column, beyond any scene"),
    (None, 1e15, 4.0, r"field 'scale': moves camera 'v' to a position of 4e\+15 \(scale 1e\+15 times 4\), beyond any scene"),
    ((0.0, 0.0, 6e14), 1.0, 5e14, r"field 'transform': moves camera 'v' to a position of 1\.1e\+15 \(its rotation and translation move "
                                   r"it to 1\.1e\+15\), beyond any scene"),
])
def test_a_dataparser_transform_that_moves_cameras_beyond_any_scene_is_refused(tmp_path, translation, scale, centre, expected):
    """Probe 2 finding 1: a dataparser_transforms.json with scale 1e300, or a translation of 1e300 or
    1e16, moved the cameras to 1e300, beyond the bound the camera files are held to, and registration
    projected the whole scene onto one pixel (exit 0, wrong labels). Now its numbers are bounded and
    every moved camera is checked: one error naming the dataparser file and the field."""
    matrix = np.eye(4)
    matrix[2, 3] = centre
    source = _transforms_dataset(tmp_path / "t", matrix=matrix.tolist(), frame={"fl_x": 50.0})
    _dataparser(source, translation, scale)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(InputError, match=f"^{source / 'dataparser_transforms.json'}: {expected}"):
            load_cameras(source, require_images=False)


def test_a_dataparser_transform_within_the_bounds_moves_cameras_as_before(tmp_path):
    """A file at the edge of the bounds (scale 1e15 on a camera within 1 of its centre) still moves
    the cameras, to the same bits as `in_trained_frame` gives."""
    from drsplat.cameras import in_trained_frame

    matrix = np.eye(4)
    matrix[2, 3] = 0.75
    source = _transforms_dataset(tmp_path / "t", matrix=matrix.tolist(), frame={"fl_x": 50.0})
    (given,) = load_cameras(source, require_images=False)
    _dataparser(source, (0.0, 0.0, 0.2), 1e15)
    (moved,) = load_cameras(source, require_images=False)
    expected = in_trained_frame(given, np.eye(3), np.array([0.0, 0.0, 0.2]), 1e15)
    assert np.array_equal(moved.R, expected.R) and np.array_equal(moved.t, expected.t)
    assert np.abs(moved.center).max() == pytest.approx(0.95e15)


def test_a_nerfstudio_runs_dataparser_transform_is_held_to_the_same_bounds(tmp_path):
    """The dataparser_transforms.json of the run a checkpoint comes from (`frames.cameras_in_scene_frame`)
    moved the cameras without the checks too."""
    from drsplat.frames import cameras_in_scene_frame

    source = _transforms_dataset(tmp_path / "t", frame={"fl_x": 50.0})
    cameras = load_cameras(source, require_images=False)
    run = tmp_path / "outputs" / "t" / "splatfacto" / "2026"
    (run / "nerfstudio_models").mkdir(parents=True)
    (run / "nerfstudio_models" / "step-000029999.ckpt").write_bytes(b"")
    _dataparser(run, scale=1e300)
    with pytest.raises(InputError, match=r"dataparser_transforms\.json: field 'scale': has scale 1e\+300"):
        cameras_in_scene_frame(np.zeros((0, 3)), cameras, source, scene_path=run / "nerfstudio_models" / "step-000029999.ckpt")


@pytest.mark.parametrize("coefficients, field, shown", [
    ({"p1": 1e308}, "p1", "1e+308"),
    ({"k1": 1e300}, "k1", "1e+300"),
    ({"k1": 0.1, "k2": 1e150}, "k2", "1e+150"),
    ({"k1": -1e3}, "k1", "-1000"),
])
def test_lens_distortion_beyond_any_lens_is_one_error_naming_the_coefficient(tmp_path, coefficients, field, shown):
    """Probe 2 finding 2: "p1": 1e308 printed numpy's overflow and cast warnings, then features of a
    blank image (exit 0); "k1": 1e300 gave a blank image and a misleading "one flat colour" warning.
    Now a lens model that moves the image's corner beyond MAX_LENS_SHIFT times its distance from the
    principal point is one error naming the coefficient that moves it most, and its value."""
    source = _transforms_dataset(tmp_path / "t", fl_x=50.0, frame=coefficients)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(InputError) as info:
            load_cameras(source)
    assert str(info.value).startswith(f"{source / 'transforms.json'}: field '{field}': has the lens distortion {field}={shown} in frame 0: ")
    assert "at most 100 times is accepted" in str(info.value)


@pytest.mark.parametrize("coefficients", [
    {"k1": 49.0, "k2": 50.0},  # together just under the bound (64x48, fl_x 40: the corners at r = 1)
    {"p1": 16.0, "p2": -16.0},  # 3 (16 + 16) r
    {"k1": -0.3, "k2": 0.1, "p1": 0.001, "p2": -0.001},  # a wide-angle barrel lens
])
def test_lens_distortion_within_the_bound_undistorts_without_numpy_warnings(tmp_path, coefficients):
    """Every coefficient the check accepts undistorts to finite pixels with no numpy warning, and a
    wide-angle lens is accepted."""
    from drsplat.cameras import MAX_LENS_SHIFT, lens_shifts

    source = _transforms_dataset(tmp_path / "t", fl_x=40.0, frame=coefficients)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        (camera,) = load_cameras(source)
        image = load_image(camera)
    assert sum(lens_shifts(camera).values()) <= MAX_LENS_SHIFT and image.shape == (48, 64, 3)


def test_undistortion_keeps_its_pixels_where_the_lens_samples_beyond_the_file(tmp_path):
    """The source coordinates are clipped to a pixel beyond the file's edges (map_coordinates' index
    wraps past about 1e18): the undistorted image of a pincushion lens whose corners sample beyond the
    file has the same bits as sampling without the clip."""
    from PIL import Image
    from scipy.ndimage import map_coordinates

    dist = np.array([0.4, 0.2, 0.01, -0.02])
    cam = Camera(R=np.eye(3), t=np.zeros(3), fx=60.0, fy=60.0, cx=64.0, cy=48.0, width=128, height=96,
                 image_path=tmp_path / "d.png", name="d", distortion=dist)
    pixels = np.random.default_rng(1).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(cam.image_path)
    u, v = np.meshgrid(np.arange(128) + 0.5, np.arange(96) + 0.5)
    src = distort_normalized(np.stack([(u - 64.0) / 60.0, (v - 48.0) / 60.0], -1), dist) * 60.0 + [64.0, 48.0] - 0.5
    assert (src < -1).any() and (src[..., 0] > 128).any()
    unclipped = np.stack([map_coordinates(pixels[..., c].astype(np.float32), [src[..., 1], src[..., 0]], order=1, mode="nearest")
                          for c in range(3)], -1)
    assert np.array_equal(load_image(cam), np.clip(np.rint(unclipped), 0, 255).astype(np.uint8))


@pytest.mark.parametrize("meta, field, words", [
    ({"camera_angle_x": 1e-6, "frame": {"h": 96, "w": 128}}, "camera_angle_x",
     "has a field of view of 1e-06 rad in frame 0, a focal length of 1.28e+08 pixels (used for the height too: the file gives no "
     "y focal length) for an image 96 pixels in height"),
    ({"camera_angle_x": 3.14159265}, "camera_angle_x", "has a field of view of 3.14159265 rad in frame 0, a focal length of 1.14873e-07 pixels for an image 128 pixels in width"),
    ({"camera_angle_x": 0.8, "camera_angle_y": 3.1415926}, "camera_angle_y", "has a field of view of 3.1415926 rad in frame 0"),
    ({"fl_x": 1e-300}, "fl_x", "frame 0 has fl_x=1e-300 for an image 128 pixels in width"),
    ({"fl_x": 1.28e8, "frame": {"h": 96}}, "fl_x", "frame 0 has fl_x=1.28e+08 for an image 96 pixels in height"),
    ({"fl_x": 100.0, "fl_y": -3.0}, "fl_y", "frame 0 has focal length fl_y=-3; it must be a positive number"),
])
def test_focal_errors_name_the_field_the_transforms_json_has(tmp_path, meta, field, words):
    """Probe 2 finding 3: errors about focal lengths named fx or fy, fields a transforms.json does not
    have: camera_angle_x 1e-6 on a 128x96 image was "field 'fy'" (fy = fx without camera_angle_y),
    3.14159265 rad "field 'fx': ... fx=1.14873e-07" (no check at the wide end), fl_x 1e-300 "field
    'fx'". Now each names the field the file gives the focal length in."""
    frame = {"w": 128, "h": 96, **meta.pop("frame", {})}
    source = _transforms_dataset(tmp_path / "t", frame=frame, **meta)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(InputError) as info:
            load_cameras(source, require_images=False)
    assert str(info.value).startswith(f"{source / 'transforms.json'}: field '{field}': {words}")


def test_a_field_of_view_near_pi_still_gives_its_focal_length(tmp_path):
    """A wide field of view within the intrinsics' range loads with the focal length it always gave."""
    source = _transforms_dataset(tmp_path / "t", camera_angle_x=3.1, frame={"h": 64})
    (camera,) = load_cameras(source, require_images=False)
    assert camera.fx == camera.fy == 0.5 * 64 / np.tan(0.5 * 3.1)


def test_a_camera_position_that_is_not_a_number_names_the_field_position(tmp_path):
    """Probe 2 finding 3: a NaN position in a 3DGS cameras.json was refused as "field 'translation'"."""
    (tmp_path / "cameras.json").write_text(json.dumps([{"id": 0, "img_name": "v", "width": 64, "height": 48, "fx": 50, "fy": 50,
                                                        "rotation": np.eye(3).tolist(), "position": [0.0, float("nan"), 4.0]}]))
    with pytest.raises(InputError, match=r"cameras\.json: field 'position': camera 0 has the camera position 0 nan 4, which is not finite"):
        load_cameras(tmp_path / "cameras.json", require_images=False)


def test_a_colmap_translation_that_is_not_finite_names_tx_ty_tz(tmp_path):
    """The same rule for COLMAP: its images file calls the translation TX TY TZ (as the rotation QW QX QY QZ)."""
    root = _write_model(tmp_path / "m", {"cameras.txt": "1 PINHOLE 64 48 50 50 32 24\n", "images.txt": "1 1 0 0 0 0 inf 4 1 a.png\n\n"})
    with pytest.raises(InputError, match=r"images\.txt: field 'TX TY TZ': image 1 \('a\.png'\) has a non-finite translation"):
        load_cameras(root, require_images=False)


def test_a_stray_binary_file_beside_a_text_model_is_named_in_a_warning(tmp_path, caplog):
    """Probe 2 finding 4: a lone cameras.bin beside a complete text model was ignored without a word.
    The text model is still used, with one warning naming the stray file and the one it lacks."""
    binary = _one_image_model(tmp_path / "b", QUATERNION, "bin") / "sparse" / "0"
    root = _one_image_model(tmp_path / "m", QUATERNION, "txt")
    sparse = root / "sparse" / "0"
    (sparse / "cameras.bin").write_bytes((binary / "cameras.bin").read_bytes())
    with caplog.at_level(logging.WARNING):
        (camera,) = load_cameras(root, require_images=False)
    (record,) = caplog.records
    assert camera.fx == 50.0
    assert record.getMessage() == (f"{sparse} has cameras.bin but no images.bin: the text model (cameras.txt, images.txt) is used and it is "
                                   "ignored (a COLMAP model is all binary or all text: remove the stray files, or complete their model)")


@pytest.mark.parametrize("files, words", [
    (("cameras.bin", "images.txt"), "has cameras.bin and images.txt, but a COLMAP model is all binary (cameras.bin, images.bin) or all text"),
    (("cameras.txt", "images.bin"), "has cameras.txt and images.bin, but a COLMAP model is all binary"),
    (("cameras.bin", "points3D.txt"), "has cameras.bin but no images.bin: a COLMAP model needs both"),
    (("cameras.bin", "cameras.txt"), "has cameras.bin and cameras.txt but no images.bin or images.txt: a COLMAP model needs both"),
])
def test_a_colmap_folder_of_mixed_or_partial_files_says_what_is_there_and_what_is_missing(tmp_path, files, words):
    """Probe 2 finding 4: cameras.bin beside images.txt (and no complete model) was "is not a COLMAP
    sparse model". Now the error names the files there and what is missing."""
    models = {fmt: _one_image_model(tmp_path / fmt, QUATERNION, fmt) / "sparse" / "0" for fmt in ("bin", "txt")}
    (tmp_path / "txt" / "sparse" / "0" / "points3D.txt").write_text("1 0 0 0 1 1 1 0.5\n")
    sparse = tmp_path / "m" / "sparse" / "0"
    sparse.mkdir(parents=True)
    for name in files:
        (sparse / name).write_bytes((models[name.rsplit(".", 1)[1]] / name).read_bytes())
    with pytest.raises(InputError) as info:
        load_cameras(tmp_path / "m", require_images=False)
    assert str(info.value).startswith(f"{sparse}: {words}")


def _cameras_json(root, names=("a", "b"), images=("a",)):
    """A 3DGS cameras.json of 64x48 cameras `names` beside an images/ folder holding `images` (png)."""
    from PIL import Image

    (root / "images").mkdir(parents=True)
    for name in images:
        Image.new("RGB", (64, 48)).save(root / "images" / f"{name}.png")
    records = [{"id": i, "img_name": n, "width": 64, "height": 48, "position": [0.0, 0.0, -3.0 - i], "rotation": np.eye(3).tolist(),
                "fx": 50.0, "fy": 50.0} for i, n in enumerate(names)]
    (root / "cameras.json").write_text(json.dumps(records))
    return root


def test_a_cameras_json_whose_images_folder_lacks_an_image_skips_that_camera_and_says_so(tmp_path, caplog):
    """Round 39: one image missing from images/ stopped every command with "AttributeError: 'int' object has no
    attribute 'append'"; the camera is skipped and counted, as the other formats do."""
    root = _cameras_json(tmp_path)
    with caplog.at_level(logging.WARNING):
        cameras = load_cameras(root)
    assert [c.name for c in cameras] == ["a"] and "1 frame skipped because its image is missing" in caplog.text and "b" in caplog.text


def test_cameras_without_their_images_are_kept_for_registration_when_the_file_gives_their_size(tmp_path):
    """Round 39: `register` reads feature files, not images (load_cameras(require_images=False)); transforms.json and
    cameras.json ignored that and skipped every camera whose photo was absent, so such a dataset could not register."""
    root = _cameras_json(tmp_path / "json", images=())
    assert [c.name for c in load_cameras(root, require_images=False)] == ["a", "b"]
    with pytest.raises(InputError, match="no usable camera"):
        load_cameras(root)
    sized = _transforms_dataset(tmp_path / "sized", fl_x=50.0)
    (sized / "images" / "v.png").unlink()
    kept = load_cameras(sized, require_images=False)
    assert [(c.name, c.width, c.height) for c in kept] == [("v", 64, 48)]
    unsized = _transforms_dataset(tmp_path / "unsized", fl_x=50.0)
    record = json.loads((unsized / "transforms.json").read_text())
    for frame in record["frames"]:
        del frame["w"], frame["h"]
    (unsized / "transforms.json").write_text(json.dumps(record))
    (unsized / "images" / "v.png").unlink()
    with pytest.raises(InputError, match="no usable camera"):  # only the image could give its size
        load_cameras(unsized, require_images=False)


def test_a_transforms_frame_through_a_symbolic_link_is_named_as_its_file_path_names_it(tmp_path):
    """Round 39: a camera took the stem of the file its image's link leads to (a git-annex or DVC key, a content
    hash), so no feature file matched and two links to one file collided; the name is the file_path's."""
    from PIL import Image

    (tmp_path / "images").mkdir()
    (tmp_path / "store").mkdir()
    frames = []
    for i in range(2):
        Image.new("RGB", (64, 48)).save(tmp_path / "store" / f"{i:012x}.png")
        (tmp_path / "images" / f"frame_{i}.png").symlink_to(f"../store/{i:012x}.png")
        matrix = np.eye(4)
        matrix[2, 3] = 3.0 + i
        frames.append({"file_path": f"images/frame_{i}", "transform_matrix": matrix.tolist()})  # no suffix: tried
    frames[0]["file_path"] += ".png"
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 50.0, "w": 64, "h": 48, "frames": frames}))
    cameras = load_cameras(tmp_path)
    assert [c.name for c in cameras] == ["frame_0", "frame_1"]
    assert [c.image_path.name for c in cameras] == ["000000000000.png", "000000000001.png"]  # the file itself, resolved


def test_a_frames_own_camera_angle_x_wins_over_the_files_shared_fl_x(tmp_path):
    """Round 39: per-frame intrinsics override the file's, but a shared fl_x was taken before a frame's own
    camera_angle_x (a 7 % wrong focal length, silently)."""
    root = _transforms_dataset(tmp_path, fl_x=50.0, frame={"camera_angle_x": 1.2})
    (camera,) = load_cameras(root)
    assert camera.fx == pytest.approx(32.0 / np.tan(0.6), rel=1e-12)
    (shared,) = load_cameras(_transforms_dataset(tmp_path / "shared", fl_x=50.0))
    assert shared.fx == 50.0
    # the frame's own fl_y beside its camera_angle_x is kept (the review of round 39 found it dropped with the file's)
    (own,) = load_cameras(_transforms_dataset(tmp_path / "own_fy", fl_x=50.0, fl_y=45.0, frame={"camera_angle_x": 1.2, "fl_y": 40.0}))
    assert own.fx == pytest.approx(32.0 / np.tan(0.6), rel=1e-12) and own.fy == 40.0


@pytest.mark.parametrize("frame, want", [({"fl_x": 100.0}, (100.0, 100.0)), ({"fl_y": 80.0}, (80.0, 80.0)),
                                         ({"fl_x": 100.0, "fl_y": 90.0}, (100.0, 90.0)),
                                         ({"camera_angle_y": 2 * np.arctan(0.5)}, (48.0, 48.0))])
def test_a_frames_own_focal_length_on_one_axis_sets_both_as_instant_ngp_reads_it(tmp_path, frame, want):
    """Round 69b F3: a frame's own fl_x beside the file's shared fl_x = fl_y = 50 gave (100, 50), a 2:1 camera no
    trainer used (instant-ngp: (100, 100), its read_focal_length sets both axes from one; nerfstudio: the shared (50, 50)).
    A y focal length alone, at the file's level or a frame's, sets both too."""
    (camera,) = load_cameras(_transforms_dataset(tmp_path / "frame", fl_x=50.0, fl_y=50.0, frame=frame))
    assert (camera.fx, camera.fy) == pytest.approx(want, rel=1e-12)
    (alone,) = load_cameras(_transforms_dataset(tmp_path / "file", **frame))
    assert (alone.fx, alone.fy) == pytest.approx(want, rel=1e-12)
    (nerfstudio,) = load_cameras(_transforms_dataset(tmp_path / "ns", fl_x=50.0, fl_y=50.0, applied_transform=np.eye(4)[:3].tolist(),
                                                     frame=frame))
    assert (nerfstudio.fx, nerfstudio.fy) == (50.0, 50.0)  # nerfstudio's shared values win


def _focal_of_degrees(size: int, degrees: float) -> float:
    return 0.5 * size / np.tan(0.5 * np.radians(degrees))


@pytest.mark.parametrize("file, frame, want", [
    ({"fl_x": 50.0, "camera_angle_y": 2 * np.arctan(0.5)}, {}, (50.0, 48.0)),  # each axis its own (fy was fl_x)
    ({}, {"fl_x": 51.0, "camera_angle_y": 2 * np.arctan(0.5)}, (51.0, 48.0)),
    ({"fl_y": 40.0, "camera_angle_x": 2 * np.arctan(0.5), "camera_angle_y": 1.0}, {}, (64.0, 40.0)),  # fl_y before camera_angle_y
    ({"fl_x": 50.0, "fl_y": 50.0}, {"x_fov": 60.0}, (_focal_of_degrees(64, 60.0),) * 2),  # a frame's x_fov is its focal length
    ({"camera_angle_x": 1.0, "x_fov": 60.0}, {}, (_focal_of_degrees(64, 60.0),) * 2),  # x_fov before camera_angle_x
    ({"x_fov": 60.0, "y_fov": 50.0}, {}, (_focal_of_degrees(64, 60.0), _focal_of_degrees(48, 50.0))),
    ({"y_fov": 50.0}, {}, (_focal_of_degrees(48, 50.0),) * 2),
])
def test_focal_lengths_are_read_per_axis_as_instant_ngp_reads_them(tmp_path, file, frame, want):
    """Round 71a F1, F2: instant-ngp's read_focal_length takes each axis from the first of x_fov (degrees), fl_x and
    camera_angle_x (y_fov, fl_y, camera_angle_y), an axis with none the other's; drsplat took fy = fl_x beside a
    camera_angle_y, camera_angle_y before fl_y, and never read x_fov or y_fov (a frame's x_fov kept the file's fl_x)."""
    (camera,) = load_cameras(_transforms_dataset(tmp_path, **file, frame=frame))
    assert (camera.fx, camera.fy) == pytest.approx(want, rel=1e-9)


def test_a_field_of_view_in_degrees_is_checked_in_degrees(tmp_path):
    """x_fov outside (0, 180) degrees is refused in its own unit, naming it."""
    with pytest.raises(InputError, match=r"field 'x_fov': has a field of view of 200 degrees in frame 0; it must lie in \(0, 180\)"):
        load_cameras(_transforms_dataset(tmp_path, x_fov=200.0))


@pytest.mark.parametrize("lens, shown", [({"is_fisheye": True, "k1": 0.05}, "an OpenCV fisheye lens"),
                                         ({"is_fisheye": True, "p1": 0.01}, "an OpenCV fisheye lens"),
                                         ({"latlong": False}, "a lat-long panorama"), ({"orthographic": 0}, "an orthographic camera"),
                                         ({"is_fisheye": True, "k1": 0, "k2": 0, "k3": 0, "k4": 0.01}, "an OpenCV fisheye lens"),
                                         ({"latlong": True}, "a lat-long panorama"), ({"equirectangular": True}, "an equirectangular panorama"),
                                         ({"ftheta_p0": 0.0, "ftheta_p1": 0.01}, "an f-theta lens")])
@pytest.mark.parametrize("level", ["file", "frame"])
def test_instant_ngp_s_other_lenses_are_refused_naming_the_lens(tmp_path, lens, shown, level):
    """Round 69b F1: instant-ngp's `is_fisheye` (colmap2nerf.py writes it for COLMAP's fisheye cameras, with k1, k2) was
    ignored, and its k1 read as OpenCV's radial-tangential coefficient: images resampled with the wrong lens, silently.
    Its f-theta, lat-long and equirectangular lenses were read as pinholes. Each is refused, naming its field."""
    root = _transforms_dataset(tmp_path, fl_x=50.0, **(lens if level == "file" else {"frame": lens}))
    field = next(iter(lens)) if "is_fisheye" not in lens else "is_fisheye"
    with pytest.raises(InputError, match=rf"field '{field}': describes {shown}( \(is_fisheye with k1\.\.k4, p1 or p2\))? in frame 0, which no pinhole"):
        load_cameras(root)


@pytest.mark.parametrize("file, frame, refused", [
    ({"is_fisheye": True, "k1": 0.1}, {"is_fisheye": False}, "is_fisheye"),  # the frame sets no coefficient: the file's fisheye stays
    ({"is_fisheye": True, "k1": 0.1}, {"k1": 0.0}, "is_fisheye"),  # a fisheye of zero coefficients is still one
    ({"k1": 0.1}, {"is_fisheye": True}, None),  # the frame's flag without coefficients of its own: the file's OpenCV lens
    ({"is_fisheye": True, "k1": 0.1}, {"k1": 0.05, "is_fisheye": False}, None),  # the frame's own OpenCV lens
    ({"k1": 0.1, "is_fisheye": "true"}, {}, "is_fisheye"),  # not a JSON boolean
])
def test_the_lens_is_decided_object_by_object_as_instant_ngp_reads_it(tmp_path, file, frame, refused):
    """Round 72a F1, F5: the lens was decided on the file's keys and the frame's merged, so a frame's `is_fisheye: false`
    read the file's fisheye k1 as OpenCV's, a frame's `is_fisheye: true` refused the file's OpenCV lens, and a string
    "true" passed. instant-ngp's read_lens reads the file's object, then the frame's, each changing the lens only by
    what it holds."""
    root = _transforms_dataset(tmp_path, fl_x=50.0, **file, frame=frame)
    if refused is None:
        (camera,) = load_cameras(root)
        assert camera.distortion is not None
    else:
        with pytest.raises(InputError, match=f"field '{refused}'"):
            load_cameras(root)


def test_is_fisheye_without_coefficients_is_a_pinhole(tmp_path):
    """instant-ngp reads `is_fisheye` with k1..k4 all 0 as a pinhole (its lens mode stays Perspective): so does drsplat."""
    (camera,) = load_cameras(_transforms_dataset(tmp_path, fl_x=50.0, is_fisheye=True, k1=0, k2=0, k3=0, k4=0))
    assert camera.fx == 50.0 and camera.distortion is None


def test_scannet_frames_without_their_colour_image_are_left_out_where_images_are_needed(tmp_path, caplog):
    """Round 69b F2: color/ exported at a frame skip while pose/ holds every frame: the frames without a colour image were
    kept (image_path None) where images are needed, and `drsplat features` then refused with "2 of its 3 cameras have an
    image ... color, which does not exist" (they have none; it exists). Now they are skipped and counted, as every other
    reader's, the image size read from the first colour image there is; `register` (no images needed) keeps them."""
    from PIL import Image

    from drsplat.features.extract import refuse_cameras_without_images

    root = _scannet_scene(tmp_path / "s", np.eye(4))
    (root / "color" / "0.jpg").unlink()
    Image.new("RGB", (64, 48)).save(root / "color" / "1.jpg")
    for i in (1, 2):
        np.savetxt(root / "pose" / f"{i}.txt", np.eye(4))
    with caplog.at_level(logging.WARNING):
        cameras = load_cameras(root)
    assert [c.name for c in cameras] == ["1"] and (cameras[0].width, cameras[0].height) == (64, 48)
    assert "2 frames skipped because their images are missing or not a regular file (0.jpg, 2.jpg; 1 camera kept)" in caplog.text
    every = load_cameras(root, require_images=False)
    assert [(c.name, c.image_path is None) for c in every] == [("0", True), ("1", False), ("2", True)]
    with pytest.raises(InputError, match=r"2 of its 3 cameras have no image \(e\.g\. '0'\): the images are looked for in .*color, which holds "
                                         r"none of their names$"):
        refuse_cameras_without_images(root, every)


def test_a_colmap_camera_id_past_2_31_in_cameras_bin_is_read_as_images_bin_refers_to_it(tmp_path):
    """Round 39: COLMAP's camera_t is uint32; cameras.bin's id was read as int32, so a model whose camera id is
    3,000,000,000 (pycolmap writes such models) was refused with an error blaming images.bin."""
    import struct

    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    cam_id = 3_000_000_000
    (sparse / "cameras.bin").write_bytes(struct.pack("<QIiQQ4d", 1, cam_id, 1, 64, 48, 50.0, 50.0, 32.0, 24.0))
    (sparse / "images.bin").write_bytes(struct.pack("<QI7dI", 1, 1, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0, cam_id) + b"a.png\0"
                                        + struct.pack("<Q", 0))
    (camera,) = load_cameras(tmp_path, require_images=False)
    assert (camera.name, camera.width, camera.fx, camera.cx) == ("a", 64, 50.0, 32.0)


def test_a_transforms_json_giving_w_without_h_must_agree_with_its_image(tmp_path):
    """Round 39: a frame giving w but no h took both from the image, silently ignoring a w that named another size."""
    root = _transforms_dataset(tmp_path / "bad", fl_x=50.0, frame={"w": 128})
    record = json.loads((root / "transforms.json").read_text())
    del record["frames"][0]["h"]
    (root / "transforms.json").write_text(json.dumps(record))
    with pytest.raises(InputError, match=r"field 'w': gives w = 128 in frame 0 but no h, and its image v.png is 64x48"):
        load_cameras(root)
    record["frames"][0]["w"] = 64
    (root / "transforms.json").write_text(json.dumps(record))
    (camera,) = load_cameras(root)
    assert (camera.width, camera.height) == (64, 48)


def test_the_corner_shift_of_a_lens_is_where_its_distortion_moves_the_farthest_corner():
    """`lens_corner_shift`, which the warning about distorted views and another tool's features quotes: against the
    distortion of the corner computed by hand."""
    from drsplat.cameras import lens_corner_shift

    cam = Camera(R=np.eye(3), t=np.zeros(3), fx=500.0, fy=400.0, cx=300.0, cy=260.0, width=640, height=480, name="v",
                 distortion=np.array([-0.1, 0.02, 0.001, -0.002]))
    x, y = 340.0 / 500.0, -260.0 / 400.0  # the farthest corner, (640, 0)
    r2 = x * x + y * y
    radial = 1 - 0.1 * r2 + 0.02 * r2 * r2
    xd = x * radial + 2 * 0.001 * x * y - 0.002 * (r2 + 2 * x * x)
    yd = y * radial + 0.001 * (r2 + 2 * y * y) + 2 * -0.002 * x * y
    assert lens_corner_shift(cam) == pytest.approx(np.hypot((xd - x) * 500.0, (yd - y) * 400.0), rel=1e-12)
    assert lens_corner_shift(dataclasses.replace(cam, distortion=None)) == 0.0


@pytest.mark.parametrize("entry, row, column, words", [
    ("nan", 0, 0, "focal length K[0][0]=nan"),
    ("inf", 1, 1, "focal length K[1][1]=inf"),
    ("nan", 0, 2, "a non-finite principal point"),
    ("1e-320", 0, 0, "K[0][0]=9.99989e-321 for an image 64 pixels"),
])
def test_scannet_intrinsics_that_are_no_camera_name_the_intrinsic_file(tmp_path, entry, row, column, words):
    """Round 46: a NaN, infinite or subnormal entry of ScanNet's intrinsic/intrinsic_color.txt was refused as field 'fx' of
    pose/0.txt, a file that holds no intrinsics. Now the error names the intrinsic file and the matrix entry."""
    from drsplat.cameras import load_scannet_cameras

    scene = _scannet_scene(tmp_path / "scene0000_00", np.eye(4))
    K = np.loadtxt(scene / "intrinsic" / "intrinsic_color.txt")
    K[row, column] = float(entry)
    np.savetxt(scene / "intrinsic" / "intrinsic_color.txt", K)
    with pytest.raises(InputError) as info:
        load_scannet_cameras(scene)
    assert info.value.path == scene / "intrinsic" / "intrinsic_color.txt" and info.value.field == f"K[{row}][{column}]"
    assert words in str(info.value)


@pytest.mark.skipif(not hasattr(__import__("os"), "mkfifo"), reason="needs FIFOs")
def test_the_exif_orientation_of_a_pipe_a_corrupt_block_or_no_file_is_upright_without_a_word(tmp_path):
    """`exif_orientation` reads a header for registration's warning about turned photos: a named pipe
    given as a photo blocked that open for ever (round 51), and a corrupt EXIF block printed Pillow's
    warnings; each is read as upright, silently. A tagged file gives its tag."""
    import os
    import threading

    from PIL import Image

    from drsplat.cameras import EXIF_ORIENTATION, exif_orientation

    image = Image.fromarray(np.zeros((8, 8, 3), np.uint8))
    exif = image.getexif()
    exif[EXIF_ORIENTATION] = 3
    image.save(tmp_path / "turned.jpg", exif=exif)
    data = bytearray((tmp_path / "turned.jpg").read_bytes())
    at = data.find(b"Exif")
    data[at + 20:at + 26] = b"\xff" * 6  # the orientation entry's count and offset point past the file
    (tmp_path / "corrupt.jpg").write_bytes(bytes(data))
    os.mkfifo(tmp_path / "pipe.jpg")
    (tmp_path / "folder.jpg").mkdir()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = {name: exif_orientation(tmp_path / name) for name in ("turned.jpg", "corrupt.jpg", "folder.jpg", "missing.jpg")}
    assert got == {"turned.jpg": 3, "corrupt.jpg": 1, "folder.jpg": 1, "missing.jpg": 1}
    assert not caught, [str(w.message) for w in caught]
    assert exif_orientation(None) == 1
    piped = []
    reader = threading.Thread(target=lambda: piped.append(exif_orientation(tmp_path / "pipe.jpg")), daemon=True)
    reader.start()
    reader.join(30)
    assert not reader.is_alive(), "the open of a named pipe blocked"
    assert piped == [1]


def _views_dataset(root, sizes, intrinsics, image_size=None, give_size=True):
    """A transforms.json of three views looking at the origin, frame k of size `sizes[k]` (w, h) with (fl, cx, cy)
    `intrinsics[k]`; images of `image_size` (default each frame's size); w/h written only when `give_size`."""
    from PIL import Image

    from drsplat.cameras import look_at_camera, w2c_opencv_to_c2w_opengl

    (root / "images").mkdir(parents=True)
    frames = []
    for k, ((w, h), (fl, cx, cy)) in enumerate(zip(sizes, intrinsics)):
        cam = look_at_camera([np.cos(k), 0.3, np.sin(k) * 3.0 + 3.0], [0, 0, 0], w, h)
        Image.new("RGB", image_size or (w, h)).save(root / "images" / f"v{k}.png")
        frame = {"file_path": f"images/v{k}.png", "transform_matrix": w2c_opencv_to_c2w_opengl(cam.R, cam.t).tolist(), "fl_x": fl,
                 "fl_y": fl, "cx": cx, "cy": cy}
        frames.append({**frame, "w": w, "h": h} if give_size else frame)
    (root / "transforms.json").write_text(json.dumps({"frames": frames}))
    return root


def _warnings(caplog, words: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if words in r.getMessage()]


def test_intrinsics_made_for_twice_or_half_the_image_size_are_one_warning_naming_the_file(tmp_path, caplog):
    """Round 51 (F1): transforms.json without w/h beside half-size images (fl/cx of the full size), or w/h of the full
    size with fl/cx/cy halved, put every principal point at the images' corner or a quarter of the way in; registered
    without a word at seg mIoU 0.13 for 0.96. Now one warning naming the file, the field, the pattern and the size the
    intrinsics fit; a COLMAP model whose WIDTH/HEIGHT were halved without its PARAMS is named by its cameras.txt."""
    full = [(64, 48)] * 3
    downscaled = _views_dataset(tmp_path / "a", full, [(50.0, 32.0, 24.0)] * 3, image_size=(32, 24), give_size=False)
    halved = _views_dataset(tmp_path / "b", full, [(25.0, 16.0, 12.0)] * 3)
    with caplog.at_level(logging.INFO):
        assert [(c.width, c.cx) for c in load_cameras(downscaled)] == [(32, 32.0)] * 3  # warned, not rescaled
        load_cameras(halved)
    said = _warnings(caplog, "principal point")
    assert len(said) == 2, said
    assert said[0] == (f"{downscaled / 'transforms.json'}: field 'cx': the principal point of all 3 frames is at (32, 24), the corner of "
                       "their 32x24 images (2x the centre): intrinsics of a 64x48 image? (images/ holding downscaled copies where the file "
                       "gives no w/h, or w/h not scaled with fl_x/cx/cy); they are used as they are, which misplaces every Gaussian in every view")
    assert "the principal point of all 3 frames is at (16, 12), a quarter of the way into their 64x48 images (½x the centre): " \
           "intrinsics of a 32x24 image?" in said[1]
    caplog.clear()
    root = tmp_path / "colmap"
    _tiny_colmap(root)
    (root / "sparse" / "0" / "cameras.txt").write_text("1 PINHOLE 32 24 50 50 32 24\n")  # WIDTH HEIGHT halved, PARAMS not
    with caplog.at_level(logging.INFO):
        load_cameras(root)
    said = _warnings(caplog, "principal point")
    assert len(said) == 1 and said[0].startswith(f"{root / 'sparse' / '0' / 'cameras.txt'}: field 'PARAMS': the principal point of all 2 "
                                                 "images is at (32, 24), the corner of their 32x24 images (2x the centre)"), said
    assert not _warnings(caplog, "their cameras")  # the images fit the PARAMS, not the size: no hint to read them at theirs
    caplog.clear()  # a real calibration lies off-centre (fox: 1.35 % of the side): its half-size images are still caught (round 52)
    fox = _views_dataset(tmp_path / "fox", [(1080, 1920)] * 3, [(1600.0, 554.558, 965.268)] * 3, image_size=(540, 960), give_size=False)
    with caplog.at_level(logging.INFO):
        load_cameras(fox)
    said = _warnings(caplog, "principal point")
    assert len(said) == 1 and "(2x the centre): intrinsics of a 1080x1920 image?" in said[0], said
    # valid off-centre principal points say nothing: views all cropped to the top-left 200x150 of 256x192 (principal
    # point at 64%), each view cropped to its own box, a calibrated principal point (fox's), the quadrants of split images
    rng = np.random.default_rng(5)
    honest = {
        "centred": ([(256, 192)] * 3, [(128.0, 96.0)] * 3),
        "crop at 64%": ([(200, 150)] * 3, [(128.0, 96.0)] * 3),
        "random crops": tuple(zip(*[((256 - int(a), 192 - int(b)), (128.0 - int(c), 96.0 - int(d))) for a, b, c, d in rng.integers(0, 60, (3, 4))])),
        "calibrated": ([(1080, 1920)] * 3, [(554.558, 965.268)] * 3),
        "quadrants": ([(128, 96)] * 3, [(128.0, 96.0), (0.0, 96.0), (128.0, 0.0)]),
    }
    caplog.clear()
    for case, (sizes, points) in honest.items():
        with caplog.at_level(logging.INFO):
            load_cameras(_views_dataset(tmp_path / case, list(sizes), [(200.0, cx, cy) for cx, cy in points]))
        assert not _warnings(caplog, "principal point") and not _warnings(caplog, "their cameras"), case


def test_intrinsics_of_two_other_sizes_in_one_dataset_are_one_warning_counting_each(tmp_path, caplog):
    """Round 52 (left as found): frames holding downscaled copies at 2x and at 4x, beside full-size intrinsics, put every
    principal point at a corner or beyond, yet no one factor fitted every camera, so nothing was said."""
    from PIL import Image

    full = [(256, 192)] * 3
    mixed = _views_dataset(tmp_path / "mixed", full, [(200.0, 128.0, 96.0)] * 3, give_size=False)
    for k, size in enumerate([(128, 96), (64, 48), (128, 96)]):  # the files replaced by copies of half and a quarter the size
        Image.new("RGB", size).save(mixed / "images" / f"v{k}.png")
    with caplog.at_level(logging.INFO):
        assert [c.width for c in load_cameras(mixed)] == [128, 64, 128]  # warned, not rescaled
    said = _warnings(caplog, "principal point")
    assert said == [f"{mixed / 'transforms.json'}: field 'cx': the principal point of all 3 frames is off their image centres by factors "
                    "that differ (2 at 2x, 1 at 4x; e.g. 'v0''s (128, 96) in its 128x96, 2x the centre): intrinsics of images of other "
                    "sizes? (images/ holding downscaled copies where the file gives no w/h, or w/h not scaled with fl_x/cx/cy); they are "
                    "used as they are, which misplaces every Gaussian in every view"], said
    caplog.clear()  # one frame at its own size: the others may be crops or quadrants, so no word
    Image.new("RGB", (256, 192)).save(mixed / "images" / "v1.png")
    with caplog.at_level(logging.INFO):
        load_cameras(mixed)
    assert not _warnings(caplog, "principal point")


def test_colmap_cameras_of_half_the_images_size_say_at_which_size_they_are_read(tmp_path, caplog):
    """Round 51 (N1): COLMAP cameras of 32x24 (all of their intrinsics halved) beside 64x48 images registered at 32x24
    without a word, 3DGS without -r trains at the images' size. Now one INFO line saying so, and the flag for theirs."""
    root = tmp_path / "colmap"
    _tiny_colmap(root)
    (root / "sparse" / "0" / "cameras.txt").write_text("1 PINHOLE 32 24 25 25 16 12\n")
    with caplog.at_level(logging.INFO):
        assert {(c.width, c.height) for c in load_cameras(root)} == {(32, 24)}
    said = _warnings(caplog, "its camera")
    assert said == [f"{root / 'sparse' / '0' / 'cameras.txt'}: the first image is 2x its camera (a.png is 64x48, its camera 32x24): the views "
                    "are read at the cameras' size, as 3DGS trains with -r 2; where the images are all so, `--resolution 64` reads them at "
                    "their own size"], said
    assert not _warnings(caplog, "principal point")
    caplog.clear()
    with caplog.at_level(logging.INFO):  # the advice taken: the images' own size, and no "upscales ... no more detail" warning against it
        assert {(c.width, c.height) for c in load_cameras(root, resolution=64)} == {(64, 48)}
    assert not _warnings(caplog, "upscales"), caplog.text
    assert not _warnings(caplog, "its camera"), caplog.text  # a --resolution of the user's own: the note's advice is not repeated


def test_a_resolution_that_only_some_images_hold_warns_for_the_others(tmp_path, caplog):
    """Round 54: with one image at 2x its camera and the others at 1x, `--resolution 64` upscaled every other view 2x without
    a word: only the most-scaled view's image was asked, and it (the first) held the size. Each view's own image is asked."""
    from PIL import Image

    root = _tiny_colmap(tmp_path / "colmap", ("a.png", "b.png", "c.png"))
    (root / "sparse" / "0" / "cameras.txt").write_text("1 PINHOLE 32 24 25 25 16 12\n")
    for name in ("b.png", "c.png"):
        Image.new("RGB", (32, 24)).save(root / "images" / name)
    with caplog.at_level(logging.WARNING):
        assert {(c.width, c.height) for c in load_cameras(root, resolution=64)} == {(64, 48)}
    said = _warnings(caplog, "upscales")
    assert len(said) == 1 and "resolution 64 upscales 2 of 3 views beyond their images" in said[0], caplog.text


def test_a_colmap_dataset_without_images_but_images_2_names_the_path_it_read_and_the_way_out(tmp_path):
    """Round 51 (F4): DATASET/sparse/0 beside images_2/ and no images/ (3DGS's `-i images_2`, Mip-NeRF 360's layout)
    was told "every image file is missing: e.g. DATASET/DSC0001.JPG", a path the COLMAP reader never opens; with a file
    put there, the hint added that it "has its name but another extension" though its extension was the one named."""
    from PIL import Image

    root = _tiny_colmap(tmp_path / "garden", image_names=("DSC0001.JPG",))
    (root / "images").rename(root / "images_2")
    (root / "images_4").mkdir()
    Image.new("RGB", (64, 48)).save(root / "DSC0001.JPG")  # where the old hint pointed
    with pytest.raises(InputError) as caught:
        load_cameras(root)
    message = str(caught.value)
    assert f"every image file is missing: e.g. {root / 'images' / 'DSC0001.JPG'}; the folder {root / 'images'} does not exist; " \
           f"{root} holds images_2/, images_4/, which 3DGS reads with -i images_2: drsplat reads images/ only, so link or rename one " \
           f"to images/ (e.g. `ln -s images_2 {root / 'images'}`), with --resolution 2" in message, message
    assert "another extension" not in message


def test_a_missing_image_that_is_a_folder_of_its_name_is_said_to_be_no_regular_file(tmp_path):
    """The companion of the round 51 hint: the path the reader opened is there, but as a folder; the hint said only
    "e.g. DATASET/images/a.png", as if nothing were there."""
    root = _tiny_colmap(tmp_path / "d", image_names=("a.png",))
    (root / "images" / "a.png").unlink()
    (root / "images" / "a.png").mkdir()
    with pytest.raises(InputError, match=r"e\.g\. .*images/a\.png; it is there but is not a regular file"):
        load_cameras(root)


def test_the_listing_shortcut_finds_what_the_stat_calls_find(tmp_path):
    """Round 54: a transforms.json of 300,000 absent images took 2:48, a dozen stat calls and a resolve a frame.
    `DatasetPaths.may_hold` lists each folder once and answers an absent image from the listing; every name, present,
    absent, suffixless, in another case, through a link, dangling, in a missing or unlistable folder, finds what the
    stat calls alone find (`stat_named`, the reference)."""
    import os

    from drsplat.cameras import DatasetPaths

    root = tmp_path / "data"
    (root / "images" / "sub").mkdir(parents=True)
    for name in ("a.png", "B.JPG", "c", "frame.001.png", "sub/d.jpeg", "e.PNG", "caf\u0065\u0301.png"):  # the last decomposed, as macOS stores it
        (root / "images" / name).write_bytes(b"x")
    (root / "images" / "link.png").symlink_to(root / "images" / "a.png")
    (root / "images" / "dangling.png").symlink_to(root / "images" / "nowhere.png")
    (root / "images" / "folder.png").mkdir()
    locked = root / "images" / "locked"
    locked.mkdir()
    (locked / "f.png").write_bytes(b"x")

    names = ["a.png", "a", "A.png", "B", "B.JPG", "b.jpg", "c", "missing", "missing.png", "sub/d", "sub/d.jpeg", "nosub/x.png",
             "frame.001", "link", "link.png", "dangling.png", "folder.png", "folder", "e", "a.png/x", "../images/a", "locked/f",
             str(root / "images" / "a"), "sub\\d.jpeg", "caf\u00e9", "caf\u0065\u0301", "CAF\u00c9.png"]
    os.chmod(locked, 0o311)  # listable by no one but root; its files still reachable
    try:
        paths, plain = DatasetPaths(root / "images", root / "transforms.json"), DatasetPaths(root / "images", root / "transforms.json")
        for name in names:
            assert paths.find_named(name) == plain.stat_named(name), name
        assert paths.listings[root / "images"] is not None and paths.listings[root / "images" / "nosub"] == frozenset()
        assert paths.find_named("a")[0] == (root / "images" / "a.png").resolve() and paths.find_named("missing") is None
    finally:
        os.chmod(locked, 0o755)


def test_a_windows_backslash_image_path_is_named_as_the_cause(tmp_path):
    """Round 54: a transforms.json written on Windows (`images\\sub\\a.png`) lost every frame with only "missing"; on
    POSIX the backslashes are part of one file name. The error now says so and names the file that is there."""
    from PIL import Image

    (tmp_path / "images" / "sub").mkdir(parents=True)
    Image.new("RGB", (64, 48)).save(tmp_path / "images" / "sub" / "a.png")
    c2w = np.eye(4)
    c2w[2, 3] = 4.0
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": [
        {"file_path": "images\\sub\\a.png", "transform_matrix": c2w.tolist()}]}))
    with pytest.raises(InputError, match=r"the name holds Windows backslashes \('\\'\), which are no folder separators here: "
                                         r".*images/sub/a.png is there \(write '/' in transforms.json\)"):
        load_cameras(tmp_path)


def test_a_colmap_models_windows_names_blanks_and_files_are_named_as_the_cause(tmp_path):
    """Round 95b F4-F6: a COLMAP model's backslash names were to be rewritten "in 0" (the model's folder); a file_path
    with a blank at its end got no hint (the blank invisible at the line's end); --source naming a model's file was
    "not a dataset folder, transforms.json or cameras.json" without a word of what to give."""
    windows = _tiny_colmap(tmp_path / "win", image_names=("sub/a.png",))
    model = windows / "sparse" / "0" / "images.txt"
    model.write_text(model.read_text().replace("sub/a.png", "sub\\a.png"))
    with pytest.raises(InputError, match=r"images/sub/a.png is there \(write '/' in images.txt\)"):
        load_cameras(windows)
    blank = _tiny_colmap(tmp_path / "blank", image_names=("a.png",))
    c2w = np.eye(4)
    c2w[2, 3] = 4.0
    (blank / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": [{"file_path": "images/a.png ", "transform_matrix": c2w.tolist()}]}))
    with pytest.raises(InputError, match=r'the name "images/a.png " has blanks at its ends, and images/a.png is there: remove them'):
        load_cameras(blank / "transforms.json")
    (blank / "transforms.json").unlink()  # round 97a F6: a name without its suffix, as 3DGS's cameras.json gives it
    (blank / "cameras.json").write_text(json.dumps([{"id": 0, "img_name": "a ", "width": 64, "height": 48, "position": [0, 0, -4],
                                                     "rotation": np.eye(3).tolist(), "fx": 50.0, "fy": 50.0}]))
    with pytest.raises(InputError, match=r'the name "a " has blanks at its ends'):
        load_cameras(blank / "cameras.json")
    with pytest.raises(InputError, match=r"it is a file of a COLMAP model: give the dataset folder \(the one holding images/ and sparse/\), or "):
        load_cameras(windows / "sparse" / "0" / "cameras.txt")
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "images.txt").write_text("my holiday photos\n")  # round 96a F10: no model beside it
    with pytest.raises(InputError) as exc:
        load_cameras(tmp_path / "notes" / "images.txt")
    assert "COLMAP" not in str(exc.value)


def test_a_nerfstudio_run_oriented_by_pca_is_warned_about(tmp_path, caplog):
    """Round 55b: nerfstudio's --orientation-method pca may turn its poses half round about x when its up-flip fires,
    and the saved dataparser transform misses that turn in every release (which one trained a run cannot be read). A
    run whose config.yml says pca, or whose transforms.json's orientation_override does, gets one warning; another
    override replaces the config's method, as in nerfstudio."""
    from drsplat.synthetic import write_dataset

    data = write_dataset(tmp_path / "room", "tiny", 0, show_progress=False)
    (data / "dataparser_transforms.json").write_text(json.dumps({"transform": np.eye(4)[:3].tolist(), "scale": 1.0}))
    meta = json.loads((data / "transforms.json").read_text())

    def warned(config: str | None, override: str | None) -> bool:
        caplog.clear()
        if config is None:
            (data / "config.yml").unlink(missing_ok=True)
        else:
            (data / "config.yml").write_text(config)
        (data / "transforms.json").write_text(json.dumps({**meta, "orientation_override": override} if override else meta))
        with caplog.at_level(logging.WARNING):
            load_cameras(data)
        return "nerfstudio oriented this run by PCA" in caplog.text

    config = "!!python/object:nerfstudio.engine.trainer.TrainerConfig\npipeline:\n  datamanager:\n    dataparser:\n      orientation_method: {}\n"
    assert warned(config.format("pca"), None) and warned(None, "pca") and warned(config.format("up"), "pca")
    assert not warned(config.format("up"), None) and not warned(None, None) and not warned(config.format("pca"), "none")


def test_frames_intrinsics_unlike_the_shared_ones_follow_nerfstudio_in_a_nerfstudio_dataset(tmp_path, caplog):
    """Round 56b: a transforms.json with shared cx, cy and each frame's own took the frames' (instant-ngp's rule), but
    nerfstudio never reads a frame's own when the file has shared ones: a splatfacto run of such a file was registered
    with every principal point 5 px, -3 px off, without a word. A nerfstudio dataset (its dataparser_transforms.json
    beside the file) now takes the shared values; any other keeps the frames'; both say the disagreement once."""
    from drsplat.synthetic import write_dataset

    data = write_dataset(tmp_path / "room", "tiny", 0, show_progress=False)
    meta = json.loads((data / "transforms.json").read_text())
    truth = load_cameras(data)
    frame = meta["frames"][0]
    shared = {key: frame[key] for key in ("fl_x", "fl_y", "cx", "cy", "w", "h") if key in frame}
    assert {"cx", "cy"} <= set(shared), sorted(frame)
    for f in meta["frames"]:
        f["cx"], f["cy"] = f["cx"] + 5, f["cy"] - 3
    (data / "transforms.json").write_text(json.dumps({**meta, **shared}))
    for nerfstudio in (False, True):
        if nerfstudio:
            (data / "dataparser_transforms.json").write_text(json.dumps({"transform": np.eye(4)[:3].tolist(), "scale": 1.0}))
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            got = load_cameras(data)
        offset = (0.0, 0.0) if nerfstudio else (5.0, -3.0)
        assert [(c.cx - t.cx, c.cy - t.cy) for c, t in zip(got, truth)] == [offset] * len(truth)
        said = [r.getMessage() for r in caplog.records if "intrinsics of their own beside the file's shared ones" in r.getMessage()]
        assert len(said) == 1 and f"cx ({len(truth)} frames), cy ({len(truth)} frames)" in said[0], caplog.text
        assert ("so the shared ones are used" in said[0]) == nerfstudio


def test_an_image_over_pillows_pixel_limit_is_sized_without_its_raw_warning(tmp_path, monkeypatch, recwarn):
    """Round 56b: reading the size of a 108-megapixel photo (a transforms.json without w, h) printed Pillow's raw
    DecompressionBombWarning; one past twice the limit refused the dataset ("not a readable image"), though only its
    size is needed. The size is read from the header now, quietly (decoding the pixels still logs the warning, naming
    the file). Pillow's limit is lowered for the test instead of writing a 100-megapixel file."""
    from PIL import Image

    from drsplat.cameras import _image_size

    Image.new("RGB", (40, 30)).save(tmp_path / "big.png")
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)  # 1,200 pixels: over the limit, under twice it
    assert _image_size(tmp_path / "big.png") == (40, 30)
    assert not [w for w in recwarn if issubclass(w.category, Image.DecompressionBombWarning)]
    # past twice the limit Pillow's open refuses the file; its header is read all the same (round 56c: it refused the dataset)
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 500)
    assert _image_size(tmp_path / "big.png") == (40, 30)
    Image.new("RGB", (40, 30)).save(tmp_path / "big.jpg")
    assert _image_size(tmp_path / "big.jpg") == (40, 30)
    (tmp_path / "big.jpg").write_bytes((tmp_path / "big.jpg").read_bytes()[:2])
    with pytest.raises(InputError, match=r"big.jpg: is not a readable image"):
        _image_size(tmp_path / "big.jpg")
    # round 56e: WebP's opener checks the limit itself: a raw DecompressionBombError traceback; one InputError now
    Image.new("RGB", (40, 30)).save(tmp_path / "big.webp")
    with pytest.raises(InputError, match=r"big.webp: is not a readable image: Image size \(1200 pixels\) exceeds"):
        _image_size(tmp_path / "big.webp")


def test_a_nerfstudio_dataset_takes_all_its_distortion_and_its_focal_length_from_the_top_level(tmp_path, caplog):
    """Round 56c: nerfstudio reads every distortion coefficient from a transforms.json's top level once one is there (0 where
    absent), and never a frame's camera_angle_x; drsplat kept a frame's own p1 beside a shared k1, and let a frame's
    camera_angle_x replace the shared fl_x (fx 117.15 instead of 106.51)."""
    from drsplat.synthetic import write_dataset

    data = write_dataset(tmp_path / "room", "tiny", 0, show_progress=False)
    meta = json.loads((data / "transforms.json").read_text())
    truth = load_cameras(data)
    fl_x = meta["frames"][0]["fl_x"]
    for f in meta["frames"]:
        f["p1"] = 0.001
        f["camera_angle_x"] = 1.0
        del f["fl_x"]
        f.pop("fl_y", None)
    (data / "transforms.json").write_text(json.dumps({**meta, "fl_x": fl_x, "k1": 0.0}))
    (data / "dataparser_transforms.json").write_text(json.dumps({"transform": np.eye(4)[:3].tolist(), "scale": 1.0}))
    with caplog.at_level(logging.WARNING):
        got = load_cameras(data)
    assert [(c.fx, c.fy, c.distortion) for c in got] == [(fl_x, fl_x, None)] * len(truth)  # not 2·atan's focal of camera_angle_x 1.0
    assert f"p1 ({len(truth)} frames)" in caplog.text and "so the shared ones are used" in caplog.text, caplog.text
    assert f"camera_angle_x ({len(truth)} frames)" in caplog.text, "round 56e: the frames' camera_angle_x was overruled silently"
    # round 56e: nerfstudio's `distortion_params` list [k1, k2, k3, k4, p1, p2] was ignored everywhere
    meta = json.loads((data / "transforms.json").read_text())
    meta.pop("k1")
    meta["distortion_params"] = [0.01, 0.0, 0.0, 0.0, 0.002, 0.0]
    (data / "transforms.json").write_text(json.dumps(meta))
    got = load_cameras(data)
    assert all(np.array_equal(c.distortion, [0.01, 0.0, 0.002, 0.0]) for c in got)
    # a key beside the list: nerfstudio reads the list alone (drsplat took the key); one warning names it
    caplog.clear()
    meta["k1"] = 0.03
    meta["frames"][0]["distortion_params"], meta["frames"][0]["p2"] = [0.01, 0.0, 0.0, 0.0, 0.002, 0.0], 0.004
    (data / "transforms.json").write_text(json.dumps(meta))
    with caplog.at_level(logging.WARNING):
        got = load_cameras(data)
    assert all(np.array_equal(c.distortion, [0.01, 0.0, 0.002, 0.0]) for c in got)
    assert "disagree (k1 in 1 place, p1 in 1 place, p2 in 1 place): the list's are used" in caplog.text, caplog.text
    meta.pop("k1")
    meta["frames"][0].pop("distortion_params")
    meta["frames"][0].pop("p2")
    # round 57a: a top-level k4 alone was merged into every frame and refused as "k3/k4 distortion in frame 0" (field
    # 'k3'); nerfstudio reads each frame's distortion then and never that k4
    dropped = {k: meta.pop(k) for k in ("distortion_params",)}
    for f in meta["frames"]:
        f.pop("p1")
    (data / "transforms.json").write_text(json.dumps({**meta, "k4": 0.0001}))
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert all(c.distortion is None for c in load_cameras(data))
    assert "gives k4 at its top level without k1, k2, k3, p1 or p2 there" in caplog.text, caplog.text
    meta["frames"][1]["k4"] = 0.002
    (data / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match=r"field 'k4': has k4 distortion in frame 1, which drsplat does not undistort"):
        load_cameras(data)
    meta["frames"][1].pop("k4")
    meta.update(dropped)
    meta["distortion_params"] = [0.01, 0.0]
    (data / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match=r"field 'distortion_params': the file's distortion_params is not a list of 6 numbers"):
        load_cameras(data)
    meta["distortion_params"] = ["a", 0, 0, 0, 0, 0]  # the read-through: it was named 'k1' in frame 1, a key the file does not have
    (data / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match=r"field 'distortion_params': has a non-numeric value \(the file's distortion_params, its k1\)"):
        load_cameras(data)


def test_a_dataset_that_does_not_exist_is_named_as_a_dataset(tmp_path):
    """Round 54 left path errors that named the path and not what it was for: `--source /nope` said "/nope: does not
    exist"; it now says a dataset was expected there."""
    with pytest.raises(InputError, match=re.escape(f"{tmp_path / 'nope'}: dataset (a folder or its camera file) does not exist")):
        load_cameras(tmp_path / "nope")


def test_colmap_text_numbers_are_read_as_colmap_reads_them_and_a_lone_cr_ends_a_line(tmp_path):
    """Round 57b: the text readers took '6_4' as 64, Arabic-Indic and full-width digits as numbers (Python's int and
    float read them; COLMAP and pycolmap refuse them), and a points3D id '1_0' became 10, blamed as a repeat on
    another line. Each is now an error naming its line. images.txt with classic-Mac line endings (a lone CR) read 0
    images while cameras.txt of the same model was read: both split lines alike now."""
    from PIL import Image

    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (tmp_path / "images").mkdir()
    Image.new("RGB", (64, 48)).save(tmp_path / "images" / "a.png")
    cameras, images = "1 SIMPLE_PINHOLE 64 48 50 32 24\n", "1 1 0 0 0 0.5 0 2 1 a.png\n\n"
    (sparse / "cameras.txt").write_text(cameras)
    (sparse / "images.txt").write_text(images)
    assert [c.fx for c in load_cameras(tmp_path)] == [50.0]
    for bad in ("6_4", "\u0666\u0664", "\uff16\uff14"):
        (sparse / "cameras.txt").write_text(cameras.replace("64", bad))
        with pytest.raises(InputError, match=r"cameras.txt: has a malformed camera line \(data line 1\)"):
            load_cameras(tmp_path)
    (sparse / "cameras.txt").write_text(cameras)
    (sparse / "images.txt").write_text(images.replace("0.5", "0.5_1"))
    with pytest.raises(InputError, match=r"images.txt: field 'IMAGE_ID': line 1 is not an image line"):
        load_cameras(tmp_path)
    (sparse / "images.txt").write_text(images.replace("\n", "\r"))
    assert [c.name for c in load_cameras(tmp_path)] == ["a"]
    (sparse / "images.txt").write_text(images)
    (sparse / "points3D.txt").write_text("1_0 0 0 1 0 0 0 0\n10 0 0 2 0 0 0 0\n")
    with pytest.raises(InputError, match=r"points3D.txt: has a malformed point line \(data line 1\)"):
        read_colmap_model(sparse)


def test_a_colmap_model_in_another_numbered_folder_reads_the_datasets_images(tmp_path, monkeypatch):
    """Round 57b: COLMAP's mapper writes sparse/0, sparse/1, ...; `--source DATASET/sparse/1` (and '.' or '0' given from
    inside the model) looked for the images inside the model folder ("every image file is missing ... sparse/1/images"),
    and a dataset with only sparse/1 was "no COLMAP model (sparse/0)" without naming it."""
    import shutil

    root = _tiny_colmap(tmp_path / "src", ("a.png", "b.png"))
    want = [c.image_path.resolve() for c in load_cameras(root)]
    shutil.move(root / "sparse" / "0", root / "sparse" / "1")
    with pytest.raises(InputError, match=r"has no COLMAP model \(sparse/0\).*; it has the COLMAP model sparse/1: give it as --source"):
        load_cameras(root)
    assert [c.image_path.resolve() for c in load_cameras(root / "sparse" / "1")] == want
    monkeypatch.chdir(root / "sparse" / "1")
    assert [c.image_path.resolve() for c in load_cameras(".")] == want
    monkeypatch.chdir(root / "sparse")
    assert [c.image_path.resolve() for c in load_cameras("1")] == want


def test_colmaps_rig_layout_names_each_view_by_its_cameras_folder(tmp_path):
    """Round 57b: COLMAP asks a rig's images to share one file name per frame across the cameras' folders
    (images/rig1/camera1/image0001.png beside images/rig1/camera2/image0001.png), and gsplat and 3DGS train on it;
    drsplat refused the dataset (two images of stem 'image0001'). The views are now named by their folder too, in
    COLMAP models and transforms.json alike; one stem twice in one folder is still refused."""
    import json

    from drsplat.cameras import look_at_camera

    names = ("rig1/camera1/image0001.png", "rig1/camera2/image0001.png", "rig1/camera1/image0002.png", "rig1/camera2/image0002.png")
    root = _tiny_colmap(tmp_path / "rig", names)
    got = load_cameras(root)
    assert [c.name for c in got] == ["camera1_image0001", "camera1_image0002", "camera2_image0001", "camera2_image0002"]
    assert [c.image_path.relative_to(root / "images").as_posix() for c in got] == sorted(names)
    cam = look_at_camera((0, 0, -4.0), (0, 0, 0), 64, 48)
    frames = [{"file_path": f"images/{n}", "transform_matrix": np.linalg.inv(cam.viewmat).tolist()} for n in names]
    (root / "transforms.json").write_text(json.dumps({"fl_x": 50.0, "w": 64, "h": 48, "frames": frames}))
    assert sorted(c.name for c in load_cameras(root / "transforms.json")) == [c.name for c in got]
    # round 58a: names were read from where a link points: a git-annex rig's views were named after content hashes
    store = tmp_path / "annex"
    store.mkdir()
    for k, name in enumerate(names):
        image = root / "images" / name
        (store / f"SHA256E-s{k}--{k:064x}.png").write_bytes(image.read_bytes())
        image.unlink()
        image.symlink_to(store / f"SHA256E-s{k}--{k:064x}.png")
    assert [c.name for c in load_cameras(root)] == [c.name for c in got]
    assert sorted(c.name for c in load_cameras(root / "transforms.json")) == [c.name for c in got]
    (root / "images" / "rig1" / "camera1" / "image0001.jpg").write_bytes((root / "images" / "rig1" / "camera1" / "image0001.png").read_bytes())
    (root / "sparse" / "0" / "images.txt").write_text((root / "sparse" / "0" / "images.txt").read_text() + "9 1 0 0 0 0 0 4 1 rig1/camera1/image0001.jpg\n\n")
    with pytest.raises(InputError, match=r"images 1 \('rig1/camera1/image0001.png'\) and 9 \('rig1/camera1/image0001.jpg'\) \(IMAGE_ID\) both name"):
        load_cameras(root)


def test_rig_prefixes_never_put_a_separator_or_a_parent_in_a_view_name():
    """Read-through: an absolute image name beside a relative one of the same stem gave the view name '/_abs_a', so the
    feature files `features` writes under it went to the file system's root; '..' parts went into names too."""
    from drsplat.cameras import folder_prefixes

    for given in (["/abs/a.png", "b/a.png"], ["../x/a.png", "y/a.png"], ["/abs/a.png", "/abs2/a.png"]):
        prefixes = folder_prefixes(given)
        assert prefixes is not None and all("/" not in p and ".." not in p for p in prefixes.values()), prefixes
    assert folder_prefixes(["/abs/a.png", "b/a.png"]) == {"/abs/a.png": "abs_", "b/a.png": "b_"}


def test_a_view_name_that_collides_only_after_the_rig_prefixes_is_named_as_a_view_name(tmp_path):
    """Round 58a's leftover: cam1/img_00 beside a root-level cam1_img_00 (with cam2/img_00, a rig's layout) was refused as two
    cameras naming "the image stem 'cam1_img_00'": that is the view name the folder prefix made, not either file's stem."""
    root = _tiny_colmap(tmp_path / "rig", ("cam1/img_00.png", "cam2/img_00.png", "cam1_img_00.png"))
    with pytest.raises(InputError, match=r"both name the view 'cam1_img_00' \(.*cam1/img_00.png and .*images/cam1_img_00.png\): images of "
                                         r"one name in different folders are named by their folders too .*, and that name is another image's stem"):
        load_cameras(root)
    # round 60a: two prefixed names colliding (a_b/c and a/b_c), neither another image's stem
    root = _tiny_colmap(tmp_path / "rig2", ("a_b/c.png", "x/c.png", "a/b_c.png", "y/b_c.png"))
    with pytest.raises(InputError, match=r"both name the view 'a_b_c' .*, and both names are made so; rename one"):
        load_cameras(root)


def test_dot_inside_a_linked_model_folder_reads_the_images_of_the_dataset_the_shell_is_in(tmp_path, monkeypatch):
    """Round 58a's leftover: `--source .` given inside DATASET/sparse/0, a link to a model kept elsewhere, looked for the
    images beside the link's target (the process's working folder is the resolved one): every image was missing. '.' is
    now read against the shell's working folder ($PWD) when that is the same folder; a stale $PWD is not trusted."""
    import shutil

    root = _tiny_colmap(tmp_path / "src", ("a.png", "b.png"))
    want = [c.image_path.resolve() for c in load_cameras(root)]
    store = tmp_path / "models" / "run7"
    store.parent.mkdir()
    shutil.move(root / "sparse" / "0", store)
    (root / "sparse" / "0").symlink_to(store, target_is_directory=True)
    monkeypatch.chdir(root / "sparse" / "0")
    monkeypatch.setenv("PWD", str(root / "sparse" / "0"))
    assert [c.image_path.resolve() for c in load_cameras(".")] == want
    monkeypatch.setenv("PWD", str(tmp_path))  # not this folder: the resolved working folder is all there is
    with pytest.raises(InputError, match="every image file is missing"):
        load_cameras(".")


@pytest.mark.parametrize("size, resolution, want", [((6000, 4000), -1, (1600, 1066)), ((5025, 3312), -1, (1600, 1054)),
                                                    ((5187, 3361), -1, (1600, 1036)), ((5025, 3312), 1000, (999, 659)),
                                                    ((1080, 1920), 4, (270, 480)), ((1001, 667), 2, (500, 334)),
                                                    ((1080, 1920), -1, (1080, 1920))])
def test_resolution_gives_the_size_3dgs_trains_at(size, resolution, want):
    """Round 63a: `--resolution` rounded where 3DGS's loadCam truncates (int(W / d) for -1 and target widths), so
    a 6000x4000 capture at -1 was registered at 1600x1067 against the 1600x1066 its scene was trained at. The
    sizes here are loadCam's (Python floats: 5025 / (5025 / 1000) truncates to 999)."""
    from drsplat.cameras import scale_cameras

    cam = Camera(R=np.eye(3), t=np.zeros(3), fx=3000.0, fy=3000.0, cx=size[0] / 2, cy=size[1] / 2, width=size[0], height=size[1], name="c")
    got = scale_cameras([cam], resolution)[0]
    assert (got.width, got.height) == want
    assert got.fx == pytest.approx(3000.0 * want[0] / size[0]) and got.cy == pytest.approx(size[1] / 2 * want[1] / size[1])
