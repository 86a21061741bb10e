"""Label a recording in CVAT: export it for labelling, import the corrected labels as a bag.

``signal-light annotate export BAG OUT`` (:func:`export_for_labelling`) runs the engine
over the bag exactly as ``signal-light replay`` does (:func:`~signal_light_node.tools.replay.replay_bag`:
the node's pairing, every frame from the bag's start, so each track's state and the
intent filter are the node's) and writes, for the frames chosen (time range, every n-th,
see :class:`ExportOptions`):

- ``OUT/images/frame_000000.jpg`` ...: the frames, in the replay's order (CVAT's frame
  numbers);
- ``OUT/annotations.xml``: "CVAT for video 1.1" (:mod:`signal_light_node.tools.cvat_xml`):
  one track per track ID with its boxes from the detection topic (boxes whose shorter
  side, clipped to the image, is under ``min_box`` pixels are left out, as are a
  frame's repeats of a track ID), every box's ``brake`` / ``left`` / ``right`` /
  ``intent`` / ``view`` pre-filled with the node's published states, marked as
  predictions (``source="auto"`` and a meta note), and the track ID in ``track_id``;
- ``OUT/labels.json``: the label and its attributes for CVAT's raw label constructor;
- ``OUT/signal_light_export.json`` (:data:`EXPORT_FILE`): the bag's topics and pairing,
  the selection, the model, and per frame the image's stamp, the SHA-256 of its message
  data, its size and its boxes with the predictions. ``annotate import`` reads it to map
  the frame numbers back to the bag.

A frame whose image cannot be decoded is not exported. No Label Studio file is written:
its video boxes (``VideoRectangle``) carry per-region choices for a whole track, not per
frame, so light states that change along a track would need a region per frame; left for
later.

``signal-light annotate import FILE BAG OUT`` (:func:`import_labels`) reads the corrected
XML (or CVAT's export ZIP holding ``annotations.xml``) and the export file beside it,
checks them against each other and against the bag (the same frames: each frame's stamp
is an image of the bag with the same data; the same track IDs per frame; known attribute
values) and raises :class:`~signal_light_node.errors.AnnotationError` in one line on the
first mismatch, before anything is written. Otherwise it writes the labelled bag to a
temporary directory beside ``OUT`` and renames it to ``OUT`` at the end: the bag's image
and detection topics, every message of them (the whole recording, so that a replay runs
the node over it as live), plus ``/ground_truth/vehicle_lights`` as the synthetic bags
have it (:mod:`signal_light_node.synth.bag`: a ``VehicleLightStateArray`` with the
image's header, logged at the image's log time, one entry per labelled detection in the
detections' order, probability 1 on the labelled states, ``frames_observed`` counted
over the recording). ``signal-light replay``, ``evaluate --bags`` and ``train --bags``
read it as they read the synthetic bags.

Frames that were not exported (outside the time range, between every n-th frame) and
boxes left out of the export (under ``min_box``) stay in the labelled bag without ground
truth: the node runs over them as it would live, but they are neither scored nor trained
on (``evaluate --bags`` and ``train --bags`` then see every n-th frame of a track only;
label every frame for those: CVAT carries an attribute's value forward to the next
keyframe, so a labeller only marks the changes). The boxes' coordinates are not read
back: the labelled bag keeps the recording's detections.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import tempfile
import zipfile
from dataclasses import asdict, dataclass, field
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np

from signal_light_node.boxes import TrackBox
from signal_light_node.errors import AnnotationError, ConfigError
from signal_light_node.io.bagio import BagWriter, find_topic, make, open_bag
from signal_light_node.io.conversions import stamp_to_ns
from signal_light_node.io.image_codec import bgr_to_compressed_fields
from signal_light_node.io.topics import (DETECTIONS_TYPE, GROUND_TRUTH_TOPIC, IMAGE_TYPES,
                                         VEHICLE_LIGHTS_TYPE)
from signal_light_node.labels import CLASS_NAMES, TASKS, intent_from_lights
from signal_light_node.outputs.vehicle_lights import result_row, vehicle_light_array
from signal_light_node.runtime.crops import clip_roi
from signal_light_node.runtime.pairing import OrderedPairing, PairingConfig, pair_in_order
from signal_light_node.runtime.results import VehicleResult
from signal_light_node.tools.cvat_xml import (ATTRIBUTES, CvatBox, CvatVideo, label_spec,
                                              read_video_xml, write_video_xml)

LOG = logging.getLogger(__name__)

#: The export's frame list, beside ``annotations.xml``.
EXPORT_FILE = "signal_light_export.json"
#: Its ``format`` value.
EXPORT_FORMAT = "signal-light annotate export 1"
#: What ``annotate import`` reads of it.
_EXPORT_KEYS = ("bag", "image_topic", "detections_topic", "pairing", "min_box", "frames")
_NS = 1_000_000_000


@dataclass(frozen=True)
class TimePoint:
    """A ``--start`` / ``--end``: seconds after the bag's first image, or a header stamp.

    Attributes:
        ns: Nanoseconds (after the first image, or since the epoch).
        absolute: Whether ``ns`` is a header stamp.
    """

    ns: int
    absolute: bool = False

    def resolve(self, first_ns: int) -> int:
        """The header stamp meant, given the bag's first image stamp."""
        return self.ns if self.absolute else first_ns + self.ns


