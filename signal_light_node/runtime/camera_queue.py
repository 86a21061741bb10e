"""The work queue of a several-camera node: one bounded drop-oldest queue per camera,
taken one tick at a time (no ROS types).

Each camera's paired frames wait in their own bounded FIFO (``work_queue_size`` each, the
oldest dropped and counted when full, as :class:`~signal_light_node.runtime.worker.DropOldestQueue`
does for one camera), so a fast camera cannot push out a slow one's frames. The
:class:`~signal_light_node.runtime.worker.Worker` calls :meth:`CameraQueue.get`, which
hands out ONE tick: the oldest waiting frame of every camera that has one, in the
cameras' order, for one batched engine step.
"""

from __future__ import annotations

from collections import deque
from typing import Any, Deque, Dict, List, Optional, Sequence, Tuple

from signal_light_node.errors import ConfigError
from signal_light_node.runtime.worker import BoundedFifos


class CameraQueue(BoundedFifos):
    """Per-camera drop-oldest FIFOs, drained one frame per camera per :meth:`get`.

    Thread-safe; the interface :class:`~signal_light_node.runtime.worker.Worker` needs
    (``get``, ``close``, ``clear``) plus the counters of ``DropOldestQueue`` (the same
    drop-oldest rule and blocking wait, from their shared base).

    Args:
        cameras: The camera names, in the order a tick lists them.
        maxsize: Capacity per camera, at least 1.

    Attributes:
        put_count: Items offered.
        dropped: Items discarded (full queue, closed queue or ``clear``), all cameras.
        dropped_by_camera: The same per camera.

    Raises:
        ConfigError: ``maxsize`` is below 1 or no camera is given.
    """

    def __init__(self, cameras: Sequence[str], maxsize: int) -> None:
        super().__init__(maxsize)
        if not cameras:
            raise ConfigError("a camera queue needs at least one camera")
        self.cameras: Tuple[str, ...] = tuple(cameras)
        self._items: Dict[str, Deque[Any]] = {camera: deque() for camera in self.cameras}
        self.dropped_by_camera: Dict[str, int] = {camera: 0 for camera in self.cameras}

    def _has_items(self) -> bool:
        return any(self._items.values())

    def put(self, entry: Tuple[str, Any]) -> Optional[Tuple[str, Any]]:
        """Append ``(camera, item)`` to its camera's FIFO.

        Returns:
            The ``(camera, item)`` dropped to make room (the camera's oldest), the entry
            itself when the queue is closed, else None.

        Raises:
            KeyError: The camera is not one of the queue's.
        """
        camera, item = entry
        with self._cond:
            was_dropped, dropped = self._offer(self._items[camera], item)
            if not was_dropped:
                return None
            self.dropped_by_camera[camera] += 1
            return camera, dropped

    def get(self, timeout: Optional[float] = None) -> List[Tuple[str, Any]]:
        """One tick: ``[(camera, oldest item), ...]`` for every camera with a waiting item.

        Raises:
            QueueClosed: The queue is closed and empty.
            TimeoutError: Nothing arrived within ``timeout`` seconds.
        """
        return self._wait_and_take(timeout, lambda: [
            (camera, self._items[camera].popleft()) for camera in self.cameras
            if self._items[camera]])

    def clear(self) -> int:
        """Discard every waiting item (counted as dropped); returns how many."""
        with self._cond:
            n = 0
            for camera, waiting in self._items.items():
                self.dropped += len(waiting)
                self.dropped_by_camera[camera] += len(waiting)
                n += len(waiting)
                waiting.clear()
            return n

    def __len__(self) -> int:
        with self._cond:
            return sum(len(waiting) for waiting in self._items.values())

    def waiting(self, camera: str) -> int:
        """Items of one camera waiting."""
        with self._cond:
            return len(self._items[camera])
