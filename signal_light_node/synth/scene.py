"""The scene renderer: layout, vehicle motion, occlusion, tracker simulation and labels.

A ``SceneRenderer`` owns a camera on a street and a handful of vehicles seen from behind,
from the front or from a side. Each frame it moves the vehicles, decides which lamps are
lit (per-vehicle blinker and brake timelines), works out which lamps are visible
(other vehicles, poles and the image border hide them), draws everything and hands back
the image with one ``VehicleTruth`` per vehicle that is visible enough to be listed.
"""

from __future__ import annotations

import logging
import math
from typing import Any, Iterator, List, Optional, Tuple

import cv2
import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.labels import Intent, LightStatus, View, intent_from_lights
from signal_light_node.synth.camera import Camera, sample_camera
from signal_light_node.synth.environment import (GLOW_SCALE, LIGHTINGS, Environment, Lighting, Occluder, StreetGeometry,
                                                 blur_glow, sample_lighting)
from signal_light_node.synth.lamps import STYLE_FAMILIES, TRAIN_FAMILIES, flasher_level
from signal_light_node.synth.tracker import tracker_box
from signal_light_node.synth.traffic import Traffic, Vehicle
from signal_light_node.synth.truth import RenderedFrame, VehicleTruth
from signal_light_node.synth.vehicle_drawing import Drawn, VehiclePainter
from signal_light_node.synth.vehicles import CLASS_IDS

LOG = logging.getLogger(__name__)

_MARGIN = 12
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
#: Vehicles smaller than this (visible box, pixels) or more hidden than this are not listed.
MIN_LISTED_PX = 8.0
MAX_LISTED_OCCLUSION = 0.9

_SCENE_KEYS = {"vehicles", "occluders", "poles", "distractors", "weather", "effects", "shake", "respawn", "horizon", "focal",
               "family"}
_VEHICLE_KEYS = {"view", "kind", "lamp_design", "tech", "chmsl", "intent", "brake", "colour", "lights_on", "center_x",
                 "width_px", "speed", "blink_hz", "duty", "phase", "shear", "roll", "specular"}


def _light_status(on: bool, visible: bool) -> LightStatus:
    """ON or OFF for a light that can be judged, UNKNOWN for one that cannot."""
    if not visible:
        return LightStatus.UNKNOWN
    return LightStatus.ON if on else LightStatus.OFF


