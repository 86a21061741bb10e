"""Launch the signal_light_detector with its parameters file and the usual remaps.

Native ROS 2 installs only (``ros2 launch`` needs the ``launch`` packages, which are not
on PyPI)::

    ros2 launch signal_light_node detector.launch.py \
        image:=/camera/front/image_raw/compressed detections:=/perception/tracks \
        image_transport:=compressed

Arguments: ``params_file`` (default: the package's ``config/detector.yaml``), ``image``,
``detections``, ``output`` (topics the node's ``~/input/image[/compressed]``,
``~/input/detections`` and ``~/output/vehicle_lights`` are remapped to),
``image_transport`` (``raw`` | ``compressed``; picks which image input is remapped and
overrides the file's value), ``lifecycle`` (``true`` starts the lifecycle variant
``detector_lifecycle``, which waits unconfigured for its transitions), ``namespace`` and
``log_level``.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import LifecycleNode, Node

PACKAGE = "signal_light_node"
NODE_NAME = "signal_light_detector"

#: (argument, default, description); image_transport is also passed as a parameter.
ARGUMENTS = (
    ("params_file", os.path.join(get_package_share_directory(PACKAGE), "config", "detector.yaml"),
     "parameters file of the detector"),
    ("image", "/camera/image_raw", "camera image topic (raw or compressed, see image_transport)"),
    ("detections", "/perception/object_recognition/detection/tracked_boxes",
     "vision_msgs/Detection2DArray of tracked boxes (Detection2D.id = track ID)"),
    ("output", "~/output/vehicle_lights", "where the VehicleLightStateArray is published"),
    ("image_transport", "raw", "raw (sensor_msgs/Image) or compressed (CompressedImage)"),
    ("lifecycle", "false", "true: start the lifecycle node (configure/activate it yourself)"),
    ("namespace", "", "namespace of the node"),
    ("log_level", "info", "ROS log level"),
)


def generate_launch_description() -> LaunchDescription:
    """The detector (plain or lifecycle) with the params file, remaps and overrides."""
    config = {name: LaunchConfiguration(name) for name, _, _ in ARGUMENTS}
    compressed = PythonExpression(["'", config["image_transport"], "' == 'compressed'"])
    image_input = PythonExpression(["'~/input/image/compressed' if ", compressed,
                                    " else '~/input/image'"])
    common = dict(
        package=PACKAGE, name=NODE_NAME, namespace=config["namespace"], output="screen",
        parameters=[config["params_file"], {"image_transport": config["image_transport"]}],
        remappings=[(image_input, config["image"]),
                    ("~/input/detections", config["detections"]),
                    ("~/output/vehicle_lights", config["output"])],
        arguments=["--ros-args", "--log-level", config["log_level"]],
    )
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=text)
         for name, default, text in ARGUMENTS]
        + [Node(executable="detector", condition=UnlessCondition(config["lifecycle"]), **common),
           LifecycleNode(executable="detector_lifecycle",
                         condition=IfCondition(config["lifecycle"]), **common)])
