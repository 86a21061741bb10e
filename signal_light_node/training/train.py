"""The training loop behind ``signal-light train`` (one process, or DDP under torchrun).

Recipe (after the research the model follows, scaled to a CPU):

* **Loss**: the sum over heads of ``task_weight * cross-entropy``, each averaged over
  the valid frames of the batch (``mask`` True and a label >= 0). The blinker-driven
  heads (intent, left, right) skip the first ``max(loss_warmup, loss_warmup_seconds *
  fps)`` frames of every window: a window starts from a blank state and a blink cannot
  be told from a dark lamp before part of a cycle has been seen.
* **Class imbalance**: class-weighted cross-entropy with weights ``share^-power`` from
  running label counts (:class:`.sampling.ClassFrequency`), plus stratified sequences
  over the strata HAZARD / brake-with-blinker / blinker / brake / plain: replayed
  synthetic sequences are drawn uniformly over the strata (:class:`ReplayStream`;
  optionally fresh ones are thinned too, :class:`.sampling.StratumBalancer`), finite
  sources draw windows stratum-balanced (:class:`.sources.WindowDataset`).
* **Optimiser**: Adam; L2 weight decay on the dense layers' weights (the ``nn.Linear``
  of the shared layer and of the heads), dropout as configured in the model;
  ``ReduceLROnPlateau`` on the validation loss; optionally (``anneal_fraction``) a
  cosine decay to ``min_lr`` over the last part of the run's budget on top of it, for
  runs that end by their budget while the loss still falls.
* **Augmentation**: mirroring (crops flipped, left/right labels and LEFT/RIGHT views
  swapped) and per-sequence colour/brightness jitter, both from the data stream. A
  rendered synthetic sequence is served ``reuse`` times on average from a replay buffer
  (:class:`ReplayStream`), each time augmented anew: on a 2-core CPU rendering is
  slower than training, so this doubles the steps per minute.
* **Validation** every ``val_every`` steps on a fixed split: loss and the metrics of
  :mod:`signal_light_node.tools.metrics` on frames after ``val_warmup`` frames of each
  sequence (``--mode frames``: every frame alone from a zero state, as it trains); the
  best checkpoint by :func:`signal_light_node.tools.metrics.selection_score` (mean of intent
  macro-F1 and brake accuracy) is kept as ``best.pt``.
* **Files** in ``out``: ``last.pt`` / ``best.pt`` (model checkpoints), ``last.state.pt``
  (optimizer, scheduler, step, counters, RNG: what ``--resume`` needs), ``log.jsonl``
  (one line per validation) and ``options.json``.
* **DDP**: under ``torchrun`` (``WORLD_SIZE`` > 1) the model is wrapped in
  ``DistributedDataParallel`` (gloo on CPU, NCCL on CUDA); every rank draws its own
  data (the rank enters all data seeds), rank 0 alone validates and writes files, and
  the validation loss and the stop decision are broadcast so that every rank's
  scheduler and loop stay in step.
"""

from __future__ import annotations

import json
import logging
import math
import os
import random
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Iterator, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from tqdm import tqdm

from signal_light_node.runtime.crops import CropConfig
from signal_light_node.data.stream import (
    SyntheticSequenceStream,
    collate_sequences,
    jitter_colours,
    mirror_sequence,
)
from signal_light_node.errors import CheckpointError, ConfigError
from signal_light_node.labels import TASKS
from signal_light_node.tools.metrics import MetricAccumulator, selection_score
from signal_light_node.model import (
    DEFAULT_WEIGHTS,
    ModelConfig,
    build_model,
    load_checkpoint,
    save_checkpoint,
    to_input,
)
from signal_light_node.model.interface import State, state_batch_size
from signal_light_node.model.warm_start import warm_start
from signal_light_node.data.camera_response import randomise_camera
from signal_light_node.data.shape_warp import warp_sequence
from signal_light_node.training.sampling import (
    STRATA,
    ClassFrequency,
    StratumBalancer,
    sequence_stratum,
)
from signal_light_node.training.sources import (
    TrackSequence,
    WindowDataset,
    item_labels,
    load_bag_tracks,
    load_ucm_tracks,
    split_tracks,
)
from signal_light_node.training import FRAME_TARGETS
from signal_light_node.training.track_batches import FrameBatches, LaneBatches
from signal_light_node.training.options import TrainOptions

logger = logging.getLogger(__name__)

#: Tasks whose label needs time to be seen (no loss during a window's warm-up).
TEMPORAL_TASKS = ("intent", "left", "right")

STATE_SUFFIX = ".state.pt"

#: Windows cut from each track of a rendered training scene (scene length / seq_len).
SCENE_WINDOWS = 4


# ------------------------------------------------------------------------ distributed


