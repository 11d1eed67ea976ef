"""The registered-PLY format: how a `LanguageField` is stored in extra vertex properties of an INRIA PLY (the one place it is specified).

A registered PLY is an INRIA-layout PLY plus:

- the header comment `drsplat.lang kind=<exact|pq|ivfpq> dim=<D> clip=<model> [codebook=<file>
  codebook_crc=<8 hex>]` (values URL-quoted), the field's metadata; codebook_crc is the CRC-32 of
  the codebook file written beside the PLY, checked on load (files written before 2026-11-30 have
  none);
- the same metadata as a vertex property, `lang_meta` (ushort; uint when L > 255), for tools that
  keep vertex properties but drop header comments (PlayCanvas splat-transform does): with b the
  metadata's UTF-8 bytes (the comment without its prefix, L = len(b) <= META_LONG_MAX_BYTES), row i
  holds (k << 8) | b[k] with k = i mod L. Every row carries one (position, byte) pair, so the text can
  be read back after rows are reordered or subset (each position by majority over its rows) as
  long as every position keeps a row; 2 bytes per Gaussian (4 in uint cells). A scene of n < L rows gets
  C = ceil(L / n) columns `lang_meta`, `lang_meta_1`, ... (`encode_meta_columns`), so small
  exports stay queryable without their comment;
- `lang_weight` float: total registration weight (0 = unassigned);
- exact: `lang_0 .. lang_{D-1}` ushort holding float16 bit patterns; pq / ivfpq:
  `lang_code_0 .. lang_code_{M-1}` uchar, `lang_norm` float, ivfpq also `lang_list` int; the
  codebook file (`<stem>.codebook.faiss`) sits next to the PLY, named in the metadata.

Readers take the comment when present (files written before `lang_meta` existed have only it),
else `lang_meta`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import zlib
from pathlib import Path
from urllib.parse import quote, unquote

import numpy as np

from drsplat.cameras import IMAGE_SUFFIXES
from drsplat.errors import InputError, OutputError, hidden_character, shown_path
from drsplat.features.modelid import WEIGHTS_DIGEST
from drsplat.lang.backends import BACKENDS, needs_codebook
from drsplat.lang.codebook import MAX_DIM, load_codebook
from drsplat.lang.field import LanguageField
from drsplat.lang.lut import MIN_NORM, has_feature, subnormal_norms
from drsplat.scene import GaussianScene, PlyExtras, check_integer_column, counted, ply_type_name, save_ply
from drsplat.splat_formats import save_scene, written_format
from drsplat.utils import atomic_path, clipped, file_stamp, is_special_file, output_target, outputs_together, refuse_write_protected

log = logging.getLogger(__name__)

COMMENT_PREFIX = "drsplat.lang"
META_PROPERTY = "lang_meta"
META_MAX_BYTES = 255  # metadata this long or shorter is carried in ushort cells; longer in uint ones (round 56d: a long or
# non-ASCII codebook name, 6 bytes a character once URL-quoted, lost the column without a word)
META_LONG_MAX_BYTES = 1 << 15  # the longest carried: its cells stay below 2^23, which a tool's float32 copy of the column holds exactly
SHOWN_CHARS = 40  # how much of a header value an error echoes: a hostile header can hold megabytes
DIM_TEXT = re.compile(r"-?[0-9]+")  # not \d or int() alone, which take any Unicode digit ("５１２")
DIM_MAX_CHARS = 12  # a longer dim= is far beyond MAX_DIM, and int() refuses more than 4,300 digits
CRC_TEXT = re.compile(r"[0-9a-fA-F]{8}")  # not int(x, 16) alone, which takes "-0x0", " 1" and "dead_beef"


# --------------------------------------------------------------------------------------------
# PLY encoding


CODEBOOK_SUFFIX = ".codebook.faiss"


def codebook_path_for(ply_path: str | Path) -> Path:
    """The codebook file's name next to a registered PLY: `<stem>.codebook.faiss` (no link followed;
    where one is written: `written_codebook_path`)."""
    ply_path = Path(ply_path)
    return ply_path.with_name(f"{ply_path.stem}{CODEBOOK_SUFFIX}")


def written_codebook_path(ply_path: str | Path) -> Path | None:
    """Where the codebook of a registered PLY written at `ply_path` goes: `codebook_path_for` the file
    the path names, so beside a link's target and named after it (beside the link, under the link's
    name, the target read from its own folder named a file that was not there; probe round 44).
    None when `ply_path` is a device, FIFO or socket, beside which nothing is written (`--out /dev/null`
    run as root left /dev/null.codebook.faiss)."""
    target = output_target(Path(ply_path))
    return None if is_special_file(target) else codebook_path_for(target)


def codebook_name_for(ply_path: str | Path) -> str:
    """The codebook file name that a registered PLY written at `ply_path` records in its header."""
    return (written_codebook_path(ply_path) or codebook_path_for(ply_path)).name


def header_text_problem(clip_model: str, codebook_name: str | None) -> str | None:
    """Why the field's text could not be written into a registered PLY's header, or None.

    The rule is the reader's (`read_field`): no metadata value may hold a character a terminal would
    not show as itself (`hidden_character`: a newline, ESC, U+202E, a lone surrogate), since such a
    value could forge lines in every message that names it. The writer refuses what its reader would:
    a file written anyway would be refused by every command as altered."""
    for key, what, value in (("clip", "the CLIP model id", clip_model), ("codebook", "the codebook's file name", codebook_name)):
        hidden = hidden_character(value) if value is not None else None
        if hidden is not None:
            return (f"field '{key}' of the '{COMMENT_PREFIX}' header comment: {what} {json.dumps(value)[:60]} holds {hidden}, "
                    "which a registered PLY's header cannot carry (its readers would refuse the file)")
    return None


def field_comment(field: LanguageField, codebook_name: str | None, codebook_crc: int | None = None) -> str:
    """`drsplat.lang kind=<kind> dim=<D> clip=<model> [clip_weights=<size:sha1>] [codebook=<file> codebook_crc=<CRC-32, 8 hex>]`
    (values URL-quoted). ValueError for text the reader would refuse (`header_text_problem`)."""
    problem = header_text_problem(field.clip_model, codebook_name)
    if problem is not None:
        raise ValueError(problem)
    parts = [COMMENT_PREFIX, f"kind={field.kind}", f"dim={field.dim}", f"clip={quote(field.clip_model, safe='/:-_.+')}"]
    if field.clip_weights is not None:
        parts.append(f"clip_weights={quote(field.clip_weights, safe=':')}")
    if codebook_name:
        parts.append(f"codebook={quote(codebook_name, safe='/:-_.+')}")
        if codebook_crc is not None:
            parts.append(f"codebook_crc={codebook_crc:08x}")
    return " ".join(parts)


def encode_meta_column(text: str, n: int) -> np.ndarray | None:
    """[n] uint16 `lang_meta` column of a metadata text: row i = (k << 8) | byte[k], k = i mod L.

    None when the text cannot be carried: empty, longer than META_LONG_MAX_BYTES, or more bytes than
    rows (a scene of fewer Gaussians than the text's length keeps the comment form only).
    """
    data = text.encode("utf-8")
    if not data or len(data) > META_LONG_MAX_BYTES or n < len(data):
        return None
    k = np.arange(n, dtype=np.int64) % len(data)
    return _meta_cells(data, k)


def _meta_cells(data: bytes, k: np.ndarray) -> np.ndarray:
    """(k << 8) | data[k]: ushort cells for metadata of up to META_MAX_BYTES bytes, uint cells for longer."""
    return ((k << 8) | np.frombuffer(data, np.uint8)[k]).astype(np.uint16 if len(data) <= META_MAX_BYTES else np.uint32)


def meta_column_name(j: int) -> str:
    """Name of the j-th metadata column: `lang_meta`, then `lang_meta_1`, `lang_meta_2`, ..."""
    return META_PROPERTY if j == 0 else f"{META_PROPERTY}_{j}"


def _is_ascii_number(text: str) -> bool:
    """Whether `text` is a non-empty run of ASCII digits: str.isdigit alone takes '²' and '５', which
    int() then refuses or reads as another number."""
    return text.isascii() and text.isdigit()


def is_meta_column(name: str) -> bool:
    return name == META_PROPERTY or (name.startswith(META_PROPERTY + "_") and _is_ascii_number(name[len(META_PROPERTY) + 1 :]))


def encode_meta_columns(text: str, n: int) -> dict[str, np.ndarray]:
    """The metadata text as C = ceil(L / n) uint16 columns of n rows, name -> [n] column.

    Cell (i, j) holds (k << 8) | byte[k] with k = (i·C + j) mod L, so every position has a cell
    even when the scene has fewer rows than the text has bytes (a small export: a 78-Gaussian PQ
    export with an 80-byte codebook name gets 2 columns). C = 1 is exactly `encode_meta_column`.
    Empty when nothing can be carried: no rows, an empty text or one over META_LONG_MAX_BYTES.
    """
    data = text.encode("utf-8")
    if n <= 0 or not data or len(data) > META_LONG_MAX_BYTES:
        return {}
    count = -(-len(data) // n)
    k = (np.arange(n * count, dtype=np.int64) % len(data)).reshape(n, count)
    cells = _meta_cells(data, k)
    return {meta_column_name(j): np.ascontiguousarray(cells[:, j]) for j in range(count)}


def meta_cells(extra: dict[str, np.ndarray]) -> np.ndarray | None:
    """Every metadata cell of a scene's extra properties (all `lang_meta*` columns), or None."""
    columns = [np.asarray(v).reshape(-1) for name, v in extra.items() if is_meta_column(name)]
    return np.concatenate(columns) if columns else None


def decode_meta_column(column: np.ndarray) -> str | None:
    """The metadata text of a `lang_meta` column (any row order, any subset keeping each position),
    or None when it does not decode: L = 1 + the largest position, each byte by majority vote."""
    values = np.asarray(column).astype(np.int64, copy=False)
    if values.size == 0 or values.min() < 0 or values.max() >= META_LONG_MAX_BYTES << 8:
        return None
    cells, counts = np.unique(values, return_counts=True)  # sorted by position, then byte
    pos = cells >> 8
    length = int(pos[-1]) + 1
    if np.unique(pos).size != length:  # a position no row keeps
        return None
    if np.asarray(column).dtype.itemsize <= 2 and length > META_MAX_BYTES:  # a uint column narrowed to 16 bits: positions wrapped
        return None
    order = np.lexsort((-counts, pos))  # per position the most frequent byte first, the lowest among equals (stable)
    first = np.flatnonzero(np.r_[True, pos[order][1:] != pos[order][:-1]])
    try:
        text = (cells[order][first] & 0xFF).astype(np.uint8).tobytes().decode("utf-8")
    except UnicodeDecodeError:
        return None
    # metadata drsplat writes is printable (its values URL-quoted): a control character is a column cut or retyped (round 56e:
    # a uint column declared ushort decoded to "8%25A=%12", then named as a made-up entry)
    return None if hidden_character(text) is not None else text


def field_extras(field: LanguageField, meta: str | None = None) -> dict[str, np.ndarray]:
    """Extra vertex properties of the field, name -> [N] array (dtype = PLY type); `meta`, the
    comment's text without its prefix, adds the `lang_meta` column when it fits."""
    extras: dict[str, np.ndarray] = {"lang_weight": np.ascontiguousarray(field.weights, np.float32)}
    if meta is not None:
        extras.update(encode_meta_columns(meta, field.num_gaussians))
    extras.update(field.storage.columns())
    return extras


def is_lang_property(name: str) -> bool:
    """Every vertex property of the language field starts with `lang_` (no 3DGS property does)."""
    return name.startswith("lang_")


def strip_field(scene: GaussianScene) -> GaussianScene:
    """The scene without language properties and drsplat.lang comments (a plain 3DGS scene)."""
    return dataclasses.replace(
        scene,
        extra={k: v for k, v in scene.extra.items() if not is_lang_property(k)},
        comments=[c for c in scene.comments if not c.startswith(COMMENT_PREFIX)],
    )


def write_codebook_beside(codebook, ply_path: str | Path) -> tuple[Path, int]:
    """Write `codebook` (a Codebook) beside `ply_path` as `<stem>.codebook.faiss`, from memory
    (`Codebook.file_bytes`), unless that file holds those bytes already; returns (that path, the
    CRC-32 of the bytes), which the field comment records (`field_comment`) and `read_field` checks.
    Beside a link's target (`written_codebook_path`); beside a device or FIFO nothing is written, and
    a warning names the file the PLY's reader will need."""
    target = written_codebook_path(ply_path)
    # the PLY is put in place after its codebook: a write-protected PLY, refused then, had its codebook replaced (round 60a)
    refuse_write_protected(output_target(Path(ply_path)))
    data = codebook.file_bytes()
    crc = zlib.crc32(data)
    if target is None:
        named = codebook_path_for(ply_path)
        log.warning("%s is a device or pipe: the codebook its PLY names (%s) was not written; a reader of that PLY needs it "
                    "beside the PLY (or register with --codebook none)", shown_path(ply_path), shown_path(named.name))
        return named, crc
    # a name the user never typed: a dangling link there was followed, and its target made with its missing folders anywhere (round 59a)
    if target.is_symlink() and not target.exists():
        raise OutputError(target, f"is a link to {os.readlink(target)}, which does not exist: the codebook {Path(ply_path).name} needs "
                                  "goes under this name beside it; remove the link, or point it at a file")
    stamp = file_stamp(target)
    if stamp is not None and codebook.written.get(target) == stamp:  # this call's earlier chunks wrote it, and it is unchanged
        return target, crc
    if not (target.is_file() and target.stat().st_size == len(data) and zlib.crc32(target.read_bytes()) == crc):
        with atomic_path(target) as tmp:
            tmp.write_bytes(data)
    codebook.written[target] = file_stamp(target)
    return target, crc


def attach_field(scene: GaussianScene, field: LanguageField, ply_path: str | Path, write_codebook: bool = True) -> GaussianScene:
    """The scene with the field's extra properties and header comment; writes the codebook.

    The codebook (pq, ivfpq) is written next to `ply_path` as `<stem>.codebook.faiss`; save the
    returned scene to `ply_path` with `drsplat.scene.save_ply`. write_codebook=False: the comment
    names it and its CRC (from memory) but the caller writes it (`write_codebook_beside`) just before
    it puts the PLY in place: written at the first chunk, it replaced the codebook of an earlier
    output of that name for the whole rest of the write, and a run stopped there left that output
    naming a codebook it no longer matched.
    """
    if field.num_gaussians != scene.num_gaussians:
        raise ValueError(f"field has {field.num_gaussians} Gaussians, scene has {scene.num_gaussians}")
    codebook_name = codebook_name_for(ply_path) if needs_codebook(field.kind) else None
    problem = header_text_problem(field.clip_model, codebook_name)
    if problem is not None:  # before the codebook is written beside it: a refused output leaves nothing
        raise OutputError(ply_path, problem)
    base = strip_field(scene)
    if not needs_codebook(field.kind):
        name, crc = None, None
    elif write_codebook:
        name, crc = write_codebook_beside(field.codebook, ply_path)
    else:
        name, crc = Path(codebook_name), zlib.crc32(field.codebook.file_bytes())
    comment = field_comment(field, name.name if name is not None else None, crc)
    extra = dict(base.extra)
    extra.update(field_extras(field, comment[len(COMMENT_PREFIX):].strip()))
    return dataclasses.replace(base, extra=extra, comments=base.comments + [comment])


def parse_field_comment(comments: list[str]) -> dict[str, str] | None:
    """The key=value pairs of the `drsplat.lang` header comment, or None when there is none."""
    for comment in comments:
        tokens = comment.split()
        if tokens and tokens[0] == COMMENT_PREFIX:
            return _parse_pairs(tokens[1:])
    return None


def _parse_pairs(tokens: list[str]) -> dict[str, str]:
    return {k: unquote(v) for k, _, v in (t.partition("=") for t in tokens)}


def repeated_key(tokens: list[str]) -> tuple[str, str, str] | None:
    """(key, first value, other value) of the first key that the `key=value` tokens give twice with
    different values, or None. The writer writes each key once: `_parse_pairs` alone kept the last
    (a hand-edited `kind=pq ... kind=exact` was read as exact and refused for a missing lang_0)."""
    seen: dict[str, str] = {}
    for key, _, value in (t.partition("=") for t in tokens):
        if key in seen and seen[key] != value:
            return key, seen[key], value
        seen.setdefault(key, value)
    return None


def field_metadata(scene: GaussianScene | PlyExtras, ply_path: str | Path) -> dict[str, str] | None:
    """The field's key=value metadata: the header comment, else the `lang_meta` column (a file
    whose comments a tool dropped); None for a scene without a language field."""
    found = {tuple(sorted(_parse_pairs(c.split()[1:]).items())) for c in scene.comments if c.split()[:1] == [COMMENT_PREFIX]}
    if len(found) > 1:  # which one the field was written with cannot be told
        raise InputError(ply_path, f"has {len(found)} '{COMMENT_PREFIX}' header comments that disagree; keep the one the field was written with",
                         field=f"comment {COMMENT_PREFIX}")
    for comment in scene.comments:
        tokens = comment.split()
        repeated = repeated_key(tokens[1:]) if tokens[:1] == [COMMENT_PREFIX] else None
        if repeated is not None:
            key, first, other = (clipped(quote(unquote(text)), SHOWN_CHARS) for text in repeated)
            raise InputError(ply_path, f"gives the metadata entry {key} twice, as {key}={first} and {key}={other}; a header "
                                       "written by drsplat gives each once (the file was altered)", field=f"comment {COMMENT_PREFIX}")
    meta = parse_field_comment(scene.comments)
    cells = meta_cells(scene.extra)
    if meta is not None or cells is None:
        return meta
    for name, column in scene.extra.items():
        if is_meta_column(name):
            check_stored_type(Path(ply_path), name, np.asarray(column))
    text = decode_meta_column(cells)
    if text is None:
        raise InputError(ply_path, "the language field's metadata column does not decode (rows lost or altered)", field=META_PROPERTY)
    return _parse_pairs(text.split())


def read_field(scene: GaussianScene | PlyExtras, ply_path: str | Path, shared: bool = False) -> LanguageField | None:
    """The language field of a scene loaded from `ply_path` (None if it has neither a drsplat.lang
    comment nor a `lang_meta` column). shared: the field's features or codes may be the scene's own
    columns' memory (the loader's [N, L] block, not copied: a caller that drops those columns,
    `strip_field`, or never edits them); else they are a copy (round 63c: editing the scene's
    `lang_0` changed the field's scores).

    Raises InputError naming the PLY (or codebook) file and the field for missing properties,
    an unknown kind, a missing codebook, or codes that do not fit the codebook.
    """
    ply_path = Path(ply_path)
    meta = field_metadata(scene, ply_path)
    if meta is None:
        return None
    where = "comment drsplat.lang" if parse_field_comment(scene.comments) is not None else META_PROPERTY  # what the error names
    for key, value in meta.items():  # URL-quoted values could carry a newline or ESC into every message that names them
        hidden = hidden_character(key + value)
        if hidden is not None:
            raise InputError(ply_path, f"the metadata entry {clipped(quote(key), SHOWN_CHARS)}={clipped(quote(value), SHOWN_CHARS)} holds {hidden}; a header written "
                                       "by drsplat has none (the file was altered)", field=where)
    kind = meta.get("kind")
    if kind not in BACKENDS:
        raise InputError(ply_path, f"unknown language field kind {_shown(kind)}; expected one of {', '.join(BACKENDS)}", field=where)
    dim = _metadata_dim(meta.get("dim", ""), ply_path, where)
    clip_model = meta.get("clip", "unknown")
    beyond = [j for j in _numbered_columns(scene, "lang_") if j >= dim]
    if not needs_codebook(kind) and beyond:
        raise InputError(ply_path, f"declares dim={dim} but has {len(_numbered_columns(scene, 'lang_'))} feature columns lang_<j> "
                         f"(up to lang_{max(beyond)}), so the metadata does not describe this file's features", field=where)
    weights = _extra(scene, ply_path, "lang_weight")
    book = None
    if needs_codebook(kind):
        if not meta.get("codebook"):  # an empty entry too: it read as the PLY's own folder, "is not a regular file (a folder)" (round 59a)
            raise InputError(ply_path, "a quantised language field names no codebook file", field=where)
        try:
            book = load_codebook(codebook_named_by(ply_path, meta["codebook"]))
        except InputError as exc:  # say whose codebook it is: the file named is not one the user typed
            raise InputError(exc.path, f"{exc.problem} (the codebook {ply_path.name}'s header names)", field=exc.field) from None
        _check_codebook_crc(book.path, meta.get("codebook_crc"), ply_path, where)  # first: a replaced file is said so (round 85c F3)
        if book.kind != kind or book.dim != dim:
            raise InputError(book.path, f"codebook is {book.kind} d={book.dim}, but {ply_path.name} declares {kind} dim={dim}")
        extra_codes = [j for j in _numbered_columns(scene, "lang_code_") if j >= book.m]
        if extra_codes:
            raise InputError(ply_path, f"more PQ code columns than the codebook's M={book.m} (lang_code_0 .. lang_code_{book.m - 1})",
                             field=f"lang_code_{min(extra_codes)}")
    try:
        storage = BACKENDS[kind].from_columns(lambda name: _extra(scene, ply_path, name), scene.num_gaussians, dim, book)
    except InputError as exc:
        if exc.path is not None:
            raise
        raise InputError(ply_path, exc.problem, field=exc.field) from None
    if not shared and hasattr(storage, "detached"):  # a backend without `detached` made its own arrays (`from_columns`)
        storage = storage.detached()
    orphans = int(np.count_nonzero((weights > 0) & (storage.norms == 0)))
    storage = _without_altered_codes(storage, ply_path)
    weightless = int(np.count_nonzero(~(weights > 0) & has_feature(storage.norms)))
    nonfinite = int(np.count_nonzero(~np.isfinite(storage.norms)))
    if nonfinite:
        log.warning("%s: %s non-finite language features; they score 0", ply_path,
                    f"{nonfinite:,} Gaussian has" if nonfinite == 1 else f"{nonfinite:,} Gaussians have")
    tiny = int(np.count_nonzero(subnormal_norms(storage.norms)))
    if tiny:  # 1/norm overflows float32: every such row scored inf, was selected and written to --scores
        log.warning("%s: %s Gaussians have a language feature of norm below %.3g (lang_norm: float32's smallest normal number), "
                    "too small to score in float32 (a codebook of subnormal centroids?); they score 0", ply_path, f"{tiny:,}", MIN_NORM)
    negative = int(np.count_nonzero(weights < 0))
    if negative:  # a weight is a sum of w = T·α ≥ 0; nothing reads its sign, but the file is not as registration wrote it
        log.warning("%s: %d Gaussians have a negative registration weight (lang_weight < 0), which registration never writes: "
                    "the file was altered", ply_path, negative)
    if orphans:  # registration zeroes the weight of every row it leaves without a feature (normalize_rows)
        log.warning("%s: %d Gaussians have a registration weight (lang_weight > 0) but no language feature: the file was altered; "
                    "they are unassigned", ply_path, orphans)
    if weightless:  # the stored feature decides, as for the orphans above; registration writes weight 0 with norm 0 only
        log.warning("%s: %s a language feature but a registration weight (lang_weight) that is not positive (0, negative or NaN): "
                    "the file was altered; the feature decides, so %s assigned and scored", ply_path,
                    counted(weightless, "Gaussian has", "Gaussians have"), "it is" if weightless == 1 else "they are")
    return LanguageField(dim, clip_model, weights, storage, _clip_weights(meta.get("clip_weights"), ply_path, where))


def _clip_weights(value: str | None, ply_path: Path, where: str) -> str | None:
    """The `clip_weights` entry ('size:sha1' of the CLIP weights the features were made with), or None; InputError
    for any other text (the writer writes nothing else)."""
    if value is None or WEIGHTS_DIGEST.fullmatch(value):
        return value
    raise InputError(ply_path, f"the metadata entry clip_weights={clipped(quote(value), SHOWN_CHARS)} is not a weights file's "
                               "size:sha1, as registration writes it (the file was altered)", field=where)


def _shown(value: str | None) -> str:
    """A header value as an error echoes it: its repr, cut after SHOWN_CHARS characters (the
    length said), so a value of megabytes cannot flood the terminal."""
    if value is None or len(value) <= SHOWN_CHARS:
        return repr(value)
    return f"{value[:SHOWN_CHARS]!r}... ({len(value):,} characters)"


def _metadata_dim(text: str, ply_path: Path, where: str) -> int:
    """The `dim=` value: a whole number in ASCII digits (what the writer writes), within 1..MAX_DIM;
    else InputError naming the field. int() alone took full-width digits ("５１２" as 512) and a
    5,000-digit value was echoed whole."""
    if DIM_TEXT.fullmatch(text) is None:
        raise InputError(ply_path, f"dim={_shown(text)} is not an integer (ASCII digits)", field=where)
    if len(text) > DIM_MAX_CHARS or not 1 <= int(text) <= MAX_DIM:
        raise InputError(ply_path, f"dim={_shown(text)} is not a feature dimension (expected 1..{MAX_DIM})", field=where)
    return int(text)


def _check_codebook_crc(path: Path, recorded: str | None, ply_path: Path, where: str) -> None:
    """InputError unless the codebook file's CRC-32 is the one the PLY's field records (files written
    before 2026-11-30 record none: not checked). A later registration into a file of the same stem
    (`a.PLY` beside `a.ply`), one that failed after writing its codebook, or a `pq train` over the
    codebook while `register` ran left codes that this codebook decodes into other vectors, scored
    without a word (a probe, 2026-11-30)."""
    if recorded is None:
        return
    if CRC_TEXT.fullmatch(recorded) is None:  # the writer writes exactly 8 hex digits (`field_comment`)
        raise InputError(ply_path, f"codebook_crc={_shown(recorded)} is not a CRC-32 (8 hex digits)", field=where)
    expected = int(recorded, 16)
    actual = zlib.crc32(path.read_bytes())
    if actual != expected:
        raise InputError(path, f"is not the codebook {ply_path.name} was registered with (its CRC-32 is {actual:08x}, the PLY records "
                               f"{expected:08x}): it was replaced after that registration (by another registration into a file of the "
                               f"same name stem, or a new `pq train`); register {ply_path.name} again, or restore its codebook")


def _numbered_columns(scene: GaussianScene | PlyExtras, prefix: str) -> list[int]:
    """The numbers j of a scene's properties named `<prefix><j>` (lang_<j> features, lang_code_<j> codes)."""
    return [int(name[len(prefix):]) for name in scene.extra if name.startswith(prefix) and _is_ascii_number(name[len(prefix):])]


def _without_altered_codes(storage, ply_path: Path):
    """PQ storage whose rows with altered codes (`PQStorage.norm_mismatches`) score 0, with one warning."""
    if not hasattr(storage, "norm_mismatches"):
        return storage  # exact float16 features carry no redundancy to check
    bad = storage.norm_mismatches() & np.isfinite(storage.norms)  # a NaN or inf norm: the caller counts it as non-finite
    if not bad.any():
        return storage
    log.warning("%s: %d of %d Gaussians have PQ codes that do not reproduce their stored norm (lang_norm): the file was "
                "altered (flipped bytes?) or its codebook is not the one it was written with; they score 0",
                ply_path, int(bad.sum()), bad.shape[0])
    norms = storage.norms.copy()
    norms[bad] = 0.0
    return storage.with_norms(norms)


def codebook_named_by(ply_path: Path, name: str) -> Path:
    """The codebook a PLY header names, relative to the PLY's folder; a name leaving that folder
    (`../`, absolute) is followed but warned about, since a header is not trusted input. A PLY opened
    through a link whose folder lacks the file is read with the one beside the link's target, where
    `written_codebook_path` puts it."""
    target = ply_path.parent / name
    if ply_path.is_symlink() and not target.exists():
        beside_target = Path(os.path.realpath(ply_path)).parent / name
        if beside_target.exists():
            ply_path, target = Path(os.path.realpath(ply_path)), beside_target
    folder = os.path.normpath(os.path.abspath(ply_path.parent))
    if os.path.commonpath([folder, os.path.normpath(os.path.abspath(target))]) != folder:
        log.warning("%s: the header names a codebook outside the PLY's folder (%s); reading it as named", ply_path, target)
    return target


def _extra(scene: GaussianScene | PlyExtras, ply_path: Path, name: str) -> np.ndarray:
    """A language-field property, its declared type checked (`check_stored_type`); the float ones
    (lang_weight, lang_norm) as float32 (`float32_column`)."""
    if name not in scene.extra:
        raise InputError(ply_path, "missing vertex property of the language field", field=name)
    column = np.asarray(scene.extra[name])
    check_stored_type(ply_path, name, column)
    return column if integer_storage(name) is not None else float32_column(ply_path, name, column)


def float32_column(ply_path: Path, name: str, column: np.ndarray) -> np.ndarray:
    """[N] float32 of a float property (declared double by a tool that widened it): values beyond
    float32's range are read as infinite, counted in one warning naming the property, without
    numpy's "overflow encountered in cast" (a double lang_norm of 1e300 printed it, then the
    non-finite count blamed values the file does not hold: a probe, round 29a)."""
    if column.dtype == np.float32:
        return column
    with np.errstate(over="ignore", invalid="ignore"):
        wide = column.astype(np.float64)
        beyond = int(np.count_nonzero(np.isfinite(wide) & (np.abs(wide) > np.finfo(np.float32).max)))
        out = wide.astype(np.float32)
    if beyond:
        log.warning("%s: %d values of %s (declared %s) lie beyond float32's range (+-3.4e38) and are read as infinite",
                    ply_path, beyond, name, ply_type_name(column.dtype))
    return out


def integer_storage(name: str) -> tuple[str, str, bool] | None:
    """(PLY type, meaning, holds bit patterns) of a language property stored as integers, None for
    the float ones (lang_weight, lang_norm): what `check_integer_column` checks it against."""
    suffix = name[len("lang_"):]
    if _is_ascii_number(suffix):
        return "ushort", "float16 bit patterns", True
    if is_meta_column(name):  # ushort for metadata of up to 255 bytes, uint for longer: either holds its cells
        return "uint", "metadata position << 8 | byte", False
    if suffix.startswith("code_"):
        return "uchar", "PQ codes", False
    if name == "lang_list":
        return "int", "coarse list ids", False
    return None


def check_stored_type(ply_path: Path, name: str, column: np.ndarray) -> None:
    """Refuse a language property whose declared PLY type would be misread as its storage type
    (floats holding real features where float16 bits belong cast to 0)."""
    storage = integer_storage(name)
    if storage is not None:
        check_integer_column(ply_path, name, column, storage[0], storage[1], bit_pattern=storage[2])


# --------------------------------------------------------------------------------------------
# Exports

EXPORT_FORMATS = ("standard", "drsplat")
EXPORT_FORMAT_HELP = {
    "standard": "standard 3DGS scene for other tools: a PLY in the INRIA layout, or a .splat, .spz or .compressed.ply file when the name ends so",
    "drsplat": "drsplat PLY (with the language field, its codebook copied beside it; `drsplat query` reads it)",
}


def standard_scene(scene: GaussianScene) -> GaussianScene:
    """The scene in the INRIA layout only: no extra vertex properties and no header comments, as INRIA's
    3DGS writes it (round 56d: SIBR, its C++ viewer, reads the vertex count from the header's third line,
    where a carried comment such as "drsplat.synthetic preset=tiny" sat, and opened 0 Gaussians)."""
    return dataclasses.replace(strip_field(scene), extra={}, comments=[])


REGISTERED_IS_PLY = ("a registered scene is a PLY: its language field lives in the PLY's vertex properties, which .splat, "
                     ".spz and compressed PLY files (PlayCanvas's packed format) do not have")


EXPORT_SUFFIXES = ("", ".ply", ".splat", ".spz")  # no suffix: a device or FIFO (/dev/stdout), written as a PLY


OTHER_DATA_SUFFIXES = {".npy", ".npz", ".json", ".jsonl", ".txt", ".bin", ".db", ".faiss", ".csv", ".yml", ".yaml", ".pt", ".pth",
                       ".ckpt"}  # names of what a dataset or a features folder holds (and its images): a PLY written under one is a mix-up


def other_data_name(path: str | Path) -> str | None:
    """Why a registered scene cannot be written to `path`, named as another kind of data than a PLY
    (OTHER_DATA_SUFFIXES or an image's, in any case), or None: `register --out` and the viewer's Register
    button alike (round 107b F1: the viewer wrote a PLY over a dataset's gt/labels.npy)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in OTHER_DATA_SUFFIXES and suffix not in {s.lower() for s in IMAGE_SUFFIXES}:
        return None
    return (f"{path.name}: a {path.suffix} name is another kind of file (a dataset's arrays, cameras, images or a codebook), and a "
            "registered scene is a PLY: name it .ply")


def export_problem(path: str | Path, fmt: str) -> str | None:
    """Why `path` cannot take an export in format `fmt`, or None: a drsplat export is a PLY (the
    field lives in its vertex properties), so it refuses a .splat, .spz or .compressed.ply name; any
    export refuses a name of another file type (`x.codebook.faiss`, `sel.npy`), which would hold a PLY."""
    if fmt not in EXPORT_FORMATS:
        return f"unknown export format {fmt!r}; expected one of {', '.join(EXPORT_FORMATS)}"
    kind, suffix = written_format(path), Path(path).suffix.lower()
    if suffix == "" and not is_special_file(output_target(Path(path))):  # `sel` became a PLY no drop or scene dialog opens (round 61a)
        return (f"{Path(path).name}: an export is the scene file its name asks for (.ply, .compressed.ply, .splat or .spz); a name "
                f"without a suffix is for a device or pipe (/dev/stdout): name it {Path(path).name}.ply")
    if suffix not in EXPORT_SUFFIXES:
        return (f"{Path(path).name}: an export is the scene file its name asks for (.ply, .compressed.ply, .splat or .spz); "
                f"a {suffix} name would hold a PLY")
    if fmt == "drsplat" and kind != "ply":
        return (f"{Path(path).name}: a drsplat export is a PLY (the language field lives in its vertex properties); "
                f"name it .ply, or export a standard .{kind}")
    return None


def export_kind(path: str | Path, fmt: str) -> str:
    """What an export to `path` in format `fmt` writes, in words: "drsplat PLY", "standard 3DGS PLY", ".splat" or ".spz"."""
    kind = written_format(path)
    return "drsplat PLY" if fmt == "drsplat" else ("standard 3DGS PLY" if kind == "ply" else f".{kind}")


def export_scene(scene: GaussianScene, field: LanguageField | None, path: str | Path, fmt: str = "standard") -> GaussianScene:
    """Write `scene` (with `field`, the same rows) to `path` in a standard or the drsplat format.

    standard: `standard_scene(scene)`, which every 3DGS tool opens, as the file type the name asks
    for (drsplat.splat_formats.save_scene: `.splat`, `.spz`, else PLY). drsplat: a PLY of the scene
    with the field attached (`attach_field`: metadata comment + `lang_meta` column, codebook written
    beside `path`), so that `read_field` on the written file gives the field back. Returns the
    scene written (before any .splat / .spz / compressed-PLY quantisation).
    """
    problem = export_problem(path, fmt)
    if problem is not None:
        raise ValueError(problem)
    if fmt == "drsplat" and field is None:
        raise ValueError("a drsplat PLY needs a language field; this scene has none (use the standard format)")
    if fmt == "standard":
        out = standard_scene(scene)
        save_scene(out, path)
        return out
    # the codebook last, just before the PLY is renamed into place (as registration does): written first, an interrupted
    # or killed export over an earlier one of another codebook left that PLY beside a codebook it no longer matched (round 61b)
    out = attach_field(scene, field, path, write_codebook=False)
    if not needs_codebook(field.kind):
        save_ply(out, path)
        return out
    # one set: a PLY that fails at its rename (after the codebook's) puts the earlier codebook back, in every caller (round 62a:
    # the viewer's export lost an earlier export's codebook; only the command line's outputs were a set)
    with outputs_together([path, written_codebook_path(path)]):
        save_ply(out, path, before_replace=lambda: write_codebook_beside(field.codebook, path))
    return out
