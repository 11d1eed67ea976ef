"""Scene files beyond PLY: the antimatter15 `.splat` and Niantic `.spz` (versions 1-4), read into a
`GaussianScene`; `load_scene` picks the reader (`scene_format`: PLY by its first line, `.splat`, which
has no header, by its name, spz by its first bytes). `save_scene` writes a scene as the file type its
name asks for (`.splat`; `.spz` versions 3 and 4, the spz library's packing; else PLY).

`.splat` (web viewers; no header): N records of 32 bytes, little-endian,

    position  3 x float32       the mean
    scale     3 x float32       exp(log scale), linear
    rgba      4 x uint8         rgb = 255·(0.5 + SH_C0·f_dc), a = 255·σ(opacity logit)
    rotation  4 x uint8         128 + 128·q̂, q̂ the unit quaternion (w, x, y, z)

decoded as f_dc = (rgb/255 - 0.5) / SH_C0, q = (byte - 128) / 128 (the exact inverse of the reference
converter's encoding; PlayCanvas splat-transform maps a byte b to b/127.5 - 1 instead, up to 1/128 apart
per component before normalisation) and log scale = log(scale). No higher SH.

`.spz` (Niantic; Scaniverse): versions 1-3 are one gzip stream holding a 16-byte header (magic "NGSP",
version, N, SH degree, fractional bits, flags) and then, point by point within each, the blocks

    positions  N x 3 x 24-bit signed fixed point (· 2^-fractional bits; v1: float16)
    alphas     N x uint8        a = 255·σ(opacity logit)
    colors     N x 3 x uint8    c = 255·(0.15·f_dc + 0.5)
    scales     N x 3 x uint8    s = 16·(log scale + 10)
    rotations  N x 3 x uint8 (v1-2: x, y, z of q̂ with w ≥ 0, 127.5·(1 + q)) or N x uint32 (v3+: the
               largest component's index in 2 bits and the other three as sign + 9 bits of |q|/√½)
    sh         N x ((d + 1)² - 1) x 3 x uint8, (v - 128) / 128, colour channel fastest

and optional extension records ([u32 type][u32 length][payload]) after them. Version 4 keeps the same
blocks as separate zstd streams after a plain 32-byte header (…, stream count, table-of-contents
offset), extension records between the header and the table of contents. The data are stored in a
right-up-back frame (or the frame an SPZ_ADOBE_coordinate_system extension names); PLY's is
right-down-front, so y and z flip, as do the quaternion's x-y-z parts and the SH coefficients odd in
them (the spz library's tables). Every size in a header is checked against the file before anything
that size is allocated; the decompressed data are bounded by what the header declares.

8-bit alphas of 0 and 255 are read as half a step inside (0.5/255 and 1 - 0.5/255): a file that stores
a fully opaque or transparent splat holds no infinite logit (σ⁻¹ of 0.5/255 is below 3DGS's 1/255
threshold, so such a splat stays invisible). SH degree 4 (spz only) is dropped to 3 with a warning.

Trainer checkpoints (`.pt`, `.ckpt`, `.pth`; a torch zip archive, read with `weights_only`, so a
file can hold tensors and plain values but no code): gsplat's simple_trainer saves
{"step", "splats": {means, scales, quats, opacities, sh0 [N, 1, 3], shN [N, K-1, 3]}} (or colors
[N, 3] and features for its appearance model) and writes no PLY unless `save_ply` is on;
nerfstudio's splatfacto saves {"pipeline": {"_model.gauss_params.means", ... features_dc [N, 3],
features_rest [N, K-1, 3], opacities [N, 1]}} ("_model.means", ... before nerfstudio 1.1, which it still loads); a
splatfacto run of SH degree 0 (no features_rest coefficients) keeps colour logits in features_dc and draws their sigmoid,
and is read so. Both store log scales, (w, x, y, z) quaternions and
opacity logits, as PLY does, in the frame they trained in (`drsplat.frames`). A gsplat run with
`pose_opt` also saves its camera refinements ({"pose_adjust": {"embeds.weight" [T, 9]}}), read into
the load report (`LoadReport.camera_refinements`), which drsplat.frames applies to the training cameras.
"""

from __future__ import annotations

import io
import logging
import re
import warnings
import zlib
from pathlib import Path

import numpy as np
import zstandard

from drsplat.errors import InputError, OutputError
from drsplat.scene import (COARSE_EXTENT_SHARE, float32_coarse_positions, SH_C0, SH_REST_COUNTS, GaussianScene, LoadReport, assemble_scene, byte_alpha, check_element_sizes, compressed_ply_bytes,
                           dc_from_rgb, load_ply_report, opacity_logits, read_ply_header, save_ply, starts_as_ply)
from drsplat.utils import unreachable_cause, write_bytes_atomic

log = logging.getLogger(__name__)

SPLAT_RECORD = np.dtype([("position", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)), ("rotation", "u1", (4,))])
NGSP_MAGIC = 0x5053474E  # "NGSP" little-endian
GZIP_MAGIC = b"\x1f\x8b"
SPZ_VERSIONS = (1, 2, 3, 4)
SPZ_COLOR_SCALE = 0.15
SPZ_MAX_SH_DEGREE = 4
SPZ_LEGACY_HEADER = np.dtype([("magic", "<u4"), ("version", "<u4"), ("points", "<u4"), ("sh_degree", "u1"),
                              ("fractional_bits", "u1"), ("flags", "u1"), ("reserved", "u1")])
SPZ_HEADER = np.dtype([("magic", "<u4"), ("version", "<u4"), ("points", "<u4"), ("sh_degree", "u1"), ("fractional_bits", "u1"),
                       ("flags", "u1"), ("streams", "u1"), ("toc_offset", "<u4"), ("reserved", "u1", (12,))])
FLAG_ANTIALIASED = 0x1
FLAG_EXTENSIONS = 0x2
EXTENSION_COORDINATES = 0xADBE0003  # SPZ_ADOBE_coordinate_system: u32, the frame the data are stored in
MAX_LEGACY_EXTENSION_BYTES = 1 << 20  # extension records a gzip .spz may hold after its blocks
MAX_SPZ_RATIO = 1024  # data bytes per file byte a header may declare (the spz library's kMaxCompressionRatio)
# the spz library's frames: 0 unspecified (= RUB), 1-8 axis flips of one another, 9-16 rotated by 90° about x
SPZ_FRAMES = {1: "LDB", 2: "RDB", 3: "LUB", 4: "RUB", 5: "LDF", 6: "RDF", 7: "LUF", 8: "RUF"}
DEFAULT_SPZ_FRAME = 4  # RUB
SCENE_SUFFIXES = (".ply", ".splat", ".spz", ".pt", ".ckpt", ".pth")  # the scene files load_scene reads
CHECKPOINT_SUFFIXES = (".pt", ".ckpt", ".pth")  # trainer checkpoints (module docstring)
ZIP_MAGIC = b"PK\x03\x04"  # torch.save's archive
MAX_CHECKPOINT_INFLATION = 64  # record bytes per file byte a checkpoint may declare (torch.save stores them: ~1:1)
SCENE_FILES_READ = "PLY (INRIA or compressed), .splat, .spz and gsplat or nerfstudio checkpoints (.pt, .ckpt, .pth)"
OTHER_SPLAT_SUFFIXES = (".ksplat", ".sog", ".sogs", ".glb", ".gltf", ".lcc", ".ssplat", ".spx")  # splat formats drsplat does not read
SNIFF_BYTES = 4096  # what scene_format reads of a file: enough of a gzip stream to inflate an spz header


