"""A replay is the node: ``signal-light replay`` and ``evaluate`` run by default what the
node runs by default (backend and precision ``auto``), and say what ran once ``auto`` was
resolved (model file, backend, precision, threads)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Dict, List, Tuple

import pytest
import yaml

from signal_light_node.cli import build_parser, main
from signal_light_node.io import bagio
from signal_light_node.outputs.vehicle_lights import vehicle_light_array_to_results
from signal_light_node.ros.params import NODE_NAME, DetectorParams
from signal_light_node.runtime.backend import ModelRun
from signal_light_node.tools.replay import OUTPUT_TOPIC, replay_bag

REPO = Path(__file__).resolve().parents[1]
DAY_STREET = REPO / "bags" / "day_street"
YAML = REPO / "config" / "detector.yaml"

#: The model line of a replay summary / an evaluation report (``ModelRun.text``).
MODEL_LINE = re.compile(r"^model: (?P<file>\S+), backend (?P<backend>\S+), precision "
                        r"(?P<precision>\S+), device (?P<device>\S+), threads: "
                        r"(?P<threads>.+)$", re.MULTILINE)

needs_bag = pytest.mark.skipif(not (DAY_STREET / "metadata.yaml").exists(),
                               reason="bags/day_street is not committed")


def _cli_args(command: str):
    required = {"replay": ["BAG", "-o", "OUT"], "evaluate": ["--out", "OUT"]}[command]
    return build_parser([command]).parse_args([command, *required])


def _node_engine():
    """The engine the node builds from its default parameters (``DetectorNode.configure``)."""
    from signal_light_node.runtime.engine import engine_from_checkpoint

    p = DetectorParams()
    return engine_from_checkpoint(
        p.model_path or None, device=p.device, backend=p.backend, threads=p.num_threads,
        precision=p.precision, thresholds=p.thresholds, track_timeout_s=p.track_timeout_s,
        max_tracks=p.max_tracks, max_gap_s=p.max_gap_s, intent_filter=p.intent_filter_config,
        max_boxes=p.max_boxes_per_frame)


def _codes(path: Path) -> Dict[int, List[Tuple]]:
    """Per output message (by stamp), each vehicle's track, states and reported codes."""
    out: Dict[int, List[Tuple]] = {}
    with bagio.open_bag(path) as bag:
        for m in bag.messages():
            if m.topic != OUTPUT_TOPIC:
                continue
            stamp, results = vehicle_light_array_to_results(m.msg)
            out[stamp] = [
                (r.track_id, r.intent, r.brake.state, r.left.state, r.right.state, r.view,
                 tuple(code for code, _ in r.classification)) for r in results]
    return out


def _threads(text: str) -> Dict[int, int]:
    """``2 on 80 steps, 1 on 40 steps (...)`` -> {2: 80, 1: 40}."""
    return {int(t): int(n) for t, n in re.findall(r"(\d+) on (\d+) steps", text)}


@pytest.mark.parametrize("command", ["replay", "evaluate"])
def test_cli_model_defaults_are_the_nodes_parameter_defaults(command):
    args = _cli_args(command)
    params = DetectorParams()
    from_yaml = yaml.safe_load(YAML.read_text())[NODE_NAME]["ros__parameters"]
    assert (args.backend, args.precision) == (params.backend, params.precision)
    assert (args.backend, args.precision) == (from_yaml["backend"], from_yaml["precision"])
    assert args.checkpoint is None and params.model_path == ""  # both: the shipped model
    assert args.device == params.device
    assert args.threads is None and params.num_threads == 0  # both: the backend's choice


def test_model_run_text_names_what_ran():
    run = ModelRun("m.onnx", "onnxruntime", "int8", "cpu", most_threads=4,
                   threads_by_load=True)
    run.steps_by_threads.update({1: 3, 4: 7})
    assert run.text() == ("model: m.onnx, backend onnxruntime, precision int8, device cpu, "
                          "threads: 4 on 7 steps, 1 on 3 steps (1 or 4 per step, by the load)")
    fixed = ModelRun("m.pt", "torch", "fp32", "cpu", most_threads=2, last_step_threads=2)
    assert fixed.threads_text() == "2 in the last step"
    assert json.loads(json.dumps(run.as_dict()))["steps_by_threads"] == {"4": 7, "1": 3}


@needs_bag
def test_default_replay_is_the_node_and_names_what_ran(tmp_path, capsys):
    node = _node_engine()
    out = tmp_path / "default"
    assert main(["replay", str(DAY_STREET), "-o", str(out), "--no-progress"]) == 0
    text = capsys.readouterr().out
    line = MODEL_LINE.search(text)
    assert line, text
    # What the node's defaults resolve to, not what the CLI happens to say.
    assert line["file"] == node.backend.source and Path(line["file"]).is_file()
    assert (line["backend"], line["precision"], line["device"]) == (
        node.backend.name, node.backend.precision, node.backend.device)
    images = int(re.search(r"^images: (\d+) ", text, re.MULTILINE)[1])
    threads = _threads(line["threads"])
    assert threads and sum(threads.values()) == images  # every frame of it has boxes
    assert all(t >= 1 for t in threads)

    # Frame by frame, the same codes as the engine the node builds from its defaults.
    replay_bag(DAY_STREET, tmp_path / "node", node, progress=False)
    got, want = _codes(out), _codes(tmp_path / "node")
    assert len(got) == images and list(got) == list(want)
    for stamp, vehicles in want.items():
        assert got[stamp] == vehicles, stamp


@needs_bag
def test_default_evaluate_names_what_ran(tmp_path, capsys):
    node = _node_engine().backend
    out = tmp_path / "eval"
    assert main(["evaluate", "--bags", str(DAY_STREET), "--out", str(out),
                 "--no-progress"]) == 0
    printed = capsys.readouterr().out
    report = json.loads((out / "metrics.json").read_text())["model"]
    assert (report["model_file"], report["backend"], report["precision"], report["device"]) \
        == (node.source, node.name, node.precision, node.device)
    assert report["last_step_threads"] >= 1
    for markdown in (printed, (out / "metrics.md").read_text()):
        line = MODEL_LINE.search(markdown)
        assert line and line["file"] == node.source and line["backend"] == node.name
        assert line["precision"] == node.precision
        assert f"{report['last_step_threads']} in the last step" in line["threads"]
