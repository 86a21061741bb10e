"""Tests of the procedural scene renderer: determinism, label semantics, geometry."""

from __future__ import annotations

import numpy as np
import pytest

from signal_light_node.boxes import TrackBox
from signal_light_node.errors import ConfigError
from signal_light_node.labels import Intent, LightStatus, View, intent_from_lights
from signal_light_node.synth import RenderedFrame, SceneRenderer, VehicleTruth, scene, truth

# A clean stage: one parked vehicle, no distractors, no camera effects, no random poles.
CLEAN = dict(distractors=False, effects=False, poles=0, weather="clear", respawn=False, shake=False)


def _one_vehicle(view: View, intent: Intent, brake: bool = False, design: str = "amber", lighting: str = "day",
                 occluders=(), width_px: float = 200.0, center_x: float = 320.0, **vehicle) -> SceneRenderer:
    spec = dict(view=view, kind="car", lamp_design=design, tech="led", intent=intent, brake=brake, width_px=width_px,
                center_x=center_x, speed=0.0, blink_hz=1.0, duty=0.5, phase=0.0, shear=0.0, roll=0.0, specular=False)
    spec.update(vehicle)
    return SceneRenderer(seed=5, fps=10.0, lighting=lighting, vehicles=[spec], occluders=list(occluders), **CLEAN)


def _lit_and_dark(renderer: SceneRenderer):
    """Frame 1 is in the lit half of a 1 Hz / 50 % blink, frame 7 in the dark half."""
    frames = list(renderer.frames(8))
    return frames[1], frames[7]


def _amber_gain(lit: RenderedFrame, dark: RenderedFrame, box) -> tuple:
    """How much brighter/redder each half of the box got when the blinker lit (left, right)."""
    x0, y0, x1, y1 = (int(round(v)) for v in box)
    diff = lit.image[y0:y1, x0:x1].astype(np.float32) - dark.image[y0:y1, x0:x1].astype(np.float32)
    gain = np.clip(diff[..., 2], 0, None) + np.clip(diff[..., 1], 0, None)  # amber = red + green up
    mid = gain.shape[1] // 2
    return float(gain[:, :mid].sum()), float(gain[:, mid:].sum())


def test_same_seed_same_frames_and_labels():
    a = list(SceneRenderer(seed=11, width=320, height=180).frames(6))
    b = list(SceneRenderer(seed=11, width=320, height=180).frames(6))
    for fa, fb in zip(a, b):
        assert fa.stamp_ns == fb.stamp_ns
        assert np.array_equal(fa.image, fb.image)
        assert fa.vehicles == fb.vehicles
    c = list(SceneRenderer(seed=12, width=320, height=180).frames(6))
    assert any(not np.array_equal(fa.image, fc.image) for fa, fc in zip(a, c))


def test_frames_restart_from_the_same_state():
    r = SceneRenderer(seed=3, width=320, height=180)
    first = [f.image for f in r.frames(3)]
    again = [f.image for f in r.frames(3)]
    assert all(np.array_equal(x, y) for x, y in zip(first, again))


def test_front_view_left_signal_lights_the_image_right_half():
    lit, dark = _lit_and_dark(_one_vehicle(View.FRONT, Intent.LEFT))
    (v_lit,), (v_dark,) = lit.vehicles, dark.vehicles
    # ON through both halves of the blink; from the front the right blinker is visible and OFF.
    assert (v_lit.left, v_dark.left) == (LightStatus.ON, LightStatus.ON)
    assert v_lit.right == LightStatus.OFF and v_lit.intent == Intent.LEFT
    assert v_lit.brake == LightStatus.UNKNOWN  # no brake lamps on the front face
    left_half, right_half = _amber_gain(lit, dark, v_lit.box)
    assert right_half > 5 * max(left_half, 1.0), (left_half, right_half)


def test_lit_labels_follow_the_blink_phase_of_each_frame():
    lit, dark = _lit_and_dark(_one_vehicle(View.FRONT, Intent.LEFT))
    (v_lit,), (v_dark,) = lit.vehicles, dark.vehicles
    # The logical state is ON in both halves; what one frame shows is not.
    assert (v_lit.left_lit, v_dark.left_lit) == (LightStatus.ON, LightStatus.OFF)
    assert v_lit.right_lit == v_dark.right_lit == LightStatus.OFF
    hidden = _one_vehicle(View.LEFT, Intent.RIGHT)  # the right side faces away
    for frame in hidden.frames(8):
        (v,) = frame.vehicles
        assert v.right == v.right_lit == LightStatus.UNKNOWN


