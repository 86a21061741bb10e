"""``signal-light replay`` of several cameras: one bag per camera, or one bag with several
camera topic pairs, through the multi-camera engine as the node with ``cameras`` runs it.

Each camera (:class:`CameraSource`: a name, a bag, its image and detection topics) is
paired on its own, exactly as :func:`~signal_light_node.tools.replay.replay_bag` pairs one
camera (the node's :class:`~signal_light_node.runtime.pairing.OrderedPairing`, log time as
receive time). The cameras' paired images are merged in stamp order and cut into ticks as
the node's worker takes them: consecutive frames of different cameras share ONE engine
step (:meth:`~signal_light_node.runtime.engine.LightStateEngine.process_many`), a camera
that comes again starts the next. Each camera's outputs are written to its own topics,
the node's ``/signal_light_detector/<camera>/output/...`` (:func:`~signal_light_node.io.
topics.camera_topic`), header = its image's header, at its image's log time.

Camera pairs of one bag are found by namespace with :func:`detect_camera_pairs`, or named
with ``NAME=IMAGE_TOPIC,DETECTIONS_TOPIC`` (:func:`parse_camera_spec`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import heapq
import itertools
import logging
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Iterator, List, Mapping, Optional, Sequence, Tuple

from signal_light_node.errors import ConfigError, ImageConversionError
from signal_light_node.io.bagio import BagWriter, find_topic, make, open_bag
from signal_light_node.io.image_codec import DEFAULT_MAX_IMAGE_PIXELS, msg_to_bgr
from signal_light_node.io.topics import (COMPRESSED_TYPE, DETECTIONS_TYPE, GROUND_TRUTH_TOPIC,
                                         IMAGE_TYPES, VEHICLE_LIGHTS_TYPE, camera_name_problem,
                                         camera_topic)
from signal_light_node.outputs import output_adapters
from signal_light_node.outputs.vehicle_lights import truth_row
from signal_light_node.runtime.backend import ModelRun
from signal_light_node.runtime.engine import LightStateEngine
from signal_light_node.runtime.pairing import COUNTERS, OrderedPairing, PairingConfig, pair_in_order
from signal_light_node.tools.replay import ReplaySummary, _arrivals, _collect, _record

LOG = logging.getLogger(__name__)


@dataclass(frozen=True)
class CameraSource:
    """Where one camera of a replay comes from.

    Attributes:
        name: The camera's name (a ROS topic token; its outputs go under it).
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
class CamerasReplaySummary(ReplaySummary):
    """A :class:`~signal_light_node.tools.replay.ReplaySummary` of several cameras: the
    totals over all cameras, ``latencies_s`` / ``engine_s`` per shared step, ``tracks``
    keyed ``<camera>/<track ID>``, and per camera :class:`CameraFigures`.

    Attributes:
        cameras: Per camera name, its figures.
        steps: Engine steps (ticks) run.
        camera_counters: ``engine.camera_counters`` at the end.
    """

    cameras: Dict[str, CameraFigures] = field(default_factory=dict)
    steps: int = 0
    camera_counters: Dict[str, Dict[str, int]] = field(default_factory=dict)

    def text(self) -> str:
        """The single-camera summary's lines, then one line per camera."""
        lines = [super().text().replace(" engine latency ", " engine latency per step ")]
        lines.append(f"cameras: {len(self.cameras)}, {self.images} frames in {self.steps} "
                     f"shared steps ({self.images / max(self.steps, 1):.2f} frames per step)")
        for name, c in self.cameras.items():
            counts = self.camera_counters.get(name, {})
            lines.append(
                f"  {name}: {c.images} images from {c.image_topic} + {c.detections_topic} "
                f"({c.bag}) -> {', '.join(c.output_topics)}; without detections "
                f"{c.images_without_detections}, detections without image "
                f"{c.detections_without_image}, undecodable {c.bad_images}; state resets "
                f"{counts.get('resets', 0)}")
        return "\n".join(lines)


# --------------------------------------------------------------- camera choice
def parse_camera_spec(spec: str) -> Tuple[str, Optional[str], Optional[str]]:
    """``NAME`` or ``NAME=IMAGE_TOPIC,DETECTIONS_TOPIC`` -> (name, image, detections).

    Raises:
        ConfigError: Not of that form, or the name is not a ROS topic token.
    """
    name, sep, topics = spec.partition("=")
    name = name.strip()
    image = detections = None
    if sep:
        parts = [t.strip() for t in topics.split(",")]
        if len(parts) != 2 or not all(parts):
            raise ConfigError(f"--camera {spec!r}: expected NAME=IMAGE_TOPIC,DETECTIONS_TOPIC")
        image, detections = parts
    problem = camera_name_problem([name])
    if problem:
        raise ConfigError(f"--camera {spec!r}: {problem}")
    return name, image, detections


