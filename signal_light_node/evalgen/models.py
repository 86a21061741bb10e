"""Vehicle models of the evaluation generator: 3D hexahedral solids, lamp layouts placed on
their faces, and the signal timelines that drive the lamps.

Vehicle frame: ``a`` forward, ``b`` to the vehicle's own left, ``y`` up; the origin is on
the ground under the middle of the vehicle. Lamp shapes are given in face coordinates
``(u, v)``: on the rear and front faces ``u`` = ``b`` (the vehicle's left is +u), on the side
faces ``u`` = ``a``; ``v`` is the height.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, FrozenSet, List, Optional, Sequence, Tuple

import numpy as np

from signal_light_node.errors import ConfigError

Colour = Tuple[float, float, float]

#: Emission colours (BGR, linear; the small blue/green parts turn a saturated core pink-white).
RED = (0.03, 0.07, 1.0)
AMBER = (0.0, 0.45, 1.0)
WHITE = (0.9, 0.95, 1.0)
#: Unlit lens albedos.
LENS = {"red": (0.04, 0.04, 0.30), "amber": (0.05, 0.25, 0.50), "clear": (0.32, 0.33, 0.35),
        "head": (0.42, 0.42, 0.44)}

KINDS = ("sedan", "hatch", "suv", "van", "truck")
CLASS_OF_KIND = {"sedan": "car", "hatch": "car", "suv": "car", "van": "car", "truck": "truck"}
REAR_DESIGNS = ("euro_amber", "us_red", "led_bar", "vertical")


@dataclass(frozen=True)
class Solid:
    """A convex hexahedron: a bottom rectangle and a (smaller) top rectangle.

    Attributes:
        bottom: ``(a0, a1, half_width, y)`` of the bottom rectangle.
        top: ``(a0, a1, half_width, y)`` of the top rectangle.
        part: "body", "cabin", "cargo" or "tyre"; cabins are glazed.
    """

    bottom: Tuple[float, float, float, float]
    top: Tuple[float, float, float, float]
    part: str

    def vertices(self) -> np.ndarray:
        """``[8, 3]`` vertices ``(a, b, y)``: bottom 0-3 then top 4-7."""
        out = []
        for a0, a1, hw, y in (self.bottom, self.top):
            out += [(a0, -hw, y), (a1, -hw, y), (a1, hw, y), (a0, hw, y)]
        return np.array(out, dtype=np.float64)


#: Faces of a solid by vertex indices (outward order fixed later by the centroid test).
FACES: Dict[str, Tuple[int, int, int, int]] = {
    "rear": (0, 3, 7, 4), "front": (1, 2, 6, 5), "left": (3, 2, 6, 7), "right": (0, 1, 5, 4),
    "top": (4, 5, 6, 7)}


@dataclass(frozen=True)
class Lamp:
    """One lens on a vehicle face.

    Attributes:
        face: "rear", "front", "left" or "right" of the main body (or of the cabin with
            ``on_cabin``).
        side: +1 the vehicle's left, -1 its right, 0 centre.
        funcs: Functions among "tail", "brake", "blink", "head", "drl".
        blink_colour: "amber" or "red" (for a lamp with "blink").
        lens: Unlit lens kind (key of ``LENS``).
        shape: ``[N, 2]`` polygon in face coordinates ``(u, v)``.
        on_cabin: Mounted on the cabin solid (centre brake lamp on the rear window).
        switchback: A DRL that turns amber and blinks while its side signals.
    """

    face: str
    side: int
    funcs: FrozenSet[str]
    blink_colour: str
    lens: str
    shape: np.ndarray
    on_cabin: bool = False
    switchback: bool = False


@dataclass
class VehicleModel:
    """Geometry, paint and lamps of one vehicle.

    Attributes:
        kind: One of ``KINDS``.
        length: Length (m).
        width: Width (m).
        solids: Solids to draw, tyres first.
        paint: Body albedo (BGR).
        lamps: All lenses.
        design: Rear lamp design name.
        drl: Has daytime running lights.
    """

    kind: str
    length: float
    width: float
    solids: List[Solid]
    paint: Colour
    lamps: List[Lamp] = field(default_factory=list)
    design: str = ""
    drl: bool = False


def _rect(uc: float, vc: float, w: float, h: float) -> np.ndarray:
    return np.array([(uc - w / 2, vc - h / 2), (uc + w / 2, vc - h / 2),
                     (uc + w / 2, vc + h / 2), (uc - w / 2, vc + h / 2)])


def _circle(uc: float, vc: float, r: float, n: int = 14) -> np.ndarray:
    t = np.linspace(0, 2 * math.pi, n, endpoint=False)
    return np.stack([uc + r * np.cos(t), vc + r * np.sin(t)], axis=1)


def _ell(uo: float, vc: float, w: float, h: float, s: int) -> np.ndarray:
    """An L-shaped cluster whose outer arm points up, mirrored by side ``s``."""
    pts = [(0, 0), (w, 0), (w, h), (w * 0.55, h), (w * 0.55, h * 0.45), (0, h * 0.45)]
    return np.array([(s * (uo - x), vc - h / 2 + y) for x, y in pts])


def _slant(uc: float, vc: float, w: float, h: float, s: int) -> np.ndarray:
    k = 0.35 * w * s
    return np.array([(uc - w / 2 + k, vc - h / 2), (uc + w / 2 + k, vc - h / 2),
                     (uc + w / 2, vc + h / 2), (uc - w / 2, vc + h / 2)])


_DIMS = {  # length, width, body top, cabin/roof height, clearance
    "sedan": (4.6, 1.80, 0.95, 1.45, 0.28), "hatch": (4.1, 1.75, 0.95, 1.50, 0.28),
    "suv": (4.75, 1.90, 1.08, 1.75, 0.38), "van": (5.2, 2.00, 1.00, 2.25, 0.35),
    "truck": (7.4, 2.40, 1.30, 3.10, 0.55)}


def _solids(kind: str, rng: np.random.Generator) -> Tuple[float, float, List[Solid], float]:
    """Tyres, body and cabin/cargo solids of a kind, with a little random variation."""
    length, width, top, roof, clear = _DIMS[kind]
    s = float(rng.uniform(0.94, 1.06))
    length, width, top, roof = length * s, width * (0.5 + 0.5 * s), top * s, roof * s
    la, hw = length / 2, width / 2
    solids: List[Solid] = []
    for a in (-0.32 * length, 0.32 * length):  # one full-width tyre slab per axle
        solids.append(Solid((a - 0.33, a + 0.33, hw - 0.02, 0.0),
                            (a - 0.33, a + 0.33, hw - 0.02, clear + 0.1), "tyre"))
    if kind == "truck":
        solids.append(Solid((la - 1.9, la, hw * 0.97, clear),
                            (la - 1.9, la - 0.05, hw * 0.97, top), "body"))
        solids.append(Solid((la - 1.9, la - 0.05, hw * 0.95, top),
                            (la - 1.7, la - 0.6, hw * 0.9, roof * 0.82), "cabin"))
        solids.append(Solid((-la, la - 2.0, hw, clear + 0.1), (-la, la - 2.0, hw, roof), "cargo"))
        return length, width, solids, top
    solids.append(Solid((-la, la, hw, clear), (-la + 0.05, la - 0.1, hw * 0.98, top), "body"))
    rear_in = {"sedan": 0.9, "hatch": 0.25, "suv": 0.15, "van": 0.08}[kind]
    front_in = {"sedan": 1.45, "hatch": 1.3, "suv": 1.2, "van": 0.55}[kind]
    slope = {"sedan": 0.45, "hatch": 0.2, "suv": 0.15, "van": 0.1}[kind]
    solids.append(Solid((-la + rear_in, la - front_in, hw * 0.93, top),
                        (-la + rear_in + slope, la - front_in - 0.75 * slope - 0.35, hw * 0.78,
                         roof),
                        "cabin"))
    return length, width, solids, top


def _rear_lamps(design: str, hw: float, top: float, kind: str) -> List[Lamp]:
    lamps: List[Lamp] = []
    tall = kind in ("suv", "van", "truck")
    v = top - 0.17 if kind != "truck" else 1.05
    for s in (1, -1):
        edge = hw - 0.05
        if design == "euro_amber":
            lamps.append(Lamp("rear", s, frozenset({"tail", "brake"}), "amber", "red",
                              _ell(edge, v, 0.42, 0.24, s)))
            lamps.append(Lamp("rear", s, frozenset({"blink"}), "amber", "amber",
                              _rect(s * (edge - 0.32), v - 0.18, 0.2, 0.09)))
        elif design == "us_red":
            lamps.append(Lamp("rear", s, frozenset({"tail", "brake", "blink"}), "red", "red",
                              _circle(s * (edge - 0.13), v, 0.12)))
            lamps.append(Lamp("rear", s, frozenset({"tail", "brake"}), "red", "red",
                              _circle(s * (edge - 0.40), v, 0.1)))
        elif design == "led_bar":
            lamps.append(Lamp("rear", s, frozenset({"tail", "brake"}), "amber", "red",
                              _slant(s * (edge - 0.2), v, 0.38, 0.13, s)))
            lamps.append(Lamp("rear", s, frozenset({"blink"}), "amber", "clear",
                              _rect(s * (edge - 0.2), v - 0.12, 0.36, 0.05)))
        else:  # vertical
            h = 0.55 if tall else 0.35
            lamps.append(Lamp("rear", s, frozenset({"tail", "brake"}), "amber", "red",
                              _rect(s * (edge - 0.07), v + h * 0.18, 0.13, h * 0.64)))
            lamps.append(Lamp("rear", s, frozenset({"blink"}), "amber", "amber",
                              _rect(s * (edge - 0.07), v - h * 0.33, 0.13, h * 0.3)))
    if design == "led_bar":
        lamps.append(Lamp("rear", 0, frozenset({"tail"}), "amber", "red",
                          _rect(0.0, v, 2 * hw - 0.9, 0.04)))
    return lamps


def _front_lamps(hw: float, top: float, kind: str, drl: bool, style: int) -> List[Lamp]:
    lamps: List[Lamp] = []
    v = top - 0.2 if kind != "truck" else 0.95
    for s in (1, -1):
        edge = hw - 0.06
        shape = (_slant(s * (edge - 0.2), v, 0.36, 0.13, -s) if style == 0
                 else _circle(s * (edge - 0.18), v, 0.1) if style == 1
                 else _rect(s * (edge - 0.2), v, 0.34, 0.14))
        lamps.append(Lamp("front", s, frozenset({"head"}), "amber", "head", shape))
        if drl and style != 1:
            lamps.append(Lamp("front", s, frozenset({"drl", "blink"}), "amber", "clear",
                              _rect(s * (edge - 0.2), v + 0.12, 0.34, 0.05), switchback=True))
        else:
            lamps.append(Lamp("front", s, frozenset({"blink"}), "amber", "amber",
                              _rect(s * (edge - 0.08), v - 0.15, 0.18, 0.1)))
    return lamps


def _side_lamps(length: float, top: float, design: str, kind: str) -> List[Lamp]:
    la = length / 2
    v = top - 0.17 if kind != "truck" else 1.05
    red_turn = design == "us_red"
    lamps: List[Lamp] = []
    for face, s in (("left", 1), ("right", -1)):
        # the side face's u is the a coordinate: rear corner at -la
        lamps.append(Lamp(face, s, frozenset({"tail"} | ({"blink"} if red_turn else set())),
                          "red", "red", _rect(-la + 0.17, v, 0.3, 0.16)))
        if not red_turn:
            lamps.append(Lamp(face, s, frozenset({"blink"}), "amber", "amber",
                              _rect(-la + 0.16, v - 0.15, 0.26, 0.08)))
        lamps.append(Lamp(face, s, frozenset({"blink"}), "amber", "amber",
                          _rect(la - 0.14, top - 0.22, 0.26, 0.1)))
        lamps.append(Lamp(face, s, frozenset({"blink"}), "amber", "amber",
                          _rect(la * 0.45, top - 0.08, 0.18, 0.07)))
    return lamps


def sample_vehicle(rng: np.random.Generator, kind: Optional[str] = None) -> VehicleModel:
    """A random vehicle model.

    Args:
        rng: Random source.
        kind: One of ``KINDS``, or None for a random one.

    Raises:
        ConfigError: Unknown kind.
    """
    if kind is None:
        kind = str(rng.choice(KINDS, p=[0.32, 0.2, 0.26, 0.14, 0.08]))
    if kind not in KINDS:
        raise ConfigError(f"unknown vehicle kind {kind!r}; expected one of {KINDS}")
    length, width, solids, top = _solids(kind, rng)
    design = str(rng.choice(REAR_DESIGNS, p=[0.34, 0.22, 0.24, 0.2]))
    drl = bool(rng.random() < 0.55)
    hue = rng.random()
    if hue < 0.45:  # greys, black, white
        g = float(rng.choice([0.04, 0.12, 0.3, 0.55, 0.75]))
        paint = (g * 1.02, g, g * 0.98)
    else:
        base = rng.uniform(0.05, 0.6, size=3)
        paint = tuple(float(x) for x in base)
    lamps = (_rear_lamps(design, width / 2, top, kind)
             + _front_lamps(width / 2, top, kind, drl, int(rng.integers(0, 3)))
             + _side_lamps(length, top, design, kind))
    if kind != "truck" and rng.random() < 0.8:  # centre high-mount brake lamp on the rear glass
        lamps.append(Lamp("rear", 0, frozenset({"brake"}), "amber", "red",
                          _rect(0.0, 0.0, 0.5, 0.05), on_cabin=True))
    return VehicleModel(kind, length, width, solids, paint, lamps, design, drl)


@dataclass
class Signals:
    """When a vehicle brakes and blinks.

    Attributes:
        blink: ``(t0, t1, mode)`` segments, mode "left", "right" or "hazard".
        brake: ``(t0, t1)`` braking episodes.
        freq: Flash frequency (Hz), 1.0..2.2.
        duty: Lit share of a flash period, 0.3..0.7.
        bulb: Incandescent lamps (slow rise and fall) rather than LEDs.
        lights_on: Tail and head lamps lit (always at night).
    """

    blink: List[Tuple[float, float, str]] = field(default_factory=list)
    brake: List[Tuple[float, float]] = field(default_factory=list)
    freq: float = 1.5
    duty: float = 0.5
    bulb: bool = False
    lights_on: bool = False

    def active(self, side: int, t: float) -> Optional[float]:
        """Start of the blink segment that makes ``side`` (+1 left, -1 right) active at ``t``."""
        want = "left" if side > 0 else "right"
        for t0, t1, mode in self.blink:
            if t0 <= t < t1 and mode in (want, "hazard"):
                return t0
        return None

    def braking(self, t: float) -> bool:
        """Whether the brake is applied at ``t``."""
        return any(t0 <= t < t1 for t0, t1 in self.brake)

    def flash_level(self, side: int, t: float, window: float) -> float:
        """Mean lit share of ``side``'s flasher over the exposure ``[t - window, t]``."""
        w = window + (0.06 if self.bulb else 0.0)
        acc = 0.0
        samples = np.linspace(t - w, t, 7)
        for ts in samples:
            t0 = self.active(side, float(ts))
            if t0 is not None and ((ts - t0) * self.freq) % 1.0 < self.duty:
                acc += 1.0
        return acc / len(samples)


