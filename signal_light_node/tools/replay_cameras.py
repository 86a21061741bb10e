"""``signal-light replay`` of several cameras: one bag per camera, or one bag with several
camera topic pairs, through the multi-camera engine as the node with ``cameras`` runs it.

This module chooses the cameras (each a :class:`~signal_light_node.tools.replay.CameraSource`:
a name, a bag, its image and detection topics) and sums up the run; the replay itself is
:func:`~signal_light_node.tools.replay.run_replay`, the one pipeline that ``replay_bag``
runs for its single camera: each camera paired on its own, the cameras' paired images
merged in stamp order and cut into ticks as the node's worker takes them (consecutive
frames of different cameras share ONE engine step, a camera that comes again starts the
next), each camera's outputs on its own topics, the node's
``/signal_light_detector/<camera>/output/...`` (:func:`~signal_light_node.io.topics.camera_topic`).

Camera pairs of one bag are found by namespace with :func:`detect_camera_pairs`, or named
with ``NAME=IMAGE_TOPIC,DETECTIONS_TOPIC`` (:func:`parse_camera_spec`).
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

from signal_light_node.errors import ConfigError
from signal_light_node.io.bagio import open_bag
from signal_light_node.io.image_codec import DEFAULT_MAX_IMAGE_PIXELS
from signal_light_node.io.topics import (COMPRESSED_TYPE, DETECTIONS_TYPE, IMAGE_TYPES,
                                         camera_name_problem)
from signal_light_node.runtime.backend import ModelRun
from signal_light_node.runtime.engine import LightStateEngine
from signal_light_node.runtime.pairing import PairingConfig
from signal_light_node.tools.replay import (CameraFigures, CameraSource, ReplaySummary,
                                            run_replay)

__all__ = ["CameraFigures", "CameraSource", "CamerasReplaySummary", "camera_name_of",
           "camera_sources", "detect_camera_pairs", "parse_camera_spec", "replay_cameras"]

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
    summary = CamerasReplaySummary(output=Path(output), pairing=pairing,
                                   model=ModelRun.of(engine.backend))
    run = run_replay(sources, summary, engine, with_inputs=with_inputs, overwrite=overwrite,
                     progress=progress, max_pixels=max_pixels, markers=markers)
    summary.cameras, summary.steps = run.cameras, run.steps
    summary.camera_counters = engine.camera_counters
    return summary
