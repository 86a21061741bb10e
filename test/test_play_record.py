"""``signal-light play`` and ``signal-light record`` over a live graph, and the player's core.

The recorded bag is read back with the independent ``mcap`` + ``mcap_ros2`` reader.
"""

from __future__ import annotations

import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest

from signal_light_node.io.bagio import open_bag
from signal_light_node.errors import BagIOError, ConfigError
from signal_light_node.ros.bag_player import (Pacer, choose_topics, loop_gap_ns, parse_remaps,
                                               play_items)
from signal_light_node.synth.bag import write_scene_bag

N_FRAMES = 12
IMAGE = "/camera/image_raw/compressed"
DETECTIONS = "/camera/tracked_objects"


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("play") / "scene"
    write_scene_bag(path, seed=5, n_frames=N_FRAMES, width=320, height=180, fps=20.0,
                    n_vehicles=3, lighting="day", night_fraction=0.0)
    return path


# ------------------------------------------------------------------ core, no ROS graph
def test_choose_topics_by_type_or_by_name(bag):
    with open_bag(bag) as reader:
        topics = reader.topics()
    assert choose_topics(topics) == {IMAGE: "sensor_msgs/msg/CompressedImage",
                                     DETECTIONS: "vision_msgs/msg/Detection2DArray"}
    assert list(choose_topics(topics, ["/ground_truth/vehicle_lights"])) == [
        "/ground_truth/vehicle_lights"]
    with pytest.raises(BagIOError, match="/nope"):
        choose_topics(topics, ["/nope"])


def test_remaps_are_parsed_and_checked():
    assert parse_remaps(["/a:=/b", " /c := /d "]) == {"/a": "/b", "/c": "/d"}
    for bad in ("/a", ":=/b", "/a:="):
        with pytest.raises(ConfigError):
            parse_remaps([bad])


def test_play_items_are_cdr_in_order_with_offsets(bag):
    from signal_light_node.io.bagio import typestore

    with open_bag(bag) as reader:
        items = list(play_items(reader, choose_topics(reader.topics()),
                                {DETECTIONS: "/tracker/out"}))
    assert len(items) == 2 * N_FRAMES
    assert items[0].offset_ns == 0
    assert all(a.offset_ns <= b.offset_ns for a, b in zip(items, items[1:]))
    assert {i.topic for i in items} == {IMAGE, "/tracker/out"}
    msg = typestore().deserialize_cdr(items[1].data, items[1].msgtype)
    assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == items[1].stamp_ns
    # 20 fps: the last frame is 11 frame periods after the first.
    assert items[-1].offset_ns == pytest.approx(11 * 50_000_000, abs=1_000_000)
    assert loop_gap_ns(items[-1].offset_ns, N_FRAMES) == pytest.approx(50_000_000, rel=0.01)


def test_pacer_follows_the_rate_and_stops():
    now = [100.0]
    sleeps = []

    class FakeEvent(threading.Event):
        def wait(self, timeout=None):
            sleeps.append(timeout)
            now[0] += timeout
            return self.is_set()

    stop = FakeEvent()
    pacer = Pacer(2.0, stop, clock=lambda: now[0])
    assert pacer.wait(0)  # the first offset is due at once
    assert pacer.wait(1_000_000_000) and sleeps[-1] == pytest.approx(0.5)
    now[0] += 5.0  # far behind: due at once, nothing skipped
    count = len(sleeps)
    assert pacer.wait(2_000_000_000) and len(sleeps) == count
    stop.set()
    assert not pacer.wait(30_000_000_000)
    with pytest.raises(ConfigError):
        Pacer(0.0)


# ------------------------------------------------------------------ live graph
def _start(args, env, log: Path) -> subprocess.Popen:
    return subprocess.Popen(["signal-light", *args], env=env, stdout=open(log, "w"),
                            stderr=subprocess.STDOUT)


