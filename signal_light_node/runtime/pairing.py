"""Pairing camera images with the tracker's detections by header stamp (no ROS types).

The tracker answers each image with a ``Detection2DArray`` that carries the image's stamp,
but the two arrive on different topics, in any order and possibly with losses. A
:class:`StampPairer` holds the messages still waiting for their partner in two bounded
buffers and hands out a :class:`Pair` as soon as both halves are there. Messages that
wait longer than the timeout, that are pushed out of a full buffer or that are replaced
by a newer message with the same stamp are dropped and counted by reason, so every input
is accounted for.

The node feeds a :class:`StampPairer` from its subscription callbacks; the bag tools
(``signal-light replay``, the training data of labelled bags) feed the same class with a
bag's messages in log-time order, the log time standing in for the receive time, through
:func:`pair_in_order`, so they pair exactly as a node with the same settings would.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Any, Callable, Deque, Dict, Iterable, Iterator, List, Optional, Tuple

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


_NS = 1_000_000_000

#: ``on_drop(kind, stamp_ns, item, reason)``: kind is :data:`IMAGE` or :data:`DETECTIONS`,
#: reason ``"timeout"``, ``"overflow"`` or ``"duplicate"``.
DropHook = Callable[[str, int, Any, str], None]


@dataclass(frozen=True)
class PairingConfig:
    """How images and detections are paired: the node's defaults, the tools' settings.

    Attributes:
        slop_s: 0 pairs identical stamps only; > 0 pairs the nearest stamps at most this
            many seconds apart (the node's ``sync_slop_s``).
        timeout_s: A message waits this long (receive time; log time in a bag) for its
            partner (``sync_timeout_s``).
        max_images: Images waiting for their detections (``image_queue_size``).
        max_detections: Detection arrays waiting for their image (``detection_queue_size``).

    Raises:
        ConfigError: A value is out of range, or the timeout does not exceed a slop.
    """

    slop_s: float = 0.0
    timeout_s: float = 1.0
    max_images: int = 10
    max_detections: int = 10

    def __post_init__(self) -> None:
        for name in ("slop_s", "timeout_s"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not math.isfinite(value):
                raise ConfigError(f"pairing {name} must be a number, got {value!r}")
            object.__setattr__(self, name, float(value))
        if self.slop_s < 0 or self.timeout_s <= 0:
            raise ConfigError(f"pairing needs slop >= 0 and timeout > 0 s, got slop "
                              f"{self.slop_s} s, timeout {self.timeout_s} s")
        if self.slop_s > 0 and self.timeout_s <= self.slop_s:
            raise ConfigError(f"the pairing timeout ({self.timeout_s} s) must exceed the slop "
                              f"({self.slop_s} s): a message must be able to wait for a "
                              "partner that is up to the slop away")

    def describe(self) -> str:
        """``exact`` or ``within S s``, for logs and summaries."""
        return "exact stamps" if self.slop_s == 0 else f"stamps within {self.slop_s:g} s"

    def pairer(self, on_drop: Optional[DropHook] = None) -> "StampPairer":
        """A :class:`StampPairer` with these settings."""
        return StampPairer(int(round(self.slop_s * _NS)), int(round(self.timeout_s * _NS)),
                           self.max_images, self.max_detections, on_drop=on_drop)


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
        on_drop: Called (under the pairer's lock; it must not call back into the pairer)
            with every message dropped, after it is counted.

    Raises:
        ConfigError: If a bound is not positive or the slop is negative.
    """

    def __init__(self, slop_ns: int = 0, timeout_ns: int = 1_000_000_000, max_images: int = 10,
                 max_detections: int = 10, on_drop: Optional[DropHook] = None) -> None:
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
        self._on_drop = on_drop

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

    def flush(self) -> int:
        """Drop every waiting message, counted as timed out (the end of a bag: no partner
        can come any more); returns how many."""
        with self._lock:
            dropped = 0
            for kind, waiting in self._waiting.items():
                while waiting:
                    stamp, (item, _) = waiting.popitem(last=False)
                    self._dropped(kind, stamp, item, "timeout")
                    dropped += 1
            return dropped

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
                old, _ = mine.pop(stamp_ns)
                self._dropped(kind, stamp_ns, old, "duplicate")
            mine[stamp_ns] = (item, now_ns)
            while len(mine) > self._limit[kind]:
                stamp, (old, _) = mine.popitem(last=False)
                self._dropped(kind, stamp, old, "overflow")
            return None

    def _dropped(self, kind: str, stamp_ns: int, item: Any, reason: str) -> None:
        self.counters[f"dropped_{kind}_{reason}"] += 1
        if self._on_drop is not None:
            self._on_drop(kind, stamp_ns, item, reason)

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
                stamp, (item, received) = next(iter(waiting.items()))
                if now_ns - received <= self.timeout_ns:
                    break  # arrival order: everything after it is younger
                del waiting[stamp]
                self._dropped(kind, stamp, item, "timeout")
                dropped += 1
        return dropped


@dataclass(frozen=True)
class PairedImage:
    """One image of a recorded stream with the detections a node would have paired with it.

    Attributes:
        stamp_ns: The image's stamp.
        image: What was passed to :meth:`OrderedPairing.add_image`.
        received_ns: Its receive (log) time.
        detections: The paired detections, or None: the node would have dropped this
            image (timed out, pushed out of a full buffer or replaced by a duplicate stamp).
        detections_stamp_ns: The detections' stamp (None when unpaired).
    """

    stamp_ns: int
    image: Any
    received_ns: int
    detections: Any = None
    detections_stamp_ns: Optional[int] = None

    @property
    def paired(self) -> bool:
        """Whether the image found its detections."""
        return self.detections_stamp_ns is not None


class _Slot:
    """An image waiting in :class:`OrderedPairing` until its fate is known."""

    __slots__ = ("stamp_ns", "image", "received_ns", "detections", "detections_stamp_ns",
                 "decided")

    def __init__(self, stamp_ns: int, image: Any, received_ns: int) -> None:
        self.stamp_ns, self.image, self.received_ns = int(stamp_ns), image, int(received_ns)
        self.detections: Any = None
        self.detections_stamp_ns: Optional[int] = None
        self.decided = False

    def decide(self, detections: Any, detections_stamp_ns: Optional[int]) -> None:
        self.detections, self.detections_stamp_ns = detections, detections_stamp_ns
        self.decided = True


class OrderedPairing:
    """The node's pairing over a recorded stream, every image released once, in arrival order.

    Messages go in in arrival (log-time) order with their receive time; they go through a
    :class:`StampPairer`, so the pairs are exactly the node's with the same
    :class:`PairingConfig`. An image comes out as soon as its fate is known (paired, or
    dropped as the node would drop it) and all earlier images have come out, so a
    consumer with recurrent state sees the images in their order. Memory: the images
    that wait, at most the timeout's worth (in receive time) plus ``max_images``.

    Args:
        config: The pairing settings.

    Attributes:
        pairer: The underlying pairer (its ``counters`` count inputs, pairs and drops).
        unpaired_detections: Detection arrays dropped without an image.
    """

    def __init__(self, config: PairingConfig = PairingConfig()) -> None:
        self.config = config
        self.pairer = config.pairer(on_drop=self._dropped)
        self.unpaired_detections = 0
        self._slots: Deque[_Slot] = deque()

    @property
    def counters(self) -> Dict[str, int]:
        """The pairer's counters (see :data:`COUNTERS`)."""
        return dict(self.pairer.counters)

    def add_image(self, stamp_ns: int, image: Any, received_ns: int) -> List[PairedImage]:
        """Offer an image; returns the images released by it (maybe none, maybe several)."""
        slot = _Slot(stamp_ns, image, received_ns)
        self._slots.append(slot)
        pair = self.pairer.add_image(slot.stamp_ns, slot, slot.received_ns)
        if pair is not None:
            slot.decide(pair.detections, pair.detections_stamp_ns)
        return self._release()

    def add_detections(self, stamp_ns: int, detections: Any,
                       received_ns: int) -> List[PairedImage]:
        """Offer a detection array; returns the images released by it."""
        pair = self.pairer.add_detections(int(stamp_ns), detections, int(received_ns))
        if pair is not None:
            pair.image.decide(detections, int(stamp_ns))
        return self._release()

    def finish(self) -> List[PairedImage]:
        """The end of the stream: every waiting message is dropped (as timed out); returns
        the images still held back."""
        self.pairer.flush()
        return self._release()

    def _dropped(self, kind: str, stamp_ns: int, item: Any, reason: str) -> None:
        if kind == IMAGE:
            item.decide(None, None)
        else:
            self.unpaired_detections += 1

    def _release(self) -> List[PairedImage]:
        out = []
        while self._slots and self._slots[0].decided:
            s = self._slots.popleft()
            out.append(PairedImage(s.stamp_ns, s.image, s.received_ns, s.detections,
                                   s.detections_stamp_ns))
        return out


def pair_in_order(messages: Iterable[Tuple[str, int, Any, int]],
                  pairing: OrderedPairing) -> Iterator[PairedImage]:
    """Run a stream through ``pairing``: every image once, in arrival order.

    Args:
        messages: ``(kind, stamp_ns, item, received_ns)`` in arrival order, ``kind``
            :data:`IMAGE` or :data:`DETECTIONS`.
        pairing: The pairing (read its counters afterwards).

    Yields:
        :class:`PairedImage` per image, the unpaired ones included.
    """
    for kind, stamp_ns, item, received_ns in messages:
        add = pairing.add_image if kind == IMAGE else pairing.add_detections
        yield from add(stamp_ns, item, received_ns)
    yield from pairing.finish()
