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
  see :mod:`signal_light_node.ros.detector_node`) and usually remapped.
"""

from __future__ import annotations

from typing import Tuple

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
DIAGNOSTICS_TOPIC = "/diagnostics"