def sample_signals(rng: np.random.Generator, duration: float, mode: str, night: bool,
                   allow: Sequence[str] = ("left", "right", "hazard"), brakes: bool = True
                   ) -> Signals:
    """Random signal timeline over ``[0, duration]``.

    Args:
        rng: Random source.
        duration: Scene length (s).
        mode: "none" (no signal at all), "quiet" (brakes only), "busy" (blinks and brakes).
        night: Lights always on at night.
        allow: Blink modes to draw from.
        brakes: Whether braking episodes may occur.

    Raises:
        ConfigError: Unknown mode.
    """
    if mode not in ("none", "quiet", "busy"):
        raise ConfigError(f"unknown signal mode {mode!r}")
    sig = Signals(freq=float(rng.uniform(1.0, 2.2)), duty=float(rng.uniform(0.3, 0.7)),
                  bulb=bool(rng.random() < 0.4), lights_on=night or bool(rng.random() < 0.3))
    if mode == "none":
        return sig
    t = float(rng.uniform(-2.0, 3.0))
    while mode == "busy" and t < duration:
        length = float(rng.uniform(2.5, 6.5))
        sig.blink.append((max(t, 0.0), t + length, str(rng.choice(list(allow)))))
        t += length + float(rng.uniform(1.5, 5.0))
    t = float(rng.uniform(-1.0, 4.0))
    while brakes and t < duration:
        length = float(rng.uniform(1.2, 4.0))
        sig.brake.append((max(t, 0.0), t + length))
        t += length + float(rng.uniform(1.5, 6.0))
    return sig


