"""Pairing camera images with the tracker's detections by header stamp (no ROS types).

The tracker answers each image with a ``Detection2DArray`` that carries the image's stamp,
but the two arrive on different topics, in any order and possibly with losses. A
:class:`StampPairer` holds the messages still waiting for their partner in two bounded
buffers and hands out a :class:`Pair` as soon as both halves are there. Messages that
wait longer than the timeout, that are pushed out of a full buffer or that are replaced
by a newer message with the same stamp are dropped and counted by reason, so every input
is accounted for.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Dict, Optional, Tuple

from signal_light_node.errors import ConfigError

IMAGE = "image"
DETECTIONS = "detections"

#: Counter names, for diagnostics and tests.
COUNTERS: Tuple[str, ...] = (
    "images", "detections", "paired",
    "dropped_image_timeout", "dropped_detections_timeout",
    "dropped_image_overflow", "dropped_detections_overflow",
    "dropped_image_duplicate", "dropped_detections_duplicate",
)


@dataclass(frozen=True)
class Pair:
    """An image and the detections that belong to it.

    Attributes:
        stamp_ns: The image's stamp (the output is stamped with it).
        image: Whatever was passed to ``add_image`` (a message, usually).
        detections: Whatever was passed to ``add_detections``.
        image_received_ns: When the image was added (the caller's clock).
        detections_received_ns: When the detections were added.
        detections_stamp_ns: The detections' stamp (differs from ``stamp_ns`` only with a slop).
    """

    stamp_ns: int
    image: Any
    detections: Any
    image_received_ns: int
    detections_received_ns: int
    detections_stamp_ns: int


class StampPairer:
    """Pairs images and detections by stamp, exactly or within a slop.

    Thread-safe: the subscription callbacks and a parameter update may call it concurrently.

    Args:
        slop_ns: 0 pairs identical stamps only; > 0 pairs a message with the waiting
            partner whose stamp is nearest, if it is at most this far away.
        timeout_ns: A message waiting longer than this (receive time) is dropped.
        max_images: At most this many images wait; a new one pushes out the oldest.
        max_detections: At most this many detection arrays wait.

    Raises:
        ConfigError: If a bound is not positive or the slop is negative.
    """

    def __init__(self, slop_ns: int = 0, timeout_ns: int = 1_000_000_000, max_images: int = 10,
                 max_detections: int = 10) -> None:
        if max_images < 1 or max_detections < 1:
            raise ConfigError(f"pairing buffers must hold at least 1 message, got "
                              f"max_images={max_images}, max_detections={max_detections}")
        self._lock = threading.Lock()
        self.configure(slop_ns, timeout_ns)
        self._limit = {IMAGE: int(max_images), DETECTIONS: int(max_detections)}
        # stamp -> (item, received_ns); insertion order is arrival order.
        self._waiting: Dict[str, "OrderedDict[int, Tuple[Any, int]]"] = {
            IMAGE: OrderedDict(), DETECTIONS: OrderedDict()}
        self.counters: Dict[str, int] = {name: 0 for name in COUNTERS}

    def configure(self, slop_ns: int, timeout_ns: int) -> None:
        """Change slop and timeout (takes effect for the next message).

        Raises:
            ConfigError: If the slop is negative or the timeout not positive.
        """
        if slop_ns < 0 or timeout_ns <= 0:
            raise ConfigError(f"pairing needs slop >= 0 and timeout > 0, got slop={slop_ns} ns, "
                              f"timeout={timeout_ns} ns")
        with self._lock:
            self.slop_ns = int(slop_ns)
            self.timeout_ns = int(timeout_ns)

    def add_image(self, stamp_ns: int, image: Any, now_ns: int) -> Optional[Pair]:
        """Offer an image; returns the pair it completes, if any."""
        return self._add(IMAGE, stamp_ns, image, now_ns)

    def add_detections(self, stamp_ns: int, detections: Any, now_ns: int) -> Optional[Pair]:
        """Offer a detection array; returns the pair it completes, if any."""
        return self._add(DETECTIONS, stamp_ns, detections, now_ns)

    def expire(self, now_ns: int) -> int:
        """Drop every message that has waited longer than the timeout; returns how many."""
        with self._lock:
            return self._expire(now_ns)

    @property
    def pending(self) -> Tuple[int, int]:
        """(images, detection arrays) waiting for a partner."""
        with self._lock:
            return len(self._waiting[IMAGE]), len(self._waiting[DETECTIONS])

    def _add(self, kind: str, stamp_ns: int, item: Any, now_ns: int) -> Optional[Pair]:
        other = DETECTIONS if kind == IMAGE else IMAGE
        stamp_ns = int(stamp_ns)
        with self._lock:
            self.counters["images" if kind == IMAGE else "detections"] += 1
            self._expire(now_ns)
            match = self._find(self._waiting[other], stamp_ns)
            if match is not None:
                partner, partner_recv = self._waiting[other].pop(match)
                self.counters["paired"] += 1
                if kind == IMAGE:
                    return Pair(stamp_ns, item, partner, now_ns, partner_recv, match)
                return Pair(match, partner, item, partner_recv, now_ns, stamp_ns)
            mine = self._waiting[kind]
            if stamp_ns in mine:
                # A repeated stamp (a restarted source): the newer message wins.
                del mine[stamp_ns]
                self.counters[f"dropped_{kind}_duplicate"] += 1
            mine[stamp_ns] = (item, now_ns)
            while len(mine) > self._limit[kind]:
                mine.popitem(last=False)
                self.counters[f"dropped_{kind}_overflow"] += 1
            return None

    def _find(self, waiting: "OrderedDict[int, Tuple[Any, int]]", stamp_ns: int) -> Optional[int]:
        if stamp_ns in waiting:
            return stamp_ns
        if self.slop_ns == 0 or not waiting:
            return None
        # Nearest stamp within the slop; on a tie the one that arrived first.
        best = min(waiting, key=lambda s: abs(s - stamp_ns))
        return best if abs(best - stamp_ns) <= self.slop_ns else None

    def _expire(self, now_ns: int) -> int:
        dropped = 0
        for kind, waiting in self._waiting.items():
            while waiting:
                stamp, (_, received) = next(iter(waiting.items()))
                if now_ns - received <= self.timeout_ns:
                    break  # arrival order: everything after it is younger
                del waiting[stamp]
                self.counters[f"dropped_{kind}_timeout"] += 1
                dropped += 1
        return dropped
