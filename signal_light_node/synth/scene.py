"""The scene renderer: one camera on a street with a handful of vehicles seen from behind,
from the front or from a side, rendered frame by frame with each vehicle's truth.

A ``SceneRenderer`` sets the scene up from its seed and runs each frame; the work is done
by one module per concern:

* ``traffic``: which vehicles there are, where they appear and how they move;
* ``environment``: street background, lighting, distractor lights, weather, occluders;
* ``vehicle_drawing``: bodies, flanks, lamps, shadows and compositing into the frame;
* ``truth``: which lamps are lit and visible, which vehicles are listed, their labels;
* ``tracker``: the box a simulated tracker reports for each listed vehicle;
* ``camera``: exposure, haze, blur, noise and JPEG of the finished frame (and its shake).

Each frame hands back the image with one ``VehicleTruth`` per vehicle that is visible
enough to be listed.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any, Dict, Iterator, List, Optional

import cv2
import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.synth.camera import (Camera, CameraParams, sample_camera,
                                            sample_bloom, sample_night_clip,
                                            sample_streak)
from signal_light_node.synth.environment import (GLOW_SCALE, LIGHTINGS, Environment, Lighting, Occluder, StreetGeometry,
                                                 blur_glow, sample_lighting)
from signal_light_node.synth.foreign_lamps import draw_foreign_lamp
from signal_light_node.synth.lamps import STYLE_FAMILIES, TRAIN_FAMILIES, checked_brake_share
from signal_light_node.synth.lit_maps import draw_lit_map
from signal_light_node.synth.tracker import tracker_box
from signal_light_node.synth.traffic import Traffic
from signal_light_node.synth.truth import (RenderedFrame, VehicleTruth, checked_rule, lamp_states, lamp_visibility, listed_box,
                                          mark_visible, vehicle_truth)
from signal_light_node.synth.vehicle_drawing import Drawn, VehiclePainter

LOG = logging.getLogger(__name__)

_MARGIN = 12
_SCENE_KEYS = {"vehicles", "occluders", "poles", "distractors", "weather", "effects", "shake", "respawn", "horizon", "focal",
               "family", "oblique", "tail_glare", "rear_bar", "wide_truck_lamps", "night_streak",
               "night_clip", "night_bloom", "glare_tail_hot",
               "glare_tail_bright", "foreign_lamp", "foreign_high", "brake_share", "turn_hue",
               "truth_rule"}
_VEHICLE_KEYS = {"view", "kind", "lamp_design", "tech", "chmsl", "intent", "brake", "colour", "lights_on", "center_x",
                 "width_px", "speed", "blink_hz", "duty", "phase", "shear", "roll", "specular", "yaw"}


def _share(overrides: Dict[str, Any], key: str) -> float:
    """A share override (default 0), refused in one line outside [0, 1]."""
    value = float(overrides.get(key, 0.0))
    if not 0.0 <= value <= 1.0:
        raise ConfigError(f"{key} must be a share in [0, 1], got {overrides[key]!r}")
    return value


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
        lit_maps: Give every listed vehicle's truth its ``lit_map`` (``synth.lit_maps``):
            where its signal lamps are lit. The image is the same either way.
        **overrides: Scene controls for tests and tools. Scene keys: ``vehicles`` (list of
            per-vehicle dicts, see below), ``occluders`` (list of static (x0, y0, x1, y1)
            pixel rectangles in front of every vehicle), ``poles`` (number of moving poles),
            ``distractors`` (bool), ``weather`` ("clear", "rain", "haze"), ``effects`` (bool,
            camera noise/blur/JPEG), ``shake`` (bool), ``respawn`` (bool), ``horizon``
            (fraction of the height), ``focal`` (fraction of the width), ``family`` (style
            family of lamp colours and camera tone, ``synth.lamps.STYLE_FAMILIES``; default:
            one of ``TRAIN_FAMILIES`` drawn from the seed), ``oblique`` (share of front and
            rear views drawn turned by 10-40 degrees, foreshortened with their flank in
            view; default 0), ``tail_glare`` (share of lit vehicles in dusk and night
            scenes whose tail lamps are drawn clipped, told from a brake only by its
            larger glow, hotter core and the centre lamp; default 0), ``rear_bar`` (share
            of rear views given a full-width tail bar joining their side clusters, tail
            level only; default 0), ``wide_truck_lamps`` (share of truck and bus rear
            views whose side clusters are drawn as wide as real combination lamps;
            default 0), ``night_streak`` (share of dusk and night scenes whose camera
            smears over-exposed light along its row, ``synth.camera.CameraParams.streak``;
            default 0), ``night_clip`` (share of night scenes whose camera exposes for a
            lit street, 1.8-3.2 times brighter, and turns clipped light white,
            ``synth.camera.CameraParams.white_clip``; default 0), ``night_bloom`` (share
            of dusk and night scenes whose camera spreads over-exposed light into a round
            halo, ``synth.camera.CameraParams.bloom``; default 0), ``glare_tail_hot``
            (share of the ``tail_glare`` vehicles whose tail lamps' core and glow are drawn
            at their brake's colour, ``synth.traffic.Vehicle.tail_hot``; default 0),
            ``glare_tail_bright`` (share of the ``tail_glare`` vehicles whose tail lamps
            shine over the clip as brightly as another vehicle's brake, their own brake
            brighter still, ``synth.traffic.BRIGHT_TAIL_LEVEL``; default 0),
            ``foreign_lamp`` (share of vehicles with a lamp beyond them, over the roof or
            beside, inside their crop, ``synth.foreign_lamps``; default 0),
            ``foreign_high`` (share of those lamps drawn red over the middle of the roof,
            ``synth.foreign_lamps.high_foreign_lamp``; default 0), ``brake_share`` (share
            of the time a brake is pressed and of tracks first seen braking,
            ``synth.lamps.brake_timeline``; default 0: the timeline's own, about 40 %),
            ``turn_hue`` (share of vehicles whose blinkers, and the amber markers that
            match them, shine in a random hue, ``synth.lamps.recolour_turn_lamps``;
            default 0),
            ``truth_rule`` (how large the seen lamps of a light must be for it to be
            labelled, ``synth.truth.TRUTH_RULES``; default "lamp"). Vehicle keys:
            ``view`` (View), ``kind``, ``lamp_design``, ``tech`` ("led"/"bulb"), ``chmsl``,
            ``intent`` (Intent held for the whole sequence), ``brake`` (bool held),
            ``colour`` (BGR), ``lights_on``, ``center_x`` (pixels), ``width_px`` (box width),
            ``speed`` (m/s; 0 = parked), ``blink_hz``, ``duty``, ``phase`` (s), ``shear``,
            ``roll`` (degrees), ``specular`` (bool), ``yaw`` (degrees, front and rear views,
            far end to the image right when positive).

    Raises:
        ConfigError: On an unknown override or a value out of range.
    """

    def __init__(self, seed: int, width: int = 640, height: int = 360, fps: Optional[float] = None,
                 n_vehicles: Optional[int] = None, lighting: Optional[str] = None, night_fraction: float = 0.35,
                 lit_maps: bool = False, **overrides: Any) -> None:
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
        self.lit_maps = bool(lit_maps)
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
        self.oblique = _share(overrides, "oblique")
        self.tail_glare = _share(overrides, "tail_glare")
        self.rear_bar = _share(overrides, "rear_bar")
        self.wide_truck_lamps = _share(overrides, "wide_truck_lamps")
        self.night_streak = _share(overrides, "night_streak")
        self.night_clip = _share(overrides, "night_clip")
        self.night_bloom = _share(overrides, "night_bloom")
        self.glare_tail_hot = _share(overrides, "glare_tail_hot")
        self.glare_tail_bright = _share(overrides, "glare_tail_bright")
        self.foreign_lamp = _share(overrides, "foreign_lamp")
        self.foreign_high = _share(overrides, "foreign_high")
        self.brake_share = checked_brake_share(_share(overrides, "brake_share"))
        self.turn_hue = _share(overrides, "turn_hue")
        self.truth_rule = checked_rule(str(overrides.get("truth_rule", "lamp")))

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
        self._draw_streak(cam_params)
        self._draw_night_clip(cam_params)
        self._draw_bloom(cam_params)
        self._camera = Camera(cam_params, W, H, hy, self.seed * 7 + 3, enabled=bool(o.get("effects", True)))
        LOG.debug("scene seed=%d %dx%d fps=%.1f lighting=%s weather=%s focal=%.0f horizon=%.0f vehicles=%d",
                  self.seed, W, H, self.fps, self.lighting, weather, f, hy, self.n_vehicles)
        self._traffic = Traffic(self.seed, rng, W, self._geo, self._light, self.lighting, self.family,
                                self.oblique, self.tail_glare, self.rear_bar, self.wide_truck_lamps,
                                self.glare_tail_hot, self.glare_tail_bright, self.foreign_lamp,
                                self.foreign_high, self.brake_share, self.turn_hue)
        vo = o.get("vehicles") or []
        for i in range(self.n_vehicles):
            self._traffic.vehicles.append(self._traffic.spawn(vo[i] if i < len(vo) else {}, entering=False))
        self._painter = VehiclePainter(W, H, self._geo, self._light, self.lighting, self._wet)

    def _camera_draw(self, share: float, tag: int, lightings: "tuple[str, ...]"
                     ) -> Optional[np.random.Generator]:
        """The stream of a camera option's own draws when this scene (lit as one of
        ``lightings``) draws the option, with probability ``share``; else None. A stream of
        its own per option, so that every other draw of the scene stays as it was."""
        if share <= 0 or self.lighting not in lightings:
            return None
        rng = np.random.default_rng([self.seed, tag])
        return rng if rng.random() < share else None

    def _draw_streak(self, cam_params: CameraParams) -> None:
        """With probability ``night_streak``, a dusk or night scene's camera draws a glare
        streak."""
        rng = self._camera_draw(self.night_streak, 0x57EA, ("dusk", "night"))
        if rng is not None:
            cam_params.streak, cam_params.streak_len = sample_streak(rng)

    def _draw_bloom(self, cam_params: CameraParams) -> None:
        """With probability ``night_bloom``, a dusk or night scene's camera spreads
        over-exposed light into a round halo."""
        rng = self._camera_draw(self.night_bloom, 0xB100, ("dusk", "night"))
        if rng is not None:
            cam_params.bloom, cam_params.bloom_sigma = sample_bloom(rng)

    def _draw_night_clip(self, cam_params: CameraParams) -> None:
        """With probability ``night_clip``, a night scene's camera exposes for a lit street
        (its lamps saturate) and turns clipped light white."""
        rng = self._camera_draw(self.night_clip, 0xC11F, ("night",))
        if rng is not None:
            gain, cam_params.white_clip = sample_night_clip(rng)
            cam_params.exposure *= gain

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
        mark_visible(drawn, coverage)  # coverage now holds every body and occluder
        for d in drawn:  # beyond every body: the composite below hides what they cover
            if d.v.foreign is not None:
                draw_foreign_lamp(d.v.foreign, d.box, t, img, layer, self._light, coverage)
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

    def _lamps_and_truth(self, d: Drawn, t: float, layer: np.ndarray, frng: np.random.Generator) -> Optional[VehicleTruth]:
        """Draw the lamps of a drawn vehicle and return its truth, None when it is not listed."""
        states = lamp_states(d.v, t, self._light.exposure_s, self.lighting != "day")
        fracs, seen = lamp_visibility(d)
        self._painter.lamps(d, states.levels, fracs, layer)
        listed = listed_box(d)
        if listed is None:
            return None
        box, occlusion = listed
        tracker = tracker_box(d.v, box, d.box, self.width, self.height, frng)
        truth = vehicle_truth(d.v, box, occlusion, states, seen, tracker, self.truth_rule)
        if not self.lit_maps:
            return truth
        lit = states.flash_lit
        lit_map = draw_lit_map(d, states.levels, states.brake, states.left_on and lit,
                                states.right_on and lit)
        return dataclasses.replace(truth, lit_map=lit_map)
