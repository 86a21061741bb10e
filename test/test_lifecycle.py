"""The lifecycle detector (``detector_lifecycle``) driven over its lifecycle services.

The node runs in its own process; this test is the lifecycle manager: it asks for each
transition through ``~/change_state`` and checks the state (``~/get_state``) and what the
node then does on the graph: no topics before activate, frames answered while active,
nothing taken while inactive, track states kept across deactivate/activate, a failed
configure that leaves the node unconfigured and alive.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest

from node_harness import (OUTPUT_TOPIC, DetectorProcess, LiveClient, load_frames, model_args,
                          scene_bag)

rclpy = pytest.importorskip("rclpy")

from lifecycle_msgs.msg import State, Transition  # noqa: E402
from lifecycle_msgs.srv import ChangeState, GetState  # noqa: E402

NODE = "/signal_light_detector"
_RELIABLE = ["-p", "reliability:=reliable"]


class Manager:
    """Calls the node's lifecycle services from a test client."""

    def __init__(self, client: LiveClient) -> None:
        self.client = client
        self.change = client.node.create_client(ChangeState, f"{NODE}/change_state")
        self.get = client.node.create_client(GetState, f"{NODE}/get_state")
        assert client.spin_until(lambda: self.change.service_is_ready()
                                 and self.get.service_is_ready(), 30.0), "no lifecycle services"

    def _call(self, service: Any, request: Any) -> Any:
        future = service.call_async(request)
        assert self.client.spin_until(future.done, 60.0), "lifecycle service did not answer"
        return future.result()

    def state(self) -> int:
        return self._call(self.get, GetState.Request()).current_state.id

    def transition(self, transition_id: int) -> bool:
        request = ChangeState.Request(transition=Transition(id=transition_id))
        return self._call(self.change, request).success


def _input_subscribers(client: LiveClient) -> int:
    return client.image_pub.get_subscription_count() + client.det_pub.get_subscription_count()


def _settles(client: LiveClient, condition, timeout: float = 10.0) -> bool:
    """True once ``condition()`` holds (graph changes take a moment to be seen)."""
    return client.spin_until(condition, timeout)


def test_transitions_over_the_lifecycle_services(tmp_path: Path, rclpy_isolated_env) -> None:
    env = rclpy_isolated_env()
    image_type, frames = load_frames(scene_bag(tmp_path, raw=True, n_frames=12), 12)
    args, _ = model_args(tmp_path)
    node = DetectorProcess([*args, *_RELIABLE], env, tmp_path / "lifecycle.log",
                           executable="detector_lifecycle")
    try:
        node.wait_ready(line="waiting for the configure transition")
        with LiveClient(int(env["ROS_DOMAIN_ID"]), image_type) as client:
            manager = Manager(client)
            assert manager.state() == State.PRIMARY_STATE_UNCONFIGURED
            assert client.node.count_publishers(OUTPUT_TOPIC) == 0

            assert manager.transition(Transition.TRANSITION_CONFIGURE)
            assert manager.state() == State.PRIMARY_STATE_INACTIVE
            assert "model " in node.text()  # loaded at configure
            assert _input_subscribers(client) == 0  # but no topics yet

            assert manager.transition(Transition.TRANSITION_ACTIVATE)
            assert manager.state() == State.PRIMARY_STATE_ACTIVE
            client.wait_connected()
            client.warm_up(frames[0].stamp_ns, frames[0].frame_id)
            client.feed(frames[:6])

            assert manager.transition(Transition.TRANSITION_DEACTIVATE)
            assert manager.state() == State.PRIMARY_STATE_INACTIVE
            assert _settles(client, lambda: _input_subscribers(client) == 0
                            and client.node.count_publishers(OUTPUT_TOPIC) == 0)
            client.image_pub.publish(frames[6].image)  # nobody takes it
            client.det_pub.publish(frames[6].detections)
            client.spin_until(lambda: False, 1.0)
            assert frames[6].stamp_ns not in client.outputs

            assert manager.transition(Transition.TRANSITION_ACTIVATE)
            client.wait_connected()
            # Diagnostics right after re-activation: the tracks of the first half are kept.
            n_diag = len(client.diagnostics)
            assert client.spin_until(lambda: len(client.diagnostics) > n_diag, 10.0)
            values = {kv.key: kv.value for kv in client.diagnostics[-1].status[0].values}
            assert int(values["active_tracks"]) == len(frames[5].track_ids) > 0
            client.feed(frames[7:])
            # Frame 6, published while inactive, is no middleware loss (the numbers of the
            # publishers running when it subscribed again start afresh).
            n_diag = len(client.diagnostics)
            assert client.spin_until(lambda: len(client.diagnostics) > n_diag, 10.0)
            values = {kv.key: kv.value for kv in client.diagnostics[-1].status[0].values}
            assert values["dropped_image_middleware"] == "0", values
            assert values["dropped_detections_middleware"] == "0", values
            assert "2 publisher(s) already running" in values["middleware_drops_counted"]

            assert manager.transition(Transition.TRANSITION_DEACTIVATE)
            assert manager.transition(Transition.TRANSITION_CLEANUP)
            assert manager.state() == State.PRIMARY_STATE_UNCONFIGURED
            assert manager.transition(Transition.TRANSITION_CONFIGURE)  # loads again
            assert manager.transition(Transition.TRANSITION_INACTIVE_SHUTDOWN)
            assert manager.state() == State.PRIMARY_STATE_FINALIZED
        assert node.stop() == 0, node.text()
        assert "Traceback" not in node.text()
    finally:
        node.stop()


def test_failed_configure_leaves_the_node_unconfigured(tmp_path: Path,
                                                       rclpy_isolated_env) -> None:
    env = rclpy_isolated_env()
    node = DetectorProcess(["-p", f"model_path:={tmp_path / 'missing.pt'}"], env,
                           tmp_path / "lifecycle.log", executable="detector_lifecycle")
    try:
        node.wait_ready(line="waiting for the configure transition")
        with LiveClient(int(env["ROS_DOMAIN_ID"]), "sensor_msgs/msg/Image") as client:
            manager = Manager(client)
            assert not manager.transition(Transition.TRANSITION_CONFIGURE)
            assert manager.state() == State.PRIMARY_STATE_UNCONFIGURED
            deadline = time.monotonic() + 5
            while "cannot configure" not in node.text() and time.monotonic() < deadline:
                time.sleep(0.05)
            errors = [line for line in node.text().splitlines() if "cannot configure" in line]
            assert len(errors) == 1 and "missing.pt" in errors[0], node.text()
            assert node.proc.poll() is None
        assert node.stop() == 0, node.text()
        assert "Traceback" not in node.text()
    finally:
        node.stop()
