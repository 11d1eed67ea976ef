"""Mask generators (SAM, Felzenszwalb, SLIC) and LangSplat's mask post-processing.

Every generator returns LangSplat's four levels, in this order (`LEVELS`):

| index | name    | SAM (LangSplat)                                   | weight-free generators          |
|-------|---------|---------------------------------------------------|---------------------------------|
| 0     | default | all multimask outputs together (overlapping)      | between s and m                 |
| 1     | s       | SAM's first multimask output (parts, small)       | finest partition                |
| 2     | m       | second output (subparts / objects)                | coarser                         |
| 3     | l       | third output (whole objects, large)               | coarsest                        |

Feature files store one id map per level with ids *cumulative* across levels (level j's ids
follow all masks of levels 0..j-1); registration reads level 1 (s) by default.

Felzenszwalb and SLIC produce non-overlapping superpixels at four granularities: they need no
weights and run in a fraction of a second on a CPU, but their regions follow colour, not objects,
so features made from them are clearly lower quality than SAM's.
"""

from __future__ import annotations

import logging
import os
import urllib.error
import urllib.request
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numba
import numpy as np

from drsplat.errors import DrsplatError, InputError, WeightsUnavailableError
from drsplat.utils import atomic_path

log = logging.getLogger(__name__)

LEVELS = ("default", "s", "m", "l")
GENERATORS = ("sam", "felzenszwalb", "slic")
SAM_URLS = {
    "vit_h": "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_h_4b8939.pth",
    "vit_l": "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_l_0b3195.pth",
    "vit_b": "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_b_01ec64.pth",
}


@dataclass
class MaskSet:
    """Masks of one level. masks: [K, H, W] bool; scores: [K] float32 (higher is better)."""

    masks: np.ndarray
    scores: np.ndarray

    def __len__(self) -> int:
        return int(self.masks.shape[0])

    def subset(self, keep: np.ndarray) -> "MaskSet":
        return MaskSet(self.masks[keep], self.scores[keep])


def empty_maskset(height: int, width: int) -> MaskSet:
    return MaskSet(np.zeros((0, height, width), bool), np.zeros(0, np.float32))


# ---------------------------------------------------------------------------------------------
# Post-processing (LangSplat's masks_update)


@dataclass
class NmsParams:
    """LangSplat's masks_update thresholds (preprocess.py: iou 0.8, score 0.7, inner 0.5)."""

    iou_thr: float = 0.8
    score_thr: float = 0.7
    inner_thr: float = 0.5


@numba.njit(cache=True, nogil=True)
def _mask_boxes(masks: np.ndarray) -> np.ndarray:
    """[K, H, W] uint8 -> [K, 4] (y0, y1, x0, x1) half-open boxes; empty masks get y0 = y1 = 0."""
    k_count, h, w = masks.shape
    boxes = np.zeros((k_count, 4), np.int64)
    for k in range(k_count):
        y0, y1, x0, x1 = h, -1, w, -1
        for y in range(h):
            row = masks[k, y]
            for x in range(w):
                if row[x]:
                    if y < y0:
                        y0 = y
                    y1 = y
                    if x < x0:
                        x0 = x
                    if x > x1:
                        x1 = x
        if y1 >= 0:
            boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3] = y0, y1 + 1, x0, x1 + 1
    return boxes


