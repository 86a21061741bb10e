"""The world around the vehicles: street background, lighting, distractor lights, weather,
and foreground occluders (poles and signs) that pass in front of the vehicles.

Everything static is drawn once per renderer into an oversized background (the margin
lets the camera shake by slicing); everything that changes per frame is cheap: small
shapes on the frame plus emission into a quarter-resolution light layer that the
renderer blurs into glow.
"""

from __future__ import annotations

from dataclasses import dataclass
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


def add_glow(layer: np.ndarray, cx: float, cy: float, radius: float, colour, gain: float, stretch: float = 1.0) -> None:
    """Add emission of a light of ``radius`` image pixels to the quarter-resolution light layer.

    The renderer blurs the layer at two scales, so the emission only has to carry the
    light's energy: small lights get a one-pixel dot scaled down by their area.
    ``stretch`` > 1 makes a vertical streak (reflections on a wet road).
    """
    r = radius / GLOW_SCALE
    rr = max(0.7, r)
    energy = gain * min(1.0, (r / rr) ** 2)
    c = tuple(float(v) * energy for v in colour)
    x, y = cx / GLOW_SCALE, cy / GLOW_SCALE
    h, w = layer.shape[:2]
    if -2 * rr < x < w + 2 * rr and -2 * rr * stretch < y < h + 2 * rr * stretch:
        if stretch == 1.0:
            cv2.circle(layer, (int(round(x * _ONE)), int(round(y * _ONE))), max(1, int(round(rr * _ONE))), c, -1, cv2.LINE_8, _SHIFT)
        else:
            cv2.ellipse(layer, (int(round(x * _ONE)), int(round(y * _ONE))),
                        (max(1, int(round(rr * _ONE))), max(1, int(round(rr * stretch * _ONE)))), 0, 0, 360, c, -1, cv2.LINE_8, _SHIFT)


def blur_glow(layer: np.ndarray, width: int, height: int, wide: float) -> np.ndarray:
    """Bloom from a light layer: a tight and a wide halo, upsampled to ``uint8`` image size."""
    g = cv2.GaussianBlur(layer, (0, 0), 0.9)
    if wide > 0:
        g = cv2.addWeighted(g, 1.0, cv2.GaussianBlur(layer, (0, 0), 4.0), wide, 0.0)
    g = cv2.resize(g, (layer.shape[1] * GLOW_SCALE, layer.shape[0] * GLOW_SCALE), interpolation=cv2.INTER_LINEAR)
    return np.clip(g[:height, :width], 0, 255).astype(np.uint8)


