"""The evaluation scene: an urban road in 3D seen by a moving pinhole camera, with
vehicles ahead (seen from behind), oncoming (front, then side as they pass), crossing at
an intersection (sides) and parked with hazards; ground truth from the lamps' visibility.

``EvalScene`` samples the camera, the ego's drive, the traffic and the street from its
seed and renders each frame; one module per concern does the work:

* ``traffic``: every vehicle's model, signals and path over the frames;
* ``world``: illumination, road and markings, facades and poles;
* ``vehicle_drawing``: shadows, solids, glass and lamps of the vehicles;
* ``truth``: the view, lamp visibility and light states of each vehicle;
* ``tracker``: the jittered box a tracker reports, or a miss;
* ``camera``: the pinhole projection (``FrameView`` per frame) and the sensor model.

Per frame: road and buildings, then every object far to near (painter's order) into a
linear radiance buffer with an id buffer, lamp truth from the id buffer, tracker boxes
with correlated jitter and misses, and finally the sensor model (``camera.develop``).
"""

from __future__ import annotations

import math
from typing import Dict, Iterator, List, Tuple

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.evalgen.camera import (FrameView, PinholeCamera, develop, sample_camera,
                                              sample_sensor)
from signal_light_node.evalgen.config import SceneConfig
from signal_light_node.evalgen.draw import Canvas
from signal_light_node.evalgen.tracker import tracker_box
from signal_light_node.evalgen.traffic import Traffic
from signal_light_node.evalgen.truth import EvalFrame, VehicleTruth, occlusion_of, vehicle_truth
from signal_light_node.evalgen.vehicle_drawing import Drawn, VehicleDrawer
from signal_light_node.evalgen.world import Street, sample_env, sample_facades, sample_poles

_START_NS = 1_760_000_000 * 1_000_000_000


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
        traffic = Traffic(self.seed, config, self.times, self.ego_z, self.ego_speed, self.z_int,
                          self.lanes)
        self.actors = traffic.cast(rng)
        self.facades = sample_facades(rng, self.ego_z[0], self.z_int)
        self.poles = sample_poles(rng, self.ego_z[0], self.z_int)
        self._street = Street(self.env, self.z_int, crossing, self.poles)
        self.noise_rng = np.random.default_rng([self.seed, 7002])
        self._drawer = VehicleDrawer(self.env, self.sensor.exposure_s)

    # ------------------------------------------------------------------ frames

    def _frame_view(self, k: int) -> FrameView:
        """The camera in frame ``k``."""
        return FrameView(self.camera, float(self.ego_z[k]), self._sway(k))

    def _sway(self, k: int) -> float:
        """Pitch of the ego car's ride in frame ``k`` (rad)."""
        t = float(self.times[k])
        return 0.004 * math.sin(2 * math.pi * 0.7 * t + self.sway_phase) + 0.002 * math.sin(5.3 * t)

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
                out = self._drawer.draw(canvas, self.actors[obj], k, view, float(self.times[k]),
                                        obj)
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
            occlusion = occlusion_of(canvas, i, d)
            tracker = tracker_box(actor, d.box, occlusion, self.config.width, self.config.height)
            out.append(vehicle_truth(canvas, actor, d, k, self.ego_z[k], t, exposure, i, occlusion,
                                     tracker))
        return out

    def frames(self) -> Iterator[EvalFrame]:
        """Every frame in order."""
        for k in range(self.config.frames):
            yield self.render(k)