def camera_name_of(text: str) -> str:
    """A camera name made from a bag's or a namespace's name (``front-left.bag`` ->
    ``front_left``); one starting with a digit gets ``cam_`` in front."""
    name = Path(text).name
    for suffix in (".mcap", ".db3"):
        name = name[:-len(suffix)] if name.endswith(suffix) else name
    stem = re.sub(r"[^A-Za-z0-9_]", "_", name)
    stem = stem.strip("_") or "camera"
    return f"cam_{stem}" if stem[0].isdigit() else stem


def detect_camera_pairs(topics: Mapping[str, Any]) -> List[Tuple[str, str, str]]:
    """The camera topic pairs of one bag, found by namespace.

    Every ``Detection2DArray`` topic is paired with the image topic (compressed before raw)
    that shares the longest leading namespace with it (at least one segment); the camera
    is named after the last segment of that shared namespace.

    Args:
        topics: :meth:`BagReader.topics` of the bag.

    Returns:
        ``(name, image topic, detections topic)`` per camera, by name.

    Raises:
        ConfigError: No pair, an image topic claimed twice, or two cameras of one name.
    """
    def segments(topic: str) -> List[str]:
        return [s for s in topic.split("/") if s]

    images = [t for t, info in sorted(topics.items()) if info.msgtype in IMAGE_TYPES]
    found: List[Tuple[str, str, str]] = []
    for det in sorted(t for t, info in topics.items() if info.msgtype == DETECTIONS_TYPE):
        best: Tuple[int, int, str] = (0, 0, "")
        for image in images:
            shared = len(list(itertools.takewhile(lambda p: p[0] == p[1],
                                                  zip(segments(det), segments(image)))))
            preference = 1 if topics[image].msgtype == COMPRESSED_TYPE else 0
            if (shared, preference) > best[:2]:
                best = (shared, preference, image)
        if best[0] == 0:
            continue
        name = camera_name_of("/".join(segments(det)[:best[0]]).split("/")[-1])
        found.append((name, best[2], det))
    if not found:
        raise ConfigError("no camera topic pairs found: no detection topic shares a namespace "
                          f"with an image topic ({sorted(topics)})")
    for kind, values in (("image topic", [f[1] for f in found]),
                         ("camera name", [f[0] for f in found])):
        repeated = sorted({v for v in values if values.count(v) > 1})
        if repeated:
            raise ConfigError(f"camera pairs by namespace are ambiguous: {kind} {repeated[0]} "
                              f"is claimed twice; name them with --camera "
                              "NAME=IMAGE_TOPIC,DETECTIONS_TOPIC")
    return sorted(found)


def camera_sources(bags: Sequence[Path], specs: Sequence[str] = (),
                   all_cameras: bool = False) -> List[CameraSource]:
    """The cameras of a replay from the command line's bags and ``--camera`` options.

    * several bags: one camera per bag, named by the ``--camera`` option of the same
      position (``NAME`` or ``NAME=IMAGE,DETECTIONS``) or else after the bag;
    * one bag with ``--camera`` options: one camera per option (a bare ``NAME`` takes
      the pair :func:`detect_camera_pairs` finds for that name);
    * one bag with ``all_cameras``: every pair :func:`detect_camera_pairs` finds.

    Raises:
        ConfigError: Options that do not fit the bags, or bad or repeated names.
        BagIOError: A bag cannot be read.
    """
    parsed = [parse_camera_spec(s) for s in specs]
    if len(bags) > 1:
        if all_cameras:
            raise ConfigError("--all-cameras reads the camera pairs of ONE bag; with several "
                              "bags each bag is one camera")
        if parsed and len(parsed) != len(bags):
            raise ConfigError(f"{len(bags)} bags but {len(parsed)} --camera options: give one "
                              "per bag, in the same order, or none")
        sources = [CameraSource(p[0], Path(b), p[1], p[2]) for p, b in zip(parsed, bags)] \
            if parsed else [CameraSource(camera_name_of(str(b)), Path(b)) for b in bags]
    else:
        bag = Path(bags[0])
        if not parsed and not all_cameras:
            raise ConfigError("one bag: name its cameras with --camera (or --all-cameras)")
        if parsed and all_cameras:
            raise ConfigError("--camera and --all-cameras exclude each other")
        pairs: Dict[str, Tuple[str, str]] = {}
        if all_cameras or any(p[1] is None for p in parsed):
            with open_bag(bag) as reader:
                pairs = {n: (i, d) for n, i, d in detect_camera_pairs(reader.topics())}
        if all_cameras:
            sources = [CameraSource(n, bag, i, d) for n, (i, d) in pairs.items()]
        else:
            sources = []
            for name, image, dets in parsed:
                if image is None:
                    if name not in pairs:
                        raise ConfigError(f"--camera {name}: no image and detection topics "
                                          f"under a namespace {name!r} in {bag} (found "
                                          f"{sorted(pairs) or 'none'}); give them as "
                                          f"{name}=IMAGE_TOPIC,DETECTIONS_TOPIC")
                    image, dets = pairs[name]
                sources.append(CameraSource(name, bag, image, dets))
    problem = camera_name_problem([s.name for s in sources])
    if problem:
        raise ConfigError(f"cameras of the replay: {problem}")
    return sources


