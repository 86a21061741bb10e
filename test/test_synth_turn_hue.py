"""Blinkers in any hue (``turn_hue``, ``synth.lamps.recolour_turn_lamps``): a share of
vehicles whose blinkers, and the amber markers that match them, shine in a random hue, so
that a blinker can only be learnt by its flashing on one side."""

from __future__ import annotations

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.labels import Intent, LightStatus, View
from signal_light_node.synth import SceneRenderer
from signal_light_node.synth.lamps import (TURN_HUE_SATURATION, random_hue_colour,
                                           recolour_turn_lamps, rear_lamps, sample_lamp_style)

from scene_helpers import first_frame_vehicles, split_overrides

CLEAN = dict(distractors=False, effects=False, poles=0, weather="clear", respawn=False, shake=False)


def _saturation(bgr) -> float:
    hi, lo = max(bgr), min(bgr)
    return (hi - lo) / hi


def test_random_hues_cover_the_wheel_at_full_value():
    rng = np.random.default_rng(0)
    colours = np.array([random_hue_colour(rng) for _ in range(400)])
    assert np.allclose(colours.max(axis=1), 255.0)
    sats = [_saturation(c) for c in colours]
    assert TURN_HUE_SATURATION[0] - 1e-9 <= min(sats) and max(sats) <= TURN_HUE_SATURATION[1] + 1e-9
    # Each of B, G, R is the strongest channel for a fair share of the draws.
    strongest = np.bincount(colours.argmax(axis=1), minlength=3) / len(colours)
    assert strongest.min() > 0.2


def test_only_the_amber_lamps_change_colour():
    rng = np.random.default_rng(4)
    style = sample_lamp_style(rng, "car", design="amber", family=0)
    lamps = rear_lamps(style, "car", rng, 0.3)
    recoloured, new_style = recolour_turn_lamps(lamps, style, np.random.default_rng(9))
    assert new_style.amber != style.amber and new_style.red == style.red
    assert [(l.role, l.side, l.rect) for l in recoloured] == [(l.role, l.side, l.rect) for l in lamps]
    for before, after in zip(lamps, recoloured):
        if before.role == "turn":
            assert after.emit == new_style.amber
        else:
            assert after.emit == before.emit
        assert after.lens == before.lens
    assert any(l.role == "turn" for l in lamps)
    # The input is left as it was.
    assert any(l.emit == style.amber for l in lamps)


def test_red_combined_blinkers_stay_red():
    rng = np.random.default_rng(2)
    style = sample_lamp_style(rng, "car", design="red_combined", family=0)
    lamps = rear_lamps(style, "car", rng, 0.3)
    recoloured, _ = recolour_turn_lamps(lamps, style, np.random.default_rng(3))
    for before, after in zip(lamps, recoloured):
        if before.role == "turn_tail":
            assert after.emit == before.emit == style.red


def _blinking_car(turn_hue: float):
    """One parked car seen from behind by day, left blinker on: its vehicle and frames."""
    spec = dict(view=View.BEHIND, kind="car", lamp_design="amber", tech="led", intent=Intent.LEFT,
                brake=False, lights_on=False, width_px=160.0, center_x=320.0, speed=0.0,
                shear=0.0, roll=0.0, specular=False, blink_hz=1.0, duty=0.5, phase=0.0)
    renderer = SceneRenderer(seed=5, fps=10.0, lighting="day", vehicles=[spec], horizon=0.42,
                             turn_hue=turn_hue, **CLEAN)
    frames = list(renderer.frames(10))
    return renderer._traffic.vehicles[0], frames


def test_a_recoloured_blinker_still_flashes_and_keeps_its_truth():
    plain, plain_frames = _blinking_car(0.0)
    hued, hued_frames = _blinking_car(1.0)
    assert plain.style.amber != hued.style.amber
    for a, b in zip(plain_frames, hued_frames):
        assert (a.vehicles[0].left, a.vehicles[0].right, a.vehicles[0].brake) == \
            (b.vehicles[0].left, b.vehicles[0].right, b.vehicles[0].brake)
    assert LightStatus.ON in {f.vehicles[0].left for f in hued_frames}
    x0, y0, x1, y1 = (int(round(c)) for c in hued_frames[0].vehicles[0].box)
    left_half = [f.image[y0:y1, x0:(x0 + x1) // 2].astype(float) for f in hued_frames]
    # Lit and dark halves of the blink differ by a lamp's worth of light, in the new hue:
    # its strongest channel is not amber's red here, and it is the one that changes most.
    strongest = int(np.argmax(hued.style.amber))
    assert strongest != 2
    lit = max(range(len(left_half)), key=lambda i: left_half[i].sum())
    dark = min(range(len(left_half)), key=lambda i: left_half[i].sum())
    diff = left_half[lit] - left_half[dark]
    assert diff.max() > 100
    bright = diff.max(axis=-1) > 0.5 * diff.max()
    assert int(np.argmax(diff[bright].mean(axis=0))) == strongest


def test_the_share_picks_vehicles_and_keeps_everything_else():
    plain = first_frame_vehicles(13, "day")
    half = first_frame_vehicles(13, "day", turn_hue=0.5)
    assert [(v.track_id, v.view, v.kind, v.colour, v.style.red) for v in plain] == \
        [(v.track_id, v.view, v.kind, v.colour, v.style.red) for v in half]
    changed = [a.style.amber != b.style.amber for a, b in zip(plain, half)]
    assert 0.2 < np.mean(changed) < 0.8


def test_a_bad_share_is_refused_and_the_split_command_passes_it_on(monkeypatch, tmp_path):
    with pytest.raises(ConfigError, match="turn_hue"):
        SceneRenderer(seed=1, turn_hue=2.0)
    assert split_overrides(monkeypatch, tmp_path / "pool", ["--turn-hue", "0.5"]) == {"turn_hue": 0.5}