class SceneRenderer:
    """Procedural street scenes with vehicles whose lights switch on and off.

    Args:
        seed: Everything is deterministic from this seed.
        width: Image width in pixels.
        height: Image height in pixels.
        fps: Frame rate; None draws one in [10, 30].
        n_vehicles: Number of labelled vehicles in the scene at a time; None draws 3..6.
        lighting: "day", "dusk" or "night"; None draws one (night with ``night_fraction``).
        night_fraction: Probability of night when ``lighting`` is None.
        **overrides: Scene controls for tests and tools. Scene keys: ``vehicles`` (list of
            per-vehicle dicts, see below), ``occluders`` (list of static (x0, y0, x1, y1)
            pixel rectangles in front of every vehicle), ``poles`` (number of moving poles),
            ``distractors`` (bool), ``weather`` ("clear", "rain", "haze"), ``effects`` (bool,
            camera noise/blur/JPEG), ``shake`` (bool), ``respawn`` (bool), ``horizon``
            (fraction of the height), ``focal`` (fraction of the width), ``family`` (style
            family of lamp colours and camera tone, ``synth.lamps.STYLE_FAMILIES``; default:
            one of ``TRAIN_FAMILIES`` drawn from the seed). Vehicle keys:
            ``view`` (View), ``kind``, ``lamp_design``, ``tech`` ("led"/"bulb"), ``chmsl``,
            ``intent`` (Intent held for the whole sequence), ``brake`` (bool held),
            ``colour`` (BGR), ``lights_on``, ``center_x`` (pixels), ``width_px`` (box width),
            ``speed`` (m/s; 0 = parked), ``blink_hz``, ``duty``, ``phase`` (s), ``shear``,
            ``roll`` (degrees), ``specular`` (bool).

    Raises:
        ConfigError: On an unknown override or a value out of range.
    """

    def __init__(self, seed: int, width: int = 640, height: int = 360, fps: Optional[float] = None,
                 n_vehicles: Optional[int] = None, lighting: Optional[str] = None, night_fraction: float = 0.35,
                 **overrides: Any) -> None:
        unknown = set(overrides) - _SCENE_KEYS
        if unknown:
            raise ConfigError(f"unknown SceneRenderer overrides {sorted(unknown)}; allowed: {sorted(_SCENE_KEYS)}")
        for i, vo in enumerate(overrides.get("vehicles") or []):
            bad = set(vo) - _VEHICLE_KEYS
            if bad:
                raise ConfigError(f"unknown keys {sorted(bad)} in vehicles[{i}]; allowed: {sorted(_VEHICLE_KEYS)}")
        if width < 64 or height < 48:
            raise ConfigError(f"image size {width}x{height} is too small (need at least 64x48)")
        if lighting is not None and lighting not in LIGHTINGS:
            raise ConfigError(f"lighting must be one of {LIGHTINGS}, got {lighting!r}")
        if fps is not None and not (0 < fps <= 240):
            raise ConfigError(f"fps must be in (0, 240], got {fps}")
        if not 0.0 <= night_fraction <= 1.0:
            raise ConfigError(f"night_fraction must be in [0, 1], got {night_fraction}")
        self.seed = int(seed)
        self.width, self.height = int(width), int(height)
        self._overrides = overrides
        rng = np.random.default_rng([self.seed, 0x5CE7E])
        self.fps = float(fps) if fps is not None else float(rng.uniform(10.0, 30.0))
        if lighting is None:
            r = rng.random()
            lighting = "night" if r < night_fraction else ("dusk" if r < night_fraction + 0.25 * (1 - night_fraction) else "day")
        self.lighting = lighting
        vehicles_o = overrides.get("vehicles") or []
        if n_vehicles is None:
            n_vehicles = len(vehicles_o) if vehicles_o else int(rng.integers(3, 7))
        if n_vehicles < 0:
            raise ConfigError(f"n_vehicles must be >= 0, got {n_vehicles}")
        self.n_vehicles = int(n_vehicles)
        self.start_ns = int(1_700_000_000_000_000_000 + int(rng.integers(0, 10 ** 16)))
        family = overrides.get("family")
        if family is None:  # its own stream, so that the other draws stay as they were
            family = TRAIN_FAMILIES[int(np.random.default_rng([self.seed, 0xFA]).integers(len(TRAIN_FAMILIES)))]
        if family not in STYLE_FAMILIES:
            raise ConfigError(f"family must be one of {STYLE_FAMILIES}, got {family!r}")
        self.family = int(family)

    # ------------------------------------------------------------------ setup
    def _setup(self) -> None:
        """(Re)build the world so that every call of ``frames`` starts from the same state."""
        o = self._overrides
        rng = np.random.default_rng([self.seed, 1])
        W, H = self.width, self.height
        f = W * float(o.get("focal", rng.uniform(0.75, 1.3)))
        hy = H * float(o.get("horizon", rng.uniform(0.36, 0.5)))
        vx = W * rng.uniform(0.35, 0.65)
        cam_h = rng.uniform(1.2, 1.7)
        lane_w = rng.uniform(2.9, 3.7)
        n_left, n_right = int(rng.integers(1, 4)), int(rng.integers(1, 4))
        self._geo = StreetGeometry(f, cam_h, hy, vx, -n_left * lane_w + rng.uniform(-0.5, 0.5),
                                   n_right * lane_w + rng.uniform(-0.5, 0.5), lane_w)
        self._light: Lighting = sample_lighting(rng, self.lighting)
        weather = o.get("weather") or str(rng.choice(["clear", "clear", "clear", "rain", "haze"]))
        if weather not in ("clear", "rain", "haze"):
            raise ConfigError(f"weather must be clear, rain or haze, got {weather!r}")
        self._env = Environment(np.random.default_rng([self.seed, 2]), W, H, _MARGIN, self._geo, self._light,
                                distractors=bool(o.get("distractors", True)), weather=weather, n_poles=o.get("poles"))
        for rect in o.get("occluders") or []:
            x0, y0, x1, y1 = (float(v) for v in rect)
            self._env.occluders.append(Occluder(0, 0, 0, 0, 0, (90, 90, 90), rect=(x0, y0, x1, y1)))
        self._wet = weather == "rain" or (self.lighting != "day" and rng.random() < 0.3)
        cam_params = sample_camera(rng, self._light.noise, self.lighting, weather, self.family)
        if not o.get("shake", True):
            cam_params.shake = 0.0
        self._camera = Camera(cam_params, W, H, hy, self.seed * 7 + 3, enabled=bool(o.get("effects", True)))
        LOG.debug("scene seed=%d %dx%d fps=%.1f lighting=%s weather=%s focal=%.0f horizon=%.0f vehicles=%d",
                  self.seed, W, H, self.fps, self.lighting, weather, f, hy, self.n_vehicles)
        self._traffic = Traffic(self.seed, rng, W, self._geo, self._light, self.lighting, self.family)
        vo = o.get("vehicles") or []
        for i in range(self.n_vehicles):
            self._traffic.vehicles.append(self._traffic.spawn(vo[i] if i < len(vo) else {}, entering=False))
        self._painter = VehiclePainter(W, H, self._geo, self._light, self.lighting, self._wet)

    # ------------------------------------------------------------------ rendering
    def frames(self, n_frames: int) -> Iterator[RenderedFrame]:
        """Render ``n_frames`` consecutive frames (each call starts the same sequence again).

        Args:
            n_frames: Number of frames to render.

        Yields:
            One ``RenderedFrame`` per frame.
        """
        if n_frames < 0:
            raise ConfigError(f"n_frames must be >= 0, got {n_frames}")
        self._setup()
        dt = 1.0 / self.fps
        for index in range(n_frames):
            t = index * dt
            if index > 0:
                self._traffic.step(dt, bool(self._overrides.get("respawn", True)))
            yield self._render(index, t)

    def _render(self, index: int, t: float) -> RenderedFrame:
        W, H = self.width, self.height
        frng = np.random.default_rng([self.seed, 3, index])
        cam = self._camera
        shake = cam.p.shake if cam.enabled else 0.0
        sx = int(np.clip(round(_MARGIN + shake * math.sin(t * 7.3 + self.seed) + frng.normal(0, shake * 0.3)), 0, 2 * _MARGIN))
        sy = int(np.clip(round(_MARGIN + shake * math.sin(t * 5.1 + 1.7 * self.seed) + frng.normal(0, shake * 0.3)), 0, 2 * _MARGIN))
        img = self._env.background[sy:sy + H, sx:sx + W].copy()
        layer = np.zeros(((H + GLOW_SCALE - 1) // GLOW_SCALE, (W + GLOW_SCALE - 1) // GLOW_SCALE, 3), np.float32)
        ddx, ddy = sx - _MARGIN, sy - _MARGIN
        self._env.draw_lights(img, layer, t, ddx, ddy)

        # Bodies first (in any order), then visibility near-to-far, then lamps, then compositing far-to-near.
        drawn: List[Drawn] = []
        for v in self._traffic.vehicles:
            d = self._painter.body(v, self._traffic.project(v), ddx, ddy, layer)
            if d is not None:
                drawn.append(d)
        coverage = np.zeros((H, W), np.uint8)
        occ_x = [self._env.occluder_x(o, t) for o in self._env.occluders]
        for o, x in zip(self._env.occluders, occ_x):
            o.draw(coverage, x - ddx, ddy, value=255)
        drawn.sort(key=lambda d: d.v.Z)
        for d in drawn:
            x0, y0, x1, y1 = d.roi
            cov = coverage[y0:y1, x0:x1]
            sil = d.alpha > 127
            d.vis = sil & (cov == 0)
            cov[sil] = 255
        truths: List[VehicleTruth] = []
        for d in drawn:
            tr = self._lamps_and_truth(d, t, layer, frng)
            if tr is not None:
                truths.append(tr)
        self._painter.composite(img, drawn)
        for o, x in zip(self._env.occluders, occ_x):
            o.draw(img, x - ddx, ddy)
        rain = self._env.rain_slice(t)
        if rain is not None:
            img = cv2.add(img, rain)
        img = cv2.add(img, blur_glow(layer, W, H, 0.5 if self.lighting == "day" else 1.0))
        img = cam.apply(img, t, frng)
        # Listing order follows the vehicle list (stable), not depth.
        order = {v.track_id: i for i, v in enumerate(self._traffic.vehicles)}
        truths.sort(key=lambda tr: order.get(tr.track_id, 0))
        stamp = self.start_ns + int(round(index * 1e9 / self.fps))
        return RenderedFrame(index=index, stamp_ns=stamp, image=img, vehicles=truths, lighting=self.lighting)

    def _lamp_levels(self, v: Vehicle, t: float) -> Tuple[List[List[float]], bool, bool, bool, bool]:
        """Brightness of every lamp segment at time ``t`` plus (brake, left active, right
        active, flasher in its lit half)."""
        st = v.style
        state, start = v.blinker.segment(t)
        brake = bool(v.brake.segment(t)[0])
        left_on = state in (Intent.LEFT, Intent.HAZARD)
        right_on = state in (Intent.RIGHT, Intent.HAZARD)
        # A flasher starts lit when switched on; a signal held for the whole sequence
        # (override) runs with the vehicle's phase instead.
        t_act = t + v.phase if start < -1e8 else t - start
        exp_s = self._light.exposure_s
        flash_lit = flasher_level(t_act, st, exp_s) >= 0.5
        tail = st.tail_level if v.lights_on else 0.0
        night = self.lighting != "day"
        levels: List[List[float]] = []
        for lamp, polys in zip(v.lamps, v.lamp_polys):
            active = (lamp.side == "L" and left_on) or (lamp.side == "R" and right_on)
            role = lamp.role
            if role == "tail":
                lev = (1.0 if brake and lamp.side != "C" else tail)
                levels.append([lev])
            elif role == "chmsl":
                levels.append([1.0 if brake else 0.0])
            elif role == "turn":
                if not active:
                    levels.append([0.0] * len(polys))
                elif len(polys) > 1:
                    step = st.duty / st.blink_hz * st.seq_fraction / len(polys)
                    levels.append([flasher_level(t_act, st, exp_s, delay=k * step) for k in range(len(polys))])
                else:
                    levels.append([flasher_level(t_act, st, exp_s)])
            elif role == "turn_tail":
                base = 1.0 if brake else tail
                if active:
                    low = st.combined_dim if brake else tail
                    levels.append([low + (1.0 - low) * flasher_level(t_act, st, exp_s)])
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
        return levels, brake, left_on, right_on, flash_lit

    def _lamp_visibility(self, d: Drawn) -> Tuple[List[float], List[Tuple[str, str, float]]]:
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

    def _lamps_and_truth(self, d: Drawn, t: float, layer: np.ndarray, frng: np.random.Generator) -> Optional[VehicleTruth]:
        v = d.v
        rx0, ry0, rx1, ry1 = d.roi
        levels, brake, left_on, right_on, flash_lit = self._lamp_levels(v, t)
        fracs, seen = self._lamp_visibility(d)
        self._painter.lamps(d, levels, fracs, layer)
        # Labels.
        ys, xs = np.nonzero(d.vis)
        if len(xs) == 0:
            return None
        bx0, by0 = float(xs.min() + rx0), float(ys.min() + ry0)
        bx1, by1 = float(xs.max() + rx0 + 1), float(ys.max() + ry0 + 1)
        occlusion = float(np.clip(1.0 - len(xs) / d.full_area, 0.0, 1.0))
        if bx1 - bx0 < MIN_LISTED_PX or by1 - by0 < MIN_LISTED_PX or occlusion > MAX_LISTED_OCCLUSION:
            return None
        min_px = max(LAMP_MIN_PIXELS, LAMP_MIN_BOX_SHARE * max(bx1 - bx0, by1 - by0) ** 2)
        visible = {"L": False, "R": False, "brake": False}
        for role, side, pixels in seen:
            if pixels < min_px:
                continue
            if role in ("turn", "turn_tail") and side in ("L", "R"):
                visible[side] = True
            # The centre brake lamp shows the brake on its own; a centre tail bar does not
            # (it never brightens on braking).
            if role == "chmsl" or (role in ("tail", "turn_tail") and side != "C"):
                visible["brake"] = True
        left = _light_status(left_on, visible["L"])
        right = _light_status(right_on, visible["R"])
        brake_s = _light_status(brake, visible["brake"])
        # What a single frame shows: a blinker in its dark half looks like one switched off.
        left_lit = _light_status(left_on and flash_lit, visible["L"])
        right_lit = _light_status(right_on and flash_lit, visible["R"])
        class_id = CLASS_IDS[v.kind]
        tracker = tracker_box(v, (bx0, by0, bx1, by1), d.box, self.width, self.height, class_id, frng)
        return VehicleTruth(track_id=v.track_id, box=(bx0, by0, bx1, by1), tracker_box=tracker, brake=brake_s, left=left,
                            right=right, intent=intent_from_lights(left, right), view=v.view, occlusion=occlusion, kind=v.kind,
                            lamp_design=v.style.design, class_id=class_id, left_lit=left_lit, right_lit=right_lit)
