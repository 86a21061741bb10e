"""Bag I/O: every project type and vision_msgs type survives write -> read, the written MCAP
decodes with the independent ``mcap`` + ``mcap-ros2-support`` reader, sqlite3 bags and bare
``.mcap`` files read, and misuse gives BagIOError."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, Tuple

import numpy as np
import pytest

from signal_light_node.io import bagio
from signal_light_node.boxes import TrackBox
from signal_light_node.io.conversions import boxes_to_detections, detections_to_boxes, make_header
from signal_light_node.outputs.vehicle_lights import (vehicle_light_array,
                                                      vehicle_light_array_to_results)
from signal_light_node.errors import BagIOError
from signal_light_node.io.image_codec import bgr_to_compressed_fields, bgr_to_image_fields
from signal_light_node.labels import Intent, LightStatus, View
from signal_light_node.runtime.results import LightEstimate, VehicleResult

make = bagio.make
T0 = 1_700_000_000_123_456_789

# float32 fields use values exact in float32 so that == holds after a round trip.
RESULTS = [
    VehicleResult("7", (4, 5, 60, 40), LightEstimate(LightStatus.ON, 0.125, 0.75, 0.125),
                  LightEstimate(LightStatus.OFF, 0.5, 0.25, 0.25),
                  LightEstimate(LightStatus.UNKNOWN, 0.0, 0.0, 1.0), Intent.UNKNOWN, 0.5,
                  View.LEFT, 0.875, ((100, 0.75),), 12, True),
    VehicleResult("äöü-9", (0, 0, 1, 1), LightEstimate.certain(LightStatus.OFF),
                  LightEstimate.certain(LightStatus.ON), LightEstimate.certain(LightStatus.ON),
                  Intent.HAZARD, 1.0, View.BEHIND, 1.0, ((101, 1.0), (102, 1.0)), 1, True),
]
BOXES = [TrackBox("7", 10.5, 20.25, 110.5, 80.75, "car"), TrackBox("12", -5.0, 3.0, 40.0, 30.0)]


def _image() -> np.ndarray:
    return np.random.default_rng(1).integers(0, 256, (12, 16, 3), dtype=np.uint8)


def sample_messages() -> Dict[str, Any]:
    """One message of every project type, every vision_msgs type and both image types."""
    header = make_header(T0, "cam", make)
    dets = boxes_to_detections(header, BOXES, make, score=0.875)
    lights = vehicle_light_array(header, RESULTS, make)
    det = dets.detections[0]
    vehicle = lights.vehicles[0]
    return {
        "signal_light_msgs/msg/VehicleLightStateArray": lights,
        "signal_light_msgs/msg/VehicleLightState": vehicle,
        "signal_light_msgs/msg/LightState": vehicle.brake,
        "signal_light_msgs/msg/LightClassification": vehicle.classification[0],
        "vision_msgs/msg/Detection2DArray": dets,
        "vision_msgs/msg/Detection2D": det,
        "vision_msgs/msg/ObjectHypothesisWithPose": det.results[0],
        "vision_msgs/msg/ObjectHypothesis": det.results[0].hypothesis,
        "vision_msgs/msg/BoundingBox2D": det.bbox,
        "vision_msgs/msg/Pose2D": det.bbox.center,
        "vision_msgs/msg/Point2D": det.bbox.center.position,
        "sensor_msgs/msg/Image": make("sensor_msgs/msg/Image", header=header,
                                      **bgr_to_image_fields(_image(), "rgb8")),
        "sensor_msgs/msg/CompressedImage": make("sensor_msgs/msg/CompressedImage", header=header,
                                                **bgr_to_compressed_fields(_image(), "png")),
    }


def topic_of(msgtype: str) -> str:
    return "/" + msgtype.replace("/msg/", "/").lower()


def assert_same(expected: Any, got: Any, where: str = "msg") -> None:
    """Field-by-field equality of a rosbags message with any object having the same fields."""
    msgtype = getattr(expected, "__msgtype__", None)
    if msgtype is not None:
        for name, _ in bagio.typestore().fielddefs[msgtype][1]:
            assert hasattr(got, name), f"{where}.{name} missing"
            assert_same(getattr(expected, name), getattr(got, name), f"{where}.{name}")
    elif isinstance(expected, np.ndarray):
        got_arr = np.frombuffer(got, np.uint8) if isinstance(got, (bytes, bytearray)) \
            else np.asarray(got)
        assert np.array_equal(expected, got_arr.astype(expected.dtype)), where
    elif isinstance(expected, (list, tuple)):
        assert len(expected) == len(got), f"{where}: length {len(expected)} != {len(got)}"
        for i, (a, b) in enumerate(zip(expected, got)):
            assert_same(a, b, f"{where}[{i}]")
    else:
        assert expected == got, f"{where}: {expected!r} != {got!r}"


@pytest.fixture()
def written_bag(tmp_path: Path) -> Tuple[Path, Dict[str, Any]]:
    msgs = sample_messages()
    path = tmp_path / "all_types"
    with bagio.BagWriter(path) as writer:
        for i, (msgtype, msg) in enumerate(msgs.items()):
            writer.add_topic(topic_of(msgtype), msgtype)
            # Written in reverse time order: reading must still come out sorted.
            writer.write(topic_of(msgtype), T0 + (len(msgs) - i) * 1000, msg)
    return path, msgs


def test_every_type_survives_write_and_read(written_bag) -> None:
    path, msgs = written_bag
    assert (path / "metadata.yaml").is_file() and (path / "all_types.mcap").is_file()
    with bagio.open_bag(path) as bag:
        assert bag.storage == "mcap"
        topics = bag.topics()
        assert topics == {topic_of(t): bagio.TopicInfo(t, 1) for t in msgs}
        assert bag.message_count == len(msgs)
        assert bag.start_ns == T0 + 1000
        assert bag.duration_ns == (len(msgs) - 1) * 1000
        read = list(bag.messages())
    assert [m.log_time_ns for m in read] == sorted(m.log_time_ns for m in read)
    assert {m.msgtype for m in read} == set(msgs)
    for item in read:
        assert item.topic == topic_of(item.msgtype)
        assert_same(msgs[item.msgtype], item.msg, item.msgtype)


def test_written_mcap_decodes_with_independent_reader(written_bag) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path, msgs = written_bag
    seen = set()
    with open(path / "all_types.mcap", "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            assert channel.topic == topic_of(schema.name)
            assert_same(msgs[schema.name], decoded, schema.name)
            seen.add(schema.name)
    assert seen == set(msgs)


def test_conversions_survive_a_bag(written_bag) -> None:
    path, _ = written_bag
    with bagio.open_bag(path) as bag:
        dets = next(bag.messages([topic_of("vision_msgs/msg/Detection2DArray")])).msg
        lights = next(bag.messages([topic_of("signal_light_msgs/msg/VehicleLightStateArray")])).msg
    assert detections_to_boxes(dets) == BOXES
    stamp, results = vehicle_light_array_to_results(lights)
    assert stamp == T0
    assert results == RESULTS


def test_topic_filter_and_time_window(written_bag) -> None:
    path, msgs = written_bag
    with bagio.open_bag(path) as bag:
        only = list(bag.messages(["/sensor_msgs/image", "/nonexistent"]))
        assert [m.msgtype for m in only] == ["sensor_msgs/msg/Image"]
        assert list(bag.messages(["/nonexistent"])) == []
        window = list(bag.messages(start_ns=T0 + 2000, stop_ns=T0 + 4000))
        assert [m.log_time_ns for m in window] == [T0 + 2000, T0 + 3000]


def test_bare_mcap_and_directory_without_metadata(written_bag) -> None:
    path, msgs = written_bag
    with bagio.open_bag(path / "all_types.mcap") as bag:
        assert bag.topics() == {topic_of(t): bagio.TopicInfo(t, 1) for t in msgs}
        assert bag.duration_ns == (len(msgs) - 1) * 1000
        for item in bag.messages():
            assert_same(msgs[item.msgtype], item.msg, item.msgtype)
    (path / "metadata.yaml").unlink()
    with bagio.open_bag(path) as bag:
        assert len(list(bag.messages())) == len(msgs)


def test_sqlite3_rosbag2_reads(tmp_path: Path) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    msgs = sample_messages()
    store = bagio.typestore()
    path = tmp_path / "sqlite_bag"
    with Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        for i, (msgtype, msg) in enumerate(msgs.items()):
            conn = writer.add_connection(topic_of(msgtype), msgtype, typestore=store)
            writer.write(conn, T0 + i, store.serialize_cdr(msg, msgtype))
    assert list(path.glob("*.db3"))
    with bagio.open_bag(path) as bag:
        assert bag.storage == "sqlite3"
        assert {t: i.count for t, i in bag.topics().items()} == {topic_of(t): 1 for t in msgs}
        read = list(bag.messages())
    assert [m.log_time_ns for m in read] == [T0 + i for i in range(len(msgs))]
    for item in read:
        assert_same(msgs[item.msgtype], item.msg, item.msgtype)


def test_foreign_type_decodes_from_the_bags_own_definition(tmp_path: Path) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    other = get_typestore(Stores.ROS2_JAZZY)
    other.register(get_types_from_msg("string note\nint32[] values", "other_msgs/msg/Thing"))
    cls = other.types["other_msgs/msg/Thing"]
    path = tmp_path / "foreign"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/thing", "other_msgs/msg/Thing", typestore=other)
        writer.write(conn, 5, other.serialize_cdr(cls(note="hi", values=np.array([1, -2], np.int32)),
                                                  "other_msgs/msg/Thing"))
    with bagio.open_bag(path) as bag:
        (item,) = list(bag.messages())
    assert item.msg.note == "hi" and list(item.msg.values) == [1, -2]
    assert "other_msgs/msg/Thing" not in bagio.typestore().fielddefs  # ours stays clean


def test_type_with_another_definition_decodes_with_the_bags_own(tmp_path: Path) -> None:
    # Same name, different fields (hash mismatch): trusting our schema would garble it.
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    other = get_typestore(Stores.ROS2_JAZZY)
    other.register(get_types_from_msg("float32 x\nfloat32 y\nstring label",
                                      "vision_msgs/msg/Point2D"))
    cls = other.types["vision_msgs/msg/Point2D"]
    path = tmp_path / "older"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/p", "vision_msgs/msg/Point2D", typestore=other)
        writer.write(conn, 5, other.serialize_cdr(cls(x=1.5, y=-2.5, label="old"),
                                                  "vision_msgs/msg/Point2D"))
    with bagio.open_bag(path) as bag:
        (item,) = list(bag.messages())
    assert (item.msg.x, item.msg.y, item.msg.label) == (1.5, -2.5, "old")


def test_writer_refuses_to_overwrite(tmp_path: Path) -> None:
    path = tmp_path / "bag"
    with bagio.BagWriter(path) as writer:
        writer.add_topic("/a", "vision_msgs/Point2D")
        writer.write("/a", 1, make("vision_msgs/msg/Point2D", x=1.0, y=2.0))
    with pytest.raises(BagIOError, match="exists"):
        bagio.BagWriter(path)
    with bagio.BagWriter(path, overwrite=True) as writer:
        writer.add_topic("/b", "vision_msgs/msg/Point2D")
    with bagio.open_bag(path) as bag:
        assert bag.topics() == {"/b": bagio.TopicInfo("vision_msgs/msg/Point2D", 0)}
        assert bag.message_count == 0 and bag.duration_ns == 0
    precious = tmp_path / "notabag"
    precious.mkdir()
    (precious / "thesis.tex").write_text("keep me")
    with pytest.raises(BagIOError, match="refusing"):
        with bagio.BagWriter(precious, overwrite=True):
            pass
    assert (precious / "thesis.tex").read_text() == "keep me"


def test_writer_misuse_gives_bag_io_error(tmp_path: Path) -> None:
    with bagio.BagWriter(tmp_path / "bag") as writer:
        writer.add_topic("/p", "vision_msgs/msg/Point2D")
        writer.add_topic("/p", "vision_msgs/msg/Point2D")  # same again is fine
        with pytest.raises(BagIOError, match="already has type"):
            writer.add_topic("/p", "vision_msgs/msg/Pose2D")
        with pytest.raises(BagIOError, match="unknown message type"):
            writer.add_topic("/q", "nope_msgs/msg/Nothing")
        with pytest.raises(BagIOError, match="not added"):
            writer.write("/q", 1, make("vision_msgs/msg/Point2D", x=0.0, y=0.0))
        with pytest.raises(BagIOError, match="takes vision_msgs/msg/Point2D"):
            writer.write("/p", 1, make("vision_msgs/msg/ObjectHypothesis", class_id="a",
                                       score=1.0))
        with pytest.raises(BagIOError, match="cannot serialize"):
            writer.write("/p", 1, make("vision_msgs/msg/Point2D", x="left", y=0.0))


def test_make_names_missing_and_unknown_fields() -> None:
    with pytest.raises(BagIOError, match=r"missing field\(s\) size_x, size_y"):
        make("vision_msgs/BoundingBox2D", center=None)
    with pytest.raises(BagIOError, match=r"unknown field\(s\) z"):
        make("vision_msgs/msg/Point2D", x=1.0, y=2.0, z=3.0)
    with pytest.raises(BagIOError, match="unknown message type"):
        make("vision_msgs/msg/Point3000", x=1.0)
    with pytest.raises(BagIOError, match="not a message type name"):
        make("Point2D")


@pytest.mark.parametrize("content", [b"", b"\x89MCAP0\r\n garbage that is not an mcap file"])
def test_unreadable_files_give_bag_io_error(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "broken.mcap"
    path.write_bytes(content)
    with pytest.raises(BagIOError):
        with bagio.open_bag(path) as bag:
            list(bag.messages())


def test_missing_and_wrong_paths_give_bag_io_error(tmp_path: Path) -> None:
    with pytest.raises(BagIOError, match="does not exist"):
        with bagio.open_bag(tmp_path / "nothing"):
            pass
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(BagIOError, match="neither"):
        with bagio.open_bag(tmp_path / "notes.txt"):
            pass
    with pytest.raises(BagIOError, match="without metadata.yaml"):
        with bagio.open_bag(tmp_path):
            pass


def test_typestore_is_cached_and_reads_msg_schemas(repo_root: Path) -> None:
    assert bagio.typestore() is bagio.typestore()
    assert bagio.schema_dir("signal_light_msgs") == repo_root / "msg_schemas" / \
        "signal_light_msgs" / "msg"
    names = {p.stem for p in (repo_root / "msg_schemas" / "vision_msgs" / "msg").glob("*.msg")}
    assert {f"vision_msgs/msg/{n}" for n in names} <= set(bagio.typestore().fielddefs)


def test_truncated_mcap_is_recovered_up_to_the_cut(tmp_path: Path) -> None:
    # A killed recorder leaves an MCAP without summary; complete chunks must still read.
    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 256, (120, 160, 3), dtype=np.uint8) for _ in range(40)]
    path = tmp_path / "killed"
    with bagio.BagWriter(path) as writer:
        writer.add_topic("/cam", "sensor_msgs/msg/Image")
        for i, frame in enumerate(frames):
            writer.write("/cam", T0 + i, make("sensor_msgs/msg/Image",
                                              header=make_header(T0 + i, "cam", make),
                                              **bgr_to_image_fields(frame)))
    data = (path / "killed.mcap").read_bytes()
    (path / "killed.mcap").write_bytes(data[: int(len(data) * 0.7)])
    (path / "metadata.yaml").unlink()
    with bagio.open_bag(path) as bag:
        count = bag.topics()["/cam"].count
        read = list(bag.messages())
    assert 0 < count < len(frames) and len(read) == count
    for i, item in enumerate(read):
        assert item.log_time_ns == T0 + i
        assert np.array_equal(np.asarray(item.msg.data), frames[i].reshape(-1))
