"""Tests of scene bags: write_scene_bag, the ``signal-light synth`` command, and reading back."""

from __future__ import annotations

import json
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest

from signal_light_node.io import bagio
from signal_light_node.cli import main
from signal_light_node.io.conversions import detections_to_boxes, stamp_to_ns
from signal_light_node.runtime.crops import clip_roi
from signal_light_node.io.image_codec import msg_to_bgr
from signal_light_node.labels import LIGHT_CODES, LightStatus, intent_from_lights
from signal_light_node.synth import SceneRenderer
from signal_light_node.synth.bag import (COMPRESSED_TOPIC, DETECTIONS_TOPIC, GROUND_TRUTH_TOPIC,
                                         IMAGE_TOPIC, ground_truth_coverage, write_scene_bag)

SCENE = dict(seed=5, n_frames=15, fps=10.0, width=640, height=360, n_vehicles=4)


def read_by_topic(path: Path):
    out = defaultdict(list)
    with bagio.open_bag(path) as bag:
        for item in bag.messages():
            out[item.topic].append(item)
    return out


@pytest.fixture(scope="module")
def scene_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("bags") / "scene"
    summary = write_scene_bag(path, **SCENE)
    return path, summary


def test_summary_and_topics(scene_bag):
    path, summary = scene_bag
    assert summary.frames == 15 and summary.fps == 10.0 and len(summary.track_ids) >= 1
    with bagio.open_bag(path) as bag:
        topics = bag.topics()
    assert {t: (i.msgtype, i.count) for t, i in topics.items()} == {
        COMPRESSED_TOPIC: ("sensor_msgs/msg/CompressedImage", 15),
        DETECTIONS_TOPIC: ("vision_msgs/msg/Detection2DArray", 15),
        GROUND_TRUTH_TOPIC: ("signal_light_msgs/msg/VehicleLightStateArray", 15),
    }


def test_detections_and_truth_are_aligned_with_images(scene_bag):
    path, summary = scene_bag
    msgs = read_by_topic(path)
    images, dets, truth = msgs[COMPRESSED_TOPIC], msgs[DETECTIONS_TOPIC], msgs[GROUND_TRUTH_TOPIC]
    assert len(images) == len(dets) == len(truth) == 15
    observed = Counter()
    for image, det, gt in zip(images, dets, truth):
        stamp = stamp_to_ns(image.msg.header.stamp)
        assert image.log_time_ns == det.log_time_ns == gt.log_time_ns == stamp
        assert stamp_to_ns(det.msg.header.stamp) == stamp_to_ns(gt.msg.header.stamp) == stamp
        assert image.msg.header.frame_id == det.msg.header.frame_id == "camera"
        boxes = detections_to_boxes(det.msg)
        assert [b.track_id for b in boxes] == [v.track_id for v in gt.msg.vehicles]
        assert all(b.class_id for b in boxes)
        for box, v in zip(boxes, gt.msg.vehicles):
            observed[box.track_id] += 1
            assert v.frames_observed == observed[box.track_id]
            roi = (v.roi.x_offset, v.roi.y_offset, v.roi.width, v.roi.height)
            assert roi == clip_roi(box, 640, 360)
            states = {"brake": v.brake, "left": v.left_blinker, "right": v.right_blinker}
            for state in states.values():
                probs = [state.off_probability, state.on_probability, state.unknown_probability]
                assert probs[state.state] == 1.0 and sum(probs) == 1.0
            on = sorted(LIGHT_CODES[k] for k, s in states.items() if s.state == LightStatus.ON)
            assert sorted(c.label for c in v.classification) == on
            assert all(c.probability == 1.0 for c in v.classification)
            assert v.intent == intent_from_lights(v.left_blinker.state, v.right_blinker.state)
            assert v.intent_probability == 1.0 and v.view_probability == 1.0
    assert set(observed) == summary.track_ids
    assert sum(observed.values()) == summary.detections


