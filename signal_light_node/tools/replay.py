"""Run the engine over recorded bags without ROS and write its output to an MCAP bag.

This is ``signal-light replay``: the same :class:`~signal_light_node.runtime.engine.LightStateEngine`
as the live node, fed from a bag as fast as the CPU allows. Images and detections are
paired by the node's own pairing (:class:`~signal_light_node.runtime.pairing.OrderedPairing`
over a :class:`~signal_light_node.runtime.pairing.StampPairer`, the log time standing in
for the receive time): exact stamps by default, the nearest within a slop with
``PairingConfig(slop_s=S)`` (``--sync-slop S``), as a node with ``sync_slop_s: S``. Every
image gets one output per output adapter (:mod:`signal_light_node.outputs`; the
``VehicleLightStateArray`` on :data:`OUTPUT_TOPIC`, with ``markers=True`` also the
``MarkerArray`` on :data:`MARKERS_TOPIC`), header = the image's header, logged at the
image's log time, with one entry per detection paired with it, or none when the node
would have dropped the image unpaired.

:func:`run_replay` is the one pipeline, for one camera and several (each a
:class:`CameraSource`): :func:`replay_bag` replays one bag as the single camera ``""`` (the
node's topics), :func:`~signal_light_node.tools.replay_cameras.replay_cameras` several
named cameras, their frames sharing engine steps as in a node with ``cameras``.

Each bag is read twice: a first pass collects the (small) ground-truth messages by stamp;
the second pass pairs images and detections in log-time order and decodes the images
one by one, in their order.
"""

from __future__ import annotations

import contextlib
import dataclasses
import heapq
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from signal_light_node.boxes import TrackBox
from signal_light_node.errors import ConfigError, ImageConversionError
from signal_light_node.labels import LIGHT_TASKS
from signal_light_node.io.bagio import BagWriter, find_topic, make, open_bag
from signal_light_node.io.conversions import detections_to_boxes, stamp_to_ns
from signal_light_node.io.image_codec import DEFAULT_MAX_IMAGE_PIXELS, msg_to_bgr
from signal_light_node.io.topics import (DETECTIONS_TYPE, GROUND_TRUTH_TOPIC, IMAGE_TYPES,
                                         MARKERS_TOPIC, OUTPUT_TOPIC, VEHICLE_LIGHTS_TYPE,
                                         camera_topic)
from signal_light_node.outputs import output_adapters
from signal_light_node.outputs.vehicle_lights import result_row, truth_row
from signal_light_node.runtime.backend import ModelRun
from signal_light_node.runtime.engine import ENGINE_STAGES, FrameResult, LightStateEngine
from signal_light_node.runtime.pairing import (COUNTERS, DETECTIONS, IMAGE, OrderedPairing,
                                               PairingConfig, pair_in_order)
from signal_light_node.runtime.results import VehicleResult

LOG = logging.getLogger(__name__)

#: Per-step stages a replay times (``ReplaySummary.stages_s``), in order: decoding the
#: images, the engine's own stages (``engine.ENGINE_STAGES``), building the output
#: messages (every output adapter) and writing them to the bag. One camera: one frame a
#: step.
REPLAY_STAGES: Tuple[str, ...] = ("decode",) + ENGINE_STAGES + ("outputs", "write")


@dataclass
class TrackRecord:
    """One track's judged frames that have ground truth, for scoring.

    Attributes:
        stamps_ns: Frame stamps.
        truth: ``[T, 5]`` ground-truth classes (``TASKS`` order).
        pred: ``[T, 5]`` predicted classes.
        frames_observed: The engine's ``frames_observed`` per frame (1 = state just started).
        light_probs: ``[T, 3, 3]`` published (OFF, ON, UNKNOWN) probabilities of brake,
            left and right.
    """

    stamps_ns: List[int] = field(default_factory=list)
    truth: List[np.ndarray] = field(default_factory=list)
    pred: List[np.ndarray] = field(default_factory=list)
    frames_observed: List[int] = field(default_factory=list)
    light_probs: List[np.ndarray] = field(default_factory=list)


