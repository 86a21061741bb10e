"""The bad-input matrix: damaged, odd or excessive input costs one frame, never the run.

Each case feeds one kind of bad input to the live node (its own process, real rclpy),
to ``replay`` (in-process, with the fake model of ``fake_light_model``) or to start-up,
and asserts: no crash, the documented result or a counted drop, and sane outputs (one
entry per detection with its ID, probabilities finite and summing to 1, codes only
100/101/102). Damaged bags are made here in ``tmp_path``; nothing is committed.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
import pytest

from node_harness import DetectorProcess, run_until_exit, tiny_checkpoint
from signal_light_node.node.params import NODE_NAME

MS = 1_000_000
S = 1_000_000_000
T0 = 1_700_000_000 * S


def check_sane(msg, ids: Sequence[str]) -> None:
    """One entry per detection, IDs kept, probabilities finite and summing to 1, known codes.

    Works on rclpy and rosbags ``VehicleLightStateArray`` messages alike.
    """
    assert [v.track_id for v in msg.vehicles] == list(ids)
    for v in msg.vehicles:
        for light in (v.brake, v.left_blinker, v.right_blinker):
            probs = (light.on_probability, light.off_probability, light.unknown_probability)
            assert all(math.isfinite(p) and 0.0 <= p <= 1.0 for p in probs)
            assert abs(sum(probs) - 1.0) < 1e-3 and light.state in (0, 1, 2)
        assert {c.label for c in v.classification} <= {100, 101, 102}
        assert all(math.isfinite(c.probability) for c in v.classification)
        assert math.isfinite(v.intent_probability) and math.isfinite(v.view_probability)


# ------------------------------------------------------------------------- start-up
def _one_fatal_line(lines: List[str], *words: str) -> None:
    assert len(lines) == 1, lines
    assert "FATAL" in lines[0] and "Traceback" not in lines[0]
    for word in words:
        assert word in lines[0], lines[0]


def test_startup_missing_params_file_is_one_line(tmp_path, rclpy_isolated_env):
    code, lines = run_until_exit(["--params-file", str(tmp_path / "absent.yaml")],
                                 rclpy_isolated_env(), tmp_path)
    assert code == 1
    _one_fatal_line(lines, "bad ROS arguments", "absent.yaml")


def test_startup_bad_remap_rule_is_one_line(tmp_path, rclpy_isolated_env):
    code, lines = run_until_exit(["-r", "no_arrow_here"], rclpy_isolated_env(), tmp_path)
    assert code == 1
    _one_fatal_line(lines, "bad ROS arguments", "remap")


def test_startup_cuda_without_cuda_names_cuda(tmp_path, rclpy_isolated_env):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    model = tiny_checkpoint(tmp_path / "tiny.pt")
    code, lines = run_until_exit(["-p", f"model_path:={model}", "-p", "device:=cuda"],
                                 rclpy_isolated_env(), tmp_path)
    assert code == 1
    _one_fatal_line(lines, "CUDA requested but not available")
    assert "cannot be read as a checkpoint" not in lines[0]


def test_startup_params_file_for_another_node_is_warned(tmp_path, rclpy_isolated_env):
    params = tmp_path / "other.yaml"
    params.write_text("other_node:\n  ros__parameters:\n    max_tracks: 5\n")
    model = tiny_checkpoint(tmp_path / "tiny.pt")
    node = DetectorProcess(["--params-file", str(params), "-p", f"model_path:={model}"],
                           rclpy_isolated_env(), tmp_path / "detector.log")
    try:
        node.wait_ready()
        warned = [line for line in node.text().splitlines() if "other.yaml" in line]
        assert len(warned) == 1 and "WARN" in warned[0] and NODE_NAME in warned[0], warned
    finally:
        assert node.stop() == 0, node.text()


def test_params_file_sections_matching_this_node_are_not_warned(tmp_path):
    from signal_light_node.node.params import foreign_params_file, params_file_paths

    fqn = f"/{NODE_NAME}"
    for key in (NODE_NAME, fqn, "/**", "/*", "/**/" + NODE_NAME):
        path = tmp_path / "p.yaml"
        path.write_text(f"'{key}':\n  ros__parameters:\n    max_tracks: 5\n")
        assert foreign_params_file(str(path), fqn) is None, key
    for key in ("other", "/ns/*", "/signal_light"):
        path.write_text(f"'{key}':\n  ros__parameters:\n    max_tracks: 5\n")
        assert "no section for node" in foreign_params_file(str(path), fqn), key
    assert params_file_paths(["--ros-args", "--params-file", "a.yaml", "-p", "x:=1",
                              "--params-file", "b.yaml"]) == ["a.yaml", "b.yaml"]


def test_engine_from_checkpoint_without_cuda_names_cuda(tmp_path):
    import torch

    from signal_light_node.engine import engine_from_checkpoint
    from signal_light_node.errors import ConfigError

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    with pytest.raises(ConfigError, match="CUDA requested but not available"):
        engine_from_checkpoint(str(tiny_checkpoint(tmp_path / "tiny.pt")), device="cuda")


# ----------------------------------------------------------------------------- bags
IMAGE_T = "/camera/image/compressed"
RAW_T = "/camera/image_raw"
DET_T = "/tracker/detections"
DET_TYPE = "vision_msgs/msg/Detection2DArray"
OLD_VISION_MSGS = {  # vision_msgs before 4.0: the centre is a geometry_msgs/Pose2D
    "vision_msgs/msg/BoundingBox2D": "geometry_msgs/Pose2D center\nfloat64 size_x\n"
                                     "float64 size_y\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": "string id\nfloat64 score\n"
                                                "geometry_msgs/PoseWithCovariance pose\n",
    "vision_msgs/msg/Detection2D": "std_msgs/Header header\n"
                                   "vision_msgs/ObjectHypothesisWithPose[] results\n"
                                   "vision_msgs/BoundingBox2D bbox\nstring id\n",
    "vision_msgs/msg/Detection2DArray": "std_msgs/Header header\n"
                                        "vision_msgs/Detection2D[] detections\n",
}


def _boxes(i: int) -> list:
    from signal_light_node.boxes import TrackBox

    return [TrackBox(f"car{k}", 10 + 30 * k, 20, 40 + 30 * k, 50) for k in range(2)]


def _frame(i: int, raw: bool = False, size=(160, 96)) -> list:
    """``[(topic, type, log time, message)]`` of frame ``i``: an image and its detections."""
    from signal_light_node.bagio import make
    from signal_light_node.conversions import boxes_to_detections, make_header
    from signal_light_node.image_codec import bgr_to_compressed_fields, bgr_to_image_fields

    stamp = T0 + i * 100 * MS
    header = make_header(stamp, "cam", make)
    rng = np.random.default_rng(i)
    image = rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
    if raw:
        img = (RAW_T, "sensor_msgs/msg/Image", make("sensor_msgs/msg/Image", header=header,
                                                    **bgr_to_image_fields(image)))
    else:
        img = (IMAGE_T, "sensor_msgs/msg/CompressedImage",
               make("sensor_msgs/msg/CompressedImage", header=header,
                    **bgr_to_compressed_fields(image)))
    det = boxes_to_detections(header, _boxes(i), make)
    return [(*img[:2], stamp, img[2]), (DET_T, DET_TYPE, stamp + MS, det)]


def write_bag(path: Path, messages: list, store=None) -> Path:
    """An MCAP rosbag2 directory; a message given as bytes is written as is (damaged CDR)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from signal_light_node.bagio import typestore

    store = store or typestore()
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    conns: Dict[str, object] = {}
    for topic, msgtype, t, msg in messages:
        if topic not in conns:
            conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
        raw = msg if isinstance(msg, bytes) else bytes(store.serialize_cdr(msg, msgtype))
        writer.write(conns[topic], t, raw)
    writer.close()
    return path


