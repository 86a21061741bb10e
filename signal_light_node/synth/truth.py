"""Ground truth of the training renderer: what it returns per frame (the image and each
listed vehicle's ``VehicleTruth``) and the rules that decide it.

The rules: which lamps are lit at a time (``lamp_states``: blinker and brake timelines,
flasher phase, tail and head lamps); which pixels of a vehicle are visible (``mark_visible``:
occluders and nearer vehicles hide them); which lamps are seen (``lamp_visibility``: at
least ``LAMP_VISIBLE_FRACTION`` of a lamp visible); whether the vehicle is listed
(``listed_box``); and each light's label (``vehicle_truth``: ON or OFF when the lamps
showing it are seen and large enough to be judged by one of ``TRUTH_RULES``, else UNKNOWN).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, NamedTuple, Optional, Tuple

import cv2
import numpy as np

from signal_light_node.boxes import TrackBox
from signal_light_node.errors import ConfigError
from signal_light_node.labels import Intent, LightStatus, View, intent_from_lights
from signal_light_node.synth.lit_maps import LitMap
from signal_light_node.synth.lamps import TURN_ROLES, flasher_level, shows_brake
from signal_light_node.synth.traffic import Box, Vehicle
from signal_light_node.synth.vehicle_drawing import Drawn
from signal_light_node.synth.vehicles import CLASS_IDS

#: A lamp counts as visible when at least this fraction of it can be seen.
LAMP_VISIBLE_FRACTION = 0.5
#: ... and when its visible part is large enough to be judged where the node looks: the
#: node scales a square of 1.3 x the box's longer side to a 64-pixel crop, so a lamp
#: covering less than 1/600 of (longer side)^2 spans under 4 crop pixels (a side view's
#: wrap-around tail lamp or side repeater). Such a lamp's state is UNKNOWN, as an
#: annotator would mark it, rather than an ON/OFF no image can show.
LAMP_MIN_BOX_SHARE = 1.0 / 600.0
#: Nor can a lamp be judged from fewer image pixels than this, however small the box.
LAMP_MIN_PIXELS = 2.0
#: The rules a truth can be labelled by (``vehicle_truth``'s ``rule``): ``lamp`` (each lamp
#: on its own must reach ``LAMP_MIN_BOX_SHARE``) and ``function`` (the seen lamps of one
#: function, a side's blinker or the brake, together reach ``FUNCTION_MIN_BOX_SHARE``,
#: about 2 crop pixels). Under ``lamp`` a car's rear turn lamp of 3 crop pixels in plain
#: sight is UNKNOWN, and so are three-quarter and side views whose lamps are each slivers;
#: an annotator marks what the lamps of one function show together.
TRUTH_RULES = ("lamp", "function")
FUNCTION_MIN_BOX_SHARE = 1.0 / 1200.0
#: Vehicles smaller than this (visible box, pixels) or more hidden than this are not listed.
MIN_LISTED_PX = 8.0
MAX_LISTED_OCCLUSION = 0.9


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
        lit_map: Where its signal lamps are lit (``synth.lit_maps``), only from a
            renderer asked for lit maps, else None.
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
    lit_map: Optional[LitMap] = None


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


def light_status(on: bool, visible: bool) -> LightStatus:
    """ON or OFF for a light that can be judged, UNKNOWN for one that cannot."""
    if not visible:
        return LightStatus.UNKNOWN
    return LightStatus.ON if on else LightStatus.OFF


class LampStates(NamedTuple):
    """What a vehicle's lamps do at one time."""

    levels: List[List[float]]  # brightness of every lamp segment (0..1; up to Vehicle.glare)
    brake: bool
    left_on: bool  # left blinker active (lit or in its dark half)
    right_on: bool
    flash_lit: bool  # the flasher is in the lit half of a blink


