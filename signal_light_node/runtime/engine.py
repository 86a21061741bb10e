"""The runtime engine: one camera frame and its tracked boxes in, one result per box out.

The engine is what the ROS node and ``signal-light replay`` share. Per frame it crops
every box with the shared crop code, gathers the tracks' recurrent states from the
:class:`~signal_light_node.runtime.state_bank.StateBank`, runs ONE batched step of the model
backend (:mod:`signal_light_node.runtime.backend`: torch or onnxruntime; the engine never
sees a tensor) for all boxes that could be cropped, holds the outputs through blinks with the
:class:`~signal_light_node.runtime.intent_filter.IntentFilter` (its per-track rows live in the
state bank too), stores the new states and turns the probabilities into
:class:`~signal_light_node.runtime.results.VehicleResult`\\ s. It never imports rclpy.
"""

from __future__ import annotations

import logging
import math
import time
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import cv2
import numpy as np

from signal_light_node.boxes import TrackBox
from signal_light_node.runtime.crops import CropConfig, clip_roi, crop_region, crop_vehicles
from signal_light_node.errors import ConfigError
from signal_light_node.runtime.intent_filter import IntentFilter, IntentFilterConfig
from signal_light_node.labels import LIGHT_CODES, LIGHT_TASKS, Intent, LightStatus, View
from signal_light_node.runtime.backend import ModelBackend, check_device
from signal_light_node.runtime.memory import retain_freed_memory
from signal_light_node.runtime.results import LightEstimate, VehicleResult
from signal_light_node.runtime.state_bank import StateBank, check_limits

LOG = logging.getLogger(__name__)

#: ON-probability threshold per ``LightClassification`` code (brake, left, right).
DEFAULT_THRESHOLDS: Dict[int, float] = {code: 0.5 for code in LIGHT_CODES.values()}

#: Stages of :meth:`LightStateEngine.process`, in order, as keyed in ``FrameResult.stages_s``:
#: cropping every box, gathering the tracks' states (and intent-filter rows) from the
#: state bank, the backend's batched step, the intent filter, storing the new states,
#: and turning the probabilities into results.
ENGINE_STAGES: Tuple[str, ...] = ("crops", "state_gather", "step", "intent_filter",
                                  "state_store", "results")

_CODE_OF_NAME = dict(LIGHT_CODES)
_NAME_OF_CODE = {code: name for name, code in LIGHT_CODES.items()}


def normalize_thresholds(thresholds: Mapping[Any, Any]) -> Dict[int, float]:
    """Per-code thresholds with every light code present.

    Args:
        thresholds: Keys are codes (100, "101") or light names ("brake"); missing codes
            keep 0.5.

    Returns:
        ``{100: t, 101: t, 102: t}``.

    Raises:
        ConfigError: A key is not a light code or name, or a value is not in [0, 1].
    """
    if not isinstance(thresholds, Mapping):
        raise ConfigError(f"thresholds must be a mapping code -> probability, got {thresholds!r}")
    out = dict(DEFAULT_THRESHOLDS)
    for key, value in thresholds.items():
        code: Optional[int] = _CODE_OF_NAME.get(key) if isinstance(key, str) else None
        if code is None:
            try:
                code = int(key)
            except (TypeError, ValueError):
                code = None
        if code not in _NAME_OF_CODE:
            raise ConfigError(f"threshold key {key!r} is not a light code "
                              f"{sorted(_NAME_OF_CODE)} or name {sorted(_CODE_OF_NAME)}")
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                or not (math.isfinite(value) and 0.0 <= value <= 1.0):
            raise ConfigError(f"threshold of code {code} ({_NAME_OF_CODE[code]}) must be a "
                              f"probability in [0, 1], got {value!r}")
        out[code] = float(value)
    return out


