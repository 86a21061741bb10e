"""The evaluation scene: an urban road in 3D seen by a moving pinhole camera, with
vehicles ahead (seen from behind), oncoming (front, then side as they pass), crossing at
an intersection (sides) and parked with hazards; ground truth from the lamps' visibility.

Per frame: road and buildings, then every object far to near (painter's order) into a
linear radiance buffer with an id buffer, lamp truth from the id buffer, tracker boxes
with correlated jitter and misses, and finally the sensor model (``camera.develop``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Iterator, List, Optional, Tuple

import cv2
import numpy as np

from signal_light_node.boxes import TrackBox
from signal_light_node.errors import ConfigError
from signal_light_node.evalgen.camera import (NEAR_M, PinholeCamera, develop, sample_camera,
                                              sample_sensor)
from signal_light_node.evalgen.config import SceneConfig
from signal_light_node.evalgen.draw import (Canvas, add_emission, add_glow, fill_gradient,
                                            visible_fraction)
from signal_light_node.evalgen.models import (AMBER, CLASS_OF_KIND, FACE_NORMALS, FACES, LENS, RED,
                                              WHITE, Lamp, Solid, VehicleModel, lamp_points)
from signal_light_node.evalgen.tracker import tracker_box
from signal_light_node.evalgen.traffic import Actor, Traffic
from signal_light_node.labels import Intent, LightStatus, View, intent_from_lights

_START_NS = 1_760_000_000 * 1_000_000_000
_OCCLUDER = -2


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


@dataclass
class _Env:
    """Illumination of the scene."""

    night: bool
    sun: np.ndarray
    sun_level: float
    sky_level: float
    wet: float
    sky_top: Tuple[float, float, float]
    sky_horizon: Tuple[float, float, float]
    asphalt: Tuple[float, float, float]


@dataclass
class _Drawn:
    """What drawing one vehicle produced, for the ground truth."""

    box: Tuple[float, float, float, float]
    hull_area: float
    lamps: List[Tuple[Lamp, np.ndarray, float]]


def _upright_rect(x: float, z: float, half: float, y0: float, y1: float) -> np.ndarray:
    """A vertical rectangle facing the camera (constant ``z``), ``[4, 3]`` world points."""
    return np.array([(x - half, y0, z), (x + half, y0, z), (x + half, y1, z), (x - half, y1, z)])


def _sample_env(rng: np.random.Generator, night: bool) -> _Env:
    """Sun, sky, road wetness and colours of a day or night scene."""
    az = rng.uniform(-1.2, 1.2)
    el = rng.uniform(0.35, 1.0)
    sun = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
    if night:
        return _Env(True, sun, 0.0, float(rng.uniform(0.004, 0.008)), float(rng.uniform(0.0, 1.0)),
                    (0.003, 0.0015, 0.001), (0.012, 0.01, 0.009), (0.009, 0.009, 0.01))
    haze = float(rng.uniform(0.0, 0.3))
    return _Env(False, sun, float(rng.uniform(0.7, 1.0)), float(rng.uniform(0.35, 0.5)), 0.0,
                (0.75 - 0.3 * haze, 0.45, 0.25 + 0.2 * haze), (0.85, 0.8, 0.72),
                tuple(float(c) for c in rng.uniform(0.16, 0.26) * np.array([1.0, 1.0, 0.97])))


class EvalScene:
    """A generated scene, deterministic from ``seed`` and ``config``.

    Args:
        seed: Random seed.
        config: What to generate.
    """

    def __init__(self, seed: int, config: SceneConfig = SceneConfig()) -> None:
        self.seed = int(seed)
        self.config = config
        rng = np.random.default_rng([self.seed, 7001])
        self.night = config.lighting == "night"
        self.camera: PinholeCamera = sample_camera(rng, config.width, config.height)
        self.sensor = sample_sensor(rng, self.night)
        self.env = _sample_env(rng, self.night)
        self.duration = config.frames / config.fps
        self.times = np.arange(config.frames) / config.fps
        crossing = config.views == "all"
        self.ego_speed = float(rng.uniform(0.0, 1.2) if crossing else rng.uniform(4.0, 9.0))
        self.ego_z = self.ego_speed * self.times
        self.z_int = (float(self.ego_z[-1] + rng.uniform(30.0, 40.0)) if crossing else None)
        self.sway_phase = float(rng.uniform(0, 2 * math.pi))
        self.lanes = [0.0, 3.5] if crossing else [-3.5, 0.0, 3.5]
        self.actors = Traffic(self.seed, config, self.times, self.ego_z, self.ego_speed, self.z_int, self.lanes).cast(rng)
        self.facades = self._facades(rng)
        self.poles = self._poles(rng)
        self.noise_rng = np.random.default_rng([self.seed, 7002])

    # ------------------------------------------------------------------ static world

    def _facades(self, rng: np.random.Generator) -> List[Dict]:
        """Building fronts along both sides, with a gap for the cross street."""
        out = []
        for x in (10.5, -13.5):
            z = float(self.ego_z[0] - 20.0)
            while z < self.ego_z[0] + 260.0:
                length = float(rng.uniform(12.0, 40.0))
                z0, z1 = z, z + length
                if self.z_int is not None and z0 < self.z_int + 7.0 and z1 > self.z_int - 7.0:
                    z = self.z_int + 7.0
                    continue
                albedo = rng.uniform(0.15, 0.55) * rng.uniform(0.8, 1.1, size=3)
                lit = rng.random(200) < 0.3
                out.append({"x": x, "z0": z0, "z1": z1, "h": float(rng.uniform(7.0, 24.0)),
                            "albedo": albedo, "lit": lit, "warm": rng.uniform(0.3, 0.9, size=200)})
                z = z1 + float(rng.uniform(0.0, 4.0))
        return out

    def _poles(self, rng: np.random.Generator) -> List[Dict]:
        """Street lamps, sign posts and the traffic signal at the intersection."""
        out = []
        for x, arm in ((7.7, -1.8), (-9.4, 1.8)):
            z = float(self.ego_z[0] + rng.uniform(4.0, 20.0))
            while z < self.ego_z[0] + 220.0:
                if self.z_int is None or abs(z - self.z_int) > 8.0:
                    out.append({"x": x, "z": z, "arm": arm, "sign": bool(rng.random() < 0.3),
                                "sodium": bool(rng.random() < 0.5), "signal": False})
                z += float(rng.uniform(22.0, 34.0))
        if self.z_int is not None:
            out.append({"x": 7.7, "z": self.z_int - 7.5, "arm": 0.0, "sign": False, "sodium": False,
                        "signal": True})
        return out

    # ------------------------------------------------------------------ rendering

    def _project(self, pts: np.ndarray, k: int) -> Tuple[np.ndarray, np.ndarray]:
        """World points to pixels and depths in frame ``k``."""
        return self.camera.project(pts, float(self.ego_z[k]), self._sway(k))

    def _sway(self, k: int) -> float:
        """Pitch of the ego car's ride in frame ``k`` (rad)."""
        t = float(self.times[k])
        return 0.004 * math.sin(2 * math.pi * 0.7 * t + self.sway_phase) + 0.002 * math.sin(5.3 * t)

    def _ground_poly(self, k: int, x0: float, x1: float, z0: float, z1: float, y: float = 0.0
                     ) -> Optional[np.ndarray]:
        """A strip of ground ``x0..x1`` by ``z0..z1`` in pixels, or None if behind the camera."""
        ez = float(self.ego_z[k])
        z0, z1 = max(z0, ez + 1.0), min(z1, ez + 900.0)
        if z1 <= z0:
            return None
        zs = np.linspace(z0, z1, 6)
        pts = np.array([(x0, y, z) for z in zs] + [(x1, y, z) for z in zs[::-1]])
        uv, depth = self._project(pts, k)
        return uv if np.all(depth > NEAR_M) else None

    def _shade(self, albedo: np.ndarray, normal: np.ndarray, k: int, depth: float) -> np.ndarray:
        """Radiance of a surface: sky and sun by day; low beams and street light by night."""
        env = self.env
        sky = env.sky_level * (0.55 + 0.45 * max(normal[1], 0.0))
        sun = env.sun_level * max(float(np.dot(normal, env.sun)), 0.0)
        light = sky + sun
        if env.night:  # the ego car's low beams on nearby rear faces, street lamps
            light += 0.05 * min(1.0, (12.0 / max(depth, 1.0)) ** 2) * max(-normal[2], 0.0) + 0.004
        return np.asarray(albedo, np.float32) * np.float32(light)

    def _background(self, canvas: Canvas, k: int) -> None:
        """Sky, ground, kerbs, road, cross street, markings and light pools."""
        env = self.env
        far_point = np.array([[0.0, self.camera.mount_height, self.ego_z[k] + 1e5]])
        horizon = self._project(far_point, k)[0][0, 1]
        rows = np.clip(np.arange(canvas.height, dtype=np.float32) / max(horizon, 1.0), 0.0, 1.0)
        top, hor = np.asarray(env.sky_top, np.float32), np.asarray(env.sky_horizon, np.float32)
        canvas.rgb[:] = (top * (1 - rows[:, None]) + hor * rows[:, None])[:, None, :]
        far = 900.0 + self.ego_z[k]
        shade = 1.0 if not env.night else 0.08
        grass = np.array([0.12, 0.2, 0.18]) * shade
        kerb_r, kerb_l = np.array([0.38, 0.39, 0.4]) * shade, np.array([0.36, 0.37, 0.38]) * shade
        for x0, x1, z0, z1, colour in ((-400.0, 400.0, 0.0, far, grass),
                                       (7.0, 10.5, 0.0, far, kerb_r),
                                       (-13.5, -8.75, 0.0, far, kerb_l),
                                       (-8.75, 7.0, 0.0, far, np.asarray(env.asphalt))):
            poly = self._ground_poly(k, x0, x1, z0, z1)
            if poly is not None:
                near = np.asarray(colour, np.float32)
                fill_gradient(canvas, poly, near * 0.9 + hor * 0.1, near * 0.8)
        if self.z_int is not None:
            poly = self._ground_poly(k, -400.0, 400.0, self.z_int - 6.0, self.z_int + 6.0)
            if poly is not None:
                a = np.asarray(env.asphalt, np.float32)
                fill_gradient(canvas, poly, a, a)
        self._markings(canvas, k)
        if env.night:
            self._light_pools(canvas, k)

    def _markings(self, canvas: Canvas, k: int) -> None:
        """Lane lines (solid, dashed, double yellow) and the stop line."""
        bright = 0.7 if not self.env.night else 0.12
        white = (bright, bright, bright)
        yellow = (0.05, bright * 0.7, bright * 0.9)
        ez = float(self.ego_z[k])
        stop = self.z_int - 7.0 if self.z_int is not None else np.inf
        solid = [(5.25, white), (-8.6, white)] + ([(-1.65, yellow), (-1.85, yellow)]
                                                  if self.config.views == "all" else [])
        for x, colour in solid:
            poly = self._ground_poly(k, x - 0.07, x + 0.07, ez, min(stop, ez + 400.0))
            if poly is not None:
                fill_gradient(canvas, poly, colour, colour)
        dashed = [1.75, -5.25] if self.config.views == "all" else [1.75, -1.75, -5.25]
        first = math.floor(ez / 9.0) * 9.0
        for x in dashed:
            for z in np.arange(first, min(ez + 130.0, stop), 9.0):
                poly = self._ground_poly(k, x - 0.07, x + 0.07, z, z + 3.0)
                if poly is not None:
                    fill_gradient(canvas, poly, white, white)
        if self.z_int is not None:
            poly = self._ground_poly(k, -1.6, 5.2, stop, stop + 0.5)
            if poly is not None:
                fill_gradient(canvas, poly, white, white)

    def _light_pools(self, canvas: Canvas, k: int) -> None:
        """Pools of street light on the road at night."""
        for pole in self.poles:
            if pole["signal"]:
                continue
            x = pole["x"] + pole["arm"]
            uv, depth = self._project(np.array([[x, 0.0, pole["z"]]]), k)
            if depth[0] < 2.0 or depth[0] > 150.0:
                continue
            f = self.camera.focal
            colour = (0.25, 0.6, 1.0) if pole["sodium"] else (0.9, 0.95, 1.0)
            add_glow(canvas, uv[0], (f * 4.0 / depth[0], f * 1.2 / depth[0]), colour, 0.03)

    def _draw_facade(self, canvas: Canvas, fac: Dict, k: int) -> None:
        """One building front with its windows (lit at random by night)."""
        x, h = fac["x"], fac["h"]
        z0, z1 = max(fac["z0"], self.ego_z[k] + 1.0), fac["z1"]
        if z1 <= z0:
            return
        pts = np.array([(x, 0.0, z0), (x, 0.0, z1), (x, h, z1), (x, h, z0)])
        uv, depth = self._project(pts, k)
        if np.any(depth < NEAR_M):
            return
        normal = np.array([-math.copysign(1.0, x), 0.0, 0.0])
        c = self._shade(fac["albedo"], normal, k, 50.0)
        fill_gradient(canvas, uv, c * 1.05, c * 0.8, obj_id=_OCCLUDER)
        nearest = float(depth.min())
        if nearest > 120.0:
            return
        glass = np.array([0.08, 0.07, 0.06]) * (1.0 if not self.env.night else 0.2)
        i = 0
        for floor_y in np.arange(3.0, h - 1.5, 3.2):
            for wz in np.arange(fac["z0"] + 1.5, fac["z1"] - 1.5, 3.0):
                i += 1
                if wz < self.ego_z[k] + 2.0:
                    continue
                wp = np.array([(x, floor_y, wz), (x, floor_y, wz + 1.4),
                               (x, floor_y + 1.5, wz + 1.4), (x, floor_y + 1.5, wz)])
                wuv, wd = self._project(wp, k)
                if np.any(wd < NEAR_M) or np.ptp(wuv[:, 0]) < 1.5:
                    continue
                sky = np.asarray(self.env.sky_horizon, np.float32) * 0.5
                fill_gradient(canvas, wuv, glass + sky, glass, obj_id=_OCCLUDER)
                if self.night and fac["lit"][i % 200]:
                    warm = 0.2 * float(fac["warm"][i % 200])
                    add_emission(canvas, wuv, (0.35, 0.65, 1.0), warm, core=0.8)

    def _draw_pole(self, canvas: Canvas, pole: Dict, k: int) -> None:
        """A pole with its arm, sign, lamp head or traffic signal."""
        x, z = pole["x"], pole["z"]
        height = 6.0 if pole["signal"] else 7.5
        w = 0.09
        grey = np.array([0.25, 0.25, 0.26]) * (1.0 if not self.night else 0.05)
        pts = np.array([(x - w, 0.0, z), (x + w, 0.0, z), (x + w, height, z), (x - w, height, z)])
        uv, depth = self._project(pts, k)
        if np.any(depth < 1.5):
            return
        fill_gradient(canvas, uv, grey * 1.2, grey * 0.7, obj_id=_OCCLUDER)
        ax = x + pole["arm"]
        if pole["arm"]:
            arm = np.array([(min(x, ax), height - 0.1, z), (max(x, ax), height - 0.1, z),
                            (max(x, ax), height, z), (min(x, ax), height, z)])
            fill_gradient(canvas, self._project(arm, k)[0], grey, grey, obj_id=_OCCLUDER)
        if pole["sign"]:
            sp = _upright_rect(x, z - 0.02, 0.45, 2.3, 3.0)
            blue = np.array([0.55, 0.25, 0.05]) * (1.0 if not self.night else 0.15)
            fill_gradient(canvas, self._project(sp, k)[0], blue, blue * 0.8, obj_id=_OCCLUDER)
        if pole["signal"]:
            box = _upright_rect(x, z - 0.05, 0.18, 4.6, 5.6)
            buv = self._project(box, k)[0]
            fill_gradient(canvas, buv, (0.03, 0.03, 0.03), (0.02, 0.02, 0.02), obj_id=_OCCLUDER)
            t = np.linspace(0, 2 * math.pi, 12, endpoint=False)
            lens = np.stack([x + 0.11 * np.cos(t), 5.38 + 0.11 * np.sin(t),
                             np.full(12, z - 0.07)], axis=1)
            add_emission(canvas, self._project(lens, k)[0], RED, 6.0 if self.night else 2.5)
        elif self.night:
            t = np.linspace(0, 2 * math.pi, 10, endpoint=False)
            head = np.stack([ax + 0.35 * np.cos(t), height - 0.15 + 0.08 * np.sin(t),
                             np.full(10, z)], axis=1)
            colour = (0.25, 0.6, 1.0) if pole["sodium"] else (0.9, 0.95, 1.0)
            add_emission(canvas, self._project(head, k)[0], colour, 5.0)

    # ------------------------------------------------------------------ vehicles

    def _lamp_emission(self, actor: Actor, lamp: Lamp, t: float
                       ) -> Tuple[Tuple[float, float, float], float]:
        """Colour and radiance of a lens at time ``t``."""
        sig, lv = actor.signals, actor.levels
        tail = lv["tail"] if sig.lights_on else 0.0
        braking = sig.braking(t)
        active = lamp.side != 0 and sig.active(lamp.side, t) is not None
        flash = sig.flash_level(lamp.side, t, self.sensor.exposure_s) if active else 0.0
        blink_colour = AMBER if lamp.blink_colour == "amber" else RED
        funcs = lamp.funcs
        if "head" in funcs:
            return WHITE, lv["head"] if sig.lights_on else 0.0
        if "drl" in funcs:
            if active:
                return AMBER, lv["blink"] * flash
            return WHITE, lv["drl"] if actor.model.drl else 0.0
        steady = max(tail if "tail" in funcs else 0.0,
                     lv["brake"] if ("brake" in funcs and braking) else 0.0)
        if "blink" in funcs and active:
            peak = max(lv["blink"], steady)
            if "tail" in funcs or "brake" in funcs:  # combined red lamp: flashes over the tail
                return RED, tail + (peak - tail) * flash
            return blink_colour, lv["blink"] * flash
        return RED, steady

    def _to_world(self, pts: np.ndarray, x: float, z: float, yaw: float) -> np.ndarray:
        """Vehicle-frame ``(a, b, y)`` points to world ``(X, Y, Z)``."""
        a, b, y = pts[:, 0], pts[:, 1], pts[:, 2]
        s, c = math.sin(yaw), math.cos(yaw)
        return np.stack([x + a * s - b * c, y, z + a * c + b * s], axis=1)

    def _draw_vehicle(self, canvas: Canvas, actor: Actor, k: int, obj_id: int) -> Optional[_Drawn]:
        """Shadow, solids and lamps of one vehicle; None when too near to draw."""
        x, z, yaw = float(actor.x[k]), float(actor.z[k]), float(actor.yaw[k])
        model, t = actor.model, float(self.times[k])
        cam = np.array([0.0, self.camera.mount_height, self.ego_z[k]])
        all_pts = np.concatenate([s.vertices() for s in model.solids])
        world = self._to_world(all_pts, x, z, yaw)
        uv, depth = self._project(world, k)
        if np.any(depth < NEAR_M + 1.0):
            return None
        la, hw = model.length / 2 + 0.25, model.width / 2 + 0.2
        footprint = np.array([(-la, -hw, 0.01), (la, -hw, 0.01), (la, hw, 0.01), (-la, hw, 0.01)])
        shadow = self._project(self._to_world(footprint, x, z, yaw), k)[0]
        black = (0.01, 0.01, 0.01)
        fill_gradient(canvas, shadow, black, black, alpha=0.6)
        for group in self._solid_groups(model, x, z, yaw, cam):
            for solid in group:
                self._draw_solid(canvas, solid, actor, x, z, yaw, cam, k, obj_id)
        lamps = self._draw_lamps(canvas, actor, x, z, yaw, cam, k, obj_id, t)
        hull = cv2.convexHull(uv.astype(np.float32))
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        box = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
        return _Drawn(box, float(cv2.contourArea(hull)), lamps)

    def _solid_groups(self, model: VehicleModel, x: float, z: float, yaw: float,
                      cam: np.ndarray) -> List[List[Solid]]:
        """Solids in drawing order: tyres, then the cab/body and cargo groups far to near."""
        tyres = [s for s in model.solids if s.part == "tyre"]
        body = [s for s in model.solids if s.part not in ("cargo", "tyre")]
        cargo = [s for s in model.solids if s.part == "cargo"]

        def distance(group: List[Solid]) -> float:
            centre = np.mean([s.vertices().mean(axis=0) for s in group], axis=0)[None]
            return float(np.linalg.norm(self._to_world(centre, x, z, yaw)[0] - cam))

        return [tyres] + sorted([g for g in (body, cargo) if g], key=lambda g: -distance(g))

    def _draw_solid(self, canvas: Canvas, solid: Solid, actor: Actor, x: float, z: float,
                    yaw: float, cam: np.ndarray, k: int, obj_id: int) -> None:
        """The faces of one solid that face the camera, gradient-shaded; cabins glazed."""
        verts = self._to_world(solid.vertices(), x, z, yaw)
        middle = verts.mean(axis=0)
        paint = np.asarray(actor.model.paint, np.float32)
        albedo = np.array([0.03, 0.03, 0.03]) if solid.part == "tyre" else paint
        if solid.part == "cargo":
            albedo = np.array([0.62, 0.62, 0.6])
        for name, idx in FACES.items():
            quad = verts[list(idx)]
            fc = quad.mean(axis=0)
            n = np.cross(quad[1] - quad[0], quad[3] - quad[0])
            n /= max(np.linalg.norm(n), 1e-9)
            if np.dot(n, fc - middle) < 0:
                n = -n
            to_cam = cam - fc
            if np.dot(n, to_cam) <= 0:
                continue
            dist = float(np.linalg.norm(to_cam))
            colour = self._shade(albedo, n, k, dist)
            uv = self._project(quad, k)[0]
            fill_gradient(canvas, uv, colour * 1.12, colour * 0.72, obj_id=obj_id)
            if solid.part == "cabin" and name != "top":
                self._glass(canvas, quad, fc, n, actor, k, obj_id)

    def _glass(self, canvas: Canvas, quad: np.ndarray, fc: np.ndarray, n: np.ndarray,
               actor: Actor, k: int, obj_id: int) -> None:
        """The glazed inset of a cabin face: dark glass reflecting the sky, maybe a glint."""
        inner = fc + (quad - fc) * np.array([0.86, 0.8, 0.86])
        uv = self._project(inner, k)[0]
        sky = np.asarray(self.env.sky_horizon, np.float32)
        refl = 0.25 * sky * (0.5 + 0.5 * max(n[1], 0.0))
        dark = np.array([0.02, 0.02, 0.025], np.float32)
        fill_gradient(canvas, uv, dark + refl, dark + refl * 0.15, obj_id=obj_id)
        if not self.night and actor.glint:
            c = uv.mean(axis=0) + np.array([0.0, -0.25]) * np.ptp(uv[:, 1])
            r = max(np.ptp(uv[:, 0]) * 0.08, 1.0)
            add_glow(canvas, c, (r * 2.5, r * 0.6), (1.0, 1.0, 1.0), 0.5 * self.env.sun_level)

    def _draw_lamps(self, canvas: Canvas, actor: Actor, x: float, z: float, yaw: float,
                    cam: np.ndarray, k: int, obj_id: int, t: float
                    ) -> List[Tuple[Lamp, np.ndarray, float]]:
        """Housings, lenses and light of the lamps facing the camera; ``(lamp, uv, cos)``."""
        out = []
        model = actor.model
        for lamp in model.lamps:
            n_v = np.array(FACE_NORMALS[lamp.face])
            n = self._to_world(n_v[None], 0.0, 0.0, yaw)[0]
            pts = self._to_world(lamp_points(model, lamp), x, z, yaw)
            centre = pts.mean(axis=0)
            to_cam = cam - centre
            cos = float(np.dot(n, to_cam) / max(np.linalg.norm(to_cam), 1e-9))
            if cos <= 0.02:
                continue
            uv = self._project(pts, k)[0]
            housing = uv.mean(axis=0) + (uv - uv.mean(axis=0)) * 1.18
            fill_gradient(canvas, housing, (0.02, 0.02, 0.02), (0.01, 0.01, 0.01), obj_id=obj_id)
            lens = self._shade(np.asarray(LENS[lamp.lens]), n, k, float(np.linalg.norm(to_cam)))
            fill_gradient(canvas, uv, lens * 1.4, lens * 0.8, obj_id=obj_id)
            colour, level = self._lamp_emission(actor, lamp, t)
            if level > 0:
                add_emission(canvas, uv, colour, level * (0.35 + 0.65 * cos))
                if self.env.wet > 0.3 and level > 0.5:
                    self._reflection(canvas, pts, uv, colour, level * self.env.wet, k)
            out.append((lamp, uv, cos))
        return out

    def _reflection(self, canvas: Canvas, pts: np.ndarray, uv: np.ndarray,
                    colour: Tuple[float, float, float], level: float, k: int) -> None:
        """A lamp's stretched reflection on the wet road below it."""
        mirrored = pts.mean(axis=0) * np.array([1.0, -1.0, 1.0])
        muv, depth = self._project(mirrored[None], k)
        if depth[0] < NEAR_M:
            return
        rx = max(np.ptp(uv[:, 0]) * 0.45, 1.0)
        add_glow(canvas, muv[0], (rx, rx * 4.0), colour, 0.08 * level)

    # ------------------------------------------------------------------ truth

    def _view(self, actor: Actor, k: int) -> View:
        """Face of the vehicle toward the camera, in 90-degree sectors."""
        yaw = float(actor.yaw[k])
        d = np.array([0.0 - actor.x[k], self.ego_z[k] - actor.z[k]])  # (X, Z) to the camera
        fwd = np.array([math.sin(yaw), math.cos(yaw)])
        left = np.array([-math.cos(yaw), math.sin(yaw)])
        ang = math.degrees(math.atan2(float(d @ left), float(d @ fwd)))
        if abs(ang) <= 45.0:
            return View.FRONT
        if abs(ang) >= 135.0:
            return View.BEHIND
        return View.LEFT if ang > 0 else View.RIGHT

    def _truth(self, canvas: Canvas, actor: Actor, drawn: _Drawn, k: int, obj_id: int
               ) -> Tuple[LightStatus, LightStatus, LightStatus, View]:
        """Brake, left, right and view of one vehicle from what the id buffer shows."""
        view = self._view(actor, k)
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
        t = float(self.times[k])
        sig = actor.signals

        def status(key: object, hidden: bool, on: bool) -> LightStatus:
            if hidden or seen[key] < threshold:
                return LightStatus.UNKNOWN
            return LightStatus.ON if on else LightStatus.OFF

        brake = status("brake", view == View.FRONT, sig.braking(t))
        left = status(1, view == View.RIGHT, sig.active(1, t) is not None)
        right = status(-1, view == View.LEFT, sig.active(-1, t) is not None)
        return brake, left, right, view

    # ------------------------------------------------------------------ frames

    def render(self, k: int) -> EvalFrame:
        """Render frame ``k`` (0-based) with its truth.

        Raises:
            ConfigError: ``k`` out of range.
        """
        if not 0 <= k < self.config.frames:
            raise ConfigError(f"frame {k} out of range 0..{self.config.frames - 1}")
        canvas = Canvas(self.config.width, self.config.height)
        self._background(canvas, k)
        ez = float(self.ego_z[k])
        items: List[Tuple[float, str, object]] = []
        for i, actor in enumerate(self.actors):
            if np.isnan(actor.z[k]):
                continue
            depth = math.hypot(actor.x[k], actor.z[k] - ez)
            if actor.z[k] - ez > 2.0 and depth < 160.0:
                items.append((depth, "vehicle", i))
        for fac in self.facades:
            items.append((math.hypot(fac["x"], max(fac["z0"] - ez, 1.0)), "facade", fac))
        for pole in self.poles:
            if pole["z"] - ez > 1.0:
                items.append((math.hypot(pole["x"], pole["z"] - ez), "pole", pole))
        items.sort(key=lambda it: -it[0])
        drawn: Dict[int, _Drawn] = {}
        for _, what, obj in items:
            if what == "vehicle":
                out = self._draw_vehicle(canvas, self.actors[obj], k, obj)
                if out is not None:
                    drawn[obj] = out
            elif what == "facade":
                self._draw_facade(canvas, obj, k)
            else:
                self._draw_pole(canvas, obj, k)
        truths = self._truths(canvas, drawn, k)
        image = develop(canvas.rgb, self.sensor, self.noise_rng)
        stamp = _START_NS + self.seed % 1000 * 1_000_000_000 + int(round(k * 1e9 / self.config.fps))
        return EvalFrame(k, stamp, image, truths, self.config.lighting)

    def _truths(self, canvas: Canvas, drawn: Dict[int, _Drawn], k: int) -> List[VehicleTruth]:
        """Truth of every drawn vehicle, far to near."""
        out = []
        t = float(self.times[k])
        exposure = self.sensor.exposure_s
        def distance(j: int) -> float:
            return math.hypot(self.actors[j].x[k], self.actors[j].z[k] - self.ego_z[k])

        for i in sorted(drawn, key=lambda j: -distance(j)):
            actor, d = self.actors[i], drawn[i]
            seen = float((canvas.ids == i).sum())
            occlusion = float(np.clip(1.0 - seen / max(d.hull_area, 1.0), 0.0, 1.0))
            brake, left, right, view = self._truth(canvas, actor, d, k, i)
            out.append(VehicleTruth(
                actor.track_id, d.box, tracker_box(actor, d.box, occlusion, self.config.width, self.config.height), brake, left, right,
                intent_from_lights(left, right), view, occlusion, actor.model.kind,
                CLASS_OF_KIND[actor.model.kind], actor.signals.flash_level(1, t, exposure),
                actor.signals.flash_level(-1, t, exposure)))
        return out

    def frames(self) -> Iterator[EvalFrame]:
        """Every frame in order."""
        for k in range(self.config.frames):
            yield self.render(k)