def scene_format(path: Path) -> str:
    """"ply", "splat", "spz" or "checkpoint": PLY by its first line ("ply"), a trainer checkpoint by
    its name and a zip archive's first bytes, a gzipped PLY refused by its first bytes, then `.splat` by its name (the format has no header, and
    a first float's bytes can be anything, gzip's magic included) unless its first bytes are an spz
    header (`_holds_spz_header`: an spz renamed, read as spz with a warning), then spz by its first
    bytes (gzip or "NGSP") or its name; anything else is "ply", whose reader then names what is wrong."""
    with open(path, "rb") as f:
        head = f.read(SNIFF_BYTES)
    if starts_as_ply(head):
        return "ply"
    if path.suffix.lower() in CHECKPOINT_SUFFIXES:
        if head[:4] != ZIP_MAGIC:
            raise InputError(path, "is not a torch checkpoint archive (torch.save's zip; a file saved with "
                                   "_use_new_zipfile_serialization=False, or another file named like one)")
        return "checkpoint"
    # before .splat's name: a gzipped PLY named .splat was read as 6,620 garbage records (a first float whose bytes
    # start a gzip stream that inflates to "ply" is no .splat a trainer writes)
    if head[:2] == GZIP_MAGIC and _inflated_start(head, 4).startswith(b"ply"):
        raise InputError(path, f"is a gzip-compressed PLY file: decompress it first (gunzip -k); drsplat reads {SCENE_FILES_READ}")
    if path.suffix.lower() == ".splat":
        holds_spz = _holds_spz_header(head)
        if head[:2] == GZIP_MAGIC and not holds_spz and gzip_damage(path.read_bytes()) is None:
            # a whole gzip stream whose checksum holds is no .splat a trainer wrote (its first float starting 1f 8b
            # would not inflate): read as records, a gzipped .splat gave ~1,000 Gaussians of ±3e38
            raise InputError(path, "is a gzip-compressed file: decompress it first (gunzip -k, after naming it .splat.gz); drsplat "
                                   f"reads {SCENE_FILES_READ}")
        if not holds_spz:
            return "splat"
        log.warning("%s: is named .splat but holds an .spz file (its first bytes are an spz header); read as .spz", path)
        return "spz"
    if head[:2] == GZIP_MAGIC or (len(head) >= 4 and int.from_bytes(head[:4], "little") == NGSP_MAGIC) or path.suffix.lower() == ".spz":
        return "spz"
    if not head.startswith(b"ply"):
        known = f" (a {path.suffix} file: convert it to PLY first, e.g. with PlayCanvas splat-transform)" if path.suffix.lower() in OTHER_SPLAT_SUFFIXES else ""
        raise InputError(path, f"is not a PLY file (it does not start with 'ply'){known}; drsplat reads {SCENE_FILES_READ}")
    return "ply"


def _inflated_start(head: bytes, size: int) -> bytes:
    """The first `size` bytes of the gzip stream that `head` starts, b"" when it does not inflate."""
    try:
        return zlib.decompressobj(16 + zlib.MAX_WBITS).decompress(head, size)
    except zlib.error:
        return b""


def _holds_spz_header(head: bytes) -> bool:
    """Whether the first bytes of a file are an spz header: "NGSP" and a known version, plainly
    (version 4) or as the start of a gzip stream (1-3). The first record of a `.splat` could start
    with gzip's two bytes by chance, but not with a stream that inflates to such a header."""
    def is_header(data: bytes) -> bool:
        return len(data) >= 8 and int.from_bytes(data[:4], "little") == NGSP_MAGIC and int.from_bytes(data[4:8], "little") in SPZ_VERSIONS

    if is_header(head):
        return True
    return head[:2] == GZIP_MAGIC and is_header(_inflated_start(head, 8))


def load_scene_report(path: str | Path, purpose: str | None = None) -> tuple[GaussianScene, LoadReport]:
    """Load a 3DGS scene file (PLY: INRIA or compressed, `.splat`, `.spz`, a gsplat or nerfstudio checkpoint) and report what was found and
    fixed. purpose: as in `load_ply_report` (an empty file is then one error naming it)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, unreachable_cause(path, "does not exist") if not path.exists() else "is not a file")
    kind = scene_format(path)
    if kind == "ply":
        return load_ply_report(path, purpose)
    cols, order, layout = {"splat": splat_columns, "spz": spz_columns, "checkpoint": checkpoint_columns}[kind](path)
    return assemble_scene(path, cols, order, layout, [], purpose)


BASE_VALUES = 14  # a Gaussian's values besides its higher SH: mean, rotation, log scales, opacity, DC colour


def declared_scene_size(path: str | Path) -> tuple[int, int] | None:
    """(rows, values per row) of a scene file, read from its header without loading it: the rows (a PLY's vertex count,
    checked against the file's size; a `.splat`'s records; an spz header's point count, checked as its reader does) and
    the float32 values its loading makes of each (BASE_VALUES and the higher SH coefficients), which it holds for every
    row at once before dropping any. None where that is not known so cheaply (checkpoints) or the file has a problem its
    loading names (a path that is not a regular file among them: opening a FIFO no one writes to blocks, round 74c F1)."""
    path = Path(path)
    try:
        if not path.is_file():
            return None
        kind = scene_format(path)
        if kind == "splat":  # no header: the records the file's size holds, when it holds whole ones (`splat_columns`)
            size = path.stat().st_size
            return (size // SPLAT_RECORD.itemsize, BASE_VALUES) if size % SPLAT_RECORD.itemsize == 0 else None
        if kind == "spz":
            return _spz_size(path)
        if kind != "ply":
            return None
        header = read_ply_header(path)
        check_element_sizes(path, header, path.stat().st_size)
    except (InputError, OSError):
        return None
    elements = {element.name: element for element in header.elements}
    if "vertex" not in elements:
        return None
    rest = sum(name.startswith("f_rest_") for name, _ in elements["vertex"].properties)
    rest += len(elements["sh"].properties) if "sh" in elements else 0  # a compressed PLY's SH bytes
    return elements["vertex"].count, BASE_VALUES + rest


def _spz_size(path: Path) -> tuple[int, int] | None:
    """`declared_scene_size` of an `.spz`: its header's points and SH degree (gzip's first bytes inflated for versions
    1-3), None for a header its reader refuses (a version or degree it does not read, more data than the file can hold)."""
    with open(path, "rb") as f:
        head = f.read(SNIFF_BYTES)
    if head[:2] == GZIP_MAGIC:
        head = _inflated_start(head, SPZ_LEGACY_HEADER.itemsize)
    if len(head) < SPZ_LEGACY_HEADER.itemsize or int.from_bytes(head[:4], "little") != NGSP_MAGIC:
        return None
    header = np.frombuffer(head[: SPZ_LEGACY_HEADER.itemsize], SPZ_LEGACY_HEADER)[0]
    version, points, degree = int(header["version"]), int(header["points"]), int(header["sh_degree"])
    try:
        _check_spz_header(path, version, degree, int(header["fractional_bits"]))
        _check_ratio(path, spz_block_sizes(points, version, degree), path.stat().st_size)
    except InputError:
        return None
    return points, BASE_VALUES + 3 * sh_coefficients(min(degree, max(SH_REST_COUNTS)))


def load_scene(path: str | Path, purpose: str | None = None) -> GaussianScene:
    """`load_scene_report` without the report."""
    return load_scene_report(path, purpose)[0]


# ----------------------------------------------------------------------------- trainer checkpoints

NERFSTUDIO_PREFIX = "_model.gauss_params."
CHECKPOINT_LAYOUTS = {  # layout -> (where the Gaussians are, its field names for means, scales, quats, opacities, DC, rest of the SH)
    "gsplat checkpoint": ("splats", ("means", "scales", "quats", "opacities", "sh0", "shN")),
    "nerfstudio checkpoint": ("pipeline", tuple(NERFSTUDIO_PREFIX + k for k in ("means", "scales", "quats", "opacities", "features_dc", "features_rest"))),
    # splatfacto before its gauss_params ParameterDict (nerfstudio 1.0), whose checkpoints nerfstudio still loads (round 87a F4)
    "nerfstudio 1.0 checkpoint": ("pipeline", tuple("_model." + k for k in ("means", "scales", "quats", "opacities", "features_dc", "features_rest"))),
}


def _load_checkpoint(path: Path) -> dict:
    """torch.load of a checkpoint on the CPU with weights_only (tensors and plain values, no code);
    InputError naming the file for anything torch cannot read so. The archive is checked first
    (`_archive_records`: CRCs, the bytes its records inflate to). Memory-mapped then, so a checkpoint
    that also holds its optimiser's state (three times the Gaussians' bytes) is not read whole.
    Mapped, torch checks no record's size: an archive with a short or compressed record read its
    neighbours' bytes as values (round 23). So unless its records are intact (`_records_intact`),
    it is read again whole, which checks every record and inflates compressed ones."""
    records = _archive_records(path)
    data = _torch_load(path, mmap=True)
    if records is None or not _records_intact(records, data):
        del data
        data = _torch_load(path, mmap=False)
    if not isinstance(data, dict):
        raise InputError(path, f"holds a {type(data).__name__}, not a checkpoint's dictionary")
    return data


def _archive_records(path: Path) -> list | None:
    """The archive's tensor records (`<archive>/data/<key>` ZipInfos), after one pass that checks it:
    InputError when its records would inflate to more than MAX_CHECKPOINT_INFLATION times the file
    (torch.save stores them; a deflated record of zeros declares ~1000x its bytes, all allocated by a
    whole read), when a record header is damaged, or when a record fails its CRC-32 (torch reads
    records without checking them: a flipped byte loaded as a wrong value, round 23). None when
    zipfile cannot read the archive's directory (damaged, an unknown version): torch.load names it."""
    import zipfile

    try:
        archive = zipfile.ZipFile(path)
    except Exception:  # noqa: BLE001 - not a directory zipfile reads: torch.load then says what is wrong with the file
        return None
    with archive:
        infos = archive.infolist()
        inflated, size = sum(i.file_size for i in infos), path.stat().st_size
        if inflated > MAX_CHECKPOINT_INFLATION * max(size, 1):
            raise InputError(path, f"declares {inflated:,} bytes of records in a {size:,}-byte file, more than {MAX_CHECKPOINT_INFLATION}:1 "
                                   "(torch.save stores its records uncompressed): not read")
        try:
            bad = archive.testzip()
        except Exception as exc:  # noqa: BLE001 - a record's own header damaged (its name, its method, its length)
            raise InputError(path, f"has a damaged record header ({type(exc).__name__}): the archive is damaged (a copy cut or altered in transfer?)") from None
    if bad is not None:
        raise InputError(path, f"its record {bad} fails its CRC-32 check: the archive is damaged (a copy cut or altered in transfer?)")
    return [i for i in infos if re.fullmatch(r"[^/]+/data/\d+", i.filename)]


