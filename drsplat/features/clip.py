"""OpenCLIP image/text encoder shared by feature extraction and the query side.

One `ClipEncoder` embeds images (mask crops) and text; both come out unit-normalised float32
numpy. Weights come from `--clip-checkpoint PATH` or from open_clip's pretrained tags through the
Hugging Face hub cache. Without either (offline, empty cache) a `WeightsUnavailableError` says in
one sentence which flag to use; network and hub exceptions never reach the user.

`model_id` ("ViT-B-16/laion2b_s34b_b88k") is written into feature manifests and registered PLYs;
`drsplat.features.modelid.check_compatible` refuses to compare embeddings of different models.
"""

from __future__ import annotations

import functools
import json
import logging
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from drsplat.device import resolve_device
from drsplat.errors import DrsplatError, InputError, WeightsUnavailableError, one_line
from drsplat.features.modelid import CANONICAL_PHRASES, DEFAULT_MODEL, DEFAULT_PRETRAINED, hub_model_kind, make_model_id, weights_digest
from drsplat.features.weights import _quiet_open_clip, resolve_pretrained_weights
from drsplat.utils import read_json

log = logging.getLogger(__name__)

OPENAI_MEAN = (0.48145466, 0.4578275, 0.40821073)
OPENAI_STD = (0.26862954, 0.26130258, 0.27577711)


def checkpoint_problem(path: Path, exc: BaseException) -> str:
    """Why torch / open_clip could not load the checkpoint `path`, in a few words (their own
    messages run to paragraphs about torch.load's weights_only): `exc` is what loading raised."""
    import zipfile

    text = str(exc)
    # open_clip asserts "text pos_embed width changed!" for a checkpoint of another architecture (round 87c F1: then called unreadable)
    if any(word in text for word in ("size mismatch", "Missing key", "Unexpected key", "width changed")):
        return _no_weights(_torch_contents(path)) or "its weights do not fit this architecture (missing, unexpected or mis-shaped tensors)"
    try:
        with open(path, "rb") as f:
            start = f.read(4)
        head = start[:1]
        is_zip = zipfile.is_zipfile(path)
    except OSError as err:
        return f"it cannot be read ({err.strerror or err})"
    if not is_zip and start == b"PK\x03\x04":
        return "it starts as a zip archive but its end is missing: the file is cut short (an interrupted download or copy?)"
    if not is_zip and Path(path).suffix == ".safetensors":
        return "it is not a readable safetensors file (cut short, or of another format)"
    if not is_zip and head != b"\x80":
        return "it is neither a torch.save checkpoint (a zip archive) nor a pickle"
    if "unsupported global" in text.lower():  # "Unsupported global: ..." and "unsupported GLOBAL posix.system ... is blocked"
        return "it holds Python objects besides tensors, which are not unpickled (torch.load weights_only)"
    state = _torch_contents(path) if is_zip else UNREADABLE
    if state is not UNREADABLE:  # round 96b F2: readable files (a list, an fp16 state dict of another architecture) were called unreadable
        return _no_weights(state) or "its weights do not fit this architecture (another model's, or tensors of another type)"
    return "it is a zip archive, but not a readable torch.save checkpoint" if is_zip else "it is a pickle, but not of a checkpoint torch can read"


UNREADABLE = object()  # `_torch_contents` of a file torch does not read


def _torch_contents(path: Path) -> object:
    """What torch reads from `path` (tensors only, memory-mapped), its "state_dict" entry where it has one; UNREADABLE
    when torch reads nothing."""
    import torch

    try:
        state = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception:  # noqa: BLE001 - any failure: the caller's "not readable"
        return UNREADABLE
    return state["state_dict"] if isinstance(state, dict) and isinstance(state.get("state_dict"), dict) else state


def _no_weights(state: object) -> str | None:
    """Why `_torch_contents` holds no weights at all ("torch reads it, but it holds list, ..."), None where it holds a
    dict of tensors or torch read nothing (round 97a F7: a dict of no tensor was said not to fit the architecture)."""
    import torch

    if state is UNREADABLE or (isinstance(state, dict) and any(isinstance(v, torch.Tensor) for v in state.values())):
        return None
    held = type(state).__name__ if not isinstance(state, dict) else "a dict of no tensors"
    return f"torch reads it, but it holds {held}, not a state dict of weights"


