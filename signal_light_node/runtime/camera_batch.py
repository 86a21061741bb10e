"""Several cameras' frames through the engine in ONE batched model step.

``LightStateEngine.process_many`` (:mod:`signal_light_node.runtime.engine`) lands here. Per frame it does what ``process`` does (drop repeated track IDs, keep at most
``max_boxes`` boxes, crop with the shared crop code, check the camera's stamp), then
gathers the tracks of every frame from the state bank at once (keyed by camera and track
ID, each camera with its own clock: :meth:`StateBank.gather_cameras
<signal_light_node.runtime.state_bank.StateBank.gather_cameras>`), runs ONE backend step
over all their crops, the intent filter with each row's own frame stamp, stores the new
states and splits the probabilities back into one
:class:`~signal_light_node.runtime.engine.FrameResult` per frame. Nothing here imports
rclpy or torch.

When the cameras' tracks do not compete for rows (``max_tracks``), every frame's result
equals what ``process`` on an engine of that camera alone would give (up to the
backend's float rounding across batch sizes).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Dict, List, NamedTuple, Optional, Sequence

import numpy as np

from signal_light_node.boxes import TrackBox
from signal_light_node.errors import ConfigError, CropError
from signal_light_node.runtime.crops import crop_vehicles
from signal_light_node.runtime.results import VehicleResult
from signal_light_node.runtime.state_bank import CAMERA_COUNTERS

if TYPE_CHECKING:  # the engine imports this module lazily
    from signal_light_node.runtime.engine import FrameResult, LightStateEngine


class CameraFrame(NamedTuple):
    """One camera's frame for :meth:`LightStateEngine.process_many`.

    A plain ``(camera, image, stamp_ns, boxes)`` tuple is accepted as well.

    Attributes:
        camera: The camera's name (keys its tracks and its stamp clock).
        image: The frame, HxWx3 uint8 BGR.
        stamp_ns: The frame's stamp (header stamp) in nanoseconds.
        boxes: Tracked boxes; ``track_id`` (with the camera) keys the recurrent state.
    """

    camera: str
    image: np.ndarray
    stamp_ns: int
    boxes: Sequence[TrackBox]


@dataclass
class _Prepared:
    """One frame after cropping: what goes into the shared step, and what does not."""

    frame: CameraFrame
    width: int
    height: int
    warnings: List[str] = field(default_factory=list)
    first_index: Dict[str, int] = field(default_factory=dict)
    unique: List[int] = field(default_factory=list)
    over: Dict[int, str] = field(default_factory=dict)
    reasons: List[Optional[str]] = field(default_factory=list)
    valid: List[int] = field(default_factory=list)
    ids: List[str] = field(default_factory=list)
    crops: Optional[np.ndarray] = None
    unusable: Optional[str] = None


def process_many(engine: "LightStateEngine", frames: Sequence[object]) -> List["FrameResult"]:
    """Judge several cameras' frames with one backend step (see the module docstring).

    Args:
        engine: The engine (its state bank, backend, filter and counters are used).
        frames: :class:`CameraFrame` s or ``(camera, image, stamp_ns, boxes)`` tuples. A
            camera that appears again starts another step, so each camera's frames are
            judged in the given order.

    Returns:
        One result per frame, in order; ``latency_s`` of each is the wall time of the step
        it was part of (crops, step and results of every frame of it).

    Raises:
        ConfigError: A frame is not ``(camera, image, stamp_ns, boxes)`` or its camera is
            not a string.
    """
    items = [_camera_frame(f) for f in frames]
    out: List["FrameResult"] = []
    group: List[CameraFrame] = []
    for item in items:
        if any(g.camera == item.camera for g in group):
            out += _one_step(engine, group)
            group = []
        group.append(item)
    if group:
        out += _one_step(engine, group)
    return out


def camera_counters(engine: "LightStateEngine") -> Dict[str, Dict[str, int]]:
    """Per camera the state bank's counters (created, expired, evictions, overflow,
    resets) and its ``active_tracks``; the single-camera engine's camera is ``""``."""
    bank = engine.bank
    out: Dict[str, Dict[str, int]] = {}
    for camera in sorted(set(bank.camera_counters) | set(bank.cameras)):
        counts = bank.camera_counters.get(camera, {})
        out[camera] = {name: int(counts.get(name, 0)) for name in CAMERA_COUNTERS}
        out[camera]["active_tracks"] = bank.count(camera)
    return out


