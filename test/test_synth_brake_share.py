"""How often the renderer's brakes are pressed (``brake_share``, ``synth.lamps.brake_timeline``):
the timeline's own odds by default, the asked share of time and of first-seen brakes else."""

from __future__ import annotations

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.synth import SceneRenderer
from signal_light_node.synth.lamps import brake_timeline

from scene_helpers import first_frame_vehicles, split_overrides


def _odds(share: float, n: int = 300) -> tuple:
    """(share of timelines starting pressed, share of 60 s pressed) over ``n`` timelines."""
    starts, pressed = [], []
    for k in range(n):
        timeline = brake_timeline(np.random.default_rng([7, k]), share=share)
        states = [timeline.segment(t)[0] for t in np.arange(0.0, 60.0, 0.1)]
        starts.append(states[0])
        pressed.append(np.mean(states))
    return float(np.mean(starts)), float(np.mean(pressed))


def test_the_default_starts_half_the_tracks_braking():
    start, pressed = _odds(0.0)
    assert 0.42 < start < 0.58 and 0.33 < pressed < 0.47


@pytest.mark.parametrize("share", [0.15, 0.25])
def test_a_share_sets_how_often_a_brake_is_pressed_and_first_seen(share):
    start, pressed = _odds(share)
    assert abs(start - share) < 0.07
    assert abs(pressed - share) < 0.07


@pytest.mark.parametrize("share", [-0.1, 1.0])
def test_a_share_that_leaves_no_release_is_refused(share):
    with pytest.raises(ConfigError, match="brake_share"):
        brake_timeline(np.random.default_rng(1), share=share)


def test_a_held_brake_ignores_the_share():
    timeline = brake_timeline(np.random.default_rng(1), fixed=True, share=0.1)
    assert all(timeline.segment(t)[0] == 1 for t in (0.0, 5.0, 50.0))


def test_the_scene_hands_the_share_to_its_traffic(monkeypatch, tmp_path):
    def braking(**overrides):
        vehicles = first_frame_vehicles(5, "night", n_vehicles=60, **overrides)
        return np.mean([v.brake.segment(0.0)[0] for v in vehicles])

    assert braking() > 0.3 and braking(brake_share=0.1) < 0.2
    for bad in (1.5, 1.0):
        with pytest.raises(ConfigError, match="brake_share"):
            SceneRenderer(seed=1, brake_share=bad)
    assert split_overrides(monkeypatch, tmp_path / "pool", ["--brake-share", "0.2"]) == \
        {"brake_share": 0.2}


def test_without_the_share_frames_are_as_before():
    a = next(iter(SceneRenderer(seed=21, lighting="dusk", n_vehicles=5).frames(1)))
    b = next(iter(SceneRenderer(seed=21, lighting="dusk", n_vehicles=5, brake_share=0.0).frames(1)))
    assert np.array_equal(a.image, b.image)
