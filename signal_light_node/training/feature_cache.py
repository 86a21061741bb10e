"""Per-frame features of a frozen trunk, computed once per rendered split and kept on disk.

With the trunk frozen, everything a frame contributes before the track's state comes in
(trunk features and lamp maps, :meth:`TrunkLightNet.frame_features`) is fixed, so the
recurrent part can be trained from scratch over long sequences without running the
trunk again: one pass over a split writes a cache directory

* ``features.npy`` float16 ``[F, C, G, G]`` and ``maps.npy`` float16 ``[F, 6, G, G]``
  for the split's ``F`` frames, track after track;
* ``labels.npy`` / ``lit_labels.npy`` int8 ``[F, 5]``, ``lengths.npy``, ``fps.npy``,
  ``lighting.npy`` per track;
* ``cache.json``: the split it came from, the trunk's config and a hash of its weights,
  the augmentation seed and where the trunk ran (a cache made for other weights is
  refused, not reused).

``augment_seed`` applies one random camera response and shape warp per track
(``data.camera_response``, ``data.shape_warp``) before the trunk sees it, so a pool can be
cached in several looks; ``mirror`` flips every crop horizontally and swaps the labels
with it (``data.stream.mirror_sequence``: the vehicle's left becomes its right), a look of
traffic mirrored.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np
import torch

from signal_light_node.data.camera_response import randomise_camera
from signal_light_node.data.split import SequenceSplit
from signal_light_node.data.shape_warp import warp_sequence
from signal_light_node.data.stream import mirror_sequence
from signal_light_node.errors import ConfigError
from signal_light_node.labels import TASKS
from signal_light_node.model.inference import inference_copy
from signal_light_node.training.trunk_pass import trunk_pass

LOG = logging.getLogger(__name__)
MANIFEST = "cache.json"
#: The large per-frame arrays, memory-mapped on load.
MAPPED = ("features", "maps")


def trunk_fingerprint(model: torch.nn.Module) -> str:
    """Hash of the trunk's weights and the config fields the per-frame part depends on."""
    digest = hashlib.sha256()
    cfg = model.config
    per_frame = [cfg.input_size, cfg.trunk_stride, list(cfg.mean), list(cfg.std)]
    if cfg.lamp_detail != 1:  # the lamp maps' grid; left out at 1 so older caches stay valid
        per_frame.append(cfg.lamp_detail)
    if cfg.lamp_area:  # two more lamp-map channels; left out when off, likewise
        per_frame.append("lamp_area")
    if cfg.feature_grid not in (0, cfg.trunk_side):  # the trunk's map averaged down
        per_frame.append(["feature_grid", cfg.feature_grid])
    digest.update(json.dumps(per_frame).encode())
    for name, value in sorted(model.trunk.state_dict().items()):
        digest.update(name.encode())
        digest.update(value.detach().cpu().numpy().tobytes())
    return digest.hexdigest()[:16]


def split_tracks(split_dir: Path, mirror: bool = False) -> Iterator[Dict[str, Any]]:
    """The whole tracks of a split directory (:class:`~signal_light_node.data.split.SequenceSplit`),
    cut to their real frames: crops, labels, lit labels, frame rate and lighting; with
    ``mirror``, each track flipped left to right with its labels swapped to match."""
    for item in SequenceSplit(split_dir):
        if mirror:
            item = mirror_sequence(item)
        n = int(item["mask"].sum())
        yield {"crops": item["crops"][:n], "labels": item["labels"][:n],
               "lit_labels": item["lit_labels"][:n], "fps": float(item["meta"]["fps"]),
               "lighting": str(item["meta"]["lighting"])}


