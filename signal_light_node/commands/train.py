"""``signal-light train``: train (or fine-tune) the light-state model.

Examples::

    # from scratch on the synthetic stream, 60 minutes on this CPU
    signal-light train --out runs/syn --max-minutes 60

    # fine-tune the shipped weights on your labelled bags and the UCM dataset
    signal-light train --out runs/ft --init-from default --bags my.bag --ucm ~/ucm --steps 2000

    # the shipped recipe: per-frame pre-training, then stateful lanes (scripts/train_default.sh)
    signal-light train --out runs/f --pool runs/pool --mode frames --batch 64 --max-minutes 30
    signal-light train --out runs/l --pool runs/pool --mode lanes --batch 32 --seq-len 12 \
        --init-from runs/f/best.pt --max-minutes 45

    # fine-tune the shipped weights on your labelled bags, 30 % of their tracks held out,
    # and compare before / after on them (OUT/adapt_report.md, adapt_report.json)
    signal-light train --out runs/mine --init-from default --bags out/day_labelled \
        --holdout-fraction 0.3 --steps 500

    # resume an interrupted run (last.pt + last.state.pt in --out)
    signal-light train --out runs/syn --max-minutes 30 --resume

    # data-parallel over two processes (gloo on CPU; NCCL with --device cuda)
    torchrun --nproc_per_node=2 -m signal_light_node.cli train --out runs/ddp --steps 1000

See :mod:`signal_light_node.training.loop` for the recipe and the files written, and
:class:`signal_light_node.training.options.TrainOptions` for every option; the defaults
here are read from it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Dict

from signal_light_node.commands.options import add_labelled_data_options, add_torch_options
from signal_light_node.errors import ConfigError
from signal_light_node.training import BATCH_MODES, FRAME_TARGETS, PRECISIONS
from signal_light_node.training.options import SELECT_BY, TrainOptions

#: The default of a training option (``TrainOptions``: the one place they are set).
_default = TrainOptions.default


def _key_values(text: str, what: str) -> Dict[str, Any]:
    """Parse ``a=1,b=x`` or a JSON object into a dict (values JSON-decoded when possible)."""
    text = text.strip()
    if not text:
        return {}
    if text.startswith("{"):
        try:
            value = json.loads(text)
        except ValueError as exc:
            raise ConfigError(f"{what}: invalid JSON: {exc}") from None
        if not isinstance(value, dict):
            raise ConfigError(f"{what}: expected a JSON object")
        return value
    out: Dict[str, Any] = {}
    for part in text.split(","):
        key, sep, raw = part.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"{what}: expected key=value pairs, got {part!r}")
        try:
            out[key.strip()] = json.loads(raw)
        except ValueError:
            out[key.strip()] = raw.strip()
    return out


def _task_weights_text() -> str:
    """The default task weights as ``--task-weights`` spells them."""
    return ",".join(f"{task}={weight:g}" for task, weight in _default("task_weights").items())


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``signal-light train``."""
    parser.formatter_class = argparse.ArgumentDefaultsHelpFormatter
    g = parser.add_argument_group("run")
    g.add_argument("--out", required=True, type=Path, help="output directory (checkpoints, logs)")
    g.add_argument("--steps", type=int, default=_default("max_steps"),
                   help="total optimiser steps to reach")
    g.add_argument("--max-minutes", type=float, default=_default("max_minutes"),
                   help="wall-clock budget of this invocation")
    g.add_argument("--seed", type=int, default=_default("seed"),
                   help="seed of init, data and sampling")
    g.add_argument("--workers", type=int, default=_default("workers"),
                   help="DataLoader processes rendering synthetic data (0: in the main process)")
    g.add_argument("--resume", nargs="?", const="", default=_default("resume"), metavar="CKPT",
                   help="resume from CKPT (default OUT/last.pt) and its .state.pt")
    g.add_argument("--init-from", default=_default("init_from"), metavar="CKPT",
                   help="start from these weights ('default' = the shipped weights)")
    g.add_argument("--freeze-encoder", action="store_true",
                   help="train only the ConvLSTM and the heads on the --init-from encoder")
    g.add_argument("--heads-only", action="store_true",
                   help="train only the output layers (last dense layer and task heads); the "
                        "rest, batch norms included, keeps the --init-from weights")
    g.add_argument("--head-tasks", type=lambda text: tuple(t for t in text.split(",") if t),
                   default=(), metavar="TASK,...",
                   help="with --heads-only: only these tasks' heads learn (e.g. brake: the "
                        "shared dense layer and the other heads keep their weights)")
    g.add_argument("--train-trunk-from", type=int, default=None, metavar="N",
                   help="with --heads-only: the pretrained trunk's blocks N.. learn too "
                        "(their batch norms keep their statistics)")
    g.add_argument("--train-trunk-norms", action="store_true",
                   help="with --heads-only: the scale and shift of every batch norm of the "
                        "pretrained trunk learn too (their statistics kept): 16,160 numbers in "
                        "the shipped trunk that meet a camera's look without relearning what "
                        "a lamp is")
    add_torch_options(g)

    g = parser.add_argument_group("data")
    add_labelled_data_options(g)
    g.add_argument("--synthetic-fraction", type=float,
                   default=_default("synthetic_fraction"),
                   help="share of synthetic sequences (default 1 without --bags/--ucm, else 0)")
    g.add_argument("--pool", dest="pools", action="append", type=Path,
                   default=_default("pools"), metavar="SPLIT",
                   help="materialised synthetic split to train on as whole "
                   "tracks (python -m signal_light_node.data.split ... --full-tracks); repeatable")
    g.add_argument("--rehearse", action="append", type=Path, default=_default("rehearse"),
                   metavar="SPLIT",
                   help="materialised split rehearsed beside the labelled tracks (training "
                   "renders, so a fine-tune cannot learn a few tracks by heart); never held "
                   "out or validated on; repeatable; --mode windows or lanes")
    g.add_argument("--rehearse-share", type=float, default=_default("rehearse_share"),
                   help="share of the track sequences (lanes' tracks) drawn from --rehearse")
    g.add_argument("--mode", choices=BATCH_MODES, default=_default("mode"),
                   help="windows: sequences from a zero state; frames: single frames from "
                   "anywhere (per-frame pre-training); lanes: --batch tracks side by side, "
                   "--seq-len frames per step, state carried (frames/lanes need --pool/--bags)")
    g.add_argument("--frame-targets", choices=tuple(FRAME_TARGETS),
                   default=_default("frame_targets"),
                   help="--mode frames only: state: the lights' logical states; lit: what "
                   "each frame shows (a blink's dark half counts as off; --pool splits only)")
    g.add_argument("--lit-map-weight", type=float, default=_default("lit_map_weight"),
                   help="--mode frames only: weight of the loss on where the lamps are lit "
                   "(needs --model lit_map_head=true and pools written with --lit-maps)")
    g.add_argument("--batch", type=int, default=_default("batch"),
                   help="sequences (frames in --mode frames, lanes in --mode lanes) per step "
                   "per process")
    g.add_argument("--seq-len", type=int, default=_default("seq_len"),
                   help="frames per training sequence")
    g.add_argument("--no-mirror", action="store_true", help="no mirroring augmentation")
    g.add_argument("--no-jitter", action="store_true", help="no colour jitter")
    g.add_argument("--camera-response", action="store_true",
                   help="a random camera response per sequence (tone, saturation, clipping, "
                        "noise, blur, resolution, JPEG)")
    g.add_argument("--freeze-norms", action="store_true",
                   help="keep the init weights' batch-norm statistics (fine-tuning on augmented data)")
    g.add_argument("--grown-init-scale", type=float, default=_default("grown_init_scale"),
                   metavar="S",
                   help="with --init-from and --model adding input channels: their initial "
                        "weights' spread relative to the trained ones (0: zeros)")
    g.add_argument("--shape-warp", action="store_true",
                   help="a random perspective warp per sequence (vehicle shape and view)")
    g.add_argument("--no-balance", action="store_true",
                   help="replay synthetic sequences in natural shares, not stratified")
    g.add_argument("--balance-drop", type=float, default=_default("balance_max_drop"),
                   help="also drop up to this share of fresh sequences of common strata")
    g.add_argument("--reuse", type=float, default=_default("reuse"),
                   help="average times a rendered synthetic sequence is served (replay)")
    g.add_argument("--stream", default="", metavar="K=V,...",
                   help="extra SyntheticSequenceStream options, e.g. 'vehicles=[2,5]'")

    g = parser.add_argument_group("optimisation")
    g.add_argument("--lr", type=float, default=_default("lr"),
                   help="initial Adam learning rate")
    g.add_argument("--weight-decay", type=float, default=_default("weight_decay"),
                   help="L2 on dense layers")
    g.add_argument("--precision", choices=PRECISIONS, default=_default("precision"),
                   help="bf16: the forward pass autocast to bfloat16 (about 1.2x faster on a "
                        "CPU with AVX512-BF16; weights and validation stay float32); auto: "
                        "bf16 where the hardware supports it natively")
    g.add_argument("--task-weights", default="", metavar="T=W,...",
                   help=f"loss weight per head, e.g. '{_task_weights_text()}'")
    g.add_argument("--class-weight-power", type=float,
                   default=_default("class_weight_power"),
                   help="class weights (share)^-power; 0 disables")
    g.add_argument("--loss-warmup", type=int, default=_default("loss_warmup"),
                   help="leading frames per window without intent/left/right loss")
    g.add_argument("--loss-warmup-seconds", type=float,
                   default=_default("loss_warmup_seconds"),
                   help="the same in seconds; the larger of the two applies")
    g.add_argument("--model", default="", metavar="K=V,...",
                   help="ModelConfig fields, e.g. 'use_attention=false' (ignored with --init-from)")

    g = parser.add_argument_group("validation")
    g.add_argument("--val-split", type=Path, default=_default("val_split"),
                   help="materialised split to validate on (default: OUT/val_split, "
                        "or held-out bag/UCM tracks)")
    g.add_argument("--val-sequences", type=int, default=_default("val_sequences"),
                   help="size of OUT/val_split when it has to be made")
    g.add_argument("--val-every", type=int, default=_default("val_every"),
                   help="steps between validations")
    g.add_argument("--val-fraction", type=float, default=_default("val_fraction"),
                   help="share of bag/UCM tracks held out for validation")
    g.add_argument("--holdout-fraction", type=float, default=_default("holdout_fraction"),
                   help="with --init-from and --bags/--ucm/--pool: share of the track IDs "
                        "(drawn with --seed) held out of the run; the --init-from model and "
                        "the fine-tuned one are then evaluated on them (OUT/adapt_report.md "
                        "and .json)")
    g.add_argument("--select-by", choices=SELECT_BY, default=_default("select_by"),
                   help="what best.pt is chosen by: 'frames', the validation windows' "
                        "per-frame argmax, or 'published', whole validation tracks (from "
                        "--val-fraction of --bags/--pool) scored through the node's intent "
                        "filter as the before/after report scores them")
    g.add_argument("--patience", type=int, default=_default("plateau_patience"),
                   help="validations without improvement before the LR drops")
    g.add_argument("--anneal-fraction", type=float,
                   default=_default("anneal_fraction"),
                   help="final share of the budget (--max-minutes or --steps) over which the "
                        "LR decays along a cosine to its minimum, on top of the plateau "
                        "schedule (0: off)")


