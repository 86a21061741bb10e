"""``signal-light annotate export`` / ``import``: a CVAT round trip on a committed bag.

One export of ``bags/day_street`` (a time range, every 4th frame, boxes of at least
20 px) serves every test; the node's own output comes from ``signal-light replay`` of
the same bag. The import is checked to reproduce those predictions as ground truth when
nothing is edited, to carry an edit into the labelled bag, and to refuse in one line,
writing nothing, a file of another bag, a missing frame, an unknown attribute value and
a broken XML.
"""

from __future__ import annotations

import json
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Dict, Tuple

import numpy as np
import pytest

from signal_light_node.cli import main
from signal_light_node.errors import AnnotationError, ConfigError
from signal_light_node.io.bagio import open_bag
from signal_light_node.io.conversions import detections_to_boxes, stamp_to_ns
from signal_light_node.io.topics import GROUND_TRUTH_TOPIC, OUTPUT_TOPIC
from signal_light_node.labels import CLASS_NAMES, TASKS
from signal_light_node.outputs.vehicle_lights import truth_row
from signal_light_node.runtime.crops import clip_roi
from signal_light_node.tools.annotate import EXPORT_FILE, parse_time
from signal_light_node.tools.cvat_xml import ATTRIBUTES, TRACK_ID, read_video_xml

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "day_street"
OTHER_BAG = REPO / "bags" / "night_street"
EVERY, MIN_BOX, START_S, END_S = 4, 20.0, 0.5, 8.0

Rows = Dict[int, Dict[str, np.ndarray]]


def _rows(bag: Path, topic: str) -> Rows:
    """``stamp -> {track ID: TASKS-order row}`` of a ``VehicleLightStateArray`` topic."""
    with open_bag(bag) as reader:
        return {stamp_to_ns(m.msg.header.stamp): {str(v.track_id): truth_row(v)
                                                  for v in m.msg.vehicles}
                for m in reader.messages([topic])}


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("annotate") / "export"
    assert main(["annotate", "export", str(BAG), str(out), "--start", str(START_S),
                 "--end", str(END_S), "--every", str(EVERY), "--min-box", str(MIN_BOX),
                 "--no-progress"]) == 0
    return out


@pytest.fixture(scope="module")
def predictions(tmp_path_factory) -> Rows:
    """What ``signal-light replay`` publishes for the bag, with its defaults."""
    out = tmp_path_factory.mktemp("replay") / "replay"
    assert main(["replay", str(BAG), "-o", str(out), "--no-progress"]) == 0
    return _rows(out, OUTPUT_TOPIC)


def _record(exported: Path) -> dict:
    return json.loads((exported / EXPORT_FILE).read_text())


def _labels_as_rows(exported: Path, xml: Path) -> Rows:
    """The file's attribute values as ``stamp -> {track ID: row}``."""
    stamps = [f["stamp_ns"] for f in _record(exported)["frames"]]
    out: Rows = {s: {} for s in stamps}
    for (frame, track_id), box in read_video_xml(xml.read_bytes(), xml.name).boxes.items():
        out[stamps[frame]][track_id] = np.array(
            [CLASS_NAMES[t].index(box.values[t]) for t in TASKS], np.int64)
    return out


def _assert_same(got: Rows, want: Rows) -> None:
    assert sorted(got) == sorted(want)
    for stamp in want:
        assert sorted(got[stamp]) == sorted(want[stamp]), stamp
        for track_id, row in want[stamp].items():
            assert got[stamp][track_id].tolist() == row.tolist(), (stamp, track_id)


