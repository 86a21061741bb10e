"""Infinite training streams built on the synthetic stream: replay, thinning, mixing.

* :class:`ReplayStream` serves every rendered sequence several times (rendering costs
  more than a training step), replaying rare strata more often.
* :class:`BalancedStream` thins common strata of fresh sequences (``--balance-drop``).
* :class:`MixedStream` draws each item from one of several streams with fixed shares
  (the synthetic stream and bag/UCM windows).

Every stream seeds its draws from (seed, rank, DataLoader worker), so each rank and
worker sees its own data.
"""

from __future__ import annotations

from typing import Any, Dict, Iterator, List, Sequence

import numpy as np
import torch

from signal_light_node.errors import ConfigError
from signal_light_node.training.augment import Augment
from signal_light_node.training.sampling import STRATA, StratumBalancer, sequence_stratum


def _worker_id() -> int:
    info = torch.utils.data.get_worker_info()
    return info.id if info is not None else 0


class ReplayStream(torch.utils.data.IterableDataset):
    """Serves every item of an expensive stream ``reuse`` times on average.

    Rendering a synthetic sequence costs more CPU than a training step uses it for, so
    each fresh (un-augmented) item is served once and kept in a buffer, and after every
    fresh item ``reuse - 1`` items (on average) drawn from the buffer follow. With
    ``stratified`` the buffer keeps one pool per stratum (:data:`.sampling.STRATA`) and a
    replayed item comes from a stratum chosen uniformly among the non-empty pools, so
    rare sequences (HAZARD, brake with a blinker) are replayed more often than common
    ones without throwing any rendering away. Every item served is augmented anew
    (mirroring, colour jitter), so a reused sequence is rarely seen twice in one form.

    Args:
        stream: The source; it must not augment itself.
        reuse: Average number of times an item is served (1 = no replay).
        capacity: Items kept per worker (split evenly over the strata when stratified).
        augment: Augmentation applied to every served item.
        seed: Seed of the draws (combined with rank and worker).
        rank: Process rank.
        stratified: Replay strata uniformly instead of in their natural shares.
        shuffle: Size of the queue that shuffles fresh items before they are served.

    Raises:
        ConfigError: ``reuse`` is below 1.
    """

    def __init__(self, stream: torch.utils.data.IterableDataset, reuse: float, capacity: int,
                 augment: Augment, seed: int, rank: int = 0, stratified: bool = True,
                 shuffle: int = 32) -> None:
        super().__init__()
        if reuse < 1:
            raise ConfigError(f"reuse must be >= 1, got {reuse}")
        self.stream, self.reuse, self.capacity = stream, float(reuse), max(1, int(capacity))
        self.augment, self.seed, self.rank = augment, int(seed), int(rank)
        self.stratified = bool(stratified)
        self.shuffle = max(1, int(shuffle))

    def __iter__(self) -> Iterator[Dict[str, Any]]:
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, self.rank,
                                                            _worker_id(), 29]))
        keys = STRATA if self.stratified else ("all",)
        pools: Dict[str, List[Dict[str, Any]]] = {k: [] for k in keys}
        per_pool = max(1, self.capacity // len(keys))
        # Fresh items wait in a small shuffle queue: a long scene gives several
        # consecutive windows of each track, which should not share one batch.
        queue: List[Dict[str, Any]] = []
        for fresh in self.stream:
            queue.append(fresh)
            if len(queue) < self.shuffle:
                continue
            item = queue.pop(int(rng.integers(len(queue))))
            self._keep(pools, per_pool, item, rng)
            yield self.augment(item, rng)
            yield from self._replays(pools, rng)

    def _keep(self, pools: Dict[str, List[Dict[str, Any]]], per_pool: int,
              item: Dict[str, Any], rng: np.random.Generator) -> None:
        """Put a fresh item into its stratum's pool, replacing a random one when full."""
        key = sequence_stratum(item["labels"], item["mask"]) if self.stratified else "all"
        pool = pools[key]
        if len(pool) < per_pool:
            pool.append(item)
        else:
            pool[int(rng.integers(len(pool)))] = item

    def _replays(self, pools: Dict[str, List[Dict[str, Any]]],
                 rng: np.random.Generator) -> Iterator[Dict[str, Any]]:
        """``reuse - 1`` replayed items on average, each from a uniformly chosen stratum."""
        extra = self.reuse - 1.0
        n_extra = int(extra) + int(rng.random() < extra - int(extra))
        filled = [p for p in pools.values() if p]
        for _ in range(n_extra):
            pool = filled[int(rng.integers(len(filled)))]
            yield self.augment(pool[int(rng.integers(len(pool)))], rng)


class BalancedStream(torch.utils.data.IterableDataset):
    """A stream thinned by a :class:`.sampling.StratumBalancer` seeded per rank and worker.

    Args:
        stream: The source.
        seed: Seed of the balancer (combined with rank and worker).
        rank: Process rank.
        max_drop: Largest share of a common stratum's items dropped.
    """

    def __init__(self, stream: torch.utils.data.IterableDataset, seed: int, rank: int,
                 max_drop: float) -> None:
        super().__init__()
        self.stream, self.seed, self.rank, self.max_drop = stream, int(seed), int(rank), max_drop

    def __iter__(self) -> Iterator[Dict[str, Any]]:
        seed = int(np.random.SeedSequence([self.seed, self.rank, _worker_id(), 31])
                   .generate_state(1)[0])
        return StratumBalancer(seed, max_drop=self.max_drop).filter(iter(self.stream))


class MixedStream(torch.utils.data.IterableDataset):
    """Draws each item from one of several infinite datasets with fixed probabilities.

    Args:
        parts: The datasets.
        probabilities: Their shares (normalised).
        seed: Seed of the draws (combined with rank and worker).
        rank: Process rank.
    """

    def __init__(self, parts: Sequence[torch.utils.data.IterableDataset],
                 probabilities: Sequence[float], seed: int, rank: int) -> None:
        super().__init__()
        self.parts = list(parts)
        p = np.asarray(probabilities, dtype=np.float64)
        self.probabilities = p / p.sum()
        self.seed, self.rank = int(seed), int(rank)

    def __iter__(self) -> Iterator[Dict[str, Any]]:
        iters = [iter(part) for part in self.parts]
        if len(iters) == 1:
            yield from iters[0]
            return
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, self.rank,
                                                            _worker_id(), 17]))
        while True:
            k = int(rng.choice(len(iters), p=self.probabilities))
            yield next(iters[k])
