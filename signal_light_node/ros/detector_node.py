"""The ``signal_light_detector`` rclpy node (executable ``detector``).

A thin adapter over :class:`~signal_light_node.runtime.engine.LightStateEngine`:

* the subscription callbacks only read the header stamp and hand the message to a
  :class:`~signal_light_node.runtime.pairing.StampPairer`;
* a complete (image, detections) pair goes into a bounded drop-oldest queue;
* one worker thread decodes the image, runs the engine and publishes the result through
  the output adapters (:mod:`signal_light_node.outputs`): ``~/output/vehicle_lights``,
  with ``publish_markers`` and while watched ``~/output/markers``, and with
  ``publish_debug_image`` and while watched ``~/output/debug/image`` (the frame drawn by
  :class:`~signal_light_node.outputs.debug_image.DebugImageOutput`);
* a timer publishes the node's figures on ``/diagnostics``.

With ``cameras: [front, rear]`` every camera has all of the above under its name
(``~/front/input/image``, ``~/front/output/vehicle_lights``...) and its own pairing; the
paired frames wait per camera (:class:`~signal_light_node.runtime.camera_queue.CameraQueue`)
and the worker judges one frame of every camera that has one in ONE engine step
(``engine.process_many``), publishing each camera's results on its own topics with its
image's header. Per-camera figures go to ``/diagnostics`` as ``<camera>.<figure>``. The
single-camera node is the one camera ``""`` on the unprefixed topics: its frame is a tick
of one, through the same worker code.

Every conversion is the core's (``image_codec``, ``conversions``); nothing here knows a
message layout beyond the topic types.
"""

from __future__ import annotations

import logging
import re
import sys
import time
from dataclasses import dataclass
from functools import partial
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import rclpy
from rcl_interfaces.msg import SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy_impl
from rclpy.node import Node

from signal_light_node.io.conversions import detections_to_boxes, stamp_to_ns
from signal_light_node.outputs import output_adapters
from signal_light_node.ros.messages import rclpy_make
from signal_light_node.errors import (ConfigError, ImageConversionError, ImageTooLargeError,
                                      SignalLightError)
from signal_light_node.ros.cameras import CameraIO, GapsSum, PairerGroup, camera_ios
from signal_light_node.runtime.camera_queue import CameraQueue
from signal_light_node.ros.gaps import SequenceGaps
from signal_light_node.runtime.pairing import StampPairer
from signal_light_node.ros.params import (NODE_NAME, DetectorParams, foreign_params_file,
                                           params_file_paths, read_parameters, updated)
from signal_light_node.ros.ros_io import message_class, qos
from signal_light_node.runtime.stats import (ERROR, OK, WARN, LatencyWindow, Snapshot,
                                             StageWindows, health)
from signal_light_node.runtime.worker import DropOldestQueue, Worker
from signal_light_node.io.topics import (COMPRESSED_TYPE, DETECTIONS_TYPE, DIAGNOSTICS_TOPIC,
                                      DIAGNOSTICS_TYPE, IMAGE_TYPE)

_NS = 1_000_000_000

#: Topic names relative to the node (remap them with ``-r ~/input/image:=/camera/...``);
#: with ``cameras`` each camera's sit under its name (``~/front/input/image``).
IMAGE_TOPIC = "~/input/image"
COMPRESSED_TOPIC = "~/input/image/compressed"
DETECTIONS_TOPIC = "~/input/detections"
# The output topics are the output adapters' (``OutputAdapter.node_topic``).

_LEVEL_BYTES = {OK: b"\x00", WARN: b"\x01", ERROR: b"\x02"}

#: Stages of the worker's work item (one frame; with ``cameras`` one tick) timed for
#: ``/diagnostics`` (``stage_<name>_mean_ms`` / ``_p95_ms``): the wait in the work queue
#: (the tick's longest), decoding, the engine's own stages (``engine.ENGINE_STAGES``),
#: building the result arrays and publishing them.
NODE_STAGES = ("queue", "decode", "crops", "state_gather", "step", "intent_filter",
               "state_store", "results", "outputs", "publish")


