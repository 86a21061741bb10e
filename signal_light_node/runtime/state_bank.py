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

Tracks are keyed by (camera, track ID): the same ID on two cameras is two tracks. Each
camera has its own stamp clock: its stamps jumping backwards (a bag that loops) or
forwards by more than a gap (a pause or a new bag) reset that camera's tracks only, and
its tracks expire after a timeout measured in its own stamps. The number of tracks is
capped over all cameras together (the least recently stored one is evicted). A
single-camera caller never names a camera and gets :data:`DEFAULT_CAMERA`; several
cameras' frames are gathered and stored in one go with :meth:`StateBank.gather_cameras`
and :meth:`StateBank.store_cameras`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.runtime.backend import BackendState

LOG = logging.getLogger(__name__)

#: Reasons of a full reset, as counted in ``StateBank.reset_reasons``.
RESET_BACKWARDS = "stamp_backwards"
RESET_GAP = "stamp_gap"
RESET_MANUAL = "manual"

#: The camera of a single-camera caller (``gather``/``store`` without a camera).
DEFAULT_CAMERA = ""

#: A track's key in the bank: (camera, track ID).
TrackKey = Tuple[str, str]

#: Per-camera counters (``StateBank.camera_counters``).
CAMERA_COUNTERS: Tuple[str, ...] = ("created", "expired", "evictions", "overflow", "resets")


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
    """Recurrent model states of the tracked vehicles, keyed by (camera, track ID).

    Call ``gather`` then ``store`` once per frame, in stamp order per camera (or
    ``gather_cameras`` then ``store_cameras`` once per batch of several cameras' frames).
    ``gather`` also checks the camera's stamp (backward or large forward jumps reset that
    camera's tracks) and expires the camera's tracks unseen for longer than
    ``track_timeout_s`` of its stamps, so a track that comes back after the timeout
    starts from the initial state.

    Args:
        model: The model backend (``runtime.backend.ModelBackend``) that owns the
            states; a bare torch ``LightStateModel`` is wrapped in the ``torch`` backend.
        track_timeout_s: Seconds a track may stay unseen before its state is dropped.
        max_tracks: Most tracks kept over all cameras; the least recently stored one is
            evicted for a new one.
        max_gap_s: A forward stamp jump larger than this resets the camera's tracks.
        device: Device of a wrapped bare model (a backend keeps its own).
        filter_row: The filter row a new track starts with (float64 ``[W]``); None
            keeps rows of width 0.

    Attributes:
        counters: Totals over all cameras: created, expired, evictions, overflow, resets.
        camera_counters: The same per camera (an eviction counts for the evicted track's
            camera; a reset of every camera counts once for each camera it cleared).
        reset_reasons: Resets per reason, over all cameras.

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
        # Imported here: the registry's package (``model``) loads torch (see the engine).
        from signal_light_node.model.backends.registry import as_backend

        self.backend = as_backend(model, device)
        # Row `capacity` is a scratch row that always holds the initial state: tracks that
        # find no free row (more tracks in one frame than max_tracks) read it and are not stored.
        self._rows = self.backend.new_rows(self.capacity + 1)
        self._filter_initial = np.asarray([] if filter_row is None else filter_row,
                                          np.float64).reshape(-1)
        self._filter = np.tile(self._filter_initial, (self.capacity + 1, 1))
        self._slot: Dict[TrackKey, int] = {}
        self._free: List[int] = list(range(self.capacity - 1, -1, -1))
        self._last_seen = np.zeros(self.capacity, dtype=np.int64)
        # Bank-wide store count of each row's last store: the eviction order. Stamps of
        # different cameras need not share a clock, so they do not decide it.
        self._stored_at = np.zeros(self.capacity, dtype=np.int64)
        self._stores = 0
        self._frames = np.zeros(self.capacity, dtype=np.int64)
        self._pending: Optional[_Pending] = None
        self._clock: Dict[str, int] = {}
        self.counters: Dict[str, int] = {name: 0 for name in CAMERA_COUNTERS}
        self.camera_counters: Dict[str, Dict[str, int]] = {}
        self.reset_reasons: Dict[str, int] = {}

    # ------------------------------------------------------------------ queries
    def __len__(self) -> int:
        return len(self._slot)

    def __contains__(self, track: Any) -> bool:
        """A track ID of the default camera, or a ``(camera, track ID)`` key."""
        return _key(track) in self._slot

    @property
    def track_ids(self) -> List[str]:
        """IDs of the default camera's tracks that currently hold a state."""
        return self.tracks(DEFAULT_CAMERA)

    @property
    def keys(self) -> List[TrackKey]:
        """``(camera, track ID)`` of every track that currently holds a state."""
        return list(self._slot)

    @property
    def cameras(self) -> List[str]:
        """Cameras seen since the last full reset (a stamp or a track), sorted."""
        return sorted(set(self._clock) | {camera for camera, _ in self._slot})

    @property
    def last_stamp_ns(self) -> Optional[int]:
        """The default camera's last stamp, None before its first frame or after a reset."""
        return self._clock.get(DEFAULT_CAMERA)

    def camera_stamp_ns(self, camera: str) -> Optional[int]:
        """A camera's last stamp, None before its first frame or after its reset."""
        return self._clock.get(camera)

    def tracks(self, camera: str = DEFAULT_CAMERA) -> List[str]:
        """IDs of one camera's tracks that currently hold a state."""
        return [tid for cam, tid in self._slot if cam == camera]

    def count(self, camera: str) -> int:
        """How many of the camera's tracks hold a state."""
        return sum(1 for cam, _ in self._slot if cam == camera)

    def frames_observed(self, track_id: str, camera: str = DEFAULT_CAMERA) -> int:
        """Frames stored for a track since it (re)started; 0 for an unknown track."""
        slot = self._slot.get((camera, track_id))
        return 0 if slot is None else int(self._frames[slot])

    def last_seen_ns(self, track_id: str, camera: str = DEFAULT_CAMERA) -> Optional[int]:
        """Stamp of the track's last stored frame, None for an unknown track."""
        slot = self._slot.get((camera, track_id))
        return None if slot is None else int(self._last_seen[slot])

    def initial_state(self, n: int) -> BackendState:
        """The state a new track starts from, for ``n`` tracks (the backend's type)."""
        return self.backend.initial_state(n)

    # ---------------------------------------------------------------- lifecycle
    def reset(self, reason: str = RESET_MANUAL, camera: Optional[str] = None) -> None:
        """Forget tracks and stamps; counted once under ``reason``.

        Args:
            reason: Why, for ``reset_reasons``.
            camera: Only this camera's tracks and clock; None forgets every camera.
        """
        if camera is None:
            cleared = self.cameras
            if self._slot:
                self.backend.reset_rows(self._rows, np.fromiter(self._slot.values(), np.int64,
                                                                len(self._slot)))
                self._filter[:] = self._filter_initial
            self._slot.clear()
            self._free = list(range(self.capacity - 1, -1, -1))
            self._last_seen[:] = 0
            self._stored_at[:] = 0
            self._frames[:] = 0
            self._clock.clear()
        else:
            cleared = [camera]
            gone = [key for key in self._slot if key[0] == camera]
            if gone:
                slots = np.asarray([self._slot[key] for key in gone], np.int64)
                self.backend.reset_rows(self._rows, slots)
                self._filter[slots] = self._filter_initial
                for key in gone:
                    self._release(key)
            self._clock.pop(camera, None)
        self._pending = None
        self.counters["resets"] += 1
        for cam in cleared:
            self._camera(cam)["resets"] += 1
        self.reset_reasons[reason] = self.reset_reasons.get(reason, 0) + 1

    def check_stamp(self, stamp_ns: int, camera: str = DEFAULT_CAMERA) -> Optional[str]:
        """Reset the camera's tracks if ``stamp_ns`` jumps back or too far forward.

        Args:
            stamp_ns: Stamp of the camera's frame about to be processed.
            camera: Whose clock; the other cameras' tracks are never touched.

        Returns:
            The reset reason, or None when the stamp continues the camera's sequence.
        """
        stamp_ns = int(stamp_ns)
        reason = None
        last = self._clock.get(camera)
        if last is not None:
            if stamp_ns < last:
                reason = RESET_BACKWARDS
            elif stamp_ns - last > self.max_gap_ns:
                reason = RESET_GAP
        if reason is not None:
            LOG.info("resetting %d track states%s: %s (%d ns -> %d ns)", self.count(camera),
                     f" of camera {camera!r}" if camera else "", reason, last, stamp_ns)
            self.reset(reason, camera)
        self._clock[camera] = stamp_ns
        return reason

    def expire(self, stamp_ns: int, camera: str = DEFAULT_CAMERA) -> List[str]:
        """Drop the camera's tracks unseen for longer than the timeout at ``stamp_ns``.

        Returns:
            The dropped track IDs.
        """
        if not self._slot:
            return []
        limit = int(stamp_ns) - self.track_timeout_ns
        gone = [key for key, slot in self._slot.items()
                if key[0] == camera and self._last_seen[slot] < limit]
        for key in gone:
            self._release(key)
        self.counters["expired"] += len(gone)
        if gone:
            self._camera(camera)["expired"] += len(gone)
        return [tid for _, tid in gone]

    # ------------------------------------------------------------ gather/store
    def gather(self, track_ids: Sequence[str], stamp_ns: int,
               camera: str = DEFAULT_CAMERA) -> BackendState:
        """States of the given tracks for the camera's frame at ``stamp_ns``.

        Checks the stamp (see ``check_stamp``) and expires the camera's old tracks
        first; a track without a state gets the initial one (and a row, evicting the
        least recently stored other track when the bank is full).

        Args:
            track_ids: Distinct track IDs of the frame, in batch order.
            stamp_ns: The frame's stamp.
            camera: The frame's camera.

        Returns:
            The batched state of ``len(track_ids)`` tracks, in the backend's type.

        Raises:
            ValueError: ``track_ids`` holds a duplicate (the engine removes them first).
        """
        pending = self._gather([(camera, track_ids, stamp_ns)])
        if not pending.keys:
            return self.initial_state(0)
        return self.backend.gather_rows(self._rows, pending.slots)

    def gather_cameras(self, frames: Sequence[Tuple[str, Sequence[str], int]]) -> "CameraBatch":
        """States of the tracks of several cameras' frames, for one batched step.

        Each camera's stamp is checked and its old tracks expired (in the given order)
        before any row is allocated, and no track of the batch evicts another one of it.

        Args:
            frames: ``(camera, distinct track IDs, stamp_ns)`` per frame, at most one
                frame per camera.

        Returns:
            The batch: its rows are the frames' tracks in order.

        Raises:
            ValueError: A camera appears twice, or a frame repeats a track ID.
        """
        pending = self._gather(frames)
        state = self.backend.gather_rows(self._rows, pending.slots) if pending.keys \
            else self.initial_state(0)
        return CameraBatch(keys=pending.keys, stamps_ns=pending.stamps, state=state,
                           filter_rows=self._filter[pending.slots], _token=pending)

    def gather_filter_rows(self, track_ids: Sequence[str],
                           camera: str = DEFAULT_CAMERA) -> np.ndarray:
        """Filter rows of the tracks of the last ``gather`` (a copy).

        Args:
            track_ids: The same IDs, in the same order, as passed to ``gather``.
            camera: The same camera.

        Returns:
            float64 ``[len(track_ids), W]``; a new track's (and a track without a row's)
            is the initial row.

        Raises:
            ValueError: The IDs differ from the last ``gather``'s.
        """
        return self._filter[self._pending_slots(track_ids, camera)]

    def store(self, track_ids: Sequence[str], new_state: BackendState, stamp_ns: int,
              filter_rows: Optional[np.ndarray] = None,
              camera: str = DEFAULT_CAMERA) -> np.ndarray:
        """Keep the states the model returned for the tracks of the last ``gather``.

        Args:
            track_ids: The same IDs, in the same order, as passed to ``gather``.
            new_state: The backend's new batched state (from its ``step``).
            stamp_ns: The frame's stamp (the tracks' new last-seen stamp).
            filter_rows: The tracks' new filter rows ``[N, W]``; None leaves them.
            camera: The same camera as passed to ``gather``.

        Returns:
            Frames observed per track, this frame included (1 for a track that ran
            without a row because the bank was full).

        Raises:
            ValueError: The IDs differ from the last ``gather``'s.
        """
        slots = self._pending_slots(track_ids, camera)
        self._pending = None
        return self._store(slots, new_state, int(stamp_ns), filter_rows)

    def store_cameras(self, batch: "CameraBatch", new_state: BackendState,
                      filter_rows: Optional[np.ndarray] = None) -> np.ndarray:
        """Keep the states the model returned for a batch of ``gather_cameras``.

        Args:
            batch: The batch, from the last ``gather_cameras``.
            new_state: The backend's new batched state (rows in the batch's order).
            filter_rows: The rows' new filter rows ``[N, W]``; None leaves them.

        Returns:
            Frames observed per row, this frame included.

        Raises:
            ValueError: The batch is not the one of the last gather.
        """
        if self._pending is None or self._pending is not batch._token:
            raise ValueError("store_cameras must follow gather_cameras with its batch")
        self._pending = None
        return self._store(batch._token.slots, new_state, batch.stamps_ns, filter_rows)

    # ---------------------------------------------------------------- internals
    def _camera(self, camera: str) -> Dict[str, int]:
        counts = self.camera_counters.get(camera)
        if counts is None:
            counts = self.camera_counters[camera] = {name: 0 for name in CAMERA_COUNTERS}
        return counts

    def _gather(self, frames: Sequence[Tuple[str, Sequence[str], int]]) -> "_Pending":
        keys: List[TrackKey] = []
        stamps: List[int] = []
        cameras = [camera for camera, _, _ in frames]
        if len(set(cameras)) != len(cameras):
            raise ValueError("gather_cameras takes at most one frame per camera")
        for camera, track_ids, stamp_ns in frames:
            ids = tuple(track_ids)
            if len(set(ids)) != len(ids):
                raise ValueError("gather needs distinct track IDs; remove duplicates first")
            keys += [(camera, tid) for tid in ids]
            stamps += [int(stamp_ns)] * len(ids)
        for camera, _, stamp_ns in frames:
            self.check_stamp(stamp_ns, camera)
            self.expire(stamp_ns, camera)
        slots = np.empty(len(keys), dtype=np.int64)
        new_slots: List[int] = []
        in_frame = set(keys)
        for i, key in enumerate(keys):
            slot = self._slot.get(key)
            if slot is None:
                slot = self._allocate(key, in_frame)
                if slot < self.capacity:
                    new_slots.append(slot)
            slots[i] = slot
        if new_slots:
            self.backend.reset_rows(self._rows, np.asarray(new_slots, dtype=np.int64))
            self._filter[new_slots] = self._filter_initial
        self._pending = _Pending(tuple(keys), slots, np.asarray(stamps, np.int64))
        return self._pending

    def _store(self, slots: np.ndarray, new_state: BackendState, stamps_ns: Any,
               filter_rows: Optional[np.ndarray]) -> np.ndarray:
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
        stamps = np.asarray(stamps_ns, np.int64)
        self._last_seen[held] = stamps if stamps.ndim == 0 else stamps[kept]
        self._stores += 1
        self._stored_at[held] = self._stores
        self._frames[held] += 1
        frames = np.ones(len(slots), dtype=np.int64)
        frames[kept] = self._frames[held]
        return frames

    def _pending_slots(self, track_ids: Sequence[str], camera: str) -> np.ndarray:
        if self._pending is None or \
                self._pending.keys != tuple((camera, tid) for tid in track_ids):
            raise ValueError("store and gather_filter_rows must follow gather with the same "
                             "track IDs")
        return self._pending.slots

    def _release(self, key: TrackKey) -> None:
        slot = self._slot.pop(key)
        self._frames[slot] = 0
        self._free.append(slot)

    def _allocate(self, key: TrackKey, in_frame: set) -> int:
        if not self._free:
            victims = [(self._stored_at[s], k) for k, s in self._slot.items()
                       if k not in in_frame]
            if not victims:
                # Every row belongs to a track of this very frame: run this one statelessly.
                self.counters["overflow"] += 1
                self._camera(key[0])["overflow"] += 1
                return self.capacity
            _, victim = min(victims)
            LOG.debug("evicting track %r to make room for %r", victim, key)
            self._release(victim)
            self.counters["evictions"] += 1
            self._camera(victim[0])["evictions"] += 1
        slot = self._free.pop()
        self._slot[key] = slot
        self._frames[slot] = 0
        self._last_seen[slot] = 0
        self._stored_at[slot] = 0
        self.counters["created"] += 1
        self._camera(key[0])["created"] += 1
        return slot


class _Pending:
    """The rows of the last gather, until they are stored."""

    __slots__ = ("keys", "slots", "stamps")

    def __init__(self, keys: Tuple[TrackKey, ...], slots: np.ndarray, stamps: np.ndarray) -> None:
        self.keys, self.slots, self.stamps = keys, slots, stamps


@dataclass(frozen=True)
class CameraBatch:
    """The tracks of several cameras' frames gathered for one step (``gather_cameras``).

    Attributes:
        keys: ``(camera, track ID)`` per row, in batch order.
        stamps_ns: int64 ``[N]``: each row's frame stamp.
        state: The rows' batched state, in the backend's type.
        filter_rows: float64 ``[N, W]``: the rows' filter rows (a copy).
    """

    keys: Tuple[TrackKey, ...]
    stamps_ns: np.ndarray
    state: BackendState
    filter_rows: np.ndarray
    _token: _Pending

    def __len__(self) -> int:
        return len(self.keys)


def _key(track: Any) -> TrackKey:
    """A track ID of the default camera, or a ``(camera, track ID)`` key, as a key."""
    if isinstance(track, tuple) and len(track) == 2:
        return (str(track[0]), str(track[1]))
    return (DEFAULT_CAMERA, track)
