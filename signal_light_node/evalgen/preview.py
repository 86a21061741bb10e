"""Contact sheets of generated frames with their tracker boxes and truth, for eyeballing."""

from __future__ import annotations

import os
from typing import List, Sequence

import cv2
import numpy as np

from signal_light_node.errors import ConfigError
from signal_light_node.evalgen.truth import EvalFrame

_SHORT = {0: "OFF", 1: "ON", 2: "UNK"}


def annotate(frame: EvalFrame) -> np.ndarray:
    """A copy of the frame's image with every tracker box and its truth written over it."""
    img = frame.image.copy()
    for v in frame.vehicles:
        box = v.tracker_box
        if box is None:
            continue
        p0, p1 = (int(box.x0), int(box.y0)), (int(box.x1), int(box.y1))
        cv2.rectangle(img, p0, p1, (0, 255, 0), 1)
        text = (f"{v.track_id} {v.view.name[0]} B:{_SHORT[int(v.brake)]} L:{_SHORT[int(v.left)]} "
                f"R:{_SHORT[int(v.right)]}")
        cv2.putText(img, text, (p0[0], max(p0[1] - 4, 10)), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(img, text, (p0[0], max(p0[1] - 4, 10)), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (255, 255, 255), 1, cv2.LINE_AA)
    cv2.putText(img, f"#{frame.index} {frame.lighting}", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6,
                (255, 255, 255), 2, cv2.LINE_AA)
    return img


def contact_sheet(frames: Sequence[EvalFrame], columns: int = 2, scale: float = 0.5) -> np.ndarray:
    """Annotated frames tiled ``columns`` wide, each scaled by ``scale``.

    Raises:
        ConfigError: No frames, or a bad layout.
    """
    if not frames or columns < 1 or scale <= 0:
        raise ConfigError("a contact sheet needs frames, columns >= 1 and scale > 0")
    tiles: List[np.ndarray] = [cv2.resize(annotate(f), None, fx=scale, fy=scale,
                                          interpolation=cv2.INTER_AREA) for f in frames]
    blank = np.zeros_like(tiles[0])
    while len(tiles) % columns:
        tiles.append(blank)
    rows = [np.hstack(tiles[i:i + columns]) for i in range(0, len(tiles), columns)]
    return np.vstack(rows)


def write_sheet(path: "str | os.PathLike[str]", frames: Sequence[EvalFrame], columns: int = 2,
                scale: float = 0.5) -> None:
    """Write :func:`contact_sheet` as an image file.

    Raises:
        ConfigError: The file cannot be written.
    """
    if not cv2.imwrite(str(path), contact_sheet(frames, columns, scale)):
        raise ConfigError(f"cannot write image {path}")
