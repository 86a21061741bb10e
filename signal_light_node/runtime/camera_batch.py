"""The engine's one frame path: one or more cameras' frames through ONE batched model step.

:class:`FramePath` is what ``LightStateEngine.process`` (one frame: a one-camera step of
the camera ``""``) and ``LightStateEngine.process_many`` (one frame per camera) both run
(:mod:`signal_light_node.runtime.engine`). Per frame it drops repeated track IDs, keeps at
most ``max_boxes`` boxes, crops with the shared crop code and checks the camera's stamp;
then it gathers the tracks of every frame from the state bank at once (keyed by camera
and track ID, each camera with its own clock: :meth:`StateBank.gather_cameras
<signal_light_node.runtime.state_bank.StateBank.gather_cameras>`), runs ONE backend step
over all their crops, the intent filter with each row's own frame stamp, stores the new
states and splits the probabilities back into one :class:`FrameResult` per frame, with its
warnings and the engine's counters. Nothing here imports rclpy or torch, nor the engine.

When the cameras' tracks do not compete for rows (``max_tracks``), every frame's result
equals what ``process`` on an engine of that camera alone would give (up to the
backend's float rounding across batch sizes).
"""

from __future__ import annotations

import logging
import time
import weakref
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple

import numpy as np

from signal_light_node.boxes import TrackBox
from signal_light_node.errors import ConfigError, CropError
from signal_light_node.labels import LIGHT_CODES, LIGHT_TASKS, Intent, LightStatus, View
from signal_light_node.runtime import box_sight, flash_gate
from signal_light_node.runtime.crops import CropConfig, clip_roi, crop_vehicles
from signal_light_node.runtime.intent_filter import IntentFilter
from signal_light_node.runtime.results import LightEstimate, VehicleResult
from signal_light_node.runtime.state_bank import StateBank

LOG = logging.getLogger(__name__)

#: Stages of a step, in order, as keyed in ``FrameResult.stages_s``: cropping every box,
#: gathering the tracks' states (and intent-filter rows) from the state bank, the
#: backend's batched step, the intent filter, storing the new states, and turning the
#: probabilities into results.
ENGINE_STAGES: Tuple[str, ...] = ("crops", "state_gather", "step", "intent_filter",
                                  "state_store", "results")

#: The frame path's running totals (``LightStateEngine.counters`` adds the state bank's).
FRAME_COUNTERS: Tuple[str, ...] = ("frames", "boxes", "judged", "unjudged", "duplicates",
                                   "over_limit", "model_steps")

_RESET_TEXT = {"stamp_backwards": "the stamp jumped backwards (bag looped?)",
               "stamp_gap": "the stamp jumped forward by more than max_gap_s"}


class CameraFrame(NamedTuple):
    """One camera's frame for :meth:`LightStateEngine.process_many`.

    A plain ``(camera, image, stamp_ns, boxes)`` tuple is accepted as well.

    Attributes:
        camera: The camera's name (keys its tracks and its stamp clock); ``""`` for
            ``process``.
        image: The frame, HxWx3 uint8 BGR.
        stamp_ns: The frame's stamp (header stamp) in nanoseconds.
        boxes: Tracked boxes; ``track_id`` (with the camera) keys the recurrent state.
    """

    camera: str
    image: np.ndarray
    stamp_ns: int
    boxes: Sequence[TrackBox]


@dataclass(frozen=True)
class FrameResult:
    """What the engine made of one frame.

    Attributes:
        stamp_ns: The frame's stamp.
        results: One result per input box, in input order.
        warnings: Why boxes were not judged, duplicates, state resets (also counted).
        latency_s: Wall time of the step the frame was part of (``process``: its own).
        n_judged: Boxes that went through the model.
        stages_s: Wall time of each stage of that step (:data:`ENGINE_STAGES`), in
            seconds; they add up to ``latency_s`` but for the bookkeeping between them.
            Empty for a frame that was not processed (``unjudged_frame``).
    """

    stamp_ns: int
    results: List[VehicleResult]
    warnings: List[str]
    latency_s: float
    n_judged: int
    stages_s: Dict[str, float] = field(default_factory=dict)


