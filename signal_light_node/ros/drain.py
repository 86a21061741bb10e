"""Wait until a running detector has finished every frame it was given.

``python -m signal_light_node.ros.drain --expect-images N`` listens to ``/diagnostics``
and returns 0 once the detector reports at least N images received or dropped by the
middleware, nothing waiting for a partner, an empty work queue and every pair accounted
for (published, undecodable ones included, dropped or failed); 1 on timeout. The demo uses it between "the bag has been played" and
"stop everything", so no frame still in flight is lost.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import List, Mapping, Optional

from signal_light_node.runtime.stats import DROP_COUNTERS
from signal_light_node.io.topics import DIAGNOSTICS_TOPIC, DIAGNOSTICS_TYPE

_STATUS_PREFIX = "signal_light_detector"


def drained(values: Mapping[str, str], expect_images: int) -> bool:
    """Whether one diagnostics report says the detector has nothing left to do."""
    try:
        n = {k: int(values[k]) for k in ("images", "paired", "outputs", "bad_images",
                                         "dropped_work_queue", "processing_errors",
                                         "work_queue_length", "pending_images",
                                         "pending_detections")}
    except (KeyError, ValueError):
        return False
    # Undecodable images are published (their boxes unjudged): they are outputs too.
    finished = n["outputs"] + n["dropped_work_queue"] + n["processing_errors"]
    arrived = n["images"] + int(values.get("dropped_image_middleware", 0))
    return (arrived >= expect_images and n["pending_images"] == 0
            and n["pending_detections"] == 0 and n["work_queue_length"] == 0
            and finished >= n["paired"])


def main(argv: Optional[List[str]] = None) -> int:
    """Command-line entry; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--expect-images", type=int, default=1,
                        help="images the detector must have received")
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds to wait at most")
    args = parser.parse_args(argv)

    from signal_light_node.ros.ros_io import message_class, qos, ros_context, stop_on_signals

    last: dict = {}
    with stop_on_signals() as stop, ros_context() as context:
        import rclpy

        node = rclpy.create_node("signal_light_drain_probe", context=context)

        def on_diagnostics(msg: object) -> None:
            for status in msg.status:
                if status.name.startswith(_STATUS_PREFIX):
                    last.clear()
                    last.update({kv.key: kv.value for kv in status.values})

        node.create_subscription(message_class(DIAGNOSTICS_TYPE), DIAGNOSTICS_TOPIC,
                                 on_diagnostics, qos("reliable", 10))
        executor = rclpy.executors.SingleThreadedExecutor(context=context)
        executor.add_node(node)
        deadline = time.monotonic() + args.timeout
        ok = False
        try:
            while not stop.is_set() and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.1)
                if last and drained(last, args.expect_images):
                    ok = True
                    break
        finally:
            executor.shutdown()
            node.destroy_node()
    if not ok:
        seen = ", ".join(f"{k}={last.get(k)}" for k in ("images", "paired", "outputs")
                         + DROP_COUNTERS if k in last) or "no diagnostics received"
        print(f"drain: the detector did not finish within {args.timeout:.0f} s ({seen})",
              file=sys.stderr)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
