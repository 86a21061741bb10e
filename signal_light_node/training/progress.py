"""What a run reports while it trains: running figures, the progress bar, ``log.jsonl``.

The running training loss and batch accuracies (intent, brake) are exponential moving
averages over steps. They show on a tqdm bar (on an interactive terminal) or in a log
line every ``10 * log_every`` steps; every validation appends one JSON record to
``OUT/log.jsonl`` (:func:`validation_record`).
"""

from __future__ import annotations

import json
import logging
import math
import sys
import time
from pathlib import Path
from typing import Any, Dict, Mapping, Optional

import torch
from tqdm import tqdm

from signal_light_node.labels import TASKS

logger = logging.getLogger(__name__)

#: Weight of the newest step in the running figures.
RUNNING_WEIGHT = 0.1


def pct(value: Optional[float]) -> str:
    """``value`` as a percentage with one decimal ("-" for None)."""
    return "-" if value is None else f"{100 * value:.1f}%"


def batch_accuracy(logits: Mapping[str, torch.Tensor], labels: torch.Tensor,
                   mask: torch.Tensor, task: str) -> Optional[float]:
    """Accuracy of ``task``'s argmax over the batch's labelled frames (None: none)."""
    i = TASKS.index(task)
    y = labels[..., i]
    valid = mask & (y >= 0)
    n = int(valid.sum())
    if n == 0:
        return None
    return float((logits[task].argmax(-1)[valid] == y[valid]).float().mean())


def update_running(running: Dict[str, float], loss: torch.Tensor,
                   logits: Mapping[str, torch.Tensor], labels: torch.Tensor,
                   mask: torch.Tensor) -> None:
    """Fold one step's loss and intent/brake batch accuracies into ``running``."""
    for key, value in (("loss", float(loss.detach())),
                       ("intent", batch_accuracy(logits, labels, mask, "intent")),
                       ("brake", batch_accuracy(logits, labels, mask, "brake"))):
        if value is not None:
            running[key] = value if key not in running else \
                (1 - RUNNING_WEIGHT) * running[key] + RUNNING_WEIGHT * value


class ProgressReport:
    """The progress bar of a run and its periodic log lines (rank 0 only).

    Args:
        total: Steps the run ends at (None: unknown).
        start_step: The step it starts from.
        show_bar: Draw the tqdm bar (``--progress`` on rank 0).
        main: Whether this is rank 0 (the only one that logs).
        log_every: Steps between bar updates; log lines every ten times as many.
    """

    def __init__(self, total: Optional[int], start_step: int, show_bar: bool, main: bool,
                 log_every: int) -> None:
        self.interactive = sys.stderr.isatty()
        self.main, self.log_every, self.start_step = main, log_every, start_step
        self.started = time.monotonic()
        # Into a log file the bar is redrawn rarely, so that a long run's log stays small.
        self.bar = tqdm(total=total, initial=start_step, desc="train", unit="step",
                        disable=not show_bar, dynamic_ncols=True,
                        mininterval=1.0 if self.interactive else 60.0)

    def step(self, step: int, running: Mapping[str, float], lr: float, best_score: float,
             best_step: int) -> None:
        """Report that step ``step`` was taken."""
        self.bar.update(1)
        if (self.bar.disable or not self.interactive) and self.main \
                and step % (self.log_every * 10) == 0:
            logger.info("step %d: train loss %.3f, intent %s, brake %s, %.2f s/step",
                        step, running.get("loss", math.nan), pct(running.get("intent")),
                        pct(running.get("brake")),
                        (time.monotonic() - self.started) / max(1, step - self.start_step))
        if step % self.log_every == 0:
            self.bar.set_postfix(loss=f"{running.get('loss', math.nan):.3f}",
                                 intent=pct(running.get("intent")),
                                 brake=pct(running.get("brake")), lr=f"{lr:.1e}",
                                 best=f"{best_score:.3f}" if best_step >= 0 else "-")

    def close(self) -> None:
        """Close the bar."""
        self.bar.close()


def validation_record(step: int, train_seconds: float, lr: float,
                      running: Mapping[str, float], val: Optional[Mapping[str, Any]],
                      improved: bool) -> Dict[str, Any]:
    """The ``log.jsonl`` record of a validation at ``step`` (val None: none was possible)."""
    record: Dict[str, Any] = {"step": step, "time_s": round(train_seconds, 1), "lr": lr,
                              "train": {k: round(v, 4) for k, v in running.items()}}
    if val is not None:
        record.update(val_loss=round(val["loss"], 5), score=round(val["score"], 5),
                      summary=val["summary"], accuracy=val["accuracy"], best=improved)
        if "published" in val:
            record.update(published=val["published"], frame_score=round(val["frame_score"], 5))
    return record


def log_validation(step: int, val: Mapping[str, Any], improved: bool) -> None:
    """One log line of a validation's headline figures."""
    logger.info("step %d: val loss %.4f, intent F1 %s, brake acc %s, score %.4f%s",
                step, val["loss"], pct(val["summary"]["intent_macro_f1"]),
                pct(val["summary"]["brake_accuracy"]), val["score"],
                " (best)" if improved else "")


def append_log(out: Path, record: Mapping[str, Any]) -> None:
    """Append ``record`` to ``out/log.jsonl`` as one JSON line."""
    with open(out / "log.jsonl", "a") as fh:
        fh.write(json.dumps(record) + "\n")
