"""Lamp designs, their placement on each face of a vehicle, and blink/brake timing.

Coordinates are normalised to the vehicle's full box as drawn in the image: ``u`` runs
from the image-left edge (0) to the image-right edge (1), ``v`` from the top (0) to the
bottom (1). Every lamp knows which of the vehicle's own sides it belongs to, so the
label code never has to reason about mirroring again.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass, replace
from typing import List, Optional, Sequence, Tuple

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.labels import Intent, View

#: Style families: disjoint ranges of lamp colours (and, in ``synth.camera``, of camera
#: tone curves). Training renders draw from ``TRAIN_FAMILIES`` only; the rest are held
#: out, so a model can be scored on lamp colours and camera responses it never saw.
STYLE_FAMILIES: Tuple[int, ...] = (0, 1, 2)
TRAIN_FAMILIES: Tuple[int, ...] = (0, 1)
HELD_OUT_FAMILY = 2
#: Per family: amber green level (yellow-amber .. orange-red), red lamp blue and green.
_AMBER_G = {0: (150.0, 200.0), 1: (115.0, 150.0), 2: (80.0, 115.0)}
_RED_B = {0: (10.0, 35.0), 1: (35.0, 60.0), 2: (60.0, 100.0)}
_RED_G = {0: (0.0, 20.0), 1: (15.0, 35.0), 2: (35.0, 70.0)}

#: Rear lamp families; each also decides the matching front and side lamps.
LAMP_DESIGNS: Tuple[str, ...] = ("amber", "red_combined", "led_strip", "sequential")

#: Roles a lamp can play; ``turn_tail`` is the US-style red lamp that is tail, brake and blinker.
#: ``marker`` (steady side marker lamps) and ``reflector`` (retro-reflectors) look like
#: signal lamps but never signal: they are there so that a lit amber or red patch is not
#: automatically a blinker or a brake light.
ROLES = ("tail", "turn", "turn_tail", "chmsl", "head", "drl", "position", "marker", "reflector")
#: Roles of the lamps that show a blinker.
TURN_ROLES = ("turn", "turn_tail")


def shows_brake(role: str, side: str) -> bool:
    """Whether a lamp brightens on braking: the centre brake lamp and the side tail lamps
    (a centre tail bar never does)."""
    return role == "chmsl" or (role in ("tail", "turn_tail") and side != "C")

Colour = Tuple[float, float, float]


@dataclass
class Lamp:
    """One lamp (or one lamp segment group) on one face of a vehicle.

    Attributes:
        role: One of ``ROLES``.
        side: The vehicle's own side, "L", "R" or "C" (centre).
        rect: (u0, v0, u1, v1) in normalised box coordinates.
        shape: "rect", "round", "strip" or "ellipse".
        emit: Emission colour (BGR, 0..255) when fully lit.
        lens: Colour of the unlit lens (BGR) before scene lighting.
        segments: Number of segments (sequential indicators light them one by one).
        outward: +1 when the outer end of the lamp is at larger ``u``, else -1.
        glow: Relative size of the halo around the lit lamp.
    """

    role: str
    side: str
    rect: Tuple[float, float, float, float]
    shape: str
    emit: Colour
    lens: Colour
    segments: int = 1
    outward: int = 1
    glow: float = 1.0


@dataclass
class LampStyle:
    """Per-vehicle lamp parameters shared by every face (colours, timing, technology)."""

    design: str
    tech: str  # "led" or "bulb"
    amber: Colour
    red: Colour
    white: Colour
    amber_lens: Colour
    red_lens: Colour
    chmsl: bool
    blink_hz: float
    duty: float
    tau_rise: float
    tau_fall: float
    tail_level: float
    combined_dim: float
    drl_day: bool
    drl_dims_on_turn: bool
    seq_fraction: float
    seq_segments: int
    glow: float
    brightness: float


def sample_lamp_style(rng: np.random.Generator, kind: str, design: Optional[str] = None,
                      tech: Optional[str] = None, chmsl: Optional[bool] = None,
                      blink_hz: Optional[float] = None, duty: Optional[float] = None,
                      family: int = 0) -> LampStyle:
    """Draw a random lamp style; any argument given fixes that parameter.

    ``family`` (one of ``STYLE_FAMILIES``) picks the range of the lamp colours.
    """
    if design is None:
        design = str(rng.choice(LAMP_DESIGNS, p=[0.38, 0.22, 0.22, 0.18]))
    if tech is None:
        # Strips and sequential indicators only exist as LEDs.
        tech = "led" if design in ("led_strip", "sequential") else str(rng.choice(["led", "bulb"]))
    if chmsl is None:
        chmsl = bool(rng.random() < {"truck": 0.25, "bus": 0.6}.get(kind, 0.85))
    amber = (rng.uniform(0, 45), rng.uniform(*_AMBER_G[family]), 255.0)
    red = (rng.uniform(*_RED_B[family]), rng.uniform(*_RED_G[family]), rng.uniform(225, 255))
    white = (rng.uniform(225, 255), rng.uniform(235, 255), rng.uniform(235, 255))
    lens_kind = rng.random()
    if lens_kind < 0.35:  # clear / silver indicator lens
        g = rng.uniform(100, 180)
        amber_lens = (g, g * rng.uniform(0.97, 1.03), g * rng.uniform(0.98, 1.05))
    elif lens_kind < 0.7:  # amber lens
        amber_lens = (rng.uniform(15, 50), rng.uniform(65, 110), rng.uniform(115, 170))
    else:  # smoked
        g = rng.uniform(30, 70)
        amber_lens = (g, g, g * 1.1)
    red_lens = (rng.uniform(20, 55), rng.uniform(15, 45), rng.uniform(95, 160))
    return LampStyle(
        design=design, tech=tech, amber=amber, red=red, white=white,
        amber_lens=amber_lens, red_lens=red_lens, chmsl=chmsl,
        blink_hz=float(blink_hz if blink_hz is not None else rng.uniform(1.0, 2.2)),
        duty=float(duty if duty is not None else rng.uniform(0.3, 0.7)),
        tau_rise=float(rng.uniform(0.03, 0.08)), tau_fall=float(rng.uniform(0.05, 0.14)),
        tail_level=float(rng.uniform(0.18, 0.4)), combined_dim=float(rng.uniform(0.2, 0.55)),
        drl_day=bool(rng.random() < 0.6), drl_dims_on_turn=bool(rng.random() < 0.5),
        seq_fraction=float(rng.uniform(0.35, 0.7)), seq_segments=int(rng.integers(4, 8)),
        glow=float(rng.uniform(0.6, 1.5)), brightness=float(rng.uniform(0.75, 1.0)),
    )


# --------------------------------------------------------------------------- layouts

def _pair(rect_left: Tuple[float, float, float, float], mirror_sides: bool) -> List[Tuple[str, Tuple[float, float, float, float], int]]:
    """The image-left rect and its mirror, tagged with the vehicle side each one is on.

    From behind the vehicle's left is the image left; from the front it is the image right
    (``mirror_sides``). ``outward`` points to the box edge nearest to the lamp.
    """
    u0, v0, u1, v1 = rect_left
    img_left = (u0, v0, u1, v1)
    img_right = (1.0 - u1, v0, 1.0 - u0, v1)
    left_side, right_side = ("R", "L") if mirror_sides else ("L", "R")
    return [(left_side, img_left, -1), (right_side, img_right, 1)]


def _rear_band(kind: str, rng: np.random.Generator) -> Tuple[float, float]:
    """Vertical centre and height of the rear lamp band for a body kind."""
    if kind in ("truck", "bus"):
        return rng.uniform(0.78, 0.86), rng.uniform(0.04, 0.07)
    if kind == "van":
        return rng.uniform(0.45, 0.62), rng.uniform(0.1, 0.2)
    if kind == "suv":
        return rng.uniform(0.42, 0.55), rng.uniform(0.07, 0.12)
    return rng.uniform(0.38, 0.52), rng.uniform(0.07, 0.12)


def rear_lamps(style: LampStyle, kind: str, rng: np.random.Generator, chmsl_v: float) -> List[Lamp]:
    """Lamps on the rear face (view BEHIND).

    Bulb-era families come as a horizontal cluster, a tall lamp at each corner or two
    round lamps side by side; LED families as thin strips.
    """
    vc, h = _rear_band(kind, rng)
    inset = rng.uniform(0.02, 0.06)
    width = rng.uniform(0.13, 0.24) if kind not in ("truck", "bus") else rng.uniform(0.07, 0.13)
    lamps: List[Lamp] = []
    d = style.design
    layout = "horizontal"
    if d in ("amber", "red_combined"):
        layout = str(rng.choice(["horizontal", "vertical", "double"], p=[0.6, 0.2, 0.2]))
    if layout == "vertical":
        inset, width = rng.uniform(0.005, 0.03), rng.uniform(0.06, 0.1)
        h = rng.uniform(0.16, 0.3) if kind not in ("truck", "bus") else rng.uniform(0.08, 0.14)
        vc = min(vc, 0.9 - h / 2)
    shape = str(rng.choice(["rect", "round", "ellipse"])) if kind != "van" and layout == "horizontal" else "rect"
    # Drawn once so that both sides of the vehicle match.
    where = str(rng.choice(["below", "above", "inner"] if layout == "horizontal" else ["below", "above"]))
    split_below, split_above = rng.uniform(0.55, 0.7), rng.uniform(0.3, 0.45)
    cut_frac = rng.uniform(0.3, 0.45)
    strip_frac = rng.uniform(0.3, 0.45)
    amber_outer = bool(rng.random() < 0.5)
    red = lambda role, side, r, shp=shape: Lamp(role, side, r, shp, style.red, style.red_lens, glow=style.glow)  # noqa: E731
    amb = lambda side, r, shp="rect": Lamp("turn", side, r, shp, style.amber, style.amber_lens, glow=style.glow)  # noqa: E731
    for side, (u0, v0, u1, v1), out in _pair((inset, vc - h / 2, inset + width, vc + h / 2), False):
        if layout == "double":
            # Two round lamps: outer and inner (outward < 0: the outer one is at smaller u).
            mid = (u0 + u1) / 2
            gap = (u1 - u0) * 0.05
            outer, inner = ((u0, v0, mid - gap, v1), (mid + gap, v0, u1, v1)) if out < 0 else ((mid + gap, v0, u1, v1), (u0, v0, mid - gap, v1))
            if d == "red_combined":
                lamps += [red("turn_tail", side, outer, "ellipse"), red("tail", side, inner, "ellipse")]
            elif amber_outer:
                lamps += [amb(side, outer, "ellipse"), red("tail", side, inner, "ellipse")]
            else:
                lamps += [red("tail", side, outer, "ellipse"), amb(side, inner, "ellipse")]
        elif d == "red_combined":
            lamps.append(red("turn_tail", side, (u0, v0, u1, v1)))
        elif d == "amber":
            # Separate amber segment: below, above or on the inner end of the tail lamp.
            if where == "below":
                split = v0 + (v1 - v0) * split_below
                lamps += [red("tail", side, (u0, v0, u1, split)), amb(side, (u0, split, u1, v1))]
            elif where == "above":
                split = v0 + (v1 - v0) * split_above
                lamps += [amb(side, (u0, v0, u1, split)), red("tail", side, (u0, split, u1, v1))]
            else:
                cut = (u1 - u0) * cut_frac
                if out < 0:  # image-left lamp: inner end is at larger u
                    lamps += [red("tail", side, (u0, v0, u1 - cut, v1)), amb(side, (u1 - cut, v0, u1, v1))]
                else:
                    lamps += [amb(side, (u0, v0, u0 + cut, v1)), red("tail", side, (u0 + cut, v0, u1, v1))]
        else:  # LED strip / sequential: thin red strip above a thin amber strip
            sh = (v1 - v0) * strip_frac
            lamps.append(Lamp("tail", side, (u0, v0, u1, v0 + sh), "strip", style.red, style.red_lens, glow=style.glow))
            segs = style.seq_segments if d == "sequential" else 1
            lamps.append(Lamp("turn", side, (u0, v1 - sh, u1, v1), "strip", style.amber, style.amber_lens,
                              segments=segs, outward=out, glow=style.glow))
    if rng.random() < 0.6:
        # Red retro-reflectors low on the bumper corners.
        rv0 = rng.uniform(0.74, 0.84) if kind not in ("truck", "bus") else rng.uniform(0.87, 0.9)
        rw, rh = rng.uniform(0.04, 0.08), rng.uniform(0.02, 0.035)
        for side, r, _ in _pair((0.03, rv0, 0.03 + rw, rv0 + rh), False):
            lamps.append(Lamp("reflector", side, r, "rect", style.red, (35, 30, 120), glow=0.3))
    if d == "led_strip" and kind in ("car", "suv") and rng.random() < 0.5:
        # Full-width light bar joining the two tail lamps (tail only, never blinks).
        lamps.append(Lamp("tail", "C", (inset + width, vc - h / 2, 1 - inset - width, vc - h / 2 + h * 0.25),
                          "strip", style.red, style.red_lens, glow=style.glow * 0.5))
    if style.chmsl:
        cw = rng.uniform(0.12, 0.3) if kind not in ("truck", "bus") else rng.uniform(0.08, 0.15)
        lamps.append(Lamp("chmsl", "C", (0.5 - cw / 2, chmsl_v, 0.5 + cw / 2, chmsl_v + rng.uniform(0.018, 0.035)),
                          "strip", style.red, style.red_lens, glow=style.glow))
    return lamps


def _cluster_lamps(lamps: Sequence[Lamp]) -> List[Lamp]:
    """The lamps of a rear face's two per-side clusters (no reflector, no centre lamp)."""
    return [lamp for lamp in lamps if lamp.side in ("L", "R") and lamp.role in ("tail", "turn", "turn_tail")]


