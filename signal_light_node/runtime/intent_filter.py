"""A time-based hold over the model's per-frame light outputs: intent that holds.

The model's blinker probabilities sag in the dark half of every blink, so the published
states and the intent flicker (RIGHT, OFF, RIGHT, OFF, ...), and a short spike of one
side, or both, can make a blinker or a HAZARD for a frame. :class:`IntentFilter` is a
small explicit filter over those outputs, per track and per light, driven by the frame
stamps (scenes run at 10-30 fps, so frame counts mean nothing):

* a frame is **strong** for a light when its P(ON) >= ``on_threshold``; strong frames
  no more than ``hold_s`` apart form one **episode**;
* a light is **ON** while its episode is alive (the last strong frame is at most
  ``hold_s`` old) and confirmed (its strong frames span at least ``confirm_s``, so a
  single short flash or one-frame spike never makes a blinker); it goes OFF ``hold_s``
  after the last strong frame. ``hold_s`` bridges what the model's P(ON) does not hold
  through the dark half of a blink (blinks run at 1.0-2.2 Hz with 30-70 % duty: the dark
  half lasts at most 0.7 s, and the recurrent model bridges most of it);
* when both blinkers are ON but one side had no strong frame since the other side's
  episode began, the silent side was switched off (a change from RIGHT to LEFT): it is
  released at once instead of making HAZARD for ``hold_s``;
* the published probabilities agree with the published state: an ON light keeps the
  largest of its current and its last strong P(ON) (and at least enough to be the most
  likely class), OFF and UNKNOWN sharing the rest in the model's proportions; a light
  held back from ON is OFF, its P(ON) capped at P(OFF), the excess moved to OFF. The
  three still sum to 1. A frame the model judges UNKNOWN passes through unchanged;
* the intent is the model's own intent head with a switch margin (``intent_source:
  head``, the default): a new class is published once its probability beats the
  published class's by ``intent_margin``, its blinking classes behind the same flash gate
  as the blinkers (the head already bridges a blink's dark halves, so it needs no hold;
  docs/model.md, "The intent head instead of the filter's intent"); or, with
  ``intent_source: lights``, it is derived from the published left and right states with
  :func:`~signal_light_node.labels.intent_from_lights` (HAZARD only when both sides are
  ON), its probability from the two published distributions taken as independent; with
  ``blinker_source: intent`` the judged blinkers are read off the head's published intent
  instead (:func:`blinkers_from_intent`), so the two agree;
* the brake is held the same way over ``brake_hold_s`` (without confirmation), or
  passed through as the model says it when that is 0; with ``brake_released_below``, a
  track whose brake has been seen released gets ``brake_onset_shift`` more ON log-odds
  from then on (:mod:`~signal_light_node.runtime.brake_onset`).
* before all of that, a blinker must flash
  (:mod:`~signal_light_node.runtime.flash_gate`): where the engine gives each crop's lamp
  levels, a blinker whose side showed no dark-to-lit change over the last
  ``flash_window_s`` cannot be ON (its P(ON) moves to OFF), so a steady bright lamp is
  not a blinker; and first of all, with ``blinker_sight: geometry`` (``brake_sight``), a
  blinker's (the brake's) UNKNOWN comes from the view head and the boxes
  (:mod:`~signal_light_node.runtime.box_sight`).

Everything is vectorised over the tracks of a frame. The per-track state is a fixed
row of :data:`ROW_WIDTH` floats (per light: stamp of the last strong frame, stamp of
the episode's first strong frame, last strong P(ON); then the flash gate's ring of lamp
levels; then whether the brake has been seen released; last the intent head's published
class), owned by the caller: the
:class:`~signal_light_node.runtime.state_bank.StateBank` in the engine, the evaluation's own
array per batch of tracks. The filter itself keeps no per-track state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Callable, Dict, Mapping, Optional, Union

import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.runtime import brake_onset, box_sight, flash_gate, visibility_hold
from signal_light_node.labels import (CLASS_NAMES, LIGHT_TASKS, TASKS, Intent, LightStatus,
                                      intent_from_lights)

#: Fields of one light in a filter row.
_LAST, _START, _HELD = range(3)
_FIELDS = 3
#: Floats of the hold: the three fields of each of ``LIGHT_TASKS``.
_HOLD_WIDTH = _FIELDS * len(LIGHT_TASKS)
#: Floats of the visibility hold, all lights.
_VISIBILITY_WIDTH = visibility_hold.FIELDS * len(LIGHT_TASKS)
#: Floats per track: the hold's, the visibility hold's, the flash gate's ring, the brake
#: onset's, then the intent head's published class (NaN: none yet).
ROW_WIDTH = _HOLD_WIDTH + _VISIBILITY_WIDTH + flash_gate.WIDTH + brake_onset.FIELDS + 1
_RING_END = _HOLD_WIDTH + _VISIBILITY_WIDTH + flash_gate.WIDTH
_INTENT_AT = ROW_WIDTH - 1

#: Where a light's UNKNOWN comes from (``IntentFilterConfig.blinker_sight``,
#: ``brake_sight``).
SIGHTS = ("model", "geometry")
#: ... and for the brake also ``rear``: judged only where the view head sees the rear.
BRAKE_SIGHTS = SIGHTS + ("rear",)
#: Where the published intent comes from (``IntentFilterConfig.intent_source``).
INTENT_SOURCES = ("lights", "head")
#: Where the published blinkers come from (``IntentFilterConfig.blinker_source``).
BLINKER_SOURCES = ("filter", "intent")

_OFF, _ON, _UNKNOWN = int(LightStatus.OFF), int(LightStatus.ON), int(LightStatus.UNKNOWN)
_LEFT, _RIGHT = LIGHT_TASKS.index("left"), LIGHT_TASKS.index("right")
#: The intents that name each blinker's side, in ``(_LEFT, _RIGHT)`` order.
_NAMING = ((int(Intent.LEFT), int(Intent.HAZARD)), (int(Intent.RIGHT), int(Intent.HAZARD)))

#: ``INTENT_OF[left_state, right_state]``: the one rule of ``labels.intent_from_lights``.
INTENT_OF = np.array([[int(intent_from_lights(a, b)) for b in LightStatus] for a in LightStatus],
                     dtype=np.int64)
#: ``[3, 3, 5]`` one-hot of ``INTENT_OF``, to turn two light distributions into an intent one.
_INTENT_ONE_HOT = np.eye(len(Intent))[INTENT_OF]


def _is_finite_number(value: object) -> bool:
    """A real, finite number (not a bool): what every setting of the filter must be."""
    return (not isinstance(value, bool)
            and isinstance(value, (int, float, np.integer, np.floating))
            and math.isfinite(value))


def _check_seconds(name: str, value: float) -> float:
    if not _is_finite_number(value) or value < 0:
        raise ConfigError(f"{name} must be a finite number of seconds >= 0, got {value!r}")
    return float(value)


#: Fields whose command-line option is not ``--filter-`` + the field without its ``_s``.
_OPTION_STEMS = {"flash_min_evidence": "flash_min"}


def parameter_name(field_name: str) -> str:
    """The node parameter (``ros.params.DetectorParams``) of an ``IntentFilterConfig`` field."""
    return "intent_filter" if field_name == "enabled" else f"filter_{field_name}"


def option_dest(field_name: str) -> str:
    """The argparse destination of an ``IntentFilterConfig`` field's command-line option
    (``commands.options.add_intent_filter_options``: ``--filter-hold`` for ``hold_s``)."""
    if field_name == "enabled":
        return "intent_filter"
    stem = field_name[:-2] if field_name.endswith("_s") else field_name
    return f"filter_{_OPTION_STEMS.get(field_name, stem)}"


def config_from(source: object, name_of: Callable[[str], str]) -> "IntentFilterConfig":
    """An ``IntentFilterConfig`` read field by field from ``source``'s attributes, named by
    ``name_of`` (:func:`parameter_name` or :func:`option_dest`).

    Raises:
        ConfigError: A value is out of range.
    """
    return IntentFilterConfig(**{f.name: getattr(source, name_of(f.name))
                                 for f in fields(IntentFilterConfig)})


@dataclass(frozen=True)
class IntentFilterConfig:
    """Settings of the :class:`IntentFilter`; the one place of their defaults.

    Attributes:
        enabled: False publishes the model's outputs as they are (argmax states, the
            intent head's intent).
        on_threshold: P(ON) from which a frame counts as strong evidence of a light.
        hold_s: A blinker stays ON this long after its last strong frame. The model's
            own P(ON) already bridges most of a dark half, so less than the slowest
            blink's dark half (0.7 s) is needed: 0.6 s scored as well as or better than
            0.8 s (the previous default) on every evaluation set and the hard negatives,
            with intent switches at most 1.38x the truth's (docs/model.md).
        confirm_s: A blinker turns ON only once its strong frames span this long, so
            a single short flash or spike never makes a blinker (or HAZARD); the
            default asks for two strong frames at 10-20 fps, three at 30 fps.
        brake_hold_s: The same hold for the brake light (no confirmation); 0 publishes
            the brake as the model says it. A hold bridges the model's short dips but
            keeps the lamp ON after a release: 0.3 s cut the shipped model's brake
            changes from 1.79x to 1.30x the truth's on the own test split but its brake
            F1 from 87.3 to 82.0 % (README, "Intent that holds"), so the default is 0.
        flash_min_evidence: The flash evidence (:mod:`flash_gate`, 0..1) a blinker's side
            needs before the blinker can be ON; 0 turns the gate off. 0.1 scored best of
            0-0.3 on the held-out family's calibration split (docs/model.md).
        flash_window_s: How far back the flash evidence looks: at least one blink
            period (1 s at the slowest legal 60 per minute) plus its dark part.
        visibility_confirm_s: A light turns from judged (OFF/ON) to UNKNOWN or back only
            once the model has said so this long (:mod:`visibility_hold`); 0 publishes
            the model's verdict every frame.
        blinker_sight: Where a blinker's UNKNOWN comes from: ``model`` (the model's own
            UNKNOWN) or ``geometry`` (:mod:`box_sight`: the view head and how much of
            the box is covered by the image edge or nearer boxes; for cameras unlike the
            training renderer, where the model says UNKNOWN on lamps in plain sight).
        brake_sight: Where the brake's UNKNOWN comes from: ``model``, ``geometry``
            (:func:`box_sight.judge_brake`: judged where the view head sees the rear,
            hidden where it sees the front, the model's own UNKNOWN from a side) or
            ``rear`` (as ``geometry``, and hidden from a side too: a side view's brake
            lamps are slivers no crop resolves; docs/model.md, "A side view's brake").
        brake_released_below: Once a track's brake has been judged with P(ON | judged)
            under this, it has been seen released, and its brake's ON gets
            ``brake_onset_shift`` more log-odds from then on (:mod:`brake_onset`); 0
            turns this off.
        brake_onset_shift: The log-odds added to a seen-released brake's ON.
        brake_onset_rise: With > 0, a seen-released brake's frame gets the shift only
            where its ON log-odds stand this far above the lowest its track has shown
            (a rise against the track's own level); 0 shifts every later frame.
        brake_unreleased_shift: With ``brake_released_below``, the log-odds added to the
            brake's ON while its track has not been seen released (< 0: a vehicle first
            seen with its lamps lit needs a clearer brake; 0: as the model says).
        brake_hysteresis: Log-odds added to the brake's ON while its last judged frame
            came out ON (:mod:`brake_onset`): a release must be clearer than an onset;
            0: none.
        cover_max: With ``geometry``: the share of a box that may be covered before the
            model's own UNKNOWN counts again.
        intent_source: Where the published intent comes from: ``head`` (the model's intent
            head, switched with ``intent_margin``, its blinking classes behind the flash
            gate) or ``lights`` (derived from the published blinkers, so the two always
            agree). ``head`` published 2.3-3.7 points more intent macro-F1 on the
            training renderer's splits and 3.2 on the second generator, with about as
            many false intents on steady night tail lamps (docs/model.md).
        intent_margin: With ``head``: a class other than the published one is published
            once its probability is this much above the published one's (fewer switches;
            0: the head's most likely class every frame).
        blinker_source: Where the published blinkers come from: ``filter`` (the hold over
            the blinker heads) or ``intent`` (with ``intent_source: head``: a blinker the
            filter judges is ON where the published intent names its side, left for LEFT
            or HAZARD, right for RIGHT or HAZARD, and held back where the judged intent
            does not; the filter's own where the intent is UNKNOWN; so blinkers and intent
            agree).
    """

    enabled: bool = True
    on_threshold: float = 0.5
    hold_s: float = 0.6
    confirm_s: float = 0.05
    brake_hold_s: float = 0.0
    flash_min_evidence: float = 0.1
    flash_window_s: float = 1.5
    visibility_confirm_s: float = 0.2
    blinker_sight: str = "model"
    brake_sight: str = "rear"
    cover_max: float = 0.1
    brake_released_below: float = 0.0
    brake_onset_shift: float = 1.0
    brake_onset_rise: float = 0.0
    brake_unreleased_shift: float = 0.0
    brake_hysteresis: float = 0.0
    intent_source: str = "head"
    intent_margin: float = 0.2
    blinker_source: str = "filter"

    def __post_init__(self) -> None:
        if not isinstance(self.enabled, (bool, np.bool_)):
            raise ConfigError(f"enabled must be true or false, got {self.enabled!r}")
        value = self.on_threshold
        if not _is_finite_number(value) or not 0.0 < value <= 1.0:
            raise ConfigError(f"on_threshold must be a probability in (0, 1], got {value!r}")
        object.__setattr__(self, "enabled", bool(self.enabled))
        object.__setattr__(self, "on_threshold", float(value))
        for name in ("hold_s", "confirm_s", "brake_hold_s", "flash_window_s",
                     "visibility_confirm_s"):
            object.__setattr__(self, name, _check_seconds(name, getattr(self, name)))
        value = self.flash_min_evidence
        if not _is_finite_number(value) or not 0.0 <= value < 1.0:
            raise ConfigError(f"flash_min_evidence must be in [0, 1) (0: no flash gate), got "
                              f"{value!r}")
        object.__setattr__(self, "flash_min_evidence", float(value))
        if self.flash_min_evidence > 0 and self.flash_window_s <= 0:
            raise ConfigError("flash_window_s must be > 0 while the flash gate is on "
                              "(flash_min_evidence > 0)")
        for name, allowed in (("blinker_sight", SIGHTS), ("brake_sight", BRAKE_SIGHTS),
                              ("intent_source", INTENT_SOURCES),
                              ("blinker_source", BLINKER_SOURCES)):
            if getattr(self, name) not in allowed:
                raise ConfigError(f"{name} must be one of {', '.join(allowed)}, got "
                                  f"{getattr(self, name)!r}")
        value = self.cover_max
        if not _is_finite_number(value) or not 0.0 <= value <= 1.0:
            raise ConfigError(f"cover_max must be a share in [0, 1], got {value!r}")
        object.__setattr__(self, "cover_max", float(value))
        value = self.brake_released_below
        if not _is_finite_number(value) or not 0.0 <= value < 1.0:
            raise ConfigError(f"brake_released_below must be in [0, 1) (0: off), got {value!r}")
        object.__setattr__(self, "brake_released_below", float(value))
        value = self.brake_onset_shift
        if not _is_finite_number(value) or value < 0.0:
            raise ConfigError(f"brake_onset_shift must be a number >= 0, got {value!r}")
        object.__setattr__(self, "brake_onset_shift", float(value))
        value = self.brake_onset_rise
        if not _is_finite_number(value) or value < 0.0:
            raise ConfigError(f"brake_onset_rise must be a number >= 0 (0: off), got {value!r}")
        object.__setattr__(self, "brake_onset_rise", float(value))
        value = self.brake_unreleased_shift
        if not _is_finite_number(value):
            raise ConfigError(f"brake_unreleased_shift must be a finite number of log-odds, "
                              f"got {value!r}")
        object.__setattr__(self, "brake_unreleased_shift", float(value))
        value = self.brake_hysteresis
        if not _is_finite_number(value) or value < 0.0:
            raise ConfigError(f"brake_hysteresis must be a number >= 0 (0: none), got {value!r}")
        object.__setattr__(self, "brake_hysteresis", float(value))
        value = self.intent_margin
        if not _is_finite_number(value) or not 0.0 <= value < 1.0:
            raise ConfigError(f"intent_margin must be a probability margin in [0, 1), got "
                              f"{value!r}")
        object.__setattr__(self, "intent_margin", float(value))
        if self.blinker_source == "intent" and self.intent_source != "head":
            raise ConfigError("blinker_source intent reads the blinkers off the intent head: "
                              "it needs intent_source head")

    @property
    def brake_onset_settings(self) -> brake_onset.Settings:
        """The ``brake_*`` settings of :mod:`brake_onset`."""
        return brake_onset.Settings(self.brake_released_below, self.brake_onset_shift,
                                    self.brake_onset_rise, self.brake_unreleased_shift,
                                    self.brake_hysteresis)

    def describe(self) -> str:
        """One line for reports: what is published."""
        if not self.enabled:
            return "off (the raw model: argmax of every head, the intent head's intent)"
        brake = f"brake held {self.brake_hold_s:g} s" if self.brake_hold_s > 0 \
            else "brake as the model says"
        if self.brake_released_below > 0:
            brake += (f", ON +{self.brake_onset_shift:g} log-odds once seen released "
                      f"(P(ON) < {self.brake_released_below:g})")
            if self.brake_onset_rise > 0:
                brake += f" on a rise of {self.brake_onset_rise:g} over the track's lowest"
            if self.brake_unreleased_shift != 0:
                brake += f", {self.brake_unreleased_shift:+g} until then"
        if self.brake_hysteresis > 0:
            brake += f", +{self.brake_hysteresis:g} log-odds while ON (hysteresis)"
        gate = (f"a blinker must flash (evidence >= {self.flash_min_evidence:g} over "
                f"{self.flash_window_s:g} s)" if self.flash_min_evidence > 0 else "no flash gate")
        seen = (f"; visibility changes after {self.visibility_confirm_s:g} s"
                if self.visibility_confirm_s > 0 else "")
        geometry = [name for name, sight in (("blinkers", self.blinker_sight),
                                             ("brake", self.brake_sight)) if sight != "model"]
        if self.brake_sight == "rear":
            geometry[-1] = "brake (hidden from a side too)"
        if geometry:
            seen += (f"; {' and '.join(geometry)} UNKNOWN from the view and boxes covered "
                     f"over {self.cover_max:g}")
        return (f"on (blinkers ON from P(ON) >= {self.on_threshold:g} over >= "
                f"{self.confirm_s:g} s, held {self.hold_s:g} s after the last; {gate}{seen}; "
                f"{self._intent_source()}; {brake})")

    def _intent_source(self) -> str:
        if self.intent_source == "head":
            blinkers = ", blinkers read off it" if self.blinker_source == "intent" else ""
            return (f"intent from the intent head, switched on a margin of "
                    f"{self.intent_margin:g}{blinkers}")
        return "intent from the held blinkers"


@dataclass(frozen=True)
class FilterOutput:
    """What the filter publishes for the tracks of one step.

    Attributes:
        probs: Task -> ``[N, K]`` probabilities (``TASKS``; rows sum to 1), the lights
            and the intent as published, the view as the model gave it.
        states: Task -> int64 ``[N]`` published classes.
        rows: float64 ``[N, ROW_WIDTH]``: the tracks' new filter rows.
    """

    probs: Dict[str, np.ndarray]
    states: Dict[str, np.ndarray]
    rows: np.ndarray


def argmax_states(probs: Mapping[str, np.ndarray]) -> Dict[str, np.ndarray]:
    """The most likely class of every task and row: what the raw model says."""
    return {t: np.asarray(p).argmax(axis=1).astype(np.int64) for t, p in probs.items()}


class IntentFilter:
    """The hold filter (see the module docstring); stateless, vectorised over tracks.

    Args:
        config: Settings; the defaults when None.
    """

    def __init__(self, config: IntentFilterConfig | None = None) -> None:
        self.config = config or IntentFilterConfig()
        c = self.config
        self._threshold = c.on_threshold
        hold = {"brake": c.brake_hold_s, "left": c.hold_s, "right": c.hold_s}
        confirm = {"brake": 0.0, "left": c.confirm_s, "right": c.confirm_s}
        self._hold = np.array([hold[t] for t in LIGHT_TASKS])
        self._confirm = np.array([confirm[t] for t in LIGHT_TASKS])
        self._filtered = [t != "brake" or c.brake_hold_s > 0 for t in LIGHT_TASKS]
        self._hiding = tuple((LIGHT_TASKS.index(t), face)
                             for t, face in box_sight.HIDING_FACE.items())

    @property
    def gates_flashes(self) -> bool:
        """Whether :meth:`step` uses lamp levels (callers compute them only then)."""
        return self.config.enabled and self.config.flash_min_evidence > 0

    @property
    def uses_cover(self) -> bool:
        """Whether :meth:`step` uses box covers (callers compute them only then)."""
        return self.config.enabled and (self.config.blinker_sight, self.config.brake_sight) \
            != ("model", "model")

    @staticmethod
    def initial_rows(n: int) -> np.ndarray:
        """float64 ``[n, ROW_WIDTH]``: the rows of tracks that have shown nothing yet."""
        rows = np.zeros((n, len(LIGHT_TASKS), _FIELDS))
        rows[:, :, (_LAST, _START)] = np.nan
        return np.concatenate([rows.reshape(n, _HOLD_WIDTH),
                               visibility_hold.initial_rows(n, len(LIGHT_TASKS)),
                               flash_gate.initial_rows(n), brake_onset.initial_rows(n),
                               np.full((n, 1), np.nan)], axis=1)

    def step(self, probs: Mapping[str, np.ndarray], stamps_ns: Union[int, np.ndarray],
             rows: np.ndarray, lamp_levels: Optional[np.ndarray] = None,
             cover: Optional[np.ndarray] = None) -> FilterOutput:
        """Filter one frame of every track.

        Args:
            probs: Task -> ``[N, K]`` model probabilities (every task of ``TASKS``).
            stamps_ns: The frame stamp of each track (``[N]``), or one for all.
            rows: float64 ``[N, ROW_WIDTH]``: the tracks' filter rows before this frame.
            lamp_levels: ``[N, 2]`` :func:`flash_gate.lamp_levels` of the tracks' crops;
                None (a caller without crops) leaves the flash gate out of this frame.
            cover: ``[N]`` :func:`box_sight.box_cover` of the tracks' boxes (NaN where not
                known); None keeps the model's UNKNOWN (as ``blinker_sight: model``).

        Returns:
            The published probabilities and states and the new rows (``rows`` itself is
            not modified). With the filter disabled: the model's probabilities, their
            argmax and the rows unchanged.

        Raises:
            ConfigError: A task is missing or the shapes disagree.
        """
        rows = _check_inputs(probs, rows)
        if not self.config.enabled:
            return FilterOutput(dict(probs), argmax_states(probs), rows.copy())
        n = rows.shape[0]
        now = np.broadcast_to(np.asarray(stamps_ns, np.int64), (n,)) * 1e-9
        p = np.stack([np.asarray(probs[t], np.float64) for t in LIGHT_TASKS], axis=1)
        state = rows[:, :_HOLD_WIDTH].reshape(n, len(LIGHT_TASKS), _FIELDS).copy()
        shown = rows[:, _HOLD_WIDTH:_HOLD_WIDTH + _VISIBILITY_WIDTH]
        ring = rows[:, _HOLD_WIDTH + _VISIBILITY_WIDTH:_RING_END]
        released = rows[:, _RING_END:_INTENT_AT]
        intent_row = rows[:, _INTENT_AT:]
        if cover is not None and self.uses_cover:
            p = self._judge_sight(p, probs["view"], np.asarray(cover).reshape(n))
        evidence = None
        if lamp_levels is not None and self.config.flash_min_evidence > 0:
            ring = flash_gate.push(ring, now, np.asarray(lamp_levels, np.float64).reshape(n, 2))
            evidence = flash_gate.side_evidence(
                flash_gate.half_evidence(ring, now, self.config.flash_window_s), probs["view"])
            p = flash_gate.veto(p, evidence, self.config.flash_min_evidence, (_LEFT, _RIGHT))
        if self.config.brake_released_below > 0 or self.config.brake_hysteresis > 0:
            brake = LIGHT_TASKS.index("brake")
            p[:, brake], released = brake_onset.step(p[:, brake], released,
                                                     self.config.brake_onset_settings)
        if self.config.visibility_confirm_s > 0:
            p, shown = visibility_hold.step(p, now, shown, self.config.visibility_confirm_s)
        on = self._advance(state, p, now[:, None])
        q, light_states = _publish(p, on, state[..., _HELD])
        intent = None
        if self.config.intent_source == "head":
            head = probs["intent"] if evidence is None else flash_gate.veto_intent(
                probs["intent"], evidence, self.config.flash_min_evidence)
            intent = head_intent(head, intent_row[:, 0], self.config.intent_margin)
            intent_row = intent[1].astype(np.float64)[:, None]
            if self.config.blinker_source == "intent":
                on = blinkers_from_intent(on, light_states, intent[1])
                q, light_states = _publish(p, on, state[..., _HELD])
        raw = argmax_states({t: p[:, i] for i, t in enumerate(LIGHT_TASKS)})
        out_probs, out_states = dict(probs), {"view": np.asarray(probs["view"]).argmax(1)}
        for i, task in enumerate(LIGHT_TASKS):
            keep = self._filtered[i]
            out_probs[task] = q[:, i] if keep else p[:, i]
            out_states[task] = light_states[:, i] if keep else raw[task]
        if intent is not None:
            out_probs["intent"], out_states["intent"] = intent
        else:
            out_probs["intent"], out_states["intent"] = _intent(out_probs, out_states)
        return FilterOutput(out_probs, {t: out_states[t] for t in TASKS},
                            np.concatenate([state.reshape(n, _HOLD_WIDTH), shown, ring, released,
                                            intent_row], axis=1))

    def _judge_sight(self, p: np.ndarray, view: np.ndarray, cover: np.ndarray) -> np.ndarray:
        """``p`` with the UNKNOWN of the lights whose sight is ``geometry`` from
        :mod:`box_sight`."""
        c = self.config
        if c.blinker_sight == "geometry":
            p = box_sight.judge_blinkers(p, view, cover, c.cover_max, self._hiding)
        if c.brake_sight != "model":
            p = box_sight.judge_brake(p, view, cover, c.cover_max, LIGHT_TASKS.index("brake"),
                                      side_hides=c.brake_sight == "rear")
        return p

    def _advance(self, state: np.ndarray, p: np.ndarray, now: np.ndarray) -> np.ndarray:
        """Update the rows in place with this frame; returns bool ``[N, lights]`` ON."""
        last, start, held = state[..., _LAST], state[..., _START], state[..., _HELD]
        strong = p[..., _ON] >= self._threshold
        with np.errstate(invalid="ignore"):
            alive = (now - last) <= self._hold
        new_episode = strong & ~alive
        start[new_episode] = np.broadcast_to(now, start.shape)[new_episode]
        last[strong] = np.broadcast_to(now, last.shape)[strong]
        held[strong] = p[..., _ON][strong]
        with np.errstate(invalid="ignore"):
            on = ((now - last) <= self._hold) & ((last - start) >= self._confirm)
        # Both blinkers ON, one silent since the other's episode began: it was switched off.
        both = on[:, _LEFT] & on[:, _RIGHT]
        for side, other in ((_LEFT, _RIGHT), (_RIGHT, _LEFT)):
            released = both & (last[:, side] < start[:, other])
            on[released, side] = False
            state[released, side] = (np.nan, np.nan, 0.0)
        return on


def _check_inputs(probs: Mapping[str, np.ndarray], rows: np.ndarray) -> np.ndarray:
    rows = np.asarray(rows, np.float64)
    if rows.ndim != 2 or rows.shape[1] != ROW_WIDTH:
        raise ConfigError(f"filter rows must be [N, {ROW_WIDTH}], got shape {rows.shape}")
    for task in TASKS:
        if task not in probs:
            raise ConfigError(f"filter input lacks the {task!r} probabilities")
        shape = np.shape(probs[task])
        if shape != (rows.shape[0], len(CLASS_NAMES[task])):
            raise ConfigError(f"{task} probabilities must be [{rows.shape[0]}, "
                              f"{len(CLASS_NAMES[task])}], got {shape}")
    return rows


def _publish(p: np.ndarray, on: np.ndarray, held: np.ndarray) -> tuple:
    """Published ``[N, lights, 3]`` probabilities and ``[N, lights]`` states.

    ON keeps max(P(ON), held P(ON), the least that makes ON the most likely class), OFF
    and UNKNOWN sharing the rest in the model's proportions. Otherwise the light is OFF:
    P(ON) is capped at P(OFF) (a no-op where the model said OFF), the excess moved to
    OFF. A frame whose most likely class is UNKNOWN passes through.
    """
    off, p_on, unknown = p[..., _OFF], p[..., _ON], p[..., _UNKNOWN]
    rest = off + unknown
    has_rest = rest > 0
    safe = np.where(has_rest, rest, 1.0)
    top = np.where(has_rest, np.maximum(off, unknown) / safe, 1.0)
    tie = top / (1.0 + top)  # P(ON) equal to the larger of the rescaled OFF and UNKNOWN
    held_on = np.maximum(np.maximum(p_on, held), tie)
    scale = (1.0 - held_on) / safe
    capped = np.minimum(p_on, (1.0 - unknown) / 2.0)
    q_on = np.where(on, held_on, capped)
    q_off = np.where(on, np.where(has_rest, off * scale, 1.0 - held_on), 1.0 - unknown - capped)
    q_unknown = np.where(on, unknown * scale, unknown)
    q = np.stack([q_off, q_on, q_unknown], axis=-1)
    # Held back from ON: OFF, unless UNKNOWN outweighs both (the model all but said it).
    states = np.where(on, _ON, np.where(q_off >= q_unknown, _OFF, _UNKNOWN))
    passed = p.argmax(axis=-1) == _UNKNOWN
    return np.where(passed[..., None], p, q), np.where(passed, _UNKNOWN, states).astype(np.int64)


def head_intent(probs: np.ndarray, published: np.ndarray, margin: float) -> tuple:
    """The intent head's ``[N, 5]`` probabilities and ``[N]`` classes with a switch margin.

    A track keeps its ``published`` class (NaN: none yet, the most likely is taken) until
    another class's probability is more than ``margin`` above it. The published
    probabilities agree with the class: its probability is raised to the largest, the rows
    renormalised.
    """
    p = np.asarray(probs, np.float64)
    rows = np.arange(p.shape[0])
    best = p.argmax(axis=1)
    current = np.where(np.isnan(published), best, np.nan_to_num(published)).astype(np.int64)
    states = np.where(p[rows, best] > p[rows, current] + margin, best, current)
    q = p.copy()
    q[rows, states] = p[rows, best]
    return q / q.sum(axis=1, keepdims=True), states


def blinkers_from_intent(on: np.ndarray, states: np.ndarray, intent: np.ndarray) -> np.ndarray:
    """The ``[N, lights]`` ON mask with the blinkers read off the published intent.

    A blinker whose published ``states`` is judged (OFF or ON) is ON where ``intent`` (``[N]``
    classes) names its side and held back where it is judged and does not; where the intent
    is UNKNOWN, or the blinker is not judged, ``on`` stands.
    """
    on = on.copy()
    judged_intent = intent != int(Intent.UNKNOWN)
    for side, naming in zip((_LEFT, _RIGHT), _NAMING):
        judged = judged_intent & (states[:, side] != _UNKNOWN)
        on[judged, side] = np.isin(intent[judged], naming)
    return on


def _intent(probs: Mapping[str, np.ndarray], states: Mapping[str, np.ndarray]) -> tuple:
    """Intent ``[N, 5]`` probabilities and ``[N]`` classes from the published blinkers."""
    dist = np.einsum("na,nb,abk->nk", probs["left"], probs["right"], _INTENT_ONE_HOT)
    return dist, INTENT_OF[states["left"], states["right"]]
