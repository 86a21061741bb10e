"""The ``signal_light_detector`` rclpy node (executable ``detector``).

A thin adapter over :class:`~signal_light_node.runtime.engine.LightStateEngine`:

* the subscription callbacks only read the header stamp and hand the message to a
  :class:`~signal_light_node.runtime.pairing.StampPairer`;
* a complete (image, detections) pair goes into a bounded drop-oldest queue;
* one worker thread decodes the image, runs the engine and publishes the result through
  the output adapters (:mod:`signal_light_node.outputs`): ``~/output/vehicle_lights``,
  with ``publish_markers`` and while watched ``~/output/markers``, and when enabled and
  watched ``~/output/debug/image``;
* a timer publishes the node's figures on ``/diagnostics``.

Every conversion is the core's (``image_codec``, ``conversions``); nothing here knows a
message layout beyond the topic types.
"""

from __future__ import annotations

import logging
import re
import sys
import time
from typing import Any, Dict, List, Optional, Tuple

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

#: Topic names relative to the node (remap them with ``-r ~/input/image:=/camera/...``).
IMAGE_TOPIC = "~/input/image"
COMPRESSED_TOPIC = "~/input/image/compressed"
DETECTIONS_TOPIC = "~/input/detections"
OUTPUT_TOPIC = "~/output/vehicle_lights"
DEBUG_TOPIC = "~/output/debug/image"

_LEVEL_BYTES = {OK: b"\x00", WARN: b"\x01", ERROR: b"\x02"}

