"""Which lights can be seen, from geometry: the boxes of a frame and the view head.

A blinker cannot be judged when the side it sits on faces away from the camera, or when
something stands in front of the vehicle. Both are geometry, not appearance: the view head
says which face the camera sees, and the tracker's boxes say how much of each box lies
outside the image or behind a nearer vehicle (on a flat road a box whose bottom edge is
lower in the image stands nearer). The model's own UNKNOWN is learnt from how the training
renderer draws hidden and tiny lamps, and on vehicles drawn otherwise it says UNKNOWN
where the lamps are in plain sight (53 % of such frames on the independent renders).

With ``blinker_sight: geometry`` (:class:`~signal_light_node.runtime.intent_filter.
IntentFilterConfig`) a blinker's P(UNKNOWN) becomes the view head's probability of the face
that hides its side, where the box's **cover** (its share outside the image or inside a
nearer box) is at most ``cover_max``; where more of it is covered, the larger of that and
the model's own P(UNKNOWN). ON and OFF share the rest in the model's proportions. A track
whose cover is not known (NaN) keeps the model's UNKNOWN. With ``brake_sight: geometry``
the brake is judged the same way from the faces that hide the rear lamps
(:func:`judge_brake`); with ``brake_sight: rear`` a side view hides them too.

Measured (docs/model.md, "Visibility from geometry"; the shipped model as the node runs
it): intent macro-F1 on the independent renders rose from 30.5 to 43.9 %, UNKNOWN where a
lamp is visible fell from 53 to 26 %; on our own renderer's bags it fell by about 3 points
(its truth calls lamps UNKNOWN that the boxes do not show hidden: too small, foreshortened,
behind unlisted vehicles), so the default stays ``model``.

Pure numpy, vectorised over the boxes of a frame.
"""

from __future__ import annotations

from typing import Sequence, Tuple

import numpy as np

from signal_light_node.boxes import TrackBox
from signal_light_node.labels import LightStatus, View
from signal_light_node.runtime.visibility_hold import with_unknown

_UNKNOWN = int(LightStatus.UNKNOWN)
#: Points per box edge at which the cover is sampled (GRID x GRID per box).
GRID = 16
#: The face seen that hides each blinker: from the vehicle's LEFT face its right side is
#: away from the camera, and the reverse.
HIDING_FACE = {"left": View.RIGHT, "right": View.LEFT}


