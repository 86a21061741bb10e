"""The detector node's frame path: the worker's work item, from paired frames to outputs.

:class:`NodeFramePath` is the part of the node
(:class:`~signal_light_node.ros.detector_node.SignalLightDetector`) that the worker thread
runs (:class:`~signal_light_node.runtime.worker.Worker`) for every item of the work queue:
one tick, at most one paired frame per camera (the single-camera node's item is a tick of
one frame of the camera ``""``). Each frame is decoded (an image that cannot be used gives
its boxes unjudged, counted), the decoded ones are judged in ONE engine step
(``engine.process_many``), and each frame's results go out through its camera's output
adapters (:mod:`signal_light_node.outputs`) with its image's header: the result array
always, markers and the debug image as the parameters ask. The stage times, latencies and
the engine time go to the windows ``/diagnostics`` reports.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, List, Optional, Sequence, Tuple

import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy_impl

from signal_light_node.errors import ImageConversionError, ImageTooLargeError
from signal_light_node.io.conversions import detections_to_boxes
from signal_light_node.ros.cameras import CameraIO
from signal_light_node.ros.messages import rclpy_make

_NS = 1_000_000_000

#: Stages of the worker's work item (one frame; with ``cameras`` one tick) timed for
#: ``/diagnostics`` (``stage_<name>_mean_ms`` / ``_p95_ms``): the wait in the work queue
#: (the tick's longest), decoding, the engine's own stages (``engine.ENGINE_STAGES``),
#: building the result arrays and publishing them.
NODE_STAGES = ("queue", "decode", "crops", "state_gather", "step", "intent_filter",
               "state_store", "results", "outputs", "publish")


class NodeFramePath:
    """The worker's frame path (a part of ``SignalLightDetector``).

    Uses the node's ``engine``, ``params``, ``_cameras``, ``_decode``, its counts
    (``_counts``, each camera's ``counts``) and its windows (``_latency``,
    ``_processing``, ``_engine_time``, ``_stages``).
    """

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


def decoder_for(image_transport: str) -> Any:
    """The image decoder of the node's ``image_transport``."""
    from signal_light_node.io.image_codec import compressed_msg_to_bgr, image_msg_to_bgr

    return compressed_msg_to_bgr if image_transport == "compressed" else image_msg_to_bgr
