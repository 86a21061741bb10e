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

Two floats per track in the filter row: 1 once the brake has been seen released (else 0),
and the lowest judged ON log-odds so far (NaN before the first judged frame). Pure numpy,
vectorised over tracks.
"""

from __future__ import annotations

from typing import Tuple

import numpy as np

from signal_light_node.labels import LightStatus
from signal_light_node.runtime.visibility_hold import with_unknown

#: Floats per track in a filter row.
FIELDS = 2
_SEEN, _FLOOR = 0, 1
_ON, _UNKNOWN = int(LightStatus.ON), int(LightStatus.UNKNOWN)
#: P(ON | judged) is clipped to this distance from 0 and 1 before its log-odds are taken.
_EPS = 1e-6


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


def step(p: np.ndarray, rows: np.ndarray, released_below: float, shift: float,
         rise: float = 0.0, unreleased_shift: float = 0.0) -> Tuple[np.ndarray, np.ndarray]:
    """One frame of the brake: its probabilities to publish and the new rows.

    Args:
        p: ``[N, 3]`` the brake's (OFF, ON, UNKNOWN) probabilities.
        rows: ``[N, FIELDS]`` (not modified).
        released_below: P(ON | judged) under which a judged brake counts as released.
        shift: Log-odds added to ON once the track has been seen released.
        rise: With > 0, the shift applies only to frames whose ON log-odds (against OFF)
            stand at least this far above the lowest the track has shown while judged.
        unreleased_shift: Log-odds added to ON while the track has not been seen released.

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
    seen = np.maximum(rows[:, _SEEN], judged & (ratio < released_below))
    floor = np.fmin(rows[:, _FLOOR], np.where(judged, log_odds, np.nan))
    gain = seen if rise <= 0 else seen * (judged & (log_odds - floor >= rise))
    return (shift_on(p, np.where(seen > 0, shift * gain, unreleased_shift)),
            np.stack([seen, floor], axis=1))