@dataclass(frozen=True)
class EngineConfig:
    """Settings of a :class:`LightStateEngine`.

    Attributes:
        crop: Crop size and margin; None takes both from the model's config (the size
            must always equal the model's input size).
        thresholds: ON-probability from which a light goes into ``classification``, per
            code (100 brake, 101 left, 102 right); light names are accepted as keys.
        track_timeout_s: A track unseen this long starts over from the initial state.
        max_tracks: Most track states kept; the least recently seen one is evicted.
        max_gap_s: A forward stamp jump larger than this resets every track.
        device: Device of the model and the states ("cpu", "cuda", "cuda:1"); a model
            backend given to the engine keeps its own.
        intent_filter: The hold over the model's light outputs and the intent derived
            from it (``enabled=False`` publishes the raw model).
        max_boxes: Boxes judged per frame; later ones are reported unjudged and counted
            (``over_limit``), so a flood of boxes cannot stall the frame.
    """

    crop: Optional[CropConfig] = None
    thresholds: Mapping[int, float] = field(default_factory=lambda: dict(DEFAULT_THRESHOLDS))
    track_timeout_s: float = 1.0
    max_tracks: int = 128
    max_gap_s: float = 2.0
    device: str = "cpu"
    intent_filter: IntentFilterConfig = field(default_factory=IntentFilterConfig)
    max_boxes: int = 128

    def __post_init__(self) -> None:
        if isinstance(self.max_boxes, bool) or not isinstance(self.max_boxes, (int, np.integer)) \
                or self.max_boxes < 1:
            raise ConfigError(f"max_boxes must be a positive integer, got {self.max_boxes!r}")
        if self.crop is not None and not isinstance(self.crop, CropConfig):
            raise ConfigError(f"crop must be a CropConfig or None, got {self.crop!r}")
        if not isinstance(self.intent_filter, IntentFilterConfig):
            raise ConfigError(f"intent_filter must be an IntentFilterConfig, got "
                              f"{self.intent_filter!r}")
        object.__setattr__(self, "thresholds", normalize_thresholds(self.thresholds))
        limits = check_limits(self.track_timeout_s, self.max_tracks, self.max_gap_s)
        for name, value in zip(("track_timeout_s", "max_tracks", "max_gap_s"), limits):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "device", check_device(self.device))


