"""Stamp pairing of images and detections: exact, with slop, timeouts, overflow, duplicates."""

from __future__ import annotations

import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.runtime.pairing import COUNTERS, StampPairer

MS = 1_000_000


def test_exact_pairing_in_either_order():
    p = StampPairer()
    assert p.add_image(100, "img100", now_ns=0) is None
    pair = p.add_detections(100, "det100", now_ns=5)
    assert (pair.stamp_ns, pair.image, pair.detections) == (100, "img100", "det100")
    assert (pair.image_received_ns, pair.detections_received_ns) == (0, 5)
    assert p.add_detections(200, "det200", now_ns=6) is None
    pair = p.add_image(200, "img200", now_ns=7)
    assert (pair.image, pair.detections, pair.detections_stamp_ns) == ("img200", "det200", 200)
    assert p.pending == (0, 0)
    assert p.counters["paired"] == 2 and p.counters["images"] == 2


def test_exact_mode_does_not_pair_near_stamps():
    p = StampPairer(slop_ns=0)
    p.add_image(100 * MS, "img", now_ns=0)
    assert p.add_detections(100 * MS + 1, "det", now_ns=0) is None
    assert p.pending == (1, 1)


def test_slop_pairs_the_nearest_within_the_slop_and_keeps_the_image_stamp():
    p = StampPairer(slop_ns=10 * MS)
    p.add_detections(100 * MS, "far", now_ns=0)
    p.add_detections(104 * MS, "near", now_ns=0)
    pair = p.add_image(105 * MS, "img", now_ns=0)
    assert pair.detections == "near" and pair.stamp_ns == 105 * MS
    assert pair.detections_stamp_ns == 104 * MS
    # Out of the slop: waits instead.
    assert p.add_image(200 * MS, "img2", now_ns=0) is None
    assert p.pending == (1, 1)


def test_slop_tie_goes_to_the_earlier_arrival():
    p = StampPairer(slop_ns=10 * MS)
    p.add_image(110 * MS, "second", now_ns=1)
    p.add_image(90 * MS, "first", now_ns=0)
    assert p.add_detections(100 * MS, "det", now_ns=2).image == "second"


def test_unpaired_messages_time_out_and_are_counted():
    p = StampPairer(timeout_ns=100 * MS)
    p.add_image(1, "a", now_ns=0)
    p.add_detections(2, "b", now_ns=50 * MS)
    assert p.expire(now_ns=100 * MS) == 0
    assert p.expire(now_ns=120 * MS) == 1
    assert p.counters["dropped_image_timeout"] == 1 and p.pending == (0, 1)
    # Adding also expires: the late partner of the dropped image finds nothing.
    assert p.add_detections(1, "late", now_ns=200 * MS) is None
    assert p.counters["dropped_detections_timeout"] == 1


def test_full_buffers_drop_the_oldest():
    p = StampPairer(max_images=3, max_detections=2)
    for i in range(5):
        p.add_image(i, f"img{i}", now_ns=i)
    assert p.counters["dropped_image_overflow"] == 2
    assert p.add_detections(0, "d0", now_ns=6) is None  # img0 was pushed out
    assert p.add_detections(4, "d4", now_ns=7).image == "img4"
    for i in range(10, 13):
        p.add_detections(i, "d", now_ns=8)
    assert p.counters["dropped_detections_overflow"] == 2


def test_repeated_stamp_replaces_the_waiting_message():
    p = StampPairer()
    p.add_image(5, "old", now_ns=0)
    p.add_image(5, "new", now_ns=1)
    assert p.counters["dropped_image_duplicate"] == 1
    assert p.add_detections(5, "det", now_ns=2).image == "new"


def test_every_message_is_accounted_for():
    p = StampPairer(timeout_ns=10, max_images=2, max_detections=2)
    now = 0
    for i in range(20):
        now += 3
        p.add_image(i, i, now)
        if i % 3:
            p.add_detections(i, i, now)
        if i % 5 == 0:
            p.add_detections(1000 + i, i, now)  # never has an image
    p.expire(now + 100)
    c = p.counters
    assert set(c) == set(COUNTERS)
    dropped_images = sum(c[k] for k in c if k.startswith("dropped_image"))
    dropped_dets = sum(c[k] for k in c if k.startswith("dropped_detections"))
    assert c["paired"] + dropped_images == c["images"]
    assert c["paired"] + dropped_dets == c["detections"]
    assert p.pending == (0, 0)


def test_reconfigure_and_bad_arguments():
    p = StampPairer()
    p.configure(slop_ns=5, timeout_ns=10)
    p.add_image(100, "img", now_ns=0)
    assert p.add_detections(104, "det", now_ns=0) is not None
    with pytest.raises(ConfigError):
        p.configure(slop_ns=-1, timeout_ns=10)
    with pytest.raises(ConfigError):
        StampPairer(max_images=0)
