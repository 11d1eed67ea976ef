"""`.splat` and `.spz` scene files (drsplat.splat_formats): peer-decoded fixtures, round trips through
the formats' reference encoders (tests/splat_codecs.py), hostile files, and the commands that read scenes."""

from __future__ import annotations

import gzip
import json
import logging
import re
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
import zstandard

from drsplat.cli import main
from drsplat.errors import InputError, OutputError
from drsplat.scene import SH_C0, GaussianScene, compressed_ply_bytes, load_ply, morton_order, save_ply
from drsplat.splat_formats import (load_scene, load_scene_report, pack_smallest_three, save_scene, save_spz, scene_format, spz_file_bytes,
                                   written_format)
from tests.conftest import splat_transform_command
from tests.splat_codecs import COORDINATE_EXTENSION, encode_splat, encode_spz, extension_record
from tests.splat_codecs import pack_smallest_three as codec_pack_smallest_three

PEERS = Path(__file__).parent / "data" / "peers"


def random_scene(n: int = 64, degree: int = 3, seed: int = 0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    sh = rng.normal(scale=0.25, size=(n, (degree + 1) ** 2, 3)).astype(np.float32)
    sh[:, 0] = rng.normal(scale=1.0, size=(n, 3))
    return GaussianScene(means=rng.uniform(-4, 4, size=(n, 3)).astype(np.float32), quats=rng.normal(size=(n, 4)).astype(np.float32),
                         log_scales=rng.uniform(-7, 1, size=(n, 3)).astype(np.float32),
                         opacity_logits=rng.normal(scale=2.0, size=n).astype(np.float32), sh=sh)


def rotations(quats: np.ndarray) -> np.ndarray:
    """[N, 3, 3] rotation matrices of (w, x, y, z) quaternions (sign-free, for comparing)."""
    q = quats.astype(np.float64) / np.linalg.norm(quats, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1).reshape(-1, 3, 3)


def opacities(scene: GaussianScene) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-scene.opacity_logits.astype(np.float64)))


def write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


# ---------------------------------------------------------------------------------------------- peers


@pytest.mark.parametrize("name", ["peer_v3.spz", "peer_v4.spz"])
def test_spz_decodes_as_the_spz_library_does(name):
    """splat-transform 2.7.1 (the spz library's WASM, into PLY's frame) wrote and decoded these files:
    every field the same float32 bits but the opacity: the library takes its logit in float32 (here
    float64: within 1e-6), and reads 8-bit alphas 0 and 255 as ±inf (here half a step inside)."""
    ours, report = load_scene_report(PEERS / name)
    peer = load_ply(PEERS / "peer_spz_decoded.ply")
    assert report.layout == f"spz v{name[6]}" and report.findings() == [] and ours.sh_degree == 3
    for field in ("means", "quats", "log_scales", "sh"):
        assert np.array_equal(getattr(ours, field), getattr(peer, field)), field
    extreme = np.abs(peer.opacity_logits) == 30.0  # the peer's ±inf, clamped by load_ply
    assert extreme.sum() == 8  # the 4 logits of ±9 and ±40 and 4 random ones beyond ±5.5
    assert np.allclose(ours.opacity_logits[~extreme], peer.opacity_logits[~extreme], rtol=1e-6, atol=1e-6)
    assert np.allclose(np.abs(ours.opacity_logits[extreme]), np.log(254.5 / 0.5), rtol=1e-6)
    assert np.array_equal(np.sign(ours.opacity_logits[extreme]), np.sign(peer.opacity_logits[extreme]))


def test_splat_decodes_as_splat_transform_does():
    """The same .splat read by splat-transform 2.7.1: positions and scales equal, colours to float32
    rounding, rotations within its other byte mapping (b/127.5 - 1 against (b - 128)/128), opacity
    but for bytes 0 and 255."""
    ours, report = load_scene_report(PEERS / "peer.splat")
    peer = load_ply(PEERS / "peer_splat_decoded.ply")
    assert report.layout == "splat" and ours.num_gaussians == 120 and ours.sh_degree == 0
    assert np.array_equal(ours.means, peer.means)
    assert np.array_equal(ours.log_scales, peer.log_scales)
    assert np.allclose(ours.sh, peer.sh, rtol=0, atol=2e-6)
    assert np.abs(rotations(ours.quats) - rotations(peer.quats)).max() < 0.03
    a, b = opacities(ours), opacities(peer)
    middle = (b > 1e-5) & (b < 1 - 1e-5)
    assert middle.sum() >= 110 and np.allclose(a[middle], b[middle], rtol=1e-5)
    assert np.all(np.abs(a[~middle] - b[~middle]) <= 0.5 / 255 + 1e-9)


@pytest.mark.parametrize("version", [3, 4])
def test_spz_written_by_splat_transform_now(tmp_path, version):
    """With splat-transform on this machine (skipped otherwise): a fresh random scene through its spz
    writer and reader, read by drsplat too."""
    command = splat_transform_command()
    src = tmp_path / "scene.ply"
    save_ply(random_scene(200, seed=version), src)
    spz, back = tmp_path / "scene.spz", tmp_path / "back.ply"
    subprocess.run([*command, "-q", "-w", str(src), "--spz-version", str(version), str(spz)], check=True, timeout=120, capture_output=True)
    subprocess.run([*command, "-q", "-w", str(spz), str(back)], check=True, timeout=120, capture_output=True)
    ours, peer = load_scene(spz), load_ply(back)
    for field in ("means", "quats", "log_scales", "sh"):
        assert np.array_equal(getattr(ours, field), getattr(peer, field)), field


