"""Per-sequence augmentation of training items: mirroring, then crop transforms.

A rendered synthetic sequence is replayed several times (:class:`.streams.ReplayStream`)
and augmented anew each time, so a reused sequence is rarely seen twice in one form.
"""

from __future__ import annotations

from typing import Any, Dict

import numpy as np

from signal_light_node.data.camera_response import randomise_camera
from signal_light_node.data.shape_warp import warp_sequence
from signal_light_node.data.stream import jitter_colours, mirror_sequence


class Augment:
    """Mirroring, then the enabled per-sequence crop transforms: colour jitter (the stream's
    own), perspective warp (``data.shape_warp``), camera response (``data.camera_response``).

    Args:
        mirror_prob: Probability that a sequence is mirrored (crops flipped, left/right
            labels and LEFT/RIGHT views swapped).
        jitter: Colour/brightness jitter.
        camera: A random camera response.
        warp: A random perspective warp.
    """

    def __init__(self, mirror_prob: float, jitter: bool, camera: bool = False,
                 warp: bool = False) -> None:
        self.mirror_prob = mirror_prob
        self.transforms = [f for f, on in ((jitter_colours, jitter), (warp_sequence, warp),
                                           (randomise_camera, camera)) if on]

    def __call__(self, item: Dict[str, Any], rng: np.random.Generator) -> Dict[str, Any]:
        """``item`` augmented with draws from ``rng`` (padding frames stay zero)."""
        if self.mirror_prob > 0 and rng.random() < self.mirror_prob:
            item = mirror_sequence(item)
        for transform in self.transforms:
            crops = transform(item["crops"], rng)
            crops[~item["mask"]] = 0
            item = dict(item, crops=crops)
        return item
