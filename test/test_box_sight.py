"""Tests of runtime.box_sight: a light's UNKNOWN from the view head and the boxes."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from fake_light_model import FakeLightModel
from signal_light_node.boxes import TrackBox
from signal_light_node.errors import ConfigError
from signal_light_node.labels import LIGHT_TASKS, LightStatus, View
from signal_light_node.runtime import box_sight
from signal_light_node.runtime.engine import EngineConfig, LightStateEngine
from signal_light_node.runtime.intent_filter import IntentFilter, IntentFilterConfig

MS = 1_000_000
BRAKE, LEFT, RIGHT = (LIGHT_TASKS.index(t) for t in ("brake", "left", "right"))
COLUMNS = ((LEFT, View.RIGHT), (RIGHT, View.LEFT))
#: The model is nearly sure it cannot see the lamps, and leans ON where it can.
UNSURE = [0.04, 0.06, 0.90]


def _view(face: View, p: float = 0.97) -> np.ndarray:
    view = np.full(len(View), (1.0 - p) / (len(View) - 1))
    view[int(face)] = p
    return view


def test_cover_counts_the_image_edge_and_nearer_boxes_only():
    boxes = np.array([[100, 100, 200, 200],    # far; its lower right quarter behind the next
                      [150, 150, 250, 260],    # nearer (lower bottom edge): nothing covers it
                      [-50, 10, 50, 60],       # half left of the image
                      [300, 300, 340, 340],    # below the far box's bottom: nearer, apart
                      [math.nan, 0, 1, 1]])    # not a box: NaN, covers nothing
    cover = box_sight.box_cover(boxes, 640, 360)
    assert cover[:4] == pytest.approx([0.25, 0.0, 0.5, 0.0])
    assert math.isnan(cover[4])
    # A box reaching below the image is covered there.
    assert box_sight.box_cover(np.array([[0, 300, 40, 420]]), 640, 360)[0] == pytest.approx(0.5)
    assert box_sight.box_cover(np.zeros((0, 4)), 640, 360).shape == (0,)


def test_an_uncovered_rear_view_judges_the_blinkers_the_model_called_unknown():
    p = np.array([[[0.5, 0.3, 0.2], UNSURE, UNSURE]])
    out = box_sight.judge_blinkers(p, _view(View.BEHIND)[None], np.array([0.0]), 0.1, COLUMNS)
    for column in (LEFT, RIGHT):
        q = out[0, column]
        assert q[2] == pytest.approx(0.01)  # P(the face that hides it): 0.03 / 3
        assert q[1] / q[0] == pytest.approx(0.06 / 0.04)  # ON and OFF keep their ratio
        assert q.sum() == pytest.approx(1.0)
        assert q.argmax() == int(LightStatus.ON)
    np.testing.assert_array_equal(out[0, 0], p[0, 0])  # the brake is the model's
    np.testing.assert_array_equal(p[0, LEFT], UNSURE)  # the input is not modified


def test_the_side_facing_away_is_unknown_and_a_covered_box_keeps_the_model():
    p = np.array([[[0.5, 0.3, 0.2], [0.7, 0.25, 0.05], [0.7, 0.25, 0.05]],
                  [[0.5, 0.3, 0.2], UNSURE, UNSURE],
                  [[0.5, 0.3, 0.2], UNSURE, UNSURE]])
    view = np.stack([_view(View.LEFT), _view(View.BEHIND), _view(View.BEHIND)])
    out = box_sight.judge_blinkers(p, view, np.array([0.0, 0.4, math.nan]), 0.1, COLUMNS)
    # Seen from its left face, the vehicle's right blinker is away from the camera.
    assert out[0, RIGHT].argmax() == int(LightStatus.UNKNOWN)
    assert out[0, RIGHT, 2] == pytest.approx(0.97)
    assert out[0, LEFT, 2] == pytest.approx(0.01)
    # Covered beyond cover_max: the model's own UNKNOWN counts; unknown cover: as given.
    np.testing.assert_allclose(out[1], p[1])
    np.testing.assert_array_equal(out[2], p[2])


def _mixed_view(behind: float, side: float, front: float) -> np.ndarray:
    view = np.zeros(len(View))
    view[[int(View.BEHIND), int(View.LEFT), int(View.FRONT)]] = behind, side, front
    return view


def test_the_brake_is_judged_from_behind_hidden_from_the_front_the_model_s_from_a_side():
    p = np.array([[UNSURE, UNSURE, UNSURE]] * 4)
    view = np.stack([_view(View.BEHIND), _view(View.FRONT), _view(View.LEFT),
                     _mixed_view(0.5, 0.3, 0.2)])
    out = box_sight.judge_brake(p, view, np.zeros(4), 0.1, BRAKE)
    unknown = out[:, BRAKE, 2]
    assert unknown[0] == pytest.approx(0.01 + 0.02 * 0.90)  # FRONT + sides * model's UNKNOWN
    assert out[0, BRAKE].argmax() == int(LightStatus.ON)
    assert out[0, BRAKE, 1] / out[0, BRAKE, 0] == pytest.approx(0.06 / 0.04)
    assert unknown[1] > 0.97
    assert unknown[2] == pytest.approx(0.01 + 0.98 * 0.90)
    assert unknown[3] == pytest.approx(0.2 + 0.3 * 0.90)
    np.testing.assert_array_equal(out[:, LEFT], p[:, LEFT])  # the blinkers are the model's
    # A covered box keeps at least the model's UNKNOWN; an unknown cover, the model's.
    covered = box_sight.judge_brake(p[:2], view[:2], np.array([0.5, math.nan]), 0.1, BRAKE)
    np.testing.assert_allclose(covered[:, BRAKE], p[:2, BRAKE])


def test_with_rear_sight_a_side_hides_the_brake_and_the_rear_still_judges_it():
    """``brake_sight: rear``: P(UNKNOWN) = 1 - P(BEHIND), where the model's own would
    have decided from a side (the test above)."""
    p = np.array([[UNSURE, UNSURE, UNSURE], [[0.7, 0.25, 0.05]] * 3, [UNSURE] * 3])
    view = np.stack([_view(View.BEHIND), _view(View.LEFT), _mixed_view(0.5, 0.3, 0.2)])
    out = box_sight.judge_brake(p, view, np.zeros(3), 0.1, BRAKE, side_hides=True)
    unknown = out[:, BRAKE, 2]
    assert unknown == pytest.approx([0.03, 0.99, 0.5])
    assert out[0, BRAKE].argmax() == int(LightStatus.ON)
    # A model sure it sees a side view's brake OFF is overruled: its lamps face away.
    assert out[1, BRAKE].argmax() == int(LightStatus.UNKNOWN)
    assert out[1, BRAKE, 0] / out[1, BRAKE, 1] == pytest.approx(0.7 / 0.25)
    default = box_sight.judge_brake(p, view, np.zeros(3), 0.1, BRAKE)
    assert default[1, BRAKE].argmax() == int(LightStatus.OFF)


def test_config_checks_the_sight_and_the_cover():
    assert IntentFilterConfig().blinker_sight == "model"
    # The shipped weights' setting (2026-11-29): a side view hides the brake.
    assert IntentFilterConfig().brake_sight == "rear"
    for name in ("blinker_sight", "brake_sight"):
        with pytest.raises(ConfigError, match=name):
            IntentFilterConfig(**{name: "eyes"})
    with pytest.raises(ConfigError, match="blinker_sight"):
        IntentFilterConfig(blinker_sight="rear")  # a blinker has no rear-only sight
    brake = IntentFilterConfig(brake_sight="geometry")
    assert IntentFilter(brake).uses_cover
    assert "brake UNKNOWN from the view" in brake.describe()
    rear = IntentFilterConfig(brake_sight="rear")
    assert IntentFilter(rear).uses_cover
    assert "brake (hidden from a side too) UNKNOWN" in rear.describe()
    for bad in (-0.1, 1.5, math.nan, True):
        with pytest.raises(ConfigError, match="cover_max"):
            IntentFilterConfig(cover_max=bad)
    geometry = IntentFilterConfig(blinker_sight="geometry")
    model = IntentFilterConfig(brake_sight="model")
    assert IntentFilter(geometry).uses_cover and not IntentFilter(model).uses_cover
    assert IntentFilter().uses_cover  # the default brake sight, rear, needs the covers
    assert not IntentFilter(IntentFilterConfig(enabled=False, blinker_sight="geometry")).uses_cover
    assert "from the view and boxes" in geometry.describe()


def _probs(n: int) -> dict:
    return {"intent": np.full((n, 5), 0.2), "brake": np.tile([0.9, 0.05, 0.05], (n, 1)),
            "left": np.tile(UNSURE, (n, 1)), "right": np.tile(UNSURE, (n, 1)),
            "view": np.tile(_view(View.BEHIND), (n, 1))}


@pytest.mark.parametrize("sight, cover, state", [("model", [0.0], LightStatus.UNKNOWN),
                                                 ("geometry", None, LightStatus.UNKNOWN),
                                                 ("geometry", [0.5], LightStatus.UNKNOWN),
                                                 ("geometry", [0.0], LightStatus.OFF)])
def test_filter_publishes_what_geometry_says_only_with_a_cover(sight, cover, state):
    """With geometry and an uncovered box the blinker is judged (the model leans ON, but
    one frame never makes a blinker: OFF); otherwise it stays the model's UNKNOWN."""
    filt = IntentFilter(IntentFilterConfig(blinker_sight=sight))
    out = filt.step(_probs(1), 0, filt.initial_rows(1), None,
                    None if cover is None else np.array(cover))
    assert out.states["left"][0] == state and out.states["right"][0] == state


