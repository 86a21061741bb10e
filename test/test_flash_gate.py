"""A blinker must flash: lamp levels, the ring of a track's levels, the evidence per side,
and the intent filter's veto of a steady lamp."""

from __future__ import annotations

from typing import Optional

import numpy as np
import pytest

from signal_light_node.labels import TASKS, Intent, LightStatus, View
from signal_light_node.runtime import flash_gate
from signal_light_node.runtime.intent_filter import IntentFilter, IntentFilterConfig

GREY = (110, 110, 110)  # BGR
RED = (30, 30, 230)
AMBER = (20, 150, 250)
WHITE = (250, 250, 250)


def _crop(left=None, right=None, size=64) -> np.ndarray:
    """A grey crop with a lit lamp (a 6x10 block of a colour) in either half."""
    crop = np.empty((size, size, 3), np.uint8)
    crop[:] = GREY
    for colour, x in ((left, size // 8), (right, size - size // 8 - 10)):
        if colour is not None:
            crop[size // 2:size // 2 + 6, x:x + 10] = colour
    return crop


def test_lamp_levels_see_red_and_amber_lamps_in_their_half_not_white():
    levels = flash_gate.lamp_levels(np.stack([_crop(), _crop(left=RED), _crop(right=AMBER),
                                              _crop(left=WHITE, right=WHITE)]))
    assert levels.shape == (4, 2) and levels.dtype == np.float32
    dark, red_left, amber_right, white = levels
    assert np.allclose(dark, 0) and np.allclose(white, 0)
    assert red_left[0] > 150 and red_left[1] == 0
    assert amber_right[1] > 150 and amber_right[0] == 0
    assert flash_gate.lamp_levels(np.zeros((0, 64, 64, 3), np.uint8)).shape == (0, 2)


def test_lamp_levels_scale_with_the_crop_size():
    """A lamp covering the same share of a larger crop gives the same level."""
    small = flash_gate.lamp_levels(_crop(left=RED)[None])
    big = flash_gate.lamp_levels(np.kron(_crop(left=RED), np.ones((2, 2, 1), np.uint8))[None])
    np.testing.assert_allclose(small, big, atol=1.0)


def _ring(levels, stamps_s) -> np.ndarray:
    rows = flash_gate.initial_rows(1)
    for level, t in zip(levels, stamps_s):
        rows = flash_gate.push(rows, np.array([t]), np.array([level], np.float64))
    return rows


def test_steady_lamps_have_no_evidence_flashing_ones_do():
    t = np.arange(20) * 0.1
    steady = _ring([(200.0, 200.0)] * 20, t)
    flashing = _ring([(200.0 if (k // 4) % 2 else 0.0, 200.0) for k in range(20)], t)
    now = np.array([t[-1]])
    assert flash_gate.half_evidence(steady, now, 1.5).tolist() == [[0.0, 0.0]]
    left, right = flash_gate.half_evidence(flashing, now, 1.5)[0]
    assert left == pytest.approx(200 / 220) and right == 0.0


def test_evidence_looks_back_only_over_the_window():
    """A flash 2 s ago is outside a 1.5 s window; a new track's first frame has none."""
    t = np.arange(30) * 0.1
    levels = [(0.0, 0.0)] * 5 + [(200.0, 0.0)] * 25
    rows = _ring(levels, t)
    assert flash_gate.half_evidence(rows, np.array([t[-1]]), 1.5)[0, 0] == 0.0
    assert flash_gate.half_evidence(rows, np.array([t[-1]]), 3.0)[0, 0] > 0.5
    first = _ring([(200.0, 200.0)], [0.0])
    assert flash_gate.half_evidence(first, np.array([0.0]), 1.5).tolist() == [[0.0, 0.0]]


def test_the_ring_keeps_the_last_slots_frames_and_is_not_modified_in_place():
    rows = flash_gate.initial_rows(2)
    before = rows.copy()
    out = flash_gate.push(rows, np.array([1.0, 2.0]), np.array([[1.0, 2.0], [3.0, 4.0]]))
    np.testing.assert_array_equal(rows, before)
    assert out.shape == (2, flash_gate.WIDTH)
    n = flash_gate.SLOTS + 5
    ring = _ring([(float(k), 0.0) for k in range(n)], np.arange(n) * 0.01)
    stamps = np.sort(ring[0, :flash_gate.SLOTS])
    np.testing.assert_allclose(stamps, np.arange(5, n) * 0.01)
    assert sorted(ring[0, flash_gate.SLOTS:2 * flash_gate.SLOTS]) == list(range(5, n))


@pytest.mark.parametrize("face, expected", [
    (View.BEHIND, [0.8, 0.1]), (View.FRONT, [0.1, 0.8]),
    (View.LEFT, [0.8, 0.8]), (View.RIGHT, [0.8, 0.8]),
])
def test_halves_map_to_the_vehicles_sides_by_its_face(face, expected):
    view = np.eye(4)[[int(face)]]
    got = flash_gate.side_evidence(np.array([[0.8, 0.1]]), view)
    np.testing.assert_allclose(got[0], expected)


def test_veto_moves_on_to_off_where_evidence_is_weak_only():
    lights = np.array([[[0.1, 0.8, 0.1], [0.1, 0.8, 0.1], [0.1, 0.8, 0.1]]] * 2)
    out = flash_gate.veto(lights, np.array([[0.05, 0.5], [0.5, 0.05]]), 0.1, (1, 2))
    np.testing.assert_allclose(out[0, 1], [0.9, 0.0, 0.1])
    np.testing.assert_allclose(out[0, 2], lights[0, 2])
    np.testing.assert_allclose(out[1, 2], [0.9, 0.0, 0.1])
    np.testing.assert_allclose(out[:, 0], lights[:, 0])  # the brake is never touched
    np.testing.assert_allclose(out.sum(-1), 1.0)


def _model_says_left(p_on: float = 0.9) -> dict:
    probs = {t: np.eye(k)[[0]] for t, k in zip(TASKS, (5, 3, 3, 3, 4))}  # view: BEHIND
    probs["left"] = np.array([[1.0 - p_on - 0.02, p_on, 0.02]])
    return probs


def _published(config: IntentFilterConfig, crops, task: str = "left",
                 probs: Optional[dict] = None) -> list:
    """The published ``task`` (default the left blinker), frame by frame at 10 fps, the
    model sure the left blinker is ON (or saying ``probs``)."""
    filt = IntentFilter(config)
    rows, states = filt.initial_rows(1), []
    for k, crop in enumerate(crops):
        levels = flash_gate.lamp_levels(crop[None]) if filt.gates_flashes else None
        out = filt.step(probs or _model_says_left(), int(k * 1e8), rows, levels)
        rows = out.rows
        states.append(int(out.states[task][0]))
    return states


def test_a_steady_lamp_is_never_a_blinker_a_flashing_one_is():
    steady = [_crop(left=RED)] * 20
    flashing = [_crop(left=AMBER) if (k // 4) % 2 else _crop() for k in range(20)]
    gate = IntentFilterConfig()
    assert gate.flash_min_evidence > 0 and IntentFilter(gate).gates_flashes
    assert set(_published(gate, steady)) == {int(LightStatus.OFF)}
    flashed = _published(gate, flashing)
    assert flashed[-10:] == [int(LightStatus.ON)] * 10
    # Without the gate the model's word stands, steady lamp or not.
    no_gate = IntentFilterConfig(flash_min_evidence=0.0)
    assert not IntentFilter(no_gate).gates_flashes
    assert _published(no_gate, steady)[-10:] == [int(LightStatus.ON)] * 10


def test_veto_intent_needs_the_flash_of_every_side_it_names():
    intent = np.array([[0.1, 0.3, 0.3, 0.2, 0.1]] * 3)  # OFF LEFT RIGHT HAZARD UNKNOWN
    evidence = np.array([[0.5, 0.05], [0.05, 0.05], [0.5, 0.5]])
    out = flash_gate.veto_intent(intent, evidence, 0.1)
    np.testing.assert_allclose(out[0], [0.6, 0.3, 0.0, 0.0, 0.1])  # only the left flashes
    np.testing.assert_allclose(out[1], [0.9, 0.0, 0.0, 0.0, 0.1])  # neither
    np.testing.assert_allclose(out[2], intent[2])  # both
    np.testing.assert_allclose(intent[0], [0.1, 0.3, 0.3, 0.2, 0.1])  # not modified


def test_the_intent_head_too_must_see_a_steady_lamp_flash():
    head = IntentFilterConfig(intent_source="head")
    steady = [_crop(left=RED)] * 20
    flashing = [_crop(left=AMBER) if (k // 4) % 2 else _crop() for k in range(20)]
    says_left = dict(_model_says_left(), intent=np.array([[0.05, 0.9, 0.0, 0.0, 0.05]]))
    assert set(_published(head, steady, "intent", says_left)) == {int(Intent.OFF)}
    assert _published(head, flashing, "intent", says_left)[-10:] == [int(Intent.LEFT)] * 10


def test_describe_names_the_gate():
    assert "must flash" in IntentFilterConfig().describe()
    assert "no flash gate" in IntentFilterConfig(flash_min_evidence=0.0).describe()
