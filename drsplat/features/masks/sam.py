"""SAM automatic masks at LangSplat's four levels, on stock segment-anything (no OpenCV)."""

from __future__ import annotations

import logging
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from drsplat.errors import InputError
from drsplat.features.clip import checkpoint_problem
from drsplat.features.masks.base import MaskSet, empty_maskset

log = logging.getLogger(__name__)




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
    from segment_anything.modeling import (
        ImageEncoderViT,
        MaskDecoder,
        PromptEncoder,
        Sam,
        TwoWayTransformer,
    )

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


def sam_checkpoint_file_problem(checkpoint: Path) -> str | None:
    """Why `checkpoint` (--sam-checkpoint) is no checkpoint file, or None: a folder, FIFO or device exists but is none."""
    if checkpoint.is_file():
        return None
    return ("is not a file (--sam-checkpoint): expected a SAM checkpoint file" if checkpoint.exists()
            else "SAM checkpoint file does not exist (--sam-checkpoint)")


def load_sam(checkpoint: str | Path, device: str = "cpu"):
    """SAM model from a checkpoint file; the architecture (vit_b/l/h or smaller) is read off it."""
    import torch

    checkpoint = Path(checkpoint)
    problem = sam_checkpoint_file_problem(checkpoint)
    if problem is not None:
        raise InputError(checkpoint, problem)
    try:
        with warnings.catch_warnings():  # torch's UserWarning on a pickle protocol its safe unpickler may not read
            warnings.simplefilter("ignore")
            state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    except Exception as exc:  # pickle / zip errors of many kinds: torch's text runs to paragraphs on weights_only
        raise InputError(checkpoint, f"not a readable PyTorch checkpoint: {checkpoint_problem(checkpoint, exc)}") from None
    if isinstance(state, dict) and "model" in state and isinstance(state["model"], dict):
        state = state["model"]
    try:
        arch = sam_architecture_from_state_dict(state)
        sam = build_sam(arch)
        sam.load_state_dict(state, strict=True)
    except (KeyError, RuntimeError, TypeError, IndexError, AttributeError, ValueError) as exc:
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()] or [type(exc).__name__]
        # torch's first line only says "Error(s) in loading state_dict for Sam:"; the tensor at fault is on the next (round 87c F3)
        shown = lines[1] if len(lines) > 1 and lines[0].startswith("Error(s) in loading state_dict") else lines[0]
        raise InputError(checkpoint, f"not a segment-anything SAM checkpoint ({shown[:200]})") from None
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

    def __init__(self, sam, params: SamParams | None = None, checkpoint: Path | None = None):
        from segment_anything import SamPredictor
        from segment_anything.utils.amg import build_all_layer_point_grids

        self.checkpoint = checkpoint  # the weights file (given or downloaded): the manifest records its digest
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
        from segment_anything.utils.transforms import ResizeLongestSide

        h, w = image.shape[:2]
        crop_boxes, layer_idxs = generate_crop_boxes((h, w), self.params.crop_n_layers, self.params.crop_overlap_ratio)
        # a crop SAM would resize to no pixels (an image 1 px high cut in two by the crop layer, or one past
        # 2048:1) cannot be segmented: torchvision's resize raised "height and width must be > 0"
        target = self.predictor.transform.target_length
        usable = [(box, layer) for box, layer in zip(crop_boxes, layer_idxs)
                  if min(box[3] - box[1], box[2] - box[0]) > 0
                  and min(ResizeLongestSide.get_preprocess_shape(box[3] - box[1], box[2] - box[0], target)) > 0]
        if not usable:
            return [empty_maskset(h, w) for _ in range(4)]
        crop_boxes, layer_idxs = [box for box, _ in usable], [layer for _, layer in usable]
        per_crop = [self._process_crop(image, box, layer, (h, w)) for box, layer in zip(crop_boxes, layer_idxs)]
        levels = []
        with torch.inference_mode():
            for group in range(4):
                data = _cat([crop[group] for crop in per_crop])
                levels.append(self._finish_level(data, len(crop_boxes) > 1, (h, w)))
        return levels

    def _process_crop(self, image, crop_box, layer_idx, orig_size):
        import torch
        from segment_anything.utils.amg import (
            batch_iterator,
            uncrop_boxes_xyxy,
            uncrop_points,
        )

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
        scores = mask_scores(data["iou_preds"], data["stability_score"])
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
        return MaskSet(np.stack(masks).astype(bool), scores)  # float64 to the score threshold (round 75a F2)


def mask_scores(iou_preds, stability):
    """A mask's score, predicted IoU x stability score: [K] float64 from two [K] float32 tensors, multiplied in float64
    as LangSplat's preprocess.py multiplies the Python floats SAM's generator hands it (round 74b F8: a float32 product
    put 0.75578094 x 0.9261943 = 0.70000000 just under LangSplat's 0.7 score threshold, a mask LangSplat keeps)."""
    return (iou_preds.double() * stability.double()).cpu().numpy()


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


