"""The track: one vehicle's frames as the model sees them, what evaluation scores and
training draws windows from.

:class:`TrackSequence` holds one vehicle track: its crops (in memory, or image files
cropped on demand with :func:`signal_light_node.runtime.crops.crop_vehicle`, the one crop
code), one label row per frame in ``labels.TASKS`` order, a mask of the frames that have
a crop, the stamps, and what the evaluation groups by (lighting, box size, occlusion).
:func:`track_from_item` makes one from a stream or split item (``crops``, ``labels``,
``mask``, ``meta``). The sources that produce tracks (bags, UC Merced, materialised
splits) live in :mod:`signal_light_node.training.sources`; this module sits below both
training and evaluation so that either can use the type without the other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, List, Mapping, Optional

import cv2
import numpy as np

from signal_light_node.boxes import TrackBox
from signal_light_node.errors import ConfigError, CropError
from signal_light_node.runtime.crops import CropConfig, crop_vehicle


@dataclass
class TrackSequence:
    """One vehicle track as the model sees it.

    Attributes:
        track_id: Unique name of the track within its source.
        labels: int64 ``[T, len(TASKS)]`` ground truth per frame (negative = not labelled).
        mask: bool ``[T]``; False for frames without a usable crop (never stepped).
        stamps_ns: int64 ``[T]`` frame times.
        box_size: float ``[T]`` box size ``sqrt(width * height)`` in pixels (NaN if unknown).
        occlusion: float ``[T]`` hidden fraction 0..1 (NaN if unknown).
        lighting: "day", "dusk", "night" or "unknown".
        source: Where the track came from (for reports).
        crops: uint8 ``[T, S, S, 3]`` when held in memory, else None.
        frame_paths: Image files cropped on demand when ``crops`` is None.
        crop_config: Crop settings for ``frame_paths``.
        lit_maps: uint8 ``[T, M, M, 3]`` where the vehicle's lamps are lit (rendered
            training tracks with lit maps only; ``data.stream``), else None.
        cover: float ``[T]`` share of the box outside the image or behind a nearer box
            (``runtime.box_sight.box_cover``, what the node can tell from the frame's
            boxes; NaN where not known), or None: tracks read from bags have it, splits
            keep no other boxes.
        scene: The scene the track was recorded in (a split's scene seed, a bag's name);
            tracks of one scene share its camera and light, so confidence intervals
            resample scenes (``evaluation.bootstrap``). Empty: not known.
    """

    track_id: str
    labels: np.ndarray
    mask: np.ndarray
    stamps_ns: np.ndarray
    box_size: np.ndarray
    occlusion: np.ndarray
    lighting: str = "unknown"
    source: str = ""
    crops: Optional[np.ndarray] = None
    frame_paths: Optional[List[Path]] = None
    crop_config: CropConfig = field(default_factory=CropConfig)
    lit_maps: Optional[np.ndarray] = None
    cover: Optional[np.ndarray] = None
    scene: str = ""

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    @property
    def fps(self) -> float:
        """Frame rate from the stamps (10 Hz when fewer than two frames)."""
        if len(self) < 2:
            return 10.0
        span = float(self.stamps_ns[-1] - self.stamps_ns[0]) / 1e9
        return (len(self) - 1) / span if span > 0 else 10.0

    def crop_window(self, start: int, stop: int) -> np.ndarray:
        """Crops of frames ``start..stop-1`` as uint8 ``[n, S, S, 3]``.

        Raises:
            ConfigError: The window is outside the track.
            CropError: A lazily read frame cannot be read.
        """
        if not 0 <= start <= stop <= len(self):
            raise ConfigError(f"window {start}..{stop} outside track {self.track_id} "
                              f"of {len(self)} frames")
        if self.crops is not None:
            return self.crops[start:stop]
        if self.frame_paths is None:
            raise ConfigError(f"track {self.track_id} has neither crops nor frame paths")
        return np.stack([_read_full_image_crop(p, self.crop_config)
                         for p in self.frame_paths[start:stop]]) if stop > start else \
            np.zeros((0, self.crop_config.size, self.crop_config.size, 3), np.uint8)


def _read_full_image_crop(path: Path, config: CropConfig) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise CropError(f"cannot read image {path}")
    h, w = image.shape[:2]
    return crop_vehicle(image, TrackBox(path.name, 0.0, 0.0, float(w), float(h)), config)


def item_labels(item: Mapping[str, Any], label_key: str, name: str) -> np.ndarray:
    """An item's ``label_key`` array (``"labels"`` or ``"lit_labels"``) as int64.

    Args:
        item: A stream or split item.
        label_key: Which label array.
        name: What the item is, for the message.

    Raises:
        ConfigError: The item has no such array (a split written before it existed).
    """
    if label_key not in item:
        raise ConfigError(f"{name} has no {label_key!r}: a split rendered before they were "
                          "written; render it again")
    return np.asarray(item[label_key], dtype=np.int64)


def track_from_item(item: Mapping[str, Any], track_id: str, source: str = "synthetic",
                    label_key: str = "labels") -> TrackSequence:
    """A :class:`TrackSequence` from a stream/split item (``crops``, ``labels``, ``mask``, ``meta``).

    Args:
        item: The item.
        track_id: Name used when the item's meta has no ``track_id``.
        source: Where the item came from (for reports).
        label_key: Which of the item's label arrays becomes the track's labels:
            ``"labels"`` (logical light states) or ``"lit_labels"`` (what each single
            frame shows; see ``data.stream``).

    Raises:
        ConfigError: The item has no ``label_key`` array.
    """
    labels = item_labels(item, label_key, f"track {track_id}")
    crops = np.asarray(item["crops"])
    n = labels.shape[0]
    mask = np.asarray(item.get("mask", np.ones(n, bool)), dtype=bool)
    meta = dict(item.get("meta") or {})
    fps = float(meta.get("fps") or 10.0)
    # Frames the tracker missed are left out of a sequence, so time comes from the
    # frame index (padding has -1 and continues at the frame rate).
    index = np.asarray(meta.get("frame_index", np.arange(n)), dtype=np.int64).reshape(-1)
    if index.shape[0] != n:
        index = np.arange(n)
    valid = index >= 0
    if not valid.all():
        last = int(index[valid].max()) if valid.any() else -1
        index = index.copy()
        index[~valid] = last + 1 + np.arange(int((~valid).sum()))
    stamps = np.round(index * (1e9 / fps)).astype(np.int64)

    def per_frame(key: str) -> np.ndarray:
        value = meta.get(key)
        if value is None:
            return np.full(n, math.nan)
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
        return np.full(n, float(arr[0])) if arr.size == 1 else arr

    return TrackSequence(track_id=str(meta.get("track_id", track_id)), labels=labels, mask=mask,
                         stamps_ns=stamps, box_size=per_frame("box_size"),
                         occlusion=per_frame("occlusion"),
                         lighting=str(meta.get("lighting", "unknown")),
                         source=source, crops=crops, lit_maps=item.get("lit_maps"),
                         scene=str(meta.get("seed", "")))
