"""The generated message types import and carry the constants and fields of the schemas."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from signal_light_node.io import bagio
from signal_light_node.labels import LIGHT_CODES, Intent, LightStatus, View

CONSTANTS = {
    "LightClassification": {"BRAKE": 100, "LEFT_BLINKER": 101, "RIGHT_BLINKER": 102},
    "LightState": {"OFF": 0, "ON": 1, "UNKNOWN": 2},
    "VehicleLightState": {
        "INTENT_OFF": 0, "INTENT_LEFT": 1, "INTENT_RIGHT": 2, "INTENT_HAZARD": 3,
        "INTENT_UNKNOWN": 4, "VIEW_BEHIND": 0, "VIEW_LEFT": 1, "VIEW_FRONT": 2, "VIEW_RIGHT": 3,
    },
    "VehicleLightStateArray": {},
}

FIELDS = {
    "LightClassification": {"label": "uint8", "probability": "float"},
    "LightState": {"state": "uint8", "on_probability": "float", "off_probability": "float",
                   "unknown_probability": "float"},
    "VehicleLightState": {
        "track_id": "string", "roi": "sensor_msgs/RegionOfInterest",
        "classification": "sequence<signal_light_msgs/LightClassification>",
        "brake": "signal_light_msgs/LightState", "left_blinker": "signal_light_msgs/LightState",
        "right_blinker": "signal_light_msgs/LightState", "intent": "uint8",
        "intent_probability": "float", "view": "uint8", "view_probability": "float",
        "frames_observed": "uint32",
    },
    "VehicleLightStateArray": {"header": "std_msgs/Header",
                               "vehicles": "sequence<signal_light_msgs/VehicleLightState>"},
}

VISION_FIELDS = {
    "Point2D": {"x": "double", "y": "double"},
    "Pose2D": {"position": "vision_msgs/Point2D", "theta": "double"},
    "BoundingBox2D": {"center": "vision_msgs/Pose2D", "size_x": "double", "size_y": "double"},
    "ObjectHypothesis": {"class_id": "string", "score": "double"},
    "ObjectHypothesisWithPose": {"hypothesis": "vision_msgs/ObjectHypothesis",
                                 "pose": "geometry_msgs/PoseWithCovariance"},
    "Detection2D": {"header": "std_msgs/Header",
                    "results": "sequence<vision_msgs/ObjectHypothesisWithPose>",
                    "bbox": "vision_msgs/BoundingBox2D", "id": "string"},
    "Detection2DArray": {"header": "std_msgs/Header",
                         "detections": "sequence<vision_msgs/Detection2D>"},
}


@pytest.mark.parametrize("name", sorted(CONSTANTS))
def test_rclpy_types_carry_constants_and_fields(name: str) -> None:
    import signal_light_msgs.msg as msgs

    cls = getattr(msgs, name)
    for const, value in CONSTANTS[name].items():
        assert getattr(cls, const) == value, f"{name}.{const}"
    assert cls.get_fields_and_field_types() == FIELDS[name]


def test_vision_msgs_types_match_jazzy_definition() -> None:
    import vision_msgs.msg as vision

    for name, fields in VISION_FIELDS.items():
        assert getattr(vision, name).get_fields_and_field_types() == fields, name


def test_labels_equal_message_constants() -> None:
    from signal_light_msgs.msg import LightClassification, LightState, VehicleLightState

    for status in LightStatus:
        assert getattr(LightState, status.name) == int(status)
    for intent in Intent:
        assert getattr(VehicleLightState, f"INTENT_{intent.name}") == int(intent)
    for view in View:
        assert getattr(VehicleLightState, f"VIEW_{view.name}") == int(view)
    assert LIGHT_CODES == {"brake": LightClassification.BRAKE,
                           "left": LightClassification.LEFT_BLINKER,
                           "right": LightClassification.RIGHT_BLINKER}


@pytest.mark.parametrize("name", sorted(CONSTANTS))
def test_rosbags_types_carry_the_same_constants(name: str) -> None:
    store = bagio.typestore()
    consts, fields = store.fielddefs[f"signal_light_msgs/msg/{name}"]
    assert {c: v for c, _, v in consts} == CONSTANTS[name]
    assert [f for f, _ in fields] == list(FIELDS[name])
    cls = store.types[f"signal_light_msgs/msg/{name}"]
    for const, value in CONSTANTS[name].items():
        assert getattr(cls, const) == value


def _installed_hashes():
    """(type name, RIHS01 hash) from the rosidl build's JSON type descriptions."""
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        for pkg in bagio.SCHEMA_PACKAGES:
            for path in sorted((Path(prefix) / "share" / pkg / "msg").glob("*.json")):
                name = f"{pkg}/msg/{path.stem}"
                for entry in json.loads(path.read_text())["type_hashes"]:
                    if entry["type_name"] == name:
                        yield name, entry["hash_string"]


def test_rosbags_type_hashes_equal_the_rosidl_build() -> None:
    # Same hash = the bag writer's schemas are exactly what rclpy/ros2 bag expect.
    hashes = dict(_installed_hashes())
    if not hashes:
        pytest.skip("no rosidl type descriptions on AMENT_PREFIX_PATH")
    assert any(n.startswith("signal_light_msgs/") for n in hashes)
    store = bagio.typestore()
    for name, expected in hashes.items():
        assert store.hash_rihs01(name) == expected, name
