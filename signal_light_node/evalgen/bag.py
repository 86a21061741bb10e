"""Write an evaluation scene as an MCAP rosbag2 bag laid out like the project's scene bags.

Topics (log time = the image's stamp, every message with the image's header):
``/camera/image_raw/compressed`` (JPEG ``CompressedImage``), ``/camera/tracked_objects``
(``Detection2DArray``, ``id`` = track ID, class in ``results[0]``) and
``/ground_truth/vehicle_lights`` (``VehicleLightStateArray``: one entry per detection, same
order, probability 1 on the true states), so that ``signal-light replay`` scores it.
"""

from __future__ import annotations

import logging
import math
import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, List, Optional, Set, Tuple

from signal_light_node.io import bagio
from signal_light_node.boxes import TrackBox
from signal_light_node.io.conversions import boxes_to_detections, make_header
from signal_light_node.errors import ConfigError
from signal_light_node.evalgen.config import SceneConfig
from signal_light_node.evalgen.scene import EvalScene
from signal_light_node.evalgen.truth import EvalFrame, VehicleTruth
from signal_light_node.io.image_codec import bgr_to_compressed_fields
from signal_light_node.labels import LIGHT_CODES, LightStatus
from signal_light_node.outputs.vehicle_lights import vehicle_light_array
from signal_light_node.runtime.results import LightEstimate, VehicleResult
from signal_light_node.io.topics import (COMPRESSED_TYPE, DETECTIONS_TYPE, GROUND_TRUTH_TOPIC,
                                      VEHICLE_LIGHTS_TYPE)
from signal_light_node.io.topics import CAMERA_COMPRESSED_TOPIC as IMAGE_TOPIC
from signal_light_node.io.topics import TRACKED_OBJECTS_TOPIC as DETECTIONS_TOPIC

LOG = logging.getLogger(__name__)


@dataclass
class EvalBagSummary:
    """What :func:`write_eval_bag` wrote.

    Attributes:
        path: Bag directory.
        frames: Images written.
        detections: Detections over all frames.
        track_ids: Every track ID in the detections.
    """

    path: Path
    frames: int = 0
    detections: int = 0
    track_ids: Set[str] = field(default_factory=set)


def roi_of(box: TrackBox, width: int, height: int) -> Tuple[int, int, int, int]:
    """``(x, y, w, h)`` of the box clipped to the image, edges rounded outwards; zero if empty."""
    if not box.is_finite:
        return 0, 0, 0, 0
    x0 = min(max(math.floor(box.x0), 0), width)
    y0 = min(max(math.floor(box.y0), 0), height)
    x1 = min(max(math.ceil(box.x1), 0), width)
    y1 = min(max(math.ceil(box.y1), 0), height)
    if x1 <= x0 or y1 <= y0:
        return 0, 0, 0, 0
    return x0, y0, x1 - x0, y1 - y0


def truth_entry(truth: VehicleTruth, box: TrackBox, width: int, height: int,
                frames_observed: int) -> VehicleResult:
    """One vehicle's truth as a one-hot result (what the ground-truth topic carries).

    Args:
        truth: The vehicle's truth.
        box: Its tracker box.
        width: Image width.
        height: Image height.
        frames_observed: Frames this track has been detected so far, this one included.
    """
    lights = {"brake": truth.brake, "left": truth.left, "right": truth.right}
    return VehicleResult(
        track_id=truth.track_id, roi=roi_of(box, width, height),
        brake=LightEstimate.certain(truth.brake), left=LightEstimate.certain(truth.left),
        right=LightEstimate.certain(truth.right), intent=truth.intent, intent_probability=1.0,
        view=truth.view, view_probability=1.0,
        classification=tuple((LIGHT_CODES[k], 1.0) for k, v in lights.items()
                             if v == LightStatus.ON),
        frames_observed=frames_observed, judged=True)


def write_eval_bag(path: "str | os.PathLike[str]", seed: int,
                   config: SceneConfig = SceneConfig(), *, jpeg_quality: int = 80,
                   frame_id: str = "camera", overwrite: bool = False,
                   on_frame: Optional[Callable[[EvalFrame], None]] = None) -> EvalBagSummary:
    """Generate a scene and write it as a bag.

    Args:
        path: Bag directory to create.
        seed: Scene seed.
        config: What to generate.
        jpeg_quality: JPEG quality 1..100.
        frame_id: ``header.frame_id`` of every message.
        overwrite: Replace an existing bag.
        on_frame: Called with every frame after it is written (previews, progress).

    Returns:
        A summary.

    Raises:
        ConfigError: Bad options.
        BagIOError: The bag cannot be written.
    """
    if not 1 <= int(jpeg_quality) <= 100:
        raise ConfigError(f"jpeg_quality must be in 1..100, got {jpeg_quality}")
    scene = EvalScene(seed, config)
    make = bagio.make
    summary = EvalBagSummary(Path(path))
    observed: Counter = Counter()
    with bagio.BagWriter(path, overwrite=overwrite) as bag:
        for topic, msgtype in ((IMAGE_TOPIC, COMPRESSED_TYPE), (DETECTIONS_TOPIC, DETECTIONS_TYPE),
                               (GROUND_TRUTH_TOPIC, VEHICLE_LIGHTS_TYPE)):
            bag.add_topic(topic, msgtype)
        for frame in scene.frames():
            header = make_header(frame.stamp_ns, frame_id, make)
            boxes: List[TrackBox] = []
            truths: List[VehicleResult] = []
            for truth in frame.vehicles:
                if truth.tracker_box is None:
                    continue
                observed[truth.track_id] += 1
                boxes.append(truth.tracker_box)
                truths.append(truth_entry(truth, truth.tracker_box, config.width, config.height,
                                          observed[truth.track_id]))
            fields = bgr_to_compressed_fields(frame.image, "jpeg", int(jpeg_quality))
            bag.write(IMAGE_TOPIC, frame.stamp_ns, make(COMPRESSED_TYPE, header=header, **fields))
            bag.write(DETECTIONS_TOPIC, frame.stamp_ns, boxes_to_detections(header, boxes, make))
            bag.write(GROUND_TRUTH_TOPIC, frame.stamp_ns, vehicle_light_array(header, truths, make))
            summary.frames += 1
            summary.detections += len(boxes)
            summary.track_ids.update(b.track_id for b in boxes)
            if on_frame is not None:
                on_frame(frame)
    LOG.info("wrote %s: %d frames, %d tracks", summary.path, summary.frames, len(summary.track_ids))
    return summary