@dataclass
class ReplaySummary:
    """What a replay did.

    Attributes:
        output: The bag written.
        image_topic: Image topic read.
        detections_topic: Detection topic read.
        images: Image messages read.
        outputs: Output messages written (one per image).
        detections: Boxes given to the engine.
        entries: Vehicle entries written (one per box).
        images_without_detections: Images the pairing left without detections (the node
            would have dropped them; replay writes an empty array).
        detections_without_image: Detection messages the pairing left without an image.
        bad_images: Images that could not be decoded or exceed the pixel limit (their
            boxes are written unjudged).
        skipped: Per topic, messages skipped because they could not be deserialized or
            converted (an image skipped so has no output: images in = outputs + skipped).
        recovered: Messages recovered from a cut MCAP file; None for an intact bag.
        elapsed_s: Wall time of the second pass (decode, engine, write).
        engine_s: Time spent in the engine's steps.
        latencies_s: ``latency_s`` of every engine step (one camera: of every processed
            frame).
        stages_s: Per stage of :data:`REPLAY_STAGES`, its wall time in every step (same
            steps and order as ``latencies_s``).
        counters: The engine's counters at the end.
        tracks: Per track (by ID), the frames with ground truth; empty without it.
        has_ground_truth: Whether the bag has the ground-truth topic.
        video: The annotated video written, if any.
        pairing: How images and detections were paired.
        pairing_counters: The pairer's counters (``runtime.pairing.COUNTERS``).
        topics_written: The output topics written, result array first.
        model: The model that ran (file, backend, precision, device, the threads of its
            steps); None until a replay fills it.
    """

    output: Path
    image_topic: str = ""
    detections_topic: str = ""
    images: int = 0
    outputs: int = 0
    detections: int = 0
    entries: int = 0
    images_without_detections: int = 0
    detections_without_image: int = 0
    bad_images: int = 0
    skipped: Dict[str, int] = field(default_factory=dict)
    recovered: Optional[int] = None
    elapsed_s: float = 0.0
    engine_s: float = 0.0
    latencies_s: List[float] = field(default_factory=list)
    stages_s: Dict[str, List[float]] = field(
        default_factory=lambda: {stage: [] for stage in REPLAY_STAGES})
    counters: Dict[str, int] = field(default_factory=dict)
    tracks: Dict[str, TrackRecord] = field(default_factory=dict)
    has_ground_truth: bool = False
    video: Optional[Path] = None
    pairing: PairingConfig = PairingConfig()
    pairing_counters: Dict[str, int] = field(default_factory=dict)
    topics_written: List[str] = field(default_factory=list)
    model: Optional[ModelRun] = None

    @property
    def frames_per_s(self) -> float:
        """Images processed per second of wall time (decode, engine and writing included)."""
        return self.images / self.elapsed_s if self.elapsed_s > 0 else math.nan

    @property
    def track_steps_per_s(self) -> float:
        """Judged boxes per second of wall time."""
        judged = self.counters.get("judged", 0)
        return judged / self.elapsed_s if self.elapsed_s > 0 else math.nan

    def latency_ms(self) -> Tuple[float, float]:
        """Mean and 95th percentile of the engine's per-frame latency, in ms."""
        if not self.latencies_s:
            return math.nan, math.nan
        lat = np.asarray(self.latencies_s) * 1e3
        return float(lat.mean()), float(np.percentile(lat, 95))

    def text(self) -> str:
        """A few lines for the terminal."""
        mean, p95 = self.latency_ms()
        c = self.counters
        lines = [self.model.text()] if self.model is not None else []
        lines += [
            f"output: {self.output} ({self.outputs} messages on "
            f"{', '.join(self.topics_written or [OUTPUT_TOPIC])})",
            f"images: {self.images} from {self.image_topic}, detections from "
            f"{self.detections_topic}: {self.detections} boxes -> {self.entries} entries",
            f"pairing: {self.pairing.describe()}, timeout {self.pairing.timeout_s:g} s "
            f"(as the node's): {self.pairing_counters.get('paired', 0)} pairs",
            f"frames without detections: {self.images_without_detections}; detection messages "
            f"without an image: {self.detections_without_image}; undecodable images: "
            f"{self.bad_images}",
            f"unjudged boxes: {c.get('unjudged', 0)} (duplicates {c.get('duplicates', 0)}); "
            f"state resets: {c.get('resets', 0)}; evictions: {c.get('evictions', 0)}",
            f"throughput: {self.frames_per_s:.1f} frames/s, {self.track_steps_per_s:.1f} "
            f"track-steps/s; engine latency mean {mean:.1f} ms, p95 {p95:.1f} ms",
        ]
        if self.skipped:
            lines.append("skipped messages (undecodable or unconvertible): " + ", ".join(
                f"{n} on {topic}" for topic, n in sorted(self.skipped.items())))
        if self.recovered is not None:
            lines.append(f"the bag's MCAP file is cut short: recovered {self.recovered} "
                         "messages up to the last complete record")
        if self.video is not None:
            lines.append(f"video: {self.video}")
        return "\n".join(lines)


