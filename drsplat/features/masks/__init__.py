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

from collections.abc import Callable
from pathlib import Path

from drsplat.errors import DrsplatError
from drsplat.features.masks.base import LEVELS, MaskGenerator, MaskSet, empty_maskset
from drsplat.features.masks.superpixel import FelzenszwalbGenerator, SlicGenerator
from drsplat.features.weights import resolve_sam_checkpoint
from drsplat.features.masks.sam import load_sam, SamGenerator


def _sam(options: dict) -> MaskGenerator:
    checkpoint = options.get("sam_checkpoint")
    checkpoint = Path(checkpoint) if checkpoint is not None else resolve_sam_checkpoint(options.get("sam_model", "vit_h"))
    return SamGenerator(load_sam(checkpoint, options.get("device", "cpu")), options.get("sam_params"), checkpoint)


def _felzenszwalb(options: dict) -> MaskGenerator:
    return FelzenszwalbGenerator()


def _slic(options: dict) -> MaskGenerator:
    return SlicGenerator()


# name -> factory(options) (options: sam_checkpoint, sam_model, device, sam_params). A new generator is one
# module with a class that follows MaskGenerator, plus one line here.
GENERATORS: dict[str, Callable[[dict], MaskGenerator]] = {
    "sam": _sam,
    "felzenszwalb": _felzenszwalb,
    "slic": _slic,
}


def make_generator(name: str, sam_checkpoint: str | Path | None = None, sam_model: str = "vit_h", device: str = "cpu", sam_params=None) -> MaskGenerator:
    """The mask generator called `name` (a key of GENERATORS); SAM weights are resolved here."""
    if name not in GENERATORS:
        raise DrsplatError(f"unknown mask generator '{name}': use one of {', '.join(GENERATORS)}")
    return GENERATORS[name]({"sam_checkpoint": sam_checkpoint, "sam_model": sam_model, "device": device, "sam_params": sam_params})


__all__ = ["GENERATORS", "LEVELS", "MaskGenerator", "MaskSet", "empty_maskset", "make_generator"]