# ---------------------------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("version", [1, 2, 3, 4])
@pytest.mark.parametrize("frame", [4, 6, 7, 1])  # RUB (no extension), RDF, LUF, LDB: stored frames named by the extension
@pytest.mark.parametrize("degree", [0, 1, 3])
def test_spz_round_trip_within_quantisation(tmp_path, version, frame, degree):
    """encode (the spz library's packing, any stored frame) then read: each field back within its
    quantisation step, in PLY's frame."""
    scene = random_scene(degree=degree, seed=version * 10 + frame)
    scene.means[:] = np.clip(scene.means, -4, 4)
    scene.log_scales[:] = np.clip(scene.log_scales, -9.9, 5.9)
    back = load_scene(write(tmp_path / "s.spz", encode_spz(scene, version, frame)))
    assert back.num_gaussians == scene.num_gaussians and back.sh_degree == degree
    pos_step = 2e-3 if version == 1 else 2.0 ** -12  # float16 or 12 fractional bits
    assert np.abs(back.means - scene.means).max() <= pos_step
    assert np.abs(back.log_scales - scene.log_scales).max() <= 1 / 32 + 1e-6
    reach = 127.5 / (0.15 * 255)  # the colour bytes hold f_dc in ±3.33
    assert np.abs(back.sh[:, 0] - np.clip(scene.sh[:, 0], -reach, reach)).max() <= 0.5 / (0.15 * 255) + 1e-5
    if degree:
        assert np.abs(back.sh[:, 1:] - np.clip(scene.sh[:, 1:], -1, 127 / 128)).max() <= 0.5 / 128 + 1e-6
    assert np.abs(opacities(back) - np.clip(opacities(scene), 0.5 / 255, 254.5 / 255)).max() <= 0.5 / 255 + 1e-7
    error = np.abs(rotations(back.quats) - rotations(scene.quats)).max(axis=(1, 2))
    if version >= 3:
        assert error.max() < 0.006
    else:  # x, y, z in 8 bits and w = sqrt(1 - |xyz|²): a step of 1/127.5 moves a small w by ~1/(127.5 w)
        w = np.abs(scene.quats[:, 0]) / np.linalg.norm(scene.quats, axis=1)
        assert np.all(error < 0.012 + 0.02 / np.maximum(w, 0.02))


def test_splat_round_trip_within_quantisation(tmp_path):
    scene = random_scene(degree=0, seed=5)
    back, report = load_scene_report(write(tmp_path / "s.splat", encode_splat(scene)))
    assert report.layout == "splat" and report.findings() == []
    assert np.array_equal(back.means, scene.means)
    assert np.allclose(back.log_scales, scene.log_scales, atol=1e-6)
    base = np.clip(0.5 + 0.28209479177387814 * scene.sh[:, 0], 0, 1)
    assert np.abs((0.5 + 0.28209479177387814 * back.sh[:, 0]) - base).max() <= 1 / 255 + 1e-6  # convert.py truncates
    assert np.abs(rotations(back.quats) - rotations(scene.quats)).max() < 0.05


def test_scene_format_reads_the_first_bytes(tmp_path):
    scene = random_scene(8, degree=0)
    save_ply(scene, tmp_path / "a.ply")
    cases = {"a.ply": "ply", "named.splat": "ply", "b.spz": "spz", "b.bin": "spz", "c.splat": "splat", "v4.data": "spz",
             "gzip-like.splat": "splat"}
    (tmp_path / "named.splat").write_bytes((tmp_path / "a.ply").read_bytes())  # a PLY named .splat is still read as PLY
    write(tmp_path / "b.spz", encode_spz(scene))
    write(tmp_path / "b.bin", encode_spz(scene))
    write(tmp_path / "c.splat", encode_splat(scene))
    write(tmp_path / "c.dat", encode_splat(scene))
    write(tmp_path / "v4.data", encode_spz(scene, 4))
    first = np.frombuffer(encode_splat(scene), np.uint8).copy()
    first[:2] = (0x1F, 0x8B)  # a first x coordinate whose low bytes are gzip's magic (1 file in 65,536)
    write(tmp_path / "gzip-like.splat", first.tobytes())
    assert {name: scene_format(tmp_path / name) for name in cases} == cases
    assert load_scene(tmp_path / "named.splat").num_gaussians == 8
    with pytest.raises(InputError, match="c.dat: is not a PLY file"):  # a .splat by its bytes, but no name says so
        scene_format(tmp_path / "c.dat")


# ---------------------------------------------------------------------------------------------- writing


def spz_payload(data: bytes) -> tuple[bytes, list[bytes]]:
    """(header, [decompressed block streams]) of a gzip or zstd spz file (the header without the v4 table of contents)."""
    if data[:2] == b"\x1f\x8b":
        raw = gzip.decompress(data)
        return raw[:16], [raw[16:]]
    streams, toc = data[15], struct.unpack_from("<I", data, 16)[0]
    sizes = np.frombuffer(data, "<u8", count=2 * streams, offset=toc).reshape(-1, 2)
    offset, out = toc + 16 * streams, []
    for compressed, _ in sizes:
        out.append(zstandard.ZstdDecompressor().decompress(data[offset:offset + int(compressed)]))
        offset += int(compressed)
    return data[:32], out


def alphas_of(data: bytes, points: int) -> np.ndarray:
    """The alpha bytes of a gzip spz (they follow 16 header bytes and 9 position bytes per point)."""
    raw = gzip.decompress(data)
    return np.frombuffer(raw, np.uint8, count=points, offset=16 + 9 * points)


@pytest.mark.parametrize("name", ["peer_v3.spz", "peer_v4.spz"])
def test_spz_writer_writes_the_spz_librarys_bytes(name):
    """The spz library (splat-transform 2.7.1's WASM build) wrote these files; read and written again by
    drsplat, every block comes back byte for byte (the header too), but for the 8 alphas the library
    stored as 0 and 255, which the reader takes half a step inside: they come back within one step."""
    peer = (PEERS / name).read_bytes()
    scene = load_scene(PEERS / name)
    ours, bits, clipped = spz_file_bytes(scene, int(name[6]))
    assert bits == 12 and clipped["colour"] == 0 and clipped["scale"] == 0
    (peer_header, peer_blocks), (our_header, our_blocks) = spz_payload(peer), spz_payload(ours)
    assert our_header == peer_header
    if name == "peer_v3.spz":
        a, b = alphas_of(peer, 120), alphas_of(ours, 120)
        extreme = (a == 0) | (a == 255)
        assert extreme.sum() == 8 and np.array_equal(a[~extreme], b[~extreme]) and np.abs(a.astype(int) - b).max() <= 1
        start, stop = 9 * 120, 10 * 120  # the alpha block, after the positions
        assert peer_blocks[0][:start] == our_blocks[0][:start] and peer_blocks[0][stop:] == our_blocks[0][stop:]
    else:
        assert len(our_blocks) == len(peer_blocks) == 6
        for i, (p, o) in enumerate(zip(peer_blocks, our_blocks)):
            if i != 1:  # alphas: as above
                assert p == o, f"block {i}"


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_spz_and_splat_writers_agree_with_splat_transform_now(tmp_path, degree):
    """With splat-transform on this machine (skipped otherwise): a fresh random scene packed by the
    spz library and by drsplat holds the same blocks (alphas: the libraries' float32 exp may differ
    by an ulp, so at most 0.2% of them one step apart), and splat-transform reads drsplat's .spz
    (versions 3 and 4) and .splat to the values drsplat reads."""
    command = splat_transform_command()
    scene = random_scene(3000, degree=degree, seed=40 + degree)
    save_ply(scene, tmp_path / "in.ply")
    subprocess.run([*command, "-q", "-w", str(tmp_path / "in.ply"), "--spz-version", "3", str(tmp_path / "lib.spz")],
                   check=True, timeout=120, capture_output=True)
    lib = (tmp_path / "lib.spz").read_bytes()
    ours = spz_file_bytes(scene, 3)[0]
    a, b = alphas_of(lib, 3000), alphas_of(ours, 3000)
    assert np.abs(a.astype(int) - b).max() <= 1 and np.count_nonzero(a != b) <= 6
    raw_lib, raw_ours = gzip.decompress(lib), gzip.decompress(ours)
    cut = 16 + 9 * 3000
    assert raw_lib[:cut] == raw_ours[:cut] and raw_lib[cut + 3000:] == raw_ours[cut + 3000:]
    for name in ("v3.spz", "v4.spz", "ours.splat"):
        path = tmp_path / name
        save_scene(scene, path, spz_version=int(name[1]) if name.endswith(".spz") else 3)
        subprocess.run([*command, "-q", "-w", str(path), str(tmp_path / "back.ply")], check=True, timeout=120, capture_output=True)
        peer, mine = load_ply(tmp_path / "back.ply"), load_scene(path)
        assert np.array_equal(peer.means, mine.means) and np.array_equal(peer.log_scales, mine.log_scales), name
        assert np.allclose(peer.sh, mine.sh, rtol=0, atol=2e-6), name
        assert np.abs(rotations(peer.quats) - rotations(mine.quats)).max() < (0.03 if name.endswith(".splat") else 1e-6), name


