"""Build script of signal_light_node (ament_python); setup.cfg places the executables for ros2 run."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "signal_light_node"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={PACKAGE: ["weights/*.pt", "weights/*.onnx"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    description="Online vehicle light-state perception node for ROS 2 Jazzy",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "detector = signal_light_node.ros.detector_node:main",
            "detector_lifecycle = signal_light_node.ros.lifecycle_node:main",
            "signal-light = signal_light_node.cli:main",
        ],
    },
)
