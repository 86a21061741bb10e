"""Rasterisation into the linear radiance buffer: gradient-shaded polygons, emissive
lenses with a hot core, soft glows, plus an object-id buffer for occlusion truth.

Every polygon is drawn on a small window around it with sub-pixel precision; coverage is
anti-aliased and the id buffer takes the object wherever it covers at least half a pixel.
"""

from __future__ import annotations

from typing import Optional, Sequence, Tuple

import cv2
import numpy as np

Colour = Tuple[float, float, float]

_SHIFT = 4
_SCALE = float(1 << _SHIFT)


class Canvas:
    """A linear BGR radiance buffer with an int32 object-id buffer of the same size.

    Args:
        width: Image width.
        height: Image height.
    """

    def __init__(self, width: int, height: int) -> None:
        self.width = int(width)
        self.height = int(height)
        self.rgb = np.zeros((self.height, self.width, 3), dtype=np.float32)
        self.ids = np.full((self.height, self.width), -1, dtype=np.int32)

    def window(self, poly: np.ndarray, pad: int = 1) -> Optional[Tuple[int, int, int, int]]:
        """Pixel window ``(x0, y0, x1, y1)`` covering ``poly``, clipped; None if off-image."""
        if poly.size == 0 or not np.all(np.isfinite(poly)):
            return None
        x0 = max(int(np.floor(poly[:, 0].min())) - pad, 0)
        y0 = max(int(np.floor(poly[:, 1].min())) - pad, 0)
        x1 = min(int(np.ceil(poly[:, 0].max())) + pad + 1, self.width)
        y1 = min(int(np.ceil(poly[:, 1].max())) + pad + 1, self.height)
        if x1 <= x0 or y1 <= y0:
            return None
        return x0, y0, x1, y1

    def coverage(self, poly: np.ndarray) -> Optional[Tuple[Tuple[int, int, int, int], np.ndarray]]:
        """Anti-aliased coverage ``float32 [h, w]`` in 0..1 of ``poly`` in its window."""
        win = self.window(poly)
        if win is None:
            return None
        x0, y0, x1, y1 = win
        mask = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)
        pts = np.round((poly - np.array([x0, y0])) * _SCALE).astype(np.int32)
        cv2.fillPoly(mask, [pts], 255, lineType=cv2.LINE_AA, shift=_SHIFT)
        return win, mask.astype(np.float32) / 255.0


def fill_gradient(canvas: Canvas, poly: np.ndarray, top: Colour, bottom: Colour,
                  obj_id: Optional[int] = None, alpha: float = 1.0) -> None:
    """Paint ``poly`` with a vertical gradient from ``top`` to ``bottom`` (over-blend).

    Args:
        canvas: Target.
        poly: ``[N, 2]`` pixel polygon.
        top: Radiance at the polygon's top edge.
        bottom: Radiance at its bottom edge.
        obj_id: Object id written to the id buffer where covered (None: untouched).
        alpha: Opacity.
    """
    cov = canvas.coverage(poly)
    if cov is None:
        return
    (x0, y0, x1, y1), a = cov
    ytop, ybot = float(poly[:, 1].min()), float(poly[:, 1].max())
    rows = (np.arange(y0, y1, dtype=np.float32) - ytop) / max(ybot - ytop, 1.0)
    t = np.clip(rows, 0.0, 1.0)[:, None, None]
    colour = np.asarray(top, np.float32) * (1 - t) + np.asarray(bottom, np.float32) * t
    a = a[..., None] * np.float32(alpha)
    region = canvas.rgb[y0:y1, x0:x1]
    region *= 1.0 - a
    region += colour * a
    if obj_id is not None:
        canvas.ids[y0:y1, x0:x1][a[..., 0] >= 0.5] = obj_id


def add_emission(canvas: Canvas, poly: np.ndarray, colour: Colour, level: float,
                 core: float = 0.55) -> None:
    """Add the light of a lit lens: the whole lens glows, a shrunken core glows twice as hot.

    Args:
        canvas: Target.
        poly: Lens polygon in pixels.
        colour: Emission colour (BGR, roughly unit peak).
        level: Radiance scale.
        core: Size of the hot core relative to the lens.
    """
    if level <= 0:
        return
    c = np.asarray(colour, np.float32) * np.float32(level)
    cov = canvas.coverage(poly)
    if cov is None:
        return
    (x0, y0, x1, y1), a = cov
    canvas.rgb[y0:y1, x0:x1] += a[..., None] * c
    centre = poly.mean(axis=0)
    inner = centre + (poly - centre) * core
    cov = canvas.coverage(inner)
    if cov is not None:
        (x0, y0, x1, y1), a = cov
        canvas.rgb[y0:y1, x0:x1] += a[..., None] * c


def add_glow(canvas: Canvas, centre: Sequence[float], radii: Tuple[float, float], colour: Colour,
             level: float) -> None:
    """Add an elliptical Gaussian glow (halo, reflection, light pool).

    Args:
        canvas: Target.
        centre: ``(u, v)`` pixel centre.
        radii: ``(rx, ry)`` standard deviations in pixels.
        colour: Colour.
        level: Peak radiance.
    """
    rx, ry = max(float(radii[0]), 0.5), max(float(radii[1]), 0.5)
    u, v = float(centre[0]), float(centre[1])
    x0, x1 = max(int(u - 3 * rx), 0), min(int(u + 3 * rx) + 1, canvas.width)
    y0, y1 = max(int(v - 3 * ry), 0), min(int(v + 3 * ry) + 1, canvas.height)
    if x1 <= x0 or y1 <= y0 or level <= 0:
        return
    gx = np.exp(-0.5 * ((np.arange(x0, x1, dtype=np.float32) - u) / rx) ** 2)
    gy = np.exp(-0.5 * ((np.arange(y0, y1, dtype=np.float32) - v) / ry) ** 2)
    canvas.rgb[y0:y1, x0:x1] += (gy[:, None] * gx[None, :])[..., None] * (
        np.asarray(colour, np.float32) * np.float32(level))


def visible_fraction(canvas: Canvas, poly: np.ndarray, obj_id: int) -> float:
    """Share of ``poly``'s area that shows ``obj_id`` in the id buffer (off-image = hidden)."""
    area = abs(float(cv2.contourArea(poly.astype(np.float32))))
    if area < 1e-6:
        return 0.0
    cov = canvas.coverage(poly)
    if cov is None:
        return 0.0
    (x0, y0, x1, y1), a = cov
    seen = float(a[canvas.ids[y0:y1, x0:x1] == obj_id].sum())
    return min(seen / area, 1.0)
