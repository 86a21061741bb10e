"""``signal-light replay`` of several cameras: several bags (one camera each) or one bag
with several camera topic pairs, merged in stamp order through the multi-camera engine,
each camera's outputs on its own topics."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Dict, List

import numpy as np
import pytest

from fake_light_model import FakeLightModel
from signal_light_node.boxes import TrackBox
from signal_light_node.cli import main
from signal_light_node.errors import ConfigError
from signal_light_node.io import bagio
from signal_light_node.io.conversions import boxes_to_detections, make_header, stamp_to_ns
from signal_light_node.outputs.vehicle_lights import vehicle_light_array
from signal_light_node.io.image_codec import bgr_to_compressed_fields
from signal_light_node.io.topics import GROUND_TRUTH_TOPIC, OUTPUT_TOPIC, camera_topic
from signal_light_node.labels import Intent, LightStatus, View
from signal_light_node.runtime.engine import EngineConfig, LightStateEngine
from signal_light_node.runtime.results import LightEstimate, VehicleResult
from signal_light_node.tools.replay import replay_bag, score_summary
from signal_light_node.tools.replay_cameras import (camera_sources, detect_camera_pairs,
                                                    parse_camera_spec, replay_cameras)

MS = 1_000_000
T0 = 1_700_000_000 * 1_000_000_000
N = 10
COMPRESSED = "sensor_msgs/msg/CompressedImage"
DETECTIONS = "vision_msgs/msg/Detection2DArray"
#: Per camera: (image size, box of its track "1"); both cameras have a track "1".
CAMS = {"front": ((96, 160), TrackBox("1", 10, 20, 60, 60)),
        "rear": ((120, 200), TrackBox("1", 120, 40, 190, 100))}


def _frame(camera: str, t: int, stamp: int):
    (h, w), box = CAMS[camera]
    rng = np.random.default_rng(hash((camera, t)) % 2**32)
    image = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
    header = make_header(stamp, f"{camera}_camera", bagio.make)
    return (bagio.make(COMPRESSED, header=header, **bgr_to_compressed_fields(image, "png")),
            boxes_to_detections(header, [box, TrackBox(f"{camera}_only", 5, 5, 40, 40)],
                                bagio.make), header)


def _truth(header) -> object:
    result = VehicleResult(track_id="1", roi=(0, 0, 1, 1),
                           brake=LightEstimate.certain(LightStatus.ON),
                           left=LightEstimate.certain(LightStatus.OFF),
                           right=LightEstimate.certain(LightStatus.OFF),
                           intent=Intent.OFF, intent_probability=1.0, view=View.BEHIND,
                           view_probability=1.0)
    return vehicle_light_array(header, [result], bagio.make)


def _stamps(camera: str, loop_at: int = -1) -> List[int]:
    """The camera's stamps; from ``loop_at`` on they start again from T0 - 60 s."""
    return [T0 + t * 100 * MS if loop_at < 0 or t < loop_at else
            T0 - 60_000 * MS + (t - loop_at) * 100 * MS for t in range(N)]


def _camera_bag(path: Path, camera: str, loop_at: int = -1) -> Path:
    """One camera's bag with the usual topic names and ground truth."""
    with bagio.BagWriter(path) as bag:
        bag.add_topic("/camera/image_raw/compressed", COMPRESSED)
        bag.add_topic("/camera/tracked_objects", DETECTIONS)
        bag.add_topic(GROUND_TRUTH_TOPIC, "signal_light_msgs/msg/VehicleLightStateArray")
        for t, stamp in enumerate(_stamps(camera, loop_at)):
            image, dets, header = _frame(camera, t, stamp)
            log = T0 + t * 100 * MS  # the log time goes on when the stamps loop
            bag.write("/camera/tracked_objects", log + 2 * MS, dets)
            bag.write("/camera/image_raw/compressed", log + 5 * MS, image)
            bag.write(GROUND_TRUTH_TOPIC, log + 5 * MS, _truth(header))
    return path


def _two_camera_bag(path: Path) -> Path:
    """One bag with both cameras under their namespaces (and a stray image topic)."""
    with bagio.BagWriter(path) as bag:
        for camera in CAMS:
            bag.add_topic(f"/{camera}/image/compressed", COMPRESSED)
            bag.add_topic(f"/{camera}/tracker/detections", DETECTIONS)
        for t in range(N):
            for k, camera in enumerate(CAMS):
                stamp = T0 + t * 100 * MS + k * 3 * MS
                image, dets, _ = _frame(camera, t, stamp)
                bag.write(f"/{camera}/tracker/detections", stamp + 2 * MS, dets)
                bag.write(f"/{camera}/image/compressed", stamp + 4 * MS, image)
    return path


