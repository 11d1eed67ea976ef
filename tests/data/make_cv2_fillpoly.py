"""Writes tests/data/cv2_fillpoly.npz: 360 polygons and the masks cv2.fillPoly paints for them
(run with opencv-python installed: ``python tests/data/make_cv2_fillpoly.py``; it was made with
OpenCV 5.0.0). tests/test_polyfill.py checks drsplat.eval.polyfill against them without OpenCV."""

import cv2
import numpy as np


def polygon(rng: np.random.Generator, kind: int, h: int, w: int, p: int) -> np.ndarray:
    if kind == 0:  # anywhere near the image
        return rng.integers(-10, max(h, w) + 10, (p, 2))
    if kind == 1:  # inside
        return np.stack([rng.integers(0, w, p), rng.integers(0, h, p)], 1)
    if kind == 2:  # mostly outside
        return rng.integers(-300, 300, (p, 2))
    if kind == 3:  # a coarse grid: level and upright edges, repeated vertices
        return rng.integers(-2, 6, (p, 2)) * max(1, max(h, w) // 4)
    if kind == 4:  # thin slivers
        return np.stack([rng.integers(-20, w + 20, p), np.where(np.arange(p) % 2, 3, 4) + rng.integers(0, 2, p)], 1)
    centre = rng.uniform(-20, 220, 2)  # stars across the border
    angle = np.sort(rng.uniform(0, 2 * np.pi, p + 3))
    radius = rng.uniform(3, 120, p + 3)
    return np.trunc(np.stack([centre[0] + radius * np.cos(angle), centre[1] + radius * np.sin(angle)], 1))


def main() -> None:
    rng = np.random.default_rng(2026)
    polys, shapes, masks = [], [], []
    for trial in range(360):
        kind = trial % 6
        h, w = (int(v) for v in rng.integers(1, 64, 2)) if kind != 5 else (150, 200)
        v = np.asarray(polygon(rng, kind, h, w, int(rng.integers(1, 14))), np.int64)
        m = np.zeros((h, w), np.uint8)
        cv2.fillPoly(m, [v.astype(np.int32)], 1)
        polys.append(v)
        shapes.append((h, w))
        masks.append(np.packbits(m.astype(bool).ravel()))
    np.savez_compressed("tests/data/cv2_fillpoly.npz", vertices=np.concatenate(polys), counts=np.array([len(p) for p in polys]),
                        shapes=np.array(shapes), mask_bits=np.concatenate(masks), mask_bytes=np.array([len(m) for m in masks]),
                        opencv=np.array(cv2.__version__))


if __name__ == "__main__":
    main()
