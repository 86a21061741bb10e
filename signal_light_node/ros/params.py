"""Every parameter of the ``signal_light_detector`` node, declared and validated in one place.

:class:`DetectorParams` holds the values and their defaults (the only copy of the defaults
but ``backend`` and ``precision``, which come from ``runtime.backend`` because
``signal-light replay`` and ``evaluate`` default to them too; ``config/detector.yaml`` is
tested against it), :data:`PARAM_SPECS` describes each one (description, range or
choices, whether it may change at run time; the backend choices are the registry's,
``model.backends.registry.known_backends()``, plus ``auto``), and
:func:`validate_params` checks a set of values with a reason a user can act on. Only
:func:`declare_parameters` and :func:`read_parameters` touch rclpy, and they import it
lazily, so the rest is usable and testable without ROS.
"""

from __future__ import annotations

import dataclasses
import logging
import re
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple, Union

from signal_light_node.errors import ConfigError
from signal_light_node.io.image_codec import DEFAULT_MAX_IMAGE_PIXELS
from signal_light_node.io.topics import camera_name_problem
from signal_light_node.model.backends.registry import known_backends
from signal_light_node.runtime.backend import (AUTO_BACKEND, DEFAULT_BACKEND, DEFAULT_PRECISION,
                                               PRECISIONS)
from signal_light_node.runtime.intent_filter import (BLINKER_SOURCES, BRAKE_SIGHTS,
                                                     INTENT_SOURCES, SIGHTS,
                                                     IntentFilterConfig, config_from,
                                                     parameter_name)
from signal_light_node.labels import LIGHT_CODES

LOG = logging.getLogger(__name__)

#: The node's name; also the top-level key of ``config/detector.yaml``.
NODE_NAME = "signal_light_detector"

Number = Union[int, float]


