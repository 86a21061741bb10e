"""The per-camera parts of the detector node: pairing, drop counts, topics, counters.

The node (:mod:`signal_light_node.ros.detector_node`) holds one :class:`CameraIO` per
camera: its own :class:`~signal_light_node.runtime.pairing.StampPairer`, its own
middleware gap counters, its subscriptions and publishers (created by the node) and its
figures for ``/diagnostics``. The single-camera node (``cameras: []``) has one, named
``""``, on the unprefixed topics. :class:`PairerGroup` and :class:`GapsSum` show several
cameras' pairers and gap counters as one, so the node's totals (``counters()``, the
drop counters that raise WARN) are the same code for one camera or several.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

from signal_light_node.io.topics import camera_topic
from signal_light_node.ros.gaps import SequenceGaps
from signal_light_node.runtime.pairing import COUNTERS, StampPairer


@dataclass
class CameraIO:
    """One camera of the node.

    Attributes:
        name: The camera's name; ``""`` for the single-camera node.
        gaps: Middleware drops per input (``image``, ``detections``).
        pairer: Its pairing (set by the node's ``configure``).
        outputs: ``(adapter, publisher)`` per output adapter, result array first (the
            debug image is one when enabled).
        subscriptions: Its input subscriptions.
        image_topic: The resolved image topic (for error messages).
        counts: ``outputs``, ``bad_images``, ``oversized_images`` of this camera.
        dropped_before: Work-queue drops of queues closed by ``deactivate``.
    """

    name: str
    gaps: Dict[str, SequenceGaps] = field(
        default_factory=lambda: {"image": SequenceGaps(), "detections": SequenceGaps()})
    pairer: Optional[StampPairer] = None
    outputs: List[Tuple[Any, Any]] = field(default_factory=list)
    subscriptions: List[Any] = field(default_factory=list)
    image_topic: str = ""
    counts: Dict[str, int] = field(
        default_factory=lambda: {"outputs": 0, "bad_images": 0, "oversized_images": 0})
    dropped_before: int = 0

    def topic(self, name: str) -> str:
        """The node's topic ``name`` (``~/...``) of this camera."""
        return camera_topic(name, self.name)

    def values(self, work_queue_drops: int, engine: Dict[str, int]) -> List[Tuple[str, str]]:
        """This camera's ``/diagnostics`` key/values (prefixed ``<camera>.``).

        Args:
            work_queue_drops: Its frames dropped from the current work queue.
            engine: Its entry of ``engine.camera_counters``.
        """
        pairing = self.pairer.counters if self.pairer is not None else {}
        figures = {
            "images": pairing.get("images", 0),
            "outputs": self.counts["outputs"],
            "active_tracks": engine.get("active_tracks", 0),
            "track_resets": engine.get("resets", 0),
            "dropped_pairing": sum(v for k, v in pairing.items() if k.startswith("dropped_")),
            "dropped_work_queue": self.dropped_before + work_queue_drops,
            "dropped_middleware": sum(g.lost for g in self.gaps.values()),
            "bad_images": self.counts["bad_images"] + self.counts["oversized_images"],
        }
        return [(f"{self.name}.{key}", str(int(value))) for key, value in figures.items()]


def camera_ios(names: Sequence[str]) -> List[CameraIO]:
    """The node's cameras: one per name, or the single unnamed one for no names."""
    return [CameraIO(name) for name in names] or [CameraIO("")]


class PairerGroup:
    """Several cameras' pairers seen as one (counters and pending summed).

    Args:
        pairers: One per camera.
    """

    def __init__(self, pairers: Sequence[StampPairer]) -> None:
        self.pairers = list(pairers)

    @property
    def counters(self) -> Dict[str, int]:
        """Every pairer's counters summed (``runtime.pairing.COUNTERS``)."""
        out = {name: 0 for name in COUNTERS}
        for pairer in self.pairers:
            for name, value in pairer.counters.items():
                out[name] = out.get(name, 0) + value
        return out

    @property
    def pending(self) -> Tuple[int, int]:
        """(images, detection arrays) waiting for a partner, over all cameras."""
        waiting = [pairer.pending for pairer in self.pairers]
        return sum(w[0] for w in waiting), sum(w[1] for w in waiting)

    def expire(self, now_ns: int) -> int:
        """Expire every pairer; returns how many messages were dropped."""
        return sum(pairer.expire(now_ns) for pairer in self.pairers)

    def configure(self, slop_ns: int, timeout_ns: int) -> None:
        """Change slop and timeout of every pairer."""
        for pairer in self.pairers:
            pairer.configure(slop_ns, timeout_ns)


class GapsSum:
    """One input's middleware drop counts over several cameras (``lost``, ``supported``,
    ``publishers_before``).

    Args:
        gaps: That input's :class:`SequenceGaps` of each camera.
    """

    def __init__(self, gaps: Sequence[SequenceGaps]) -> None:
        self.gaps = list(gaps)

    @property
    def lost(self) -> int:
        """Messages lost, all cameras."""
        return sum(g.lost for g in self.gaps)

    @property
    def publishers_before(self) -> int:
        """Publishers already running when subscribed, all cameras."""
        return sum(g.publishers_before for g in self.gaps)

    @property
    def supported(self) -> Optional[bool]:
        """True once any camera saw sequence numbers, False once any saw none, else None."""
        seen = [g.supported for g in self.gaps if g.supported is not None]
        if any(seen):
            return True
        return False if seen else None
