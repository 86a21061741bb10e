"""Ground truth of the evaluation generator: what it returns per frame (``EvalFrame``
with one ``VehicleTruth`` per drawn vehicle) and the rules that decide it (the package
doc, "Ground truth", states them): the view is the vehicle's face toward the camera; a
light is ON or OFF only when enough unoccluded area of the lamps showing it faces the
camera, per the id buffer, else UNKNOWN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Tuple

import cv2
import numpy as np

from signal_light_node.boxes import TrackBox
from signal_light_node.evalgen.draw import Canvas, visible_fraction
from signal_light_node.evalgen.models import CLASS_OF_KIND
from signal_light_node.evalgen.traffic import Actor
from signal_light_node.evalgen.vehicle_drawing import Drawn
from signal_light_node.labels import Intent, LightStatus, View, intent_from_lights


@dataclass(frozen=True)
class VehicleTruth:
    """Ground truth of one vehicle in one frame.

    Attributes:
        track_id: Stable string ID.
        box: True projected box ``(x0, y0, x1, y1)`` (pixels, unclipped).
        tracker_box: The jittered tracker box, None when the tracker misses the vehicle.
        brake: Brake lamp state.
        left: The vehicle's own left blinker.
        right: Its right blinker.
        intent: ``intent_from_lights(left, right)``.
        view: Face the camera sees.
        occlusion: Hidden share of the vehicle's silhouette (0..1, off-image counts as hidden).
        kind: Vehicle kind.
        class_id: Detector class ("car", "truck").
        flash_left: Lit share of the left flasher in this exposure (0..1).
        flash_right: Lit share of the right flasher.
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
    class_id: str
    flash_left: float = 0.0
    flash_right: float = 0.0


@dataclass(frozen=True)
class EvalFrame:
    """One generated frame.

    Attributes:
        index: Frame number.
        stamp_ns: Time stamp.
        image: ``uint8 [H, W, 3]`` BGR.
        vehicles: Truth of every vehicle in view, tracked or not, far to near.
        lighting: "day" or "night".
    """

    index: int
    stamp_ns: int
    image: np.ndarray
    vehicles: List[VehicleTruth]
    lighting: str


def view_of(actor: Actor, k: int, ego_z: float) -> View:
    """Face of the vehicle toward the camera (at ``ego_z``) in frame ``k``, in 90-degree
    sectors."""
    yaw = float(actor.yaw[k])
    d = np.array([0.0 - actor.x[k], ego_z - actor.z[k]])  # (X, Z) to the camera
    fwd = np.array([math.sin(yaw), math.cos(yaw)])
    left = np.array([-math.cos(yaw), math.sin(yaw)])
    ang = math.degrees(math.atan2(float(d @ left), float(d @ fwd)))
    if abs(ang) <= 45.0:
        return View.FRONT
    if abs(ang) >= 135.0:
        return View.BEHIND
    return View.LEFT if ang > 0 else View.RIGHT


def light_truth(canvas: Canvas, actor: Actor, drawn: Drawn, view: View, t: float, obj_id: int
                ) -> Tuple[LightStatus, LightStatus, LightStatus]:
    """Brake, left and right of one vehicle (id ``obj_id``, face ``view`` toward the camera)
    at time ``t`` from what the id buffer shows: UNKNOWN when its lamps are hidden, too
    small, or on the far side."""
    x0, y0, x1, y1 = drawn.box
    threshold = max(x1 - x0, y1 - y0) ** 2 / 600.0
    seen = {"brake": 0.0, 1: 0.0, -1: 0.0}
    for lamp, uv, cos in drawn.lamps:
        if cos < 0.15:
            continue
        full = abs(float(cv2.contourArea(uv.astype(np.float32))))
        area = visible_fraction(canvas, uv, obj_id) * full
        if "brake" in lamp.funcs and lamp.face == "rear":
            seen["brake"] += area
        if "blink" in lamp.funcs and lamp.side:
            seen[lamp.side] += area
    sig = actor.signals

    def status(key: object, hidden: bool, on: bool) -> LightStatus:
        if hidden or seen[key] < threshold:
            return LightStatus.UNKNOWN
        return LightStatus.ON if on else LightStatus.OFF

    brake = status("brake", view == View.FRONT, sig.braking(t))
    left = status(1, view == View.RIGHT, sig.active(1, t) is not None)
    right = status(-1, view == View.LEFT, sig.active(-1, t) is not None)
    return brake, left, right


def occlusion_of(canvas: Canvas, obj_id: int, drawn: Drawn) -> float:
    """Hidden share of a drawn vehicle's silhouette (off-image counts as hidden)."""
    seen = float((canvas.ids == obj_id).sum())
    return float(np.clip(1.0 - seen / max(drawn.hull_area, 1.0), 0.0, 1.0))


def vehicle_truth(canvas: Canvas, actor: Actor, drawn: Drawn, k: int, ego_z: float, t: float,
                  exposure_s: float, obj_id: int, occlusion: float, tracker: Optional[TrackBox]
                  ) -> VehicleTruth:
    """The truth of one drawn vehicle (id ``obj_id``) in frame ``k`` at time ``t``."""
    view = view_of(actor, k, ego_z)
    brake, left, right = light_truth(canvas, actor, drawn, view, t, obj_id)
    return VehicleTruth(
        actor.track_id, drawn.box, tracker, brake, left, right,
        intent_from_lights(left, right), view, occlusion, actor.model.kind,
        CLASS_OF_KIND[actor.model.kind], actor.signals.flash_level(1, t, exposure_s),
        actor.signals.flash_level(-1, t, exposure_s))