def _image_left(rect: Tuple[float, float, float, float]) -> bool:
    """Whether a lamp's rect lies on the image-left half of its face."""
    return rect[0] + rect[2] < 1.0


def widen_clusters(lamps: Sequence[Lamp], factor: float, limit: float = 0.42) -> None:
    """Widen a rear face's per-side clusters in place by ``factor``, about the box edge
    each one sits on (a truck's combination lamps are wider than ``rear_lamps`` draws
    them); adjacent segments stay adjacent and no cluster passes ``limit`` of the width.
    Reflectors and centre lamps stay as they were."""
    sides = _cluster_lamps(lamps)
    # How far from its own box edge the innermost end of any cluster reaches.
    reach = max([lamp.rect[2] if _image_left(lamp.rect) else 1.0 - lamp.rect[0] for lamp in sides] + [1e-6])
    f = max(1.0, min(factor, limit / reach))
    for lamp in sides:
        u0, v0, u1, v1 = lamp.rect
        if _image_left(lamp.rect):
            lamp.rect = (u0 * f, v0, u1 * f, v1)
        else:
            lamp.rect = (1.0 - (1.0 - u0) * f, v0, 1.0 - (1.0 - u1) * f, v1)


#: Saturation range of a recoloured blinker (``recolour_turn_lamps``): from pastel to pure.
TURN_HUE_SATURATION = (0.55, 1.0)