def _torch_load(path: Path, mmap: bool):
    import pickle

    import torch

    try:
        with warnings.catch_warnings():  # torch's own notes (a sparse tensor's invariants scanned): the refusal says what matters
            warnings.simplefilter("ignore", UserWarning)
            return torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
    except pickle.UnpicklingError as exc:
        raise InputError(path, f"holds something other than tensors and plain values, which is not read ({_refusal(exc)})") from None
    except Exception as exc:  # noqa: BLE001 - torch's reader of an untrusted archive raises many kinds (KeyError, IndexError, AssertionError, ...)
        raise InputError(path, f"cannot be read as a torch checkpoint ({type(exc).__name__}: {_first_line(exc) or 'no detail'})") from None


def _records_intact(records: list, data) -> bool:
    """Whether the tensor records (`_archive_records`) are stored uncompressed and have exactly the
    sizes of the storages the loaded object holds (each storage is one record; empty ones aside),
    so a mapped read took every value from its own record."""
    import zipfile

    import torch

    if any(i.compress_type != zipfile.ZIP_STORED for i in records):
        return False
    storages: dict[int, int] = {}
    stack = [data]
    while stack:
        item = stack.pop()
        if isinstance(item, dict):
            stack.extend(item.values())
        elif isinstance(item, (list, tuple)):
            stack.extend(item)
        elif isinstance(item, torch.Tensor):
            if item.layout != torch.strided or item.device.type != "cpu":
                return False
            storage = item.untyped_storage()
            if storage.nbytes():
                storages[storage.data_ptr()] = storage.nbytes()
    return sorted(storages.values()) == sorted(i.file_size for i in records if i.file_size)


def _plain_text(exc: BaseException) -> str:
    """The exception's message without terminal colour codes (torch bolds its advice)."""
    return re.sub(r"\x1b\[[0-9;]*m", "", str(exc))


def _first_line(exc: BaseException) -> str:
    """The exception's first non-empty line, without terminal colour codes."""
    return next((line.strip() for line in _plain_text(exc).splitlines() if line.strip()), "")


def _refusal(exc: BaseException) -> str:
    """What weights_only refused, from torch's message: 'a reference to module.name' when it names the
    global, else its first line that is not advice to turn the check off."""
    text = _plain_text(exc)
    found = re.search(r"GLOBAL ([\w.]+)", text)
    if found:
        return f"a reference to {found.group(1)}"
    advice = ("Weights only load failed", "Check the documentation", "Please file an issue", "(1)", "(2)")
    lines = [line.strip().removeprefix("WeightsUnpickler error:").strip() for line in text.splitlines()]
    return next((line for line in lines if line and not line.startswith(advice)), "weights_only refused it")


def _checkpoint_tensor(path: Path, where: dict, key: str, dims: int, width: int | None = None):
    """where[key] as float32 numpy, checked: a dense CPU tensor of floats, of `dims` dimensions, last of size
    `width` (None: any), whose storage holds every element (a tensor expanded over one row, a few bytes on
    disk, could declare a billion rows)."""
    import torch

    if key not in where:
        raise InputError(path, "has no such entry (a checkpoint of a trainer or version drsplat does not know?)", field=key)
    value = where[key]
    if not isinstance(value, torch.Tensor) or not value.is_floating_point():
        raise InputError(path, f"is a {type(value).__name__}{' of ' + str(value.dtype) if isinstance(value, torch.Tensor) else ''}, "
                               "not a floating-point tensor", field=key)
    if value.layout != torch.strided or value.device.type != "cpu":
        raise InputError(path, f"is a {value.layout} tensor on {value.device.type}, not a dense one with its values", field=key)
    if value.dim() != dims or (width is not None and value.shape[-1] != width):
        expected = ["N"] + ["?"] * (dims - 1)
        if width is not None:
            expected[-1] = str(width)
        raise InputError(path, f"has shape {list(value.shape)}, expected [{', '.join(expected)}]", field=key)
    if value.untyped_storage().nbytes() < value.numel() * value.element_size():
        raise InputError(path, f"declares {value.numel():,} values but stores {value.untyped_storage().nbytes():,} bytes "
                               "(a tensor expanded over shared memory, not one value per element)", field=key)
    return value.detach().resolve_conj().resolve_neg().to(torch.float32).contiguous().numpy()


RANK_SHARE = re.compile(r"(ckpt_\d+)_rank(\d+)(\.pt)", re.IGNORECASE)  # gsplat's name for one GPU's checkpoint


def rank_shares(path: Path) -> list[Path]:
    """The checkpoints of every GPU of the gsplat run `path` (ckpt_<step>_rank<r>.pt) is one of, in rank
    order: a run on W GPUs gives each a disjoint share of the Gaussians (its points [r::W]) and saves
    one file per rank, which gsplat's own viewer concatenates. [path] for any other file. InputError
    when a rank between 0 and the highest found is missing (a copy that left one behind)."""
    match = RANK_SHARE.fullmatch(path.name)
    if match is None:
        return [path]
    prefix, _, suffix = match.groups()
    found = {int(m.group(2)): sibling for sibling in path.parent.iterdir()
             if (m := RANK_SHARE.fullmatch(sibling.name)) and m.group(1) == prefix and sibling.is_file()}
    ranks = sorted(found)
    gap = next((i for i, r in enumerate(ranks) if r != i), None)  # the first rank missing; no range up to the highest (a name can say rank 10^11)
    if gap is not None:
        raise InputError(path, f"is one of the per-GPU shares of a gsplat run, but the share of rank {gap} "
                               f"({prefix}_rank{gap}{suffix}) is not beside it: every rank's file is needed for the whole scene")
    return [found[r] for r in ranks]


def checkpoint_columns(path: Path) -> tuple[dict, list[str], str]:
    """A gsplat or nerfstudio checkpoint (module docstring) as `assemble_scene`'s columns, its field
    names and layout name; a gsplat run's per-GPU shares (`rank_shares`) read and joined in rank
    order. Every field is checked: present, a floating-point tensor of the right shape, one row per
    Gaussian; the SH coefficients a whole degree (1, 4, 9 or 16 of them), the same in every share."""
    shares = rank_shares(path)
    if len(shares) == 1:
        return _checkpoint_file_columns(path)
    parts = [_checkpoint_file_columns(share) for share in shares]
    for share, (cols, _, _) in zip(shares, parts):
        if cols["sh"].shape[1:] != parts[0][0]["sh"].shape[1:]:
            raise InputError(share, f"has SH of {cols['sh'].shape[1]} coefficients per colour, but {shares[0].name} has {parts[0][0]['sh'].shape[1]}")
    joined = {key: np.concatenate([cols[key] for cols, _, _ in parts]) for key in ("means", "log_scales", "quats", "opacity_logits", "sh")}
    log.info("%s: the Gaussians of the %d per-GPU shares of its gsplat run (%s), joined in rank order", path, len(shares),
             ", ".join(f"{len(cols['means']):,}" for cols, _, _ in parts))
    given = next(cols for share, (cols, _, _) in zip(shares, parts) if share.name == path.name)  # its pose_adjust: the ranks hold one each
    return {**joined, "extra": {}, "camera_refinements": given["camera_refinements"]}, parts[0][1], f"{parts[0][2]} ({len(shares)} ranks)"