@dataclass(frozen=True)
class DistInfo:
    """Process group facts: rank, world size and whether DDP is active."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def active(self) -> bool:
        return self.world > 1

    @property
    def main(self) -> bool:
        return self.rank == 0


def init_distributed(device: str) -> DistInfo:
    """Join the process group when started by torchrun (``WORLD_SIZE`` > 1)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistInfo()
    import torch.distributed as dist

    backend = "nccl" if device.startswith("cuda") else "gloo"
    if not dist.is_initialized():
        dist.init_process_group(backend=backend)
    info = DistInfo(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", 0)))
    logger.info("DDP: rank %d of %d (%s)", info.rank, info.world, backend)
    return info


def _broadcast_float(value: float, dist_info: DistInfo, device: torch.device) -> float:
    if not dist_info.active:
        return value
    import torch.distributed as dist

    t = torch.tensor([value], dtype=torch.float64, device=device)
    dist.broadcast(t, 0)
    return float(t.item())


# ------------------------------------------------------------------------------- data


def _worker_init(worker_id: int) -> None:
    """Data workers render on one core each; OpenCV's own pool would fight the trainer."""
    import cv2

    cv2.setNumThreads(1)
    torch.set_num_threads(1)


class _Augment:
    """Mirroring, then the enabled per-sequence crop transforms: colour jitter (the stream's
    own), perspective warp (``data.shape_warp``), camera response (``data.camera_response``)."""

    def __init__(self, mirror_prob: float, jitter: bool, camera: bool = False,
                 warp: bool = False) -> None:
        self.mirror_prob = mirror_prob
        self.transforms = [f for f, on in ((jitter_colours, jitter), (warp_sequence, warp),
                                           (randomise_camera, camera)) if on]

    def __call__(self, item: Dict[str, Any], rng: np.random.Generator) -> Dict[str, Any]:
        if self.mirror_prob > 0 and rng.random() < self.mirror_prob:
            item = mirror_sequence(item)
        for transform in self.transforms:
            crops = transform(item["crops"], rng)
            crops[~item["mask"]] = 0
            item = dict(item, crops=crops)
        return item


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
    """

    def __init__(self, stream: torch.utils.data.IterableDataset, reuse: float, capacity: int,
                 augment: "_Augment", seed: int, rank: int = 0, stratified: bool = True,
                 shuffle: int = 32) -> None:
        super().__init__()
        if reuse < 1:
            raise ConfigError(f"reuse must be >= 1, got {reuse}")
        self.stream, self.reuse, self.capacity = stream, float(reuse), max(1, int(capacity))
        self.augment, self.seed, self.rank = augment, int(seed), int(rank)
        self.stratified = bool(stratified)
        self.shuffle = max(1, int(shuffle))

    def __iter__(self) -> Iterator[Dict[str, Any]]:
        info = torch.utils.data.get_worker_info()
        worker = info.id if info is not None else 0
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, self.rank, worker, 29]))
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
            key = sequence_stratum(item["labels"], item["mask"]) if self.stratified else "all"
            pool = pools[key]
            if len(pool) < per_pool:
                pool.append(item)
            else:
                pool[int(rng.integers(len(pool)))] = item
            yield self.augment(item, rng)
            extra = self.reuse - 1.0
            n_extra = int(extra) + int(rng.random() < extra - int(extra))
            filled = [p for p in pools.values() if p]
            for _ in range(n_extra):
                pool = filled[int(rng.integers(len(filled)))]
                yield self.augment(pool[int(rng.integers(len(pool)))], rng)


class _Balanced(torch.utils.data.IterableDataset):
    """A stream thinned by a :class:`StratumBalancer` seeded per rank and worker."""

    def __init__(self, stream: torch.utils.data.IterableDataset, seed: int, rank: int,
                 max_drop: float) -> None:
        super().__init__()
        self.stream, self.seed, self.rank, self.max_drop = stream, int(seed), int(rank), max_drop

    def __iter__(self) -> Iterator[Dict[str, Any]]:
        info = torch.utils.data.get_worker_info()
        worker = info.id if info is not None else 0
        seed = int(np.random.SeedSequence([self.seed, self.rank, worker, 31]).generate_state(1)[0])
        return StratumBalancer(seed, max_drop=self.max_drop).filter(iter(self.stream))


class _MixedStream(torch.utils.data.IterableDataset):
    """Draws each item from one of several infinite datasets with fixed probabilities."""

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
        info = torch.utils.data.get_worker_info()
        worker = info.id if info is not None else 0
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, self.rank, worker, 17]))
        while True:
            k = int(rng.choice(len(iters), p=self.probabilities))
            yield next(iters[k])


def _split_tracks(tracks: List[TrackSequence], fraction: float
                  ) -> Tuple[List[TrackSequence], List[TrackSequence]]:
    """Every k-th track (k = 1/fraction) goes to validation; deterministic."""
    if fraction <= 0 or len(tracks) < 2:
        return tracks, []
    k = max(2, int(round(1.0 / fraction)))
    val = [t for i, t in enumerate(tracks) if i % k == k - 1]
    train = [t for i, t in enumerate(tracks) if i % k != k - 1]
    return train, val


def _load_sources(opts: TrainOptions, crop: CropConfig) -> List[TrackSequence]:
    tracks: List[TrackSequence] = []
    for bag in opts.bags:
        tracks += load_bag_tracks(Path(bag), crop)
    for root in opts.ucm:
        tracks += load_ucm_tracks(Path(root), crop)
    for pool in opts.pools:
        tracks += split_tracks(Path(pool), crop, role="pool",
                               label_key=FRAME_TARGETS[opts.frame_targets])
    return tracks


# ----------------------------------------------------------------------------- model


def resolve_precision(precision: str, device: torch.device) -> str:
    """The precision a run uses (``TrainOptions.precision``).

    Args:
        precision: "fp32", "bf16" or "auto".
        device: The device the run trains on.

    Returns:
        ``precision`` itself unless it is "auto"; then "bf16" where ``device`` computes
        bfloat16 natively (a CPU with AVX512-BF16 or AMX, a CUDA device that supports it)
        and "fp32" elsewhere, where bfloat16 is emulated and slower than float32.
    """
    if precision != "auto":
        return precision
    if device.type == "cuda":
        native = torch.cuda.is_bf16_supported()
    else:
        # torch's own probes (private, hence the fallback; torch is pinned in requirements.txt)
        probes = [getattr(torch.cpu, name, lambda: False)
                  for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")]
        native = any(probe() for probe in probes)
    return "bf16" if native else "fp32"


def dense_parameter_groups(model: nn.Module, weight_decay: float) -> List[Dict[str, Any]]:
    """Adam parameter groups: weight decay on ``nn.Linear`` weights, none elsewhere."""
    decay, plain = [], []
    dense_weights = {id(m.weight) for m in model.modules() if isinstance(m, nn.Linear)}
    for p in model.parameters():
        if not p.requires_grad:
            continue
        (decay if id(p) in dense_weights else plain).append(p)
    return [{"params": decay, "weight_decay": weight_decay},
            {"params": plain, "weight_decay": 0.0}]


def batch_input(crops: torch.Tensor, device: torch.device) -> torch.Tensor:
    """uint8 ``[B, T, S, S, 3]`` crops -> float ``[B, T, 3, S, S]`` via :func:`model.to_input`."""
    b, t, s = crops.shape[0], crops.shape[1], crops.shape[2]
    x = to_input(crops.reshape(b * t, s, s, 3).numpy())
    return x.reshape(b, t, 3, s, s).to(device, non_blocking=True)


def multitask_loss(logits: Mapping[str, torch.Tensor], labels: torch.Tensor, mask: torch.Tensor,
                   task_weights: Mapping[str, float],
                   class_weights: Optional[Mapping[str, torch.Tensor]] = None,
                   loss_warmup: "int | torch.Tensor" = 0) -> Tuple[torch.Tensor, Dict[str, float]]:
    """Weighted sum of per-head cross-entropies over the valid frames.

    Args:
        logits: Task -> ``[B, T, K]``.
        labels: int64 ``[B, T, len(TASKS)]``; negative entries are ignored.
        mask: bool ``[B, T]``; False frames are ignored.
        task_weights: Task -> weight (missing or 0: not in the loss).
        class_weights: Task -> ``[K]`` class weights, or None.
        loss_warmup: Leading frames without loss for :data:`TEMPORAL_TASKS`: one number
            for all sequences, or an int64 ``[B]`` tensor per sequence.

    Returns:
        ``(total loss, {task: its mean cross-entropy})``.
    """
    total = logits[TASKS[0]].new_zeros(())
    parts: Dict[str, float] = {}
    t_idx = torch.arange(labels.shape[1], device=labels.device)
    for i, task in enumerate(TASKS):
        w = float(task_weights.get(task, 0.0))
        if w <= 0 or task not in logits:
            continue
        y = labels[..., i]
        valid = mask & (y >= 0)
        if task in TEMPORAL_TASKS:
            warm = torch.as_tensor(loss_warmup, device=labels.device).reshape(-1, 1)
            valid = valid & (t_idx[None, :] >= warm)
        k = logits[task].shape[-1]
        ce = F.cross_entropy(logits[task].reshape(-1, k), y.clamp(min=0).reshape(-1),
                             weight=None if class_weights is None else class_weights.get(task),
                             reduction="none")
        valid_f = valid.reshape(-1).to(ce.dtype)
        loss = (ce * valid_f).sum() / valid_f.sum().clamp(min=1.0)
        parts[task] = float(loss.detach())
        total = total + w * loss
    return total, parts


def warmup_frames(fps: Sequence[float], frames: int, seconds: float) -> torch.Tensor:
    """Per-sequence warm-up length: ``max(frames, ceil(seconds * fps))``, int64 ``[B]``."""
    rates = torch.as_tensor([float(f) if f else 10.0 for f in fps], dtype=torch.float64)
    return torch.clamp(torch.ceil(rates * float(seconds)), min=float(frames)).to(torch.int64)


def annealed_lr(lr: float, progress: float, fraction: float, min_lr: float) -> float:
    """The learning rate after the final cosine decay of ``TrainOptions.anneal_fraction``.

    Args:
        lr: The plateau schedule's learning rate.
        progress: Share of the run's budget used so far (0 at the start, 1 at the end).
        fraction: Final share of the budget over which the rate decays (0: never).
        min_lr: The rate at the end of the budget (never raised above ``lr``).

    Returns:
        ``lr`` before the last ``fraction`` of the budget, then a cosine from ``lr`` down to
        ``min_lr``.
    """
    if fraction <= 0 or lr <= min_lr:
        return lr
    into = min(1.0, max(0.0, (progress - (1.0 - fraction)) / fraction))
    return min_lr + (lr - min_lr) * 0.5 * (1.0 + math.cos(math.pi * into))


def _batch_accuracy(logits: Mapping[str, torch.Tensor], labels: torch.Tensor,
                    mask: torch.Tensor, task: str) -> Optional[float]:
    i = TASKS.index(task)
    y = labels[..., i]
    valid = mask & (y >= 0)
    n = int(valid.sum())
    if n == 0:
        return None
    return float((logits[task].argmax(-1)[valid] == y[valid]).float().mean())


@torch.no_grad()
def validate(model: nn.Module, items: Sequence[Mapping[str, Any]], device: torch.device,
             task_weights: Mapping[str, float], warmup: int, batch: int = 16,
             warmup_seconds: float = 0.0, per_frame: bool = False) -> Dict[str, Any]:
    """Loss and metrics of ``model`` on fixed sequence items (eval mode, no class weights).

    The first ``max(warmup, warmup_seconds * fps)`` frames of each sequence are left out
    of the metrics and of the intent/left/right loss.

    Args:
        per_frame: Judge every frame alone from a zero state, with no warm-up, as the
            per-frame stage trains. A model that never saw a carried state is otherwise
            judged on states it was not trained for, and the plateau schedule cuts its
            learning rate on that drift instead of on what it learns.

    Returns:
        ``{"loss": float, "summary": metrics summary, "accuracy": {task: acc}, "score": float}``;
        the score only counts heads with a positive weight.
    """
    was_training = model.training
    model.eval()
    acc = MetricAccumulator()
    losses, weights = [], []
    try:
        for a in range(0, len(items), batch):
            chunk = collate_sequences(list(items[a:a + batch]))
            x = batch_input(chunk["crops"], device)
            labels = chunk["labels"].to(device)
            mask = chunk["mask"].to(device)
            if per_frame:
                n_seq, n_t = x.shape[:2]
                warm = torch.zeros(n_seq, dtype=torch.long, device=device)
                logits, _ = model(x.flatten(0, 1).unsqueeze(1))
                logits = {t: v.reshape(n_seq, n_t, -1) for t, v in logits.items()}
            else:
                warm = warmup_frames(chunk["meta"].get("fps", [None] * len(x)), warmup,
                                     warmup_seconds).to(device)
                logits, _ = model(x)
            loss, _ = multitask_loss(logits, labels, mask, task_weights, None, warm)
            n = float(mask.sum())
            losses.append(float(loss) * n)
            weights.append(n)
            t_idx = torch.arange(mask.shape[1], device=device)
            scored = mask & (t_idx[None, :] >= warm[:, None])
            sel = scored.cpu().numpy()
            y = labels.cpu().numpy()[sel]
            p = np.stack([logits[t].argmax(-1).cpu().numpy()[sel] for t in TASKS], axis=1)
            acc.add_frames(y, p)
    finally:
        model.train(was_training)
    report = acc.report()
    summary = report["summary"]
    return {"loss": sum(losses) / max(sum(weights), 1.0), "summary": summary,
            "accuracy": {t: m["accuracy"] for t, m in report["overall"].items()},
            "macro_f1": {t: m["macro_f1"] for t, m in report["overall"].items()},
            "score": selection_score(summary, [t for t, w in task_weights.items() if w > 0])}


# ------------------------------------------------------------------------------ trainer


def _state_path(checkpoint: Path) -> Path:
    return checkpoint.with_name(checkpoint.stem + STATE_SUFFIX)


def _resolve_init(path: Optional[Path]) -> Optional[Path]:
    if path is None:
        return None
    return DEFAULT_WEIGHTS if str(path) in ("default", "shipped") else Path(path)


class Trainer:
    """One training run; :meth:`run` returns a summary dict.

    Args:
        opts: The options.
    """

    def __init__(self, opts: TrainOptions) -> None:
        opts.validate()
        self.opts = opts
        self.out = Path(opts.out)
        self.dist = init_distributed(str(opts.device))
        if opts.threads:
            torch.set_num_threads(int(opts.threads))
        if str(opts.device).startswith("cuda") and self.dist.active:
            self.device = torch.device("cuda", self.dist.local_rank)
        else:
            self.device = torch.device(opts.device)
        torch.manual_seed(opts.seed)
        np.random.seed(opts.seed % (2**32))
        random.seed(opts.seed)

        self.meta_from_init: Dict[str, Any] = {}
        self.start_step = 0
        self.best_score = -math.inf
        self.best_step = -1
        state: Optional[Dict[str, Any]] = None
        init = _resolve_init(opts.init_from)
        if opts.resume is not None:
            loaded = load_checkpoint(opts.resume, map_location="cpu")
            self.config, model = loaded.config, loaded.model
            state_file = _state_path(Path(opts.resume))
            if not state_file.is_file():
                raise CheckpointError(f"cannot resume: training state {state_file} is missing")
            state = torch.load(state_file, map_location="cpu", weights_only=True)
        elif init is not None:
            loaded = load_checkpoint(init, map_location="cpu")
            self.config, model = loaded.config, loaded.model
            self.meta_from_init = {"init_from": str(init),
                                   "init_training_data": loaded.meta.get("training_data")}
            if opts.model:
                # A grown architecture (e.g. temporal_input) starts from the old weights.
                self.config = loaded.config.replace(**opts.model)
                model = build_model(self.config)
                grown = warm_start(model, loaded.model.state_dict(), opts.grown_init_scale)
                self.meta_from_init["init_model_changes"] = dict(opts.model)
                logger.info("warm start from %s with %s; new input channels in %s",
                            init, dict(opts.model), grown)
        else:
            self.config = ModelConfig().replace(**opts.model) if opts.model else ModelConfig()
            model = build_model(self.config)
        if opts.freeze_encoder:
            if not hasattr(model, "freeze_encoder"):
                raise ConfigError(f"--freeze-encoder: architecture {self.config.arch!r} has no "
                                  "encoder to freeze")
            model.freeze_encoder()
        if opts.freeze_norms:
            if not hasattr(model, "freeze_norms"):
                raise ConfigError(f"--freeze-norms: architecture {self.config.arch!r} cannot "
                                  "freeze its norms")
            model.freeze_norms()
        self.model = model.to(self.device).train()
        self.precision = resolve_precision(opts.precision, self.device)
        logger.info("training precision: %s", self.precision)
        self.crop = self.config.crop_config()

        self.optimizer = torch.optim.Adam(dense_parameter_groups(self.model, opts.weight_decay),
                                          lr=opts.lr)
        self.scheduler = torch.optim.lr_scheduler.ReduceLROnPlateau(
            self.optimizer, mode="min", factor=opts.plateau_factor,
            patience=opts.plateau_patience, threshold=1e-3, min_lr=opts.min_lr)
        self.freq = ClassFrequency(self.config.num_classes, power=opts.class_weight_power)
        self.train_seconds = 0.0
        self.data_wait = 0.0  # seconds this invocation waited for batches
        self._ema: Dict[str, float] = {}  # running training loss and batch accuracies
        self._lanes: Optional[State] = None  # carried state of the lanes (mode "lanes")
        if state is not None:
            self.optimizer.load_state_dict(state["optimizer"])
            self.scheduler.load_state_dict(state["scheduler"])
            self.freq.load_state_dict(state["class_counts"])
            self.start_step = int(state["step"])
            self.best_score = float(state["best_score"])
            self.best_step = int(state["best_step"])
            self.train_seconds = float(state.get("train_seconds", 0.0))
            torch.set_rng_state(state["rng"]["torch"])
            logger.info("resumed from %s at step %d (best %.4f at step %d)", opts.resume,
                        self.start_step, self.best_score, self.best_step)
        self.lr_now = self.optimizer.param_groups[0]["lr"]  # the last step's, annealing included

        if self.dist.active:
            from torch.nn.parallel import DistributedDataParallel

            self.net: nn.Module = DistributedDataParallel(
                self.model, device_ids=[self.device.index] if self.device.type == "cuda" else None)
        else:
            self.net = self.model

        self.tracks = _load_sources(opts, self.crop)
        self.train_tracks, held_out = _split_tracks(
            self.tracks, opts.val_fraction if opts.val_split is None else 0.0)
        self.val_items = self._validation_items(held_out) if self.dist.main else []
        self.loader = self._loader()

    # ----------------------------------------------------------------- data plumbing

    def _synthetic_fraction(self) -> float:
        if self.opts.synthetic_fraction is not None:
            return float(self.opts.synthetic_fraction)
        return 0.0 if self.tracks else 1.0

    def _data_seed(self) -> int:
        # A resumed run must not replay the data of the steps already taken.
        return int(self.opts.seed) * 1_000_003 + self.start_step

    def _loader(self) -> torch.utils.data.DataLoader:
        opts = self.opts
        parts, probs = [], []
        frac = self._synthetic_fraction()
        augment = _Augment(opts.mirror_prob, opts.jitter, opts.camera_response, opts.shape_warp)
        if opts.mode != "windows":
            # In-process: lanes must stay in the order of the state the trainer keeps,
            # and the tracks are already in memory (nothing to render).
            if opts.mode == "frames":
                batches: torch.utils.data.IterableDataset = FrameBatches(
                    self.train_tracks, opts.batch, self._data_seed(), augment, self.dist.rank)
            else:
                batches = LaneBatches(self.train_tracks, opts.batch, opts.seq_len,
                                      self._data_seed(), augment, self.dist.rank)
            return torch.utils.data.DataLoader(batches, batch_size=None, num_workers=0)
        if frac > 0:
            stream_opts = dict(opts.stream)
            # Setting up a scene costs about as much as rendering 10 frames: render
            # longer scenes and cut several windows from each track.
            stream_opts.setdefault("scene_frames", SCENE_WINDOWS * opts.seq_len)
            stream: torch.utils.data.IterableDataset = SyntheticSequenceStream(
                self._data_seed() % (2**31), opts.seq_len, self.crop,
                mirror_prob=0.0, jitter=False, rank=self.dist.rank, **stream_opts)
            if opts.balance and opts.balance_max_drop > 0:
                stream = _Balanced(stream, self._data_seed(), self.dist.rank,
                                   opts.balance_max_drop)
            # Augmentation comes after the balancer and the replay buffer, so that every
            # served copy of a sequence is augmented on its own.
            parts.append(ReplayStream(stream, opts.reuse, opts.replay_capacity, augment,
                                      self._data_seed(), self.dist.rank,
                                      stratified=opts.balance))
            probs.append(frac)
        if frac < 1:
            if not self.train_tracks:
                raise ConfigError("no training tracks: --bags / --ucm gave nothing to train on")
            # WindowDataset draws stratum-balanced windows itself.
            parts.append(WindowDataset(self.train_tracks, opts.seq_len, seed=self._data_seed(),
                                       augment=augment, rank=self.dist.rank))
            probs.append(1.0 - frac)
        mixed = _MixedStream(parts, probs, self._data_seed(), self.dist.rank)
        workers = int(opts.workers)
        # "spawn", not fork: a child forked after OpenCV or OpenMP ran their thread pools
        # in this process can deadlock on a lock copied in the held state.
        return torch.utils.data.DataLoader(
            mixed, batch_size=opts.batch, collate_fn=collate_sequences, num_workers=workers,
            persistent_workers=workers > 0, prefetch_factor=4 if workers > 0 else None,
            multiprocessing_context="spawn" if workers > 0 else None,
            worker_init_fn=_worker_init if workers > 0 else None)

    def _validation_items(self, held_out: List[TrackSequence]) -> List[Dict[str, Any]]:
        opts = self.opts
        if opts.val_split is not None:
            from signal_light_node.data.split import SequenceSplit

            split = SequenceSplit(opts.val_split)
            split.require_crop(self.crop, "validation split")
            key = FRAME_TARGETS[opts.frame_targets]
            items = [split[i] for i in range(len(split))]
            if key == "labels":
                return items
            return [dict(item, labels=item_labels(item, key, f"validation split {opts.val_split}"))
                    for item in items]
        if held_out:
            win = WindowDataset(held_out, max(opts.seq_len, opts.val_seq_len), seed=opts.seed)
            return [win.window(i) for i in range(len(win.windows))]
        if self._synthetic_fraction() > 0:
            from signal_light_node.data.split import SequenceSplit, write_split

            val_dir = self.out / "val_split"
            if not (val_dir / "manifest.json").is_file():
                logger.info("materialising a validation split of %d sequences in %s",
                            opts.val_sequences, val_dir)
                write_split(val_dir, seed=(opts.seed + 1_000_003) % (2**31),
                            n_sequences=opts.val_sequences,
                            seq_len=max(opts.seq_len, opts.val_seq_len),
                            crop=self.crop, progress=opts.progress, **opts.stream)
            split = SequenceSplit(val_dir)
            return [split[i] for i in range(len(split))]
        return []

    # -------------------------------------------------------------------- saving

    def _meta(self, step: int, val: Optional[Mapping[str, Any]]) -> Dict[str, Any]:
        opts = self.opts
        sources = []
        if self._synthetic_fraction() > 0:
            sources.append("synthetic stream (signal_light_node.synth scenes)")
        sources += [f"bag {b}" for b in opts.bags] + [f"UCM {u}" for u in opts.ucm]
        sources += [f"synthetic pool {p}" for p in opts.pools]
        meta = {
            "training_data": {"sources": sources,
                              "synthetic_fraction": self._synthetic_fraction(),
                              "seed": opts.seed, "seq_len": opts.seq_len, "batch": opts.batch,
                              "world_size": self.dist.world,
                              "mode": opts.mode,
                              "frames_seen": int(step * opts.batch
                                                 * (1 if opts.mode == "frames" else opts.seq_len)
                                                 * self.dist.world)},
            "training": {"step": step, "lr": self.lr_now, "precision": self.precision,
                         "train_seconds": round(self.train_seconds, 1),
                         "options": opts.to_json()},
        }
        meta.update(self.meta_from_init)
        if val is not None:
            meta["metrics"] = {"validation": {k: val[k] for k in
                                              ("loss", "summary", "accuracy", "macro_f1", "score")}}
        return meta

    def _save(self, name: str, step: int, val: Optional[Mapping[str, Any]]) -> Path:
        path = self.out / name
        save_checkpoint(path, self.model, self.config, self._meta(step, val))
        if name == "last.pt":
            state = {"step": step, "optimizer": self.optimizer.state_dict(),
                     "scheduler": self.scheduler.state_dict(),
                     "class_counts": self.freq.state_dict(), "best_score": self.best_score,
                     "best_step": self.best_step, "train_seconds": self.train_seconds,
                     "rng": {"torch": torch.get_rng_state()}}
            tmp = _state_path(path).with_suffix(".tmp")
            torch.save(state, tmp)
            os.replace(tmp, _state_path(path))
        return path

    def _log(self, record: Mapping[str, Any]) -> None:
        with open(self.out / "log.jsonl", "a") as fh:
            fh.write(json.dumps(record) + "\n")

    # ----------------------------------------------------------------------- loop

    def _lane_state(self, reset: Optional[torch.Tensor]) -> Optional[State]:
        """The lanes' carried state, zeroed where a lane starts a new track (None: no lanes)."""
        if reset is None:
            return None
        reset = reset.to(self.device)
        if self._lanes is None or state_batch_size(self._lanes) != reset.numel():
            return self.model.initial_state(int(reset.numel()))
        keep = (~reset).to(self._lanes[0][0].dtype).view(-1, 1, 1, 1)
        return tuple((h * keep, c * keep) for h, c in self._lanes)

    def _loss_warmup(self, batch: Mapping[str, Any]) -> "int | torch.Tensor":
        """Leading frames per sequence without loss on the blinker-driven heads."""
        if self.opts.mode == "frames":
            # Single frames: a lit lamp is a per-frame cue; a blinker's dark phase is
            # label noise the recurrent stage later resolves.
            return 0
        fps = batch["meta"].get("fps", [None] * len(batch["labels"]))
        warm = warmup_frames(fps, self.opts.loss_warmup, self.opts.loss_warmup_seconds)
        if "start" in batch:  # lanes: only the start of each track warms up
            warm = (warm - batch["start"]).clamp(min=0)
        return warm.to(self.device)

    def _progress(self, elapsed: float, step: int, budget: float) -> float:
        """Share of this run's budget used: its minutes or its steps, whichever ends it first."""
        shares = [elapsed / budget] if math.isfinite(budget) else []
        if self.opts.max_steps:
            shares.append(step / self.opts.max_steps)
        return max(shares, default=0.0)

    def _optimizer_step(self, progress: float) -> None:
        """Adam's step at the annealed rate; the plateau schedule keeps its own rate."""
        scheduled = [group["lr"] for group in self.optimizer.param_groups]
        for group, lr in zip(self.optimizer.param_groups, scheduled):
            group["lr"] = annealed_lr(lr, progress, self.opts.anneal_fraction, self.opts.min_lr)
        self.lr_now = self.optimizer.param_groups[0]["lr"]
        self.optimizer.step()
        for group, lr in zip(self.optimizer.param_groups, scheduled):
            group["lr"] = lr

    def _validate_and_keep(self, step: int) -> Optional[Dict[str, Any]]:
        """Rank 0 validates and saves; every rank steps its scheduler with the same loss."""
        val = None
        loss = math.nan
        if self.dist.main and self.val_items:
            val = validate(self.model, self.val_items, self.device, self.opts.task_weights,
                           self.opts.val_warmup, warmup_seconds=self.opts.val_warmup_seconds,
                           per_frame=self.opts.mode == "frames")
            loss = val["loss"]
        loss = _broadcast_float(loss, self.dist, self.device)
        if not math.isnan(loss):
            self.scheduler.step(loss)
        if self.dist.main:
            improved = val is not None and val["score"] > self.best_score
            if improved:
                self.best_score, self.best_step = float(val["score"]), step
            self._save("last.pt", step, val)
            if improved or (val is None and step > 0):
                self._save("best.pt", step, val)
            record = {"step": step, "time_s": round(self.train_seconds, 1),
                      "lr": self.lr_now,
                      "train": {k: round(v, 4) for k, v in self._ema.items()}}
            if val is not None:
                record.update(val_loss=round(val["loss"], 5), score=round(val["score"], 5),
                              summary=val["summary"], accuracy=val["accuracy"],
                              best=improved)
                logger.info("step %d: val loss %.4f, intent F1 %s, brake acc %s, score %.4f%s",
                            step, val["loss"], _pct(val["summary"]["intent_macro_f1"]),
                            _pct(val["summary"]["brake_accuracy"]), val["score"],
                            " (best)" if improved else "")
            self._log(record)
        return val

    def run(self) -> Dict[str, Any]:
        """Train until ``max_steps`` or ``max_minutes``; returns a summary of the run."""
        opts = self.opts
        if self.dist.main:
            self.out.mkdir(parents=True, exist_ok=True)
            (self.out / "options.json").write_text(json.dumps(opts.to_json(), indent=2) + "\n")
        budget = opts.max_minutes * 60.0 if opts.max_minutes else math.inf
        max_steps = opts.max_steps if opts.max_steps is not None else None
        step = self.start_step
        started = time.monotonic()
        interactive = sys.stderr.isatty()
        # Into a log file the bar is redrawn rarely, so that a long run's log stays small.
        bar = tqdm(total=max_steps, initial=step, desc="train", unit="step",
                   disable=not (opts.progress and self.dist.main), dynamic_ncols=True,
                   mininterval=1.0 if interactive else 60.0)
        ema = self._ema
        data_iter = iter(self.loader)
        last_val: Optional[Dict[str, Any]] = None
        try:
            while True:
                elapsed = time.monotonic() - started
                stop = (max_steps is not None and step >= max_steps) or elapsed >= budget
                stop = bool(_broadcast_float(float(stop), self.dist, self.device))
                if stop:
                    break
                t0 = time.monotonic()
                batch = next(data_iter)
                t_data = time.monotonic()
                self.data_wait += t_data - t0
                labels = batch["labels"].to(self.device)
                mask = batch["mask"].to(self.device)
                self.freq.update(batch["labels"].numpy(), batch["mask"].numpy())
                x = batch_input(batch["crops"], self.device)
                state = self._lane_state(batch.get("reset"))
                with torch.autocast(self.device.type, dtype=torch.bfloat16,
                                    enabled=self.precision == "bf16"):
                    logits, new_state = self.net(x, state)
                # The loss, and the state carried to the next step, in float32.
                logits = {task: v.float() for task, v in logits.items()}
                if state is not None:
                    # Truncated back-propagation: the next step starts from these values.
                    self._lanes = tuple((h.detach().float(), c.detach().float())
                                        for h, c in new_state)
                warm = self._loss_warmup(batch)
                loss, parts = multitask_loss(logits, labels, mask, opts.task_weights,
                                             self.freq.tensors(self.device), warm)
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                if opts.grad_clip > 0:
                    nn.utils.clip_grad_norm_(self.model.parameters(), opts.grad_clip)
                self._optimizer_step(self._progress(elapsed, step, budget))
                step += 1
                self.train_seconds += time.monotonic() - t0
                for key, value in (("loss", float(loss.detach())),
                                   ("intent", _batch_accuracy(logits, labels, mask, "intent")),
                                   ("brake", _batch_accuracy(logits, labels, mask, "brake"))):
                    if value is not None:
                        ema[key] = value if key not in ema else 0.9 * ema[key] + 0.1 * value
                bar.update(1)
                if (bar.disable or not interactive) and self.dist.main \
                        and step % (opts.log_every * 10) == 0:
                    logger.info("step %d: train loss %.3f, intent %s, brake %s, %.2f s/step",
                                step, ema.get("loss", math.nan), _pct(ema.get("intent")),
                                _pct(ema.get("brake")),
                                (time.monotonic() - started) / max(1, step - self.start_step))
                if step % opts.log_every == 0:
                    bar.set_postfix(loss=f"{ema.get('loss', math.nan):.3f}",
                                    intent=_pct(ema.get("intent")), brake=_pct(ema.get("brake")),
                                    lr=f"{self.lr_now:.1e}",
                                    best=f"{self.best_score:.3f}" if self.best_step >= 0 else "-")
                if step % opts.val_every == 0:
                    last_val = self._validate_and_keep(step)
                elif opts.checkpoint_every and step % opts.checkpoint_every == 0 \
                        and self.dist.main:
                    self._save("last.pt", step, None)
            # Same condition on every rank: the final state is always validated and saved.
            if step % opts.val_every != 0 or step == self.start_step:
                last_val = self._validate_and_keep(step)
        finally:
            bar.close()
            if self.dist.active:
                import torch.distributed as dist

                dist.barrier()
        wall = time.monotonic() - started
        summary = {"steps": step, "steps_this_run": step - self.start_step,
                   "wall_seconds": round(wall, 1),
                   "seconds_per_step": round(wall / max(1, step - self.start_step), 3),
                   "data_wait_seconds": round(self.data_wait, 1),
                   "best_score": self.best_score if self.best_step >= 0 else None,
                   "best_step": self.best_step, "out": str(self.out),
                   "last_validation": None if last_val is None else {
                       k: last_val[k] for k in ("loss", "score", "summary", "accuracy")}}
        if self.dist.main:
            (self.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        return summary

    def close(self) -> None:
        """Leave the process group (if any)."""
        if self.dist.active:
            import torch.distributed as dist

            if dist.is_initialized():
                dist.destroy_process_group()


def _pct(value: Optional[float]) -> str:
    return "-" if value is None else f"{100 * value:.1f}%"


def train(opts: TrainOptions) -> Dict[str, Any]:
    """Run one training (see :class:`Trainer`) and return its summary."""
    trainer = Trainer(opts)
    try:
        return trainer.run()
    finally:
        trainer.close()
