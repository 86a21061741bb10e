"""Running figures of the detector node and the status built from them (no ROS types).

:class:`LatencyWindow` keeps the latest per-frame latencies for mean and p95;
:func:`health` turns two successive counter snapshots into the level, message and
key/value pairs of a ``diagnostic_msgs/DiagnosticStatus``, so the node only copies them
into a message.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass
from typing import Deque, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

#: ``diagnostic_msgs/DiagnosticStatus`` levels.
OK, WARN, ERROR = 0, 1, 2

#: Counters whose growth means input was lost or could not be used; each is reported
#: and raises WARN. Images and detection arrays published = received + ``*_middleware``
#: (for a publisher already running when the node subscribed: from its first delivered
#: message; ``ros/gaps.py``); every image received ends as an output (bad and oversized
#: ones published unjudged) or in one ``dropped_*`` counter, every detection array
#: received as paired or in one ``dropped_detections_*`` counter (or still waiting).
DROP_COUNTERS: Tuple[str, ...] = (
    "dropped_image_middleware", "dropped_detections_middleware",
    "dropped_image_timeout", "dropped_detections_timeout", "dropped_image_overflow",
    "dropped_detections_overflow", "dropped_image_duplicate", "dropped_detections_duplicate",
    "dropped_work_queue", "bad_images", "oversized_images", "processing_errors",
)


class LatencyWindow:
    """Thread-safe window of the latest ``size`` latencies (seconds).

    Args:
        size: How many of the latest values the figures cover.
    """

    def __init__(self, size: int = 1000) -> None:
        self._values: Deque[float] = deque(maxlen=int(size))
        self._lock = threading.Lock()

    def add(self, seconds: float) -> None:
        """Record one latency."""
        with self._lock:
            self._values.append(float(seconds))

    def summary(self) -> Tuple[int, float, float, float]:
        """``(n, mean, p95, max)`` in seconds over the window; NaNs when empty."""
        with self._lock:
            values = np.fromiter(self._values, dtype=np.float64)
        if values.size == 0:
            return 0, math.nan, math.nan, math.nan
        return (int(values.size), float(values.mean()), float(np.percentile(values, 95)),
                float(values.max()))


class StageWindows:
    """A :class:`LatencyWindow` per stage of a frame's processing (decode, crops, step...).

    Args:
        stages: The stage names, in the order they are reported.
        size: How many of the latest frames each window covers.
    """

    def __init__(self, stages: Sequence[str], size: int = 1000) -> None:
        self.stages: Tuple[str, ...] = tuple(stages)
        self._windows = {stage: LatencyWindow(size) for stage in self.stages}

    def add(self, times_s: Mapping[str, float]) -> None:
        """Record one frame's stage times (seconds); stages not named are left alone."""
        for stage, seconds in times_s.items():
            window = self._windows.get(stage)
            if window is not None:
                window.add(seconds)

    def summary(self) -> Dict[str, Tuple[int, float, float, float]]:
        """Per stage ``LatencyWindow.summary()``: ``(n, mean, p95, max)`` in seconds."""
        return {stage: self._windows[stage].summary() for stage in self.stages}

    def values(self) -> List[Tuple[str, str]]:
        """``stage_<name>_mean_ms`` and ``stage_<name>_p95_ms`` key/values for diagnostics."""
        out: List[Tuple[str, str]] = []
        for stage, (_, mean, p95, _) in self.summary().items():
            out += [(f"stage_{stage}_mean_ms", _ms(mean)), (f"stage_{stage}_p95_ms", _ms(p95))]
        return out


@dataclass(frozen=True)
class Snapshot:
    """Counters of the node at one instant.

    Attributes:
        time_s: Monotonic time of the snapshot.
        counters: Totals since start (images, detections, paired, outputs, drops...).
    """

    time_s: float
    counters: Mapping[str, int]


def _ms(seconds: float) -> str:
    return "nan" if math.isnan(seconds) else f"{seconds * 1e3:.1f}"


def health(previous: Optional[Snapshot], current: Snapshot,
           latency: Tuple[int, float, float, float],
           processing: Tuple[int, float, float, float],
           engine: Tuple[int, float, float, float],
           extra: Mapping[str, object]) -> Tuple[int, str, List[Tuple[str, str]]]:
    """The node's status for one diagnostics period.

    Args:
        previous: The snapshot of the previous period (None on the first).
        current: The snapshot now.
        latency: ``LatencyWindow.summary()`` of image receipt -> output published.
        processing: Same for pair complete -> output published.
        engine: Same for the engine's ``process`` alone (crops, model step, results).
        extra: Further key/values to append (model path, device, active tracks...).

    Returns:
        ``(level, message, [(key, value), ...])``.
    """
    now = dict(current.counters)
    before = dict(previous.counters) if previous else {k: 0 for k in now}
    elapsed = current.time_s - previous.time_s if previous else 0.0

    def rate(key: str) -> str:
        if elapsed <= 0:
            return "nan"
        return f"{(now.get(key, 0) - before.get(key, 0)) / elapsed:.2f}"

    values: List[Tuple[str, str]] = [
        ("image_rate_hz", rate("images")),
        ("detections_rate_hz", rate("detections")),
        ("output_rate_hz", rate("outputs")),
    ]
    values += [(key, str(int(now.get(key, 0)))) for key in
               ("images", "detections", "paired", "outputs") + DROP_COUNTERS]
    n, mean, p95, worst = latency
    values += [("latency_frames", str(n)), ("latency_mean_ms", _ms(mean)),
               ("latency_p95_ms", _ms(p95)), ("latency_max_ms", _ms(worst))]
    _, pmean, pp95, _ = processing
    values += [("processing_mean_ms", _ms(pmean)), ("processing_p95_ms", _ms(pp95))]
    _, emean, ep95, _ = engine
    values += [("engine_mean_ms", _ms(emean)), ("engine_p95_ms", _ms(ep95))]
    values += [(k, str(v)) for k, v in extra.items()]

    new_drops = {k: now.get(k, 0) - before.get(k, 0) for k in DROP_COUNTERS}
    new_drops = {k: v for k, v in new_drops.items() if v > 0}
    if now.get("worker_alive", 1) == 0:
        return ERROR, "inference worker stopped; no output will be published", values
    if new_drops:
        what = ", ".join(f"{v} {k}" for k, v in sorted(new_drops.items()))
        return WARN, f"lost or unusable input in the last {elapsed:.1f} s: {what}", values
    if previous is not None and now.get("images", 0) == before.get("images", 0):
        return OK, "waiting for images", values
    return OK, "ok", values