def unsupported_model_name(model: str) -> str | None:
    """Why an open_clip model name cannot be used, as a predicate ("is an open_clip hf-hub: name, ..."; None: it can):
    drsplat records an embedding space as architecture and weights apart (`modelid`), which open_clip's
    "hf-hub:ORG/REPO" and "local-dir:PATH" names join (`modelid.hub_model_kind`; round 61c)."""
    kind = hub_model_kind(model)
    return None if kind is None else f"is an open_clip {kind}: name, which drsplat does not load"


def open_clip_spelling(name: str, known: list[str]) -> str:
    """`name` as `known` spells it when they differ in case only (model ids compare case-insensitively,
    `modelid.canonical_model_id`, but open_clip's lookups are exact: round 83a F2); else `name`."""
    if name in known:
        return name
    same = [k for k in known if k.lower() == name.lower()]
    return same[0] if len(same) == 1 else name


class ClipEncoder:
    """OpenCLIP model embedding images and text into one unit-normalised space.

    model: open_clip architecture name (e.g. "ViT-B-16"); pretrained: tag naming the weights
    (default "laion2b_s34b_b88k"); checkpoint: local weights file (replaces the tag's download;
    `pretrained` then only labels the embedding space, default "file:<checkpoint name>").
    device: auto|cpu|cuda. fp16 on CUDA, fp32 on CPU. Text embeddings are cached per phrase.
    """

    def __init__(
        self,
        model: str = DEFAULT_MODEL,
        pretrained: str | None = None,
        checkpoint: str | Path | None = None,
        device: str = "auto",
        batch_size: int = 64,
        *,
        random_weights: bool = False,
    ):
        import open_clip
        import torch

        problem = unsupported_model_name(model)
        if problem is not None:
            raise DrsplatError(f"CLIP model {model!r} {problem}: use an architecture of open_clip.list_models() with --clip-checkpoint "
                               "FILE (and --clip-config CONFIG.json for one open_clip does not ship)")
        model = open_clip_spelling(model, open_clip.list_models())
        if model not in open_clip.list_models():  # a config of another name read as none given (round 61c): say how names are made
            raise DrsplatError(f"unknown OpenCLIP model {model!r} (see open_clip.list_models()); an architecture open_clip does not ship "
                               f"needs its model config, --clip-config CONFIG.json, and open_clip names that model after the file: "
                               f"{json.dumps(model)[1:-1]}.json registers --clip-model {json.dumps(model)[1:-1]}")
        self.device = resolve_device(device)
        self.dtype = torch.float16 if self.device == "cuda" else torch.float32
        self.batch_size = int(batch_size)
        self.model_name = model
        if checkpoint is not None:
            checkpoint = Path(checkpoint)
            problem = checkpoint_file_problem(checkpoint)
            if problem is not None:
                raise InputError(checkpoint, problem)
            self.pretrained = pretrained or f"file:{checkpoint.name}"
            weights = str(checkpoint)
        elif random_weights:
            self.pretrained = "random"
            weights = None
        else:
            self.pretrained = open_clip_spelling(pretrained or DEFAULT_PRETRAINED, open_clip.list_pretrained_tags_by_model(model))
            weights = resolve_pretrained_weights(model, self.pretrained)
        self.checkpoint = weights
        try:
            with _quiet_open_clip(), warnings.catch_warnings():  # torch's pickle-protocol UserWarning: the error below says it
                warnings.simplefilter("ignore", UserWarning)
                net = open_clip.create_model(model, pretrained=weights, device="cpu")
        except Exception as exc:  # unpickling / zip / shape errors of many kinds: one clear line
            if weights is None:
                raise
            unbuildable = _architecture_problem(open_clip, model)
            if unbuildable is not None:  # the model's config, not the weights file, is at fault (round 61c: blamed the checkpoint)
                raise DrsplatError(f"open_clip cannot build model {model} from its config (--clip-config): {unbuildable}") from None
            raise InputError(weights, f"not an open_clip checkpoint for {model}: {checkpoint_problem(Path(weights), exc)}") from None
        self.net = net.to(self.device, dtype=self.dtype).eval()
        try:
            with _quiet_open_clip():
                self.tokenizer = open_clip.get_tokenizer(model)
        except ImportError as exc:  # Hugging Face tokenizers (SigLIP, ...) need transformers
            raise DrsplatError(f"the text tokenizer of OpenCLIP model {model} needs the Python package "
                               f"'{exc.name or 'transformers'}', which is not installed (pip install {exc.name or 'transformers'})") from None
        except OSError:  # a Hugging Face tokenizer neither in the cache nor downloadable
            raise WeightsUnavailableError(f"the text tokenizer of OpenCLIP model {model} is not in the local Hugging Face cache and "
                                          "cannot be downloaded; run once with internet access") from None
        tag_cfg = open_clip.get_pretrained_cfg(model, self.pretrained) if not self.pretrained.startswith(("file:", "random")) else {}
        self.normalisation_problem: str | None = None  # why the images' normalisation is unknown (`require_image_normalisation`)
        known_tags = open_clip.list_pretrained_tags_by_model(model)
        if checkpoint is not None and not self.pretrained.startswith("file:") and known_tags and self.pretrained not in known_tags:
            # a tag open_clip does not know for this model (a typo: laion2b_s32b_b82) set OpenAI's normalisation (round 62b)
            log.warning("--pretrained %s is not a tag open_clip knows for %s (%s); the crops are normalised as the model's known "
                        "weights say", json.dumps(self.pretrained), model, ", ".join(known_tags[:6]) + (", ..." if len(known_tags) > 6 else ""))
        if self.pretrained.startswith("file:") or (checkpoint is not None and known_tags and self.pretrained not in known_tags):
            tag_cfg, self.normalisation_problem = checkpoint_normalisation(open_clip, model)  # the model's known weights decide
        self.mean = tuple(tag_cfg.get("mean") or OPENAI_MEAN)
        self.std = tuple(tag_cfg.get("std") or OPENAI_STD)
        size = getattr(self.net.visual, "image_size", 224)
        if isinstance(size, (tuple, list)) and len(set(size)) > 1:  # crops are square: a [224, 160] input failed inside torch (round 61c)
            raise DrsplatError(f"OpenCLIP model {model} takes {'x'.join(str(v) for v in size)} images; drsplat embeds square mask crops "
                               "(LangSplat's recipe), so only models of a square image_size can be used")
        self.image_size = int(size[0] if isinstance(size, (tuple, list)) else size)
        self._text_cache: dict[str, np.ndarray] = {}

    def require_image_normalisation(self) -> None:
        """Refuse to embed images whose normalisation is a guess (a --clip-checkpoint of a model whose known weights
        are normalised in more than one way, given without --pretrained); text needs none."""
        if self.normalisation_problem is not None:
            raise InputError(self.checkpoint, self.normalisation_problem)

    @classmethod
    def random(cls, model: str = DEFAULT_MODEL, device: str = "cpu", batch_size: int = 64) -> "ClipEncoder":
        """The architecture with random weights: for speed benchmarks only (timing is the same)."""
        return cls(model, None, None, device, batch_size, random_weights=True)

    @property
    def model_id(self) -> str:
        return make_model_id(self.model_name, self.pretrained)

    @functools.cached_property
    def weights_digest(self) -> str | None:
        """'size:sha1' of the weights file loaded (a --clip-checkpoint or the hub's cached file; `weights_digest`), None
        for random weights; read once, when a field that records its features' weights asks (about a second for 600 MB)."""
        return weights_digest(self.checkpoint)

    @property
    def dim(self) -> int:
        projection = getattr(self.net, "text_projection", None)
        if getattr(projection, "shape", None) is not None:  # a [width, D] parameter
            return int(projection.shape[1])
        if isinstance(getattr(projection, "out_features", None), int):  # an nn.Linear ("proj_bias": true; round 61c: AttributeError)
            return int(projection.out_features)
        return int(self.encode_text(["object"]).shape[1])

    def _normalised(self, x) -> np.ndarray:
        import torch

        x = x.float()
        x = x / torch.linalg.vector_norm(x, dim=-1, keepdim=True).clamp_min(1e-12)
        return x.cpu().numpy().astype(np.float32)

    def encode_images(self, images) -> np.ndarray:
        """Embed images already cropped to the model's input size.

        images: [B, 3, S, S] float RGB in [0, 1] (numpy or torch), S = self.image_size.
        CLIP normalisation (x - mean) / std is applied here. Returns [B, D] unit float32.
        """
        import torch

        self.require_image_normalisation()

        x = torch.as_tensor(images)
        if x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"images must be [B, 3, S, S], got {tuple(x.shape)}")
        mean = torch.tensor(self.mean, dtype=torch.float32).view(1, 3, 1, 1)
        std = torch.tensor(self.std, dtype=torch.float32).view(1, 3, 1, 1)
        out = []
        with torch.inference_mode():
            for start in range(0, x.shape[0], self.batch_size):
                chunk = (x[start : start + self.batch_size].float() - mean) / std
                out.append(self._normalised(self.net.encode_image(chunk.to(self.device, dtype=self.dtype))))
        if not out:
            return np.zeros((0, self.dim), np.float32)
        return np.concatenate(out)

    def encode_text(self, phrases: Sequence[str]) -> np.ndarray:
        """Embed phrases, [K] -> [K, D] unit float32; each phrase is computed once per encoder."""
        import torch

        phrases = list(phrases)
        missing = list(dict.fromkeys(p for p in phrases if p not in self._text_cache))
        if missing:
            self._warn_if_cut(missing)
            with torch.inference_mode():
                tokens = self.tokenizer(missing).to(self.device)
                emb = self._normalised(self.net.encode_text(tokens))
            self._text_cache.update(zip(missing, emb))
        if not phrases:
            return np.zeros((0, self.dim), np.float32)
        return np.stack([self._text_cache[p] for p in phrases])

    def _warn_if_cut(self, phrases: Sequence[str]) -> None:
        """A warning for each phrase longer than the text encoder's context (77 tokens for CLIP, start and end
        included): the tokenizer cuts it there, so the words after change nothing (round 61a: twelve phrases and
        'mug' scored as the twelve without it). Tokenizers without a plain `encode` (Hugging Face's) are not checked."""
        encode = getattr(self.tokenizer, "encode", None)
        limit = getattr(self.tokenizer, "context_length", None)
        if not callable(encode) or not isinstance(limit, int) or getattr(self.tokenizer, "reduction_fn", None) is not None:
            return
        for phrase in phrases:
            count = len(encode(phrase)) + 2  # its start and end tokens
            if count > limit:
                shown = phrase if len(phrase) <= 60 else phrase[:57] + "..."
                log.warning("the phrase %s is %d tokens, more than the %d of %s's text context: only its first %d are embedded, "
                            "the words after them change nothing", json.dumps(shown, ensure_ascii=False), count, limit, self.model_name, limit - 2)

    def canonical_embeddings(self) -> np.ndarray:
        """[4, D] embeddings of the relevancy score's canonical phrases (CANONICAL_PHRASES)."""
        return self.encode_text(CANONICAL_PHRASES)