#: What a message of an unexpected layout raises in a conversion.
_CONVERSION_ERRORS = (AttributeError, TypeError, ValueError, OverflowError)


def _collect(bag: Any, topic: Optional[str], key: Callable[[Any], Any]) -> Dict[int, Any]:
    """``stamp -> key(msg)`` of every message on ``topic`` (the first one of a stamp).

    A message that cannot be deserialized or converted is skipped, counted in ``bag.skipped``.
    """
    out: Dict[int, Any] = {}
    if topic is None:
        return out
    duplicates = 0
    for m in bag.messages([topic], skip_undecodable=True):
        try:
            stamp = stamp_to_ns(m.msg.header.stamp)
            value = key(m.msg)
        except _CONVERSION_ERRORS as exc:
            bag.note_skipped(topic, f"cannot convert {m.msgtype} on {topic} at "
                             f"{m.log_time_ns} ns: {type(exc).__name__}: {exc}")
            continue
        if stamp in out:
            duplicates += 1
            continue
        out[stamp] = value
    if duplicates:
        LOG.warning("%s: %d messages repeat an earlier header stamp; the first one is used",
                    topic, duplicates)
    return out


def bag_arrivals(bag: Any, topics: Sequence[str], img_t: str, det_t: str,
                 writer: Optional[BagWriter] = None) -> Iterator[Tuple[str, int, Any, int]]:
    """The bag's images and detections in log-time order, as ``pair_in_order`` takes them.

    Images go in as their ``BagMessage``, detections as their boxes; the log time stands
    in for the receive time. A detection message that cannot be converted is skipped,
    counted in ``bag.skipped``. With a ``writer`` every message read is copied into it.
    """
    for m in bag.messages(topics, skip_undecodable=True):
        if writer is not None:
            writer.write(m.topic, m.log_time_ns, m.msg)
        if m.topic == img_t:
            yield IMAGE, stamp_to_ns(m.msg.header.stamp), m, m.log_time_ns
        elif m.topic == det_t:
            try:
                stamp, boxes = stamp_to_ns(m.msg.header.stamp), detections_to_boxes(m.msg)
            except _CONVERSION_ERRORS as exc:
                bag.note_skipped(det_t, f"cannot convert {m.msgtype} on {det_t} at "
                                 f"{m.log_time_ns} ns: {type(exc).__name__}: {exc}")
                continue
            yield DETECTIONS, stamp, boxes, m.log_time_ns


@dataclass(frozen=True)
class CameraSource:
    """Where one camera of a replay comes from.

    Attributes:
        name: The camera's name (a ROS topic token; its outputs go under it), or ``""``
            for the single camera of :func:`replay_bag` (outputs on the node's topics).
        bag: The bag holding its topics.
        image_topic: Its image topic; None picks the bag's first (compressed first).
        detections_topic: Its detections topic; None picks the bag's first.
    """

    name: str
    bag: Path
    image_topic: Optional[str] = None
    detections_topic: Optional[str] = None


