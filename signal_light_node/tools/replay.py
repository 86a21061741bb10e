"""Run the engine over a recorded bag without ROS and write its output to an MCAP bag.

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

The bag is read twice: a first pass collects the (small) ground-truth messages by stamp;
the second pass pairs images and detections in log-time order and decodes the images
one by one, in their order.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from signal_light_node.io.bagio import BagWriter, find_topic, make, open_bag
from signal_light_node.boxes import TrackBox
from signal_light_node.io.conversions import detections_to_boxes, stamp_to_ns
from signal_light_node.runtime.backend import ModelRun
from signal_light_node.runtime.engine import ENGINE_STAGES, FrameResult, LightStateEngine
from signal_light_node.errors import ImageConversionError
from signal_light_node.io.image_codec import DEFAULT_MAX_IMAGE_PIXELS, msg_to_bgr
from signal_light_node.runtime.results import VehicleResult
from signal_light_node.io.topics import (DETECTIONS_TYPE, GROUND_TRUTH_TOPIC, IMAGE_TYPES,
                                      MARKERS_TOPIC, OUTPUT_TOPIC, VEHICLE_LIGHTS_TYPE)
from signal_light_node.outputs import output_adapters
from signal_light_node.outputs.vehicle_lights import result_row, truth_row
from signal_light_node.runtime.pairing import (DETECTIONS, IMAGE, OrderedPairing,
                                               PairingConfig, pair_in_order)

LOG = logging.getLogger(__name__)

#: Per-frame stages a replay times (``ReplaySummary.stages_s``), in order: decoding the
#: image, the engine's own stages (``engine.ENGINE_STAGES``), building the output
#: messages (every output adapter) and writing them to the bag.
REPLAY_STAGES: Tuple[str, ...] = ("decode",) + ENGINE_STAGES + ("outputs", "write")


@dataclass
class TrackRecord:
    """One track's judged frames that have ground truth, for scoring.

    Attributes:
        stamps_ns: Frame stamps.
        truth: ``[T, 5]`` ground-truth classes (``TASKS`` order).
        pred: ``[T, 5]`` predicted classes.
        frames_observed: The engine's ``frames_observed`` per frame (1 = state just started).
    """

    stamps_ns: List[int] = field(default_factory=list)
    truth: List[np.ndarray] = field(default_factory=list)
    pred: List[np.ndarray] = field(default_factory=list)
    frames_observed: List[int] = field(default_factory=list)


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
        engine_s: Time spent in ``engine.process``.
        latencies_s: ``latency_s`` of every processed frame.
        stages_s: Per stage of :data:`REPLAY_STAGES`, its wall time in every processed
            frame (same frames and order as ``latencies_s``).
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


def _arrivals(bag: Any, topics: Sequence[str], img_t: str, det_t: str,
              writer: Optional[BagWriter]) -> Iterator[Tuple[str, int, Any, int]]:
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


def replay_bag(bag_path: "str | Path", output: "str | Path", engine: LightStateEngine,
               image_topic: Optional[str] = None, detections_topic: Optional[str] = None,
               with_inputs: bool = False, video: "str | Path | None" = None,
               video_attention: bool = False, overwrite: bool = False,
               progress: bool = True, max_pixels: Optional[int] = DEFAULT_MAX_IMAGE_PIXELS,
               on_frame: Optional[Callable[[Any, List[TrackBox], FrameResult], None]] = None,
               pairing: PairingConfig = PairingConfig(), markers: bool = False
               ) -> ReplaySummary:
    """Replay a bag through the engine and write the output bag.

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
    from signal_light_node.outputs.debug_image import draw_results
    from signal_light_node.tools.visualize import VideoSink

    bag_path, output = Path(bag_path), Path(output)
    adapters = output_adapters(markers=markers)
    summary = ReplaySummary(output=output, pairing=pairing,
                            topics_written=[a.topic for a in adapters],
                            model=ModelRun.of(engine.backend))
    with open_bag(bag_path) as bag:
        topics = bag.topics()
        img_t = find_topic(topics, IMAGE_TYPES, image_topic, "image", bag_path)
        det_t = find_topic(topics, (DETECTIONS_TYPE,), detections_topic, "detections", bag_path)
        gt_info = topics.get(GROUND_TRUTH_TOPIC)
        gt_t = GROUND_TRUTH_TOPIC if gt_info is not None and \
            gt_info.msgtype == VEHICLE_LIGHTS_TYPE else None
        summary.image_topic, summary.detections_topic = img_t, det_t
        summary.has_ground_truth = gt_t is not None
        n_images = topics[img_t].count

        # Pass 1: the small ground-truth messages, keyed by header stamp.
        truth = _collect(bag, gt_t, lambda msg: {str(v.track_id): truth_row(v)
                                                 for v in msg.vehicles})
        skipped = dict(bag.skipped)  # pass 2 may read these topics again (with_inputs)
        sink = None
        if video is not None:
            duration_s = bag.duration_ns / 1e9
            fps = (n_images - 1) / duration_s if n_images > 1 and duration_s > 0 else 10.0
            sink = VideoSink(video, fps=min(max(fps, 1.0), 60.0))

        # Pass 2: pair as the node would, decode each image in its order, run the engine,
        # write.
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=n_images, unit="frame", desc=bag_path.name, leave=False)
        input_topics = [img_t, det_t] + ([gt_t] if gt_t else [])
        ordered = OrderedPairing(pairing)
        start = time.perf_counter()
        with BagWriter(output, overwrite=overwrite) as writer:
            for adapter in adapters:
                writer.add_topic(adapter.topic, adapter.msgtype)
            if with_inputs:
                for t in input_topics:
                    writer.add_topic(t, topics[t].msgtype)
            arrivals = _arrivals(bag, input_topics if with_inputs else [img_t, det_t], img_t,
                                 det_t, writer if with_inputs else None)
            for paired in pair_in_order(arrivals, ordered):
                m, stamp = paired.image, paired.stamp_ns
                boxes = paired.detections if paired.paired else []
                if not paired.paired:
                    summary.images_without_detections += 1
                t_decode = time.perf_counter()
                try:
                    image = msg_to_bgr(m.msg, img_t, stamp, max_pixels)
                except ImageConversionError as exc:
                    LOG.warning("%s", exc)
                    summary.bad_images += 1
                    image = None
                t_decode = time.perf_counter() - t_decode
                if image is None:
                    frame = engine.unjudged_frame(stamp, boxes, int(getattr(m.msg, "width", 0)),
                                                  int(getattr(m.msg, "height", 0)),
                                                  "image could not be decoded")
                else:
                    frame = engine.process(image, stamp, boxes)
                    if frame.n_judged:  # the frame ran a model step
                        summary.model.count_step(engine.backend)
                    summary.engine_s += frame.latency_s
                    summary.latencies_s.append(frame.latency_s)
                t_build = time.perf_counter()
                messages = [adapter.build(m.msg.header, frame.results, make)
                            for adapter in adapters]
                t_write = time.perf_counter()
                for adapter, message in zip(adapters, messages):
                    writer.write(adapter.topic, m.log_time_ns, message)
                if image is not None:
                    _add_stages(summary.stages_s, t_decode, frame.stages_s, t_write - t_build,
                                time.perf_counter() - t_write)
                summary.images += 1
                summary.outputs += 1
                summary.detections += len(boxes)
                summary.entries += len(frame.results)
                gt = truth.get(stamp)
                if gt:
                    _record(summary.tracks, stamp, gt, frame.results)
                if sink is not None and image is not None:
                    heat = engine.attention_masks(image, boxes) if video_attention else None
                    sink.add(draw_results(image, frame.results, heat,
                                          caption=f"{stamp / 1e9:.3f} s"))
                if on_frame is not None:
                    on_frame(image, boxes, frame)
                if bar is not None:
                    bar.update(1)
        summary.elapsed_s = time.perf_counter() - start
        if bar is not None:
            bar.close()
        if sink is not None:
            summary.video = sink.close()
        # Pass 1's counts for the topics it read (pass 2 reads them again with_inputs).
        summary.skipped = {**bag.skipped, **skipped}
        summary.recovered = bag.recovered
    summary.detections_without_image = ordered.unpaired_detections
    summary.pairing_counters = ordered.counters
    summary.counters = engine.counters
    return summary


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
        ``{"settings", "counts", "no_grace", "grace"}`` shaped like ``evaluate_tracks``'
        result (reports from ``metrics.MetricAccumulator.report``, without breakdowns),
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
            scorer.add(seq, np.stack(rec.pred[a:b]), breakdowns=False)
    return scorer.result()
