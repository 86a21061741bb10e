"""Publish a bag's topics into a live ROS graph (the body of ``signal-light play``).

The command-line options are in :mod:`signal_light_node.commands.play`.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from collections import Counter
from typing import Dict

from signal_light_node.errors import SignalLightError

LOG = logging.getLogger("signal_light_node.play")


def run(args: argparse.Namespace) -> int:
    """Play the bag; returns the exit code (0 also when stopped by SIGINT/SIGTERM)."""
    from signal_light_node.io.bagio import open_bag
    from signal_light_node.ros.bag_player import (Pacer, choose_topics, loop_gap_ns,
                                                   parse_remaps, play_items)
    from signal_light_node.ros.ros_io import (message_class, qos, ros_context,
                                               stop_on_signals, wait_until)

    if not args.rate > 0:
        raise SignalLightError(f"--rate must be > 0, got {args.rate}")
    remaps = parse_remaps(args.remap)
    with stop_on_signals() as stop, ros_context() as context, open_bag(args.bag) as bag:
        topics = choose_topics(bag.topics(), args.topics)
        node = _node(context)
        try:
            pubs: Dict[str, object] = {}
            for topic, msgtype in topics.items():
                name = remaps.get(topic, topic)
                pubs[name] = node.create_publisher(message_class(msgtype), name,
                                                   qos(args.qos, args.depth))
                LOG.info("playing %s [%s]%s", topic, msgtype,
                         f" as {name}" if name != topic else "")
            if args.wait_for_subscribers > 0:
                need = args.wait_for_subscribers
                ok = wait_until(lambda: all(p.get_subscription_count() >= need
                                            for p in pubs.values()), args.wait_timeout, stop)
                if not ok and not stop.is_set():
                    missing = [t for t, p in pubs.items() if p.get_subscription_count() < need]
                    LOG.error("no %d subscriber(s) on %s after %.1f s", need,
                              ", ".join(missing), args.wait_timeout)
                    return 1
            sent: Counter = Counter()
            pacer = Pacer(args.rate, stop)
            started = time.monotonic()
            passes = 0
            while not stop.is_set():
                pacer.restart()
                last, count = 0, 0
                for item in play_items(bag, topics, remaps):
                    if not pacer.wait(item.offset_ns):
                        break
                    pubs[item.topic].publish(item.data)
                    sent[item.topic] += 1
                    last, count = item.offset_ns, count + 1
                passes += 1
                if not args.loop or count == 0:
                    break
                stop.wait(loop_gap_ns(last, count) / 1e9 / args.rate)
            _flush(pubs, args.qos)
            LOG.info("published %d messages in %.1f s (%d pass%s%s): %s", sum(sent.values()),
                     time.monotonic() - started, passes, "" if passes == 1 else "es",
                     ", stopped by signal" if stop.is_set() else "",
                     ", ".join(f"{t} {n}" for t, n in sorted(sent.items())))
        finally:
            node.destroy_node()
    return 0


def _node(context: object) -> object:
    from rclpy.node import Node

    # One player per process; the pid keeps two players in one graph apart.
    return Node(f"signal_light_player_{os.getpid()}", context=context)


def _flush(pubs: Dict[str, object], reliability: str) -> None:
    """Give reliable subscribers the chance to fetch the last messages before we go."""
    if reliability != "reliable":
        return
    from rclpy.duration import Duration

    for pub in pubs.values():
        if pub.get_subscription_count() > 0:
            pub.wait_for_all_acked(Duration(seconds=5))
