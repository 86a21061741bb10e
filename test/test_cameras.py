"""Several cameras in one engine: the state bank keyed by (camera, track ID) with one
stamp clock per camera, ``process_many`` (one backend step for every camera's frame), the
camera names and topics, and the node's per-camera work queue."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from fake_light_model import FakeLightModel, row_values, state_of
from signal_light_node.boxes import TrackBox
from signal_light_node.errors import ConfigError
from signal_light_node.io.topics import OUTPUT_TOPIC, camera_name_problem, camera_topic
from signal_light_node.runtime.camera_batch import CameraFrame
from signal_light_node.runtime.camera_queue import CameraQueue
from signal_light_node.runtime.engine import EngineConfig, LightStateEngine
from signal_light_node.runtime.intent_filter import IntentFilterConfig
from signal_light_node.runtime.state_bank import RESET_BACKWARDS, RESET_GAP, StateBank

MS = 1_000_000
W, H = 320, 180


def _step(bank, camera, ids, stamp_ns, values):
    bank.gather(ids, stamp_ns, camera=camera)
    return bank.store(ids, state_of(values), stamp_ns, camera=camera)


# ------------------------------------------------------------------ state bank
def test_the_same_track_id_on_two_cameras_is_two_tracks():
    bank = StateBank(FakeLightModel())
    _step(bank, "front", ["1"], 0, [1.0])
    _step(bank, "rear", ["1"], 0, [2.0])
    _step(bank, "front", ["1"], 10 * MS, [3.0])
    assert sorted(bank.keys) == [("front", "1"), ("rear", "1")]
    assert bank.frames_observed("1", "front") == 2 and bank.frames_observed("1", "rear") == 1
    assert bank.frames_observed("1") == 0 and "1" not in bank and ("rear", "1") in bank
    assert row_values(bank.gather(["1"], 20 * MS, camera="rear")) == [2.0]
    assert bank.tracks("front") == ["1"] and bank.track_ids == []


def test_a_stamp_jump_on_one_camera_resets_only_its_tracks():
    bank = StateBank(FakeLightModel(), track_timeout_s=10.0, max_gap_s=2.0)
    _step(bank, "front", ["a"], 500 * MS, [1.0])
    _step(bank, "rear", ["a", "b"], 500 * MS, [2.0, 3.0])
    # rear loops back: only rear's tracks start over
    assert bank.check_stamp(100 * MS, "rear") == RESET_BACKWARDS
    assert sorted(bank.keys) == [("front", "a")]
    assert bank.camera_counters["rear"]["resets"] == 1
    assert bank.camera_counters["front"]["resets"] == 0
    assert bank.camera_stamp_ns("front") == 500 * MS
    assert row_values(bank.gather(["a"], 600 * MS, camera="front")) == [1.0]
    bank.store(["a"], state_of([4.0]), 600 * MS, camera="front")
    # front jumps forward by more than the gap: rear untouched
    _step(bank, "rear", ["a"], 200 * MS, [5.0])
    assert bank.check_stamp(5000 * MS, "front") == RESET_GAP
    assert bank.keys == [("rear", "a")] and bank.counters["resets"] == 2
    assert bank.reset_reasons == {RESET_BACKWARDS: 1, RESET_GAP: 1}


def test_tracks_expire_by_their_own_cameras_stamps():
    bank = StateBank(FakeLightModel(), track_timeout_s=0.5, max_gap_s=100.0)
    _step(bank, "front", ["a"], 0, [1.0])
    _step(bank, "rear", ["a"], 0, [2.0])
    # front moves on by 1.4 s: its own "a" expires, rear's (whose clock stands at 0) does not
    _step(bank, "front", ["b"], 1000 * MS, [3.0])
    _step(bank, "front", ["b"], 1400 * MS, [3.0])
    assert sorted(bank.keys) == [("front", "b"), ("rear", "a")]
    assert bank.camera_counters["front"]["expired"] == 1
    assert bank.camera_counters.get("rear", {}).get("expired", 0) == 0


def test_max_tracks_is_global_and_evicts_the_least_recently_stored_of_any_camera():
    bank = StateBank(FakeLightModel(), max_tracks=3, track_timeout_s=100.0)
    _step(bank, "front", ["1"], 0, [1.0])
    _step(bank, "rear", ["1"], 5_000 * MS, [2.0])     # rear's clock is far ahead
    _step(bank, "front", ["2"], 10 * MS, [3.0])
    _step(bank, "rear", ["1"], 5_010 * MS, [4.0])     # rear's "1" is the most recent
    _step(bank, "side", ["9"], 0, [5.0])               # full: front "1" goes (not by stamp)
    assert sorted(bank.keys) == [("front", "2"), ("rear", "1"), ("side", "9")]
    assert bank.counters["evictions"] == 1 and bank.camera_counters["front"]["evictions"] == 1
    assert len(bank) == 3


def test_gather_cameras_one_batch_for_all_cameras_and_store_by_row():
    bank = StateBank(FakeLightModel(), filter_row=np.array([0.0, 0.0]))
    _step(bank, "front", ["1"], 0, [1.0])
    batch = bank.gather_cameras([("front", ["1", "2"], 10 * MS), ("rear", ["1"], 7 * MS)])
    assert batch.keys == (("front", "1"), ("front", "2"), ("rear", "1"))
    assert batch.stamps_ns.tolist() == [10 * MS, 10 * MS, 7 * MS]
    assert row_values(batch.state) == [1.0, 0.0, 0.0] and batch.filter_rows.shape == (3, 2)
    frames = bank.store_cameras(batch, state_of([5.0, 6.0, 7.0]),
                                np.array([[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]))
    assert frames.tolist() == [2, 1, 1]
    assert bank.last_seen_ns("1", "rear") == 7 * MS and bank.last_seen_ns("2", "front") == 10 * MS
    again = bank.gather_cameras([("rear", ["1"], 20 * MS), ("front", ["2", "1"], 20 * MS)])
    assert row_values(again.state) == [7.0, 6.0, 5.0]
    assert again.filter_rows[:, 0].tolist() == [3.0, 2.0, 1.0]
    with pytest.raises(ValueError, match="one frame per camera"):
        bank.gather_cameras([("front", ["1"], 0), ("front", ["2"], 0)])
    bank.gather(["x"], 30 * MS, camera="front")  # a later gather: `again` is stale
    with pytest.raises(ValueError, match="must follow gather_cameras"):
        bank.store_cameras(again, state_of([0.0, 0.0, 0.0]))


def test_a_full_reset_clears_every_camera():
    bank = StateBank(FakeLightModel())
    _step(bank, "front", ["1"], 100 * MS, [1.0])
    _step(bank, "rear", ["1"], 100 * MS, [1.0])
    bank.reset()
    assert len(bank) == 0 and bank.camera_stamp_ns("front") is None
    assert bank.counters["resets"] == 1
    assert {c: v["resets"] for c, v in bank.camera_counters.items()} == {"front": 1, "rear": 1}


# ---------------------------------------------------------------------- engine
def _image(value: int) -> np.ndarray:
    return np.full((H, W, 3), value, dtype=np.uint8)


def _box(tid: str, x: float = 20.0, y: float = 30.0, size: float = 40.0) -> TrackBox:
    return TrackBox(tid, x, y, x + size, y + size)


def _engine(model=None, **kwargs) -> LightStateEngine:
    return LightStateEngine(model or FakeLightModel(), EngineConfig(**kwargs))


def _stream(camera: int, t: int):
    """A camera's frame t: its own brightness, boxes and track IDs (all cameras use "1")."""
    image = np.full((H, W, 3), 40 + 50 * camera, np.uint8)
    image[60:120, 30 + 20 * camera:90 + 20 * camera] = 200 - 30 * camera + 3 * t
    boxes = [_box("1", 20 + 20 * camera + t, 50, 60), _box(f"c{camera}", 150, 40 + 10 * t, 30)]
    if t % 3 == 2:
        boxes.append(_box("late", 200, 100, 40))
    return image, (1000 + 100 * t + 7 * camera) * MS, boxes


