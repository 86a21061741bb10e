"""Data sources other than the live synthetic stream, as per-track sequences.

Every source is turned into :class:`~signal_light_node.evaluation.tracks.TrackSequence`
objects (the type lives below training and evaluation, in ``evaluation.tracks``): one
vehicle track, its crops (cut with :func:`signal_light_node.runtime.crops.crop_vehicle`,
the one crop code), one label row per frame in ``labels.TASKS`` order, and what the
evaluation groups by (lighting, box size, occlusion). Training draws windows from them
with :class:`WindowDataset`; evaluation streams them frame by frame.

Sources:

* **Labelled bags** (:func:`load_bag_tracks`): images (raw or compressed), tracked
  detections (``vision_msgs/Detection2DArray``) and ground truth on
  ``/ground_truth/vehicle_lights`` (``signal_light_msgs/VehicleLightStateArray``). Images
  and detections are paired as the node pairs them (:mod:`signal_light_node.runtime.pairing`,
  exact stamps unless a slop is given), the ground truth by the image's stamp. A vehicle is
  used in a frame when the frame has its detection (the box the engine would crop) and
  its ground-truth entry (same track ID).
* **Unlabelled bags** (:func:`load_unlabelled_bag_tracks`, for ``signal-light adapt``):
  the same reader without the ground truth: every paired frame, every box, labels
  ``PAD_LABEL``.
* **UC Merced Vehicle Rear Signal layout** (:func:`load_ucm_tracks`):
  ``<footage>/<footage>_<XXX>/<footage>_<XXX>_<start>/light_mask/frameNNNNNNNN.png``
  with XXX in OOO, BOO, OLO, BLO, OOR, BOR, OLR, BLR (B brake, L left, R right, O off).
  Every image is already a crop of one vehicle seen from behind, so the whole image is
  the box; the label holds for the whole sequence. Frames are read lazily.
* **Materialised synthetic splits** (:func:`split_tracks`): items of
  :class:`signal_light_node.data.split.SequenceSplit`.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import cv2
import numpy as np
import torch

from signal_light_node.evaluation.tracks import TrackSequence, track_from_item
from signal_light_node.runtime.box_sight import box_cover, boxes_array
from signal_light_node.runtime.crops import CropConfig, crop_vehicle
from signal_light_node.runtime.pairing import (DETECTIONS, IMAGE, OrderedPairing, PairingConfig,
                                               pair_in_order)
from signal_light_node.data.stream import PAD_LABEL
from signal_light_node.errors import BagIOError, ConfigError, CropError
from signal_light_node.labels import TASKS, LightStatus, View, intent_from_lights
from signal_light_node.io.topics import (DETECTIONS_TYPE, GROUND_TRUTH_TOPIC, IMAGE_TYPES,
                                      VEHICLE_LIGHTS_TYPE)

logger = logging.getLogger(__name__)

#: The eight UCM sequence codes: (brake, left, right) letters, O = off.
UCM_CODES = ("OOO", "BOO", "OLO", "BLO", "OOR", "BOR", "OLR", "BLR")
_UCM_FRAME = re.compile(r"^frame(\d+)\.png$", re.IGNORECASE)


# ------------------------------------------------------------------------------- UCM


def ucm_labels(code: str) -> np.ndarray:
    """Label row (``TASKS`` order) of a UCM sequence code such as ``"BLO"``.

    Raises:
        ConfigError: ``code`` is not one of :data:`UCM_CODES`.
    """
    code = code.upper()
    if code not in UCM_CODES:
        raise ConfigError(f"unknown UCM sequence code {code!r}; expected one of {UCM_CODES}")
    on, off = int(LightStatus.ON), int(LightStatus.OFF)
    brake = on if code[0] == "B" else off
    left = on if code[1] == "L" else off
    right = on if code[2] == "R" else off
    row = {"intent": int(intent_from_lights(left, right)), "brake": brake, "left": left,
           "right": right, "view": int(View.BEHIND)}
    return np.array([row[t] for t in TASKS], dtype=np.int64)


def find_ucm_sequences(root: Path) -> List[Tuple[str, Path]]:
    """``(code, light_mask dir)`` of every sequence under a UCM root, sorted by path.

    Raises:
        ConfigError: ``root`` is not a directory or holds no sequence in the layout.
    """
    root = Path(root)
    if not root.is_dir():
        raise ConfigError(f"UCM root {root} is not a directory")
    found = []
    for mask_dir in sorted(root.glob("*/*/*/light_mask")):
        seq_dir, code_dir, footage_dir = mask_dir.parent, mask_dir.parent.parent, \
            mask_dir.parent.parent.parent
        prefix = footage_dir.name + "_"
        if not code_dir.name.startswith(prefix):
            continue
        code = code_dir.name[len(prefix):].upper()
        if code not in UCM_CODES or not seq_dir.name.startswith(code_dir.name + "_"):
            logger.debug("skipping %s: not in the UCM layout", mask_dir)
            continue
        found.append((code, mask_dir))
    if not found:
        raise ConfigError(f"no sequence in the UCM layout "
                          f"<footage>/<footage>_<XXX>/<footage>_<XXX>_<start>/light_mask under {root}")
    return found


def load_ucm_tracks(root: Path, crop_config: CropConfig = CropConfig(), fps: float = 15.0
                    ) -> List[TrackSequence]:
    """One lazily read track per UCM sequence.

    Args:
        root: Directory holding the ``<footage>`` folders.
        crop_config: Crop settings of the model (the whole image is the box).
        fps: Frame rate assumed for the stamps.

    Returns:
        Tracks in path order, labelled as a whole by their sequence code, view BEHIND,
        lighting and occlusion unknown, box size ``sqrt(w * h)`` of the image.
    """
    tracks = []
    for code, mask_dir in find_ucm_sequences(root):
        frames = []
        for p in mask_dir.iterdir():
            m = _UCM_FRAME.match(p.name)
            if m:
                frames.append((int(m.group(1)), p))
        if not frames:
            logger.warning("UCM sequence %s has no frameNNNNNNNN.png files; skipped", mask_dir)
            continue
        frames.sort()
        paths = [p for _, p in frames]
        n = len(paths)
        first = cv2.imread(str(paths[0]), cv2.IMREAD_UNCHANGED)
        if first is None:
            raise CropError(f"cannot read image {paths[0]}")
        size = math.sqrt(float(first.shape[0] * first.shape[1]))
        numbers = np.array([k for k, _ in frames], dtype=np.int64)
        stamps = ((numbers - numbers[0]) * (1e9 / fps)).astype(np.int64)
        tracks.append(TrackSequence(
            track_id=str(mask_dir.parent.relative_to(root)),
            labels=np.tile(ucm_labels(code), (n, 1)),
            mask=np.ones(n, bool),
            stamps_ns=stamps,
            box_size=np.full(n, size),
            occlusion=np.full(n, math.nan),
            lighting="unknown",
            source=f"ucm:{code}",
            frame_paths=paths,
            crop_config=crop_config,
        ))
    logger.info("UCM %s: %d sequences, %d frames", root, len(tracks), sum(len(t) for t in tracks))
    return tracks


# ------------------------------------------------------------------------------- bags


def load_bag_tracks(path: Path, crop_config: CropConfig = CropConfig(),
                    image_topic: Optional[str] = None, detection_topic: Optional[str] = None,
                    ground_truth_topic: str = GROUND_TRUTH_TOPIC,
                    lighting: str = "unknown",
                    pairing: PairingConfig = PairingConfig()) -> List[TrackSequence]:
    """Per-track sequences of a bag with ground truth.

    Images and detections are paired exactly as the node pairs them (the same
    :class:`~signal_light_node.runtime.pairing.StampPairer`, fed in log-time order); the
    ground truth is matched by the image's stamp. A frame is used when its image has
    both. Within one frame, a track is used when both its detection and its ground-truth
    entry exist; a box that cannot be cropped gives a masked frame (never stepped, never
    scored), as in the engine.

    Args:
        path: The bag.
        crop_config: Crop settings of the model.
        image_topic: Image topic (default: chosen by :func:`bagio.find_topic`, the first
            CompressedImage topic, else the first Image topic).
        detection_topic: Detection topic (default: the first Detection2DArray topic).
        ground_truth_topic: Ground-truth topic (a ``VehicleLightStateArray``).
        lighting: Lighting written into the tracks (bags do not say).
        pairing: How images and detections are paired (default: the node's defaults,
            exact stamps).

    Returns:
        Tracks sorted by track ID; frames of a track in stamp order.

    Raises:
        BagIOError: The bag cannot be read, lacks one of the three topics, a named
            topic has another type, or no frame has all three.
    """
    return _read_bag_tracks(path, crop_config, (image_topic, detection_topic,
                                                ground_truth_topic), lighting, pairing)


def load_unlabelled_bag_tracks(path: Path, crop_config: CropConfig = CropConfig(),
                               image_topic: Optional[str] = None,
                               detection_topic: Optional[str] = None,
                               lighting: str = "unknown",
                               pairing: PairingConfig = PairingConfig()) -> List[TrackSequence]:
    """Per-track sequences of a bag without ground truth (a user's plain recording).

    The same pairing and crops as :func:`load_bag_tracks` (one shared reader), but every
    paired frame is used and every detection in it; a ground-truth topic, if the bag has
    one, is not read. The tracks' labels are all ``PAD_LABEL`` (not labelled).

    Args:
        path: The bag.
        crop_config: Crop settings of the model.
        image_topic: Image topic (default: as :func:`load_bag_tracks`).
        detection_topic: Detection topic (default: the first Detection2DArray topic).
        lighting: Lighting written into the tracks.
        pairing: How images and detections are paired.

    Returns:
        Tracks sorted by track ID; frames of a track in stamp order.

    Raises:
        BagIOError: The bag cannot be read, lacks an image or detection topic, a named
            topic has another type, or no image has detections with its stamp.
    """
    return _read_bag_tracks(path, crop_config, (image_topic, detection_topic, None),
                            lighting, pairing)


def _read_bag_tracks(path: Path, crop_config: CropConfig,
                     topics_wanted: Tuple[Optional[str], Optional[str], Optional[str]],
                     lighting: str, pairing: PairingConfig) -> List[TrackSequence]:
    """The reader of :func:`load_bag_tracks` (ground-truth topic given) and
    :func:`load_unlabelled_bag_tracks` (ground-truth topic None: every paired box, no
    labels); ``topics_wanted`` is ``(image, detections, ground truth)``."""
    from signal_light_node.io.bagio import find_topic, open_bag
    from signal_light_node.io.conversions import detections_to_boxes, stamp_to_ns
    from signal_light_node.outputs.vehicle_lights import truth_row
    from signal_light_node.io.image_codec import msg_to_bgr

    path = Path(path)
    image_topic, detection_topic, ground_truth_topic = topics_wanted
    labelled = ground_truth_topic is not None
    unlabelled_row = np.full(len(TASKS), PAD_LABEL, np.int64)
    per_track: Dict[str, Dict[str, list]] = {}
    ordered = OrderedPairing(pairing)
    no_truth = 0
    with open_bag(path) as bag:
        topics = bag.topics()
        img_t = find_topic(topics, IMAGE_TYPES, image_topic, "image", path)
        det_t = find_topic(topics, (DETECTIONS_TYPE,), detection_topic, "detection", path)
        ground_truth: Dict[int, Any] = {}
        if labelled:
            gt_t = find_topic(topics, (VEHICLE_LIGHTS_TYPE,), ground_truth_topic,
                              "ground truth", path)
            for m in bag.messages([gt_t]):
                ground_truth.setdefault(stamp_to_ns(m.msg.header.stamp), m.msg)
        arrivals = ((IMAGE if m.topic == img_t else DETECTIONS, stamp_to_ns(m.msg.header.stamp),
                     m.msg, m.log_time_ns) for m in bag.messages([img_t, det_t]))
        for frame in pair_in_order(arrivals, ordered):
            gt_msg = ground_truth.get(frame.stamp_ns)
            if not frame.paired or (labelled and gt_msg is None):
                no_truth += frame.paired
                continue
            stamp = frame.stamp_ns
            image = msg_to_bgr(frame.image, img_t, stamp)
            truth = {str(v.track_id): v for v in gt_msg.vehicles} if labelled else {}
            boxes = detections_to_boxes(frame.detections)
            covers = box_cover(boxes_array(boxes), image.shape[1], image.shape[0])
            for box, cover in zip(boxes, covers):
                gt = truth.get(box.track_id)
                if labelled and gt is None:
                    continue
                rec = per_track.setdefault(box.track_id, {k: [] for k in (
                    "stamp", "crop", "label", "size", "ok", "cover")})
                try:
                    crop = crop_vehicle(image, box, crop_config)
                    ok = True
                except CropError:
                    crop = np.zeros((crop_config.size, crop_config.size, 3), np.uint8)
                    ok = False
                rec["stamp"].append(stamp)
                rec["crop"].append(crop)
                rec["label"].append(truth_row(gt) if labelled else unlabelled_row)
                size = math.sqrt(max(box.width, 0.0) * max(box.height, 0.0))
                rec["size"].append(float(size) if math.isfinite(size) else math.nan)
                rec["ok"].append(ok)
                rec["cover"].append(cover)
    counters = ordered.counters
    unpaired = counters["images"] - counters["paired"]
    if unpaired or no_truth or ordered.unpaired_detections:
        logger.info("bag %s (pairing: %s): %d images without detections, %d detection "
                    "messages without an image, %d paired frames without ground truth", path,
                    ordered.config.describe(), unpaired, ordered.unpaired_detections, no_truth)
    tracks = []
    for track_id in sorted(per_track):
        rec = per_track[track_id]
        order = np.argsort(np.asarray(rec["stamp"]), kind="stable")
        n = len(order)
        tracks.append(TrackSequence(
            track_id=f"{path.name}:{track_id}",
            labels=np.stack(rec["label"])[order],
            mask=np.asarray(rec["ok"], bool)[order],
            stamps_ns=np.asarray(rec["stamp"], np.int64)[order],
            box_size=np.asarray(rec["size"], np.float64)[order],
            occlusion=np.full(n, math.nan),
            lighting=lighting,
            source=f"bag:{path.name}",
            crops=np.stack(rec["crop"])[order],
            crop_config=crop_config,
            cover=np.asarray(rec["cover"], np.float64)[order],
            scene=path.name,
        ))
    if not tracks:
        raise BagIOError(f"bag {path}: no frame has an image, detections"
                         + (" and ground truth with matching stamps and track IDs" if labelled
                            else " with matching stamps and at least one box"))
    logger.info("bag %s: %d tracks, %d frames", path, len(tracks), sum(len(t) for t in tracks))
    return tracks


# ------------------------------------------------------------------------------ splits


def split_tracks(split_dir: Path, crop: Optional[CropConfig] = None,
                 role: str = "split", label_key: str = "labels") -> List[TrackSequence]:
    """Every item of a materialised split as a track.

    Args:
        split_dir: The split's directory.
        crop: The model's crop settings; the split must have been cropped with them.
        role: What the split is used as, for the mismatch message.
        label_key: The items' label array to use (see :func:`track_from_item`).

    Raises:
        ConfigError: The split was cropped with other settings than ``crop``, or lacks
            ``label_key``.
    """
    from signal_light_node.data.split import SequenceSplit

    split = SequenceSplit(split_dir)
    if crop is not None:
        split.require_crop(crop, role)
    return [track_from_item(split[i], f"{Path(split_dir).name}:{i}", "synthetic", label_key)
            for i in range(len(split))]


def is_split_dir(path: Path) -> bool:
    """Whether ``path`` is a materialised split (a directory with the split's manifest)."""
    from signal_light_node.data.split import MANIFEST

    return Path(path).is_dir() and (Path(path) / MANIFEST).is_file()


def paths_cut_with(paths: Sequence[Path], crop: CropConfig) -> List[Path]:
    """The data of ``paths`` a model that crops with ``crop`` reads: every bag (the model
    crops it), and the splits cut with ``crop``. A split's twin cut the other way (the same
    tracks with ``CropConfig.fill`` or without) is left for a model that crops that way.

    Raises:
        ConfigError: No path is a bag and no split was cut with ``crop``.
    """
    from signal_light_node.data.split import SequenceSplit

    chosen = [Path(p) for p in paths if not is_split_dir(Path(p)) or SequenceSplit(p).crop == crop]
    if not chosen:
        raise ConfigError(f"no bag, and no split cut with {crop}, among "
                          f"{', '.join(map(str, paths))}")
    return chosen


def tracks_from(paths: Sequence[Path], crop: CropConfig, role: str,
                bag_tracks: Callable[[Path], List[TrackSequence]]) -> List[TrackSequence]:
    """Every track of the split directories and bags of ``paths``, in the order given.

    Args:
        paths: Materialised splits (:func:`is_split_dir`) and bags.
        crop: The model's crop settings; every split must have been cropped with them.
        role: What the splits are used as, for the mismatch message.
        bag_tracks: Reads one bag (:func:`load_bag_tracks` with labels, or
            :func:`load_unlabelled_bag_tracks`).

    Raises:
        ConfigError: A split was cropped with other settings than ``crop``.
        BagIOError: What ``bag_tracks`` raises.
    """
    tracks: List[TrackSequence] = []
    for path in map(Path, paths):
        tracks += split_tracks(path, crop, role=role) if is_split_dir(path) else bag_tracks(path)
    return tracks


# ----------------------------------------------------------------------------- windows

Augment = Callable[[Dict[str, Any], np.random.Generator], Dict[str, Any]]


class WindowDataset(torch.utils.data.IterableDataset):
    """Infinite stratified windows of length ``seq_len`` from a fixed set of tracks.

    Items have the layout of the synthetic stream (``crops`` uint8 [T,S,S,3], ``labels``
    int64 [T,5], ``mask`` bool [T], ``meta``). Tracks shorter than ``seq_len`` are
    padded with masked frames. Each window is drawn by first choosing a candidate window
    start uniformly per track and then weighting windows by stratum
    (:func:`.sampling.stratum_weights`), so rare strata are seen as often as common ones.

    Args:
        tracks: The tracks.
        seq_len: Window length T.
        seed: Base seed; worker ``w`` of rank ``r`` uses ``seed + 7919 * r + w``.
        augment: Optional ``f(item, rng) -> item`` (mirroring, colour jitter).
        rank: Process rank under DDP.
        stride: Distance between candidate window starts inside a track.
    """

    def __init__(self, tracks: Sequence[TrackSequence], seq_len: int, seed: int = 0,
                 augment: Optional[Augment] = None, rank: int = 0,
                 stride: Optional[int] = None) -> None:
        super().__init__()
        if not tracks:
            raise ConfigError("WindowDataset needs at least one track")
        if seq_len < 1:
            raise ConfigError(f"seq_len must be >= 1, got {seq_len}")
        from signal_light_node.training.sampling import sequence_stratum, stratum_weights

        self.tracks = list(tracks)
        self.seq_len = int(seq_len)
        self.seed = int(seed)
        self.rank = int(rank)
        self.augment = augment
        stride = max(1, int(stride or max(1, seq_len // 2)))
        self.windows: List[Tuple[int, int]] = []
        strata = []
        for ti, track in enumerate(self.tracks):
            last = max(0, len(track) - self.seq_len)
            starts = list(range(0, last + 1, stride))
            if starts[-1] != last:
                starts.append(last)
            for s in starts:
                self.windows.append((ti, s))
                end = min(len(track), s + self.seq_len)
                strata.append(sequence_stratum(track.labels[s:end], track.mask[s:end]))
        self.strata = strata
        self.probabilities = stratum_weights(strata)

    def window(self, index: int) -> Dict[str, Any]:
        """The (unaugmented) window number ``index`` of :attr:`windows`."""
        ti, start = self.windows[index]
        track = self.tracks[ti]
        stop = min(len(track), start + self.seq_len)
        n = stop - start
        crops = track.crop_window(start, stop)
        size = crops.shape[1] if n else track.crop_config.size
        pad = self.seq_len - n
        labels = track.labels[start:stop]
        mask = track.mask[start:stop]
        if pad:
            crops = np.concatenate([crops, np.zeros((pad, size, size, 3), np.uint8)])
            labels = np.concatenate([labels, np.full((pad, labels.shape[1]), PAD_LABEL,
                                                     np.int64)])
            mask = np.concatenate([mask, np.zeros(pad, bool)])
        meta = {"track_id": track.track_id, "source": track.source, "lighting": track.lighting,
                "box_size": np.pad(track.box_size[start:stop], (0, pad),
                                   constant_values=np.nan),
                "occlusion": np.pad(track.occlusion[start:stop], (0, pad),
                                    constant_values=np.nan),
                "fps": track.fps, "start": start, "mirrored": False}
        return {"crops": np.ascontiguousarray(crops), "labels": labels.astype(np.int64),
                "mask": mask.astype(bool), "meta": meta}

    def __iter__(self) -> Iterator[Dict[str, Any]]:
        info = torch.utils.data.get_worker_info()
        worker = info.id if info is not None else 0
        rng = np.random.default_rng(self.seed + 7919 * self.rank + worker)
        while True:
            index = int(rng.choice(len(self.windows), p=self.probabilities))
            item = self.window(index)
            if self.augment is not None:
                item = self.augment(item, rng)
            yield item
