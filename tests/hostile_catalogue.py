"""A catalogue of hostile inputs, generated (never committed as binaries).

Each builder writes one bad file into a folder and returns its path; `CATALOGUE` lists them by
class so tests (and the report) can count classes x cases. Files are tiny: the point of the
memory bombs is a header that claims far more data than the file holds.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np

INRIA_PROPS = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
               "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def ply_bytes(header_lines: list[str], body: bytes = b"", fmt: str = "binary_little_endian") -> bytes:
    return ("\n".join(["ply", f"format {fmt} 1.0", *header_lines, "end_header"]) + "\n").encode("ascii") + body


def vertex_header(count: int, props: list[str] = INRIA_PROPS, ptype: str = "float") -> list[str]:
    return [f"element vertex {count}"] + [f"property {ptype} {p}" for p in props]


def vertex_body(count: int, props: list[str] = INRIA_PROPS) -> bytes:
    rows = np.zeros((count, len(props)), "<f4")
    if "rot_0" in props:
        rows[:, props.index("rot_0")] = 1.0
    return rows.tobytes()


# ---------------------------------------------------------------------------------------------- PLY


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


PLY_CASES: dict[str, Callable[[Path], bytes]] = {
    # memory bombs: counts that the bytes cannot hold
    "face_2e9_after_vertex": lambda d: ply_bytes(vertex_header(2) + ["element face 2000000000", "property list uchar int vertex_indices"], vertex_body(2) + b"\x03" + b"\0" * 12),
    "face_2e9_before_vertex": lambda d: ply_bytes(["element face 2000000000", "property list uchar int vertex_indices"] + vertex_header(2), b"\0" * 600),
    "vertex_2e9": lambda d: ply_bytes(vertex_header(2_000_000_000), vertex_body(3)),
    "vertex_1e15_ascii": lambda d: ply_bytes(vertex_header(10**15), b"0 " * 17 + b"\n", fmt="ascii"),
    "chunk_bomb_compressed": lambda d: ply_bytes(["element chunk 900000000"] + [f"property float {n}" for n in ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z")]
                                                 + ["element vertex 1", "property uint packed_position"], b"\0" * 100),
    "list_in_vertex": lambda d: ply_bytes(["element vertex 1", "property list uchar float x"], b"\0" * 8),
    "list_count_type_bogus": lambda d: ply_bytes(["element vertex 1", "property list blob float x"], b"\0" * 8),
    # malformed headers and layouts
    "duplicate_property": lambda d: ply_bytes(vertex_header(1, INRIA_PROPS + ["x"]), b"\0" * 72),
    "duplicate_element": lambda d: ply_bytes(vertex_header(1) + vertex_header(1), vertex_body(2)),
    "misnumbered_f_rest": lambda d: ply_bytes(vertex_header(1, INRIA_PROPS + [f"f_rest_{i}" for i in range(8)] + ["f_rest_42"]), vertex_body(1, INRIA_PROPS + ["f"] * 9)),
    "truncated_body": lambda d: ply_bytes(vertex_header(10), vertex_body(3)),
    "non_ascii_header": lambda d: b"ply\nformat binary_little_endian 1.0\ncomment \xff\xfe\n" + ply_bytes(vertex_header(1))[36:],
    "no_end_header": lambda d: b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n",
    "unknown_keyword": lambda d: ply_bytes(["elephant vertex 1"]),
    "bad_format": lambda d: ply_bytes(vertex_header(1), vertex_body(1), fmt="binary_middle_endian"),
    "negative_count": lambda d: ply_bytes(vertex_header(1)[:0] + ["element vertex -5"] + [f"property float {p}" for p in INRIA_PROPS]),
    "missing_rot": lambda d: ply_bytes(vertex_header(1, INRIA_PROPS[:-1]), vertex_body(1, INRIA_PROPS[:-1])),
    "not_a_ply": lambda d: b"\x89PNG\r\n\x1a\n" + b"\0" * 64,
    "empty_file": lambda d: b"",
    "ascii_garbage_rows": lambda d: ply_bytes(vertex_header(2), b"1 2 3\nfoo bar\n" + b"0 " * 40, fmt="ascii"),
    # rows of 18 floats under a header that lists 17: every row after the first would be read shifted
    "property_missing_from_header": lambda d: ply_bytes(vertex_header(100), vertex_body(100, INRIA_PROPS + ["nz"])),
    "cr_only_header": lambda d: ply_bytes(vertex_header(1), vertex_body(1)).replace(b"\n", b"\r", len(vertex_header(1)) + 3),
}

PLY_BOMBS = ("face_2e9_after_vertex", "face_2e9_before_vertex", "vertex_2e9", "vertex_1e15_ascii", "chunk_bomb_compressed")


def make_ply(folder: Path, name: str) -> Path:
    return _write(folder / f"{name}.ply", PLY_CASES[name](folder))


# ---------------------------------------------------------------------------------------------- .npy


def npy_with_header(header: dict, body: bytes = b"") -> bytes:
    text = repr(header).encode("latin1")
    pad = 64 - (10 + len(text) + 1) % 64
    text += b" " * pad + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text + body


NPY_CASES: dict[str, Callable[[], bytes]] = {
    "shape_1e12": lambda: npy_with_header({"descr": "<f4", "fortran_order": False, "shape": (10**12,)}, b"\0" * 64),
    "shape_2d_bomb": lambda: npy_with_header({"descr": "<f4", "fortran_order": False, "shape": (10**7, 10**6)}, b"\0" * 64),
    "object_pickle": lambda: npy_with_header({"descr": "|O", "fortran_order": False, "shape": (1,)}, b"\x80\x04N."),
    "truncated": lambda: npy_with_header({"descr": "<f4", "fortran_order": False, "shape": (100,)}, b"\0" * 12),
    "bad_magic": lambda: b"NOTNUMPY" + b"\0" * 100,
    "bad_header_syntax": lambda: b"\x93NUMPY\x01\x00" + struct.pack("<H", 54) + b"{'descr': '<f4', 'shape': (((((((((( " + b" " * 17 + b"\n",
    "empty_file": lambda: b"",
}
NPY_BOMBS = ("shape_1e12", "shape_2d_bomb")


def make_npy(folder: Path, name: str) -> Path:
    return _write(folder / f"{name}.npy", NPY_CASES[name]())


# ---------------------------------------------------------------------------------------------- cameras


def _c2w() -> list[list[float]]:
    m = np.eye(4)
    m[:3, 3] = [0, 0, 4]
    return m.tolist()


def _frame(**kw) -> dict:
    frame = {"file_path": "images/v.png", "transform_matrix": _c2w(), "fl_x": 50.0, "w": 64, "h": 48}
    frame.update(kw)
    return frame


TRANSFORMS_CASES: dict[str, tuple[object, str]] = {
    # name: (JSON document, a word the error must contain)
    "top_level_list": ([_frame()], "frames"),
    "frames_not_list": ({"frames": {"a": 1}}, "frames"),
    "frame_not_dict": ({"frames": [3]}, "frame 0"),
    "string_camera_angle_y": (None, "camera_angle_y"),  # written by make_transforms_dataset
    "string_k3": ({"frames": [_frame(k3="0.1")]}, "k3"),
    "width_zero": ({"frames": [_frame(w=0)]}, "'w'"),
    "fractional_height": ({"frames": [_frame(h=47.5)]}, "'h'"),
    "nan_focal": ({"frames": [_frame(fl_x=float("nan"))]}, "fl_x"),
    "negative_focal": ({"frames": [_frame(fl_x=-50.0)]}, "fl_x"),
    "zero_focal": ({"frames": [_frame(fl_x=0.0)]}, "fl_x"),
    "huge_width": ({"frames": [_frame(w=10**9)]}, "'w'"),
    "all_zero_matrix": ({"frames": [_frame(transform_matrix=np.zeros((4, 4)).tolist())]}, "transform_matrix"),
    "scaled_rotation": ({"frames": [_frame(transform_matrix=np.diag([3.0, 3.0, 3.0, 1.0]).tolist())]}, "rotation"),  # eye(4) * 3 is now a bottom-row error
    "nan_translation": ({"frames": [_frame(transform_matrix=[[1, 0, 0, float("nan")], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])]},
                        "frame 0 has a non-finite value (nan) at row 0, column 3 of its transform_matrix"),  # round 54: was "of shape (4, 4) or with non-finite values"
    "three_by_four_matrix": ({"frames": [_frame(transform_matrix=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]])]},
                             "frame 0 has a 3x4 transform_matrix; expected 4x4"),
    "matrix_of_strings": ({"frames": [_frame(transform_matrix=[["a"] * 4] * 4)]}, "transform_matrix"),
    "file_path_int": ({"frames": [_frame(file_path=7)]}, "file_path"),
    "bool_width": ({"frames": [_frame(w=True)]}, "'w'"),
    "angle_out_of_range": ({"camera_angle_x": 4.0, "frames": [{k: v for k, v in _frame().items() if k != "fl_x"}]}, "camera_angle_x"),
    "deep_nesting": (None, "JSON"),  # written as text below
    # round 3: finite but absurd intrinsics overflowed the culling bound; a NUL byte in a name raised ValueError
    "focal_1e300": ({"frames": [_frame(fl_x=1e300)]}, "field 'fl_x': frame 0 has fl_x=1e+300"),
    "focal_1e-300": ({"frames": [_frame(fl_x=1e-300)]}, "field 'fl_x': frame 0 has fl_x=1e-300"),
    "cx_1e300": ({"frames": [_frame(cx=1e300)]}, "field 'cx': frame 0 has cx=1e+300"),
    "nul_in_file_path": ({"frames": [_frame(file_path="images/v\x00.png")]}, "field 'file_path': frame 0 has an image name with a NUL byte"),
    # round 3 (C6): the bottom row was never read; a string "1" was parsed as a number
    "bottom_row_not_0001": ({"frames": [_frame(transform_matrix=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0.5, 0, 0, 1]])]},
                            "field 'transform_matrix': frame 0 has the bottom row [0.5, 0.0, 0.0, 1.0]"),
    "transposed_matrix": ({"frames": [_frame(transform_matrix=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0.1, 0.2, 3, 1]])]},
                          "expected [0, 0, 0, 1]"),
    "string_one_in_matrix": ({"frames": [_frame(transform_matrix=[["1", 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])]},
                             "field 'transform_matrix': frame 0 has \"1\" at row 0, column 0"),
    "bool_in_matrix": ({"frames": [_frame(transform_matrix=[[True, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])]},
                       "frame 0 has true at row 0, column 0"),
    # round 5: a lone surrogate raised UnicodeEncodeError, "/" raised ValueError (empty name), both as tracebacks
    "surrogate_in_file_path": ({"frames": [_frame(file_path="images/\ud800x.png")]}, "field 'file_path': frame 0 has an image name with a lone UTF-16 surrogate"),
    "file_path_root": ({"frames": [_frame(file_path="/")]}, "field 'file_path': frame 0 has the image name '/', which names a folder"),
    "file_path_folder": ({"frames": [_frame(file_path="images/")]}, "names a folder"),
}


def make_transforms_dataset(folder: Path, name: str) -> Path:
    """A transforms.json dataset with one 64x48 image and the bad document `name`."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    (folder / "images").mkdir(exist_ok=True)
    Image.new("RGB", (64, 48)).save(folder / "images" / "v.png")
    doc, _ = TRANSFORMS_CASES[name]
    if name == "string_camera_angle_y":
        frame = _frame()
        del frame["fl_x"]
        doc = {"camera_angle_x": 0.7, "camera_angle_y": "wide", "frames": [frame]}
    text = "[" * 100_000 + "]" * 100_000 if name == "deep_nesting" else json.dumps(doc)
    (folder / "transforms.json").write_text(text)
    return folder