def _same(a, b, atol=1e-6) -> None:
    assert [r.track_id for r in a.results] == [r.track_id for r in b.results]
    for ra, rb in zip(a.results, b.results):
        assert ra.roi == rb.roi and ra.frames_observed == rb.frames_observed
        assert ra.judged == rb.judged and ra.classification.__len__() == len(rb.classification)
        assert (ra.intent, ra.view) == (rb.intent, rb.view)
        for light in ("brake", "left", "right"):
            la, lb = getattr(ra, light), getattr(rb, light)
            assert la.state == lb.state
            assert np.allclose([la.off, la.on, la.unknown], [lb.off, lb.on, lb.unknown],
                               atol=atol)
        assert abs(ra.intent_probability - rb.intent_probability) <= atol
        assert abs(ra.view_probability - rb.view_probability) <= atol
    assert a.n_judged == b.n_judged and a.stamp_ns == b.stamp_ns


@pytest.mark.parametrize("filtered", [True, False], ids=["intent_filter", "raw"])
def test_process_many_equals_process_per_camera_in_one_step(filtered):
    cameras = ["front", "rear", "side"]
    config = dict(intent_filter=IntentFilterConfig(enabled=filtered))
    model = FakeLightModel()
    many = _engine(model, **config)
    alone = {c: _engine(**config) for c in cameras}
    for t in range(8):
        frames = [CameraFrame(c, *_stream(k, t)) for k, c in enumerate(cameras)]
        results = many.process_many(frames)
        for frame, result in zip(frames, results):
            _same(result, alone[frame.camera].process(frame.image, frame.stamp_ns, frame.boxes))
    # one backend step per tick, for every camera's boxes together
    assert model.calls == 8 and model.batch_sizes[2] == 9
    assert many.counters["model_steps"] == 8 and many.counters["frames"] == 24
    assert many.counters["judged"] == sum(e.counters["judged"] for e in alone.values())
    counters = many.camera_counters
    assert sorted(counters) == cameras
    assert all(counters[c]["active_tracks"] == 3 for c in cameras)


