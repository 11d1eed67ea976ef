"""The registered-PLY format: how a `LanguageField` is stored in extra vertex properties of an INRIA PLY (the one place it is specified)."""

from __future__ import annotations

import dataclasses
import logging
import shutil
from pathlib import Path
from urllib.parse import quote, unquote

import numpy as np

from drsplat.errors import InputError
from drsplat.lang.codebook import load_codebook
from drsplat.lang.backends import BACKENDS, needs_codebook
from drsplat.lang.field import LanguageField
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


def attach_field(scene: GaussianScene, field: LanguageField, ply_path: str | Path) -> GaussianScene:
    """The scene with the field's extra properties and header comment; writes the codebook.

    The codebook (pq, ivfpq) is written next to `ply_path` as `<stem>.codebook.faiss`; save the
    returned scene to `ply_path` with `drsplat.scene.save_ply`.
    """
    if field.num_gaussians != scene.num_gaussians:
        raise ValueError(f"field has {field.num_gaussians} Gaussians, scene has {scene.num_gaussians}")
    base = strip_field(scene)
    name = None
    if needs_codebook(field.kind):
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
    if kind not in BACKENDS:
        raise InputError(ply_path, f"unknown language field kind {kind!r}; expected one of {', '.join(BACKENDS)}", field="comment drsplat.lang")
    try:
        dim = int(meta.get("dim", ""))
    except ValueError:
        raise InputError(ply_path, f"dim={meta.get('dim')!r} is not an integer", field="comment drsplat.lang") from None
    clip_model = meta.get("clip", "unknown")
    weights = _extra(scene, ply_path, "lang_weight").astype(np.float32)
    book = None
    if needs_codebook(kind):
        if "codebook" not in meta:
            raise InputError(ply_path, "a quantised language field names no codebook file", field="comment drsplat.lang")
        book = load_codebook(ply_path.parent / meta["codebook"])
        if book.kind != kind or book.dim != dim:
            raise InputError(book.path, f"codebook is {book.kind} d={book.dim}, but {ply_path.name} declares {kind} dim={dim}")
        if f"lang_code_{book.m}" in scene.extra:
            raise InputError(ply_path, f"more PQ code columns than the codebook's M={book.m}", field=f"lang_code_{book.m}")
    try:
        storage = BACKENDS[kind].from_columns(lambda name: _extra(scene, ply_path, name), scene.num_gaussians, dim, book)
    except InputError as exc:
        if exc.path is not None:
            raise
        raise InputError(ply_path, exc.problem, field=exc.field) from None
    nonfinite = int(np.count_nonzero(~np.isfinite(storage.norms)))
    if nonfinite:
        log.warning("%s: %d Gaussians have non-finite language features; they score 0", ply_path, nonfinite)
    return LanguageField(dim, clip_model, weights, storage)


def _extra(scene: GaussianScene, ply_path: Path, name: str) -> np.ndarray:
    if name not in scene.extra:
        raise InputError(ply_path, "missing vertex property of the language field", field=name)
    return np.asarray(scene.extra[name])
