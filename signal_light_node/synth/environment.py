"""The world around the vehicles: street background, lighting, distractor lights, weather,
and foreground occluders (poles and signs) that pass in front of the vehicles.

Everything static is drawn once per renderer into an oversized background (the margin
lets the camera shake by slicing); everything that changes per frame is cheap: small
shapes on the frame plus emission into a quarter-resolution light layer that the
renderer blurs into glow.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List, Optional, Tuple

import cv2
import numpy as np

LIGHTINGS: Tuple[str, ...] = ("day", "dusk", "night")
#: Quarter-resolution light layer: one light-layer pixel per ``GLOW_SCALE`` image pixels.
GLOW_SCALE = 4
_SHIFT = 3
_ONE = 1 << _SHIFT


@dataclass
class Lighting:
    """Scene illumination and the rules that depend on it.

    Attributes:
        name: "day", "dusk" or "night".
        ambient: Multiplier for diffuse surfaces.
        tint: Per-channel colour of the ambient light (BGR multipliers).
        lights_on: Probability that a vehicle drives with position lights (and headlights).
        glow: Gain of the glow (bloom) of emissive things.
        lamp_gain: Brightness of lamps relative to the scene (lamps look brighter in the dark).
        noise: Sensor noise sigma in grey levels.
        exposure_s: Exposure time of the camera in seconds.
        sun_side: -1 or +1, the side the light comes from (for body shading).
    """

    name: str
    ambient: float
    tint: Tuple[float, float, float]
    lights_on: float
    glow: float
    lamp_gain: float
    noise: float
    exposure_s: float
    sun_side: int


def sample_lighting(rng: np.random.Generator, name: str) -> Lighting:
    """Random illumination parameters for one of ``LIGHTINGS``."""
    side = int(rng.choice([-1, 1]))
    if name == "day":
        overcast = rng.random() < 0.4
        amb = rng.uniform(0.75, 0.95) if overcast else rng.uniform(0.9, 1.15)
        tint = (1.0 + rng.uniform(-0.05, 0.08), 1.0, 1.0 + rng.uniform(-0.06, 0.04))
        return Lighting(name, amb, tint, rng.uniform(0.15, 0.5), rng.uniform(0.25, 0.6), rng.uniform(0.75, 1.0),
                        rng.uniform(1.0, 4.0), rng.uniform(0.001, 0.008), side)
    if name == "dusk":
        tint = (rng.uniform(0.75, 0.95), rng.uniform(0.85, 0.97), 1.0 + rng.uniform(0.0, 0.12))
        return Lighting(name, rng.uniform(0.35, 0.6), tint, rng.uniform(0.6, 0.9), rng.uniform(0.6, 1.0), rng.uniform(0.9, 1.1),
                        rng.uniform(2.5, 6.0), rng.uniform(0.008, 0.02), side)
    if name == "night":
        sodium = rng.random() < 0.5
        tint = (0.65, 0.85, 1.15) if sodium else (1.05, 1.0, 0.95)
        return Lighting(name, rng.uniform(0.14, 0.3), tint, rng.uniform(0.9, 1.0), rng.uniform(0.9, 1.5), rng.uniform(1.0, 1.2),
                        rng.uniform(3.5, 9.0), rng.uniform(0.015, 0.035), side)
    raise ValueError(name)


def shade(colour, lighting: Lighting, extra: float = 1.0) -> Tuple[float, float, float]:
    """A surface colour under the scene's ambient light."""
    return tuple(float(min(255.0, c * lighting.ambient * t * extra)) for c, t in zip(colour, lighting.tint))


def fill(img: np.ndarray, pts: np.ndarray, colour, aa: bool = True) -> None:
    """Fill a polygon given in float pixel coordinates with sub-pixel precision."""
    cv2.fillPoly(img, [np.round(np.asarray(pts) * _ONE).astype(np.int32)], colour, cv2.LINE_AA if aa else cv2.LINE_8, _SHIFT)


def ellipse(img: np.ndarray, cx: float, cy: float, rx: float, ry: float, colour, aa: bool = True, angle: float = 0.0) -> None:
    """Filled ellipse at float pixel coordinates."""
    cv2.ellipse(img, (int(round(cx * _ONE)), int(round(cy * _ONE))),
                (max(1, int(round(rx * _ONE))), max(1, int(round(ry * _ONE)))), angle, 0, 360, colour, -1,
                cv2.LINE_AA if aa else cv2.LINE_8, _SHIFT)


