"""Tests of the runtime engine: batching, state handling, unjudged boxes, thresholds."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fake_light_model import FakeLightModel
from signal_light_node.boxes import TrackBox
from signal_light_node.runtime import flash_gate
from signal_light_node.runtime.crops import CropConfig, clip_roi
from signal_light_node.runtime.engine import (EngineConfig, LightStateEngine, engine_from_checkpoint,
                                      normalize_thresholds)
from signal_light_node.errors import CheckpointError, ConfigError, CropError
from signal_light_node.runtime.intent_filter import IntentFilter, IntentFilterConfig
from signal_light_node.labels import Intent, LightStatus
from signal_light_node.runtime.results import LightEstimate

MS = 1_000_000
W, H = 320, 180


def _image(value: int = 128) -> np.ndarray:
    return np.full((H, W, 3), value, dtype=np.uint8)


def _box(tid: str, x: float = 20.0, y: float = 30.0, size: float = 40.0) -> TrackBox:
    return TrackBox(tid, x, y, x + size, y + size)


def _engine(**kwargs) -> LightStateEngine:
    # The fake model's blinker outputs count steps, not lamps: no flash gate unless asked;
    # its view head sees no rear, so the brake keeps the model's sight (test_box_sight
    # tests the node's default, ``rear``).
    kwargs.setdefault("intent_filter", IntentFilterConfig(flash_min_evidence=0.0,
                                                          brake_sight="model"))
    return LightStateEngine(FakeLightModel(), EngineConfig(**kwargs))


def _left_steps(p_on: float) -> int:
    """Invert the fake model's left P(ON) = 0.9 * n / (n + 4) to the step count n."""
    q = p_on / 0.9
    return round(4 * q / (1 - q))


def test_one_result_per_box_in_input_order_with_clipped_rois():
    engine = _engine()
    boxes = [_box("b", 10, 10), _box("a", 100, 50), TrackBox("c", 300, 150, 360, 200)]
    frame = engine.process(_image(), 0, boxes)
    assert [r.track_id for r in frame.results] == ["b", "a", "c"]
    assert [r.roi for r in frame.results] == [clip_roi(b, W, H) for b in boxes]
    assert frame.results[2].roi == (300, 150, 20, 30)
    assert all(r.judged and r.frames_observed == 1 for r in frame.results)
    assert frame.n_judged == 3 and frame.warnings == [] and frame.latency_s > 0
    assert frame.stamp_ns == 0


@pytest.mark.parametrize("bad", [TrackBox("x", 50, 50, 50, 90),           # zero width
                                 TrackBox("x", 400, 10, 450, 60),         # outside
                                 TrackBox("x", -90, -90, -10, -10),       # outside
                                 TrackBox("x", math.nan, 10, 40, 40),     # NaN
                                 TrackBox("x", 10, 10, math.inf, 40)])    # not finite
def test_box_that_cannot_be_cropped_is_unknown_with_zero_on_probability(bad):
    engine = _engine()
    engine.process(_image(), 0, [_box("x")])
    frame = engine.process(_image(), 100 * MS, [_box("a"), bad, _box("b", 200, 40)])
    res = frame.results[1]
    assert res.track_id == "x" and not res.judged
    for light in (res.brake, res.left, res.right):
        assert light == LightEstimate.unjudged()
        assert light.state == LightStatus.UNKNOWN and light.on == 0.0
    assert res.intent == Intent.UNKNOWN and res.intent_probability == 0.0
    assert res.view_probability == 0.0 and res.classification == ()
    assert res.frames_observed == 1  # the earlier frame only; not advanced
    assert frame.n_judged == 2 and len(frame.warnings) == 1 and "box 1" in frame.warnings[0]
    assert engine.counters["unjudged"] == 1 and engine.counters["boxes"] == 4
    # The track's state was not advanced: its next good box is its second step.
    nxt = engine.process(_image(), 200 * MS, [_box("x")]).results[0]
    assert nxt.frames_observed == 2 and _left_steps(nxt.left.on) == 2