def options_from_args(args: argparse.Namespace) -> TrainOptions:
    """Turn parsed arguments into :class:`TrainOptions`.

    ``--task-weights`` changes the default weights of the heads it names; the ``--no-*``
    flags switch off what is on by default.
    """
    task_weights = _default("task_weights")
    task_weights.update({k: float(v) for k, v in
                         _key_values(args.task_weights, "--task-weights").items()})
    resume = None
    if args.resume is not None:
        resume = Path(args.resume) if args.resume else args.out / "last.pt"
    return TrainOptions(
        out=args.out, max_steps=args.steps, max_minutes=args.max_minutes, batch=args.batch,
        seq_len=args.seq_len, lr=args.lr, weight_decay=args.weight_decay,
        task_weights=task_weights, class_weight_power=args.class_weight_power,
        balance=not args.no_balance, balance_max_drop=args.balance_drop, reuse=args.reuse,
        loss_warmup=args.loss_warmup, loss_warmup_seconds=args.loss_warmup_seconds,
        val_split=args.val_split,
        val_sequences=args.val_sequences, val_every=args.val_every,
        val_fraction=args.val_fraction, holdout_fraction=args.holdout_fraction,
        select_by=args.select_by, plateau_patience=args.patience,
        anneal_fraction=args.anneal_fraction, device=args.device,
        precision=args.precision,
        seed=args.seed, threads=args.threads, workers=args.workers, resume=resume,
        init_from=Path(args.init_from) if args.init_from else None,
        freeze_encoder=args.freeze_encoder, freeze_norms=args.freeze_norms,
        heads_only=args.heads_only, trunk_from=args.train_trunk_from,
        trunk_norms=args.train_trunk_norms,
        head_tasks=tuple(args.head_tasks),
        grown_init_scale=args.grown_init_scale, bags=list(args.bags),
        ucm=list(args.ucm), pools=list(args.pools), rehearse=list(args.rehearse),
        rehearse_share=args.rehearse_share, mode=args.mode,
        frame_targets=args.frame_targets,
        lit_map_weight=args.lit_map_weight,
        synthetic_fraction=args.synthetic_fraction,
        mirror_prob=0.0 if args.no_mirror else _default("mirror_prob"),
        jitter=not args.no_jitter,
        camera_response=args.camera_response, shape_warp=args.shape_warp,
        model=_key_values(args.model, "--model"), stream=_key_values(args.stream, "--stream"),
        progress=not args.no_progress)


def run(args: argparse.Namespace) -> int:
    """Train; prints a JSON summary (rank 0 only under torchrun) and, with
    ``--holdout-fraction``, the before/after report."""
    from signal_light_node.training.loop import train  # imports torch: only when training

    opts = options_from_args(args)
    summary = train(opts)
    import os

    if int(os.environ.get("RANK", "0")) == 0:
        print(json.dumps(summary, indent=2))
        if summary.get("adapt_report"):
            print(Path(summary["adapt_report"]).read_text())
    return 0