def add_glow(layer: np.ndarray, cx: float, cy: float, radius: float, colour, gain: float) -> None:
    """Add emission (image coordinates) to the quarter-resolution light layer."""
    r = max(0.6, radius / GLOW_SCALE)
    c = tuple(float(v) * gain for v in colour)
    x, y = cx / GLOW_SCALE, cy / GLOW_SCALE
    h, w = layer.shape[:2]
    if -2 * r < x < w + 2 * r and -2 * r < y < h + 2 * r:
        cv2.circle(layer, (int(round(x * _ONE)), int(round(y * _ONE))), max(1, int(round(r * _ONE))), c, -1, cv2.LINE_8, _SHIFT)


# --------------------------------------------------------------------------- dynamic lights

@dataclass
class DistractorLight:
    """A light that is not a labelled vehicle lamp: beacon, sign, far vehicle, street lamp.

    ``mode`` is "steady", "blink" (period, duty, phase), "flicker" (random switching) or
    "pair" (a far vehicle's rear lights, one side sometimes blinking amber).
    """

    x: float
    y: float
    rx: float
    ry: float
    colour: Tuple[float, float, float]
    mode: str
    period: float = 1.0
    duty: float = 0.5
    phase: float = 0.0
    vx: float = 0.0
    glow: float = 1.0
    seed: int = 0
    body: Optional[Tuple[float, float, float]] = None


# --------------------------------------------------------------------------- foreground

@dataclass
class Occluder:
    """A pole or a sign (or a user-given rectangle) in front of every vehicle.

    Attributes:
        x: Horizontal position of the pole axis at t=0 (pixels).
        vx: Horizontal speed in pixels per second (the ego vehicle drives past it).
        width: Pole width in pixels.
        top: Top of the pole (pixels).
        bottom: Bottom of the pole.
        colour: Pole colour (already lit).
        sign: Optional (shape, w, h, y_centre, colour) of a sign plate on the pole.
        rect: When given, a static rectangle (x0, y0, x1, y1) instead of a pole.
    """

    x: float
    vx: float
    width: float
    top: float
    bottom: float
    colour: Tuple[float, float, float]
    sign: Optional[Tuple[str, float, float, float, Tuple[float, float, float]]] = None
    rect: Optional[Tuple[float, float, float, float]] = None

    def draw(self, img: np.ndarray, x: float, oy: float = 0.0, value=None) -> None:
        """Draw with the pole axis at image column ``x``; ``value`` replaces all colours (coverage masks)."""
        if self.rect is not None:
            x0, y0, x1, y1 = self.rect
            fill(img, np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]), value if value is not None else self.colour)
            return
        hw = self.width / 2
        fill(img, np.array([[x - hw, self.top - oy], [x + hw, self.top - oy], [x + hw, self.bottom - oy], [x - hw, self.bottom - oy]]),
             value if value is not None else self.colour)
        if self.sign is not None:
            shape, w, h, yc, colour = self.sign
            c = value if value is not None else colour
            if shape == "round":
                ellipse(img, x, yc - oy, w / 2, h / 2, c)
            else:
                fill(img, np.array([[x - w / 2, yc - h / 2 - oy], [x + w / 2, yc - h / 2 - oy], [x + w / 2, yc + h / 2 - oy],
                                    [x - w / 2, yc + h / 2 - oy]]), c)


