"""Where a vehicle's signal lamps are lit, pixel by pixel: a training target for sight.

A frame's labels say *whether* the brake or a blinker is lit; a lit map also says
*where*: one channel per signal (:data:`LIT_MAP_CHANNELS`), 255 on the visible pixels of
the vehicle's own lamps that show that signal lit in this very frame (a blink's dark half
is dark, as in ``lit_labels``), 0 elsewhere. Other vehicles' lamps inside the box stay 0:
they are exactly what the model must learn to ignore.

The renderer draws the lamp outlines it just lit (``SceneRenderer(lit_maps=True)``),
so the map costs a few polygon fills per vehicle and changes nothing in the image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Tuple

import cv2
import numpy as np

from signal_light_node.synth.lamps import TURN_ROLES, shows_brake
from signal_light_node.synth.vehicle_drawing import Drawn

#: Channels of a lit map, in order. Left and right are the vehicle's own sides.
LIT_MAP_CHANNELS: Tuple[str, ...] = ("brake", "left", "right")
#: A turn-lamp segment counts as lit from this flasher level on (as ``flash_lit``).
LIT_LEVEL = 0.5
_SHIFT = 3


@dataclass(frozen=True)
class LitMap:
    """One vehicle's lit map in frame pixels.

    Attributes:
        x0: Left edge of ``image`` in the frame.
        y0: Top edge of ``image`` in the frame.
        image: uint8 ``[h, w, len(LIT_MAP_CHANNELS)]``.
    """

    x0: int
    y0: int
    image: np.ndarray


def draw_lit_map(d: Drawn, levels: List[List[float]], brake: bool, left_lit: bool,
                 right_lit: bool) -> LitMap:
    """The lit map of a drawn vehicle (its ``vis`` set: occluded pixels stay 0).

    Args:
        d: The vehicle as drawn this frame.
        levels: Brightness of every lamp segment (``truth.lamp_states``).
        brake: The brake is on.
        left_lit: The left blinker is in the lit half of a blink.
        right_lit: The same for the right blinker.
    """
    rx0, ry0, rx1, ry1 = d.roi
    out = np.zeros((ry1 - ry0, rx1 - rx0, len(LIT_MAP_CHANNELS)), np.uint8)
    points = np.round(d.lamp_px * (1 << _SHIFT)).astype(np.int32)
    lit_side = {"L": left_lit, "R": right_lit}
    for lamp, polys, levs in zip(d.v.lamps, d.v.lamp_ranges_poly, levels):
        # A braking combined lamp that also blinks is on both channels. A sequential
        # indicator's segments light one by one: each counts from LIT_LEVEL on.
        targets = []
        if brake and shows_brake(lamp.role, lamp.side):
            targets.append((0, 0.0))
        if lamp.role in TURN_ROLES and lit_side.get(lamp.side, False):
            targets.append((1 if lamp.side == "L" else 2,
                            LIT_LEVEL if lamp.role == "turn" else 0.0))
        for channel, min_level in targets:
            plane = np.ascontiguousarray(out[..., channel])
            for (a, b), lev in zip(polys, levs):
                if lev >= min_level:
                    cv2.fillPoly(plane, [points[a:b]], 255, cv2.LINE_8, _SHIFT)
            out[..., channel] = plane
    if d.vis is not None:
        out[~d.vis] = 0
    return LitMap(rx0, ry0, out)