@pytest.mark.parametrize("design", ["amber", "red_combined", "led_strip", "sequential"])
def test_behind_view_left_signal_lights_the_image_left_half(design):
    lit, dark = _lit_and_dark(_one_vehicle(View.BEHIND, Intent.LEFT, design=design))
    (v_lit,), (v_dark,) = lit.vehicles, dark.vehicles
    assert v_lit.lamp_design == design and v_lit.view == View.BEHIND
    assert (v_lit.left, v_dark.left, v_lit.right) == (LightStatus.ON, LightStatus.ON, LightStatus.OFF)
    assert v_lit.brake == LightStatus.OFF
    left_half, right_half = _amber_gain(lit, dark, v_lit.box)
    assert left_half > 5 * max(right_half, 1.0), (left_half, right_half)


def test_hazard_lights_both_sides_in_sync():
    lit, dark = _lit_and_dark(_one_vehicle(View.BEHIND, Intent.HAZARD))
    (v,) = lit.vehicles
    assert (v.left, v.right, v.intent) == (LightStatus.ON, LightStatus.ON, Intent.HAZARD)
    left_half, right_half = _amber_gain(lit, dark, v.box)
    assert min(left_half, right_half) > 0.5 * max(left_half, right_half) > 0


def test_brake_lights_the_rear_and_is_labelled():
    on = list(_one_vehicle(View.BEHIND, Intent.OFF, brake=True).frames(1))[0]
    off = list(_one_vehicle(View.BEHIND, Intent.OFF, brake=False).frames(1))[0]
    assert on.vehicles[0].brake == LightStatus.ON and off.vehicles[0].brake == LightStatus.OFF
    assert on.vehicles[0].intent == Intent.OFF
    x0, y0, x1, y1 = (int(v) for v in on.vehicles[0].box)
    red_gain = on.image[y0:y1, x0:x1, 2].astype(float) - off.image[y0:y1, x0:x1, 2].astype(float)
    assert red_gain.clip(0).sum() > 500


@pytest.mark.parametrize("view,far", [(View.LEFT, "right"), (View.RIGHT, "left")])
def test_side_view_far_side_blinker_is_unknown(view, far, monkeypatch):
    # Side semantics only: let every visible lamp count, however small (the size rule has its own test).
    monkeypatch.setattr(truth, "LAMP_MIN_BOX_SHARE", 0.0)
    frames = list(_one_vehicle(view, Intent.HAZARD, width_px=300).frames(2))
    near = "left" if far == "right" else "right"
    for f in frames:
        (v,) = f.vehicles
        assert v.view == view
        assert getattr(v, far) == LightStatus.UNKNOWN
        assert getattr(v, near) == LightStatus.ON
        assert v.intent == (Intent.LEFT if near == "left" else Intent.RIGHT)


def test_lamps_too_small_for_the_crop_are_unknown():
    # A side view's lamps are slivers: under 4 pixels of the node's 64-pixel crop.
    (side,) = list(_one_vehicle(View.LEFT, Intent.LEFT, brake=True, width_px=300).frames(1))
    (v,) = side.vehicles
    assert (v.left, v.right, v.brake, v.intent) == (LightStatus.UNKNOWN,) * 3 + (Intent.UNKNOWN,)
    # The same vehicle from behind shows big lamps: labelled.
    (rear,) = list(_one_vehicle(View.BEHIND, Intent.LEFT, brake=True, width_px=120).frames(1))
    (v,) = rear.vehicles
    assert (v.left, v.brake, v.intent) == (LightStatus.ON, LightStatus.ON, Intent.LEFT)


def test_side_view_off_blinker_gives_unknown_intent(monkeypatch):
    monkeypatch.setattr(truth, "LAMP_MIN_BOX_SHARE", 0.0)
    (f,) = list(_one_vehicle(View.LEFT, Intent.OFF, width_px=300).frames(1))
    (v,) = f.vehicles
    assert (v.left, v.right, v.intent) == (LightStatus.OFF, LightStatus.UNKNOWN, Intent.UNKNOWN)