def lamp_states(v: Vehicle, t: float, exp_s: float, night: bool) -> LampStates:
    """Brightness of every lamp segment of ``v`` at time ``t`` (exposure ``exp_s``; ``night``:
    not daylight) plus its brake, left and right blinkers and flasher phase."""
    st = v.style
    state, start = v.blinker.segment(t)
    brake = bool(v.brake.segment(t)[0])
    left_on = state in (Intent.LEFT, Intent.HAZARD)
    right_on = state in (Intent.RIGHT, Intent.HAZARD)
    # A flasher starts lit when switched on; a signal held for the whole sequence
    # (override) runs with the vehicle's phase instead.
    t_act = t + v.phase if start < -1e8 else t - start
    flash_lit = flasher_level(t_act, st, exp_s) >= 0.5
    tail = st.tail_level if v.lights_on else 0.0
    full = v.glare  # a fully lit brake or flash; over 1 only for glaring vehicles
    levels: List[List[float]] = []
    for lamp, polys in zip(v.lamps, v.lamp_polys):
        active = (lamp.side == "L" and left_on) or (lamp.side == "R" and right_on)
        role = lamp.role
        if role == "tail":
            lev = (full if brake and lamp.side != "C" else tail)
            levels.append([lev])
        elif role == "chmsl":
            levels.append([full if brake else 0.0])
        elif role == "turn":
            if not active:
                levels.append([0.0] * len(polys))
            elif len(polys) > 1:
                step = st.duty / st.blink_hz * st.seq_fraction / len(polys)
                levels.append([full * flasher_level(t_act, st, exp_s, delay=k * step)
                               for k in range(len(polys))])
            else:
                levels.append([full * flasher_level(t_act, st, exp_s)])
        elif role == "turn_tail":
            base = full if brake else tail
            if active:
                low = st.combined_dim if brake else tail
                levels.append([low + (full - low) * flasher_level(t_act, st, exp_s)])
            else:
                levels.append([base])
        elif role == "head":
            levels.append([1.0 if (v.lights_on and (night or v.view == View.FRONT)) else 0.0])
        elif role in ("drl", "position"):
            on = v.lights_on or st.drl_day
            lev = 0.55 if on else 0.0
            if on and active and st.drl_dims_on_turn:
                lev *= 1.0 - 0.85 * flasher_level(t_act, st, exp_s)
            levels.append([lev])
        elif role == "marker":
            levels.append([0.6 if v.lights_on else 0.0])
        elif role == "reflector":
            levels.append([0.12 if night else 0.0])  # catches other vehicles' headlights
        else:
            levels.append([0.0])
    return LampStates(levels, brake, left_on, right_on, flash_lit)


def mark_visible(drawn: List[Drawn], coverage: np.ndarray) -> None:
    """Set ``vis`` of every drawn vehicle, ``drawn`` ordered near to far: the pixels of its
    silhouette that neither ``coverage`` (255 where an occluder stands, ``uint8 [H, W]``)
    nor a nearer vehicle hides. Marks each silhouette on ``coverage``."""
    for d in drawn:
        x0, y0, x1, y1 = d.roi
        cov = coverage[y0:y1, x0:x1]
        sil = d.alpha > 127
        d.vis = sil & (cov == 0)
        cov[sil] = 255


def lamp_visibility(d: Drawn) -> Tuple[List[float], List[Tuple[str, str, float]]]:
    """Visible fraction of every lamp of a drawn vehicle, and (role, side, visible lamp
    pixels) of the lamps seen well enough to be labelled by the fraction rule (the size
    rule needs the vehicle's visible box, known after drawing)."""
    v = d.v
    rx0, ry0, rx1, ry1 = d.roi
    fracs: List[float] = []
    seen: List[Tuple[str, str, float]] = []
    # Per-lamp pixel counts from integral images.
    P, lo, hi = d.lamp_px, d.lamp_lo, d.lamp_hi
    iv = cv2.integral(d.vis.view(np.uint8))
    ia = cv2.integral((d.alpha > 127).view(np.uint8))
    rw, rh = rx1 - rx0, ry1 - ry0
    for li, (lamp, polys) in enumerate(zip(v.lamps, v.lamp_ranges_poly)):
        lx0, ly0 = lo[li]
        lx1, ly1 = hi[li]
        fx0, fy0, fx1, fy1 = math.floor(lx0), math.floor(ly0), math.ceil(lx1), math.ceil(ly1)
        ix0, iy0, ix1, iy1 = max(0, fx0), max(0, fy0), min(rw, fx1), min(rh, fy1)
        frac = 0.0
        if ix1 > ix0 and iy1 > iy0:
            n_vis = float(iv[iy1, ix1] - iv[iy0, ix1] - iv[iy1, ix0] + iv[iy0, ix0])
            n_sil = float(ia[iy1, ix1] - ia[iy0, ix1] - ia[iy1, ix0] + ia[iy0, ix0])
            outside = max(0.0, (fx1 - fx0) * (fy1 - fy0) - (ix1 - ix0) * (iy1 - iy0))
            frac = n_vis / max(1.0, n_sil + outside * 0.8)
        if frac >= LAMP_VISIBLE_FRACTION:
            area = sum(cv2.contourArea(P[a:b].astype(np.float32)) for a, b in polys)
            seen.append((lamp.role, lamp.side, frac * area))
        fracs.append(frac)
    return fracs, seen


