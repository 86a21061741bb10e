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
from signal_light_node.ros.params import NODE_NAME

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


@pytest.mark.parametrize("backend", ["torch", "onnxruntime"])
def test_startup_cuda_without_cuda_names_cuda(tmp_path, rclpy_isolated_env, backend):
    import onnxruntime
    import torch

    if torch.cuda.is_available() or "CUDAExecutionProvider" in \
            onnxruntime.get_available_providers():
        pytest.skip("this machine has CUDA")
    model = [] if backend == "onnxruntime" else \
        ["-p", f"model_path:={tiny_checkpoint(tmp_path / 'tiny.pt')}"]
    code, lines = run_until_exit([*model, "-p", "device:=cuda", "-p", f"backend:={backend}"],
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
    from signal_light_node.ros.params import foreign_params_file, params_file_paths

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

    from signal_light_node.runtime.engine import engine_from_checkpoint
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
    from signal_light_node.io.bagio import make
    from signal_light_node.io.conversions import boxes_to_detections, make_header
    from signal_light_node.io.image_codec import bgr_to_compressed_fields, bgr_to_image_fields

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


def write_bag(path: Path, messages: list, store=None, zstd: bool = False) -> Path:
    """An MCAP rosbag2 directory; a message given as bytes is written as is (damaged CDR)."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    from signal_light_node.io.bagio import typestore

    store = store or typestore()
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    if zstd:
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
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
    from signal_light_node.io.bagio import typestore

    return bytes(typestore().serialize_cdr(message[3], message[1]))


def _fake_engine(**kwargs):
    from fake_light_model import FakeLightModel
    from signal_light_node.runtime.engine import EngineConfig, LightStateEngine

    return LightStateEngine(FakeLightModel(), EngineConfig(**kwargs))


def replay(bag: Path, tmp_path: Path, **kwargs):
    """``(summary, {stamp: output message})`` of a replay with the fake model."""
    from signal_light_node.io.bagio import open_bag
    from signal_light_node.io.conversions import stamp_to_ns
    from signal_light_node.tools.replay import OUTPUT_TOPIC, replay_bag

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
    from signal_light_node.io.bagio import make
    from signal_light_node.io.conversions import boxes_to_detections

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


@pytest.mark.parametrize("zstd", [False, True], ids=["plain", "zstd"])
def test_bag_cut_inside_its_only_chunk_is_recovered(tmp_path, zstd):
    """Defect 8: a bag whose single chunk is cut was not recovered at all."""
    from signal_light_node.io.bagio import open_bag

    # 40 frames of about 20 kB stay in one 1 MB chunk: with zstd, several 128 kB blocks,
    # the complete ones of which can be decompressed.
    bag = write_bag(tmp_path / "bag", [m for i in range(40) for m in _frame(i)], zstd=zstd)
    mcap = next(bag.glob("*.mcap"))
    _cut(mcap, 0.6)
    with open_bag(mcap) as reader:
        assert 5 <= reader.recovered < 80
        assert reader.topics()[IMAGE_T].count >= 3
    summary, _ = replay(bag, tmp_path)
    assert summary.recovered == reader.recovered and summary.outputs >= 3


def test_bag_unconvertible_detections_are_skipped_and_counted(tmp_path):
    """A detection array whose box size is not a number is skipped, not fatal."""
    from signal_light_node.io.bagio import BagReader

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


# --------------------------------------------------------------------------- limits
def _peak_mb(fn) -> float:
    import tracemalloc

    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1] / 1e6
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("side, size", [(10_000, (320, 180)), (15_000, (640, 360))])
def test_limits_attention_overlay_memory_is_bounded_by_the_image(side, size):
    """Defect 4: the overlay took (1.3 x box side)^2 floats per box (965 MB, 1.76 GB)."""
    from signal_light_node.boxes import TrackBox
    from signal_light_node.outputs.debug_image import draw_results

    engine = _fake_engine()
    image = np.full((size[1], size[0], 3), 120, np.uint8)
    box = TrackBox.from_center("huge", size[0] / 2, size[1] / 2, side, side)

    def overlay():
        heat = engine.attention_masks(image, [box])
        assert heat.shape == image.shape[:2] and 0.0 < heat.max() <= 1.0
        draw_results(image, engine.process(image, T0, [box]).results, heat)

    start = time.perf_counter()
    assert _peak_mb(overlay) < 40
    assert time.perf_counter() - start < 2.0


def test_limits_boxes_beyond_the_limit_are_reported_unjudged_and_counted():
    """Defect 5: 1,000 boxes took 4.9 s a frame; now at most max_boxes are judged."""
    from signal_light_node.boxes import TrackBox

    engine = _fake_engine(max_boxes=50, max_tracks=20)
    image = np.full((360, 640, 3), 100, np.uint8)
    boxes = [TrackBox(f"t{k}", k % 600, 10, k % 600 + 30, 40) for k in range(1000)]
    frame = engine.process(image, T0, boxes)
    assert [r.track_id for r in frame.results] == [b.track_id for b in boxes]
    assert frame.n_judged == 50 and sum(r.judged for r in frame.results) == 50
    counters = engine.counters
    assert counters["over_limit"] == 950
    assert counters["overflow"] == 30  # 50 judged tracks, 20 of them keep a state
    assert sum("over the limit of 50" in w for w in frame.warnings) == 1


def _png_bomb(width: int, height: int) -> bytes:
    """A valid greyscale PNG of ``width x height`` zeros, built row by row (a few hundred kB)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    packer = zlib.compressobj(9)
    row = bytes(width + 1)
    body = b"".join(packer.compress(row) for _ in range(height)) + packer.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", body)
            + chunk(b"IEND", b""))


