"""Helpers of the live-node tests: a model to load, a bag to feed, the node as a subprocess,
and an in-process rclpy client that feeds frames and collects the node's outputs.

The client uses a private rclpy context without signal handlers, on the same
``ROS_DOMAIN_ID`` as the subprocesses it talks to.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

REPO = Path(__file__).resolve().parents[1]
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
RAW_TYPE = "sensor_msgs/msg/Image"
DETECTIONS_TYPE = "vision_msgs/msg/Detection2DArray"
OUTPUT_TOPIC = "/signal_light_detector/output/vehicle_lights"
DEBUG_TOPIC = "/signal_light_detector/output/debug/image"
MARKERS_TOPIC = "/signal_light_detector/output/markers"


def tiny_checkpoint(path: Path) -> Path:
    """A small, untrained checkpoint written with the model factory (loads in well under 1 s)."""
    from signal_light_node.model.checkpoint import save_checkpoint
    from signal_light_node.model.config import ModelConfig
    from signal_light_node.model.registry import build_model

    config = ModelConfig(input_size=32, attention_channels=(4, 4, 4), backbone_channels=(8, 8),
                         lstm_hidden=(8, 8), head_channels=4, fc_hidden=16)
    return save_checkpoint(path, build_model(config), config)


def model_args(tmp_path: Path) -> Tuple[List[str], bool]:
    """``(--ros-args parameters, uses the shipped weights)``: the shipped weights when they
    exist, else a tiny checkpoint in ``tmp_path``."""
    from signal_light_node.model.checkpoint import DEFAULT_WEIGHTS

    if Path(DEFAULT_WEIGHTS).is_file():
        return [], True
    return ["-p", f"model_path:={tiny_checkpoint(tmp_path / 'tiny.pt')}"], False


def committed_bag(image_type: str) -> Optional[Path]:
    """A committed bag under ``bags/`` with an image topic of ``image_type``, if any."""
    from signal_light_node.io.bagio import open_bag

    for path in sorted((REPO / "bags").iterdir()) if (REPO / "bags").is_dir() else []:
        if not (path.is_dir() and (path / "metadata.yaml").exists()) and path.suffix != ".mcap":
            continue
        with open_bag(path) as bag:
            types = {info.msgtype for info in bag.topics().values()}
        if image_type in types and DETECTIONS_TYPE in types:
            return path
    return None


def scene_bag(tmp_path: Path, raw: bool, n_frames: int = 20) -> Path:
    """The committed bag for this image type, else a small synthetic one in ``tmp_path``."""
    found = committed_bag(RAW_TYPE if raw else COMPRESSED_TYPE)
    if found is not None:
        return found
    from signal_light_node.synth.bag import write_scene_bag

    path = tmp_path / ("scene_raw" if raw else "scene")
    write_scene_bag(path, seed=11, n_frames=n_frames, width=480, height=270, fps=10.0, raw=raw,
                    n_vehicles=4, lighting="day", night_fraction=0.0)
    return path


@dataclass
class Frame:
    """One camera frame of a bag, ready to publish."""

    stamp_ns: int
    frame_id: str
    image: bytes
    detections: bytes
    track_ids: List[str]
    size: Tuple[int, int] = (0, 0)
    truth: Optional[object] = None


def load_frames(bag_path: Path, max_frames: int) -> Tuple[str, List[Frame]]:
    """``(image type, frames)``: the first ``max_frames`` frames with image and detections."""
    from signal_light_node.io.bagio import open_bag, typestore
    from signal_light_node.io.conversions import detections_to_boxes, stamp_to_ns
    from signal_light_node.io.image_codec import msg_to_bgr
    from signal_light_node.ros.bag_player import choose_topics

    store = typestore()
    by_stamp: Dict[int, Dict[str, object]] = defaultdict(dict)
    with open_bag(bag_path) as bag:
        topics = choose_topics(bag.topics())
        image_type = next(t for t in topics.values() if t != DETECTIONS_TYPE)
        gt = "/ground_truth/vehicle_lights"
        wanted = list(topics) + ([gt] if gt in bag.topics() else [])
        for m in bag.messages(wanted):
            entry = by_stamp[stamp_to_ns(m.msg.header.stamp)]
            if m.topic == gt:
                entry["truth"] = m.msg
            elif m.msgtype == DETECTIONS_TYPE:
                entry["detections"] = bytes(store.serialize_cdr(m.msg, m.msgtype))
                entry["ids"] = [b.track_id for b in detections_to_boxes(m.msg)]
            else:
                entry["image"] = bytes(store.serialize_cdr(m.msg, m.msgtype))
                entry["frame_id"] = m.msg.header.frame_id
                entry["size"] = msg_to_bgr(m.msg).shape[:2]
            complete = [s for s, e in by_stamp.items() if "image" in e and "detections" in e]
            if len(complete) >= max_frames and (gt not in wanted or all(
                    "truth" in by_stamp[s] for s in complete)):
                break
    frames = [Frame(s, e["frame_id"], e["image"], e["detections"], e["ids"], e["size"],
                    e.get("truth"))
              for s, e in sorted(by_stamp.items()) if "image" in e and "detections" in e]
    return image_type, frames[:max_frames]


class DetectorProcess:
    """``detector`` in its own process; output goes to a log file.

    Args:
        args: Arguments after ``--ros-args``.
        env: Environment (the test's ROS domain).
        log: Log file.
        executable: ``detector`` or ``detector_lifecycle``.
    """

    def __init__(self, args: Sequence[str], env: Dict[str, str], log: Path,
                 executable: str = "detector") -> None:
        self.log = log
        self._file = open(log, "w")
        # faulthandler: a node that hangs at stop writes every thread's stack on SIGABRT.
        self.proc = subprocess.Popen([executable, "--ros-args", *args],
                                     env={**env, "PYTHONFAULTHANDLER": "1"}, cwd=REPO,
                                     stdout=self._file, stderr=subprocess.STDOUT)

    def text(self) -> str:
        """Everything the node logged so far (it writes to the file directly)."""
        return self.log.read_text()

    def wait_ready(self, timeout: float = 60.0, line: str = "ready:") -> None:
        """Wait for the node's ``ready`` line (or ``line``); fail with its log if it exits
        or hangs."""
        deadline = time.monotonic() + timeout
        while line not in self.text():
            if self.proc.poll() is not None:
                raise AssertionError(f"detector exited with {self.proc.returncode}:\n{self.text()}")
            if time.monotonic() > deadline:
                raise AssertionError(f"detector not ready after {timeout} s:\n{self.text()}")
            time.sleep(0.05)

    def stop(self, timeout: float = 20.0) -> int:
        """SIGINT, then wait; if it does not end, SIGABRT (its log then holds where every
        thread hung), then SIGKILL. Returns the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.send_signal(signal.SIGABRT)
                try:
                    self.proc.wait(10)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait(10)
        if not self._file.closed:
            self._file.close()
        return self.proc.returncode


def run_until_exit(args: Sequence[str], env: Dict[str, str], tmp_path: Path,
                   timeout_s: float = 60.0) -> Tuple[Optional[int], List[str]]:
    """Start the detector with ``args``, poll until it exits (or time out) and return
    its exit code and non-empty log lines."""
    node = DetectorProcess(args, env, tmp_path / "detector.log")
    deadline = time.monotonic() + timeout_s
    while node.proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    code = node.stop()
    return code, [line for line in node.text().splitlines() if line.strip()]


class _GraphClient:
    """A test's own rclpy context, node and executor on the node's domain (``domain_id``);
    the clients below build on it and are used as context managers."""

    domain_id: int

    def _start_client(self, name: str) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        self._rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=self.domain_id,
                   signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
        self.node = rclpy.create_node(f"{name}_{os.getpid()}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def __exit__(self, *exc: object) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.context)

    def spin_until(self, condition, timeout: float) -> bool:
        """Process callbacks until ``condition()`` holds or the timeout passes."""
        deadline = time.monotonic() + timeout
        while not condition():
            if time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=0.05)
        return True


@dataclass
class LiveClient(_GraphClient):
    """Publishes frames to the node and collects what it publishes.

    Use as a context manager; ``domain_id`` must be the node's.
    """

    domain_id: int
    image_type: str
    outputs: Dict[int, List[object]] = field(default_factory=lambda: defaultdict(list))
    diagnostics: List[object] = field(default_factory=list)
    debug_images: List[object] = field(default_factory=list)
    markers: Dict[int, List[object]] = field(default_factory=lambda: defaultdict(list))

    def __enter__(self) -> "LiveClient":
        from signal_light_node.io.conversions import stamp_to_ns
        from signal_light_node.ros.ros_io import message_class, qos

        self._start_client("live_test_client")
        image_topic = ("/signal_light_detector/input/image/compressed"
                       if self.image_type == COMPRESSED_TYPE else
                       "/signal_light_detector/input/image")
        self.image_pub = self.node.create_publisher(message_class(self.image_type), image_topic,
                                                    qos("reliable", 50))
        self.det_pub = self.node.create_publisher(
            message_class(DETECTIONS_TYPE), "/signal_light_detector/input/detections",
            qos("reliable", 50))

        def on_output(msg: object) -> None:
            self.outputs[stamp_to_ns(msg.header.stamp)].append(msg)

        self.node.create_subscription(
            message_class("signal_light_msgs/msg/VehicleLightStateArray"), OUTPUT_TOPIC,
            on_output, qos("reliable", 100))
        self.node.create_subscription(message_class(RAW_TYPE), DEBUG_TOPIC,
                                      self.debug_images.append, qos("reliable", 100))

        def on_markers(msg: object) -> None:  # every array begins with a DELETEALL marker
            self.markers[stamp_to_ns(msg.markers[0].header.stamp)].append(msg)

        self.node.create_subscription(message_class("visualization_msgs/msg/MarkerArray"),
                                      MARKERS_TOPIC, on_markers, qos("reliable", 100))
        self.node.create_subscription(message_class("diagnostic_msgs/msg/DiagnosticArray"),
                                      "/diagnostics", self.diagnostics.append,
                                      qos("reliable", 100))
        return self

    def wait_connected(self, timeout: float = 30.0) -> None:
        """Wait until the node subscribes our inputs and we subscribe its output."""
        ok = self.spin_until(lambda: self.image_pub.get_subscription_count() > 0
                             and self.det_pub.get_subscription_count() > 0
                             and self.node.count_publishers(OUTPUT_TOPIC) > 0, timeout)
        assert ok, "the detector and the test client did not discover each other"

    def warm_up(self, before_stamp_ns: int, frame_id: str, timeout: float = 30.0) -> int:
        """Publish small empty frames, stamped 100 s before ``before_stamp_ns``, until one
        comes back: then the node's output publisher surely knows our subscription.

        Returns:
            How many warm-up frames were published (each is an input image for the node).
        """
        import numpy as np

        from signal_light_node.io.conversions import make_header
        from signal_light_node.ros.messages import rclpy_make
        from signal_light_node.io.image_codec import bgr_to_compressed_fields, bgr_to_image_fields

        image = np.full((48, 64, 3), 60, np.uint8)
        fields = (bgr_to_compressed_fields(image) if self.image_type == COMPRESSED_TYPE
                  else bgr_to_image_fields(image))
        deadline = time.monotonic() + timeout
        sent = 0
        while True:
            stamp = before_stamp_ns - 100_000_000_000 + sent * 100_000_000
            header = make_header(stamp, frame_id, rclpy_make)
            self.image_pub.publish(rclpy_make(self.image_type, header=header, **fields))
            self.det_pub.publish(rclpy_make(DETECTIONS_TYPE, header=header))
            sent += 1
            if self.spin_until(lambda: stamp in self.outputs, 1.0):
                return sent
            assert time.monotonic() < deadline, "no output for any warm-up frame"

    def get_parameters(self, names: Sequence[str], timeout: float = 20.0) -> Dict[str, object]:
        """The node's current values of ``names`` through its parameter service."""
        from rcl_interfaces.srv import GetParameters
        from rclpy.parameter import parameter_value_to_python

        client = self.node.create_client(GetParameters, "/signal_light_detector/get_parameters")
        try:
            assert self.spin_until(client.service_is_ready, timeout), "no parameter service"
            future = client.call_async(GetParameters.Request(names=list(names)))
            assert self.spin_until(future.done, timeout), "parameter service did not answer"
            return {n: parameter_value_to_python(v)
                    for n, v in zip(names, future.result().values)}
        finally:
            self.node.destroy_client(client)

    def set_parameters(self, values: Dict[str, object], timeout: float = 20.0) -> List[object]:
        """Set parameters through the node's service; returns the SetParametersResults."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        client = self.node.create_client(SetParameters, "/signal_light_detector/set_parameters")
        try:
            assert self.spin_until(client.service_is_ready, timeout), "no parameter service"
            request = SetParameters.Request(
                parameters=[Parameter(n, value=v).to_parameter_msg() for n, v in values.items()])
            future = client.call_async(request)
            assert self.spin_until(future.done, timeout), "parameter service did not answer"
            return list(future.result().results)
        finally:
            self.node.destroy_client(client)

    def feed(self, frames: Sequence[Frame], timeout_per_frame: float = 20.0) -> None:
        """Publish frame by frame, each time waiting for its output (no overload drops)."""
        for frame in frames:
            self.image_pub.publish(frame.image)
            self.det_pub.publish(frame.detections)
            assert self.spin_until(lambda: frame.stamp_ns in self.outputs, timeout_per_frame), \
                f"no output for the frame stamped {frame.stamp_ns}"


def camera_frame(stamp_ns: int, frame_id: str, image, boxes, image_type: str = RAW_TYPE):
    """``(image message, detections message)`` of one frame, as rclpy messages."""
    from signal_light_node.io.conversions import boxes_to_detections, make_header
    from signal_light_node.io.image_codec import bgr_to_compressed_fields, bgr_to_image_fields
    from signal_light_node.ros.messages import rclpy_make

    header = make_header(stamp_ns, frame_id, rclpy_make)
    fields = (bgr_to_compressed_fields(image) if image_type == COMPRESSED_TYPE
              else bgr_to_image_fields(image))
    return (rclpy_make(image_type, header=header, **fields),
            boxes_to_detections(header, list(boxes), rclpy_make))


@dataclass
class CamerasClient(_GraphClient):
    """Publishes frames to a several-camera node and collects each camera's outputs.

    Use as a context manager; ``domain_id`` must be the node's. ``outputs[camera][stamp]``
    lists the ``VehicleLightStateArray`` s received on ``~/<camera>/output/vehicle_lights``.
    """

    domain_id: int
    cameras: Sequence[str]
    image_type: str = RAW_TYPE
    outputs: Dict[str, Dict[int, List[object]]] = field(default_factory=dict)
    debug_images: Dict[str, List[object]] = field(default_factory=dict)
    diagnostics: List[object] = field(default_factory=list)

    def __enter__(self) -> "CamerasClient":
        from signal_light_node.io.conversions import stamp_to_ns
        from signal_light_node.ros.ros_io import message_class, qos

        self._start_client("cameras_test_client")
        image = "image/compressed" if self.image_type == COMPRESSED_TYPE else "image"
        self.publishers: Dict[str, Tuple[object, object]] = {}
        for camera in self.cameras:
            base = f"/signal_light_detector/{camera}"
            self.publishers[camera] = (
                self.node.create_publisher(message_class(self.image_type),
                                           f"{base}/input/{image}", qos("reliable", 50)),
                self.node.create_publisher(message_class(DETECTIONS_TYPE),
                                           f"{base}/input/detections", qos("reliable", 50)))
            self.outputs[camera] = defaultdict(list)

            def on_output(msg: object, camera: str = camera) -> None:
                self.outputs[camera][stamp_to_ns(msg.header.stamp)].append(msg)

            self.node.create_subscription(
                message_class("signal_light_msgs/msg/VehicleLightStateArray"),
                self.output_topic(camera), on_output, qos("reliable", 100))
            self.debug_images[camera] = []
            self.node.create_subscription(
                message_class(RAW_TYPE), f"{base}/output/debug/image",
                self.debug_images[camera].append, qos("reliable", 100))
        self.node.create_subscription(message_class("diagnostic_msgs/msg/DiagnosticArray"),
                                      "/diagnostics", self.diagnostics.append,
                                      qos("reliable", 100))
        return self

    @staticmethod
    def output_topic(camera: str) -> str:
        """Where the node publishes the camera's results."""
        return f"/signal_light_detector/{camera}/output/vehicle_lights"

    def wait_connected(self, timeout: float = 30.0) -> None:
        """Wait until the node subscribes every input and publishes every output."""
        ok = self.spin_until(lambda: all(
            image.get_subscription_count() > 0 and dets.get_subscription_count() > 0
            and self.node.count_publishers(self.output_topic(camera)) > 0
            for camera, (image, dets) in self.publishers.items()), timeout)
        assert ok, "the detector and the test client did not discover each other"

    def publish(self, camera: str, stamp_ns: int, frame_id: str, image, boxes) -> None:
        """Publish one frame (image, then detections) of ``camera``."""
        image_msg, dets_msg = camera_frame(stamp_ns, frame_id, image, boxes, self.image_type)
        image_pub, dets_pub = self.publishers[camera]
        image_pub.publish(image_msg)
        dets_pub.publish(dets_msg)

    def warm_up(self, before_stamp_ns: int, timeout: float = 30.0,
                debug: bool = False) -> Dict[str, int]:
        """Small empty frames on every camera, stamped 100 s before ``before_stamp_ns``,
        until each camera's output (and with ``debug`` its debug image) comes back;
        returns how many each camera sent."""
        import numpy as np

        from signal_light_node.io.conversions import stamp_to_ns

        image = np.full((48, 64, 3), 60, np.uint8)
        sent = {camera: 0 for camera in self.cameras}
        deadline = time.monotonic() + timeout
        for camera in self.cameras:
            while True:
                stamp = before_stamp_ns - 100_000_000_000 + sent[camera] * 100_000_000
                self.publish(camera, stamp, f"{camera}_warm_up", image, [])
                sent[camera] += 1
                if self.spin_until(lambda: stamp in self.outputs[camera] and (not debug or any(
                        stamp_to_ns(i.header.stamp) == stamp
                        for i in self.debug_images[camera])), 1.0):
                    break
                assert time.monotonic() < deadline, f"no output for camera {camera}"
        return sent

    def diagnostics_values(self) -> Dict[str, str]:
        """The latest status's key/values."""
        status = self.diagnostics[-1].status[0]
        return {kv.key: kv.value for kv in status.values}