def test_occluded_lamp_turns_unknown():
    # Vehicle box spans x 220..420 from behind: its left lamps are at the image left end.
    free = list(_one_vehicle(View.BEHIND, Intent.LEFT, brake=True).frames(1))[0].vehicles[0]
    assert free.left == LightStatus.ON
    x0 = free.box[0]
    width = free.box[2] - free.box[0]
    pole = (x0 - 10, 0, x0 + 0.4 * width, 360)
    (f,) = list(_one_vehicle(View.BEHIND, Intent.LEFT, brake=True, occluders=[pole]).frames(1))
    (v,) = f.vehicles
    assert v.left == LightStatus.UNKNOWN
    assert v.right == LightStatus.OFF
    assert v.brake == LightStatus.ON  # the right tail lamp still shows the brake
    assert v.intent == Intent.UNKNOWN
    assert 0.2 < v.occlusion < 0.6
    assert v.box[0] >= pole[2] - 2  # the tight box covers only the visible part


def test_centre_brake_lamp_alone_shows_the_brake():
    # From behind, both tail lamps hidden by poles; only the centre brake lamp between them shows.
    free = list(_one_vehicle(View.BEHIND, Intent.OFF, brake=True, chmsl=True).frames(1))[0].vehicles[0]
    x0, _, x1, _ = free.box
    width = x1 - x0
    poles = [(x0 - 10, 0, x0 + 0.35 * width, 360), (x1 - 0.35 * width, 0, x1 + 10, 360)]
    for brake, label in ((True, LightStatus.ON), (False, LightStatus.OFF)):
        (f,) = list(_one_vehicle(View.BEHIND, Intent.OFF, brake=brake, chmsl=True, occluders=poles).frames(1))
        (v,) = f.vehicles
        assert (v.left, v.right) == (LightStatus.UNKNOWN, LightStatus.UNKNOWN)
        assert v.brake == label
    # Without a centre brake lamp nothing left in sight tells the brake.
    (f,) = list(_one_vehicle(View.BEHIND, Intent.OFF, brake=True, chmsl=False, occluders=poles).frames(1))
    assert f.vehicles[0].brake == LightStatus.UNKNOWN


def test_vehicle_mostly_outside_the_image_is_not_listed():
    # Side view, 300 px long, pointing to the image left: its front end is cut off first.
    (f,) = list(_one_vehicle(View.LEFT, Intent.LEFT, center_x=-142, width_px=300).frames(1))
    assert f.vehicles == []
    (g,) = list(_one_vehicle(View.LEFT, Intent.LEFT, center_x=-60, width_px=300).frames(1))
    (v,) = g.vehicles
    assert v.box[0] == 0.0 and 0.5 < v.occlusion < 0.9
    # Front lamps and repeater are outside the image, the rear indicator at the rear end is not.
    assert (v.left, v.right, v.intent) == (LightStatus.ON, LightStatus.UNKNOWN, Intent.LEFT)
    # Cut at the rear instead, with a red combined rear lamp: the front indicator still shows.
    (h,) = list(_one_vehicle(View.LEFT, Intent.LEFT, center_x=700, width_px=300, design="red_combined").frames(1))
    (w,) = h.vehicles
    assert w.left == LightStatus.ON and w.brake == LightStatus.UNKNOWN


def test_random_scenes_keep_their_invariants():
    n_listed = 0
    for seed in range(6):
        r = SceneRenderer(seed=seed, width=320, height=180)
        assert 10.0 <= r.fps <= 30.0
        assert r.lighting in ("day", "dusk", "night")
        stamps = []
        for f in r.frames(12):
            assert f.image.shape == (180, 320, 3) and f.image.dtype == np.uint8
            assert f.lighting == r.lighting
            stamps.append(f.stamp_ns)
            ids = [v.track_id for v in f.vehicles]
            assert len(ids) == len(set(ids))
            for v in f.vehicles:
                n_listed += 1
                assert isinstance(v, VehicleTruth) and isinstance(v.track_id, str)
                x0, y0, x1, y1 = v.box
                assert 0 <= x0 < x1 <= 320 and 0 <= y0 < y1 <= 180
                assert x1 - x0 >= 8 and y1 - y0 >= 8
                assert v.intent == intent_from_lights(v.left, v.right)
                assert 0.0 <= v.occlusion <= 0.9
                assert v.tracker_box is None or (isinstance(v.tracker_box, TrackBox) and v.tracker_box.track_id == v.track_id)
                if v.view == View.FRONT:
                    assert v.brake == LightStatus.UNKNOWN
                if v.view == View.LEFT:
                    assert v.right == LightStatus.UNKNOWN
                if v.view == View.RIGHT:
                    assert v.left == LightStatus.UNKNOWN
        steps = np.diff(stamps)
        assert np.all(np.abs(steps - 1e9 / r.fps) <= 1)
    assert n_listed > 50


