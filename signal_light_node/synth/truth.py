"""What the renderer returns per frame: the image and each vehicle's ground truth."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional, Tuple

import numpy as np

from signal_light_node.boxes import TrackBox
from signal_light_node.labels import Intent, LightStatus, View


@dataclass(frozen=True)
class VehicleTruth:
    """Ground truth of one listed vehicle in one frame.

    Attributes:
        track_id: ID that stays the same for this vehicle within one renderer.
        box: Tight box of the vehicle's visible pixels (x0, y0, x1, y1), clipped to the image.
        tracker_box: What a simulated tracker reports (jittered, sometimes too large or cut
            off), or None when the tracker missed the vehicle in this frame.
        brake: Brake light state; UNKNOWN when no brake lamp is visible.
        left: The vehicle's own left blinker (ON also in the dark half of a blink).
        right: The vehicle's own right blinker.
        intent: ``labels.intent_from_lights(left, right)``.
        view: Face of the vehicle the camera sees.
        occlusion: Fraction of the vehicle hidden by other things or outside the image.
        kind: Body type ("car", "suv", "van", "truck", "bus").
        lamp_design: Rear lamp family ("amber", "red_combined", "led_strip", "sequential").
        class_id: What a detector would call it ("car", "truck", "bus").
        left_lit: The left blinker as this one frame shows it: ON only while its flasher
            is in the lit half of a blink (OFF in the dark half), UNKNOWN when not visible.
        right_lit: The same for the right blinker.
    """

    track_id: str
    box: Tuple[float, float, float, float]
    tracker_box: Optional[TrackBox]
    brake: LightStatus
    left: LightStatus
    right: LightStatus
    intent: Intent
    view: View
    occlusion: float
    kind: str
    lamp_design: str
    class_id: str
    left_lit: LightStatus = LightStatus.UNKNOWN
    right_lit: LightStatus = LightStatus.UNKNOWN


@dataclass(frozen=True)
class RenderedFrame:
    """One rendered camera frame.

    Attributes:
        index: Frame number within the sequence, from 0.
        stamp_ns: Capture time in nanoseconds.
        image: BGR image, ``uint8`` of shape (H, W, 3).
        vehicles: Ground truth of every vehicle that is visible enough to be listed.
        lighting: "day", "dusk" or "night".
    """

    index: int
    stamp_ns: int
    image: np.ndarray
    vehicles: List[VehicleTruth] = field(default_factory=list)
    lighting: str = "day"
