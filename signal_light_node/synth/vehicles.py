"""Vehicle bodies: kinds, sizes, colours and a silhouette per kind and view.

Shapes are polygons in normalised box coordinates (u right, v down, both 0..1), so one
shape serves every size; the renderer maps them to pixels with a per-frame affine
transform (scale, slight shear and roll) and fills them anti-aliased.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Tuple

import numpy as np

from signal_light_node.labels import View
from signal_light_node.synth.environment import Lighting, shade

#: Body kinds with (width, height, length) in metres.
KIND_DIMS: Dict[str, Tuple[float, float, float]] = {
    "car": (1.8, 1.45, 4.5),
    "suv": (1.9, 1.75, 4.8),
    "van": (2.0, 2.3, 5.3),
    "truck": (2.5, 3.3, 8.0),
    "bus": (2.55, 3.1, 12.0),
}
KINDS: Tuple[str, ...] = tuple(KIND_DIMS)
KIND_WEIGHTS: Tuple[float, ...] = (0.45, 0.22, 0.14, 0.1, 0.09)

#: What a detector calls each kind.
CLASS_IDS: Dict[str, str] = {"car": "car", "suv": "car", "van": "car", "truck": "truck", "bus": "bus"}

#: Body paint palette (BGR) with sampling weights; red, orange, white, dark and silver included.
PALETTE: Tuple[Tuple[Tuple[int, int, int], float], ...] = (
    ((235, 235, 235), 0.16),   # white
    ((30, 30, 32), 0.14),      # black
    ((70, 70, 72), 0.1),       # dark grey
    ((175, 172, 168), 0.14),   # silver
    ((120, 118, 115), 0.07),   # grey
    ((35, 35, 170), 0.08),     # red
    ((25, 25, 110), 0.04),     # dark red
    ((20, 110, 230), 0.05),    # orange
    ((120, 60, 20), 0.07),     # blue
    ((90, 40, 25), 0.04),      # dark blue
    ((50, 90, 40), 0.03),      # green
    ((20, 190, 225), 0.03),    # yellow
    ((140, 170, 190), 0.03),   # beige
    ((60, 80, 105), 0.02),     # brown
)

Poly = np.ndarray  # (N, 2) float32 normalised points


@dataclass
class BodyShape:
    """Polygons of one face of a body, grouped by paint key, in draw order.

    Attributes:
        silhouette: Polygons whose union is the vehicle's outline.
        parts: (paint key, polygon) in draw order; keys: body, shade, glass, dark, trim,
            plate, grille, sign, box, arch, tyre, hub.
        fill_ratio: Fraction of the box the silhouette covers (for occlusion bookkeeping).
        chmsl_v: Vertical position for a centre brake lamp.
    """

    silhouette: List[Poly]
    parts: List[Tuple[str, Poly]]
    fill_ratio: float = 0.8
    chmsl_v: float = 0.05


def sample_colour(rng: np.random.Generator) -> Tuple[float, float, float]:
    """A body colour from the palette with a little per-vehicle variation."""
    colours, weights = zip(*PALETTE)
    w = np.asarray(weights) / np.sum(weights)
    base = np.asarray(colours[int(rng.choice(len(colours), p=w))], dtype=float)
    base = base * rng.uniform(0.85, 1.12) + rng.normal(0, 6, 3)
    return tuple(float(c) for c in np.clip(base, 5, 250))



def sample_paints(rng: np.random.Generator, colour, lt: Lighting) -> Dict[str, Tuple[float, float, float]]:
    """Colour of every paint key of a body (``BodyShape.parts``, plus the flank and its
    glass) under the scene's light, from the body colour and a few random trims."""
    glass_g = rng.uniform(35, 95) if lt.name == "day" else rng.uniform(10, 35)
    glass = (glass_g * rng.uniform(1.0, 1.25), glass_g * rng.uniform(0.95, 1.1), glass_g)
    trim = (rng.uniform(25, 50),) * 3 if rng.random() < 0.6 else tuple(c * 0.8 for c in colour)
    plate = (230, 230, 230) if rng.random() < 0.75 else (40, 200, 240)
    box = colour if rng.random() < 0.4 else (rng.uniform(180, 240),) * 3
    return {
        "body": shade(colour, lt), "shade": shade(colour, lt, 0.55), "glass": shade(glass, lt, 1.0 / max(lt.ambient, 0.5)),
        "dark": shade((22, 22, 24), lt), "trim": shade(trim, lt), "plate": shade(plate, lt, 1.0 if lt.name == "day" else 2.0),
        "grille": shade((rng.uniform(20, 60),) * 3 if rng.random() < 0.8 else (160, 160, 165), lt),
        "sign": (20, 150, 250) if lt.name != "day" else shade((20, 120, 220), lt, 1.3), "box": shade(box, lt),
        "arch": shade((18, 18, 20), lt), "tyre": shade((rng.uniform(25, 40),) * 3, lt),
        "hub": shade((rng.uniform(60, 190),) * 3, lt), "flank": shade(colour, lt, rng.uniform(0.6, 0.85)),
        "flank_glass": shade(glass, lt, 0.8 / max(lt.ambient, 0.5)),
    }