@dataclass
class CameraFigures:
    """One camera's share of a replay.

    Attributes:
        bag: Its bag.
        image_topic: Image topic read.
        detections_topic: Detection topic read.
        output_topics: Its output topics, result array first.
        images: Images read (= outputs written).
        entries: Vehicle entries written.
        images_without_detections: Images the pairing left without detections.
        detections_without_image: Detection messages the pairing left without an image.
        bad_images: Images that could not be decoded or exceed the pixel limit.
        has_ground_truth: Whether its ground truth was read.
        pairing_counters: Its pairer's counters.
    """

    bag: Path
    image_topic: str = ""
    detections_topic: str = ""
    output_topics: List[str] = field(default_factory=list)
    images: int = 0
    entries: int = 0
    images_without_detections: int = 0
    detections_without_image: int = 0
    bad_images: int = 0
    has_ground_truth: bool = False
    pairing_counters: Dict[str, int] = field(default_factory=dict)


@dataclass
class ReplayRun:
    """What :func:`run_replay` adds to its summary for a several-camera one.

    Attributes:
        cameras: Per camera name, its figures.
        steps: Engine steps (ticks with a decoded image) run.
    """

    cameras: Dict[str, CameraFigures]
    steps: int = 0


def replay_bag(bag_path: "str | Path", output: "str | Path", engine: LightStateEngine,
               image_topic: Optional[str] = None, detections_topic: Optional[str] = None,
               with_inputs: bool = False, video: "str | Path | None" = None,
               video_attention: bool = False, overwrite: bool = False,
               progress: bool = True, max_pixels: Optional[int] = DEFAULT_MAX_IMAGE_PIXELS,
               on_frame: Optional[Callable[[Any, List[TrackBox], FrameResult], None]] = None,
               pairing: PairingConfig = PairingConfig(), markers: bool = False
               ) -> ReplaySummary:
    """Replay a bag through the engine and write the output bag: :func:`run_replay` of
    one camera named ``""`` (the node's topics, track IDs as they are).

    Args:
        bag_path: The input bag (rosbag2 directory or ``.mcap``).
        output: The MCAP rosbag2 directory to write.
        engine: The engine (its track states carry over from earlier calls).
        image_topic: Image topic; by default the first CompressedImage topic, else the
            first Image topic.
        detections_topic: Detection topic; by default the first Detection2DArray topic.
        with_inputs: Also write the image, detection and ground-truth topics.
        video: Optional ``.mp4`` or ``.gif`` for the annotated frames.
        video_attention: Overlay the attention masks in the video (one more model pass).
        overwrite: Replace an existing output bag.
        progress: Show a tqdm progress bar.
        max_pixels: Images of more pixels are not decoded (counted as bad images).
        on_frame: Called as ``on_frame(image_bgr_or_None, boxes, frame_result)`` per image.
        pairing: How images and detections are paired (default: the node's defaults,
            exact stamps).
        markers: Also write the results drawn as a ``MarkerArray`` on :data:`MARKERS_TOPIC`.

    Returns:
        The summary, with per-track records for scoring when the bag has ground truth.

    Raises:
        BagIOError: The bag cannot be read, lacks the topics, or the output cannot be written.
        ConfigError: The video path has an unsupported suffix.
    """
    summary = ReplaySummary(output=Path(output), pairing=pairing,
                            model=ModelRun.of(engine.backend))
    run_replay([CameraSource("", Path(bag_path), image_topic, detections_topic)], summary,
               engine, with_inputs=with_inputs, video=video, video_attention=video_attention,
               overwrite=overwrite, progress=progress, max_pixels=max_pixels,
               on_frame=on_frame, markers=markers)
    return summary