def _engine(model=None) -> LightStateEngine:
    return LightStateEngine(model or FakeLightModel(), EngineConfig(track_timeout_s=5.0))


def _outputs(path: Path) -> Dict[str, Dict[int, object]]:
    out: Dict[str, Dict[int, object]] = defaultdict(dict)
    with bagio.open_bag(path) as bag:
        for m in bag.messages():
            header = m.msg.markers[0].header if hasattr(m.msg, "markers") else m.msg.header
            out[m.topic][stamp_to_ns(header.stamp)] = m.msg
    return out


def _rows(msg) -> list:
    return [(v.track_id, v.roi.x_offset, v.roi.y_offset, v.roi.width, v.roi.height,
             v.frames_observed, round(v.brake.on_probability, 6),
             round(v.left_blinker.on_probability, 6), round(v.right_blinker.on_probability, 6))
            for v in msg.vehicles]


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> Dict[str, Path]:
    root = tmp_path_factory.mktemp("cameras")
    return {"front": _camera_bag(root / "front", "front"),
            "rear": _camera_bag(root / "rear", "rear"),
            "rear_loop": _camera_bag(root / "rear_loop", "rear", loop_at=6),
            "both": _two_camera_bag(root / "both")}


def test_two_bags_equal_each_bag_replayed_alone_and_share_steps(bags, tmp_path):
    model = FakeLightModel()
    sources = camera_sources([bags["front"], bags["rear"]])
    assert [(s.name, s.bag) for s in sources] == [("front", bags["front"]),
                                                  ("rear", bags["rear"])]
    summary = replay_cameras(sources, tmp_path / "out", _engine(model), progress=False,
                             markers=True)
    out = _outputs(tmp_path / "out")
    for camera in CAMS:
        alone = tmp_path / f"alone_{camera}"
        replay_bag(bags[camera], alone, _engine(), progress=False)
        want = _outputs(alone)[OUTPUT_TOPIC]
        got = out[camera_topic(OUTPUT_TOPIC, camera)]
        assert sorted(got) == sorted(want) == _stamps(camera)
        for stamp in want:
            assert got[stamp].header.frame_id == f"{camera}_camera"
            assert _rows(got[stamp]) == _rows(want[stamp])
        (_, box) = CAMS[camera]
        assert all(_rows(m)[0][1:5] == (box.x0, box.y0, box.x1 - box.x0, box.y1 - box.y0)
                   for m in got.values())
        assert len(out[f"/signal_light_detector/{camera}/output/markers"]) == N
    assert OUTPUT_TOPIC not in out
    # both cameras' frames (same stamps) share each step
    assert summary.steps == N and model.batch_sizes == [4] * N
    assert summary.images == summary.outputs == 2 * N and len(summary.latencies_s) == N
    assert summary.cameras["rear"].images == N
    assert sorted(summary.topics_written) == sorted(
        camera_topic(t, c) for c in CAMS for t in (OUTPUT_TOPIC,
                                                   "/signal_light_detector/output/markers"))
    text = summary.text()
    assert "2 shared steps" not in text and f"{2 * N} frames in {N} shared steps" in text
    assert "front: 10 images" in text and "rear: 10 images" in text
    # ground truth per camera; track IDs kept apart as <camera>/<id>
    assert sorted(summary.tracks) == ["front/1", "rear/1"]
    assert score_summary(summary) is not None


def test_a_loop_in_one_cameras_bag_resets_only_that_camera(bags, tmp_path):
    engine = _engine()
    sources = camera_sources([bags["front"], bags["rear_loop"]], ["front", "rear"])
    summary = replay_cameras(sources, tmp_path / "out", engine, progress=False)
    out = _outputs(tmp_path / "out")
    front = out[camera_topic(OUTPUT_TOPIC, "front")]
    rear = out[camera_topic(OUTPUT_TOPIC, "rear")]
    assert [_rows(front[s])[0][5] for s in _stamps("front")] == list(range(1, N + 1))
    assert [_rows(rear[s])[0][5] for s in _stamps("rear", 6)] == [1, 2, 3, 4, 5, 6, 1, 2, 3, 4]
    assert summary.camera_counters["rear"]["resets"] == 1
    assert summary.camera_counters["front"]["resets"] == 0