def unjudged_result(box: TrackBox, width: int, height: int,
                    frames_observed: int = 0) -> VehicleResult:
    """The result of a box that could not be judged: every light UNKNOWN with P(ON) = 0."""
    return VehicleResult(
        track_id=box.track_id, roi=clip_roi(box, width, height),
        brake=LightEstimate.unjudged(), left=LightEstimate.unjudged(),
        right=LightEstimate.unjudged(), intent=Intent.UNKNOWN, intent_probability=0.0,
        view=View.BEHIND, view_probability=0.0, classification=(),
        frames_observed=frames_observed, judged=False)


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
    cover: Optional[np.ndarray] = None
    unusable: Optional[str] = None


class FramePath:
    """Frames in, one batched backend step, one :class:`FrameResult` per frame out.

    Not thread-safe; each camera's frames in stamp order (a stamp that jumps back resets
    that camera's tracks, as when a bag loops).

    Args:
        backend: The model backend (``runtime.backend.ModelBackend``).
        bank: The state bank of the backend's states (and the filter's rows).
        intent_filter: The hold over the model's light outputs.
        crop: Crop size and margin (the model's input size).
        max_boxes: Boxes judged per frame; later ones are reported unjudged (``over_limit``).
        thresholds: ON-probability per light code from which a light goes into
            ``classification`` (every code of ``LIGHT_CODES``).

    Attributes:
        counts: Running totals (:data:`FRAME_COUNTERS`).
        keep_attention: Keep the attention masks of each step (:meth:`kept_mask`).
    """

    def __init__(self, backend: Any, bank: StateBank, intent_filter: IntentFilter,
                 crop: CropConfig, max_boxes: int, thresholds: Mapping[int, float]) -> None:
        self.backend = backend
        self.bank = bank
        self.filter = intent_filter
        self.crop = crop
        self.max_boxes = max_boxes
        self._thresholds = [(task, LIGHT_CODES[task], thresholds[LIGHT_CODES[task]])
                            for task in LIGHT_TASKS]
        self.counts: Dict[str, int] = {name: 0 for name in FRAME_COUNTERS}
        self.keep_attention = False
        self._attention: Optional[_StepAttention] = None

    def run(self, frames: Sequence[object], strict: bool = False) -> List[FrameResult]:
        """Judge the frames, one step per run of frames of distinct cameras.

        Args:
            frames: :class:`CameraFrame` s or ``(camera, image, stamp_ns, boxes)`` tuples. A
                camera that appears again starts another step, so each camera's frames are
                judged in the given order.
            strict: Raise on an image that is not an HxWx3 uint8 array (``process``);
                otherwise that frame is answered unjudged with a warning and the others
                go on.

        Returns:
            One result per frame, in order.

        Raises:
            ConfigError: A frame is not ``(camera, image, stamp_ns, boxes)`` or its camera
                is not a string.
            CropError: ``strict`` and an image is unusable.
        """
        items = [_camera_frame(f) for f in frames]
        out: List[FrameResult] = []
        group: List[CameraFrame] = []
        for item in items:
            if any(g.camera == item.camera for g in group):
                out += self._one_step(group, strict)
                group = []
            group.append(item)
        if group:
            out += self._one_step(group, strict)
        return out

    def unjudged(self, camera: str, stamp_ns: int, boxes: Sequence[TrackBox], width: int,
                 height: int, reason: str) -> FrameResult:
        """A frame answered without a step: every box unjudged with its camera's
        ``frames_observed``, ``reason`` its warning; no state changes."""
        return FrameResult(int(stamp_ns), self._unjudged_all(camera, boxes, width, height),
                           [reason], 0.0, 0)

    def kept_mask(self, image: np.ndarray, box: TrackBox) -> Optional[np.ndarray]:
        """The attention mask the last step computed for ``box`` of ``image`` (the very
        array), or None."""
        if self._attention is None:
            return None
        return self._attention.masks_for(image).get(_box_key(box))

    # --------------------------------------------------------------- the step
    def _one_step(self, frames: Sequence[CameraFrame], strict: bool) -> List[FrameResult]:
        """At most one frame per camera: one gather, one backend step, one store."""
        clock = time.perf_counter
        start = clock()
        bank = self.bank
        prepared = [self._prepare(frame, strict) for frame in frames]
        usable = [p for p in prepared if p.unusable is None]
        t_crops = clock()
        for p in usable:
            reason = bank.check_stamp(p.frame.stamp_ns, p.frame.camera)
            if reason is not None:
                whose = f"track states of camera {p.frame.camera!r}" if p.frame.camera \
                    else "all track states"
                p.warnings.append(f"{whose} reset at stamp {p.frame.stamp_ns}: "
                                  f"{_RESET_TEXT.get(reason, reason)}")
        batch = bank.gather_cameras([(p.frame.camera, p.ids, p.frame.stamp_ns) for p in usable])
        t_gather = clock()
        self._attention = None
        table: Optional[_ProbTable] = None
        if len(batch):
            parts = [p.crops for p in usable if p.ids]
            crops = parts[0] if len(parts) == 1 else np.concatenate(parts)
            step = self.backend.step(crops, batch.state, attention=self.keep_attention)
            self.counts["model_steps"] += 1
            t_step = clock()
            levels = flash_gate.lamp_levels(crops) if self.filter.gates_flashes else None
            cover = (np.concatenate([p.cover for p in usable if p.ids])
                     if self.filter.uses_cover else None)
            filtered = self.filter.step(step.probs, batch.stamps_ns, batch.filter_rows, levels,
                                        cover)
            t_filter = clock()
            frames_observed = bank.store_cameras(batch, step.state, filtered.rows)
            table = _ProbTable(filtered.probs, filtered.states)
            if step.attention is not None:
                self._attention = _StepAttention(usable, step.attention)
        else:
            t_step = t_filter = t_gather  # no step
            frames_observed = bank.store_cameras(batch, batch.state)
        t_store = clock()
        results: List[List[VehicleResult]] = []
        offset = 0
        for p in prepared:
            if p.unusable is not None:
                p.warnings.append(p.unusable)
                results.append(self._unjudged_all(p.frame.camera, p.frame.boxes, p.width,
                                                  p.height))
                continue
            results.append(self._frame_results(p, table, offset, frames_observed))
            offset += len(p.ids)
        for p in prepared:
            for text in p.warnings:
                LOG.debug("%s", text)
        end = clock()
        stages = dict(zip(ENGINE_STAGES, (t_crops - start, t_gather - t_crops, t_step - t_gather,
                                          t_filter - t_step, t_store - t_filter, end - t_store)))
        return [FrameResult(p.frame.stamp_ns, res, p.warnings, end - start,
                            0 if p.unusable is not None else len(p.ids), stages)
                for p, res in zip(prepared, results)]

    def _prepare(self, frame: CameraFrame, strict: bool) -> _Prepared:
        """Before the step: unique IDs, the box limit, the crops."""
        image, boxes = frame.image, frame.boxes
        height, width = image.shape[:2] if isinstance(image, np.ndarray) and image.ndim == 3 \
            else (0, 0)
        prep = _Prepared(frame, width, height)
        for i, box in enumerate(boxes):
            if box.track_id in prep.first_index:
                continue
            prep.first_index[box.track_id] = i
            prep.unique.append(i)
        limit = self.max_boxes
        prep.over = {i: f"over the limit of {limit} boxes per frame" for i in prep.unique[limit:]}
        prep.unique = prep.unique[:limit]
        try:
            crops, prep.reasons = crop_vehicles(image, [boxes[i] for i in prep.unique], self.crop)
        except CropError as exc:  # this camera's image is unusable; the others go on
            if strict:
                raise
            prep.unusable = f"image of camera {frame.camera!r} not usable: {exc}"
            return prep
        prep.valid = [k for k, reason in enumerate(prep.reasons) if reason is None]
        prep.ids = [boxes[prep.unique[k]].track_id for k in prep.valid]
        prep.crops = crops if len(prep.valid) == len(crops) else crops[prep.valid]
        if self.filter.uses_cover:  # every box of the frame can hide the others
            cover = box_sight.box_cover(box_sight.boxes_array(boxes), width, height)
            prep.cover = cover[[prep.unique[k] for k in prep.valid]]
        return prep

    def _frame_results(self, p: _Prepared, table: Optional["_ProbTable"], offset: int,
                       frames_observed: np.ndarray) -> List[VehicleResult]:
        """One frame's results, its rows starting at ``offset`` of the step; counted."""
        boxes, camera = p.frame.boxes, p.frame.camera
        row_of = {p.unique[k]: offset + j for j, k in enumerate(p.valid)}
        reason_of = {i: p.reasons[k] for k, i in enumerate(p.unique)}
        reason_of.update(p.over)
        out: List[VehicleResult] = []
        n_dup = n_bad = 0
        for i, box in enumerate(boxes):
            j = row_of.get(i)
            if j is not None:
                assert table is not None
                out.append(self._judged(box, p.width, p.height, table, j,
                                        int(frames_observed[j])))
                continue
            if p.first_index[box.track_id] != i:
                n_dup += 1
                p.warnings.append(f"duplicate track ID {box.track_id!r} at box {i} (first at "
                                  f"box {p.first_index[box.track_id]}); reported unjudged")
            else:
                n_bad += 1
                if i not in p.over:
                    p.warnings.append(f"box {i} not judged: {reason_of[i]}")
            out.append(unjudged_result(box, p.width, p.height,
                                       self.bank.frames_observed(box.track_id, camera)))
        if p.over:
            p.warnings.append(f"{len(p.over)} boxes not judged: {p.over[min(p.over)]}")
        counts = self.counts
        counts["frames"] += 1
        counts["boxes"] += len(boxes)
        counts["judged"] += len(p.ids)
        counts["unjudged"] += n_bad + n_dup
        counts["duplicates"] += n_dup
        counts["over_limit"] += len(p.over)
        return out

    def _judged(self, box: TrackBox, width: int, height: int, table: "_ProbTable",
                j: int, frames_observed: int) -> VehicleResult:
        lights = {}
        classification: List[Tuple[int, float]] = []
        for task, code, threshold in self._thresholds:
            off, on, unknown = table.rows[task][j][:3]
            lights[task] = LightEstimate(LightStatus(table.best[task][j]), off, on, unknown)
            if on >= threshold:
                classification.append((code, on))
        intent, view = table.best["intent"][j], table.best["view"][j]
        return VehicleResult(
            track_id=box.track_id, roi=clip_roi(box, width, height),
            brake=lights["brake"], left=lights["left"], right=lights["right"],
            intent=Intent(intent), intent_probability=table.rows["intent"][j][intent],
            view=View(view), view_probability=table.rows["view"][j][view],
            classification=tuple(classification), frames_observed=frames_observed, judged=True)

    def _unjudged_all(self, camera: str, boxes: Sequence[TrackBox], width: int,
                      height: int) -> List[VehicleResult]:
        """Every box unjudged, with its camera's ``frames_observed`` (no state changes)."""
        return [unjudged_result(box, width, height, self.bank.frames_observed(box.track_id, camera))
                for box in boxes]


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


