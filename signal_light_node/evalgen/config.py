"""What the evaluation generator is asked to generate: frame count and rate, image size,
lighting, traffic and events (``SceneConfig``), checked when made."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from signal_light_node.errors import ConfigError

LIGHTINGS = ("day", "night")
VIEW_MIXES = ("all", "behind")
EVENTS = ("mixed", "none")


@dataclass(frozen=True)
class SceneConfig:
    """What to generate.

    Attributes:
        frames: Number of frames.
        fps: Frame rate.
        width: Image width.
        height: Image height.
        lighting: "day" or "night".
        n_vehicles: Number of vehicles, or None for a random 6..9 (4..6 with ``views="behind"``).
        views: "all" (ahead, oncoming, crossing, parked) or "behind" (a one-way road, all ahead).
        events: "mixed" (blinks, hazards, braking, quiet stretches) or "none" (no signal at all).
    """

    frames: int = 100
    fps: float = 10.0
    width: int = 1280
    height: int = 720
    lighting: str = "day"
    n_vehicles: Optional[int] = None
    views: str = "all"
    events: str = "mixed"

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ConfigError(f"frames must be >= 1, got {self.frames}")
        if not 1.0 <= self.fps <= 60.0:
            raise ConfigError(f"fps must be in 1..60, got {self.fps}")
        if self.lighting not in LIGHTINGS:
            raise ConfigError(f"lighting must be one of {LIGHTINGS}, got {self.lighting!r}")
        if self.views not in VIEW_MIXES:
            raise ConfigError(f"views must be one of {VIEW_MIXES}, got {self.views!r}")
        if self.events not in EVENTS:
            raise ConfigError(f"events must be one of {EVENTS}, got {self.events!r}")
        if self.n_vehicles is not None and not 1 <= self.n_vehicles <= 24:
            raise ConfigError(f"n_vehicles must be in 1..24, got {self.n_vehicles}")