def random_hue_colour(rng: np.random.Generator) -> Colour:
    """A lamp colour of any hue (BGR, full value, saturation in ``TURN_HUE_SATURATION``)."""
    hue = rng.uniform(0.0, 1.0)
    sat = rng.uniform(*TURN_HUE_SATURATION)
    r, g, b = colorsys.hsv_to_rgb(hue, sat, 1.0)
    return (255.0 * b, 255.0 * g, 255.0 * r)


def recolour_turn_lamps(lamps: Sequence[Lamp], style: LampStyle, rng: np.random.Generator
                        ) -> Tuple[List[Lamp], LampStyle]:
    """The vehicle's amber lamps (blinkers, and the steady side markers drawn in the same
    amber) shining in one random hue instead, and its style with that ``amber``.

    A blinker is a lamp that flashes on one side of the vehicle, whatever its colour; drawn
    in every hue, it can only be learnt by its flashing. Red combined lamps (``turn_tail``,
    which are also the tail and brake lamps) keep their red; lenses keep their colour.

    Args:
        lamps: The vehicle's lamps (not modified).
        style: Its lamp style.
        rng: The vehicle's own stream for this option.

    Returns:
        ``(lamps, style)``: new lamps, recoloured where they shone amber, and the style.
    """
    colour = random_hue_colour(rng)
    out = [replace(lamp, emit=colour) if lamp.role == "turn" or lamp.emit == style.amber
           else lamp for lamp in lamps]
    return out, replace(style, amber=colour)