@pytest.mark.parametrize("sight, state", [("model", LightStatus.UNKNOWN),
                                          ("geometry", LightStatus.ON),
                                          ("rear", LightStatus.ON)])
def test_filter_judges_the_brake_with_its_own_sight(sight, state):
    """The brake's sight is set apart from the blinkers': only ``brake_sight`` moves it,
    and the brake is published as judged from its first frame (no hold)."""
    probs = {**_probs(1), "brake": np.array([UNSURE])}
    filt = IntentFilter(IntentFilterConfig(brake_sight=sight))
    out = filt.step(probs, 0, filt.initial_rows(1), None, np.array([0.0]))
    assert out.states["brake"][0] == state
    assert out.states["left"][0] == LightStatus.UNKNOWN


class _UnsureModel(FakeLightModel):
    """The fake model, sure of a rear view and unsure whether it sees the blinkers."""

    def step(self, crops, state):
        probs, new_state = super().step(crops, state)
        n = len(crops)
        probs["left"] = torch.tensor([UNSURE]).repeat(n, 1)
        probs["right"] = torch.tensor([UNSURE]).repeat(n, 1)
        probs["view"] = torch.tensor(_view(View.BEHIND)[None], dtype=torch.float32).repeat(n, 1)
        return probs, new_state


def test_engine_judges_a_free_vehicle_and_not_one_behind_another():
    engine = LightStateEngine(_UnsureModel(), EngineConfig(intent_filter=IntentFilterConfig(
        blinker_sight="geometry", flash_min_evidence=0.0)))
    image = np.full((180, 320, 3), 60, np.uint8)
    boxes = [TrackBox("far", 100, 40, 160, 100), TrackBox("near", 120, 60, 200, 140),
             TrackBox("free", 240, 40, 300, 100)]
    for k in range(3):
        results = engine.process(image, k * 100 * MS, boxes).results
    by_id = {r.track_id: r for r in results}
    assert by_id["far"].left.state == LightStatus.UNKNOWN  # 44 % behind "near"
    for tid in ("near", "free"):
        assert by_id[tid].left.state == LightStatus.ON  # judged: the model leans ON
        assert by_id[tid].right.state == LightStatus.ON