def _serialized(message: tuple) -> bytes:
    from signal_light_node.bagio import typestore

    return bytes(typestore().serialize_cdr(message[3], message[1]))


def _fake_engine(**kwargs):
    from fake_light_model import FakeLightModel
    from signal_light_node.engine import EngineConfig, LightStateEngine

    return LightStateEngine(FakeLightModel(), EngineConfig(**kwargs))


def replay(bag: Path, tmp_path: Path, **kwargs):
    """``(summary, {stamp: output message})`` of a replay with the fake model."""
    from signal_light_node.bagio import open_bag
    from signal_light_node.conversions import stamp_to_ns
    from signal_light_node.replay import OUTPUT_TOPIC, replay_bag

    out = tmp_path / "out"
    summary = replay_bag(bag, out, _fake_engine(**kwargs), progress=False)
    with open_bag(out) as reader:
        outputs = {stamp_to_ns(m.msg.header.stamp): m.msg for m in reader.messages([OUTPUT_TOPIC])}
    assert len(outputs) == summary.outputs
    for msg in outputs.values():
        check_sane(msg, [v.track_id for v in msg.vehicles])
    return summary, outputs


def test_bag_old_vision_msgs_pose2d_centre_is_read(tmp_path):
    """Defect 2: a bag with the vision_msgs < 4 layout ended in an AttributeError."""
    from rosbags.typesys import Stores, get_typestore, get_types_from_msg

    old = get_typestore(Stores.ROS2_JAZZY)
    for name, text in OLD_VISION_MSGS.items():
        old.register(get_types_from_msg(text, name))
    messages = []
    for i in range(4):
        img, _ = _frame(i)
        header = img[3].header
        centre = old.types["geometry_msgs/msg/Pose2D"](x=35.0 + i, y=40.0, theta=0.0)
        dets = [old.types["vision_msgs/msg/Detection2D"](
            header=header, results=[], id=f"old{i}",
            bbox=old.types["vision_msgs/msg/BoundingBox2D"](center=centre, size_x=30.0,
                                                            size_y=20.0))]
        messages += [img, (DET_T, DET_TYPE, img[2] + MS,
                           old.types[DET_TYPE](header=header, detections=dets))]
    bag = write_bag(tmp_path / "old", messages, store=old)
    summary, outputs = replay(bag, tmp_path)
    assert summary.outputs == 4 and not summary.skipped
    for i, stamp in enumerate(sorted(outputs)):
        check_sane(outputs[stamp], [f"old{i}"])
        roi = outputs[stamp].vehicles[0].roi
        assert (roi.x_offset, roi.y_offset, roi.width) == (20 + i, 30, 30)


