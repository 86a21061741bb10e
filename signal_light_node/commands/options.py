"""Command-line options that several ``signal-light`` commands share.

One definition each, so that ``train``, ``evaluate``, ``replay`` and ``annotate`` spell,
default and explain them alike. Every helper takes an ``argparse`` parser or argument
group; ``engine_from_args`` and ``pairing_from_args`` turn the options back into what
the replay runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, Dict, Optional

# The common base of ArgumentParser and argument groups (what add_argument lives on).
ArgumentContainer = argparse._ActionsContainer


def add_labelled_data_options(group: ArgumentContainer) -> None:
    """``--bags`` and ``--ucm``: labelled data (both lists of paths, empty by default)."""
    group.add_argument("--bags", nargs="+", type=Path, default=[], metavar="BAG",
                       help="labelled bags (/ground_truth/vehicle_lights + images + detections)")
    group.add_argument("--ucm", nargs="+", type=Path, default=[], metavar="ROOT",
                       help="UC Merced Vehicle Rear Signal dataset roots")


def add_input_topic_options(group: ArgumentContainer) -> None:
    """``--image-topic`` and ``--detections-topic`` of a single-camera run over a bag."""
    group.add_argument("--image-topic", default=None,
                       help="image topic (default: the first CompressedImage, else Image topic)")
    group.add_argument("--detections-topic", default=None,
                       help="Detection2DArray topic (default: the first one)")


def add_model_options(group: ArgumentContainer) -> None:
    """``--checkpoint``, ``--backend`` and ``--precision`` of the commands that run a model.

    ``--backend`` and ``--precision`` default to the node's parameters (one copy of them,
    in ``runtime.backend``), so that a replay or an evaluation runs what the node runs.
    """
    from signal_light_node.model.backends.registry import known_backends
    from signal_light_node.runtime.backend import (AUTO_BACKEND, DEFAULT_BACKEND,
                                                   DEFAULT_PRECISION, PRECISIONS)

    group.add_argument("--checkpoint", type=Path, default=None,
                       help="model file: a .pt checkpoint (--backend torch) or its .onnx export "
                            "(--backend onnxruntime); default: the shipped one")
    group.add_argument("--backend", choices=known_backends() + (AUTO_BACKEND,),
                       default=DEFAULT_BACKEND,
                       help="model backend, as the node's backend parameter (default "
                            "%(default)s); auto picks by the file's suffix, and for the "
                            "shipped model onnxruntime on the CPU, torch on CUDA; onnxruntime "
                            "runs the file `signal-light export --onnx` writes")
    group.add_argument("--precision", choices=PRECISIONS, default=DEFAULT_PRECISION,
                       help="weights, as the node's precision parameter (default "
                            "%(default)s): fp32, int8 (an int8 export, onnxruntime on "
                            "the CPU) or auto: a --checkpoint as it is; of the shipped model "
                            "int8 with onnxruntime on the CPU, else fp32")


def add_torch_options(group: ArgumentContainer) -> None:
    """``--device``, ``--threads`` and ``--no-progress`` of the commands that run the model."""
    group.add_argument("--device", default="cpu", help="device: cpu, cuda or cuda:N")
    group.add_argument("--threads", type=int, default=None,
                       help="CPU threads of a model step (torch: intra-op; onnxruntime: "
                            "splitting the batch); unset: the backend's choice, as the node's "
                            "num_threads 0 (onnxruntime: 1 or all per step, by the load)")
    group.add_argument("--no-progress", action="store_true", help="no progress bars")


def add_intent_filter_options(group: ArgumentContainer) -> None:
    """``--intent-filter`` / ``--no-intent-filter`` and the filter's settings.

    Defaults come from ``intent_filter.IntentFilterConfig`` (as the node's parameters do).
    """
    from signal_light_node.runtime.intent_filter import (BLINKER_SOURCES, BRAKE_SIGHTS,
                                                         INTENT_SOURCES, SIGHTS,
                                                         IntentFilterConfig)

    d = IntentFilterConfig()
    group.add_argument("--intent-filter", action=argparse.BooleanOptionalAction,
                       default=d.enabled,
                       help="hold the blinkers through the dark half of a blink and derive "
                            "the intent from them, as the node does (--no-intent-filter: "
                            "the raw model)")
    group.add_argument("--filter-on-threshold", type=float, default=d.on_threshold,
                       metavar="P", help="P(ON) of a frame that counts as a flash")
    group.add_argument("--filter-hold", type=float, default=d.hold_s, metavar="S",
                       help="seconds a blinker stays ON after its last flash")
    group.add_argument("--filter-confirm", type=float, default=d.confirm_s, metavar="S",
                       help="seconds a blinker's flashes must span before it turns ON")
    group.add_argument("--filter-brake-hold", type=float, default=d.brake_hold_s, metavar="S",
                       help="seconds the brake stays ON after its last ON frame (0: as the "
                            "model says)")
    group.add_argument("--filter-flash-min", type=float, default=d.flash_min_evidence,
                       metavar="E", help="flash evidence (0..1) a blinker's side needs before "
                       "the blinker can be ON: a steady lamp is not a blinker (0: no gate)")
    group.add_argument("--filter-flash-window", type=float, default=d.flash_window_s,
                       metavar="S", help="seconds the flash evidence looks back")
    group.add_argument("--filter-visibility-confirm", type=float,
                       default=d.visibility_confirm_s, metavar="S",
                       help="seconds the model must say a light turned UNKNOWN (or back) "
                            "before it is published (0: every frame)")
    group.add_argument("--filter-blinker-sight", choices=SIGHTS,
                       default=d.blinker_sight,
                       help="where a blinker's UNKNOWN comes from: the model's own, or the "
                            "view head and how much of the box the image edge and nearer "
                            "boxes cover (bags only: splits keep no other boxes)")
    group.add_argument("--filter-brake-sight", choices=BRAKE_SIGHTS, default=d.brake_sight,
                       help="where the brake's UNKNOWN comes from: the model's own; "
                            "geometry: judged where the view head sees the rear, hidden "
                            "where it sees the front, the model's own from a side; rear: "
                            "hidden from a side too (bags only, as above)")
    group.add_argument("--filter-cover-max", type=float, default=d.cover_max, metavar="C",
                       help="with a sight of geometry: the share of a box that "
                            "may be covered before the model's own UNKNOWN counts again")
    group.add_argument("--filter-brake-released-below", type=float,
                       default=d.brake_released_below, metavar="P",
                       help="a judged brake under this P(ON) marks its track seen released; "
                            "its later rise gets --filter-brake-onset-shift more ON "
                            "log-odds (0: off)")
    group.add_argument("--filter-brake-onset-shift", type=float, default=d.brake_onset_shift,
                       metavar="L", help="ON log-odds added to a seen-released brake")
    group.add_argument("--filter-brake-onset-rise", type=float, default=d.brake_onset_rise,
                       metavar="L", help="with > 0: the shift only on frames whose ON "
                       "log-odds stand this far above the track's lowest (0: every frame)")
    group.add_argument("--filter-brake-unreleased-shift", type=float,
                       default=d.brake_unreleased_shift, metavar="L",
                       help="with --filter-brake-released-below: ON log-odds added to a "
                       "brake until its track is seen released (< 0: stricter)")
    group.add_argument("--filter-brake-hysteresis", type=float, default=d.brake_hysteresis,
                       metavar="L", help="ON log-odds a brake keeps while it was last "
                       "published ON (0: none)")
    group.add_argument("--filter-intent-source", choices=INTENT_SOURCES, default=d.intent_source,
                       help="where the published intent comes from: the published blinkers "
                            "(lights) or the model's intent head with a switch margin (head)")
    group.add_argument("--filter-intent-margin", type=float, default=d.intent_margin,
                       metavar="P", help="with --filter-intent-source head: another intent "
                       "is published once its probability is this much above the "
                       "published one's")
    group.add_argument("--filter-blinker-source", choices=BLINKER_SOURCES,
                       default=d.blinker_source,
                       help="where the published blinkers come from: the hold over the "
                            "blinker heads (filter) or the published intent (intent; needs "
                            "--filter-intent-source head)")


def intent_filter_from_args(args: argparse.Namespace) -> Any:
    """The ``IntentFilterConfig`` of :func:`add_intent_filter_options`' options.

    Raises:
        ConfigError: A value is out of range.
    """
    from signal_light_node.runtime.intent_filter import config_from, option_dest

    return config_from(args, option_dest)


def add_pairing_options(group: ArgumentContainer) -> None:
    """``--sync-slop`` and ``--sync-timeout``: how images and detections are paired, as the
    node's ``sync_slop_s`` / ``sync_timeout_s`` (defaults from ``runtime.pairing.PairingConfig``)."""
    from signal_light_node.runtime.pairing import PairingConfig

    default = PairingConfig()
    group.add_argument("--sync-slop", type=float, default=default.slop_s, metavar="S",
                       help="pair images and detections whose stamps are at most S seconds "
                            "apart, as the node with sync_slop_s: S (default: exact stamps)")
    group.add_argument("--sync-timeout", type=float, default=default.timeout_s, metavar="S",
                       help="log-time seconds a message waits for its partner, as the node's "
                            f"sync_timeout_s (default {default.timeout_s:g})")


def pairing_from_args(args: argparse.Namespace) -> Any:
    """The ``PairingConfig`` of :func:`add_pairing_options`' options.

    Raises:
        ConfigError: A negative slop, a non-positive timeout or a timeout within the slop.
    """
    from signal_light_node.runtime.pairing import PairingConfig

    return PairingConfig(slop_s=args.sync_slop, timeout_s=args.sync_timeout)


def add_track_timeout_option(group: ArgumentContainer) -> None:
    """``--track-timeout``: seconds a track may stay unseen (the node's ``track_timeout_s``)."""
    group.add_argument("--track-timeout", type=float, default=1.0, metavar="S",
                       help="seconds a track may stay unseen before its state is dropped")


def engine_from_args(args: argparse.Namespace,
                     thresholds: Optional[Dict[str, float]] = None) -> Any:
    """The engine of the model, torch, track-timeout and intent-filter options (what
    ``signal-light replay`` runs).

    Args:
        args: Parsed options of :func:`add_model_options`, :func:`add_torch_options`,
            :func:`add_track_timeout_option` and :func:`add_intent_filter_options`.
        thresholds: ON-probability thresholds of the classification codes (default 0.5).

    Raises:
        CheckpointError: The model file is missing or unusable.
        ConfigError: An option, the backend or the device is invalid.
    """
    from signal_light_node.runtime.engine import engine_from_checkpoint

    return engine_from_checkpoint(args.checkpoint, device=args.device, backend=args.backend,
                                  precision=args.precision,
                                  threads=args.threads, thresholds=dict(thresholds or {}),
                                  track_timeout_s=args.track_timeout,
                                  intent_filter=intent_filter_from_args(args))


def require_pt_checkpoints(args: argparse.Namespace, verb: str, why: str = "") -> None:
    """Refuse an ``--out`` that is not a ``.pt`` and a ``--checkpoint`` that is an ONNX
    export: the commands that rewrite a checkpoint's tensors (``adapt``, ``calibrate``)
    need the torch file, and their result is exported afterwards.

    Args:
        args: Parsed options with ``out`` and ``checkpoint``.
        verb: The command, as in "adapt needs the .pt checkpoint".
        why: Why an export will not do, appended in parentheses.

    Raises:
        ConfigError: Naming the option at fault.
    """
    from signal_light_node.errors import ConfigError

    if args.out.suffix != ".pt":
        raise ConfigError(f"--out must name a .pt checkpoint, got {str(args.out)!r}")
    if args.checkpoint is not None and args.checkpoint.suffix.lower() == ".onnx":
        because = f" ({why})" if why else ""
        raise ConfigError(f"{verb} needs the .pt checkpoint{because}; {verb} the .pt, then "
                          "export it")