def unjudged_camera_frame(engine: "LightStateEngine", camera: str, stamp_ns: int,
                          boxes: Sequence[TrackBox], width: int, height: int,
                          reason: str) -> "FrameResult":
    """``engine.unjudged_frame`` for a camera's frame: every box unjudged, its
    ``frames_observed`` the camera's own, no state changed."""
    from signal_light_node.runtime.engine import FrameResult, unjudged_result

    results = [unjudged_result(box, width, height,
                               engine.bank.frames_observed(box.track_id, camera))
               for box in boxes]
    return FrameResult(int(stamp_ns), results, [reason], 0.0, 0)


# ------------------------------------------------------------------ internals
def _camera_frame(frame: object) -> CameraFrame:
    if isinstance(frame, CameraFrame):
        item = frame
    else:
        try:
            item = CameraFrame(*frame)  # type: ignore[misc]
        except TypeError:
            raise ConfigError(f"process_many takes (camera, image, stamp_ns, boxes) per frame, "
                              f"got {type(frame).__name__}") from None
    if not isinstance(item.camera, str):
        raise ConfigError(f"a frame's camera must be a name (str), got {item.camera!r}")
    return item._replace(stamp_ns=int(item.stamp_ns))


def _prepare(engine: "LightStateEngine", frame: CameraFrame) -> _Prepared:
    """What ``process`` does before the step: unique IDs, the box limit, the crops."""
    image, boxes = frame.image, frame.boxes
    height, width = image.shape[:2] if isinstance(image, np.ndarray) and image.ndim == 3 \
        else (0, 0)
    prep = _Prepared(frame, width, height)
    for i, box in enumerate(boxes):
        if box.track_id in prep.first_index:
            continue
        prep.first_index[box.track_id] = i
        prep.unique.append(i)
    limit = engine.config.max_boxes
    prep.over = {i: f"over the limit of {limit} boxes per frame" for i in prep.unique[limit:]}
    prep.unique = prep.unique[:limit]
    try:
        crops, prep.reasons = crop_vehicles(image, [boxes[i] for i in prep.unique], engine.crop)
    except CropError as exc:  # this camera's image is unusable; the others go on
        prep.unusable = f"image of camera {frame.camera!r} not usable: {exc}"
        return prep
    prep.valid = [k for k, reason in enumerate(prep.reasons) if reason is None]
    prep.ids = [boxes[prep.unique[k]].track_id for k in prep.valid]
    prep.crops = crops if len(prep.valid) == len(crops) else crops[prep.valid]
    return prep


def _one_step(engine: "LightStateEngine", frames: Sequence[CameraFrame]) -> List["FrameResult"]:
    """At most one frame per camera: one gather, one backend step, one store."""
    from signal_light_node.runtime.engine import (_RESET_TEXT, FrameResult, _box_key,
                                                  _FrameAttention, _ProbTable)

    start = time.perf_counter()
    bank = engine.bank
    prepared = [_prepare(engine, frame) for frame in frames]
    usable = [p for p in prepared if p.unusable is None]
    for p in usable:
        reason = bank.check_stamp(p.frame.stamp_ns, p.frame.camera)
        if reason is not None:
            p.warnings.append(f"track states of camera {p.frame.camera!r} reset at stamp "
                              f"{p.frame.stamp_ns}: {_RESET_TEXT.get(reason, reason)}")
    batch = bank.gather_cameras([(p.frame.camera, p.ids, p.frame.stamp_ns) for p in usable])
    engine._frame_attention = None
    table: Optional[_ProbTable] = None
    if len(batch):
        crops = np.concatenate([p.crops for p in usable if p.ids])
        step = engine.backend.step(crops, batch.state, attention=engine.keep_attention)
        engine._counts["model_steps"] += 1
        filtered = engine.filter.step(step.probs, batch.stamps_ns, batch.filter_rows)
        frames_observed = bank.store_cameras(batch, step.state, filtered.rows)
        table = _ProbTable(filtered.probs, filtered.states)
        if step.attention is not None:
            engine._frame_attention = _ImagesAttention(_FrameAttention, usable, step.attention,
                                                       _box_key)
    else:
        frames_observed = bank.store_cameras(batch, batch.state)

    results: List[List[VehicleResult]] = []
    offset = 0
    for p in prepared:
        if p.unusable is not None:
            results.append(_unjudged_all(engine, p))
            continue
        results.append(_frame_results(engine, p, table, offset, frames_observed))
        offset += len(p.ids)
    latency = time.perf_counter() - start
    return [FrameResult(p.frame.stamp_ns, res, p.warnings, latency,
                        0 if p.unusable is not None else len(p.ids))
            for p, res in zip(prepared, results)]


