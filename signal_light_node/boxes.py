"""Tracked boxes as the core sees them: plain Python, no ROS message types."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class TrackBox:
    """One tracked vehicle's box in one image.

    Attributes:
        track_id: The tracker's ID (``vision_msgs/Detection2D.id``).
        x0: Left edge in pixels (may lie outside the image or be NaN on bad input).
        y0: Top edge in pixels.
        x1: Right edge in pixels.
        y1: Bottom edge in pixels.
        class_id: The detector's class (``results[0].hypothesis.class_id``), "" if none.
    """

    track_id: str
    x0: float
    y0: float
    x1: float
    y1: float
    class_id: str = ""

    @classmethod
    def from_center(cls, track_id: str, cx: float, cy: float, width: float, height: float,
                    class_id: str = "") -> "TrackBox":
        """Build a box from a ``vision_msgs/BoundingBox2D``-style centre and size."""
        return cls(track_id, cx - width / 2.0, cy - height / 2.0, cx + width / 2.0,
                   cy + height / 2.0, class_id)

    @property
    def width(self) -> float:
        return self.x1 - self.x0

    @property
    def height(self) -> float:
        return self.y1 - self.y0

    @property
    def is_finite(self) -> bool:
        return all(math.isfinite(v) for v in (self.x0, self.y0, self.x1, self.y1))