def tail_bar(lamps: Sequence[Lamp], style: LampStyle, rng: np.random.Generator) -> Optional[Lamp]:
    """A full-width tail bar across a rear face, joining its two per-side clusters.

    Tail level only (a centre tail lamp never brakes or blinks, ``shows_brake``); it sits
    at the top, middle or bottom of the clusters' band. None when the face has no pair of
    side clusters or already has a centre tail bar.

    Args:
        lamps: The rear face's lamps (``rear_lamps``).
        style: The vehicle's lamp style (colours, glow).
        rng: The bar's own stream.
    """
    if any(lamp.role == "tail" and lamp.side == "C" for lamp in lamps):
        return None
    rects = [lamp.rect for lamp in _cluster_lamps(lamps)]
    left = [r for r in rects if _image_left(r)]
    right = [r for r in rects if not _image_left(r)]
    if not left or not right:
        return None
    u0, u1 = max(r[2] for r in left), min(r[0] for r in right)
    v0, v1 = min(r[1] for r in rects), max(r[3] for r in rects)
    h = (v1 - v0) * rng.uniform(0.25, 0.6)
    top = v0 + (v1 - v0 - h) * float(rng.choice([0.0, 0.5, 1.0]))
    return Lamp("tail", "C", (u0, top, u1, top + h), "strip", style.red, style.red_lens, glow=style.glow * 0.5)