@dataclass(frozen=True)
class FrameResult:
    """What the engine made of one frame.

    Attributes:
        stamp_ns: The frame's stamp.
        results: One result per input box, in input order.
        warnings: Why boxes were not judged, duplicates, state resets (also counted).
        latency_s: Wall time of ``process``.
        n_judged: Boxes that went through the model.
        stages_s: Wall time of each stage of ``process`` (:data:`ENGINE_STAGES`), in
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


class LightStateEngine:
    """Per-frame light-state inference over tracked vehicles.

    Not thread-safe: call ``process`` from one thread, frames in stamp order (a stamp
    that jumps back resets every track, as when a bag loops). Creating an engine makes
    the process keep freed heap memory (``runtime.memory.retain_freed_memory``), so the
    per-frame arrays do not fault fresh pages in every frame.

    Args:
        model: A model backend (``runtime.backend.ModelBackend``, e.g. from
            ``model.backends.registry.create_backend``), or a bare torch
            ``LightStateModel`` (``initial_state``, ``step``, ``config``), which is
            wrapped in the ``torch`` backend on ``config.device``.
        config: Engine settings.

    Raises:
        ConfigError: The crop size differs from the model's input size, or the device
            is CUDA while CUDA is unavailable.
    """

    def __init__(self, model: Any, config: Optional[EngineConfig] = None) -> None:
        # The registry is imported here, not at the top: its package (``model``) loads
        # torch, and importing the engine loads no framework.
        from signal_light_node.model.backends.registry import as_backend

        config = config or EngineConfig()
        retain_freed_memory()
        backend: ModelBackend = as_backend(model, config.device)
        model_config = backend.config
        input_size = int(getattr(backend, "input_size", model_config.input_size))
        crop = config.crop or model_config.crop_config()
        if crop.size != input_size:
            raise ConfigError(f"crop size {crop.size} differs from the model's input size "
                              f"{input_size}")
        trained_margin = getattr(model_config, "crop_margin", None)
        if trained_margin is not None and abs(crop.margin - trained_margin) > 1e-9:
            LOG.warning("crop margin %.3f differs from the %.3f the model was trained with",
                        crop.margin, trained_margin)
        self.backend = backend
        self.config = config
        self.crop = crop
        self.device = backend.device
        #: Keep the attention masks of each step for ``attention_masks`` (switched on by
        #: its first call, so engines without an overlay never pay for them).
        self.keep_attention = False
        self._frame_attention: Optional[_FrameAttention] = None
        codes = dict(getattr(model_config, "light_codes", LIGHT_CODES))
        if codes != LIGHT_CODES:
            raise ConfigError(f"model light codes {codes} differ from {LIGHT_CODES}")
        self._thresholds = [(task, LIGHT_CODES[task], config.thresholds[LIGHT_CODES[task]])
                            for task in LIGHT_TASKS]
        self.filter = IntentFilter(config.intent_filter)
        self.bank = StateBank(backend, track_timeout_s=config.track_timeout_s,
                              max_tracks=config.max_tracks, max_gap_s=config.max_gap_s,
                              filter_row=self.filter.initial_rows(1)[0])
        self._counts = {"frames": 0, "boxes": 0, "judged": 0, "unjudged": 0,
                        "duplicates": 0, "over_limit": 0, "model_steps": 0}

    # -------------------------------------------------------------- diagnostics
    @property
    def model(self) -> Any:
        """The backend's underlying model (``TorchBackend.model``), else the backend."""
        return getattr(self.backend, "model", self.backend)

    @property
    def counters(self) -> Dict[str, int]:
        """Running totals: frames, boxes, judged, unjudged, duplicates, over_limit (boxes
        past ``max_boxes``), model_steps, resets, evictions, expired, overflow (tracks run
        without a kept state because ``max_tracks`` were in the frame) and the current
        active_tracks."""
        out = dict(self._counts)
        for key in ("resets", "evictions", "expired", "overflow"):
            out[key] = int(self.bank.counters[key])
        out["active_tracks"] = len(self.bank)
        return out

    @property
    def reset_reasons(self) -> Dict[str, int]:
        """How often the state bank was reset, per reason."""
        return dict(self.bank.reset_reasons)

    def reset(self) -> None:
        """Forget every track's state (counted as a manual reset)."""
        self.bank.reset()

    # --------------------------------------------------------------- the step
    def process(self, image: np.ndarray, stamp_ns: int,
                boxes: Sequence[TrackBox]) -> FrameResult:
        """Judge the lights of every tracked vehicle of one frame.

        Args:
            image: The camera frame, HxWx3 uint8 BGR.
            stamp_ns: The frame's stamp (header stamp) in nanoseconds.
            boxes: Tracked boxes; ``track_id`` keys the recurrent state.

        Returns:
            One result per box, in order. A box that cannot be cropped, and every later
            box repeating an earlier box's track ID, gets an unjudged result and a
            warning; their track state is not advanced.

        Raises:
            CropError: The image itself is not an HxWx3 uint8 array.
        """
        clock = time.perf_counter
        start = clock()
        stamp_ns = int(stamp_ns)
        height, width = image.shape[:2] if isinstance(image, np.ndarray) and image.ndim == 3 \
            else (0, 0)
        warnings: List[str] = []
        first_index: Dict[str, int] = {}
        unique: List[int] = []
        for i, box in enumerate(boxes):
            if box.track_id in first_index:
                continue
            first_index[box.track_id] = i
            unique.append(i)
        limit = self.config.max_boxes
        over = {i: f"over the limit of {limit} boxes per frame" for i in unique[limit:]}
        unique = unique[:limit]
        crops, reasons = crop_vehicles(image, [boxes[i] for i in unique], self.crop)
        valid = [k for k, reason in enumerate(reasons) if reason is None]
        ids = [boxes[unique[k]].track_id for k in valid]
        t_crops = clock()

        reset_reason = self.bank.check_stamp(stamp_ns)
        if reset_reason is not None:
            warnings.append(f"all track states reset at stamp {stamp_ns}: "
                            f"{_RESET_TEXT.get(reset_reason, reset_reason)}")
        state = self.bank.gather(ids, stamp_ns)
        self._frame_attention = None
        if ids:
            filter_rows = self.bank.gather_filter_rows(ids)
            t_gather = clock()
            batch = crops if len(valid) == len(crops) else crops[valid]
            step = self.backend.step(batch, state, attention=self.keep_attention)
            self._counts["model_steps"] += 1
            t_step = clock()
            out = self.filter.step(step.probs, stamp_ns, filter_rows)
            t_filter = clock()
            frames = self.bank.store(ids, step.state, stamp_ns, out.rows)
            table = _ProbTable(out.probs, out.states)
            if step.attention is not None:
                self._frame_attention = _FrameAttention(
                    image, {_box_key(boxes[unique[k]]): mask
                            for k, mask in zip(valid, step.attention)})
        else:
            t_gather = t_step = t_filter = clock()
            frames = self.bank.store(ids, state, stamp_ns)
            table = None
        t_store = clock()
        row_of = {unique[k]: j for j, k in enumerate(valid)}
        reason_of = {i: reasons[k] for k, i in enumerate(unique)}
        reason_of.update(over)
        results: List[VehicleResult] = []
        n_dup = n_bad = 0
        for i, box in enumerate(boxes):
            j = row_of.get(i)
            if j is not None:
                results.append(self._judged(box, width, height, table, j, int(frames[j])))
                continue
            if first_index[box.track_id] != i:
                n_dup += 1
                warnings.append(f"duplicate track ID {box.track_id!r} at box {i} (first at box "
                                f"{first_index[box.track_id]}); reported unjudged")
            else:
                n_bad += 1
                if i not in over:
                    warnings.append(f"box {i} not judged: {reason_of[i]}")
            results.append(unjudged_result(box, width, height,
                                           self.bank.frames_observed(box.track_id)))

        if over:
            warnings.append(f"{len(over)} boxes not judged: {over[min(over)]}")
        self._counts["frames"] += 1
        self._counts["boxes"] += len(boxes)
        self._counts["judged"] += len(ids)
        self._counts["unjudged"] += n_bad + n_dup
        self._counts["duplicates"] += n_dup
        self._counts["over_limit"] += len(over)
        for text in warnings:
            LOG.debug("%s", text)
        end = clock()
        stages = dict(zip(ENGINE_STAGES, (t_crops - start, t_gather - t_crops, t_step - t_gather,
                                          t_filter - t_step, t_store - t_filter, end - t_store)))
        return FrameResult(stamp_ns, results, warnings, end - start, len(ids), stages)

    def unjudged_frame(self, stamp_ns: int, boxes: Sequence[TrackBox], width: int, height: int,
                       reason: str) -> FrameResult:
        """The result of a frame whose image cannot be used (undecodable, too large).

        Every box is reported unjudged, its ID kept; no track state changes.

        Args:
            stamp_ns: The frame's stamp.
            boxes: The frame's boxes.
            width: Image width the ROIs are clipped to (0 when unknown).
            height: Image height (0 when unknown).
            reason: Why, for the warnings.
        """
        results = [unjudged_result(box, width, height, self.bank.frames_observed(box.track_id))
                   for box in boxes]
        return FrameResult(int(stamp_ns), results, [reason], 0.0, 0)

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

    # ------------------------------------------------------------ debug overlay
    def attention_masks(self, image: np.ndarray, boxes: Sequence[TrackBox]) -> np.ndarray:
        """The model's attention masks pasted back into the image, for debug overlays.

        Does not touch any track state. For the image and boxes of the last ``process``
        the masks its step computed are reused; only other boxes (or a backend whose
        step does not return masks) are cropped and run through the attention net. The
        first call switches on ``keep_attention``.

        Args:
            image: The camera frame, HxWx3 uint8 BGR.
            boxes: Tracked boxes.

        Returns:
            float32 ``[H, W]`` in [0, 1]: per pixel the largest mask value of the boxes
            whose crop covers it (0 elsewhere, or when the model has no ``attention``).
        """
        height, width = image.shape[:2]
        heat = np.zeros((height, width), dtype=np.float32)
        self.keep_attention = True
        if not boxes:
            return heat
        boxes = list(boxes)[:self.config.max_boxes]
        kept = self._frame_attention.masks_for(image) if self._frame_attention is not None \
            else {}
        masks: Dict[int, np.ndarray] = {}
        missing = []
        for k, box in enumerate(boxes):
            mask = kept.get(_box_key(box))
            if mask is not None:
                masks[k] = mask
            else:
                missing.append(k)
        if missing:
            crops, reasons = crop_vehicles(image, [boxes[k] for k in missing], self.crop)
            valid = [j for j, reason in enumerate(reasons) if reason is None]
            computed = self.backend.attention(crops[valid]) if valid else None
            if computed is not None:
                masks.update({missing[j]: mask for j, mask in zip(valid, computed)})
        for k, mask in masks.items():
            # The crop's own square, so the mask lands where it was cut.
            _paste_mask(heat, mask, *crop_region(boxes[k], width, height, self.crop))
        return np.clip(heat, 0.0, 1.0)

    # ----------------------------------------------------------- several cameras
    def process_many(self, frames: Sequence[Any]) -> List[FrameResult]:
        """Judge several cameras' frames with ONE batched backend step.

        Per frame as ``process`` (unique track IDs, ``max_boxes``, crops, warnings and
        counters), but the state bank is keyed by (camera, track ID) and each camera has
        its own stamp clock: a jump on one camera resets only its tracks, and its tracks
        expire by its own stamps. ``max_tracks`` holds for all cameras together. See
        :mod:`signal_light_node.runtime.camera_batch`.

        Args:
            frames: ``camera_batch.CameraFrame(camera, image, stamp_ns, boxes)`` or plain
                tuples of those four, at most one per camera per step (a camera given
                again starts another step, in order).

        Returns:
            One ``FrameResult`` per frame, in order (``latency_s``: the wall time of the
            step the frame was part of). A frame whose image is not an HxWx3 uint8 array
            is answered unjudged with a warning instead of raising, so it cannot cost
            the other cameras their frames.

        Raises:
            ConfigError: A frame is not ``(camera, image, stamp_ns, boxes)``.
        """
        from signal_light_node.runtime.camera_batch import process_many

        return process_many(self, frames)

    @property
    def camera_counters(self) -> Dict[str, Dict[str, int]]:
        """Per camera (``""`` for ``process``): the state bank's created, expired,
        evictions, overflow, resets and the current active_tracks."""
        from signal_light_node.runtime.camera_batch import camera_counters

        return camera_counters(self)


