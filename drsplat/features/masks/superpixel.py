"""Weight-free mask generators: Felzenszwalb and SLIC superpixels at LangSplat's four granularities."""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import numpy as np

from drsplat.features.masks.base import MaskSet
from drsplat.features.format import resample_nearest

log = logging.getLogger(__name__)




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


