"""The demo's report: run lengths, input/output accounting, timelines, video and sheet.

The output bag comes from the engine replay (same output topic as the live node), so
these tests need no ROS graph.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from signal_light_node.io.bagio import BagWriter, open_bag
from signal_light_node.tools.demo_report import (OUTPUT_TOPIC, build_report, inspect_inputs,
                                           run_lengths)
from signal_light_node.runtime.engine import engine_from_checkpoint
from signal_light_node.tools.replay import replay_bag
from signal_light_node.synth.bag import write_scene_bag

from node_harness import tiny_checkpoint

N_FRAMES = 10


@pytest.fixture(scope="module")
def replayed(tmp_path_factory):
    root = tmp_path_factory.mktemp("demo_report")
    bag = root / "scene"
    write_scene_bag(bag, seed=4, n_frames=N_FRAMES, width=320, height=180, fps=10.0,
                    n_vehicles=3, lighting="day", night_fraction=0.0)
    engine = engine_from_checkpoint(str(tiny_checkpoint(root / "tiny.pt")))
    out = root / "out"
    replay_bag(bag, out, engine, progress=False)
    return bag, out


def test_run_lengths():
    assert run_lengths([]) == []
    assert run_lengths(["a", "a", "b", "a"]) == [("a", 2), ("b", 1), ("a", 1)]


def test_inspect_finds_the_inputs(replayed):
    bag, _ = replayed
    found = inspect_inputs(bag)
    assert (found.transport, found.image_topic, found.detections_topic, found.frames) == (
        "compressed", "/camera/image_raw/compressed", "/camera/tracked_objects", N_FRAMES)


def test_complete_output_gives_timelines_video_and_sheet(replayed, tmp_path):
    bag, out = replayed
    report = build_report(bag, out, tmp_path)
    assert report.complete
    assert report.frames_in == report.outputs == report.outputs_matched == N_FRAMES
    assert report.entries == report.boxes_in > 0
    with open_bag(bag) as reader:
        ids = {d.id for m in reader.messages(["/camera/tracked_objects"])
               for d in m.msg.detections}
    assert set(report.timelines) == ids
    for tl in report.timelines.values():
        assert len(tl.brake) == len(tl.left) == len(tl.right) == len(tl.intent) >= 1
    assert set(report.ground_truth) >= {"brake", "left", "right", "intent"}
    assert report.video.is_file() and report.video.stat().st_size > 0
    assert report.contact_sheet.is_file()
    text = report.text()
    assert "every input frame has its output" in text and "OK: one output" in text
    assert "no /diagnostics message was recorded" in text  # replay writes none


def test_missing_outputs_are_reported(replayed, tmp_path):
    bag, out = replayed
    partial = tmp_path / "partial"
    with open_bag(out) as reader, BagWriter(partial) as writer:
        writer.add_topic(OUTPUT_TOPIC, "signal_light_msgs/msg/VehicleLightStateArray")
        for i, m in enumerate(reader.messages([OUTPUT_TOPIC])):
            if i not in (3, 7):
                writer.write(OUTPUT_TOPIC, m.log_time_ns, m.msg)
    report = build_report(bag, partial, video=False)
    assert not report.complete
    assert len(report.missing) == 2 and report.outputs == N_FRAMES - 2
    assert "2 input frame(s) without output" in report.text()
    assert report.video is None
