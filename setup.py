"""Build script of signal_light_node (ament_python); metadata lives in setup.cfg."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "signal_light_node"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={PACKAGE: ["weights/*.pt"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
    ],
    zip_safe=False,
)