def test_bag_matches_the_renderer(scene_bag):
    path, _ = scene_bag
    msgs = read_by_topic(path)
    frames = list(SceneRenderer(SCENE["seed"], width=640, height=360, fps=10.0,
                                n_vehicles=4).frames(15))
    for frame, image, det, gt in zip(frames, msgs[COMPRESSED_TOPIC], msgs[DETECTIONS_TOPIC],
                                     msgs[GROUND_TRUTH_TOPIC]):
        assert image.log_time_ns == frame.stamp_ns
        decoded = msg_to_bgr(image.msg)
        assert decoded.shape == frame.image.shape
        assert np.abs(decoded.astype(int) - frame.image).mean() < 4.0  # JPEG
        tracked = [v for v in frame.vehicles if v.tracker_box is not None]
        boxes = detections_to_boxes(det.msg)
        assert [b.track_id for b in boxes] == [v.track_id for v in tracked]
        for box, v, out in zip(boxes, tracked, gt.msg.vehicles):
            tb = v.tracker_box
            assert np.allclose([box.x0, box.y0, box.x1, box.y1], [tb.x0, tb.y0, tb.x1, tb.y1],
                               atol=1e-6)
            assert (out.brake.state, out.left_blinker.state, out.right_blinker.state,
                    out.intent, out.view) == (v.brake, v.left, v.right, v.intent, v.view)


