"""Lamps beyond a vehicle inside its crop (``foreign_lamp``, ``synth.foreign_lamps``): drawn
where they are placed, behind the body, lit as their kind says, and never in the truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.labels import Intent, View
from signal_light_node.synth import SceneRenderer
from signal_light_node.synth.foreign_lamps import (FOREIGN_KINDS, ForeignLamp,
                                                   high_foreign_lamp, lamp_centre,
                                                   sample_foreign_lamp, visible_share)

from scene_helpers import CLEAN, first_frame_vehicles, split_overrides

OVER_THE_ROOF = ForeignLamp(kind="red_steady", u=0.0, v=-0.12, radius=0.06, level=1.0, hz=1.5,
                            duty=0.5, phase=0.0, spell_s=1.0, seed=3)


def _frames(lamp, n=1, lighting="night", share=1.0):
    """Frames of one parked, lit car seen from behind, with ``lamp`` beyond it (or none)."""
    spec = dict(view=View.BEHIND, kind="car", lamp_design="amber", tech="led", intent=Intent.OFF,
                brake=False, lights_on=True, chmsl=False, width_px=150.0, center_x=320.0,
                speed=0.0, shear=0.0, roll=0.0, specular=False)
    renderer = SceneRenderer(seed=5, fps=10.0, lighting=lighting, vehicles=[spec], horizon=0.42,
                             foreign_lamp=share, **CLEAN)
    renderer._setup()
    renderer._traffic.vehicles[0].foreign = lamp  # the lamp under test, not a drawn one
    # A parked car: no traffic step is needed between frames.
    return [renderer._render(i, i / renderer.fps) for i in range(n)]


def _red(frame, x, y, r):
    y0, y1, x0, x1 = (int(round(c)) for c in (y - r, y + r + 1, x - r, x + r + 1))
    patch = frame.image[max(y0, 0):y1, max(x0, 0):x1].astype(float)
    return float(np.clip(patch[..., 2] - patch[..., 1], 0, None).mean())


def test_a_lamp_over_the_roof_shows_there_and_leaves_the_truth_alone():
    (plain,) = _frames(None)
    (with_lamp,) = _frames(OVER_THE_ROOF)
    box = with_lamp.vehicles[0].box
    x, y, r = lamp_centre(OVER_THE_ROOF, box)
    assert y < box[1]  # over the roof
    assert _red(with_lamp, x, y, r) > _red(plain, x, y, r) + 40
    truth = lambda f: [(v.track_id, v.brake, v.left, v.right, v.intent, v.view, v.box)  # noqa: E731
                       for v in f.vehicles]
    assert truth(with_lamp) == truth(plain)


def test_the_body_hides_a_lamp_behind_it():
    inside = replace(OVER_THE_ROOF, v=0.5, radius=0.05)  # behind the middle of the rear face
    (plain,) = _frames(None)
    (with_lamp,) = _frames(inside)
    x, y, r = lamp_centre(inside, with_lamp.vehicles[0].box)
    core = slice(int(y - r / 2), int(y + r / 2) + 1), slice(int(x - r / 2), int(x + r / 2) + 1)
    # Only its glow can reach over the body: the lens itself never shows.
    assert np.abs(with_lamp.image[core].astype(int) - plain.image[core]).max() < 40


def test_an_amber_lamp_flashes_and_a_switching_red_one_changes():
    amber = replace(OVER_THE_ROOF, kind="amber_blink", hz=1.25, duty=0.5, phase=0.0)
    assert [amber.lit(t) for t in (0.1, 0.5, 0.9, 1.3)] == [True, False, True, False]
    switching = replace(OVER_THE_ROOF, kind="red_switching", spell_s=1.0)
    states = {switching.lit(t + 0.5) for t in range(40)}
    assert states == {True, False}
    assert all(switching.lit(t + 0.1) == switching.lit(t + 0.9) for t in range(10))  # one spell
    frames = _frames(amber, n=10)
    x, y, r = lamp_centre(amber, frames[0].vehicles[0].box)
    lit = [_red(f, x, y, r) + float(f.image[int(y), int(x), 1]) for f in frames]
    assert max(lit) > min(lit) + 60


def test_samples_cover_every_kind_and_both_places():
    rng = np.random.default_rng(0)
    lamps = [sample_foreign_lamp(rng) for _ in range(400)]
    assert {lamp.kind for lamp in lamps} == set(FOREIGN_KINDS)
    above = [lamp for lamp in lamps if lamp.v < 0]
    beside = [lamp for lamp in lamps if abs(lamp.u) > 0.45]
    assert 0.45 < len(above) / len(lamps) < 0.75 and len(above) + len(beside) == len(lamps)
    assert all(0.9 <= lamp.hz <= 2.1 for lamp in lamps)  # a blinker's legal rate


def test_the_share_picks_vehicles_and_keeps_the_scene():
    plain = first_frame_vehicles(13, "night")
    half = first_frame_vehicles(13, "night", foreign_lamp=0.5)
    key = lambda vs: [(v.track_id, v.view, v.kind, v.colour, v.lights_on, v.X, v.Z)  # noqa: E731
                      for v in vs]
    assert key(plain) == key(half)
    assert all(v.foreign is None for v in plain)
    assert 0.25 < np.mean([v.foreign is not None for v in half]) < 0.75


def test_high_lamps_sit_red_over_the_middle_of_the_roof_inside_the_crop():
    rng = np.random.default_rng(4)
    lamps = [high_foreign_lamp(sample_foreign_lamp(rng), rng) for _ in range(200)]
    assert {lamp.kind for lamp in lamps} == {"red_steady", "red_switching"}
    assert all(abs(lamp.u) <= 0.08 and -0.15 < lamp.v < 0 for lamp in lamps)  # crop margin 0.15
    assert all(2.0 <= lamp.aspect <= 4.0 for lamp in lamps)


def test_a_high_lamp_is_drawn_wide():
    wide = replace(OVER_THE_ROOF, v=-0.06, radius=0.04, aspect=3.0)
    (plain,) = _frames(None)
    (round_,) = _frames(replace(wide, aspect=1.0))
    (with_wide,) = _frames(wide)
    x, y, r = lamp_centre(wide, with_wide.vehicles[0].box)
    off = 2.0 * r  # beside the round lens, inside the wide one
    assert _red(with_wide, x + off, y, r / 2) > _red(round_, x + off, y, r / 2) + 40
    assert abs(_red(round_, x + off, y, r / 2) - _red(plain, x + off, y, r / 2)) < 40


def test_the_high_share_moves_picked_lamps_and_keeps_the_others():
    some = first_frame_vehicles(13, "night", foreign_lamp=0.8)
    high = first_frame_vehicles(13, "night", foreign_lamp=0.8, foreign_high=0.5)
    pairs = [(a.foreign, b.foreign) for a, b in zip(some, high) if a.foreign is not None]
    assert [b is not None for _, b in pairs] == [True] * len(pairs)
    moved = [a != b for a, b in pairs]
    assert any(moved) and not all(moved)
    for a, b in pairs:
        if a != b:
            assert (b.level, b.hz, b.seed, b.radius) == (a.level, a.hz, a.seed, a.radius)


def test_without_the_share_frames_are_as_before():
    a = next(iter(SceneRenderer(seed=21, lighting="dusk", n_vehicles=5).frames(1)))
    b = next(iter(SceneRenderer(seed=21, lighting="dusk", n_vehicles=5, foreign_lamp=0.0).frames(1)))
    assert np.array_equal(a.image, b.image)


def test_a_bad_share_is_refused_and_the_split_command_hands_it_on(monkeypatch, tmp_path):
    with pytest.raises(ConfigError, match="foreign_lamp"):
        SceneRenderer(seed=1, foreign_lamp=2.0)
    assert split_overrides(monkeypatch, tmp_path / "pool", ["--foreign-lamp", "0.3"]) == \
        {"foreign_lamp": 0.3}
    with pytest.raises(ConfigError, match="foreign_high"):
        SceneRenderer(seed=1, foreign_high=-0.1)
    assert split_overrides(monkeypatch, tmp_path / "pool2", ["--foreign-high", "0.5"]) == \
        {"foreign_high": 0.5}


def test_the_visible_share_reads_the_coverage_inside_the_image_only():
    coverage = np.zeros((40, 60), np.uint8)
    coverage[:, :30] = 255
    assert visible_share(15.0, 20.0, 4.0, coverage) == 0.0
    assert visible_share(45.0, 20.0, 4.0, coverage) == 1.0
    assert 0.3 < visible_share(30.0, 20.0, 4.0, coverage) < 0.7
    # Partly or wholly past the border (a lamp beyond a vehicle leaving the image).
    assert visible_share(-2.0, 20.0, 4.0, coverage) == 0.0
    for x, y in ((-9.0, 20.0), (70.0, 20.0), (30.0, -9.0), (30.0, 50.0)):
        assert visible_share(x, y, 4.0, coverage) == 1.0