def test_bag_invalid_utf8_track_id_skips_that_message(tmp_path):
    """Defect 3: one detection array with an ID that is not UTF-8 ended the replay (exit 2)."""
    from signal_light_node.boxes import TrackBox
    from signal_light_node.bagio import make
    from signal_light_node.conversions import boxes_to_detections

    messages = []
    for i in range(5):
        img, det = _frame(i)
        if i == 2:
            det = boxes_to_detections(img[3].header, [TrackBox("XXXX", 1, 1, 30, 30)], make)
            det = (DET_T, DET_TYPE, img[2] + MS, _serialized((0, DET_TYPE, 0, det))
                   .replace(b"XXXX", b"\xff\xfe\xfd\xfc"))
        messages += [img, det]
    summary, outputs = replay(write_bag(tmp_path / "bag", messages), tmp_path)
    assert summary.outputs == 5 and summary.skipped == {DET_T: 1}
    assert summary.images_without_detections == 1
    assert list(outputs[T0 + 200 * MS].vehicles) == []
    check_sane(outputs[T0 + 300 * MS], ["car0", "car1"])


def test_bag_truncated_image_message_costs_one_frame(tmp_path, capsys):
    """Defect 3: one truncated Image ended the replay with 2 of 5 frames written (exit 2)."""
    from signal_light_node.cli import main

    messages = []
    for i in range(5):
        img, det = _frame(i, raw=True)
        if i == 2:
            img = (*img[:3], _serialized(img)[:500])
        messages += [img, det]
    bag = write_bag(tmp_path / "bag", messages)
    ckpt = tiny_checkpoint(tmp_path / "tiny.pt")
    code = main(["replay", str(bag), "-o", str(tmp_path / "cli"), "--checkpoint", str(ckpt),
                 "--no-progress"])
    assert code == 0
    assert f"skipped messages (undecodable or unconvertible): 1 on {RAW_T}" in \
        capsys.readouterr().out
    summary, outputs = replay(bag, tmp_path)
    assert summary.images == summary.outputs == 4 and summary.skipped == {RAW_T: 1}
    assert sorted(outputs) == [T0 + k * 100 * MS for k in (0, 1, 3, 4)]


