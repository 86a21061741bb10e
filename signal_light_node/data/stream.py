"""An endless stream of per-track crop sequences rendered on the fly.

Each scene is rendered once for a few more frames than one sequence needs; every
vehicle the simulated tracker reports is cropped from its *tracker* box with the
node's crop code (``signal_light_node.runtime.crops``), and each track's observations are cut
into windows of ``seq_len`` consecutive observations. A frame in which the tracker
misses a vehicle, or its box cannot be cropped, is left out of that track's sequence,
exactly as the node never sees it. One render thus serves several sequences.

Use it with ``DataLoader(stream, batch_size=B, collate_fn=collate_sequences,
num_workers=N, multiprocessing_context="spawn")``: a worker *forked* from a process that
has used OpenCV's thread pool can deadlock in it.

Items are dicts of numpy arrays (``collate_sequences`` turns a batch into tensors)::

    crops   uint8 [T, S, S, 3]  BGR crops
    labels  int64 [T, 5]        per-frame labels in ``labels.TASKS`` order, PAD_LABEL where mask is False
    lit_labels int64 [T, 5]     the same as the single frame shows it: a blinker is ON only in
                                the lit half of a blink and the intent follows (per-frame
                                pre-training targets; ``labels`` holds the logical states)
    lit_maps uint8 [T, M, M, 3] only from a stream with ``lit_maps``: where the vehicle's own
                                brake, left and right lamps are lit (``synth.lit_maps``),
                                cut like the crop and shrunk to M = crop size / LIT_MAP_SCALE
    mask    bool  [T]           True for real observations (padding only at the end)
    meta    dict                lighting (str), box_size float32 [T] (sqrt(w*h) of the tracker
                                box), occlusion float32 [T], frame_index int64 [T] (-1 = padding),
                                fps (float), seed (int, the scene's), track_id, kind, lamp_design
                                (str), mirrored (bool)
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple

import cv2
import numpy as np
import torch
from torch.utils.data import IterableDataset, get_worker_info

from signal_light_node.runtime.crops import CropConfig, crop_vehicles
from signal_light_node.errors import ConfigError
from signal_light_node.labels import TASKS, intent_from_lights, mirror_labels

LOG = logging.getLogger(__name__)

#: Label written where ``mask`` is False; ``torch.nn.CrossEntropyLoss`` ignores it by default.
PAD_LABEL = -100

#: Image sizes a scene is rendered at, and how often each is drawn. Crops of small boxes
#: come out the same at any size, so the large (costly) size is drawn least.
DEFAULT_SIZES: Tuple[Tuple[int, int], ...] = ((640, 360), (960, 540), (1280, 720))
DEFAULT_SIZE_WEIGHTS: Tuple[float, ...] = (0.5, 0.35, 0.15)

#: A lit map is this many times smaller than the crop (16 px for a 64 px crop).
LIT_MAP_SCALE = 4

#: Consecutive scenes without a single sequence after which the options are deemed unusable.
MAX_EMPTY_SCENES = 50

Item = Dict[str, Any]


@dataclass
class _Track:
    """Observations of one track within one rendered scene."""

    crops: List[np.ndarray] = field(default_factory=list)
    labels: List[Tuple[int, ...]] = field(default_factory=list)
    lit_labels: List[Tuple[int, ...]] = field(default_factory=list)
    lit_maps: List[np.ndarray] = field(default_factory=list)
    box_size: List[float] = field(default_factory=list)
    occlusion: List[float] = field(default_factory=list)
    frame_index: List[int] = field(default_factory=list)
    kind: str = ""
    lamp_design: str = ""


def _labels_of(vehicle, lit: bool = False) -> Tuple[int, ...]:
    left, right = (vehicle.left_lit, vehicle.right_lit) if lit else (vehicle.left, vehicle.right)
    values = {"intent": intent_from_lights(left, right) if lit else vehicle.intent,
              "brake": vehicle.brake, "left": left, "right": right, "view": vehicle.view}
    return tuple(int(values[task]) for task in TASKS)


def _mirror_rows(labels: np.ndarray, mask: np.ndarray) -> np.ndarray:
    mirrored_rows = labels.copy()
    for t in np.flatnonzero(mask):
        mirrored = mirror_labels(dict(zip(TASKS, (int(v) for v in labels[t]))))
        mirrored_rows[t] = [mirrored[task] for task in TASKS]
    return mirrored_rows


def mirror_sequence(item: Item) -> Item:
    """Flip every crop of a sequence horizontally and swap its labels to match.

    The vehicle's left becomes its right: blinker labels swap, LEFT/RIGHT intents swap
    and LEFT/RIGHT views swap (``labels.mirror_labels``). Padding rows stay as they are.

    Args:
        item: A sequence item (not modified).

    Returns:
        A new item with ``meta["mirrored"]`` toggled.
    """
    crops = np.ascontiguousarray(item["crops"][:, :, ::-1])
    meta = dict(item["meta"])
    meta["mirrored"] = not meta.get("mirrored", False)
    out = {"crops": crops, "labels": _mirror_rows(item["labels"], item["mask"]),
           "mask": item["mask"].copy(), "meta": meta}
    if "lit_labels" in item:
        out["lit_labels"] = _mirror_rows(item["lit_labels"], item["mask"])
    if "lit_maps" in item:
        # Flipped like the crop; the vehicle's left lamp is now on the right.
        out["lit_maps"] = np.ascontiguousarray(item["lit_maps"][:, :, ::-1][..., [0, 2, 1]])
    return out


def jitter_colours(crops: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Apply one random brightness/contrast/channel-gain/hue change to a whole sequence.

    One affine colour transform per sequence (the same for all its frames, as a camera's
    white balance and exposure change slowly); a single ``cv2.transform`` call.

    Args:
        crops: uint8 ``[T, S, S, 3]`` BGR crops.
        rng: Source of the random parameters.

    Returns:
        New uint8 crops of the same shape.
    """
    contrast = rng.uniform(0.7, 1.3)
    brightness = rng.uniform(-30.0, 30.0)
    gains = rng.uniform(0.9, 1.1, size=3)
    hue = rng.uniform(-0.08, 0.08)
    # A small hue rotation: each channel takes a little of its neighbour (B<-G<-R<-B or back).
    cycle = np.roll(np.eye(3), 1 if hue > 0 else -1, axis=1)
    colour = (1.0 - abs(hue)) * np.eye(3) + abs(hue) * cycle
    matrix = np.diag(gains) @ colour * contrast
    mean = float(crops.mean()) if crops.size else 0.0
    offset = (1.0 - contrast) * mean * gains + brightness
    affine = np.hstack([matrix, offset[:, None]]).astype(np.float32)
    t, s = crops.shape[0], crops.shape[1]
    flat = crops.reshape(t * s, s, 3)
    return cv2.transform(flat, affine).reshape(crops.shape)