def test_bag_tracks_carry_the_cover_the_node_would_compute():
    """Tracks read from a bag carry each frame's cover from all of that frame's boxes, so
    ``evaluate`` and ``replay`` judge with the same geometry as the node."""
    from signal_light_node.io.bagio import find_topic, open_bag
    from signal_light_node.io.conversions import detections_to_boxes, stamp_to_ns
    from signal_light_node.io.topics import DETECTIONS_TYPE
    from signal_light_node.training.sources import load_bag_tracks

    bag = Path(__file__).resolve().parents[1] / "bags" / "day_street"
    tracks = load_bag_tracks(bag)
    with open_bag(bag) as reader:
        topic = find_topic(reader.topics(), (DETECTIONS_TYPE,), None, "detection", bag)
        frames = {stamp_to_ns(m.msg.header.stamp): detections_to_boxes(m.msg)
                  for m in reader.messages([topic])}
    width, height = 640, 360
    checked = 0
    for track in tracks:
        assert track.cover is not None and track.cover.shape == (len(track),)
        tid = track.track_id.split(":", 1)[1]
        for stamp, cover in zip(track.stamps_ns[:5], track.cover[:5]):
            boxes = frames[int(stamp)]
            want = box_sight.box_cover(box_sight.boxes_array(boxes), width, height)
            assert cover == want[[b.track_id for b in boxes].index(tid)]
            checked += 1
    assert checked >= 10
