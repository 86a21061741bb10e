"""The ``signal_light_msgs/VehicleLightStateArray`` message: built from the engine's
results, read back into them, and its label rows.

The node's result (:class:`~signal_light_node.outputs.adapter.VehicleLightsOutput`) and
the ground truth of the synthetic bags (``synth.bag``, ``evalgen.bag``) are both this
message, built by :func:`vehicle_light_array` through a message factory
``make(msgtype, **fields)`` (:func:`signal_light_node.io.bagio.make` for bags,
:func:`signal_light_node.ros.messages.rclpy_make` for rclpy). Everything reads messages
through attribute access only, so rosbags and rclpy objects work alike; no rclpy here.
"""

from __future__ import annotations

import math
from typing import Any, List, Sequence, Tuple

import numpy as np

from signal_light_node.io.conversions import MessageFactory, copy_header, stamp_to_ns
from signal_light_node.labels import TASKS, Intent, LightStatus, View
from signal_light_node.runtime.results import LightEstimate, VehicleResult


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
                header=copy_header(header, make), vehicles=vehicles)


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
