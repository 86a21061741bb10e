"""What a run saves and resumes from.

``last.pt`` / ``best.pt`` are model checkpoints (``model.checkpoint`` file format) whose
metadata (:func:`checkpoint_meta`) describes the training data, the run and its last
validation. Beside ``last.pt`` lies ``last.state.pt``, the training state ``--resume``
needs: optimiser, scheduler, step, class counts, best score and the torch RNG
(:func:`training_state`, :func:`restore_training_state`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional

import torch

from signal_light_node.errors import CheckpointError
from signal_light_node.training.options import TrainOptions
from signal_light_node.training.sampling import ClassFrequency

#: Suffix of the training state beside a checkpoint (``last.pt`` -> ``last.state.pt``).
STATE_SUFFIX = ".state.pt"


def state_path(checkpoint: Path) -> Path:
    """The training state file beside ``checkpoint``."""
    return checkpoint.with_name(checkpoint.stem + STATE_SUFFIX)


@dataclass
class RunCounters:
    """The figures of a run that carry over a resume.

    Attributes:
        step: Optimiser steps taken.
        best_score: Best validation score so far (``-inf``: none yet).
        best_step: Its step (-1: none yet).
        train_seconds: Seconds spent training (all invocations).
    """

    step: int
    best_score: float
    best_step: int
    train_seconds: float


def training_state(counters: RunCounters, optimizer: torch.optim.Optimizer,
                   scheduler: Any, freq: ClassFrequency) -> Dict[str, Any]:
    """The dict written to the state file (the torch RNG as it is now included)."""
    return {"step": counters.step, "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict(),
            "class_counts": freq.state_dict(), "best_score": counters.best_score,
            "best_step": counters.best_step, "train_seconds": counters.train_seconds,
            "rng": {"torch": torch.get_rng_state()}}


def write_training_state(checkpoint: Path, state: Mapping[str, Any]) -> None:
    """Write ``state`` beside ``checkpoint``, atomically (a crash leaves the old one)."""
    tmp = state_path(checkpoint).with_suffix(".tmp")
    torch.save(dict(state), tmp)
    os.replace(tmp, state_path(checkpoint))


def load_training_state(checkpoint: Path) -> Dict[str, Any]:
    """The training state beside ``checkpoint``.

    Raises:
        CheckpointError: It is missing.
    """
    state_file = state_path(Path(checkpoint))
    if not state_file.is_file():
        raise CheckpointError(f"cannot resume: training state {state_file} is missing")
    return torch.load(state_file, map_location="cpu", weights_only=True)


def restore_training_state(state: Mapping[str, Any], optimizer: torch.optim.Optimizer,
                           scheduler: Any, freq: ClassFrequency) -> RunCounters:
    """Load ``state`` into the optimiser, scheduler and class counts, and set the torch RNG.

    Returns:
        The run's counters as saved.
    """
    optimizer.load_state_dict(state["optimizer"])
    scheduler.load_state_dict(state["scheduler"])
    freq.load_state_dict(state["class_counts"])
    counters = RunCounters(step=int(state["step"]), best_score=float(state["best_score"]),
                           best_step=int(state["best_step"]),
                           train_seconds=float(state.get("train_seconds", 0.0)))
    torch.set_rng_state(state["rng"]["torch"])
    return counters


def data_sources(opts: TrainOptions, synthetic_share: float) -> List[str]:
    """What the run trains on, in words (checkpoint metadata)."""
    sources = []
    if synthetic_share > 0:
        sources.append("synthetic stream (signal_light_node.synth scenes)")
    sources += [f"bag {b}" for b in opts.bags] + [f"UCM {u}" for u in opts.ucm]
    sources += [f"synthetic pool {p}" for p in opts.pools]
    return sources


def checkpoint_meta(opts: TrainOptions, counters: RunCounters, *, synthetic_share: float,
                    world: int, lr: float, precision: str, init_meta: Mapping[str, Any],
                    val: Optional[Mapping[str, Any]]) -> Dict[str, Any]:
    """The metadata of a checkpoint saved at ``counters.step``.

    Args:
        opts: The run's options.
        counters: The run's counters now.
        synthetic_share: Share of sequences from the synthetic stream.
        world: Number of processes.
        lr: The last step's learning rate.
        precision: The resolved precision.
        init_meta: What the run records of ``--init-from``.
        val: The validation at this step, or None.
    """
    frames_per_item = 1 if opts.mode == "frames" else opts.seq_len
    meta = {
        "training_data": {"sources": data_sources(opts, synthetic_share),
                          "synthetic_fraction": synthetic_share,
                          "seed": opts.seed, "seq_len": opts.seq_len, "batch": opts.batch,
                          "world_size": world,
                          "mode": opts.mode,
                          "frames_seen": int(counters.step * opts.batch * frames_per_item
                                             * world)},
        "training": {"step": counters.step, "lr": lr, "precision": precision,
                     "train_seconds": round(counters.train_seconds, 1),
                     "options": opts.to_json()},
    }
    meta.update(init_meta)
    if val is not None:
        meta["metrics"] = {"validation": {k: val[k] for k in
                                          ("loss", "summary", "accuracy", "macro_f1", "score")}}
    return meta