@dataclass(frozen=True)
class DetectorParams:
    """Parameter values of the detector node (defaults = the shipped configuration).

    Attributes:
        model_path: Model file (a ``.pt`` checkpoint for the torch backend, an ``.onnx``
            export for onnxruntime); "" means the one shipped with the package.
        device: ``cpu`` or ``cuda``.
        backend: Model backend, ``torch`` or ``onnxruntime`` (``model.backends.registry``),
            or ``auto``: by ``model_path``'s suffix, and for the shipped model onnxruntime on
            the CPU (faster there), torch on CUDA.
        precision: Weights: ``fp32``, ``int8`` (an export with int8 convolutions, run by
            onnxruntime on the CPU) or ``auto``: a ``model_path`` as it is; of the
            shipped model int8 where it runs (onnxruntime on the CPU), else fp32.
        image_transport: ``raw`` (``~/input/image``) or ``compressed``
            (``~/input/image/compressed``).
        cameras: Camera names; empty = one camera on the topics above. With names,
            each camera has its own ``~/<camera>/input/image[/compressed]``,
            ``~/<camera>/input/detections`` and ``~/<camera>/output/...``, its own pairing
            and stamp clock, and all cameras' pending frames share one model step.
        reliability: QoS reliability of the input subscriptions.
        sync_slop_s: 0 pairs image and detections only on identical stamps; > 0 pairs the
            nearest stamps at most this far apart.
        sync_timeout_s: An unpaired message is dropped after waiting this long.
        image_queue_size: Images waiting for their detections (and the subscription depth).
        detection_queue_size: Detection arrays waiting for their image (and subscription depth).
        work_queue_size: Paired frames waiting for inference; the oldest is dropped when full.
        threshold_brake: ON probability from which brake (code 100) is reported.
        threshold_left_blinker: Same for the left blinker (code 101).
        threshold_right_blinker: Same for the right blinker (code 102).
        track_timeout_s: A track unseen this long loses its recurrent state.
        max_tracks: At most this many track states; the longest unseen is evicted.
        max_gap_s: A forward stamp jump larger than this resets every track.
        intent_filter: Hold the blinkers through blinks and derive the intent from them
            (``intent_filter.IntentFilterConfig``, whose defaults these are); false
            publishes the raw model.
        filter_on_threshold: P(ON) of a frame that counts as a flash.
        filter_hold_s: A blinker stays ON this long after its last flash.
        filter_confirm_s: A blinker's flashes must span this long before it turns ON.
        filter_brake_hold_s: The brake stays ON this long after its last ON frame (0: as
            the model says).
        filter_flash_min_evidence: Flash evidence a blinker's side needs before the
            blinker can be ON (``runtime.flash_gate``; 0: no gate).
        filter_flash_window_s: How far back the flash evidence looks.
        filter_visibility_confirm_s: A light turns UNKNOWN or back only once the model
            has said so this long (``runtime.visibility_hold``; 0: every frame).
        filter_blinker_sight: Where a blinker's UNKNOWN comes from: ``model`` or
            ``geometry`` (``runtime.box_sight``: the view head and the boxes' cover).
        filter_cover_max: With ``geometry``: the share of a box that may be covered
            before the model's own UNKNOWN counts again.
        filter_brake_released_below: A judged brake under this P(ON) marks its track as
            seen released (``runtime.brake_onset``; 0: off).
        filter_brake_onset_shift: ON log-odds a seen-released brake gets from then on.
        filter_brake_onset_rise: With > 0, only on frames whose ON log-odds stand this far
            above the track's lowest (0: every later frame).
        filter_brake_unreleased_shift: ON log-odds a brake gets while its track has not
            been seen released (< 0: stricter for vehicles first seen with lamps lit).
        filter_brake_hysteresis: ON log-odds a brake keeps while it was last published ON
            (0: none).
        filter_intent_source: Where the published intent comes from: ``lights`` (the
            published blinkers) or ``head`` (the model's intent head with a switch margin).
        filter_intent_margin: With ``head``: how much more probable another intent must be
            before it is published.
        filter_blinker_source: Where the published blinkers come from: ``filter`` (the hold
            over the blinker heads) or ``intent`` (read off the published intent head).
        publish_debug_image: Publish the annotated frame on ``~/output/debug/image``.
        publish_markers: Publish the results drawn for RViz on ``~/output/markers``
            (``visualization_msgs/MarkerArray``, see :mod:`signal_light_node.outputs.markers`).
        diagnostics_period_s: Period of the ``/diagnostics`` status.
        num_threads: CPU threads of a step: torch's intra-op threads, onnxruntime's
            threads splitting the frame's batch; 0 keeps the backend's default (torch's
            choice; for onnxruntime one per CPU while they pay, one while other processes
            hold the cores: ``model.backends.thread_choice``).
        max_image_pixels: Larger images (width x height) are refused before decoding.
        max_boxes_per_frame: Boxes judged per frame; later ones are reported unjudged.
    """

    model_path: str = ""
    device: str = "cpu"
    # Shared with signal-light replay / evaluate (runtime.backend), so a replay is the node.
    backend: str = DEFAULT_BACKEND
    precision: str = DEFAULT_PRECISION
    image_transport: str = "raw"
    cameras: List[str] = field(default_factory=list)
    reliability: str = "best_effort"
    sync_slop_s: float = 0.0
    sync_timeout_s: float = 1.0
    image_queue_size: int = 10
    detection_queue_size: int = 10
    work_queue_size: int = 2
    threshold_brake: float = 0.5
    threshold_left_blinker: float = 0.5
    threshold_right_blinker: float = 0.5
    track_timeout_s: float = 1.0
    max_tracks: int = 128
    max_gap_s: float = 2.0
    intent_filter: bool = IntentFilterConfig.enabled
    filter_on_threshold: float = IntentFilterConfig.on_threshold
    filter_hold_s: float = IntentFilterConfig.hold_s
    filter_confirm_s: float = IntentFilterConfig.confirm_s
    filter_brake_hold_s: float = IntentFilterConfig.brake_hold_s
    filter_flash_min_evidence: float = IntentFilterConfig.flash_min_evidence
    filter_flash_window_s: float = IntentFilterConfig.flash_window_s
    filter_visibility_confirm_s: float = IntentFilterConfig.visibility_confirm_s
    filter_blinker_sight: str = IntentFilterConfig.blinker_sight
    filter_brake_sight: str = IntentFilterConfig.brake_sight
    filter_cover_max: float = IntentFilterConfig.cover_max
    filter_brake_released_below: float = IntentFilterConfig.brake_released_below
    filter_brake_onset_shift: float = IntentFilterConfig.brake_onset_shift
    filter_brake_onset_rise: float = IntentFilterConfig.brake_onset_rise
    filter_brake_unreleased_shift: float = IntentFilterConfig.brake_unreleased_shift
    filter_brake_hysteresis: float = IntentFilterConfig.brake_hysteresis
    filter_intent_source: str = IntentFilterConfig.intent_source
    filter_intent_margin: float = IntentFilterConfig.intent_margin
    filter_blinker_source: str = IntentFilterConfig.blinker_source
    publish_debug_image: bool = False
    publish_markers: bool = False
    diagnostics_period_s: float = 1.0
    num_threads: int = 0
    max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS
    max_boxes_per_frame: int = 128

    @property
    def thresholds(self) -> Dict[int, float]:
        """Per-code ON thresholds, keyed by the ``LightClassification`` codes."""
        return {LIGHT_CODES["brake"]: self.threshold_brake,
                LIGHT_CODES["left"]: self.threshold_left_blinker,
                LIGHT_CODES["right"]: self.threshold_right_blinker}

    @property
    def intent_filter_config(self) -> IntentFilterConfig:
        """The engine's filter settings."""
        return config_from(self, parameter_name)

    @property
    def pairing_ns(self) -> Tuple[int, int]:
        """``(sync_slop_s, sync_timeout_s)`` in nanoseconds, as the pairing takes them."""
        return int(self.sync_slop_s * 1_000_000_000), int(self.sync_timeout_s * 1_000_000_000)

    def as_dict(self) -> Dict[str, Any]:
        """Name -> value, in declaration order."""
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class ParamSpec:
    """How one parameter is declared and checked.

    Attributes:
        description: Shown by ``ros2 param describe``.
        low: Smallest allowed value (numbers only).
        high: Largest allowed value (numbers only).
        choices: Allowed values (strings only); empty = any.
        read_only: True when changing it on a running node makes no sense.
    """

    description: str
    low: Optional[Number] = None
    high: Optional[Number] = None
    choices: Tuple[str, ...] = ()
    read_only: bool = True


