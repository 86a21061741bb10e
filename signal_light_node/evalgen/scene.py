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
from signal_light_node.evalgen.camera import FrameView, PinholeCamera, develop, sample_camera, sample_sensor
from signal_light_node.evalgen.config import SceneConfig
from signal_light_node.evalgen.draw import Canvas, visible_fraction
from signal_light_node.evalgen.models import CLASS_OF_KIND
from signal_light_node.evalgen.tracker import tracker_box
from signal_light_node.evalgen.traffic import Actor, Traffic
from signal_light_node.evalgen.vehicle_drawing import Drawn, VehicleDrawer
from signal_light_node.evalgen.world import Street, sample_env, sample_facades, sample_poles
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
        self._street = Street(self.env, self.z_int, crossing, self.poles)
        self.noise_rng = np.random.default_rng([self.seed, 7002])
        self._drawer = VehicleDrawer(self.env, self.sensor.exposure_s)

    # ------------------------------------------------------------------ rendering

    def _frame_view(self, k: int) -> FrameView:
        """The camera in frame ``k``."""
        return FrameView(self.camera, float(self.ego_z[k]), self._sway(k))

    def _sway(self, k: int) -> float:
        """Pitch of the ego car's ride in frame ``k`` (rad)."""
        t = float(self.times[k])
        return 0.004 * math.sin(2 * math.pi * 0.7 * t + self.sway_phase) + 0.002 * math.sin(5.3 * t)

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

    def _truth(self, canvas: Canvas, actor: Actor, drawn: Drawn, k: int, obj_id: int
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
        self._street.background(canvas, view)
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
        drawn: Dict[int, Drawn] = {}
        for _, what, obj in items:
            if what == "vehicle":
                out = self._drawer.draw(canvas, self.actors[obj], k, view, float(self.times[k]), obj)
                if out is not None:
                    drawn[obj] = out
            elif what == "facade":
                self._street.facade(canvas, obj, view)
            else:
                self._street.pole(canvas, obj, view)
        truths = self._truths(canvas, drawn, k)
        image = develop(canvas.rgb, self.sensor, self.noise_rng)
        stamp = _START_NS + self.seed % 1000 * 1_000_000_000 + int(round(k * 1e9 / self.config.fps))
        return EvalFrame(k, stamp, image, truths, self.config.lighting)

    def _truths(self, canvas: Canvas, drawn: Dict[int, Drawn], k: int) -> List[VehicleTruth]:
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
