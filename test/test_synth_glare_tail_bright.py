"""Glaring tail lamps as bright as another vehicle's brake (``glare_tail_bright``): across
vehicles no lamp size or glow tells a brake, only the vehicle's own step (its brake is a
multiple of its tail) and its centre lamp; truth and scenes without glaring vehicles
unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.labels import LightStatus
from signal_light_node.synth import SceneRenderer
from signal_light_node.synth.traffic import BRIGHT_BRAKE_RATIO, BRIGHT_TAIL_LEVEL

from scene_helpers import first_frame_vehicles, parked_rear_car


def _parked(brake: bool, glare: float, bright: float, lighting: str = "night"):
    return parked_rear_car(brake, lighting, tail_glare=glare, glare_tail_bright=bright)


def _red_area(frame) -> int:
    """Pixels of the box and a margin whose red channel is over 150 (lamps and glow)."""
    x0, y0, x1, y1 = (int(round(c)) for c in frame.vehicles[0].box)
    crop = frame.image[max(0, y0 - 20):y1 + 20, max(0, x0 - 20):x1 + 20]
    return int((crop[..., 2] > 150).sum())


def test_a_bright_tail_outshines_a_plain_glaring_brake_and_its_own_brake_outshines_it():
    plain_brake, _ = _parked(True, 1.0, 0.0)
    bright_tail, vehicle = _parked(False, 1.0, 1.0)
    bright_brake, _ = _parked(True, 1.0, 1.0)
    assert BRIGHT_TAIL_LEVEL[0] <= vehicle.style.tail_level <= BRIGHT_TAIL_LEVEL[1]
    ratio = vehicle.glare / vehicle.style.tail_level
    assert BRIGHT_BRAKE_RATIO[0] <= ratio <= BRIGHT_BRAKE_RATIO[1]
    assert _red_area(bright_tail) > _red_area(plain_brake)      # across vehicles: no size cue
    assert _red_area(bright_brake) > 1.3 * _red_area(bright_tail)  # within the vehicle: a step
    assert bright_tail.vehicles[0].brake == LightStatus.OFF
    assert bright_brake.vehicles[0].brake == LightStatus.ON


@pytest.mark.parametrize("glare, lighting", [(0.0, "night"), (1.0, "day")])
def test_without_glaring_vehicles_nothing_changes(glare, lighting):
    for brake in (False, True):
        before, plain = _parked(brake, glare, 0.0, lighting)
        after, vehicle = _parked(brake, glare, 1.0, lighting)
        assert (vehicle.style, vehicle.glare) == (plain.style, plain.glare)
        assert np.array_equal(before.image, after.image)


def test_the_share_picks_among_glaring_vehicles_and_keeps_every_other_draw():
    glare = first_frame_vehicles(12, "night", tail_glare=0.5)
    bright = first_frame_vehicles(12, "night", tail_glare=0.5, glare_tail_bright=0.5)
    assert [(v.track_id, v.view, v.kind, v.colour) for v in glare] == \
        [(v.track_id, v.view, v.kind, v.colour) for v in bright]
    picked = [b.style.tail_level > 1.0 for g, b in zip(glare, bright) if g.glare > 1.0]
    assert 0.2 < np.mean(picked) < 0.8
    assert all(b.style == g.style and b.glare == g.glare
               for g, b in zip(glare, bright) if g.glare == 1.0)


def test_a_bad_share_is_refused():
    with pytest.raises(ConfigError, match="glare_tail_bright"):
        SceneRenderer(seed=1, glare_tail_bright=-0.5)
