"""Counting the messages the middleware dropped before a subscription saw them (no ROS types).

A keep-last subscription whose reader history is full replaces its oldest waiting
message without telling anyone (Fast DDS fires no "message lost" event for it), so a burst
larger than the depth would vanish uncounted. Every DDS writer numbers its messages
1, 2, 3...; rclpy hands that ``publication_sequence_number`` to a callback that takes
the message info. A :class:`SequenceGaps` per subscription turns gaps in those numbers
into a count of lost messages.

rclpy does not say which publisher a message came from, so the numbers of several
publishers on one topic are told apart heuristically: each message continues the
stream whose last number is the largest one below its own (a publisher's numbers only
grow), and a number below every stream's last starts a new stream (a new or restarted
publisher).

Losses before a stream's first delivered message: a publisher that appeared after the
subscription was made published every one of its messages while the node was
subscribed, from number 1, so a first delivered number ``s`` means ``s - 1`` lost (in the
reader's history, or published before discovery had connected the two). The node tells
:meth:`SequenceGaps.subscribed` how many publishers the topic had when it subscribed; that
many streams start uncounted, because the numbers of a publisher that was already running
cannot be told from messages published before the node subscribed (rclpy gives no
publisher ID, no first number intended for the reader and no count of replaced messages;
see ``docs/ARCHITECTURE.md``, "Every message in one counter"). Losses at the end of a
stream are counted when its next message arrives. A reliable writer may repair a loss
after later messages got through: such a late message fills its gap again (the latest
``max_gaps`` gaps are remembered).
"""

from __future__ import annotations

from typing import List, Optional, Tuple


class SequenceGaps:
    """Lost-message count of one subscription from its publishers' sequence numbers.

    Args:
        max_streams: Publisher streams remembered; the least recently continued is forgotten.
        max_gaps: Recent gaps remembered, so that a late message is not counted twice.

    Attributes:
        lost: Messages missing before or between delivered ones, since start.
        supported: False once a message came without a sequence number (the middleware
            does not provide them), True once one came with one, None before any.
        publishers_before: Publishers on the topic when it was last subscribed (their
            losses before their first delivered message are not counted).
    """

    def __init__(self, max_streams: int = 8, max_gaps: int = 256) -> None:
        self.max_streams = int(max_streams)
        self.max_gaps = int(max_gaps)
        self._tails: List[int] = []  # last number of each stream, least recently used first
        self._gaps: List[Tuple[int, int]] = []  # (first, last) missing numbers, oldest first
        self.lost = 0
        self.supported: Optional[bool] = None
        # Streams still to start uncounted (publishers already running when subscribed);
        # None before ``subscribed``: every stream starts uncounted.
        self._running: Optional[int] = None
        self.publishers_before = 0

    def subscribed(self, publishers: int) -> None:
        """A new subscription to the topic: forget the streams seen so far (numbers
        published while unsubscribed are no loss) and take ``publishers`` (the topic's
        publishers at this moment) as already running: that many new streams start
        uncounted, every later one is counted from number 1. ``lost`` is kept."""
        self._tails.clear()
        self._gaps.clear()
        self._running = self.publishers_before = max(0, int(publishers))

    def add(self, sequence_number: Optional[int]) -> int:
        """Account for one delivered message.

        Returns:
            How many were lost just before it; -1 for a late message that filled a gap.
        """
        if not sequence_number or sequence_number < 0:
            self.supported = False if self.supported is None else self.supported
            return 0
        self.supported = True
        seq = int(sequence_number)
        if self._fill(seq):
            self.lost -= 1
            return -1
        below = [t for t in self._tails if t < seq]
        gap = 0
        if below:
            tail = max(below)
            gap = seq - tail - 1
            self._tails.remove(tail)
        else:
            gap = self._new_stream(seq)
        self._tails.append(seq)
        if gap and below:
            self._gaps.append((seq - gap, seq - 1))
            del self._gaps[:-self.max_gaps]
        self.lost += gap
        return gap

    def _new_stream(self, seq: int) -> int:
        """Make room for a stream starting at ``seq``; returns its numbers lost before it."""
        lost = 0
        if self._running is not None:
            if self._running > 0:
                self._running -= 1
            else:
                lost = seq - 1
        if len(self._tails) >= self.max_streams:
            self._tails.pop(0)
            if self._running is not None:
                self._running += 1  # its publisher may come back: a running one again
        return lost

    def _fill(self, seq: int) -> bool:
        """Remove ``seq`` from a remembered gap; False when it is in none."""
        for i, (first, last) in enumerate(self._gaps):
            if first <= seq <= last:
                parts = [(a, b) for a, b in ((first, seq - 1), (seq + 1, last)) if a <= b]
                self._gaps[i:i + 1] = parts
                return True
        return False
