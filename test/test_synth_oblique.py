"""Turned front and rear views in the training renderer (``oblique``, vehicle ``yaw``): the
face foreshortened, the flank in view on the side the body runs to, the truth still judged."""

from __future__ import annotations

import math

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.labels import Intent, LightStatus, View
from signal_light_node.synth import SceneRenderer
from signal_light_node.synth.traffic import OBLIQUE_YAW_DEG

from scene_helpers import first_frame_vehicles

CLEAN = dict(distractors=False, effects=False, poles=0, weather="clear", respawn=False, shake=False)


def _turned(yaw: float, view: View = View.BEHIND, brake: bool = True):
    """One parked car at the image centre, face 160 px wide before turning; its frame."""
    spec = dict(view=view, kind="car", lamp_design="amber", tech="led", intent=Intent.OFF, brake=brake,
                width_px=160.0, center_x=320.0, speed=0.0, shear=0.0, roll=0.0, specular=False, yaw=yaw)
    renderer = SceneRenderer(seed=5, fps=10.0, lighting="day", vehicles=[spec], horizon=0.42, **CLEAN)
    return next(iter(renderer.frames(1))), renderer


@pytest.mark.parametrize("yaw", [30.0, -30.0])
def test_a_turned_rear_view_shows_its_flank_on_the_side_its_body_runs_to(yaw):
    frame, renderer = _turned(yaw)
    vehicle = frame.vehicles[0]
    x0, _, x1, _ = vehicle.box
    face = renderer._traffic.project(renderer._traffic.vehicles[0])
    # The face is foreshortened by cos(yaw); the flank widens the listed box beyond it.
    assert face[2] - face[0] == pytest.approx(160.0 * math.cos(math.radians(yaw)), rel=1e-6)
    right, left = x1 - face[2], face[0] - x0
    if yaw > 0:
        assert right > 0.5 * (face[2] - face[0]) and left < 3
    else:
        assert left > 0.5 * (face[2] - face[0]) and right < 3
    # Still the rear face toward the camera: view and brake are judged.
    assert vehicle.view == View.BEHIND
    assert vehicle.brake == LightStatus.ON


def test_a_turned_front_view_and_a_straight_one_differ_only_by_the_turn():
    straight, _ = _turned(0.0, View.FRONT, brake=False)
    turned, _ = _turned(25.0, View.FRONT, brake=False)
    assert turned.vehicles[0].view == View.FRONT
    w = lambda v: v.box[2] - v.box[0]  # noqa: E731
    assert w(turned.vehicles[0]) > w(straight.vehicles[0])
    assert not np.array_equal(turned.image, straight.image)


def test_oblique_turns_that_share_of_front_and_rear_views_and_keeps_the_vehicles():
    def vehicles(**kw):
        return first_frame_vehicles(11, "day", **kw)

    plain, all_turned = vehicles(), vehicles(oblique=1.0)
    # The same vehicles (positions may differ: a turned box overlaps others differently).
    assert [(v.track_id, v.view, v.kind, v.colour) for v in plain] == \
        [(v.track_id, v.view, v.kind, v.colour) for v in all_turned]
    assert all(v.yaw == 0.0 for v in plain)
    lo, hi = OBLIQUE_YAW_DEG
    for v in all_turned:
        if v.view in (View.BEHIND, View.FRONT):
            assert lo <= abs(v.yaw) <= hi
        else:
            assert v.yaw == 0.0
    assert {math.copysign(1.0, v.yaw) for v in all_turned if v.yaw} == {1.0, -1.0}
    some = vehicles(oblique=0.5)
    share = np.mean([v.yaw != 0 for v in some if v.view in (View.BEHIND, View.FRONT)])
    assert 0.2 < share < 0.8


def test_bad_turns_are_refused():
    with pytest.raises(ConfigError, match="oblique"):
        SceneRenderer(seed=1, oblique=1.5)
    with pytest.raises(ConfigError, match="yaw"):
        next(iter(SceneRenderer(seed=1, vehicles=[{"view": View.BEHIND, "yaw": 50.0}]).frames(1)))
    with pytest.raises(ConfigError, match="front and rear"):
        next(iter(SceneRenderer(seed=1, vehicles=[{"view": View.LEFT, "yaw": 20.0}]).frames(1)))
