"""Validation of a model on fixed sequences: loss, metrics and the selection score.

The first ``max(warmup, warmup_seconds * fps)`` frames of each sequence are left out of
the metrics and of the intent/left/right loss; with ``per_frame`` every frame is judged
alone from a zero state, as ``--mode frames`` trains. The score is
:func:`signal_light_node.evaluation.metrics.selection_score` (the mean of intent macro-F1 and
brake accuracy), by which a run keeps its best checkpoint. With ``--select-by published``
:func:`with_published_score` replaces it by what the node would publish on whole validation
tracks (the before/after report's and ``signal-light calibrate``'s objective).
"""

from __future__ import annotations

from typing import Any, Dict, Mapping, Sequence, Tuple

import numpy as np
import torch
from torch import nn

from signal_light_node.data.stream import collate_sequences
from signal_light_node.evaluation.tracks import TrackSequence
from signal_light_node.labels import TASKS
from signal_light_node.evaluation.metrics import MetricAccumulator, selection_score
from signal_light_node.training.loss import multitask_loss, warmup_frames
from signal_light_node.training.model_inputs import batch_input


@torch.no_grad()
def validate(model: nn.Module, items: Sequence[Mapping[str, Any]], device: torch.device,
             task_weights: Mapping[str, float], warmup: int, batch: int = 16,
             warmup_seconds: float = 0.0, per_frame: bool = False) -> Dict[str, Any]:
    """Loss and metrics of ``model`` on fixed sequence items (eval mode, no class weights).

    Args:
        model: The model (put back into its previous train/eval mode afterwards).
        items: Sequence items (``crops``, ``labels``, ``mask``, ``meta``).
        device: Where the model runs.
        task_weights: Loss weight per head; the score counts the heads weighted > 0.
        warmup: Leading frames of each sequence not scored.
        batch: Sequences per forward pass.
        warmup_seconds: The same in seconds (the larger of the two applies).
        per_frame: Judge every frame alone from a zero state, with no warm-up, as the
            per-frame stage trains. A model that never saw a carried state is otherwise
            judged on states it was not trained for, and the plateau schedule cuts its
            learning rate on that drift instead of on what it learns.

    Returns:
        ``{"loss": float, "summary": metrics summary, "accuracy": {task: acc},
        "macro_f1": {task: F1}, "score": float}``.
    """
    was_training = model.training
    model.eval()
    acc = MetricAccumulator()
    losses, weights = [], []
    try:
        for a in range(0, len(items), batch):
            chunk = collate_sequences(list(items[a:a + batch]))
            loss, n = _score_chunk(model, chunk, device, task_weights, acc,
                                   (warmup, warmup_seconds, per_frame))
            losses.append(loss * n)
            weights.append(n)
    finally:
        model.train(was_training)
    report = acc.report()
    summary = report["summary"]
    return {"loss": sum(losses) / max(sum(weights), 1.0), "summary": summary,
            "accuracy": {t: m["accuracy"] for t, m in report["overall"].items()},
            "macro_f1": {t: m["macro_f1"] for t, m in report["overall"].items()},
            "score": selection_score(summary, [t for t, w in task_weights.items() if w > 0])}


def _score_chunk(model: nn.Module, chunk: Mapping[str, Any], device: torch.device,
                 task_weights: Mapping[str, float], acc: MetricAccumulator,
                 warm_up: Tuple[int, float, bool]) -> Tuple[float, float]:
    """Add one collated chunk's scored frames to ``acc``; returns (loss, valid frames)."""
    x = batch_input(chunk["crops"], device)
    labels = chunk["labels"].to(device)
    mask = chunk["mask"].to(device)
    logits, warm = _forward(model, x, chunk, device, *warm_up)
    loss, _ = multitask_loss(logits, labels, mask, task_weights, None, warm)
    t_idx = torch.arange(mask.shape[1], device=device)
    scored = mask & (t_idx[None, :] >= warm[:, None])
    sel = scored.cpu().numpy()
    y = labels.cpu().numpy()[sel]
    p = np.stack([logits[t].argmax(-1).cpu().numpy()[sel] for t in TASKS], axis=1)
    acc.add_frames(y, p)
    return float(loss), float(mask.sum())


def _forward(model: nn.Module, x: torch.Tensor, chunk: Mapping[str, Any], device: torch.device,
             warmup: int, warmup_seconds: float, per_frame: bool
             ) -> Tuple[Dict[str, torch.Tensor], torch.Tensor]:
    """Logits ``[N, T, K]`` per task and the per-sequence warm-up (0 with ``per_frame``)."""
    if per_frame:
        n_seq, n_t = x.shape[:2]
        warm = torch.zeros(n_seq, dtype=torch.long, device=device)
        logits, _ = model(x.flatten(0, 1).unsqueeze(1))
        return {t: v.reshape(n_seq, n_t, -1) for t, v in logits.items()}, warm
    warm = warmup_frames(chunk["meta"].get("fps", [None] * len(x)), warmup,
                         warmup_seconds).to(device)
    logits, _ = model(x)
    return logits, warm


def with_published_score(val: Dict[str, Any], model: nn.Module,
                         tracks: Sequence[TrackSequence], device: torch.device) -> Dict[str, Any]:
    """``val`` with its ``score`` taken from what the node publishes on ``tracks``.

    A fine-tune is judged afterwards through the node's intent filter (the before/after
    report); selecting its checkpoint by the raw heads' per-frame argmax can keep a step
    that publishes worse. The per-frame score stays under ``frame_score``, the published
    headline under ``published``.

    Args:
        val: :func:`validate`'s result.
        model: The model (put back into its previous train/eval mode afterwards).
        tracks: Whole validation tracks with ground truth.
        device: Where the model runs.
    """
    from signal_light_node.evaluation.streaming import evaluate_tracks
    from signal_light_node.training.holdout import headline
    from signal_light_node.training.unknown_bias import score

    was_training = model.training
    try:
        result = evaluate_tracks(model.eval(), tracks, device=device, progress=False)
    finally:
        model.train(was_training)
    return dict(val, frame_score=val["score"], published=headline(result), score=score(result))
