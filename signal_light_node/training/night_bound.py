"""ON offsets held to bounds on false lights at night: brakes, and blinkers.

Steady tail lamps at night are bright, red and clipped, as brake lamps are; a model may
rank a brake above a tail lamp within a scene and still call the tail lamps braking where
its absolute level does not carry over (docs/model.md, "A bound on false night brakes"),
and a glaring steady lamp may be taken for a blinker. The held-out family's calibration
split does not see that failure, so the UNKNOWN margin and blinker offset fitted there
(``unknown_bias``) leave the thresholds where training put them. A false light is what a
prediction module reacts to, so each light group gets a bound of its own, checked on hard
negatives of the project's own renderer: night tracks of the held-out family whose tail
lamps glare as brightly as brakes (``scripts/render_data.sh``: ``NIGHT_NEGATIVE_TRACKS``).

:func:`fit_light_offset` runs the model once over those tracks; for each offset of a grid
(log-odds, 0 or below) it shifts the ON of the group's lights against their OFF, as the
config's ``on_offsets`` would (``unknown_bias.with_offsets``; P(UNKNOWN) stays), publishes
through the node's intent
filter, and counts the OFF frames published ON (over the group's lights together). The
offset nearest 0 whose share is within the bound wins: the least recall given up for it.
``signal-light calibrate --night-negatives ... --max-false-brake X --max-false-blinker Y``
applies them after the UNKNOWN margin, so the checkpoint and its exports carry them in the
config's ``on_offsets``.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Sequence, Tuple

import torch.nn as nn

from signal_light_node.errors import ConfigError
from signal_light_node.evaluation.tracks import TrackSequence
from signal_light_node.labels import LightStatus
from signal_light_node.training.unknown_bias import (ON_HEADS, ModelPass, add_on_offsets,
                                                     load_labelled, on_offsets)

logger = logging.getLogger(__name__)

#: ON offsets tried by default (log-odds; 0 = the lights as trained). Steps of 1/8 to -2:
#: the offset nearest 0 within the bound is kept, and a coarse step overshoots it (a brake
#: bound of 20 % got 16.9 % between 24.5 % at -0.25 and -0.5; candidate W's bounds of 10 and
#: 5 % got -1.5 where -1.125 and -1.375 held them, 3 points of brake F1; docs/model.md).
DEFAULT_OFFSET_GRID: Tuple[float, ...] = (0.0,) + tuple(-0.125 * i for i in range(1, 17))
#: The light groups a bound is for: name -> the heads whose ON it shifts against OFF.
LIGHT_GROUPS: Dict[str, Tuple[str, ...]] = {"brake": ("brake",), "blinker": ON_HEADS}

OFF, ON = int(LightStatus.OFF), int(LightStatus.ON)


def meta_key(group: str) -> str:
    """Checkpoint metadata key of a group's fit (``brake_bound``, ``blinker_bound``)."""
    return f"{group}_bound"


@dataclass
class LightBoundFit:
    """What :func:`fit_light_offset` found.

    Attributes:
        group: The light group (a key of :data:`LIGHT_GROUPS`).
        offset: The ON offset chosen (the group's heads' ON against OFF, log-odds).
        bound: The largest share of OFF frames published ON that was allowed.
        met: Whether the chosen offset meets the bound (else it is the grid's lowest).
        false_on: Per offset tried, the share of OFF frames published ON.
        recall: Per offset tried, the share of ON frames published ON.
        tracks: Negative tracks it was fitted on.
        off_frames: Their OFF light-frames scored.
    """

    group: str
    offset: float
    bound: float
    met: bool
    false_on: Dict[float, float] = field(default_factory=dict)
    recall: Dict[float, float] = field(default_factory=dict)
    tracks: int = 0
    off_frames: int = 0


def light_offsets(group: str, offset: float) -> Dict[str, float]:
    """The group's heads' shifts of ON against OFF: ``offset`` each."""
    return on_offsets(LIGHT_GROUPS[group], offset)


def choose_offset(false_on: Dict[float, float], bound: float) -> Tuple[float, bool]:
    """The offset nearest 0 whose share is within ``bound``; else the lowest, not met."""
    within = [o for o, share in false_on.items() if share <= bound]
    if within:
        return max(within), True
    return min(false_on), False


