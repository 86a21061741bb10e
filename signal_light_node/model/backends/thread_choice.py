"""How many threads the next CPU step should use, from what recent steps cost.

A second thread makes a 32-track step 1.4-1.6x faster on a quiet 2-core machine, but
when another process keeps a core busy it makes the step no faster (0.8-1.0x: the
second thread waits for a core) while it still takes CPU from the node's own decoding,
pairing and publishing. Measured live on such a machine (``scripts/benchmark_node.py
--busy-cores 1``, int8 model, 32 tracks at 10 Hz): p95 latency 95-139 ms with two
threads against 77-90 ms with one; quiet, 52-58 ms with two against 72-86 with one.

So the backend keeps, per thread count, a running mean of the wall time per track of
its steps, runs the count that is worth it (all threads only while they are at least
``min_speedup`` times faster than one), and every ``probe_every`` steps runs the other
count once, so that a change in the load is noticed both ways. A probe's time replaces
that count's mean (what it cost many steps ago says nothing about now), and the first
step of each count is not counted (onnxruntime's first run of a shape is slow).
"""

from __future__ import annotations

from typing import Dict, Optional


class ThreadChoice:
    """One or ``most`` threads per step, whichever recent steps say pays.

    Args:
        most: The thread count to use when the CPU has room for it (> 1).
        min_speedup: How much faster per track ``most`` threads must be than one.
        probe_every: Steps between two runs of the count not chosen.
        weight: Weight of a new measurement in the running means.

    Raises:
        ValueError: ``most`` < 2, ``min_speedup`` < 1, ``probe_every`` < 2 or
            ``weight`` outside (0, 1].
    """

    def __init__(self, most: int, min_speedup: float = 1.1, probe_every: int = 30,
                 weight: float = 0.3) -> None:
        if most < 2 or min_speedup < 1 or probe_every < 2 or not 0 < weight <= 1:
            raise ValueError(f"ThreadChoice(most={most}, min_speedup={min_speedup}, "
                             f"probe_every={probe_every}, weight={weight})")
        self.most = int(most)
        self.min_speedup = float(min_speedup)
        self.probe_every = int(probe_every)
        self.weight = float(weight)
        #: Running mean of seconds per track, per thread count (None: not measured yet).
        self.per_track: Dict[int, Optional[float]] = {self.most: None, 1: None}
        self._runs = {self.most: 0, 1: 0}
        self._steps = 0
        self._probe: Optional[int] = None

    @property
    def preferred(self) -> int:
        """The count the measurements favour (``most`` until both are measured)."""
        one, many = self.per_track[1], self.per_track[self.most]
        if one is None or many is None:
            return self.most
        return self.most if one >= self.min_speedup * many else 1

    def next(self) -> int:
        """Threads for the next step: unmeasured counts first, then the preferred one,
        the other every ``probe_every`` steps."""
        for count, value in self.per_track.items():
            if value is None:
                return count
        self._steps += 1
        preferred = self.preferred
        if self._steps % self.probe_every == 0:
            self._probe = 1 if preferred == self.most else self.most
            return self._probe
        return preferred

    def record(self, threads: int, tracks: int, seconds: float) -> None:
        """Add a step that ran ``tracks`` tracks on ``threads`` threads in ``seconds``."""
        if threads not in self.per_track or tracks <= 0:
            return
        self._runs[threads] += 1
        if self._runs[threads] == 1:
            return  # a first run: warm-up
        value = seconds / tracks
        old = self.per_track[threads]
        probe, self._probe = threads == self._probe, None
        self.per_track[threads] = value if old is None or probe \
            else old + self.weight * (value - old)