def _checkpoint_file_columns(path: Path) -> tuple[dict, list[str], str]:
    """`checkpoint_columns` of one file."""
    data = _load_checkpoint(path)
    layout = next((name for name, (group, fields) in CHECKPOINT_LAYOUTS.items()
                   if isinstance(data.get(group), dict) and fields[0] in data[group]), None)
    if layout is None:
        for name, (group, fields) in CHECKPOINT_LAYOUTS.items():  # the group there without its means (round 85b F9: "holds neither ... 'splats'")
            if not isinstance(data.get(group), dict):
                continue
            if name == "nerfstudio checkpoint" and not any(str(k).startswith(NERFSTUDIO_PREFIX) for k in data[group]) and \
                    any(str(k).startswith("_model.") and str(k).endswith("features_dc") for k in data[group]):
                continue  # a 1.0 layout's missing means is named as that layout's (round 87b F7)
            keys = sorted(map(str, data[group]))
            held = (", ".join(keys[:8]) + (", ..." if len(keys) > 8 else "")) or "nothing"
            if group == "pipeline" and not any(k.startswith(NERFSTUDIO_PREFIX) or k.startswith("_model.") and k.endswith("features_dc") for k in keys):
                # a NeRF's checkpoint (nerfacto): no Gaussians at all, not a damaged splat file (round 86c F4)
                raise InputError(path, f"is a nerfstudio checkpoint of a model without Gaussians (its 'pipeline' holds no "
                                       f"'{NERFSTUDIO_PREFIX}*': {held}): a NeRF such as nerfacto, not splatfacto")
            raise InputError(path, f"is a {name} whose '{group}' has no '{fields[0]}' (it holds {held})", field=f"{group}.{fields[0]}")
        raise InputError(path, f"holds neither a gsplat checkpoint's 'splats' nor a nerfstudio one's 'pipeline' with "
                               f"'{NERFSTUDIO_PREFIX}means' (its entries: {', '.join(sorted(map(str, data))[:8]) or 'none'})")
    group, (k_means, k_scales, k_quats, k_opacities, k_dc, k_rest) = CHECKPOINT_LAYOUTS[layout]
    where = data[group]
    gsplat = layout == "gsplat checkpoint"
    read = {k_means: _checkpoint_tensor(path, where, k_means, 2, 3), k_scales: _checkpoint_tensor(path, where, k_scales, 2, 3),
            k_quats: _checkpoint_tensor(path, where, k_quats, 2, 4)}
    read[k_opacities] = (_checkpoint_tensor(path, where, k_opacities, 1) if gsplat else _checkpoint_tensor(path, where, k_opacities, 2, 1))
    if gsplat and k_dc not in where and "colors" in where:  # its appearance model: a base colour per Gaussian, no SH
        read["colors"] = _checkpoint_tensor(path, where, "colors", 2, 3)
        log.warning("%s: a gsplat checkpoint of its appearance model (colors, features): read with each Gaussian's base colour "
                    "sigmoid(colors) as SH degree 0; the view-dependent part is not read", path)
    else:
        read[k_dc] = _checkpoint_tensor(path, where, k_dc, 3, 3) if gsplat else _checkpoint_tensor(path, where, k_dc, 2, 3)[:, None, :]
        if read[k_dc].shape[1] != 1:
            raise InputError(path, f"has shape {list(read[k_dc].shape)}, expected [N, 1, 3]: one DC coefficient per colour", field=k_dc)
        read[k_rest] = _checkpoint_tensor(path, where, k_rest, 3, 3) if k_rest in where else np.zeros((len(read[k_means]), 0, 3), np.float32)
        if read[k_rest].shape[1] + 1 not in (1, 4, 9, 16):
            raise InputError(path, f"has {read[k_rest].shape[1]} higher SH coefficients per colour; a whole degree has 0, 3, 8 or 15", field=k_rest)
    n = len(read[k_means])
    for key, column in read.items():
        if len(column) != n:
            raise InputError(path, f"has {len(column):,} rows but {k_means} has {n:,}: one row per Gaussian", field=key)
    if "colors" in read:
        with np.errstate(over="ignore"):  # a colour logit below -709: its sigmoid is 0, as it should be
            sh = dc_from_rgb(1.0 / (1.0 + np.exp(-read["colors"].astype(np.float64))))[:, None, :].astype(np.float32)
    elif not gsplat and read[k_rest].shape[1] == 0:
        # splatfacto at SH degree 0 keeps a colour logit in features_dc and draws sigmoid of it (its `colors`, what ns-export
        # writes), not SH: read as SH, (0.9, 0.1, 0.1) showed as (1.12, -0.12, -0.12) (round 87b F6)
        with np.errstate(over="ignore"):
            sh = dc_from_rgb(1.0 / (1.0 + np.exp(-read[k_dc][:, 0].astype(np.float64))))[:, None, :].astype(np.float32)
        log.info("%s: a splatfacto checkpoint of SH degree 0: its features_dc are colour logits (nerfstudio draws their sigmoid), "
                 "read as such", path)
    else:
        sh = np.concatenate([read[k_dc], read[k_rest]], axis=1)
    cols = {"means": read[k_means], "log_scales": read[k_scales], "quats": read[k_quats], "opacity_logits": read[k_opacities].reshape(-1),
            "sh": sh, "extra": {}, "camera_refinements": _pose_deltas(path, data) if gsplat else None}
    return cols, list(read), layout


POSE_ADJUST = ("pose_adjust", "embeds.weight")  # where gsplat's simple_trainer (pose_opt) keeps its camera refinements


def _pose_deltas(path: Path, data: dict) -> np.ndarray | None:
    """[T, 9] float64: the camera refinements a gsplat checkpoint `data` (read from `path`) saved with
    `pose_opt` holds (its CameraOptModule's `pose_adjust` state, `embeds.weight`: per training image
    a shift dx [3] and a 6-D rotation offset [6]; drsplat.frames applies them), or None without
    them. The rows are as stored: non-finite ones are the caller's to count. InputError naming the
    file and field for an entry of another kind or shape."""
    group, key = POSE_ADJUST
    if group not in data:
        return None
    if not isinstance(data[group], dict):
        raise InputError(path, f"is a {type(data[group]).__name__}, not the state of gsplat's CameraOptModule (a dictionary holding {key})",
                         field=group)
    named = {f"{group}.{k}": v for k, v in data[group].items()}
    return _checkpoint_tensor(path, named, f"{group}.{key}", 2, 9).astype(np.float64)


def checkpoint_refinements(path: str | Path) -> np.ndarray | None:
    """The camera refinements of the gsplat checkpoint `path` (`_pose_deltas`) without its Gaussians:
    what `eval lerf` needs of the checkpoint a registered scene names (`frames.refined_by`).
    InputError for a file that is no gsplat checkpoint."""
    path = Path(path)
    if path.suffix.lower() not in CHECKPOINT_SUFFIXES:
        raise InputError(path, f"is not a trainer checkpoint (no {', '.join(CHECKPOINT_SUFFIXES)} name)")
    data = _load_checkpoint(path)
    if not isinstance(data.get("splats"), dict):
        raise InputError(path, "holds no gsplat checkpoint's 'splats'")
    return _pose_deltas(path, data)


# ----------------------------------------------------------------------------- .splat


def splat_columns(path: Path) -> tuple[dict, list[str], str]:
    """Decode a `.splat` file (module docstring) into `assemble_scene`'s columns, its field names and layout name."""
    size = path.stat().st_size
    if size % SPLAT_RECORD.itemsize:
        raise InputError(path, f"is {size:,} bytes, not a whole number of {SPLAT_RECORD.itemsize}-byte .splat records "
                               f"({size // SPLAT_RECORD.itemsize:,} records and {size % SPLAT_RECORD.itemsize} bytes): truncated, "
                               "or not a .splat file", field="size")
    rec = np.fromfile(path, SPLAT_RECORD)
    with np.errstate(invalid="ignore"):  # a signalling NaN is a NaN here, dropped and counted by assemble_scene
        scales = rec["scale"].astype(np.float64)
    # A viewer's covariance (R S)(R S)ᵀ = R S² Rᵀ holds the square of each scale, so a negative scale
    # draws as its magnitude: read as that and counted. A zero scale's log is -inf, which assemble_scene drops and counts.
    with np.errstate(divide="ignore"):
        log_scales = np.log(np.abs(scales)).astype(np.float32)
    negative = (scales < 0).any(axis=1) & np.isfinite(log_scales).all(axis=1)  # a row of -inf or 0 scale is dropped, not read
    cols = {
        "means": rec["position"].astype(np.float32),
        "quats": (rec["rotation"].astype(np.float32) - 128.0) / 128.0,
        "log_scales": log_scales,
        "opacity_logits": opacity_logits(byte_alpha(rec["rgba"][:, 3])),
        "sh": dc_from_rgb(rec["rgba"][:, :3].astype(np.float32) / 255.0)[:, None, :],
        "extra": {},
        "negative_scales": int(negative.sum()),
    }
    return cols, list(SPLAT_RECORD.names), "splat"


# ----------------------------------------------------------------------------- .spz


def sh_coefficients(degree: int) -> int:
    """Higher-order SH coefficients per colour channel of a degree: (d + 1)² - 1."""
    return (degree + 1) ** 2 - 1


def spz_block_sizes(points: int, version: int, sh_degree: int) -> list[tuple[str, int]]:
    """The data blocks of an spz file of `points` points, in file order, with their byte counts."""
    return [("positions", points * (6 if version == 1 else 9)), ("alphas", points), ("colors", points * 3),
            ("scales", points * 3), ("rotations", points * (4 if version >= 3 else 3)),
            ("sh", points * sh_coefficients(sh_degree) * 3)]