def front_lamps(style: LampStyle, kind: str, rng: np.random.Generator) -> List[Lamp]:
    """Lamps on the front face (view FRONT): the vehicle's left is the image right."""
    if kind in ("truck", "bus"):
        vc, h = rng.uniform(0.7, 0.82), rng.uniform(0.05, 0.09)
    elif kind == "van":
        vc, h = rng.uniform(0.5, 0.62), rng.uniform(0.06, 0.1)
    else:
        vc, h = rng.uniform(0.5, 0.62), rng.uniform(0.06, 0.11)
    inset = rng.uniform(0.03, 0.07)
    width = rng.uniform(0.14, 0.24)
    d = style.design
    lamps: List[Lamp] = []
    place = str(rng.choice(["outer", "below", "strip"])) if d in ("amber", "red_combined") else "strip"
    shape = str(rng.choice(["ellipse", "rect", "round"])) if d in ("amber", "red_combined") else str(rng.choice(["rect", "round"]))
    for side, (u0, v0, u1, v1), out in _pair((inset, vc - h / 2, inset + width, vc + h / 2), True):
        lamps.append(Lamp("head", side, (u0, v0, u1, v1), shape, style.white, (150, 150, 150), glow=style.glow * 1.6))
        if place == "outer":
            cw = (u1 - u0) * 0.3
            r = (u0 - cw * 0.6, v0, u0 + cw * 0.4, v1) if out < 0 else (u1 - cw * 0.4, v0, u1 + cw * 0.6, v1)
            lamps.append(Lamp("turn", side, r, "rect", style.amber, style.amber_lens, glow=style.glow))
        elif place == "below":
            w2 = (u1 - u0) * 0.6
            r = (u0, v1 + h * 0.4, u0 + w2, v1 + h * 0.9) if out < 0 else (u1 - w2, v1 + h * 0.4, u1, v1 + h * 0.9)
            lamps.append(Lamp("turn", side, r, "rect", style.amber, style.amber_lens, glow=style.glow))
        else:
            lamps.append(Lamp("drl", side, (u0, v0 - h * 0.45, u1, v0 - h * 0.1), "strip", style.white, (170, 170, 170), glow=style.glow))
            segs = style.seq_segments if d == "sequential" else 1
            lamps.append(Lamp("turn", side, (u0, v1 + h * 0.15, u1, v1 + h * 0.5), "strip", style.amber, style.amber_lens,
                              segments=segs, outward=out, glow=style.glow))
    return lamps