@pytest.mark.parametrize("kind", ["v3.spz", "v4.spz", "s.splat", "S.SPZ"])
@pytest.mark.parametrize("degree", [0, 1, 3])
def test_written_scenes_read_back_within_their_steps(tmp_path, kind, degree):
    """save_scene by the name, then load_scene: the same Gaussians in the same order, each field within
    its format's step; .splat keeps the base colour only."""
    scene = random_scene(300, degree=degree, seed=degree)
    scene.sh[:, 0] = np.clip(scene.sh[:, 0], -1.7, 1.7)  # inside what both formats' colour bytes hold
    scene.sh[:, 1:] = np.clip(scene.sh[:, 1:], -0.99, 0.99)
    path = tmp_path / kind
    written = save_scene(scene, path, spz_version=4 if kind.startswith("v4") else 3)
    assert written == ("splat" if kind.endswith(".splat") else "spz") == scene_format(path)
    back = load_scene(path)
    assert back.num_gaussians == scene.num_gaussians
    assert np.abs(opacities(back) - np.clip(opacities(scene), 0.5 / 255, 254.5 / 255)).max() <= 0.5 / 255 + 1e-6
    if written == "splat":
        assert back.sh_degree == 0 and np.array_equal(back.means, scene.means)
        assert np.allclose(back.log_scales, scene.log_scales, atol=1e-6)
        assert np.abs(back.sh[:, 0] - scene.sh[:, 0]).max() <= 0.5 / 255 / SH_C0 + 1e-6
        assert np.abs(rotations(back.quats) - rotations(scene.quats)).max() < 0.03
        return
    assert back.sh_degree == degree
    assert np.abs(back.means - scene.means).max() <= 2.0 ** -13 + 1e-6
    assert np.abs(back.log_scales - scene.log_scales).max() <= 1 / 32 + 1e-6
    assert np.abs(back.sh[:, 0] - scene.sh[:, 0]).max() <= 0.5 / (0.15 * 255) + 1e-5
    if degree:  # degree 1 in 5 bits (buckets of 8/128), the rest in 4 (16/128): half a bucket, and the 8-bit rounding
        step = np.where(np.arange(back.sh.shape[1] - 1) < 3, 4 / 128, 8 / 128)[None, :, None]
        assert np.all(np.abs(back.sh[:, 1:] - scene.sh[:, 1:]) <= step + 0.5 / 128 + 1e-6)
    assert np.abs(rotations(back.quats) - rotations(scene.quats)).max() < 0.006


def test_pack_smallest_three_matches_the_reference_loop():
    """The vectorised packing against tests/splat_codecs' per-row loop (the library's code) on random
    and hard quaternions: identity, a negative largest component, equal largest components (the first
    wins), components of exactly √½, tiny ones, each axis."""
    rng = np.random.default_rng(7)
    q = rng.normal(size=(4000, 4))
    h = np.sqrt(0.5)
    hard = np.array([[0, 0, 0, 1], [0, 0, 0, -1], [1, 0, 0, 0], [0, -1, 0, 0], [h, h, 0, 0], [-h, h, 0, 0], [0, h, -h, 0],
                     [0.5, 0.5, 0.5, 0.5], [-0.5, 0.5, -0.5, 0.5], [1e-30, 0, 0, 1], [1, 1e-8, -1e-8, 1e-8], [0, 0, h, -h]])
    q = np.concatenate([q, hard, rng.normal(size=(500, 4)) * (rng.random((500, 4)) < 0.5)])
    q = q[np.linalg.norm(q, axis=1) > 0]
    unit = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)
    assert np.array_equal(pack_smallest_three(unit), codec_pack_smallest_three(unit))


def test_a_far_splat_that_coarsens_its_chunk_neighbours_is_said(tmp_path, caplog):
    """Round 42 (left as found then): one splat at 1e30 widened its chunk's position range, and the
    compressed PLY stored its 255 neighbours ~1e26 from their places without a word. Now a warning
    counts the splats moved by more than their own size and 1% of the scene's extent; an ordinary
    scene (and a .ply) gets none."""
    scene = random_scene(1024, degree=0)
    with caplog.at_level(logging.WARNING, logger="drsplat.splat_formats"):
        save_scene(scene, tmp_path / "plain.compressed.ply")
    assert not caplog.records, caplog.text
    assert compressed_ply_bytes(scene)[1]["coarse position"] == 0
    scene.means[7] = (1e30, 0.0, 0.0)
    with caplog.at_level(logging.WARNING, logger="drsplat.splat_formats"):
        save_scene(scene, tmp_path / "far.compressed.ply")
    (record,) = caplog.records
    stored = load_scene(tmp_path / "far.compressed.ply").means.astype(np.float64)  # in Morton order, as written
    moved = np.linalg.norm(stored - scene.means[morton_order(scene.means)], axis=1)
    count = compressed_ply_bytes(scene)[1]["coarse position"]
    assert f"{count:,} splats are stored farther from their place" in record.getMessage() and "far.compressed.ply" in record.getMessage()
    assert 200 <= count <= 256 and np.count_nonzero(moved > 1.0) >= 200