def test_export_writes_a_cvat_video_task_with_the_nodes_predictions(exported, predictions):
    record = _record(exported)
    frames = record["frames"]
    stamps = [f["stamp_ns"] for f in frames]
    images = sorted((exported / "images").iterdir())
    assert [p.name for p in images] == [f"frame_{k:06d}.jpg" for k in range(len(frames))]
    root = ET.parse(exported / "annotations.xml").getroot()
    assert root.findtext("version") == "1.1"
    assert int(root.findtext("meta/task/size")) == len(frames)
    assert "the node's predictions" in root.findtext("meta/signal_light/predictions")
    assert {t.get("source") for t in root.findall("track")} == {"auto"}
    labels = json.loads((exported / "labels.json").read_text())
    assert [a["name"] for a in labels[0]["attributes"]] == list(ATTRIBUTES) + [TRACK_ID]
    # The range and every 4th frame of it (12 Hz: 4 frames = 1/3 s).
    with open_bag(BAG) as reader:
        bag_stamps = sorted(stamp_to_ns(m.msg.header.stamp)
                            for m in reader.messages(["/camera/image_raw/compressed"]))
        detections = {stamp_to_ns(m.msg.header.stamp): detections_to_boxes(m.msg)
                      for m in reader.messages(["/camera/tracked_objects"])}
    first = bag_stamps[0]
    in_range = [s for s in bag_stamps if START_S * 1e9 <= s - first <= END_S * 1e9]
    assert stamps == in_range[::EVERY]
    # Every box of at least MIN_BOX pixels is there, and only those.
    small = 0
    for k, stamp in enumerate(stamps):
        sizes = {b.track_id: min(clip_roi(b, 640, 360)[2:]) for b in detections[stamp]}
        kept = [b["track_id"] for b in frames[k]["boxes"]]
        assert kept == [t for t, size in sizes.items() if size >= MIN_BOX]
        small += len(sizes) - len(kept)
    assert small > 0
    # The attribute values are what the node publishes.
    _assert_same(_labels_as_rows(exported, exported / "annotations.xml"),
                 {s: {t: predictions[s][t] for t in [b["track_id"] for b in f["boxes"]]}
                  for s, f in zip(stamps, frames)})


def test_the_unedited_file_gives_the_predictions_as_ground_truth(exported, predictions,
                                                                   tmp_path, capsys):
    from signal_light_node.runtime.crops import CropConfig
    from signal_light_node.tools.replay import replay_bag, score_summary
    from signal_light_node.training.sources import load_bag_tracks

    out = tmp_path / "labelled"
    assert main(["annotate", "import", str(exported / "annotations.xml"), str(BAG),
                 str(out)]) == 0
    assert "brake 0, left 0, right 0, intent 0, view 0" in capsys.readouterr().out
    truth = _rows(out, GROUND_TRUTH_TOPIC)
    frames = _record(exported)["frames"]
    _assert_same(truth, {f["stamp_ns"]: {b["track_id"]: predictions[f["stamp_ns"]][b["track_id"]]
                                         for b in f["boxes"]} for f in frames})
    # The whole recording is there: the node runs over it as it ran over the bag.
    with open_bag(out) as labelled, open_bag(BAG) as original:
        for topic in ("/camera/image_raw/compressed", "/camera/tracked_objects"):
            assert labelled.topics()[topic] == original.topics()[topic]
    # replay scores it: the node agrees with its own predictions everywhere.
    from signal_light_node.runtime.engine import engine_from_checkpoint

    summary = replay_bag(out, tmp_path / "replayed", engine_from_checkpoint(backend="auto"),
                         progress=False)
    assert summary.has_ground_truth
    pairs = [(t.tolist(), p.tolist()) for rec in summary.tracks.values()
             for t, p in zip(rec.truth, rec.pred)]
    assert len(pairs) == sum(len(f["boxes"]) for f in frames)
    assert all(t == p for t, p in pairs)
    assert all(m["accuracy"] == 1.0 for m in score_summary(summary)["no_grace"]["overall"].values())
    # train --bags and evaluate --bags read it as a labelled bag (load_bag_tracks).
    tracks = load_bag_tracks(out, CropConfig(size=32))
    assert sum(len(t) for t in tracks) == len(pairs)
    assert main(["evaluate", "--bags", str(out), "--out", str(tmp_path / "evaluated"),
                 "--no-progress"]) == 0
    assert (tmp_path / "evaluated" / "metrics.json").is_file()


