"""``launch/detector.launch.py`` imports and names only things that exist.

ROS launch is not installable from PyPI, so the launch packages are replaced by small
recording stand-ins: the file is imported and run as ``ros2 launch`` would, and what it
asks for (executables, parameters, remapped topics, the params file) is checked against
the package. Substitutions are evaluated the way launch would, for given arguments.
"""

from __future__ import annotations

import importlib.util
import re
import sys
import types
from pathlib import Path
from typing import Any, Dict, List

import pytest

from signal_light_node.ros.params import NODE_NAME, DetectorParams

REPO = Path(__file__).resolve().parents[1]
LAUNCH_FILE = REPO / "launch" / "detector.launch.py"


class _Recorded:
    """Stand-in for a launch class: keeps its arguments."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args, self.kwargs = args, kwargs


class LaunchConfiguration(_Recorded):
    def evaluate(self, values: Dict[str, str]) -> str:
        return values[self.args[0]]


class PythonExpression(_Recorded):
    def evaluate(self, values: Dict[str, str]) -> str:
        return str(eval("".join(_evaluate(p, values) for p in self.args[0])))  # noqa: S307


class _Condition(_Recorded):
    def holds(self, values: Dict[str, str]) -> bool:
        value = _evaluate(self.args[0], values).lower() == "true"
        return value if isinstance(self, IfCondition) else not value


class IfCondition(_Condition):
    pass


class UnlessCondition(_Condition):
    pass


def _evaluate(item: Any, values: Dict[str, str]) -> str:
    return item if isinstance(item, str) else item.evaluate(values)


def _stub_modules(monkeypatch: pytest.MonkeyPatch) -> None:
    modules = {
        "launch": {"LaunchDescription": type("LaunchDescription", (_Recorded,), {})},
        "launch.actions": {"DeclareLaunchArgument": type("DeclareLaunchArgument",
                                                         (_Recorded,), {})},
        "launch.conditions": {"IfCondition": IfCondition, "UnlessCondition": UnlessCondition},
        "launch.substitutions": {"LaunchConfiguration": LaunchConfiguration,
                                 "PythonExpression": PythonExpression},
        "launch_ros": {},
        "launch_ros.actions": {"Node": type("Node", (_Recorded,), {}),
                               "LifecycleNode": type("LifecycleNode", (_Recorded,), {})},
    }
    for name, attrs in modules.items():
        module = types.ModuleType(name)
        module.__dict__.update(attrs)
        monkeypatch.setitem(sys.modules, name, module)
    # The real ament index (a wheel) knows no share directory of a source checkout.
    packages = pytest.importorskip("ament_index_python.packages")
    monkeypatch.setattr(packages, "get_package_share_directory", lambda package: str(REPO))


@pytest.fixture
def description(monkeypatch: pytest.MonkeyPatch) -> Any:
    _stub_modules(monkeypatch)
    spec = importlib.util.spec_from_file_location("detector_launch", LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.generate_launch_description()


def _arguments(description: Any, **given: str) -> Dict[str, str]:
    values = {a.args[0]: a.kwargs["default_value"] for a in description.args[0]
              if type(a).__name__ == "DeclareLaunchArgument"}
    values.update(given)
    return values


def _started(description: Any, values: Dict[str, str]) -> List[Any]:
    nodes = [a for a in description.args[0] if type(a).__name__ in ("Node", "LifecycleNode")]
    return [n for n in nodes if n.kwargs["condition"].holds(values)]


def _entry_points() -> List[str]:
    text = (REPO / "setup.py").read_text()
    return re.findall(r'"(\w+) = signal_light_node\.', text)


@pytest.mark.parametrize("lifecycle,executable", [("false", "detector"),
                                                  ("true", "detector_lifecycle")])
def test_one_node_starts_with_an_existing_executable(description: Any, lifecycle: str,
                                                     executable: str) -> None:
    started = _started(description, _arguments(description, lifecycle=lifecycle))
    assert [n.kwargs["executable"] for n in started] == [executable]
    assert executable in _entry_points()
    node = started[0]
    assert node.kwargs["package"] == "signal_light_node"
    assert node.kwargs["name"] == NODE_NAME


def test_params_file_and_overrides_name_real_parameters(description: Any) -> None:
    values = _arguments(description)
    node = _started(description, values)[0]
    params_file, overrides = node.kwargs["parameters"]
    assert Path(_evaluate(params_file, values)) == REPO / "config" / "detector.yaml"
    assert Path(_evaluate(params_file, values)).is_file()
    assert "config/*.yaml" in (REPO / "setup.py").read_text()  # installed where it looks
    known = set(DetectorParams().as_dict())
    assert set(overrides) <= known


@pytest.mark.parametrize("transport,image_input", [("raw", "~/input/image"),
                                                   ("compressed", "~/input/image/compressed")])
def test_remaps_use_the_nodes_topics(description: Any, transport: str, image_input: str) -> None:
    pytest.importorskip("rclpy")
    from signal_light_node.ros import detector_node

    values = _arguments(description, image_transport=transport, image="/cam/x")
    node = _started(description, values)[0]
    remaps = {_evaluate(a, values): _evaluate(b, values) for a, b in node.kwargs["remappings"]}
    assert remaps[image_input] == "/cam/x"
    node_topics = {detector_node.IMAGE_TOPIC, detector_node.COMPRESSED_TOPIC,
                   detector_node.DETECTIONS_TOPIC, detector_node.OUTPUT_TOPIC}
    assert set(remaps) <= node_topics
    assert _evaluate(node.kwargs["parameters"][1]["image_transport"], values) == transport


def test_launch_directory_is_installed() -> None:
    assert "launch/*.launch.py" in (REPO / "setup.py").read_text()