def _rrect(u0: float, v0: float, u1: float, v1: float, ru: float = 0.0, rv: float = 0.0, n: int = 3) -> Poly:
    """Rounded rectangle as a polygon (radii in normalised units per axis)."""
    if ru <= 0 or rv <= 0:
        return np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]], np.float32)
    pts = []
    corners = ((u1 - ru, v0 + rv, -np.pi / 2), (u1 - ru, v1 - rv, 0.0), (u0 + ru, v1 - rv, np.pi / 2), (u0 + ru, v0 + rv, np.pi))
    for cu, cv, a0 in corners:
        for k in range(n + 1):
            a = a0 + (np.pi / 2) * k / n
            pts.append((cu + ru * np.cos(a), cv + rv * np.sin(a)))
    return np.array(pts, np.float32)


def _ellipse(cu: float, cv: float, ru: float, rv: float, n: int = 14) -> Poly:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([cu + ru * np.cos(a), cv + rv * np.sin(a)], 1).astype(np.float32)


def _p(*pts: Tuple[float, float]) -> Poly:
    return np.array(pts, np.float32)


def _mirror(shape: BodyShape) -> BodyShape:
    def m(p: Poly) -> Poly:
        q = p.copy()
        q[:, 0] = 1.0 - q[:, 0]
        return q
    return BodyShape([m(p) for p in shape.silhouette], [(k, m(p)) for k, p in shape.parts], shape.fill_ratio, shape.chmsl_v)


