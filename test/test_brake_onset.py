"""A brake seen released gets more ON from then on; one never seen released does not
(``runtime.brake_onset`` and the filter's ``brake_released_below``)."""

import numpy as np
import pytest

from signal_light_node.runtime import brake_onset
from signal_light_node.runtime.intent_filter import IntentFilter, IntentFilterConfig


def test_shift_moves_on_against_off_and_keeps_unknown():
    p = np.array([[0.6, 0.3, 0.1], [0.0, 0.0, 1.0]])
    out = brake_onset.shift_on(p, np.array([1.0, 1.0]))
    assert out[0, 2] == pytest.approx(0.1) and out[0, :2].sum() == pytest.approx(0.9)
    assert out[0, 1] / out[0, 0] == pytest.approx(0.5 * np.e)
    np.testing.assert_array_equal(out[1], [0.0, 0.0, 1.0])  # nothing judged, nothing moved
    np.testing.assert_array_equal(p[0], [0.6, 0.3, 0.1])


def test_released_from_the_frame_it_is_seen_and_only_when_judged():
    rows = brake_onset.initial_rows(3)
    p = np.array([[0.97, 0.02, 0.01],   # judged, clearly released
                  [0.05, 0.01, 0.94],   # UNKNOWN: says nothing about the lamps
                  [0.60, 0.30, 0.10]])  # judged, not released
    out, rows = brake_onset.step(p, rows, brake_onset.Settings(0.05, 1.0))
    np.testing.assert_array_equal(rows[:, 0], [1.0, 0.0, 0.0])
    assert out[0, 1] > p[0, 1] and out[2, 1] == pytest.approx(p[2, 1])
    later, rows2 = brake_onset.step(np.repeat([[0.6, 0.4, 0.0]], 3, 0), rows,
                                    brake_onset.Settings(0.05, 1.0))
    np.testing.assert_array_equal(rows2[:, 0], rows[:, 0])  # a flag once set stays
    assert later[0].argmax() == 1 and later[1].argmax() == 0 and later[2].argmax() == 0


def test_a_rise_is_measured_against_the_tracks_own_lowest_level():
    rows = brake_onset.initial_rows(2)
    assert np.isnan(rows[:, 1]).all()
    # Track 0 was released far down (P 0.001), track 1 only just (P 0.04).
    for q in ([0.001, 0.04], [0.3, 0.3]):
        p = np.array([[1 - q[0], q[0], 0.0], [1 - q[1], q[1], 0.0]])
        out, rows = brake_onset.step(p, rows, brake_onset.Settings(0.05, 1.0, rise=4.0))
    np.testing.assert_array_equal(rows[:, 0], [1.0, 1.0])
    np.testing.assert_allclose(rows[:, 1], np.log([0.001 / 0.999, 0.04 / 0.96]))
    # logit(0.3) - logit(0.001) = 6.1 >= 4: shifted; - logit(0.04) = 2.3 < 4: not.
    assert out[0, 1] > 0.3 and out[1, 1] == pytest.approx(0.3)
    unknown, rows2 = brake_onset.step(np.array([[0.0, 0.0, 1.0]] * 2), rows,
                                      brake_onset.Settings(0.05, 1.0, rise=4.0))
    np.testing.assert_array_equal(rows2, rows)  # an UNKNOWN frame moves no field


def test_until_released_a_brake_takes_the_unreleased_shift():
    rows = brake_onset.initial_rows(1)
    lit = np.array([[0.45, 0.55, 0.0]])  # a tail lamp lit from the first frame
    settings = brake_onset.Settings(0.2, 0.5, unreleased_shift=-1.0)
    out, rows = brake_onset.step(lit, rows, settings)
    assert out[0].argmax() == 0 and rows[0, 0] == 0.0
    out, rows = brake_onset.step(np.array([[0.9, 0.1, 0.0]]), rows, settings)
    assert rows[0, 0] == 1.0  # seen released: the strict shift is gone
    out, rows = brake_onset.step(lit, rows, settings)
    assert out[0, 1] / out[0, 0] == pytest.approx(0.55 / 0.45 * np.exp(0.5))


def test_hysteresis_keeps_a_brake_on_through_a_shallow_dip_not_a_release():
    settings = brake_onset.Settings(hysteresis=1.0)
    rows, states = brake_onset.initial_rows(1), []
    for q in (0.2, 0.6, 0.4, 0.0, 0.4, 0.1):  # on, shallow dip, UNKNOWN, dip, release
        p = np.array([[1 - q, q, 0.0]]) if q else np.array([[0.0, 0.0, 1.0]])
        out, rows = brake_onset.step(p, rows, settings)
        states.append(int(out[0].argmax()))
    assert states == [0, 1, 1, 2, 1, 0]
    assert brake_onset.step(np.array([[0.6, 0.4, 0.0]]), brake_onset.initial_rows(1),
                            settings)[0][0].argmax() == 0  # no hysteresis from OFF


def _brake_states(p_on, config):
    filt = IntentFilter(config)
    rows, states = filt.initial_rows(1), []
    for i, q in enumerate(p_on):
        probs = {"intent": np.array([[1.0, 0, 0, 0, 0]]), "view": np.array([[1.0, 0, 0, 0]]),
                 "brake": np.array([[1.0 - q, q, 0.0]]), "left": np.array([[1.0, 0, 0]]),
                 "right": np.array([[1.0, 0, 0]])}
        out = filt.step(probs, i * 100_000_000, rows)
        rows = out.rows
        states.append(int(out.states["brake"][0]))
    return states


def test_a_rise_after_a_release_is_a_brake_a_steady_middling_lamp_is_not():
    on = IntentFilterConfig(brake_released_below=0.05, brake_onset_shift=1.0)
    seen_released = [0.02, 0.02, 0.4, 0.4, 0.4]
    steady_tail = [0.4] * 5
    assert _brake_states(seen_released, on) == [0, 0, 1, 1, 1]
    assert _brake_states(steady_tail, on) == [0] * 5
    assert _brake_states(seen_released, IntentFilterConfig()) == [0] * 5  # off by default
    dip = [0.6, 0.4, 0.4]
    assert _brake_states(dip, IntentFilterConfig()) == [1, 0, 0]
    assert _brake_states(dip, IntentFilterConfig(brake_hysteresis=1.0)) == [1, 1, 1]
    assert "once seen released" in on.describe()


def test_the_node_parameters_and_the_cli_options_reach_the_filter():
    from signal_light_node.cli import build_parser
    from signal_light_node.commands.options import intent_filter_from_args
    from signal_light_node.ros.params import DetectorParams

    params = DetectorParams(filter_brake_released_below=0.05, filter_brake_onset_shift=2.0,
                            filter_brake_onset_rise=3.0, filter_brake_unreleased_shift=-1.0,
                            filter_brake_hysteresis=1.5)
    config = params.intent_filter_config
    assert config.brake_onset_settings == (0.05, 2.0, 3.0, -1.0, 1.5)
    args = build_parser(["evaluate"]).parse_args(
        ["evaluate", "--out", "OUT", "--filter-brake-released-below", "0.05",
         "--filter-brake-onset-shift", "2", "--filter-brake-onset-rise", "3",
         "--filter-brake-unreleased-shift", "-1", "--filter-brake-hysteresis", "1.5"])
    assert intent_filter_from_args(args) == config