def write_cache(split_dir: "str | os.PathLike[str]", model: torch.nn.Module,
                out_dir: "str | os.PathLike[str]", augment_seed: Optional[int] = None,
                batch: int = 512, white_balance: float = 0.0, mirror: bool = False,
                backend: str = "torch", threads: int = 1) -> Path:
    """Cache the per-frame features of every track of ``split_dir`` (see the module doc).

    Reuses an existing cache made from the same split, trunk, seed, white balance,
    mirroring and backend. The split must have been cropped as the model crops
    (``ModelConfig.crop_config``).

    Args:
        white_balance: With ``augment_seed``, the random camera's per-channel gain range
            (``CameraResponse.draw``); 0 draws none, as caches made before it.
        mirror: Cache every track mirrored (flipped crops, swapped labels), before any
            augmentation.
        backend: Where the trunk runs (:data:`~.trunk_pass.PASS_BACKENDS`); a cache made
            on another backend is made again, not reused.
        threads: The onnxruntime pass's threads.

    Returns:
        The cache directory.

    Raises:
        ConfigError: The split's crops are not the model's.
    """
    split_dir, out = Path(split_dir), Path(out_dir)
    SequenceSplit(split_dir).require_crop(model.config.crop_config())
    if augment_seed is None:
        white_balance = 0.0  # the clean look draws no camera: one cache whatever is asked
    info = {"split": str(split_dir.resolve()), "trunk": trunk_fingerprint(model),
            "augment_seed": augment_seed, "white_balance": float(white_balance),
            "mirror": bool(mirror), "backend": backend, "config": model.config.to_dict()}
    if _holds(out, info):
        LOG.info("%s: cache exists, reused", out)
        return out
    run = trunk_pass(inference_copy(model.eval()), backend, batch, threads)
    rng = np.random.default_rng(augment_seed) if augment_seed is not None else None
    # Per process: runs that cache the same split side by side each write their own.
    tmp = out.with_name(f"{out.name}.tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    columns: Dict[str, List[Any]] = {k: [] for k in ("features", "maps", "labels", "lit_labels",
                                                      "lengths", "fps", "lighting")}
    for track in split_tracks(split_dir, mirror):
        crops = track["crops"]
        if rng is not None:
            crops = randomise_camera(warp_sequence(crops, rng), rng, white_balance)
        f, m = run(crops)
        columns["features"].append(f)
        columns["maps"].append(m)
        columns["labels"].append(track["labels"].astype(np.int8))
        columns["lit_labels"].append(track["lit_labels"].astype(np.int8))
        columns["lengths"].append(len(crops))
        columns["fps"].append(track["fps"])
        columns["lighting"].append(track["lighting"])
    for key, values in columns.items():
        array = np.concatenate(values) if key in ("features", "maps", "labels", "lit_labels") \
            else np.asarray(values)
        np.save(tmp / f"{key}.npy", array)
    info["frames"] = int(sum(columns["lengths"]))
    info["tracks"] = len(columns["lengths"])
    (tmp / MANIFEST).write_text(json.dumps(info, indent=1))
    _publish(tmp, out, info)
    LOG.info("%s: %d tracks, %d frames cached", out, info["tracks"], info["frames"])
    return out


#: What makes two caches of a split the same (the manifest's keys).
CACHE_KEYS = ("split", "trunk", "augment_seed", "white_balance", "mirror", "backend")


#: The keys' values in caches written before the options existed.
OLD_DEFAULTS = {"white_balance": 0.0, "mirror": False, "backend": "torch"}


def _same_cache(old: Dict[str, Any], info: Dict[str, Any]) -> bool:
    old = dict(OLD_DEFAULTS, **old)
    return all(old.get(k) == info[k] for k in CACHE_KEYS)


def _holds(out: Path, info: Dict[str, Any]) -> bool:
    manifest = out / MANIFEST
    return manifest.is_file() and _same_cache(json.loads(manifest.read_text()), info)


def _publish(tmp: Path, out: Path, info: Dict[str, Any]) -> None:
    """Move a written cache into place; where another process has just put the same cache
    there, keep that one (it may be loading it)."""
    if not _holds(out, info):
        shutil.rmtree(out, ignore_errors=True)  # a stale cache of other inputs
        try:
            os.replace(tmp, out)
            return
        except OSError:
            if not _holds(out, info):
                raise
    shutil.rmtree(tmp, ignore_errors=True)