def spz_columns(path: Path) -> tuple[dict, list[str], str]:
    """Decode an `.spz` file (module docstring) into `assemble_scene`'s columns, its block names and layout name."""
    data = path.read_bytes()
    if data[:2] == GZIP_MAGIC:
        header, blocks, extensions = _read_legacy_spz(path, data)
    else:
        header, blocks, extensions = _read_ngsp_spz(path, data)
    frame = _storage_frame(path, extensions)
    version, points, degree = int(header["version"]), int(header["points"]), int(header["sh_degree"])
    if header["flags"] & FLAG_ANTIALIASED:
        log.warning("%s: was trained with anti-aliasing (mip-splatting's 2D filter); drsplat rasterizes it as plain 3DGS, "
                    "so small splats weigh a little more than in its own renderer", path)
    with np.errstate(invalid="ignore", over="ignore"):  # a float16 NaN or inf (version 1) flips without numpy's warning: the load counts it
        cols = _decode_spz_blocks(blocks, version, points, degree, int(header["fractional_bits"]))
        _to_ply_frame(cols, frame)
    cols["position_step"] = 2.0 ** -int(header["fractional_bits"])  # its fixed-point grid: the load's coarse-positions finding judges it
    if degree > max(SH_REST_COUNTS):  # the degrees a GaussianScene (and 3DGS) holds
        log.warning("%s: has SH degree %d; drsplat keeps degrees 0-%d (the rest only tints view-dependent colour)",
                    path, degree, max(SH_REST_COUNTS))
        cols["sh"] = cols["sh"][:, : (max(SH_REST_COUNTS) + 1) ** 2]
    return cols, [name for name, _ in spz_block_sizes(points, version, degree)], f"spz v{version}"


def _check_spz_header(path: Path, version: int, degree: int, fractional_bits: int) -> None:
    if version not in SPZ_VERSIONS:
        raise InputError(path, f"is spz version {version}; drsplat reads versions {SPZ_VERSIONS[0]}-{SPZ_VERSIONS[-1]}", field="version")
    if degree > SPZ_MAX_SH_DEGREE:
        raise InputError(path, f"declares SH degree {degree}; spz holds degrees 0-{SPZ_MAX_SH_DEGREE}", field="shDegree")
    if version > 1 and fractional_bits > SPZ_MAX_FRACTIONAL_BITS:
        raise InputError(path, f"declares {fractional_bits} fractional bits for its 24-bit positions; the spz library scales by "
                               f"1 << fractionalBits in a 32-bit int, so at most {SPZ_MAX_FRACTIONAL_BITS} mean anything (it writes "
                               f"{SPZ_FRACTIONAL_BITS})", field="fractionalBits")


def _read_legacy_spz(path: Path, data: bytes) -> tuple[np.void, dict[str, bytes], bytes]:
    """Versions 1-3: (header, {block: bytes}, extension bytes) from the gzip stream, decompressing no
    more than the header declares (plus MAX_LEGACY_EXTENSION_BYTES of extensions)."""
    inflater = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        head = inflater.decompress(data, SPZ_LEGACY_HEADER.itemsize)
    except zlib.error as exc:
        raise InputError(path, f"is not a readable gzip stream ({exc})", field="gzip") from None
    if len(head) < SPZ_LEGACY_HEADER.itemsize:
        raise InputError(path, f"holds {len(head)} bytes once decompressed, fewer than the {SPZ_LEGACY_HEADER.itemsize}-byte spz header", field="header")
    header = np.frombuffer(head, SPZ_LEGACY_HEADER)[0]
    if int(header["magic"]) != NGSP_MAGIC:
        raise InputError(path, "is a gzip file without the spz header (magic 'NGSP'): not an .spz file", field="magic")
    version, points, degree = int(header["version"]), int(header["points"]), int(header["sh_degree"])
    if version == 4 and gzip_damage(data) is None:  # version 4 is no gzip stream: read as one, it was called "truncated"; 5 and up are unknown (round 85b F2)
        raise InputError(path, f"is a gzip-compressed spz version {version} file (version 4 is a plain 'NGSP' file of zstd "
                               "streams, not a gzip stream): decompress it first (gunzip -k, after naming it .spz.gz)", field="gzip")
    try:
        _check_spz_header(path, version, degree, int(header["fractional_bits"]))
    except InputError:
        damage = gzip_damage(data)  # a header of nonsense in a stream that fails its checksum: the stream is what is wrong
        if damage is not None:
            raise InputError(path, f"is a damaged gzip stream ({damage}), so its spz header reads as nonsense", field="gzip") from None
        raise
    sizes = spz_block_sizes(points, version, degree)
    need = _check_ratio(path, sizes, len(data))
    body = _inflate(path, inflater, need + MAX_LEGACY_EXTENSION_BYTES)
    if len(body) < need:
        raise InputError(path, f"is truncated: its header declares {points:,} points ({need:,} bytes of data) "
                               f"but the stream holds {len(body):,}", field="numPoints")
    blocks, at = {}, 0
    for name, n in sizes:
        blocks[name] = body[at: at + n]
        at += n
    extensions = body[at:]
    if extensions and not header["flags"] & FLAG_EXTENSIONS:
        log.warning("%s: %d bytes follow the %d points its header declares (and no extension flag): the point count may be "
                    "smaller than the data, which is ignored", path, len(extensions), points)
        extensions = b""
    return header, blocks, extensions


def gzip_damage(data: bytes, block: int = 1 << 20) -> str | None:
    """What is wrong with the gzip stream that `data` starts (zlib's words, or "it ends before its
    end"), or None when it inflates whole and its checksum holds. Inflates at most MAX_SPZ_RATIO
    times len(data), in `block`-byte steps, keeping none of it (a stream that would inflate past
    that is not judged: None)."""
    inflater = zlib.decompressobj(16 + zlib.MAX_WBITS)
    budget, pending = MAX_SPZ_RATIO * len(data), data
    try:
        while budget > 0 and not inflater.eof:
            out = inflater.decompress(pending, block)
            pending = inflater.unconsumed_tail
            budget -= len(out)
            if not out and not pending:
                return "it ends before its end"
    except zlib.error as exc:
        return str(exc)
    return None


def _check_ratio(path: Path, sizes: list[tuple[str, int]], file_bytes: int) -> int:
    """The data bytes a header declares, checked against the file's size before anything is
    decompressed: no more than MAX_SPZ_RATIO times it (the spz library's own bound)."""
    need = sum(n for _, n in sizes)
    if need > MAX_SPZ_RATIO * file_bytes:
        raise InputError(path, f"declares {need:,} bytes of point data in a {file_bytes:,}-byte file, more than {MAX_SPZ_RATIO}:1 "
                               "compression gives: a damaged header", field="numPoints")
    return need


def _inflate(path: Path, inflater, limit: int) -> bytes:
    """The rest of a gzip stream, at most `limit` bytes (InputError when it holds more, is damaged or ends early)."""
    try:
        body = inflater.decompress(inflater.unconsumed_tail, limit + 1)
    except zlib.error as exc:
        raise InputError(path, f"has a damaged gzip stream ({exc})", field="gzip") from None
    if len(body) > limit:
        raise InputError(path, f"decompresses to more than the {limit:,} bytes its header allows", field="gzip")
    if not inflater.eof:
        raise InputError(path, "is truncated: its gzip stream ends early", field="gzip")
    if inflater.unused_data:
        log.warning("%s: %d bytes after the end of its gzip stream ignored", path, len(inflater.unused_data))
    return body


def _unzstd(path: Path, name: str, packed: bytes, size: int) -> bytes:
    """One zstd stream that must decompress to exactly `size` bytes (never more is decompressed)."""
    out = bytearray()
    try:
        with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(packed)) as reader:
            while len(out) <= size:
                chunk = reader.read(size + 1 - len(out))
                if not chunk:
                    break
                out += chunk
    except zstandard.ZstdError as exc:
        raise InputError(path, f"has a damaged zstd stream for {name} ({exc})", field=name) from None
    if len(out) != size:
        raise InputError(path, f"decompresses {name} to {'more than ' if len(out) > size else ''}{len(out):,} bytes; "
                               f"its table of contents says {size:,}", field=name)
    return bytes(out)


