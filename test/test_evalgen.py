"""The independent evaluation generator (``signal_light_node.evalgen``): determinism, ground
truth consistent with the detections and the message semantics, lit blinkers visibly
brighter than their dark phase, readable bags, and no code shared with ``synth``."""

from __future__ import annotations

import ast
import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from signal_light_node.io import bagio
from signal_light_node.errors import ConfigError
from signal_light_node.evalgen.bag import write_eval_bag
from signal_light_node.evalgen.models import Signals
from signal_light_node.evalgen.scene import EvalScene, SceneConfig
from signal_light_node.labels import Intent, LightStatus, View, intent_from_lights
from signal_light_node.io.topics import (CAMERA_COMPRESSED_TOPIC, COMPRESSED_TYPE, DETECTIONS_TYPE,
                                      GROUND_TRUTH_TOPIC, TRACKED_OBJECTS_TOPIC,
                                      VEHICLE_LIGHTS_TYPE)

SMALL = SceneConfig(frames=12, width=320, height=180)
PACKAGE = Path(__file__).resolve().parents[1] / "signal_light_node" / "evalgen"


def _frames(seed: int, config: SceneConfig, n: int):
    return [f for _, f in zip(range(n), EvalScene(seed, config).frames())]


def test_same_seed_same_frames_other_seed_differs():
    a, b = _frames(5, SMALL, 3), _frames(5, SMALL, 3)
    c = _frames(6, SMALL, 3)
    for fa, fb in zip(a, b):
        assert fa.stamp_ns == fb.stamp_ns
        assert np.array_equal(fa.image, fb.image)
        assert fa.vehicles == fb.vehicles
    assert not np.array_equal(a[0].image, c[0].image)


@pytest.mark.parametrize("lighting,views", [("day", "all"), ("night", "all"), ("night", "behind")])
def test_truth_follows_the_view_and_intent_rules(lighting, views):
    config = dataclasses.replace(SMALL, frames=20, lighting=lighting, views=views)
    seen_views = set()
    for frame in EvalScene(3, config).frames():
        for v in frame.vehicles:
            seen_views.add(v.view)
            assert v.intent == intent_from_lights(v.left, v.right)
            if v.view == View.FRONT:
                assert v.brake == LightStatus.UNKNOWN  # brake lamps are at the back
            if v.view == View.LEFT:
                assert v.right == LightStatus.UNKNOWN  # far side
            if v.view == View.RIGHT:
                assert v.left == LightStatus.UNKNOWN
            if v.tracker_box is not None:
                assert v.tracker_box.track_id == v.track_id
    if views == "behind":
        assert seen_views == {View.BEHIND}
    else:
        assert len(seen_views) >= 3


def test_no_signal_scene_has_no_active_light():
    config = dataclasses.replace(SMALL, frames=10, lighting="night", views="behind", events="none")
    states = [(v.brake, v.left, v.right, v.intent) for f in EvalScene(4, config).frames()
              for v in f.vehicles]
    assert states
    assert all(LightStatus.ON not in s[:3] for s in states)
    assert any(s[3] == Intent.OFF for s in states)


def _one_blinking_car(lighting: str, phase_lit: bool):
    """Render frame 5 of a one-car scene whose hazard blinks lit (or dark) at that instant."""
    config = SceneConfig(frames=8, width=320, height=180, lighting=lighting, n_vehicles=1,
                         views="behind", events="none")
    scene = EvalScene(21, config)
    t = float(scene.times[5])
    # 1 Hz, 50 % duty, started 0.2 s (lit) or 0.7 s (dark) before the frame
    start = t - (0.2 if phase_lit else 0.7)
    scene.actors[0].signals = Signals(blink=[(start, 99.0, "hazard")], freq=1.0, duty=0.5,
                                      lights_on=lighting == "night")
    return scene.render(5)


@pytest.mark.parametrize("lighting", ["day", "night"])
def test_lit_blinker_brightens_its_lamps(lighting):
    lit, dark = _one_blinking_car(lighting, True), _one_blinking_car(lighting, False)
    (vl,), (vd,) = lit.vehicles, dark.vehicles
    # ON through the dark half of the blink, too
    assert vl.left == vd.left == LightStatus.ON and vl.intent == vd.intent == Intent.HAZARD
    assert vl.flash_left > 0.9 and vd.flash_left < 0.1
    x0, y0, x1, y1 = (int(round(c)) for c in vl.box)
    x0, y0 = max(x0, 0), max(y0, 0)
    diff = lit.image.astype(np.int32) - dark.image.astype(np.int32)
    inside = diff[y0:y1, x0:x1].max(axis=2)
    assert inside.max() >= 40  # the lamp lights up strongly somewhere on the car
    assert (inside >= 20).sum() >= 4
    outside = np.abs(diff).max(axis=2)
    outside[max(y0 - 8, 0):y1 + 8, max(x0 - 8, 0):x1 + 8] = 0
    assert outside.max() < inside.max()  # and nowhere else


def test_bag_is_readable_and_truth_matches_detections(tmp_path):
    summary = write_eval_bag(tmp_path / "bag", 7, dataclasses.replace(SMALL, frames=8))
    assert summary.frames == 8 and summary.detections > 0
    with bagio.open_bag(tmp_path / "bag") as bag:
        topics = bag.topics()
        assert topics[CAMERA_COMPRESSED_TOPIC].msgtype == COMPRESSED_TYPE
        assert topics[TRACKED_OBJECTS_TOPIC].msgtype == DETECTIONS_TYPE
        assert topics[GROUND_TRUTH_TOPIC].msgtype == VEHICLE_LIGHTS_TYPE
        by_stamp = {}
        for item in bag.messages():
            by_stamp.setdefault(item.log_time_ns, {})[item.topic] = item.msg
    assert len(by_stamp) == 8
    for stamp, msgs in by_stamp.items():
        assert set(msgs) == {CAMERA_COMPRESSED_TOPIC, TRACKED_OBJECTS_TOPIC, GROUND_TRUTH_TOPIC}
        dets, truth = msgs[TRACKED_OBJECTS_TOPIC].detections, msgs[GROUND_TRUTH_TOPIC].vehicles
        assert [d.id for d in dets] == [v.track_id for v in truth]
        for v in truth:
            assert v.intent == intent_from_lights(v.left_blinker.state, v.right_blinker.state)
            b = v.brake
            assert b.on_probability + b.off_probability + b.unknown_probability == 1
            on_codes = {c.label for c in v.classification}
            assert (100 in on_codes) == (v.brake.state == LightStatus.ON)


def test_bad_options_raise_config_error():
    with pytest.raises(ConfigError):
        SceneConfig(lighting="dusk")
    with pytest.raises(ConfigError):
        SceneConfig(frames=0)
    with pytest.raises(ConfigError):
        write_eval_bag("/nonexistent/never", 0, SMALL, jpeg_quality=0)


def test_shares_no_code_with_synth():
    for path in PACKAGE.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            for name in names:
                assert not name.startswith(("signal_light_node.synth", "synth")), (path, name)
    code = ("import sys, signal_light_node.evalgen.bag, signal_light_node.evalgen.__main__; "
            "bad = [m for m in sys.modules if m.startswith('signal_light_node.synth')]; "
            "print(bad); sys.exit(1 if bad else 0)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
