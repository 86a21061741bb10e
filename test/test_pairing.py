"""Stamp pairing of images and detections: exact, with slop, timeouts, overflow, duplicates."""

from __future__ import annotations

import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.runtime.pairing import (COUNTERS, DETECTIONS, IMAGE, OrderedPairing,
                                            PairingConfig, StampPairer, pair_in_order)

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


# ------------------------------------------------- drops reported, offline (bag) pairing


def test_every_drop_is_reported_with_its_item_and_reason():
    drops = []
    p = StampPairer(timeout_ns=10, max_images=2, on_drop=lambda *d: drops.append(d))
    p.add_image(1, "a", now_ns=0)
    p.add_image(1, "a2", now_ns=1)           # duplicate stamp: "a" goes
    p.add_image(2, "b", now_ns=2)
    p.add_image(3, "c", now_ns=3)            # overflow: "a2" goes
    p.add_detections(9, "d", now_ns=30)      # expires "b" and "c" first
    assert drops == [("image", 1, "a", "duplicate"), ("image", 1, "a2", "overflow"),
                     ("image", 2, "b", "timeout"), ("image", 3, "c", "timeout")]
    assert p.flush() == 1 and drops[-1] == ("detections", 9, "d", "timeout")
    assert p.pending == (0, 0) and p.counters["dropped_detections_timeout"] == 1


def test_pairing_config_validates_and_builds_the_pairer():
    config = PairingConfig(slop_s=0.02, timeout_s=0.5, max_images=3, max_detections=4)
    p = config.pairer()
    assert (p.slop_ns, p.timeout_ns) == (20 * MS, 500 * MS)
    assert config.describe() == "stamps within 0.02 s"
    assert PairingConfig().describe() == "exact stamps"
    for bad in (dict(slop_s=-0.1), dict(timeout_s=0), dict(slop_s=0.5, timeout_s=0.4),
                dict(slop_s=float("nan")), dict(timeout_s="1")):
        with pytest.raises(ConfigError):
            PairingConfig(**bad)


def _run(events, config=PairingConfig()):
    pairing = OrderedPairing(config)
    out = list(pair_in_order(events, pairing))
    return [(f.image, f.detections) for f in out], pairing


def test_ordered_pairing_releases_every_image_once_in_arrival_order():
    events = [
        (IMAGE, 100 * MS, "i1", 0),
        (IMAGE, 200 * MS, "i2", 100 * MS),          # its detections never come
        (DETECTIONS, 100 * MS, "d1", 105 * MS),     # after its image
        (DETECTIONS, 300 * MS, "d3", 290 * MS),     # before its image
        (IMAGE, 300 * MS, "i3", 300 * MS),
        (DETECTIONS, 999 * MS, "lonely", 310 * MS),
        (IMAGE, 400 * MS, "i4", 1500 * MS),         # i2 and the lonely one time out first
    ]
    got, pairing = _run(events)
    assert got == [("i1", "d1"), ("i2", None), ("i3", "d3"), ("i4", None)]
    c = pairing.counters
    assert (c["images"], c["detections"], c["paired"]) == (4, 3, 2)
    assert c["dropped_image_timeout"] == 2  # i2 by the timeout, i4 at the end
    assert pairing.unpaired_detections == 1


def test_ordered_pairing_holds_later_images_until_an_earlier_one_is_decided():
    pairing = OrderedPairing()
    assert pairing.add_image(1, "a", 0) == []
    assert pairing.add_image(2, "b", 1) == []
    assert pairing.add_detections(2, "db", 2) == []    # b is paired, a still waits
    released = pairing.add_detections(1, "da", 3)
    assert [(f.image, f.detections, f.paired) for f in released] == \
        [("a", "da", True), ("b", "db", True)]
    assert pairing.finish() == []


def test_ordered_pairing_with_slop_is_the_node_pairers_greedy_choice():
    # Jittered detection stamps: exact pairing drops them, a slop pairs them, and in the
    # same way as a StampPairer fed the same stream (nearest waiting partner on arrival).
    events = []
    for i in range(30):
        stamp = i * 100 * MS
        jitter = (i % 5 - 2) * 3 * MS
        events += [(IMAGE, stamp, f"i{i}", stamp + 10 * MS),
                   (DETECTIONS, stamp + jitter, f"d{i}", stamp + (5 if i % 2 else 15) * MS)]
    events.sort(key=lambda e: e[3])
    exact, _ = _run(events)
    assert [d for _, d in exact] == [f"d{i}" if i % 5 == 2 else None for i in range(30)]
    config = PairingConfig(slop_s=0.01)
    slop, pairing = _run(events, config)
    reference, pairs = config.pairer(), {}
    for kind, stamp, item, now in events:
        pair = (reference.add_image if kind == IMAGE else reference.add_detections)(
            stamp, item, now)
        if pair is not None:
            pairs[pair.image] = pair.detections
    assert slop == [(f"i{i}", pairs.get(f"i{i}")) for i in range(30)]
    assert all(d == f"d{i}" for i, (_, d) in enumerate(slop))
    assert pairing.counters == {**reference.counters}
