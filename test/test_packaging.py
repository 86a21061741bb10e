"""The package layout works for both routes: the venv set-up and colcon on a native ROS install."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _colcon(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    colcon = shutil.which("colcon")
    if colcon is None:
        pytest.skip("colcon is not installed in this environment")
    return subprocess.run([colcon, *args], cwd=cwd, capture_output=True, text=True, timeout=300)


def test_colcon_finds_the_packages_but_not_the_vision_msgs_fallback() -> None:
    out = _colcon("list", "--base-paths", ".", "msg_schemas", cwd=REPO)
    assert out.returncode == 0, out.stderr
    names = {line.split()[0] for line in out.stdout.splitlines() if line.strip()}
    assert {"signal_light_node", "signal_light_msgs"} <= names
    # An installed vision_msgs must win on native installs: the fallback is never crawled.
    assert "vision_msgs" not in names


def test_colcon_installs_executables_where_ros2_run_looks(tmp_path: Path) -> None:
    src = tmp_path / "src" / "signal_light_node"
    ignore = shutil.ignore_patterns(".venv", "build", "install", "log", ".git", "bags", "runs", "out",
                                    "__pycache__", "*.egg-info", ".fallback_src", "docs")
    shutil.copytree(REPO, src, ignore=ignore)
    out = _colcon("build", "--base-paths", str(src), "--packages-select", "signal_light_node", cwd=tmp_path)
    assert out.returncode == 0, out.stdout + out.stderr
    lib = tmp_path / "install" / "signal_light_node" / "lib" / "signal_light_node"
    assert (lib / "detector").is_file()
    assert (lib / "signal-light").is_file()
    share = tmp_path / "install" / "signal_light_node" / "share"
    assert (share / "ament_index" / "resource_index" / "packages" / "signal_light_node").is_file()
    assert (share / "signal_light_node" / "package.xml").is_file()


def test_venv_entry_points_exist() -> None:
    bindir = Path(sys.executable).parent
    for exe in ("detector", "signal-light"):
        assert (bindir / exe).is_file() or shutil.which(exe), f"{exe} is not installed"


def test_cli_help_lists_every_subcommand() -> None:
    out = subprocess.run([sys.executable, "-m", "signal_light_node.cli", "--help"], capture_output=True,
                         text=True, timeout=60, env=os.environ.copy())
    assert out.returncode == 0, out.stderr
    for name in ("info", "synth", "train", "evaluate", "replay", "annotate", "play", "record"):
        assert name in out.stdout
