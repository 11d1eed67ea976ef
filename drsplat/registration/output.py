"""Targets: where a registration's finished blocks go (unit features and weights per Gaussian).

    target       what it makes
    PlyTarget    the registered PLY: rows encoded with the codebook (drsplat.lang), appended to a
                 body file chunk by chunk, then header + body -> the output, atomically (in place
                 behind a reserved header when the row count's digits were foreseen)
    ArrayTarget  features [N, D] and weights [N] in memory (evaluation, tests, the Python API)

The PLY is written the same way for one block or many, so a file does not depend on the memory
plan. Per row the encoding (float16 or PQ codes) and the `lang_meta` column only depend on the
row and its index in the file, so chunks and blocks join into the bytes of a single write.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import numpy as np

from drsplat.lang import COMMENT_PREFIX, META_PROPERTY, Codebook, attach_field, build_field, encode_meta_column, encode_meta_columns, is_meta_column
from drsplat.lang.plyformat import write_codebook_beside
from drsplat.memory import small_page_zeros
from drsplat.registration.plan import WRITE_CHUNK
from drsplat.registration.sink import Block
from drsplat.scene import GaussianScene, ply_header, scene_to_vertices
from drsplat.errors import DrsplatError
from drsplat.utils import (TEMP_SUFFIX, CancelToken, atomic_path, is_special_file, output_target, replace_with_temp, temp_beside, temp_prefix,
                           work_folder)


class Target(Protocol):
    """Receives the finished blocks in Gaussian order: `open(codebook)`, `add(block, keep)` per block
    (block.F unit rows, zero where unassigned; keep [B] bool: the rows to store), `close()`;
    `abort()` when the run fails."""

    def open(self, codebook: Codebook | str, rows_hint: int | None = None) -> None: ...

    def add(self, block: Block, keep: np.ndarray) -> None: ...

    def close(self) -> int: ...

    def abort(self) -> None: ...


class ArrayTarget:
    """features [N, D] float32 (unit rows, zero where unassigned or not kept) in memory; the
    sums of a single block are kept as they are, not copied."""

    def __init__(self, num_gaussians: int, dim: int):
        self.num_gaussians, self.dim = num_gaussians, dim
        self.features: np.ndarray | None = None

    def open(self, codebook: Codebook | str, rows_hint: int | None = None) -> None:
        pass

    def add(self, block: Block, keep: np.ndarray) -> None:
        F = block.F
        F[~keep] = 0.0
        if block.lo == 0 and block.hi == self.num_gaussians:
            self.features = F
            return
        if self.features is None:
            self.features = small_page_zeros((self.num_gaussians, self.dim), np.float32)  # made once: no huge pages (drsplat.memory)
        self.features[block.lo : block.hi] = F

    def close(self) -> int:
        if self.features is None:
            self.features = np.zeros((self.num_gaussians, self.dim), np.float32)
        return self.num_gaussians

    def abort(self) -> None:
        self.features = None


class PlyTarget:
    """The registered PLY `out` of `scene` (see the module docstring). clip_model: the embedding
    space's id written in the field's metadata; clip_weights: the 'size:sha1' of the CLIP weights the
    features were made with (their manifest's), written beside it when known.

    The header holds the final row count, known only once every block is written. With a
    `rows_hint` (the expected count) and a regular-file output, the body is written into the
    output's temp file behind room for the header of `rows_hint` rows: when the final count has as
    many digits, the header goes into that room and the temp file is renamed over `out`, so the
    body is written once. Otherwise (a device or FIFO, other digits, a short file whose metadata
    is widened) header + body are copied into `out` (`atomic_path`).
    """

    def __init__(self, scene: GaussianScene, out: Path, clip_model: str, cancel: CancelToken | None = None, clip_weights: str | None = None):
        self.scene, self.out, self.clip_model, self.clip_weights = scene, Path(out), clip_model, clip_weights
        self.cancel = cancel  # read while a FIFO output waits for its reader (`atomic_path`)
        self.written = 0
        self._codebook: Codebook | str = "none"
        self._header: tuple | None = None
        self._body = None
        self._body_path: Path | None = None
        self._rows_hint: int | None = None
        self._body_offset = 0  # where the body starts in the body file (room for the header)

    def open(self, codebook: Codebook | str, rows_hint: int | None = None) -> None:
        """Start the body; rows_hint: the rows expected (the kept Gaussians), or None."""
        self._codebook = codebook
        if rows_hint is not None and not is_special_file(output_target(self.out)):  # the body becomes the output: atomic_path's temp
            self._rows_hint = rows_hint
            self._body_path = temp_beside(self.out)
            self._body = open(self._body_path, "wb")
            return
        self._rows_hint = None
        fd, name = tempfile.mkstemp(prefix=temp_prefix(self.out), suffix=TEMP_SUFFIX, dir=work_folder(self.out))
        self._body_path = Path(name)
        self._body = os.fdopen(fd, "wb")

    def add(self, block: Block, keep: np.ndarray) -> None:
        """Encode and append the kept rows of `block`, WRITE_CHUNK Gaussians at a time."""
        for vertices, comments in encode_rows(self.scene, self.out, self.clip_model, self._codebook, block, keep, self.written,
                                              self.clip_weights):
            if self._header is None:
                self._header = (vertices.dtype, comments)
                if self._rows_hint is not None:  # the header's room: its length depends on the count's digits only
                    self._body_offset = len(ply_header(vertices.dtype, comments, self._rows_hint))
                    self._body.seek(self._body_offset)
            self._write(vertices.tobytes())
            self.written += int(vertices.shape[0])

    def close(self) -> int:
        """Header + body -> `out` (atomic); returns the rows written."""
        self._body.close()
        try:
            if self._header is None:
                raise DrsplatError(f"the scene has no Gaussians to write to {self.out}")
            dtype, comments, offset = _widen_meta_if_short(self._body_path, self._header, self.written, self._body_offset)
            header = ply_header(dtype, comments, self.written)
            # the codebook is written last, just before the PLY's rename: an earlier output of this name keeps its own until then
            if offset > 0 and len(header) == offset:
                with open(self._body_path, "r+b") as f:
                    f.write(header)
                write_codebook_of(self._codebook, self.out)
                replace_with_temp(self._body_path, self.out)
            else:
                with atomic_path(self.out, self.cancel) as tmp:
                    with open(tmp, "wb") as f, open(self._body_path, "rb") as src:
                        f.write(header)
                        src.seek(offset)
                        shutil.copyfileobj(src, f, 1 << 24)
                    write_codebook_of(self._codebook, self.out)
        finally:
            self._body_path.unlink(missing_ok=True)
        return self.written

    def abort(self) -> None:
        if self._body is not None:
            self._body.close()
        if self._body_path is not None:
            self._body_path.unlink(missing_ok=True)

    def _write(self, data: bytes) -> None:
        try:
            self._body.write(data)
        except OSError as exc:  # name the output being written (through its temp body file): a bare ENOSPC carries no name
            raise OSError(exc.errno, exc.strerror, str(self.out)) from None


def write_codebook_of(codebook: Codebook | str, out: Path) -> None:
    """Write a codebook beside `out` (`write_codebook_beside`; "none" or a name: nothing), the last step
    before the registered PLY is renamed into place, after its body is written (`encode_rows` leaves it
    out): an earlier output of that name names its own codebook until the new PLY replaces it."""
    if not isinstance(codebook, str):
        write_codebook_beside(codebook, out)


def encode_rows(scene: GaussianScene, out: Path, clip_model: str, codebook: Codebook | str, block: Block, keep: np.ndarray,
                first_row: int, clip_weights: str | None = None) -> Iterator[tuple[np.ndarray, list[str]]]:
    """The kept rows of `block` as PLY vertex records, WRITE_CHUNK Gaussians at a time: (vertices
    [R] structured, the header comments) per chunk, `lang_meta` numbered from `first_row` (the
    index in the file of the block's first kept row). keep: [hi - lo] bool. The one encoder of
    registered rows (PlyTarget and the reducers, drsplat.registration.reduce)."""
    written = first_row
    for lo in range(block.lo, block.hi, WRITE_CHUNK):
        hi = min(block.hi, lo + WRITE_CHUNK)
        rows = slice(lo - block.lo, hi - block.lo)
        chunk_keep = keep[rows]
        field = build_field(block.F[rows][chunk_keep], block.W[rows][chunk_keep], codebook=codebook, clip_model=clip_model,
                            clip_weights=clip_weights)
        part = _with_meta_rows(attach_field(scene.subset(slice(lo, hi)).subset(chunk_keep), field, out, write_codebook=False), written)
        vertices = scene_to_vertices(part)
        yield vertices, part.comments
        written += int(vertices.shape[0])


def _meta_period(comments: list[str]) -> np.ndarray | None:
    """One period of the `lang_meta` column of the field comment (None when it is not carried)."""
    comment = next((c for c in reversed(comments) if c.startswith(COMMENT_PREFIX)), "")
    text = comment[len(COMMENT_PREFIX):].strip()
    return encode_meta_column(text, len(text.encode("utf-8")))


def _with_meta_rows(part: GaussianScene, first_row: int) -> GaussianScene:
    """The block with its `lang_meta` rows numbered from `first_row`, as in the whole file.

    The column's row i holds byte i mod L of the field comment, so a block written alone would
    restart at 0 (and a block shorter than L would not carry the column at all).
    """
    period = _meta_period(part.comments)
    if period is None:
        return part
    column = period[(first_row + np.arange(part.num_gaussians)) % period.shape[0]]
    extra = {}
    for name, values in part.extra.items():
        if not is_meta_column(name):  # a block shorter than L got several columns from attach_field: one, numbered as in the file
            extra[name] = values
        if name == "lang_weight":
            extra[META_PROPERTY] = column
    return dataclasses.replace(part, extra=extra)


def _widen_meta_if_short(body_path: Path, header: tuple, written: int, offset: int = 0) -> tuple:
    """A file of fewer rows than the comment's length carries its metadata in several columns
    (`encode_meta_columns`, as in memory): rewrite the (then tiny) body, which starts at `offset`
    of `body_path`, with them, from offset 0. Returns the header's (dtype, comments) and where the
    body starts."""
    dtype, comments = header
    period = _meta_period(comments)
    if META_PROPERTY not in dtype.names or period is None or written >= period.shape[0]:
        return dtype, comments, offset
    comment = next(c for c in reversed(comments) if c.startswith(COMMENT_PREFIX))
    columns = encode_meta_columns(comment[len(COMMENT_PREFIX):].strip(), written)
    rows = np.fromfile(body_path, dtype, offset=offset)
    fields: list[tuple[str, np.dtype]] = []
    for name in dtype.names:
        if name != META_PROPERTY:
            fields.append((name, dtype[name]))
        if name == "lang_weight":
            fields.extend((meta, column.dtype.newbyteorder("<")) for meta, column in columns.items())  # ushort or, past 255 bytes, uint (round 58b)
    widened = np.empty(rows.shape[0], np.dtype(fields))
    for name in dtype.names:
        if name != META_PROPERTY:
            widened[name] = rows[name]
    for name, column in columns.items():
        widened[name] = column
    body_path.write_bytes(widened.tobytes())
    return widened.dtype, comments, 0