#: One entry per field of :class:`DetectorParams`, same order.
PARAM_SPECS: Dict[str, ParamSpec] = {
    "model_path": ParamSpec("Model file: a checkpoint (.pt) for backend torch, an export "
                            "(.onnx, signal-light export --onnx) for backend onnxruntime; "
                            "empty = the one shipped with the package."),
    "device": ParamSpec("Device for inference.", choices=("cpu", "cuda")),
    "backend": ParamSpec("Model backend: torch (the .pt checkpoint), onnxruntime (its ONNX "
                         "export), or auto: by model_path's suffix; for the shipped model "
                         "onnxruntime on the CPU, torch on CUDA.",
                         choices=known_backends() + (AUTO_BACKEND,)),
    "precision": ParamSpec("Weights: fp32, int8 (an export with int8 convolutions, "
                           "onnxruntime on the CPU: 0.76x the fp32 step on one AVX2 core, the "
                           "same accuracy) or auto: a model_path as it is; of the shipped "
                           "model int8 with onnxruntime on the CPU, else fp32. A model_path "
                           "of another precision is refused at start.",
                           choices=PRECISIONS),
    "image_transport": ParamSpec(
        "raw: subscribe ~/input/image (sensor_msgs/Image); compressed: subscribe "
        "~/input/image/compressed (sensor_msgs/CompressedImage).", choices=("raw", "compressed")),
    "cameras": ParamSpec(
        "Camera names (ROS topic tokens, unique); empty = one camera on ~/input/... and "
        "~/output/.... With names, each camera subscribes ~/<camera>/input/image[/compressed] "
        "and ~/<camera>/input/detections and publishes ~/<camera>/output/vehicle_lights "
        "(and markers, debug image); one model step per tick for every camera's pending "
        "frame."),
    "reliability": ParamSpec("QoS reliability of the input subscriptions (sensor-data profile "
                             "otherwise).", choices=("best_effort", "reliable")),
    "sync_slop_s": ParamSpec("0 = pair image and detections on identical header stamps only; "
                             "> 0 = pair the nearest stamps at most this many seconds apart.",
                             low=0.0, high=1.0, read_only=False),
    "sync_timeout_s": ParamSpec("Seconds an image or detection array waits for its partner "
                                "before it is dropped (counted).", low=0.01, high=30.0,
                                read_only=False),
    "image_queue_size": ParamSpec("Images buffered while waiting for detections; also the "
                                  "subscription depth.", low=1, high=1000),
    "detection_queue_size": ParamSpec("Detection arrays buffered while waiting for their image; "
                                      "also the subscription depth.", low=1, high=1000),
    "work_queue_size": ParamSpec("Paired frames waiting for inference; when full the oldest is "
                                 "dropped (counted).", low=1, high=100),
    "threshold_brake": ParamSpec("ON probability from which the brake light (code 100) is "
                                 "reported in classification.", low=0.0, high=1.0),
    "threshold_left_blinker": ParamSpec("ON probability from which the left blinker (code 101) "
                                        "is reported.", low=0.0, high=1.0),
    "threshold_right_blinker": ParamSpec("ON probability from which the right blinker (code 102) "
                                         "is reported.", low=0.0, high=1.0),
    "track_timeout_s": ParamSpec("A track not seen for this many seconds (stamp time) starts "
                                 "fresh when it returns.", low=0.01, high=3600.0),
    "max_tracks": ParamSpec("Most track states kept; the longest unseen is evicted first.",
                            low=1, high=100000),
    "max_gap_s": ParamSpec("A forward stamp jump larger than this many seconds resets all "
                           "tracks (backward jumps always do).", low=0.01, high=3600.0),
    "intent_filter": ParamSpec("Hold the blinkers ON through the dark half of a blink and "
                               "derive the intent from them (HAZARD only when both are held); "
                               "false publishes the model's per-frame outputs."),
    "filter_on_threshold": ParamSpec("P(ON) from which a frame counts as a flash of a light.",
                                     low=0.01, high=1.0),
    "filter_hold_s": ParamSpec("A blinker stays ON this many seconds (stamp time) after its "
                               "last flash, through the dark half of a blink.", low=0.0,
                               high=10.0),
    "filter_confirm_s": ParamSpec("A blinker turns ON only once its flashes span this many "
                                  "seconds, so a single spike never makes one.",
                                  low=0.0, high=5.0),
    "filter_brake_hold_s": ParamSpec("The brake stays ON this many seconds after its last ON "
                                     "frame; 0 = as the model says.", low=0.0, high=10.0),
    "filter_flash_min_evidence": ParamSpec("A blinker can be ON only when its side's lamps "
                                           "changed from dark to lit by at least this share "
                                           "within filter_flash_window_s (a steady lamp is "
                                           "not a blinker); 0 = no such gate.", low=0.0,
                                           high=0.99),
    "filter_flash_window_s": ParamSpec("How many seconds back the flash evidence looks (at "
                                       "least one blink period).", low=0.1, high=10.0),
    "filter_visibility_confirm_s": ParamSpec("A light turns from judged to UNKNOWN or back "
                                             "only once the model has said so this many "
                                             "seconds (fewer swaps, about a point of intent "
                                             "F1); 0 = every frame as the model says.",
                                             low=0.0, high=5.0),
    "filter_blinker_sight": ParamSpec("Where a blinker's UNKNOWN comes from: model (the "
                                      "model's own) or geometry (the view head, and the "
                                      "share of the box outside the image or behind nearer "
                                      "boxes: for a camera on which the model says UNKNOWN "
                                      "on lamps in plain sight).",
                                      choices=SIGHTS),
    "filter_brake_sight": ParamSpec("Where the brake's UNKNOWN comes from: model (the "
                                    "model's own) or geometry (judged where the view head "
                                    "sees the rear, hidden where it sees the front, the "
                                    "model's own from a side; the cover as for the "
                                    "blinkers) or rear (as geometry, and hidden from a "
                                    "side too).", choices=BRAKE_SIGHTS),
    "filter_cover_max": ParamSpec("With a sight of geometry: the share of a box "
                                  "that may be covered (image edge, nearer boxes) before "
                                  "the model's own UNKNOWN counts again.", low=0.0,
                                  high=1.0),
    "filter_brake_released_below": ParamSpec("Once a track's brake is judged with P(ON) "
                                             "under this, the track has been seen released "
                                             "and its brake's later rise counts for "
                                             "filter_brake_onset_shift more log-odds (a tail "
                                             "lamp never released keeps the strict point); "
                                             "0 = off.", low=0.0, high=0.99),
    "filter_brake_onset_shift": ParamSpec("ON log-odds added to a brake whose track has been "
                                          "seen released.", low=0.0, high=10.0),
    "filter_brake_onset_rise": ParamSpec("With > 0, a seen-released brake gets the onset "
                                         "shift only on frames whose ON log-odds stand this "
                                         "far above the lowest its track has shown; 0 = "
                                         "every later frame.", low=0.0, high=20.0),
    "filter_brake_unreleased_shift": ParamSpec("With filter_brake_released_below > 0: ON "
                                               "log-odds added to a brake while its track "
                                               "has not been seen released (< 0: a vehicle "
                                               "first seen with its lamps lit, e.g. tail "
                                               "lamps at night, needs a clearer brake).",
                                               low=-10.0, high=10.0),
    "filter_brake_hysteresis": ParamSpec("ON log-odds a brake keeps while it was last "
                                         "published ON: a release must be clearer than an "
                                         "onset (fewer brake flickers); 0 = none.",
                                         low=0.0, high=10.0),
    "filter_intent_source": ParamSpec("Where the published intent comes from: lights (derived "
                                      "from the published blinkers) or head (the model's "
                                      "own intent head, switched on filter_intent_margin).",
                                      choices=INTENT_SOURCES),
    "filter_intent_margin": ParamSpec("With filter_intent_source head: another intent is "
                                      "published once its probability is this much above "
                                      "the published one's (0 = the head's most likely "
                                      "every frame).", low=0.0, high=0.99),
    "filter_blinker_source": ParamSpec("Where the published blinkers come from: filter (the "
                                       "hold over the blinker heads) or intent (with "
                                       "filter_intent_source head: ON where the published "
                                       "intent names the side, so the two agree).",
                                       choices=BLINKER_SOURCES),
    "publish_debug_image": ParamSpec("Publish the annotated frame on ~/output/debug/image "
                                     "(costs CPU)."),
    "publish_markers": ParamSpec("Publish the results drawn for RViz on ~/output/markers "
                                 "(visualization_msgs/MarkerArray in the image's frame, "
                                 "0.01 m per pixel; built only while subscribed)."),
    "diagnostics_period_s": ParamSpec("Period of the status published on /diagnostics.",
                                      low=0.1, high=60.0),
    "num_threads": ParamSpec("CPU threads of a step: torch's intra-op threads, onnxruntime's "
                             "threads splitting the frame's batch; 0 keeps the backend's "
                             "default (onnxruntime: all CPUs while they make the step faster, "
                             "one while other processes hold the cores).", low=0, high=256),
    "max_image_pixels": ParamSpec("Images of more pixels (width x height) are refused before "
                                  "decoding (counted as oversized_images); their boxes are "
                                  "published unjudged.", low=1, high=2**31 - 1),
    "max_boxes_per_frame": ParamSpec("Boxes judged per frame; the ones after are published "
                                     "unjudged (counted as boxes_over_limit).", low=1,
                                     high=100000),
}


