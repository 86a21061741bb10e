"""The node's latency window, its diagnostics status and the demo's drain condition."""

from __future__ import annotations

import math

import pytest

from signal_light_node.ros.drain import drained
from signal_light_node.runtime.stats import (DROP_COUNTERS, ERROR, OK, WARN, LatencyWindow,
                                          Snapshot, health)

NAN4 = (0, math.nan, math.nan, math.nan)


def test_latency_window_keeps_the_latest_values():
    window = LatencyWindow(size=100)
    assert window.summary()[0] == 0 and math.isnan(window.summary()[1])
    for ms in range(1, 201):  # only 101..200 stay
        window.add(ms / 1000)
    n, mean, p95, worst = window.summary()
    assert n == 100
    assert mean == pytest.approx(0.1505) and worst == pytest.approx(0.2)
    assert 0.19 < p95 < 0.2


def _counters(**changes):
    base = {"images": 0, "detections": 0, "paired": 0, "outputs": 0, "worker_alive": 1}
    base.update({k: 0 for k in DROP_COUNTERS})
    base.update(changes)
    return base


def test_rates_and_values():
    before = Snapshot(10.0, _counters(images=10, detections=10, outputs=8))
    now = Snapshot(12.0, _counters(images=30, detections=30, outputs=28, paired=28))
    level, message, values = health(before, now, (5, 0.05, 0.08, 0.09), NAN4, NAN4,
                                    {"model_path": "/m.pt"})
    v = dict(values)
    assert level == OK and message == "ok"
    assert v["image_rate_hz"] == "10.00" and v["output_rate_hz"] == "10.00"
    assert v["latency_mean_ms"] == "50.0" and v["latency_p95_ms"] == "80.0"
    assert v["processing_mean_ms"] == "nan" and v["model_path"] == "/m.pt"
    assert all(k in v for k in DROP_COUNTERS)


def test_new_drops_warn_and_name_the_reason():
    before = Snapshot(0.0, _counters(images=5, dropped_work_queue=1))
    now = Snapshot(1.0, _counters(images=15, dropped_work_queue=4, bad_images=1))
    level, message, _ = health(before, now, NAN4, NAN4, NAN4, {})
    assert level == WARN
    assert "3 dropped_work_queue" in message and "1 bad_images" in message
    # Old drops alone do not warn again.
    level, _, _ = health(now, Snapshot(2.0, _counters(images=25, dropped_work_queue=4,
                                                      bad_images=1)), NAN4, NAN4, NAN4, {})
    assert level == OK


def test_idle_and_dead_worker():
    snap = Snapshot(0.0, _counters(images=5))
    assert health(snap, Snapshot(1.0, _counters(images=5)), NAN4, NAN4, NAN4, {})[1] == \
        "waiting for images"
    level, message, _ = health(snap, Snapshot(1.0, _counters(images=9, worker_alive=0)),
                               NAN4, NAN4, NAN4, {})
    assert level == ERROR and "worker" in message


def _values(**changes):
    base = {"images": "10", "paired": "10", "outputs": "10", "bad_images": "1",
            "dropped_work_queue": "0", "processing_errors": "0", "work_queue_length": "0",
            "pending_images": "0", "pending_detections": "0"}
    base.update({k: str(v) for k, v in changes.items()})
    return base


def test_drained_only_when_everything_is_accounted_for():
    assert drained(_values(), expect_images=10)
    assert not drained(_values(), expect_images=11)          # not all images arrived yet
    assert not drained(_values(outputs=9), expect_images=10)  # one frame still in the works
    # Two images lost in the middleware (counted) are accounted for as well.
    assert drained(_values(images=8, paired=8, outputs=8, dropped_image_middleware=2),
                   expect_images=10)
    assert not drained(_values(work_queue_length=1), expect_images=10)
    assert not drained(_values(pending_detections=2), expect_images=10)
    assert not drained({"images": "10"}, expect_images=1)    # an older node without the keys
