"""The layout's rule: only ``signal_light_node/ros/`` may import rclpy or generated ROS messages.

Every module of the package is parsed (not imported) and its imports are checked, so the
test also catches imports inside functions. ``importlib.import_module`` outside ``ros/``
may only load the package's own modules.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path
from typing import Iterator, List, Tuple

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "signal_light_node"

#: Top-level modules that are ROS itself or generated ROS message packages.
ROS_MODULES = ("rclpy", "rosidl_runtime_py", "rosidl_parser", "rmw", "rcl_interfaces",
               "builtin_interfaces", "std_msgs", "sensor_msgs", "geometry_msgs",
               "vision_msgs", "visualization_msgs", "diagnostic_msgs", "lifecycle_msgs",
               "signal_light_msgs", "launch", "launch_ros")


def _is_ros(module: str) -> bool:
    top = module.split(".")[0]
    return top in ROS_MODULES or top.endswith("_msgs") or top.endswith("_interfaces")


def ros_imports(source: str) -> Iterator[Tuple[int, str]]:
    """``(line, module)`` of every ROS import in ``source``, nested ones included."""
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        elif isinstance(node, ast.Call) and _calls_import_module(node):
            arg = node.args[0] if node.args else None
            literal = isinstance(arg, ast.Constant) and isinstance(arg.value, str)
            own = isinstance(arg, ast.JoinedStr) and arg.values \
                and isinstance(arg.values[0], ast.Constant) \
                and str(arg.values[0].value).startswith("signal_light_node.")
            if literal:
                names = [arg.value]
            elif own:
                continue
            else:  # a computed name could be anything, a message module included
                names = ["<computed import_module>"]
                yield node.lineno, names[0]
                continue
        else:
            continue
        for name in names:
            if _is_ros(name):
                yield node.lineno, name


def _calls_import_module(node: ast.Call) -> bool:
    func = node.func
    return (isinstance(func, ast.Attribute) and func.attr == "import_module") \
        or (isinstance(func, ast.Name) and func.id in ("import_module", "__import__"))


def core_violations(package: Path = PACKAGE) -> List[str]:
    """``path:line module`` for every ROS import outside ``ros/``."""
    found = []
    for path in sorted(package.rglob("*.py")):
        if package / "ros" in path.parents:
            continue
        for line, module in ros_imports(path.read_text()):
            found.append(f"{path.relative_to(package.parent)}:{line} {module}")
    return found


def test_only_the_ros_adapter_imports_rclpy_or_messages() -> None:
    assert core_violations() == []


@pytest.mark.parametrize("snippet", [
    "import rclpy",
    "from rclpy.node import Node",
    "def f():\n    from sensor_msgs.msg import Image\n",
    "import signal_light_msgs.msg as m",
    "import importlib\nimportlib.import_module(f'{pkg}.msg')",
    "import importlib\nimportlib.import_module('vision_msgs.msg')",
])
def test_the_check_catches_a_ros_import_in_a_core_module(tmp_path: Path, snippet: str) -> None:
    package = tmp_path / "signal_light_node"
    (package / "runtime").mkdir(parents=True)
    (package / "ros").mkdir()
    (package / "runtime" / "engine.py").write_text(snippet + "\n")
    (package / "ros" / "node.py").write_text(snippet + "\n")  # allowed there
    assert [v.split(":")[0] for v in core_violations(package)] == \
        ["signal_light_node/runtime/engine.py"]


def test_own_dynamic_imports_and_plain_libraries_pass() -> None:
    source = ("import importlib\nimport numpy\nfrom rosbags.typesys import Stores\n"
              "importlib.import_module(f'signal_light_node.commands.{name}')\n")
    assert list(ros_imports(source)) == []


def test_importing_the_core_loads_no_rclpy() -> None:
    """Imported for real in a fresh interpreter: the engine, replay and CLI need no ROS."""
    code = ("import sys; import signal_light_node.runtime.engine, signal_light_node.tools.replay, "
            "signal_light_node.cli, signal_light_node.io.conversions; "
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in "
            f"{ROS_MODULES!r}); print(bad); sys.exit(1 if bad else 0)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
