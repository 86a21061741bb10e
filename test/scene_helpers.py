"""Helpers of the renderer tests: the vehicles of a scene's first frame, a parked car seen
from behind, and what the split command hands the renderer."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

from signal_light_node.data import split as split_cli
from signal_light_node.errors import ConfigError
from signal_light_node.labels import Intent, View
from signal_light_node.synth import SceneRenderer

#: A scene without distractors, camera effects or motion: only the drawn vehicles change.
CLEAN = dict(distractors=False, effects=False, poles=0, weather="clear", respawn=False, shake=False)


def first_frame_vehicles(seed: int, lighting: str, n_vehicles: int = 40, **overrides: Any
                         ) -> List[Any]:
    """The traffic's vehicles once a scene of ``n_vehicles`` has rendered its first frame."""
    renderer = SceneRenderer(seed=seed, n_vehicles=n_vehicles, lighting=lighting, **overrides)
    next(iter(renderer.frames(1)))
    return renderer._traffic.vehicles


def first_frame_renderer(lighting: str, **overrides: Any) -> SceneRenderer:
    """A four-vehicle scene (seed 12) lit as ``lighting`` once it has rendered its first frame."""
    renderer = SceneRenderer(seed=12, lighting=lighting, n_vehicles=4, **overrides)
    next(iter(renderer.frames(1)))
    return renderer


def traffic_key(renderer: SceneRenderer) -> List[Any]:
    """What places a scene's vehicles: ID, kind, view and position of each."""
    return [(v.track_id, v.kind, v.view, v.X, v.Z) for v in renderer._traffic.vehicles]


def camera_option_params(lighting: str, option: str) -> Tuple[Any, Any]:
    """The camera parameters of one scene lit as ``lighting``, drawn without and with the
    camera ``option`` at share 1; asserts that the option moved no vehicle."""
    before = first_frame_renderer(lighting, **{option: 0.0})
    after = first_frame_renderer(lighting, **{option: 1.0})
    assert traffic_key(before) == traffic_key(after)
    return before._camera.p, after._camera.p


def parked_rear_car(brake: bool, lighting: str = "night", **overrides: Any) -> Tuple[Any, Any]:
    """One parked, lit car without a centre lamp seen from behind at the image centre (so
    that only its tail lamps show a brake), in a clean scene: its first frame and vehicle."""
    spec = dict(view=View.BEHIND, kind="car", lamp_design="amber", tech="led", intent=Intent.OFF,
                brake=brake, lights_on=True, chmsl=False, width_px=140.0, center_x=320.0,
                speed=0.0, shear=0.0, roll=0.0, specular=False)
    renderer = SceneRenderer(seed=8, fps=10.0, lighting=lighting, vehicles=[spec], horizon=0.42,
                             **CLEAN, **overrides)
    return next(iter(renderer.frames(1))), renderer._traffic.vehicles[0]


def split_overrides(monkeypatch: Any, out: Path, options: Sequence[str]) -> Optional[Dict[str, Any]]:
    """The renderer overrides ``python -m signal_light_node.data.split`` passes on with
    ``options`` (None when it passes none); nothing is rendered."""
    seen: Dict[str, Any] = {}

    def capture(*args: Any, **kwargs: Any) -> None:
        seen.update(kwargs)
        raise ConfigError("captured")

    monkeypatch.setattr(split_cli, "write_split", capture)
    argv = [str(out), "--seed", "3", "--sequences", "2", "--full-tracks", *options]
    assert split_cli.main(argv) == 2
    return seen.get("renderer_overrides")