def listed_box(d: Drawn) -> Optional[Tuple[Box, float]]:
    """Tight box of a drawn vehicle's visible pixels and its occlusion, or None when it is
    too small or too hidden to be listed."""
    rx0, ry0 = d.roi[0], d.roi[1]
    ys, xs = np.nonzero(d.vis)
    if len(xs) == 0:
        return None
    bx0, by0 = float(xs.min() + rx0), float(ys.min() + ry0)
    bx1, by1 = float(xs.max() + rx0 + 1), float(ys.max() + ry0 + 1)
    occlusion = float(np.clip(1.0 - len(xs) / d.full_area, 0.0, 1.0))
    if bx1 - bx0 < MIN_LISTED_PX or by1 - by0 < MIN_LISTED_PX or occlusion > MAX_LISTED_OCCLUSION:
        return None
    return (bx0, by0, bx1, by1), occlusion


def checked_rule(rule: str) -> str:
    """``rule`` if it is one of ``TRUTH_RULES``; else ConfigError in one line."""
    if rule not in TRUTH_RULES:
        raise ConfigError(f"truth_rule must be one of {TRUTH_RULES}, got {rule!r}")
    return rule


def judged_lights(box: Box, seen: List[Tuple[str, str, float]], rule: str = "lamp") -> Dict[str, bool]:
    """Which lights (``L``, ``R``, ``brake``) a vehicle's seen lamps (``lamp_visibility``)
    show large enough in its ``box`` to be judged, by one of ``TRUTH_RULES``."""
    checked_rule(rule)
    bx0, by0, bx1, by1 = box
    share = LAMP_MIN_BOX_SHARE if rule == "lamp" else FUNCTION_MIN_BOX_SHARE
    min_px = max(LAMP_MIN_PIXELS, share * max(bx1 - bx0, by1 - by0) ** 2)
    pixels = {"L": 0.0, "R": 0.0, "brake": 0.0}
    for role, side, px in seen:
        keys = [side] if role in TURN_ROLES and side in ("L", "R") else []
        # The centre brake lamp shows the brake on its own; a centre tail bar does not
        # (it never brightens on braking).
        if shows_brake(role, side):
            keys.append("brake")
        for key in keys:
            pixels[key] = pixels[key] + px if rule == "function" else max(pixels[key], px)
    return {key: px >= min_px for key, px in pixels.items()}


def vehicle_truth(v: Vehicle, box: Box, occlusion: float, states: LampStates, seen: List[Tuple[str, str, float]],
                  tracker: Optional[TrackBox], rule: str = "lamp") -> VehicleTruth:
    """The truth of a listed vehicle: a light is ON or OFF when the lamps showing it are
    seen (``lamp_visibility``) and large enough in the ``box`` to be judged by ``rule``
    (``judged_lights``), else UNKNOWN."""
    visible = judged_lights(box, seen, rule)
    left = light_status(states.left_on, visible["L"])
    right = light_status(states.right_on, visible["R"])
    brake_s = light_status(states.brake, visible["brake"])
    # What a single frame shows: a blinker in its dark half looks like one switched off.
    left_lit = light_status(states.left_on and states.flash_lit, visible["L"])
    right_lit = light_status(states.right_on and states.flash_lit, visible["R"])
    return VehicleTruth(track_id=v.track_id, box=box, tracker_box=tracker, brake=brake_s, left=left,
                        right=right, intent=intent_from_lights(left, right), view=v.view, occlusion=occlusion, kind=v.kind,
                        lamp_design=v.style.design, class_id=CLASS_IDS[v.kind], left_lit=left_lit, right_lit=right_lit)