def test_limits_huge_png_is_refused_before_decoding():
    """Defect 5: a 420 kB PNG of 12000 x 12000 took the node to 1.12 GB, 2 s a frame."""
    from signal_light_node.errors import ImageTooLargeError
    from signal_light_node.io.image_codec import DEFAULT_MAX_IMAGE_PIXELS, compressed_msg_to_bgr

    class Msg:
        format = "png"
        data = _png_bomb(12_000, 12_000)

    assert len(Msg.data) < 1_000_000
    start = time.perf_counter()
    with pytest.raises(ImageTooLargeError, match="12000x12000"):
        compressed_msg_to_bgr(Msg, "/camera", T0, max_pixels=DEFAULT_MAX_IMAGE_PIXELS)
    assert time.perf_counter() - start < 0.5


@pytest.mark.parametrize("kind", ["png", "jpeg", "progressive_jpeg"])
def test_limits_header_sizes_are_read_without_decoding(kind):
    import cv2

    from signal_light_node.io.image_codec import compressed_dimensions

    image = np.zeros((37, 53, 3), np.uint8)
    params = [cv2.IMWRITE_JPEG_PROGRESSIVE, 1] if kind == "progressive_jpeg" else []
    ok, data = cv2.imencode(".png" if kind == "png" else ".jpg", image, params)
    assert ok and compressed_dimensions(data.tobytes()) == (53, 37)
    assert compressed_dimensions(b"GIF89a....") is None


# ------------------------------------------------------------------------ live node
RAW_TYPE = "sensor_msgs/msg/Image"
LIVE_LIMITS = {"max_image_pixels": 200_000, "max_boxes_per_frame": 64, "max_tracks": 16}


