"""A VehicleLightStateArray makes a round trip between two processes over real rclpy.

Both ends are subprocesses (rclpy is never initialised inside pytest): the publisher builds
the message with ``outputs.vehicle_lights.vehicle_light_array`` + ``rclpy_make``, the subscriber reads
it back with ``vehicle_light_array_to_results`` and prints it as JSON.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path

import pytest

from signal_light_node.labels import Intent, LightStatus, View
from signal_light_node.runtime.results import LightEstimate, VehicleResult

TOPIC = "/signal_light_test/vehicle_lights"
STAMP_NS = 1_700_000_123_456_789_012
FRAME_ID = "camera_front"

# Probabilities are exact in float32, so the round trip can be compared with ==.
EXPECTED = [
    VehicleResult(
        track_id="car-7", roi=(10, 20, 130, 90),
        brake=LightEstimate(LightStatus.ON, 0.125, 0.75, 0.125),
        left=LightEstimate(LightStatus.ON, 0.25, 0.5, 0.25),
        right=LightEstimate(LightStatus.OFF, 0.875, 0.0625, 0.0625),
        intent=Intent.LEFT, intent_probability=0.625, view=View.BEHIND,
        view_probability=0.9375, classification=((100, 0.75), (101, 0.5)),
        frames_observed=42, judged=True),
    VehicleResult(
        track_id="truck_3", roi=(0, 0, 640, 360),
        brake=LightEstimate.unjudged(), left=LightEstimate.unjudged(),
        right=LightEstimate.unjudged(), intent=Intent.UNKNOWN, intent_probability=0.0,
        view=View.FRONT, view_probability=0.0, classification=(),
        frames_observed=1, judged=False),
]

PUBLISHER = f"""
import sys, time
sys.path.insert(0, {str(Path(__file__).parent)!r})
import rclpy
from test_rclpy_roundtrip import EXPECTED, FRAME_ID, STAMP_NS, TOPIC
from signal_light_node.io.conversions import make_header
from signal_light_node.outputs.vehicle_lights import vehicle_light_array
from signal_light_node.ros.messages import rclpy_make

rclpy.init()
node = rclpy.create_node("roundtrip_publisher")
pub = node.create_publisher(rclpy_make("signal_light_msgs/VehicleLightStateArray").__class__,
                            TOPIC, 10)
msg = vehicle_light_array(make_header(STAMP_NS, FRAME_ID, rclpy_make), EXPECTED, rclpy_make)
deadline = time.monotonic() + float(sys.argv[1])
while time.monotonic() < deadline:  # until the test kills us once the subscriber is done
    pub.publish(msg)
    rclpy.spin_once(node, timeout_sec=0.1)
"""

SUBSCRIBER = """
import json, sys, time
from dataclasses import asdict
import rclpy
from signal_light_msgs.msg import VehicleLightStateArray
from signal_light_node.outputs.vehicle_lights import vehicle_light_array_to_results

received = []
rclpy.init()
node = rclpy.create_node("roundtrip_subscriber")
node.create_subscription(VehicleLightStateArray, sys.argv[1], received.append, 10)
print("ready", flush=True)
deadline = time.monotonic() + float(sys.argv[2])
while not received and time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.1)
if not received:
    sys.exit(3)
msg = received[0]
stamp_ns, results = vehicle_light_array_to_results(msg)
print(json.dumps({"stamp_ns": stamp_ns, "frame_id": msg.header.frame_id,
                  "type": type(msg).__module__ + "." + type(msg).__name__,
                  "results": [asdict(r) for r in results]}))
"""


def test_vehicle_light_array_crosses_process_boundary(tmp_path: Path, rclpy_isolated_env) -> None:
    pytest.importorskip("rclpy")
    env = rclpy_isolated_env()
    (tmp_path / "pub.py").write_text(PUBLISHER)
    (tmp_path / "sub.py").write_text(SUBSCRIBER)
    timeout = 40.0
    sub = subprocess.Popen([sys.executable, str(tmp_path / "sub.py"), TOPIC, str(timeout)],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    pub = subprocess.Popen([sys.executable, str(tmp_path / "pub.py"), str(timeout)], env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        out, err = sub.communicate(timeout=timeout + 20)
    finally:
        pub.kill()
        _, pub_err = pub.communicate(timeout=20)
        if sub.poll() is None:
            sub.kill()
            sub.communicate()
    assert sub.returncode == 0, f"subscriber rc={sub.returncode}\n{err}\npublisher:\n{pub_err}"
    lines = out.strip().splitlines()
    assert lines[0] == "ready"
    got = json.loads(lines[-1])
    assert got["type"].startswith("signal_light_msgs.msg")
    assert got["stamp_ns"] == STAMP_NS
    assert got["frame_id"] == FRAME_ID
    assert got["results"] == json.loads(json.dumps([asdict(r) for r in EXPECTED]))