def test_far_positions_get_fewer_fractional_bits_and_too_far_is_refused(tmp_path, caplog):
    """The library writes 12 fractional bits and wraps a coordinate beyond ±2048 around; drsplat stores
    such a scene with as many bits as fit (the header says how many) and refuses one beyond 24 bits."""
    scene = random_scene(50, degree=0)
    scene.means[0] = (1e5, -3e4, 7.0)
    scene.log_scales[:] = np.log(0.5)
    with caplog.at_level(logging.INFO, logger="drsplat.splat_formats"):
        save_spz(scene, tmp_path / "far.spz")
    assert "6 fractional bits" in caplog.text and all(r.levelno == logging.INFO for r in caplog.records), caplog.text
    caplog.clear()
    scene.log_scales[:] = np.log(0.05)  # rounded by up to 1/128: 16% of the Gaussians' size
    with caplog.at_level(logging.INFO, logger="drsplat.splat_formats"):
        save_spz(scene, tmp_path / "far-and-small.spz")
    (record,) = caplog.records
    assert record.levelno == logging.WARNING and "moves a Gaussian by up to 0.16 of the median Gaussian's size (0.05)" in record.getMessage()
    assert gzip.decompress((tmp_path / "far.spz").read_bytes())[13] == 6
    assert np.abs(load_scene(tmp_path / "far.spz").means - scene.means).max() <= 2.0 ** -7 + 1e-3
    scene.means[0, 0] = 2e7
    with pytest.raises(OutputError, match=r"too\.spz.*24-bit fixed point"):
        save_spz(scene, tmp_path / "too.spz")
    assert not (tmp_path / "too.spz").exists()


def test_non_finite_values_are_refused_and_clipping_is_counted(tmp_path, caplog):
    scene = random_scene(40, degree=1)
    scene.means[3, 1] = np.nan
    scene.log_scales[5:7, 0] = np.inf
    for name in ("bad.spz", "bad.splat"):
        with pytest.raises(OutputError, match=r"bad\.s.*1 Gaussians have non-finite means, 2 Gaussians have non-finite scales.*\.ply"):
            save_scene(scene, tmp_path / name)
        assert not (tmp_path / name).exists()
    scene = random_scene(40, degree=1)
    scene.sh[:4, 0, 0] = 9.0  # beyond both formats' colour bytes
    scene.log_scales[0] = (-12.0, 0.0, 7.0)  # beyond .spz's [-10, 5.94]
    with caplog.at_level(logging.WARNING, logger="drsplat.splat_formats"):
        save_scene(scene, tmp_path / "bright.spz")
        save_scene(scene, tmp_path / "bright.splat")
    assert "bright.spz: 4 colour values, 2 scale values clipped to what .spz holds" in caplog.text
    assert "bright.splat: " in caplog.text and "colour values clipped to what .splat holds" in caplog.text
    scene.log_scales[1] = (-120.0, 100.0, 0.0)  # exp() underflows / overflows float32: a 0 scale read back as log 0 = -inf
    save_scene(scene, tmp_path / "tiny.splat")
    (line,) = [line for line in caplog.text.splitlines() if "tiny.splat: " in line]
    assert "2 scale values clipped to what .splat holds" in line
    back = load_scene(tmp_path / "tiny.splat")
    assert back.num_gaussians == 40 and np.all(np.isfinite(back.log_scales))
    assert np.allclose(back.log_scales[1], (np.log(np.finfo(np.float32).smallest_normal), np.log(np.finfo(np.float32).max), 0.0), atol=1e-5)


