"""The registered-PLY format: how a `LanguageField` is stored in extra vertex properties of an INRIA PLY (the one place it is specified)."""

from __future__ import annotations

import dataclasses
import logging
import os
import re
import shutil
from pathlib import Path
from urllib.parse import quote, unquote

import numpy as np

from drsplat.errors import InputError
from drsplat.lang.codebook import MAX_DIM, load_codebook
from drsplat.lang.field import EXACT_CHUNK, KINDS, LanguageField
from drsplat.scene import GaussianScene
from drsplat.utils import atomic_path

log = logging.getLogger(__name__)

COMMENT_PREFIX = "drsplat.lang"


# --------------------------------------------------------------------------------------------
# PLY encoding


def codebook_path_for(ply_path: str | Path) -> Path:
    """The codebook file next to a registered PLY: `<stem>.codebook.faiss`."""
    ply_path = Path(ply_path)
    return ply_path.with_name(f"{ply_path.stem}.codebook.faiss")


def field_comment(field: LanguageField, codebook_name: str | None) -> str:
    """`drsplat.lang kind=<kind> dim=<D> clip=<model> [codebook=<file>]` (values URL-quoted)."""
    parts = [COMMENT_PREFIX, f"kind={field.kind}", f"dim={field.dim}", f"clip={quote(field.clip_model, safe='/:-_.+')}"]
    if codebook_name:
        parts.append(f"codebook={quote(codebook_name, safe='/:-_.+')}")
    return " ".join(parts)


def field_extras(field: LanguageField) -> dict[str, np.ndarray]:
    """Extra vertex properties of the field, name -> [N] array (dtype = PLY type)."""
    extras: dict[str, np.ndarray] = {"lang_weight": np.ascontiguousarray(field.weights, np.float32)}
    if field.kind == "exact":
        bits = field.features.astype(np.float16).view(np.uint16)
        for j in range(field.dim):
            extras[f"lang_{j}"] = np.ascontiguousarray(bits[:, j])
        return extras
    for j in range(field.codes.shape[1]):
        extras[f"lang_code_{j}"] = np.ascontiguousarray(field.codes[:, j], np.uint8)
    extras["lang_norm"] = np.ascontiguousarray(field.norms, np.float32)
    if field.kind == "ivfpq":
        extras["lang_list"] = np.ascontiguousarray(field.list_ids, np.int32)
    return extras


def is_lang_property(name: str) -> bool:
    return name == "lang_weight" or name == "lang_norm" or name == "lang_list" or re.fullmatch(r"lang_(code_)?\d+", name) is not None


def strip_field(scene: GaussianScene) -> GaussianScene:
    """The scene without language properties and drsplat.lang comments (a plain 3DGS scene)."""
    return dataclasses.replace(
        scene,
        extra={k: v for k, v in scene.extra.items() if not is_lang_property(k)},
        comments=[c for c in scene.comments if not c.startswith(COMMENT_PREFIX)],
    )


def attach_field(scene: GaussianScene, field: LanguageField, ply_path: str | Path) -> GaussianScene:
    """The scene with the field's extra properties and header comment; writes the codebook.

    The codebook (pq, ivfpq) is written next to `ply_path` as `<stem>.codebook.faiss`; save the
    returned scene to `ply_path` with `drsplat.scene.save_ply`.
    """
    if field.num_gaussians != scene.num_gaussians:
        raise ValueError(f"field has {field.num_gaussians} Gaussians, scene has {scene.num_gaussians}")
    base = strip_field(scene)
    name = None
    if field.kind != "exact":
        target = codebook_path_for(ply_path)
        name = target.name
        source = field.codebook.path
        if source is not None and source.is_file() and source.resolve() != target.resolve():
            with atomic_path(target) as tmp:
                shutil.copyfile(source, tmp)
        elif source is None or source.resolve() != target.resolve():
            field.codebook.save(target)
    extra = dict(base.extra)
    extra.update(field_extras(field))
    return dataclasses.replace(base, extra=extra, comments=base.comments + [field_comment(field, name)])


def parse_field_comment(comments: list[str]) -> dict[str, str] | None:
    """The key=value pairs of the `drsplat.lang` header comment, or None when there is none."""
    for comment in comments:
        tokens = comment.split()
        if tokens and tokens[0] == COMMENT_PREFIX:
            return {k: unquote(v) for k, _, v in (t.partition("=") for t in tokens[1:])}
    return None


