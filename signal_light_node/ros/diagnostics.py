"""The detector node's ``/diagnostics``: one ``DiagnosticStatus`` per period.

:class:`NodeDiagnostics` is the part of the node
(:class:`~signal_light_node.ros.detector_node.SignalLightDetector`) that the diagnostics
timer runs: it expires the pairing's stale messages, takes a snapshot of the node's
counters (``counters()``), lets :func:`~signal_light_node.runtime.stats.health` turn two
snapshots and the latency windows into the level, message and key/values, adds the
engine's figures, the model and, with ``cameras``, every camera's ``<camera>.<figure>``,
and publishes it.
"""

from __future__ import annotations

import time
from typing import Any, Dict, List, Optional, Tuple

from signal_light_node.io.topics import DIAGNOSTICS_TYPE
from signal_light_node.ros.messages import rclpy_make
from signal_light_node.ros.ros_io import message_class
from signal_light_node.runtime.stats import ERROR, OK, WARN, Snapshot, health

_LEVEL_BYTES = {OK: b"\x00", WARN: b"\x01", ERROR: b"\x02"}


class NodeDiagnostics:
    """The node's status on ``/diagnostics`` (a part of ``SignalLightDetector``).

    Uses the node's ``counters()``, ``engine``, ``params``, ``model_path``, ``_cameras``,
    ``_several``, ``_pairer``, ``_queue`` (``_camera_queue_drops``), ``_gaps``, the latency
    and stage windows, ``_precision()``, ``_diag`` (the publisher) and ``_last_snapshot``.
    """

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
            "middleware_drops_counted": _middleware_counted(self._gaps),
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


def _middleware_counted(gaps: Dict[str, Any]) -> str:
    """``middleware_drops_counted``: whether the RMW numbers its messages, and which losses
    the numbers cannot show (those of publishers already running when the node
    subscribed, before their first delivered message: ros/gaps.py)."""
    supported = gaps["image"].supported
    text = {True: "yes", False: "no (the middleware gives no sequence numbers)"}.get(
        supported, "not yet known")
    running = sum(g.publishers_before for g in gaps.values())
    if supported and running:
        text += (f", except before the first delivered message of the {running} "
                 "publisher(s) already running when the node subscribed")
    return text
