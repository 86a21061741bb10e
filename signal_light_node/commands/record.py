"""``signal-light record -o OUT --topics ...``: write live topics into an MCAP bag.

Each topic is subscribed as soon as it shows up in the graph (its type is taken from
there) and received as raw CDR bytes, which rosbags deserializes with the project's
typestore and ``bagio.BagWriter`` writes; the log time is the receive time. Stops after
``--duration`` seconds, ``--count`` messages, ``--idle-timeout`` seconds without a
message, or on SIGINT/SIGTERM, always closing the bag properly.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``signal-light record``."""
    parser.add_argument("-o", "--output", required=True, help="bag directory to create")
    parser.add_argument("--topics", nargs="+", required=True, metavar="TOPIC",
                        help="topics to record (subscribed as soon as they appear)")
    parser.add_argument("--duration", type=float, metavar="S",
                        help="stop after S seconds")
    parser.add_argument("--count", type=int, metavar="N",
                        help="stop after N messages (all topics together)")
    parser.add_argument("--idle-timeout", type=float, metavar="S",
                        help="stop when nothing arrived for S seconds after the first message")
    parser.add_argument("--qos", choices=("reliable", "best_effort"), default="reliable",
                        help="reliability of the subscriptions (default reliable; "
                             "best_effort also hears best-effort publishers)")
    parser.add_argument("--depth", type=int, default=100, help="subscription queue depth")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing bag")


def run(args: argparse.Namespace) -> int:
    """Run ``signal-light record``; returns the exit code (rclpy is imported by ``ros.record`` only)."""
    from signal_light_node.ros.record import run as run_ros

    return run_ros(args)
