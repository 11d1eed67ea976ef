"""CLIP model ids: the one owner of how an embedding space is named, recorded and compared.

An id is "model/pretrained" (e.g. "ViT-B-16/laion2b_s34b_b88k"). Feature manifests record it
(`manifest_clip_entry`), registered PLYs copy it, and queries check it (`check_compatible`): embeddings of
two different CLIP models live in unrelated spaces and their cosine is meaningless. "unknown" (features made
without a manifest, e.g. by LangSplat) is compared with anything, with a warning. ORACLE_MODEL_ID names the
synthetic scenes' oracle space, which only matches itself.
"""

from __future__ import annotations

import hashlib
import logging
import re
from pathlib import Path

from drsplat.errors import DrsplatError

log = logging.getLogger(__name__)

DEFAULT_MODEL = "ViT-B-16"
DEFAULT_PRETRAINED = "laion2b_s34b_b88k"
UNKNOWN_MODEL = "unknown"
ORACLE_MODEL_ID = "oracle"
CANONICAL_PHRASES = ("object", "things", "stuff", "texture")  # LERF relevancy's negatives (the official code's)


def make_model_id(model: str, pretrained: str | None) -> str:
    """The string that names an embedding space, e.g. "ViT-B-16/laion2b_s34b_b88k" ("oracle" alone)."""
    return f"{model}/{pretrained}" if pretrained else str(model)


def canonical_model_id(model_id: str) -> str:
    """Ids compare case-insensitively, with ':' and '/' as the same separator."""
    return model_id.strip().replace(":", "/").lower()


HUB_MODEL_PREFIXES = ("hf-hub:", "local-dir:")  # open_clip's names of a model and its weights together (any case)


def hub_model_kind(model: str) -> str | None:
    """'hf-hub' or 'local-dir' for an open_clip name of a model and its weights together ("hf-hub:ORG/REPO",
    "local-dir:PATH", in any case), else None."""
    lowered = model.strip().lower()
    return next((prefix[:-1] for prefix in HUB_MODEL_PREFIXES if lowered.startswith(prefix)), None)


def split_model_id(model_id: str) -> tuple[str, str | None]:
    """(architecture, weights tag or None) of a model id: split at its first '/' or ':' (the separators
    `canonical_model_id` reads as one), so "ViT-L-14:openai" and "ViT-B-16/file:ckpt.pt" both split after
    the architecture; an open_clip "hf-hub:ORG/REPO" or "local-dir:PATH" name is kept whole (`hub_model_kind`)."""
    model_id = model_id.strip()
    if hub_model_kind(model_id) is not None:
        return model_id, None
    cut = min((i for i in (model_id.find("/"), model_id.find(":")) if i >= 0), default=-1)
    if cut < 0:
        return model_id, None
    return model_id[:cut], model_id[cut + 1:] or None


def named_model(model_id: str | None) -> tuple[str, str | None] | None:
    """(architecture, weights tag or None) of the model an id names; None for no id ('' or 'unknown', in any case)."""
    if not model_id or canonical_model_id(model_id) == UNKNOWN_MODEL:
        return None
    return split_model_id(model_id)


def manifest_clip_entry(model: str, pretrained: str | None, checkpoint: str | None = None) -> dict:
    """The manifest.json keys that record the CLIP model (`clip` and `clip_model_id`, always consistent)."""
    return {
        "clip": {"model": model, "pretrained": pretrained or "", "checkpoint": checkpoint},
        "clip_model_id": make_model_id(model, pretrained),
    }


def manifest_model_id(manifest: dict) -> str:
    """The CLIP model id of a feature folder's manifest.json: `clip_model_id`, else 'model/pretrained' of
    `clip`, else UNKNOWN_MODEL (no manifest, or one written by another tool)."""
    model_id = manifest.get("clip_model_id")
    if isinstance(model_id, str) and model_id:
        return model_id
    clip = manifest.get("clip")
    if isinstance(clip, dict) and isinstance(clip.get("model"), str) and clip["model"]:
        pretrained = clip.get("pretrained")
        return make_model_id(clip["model"], pretrained if isinstance(pretrained, str) else None)
    if isinstance(clip, str) and clip:
        return clip
    return UNKNOWN_MODEL


def model_id_sources(manifest: dict) -> list[tuple[str, str]]:
    """(field, text) of every manifest string `manifest_model_id` may build the id from: `clip_model_id`,
    `clip` (a string), `clip.model` and `clip.pretrained`, with the field named as an error names it.
    All of them are checked, not only the one in use: they are recorded together and always consistent."""
    sources = [("clip_model_id", manifest.get("clip_model_id"))]
    clip = manifest.get("clip")
    if isinstance(clip, dict):
        sources += [("clip.model", clip.get("model")), ("clip.pretrained", clip.get("pretrained"))]
    else:
        sources.append(("clip", clip))
    return [(field, text) for field, text in sources if isinstance(text, str)]


