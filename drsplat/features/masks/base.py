"""The mask record shared by every generator: `MaskSet`, the level names, and the `MaskGenerator` protocol."""


from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

LEVELS = ("default", "s", "m", "l")  # LangSplat's levels, in file order (see the package docstring)


@dataclass
class MaskSet:
    """Masks of one level. masks: [K, H, W] bool; scores: [K] float (higher is better; SAM's are float64, `sam.mask_scores`)."""

    masks: np.ndarray
    scores: np.ndarray

    def __len__(self) -> int:
        return int(self.masks.shape[0])

    def subset(self, keep: np.ndarray) -> "MaskSet":
        return MaskSet(self.masks[keep], self.scores[keep])


def empty_maskset(height: int, width: int) -> MaskSet:
    return MaskSet(np.zeros((0, height, width), bool), np.zeros(0, np.float32))


class MaskGenerator(Protocol):
    """What `drsplat features` needs of a mask generator.

    name: recorded in manifest.json (a folder never mixes generators).
    parameters(): the settings that made the masks, recorded in manifest.json.
    generate(image [H, W, 3] uint8 RGB) -> four MaskSets in LEVELS order, each [K, H, W].
    """

    name: str

    def parameters(self) -> dict: ...

    def generate(self, image: np.ndarray) -> list[MaskSet]: ...
