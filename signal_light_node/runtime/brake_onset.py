"""A brake is switched on at a moment: once a track has shown its brake released, a rise
counts for more.

A steady lit tail lamp at night and a brake look alike to the model in a single frame,
and a vehicle first seen with its lamps lit may be either; so the brake's ON takes a
strict operating point (the model file's ``on_offsets``), which also costs brakes that
the model sees rise on a vehicle it has just seen unbraked (docs/model.md, "Where the
held-out family's brake F1 goes"). This step tells the two cases apart by the track's own
past: once the brake has been judged with P(ON | judged) under ``released_below`` the
track has shown its lamps unbraked, and from that frame on the brake's ON log-odds get
``shift`` more. A vehicle never seen released keeps the strict point, so a tail lamp that
stays lit (the model's P(ON) on such tracks seldom falls that low) gains nothing.

With ``rise`` > 0 the shift is stated against the track's own levels: a frame of a
released track gets it only where its ON log-odds stand ``rise`` above the lowest the
track has shown. A camera the model reads with a high unbraked level (the second
generator's released frames sit at P(ON) about 0.13, the training family's at 0.01) then
needs a real step before its middling frames count as braking.

With ``unreleased_shift`` < 0 the other side of the same evidence is used as well: until a
track has been seen released, its brake's ON log-odds get that (negative) shift, so a
vehicle first seen with its lamps lit needs a clearer brake, and a tail lamp that stays lit
at night, which the model puts at a median P(ON) of 0.43, is not published braking.

With ``hysteresis`` > 0 a brake that came out ON keeps that many more log-odds until it
comes out OFF: a release has to be clearer than an onset, so a brake the model holds near
its operating point does not flicker. Together with a negative ``unreleased_shift`` a
steady tail lamp never turns ON in the first place, so it cannot latch.

Three floats per track in the filter row: 1 once the brake has been seen released (else
0), the lowest judged ON log-odds so far (NaN before the first judged frame), and 1 while
the brake last came out of this step ON (an UNKNOWN frame keeps it). Pure numpy,
vectorised over tracks.
"""

from __future__ import annotations

from typing import NamedTuple, Tuple

import numpy as np

from signal_light_node.labels import LightStatus
from signal_light_node.runtime.visibility_hold import with_unknown

#: Floats per track in a filter row.
FIELDS = 3
_SEEN, _FLOOR, _WAS_ON = 0, 1, 2
_ON, _UNKNOWN = int(LightStatus.ON), int(LightStatus.UNKNOWN)
#: P(ON | judged) is clipped to this distance from 0 and 1 before its log-odds are taken.
_EPS = 1e-6


class Settings(NamedTuple):
    """What :func:`step` does (``IntentFilterConfig``'s ``brake_*`` fields, module doc).

    Attributes:
        released_below: P(ON | judged) under which a judged brake counts as released
            (0: no release is ever seen, and neither shift applies).
        shift: Log-odds added to ON once the track has been seen released.
        rise: With > 0, the shift applies only to frames whose ON log-odds (against OFF)
            stand at least this far above the lowest the track has shown while judged.
        unreleased_shift: Log-odds added to ON while the track has not been seen released.
        hysteresis: Log-odds added to ON while the track's last judged frame came out of
            this step ON.
    """

    released_below: float = 0.0
    shift: float = 0.0
    rise: float = 0.0
    unreleased_shift: float = 0.0
    hysteresis: float = 0.0


def initial_rows(n: int) -> np.ndarray:
    """float64 ``[n, FIELDS]``: tracks whose brake has not been seen released or judged."""
    rows = np.zeros((n, FIELDS))
    rows[:, _FLOOR] = np.nan
    return rows


def shift_on(p: np.ndarray, shift: "float | np.ndarray") -> np.ndarray:
    """``p`` (``[..., 3]`` OFF, ON, UNKNOWN) with the ON log-odds against OFF moved by
    ``shift`` (broadcast over the rows); UNKNOWN keeps its probability. Not in place."""
    p = np.asarray(p, np.float64)
    raised = p.copy()
    raised[..., _ON] *= np.exp(shift)
    return with_unknown(raised, p[..., _UNKNOWN], np.ones(p.shape[:-1], bool))


def step(p: np.ndarray, rows: np.ndarray, settings: Settings
         ) -> Tuple[np.ndarray, np.ndarray]:
    """One frame of the brake: its probabilities to publish and the new rows.

    Args:
        p: ``[N, 3]`` the brake's (OFF, ON, UNKNOWN) probabilities.
        rows: ``[N, FIELDS]`` (not modified).
        settings: What to shift, and when.

    Returns:
        ``(probabilities [N, 3], rows [N, FIELDS])``.
    """
    p = np.asarray(p, np.float64)
    rows = np.asarray(rows, np.float64)
    off_on = p[:, :2].sum(-1)
    judged = (p.argmax(-1) != _UNKNOWN) & (off_on > 0)
    ratio = p[:, _ON] / np.where(judged, off_on, 1.0)
    q = np.clip(ratio, _EPS, 1.0 - _EPS)
    log_odds = np.log(q / (1.0 - q))
    seen = np.maximum(rows[:, _SEEN], judged & (ratio < settings.released_below))
    floor = np.fmin(rows[:, _FLOOR], np.where(judged, log_odds, np.nan))
    shift = settings.hysteresis * rows[:, _WAS_ON]
    if settings.released_below > 0:
        gain = seen if settings.rise <= 0 else \
            seen * (judged & (log_odds - floor >= settings.rise))
        shift = shift + np.where(seen > 0, settings.shift * gain, settings.unreleased_shift)
    out = shift_on(p, shift)
    state = out.argmax(-1)
    was_on = np.where(state == _UNKNOWN, rows[:, _WAS_ON], state == _ON)
    return out, np.stack([seen, floor, was_on], axis=1)