@dataclass
class FeatureCache:
    """A cache directory in memory: arrays per frame and each track's slice of them."""

    features: np.ndarray
    maps: np.ndarray
    labels: np.ndarray
    lit_labels: np.ndarray
    lengths: np.ndarray
    fps: np.ndarray
    lighting: np.ndarray
    offsets: np.ndarray

    @classmethod
    def load(cls, path: "str | os.PathLike[str]", fingerprint: Optional[str] = None) -> "FeatureCache":
        """Read a cache; ``fingerprint`` (:func:`trunk_fingerprint`) must match if given.

        Raises:
            ConfigError: The directory is not a cache or was made with another trunk.
        """
        path = Path(path)
        if not (path / MANIFEST).is_file():
            raise ConfigError(f"{path} is not a feature cache (no {MANIFEST})")
        info = json.loads((path / MANIFEST).read_text())
        if fingerprint is not None and info.get("trunk") != fingerprint:
            raise ConfigError(f"{path} was cached with another trunk ({info.get('trunk')}, "
                              f"this model's is {fingerprint})")
        # The per-frame arrays are mapped, not read: members trained side by side then
        # share one copy in the page cache (many pools, looks and mirrors add up to GBs).
        arrays = {k: np.load(path / f"{k}.npy", mmap_mode="r" if k in MAPPED else None)
                  for k in ("features", "maps", "labels", "lit_labels", "lengths", "fps",
                            "lighting")}
        offsets = np.concatenate(([0], np.cumsum(arrays["lengths"]))).astype(np.int64)
        return cls(offsets=offsets, **arrays)

    def __len__(self) -> int:
        return len(self.lengths)

    def window(self, track: int, start: int, length: int) -> Dict[str, np.ndarray]:
        """Frames ``start .. start+length`` of one track (fewer at its end)."""
        a = int(self.offsets[track]) + start
        b = min(a + length, int(self.offsets[track + 1]))
        return {"features": self.features[a:b], "maps": self.maps[a:b],
                "labels": self.labels[a:b], "lit_labels": self.lit_labels[a:b]}


def collate_windows(rows: Sequence[Tuple[Dict[str, np.ndarray], float]], seq_len: int
                    ) -> Dict[str, torch.Tensor]:
    """Windows ``(arrays, fps)`` as float tensors ``[B, T, ...]`` padded to ``seq_len``,
    with labels (-1 in the padding), a frame mask and each window's frame rate."""
    first = rows[0][0]
    n = len(rows)
    feats = np.zeros((n, seq_len) + first["features"].shape[1:], np.float32)
    maps = np.zeros((n, seq_len) + first["maps"].shape[1:], np.float32)
    labels = np.full((n, seq_len, len(TASKS)), -1, np.int64)
    lit = np.full((n, seq_len, len(TASKS)), -1, np.int64)
    mask = np.zeros((n, seq_len), bool)
    for i, (w, _) in enumerate(rows):
        t = len(w["labels"])
        feats[i, :t], maps[i, :t], labels[i, :t] = w["features"], w["maps"], w["labels"]
        lit[i, :t] = w["lit_labels"]
        mask[i, :t] = True
    return {"features": torch.from_numpy(feats), "maps": torch.from_numpy(maps),
            "labels": torch.from_numpy(labels), "lit_labels": torch.from_numpy(lit),
            "mask": torch.from_numpy(mask),
            "fps": torch.tensor([fps for _, fps in rows], dtype=torch.float64)}


@torch.no_grad()
def track_logits(model: torch.nn.Module, cache: FeatureCache, batch: int = 64
                 ) -> Dict[str, Tuple[np.ndarray, np.ndarray]]:
    """Per task ``(logits [M, K], labels [M])`` of every track stepped from its first
    frame, over the labelled frames after the evaluation's warm-up (1 s, >= 10 frames)."""
    model.eval()
    device = next(model.parameters()).device
    out: Dict[str, List[Tuple[np.ndarray, np.ndarray]]] = {t: [] for t in TASKS}
    for start in range(0, len(cache), batch):
        tracks = range(start, min(start + batch, len(cache)))
        rows = [(cache.window(i, 0, int(cache.lengths[i])), float(cache.fps[i])) for i in tracks]
        b = collate_windows(rows, max(int(cache.lengths[i]) for i in tracks))
        logits, _ = model.sequence_features(b["features"].to(device), b["maps"].to(device))
        collect_scored(out, {k: v.cpu() for k, v in logits.items()}, b)
    return {t: (np.concatenate([a for a, _ in v]), np.concatenate([y for _, y in v]))
            for t, v in out.items()}


def collect_scored(out: Dict[str, List[Tuple[np.ndarray, np.ndarray]]],
                   logits: Dict[str, torch.Tensor], batch: Dict[str, torch.Tensor]) -> None:
    """Append per task the ``(logits, labels)`` of a batch's labelled frames past the
    evaluation's warm-up (1 s of the track, at least 10 frames)."""
    warm = torch.clamp(torch.ceil(batch["fps"]), min=10).to(torch.int64)
    scored = batch["mask"] & (torch.arange(batch["mask"].shape[1])[None] >= warm[:, None])
    for i, task in enumerate(TASKS):
        y = batch["labels"][..., i]
        keep = scored & (y >= 0)
        out[task].append((logits[task][keep].numpy(), y[keep].numpy()))
