"""Visibility that holds: UNKNOWN <-> judged changes are published only once they last."""

from __future__ import annotations

import numpy as np
import pytest

from signal_light_node.labels import TASKS, LightStatus
from signal_light_node.runtime import visibility_hold
from signal_light_node.runtime.intent_filter import IntentFilter, IntentFilterConfig

OFF_LIKELY = np.array([0.5, 0.1, 0.4])
UNKNOWN_LIKELY = np.array([0.35, 0.1, 0.55])


def _run(frames, confirm_s, fps=10.0):
    """One track, one light: published probabilities per frame."""
    rows = visibility_hold.initial_rows(1, 1)
    out = []
    for k, p in enumerate(frames):
        before = rows.copy()
        q, new_rows = visibility_hold.step(p[None, None], np.array([k / fps]), rows, confirm_s)
        np.testing.assert_array_equal(rows, before)  # not modified in place
        rows = new_rows
        out.append(q[0, 0])
    return np.array(out)


def test_a_verdict_that_swaps_every_frame_is_not_published():
    frames = [OFF_LIKELY, UNKNOWN_LIKELY] * 10
    q = _run(frames, confirm_s=0.3)
    assert (q.argmax(1) == 0).all()  # the first verdict (judged: OFF) holds
    np.testing.assert_allclose(q.sum(1), 1.0)
    # OFF and ON keep the model's ratio where the probabilities were moved.
    np.testing.assert_allclose(q[1::2, 0] / q[1::2, 1], 0.35 / 0.1)
    # Without the hold the model's swaps go through.
    assert (_run(frames, confirm_s=0.0).argmax(1) == [0, 2] * 10).all()


def test_a_lasting_change_is_published_after_confirm_s():
    frames = [OFF_LIKELY] * 5 + [UNKNOWN_LIKELY] * 10 + [OFF_LIKELY] * 10
    states = _run(frames, confirm_s=0.3).argmax(1)
    # The UNKNOWN from frame 5 lasts 0.3 s at frame 8; OFF again from 15, published at 18.
    assert states.tolist() == [0] * 8 + [2] * 10 + [0] * 7


def test_a_new_track_adopts_the_first_verdict():
    assert _run([UNKNOWN_LIKELY, OFF_LIKELY], confirm_s=1.0).argmax(1).tolist() == [2, 2]


def _probs(light: np.ndarray) -> dict:
    probs = {t: np.eye(k)[[0]] for t, k in zip(TASKS, (5, 3, 3, 3, 4))}
    probs["brake"] = light[None]
    return probs


@pytest.mark.parametrize("confirm_s, expected", [(0.0, [0, 2] * 6), (0.3, [0] * 12)])
def test_the_filter_holds_visibility_when_asked(confirm_s, expected):
    filt = IntentFilter(IntentFilterConfig(visibility_confirm_s=confirm_s))
    rows, states = filt.initial_rows(1), []
    for k, light in enumerate([OFF_LIKELY, UNKNOWN_LIKELY] * 6):
        out = filt.step(_probs(light), int(k * 1e8), rows)
        rows = out.rows
        states.append(int(out.states["brake"][0]))
        assert int(out.probs["brake"][0].argmax()) == states[-1]
    assert states == [int(LightStatus(s)) for s in expected]
    if confirm_s:
        assert "visibility changes after" in filt.config.describe()