class Live:
    """The detector (raw images, reliable, small limits) and a client, shared by the cases."""

    def __init__(self, node: DetectorProcess, client) -> None:
        self.node, self.client = node, client
        self.stamp = T0

    def next_stamp(self) -> int:
        self.stamp += 100 * MS
        return self.stamp

    def image(self, stamp: int, fields: dict):
        from signal_light_node.io.conversions import make_header
        from signal_light_node.ros.messages import rclpy_make

        return rclpy_make(RAW_TYPE, header=make_header(stamp, "cam", rclpy_make), **fields)

    def detections(self, stamp: int, boxes: list):
        from signal_light_node.io.conversions import boxes_to_detections, make_header
        from signal_light_node.ros.messages import rclpy_make

        return boxes_to_detections(make_header(stamp, "cam", rclpy_make), boxes, rclpy_make)

    def send(self, fields: Optional[dict], boxes: Optional[list], stamp: Optional[int] = None,
             timeout: float = 20.0):
        """Publish an image and / or detections; the output for the stamp, or None."""
        stamp = self.next_stamp() if stamp is None else stamp
        if fields is not None:
            self.client.image_pub.publish(self.image(stamp, fields))
        if boxes is not None:
            self.client.det_pub.publish(self.detections(stamp, boxes))
        if fields is None or boxes is None:
            return None
        assert self.client.spin_until(lambda: stamp in self.client.outputs, timeout), \
            self.node.text()[-3000:]
        return self.client.outputs[stamp][-1]

    def diag(self) -> Dict[str, str]:
        if not self.client.diagnostics:
            return {}
        return {kv.key: kv.value for kv in self.client.diagnostics[-1].status[0].values}

    def count(self, key: str) -> int:
        return int(self.diag().get(key, 0))

    def wait_count(self, key: str, at_least: int, timeout: float = 10.0) -> int:
        self.client.spin_until(lambda: self.count(key) >= at_least, timeout)
        return self.count(key)


def _live_args(tmp: Path, reliability: str, **params: str) -> List[str]:
    """The live node's arguments: a tiny model, short timeouts, ``LIVE_LIMITS``."""
    values = {"model_path": str(tiny_checkpoint(tmp / "tiny.pt")), "reliability": reliability,
              "sync_timeout_s": "0.5", "diagnostics_period_s": "0.2", **LIVE_LIMITS, **params}
    return [a for k, v in values.items() for a in ("-p", f"{k}:={v}")]


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    from conftest import isolated_ros_env
    from node_harness import LiveClient

    tmp = tmp_path_factory.mktemp("live")
    env = isolated_ros_env()
    node = DetectorProcess(_live_args(tmp, "reliable", publish_debug_image="true"), env,
                           tmp / "detector.log")
    try:
        node.wait_ready()
        with LiveClient(int(env["ROS_DOMAIN_ID"]), RAW_TYPE) as client:
            client.wait_connected()
            client.spin_until(lambda: client.node.count_publishers(
                "/signal_light_detector/output/debug/image") > 0, 20.0)
            client.warm_up(T0, "cam")
            yield Live(node, client)
            assert node.proc.poll() is None, node.text()[-3000:]
    finally:
        code = node.stop()
    assert code == 0 and "Traceback" not in node.text(), node.text()[-3000:]


def _raw(enc: str = "bgr8", size=(160, 96), **changes) -> dict:
    """Image fields of a noise image encoded as ``enc``, with ``changes`` (bad fields) applied."""
    from signal_light_node.io.image_codec import bgr_to_image_fields

    image = np.random.default_rng(7).integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
    fields = bgr_to_image_fields(image, enc)
    fields.update(changes)
    return fields


def _padded() -> dict:
    fields = _raw()
    rows = fields["data"].reshape(96, 480)
    fields.update(step=500, data=np.concatenate([rows, np.zeros((96, 20), np.uint8)], 1)
                  .reshape(-1))
    return fields


def _box(track_id: str, x0: float, y0: float, x1: float, y1: float):
    from signal_light_node.boxes import TrackBox

    return TrackBox(track_id, x0, y0, x1, y1)


TWO = [("a", 10, 10, 60, 50), ("b", 80, 20, 150, 90)]

#: name -> (image fields, boxes, counter that grows by one or None, judged)
IMAGE_CASES = {
    "rgb8": (lambda: _raw("rgb8"), None, True),
    "bgra8": (lambda: _raw("bgra8"), None, True),
    "mono8": (lambda: _raw("mono8"), None, True),
    "mono16": (lambda: _raw("mono16"), None, True),
    "opencv_alias_8UC3": (lambda: _raw("8UC3"), None, True),
    "row_padding": (_padded, None, True),
    "unsupported_yuv422": (lambda: _raw(encoding="yuv422"), "bad_images", False),
    "float_32FC1": (lambda: _raw(encoding="32FC1"), "bad_images", False),
    "truncated_data": (lambda: _raw(data=_raw()["data"][:1000]), "bad_images", False),
    "step_too_small": (lambda: _raw(step=100), "bad_images", False),
    "zero_size": (lambda: _raw(width=0, height=0, step=0, data=np.zeros(0, np.uint8)),
                  "bad_images", False),
    "oversized": (lambda: _raw(size=(600, 400)), "oversized_images", False),
}