def checkpoint_file_problem(checkpoint: Path) -> str | None:
    """Why `checkpoint` (--clip-checkpoint) is no checkpoint file, or None: a folder, FIFO or device exists but is
    none (a FIFO would block the read)."""
    if checkpoint.is_file():
        return None
    return ("is not a file (--clip-checkpoint): expected an open_clip checkpoint file" if checkpoint.exists()
            else "CLIP checkpoint file does not exist (--clip-checkpoint)")


def check_clip_config(path: Path) -> None:
    """Refuse a --clip-config file that open_clip would fail on with a traceback (bad JSON) or skip
    silently (not .json, not a model config). In a folder open_clip reads every .json file and takes the model
    configs among them: one it cannot parse is refused (a JSONDecodeError traceback, round 61c), other JSON
    is left to it as it leaves it (round 62b: an open_clip_config.json beside the config was refused), and a
    folder without a model config is refused."""
    path = Path(path)
    if path.is_dir():
        found = 0
        for config in sorted(path.glob("*.json")):
            data = read_json(config, "a JSON file of a --clip-config folder (open_clip reads each)")
            found += isinstance(data, dict) and all(key in data for key in ("embed_dim", "vision_cfg", "text_cfg"))
        if not found:
            raise InputError(path, "holds no open_clip model config (a .json file with embed_dim, vision_cfg and text_cfg; "
                                   "--clip-config takes such a file, or a folder of them)")
        return
    if path.suffix != ".json":
        raise InputError(path, "must be a .json file: open_clip ignores a --clip-config of another suffix")
    config = read_json(path, "an open_clip model config (--clip-config)")
    missing = [key for key in ("embed_dim", "vision_cfg", "text_cfg") if not isinstance(config, dict) or key not in config]
    if missing:
        raise InputError(path, "is not an open_clip model config (--clip-config): it has no " + ", ".join(missing), field=missing[0])


