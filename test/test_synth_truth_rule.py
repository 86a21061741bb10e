"""The truth's two rules for how large a light's seen lamps must be to be labelled
(``synth.truth.TRUTH_RULES``): each lamp on its own (``lamp``, the default) or the lamps of
one function together (``function``)."""

from __future__ import annotations

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.labels import Intent, LightStatus, View
from signal_light_node.synth import SceneRenderer
from signal_light_node.synth.truth import FUNCTION_MIN_BOX_SHARE, LAMP_MIN_BOX_SHARE, judged_lights

from scene_helpers import split_overrides

CLEAN = dict(distractors=False, effects=False, poles=0, weather="clear", respawn=False, shake=False)
BOX = (0.0, 0.0, 120.0, 60.0)  # longer side 120 px


def _side_view(view: View, rule: str):
    spec = dict(view=view, kind="car", lamp_design="amber", tech="led", intent=Intent.HAZARD, brake=True,
                width_px=200.0, center_x=320.0, speed=0.0, blink_hz=1.0, duty=0.5, phase=0.0, shear=0.0,
                roll=0.0, specular=False)
    renderer = SceneRenderer(seed=5, fps=10.0, lighting="day", vehicles=[spec], truth_rule=rule, **CLEAN)
    (frame,) = list(renderer.frames(1))
    return frame


def test_the_lamps_of_one_function_count_together():
    lamp_min = LAMP_MIN_BOX_SHARE * 120 ** 2
    function_min = FUNCTION_MIN_BOX_SHARE * 120 ** 2
    piece = 0.6 * function_min  # two pieces pass together, neither alone
    # Left: a turn lamp and a combined lamp; brake: the combined lamp and a right tail lamp.
    seen = [("turn", "L", piece), ("turn_tail", "L", piece), ("turn", "R", piece), ("tail", "R", piece)]
    assert judged_lights(BOX, seen, "function") == {"L": True, "R": False, "brake": True}
    assert judged_lights(BOX, seen, "lamp") == {"L": False, "R": False, "brake": False}
    # Under the lamp rule one lamp must reach the larger share on its own.
    assert judged_lights(BOX, [("turn", "R", lamp_min)], "lamp")["R"]
    assert not judged_lights(BOX, [("turn", "R", 0.99 * lamp_min)], "lamp")["R"]


def test_a_centre_tail_bar_never_shows_the_brake_under_either_rule():
    seen = [("tail", "C", 1000.0)]
    for rule in ("lamp", "function"):
        assert judged_lights(BOX, seen, rule) == {"L": False, "R": False, "brake": False}


@pytest.mark.parametrize("view,near,far", [(View.LEFT, "left", "right"), (View.RIGHT, "right", "left")])
def test_a_side_view_is_judged_on_its_near_side_by_the_function_rule(view, near, far):
    lamp = _side_view(view, "lamp").vehicles[0]
    assert (lamp.left, lamp.right, lamp.brake) == (LightStatus.UNKNOWN,) * 3
    function = _side_view(view, "function").vehicles[0]
    assert getattr(function, near) == LightStatus.ON and function.brake == LightStatus.ON
    assert getattr(function, far) == LightStatus.UNKNOWN  # the far side faces away


def test_the_rule_changes_labels_only_and_never_judges_fewer_lights():
    frames = {rule: list(SceneRenderer(seed=41, n_vehicles=8, lighting="dusk", truth_rule=rule).frames(6))
              for rule in ("lamp", "function")}
    more = 0
    for a, b in zip(frames["lamp"], frames["function"]):
        assert np.array_equal(a.image, b.image)
        assert [v.track_id for v in a.vehicles] == [v.track_id for v in b.vehicles]
        for va, vb in zip(a.vehicles, b.vehicles):
            for light in ("brake", "left", "right"):
                la, lb = getattr(va, light), getattr(vb, light)
                assert la == LightStatus.UNKNOWN or la == lb
                more += int(la == LightStatus.UNKNOWN and lb != LightStatus.UNKNOWN)
    assert more > 0


def test_an_unknown_rule_is_refused():
    with pytest.raises(ConfigError, match="truth_rule"):
        SceneRenderer(seed=1, truth_rule="largest")
    with pytest.raises(ConfigError, match="truth_rule"):
        judged_lights(BOX, [], "largest")


def test_the_split_command_hands_the_rule_to_the_renderer(monkeypatch, tmp_path):
    rule = split_overrides(monkeypatch, tmp_path / "pool", ["--truth-rule", "function"])
    assert rule == {"truth_rule": "function"}
    assert split_overrides(monkeypatch, tmp_path / "pool", ["--truth-rule", "lamp"]) is None