def parse_time(text: str) -> TimePoint:
    """``S`` (seconds after the bag's first image) or ``@S`` (a header stamp in seconds).

    Raises:
        ConfigError: Not a non-negative number.
    """
    absolute = text.startswith("@")
    try:
        seconds = Decimal(text[1:] if absolute else text)
    except InvalidOperation:
        raise ConfigError(f"time {text!r} is neither S (seconds after the first image) nor "
                          "@S (a header stamp in seconds)") from None
    if not seconds.is_finite() or seconds < 0:
        raise ConfigError(f"time {text!r} must be a number >= 0")
    return TimePoint(int(seconds * _NS), absolute)


@dataclass(frozen=True)
class ExportOptions:
    """Which frames and boxes ``annotate export`` writes, and how it pairs them.

    Attributes:
        start: The first stamp (None: the first image).
        end: The last stamp (None: the last image); both ends are included.
        every: Every n-th frame of the range (1: all).
        min_box: Boxes whose shorter side, clipped to the image, is under this many pixels
            are left out.
        image_topic: Image topic (None: replay's choice).
        detections_topic: Detection topic (None: replay's choice).
        pairing: How images and detections are paired (as ``replay --sync-slop``).
        jpeg_quality: Quality of the frames written.
    """

    start: Optional[TimePoint] = None
    end: Optional[TimePoint] = None
    every: int = 1
    min_box: float = 0.0
    image_topic: Optional[str] = None
    detections_topic: Optional[str] = None
    pairing: PairingConfig = PairingConfig()
    jpeg_quality: int = 95

    def __post_init__(self) -> None:
        if int(self.every) != self.every or self.every < 1:
            raise ConfigError(f"--every must be an integer >= 1, got {self.every}")
        if not self.min_box >= 0:
            raise ConfigError(f"--min-box must be >= 0 pixels, got {self.min_box}")


def labelled_boxes(boxes: Sequence[TrackBox], width: int, height: int,
                   min_box: float) -> List[TrackBox]:
    """The boxes of a frame that are labelled, clipped to the image, in detection order.

    Left out: a box whose clipped shorter side is under ``min_box`` pixels (or that is
    empty, outside the image or not finite) and a repeat of a track ID already in the frame.
    """
    out: List[TrackBox] = []
    seen = set()
    for box in boxes:
        x, y, w, h = clip_roi(box, width, height)
        if w <= 0 or h <= 0 or min(w, h) < min_box or box.track_id in seen:
            continue
        seen.add(box.track_id)
        out.append(TrackBox(box.track_id, max(box.x0, 0.0), max(box.y0, 0.0),
                            min(box.x1, float(width)), min(box.y1, float(height)),
                            box.class_id))
    return out


def _digest(msg: Any) -> str:
    """SHA-256 of an image message's data: which recording a frame belongs to."""
    return hashlib.sha256(np.asarray(msg.data, np.uint8).tobytes()).hexdigest()


def check_new_output(out: Path) -> None:
    """Refuse an ``OUT`` that exists (nothing is ever overwritten)."""
    if Path(out).exists():
        raise AnnotationError(f"{out} exists already; choose another path")


