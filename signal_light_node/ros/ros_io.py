"""Small rclpy helpers shared by the node, ``signal-light play`` / ``record`` and the benchmark."""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from typing import Any, Callable, Iterator, List, Optional

import rclpy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from signal_light_node.ros.messages import rclpy_class

RELIABILITIES = ("reliable", "best_effort")


def qos(reliability: str, depth: int = 10) -> QoSProfile:
    """Keep-last, volatile QoS (the sensor-data shape) with the named reliability."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth),
                      reliability=(ReliabilityPolicy.RELIABLE if reliability == "reliable"
                                   else ReliabilityPolicy.BEST_EFFORT),
                      durability=DurabilityPolicy.VOLATILE)


def message_class(msgtype: str) -> type:
    """The rclpy class of ``pkg/msg/Name`` (resolved by the core's message factory)."""
    return rclpy_class(msgtype)


@contextlib.contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An event set by SIGINT or SIGTERM while the block runs; the old handlers come back after.

    Commands use it with ``rclpy.init(signal_handler_options=NO)`` so that Ctrl-C ends their
    loops cleanly (the bag is closed, the publishers are flushed) instead of raising.
    """
    stop = threading.Event()
    previous = {}

    def handler(signum: int, frame: Any) -> None:
        stop.set()

    on_main = threading.current_thread() is threading.main_thread()
    if on_main:
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, handler)
    try:
        yield stop
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


@contextlib.contextmanager
def ros_context(args: Optional[List[str]] = None) -> Iterator[Any]:
    """A private rclpy context without rclpy's own signal handlers, shut down on exit.

    ``args`` default to none at all: rclpy would otherwise parse ``sys.argv``, where a
    command's own ``FROM:=TO`` options look like (deprecated) ROS remap rules.
    """
    context = rclpy.Context()
    rclpy.init(args=list(args or []), context=context,
               signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    try:
        yield context
    finally:
        rclpy.try_shutdown(context=context)


def wait_until(condition: Callable[[], bool], timeout_s: float,
               stop: Optional[threading.Event] = None, poll_s: float = 0.05) -> bool:
    """Poll ``condition`` until it holds, the timeout passes or ``stop`` is set."""
    deadline = time.monotonic() + timeout_s
    while True:
        if condition():
            return True
        if time.monotonic() >= deadline or (stop is not None and stop.is_set()):
            return False
        if stop is not None:
            stop.wait(poll_s)
        else:
            time.sleep(poll_s)
