"""LangSplat per-image feature files: `<stem>_s.npy` mask ids and `<stem>_f.npy` embeddings.

Format (as written by LangSplat's preprocess.py and by `drsplat features`):
- `<stem>_s.npy`: (L, H, W) mask ids, -1 = no mask, any int or float dtype. LangSplat writes
  L = 4 levels (default, s, m, l) whose ids are *cumulative*: the ids of level j are offsets
  into the one concatenated embedding array, after the masks of levels 0..j-1.
  A (H, W) array is read as a single level.
- `<stem>_f.npy`: (M, D) embeddings, one row per mask of all levels together.
- `manifest.json` (optional, drsplat's own): how the features were made (mask generator,
  CLIP model and pretrained tag, versions, parameters).

Files whose per-level ids restart at 0 (not cumulative) are recognised because their levels'
id ranges overlap; they are read with offsets = Σ (max id + 1) of the previous levels.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from drsplat.errors import InputError, OutputError, hidden_character
from drsplat.features.modelid import WEIGHTS_DIGEST, model_id_sources
from drsplat.utils import atomic_path, load_npy, npy_header, output_target, read_json, refuse_write_protected, save_npy_atomic
from drsplat.defaults import DEFAULT_LEVEL, MIN_NORM, UNIT_TOLERANCE

log = logging.getLogger(__name__)

SEG_SUFFIX = "_s.npy"
FEAT_SUFFIX = "_f.npy"
MANIFEST_NAME = "manifest.json"
STAMP_JOURNAL = ".image_stamps.jsonl"  # `features`' journal of a run's image stamps (drsplat.features.extract.ImageStamps)
MAX_MODEL_ID_CHARS = 256  # the longest CLIP model id a manifest may give (open_clip's names are under 60 characters)
# the manifest fields drsplat reads: (name, accepted JSON types, what it should be)
MANIFEST_FIELDS = (("clip_model_id", str, "a CLIP model id"), ("clip", (dict, str), "an object naming the CLIP model"),
                   ("dim", int, "the embedding dimension"))
INT64_LIMIT = 2.0**63  # the first float mask id that int64 cannot hold
FEATURE_FILE_PATTERNS = (f"*{SEG_SUFFIX}", f"*{FEAT_SUFFIX}", MANIFEST_NAME, STAMP_JOURNAL)  # what an output must not be named inside a features folder


def seg_path(features_dir: str | Path, stem: str) -> Path:
    return Path(features_dir) / f"{stem}{SEG_SUFFIX}"


def feat_path(features_dir: str | Path, stem: str) -> Path:
    return Path(features_dir) / f"{stem}{FEAT_SUFFIX}"


def is_apple_double(name: str) -> bool:
    """True for a macOS AppleDouble file name, `._<name>`: the resource fork a Mac writes beside every
    file it copies to a FAT/exFAT disk or into a zip (`._orbit_000_s.npy`, 4 KiB of metadata). Never a
    feature file, so never counted as one (round 51: each was listed as a feature file without a camera)."""
    return name.startswith("._")


def list_stems(features_dir: str | Path, suffix: str = SEG_SUFFIX) -> list[str]:
    """Sorted image stems that have a `<stem><suffix>` regular file (by default `<stem>_s.npy`) in
    `features_dir`; AppleDouble files (`is_apple_double`) are not feature files."""
    features_dir = Path(features_dir)
    if not features_dir.is_dir():
        raise InputError(features_dir, "features folder does not exist")
    return sorted(p.name[: -len(suffix)] for p in features_dir.glob(f"*{suffix}") if p.is_file() and not is_apple_double(p.name))


def irregular_feature_entries(features_dir: str | Path) -> list[str]:
    """Names in `features_dir` shaped like a feature file (`*_s.npy`, `*_f.npy`) that are not regular
    files (a folder, a device, a broken link): `list_stems` passes over them. AppleDouble names are no
    feature files whatever they are."""
    return sorted(p.name for suffix in (SEG_SUFFIX, FEAT_SUFFIX) for p in Path(features_dir).glob(f"*{suffix}")
                  if not p.is_file() and not is_apple_double(p.name))


def write_features(features_dir: str | Path, stem: str, seg: np.ndarray, feats: np.ndarray) -> None:
    """Write one image's feature pair atomically (embeddings first, then mask ids).

    seg: [L, H, W] (or [H, W]) integer mask ids, -1 = none, cumulative across levels.
    feats: [M, D] float embeddings; every id in `seg` must be < M.
    """
    seg = np.asarray(seg)
    feats = np.asarray(feats)
    if seg.ndim == 2:
        seg = seg[None]
    if seg.ndim != 3:
        raise ValueError(f"seg must be [L, H, W], got shape {seg.shape}")
    if feats.ndim != 2:
        raise ValueError(f"feats must be [M, D], got shape {feats.shape}")
    if not np.issubdtype(seg.dtype, np.integer):
        raise ValueError(f"seg must be an integer array, got {seg.dtype}")
    if seg.size and (seg.min() < -1 or seg.max() >= feats.shape[0]):
        raise ValueError(f"seg ids must be in [-1, {feats.shape[0] - 1}], got [{seg.min()}, {seg.max()}]")
    dtype = np.int16 if feats.shape[0] < 2**15 else np.int32
    for path in (feat_path(features_dir, stem), seg_path(features_dir, stem)):  # both before either: never one file of a pair replaced
        refuse_write_protected(output_target(path))  # (round 60c: a new _f.npy beside a protected old _s.npy)
    save_npy_atomic(feat_path(features_dir, stem), np.ascontiguousarray(feats, dtype=np.float32 if feats.dtype == np.float64 else feats.dtype))
    save_npy_atomic(seg_path(features_dir, stem), np.ascontiguousarray(seg, dtype=dtype))


def is_valid_pair(features_dir: str | Path, stem: str) -> bool:
    """True if both files of `stem` exist, have readable headers, full data and matching shapes.

    Cheap: reads only the headers and compares file sizes, so truncated or half-written files
    are detected without loading the arrays.
    """
    paths = seg_path(features_dir, stem), feat_path(features_dir, stem)
    try:
        (s_shape, s_dtype, s_offset), (f_shape, f_dtype, f_offset) = (npy_header(p) for p in paths)
        for path, shape, dtype, offset in ((paths[0], s_shape, s_dtype, s_offset), (paths[1], f_shape, f_dtype, f_offset)):
            if path.stat().st_size != offset + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize:  # trailing bytes: not ours
                return False
        check_seg_layout(paths[0], s_shape, s_dtype)
        check_feat_layout(paths[1], f_shape, f_dtype)
    except (InputError, OSError):
        return False
    return True


def check_seg_layout(path: Path, shape: tuple[int, ...], dtype: np.dtype, level: int | None = None) -> None:
    """InputError (naming `path` and the field) unless a mask-id file's shape and dtype are the
    format's: (L, H, W) or (H, W) with L, H, W > 0, integer or float ids (not bool), and, for a
    `level`, level < L unless L = 1 (a single level serves every level; among files with several
    levels, registration warns of it: `registration.views.single_level_files_note`)."""
    if len(shape) not in (2, 3) or 0 in shape:
        raise InputError(path, f"mask ids have shape {tuple(shape)}, expected (L, H, W) or (H, W) with L, H, W > 0", field="shape")
    if dtype.kind not in "iuf":
        raise InputError(path, f"mask ids have dtype {dtype}, expected integers or floats (-1 = no mask, else an embedding row)", field="dtype")
    levels = shape[0] if len(shape) == 3 else 1
    if level is not None and levels > 1 and not 0 <= level < levels:
        raise InputError(path, f"level {level} requested but the file has {levels} levels (0..{levels - 1})", field="shape")


def check_feat_layout(path: Path, shape: tuple[int, ...], dtype: np.dtype) -> None:
    """InputError (naming `path` and the field) unless an embedding file is (M, D) numbers with D > 0."""
    if len(shape) != 2 or shape[1] == 0:
        raise InputError(path, f"embeddings have shape {tuple(shape)}, expected (M, D) with D > 0", field="shape")
    if dtype.kind not in "iuf":
        raise InputError(path, f"embeddings have dtype {dtype}, expected floats", field="dtype")


def _load_npy(path: Path, what: str) -> np.ndarray:
    if not path.is_file():
        raise InputError(path, f"{what} file is missing")
    return load_npy(path, what)


def _ids_as_int(seg: np.ndarray, path: Path) -> np.ndarray:
    """Mask ids of any int/float dtype as int64; non-integer or non-finite floats, and floats outside
    [-1, 2^63) (`check_float_id_range`), are errors."""
    if np.issubdtype(seg.dtype, np.unsignedinteger) and seg.size and seg.dtype.itemsize >= 8:
        top = int(seg.max())
        if top > np.iinfo(np.int64).max:  # astype(int64) would wrap 2^64-1 to -1 ("no mask") silently
            raise InputError(path, f"mask id {top} ({seg.dtype}) is out of range: unsigned ids cannot mean -1 (no mask); "
                                   "store ids in a signed integer dtype with -1 for no mask")
    if np.issubdtype(seg.dtype, np.integer):  # bool and other kinds are refused by check_seg_layout before
        return seg.astype(np.int64, copy=False)
    bad = int(np.count_nonzero(~np.isfinite(seg)))
    if bad:
        raise InputError(path, f"{bad} mask ids are not finite (NaN/inf)")
    ids = np.rint(seg)
    off = int(np.count_nonzero(np.abs(ids - seg) > 1e-3))
    if off:
        raise InputError(path, f"{off} mask ids are not whole numbers")
    check_float_id_range(ids, path)
    return ids.astype(np.int64)


def check_float_id_range(ids: np.ndarray, path: Path) -> None:
    """InputError, naming the value the file holds, unless whole-number float ids lie in
    [-1, 2^63): below -1 no id means anything, and at 2^63 or more it is no row of any embedding
    file. Checked before the cast to int64, which would turn such values into -2^63 with a
    RuntimeWarning and report a value the file does not hold."""
    if ids.size == 0:
        return
    low = float(ids.min())
    if low < -1:
        raise InputError(path, f"mask ids must be >= -1, found {low:g}")
    # compared in long double, which holds every float16-64 value and 2^63 exactly: float(2^63 - 1) of a
    # long-double file rounds up to 2^63, and the count, taken in the file's precision, then found none
    limit = np.longdouble(INT64_LIMIT)
    top = np.longdouble(ids.max())
    if top >= limit:
        beyond = int(np.count_nonzero(ids >= limit))
        raise InputError(path, f"{beyond} mask ids are beyond any embedding row (largest {float(top):g})")


def restarted_level_counts(seg: np.ndarray) -> list[int] | None:
    """Each level's embedding count read from its ids when the levels' ids restart at 0, or None
    when they are already cumulative (LangSplat's form: the id ranges of the levels do not overlap).

    seg: [L, H, W] int64. A level's count is read as its largest id + 1 (0 for a level with no
    mask), which is short by the masks after its last visible one (a mask painted over by later
    ones covers no pixel): `read_features_report` checks the counts against the embeddings
    (`restarted_counts_problem`) before offsetting a level by the counts before it. Python
    ints: a hostile id near 2^63 made the int64 sums wrap, and the wrapped ids then named valid rows.
    """
    lo = [int(lvl[lvl >= 0].min()) if (lvl >= 0).any() else -1 for lvl in seg]
    hi = [int(lvl.max()) for lvl in seg]
    present = [low >= 0 for low in lo]
    overlapping = any(present[j] and any(present[i] and lo[j] <= hi[i] for i in range(j)) for j in range(1, len(seg)))
    return [top + 1 if here else 0 for top, here in zip(hi, present)] if overlapping else None


def restarted_counts_problem(counts: list[int], level: int, num_embeddings: int, feat_name: str) -> str | None:
    """Why level `level`'s rows cannot be told in a file whose levels' ids restart at 0 (`counts`, its
    levels' counts read from the ids), or None: the counts must add up to the file's embeddings,
    else a level before it may have lost its last masks from the ids, and its rows would be shifted
    (round 63a: a painted-over last mask of level 0 gave every level-1 pixel the embedding of the mask
    before its own, silently)."""
    if not level or sum(counts) == num_embeddings:
        return None
    return (f"its {len(counts)} levels' mask ids each start at 0, so level {level}'s embeddings are taken to follow those of the "
            f"levels before it, each level's count read as its largest id + 1 ({' + '.join(map(str, counts))} = {sum(counts)}); but "
            f"{feat_name} holds {num_embeddings} embeddings, so a level's last masks cover no pixel (painted over) or rows are missing, "
            f"and which rows are level {level}'s cannot be told. Store the ids cumulative across levels (LangSplat's form: each "
            "level's ids continue after the previous level's)")


def out_of_range_ids(top: int, offset: int, level: int, num_embeddings: int, feat_name: str, dtype: np.dtype) -> str:
    """Why mask id `top` (after the level's `offset`, 0 when the levels' ids are already global) is
    no row of the embeddings, naming the value stored in the file and, for the largest value of an
    unsigned dtype, the likely cause: that value meant as "no mask", which has no -1."""
    stored = top - offset
    where = f"mask id {stored} at level {level}" + (f" ({top} once offset by the {offset} ids of the levels before it)" if offset else "")
    hint = ""
    if np.dtype(dtype).kind == "u" and stored == np.iinfo(dtype).max:
        hint = f"; {stored} is the largest {np.dtype(dtype)}: if it means 'no mask', store the ids in a signed dtype with -1 there"
    return f"{where} is out of range: {feat_name} has only {num_embeddings} embeddings{hint}"


def read_features(features_dir: str | Path, stem: str, level: int = DEFAULT_LEVEL, *, drop_nonfinite: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Mask ids of one level and all embeddings of one image.

    Returns mask_ids: [H, W] int32, -1 = none, indices into feats; feats: [M, D] float32.
    A single-level file (2-D, or L = 1) serves every requested level.

    Non-finite embeddings are an error naming their count; with drop_nonfinite=True their rows
    are zeroed and their pixels set to -1 instead (a warning gives the count).
    """
    ids, feats, _ = read_features_report(features_dir, stem, level, drop_nonfinite=drop_nonfinite)
    return ids, feats


def read_features_report(features_dir: str | Path, stem: str, level: int = DEFAULT_LEVEL, *, drop_nonfinite: bool = False) -> tuple[np.ndarray, np.ndarray, int]:
    """`read_features` plus the number of embeddings dropped for non-finite values."""
    spath, fpath = seg_path(features_dir, stem), feat_path(features_dir, stem)
    seg = _load_npy(spath, "mask-id")
    feats = _load_npy(fpath, "embedding")
    check_seg_layout(spath, seg.shape, seg.dtype, level)
    check_feat_layout(fpath, feats.shape, feats.dtype)
    if seg.ndim == 2:
        seg = seg[None]
    if seg.shape[0] == 1:
        level = 0
    raw_dtype = seg.dtype
    seg = _ids_as_int(seg, spath)
    if seg.size and seg.min() < -1:
        raise InputError(spath, f"mask ids must be >= -1, found {int(seg.min())}")
    m = feats.shape[0]
    for at, lvl in enumerate(seg):  # an id ≥ M is no row in either reading of the levels (round 85d F5: one at level 0 was
        top = int(lvl.max()) if lvl.size else -1  # blamed on a valid level-1 id, one at level 3 passed without a word)
        if top >= m:
            raise InputError(spath, out_of_range_ids(top, 0, at, m, fpath.name, raw_dtype))
    ids = seg[level]
    counts = restarted_level_counts(seg)
    offset = 0 if counts is None else sum(counts[:level])
    stored_top = int(ids.max())
    if stored_top >= 0 and stored_top + offset >= m:  # compared in Python ints, before any int64 sum could wrap
        raise InputError(spath, out_of_range_ids(stored_top + offset, offset, level, m, fpath.name, raw_dtype))
    problem = None if counts is None else restarted_counts_problem(counts, level, m, fpath.name)
    if problem is not None:
        raise InputError(spath, problem)
    if offset:
        ids = np.where(ids >= 0, ids + offset, -1)
    with np.errstate(over="ignore", invalid="ignore"):  # float64 values past float32 become inf: counted below, without numpy's warning
        feats = feats.astype(np.float32)
    row_ok = np.isfinite(feats).all(axis=1)
    norms = embedding_norms(feats)
    row_ok &= norms <= np.finfo(np.float32).max  # rows whose norm overflows float32 (values near 3e38): as unusable as inf
    bad = int(m - np.count_nonzero(row_ok))
    if bad:
        if not drop_nonfinite:
            raise InputError(fpath, f"{bad} of {m} embeddings contain non-finite values (NaN/inf) or have a norm beyond float32")
        log.warning("%s: %d of %d embeddings contain non-finite values or have a norm beyond float32; their masks are ignored", fpath, bad, m)
        feats[~row_ok] = 0.0
        ids = np.where((ids >= 0) & ~row_ok[np.maximum(ids, 0)], -1, ids)
    zero = row_ok & ~(feats != 0).any(axis=1)
    if zero.any():  # a placeholder, not an embedding: its pixels would add weight to their Gaussians and no direction
        log.warning("%s: %d of %d embeddings are all zero (no direction to lift); their masks are ignored", fpath, int(zero.sum()), m)
        ids = np.where((ids >= 0) & zero[np.maximum(ids, 0)], -1, ids)
    tiny = row_ok & ~zero & (norms < MIN_NORM)
    if tiny.any():  # subnormal entries keep few bits: rescaled, a row of 1e-44 kept cosine 0.61 to its direction (round 30)
        log.warning("%s: %d of %d embeddings have a norm below %.3g (float32's smallest normal number; the smallest %.3g), too "
                    "small to hold a direction; their masks are ignored", fpath, int(tiny.sum()), m, MIN_NORM, norms[tiny].min())
        ids = np.where((ids >= 0) & tiny[np.maximum(ids, 0)], -1, ids)
        zero |= tiny
    # registration lifts directions: a mask's length would weigh it in the paper's mean, the vote trims
    # by unit cluster means, and tiny lengths sum into float32 subnormals
    off = row_ok & ~zero & (np.abs(norms - 1.0) > UNIT_TOLERANCE)
    if off.any():
        log.warning("%s: %d of %d embeddings are not of unit length (norms %.3g to %.3g; CLIP's are 1); rescaled to unit length, "
                    "since only their direction is lifted", fpath, int(off.sum()), m, norms[off].min(), norms[off].max())
        feats[off] = (feats[off].astype(np.float64) / norms[off, None]).astype(np.float32)
    return ids.astype(np.int32), feats, bad


def embedding_norms(feats: np.ndarray, chunk: int = 1 << 16) -> np.ndarray:
    """[N] float64 L2 norms of embedding rows feats [N, D] float32, squares summed in float64 (whose range
    holds the square of every finite float32, 3.4e38² and 1e-45²: no overflow or underflow), `chunk`
    rows at a time so a large array is not copied whole in float64. A non-finite row's norm is NaN or inf."""
    out = np.empty(feats.shape[0], np.float64)
    with np.errstate(invalid="ignore"):
        for i in range(0, feats.shape[0], chunk):
            out[i : i + chunk] = np.sqrt(np.square(feats[i : i + chunk], dtype=np.float64).sum(axis=1))
    return out


def resample_nearest(mask_ids: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour resize of a mask-id map to (height, width).

    mask_ids: [H, W]. Returns [height, width]. Pixel centres map onto each other as intrinsics
    scale (Camera.scaled): destination pixel x samples source column
    floor((x + 0.5) · W / width), and the same for rows: in integers, ((2x + 1) · W) // (2 · width),
    so a centre that falls exactly on a source pixel's edge takes the pixel after it (in float64,
    (x + 0.5) · (W / width) fell one short for ~2 % of the size pairs, e.g. x = 24 of 49 from 2).
    """
    h, w = mask_ids.shape
    if (h, w) == (height, width):
        return mask_ids
    return mask_ids[source_pixels(height, h)[:, None], source_pixels(width, w)[None, :]]


def source_pixels(size: int, source_size: int) -> np.ndarray:
    """[size] int64: the source pixel under each destination pixel centre, ⌊(x + ½)·source_size / size⌋."""
    x = np.arange(size, dtype=np.int64)
    return np.minimum(((2 * x + 1) * source_size) // (2 * size), source_size - 1)


def write_manifest(features_dir: str | Path, manifest: dict[str, Any]) -> None:
    """Write `manifest.json` atomically (mask generator, CLIP model/pretrained, versions, params);
    OutputError, before anything is written, for a CLIP model text `read_manifest` would refuse
    (`model_id_text_problem`; `--pretrained` is free text with --clip-checkpoint)."""
    path = Path(features_dir) / MANIFEST_NAME
    problem = model_id_text_problem(manifest)
    if problem is not None:
        raise OutputError(path, f"field '{problem[0]}': {problem[1]}")
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(manifest, indent=2, sort_keys=True, default=str) + "\n")


def read_manifest(features_dir: str | Path) -> dict[str, Any]:
    """The features folder's manifest, or {} when there is none (e.g. features made by LangSplat)."""
    path = Path(features_dir) / MANIFEST_NAME
    if not os.path.lexists(path):
        return {}
    if not path.exists():  # a symlink to nothing (or a loop): not "no manifest", whose model id would then be unknown
        raise InputError(path, "is a symbolic link to nothing (or a loop of links); point it at the features' manifest, or remove it")
    data = read_json(path, "a features manifest")
    if not isinstance(data, dict):
        raise InputError(path, "expected a JSON object")
    for field, kinds, meaning in MANIFEST_FIELDS:
        if field in data and not isinstance(data[field], kinds):
            log.warning("%s: field '%s' is %s, not %s; it is ignored", path, field, json.dumps(data[field])[:40], meaning)
    warn_if_weights_unreadable(path, data.get("clip_weights"))
    problem = model_id_text_problem(data)
    if problem is not None:
        raise InputError(path, problem[1], field=problem[0])
    return data


def warn_if_weights_unreadable(path: Path, value: Any) -> None:
    """Warn when a manifest's `clip_weights` is neither null (a hub tag, no file) nor the 'size:sha1' digest
    `drsplat features` writes: registration then records no digest, and no query can tell the text encoder's
    weights from another file's (`check_clip_weights`), so a hand-edited or damaged value is said, not dropped."""
    if value is None or (isinstance(value, str) and WEIGHTS_DIGEST.fullmatch(value)):
        return
    log.warning("%s: field 'clip_weights' is %s, not the 'size:sha1' digest of a CLIP weights file that drsplat features writes; it is "
                "ignored, so the registered PLY records no weights and queries check the text encoder by its model name alone",
                path, json.dumps(value)[:60])


def model_id_text_problem(manifest: dict[str, Any]) -> tuple[str, str] | None:
    """(field, why) for the first string the CLIP model id is made of (`model_id_sources`) that holds
    a character a terminal would not show as itself (`hidden_character`: a newline, ESC, U+202E) or
    is longer than MAX_MODEL_ID_CHARS, or None. Registration copies the id into the registered PLY's header, whose reader refuses such a
    character as a sign of tampering: the manifest's reader and writer refuse it first."""
    for field, text in model_id_sources(manifest):
        if len(text) > MAX_MODEL_ID_CHARS:
            return field, (f"{json.dumps(text[:40])[:-1]}...\" is {len(text):,} characters long; a CLIP model name is at most "
                           f"{MAX_MODEL_ID_CHARS} (e.g. \"ViT-B-16/laion2b_s34b_b88k\"), and every registered PLY's header would carry it")
        hidden = hidden_character(text)
        if hidden is not None:  # json.dumps escapes it, so the message itself stays one plain line
            return field, (f"{json.dumps(text)[:60]} holds {hidden}, which a terminal would not show as itself; a CLIP model is named "
                           "in printable text (e.g. \"ViT-B-16/laion2b_s34b_b88k\"), and a registered PLY could not carry this name in its header")
    return None


def check_manifest_dim(features_dir: str | Path, manifest: dict[str, Any], dim: int) -> None:
    """Warn when the manifest's `dim` disagrees with the dimension of the feature files (`dim`):
    the files are what registration reads, so the manifest describes other features."""
    stated = manifest.get("dim")
    if isinstance(stated, int) and not isinstance(stated, bool) and stated != dim:
        log.warning("%s: field 'dim' says %d-D embeddings, but the feature files hold %d-D ones: the manifest describes other "
                    "features (its CLIP model may be wrong too)", Path(features_dir) / MANIFEST_NAME, stated, dim)
