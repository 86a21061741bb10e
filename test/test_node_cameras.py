"""The ``detector`` node with two cameras, in its own process, fed on both cameras' topics.

``cameras: [front, rear]``: every frame of each camera is answered once on that camera's
own ``~/<camera>/output/vehicle_lights`` with its image's header; both cameras carry a
track "1" (different boxes, different lamps, same stamps) that is never mixed up (ROIs
and frames_observed are each camera's own); frames of both cameras share model steps;
a loop of one camera's stream (stamps jumping back) resets only that camera's tracks.
"""

from __future__ import annotations

import numpy as np
import pytest

from node_harness import CamerasClient, DetectorProcess, model_args, run_until_exit
from signal_light_node.boxes import TrackBox

rclpy = pytest.importorskip("rclpy")

MS = 1_000_000
T0 = 1_700_000_000 * 1_000_000_000
CAMERAS = ("front", "rear")
#: Per camera: image size (h, w), frame_id and the box of its track "1" (and one more).
SCENES = {
    "front": ((180, 320), "front_camera", TrackBox("1", 20, 30, 100, 90),
              TrackBox("f", 200, 40, 260, 100)),
    "rear": ((240, 400), "rear_camera", TrackBox("1", 210, 110, 330, 210),
             TrackBox("r", 30, 20, 90, 70)),
}
#: Small extra tracks per frame: they make a step take long enough that the other
#: camera's frames are waiting when it ends, so the node's steps are shared ones.
N_EXTRA = 40


def _boxes(camera: str) -> list:
    """The frame's boxes: track "1", the camera's other track, then the extra ones."""
    (h, w), _, one, other = SCENES[camera]
    extra = [TrackBox(f"x{k}", 4 + (k * 23) % (w - 30), 4 + (k * 37) % (h - 30),
                      28 + (k * 23) % (w - 30), 28 + (k * 37) % (h - 30))
             for k in range(N_EXTRA)]
    return [one, other] + extra


def _image(camera: str, t: int) -> np.ndarray:
    """The camera's frame t: grey road, dark car bodies, the rear camera's brake lamps lit."""
    (h, w), _, one, other = SCENES[camera]
    image = np.full((h, w, 3), 90, np.uint8)
    for box in (one, other):
        image[int(box.y0):int(box.y1), int(box.x0):int(box.x1)] = 40
    if camera == "rear":
        y = int(one.y0 + 0.6 * (one.y1 - one.y0))
        image[y:y + 10, int(one.x0) + 5:int(one.x0) + 20] = (40, 40, 250)
        image[y:y + 10, int(one.x1) - 20:int(one.x1) - 5] = (40, 40, 250)
    image[:, (7 * t) % w] = 120  # something changes from frame to frame
    return image


def _roi(v) -> tuple:
    return (v.roi.x_offset, v.roi.y_offset, v.roi.width, v.roi.height)


def _box_roi(box: TrackBox) -> tuple:
    return (int(box.x0), int(box.y0), int(box.x1 - box.x0), int(box.y1 - box.y0))


def _publish_burst(client: CamerasClient, stamps, cameras=CAMERAS, t0: int = 0) -> None:
    """Both cameras' frames at the same stamps, published back to back (no waiting), so
    the worker finds several cameras' frames pending and judges them in one step."""
    for t, stamp in enumerate(stamps):
        for camera in cameras:
            client.publish(camera, stamp, SCENES[camera][1], _image(camera, t0 + t),
                           _boxes(camera))


def _answered(client: CamerasClient, camera: str, stamps) -> bool:
    return all(stamp in client.outputs[camera] for stamp in stamps)


def _frames_observed(client: CamerasClient, camera: str, stamp: int, track: str) -> int:
    (msg,) = client.outputs[camera][stamp]
    (vehicle,) = [v for v in msg.vehicles if v.track_id == track]
    return vehicle.frames_observed


