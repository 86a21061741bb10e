"""Helpers of the renderer tests: the vehicles of a scene's first frame."""

from __future__ import annotations

from typing import Any, List

from signal_light_node.synth import SceneRenderer


def first_frame_vehicles(seed: int, lighting: str, n_vehicles: int = 40, **overrides: Any
                         ) -> List[Any]:
    """The traffic's vehicles once a scene of ``n_vehicles`` has rendered its first frame."""
    renderer = SceneRenderer(seed=seed, n_vehicles=n_vehicles, lighting=lighting, **overrides)
    next(iter(renderer.frames(1)))
    return renderer._traffic.vehicles
