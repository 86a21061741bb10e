"""Conversions between ROS messages and the core's plain Python types: stamps, headers,
detections <-> track boxes.

Everything here is duck-typed: it reads messages through attribute access only, so
``rosbags`` objects (bag I/O) and rclpy objects (the live node) work alike. Messages are
built through a factory ``make(msgtype, **fields)``: :func:`signal_light_node.io.bagio.make`
for bags, :func:`signal_light_node.ros.messages.rclpy_make` for rclpy. This module
never imports rclpy. The node's own result message (``VehicleLightStateArray``) is built
and read in :mod:`signal_light_node.outputs.vehicle_lights`.
"""

from __future__ import annotations

from typing import Any, Callable, List, Sequence, Tuple

import numpy as np

from signal_light_node.boxes import TrackBox

#: ``make(msgtype, **fields) -> message``
MessageFactory = Callable[..., Any]

_NS = 1_000_000_000


def stamp_to_ns(stamp: Any) -> int:
    """Nanoseconds of a ``builtin_interfaces/Time`` (``sec`` and ``nanosec``)."""
    return int(stamp.sec) * _NS + int(stamp.nanosec)


def ns_to_stamp_fields(ns: int) -> Tuple[int, int]:
    """``(sec, nanosec)`` of a time in nanoseconds; ``nanosec`` is always in [0, 1e9)."""
    sec, nanosec = divmod(int(ns), _NS)
    return sec, nanosec


def make_header(stamp_ns: int, frame_id: str, make: MessageFactory) -> Any:
    """Build a ``std_msgs/Header`` with the given factory."""
    sec, nanosec = ns_to_stamp_fields(stamp_ns)
    return make("std_msgs/msg/Header",
                stamp=make("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec),
                frame_id=str(frame_id))


def copy_header(header: Any, make: MessageFactory) -> Any:
    """A new ``std_msgs/Header`` with ``header``'s stamp and frame, built with ``make``.

    Rebuilt rather than reused so that a rosbags header can go into an rclpy message.
    """
    return make_header(stamp_to_ns(header.stamp), header.frame_id, make)


def _center_xy(center: Any) -> Tuple[float, float]:
    """A box centre's (x, y): ``vision_msgs/Pose2D`` (``position.x``; vision_msgs >= 4) or
    the older ``geometry_msgs/Pose2D`` (``x``, ``y``, ``theta``)."""
    point = getattr(center, "position", center)
    return float(point.x), float(point.y)


def _class_id(result: Any) -> str:
    """``hypothesis.class_id`` of an ``ObjectHypothesisWithPose``, or the older ``id`` field."""
    hypothesis = getattr(result, "hypothesis", None)
    return str(hypothesis.class_id if hypothesis is not None else getattr(result, "id", ""))


def detections_to_boxes(msg: Any) -> List[TrackBox]:
    """Track boxes of a ``vision_msgs/Detection2DArray``, in message order.

    ``Detection2D.id`` is the track ID; the class is ``results[0].hypothesis.class_id``
    (empty when there are no results). Boxes whose centre is a ``geometry_msgs/Pose2D``
    (the layout before vision_msgs 4) are read too.
    """
    boxes = []
    for det in msg.detections:
        bbox = det.bbox
        class_id = _class_id(det.results[0]) if len(det.results) else ""
        x, y = _center_xy(bbox.center)
        boxes.append(TrackBox.from_center(str(det.id), x, y, float(bbox.size_x),
                                          float(bbox.size_y), class_id))
    return boxes


def boxes_to_detections(header: Any, boxes: Sequence[TrackBox], make: MessageFactory,
                        score: float = 1.0) -> Any:
    """Build a ``vision_msgs/Detection2DArray`` from track boxes.

    Args:
        header: Header of the image the boxes belong to (copied into every detection).
        boxes: The boxes; a box with ``class_id`` gets one hypothesis with ``score``.
        make: Message factory.
        score: Score written for each hypothesis.

    Returns:
        The message.
    """
    detections = []
    for box in boxes:
        results = []
        if box.class_id:
            pose = make("geometry_msgs/msg/PoseWithCovariance",
                        pose=make("geometry_msgs/msg/Pose",
                                  position=make("geometry_msgs/msg/Point", x=0.0, y=0.0, z=0.0),
                                  orientation=make("geometry_msgs/msg/Quaternion",
                                                   x=0.0, y=0.0, z=0.0, w=1.0)),
                        covariance=np.zeros(36, dtype=np.float64))
            results.append(make("vision_msgs/msg/ObjectHypothesisWithPose",
                                hypothesis=make("vision_msgs/msg/ObjectHypothesis",
                                                class_id=str(box.class_id), score=float(score)),
                                pose=pose))
        center = make("vision_msgs/msg/Pose2D",
                      position=make("vision_msgs/msg/Point2D", x=(box.x0 + box.x1) / 2.0,
                                    y=(box.y0 + box.y1) / 2.0),
                      theta=0.0)
        detections.append(make("vision_msgs/msg/Detection2D",
                               header=copy_header(header, make), results=results,
                               bbox=make("vision_msgs/msg/BoundingBox2D", center=center,
                                         size_x=float(box.width), size_y=float(box.height)),
                               id=str(box.track_id)))
    return make("vision_msgs/msg/Detection2DArray", header=copy_header(header, make),
                detections=detections)