def run_replay(sources: Sequence[CameraSource], summary: ReplaySummary, engine: LightStateEngine,
               with_inputs: bool = False, video: "str | Path | None" = None,
               video_attention: bool = False, overwrite: bool = False, progress: bool = True,
               max_pixels: Optional[int] = DEFAULT_MAX_IMAGE_PIXELS,
               on_frame: Optional[Callable[[Any, List[TrackBox], FrameResult], None]] = None,
               markers: bool = False) -> ReplayRun:
    """The one replay pipeline: the cameras' bags paired, decoded, cut into ticks, judged
    one engine step per tick and written, as the node's worker does.

    Each camera is paired on its own (the node's :class:`OrderedPairing` with
    ``summary.pairing``, log time as receive time); the cameras' paired images are merged
    in stamp order and cut into ticks as the node's worker takes them: consecutive frames
    of different cameras share ONE step (``engine.process_many``), a camera that comes
    again starts the next (one camera: one frame per step). Each camera's outputs go to
    its own topics (:func:`~signal_light_node.io.topics.camera_topic`; the node's own for
    the camera ``""``), header = its image's header, at its image's log time.

    Args:
        sources: The cameras; names are not checked here (``""`` only alone).
        summary: Filled in place (``summary.output`` is the bag written).
        engine: The engine (its track states carry over from earlier calls).
        with_inputs: Also write every camera's image, detection and ground-truth topics.
        video: Optional ``.mp4`` or ``.gif`` of the first camera's annotated frames.
        video_attention: Overlay the attention masks in the video (one more model pass).
        overwrite: Replace an existing output bag.
        progress: Show a tqdm progress bar.
        max_pixels: Images of more pixels are not decoded (counted as bad images).
        on_frame: Called as ``on_frame(image_bgr_or_None, boxes, frame_result)`` per image.
        markers: Also write each camera's results drawn as a ``MarkerArray``.

    Returns:
        The per-camera figures and the number of steps.

    Raises:
        BagIOError: A bag cannot be read or lacks a topic, or the output cannot be written.
        ConfigError: Input topics that collide, or a video path of another suffix.
    """
    from signal_light_node.outputs.debug_image import draw_results
    from signal_light_node.tools.visualize import VideoSink

    adapters = output_adapters(markers=markers)
    per_bag = {b: sum(s.bag == b for s in sources) for b in {s.bag for s in sources}}
    with contextlib.ExitStack() as stack:
        cameras = [_Camera(stack.enter_context(open_bag(s.bag)), s, per_bag[s.bag] == 1,
                           adapters, summary.pairing) for s in sources]
        run = ReplayRun({c.source.name: c.figures for c in cameras})
        summary.topics_written = [t for c in cameras for t in c.figures.output_topics]
        summary.image_topic = ", ".join(_named(c.source.name, c.image_t) for c in cameras)
        summary.detections_topic = ", ".join(_named(c.source.name, c.det_t) for c in cameras)
        summary.has_ground_truth = any(c.gt_t for c in cameras)
        copied = _check_input_copies(cameras) if with_inputs else {}
        sink = None
        if video is not None:
            sink = VideoSink(video, fps=cameras[0].fps())

        def after(frame: _Frame, result: FrameResult) -> None:
            if sink is not None and frame.image is not None and frame.camera is cameras[0]:
                heat = engine.attention_masks(frame.image, frame.boxes) if video_attention \
                    else None
                sink.add(draw_results(frame.image, result.results, heat,
                                      caption=f"{frame.stamp_ns / 1e9:.3f} s"))
            if on_frame is not None:
                on_frame(frame.image, frame.boxes, result)

        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=sum(c.n_images for c in cameras), unit="frame", leave=False,
                       desc=sources[0].bag.name if len(cameras) == 1 else "cameras")
        start = time.perf_counter()
        with BagWriter(summary.output, overwrite=overwrite) as writer:
            for c in cameras:
                for adapter, topic in zip(adapters, c.figures.output_topics):
                    writer.add_topic(topic, adapter.msgtype)
            for topic, msgtype in copied.items():
                writer.add_topic(topic, msgtype)
            streams = [c.stream(writer if with_inputs else None, max_pixels, k)
                       for k, c in enumerate(cameras)]
            tick: List[_Frame] = []
            for frame in heapq.merge(*streams, key=lambda f: (f.stamp_ns, f.index)):
                if any(f.camera is frame.camera for f in tick):
                    run.steps += _run_tick(engine, tick, adapters, writer, summary, after)
                    tick = []
                tick.append(frame)
                if len(tick) == len(cameras):  # no other frame can join: run it now
                    run.steps += _run_tick(engine, tick, adapters, writer, summary, after)
                    tick = []
                if bar is not None:
                    bar.update(1)
            if tick:
                run.steps += _run_tick(engine, tick, adapters, writer, summary, after)
        summary.elapsed_s = time.perf_counter() - start
        if bar is not None:
            bar.close()
        if sink is not None:
            summary.video = sink.close()
        for c in cameras:
            c.finish(summary)
    summary.pairing_counters = {name: sum(c.figures.pairing_counters.get(name, 0)
                                          for c in cameras) for name in COUNTERS}
    summary.detections_without_image = sum(c.figures.detections_without_image for c in cameras)
    summary.images_without_detections = sum(c.figures.images_without_detections
                                            for c in cameras)
    summary.counters = engine.counters
    return run


