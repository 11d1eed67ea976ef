"""Model weights: where they are cached, how they are found offline, and how they are downloaded once.

One owner for every cache directory drsplat reads or writes:
- `user_cache_root()`: $XDG_CACHE_HOME, else ~/.cache.
- `drsplat_cache_dir()`: drsplat's own downloads (SAM checkpoints): $DRSPLAT_CACHE, else <root>/drsplat.
- `hf_cache_dir()`: the Hugging Face hub cache OpenCLIP weights come from (HF_HUB_CACHE, HF_HOME, <root>/huggingface/hub).
- `clip_url_cache_dir()`: open_clip's cache for weights published by URL (<root>/clip).
Every path is read from the environment at call time (tests and users may change it). Offline (HF_HUB_OFFLINE or
DRSPLAT_OFFLINE) or unreachable, a missing file becomes one `WeightsUnavailableError` naming the flag to use.
"""

from __future__ import annotations

import contextlib
import logging
import os
import urllib.error
import urllib.request
from collections.abc import Iterator, Sequence
from pathlib import Path

from drsplat.errors import DrsplatError, WeightsUnavailableError
from drsplat.utils import atomic_path, host_reachable

log = logging.getLogger(__name__)


def user_cache_root() -> Path:
    """$XDG_CACHE_HOME, else ~/.cache."""
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))


def clip_url_cache_dir() -> Path:
    """Where open_clip keeps weights it downloads by URL (not through the hub)."""
    return user_cache_root() / "clip"


_HF_FILENAMES = ("open_clip_model.safetensors", "open_clip_pytorch_model.bin")


SAM_URLS = {
    "vit_h": "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_h_4b8939.pth",
    "vit_l": "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_l_0b3195.pth",
    "vit_b": "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_b_01ec64.pth",
}


def _env_flag(name: str) -> bool:
    return os.environ.get(name, "").strip().lower() in ("1", "true", "yes", "on")


def hf_offline() -> bool:
    """True when downloads are disabled (HF_HUB_OFFLINE or DRSPLAT_OFFLINE), read at call time."""
    return _env_flag("HF_HUB_OFFLINE") or _env_flag("DRSPLAT_OFFLINE")


def hf_cache_dir() -> Path:
    """The Hugging Face hub cache, from the environment at call time (HF_HUB_CACHE, HF_HOME)."""
    if os.environ.get("HF_HUB_CACHE"):
        return Path(os.environ["HF_HUB_CACHE"])
    if os.environ.get("HF_HOME"):
        return Path(os.environ["HF_HOME"]) / "hub"
    return user_cache_root() / "huggingface" / "hub"


def _unavailable(model: str, pretrained: str) -> WeightsUnavailableError:
    return WeightsUnavailableError(
        f"OpenCLIP weights for {model} ({pretrained}) are not in the local cache and cannot be downloaded; "
        "pass --clip-checkpoint PATH to a local open_clip checkpoint, or run once with internet access."
    )


def _cached_hf_file(repo_id: str, filenames: Sequence[str], cache_dir: Path) -> str | None:
    from huggingface_hub import try_to_load_from_cache

    for name in filenames:
        found = try_to_load_from_cache(repo_id, name, cache_dir=str(cache_dir))
        if isinstance(found, str) and os.path.isfile(found):
            return found
    return None