#: Parameters of earlier releases that an old params file may still set: name -> why the
#: value is ignored. Setting one is warned about, never an error.
RETIRED_PARAMS: Dict[str, str] = {
    "crop_margin": "the crop margin is the one the model was trained with, read from its "
                   "checkpoint",
}


def retired_warning(name: str, value: Any) -> str:
    """The one-line warning for a retired parameter that is still set."""
    return f"parameter {name} ({value!r}) is no longer used and is ignored: {RETIRED_PARAMS[name]}"


def _field_types() -> Dict[str, type]:
    return {f.name: type(f.default if f.default is not dataclasses.MISSING
                         else f.default_factory())  # type: ignore[misc]
            for f in dataclasses.fields(DetectorParams)}


def _check_one(name: str, value: Any, kind: type, spec: ParamSpec) -> Tuple[Any, Optional[str]]:
    """Coerce ``value`` to the parameter's type and check it; returns (value, problem)."""
    # bool is an int subclass; a YAML `true` must not pass as a number or vice versa.
    if kind is bool:
        if not isinstance(value, bool):
            return value, f"{name} must be true or false, got {value!r}"
    elif kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            return value, f"{name} must be an integer, got {value!r}"
    elif kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return value, f"{name} must be a number, got {value!r}"
        value = float(value)
        if value != value:  # NaN passes every range comparison
            return value, f"{name} must be a number, got NaN"
    elif kind is list:
        if isinstance(value, str) or not isinstance(value, (list, tuple)):
            return value, f"{name} must be a list of names, got {value!r}"
        value = list(value)
        problem = camera_name_problem(value)
        if problem:
            return value, f"{name}: {problem}"
    elif kind is str:
        if not isinstance(value, str):
            return value, f"{name} must be a string, got {value!r}"
        if spec.choices and value not in spec.choices:
            return value, f"{name} must be one of {', '.join(spec.choices)}, got {value!r}"
    if spec.low is not None and value < spec.low:
        return value, f"{name} must be >= {spec.low}, got {value}"
    if spec.high is not None and value > spec.high:
        return value, f"{name} must be <= {spec.high}, got {value}"
    return value, None


