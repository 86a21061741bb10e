"""The layout's rules, checked on the source (every module parsed, not imported, so imports
inside functions count too):

* only ``signal_light_node/ros/`` may import rclpy or generated ROS messages
  (``importlib.import_module`` outside ``ros/`` may only load the package's own modules);
* no import circle among the package's modules (:func:`import_cycles`);
* the layers (:data:`LAYERS`, also in ``docs/ARCHITECTURE.md``): a module imports its own
  layer and those below, never one above (:func:`layer_violations`).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from collections import deque
from pathlib import Path
from typing import Dict, FrozenSet, Iterator, List, Optional, Set, Tuple

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


# ------------------------------------------------------------------ the import graph
#: ``{module: {imported module: line of the first such import}}``, module names dotted
#: from the package (``signal_light_node.runtime.engine``).
Graph = Dict[str, Dict[str, int]]


def package_modules(package: Path = PACKAGE) -> Dict[str, Path]:
    """Every module of the package by dotted name (a package by its ``__init__.py``)."""
    modules = {}
    for path in sorted(package.rglob("*.py")):
        parts = list(path.relative_to(package.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        modules[".".join(parts)] = path
    return modules


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _import_nodes(tree: ast.AST) -> Iterator[ast.AST]:
    """Every import statement and call of the tree, at any depth, except the bodies of
    ``if TYPE_CHECKING:`` (annotations only: they never run, so they load nothing and
    can close no circle)."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            stack.extend(node.orelse)
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom, ast.Call)):
            yield node
        stack.extend(ast.iter_child_nodes(node))