def test_one_bag_with_two_camera_pairs_by_namespace_or_by_name(bags, tmp_path):
    with bagio.open_bag(bags["both"]) as bag:
        pairs = detect_camera_pairs(bag.topics())
    assert pairs == [("front", "/front/image/compressed", "/front/tracker/detections"),
                     ("rear", "/rear/image/compressed", "/rear/tracker/detections")]
    auto = replay_cameras(camera_sources([bags["both"]], all_cameras=True), tmp_path / "auto",
                          _engine(), progress=False, with_inputs=True)
    named = replay_cameras(
        camera_sources([bags["both"]], ["rear", "front=/front/image/compressed,"
                                                "/front/tracker/detections"]),
        tmp_path / "named", _engine(), progress=False)
    a, n = _outputs(tmp_path / "auto"), _outputs(tmp_path / "named")
    for camera in CAMS:
        topic = camera_topic(OUTPUT_TOPIC, camera)
        assert len(a[topic]) == N and {s: _rows(m) for s, m in a[topic].items()} == \
            {s: _rows(m) for s, m in n[topic].items()}
        # track "1" of each camera keeps its own box and its own count of frames
        assert [r[0][5] for r in (_rows(m) for _, m in sorted(a[topic].items()))] == \
            list(range(1, N + 1))
    assert "/front/image/compressed" in a and "/rear/tracker/detections" in a  # with_inputs
    assert auto.steps == named.steps == N and not auto.has_ground_truth
    assert list(named.cameras) == ["rear", "front"]


@pytest.mark.parametrize("spec, want", [
    ("front", ("front", None, None)),
    ("rear=/r/image,/r/dets", ("rear", "/r/image", "/r/dets")),
])
def test_camera_specs(spec, want):
    assert parse_camera_spec(spec) == want


@pytest.mark.parametrize("spec", ["front=/only/one", "9front", "a b=/x,/y", "front=,/dets"])
def test_bad_camera_specs(spec):
    with pytest.raises(ConfigError):
        parse_camera_spec(spec)


def test_camera_choice_errors(bags):
    with pytest.raises(ConfigError, match="one per bag"):
        camera_sources([bags["front"], bags["rear"]], ["a"])
    with pytest.raises(ConfigError, match="twice"):
        camera_sources([bags["front"], bags["rear"]], ["a", "a"])
    with pytest.raises(ConfigError, match="name its cameras"):
        camera_sources([bags["front"]])
    with pytest.raises(ConfigError, match="no image and detection topics"):
        camera_sources([bags["both"]], ["side"])
    with pytest.raises(ConfigError, match="ONE bag"):
        camera_sources([bags["front"], bags["rear"]], all_cameras=True)


def test_cli_replays_several_bags(bags, tmp_path, capsys):
    from signal_light_node.model.checkpoint import ModelConfig, save_checkpoint
    from signal_light_node.model.registry import build_model

    config = ModelConfig(input_size=32, attention_channels=(4, 4, 4), backbone_channels=(8, 8),
                         lstm_hidden=(8, 8), head_channels=4, fc_hidden=16)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", build_model(config), config)
    out = tmp_path / "out"
    code = main(["replay", str(bags["front"]), str(bags["rear_loop"]), "-o", str(out),
                 "--checkpoint", str(ckpt), "--no-progress", "--camera", "left",
                 "--camera", "right"])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "cameras: 2" in text and "left: 10 images" in text and "right: 10 images" in text
    assert "Agreement with the ground truth of left" in text
    topics = _outputs(out)
    assert len(topics[camera_topic(OUTPUT_TOPIC, "left")]) == N
    assert len(topics[camera_topic(OUTPUT_TOPIC, "right")]) == N
    assert main(["replay", str(bags["front"]), str(bags["rear"]), "-o", str(tmp_path / "v"),
                 "--checkpoint", str(ckpt), "--no-progress", "--video", "x.mp4"]) == 2
    assert "single camera" in capsys.readouterr().err
    assert main(["replay", str(bags["both"]), "-o", str(tmp_path / "auto"), "--checkpoint",
                 str(ckpt), "--no-progress", "--all-cameras"]) == 0
    assert "front: 10 images from /front/image/compressed" in capsys.readouterr().out
