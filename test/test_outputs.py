"""The output adapters: the result array, the RViz markers and the debug image, with both
message factories."""

from __future__ import annotations

import numpy as np
import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.io import bagio
from signal_light_node.io.conversions import make_header, stamp_to_ns
from signal_light_node.io.image_codec import image_msg_to_bgr
from signal_light_node.io.topics import (DEBUG_IMAGE_TOPIC, IMAGE_TYPE, MARKER_ARRAY_TYPE,
                                         MARKERS_TOPIC, OUTPUT_TOPIC, VEHICLE_LIGHTS_TYPE)
from signal_light_node.labels import Intent, LightStatus, View
from signal_light_node.outputs import (METRES_PER_PIXEL, DebugImageOutput, MarkerOutput,
                                       OutputAdapter, VehicleLightsOutput, output_adapters)
from signal_light_node.outputs.debug_image import draw_results
from signal_light_node.outputs.markers import (AMBER, ARROW, CUBE, DELETEALL, GREEN,
                                               LINE_STRIP, RED, TEXT_VIEW_FACING,
                                               UNKNOWN_GREY, is_unknown, marker_label)
from signal_light_node.outputs.vehicle_lights import vehicle_light_array
from signal_light_node.runtime.results import LightEstimate, VehicleResult

STAMP = 1_700_000_000_123_456_789
ON, OFF, UNK = (LightEstimate.certain(s) for s in (LightStatus.ON, LightStatus.OFF,
                                                   LightStatus.UNKNOWN))


def _result(track_id="7", roi=(100, 50, 80, 40), brake=OFF, left=OFF, right=OFF,
            intent=Intent.OFF, view=View.BEHIND, judged=True) -> VehicleResult:
    return VehicleResult(track_id=track_id, roi=roi, brake=brake, left=left, right=right,
                         intent=intent, intent_probability=0.9, view=view, view_probability=0.9,
                         judged=judged)


def _build(results, make=bagio.make):
    return MarkerOutput().build(make_header(STAMP, "camera_optical", make), results, make)


def _by_ns(msg, ns):
    return [m for m in msg.markers if m.ns == ns]


def _rgba(marker):
    c = marker.color
    return tuple(round(float(v), 3) for v in (c.r, c.g, c.b, c.a))


def _same(colour):
    return tuple(round(v, 3) for v in colour)


def test_adapters_choice_and_interface():
    plain, with_markers = output_adapters(), output_adapters(markers=True)
    assert [type(a) for a in plain] == [VehicleLightsOutput]
    assert [type(a) for a in with_markers] == [VehicleLightsOutput, MarkerOutput]
    assert all(isinstance(a, OutputAdapter) for a in with_markers)
    assert (VehicleLightsOutput.topic, VehicleLightsOutput.msgtype) == (OUTPUT_TOPIC,
                                                                        VEHICLE_LIGHTS_TYPE)
    assert (MarkerOutput.topic, MarkerOutput.msgtype) == (MARKERS_TOPIC, MARKER_ARRAY_TYPE)
    assert VehicleLightsOutput.node_topic == "~/output/vehicle_lights"
    assert MarkerOutput.node_topic == "~/output/markers" and MarkerOutput.when_subscribed
    with pytest.raises(ConfigError):
        MarkerOutput(metres_per_pixel=0)
    every = output_adapters(markers=True, debug_image=True)
    assert [type(a) for a in every] == [VehicleLightsOutput, MarkerOutput, DebugImageOutput]
    assert (DebugImageOutput.topic, DebugImageOutput.msgtype) == (DEBUG_IMAGE_TOPIC, IMAGE_TYPE)
    assert DebugImageOutput.node_topic == "~/output/debug/image"
    assert DebugImageOutput.when_subscribed and DebugImageOutput.draws_image
    assert not (VehicleLightsOutput.draws_image or MarkerOutput.draws_image)


@pytest.mark.parametrize("make", ["bags", "rclpy"])
def test_debug_image_adapter_draws_the_frame_with_its_stamp(make):
    if make == "rclpy":
        from signal_light_node.ros.messages import rclpy_make as make
    else:
        make = bagio.make
    header = make_header(STAMP, "camera", make)
    image = np.full((120, 200, 3), 90, np.uint8)
    results = [_result(roi=(20, 30, 60, 40), brake=ON)]
    heat = np.zeros((120, 200), np.float32)
    heat[30:70, 20:80] = 0.5
    msg = DebugImageOutput().build(header, results, make, image=image, attention=heat)
    assert msg.header.frame_id == "camera" and stamp_to_ns(msg.header.stamp) == STAMP
    want = draw_results(image, results, attention=heat, caption=f"{STAMP / 1e9:.3f}")
    np.testing.assert_array_equal(image_msg_to_bgr(msg), want)
    assert (image == 90).all()  # the frame itself is not drawn on
    with pytest.raises(ConfigError, match="decoded frame"):
        DebugImageOutput().build(header, results, make)