def test_two_cameras_live(tmp_path, rclpy_isolated_env):
    env = rclpy_isolated_env()
    args, _ = model_args(tmp_path)
    node = DetectorProcess(["-p", "cameras:=[front, rear]", "-p", "reliability:=reliable",
                            "-p", "work_queue_size:=20", "-p", "diagnostics_period_s:=0.2",
                            "-p", "track_timeout_s:=30.0", "-p", "max_tracks:=200",
                            "-p", "publish_debug_image:=true", *args],
                           env, tmp_path / "detector.log")
    try:
        node.wait_ready()
        log = node.text()
        assert "ready: 2 cameras" in log
        for camera in CAMERAS:
            assert f"/signal_light_detector/{camera}/input/image" in log
            assert f"/signal_light_detector/{camera}/output/vehicle_lights" in log
        with CamerasClient(int(env["ROS_DOMAIN_ID"]), CAMERAS) as client:
            client.wait_connected()
            warm = client.warm_up(T0, debug=True)
            stamps = [T0 + t * 100 * MS for t in range(8)]
            _publish_burst(client, stamps)
            assert client.spin_until(lambda: all(_answered(client, c, stamps) for c in CAMERAS),
                                     60.0), node.text()

            for camera in CAMERAS:
                frame_id, boxes = SCENES[camera][1], _boxes(camera)
                for t, stamp in enumerate(stamps):
                    msgs = client.outputs[camera][stamp]
                    assert len(msgs) == 1, f"{camera}: {len(msgs)} outputs at {stamp}"
                    out = msgs[0]
                    assert out.header.frame_id == frame_id
                    assert [v.track_id for v in out.vehicles] == [b.track_id for b in boxes]
                    # each camera's track "1" has that camera's box, never the other's
                    assert [_roi(v) for v in out.vehicles] == [_box_roi(b) for b in boxes]
                    # ... and its own recurrent state: one more frame per frame of its camera
                    assert {v.frames_observed for v in out.vehicles} == {t + 1}
                    assert all(v.view_probability > 0 for v in out.vehicles)  # judged
            # each camera's debug images on its own topic, of its own image size
            from signal_light_node.io.conversions import stamp_to_ns

            def debug_of(camera: str) -> list:
                return [i for i in client.debug_images[camera]
                        if stamp_to_ns(i.header.stamp) in stamps]

            assert client.spin_until(lambda: all(len(debug_of(c)) == len(stamps)
                                                 for c in CAMERAS), 30.0)
            for camera in CAMERAS:
                assert {(i.height, i.width) for i in debug_of(camera)} == {SCENES[camera][0]}
            # the two cameras' "1" are different tracks: different lamps, different outputs
            front, rear = (client.outputs[c][stamps[-1]][0].vehicles[0] for c in CAMERAS)
            assert (front.brake.on_probability, front.left_blinker.on_probability) != \
                (rear.brake.on_probability, rear.left_blinker.on_probability)

            def diag() -> dict:
                return client.diagnostics_values() if client.diagnostics else {}

            judged = 2 * len(stamps)
            assert client.spin_until(lambda: int(diag().get("rear.outputs", 0))
                                     == warm["rear"] + len(stamps), 20.0)
            before = diag()
            assert before["cameras"] == "front, rear"
            for camera in CAMERAS:
                assert int(before[f"{camera}.outputs"]) == warm[camera] + len(stamps)
                assert int(before[f"{camera}.images"]) == warm[camera] + len(stamps)
                assert before[f"{camera}.active_tracks"] == str(2 + N_EXTRA)
                assert int(before[f"{camera}.dropped_work_queue"]) == 0
            # several cameras' frames went through shared model steps
            assert int(before["model_steps"]) < judged, before

            # The rear stream loops (stamps jump back 50 s); the front one goes on.
            loop = [T0 - 50_000 * MS + t * 100 * MS for t in range(3)]
            ahead = [stamps[-1] + (t + 1) * 100 * MS for t in range(3)]
            for t, (rear_stamp, front_stamp) in enumerate(zip(loop, ahead)):
                client.publish("rear", rear_stamp, SCENES["rear"][1], _image("rear", t),
                               _boxes("rear"))
                client.publish("front", front_stamp, SCENES["front"][1], _image("front", 8 + t),
                               _boxes("front"))
            assert client.spin_until(lambda: _answered(client, "rear", loop)
                                     and _answered(client, "front", ahead), 60.0), node.text()
            assert [_frames_observed(client, "rear", s, "1") for s in loop] == [1, 2, 3]
            assert [_frames_observed(client, "front", s, "1") for s in ahead] == [9, 10, 11]
            assert client.spin_until(
                lambda: int(diag().get("rear.outputs", 0)) == warm["rear"] + 11, 20.0)
            after = diag()
            assert int(after["rear.track_resets"]) == int(before["rear.track_resets"]) + 1
            assert after["front.track_resets"] == before["front.track_resets"]
            assert after["front.active_tracks"] == after["rear.active_tracks"] == str(2 + N_EXTRA)
            assert node.proc.poll() is None
        assert node.stop() == 0, node.text()
        assert "Traceback" not in node.text()
    finally:
        node.stop()


def test_bad_camera_names_stop_the_node_with_one_clear_line(tmp_path, rclpy_isolated_env):
    code, lines = run_until_exit(["-p", "cameras:=[front, front]"], rclpy_isolated_env(),
                                 tmp_path)
    assert code != 0 and len(lines) == 1, lines
    assert "cameras" in lines[0] and "twice" in lines[0]


@pytest.mark.parametrize("transport, image", [("raw", "image"),
                                              ("compressed", "image/compressed")])
def test_lifecycle_steps_with_cameras_create_and_remove_every_cameras_topics(
        tmp_path, transport, image):
    """configure/activate/deactivate/activate/cleanup (the lifecycle variant's steps) with
    two cameras: each camera's inputs and outputs exist exactly while active."""
    from signal_light_node.ros.lifecycle_node import LifecycleSignalLightDetector

    args, _ = model_args(tmp_path)
    context = rclpy.Context()
    rclpy.init(context=context, args=["--ros-args", "-p", "cameras:=[front, rear]",
                                      "-p", "publish_markers:=true",
                                      "-p", "publish_debug_image:=true",
                                      "-p", f"image_transport:={transport}", *args])
    try:
        node = LifecycleSignalLightDetector(context=context)
        try:
            def topics(entities) -> set:
                return {e.topic_name for e in entities
                        if e.topic_name.startswith("/signal_light_detector/")}

            node.configure()
            assert topics(node.subscriptions) == set()
            for _ in range(2):
                node.activate()
                assert topics(node.subscriptions) == {
                    f"/signal_light_detector/{c}/input/{what}"
                    for c in ("front", "rear") for what in (image, "detections")}
                assert topics(node.publishers) == {
                    f"/signal_light_detector/{c}/output/{what}" for c in ("front", "rear")
                    for what in ("vehicle_lights", "markers", "debug/image")}
                node.stop()  # the worker ends; the queue is closed
                node._queue.put(("rear", object()))  # refused by the closed queue, counted
                node.deactivate()
                assert topics(node.subscriptions) == topics(node.publishers) == set()
            assert node.counters()["dropped_work_queue"] == 2
            per_camera = dict(node._camera_values())
            assert per_camera["rear.dropped_work_queue"] == "2"
            assert per_camera["front.dropped_work_queue"] == "0"
            node.cleanup()
            assert node.engine is None
        finally:
            node.stop()
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