@numba.njit(cache=True, nogil=True)
def _intersections_kernel(masks: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    k_count, h, w = masks.shape
    n_words = (k_count + 63) // 64
    inter = np.zeros((k_count, k_count), np.int64)
    words = np.zeros((w + 1, n_words), np.uint64)
    members = np.empty(k_count, np.int64)
    for y in range(h):
        words[:] = 0
        for k in range(k_count):
            if boxes[k, 0] <= y < boxes[k, 1]:
                bit = np.uint64(1) << np.uint64(k & 63)
                wi = k >> 6
                row = masks[k, y]
                for x in range(boxes[k, 2], boxes[k, 3]):
                    if row[x]:
                        words[x, wi] |= bit
        start = 0
        for x in range(1, w + 1):
            same = x < w
            if same:
                for wi in range(n_words):
                    if words[x, wi] != words[start, wi]:
                        same = False
                        break
            if same:
                continue
            run = x - start
            n = 0
            for wi in range(n_words):
                word = words[start, wi]
                b = 0
                while word != 0:
                    if word & np.uint64(1):
                        members[n] = wi * 64 + b
                        n += 1
                    word >>= np.uint64(1)
                    b += 1
            for i in range(n):
                for j in range(n):
                    inter[members[i], members[j]] += run
            start = x
    return inter


def intersections(masks: np.ndarray) -> np.ndarray:
    """Pairwise pixel intersections I[i, j] = |m_i ∧ m_j|: masks [K, H, W] bool -> [K, K] int64.

    Numba kernel: per image row, each mask ORs its bit into a per-pixel bitset (only inside its
    bounding box); runs of equal bitsets add their length to every pair of member masks. Cost
    ∝ Σ box areas + Σ_runs (members)², never a dense K·P product.
    """
    m = np.ascontiguousarray(masks, dtype=bool).view(np.uint8)
    if m.shape[0] == 0:
        return np.zeros((0, 0), np.int64)
    return _intersections_kernel(m, _mask_boxes(m))


def intersections_reference(masks: np.ndarray) -> np.ndarray:
    """Obviously-correct reference of `intersections`: a float64 matrix product of flat masks."""
    flat = masks.reshape(masks.shape[0], -1).astype(np.float64)
    return np.rint(flat @ flat.T).astype(np.int64)


def _nms_from_overlaps(inter: np.ndarray, area: np.ndarray, scores: np.ndarray, p: NmsParams) -> np.ndarray:
    """Kept positions, given the overlaps of masks already sorted by descending score."""
    k = len(scores)
    with np.errstate(divide="ignore", invalid="ignore"):
        frac_i = inter / area[:, None]  # share of mask i (row) covered by mask j
        frac_j = inter / area[None, :]
        iou = inter / (area[:, None] + area[None, :] - inter)
    upper = np.triu(np.ones((k, k), bool), 1)
    iou_max = np.where(upper, iou, 0.0).max(axis=0, initial=0.0)
    inner_val = 1.0 - frac_i * frac_j
    j_in_i = (frac_i < 0.5) & (frac_j >= 0.85)  # mask j lies mostly inside the larger mask i
    i_in_j = (frac_i >= 0.85) & (frac_j < 0.5)
    inner = np.where(upper & j_in_i, inner_val, 0.0)
    inner = np.maximum(inner, np.where(upper & i_in_j, inner_val, 0.0).T)
    band_l = np.tril(np.ones((k, k), bool), 1)  # torch.tril(diagonal=1) as in LangSplat
    inner_u = np.where(upper, inner, 0.0).max(axis=0, initial=0.0)
    inner_l = np.where(band_l, inner, 0.0).max(axis=0, initial=0.0)
    return _combine_keeps(iou_max, inner_u, inner_l, scores, p)


def _combine_keeps(iou_max: np.ndarray, inner_u: np.ndarray, inner_l: np.ndarray, scores: np.ndarray, p: NmsParams) -> np.ndarray:
    keep = iou_max <= p.iou_thr
    conds = [scores > p.score_thr, inner_u <= 1 - p.inner_thr, inner_l <= 1 - p.inner_thr]
    for cond in conds:
        if not cond.any():  # LangSplat's fallback: the three best-scored masks pass this test
            cond[: min(3, len(cond))] = True
        keep &= cond
    return np.flatnonzero(keep)


def _sorted_by_score(masks: np.ndarray, scores: np.ndarray) -> np.ndarray:
    if masks.ndim != 3 or len(scores) != masks.shape[0]:
        raise ValueError(f"masks must be [K, H, W] with K scores, got {masks.shape} and {len(scores)}")
    if masks.shape[0] and not masks.reshape(masks.shape[0], -1).any(axis=1).all():
        raise ValueError("masks must be non-empty")
    return np.argsort(-np.asarray(scores, np.float64), kind="stable")


def mask_nms(masks: np.ndarray, scores: np.ndarray, params: NmsParams = NmsParams()) -> np.ndarray:
    """LangSplat's mask NMS, vectorised. masks: [K, H, W] bool (non-empty), scores: [K].

    Masks are sorted by descending score (stable). With I = |m_i ∧ m_j|, a_i = |m_i|, for i < j:
    IoU_ij = I / (a_i + a_j - I); mask j is dropped if max_{i<j} IoU_ij > iou_thr, or its score
    <= score_thr, or it is in an "inner" relation 1 - (I/a_i)(I/a_j) > 1 - inner_thr with a mask
    where one covers >= 85 % of the other and the other < 50 % of it. The inner maxima are taken
    as LangSplat does: over rows above the diagonal (upper) and over rows >= j - 1 (its
    torch.tril(diagonal=1), which includes the first superdiagonal). If a test would drop every
    mask, the three best-scored masks pass it. Returns kept indices into `masks`, in score order.
    """
    order = _sorted_by_score(masks, scores)
    if len(order) == 0:
        return order
    ordered = masks[order]
    inter = intersections(ordered).astype(np.float64)
    area = np.diag(inter).copy()
    return order[_nms_from_overlaps(inter, area, np.asarray(scores, np.float64)[order], params)]


def mask_nms_reference(masks: np.ndarray, scores: np.ndarray, params: NmsParams = NmsParams()) -> np.ndarray:
    """Straightforward double loop over mask pairs, as LangSplat's preprocess.py (for tests)."""
    order = _sorted_by_score(masks, scores)
    k = len(order)
    if k == 0:
        return order
    m = masks[order].reshape(k, -1)
    s = np.asarray(scores, np.float64)[order]
    area = m.sum(axis=1).astype(np.float64)
    iou = np.zeros((k, k))
    inner = np.zeros((k, k))
    for i in range(k):
        for j in range(i, k):
            inter = float(np.logical_and(m[i], m[j]).sum())
            union = float(np.logical_or(m[i], m[j]).sum())
            iou[i, j] = inter / union
            a, b = inter / area[i], inter / area[j]
            if a < 0.5 and b >= 0.85:
                inner[i, j] = 1 - b * a
            if a >= 0.85 and b < 0.5:
                inner[j, i] = 1 - b * a
    iou_max = np.triu(iou, 1).max(axis=0)
    inner_u = np.triu(inner, 1).max(axis=0)
    inner_l = np.tril(inner, 1).max(axis=0)
    return order[_combine_keeps(iou_max, inner_u, inner_l, s, params)]


def masks_update(levels: list[MaskSet], params: NmsParams = NmsParams()) -> list[MaskSet]:
    """Remove redundant masks of each level (LangSplat's masks_update); kept masks keep their order.

    Empty masks are dropped first (they carry no pixels to register).
    """
    out = []
    for level in levels:
        nonempty = np.flatnonzero(level.masks.reshape(len(level), -1).any(axis=1)) if len(level) else np.zeros(0, np.int64)
        level = level.subset(nonempty)
        keep = np.sort(mask_nms(level.masks, level.scores, params))
        out.append(level.subset(keep))
    return out


# ---------------------------------------------------------------------------------------------
# Weight-free generators


def _partition_to_maskset(labels: np.ndarray, min_area: int) -> MaskSet:
    """labels: [H, W] int >= 0 -> one mask per label with at least min_area pixels."""
    ids, inverse, counts = np.unique(labels.ravel(), return_inverse=True, return_counts=True)
    big = np.flatnonzero(counts >= min_area)
    masks = inverse.reshape(labels.shape)[None] == big[:, None, None]
    return MaskSet(masks, np.ones(len(big), np.float32))


def _work_image(image: np.ndarray, max_side: int) -> np.ndarray:
    """The image shrunk (bilinear) so its longer side is at most max_side: superpixels of a
    ~0.1 MP image are as good as full-size ones and several times cheaper."""
    from PIL import Image

    h, w = image.shape[:2]
    scale = max_side / max(h, w)
    if scale >= 1.0:
        return image
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return np.asarray(Image.fromarray(image).resize(size, Image.BILINEAR))


def _levels_from_label_maps(label_maps: list[np.ndarray], height: int, width: int, min_area_fraction: float) -> list[MaskSet]:
    from drsplat.features.format import resample_nearest

    min_area = max(16, int(min_area_fraction * height * width))
    return [_partition_to_maskset(resample_nearest(labels, width, height), min_area) for labels in label_maps]


@dataclass
class FelzenszwalbParams:
    """Felzenszwalb `scale` per level (default, s, m, l) on the working image (longer side
    `work_size` px), Gaussian pre-smoothing `sigma`, and the smallest region kept as a fraction
    of the image (smaller segments are merged by the algorithm, leftovers dropped)."""

    scales: tuple[float, float, float, float] = (300.0, 150.0, 800.0, 2000.0)
    sigma: float = 0.8
    min_area_fraction: float = 0.003
    work_size: int = 320


@dataclass
class SlicParams:
    """SLIC `n_segments` per level (default, s, m, l), compactness, working image size, and the
    smallest region kept as a fraction of the image."""

    n_segments: tuple[int, int, int, int] = (32, 64, 16, 6)
    compactness: float = 10.0
    min_area_fraction: float = 0.003
    work_size: int = 320


class FelzenszwalbGenerator:
    """Graph-based superpixels (scikit-image felzenszwalb) at four scales; no weights."""

    name = "felzenszwalb"

    def __init__(self, params: FelzenszwalbParams | None = None):
        self.params = params or FelzenszwalbParams()

    def parameters(self) -> dict:
        return asdict(self.params)

    def generate(self, image: np.ndarray) -> list[MaskSet]:
        """image: [H, W, 3] uint8 RGB -> four MaskSets (LEVELS order) of disjoint regions."""
        from skimage.segmentation import felzenszwalb

        p = self.params
        work = _work_image(image, p.work_size)
        min_size = max(4, int(p.min_area_fraction * work.shape[0] * work.shape[1]))
        maps = [felzenszwalb(work, scale=scale, sigma=p.sigma, min_size=min_size) for scale in p.scales]
        return _levels_from_label_maps(maps, image.shape[0], image.shape[1], p.min_area_fraction)


class SlicGenerator:
    """k-means superpixels (scikit-image slic) at four segment counts; no weights."""

    name = "slic"

    def __init__(self, params: SlicParams | None = None):
        self.params = params or SlicParams()

    def parameters(self) -> dict:
        return asdict(self.params)

    def generate(self, image: np.ndarray) -> list[MaskSet]:
        """image: [H, W, 3] uint8 RGB -> four MaskSets (LEVELS order) of disjoint regions."""
        from skimage.segmentation import slic

        p = self.params
        work = _work_image(image, p.work_size)
        maps = [slic(work, n_segments=n, compactness=p.compactness, start_label=0, channel_axis=-1) for n in p.n_segments]
        return _levels_from_label_maps(maps, image.shape[0], image.shape[1], p.min_area_fraction)


# ---------------------------------------------------------------------------------------------
# SAM


@dataclass
class SamParams:
    """SamAutomaticMaskGenerator parameters as LangSplat's preprocess.py sets them."""

    points_per_side: int = 32
    points_per_batch: int = 64
    pred_iou_thresh: float = 0.7
    stability_score_thresh: float = 0.85
    stability_score_offset: float = 1.0
    box_nms_thresh: float = 0.7
    crop_n_layers: int = 1
    crop_nms_thresh: float = 0.7
    crop_overlap_ratio: float = 512 / 1500
    crop_n_points_downscale_factor: int = 1
    min_mask_region_area: int = 100


@dataclass
class SamArchitecture:
    """The shape of a SAM model, as read from its checkpoint (vit_b / vit_l / vit_h or smaller)."""

    encoder_embed_dim: int
    encoder_depth: int
    encoder_num_heads: int
    encoder_mlp_ratio: float = 4.0
    image_size: int = 1024
    patch_size: int = 16
    prompt_embed_dim: int = 256
    mask_in_chans: int = 16
    decoder_depth: int = 2
    decoder_mlp_dim: int = 2048
    decoder_num_heads: int = 8
    iou_head_depth: int = 3
    iou_head_hidden_dim: int = 256
    window_size: int = 14
    global_attn_indexes: list[int] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.global_attn_indexes:
            d = self.encoder_depth
            self.global_attn_indexes = sorted({(q + 1) * d // 4 - 1 for q in range(4)} - {-1})


SAM_ARCHITECTURES = {
    "vit_b": SamArchitecture(768, 12, 12),
    "vit_l": SamArchitecture(1024, 24, 16),
    "vit_h": SamArchitecture(1280, 32, 16),
}


def sam_architecture_from_state_dict(state: dict) -> SamArchitecture:
    """Read a SAM architecture off its weights' shapes (official checkpoints and smaller ones)."""

    def shape(key: str) -> tuple[int, ...]:
        if key not in state:
            raise KeyError(key)
        return tuple(state[key].shape)

    embed = shape("image_encoder.patch_embed.proj.weight")
    depth = len({k.split(".")[2] for k in state if k.startswith("image_encoder.blocks.")})
    head_dim = shape("image_encoder.blocks.0.attn.rel_pos_h")[1]
    return SamArchitecture(
        encoder_embed_dim=embed[0],
        encoder_depth=depth,
        encoder_num_heads=embed[0] // head_dim,
        encoder_mlp_ratio=shape("image_encoder.blocks.0.mlp.lin1.weight")[0] / embed[0],
        image_size=shape("image_encoder.pos_embed")[1] * embed[2],
        patch_size=embed[2],
        prompt_embed_dim=shape("prompt_encoder.no_mask_embed.weight")[1],
        mask_in_chans=shape("prompt_encoder.mask_downscaling.3.weight")[0],
        decoder_depth=len({k.split(".")[3] for k in state if k.startswith("mask_decoder.transformer.layers.")}),
        decoder_mlp_dim=shape("mask_decoder.transformer.layers.0.mlp.lin1.weight")[0],
        iou_head_depth=len({k.split(".")[3] for k in state if k.startswith("mask_decoder.iou_prediction_head.layers.")}),
        iou_head_hidden_dim=shape("mask_decoder.iou_prediction_head.layers.0.weight")[0],
        window_size=_window_size(state, shape),
        global_attn_indexes=sorted(_global_blocks(state, shape)),
    )


def _window_size(state: dict, shape) -> int:
    """Windowed blocks have a relative position table of 2·window - 1 entries (14 if none)."""
    windowed = [b for b in range(len({k.split(".")[2] for k in state if k.startswith("image_encoder.blocks.")})) if b not in _global_blocks(state, shape)]
    return (shape(f"image_encoder.blocks.{windowed[0]}.attn.rel_pos_h")[0] + 1) // 2 if windowed else 14


def _global_blocks(state: dict, shape) -> set[int]:
    """Encoder blocks with global attention: their relative position table spans the whole grid."""
    grid = shape("image_encoder.pos_embed")[1]
    blocks = {int(k.split(".")[2]) for k in state if k.startswith("image_encoder.blocks.") and k.endswith("attn.rel_pos_h")}
    return {b for b in blocks if shape(f"image_encoder.blocks.{b}.attn.rel_pos_h")[0] == 2 * grid - 1}


def build_sam(arch: SamArchitecture):
    """A SAM model (segment_anything.modeling) of the given architecture, random weights."""
    from functools import partial

    import torch
    from segment_anything.modeling import ImageEncoderViT, MaskDecoder, PromptEncoder, Sam, TwoWayTransformer

    grid = arch.image_size // arch.patch_size
    sam = Sam(
        image_encoder=ImageEncoderViT(
            depth=arch.encoder_depth,
            embed_dim=arch.encoder_embed_dim,
            img_size=arch.image_size,
            mlp_ratio=arch.encoder_mlp_ratio,
            norm_layer=partial(torch.nn.LayerNorm, eps=1e-6),
            num_heads=arch.encoder_num_heads,
            patch_size=arch.patch_size,
            qkv_bias=True,
            use_rel_pos=True,
            global_attn_indexes=tuple(arch.global_attn_indexes),
            window_size=arch.window_size,
            out_chans=arch.prompt_embed_dim,
        ),
        prompt_encoder=PromptEncoder(
            embed_dim=arch.prompt_embed_dim,
            image_embedding_size=(grid, grid),
            input_image_size=(arch.image_size, arch.image_size),
            mask_in_chans=arch.mask_in_chans,
        ),
        mask_decoder=MaskDecoder(
            num_multimask_outputs=3,
            transformer=TwoWayTransformer(
                depth=arch.decoder_depth, embedding_dim=arch.prompt_embed_dim, mlp_dim=arch.decoder_mlp_dim, num_heads=arch.decoder_num_heads
            ),
            transformer_dim=arch.prompt_embed_dim,
            iou_head_depth=arch.iou_head_depth,
            iou_head_hidden_dim=arch.iou_head_hidden_dim,
        ),
        pixel_mean=[123.675, 116.28, 103.53],
        pixel_std=[58.395, 57.12, 57.375],
    )
    return sam.eval()


def drsplat_cache_dir() -> Path:
    """Where downloaded weights are kept: $DRSPLAT_CACHE, else $XDG_CACHE_HOME/drsplat (~/.cache/drsplat)."""
    if os.environ.get("DRSPLAT_CACHE"):
        return Path(os.environ["DRSPLAT_CACHE"])
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "drsplat"


def _sam_unavailable(model_type: str, cache: Path) -> WeightsUnavailableError:
    return WeightsUnavailableError(
        f"SAM weights ({model_type}) are not in the cache {cache} and cannot be downloaded; "
        "pass --sam-checkpoint PATH to a local SAM checkpoint, or run once with internet access."
    )


def resolve_sam_checkpoint(model_type: str = "vit_h", timeout: float = 30.0) -> Path:
    """The official SAM checkpoint for `model_type`, downloaded once into drsplat_cache_dir()."""
    from drsplat.features.clip import hf_offline

    if model_type not in SAM_URLS:
        raise DrsplatError(f"unknown SAM model '{model_type}': use one of {', '.join(SAM_URLS)}")
    url = SAM_URLS[model_type]
    cache = drsplat_cache_dir()
    path = cache / os.path.basename(url)
    if path.is_file():
        return path
    if hf_offline():
        raise _sam_unavailable(model_type, cache)
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


def load_sam(checkpoint: str | Path, device: str = "cpu"):
    """SAM model from a checkpoint file; the architecture (vit_b/l/h or smaller) is read off it."""
    import torch

    checkpoint = Path(checkpoint)
    if not checkpoint.is_file():
        raise InputError(checkpoint, "SAM checkpoint file does not exist (--sam-checkpoint)")
    try:
        state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    except Exception as exc:  # pickle / zip errors of many kinds
        first_line = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
        raise InputError(checkpoint, f"not a readable PyTorch checkpoint ({first_line})") from None
    if isinstance(state, dict) and "model" in state and isinstance(state["model"], dict):
        state = state["model"]
    try:
        arch = sam_architecture_from_state_dict(state)
        sam = build_sam(arch)
        sam.load_state_dict(state, strict=True)
    except (KeyError, RuntimeError, TypeError, IndexError, AttributeError, ValueError) as exc:
        first_line = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
        raise InputError(checkpoint, f"not a segment-anything SAM checkpoint ({first_line})") from None
    return sam.to(device)


def remove_small_regions(mask: np.ndarray, area_thresh: float, mode: str) -> tuple[np.ndarray, bool]:
    """Fill holes ("holes") or drop islands ("islands") smaller than area_thresh; 8-connectivity.

    SAM's amg.remove_small_regions without OpenCV. mask: [H, W] bool. Returns (mask, changed).
    """
    from scipy import ndimage

    fill_holes = mode == "holes"
    working = fill_holes ^ mask
    regions, n = ndimage.label(working, structure=np.ones((3, 3), bool))
    sizes = np.bincount(regions.ravel(), minlength=n + 1)[1:]
    small = np.flatnonzero(sizes < area_thresh) + 1
    if small.size == 0:
        return mask, False
    if fill_holes:
        return mask | np.isin(regions, small), True
    keep = np.setdiff1d(np.arange(1, n + 1), small)
    if keep.size == 0:
        keep = np.array([int(np.argmax(sizes)) + 1])
    return np.isin(regions, keep), True


class SamGenerator:
    """SAM automatic masks at LangSplat's four levels (default = all outputs, s / m / l = each
    multimask output alone), each level filtered and de-duplicated independently as in
    LangSplat's modified SamAutomaticMaskGenerator. Needs no OpenCV."""

    name = "sam"

    def __init__(self, sam, params: SamParams | None = None):
        from segment_anything import SamPredictor
        from segment_anything.utils.amg import build_all_layer_point_grids

        self.params = params or SamParams()
        self.predictor = SamPredictor(sam)
        p = self.params
        self.point_grids = build_all_layer_point_grids(p.points_per_side, p.crop_n_layers, p.crop_n_points_downscale_factor)

    def parameters(self) -> dict:
        return asdict(self.params)

    def generate(self, image: np.ndarray) -> list[MaskSet]:
        """image: [H, W, 3] uint8 RGB -> four MaskSets (LEVELS order), scores = IoU · stability."""
        import torch
        from segment_anything.utils.amg import generate_crop_boxes

        h, w = image.shape[:2]
        crop_boxes, layer_idxs = generate_crop_boxes((h, w), self.params.crop_n_layers, self.params.crop_overlap_ratio)
        per_crop = [self._process_crop(image, box, layer, (h, w)) for box, layer in zip(crop_boxes, layer_idxs)]
        levels = []
        with torch.inference_mode():
            for group in range(4):
                data = _cat([crop[group] for crop in per_crop])
                levels.append(self._finish_level(data, len(crop_boxes) > 1, (h, w)))
        return levels

    def _process_crop(self, image, crop_box, layer_idx, orig_size):
        import torch
        from segment_anything.utils.amg import batch_iterator, uncrop_boxes_xyxy, uncrop_points

        x0, y0, x1, y1 = crop_box
        crop = image[y0:y1, x0:x1, :]
        self.predictor.set_image(crop)
        points_for_image = self.point_grids[layer_idx] * np.array(crop.shape[:2])[None, ::-1]
        batches = [self._process_batch(points, crop.shape[:2], crop_box, orig_size) for (points,) in batch_iterator(self.params.points_per_batch, points_for_image)]
        self.predictor.reset_image()
        data = _cat(batches)
        groups = []
        for group in range(4):
            sub = _select(data, data["level"] == group - 1) if group else _select(data, torch.ones_like(data["level"], dtype=torch.bool))
            sub = _nms(sub, sub["iou_preds"], self.params.box_nms_thresh)
            sub["boxes"] = uncrop_boxes_xyxy(sub["boxes"], crop_box)
            sub["points"] = uncrop_points(sub["points"], crop_box)
            sub["crop_boxes"] = torch.tensor([crop_box for _ in range(len(sub["rles"]))], dtype=torch.float32).reshape(-1, 4)
            groups.append(sub)
        return groups

    def _process_batch(self, points, im_size, crop_box, orig_size):
        import torch
        from segment_anything.utils.amg import (
            MaskData,
            batched_mask_to_box,
            calculate_stability_score,
            is_box_near_crop_edge,
            mask_to_rle_pytorch,
            uncrop_masks,
        )

        p = self.params
        orig_h, orig_w = orig_size
        coords = torch.as_tensor(self.predictor.transform.apply_coords(points, im_size), device=self.predictor.device)
        labels = torch.ones(coords.shape[0], dtype=torch.int, device=coords.device)
        with torch.inference_mode():
            masks, iou_preds, _ = self.predictor.predict_torch(coords[:, None, :], labels[:, None], multimask_output=True, return_logits=True)
        n_out = masks.shape[1]
        data = MaskData(
            masks=masks.flatten(0, 1),
            iou_preds=iou_preds.flatten(0, 1),
            points=torch.as_tensor(points.repeat(n_out, axis=0)),
            level=torch.arange(n_out).repeat(masks.shape[0]),
        )
        if p.pred_iou_thresh > 0.0:
            data.filter(data["iou_preds"] > p.pred_iou_thresh)
        data["stability_score"] = calculate_stability_score(data["masks"], self.predictor.model.mask_threshold, p.stability_score_offset)
        if p.stability_score_thresh > 0.0:
            data.filter(data["stability_score"] >= p.stability_score_thresh)
        data["masks"] = data["masks"] > self.predictor.model.mask_threshold
        data["boxes"] = batched_mask_to_box(data["masks"])
        keep = ~is_box_near_crop_edge(data["boxes"], crop_box, [0, 0, orig_w, orig_h])
        if not torch.all(keep):
            data.filter(keep)
        data["masks"] = uncrop_masks(data["masks"], crop_box, orig_h, orig_w)
        data["rles"] = mask_to_rle_pytorch(data["masks"])
        del data["masks"]
        return data

    def _finish_level(self, data, several_crops: bool, size: tuple[int, int]) -> MaskSet:
        import torch
        from segment_anything.utils.amg import batched_mask_to_box, rle_to_mask
        from torchvision.ops.boxes import box_area

        if len(data["rles"]) == 0:
            return empty_maskset(*size)
        if several_crops:
            data = _nms(data, 1 / box_area(data["crop_boxes"]), self.params.crop_nms_thresh)
        masks = [rle_to_mask(rle) for rle in data["rles"]]
        scores = (data["iou_preds"] * data["stability_score"]).float().cpu().numpy()
        if self.params.min_mask_region_area > 0:
            unchanged = []
            for i, mask in enumerate(masks):
                mask, holes = remove_small_regions(mask, self.params.min_mask_region_area, "holes")
                mask, islands = remove_small_regions(mask, self.params.min_mask_region_area, "islands")
                masks[i] = mask
                unchanged.append(float(not (holes or islands)))
            stacked = torch.as_tensor(np.stack(masks))
            keep = _box_nms_indices(batched_mask_to_box(stacked), torch.tensor(unchanged), max(self.params.box_nms_thresh, self.params.crop_nms_thresh))
            masks = [masks[i] for i in keep]
            scores = scores[keep]
        return MaskSet(np.stack(masks).astype(bool), scores.astype(np.float32))


def _cat(parts):
    from segment_anything.utils.amg import MaskData

    out = MaskData()
    for part in parts:
        out.cat(part)
    return out


def _select(data, keep):
    from segment_anything.utils.amg import MaskData

    sub = MaskData(**dict(data.items()))
    sub.filter(keep)
    return sub


def _box_nms_indices(boxes, scores, thresh: float) -> np.ndarray:
    import torch
    from torchvision.ops.boxes import batched_nms

    boxes = boxes.float()
    scores = scores.float().to(boxes.device)
    keep = batched_nms(boxes, scores, torch.zeros(len(boxes), device=boxes.device), iou_threshold=thresh)
    return keep.cpu().numpy()


def _nms(data, scores, thresh: float):
    if len(data["rles"]) == 0:
        return data
    import torch

    keep = torch.as_tensor(_box_nms_indices(data["boxes"], scores, thresh))
    data.filter(keep)
    return data


def make_generator(name: str, sam_checkpoint: str | Path | None = None, sam_model: str = "vit_h", device: str = "cpu", sam_params: SamParams | None = None):
    """The mask generator called `name` (sam | felzenszwalb | slic), SAM weights resolved here."""
    if name == "felzenszwalb":
        return FelzenszwalbGenerator()
    if name == "slic":
        return SlicGenerator()
    if name != "sam":
        raise DrsplatError(f"unknown mask generator '{name}': use one of {', '.join(GENERATORS)}")
    checkpoint = Path(sam_checkpoint) if sam_checkpoint is not None else resolve_sam_checkpoint(sam_model)
    return SamGenerator(load_sam(checkpoint, device), sam_params)
