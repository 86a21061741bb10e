"""Per-track recurrent state of the light-state model, kept outside the model.

The model is stateless between calls: the engine gathers the recurrent states of the
tracks of a frame from this bank, runs one batched step and stores the new states back.
The states themselves are opaque here: they live in a row store owned by the model
backend (:mod:`signal_light_node.runtime.backend`; a torch tensor on the model's device,
a numpy array for onnxruntime), one row per track, and the bank only decides which row
belongs to which track. Gathering or storing a whole frame is one ``gather_rows`` /
``store_rows`` call however many layers and tracks there are.

Beside the model state, each track may own a fixed-size float64 row of the output
filter (:mod:`signal_light_node.runtime.intent_filter`): created with the track, gathered and
stored with it, and gone when the track is.

Tracks unseen for longer than a timeout are dropped, the number of tracks is capped
(least recently seen evicted), and the whole bank resets when the frame stamps jump
backwards (a bag that loops) or forwards by more than a gap (a pause or a new bag).
"""

from __future__ import annotations

import logging
import math
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.runtime.backend import BackendState, as_backend

LOG = logging.getLogger(__name__)

#: Reasons of a full reset, as counted in ``StateBank.reset_reasons``.
RESET_BACKWARDS = "stamp_backwards"
RESET_GAP = "stamp_gap"
RESET_MANUAL = "manual"


def check_limits(track_timeout_s: Any, max_tracks: Any,
                 max_gap_s: Any) -> Tuple[float, int, float]:
    """Validate the limits of a :class:`StateBank` (also checked by ``EngineConfig``).

    Args:
        track_timeout_s: Seconds a track may stay unseen; a positive finite number.
        max_tracks: Most tracks kept; a positive integer.
        max_gap_s: Largest forward stamp jump in seconds; a positive finite number.

    Returns:
        ``(track_timeout_s, max_tracks, max_gap_s)`` as float, int, float.

    Raises:
        ConfigError: A limit is not of that kind.
    """
    for name, value in (("track_timeout_s", track_timeout_s), ("max_gap_s", max_gap_s)):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                or not math.isfinite(value) or value <= 0:
            raise ConfigError(f"{name} must be a positive number of seconds, got {value!r}")
    if isinstance(max_tracks, bool) or not isinstance(max_tracks, (int, np.integer)) \
            or max_tracks < 1:
        raise ConfigError(f"max_tracks must be a positive integer, got {max_tracks!r}")
    return float(track_timeout_s), int(max_tracks), float(max_gap_s)


