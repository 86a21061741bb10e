"""Glaring tail lamps drawn at their brake's colour (``glare_tail_hot``, vehicle
``tail_hot``): the steady tail's core is as white as the brake's, so that only the glow's
extent, the growth over the track's own level and the centre lamp tell a brake; truth and
every scene without glaring vehicles unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.labels import LightStatus
from signal_light_node.synth import SceneRenderer

from scene_helpers import first_frame_vehicles, parked_rear_car


def _parked(brake: bool, glare: float, hot: float, lighting: str = "night"):
    return parked_rear_car(brake, lighting, tail_glare=glare, glare_tail_hot=hot)


def _box(frame, margin: int = 0) -> np.ndarray:
    x0, y0, x1, y1 = (int(round(c)) for c in frame.vehicles[0].box)
    return frame.image[max(0, y0 - margin):y1 + margin, max(0, x0 - margin):x1 + margin].astype(np.float64)


def _core_white(frame) -> float:
    """How white the 16 whitest pixels of the box are (their smallest channel)."""
    return float(np.sort(_box(frame).min(axis=-1).ravel())[-16:].mean())


def _bright_red_area(frame) -> int:
    """Pixels of the box and a margin whose red channel is over 150 (lamps and glow)."""
    return int((_box(frame, 20)[..., 2] > 150).sum())


def test_a_hot_tail_has_its_brakes_core_and_a_smaller_glow():
    tail, _ = _parked(False, 1.0, 0.0)
    hot_tail, vehicle = _parked(False, 1.0, 1.0)
    brake, _ = _parked(True, 1.0, 1.0)
    assert vehicle.tail_hot and vehicle.glare > 1.0
    # Without the option a glaring tail's core is clearly less white than its brake's ...
    assert _core_white(tail) < _core_white(brake) - 30
    # ... with it the core is the brake's, and only the glow's extent still tells.
    assert _core_white(hot_tail) > _core_white(brake) - 5
    assert _bright_red_area(brake) > 1.1 * _bright_red_area(hot_tail)
    assert hot_tail.vehicles[0].brake == LightStatus.OFF
    assert brake.vehicles[0].brake == LightStatus.ON


def test_a_brake_is_drawn_as_without_the_option():
    before, _ = _parked(True, 1.0, 0.0)
    after, _ = _parked(True, 1.0, 1.0)
    assert np.array_equal(before.image, after.image)


@pytest.mark.parametrize("glare, lighting", [(0.0, "night"), (1.0, "day")])
def test_without_glaring_vehicles_nothing_changes(glare, lighting):
    for brake in (False, True):
        before, _ = _parked(brake, glare, 0.0, lighting)
        after, vehicle = _parked(brake, glare, 1.0, lighting)
        assert not vehicle.tail_hot
        assert np.array_equal(before.image, after.image)


def test_the_share_picks_among_glaring_vehicles_and_keeps_every_other_draw():
    glare = first_frame_vehicles(12, "night", tail_glare=0.5)
    hot = first_frame_vehicles(12, "night", tail_glare=0.5, glare_tail_hot=0.5)
    assert [(v.track_id, v.view, v.kind, v.glare, v.style) for v in glare] == \
        [(v.track_id, v.view, v.kind, v.glare, v.style) for v in hot]
    assert not any(v.tail_hot for v in glare)
    assert all(v.glare > 1.0 for v in hot if v.tail_hot)
    glaring = [v.tail_hot for v in hot if v.glare > 1.0]
    assert 0.2 < np.mean(glaring) < 0.8


def test_a_bad_share_is_refused():
    with pytest.raises(ConfigError, match="glare_tail_hot"):
        SceneRenderer(seed=1, glare_tail_hot=1.5)