def side_lamps(style: LampStyle, kind: str, rng: np.random.Generator, view: View) -> List[Lamp]:
    """Lamps on one flank. From the LEFT the vehicle points to the image left, from the RIGHT to the image right."""
    side = "L" if view == View.LEFT else "R"
    if kind in ("truck", "bus"):
        v_front, v_rear = rng.uniform(0.7, 0.8), rng.uniform(0.76, 0.86)
    else:
        v_front, v_rear = rng.uniform(0.45, 0.6), rng.uniform(0.36, 0.52)
    h = rng.uniform(0.06, 0.1)
    ew = rng.uniform(0.025, 0.045) if kind != "bus" else rng.uniform(0.012, 0.02)
    lamps: List[Lamp] = [
        Lamp("head", side, (0.0, v_front - h / 2, ew * 1.5, v_front + h / 2), "rect", style.white, (150, 150, 150), glow=style.glow),
        Lamp("turn", side, (0.0, v_front + h / 2, ew, v_front + h), "rect", style.amber, style.amber_lens, glow=style.glow),
    ]
    # Side repeater on the front wing (cars) or along the body (trucks and buses).
    rep_u = rng.uniform(0.14, 0.24) if kind not in ("truck", "bus") else rng.uniform(0.1, 0.5)
    rw = rng.uniform(0.012, 0.025)
    lamps.append(Lamp("turn", side, (rep_u, v_front - h * 0.6, rep_u + rw * 2, v_front - h * 0.2), "rect",
                      style.amber, style.amber_lens, glow=style.glow * 0.8))
    rear_role = "turn_tail" if style.design == "red_combined" else "tail"
    lamps.append(Lamp(rear_role, side, (1.0 - ew, v_rear - h / 2, 1.0, v_rear + h / 2), "rect", style.red, style.red_lens, glow=style.glow))
    if style.design != "red_combined":
        lamps.append(Lamp("turn", side, (1.0 - ew, v_rear + h / 2, 1.0, v_rear + h), "rect", style.amber, style.amber_lens, glow=style.glow))
    if style.design == "red_combined" or kind in ("truck", "bus") or rng.random() < 0.15:
        # Steady side-marker lamps (amber at the front, red at the rear; amber along long bodies).
        mw = rng.uniform(0.015, 0.03) if kind not in ("truck", "bus") else rng.uniform(0.006, 0.012)
        mh = rng.uniform(0.025, 0.045)
        lamps.append(Lamp("marker", side, (ew * 1.8, v_front - mh / 2, ew * 1.8 + mw, v_front + mh / 2), "rect",
                          style.amber, style.amber_lens, glow=0.6))
        lamps.append(Lamp("marker", side, (1.0 - ew * 1.8 - mw, v_rear - mh / 2, 1.0 - ew * 1.8, v_rear + mh / 2), "rect",
                          style.red, style.red_lens, glow=0.6))
        if kind in ("truck", "bus"):
            for u in np.linspace(0.25, 0.85, int(rng.integers(2, 6))):
                lamps.append(Lamp("marker", side, (u, 0.8, u + mw, 0.8 + mh), "rect", style.amber, style.amber_lens, glow=0.5))
    if view == View.RIGHT:  # the vehicle points to the image right: mirror
        for lamp in lamps:
            u0, v0, u1, v1 = lamp.rect
            lamp.rect = (1.0 - u1, v0, 1.0 - u0, v1)
    return lamps


