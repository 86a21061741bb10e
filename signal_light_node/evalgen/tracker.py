"""The simulated tracker of the evaluation generator: the projected 3D box plus AR(1)
correlated jitter (3 % in position, 4.5 % in size); a track is dropped when more than 70 %
occluded, too small or mostly off the image, and 1.5 % of boxes drop at random.
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

from signal_light_node.boxes import TrackBox
from signal_light_node.evalgen.models import CLASS_OF_KIND
from signal_light_node.evalgen.traffic import Actor


def tracker_box(actor: Actor, box: Tuple[float, float, float, float], occlusion: float,
                width: int, height: int) -> Optional[TrackBox]:
    """The jittered box the tracker reports for ``actor`` (true projected box ``box``, hidden
    share ``occlusion``, in an image ``width`` x ``height``), or None when it misses it.
    Draws from the actor's own jitter stream in every frame it is drawn."""
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    rho = 0.75
    fresh = actor.jitter_rng.standard_normal(4)
    actor.jitter = rho * actor.jitter + math.sqrt(1 - rho ** 2) * fresh
    drop = actor.jitter_rng.random() < 0.015
    cw, ch = width, height
    on_image = (min(x1, cw) - max(x0, 0)) * (min(y1, ch) - max(y0, 0)) / max(w * h, 1e-6)
    if drop or occlusion > 0.7 or w < 12 or h < 10 or on_image < 0.45:
        return None
    e = actor.jitter
    cx, cy = (x0 + x1) / 2 + e[0] * 0.03 * w, (y0 + y1) / 2 + e[1] * 0.03 * h
    bw, bh = w * math.exp(0.045 * e[2]), h * math.exp(0.045 * e[3])
    return TrackBox.from_center(actor.track_id, cx, cy, bw, bh, CLASS_OF_KIND[actor.model.kind])
