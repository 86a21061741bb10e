"""A bounded drop-oldest work queue and the thread that drains it (no ROS types).

Inference must never run inside a subscription callback and must never fall further and
further behind the camera: the callbacks put paired frames into a :class:`DropOldestQueue`,
which, when full, discards the oldest waiting frame (the one least worth processing now)
and counts it; a :class:`Worker` thread takes frames one by one and calls the processing
function. An exception from that function is logged and counted, and the worker goes on.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from typing import Any, Callable, Deque, Optional, Tuple

from signal_light_node.errors import ConfigError

LOG = logging.getLogger(__name__)


class QueueClosed(Exception):
    """Raised by :meth:`DropOldestQueue.get` once the queue is closed and empty."""


class BoundedFifos:
    """What every drop-oldest work queue shares: the lock, closing, counting, waiting.

    Subclasses keep their items in one or more deques of at most ``maxsize`` items and say
    whether anything waits (:meth:`_has_items`); :meth:`_offer` appends under the same
    drop-oldest rule for all of them and :meth:`_wait_and_take` is the one blocking wait.

    Args:
        maxsize: Capacity of each FIFO, at least 1.

    Attributes:
        put_count: Items offered.
        dropped: Items discarded (full FIFO, closed queue or ``clear``).
    """

    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ConfigError(f"work queue size must be at least 1, got {maxsize}")
        self.maxsize = int(maxsize)
        self._cond = threading.Condition()
        self._closed = False
        self.put_count = 0
        self.dropped = 0

    def _has_items(self) -> bool:
        raise NotImplementedError

    def _offer(self, fifo: Deque[Any], item: Any) -> Tuple[bool, Any]:
        """Append ``item`` to ``fifo`` (lock held); ``(True, what was dropped)`` or
        ``(False, None)``. After :meth:`close` the item itself is dropped."""
        self.put_count += 1
        if self._closed:
            self.dropped += 1
            return True, item
        dropped: Tuple[bool, Any] = (False, None)
        if len(fifo) >= self.maxsize:
            dropped = (True, fifo.popleft())
            self.dropped += 1
        fifo.append(item)
        self._cond.notify()
        return dropped

    def _wait_and_take(self, timeout: Optional[float], take: Callable[[], Any]) -> Any:
        """``take()`` (lock held) once something waits.

        Raises:
            QueueClosed: If the queue is closed and empty.
            TimeoutError: If nothing arrived within ``timeout`` seconds.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while not self._has_items():
                if self._closed:
                    raise QueueClosed()
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    raise TimeoutError("no work item within the timeout")
                self._cond.wait(remaining)
            return take()

    def close(self) -> None:
        """Refuse new items and wake every waiting ``get``; waiting items are still served."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed


class DropOldestQueue(BoundedFifos):
    """A thread-safe FIFO of bounded size that drops its oldest item when full.

    Args:
        maxsize: Capacity, at least 1.

    Attributes:
        put_count: Items offered.
        dropped: Items discarded because the queue was full.
    """

    def __init__(self, maxsize: int) -> None:
        super().__init__(maxsize)
        self._items: Deque[Any] = deque()

    def _has_items(self) -> bool:
        return bool(self._items)

    def put(self, item: Any) -> Optional[Any]:
        """Append an item; returns the item dropped to make room, else None.

        Items put after :meth:`close` are dropped (and returned) at once.
        """
        with self._cond:
            was_dropped, dropped = self._offer(self._items, item)
            return dropped if was_dropped else None

    def get(self, timeout: Optional[float] = None) -> Any:
        """Take the oldest item, waiting for one.

        Raises:
            QueueClosed: If the queue is closed and empty.
            TimeoutError: If nothing arrived within ``timeout`` seconds.
        """
        return self._wait_and_take(timeout, self._items.popleft)

    def clear(self) -> int:
        """Discard every waiting item (counted as dropped); returns how many."""
        with self._cond:
            n = len(self._items)
            self._items.clear()
            self.dropped += n
            return n

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)


class Worker:
    """A thread that calls ``process(item)`` for every item of a queue, in order.

    Args:
        queue: Where the items come from.
        process: Called once per item in the worker thread.
        name: Thread name (shows in logs and debuggers).

    Attributes:
        processed: Items processed without an exception.
        errors: Items whose processing raised.
    """

    def __init__(self, queue: DropOldestQueue, process: Callable[[Any], None],
                 name: str = "worker") -> None:
        self.queue = queue
        self._process = process
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._stop_now = False
        self.processed = 0
        self.errors = 0

    def start(self) -> "Worker":
        """Start the thread; returns self."""
        self._thread.start()
        return self

    @property
    def alive(self) -> bool:
        """True while the thread runs."""
        return self._thread.is_alive()

    def stop(self, drain: bool = False, timeout: float = 5.0) -> bool:
        """Stop the thread.

        Args:
            drain: Process the items already waiting before stopping; otherwise they are
                discarded (counted as dropped).
            timeout: Seconds to wait for the item in progress (and the drain) to finish.

        Returns:
            True if the thread has ended.
        """
        if not drain:
            self._stop_now = True
            self.queue.clear()
        self.queue.close()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout)
        return not self._thread.is_alive()

    def _run(self) -> None:
        while not self._stop_now:
            try:
                item = self.queue.get()
            except QueueClosed:
                return
            try:
                self._process(item)
                self.processed += 1
            except Exception:  # one bad frame must not end the node's processing
                self.errors += 1
                LOG.exception("processing a work item failed; continuing with the next one")