def _rear(kind: str, rng: np.random.Generator) -> BodyShape:
    j = lambda s: float(rng.uniform(-s, s))  # noqa: E731 - tiny jitter helper
    tyre_w = 0.13 + j(0.02)
    tyres = [_rrect(0.06, 0.8, 0.06 + tyre_w, 1.0, 0.02, 0.02), _rrect(0.94 - tyre_w, 0.8, 0.94, 1.0, 0.02, 0.02)]
    parts: List[Tuple[str, Poly]] = [("tyre", t) for t in tyres]
    if kind in ("car", "suv"):
        roof_in = 0.15 + j(0.04)
        belt = (0.4 if kind == "car" else 0.44) + j(0.04)
        cabin = _p((roof_in, 0.0), (1 - roof_in, 0.0), (0.96, belt), (0.04, belt))
        body = _rrect(0.0, belt - 0.03, 1.0, 0.9, 0.05, 0.07)
        win_top, win_bot = 0.05 + j(0.02), belt - 0.05 + j(0.02)
        gi = roof_in + 0.04
        glass = _p((gi, win_top), (1 - gi, win_top), (1 - gi + 0.07 * (win_bot - win_top) / 0.35, win_bot), (gi - 0.07 * (win_bot - win_top) / 0.35, win_bot))
        parts += [("body", cabin), ("body", body), ("glass", glass),
                  ("trim", _rrect(0.02, 0.74 + j(0.03), 0.98, 0.87, 0.03, 0.03)),
                  ("shade", _p((0.03, belt + 0.01), (0.97, belt + 0.01), (0.97, belt + 0.025), (0.03, belt + 0.025))),
                  ("plate", _rrect(0.39, 0.6, 0.61, 0.7, 0.01, 0.01))]
        sil = [cabin, body] + tyres
        return BodyShape(sil, parts, 0.86, max(0.005, win_top - 0.04) if rng.random() < 0.5 else win_top + 0.01)
    if kind == "van":
        body = _rrect(0.0, 0.0, 1.0, 0.92, 0.07, 0.06)
        parts += [("body", body),
                  ("glass", _rrect(0.08, 0.07, 0.48, 0.36, 0.02, 0.02)), ("glass", _rrect(0.52, 0.07, 0.92, 0.36, 0.02, 0.02)),
                  ("shade", _p((0.495, 0.04), (0.505, 0.04), (0.505, 0.82), (0.495, 0.82))),
                  ("trim", _rrect(0.01, 0.82, 0.99, 0.92, 0.02, 0.02)), ("plate", _rrect(0.39, 0.7, 0.61, 0.79, 0.01, 0.01))]
        return BodyShape([body] + tyres, parts, 0.93, 0.012)
    if kind == "truck":
        box = _p((0.0, 0.0), (1.0, 0.0), (1.0, 0.84), (0.0, 0.84))
        frame = _p((0.04, 0.84), (0.96, 0.84), (0.96, 0.9), (0.04, 0.9))
        parts += [("body", box), ("shade", _p((0.497, 0.02), (0.503, 0.02), (0.503, 0.83), (0.497, 0.83))),
                  ("shade", _p((0.02, 0.02), (0.98, 0.02), (0.98, 0.035), (0.02, 0.035))),
                  ("dark", frame), ("trim", _p((0.1, 0.9), (0.9, 0.9), (0.9, 0.94), (0.1, 0.94))),
                  ("plate", _rrect(0.4, 0.86, 0.6, 0.93, 0.01, 0.01))]
        return BodyShape([box, frame] + tyres, parts, 0.9, 0.01)
    # bus
    body = _rrect(0.0, 0.0, 1.0, 0.95, 0.06, 0.05)
    parts += [("body", body), ("glass", _rrect(0.07, 0.05, 0.93, 0.33 + j(0.05), 0.02, 0.02)),
              ("grille", _rrect(0.15, 0.45, 0.85, 0.7, 0.02, 0.02)),
              ("trim", _rrect(0.01, 0.86, 0.99, 0.95, 0.02, 0.02)), ("plate", _rrect(0.4, 0.76, 0.6, 0.83, 0.01, 0.01))]
    return BodyShape([body] + tyres, parts, 0.95, 0.008)


def _front(kind: str, rng: np.random.Generator) -> BodyShape:
    j = lambda s: float(rng.uniform(-s, s))  # noqa: E731
    tyre_w = 0.12 + j(0.02)
    tyres = [_rrect(0.07, 0.82, 0.07 + tyre_w, 1.0, 0.02, 0.02), _rrect(0.93 - tyre_w, 0.82, 0.93, 1.0, 0.02, 0.02)]
    parts: List[Tuple[str, Poly]] = [("tyre", t) for t in tyres]
    mirrors = [_rrect(0.0, 0.3, 0.05, 0.4, 0.01, 0.01), _rrect(0.95, 0.3, 1.0, 0.4, 0.01, 0.01)]
    if kind in ("car", "suv", "van"):
        roof_in = {"car": 0.16, "suv": 0.13, "van": 0.08}[kind] + j(0.03)
        belt = {"car": 0.42, "suv": 0.45, "van": 0.48}[kind] + j(0.03)
        cabin = _p((roof_in, 0.0), (1 - roof_in, 0.0), (0.95, belt), (0.05, belt))
        body = _rrect(0.03, belt - 0.04, 0.97, 0.9, 0.05, 0.07)
        glass = _p((roof_in + 0.03, 0.04), (0.97 - roof_in, 0.04), (0.9, belt - 0.03), (0.1, belt - 0.03))
        gw = 0.2 + j(0.08)
        parts += [("body", cabin), ("body", body), ("glass", glass), ("dark", mirrors[0]), ("dark", mirrors[1]),
                  ("grille", _rrect(0.5 - gw, belt + 0.12 + j(0.03), 0.5 + gw, belt + 0.27, 0.03, 0.03)),
                  ("dark", _rrect(0.22, 0.78, 0.78, 0.87, 0.02, 0.02)), ("plate", _rrect(0.4, 0.77, 0.6, 0.85, 0.01, 0.01))]
        return BodyShape([cabin, body] + tyres + mirrors, parts, 0.84, 0.0)
    body = _rrect(0.03, 0.0, 0.97, 0.92, 0.05, 0.04)
    if kind == "truck":
        parts += [("body", body), ("glass", _rrect(0.08, 0.1, 0.92, 0.45, 0.03, 0.03)), ("dark", mirrors[0]), ("dark", mirrors[1]),
                  ("grille", _rrect(0.25, 0.55, 0.75, 0.75, 0.02, 0.02)), ("trim", _rrect(0.03, 0.84, 0.97, 0.92, 0.02, 0.02)),
                  ("plate", _rrect(0.4, 0.85, 0.6, 0.91, 0.01, 0.01))]
    else:
        parts += [("body", body), ("glass", _rrect(0.06, 0.12, 0.94, 0.6, 0.03, 0.03)), ("sign", _rrect(0.15, 0.025, 0.85, 0.1, 0.01, 0.01)),
                  ("dark", mirrors[0]), ("dark", mirrors[1]),
                  ("trim", _rrect(0.03, 0.86, 0.97, 0.92, 0.02, 0.02)), ("plate", _rrect(0.4, 0.8, 0.6, 0.86, 0.01, 0.01))]
    return BodyShape([body] + tyres + mirrors, parts, 0.9, 0.0)


