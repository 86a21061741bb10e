"""The intent filter by hand: holds through blinks, ignores spikes, consistent outputs."""

from __future__ import annotations

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.runtime import brake_onset, flash_gate, visibility_hold
from signal_light_node.runtime.intent_filter import (INTENT_OF, ROW_WIDTH, IntentFilter,
                                             IntentFilterConfig)
from signal_light_node.labels import LIGHT_TASKS, TASKS, Intent, LightStatus, intent_from_lights

ON, OFF, UNKNOWN = LightStatus.ON, LightStatus.OFF, LightStatus.UNKNOWN
#: No visibility hold (the node's default holds 0.2 s; test_visibility_hold tests it), so a
#: model's UNKNOWN shows at once; the intent from the held blinkers, whose hold these tests
#: are about (the intent head's margin has tests of its own below).
CONFIG = IntentFilterConfig(on_threshold=0.5, hold_s=0.8, confirm_s=0.15, brake_hold_s=0.0,
                            visibility_confirm_s=0.0, intent_source="lights")
#: The node's defaults, the intent from the held blinkers.
LIGHTS = IntentFilterConfig(intent_source="lights")


def _light(p_on: float, p_unknown: float = 0.02) -> np.ndarray:
    assert p_on + p_unknown <= 1.0
    return np.array([1.0 - p_on - p_unknown, p_on, p_unknown])


def _probs(left: float, right: float, brake: float = 0.0, unknown: float = 0.02) -> dict:
    """One track's model output; the intent head says UNKNOWN, so nothing comes from it."""
    return {"intent": np.array([[0, 0, 0, 0, 1.0]]), "brake": _light(brake, unknown)[None],
            "left": _light(left, unknown)[None], "right": _light(right, unknown)[None],
            "view": np.array([[1.0, 0, 0, 0]])}


def _run(stamps_s, left, right, config=CONFIG, brake=None, intents=None):
    """Filter one track frame by frame; returns the outputs per frame. ``intents``: the
    intent head's 5 probabilities per frame (default: UNKNOWN, as ``_probs`` says)."""
    filt = IntentFilter(config)
    rows = filt.initial_rows(1)
    outs = []
    brake = np.zeros(len(stamps_s)) if brake is None else brake
    for k, (t, a, b, c) in enumerate(zip(stamps_s, left, right, brake)):
        probs = _probs(a, b, c)
        if intents is not None:
            probs["intent"] = np.asarray(intents[k], float)[None]
        out = filt.step(probs, int(round(t * 1e9)), rows)
        rows = out.rows
        outs.append(out)
    return outs


def _states(outs, task):
    return np.array([int(o.states[task][0]) for o in outs])


def _square(stamps_s, hz=1.5, duty=0.5, start=1.0, stop=None, high=0.95, low=0.05):
    """P(ON) of a lamp blinking from ``start`` to ``stop``: high in the lit half only."""
    t = np.asarray(stamps_s)
    lit = ((t - start) * hz) % 1.0 < duty
    lit &= t >= start
    if stop is not None:
        lit &= t < stop
    return np.where(lit, high, low)


