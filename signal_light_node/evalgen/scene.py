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
from signal_light_node.evalgen.camera import (NEAR_M, FrameView, PinholeCamera, develop, sample_camera,
                                              sample_sensor)
from signal_light_node.evalgen.config import SceneConfig
from signal_light_node.evalgen.draw import (Canvas, add_emission, add_glow, fill_gradient,
                                            visible_fraction)
from signal_light_node.evalgen.models import (AMBER, CLASS_OF_KIND, FACE_NORMALS, FACES, LENS, RED,
                                              WHITE, Lamp, Solid, VehicleModel, lamp_points)
from signal_light_node.evalgen.tracker import tracker_box
from signal_light_node.evalgen.traffic import Actor, Traffic
from signal_light_node.evalgen.world import Street, sample_env, sample_facades, sample_poles, shade
from signal_light_node.labels import Intent, LightStatus, View, intent_from_lights

_START_NS = 1_760_000_000 * 1_000_000_000


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
class _Drawn:
    """What drawing one vehicle produced, for the ground truth."""

    box: Tuple[float, float, float, float]
    hull_area: float
    lamps: List[Tuple[Lamp, np.ndarray, float]]


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
        self.env = sample_env(rng, self.night)
        self.duration = config.frames / config.fps
        self.times = np.arange(config.frames) / config.fps
        crossing = config.views == "all"
        self.ego_speed = float(rng.uniform(0.0, 1.2) if crossing else rng.uniform(4.0, 9.0))
        self.ego_z = self.ego_speed * self.times
        self.z_int = (float(self.ego_z[-1] + rng.uniform(30.0, 40.0)) if crossing else None)
        self.sway_phase = float(rng.uniform(0, 2 * math.pi))
        self.lanes = [0.0, 3.5] if crossing else [-3.5, 0.0, 3.5]
        self.actors = Traffic(self.seed, config, self.times, self.ego_z, self.ego_speed, self.z_int, self.lanes).cast(rng)
        self.facades = sample_facades(rng, self.ego_z[0], self.z_int)
        self.poles = sample_poles(rng, self.ego_z[0], self.z_int)
        self.street = Street(self.env, self.z_int, crossing, self.poles)
        self.noise_rng = np.random.default_rng([self.seed, 7002])

    # ------------------------------------------------------------------ rendering

    def _frame_view(self, k: int) -> FrameView:
        """The camera in frame ``k``."""
        return FrameView(self.camera, float(self.ego_z[k]), self._sway(k))

    def _project(self, pts: np.ndarray, k: int) -> Tuple[np.ndarray, np.ndarray]:
        """World points to pixels and depths in frame ``k``."""
        return self._frame_view(k).project(pts)

    def _sway(self, k: int) -> float:
        """Pitch of the ego car's ride in frame ``k`` (rad)."""
        t = float(self.times[k])
        return 0.004 * math.sin(2 * math.pi * 0.7 * t + self.sway_phase) + 0.002 * math.sin(5.3 * t)

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
            colour = shade(self.env, albedo, n, dist)
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
            lens = shade(self.env, np.asarray(LENS[lamp.lens]), n, float(np.linalg.norm(to_cam)))
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
        view = self._frame_view(k)
        self.street.background(canvas, view)
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
                self.street.facade(canvas, obj, view)
            else:
                self.street.pole(canvas, obj, view)
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