def test_labels_switch_within_sequences_and_are_balanced():
    """Across many short sequences, signals are ON a fair share of the time and change mid-sequence."""
    blink_on = brake_on = known = changes = 0
    for seed in range(8):
        r = SceneRenderer(seed=100 + seed, width=160, height=90, fps=10.0, distractors=False, effects=False)
        last = {}
        for f in r.frames(80):
            for v in f.vehicles:
                key = (v.left, v.right, v.brake)
                if v.track_id in last and last[v.track_id] != key:
                    changes += 1
                last[v.track_id] = key
                if v.view == View.BEHIND:
                    known += 1
                    blink_on += v.intent in (Intent.LEFT, Intent.RIGHT, Intent.HAZARD)
                    brake_on += v.brake == LightStatus.ON
    assert known > 100
    assert 0.2 < blink_on / known < 0.7
    assert 0.2 < brake_on / known < 0.65
    assert changes > 10


def test_bad_overrides_are_reported():
    with pytest.raises(ConfigError, match="unknown SceneRenderer overrides"):
        SceneRenderer(seed=1, colour_scheme="x")
    with pytest.raises(ConfigError, match="vehicles\\[0\\]"):
        SceneRenderer(seed=1, vehicles=[{"wheels": 3}])
    with pytest.raises(ConfigError, match="lighting"):
        SceneRenderer(seed=1, lighting="noon")


def test_lighting_choice_follows_night_fraction():
    assert all(SceneRenderer(seed=s, night_fraction=1.0).lighting == "night" for s in range(5))
    assert all(SceneRenderer(seed=s, night_fraction=0.0).lighting != "night" for s in range(5))
    assert SceneRenderer(seed=1, lighting="dusk").lighting == "dusk"
    assert SceneRenderer(seed=1, fps=12.5).fps == 12.5


def test_tracker_boxes_are_jittered_and_sometimes_missing():
    rel, missing, total = [], 0, 0
    for seed in range(4):
        for f in SceneRenderer(seed=200 + seed, width=320, height=180, fps=10.0, effects=False).frames(40):
            for v in f.vehicles:
                total += 1
                if v.tracker_box is None:
                    missing += 1
                    continue
                t = v.tracker_box
                w, h = v.box[2] - v.box[0], v.box[3] - v.box[1]
                rel.append(max(abs(t.x0 - v.box[0]) / w, abs(t.x1 - v.box[2]) / w))
    assert total > 200
    assert 0 < missing / total < 0.1
    rel = np.asarray(rel)
    assert np.median(rel) < 0.1  # usually a few percent off
    assert np.mean(rel > 0.005) > 0.5  # but rarely exact


@pytest.mark.parametrize("kind", ["car", "suv"])
def test_lit_red_combined_lamp_is_clearly_visible_in_daylight(kind):
    """A lit bulb brightens its lens in daylight too: the lit half of a red combined
    blinker differs from the dark half by far more than the old 27 grey levels."""
    lit, dark = _lit_and_dark(_one_vehicle(View.BEHIND, Intent.LEFT, design="red_combined",
                                           kind=kind, tech="bulb", lights_on=False))
    x0, y0, x1, y1 = (int(round(v)) for v in lit.vehicles[0].box)
    grey = lambda im: im[y0:y1, x0:x1].astype(np.float32) @ np.float32([0.114, 0.587, 0.299])  # noqa: E731
    assert float((grey(lit.image) - grey(dark.image)).max()) >= 60  # was 22 with the faint drawing


def test_style_families():
    default = SceneRenderer(seed=21, width=320, height=180)
    assert default.family in scene.TRAIN_FAMILIES
    held_out = SceneRenderer(seed=21, width=320, height=180, family=2)
    frames = list(held_out.frames(2))
    assert held_out.family == 2 and frames[0].image.shape == (180, 320, 3)
    with pytest.raises(ConfigError, match="family"):
        SceneRenderer(seed=21, family=7)