def test_duplicate_track_ids_keep_the_first_box_and_report_the_rest():
    def run():
        engine = _engine()
        boxes = [_box("a", 10, 10), _box("b", 100, 10), _box("a", 200, 100, 20), _box("a", 0, 0)]
        frames = [engine.process(_image(60 + 40 * t), t * 100 * MS, boxes) for t in range(3)]
        return engine, frames

    engine, frames = run()
    for frame in frames:
        assert [r.judged for r in frame.results] == [True, True, False, False]
        assert [r.track_id for r in frame.results] == ["a", "b", "a", "a"]
        assert frame.results[0].roi == (10, 10, 40, 40)
        assert frame.results[2].left.on == 0.0 and frame.results[2].roi == (200, 100, 20, 20)
        assert sum("duplicate track ID 'a'" in w for w in frame.warnings) == 2
    # The first box of "a" advanced once per frame, not three times.
    assert [f.results[0].frames_observed for f in frames] == [1, 2, 3]
    assert engine.counters["duplicates"] == 6 and engine.counters["unjudged"] == 6
    assert engine.model.batch_sizes == [2, 2, 2]
    _, again = run()
    assert [f.results for f in again] == [f.results for f in frames]


def test_exactly_one_batched_model_step_per_frame():
    engine = _engine()
    counts = [1, 8, 0, 5, 3]
    for t, n in enumerate(counts):
        boxes = [_box(str(i), 5 + 30 * (i % 10), 5 + 30 * (i // 10), 25) for i in range(n)]
        engine.process(_image(), t * 100 * MS, boxes)
    # Empty frames run no step at all; every other frame exactly one with all its tracks.
    assert engine.model.batch_sizes == [1, 8, 5, 3]
    assert engine.counters["model_steps"] == 4 and engine.counters["frames"] == 5


def test_one_step_per_frame_even_when_step_is_wrapped():
    model = FakeLightModel()
    calls = []
    original = model.step

    def counting_step(crops, state):
        calls.append(crops.shape[0])
        return original(crops, state)

    model.step = counting_step
    engine = LightStateEngine(model, EngineConfig())
    for t in range(4):
        engine.process(_image(), t * 50 * MS, [_box(str(i), 10 + 40 * i, 20) for i in range(6)])
    assert calls == [6, 6, 6, 6]


def test_state_is_carried_per_track():
    engine = _engine()
    for t in range(4):
        boxes = [_box("a")] if t < 2 else [_box("b", 150), _box("a")]
        frame = engine.process(_image(), t * 100 * MS, boxes)
    by_id = {r.track_id: r for r in frame.results}
    assert by_id["a"].frames_observed == 4 and _left_steps(by_id["a"].left.on) == 4
    assert by_id["b"].frames_observed == 2 and _left_steps(by_id["b"].left.on) == 2


def test_track_returning_after_the_timeout_starts_fresh():
    engine = _engine(track_timeout_s=0.5, max_gap_s=5.0)
    for t in range(5):  # "a" for 5 frames at 10 Hz, "b" keeps the stream going
        engine.process(_image(), t * 100 * MS, [_box("a"), _box("b", 150)])
    for t in range(5, 12):
        engine.process(_image(), t * 100 * MS, [_box("b", 150)])
    assert "a" not in engine.bank
    back = engine.process(_image(), 1200 * MS, [_box("a")]).results[0]
    assert back.frames_observed == 1 and _left_steps(back.left.on) == 1
    fresh = _engine().process(_image(), 0, [_box("a")]).results[0]
    assert back == fresh
    # Within the timeout the state is kept.
    engine.process(_image(), 1600 * MS, [_box("a")])
    assert engine.process(_image(), 1700 * MS, [_box("a")]).results[0].frames_observed == 3


def _sequence():
    rng = np.random.default_rng(3)
    frames = []
    for t in range(8):
        image = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
        boxes = [_box(tid, 10 + 60 * k + 3 * t, 20 + 2 * k) for k, tid in enumerate("abc")
                 if not (tid == "c" and t in (2, 3))]
        frames.append((image, 1_000 * MS + t * 100 * MS, boxes))
    return frames


def test_stamps_jumping_back_reset_and_a_replayed_sequence_gives_identical_outputs():
    engine = _engine()
    first = [engine.process(*f) for f in _sequence()]
    assert engine.counters["resets"] == 0
    second = [engine.process(*f) for f in _sequence()]
    assert engine.counters["resets"] == 1
    assert engine.reset_reasons == {"stamp_backwards": 1}
    assert "jumped backwards" in second[0].warnings[0]
    assert [f.results for f in second] == [f.results for f in first]
    assert second[-1].results[0].frames_observed == 8


def test_forward_gap_resets_states():
    engine = _engine(max_gap_s=1.0, track_timeout_s=10.0)
    engine.process(_image(), 0, [_box("a")])
    engine.process(_image(), 900 * MS, [_box("a")])
    frame = engine.process(_image(), 2500 * MS, [_box("a")])
    assert frame.results[0].frames_observed == 1
    assert engine.reset_reasons == {"stamp_gap": 1}


def test_thresholds_control_classification():
    image = _image(200)  # fake brake P(ON) = 0.9 * 200/255 = 0.706; left starts at 0.18
    p_brake = 0.9 * 200 / 255
    low = _engine(thresholds={100: 0.70, 101: 0.1, 102: 0.99}).process(image, 0, [_box("a")])
    high = _engine(thresholds={"brake": 0.71, "right": 0.71}).process(image, 0, [_box("a")])
    codes_low = dict(low.results[0].classification)
    assert sorted(codes_low) == [100, 101]
    assert codes_low[100] == pytest.approx(p_brake, abs=1e-5)
    assert codes_low[101] == pytest.approx(0.18, abs=1e-5)
    assert high.results[0].classification == ()
    # The state (argmax) does not depend on the threshold.
    assert high.results[0].brake.state == LightStatus.ON


def test_probabilities_and_argmax_fill_the_result():
    # The raw model's outputs (filter off): the intent is the intent head's argmax.
    frame = _engine(intent_filter=IntentFilterConfig(enabled=False)).process(
        _image(30), 0, [_box("a")])
    res = frame.results[0]
    assert res.brake.state == LightStatus.OFF
    assert res.brake.off + res.brake.on + res.brake.unknown == pytest.approx(1.0)
    assert res.intent == Intent.LEFT  # fake: phase = steps % 5 = 1
    assert 0.5 < res.intent_probability <= 1.0 and 0.0 < res.view_probability <= 1.0


class _BlinkModel(FakeLightModel):
    """The fake model, with the left blinker's P(ON) following the crop's brightness."""

    def step(self, crops, state):
        probs, new_state = super().step(crops, state)
        b = crops.mean(dim=(1, 2, 3)).clamp(0.0, 1.0) * 0.98
        probs["left"] = torch.stack([0.98 - b, b, torch.full_like(b, 0.02)], dim=1)
        probs["right"] = torch.tensor([[0.93, 0.05, 0.02]]).repeat(len(b), 1)
        return probs, new_state


AMBER = (20, 150, 250)  # BGR: a lamp colour the flash gate sees (grey and white have none)


def _blink_frames(n=40, fps=10.0, hz=1.5, stop_s=2.5):
    """A 1.5 Hz, 50 % duty amber blink of track "a" until ``stop_s``; "b" stays dark."""
    frames = []
    for k in range(n):
        t = k / fps
        lit = t < stop_s and (t * hz) % 1.0 < 0.5
        image = _image(10)
        if lit:
            image[:] = AMBER
        frames.append((image, int(t * 1e9)))
    return frames


def test_engine_publishes_the_filtered_lights_and_intent():
    # The filter stepped by hand below gets no box cover: the brake keeps the model's sight.
    config = IntentFilterConfig(brake_sight="model", intent_source="lights")
    on = LightStateEngine(_BlinkModel(), EngineConfig(intent_filter=config))
    raw = LightStateEngine(_BlinkModel(), EngineConfig(
        intent_filter=IntentFilterConfig(enabled=False)))
    filt = IntentFilter(config)
    rows = filt.initial_rows(1)
    intents = []
    for image, stamp in _blink_frames():
        got = on.process(image, stamp, [_box("a")]).results[0]
        want = raw.process(image, stamp, [_box("a")]).results[0]
        probs = {"intent": np.full((1, 5), 0.2), "view": np.full((1, 4), 0.25)}
        for task in ("brake", "left", "right"):
            light = getattr(want, task)
            probs[task] = np.array([[light.off, light.on, light.unknown]])
        out = filt.step(probs, stamp, rows, flash_gate.lamp_levels(image[None, :64, :64]))
        rows = out.rows
        for task in ("brake", "left", "right"):
            light = getattr(got, task)
            assert light.state == out.states[task][0], (stamp, task)
            assert (light.off, light.on, light.unknown) == pytest.approx(
                tuple(out.probs[task][0]), abs=1e-6)
        assert got.intent == out.states["intent"][0]
        assert got.intent_probability == pytest.approx(
            out.probs["intent"][0, got.intent], abs=1e-6)
        intents.append(got.intent)
    # Held through every dark half: OFF, then LEFT without a gap, then OFF for good.
    runs = [k for k, prev in zip(intents[1:], intents) if k != prev]
    assert runs == [Intent.LEFT, Intent.OFF]


@pytest.mark.parametrize("min_evidence, state", [(0.1, LightStatus.OFF), (0.0, LightStatus.ON)])
def test_engine_gates_a_steady_lamp_from_its_crops(min_evidence, state):
    """The model is sure of a left blinker, but the lamp never goes dark: with the flash
    gate (the default) the engine publishes OFF, without it ON."""
    engine = LightStateEngine(_BlinkModel(), EngineConfig(
        intent_filter=IntentFilterConfig(flash_min_evidence=min_evidence)))
    steady = _image(10)
    steady[:] = AMBER
    for k in range(20):
        last = engine.process(steady, k * 100 * MS, [_box("a")]).results[0]
    assert last.left.on > 0 if state == LightStatus.ON else last.left.on == 0.0
    assert last.left.state == state


@pytest.mark.parametrize("back_ms, state", [(2_150, LightStatus.ON), (2_250, LightStatus.OFF)])
def test_filter_rows_follow_the_track_state(back_ms, state):
    engine = LightStateEngine(_BlinkModel(), EngineConfig(track_timeout_s=0.3, max_gap_s=5.0))
    for image, stamp in _blink_frames(n=20, stop_s=10.0):
        last = engine.process(image, stamp, [_box("a")]).results[0]
    assert last.left.state == LightStatus.ON  # last flash at 1.6 s, held at 1.9 s
    # Dark and back within the 0.3 s track timeout: still held (0.55 s after the flash);
    # after it (0.65 s after the flash, still within hold_s): the track starts fresh.
    back = engine.process(_image(10), back_ms * MS, [_box("a")]).results[0]
    assert back.left.state == state and (back.frames_observed == 1) == (state == LightStatus.OFF)


def test_counters_cover_resets_evictions_and_active_tracks():
    engine = _engine(max_tracks=2)
    engine.process(_image(), 0, [_box("a"), _box("b", 100)])
    engine.process(_image(), 10 * MS, [_box("c", 200)])
    engine.process(_image(), 0, [])
    c = engine.counters
    assert c["evictions"] == 1 and c["resets"] == 1 and c["active_tracks"] == 0
    assert c["frames"] == 3 and c["boxes"] == 3 and c["judged"] == 3


def test_bad_image_raises_crop_error():
    with pytest.raises(CropError):
        _engine().process(np.zeros((10, 10), dtype=np.uint8), 0, [_box("a")])
    with pytest.raises(CropError):
        _engine().process(np.zeros((10, 10, 3), dtype=np.float32), 0, [])


@pytest.mark.parametrize("kwargs, match", [
    ({"thresholds": {100: 1.5}}, "probability"),
    ({"thresholds": {103: 0.5}}, "light code"),
    ({"thresholds": {"fog": 0.5}}, "light code"),
    ({"thresholds": {100: float("nan")}}, "probability"),
    ({"track_timeout_s": 0.0}, "track_timeout_s"),
    ({"max_gap_s": "x"}, "max_gap_s"),
    ({"max_tracks": 0}, "max_tracks"),
    ({"device": "tpu"}, "device"),
])
def test_engine_config_validation(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        EngineConfig(**kwargs)


def test_thresholds_accept_names_and_string_codes():
    assert normalize_thresholds({"left": 0.3, "102": 0.7}) == {100: 0.5, 101: 0.3, 102: 0.7}


def test_crop_follows_the_model_and_must_match_its_input_size():
    engine = _engine()
    assert engine.crop == CropConfig(size=16, margin=engine.model.config.crop_margin)
    engine = LightStateEngine(FakeLightModel(), EngineConfig(crop=CropConfig(16, 0.3)))
    assert engine.crop.margin == 0.3
    with pytest.raises(ConfigError, match="input size"):
        LightStateEngine(FakeLightModel(), EngineConfig(crop=CropConfig(size=32)))


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the no-CUDA error")
def test_cuda_without_cuda_is_a_config_error():
    with pytest.raises(ConfigError, match="CUDA"):
        LightStateEngine(FakeLightModel(), EngineConfig(device="cuda"))


def test_missing_checkpoint_propagates_checkpoint_error(tmp_path):
    with pytest.raises(CheckpointError):
        engine_from_checkpoint(tmp_path / "nope.pt")


def test_attention_masks_land_inside_the_crops_and_leave_state_alone():
    engine = _engine()
    image = _image(255)
    heat = engine.attention_masks(image, [_box("a", 100, 50, 40), TrackBox("z", 0, 0, 0, 0)])
    assert heat.shape == (H, W) and heat.dtype == np.float32
    ys, xs = np.nonzero(heat)
    margin = engine.crop.margin * 40 + 1
    assert xs.min() >= 100 - margin and xs.max() <= 140 + margin
    assert ys.min() >= 50 - margin and ys.max() <= 90 + margin
    assert heat.max() == pytest.approx(1.0)
    assert len(engine.bank) == 0 and engine.model.calls == 0


def test_fill_crops_follow_the_model_and_their_masks_fill_the_stretched_box():
    model = FakeLightModel()
    model.config = model.config.replace(crop_fill=True)
    engine = LightStateEngine(model, EngineConfig(intent_filter=IntentFilterConfig(
        flash_min_evidence=0.0)))
    assert engine.crop.fill
    # A wide box: the mask covers its width and height with their margins, no square.
    heat = engine.attention_masks(_image(255), [TrackBox("a", 100, 60, 180, 80)])
    ys, xs = np.nonzero(heat > 0.5)
    assert 100 - 12 - 1 <= xs.min() <= 100 and 180 <= xs.max() <= 180 + 12 + 1
    assert 60 - 3 - 1 <= ys.min() <= 60 and 80 <= ys.max() <= 80 + 3 + 1


def test_a_mask_is_scaled_to_its_rectangle_on_each_axis():
    from signal_light_node.runtime.engine import _paste_mask

    mask = np.zeros((16, 16), np.float32)
    mask[8:, 8:] = 1.0  # the bottom-right quarter
    heat = np.zeros((100, 200), np.float32)
    _paste_mask(heat, mask, 20, 10, 160, 40)
    ys, xs = np.nonzero(heat > 0.5)
    assert abs(xs.min() - 100) <= 3 and xs.max() == 179
    assert abs(ys.min() - 30) <= 2 and ys.max() == 49


# ------------------------------------------------------------- with the real network
TINY = dict(input_size=24, attention_channels=(4, 4, 4), backbone_channels=(6, 8, 8),
            lstm_hidden=(6, 5), head_channels=4, head_grid=2, fc_hidden=16)


def _tiny_net(seed: int = 0):
    from signal_light_node.model import ModelConfig, build_model

    torch.manual_seed(seed)
    return build_model(ModelConfig(**TINY))


def test_batched_tracks_match_tracks_run_alone_with_the_real_network():
    rng = np.random.default_rng(5)
    images = [rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8) for _ in range(4)]
    boxes = [_box("a", 10, 20), _box("b", 120, 40, 60), _box("c", 250, 100, 30)]
    together = LightStateEngine(_tiny_net())
    alone = {b.track_id: LightStateEngine(_tiny_net()) for b in boxes}
    for t, image in enumerate(images):
        joint = together.process(image, t * 100 * MS, boxes).results
        for box, res in zip(boxes, joint):
            single = alone[box.track_id].process(image, t * 100 * MS, [box]).results[0]
            assert res.frames_observed == single.frames_observed == t + 1
            for name in ("brake", "left", "right"):
                a, b = getattr(res, name), getattr(single, name)
                assert (a.off, a.on, a.unknown) == pytest.approx((b.off, b.on, b.unknown),
                                                                 abs=1e-5)
            assert res.intent_probability == pytest.approx(single.intent_probability, abs=1e-5)


def test_real_network_state_is_explicit_and_resets_to_initial():
    engine = LightStateEngine(_tiny_net(), EngineConfig(track_timeout_s=0.3))
    rng = np.random.default_rng(9)
    image = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
    first = engine.process(image, 0, [_box("a")]).results[0]
    second = engine.process(image, 100 * MS, [_box("a")]).results[0]
    assert second.brake != first.brake  # the recurrent state changed the output
    back = engine.process(image, 600 * MS, [_box("a")]).results[0]  # after the timeout
    assert back == first


def test_engine_from_checkpoint_loads_config_and_overrides(tmp_path):
    from signal_light_node.model import save_checkpoint

    net = _tiny_net()
    path = save_checkpoint(tmp_path / "tiny.pt", net, net.config)
    engine = engine_from_checkpoint(path, thresholds={"brake": 0.8}, max_tracks=7)
    # The crop margin is the checkpoint's: the one the model was trained with.
    assert engine.crop == CropConfig(size=24, margin=net.config.crop_margin)
    assert engine.config.thresholds[100] == 0.8 and engine.bank.capacity == 7
    image = np.full((H, W, 3), 90, dtype=np.uint8)
    got = engine.process(image, 0, [_box("a")]).results[0]
    want = LightStateEngine(net, EngineConfig()).process(image, 0, [_box("a")]).results[0]
    assert got.brake.on == pytest.approx(want.brake.on, abs=1e-6)
    for bad in ({"colour": "red"}, {"crop_margin": 0.25}):
        with pytest.raises(ConfigError, match="unknown engine option"):
            engine_from_checkpoint(path, **bad)