def _deepest_module(name: str, modules: Dict[str, Path]) -> Optional[str]:
    """``name`` itself when it is a module, else its closest enclosing one (an attribute
    imported from a module is that module)."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def _imported_modules(node: ast.AST, module: str, modules: Dict[str, Path]) -> List[str]:
    """The package's modules ``node`` imports (relative imports resolved; ``from X import
    a`` is ``X.a`` when that is a module, else ``X``)."""
    root = module.split(".")[0]
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    elif isinstance(node, ast.ImportFrom):
        if node.level:
            base = module.split(".")
            if modules[module].name != "__init__.py":
                base.pop()  # a module's level 1 is its package
            base = base[:len(base) - node.level + 1]
            target = ".".join(base + ([node.module] if node.module else []))
        else:
            target = node.module or ""
        names = [f"{target}.{a.name}" if f"{target}.{a.name}" in modules else target
                 for a in node.names]
    elif isinstance(node, ast.Call) and _calls_import_module(node) and node.args \
            and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str):
        names = [node.args[0].value]  # only a literal name can be followed
    else:
        return []
    found = [_deepest_module(n, modules) for n in names if n.split(".")[0] == root]
    return sorted({f for f in found if f})


def import_graph(package: Path = PACKAGE, implicit: bool = True) -> Graph:
    """The package's module import graph, read from the source.

    Args:
        package: The package directory.
        implicit: Also the imports Python makes on the way: importing ``a.b.c`` runs the
            ``__init__`` of ``a.b`` (and ``a``), so those packages are imported too
            (except the importer's own enclosing packages, which are loaded already).
    """
    modules = package_modules(package)
    graph: Graph = {}
    for module, path in modules.items():
        edges: Dict[str, int] = {}
        own = {module.rsplit(".", k)[0] for k in range(module.count(".") + 1)}
        for node in _import_nodes(ast.parse(path.read_text())):
            for target in _imported_modules(node, module, modules):
                parts = target.split(".")
                implied = [".".join(parts[:k]) for k in range(1, len(parts))] if implicit \
                    else []
                for name in [target] + [p for p in implied if p not in own]:
                    if name != module:
                        edges[name] = min(edges.get(name, node.lineno), node.lineno)
        graph[module] = edges
    return graph


def _strong_components(graph: Graph) -> List[List[str]]:
    """Tarjan's strongly connected components (iterative), those with a circle only."""
    index: Dict[str, int] = {}
    low: Dict[str, int] = {}
    on_stack: Set[str] = set()
    stack: List[str] = []
    found: List[List[str]] = []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is None:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
            elif child not in graph:
                continue
            elif child not in index:
                index[child] = low[child] = counter
                counter += 1
                stack.append(child)
                on_stack.add(child)
                work.append((child, iter(sorted(graph[child]))))
            elif child in on_stack:
                low[node] = min(low[node], index[child])
    return found


def _one_cycle(graph: Graph, component: List[str]) -> List[str]:
    """A shortest circle through the component's first module, as a path back to it."""
    start, members = component[0], set(component)
    parent: Dict[str, str] = {}
    queue = deque([start])
    while queue:
        node = queue.popleft()
        for child in sorted(graph[node]):
            if child == start:
                path = [node]
                while path[-1] != start:
                    path.append(parent[path[-1]])
                return list(reversed(path)) + [start]
            if child in members and child not in parent:
                parent[child] = node
                queue.append(child)
    return component  # pragma: no cover - a component always has a circle


def import_cycles(package: Path = PACKAGE) -> List[Tuple[FrozenSet[str], str]]:
    """Every import circle as ``(its modules, one circle written out)``: each strongly
    connected set of modules, one per set, e.g. ``a (line 3) -> b (line 9) -> a``."""
    graph = import_graph(package)
    cycles = []
    for component in _strong_components(graph):
        path = _one_cycle(graph, component)
        text = " -> ".join(f"{a} (line {graph[a][b]})" for a, b in zip(path, path[1:]))
        cycles.append((frozenset(component), f"{text} -> {path[-1]}"))
    return cycles


#: Circles known and scheduled to go, with the work that removes them. Only ever shrinks:
#: the test fails on any other circle, and on an entry here that is no longer a circle.
KNOWN_CYCLES: Dict[FrozenSet[str], str] = {}


def test_no_import_circle_in_the_package() -> None:
    cycles = import_cycles()
    new = [text for members, text in cycles if members not in KNOWN_CYCLES]
    assert not new, "import circles:\n" + "\n".join(new)
    gone = [why for members, why in KNOWN_CYCLES.items()
            if members not in {m for m, _ in cycles}]
    assert not gone, f"no longer a circle, remove it from KNOWN_CYCLES: {gone}"


# ------------------------------------------------------------------ the layers
#: The package's layers, bottom first. A module may import modules of its own layer and
#: of the layers below, never of one above. Entries are module prefixes under the package
#: ("" = the package itself); a module is in the layer of its longest matching prefix.
#: Why this order (what the code needs):
#:
#: * vocabulary: ``labels``, ``errors``, ``boxes`` and the package's ``__version__``.
#: * io: bags, image <-> array, detection messages <-> boxes, topic names.
#: * runtime contracts: the runtime modules the model side builds on: the backend
#:   protocol (the backends implement it), the crop code and ``CropConfig`` (a
#:   ``ModelConfig`` holds one; the data side cuts crops with it), the result types and
#:   the allocator setting (the torch backend applies it).
#: * model: networks, checkpoints, ONNX, the backends and their registry.
#: * runtime: pairing, queues, state bank, intent filter, engine (it creates backends
#:   through the registry).
#: * outputs: the messages built from results (result array, markers, debug image).
#: * evaluation: tracks, metrics, the track scorer, streaming evaluation (steps a
#:   backend through the runtime's intent filter), the ideal observer.
#: * scenes and data: the two scene generators (their bags' ground truth is the result
#:   message) and the training streams and splits (rendered by ``synth``).
#: * training: the trainer (sources, loops, validation with ``evaluation``).
#: * tools: replay, benchmarks, demo report, calibration, video (library code of the
#:   front ends; never imported by training or the node).
#: * ros: the node and the ROS bodies of ``play`` / ``record`` (rclpy only here).
#: * commands: the ``signal-light`` CLI, on top of everything (``play`` / ``record`` run
#:   ``ros/``'s bodies).
LAYERS: Tuple[Tuple[str, Tuple[str, ...]], ...] = (
    ("vocabulary", ("", "labels", "errors", "boxes")),
    ("io", ("io",)),
    ("runtime contracts", ("runtime.backend", "runtime.crops", "runtime.results",
                           "runtime.memory")),
    ("model", ("model",)),
    ("runtime", ("runtime",)),
    ("outputs", ("outputs",)),
    ("evaluation", ("evaluation",)),
    ("scenes and data", ("synth", "evalgen", "data")),
    ("training", ("training",)),
    ("tools", ("tools",)),
    ("ros", ("ros",)),
    ("commands", ("commands", "cli")),
)


def layer_of(module: str, root: str = PACKAGE.name,
             layers: Tuple[Tuple[str, Tuple[str, ...]], ...] = LAYERS) -> Optional[int]:
    """Index in ``layers`` of ``module`` (dotted, from the package), None when in none."""
    rel = module[len(root) + 1:] if module.startswith(root + ".") else \
        ("" if module == root else None)
    if rel is None:
        return None
    best: Tuple[int, Optional[int]] = (-1, None)
    for i, (_, prefixes) in enumerate(layers):
        for prefix in prefixes:
            if (rel == prefix or (prefix and rel.startswith(prefix + "."))) \
                    and len(prefix) > best[0]:
                best = (len(prefix), i)
    return best[1]


def layer_violations(package: Path = PACKAGE,
                     layers: Tuple[Tuple[str, Tuple[str, ...]], ...] = LAYERS) -> List[str]:
    """``path:line module (layer) imports module (higher layer)`` for every upward import,
    and every module that is in no layer."""
    root = package.name
    modules = package_modules(package)
    found = []
    for module, edges in import_graph(package, implicit=False).items():
        mine = layer_of(module, root, layers)
        where = modules[module].relative_to(package.parent)
        if mine is None:
            found.append(f"{where}: {module} is in no layer of LAYERS")
            continue
        for target, line in sorted(edges.items(), key=lambda e: e[1]):
            theirs = layer_of(target, root, layers)
            if theirs is not None and theirs > mine:
                found.append(f"{where}:{line} {module} ({layers[mine][0]}) imports {target} "
                             f"({layers[theirs][0]}, a higher layer)")
    return found


def test_no_module_imports_a_higher_layer() -> None:
    found = layer_violations()
    assert not found, "imports against the layers (LAYERS):\n" + "\n".join(found)


def test_every_layer_entry_names_a_module() -> None:
    modules = package_modules()
    root = PACKAGE.name
    for name, prefixes in LAYERS:
        for prefix in prefixes:
            full = f"{root}.{prefix}" if prefix else root
            assert full in modules, f"layer {name}: {full} is not a module or package"


def test_the_layers_in_the_docs_are_the_tests() -> None:
    """docs/ARCHITECTURE.md's layer table lists the layers of :data:`LAYERS`, in order."""
    text = (PACKAGE.parent / "docs" / "ARCHITECTURE.md").read_text()
    section = text.split("\n## Layers\n", 1)[1].split("\n## ", 1)[0]
    rows = [line.split("|")[1].strip() for line in section.splitlines()
            if line.startswith("| ") and not line.startswith(("| layer ", "| ---"))]
    assert rows == [name for name, _ in LAYERS]


# ------------------------------------------------------------------ the checks, checked
def _package(tmp_path: Path, files: Dict[str, str]) -> Path:
    package = tmp_path / "signal_light_node"
    for rel, text in files.items():
        path = package / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        for parent in path.relative_to(package).parents:
            (package / parent / "__init__.py").touch()
        path.write_text(text)
    return package


def test_a_circle_through_a_function_level_and_a_relative_import_is_found(tmp_path) -> None:
    package = _package(tmp_path, {
        "runtime/engine.py": "from .state_bank import StateBank\n",
        "runtime/state_bank.py": ("import numpy\n\ndef f():\n"
                                  "    from signal_light_node.runtime import engine\n"),
        "runtime/results.py": "from signal_light_node.runtime.engine import x\n",
    })
    (members, text), = import_cycles(package)
    assert members == {"signal_light_node.runtime.engine", "signal_light_node.runtime.state_bank"}
    assert text == ("signal_light_node.runtime.engine (line 1) -> "
                    "signal_light_node.runtime.state_bank (line 4) -> "
                    "signal_light_node.runtime.engine")


def test_a_circle_through_a_package_init_is_found_and_type_checking_is_not_one(tmp_path):
    package = _package(tmp_path, {
        "model/__init__.py": "from signal_light_node.model.checkpoint import load\n",
        "model/checkpoint.py": "import signal_light_node.runtime.engine\n",
        "model/config.py": "x = 1\n",
        "runtime/engine.py": "def f():\n    from signal_light_node.model.config import x\n",
        "io/bagio.py": ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                        "    from signal_light_node.io.topics import T\n"),
        "io/topics.py": "from signal_light_node.io.bagio import B\n",
    })
    (members, text), = import_cycles(package)
    assert members == {"signal_light_node.model", "signal_light_node.model.checkpoint",
                       "signal_light_node.runtime.engine"}
    assert text == ("signal_light_node.model (line 1) -> signal_light_node.model.checkpoint "
                    "(line 1) -> signal_light_node.runtime.engine (line 2) -> "
                    "signal_light_node.model")


