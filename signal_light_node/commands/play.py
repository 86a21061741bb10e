"""``signal-light play BAG``: publish a bag's image and detection topics into a live ROS graph.

Messages are published as the CDR bytes stored in the bag (re-serialized by rosbags),
so any message type works without conversion code, at the recorded pace times
``--rate``. Header stamps are kept as recorded.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``signal-light play``."""
    parser.add_argument("bag", help="rosbag2 directory or .mcap file")
    parser.add_argument("--rate", type=float, default=1.0,
                        help="speed factor relative to the recording (default 1.0)")
    parser.add_argument("--loop", action="store_true", help="start over at the end until stopped")
    parser.add_argument("--topics", nargs="+", metavar="TOPIC",
                        help="topics to play (default: every image, compressed image and "
                             "Detection2DArray topic)")
    parser.add_argument("--remap", nargs="+", default=[], metavar="FROM:=TO",
                        help="publish topic FROM under the name TO")
    parser.add_argument("--qos", choices=("reliable", "best_effort"), default="reliable",
                        help="reliability of the publishers (default reliable)")
    parser.add_argument("--depth", type=int, default=10, help="publisher queue depth")
    parser.add_argument("--wait-for-subscribers", type=int, default=0, metavar="N",
                        help="before playing, wait until every topic has N subscribers")
    parser.add_argument("--wait-timeout", type=float, default=30.0, metavar="S",
                        help="give up waiting for subscribers after S seconds (exit 1)")


def run(args: argparse.Namespace) -> int:
    """Run ``signal-light play``; returns the exit code (rclpy is imported by ``ros.play`` only)."""
    from signal_light_node.ros.play import run as run_ros

    return run_ros(args)
