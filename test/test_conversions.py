"""Message <-> core conversions with both factories (rosbags and rclpy message classes)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from signal_light_node.io import bagio
from signal_light_node.boxes import TrackBox
from signal_light_node.io.conversions import (boxes_to_detections, detections_to_boxes, make_header,
                                           ns_to_stamp_fields, stamp_to_ns)
from signal_light_node.outputs.vehicle_lights import (vehicle_light_array,
                                                      vehicle_light_array_to_results)
from signal_light_node.ros.messages import rclpy_make
from signal_light_node.labels import Intent, LightStatus, View
from signal_light_node.runtime.results import LightEstimate, VehicleResult


FACTORIES = [pytest.param(bagio.make, id="rosbags"), pytest.param(rclpy_make, id="rclpy")]


@pytest.mark.parametrize("ns", [0, 1, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789, -1])
def test_stamp_round_trip(ns: int) -> None:
    sec, nanosec = ns_to_stamp_fields(ns)
    assert 0 <= nanosec < 1_000_000_000
    header = make_header(ns, "f", bagio.make)
    assert (header.stamp.sec, header.stamp.nanosec) == (sec, nanosec)
    assert stamp_to_ns(header.stamp) == ns


@pytest.mark.parametrize("make", FACTORIES)
def test_detections_round_trip(make) -> None:
    if make is rclpy_make:
        pytest.importorskip("vision_msgs.msg")
    boxes = [TrackBox("a", 1.5, 2.0, 11.5, 22.0, "car"), TrackBox("b", -4.0, 0.0, 4.0, 8.0),
             TrackBox("nan", math.nan, 0.0, 3.0, 3.0, "truck")]
    msg = boxes_to_detections(make_header(7, "cam", make), boxes, make, score=0.5)
    assert [d.id for d in msg.detections] == ["a", "b", "nan"]
    assert msg.detections[0].results[0].hypothesis.score == 0.5
    assert len(msg.detections[1].results) == 0
    assert stamp_to_ns(msg.detections[2].header.stamp) == 7
    got = detections_to_boxes(msg)
    assert got[:2] == boxes[:2]
    assert got[2].track_id == "nan" and math.isnan(got[2].x0) and got[2].class_id == "truck"


@pytest.mark.parametrize("make", FACTORIES)
def test_vehicle_light_array_round_trip(make) -> None:
    if make is rclpy_make:
        pytest.importorskip("signal_light_msgs.msg")
    results = [VehicleResult("3", (-5, 2, 10, 20), LightEstimate(LightStatus.ON, 0.25, 0.5, 0.25),
                             LightEstimate.certain(LightStatus.OFF),
                             LightEstimate.certain(LightStatus.UNKNOWN), Intent.OFF, 0.75,
                             View.RIGHT, 0.5, ((100, 0.5),), 3, True)]
    # A rosbags header goes into an rclpy message too: the header is rebuilt, not reused.
    msg = vehicle_light_array(make_header(42, "cam", bagio.make), results, make)
    assert msg.header.frame_id == "cam" and msg.vehicles[0].roi.x_offset == 0
    stamp, back = vehicle_light_array_to_results(msg)
    assert stamp == 42
    assert back == [dataclasses.replace(results[0], roi=(0, 2, 10, 20))]


def test_rclpy_make_accepts_numpy_payloads() -> None:
    pytest.importorskip("sensor_msgs.msg")
    data = np.arange(12, dtype=np.uint8)
    msg = rclpy_make("sensor_msgs/Image", height=2, width=2, encoding="bgr8", step=6, data=data)
    assert bytes(msg.data) == data.tobytes()
