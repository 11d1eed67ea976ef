"""Scene files that are damaged in ways a reader could take for values (round 53a, docs/hostile.md):
signalling NaNs, Python-only numbers in an ASCII PLY, compressed-PLY chunk ranges that are inverted or
integer-typed, a gzipped PLY named .splat, an spz stream whose checksum fails, list properties; and round 53a's
leftovers: a header line outside ASCII, two format lines, a gzipped version-4 spz."""

from __future__ import annotations

import gzip
import logging
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest

from drsplat.errors import InputError
from drsplat.scene import GaussianScene, compressed_ply_bytes, load_ply, save_ply
from drsplat.splat_formats import load_scene_report, save_scene

SIGNALLING_NAN32 = np.array([0x7F800001], np.uint32).view(np.float32)[0]  # quiet bit clear
SIGNALLING_NAN64 = np.array([0x7FF0000000000001], np.uint64).view(np.float64)[0]


def small_scene(n: int = 300, seed: int = 0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    return GaussianScene(means=rng.uniform(-4, 4, (n, 3)).astype(np.float32), quats=rng.normal(size=(n, 4)).astype(np.float32),
                         log_scales=rng.uniform(-5, -1, (n, 3)).astype(np.float32), opacity_logits=rng.normal(size=n).astype(np.float32),
                         sh=rng.normal(scale=0.5, size=(n, 1, 3)).astype(np.float32))


def load_without_numpy_warnings(path: Path):
    """The scene and report of `path`, failing on any Python warning (numpy's RuntimeWarning on a cast among them)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return load_scene_report(path)


def inria_with_double_column(path: Path, scene: GaussianScene, column: str, row: int, value: float) -> Path:
    """`scene` as an INRIA PLY whose `column` is stored as double, with `value` at `row`."""
    from plyfile import PlyData, PlyElement

    save_ply(scene, path)
    vertex = PlyData.read(str(path))["vertex"].data
    dtype = [(name, "<f8" if name == column else vertex.dtype[name].str) for name in vertex.dtype.names]
    out = np.empty(len(vertex), dtype)
    for name in vertex.dtype.names:
        out[name] = vertex[name]
    out[column][row] = value
    PlyData([PlyElement.describe(out, "vertex")]).write(str(path))
    return path


def test_a_signalling_nan_is_dropped_and_counted_without_numpys_cast_warning(tmp_path, caplog):
    """A NaN whose quiet bit is clear printed numpy's "invalid value encountered in cast" (a traceback under -W error)
    before drsplat's own count: in a .splat scale and in an INRIA PLY's double column."""
    scene = small_scene()
    splat = tmp_path / "s.splat"
    save_scene(scene, splat)
    raw = bytearray(splat.read_bytes())
    raw[12:16] = SIGNALLING_NAN32.tobytes()  # row 0's first scale (position 12 bytes, then 3 float32 scales)
    splat.write_bytes(bytes(raw))
    ply = inria_with_double_column(tmp_path / "d.ply", scene, "x", 5, SIGNALLING_NAN64)
    for path in (splat, ply):
        with caplog.at_level(logging.WARNING):
            loaded, _ = load_without_numpy_warnings(path)
        assert loaded.num_gaussians == scene.num_gaussians - 1, path
        assert f"{path}: 1 row with NaN values dropped" in caplog.text
        caplog.clear()


def test_an_ascii_ply_number_with_an_underscore_or_a_non_ascii_digit_is_refused(tmp_path):
    """'1_5' was read as 15 (Python's int/float read PEP 515 literals; a PLY number has no '_'), silently; Unicode
    digits likewise. Each is one error naming the body's line."""
    scene = small_scene(3)
    save_ply(scene, tmp_path / "b.ply")
    from plyfile import PlyData

    ply = PlyData.read(str(tmp_path / "b.ply"))
    ply.text = True
    ply.write(str(tmp_path / "a.ply"))
    text = (tmp_path / "a.ply").read_bytes()
    head, body = text.split(b"end_header\n", 1)
    lines = body.split(b"\n")
    assert load_ply(tmp_path / "a.ply").num_gaussians == 3  # the file as written reads
    for bad, shown in ((b"1_5", "'_'"), ("\u0661\u0665".encode(), "'\u0661'")):  # the digit, not its lead byte as Latin-1
        fields = lines[1].split(b" ")
        fields[0] = bad
        damaged = head + b"end_header\n" + b"\n".join([lines[0], b" ".join(fields), *lines[2:]])
        (tmp_path / "x.ply").write_bytes(damaged)
        with pytest.raises(InputError, match=rf"x.ply: data line 2 of the ASCII body .* holds {shown}, which no PLY number has"):
            load_ply(tmp_path / "x.ply")


def test_inverted_or_integer_chunk_ranges_of_a_compressed_ply_are_said(tmp_path, caplog):
    """Chunk ranges with min above max were decoded mirrored (splats moved by the whole extent) with no finding; a
    range declared int had its float's bits read as an integer (min_x -1.08e9). The first is a warning naming the
    field, the second an error."""
    data, _ = compressed_ply_bytes(small_scene())
    head, body = data.split(b"end_header\n", 1)
    assert head.startswith(b"ply\nformat binary_little_endian") and b"element chunk 2\n" in head
    chunk_props = [line.split()[2] for line in head.split(b"element chunk")[1].split(b"element")[0].split(b"\n") if line.startswith(b"property")]
    assert chunk_props[:2] == [b"min_x", b"min_y"] and len(chunk_props) == 18
    chunks = np.frombuffer(body[: 2 * 18 * 4], "<f4").reshape(2, 18).copy()
    names = [p.decode() for p in chunk_props]
    ix, ax = names.index("min_x"), names.index("max_x")
    chunks[0, [ix, ax]] = chunks[0, [ax, ix]]  # chunk 0's x range inverted
    (tmp_path / "inverted.compressed.ply").write_bytes(head + b"end_header\n" + chunks.tobytes() + body[2 * 18 * 4:])
    with caplog.at_level(logging.WARNING):
        load_scene_report(tmp_path / "inverted.compressed.ply")
    assert "field 'min_x': 1 of 2 chunks hold a range whose min is above its max (chunk 0:" in caplog.text, caplog.text
    (tmp_path / "int.compressed.ply").write_bytes(head.replace(b"property float min_x", b"property int min_x", 1) + b"end_header\n" + body)
    with pytest.raises(InputError, match=r"field 'min_x': is a compressed PLY whose chunk property min_x is declared int"):
        load_scene_report(tmp_path / "int.compressed.ply")


def test_a_compressed_ply_without_its_chunk_element_is_named_so(tmp_path):
    """Round 98b F1: packed vertex rows without the `chunk` element (dropped, or renamed 'chunks') were read as an INRIA
    file and refused as "missing a required vertex property" x, which such a file never has."""
    data, _ = compressed_ply_bytes(small_scene())
    head, body = data.split(b"end_header\n", 1)
    chunk_head = b"element chunk" + head.split(b"element chunk", 1)[1].split(b"element vertex", 1)[0]
    chunk_bytes = 2 * 18 * 4
    (tmp_path / "renamed.ply").write_bytes(head.replace(b"element chunk 2", b"element chunks 2", 1) + b"end_header\n" + body)
    (tmp_path / "dropped.ply").write_bytes(head.replace(chunk_head, b"", 1) + b"end_header\n" + body[chunk_bytes:])
    for name, elements in (("renamed.ply", "'chunks', 'vertex'"), ("dropped.ply", "'vertex'")):
        with pytest.raises(InputError, match=rf"{name}: field 'chunk': is a compressed PLY \(packed vertex rows\) without its 'chunk' "
                                             rf"element of per-256-splat ranges.*\(elements: {elements}\)"):
            load_scene_report(tmp_path / name)


def test_a_gzipped_ply_named_splat_is_refused_as_a_gzipped_ply(tmp_path):
    """It was decoded as .splat records: hundreds of garbage Gaussians and five warnings; named .ply it was refused."""
    save_ply(small_scene(), tmp_path / "s.ply")
    data = gzip.compress((tmp_path / "s.ply").read_bytes())
    (tmp_path / "s.splat").write_bytes(data + b"\0" * (-len(data) % 32))
    with pytest.raises(InputError, match=r"s.splat: is a gzip-compressed PLY file: decompress it first"):
        load_scene_report(tmp_path / "s.splat")


def test_an_spz_stream_that_fails_its_checksum_is_named_not_its_header_field(tmp_path):
    """A damaged deflate stream whose header came out as nonsense was blamed on the header ("is spz version
    4294967043"); the gzip checksum says what is wrong."""
    rng = np.random.default_rng(1)
    body = bytes(rng.integers(0, 256, 10 * 20, dtype=np.uint8))
    stream = gzip.compress(struct.pack("<IIIBBBB", 0x5053474E, 3, 10, 0, 12, 0, 0) + body)
    damaged = stream[:20] + bytes(b ^ 0xFF for b in stream[20:40]) + stream[40:]
    (tmp_path / "d.spz").write_bytes(damaged)
    with pytest.raises(InputError) as err:
        load_scene_report(tmp_path / "d.spz")
    assert "field 'gzip': is a damaged gzip stream (Error -3 while decompressing data: incorrect data check)" in str(err.value), err.value
    assert "version" not in str(err.value)


def test_a_list_property_in_the_vertex_element_is_named_not_called_a_truncation(tmp_path):
    path = tmp_path / "l.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty list uchar int idx\n"
                     b"end_header\n" + b"\0" * 6)
    with pytest.raises(InputError, match=r"field 'vertex': element 'vertex' has list properties, which 3DGS files never have"):
        load_ply(path)


def test_a_gzipped_splat_is_refused_not_read_as_records(tmp_path):
    """Round 53a (second probe): a gzip of a .splat whose size is a multiple of 32 was read as ~1,000 Gaussians of ±3e38
    with warnings that blamed the scene, exit 0. A whole gzip stream whose checksum holds is refused."""
    save_scene(small_scene(), tmp_path / "plain.splat")
    (tmp_path / "g.splat").write_bytes(gzip.compress((tmp_path / "plain.splat").read_bytes(), mtime=0))
    with pytest.raises(InputError, match=r"g.splat: is a gzip-compressed file: decompress it first"):
        load_scene_report(tmp_path / "g.splat")
    assert load_scene_report(tmp_path / "plain.splat")[0].num_gaussians == 300  # the file itself still reads


def test_an_ascii_value_beyond_float32_is_counted_without_numpys_overflow_warning(tmp_path, caplog):
    """1e39 in an ASCII float property leaked numpy's "overflow encountered in cast" (a refusal under -W error)."""
    header = "ply\nformat ascii 1.0\nelement vertex 2\n" + "".join(f"property float {name}\n" for name in (
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"))
    row = "2 3 0.1 0.2 0.3 0.5 -1 -2 -3 1 0 0 0\n"
    (tmp_path / "big.ply").write_text(header + "end_header\n" + "1e39 " + row + "1 " + row)
    with caplog.at_level(logging.WARNING):
        scene, _ = load_without_numpy_warnings(tmp_path / "big.ply")
    assert scene.num_gaussians == 1 and "1 row with infinite" in caplog.text


def test_a_header_comment_outside_ascii_is_dropped_with_a_warning_and_another_line_is_named(tmp_path, caplog):
    """A UTF-8 comment ("Made by Jörg") refused the whole file as "a header that is not ASCII text", naming no line
    (splat-transform reads it). A binary PLY now reads with the comment dropped and said; an ASCII PLY (parsed by
    plyfile, which refuses such a header) and a non-comment line are one error naming the line and character."""
    scene = small_scene(5)
    save_ply(scene, tmp_path / "a.ply")
    data = (tmp_path / "a.ply").read_bytes()
    fmt = b"format binary_little_endian 1.0\n"
    (tmp_path / "u.ply").write_bytes(data.replace(fmt, fmt + "comment Made by Jörg\n".encode(), 1))
    with caplog.at_level(logging.WARNING):
        loaded = load_ply(tmp_path / "u.ply")
    np.testing.assert_array_equal(loaded.means, scene.means)
    assert not any("Jörg" in c for c in loaded.comments)
    assert "u.ply: header line 3 ('comment Made by Jörg') holds 'ö', outside ASCII; the comment is dropped" in caplog.text
    (tmp_path / "p.ply").write_bytes(data.replace(b"property float x", "property float é".encode(), 1))
    with pytest.raises(InputError, match=r"p.ply: header line \d+ \('property float é'\) holds 'é', outside ASCII"):
        load_ply(tmp_path / "p.ply")
    from plyfile import PlyData

    ply = PlyData.read(str(tmp_path / "a.ply"))
    ply.text = True
    ply.write(str(tmp_path / "t.ply"))
    text = (tmp_path / "t.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(text.replace(b"format ascii 1.0\n", "format ascii 1.0\ncomment Jörg\n".encode(), 1))
    with pytest.raises(InputError, match=r"t.ply: header line 3 \('comment Jörg'\) holds 'ö', outside ASCII; an ASCII PLY's header"):
        load_ply(tmp_path / "t.ply")


def test_two_format_lines_are_refused(tmp_path):
    """The second format line won over the first (plyfile's reading); a hand parser would take the first. Neither is right."""
    save_ply(small_scene(5), tmp_path / "a.ply")
    data = (tmp_path / "a.ply").read_bytes()
    (tmp_path / "f.ply").write_bytes(data.replace(b"element vertex", b"format ascii 1.0\nelement vertex", 1))
    with pytest.raises(InputError, match=r"f.ply: has two 'format' lines \(header lines 2 and 3\)"):
        load_ply(tmp_path / "f.ply")


@pytest.mark.parametrize("line", [b"format binary_little_endian 2.0", b"format binary_little_endian", b"format binary_little_endian 1.0 x"])
def test_a_format_line_of_another_version_is_refused(tmp_path, line):
    """Round 85b F7: 'format binary_little_endian 2.0' (no such PLY; plyfile refuses it) was read without a word."""
    save_ply(small_scene(5), tmp_path / "a.ply")
    data = (tmp_path / "a.ply").read_bytes()
    (tmp_path / "v.ply").write_bytes(data.replace(b"format binary_little_endian 1.0", line, 1))
    with pytest.raises(InputError, match=r"v.ply: has format line 'format binary_little_endian' with version .* \(header line 2\); PLY has "
                                         "version 1.0 only"):
        load_ply(tmp_path / "v.ply")


def test_a_gzipped_version_4_spz_is_named_not_called_truncated(tmp_path):
    """Version 4 is a plain file of zstd streams; gzipped, it was read as a version 1-3 stream and called "truncated"."""
    scene = small_scene()
    save_scene(scene, tmp_path / "v4.spz", spz_version=4)
    assert load_scene_report(tmp_path / "v4.spz")[0].num_gaussians == 300
    (tmp_path / "g.spz").write_bytes(gzip.compress((tmp_path / "v4.spz").read_bytes(), mtime=0))
    with pytest.raises(InputError) as err:
        load_scene_report(tmp_path / "g.spz")
    assert "is a gzip-compressed spz version 4 file" in str(err.value) and "truncated" not in str(err.value), err.value
    # round 85b F2: a gzip stream whose header says 5 or more was told to decompress it too, which does not help
    save_scene(scene, tmp_path / "v3.spz", spz_version=3)
    raw = gzip.decompress((tmp_path / "v3.spz").read_bytes())
    for version in (5, 255):
        (tmp_path / "v.spz").write_bytes(gzip.compress(raw[:4] + version.to_bytes(4, "little") + raw[8:], mtime=0))
        with pytest.raises(InputError) as err:
            load_scene_report(tmp_path / "v.spz")
        assert f"is spz version {version}; drsplat reads versions 1-4" in str(err.value) and "decompress" not in str(err.value), err.value