def resolve_pretrained_weights(model: str, pretrained: str) -> str:
    """Local file holding open_clip weights for (model, pretrained tag); downloads once if allowed.

    Looks in the HF hub cache first (no network), then downloads unless offline. Any failure
    becomes one WeightsUnavailableError naming --clip-checkpoint.
    """
    import open_clip

    if pretrained.startswith("file:"):
        raise WeightsUnavailableError(
            f"the embeddings were made with a local checkpoint ({pretrained[5:]}) of {model}; pass --clip-checkpoint PATH to that file"
        )
    cfg = open_clip.get_pretrained_cfg(model, pretrained)
    if not cfg:
        tags = ", ".join(open_clip.list_pretrained_tags_by_model(model)) or "none"
        raise DrsplatError(f"unknown OpenCLIP pretrained tag {pretrained!r} for model {model!r} (known tags: {tags}); or pass --clip-checkpoint PATH")
    cache_dir = hf_cache_dir()
    hub = cfg.get("hf_hub", "")
    if hub:
        repo_id, filename = os.path.split(hub)
        names = tuple(dict.fromkeys(((filename,) if filename else ()) + _HF_FILENAMES))
        cached = _cached_hf_file(repo_id, names, cache_dir)
        if cached:
            return cached
    elif cfg.get("url"):
        cached_url = clip_url_cache_dir() / os.path.basename(cfg["url"])
        if cached_url.is_file():
            return str(cached_url)
    source = f"{os.environ.get('HF_ENDPOINT', 'https://huggingface.co')}/{hub}" if hub else cfg["url"]
    if hf_offline() or not host_reachable(source):
        raise _unavailable(model, pretrained)
    try:
        from open_clip.pretrained import download_pretrained

        with _quiet_open_clip():
            path = download_pretrained(cfg, cache_dir=str(cache_dir) if hub else None)
    except Exception:  # requests / huggingface_hub / urllib errors: the user needs the flag, not the trace
        log.debug("download of %s/%s failed", model, pretrained, exc_info=True)
        raise _unavailable(model, pretrained) from None
    if not path or not os.path.isfile(path):
        raise _unavailable(model, pretrained)
    return path


@contextlib.contextmanager
def _quiet_open_clip() -> Iterator[None]:
    """open_clip logs its progress on the root logger at INFO/WARNING; keep the user's log clean."""
    previous = logging.root.manager.disable
    logging.disable(logging.WARNING)
    try:
        yield
    finally:
        logging.disable(previous)


def drsplat_cache_dir() -> Path:
    """Where downloaded weights are kept: $DRSPLAT_CACHE, else $XDG_CACHE_HOME/drsplat (~/.cache/drsplat)."""
    if os.environ.get("DRSPLAT_CACHE"):
        return Path(os.environ["DRSPLAT_CACHE"])
    return user_cache_root() / "drsplat"


def _sam_unavailable(model_type: str, cache: Path) -> WeightsUnavailableError:
    return WeightsUnavailableError(
        f"SAM weights ({model_type}) are not in the cache {cache} and cannot be downloaded; "
        "pass --sam-checkpoint PATH to a local SAM checkpoint, or run once with internet access."
    )


def sam_checkpoint_unavailable(model_type: str = "vit_h") -> WeightsUnavailableError | None:
    """The error `resolve_sam_checkpoint` would raise before downloading anything (the checkpoint is neither cached
    nor downloadable: offline, or its host unreachable), or None; checked before CLIP is built, so that a user
    without either weight file hears of both at once (round 104c F1: SAM's absence came a run later)."""
    if model_type not in SAM_URLS:
        raise DrsplatError(f"unknown SAM model '{model_type}': use one of {', '.join(SAM_URLS)}")
    url = SAM_URLS[model_type]
    cache = drsplat_cache_dir()
    if (cache / os.path.basename(url)).is_file():
        return None
    return _sam_unavailable(model_type, cache) if hf_offline() or not host_reachable(url) else None


def resolve_sam_checkpoint(model_type: str = "vit_h", timeout: float = 30.0) -> Path:
    """The official SAM checkpoint for `model_type`, downloaded once into drsplat_cache_dir()."""
    unavailable = sam_checkpoint_unavailable(model_type)
    if unavailable is not None:  # offline, no "downloading ..." line before it (round 104c F1)
        raise unavailable
    url = SAM_URLS[model_type]
    cache = drsplat_cache_dir()
    path = cache / os.path.basename(url)
    if path.is_file():
        return path
    log.info("downloading SAM %s weights from %s into %s", model_type, url, cache)
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response, atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                while chunk := response.read(1 << 20):
                    f.write(chunk)
    except (urllib.error.URLError, OSError, ValueError):
        log.debug("SAM download failed", exc_info=True)
        raise _sam_unavailable(model_type, cache) from None
    return path