#: Outward normal of each face in the vehicle frame ``(a, b, y)``.
FACE_NORMALS: Dict[str, Tuple[float, float, float]] = {
    "rear": (-1.0, 0.0, 0.0), "front": (1.0, 0.0, 0.0), "left": (0.0, 1.0, 0.0),
    "right": (0.0, -1.0, 0.0)}


def lamp_points(model: VehicleModel, lamp: Lamp, eps: float = 0.015) -> np.ndarray:
    """The lamp polygon in the vehicle frame, ``[N, 3]`` as ``(a, b, y)``.

    Lamps sit ``eps`` proud of their face so that they are never hidden by it.

    Args:
        model: The vehicle.
        lamp: One of its lamps.
        eps: Offset from the face (m).

    Raises:
        ConfigError: A cabin lamp on a vehicle without a cabin, or an unknown face.
    """
    u, v = lamp.shape[:, 0], lamp.shape[:, 1]
    la, hw = model.length / 2, model.width / 2
    if lamp.on_cabin:
        cabins = [s for s in model.solids if s.part == "cabin"]
        if not cabins:
            raise ConfigError("a cabin lamp needs a vehicle with a cabin")
        (a0, _, _, y0), (a0t, _, _, y1) = cabins[-1].bottom, cabins[-1].top
        k = 0.85
        a = np.full_like(u, a0 + k * (a0t - a0) - eps)
        return np.stack([a, u, y0 + k * (y1 - y0) + v], axis=1)
    if lamp.face in ("rear", "front"):
        sign = -1.0 if lamp.face == "rear" else 1.0
        return np.stack([np.full_like(u, sign * (la + eps)), u, v], axis=1)
    if lamp.face in ("left", "right"):
        sign = 1.0 if lamp.face == "left" else -1.0
        return np.stack([u, np.full_like(u, sign * (hw + eps)), v], axis=1)
    raise ConfigError(f"unknown lamp face {lamp.face!r}")