def validate_params(values: Union[DetectorParams, Mapping[str, Any]]) -> DetectorParams:
    """Check a complete or partial set of parameter values.

    Args:
        values: A :class:`DetectorParams` or a mapping name -> value; missing names take
            their defaults; names in :data:`RETIRED_PARAMS` are warned about and ignored.

    Returns:
        The validated parameters (integers given for float parameters become floats).

    Raises:
        ConfigError: Naming every unknown parameter and every bad value with the reason.
    """
    given = values.as_dict() if isinstance(values, DetectorParams) else dict(values)
    for name in [n for n in given if n in RETIRED_PARAMS]:
        LOG.warning("%s", retired_warning(name, given.pop(name)))
    kinds = _field_types()
    problems = [f"unknown parameter {name!r}" for name in given if name not in kinds]
    clean: Dict[str, Any] = {}
    for name, value in given.items():
        if name in kinds:
            clean[name], problem = _check_one(name, value, kinds[name], PARAM_SPECS[name])
            if problem:
                problems.append(problem)
    if not problems:
        params = DetectorParams(**clean)
        suffix = {"torch": ".pt", "onnxruntime": ".onnx"}.get(params.backend, "")
        if suffix and params.model_path \
                and params.model_path.lower().endswith((".pt", ".onnx")) \
                and not params.model_path.lower().endswith(suffix):
            problems.append(f"model_path {params.model_path!r} does not fit backend "
                            f"{params.backend}, which loads a {suffix} file (a checkpoint "
                            "becomes an .onnx file with signal-light export --onnx OUT "
                            "--weights CKPT)")
        if params.sync_slop_s > 0 and params.sync_timeout_s <= params.sync_slop_s:
            problems.append(f"sync_timeout_s ({params.sync_timeout_s}) must exceed sync_slop_s "
                            f"({params.sync_slop_s}): a message must be able to wait for a "
                            "partner that is up to sync_slop_s away")
    if problems:
        raise ConfigError("invalid parameters: " + "; ".join(problems))
    return params


