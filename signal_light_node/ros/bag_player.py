"""What ``signal-light play`` publishes and when (no ROS types).

rosbag2's player is not available as a wheel, so ``signal-light play`` replays a bag
itself. This module decides the topics (by type unless named), applies remappings,
serializes each message back to CDR (the bytes an rclpy publisher sends as they are, so
no per-type conversion code is needed) and paces them at the recorded speed times a rate.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Callable, Dict, Iterator, Mapping, Optional, Sequence

from signal_light_node.io.bagio import BagReader, normalize_msgtype, typestore
from signal_light_node.errors import BagIOError, ConfigError
from signal_light_node.io.topics import DETECTIONS_TYPE, IMAGE_TYPES

#: Types that ``play`` publishes when no topics are named: the detector's inputs.
INPUT_TYPES = IMAGE_TYPES + (DETECTIONS_TYPE,)


@dataclass(frozen=True)
class PlayItem:
    """One message to publish.

    Attributes:
        offset_ns: Bag time since the first played message of this pass.
        topic: Topic to publish on (after remapping).
        msgtype: ``pkg/msg/Name``.
        data: The serialized message (CDR with encapsulation header).
        stamp_ns: The message's ``header.stamp`` when it has one, else None.
    """

    offset_ns: int
    topic: str
    msgtype: str
    data: bytes
    stamp_ns: Optional[int]


def parse_remaps(items: Optional[Sequence[str]]) -> Dict[str, str]:
    """``["/a:=/b", ...]`` -> ``{"/a": "/b"}``.

    Raises:
        ConfigError: If an item is not ``FROM:=TO`` with both sides non-empty.
    """
    out: Dict[str, str] = {}
    for item in items or ():
        src, sep, dst = item.partition(":=")
        if not sep or not src.strip() or not dst.strip():
            raise ConfigError(f"remap {item!r} is not FROM:=TO")
        out[src.strip()] = dst.strip()
    return out


def choose_topics(topics: Mapping[str, object], wanted: Optional[Sequence[str]] = None
                  ) -> Dict[str, str]:
    """Topics to play with their types.

    Args:
        topics: ``BagReader.topics()`` (topic -> ``TopicInfo``).
        wanted: Topics named by the user; None = every topic of one of ``INPUT_TYPES``.

    Returns:
        topic -> msgtype, in the bag's topic order.

    Raises:
        BagIOError: A named topic is not in the bag, or nothing is left to play.
    """
    types = {t: normalize_msgtype(info.msgtype.split("|")[0]) for t, info in topics.items()}
    if wanted:
        missing = [t for t in wanted if t not in types]
        if missing:
            raise BagIOError(f"topic(s) {', '.join(missing)} not in the bag (it has "
                             f"{', '.join(types) or 'no topics'})")
        chosen = {t: types[t] for t in types if t in set(wanted)}
    else:
        chosen = {t: m for t, m in types.items() if m in INPUT_TYPES}
    if not chosen:
        raise BagIOError("nothing to play: the bag has no image or Detection2DArray topic "
                         f"(topics: {', '.join(f'{t} [{m}]' for t, m in types.items()) or 'none'})")
    return chosen


def _stamp_ns(msg: object) -> Optional[int]:
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None:
        return None
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def play_items(bag: BagReader, topics: Mapping[str, str],
               remaps: Optional[Mapping[str, str]] = None) -> Iterator[PlayItem]:
    """The messages of ``topics`` in log-time order, serialized, with offsets from the first.

    A message that cannot be deserialized is skipped (warned, counted in ``bag.skipped``).

    Raises:
        BagIOError: The bag cannot be read or a message cannot be serialized.
    """
    store = typestore()
    remaps = remaps or {}
    first: Optional[int] = None
    for m in bag.messages(topics=list(topics), skip_undecodable=True):
        first = m.log_time_ns if first is None else first
        try:
            data = bytes(store.serialize_cdr(m.msg, m.msgtype))
        except Exception as exc:  # rosbags raises various errors on odd messages
            raise BagIOError(f"cannot serialize {m.msgtype} on {m.topic} at "
                             f"{m.log_time_ns} ns: {exc}") from exc
        yield PlayItem(m.log_time_ns - first, remaps.get(m.topic, m.topic), m.msgtype, data,
                       _stamp_ns(m.msg))


class Pacer:
    """Waits until a bag offset is due at ``rate`` times the recorded speed.

    Args:
        rate: Playback speed factor (> 0); 2.0 plays twice as fast.
        stop: Set to abort waiting.
        clock: Monotonic clock in seconds (injectable for tests).
    """

    def __init__(self, rate: float, stop: Optional[threading.Event] = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not rate > 0:
            raise ConfigError(f"rate must be > 0, got {rate}")
        self.rate = float(rate)
        self.stop = stop or threading.Event()
        self._clock = clock
        self._start: Optional[float] = None

    def restart(self) -> None:
        """Make the next :meth:`wait` due at once and pace from there (a new pass)."""
        self._start = None

    def wait(self, offset_ns: int) -> bool:
        """Sleep until ``offset_ns`` is due; returns False if stopped meanwhile.

        A late message is due at once: playback never skips, it only falls behind.
        """
        now = self._clock()
        if self._start is None:
            self._start = now - offset_ns / 1e9 / self.rate
        due = self._start + offset_ns / 1e9 / self.rate
        if due > now:
            return not self.stop.wait(due - now)
        return not self.stop.is_set()


def loop_gap_ns(last_offset_ns: int, count: int) -> int:
    """Pause between two passes of a loop: the mean gap between the messages of a pass."""
    if count < 2 or last_offset_ns <= 0:
        return 100_000_000
    return max(1, last_offset_ns // (count - 1))