def _check(group: str, bound: float, grid: Sequence[float],
           tracks: Sequence[TrackSequence]) -> None:
    if group not in LIGHT_GROUPS:
        raise ConfigError(f"no light group {group!r}; one of {sorted(LIGHT_GROUPS)}")
    if not 0.0 <= bound < 1.0:
        raise ConfigError(f"the false {group} bound must be in [0, 1), got {bound}")
    if not grid or max(grid) > 0.0:
        raise ConfigError(f"{group} ON offsets must be 0 or below, got {list(grid)}")
    if not tracks:
        raise ConfigError(f"no night negative track to bound the false {group}s on")


def fit_light_offset(model: nn.Module, tracks: Sequence[TrackSequence], bound: float,
                     grid: Sequence[float] = DEFAULT_OFFSET_GRID,
                     group: str = "brake") -> LightBoundFit:
    """Choose the group's ON offset on ``tracks`` (see the module doc); ``model`` is unchanged.

    Raises:
        ConfigError: An unknown group, a bound outside [0, 1), an offset above 0, no track,
            or tracks without an OFF frame of the group.
    """
    _check(group, bound, grid, tracks)
    return fit_on_pass(ModelPass(model, tracks), bound, grid, group)


def fit_on_pass(passed: ModelPass, bound: float, grid: Sequence[float],
                group: str) -> LightBoundFit:
    """:func:`fit_light_offset` on a model pass already made (the groups' heads are scored
    apart, so each group's fit ignores the others' offsets)."""
    fit = LightBoundFit(group=group, offset=0.0, bound=float(bound), met=False,
                        tracks=sum(len(batch) for batch, _ in passed.outputs))
    for offset in sorted({float(o) for o in grid}, reverse=True):
        strict = passed.scorer({}, light_offsets(group, offset)).strict
        m = sum(strict.confusion(task) for task in LIGHT_GROUPS[group])
        if m[OFF].sum() == 0:
            raise ConfigError(f"the night negative tracks have no {group}-OFF frame to count")
        fit.off_frames = int(m[OFF].sum())
        fit.false_on[offset] = float(m[OFF, ON] / m[OFF].sum())
        fit.recall[offset] = float(m[ON, ON] / m[ON].sum()) if m[ON].sum() else float("nan")
        logger.info("%s ON offset %+.2f: %.1f %% of %s-OFF frames published ON",
                    group, offset, 100 * fit.false_on[offset], group)
    fit.offset, fit.met = choose_offset(fit.false_on, bound)
    return fit


class NightBounds:
    """``calibrate_checkpoint``'s ``after_fit``: one model pass over the night negatives,
    each group's ON offset fitted on it, all applied to the model; returns their metadata
    entries (the fits stay in :attr:`fits`).

    Args:
        negatives: Labelled splits or bags of night negatives.
        bounds: ``(group, bound, grid)`` per light group: the largest share of its OFF
            frames that may be published ON, and the ON offsets to try (0 or below).
    """

    def __init__(self, negatives: Sequence[Path],
                 bounds: Sequence[Tuple[str, float, Sequence[float]]]) -> None:
        self.negatives = list(negatives)
        self.bounds = [(group, float(bound), tuple(grid)) for group, bound, grid in bounds]
        self.fits: List[LightBoundFit] = []

    def __call__(self, model: nn.Module) -> Dict[str, Any]:
        tracks = load_labelled(self.negatives, model.config.crop_config())
        for group, bound, grid in self.bounds:
            _check(group, bound, grid, tracks)
        passed, chosen, meta = ModelPass(model, tracks), {}, {}
        self.fits = []
        for group, bound, grid in self.bounds:
            fit = fit_on_pass(passed, bound, grid, group)
            chosen.update(light_offsets(group, fit.offset))
            self.fits.append(fit)
            meta[meta_key(group)] = self._entry(fit)
        add_on_offsets(model, chosen)
        return meta

    def _entry(self, fit: LightBoundFit) -> Dict[str, Any]:
        entry = asdict(fit)
        for key in ("false_on", "recall"):
            entry[key] = {f"{o:g}": v for o, v in entry[key].items()}
        entry["data"] = [str(p) for p in self.negatives]
        return entry


def summary_line(fit: LightBoundFit) -> str:
    """What ``signal-light calibrate`` prints of a fit."""
    shares = ", ".join(f"{o:+g}: {100 * s:.1f} %" for o, s in sorted(fit.false_on.items(),
                                                                       reverse=True))
    verdict = "within" if fit.met else "NOT within (the grid's lowest offset kept)"
    return (f"{fit.group} ON offset {fit.offset:+g}, {verdict} the bound of "
            f"{100 * fit.bound:.1f} % of {fit.group}-OFF frames published ON on {fit.tracks} "
            f"night negative tracks ({fit.off_frames} frames; per offset: {shares})")