def updated(params: DetectorParams, changes: Mapping[str, Any]) -> DetectorParams:
    """``params`` with ``changes`` applied, validated; read-only names are refused.

    Raises:
        ConfigError: If a change names a read-only or unknown parameter or a bad value.
    """
    frozen = [n for n in changes if n in PARAM_SPECS and PARAM_SPECS[n].read_only]
    if frozen:
        raise ConfigError(f"{', '.join(frozen)} cannot change while the node runs "
                          "(read-only; restart the node)")
    merged = params.as_dict()
    merged.update(changes)
    return validate_params(merged)


def _descriptor(name: str, kind: type, spec: ParamSpec) -> Any:
    from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                    ParameterType)

    types = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
             float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING,
             list: ParameterType.PARAMETER_STRING_ARRAY}
    desc = ParameterDescriptor(name=name, type=types[kind], description=spec.description,
                               read_only=spec.read_only)
    if spec.choices:
        desc.additional_constraints = "one of: " + ", ".join(spec.choices)
    if kind is float and spec.low is not None:
        desc.floating_point_range = [FloatingPointRange(
            from_value=float(spec.low), to_value=float(spec.high), step=0.0)]
    elif kind is int and spec.low is not None:
        desc.integer_range = [IntegerRange(from_value=int(spec.low), to_value=int(spec.high),
                                           step=1)]
    return desc


def declare_parameters(node: Any) -> None:
    """Declare every parameter on an rclpy node with its default and descriptor.

    Values given on the command line or in a params file override the defaults here.

    Raises:
        ConfigError: If a given value has the wrong type or lies outside its range.
    """
    from rclpy.exceptions import (InvalidParameterTypeException,
                                  InvalidParameterValueException)

    defaults = DetectorParams()
    kinds = _field_types()
    for name, spec in PARAM_SPECS.items():
        if kinds[name] is list:
            _declare_string_array(node, name, _descriptor(name, kinds[name], spec))
            continue
        try:
            node.declare_parameter(name, getattr(defaults, name),
                                   _descriptor(name, kinds[name], spec))
        except InvalidParameterTypeException as exc:
            raise ConfigError(f"invalid parameters: {name} must be of type "
                              f"{kinds[name].__name__} ({exc})") from None
        except InvalidParameterValueException:
            given = _override(node, name)
            _, problem = _check_one(name, given, kinds[name], spec)
            raise ConfigError("invalid parameters: "
                              + (problem or f"{name}={given!r} is refused")) from None