def _wait_for_line(log: Path, text: str, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while text not in log.read_text():
        assert proc.poll() is None, f"exited with {proc.returncode}:\n{log.read_text()}"
        assert time.monotonic() < deadline, f"no {text!r} after {timeout} s:\n{log.read_text()}"
        time.sleep(0.05)


def _read_mcap(bag_dir: Path) -> dict:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    (mcap_file,) = sorted(bag_dir.glob("*.mcap"))
    out: dict = {}
    with open(mcap_file, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, msg in reader.iter_decoded_messages():
            out.setdefault(channel.topic, []).append(msg)
    return out


def test_play_into_record_gives_a_bag_mcap_reads(bag, tmp_path, rclpy_isolated_env):
    env = rclpy_isolated_env()
    counted, interrupted = tmp_path / "counted", tmp_path / "interrupted"
    remapped = "/remapped/detections"
    # One recorder stops by itself after every message; the other runs until SIGINT.
    rec1 = _start(["record", "-o", str(counted), "--topics", IMAGE, remapped,
                   "--count", str(2 * N_FRAMES)], env, tmp_path / "rec1.log")
    rec2 = _start(["record", "-o", str(interrupted), "--topics", remapped, IMAGE], env,
                  tmp_path / "rec2.log")
    try:
        play = subprocess.run(
            ["signal-light", "play", str(bag), "--rate", "2", "--remap",
             f"{DETECTIONS}:={remapped}", "--wait-for-subscribers", "2", "--wait-timeout", "60"],
            env=env, capture_output=True, text=True, timeout=120)
        assert play.returncode == 0, play.stdout + play.stderr
        assert f"published {2 * N_FRAMES} messages" in play.stderr
        assert rec1.wait(60) == 0, (tmp_path / "rec1.log").read_text()
        _wait_for_line(tmp_path / "rec2.log", "recording all 2 topic", rec2)
        rec2.send_signal(signal.SIGINT)
        assert rec2.wait(30) == 0, (tmp_path / "rec2.log").read_text()
    finally:
        for proc in (rec1, rec2):
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)

    with open_bag(bag) as reader:
        source = {m.topic: m.msg for m in reader.messages([IMAGE, DETECTIONS])}
        stamps = [m.msg.header.stamp for m in reader.messages([IMAGE])]
    got = _read_mcap(counted)
    assert sorted(got) == sorted([IMAGE, remapped])
    assert len(got[IMAGE]) == N_FRAMES and len(got[remapped]) == N_FRAMES
    assert [(m.header.stamp.sec, m.header.stamp.nanosec) for m in got[IMAGE]] == \
        [(s.sec, s.nanosec) for s in stamps]
    last_image = got[IMAGE][-1]
    assert bytes(last_image.data) == bytes(source[IMAGE].data)
    assert [d.id for d in got[remapped][-1].detections] == \
        [d.id for d in source[DETECTIONS].detections]
    # The interrupted recording was closed properly: metadata and an indexed MCAP.
    assert (interrupted / "metadata.yaml").exists()
    assert {t: len(m) for t, m in _read_mcap(interrupted).items()} == {remapped: N_FRAMES,
                                                                       IMAGE: N_FRAMES}
    with open_bag(interrupted) as reader:
        assert reader.topics()[remapped].count == N_FRAMES


def test_play_gives_up_when_nobody_listens(bag, tmp_path, rclpy_isolated_env):
    play = subprocess.run(["signal-light", "play", str(bag), "--wait-for-subscribers", "1",
                           "--wait-timeout", "1"], env=rclpy_isolated_env(),
                          capture_output=True, text=True, timeout=60)
    assert play.returncode == 1
    assert "no 1 subscriber(s)" in play.stderr


def test_loop_plays_again_until_interrupted(bag, tmp_path, rclpy_isolated_env):
    env = rclpy_isolated_env()
    out = tmp_path / "looped"
    wanted = N_FRAMES + N_FRAMES // 2  # more than one pass holds
    rec = _start(["record", "-o", str(out), "--topics", DETECTIONS, "--count", str(wanted)],
                 env, tmp_path / "rec.log")
    player = _start(["play", str(bag), "--loop", "--rate", "4", "--topics", DETECTIONS,
                     "--wait-for-subscribers", "1", "--wait-timeout", "60"], env,
                    tmp_path / "play.log")
    try:
        assert rec.wait(90) == 0, (tmp_path / "rec.log").read_text()
        assert player.poll() is None, (tmp_path / "play.log").read_text()
        player.send_signal(signal.SIGINT)
        assert player.wait(30) == 0
    finally:
        for proc in (rec, player):
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
    assert "stopped by signal" in (tmp_path / "play.log").read_text()
    msgs = _read_mcap(out)[DETECTIONS]
    assert len(msgs) == wanted
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in msgs]
    # The second pass starts over: the stamps jump back to the first frame's.
    assert stamps[N_FRAMES] == stamps[0] and stamps[N_FRAMES - 1] > stamps[0]