def test_independent_mcap_reader_decodes_it(scene_bag):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path, _ = scene_bag
    counts = Counter()
    (mcap_file,) = path.glob("*.mcap")
    with open(mcap_file, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for _schema, channel, _message, decoded in reader.iter_decoded_messages():
            counts[channel.topic] += 1
            if channel.topic == GROUND_TRUTH_TOPIC:
                assert all(v.track_id for v in decoded.vehicles)
    assert counts == {COMPRESSED_TOPIC: 15, DETECTIONS_TOPIC: 15, GROUND_TRUTH_TOPIC: 15}


def test_raw_bag_holds_the_exact_frames(tmp_path):
    write_scene_bag(tmp_path / "raw", seed=8, n_frames=3, fps=12.0, width=320, height=180,
                    n_vehicles=3, raw=True)
    msgs = read_by_topic(tmp_path / "raw")
    assert set(msgs) == {IMAGE_TOPIC, DETECTIONS_TOPIC, GROUND_TRUTH_TOPIC}
    frames = SceneRenderer(8, width=320, height=180, fps=12.0, n_vehicles=3).frames(3)
    for frame, image in zip(frames, msgs[IMAGE_TOPIC]):
        assert image.msg.encoding == "bgr8"
        np.testing.assert_array_equal(msg_to_bgr(image.msg), frame.image)


def test_same_options_give_the_same_bag(tmp_path):
    for name in ("a", "b"):
        write_scene_bag(tmp_path / name, seed=3, n_frames=4, fps=10.0, n_vehicles=4)
    a, b = read_by_topic(tmp_path / "a"), read_by_topic(tmp_path / "b")
    for topic in a:
        for x, y in zip(a[topic], b[topic]):
            assert x.log_time_ns == y.log_time_ns
            assert bagio.typestore().serialize_cdr(x.msg, x.msgtype).tobytes() == \
                bagio.typestore().serialize_cdr(y.msg, y.msgtype).tobytes()


def test_synth_command_and_info(tmp_path, capsys):
    out = tmp_path / "cli_bag"
    code = main(["synth", "-o", str(out), "--seed", "2", "--frames", "6", "--fps", "15",
                 "--vehicles", "4", "--lighting", "night", "--width", "480", "--height", "270",
                 "--no-progress"])
    assert code == 0
    assert "6 frames" in capsys.readouterr().out
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    topics = {t["topic"]: t for t in info["topics"]}
    assert topics[COMPRESSED_TOPIC]["count"] == 6
    assert topics[COMPRESSED_TOPIC]["image"]["width"] == 480
    assert topics[DETECTIONS_TOPIC]["count"] == 6 and topics[GROUND_TRUTH_TOPIC]["count"] == 6
    assert info["track_ids"] >= 1
    cover = ground_truth_coverage(out)
    assert cover["frames"] == 6 and abs(cover["duration_s"] - 5 / 15) < 1e-6
    # An existing bag is not overwritten silently; bad options fail with exit code 2.
    assert main(["synth", "-o", str(out), "--frames", "2", "--no-progress"]) == 2
    assert main(["synth", "-o", str(tmp_path / "x"), "--frames", "0"]) == 2
    assert "error" in capsys.readouterr().err
    assert main(["synth", "-o", str(out), "--frames", "2", "--fps", "10", "--overwrite",
                 "--no-progress", "--raw"]) == 0
    with bagio.open_bag(out) as bag:
        assert set(bag.topics()) == {IMAGE_TOPIC, DETECTIONS_TOPIC, GROUND_TRUTH_TOPIC}


def test_synth_command_renders_the_held_out_family(tmp_path, capsys):
    """--family picks the style family (the renderer's own check refuses an unknown one);
    the same seed in another family draws other lamp colours, so other frames."""
    bags = {}
    for family in (2, 0):
        bags[family] = tmp_path / f"family_{family}"
        assert main(["synth", "-o", str(bags[family]), "--seed", "4", "--frames", "3", "--fps",
                     "10", "--vehicles", "3", "--lighting", "night", "--family", str(family),
                     "--raw", "--no-progress"]) == 0
    frames = {f: [m.msg.data.tobytes() for m in read_by_topic(b)[IMAGE_TOPIC]]
              for f, b in bags.items()}
    assert frames[2] != frames[0]
    assert main(["synth", "-o", str(tmp_path / "bad"), "--frames", "2", "--family", "7",
                 "--no-progress"]) == 2
    assert "family must be one of" in capsys.readouterr().err


def test_synth_command_turns_front_and_rear_views_with_oblique(tmp_path, capsys):
    """--oblique reaches the renderer: the same seed with every front and rear view turned
    draws other frames; a share outside [0, 1] is refused."""
    bags = {}
    for share in ("1", "0"):
        bags[share] = tmp_path / f"oblique_{share}"
        assert main(["synth", "-o", str(bags[share]), "--seed", "4", "--frames", "2", "--fps",
                     "10", "--vehicles", "4", "--lighting", "day", "--oblique", share, "--raw",
                     "--no-progress"]) == 0
    frames = {s: [m.msg.data.tobytes() for m in read_by_topic(b)[IMAGE_TOPIC]]
              for s, b in bags.items()}
    assert frames["1"] != frames["0"]
    assert main(["synth", "-o", str(tmp_path / "bad"), "--frames", "2", "--oblique", "1.5",
                 "--no-progress"]) == 2
    assert "oblique must be a share" in capsys.readouterr().err


def test_synth_command_labels_by_the_truth_rule_it_is_given(tmp_path):
    """--truth-rule reaches the renderer's truth only: the same seed draws the same frames,
    and the function rule judges at least every light the lamp rule judges, more here."""
    bags = {}
    for rule in ("lamp", "function"):
        bags[rule] = tmp_path / rule
        assert main(["synth", "-o", str(bags[rule]), "--seed", "22", "--frames", "12", "--fps",
                     "12", "--vehicles", "6", "--lighting", "night", "--truth-rule", rule,
                     "--raw", "--no-progress"]) == 0
    frames = {r: [m.msg.data.tobytes() for m in read_by_topic(b)[IMAGE_TOPIC]]
              for r, b in bags.items()}
    assert frames["lamp"] == frames["function"]
    unknown = {r: sum(ground_truth_coverage(b)[light].get("UNKNOWN", 0)
                      for light in ("brake", "left", "right")) for r, b in bags.items()}
    assert unknown["function"] < unknown["lamp"], unknown
