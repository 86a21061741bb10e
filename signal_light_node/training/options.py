"""The options of a training run: one dataclass with every default and its validation.

:class:`TrainOptions` is the single source of the defaults of ``signal-light train``
(``commands/train.py`` reads them with :meth:`TrainOptions.default`). This module imports
no torch, so that building the command line stays fast.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from signal_light_node.errors import ConfigError
from signal_light_node.labels import TASKS
from signal_light_node.training import BATCH_MODES, FRAME_TARGETS, PRECISIONS

#: Loss weight per head unless ``--task-weights`` changes it.
DEFAULT_TASK_WEIGHTS: Dict[str, float] = {"intent": 1.0, "brake": 1.0, "left": 0.5,
                                          "right": 0.5, "view": 0.5}

#: What a run's ``best.pt`` can be chosen by (``--select-by``).
SELECT_BY = ("frames", "published")


@dataclass
class TrainOptions:
    """Everything a training run depends on (also written to ``options.json``).

    Attributes:
        out: Output directory.
        max_steps: Stop after this many optimiser steps in total (None: no limit).
        max_minutes: Stop after this many minutes of this invocation (None: no limit).
        batch: Sequences per step per process.
        seq_len: Frames per training sequence.
        lr: Initial learning rate of Adam.
        weight_decay: L2 weight decay of the dense layers' weights.
        task_weights: Loss weight per head (0 drops a head from the loss).
        class_weight_power: Exponent of the class weights (0: unweighted).
        balance: Stratified sampling: replayed synthetic sequences are drawn uniformly
            over the strata (see :class:`.streams.ReplayStream`).
        balance_max_drop: Also thin fresh synthetic sequences of common strata with a
            :class:`.sampling.StratumBalancer` dropping at most this share (0: off; it
            throws rendering away, so it only pays where rendering is cheap).
        loss_warmup: Frames at the start of each window without intent/left/right loss.
        loss_warmup_seconds: The same in seconds (the larger of the two applies).
        grad_clip: Max gradient norm (0: no clipping).
        val_split: Materialised validation split (None: see ``val_sequences``).
        val_sequences: Size of the split materialised under ``out/val_split`` when no
            split is given and the data is synthetic.
        val_every: Steps between validations.
        val_warmup: Frames at the start of each validation sequence not scored.
        val_warmup_seconds: The same in seconds (the larger of the two applies).
        val_seq_len: Length of the sequences of a materialised validation split.
        val_fraction: Share of bag/UCM tracks held out for validation (no val_split).
        holdout_fraction: Share of the track IDs the run loads (bags, UCM, pools) held
            out of it altogether, for the before/after report (:mod:`.holdout`); 0: none.
        select_by: What ``best.pt`` is chosen by: ``frames`` (the validation windows'
            per-frame argmax, :func:`.validation.validate`) or ``published`` (whole
            validation tracks through the node's intent filter, as the before/after report
            and ``signal-light calibrate`` score them).
        plateau_patience: Validations without improvement before the LR drops.
        plateau_factor: LR multiplier on a plateau.
        min_lr: Lowest LR.
        anneal_fraction: Final share of the run's budget (its minutes or steps, whichever
            ends it first) over which the LR follows a cosine from the plateau schedule's
            value down to ``min_lr`` (0: off). A run cut by its budget while the loss still
            falls otherwise ends at its full LR, on a noisy point of the curve.
        device: "cpu" or "cuda" (or "cuda:N").
        precision: "fp32"; "bf16": the training forward pass under ``torch.autocast``
            with bfloat16 (weights, optimiser, loss and validation stay float32; about 1.2x
            the steps per second of a per-frame run on the 2-core development machine,
            whose CPU has AVX512-BF16, for the same validation score per step); or
            "auto": bf16 where :func:`.precision.resolve_precision` finds native support.
        seed: Seed of the model init, the data and the sampling.
        threads: torch intra-op threads (None: torch's default).
        workers: DataLoader worker processes for the synthetic stream (0: in-process).
        resume: Checkpoint to resume from (its ``.state.pt`` beside it), or None.
        init_from: Checkpoint whose weights (and model config) start the run, or None.
        freeze_encoder: Train only the ConvLSTM and the heads; the attention and the
            backbone keep their (``init_from``) weights (``LightStateNet.freeze_encoder``).
        freeze_norms: Keep the batch-norm statistics of the init weights
            (``LightStateNet.freeze_norms``); the weights still train.
        heads_only: Train only the output layers (the last dense layer and the task
            heads, every member's); everything before them, batch norms included, keeps
            its ``init_from`` weights (:func:`.run_model.freeze_to_heads`). What a few
            labelled tracks of a user's camera can move without overfitting.
        head_tasks: With ``heads_only``: only these tasks' heads learn (the shared dense
            layer and every other head keep their weights); empty: all output layers.
        trunk_from: With ``heads_only``: the pretrained trunk's blocks from this index on
            learn too, their batch norms keeping their statistics
            (:func:`.run_model.train_trunk_blocks`); None: the trunk stays fixed.
        trunk_norms: With ``heads_only``: the scale and shift of every batch norm of the
            pretrained trunk learn too, their statistics kept
            (:func:`.run_model.train_trunk_norms`).
        grown_init_scale: With ``init_from`` and ``model`` changes that add input
            channels: their initial weights' spread relative to the trained ones (0: zeros).
        bags: Labelled bags to train on.
        ucm: UC Merced rear-signal dataset roots to train on.
        pools: Materialised synthetic splits (``data.split``) to train on, as tracks.
        rehearse: Materialised splits rehearsed beside the labelled tracks (the training
            renders, so that a fine-tune on a few labelled tracks cannot learn them by
            heart); never held out, never validated on. Modes "windows" and "lanes".
        rehearse_share: Share of the sequences from tracks (lanes' tracks in "lanes") that
            come from ``rehearse``.
        mode: How batches are cut: "windows" (``batch`` windows of ``seq_len`` frames,
            each from a zero state), "frames" (``batch`` single frames from anywhere in
            the tracks: per-frame pre-training) or "lanes" (``batch`` tracks played side
            by side, ``seq_len`` frames per step, their state carried between steps; see
            :mod:`.track_batches`). Frames and lanes take in-memory tracks (bags, pools)
            only; the live synthetic stream gives windows.
        frame_targets: What the heads learn in ``mode`` "frames": "state" (the logical
            light states) or "lit" (what the single frame shows: a blinker counts as ON
            only in the lit half of a blink, intent following; pools and the validation
            split give these as ``lit_labels``). A blink's dark half is otherwise label
            noise for a model that sees one frame.
        lit_map_weight: Weight of the lit-map loss (``training.loss.lit_map_loss``) in
            ``mode`` "frames": the model's ``lit_map_head`` draws where the vehicle's
            lamps are lit, against the pools' ``lit_maps`` (splits written with
            ``--lit-maps``). 0: off.
        synthetic_fraction: Share of sequences from the synthetic stream; None means 1
            without bags/UCM and 0 with them.
        mirror_prob: Probability that a sequence is mirrored.
        jitter: Colour/brightness jitter per sequence.
        camera_response: A random camera response per sequence (tone curve, saturation,
            clipping, noise, blur, resolution, JPEG; ``data.camera_response``).
        shape_warp: A random perspective warp per sequence (``data.shape_warp``).
        reuse: Average number of times a rendered synthetic sequence is served
            (:class:`.streams.ReplayStream`; rendering costs more than a training step).
        replay_capacity: Rendered sequences kept for reuse, per data worker.
        model: ``ModelConfig`` fields that differ from the defaults (ignored with init_from).
        stream: Extra ``SyntheticSequenceStream`` options (vehicles, sizes, ...).
        log_every: Steps between progress-bar metric updates.
        progress: Show tqdm progress bars.
        checkpoint_every: Steps between ``last.pt`` saves (0: only at validations).
    """

    out: Path
    max_steps: Optional[int] = None
    max_minutes: Optional[float] = None
    batch: int = 8
    seq_len: int = 16
    lr: float = 1e-3
    weight_decay: float = 1e-4
    task_weights: Dict[str, float] = field(default_factory=lambda: dict(DEFAULT_TASK_WEIGHTS))
    class_weight_power: float = 0.5
    balance: bool = True
    balance_max_drop: float = 0.0
    loss_warmup: int = 2
    loss_warmup_seconds: float = 0.4
    grad_clip: float = 5.0
    val_split: Optional[Path] = None
    val_sequences: int = 96
    val_every: int = 200
    val_warmup: int = 8
    val_warmup_seconds: float = 0.75
    val_seq_len: int = 48
    val_fraction: float = 0.1
    holdout_fraction: float = 0.0
    select_by: str = "frames"
    plateau_patience: int = 3
    plateau_factor: float = 0.3
    min_lr: float = 1e-5
    anneal_fraction: float = 0.0
    device: str = "cpu"
    precision: str = "fp32"
    seed: int = 0
    threads: Optional[int] = None
    workers: int = 1
    resume: Optional[Path] = None
    init_from: Optional[Path] = None
    freeze_encoder: bool = False
    freeze_norms: bool = False
    heads_only: bool = False
    trunk_from: Optional[int] = None
    trunk_norms: bool = False
    head_tasks: Tuple[str, ...] = ()
    grown_init_scale: float = 0.0
    bags: List[Path] = field(default_factory=list)
    ucm: List[Path] = field(default_factory=list)
    pools: List[Path] = field(default_factory=list)
    rehearse: List[Path] = field(default_factory=list)
    rehearse_share: float = 0.5
    mode: str = "windows"
    frame_targets: str = "state"
    lit_map_weight: float = 0.0
    synthetic_fraction: Optional[float] = None
    mirror_prob: float = 0.5
    jitter: bool = True
    camera_response: bool = False
    shape_warp: bool = False
    reuse: float = 2.0
    replay_capacity: int = 1500
    model: Dict[str, Any] = field(default_factory=dict)
    stream: Dict[str, Any] = field(default_factory=dict)
    log_every: int = 10
    progress: bool = True
    checkpoint_every: int = 0


    @classmethod
    def default(cls, name: str) -> Any:
        """The default value of option ``name`` (a fresh copy for lists and dicts).

        Raises:
            ConfigError: There is no such option, or it has no default (``out``).
        """
        for f in dataclasses.fields(cls):
            if f.name != name:
                continue
            if f.default_factory is not dataclasses.MISSING:
                return f.default_factory()
            if f.default is not dataclasses.MISSING:
                return f.default
            raise ConfigError(f"training option {name!r} has no default")
        raise ConfigError(f"no training option named {name!r}")

    def validate(self) -> None:
        """Raise ConfigError for values that cannot work."""
        self._check_budget()
        self._check_optimisation()
        self._check_data()
        self._check_device()

    def _check_budget(self) -> None:
        if self.max_steps is None and self.max_minutes is None:
            raise ConfigError("give --steps or --max-minutes (or both); training would never stop")
        if self.max_steps is not None and self.max_steps < 0:
            raise ConfigError(f"--steps must be >= 0, got {self.max_steps}")
        if self.max_minutes is not None and not self.max_minutes > 0:
            raise ConfigError(f"--max-minutes must be positive, got {self.max_minutes}")
        for name in ("batch", "seq_len", "val_every", "val_sequences", "log_every"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")

    def _check_optimisation(self) -> None:
        if not self.lr > 0:
            raise ConfigError(f"learning rate must be positive, got {self.lr}")
        unknown = sorted(set(self.task_weights) - set(TASKS))
        if unknown:
            raise ConfigError(f"task weights for unknown tasks {unknown}; tasks are {list(TASKS)}")
        if any(w < 0 for w in self.task_weights.values()) or \
                not any(w > 0 for w in self.task_weights.values()):
            raise ConfigError(f"task weights must be >= 0 with at least one > 0, got "
                              f"{self.task_weights}")
        if not 0 <= self.anneal_fraction < 1:
            raise ConfigError(f"anneal fraction must be in [0, 1), got {self.anneal_fraction}")

    def _check_data(self) -> None:
        if self.synthetic_fraction is not None and not 0 <= self.synthetic_fraction <= 1:
            raise ConfigError(f"synthetic fraction must be in 0..1, got {self.synthetic_fraction}")
        if self.synthetic_fraction == 0 and not (self.bags or self.ucm or self.pools):
            raise ConfigError("no data: the synthetic fraction is 0 and no --bags / --ucm / "
                              "--pool given")
        self._check_mode()
        if self.freeze_encoder and self.init_from is None and self.resume is None:
            raise ConfigError("--freeze-encoder needs --init-from (or --resume): a frozen "
                              "untrained encoder would never learn")
        if self.heads_only and self.init_from is None and self.resume is None:
            raise ConfigError("--heads-only needs --init-from (or --resume): heads on an "
                              "untrained network would learn nothing")
        for flag, asked, what in (
                ("--head-tasks", bool(self.head_tasks), "it narrows the output layers that learn"),
                ("--train-trunk-from", self.trunk_from is not None,
                 "it adds trunk blocks to the output layers that learn"),
                ("--train-trunk-norms", self.trunk_norms,
                 "it adds the trunk's batch-norm scales and shifts to the output layers that "
                 "learn")):
            if asked and not self.heads_only:
                raise ConfigError(f"{flag} goes with --heads-only: {what}")
        unknown = [t for t in self.head_tasks if t not in TASKS]
        if unknown:
            raise ConfigError(f"--head-tasks: unknown task {unknown[0]!r} (tasks: "
                              f"{', '.join(TASKS)})")
        if not 0 <= self.val_fraction < 1:
            raise ConfigError(f"validation fraction must be in [0, 1), got {self.val_fraction}")
        if not 0 <= self.holdout_fraction < 1:
            raise ConfigError(f"holdout fraction must be in [0, 1), got {self.holdout_fraction}")
        if self.holdout_fraction > 0 and (self.init_from is None
                                          or not (self.bags or self.ucm or self.pools)):
            raise ConfigError("--holdout-fraction needs --init-from and labelled tracks "
                              "(--bags, --ucm or --pool): it compares the model before and "
                              "after")
        self._check_selection()
        self._check_rehearsal()

    def _check_rehearsal(self) -> None:
        if not self.rehearse:
            return
        if not (self.bags or self.ucm or self.pools):
            raise ConfigError("--rehearse goes beside labelled tracks (--bags, --ucm or "
                              "--pool); alone, give the splits as --pool")
        if self.mode == "frames":
            raise ConfigError("--rehearse is for --mode windows or lanes")
        if not 0 < self.rehearse_share < 1:
            raise ConfigError(f"--rehearse-share must be in (0, 1), got {self.rehearse_share}")

    def _check_selection(self) -> None:
        if self.select_by not in SELECT_BY:
            raise ConfigError(f"--select-by must be one of {list(SELECT_BY)}, got "
                              f"{self.select_by!r}")
        if self.select_by == "published" and (self.val_split is not None
                                              or self.val_fraction <= 0
                                              or not (self.bags or self.pools)):
            raise ConfigError("--select-by published scores whole labelled tracks the run "
                              "holds out: it needs --bags or --pool, --val-fraction > 0 and "
                              "no --val-split")

    def _check_mode(self) -> None:
        if self.mode not in BATCH_MODES:
            raise ConfigError(f"mode must be one of {list(BATCH_MODES)}, got {self.mode!r}")
        if self.mode != "windows":
            if not (self.bags or self.pools):
                raise ConfigError(f"--mode {self.mode} needs in-memory tracks: give --pool or "
                                  "--bags (the live synthetic stream only gives windows)")
            if self.synthetic_fraction:
                raise ConfigError(f"--mode {self.mode} cannot mix in the live synthetic "
                                  "stream; drop --synthetic-fraction")
            if self.ucm:
                raise ConfigError(f"--mode {self.mode} needs in-memory tracks; UCM frames are "
                                  "read lazily, use --mode windows for --ucm")
        if self.frame_targets not in FRAME_TARGETS:
            raise ConfigError(f"frame targets must be one of {list(FRAME_TARGETS)}, got "
                              f"{self.frame_targets!r}")
        if self.frame_targets == "lit" and (self.mode != "frames" or self.bags or self.ucm):
            raise ConfigError("--frame-targets lit is for --mode frames on --pool splits: "
                              "only single frames are judged by what they show, and only "
                              "rendered splits carry per-frame lamp labels")
        self._check_lit_maps()

    def _check_lit_maps(self) -> None:
        if self.lit_map_weight < 0:
            raise ConfigError(f"--lit-map-weight must be >= 0, got {self.lit_map_weight}")
        if self.lit_map_weight == 0:
            return
        if self.mode != "frames" or self.bags or self.ucm:
            raise ConfigError("--lit-map-weight is for --mode frames on --pool splits written "
                              "with --lit-maps")
        if self.shape_warp:
            # The warp moves the crop's pixels; the maps would no longer lie under them.
            raise ConfigError("--lit-map-weight cannot be combined with --shape-warp")

    def _check_device(self) -> None:
        if not str(self.device).startswith(("cpu", "cuda")):
            raise ConfigError(f"device must be cpu or cuda[:N], got {self.device!r}")
        if self.precision not in PRECISIONS:
            raise ConfigError(f"precision must be one of {list(PRECISIONS)}, got "
                              f"{self.precision!r}")
        if str(self.device).startswith("cuda"):
            import torch  # here, not at the top: the command line is built without torch

            if not torch.cuda.is_available():
                raise ConfigError("--device cuda was asked for but torch sees no CUDA device")

    def to_json(self) -> Dict[str, Any]:
        """Plain dict of the options (paths as strings)."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, Path):
                v = str(v)
            elif isinstance(v, list):
                v = [str(x) if isinstance(x, Path) else x for x in v]
            out[f.name] = v
        return out
