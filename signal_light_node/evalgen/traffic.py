"""The traffic of the evaluation generator: every vehicle with its model, signals and
path over the frames.

Roles: queues ``ahead`` in the ego's direction that brake and keep their gaps before the
stop line, ``oncoming`` traffic that passes (a front view turning into a side view),
traffic ``crossing_r`` / ``crossing_l`` at the intersection and one ``parked`` car with
its hazards on. A path holds ``x``, ``z`` and ``yaw`` per frame, NaN while the vehicle
is absent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from signal_light_node.evalgen.config import SceneConfig
from signal_light_node.evalgen.models import Signals, VehicleModel, sample_signals, sample_vehicle


@dataclass
class Actor:
    """A vehicle with its path over the frames (``x``, ``z``, ``yaw`` NaN when absent)."""

    track_id: str
    model: VehicleModel
    signals: Signals
    role: str
    x: np.ndarray
    z: np.ndarray
    yaw: np.ndarray
    levels: Dict[str, float]
    glint: bool
    jitter_rng: np.random.Generator
    jitter: np.ndarray = field(default_factory=lambda: np.zeros(4))


def sample_levels(rng: np.random.Generator, night: bool) -> Dict[str, float]:
    """Emission levels of one vehicle's lamps (radiance units)."""
    if night:
        return {"tail": float(rng.uniform(0.55, 1.1)), "brake": float(rng.uniform(3.0, 5.5)),
                "blink": float(rng.uniform(2.5, 4.5)), "head": float(rng.uniform(9.0, 16.0)),
                "drl": float(rng.uniform(2.5, 4.0))}
    return {"tail": float(rng.uniform(0.25, 0.45)), "brake": float(rng.uniform(1.1, 2.2)),
            "blink": float(rng.uniform(1.1, 2.0)), "head": float(rng.uniform(1.0, 1.8)),
            "drl": float(rng.uniform(1.6, 2.6))}