def _named(camera: str, text: str) -> str:
    """``text`` for the unnamed camera, else ``camera: text``."""
    return f"{camera}: {text}" if camera else text


@dataclass
class _Frame:
    """One paired image of one camera, decoded, on its way to a tick."""

    stamp_ns: int
    index: int
    camera: "_Camera"
    message: Any
    boxes: List[Any]
    image: Any
    decode_s: float


class _Camera:
    """One camera's open bag, topics, ground truth and pairing during a replay."""

    def __init__(self, reader: Any, source: CameraSource, only_camera_of_bag: bool,
                 adapters: Sequence[Any], pairing: PairingConfig) -> None:
        self.source = source
        self.pairing_config = pairing
        self.reader = reader
        topics = reader.topics()
        self.topics = topics
        self.image_t = find_topic(topics, IMAGE_TYPES, source.image_topic, "image", source.bag)
        self.det_t = find_topic(topics, (DETECTIONS_TYPE,), source.detections_topic,
                                "detections", source.bag)
        gt = topics.get(GROUND_TRUTH_TOPIC)
        self.gt_t = GROUND_TRUTH_TOPIC if only_camera_of_bag and gt is not None \
            and gt.msgtype == VEHICLE_LIGHTS_TYPE else None
        self.n_images = topics[self.image_t].count
        # Pass 1: the small ground-truth messages, keyed by header stamp.
        self.truth = _collect(reader, self.gt_t, lambda msg: {str(v.track_id): truth_row(v)
                                                             for v in msg.vehicles})
        self.skipped_pass1 = dict(reader.skipped)  # pass 2 may read them again (with_inputs)
        self.pairing: Optional[OrderedPairing] = None
        self.figures = CameraFigures(
            bag=source.bag, image_topic=self.image_t, detections_topic=self.det_t,
            output_topics=[camera_topic(a.topic, source.name) for a in adapters],
            has_ground_truth=self.gt_t is not None)

    def input_topics(self) -> List[str]:
        return [self.image_t, self.det_t] + ([self.gt_t] if self.gt_t else [])

    def fps(self) -> float:
        """The frame rate of its images over the bag's duration (for a video)."""
        duration_s = self.reader.duration_ns / 1e9
        n = self.n_images
        fps = (n - 1) / duration_s if n > 1 and duration_s > 0 else 10.0
        return min(max(fps, 1.0), 60.0)

    def stream(self, writer: Optional[BagWriter], max_pixels: Optional[int],
               index: int) -> Iterator[_Frame]:
        """Pass 2: the camera's images in arrival order, paired as the node would, decoded
        one by one; with a ``writer`` every message read is copied into it."""
        self.pairing = OrderedPairing(self.pairing_config)
        topics = self.input_topics() if writer is not None else [self.image_t, self.det_t]
        arrivals = bag_arrivals(self.reader, topics, self.image_t, self.det_t, writer)
        for paired in pair_in_order(arrivals, self.pairing):
            m = paired.image
            boxes = paired.detections if paired.paired else []
            if not paired.paired:
                self.figures.images_without_detections += 1
            start = time.perf_counter()
            try:
                image = msg_to_bgr(m.msg, self.image_t, paired.stamp_ns, max_pixels)
            except ImageConversionError as exc:
                LOG.warning("%s", exc)
                self.figures.bad_images += 1
                image = None
            yield _Frame(paired.stamp_ns, index, self, m, boxes, image,
                         time.perf_counter() - start)

    def finish(self, summary: ReplaySummary) -> None:
        """Fold the camera's pairing and skip counts into the summary."""
        assert self.pairing is not None
        self.figures.detections_without_image = self.pairing.unpaired_detections
        self.figures.pairing_counters = self.pairing.counters
        for topic, n in {**self.reader.skipped, **self.skipped_pass1}.items():
            summary.skipped[topic] = summary.skipped.get(topic, 0) + n
        if self.reader.recovered is not None:
            summary.recovered = (summary.recovered or 0) + self.reader.recovered