def read_field(scene: GaussianScene, ply_path: str | Path) -> LanguageField | None:
    """The language field of a scene loaded from `ply_path` (None if it has no drsplat.lang comment).

    Raises InputError naming the PLY (or codebook) file and the field for missing properties,
    an unknown kind, a missing codebook, or codes that do not fit the codebook.
    """
    ply_path = Path(ply_path)
    meta = parse_field_comment(scene.comments)
    if meta is None:
        return None
    kind = meta.get("kind")
    if kind not in KINDS:
        raise InputError(ply_path, f"unknown language field kind {kind!r}; expected one of {', '.join(KINDS)}", field="comment drsplat.lang")
    try:
        dim = int(meta.get("dim", ""))
    except ValueError:
        raise InputError(ply_path, f"dim={meta.get('dim')!r} is not an integer", field="comment drsplat.lang") from None
    if not 1 <= dim <= MAX_DIM:
        raise InputError(ply_path, f"dim={dim} is not a feature dimension (expected 1..{MAX_DIM})", field="comment drsplat.lang")
    clip_model = meta.get("clip", "unknown")
    weights = _extra(scene, ply_path, "lang_weight").astype(np.float32)
    if kind == "exact":
        cols = [_extra(scene, ply_path, f"lang_{j}") for j in range(dim)]
        features = _stack_columns(cols, np.uint16, scene.num_gaussians, dim).view(np.float16)
        norms = np.empty(scene.num_gaussians, np.float32)
        for start in range(0, scene.num_gaussians, EXACT_CHUNK):
            norms[start : start + EXACT_CHUNK] = np.linalg.norm(features[start : start + EXACT_CHUNK].astype(np.float32), axis=1)
        nonfinite = int(np.count_nonzero(~np.isfinite(norms)))
        if nonfinite:
            log.warning("%s: %d Gaussians have non-finite language features; they score 0", ply_path, nonfinite)
        return LanguageField(kind, dim, clip_model, weights, features=features, norms=norms)
    if "codebook" not in meta:
        raise InputError(ply_path, "a quantised language field names no codebook file", field="comment drsplat.lang")
    book = load_codebook(codebook_named_by(ply_path, meta["codebook"]))
    if book.kind != kind or book.dim != dim:
        raise InputError(book.path, f"codebook is {book.kind} d={book.dim}, but {ply_path.name} declares {kind} dim={dim}")
    cols = [_extra(scene, ply_path, f"lang_code_{j}") for j in range(book.m)]
    if f"lang_code_{book.m}" in scene.extra:
        raise InputError(ply_path, f"more PQ code columns than the codebook's M={book.m}", field=f"lang_code_{book.m}")
    codes = _stack_columns(cols, np.uint8, scene.num_gaussians, book.m)
    norms = _extra(scene, ply_path, "lang_norm").astype(np.float32)
    list_ids = None
    if kind == "ivfpq":
        list_ids = _extra(scene, ply_path, "lang_list").astype(np.int32)
        nlist = int(book.index.nlist)
        bad = (list_ids < 0) | (list_ids >= nlist)
        if np.any(bad):
            raise InputError(ply_path, f"{int(bad.sum())} coarse list ids fall outside 0..{nlist - 1}", field="lang_list")
    return LanguageField(kind, dim, clip_model, weights, codes=codes, list_ids=list_ids, norms=norms, codebook=book)


def codebook_named_by(ply_path: Path, name: str) -> Path:
    """The codebook a PLY header names, relative to the PLY's folder; a name leaving that folder
    (`../`, absolute) is followed but warned about, since a header is not trusted input."""
    target = ply_path.parent / name
    folder = os.path.normpath(os.path.abspath(ply_path.parent))
    if os.path.commonpath([folder, os.path.normpath(os.path.abspath(target))]) != folder:
        log.warning("%s: the header names a codebook outside the PLY's folder (%s); reading it as named", ply_path, target)
    return target


def _extra(scene: GaussianScene, ply_path: Path, name: str) -> np.ndarray:
    if name not in scene.extra:
        raise InputError(ply_path, "missing vertex property of the language field", field=name)
    return np.asarray(scene.extra[name])


def _stack_columns(cols: list[np.ndarray], dtype: type, n: int, width: int) -> np.ndarray:
    out = np.empty((n, width), dtype)
    for j, col in enumerate(cols):
        out[:, j] = col.astype(dtype, copy=False)
    return out
