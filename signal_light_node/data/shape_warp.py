"""Random perspective warps of training crops (domain randomisation of vehicle shape).

The renderer draws a handful of flat-shaded body shapes, seen straight on; real vehicles
and other renderers show other proportions and a little of their sides. :func:`warp_sequence`
draws one mild perspective warp per sequence (each corner of the crop moved by up to
``strength`` of its side, so aspect, shear, keystone and rotation all vary) and applies it
to every frame alike, so the track's history stays aligned and its left and right stay
where they were: the labels do not change.
"""

from __future__ import annotations

import cv2
import numpy as np


def random_warp(size: int, rng: np.random.Generator, strength: float = 0.08) -> np.ndarray:
    """A 3x3 perspective matrix moving each crop corner by up to ``strength * size``."""
    corners = np.float32([[0, 0], [size - 1, 0], [size - 1, size - 1], [0, size - 1]])
    moved = corners + rng.uniform(-strength, strength, (4, 2)).astype(np.float32) * size
    return cv2.getPerspectiveTransform(corners, moved.astype(np.float32))


def warp_sequence(crops: np.ndarray, rng: np.random.Generator,
                  strength: float = 0.08) -> np.ndarray:
    """One random warp applied to every frame of uint8 ``[T, S, S, 3]`` crops (new array)."""
    if crops.size == 0:
        return crops.copy()
    size = crops.shape[1]
    matrix = random_warp(size, rng, strength)
    return np.stack([cv2.warpPerspective(frame, matrix, (size, size), flags=cv2.INTER_LINEAR,
                                         borderMode=cv2.BORDER_REPLICATE) for frame in crops])