class Environment:
    """Static background, distractor lights, weather and foreground for one renderer.

    Args:
        rng: The environment's own random generator.
        width: Image width.
        height: Image height.
        margin: Extra pixels on each side of the background for camera shake.
        horizon: Image row of the horizon.
        vanish_x: Image column of the road's vanishing point.
        lighting: The scene illumination.
        distractors: Whether to add distractor lights and background traffic.
        weather: "clear", "rain" or "haze".
        n_poles: Number of moving foreground poles/signs (None = random).
    """

    def __init__(self, rng: np.random.Generator, width: int, height: int, margin: int, horizon: float, vanish_x: float,
                 lighting: Lighting, distractors: bool = True, weather: str = "clear", n_poles: Optional[int] = None) -> None:
        self.rng = rng
        self.width, self.height, self.margin = width, height, margin
        self.horizon, self.vanish_x = horizon, vanish_x
        self.lighting = lighting
        self.weather = weather
        self.lights: List[DistractorLight] = []
        self.occluders: List[Occluder] = []
        self.background = self._build_background(distractors)
        if distractors:
            self._add_dynamic_lights()
        n = int(rng.choice([0, 0, 1, 1, 2, 3])) if n_poles is None else n_poles
        for _ in range(n):
            self.occluders.append(self._random_pole())
        self.rain = self._rain_layer() if weather == "rain" else None

    # ----------------------------------------------------------------- background
    def _build_background(self, distractors: bool) -> np.ndarray:
        rng, lt = self.rng, self.lighting
        m = self.margin
        W, H = self.width + 2 * m, self.height + 2 * m
        hy, vx = self.horizon + m, self.vanish_x + m
        bg = np.zeros((H, W, 3), np.uint8)
        glow = np.zeros(((H + GLOW_SCALE - 1) // GLOW_SCALE, (W + GLOW_SCALE - 1) // GLOW_SCALE, 3), np.float32)
        # Sky: vertical gradient from zenith to horizon.
        if lt.name == "day":
            top = np.array([rng.uniform(150, 220), rng.uniform(110, 170), rng.uniform(60, 110)])
            if rng.random() < 0.4:
                g = rng.uniform(150, 215)
                top = np.array([g + 8, g + 3, g])
            hor = np.array([rng.uniform(200, 240), rng.uniform(195, 235), rng.uniform(185, 230)])
        elif lt.name == "dusk":
            top = np.array([rng.uniform(70, 120), rng.uniform(40, 70), rng.uniform(40, 80)])
            hor = np.array([rng.uniform(60, 130), rng.uniform(110, 170), rng.uniform(170, 230)])
        else:
            top = np.array([rng.uniform(10, 30), rng.uniform(5, 20), rng.uniform(3, 15)])
            hor = np.array([rng.uniform(25, 50), rng.uniform(25, 50), rng.uniform(30, 60)])
        rows = np.clip(np.arange(H) / max(hy, 1.0), 0, 1)[:, None]
        bg[:] = (top[None, :] * (1 - rows) + hor[None, :] * rows).astype(np.uint8)[:, None, :]

        scene = str(rng.choice(["city", "city", "suburb", "open"]))
        amb = lambda c, e=1.0: shade(c, lt, e)  # noqa: E731
        # Far skyline around the horizon.
        x = 0.0
        while x < W:
            bw = rng.uniform(15, 70)
            bh = rng.uniform(5, 60) if scene != "open" else rng.uniform(2, 14)
            g = rng.uniform(70, 170)
            col = amb((g * rng.uniform(0.9, 1.1), g, g * rng.uniform(0.9, 1.15)), 0.8)
            if scene == "open":
                col = amb((rng.uniform(40, 90), rng.uniform(80, 130), rng.uniform(60, 100)), 0.8)
            fill(bg, np.array([[x, hy - bh], [x + bw, hy - bh], [x + bw, hy + 2], [x, hy + 2]]), col)
            if lt.name != "day" and scene != "open":
                for _ in range(int(bw * bh / 120)):
                    if rng.random() < 0.5:
                        wx, wy = x + rng.uniform(2, bw - 2), hy - rng.uniform(2, bh)
                        c = (rng.uniform(60, 140), rng.uniform(150, 210), rng.uniform(200, 255))
                        cv2.rectangle(bg, (int(wx), int(wy)), (int(wx) + 1, int(wy) + 1), c, -1)
            x += bw
        # Road: from the bottom corners (plus extra) to the vanishing point.
        road_l, road_r = vx - rng.uniform(1.2, 2.2) * (H - hy), vx + rng.uniform(1.2, 2.2) * (H - hy)
        asphalt = amb((rng.uniform(70, 110),) * 3, 1.0)
        asphalt = (asphalt[0] * rng.uniform(0.95, 1.05), asphalt[1], asphalt[2] * rng.uniform(0.95, 1.05))
        ground = amb((rng.uniform(90, 150), rng.uniform(110, 160), rng.uniform(110, 170)))
        fill(bg, np.array([[0, hy], [W, hy], [W, H], [0, H]]), ground)
        fill(bg, np.array([[vx - 2, hy], [vx + 2, hy], [road_r, H], [road_l, H]]), asphalt)
        # Kerb lines and lane markings converging to the vanishing point.
        mark = amb((rng.uniform(200, 240), rng.uniform(200, 240), rng.uniform(200, 245)))
        yellow = amb((40, 190, 230))
        n_lanes = int(rng.integers(2, 6))
        for k in range(1, n_lanes):
            f = k / n_lanes
            xb = road_l + (road_r - road_l) * f
            col = yellow if (k == n_lanes // 2 and rng.random() < 0.3) else mark
            dashed = rng.random() < 0.7
            s_vals = np.linspace(0.02, 1.0, 40) ** 2
            for a, b in zip(s_vals[:-1], s_vals[1:]):
                if dashed and int(round(math.log(a + 1e-3) * 7)) % 2:
                    continue
                ya, yb = hy + (H - hy) * a, hy + (H - hy) * b
                xa, xb2 = vx + (xb - vx) * a, vx + (xb - vx) * b
                wa, wb = 0.3 + 3.5 * a, 0.3 + 3.5 * b
                fill(bg, np.array([[xa - wa, ya], [xa + wa, ya], [xb2 + wb, yb], [xb2 - wb, yb]]), col)
        for edge in (road_l, road_r):
            fill(bg, np.array([[vx - 1, hy], [vx + 1, hy], [edge + 4, H], [edge - 4, H]]), amb((170, 170, 170)))
        if rng.random() < 0.25:  # pedestrian crossing
            yc = hy + (H - hy) * rng.uniform(0.25, 0.7)
            s = (yc - hy) / (H - hy)
            xl, xr = vx + (road_l - vx) * s, vx + (road_r - vx) * s
            n = 12
            for i in range(0, n, 2):
                u0, u1 = xl + (xr - xl) * i / n, xl + (xr - xl) * (i + 1) / n
                fill(bg, np.array([[u0, yc - 4 * s - 1], [u1, yc - 4 * s - 1], [u1, yc + 4 * s + 1], [u0, yc + 4 * s + 1]]), mark)
        # Building facades (city) or trees (suburb) along both sides.
        for side in (-1, 1):
            if scene == "open":
                break
            x_near = 0.0 if side < 0 else float(W)
            top_near = hy - rng.uniform(0.6, 1.6) * hy if scene == "city" else hy - rng.uniform(0.15, 0.45) * hy
            gap = rng.uniform(10, 40)
            xf = vx + side * gap
            ground_near = H * rng.uniform(0.7, 1.0)
            col = amb((rng.uniform(90, 200), rng.uniform(90, 190), rng.uniform(90, 200)))
            if scene == "city":
                fill(bg, np.array([[x_near, top_near], [xf, hy - (hy - top_near) * 0.08], [xf, hy + 1], [x_near, ground_near]]), col)
                # Window columns at geometric depth steps (perspective spacing).
                s = 1.0
                lit_p = 0.35 if lt.name != "day" else 0.0
                while s > 0.1:
                    s_next = s * rng.uniform(0.72, 0.85)
                    for fl in np.linspace(0.1, 0.85, int(rng.integers(3, 7))):
                        xa = xf + (x_near - xf) * s * 0.96
                        xb = xf + (x_near - xf) * (s_next + (s - s_next) * 0.35)
                        ya0 = (hy - (hy - top_near) * s) + (ground_near - top_near) * s * fl
                        ya1 = ya0 + (ground_near - top_near) * s * 0.06
                        yb0 = (hy - (hy - top_near) * (s_next + (s - s_next) * 0.35)) + (ground_near - top_near) * (s_next + (s - s_next) * 0.35) * fl
                        yb1 = yb0 + (ground_near - top_near) * (s_next + (s - s_next) * 0.35) * 0.06
                        lit = rng.random() < lit_p
                        wc = (rng.uniform(80, 150), rng.uniform(170, 220), rng.uniform(210, 255)) if lit else amb((rng.uniform(40, 90),) * 3, 0.8)
                        fill(bg, np.array([[xa, ya0], [xb, yb0], [xb, yb1], [xa, ya1]]), wc)
                        if lit:
                            add_glow(glow, (xa + xb) / 2, (ya0 + yb1) / 2, abs(xb - xa), wc, 0.15)
                    # Shop signs at street level, lit after dark; some are amber or red.
                    if distractors and rng.random() < 0.35 and s > 0.2:
                        sc = [(40, 160, 255), (40, 40, 230), (230, 160, 40), (80, 220, 80), (200, 80, 220), (220, 220, 230)][int(rng.integers(0, 6))]
                        xa, xb = xf + (x_near - xf) * s * 0.92, xf + (x_near - xf) * (s_next + (s - s_next) * 0.3)
                        ya = ground_near * s + hy * (1 - s) - (ground_near - top_near) * s * 0.15
                        hh = (ground_near - top_near) * s * 0.05
                        if lt.name == "day":
                            fill(bg, np.array([[xa, ya - hh], [xb, ya - hh * 0.8], [xb, ya + hh * 0.8], [xa, ya + hh]]), amb(sc, 0.9))
                        else:
                            fill(bg, np.array([[xa, ya - hh], [xb, ya - hh * 0.8], [xb, ya + hh * 0.8], [xa, ya + hh]]), sc)
                            add_glow(glow, (xa + xb) / 2, ya, abs(xb - xa) * 0.7, sc, 0.5)
                    s = s_next
            else:
                s = 1.0
                while s > 0.08:
                    xa = xf + (x_near - xf) * s
                    yb = hy + (ground_near - hy) * s
                    r = (hy - top_near) * s * rng.uniform(0.4, 0.9)
                    fill(bg, np.array([[xa - r * 0.06, yb - r], [xa + r * 0.06, yb - r], [xa + r * 0.06, yb], [xa - r * 0.06, yb]]), amb((40, 55, 70)))
                    tc = amb((rng.uniform(30, 70), rng.uniform(80, 130), rng.uniform(40, 80)))
                    ellipse(bg, xa, yb - r * 1.2, r * rng.uniform(0.5, 0.9), r * rng.uniform(0.45, 0.8), tc)
                    s *= rng.uniform(0.6, 0.8)
        # Street lamps along the road edges.
        if distractors or lt.name != "day":
            head = [(80, 170, 255), (230, 235, 245), (160, 220, 255)][int(rng.integers(0, 3))]
            for side, edge in ((-1, road_l), (1, road_r)):
                s = rng.uniform(0.5, 1.0)
                while s > 0.1:
                    xb = vx + (edge - vx) * s + side * 12 * s
                    yb = hy + (H - hy) * s
                    top = yb - 9.0 * s * (H - hy) / 1.6 * 0.45
                    fill(bg, np.array([[xb - 1.2 * s - 0.4, top], [xb + 1.2 * s + 0.4, top], [xb + 1.2 * s + 0.4, yb], [xb - 1.2 * s - 0.4, yb]]),
                         amb((60, 60, 65)))
                    hx = xb - side * 12 * s
                    fill(bg, np.array([[xb, top], [hx, top - 2 * s], [hx, top + 1], [xb, top + 2]]), amb((60, 60, 65)))
                    if lt.name != "day":
                        ellipse(bg, hx, top + 1, 3 * s + 0.8, 1.4 * s + 0.6, head)
                        add_glow(glow, hx, top + 2, 14 * s + 3, head, 0.8)
                        add_glow(glow, hx, yb, 30 * s + 4, head, 0.05)  # pool of light on the ground
                    s *= rng.uniform(0.55, 0.75)
        # Low-frequency texture so that flat areas are not perfectly flat.
        tex = cv2.resize(rng.normal(0, 1, (H // 16 + 2, W // 16 + 2)).astype(np.float32), (W, H), interpolation=cv2.INTER_CUBIC)
        fine = rng.normal(0, 1, (H, W)).astype(np.float32)
        t = (tex * rng.uniform(3, 9) * lt.ambient + cv2.GaussianBlur(fine, (3, 3), 0) * 3 * lt.ambient)
        out = bg.astype(np.float32) + t[:, :, None]
        if lt.name != "day":
            g = cv2.GaussianBlur(glow, (0, 0), 2.5)
            g = cv2.resize(g, (glow.shape[1] * GLOW_SCALE, glow.shape[0] * GLOW_SCALE), interpolation=cv2.INTER_LINEAR)[:H, :W]
            out += g * lt.glow
        return np.clip(out, 0, 255).astype(np.uint8)

    # ----------------------------------------------------------------- distractors
    def _add_dynamic_lights(self) -> None:
        rng, lt = self.rng, self.lighting
        W, H, hy, vx = self.width, self.height, self.horizon, self.vanish_x
        n = int(rng.integers(1, 5)) + (2 if lt.name != "day" else 0)
        for i in range(n):
            kind = rng.choice(["beacon", "sign", "pair", "pair", "traffic"])
            if kind == "pair":
                # A far vehicle: two small red lights (or headlights) near the horizon.
                x = vx + rng.uniform(-0.35, 0.35) * W
                y = hy + rng.uniform(0.5, 6)
                sep = rng.uniform(2.5, 6)
                head = rng.random() < 0.35
                col = (240, 240, 250) if head else (30, 20, 235)
                body = (rng.uniform(20, 200),) * 3
                self.lights.append(DistractorLight(x, y, sep, rng.uniform(0.6, 1.4), col, "pair", period=1 / rng.uniform(1, 2.2),
                                                   duty=rng.uniform(0.3, 0.7), phase=rng.uniform(0, 1), vx=rng.uniform(-6, 6),
                                                   glow=rng.uniform(0.5, 1.2), seed=int(rng.integers(0, 1 << 30)), body=body))
            elif kind == "beacon":
                x, y = rng.uniform(0, W), hy + rng.uniform(-0.25, 0.35) * (H - hy)
                col = (rng.uniform(0, 40), rng.uniform(130, 200), 255.0) if rng.random() < 0.7 else (30, 30, 240)
                r = rng.uniform(1.2, 4)
                self.lights.append(DistractorLight(x, y, r, r, col, "blink", period=1 / rng.uniform(0.8, 2.5),
                                                   duty=rng.uniform(0.3, 0.7), phase=rng.uniform(0, 1), glow=rng.uniform(0.6, 1.5)))
            elif kind == "traffic":
                x, y = vx + rng.uniform(-0.45, 0.45) * W, hy - rng.uniform(5, 45)
                col = [(40, 40, 240), (90, 230, 60), (20, 170, 255)][int(rng.integers(0, 3))]
                mode = "blink" if col[2] == 255 and rng.random() < 0.6 else "steady"
                r = rng.uniform(1.2, 3.0)
                self.lights.append(DistractorLight(x, y, r, r, col, mode, period=1 / rng.uniform(0.8, 1.5), duty=0.5,
                                                   phase=rng.uniform(0, 1), glow=1.0, body=(25, 25, 25)))
            else:
                x, y = rng.uniform(0, W), rng.uniform(0.3, 1.0) * hy
                col = [(40, 160, 255), (40, 40, 230), (230, 160, 40), (80, 220, 80), (200, 80, 220)][int(rng.integers(0, 5))]
                self.lights.append(DistractorLight(x, y, rng.uniform(4, 18), rng.uniform(1.5, 5), col, "flicker",
                                                   period=rng.uniform(0.2, 2.0), glow=0.8, seed=int(rng.integers(0, 1 << 30))))

    def draw_lights(self, img: np.ndarray, layer: np.ndarray, t: float, ox: float, oy: float) -> None:
        """Draw the distractor lights at time ``t`` (``ox, oy`` = camera shake)."""
        night = self.lighting.name != "day"
        for d in self.lights:
            x, y = d.x + d.vx * t - ox, d.y - oy
            if d.mode == "pair":
                x = (x + self.width * 0.5) % (self.width * 1.5) - self.width * 0.25
                if d.body is not None and not night:
                    fill(img, np.array([[x - d.rx - 1, y - d.rx * 0.8], [x + d.rx + 1, y - d.rx * 0.8], [x + d.rx + 1, y + d.ry],
                                        [x - d.rx - 1, y + d.ry]]), shade(d.body, self.lighting))
                blink_side = 1 if (d.seed % 3 == 0) else (-1 if d.seed % 3 == 1 else 0)
                on_phase = ((t / d.period + d.phase) % 1.0) < d.duty
                brake = ((t * 0.21 + d.seed * 1e-6) % 1.0) < 0.4
                for sgn in (-1, 1):
                    col = d.colour
                    level = (1.0 if (brake or night) else 0.0) if col[2] > col[0] else 1.0
                    if sgn == blink_side and on_phase and col[2] > col[0]:
                        col, level = (10, 160, 255), 1.0
                    if level <= 0:
                        continue
                    lev = level * (0.6 if night else 0.9)
                    c = tuple(v * lev for v in col)
                    ellipse(img, x + sgn * d.rx, y, d.ry, d.ry * 0.8, c)
                    add_glow(layer, x + sgn * d.rx, y, d.ry * 4, col, 0.3 * d.glow * lev * self.lighting.glow)
                continue
            if d.mode == "blink":
                on = ((t / d.period + d.phase) % 1.0) < d.duty
            elif d.mode == "flicker":
                k = int(t / d.period)
                on = ((k * 2654435761 + d.seed) >> 7) % 5 != 0
            else:
                on = True
            if d.body is not None:
                fill(img, np.array([[x - d.rx * 1.6, y - d.ry * 1.6], [x + d.rx * 1.6, y - d.ry * 1.6], [x + d.rx * 1.6, y + d.ry * 5.5],
                                    [x - d.rx * 1.6, y + d.ry * 5.5]]), (25, 25, 25))
            if not on:
                if d.mode == "flicker" and not night:
                    continue
                ellipse(img, x, y, d.rx, d.ry, tuple(c * 0.25 for c in d.colour))
                continue
            lev = 1.0 if night else 0.85
            if d.mode == "flicker":
                fill(img, np.array([[x - d.rx, y - d.ry], [x + d.rx, y - d.ry], [x + d.rx, y + d.ry], [x - d.rx, y + d.ry]]),
                     tuple(c * lev for c in d.colour))
            else:
                ellipse(img, x, y, d.rx, d.ry, tuple(c * lev for c in d.colour))
            add_glow(layer, x, y, max(d.rx, d.ry) * 3, d.colour, 0.35 * d.glow * self.lighting.glow)

    # ----------------------------------------------------------------- foreground
    def _random_pole(self) -> Occluder:
        rng, lt = self.rng, self.lighting
        W, H = self.width, self.height
        width = rng.uniform(5, 28)
        vx = rng.choice([-1, 1]) * rng.uniform(10, 90) if rng.random() < 0.7 else 0.0
        g = rng.uniform(40, 150)
        colour = shade((g, g * rng.uniform(0.95, 1.05), g * rng.uniform(0.9, 1.1)), lt)
        sign = None
        if rng.random() < 0.6:
            sc = [(160, 80, 20), (30, 30, 200), (230, 230, 230), (20, 160, 230), (40, 120, 40)][int(rng.integers(0, 5))]
            sw = rng.uniform(2.0, 5.0) * width
            sign = (str(rng.choice(["round", "rect"])), sw, sw * rng.uniform(0.6, 1.1), rng.uniform(0.1, 0.5) * H, shade(sc, lt))
        return Occluder(x=rng.uniform(-0.2, 1.2) * W, vx=float(vx), width=width, top=-10.0 if rng.random() < 0.6 else rng.uniform(0, 0.3) * H,
                        bottom=H + 10.0, colour=colour, sign=sign)

    def occluder_x(self, occ: Occluder, t: float) -> float:
        """Pole position at time ``t``, wrapping around so that poles keep passing by."""
        if occ.rect is not None or occ.vx == 0:
            return occ.x
        span = self.width * 1.6
        return (occ.x + occ.vx * t + self.width * 0.3) % span - self.width * 0.3

    # ----------------------------------------------------------------- weather
    def _rain_layer(self) -> np.ndarray:
        rng = self.rng
        H, W = self.height * 2, self.width
        layer = np.zeros((H, W, 3), np.uint8)
        n = int(rng.uniform(300, 1200))
        ang = rng.uniform(-0.3, 0.3)
        g = 40 if self.lighting.name == "day" else 28
        for _ in range(n):
            x, y = rng.uniform(0, W), rng.uniform(0, H)
            ln = rng.uniform(6, 22)
            cv2.line(layer, (int(x), int(y)), (int(x + ln * ang), int(y + ln)), (g, g, g), 1, cv2.LINE_AA)
        return layer

    def rain_slice(self, t: float) -> Optional[np.ndarray]:
        """The rain streaks at time ``t`` (full frame) or None without rain."""
        if self.rain is None:
            return None
        off = int(t * 900) % self.height
        return self.rain[off:off + self.height]
