"""Rear lamps the training renderer drew too seldom: a full-width tail bar across a rear
face (``rear_bar``, ``synth.lamps.tail_bar``: tail level only, joining the two side
clusters, so the brake and blinkers still come from the clusters) and trucks' and buses'
clusters as wide as real combination lamps (``wide_truck_lamps``)."""

from __future__ import annotations

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.labels import Intent, LightStatus, View
from signal_light_node.synth import SceneRenderer
from signal_light_node.synth.lamps import shows_brake

from scene_helpers import first_frame_vehicles, split_overrides

CLEAN = dict(distractors=False, effects=False, poles=0, weather="clear", respawn=False, shake=False)


def _bars(vehicle) -> list:
    return [lamp for lamp in vehicle.lamps if lamp.role == "tail" and lamp.side == "C"]


def _truck(brake: bool, bar: float, wide: float = 1.0):
    """One parked, lit truck seen from behind at night: its first frame and vehicle."""
    spec = dict(view=View.BEHIND, kind="truck", lamp_design="amber", tech="led", intent=Intent.OFF,
                brake=brake, lights_on=True, chmsl=False, width_px=160.0, center_x=320.0,
                speed=0.0, shear=0.0, roll=0.0, specular=False)
    renderer = SceneRenderer(seed=5, fps=10.0, lighting="night", vehicles=[spec], horizon=0.42,
                             rear_bar=bar, wide_truck_lamps=wide, **CLEAN)
    return next(iter(renderer.frames(1))), renderer._traffic.vehicles[0]


def test_the_bar_joins_the_side_clusters_and_never_brakes():
    _, vehicle = _truck(False, 1.0)
    (bar,) = _bars(vehicle)
    sides = [lamp.rect for lamp in vehicle.lamps if lamp.side in ("L", "R") and lamp.role != "reflector"]
    left = max(r[2] for r in sides if r[0] + r[2] < 1.0)
    right = min(r[0] for r in sides if r[0] + r[2] > 1.0)
    assert bar.rect[0] == pytest.approx(left) and bar.rect[2] == pytest.approx(right)
    assert min(r[1] for r in sides) <= bar.rect[1] < bar.rect[3] <= max(r[3] for r in sides)
    assert not shows_brake(bar.role, bar.side)


def test_the_bar_is_lit_at_tail_level_and_the_truth_is_unchanged():
    plain_tail, _ = _truck(False, 0.0)
    bar_tail, _ = _truck(False, 1.0)
    bar_brake, _ = _truck(True, 1.0)
    x0, y0, x1, y1 = (int(round(c)) for c in bar_tail.vehicles[0].box)
    mid = slice(x0 + (x1 - x0) * 2 // 5, x0 + (x1 - x0) * 3 // 5)  # between the side clusters
    red = lambda f: float(np.clip(f.image[y0:y1, mid, 2].astype(float) - f.image[y0:y1, mid, 1], 0, None).sum())  # noqa: E731
    assert red(bar_tail) > 1.5 * red(plain_tail)
    # A brake lights the side clusters, not the bar: the middle stays as it was.
    assert red(bar_brake) == pytest.approx(red(bar_tail), rel=0.1)
    assert bar_tail.vehicles[0].brake == LightStatus.OFF and bar_brake.vehicles[0].brake == LightStatus.ON
    assert bar_tail.vehicles[0].left == plain_tail.vehicles[0].left


def test_wide_truck_lamps_make_a_large_trucks_brake_and_blinkers_judged():
    narrow, narrow_truck = _truck(False, 0.0, wide=0.0)
    wide, wide_truck = _truck(False, 0.0, wide=1.0)
    # This truck's clusters fall under the truth's size rule as rear_lamps draws them ...
    assert (narrow.vehicles[0].brake, narrow.vehicles[0].left) == (LightStatus.UNKNOWN, LightStatus.UNKNOWN)
    # ... and are judged once as wide as real combination lamps, each still on its own side.
    assert (wide.vehicles[0].brake, wide.vehicles[0].left) == (LightStatus.OFF, LightStatus.OFF)
    for before, after in zip(narrow_truck.lamps, wide_truck.lamps):
        assert (after.role, after.side) == (before.role, before.side)
        width = lambda r: r[2] - r[0]  # noqa: E731
        if after.side in ("L", "R") and after.role != "reflector":
            assert width(after.rect) > 1.5 * width(before.rect)
            assert (after.rect[0] + after.rect[2] < 1.0) == (before.rect[0] + before.rect[2] < 1.0)
        else:
            assert after.rect == before.rect


def test_rear_bar_picks_that_share_of_rear_views_and_keeps_the_vehicles():
    plain, half = first_frame_vehicles(13, "day"), first_frame_vehicles(13, "day", rear_bar=0.5)
    assert [(v.track_id, v.view, v.kind, v.colour, v.lights_on) for v in plain] == \
        [(v.track_id, v.view, v.kind, v.colour, v.lights_on) for v in half]
    assert all(len(_bars(v)) == 0 for v in half if v.view != View.BEHIND)
    rear = [v for v in half if v.view == View.BEHIND and v.style.design != "led_strip"]
    assert len(rear) >= 8
    assert 0.2 < np.mean([len(_bars(v)) == 1 for v in rear]) < 0.8


def test_a_bad_share_is_refused():
    with pytest.raises(ConfigError, match="rear_bar"):
        SceneRenderer(seed=1, rear_bar=1.5)
    with pytest.raises(ConfigError, match="wide_truck_lamps"):
        SceneRenderer(seed=1, wide_truck_lamps=-0.5)


def test_the_split_command_hands_both_shares_to_the_renderer(monkeypatch, tmp_path):
    shares = ["--rear-bar", "0.5", "--wide-truck-lamps", "1"]
    assert split_overrides(monkeypatch, tmp_path / "pool", shares) == {"rear_bar": 0.5,
                                                                      "wide_truck_lamps": 1.0}
    assert split_overrides(monkeypatch, tmp_path / "pool", []) is None
