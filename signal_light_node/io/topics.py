"""Topic and message type names that the tools, bags and node share.

The one place these strings are spelled out; everything that reads or writes bags, or
talks to the node from outside, imports them from here. This module never imports
rclpy.

Three kinds of names:

* message type names, in the full ``pkg/msg/Name`` form that bags and
  :func:`signal_light_node.ros.ros_io.message_class` use;
* the topics of the synthetic bags (:mod:`signal_light_node.synth.bag`): a camera with
  a tracker, plus the ground truth;
* the node's topics as seen from outside under its default name
  ``signal_light_detector``. Inside the node they are private (``~/input/image`` ...,
  see :mod:`signal_light_node.ros.detector_node`) and usually remapped. With several
  cameras each camera's topics sit under its name (:func:`camera_topic`:
  ``~/front/input/image``, ``/signal_light_detector/front/output/vehicle_lights``).
"""

from __future__ import annotations

import re
from typing import Optional, Sequence, Tuple

# ----------------------------------------------------------------------- message types

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
#: Image types in order of preference when a tool picks an image topic by itself.
IMAGE_TYPES: Tuple[str, str] = (COMPRESSED_TYPE, IMAGE_TYPE)
DETECTIONS_TYPE = "vision_msgs/msg/Detection2DArray"
#: The node's output, and the ground truth of the synthetic bags.
VEHICLE_LIGHTS_TYPE = "signal_light_msgs/msg/VehicleLightStateArray"
DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
#: The node's optional RViz drawing of its results.
MARKER_ARRAY_TYPE = "visualization_msgs/msg/MarkerArray"

# ------------------------------------------------------------------ synthetic bags

CAMERA_IMAGE_TOPIC = "/camera/image_raw"
CAMERA_COMPRESSED_TOPIC = "/camera/image_raw/compressed"
TRACKED_OBJECTS_TOPIC = "/camera/tracked_objects"
#: Ground-truth ``VehicleLightStateArray``: one entry per detection, probability 1.
GROUND_TRUTH_TOPIC = "/ground_truth/vehicle_lights"

# ------------------------------------------------------- the node, seen from outside

INPUT_IMAGE_TOPIC = "/signal_light_detector/input/image"
INPUT_COMPRESSED_TOPIC = "/signal_light_detector/input/image/compressed"
INPUT_DETECTIONS_TOPIC = "/signal_light_detector/input/detections"
#: Where the node publishes its results (and where ``signal-light replay`` writes them).
OUTPUT_TOPIC = "/signal_light_detector/output/vehicle_lights"
#: The results drawn for RViz (``publish_markers``; ``signal-light replay --markers``).
MARKERS_TOPIC = "/signal_light_detector/output/markers"
#: The annotated frame (``publish_debug_image``).
DEBUG_IMAGE_TOPIC = "/signal_light_detector/output/debug/image"
DIAGNOSTICS_TOPIC = "/diagnostics"

#: The node's namespace of private topics under its default name.
NODE_TOPIC_PREFIX = "/signal_light_detector/"

_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")


def camera_name_problem(names: Sequence[object]) -> Optional[str]:
    """Why a list of camera names is unusable, in one line, or None when it is fine.

    Each name becomes one token of the node's topic names (``~/<camera>/input/image``), so
    it must be a ROS name token (as rcl checks it): letters, digits and underscores, not
    starting with a digit; names must be unique.

    Args:
        names: The camera names (the node's ``cameras``, replay's ``--camera`` names).
    """
    seen = set()
    for name in names:
        if not isinstance(name, str):
            return f"camera names must be strings, got {name!r}"
        if not _TOKEN.match(name):
            return (f"camera name {name!r} is not a ROS topic token (letters, digits and "
                    "underscores, not starting with a digit)")
        if name in seen:
            return f"camera name {name!r} is given twice; names must be unique"
        seen.add(name)
    return None


def camera_topic(topic: str, camera: str) -> str:
    """A node topic name of one camera: ``camera`` inserted after the node's namespace.

    ``~/output/vehicle_lights`` -> ``~/front/output/vehicle_lights`` (inside the node),
    ``/signal_light_detector/output/markers`` ->
    ``/signal_light_detector/front/output/markers`` (seen from outside); an empty
    ``camera`` (the single-camera node) leaves the name as it is.

    Args:
        topic: A private (``~/...``) or outside (``/signal_light_detector/...``) name.
        camera: The camera's name, or "".

    Raises:
        ValueError: ``topic`` is neither.
    """
    if not camera:
        return topic
    for prefix in ("~/", NODE_TOPIC_PREFIX):
        if topic.startswith(prefix):
            return f"{prefix}{camera}/{topic[len(prefix):]}"
    raise ValueError(f"{topic!r} is not one of the node's topics (~/... or {NODE_TOPIC_PREFIX}...)")
