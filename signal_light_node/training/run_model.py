"""The model a run trains: fresh, warm-started from other weights, or resumed.

* ``--resume``: the checkpoint's model and config as saved.
* ``--init-from``: those weights (and their config); with ``--model`` changes the
  architecture is grown (e.g. ``temporal_input``) and starts from the old weights
  (:func:`signal_light_node.model.warm_start.warm_start`).
* otherwise a fresh ``ModelConfig`` (with the ``--model`` changes), initialised from the
  torch seed.

``--freeze-encoder`` / ``--freeze-norms`` / ``--heads-only`` then fix parts of it
(:func:`freeze_parts`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Sequence

from torch import nn

from signal_light_node.errors import ConfigError
from signal_light_node.model import DEFAULT_WEIGHTS, ModelConfig, build_model, load_checkpoint
from signal_light_node.model.config import trunk_config
from signal_light_node.model.warm_start import warm_start
from signal_light_node.training.options import TrainOptions
from signal_light_node.training.trunk_finetune import set_trainable

logger = logging.getLogger(__name__)


@dataclass
class RunModel:
    """A run's model before training.

    Attributes:
        config: Its configuration.
        model: The model (on the CPU).
        init_meta: What checkpoints record of ``--init-from`` (empty otherwise).
    """

    config: ModelConfig
    model: nn.Module
    init_meta: Dict[str, Any] = field(default_factory=dict)


def resolve_init(path: Optional[Path]) -> Optional[Path]:
    """The checkpoint ``--init-from`` names ("default" or "shipped": the shipped weights)."""
    if path is None:
        return None
    return DEFAULT_WEIGHTS if str(path) in ("default", "shipped") else Path(path)


def load_run_model(opts: TrainOptions) -> RunModel:
    """The model ``opts`` starts from (resumed, warm-started or fresh; see the module doc).

    Raises:
        CheckpointError: A checkpoint cannot be loaded.
    """
    if opts.resume is not None:
        loaded = load_checkpoint(opts.resume, map_location="cpu")
        return RunModel(loaded.config, loaded.model)
    init = resolve_init(opts.init_from)
    if init is not None:
        return _warm_started(init, opts.model, opts.grown_init_scale)
    config = ModelConfig().replace(**opts.model) if opts.model else ModelConfig()
    if config.encoder != "cnn" and "mean" not in opts.model:
        config = trunk_config(**dict(opts.model))  # the trunk's own input statistics
    return RunModel(config, build_model(config, pretrained=True))


def _warm_started(init: Path, changes: Mapping[str, Any], grown_init_scale: float) -> RunModel:
    """The weights of ``init``, in an architecture grown by ``changes`` if any."""
    loaded = load_checkpoint(init, map_location="cpu")
    meta = {"init_from": str(init), "init_training_data": loaded.meta.get("training_data")}
    if not changes:
        return RunModel(loaded.config, loaded.model, meta)
    # A grown architecture (e.g. temporal_input) starts from the old weights.
    config = loaded.config.replace(**changes)
    model = build_model(config)
    grown = warm_start(model, loaded.model.state_dict(), grown_init_scale)
    meta["init_model_changes"] = dict(changes)
    logger.info("warm start from %s with %s; new input channels in %s", init, dict(changes),
                grown)
    return RunModel(config, model, meta)


def freeze_parts(model: nn.Module, config: ModelConfig, encoder: bool, norms: bool,
                 heads_only: bool = False, trunk_from: Optional[int] = None,
                 head_tasks: Sequence[str] = (), trunk_norms: bool = False) -> None:
    """``--freeze-encoder`` (train only the ConvLSTM and the heads) and ``--freeze-norms``
    (keep the batch-norm statistics; the weights still train) and ``--heads-only``
    (:func:`freeze_to_heads`), with ``--train-trunk-from`` (:func:`train_trunk_blocks`)
    and ``--train-trunk-norms`` (:func:`train_trunk_norms`).

    Raises:
        ConfigError: The architecture cannot freeze what is asked.
    """
    if encoder:
        if not hasattr(model, "freeze_encoder"):
            raise ConfigError(f"--freeze-encoder: architecture {config.arch!r} has no "
                              "encoder to freeze")
        model.freeze_encoder()
    if norms:
        if not hasattr(model, "freeze_norms"):
            raise ConfigError(f"--freeze-norms: architecture {config.arch!r} cannot "
                              "freeze its norms")
        model.freeze_norms()
    if heads_only:
        freeze_to_heads(model, config, head_tasks)
    if trunk_from is not None:
        train_trunk_blocks(model, config, trunk_from)
    if trunk_norms:
        train_trunk_norms(model, config)


#: Parameters under a module of one of these names train with ``--heads-only``: the last
#: dense layer and the task heads (of every member of an ensemble).
HEAD_MODULES = ("fc", "heads")


def freeze_to_heads(model: nn.Module, config: ModelConfig, tasks: Sequence[str] = ()) -> None:
    """Fix everything but the output layers (:data:`HEAD_MODULES`), batch norms included;
    with ``tasks``, everything but those tasks' heads (the shared dense layer fixed too, so
    the other heads publish exactly as before).

    On a few labelled tracks a fine-tune of the recurrent part learns them by heart (on
    24 tracks of a held-out style family it lowered intent macro-F1 on the other 32:
    docs/results/adapt_family.md); the output layers alone re-weigh features the model
    already has.

    Raises:
        ConfigError: The model has no such layers or cannot keep its norms.
    """
    trainable = 0
    for name, parameter in model.named_parameters():
        parts = name.split(".")[:-1]
        keep = (any(part in HEAD_MODULES for part in parts) if not tasks
                else any(a == "heads" and b in tasks for a, b in zip(parts, parts[1:])))
        parameter.requires_grad_(keep)
        trainable += parameter.numel() if keep else 0
    if not trainable or not hasattr(model, "freeze_norms"):
        raise ConfigError(f"--heads-only: architecture {config.arch!r} has no output layers "
                          f"named {' / '.join(HEAD_MODULES)}"
                          f"{' for ' + ', '.join(tasks) if tasks else ''} to train")
    model.freeze_norms()
    logger.info("--heads-only: %d trainable parameters", trainable)


def train_trunk_blocks(model: nn.Module, config: ModelConfig, first: int) -> None:
    """Let the pretrained trunk's blocks ``first``.. learn too (their batch norms keep their
    statistics), on a model :func:`freeze_to_heads` has fixed: the output layers re-weigh
    only features the trunk already computes, and its last blocks are where a new
    camera's look can still be met.

    Raises:
        ConfigError: The model has no pretrained trunk, or ``first`` names no block.
    """
    trunk = getattr(model, "trunk", None)
    blocks = getattr(trunk, "blocks", None)
    if blocks is None:
        raise ConfigError(f"--train-trunk-from: architecture {config.arch!r} with encoder "
                          f"{config.encoder!r} has no pretrained trunk")
    if not 0 <= first < len(blocks):
        raise ConfigError(f"--train-trunk-from must name a block 0..{len(blocks) - 1}, got {first}")
    trainable = sum(p.numel() for p in set_trainable(trunk, first))
    logger.info("--train-trunk-from %d: %d more trainable parameters in %d trunk blocks",
                first, trainable, len(blocks) - first)


def train_trunk_norms(model: nn.Module, config: ModelConfig) -> None:
    """Let the scale and shift of every batch norm of the pretrained trunk learn (their
    statistics stay, as :func:`freeze_to_heads` keeps them), on a model it has fixed.

    A new camera changes how a lamp looks, not what it is: per-channel scales and shifts
    (16,160 in the shipped trunk) can meet its look while the convolutions keep what they learnt
    (on labelled tracks the trunk's last blocks learnt the tracks by heart:
    docs/results/adapt_family.md).

    Raises:
        ConfigError: The model has no pretrained trunk with batch norms.
    """
    trunk = getattr(model, "trunk", None)
    norms = [m for m in trunk.modules() if isinstance(m, nn.BatchNorm2d)] if trunk else []
    if not norms:
        raise ConfigError(f"--train-trunk-norms: architecture {config.arch!r} with encoder "
                          f"{config.encoder!r} has no pretrained trunk with batch norms")
    trainable = 0
    for norm in norms:
        for parameter in (norm.weight, norm.bias):
            parameter.requires_grad_(True)
            trainable += parameter.numel()
    logger.info("--train-trunk-norms: %d more trainable parameters in %d batch norms",
                trainable, len(norms))