def lattice_scene(n: int = 700, degree: int = 1) -> GaussianScene:
    """A scene made with integer arithmetic only (the same float32 bits on every machine): a spread of
    Gaussians, a third of them packed within 1e-5 units (Morton runs longer than 256 are ordered again),
    rotations with negative and tied largest components, log scales down to -25 (past the ±20 that a
    compressed PLY's ranges are clamped to), colours past what bytes hold."""
    i = np.arange(n, dtype=np.int64)
    means = np.stack([((i * 37) % 101) / 101.0 * 4.0 - 2.0, ((i * 53) % 97) / 97.0 * 3.0, ((i * 71) % 89) / 89.0 - 0.5], axis=1)
    means[: n // 3] = 0.5 + np.stack([(i[: n // 3] % 7), (i[: n // 3] % 5), (i[: n // 3] % 3)], axis=1) * 1e-6
    quats = np.stack([((i * 13) % 17) - 8, ((i * 19) % 23) - 11, ((i * 29) % 31) - 15, ((i * 7) % 11) - 5], axis=1) / 8.0
    quats[::50] = (0.5, -0.5, 0.5, -0.5)
    log_scales = np.stack([-7.0 + ((i * 29) % 41) / 41.0 * 8.0, -6.0 + ((i * 31) % 43) / 43.0 * 7.0, -25.0 + ((i * 3) % 47)], axis=1)
    logits = (((i * 11) % 23) - 11) / 2.0
    k = (degree + 1) ** 2
    sh = np.stack([(((i * (5 + j)) % (13 + 2 * j)) - (6 + j)) / (4.0 if j == 0 else 16.0) for j in range(k)], axis=1)
    sh = np.repeat(sh[:, :, None], 3, axis=2) * np.array([1.0, -0.5, 0.25])
    return GaussianScene(means=means.astype(np.float32), quats=quats.astype(np.float32), log_scales=log_scales.astype(np.float32),
                         opacity_logits=logits.astype(np.float32), sh=sh.astype(np.float32))


def after_header_comment(data: bytes) -> bytes:
    """A PLY's bytes without its comment lines (the writer's name)."""
    head, _, body = data.partition(b"end_header\n")
    return b"\n".join(line for line in head.split(b"\n") if not line.startswith(b"comment ")) + b"end_header\n" + body


def test_compressed_ply_writer_writes_splat_transforms_bytes(tmp_path):
    """PlayCanvas splat-transform 2.7.1 wrote peer.compressed.ply from lattice_scene(); drsplat's writer
    gives the same bytes but the header's comment (its Morton order, chunk ranges and packing), and
    the file reads back, in Morton order, within the chunks' steps."""
    scene = lattice_scene()
    peer = (PEERS / "peer.compressed.ply").read_bytes()
    assert after_header_comment(compressed_ply_bytes(scene)[0]) == after_header_comment(peer)
    path = tmp_path / "mine.COMPRESSED.PLY"
    assert save_scene(scene, path) == "compressed.ply" == written_format(path)
    back, report = load_scene_report(path)
    assert report.layout == load_scene_report(PEERS / "peer.compressed.ply")[1].layout and back.num_gaussians == 700
    ordered = scene.subset(morton_order(scene.means))  # the file holds the splats in Morton order
    assert np.abs(back.means - ordered.means).max() <= 4.0 / 2047 and np.abs(back.sh[:, 1:] - ordered.sh[:, 1:]).max() <= 8 / 256
    assert written_format(tmp_path / "compressed.ply") == "ply", "a file named only .compressed.ply is a plain PLY"
    scene.quats[:5] = 0.0  # the identity, as the loaders read a zero quaternion
    save_scene(scene, path)
    assert np.allclose(np.abs(load_scene(path).unit_quats()[np.isin(morton_order(scene.means), np.arange(5))]), [1, 0, 0, 0], atol=2e-3)


@pytest.mark.parametrize("degree", [0, 3])
def test_compressed_ply_writer_agrees_with_splat_transform_now(tmp_path, degree):
    """With splat-transform on this machine (skipped otherwise): random scenes with a tight cluster, the
    same bytes but the header's comment."""
    command = splat_transform_command()
    scene = random_scene(2000, degree=degree, seed=60 + degree)
    scene.means[:700] = scene.means[:700] * 1e-6 + 0.5
    save_ply(scene, tmp_path / "in.ply")
    subprocess.run([*command, "-q", "-w", str(tmp_path / "in.ply"), str(tmp_path / "lib.compressed.ply")], check=True, timeout=120, capture_output=True)
    ours = compressed_ply_bytes(load_ply(tmp_path / "in.ply"))[0]
    assert after_header_comment(ours) == after_header_comment((tmp_path / "lib.compressed.ply").read_bytes())


@pytest.mark.parametrize("name", ["e.spz", "e4.spz", "e.splat", "e.ply", "e.compressed.ply"])
def test_a_written_scene_of_no_gaussians_reads_back_empty_with_a_finding(tmp_path, name):
    """A version-4 spz of no points has no streams at all (empty blocks have none); its reader used to
    fail there with a KeyError. Every file type reads back as no Gaussians, with the same finding."""
    save_scene(random_scene(3).subset(np.zeros(3, bool)), tmp_path / name, spz_version=4 if name == "e4.spz" else 3)
    back, report = load_scene_report(tmp_path / name)
    assert back.num_gaussians == 0 and any("holds no Gaussians" in note for note in report.findings())


def test_writing_spz_versions_other_than_3_and_4_is_refused(tmp_path):
    with pytest.raises(ValueError, match="version 2 cannot be written"):
        save_spz(random_scene(4), tmp_path / "x.spz", version=2)


# ---------------------------------------------------------------------------------------------- what the file says


def test_spz_sh_degree_4_keeps_degree_3_with_a_warning(tmp_path, caplog):
    scene = random_scene(16, degree=3)
    data = gzip.decompress(encode_spz(scene))  # degree 3 blocks; rebuild with degree 4's 24 coefficients
    header, body = data[:16], data[16:]
    n = 16
    sizes = [n * 9, n, n * 3, n * 3, n * 4]
    fixed = body[: sum(sizes)]
    sh3 = np.frombuffer(body[sum(sizes):], np.uint8).reshape(n, 15, 3)
    sh4 = np.concatenate([sh3, np.full((n, 9, 3), 192, np.uint8)], axis=1)
    raw = bytearray(header)
    raw[12] = 4
    path = write(tmp_path / "four.spz", gzip.compress(bytes(raw) + fixed + sh4.tobytes()))
    with caplog.at_level(logging.WARNING):
        back = load_scene(path)
    assert back.sh_degree == 3 and np.allclose(back.sh, load_scene(write(tmp_path / "three.spz", encode_spz(scene))).sh)
    assert "SH degree 4" in caplog.text


def test_spz_antialiased_flag_and_unknown_extensions_are_said(tmp_path, caplog):
    scene = random_scene(8)
    other = extension_record(0xADBE0002, struct.pack("<fff", 0.0, 1.0, 2.0))  # camera limits: skipped
    for version in (3, 4):
        with caplog.at_level(logging.INFO):
            back = load_scene(write(tmp_path / f"a{version}.spz", encode_spz(scene, version, antialiased=True, extensions=other)))
        assert back.num_gaussians == 8
        assert "anti-aliasing" in caplog.text and "0xADBE0002" in caplog.text
        caplog.clear()


def test_spz_frames_agree(tmp_path):
    """The same scene stored in four frames reads back to the same Gaussians (up to the rounding each frame's signs leave)."""
    scene = random_scene(32)
    reads = [load_scene(write(tmp_path / f"f{f}.spz", encode_spz(scene, 3, f))) for f in (4, 6, 7, 2)]
    for other in reads[1:]:
        assert np.abs(other.means - reads[0].means).max() <= 2.0 ** -12
        assert np.abs(other.sh - reads[0].sh).max() <= 1 / 128 + 1e-6
        assert np.abs(rotations(other.quats) - rotations(reads[0].quats)).max() < 0.006


# ---------------------------------------------------------------------------------------------- hostile files


def spz_cases(scene: GaussianScene) -> dict[str, tuple[bytes, str]]:
    """name -> (file bytes, a phrase the one error must hold)."""
    v3, v4 = encode_spz(scene, 3), encode_spz(scene, 4)
    body3 = gzip.decompress(v3)
    toc = struct.unpack_from("<I", v4, 16)[0]

    def header4(**changes):
        fields = dict(zip(("magic", "version", "points", "degree", "bits", "flags", "streams", "toc"), struct.unpack_from("<IIIBBBBI", v4)))
        fields.update(changes)
        return struct.pack("<IIIBBBBI", *fields.values()) + v4[20:]

    def toc_sizes_past_2_to_the_63():  # round 101a F1: two sizes + 2^63 summed, in uint64, to the true total
        raw = bytearray(v4)
        for i in (0, 1):
            struct.pack_into("<Q", raw, toc + 16 * i, struct.unpack_from("<Q", raw, toc + 16 * i)[0] + 2**63)
        return bytes(raw)

    return {
        "truncated gzip": (v3[: len(v3) // 2], "truncated"),
        "gzip of something else": (gzip.compress(b"hello world, not a splat"), "without the spz header"),
        "gzip shorter than a header": (gzip.compress(b"NGSP"), "fewer than the 16-byte"),
        "version 9": (gzip.compress(body3[:4] + struct.pack("<I", 9) + body3[8:]), "version 9"),
        "SH degree 7": (gzip.compress(body3[:12] + bytes([7]) + body3[13:]), "SH degree 7"),
        "points beyond the data": (gzip.compress(body3[:8] + struct.pack("<I", 40) + body3[12:]), "truncated"),
        "a billion points": (gzip.compress(body3[:8] + struct.pack("<I", 1_000_000_000) + body3[12:]), "damaged header"),
        "damaged deflate": (v3[:20] + bytes(b ^ 0xFF for b in v3[20:40]) + v3[40:], "gzip"),
        "v4 toc past the end": (header4(toc=10_000), "table of contents"),
        "v4 toc inside the header": (header4(toc=8), "table of contents"),
        "v4 stream count": (header4(streams=3), "streams"),
        "v4 truncated": (v4[:-10], "truncated or damaged"),
        "v4 a billion points": (header4(points=1_000_000_000), "damaged header"),
        "v4 shorter than a header": (v4[:20], "shorter than the 32-byte"),
        "v4 damaged stream": (v4[: toc + 16 * 6 + 4] + b"\x00" * 8 + v4[toc + 16 * 6 + 12:], "positions"),
        "v4 with a version-3 number": (header4(version=3), "versions 1-3 are gzip"),
        "v4 stream sizes past 2^63": (toc_sizes_past_2_to_the_63(), "bytes of streams but holds"),
        "extension record cut": (gzip.compress(body3[:14] + bytes([2]) + body3[15:] + struct.pack("<II", 0x1234, 99) + b"ab"), "past the end"),
        "rotated frame": (encode_spz(scene, 3, extensions=extension_record(COORDINATE_EXTENSION, struct.pack("<I", 12))), "rotated frame"),
    }


@pytest.mark.parametrize("case", list(spz_cases(random_scene(16))))
def test_hostile_spz_is_one_error_naming_the_file(tmp_path, case, capsys):
    data, phrase = spz_cases(random_scene(16))[case]
    path = write(tmp_path / "bad.spz", data)
    with pytest.raises(InputError) as info:
        load_scene(path)
    assert str(path) in str(info.value) and phrase in str(info.value), str(info.value)
    assert main(["info", str(path)]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and "bad.spz" in err


def test_a_file_named_spz_that_is_not_one_says_so(tmp_path):
    for name, data in (("empty.spz", b""), ("text.spz", b"hello, not a splat at all, nor a ply")):
        with pytest.raises(InputError, match="is not an .spz file: it starts neither with gzip's bytes"):
            load_scene(write(tmp_path / name, data))


def test_hostile_splat_files(tmp_path):
    scene = random_scene(4, degree=0)
    cut = write(tmp_path / "cut.splat", encode_splat(scene)[:-5])
    with pytest.raises(InputError, match=r"not a whole number of 32-byte \.splat records \(3 records and 27 bytes\)"):
        load_scene(cut)
    empty = write(tmp_path / "empty.splat", b"")
    scene0, report = load_scene_report(empty)
    assert scene0.num_gaussians == 0 and any("no Gaussians" in f for f in report.findings())
    raw = np.frombuffer(encode_splat(scene), np.uint8).copy().reshape(4, 32)
    raw[0, 12:16] = np.frombuffer(np.float32(0.0).tobytes(), np.uint8)  # a zero scale: log is -inf
    raw[1, 0:4] = np.frombuffer(np.float32(np.nan).tobytes(), np.uint8)
    back, report = load_scene_report(write(tmp_path / "odd.splat", raw.tobytes()))
    assert back.num_gaussians == 2 and report.dropped_nan_rows == 1 and report.dropped_inf_rows == 1


def test_a_splat_row_with_a_negative_scale_reads_as_its_magnitude_and_is_said(tmp_path):
    """Was (round 46, left as found): a `.splat` scale below 0 took a NaN log and its row was dropped
    as one "with NaN values". A viewer's covariance R S² Rᵀ holds each scale's square, so the row
    draws as the scale's magnitude: it is read so, and counted in its own finding."""
    scene = random_scene(4, degree=0)
    raw = np.frombuffer(encode_splat(scene), np.uint8).copy().reshape(4, 32)
    scales = raw[:, 12:24].copy().view(np.float32)  # [4, 3]
    flipped = scales.copy()
    flipped[1, 0] *= -1
    flipped[3] *= -1
    raw[:, 12:24] = flipped.view(np.uint8)
    back, report = load_scene_report(write(tmp_path / "signed.splat", raw.tobytes()))
    plain, _ = load_scene_report(write(tmp_path / "plain.splat", encode_splat(scene)))
    assert back.num_gaussians == 4 and report.dropped_nan_rows == 0 and report.negative_scales == 2
    np.testing.assert_array_equal(back.log_scales, plain.log_scales)
    assert any(f.startswith("2 rows have a negative scale, read as its magnitude") for f in report.findings())
    flipped[0, 1] = -np.inf  # dropped as an infinite scale, not read as a magnitude: not counted as one
    raw[:, 12:24] = flipped.view(np.uint8)
    back, report = load_scene_report(write(tmp_path / "inf.splat", raw.tobytes()))
    assert back.num_gaussians == 3 and report.dropped_inf_rows == 1 and report.negative_scales == 2


def test_trailing_bytes_in_a_gzip_spz_are_warned(tmp_path, caplog):
    scene = random_scene(8)
    body = gzip.decompress(encode_spz(scene, 3))
    with caplog.at_level(logging.WARNING):
        back = load_scene(write(tmp_path / "t.spz", gzip.compress(body + b"\x00" * 40)))
    assert back.num_gaussians == 8 and "40 bytes follow the 8 points" in caplog.text


# ---------------------------------------------------------------------------------------------- commands


def test_commands_read_splat_and_spz_scenes(tmp_path, capsys):
    """info, register and the viewer's state take the scene as .splat or .spz: registering a .splat
    gives the same bytes as registering the PLY of the Gaussians it decodes to."""
    from drsplat.synthetic import write_dataset
    from viewer.state import ViewerState

    dataset = write_dataset(tmp_path / "tiny", "tiny", 0, show_progress=False)
    scene = load_ply(dataset / "scene.ply")
    splat = write(tmp_path / "scene.splat", encode_splat(scene))
    spz = write(tmp_path / "scene.spz", encode_spz(scene, 4))
    assert main(["info", str(spz), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["layout"] == "spz v4" and summary["num_gaussians"] == scene.num_gaussians and summary["findings"] == []
    decoded = tmp_path / "decoded.ply"
    save_ply(load_scene(splat), decoded)
    outs = []
    for src in (splat, decoded):
        out_path = tmp_path / f"reg-{src.suffix[1:]}.ply"
        assert main(["register", str(src), "--source", str(dataset), "--features", str(dataset / "features"), "--out", str(out_path),
                     "--no-progress", "-q"]) == 0
        outs.append(out_path.read_bytes())
    assert outs[0] == outs[1]
    state = ViewerState()
    assert state.load_scene(spz) and state.scene.num_gaussians == scene.num_gaussians


def test_mutated_spz_files_load_or_fail_with_one_input_error(tmp_path):
    """300 random byte flips, cuts and insertions of v2, v3 and v4 files (fixed seed): each loads, or
    raises InputError naming the file; nothing else escapes."""
    rng = np.random.default_rng(0)
    scene = random_scene(12)
    path = tmp_path / "m.spz"
    outcomes = {"loaded": 0, "refused": 0}
    for version in (2, 3, 4):
        base = encode_spz(scene, version)
        for _ in range(100):
            data = bytearray(base)
            op = rng.integers(0, 3)
            if op == 0:
                for _ in range(rng.integers(1, 4)):
                    data[rng.integers(0, len(data))] = rng.integers(0, 256)
            elif op == 1:
                data = data[: rng.integers(0, len(data))]
            else:
                at = rng.integers(0, 40)
                data[at:at] = rng.integers(0, 256, rng.integers(1, 9)).astype(np.uint8).tobytes()
            path.write_bytes(bytes(data))
            try:
                load_scene(path)
                outcomes["loaded"] += 1
            except InputError as exc:
                assert str(path) in str(exc)
                outcomes["refused"] += 1
    assert outcomes["refused"] > 150 and sum(outcomes.values()) == 300


# ---------------------------------------------------------------------------------------------- round 41


def _with_sh_element_as(path: Path, out: Path, dtype: str, values=None) -> None:
    """`path`'s compressed PLY with its 'sh' element's columns retyped to `dtype` (plyfile), holding `values` or the codes."""
    from plyfile import PlyData, PlyElement

    ply = PlyData.read(str(path))
    sh = ply["sh"].data
    names = sh.dtype.names
    table = np.empty(len(sh), dtype=[(k, dtype) for k in names])
    for k in names:
        table[k] = sh[k] if values is None else values
    elements = [e if e.name != "sh" else PlyElement.describe(table, "sh") for e in ply.elements]
    PlyData(elements, text=False, byte_order="<").write(str(out))


def test_a_compressed_plys_sh_codes_are_bytes_whatever_their_declared_type(tmp_path):
    """Round 41: a compressed PLY whose 'sh' element was rewritten as char, or as float holding real coefficients,
    loaded without a word: SH off by up to 8. Codes typed char read as the same bytes; a column of non-codes is one
    error naming it."""
    scene = random_scene(300, degree=2)
    save_scene(scene, tmp_path / "c.compressed.ply")
    base = load_scene(tmp_path / "c.compressed.ply")
    _with_sh_element_as(tmp_path / "c.compressed.ply", tmp_path / "char.compressed.ply", "i2")
    np.testing.assert_array_equal(load_scene(tmp_path / "char.compressed.ply").sh, base.sh)
    _with_sh_element_as(tmp_path / "c.compressed.ply", tmp_path / "real.compressed.ply", "f4", values=0.37)
    with pytest.raises(InputError, match="f_rest_0"):
        load_scene(tmp_path / "real.compressed.ply")


def test_a_compressed_ply_of_opaque_and_clear_splats_reads_back_without_infinities(tmp_path):
    """Round 41: opacity bytes 0 and 255 decoded to logits of -inf and +inf, so re-reading drsplat's own export of a
    scene with logits of +-10 found "5 infinite opacity logits clamped"; they are read half a step inside, as .splat
    and .spz read theirs."""
    scene = random_scene(6)
    scene.opacity_logits[:] = [10, -10, 10, -10, 10, 0.5]
    save_scene(scene, tmp_path / "c.compressed.ply")
    back, report = load_scene_report(tmp_path / "c.compressed.ply")
    assert report.findings() == [] and np.isfinite(back.opacity_logits).all()
    assert back.opacity_logits.max() == pytest.approx(np.log(254.5 / 0.5), abs=1e-5) and back.opacity_logits.min() == pytest.approx(-np.log(254.5 / 0.5), abs=1e-5)


@pytest.mark.parametrize("suffix", [".splat", ".spz", ".compressed.ply"])
def test_every_alpha_byte_read_is_written_back_as_itself(tmp_path, suffix):
    """Round 85b F1: a .splat alpha of 255, read as 254.5/255, was written back as 254 (255·σ in float32 is 254.49999),
    so every fully opaque splat lost a step each time a .splat went through drsplat. Each of the 256 bytes, read from
    one file of the format and written to another, is the same byte."""
    scene = random_scene(256)
    scene.opacity_logits[:] = np.log(np.clip(np.arange(256), 0.5, 254.5) / (255.0 - np.clip(np.arange(256), 0.5, 254.5)))
    save_scene(scene, tmp_path / f"a{suffix}")
    first = load_scene(tmp_path / f"a{suffix}")
    save_scene(first, tmp_path / f"b{suffix}")
    second = load_scene(tmp_path / f"b{suffix}")
    order = np.lexsort(first.means.T)  # the compressed format stores its rows in Morton order
    again = np.lexsort(second.means.T)
    assert np.array_equal(first.opacity_logits[order], second.opacity_logits[again])
    assert np.unique(first.opacity_logits).size == 256


def test_log_scales_the_compressed_format_clamps_are_counted(tmp_path, caplog):
    """Round 41: a log scale of 25 read back as 20 without a word; .spz counted its clipping already."""
    scene = random_scene(8)
    scene.log_scales[:2, 0] = [25.0, -23.0]
    with caplog.at_level(logging.WARNING):
        save_scene(scene, tmp_path / "c.compressed.ply")
    assert "2 log scale" in caplog.text, caplog.text
    assert np.abs(load_scene(tmp_path / "c.compressed.ply").log_scales).max() <= 20.0 + 1e-5


def test_a_compressed_ply_with_more_chunks_than_its_splats_use_is_said(tmp_path):
    """Round 41, left as found then: a compressed PLY of 300 splats' chunks whose vertex and sh elements were cut to
    200 rows (a vertex count smaller than the data) loaded without a word. The spare chunk is a finding."""
    from plyfile import PlyData, PlyElement
    save_scene(random_scene(600, degree=1), tmp_path / "c.compressed.ply")
    ply = PlyData.read(str(tmp_path / "c.compressed.ply"))
    cut = [e if e.name == "chunk" else PlyElement.describe(e.data[:200], e.name) for e in ply.elements]
    PlyData(cut, text=False, byte_order="<").write(str(tmp_path / "cut.compressed.ply"))
    scene, report = load_scene_report(tmp_path / "cut.compressed.ply")
    assert len(scene) == 200 and report.spare_chunks == 2
    assert any("3 chunks where its 200 splats use 1" in note for note in report.findings()), report.findings()
    assert load_scene_report(tmp_path / "c.compressed.ply")[1].findings() == []


@pytest.mark.parametrize("name, content, expected", [
    ("scene.ply.gz", gzip.compress(b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nend_header\n", mtime=0),
     "is a gzip-compressed PLY file: decompress it first"),
    ("scene.ksplat", b"\x01\x00" + b"\x00" * 100, "(a .ksplat file: convert it to PLY first"),
    ("scene.sog", b"PK\x03\x04" + b"\x00" * 100, "(a .sog file: convert it to PLY first"),
    ("scene.bin", b"\x00" * 100, "is not a PLY file (it does not start with 'ply'); drsplat reads PLY"),
], ids=["ply.gz", "ksplat", "sog", "bin"])  # the same names in every process (pytest-xdist compares its workers' collections)
def test_scene_files_of_formats_drsplat_does_not_read_say_what_it_reads(tmp_path, name, content, expected):
    """Round 41, left as found then: scene.ply.gz was "a gzip file without the spz header", and .ksplat / .sog files
    "not a PLY file" without a word on what is read."""
    (tmp_path / name).write_bytes(content)
    with pytest.raises(InputError, match=re.escape(expected)) as info:
        load_scene(tmp_path / name)
    assert name in str(info.value) and ".spz" in str(info.value)


def test_a_compressed_plys_sh_codes_typed_char_read_as_their_bytes(tmp_path):
    """Review of round 41: its test retyped the codes as short (i2), which the reader before the mend read right too;
    char (i1) is the type that changed the values: codes 128..255 stored as -128..-1 are the same bytes."""
    scene = random_scene(300, degree=2)
    save_scene(scene, tmp_path / "c.compressed.ply")
    base = load_scene(tmp_path / "c.compressed.ply")
    from plyfile import PlyData

    codes = np.stack([PlyData.read(str(tmp_path / "c.compressed.ply"))["sh"].data[f"f_rest_{i}"] for i in range(24)])
    assert codes.max() > 127  # some codes wrap when typed char
    _with_sh_element_as(tmp_path / "c.compressed.ply", tmp_path / "char.compressed.ply", "i1")
    np.testing.assert_array_equal(load_scene(tmp_path / "char.compressed.ply").sh, base.sh)


@pytest.mark.parametrize("value", [-1.0, -2.0])
def test_a_float_sh_column_of_negative_whole_coefficients_is_refused_not_read_as_codes(tmp_path, value):
    """Review of round 41: a compressed PLY whose 'sh' element holds real coefficients as float passed the check when
    they were whole numbers: -1.0 was read as byte 255 (a coefficient of +4.0). A float holds a value, and a negative
    value is no byte code."""
    save_scene(random_scene(300, degree=2), tmp_path / "c.compressed.ply")
    _with_sh_element_as(tmp_path / "c.compressed.ply", tmp_path / "real.compressed.ply", "f4", values=value)
    with pytest.raises(InputError, match=rf"field 'f_rest_0': property f_rest_0 is declared float and row 0 holds {value!r}, which is not a whole number in 0\.\.255"):
        load_scene(tmp_path / "real.compressed.ply")


def test_a_compressed_ply_of_a_scene_spanning_past_float32_reads_back_every_gaussian(tmp_path):
    """Review of round 41: drsplat's own compressed PLY of a finite scene with means at +-3e38 put both in one chunk,
    whose range (6e38) overflowed float32 as it was read: numpy's "overflow encountered in subtract" and "invalid
    value encountered in multiply", and all 6 Gaussians dropped as NaN or infinite."""
    import warnings

    scene = random_scene(6)
    scene.means[0], scene.means[1] = [3e38, 0, 0], [-3e38, 0, 0]
    save_scene(scene, tmp_path / "far.compressed.ply")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back, report = load_scene_report(tmp_path / "far.compressed.ply")
    assert back.num_gaussians == 6 and np.isfinite(back.means).all()
    assert (back.means[:, 0].min(), back.means[:, 0].max()) == pytest.approx((-3e38, 3e38), rel=1e-6)
    assert not any("dropped" in note for note in report.findings())


@pytest.mark.parametrize("column, value", [("min_x", np.inf), ("max_scale_y", -np.inf), ("min_r", np.inf)])
def test_a_compressed_chunk_range_that_is_infinite_drops_its_splats_without_numpys_warnings(tmp_path, column, value, caplog):
    """Review of round 41: an infinite chunk range printed numpy's "invalid value encountered in multiply" before the
    loader's own count of the rows it dropped. Round 85b F6: the counts named no chunk or property ("1 row with NaN
    values" of a file that holds none): a warning names them."""
    import logging
    import warnings

    from plyfile import PlyData, PlyElement

    save_scene(random_scene(300, degree=0), tmp_path / "c.compressed.ply")
    ply = PlyData.read(str(tmp_path / "c.compressed.ply"))
    chunk = ply["chunk"].data.copy()
    chunk[column][0] = value
    elements = [e if e.name != "chunk" else PlyElement.describe(chunk, "chunk") for e in ply.elements]
    PlyData(elements, text=False, byte_order="<").write(str(tmp_path / "inf.compressed.ply"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with caplog.at_level(logging.WARNING):
            back, report = load_scene_report(tmp_path / "inf.compressed.ply")
    assert back.num_gaussians < 300 and any("dropped" in note for note in report.findings())
    assert f"field '{column}': 1 of 2 chunks hold a range bound that is not finite (chunk 0: {value:g})" in caplog.text, caplog.text
    assert "mirrored" not in caplog.text, "round 86c F5: a non-finite bound is no mirrored range"


def test_an_spz_whose_fixed_point_grid_is_coarse_is_a_load_finding(tmp_path):
    """Round 90b F2: a .spz 1.5e5 units out keeps positions in steps of 1/32 (5 fractional bits): its save warned that
    they move by up to 0.14 of the median Gaussian's size, but its load said "findings none" (float32's own step there
    is finer); 1e6 out, the finding named float32's step (0.0625), half the file's 0.125."""
    import dataclasses

    from drsplat.testing import random_scene

    base = random_scene(np.random.default_rng(0), 400, log_scale=(-2.5, -2.0))
    for shift, step in ((1.5e5, 2.0 ** -5), (1e6, 2.0 ** -3)):
        save_spz(dataclasses.replace(base, means=(base.means.astype(np.float64) + shift).astype(np.float32)), tmp_path / "far.spz")
        _, report = load_scene_report(tmp_path / "far.spz")
        assert report.coarse_positions is not None and report.coarse_positions[1] == step and report.coarse_positions[3], report.coarse_positions
        assert any(f"where the file stores them in steps of {step:.3g}" in note for note in report.findings()), report.findings()
    save_spz(base, tmp_path / "near.spz")
    assert load_scene_report(tmp_path / "near.spz")[1].coarse_positions is None
