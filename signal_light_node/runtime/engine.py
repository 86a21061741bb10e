"""The runtime engine: one camera frame and its tracked boxes in, one result per box out.

The engine is what the ROS node and ``signal-light replay`` share. Per frame it crops
every box with the shared crop code, gathers the tracks' recurrent states from the
:class:`~signal_light_node.runtime.state_bank.StateBank`, runs ONE batched step of the model
backend (:mod:`signal_light_node.runtime.backend`: torch or onnxruntime; the engine never
sees a tensor) for all boxes that could be cropped, holds the outputs through blinks with the
:class:`~signal_light_node.runtime.intent_filter.IntentFilter` (its per-track rows live in the
state bank too), stores the new states and turns the probabilities into
:class:`~signal_light_node.runtime.results.VehicleResult`\\ s. It never imports rclpy.

That frame path is :class:`~signal_light_node.runtime.camera_batch.FramePath`, the same
for one camera and several: ``process`` is a step of one frame of the camera ``""``,
``process_many`` a step of one frame per camera.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence

import cv2
import numpy as np

from signal_light_node.boxes import TrackBox
from signal_light_node.errors import ConfigError
from signal_light_node.labels import LIGHT_CODES
from signal_light_node.runtime.backend import ModelBackend, check_device
from signal_light_node.runtime.camera_batch import (ENGINE_STAGES, CameraFrame, FramePath,
                                                    FrameResult, unjudged_result)
from signal_light_node.runtime.crops import CropConfig, crop_region, crop_vehicles
from signal_light_node.runtime.intent_filter import IntentFilter, IntentFilterConfig
from signal_light_node.runtime.memory import retain_freed_memory
from signal_light_node.runtime.state_bank import (CAMERA_COUNTERS, DEFAULT_CAMERA, StateBank,
                                                  check_limits)

__all__ = ["DEFAULT_THRESHOLDS", "ENGINE_STAGES", "EngineConfig", "FrameResult",
           "LightStateEngine", "engine_from_checkpoint", "normalize_thresholds",
           "unjudged_result"]

LOG = logging.getLogger(__name__)

#: ON-probability threshold per ``LightClassification`` code (brake, left, right).
DEFAULT_THRESHOLDS: Dict[int, float] = {code: 0.5 for code in LIGHT_CODES.values()}

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
        codes = dict(getattr(model_config, "light_codes", LIGHT_CODES))
        if codes != LIGHT_CODES:
            raise ConfigError(f"model light codes {codes} differ from {LIGHT_CODES}")
        self.filter = IntentFilter(config.intent_filter)
        self.bank = StateBank(backend, track_timeout_s=config.track_timeout_s,
                              max_tracks=config.max_tracks, max_gap_s=config.max_gap_s,
                              filter_row=self.filter.initial_rows(1)[0])
        self.path = FramePath(backend, self.bank, self.filter, crop, config.max_boxes,
                              config.thresholds)

    @property
    def keep_attention(self) -> bool:
        """Keep the attention masks of each step for ``attention_masks`` (switched on by
        its first call, so engines without an overlay never pay for them)."""
        return self.path.keep_attention

    @keep_attention.setter
    def keep_attention(self, keep: bool) -> None:
        self.path.keep_attention = bool(keep)

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
        out = dict(self.path.counts)
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
        """Judge the lights of every tracked vehicle of one frame: a step of one frame of
        the camera ``""`` (``process_many([("", image, stamp_ns, boxes)])``, but strict).

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
        return self.path.run([CameraFrame(DEFAULT_CAMERA, image, stamp_ns, boxes)],
                             strict=True)[0]

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
            One ``FrameResult`` per frame, in order (``latency_s`` and ``stages_s``: those
            of the step the frame was part of). A frame whose image is not an HxWx3 uint8
            array is answered unjudged with a warning instead of raising, so it cannot
            cost the other cameras their frames.

        Raises:
            ConfigError: A frame is not ``(camera, image, stamp_ns, boxes)``.
        """
        return self.path.run(frames)

    def unjudged_frame(self, stamp_ns: int, boxes: Sequence[TrackBox], width: int, height: int,
                       reason: str, camera: str = DEFAULT_CAMERA) -> FrameResult:
        """The result of a frame whose image cannot be used (undecodable, too large).

        Every box is reported unjudged, its ID kept; no track state changes.

        Args:
            stamp_ns: The frame's stamp.
            boxes: The frame's boxes.
            width: Image width the ROIs are clipped to (0 when unknown).
            height: Image height (0 when unknown).
            reason: Why, for the warnings.
            camera: The frame's camera (whose ``frames_observed`` the results carry).
        """
        return self.path.unjudged(camera, stamp_ns, boxes, width, height, reason)

    @property
    def camera_counters(self) -> Dict[str, Dict[str, int]]:
        """Per camera (``""`` for ``process``): the state bank's created, expired,
        evictions, overflow, resets and the current active_tracks."""
        bank = self.bank
        out: Dict[str, Dict[str, int]] = {}
        for camera in sorted(set(bank.camera_counters) | set(bank.cameras)):
            counts = bank.camera_counters.get(camera, {})
            out[camera] = {name: int(counts.get(name, 0)) for name in CAMERA_COUNTERS}
            out[camera]["active_tracks"] = bank.count(camera)
        return out

    # ------------------------------------------------------------ debug overlay
    def attention_masks(self, image: np.ndarray, boxes: Sequence[TrackBox]) -> np.ndarray:
        """The model's attention masks pasted back into the image, for debug overlays.

        Does not touch any track state. For the images and boxes of the last step
        (``process`` or ``process_many``) the masks it computed are reused; only other
        boxes (or a backend whose step does not return masks) are cropped and run through
        the attention net. The first call switches on ``keep_attention``.

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
        masks: Dict[int, np.ndarray] = {}
        missing = []
        for k, box in enumerate(boxes):
            mask = self.path.kept_mask(image, box)
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


def _paste_mask(heat: np.ndarray, mask: np.ndarray, x0: int, y0: int, w: int, h: int) -> None:
    """Scale ``mask`` to the region ``(x0, y0, w, h)`` and max it into ``heat`` in place.

    Only the part of the region inside ``heat`` is computed (as ``cv2.resize`` would
    sample it), so memory stays bounded by the image whatever the box size.
    """
    height, width = heat.shape
    cx0, cy0 = max(x0, 0), max(y0, 0)
    cx1, cy1 = min(x0 + w, width), min(y0 + h, height)
    if cx1 <= cx0 or cy1 <= cy0:
        return
    scale_x, scale_y = mask.shape[1] / w, mask.shape[0] / h
    # Output pixel u of the visible part samples the mask at (u + offset + 0.5) * scale - 0.5.
    affine = np.array([[scale_x, 0.0, (cx0 - x0 + 0.5) * scale_x - 0.5],
                       [0.0, scale_y, (cy0 - y0 + 0.5) * scale_y - 0.5]])
    patch = cv2.warpAffine(mask, affine, (cx1 - cx0, cy1 - cy0),
                           flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_REPLICATE)
    np.maximum(heat[cy0:cy1, cx0:cx1], patch, out=heat[cy0:cy1, cx0:cx1])


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
