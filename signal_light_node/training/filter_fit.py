"""Fit the node's output filter on labelled tracks: ``signal-light calibrate --fit-filter``.

The filter's settings (how long a blinker is held, how long a change of visibility must
last, how the brake is released) were chosen on the training renderer's calibration
split; on a user's camera other values may publish better. With labels, one model pass
is enough to score every setting of a small grid (:data:`FILTER_GRID`, the settings the
model work measured: docs/model.md), and the best by ``calibrate``'s objective is kept,
provided it does not make the published intent or brake change much more often than
the truth does (:data:`MAX_SWITCHES`) and, where a guard is given, its gain over the
defaults holds on resamples of the fit tracks' scenes (:mod:`training.fit_guard`). The
result is a set of ``IntentFilterConfig`` changes, which the node takes as parameters
(:func:`node_parameters`).
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Dict, List, Mapping, Optional, Sequence

from signal_light_node.errors import ConfigError
from signal_light_node.runtime.intent_filter import IntentFilterConfig, option_dest, parameter_name

if TYPE_CHECKING:
    from signal_light_node.training.fit_guard import Verdict

logger = logging.getLogger(__name__)

#: The brake settings tried: the defaults, a hysteresis, and the release settings chosen
#: on the calibration sets in docs/model.md ("A release clearer than an onset").
BRAKE_CHOICES: Sequence[Dict[str, float]] = (
    {},
    {"brake_hysteresis": 0.5},
    {"brake_hysteresis": 1.0},
    {"brake_released_below": 0.2, "brake_onset_shift": 0.5, "brake_onset_rise": 3.0,
     "brake_unreleased_shift": -1.5, "brake_hysteresis": 0.5},
)
#: Every setting tried: the intent head's switch margin x visibility hold x brake. The
#: blinkers' hold is not tried: with the intent from the intent head (the default) it moves
#: neither the intent nor the brake, which is all the fit's objective scores.
FILTER_GRID: List[Dict[str, float]] = [
    {"intent_margin": margin, "visibility_confirm_s": seen, **brake}
    for margin, seen, brake in itertools.product((0.1, 0.2, 0.3), (0.0, 0.2, 0.4),
                                                 BRAKE_CHOICES)]
#: A setting may make the intent or brake change at most this many times as often as the
#: truth does on the fit tracks (or as often as the defaults do, where that is more).
MAX_SWITCHES = 1.5
_SWITCHED = ("intent", "brake")


@dataclass
class FilterFit:
    """What :func:`fit_filter` found.

    Attributes:
        changes: The chosen setting of the grid, as ``IntentFilterConfig`` fields (it may
            repeat a default's value; ``{}``: the defaults themselves won).
        score: Its score on the fit tracks (``calibrate``'s objective).
        default_score: The defaults' score there.
        tried: Settings scored; ``allowed`` of them within the switch bound.
        declined: The best setting where the guard kept the defaults instead, else None.
        verdict: The guard's verdict on the best setting, where one was asked.
    """

    changes: Dict[str, float] = field(default_factory=dict)
    score: float = 0.0
    default_score: float = 0.0
    tried: int = 0
    allowed: int = 0
    declined: Optional[Dict[str, float]] = None
    verdict: Optional["Verdict"] = None

    @property
    def config(self) -> IntentFilterConfig:
        """The chosen filter."""
        return IntentFilterConfig(**self.changes)


def switch_ratios(result: Mapping[str, Any]) -> Dict[str, Optional[float]]:
    """Per task of :data:`_SWITCHED`, published changes over true ones (None: no true one)."""
    return {task: result["switches"][task].get("ratio") for task in _SWITCHED}


def _within(ratios: Mapping[str, Optional[float]], bound: Mapping[str, float]) -> bool:
    return all(r is None or r <= bound[t] for t, r in ratios.items())


def fit_filter(evaluate: Callable[[IntentFilterConfig], Dict[str, Any]],
               objective: Callable[[Dict[str, Any]], float],
               grid: Sequence[Dict[str, float]] = FILTER_GRID,
               guard: Optional[Callable[[IntentFilterConfig], "Verdict"]] = None) -> FilterFit:
    """Score every setting of ``grid`` and keep the best within the switch bound.

    Args:
        evaluate: Filter config -> the fit tracks' evaluation result (``evaluate_tracks``'
            form), from one model pass.
        objective: Result -> score (higher is better).
        grid: ``IntentFilterConfig`` changes to try; the defaults are always scored.
        guard: Filter config -> its verdict against the defaults
            (:meth:`~signal_light_node.training.fit_guard.GainGuard.judge`); the best
            setting is kept only if the guard keeps it. None: no guard.

    Raises:
        ConfigError: A setting of the grid is not a valid filter config.
    """
    defaults = evaluate(IntentFilterConfig())
    bound = {t: max(MAX_SWITCHES, r or 0.0) for t, r in switch_ratios(defaults).items()}
    fit = FilterFit(score=objective(defaults), default_score=objective(defaults))
    for changes in grid:
        try:
            config = IntentFilterConfig(**changes)
        except TypeError as exc:
            raise ConfigError(f"filter setting {changes}: {exc}") from exc
        result = evaluate(config)
        fit.tried += 1
        if not _within(switch_ratios(result), bound):
            continue
        fit.allowed += 1
        value = objective(result)
        logger.info("filter %s: score %.4f", changes, value)
        if value > fit.score:
            fit.changes, fit.score = dict(changes), value
    if guard is not None and fit.changes:
        fit.verdict = guard(fit.config)
        if not fit.verdict.kept:
            fit.declined, fit.changes, fit.score = fit.changes, {}, fit.default_score
    return fit


def node_parameters(changes: Mapping[str, float]) -> Dict[str, float]:
    """The node's parameter names (``ros.params``) of ``IntentFilterConfig`` changes."""
    return {parameter_name(k): v for k, v in changes.items()}


def cli_options(changes: Mapping[str, float]) -> List[str]:
    """``evaluate`` / ``replay`` options that set the filter to ``changes``."""
    options: List[str] = []
    for name, value in changes.items():
        if name == "enabled":
            options.append("--intent-filter" if value else "--no-intent-filter")
            continue
        options += ["--" + option_dest(name).replace("_", "-"), f"{value:g}"]
    return options


def parameter_file(changes: Mapping[str, float], node: str = "signal_light_detector") -> str:
    """A ROS 2 parameter file (YAML) that sets the node's filter to ``changes``."""
    params = node_parameters(changes)
    lines = ["# The output filter fitted by signal-light calibrate --fit-filter.",
             "# Use: detector --ros-args --params-file THIS_FILE", f"{node}:",
             "  ros__parameters:" + ("" if params else " {}")]
    lines += [f"    {k}: {v!r}" for k, v in sorted(params.items())]
    return "\n".join(lines) + "\n"