class SignalLightDetector(Node):
    """The detector node. Construct, then :meth:`setup`; :meth:`stop` before destroying.

    Construction declares and validates the parameters; ``setup`` loads the model and
    creates the topics, so a failure of either leaves a node that can be destroyed cleanly.

    Raises:
        ConfigError: From the constructor, when a parameter is unusable.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.params: DetectorParams = read_parameters(self)
        self.engine: Any = None
        self.model_path = ""
        self._worker: Optional[Worker] = None
        self._counts: Dict[str, int] = {"outputs": 0, "bad_images": 0, "oversized_images": 0,
                                        "debug_images": 0}
        self._gaps = {"image": SequenceGaps(), "detections": SequenceGaps()}
        self._latency = LatencyWindow()
        self._processing = LatencyWindow()
        self._engine_time = LatencyWindow()
        self._stages = StageWindows(NODE_STAGES)
        self._last_snapshot: Optional[Snapshot] = None
        self._last_engine: Dict[str, int] = {}
        self._param_callbacks = False
        self._dropped_before = 0  # work-queue drops of queues closed by deactivate
        # One CameraIO per camera; the single-camera node's one shares the node's gaps.
        self._cameras: List[CameraIO] = camera_ios(self.params.cameras)
        if self._several:
            self._gaps = {kind: GapsSum([c.gaps[kind] for c in self._cameras])  # type: ignore
                          for kind in ("image", "detections")}
        else:
            self._cameras[0].gaps = self._gaps
        self._publishers_made: List[Any] = []

    @property
    def _several(self) -> bool:
        """Whether the node runs named cameras (``cameras`` set)."""
        return bool(self.params.cameras)

    # ------------------------------------------------------------------ start-up
    # The lifecycle variant (ros/lifecycle_node.py) calls the same four steps from its
    # transitions; the plain node runs configure + activate at start.
    def setup(self) -> None:
        """Load the model and start the topics, the worker and the diagnostics timer.

        Raises:
            CheckpointError: The model file is missing or incompatible.
            ConfigError: The model does not fit the parameters (device, crop size).
        """
        self.configure()
        self.activate()

    def configure(self) -> None:
        """Load and check the model and build the engine and the pairing (no topics yet).

        Raises:
            CheckpointError: The model file is missing or incompatible.
            ConfigError: The model does not fit the parameters (device, crop size).
        """
        from signal_light_node.runtime.engine import engine_from_checkpoint

        p = self.params
        self.engine = engine_from_checkpoint(
            p.model_path or None, device=p.device, backend=p.backend, threads=p.num_threads,
            precision=p.precision,
            thresholds=p.thresholds,
            track_timeout_s=p.track_timeout_s, max_tracks=p.max_tracks, max_gap_s=p.max_gap_s,
            intent_filter=p.intent_filter_config,
            max_boxes=p.max_boxes_per_frame)
        self.model_path = self.engine.backend.source
        for camera in self._cameras:
            camera.pairer = StampPairer(int(p.sync_slop_s * _NS), int(p.sync_timeout_s * _NS),
                                        p.image_queue_size, p.detection_queue_size)
        self._pairer = PairerGroup([c.pairer for c in self._cameras]) if self._several \
            else self._cameras[0].pairer
        self._queue = self._new_queue()
        self._decode = _decoder(p.image_transport)
        if not self._param_callbacks:
            self.add_on_set_parameters_callback(self._check_new_parameters)
            self.add_post_set_parameters_callback(self._apply_new_parameters)
            self._param_callbacks = True
        self.get_logger().info(
            f"model {self.model_path} ({self._backend_text()}) on {p.device}; crop margin "
            f"{self.engine.crop.margin:g} (the model checkpoint's)")

    def activate(self) -> None:
        """Create the publishers, the worker, the subscriptions and the diagnostics timer."""
        p = self.params
        if self._queue.closed:  # a worker stopped by deactivate closed it; keep its count
            self._dropped_before += self._queue.dropped
            for camera in self._cameras:
                camera.dropped_before += self._camera_queue_drops(camera)
            self._queue = self._new_queue()
        for camera in self._cameras:
            self._create_camera_topics(camera)
        self._diag = self._create_publisher(message_class(DIAGNOSTICS_TYPE), DIAGNOSTICS_TOPIC,
                                            10)
        process = self._process_tick if self._several else self._process_pair
        self._worker = Worker(self._queue, process, name="signal_light_inference").start()

        for camera in self._cameras:
            self._subscribe(camera)
        self._last_snapshot = self._snapshot()
        self._timer = self.create_timer(p.diagnostics_period_s, self._publish_diagnostics)
        pairing = 'exact' if p.sync_slop_s == 0 else f'within {p.sync_slop_s} s'
        for camera in self._cameras:
            self.get_logger().info(
                f"{f'camera {camera.name}: ' if camera.name else ''}outputs: "
                f"{', '.join(pub.topic_name for _, pub in camera.outputs)}")
        if not self._several:
            camera = self._cameras[0]
            self.get_logger().info(
                f"ready: {camera.image_topic} ({p.image_transport}, {p.reliability}) + "
                f"{camera.subscriptions[1].topic_name} "
                f"-> {camera.outputs[0][1].topic_name}; model {self.model_path} "
                f"({self._backend_text()}) on {p.device}, pairing {pairing}")
            return
        inputs = "; ".join(f"{c.name}: {c.image_topic} + {c.subscriptions[1].topic_name} -> "
                           f"{c.outputs[0][1].topic_name}" for c in self._cameras)
        self.get_logger().info(
            f"ready: {len(self._cameras)} cameras ({p.image_transport}, {p.reliability}), "
            f"one model step per tick: {inputs}; model {self.model_path} "
            f"({self._backend_text()}) on {p.device}, pairing {pairing}")

    def _backend_text(self) -> str:
        """The backend and weight precision in use, and whether ``auto`` chose them."""
        auto = ", chosen by backend auto" if self.params.backend == "auto" else ""
        return f"{self.engine.backend.name} {self._precision()}{auto}"

    def _precision(self) -> str:
        return str(getattr(self.engine.backend, "precision", "fp32"))

    def _create_publisher(self, msg_type: Any, topic: str, depth: int) -> Any:
        publisher = self.create_publisher(msg_type, topic, depth)
        self._publishers_made.append(publisher)
        return publisher

    def _create_camera_topics(self, camera: CameraIO) -> None:
        """One publisher per output adapter (the result array first; markers and the debug
        image as the parameters ask)."""
        adapters = output_adapters(markers=self.params.publish_markers,
                                   debug_image=self.params.publish_debug_image)
        camera.outputs = [(adapter, self._create_publisher(message_class(adapter.msgtype),
                                                           camera.topic(adapter.node_topic),
                                                           adapter.depth))
                          for adapter in adapters]

    def _subscribe(self, camera: CameraIO) -> None:
        """The camera's image and detections subscriptions (image first)."""
        p = self.params
        if p.image_transport == "compressed":
            image_type, image_topic = COMPRESSED_TYPE, COMPRESSED_TOPIC
        else:
            image_type, image_topic = IMAGE_TYPE, IMAGE_TOPIC
        if self._several:
            on_image = partial(self._on_camera_image, camera)
            on_detections = partial(self._on_camera_detections, camera)
        else:
            on_image, on_detections = self._on_image, self._on_detections
        camera.subscriptions = [
            self.create_subscription(message_class(image_type), camera.topic(image_topic),
                                     on_image, qos(p.reliability, p.image_queue_size)),
            self.create_subscription(message_class(DETECTIONS_TYPE),
                                     camera.topic(DETECTIONS_TOPIC), on_detections,
                                     qos(p.reliability, p.detection_queue_size))]
        camera.image_topic = camera.subscriptions[0].topic_name

    def _new_queue(self) -> Any:
        """The work queue: drop-oldest for one camera, one per camera for several."""
        if self._several:
            return CameraQueue([c.name for c in self._cameras], self.params.work_queue_size)
        return DropOldestQueue(self.params.work_queue_size)

    def _camera_queue_drops(self, camera: CameraIO) -> int:
        """The camera's frames dropped from the current work queue."""
        if isinstance(self._queue, CameraQueue):
            return self._queue.dropped_by_camera.get(camera.name, 0)
        return self._queue.dropped

    def deactivate(self) -> None:
        """Stop taking and publishing frames; the track states and counters are kept.

        Frames still queued are dropped and counted; messages waiting for a partner
        stay in the pairing and expire there as usual.
        """
        self.stop()
        self._worker = None
        for camera in self._cameras:
            for sub in camera.subscriptions:
                self.destroy_subscription(sub)
            camera.subscriptions, camera.outputs = [], []
        if getattr(self, "_timer", None) is not None:
            self.destroy_timer(self._timer)
            self._timer = None
        for pub in self._publishers_made:
            self.destroy_publisher(pub)
        self._publishers_made = []
        self._diag = None

    def cleanup(self) -> None:
        """Free the model and every track state (``configure`` loads them again)."""
        self.engine = None

    def stop(self) -> None:
        """Stop the worker (frames still queued are dropped and counted)."""
        if self._worker is not None:
            self._worker.stop(drain=False, timeout=5.0)

    # ---------------------------------------------------------------- callbacks
    # Both take the message info: its publication sequence numbers reveal what the
    # middleware dropped (a full keep-last reader queue drops the oldest, silently).
    def _on_image(self, msg: Any, info: Any) -> None:
        self._gaps["image"].add(info.get("publication_sequence_number"))
        pair = self._pairer.add_image(stamp_to_ns(msg.header.stamp), msg, time.monotonic_ns())
        if pair is not None:
            self._queue.put(pair)

    def _on_detections(self, msg: Any, info: Any) -> None:
        self._gaps["detections"].add(info.get("publication_sequence_number"))
        pair = self._pairer.add_detections(stamp_to_ns(msg.header.stamp), msg,
                                           time.monotonic_ns())
        if pair is not None:
            self._queue.put(pair)

    def _on_camera_image(self, camera: CameraIO, msg: Any, info: Any) -> None:
        camera.gaps["image"].add(info.get("publication_sequence_number"))
        pair = camera.pairer.add_image(stamp_to_ns(msg.header.stamp), msg, time.monotonic_ns())
        if pair is not None:
            self._queue.put((camera.name, pair))

    def _on_camera_detections(self, camera: CameraIO, msg: Any, info: Any) -> None:
        camera.gaps["detections"].add(info.get("publication_sequence_number"))
        pair = camera.pairer.add_detections(stamp_to_ns(msg.header.stamp), msg,
                                            time.monotonic_ns())
        if pair is not None:
            self._queue.put((camera.name, pair))

    # ------------------------------------------------------------------- worker
    def _process_tick(self, tick: Sequence[Tuple[str, Any]]) -> None:
        """One work item: at most one paired frame per camera (the single camera's one
        frame), decoded, judged in ONE engine step (``process_many``), each camera's
        results published on its own topics with its image's header."""
        taken = time.monotonic_ns()
        cameras = {c.name: c for c in self._cameras}
        frames = [self._decoded(cameras[name], pair) for name, pair in tick]
        usable = [f for f in frames if f.image is not None]
        judged = iter(self.engine.process_many(
            [(f.camera.name, f.image, f.pair.stamp_ns, f.boxes) for f in usable]) if usable
            else [])
        outputs_s = publish_s = 0.0
        for f in frames:
            if f.image is not None:
                f.result = next(judged)
            times = self._publish_frame(f)
            if times is None:
                return  # shutting down
            if f.image is not None:
                outputs_s, publish_s = outputs_s + times[0], publish_s + times[1]
        if not usable:
            return  # no engine step
        step = usable[0].result
        self._stages.add({"queue": max(taken - f.pair_ns for f in usable) / _NS,
                          "decode": sum(f.decode_s for f in usable), **step.stages_s,
                          "outputs": outputs_s, "publish": publish_s})
        self._engine_time.add(step.latency_s)  # the one step of this tick

    def _process_pair(self, pair: Any) -> None:
        """The single camera's work item: a tick of one frame of the camera ``""``."""
        self._process_tick([(self._cameras[0].name, pair)])

    def _decoded(self, camera: CameraIO, pair: Any) -> "_Frame":
        """A paired frame decoded; an image that cannot be used gives every box unjudged
        (counted, warned about)."""
        boxes = detections_to_boxes(pair.detections)
        start = time.perf_counter()
        try:
            image = self._decode(pair.image, camera.image_topic, pair.stamp_ns,
                                 self.params.max_image_pixels)
        except ImageConversionError as exc:
            kind = "oversized_images" if isinstance(exc, ImageTooLargeError) else "bad_images"
            self._counts[kind] += 1
            camera.counts[kind] += 1
            where = f"camera {camera.name}: " if camera.name else ""
            self.get_logger().warning(f"{where}frame published unjudged: {exc}",
                                      throttle_duration_sec=5.0)
            msg = pair.image
            return _Frame(camera, pair, boxes, None, self.engine.unjudged_frame(
                pair.stamp_ns, boxes, int(getattr(msg, "width", 0)),
                int(getattr(msg, "height", 0)), str(exc), camera=camera.name))
        return _Frame(camera, pair, boxes, image, decode_s=time.perf_counter() - start)

    def _publish_frame(self, f: "_Frame") -> Optional[Tuple[float, float]]:
        """Publish one camera's frame on its own outputs, header = its image's.

        Returns:
            The seconds spent building and publishing the result array, or None when the
            node is shutting down.
        """
        (result_out, out), *others = f.camera.outputs
        t_build = time.perf_counter()
        message = result_out.build(f.pair.image.header, f.result.results, rclpy_make)
        t_publish = time.perf_counter()
        if not self._publish(out, message):
            return None
        published = time.perf_counter()
        done = time.monotonic_ns()
        self._counts["outputs"] += 1
        f.camera.counts["outputs"] += 1
        self._latency.add((done - f.pair.image_received_ns) / _NS)
        self._processing.add((done - f.pair_ns) / _NS)
        self._publish_others(others, f.pair, f.boxes, f.image, f.result.results)
        if f.image is not None and f.result.warnings:
            where = f"camera {f.camera.name}, " if f.camera.name else ""
            self.get_logger().warning(
                f"{where}stamp {f.pair.stamp_ns}: {'; '.join(f.result.warnings)}",
                throttle_duration_sec=5.0)
        return t_publish - t_build, published - t_publish

    def _publish_others(self, others: Sequence[Tuple[Any, Any]], pair: Any, boxes: List[Any],
                        image: Any, results: List[Any]) -> None:
        """A frame's outputs after the result array: each while subscribed where it asks
        so; one that draws on the frame (the debug image) only when the image was decoded,
        with the attention masks of the boxes."""
        for adapter, publisher in others:
            if adapter.when_subscribed and publisher.get_subscription_count() == 0:
                continue
            if not adapter.draws_image:
                self._publish(publisher, adapter.build(pair.image.header, results, rclpy_make))
            elif image is not None:
                msg = adapter.build(pair.image.header, results, rclpy_make, image=image,
                                    attention=self.engine.attention_masks(image, boxes))
                if self._publish(publisher, msg):
                    self._counts["debug_images"] += 1

    def _camera_values(self) -> List[Tuple[str, str]]:
        """Per-camera ``/diagnostics`` key/values; none for the single-camera node."""
        if not self._several:
            return []
        engine = self.engine.camera_counters
        totals = self.engine.counters
        values: List[Tuple[str, str]] = [("cameras", ", ".join(c.name for c in self._cameras)),
                                         ("model_steps", str(totals.get("model_steps", 0))),
                                         ("frames_judged", str(totals.get("frames", 0)))]
        for camera in self._cameras:
            values += camera.values(self._camera_queue_drops(camera),
                                    engine.get(camera.name, {}))
        return values

    def _publish(self, publisher: Any, msg: Any) -> bool:
        """Publish from the worker; False when the node is shutting down (then the context
        can go away between any two calls, so a publish may fail)."""
        if not rclpy.ok(context=self.context):
            return False
        try:
            publisher.publish(msg)
        except _rclpy_impl.RCLError:
            if rclpy.ok(context=self.context):
                raise
            return False
        return True

    # -------------------------------------------------------------- diagnostics
    def counters(self) -> Dict[str, int]:
        """Totals since start: inputs, pairs, outputs, every drop by reason."""
        out = dict(self._pairer.counters)
        out.update(self._counts)
        out["dropped_work_queue"] = self._dropped_before + self._queue.dropped
        for kind, gaps in self._gaps.items():
            out[f"dropped_{kind}_middleware"] = gaps.lost
        out["processing_errors"] = self._worker.errors if self._worker else 0
        out["worker_alive"] = int(bool(self._worker and self._worker.alive))
        return out

    def _snapshot(self) -> Snapshot:
        return Snapshot(time.monotonic(), self.counters())

    def _publish_diagnostics(self) -> None:
        self._pairer.expire(time.monotonic_ns())
        now = self._snapshot()
        engine = self.engine.counters
        extra = {
            "active_tracks": engine.get("active_tracks", 0),
            "unjudged_boxes": engine.get("unjudged", 0),
            "duplicate_track_ids": engine.get("duplicates", 0),
            "track_resets": engine.get("resets", 0),
            "track_overflow": engine.get("overflow", 0),
            "boxes_over_limit": engine.get("over_limit", 0),
            "middleware_drops_counted": _yes_no(self._gaps["image"].supported),
            "work_queue_length": len(self._queue),
            "pending_images": self._pairer.pending[0],
            "pending_detections": self._pairer.pending[1],
            "model_path": self.model_path,
            "device": self.params.device,
            "backend": self.engine.backend.name, "precision": self._precision(),
            # Threads of the last step (onnxruntime picks 1 or all by the load).
            "model_threads": getattr(self.engine.backend, "threads_in_use", ""),
        }
        extra.update(self._stages.values())
        level, message, values = health(self._last_snapshot, now, self._latency.summary(),
                                        self._processing.summary(),
                                        self._engine_time.summary(), extra)
        self._last_snapshot = now
        values += self._camera_values()
        KeyValue = message_class("diagnostic_msgs/msg/KeyValue")
        status = rclpy_make("diagnostic_msgs/msg/DiagnosticStatus", level=_LEVEL_BYTES[level],
                            name=f"{self.get_name()}: vehicle light state",
                            message=message, hardware_id="signal_light_node",
                            values=[KeyValue(key=k, value=v) for k, v in values])
        array = rclpy_make(DIAGNOSTICS_TYPE, status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self._diag.publish(array)

    # --------------------------------------------------------------- parameters
    def _check_new_parameters(self, changes: List[Any]) -> SetParametersResult:
        try:
            updated(self.params, {c.name: c.value for c in changes})
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_new_parameters(self, changes: List[Any]) -> None:
        self.params = updated(self.params, {c.name: c.value for c in changes})
        self._pairer.configure(int(self.params.sync_slop_s * _NS),
                               int(self.params.sync_timeout_s * _NS))
        self.get_logger().info("parameters changed: " + ", ".join(
            f"{c.name}={c.value}" for c in changes))


@dataclass
class _Frame:
    """One camera's paired frame in the worker: decoded (or not), then judged."""

    camera: CameraIO
    pair: Any
    boxes: List[Any]
    image: Any = None
    result: Any = None
    decode_s: float = 0.0

    @property
    def pair_ns(self) -> int:
        """When the pair was complete (the receipt of its later message)."""
        return max(self.pair.image_received_ns, self.pair.detections_received_ns)


def _yes_no(supported: Optional[bool]) -> str:
    return {True: "yes", False: "no (the middleware gives no sequence numbers)"}.get(
        supported, "not yet known")


def _decoder(image_transport: str) -> Any:
    from signal_light_node.io.image_codec import compressed_msg_to_bgr, image_msg_to_bgr

    return compressed_msg_to_bgr if image_transport == "compressed" else image_msg_to_bgr


def _init_ros(args: Optional[List[str]]) -> None:
    """``rclpy.init`` with rcl's own error line silenced, so a bad argument is one line.

    Raises:
        ConfigError: The ROS arguments cannot be parsed (bad rule, missing params file...).
    """
    from rclpy.logging import LoggingSeverity, get_logger_level, set_logger_level

    before = get_logger_level("rcl")
    set_logger_level("rcl", LoggingSeverity.FATAL)
    try:
        rclpy.init(args=args)
    except _rclpy_impl.RCLError as exc:
        # rcl appends ", at <source file>:<line>" for every frame; the user needs none.
        text = re.sub(r", at \S+:\d+", "", str(exc).splitlines()[0])
        raise ConfigError(f"bad ROS arguments: {text}") from None
    finally:
        set_logger_level("rcl", before)


def _warn_foreign_params_files(node: Node, args: Optional[List[str]]) -> None:
    for path in params_file_paths(list(sys.argv if args is None else args)):
        problem = foreign_params_file(path, node.get_fully_qualified_name())
        if problem is not None:
            node.get_logger().warning(problem)


def run_detector(make_node: Callable[[], "SignalLightDetector"],
                 start: Callable[["SignalLightDetector"], None],
                 args: Optional[List[str]] = None) -> int:
    """Init ROS, build the node, ``start`` it and spin until Ctrl-C or a shutdown request.

    The one run loop of ``detector`` and ``detector_lifecycle``: any start-up problem (bad
    ROS arguments, parameters, model, device) is reported in ONE log line and gives exit
    code 1; a params file without a section for this node is warned about.

    Args:
        make_node: Builds the node (after ``rclpy.init``).
        start: What to do before spinning (load and activate, or wait for transitions).
        args: ROS arguments; None reads ``sys.argv``.

    Returns:
        The exit code.
    """
    logging.basicConfig(level=logging.INFO, format="[%(levelname)s] [%(name)s]: %(message)s")
    node: Optional[SignalLightDetector] = None
    code = 0
    try:
        _init_ros(args)
        node = make_node()
        _warn_foreign_params_files(node, args)
        start(node)
        _spin(node)
    except SignalLightError as exc:
        logger = node.get_logger() if node is not None else rclpy.logging.get_logger(NODE_NAME)
        logger.fatal(f"cannot start: {exc}")
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.stop()
            node.destroy_node()
        rclpy.try_shutdown()
    return code


def _spin(node: Node) -> None:
    """``rclpy.spin`` until shutdown; a Ctrl-C that lands between two waits shuts the
    context down under the executor, which then raises rclpy's RCLError ("the given
    context is not valid") instead of ExternalShutdownException: that is a shutdown too."""
    try:
        rclpy.spin(node)
    except Exception:
        if rclpy.ok(context=node.context):
            raise


def main(args: Optional[List[str]] = None) -> int:
    """Run the node (loaded and active at once); returns the exit code."""
    return run_detector(SignalLightDetector, SignalLightDetector.setup, args)


if __name__ == "__main__":
    sys.exit(main())