def test_process_many_with_the_real_network_matches_per_camera_process():
    net = _tiny_net()
    many = _engine(net)
    alone = {c: _engine(net) for c in ("front", "rear")}
    for t in range(4):
        frames = [("front", *_stream(0, t)), ("rear", *_stream(1, t))]
        for frame, result in zip(frames, many.process_many(frames)):
            _same(result, alone[frame[0]].process(*frame[1:]), atol=1e-5)


def test_a_loop_of_one_camera_leaves_the_other_cameras_tracks_alone():
    engine = _engine(max_gap_s=2.0, track_timeout_s=5.0)
    for t in range(4):
        engine.process_many([("front", *_stream(0, t)), ("rear", *_stream(1, t))])
    image, _, boxes = _stream(1, 0)
    front_image, front_stamp, front_boxes = _stream(0, 4)
    front, rear = engine.process_many([("front", front_image, front_stamp, front_boxes),
                                       ("rear", image, 500 * MS, boxes)])  # rear loops back
    assert [r.frames_observed for r in front.results if r.track_id == "1"] == [5]
    assert [r.frames_observed for r in rear.results if r.track_id == "1"] == [1]
    assert any("camera 'rear' reset" in w for w in rear.warnings) and not front.warnings
    assert engine.camera_counters["rear"]["resets"] == 1
    assert engine.camera_counters["front"]["resets"] == 0
    assert engine.counters["resets"] == 1


def test_process_many_splits_a_repeated_camera_into_steps_in_order():
    model = FakeLightModel()
    engine = _engine(model)
    a = _stream(0, 0)
    b = _stream(0, 1)
    c = _stream(1, 0)
    out = engine.process_many([("front", *a), ("front", *b), ("rear", *c)])
    assert [r.stamp_ns for r in out] == [a[1], b[1], c[1]]
    assert model.batch_sizes == [2, 4]
    assert [r.frames_observed for r in out[1].results if r.track_id == "1"] == [2]