# --------------------------------------------------------------------------- timing

def lamp_outlines(lamp: Lamp) -> List[np.ndarray]:
    """Normalised outline polygons of a lamp: one, or one per segment of a sequential lamp
    ordered from the inner end to the outer end."""
    return _segment_polys(lamp) if lamp.segments > 1 else [_lamp_poly(lamp)]


def _lamp_poly(lamp: Lamp) -> np.ndarray:
    """Normalised outline polygon of a lamp."""
    u0, v0, u1, v1 = lamp.rect
    if lamp.shape in ("round", "ellipse"):
        cu, cv, ru, rv = (u0 + u1) / 2, (v0 + v1) / 2, (u1 - u0) / 2, (v1 - v0) / 2
        if lamp.shape == "ellipse":
            a = np.linspace(0, 2 * np.pi, 12, endpoint=False)
            return np.stack([cu + ru * np.cos(a), cv + rv * np.sin(a)], 1).astype(np.float32)
        k = 0.35  # rounded rectangle: cut corners
        return np.array([[u0 + ru * k, v0], [u1 - ru * k, v0], [u1, v0 + rv * k], [u1, v1 - rv * k], [u1 - ru * k, v1],
                         [u0 + ru * k, v1], [u0, v1 - rv * k], [u0, v0 + rv * k]], np.float32)
    return np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]], np.float32)


def _segment_polys(lamp: Lamp) -> List[np.ndarray]:
    """Segments of a sequential lamp ordered from the inner end to the outer end."""
    u0, v0, u1, v1 = lamp.rect
    n = lamp.segments
    edges = np.linspace(u0, u1, n + 1)
    gap = (u1 - u0) / n * 0.15
    polys = [np.array([[edges[i] + gap, v0], [edges[i + 1] - gap, v0], [edges[i + 1] - gap, v1], [edges[i] + gap, v1]], np.float32)
             for i in range(n)]
    return polys if lamp.outward > 0 else polys[::-1]


@dataclass
class _Segment:
    start: float
    end: float
    value: int


class Timeline:
    """A piecewise-constant signal (blinker state or brake) drawn lazily from an RNG.

    Args:
        rng: Generator owned by this timeline (keeps results independent of query order).
        states: Possible values; the first is the rest state that active values mostly
            return to.
        weights: Probability of each value when a new segment starts.
        durations: Per value, (mean, min, max) seconds of a segment.
        fixed: When given, the signal holds this value forever.
    """

    def __init__(self, rng: np.random.Generator, states: Sequence[int], weights: Sequence[float],
                 durations: Sequence[Tuple[float, float, float]], fixed: Optional[int] = None) -> None:
        self._rng = rng
        self._states = list(states)
        self._weights = np.asarray(weights, dtype=float) / float(np.sum(weights))
        self._dur = list(durations)
        self._fixed = fixed
        # Start somewhere inside a segment so sequences do not all begin with a transition.
        first = self._draw_state(None)
        length = self._draw_duration(first)
        offset = rng.uniform(0.0, length)
        self._segments: List[_Segment] = [_Segment(-offset, length - offset, first)]

    def _draw_state(self, previous: Optional[int]) -> int:
        w = self._weights.copy()
        if previous is not None:
            if previous != self._states[0] and self._rng.random() < 0.85:
                return int(self._states[0])  # signals mostly switch off before switching to another
            w[self._states.index(previous)] = 0.0  # a new segment always changes the value
            w /= w.sum()
        return int(self._states[int(self._rng.choice(len(self._states), p=w))])

    def _draw_duration(self, state: int) -> float:
        mean, lo, hi = self._dur[self._states.index(state)]
        return float(np.clip(self._rng.exponential(mean), lo, hi))

    def segment(self, t: float) -> Tuple[int, float]:
        """The value at time ``t`` (s) and the time its segment started."""
        if self._fixed is not None:
            return self._fixed, -1e9
        while self._segments[-1].end <= t:
            last = self._segments[-1]
            state = self._draw_state(last.value)
            self._segments.append(_Segment(last.end, last.end + self._draw_duration(state), state))
        for seg in reversed(self._segments):
            if seg.start <= t:
                return seg.value, seg.start
        return self._segments[0].value, self._segments[0].start