@contextlib.contextmanager
def _staged(out: Path) -> Iterator[Path]:
    """A path to build ``out`` at, in a temporary directory beside it; renamed to ``out``
    when the block ends without an error, removed with the directory otherwise."""
    check_new_output(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
    try:
        yield tmp / out.name
        check_new_output(out)
        os.rename(tmp / out.name, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _names(row: np.ndarray) -> Dict[str, str]:
    """A ``TASKS``-order label row as attribute values (class names)."""
    return {task: CLASS_NAMES[task][int(v)] for task, v in zip(TASKS, row)}


@dataclass
class ExportSummary:
    """What :func:`export_for_labelling` wrote.

    Attributes:
        out: The directory.
        bag: The bag.
        frames: Frames exported.
        boxes: Boxes in them.
        tracks: Distinct track IDs.
        small_boxes: Boxes of the exported frames left out: under ``min_box``, empty or
            outside the image.
        undecodable: Chosen frames left out because their image could not be decoded.
        model: The model that made the predictions (``ModelRun.text()``).
    """

    out: Path
    bag: Path
    frames: int = 0
    boxes: int = 0
    tracks: int = 0
    small_boxes: int = 0
    undecodable: int = 0
    model: str = ""

    def text(self) -> str:
        """A few lines for the terminal."""
        lines = [self.model, f"exported {self.frames} frames of {self.bag}: {self.boxes} boxes "
                             f"of {self.tracks} tracks, attribute values = the node's "
                             f"predictions"]
        if self.small_boxes:
            lines.append(f"boxes left out (under --min-box, empty or outside the image): "
                         f"{self.small_boxes}")
        if self.undecodable:
            lines.append(f"frames left out, image not decodable: {self.undecodable}")
        lines.append(f"wrote {self.out}/images/frame_NNNNNN.jpg, {self.out}/annotations.xml "
                     f"(CVAT for video 1.1), {self.out}/labels.json (CVAT's raw labels), "
                     f"{self.out}/{EXPORT_FILE} (for annotate import)")
        return "\n".join(lines)


def export_for_labelling(bag: "str | Path", out: "str | Path", engine: Any,
                         options: ExportOptions = ExportOptions(),
                         progress: bool = True) -> ExportSummary:
    """Write a CVAT video task of ``bag`` with the node's predictions (module docstring).

    Args:
        bag: The recording (rosbag2 directory or ``.mcap``).
        out: The directory to create; must not exist.
        engine: The engine (``signal-light replay``'s: ``commands.options.engine_from_args``).
        options: Frames, boxes, topics and pairing.
        progress: Show the replay's progress bar.

    Returns:
        What was written.

    Raises:
        AnnotationError: ``out`` exists, or no frame is chosen.
        BagIOError: The bag cannot be read or lacks a topic.
    """
    from signal_light_node.tools.replay import replay_bag  # loads the engine's framework

    bag, out = Path(bag), Path(out)
    check_new_output(out)
    with open_bag(bag) as reader:
        topics = reader.topics()
        image_t = find_topic(topics, IMAGE_TYPES, options.image_topic, "image", bag)
        det_t = find_topic(topics, (DETECTIONS_TYPE,), options.detections_topic, "detections",
                           bag)
        digests: Dict[int, str] = {}
        for m in reader.messages([image_t], skip_undecodable=True):
            digests.setdefault(stamp_to_ns(m.msg.header.stamp), _digest(m.msg))
    if not digests:
        raise AnnotationError(f"{bag}: no image on {image_t}")
    first = min(digests)
    start = options.start.resolve(first) if options.start else first
    end = options.end.resolve(first) if options.end else max(digests)
    if end < start:
        raise ConfigError(f"--end ({(end - first) / 1e9:g} s) is before --start "
                          f"({(start - first) / 1e9:g} s after the first image)")
    summary = ExportSummary(out=out, bag=bag)
    frames: List[Dict[str, Any]] = []
    exported: set = set()
    in_range = [0]

    def on_frame(image: Any, boxes: List[TrackBox], result: Any) -> None:
        stamp = int(result.stamp_ns)
        if not start <= stamp <= end:
            return
        in_range[0] += 1
        if (in_range[0] - 1) % options.every:
            return
        if image is None:
            summary.undecodable += 1
            return
        if stamp in exported:
            LOG.warning("%s: a second image stamped %d ns; only the first is exported", bag,
                        stamp)
            return
        exported.add(stamp)
        height, width = image.shape[:2]
        fields = bgr_to_compressed_fields(image, "jpeg", options.jpeg_quality)
        (images / f"frame_{len(frames):06d}.jpg").write_bytes(
            np.asarray(fields["data"], np.uint8).tobytes())
        predicted = {}
        for box, res in zip(boxes, result.results):
            predicted.setdefault(box.track_id, _names(result_row(res)))
        kept = labelled_boxes(boxes, width, height, options.min_box)
        summary.small_boxes += len({b.track_id for b in boxes}) - len(kept)
        frames.append({"stamp_ns": stamp, "image_sha256": digests.get(stamp, ""),
                       "width": int(width), "height": int(height),
                       "boxes": [{"track_id": b.track_id,
                                  "box": [round(v, 2) for v in (b.x0, b.y0, b.x1, b.y1)],
                                  "prediction": predicted[b.track_id]} for b in kept]})

    with _staged(out) as staging, tempfile.TemporaryDirectory() as scratch:
        images = staging / "images"
        images.mkdir(parents=True)
        replay = replay_bag(bag, Path(scratch) / "replay", engine, image_topic=image_t,
                            detections_topic=det_t, progress=progress, on_frame=on_frame,
                            pairing=options.pairing)
        if not frames:
            raise AnnotationError(f"{bag}: no decodable frame between {(start - first) / 1e9:g} "
                                  f"and {(end - first) / 1e9:g} s after its first image")
        run = replay.model
        summary.model = run.text() if run is not None else ""
        model = (f"model {run.model_file or '(in memory)'} ({run.backend}, {run.precision}), "
                 if run is not None else "") + \
            f"intent filter {engine.config.intent_filter.describe()}"
        _write_export(staging, bag, image_t, det_t, options, start, end, model, frames)
    summary.frames = len(frames)
    summary.boxes = sum(len(f["boxes"]) for f in frames)
    summary.tracks = len({b["track_id"] for f in frames for b in f["boxes"]})
    return summary


def _write_export(out: Path, bag: Path, image_t: str, det_t: str, options: ExportOptions,
                  start: int, end: int, model: str, frames: List[Dict[str, Any]]) -> None:
    """``annotations.xml``, ``labels.json`` and the export file of the chosen frames."""
    boxes = [CvatBox(k, b["track_id"], tuple(b["box"]), b["prediction"])
             for k, f in enumerate(frames) for b in f["boxes"]]
    note = {"bag": str(bag), "image_topic": image_t, "detections_topic": det_t,
            "predictions": "the node's predictions, to be corrected: every attribute value is "
                           f"its own output (signal-light annotate export; {model})",
            "frames": f"{EXPORT_FILE} maps frame numbers to the bag's image stamps"}
    write_video_xml(out / "annotations.xml", boxes, len(frames), frames[0]["width"],
                    frames[0]["height"], f"{bag.name} (signal-light predictions)", note)
    (out / "labels.json").write_text(json.dumps(label_spec(), indent=2) + "\n")
    record = {"format": EXPORT_FORMAT, "bag": str(bag), "image_topic": image_t,
              "detections_topic": det_t, "pairing": asdict(options.pairing),
              "start_ns": start, "end_ns": end, "every": options.every,
              "min_box": options.min_box, "model": model, "frames": frames}
    (out / EXPORT_FILE).write_text(json.dumps(record, indent=1) + "\n")


# --------------------------------------------------------------------------- import


@dataclass
class ImportSummary:
    """What :func:`import_labels` wrote.

    Attributes:
        out: The labelled bag.
        frames: Frames with ground truth.
        boxes: Ground-truth entries.
        changed: Per attribute, boxes whose label differs from the exported prediction.
        intent_mismatch: Boxes whose intent is not the one their blinkers give
            (``labels.intent_from_lights``); kept as labelled.
        images: Images in the labelled bag.
    """

    out: Path
    frames: int = 0
    boxes: int = 0
    changed: Dict[str, int] = field(default_factory=dict)
    intent_mismatch: int = 0
    images: int = 0

    def text(self) -> str:
        """A few lines for the terminal."""
        changed = ", ".join(f"{name} {n}" for name, n in self.changed.items())
        lines = [f"labelled bag: {self.out} ({self.images} images with their detections; "
                 f"{GROUND_TRUTH_TOPIC} on {self.frames} frames, {self.boxes} boxes)",
                 f"labels that differ from the node's predictions: {changed}"]
        if self.intent_mismatch:
            lines.append(f"boxes whose intent is not the one their blinkers give: "
                         f"{self.intent_mismatch} (kept as labelled)")
        return "\n".join(lines)


def _read_annotations(path: Path) -> bytes:
    """The XML's bytes: the file, or ``annotations.xml`` of CVAT's export ZIP."""
    try:
        if zipfile.is_zipfile(path):
            with zipfile.ZipFile(path) as archive:
                names = [n for n in archive.namelist() if Path(n).name == "annotations.xml"]
                if not names:
                    raise AnnotationError(f"{path}: the ZIP holds no annotations.xml")
                return archive.read(names[0])
        return path.read_bytes()
    except OSError as exc:
        raise AnnotationError(f"cannot read {path}: {exc.strerror or exc}") from None


def read_export(path: Path) -> Dict[str, Any]:
    """The export file written beside ``annotations.xml``.

    Raises:
        AnnotationError: Missing, not JSON or not an export file.
    """
    try:
        record = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise AnnotationError(f"no {path}: give the export's {EXPORT_FILE} with "
                              "--export") from None
    except (OSError, ValueError) as exc:
        raise AnnotationError(f"cannot read {path}: {exc}") from None
    if not isinstance(record, dict) or record.get("format") != EXPORT_FORMAT:
        raise AnnotationError(f"{path} is not a file of signal-light annotate export")
    missing = [key for key in _EXPORT_KEYS if key not in record]
    if missing:
        raise AnnotationError(f"{path}: no {missing[0]!r}; write it again with annotate export")
    return record


def _where(record: Dict[str, Any], k: int) -> str:
    stamp = record["frames"][k]["stamp_ns"]
    return f"frame {k} (stamp {stamp // _NS}.{stamp % _NS:09d})"


def check_against_export(video: CvatVideo, record: Dict[str, Any], name: str) -> None:
    """The file's frames and track IDs are the export's.

    Raises:
        AnnotationError: The first frame (then track ID) where they differ.
    """
    frames = record["frames"]
    if video.size is not None and video.size != len(frames):
        raise AnnotationError(f"{name}: the task has {video.size} frames, the export "
                              f"{len(frames)}")
    per_frame: Dict[int, set] = {}
    for frame, track_id in video.boxes:
        per_frame.setdefault(frame, set()).add(track_id)
    beyond = [f for f in per_frame if f >= len(frames)]
    if beyond:
        raise AnnotationError(f"{name}: frame {min(beyond)} is beyond the export's "
                              f"{len(frames)} frames")
    for k, frame in enumerate(frames):
        want = [b["track_id"] for b in frame["boxes"]]
        have = per_frame.get(k, set())
        missing = [t for t in want if t not in have]
        if missing:
            raise AnnotationError(f"{name}: {_where(record, k)}: no box of track ID "
                                  f"{missing[0]} (the export has one there)")
        extra = sorted(have - set(want))
        if extra:
            raise AnnotationError(f"{name}: {_where(record, k)}: a box of track ID {extra[0]}, "
                                  "which the export does not have there")


def _ground_truth(bag: Path, record: Dict[str, Any], video: CvatVideo
                  ) -> Tuple[str, str, List[Tuple[int, Any]], int]:
    """Check the bag against the export and build the ground-truth messages.

    Returns:
        Image topic, detection topic, ``(log time, VehicleLightStateArray)`` per exported
        frame in log-time order, and the bag's image count.

    Raises:
        AnnotationError: The bag lacks a topic, an exported frame's image, or has another
            image or other track IDs there.
    """
    from signal_light_node.tools.replay import bag_arrivals

    frames = record["frames"]
    wanted = {int(f["stamp_ns"]): k for k, f in enumerate(frames)}
    other = f"the file was exported from {record['bag']}"
    truth: Dict[int, Tuple[int, Any]] = {}
    seen: Dict[str, int] = {}
    ordered = OrderedPairing(PairingConfig(**record["pairing"]))
    with open_bag(bag) as reader:
        topics = reader.topics()
        image_t, det_t = record["image_topic"], record["detections_topic"]
        for topic, types in ((image_t, IMAGE_TYPES), (det_t, (DETECTIONS_TYPE,))):
            if topic not in topics or topics[topic].msgtype not in types:
                raise AnnotationError(f"{bag} has no {topic} of type {' or '.join(types)}; "
                                      f"{other}")
        images = topics[image_t].count
        # The replay's reader of the bag, so the frames pair as they did for the export.
        arrivals = bag_arrivals(reader, [image_t, det_t], image_t, det_t)
        for paired in pair_in_order(arrivals, ordered):
            boxes = paired.detections if paired.paired else []
            for track_id in {b.track_id for b in boxes}:
                seen[track_id] = seen.get(track_id, 0) + 1
            k = wanted.get(paired.stamp_ns)
            if k is None or k in truth:
                continue
            frame = frames[k]
            if _digest(paired.image.msg) != frame["image_sha256"]:
                raise AnnotationError(f"{bag}: {_where(record, k)}: the image differs from the "
                                      f"one exported; {other}")
            kept = labelled_boxes(boxes, frame["width"], frame["height"], record["min_box"])
            ids = [b.track_id for b in kept]
            want = [b["track_id"] for b in frame["boxes"]]
            if ids != want:
                diff = next((t for t in want if t not in ids), None) or \
                    next(t for t in ids if t not in want)
                raise AnnotationError(f"{bag}: {_where(record, k)}: the detections differ "
                                      f"from the export's at track ID {diff}; {other}")
            results = [VehicleResult.certain(b.track_id,
                                             clip_roi(b, frame["width"], frame["height"]),
                                             frames_observed=seen[b.track_id],
                                             **_label_values(video.boxes[(k, b.track_id)]))
                       for b in kept]
            truth[k] = (paired.received_ns,
                        vehicle_light_array(paired.image.msg.header, results, make))
    missing = [k for k in range(len(frames)) if k not in truth]
    if missing:
        raise AnnotationError(f"{bag}: {_where(record, missing[0])}: no image of this "
                              f"stamp; {other}")
    return image_t, det_t, sorted(truth.values(), key=lambda t: t[0]), images


def _label_values(box: CvatBox) -> Dict[str, int]:
    """A box's attribute values as the class integers of ``VehicleResult.certain``."""
    return {task: CLASS_NAMES[task].index(box.values[task]) for task in ATTRIBUTES}


def import_labels(file: "str | Path", bag: "str | Path", out: "str | Path",
                  export: "str | Path | None" = None) -> ImportSummary:
    """Check a corrected CVAT file against its export and the bag, then write the
    labelled bag (module docstring); nothing is written when a check fails.

    Args:
        file: The corrected ``annotations.xml`` (or CVAT's export ZIP holding it).
        bag: The recording it was exported from.
        out: The labelled bag to create; must not exist.
        export: The export file (default: :data:`EXPORT_FILE` beside ``file``).

    Returns:
        What was written.

    Raises:
        AnnotationError: One line naming the first mismatch or unreadable input.
        BagIOError: The bag cannot be read or the output cannot be written.
    """
    file, bag, out = Path(file), Path(bag), Path(out)
    check_new_output(out)
    record = read_export(Path(export) if export is not None else file.parent / EXPORT_FILE)
    video = read_video_xml(_read_annotations(file), str(file))
    check_against_export(video, record, str(file))
    image_t, det_t, truth, images = _ground_truth(bag, record, video)
    summary = ImportSummary(out=out, frames=len(truth), boxes=len(video.boxes), images=images)
    summary.changed = {name: 0 for name in ATTRIBUTES}
    for k, frame in enumerate(record["frames"]):
        for b in frame["boxes"]:
            labels = video.boxes[(k, b["track_id"])].values
            for name in ATTRIBUTES:
                summary.changed[name] += labels[name] != b["prediction"][name]
            values = _label_values(video.boxes[(k, b["track_id"])])
            summary.intent_mismatch += intent_from_lights(values["left"], values["right"]) \
                != values["intent"]
    with _staged(out) as staging, open_bag(bag) as reader:
        topics = reader.topics()
        with BagWriter(staging) as writer:
            for topic in (image_t, det_t):
                writer.add_topic(topic, topics[topic].msgtype)
            writer.add_topic(GROUND_TRUTH_TOPIC, VEHICLE_LIGHTS_TYPE)
            pending = iter(truth + [(None, None)])
            log_ns, msg = next(pending)
            for m in reader.messages([image_t, det_t], skip_undecodable=True):
                writer.write(m.topic, m.log_time_ns, m.msg)
                while log_ns is not None and log_ns <= m.log_time_ns:
                    writer.write(GROUND_TRUTH_TOPIC, log_ns, msg)
                    log_ns, msg = next(pending)
            while log_ns is not None:
                writer.write(GROUND_TRUTH_TOPIC, log_ns, msg)
                log_ns, msg = next(pending)
    return summary