def _irregular_stamps(duration_s=8.0, seed=0):
    """Stamps at 10-30 fps with jitter."""
    rng = np.random.default_rng(seed)
    return np.cumsum(rng.uniform(1 / 30, 1 / 10, size=int(duration_s * 30)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_square_wave_is_held_on_after_onset_and_off_within_hold_after_the_last_flash(seed):
    stamps = _irregular_stamps(seed=seed)
    stamps = stamps[stamps < 7.0]
    left = _square(stamps, start=1.0, stop=5.0)
    outs = _run(stamps, left, np.full(len(stamps), 0.05))
    state = _states(outs, "left")
    flashes = stamps[left > 0.5]
    onset = flashes[flashes - flashes[0] >= CONFIG.confirm_s][0]
    last_flash = flashes[-1]
    assert np.all(state[stamps < 1.0] == OFF)
    # ON from the first frame whose flashes span confirm_s, through every dark half.
    held = (stamps >= onset) & (stamps <= last_flash + CONFIG.hold_s)
    assert np.all(state[held] == ON)
    assert np.all(state[~held] == OFF)
    intent = _states(outs, "intent")
    assert np.all(intent[held] == Intent.LEFT) and np.all(intent[~held] == Intent.OFF)
    assert np.all(_states(outs, "right") == OFF)


@pytest.mark.parametrize("config", [CONFIG, LIGHTS], ids=["0.15s", "default"])
@pytest.mark.parametrize("fps", [10, 30])
def test_one_frame_spikes_never_make_a_blinker_nor_hazard(config, fps):
    stamps = np.arange(0, 6, 1 / fps)
    spike = np.full(len(stamps), 0.05)
    spike[[fps, 3 * fps, 5 * fps]] = 0.95  # single frames, 2 s apart
    outs = _run(stamps, spike, spike, config)
    assert np.all(_states(outs, "left") != ON) and np.all(_states(outs, "right") != ON)
    assert Intent.HAZARD not in _states(outs, "intent")
    # The capped P(ON) of a spike frame is below the published state's probability.
    out = outs[fps]
    assert out.states["left"][0] == OFF
    assert out.probs["left"][0, 1] <= out.probs["left"][0, 0]


def test_steady_zero_is_off():
    stamps = np.arange(0, 3, 0.1)
    outs = _run(stamps, np.zeros(len(stamps)), np.zeros(len(stamps)))
    assert np.all(_states(outs, "left") == OFF) and np.all(_states(outs, "intent") == Intent.OFF)


def test_both_sides_flashing_is_hazard_one_side_is_left_or_right():
    stamps = np.arange(0, 5, 1 / 12)
    wave = _square(stamps, hz=1.2, duty=0.4, start=0.5)
    quiet = np.full(len(stamps), 0.03)
    late = stamps > 1.5
    assert set(_states(_run(stamps, wave, wave), "intent")[late]) == {Intent.HAZARD}
    assert set(_states(_run(stamps, wave, quiet), "intent")[late]) == {Intent.LEFT}
    assert set(_states(_run(stamps, quiet, wave), "intent")[late]) == {Intent.RIGHT}


def test_switching_sides_releases_the_silent_side_instead_of_making_hazard():
    stamps = np.arange(0, 6, 0.1)
    right = _square(stamps, hz=1.5, start=0.0, stop=2.6)
    left = _square(stamps, hz=1.5, start=2.8)
    intent = _states(_run(stamps, left, right), "intent")
    assert Intent.HAZARD not in intent
    assert intent[stamps < 2.5][-1] == Intent.RIGHT and intent[-1] == Intent.LEFT


def test_model_unknown_passes_through_and_the_hold_goes_on():
    filt = IntentFilter(CONFIG)
    rows = filt.initial_rows(1)
    for t in (0.0, 0.1, 0.2):
        rows = filt.step(_probs(0.9, 0.0), int(t * 1e9), rows).rows
    hidden = _probs(0.1, 0.0, unknown=0.8)
    out = filt.step(hidden, int(0.3e9), rows)
    assert out.states["left"][0] == UNKNOWN
    np.testing.assert_allclose(out.probs["left"], hidden["left"])
    assert out.states["intent"][0] == intent_from_lights(UNKNOWN, OFF)
    # Seen again in its dark half: still held ON.
    assert filt.step(_probs(0.1, 0.0), int(0.4e9), out.rows).states["left"][0] == ON


@pytest.mark.parametrize("source,blinkers", [("lights", "filter"), ("head", "filter"),
                                              ("head", "intent")])
def test_probabilities_sum_to_one_and_agree_with_the_states(source, blinkers):
    rng = np.random.default_rng(4)
    n, filt = 64, IntentFilter(IntentFilterConfig(brake_hold_s=0.3, intent_source=source,
                                                  blinker_source=blinkers))
    rows = filt.initial_rows(n)
    for k in range(40):
        probs = {t: rng.dirichlet(np.full(len(Intent) if t == "intent" else 4 if t == "view"
                                          else 3, 0.5), size=n) for t in TASKS}
        stamps = np.int64(k * 80e6) + rng.integers(0, 30e6, size=n)
        out = filt.step(probs, stamps, rows)
        rows = out.rows
        for task in TASKS:
            p = out.probs[task]
            assert p.shape == probs[task].shape and np.all(p >= -1e-12)
            np.testing.assert_allclose(p.sum(axis=1), 1.0, atol=1e-9)
            if task != "intent" or source == "head":  # the published class is most likely
                chosen = p[np.arange(n), out.states[task]]
                assert np.all(chosen >= p.max(axis=1) - 1e-9), task
        if source == "lights":
            np.testing.assert_array_equal(out.states["intent"],
                                          INTENT_OF[out.states["left"], out.states["right"]])
        np.testing.assert_array_equal(out.states["view"], probs["view"].argmax(1))


def test_held_on_probability_is_the_last_strong_one():
    outs = _run([0.0, 0.1, 0.2, 0.3, 0.4], [0.9, 0.9, 0.8, 0.2, 0.1], [0] * 5)
    left = [o.probs["left"][0] for o in outs]
    assert [int(o.states["left"][0]) for o in outs] == [OFF, OFF, ON, ON, ON]
    assert left[2][1] == pytest.approx(0.8) and left[4][1] == pytest.approx(0.8)
    # OFF and UNKNOWN keep the model's 0.88 : 0.02 proportion.
    assert left[4][0] / left[4][2] == pytest.approx(0.88 / 0.02)


def test_tracks_are_independent_and_stamps_may_differ_per_track():
    filt = IntentFilter(CONFIG)
    rows = filt.initial_rows(2)
    probs = {t: np.repeat(p, 2, axis=0) for t, p in _probs(0.9, 0.0).items()}
    for t in (0.0, 0.1, 0.2):
        rows = filt.step(probs, np.array([int(t * 1e9), int(t * 1e8)]), rows).rows
    out = filt.step(probs, np.array([int(0.3e9), int(0.03e9)]), rows)
    # Track 0's flashes span 0.3 s (confirmed), track 1's only 0.03 s.
    assert out.states["left"].tolist() == [ON, OFF]


def test_brake_is_held_only_with_a_brake_hold():
    stamps = np.arange(0, 1, 0.1)
    brake = np.array([0.9, 0.9, 0.3, 0.9, 0.9, 0.1, 0.1, 0.1, 0.1, 0.1])
    quiet = np.zeros(len(stamps))
    raw = _states(_run(stamps, quiet, quiet, CONFIG, brake), "brake")
    assert raw.tolist() == [ON, ON, OFF, ON, ON, OFF, OFF, OFF, OFF, OFF]
    cfg = IntentFilterConfig(brake_hold_s=0.25)
    held = _states(_run(stamps, quiet, quiet, cfg, brake), "brake")
    assert held.tolist() == [ON, ON, ON, ON, ON, ON, ON, OFF, OFF, OFF]


def test_disabled_filter_is_the_raw_model():
    probs = _probs(0.9, 0.0)
    filt = IntentFilter(IntentFilterConfig(enabled=False))
    out = filt.step(probs, 0, filt.initial_rows(1))
    assert out.states["intent"][0] == Intent.UNKNOWN and out.states["left"][0] == ON
    for task in TASKS:
        np.testing.assert_array_equal(out.probs[task], probs[task])


def test_rows_are_fixed_size_and_not_modified_in_place():
    rows = IntentFilter.initial_rows(3)
    assert rows.shape == (3, ROW_WIDTH)
    assert ROW_WIDTH == (3 + visibility_hold.FIELDS) * len(LIGHT_TASKS) + flash_gate.WIDTH \
        + brake_onset.FIELDS + 1  # the intent head's published class
    before = rows.copy()
    probs = {t: np.repeat(p, 3, axis=0) for t, p in _probs(0.9, 0.9).items()}
    out = IntentFilter(CONFIG).step(probs, 0, rows, np.full((3, 2), 50.0))
    np.testing.assert_array_equal(rows, before)
    assert out.rows.shape == rows.shape and not np.array_equal(out.rows, rows, equal_nan=True)


@pytest.mark.parametrize("kwargs, word", [
    ({"on_threshold": 0.0}, "on_threshold"), ({"on_threshold": 1.5}, "on_threshold"),
    ({"hold_s": -0.1}, "hold_s"), ({"confirm_s": float("nan")}, "confirm_s"),
    ({"brake_hold_s": "x"}, "brake_hold_s"), ({"enabled": "yes"}, "enabled"),
    ({"flash_min_evidence": 1.0}, "flash_min_evidence"),
    ({"flash_min_evidence": -0.1}, "flash_min_evidence"),
    ({"brake_released_below": 1.0}, "brake_released_below"),
    ({"brake_onset_shift": -1.0}, "brake_onset_shift"),
    ({"brake_onset_rise": float("nan")}, "brake_onset_rise"),
    ({"brake_unreleased_shift": float("inf")}, "brake_unreleased_shift"),
    ({"brake_hysteresis": -0.5}, "brake_hysteresis"),
    ({"flash_window_s": 0.0}, "flash_window_s"), ({"flash_window_s": -1.0}, "flash_window_s"),
])
def test_bad_settings_are_config_errors(kwargs, word):
    with pytest.raises(ConfigError, match=word):
        IntentFilterConfig(**kwargs)


def test_bad_inputs_are_config_errors():
    filt = IntentFilter()
    with pytest.raises(ConfigError, match="rows"):
        filt.step(_probs(0, 0), 0, np.zeros((1, 2)))
    probs = _probs(0, 0)
    del probs["view"]
    with pytest.raises(ConfigError, match="view"):
        filt.step(probs, 0, filt.initial_rows(1))


def _head_track(intents, config):
    """Filter one track whose intent head says ``intents`` (rows of 5 probabilities) at
    10 fps; the blinker heads say OFF throughout."""
    off = np.zeros(len(intents))
    return _run(np.arange(len(intents)) * 0.1, off, off, config, intents=intents)


def test_intent_from_the_head_switches_only_past_the_margin():
    head = IntentFilterConfig(intent_source="head", intent_margin=0.2, visibility_confirm_s=0.0)
    off, left = Intent.OFF, Intent.LEFT
    intents = [[0.7, 0.3, 0, 0, 0],   # first frame: the most likely
               [0.45, 0.55, 0, 0, 0],  # LEFT leads by 0.10: kept OFF
               [0.3, 0.7, 0, 0, 0],   # by 0.40: LEFT
               [0.55, 0.45, 0, 0, 0],  # OFF leads by 0.10: kept LEFT
               [0.8, 0.2, 0, 0, 0]]   # by 0.60: OFF
    outs = _head_track(intents, head)
    assert _states(outs, "intent").tolist() == [off, off, left, left, off]
    for out in outs:  # the published class is the most likely published one
        p = out.probs["intent"][0]
        assert p[out.states["intent"][0]] == pytest.approx(p.max())
        assert p.sum() == pytest.approx(1.0)
    # with no margin it is the head's argmax; from the lights, the blinkers' OFF
    no_margin = IntentFilterConfig(intent_source="head", intent_margin=0.0,
                                   visibility_confirm_s=0.0)
    assert _states(_head_track(intents, no_margin), "intent").tolist() == \
        [off, left, left, off, off]
    assert set(_states(_head_track(intents, CONFIG), "intent").tolist()) == {off}


def test_intent_from_the_head_leaves_the_lights_as_the_filter_publishes_them():
    stamps = np.arange(0, 4.0, 0.05)
    left = _square(stamps)
    lights, head = CONFIG, IntentFilterConfig(
        **{**CONFIG.__dict__, "intent_source": "head"})
    a, b = _run(stamps, left, np.zeros_like(left), lights), \
        _run(stamps, left, np.zeros_like(left), head)
    for task in ("left", "right", "brake"):
        assert _states(a, task).tolist() == _states(b, task).tolist()
    assert (_states(a, "intent") == Intent.LEFT).any()
    assert (_states(b, "intent") == Intent.UNKNOWN).all()  # _probs' intent head: UNKNOWN


#: Blinkers read off the intent head, which switches on its argmax (no margin).
FROM_INTENT = IntentFilterConfig(intent_source="head", intent_margin=0.0, blinker_source="intent",
                                 visibility_confirm_s=0.0)
_OFF, _LEFT, _RIGHT, _HAZARD, _UNKNOWN = (np.eye(len(Intent))[i] for i in
                                          (Intent.OFF, Intent.LEFT, Intent.RIGHT, Intent.HAZARD,
                                           Intent.UNKNOWN))


def test_blinkers_read_off_the_intent_name_its_sides():
    intents = [_OFF, _LEFT, _LEFT, _HAZARD, _RIGHT, _OFF]
    outs = _head_track(intents, FROM_INTENT)  # the blinker heads say OFF throughout
    assert _states(outs, "left").tolist() == [OFF, ON, ON, ON, OFF, OFF]
    assert _states(outs, "right").tolist() == [OFF, OFF, OFF, ON, ON, OFF]
    np.testing.assert_array_equal(_states(outs, "intent"),
                                  INTENT_OF[_states(outs, "left"), _states(outs, "right")])
    for out in outs:  # the published class of each blinker is its most likely
        for task in ("left", "right"):
            p = out.probs[task][0]
            assert p[out.states[task][0]] == pytest.approx(p.max())
    # the filter's own blinkers from the same heads: OFF throughout
    own = _head_track(intents, IntentFilterConfig(**{**FROM_INTENT.__dict__,
                                                     "blinker_source": "filter"}))
    assert set(_states(own, "left").tolist()) == set(_states(own, "right").tolist()) == {OFF}


def test_a_judged_intent_holds_back_the_blinker_the_filter_would_publish_on():
    stamps = np.arange(0, 4.0, 0.05)
    left = _square(stamps)
    outs = _run(stamps, left, np.zeros_like(left), FROM_INTENT, intents=[_OFF] * len(stamps))
    assert set(_states(outs, "left").tolist()) == {OFF}
    # where the intent is UNKNOWN the filter's own hold stands
    own = _run(stamps, left, np.zeros_like(left), FROM_INTENT, intents=[_UNKNOWN] * len(stamps))
    held = _run(stamps, left, np.zeros_like(left), IntentFilterConfig(
        **{**FROM_INTENT.__dict__, "blinker_source": "filter"}))
    assert (_states(own, "left") == ON).any()
    assert _states(own, "left").tolist() == _states(held, "left").tolist()


def test_a_blinker_that_cannot_be_seen_stays_unknown_whatever_the_intent():
    filt = IntentFilter(FROM_INTENT)
    probs = _probs(0.0, 0.0, unknown=0.9)
    probs["intent"] = _LEFT[None]
    out = filt.step(probs, 0, filt.initial_rows(1))
    assert out.states["left"][0] == out.states["right"][0] == UNKNOWN
    assert out.states["intent"][0] == Intent.LEFT
    # a first ON frame (not yet confirmed) the filter holds back to UNKNOWN stays UNKNOWN
    probs["left"] = np.array([[0.1, 0.5, 0.4]])
    assert filt.step(probs, 0, filt.initial_rows(1)).states["left"][0] == UNKNOWN


@pytest.mark.parametrize("changes,match", [({"intent_source": "model"}, "intent_source"),
                                           ({"intent_margin": 1.0}, "intent_margin"),
                                           ({"intent_margin": -0.1}, "intent_margin"),
                                           ({"blinker_source": "head"}, "blinker_source"),
                                           ({"blinker_source": "intent",
                                             "intent_source": "lights"}, "intent_source")])
def test_intent_source_settings_are_checked(changes, match):
    with pytest.raises(ConfigError, match=match):
        IntentFilterConfig(**changes)