class _FrameAttention:
    """The attention masks of the last step, by box, and (weakly) the image they came from."""

    def __init__(self, image: np.ndarray, masks: Dict[tuple, np.ndarray]) -> None:
        try:
            self.image = weakref.ref(image)
        except TypeError:  # not weak-referenceable: never matches, masks are recomputed
            self.image = lambda: None
        self.masks = masks

    def masks_for(self, image: np.ndarray) -> Dict[tuple, np.ndarray]:
        """The masks, if they were computed for ``image`` (the very array), else none."""
        return self.masks if self.image() is image else {}


def _box_key(box: TrackBox) -> tuple:
    """What decides a box's crop within one image."""
    return (box.track_id, box.x0, box.y0, box.x1, box.y1)


def _paste_mask(heat: np.ndarray, mask: np.ndarray, x0: int, y0: int, side: int) -> None:
    """Scale ``mask`` to the square ``(x0, y0, side)`` and max it into ``heat`` in place.

    Only the part of the square inside ``heat`` is computed (as ``cv2.resize`` would
    sample it), so memory stays bounded by the image whatever the box size.
    """
    height, width = heat.shape
    cx0, cy0 = max(x0, 0), max(y0, 0)
    cx1, cy1 = min(x0 + side, width), min(y0 + side, height)
    if cx1 <= cx0 or cy1 <= cy0:
        return
    scale = mask.shape[1] / side
    # Output pixel u of the visible part samples the mask at (u + offset + 0.5) * scale - 0.5.
    affine = np.array([[scale, 0.0, (cx0 - x0 + 0.5) * scale - 0.5],
                       [0.0, scale, (cy0 - y0 + 0.5) * scale - 0.5]])
    patch = cv2.warpAffine(mask, affine, (cx1 - cx0, cy1 - cy0),
                           flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_REPLICATE)
    np.maximum(heat[cy0:cy1, cx0:cx1], patch, out=heat[cy0:cy1, cx0:cx1])