@pytest.mark.parametrize("name", list(IMAGE_CASES))
def test_live_image_encodings(live, name):
    make_fields, counter, judged = IMAGE_CASES[name]
    before = live.count(counter) if counter else 0
    out = live.send(make_fields(), [_box(*b) for b in TWO])
    check_sane(out, ["a", "b"])
    assert all((v.view_probability > 0) == judged for v in out.vehicles)
    if counter:
        assert live.wait_count(counter, before + 1) == before + 1


BOX_CASES = {
    "nan": ([("n", math.nan, 10, 50, 40)], [False]),
    "outside": ([("o", 500, 300, 600, 400)], [False]),
    "zero_size": ([("z", 20, 20, 20, 20)], [False]),
    "negative_size": ([("neg", 60, 60, 20, 20)], [False]),
    "infinite": ([("inf", 0, 0, math.inf, 50)], [False]),
    "huge_10000px": ([("huge", -4840, -4910, 5160, 5090)], [True]),
    "duplicate_ids": ([("d", 10, 10, 60, 50), ("d", 80, 20, 150, 90)], [True, False]),
    "empty_id": ([("", 10, 10, 60, 50)], [True]),
    "long_id": ([("x" * 5000, 10, 10, 60, 50)], [True]),
    "unicode_id": (["\u8eca-\U0001F697-\u00e9", 10, 10, 60, 50], None),
    "no_detections": ([], []),
}


@pytest.mark.parametrize("name", list(BOX_CASES))
def test_live_boxes_and_ids(live, name):
    from signal_light_node.io.conversions import stamp_to_ns

    boxes, judged = BOX_CASES[name]
    if judged is None:  # a single box given flat
        boxes, judged = [tuple(boxes)], [True]
    before = int(_vm_hwm_kb(live.node.proc.pid))
    out = live.send(_raw(size=(320, 180)), [_box(*b) for b in boxes])
    check_sane(out, [b[0] for b in boxes])
    assert [v.view_probability > 0 for v in out.vehicles] == judged
    # The debug overlay (published: the client watches it) stays within the image's size.
    stamp = live.stamp
    assert live.client.spin_until(lambda: any(
        stamp_to_ns(m.header.stamp) == stamp for m in live.client.debug_images), 20.0)
    assert _vm_hwm_kb(live.node.proc.pid) - before < 150_000


