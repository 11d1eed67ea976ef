"""Test-side encoders of `.splat` and `.spz`, written from the formats' reference writers (antimatter15's
convert.py; the spz library's packGaussians) and independent of drsplat.splat_formats' decoders, so
that decode(encode(scene)) checks the readers against the formats rather than against themselves."""

from __future__ import annotations

import gzip
import struct

import numpy as np
import zstandard

from drsplat.scene import SH_C0, GaussianScene

FRAME_NAMES = {1: "LDB", 2: "RDB", 3: "LUB", 4: "RUB", 5: "LDF", 6: "RDF", 7: "LUF", 8: "RUF"}
COORDINATE_EXTENSION = 0xADBE0003


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))


def encode_splat(scene: GaussianScene) -> bytes:
    """antimatter15's convert.py: float32 position and exp(scale), uint8 rgba and 128 + 128·q̂ (truncated)."""
    n = scene.num_gaussians
    out = np.zeros(n, [("p", "<f4", (3,)), ("s", "<f4", (3,)), ("c", "u1", (4,)), ("r", "u1", (4,))])
    out["p"] = scene.means
    out["s"] = np.exp(scene.log_scales.astype(np.float64))
    color = np.concatenate([0.5 + SH_C0 * scene.sh[:, 0].astype(np.float64), sigmoid(scene.opacity_logits)[:, None]], axis=1)
    out["c"] = (color * 255).clip(0, 255).astype(np.uint8)
    q = scene.quats.astype(np.float64)
    out["r"] = (q / np.linalg.norm(q, axis=1, keepdims=True) * 128 + 128).clip(0, 255).astype(np.uint8)
    return out.tobytes()


def frame_signs(frame: int) -> np.ndarray:
    """Axis signs between PLY's right-down-front and an spz frame (LDB ... RUF)."""
    name = FRAME_NAMES[frame]
    return np.array([1.0 if name[0] == "R" else -1.0, 1.0 if name[1] == "D" else -1.0, 1.0 if name[2] == "F" else -1.0])


def sh_parity(signs: np.ndarray, degree: int) -> np.ndarray:
    """Signs of the 3DGS real SH basis functions of degrees 1..degree under the axis flip, found by
    evaluating the basis polynomials at random directions d and at F·d (constants do not matter)."""
    d = np.random.default_rng(0).normal(size=(16, 3))

    def basis(v):
        x, y, z = v[:, 0], v[:, 1], v[:, 2]
        return np.stack([y, z, x, x * y, y * z, 2 * z * z - x * x - y * y, x * z, x * x - y * y,
                         y * (3 * x * x - y * y), x * y * z, y * (4 * z * z - x * x - y * y), z * (2 * z * z - 3 * x * x - 3 * y * y),
                         x * (4 * z * z - x * x - y * y), z * (x * x - y * y), x * (x * x - 3 * y * y)], axis=1)

    ratio = basis(d * signs) / basis(d)
    assert np.allclose(np.abs(ratio), 1.0)
    return np.sign(ratio[0])[: (degree + 1) ** 2 - 1]


def to_uint8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x), 0, 255).astype(np.uint8)


def pack_smallest_three(q_xyzw: np.ndarray) -> np.ndarray:
    """The spz library's packQuaternionSmallestThree, per row of unit quaternions, in its float32
    arithmetic (the largest |component| by a strict > scan, so the first of equal ones)."""
    out = np.empty(q_xyzw.shape[0], np.uint32)
    half = np.float32(0.707106781186547524401)
    for row, q in enumerate(np.asarray(q_xyzw, np.float32)):
        largest = 0
        for i in range(1, 4):
            if abs(q[i]) > abs(q[largest]):
                largest = i
        negate = q[largest] < 0
        comp = largest
        for i in range(4):
            if i != largest:
                negbit = int((q[i] < 0) ^ negate)
                mag = int(np.float32(511.0) * (np.abs(q[i]) / half) + np.float32(0.5))
                comp = (comp << 10) | (negbit << 9) | mag
        out[row] = comp
    return out


def spz_blocks(scene: GaussianScene, version: int, frame: int, fractional_bits: int) -> list[bytes]:
    """positions, alphas, colors, scales, rotations, sh of a scene stored in `frame` (packGaussians)."""
    s = frame_signs(frame)
    means = scene.means.astype(np.float64) * s
    if version == 1:
        positions = means.astype("<f2").tobytes()
    else:
        fixed = np.round(means * (1 << fractional_bits)).astype(np.int64) & 0xFFFFFF
        positions = np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, (fixed >> 16) & 0xFF], axis=-1).astype(np.uint8).tobytes()
    alphas = to_uint8(sigmoid(scene.opacity_logits) * 255).tobytes()
    colors = to_uint8(scene.sh[:, 0].astype(np.float64) * (0.15 * 255) + 0.5 * 255).tobytes()
    scales = to_uint8((scene.log_scales.astype(np.float64) + 10) * 16).tobytes()
    q = scene.quats.astype(np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    xyzw = np.concatenate([q[:, 1:], q[:, :1]], axis=1) * np.array([s[1] * s[2], s[0] * s[2], s[0] * s[1], 1.0])
    if version >= 3:
        rotations = pack_smallest_three(xyzw).astype("<u4").tobytes()
    else:
        xyz = xyzw[:, :3] * np.where(xyzw[:, 3:] < 0, -127.5, 127.5) + 127.5
        rotations = to_uint8(xyz).tobytes()
    degree = scene.sh_degree
    rest = scene.sh[:, 1:].astype(np.float64) * sh_parity(s, degree)[None, :, None] if degree else np.zeros((scene.num_gaussians, 0, 3))
    sh = to_uint8(rest * 128 + 128).tobytes()
    return [positions, alphas, colors, scales, rotations, sh]


def extension_record(kind: int, payload: bytes) -> bytes:
    return struct.pack("<II", kind, len(payload)) + payload


def encode_spz(scene: GaussianScene, version: int = 3, frame: int = 4, extensions: bytes = b"", antialiased: bool = False,
               fractional_bits: int = 12, points: int | None = None, sh_degree: int | None = None) -> bytes:
    """An .spz of the scene: versions 1-3 gzip (header, blocks, extension records), 4 the zstd layout.
    `frame` != RUB adds a coordinate-system extension record; points / sh_degree override the header's."""
    if frame != 4:
        extensions = extension_record(COORDINATE_EXTENSION, struct.pack("<I", frame)) + extensions
    flags = (1 if antialiased else 0) | (2 if extensions else 0)
    n = scene.num_gaussians if points is None else points
    degree = scene.sh_degree if sh_degree is None else sh_degree
    blocks = spz_blocks(scene, version, frame, fractional_bits)
    if version < 4:
        header = struct.pack("<IIIBBBB", 0x5053474E, version, n, degree, fractional_bits, flags, 0)
        return gzip.compress(header + b"".join(blocks) + extensions)
    streams = [zstandard.ZstdCompressor().compress(b) for b in blocks if b]
    sizes = [len(b) for b in blocks if b]
    toc_offset = 32 + len(extensions)
    header = struct.pack("<IIIBBBBI", 0x5053474E, version, n, degree, fractional_bits, flags, len(streams), toc_offset) + bytes(12)
    toc = b"".join(struct.pack("<QQ", len(c), u) for c, u in zip(streams, sizes))
    return header + extensions + toc + b"".join(streams)
