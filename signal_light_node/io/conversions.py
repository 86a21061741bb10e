"""Conversions between ROS messages and the core's plain Python types.

Everything here is duck-typed: it reads messages through attribute access only, so
``rosbags`` objects (bag I/O) and rclpy objects (the live node) work alike. Messages are
built through a factory ``make(msgtype, **fields)``: :func:`signal_light_node.io.bagio.make`
for bags, :func:`signal_light_node.ros.messages.rclpy_make` for rclpy. This module
never imports rclpy.
"""

from __future__ import annotations

import math
from typing import Any, Callable, List, Sequence, Tuple

import numpy as np

from signal_light_node.boxes import TrackBox
from signal_light_node.labels import TASKS, Intent, LightStatus, View
from signal_light_node.runtime.results import LightEstimate, VehicleResult

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


def _copy_header(header: Any, make: MessageFactory) -> Any:
    # Rebuilt rather than reused so that a rosbags header can go into an rclpy message.
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
                               header=_copy_header(header, make), results=results,
                               bbox=make("vision_msgs/msg/BoundingBox2D", center=center,
                                         size_x=float(box.width), size_y=float(box.height)),
                               id=str(box.track_id)))
    return make("vision_msgs/msg/Detection2DArray", header=_copy_header(header, make),
                detections=detections)


def _light_state(estimate: LightEstimate, make: MessageFactory) -> Any:
    return make("signal_light_msgs/msg/LightState", state=int(estimate.state),
                on_probability=float(estimate.on), off_probability=float(estimate.off),
                unknown_probability=float(estimate.unknown))


def _roi(roi: Tuple[int, int, int, int], make: MessageFactory) -> Any:
    # RegionOfInterest is unsigned; a box wholly outside the image has an empty ROI.
    x, y, w, h = (max(0, int(v)) if math.isfinite(v) else 0 for v in roi)
    return make("sensor_msgs/msg/RegionOfInterest", x_offset=x, y_offset=y, height=h, width=w,
                do_rectify=False)


def vehicle_light_array(header: Any, results: Sequence[VehicleResult],
                        make: MessageFactory) -> Any:
    """Build a ``signal_light_msgs/VehicleLightStateArray``.

    Args:
        header: The image's header (any object with ``stamp.sec/nanosec`` and ``frame_id``).
        results: One result per vehicle, in output order.
        make: Message factory (``bagio.make`` or :func:`rclpy_make`).

    Returns:
        The message.
    """
    vehicles = []
    for res in results:
        classification = [make("signal_light_msgs/msg/LightClassification", label=int(code),
                               probability=float(prob)) for code, prob in res.classification]
        vehicles.append(make(
            "signal_light_msgs/msg/VehicleLightState",
            track_id=str(res.track_id),
            roi=_roi(res.roi, make),
            classification=classification,
            brake=_light_state(res.brake, make),
            left_blinker=_light_state(res.left, make),
            right_blinker=_light_state(res.right, make),
            intent=int(res.intent),
            intent_probability=float(res.intent_probability),
            view=int(res.view),
            view_probability=float(res.view_probability),
            frames_observed=int(res.frames_observed),
        ))
    return make("signal_light_msgs/msg/VehicleLightStateArray",
                header=_copy_header(header, make), vehicles=vehicles)


def _estimate(state: Any) -> LightEstimate:
    return LightEstimate(LightStatus(int(state.state)), float(state.off_probability),
                         float(state.on_probability), float(state.unknown_probability))


def vehicle_light_array_to_results(msg: Any) -> Tuple[int, List[VehicleResult]]:
    """Read a ``VehicleLightStateArray`` back into core results.

    ``judged`` is not carried by the message; it is reconstructed as False only for an
    entry that says nothing at all (every light unjudged and zero intent/view probability).

    Returns:
        ``(stamp_ns of the header, results in message order)``.
    """
    unjudged = LightEstimate.unjudged()
    results = []
    for v in msg.vehicles:
        roi = v.roi
        lights = (_estimate(v.brake), _estimate(v.left_blinker), _estimate(v.right_blinker))
        intent_p, view_p = float(v.intent_probability), float(v.view_probability)
        judged = not (all(x == unjudged for x in lights) and intent_p == 0.0 and view_p == 0.0)
        results.append(VehicleResult(
            track_id=str(v.track_id),
            roi=(int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height)),
            brake=lights[0], left=lights[1], right=lights[2],
            intent=Intent(int(v.intent)), intent_probability=intent_p,
            view=View(int(v.view)), view_probability=view_p,
            classification=tuple((int(c.label), float(c.probability)) for c in v.classification),
            frames_observed=int(v.frames_observed),
            judged=judged,
        ))
    return stamp_to_ns(msg.header.stamp), results


def _task_row(intent: Any, brake: Any, left: Any, right: Any, view: Any) -> np.ndarray:
    values = {"intent": intent, "brake": brake, "left": left, "right": right, "view": view}
    return np.array([int(values[t]) for t in TASKS], dtype=np.int64)


def truth_row(vehicle: Any) -> np.ndarray:
    """A ``VehicleLightState`` message's classes as int64 ``[len(TASKS)]``, ``TASKS`` order.

    The label row of a ground-truth entry, as training, evaluation and replay score it.
    """
    return _task_row(vehicle.intent, vehicle.brake.state, vehicle.left_blinker.state,
                     vehicle.right_blinker.state, vehicle.view)


def result_row(result: VehicleResult) -> np.ndarray:
    """A :class:`VehicleResult`'s classes in the layout of :func:`truth_row`."""
    return _task_row(result.intent, result.brake.state, result.left.state, result.right.state,
                     result.view)