def box_cover(boxes: np.ndarray, width: int, height: int) -> np.ndarray:
    """float64 ``[N]``: the share of each box outside the image or inside a nearer box.

    A box is nearer when its bottom edge is lower in the image (larger ``y1``). The share
    is sampled on a ``GRID`` x ``GRID`` lattice of points inside each box.

    Args:
        boxes: ``[N, 4]`` boxes ``(x0, y0, x1, y1)`` in pixels. A box with a non-finite
            edge gets NaN and covers nothing.
        width: Image width in pixels.
        height: Image height in pixels.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    n = len(boxes)
    if n == 0:
        return np.zeros(0)
    finite = np.isfinite(boxes).all(axis=1)
    b = np.where(finite[:, None], boxes, 0.0)
    t = (np.arange(GRID) + 0.5) / GRID
    xs = b[:, 0:1] + t * (b[:, 2:3] - b[:, 0:1])  # [N, G]
    ys = b[:, 1:2] + t * (b[:, 3:4] - b[:, 1:2])
    outside = ((xs < 0) | (xs >= width))[:, None, :] | ((ys < 0) | (ys >= height))[:, :, None]
    nearer = (b[None, :, 3] > b[:, None, 3]) & finite[None, :]  # [i, j]: j is nearer than i
    in_x = (xs[:, :, None] >= b[None, None, :, 0]) & (xs[:, :, None] <= b[None, None, :, 2])
    in_y = (ys[:, :, None] >= b[None, None, :, 1]) & (ys[:, :, None] <= b[None, None, :, 3])
    in_y &= nearer[:, None, :]
    # [i, y, x]: some nearer box j holds both the point's row and its column.
    behind = np.einsum("iyj,ixj->iyx", in_y.astype(np.float32), in_x.astype(np.float32)) > 0
    cover = (outside | behind).mean(axis=(1, 2))
    return np.where(finite, cover, np.nan)


def boxes_array(boxes: Sequence[TrackBox]) -> np.ndarray:
    """float64 ``[N, 4]`` ``(x0, y0, x1, y1)`` of ``boxes``."""
    return np.array([(b.x0, b.y0, b.x1, b.y1) for b in boxes], np.float64).reshape(-1, 4)


def judge_blinkers(p: np.ndarray, view: np.ndarray, cover: np.ndarray, cover_max: float,
                   columns: Tuple[Tuple[int, int], ...]) -> np.ndarray:
    """The lights' probabilities with the blinkers' UNKNOWN from geometry (module doc).

    Args:
        p: ``[N, lights, 3]`` OFF/ON/UNKNOWN probabilities (not modified).
        view: ``[N, len(View)]`` the view head's probabilities.
        cover: ``[N]`` :func:`box_cover` of the tracks' boxes; NaN where not known.
        cover_max: Cover up to which the view head alone decides.
        columns: ``(light column of p, hiding face)`` of each blinker.

    Returns:
        A new ``[N, lights, 3]`` array; rows still sum to 1. A row whose OFF and ON are
        both 0 stays as the model gave it.
    """
    out = p.copy()
    view = np.asarray(view, np.float64)
    for column, face in columns:
        out[:, column] = _judged(p[:, column], view[:, int(face)], cover, cover_max)
    return out


def side_mass(view: np.ndarray) -> np.ndarray:
    """The view head's probability that a side faces the camera, P(LEFT) + P(RIGHT), over
    the last axis of ``view`` (``[..., 4]``)."""
    view = np.asarray(view, np.float64)
    return view[..., int(View.LEFT)] + view[..., int(View.RIGHT)]


def judge_brake(p: np.ndarray, view: np.ndarray, cover: np.ndarray, cover_max: float,
                column: int, side_hides: bool = False) -> np.ndarray:
    """The lights' probabilities with the brake's UNKNOWN from geometry.

    The rear lamps face away from a camera that sees the FRONT, and are in plain sight of
    one that sees the rear (BEHIND). From a side the rear may be foreshortened out of
    sight or still show (a three-quarter view), which the view head cannot tell: there the
    model's own UNKNOWN decides. So P(UNKNOWN) = P(FRONT) + P(LEFT or RIGHT) * the model's
    P(UNKNOWN); where the box's cover exceeds ``cover_max``, the larger of that and the
    model's. With ``side_hides`` (``brake_sight: rear``) a side hides the brake too:
    P(UNKNOWN) = 1 - P(BEHIND). Arguments and return as :func:`judge_blinkers`, with
    ``column`` the brake's light column of ``p``.
    """
    out = p.copy()
    view = np.asarray(view, np.float64)
    q = p[:, column]
    side = side_mass(view)
    from_side = side if side_hides else side * q[:, _UNKNOWN]
    out[:, column] = _judged(q, view[:, int(View.FRONT)] + from_side, cover, cover_max)
    return out


def _judged(q: np.ndarray, hidden: np.ndarray, cover: np.ndarray, cover_max: float
            ) -> np.ndarray:
    """One light's ``[N, 3]`` probabilities with P(UNKNOWN) = ``hidden`` (the larger of it
    and the model's where the cover exceeds ``cover_max``; the model's where the cover is
    not known)."""
    cover = np.asarray(cover, np.float64)
    unknown = np.where(cover > cover_max, np.maximum(hidden, q[:, _UNKNOWN]), hidden)
    return with_unknown(q, unknown, np.isfinite(cover))