def _check_input_copies(cameras: Sequence[_Camera]) -> Dict[str, str]:
    """Input topic -> type of every topic ``with_inputs`` copies.

    Raises:
        ConfigError: Two cameras of different bags bring the same topic name.
    """
    out: Dict[str, str] = {}
    owner: Dict[str, Path] = {}
    for c in cameras:
        for topic in c.input_topics():
            if topic in owner and owner[topic] != c.source.bag:
                raise ConfigError(f"--with-inputs: topic {topic} is in {owner[topic]} and in "
                                  f"{c.source.bag}; the output bag cannot hold both")
            owner[topic] = c.source.bag
            out[topic] = c.topics[topic].msgtype
    return out


def _run_tick(engine: LightStateEngine, tick: Sequence[_Frame], adapters: Sequence[Any],
              writer: BagWriter, summary: ReplaySummary,
              after: Callable[[_Frame, FrameResult], None]) -> int:
    """One shared engine step for the tick's frames (one per camera), then their outputs.

    Returns:
        1 when the tick ran a step (it had a decoded image), else 0.
    """
    usable = [f for f in tick if f.image is not None]
    judged = iter(engine.process_many([(f.camera.source.name, f.image, f.stamp_ns, f.boxes)
                                       for f in usable]) if usable else [])
    results = [next(judged) if f.image is not None else
               engine.unjudged_frame(f.stamp_ns, f.boxes,
                                     int(getattr(f.message.msg, "width", 0)),
                                     int(getattr(f.message.msg, "height", 0)),
                                     "image could not be decoded", camera=f.camera.source.name)
               for f in tick]
    step = next((r for f, r in zip(tick, results) if f.image is not None), None)
    if step is not None:
        if any(r.n_judged for r in results):  # the tick ran one shared model step
            summary.model.count_step(engine.backend)
        summary.engine_s += step.latency_s
        summary.latencies_s.append(step.latency_s)
    t_build = time.perf_counter()
    messages = [[adapter.build(f.message.msg.header, r.results, make) for adapter in adapters]
                for f, r in zip(tick, results)]
    t_write = time.perf_counter()
    for f, built in zip(tick, messages):
        for topic, message in zip(f.camera.figures.output_topics, built):
            writer.write(topic, f.message.log_time_ns, message)
    if step is not None:
        _add_stages(summary.stages_s, sum(f.decode_s for f in usable), step.stages_s,
                    t_write - t_build, time.perf_counter() - t_write)
    for f, result in zip(tick, results):
        name = f.camera.source.name
        figures = f.camera.figures
        figures.images += 1
        figures.entries += len(result.results)
        summary.images += 1
        summary.outputs += 1
        summary.detections += len(f.boxes)
        summary.entries += len(result.results)
        summary.bad_images += f.image is None
        gt = f.camera.truth.get(f.stamp_ns)
        if gt:
            _record(summary.tracks, f.stamp_ns,
                    {_track_key(name, tid): row for tid, row in gt.items()},
                    [dataclasses.replace(r, track_id=_track_key(name, r.track_id))
                     for r in result.results] if name else result.results)
        after(f, result)
    return int(step is not None)