def _declare_string_array(node: Any, name: str, descriptor: Any) -> None:
    """Declare a string-array parameter whose default is the empty list.

    rclpy infers a byte array from an empty list, and rcl reads ``[]`` in a params file
    (or ``-p name:=[]``) as a value without a type, so neither can be declared as is:
    the value (a given string array, else ``[]``) is declared with its type explicitly.

    Raises:
        ConfigError: The given value is not a list of strings.
    """
    from rclpy.parameter import Parameter

    given = getattr(node, "_parameter_overrides", {}).get(name)
    value: List[str] = []
    if given is not None and given.type_ != Parameter.Type.NOT_SET:
        if given.type_ != Parameter.Type.STRING_ARRAY:
            raise ConfigError(f"invalid parameters: {name} must be a list of names, e.g. "
                              f"[front, rear], got {given.value!r}")
        value = list(given.value)
    # rclpy's own path of declare_parameters (Jazzy), with the type given explicitly.
    node._declare_parameter_common([Parameter(name, Parameter.Type.STRING_ARRAY, value)],
                                   {name: descriptor})


def _override(node: Any, name: str) -> Any:
    param = getattr(node, "_parameter_overrides", {}).get(name)
    return None if param is None else param.value


def read_parameters(node: Any) -> DetectorParams:
    """Declare the parameters on ``node`` and return their validated values.

    A retired parameter (:data:`RETIRED_PARAMS`) still set is warned about in one line
    and ignored.

    Raises:
        ConfigError: If any value is unusable; the message says which and why.
    """
    declare_parameters(node)
    # rclpy keeps the command-line / params-file values it was given; names nobody declared
    # (qos_overrides.* are declared later by rclpy itself) are almost always typos, except
    # the retired ones an old params file may still hold: those are warned about.
    overrides = getattr(node, "_parameter_overrides", {})
    for name in sorted(n for n in overrides if n in RETIRED_PARAMS):
        node.get_logger().warning(retired_warning(name, overrides[name].value))
    extra = sorted(n for n in overrides if not node.has_parameter(n)
                   and not n.startswith("qos_overrides.") and n not in RETIRED_PARAMS)
    if extra:
        raise ConfigError(f"invalid parameters: unknown parameter(s) {', '.join(extra)} "
                          f"(known: {', '.join(PARAM_SPECS)})")
    return validate_params({name: node.get_parameter(name).value for name in PARAM_SPECS})


def params_file_paths(args: Sequence[str]) -> List[str]:
    """The files named by ``--params-file FILE`` in a command line, in order."""
    return [args[i + 1] for i, arg in enumerate(args[:-1]) if arg == "--params-file"]


def _node_pattern(key: str) -> "re.Pattern[str]":
    """A params-file section name (``/**``, ``/ns/*``, ``name``) as a regex over node names."""
    key = key if key.startswith("/") else "/" + key
    parts = re.split(r"(/\*\*|\*)", key)
    regex = "".join("(/[^/]+)*" if p == "/**" else "[^/]+" if p == "*" else re.escape(p)
                    for p in parts)
    return re.compile(regex + r"\Z")


def foreign_params_file(path: str, node_name: str) -> Optional[str]:
    """Why a params file gives this node nothing, or None when it has a section for it.

    rcl silently ignores sections for other nodes; a file written for another node name
    (or a renamed node) would leave every parameter at its default without a word.

    Args:
        path: The params file (read with PyYAML; rcl has already parsed it).
        node_name: The node's fully qualified name, e.g. ``/signal_light_detector``.

    Returns:
        A one-line warning, or None.
    """
    import yaml

    try:
        with open(path, encoding="utf-8") as stream:
            sections = yaml.safe_load(stream)
    except (OSError, yaml.YAMLError) as exc:
        return f"params file {path} cannot be read ({type(exc).__name__}); it was not checked"
    names = [str(k) for k in sections] if isinstance(sections, dict) else []
    if any(_node_pattern(name).match(node_name) for name in names):
        return None
    return (f"params file {path} has no section for node {node_name} (it has: "
            f"{', '.join(names) or 'none'}); none of its values apply to this node")