def check_compatible(a: str | None, b: str | None, what_a: str = "the features", what_b: str = "the text encoder") -> None:
    """Raise DrsplatError unless two CLIP model ids can name the same embedding space.

    A missing id (None, "" or "unknown") on either side is accepted with a warning: nothing says the spaces differ;
    so is an id naming an architecture without a weights tag ("ViT-L-14", as another tool's manifest may write it)
    beside one of that architecture with a tag.
    """
    known = [m for m in (a, b) if named_model(m) is not None]
    if len(known) < 2:
        if (a or UNKNOWN_MODEL) != (b or UNKNOWN_MODEL):
            log.warning("the CLIP model of %s is %s and of %s is %s: cannot check they match", what_a, a or UNKNOWN_MODEL, what_b, b or UNKNOWN_MODEL)
        return
    # split as written (an hf-hub architecture keeps its ':'), compared as canonical ids are (round 83a F3)
    (arch_a, tag_a), (arch_b, tag_b) = ((canonical_model_id(arch), tag) for arch, tag in map(split_model_id, known))
    if arch_a == arch_b != ORACLE_MODEL_ID and (tag_a is None or tag_b is None) and tag_a != tag_b:  # one names no weights (round 79a F2)
        log.warning("the CLIP model of %s is %s and of %s is %s: one names no weights tag, so only the architecture is "
                    "checked", what_a, a, what_b, b)
        return
    if canonical_model_id(known[0]) != canonical_model_id(known[1]):
        # a tag "file:NAME" labels a checkpoint file: no --pretrained makes other weights those (round 87c F2: advised, refused again)
        how = (f"pass the checkpoint they were made with, {tag_a[len('file:'):]}, as --clip-checkpoint (with --clip-model {arch_a}), or "
               "make them again" if tag_a is not None and tag_a.startswith("file:") else f"use --clip-model/--pretrained to match {a}")
        raise DrsplatError(f"CLIP model mismatch: {what_a} were made with {a} but {what_b} is {b}; embeddings of different CLIP models "
                           f"cannot be compared ({how})")


def is_oracle(model_id: str | None) -> bool:
    """True for the synthetic scenes' oracle space (whatever preset/seed suffix an older file carries)."""
    return bool(model_id) and canonical_model_id(model_id).split("/")[0] == ORACLE_MODEL_ID


def weights_digest(path: str | Path | None) -> str | None:
    """'size:sha1' of a CLIP or SAM weights file (None without one): two files of one name (every download
    is `open_clip_pytorch_model.bin`) are told apart by their contents, so that features of two
    weights are not mixed in one folder (`RESUME_KEYS`). 0.68-0.74 s for 600 MB (ViT-B-16's size; page-cached, x86_64 Xeon)."""
    if path is None or not Path(path).is_file():
        return None
    digest = hashlib.sha1()
    with open(path, "rb") as f:
        while piece := f.read(1 << 24):
            digest.update(piece)
    return f"{Path(path).stat().st_size}:{digest.hexdigest()}"


WEIGHTS_DIGEST = re.compile(r"[0-9]{1,20}:[0-9a-f]{40}")  # what `weights_digest` writes


def check_clip_weights(field_weights: str | None, encoder_weights: str | None, checkpoint: str | Path | None) -> None:
    """Refuse a text encoder whose weights file is not the one the features were made with (`clip_weights_problem`)."""
    problem = clip_weights_problem(field_weights, encoder_weights, checkpoint)
    if problem is not None:
        raise DrsplatError(problem)


def clip_weights_problem(field_weights: str | None, encoder_weights: str | None, checkpoint: str | Path | None) -> str | None:
    """Why a text encoder cannot embed queries for a field: its weights file is not the one the features were made
    with, both known ('size:sha1', `weights_digest`) and different (None: it can). The model id alone cannot tell: a
    `--clip-checkpoint` is labelled with the field's own tag when --pretrained is not given, so any file passed it
    (round 57c: scores from another embedding space, no word). Unknown on either side (an older PLY, features of a
    hub tag without a file): not checked."""
    if field_weights is None or encoder_weights is None or field_weights == encoder_weights:
        return None
    return (f"CLIP weights mismatch: the registered features were made with a weights file of size:sha1 {field_weights}, "
            f"but the text encoder's ({checkpoint}) is {encoder_weights}: its text embeddings lie in another space; pass "
            "the checkpoint the features were made with")


def manifest_weights(manifest: dict) -> str | None:
    """The 'size:sha1' of the CLIP weights a feature folder's manifest.json records (`clip_weights`, written by
    `drsplat features`), or None: none recorded (LangSplat's own folders, synthetic features) or not one."""
    value = manifest.get("clip_weights")
    return value if isinstance(value, str) and WEIGHTS_DIGEST.fullmatch(value) else None