class StateBank:
    """Recurrent model states of the tracked vehicles, keyed by track ID.

    Call ``gather`` then ``store`` once per frame, in stamp order. ``gather`` also
    checks the stamp (backward or large forward jumps reset everything) and expires
    tracks unseen for longer than ``track_timeout_s``, so a track that comes back after
    the timeout starts from the initial state.

    Args:
        model: The model backend (``runtime.backend.ModelBackend``) that owns the
            states; a bare torch ``LightStateModel`` is wrapped in the ``torch`` backend.
        track_timeout_s: Seconds a track may stay unseen before its state is dropped.
        max_tracks: Most tracks kept; the least recently seen one is evicted for a new one.
        max_gap_s: A forward stamp jump larger than this resets the bank.
        device: Device of a wrapped bare model (a backend keeps its own).
        filter_row: The filter row a new track starts with (float64 ``[W]``); None
            keeps rows of width 0.

    Raises:
        ConfigError: A limit is not a positive finite number.
    """

    def __init__(self, model: Any, track_timeout_s: float = 1.0,
                 max_tracks: int = 128, max_gap_s: float = 2.0, device: str = "cpu",
                 filter_row: Optional[np.ndarray] = None) -> None:
        track_timeout_s, max_tracks, max_gap_s = check_limits(track_timeout_s, max_tracks,
                                                              max_gap_s)
        self.track_timeout_ns = int(round(track_timeout_s * 1e9))
        self.max_gap_ns = int(round(max_gap_s * 1e9))
        self.capacity = max_tracks
        self.backend = as_backend(model, device)
        # Row `capacity` is a scratch row that always holds the initial state: tracks that
        # find no free row (more tracks in one frame than max_tracks) read it and are not stored.
        self._rows = self.backend.new_rows(self.capacity + 1)
        self._filter_initial = np.asarray([] if filter_row is None else filter_row,
                                          np.float64).reshape(-1)
        self._filter = np.tile(self._filter_initial, (self.capacity + 1, 1))
        self._slot: Dict[str, int] = {}
        self._free: List[int] = list(range(self.capacity - 1, -1, -1))
        self._last_seen = np.zeros(self.capacity, dtype=np.int64)
        self._frames = np.zeros(self.capacity, dtype=np.int64)
        self._pending: Optional[Tuple[Tuple[str, ...], np.ndarray, int]] = None
        self.last_stamp_ns: Optional[int] = None
        self.counters: Dict[str, int] = {"created": 0, "expired": 0, "evictions": 0,
                                         "overflow": 0, "resets": 0}
        self.reset_reasons: Dict[str, int] = {}

    # ------------------------------------------------------------------ queries
    def __len__(self) -> int:
        return len(self._slot)

    def __contains__(self, track_id: str) -> bool:
        return track_id in self._slot

    @property
    def track_ids(self) -> List[str]:
        """IDs of the tracks that currently hold a state."""
        return list(self._slot)

    def frames_observed(self, track_id: str) -> int:
        """Frames stored for a track since it (re)started; 0 for an unknown track."""
        slot = self._slot.get(track_id)
        return 0 if slot is None else int(self._frames[slot])

    def last_seen_ns(self, track_id: str) -> Optional[int]:
        """Stamp of the track's last stored frame, None for an unknown track."""
        slot = self._slot.get(track_id)
        return None if slot is None else int(self._last_seen[slot])

    def initial_state(self, n: int) -> BackendState:
        """The state a new track starts from, for ``n`` tracks (the backend's type)."""
        return self.backend.initial_state(n)

    # ---------------------------------------------------------------- lifecycle
    def reset(self, reason: str = RESET_MANUAL) -> None:
        """Forget every track (and the last stamp); counted under ``reason``."""
        if self._slot:
            self.backend.reset_rows(self._rows, np.fromiter(self._slot.values(), np.int64,
                                                            len(self._slot)))
            self._filter[:] = self._filter_initial
        self._slot.clear()
        self._free = list(range(self.capacity - 1, -1, -1))
        self._last_seen[:] = 0
        self._frames[:] = 0
        self._pending = None
        self.last_stamp_ns = None
        self.counters["resets"] += 1
        self.reset_reasons[reason] = self.reset_reasons.get(reason, 0) + 1

    def check_stamp(self, stamp_ns: int) -> Optional[str]:
        """Reset the bank if ``stamp_ns`` jumps back or too far forward.

        Args:
            stamp_ns: Stamp of the frame about to be processed.

        Returns:
            The reset reason, or None when the stamp continues the sequence.
        """
        stamp_ns = int(stamp_ns)
        reason = None
        if self.last_stamp_ns is not None:
            if stamp_ns < self.last_stamp_ns:
                reason = RESET_BACKWARDS
            elif stamp_ns - self.last_stamp_ns > self.max_gap_ns:
                reason = RESET_GAP
        if reason is not None:
            LOG.info("resetting %d track states: %s (%d ns -> %d ns)", len(self._slot),
                     reason, self.last_stamp_ns, stamp_ns)
            self.reset(reason)
        self.last_stamp_ns = stamp_ns
        return reason

    def expire(self, stamp_ns: int) -> List[str]:
        """Drop tracks unseen for longer than the timeout at ``stamp_ns``.

        Returns:
            The dropped track IDs.
        """
        if not self._slot:
            return []
        limit = int(stamp_ns) - self.track_timeout_ns
        gone = [tid for tid, slot in self._slot.items() if self._last_seen[slot] < limit]
        for tid in gone:
            self._release(tid)
        self.counters["expired"] += len(gone)
        return gone

    # ------------------------------------------------------------ gather/store
    def gather(self, track_ids: Sequence[str], stamp_ns: int) -> BackendState:
        """States of the given tracks for the frame at ``stamp_ns``.

        Checks the stamp (see ``check_stamp``) and expires old tracks first; a track
        without a state gets the initial one (and a row, evicting the least recently
        seen other track when the bank is full).

        Args:
            track_ids: Distinct track IDs of the frame, in batch order.
            stamp_ns: The frame's stamp.

        Returns:
            The batched state of ``len(track_ids)`` tracks, in the backend's type.

        Raises:
            ValueError: ``track_ids`` holds a duplicate (the engine removes them first).
        """
        ids = tuple(track_ids)
        if len(set(ids)) != len(ids):
            raise ValueError("gather needs distinct track IDs; remove duplicates first")
        self.check_stamp(stamp_ns)
        self.expire(stamp_ns)
        slots = np.empty(len(ids), dtype=np.int64)
        new_slots: List[int] = []
        in_frame = set(ids)
        for i, tid in enumerate(ids):
            slot = self._slot.get(tid)
            if slot is None:
                slot = self._allocate(tid, in_frame)
                if slot < self.capacity:
                    new_slots.append(slot)
            slots[i] = slot
        if new_slots:
            self.backend.reset_rows(self._rows, np.asarray(new_slots, dtype=np.int64))
            self._filter[new_slots] = self._filter_initial
        self._pending = (ids, slots, int(stamp_ns))
        if not ids:
            return self.initial_state(0)
        return self.backend.gather_rows(self._rows, slots)

    def gather_filter_rows(self, track_ids: Sequence[str]) -> np.ndarray:
        """Filter rows of the tracks of the last ``gather`` (a copy).

        Args:
            track_ids: The same IDs, in the same order, as passed to ``gather``.

        Returns:
            float64 ``[len(track_ids), W]``; a new track's (and a track without a row's)
            is the initial row.

        Raises:
            ValueError: The IDs differ from the last ``gather``'s.
        """
        return self._filter[self._pending_slots(track_ids)]

    def store(self, track_ids: Sequence[str], new_state: BackendState, stamp_ns: int,
              filter_rows: Optional[np.ndarray] = None) -> np.ndarray:
        """Keep the states the model returned for the tracks of the last ``gather``.

        Args:
            track_ids: The same IDs, in the same order, as passed to ``gather``.
            new_state: The backend's new batched state (from its ``step``).
            stamp_ns: The frame's stamp (the tracks' new last-seen stamp).
            filter_rows: The tracks' new filter rows ``[N, W]``; None leaves them.

        Returns:
            Frames observed per track, this frame included (1 for a track that ran
            without a row because the bank was full).

        Raises:
            ValueError: The IDs differ from the last ``gather``'s.
        """
        slots = self._pending_slots(track_ids)
        self._pending = None
        if not len(slots):
            return np.zeros(0, dtype=np.int64)
        kept = slots < self.capacity
        if filter_rows is not None:
            self._filter[slots[kept]] = np.asarray(filter_rows, np.float64)[kept]
        if kept.all():
            self.backend.store_rows(self._rows, slots, new_state)
        elif kept.any():
            self.backend.store_rows(self._rows, slots[kept], new_state, np.flatnonzero(kept))
        held = slots[kept]
        self._last_seen[held] = int(stamp_ns)
        self._frames[held] += 1
        frames = np.ones(len(slots), dtype=np.int64)
        frames[kept] = self._frames[held]
        return frames

    # ---------------------------------------------------------------- internals
    def _pending_slots(self, track_ids: Sequence[str]) -> np.ndarray:
        if self._pending is None or self._pending[0] != tuple(track_ids):
            raise ValueError("store and gather_filter_rows must follow gather with the same "
                             "track IDs")
        return self._pending[1]

    def _release(self, track_id: str) -> None:
        slot = self._slot.pop(track_id)
        self._frames[slot] = 0
        self._free.append(slot)

    def _allocate(self, track_id: str, in_frame: set) -> int:
        if not self._free:
            victims = [(self._last_seen[s], tid) for tid, s in self._slot.items()
                       if tid not in in_frame]
            if not victims:
                # Every row belongs to a track of this very frame: run this one statelessly.
                self.counters["overflow"] += 1
                return self.capacity
            _, victim = min(victims)
            LOG.debug("evicting track %r to make room for %r", victim, track_id)
            self._release(victim)
            self.counters["evictions"] += 1
        slot = self._free.pop()
        self._slot[track_id] = slot
        self._frames[slot] = 0
        self._last_seen[slot] = 0
        self.counters["created"] += 1
        return slot