def blinker_timeline(rng: np.random.Generator, fixed: Optional[Intent] = None, hazard_rate: float = 0.12) -> Timeline:
    """Blinker state over time: OFF, LEFT, RIGHT or HAZARD segments (~40-50 % of time ON)."""
    states = [int(Intent.OFF), int(Intent.LEFT), int(Intent.RIGHT), int(Intent.HAZARD)]
    w_turn = (1.0 - hazard_rate) / 2.0
    weights = [1.0, w_turn, w_turn, hazard_rate]
    durations = [(3.5, 0.8, 12.0), (4.0, 1.2, 12.0), (4.0, 1.2, 12.0), (4.0, 1.5, 12.0)]
    return Timeline(rng, states, weights, durations, None if fixed is None else int(fixed))


#: A brake press: (mean, min, max) seconds.
BRAKE_PRESS_S = (2.2, 0.5, 8.0)


def checked_brake_share(share: float) -> float:
    """``share`` if a brake timeline can be drawn with it.

    Raises:
        ConfigError: ``share`` is not in [0, 1) (a brake never released has no timeline).
    """
    if not 0.0 <= share < 1.0:
        raise ConfigError(f"brake_share must be in [0, 1), got {share!r}")
    return share


def brake_timeline(rng: np.random.Generator, fixed: Optional[bool] = None,
                   share: float = 0.0) -> Timeline:
    """Brake pressed (1) or released (0) over time.

    Args:
        rng: The timeline's own generator.
        fixed: When given, the brake holds this state forever.
        share: 0: the renderer's own timeline (releases of about 3 s, about 40 % of the
            time pressed, a track as likely to start pressed as not). Above 0: releases
            long enough for about that share of the time to be pressed, and a track starts
            pressed with that probability.

    Raises:
        ConfigError: ``share`` is not in [0, 1) (a brake never released has no timeline).
    """
    share = checked_brake_share(share)
    held = None if fixed is None else int(bool(fixed))
    if share == 0.0:
        return Timeline(rng, [0, 1], [1.0, 1.0], [(3.0, 0.5, 10.0), BRAKE_PRESS_S], held)
    release = BRAKE_PRESS_S[0] * (1.0 - share) / share
    return Timeline(rng, [0, 1], [1.0 - share, share],
                    [(release, 0.5, 4.0 * release), BRAKE_PRESS_S], held)


def flasher_level(t_active: float, style: LampStyle, exposure_s: float, delay: float = 0.0) -> float:
    """Brightness (0..1) of a blinker that was switched on ``t_active`` seconds ago.

    Real flashers start with a lit half; LEDs switch hard, bulbs rise and fade with time
    constants. The camera integrates over its exposure time, so a transition inside the
    exposure gives an intermediate level.

    Args:
        t_active: Seconds since the blinker was switched on (plus the vehicle's phase).
        style: The vehicle's lamp style (frequency, duty, technology).
        exposure_s: Camera exposure time in seconds.
        delay: Extra delay of this segment within the on phase (sequential indicators).
    """
    period = 1.0 / style.blink_hz
    on = style.duty * period
    total = 0.0
    samples = (0.0, 0.5, 1.0)
    for s in samples:
        tau = (t_active - s * exposure_s) % period
        if style.tech == "led":
            total += 1.0 if delay <= tau < on else 0.0
        else:
            er, ef = math.exp(-on / style.tau_rise), math.exp(-(period - on) / style.tau_fall)
            r0 = ef * (1 - er) / (1 - er * ef)
            if tau < on:
                total += 1.0 - (1.0 - r0) * math.exp(-tau / style.tau_rise)
            else:
                v_end = 1.0 - (1.0 - r0) * er
                total += v_end * math.exp(-(tau - on) / style.tau_fall)
    return total / len(samples)