def _read_ngsp_spz(path: Path, data: bytes) -> tuple[np.void, dict[str, bytes], bytes]:
    """Version 4: (header, {block: bytes}, extension bytes) from the table of contents and zstd streams."""
    if data[:4] != NGSP_MAGIC.to_bytes(4, "little"):
        raise InputError(path, "is not an .spz file: it starts neither with gzip's bytes (versions 1-3) nor with 'NGSP' (version 4)",
                         field="magic")
    if len(data) < SPZ_HEADER.itemsize:
        raise InputError(path, f"is {len(data)} bytes, shorter than the {SPZ_HEADER.itemsize}-byte spz header", field="header")
    header = np.frombuffer(data[: SPZ_HEADER.itemsize], SPZ_HEADER)[0]
    version, points, degree = int(header["version"]), int(header["points"]), int(header["sh_degree"])
    if version < 4:
        raise InputError(path, f"has a plain 'NGSP' header of version {version}; versions 1-3 are gzip streams", field="version")
    _check_spz_header(path, version, degree, int(header["fractional_bits"]))
    sizes = [(name, n) for name, n in spz_block_sizes(points, version, degree) if n > 0]
    toc, count = int(header["toc_offset"]), int(header["streams"])
    if count != len(sizes):
        raise InputError(path, f"has {count} streams; {points:,} points of SH degree {degree} need {len(sizes)}", field="numStreams")
    toc_end = toc + 16 * count
    if toc < SPZ_HEADER.itemsize or toc_end > len(data):
        raise InputError(path, f"puts its table of contents at bytes {toc:,}-{toc_end:,} of a {len(data):,}-byte file", field="tocByteOffset")
    table = np.frombuffer(data[toc:toc_end], "<u8").reshape(count, 2)
    listed = sum(int(packed) for packed in table[:, 0])  # Python ints: numpy's uint64 sum wrapped two 2^63 sizes back to the true total (round 101a F1)
    if listed != len(data) - toc_end:
        raise InputError(path, f"lists {listed:,} bytes of streams but holds {len(data) - toc_end:,} after its table "
                               "of contents: truncated or damaged", field="toc")
    _check_ratio(path, sizes, len(data))
    blocks, at = {}, toc_end
    for (name, n), (packed, unpacked) in zip(sizes, table.tolist()):
        if unpacked != n:
            raise InputError(path, f"stores {unpacked:,} bytes of {name}; {points:,} points need {n:,}", field=name)
        blocks[name] = _unzstd(path, name, data[at: at + packed], n)
        at += packed
    for name, _ in spz_block_sizes(points, version, degree):  # empty blocks (no points, or SH degree 0) have no stream
        blocks.setdefault(name, b"")
    return header, blocks, data[SPZ_HEADER.itemsize:toc] if header["flags"] & FLAG_EXTENSIONS else b""


def _storage_frame(path: Path, extensions: bytes) -> int:
    """The frame the data are stored in (SPZ_FRAMES key): RUB unless a coordinate-system extension names
    another; other extensions (camera limits, ...) are skipped. InputError for a damaged record or a
    rotated frame (9-16), which drsplat does not convert."""
    frame, at = DEFAULT_SPZ_FRAME, 0
    while at < len(extensions):
        if at + 8 > len(extensions):
            raise InputError(path, f"ends inside an extension record header ({len(extensions) - at} of 8 bytes)", field="extensions")
        kind, length = (int(v) for v in np.frombuffer(extensions[at: at + 8], "<u4"))
        if at + 8 + length > len(extensions):
            raise InputError(path, f"has an extension record (type 0x{kind:08X}) of {length:,} bytes past the end of its extensions", field="extensions")
        if kind == EXTENSION_COORDINATES:
            if length < 4:
                raise InputError(path, f"has a coordinate-system extension of {length} bytes (expected 4)", field="extensions")
            value = int(np.frombuffer(extensions[at + 8: at + 12], "<u4")[0])
            if value not in SPZ_FRAMES and value != 0:
                raise InputError(path, f"stores its data in spz coordinate system {value} (a rotated frame), which drsplat does not convert; "
                                       "re-export it from the spz tools in RUB or RDF", field="SPZ_ADOBE_coordinate_system")
            frame = value or DEFAULT_SPZ_FRAME
        else:
            log.info("%s: extension 0x%08X (%d bytes) skipped", path, kind, length)
        at += 8 + length
    return frame


def _decode_spz_blocks(blocks: dict[str, bytes], version: int, points: int, degree: int, fractional_bits: int) -> dict:
    """The blocks as `assemble_scene` columns in the file's own frame (quaternions w, x, y, z)."""
    n = points
    if version == 1:
        means = np.frombuffer(blocks["positions"], "<f2").reshape(n, 3).astype(np.float32)
    else:
        b = np.frombuffer(blocks["positions"], np.uint8).reshape(n, 3, 3).astype(np.int32)
        fixed = b[..., 0] | (b[..., 1] << 8) | (b[..., 2] << 16)
        fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
        means = (fixed.astype(np.float64) * 2.0 ** -fractional_bits).astype(np.float32)
    alphas = np.frombuffer(blocks["alphas"], np.uint8)
    colors = np.frombuffer(blocks["colors"], np.uint8).reshape(n, 3).astype(np.float32)
    dc = (colors / np.float32(255.0) - np.float32(0.5)) / np.float32(SPZ_COLOR_SCALE)
    log_scales = np.frombuffer(blocks["scales"], np.uint8).reshape(n, 3).astype(np.float32) / np.float32(16.0) - np.float32(10.0)
    if version >= 3:
        xyzw = _smallest_three(np.frombuffer(blocks["rotations"], "<u4"))
    else:
        xyz = np.frombuffer(blocks["rotations"], np.uint8).reshape(n, 3).astype(np.float32) / np.float32(127.5) - np.float32(1.0)
        w = np.sqrt(np.maximum(np.float32(0.0), np.float32(1.0) - (xyz * xyz).sum(axis=1)))
        xyzw = np.concatenate([xyz, w[:, None]], axis=1)
    k = sh_coefficients(degree)
    sh = np.empty((n, k + 1, 3), np.float32)
    sh[:, 0] = dc
    sh[:, 1:] = (np.frombuffer(blocks["sh"], np.uint8).reshape(n, k, 3).astype(np.float32) - np.float32(128.0)) / np.float32(128.0)
    return {"means": means, "quats": xyzw[:, [3, 0, 1, 2]], "log_scales": log_scales, "opacity_logits": opacity_logits(byte_alpha(alphas)),
            "sh": sh, "extra": {}}


def _smallest_three(packed: np.ndarray) -> np.ndarray:
    """[N] uint32 -> [N, 4] float32 (x, y, z, w): 2 bits name the largest component; the other three, from
    the highest index down, are 10 bits each from the low end (sign bit, then 9 bits of |q| / √½)."""
    comp = packed.astype(np.uint32).copy()
    largest = (comp >> 30).astype(np.int64)
    q = np.zeros((comp.shape[0], 4), np.float32)
    squares = np.zeros(comp.shape[0], np.float32)
    mask, half = np.uint32(511), np.float32(np.sqrt(0.5))
    for i in range(3, -1, -1):
        rows = largest != i
        mag = (comp & mask).astype(np.float32)
        negative = ((comp >> 9) & 1).astype(bool)
        value = half * mag / np.float32(511.0)
        value = np.where(negative, -value, value)
        q[rows, i] = value[rows]
        squares[rows] += value[rows] * value[rows]
        comp = np.where(rows, comp >> 10, comp)
    q[np.arange(q.shape[0]), largest] = np.sqrt(np.maximum(np.float32(0.0), np.float32(1.0) - squares))
    return q


def _frame_signs(frame: int) -> tuple[float, float, float]:
    """(sx, sy, sz) that take a frame of SPZ_FRAMES to PLY's right-down-front: +1 where the axis agrees."""
    name = SPZ_FRAMES[frame]
    return (1.0 if name[0] == "R" else -1.0, 1.0 if name[1] == "D" else -1.0, 1.0 if name[2] == "F" else -1.0)


def sh_flip_signs(x: float, y: float, z: float) -> np.ndarray:
    """[15] signs of the degree 1-3 SH coefficients (3DGS order) when the axes are scaled by (x, y, z) ∈ {±1}³:
    each real SH basis function is a polynomial of one parity in each axis (the spz library's table)."""
    return np.array([y, z, x,  # degree 1: y, z, x
                     x * y, y * z, 1.0, x * z, 1.0,  # degree 2: xy, yz, 3z²-1, xz, x²-y²
                     y, x * y * z, y, z, x, z, x],  # degree 3
                    np.float32)


def _to_ply_frame(cols: dict, frame: int) -> None:
    """Flip the columns in place from `frame` to PLY's right-down-front (an axis flip F: μ -> Fμ,
    q's (x, y, z) -> (sy·sz·x, sx·sz·y, sx·sy·z), the SH by parity)."""
    sx, sy, sz = _frame_signs(frame)
    if (sx, sy, sz) == (1.0, 1.0, 1.0):
        return
    cols["means"] = cols["means"] * np.array([sx, sy, sz], np.float32) + np.float32(0.0)  # + 0: a flipped 0 is 0, not -0
    cols["quats"] = cols["quats"] * np.array([1.0, sy * sz, sx * sz, sx * sy], np.float32)
    k = cols["sh"].shape[1] - 1
    if k:
        signs = np.ones(k, np.float32)
        table = sh_flip_signs(sx, sy, sz)
        signs[: min(k, table.size)] = table[: min(k, table.size)]
        cols["sh"][:, 1:] *= signs[None, :, None]


