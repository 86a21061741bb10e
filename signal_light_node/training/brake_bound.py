"""A brake ON offset held to a bound on false brakes at night.

Steady tail lamps at night are bright, red and clipped, as brake lamps are; a model may
rank a brake above a tail lamp within a scene and still call the tail lamps braking where
its absolute level does not carry over (docs/model.md, "A bound on false night brakes").
The held-out family's calibration split does not see that failure, so the UNKNOWN margin
and blinker offset fitted there (``unknown_bias``) leave the brake's threshold where
training put it. A false brake is what a prediction module reacts to, so the brake gets a
bound of its own, checked on hard negatives of the project's own renderer: night tracks of
the held-out family whose tail lamps glare as brightly as brakes
(``scripts/render_data.sh``: ``NIGHT_NEGATIVE_TRACKS``).

:func:`fit_brake_offset` runs the model once over those tracks; for each offset of a grid
(logit units, 0 or below) it moves the brake's ON logit as adding it to the head's bias
would (``unknown_bias.with_offsets``), publishes through the node's intent filter, and
counts the brake-OFF frames published ON. The offset nearest 0 whose share is within the
bound wins: the least recall given up for it. ``signal-light calibrate --night-negatives
... --max-false-brake X`` applies it after the UNKNOWN margin, so the checkpoint and its
exports carry it in the brake head's bias.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np
import torch.nn as nn

from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.tracks import TrackSequence
from signal_light_node.labels import LightStatus
from signal_light_node.training.unknown_bias import (ModelPass, apply_offsets, class_index,
                                                     load_labelled)

logger = logging.getLogger(__name__)

#: Brake ON offsets tried by default (logit units; 0 = the brake as trained).
DEFAULT_BRAKE_GRID: Tuple[float, ...] = (0.0, -0.25, -0.5, -0.75, -1.0, -1.5, -2.0)
#: Checkpoint metadata key of the fit.
BRAKE_META_KEY = "brake_bound"

OFF, ON = int(LightStatus.OFF), int(LightStatus.ON)


@dataclass
class BrakeBoundFit:
    """What :func:`fit_brake_offset` found.

    Attributes:
        offset: The brake ON offset chosen (added to the brake head's ON logit).
        bound: The largest share of brake-OFF frames published ON that was allowed.
        met: Whether the chosen offset meets the bound (else it is the grid's lowest).
        false_on: Per offset tried, the share of brake-OFF frames published ON.
        recall: Per offset tried, the share of brake-ON frames published ON.
        tracks: Negative tracks it was fitted on.
        off_frames: Their brake-OFF frames scored.
    """

    offset: float
    bound: float
    met: bool
    false_on: Dict[float, float] = field(default_factory=dict)
    recall: Dict[float, float] = field(default_factory=dict)
    tracks: int = 0
    off_frames: int = 0


def brake_offsets(model: nn.Module, offset: float) -> Dict[str, np.ndarray]:
    """What to add to each brake class's logit: ``offset`` on ON."""
    delta = np.zeros(len(model.config.class_names["brake"]))
    delta[class_index(model, "brake", "ON")] = float(offset)
    return {"brake": delta}


def choose_offset(false_on: Dict[float, float], bound: float) -> Tuple[float, bool]:
    """The offset nearest 0 whose share is within ``bound``; else the lowest, not met."""
    within = [o for o, share in false_on.items() if share <= bound]
    if within:
        return max(within), True
    return min(false_on), False


def _check(bound: float, grid: Sequence[float], tracks: Sequence[TrackSequence]) -> None:
    if not 0.0 <= bound < 1.0:
        raise ConfigError(f"the false brake bound must be in [0, 1), got {bound}")
    if not grid or max(grid) > 0.0:
        raise ConfigError(f"brake ON offsets must be 0 or below, got {list(grid)}")
    if not tracks:
        raise ConfigError("no night negative track to bound the false brakes on")


def fit_brake_offset(model: nn.Module, tracks: Sequence[TrackSequence], bound: float,
                     grid: Sequence[float] = DEFAULT_BRAKE_GRID) -> BrakeBoundFit:
    """Choose the brake ON offset on ``tracks`` (see the module doc); ``model`` is unchanged.

    Raises:
        ConfigError: A bound outside [0, 1), an offset above 0, no track, or tracks without
            a brake-OFF frame.
    """
    _check(bound, grid, tracks)
    passed = ModelPass(model, tracks)
    fit = BrakeBoundFit(offset=0.0, bound=float(bound), met=False, tracks=len(tracks))
    for offset in sorted({float(o) for o in grid}, reverse=True):
        m = passed.scorer(brake_offsets(model, offset)).strict.confusion("brake")
        if m[OFF].sum() == 0:
            raise ConfigError("the night negative tracks have no brake-OFF frame to count")
        fit.off_frames = int(m[OFF].sum())
        fit.false_on[offset] = float(m[OFF, ON] / m[OFF].sum())
        fit.recall[offset] = float(m[ON, ON] / m[ON].sum()) if m[ON].sum() else float("nan")
        logger.info("brake ON offset %+.2f: %.1f %% of brake-OFF frames published ON",
                    offset, 100 * fit.false_on[offset])
    fit.offset, fit.met = choose_offset(fit.false_on, bound)
    return fit


class BrakeBound:
    """``calibrate_checkpoint``'s ``after_fit``: fit the brake ON offset on the night
    negatives, apply it to the model, and return its metadata entry (the fit stays in
    :attr:`fit`).

    Args:
        negatives: Labelled splits or bags of night negatives.
        bound: The largest share of their brake-OFF frames that may be published ON.
        grid: The brake ON offsets to try (0 or below).
    """

    def __init__(self, negatives: Sequence[Path], bound: float,
                 grid: Sequence[float] = DEFAULT_BRAKE_GRID) -> None:
        self.negatives, self.bound, self.grid = list(negatives), float(bound), tuple(grid)
        self.fit: Optional[BrakeBoundFit] = None

    def __call__(self, model: nn.Module) -> Dict[str, Any]:
        tracks = load_labelled(self.negatives, model.config.crop_config())
        self.fit = fit_brake_offset(model, tracks, self.bound, self.grid)
        apply_offsets(model, brake_offsets(model, self.fit.offset))
        entry = asdict(self.fit)
        for key in ("false_on", "recall"):
            entry[key] = {f"{o:g}": v for o, v in entry[key].items()}
        entry["data"] = [str(p) for p in self.negatives]
        return {BRAKE_META_KEY: entry}


def summary_line(fit: BrakeBoundFit) -> str:
    """What ``signal-light calibrate`` prints of the fit."""
    shares = ", ".join(f"{o:+g}: {100 * s:.1f} %" for o, s in sorted(fit.false_on.items(),
                                                                       reverse=True))
    verdict = "within" if fit.met else "NOT within (the grid's lowest offset kept)"
    return (f"brake ON offset {fit.offset:+g}, {verdict} the bound of {100 * fit.bound:.1f} % "
            f"of brake-OFF frames published ON on {fit.tracks} night negative tracks "
            f"({fit.off_frames} frames; per offset: {shares})")
