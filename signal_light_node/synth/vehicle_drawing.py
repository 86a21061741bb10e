"""Drawing the labelled vehicles of the training renderer: body, flank, shading and
specular spots onto a canvas of each vehicle's own, its lamps (unlit lens, lit colour,
over-exposed core, glow and wet-road reflection), then the contact shadow and the
composite into the frame, far to near.

Shapes and lamp outlines are in normalised face coordinates (``vehicles``, ``lamps``);
one affine transform per vehicle and frame (``affine``) maps them to pixels, and polygons
are filled anti-aliased with sub-pixel precision.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np

from signal_light_node.labels import View
from signal_light_node.synth.environment import Lighting, StreetGeometry, add_glow, ellipse
from signal_light_node.synth.traffic import Box, Vehicle
from signal_light_node.synth.vehicles import KIND_DIMS

_SHIFT = 3
_ONE = 1 << _SHIFT
#: A lit signal lamp (level 1) blends at least this far from its unlit lens to its lit
#: colour, whatever the light: a lit bulb or LED visibly brightens its lens in daylight too.
LIT_LAMP_MIN_GAIN = 0.85
#: Share of white in the clipped core of a lit lamp in daylight (a camera clips a lit
#: lamp towards white even in the sun; 0.2 until 2026-11-22 left red lamps faint).
LIT_CORE_DAY = 0.45


@dataclass
class Drawn:
    """Per-frame drawing state of one vehicle."""

    v: Vehicle
    box: Box  # full (unclipped) extent
    roi: Tuple[int, int, int, int]  # clipped integer ROI x0, y0, x1, y1
    M: np.ndarray
    canvas: np.ndarray
    alpha: np.ndarray
    vis: Optional[np.ndarray] = None
    full_area: float = 1.0
    #: Every lamp outline point in ROI pixels, and each lamp's bounding corners.
    lamp_px: Optional[np.ndarray] = None
    lamp_lo: Optional[np.ndarray] = None
    lamp_hi: Optional[np.ndarray] = None


def _lamp_pixels(v: Vehicle, M: np.ndarray) -> Dict[str, np.ndarray]:
    """All lamp outlines in one transform, with each lamp's extent."""
    P = v.lamp_pts @ M[:, :2].T + M[:, 2]
    starts = [a for a, _ in v.lamp_ranges]
    return {"lamp_px": P, "lamp_lo": np.minimum.reduceat(P, starts, axis=0),
            "lamp_hi": np.maximum.reduceat(P, starts, axis=0)}


def affine(v: Vehicle, box: Box, ox: float, oy: float) -> np.ndarray:
    """Normalised face coordinates (u, v) to pixels of a ROI at (``ox``, ``oy``): scale to the
    box, shear, roll about its centre."""
    x0, y0, x1, y1 = box
    bw, bh = x1 - x0, y1 - y0
    a = math.radians(v.roll)
    c, s = math.cos(a), math.sin(a)
    # u,v -> local (centred, sheared) -> rotated -> ROI coordinates.
    A = np.array([[bw, v.shear * bh], [0.0, bh]])
    R = np.array([[c, -s], [s, c]])
    L = R @ A
    centre = np.array([(x0 + x1) / 2 - ox, (y0 + y1) / 2 - oy])
    t = centre - L @ np.array([0.5, 0.5])
    return np.hstack([L, t[:, None]]).astype(np.float64)


def _visible_side(v: Vehicle) -> Optional[Tuple[Tuple[float, float], Tuple[float, float]]]:
    """The flank of a front or rear view that faces the camera, as its near and far ends
    ``((X, Z), (X, Z))`` in metres on the ground at the face's depth and the body's length
    behind it; None when neither flank faces the camera.

    The face (width ``face_w``) is centred at (``X``, ``Z``) and turned by ``yaw``: its
    corners lie at the centre plus or minus half the width along (cos yaw, -sin yaw); the
    body runs away from the camera along (sin yaw, cos yaw). A flank faces the camera (at
    the origin) when the camera lies on its outer side.
    """
    a = math.radians(v.yaw)
    across, along = (math.cos(a), -math.sin(a)), (math.sin(a), math.cos(a))
    length = KIND_DIMS[v.kind][2] * (v.face_h / KIND_DIMS[v.kind][1])
    for sign in (1.0, -1.0):
        near = (v.X + sign * v.face_w / 2 * across[0], v.Z + sign * v.face_w / 2 * across[1])
        if -(near[0] * across[0] + near[1] * across[1]) * sign > 0:
            return near, (near[0] + length * along[0], near[1] + length * along[1])
    return None