# ----------------------------------------------------------------------------- writing

SPZ_WRITE_VERSIONS = (3, 4)
SPZ_WRITE_VERSION = 3  # gzip: every spz reader takes it; version 4 (zstd, 2025) only the current library and its ports
SPZ_FRACTIONAL_BITS = 12  # the spz library's: ~0.24 mm steps for positions within ±2048 units
SPZ_MAX_FRACTIONAL_BITS = 30  # the most whose scale 1 << bits a 32-bit int holds (the library's arithmetic)
SPZ_MAX_FIXED = (1 << 23) - 1  # the largest magnitude a 24-bit signed position holds
SPZ_SH1_BITS, SPZ_SH_REST_BITS = 5, 4  # the spz library's default quantisation of SH degree 1 and of degrees 2-3
SPZ_ZSTD_LEVEL = 12  # the spz library's
SQRT_HALF32 = np.float32(0.707106781186547524401)
WRITTEN_SUFFIXES = {".splat": "splat", ".spz": "spz"}  # any other name is written as a PLY
COMPRESSED_PLY_SUFFIX = ".compressed.ply"  # PlayCanvas's name for its compressed PLY


def written_format(path: str | Path) -> str:
    """"splat", "spz", "compressed.ply" or "ply": the file type `save_scene` writes to `path`, by its name."""
    name = Path(path).name.lower()
    if name.endswith(COMPRESSED_PLY_SUFFIX) and len(name) > len(COMPRESSED_PLY_SUFFIX):
        return "compressed.ply"
    return WRITTEN_SUFFIXES.get(Path(path).suffix.lower(), "ply")


def save_scene(scene: GaussianScene, path: str | Path, spz_version: int = SPZ_WRITE_VERSION) -> str:
    """Write `scene` atomically as the file type its name asks for (`written_format`): `.splat`
    (`save_splat`), `.spz` (`save_spz`), `.compressed.ply` (`save_compressed_ply`) or else an INRIA
    PLY (`save_ply`, lossless, extra properties and comments kept). Returns the type written."""
    kind = written_format(path)
    if kind == "splat":
        save_splat(scene, path)
    elif kind == "spz":
        save_spz(scene, path, spz_version)
    elif kind == "compressed.ply":
        save_compressed_ply(scene, path)
    else:
        save_ply(scene, path)
    return kind


def save_compressed_ply(scene: GaussianScene, path: str | Path) -> None:
    """Write `scene` as a PlayCanvas/SuperSplat compressed PLY (`scene.compressed_ply_bytes`: what
    splat-transform writes, byte for byte but the header's comment), atomically; SH values beyond
    ±4 are clipped and counted in a warning, non-finite values refuse the write."""
    path = Path(path)
    _refuse_nonfinite(scene, path, "compressed.ply")
    data, clipped = compressed_ply_bytes(scene)
    coarse = clipped.pop("coarse position")
    _warn_clipped(path, "compressed.ply", clipped)
    if coarse:
        log.warning("%s: %s splats are stored farther from their place than their own size and %.0f%% of the scene's extent: a far splat "
                    "widened their chunk's position range (the format keeps 11-10-11 bits of a chunk's range); a .ply keeps them exact",
                    path, f"{coarse:,}", 100 * COARSE_EXTENT_SHARE)
    write_bytes_atomic(path, data)


def check_writable(scene: GaussianScene, path: str | Path) -> None:
    """OutputError now for what `save_scene` would refuse later (non-finite values in a .splat, .spz or
    compressed PLY, positions beyond .spz's 24 bits), so that a command checks its export before it writes its
    other outputs."""
    path = Path(path)
    kind = written_format(path)
    if kind == "ply":
        return
    _refuse_nonfinite(scene, path, kind)
    if kind == "spz":
        spz_fractional_bits(scene.means, path)


def save_splat(scene: GaussianScene, path: str | Path) -> None:
    """Write `scene` as a `.splat` (module docstring), in the scene's order, atomically. Each byte is
    the nearest to what the reader decodes (antimatter15's converter truncates); colours beyond
    [0, 1], the only values the format cannot hold, are clipped and counted in a warning, and the
    view-dependent SH (degree ≥ 1) is dropped with a note."""
    path = Path(path)
    _refuse_nonfinite(scene, path, "splat")
    if scene.sh_degree:
        log.info("%s: .splat holds the base colour only: SH degrees 1-%d are dropped", path, scene.sh_degree)
    records, clipped = splat_records(scene)
    _warn_clipped(path, "splat", clipped)
    write_bytes_atomic(path, records.tobytes())


def splat_records(scene: GaussianScene) -> tuple[np.ndarray, dict[str, int]]:
    """[N] SPLAT_RECORD of a (finite) scene and the count of clipped values per field:

        scale = exp(log s)                   (float32; beyond float32's normal range: its largest or smallest, counted)
        rgba  = round(255·(½ + SH_C0·f_dc)), round(255·σ(opacity logit))
        rot   = round(128 + 128·q̂) ∈ [0, 255]  (q̂ = (w, x, y, z) / |q|; a component of 1 stores 255)
    """
    n = scene.num_gaussians
    out = np.zeros(n, SPLAT_RECORD)
    out["position"] = scene.means
    with np.errstate(over="ignore"):
        scale = np.exp(scene.log_scales.astype(np.float64))
    limits = np.finfo(np.float32)
    outside = (scale > limits.max) | (scale < limits.smallest_normal)  # a scale that rounds to 0 reads back as log 0 = -inf
    out["scale"] = np.clip(scale, limits.smallest_normal, limits.max)
    rgb, clipped_rgb = _bytes_of(255.0 * (0.5 + SH_C0 * scene.sh[:, 0].astype(np.float64)))
    with np.errstate(over="ignore"):  # σ in float64 from the logit: float32's σ of a read 255 (254.5/255) gave 254.49999 -> 254 (round 85b F1)
        alpha, _ = _bytes_of(255.0 / (1.0 + np.exp(-scene.opacity_logits.astype(np.float64))))
    out["rgba"][:, :3], out["rgba"][:, 3] = rgb, alpha
    out["rotation"], _ = _bytes_of(128.0 + 128.0 * scene.unit_quats64())
    return out, {"colour": clipped_rgb, "scale": int(outside.sum())}


def save_spz(scene: GaussianScene, path: str | Path, version: int = SPZ_WRITE_VERSION) -> None:
    """Write `scene` as an `.spz` of `version` (3: gzip, 4: zstd streams), atomically: the spz library's
    packGaussians (its float32 arithmetic, rounding half away from zero, SH degree 1 in 5 bits and
    2-3 in 4), stored right-up-back. Two things differ: positions beyond ±2048 units get fewer
    fractional bits (the header records them; the library wraps them around), and values the bytes
    cannot hold (colours, log scales outside [-10, 5.94], SH outside [-1, 1)) are counted in a warning
    when clipped."""
    path = Path(path)
    if version not in SPZ_WRITE_VERSIONS:
        raise ValueError(f"spz version {version} cannot be written; drsplat writes versions {SPZ_WRITE_VERSIONS}")
    _refuse_nonfinite(scene, path, "spz")
    data, fractional_bits, clipped = spz_file_bytes(scene, version, path)
    if fractional_bits < SPZ_FRACTIONAL_BITS:
        _say_coarse_positions(scene, path, fractional_bits)
    _warn_clipped(path, "spz", clipped)
    write_bytes_atomic(path, data)




def _say_coarse_positions(scene: GaussianScene, path: Path, fractional_bits: int) -> None:
    """The note that positions beyond ±2048 units are stored in coarser steps: a warning when the
    rounding (half a step) exceeds COARSE_STEP_SHARE of the median Gaussian's largest scale (a
    georeferenced scene 1e6 units out: steps of 1/8 against Gaussians of 0.1 lose their detail)."""
    step = 2.0 ** -fractional_bits
    text = (f"{path}: positions reach {float(np.abs(scene.means).max()):.4g} units, beyond the ±2048 that .spz holds at 1/4096 "
            f"steps: stored with {fractional_bits} fractional bits (steps of {step:.3g})")
    coarse = float32_coarse_positions(scene.means, scene.log_scales.max(axis=1), step)  # the rule a load of the file judges it by
    if coarse is not None:
        size = coarse[2]
        log.warning("%s, which moves a Gaussian by up to %.2g of the median Gaussian's size (%.3g); move the scene near the origin, "
                    "or export .ply or .compressed.ply, to keep its detail", text, step / 2 / size, size)
    else:
        log.info("%s", text)