@dataclass
class StreetGeometry:
    """Pinhole camera over a straight road (metres and pixels).

    Attributes:
        focal: Focal length in pixels.
        cam_h: Camera height above the road in metres.
        horizon: Image row of the horizon.
        vanish_x: Image column of the vanishing point.
        x_left: Lateral position of the left kerb (metres, negative).
        x_right: Lateral position of the right kerb.
        lane_w: Lane width in metres.
    """

    focal: float
    cam_h: float
    horizon: float
    vanish_x: float
    x_left: float
    x_right: float
    lane_w: float


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
        geo: Camera and road geometry.
        lighting: The scene illumination.
        distractors: Whether to add distractor lights and background traffic.
        weather: "clear", "rain" or "haze".
        n_poles: Number of moving foreground poles/signs (None = random).
    """

    def __init__(self, rng: np.random.Generator, width: int, height: int, margin: int, geo: "StreetGeometry",
                 lighting: Lighting, distractors: bool = True, weather: str = "clear", n_poles: Optional[int] = None) -> None:
        self.rng = rng
        self.width, self.height, self.margin = width, height, margin
        self.geo = geo
        self.horizon, self.vanish_x = geo.horizon, geo.vanish_x
        self.lighting = lighting
        self.weather = weather
        self.lights: List[DistractorLight] = []
        self.occluders: List[Occluder] = []
        self.background = self._build_background(distractors)
        if distractors:
            self._add_dynamic_lights()
        n = int(rng.choice([0, 0, 0, 1, 1, 2])) if n_poles is None else n_poles
        for _ in range(n):
            self.occluders.append(self._random_pole())
        self.rain = self._rain_layer() if weather == "rain" else None

    # ----------------------------------------------------------------- background
    def _proj(self, X: float, Y: float, Z: float, m: float = 0.0) -> Tuple[float, float]:
        """Image position of the world point (X right, Y up from the ground, Z ahead), plus margin ``m``."""
        g = self.geo
        return g.vanish_x + m + g.focal * X / Z, g.horizon + m + g.focal * (g.cam_h - Y) / Z

    def _quad(self, img: np.ndarray, X0: float, X1: float, Y0: float, Y1: float, Z0: float, Z1: float, colour, m: float) -> None:
        """Fill the projection of a world rectangle that is either vertical along Z (X0 == X1),
        facing the camera (Z0 == Z1) or lying on the ground (Y0 == Y1)."""
        if X0 == X1:
            pts = [self._proj(X0, Y0, Z0, m), self._proj(X0, Y1, Z0, m), self._proj(X0, Y1, Z1, m), self._proj(X0, Y0, Z1, m)]
        elif Z0 == Z1:
            pts = [self._proj(X0, Y0, Z0, m), self._proj(X1, Y0, Z0, m), self._proj(X1, Y1, Z0, m), self._proj(X0, Y1, Z0, m)]
        else:
            pts = [self._proj(X0, Y0, Z0, m), self._proj(X1, Y0, Z0, m), self._proj(X1, Y0, Z1, m), self._proj(X0, Y0, Z1, m)]
        fill(img, np.array(pts), colour)

    def _build_background(self, distractors: bool) -> np.ndarray:
        rng, lt, g = self.rng, self.lighting, self.geo
        m = self.margin
        W, H = self.width + 2 * m, self.height + 2 * m
        hy = g.horizon + m
        bg = np.zeros((H, W, 3), np.uint8)
        glow = np.zeros(((H + GLOW_SCALE - 1) // GLOW_SCALE, (W + GLOW_SCALE - 1) // GLOW_SCALE, 3), np.float32)
        amb = lambda c, e=1.0: shade(c, lt, e)  # noqa: E731
        # Sky: vertical gradient from zenith to horizon.
        if lt.name == "day":
            top = np.array([rng.uniform(150, 225), rng.uniform(110, 175), rng.uniform(60, 115)])
            if rng.random() < 0.4:
                v = rng.uniform(150, 215)
                top = np.array([v + 8, v + 3, v])
            hor = np.array([rng.uniform(200, 245), rng.uniform(195, 240), rng.uniform(185, 235)])
        elif lt.name == "dusk":
            top = np.array([rng.uniform(70, 120), rng.uniform(40, 70), rng.uniform(40, 80)])
            hor = np.array([rng.uniform(60, 130), rng.uniform(110, 170), rng.uniform(170, 230)])
        else:
            top = np.array([rng.uniform(8, 30), rng.uniform(5, 20), rng.uniform(3, 15)])
            hor = np.array([rng.uniform(25, 55), rng.uniform(25, 55), rng.uniform(30, 65)])
        rows = np.clip(np.arange(H) / max(hy, 1.0), 0, 1)[:, None] ** 1.5
        bg[:] = (top[None, :] * (1 - rows) + hor[None, :] * rows).astype(np.uint8)[:, None, :]
        scene = str(rng.choice(["city", "city", "suburb", "open"]))
        self.scene = scene
        # Far skyline at the horizon.
        x = 0.0
        while x < W:
            bw = rng.uniform(10, 60)
            bh = (rng.uniform(4, 50) if scene == "city" else rng.uniform(2, 12))
            if scene == "city":
                v = rng.uniform(90, 190)
                col = amb((v * rng.uniform(0.9, 1.1), v, v * rng.uniform(0.9, 1.15)), 0.75)
            else:
                col = amb((rng.uniform(40, 90), rng.uniform(80, 130), rng.uniform(60, 100)), 0.7)
            fill(bg, np.array([[x, hy - bh], [x + bw, hy - bh], [x + bw, hy + 3], [x, hy + 3]]), col)
            if lt.name != "day" and scene == "city":
                for _ in range(int(bw * bh / 60)):
                    if rng.random() < 0.4:
                        wx, wy = int(x + rng.uniform(1, bw - 1)), int(hy - rng.uniform(1, bh))
                        bg[max(wy, 0), min(max(wx, 0), W - 1)] = (rng.uniform(60, 140), rng.uniform(150, 210), rng.uniform(200, 255))
            x += bw
        z_near, z_far = 0.6, 400.0
        xl, xr = g.x_left, g.x_right
        # Ground, sidewalks, road, kerbs, lane markings.
        ground = amb((rng.uniform(80, 140), rng.uniform(110, 165), rng.uniform(100, 160)) if scene != "city" else (rng.uniform(120, 170),) * 3)
        fill(bg, np.array([[0, hy], [W, hy], [W, H], [0, H]]), ground)
        walk = amb((rng.uniform(120, 180), rng.uniform(125, 180), rng.uniform(125, 190)))
        sw = rng.uniform(2.0, 5.0)
        if scene == "city":
            self._quad(bg, xl - sw, xl, 0, 0, z_near, z_far, walk, m)
            self._quad(bg, xr, xr + sw, 0, 0, z_near, z_far, walk, m)
        asphalt = amb((rng.uniform(65, 115),) * 3)
        asphalt = (asphalt[0] * rng.uniform(0.95, 1.06), asphalt[1], asphalt[2] * rng.uniform(0.94, 1.05))
        self._quad(bg, xl, xr, 0, 0, z_near, z_far, asphalt, m)
        # Darker wheel tracks and patches give the asphalt some structure.
        for _ in range(int(rng.integers(2, 8))):
            X = rng.uniform(xl, xr)
            Z = rng.uniform(3, 60)
            self._quad(bg, X, X + rng.uniform(0.5, 3), 0, 0, Z, Z + rng.uniform(2, 15), tuple(c * rng.uniform(0.85, 1.1) for c in asphalt), m)
        kerb = amb((185, 185, 185))
        for X in (xl, xr):
            self._quad(bg, X - 0.12, X + 0.12, 0, 0, z_near, z_far, kerb, m)
        mark = amb((rng.uniform(205, 240), rng.uniform(205, 240), rng.uniform(205, 245)))
        yellow = amb((40, 185, 230))
        n_lanes = max(1, int((xr - xl) / g.lane_w))
        dash, gap = rng.uniform(2.5, 4.5), rng.uniform(4.0, 9.0)
        for k in range(1, n_lanes):
            X = xl + (xr - xl) * k / n_lanes
            centre = abs(X) < g.lane_w * 0.5 and rng.random() < 0.35
            col = yellow if centre else mark
            if centre or rng.random() < 0.15:
                self._quad(bg, X - 0.07, X + 0.07, 0, 0, 1.0, z_far, col, m)
                continue
            Z = 1.0 + rng.uniform(0, dash + gap)
            while Z < 160:
                self._quad(bg, X - 0.07, X + 0.07, 0, 0, Z, Z + dash, col, m)
                Z += dash + gap
        if rng.random() < 0.25:  # pedestrian crossing
            Z = rng.uniform(6, 30)
            X = xl
            while X < xr:
                self._quad(bg, X, X + 0.5, 0, 0, Z, Z + 3.0, mark, m)
                X += 1.0
        # Roadside: facades (city), houses and trees (suburb), guard rail (open).
        lit_p = 0.35 if lt.name != "day" else 0.0
        for side in (-1, 1):
            Xf = (xl - sw) if side < 0 else (xr + sw)
            if scene == "city":
                Z = z_near
                while Z < 220:
                    length = rng.uniform(8, 30)
                    height = rng.uniform(6, 28)
                    v = rng.uniform(80, 210)
                    col = amb((v * rng.uniform(0.8, 1.15), v * rng.uniform(0.85, 1.1), v * rng.uniform(0.85, 1.2)))
                    if rng.random() < 0.12:  # side street: a gap
                        Z += rng.uniform(8, 15)
                        continue
                    self._quad(bg, Xf, Xf, 0, height, Z, Z + length, col, m)
                    # Front face of the next building block shows when it is taller.
                    win_w, win_h = rng.uniform(0.9, 1.8), rng.uniform(1.0, 1.8)
                    pitch = rng.uniform(2.4, 4.0)
                    dark = amb((rng.uniform(30, 80),) * 3, 0.9)
                    scale_px = g.focal / max(Z, 1.0)
                    if scale_px * win_w > 0.7:
                        for fl in np.arange(4.0, height - 1.5, 3.0):
                            for zc in np.arange(Z + 1.0, Z + length - win_w, pitch):
                                if g.focal * win_w / zc < 0.6:
                                    break
                                lit = rng.random() < lit_p
                                wc = (rng.uniform(70, 150), rng.uniform(160, 220), rng.uniform(200, 255)) if lit else dark
                                self._quad(bg, Xf, Xf, fl, fl + win_h, zc, zc + win_w, wc, m)
                                if lit:
                                    x, y = self._proj(Xf, fl + win_h / 2, zc + win_w / 2, m)
                                    add_glow(glow, x, y, 0.5 * g.focal * win_w / zc, wc, 0.1)
                    # Shop fronts at street level: windows and a sign, lit after dark.
                    if rng.random() < 0.55:
                        z0 = Z + rng.uniform(0.5, 3)
                        z1 = min(Z + length - 0.5, z0 + rng.uniform(3, 10))
                        shop_lit = lt.name != "day" and rng.random() < 0.7
                        sc = (rng.uniform(110, 190), rng.uniform(170, 230), rng.uniform(200, 250)) if shop_lit else amb((rng.uniform(35, 70),) * 3)
                        self._quad(bg, Xf, Xf, 0.3, 2.6, z0, z1, sc, m)
                        if shop_lit:
                            x, y = self._proj(Xf, 1.4, (z0 + z1) / 2, m)
                            add_glow(glow, x, y, g.focal * 1.0 / z0, sc, 0.2)
                        if distractors and rng.random() < 0.7:
                            palette = [(40, 160, 255), (40, 40, 230), (230, 160, 40), (80, 220, 80), (200, 80, 220), (230, 230, 235), (30, 200, 250)]
                            sgc = palette[int(rng.integers(0, len(palette)))]
                            self._quad(bg, Xf, Xf, 2.8, 3.5, z0, z1, sgc if lt.name != "day" else amb(sgc, 0.9), m)
                            if lt.name != "day":
                                x, y = self._proj(Xf, 3.15, (z0 + z1) / 2, m)
                                add_glow(glow, x, y, g.focal * 0.5 / z0, sgc, 0.4)
                    Z += length
            elif scene == "suburb":
                Z = z_near + rng.uniform(0, 5)
                while Z < 150:
                    if rng.random() < 0.5:  # a house behind the trees
                        Xh = Xf + side * rng.uniform(5, 12)
                        hc = amb((rng.uniform(120, 220), rng.uniform(130, 220), rng.uniform(140, 230)))
                        hh, hl = rng.uniform(3.5, 6), rng.uniform(6, 12)
                        self._quad(bg, Xh, Xh, 0, hh, Z, Z + hl, hc, m)
                        roof = [self._proj(Xh, hh, Z, m), self._proj(Xh, hh + rng.uniform(1.5, 3), Z + hl / 2, m), self._proj(Xh, hh, Z + hl, m)]
                        fill(bg, np.array(roof), amb((rng.uniform(30, 80), rng.uniform(40, 80), rng.uniform(60, 140))))
                        for zc in np.arange(Z + 1.0, Z + hl - 1.5, 3.0):
                            self._quad(bg, Xh, Xh, 1.0, 2.2, zc, zc + 1.2, amb((50, 50, 55)) if lt.name == "day" or rng.random() < 0.5
                                       else (90, 170, 230), m)
                    Xt = Xf + side * rng.uniform(0.5, 2.0)
                    r = rng.uniform(1.5, 4.0)
                    x, y = self._proj(Xt, 0, Z, m)
                    _, yt = self._proj(Xt, rng.uniform(2.0, 3.0), Z, m)
                    px = g.focal / Z
                    fill(bg, np.array([[x - 0.15 * px, yt], [x + 0.15 * px, yt], [x + 0.15 * px, y], [x - 0.15 * px, y]]), amb((40, 55, 70)))
                    tc = amb((rng.uniform(30, 70), rng.uniform(80, 135), rng.uniform(40, 85)))
                    ellipse(bg, x, yt - r * px * 0.6, r * px, r * px * rng.uniform(0.7, 1.0), tc)
                    Z += rng.uniform(6, 20)
            else:
                rail = amb((170, 170, 175))
                for Z in np.arange(2.0, 120.0, 4.0):
                    x0, y0 = self._proj(Xf, 0, Z, m)
                    x1, y1 = self._proj(Xf, 0.75, Z, m)
                    fill(bg, np.array([[x0 - 0.4, y1], [x0 + 0.4, y1], [x0 + 0.4, y0], [x0 - 0.4, y0]]), amb((90, 90, 90)))
                self._quad(bg, Xf, Xf, 0.55, 0.8, 1.0, 300, rail, m)
        # Street lamps along the kerbs.
        head = [(80, 170, 255), (230, 235, 245), (160, 220, 255)][int(rng.integers(0, 3))]
        spacing = rng.uniform(20, 40)
        pole = amb((70, 70, 75))
        for side, X in ((-1, xl - 0.4), (1, xr + 0.4)):
            Z = rng.uniform(3, spacing)
            height = rng.uniform(7, 10)
            while Z < 200:
                x0, y0 = self._proj(X, 0, Z, m)
                x1, y1 = self._proj(X, height, Z, m)
                x2, y2 = self._proj(X - side * 2.0, height, Z, m)
                hw = max(0.4, 0.12 * g.focal / Z)
                fill(bg, np.array([[x0 - hw, y1], [x0 + hw, y1], [x0 + hw, y0], [x0 - hw, y0]]), pole)
                fill(bg, np.array([[x1, y1 - hw], [x2, y2 - hw], [x2, y2 + hw], [x1, y1 + hw]]), pole)
                if lt.name != "day":
                    ellipse(bg, x2, y2 + hw, max(0.8, 0.35 * g.focal / Z), max(0.5, 0.12 * g.focal / Z), head)
                    add_glow(glow, x2, y2 + hw, 0.25 * g.focal / Z + 1, head, 0.8)
                    xg, yg = self._proj(X - side * 2.0, 0, Z, m)
                    add_glow(glow, xg, yg, 2.5 * g.focal / Z, head, 0.03)  # pool of light on the road
                Z += spacing
        sun = lt.name != "night" and rng.random() < (0.25 if lt.name == "day" else 0.35)
        if sun:
            # Low sun in the sky: a white-hot disk and a wide warm halo (glare).
            sx, sy = rng.uniform(0, W), hy * rng.uniform(0.1, 0.9)
            r = rng.uniform(6, 14)
            ellipse(bg, sx, sy, r, r, (235, 250, 255))
            add_glow(glow, sx, sy, r * 4, (200, 235, 255), rng.uniform(0.4, 0.9))
        # Low-frequency texture so that flat areas are not perfectly flat.
        tex = cv2.resize(rng.normal(0, 1, (H // 16 + 2, W // 16 + 2)).astype(np.float32), (W, H), interpolation=cv2.INTER_CUBIC)
        fine = rng.normal(0, 1, (H, W)).astype(np.float32)
        below = (np.arange(H, dtype=np.float32) > hy)[:, None]  # the sky stays smooth
        t = (tex * rng.uniform(2, 6) * below + cv2.GaussianBlur(fine, (3, 3), 0) * 2.5) * lt.ambient
        out = bg.astype(np.float32) + t[:, :, None]
        if lt.name != "day" or sun:
            out += blur_glow(glow * lt.glow, W, H, 2.0 if sun else 0.8).astype(np.float32)
        return np.clip(out, 0, 255).astype(np.uint8)

    # ----------------------------------------------------------------- distractors
    def _add_dynamic_lights(self) -> None:
        rng, lt, g = self.rng, self.lighting, self.geo
        W = self.width
        n = int(rng.integers(1, 5)) + (2 if lt.name != "day" else 0)
        for _ in range(n):
            kind = rng.choice(["beacon", "sign", "pair", "pair", "traffic"])
            if kind == "pair":
                # A far vehicle: two small rear lights (or headlights) far down the road.
                Z = rng.uniform(70, 220)
                X = rng.uniform(g.x_left + 1, g.x_right - 1)
                x, y = self._proj(X, 0.8, Z)
                sep = 0.75 * g.focal / Z
                head = rng.random() < 0.35
                col = (240, 240, 250) if head else (30, 20, 235)
                body = (rng.uniform(20, 200),) * 3
                self.lights.append(DistractorLight(x, y, sep, max(0.6, 0.12 * g.focal / Z), col, "pair", period=1 / rng.uniform(1, 2.2),
                                                   duty=rng.uniform(0.3, 0.7), phase=rng.uniform(0, 1), vx=rng.uniform(-3, 3),
                                                   glow=rng.uniform(0.5, 1.2), seed=int(rng.integers(0, 1 << 30)), body=body))
            elif kind == "beacon":
                Z = rng.uniform(8, 80)
                X = rng.choice([g.x_left, g.x_right]) + rng.uniform(-1.5, 1.5)
                x, y = self._proj(X, rng.uniform(0.5, 2.5), Z)
                col = (rng.uniform(0, 40), rng.uniform(130, 200), 255.0) if rng.random() < 0.7 else (30, 30, 240)
                r = max(0.8, 0.12 * g.focal / Z)
                self.lights.append(DistractorLight(x, y, r, r, col, "blink", period=1 / rng.uniform(0.8, 2.5),
                                                   duty=rng.uniform(0.3, 0.7), phase=rng.uniform(0, 1), glow=rng.uniform(0.6, 1.5)))
            elif kind == "traffic":
                Z = rng.uniform(20, 90)
                X = rng.choice([g.x_left, g.x_right]) + rng.uniform(-1, 1)
                x, y = self._proj(X, rng.uniform(3.5, 5.5), Z)
                col = [(40, 40, 240), (90, 230, 60), (20, 170, 255)][int(rng.integers(0, 3))]
                mode = "blink" if col[2] == 255 and rng.random() < 0.6 else "steady"
                r = max(0.8, 0.12 * g.focal / Z)
                self.lights.append(DistractorLight(x, y, r, r, col, mode, period=1 / rng.uniform(0.8, 1.5), duty=0.5,
                                                   phase=rng.uniform(0, 1), glow=1.0, body=(25, 25, 25)))
            else:
                x, y = rng.uniform(0, W), rng.uniform(0.3, 1.0) * g.horizon
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
                    add_glow(layer, x + sgn * d.rx, y, d.ry * 1.5, col, 0.6 * d.glow * lev * self.lighting.glow)
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
            add_glow(layer, x, y, max(d.rx, d.ry) * 1.0, d.colour, 0.5 * d.glow * self.lighting.glow)

    # ----------------------------------------------------------------- foreground
    def _random_pole(self) -> Occluder:
        rng, lt = self.rng, self.lighting
        W, H = self.width, self.height
        width = rng.uniform(4, 20)
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