CAMERAS_JSON_CASES: dict[str, tuple[object, str]] = {
    "not_a_list": ({"a": 1}, "list"),
    "record_not_dict": ([5], "camera 0"),
    "missing_rotation": ([{"position": [0, 0, 0], "img_name": "v", "width": 64, "height": 48, "fx": 50, "fy": 50}], "rotation"),
    "string_width": ([{"rotation": np.eye(3).tolist(), "position": [0, 0, 0], "img_name": "v", "width": "64", "height": 48, "fx": 50, "fy": 50}], "width"),
    "negative_fy": ([{"rotation": np.eye(3).tolist(), "position": [0, 0, 0], "img_name": "v", "width": 64, "height": 48, "fx": 50, "fy": -5}], "fy"),
    "zero_rotation": ([{"rotation": np.zeros((3, 3)).tolist(), "position": [0, 0, 0], "img_name": "v", "width": 64, "height": 48, "fx": 50, "fy": 50}], "rotation"),
}


def make_cameras_json_dataset(folder: Path, name: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cameras.json").write_text(json.dumps(CAMERAS_JSON_CASES[name][0]))
    return folder


COLMAP_CASES: dict[str, tuple[str, str, str]] = {
    # name: (cameras.txt, images.txt, a word the error must contain)
    "non_utf8": ("1 PINHOLE 64 48 50 50 32 24\n", "1 1 0 0 0 0 0 4 1 v\xe9.png\n\n", "UTF-8"),
    "zero_quaternion": ("1 PINHOLE 64 48 50 50 32 24\n", "1 0 0 0 0 0 0 4 1 v.png\n\n", "quaternion"),
    "nan_translation": ("1 PINHOLE 64 48 50 50 32 24\n", "1 1 0 0 0 nan 0 4 1 v.png\n\n", "translation"),
    "negative_focal": ("1 PINHOLE 64 48 -50 50 32 24\n", "1 1 0 0 0 0 0 4 1 v.png\n\n", "fx"),
    "nan_focal": ("1 PINHOLE 64 48 nan 50 32 24\n", "1 1 0 0 0 0 0 4 1 v.png\n\n", "fx"),
    "zero_width": ("1 PINHOLE 0 48 50 50 32 24\n", "1 1 0 0 0 0 0 4 1 v.png\n\n", "width"),
    "negative_width": ("1 PINHOLE -64 48 50 50 32 24\n", "1 1 0 0 0 0 0 4 1 v.png\n\n", "width"),
    "missing_camera": ("1 PINHOLE 64 48 50 50 32 24\n", "1 1 0 0 0 0 0 4 9 v.png\n\n", "camera 9"),
    # round 3
    "focal_1e300": ("1 PINHOLE 64 48 1e300 1e300 32 24\n", "1 1 0 0 0 0 0 4 1 v.png\n\n", r"cameras\.txt: field 'fx': camera 1 .*fx=1e\+300"),
    "cy_1e300": ("1 PINHOLE 64 48 50 50 32 1e300\n", "1 1 0 0 0 0 0 4 1 v.png\n\n", r"cameras\.txt: field 'cy': camera 1 .*cy=1e\+300"),
    "nul_in_name": ("1 PINHOLE 64 48 50 50 32 24\n", "1 1 0 0 0 0 0 4 1 v\x00.png\n\n", r"images\.txt: field 'NAME': image 1 .*NUL byte"),
    "duplicate_image_id": ("1 PINHOLE 64 48 50 50 32 24\n", "1 1 0 0 0 0 0 4 1 v.png\n\n1 1 0 0 0 0 0 5 1 w.png\n\n",
                           r"images\.txt: field 'IMAGE_ID': line 3 repeats IMAGE_ID 1"),
    "duplicate_camera_id": ("1 PINHOLE 64 48 50 50 32 24\n1 PINHOLE 64 48 60 60 32 24\n", "1 1 0 0 0 0 0 4 1 v.png\n\n",
                            r"cameras\.txt: field 'CAMERA_ID': camera line 2 repeats CAMERA_ID 1"),
    "image_line_missing_points2d": ("1 PINHOLE 64 48 50 50 32 24\n", "1 1 0 0 0 0 0 4 1 v.png\n2 1 0 0 0 0 0 5 1 w.png\n\n",
                                    r"images\.txt: field 'POINTS2D': line 2 is an image line where the POINTS2D line of the image on line 1"),
    "points2d_not_triples": ("1 PINHOLE 64 48 50 50 32 24\n", "1 1 0 0 0 0 0 4 1 v.png\n1.0 2.0\n", r"images\.txt: field 'POINTS2D': line 2"),
}


def make_colmap_dataset(folder: Path, name: str) -> Path:
    cams, imgs, _ = COLMAP_CASES[name]
    sparse = folder / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    (sparse / "cameras.txt").write_text(cams)
    (sparse / "images.txt").write_bytes(imgs.encode("latin1"))
    return folder


# ---------------------------------------------------------------------------------------------- round 2 (issue 27)


def _inria_rows(count: int) -> np.ndarray:
    rows = np.zeros((count, len(INRIA_PROPS)), "<f4")
    rows[:, INRIA_PROPS.index("rot_0")] = 1.0
    return rows


def _with(count: int, prop: str, row: int, value: float) -> bytes:
    rows = _inria_rows(count)
    rows[row, INRIA_PROPS.index(prop)] = value
    return ply_bytes(vertex_header(count), rows.tobytes())


def _spread_with_one_huge(count: int = 200, log_scale: float = 5.0, far: float | None = None) -> bytes:
    """`count` small Gaussians along x in [0, 1] and one whose scale is e^log_scale (148 for 5: 100x the scene);
    with `far`, one more mean (another Gaussian's) that far out on y."""
    rows = _inria_rows(count)
    rows[:, INRIA_PROPS.index("x")] = np.linspace(0.0, 1.0, count)
    rows[:, [INRIA_PROPS.index(f"scale_{i}") for i in range(3)]] = -5.0
    rows[7, INRIA_PROPS.index("scale_0")] = log_scale
    if far is not None:
        rows[11, INRIA_PROPS.index("y")] = far
    return ply_bytes(vertex_header(count), rows.tobytes())


def _doubles_with(count: int, prop: str, row: int, value: float) -> bytes:
    """The `_with` scene written with double properties (a tool that widened every column)."""
    rows = _inria_rows(count).astype("<f8")
    rows[row, INRIA_PROPS.index(prop)] = value
    return ply_bytes(vertex_header(count, ptype="double"), rows.tobytes())


INFO_FINDING_CASES: dict[str, tuple[Callable[[], bytes], str]] = {
    # name: (PLY bytes, words `drsplat info` must list among its findings) -- was "findings none" for the first three
    "count_smaller_than_data": (lambda: ply_bytes(vertex_header(3), vertex_body(10)), "vertex count (3) may be smaller than the data"),
    "zero_rows": (lambda: ply_bytes(vertex_header(0)), "no Gaussians"),
    "overflowing_scale": (lambda: _with(4, "scale_1", 1, 100.0), "1 Gaussian has a log scale above 88.7"),
    "infinite_opacity": (lambda: _with(4, "opacity", 2, np.inf), "1 infinite opacity logit clamped"),
    "zero_quaternion": (lambda: _with(4, "rot_0", 0, 0.0), "1 zero quaternion replaced"),
    "mean_beyond_any_camera": (lambda: _with(4, "y", 3, 3e38), "1 Gaussian lies beyond 1e+15 from the origin"),  # round 5: "findings none"
    # 2026-12-01 probes: "findings none" and a render of inf colours; "findings none" and a registration wrecked by 10 Gaussians;
    # numpy's "overflow encountered in cast" twice and a finite double called infinite
    "sh_beyond_float32_colour": (lambda: _with(4, "f_dc_1", 2, 3e38), "1 Gaussian has an SH coefficient beyond 1e+30"),
    "huge_gaussian": (_spread_with_one_huge, "1 Gaussian is over 10x as large as the scene"),
    # was (a probe, 2026-12-01): one stray mean 1e14 away made the box so large that nothing was huge beside it
    "huge_gaussian_beside_a_stray_mean": (lambda: _spread_with_one_huge(log_scale=30.0, far=1e14),
                                          "1 Gaussian is over 10x as large as the scene"),
    "double_beyond_float32": (lambda: _doubles_with(4, "x", 1, 1e300), "1 row holds double-precision values beyond float32's range"),
}


def make_info_ply(folder: Path, name: str) -> Path:
    return _write(folder / f"{name}.ply", INFO_FINDING_CASES[name][0]())


def _view_without_masks(features: Path, stem: str, dim: int) -> None:
    seg = np.load(features / f"{stem}_s.npy")
    np.save(features / f"{stem}_s.npy", np.full(seg.shape, -1, seg.dtype))
    np.save(features / f"{stem}_f.npy", np.zeros((0, dim), np.float32))


def _masks_cover_nothing(features: Path, stem: str, dim: int) -> None:
    seg = np.load(features / f"{stem}_s.npy")
    np.save(features / f"{stem}_s.npy", np.full(seg.shape, -1, seg.dtype))


def _ids_as(dtype: str, wrap: bool = False) -> Callable[[Path, str, int], None]:
    def mutate(features: Path, stem: str, dim: int) -> None:
        seg = np.load(features / f"{stem}_s.npy").astype(np.int64)
        if wrap:
            seg[seg < 0] = 0
            seg.flat[0] = -1  # 2^64-1 as uint64: wrapped to -1 ("no mask") by a plain astype(int64)
        np.save(features / f"{stem}_s.npy", seg.astype(dtype) if not wrap else seg.astype(np.uint64))
    return mutate


def _mask_map_transposed(features: Path, stem: str, dim: int) -> None:
    seg = np.load(features / f"{stem}_s.npy")
    np.save(features / f"{stem}_s.npy", np.ascontiguousarray(np.swapaxes(seg, -1, -2)))  # (L, W, H): stretched before


def _mask_map_bool(features: Path, stem: str, dim: int) -> None:
    seg = np.load(features / f"{stem}_s.npy")
    np.save(features / f"{stem}_s.npy", seg >= 0)  # False was read as mask 0, True as mask 1


def _mask_map_half_resolution(features: Path, stem: str, dim: int) -> None:
    seg = np.load(features / f"{stem}_s.npy")
    np.save(features / f"{stem}_s.npy", np.ascontiguousarray(seg[..., ::2, ::2]))  # a uniform scale: resampled


def _ids_as_uint8_with_255_for_none(features: Path, stem: str, dim: int) -> None:
    seg = np.load(features / f"{stem}_s.npy").astype(np.int64)
    seg[seg < 0] = 255  # "no mask" as an unsigned dtype cannot store it: the error named 511, a value not in the file
    np.save(features / f"{stem}_s.npy", seg.astype(np.uint8))


FEATURE_VIEW_CASES: dict[str, tuple[Callable[[Path, str, int], None], str | None]] = {
    # name: (mutates one view of a features folder, None = registers (exit 0) | words of the one error)
    "no_masks": (_view_without_masks, None),  # was: TypeError in the pair log (memoryview cast)
    "masks_cover_nothing": (_masks_cover_nothing, None),
    "ids_as_float32": (_ids_as("float32"), None),
    "ids_as_int64": (_ids_as("int64"), None),
    "uint64_wraps_to_minus_one": (_ids_as("uint64", wrap=True), str(2**64 - 1)),
    "mask_map_half_resolution": (_mask_map_half_resolution, None),
    "mask_map_transposed": (_mask_map_transposed, "differ (a transposed or cropped map?)"),
    "mask_map_bool": (_mask_map_bool, "dtype bool"),
    "uint8_255_for_no_mask": (_ids_as_uint8_with_255_for_none, "255 is the largest uint8: if it means 'no mask'"),
}

SPECIAL_OUTPUTS = ("/dev/full", "/dev/null", "fifo", "symlink", "rlimit_fsize", "injected_enospc")  # tests/test_hostile.py

SILENT_RUN_CASES = ("resolution_0.001", "embedding_norm_overflow", "zero_gaussian_registered_ply", "flipped_pq_codes",
                    "screenshot_into_unwritable_folder", "bench_list_flags")


# ---------------------------------------------------------------------------------------------- counts


def catalogue_counts() -> dict[str, int]:
    """Hostile input classes and how many generated cases each holds (for the report)."""
    return {
        "PLY headers / layouts (memory bombs included)": len(PLY_CASES),
        ".npy headers (memory bombs, pickles, truncation)": len(NPY_CASES),
        "transforms.json values": len(TRANSFORMS_CASES),
        "3DGS cameras.json values": len(CAMERAS_JSON_CASES),
        "COLMAP text values": len(COLMAP_CASES),
        "info findings (short count, zero rows, overflowing scale, ...)": len(INFO_FINDING_CASES),
        "feature views (no masks, id dtypes, wrapped uint64, mask map shapes)": len(FEATURE_VIEW_CASES),
        "outputs that are not regular files or fail mid-write": len(SPECIAL_OUTPUTS),
        "formerly silent runs (now one warning or error)": len(SILENT_RUN_CASES),
    }