def test_process_many_unusable_image_is_answered_unjudged_without_failing_the_others():
    engine = _engine()
    bad = np.zeros((10, 10), np.uint8)  # not HxWx3
    good, bad_frame = engine.process_many([("front", *_stream(0, 0)),
                                           ("rear", bad, 5 * MS, [_box("1")])])
    assert all(r.judged for r in good.results)
    assert [r.judged for r in bad_frame.results] == [False] and bad_frame.n_judged == 0
    assert "camera 'rear'" in bad_frame.warnings[0]


def test_process_many_duplicates_and_box_limit_per_frame_as_process():
    engine = _engine(max_boxes=2)
    boxes = [_box("a"), _box("a", 60), _box("b", 100), _box("c", 150)]
    front, rear = engine.process_many([("front", _image(100), 0, boxes),
                                       ("rear", _image(120), 0, boxes[:2])])
    assert [r.judged for r in front.results] == [True, False, True, False]
    assert [r.judged for r in rear.results] == [True, False]
    assert engine.counters["duplicates"] == 2 and engine.counters["over_limit"] == 1


def _tiny_net():
    from signal_light_node.model.checkpoint import ModelConfig
    from signal_light_node.model.registry import build_model

    torch.manual_seed(0)
    config = ModelConfig(input_size=32, attention_channels=(4, 4, 4), backbone_channels=(8, 8),
                         lstm_hidden=(8, 8), head_channels=4, fc_hidden=16)
    return build_model(config).eval()


def test_process_many_attention_masks_are_kept_per_image():
    engine = _engine(_tiny_net())
    engine.keep_attention = True
    front, rear = (_stream(0, 0), _stream(1, 0))
    engine.process_many([("front", *front), ("rear", *rear)])
    computed = []
    original = engine.backend.attention
    engine.backend.attention = lambda crops: computed.append(len(crops)) or original(crops)
    for image, _, boxes in (front, rear):
        heat = engine.attention_masks(image, boxes)
        assert heat.shape == (H, W) and heat.max() > 0
    assert computed == []  # both images' masks came from the shared step
    engine.attention_masks(_image(9), front[2])
    assert computed == [len(front[2])]


def test_process_many_refuses_malformed_frames():
    engine = _engine()
    with pytest.raises(ConfigError):
        engine.process_many([("front", _image(1))])
    with pytest.raises(ConfigError):
        engine.process_many([(3, _image(1), 0, [])])


# ------------------------------------------------------------- names and topics
@pytest.mark.parametrize("names, problem", [
    (["front", "rear"], None), (["cam_0", "_x"], None),
    (["front", "front"], "twice"), (["1st"], "ROS topic token"), (["front/left"], "token"),
    ([""], "token"), (["a b"], "token"), ([3], "strings"),
])
def test_camera_names(names, problem):
    found = camera_name_problem(names)
    assert (found is None) if problem is None else (problem in found)


def test_camera_topics():
    assert camera_topic("~/input/image/compressed", "front") == "~/front/input/image/compressed"
    assert camera_topic(OUTPUT_TOPIC, "rear") == "/signal_light_detector/rear/output/vehicle_lights"
    assert camera_topic(OUTPUT_TOPIC, "") == OUTPUT_TOPIC
    with pytest.raises(ValueError):
        camera_topic("/other/topic", "front")