class _ProbTable:
    """One frame's published probabilities and classes as Python floats and ints.

    Converting once per frame keeps the per-box work free of numpy scalar overhead.
    """

    def __init__(self, probs: Mapping[str, np.ndarray],
                 states: Mapping[str, np.ndarray]) -> None:
        self.rows = {t: np.asarray(p).tolist() for t, p in probs.items()}
        self.best = {t: np.asarray(c).tolist() for t, c in states.items()}


_RESET_TEXT = {"stamp_backwards": "the stamp jumped backwards (bag looped?)",
               "stamp_gap": "the stamp jumped forward by more than max_gap_s"}


def engine_from_checkpoint(path: "str | Path | None" = None, device: str = "cpu",
                           backend: str = "torch", threads: Optional[int] = None,
                           precision: str = "auto", **overrides: Any) -> LightStateEngine:
    """Load a model file (the shipped one when ``path`` is None) into an engine.

    Args:
        path: The model file: a ``.pt`` checkpoint for ``backend="torch"``, an ``.onnx``
            export (``signal-light export --onnx``) for ``"onnxruntime"``; None for the
            one shipped with the package.
        device: ``cpu``, ``cuda`` or ``cuda:N``.
        backend: A name of ``model.backends.registry.known_backends()``, or ``auto``
            (``registry.resolve_backend``: by the file's suffix; onnxruntime on the
            CPU for the shipped model).
        threads: Intra-op CPU threads of the backend; None or 0 keeps its default.
        precision: ``fp32``, ``int8`` or ``auto`` (``registry.create_backend``).
        **overrides: Other ``EngineConfig`` fields (thresholds, track_timeout_s,
            intent_filter, ...). The crop (size and margin) is the checkpoint's.

    Returns:
        The engine.

    Raises:
        CheckpointError: The file is missing, unreadable or incompatible.
        ConfigError: An override, the backend or the device is invalid.
    """
    from signal_light_node.model.backends.registry import create_backend

    model = create_backend(backend, None if path is None else str(path), device=device,
                           threads=threads, precision=precision)
    try:
        config = EngineConfig(device=device, **overrides)
    except TypeError as exc:
        raise ConfigError(f"unknown engine option: {exc}") from None
    return LightStateEngine(model, config)