#: Stages of the worker's frame timed for ``/diagnostics`` (``stage_<name>_mean_ms`` /
#: ``_p95_ms``): the wait in the work queue, decoding, the engine's own stages
#: (``engine.ENGINE_STAGES``), building the output messages and publishing them.
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

    # ------------------------------------------------------------------ start-up
    def setup(self) -> None:
        """Load the model and start the topics, the worker and the diagnostics timer.

        Raises:
            CheckpointError: The model file is missing or incompatible.
            ConfigError: The model does not fit the parameters (device, crop size).
        """
        from signal_light_node.runtime.engine import engine_from_checkpoint

        p = self.params
        self.engine = engine_from_checkpoint(
            p.model_path or None, device=p.device, backend=p.backend, threads=p.num_threads,
            thresholds=p.thresholds,
            track_timeout_s=p.track_timeout_s, max_tracks=p.max_tracks, max_gap_s=p.max_gap_s,
            intent_filter=p.intent_filter_config,
            max_boxes=p.max_boxes_per_frame)
        self.model_path = self.engine.backend.source

        self._pairer = StampPairer(int(p.sync_slop_s * _NS), int(p.sync_timeout_s * _NS),
                                   p.image_queue_size, p.detection_queue_size)
        self._queue = DropOldestQueue(p.work_queue_size)
        # One publisher per output adapter; the first is the result array.
        self._outputs = [(adapter, self.create_publisher(message_class(adapter.msgtype),
                                                         adapter.node_topic, adapter.depth))
                         for adapter in output_adapters(markers=p.publish_markers)]
        self._out = self._outputs[0][1]
        self._debug = None
        if p.publish_debug_image:
            self._debug = self.create_publisher(message_class(IMAGE_TYPE), DEBUG_TOPIC, 2)
        self._diag = self.create_publisher(message_class(DIAGNOSTICS_TYPE), DIAGNOSTICS_TOPIC,
                                           10)
        self._worker = Worker(self._queue, self._process, name="signal_light_inference").start()

        if p.image_transport == "compressed":
            image_type, image_topic = COMPRESSED_TYPE, COMPRESSED_TOPIC
        else:
            image_type, image_topic = IMAGE_TYPE, IMAGE_TOPIC
        self._image_sub = self.create_subscription(
            message_class(image_type), image_topic, self._on_image,
            qos(p.reliability, p.image_queue_size))
        self._det_sub = self.create_subscription(
            message_class(DETECTIONS_TYPE), DETECTIONS_TOPIC,
            self._on_detections, qos(p.reliability, p.detection_queue_size))
        self._image_topic = self._image_sub.topic_name
        self._decode = _decoder(p.image_transport)
        self._last_snapshot = self._snapshot()
        self._timer = self.create_timer(p.diagnostics_period_s, self._publish_diagnostics)
        self.add_on_set_parameters_callback(self._check_new_parameters)
        self.add_post_set_parameters_callback(self._apply_new_parameters)
        self.get_logger().info(
            f"outputs: {', '.join(pub.topic_name for _, pub in self._outputs)}; crop margin "
            f"{self.engine.crop.margin:g} (the model checkpoint's)")
        self.get_logger().info(
            f"ready: {self._image_topic} ({p.image_transport}, {p.reliability}) + "
            f"{self._det_sub.topic_name} "
            f"-> {self._out.topic_name}; model {self.model_path} ({self.engine.backend.name}"
            f"{', chosen by backend auto' if p.backend == 'auto' else ''}) on {p.device}, "
            f"pairing {'exact' if p.sync_slop_s == 0 else f'within {p.sync_slop_s} s'}")

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

    # ------------------------------------------------------------------- worker
    def _run_engine(self, pair: Any, boxes: List[Any]) -> Tuple[Any, Any, float]:
        """``(image or None, frame, decode seconds)``: an image that cannot be used gives
        every box unjudged."""
        start = time.perf_counter()
        try:
            image = self._decode(pair.image, self._image_topic, pair.stamp_ns,
                                 self.params.max_image_pixels)
        except ImageConversionError as exc:
            self._counts["oversized_images" if isinstance(exc, ImageTooLargeError)
                         else "bad_images"] += 1
            self.get_logger().warning(f"frame published unjudged: {exc}",
                                      throttle_duration_sec=5.0)
            msg = pair.image
            return None, self.engine.unjudged_frame(
                pair.stamp_ns, boxes, int(getattr(msg, "width", 0)),
                int(getattr(msg, "height", 0)), str(exc)), 0.0
        decoded = time.perf_counter()
        return image, self.engine.process(image, pair.stamp_ns, boxes), decoded - start

    def _process(self, pair: Any) -> None:
        taken = time.monotonic_ns()
        boxes = detections_to_boxes(pair.detections)
        image, frame, decode_s = self._run_engine(pair, boxes)
        (result_out, out), *others = self._outputs
        t_build = time.perf_counter()
        message = result_out.build(pair.image.header, frame.results, rclpy_make)
        t_publish = time.perf_counter()
        if not self._publish(out, message):
            return
        done = time.monotonic_ns()
        self._counts["outputs"] += 1
        self._latency.add((done - pair.image_received_ns) / _NS)
        self._processing.add(
            (done - max(pair.image_received_ns, pair.detections_received_ns)) / _NS)
        if image is not None:
            self._stages.add({
                "queue": (taken - max(pair.image_received_ns, pair.detections_received_ns)) / _NS,
                "decode": decode_s, **frame.stages_s, "outputs": t_publish - t_build,
                "publish": time.perf_counter() - t_publish})
        for adapter, publisher in others:
            if not adapter.when_subscribed or publisher.get_subscription_count() > 0:
                self._publish(publisher, adapter.build(pair.image.header, frame.results,
                                                       rclpy_make))
        if image is None:
            return  # no engine run, no debug image
        self._engine_time.add(frame.latency_s)
        if frame.warnings:
            self.get_logger().warning(f"stamp {pair.stamp_ns}: {'; '.join(frame.warnings)}",
                                      throttle_duration_sec=5.0)
        if self._debug is not None and self._debug.get_subscription_count() > 0:
            self._publish_debug(image, pair, boxes, frame.results)

    def _publish_debug(self, image: Any, pair: Any, boxes: List[Any], results: List[Any]) -> None:
        from signal_light_node.io.image_codec import bgr_to_image_fields
        from signal_light_node.tools.visualize import draw_results

        attention = self.engine.attention_masks(image, boxes)
        drawn = draw_results(image, results, attention=attention,
                             caption=f"{pair.stamp_ns / 1e9:.3f}")
        msg = rclpy_make(IMAGE_TYPE, header=pair.image.header,
                         **bgr_to_image_fields(drawn))
        if self._publish(self._debug, msg):
            self._counts["debug_images"] += 1

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
        out["dropped_work_queue"] = self._queue.dropped
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
            "backend": self.engine.backend.name,
        }
        extra.update(self._stages.values())
        level, message, values = health(self._last_snapshot, now, self._latency.summary(),
                                        self._processing.summary(),
                                        self._engine_time.summary(), extra)
        self._last_snapshot = now
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


def main(args: Optional[List[str]] = None) -> int:
    """Run the node until Ctrl-C or a shutdown request; returns the exit code.

    Any start-up problem (bad ROS arguments, parameters, model, device) is reported in
    ONE log line and gives exit code 1; a params file without a section for this node
    is warned about.
    """
    logging.basicConfig(level=logging.INFO, format="[%(levelname)s] [%(name)s]: %(message)s")
    node: Optional[SignalLightDetector] = None
    code = 0
    try:
        _init_ros(args)
        node = SignalLightDetector()
        _warn_foreign_params_files(node, args)
        node.setup()
        rclpy.spin(node)
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


if __name__ == "__main__":
    sys.exit(main())
