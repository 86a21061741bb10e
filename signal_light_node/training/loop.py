"""The training run behind ``signal-light train`` (one process, or DDP under torchrun).

Recipe (after the research the model follows, scaled to a CPU), and where each part is:

* **Options** and their defaults: :class:`.options.TrainOptions`.
* **Loss** (:mod:`.loss`): the sum over heads of ``task_weight * cross-entropy``, each
  averaged over the valid frames of the batch; the blinker-driven heads skip a warm-up at
  the start of every window. Class-weighted by running label counts
  (:class:`.sampling.ClassFrequency`).
* **Data** (:mod:`.run_data`, :mod:`.loaders`, :mod:`.streams`, :mod:`.augment`):
  stratified sequences over the strata HAZARD / brake-with-blinker / blinker / brake /
  plain; a rendered synthetic sequence is served ``reuse`` times on average from a replay
  buffer, each time augmented anew (mirroring, colour jitter, optionally camera response
  and shape warp): on a 2-core CPU rendering is slower than training. Batches are windows,
  single frames or stateful lanes (``--mode``; lanes carry their state across steps,
  :class:`.model_inputs.LaneState`).
* **Optimiser and schedule** (:mod:`.optimizer`, :mod:`.schedule`): Adam, L2 weight decay
  on the dense layers' weights; ``ReduceLROnPlateau`` on the validation loss, optionally
  a cosine decay to ``min_lr`` over the last ``anneal_fraction`` of the budget.
* **Precision** (:mod:`.precision`): the forward pass optionally under bfloat16 autocast.
* **Validation** every ``val_every`` steps on fixed sequences (:mod:`.validation`), and
  before the first step of a run from ``init_from``; the best checkpoint by the selection
  score is kept as ``best.pt``.
* **Files** in ``out`` (:mod:`.checkpointing`, :mod:`.progress`): ``last.pt`` /
  ``best.pt`` (model checkpoints), ``last.state.pt`` (what ``--resume`` needs),
  ``log.jsonl`` (one line per validation), ``options.json`` and ``summary.json``.
* **DDP** (:mod:`.distributed`): every rank draws its own data (the rank enters all data
  seeds), rank 0 alone validates and writes files, and the validation loss and the stop
  decision are broadcast so that every rank's scheduler and loop stay in step.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path
from typing import Any, Dict, Iterator, Mapping, Optional, Tuple

import torch
from torch import nn

from signal_light_node.errors import ConfigError
from signal_light_node.model import save_checkpoint
from signal_light_node.model.network import LIT_MAP_KEY
from signal_light_node.training.checkpointing import (
    RunCounters,
    checkpoint_meta,
    load_training_state,
    restore_training_state,
    training_state,
    write_training_state,
)
from signal_light_node.training.distributed import (
    barrier,
    broadcast_float,
    init_distributed,
    leave,
    rank_device,
    wrap_model,
)
from signal_light_node.training.loaders import training_loader
from signal_light_node.training.loss import batch_loss_warmup, lit_map_loss, multitask_loss
from signal_light_node.training.model_inputs import LaneState, batch_input
from signal_light_node.training.optimizer import build_optimizer
from signal_light_node.training.options import TrainOptions
from signal_light_node.training.precision import forward_autocast, resolve_precision
from signal_light_node.training.progress import (
    ProgressReport,
    append_log,
    log_validation,
    update_running,
    validation_record,
)
from signal_light_node.training.holdout import report_after_run, split_by_track_id
from signal_light_node.training.run_data import (
    hold_out_tracks,
    load_rehearsal,
    load_tracks,
    synthetic_share,
    validation_items,
)
from signal_light_node.training.run_model import freeze_parts, load_run_model
from signal_light_node.training.sampling import ClassFrequency
from signal_light_node.training.schedule import annealed_step, budget_progress, plateau_scheduler
from signal_light_node.training.seeding import data_seed, seed_everything
from signal_light_node.training.validation import validate, with_published_score

logger = logging.getLogger(__name__)

Batch = Mapping[str, Any]


class Trainer:
    """One training run; :meth:`run` returns a summary dict.

    Setting up follows a fixed order (process group, seeds, model, optimiser, resumed
    state, data), so that a seed gives the same run every time.

    Args:
        opts: The options (validated here).

    Raises:
        ConfigError: An option cannot work.
        CheckpointError: A checkpoint to start from cannot be loaded.
    """

    def __init__(self, opts: TrainOptions) -> None:
        opts.validate()
        self.opts = opts
        self.out = Path(opts.out)
        self.dist = init_distributed(str(opts.device))
        if opts.threads:
            torch.set_num_threads(int(opts.threads))
        self.device = rank_device(opts.device, self.dist)
        seed_everything(opts.seed)
        resumed = self._setup_model()
        self._setup_optimisation(resumed)
        self.net: nn.Module = wrap_model(self.model, self.dist, self.device)
        self._setup_data()

    # --------------------------------------------------------------------- set-up

    def _setup_model(self) -> Optional[Dict[str, Any]]:
        """The model, its precision and crop; returns the training state to resume, if any."""
        opts = self.opts
        loaded = load_run_model(opts)
        resumed = load_training_state(Path(opts.resume)) if opts.resume is not None else None
        self.config, self.meta_from_init = loaded.config, loaded.init_meta
        freeze_parts(loaded.model, self.config, opts.freeze_encoder, opts.freeze_norms,
                     opts.heads_only, opts.trunk_from, opts.head_tasks, opts.trunk_norms)
        self.model = loaded.model.to(self.device).train()
        self.precision = resolve_precision(opts.precision, self.device)
        logger.info("training precision: %s", self.precision)
        self.crop = self.config.crop_config()
        return resumed

    def _setup_optimisation(self, resumed: Optional[Mapping[str, Any]]) -> None:
        """Optimiser, schedule, class counts and counters, restored from ``resumed``."""
        opts = self.opts
        self.optimizer = build_optimizer(self.model, opts.lr, opts.weight_decay)
        self.scheduler = plateau_scheduler(self.optimizer, opts.plateau_patience,
                                           opts.plateau_factor, opts.min_lr)
        self.freq = ClassFrequency(self.config.num_classes, power=opts.class_weight_power)
        self.counters = RunCounters(step=0, best_score=-math.inf, best_step=-1,
                                    train_seconds=0.0)
        self.data_wait = 0.0  # seconds this invocation waited for batches
        self.running: Dict[str, float] = {}  # running training loss and batch accuracies
        self.lanes = LaneState()  # carried state of the lanes (mode "lanes")
        if resumed is not None:
            self.counters = restore_training_state(resumed, self.optimizer, self.scheduler,
                                                   self.freq)
            logger.info("resumed from %s at step %d (best %.4f at step %d)", opts.resume,
                        self.counters.step, self.counters.best_score, self.counters.best_step)
        self.start_step = self.counters.step
        self.lr_now = self.optimizer.param_groups[0]["lr"]  # the last step's, annealing included

    def _setup_data(self) -> None:
        """Tracks, held-out tracks, validation items and the training loader."""
        opts = self.opts
        # Tracks held out for the before/after report (.holdout) never reach the run.
        self.tracks, self.holdout_tracks = split_by_track_id(
            load_tracks(opts, self.crop), opts.holdout_fraction, opts.seed)
        self.synthetic_share = synthetic_share(opts, self.tracks)
        self.train_tracks, held_out = hold_out_tracks(
            self.tracks, opts.val_fraction if opts.val_split is None else 0.0)
        if opts.lit_map_weight > 0:
            self._check_lit_maps()
        self.val_items = (validation_items(opts, self.crop, held_out, self.synthetic_share)
                          if self.dist.main else [])
        self.val_tracks = held_out  # whole, for --select-by published
        # Rehearsed tracks only train: the held-out and validation draws never see them.
        self.loader = training_loader(opts, self.crop, self.train_tracks, self.synthetic_share,
                                      data_seed(opts.seed, self.start_step), self.dist.rank,
                                      load_rehearsal(opts, self.crop))

    def _check_lit_maps(self) -> None:
        """``--lit-map-weight`` needs the model's lit-map head and maps on every track."""
        if getattr(self.model, "lit_map_head", None) is None:
            raise ConfigError("--lit-map-weight needs a model with a lit-map head: "
                              "--model lit_map_head=true")
        bare = [t.track_id for t in self.train_tracks if t.lit_maps is None]
        if bare:
            raise ConfigError(f"--lit-map-weight: {len(bare)} training tracks have no lit "
                              "maps; write the pools with --lit-maps")

    # ------------------------------------------------------------------------ loop

    def run(self) -> Dict[str, Any]:
        """Train until ``max_steps`` or ``max_minutes``; returns a summary of the run."""
        opts = self.opts
        if self.dist.main:
            self.out.mkdir(parents=True, exist_ok=True)
            (self.out / "options.json").write_text(json.dumps(opts.to_json(), indent=2) + "\n")
        budget = opts.max_minutes * 60.0 if opts.max_minutes else math.inf
        started = time.monotonic()
        report = ProgressReport(opts.max_steps, self.start_step,
                                show_bar=opts.progress and self.dist.main, main=self.dist.main,
                                log_every=opts.log_every)
        data_iter = iter(self.loader)
        last_val: Optional[Dict[str, Any]] = None
        try:
            if self.start_step == 0 and opts.init_from is not None:
                # The weights it starts from compete for best.pt: a fine-tune on a few
                # tracks that only loses on validation hands them back unchanged.
                last_val = self._validate_and_keep(only_scored=True)
            while True:
                elapsed = time.monotonic() - started
                if self._should_stop(elapsed, budget):
                    break
                share = budget_progress(elapsed, budget, self.counters.step, opts.max_steps)
                self._train_step(data_iter, share)
                step = self.counters.step
                report.step(step, self.running, self.lr_now, self.counters.best_score,
                            self.counters.best_step)
                if step % opts.val_every == 0:
                    last_val = self._validate_and_keep()
                elif opts.checkpoint_every and step % opts.checkpoint_every == 0 \
                        and self.dist.main:
                    self._save("last.pt", None)
            # Same condition on every rank: the final state is always validated and saved.
            if self.counters.step % opts.val_every != 0 or self.counters.step == self.start_step:
                last_val = self._validate_and_keep()
        finally:
            report.close()
            barrier(self.dist)
        summary = self._summary(time.monotonic() - started, last_val)
        if self.dist.main and self.holdout_tracks:
            summary["adapt_report"] = str(report_after_run(opts, summary, self.holdout_tracks))
        return summary

    def _should_stop(self, elapsed: float, budget: float) -> bool:
        """Rank 0's decision whether the step or time budget is spent."""
        max_steps = self.opts.max_steps
        stop = (max_steps is not None and self.counters.step >= max_steps) or elapsed >= budget
        return bool(broadcast_float(float(stop), self.dist, self.device))

    def _train_step(self, data_iter: Iterator[Batch], share: float) -> None:
        """One optimiser step on the next batch; ``share``: of the budget used (annealing)."""
        t0 = time.monotonic()
        batch = next(data_iter)
        self.data_wait += time.monotonic() - t0
        logits, labels, mask = self._forward(batch)
        warm = batch_loss_warmup(batch, self.opts.loss_warmup, self.opts.loss_warmup_seconds,
                                 self.opts.mode == "frames", self.device)
        loss, _ = multitask_loss(logits, labels, mask, self.opts.task_weights,
                                 self.freq.tensors(self.device), warm)
        if self.opts.lit_map_weight > 0:
            loss = loss + self.opts.lit_map_weight * lit_map_loss(
                logits[LIT_MAP_KEY], batch["lit_maps"])
        self._optimise(loss, share)
        self.counters.step += 1
        self.counters.train_seconds += time.monotonic() - t0
        update_running(self.running, loss, logits, labels, mask)

    def _forward(self, batch: Batch) -> Tuple[Dict[str, torch.Tensor], torch.Tensor,
                                              torch.Tensor]:
        """Float32 logits of a training batch (lanes: carrying their state), labels, mask."""
        labels = batch["labels"].to(self.device)
        mask = batch["mask"].to(self.device)
        self.freq.update(batch["labels"].numpy(), batch["mask"].numpy())
        x = batch_input(batch["crops"], self.device)
        state = self.lanes.begin(batch.get("reset"), self.model, self.device)
        with forward_autocast(self.precision, self.device):
            logits, new_state = self.net(x, state)
        # The loss, and the state carried to the next step, in float32.
        logits = {task: v.float() for task, v in logits.items()}
        if state is not None:
            # Truncated back-propagation: the next step starts from these values.
            self.lanes.keep(new_state)
        return logits, labels, mask

    def _optimise(self, loss: torch.Tensor, share: float) -> None:
        """Back-propagate ``loss``, clip the gradients, take the (annealed) Adam step."""
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.opts.grad_clip > 0:
            nn.utils.clip_grad_norm_(self.model.parameters(), self.opts.grad_clip)
        self.lr_now = annealed_step(self.optimizer, share, self.opts.anneal_fraction,
                                    self.opts.min_lr)

    # ------------------------------------------------------- validation and files

    def _validate_and_keep(self, only_scored: bool = False) -> Optional[Dict[str, Any]]:
        """Rank 0 validates and saves; every rank steps its scheduler with the same loss.

        ``only_scored``: save nothing when there is nothing to validate on (the start
        weights, unscored, are no checkpoint worth writing).
        """
        val = None
        if self.dist.main and self.val_items:
            opts = self.opts
            val = validate(self.model, self.val_items, self.device, opts.task_weights,
                           opts.val_warmup, warmup_seconds=opts.val_warmup_seconds,
                           per_frame=opts.mode == "frames")
            if opts.select_by == "published":
                val = with_published_score(val, self.model, self.val_tracks, self.device)
        loss = broadcast_float(math.nan if val is None else val["loss"], self.dist, self.device)
        if not math.isnan(loss):
            self.scheduler.step(loss)
        if self.dist.main and (val is not None or not only_scored):
            self._keep(val)
        return val

    def _keep(self, val: Optional[Mapping[str, Any]]) -> None:
        """Save ``last.pt`` (and ``best.pt`` when the score improved) and log the validation."""
        step = self.counters.step
        improved = val is not None and val["score"] > self.counters.best_score
        if improved:
            self.counters.best_score, self.counters.best_step = float(val["score"]), step
        self._save("last.pt", val)
        if improved or (val is None and step > 0):
            self._save("best.pt", val)
        record = validation_record(step, self.counters.train_seconds, self.lr_now,
                                   self.running, val, improved)
        if val is not None:
            log_validation(step, val, improved)
        append_log(self.out, record)

    def _save(self, name: str, val: Optional[Mapping[str, Any]]) -> Path:
        """Save the model as ``out/name``; ``last.pt`` gets its training state beside it."""
        path = self.out / name
        meta = checkpoint_meta(self.opts, self.counters, synthetic_share=self.synthetic_share,
                               world=self.dist.world, lr=self.lr_now, precision=self.precision,
                               init_meta=self.meta_from_init, val=val)
        save_checkpoint(path, self.model, self.config, meta)
        if name == "last.pt":
            write_training_state(path, training_state(self.counters, self.optimizer,
                                                      self.scheduler, self.freq))
        return path

    def _summary(self, wall: float, last_val: Optional[Mapping[str, Any]]) -> Dict[str, Any]:
        """The run's summary (also written to ``out/summary.json`` by rank 0)."""
        steps_this_run = self.counters.step - self.start_step
        summary = {"steps": self.counters.step, "steps_this_run": steps_this_run,
                   "wall_seconds": round(wall, 1),
                   "seconds_per_step": round(wall / max(1, steps_this_run), 3),
                   "data_wait_seconds": round(self.data_wait, 1),
                   "best_score": (self.counters.best_score if self.counters.best_step >= 0
                                  else None),
                   "best_step": self.counters.best_step, "out": str(self.out),
                   "last_validation": None if last_val is None else {
                       k: last_val[k] for k in ("loss", "score", "summary", "accuracy")}}
        if self.dist.main:
            (self.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        return summary

    def close(self) -> None:
        """Leave the process group (if any)."""
        leave(self.dist)


def train(opts: TrainOptions) -> Dict[str, Any]:
    """Run one training (see :class:`Trainer`) and return its summary."""
    trainer = Trainer(opts)
    try:
        return trainer.run()
    finally:
        trainer.close()
