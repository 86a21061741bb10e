"""The bad-input matrix: damaged, odd or excessive input costs one frame, never the run.

Each case feeds one kind of bad input to the live node (its own process, real rclpy),
to ``replay`` (in-process, with the fake model of ``fake_light_model``) or to start-up,
and asserts: no crash, the documented result or a counted drop, and sane outputs (one
entry per detection with its ID, probabilities finite and summing to 1, codes only
100/101/102). Damaged bags are made here in ``tmp_path``; nothing is committed.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
import pytest

from node_harness import DetectorProcess, run_until_exit, tiny_checkpoint
from signal_light_node.node.params import NODE_NAME

MS = 1_000_000
S = 1_000_000_000
T0 = 1_700_000_000 * S


def check_sane(msg, ids: Sequence[str]) -> None:
    """One entry per detection, IDs kept, probabilities finite and summing to 1, known codes.

    Works on rclpy and rosbags ``VehicleLightStateArray`` messages alike.
    """
    assert [v.track_id for v in msg.vehicles] == list(ids)
    for v in msg.vehicles:
        for light in (v.brake, v.left_blinker, v.right_blinker):
            probs = (light.on_probability, light.off_probability, light.unknown_probability)
            assert all(math.isfinite(p) and 0.0 <= p <= 1.0 for p in probs)
            assert abs(sum(probs) - 1.0) < 1e-3 and light.state in (0, 1, 2)
        assert {c.label for c in v.classification} <= {100, 101, 102}
        assert all(math.isfinite(c.probability) for c in v.classification)
        assert math.isfinite(v.intent_probability) and math.isfinite(v.view_probability)


# ------------------------------------------------------------------------- start-up
def _one_fatal_line(lines: List[str], *words: str) -> None:
    assert len(lines) == 1, lines
    assert "FATAL" in lines[0] and "Traceback" not in lines[0]
    for word in words:
        assert word in lines[0], lines[0]


def test_startup_missing_params_file_is_one_line(tmp_path, rclpy_isolated_env):
    code, lines = run_until_exit(["--params-file", str(tmp_path / "absent.yaml")],
                                 rclpy_isolated_env(), tmp_path)
    assert code == 1
    _one_fatal_line(lines, "bad ROS arguments", "absent.yaml")


def test_startup_bad_remap_rule_is_one_line(tmp_path, rclpy_isolated_env):
    code, lines = run_until_exit(["-r", "no_arrow_here"], rclpy_isolated_env(), tmp_path)
    assert code == 1
    _one_fatal_line(lines, "bad ROS arguments", "remap")


def test_startup_cuda_without_cuda_names_cuda(tmp_path, rclpy_isolated_env):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    model = tiny_checkpoint(tmp_path / "tiny.pt")
    code, lines = run_until_exit(["-p", f"model_path:={model}", "-p", "device:=cuda"],
                                 rclpy_isolated_env(), tmp_path)
    assert code == 1
    _one_fatal_line(lines, "CUDA requested but not available")
    assert "cannot be read as a checkpoint" not in lines[0]


def test_startup_params_file_for_another_node_is_warned(tmp_path, rclpy_isolated_env):
    params = tmp_path / "other.yaml"
    params.write_text("other_node:\n  ros__parameters:\n    max_tracks: 5\n")
    model = tiny_checkpoint(tmp_path / "tiny.pt")
    node = DetectorProcess(["--params-file", str(params), "-p", f"model_path:={model}"],
                           rclpy_isolated_env(), tmp_path / "detector.log")
    try:
        node.wait_ready()
        warned = [line for line in node.text().splitlines() if "other.yaml" in line]
        assert len(warned) == 1 and "WARN" in warned[0] and NODE_NAME in warned[0], warned
    finally:
        assert node.stop() == 0, node.text()


def test_params_file_sections_matching_this_node_are_not_warned(tmp_path):
    from signal_light_node.node.params import foreign_params_file, params_file_paths

    fqn = f"/{NODE_NAME}"
    for key in (NODE_NAME, fqn, "/**", "/*", "/**/" + NODE_NAME):
        path = tmp_path / "p.yaml"
        path.write_text(f"'{key}':\n  ros__parameters:\n    max_tracks: 5\n")
        assert foreign_params_file(str(path), fqn) is None, key
    for key in ("other", "/ns/*", "/signal_light"):
        path.write_text(f"'{key}':\n  ros__parameters:\n    max_tracks: 5\n")
        assert "no section for node" in foreign_params_file(str(path), fqn), key
    assert params_file_paths(["--ros-args", "--params-file", "a.yaml", "-p", "x:=1",
                              "--params-file", "b.yaml"]) == ["a.yaml", "b.yaml"]


def test_engine_from_checkpoint_without_cuda_names_cuda(tmp_path):
    import torch

    from signal_light_node.engine import engine_from_checkpoint
    from signal_light_node.errors import ConfigError

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    with pytest.raises(ConfigError, match="CUDA requested but not available"):
        engine_from_checkpoint(str(tiny_checkpoint(tmp_path / "tiny.pt")), device="cuda")