def _cut(path: Path, fraction: float) -> int:
    data = path.read_bytes()
    path.write_bytes(data[:int(len(data) * fraction)])
    return len(data)


def test_bag_cut_mcap_inside_a_bag_directory_is_recovered(tmp_path):
    """Defect 8: with metadata.yaml present, a cut MCAP was refused ("end magic")."""
    messages = [m for i in range(12) for m in _frame(i, raw=True, size=(320, 240))]
    bag = write_bag(tmp_path / "bag", messages)  # 230 kB images: several 1 MB chunks
    assert (bag / "metadata.yaml").exists()
    _cut(next(bag.glob("*.mcap")), 0.8)
    summary, outputs = replay(bag, tmp_path)
    assert summary.recovered is not None and 10 <= summary.recovered < 24
    assert summary.outputs >= 5 and not summary.skipped
    for stamp, msg in outputs.items():
        check_sane(msg, ["car0", "car1"])


def test_bag_cut_inside_its_only_chunk_is_recovered(tmp_path):
    """Defect 8: a bag whose single chunk is cut was not recovered at all."""
    from signal_light_node.bagio import open_bag

    bag = write_bag(tmp_path / "bag", [m for i in range(10) for m in _frame(i)])
    mcap = next(bag.glob("*.mcap"))
    _cut(mcap, 0.6)
    with open_bag(mcap) as reader:
        assert 5 <= reader.recovered < 20
        assert reader.topics()[IMAGE_T].count >= 3
    summary, _ = replay(bag, tmp_path)
    assert summary.recovered == reader.recovered and summary.outputs >= 3


def test_bag_unconvertible_detections_are_skipped_and_counted(tmp_path):
    """A detection array whose box size is not a number is skipped, not fatal."""
    from signal_light_node.bagio import BagReader

    messages = [m for i in range(3) for m in _frame(i)]
    bag = write_bag(tmp_path / "bag", messages)
    original = BagReader.messages

    def broken(self, *args, **kwargs):
        for m in original(self, *args, **kwargs):
            if m.topic == DET_T and m.log_time_ns == T0 + 100 * MS + MS:
                m.msg.detections[0].bbox.size_x = "wide"
            yield m

    BagReader.messages = broken
    try:
        summary, outputs = replay(bag, tmp_path)
    finally:
        BagReader.messages = original
    assert summary.skipped == {DET_T: 1} and summary.outputs == 3
    assert list(outputs[T0 + 100 * MS].vehicles) == []


@pytest.mark.parametrize("case", ["empty_dir", "detections_only", "not_mcap"])
def test_bag_unusable_bags_are_one_line_errors(tmp_path, capsys, case):
    from signal_light_node.cli import main

    bag = tmp_path / "bag"
    if case == "empty_dir":
        bag.mkdir()
    elif case == "detections_only":
        write_bag(bag, [m for i in range(3) for m in _frame(i) if m[0] == DET_T])
    else:
        bag = tmp_path / "bag.mcap"
        bag.write_bytes(b"this is not an MCAP file at all" * 10)
    code = main(["replay", str(bag), "-o", str(tmp_path / "out"), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "error" in err[0], err
