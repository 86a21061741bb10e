"""The traffic of the training renderer: which vehicles a scene holds, where each one
appears, what it looks like and how it moves.

A vehicle is one face (behind, front or a side) of a body of some kind, seen at a depth
``Z`` and a lateral offset ``X`` on the street of ``environment.StreetGeometry``. A front or
rear view may be turned (``Vehicle.yaw``, a share ``oblique`` of them): its face is
foreshortened and its flank shows, as a turning vehicle or one seen three-quarter on. New
vehicles are placed so that they seldom hide most of one already there; front and rear
views drive along a lane, side views cross the image. A vehicle that leaves the scene is
replaced by one entering it (``Traffic.step``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.labels import Intent, View
from signal_light_node.synth import lamps as lamp_mod
from signal_light_node.synth.environment import Lighting, StreetGeometry, shade
from signal_light_node.synth.foreign_lamps import (ForeignLamp, high_foreign_lamp,
                                                   sample_foreign_lamp)
from signal_light_node.synth.lamps import Lamp, LampStyle, blinker_timeline, brake_timeline, lamp_outlines, sample_lamp_style
from signal_light_node.synth.vehicles import (KIND_DIMS, KIND_WEIGHTS, KINDS, BodyShape, body_shape, face_size_m, sample_colour,
                                              sample_paints)

Box = Tuple[float, float, float, float]

_VIEW_WEIGHTS = {View.BEHIND: 0.42, View.FRONT: 0.26, View.LEFT: 0.16, View.RIGHT: 0.16}
#: Range of |yaw| (degrees) of a turned front or rear view. Under 45 degrees the face
#: toward the camera is still the one labelled (the 90-degree sectors of the truth).
OBLIQUE_YAW_DEG = (10.0, 40.0)
#: With ``tail_glare``: the chosen vehicles' tail level (clipped on the lens by the lamp
#: gain) and the level of their brake and flashes over it.
GLARE_TAIL_LEVEL = (0.7, 1.0)
GLARE_LEVEL = (2.0, 4.0)
#: With ``glare_tail_bright``: the chosen glaring vehicles' steady tail level (over the
#: clip, as bright as another vehicle's brake can be), and their brake's as a multiple of it.
BRIGHT_TAIL_LEVEL = (1.5, 6.0)
BRIGHT_BRAKE_RATIO = (1.5, 3.0)
#: How much wider ``wide_truck_lamps`` draws a truck's or bus's rear clusters: ``rear_lamps``
#: makes them 7-13 % of the width, split in two on some designs, so that on a tall body many
#: fall under the truth's size rule (``truth.LAMP_MIN_BOX_SHARE``); real combination lamps
#: are 0.3-0.5 m of a 2.5 m rear.
WIDE_TRUCK_FACTOR = (1.6, 2.6)
#: Largest |yaw| a vehicle override may ask for.
MAX_YAW_DEG = 44.0


@dataclass
class Vehicle:
    """One labelled vehicle: its face, looks, lamps, position and motion, signal timelines
    and the bias of its simulated tracker; the stacked outlines let one matrix product per
    frame map every part or lamp to pixels."""

    track_id: str
    kind: str
    view: View
    style: LampStyle
    colour: Tuple[float, float, float]
    face_w: float
    face_h: float
    shape: BodyShape
    lamps: List[Lamp]
    lamp_polys: List[List[np.ndarray]]
    X: float
    Z: float
    vx: float
    vz: float
    lights_on: bool
    blinker: lamp_mod.Timeline
    brake: lamp_mod.Timeline
    phase: float
    shear: float
    roll: float
    spots: List[Tuple[float, float, float, float, float]]
    paints: Dict[str, Tuple[float, float, float]]
    part_pts: np.ndarray = field(default=None)
    part_splits: List[Tuple[str, int, int]] = field(default_factory=list)
    sil_splits: List[Tuple[int, int]] = field(default_factory=list)
    tracker_bias: Tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    tracker_sigma: float = 0.02
    tracker_amodal: bool = False
    lamp_pts: np.ndarray = field(default=None)
    lamp_ranges: List[Tuple[int, int]] = field(default_factory=list)
    lamp_ranges_poly: List[List[Tuple[int, int]]] = field(default_factory=list)
    lens_cols: List[Tuple[float, float, float]] = field(default_factory=list)
    #: Degrees the body's axis is turned from the line of sight's depth direction; its
    #: far end lies to the image right for a positive yaw (front and rear views only).
    yaw: float = 0.0
    #: Level of a fully lit brake or flash over the lens's clipping (1: none). Above 1
    #: the vehicle's tail lamps are drawn clipped too, as a camera at night shows them,
    #: and only the larger glow, the hotter core and the centre lamp tell a brake.
    glare: float = 1.0
    #: With ``glare`` over 1: the steady tail lamps' core and glow drawn at the brake's
    #: colour and strength, so that only the glow's extent, the growth over the track's own
    #: level and the centre lamp tell a brake (``Traffic.glare_tail_hot``).
    tail_hot: bool = False
    #: A lamp beyond the vehicle that falls inside its crop (``Traffic.foreign_lamp``;
    #: ``synth.foreign_lamps``), or None.
    foreign: Optional[ForeignLamp] = None


class Traffic:
    """The labelled vehicles of one scene (``vehicles``, in listing order).

    Args:
        seed: The scene's seed (each vehicle draws from its own stream of it).
        rng: The scene's setup stream; track IDs and their steps come from it.
        width: Image width in pixels.
        geo: The street and the camera over it.
        light: The scene's light.
        lighting: "day", "dusk" or "night".
        family: Style family of the lamps.
        oblique: Share of front and rear views drawn turned (``OBLIQUE_YAW_DEG``).
        tail_glare: Share of vehicles with lamps lit in a dusk or night scene whose tail
            lamps are drawn clipped like their brake lamps (``Vehicle.glare``).
        rear_bar: Share of rear views given a full-width tail bar (``lamps.tail_bar``).
        wide_truck_lamps: Share of truck and bus rear views whose side clusters are drawn
            ``WIDE_TRUCK_FACTOR`` times wider (``lamps.widen_clusters``).
        glare_tail_hot: Share of the glaring vehicles whose tail lamps' core and glow are
            drawn at their brake's colour (``Vehicle.tail_hot``).
        glare_tail_bright: Share of the glaring vehicles whose steady tail lamps shine over
            the clip (``BRIGHT_TAIL_LEVEL``) and whose brake is ``BRIGHT_BRAKE_RATIO`` times
            that: across vehicles no lamp size or glow tells a brake, only the vehicle's
            own step and its centre lamp.
        foreign_lamp: Share of vehicles with a lamp beyond them, over the roof or beside,
            inside their crop (``Vehicle.foreign``, ``synth.foreign_lamps``).
        foreign_high: Share of those lamps drawn red over the middle of the roof, where the
            vehicle's own centre high-mounted stop lamp would be (``high_foreign_lamp``).
        brake_share: Share of the time a brake is pressed, and of tracks first seen
            braking (``lamps.brake_timeline``; 0: the timeline's own, about 40 % and half).
        turn_hue: Share of vehicles whose blinkers (and the amber markers that match them)
            shine in a random hue (``lamps.recolour_turn_lamps``).
    """

    def __init__(self, seed: int, rng: np.random.Generator, width: int, geo: StreetGeometry, light: Lighting, lighting: str,
                 family: int, oblique: float = 0.0, tail_glare: float = 0.0, rear_bar: float = 0.0,
                 wide_truck_lamps: float = 0.0, glare_tail_hot: float = 0.0,
                 glare_tail_bright: float = 0.0, foreign_lamp: float = 0.0,
                 foreign_high: float = 0.0, brake_share: float = 0.0,
                 turn_hue: float = 0.0) -> None:
        self.seed = seed
        self.width = width
        self._rng = rng
        self._geo = geo
        self._light = light
        self.lighting = lighting
        self.family = family
        self.oblique = oblique
        self.tail_glare = tail_glare
        self.rear_bar = rear_bar
        self.wide_truck_lamps = wide_truck_lamps
        self.glare_tail_hot = glare_tail_hot
        self.glare_tail_bright = glare_tail_bright
        self.foreign_lamp = foreign_lamp
        self.foreign_high = foreign_high
        self.brake_share = brake_share
        self.turn_hue = turn_hue
        self._next_id = int(rng.integers(1, 50))
        self.vehicles: List[Vehicle] = []

    def project(self, v: Vehicle) -> Box:
        """The full box of a vehicle's face in the (unshaken) image."""
        f = self._geo.focal
        bottom = self._geo.horizon + f * self._geo.cam_h / v.Z
        h = v.face_h * f / v.Z
        w = v.face_w * math.cos(math.radians(v.yaw)) * f / v.Z  # foreshortened when turned
        cx = self._geo.vanish_x + f * v.X / v.Z
        return cx - w / 2, bottom - h, cx + w / 2, bottom

    def step(self, dt: float, respawn: bool) -> None:
        """Move every vehicle by ``dt`` seconds; one that left is replaced by a new one
        entering the scene when ``respawn``."""
        for i, v in enumerate(self.vehicles):
            if not self._move(v, dt) and respawn:
                self.vehicles[i] = self.spawn({}, entering=True)

    def _move(self, v: Vehicle, dt: float) -> bool:
        """Advance a vehicle by ``dt`` seconds; False when it left the scene."""
        v.X += v.vx * dt
        v.Z += v.vz * dt
        z_min = v.face_w * self._geo.focal / (0.55 * self.width)
        if v.Z < z_min:
            if v.view == View.BEHIND:
                v.vz = abs(v.vz)
                v.Z = z_min
            else:
                return False
        if v.Z > 90:
            return False
        x0, y0, x1, y1 = self.project(v)
        if x1 < -2 or x0 > self.width + 2:
            return False
        return True

    def spawn(self, vo: Dict[str, Any], entering: bool) -> Vehicle:
        """A new vehicle (``vo``: the per-vehicle overrides of ``SceneRenderer``); one
        ``entering`` comes in from an image side, from far away or from below."""
        rng = self._rng
        vrng = np.random.default_rng([self.seed, 100 + self._next_id])
        track_id = str(self._next_id)
        self._next_id += int(rng.integers(1, 4))
        views = list(_VIEW_WEIGHTS)
        view = View(vo["view"]) if "view" in vo else views[int(vrng.choice(4, p=list(_VIEW_WEIGHTS.values())))]
        kind = vo.get("kind") or str(vrng.choice(KINDS, p=np.asarray(KIND_WEIGHTS) / sum(KIND_WEIGHTS)))
        if kind not in KIND_DIMS:
            raise ConfigError(f"kind must be one of {KINDS}, got {kind!r}")
        design = vo.get("lamp_design")
        if design is not None and design not in lamp_mod.LAMP_DESIGNS:
            raise ConfigError(f"lamp_design must be one of {lamp_mod.LAMP_DESIGNS}, got {design!r}")
        style = sample_lamp_style(vrng, kind, design, vo.get("tech"), vo.get("chmsl"), vo.get("blink_hz"), vo.get("duty"),
                                  family=self.family)
        scale = vrng.uniform(0.93, 1.07)
        face_w, face_h = face_size_m(kind, view, scale)
        shape = body_shape(kind, view, vrng)
        if view == View.BEHIND:
            lamps = lamp_mod.rear_lamps(style, kind, vrng, shape.chmsl_v)
        elif view == View.FRONT:
            lamps = lamp_mod.front_lamps(style, kind, vrng)
        else:
            lamps = lamp_mod.side_lamps(style, kind, vrng, view)
        lamp_polys = [lamp_outlines(l) for l in lamps]
        W, f = self.width, self._geo.focal
        z_min = face_w * f / (0.5 * W)
        z_max = min(70.0, face_w * f / 22.0)
        Z, X = self._place(vo, view, face_w, face_h, entering, vrng, z_min, z_max)
        x_img = self._geo.vanish_x + f * X / Z
        speed = vo.get("speed")
        if view in (View.LEFT, View.RIGHT):
            # Crossing traffic: moves towards its front (image left from the LEFT view).
            heading = -1.0 if view == View.LEFT else 1.0
            s = float(speed) if speed is not None else (0.0 if vrng.random() < 0.3 else vrng.uniform(1.0, 7.0))
            if entering and s == 0.0:
                s = vrng.uniform(1.0, 5.0)
            if entering and speed is None:
                heading = 1.0 if x_img < 0 else -1.0
                view = View.RIGHT if heading > 0 else View.LEFT
                if view != (View.LEFT if lamps[0].side == "L" else View.RIGHT):
                    shape = body_shape(kind, view, vrng)
                    lamps = lamp_mod.side_lamps(style, kind, vrng, view)
                    lamp_polys = [lamp_outlines(l) for l in lamps]
            vx, vz = heading * s, 0.0
        else:
            s = float(speed) if speed is not None else None
            if view == View.BEHIND:
                vz = s if s is not None else vrng.uniform(-1.5, 1.5)
                if entering and s is None:
                    vz = -vrng.uniform(0.5, 3.0) if Z > z_max * 0.5 else vrng.uniform(1.0, 4.0)
            else:
                vz = -(s if s is not None else vrng.uniform(0.0, 4.0))
            vx = 0.0 if s is not None else vrng.uniform(-0.25, 0.25)
        fixed_intent = vo.get("intent")
        if fixed_intent is not None and Intent(fixed_intent) == Intent.UNKNOWN:
            raise ConfigError("intent override must be OFF, LEFT, RIGHT or HAZARD")
        lights_on = bool(vo["lights_on"]) if "lights_on" in vo else bool(vrng.random() < self._light.lights_on)
        colour = tuple(float(c) for c in vo["colour"]) if "colour" in vo else sample_colour(vrng)
        paints = sample_paints(vrng, colour, self._light)
        spots = []
        if vo.get("specular", vrng.random() < (0.7 if self.lighting == "day" else 0.4)):
            for _ in range(int(vrng.integers(1, 4))):
                spots.append((vrng.uniform(0.1, 0.9), vrng.uniform(0.05, 0.6), vrng.uniform(0.012, 0.045), vrng.uniform(0.008, 0.03),
                              vrng.uniform(0.4, 1.0)))
        v = Vehicle(track_id=track_id, kind=kind, view=view, style=style, colour=colour, face_w=face_w, face_h=face_h,
                    shape=shape, lamps=lamps, lamp_polys=lamp_polys, X=X, Z=Z, vx=vx, vz=vz, lights_on=lights_on,
                    blinker=blinker_timeline(np.random.default_rng([self.seed, 200 + int(track_id)]),
                                             None if fixed_intent is None else Intent(fixed_intent)),
                    brake=brake_timeline(np.random.default_rng([self.seed, 300 + int(track_id)]),
                                         None if vo.get("brake") is None else bool(vo["brake"]),
                                         self.brake_share),
                    phase=float(vo["phase"]) if "phase" in vo else float(vrng.uniform(0, 1.0 / style.blink_hz)),
                    shear=float(vo.get("shear", vrng.uniform(-0.05, 0.05))),
                    roll=float(vo.get("roll", vrng.uniform(-1.5, 1.5))), spots=spots, paints=paints,
                    tracker_bias=tuple(float(b) for b in vrng.normal(0, 0.02, 4)),
                    tracker_sigma=float(vrng.uniform(0.008, 0.035)), tracker_amodal=bool(vrng.random() < 0.3))
        v.yaw = self._yaw(vo, v)
        self._glare(v)
        self._wide_truck_lamps(v)
        self._rear_bar(v)
        self._foreign(v)
        self._turn_hue(v)
        pts, splits, sil = [], [], []
        n = 0
        for key, poly in shape.parts:
            pts.append(poly)
            splits.append((key, n, n + len(poly)))
            n += len(poly)
        for poly in shape.silhouette:
            pts.append(poly)
            sil.append((n, n + len(poly)))
            n += len(poly)
        v.part_pts = np.concatenate(pts, 0).astype(np.float32)
        v.part_splits, v.sil_splits = splits, sil
        self._prepare_lamps(v)
        return v

    def _picked(self, v: Vehicle, stream: int, share: float) -> Optional[np.random.Generator]:
        """The vehicle's own stream number ``stream`` (+ its track ID) when its first draw
        picks the vehicle with probability ``share``, else None. A stream of its own per
        option keeps every other draw of the scene as it was without that option."""
        rng = np.random.default_rng([self.seed, stream + int(v.track_id)])
        return rng if rng.random() < share else None

    def _yaw(self, vo: Dict[str, Any], v: Vehicle) -> float:
        """The yaw of a new vehicle: the override, else with probability ``oblique`` one
        drawn from ``OBLIQUE_YAW_DEG`` (a stream of its own: every other draw of the scene
        stays as it was without turned vehicles)."""
        if "yaw" in vo:
            yaw = float(vo["yaw"])
            if not math.isfinite(yaw) or abs(yaw) > MAX_YAW_DEG:
                raise ConfigError(f"yaw must be within +-{MAX_YAW_DEG:g} degrees, got {vo['yaw']!r}")
            if yaw and v.view not in (View.BEHIND, View.FRONT):
                raise ConfigError("yaw turns front and rear views only")
            return yaw
        if self.oblique <= 0 or v.view not in (View.BEHIND, View.FRONT):
            return 0.0
        yrng = self._picked(v, 400, self.oblique)
        if yrng is None:
            return 0.0
        return float(yrng.uniform(*OBLIQUE_YAW_DEG) * (1.0 if yrng.random() < 0.5 else -1.0))

    def _glare(self, v: Vehicle) -> None:
        """With probability ``tail_glare``, a lit vehicle of a dusk or night scene gets
        clipped tail lamps and a brake and flashes brighter still (a stream of its own, as
        ``_yaw``'s); with probability ``glare_tail_hot`` its tail lamps are drawn at the
        brake's colour, with probability ``glare_tail_bright`` they shine over the clip and
        the brake further still (each another stream of its own)."""
        if self.tail_glare <= 0 or self.lighting == "day" or not v.lights_on:
            return
        grng = self._picked(v, 500, self.tail_glare)
        if grng is None:
            return
        v.style = replace(v.style, tail_level=float(grng.uniform(*GLARE_TAIL_LEVEL)))
        v.glare = float(grng.uniform(*GLARE_LEVEL))
        v.tail_hot = self._picked(v, 800, self.glare_tail_hot) is not None
        brng = self._picked(v, 900, self.glare_tail_bright)
        if brng is not None:
            tail = float(brng.uniform(*BRIGHT_TAIL_LEVEL))
            v.style = replace(v.style, tail_level=tail)
            v.glare = tail * float(brng.uniform(*BRIGHT_BRAKE_RATIO))

    def _wide_truck_lamps(self, v: Vehicle) -> None:
        """With probability ``wide_truck_lamps``, a truck or bus seen from behind gets side
        clusters as wide as real combination lamps (a stream of its own)."""
        if self.wide_truck_lamps <= 0 or v.view != View.BEHIND or v.kind not in ("truck", "bus"):
            return
        wrng = self._picked(v, 700, self.wide_truck_lamps)
        if wrng is None:
            return
        lamp_mod.widen_clusters(v.lamps, float(wrng.uniform(*WIDE_TRUCK_FACTOR)))
        v.lamp_polys = [lamp_outlines(lamp) for lamp in v.lamps]

    def _rear_bar(self, v: Vehicle) -> None:
        """With probability ``rear_bar``, a rear view gets a full-width tail bar (a stream
        of its own, as ``_yaw``'s: the scene's other draws stay as they were)."""
        if self.rear_bar <= 0 or v.view != View.BEHIND:
            return
        brng = self._picked(v, 600, self.rear_bar)
        if brng is None:
            return
        bar = lamp_mod.tail_bar(v.lamps, v.style, brng)
        if bar is not None:
            v.lamps.append(bar)
            v.lamp_polys.append(lamp_outlines(bar))

    def _place(self, vo: Dict[str, Any], view: View, face_w: float, face_h: float, entering: bool,
               vrng: np.random.Generator, z_min: float, z_max: float) -> Tuple[float, float]:
        """Depth and lateral position of a new vehicle.

        Sizes run from ~22 px to half the frame wide; front/rear views sit in a lane,
        crossing traffic anywhere. Random placements that would mostly hide behind (or
        hide) a vehicle already there are drawn again, so that occlusion stays partial.
        """
        f, W = self._geo.focal, self.width
        geo = self._geo
        best = None
        for attempt in range(8):
            if "width_px" in vo:
                Z = face_w * f / float(vo["width_px"])
            elif entering and view == View.FRONT:
                Z = z_max * vrng.uniform(0.6, 1.0)  # oncoming: appears far away
            elif entering and view == View.BEHIND:
                # Either far ahead (we catch up) or close, overtaking us from the image bottom.
                Z = z_max * vrng.uniform(0.6, 1.0) if vrng.random() < 0.6 else z_min * vrng.uniform(1.0, 1.3)
            else:
                Z = float(math.exp(vrng.uniform(math.log(z_min), math.log(max(z_max, z_min * 1.01)))))
            if "center_x" in vo:
                X = (float(vo["center_x"]) - geo.vanish_x) * Z / f
            elif view in (View.LEFT, View.RIGHT):
                x_img = vrng.uniform(-0.1, 1.1) * W
                if entering:
                    x_img = -0.45 * face_w * f / Z if vrng.random() < 0.5 else W + 0.45 * face_w * f / Z
                X = (x_img - geo.vanish_x) * Z / f
            else:
                n_lanes = max(1, int(round((geo.x_right - geo.x_left) / geo.lane_w)))
                lane = int(vrng.integers(0, n_lanes))
                X = geo.x_left + (lane + 0.5) * (geo.x_right - geo.x_left) / n_lanes + vrng.normal(0, 0.25)
            if "width_px" in vo or "center_x" in vo:
                return Z, X
            overlap = self._overlap(Z, X, face_w, face_h)
            if best is None or overlap < best[0]:
                best = (overlap, Z, X)
            if overlap < 0.35:
                break
        return best[1], best[2]

    def _overlap(self, Z: float, X: float, face_w: float, face_h: float) -> float:
        """Largest fraction of either box that a candidate and an existing vehicle share."""
        f = self._geo.focal
        bottom = self._geo.horizon + f * self._geo.cam_h / Z
        w, h = face_w * f / Z, face_h * f / Z
        cx = self._geo.vanish_x + f * X / Z
        a = (cx - w / 2, bottom - h, cx + w / 2, bottom)
        worst = 0.0
        for other in self.vehicles:
            b = self.project(other)
            iw = min(a[2], b[2]) - max(a[0], b[0])
            ih = min(a[3], b[3]) - max(a[1], b[1])
            if iw <= 0 or ih <= 0:
                continue
            inter = iw * ih
            smaller = min((a[2] - a[0]) * (a[3] - a[1]), (b[2] - b[0]) * (b[3] - b[1]))
            worst = max(worst, inter / max(smaller, 1e-6))
        return worst

    def _foreign(self, v: Vehicle) -> None:
        """With probability ``foreign_lamp``, a lamp beyond the vehicle inside its crop (a
        stream of its own, as ``_yaw``'s); with probability ``foreign_high`` it is moved
        over the middle of the roof (another stream of its own)."""
        if self.foreign_lamp <= 0:
            return
        frng = self._picked(v, 1000, self.foreign_lamp)
        if frng is None:
            return
        v.foreign = sample_foreign_lamp(frng)
        hrng = self._picked(v, 1100, self.foreign_high)
        if hrng is not None:
            v.foreign = high_foreign_lamp(v.foreign, hrng)

    def _turn_hue(self, v: Vehicle) -> None:
        """With probability ``turn_hue``, the vehicle's blinkers and matching markers shine
        in a random hue (a stream of its own, as ``_yaw``'s)."""
        if self.turn_hue <= 0:
            return
        hrng = self._picked(v, 1200, self.turn_hue)
        if hrng is not None:
            v.lamps, v.style = lamp_mod.recolour_turn_lamps(v.lamps, v.style, hrng)

    def _prepare_lamps(self, v: Vehicle) -> None:
        """Stack all lamp outlines so that one matrix product per frame maps them to pixels."""
        pts, ranges, ranges_poly = [], [], []
        n = 0
        for polys in v.lamp_polys:
            a0 = n
            rp = []
            for poly in polys:
                pts.append(poly)
                rp.append((n, n + len(poly)))
                n += len(poly)
            ranges.append((a0, n))
            ranges_poly.append(rp)
        v.lamp_pts = np.concatenate(pts, 0).astype(np.float64)
        v.lamp_ranges, v.lamp_ranges_poly = ranges, ranges_poly
        lt = self._light
        night = self.lighting != "day"
        v.lens_cols = [shade(l.lens, lt, 1.0 / max(lt.ambient, 0.35) * (0.7 if night else 1.0)) for l in v.lamps]