def _side(kind: str, rng: np.random.Generator) -> BodyShape:
    """Flank with the vehicle pointing to the image left (the view from its left side)."""
    j = lambda s: float(rng.uniform(-s, s))  # noqa: E731
    _, height, length = KIND_DIMS[kind]
    radius = {"car": 0.32, "suv": 0.37, "van": 0.35, "truck": 0.5, "bus": 0.5}[kind]
    rv, ru = radius / height, radius / length
    wheel_v = 1.0 - rv
    front_u, rear_u = (0.17 + j(0.02), 0.82 + j(0.02)) if kind != "bus" else (0.13, 0.76)
    wheels = [_ellipse(front_u, wheel_v, ru, rv), _ellipse(rear_u, wheel_v, ru, rv)]
    hubs = [_ellipse(front_u, wheel_v, ru * 0.5, rv * 0.5), _ellipse(rear_u, wheel_v, ru * 0.5, rv * 0.5)]
    arches = [_ellipse(front_u, wheel_v, ru * 1.12, rv * 1.12), _ellipse(rear_u, wheel_v, ru * 1.12, rv * 1.12)]
    if kind in ("car", "suv"):
        low = 0.38 if kind == "car" else 0.36
        roof = 0.0
        a, b = (0.34 + j(0.04), 0.78 + j(0.04)) if kind == "car" else (0.3 + j(0.03), 0.92)
        hood = 0.35 if kind == "car" else 0.3
        outline = _p((0.0, hood + 0.12), (0.02, hood), (a - 0.12, hood - 0.03), (a, roof + 0.03), (a + 0.05, roof), (b - 0.02, roof),
                     (b + 0.07, low - 0.05 if kind == "car" else roof + 0.04), (1.0, low - 0.02), (1.0, 0.76), (0.98, 1.0 - rv * 0.4),
                     (0.02, 1.0 - rv * 0.4), (0.0, 0.72))
        glass = _p((a - 0.08, hood - 0.03), (a + 0.01, roof + 0.06), (a + 0.05, roof + 0.04), (b - 0.03, roof + 0.04),
                   (b + 0.04, low - 0.07 if kind == "car" else roof + 0.08), (b + 0.04, hood - 0.02))
        pillar = _p((0.56 + j(0.03), roof + 0.03), (0.59 + j(0.0), roof + 0.03), (0.59, hood), (0.56, hood))
        parts = [("body", outline), ("glass", glass), ("body", pillar), ("arch", arches[0]), ("arch", arches[1]), ("tyre", wheels[0]), ("tyre", wheels[1]),
                 ("hub", hubs[0]), ("hub", hubs[1]),
                 ("shade", _p((0.02, 0.78), (0.98, 0.78), (0.98, 0.82), (0.02, 0.82))),
                 ("shade", _p((0.57, hood + 0.02), (0.575, hood + 0.02), (0.575, 0.8), (0.57, 0.8)))]
        return BodyShape([outline] + wheels, parts, 0.78, 0.0)
    if kind == "van":
        outline = _p((0.0, 0.5), (0.03, 0.38), (0.13, 0.3), (0.22, 0.02), (0.26, 0.0), (1.0, 0.0), (1.0, 1.0 - rv * 0.4), (0.0, 1.0 - rv * 0.4))
        parts = [("body", outline), ("glass", _p((0.14, 0.3), (0.23, 0.05), (0.32, 0.05), (0.32, 0.3))),
                 ("glass", _rrect(0.36, 0.06, 0.62, 0.3, 0.01, 0.02)),
                 ("arch", arches[0]), ("arch", arches[1]), ("tyre", wheels[0]), ("tyre", wheels[1]),
                 ("hub", hubs[0]), ("hub", hubs[1]),
                 ("shade", _p((0.34, 0.05), (0.345, 0.05), (0.345, 0.85), (0.34, 0.85)))]
        return BodyShape([outline] + wheels, parts, 0.88, 0.0)
    if kind == "truck":
        cab = _p((0.0, 0.35), (0.02, 0.12), (0.05, 0.06), (0.2, 0.06), (0.2, 1.0 - rv * 0.4), (0.0, 1.0 - rv * 0.4))
        box = _p((0.22, 0.0), (1.0, 0.0), (1.0, 0.8), (0.22, 0.8))
        chassis = _p((0.18, 0.8), (1.0, 0.8), (1.0, 0.86), (0.18, 0.86))
        parts = [("box", box), ("body", cab), ("glass", _p((0.03, 0.14), (0.06, 0.1), (0.16, 0.1), (0.16, 0.38), (0.02, 0.38))),
                 ("dark", chassis), ("arch", arches[0]), ("arch", arches[1]), ("tyre", wheels[0]), ("tyre", wheels[1]),
                 ("hub", hubs[0]), ("hub", hubs[1]),
                 ("shade", _p((0.22, 0.77), (1.0, 0.77), (1.0, 0.8), (0.22, 0.8)))]
        return BodyShape([cab, box, chassis] + wheels, parts, 0.82, 0.0)
    body = _rrect(0.0, 0.0, 1.0, 1.0 - rv * 0.35, 0.01, 0.04)
    parts = [("body", body), ("glass", _rrect(0.0, 0.12, 0.1, 0.55, 0.005, 0.02)),
             ("glass", _p((0.14, 0.12), (0.98, 0.12), (0.98, 0.42), (0.14, 0.42))),
             ("glass", _p((0.03, 0.6), (0.06, 0.6), (0.06, 0.92), (0.03, 0.92))),
             ("sign", _p((0.015, 0.03), (0.09, 0.03), (0.09, 0.09), (0.015, 0.09))),
             ("shade", _p((0.0, 0.5), (1.0, 0.5), (1.0, 0.53), (0.0, 0.53))),
             ("arch", arches[0]), ("arch", arches[1]), ("tyre", wheels[0]), ("tyre", wheels[1]), ("hub", hubs[0]), ("hub", hubs[1])]
    for k in range(1, 7):
        u = 0.14 + k * 0.12
        parts.append(("shade", _p((u, 0.12), (u + 0.006, 0.12), (u + 0.006, 0.42), (u, 0.42))))
    return BodyShape([body] + wheels, parts, 0.92, 0.0)


def body_shape(kind: str, view: View, rng: np.random.Generator) -> BodyShape:
    """The polygons of ``kind`` seen from ``view`` with a little per-vehicle variation."""
    if view == View.BEHIND:
        return _rear(kind, rng)
    if view == View.FRONT:
        return _front(kind, rng)
    shape = _side(kind, rng)
    return shape if view == View.LEFT else _mirror(shape)


def face_size_m(kind: str, view: View, scale: float = 1.0) -> Tuple[float, float]:
    """Width and height in metres of the face the camera sees."""
    w, h, length = KIND_DIMS[kind]
    return ((w if view in (View.BEHIND, View.FRONT) else length) * scale, h * scale)
