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

This module is the node itself: its parameters, cameras and inputs (subscriptions, the
callbacks, the input counters). Its other parts each have their own module:
:mod:`~signal_light_node.ros.node_lifecycle` (configure, activate, deactivate, cleanup and
the run loop), :mod:`~signal_light_node.ros.frame_path` (the worker: decode, engine,
outputs), :mod:`~signal_light_node.ros.diagnostics` (``/diagnostics``) and
:mod:`~signal_light_node.ros.param_callbacks` (parameter changes).
"""

from __future__ import annotations

import sys
import time
from functools import partial
from typing import Any, Dict, List, Optional

from rclpy.node import Node

from signal_light_node.io.conversions import stamp_to_ns
from signal_light_node.io.topics import COMPRESSED_TYPE, DETECTIONS_TYPE, IMAGE_TYPE
from signal_light_node.outputs import VehicleLightsOutput
from signal_light_node.ros.cameras import CameraIO, GapsSum, camera_ios
from signal_light_node.ros.diagnostics import NodeDiagnostics
from signal_light_node.ros.frame_path import NODE_STAGES, NodeFramePath
from signal_light_node.ros.gaps import SequenceGaps
from signal_light_node.ros.node_lifecycle import NodeLifecycle, run_detector
from signal_light_node.ros.param_callbacks import ParameterCallbacks
from signal_light_node.ros.params import NODE_NAME, DetectorParams, read_parameters
from signal_light_node.ros.ros_io import message_class, qos
from signal_light_node.runtime.stats import LatencyWindow, Snapshot, StageWindows
from signal_light_node.runtime.worker import Worker

__all__ = ["COMPRESSED_TOPIC", "DETECTIONS_TOPIC", "IMAGE_TOPIC", "NODE_STAGES", "OUTPUT_TOPIC",
           "SignalLightDetector", "main", "run_detector"]

#: Topic names relative to the node (remap them with ``-r ~/input/image:=/camera/...``);
#: with ``cameras`` each camera's sit under its name (``~/front/input/image``).
IMAGE_TOPIC = "~/input/image"
COMPRESSED_TOPIC = "~/input/image/compressed"
DETECTIONS_TOPIC = "~/input/detections"
#: The result array's topic; every output topic is its adapter's ``OutputAdapter.node_topic``.
OUTPUT_TOPIC = VehicleLightsOutput.node_topic


class SignalLightDetector(NodeLifecycle, NodeFramePath, NodeDiagnostics, ParameterCallbacks,
                          Node):
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

    # ------------------------------------------------------------------- inputs
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
        # Publishers already on a topic may have numbered messages before we subscribed;
        # every later one is counted from its first message (ros/gaps.py).
        for kind, sub in zip(("image", "detections"), camera.subscriptions):
            camera.gaps[kind].subscribed(self.count_publishers(sub.topic_name))

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


def main(args: Optional[List[str]] = None) -> int:
    """Run the node (loaded and active at once); returns the exit code."""
    return run_detector(SignalLightDetector, SignalLightDetector.setup, args)


if __name__ == "__main__":
    sys.exit(main())
