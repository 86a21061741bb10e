"""End-to-end tests of ``replay_bag`` and ``signal-light replay``.

A small bag is built here with every awkward case (detections logged before their
image, an image without detections, detections without an image, a box outside the
image, a duplicate track ID); the committed bags in ``bags/`` are replayed too.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Dict, List

import cv2
import numpy as np
import pytest
import torch

from fake_light_model import FakeLightModel
from signal_light_node.io import bagio
from signal_light_node.boxes import TrackBox
from signal_light_node.cli import main
from signal_light_node.io.conversions import boxes_to_detections, make_header, stamp_to_ns
from signal_light_node.outputs.vehicle_lights import (vehicle_light_array,
                                                      vehicle_light_array_to_results)
from signal_light_node.runtime.engine import EngineConfig, LightStateEngine
from signal_light_node.errors import BagIOError
from signal_light_node.io.image_codec import bgr_to_compressed_fields, bgr_to_image_fields
from signal_light_node.labels import LIGHT_CODES, Intent, LightStatus, View
from signal_light_node.evaluation.metrics import macro_f1
from signal_light_node.tools.replay import (GROUND_TRUTH_TOPIC, OUTPUT_TOPIC, replay_bag,
                                      score_summary)
from signal_light_node.runtime.crops import CropConfig
from signal_light_node.runtime.results import LightEstimate, VehicleResult

REPO = Path(__file__).resolve().parents[1]
COMMITTED_BAGS = sorted(p for p in (REPO / "bags").glob("*")
                        if (p / "metadata.yaml").exists() or p.suffix == ".mcap")

#: Lower bounds of the agreement between the shipped model's replay output (intent filter
#: on, as the node publishes) and the ground truth of the committed training-renderer bags
#: (after warm-up, no grace window). The weights shipped 2026-11-22 measured brake 94.3 % /
#: 97.1 % and intent macro-F1 72.1 % / 68.4 % (day / night; `signal-light evaluate --bags
#: bags/X`); the two members shipped 2026-11-26 (fourth session) brake 95.5 % / 98.1 %,
#: intent 83.7 % / 70.6 % (`--backend torch`), with the blinkers' ON offset (fifth session)
#: brake 95.5 % / 98.1 %, intent 84.8 % / 70.8 %; the filled-crop members shipped
#: 2026-11-29 with the node's brake sight ``rear`` and 0.2 s visibility hold brake 94.2 % /
#: 96.4 %, intent 82.8 % / 63.7 % (`--backend torch`). Their night intent is lower because
#: these bags' truth is the ``lamp`` rule, which leaves 147 frames of a right blinker in plain
#: sight UNKNOWN that the ``function`` rule they were trained by judges (on the night scene
#: labelled by it: 74.4 %, the file before 77.0 %; docs/model.md, "A side view's brake").
#: The bounds leave a margin for the few vehicles of each bag. Raise them with the weights.
MIN_BRAKE_ACCURACY = 0.93
MIN_INTENT_MACRO_F1 = 0.60
#: How far the shipped weights must beat the best constant answer on a committed bag.
BASELINE_MARGIN = 0.10

IMAGE_T = "/camera/image/compressed"
DET_T = "/tracker/detections"
MS = 1_000_000
T0 = 1_700_000_000 * 1_000_000_000
W, H = 160, 96
N_FRAMES = 12
MISSING_DET = 4        # this frame's image has no detection message
LONELY_DET_STAMP = T0 + 55 * MS  # a detection message with no image


def _boxes(t: int) -> List[TrackBox]:
    boxes = [TrackBox("7", 10 + t, 20, 50 + t, 60), TrackBox("3", 90, 30, 130, 70 - t % 3)]
    if t == 2:
        boxes.append(TrackBox("9", 400, 400, 450, 450))  # outside the image
    if t == 5:
        boxes.append(TrackBox("7", 100, 10, 120, 30))    # duplicate ID
    return boxes


def _truth(t: int, header) -> object:
    brake = LightStatus.ON if t >= 6 else LightStatus.OFF
    results = [VehicleResult(track_id=b.track_id, roi=(0, 0, 1, 1),
                             brake=LightEstimate.certain(brake),
                             left=LightEstimate.certain(LightStatus.OFF),
                             right=LightEstimate.certain(LightStatus.OFF),
                             intent=Intent.OFF, intent_probability=1.0, view=View.BEHIND,
                             view_probability=1.0)
               for b in _boxes(t)[:2]]
    return vehicle_light_array(header, results, bagio.make)


def _write_bag(path: Path, raw: bool = False) -> Path:
    rng = np.random.default_rng(0)
    image_t = "/camera/image_raw" if raw else IMAGE_T
    image_type = "sensor_msgs/msg/Image" if raw else "sensor_msgs/msg/CompressedImage"
    with bagio.BagWriter(path) as bag:
        bag.add_topic(image_t, image_type)
        bag.add_topic(DET_T, "vision_msgs/msg/Detection2DArray")
        bag.add_topic(GROUND_TRUTH_TOPIC, "signal_light_msgs/msg/VehicleLightStateArray")
        for t in range(N_FRAMES):
            stamp = T0 + t * 100 * MS
            header = make_header(stamp, "camera", bagio.make)
            image = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
            fields = bgr_to_image_fields(image) if raw else bgr_to_compressed_fields(image, "png")
            img_msg = bagio.make(image_type, header=header, **fields)
            det_msg = boxes_to_detections(header, _boxes(t), bagio.make)
            # Odd frames: the tracker's output is logged before the image it belongs to.
            det_log = stamp + (-5 if t % 2 else 20) * MS
            if t != MISSING_DET:
                bag.write(DET_T, det_log, det_msg)
            bag.write(image_t, stamp + 10 * MS, img_msg)
            bag.write(GROUND_TRUTH_TOPIC, stamp + 10 * MS, _truth(t, header))
        lonely = make_header(LONELY_DET_STAMP, "camera", bagio.make)
        bag.write(DET_T, LONELY_DET_STAMP, boxes_to_detections(lonely, _boxes(0), bagio.make))
    return path


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory) -> Path:
    return _write_bag(tmp_path_factory.mktemp("replay") / "small")


def _read(path: Path) -> Dict[str, list]:
    out = defaultdict(list)
    with bagio.open_bag(path) as bag:
        for m in bag.messages():
            out[m.topic].append(m)
    return out


def _tiny_engine(**kwargs) -> LightStateEngine:
    from signal_light_node.model import ModelConfig, build_model

    torch.manual_seed(0)
    net = build_model(ModelConfig(input_size=24, attention_channels=(4, 4, 4),
                                  backbone_channels=(6, 8, 8), lstm_hidden=(6, 5),
                                  head_channels=4, head_grid=2, fc_hidden=16))
    return LightStateEngine(net, EngineConfig(**kwargs))


def _check_structure(bag_in: Path, bag_out: Path, image_topic: str, det_topic: str) -> int:
    """Every image has one output with its header; every detection an entry, same IDs."""
    inputs, outputs = _read(bag_in), _read(bag_out)
    images = inputs[image_topic]
    dets = {stamp_to_ns(m.msg.header.stamp): m.msg for m in inputs[det_topic]}
    outs = outputs[OUTPUT_TOPIC]
    assert len(outs) == len(images) > 0
    for img, out in zip(sorted(images, key=lambda m: m.log_time_ns),
                        sorted(outs, key=lambda m: m.log_time_ns)):
        stamp = stamp_to_ns(img.msg.header.stamp)
        assert stamp_to_ns(out.msg.header.stamp) == stamp
        assert out.msg.header.frame_id == img.msg.header.frame_id
        assert out.log_time_ns == img.log_time_ns
        det = dets.get(stamp)
        want_ids = [str(d.id) for d in det.detections] if det is not None else []
        assert [v.track_id for v in out.msg.vehicles] == want_ids
        for v in out.msg.vehicles:
            assert {c.label for c in v.classification} <= set(LIGHT_CODES.values())
    return len(outs)


def test_every_image_gets_one_output_and_every_detection_an_entry(small_bag, tmp_path):
    engine = _tiny_engine()
    summary = replay_bag(small_bag, tmp_path / "out", engine, progress=False)
    assert _check_structure(small_bag, tmp_path / "out", IMAGE_T, DET_T) == N_FRAMES
    assert summary.images == summary.outputs == N_FRAMES
    assert summary.images_without_detections == 1
    assert summary.detections_without_image == 1
    assert summary.detections == summary.entries == sum(
        len(_boxes(t)) for t in range(N_FRAMES) if t != MISSING_DET)
    assert summary.counters["unjudged"] == 2 and summary.counters["duplicates"] == 1
    assert summary.image_topic == IMAGE_T and summary.detections_topic == DET_T
    assert len(summary.latencies_s) == N_FRAMES and summary.frames_per_s > 0
    outs = _read(tmp_path / "out")[OUTPUT_TOPIC]
    assert list(_read(tmp_path / "out")) == [OUTPUT_TOPIC]
    assert outs[MISSING_DET].msg.vehicles == []
    _, frame2 = vehicle_light_array_to_results(outs[2].msg)
    assert [r.judged for r in frame2] == [True, True, False]
    assert frame2[2].brake.on == 0.0 and frame2[2].brake.state == LightStatus.UNKNOWN
    _, frame5 = vehicle_light_array_to_results(outs[5].msg)
    assert [r.judged for r in frame5] == [True, True, False]
    # Track "7" was seen in every frame with detections: frames_observed counts them.
    assert [v.frames_observed for m in outs for v in m.msg.vehicles[:1]] == \
        [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11]


def test_raw_images_and_explicit_topics(tmp_path):
    bag = _write_bag(tmp_path / "raw", raw=True)
    summary = replay_bag(bag, tmp_path / "out", _tiny_engine(), image_topic="/camera/image_raw",
                         detections_topic=DET_T, progress=False)
    assert summary.image_topic == "/camera/image_raw"
    assert _check_structure(bag, tmp_path / "out", "/camera/image_raw", DET_T) == N_FRAMES


def test_with_inputs_copies_the_input_topics(small_bag, tmp_path):
    replay_bag(small_bag, tmp_path / "out", _tiny_engine(), with_inputs=True, progress=False)
    inputs, outputs = _read(small_bag), _read(tmp_path / "out")
    for topic in (IMAGE_T, DET_T, GROUND_TRUTH_TOPIC):
        assert [m.log_time_ns for m in outputs[topic]] == [m.log_time_ns for m in inputs[topic]]
    got = outputs[IMAGE_T][3].msg.data
    assert np.array_equal(got, inputs[IMAGE_T][3].msg.data)
    assert len(outputs[OUTPUT_TOPIC]) == N_FRAMES


def test_output_decodes_with_the_independent_mcap_reader(small_bag, tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    replay_bag(small_bag, tmp_path / "out", _tiny_engine(), progress=False)
    files = list((tmp_path / "out").glob("*.mcap"))
    assert len(files) == 1
    stamps, ids = [], []
    with open(files[0], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, _, msg in reader.iter_decoded_messages():
            assert channel.topic == OUTPUT_TOPIC
            assert schema.name == "signal_light_msgs/msg/VehicleLightStateArray"
            stamps.append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
            ids.append([v.track_id for v in msg.vehicles])
            for v in msg.vehicles:
                assert 0.0 <= v.brake.on_probability <= 1.0
    assert stamps == [T0 + t * 100 * MS for t in range(N_FRAMES)]
    assert ids[0] == ["7", "3"] and ids[MISSING_DET] == []


def test_replaying_twice_with_one_engine_gives_identical_outputs(small_bag, tmp_path):
    engine = _tiny_engine()
    replay_bag(small_bag, tmp_path / "a", engine, progress=False)
    replay_bag(small_bag, tmp_path / "b", engine, progress=False)
    assert engine.counters["resets"] == 1  # the stamps jumped back once
    a = [vehicle_light_array_to_results(m.msg) for m in _read(tmp_path / "a")[OUTPUT_TOPIC]]
    b = [vehicle_light_array_to_results(m.msg) for m in _read(tmp_path / "b")[OUTPUT_TOPIC]]
    assert a == b


def test_ground_truth_is_matched_per_track_and_scored(small_bag, tmp_path):
    summary = replay_bag(small_bag, tmp_path / "out", LightStateEngine(FakeLightModel()),
                         progress=False)
    assert summary.has_ground_truth
    assert sorted(summary.tracks) == ["3", "7"]
    rec = summary.tracks["7"]
    assert len(rec.stamps_ns) == N_FRAMES - 1  # every frame with detections, judged
    assert [int(r[1]) for r in rec.truth] == [int(t >= 6) for t in range(N_FRAMES)
                                              if t != MISSING_DET]
    from signal_light_node.evaluation.scoring import EvalSettings

    result = score_summary(summary, EvalSettings(warmup_frames=0, warmup_seconds=0.0))
    assert result["counts"]["scored"] == 2 * (N_FRAMES - 1)
    # Switches, per track segment: the brake truth changes once in each.
    brake = result["switches"]["brake"]
    assert brake["true"] == 2 and set(brake["per_track"]) == {"3@0", "7@0"}
    assert brake["predicted"] == sum(int(np.count_nonzero(np.diff([int(p[1]) for p in r.pred])))
                                     for r in summary.tracks.values())
    brake = result["no_grace"]["overall"]["brake"]
    want = sum(int(p[1] == t[1]) for r in summary.tracks.values()
               for p, t in zip(r.pred, r.truth)) / (2 * (N_FRAMES - 1))
    assert brake["accuracy"] == pytest.approx(want)
    # Default warm-up (10 frames and 1 s): only the last frame of each track is scored.
    result = score_summary(summary)
    assert result["counts"]["scored"] == 2 and result["counts"]["warmup_excluded"] == 20
    # The brake label changes at t = 6: the 0.5 s grace window drops frames 6..10.
    graced = score_summary(summary, EvalSettings(warmup_frames=0, warmup_seconds=0.0))
    assert graced["counts"]["grace_excluded"]["brake"] == 2 * 5
    assert graced["counts"]["grace_excluded"]["view"] == 0


def test_scoring_restarts_the_warm_up_when_a_track_state_restarts(small_bag, tmp_path):
    from signal_light_node.evaluation.scoring import EvalSettings

    # A 0.15 s timeout: track "7" times out across the missing frame 4 and starts over.
    engine = LightStateEngine(FakeLightModel(), EngineConfig(track_timeout_s=0.15))
    summary = replay_bag(small_bag, tmp_path / "out", engine, progress=False)
    assert summary.tracks["7"].frames_observed == [1, 2, 3, 4, 1, 2, 3, 4, 5, 6, 7]
    result = score_summary(summary, EvalSettings(warmup_frames=2, warmup_seconds=0.0))
    assert result["counts"]["tracks"] == 4
    assert result["counts"]["scored"] == 2 * ((4 - 2) + (7 - 2))


def test_bag_without_ground_truth_reports_none(tmp_path):
    bag_in = tmp_path / "nogt"
    with bagio.BagWriter(bag_in) as bag:
        bag.add_topic("/img", "sensor_msgs/msg/Image")
        bag.add_topic("/det", "vision_msgs/msg/Detection2DArray")
        header = make_header(T0, "cam", bagio.make)
        bag.write("/img", T0, bagio.make("sensor_msgs/msg/Image", header=header,
                                         **bgr_to_image_fields(np.zeros((H, W, 3), np.uint8))))
        bag.write("/det", T0, boxes_to_detections(header, _boxes(0), bagio.make))
    summary = replay_bag(bag_in, tmp_path / "out", LightStateEngine(FakeLightModel()),
                         progress=False)
    assert not summary.has_ground_truth and summary.tracks == {}
    assert score_summary(summary) is None
    assert summary.entries == 2


def test_missing_topics_are_bag_errors(small_bag, tmp_path):
    engine = LightStateEngine(FakeLightModel())
    with pytest.raises(BagIOError, match="no topic '/nope'"):
        replay_bag(small_bag, tmp_path / "o1", engine, image_topic="/nope", progress=False)
    with pytest.raises(BagIOError, match="has type"):
        replay_bag(small_bag, tmp_path / "o2", engine, image_topic=DET_T, progress=False)
    with pytest.raises(BagIOError, match="exists"):
        (tmp_path / "o3").mkdir()
        replay_bag(small_bag, tmp_path / "o3", engine, progress=False)


@pytest.mark.parametrize("suffix", [".mp4", ".gif"])
def test_annotated_video(small_bag, tmp_path, suffix):
    video = tmp_path / f"v{suffix}"
    summary = replay_bag(small_bag, tmp_path / "out", LightStateEngine(FakeLightModel()),
                         video=video, video_attention=True, progress=False)
    assert summary.video == video and video.stat().st_size > 0
    if suffix == ".gif":
        ok, animation = cv2.imreadanimation(str(video))
        assert ok and len(animation.frames) == N_FRAMES
    else:
        cap = cv2.VideoCapture(str(video))
        n = 0
        while cap.read()[0]:
            n += 1
        cap.release()
        assert n == N_FRAMES


def test_cli_replay_prints_summary_and_metrics(small_bag, tmp_path, capsys):
    from signal_light_node.model import save_checkpoint

    net = _tiny_engine().model
    ckpt = save_checkpoint(tmp_path / "tiny.pt", net, net.config)
    out = tmp_path / "out"
    code = main(["replay", str(small_bag), "-o", str(out), "--checkpoint", str(ckpt),
                 "--no-progress", "--threshold", "brake=0.9", "--threshold", "101=0.2",
                 "--threads", "1"])
    text = capsys.readouterr().out
    assert code == 0
    assert f"{N_FRAMES} messages on {OUTPUT_TOPIC}" in text
    assert "Agreement with the ground truth" in text and "scored after the warm-up" in text
    assert "Intent filter: on" in text and "### Switches" in text
    assert "| intent | " in text and "Intent changes per track" in text
    assert _check_structure(small_bag, out, IMAGE_T, DET_T) == N_FRAMES
    raw = tmp_path / "raw"
    assert main(["replay", str(small_bag), "-o", str(raw), "--checkpoint", str(ckpt),
                 "--no-progress", "--no-intent-filter"]) == 0
    assert "Intent filter: off" in capsys.readouterr().out
    # An existing output without --overwrite is a clear error, not a traceback.
    assert main(["replay", str(small_bag), "-o", str(out), "--checkpoint", str(ckpt),
                 "--no-progress"]) == 2
    assert "exists" in capsys.readouterr().err
    assert main(["replay", str(small_bag), "-o", str(out), "--checkpoint",
                 str(tmp_path / "missing.pt"), "--no-progress", "--overwrite"]) == 2


def test_rendered_scene_bag_end_to_end(tmp_path):
    from signal_light_node.synth.bag import DETECTIONS_TOPIC, write_scene_bag

    bag = tmp_path / "scene"
    write_scene_bag(bag, seed=11, n_frames=12, fps=10.0, width=480, height=270, n_vehicles=3)
    summary = replay_bag(bag, tmp_path / "out", _tiny_engine(), progress=False)
    assert summary.has_ground_truth and summary.tracks
    assert _check_structure(bag, tmp_path / "out", summary.image_topic, DETECTIONS_TOPIC) == 12


# ------------------------------------------------- pairing with a slop, markers

N_JITTER = 24
SLOP_S = 0.01


def _jitter_ms(t: int) -> int:
    """Detection stamp minus image stamp of frame t: 0 on every third frame, a few ms on
    the others, and 40 ms (beyond the slop) on frame 7."""
    return 40 if t == 7 else (0 if t % 3 == 0 else (-1) ** t * (2 + t % 5))


def _write_jittered_bag(path: Path) -> Path:
    """A tracker that stamps its detections with its own clock: a few ms off the image.

    Each detection message holds one box with track ID ``d<t>``, so an output tells which
    message was paired with its image; the log times interleave both ways.
    """
    rng = np.random.default_rng(1)
    with bagio.BagWriter(path) as bag:
        bag.add_topic(IMAGE_T, "sensor_msgs/msg/CompressedImage")
        bag.add_topic(DET_T, "vision_msgs/msg/Detection2DArray")
        bag.add_topic(GROUND_TRUTH_TOPIC, "signal_light_msgs/msg/VehicleLightStateArray")
        for t in range(N_JITTER):
            stamp = T0 + t * 100 * MS
            header = make_header(stamp, "camera", bagio.make)
            image = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
            bag.write(IMAGE_T, stamp + 10 * MS, bagio.make(
                "sensor_msgs/msg/CompressedImage", header=header,
                **bgr_to_compressed_fields(image, "png")))
            det_header = make_header(stamp + _jitter_ms(t) * MS, "camera", bagio.make)
            box = TrackBox(f"d{t}", 20 + t, 20, 70 + t, 60)
            bag.write(DET_T, stamp + (4 if t % 2 else 30) * MS,
                      boxes_to_detections(det_header, [box], bagio.make))
            truth = VehicleResult(track_id=f"d{t}", roi=(0, 0, 1, 1),
                                  brake=LightEstimate.certain(LightStatus.OFF),
                                  left=LightEstimate.certain(LightStatus.OFF),
                                  right=LightEstimate.certain(LightStatus.OFF),
                                  intent=Intent.OFF, intent_probability=1.0,
                                  view=View.BEHIND, view_probability=1.0)
            bag.write(GROUND_TRUTH_TOPIC, stamp + 10 * MS,
                      vehicle_light_array(header, [truth], bagio.make))
    return path


def _node_pairs(bag_path: Path, config) -> Dict[int, List[str]]:
    """What a node's StampPairer pairs, fed the bag in log-time order (log time = receive
    time): image stamp -> track IDs of the paired detections."""
    pairer, pairs = config.pairer(), {}
    with bagio.open_bag(bag_path) as bag:
        for m in bag.messages([IMAGE_T, DET_T]):
            stamp = stamp_to_ns(m.msg.header.stamp)
            add = pairer.add_image if m.topic == IMAGE_T else pairer.add_detections
            pair = add(stamp, m.msg, m.log_time_ns)
            if pair is not None:
                pairs[pair.stamp_ns] = [str(d.id) for d in pair.detections.detections]
    return pairs


def _output_ids(path: Path) -> Dict[int, List[str]]:
    return {stamp_to_ns(m.msg.header.stamp): [v.track_id for v in m.msg.vehicles]
            for m in _read(path)[OUTPUT_TOPIC]}


def test_sync_slop_pairs_jittered_detections_as_the_node_pairer_does(tmp_path):
    from signal_light_node.runtime.pairing import PairingConfig
    from signal_light_node.training.sources import load_bag_tracks

    bag = _write_jittered_bag(tmp_path / "jitter")
    stamps = [T0 + t * 100 * MS for t in range(N_JITTER)]
    jittered = [t for t in range(N_JITTER) if _jitter_ms(t) != 0]
    config = PairingConfig(slop_s=SLOP_S)
    node = _node_pairs(bag, config)
    summary = replay_bag(bag, tmp_path / "slop", _tiny_engine(), pairing=config, progress=False)
    got = _output_ids(tmp_path / "slop")
    assert sorted(got) == stamps
    for stamp in stamps:  # frame by frame: the node's pairs, an empty array where it has none
        assert got[stamp] == node.get(stamp, []), stamp
    assert got[stamps[7]] == [] and all(got[stamps[t]] == [f"d{t}"]
                                        for t in range(N_JITTER) if t != 7)
    assert summary.images_without_detections == summary.detections_without_image == 1
    assert summary.pairing_counters["paired"] == N_JITTER - 1
    # The CLI's --sync-slop gives the same output.
    net = _tiny_engine().model
    ckpt = tmp_path / "tiny.pt"
    from signal_light_node.model import save_checkpoint

    save_checkpoint(ckpt, net, net.config)
    assert main(["replay", str(bag), "-o", str(tmp_path / "cli"), "--checkpoint", str(ckpt),
                 "--no-progress", "--sync-slop", str(SLOP_S)]) == 0
    assert _output_ids(tmp_path / "cli") == got

    # Without a slop the jittered frames stay unpaired and are counted, as before.
    exact = replay_bag(bag, tmp_path / "exact", _tiny_engine(), progress=False)
    got = _output_ids(tmp_path / "exact")
    assert got == {s: ([f"d{t}"] if t not in jittered else []) for t, s in enumerate(stamps)}
    assert got == {s: _node_pairs(bag, PairingConfig()).get(s, []) for s in stamps}
    assert exact.images == exact.outputs == N_JITTER
    assert exact.images_without_detections == exact.detections_without_image == len(jittered)

    # The training data of labelled bags pairs the same way.
    frames = lambda tracks: sorted(int(s) for t in tracks for s in t.stamps_ns)  # noqa: E731
    assert frames(load_bag_tracks(bag, CropConfig(size=24))) == \
        [s for t, s in enumerate(stamps) if t not in jittered]
    assert frames(load_bag_tracks(bag, CropConfig(size=24), pairing=config)) == \
        [s for t, s in enumerate(stamps) if t != 7]


def test_bad_sync_options_are_one_line_errors(small_bag, tmp_path, capsys):
    for bad in (["--sync-slop", "-1"], ["--sync-slop", "0.5", "--sync-timeout", "0.2"]):
        assert main(["replay", str(small_bag), "-o", str(tmp_path / "o"), "--no-progress",
                     *bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "pairing" in err[0], err


def test_markers_are_written_beside_the_results(small_bag, tmp_path):
    from signal_light_node.io.topics import MARKERS_TOPIC
    from signal_light_node.outputs.markers import DELETEALL

    summary = replay_bag(small_bag, tmp_path / "out", _tiny_engine(), markers=True,
                         progress=False)
    assert summary.topics_written == [OUTPUT_TOPIC, MARKERS_TOPIC]
    out = _read(tmp_path / "out")
    results, markers = out[OUTPUT_TOPIC], out[MARKERS_TOPIC]
    assert len(markers) == len(results) == N_FRAMES
    for res, mark in zip(results, markers):
        assert mark.log_time_ns == res.log_time_ns
        first, rest = mark.msg.markers[0], mark.msg.markers[1:]
        assert first.action == DELETEALL
        drawn = [v for v in res.msg.vehicles if v.roi.width > 0 and v.roi.height > 0]
        boxes = [m for m in rest if m.ns == "box"]
        texts = [m.text for m in rest if m.ns == "track_id"]
        assert len(boxes) == len(drawn)
        assert [t.split(" ")[0] for t in texts] == [v.track_id for v in drawn]
        for m in mark.msg.markers:
            assert m.header.frame_id == "camera"
            assert stamp_to_ns(m.header.stamp) == stamp_to_ns(res.msg.header.stamp)
    # Frame 2's third box lies outside the image: it has an entry but nothing to draw.
    assert len(results[2].msg.vehicles) == 3
    assert len([m for m in markers[2].msg.markers if m.ns == "box"]) == 2
    # Without the option: the result topic only.
    assert replay_bag(small_bag, tmp_path / "plain", _tiny_engine(),
                      progress=False).topics_written == [OUTPUT_TOPIC]


# ------------------------------------------------------------------ committed bags


def _detection_topic(path: Path) -> str:
    with bagio.open_bag(path) as bag:
        return next(t for t, i in bag.topics().items()
                    if i.msgtype == "vision_msgs/msg/Detection2DArray")


@pytest.mark.skipif(not COMMITTED_BAGS, reason="no committed bags in bags/ yet")
@pytest.mark.parametrize("bag", COMMITTED_BAGS, ids=lambda p: p.name)
def test_committed_bag_structure_with_a_tiny_model(bag, tmp_path):
    summary = replay_bag(bag, tmp_path / "out", _tiny_engine(), progress=False)
    n = _check_structure(bag, tmp_path / "out", summary.image_topic, _detection_topic(bag))
    assert n == summary.images


#: Bags scored against their ground truth with the bounds above. ``night_tail_lamps``
#: holds no signal at all (a constant answer is perfect there); test_night_tail_lamps.py
#: checks it.
SCORED_BAGS = [p for p in COMMITTED_BAGS if p.name in ("day_street", "night_street")]


@pytest.mark.skipif(not SCORED_BAGS, reason="no committed bags in bags/ yet")
@pytest.mark.parametrize("bag", SCORED_BAGS, ids=lambda p: p.name)
def test_committed_bag_agrees_with_ground_truth(bag, tmp_path):
    from signal_light_node.runtime.engine import engine_from_checkpoint
    from signal_light_node.model import DEFAULT_WEIGHTS

    if not DEFAULT_WEIGHTS.exists():
        pytest.skip(f"shipped weights {DEFAULT_WEIGHTS} do not exist yet")
    summary = replay_bag(bag, tmp_path / "out", engine_from_checkpoint(), progress=False)
    if not summary.has_ground_truth:
        pytest.skip(f"{bag.name} has no {GROUND_TRUTH_TOPIC}")
    result = score_summary(summary)
    assert result is not None, "no judged detection matched the ground truth"
    s = result["no_grace"]["summary"]
    assert s["brake_accuracy"] >= MIN_BRAKE_ACCURACY, s
    assert s["intent_macro_f1"] >= MIN_INTENT_MACRO_F1, s
    # A clear margin over the best trivial answer: one constant class for every frame.
    overall = result["no_grace"]["overall"]
    assert s["brake_accuracy"] >= constant_accuracy(overall["brake"]) + BASELINE_MARGIN, s
    assert s["intent_macro_f1"] >= constant_macro_f1(overall["intent"]) + BASELINE_MARGIN, s


def constant_accuracy(scores: dict) -> float:
    """Accuracy of always answering the most common ground-truth class."""
    support = scores["per_class"]["support"]
    return max(support) / sum(support)


def constant_macro_f1(scores: dict) -> float:
    """Best macro-F1 (the project's metric) of answering one class for every frame."""
    support = np.asarray(scores["per_class"]["support"])
    best = 0.0
    for answer in range(len(support)):
        confusion = np.zeros((len(support), len(support)), np.int64)
        confusion[:, answer] = support
        best = max(best, macro_f1(confusion) or 0.0)
    return best


def test_trivial_baselines_by_hand():
    scores = {"per_class": {"support": [30, 10, 0, 60]}}
    assert constant_accuracy(scores) == pytest.approx(0.6)
    # answering class 3: F1 2*0.6/1.6 = 0.75 for it, 0 for the two other present classes
    assert constant_macro_f1(scores) == pytest.approx(0.75 / 3)


@pytest.mark.skipif(not (REPO / "bags" / "independent_day").exists(),
                    reason="bags/independent_day is not committed")
def test_geometry_judges_blinkers_the_model_calls_unknown_on_another_renderer(tmp_path):
    """On the independent generator's day bag the shipped model calls many visible blinkers
    UNKNOWN; with ``blinker_sight: geometry`` (view head and box cover) most are judged, the
    brake untouched (docs/model.md, "Visibility from geometry"). The CNN shipped until
    2026-11-26 called 91 / 98 % of them UNKNOWN (geometry: 29 / 59 %); the fine-tuned trunk
    42 / 44 % (geometry: 13 / 16 %); the filled-crop members shipped 2026-11-29 call 19 /
    25 % (geometry: 6 / 7 %)."""
    from signal_light_node.model import DEFAULT_WEIGHTS
    from signal_light_node.runtime.engine import engine_from_checkpoint
    from signal_light_node.runtime.intent_filter import IntentFilterConfig

    if not DEFAULT_WEIGHTS.exists():
        pytest.skip(f"shipped weights {DEFAULT_WEIGHTS} do not exist yet")
    bag = REPO / "bags" / "independent_day"
    shares = {}
    for sight in ("model", "geometry"):
        engine = engine_from_checkpoint(
            threads=1, intent_filter=IntentFilterConfig(blinker_sight=sight))
        result = score_summary(replay_bag(bag, tmp_path / sight, engine, progress=False))
        assert result is not None
        shares[sight] = {light: result["unknown_share"][light]["share"]
                         for light in ("brake", "left", "right")}
    model, geometry = shares["model"], shares["geometry"]
    assert geometry["brake"] == model["brake"]
    for light in ("left", "right"):  # measured 0.19 -> 0.06 and 0.25 -> 0.07
        assert geometry[light] <= model[light] - 0.1, shares