# ------------------------------------------------------------------ work queue
def test_camera_queue_takes_one_frame_per_camera_per_tick_oldest_first():
    queue = CameraQueue(["front", "rear"], maxsize=2)
    queue.put(("front", "f1"))
    queue.put(("front", "f2"))
    queue.put(("front", "f3"))       # front's f1 dropped: the oldest
    queue.put(("rear", "r1"))
    assert queue.dropped == 1 and queue.dropped_by_camera == {"front": 1, "rear": 0}
    assert len(queue) == 3
    assert queue.get(timeout=1) == [("front", "f2"), ("rear", "r1")]
    assert queue.get(timeout=1) == [("front", "f3")]
    with pytest.raises(TimeoutError):
        queue.get(timeout=0.01)
    queue.put(("rear", "r2"))
    assert queue.clear() == 1 and queue.dropped_by_camera["rear"] == 1


def test_camera_queue_close_wakes_a_waiting_get_and_refuses_new_items():
    from signal_light_node.runtime.worker import QueueClosed

    queue = CameraQueue(["a"], maxsize=1)
    errors = []

    def wait():
        try:
            queue.get()
        except QueueClosed:
            errors.append("closed")

    thread = threading.Thread(target=wait)
    thread.start()
    queue.close()
    thread.join(5)
    assert errors == ["closed"] and queue.closed
    assert queue.put(("a", 1)) == ("a", 1) and queue.dropped == 1
    with pytest.raises(ConfigError):
        CameraQueue(["a"], maxsize=0)
    with pytest.raises(KeyError):
        CameraQueue(["a"], maxsize=1).put(("b", 1))


# ------------------------------------------------------------------ parameters
def test_cameras_parameter_defaults_to_one_camera_and_validates_names():
    from signal_light_node.ros.params import DetectorParams, updated, validate_params

    assert DetectorParams().cameras == [] and validate_params({}).cameras == []
    assert validate_params({"cameras": ("front", "rear")}).cameras == ["front", "rear"]
    for value, words in (("front", "list of names"), (["front", "front"], "twice"),
                         (["front", "2nd"], "ROS topic token"), ([1], "strings"),
                         (["a/b"], "token")):
        with pytest.raises(ConfigError) as info:
            validate_params({"cameras": value})
        assert "cameras" in str(info.value) and words in str(info.value)
        assert "\n" not in str(info.value)
    with pytest.raises(ConfigError, match="read-only"):
        updated(DetectorParams(), {"cameras": ["front"]})


@pytest.mark.parametrize("args, want", [
    ([], []),
    (["-p", "cameras:=[]"], []),
    (["-p", "cameras:=[front, rear]"], ["front", "rear"]),
    (["--params-file", "config/detector.yaml"], []),
])
def test_cameras_on_a_real_node_is_a_read_only_string_array(args, want, repo_root, monkeypatch):
    rclpy = pytest.importorskip("rclpy")
    from rcl_interfaces.msg import ParameterType
    from rclpy.parameter import Parameter

    from signal_light_node.ros.params import NODE_NAME, read_parameters

    monkeypatch.chdir(repo_root)
    context = rclpy.Context()
    rclpy.init(context=context, args=["--ros-args", *args])
    try:
        node = rclpy.create_node(NODE_NAME, context=context)
        try:
            assert read_parameters(node).cameras == want
            (desc,) = node.describe_parameters(["cameras"])
            assert desc.type == ParameterType.PARAMETER_STRING_ARRAY and desc.read_only
            assert node.get_parameter("cameras").value == want
            result = node.set_parameters([Parameter("cameras", value=["x"])])[0]
            assert not result.successful and "read-only" in result.reason.lower()
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


@pytest.mark.parametrize("value, words", [("front", "list of names"),
                                          ("[front, front]", "twice"),
                                          ("[9lives]", "ROS topic token")])
def test_bad_cameras_on_a_real_node_become_config_errors(value, words):
    rclpy = pytest.importorskip("rclpy")
    from signal_light_node.ros.params import read_parameters

    context = rclpy.Context()
    rclpy.init(context=context, args=["--ros-args", "-p", f"cameras:={value}"])
    try:
        node = rclpy.create_node("params_probe", context=context)
        try:
            with pytest.raises(ConfigError) as info:
                read_parameters(node)
            assert "cameras" in str(info.value) and words in str(info.value)
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
