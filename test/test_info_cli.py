"""``signal-light info`` on bags written in tmp_path."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from signal_light_node.io import bagio
from signal_light_node.boxes import TrackBox
from signal_light_node.cli import main
from signal_light_node.io.conversions import boxes_to_detections, make_header
from signal_light_node.io.image_codec import bgr_to_compressed_fields, bgr_to_image_fields

T0 = 1_000_000_000_000
PERIOD = 100_000_000  # 10 Hz
N = 12


@pytest.fixture()
def scene_bag(tmp_path: Path) -> Path:
    """12 frames: raw 32x24 images, JPEG 40x30 images, detections with tracks 1..5."""
    make = bagio.make
    path = tmp_path / "scene"
    raw = np.zeros((24, 32, 3), np.uint8)
    jpeg = bgr_to_compressed_fields(np.full((30, 40, 3), 90, np.uint8), "jpeg")
    with bagio.BagWriter(path) as writer:
        writer.add_topic("/cam/image_raw", "sensor_msgs/msg/Image")
        writer.add_topic("/cam/image/compressed", "sensor_msgs/msg/CompressedImage")
        writer.add_topic("/tracks", "vision_msgs/msg/Detection2DArray")
        writer.add_topic("/tracks_extra", "vision_msgs/msg/Detection2DArray")
        for i in range(N):
            stamp = T0 + i * PERIOD
            header = make_header(stamp, "cam", make)
            writer.write("/cam/image_raw", stamp, make("sensor_msgs/msg/Image", header=header,
                                                       **bgr_to_image_fields(raw, "rgb8")))
            writer.write("/cam/image/compressed", stamp,
                         make("sensor_msgs/msg/CompressedImage", header=header, **jpeg))
            # Tracks 1..4 come and go; "5" only on the second topic; "1" on both.
            ids = [str(1 + (i + k) % 4) for k in range(2)]
            writer.write("/tracks", stamp, boxes_to_detections(
                header, [TrackBox(t, 1, 2, 10, 12, "car") for t in ids], make))
            if i % 3 == 0:
                writer.write("/tracks_extra", stamp, boxes_to_detections(
                    header, [TrackBox("5", 0, 0, 4, 4), TrackBox("1", 0, 0, 4, 4)], make))
    return path


def test_info_json_reports_everything(scene_bag: Path, capsys) -> None:
    assert main(["info", str(scene_bag), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["storage"] == "mcap"
    assert report["message_count"] == 3 * N + 4
    assert report["start_ns"] == T0
    assert report["duration_ns"] == (N - 1) * PERIOD
    topics = {t["topic"]: t for t in report["topics"]}
    assert topics["/cam/image_raw"]["msgtype"] == "sensor_msgs/msg/Image"
    assert topics["/cam/image_raw"]["count"] == N
    assert topics["/cam/image_raw"]["image"] == {"width": 32, "height": 24, "encoding": "rgb8"}
    assert topics["/cam/image/compressed"]["image"]["width"] == 40
    assert topics["/cam/image/compressed"]["image"]["height"] == 30
    assert topics["/tracks"]["count"] == N and topics["/tracks"]["track_ids"] == 4
    assert topics["/tracks_extra"]["count"] == 4 and topics["/tracks_extra"]["track_ids"] == 2
    assert report["track_ids"] == 5


def test_info_text_via_installed_command(scene_bag: Path) -> None:
    exe = shutil.which("signal-light")
    if exe is None:
        pytest.skip("signal-light is not installed in this environment")
    out = subprocess.run([exe, "info", str(scene_bag)], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    text = out.stdout
    assert "duration:   1.100 s" in text
    assert "32x24 rgb8" in text and "40x30" in text
    line = next(l for l in text.splitlines() if l.strip().startswith("/tracks "))
    assert "vision_msgs/msg/Detection2DArray" in line and f"{N} msgs" in line
    assert "track IDs:  5 distinct" in text


def test_info_on_missing_bag_is_a_clean_error(tmp_path: Path, capsys) -> None:
    assert main(["info", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert "does not exist" in err and "Traceback" not in err


def test_info_reports_undecodable_first_image(tmp_path: Path, capsys) -> None:
    make = bagio.make
    path = tmp_path / "bad"
    with bagio.BagWriter(path) as writer:
        writer.add_topic("/img", "sensor_msgs/msg/CompressedImage")
        writer.write("/img", 5, make("sensor_msgs/msg/CompressedImage",
                                     header=make_header(5, "c", make), format="jpeg",
                                     data=np.frombuffer(b"not a jpeg", np.uint8)))
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "undecodable first image" in out and "/img" in out
    assert "track IDs:  0 distinct" in out