def _edit(exported: Path, tmp_path: Path, change) -> Path:
    """A copy of the export's XML, changed by ``change(root)``, in a folder of its own."""
    tree = ET.parse(exported / "annotations.xml")
    change(tree.getroot())
    path = tmp_path / "edited" / "annotations.xml"
    path.parent.mkdir()
    tree.write(path, encoding="utf-8", xml_declaration=True)
    return path


def _a_box(root: ET.Element, frame: int) -> Tuple[ET.Element, str]:
    """A box inside the image at ``frame`` and its track ID."""
    box = next(b for b in root.iter("box") if b.get("frame") == str(frame)
               and b.get("outside") == "0")
    return box, next(a.text for a in box.findall("attribute") if a.get("name") == TRACK_ID)


def _set(box: ET.Element, name: str, value: str) -> None:
    next(a for a in box.findall("attribute") if a.get("name") == name).text = value


def test_an_edited_label_shows_up_in_the_labelled_bag(exported, predictions, tmp_path,
                                                      capsys):
    frame = 5
    stamp = _record(exported)["frames"][frame]["stamp_ns"]
    edited = {}

    def change(root):
        box, track_id = _a_box(root, frame)
        was = next(a.text for a in box.findall("attribute") if a.get("name") == "brake")
        edited.update(track_id=track_id, brake="ON" if was != "ON" else "OFF")
        _set(box, "brake", edited["brake"])
        _set(box, "left", "ON")
        _set(box, "right", "ON")
        _set(box, "intent", "HAZARD")

    xml = _edit(exported, tmp_path, change)
    out = tmp_path / "labelled"
    assert main(["annotate", "import", str(xml), str(BAG), str(out),
                 "--export", str(exported / EXPORT_FILE)]) == 0
    assert "brake 1" in capsys.readouterr().out
    truth = _rows(out, GROUND_TRUTH_TOPIC)
    row = dict(zip(TASKS, truth[stamp][edited["track_id"]].tolist()))
    assert row["brake"] == CLASS_NAMES["brake"].index(edited["brake"])
    assert (row["left"], row["right"], row["intent"]) == (1, 1, 3)
    # Everything else is as exported.
    _assert_same({s: {t: r for t, r in rows.items() if (s, t) != (stamp, edited["track_id"])}
                  for s, rows in truth.items()},
                 {s: {t: r for t, r in rows.items() if (s, t) != (stamp, edited["track_id"])}
                  for s, rows in _labels_as_rows(exported, exported / "annotations.xml").items()})


def _drop_frame(root: ET.Element) -> None:
    for track in root.findall("track"):
        for box in [b for b in track.findall("box") if b.get("frame") == "3"]:
            track.remove(box)


def _unknown_value(root: ET.Element) -> None:
    _set(_a_box(root, 2)[0], "left", "MAYBE")


