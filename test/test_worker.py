"""The bounded drop-oldest work queue and its worker thread."""

from __future__ import annotations

import threading
import time

import pytest

from signal_light_node.errors import ConfigError
from signal_light_node.runtime.worker import DropOldestQueue, QueueClosed, Worker


def _wait_for(cond, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.005)


def test_queue_drops_oldest_when_full():
    q = DropOldestQueue(2)
    assert q.put(1) is None and q.put(2) is None
    assert q.put(3) == 1
    assert (q.get(), q.get()) == (2, 3)
    assert q.dropped == 1 and q.put_count == 3
    with pytest.raises(TimeoutError):
        q.get(timeout=0.01)


def test_queue_close_serves_waiting_items_then_raises():
    q = DropOldestQueue(3)
    q.put("a")
    q.close()
    assert q.put("late") == "late" and q.dropped == 1
    assert q.get() == "a"
    with pytest.raises(QueueClosed):
        q.get()


def test_queue_size_must_be_positive():
    with pytest.raises(ConfigError):
        DropOldestQueue(0)


def test_worker_processes_in_order_and_survives_errors():
    seen = []

    def process(item):
        if item == "bad":
            raise ValueError("broken frame")
        seen.append(item)

    q = DropOldestQueue(10)
    worker = Worker(q, process).start()
    for item in ["a", "bad", "b", "c"]:
        q.put(item)
    _wait_for(lambda: worker.processed == 3)
    assert seen == ["a", "b", "c"] and worker.errors == 1 and worker.alive
    assert worker.stop()
    assert not worker.alive


def test_slow_worker_drops_oldest_frames_and_stops_without_draining():
    gate = threading.Event()
    started = threading.Event()
    seen = []

    def process(item):
        started.set()
        gate.wait(5)
        seen.append(item)

    q = DropOldestQueue(2)
    worker = Worker(q, process).start()
    q.put(0)
    assert started.wait(5)  # 0 is in progress, the queue is empty again
    for item in range(1, 6):
        q.put(item)
    assert q.dropped == 3 and len(q) == 2  # 4 and 5 wait; 1, 2, 3 dropped
    gate.set()
    assert worker.stop(drain=False)
    assert seen == [0] and q.dropped == 5


def test_stop_with_drain_processes_what_waits():
    q = DropOldestQueue(5)
    seen = []
    worker = Worker(q, seen.append)
    for item in range(4):
        q.put(item)
    worker.start()
    assert worker.stop(drain=True)
    assert seen == [0, 1, 2, 3]
