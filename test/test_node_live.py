"""The ``detector`` node in its own process, fed by a test publisher replaying a bag.

Each test starts the real executable on a fresh ROS domain and talks to it over rclpy
(reliable QoS, frame by frame, so a slow CI machine drops nothing): one output per input
frame, stamped and ordered like the inputs, track IDs equal to the detections', only the
codes 100/101/102; a frame without detections gives an empty array, an undecodable image
is published with its boxes unjudged and counted without killing the node, and a missing
model stops it at start with one log line and a non-zero exit code.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from node_harness import (COMPRESSED_TYPE, DEBUG_TOPIC, MARKERS_TOPIC, RAW_TYPE, REPO,
                          DetectorProcess, LiveClient, load_frames, model_args, run_until_exit,
                          scene_bag)
from signal_light_node.ros.params import NODE_NAME

rclpy = pytest.importorskip("rclpy")

#: Lower bound of the per-light state accuracy (brake, left, right pooled, judged entries)
#: of the live node against the bag's ground truth. Checked only with the shipped weights.
#: The shipped (interim) weights score 61.8 % (day bag) and 55.1 % (night bag) on this
#: measure in `signal-light replay`; the bound leaves a margin. Raise it with the weights.
LIVE_MIN_LIGHT_ACCURACY = 0.45

#: Frames fed per test: enough to exercise the recurrent state, small enough for CI.
N_FRAMES = 25

_RELIABLE = ["-p", "reliability:=reliable"]


def _domain(env: dict) -> int:
    return int(env["ROS_DOMAIN_ID"])


def _check_outputs(client: LiveClient, frames) -> None:
    codes = set()
    for frame in frames:
        msgs = client.outputs.get(frame.stamp_ns, [])
        assert len(msgs) == 1, f"{len(msgs)} outputs for the frame stamped {frame.stamp_ns}"
        out = msgs[0]
        assert out.header.frame_id == frame.frame_id
        assert [v.track_id for v in out.vehicles] == frame.track_ids
        for v in out.vehicles:
            codes.update(c.label for c in v.classification)
            for light in (v.brake, v.left_blinker, v.right_blinker):
                total = light.on_probability + light.off_probability + light.unknown_probability
                assert light.state in (0, 1, 2) and abs(total - 1.0) < 1e-3
            assert v.frames_observed >= 1 or v.intent_probability == 0.0
    assert codes <= {100, 101, 102}
    assert sum(len(f.track_ids) for f in frames) > 0, "the bag fed no detections at all"


def _check_dynamic_parameters(client: LiveClient) -> None:
    ok, = client.set_parameters({"sync_slop_s": 0.02})
    assert ok.successful, ok.reason
    assert client.get_parameters(["sync_slop_s"]) == {"sync_slop_s": 0.02}
    refused, = client.set_parameters({"model_path": "/elsewhere.pt"})
    assert not refused.successful
    refused, = client.set_parameters({"sync_timeout_s": 0.015})  # below the slop of 0.02
    assert not refused.successful and "exceed sync_slop_s" in refused.reason
    assert client.get_parameters(["sync_timeout_s"]) == {"sync_timeout_s": 1.0}


def _check_debug_images(client: LiveClient, frames) -> None:
    from signal_light_node.io.conversions import stamp_to_ns

    sizes = {f.stamp_ns: f.size for f in frames}

    def of_frames():
        return [i for i in client.debug_images if stamp_to_ns(i.header.stamp) in sizes]

    # Debug images are published only while watched; after the warm-up they all are.
    assert client.spin_until(lambda: len(of_frames()) == len(frames), 20.0), \
        f"only {len(of_frames())} debug images for {len(frames)} frames"
    for img in of_frames():
        assert (img.height, img.width) == sizes[stamp_to_ns(img.header.stamp)]
        assert img.encoding == "bgr8" and len(img.data) == img.height * img.step


def _light_accuracy(client: LiveClient, frames) -> float:
    hits = total = 0
    for frame in frames:
        if frame.truth is None:
            continue
        truth = {v.track_id: v for v in frame.truth.vehicles}
        for v in client.outputs[frame.stamp_ns][0].vehicles:
            gt = truth.get(v.track_id)
            if gt is None or v.view_probability == 0.0:  # no truth, or not judged
                continue
            for name in ("brake", "left_blinker", "right_blinker"):
                hits += getattr(v, name).state == getattr(gt, name).state
                total += 1
    return hits / total if total else float("nan")


def _diag_values(client: LiveClient) -> dict:
    status = client.diagnostics[-1].status[0]
    return {kv.key: kv.value for kv in status.values}


def _extra_frames(last_stamp_ns: int, frame_id: str, compressed: bool):
    """(bad image, its detections), (good image, empty detections) stamped after the bag."""
    from signal_light_node.boxes import TrackBox
    from signal_light_node.io.conversions import boxes_to_detections, make_header
    from signal_light_node.ros.messages import rclpy_make
    from signal_light_node.io.image_codec import bgr_to_compressed_fields, bgr_to_image_fields

    bad_stamp, empty_stamp = last_stamp_ns + 100_000_000, last_stamp_ns + 200_000_000
    image = np.full((120, 160, 3), 90, np.uint8)
    if compressed:
        bad = rclpy_make(COMPRESSED_TYPE, header=make_header(bad_stamp, frame_id, rclpy_make),
                         format="jpeg", data=b"definitely not a jpeg")
        good = rclpy_make(COMPRESSED_TYPE, header=make_header(empty_stamp, frame_id, rclpy_make),
                          **bgr_to_compressed_fields(image))
    else:
        fields = bgr_to_image_fields(image)
        fields["data"] = fields["data"][:100]  # far shorter than step x height
        bad = rclpy_make(RAW_TYPE, header=make_header(bad_stamp, frame_id, rclpy_make), **fields)
        good = rclpy_make(RAW_TYPE, header=make_header(empty_stamp, frame_id, rclpy_make),
                          **bgr_to_image_fields(image))
    box = boxes_to_detections(make_header(bad_stamp, frame_id, rclpy_make),
                              [TrackBox("bad", 10, 10, 60, 50)], rclpy_make)
    empty = rclpy_make("vision_msgs/msg/Detection2DArray",
                       header=make_header(empty_stamp, frame_id, rclpy_make))
    return (bad_stamp, bad, box), (empty_stamp, good, empty)


def _run_live(tmp_path: Path, env: dict, raw: bool, extra_args, expect_params=None,
              debug_image: bool = False) -> None:
    bag = scene_bag(tmp_path, raw=raw)
    image_type, frames = load_frames(bag, N_FRAMES)
    assert image_type == (RAW_TYPE if raw else COMPRESSED_TYPE)
    args, shipped = model_args(tmp_path)
    node = DetectorProcess([*extra_args, *args, *_RELIABLE], env, tmp_path / "detector.log")
    try:
        node.wait_ready()
        with LiveClient(_domain(env), image_type) as client:
            client.wait_connected()
            if expect_params:
                assert client.get_parameters(list(expect_params)) == expect_params
            if debug_image:
                assert client.spin_until(
                    lambda: client.node.count_publishers(DEBUG_TOPIC) > 0, 20.0)
            else:
                _check_dynamic_parameters(client)
            warm = client.warm_up(frames[0].stamp_ns, frames[0].frame_id)
            client.feed(frames)
            _check_outputs(client, frames)
            if debug_image:
                _check_debug_images(client, frames)
            if shipped and LIVE_MIN_LIGHT_ACCURACY is not None:
                assert _light_accuracy(client, frames) >= LIVE_MIN_LIGHT_ACCURACY

            (bad_stamp, bad, box), (empty_stamp, good, empty) = _extra_frames(
                frames[-1].stamp_ns, frames[-1].frame_id, compressed=not raw)
            client.image_pub.publish(bad)
            client.det_pub.publish(box)
            client.image_pub.publish(good)
            client.det_pub.publish(empty)
            assert client.spin_until(lambda: empty_stamp in client.outputs, 20.0), node.text()
            assert list(client.outputs[empty_stamp][0].vehicles) == []
            # An undecodable image is published like replay writes it: its boxes unjudged.
            assert [v.track_id for v in client.outputs[bad_stamp][0].vehicles] == ["bad"]
            assert client.outputs[bad_stamp][0].vehicles[0].view_probability == 0.0
            # The next diagnostics report counts the bad image; the node is still alive.
            assert client.spin_until(
                lambda: client.diagnostics and _diag_values(client)["bad_images"] == "1", 10.0)
            values = _diag_values(client)
            assert int(values["outputs"]) == warm + len(frames) + 2
            assert int(values["images"]) == warm + len(frames) + 2
            assert float(values["latency_p95_ms"]) > 0
            # backend auto: the shipped model runs in onnxruntime (its .onnx export) on the
            # CPU, a .pt checkpoint in torch.
            assert values["backend"] == ("onnxruntime" if shipped else "torch")
            assert values["model_path"].endswith(".onnx" if shipped else ".pt")
            assert node.proc.poll() is None
        assert node.stop() == 0, node.text()
        assert "Traceback" not in node.text()
        assert "frame published unjudged" in node.text()
    finally:
        node.stop()


def test_compressed_images_with_the_params_file(tmp_path, rclpy_isolated_env):
    shipped = yaml.safe_load((REPO / "config" / "detector.yaml").read_text())
    expected = dict(shipped[NODE_NAME]["ros__parameters"], image_transport="compressed",
                    reliability="reliable")
    expected.pop("model_path")  # replaced by the tiny checkpoint when no weights ship
    _run_live(tmp_path, rclpy_isolated_env(), raw=False,
              extra_args=["--params-file", "config/detector.yaml",
                          "-p", "image_transport:=compressed"], expect_params=expected)


def test_raw_images_with_an_edited_params_file(tmp_path, rclpy_isolated_env):
    config = yaml.safe_load((REPO / "config" / "detector.yaml").read_text())
    params = config[NODE_NAME]["ros__parameters"]
    params.update(sync_timeout_s=2.5, max_tracks=77, threshold_brake=0.6,
                  publish_debug_image=True)
    path = tmp_path / "edited.yaml"
    path.write_text(yaml.safe_dump(config))
    _run_live(tmp_path, rclpy_isolated_env(), raw=True, extra_args=["--params-file", str(path)],
              expect_params={"sync_timeout_s": 2.5, "max_tracks": 77, "threshold_brake": 0.6,
                             "image_transport": "raw", "publish_debug_image": True},
              debug_image=True)


def test_markers_one_array_per_answered_frame(tmp_path, rclpy_isolated_env):
    """``publish_markers: true``: each answered frame gives one MarkerArray on
    ~/output/markers, a DELETEALL and then per vehicle its box and ID text in the image's
    frame, blinker arrows and brake bars exactly where the result says ON."""
    from signal_light_node.io.conversions import stamp_to_ns
    from signal_light_node.outputs.vehicle_lights import vehicle_light_array_to_results
    from signal_light_node.outputs.markers import DELETEALL, is_unknown, marker_label

    bag = scene_bag(tmp_path, raw=False)
    image_type, frames = load_frames(bag, 12)
    args, _ = model_args(tmp_path)
    env = rclpy_isolated_env()
    node = DetectorProcess(["-p", "publish_markers:=true", "-p", "image_transport:=compressed",
                            *args, *_RELIABLE], env, tmp_path / "detector.log")
    try:
        node.wait_ready()
        assert "/signal_light_detector/output/markers" in node.text()
        with LiveClient(_domain(env), image_type) as client:
            client.wait_connected()
            assert client.spin_until(lambda: client.node.count_publishers(MARKERS_TOPIC) > 0,
                                     20.0)
            # Markers are built only while someone listens: warm up until they come.
            for k in range(30):
                client.warm_up(frames[0].stamp_ns - k * 10_000_000_000, frames[0].frame_id)
                if client.spin_until(lambda: len(client.markers) > 0, 1.0):
                    break
            assert client.markers, "no MarkerArray for any warm-up frame"
            client.feed(frames)
            assert client.spin_until(
                lambda: all(f.stamp_ns in client.markers for f in frames), 20.0), \
                f"markers for {sum(f.stamp_ns in client.markers for f in frames)} of " \
                f"{len(frames)} frames"
            drawn = 0
            for frame in frames:
                arrays = client.markers[frame.stamp_ns]
                assert len(arrays) == 1, f"{len(arrays)} MarkerArrays for one frame"
                markers = arrays[0].markers
                assert markers[0].action == DELETEALL
                for m in markers:
                    assert m.header.frame_id == frame.frame_id
                    assert stamp_to_ns(m.header.stamp) == frame.stamp_ns
                _, results = vehicle_light_array_to_results(client.outputs[frame.stamp_ns][0])
                visible = [r for r in results if r.roi[2] > 0 and r.roi[3] > 0]
                by_ns = lambda ns: [m for m in markers if m.ns == ns]  # noqa: E731
                assert [m.text for m in by_ns("track_id")] == [marker_label(r) for r in visible]
                assert len(by_ns("box")) == len(visible)
                assert len(by_ns("blinker")) == sum(
                    (r.left.state == 1) + (r.right.state == 1) for r in visible
                    if not is_unknown(r))
                assert len(by_ns("brake")) == sum(r.brake.state == 1 for r in visible
                                                  if not is_unknown(r))
                drawn += len(visible)
            assert drawn > 0, "no vehicle was drawn"
        assert node.stop() == 0, node.text()
        assert "Traceback" not in node.text()
    finally:
        node.stop()


@pytest.mark.parametrize("content", [None, b"not a torch checkpoint"],
                         ids=["missing", "incompatible"])
def test_missing_or_bad_model_stops_with_one_clear_line(tmp_path, rclpy_isolated_env, content):
    missing = tmp_path / "no_such_model.pt"
    if content is not None:
        missing.write_bytes(content)
    code, lines = run_until_exit(["-p", f"model_path:={missing}"], rclpy_isolated_env(), tmp_path)
    assert code != 0
    assert len(lines) == 1, lines
    assert "no_such_model.pt" in lines[0] and "FATAL" in lines[0]


def test_bad_parameter_stops_with_one_clear_line(tmp_path, rclpy_isolated_env):
    code, lines = run_until_exit(["-p", "image_transport:=theora"], rclpy_isolated_env(), tmp_path)
    assert code != 0 and len(lines) == 1, lines
    assert "image_transport" in lines[0] and "raw, compressed" in lines[0]