def _track_key(camera: str, track_id: str) -> str:
    """A track's key in ``ReplaySummary.tracks``: ``<camera>/<id>``, the bare ID for ``""``."""
    return f"{camera}/{track_id}" if camera else track_id


def _add_stages(stages: Dict[str, List[float]], decode_s: float, engine_s: Mapping[str, float],
                outputs_s: float, write_s: float) -> None:
    """Append one processed frame's stage times to ``ReplaySummary.stages_s``."""
    stages["decode"].append(decode_s)
    for stage in ENGINE_STAGES:
        stages[stage].append(float(engine_s.get(stage, 0.0)))
    stages["outputs"].append(outputs_s)
    stages["write"].append(write_s)


def _record(tracks: Dict[str, TrackRecord], stamp: int, truth: Mapping[str, np.ndarray],
            results: Sequence[VehicleResult]) -> None:
    """Keep the judged results that have a ground-truth entry of the same track ID."""
    for res in results:
        row = truth.get(res.track_id)
        if row is None or not res.judged:
            continue
        rec = tracks.setdefault(res.track_id, TrackRecord())
        rec.stamps_ns.append(stamp)
        rec.truth.append(row)
        rec.pred.append(result_row(res))
        rec.frames_observed.append(res.frames_observed)
        rec.light_probs.append(np.array([[e.off, e.on, e.unknown] for e in
                                         (res.brake, res.left, res.right)], np.float64))


def score_summary(summary: ReplaySummary, settings: Any = None) -> Optional[Dict[str, Any]]:
    """Score the replay's output against the bag's ground truth, with the evaluation's rules.

    The warm-up and grace-window rules are those of ``signal-light evaluate``
    (:class:`signal_light_node.evaluation.scoring.TrackScorer`); they apply from each
    start of a track's state in the engine (``frames_observed == 1``), so a track that
    timed out and came back warms up again. Only judged boxes with a ground-truth entry
    of the same track ID are scored.

    Args:
        summary: A replay summary of a bag with ground truth.
        settings: ``evaluation.scoring.EvalSettings`` (default: its defaults).

    Returns:
        ``{"settings", "counts", "no_grace", "grace", "switches", "flicker",
        "unknown_share", "unknown_by_view", "calibration"}`` shaped like
        ``evaluate_tracks``' result (reports from ``metrics.MetricAccumulator.report``,
        without breakdowns, so ``unknown_by_view`` is empty),
        where a track is one segment of a track's state, or None when no judged box had
        ground truth.
    """
    from signal_light_node.evaluation.scoring import EvalSettings, TrackScorer
    from signal_light_node.evaluation.tracks import TrackSequence

    if not summary.tracks:
        return None
    scorer = TrackScorer(settings or EvalSettings())
    for track_id, rec in sorted(summary.tracks.items()):
        frames = np.asarray(rec.frames_observed)
        starts = list(np.flatnonzero(frames == 1)) or [0]
        if starts[0] != 0:
            starts.insert(0, 0)
        for a, b in zip(starts, starts[1:] + [len(frames)]):
            n = b - a
            seq = TrackSequence(track_id=f"{track_id}@{a}", labels=np.stack(rec.truth[a:b]),
                                mask=np.ones(n, bool),
                                stamps_ns=np.asarray(rec.stamps_ns[a:b], np.int64),
                                box_size=np.full(n, math.nan), occlusion=np.full(n, math.nan),
                                source=f"replay:{summary.output.name}")
            lights = np.stack(rec.light_probs[a:b])
            scorer.add(seq, np.stack(rec.pred[a:b]), breakdowns=False,
                       probs={t: lights[:, i] for i, t in enumerate(LIGHT_TASKS)})
    return scorer.result()