class SyntheticSequenceStream(IterableDataset):
    """Infinite ``IterableDataset`` of per-track crop sequences from the scene renderer.

    Every (``seed``, ``rank``, DataLoader worker) triple draws its own deterministic series
    of scenes, so workers and distributed processes never repeat each other's data and a
    run can be reproduced.

    Args:
        seed: Base seed (non-negative).
        seq_len: Observations per sequence (T).
        crop: Crop size and margin, as the node will use them.
        mirror_prob: Probability that a sequence is mirrored (crops flipped, labels swapped).
        jitter: Apply a random colour/brightness change per sequence.
        sizes: ``(width, height)`` choices for the rendered frames.
        size_weights: Probability of each size (default: favour the cheaper sizes).
        vehicles: Inclusive ``(min, max)`` number of vehicles per scene.
        fps: Frame rate of every scene, or None for the renderer's random choice.
        lighting: "day", "dusk", "night", or None for the renderer's random choice.
        night_fraction: Passed to the renderer (share of dark scenes when lighting is None).
        scene_frames: Frames rendered per scene; default ``2 seq_len + max(4, seq_len // 4)``
            (up to two windows per track: a scene's set-up costs about as much as ten
            frames, so longer scenes are cheaper per sequence), or ``seq_len`` with
            ``full_tracks``.
        full_tracks: Emit each track's observations of the whole scene as one item (padded
            to ``seq_len`` with ``mask`` False) instead of windows; for evaluation splits.
        min_observations: Shortest track that is still emitted (padded); default
            ``seq_len`` (windows) or 1 (full tracks).
        rank: Distributed rank; None reads ``torch.distributed`` when it is initialised.
        renderer_overrides: Extra keyword arguments for ``SceneRenderer``.
        lit_maps: Give every item its ``lit_maps`` (see the module docstring).

    Raises:
        ConfigError: If an argument is out of range.
    """

    def __init__(self, seed: int = 0, seq_len: int = 16, crop: CropConfig = CropConfig(), *,
                 mirror_prob: float = 0.5, jitter: bool = False,
                 sizes: Sequence[Tuple[int, int]] = DEFAULT_SIZES,
                 size_weights: Optional[Sequence[float]] = None,
                 vehicles: Tuple[int, int] = (3, 6), fps: Optional[float] = None,
                 lighting: Optional[str] = None, night_fraction: Optional[float] = None,
                 scene_frames: Optional[int] = None, full_tracks: bool = False,
                 min_observations: Optional[int] = None, rank: Optional[int] = None,
                 renderer_overrides: Optional[Dict[str, Any]] = None,
                 lit_maps: bool = False) -> None:
        super().__init__()
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ConfigError(f"seed must be a non-negative integer, got {seed!r}")
        if not isinstance(seq_len, (int, np.integer)) or seq_len < 1:
            raise ConfigError(f"seq_len must be a positive integer, got {seq_len!r}")
        if not isinstance(crop, CropConfig):
            raise ConfigError(f"crop must be a CropConfig, got {type(crop).__name__}")
        if not 0.0 <= float(mirror_prob) <= 1.0:
            raise ConfigError(f"mirror_prob must be in 0..1, got {mirror_prob}")
        sizes = tuple((int(w), int(h)) for w, h in sizes)
        if not sizes or any(w < 32 or h < 32 for w, h in sizes):
            raise ConfigError(f"sizes must be a non-empty list of (width, height) >= 32, got {sizes}")
        if size_weights is None:
            size_weights = DEFAULT_SIZE_WEIGHTS if sizes == DEFAULT_SIZES else [1.0] * len(sizes)
        weights = np.asarray(size_weights, dtype=float)
        if weights.shape != (len(sizes),) or (weights < 0).any() or weights.sum() <= 0:
            raise ConfigError(f"size_weights must give one non-negative weight per size, "
                              f"got {size_weights} for {len(sizes)} sizes")
        lo, hi = (int(v) for v in vehicles)
        if not 1 <= lo <= hi:
            raise ConfigError(f"vehicles must be (min, max) with 1 <= min <= max, got {vehicles}")
        frames = scene_frames if scene_frames is not None else (
            seq_len if full_tracks else 2 * seq_len + max(4, seq_len // 4))
        if int(frames) < 1:
            raise ConfigError(f"scene_frames must be positive, got {scene_frames}")
        min_obs = min_observations if min_observations is not None else (
            1 if full_tracks else seq_len)
        if not 1 <= int(min_obs) <= seq_len:
            raise ConfigError(f"min_observations must be in 1..seq_len ({seq_len}), got {min_obs}")
        if int(min_obs) > int(frames):
            raise ConfigError(f"scenes of {frames} frames can never give {min_obs} observations "
                              "of a track; raise scene_frames or lower min_observations")
        if rank is not None and int(rank) < 0:
            raise ConfigError(f"rank must be non-negative, got {rank}")
        self.seed = int(seed)
        self.seq_len = int(seq_len)
        self.crop = crop
        self.mirror_prob = float(mirror_prob)
        self.jitter = bool(jitter)
        self.sizes = sizes
        self.size_weights = weights / weights.sum()
        self.vehicles = (lo, hi)
        self.fps = fps
        self.lighting = lighting
        self.night_fraction = night_fraction
        self.scene_frames = int(frames)
        self.full_tracks = bool(full_tracks)
        self.min_observations = int(min_obs)
        self.rank = rank
        self.renderer_overrides = dict(renderer_overrides or {})
        self.lit_maps = bool(lit_maps)

    def __iter__(self) -> Iterator[Item]:
        info = get_worker_info()
        if info is None:
            return self.sequences(worker_id=0)
        # Inside a DataLoader worker: one OpenCV thread, as torch does for itself, so that
        # the workers do not oversubscribe the cores.
        cv2.setNumThreads(1)
        return self.sequences(worker_id=info.id)

    def _resolve_rank(self) -> int:
        if self.rank is not None:
            return int(self.rank)
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            return int(torch.distributed.get_rank())
        return 0

    def sequences(self, worker_id: int = 0) -> Iterator[Item]:
        """The endless series of items that DataLoader worker ``worker_id`` yields.

        Args:
            worker_id: The worker's index (0 without workers).

        Yields:
            Sequence items (see the module docstring).
        """
        rng = np.random.default_rng(np.random.SeedSequence(
            [self.seed, self._resolve_rank(), int(worker_id)]))
        empty = 0
        while True:
            scene_seed = int(rng.integers(0, 2**31 - 1))
            items = self.scene_sequences(scene_seed, rng)
            empty = 0 if items else empty + 1
            if empty == MAX_EMPTY_SCENES:
                raise ConfigError(f"{empty} scenes in a row gave no track with "
                                  f"{self.min_observations} observations; raise scene_frames "
                                  "or vehicles, or lower min_observations")
            for item in items:
                if self.mirror_prob > 0 and rng.random() < self.mirror_prob:
                    item = mirror_sequence(item)
                if self.jitter:
                    crops = jitter_colours(item["crops"], rng)
                    crops[~item["mask"]] = 0
                    item["crops"] = crops
                yield item

    def scene_sequences(self, scene_seed: int, rng: np.random.Generator) -> List[Item]:
        """Render one scene and cut its tracks into (unaugmented) sequence items.

        Args:
            scene_seed: The renderer's seed.
            rng: Draws the image size, the vehicle count and the window offsets.

        Returns:
            The scene's items, in order of each track's first appearance.
        """
        from signal_light_node.synth import SceneRenderer  # heavy; only when rendering

        width, height = self.sizes[int(rng.choice(len(self.sizes), p=self.size_weights))]
        n_vehicles = int(rng.integers(self.vehicles[0], self.vehicles[1] + 1))
        options = dict(self.renderer_overrides)
        if self.night_fraction is not None:  # else the renderer's default share
            options["night_fraction"] = self.night_fraction
        renderer = SceneRenderer(scene_seed, width=width, height=height, fps=self.fps,
                                 n_vehicles=n_vehicles, lighting=self.lighting,
                                 lit_maps=self.lit_maps, **options)
        tracks: Dict[str, _Track] = {}
        lighting = None
        for frame in renderer.frames(self.scene_frames):
            lighting = lighting or frame.lighting
            seen = [v for v in frame.vehicles if v.tracker_box is not None]
            if not seen:
                continue
            crops, reasons = crop_vehicles(frame.image, [v.tracker_box for v in seen], self.crop)
            maps = self._lit_maps(frame.image.shape, seen) if self.lit_maps else None
            for k, (vehicle, crop, reason) in enumerate(zip(seen, crops, reasons)):
                if reason is not None:
                    continue  # the node could not judge this frame of the track either
                track = tracks.setdefault(vehicle.track_id, _Track(
                    kind=vehicle.kind, lamp_design=vehicle.lamp_design))
                box = vehicle.tracker_box
                track.crops.append(crop)
                track.labels.append(_labels_of(vehicle))
                track.lit_labels.append(_labels_of(vehicle, lit=True))
                if maps is not None:
                    track.lit_maps.append(maps[k])
                track.box_size.append(math.sqrt(box.width * box.height))
                track.occlusion.append(float(vehicle.occlusion))
                track.frame_index.append(int(frame.index))
        base_meta = {"lighting": lighting or "", "fps": float(renderer.fps), "seed": scene_seed}
        items: List[Item] = []
        for track_id, track in tracks.items():
            n = len(track.crops)
            if n < self.min_observations:
                continue
            if self.full_tracks or n < self.seq_len:
                spans = [(0, min(n, self.seq_len))]
            else:
                count = n // self.seq_len
                start = int(rng.integers(0, n - count * self.seq_len + 1))
                spans = [(start + k * self.seq_len, start + (k + 1) * self.seq_len)
                         for k in range(count)]
            for a, b in spans:
                items.append(self._item(track_id, track, a, b, base_meta))
        return items

    def _item(self, track_id: str, track: _Track, a: int, b: int, base_meta: Dict[str, Any]) -> Item:
        t, s, n = self.seq_len, self.crop.size, b - a
        crops = np.zeros((t, s, s, 3), dtype=np.uint8)
        crops[:n] = np.stack(track.crops[a:b])
        labels = np.full((t, len(TASKS)), PAD_LABEL, dtype=np.int64)
        labels[:n] = track.labels[a:b]
        lit_labels = np.full((t, len(TASKS)), PAD_LABEL, dtype=np.int64)
        lit_labels[:n] = track.lit_labels[a:b]
        mask = np.zeros(t, dtype=bool)
        mask[:n] = True
        extra: Item = {}
        if track.lit_maps:
            m = s // LIT_MAP_SCALE
            extra["lit_maps"] = np.zeros((t, m, m, 3), dtype=np.uint8)
            extra["lit_maps"][:n] = np.stack(track.lit_maps[a:b])
        box_size = np.zeros(t, dtype=np.float32)
        box_size[:n] = track.box_size[a:b]
        occlusion = np.zeros(t, dtype=np.float32)
        occlusion[:n] = track.occlusion[a:b]
        frame_index = np.full(t, -1, dtype=np.int64)
        frame_index[:n] = track.frame_index[a:b]
        meta = dict(base_meta, box_size=box_size, occlusion=occlusion, frame_index=frame_index,
                    track_id=track_id, kind=track.kind, lamp_design=track.lamp_design,
                    mirrored=False)
        return {"crops": crops, "labels": labels, "lit_labels": lit_labels, "mask": mask,
                "meta": meta, **extra}

    def _lit_maps(self, shape: Tuple[int, ...], vehicles: Sequence[Any]) -> np.ndarray:
        """Each vehicle's lit map cut from its tracker box like its crop, then shrunk:
        uint8 ``[N, M, M, 3]`` (all zeros where the box cannot be cut)."""
        canvas = np.zeros(shape[:2] + (3,), np.uint8)
        crops = []
        for vehicle in vehicles:
            lit_map = vehicle.lit_map
            h, w = lit_map.image.shape[:2]
            region = canvas[lit_map.y0:lit_map.y0 + h, lit_map.x0:lit_map.x0 + w]
            region[...] = lit_map.image
            crops.append(crop_vehicles(canvas, [vehicle.tracker_box], self.crop)[0][0])
            region[...] = 0
        m = self.crop.size // LIT_MAP_SCALE
        return np.stack([cv2.resize(c, (m, m), interpolation=cv2.INTER_AREA) for c in crops])


def collate_sequences(batch: Sequence[Item]) -> Dict[str, Any]:
    """Stack sequence items into a batch for ``torch.utils.data.DataLoader``.

    Items of different lengths are padded at the end to the longest (mask False,
    labels ``PAD_LABEL``).

    Args:
        batch: Items from the stream or from ``split.SequenceSplit``.

    Returns:
        ``{"crops": uint8 [B,T,S,S,3], "labels": int64 [B,T,5], "mask": bool [B,T],
        "meta": {key: list of the items' values}}`` with torch tensors.

    Raises:
        ConfigError: If the batch is empty or its crops differ in size.
    """
    if not batch:
        raise ConfigError("cannot collate an empty batch")
    length = max(item["crops"].shape[0] for item in batch)
    shapes = {item["crops"].shape[1:] for item in batch}
    if len(shapes) != 1:
        raise ConfigError(f"cannot batch crops of different sizes: {sorted(shapes)}")

    def pad(array: np.ndarray, fill) -> np.ndarray:
        if array.shape[0] == length:
            return array
        widths = [(0, length - array.shape[0])] + [(0, 0)] * (array.ndim - 1)
        return np.pad(array, widths, constant_values=fill)

    crops = np.stack([pad(item["crops"], 0) for item in batch])
    labels = np.stack([pad(np.asarray(item["labels"], dtype=np.int64), PAD_LABEL) for item in batch])
    mask = np.stack([pad(np.asarray(item["mask"], dtype=bool), False) for item in batch])
    meta: Dict[str, List[Any]] = {}
    for item in batch:
        for key, value in item["meta"].items():
            meta.setdefault(key, []).append(value)
    return {"crops": torch.from_numpy(crops), "labels": torch.from_numpy(labels),
            "mask": torch.from_numpy(mask), "meta": meta}
