"""Clipped tail lamps at night in the training renderer (``tail_glare``, vehicle ``glare``):
steady tail lamps drawn as brightly as a plain vehicle's brake, the brake told only by its
larger glow, its hotter core and the centre lamp; truth and day scenes unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.labels import LightStatus
from signal_light_node.synth import SceneRenderer
from signal_light_node.synth.traffic import GLARE_LEVEL, GLARE_TAIL_LEVEL

from scene_helpers import first_frame_vehicles, parked_rear_car

def _parked(brake: bool, glare: float, lighting: str = "night"):
    return parked_rear_car(brake, lighting, tail_glare=glare)


def _red_light(frame) -> float:
    """Summed red over green of the vehicle's box and a margin around it (lamps and glow)."""
    x0, y0, x1, y1 = (int(round(c)) for c in frame.vehicles[0].box)
    crop = frame.image[max(0, y0 - 20):y1 + 20, max(0, x0 - 20):x1 + 20].astype(np.float64)
    return float(np.clip(crop[..., 2] - crop[..., 1], 0, None).sum())


def test_glaring_tail_lamps_look_like_a_plain_brake_and_its_brake_glows_larger():
    plain_tail, plain = _parked(False, 0.0)
    plain_brake, _ = _parked(True, 0.0)
    glare_tail, glaring = _parked(False, 1.0)
    glare_brake, _ = _parked(True, 1.0)
    assert plain.glare == 1.0
    assert GLARE_LEVEL[0] <= glaring.glare <= GLARE_LEVEL[1]
    assert GLARE_TAIL_LEVEL[0] <= glaring.style.tail_level <= GLARE_TAIL_LEVEL[1]
    # Steady tail lamps now shine about as a plain vehicle's brake does ...
    assert _red_light(glare_tail) > 1.2 * _red_light(plain_tail)
    assert _red_light(glare_tail) > 0.9 * _red_light(plain_brake)
    # ... and the brake is still brighter than the same vehicle's tail lamps.
    assert _red_light(glare_brake) > 1.3 * _red_light(glare_tail)
    # The truth does not change: the brake is what the vehicle does, not how it is drawn.
    assert glare_tail.vehicles[0].brake == LightStatus.OFF
    assert glare_brake.vehicles[0].brake == LightStatus.ON


def test_day_scenes_and_the_default_are_drawn_as_before():
    for brake in (False, True):
        before, _ = _parked(brake, 0.0, "day")
        after, vehicle = _parked(brake, 1.0, "day")
        assert vehicle.glare == 1.0
        assert np.array_equal(before.image, after.image)


def test_tail_glare_picks_that_share_of_lit_vehicles_at_night_and_keeps_the_vehicles():
    plain, half = first_frame_vehicles(12, "night"), first_frame_vehicles(12, "night", tail_glare=0.5)
    assert [(v.track_id, v.view, v.kind, v.colour, v.lights_on) for v in plain] == \
        [(v.track_id, v.view, v.kind, v.colour, v.lights_on) for v in half]
    assert all(v.glare == 1.0 for v in plain)
    lit = [v for v in half if v.lights_on]
    assert all(v.glare == 1.0 for v in half if not v.lights_on)
    assert 0.2 < np.mean([v.glare > 1.0 for v in lit]) < 0.8


def test_a_bad_share_is_refused():
    with pytest.raises(ConfigError, match="tail_glare"):
        SceneRenderer(seed=1, tail_glare=-0.1)
