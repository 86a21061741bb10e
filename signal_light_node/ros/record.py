"""Record live topics into an MCAP bag (the body of ``signal-light record``).

The command-line options are in :mod:`signal_light_node.commands.record`.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from collections import Counter
from typing import Dict, List

from signal_light_node.errors import SignalLightError

LOG = logging.getLogger("signal_light_node.record")

#: How often the graph is checked for topics that are not subscribed yet.
_GRAPH_POLL_S = 0.2


def _flush(executor: object, counts: Counter, quiet_s: float = 0.3) -> None:
    """Write what has already arrived: spin until nothing came for ``quiet_s`` seconds."""
    quiet_until = time.monotonic() + quiet_s
    while time.monotonic() < quiet_until:
        before = sum(counts.values())
        executor.spin_once(timeout_sec=0.05)
        if sum(counts.values()) != before:
            quiet_until = time.monotonic() + quiet_s


def run(args: argparse.Namespace) -> int:
    """Record until a stop condition; returns the exit code."""
    from signal_light_node.io.bagio import BagWriter, normalize_msgtype, typestore
    from signal_light_node.ros.ros_io import message_class, qos, ros_context, stop_on_signals

    for name in ("duration", "idle_timeout"):
        value = getattr(args, name)
        if value is not None and not value > 0:
            raise SignalLightError(f"--{name.replace('_', '-')} must be > 0, got {value}")
    if args.count is not None and args.count < 1:
        raise SignalLightError(f"--count must be >= 1, got {args.count}")
    store = typestore()
    wanted: List[str] = list(dict.fromkeys(args.topics))
    counts: Counter = Counter()
    last_message = [0.0]

    with stop_on_signals() as stop, ros_context() as context, \
            BagWriter(args.output, overwrite=args.overwrite) as bag:
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        node = Node(f"signal_light_recorder_{os.getpid()}", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        subs: Dict[str, object] = {}

        def callback_for(topic: str, msgtype: str):
            def on_message(raw: bytes) -> None:
                now = time.time_ns()
                bag.write(topic, now, store.deserialize_cdr(raw, msgtype))
                counts[topic] += 1
                last_message[0] = time.monotonic()
                if args.count is not None and sum(counts.values()) >= args.count:
                    stop.set()
            return on_message

        def subscribe_new() -> None:
            graph = dict(node.get_topic_names_and_types())
            for topic in wanted:
                if topic in subs or topic not in graph:
                    continue
                msgtype = normalize_msgtype(graph[topic][0])
                bag.add_topic(topic, msgtype)
                subs[topic] = node.create_subscription(
                    message_class(msgtype), topic, callback_for(topic, msgtype),
                    qos(args.qos, args.depth), raw=True)
                LOG.info("recording %s [%s]", topic, msgtype)
                if len(subs) == len(wanted):
                    LOG.info("recording all %d topic(s) into %s", len(wanted), args.output)

        started = time.monotonic()
        next_poll = started
        try:
            while not stop.is_set():
                now = time.monotonic()
                if len(subs) < len(wanted) and now >= next_poll:
                    subscribe_new()
                    next_poll = now + _GRAPH_POLL_S
                if args.duration is not None and now - started >= args.duration:
                    break
                if (args.idle_timeout is not None and last_message[0]
                        and now - last_message[0] >= args.idle_timeout):
                    LOG.info("no message for %.1f s; stopping", args.idle_timeout)
                    break
                executor.spin_once(timeout_sec=0.05)
            if stop.is_set() and args.count is None:
                _flush(executor, counts)
        finally:
            executor.remove_node(node)
            node.destroy_node()
        missing = [t for t in wanted if t not in subs]
        if missing:
            LOG.warning("never saw topic(s) %s in the graph", ", ".join(missing))
        LOG.info("wrote %d messages to %s%s: %s", sum(counts.values()), args.output,
                 " (stopped by signal)" if stop.is_set() and args.count is None else "",
                 ", ".join(f"{t} {counts[t]}" for t in wanted))
    return 0