@pytest.mark.parametrize("source, upward", [
    ("from signal_light_node.tools.replay import replay_bag\n", True),
    ("def f():\n    import signal_light_node.training.loop\n", True),
    ("import importlib\nimportlib.import_module('signal_light_node.ros.params')\n", True),
    ("from ..outputs import output_adapters\n", True),
    ("from signal_light_node.model.backends.registry import as_backend\n", False),
    ("from signal_light_node.runtime.crops import CropConfig\n", False),
    ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
     "    from signal_light_node.tools.replay import R\n", False),
])
def test_the_layer_check_catches_an_upward_import(tmp_path, source, upward) -> None:
    package = _package(tmp_path, {
        "runtime/engine.py": source, "runtime/crops.py": "", "tools/replay.py": "",
        "training/loop.py": "", "ros/params.py": "", "outputs/__init__.py": "",
        "model/backends/registry.py": "",
    })
    found = layer_violations(package)
    assert bool(found) == upward, found
    if upward:
        assert found[0].startswith("signal_light_node/runtime/engine.py:")
        assert "signal_light_node.runtime.engine (runtime) imports" in found[0]


def test_a_module_in_no_layer_is_reported(tmp_path) -> None:
    package = _package(tmp_path, {"plugins/extra.py": ""})
    assert layer_violations(package) == [
        "signal_light_node/plugins/__init__.py: signal_light_node.plugins is in no layer of "
        "LAYERS",
        "signal_light_node/plugins/extra.py: signal_light_node.plugins.extra is in no layer "
        "of LAYERS"]