def test_result_adapter_is_the_vehicle_light_array():
    header = make_header(STAMP, "camera", bagio.make)
    results = [_result(), _result("9", judged=False)]
    store = bagio.typestore()
    got = VehicleLightsOutput().build(header, results, bagio.make)
    want = vehicle_light_array(header, results, bagio.make)
    assert bytes(store.serialize_cdr(got, VEHICLE_LIGHTS_TYPE)) == \
        bytes(store.serialize_cdr(want, VEHICLE_LIGHTS_TYPE))


def test_markers_box_text_and_header_in_metres():
    msg = _build([_result()])
    first = msg.markers[0]
    assert first.action == DELETEALL
    for m in msg.markers:
        assert m.header.frame_id == "camera_optical" and stamp_to_ns(m.header.stamp) == STAMP
        assert (m.lifetime.sec, m.lifetime.nanosec) == (1, 0)
    box, = _by_ns(msg, "box")
    assert box.type == LINE_STRIP and _rgba(box) == _same(GREEN)
    corners = [(round(p.x, 6), round(p.y, 6), p.z) for p in box.points]
    s = METRES_PER_PIXEL
    assert corners == [(round(u * s, 6), round(v * s, 6), 0.0) for u, v in
                       ((100, 50), (180, 50), (180, 90), (100, 90), (100, 50))]
    text, = _by_ns(msg, "track_id")
    assert text.type == TEXT_VIEW_FACING and text.text == "7"
    assert text.pose.position.x == pytest.approx(1.40) and text.pose.position.y < 0.50
    assert _by_ns(msg, "blinker") == [] and _by_ns(msg, "brake") == []
    bagio.typestore().serialize_cdr(msg, MARKER_ARRAY_TYPE)  # a valid message for bags


@pytest.mark.parametrize("view, left_points", [(View.BEHIND, -1), (View.FRONT, +1)])
def test_blinker_arrows_point_to_the_lamps_side(view, left_points):
    msg = _build([_result(left=ON, intent=Intent.LEFT, view=view)])
    arrow, = _by_ns(msg, "blinker")
    assert arrow.type == ARROW and _rgba(arrow) == _same(AMBER)
    start, tip = arrow.points
    assert np.sign(tip.x - start.x) == left_points and tip.y == start.y
    assert _by_ns(msg, "track_id")[0].text == "7 L"
    both = _build([_result(left=ON, right=ON, intent=Intent.HAZARD)])
    assert sorted(m.id for m in _by_ns(both, "blinker")) == [0, 1]
    assert _by_ns(both, "track_id")[0].text == "7 HAZ"


def test_brake_mark_and_red_box():
    msg = _build([_result(brake=ON)])
    assert _rgba(_by_ns(msg, "box")[0]) == _same(RED)
    bar, = _by_ns(msg, "brake")
    assert bar.type == CUBE and _rgba(bar) == _same(RED)
    assert bar.pose.position.y == pytest.approx((90 - 2) * METRES_PER_PIXEL)  # bottom of box
    assert bar.scale.x == pytest.approx(0.6 * 80 * METRES_PER_PIXEL)


@pytest.mark.parametrize("result", [
    _result(judged=False, left=ON),                    # not judged at all
    _result(brake=UNK, left=UNK, right=UNK),          # judged, every light unknown
], ids=["unjudged", "all_unknown"])
def test_unknown_vehicles_are_drawn_grey_without_marks(result):
    assert is_unknown(result) and marker_label(result) == "7 ?"
    msg = _build([result])
    assert _rgba(_by_ns(msg, "box")[0]) == _same(UNKNOWN_GREY)
    assert _by_ns(msg, "track_id")[0].text == "7 ?"
    assert _by_ns(msg, "blinker") == [] and _by_ns(msg, "brake") == []


def test_ids_follow_the_vehicle_index_and_empty_rois_draw_nothing():
    results = [_result("a"), _result("out", roi=(0, 0, 0, 0)), _result("c", brake=ON)]
    msg = _build(results)
    assert [(m.id, m.text) for m in _by_ns(msg, "track_id")] == [(0, "a"), (2, "c")]
    assert [m.id for m in _by_ns(msg, "brake")] == [2]
    assert len(_build([]).markers) == 1  # an empty frame still clears the display


def test_rclpy_factory_builds_the_same_markers():
    pytest.importorskip("rclpy")
    from rclpy.serialization import serialize_message

    from signal_light_node.ros.messages import rclpy_make

    results = [_result(brake=ON, left=ON, intent=Intent.LEFT), _result("x", judged=False)]
    ours, theirs = _build(results), _build(results, rclpy_make)
    store = bagio.typestore()
    # Through rosbags again: CDR padding bytes need not be zero.
    again = store.deserialize_cdr(serialize_message(theirs), MARKER_ARRAY_TYPE)
    assert bytes(store.serialize_cdr(again, MARKER_ARRAY_TYPE)) == \
        bytes(store.serialize_cdr(ours, MARKER_ARRAY_TYPE))
    assert len(again.markers) == 1 + 4 + 2