def spz_file_bytes(scene: GaussianScene, version: int = SPZ_WRITE_VERSION, path: Path | None = None) -> tuple[bytes, int, dict[str, int]]:
    """The bytes of an spz file of a (finite) scene, its positions' fractional bits and the count of
    clipped values per field (`save_spz`). path: named by the error when positions do not fit."""
    fractional_bits = spz_fractional_bits(scene.means, path)
    blocks, clipped = spz_blocks_of(scene, version, fractional_bits)
    n, degree = scene.num_gaussians, scene.sh_degree
    if version < 4:
        header = np.zeros(1, SPZ_LEGACY_HEADER)
        header[["magic", "version", "points", "sh_degree", "fractional_bits"]] = (NGSP_MAGIC, version, n, degree, fractional_bits)
        packer = zlib.compressobj(6, zlib.DEFLATED, 16 + zlib.MAX_WBITS, 9)  # the library's deflateInit2 (gzip wrapper)
        payload = header.tobytes() + b"".join(blocks)
        return packer.compress(payload) + packer.flush(), fractional_bits, clipped
    compressor = zstandard.ZstdCompressor(level=SPZ_ZSTD_LEVEL)
    streams = [(compressor.compress(b), len(b)) for b in blocks if b]  # empty blocks (SH of degree 0) have no stream
    header = np.zeros(1, SPZ_HEADER)
    header[["magic", "version", "points", "sh_degree", "fractional_bits", "streams", "toc_offset"]] = (
        NGSP_MAGIC, version, n, degree, fractional_bits, len(streams), SPZ_HEADER.itemsize)
    toc = np.array([(len(c), u) for c, u in streams], "<u8").reshape(-1, 2)
    return header.tobytes() + toc.tobytes() + b"".join(c for c, _ in streams), fractional_bits, clipped


def spz_fractional_bits(means: np.ndarray, path: Path | None = None) -> int:
    """The most fractional bits (≤ SPZ_FRACTIONAL_BITS) at which every coordinate of means [N, 3]
    fits a 24-bit signed fixed-point number; OutputError when none does."""
    reach = float(np.abs(means.astype(np.float64)).max()) if means.size else 0.0
    for bits in range(SPZ_FRACTIONAL_BITS, -1, -1):
        if np.floor(reach * 2.0 ** bits + 0.5) <= SPZ_MAX_FIXED:
            return bits
    raise OutputError(path, f"positions reach {reach:.4g} units; .spz stores 24-bit fixed point (at most ±{SPZ_MAX_FIXED:,}): "
                            "write a .ply, or move the scene nearer the origin")


def spz_blocks_of(scene: GaussianScene, version: int, fractional_bits: int) -> tuple[list[bytes], dict[str, int]]:
    """positions, alphas, colors, scales, rotations, sh of a scene (packGaussians, stored right-up-back)
    and the count of clipped values per field. The arithmetic is the library's float32:

        position  round(x·2^f) in 24 bits            alpha  round(255·σ(logit))
        color     round(f_dc·38.25 + 127.5)          scale  round((log s + 10)·16)
        rotation  smallest three (`pack_smallest_three`)
        sh        round(v·128) + 128, to the centre of its 2^(8 - bits) bucket
    """
    sx, sy, sz = _frame_signs(DEFAULT_SPZ_FRAME)
    f32 = np.float32
    means = scene.means.astype(f32) * np.array([sx, sy, sz], f32)
    fixed = _round_half_away(means * f32(2.0 ** fractional_bits)).astype(np.int64) & 0xFFFFFF
    positions = np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, (fixed >> 16) & 0xFF], axis=-1).astype(np.uint8)
    with np.errstate(over="ignore"):  # exp(-logit) of a logit below -88.7 is inf in float32: σ = 0, as intended
        sigmoid = f32(1.0) / (f32(1.0) + np.exp(-scene.opacity_logits.astype(f32)))
    alphas, _ = _bytes_of(sigmoid * f32(255.0))
    colors, clipped_colors = _bytes_of(scene.sh[:, 0].astype(f32) * f32(SPZ_COLOR_SCALE * 255.0) + f32(0.5 * 255.0))
    scales, clipped_scales = _bytes_of((scene.log_scales.astype(f32) + f32(10.0)) * f32(16.0))
    xyzw = scene.unit_quats64()[:, [1, 2, 3, 0]].astype(f32) * np.array([sy * sz, sx * sz, sx * sy, 1.0], f32)
    rotations = pack_smallest_three(xyzw)
    sh, clipped_sh = _sh_bytes(scene, (sx, sy, sz))
    blocks = [positions.tobytes(), alphas.tobytes(), colors.tobytes(), scales.tobytes(), rotations.tobytes(), sh.tobytes()]
    return blocks, {"colour": clipped_colors, "scale": clipped_scales, "SH": clipped_sh}


def pack_smallest_three(xyzw: np.ndarray) -> np.ndarray:
    """[N, 4] float32 unit quaternions (x, y, z, w) -> [N] '<u4' (the spz library's
    packQuaternionSmallestThree): the index of the largest |component| (the first of equal ones) in
    the top 2 bits, then the other three in index order, 10 bits each: the sign relative to the
    largest's, then trunc(511·|q_i|/√½ + ½) in 9 bits (float32)."""
    n = xyzw.shape[0]
    largest = np.argmax(np.abs(xyzw), axis=1)
    negate = xyzw[np.arange(n), largest] < 0
    comp = largest.astype(np.uint32)
    for i in range(4):
        other = largest != i
        q = xyzw[:, i]
        sign = ((q < 0) ^ negate).astype(np.uint32)
        mag = (np.float32(511.0) * (np.abs(q) / SQRT_HALF32) + np.float32(0.5)).astype(np.uint32)
        comp = np.where(other, (comp << np.uint32(10)) | (sign << np.uint32(9)) | mag, comp)
    return comp.astype("<u4")


def _sh_bytes(scene: GaussianScene, signs: tuple[float, float, float]) -> tuple[np.ndarray, int]:
    """[N, K, 3] uint8 of the SH beyond the base colour (flipped to the stored frame by parity) and
    how many were clipped: quantizeSH of the spz library, degree 1 in SPZ_SH1_BITS, the rest in
    SPZ_SH_REST_BITS."""
    rest = scene.sh[:, 1:].astype(np.float32)
    k = rest.shape[1]
    if k == 0:
        return np.zeros((scene.num_gaussians, 0, 3), np.uint8), 0
    rest = rest * sh_flip_signs(*signs)[:k][None, :, None]
    q = _round_half_away(rest * np.float32(128.0)).astype(np.int64) + 128
    clipped = int(((q < 0) | (q > 255)).sum())  # outside [-1, 127/128]; the top bucket's centre 256 -> 255 is the format's own
    bucket = np.where(np.arange(k) < 3, 1 << (8 - SPZ_SH1_BITS), 1 << (8 - SPZ_SH_REST_BITS))[None, :, None]
    q = (q + bucket // 2) // bucket * bucket
    return np.clip(q, 0, 255).astype(np.uint8), clipped


def _round_half_away(x: np.ndarray) -> np.ndarray:
    """C's round() of float32 values (half away from zero), exactly: in float64, where x + ½ is exact."""
    x = np.asarray(x, np.float64)
    return np.copysign(np.floor(np.abs(x) + 0.5), x)


def _bytes_of(x: np.ndarray) -> tuple[np.ndarray, int]:
    """The spz library's toUint8 (round half away, clamp to [0, 255]) and how many values were clamped."""
    r = _round_half_away(x)
    clipped = int(((r < 0) | (r > 255)).sum())
    return np.clip(r, 0, 255).astype(np.uint8), clipped


def _refuse_nonfinite(scene: GaussianScene, path: Path, kind: str) -> None:
    """OutputError naming how many Gaussians hold a NaN or infinite value, field by field: the bytes
    of a .splat, .spz or compressed PLY hold none (a loaded scene has none: its reader drops such rows)."""
    fields = {"means": scene.means, "rotations": scene.quats, "scales": scene.log_scales, "opacities": scene.opacity_logits[:, None],
              "colours and SH": scene.sh.reshape(scene.num_gaussians, scene.sh.shape[1] * 3)}
    counts = {name: int((~np.isfinite(v)).any(axis=1).sum()) for name, v in fields.items()}
    bad = {name: c for name, c in counts.items() if c}
    if bad:
        raise OutputError(path, f"{', '.join(f'{c:,} Gaussians have non-finite {name}' for name, c in bad.items())}; "
                                f".{kind} stores quantised values, which hold no NaN or infinity: write a plain .ply")


def _warn_clipped(path: Path, kind: str, clipped: dict[str, int]) -> None:
    counts = {name: c for name, c in clipped.items() if c}
    if counts:
        log.warning("%s: %s clipped to what .%s holds", path, ", ".join(f"{c:,} {name} values" for name, c in counts.items()), kind)