def _frame_results(engine: "LightStateEngine", p: _Prepared, table: object, offset: int,
                   frames_observed: np.ndarray) -> List[VehicleResult]:
    """``process``'s results of one frame, its rows starting at ``offset`` of the step."""
    from signal_light_node.runtime.engine import unjudged_result

    boxes, camera = p.frame.boxes, p.frame.camera
    row_of = {p.unique[k]: offset + j for j, k in enumerate(p.valid)}
    reason_of = {i: p.reasons[k] for k, i in enumerate(p.unique)}
    reason_of.update(p.over)
    out: List[VehicleResult] = []
    n_dup = n_bad = 0
    for i, box in enumerate(boxes):
        j = row_of.get(i)
        if j is not None:
            out.append(engine._judged(box, p.width, p.height, table, j, int(frames_observed[j])))
            continue
        if p.first_index[box.track_id] != i:
            n_dup += 1
            p.warnings.append(f"duplicate track ID {box.track_id!r} at box {i} (first at box "
                              f"{p.first_index[box.track_id]}); reported unjudged")
        else:
            n_bad += 1
            if i not in p.over:
                p.warnings.append(f"box {i} not judged: {reason_of[i]}")
        out.append(unjudged_result(box, p.width, p.height,
                                   engine.bank.frames_observed(box.track_id, camera)))
    if p.over:
        p.warnings.append(f"{len(p.over)} boxes not judged: {p.over[min(p.over)]}")
    counts = engine._counts
    counts["frames"] += 1
    counts["boxes"] += len(boxes)
    counts["judged"] += len(p.ids)
    counts["unjudged"] += n_bad + n_dup
    counts["duplicates"] += n_dup
    counts["over_limit"] += len(p.over)
    return out


def _unjudged_all(engine: "LightStateEngine", p: _Prepared) -> List[VehicleResult]:
    """Every box of a frame whose image is unusable, unjudged (no state changes)."""
    from signal_light_node.runtime.engine import unjudged_result

    p.warnings.append(p.unusable or "image not usable")
    return [unjudged_result(box, p.width, p.height,
                            engine.bank.frames_observed(box.track_id, p.frame.camera))
            for box in p.frame.boxes]


class _ImagesAttention:
    """The attention masks of one shared step, per image (for ``attention_masks``)."""

    def __init__(self, frame_attention: type, prepared: Sequence[_Prepared],
                 masks: np.ndarray, box_key: object) -> None:
        self._frames = []
        offset = 0
        for p in prepared:
            boxes = p.frame.boxes
            own = masks[offset:offset + len(p.ids)]
            offset += len(p.ids)
            self._frames.append(frame_attention(
                p.frame.image, {box_key(boxes[p.unique[k]]): mask  # type: ignore[operator]
                                for k, mask in zip(p.valid, own)}))

    def masks_for(self, image: np.ndarray) -> Dict[tuple, np.ndarray]:
        """The masks kept for ``image`` (the very array), else none."""
        for frame in self._frames:
            if frame.image() is image:
                return frame.masks
        return {}