def _vm_hwm_kb(pid: int) -> int:
    """Peak resident memory of a process, kB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
    raise AssertionError("no VmHWM")


def test_live_too_many_boxes_are_counted(live):
    before = live.count("boxes_over_limit")
    boxes = [_box(f"m{k}", k % 140, 10, k % 140 + 20, 40) for k in range(300)]
    out = live.send(_raw(), boxes)
    check_sane(out, [b.track_id for b in boxes])
    assert sum(v.view_probability > 0 for v in out.vehicles) == 64
    assert live.wait_count("boxes_over_limit", before + 236) == before + 236


def test_live_tracks_beyond_max_tracks_are_counted(live):
    """Defect 5: tracks past max_tracks started fresh every frame, unreported."""
    before = live.count("track_overflow")
    boxes = [_box(f"ov{k}", 5 * k, 10, 5 * k + 20, 40) for k in range(30)]
    for _ in range(2):
        check_sane(live.send(_raw(), boxes), [b.track_id for b in boxes])
    assert live.wait_count("track_overflow", before + 28) == before + 28


def test_live_stamp_jumping_back_resets_and_goes_on(live):
    before = live.count("track_resets")
    out = live.send(_raw(), [_box(*TWO[0])], stamp=live.stamp - 5 * S)
    check_sane(out, ["a"])
    assert live.wait_count("track_resets", before + 1) >= before + 1
    check_sane(live.send(_raw(), [_box(*TWO[0])]), ["a"])


@pytest.mark.parametrize("half", ["image", "detections"])
def test_live_unpaired_half_is_dropped_and_counted(live, half):
    key = f"dropped_{half}_timeout"
    before = live.count(key)
    live.send(_raw() if half == "image" else None,
              [_box(*TWO[0])] if half == "detections" else None)
    assert live.wait_count(key, before + 1) == before + 1
    check_sane(live.send(_raw(), [_box(*TWO[0])]), ["a"])


# ----------------------------------------------------------------- bursts and rates
IMAGE_DROPS = ("dropped_image_timeout", "dropped_image_overflow", "dropped_image_duplicate")
DETECTION_DROPS = ("dropped_detections_timeout", "dropped_detections_overflow",
                   "dropped_detections_duplicate")


def _counters(report) -> Dict[str, int]:
    """The frame counters of one /diagnostics report."""
    from signal_light_node.runtime.stats import DROP_COUNTERS

    keys = ("images", "detections", "paired", "outputs", "pending_images",
            "pending_detections", "work_queue_length") + DROP_COUNTERS
    values = {kv.key: kv.value for kv in report.status[0].values}
    return {k: int(values[k]) for k in keys}


def _quiet(live) -> Dict[str, int]:
    """The counters once two fresh reports agree and nothing waits."""
    reports = live.client.diagnostics
    start = len(reports)

    def quiet() -> bool:
        if len(reports) < start + 2:
            return False
        now = _counters(reports[-1])
        return now == _counters(reports[-2]) and not (
            now["pending_images"] or now["pending_detections"] or now["work_queue_length"])

    assert live.client.spin_until(quiet, 30.0), live.diag()
    return _counters(reports[-1])


def _balance(d: Dict[str, int], n: int) -> List[str]:
    """The books that do not balance after ``n`` frames were published (empty: all do)."""
    problems = []
    # Everything published reached the node or is counted as lost by the middleware ...
    if d["images"] + d["dropped_image_middleware"] != n:
        problems.append("images received + dropped by the middleware != published")
    if d["detections"] + d["dropped_detections_middleware"] != n:
        problems.append("detections received + dropped by the middleware != published")
    # ... and everything that reached it is an output or a counted drop.
    if d["images"] != d["paired"] + sum(d[k] for k in IMAGE_DROPS):
        problems.append("images received != paired + image drops")
    if d["detections"] != d["paired"] + sum(d[k] for k in DETECTION_DROPS):
        problems.append("detections received != paired + detection drops")
    if d["paired"] != d["outputs"] + d["dropped_work_queue"] + d["processing_errors"]:
        problems.append("paired != outputs + work-queue drops + errors")
    return problems


def _accounted(live, send) -> Dict[str, int]:
    """Run ``send`` (it publishes frames and returns how many), then poll until every one
    is accounted for: an output or a counted drop (reliable repair can take seconds)."""
    before = _quiet(live)
    n = send()
    diff: Dict[str, int] = {}

    def balanced() -> bool:
        nonlocal diff
        diff = {k: v - before[k] for k, v in _counters(live.client.diagnostics[-1]).items()}
        return not _balance(diff, n)

    assert live.client.spin_until(balanced, 30.0), f"{_balance(diff, n)}: {diff}"
    return diff


def _burst(live, image_pub, det_pub, n: int = 200):
    """``(frames, send)``: ``n`` frames (image, detections) with successive stamps and the
    function that publishes them all at once and returns ``n`` (for ``_accounted``)."""
    frames = []
    for _ in range(n):
        stamp = live.next_stamp()
        frames.append((live.image(stamp, _raw()), live.detections(stamp, [_box(*TWO[0])])))

    def send() -> int:
        for image, detections in frames:
            image_pub.publish(image)
            det_pub.publish(detections)
        return len(frames)

    return frames, send


def test_live_burst_of_200_frames_is_accounted_for(live):
    """Defect 1: of 200 frames published at once most appeared in no counter."""
    frames, send = _burst(live, live.client.image_pub, live.client.det_pub)
    d = _accounted(live, send)
    # Depth 10 against 200 at once: the middleware drops (here, always so far), or a
    # machine fast enough took them all.
    assert d["outputs"] > 0 and (d["dropped_image_middleware"] > 0 or d["outputs"] == 200), d
    assert live.diag()["middleware_drops_counted"] == "yes"
    for image, _ in frames:
        stamp = image.header.stamp.sec * S + image.header.stamp.nanosec
        for msg in live.client.outputs.get(stamp, []):
            check_sane(msg, ["a"])


def _burst_figures(d: Dict[str, int], n: int) -> str:
    """Both inputs' books on one line: sent, received, output or paired, each drop and
    what is in no counter."""
    image_drops = ("dropped_image_middleware",) + IMAGE_DROPS + (
        "dropped_work_queue", "processing_errors")
    detection_drops = ("dropped_detections_middleware",) + DETECTION_DROPS
    images = n - d["outputs"] - sum(d[k] for k in image_drops)
    detections = n - d["paired"] - sum(d[k] for k in detection_drops)
    return (f"images sent {n} received {d['images']} output {d['outputs']} "
            + " ".join(f"{k} {d[k]}" for k in image_drops) + f" unaccounted {images}; "
            f"detection arrays sent {n} received {d['detections']} paired {d['paired']} "
            + " ".join(f"{k} {d[k]}" for k in detection_drops)
            + f" unaccounted {detections}")


@pytest.mark.parametrize("reliability", ["reliable", "best_effort"])
def test_live_burst_from_new_publishers_is_accounted_for(tmp_path, reliability):
    """Issue 25: a new user's burst, 200 images and 200 detection arrays published at once
    by publishers made for it (depth 10, the case's reliability, no warm-up frame) to a
    fresh node: every one of them is an output or a counted drop, none in no counter."""
    from conftest import isolated_ros_env
    from node_harness import LiveClient
    from signal_light_node.ros.ros_io import message_class, qos

    env = isolated_ros_env()
    node = DetectorProcess(_live_args(tmp_path, reliability), env, tmp_path / "detector.log")
    try:
        node.wait_ready()
        with LiveClient(int(env["ROS_DOMAIN_ID"]), RAW_TYPE) as client:
            live = Live(node, client)
            image_pub = client.node.create_publisher(
                message_class(RAW_TYPE), "/signal_light_detector/input/image",
                qos(reliability, 10))
            det_pub = client.node.create_publisher(
                message_class("vision_msgs/msg/Detection2DArray"),
                "/signal_light_detector/input/detections", qos(reliability, 10))
            assert client.spin_until(lambda: image_pub.get_subscription_count() > 0
                                     and det_pub.get_subscription_count() > 0
                                     and client.diagnostics, 30.0), node.text()[-3000:]
            frames, send = _burst(live, image_pub, det_pub)
            d = _accounted(live, send)
            print(f"burst {reliability}: {_burst_figures(d, len(frames))}")
            assert d["outputs"] > 0 and live.diag()["middleware_drops_counted"] == "yes"
    finally:
        code = node.stop()
    assert code == 0 and "Traceback" not in node.text(), node.text()[-3000:]


@pytest.mark.parametrize("rate_hz", [30, 200])
def test_live_steady_rates_are_accounted_for(live, rate_hz):
    def send() -> int:
        n = rate_hz  # one second of frames
        for _ in range(n):
            stamp = live.next_stamp()
            live.client.image_pub.publish(live.image(stamp, _raw()))
            live.client.det_pub.publish(live.detections(stamp, [_box(*TWO[0])]))
            live.client.spin_until(lambda: False, 1.0 / rate_hz)
        return n

    d = _accounted(live, send)
    assert d["outputs"] > 0


# ------------------------------------------------------------- compressed payloads
def _jpeg(size=(160, 96)) -> bytes:
    import cv2

    image = np.random.default_rng(3).integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
    return cv2.imencode(".jpg", image)[1].tobytes()


def _png(image: np.ndarray) -> bytes:
    import cv2

    return cv2.imencode(".png", image)[1].tobytes()


#: name -> (format, payload, decoded)
PAYLOAD_CASES = {
    "garbage": ("jpeg", lambda: b"definitely not a jpeg" * 20, False),
    "truncated_jpeg": ("jpeg", lambda: _jpeg()[:200], False),
    "empty": ("jpeg", lambda: b"", False),
    "unsupported_format": ("h264", lambda: _jpeg(), False),
    "png_labelled_jpeg": ("jpeg", lambda: _png(np.zeros((96, 160, 3), np.uint8)), True),
    "unnamed_format": ("", lambda: _jpeg(), True),
    "grey_png": ("png", lambda: _png(np.zeros((96, 160), np.uint8)), True),
    "png_16bit_alpha": ("png", lambda: _png(np.zeros((96, 160, 4), np.uint16)), True),
    "png_bomb_12000px": ("png", lambda: _png_bomb(12_000, 12_000), False),
}


@pytest.mark.parametrize("name", list(PAYLOAD_CASES))
def test_payload_compressed_images_in_replay(tmp_path, name):
    """Each damaged payload costs its frame only: written unjudged, counted as bad."""
    from signal_light_node.io.bagio import make

    fmt, payload, decoded = PAYLOAD_CASES[name]
    messages = []
    for i in range(3):
        img, det = _frame(i)
        if i == 1:
            img = (*img[:3], make("sensor_msgs/msg/CompressedImage", header=img[3].header,
                                  format=fmt, data=np.frombuffer(payload(), np.uint8)))
        messages += [img, det]
    start = time.perf_counter()
    summary, outputs = replay(write_bag(tmp_path / "bag", messages), tmp_path)
    assert time.perf_counter() - start < 10.0
    assert summary.outputs == 3 and summary.bad_images == (0 if decoded else 1)
    for stamp, msg in outputs.items():
        check_sane(msg, ["car0", "car1"])
        judged = decoded or stamp != T0 + 100 * MS
        assert all((v.view_probability > 0) == judged for v in msg.vehicles), name


def test_bag_info_and_play_skip_what_cannot_be_read(tmp_path, capsys):
    """``info`` and ``play`` read the damaged bag of defect 3 too, skipping one message."""
    from signal_light_node.io.bagio import open_bag
    from signal_light_node.cli import main
    from signal_light_node.ros.bag_player import play_items

    messages = []
    for i in range(3):
        img, det = _frame(i, raw=True)
        messages += [(*img[:3], _serialized(img)[:300]) if i == 0 else img, det]
    bag = write_bag(tmp_path / "bag", messages)
    assert main(["info", str(bag)]) == 0
    assert f"skipped:    1 undecodable on {RAW_T}" in capsys.readouterr().out
    with open_bag(bag) as reader:
        items = list(play_items(reader, {RAW_T: "sensor_msgs/msg/Image", DET_T: DET_TYPE}))
        assert len(items) == 5 and reader.skipped == {RAW_T: 1}


def test_live_invalid_utf8_track_id_keeps_the_node_going(live):
    """The detections of defect 3, live: the array is taken (or counted), the node goes on."""
    from rclpy.serialization import serialize_message

    stamp = live.next_stamp()
    raw = serialize_message(live.detections(stamp, [_box("XXXX", 10, 10, 60, 50)]))
    live.client.image_pub.publish(live.image(stamp, _raw()))
    live.client.det_pub.publish(raw.replace(b"XXXX", b"\xff\xfe\xfd\xfc"))
    if live.client.spin_until(lambda: stamp in live.client.outputs, 5.0):
        (vehicle,) = live.client.outputs[stamp][-1].vehicles
        assert vehicle.track_id  # decoded somehow (rclpy replaces what is not UTF-8)
    check_sane(live.send(_raw(), [_box(*TWO[0])]), ["a"])
    assert live.node.proc.poll() is None