@pytest.mark.parametrize("case, expected", [
    ("another bag", f"exported from {BAG}"),
    ("same stamps, other images", "the image differs from the one exported"),
    ("missing frame", "frame 3"),
    ("unknown value", "left is 'MAYBE'"),
    ("broken XML", "not well-formed XML"),
])
def test_a_mismatch_is_refused_in_one_line_and_writes_nothing(exported, tmp_path, capsys,
                                                              case, expected):
    bag = OTHER_BAG if case == "another bag" else BAG
    export = exported / EXPORT_FILE
    if case == "same stamps, other images":  # a recording of the same clock, other pixels
        record = _record(exported)
        record["frames"][0]["image_sha256"] = "0" * 64
        export = tmp_path / EXPORT_FILE
        export.write_text(json.dumps(record))
    if case == "missing frame":
        xml = _edit(exported, tmp_path, _drop_frame)
    elif case == "unknown value":
        xml = _edit(exported, tmp_path, _unknown_value)
    else:
        xml = tmp_path / "edited" / "annotations.xml"
        xml.parent.mkdir()
        shutil.copy(exported / "annotations.xml", xml)
        if case == "broken XML":
            xml.write_bytes(xml.read_bytes()[:-200])
    out = tmp_path / "labelled" / "bag"
    assert main(["annotate", "import", str(xml), str(bag), str(out),
                 "--export", str(export)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("signal-light annotate: error:"), err
    assert expected in err[0], err
    assert not (tmp_path / "labelled").exists()


def test_the_export_file_is_found_beside_the_xml_or_asked_for(exported, tmp_path, capsys):
    xml = tmp_path / "annotations.xml"
    shutil.copy(exported / "annotations.xml", xml)
    assert main(["annotate", "import", str(xml), str(BAG), str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--export" in err[0], err
    assert not (tmp_path / "out").exists()


def test_cvats_export_zip_is_read(exported, predictions, tmp_path):
    import zipfile

    archive = tmp_path / "task_7-cvat for video 1.1.zip"
    with zipfile.ZipFile(archive, "w") as z:
        z.write(exported / "annotations.xml", "annotations.xml")
    out = tmp_path / "labelled"
    assert main(["annotate", "import", str(archive), str(BAG), str(out),
                 "--export", str(exported / EXPORT_FILE)]) == 0
    _assert_same(_rows(out, GROUND_TRUTH_TOPIC),
                 _labels_as_rows(exported, exported / "annotations.xml"))


def test_cvats_own_export_of_the_task_reads_the_same():
    """CVAT's download: its meta (a job), its own track numbers, interpolated boxes,
    outside boxes, attributes in another order and one more attribute."""
    data = b"""<?xml version="1.0" encoding="utf-8"?>
<annotations><version>1.1</version>
  <meta><job><id>7</id><size>3</size><mode>interpolation</mode></job></meta>
  <track id="12" label="vehicle" source="manual">
    <box frame="0" outside="0" occluded="1" keyframe="1" xtl="1" ytl="2" xbr="30" ybr="40" z_order="0">
      <attribute name="track_id">a7</attribute><attribute name="note">x</attribute>
      <attribute name="view">FRONT</attribute><attribute name="intent">LEFT</attribute>
      <attribute name="right">OFF</attribute><attribute name="left">ON</attribute>
      <attribute name="brake">UNKNOWN</attribute></box>
    <box frame="1" outside="0" occluded="0" keyframe="0" xtl="2" ytl="2" xbr="31" ybr="40" z_order="0">
      <attribute name="track_id">a7</attribute><attribute name="view">FRONT</attribute>
      <attribute name="intent">LEFT</attribute><attribute name="right">OFF</attribute>
      <attribute name="left">ON</attribute><attribute name="brake">ON</attribute></box>
    <box frame="2" outside="1" occluded="0" keyframe="1" xtl="2" ytl="2" xbr="31" ybr="40" z_order="0">
      <attribute name="track_id">a7</attribute></box>
  </track>
</annotations>"""
    video = read_video_xml(data, "cvat.xml")
    assert video.size == 3 and sorted(video.boxes) == [(0, "a7"), (1, "a7")]
    assert dict(video.boxes[(1, "a7")].values) == {"brake": "ON", "left": "ON", "right": "OFF",
                                                   "intent": "LEFT", "view": "FRONT"}
    with pytest.raises(AnnotationError, match="CVAT for images"):
        read_video_xml(b"<annotations><version>1.1</version><image id='0'/></annotations>",
                       "images.xml")


def test_times_and_bad_export_options(tmp_path, capsys):
    assert parse_time("2.5").resolve(10) == 10 + 2_500_000_000
    assert parse_time("@1701450732.195843948").resolve(10) == 1701450732195843948
    for bad in ("-1", "soon", "@x"):
        with pytest.raises(ConfigError):
            parse_time(bad)
    for args in (["--every", "0"], ["--start", "5", "--end", "2"],
                 ["--start", "9.95", "--end", "20"]):  # the last: no frame, after the replay
        assert main(["annotate", "export", str(BAG), str(tmp_path / "o"), "--no-progress",
                     *args]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("signal-light annotate: error:"), err
        assert not (tmp_path / "o").exists() and list(tmp_path.iterdir()) == []