def _architecture_problem(open_clip, model: str) -> str | None:
    """Why open_clip cannot build `model` with random weights (its config at fault), or None when it can."""
    try:
        with _quiet_open_clip(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            open_clip.create_model(model, pretrained=None, device="cpu")
    except Exception as exc:  # noqa: BLE001 - any failure of the config itself, named in one line
        return one_line(f"{type(exc).__name__}: {exc}")[:300]
    return None


def checkpoint_normalisation(open_clip, model: str) -> tuple[dict, str | None]:
    """({mean, std} or {}, problem) for a --clip-checkpoint of `model` given without --pretrained: the image
    normalisation every known weights tag of the model uses (OpenAI's for ViT-B-16; 0.5 for SigLIP; 0 / 1 for
    MobileCLIP), {} (OpenAI's, open_clip's own default for a file) for a model no tag is known for, and a problem
    when its tags disagree (ViT-L-14: OpenAI's, or 0.5 for laion2b_s32b_b82k). OpenAI's was used for every checkpoint,
    a SigLIP one too: cosine 0.85 to the right embedding of the same crops, without a word (round 61c)."""
    ways: dict[tuple, list[str]] = {}
    for tag in open_clip.list_pretrained_tags_by_model(model):
        cfg = open_clip.get_pretrained_cfg(model, tag)
        ways.setdefault((tuple(cfg.get("mean") or OPENAI_MEAN), tuple(cfg.get("std") or OPENAI_STD)), []).append(tag)
    if len(ways) == 1:
        (mean, std), = ways
        return {"mean": mean, "std": std}, None
    if not ways:
        return {}, None
    listed = "; ".join(f"{', '.join(tags[:3])}{', ...' if len(tags) > 3 else ''}: mean {', '.join(f'{v:.3g}' for v in mean)}"
                       for (mean, _), tags in ways.items())
    return {}, (f"the known weights of {model} normalise images in {len(ways)} ways ({listed}), and this checkpoint was "
                "given without --pretrained: pass --pretrained TAG naming the weights it holds, which also sets how its crops "
                "are normalised")


def config_model_names(path: Path) -> list[str]:
    """The models a --clip-config registers, as open_clip names them: each model config's file name without .json (a
    file, or the model configs of a folder; `check_clip_config` has refused any other)."""
    path = Path(path)
    if not path.is_dir():
        return [path.stem]
    names = []
    for config in sorted(path.glob("*.json")):
        data = read_json(config, "a JSON file of a --clip-config folder (open_clip reads each)")
        if isinstance(data, dict) and all(key in data for key in ("embed_dim", "vision_cfg", "text_cfg")):
            names.append(config.stem)
    return names


def model_for_config(given: str | None, config: Path | None, default: str = DEFAULT_MODEL) -> str:
    """The open_clip model to build: --clip-model when given; else, when --clip-config registers one model and not
    `default`, that model (round 66b F1: `--clip-checkpoint tiny.pt --clip-config TinyCLIP.json` built ViT-B-16 and
    called the checkpoint unreadable); else `default`. A config that does not register the model chosen is said, once:
    it is not used."""
    if config is not None:
        check_clip_config(config)
    names = config_model_names(config) if config is not None else []
    model = given if given is not None else (names[0] if len(names) == 1 and default not in names else default)
    if given is None and model != default:
        log.info("--clip-config %s registers model %s: built as --clip-model %s", config, model, model)
    if names and model not in names:
        log.warning("--clip-config %s registers %s, not model %s (--clip-model%s), so it is not used: open_clip names a config's "
                    "model after its file", config, ", ".join(names), model, "" if given is not None else ", by default")
    return model


def use_clip_config(path: Path | None) -> None:
    """Make the architecture of an open_clip model config (--clip-config: JSON, or a folder of
    them) known to open_clip, after `check_clip_config`; nothing for None."""
    if path is None:
        return
    import open_clip

    check_clip_config(path)
    open_clip.add_model_config(path)
