"""The simulated tracker of the training renderer: the box a tracker reports for a listed
vehicle, jittered by the vehicle's own tracker bias and noise, sometimes too large, cut
off on one side or missing; an amodal tracker keeps the full extent behind an occluder.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from signal_light_node.boxes import TrackBox
from signal_light_node.synth.traffic import Box, Vehicle
from signal_light_node.synth.vehicles import CLASS_IDS


def tracker_box(v: Vehicle, box: Box, full_box: Box, width: int, height: int,
                frng: np.random.Generator) -> Optional[TrackBox]:
    """What a tracker would report: jittered, sometimes too large, cut off or missing.

    Args:
        v: The vehicle (its track ID, kind and tracker bias, noise and amodal flag).
        box: Tight box of its visible pixels (x0, y0, x1, y1).
        full_box: Its full (unclipped) extent in the image.
        width: Image width.
        height: Image height.
        frng: The frame's random stream (five draws per call, missing or not).
    """
    r = frng.random()
    jit = frng.normal(0, 1, 4)
    mode = frng.random()
    side = int(frng.integers(0, 4))
    amount = frng.uniform(0.08, 0.3)
    if r < 0.03:
        return None
    x0, y0, x1, y1 = box
    if v.tracker_amodal:
        # Amodal box: the tracker keeps the full extent behind an occluder (clipped to the image).
        fx0, fy0, fx1, fy1 = full_box
        x0, y0 = max(0.0, fx0), max(0.0, fy0)
        x1, y1 = min(float(width), fx1), min(float(height), fy1)
    w, h = x1 - x0, y1 - y0
    b = v.tracker_bias
    s = v.tracker_sigma
    x0 += (b[0] + s * jit[0]) * w
    x1 += (b[1] + s * jit[1]) * w
    y0 += (b[2] + s * jit[2]) * h
    y1 += (b[3] + s * jit[3]) * h
    if mode < 0.08:  # too large
        x0, x1 = x0 - amount * w * 0.5, x1 + amount * w * 0.5
        y0, y1 = y0 - amount * h * 0.5, y1 + amount * h * 0.5
    elif mode < 0.14:  # cut off on one side
        if side == 0:
            x0 += amount * w
        elif side == 1:
            x1 -= amount * w
        elif side == 2:
            y0 += amount * h
        else:
            y1 -= amount * h
    return TrackBox(v.track_id, float(x0), float(y0), float(x1), float(y1), CLASS_IDS[v.kind])
