"""Whether a light can be seen changes only once the model has said so for a while.

A light is *judged* (OFF or ON) or UNKNOWN (its lamps cannot be seen). Where the model is
unsure whether a lamp is visible, its most likely class swaps between UNKNOWN and OFF
from frame to frame; on the independent renders those swaps are most of the published
intent changes (docs/model.md, "Visibility that holds"). This hold publishes a change of
visibility only after the model's new verdict has lasted ``confirm_s`` seconds (stamp
time); until then the light keeps its last published visibility, with its probabilities
moved just enough that the published class agrees (OFF and ON keep their ratio). A new
track adopts the model's first verdict at once.

Per light, two floats of the track's filter row: the published visibility (1 judged, 0
UNKNOWN, NaN before the first frame) and the stamp since which the model has disagreed
(NaN while it agrees). Pure numpy, vectorised over tracks and lights.
"""

from __future__ import annotations

import numpy as np

from signal_light_node.labels import LightStatus

#: Floats per light in a filter row.
FIELDS = 2
_SHOWN, _SINCE = range(FIELDS)
_OFF, _ON, _UNKNOWN = int(LightStatus.OFF), int(LightStatus.ON), int(LightStatus.UNKNOWN)
#: How far past the tie a moved UNKNOWN probability goes (keeps the argmax unambiguous).
_MARGIN = 1e-3


def initial_rows(n: int, lights: int) -> np.ndarray:
    """float64 ``[n, lights * FIELDS]``: tracks that have shown nothing yet."""
    return np.full((n, lights * FIELDS), np.nan)


def step(p: np.ndarray, now_s: np.ndarray, rows: np.ndarray, confirm_s: float
         ) -> tuple:
    """One frame: the probabilities to publish and the new rows.

    Args:
        p: ``[N, lights, 3]`` (OFF, ON, UNKNOWN) model probabilities.
        now_s: ``[N]`` frame stamps in seconds.
        rows: ``[N, lights * FIELDS]`` (not modified).
        confirm_s: How long a new verdict must last before it is published.

    Returns:
        ``(probabilities [N, lights, 3], rows [N, lights * FIELDS])``.
    """
    n, lights = p.shape[:2]
    state = np.array(rows, np.float64, copy=True).reshape(n, lights, FIELDS)
    shown, since = state[..., _SHOWN], state[..., _SINCE]
    seen = p[..., :2].sum(-1) > 0
    verdict = ((p.argmax(-1) != _UNKNOWN) & seen).astype(np.float64)
    now = np.broadcast_to(np.asarray(now_s, np.float64)[:, None], verdict.shape)
    first = np.isnan(shown)
    shown[first] = verdict[first]
    agrees = verdict == shown
    since[agrees] = np.nan
    starts = ~agrees & np.isnan(since)
    since[starts] = now[starts]
    with np.errstate(invalid="ignore"):
        lasted = ~agrees & (now - since >= confirm_s)
    shown[lasted] = verdict[lasted]
    since[lasted] = np.nan
    return _agree(p, shown == 1.0, seen), state.reshape(n, lights * FIELDS)


def with_unknown(p: np.ndarray, unknown: np.ndarray, where: np.ndarray) -> np.ndarray:
    """``p`` (``[..., 3]`` OFF, ON, UNKNOWN) with P(UNKNOWN) set to ``unknown`` where
    ``where``, OFF and ON sharing the rest in their ratio; a row whose OFF and ON are both
    0 has no ratio to keep and stays as it is. ``p`` is not modified."""
    out = np.array(p, np.float64, copy=True)
    off_on = out[..., :2].sum(-1)
    change = where & (off_on > 0)
    scale = (1.0 - unknown) / np.where(off_on > 0, off_on, 1.0)
    out[..., :2] = np.where(change[..., None], out[..., :2] * scale[..., None], out[..., :2])
    out[..., _UNKNOWN] = np.where(change, unknown, out[..., _UNKNOWN])
    return out


def _agree(p: np.ndarray, judged: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """``p`` with P(UNKNOWN) moved just past the larger of OFF and ON where the published
    visibility and the model's argmax differ; OFF and ON share the rest in their ratio."""
    off_on = p[..., :2].sum(-1)
    top = p[..., :2].max(-1)
    tie = top / (np.where(off_on > 0, off_on, 1.0) + top)  # P(UNKNOWN) = larger rescaled OFF/ON
    model_judged = p.argmax(-1) != _UNKNOWN
    unknown = p[..., _UNKNOWN]
    lower = judged & ~model_judged & seen
    raise_ = ~judged & model_judged
    new_unknown = np.where(lower, np.minimum(unknown, tie * (1 - _MARGIN)),
                           np.minimum(1.0, np.maximum(unknown, tie * (1 + _MARGIN))))
    return with_unknown(p, new_unknown, lower | raise_)