class Traffic:
    """Casts the vehicles of one scene (``cast``) on the ego's road.

    Args:
        seed: The scene's seed (each vehicle's tracker jitter has its own stream of it).
        config: What the scene generates.
        times: Time of every frame (s).
        ego_z: The ego camera's position along the road in every frame (m).
        ego_speed: The ego's speed (m/s).
        z_int: Position of the intersection's centre, None on a road without one.
        lanes: Lateral positions of the lanes in the ego's direction.
    """

    def __init__(self, seed: int, config: SceneConfig, times: np.ndarray, ego_z: np.ndarray,
                 ego_speed: float, z_int: Optional[float], lanes: Sequence[float]) -> None:
        self.seed = seed
        self.config = config
        self.night = config.lighting == "night"
        self.duration = config.frames / config.fps
        self.times = times
        self.ego_z = ego_z
        self.ego_speed = ego_speed
        self.z_int = z_int
        self.lanes = lanes

    def _roles(self, rng: np.random.Generator) -> List[str]:
        """The role of every vehicle: ahead, parked, oncoming, crossing_r/_l."""
        cfg = self.config
        if cfg.views == "behind":
            n = cfg.n_vehicles or int(rng.integers(4, 7))
            return ["ahead"] * n
        n = cfg.n_vehicles or int(rng.integers(6, 10))
        fixed = ["crossing_r", "crossing_l", "oncoming", "ahead", "ahead", "oncoming", "parked"]
        extra = list(rng.choice(["ahead", "oncoming", "crossing_r", "crossing_l"],
                                size=max(n - 7, 0), p=[0.45, 0.25, 0.15, 0.15]))
        order = ("ahead", "parked", "oncoming", "crossing_r", "crossing_l")
        return sorted((fixed + extra)[:n], key=order.index)

    def _signal_mode(self, rng: np.random.Generator, role: str) -> str:
        """Whether a vehicle signals (busy), only brakes (quiet) or does nothing."""
        if self.config.events == "none":
            return "none"
        busy = 0.75 if role in ("ahead", "oncoming") else 0.6
        return "busy" if rng.random() < busy else "quiet"

    def cast(self, rng: np.random.Generator) -> List[Actor]:
        """Every vehicle with its model, signals and path."""
        actors: List[Actor] = []
        queue: Dict[float, List[Actor]] = {lane: [] for lane in self.lanes}
        for k, role in enumerate(self._roles(rng)):
            kind = None if role != "parked" else str(rng.choice(["sedan", "suv", "van"]))
            model = sample_vehicle(rng, kind)
            allow = {"oncoming": ("left", "left", "hazard")}.get(role, ("left", "right", "hazard"))
            if role == "parked":
                sig = sample_signals(rng, self.duration, "none", self.night)
                if self.config.events != "none":
                    t0 = float(rng.uniform(-3.0, 2.0))
                    sig.blink.append((max(t0, 0.0), self.duration + 1.0, "hazard"))
            else:
                mode = self._signal_mode(rng, role)
                sig = sample_signals(rng, self.duration, mode, self.night, allow)
            levels = sample_levels(rng, self.night)
            actor = Actor(f"{k + 1}", model, sig, role, *self._empty_path(), levels,
                           bool(rng.random() < 0.5), np.random.default_rng([self.seed, 7100 + k]))
            if role == "ahead":
                lane = self._free_lane(queue, model.length, rng)
                if lane is None:  # no room before the stop line: it comes the other way
                    actor.role = "oncoming"
                    self._place(actor, rng)
                    actors.append(actor)
                    continue
                queue[lane].append(actor)
                actor.x[:] = lane
            else:
                self._place(actor, rng)
            actors.append(actor)
        for lane, cars in queue.items():
            self._drive_queue(cars, lane, rng)
        return actors

    def _free_lane(self, queue: Dict[float, List[Actor]], length: float, rng: np.random.Generator
                   ) -> Optional[float]:
        """A lane whose queue still has room for a car of ``length`` (m), or None."""
        lanes = list(queue)
        rng.shuffle(lanes)
        if self.z_int is None:
            return lanes[0]
        room = self.z_int - 8.0 - (self.ego_z[-1] + 9.5)
        for lane in lanes:
            used = sum(c.model.length + 3.0 for c in queue[lane])
            if used + length + 3.0 <= room:
                return lane
        return None

    def _empty_path(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(x, z, yaw)`` per frame, all NaN (absent)."""
        n = self.config.frames
        return np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)

    def _place(self, actor: Actor, rng: np.random.Generator) -> None:
        """Paths of the parked, oncoming and crossing roles."""
        t = self.times
        if actor.role == "parked":
            actor.x[:] = 6.1
            actor.z[:] = self.ego_z[0] + rng.uniform(22.0, 40.0)
            actor.yaw[:] = 0.0
        elif actor.role == "oncoming":
            lane = -3.5 if rng.random() < 0.6 else -7.0
            t0 = float(rng.uniform(-3.0, max(self.duration - 4.0, -2.0)))
            speed = rng.uniform(4.0, 9.0)
            z = self.ego_speed * t0 + rng.uniform(50.0, 75.0) - speed * (t - t0)
            present = (t >= t0) & (z - self.ego_z > 1.0)
            actor.x[present], actor.z[present], actor.yaw[present] = lane, z[present], math.pi
        else:
            right = actor.role == "crossing_r"
            speed = rng.uniform(4.0, 8.0)
            t0 = float(rng.uniform(-4.0, max(self.duration - 6.0, -3.0)))
            x = (-32.0 + speed * (t - t0)) if right else (32.0 - speed * (t - t0))
            present = (t >= t0) & (np.abs(x) < 34.0)
            actor.x[present] = x[present]
            actor.z[present] = self.z_int + (-2.6 if right else 2.6)
            actor.yaw[present] = math.pi / 2 if right else -math.pi / 2

    def _drive_queue(self, cars: List[Actor], lane: float, rng: np.random.Generator) -> None:
        """Integrate the speeds of one lane's cars ahead, keeping gaps and the stop line."""
        d = float(rng.uniform(9.0, 15.0))
        for car in cars:
            car.z[0] = self.ego_z[0] + d + car.model.length / 2
            d += car.model.length + float(rng.uniform(4.0, 13.0))
        dt = 1.0 / self.config.fps
        spread = (-1.5, 2.0) if self.z_int is not None else (-0.5, 2.5)
        base = [max(self.ego_speed + float(rng.uniform(*spread)), 0.0) for _ in cars]
        speed = list(base)
        for k in range(len(self.times)):
            t = self.times[k]
            for i, car in enumerate(cars):
                if k > 0:
                    target = 0.0 if car.signals.braking(t) else base[i]
                    rate = 2.5 if speed[i] > target else 1.0
                    speed[i] += float(np.clip(target - speed[i], -rate * dt, rate * dt))
                    car.z[k] = car.z[k - 1] + speed[i] * dt
                car.yaw[k] = self._turn_yaw(car.signals, t)
            self._keep_gaps(cars, k)

    def _keep_gaps(self, cars: List[Actor], k: int) -> None:
        """Stop line and leaders hold cars back; then the camera pushes the queue ahead."""
        lead_rear = self.z_int - 8.0 if self.z_int is not None else np.inf
        for car in cars:
            half = car.model.length / 2
            car.z[k] = min(car.z[k], lead_rear - 2.0 - half)
            lead_rear = car.z[k] - half
        floor = self.ego_z[k] + 8.5
        for car in reversed(cars):
            half = car.model.length / 2
            car.z[k] = max(car.z[k], floor + half)
            floor = car.z[k] + half + 2.0

    @staticmethod
    def _turn_yaw(sig: Signals, t: float) -> float:
        """A slight steer towards the signalled side (negative yaw heads to the left)."""
        for t0, t1, mode in sig.blink:
            if t0 <= t < t1 and mode in ("left", "right"):
                ramp = min(t - t0, t1 - t, 1.0)
                return (-0.06 if mode == "left" else 0.06) * max(ramp, 0.0)
        return 0.0