# --------------------------------------------------------------------- replay
def replay_cameras(sources: Sequence[CameraSource], output: "str | Path",
                   engine: LightStateEngine, with_inputs: bool = False,
                   overwrite: bool = False, progress: bool = True,
                   max_pixels: Optional[int] = DEFAULT_MAX_IMAGE_PIXELS,
                   pairing: PairingConfig = PairingConfig(),
                   markers: bool = False) -> CamerasReplaySummary:
    """Replay several cameras through the engine, one shared step per tick.

    Args:
        sources: The cameras (see :func:`camera_sources`).
        output: The MCAP rosbag2 directory to write.
        engine: The engine (its track states carry over from earlier calls).
        with_inputs: Also write every camera's image, detection and ground-truth topics
            (their names must not collide across bags).
        overwrite: Replace an existing output bag.
        progress: Show a tqdm progress bar.
        max_pixels: Images of more pixels are not decoded (counted as bad images).
        pairing: How each camera's images and detections are paired.
        markers: Also write each camera's results drawn as a ``MarkerArray``.

    Returns:
        The summary; ``tracks`` (for :func:`~signal_light_node.tools.replay.score_summary`)
        holds the judged frames of cameras whose bag has ground truth and that are the
        only camera of their bag.

    Raises:
        BagIOError: A bag cannot be read or lacks a topic, or the output cannot be written.
        ConfigError: No camera, repeated names, or input topics that collide.
    """
    if not sources:
        raise ConfigError("replay_cameras needs at least one camera")
    problem = camera_name_problem([s.name for s in sources])
    if problem:
        raise ConfigError(f"cameras of the replay: {problem}")
    output = Path(output)
    adapters = output_adapters(markers=markers)
    summary = CamerasReplaySummary(output=output, pairing=pairing,
                                   model=ModelRun.of(engine.backend))
    per_bag = {b: sum(s.bag == b for s in sources) for b in {s.bag for s in sources}}
    with contextlib.ExitStack() as stack:
        cameras = [_open_camera(stack, s, per_bag[s.bag] == 1, adapters, pairing)
                   for s in sources]
        summary.topics_written = [t for c in cameras for t in c.figures.output_topics]
        summary.image_topic = ", ".join(f"{c.source.name}: {c.image_t}" for c in cameras)
        summary.detections_topic = ", ".join(f"{c.source.name}: {c.det_t}" for c in cameras)
        summary.has_ground_truth = any(c.gt_t for c in cameras)
        summary.cameras = {c.source.name: c.figures for c in cameras}
        copied = _check_input_copies(cameras) if with_inputs else {}
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=sum(c.n_images for c in cameras), unit="frame", desc="cameras",
                       leave=False)
        start = time.perf_counter()
        with BagWriter(output, overwrite=overwrite) as writer:
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
                    _run_tick(engine, tick, adapters, writer, summary)
                    tick = []
                tick.append(frame)
                if bar is not None:
                    bar.update(1)
            if tick:
                _run_tick(engine, tick, adapters, writer, summary)
        summary.elapsed_s = time.perf_counter() - start
        if bar is not None:
            bar.close()
        for c in cameras:
            c.finish(summary)
    summary.pairing_counters = {name: sum(c.figures.pairing_counters.get(name, 0)
                                          for c in cameras) for name in COUNTERS}
    summary.detections_without_image = sum(c.figures.detections_without_image for c in cameras)
    summary.images_without_detections = sum(c.figures.images_without_detections
                                            for c in cameras)
    summary.counters = engine.counters
    summary.camera_counters = engine.camera_counters
    return summary


