"""Helpers of the renderer tests: the vehicles of a scene's first frame, and what the split
command hands the renderer."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

from signal_light_node.data import split as split_cli
from signal_light_node.errors import ConfigError
from signal_light_node.synth import SceneRenderer


def first_frame_vehicles(seed: int, lighting: str, n_vehicles: int = 40, **overrides: Any
                         ) -> List[Any]:
    """The traffic's vehicles once a scene of ``n_vehicles`` has rendered its first frame."""
    renderer = SceneRenderer(seed=seed, n_vehicles=n_vehicles, lighting=lighting, **overrides)
    next(iter(renderer.frames(1)))
    return renderer._traffic.vehicles


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
