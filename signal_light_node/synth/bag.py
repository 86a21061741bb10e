"""Write a rendered scene as a rosbag2 MCAP bag with tracked boxes and ground truth.

Topics (log time = the image's stamp; every message of a frame has the image's header):

- ``/camera/image_raw/compressed`` ``sensor_msgs/CompressedImage`` (JPEG), or with
  ``raw=True`` ``/camera/image_raw`` ``sensor_msgs/Image`` (bgr8);
- ``/camera/tracked_objects`` ``vision_msgs/Detection2DArray``: one detection per vehicle
  the simulated tracker reports, ``id`` = track ID, class in ``results[0]``;
- ``/ground_truth/vehicle_lights`` ``signal_light_msgs/VehicleLightStateArray``: one entry
  per detection, in the same order, with probability 1 on the true states.

Used by ``signal-light synth``, ``scripts/make_bags.sh`` and the tests.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Set

from tqdm import tqdm

from signal_light_node.io import bagio
from signal_light_node.boxes import TrackBox
from signal_light_node.io.conversions import boxes_to_detections, make_header
from signal_light_node.runtime.crops import clip_roi
from signal_light_node.errors import ConfigError
from signal_light_node.io.image_codec import bgr_to_compressed_fields, bgr_to_image_fields
from signal_light_node.labels import Intent, LightStatus, View
from signal_light_node.outputs.vehicle_lights import vehicle_light_array
from signal_light_node.runtime.results import VehicleResult
# The topics under the names the tests and tools import them by from here.
from signal_light_node.io.topics import CAMERA_COMPRESSED_TOPIC as COMPRESSED_TOPIC
from signal_light_node.io.topics import CAMERA_IMAGE_TOPIC as IMAGE_TOPIC
from signal_light_node.io.topics import TRACKED_OBJECTS_TOPIC as DETECTIONS_TOPIC
from signal_light_node.io.topics import (COMPRESSED_TYPE, DETECTIONS_TYPE, GROUND_TRUTH_TOPIC,
                                      IMAGE_TYPE, VEHICLE_LIGHTS_TYPE)

LOG = logging.getLogger(__name__)


@dataclass
class SceneBagSummary:
    """What :func:`write_scene_bag` wrote.

    Attributes:
        path: The bag directory.
        frames: Number of images.
        fps: Frame rate.
        width: Image width.
        height: Image height.
        lighting: Lighting of the scene.
        track_ids: Every track ID that appears in the detections.
        detections: Total number of detections over all frames.
    """

    path: Path
    frames: int
    fps: float
    width: int
    height: int
    lighting: str
    track_ids: Set[str] = field(default_factory=set)
    detections: int = 0


def truth_result(vehicle: Any, box: TrackBox, width: int, height: int,
                 frames_observed: int) -> VehicleResult:
    """The ground truth of one rendered vehicle as a one-hot ``VehicleResult``.

    Args:
        vehicle: A ``synth.VehicleTruth``.
        box: The box published for it (its tracker box).
        width: Image width (for the ROI).
        height: Image height.
        frames_observed: Frames this track has been in the detections so far, this one included.

    Returns:
        The result: every state with probability 1, ``classification`` = the lights ON.
    """
    return VehicleResult.certain(str(vehicle.track_id), clip_roi(box, width, height),
                                 vehicle.brake, vehicle.left, vehicle.right, vehicle.intent,
                                 vehicle.view, frames_observed)


def write_scene_bag(path: "str | os.PathLike[str]", seed: int = 0, *,
                    n_frames: Optional[int] = None, duration_s: Optional[float] = None,
                    fps: Optional[float] = None, width: int = 640, height: int = 360,
                    n_vehicles: Optional[int] = None, lighting: Optional[str] = None,
                    night_fraction: Optional[float] = None, raw: bool = False,
                    jpeg_quality: int = 85, frame_id: str = "camera", overwrite: bool = False,
                    progress: bool = False, **overrides: Any) -> SceneBagSummary:
    """Render one scene and write it as an MCAP rosbag2 directory.

    Args:
        path: Bag directory to create.
        seed: Renderer seed; the same arguments always give the same bag content.
        n_frames: Number of frames; or give ``duration_s`` instead (default 10 s).
        duration_s: Length in seconds (frames = round(duration * fps)).
        fps: Frame rate, or None for the renderer's random choice.
        width: Image width.
        height: Image height.
        n_vehicles: Number of vehicles, or None for the renderer's choice.
        lighting: "day", "dusk", "night", or None for a random one (see ``night_fraction``).
        night_fraction: Share of dark scenes when ``lighting`` is None.
        raw: Write ``sensor_msgs/Image`` bgr8 instead of JPEG ``CompressedImage``.
        jpeg_quality: JPEG quality 1..100.
        frame_id: ``header.frame_id`` of every message.
        overwrite: Replace an existing bag at ``path``.
        progress: Show a tqdm progress bar.
        **overrides: Further ``SceneRenderer`` parameters.

    Returns:
        A summary of what was written.

    Raises:
        ConfigError: Conflicting or out-of-range options.
        BagIOError: The bag cannot be written.
    """
    from signal_light_node.synth import SceneRenderer  # heavy; only when rendering

    if n_frames is not None and duration_s is not None:
        raise ConfigError("give either n_frames or duration_s, not both")
    if not 1 <= int(jpeg_quality) <= 100:
        raise ConfigError(f"jpeg_quality must be in 1..100, got {jpeg_quality}")
    if night_fraction is not None:  # else the renderer's default share
        overrides["night_fraction"] = night_fraction
    renderer = SceneRenderer(seed, width=width, height=height, fps=fps, n_vehicles=n_vehicles,
                             lighting=lighting, **overrides)
    if n_frames is None:
        n_frames = int(round((10.0 if duration_s is None else float(duration_s)) * renderer.fps))
    if n_frames < 1:
        raise ConfigError(f"a bag needs at least one frame, got {n_frames}")
    image_topic, image_type = (IMAGE_TOPIC, IMAGE_TYPE) if raw else (COMPRESSED_TOPIC,
                                                                      COMPRESSED_TYPE)
    make = bagio.make
    summary = SceneBagSummary(Path(path), 0, float(renderer.fps), int(width), int(height), "")
    observed: Counter = Counter()
    with bagio.BagWriter(path, overwrite=overwrite) as bag:
        for topic, msgtype in ((image_topic, image_type), (DETECTIONS_TOPIC, DETECTIONS_TYPE),
                               (GROUND_TRUTH_TOPIC, VEHICLE_LIGHTS_TYPE)):
            bag.add_topic(topic, msgtype)
        frames = renderer.frames(n_frames)
        for frame in tqdm(frames, total=n_frames, desc=f"synth {summary.path.name}",
                          unit="frame", disable=not progress):
            stamp = int(frame.stamp_ns)
            header = make_header(stamp, frame_id, make)
            h, w = frame.image.shape[:2]
            fields = (bgr_to_image_fields(frame.image) if raw
                      else bgr_to_compressed_fields(frame.image, "jpeg", jpeg_quality))
            boxes: List[TrackBox] = []
            truths: List[VehicleResult] = []
            for vehicle in frame.vehicles:
                box = vehicle.tracker_box
                if box is None:
                    continue  # the tracker missed it: absent from this frame's detections
                if not box.class_id:
                    box = dataclasses.replace(box, class_id=str(vehicle.class_id))
                observed[vehicle.track_id] += 1
                boxes.append(box)
                truths.append(truth_result(vehicle, box, w, h, observed[vehicle.track_id]))
            bag.write(image_topic, stamp, make(image_type, header=header, **fields))
            bag.write(DETECTIONS_TOPIC, stamp, boxes_to_detections(header, boxes, make))
            bag.write(GROUND_TRUTH_TOPIC, stamp, vehicle_light_array(header, truths, make))
            summary.frames += 1
            summary.lighting = summary.lighting or frame.lighting
            summary.detections += len(boxes)
            summary.track_ids.update(b.track_id for b in boxes)
    LOG.info("wrote %s: %d frames at %.1f Hz, %d tracks, %s", summary.path, summary.frames,
             summary.fps, len(summary.track_ids), summary.lighting)
    return summary


def ground_truth_coverage(path: "str | os.PathLike[str]") -> Dict[str, Any]:
    """Count what the ground truth of a bag covers (for choosing and checking bags).

    Args:
        path: A bag with ``/ground_truth/vehicle_lights``.

    Returns:
        ``{"frames", "duration_s", "tracks", "views": {name: n}, "intents": {name: n},
        "brake": {name: n}, "left": ..., "right": ...}`` counted over all vehicle entries.
    """
    counts: Dict[str, Counter] = {k: Counter() for k in ("views", "intents", "brake", "left",
                                                          "right")}
    tracks: Set[str] = set()
    frames = 0
    first = last = None
    with bagio.open_bag(path) as bag:
        for item in bag.messages([GROUND_TRUTH_TOPIC]):
            frames += 1
            first = item.log_time_ns if first is None else first
            last = item.log_time_ns
            for v in item.msg.vehicles:
                tracks.add(str(v.track_id))
                counts["views"][View(int(v.view)).name] += 1
                counts["intents"][Intent(int(v.intent)).name] += 1
                counts["brake"][LightStatus(int(v.brake.state)).name] += 1
                counts["left"][LightStatus(int(v.left_blinker.state)).name] += 1
                counts["right"][LightStatus(int(v.right_blinker.state)).name] += 1
    duration = (last - first) / 1e9 if frames > 1 else 0.0
    out: Dict[str, Any] = {"frames": frames, "duration_s": duration, "tracks": len(tracks)}
    out.update({k: dict(sorted(c.items())) for k, c in counts.items()})
    return out


#: What a test bag's ground truth must contain (``coverage_gaps``).
REQUIRED_CLASSES: Dict[str, List[str]] = {
    "views": [v.name for v in View],
    "intents": [i.name for i in Intent],
    "brake": [LightStatus.ON.name, LightStatus.OFF.name],
}


def coverage_gaps(coverage: Dict[str, Any], min_tracks: int = 4) -> List[str]:
    """What a coverage dict (:func:`ground_truth_coverage`) lacks for a test bag.

    Args:
        coverage: Counts with at least ``tracks``, ``views``, ``intents`` and ``brake``.
        min_tracks: Fewest distinct tracks required.

    Returns:
        One ``"key=NAME"`` entry per required class that never occurs, plus a note when
        there are too few tracks; empty when the bag covers everything.
    """
    gaps = [f"{key}={name}" for key, names in REQUIRED_CLASSES.items() for name in names
            if coverage[key].get(name, 0) == 0]
    if coverage["tracks"] < min_tracks:
        gaps.append(f"tracks={coverage['tracks']}<{min_tracks}")
    return gaps