def _over_clip(level: float) -> float:
    """How much a lamp's core and glow grow at ``level`` over the lens's clipping (1 up to it)."""
    return math.sqrt(level) if level > 1.0 else 1.0


class VehiclePainter:
    """Draws the vehicles of one scene.

    Args:
        width: Image width in pixels.
        height: Image height in pixels.
        geo: The street and the camera over it.
        light: The scene's light.
        lighting: "day", "dusk" or "night".
        wet: Whether the road is wet (lamps reflect on it).
    """

    def __init__(self, width: int, height: int, geo: StreetGeometry, light: Lighting, lighting: str, wet: bool) -> None:
        self.width, self.height = width, height
        self._geo = geo
        self._light = light
        self.lighting = lighting
        self._wet = wet

    def body(self, v: Vehicle, box: Box, ddx: float, ddy: float, layer: np.ndarray) -> Optional[Drawn]:
        """Draw the body of ``v`` (full box ``box`` in the unshaken image; the frame is
        shifted by ``ddx``, ``ddy``) onto its own ROI canvas, soft light onto ``layer``;
        None when it is too small or off the image."""
        W, H = self.width, self.height
        box = (box[0] - ddx, box[1] - ddy, box[2] - ddx, box[3] - ddy)
        bw, bh = box[2] - box[0], box[3] - box[1]
        if bw < 2 or bh < 2:
            return None
        pad = abs(v.shear) * bh + abs(math.radians(v.roll)) * max(bw, bh) + 2
        ext = [box[0] - pad, box[1] - pad, box[2] + pad, box[3] + pad]
        flank = self.flank(v, ddx, ddy)
        if flank is not None:
            ext = [min(ext[0], flank[0][:, 0].min()), min(ext[1], flank[0][:, 1].min()),
                   max(ext[2], flank[0][:, 0].max()), max(ext[3], flank[0][:, 1].max())]
        rx0, ry0 = int(max(0, math.floor(ext[0]))), int(max(0, math.floor(ext[1])))
        rx1, ry1 = int(min(W, math.ceil(ext[2]))), int(min(H, math.ceil(ext[3])))
        if rx1 - rx0 < 1 or ry1 - ry0 < 1:
            return None
        M = affine(v, box, rx0, ry0)
        pts = v.part_pts @ M[:, :2].T + M[:, 2]
        ipts = np.round(pts * _ONE).astype(np.int32)
        canvas = np.zeros((ry1 - ry0, rx1 - rx0, 3), np.uint8)
        alpha = np.zeros((ry1 - ry0, rx1 - rx0), np.uint8)
        if flank is not None:
            # The flank is drawn first; the face drawn over it hides the seam.
            outline, glass = flank
            io = np.round((outline - (rx0, ry0)) * _ONE).astype(np.int32)
            cv2.fillPoly(alpha, [io], 255, cv2.LINE_AA, _SHIFT)
            cv2.fillPoly(canvas, [io], v.paints["flank"], cv2.LINE_AA, _SHIFT)
            if glass is not None:
                cv2.fillPoly(canvas, [np.round((glass - (rx0, ry0)) * _ONE).astype(np.int32)], v.paints["flank_glass"], cv2.LINE_AA, _SHIFT)
        cv2.fillPoly(alpha, [ipts[a:b] for a, b in v.sil_splits], 255, cv2.LINE_AA, _SHIFT)
        for key, a, b in v.part_splits:
            cv2.fillPoly(canvas, [ipts[a:b]], v.paints.get(key, v.paints["body"]), cv2.LINE_AA, _SHIFT)
        # Shading: light from above and from the sun's side, darker towards the ground.
        hh, ww = canvas.shape[:2]
        ys = (np.arange(hh, dtype=np.float32) + ry0 - box[1]) / bh
        xs = (np.arange(ww, dtype=np.float32) + rx0 - box[0]) / bw
        gy = 1.12 - 0.35 * np.clip(ys, 0, 1)
        gx = 1.0 + 0.12 * self._light.sun_side * (np.clip(xs, 0, 1) - 0.5)
        g = (gy[:, None] * gx[None, :]).astype(np.float32)
        canvas = np.minimum(canvas.astype(np.float32) * g[:, :, None], 255.0).astype(np.uint8)
        # Specular spots (sun or street-light reflections) slide over the body as the vehicle
        # moves through the image and come and go; they are soft light, plus a sharp glint.
        cx_img = (box[0] + box[2]) / 2
        for (su, sv, sru, srv, strength) in v.spots:
            u = su + 0.25 * (cx_img / W - 0.5)
            flick = 0.5 + 0.5 * math.sin(cx_img * 0.05 + su * 10)
            s = strength * flick * (1.0 if self.lighting == "day" else 0.6)
            if s < 0.15:
                continue
            p = M @ np.array([u, sv, 1.0])
            if sv < 0.6 and 0 <= p[0] < ww and 0 <= p[1] < hh and alpha[int(p[1]), int(p[0])] > 127:
                add_glow(layer, p[0] + rx0, p[1] + ry0, sru * bw, (255, 255, 255), 0.6 * s)
                if s > 0.5:
                    ellipse(canvas, p[0], p[1], max(0.6, sru * bw * 0.35), max(0.5, srv * bh * 0.3),
                            (235, 240, 245), angle=-12.0)
        area_in = float(np.count_nonzero(alpha > 127))
        full_box_area = bw * bh
        in_box_area = max(0.0, (min(box[2], W) - max(box[0], 0))) * max(0.0, (min(box[3], H) - max(box[1], 0)))
        full_area = area_in + max(0.0, full_box_area - in_box_area) * v.shape.fill_ratio
        return Drawn(v, box, (rx0, ry0, rx1, ry1), M, canvas, alpha, full_area=max(full_area, 1.0), **_lamp_pixels(v, M))

    def flank(self, v: Vehicle, ddx: float, ddy: float) -> Optional[Tuple[np.ndarray, Optional[np.ndarray]]]:
        """Outline (and side windows) of the flank that a front or rear view shows when the
        vehicle is off the camera axis or turned (``yaw``), in image coordinates; None when
        none shows."""
        if v.view in (View.LEFT, View.RIGHT):
            return None
        side = _visible_side(v)
        if side is None:
            return None  # straight ahead and not turned: no flank visible
        (near_x, Zn), (far_x, Zf) = side
        geo = self._geo
        f, hy, vx, ch = geo.focal, geo.horizon - ddy, geo.vanish_x - ddx, geo.cam_h
        xn, xf = vx + f * near_x / Zn, vx + f * far_x / Zf
        if abs(xn - xf) < 1.0:
            return None
        h_m = KIND_DIMS[v.kind][1]
        top_far = h_m * (0.62 if v.kind in ("car", "suv") else 1.0) * v.face_h / KIND_DIMS[v.kind][1]
        ground = 0.2 * v.face_h / KIND_DIMS[v.kind][1]
        yn = lambda hgt: hy + f * (ch - hgt) / Zn  # noqa: E731
        yf = lambda hgt: hy + f * (ch - hgt) / Zf  # noqa: E731
        top_near = v.face_h * (0.62 if v.kind in ("car", "suv") else 1.0)
        outline = np.array([[xn, yn(top_near)], [xf, yf(top_far)], [xf, yf(ground)], [xn, yn(ground)]], np.float64)
        glass = None
        if v.kind in ("car", "suv", "van", "bus"):
            # Side windows: a band under the roof line, shorter than the body.
            g_lo, g_hi = v.face_h * 0.62, v.face_h * (0.92 if v.kind in ("car", "suv") else 0.85)
            za, zb = Zn + (Zf - Zn) * 0.12, Zn + (Zf - Zn) * 0.8
            la, lb = near_x + (far_x - near_x) * 0.12, near_x + (far_x - near_x) * 0.8
            xa, xb = vx + f * la / za, vx + f * lb / zb
            ya = lambda hgt: hy + f * (ch - hgt) / za  # noqa: E731
            yb = lambda hgt: hy + f * (ch - hgt) / zb  # noqa: E731
            glass = np.array([[xa, ya(g_hi)], [xb, yb(g_hi)], [xb, yb(g_lo)], [xa, ya(g_lo)]], np.float64)
            if v.kind in ("car", "suv"):
                # The cabin sits on top of the body and is narrower: its roof edge is set
                # in from the body side, so the roof line starts inside the face outline.
                inset = v.X - near_x
                xr_n, xr_b = vx + f * (near_x + inset * 0.3) / Zn, vx + f * (lb + inset * 0.3) / zb
                roof_n = np.array([[xr_n, yn(v.face_h * 0.97)], [xr_b, yb(v.face_h * 0.95)], [xb, yb(top_far)]])
                outline = np.vstack([outline[:1], roof_n, outline[1:]])
                glass[0, 0] = vx + f * (la + inset * 0.2) / za
                glass[1, 0] = vx + f * (lb + inset * 0.2) / zb
        return outline, glass

    def shadow(self, img: np.ndarray, d: Drawn) -> None:
        """Contact shadow on the road under a vehicle (darker in daylight)."""
        x0, y0, x1, y1 = d.box
        cx, cy = (x0 + x1) / 2, y1 - (y1 - y0) * 0.02
        H, W = img.shape[:2]
        sx, sy = int(min(max(cx, 0), W - 1)), int(min(max(cy + 2, 0), H - 1))
        under = img[sy, sx].astype(np.float32)
        dark = tuple(float(c) * (0.45 if self.lighting == "day" else 0.7) for c in under)
        ellipse(img, cx, cy, (x1 - x0) * 0.53, max(1.0, (y1 - y0) * 0.06), dark)

    def lamps(self, d: Drawn, levels: List[List[float]], fracs: List[float], layer: np.ndarray) -> None:
        """Draw the lamps of a drawn vehicle at their ``levels`` (per lamp, per segment);
        glow goes onto ``layer`` in proportion to each lamp's visible fraction ``fracs``."""
        v = d.v
        rx0, ry0 = d.roi[0], d.roi[1]
        lt = self._light
        night = self.lighting != "day"
        P, lo, hi = d.lamp_px, d.lamp_lo, d.lamp_hi
        IP = np.round(P * _ONE).astype(np.int32)
        gain = max(LIT_LAMP_MIN_GAIN, v.style.brightness * lt.lamp_gain * (1.25 if night else 1.0))
        for li, (lamp, polys, levs, frac) in enumerate(zip(v.lamps, v.lamp_ranges_poly, levels, fracs)):
            # Unlit lens, then the lit colour blended in by the level.
            lens = v.lens_cols[li]
            hot_tail = v.tail_hot and lamp.role in ("tail", "turn_tail")
            for (a, b), lev in zip(polys, levs):
                # Over the lens's clipping (a glaring vehicle's brake and flashes) the light
                # still grows: a hotter core and a larger glow. Levels up to 1 as before.
                extent = _over_clip(lev)
                if hot_tail and 0.0 < lev <= 1.0:
                    lev = v.glare  # a steady tail at the brake's colour; its glow keeps its extent
                k = min(1.0, lev * gain)
                over = _over_clip(lev)
                col = (lens[0] + (lamp.emit[0] - lens[0]) * k, lens[1] + (lamp.emit[1] - lens[1]) * k,
                       lens[2] + (lamp.emit[2] - lens[2]) * k)
                cv2.fillPoly(d.canvas, [IP[a:b]], col, cv2.LINE_AA, _SHIFT)
                if k > 0.05:
                    p = P[a:b]
                    c = p.mean(0)
                    size = max(hi[li][0] - lo[li][0], hi[li][1] - lo[li][1]) if len(polys) == 1 else \
                        max(float(np.ptp(p[:, 0])), float(np.ptp(p[:, 1])))
                    if (night and k > 0.5) or k > 0.6:
                        # Over-exposed core: the centre of a bright lamp clips towards white.
                        core = (p - c) * 0.55 + c
                        hot = (0.35 + 0.4 * k) if night else LIT_CORE_DAY * v.style.brightness
                        if over > 1.0:
                            hot = min(0.95, hot * over)
                        cc = tuple(e + (255 - e) * hot for e in lamp.emit)
                        cv2.fillPoly(d.canvas, [np.round(core * _ONE).astype(np.int32)], cc, cv2.LINE_AA, _SHIFT)
                    add_glow(layer, c[0] + rx0, c[1] + ry0, size * 0.5 * extent, lamp.emit,
                             0.5 * k * over * lt.glow * frac * lamp.glow)
                    if self._wet:
                        # Reflection on the wet road, mirrored about the vehicle's ground line.
                        gy = d.box[3]
                        ry = gy + (gy - (c[1] + ry0)) * 0.9
                        add_glow(layer, c[0] + rx0, ry, size * 0.5, lamp.emit, 0.3 * k * lt.glow * frac, stretch=3.0)

    def composite(self, img: np.ndarray, drawn: List[Drawn]) -> None:
        """Shadow and canvas of every drawn vehicle into the frame, in reverse order of
        ``drawn`` (near to far there: so far to near here)."""
        for d in reversed(drawn):
            x0, y0, x1, y1 = d.roi
            self.shadow(img, d)
            a = d.alpha.astype(np.float32) * (1.0 / 255.0)
            roi = img[y0:y1, x0:x1]
            img[y0:y1, x0:x1] = cv2.blendLinear(d.canvas, roi, a, 1.0 - a)