@dataclass
class _Frame:
    """One paired image of one camera, decoded, on its way to a tick."""

    stamp_ns: int
    index: int
    camera: "_Camera"
    message: Any
    boxes: List[Any]
    image: Any


class _Camera:
    """One camera's open bag, topics, ground truth and pairing during a replay."""

    def __init__(self, source: CameraSource, reader: Any, only_camera_of_bag: bool,
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
        self.truth = _collect(reader, self.gt_t, lambda msg: {str(v.track_id): truth_row(v)
                                                             for v in msg.vehicles})
        self.skipped_pass1 = dict(reader.skipped)
        self.pairing: Optional[OrderedPairing] = None
        self.figures = CameraFigures(
            bag=source.bag, image_topic=self.image_t, detections_topic=self.det_t,
            output_topics=[camera_topic(a.topic, source.name) for a in adapters],
            has_ground_truth=self.gt_t is not None)

    def input_topics(self) -> List[str]:
        return [self.image_t, self.det_t] + ([self.gt_t] if self.gt_t else [])

    def stream(self, writer: Optional[BagWriter], max_pixels: Optional[int],
               index: int) -> Iterator[_Frame]:
        """The camera's images in arrival order, paired as the node would, decoded."""
        self.pairing = OrderedPairing(self.pairing_config)
        topics = self.input_topics() if writer is not None else [self.image_t, self.det_t]
        arrivals = _arrivals(self.reader, topics, self.image_t, self.det_t, writer)
        for paired in pair_in_order(arrivals, self.pairing):
            m = paired.image
            boxes = paired.detections if paired.paired else []
            if not paired.paired:
                self.figures.images_without_detections += 1
            try:
                image = msg_to_bgr(m.msg, self.image_t, paired.stamp_ns, max_pixels)
            except ImageConversionError as exc:
                LOG.warning("%s", exc)
                self.figures.bad_images += 1
                image = None
            yield _Frame(paired.stamp_ns, index, self, m, boxes, image)

    def finish(self, summary: CamerasReplaySummary) -> None:
        """Fold the camera's pairing and skip counts into the summary."""
        assert self.pairing is not None
        self.figures.detections_without_image = self.pairing.unpaired_detections
        self.figures.pairing_counters = self.pairing.counters
        for topic, n in {**self.reader.skipped, **self.skipped_pass1}.items():
            summary.skipped[topic] = summary.skipped.get(topic, 0) + n
        if self.reader.recovered is not None:
            summary.recovered = (summary.recovered or 0) + self.reader.recovered


def _open_camera(stack: contextlib.ExitStack, source: CameraSource, only_camera_of_bag: bool,
                 adapters: Sequence[Any], pairing: PairingConfig) -> _Camera:
    reader = stack.enter_context(open_bag(source.bag))
    return _Camera(source, reader, only_camera_of_bag, adapters, pairing)


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
              writer: BagWriter, summary: CamerasReplaySummary) -> None:
    """One shared engine step for the tick's frames (one per camera), then their outputs."""
    usable = [f for f in tick if f.image is not None]
    frames = engine.process_many([(f.camera.source.name, f.image, f.stamp_ns, f.boxes)
                                  for f in usable]) if usable else []
    judged = iter(frames)
    if usable:
        summary.steps += 1
    if any(r.n_judged for r in frames):  # the tick ran one shared model step
        summary.model.count_step(engine.backend)
    step_s = None
    for f in tick:
        name = f.camera.source.name
        if f.image is None:
            msg = f.message.msg
            result = engine.unjudged_frame(f.stamp_ns, f.boxes, int(getattr(msg, "width", 0)),
                                           int(getattr(msg, "height", 0)),
                                           "image could not be decoded", camera=name)
        else:
            result = next(judged)
            step_s = result.latency_s
        for adapter, topic in zip(adapters, f.camera.figures.output_topics):
            writer.write(topic, f.message.log_time_ns,
                         adapter.build(f.message.msg.header, result.results, make))
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
                    {f"{name}/{tid}": row for tid, row in gt.items()},
                    [dataclasses.replace(r, track_id=f"{name}/{r.track_id}")
                     for r in result.results])
    if step_s is not None:
        summary.engine_s += step_s
        summary.latencies_s.append(step_s)