def _box_key(box: TrackBox) -> tuple:
    """What decides a box's crop within one image."""
    return (box.track_id, box.x0, box.y0, box.x1, box.y1)


class _StepAttention:
    """The attention masks of one step, by box, per image (held weakly)."""

    def __init__(self, prepared: Sequence[_Prepared], masks: np.ndarray) -> None:
        self._images: List[Tuple[Any, Dict[tuple, np.ndarray]]] = []
        offset = 0
        for p in prepared:
            boxes = p.frame.boxes
            own = masks[offset:offset + len(p.ids)]
            offset += len(p.ids)
            try:
                image = weakref.ref(p.frame.image)
            except TypeError:  # not weak-referenceable: never matches, masks are recomputed
                image = _nothing
            self._images.append((image, {_box_key(boxes[p.unique[k]]): mask
                                         for k, mask in zip(p.valid, own)}))

    def masks_for(self, image: np.ndarray) -> Dict[tuple, np.ndarray]:
        """The masks kept for ``image`` (the very array), else none."""
        for ref, masks in self._images:
            if ref() is image:
                return masks
        return {}


def _nothing() -> None:
    return None


class _ProbTable:
    """One step's published probabilities and classes as Python floats and ints.

    Converting once per step keeps the per-box work free of numpy scalar overhead.
    """

    def __init__(self, probs: Mapping[str, np.ndarray],
                 states: Mapping[str, np.ndarray]) -> None:
        self.rows = {t: np.asarray(p).tolist() for t, p in probs.items()}
        self.best = {t: np.asarray(c).tolist() for t, c in states.items()}
