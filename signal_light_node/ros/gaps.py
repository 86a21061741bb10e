"""Counting the messages the middleware dropped before a subscription saw them (no ROS types).

A keep-last subscription whose reader history is full replaces its oldest waiting
message without telling anyone (no "message lost" event fires for it), so a burst
larger than the depth would vanish uncounted. Every DDS writer numbers its messages
1, 2, 3...; rclpy hands that ``publication_sequence_number`` to a callback that takes
the message info. A :class:`SequenceGaps` per subscription turns gaps in those numbers
into a count of lost messages.

rclpy does not say which publisher a message came from, so the numbers of several
publishers on one topic are told apart heuristically: each message continues the
stream whose last number is the largest one below its own (a publisher's numbers only
grow), and a number below every stream's last starts a new stream (a new or restarted
publisher). Losses before a stream's first delivered message cannot be told from
messages published before this node subscribed, and are not counted; losses at the end
of a stream are counted when its next message arrives. A reliable writer may repair a
loss after later messages got through: such a late message fills its gap again (the
latest ``max_gaps`` gaps are remembered).
"""

from __future__ import annotations

from typing import List, Optional, Tuple


class SequenceGaps:
    """Lost-message count of one subscription from its publishers' sequence numbers.

    Args:
        max_streams: Publisher streams remembered; the least recently continued is forgotten.
        max_gaps: Recent gaps remembered, so that a late message is not counted twice.

    Attributes:
        lost: Messages missing between delivered ones, since start.
        supported: False once a message came without a sequence number (the middleware
            does not provide them), True once one came with one, None before any.
    """

    def __init__(self, max_streams: int = 8, max_gaps: int = 256) -> None:
        self.max_streams = int(max_streams)
        self.max_gaps = int(max_gaps)
        self._tails: List[int] = []  # last number of each stream, least recently used first
        self._gaps: List[Tuple[int, int]] = []  # (first, last) missing numbers, oldest first
        self.lost = 0
        self.supported: Optional[bool] = None

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
        elif len(self._tails) >= self.max_streams:
            self._tails.pop(0)
        self._tails.append(seq)
        if gap:
            self._gaps.append((seq - gap, seq - 1))
            del self._gaps[:-self.max_gaps]
        self.lost += gap
        return gap

    def _fill(self, seq: int) -> bool:
        """Remove ``seq`` from a remembered gap; False when it is in none."""
        for i, (first, last) in enumerate(self._gaps):
            if first <= seq <= last:
                parts = [(a, b) for a, b in ((first, seq - 1), (seq + 1, last)) if a <= b]
                self._gaps[i:i + 1] = parts
                return True
        return False
