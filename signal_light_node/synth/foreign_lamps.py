"""Lamps that are not the vehicle's own but fall inside its crop: the renderer's
``foreign_lamp`` hard negative.

On a real road the crop the node cuts around a vehicle holds more than its lamps: a red
lamp shows over a truck's roof (a vehicle beyond it braking, a traffic light), another
vehicle's blinker flashes just beside a car, head lamps glare next to a side view. The
second generator's night bag has such a truck, whose foreign red light the model reads as
its brake (docs/model.md, "The long members shipped with a bound on false night brakes?").

A vehicle picked by the share gets one :class:`ForeignLamp`, placed relative to its box
(over its roof, or beside it at lamp height) and moving with it, as a vehicle beyond at
the same speed would. It is drawn before the bodies, so every vehicle in front hides it,
and its glow goes onto the light layer like any lamp's. Its kinds (:data:`FOREIGN_KINDS`)
are what the vehicle's own lights are told from: a steady red lamp, a red lamp switched
on and off at random moments like a brake, an amber lamp flashing at a blinker's rate,
steady white head lamps. The truth does not change: the labels are the vehicle's own lamps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional, Tuple

import numpy as np

from signal_light_node.synth.environment import Lighting, add_glow, ellipse

#: What a foreign lamp looks like and does.
FOREIGN_KINDS = ("red_steady", "red_switching", "amber_blink", "white_steady")
#: BGR emission of each kind when lit.
_COLOUR = {"red_steady": (30.0, 25.0, 240.0), "red_switching": (30.0, 25.0, 240.0),
           "amber_blink": (20.0, 150.0, 255.0), "white_steady": (240.0, 245.0, 250.0)}
#: A blinker's legal rate (ECE R48: 90 +- 30 flashes a minute), and a brake's on/off spells.
BLINK_HZ = (1.0, 2.0)
SWITCH_SPELL_S = (0.8, 3.0)
#: How far the lamp sits over the roof (box heights above the top) or beside the box (box
#: widths from its centre), and its radius in box heights: small, as a lamp further away.
ABOVE_V = (-0.22, -0.03)
ABOVE_U = (-0.35, 0.35)
BESIDE_U = (0.47, 0.62)
BESIDE_V = (0.3, 0.7)
RADIUS = (0.03, 0.07)
#: Where a lamp beyond sits when it is drawn as a high one (``foreign_high``): over the
#: middle of the roof, just above it (inside a crop's 0.15 margin), as wide as a centre
#: high-mounted stop lamp, so only the vehicle's own lamps tell it from a brake.
HIGH_U = (-0.08, 0.08)
HIGH_V = (-0.09, -0.02)
HIGH_ASPECT = (2.0, 4.0)


@dataclass(frozen=True)
class ForeignLamp:
    """One lamp beyond a vehicle, in the vehicle's box coordinates.

    Attributes:
        kind: One of :data:`FOREIGN_KINDS`.
        u: Centre, in box widths from the box's centre (negative: to the image left).
        v: Centre, in box heights from the box's top (negative: above it).
        radius: Radius in box heights.
        level: Brightness when lit, 0..1 of the kind's emission.
        hz: Flash rate of ``amber_blink``.
        duty: Lit share of a flash period.
        phase: Offset of the flashes, or of the switching pattern, in seconds.
        spell_s: Length of each on or off spell of ``red_switching``.
        seed: Which spells of ``red_switching`` are on.
        aspect: Width over height of the lens (1: round).
    """

    kind: str
    u: float
    v: float
    radius: float
    level: float
    hz: float
    duty: float
    phase: float
    spell_s: float
    seed: int
    aspect: float = 1.0

    def lit(self, t: float) -> bool:
        """Whether the lamp is lit at scene time ``t`` seconds."""
        if self.kind == "amber_blink":
            return ((t + self.phase) * self.hz) % 1.0 < self.duty
        if self.kind == "red_switching":
            spell = int(math.floor((t + self.phase) / self.spell_s))
            return bool(np.random.default_rng([self.seed, spell]).random() < 0.5)
        return True


def sample_foreign_lamp(rng: np.random.Generator) -> ForeignLamp:
    """A foreign lamp drawn from ``rng``: kind, place (over the roof or beside), size,
    brightness and timing."""
    kind = FOREIGN_KINDS[int(rng.integers(len(FOREIGN_KINDS)))]
    if rng.random() < 0.6:
        u, v = float(rng.uniform(*ABOVE_U)), float(rng.uniform(*ABOVE_V))
    else:
        u = float(rng.uniform(*BESIDE_U) * (1.0 if rng.random() < 0.5 else -1.0))
        v = float(rng.uniform(*BESIDE_V))
    return ForeignLamp(kind=kind, u=u, v=v, radius=float(rng.uniform(*RADIUS)),
                       level=float(rng.uniform(0.6, 1.0)), hz=float(rng.uniform(*BLINK_HZ)),
                       duty=float(rng.uniform(0.4, 0.6)), phase=float(rng.uniform(0.0, 3.0)),
                       spell_s=float(rng.uniform(*SWITCH_SPELL_S)),
                       seed=int(rng.integers(0, 1 << 30)))


def high_foreign_lamp(lamp: ForeignLamp, rng: np.random.Generator) -> ForeignLamp:
    """``lamp`` moved to where a centre high-mounted stop lamp would be seen over the roof
    and drawn red, steady or switching like a brake; its level and timing are kept."""
    kind = "red_steady" if rng.random() < 0.5 else "red_switching"
    return replace(lamp, kind=kind, u=float(rng.uniform(*HIGH_U)), v=float(rng.uniform(*HIGH_V)),
                   aspect=float(rng.uniform(*HIGH_ASPECT)))


def lamp_centre(lamp: ForeignLamp, box: Tuple[float, float, float, float]
                ) -> Tuple[float, float, float]:
    """``(x, y, radius)`` of the lamp in image pixels for a vehicle box ``(x0, y0, x1, y1)``."""
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    return 0.5 * (x0 + x1) + lamp.u * w, y0 + lamp.v * h, max(0.7, lamp.radius * h)


def visible_share(x: float, y: float, r: float, coverage: np.ndarray) -> float:
    """The share of the disc ``(x, y, r)`` inside the image that ``coverage`` leaves free
    (``uint8 [H, W]``, non-zero where a body or an occluder stands: what
    ``truth.mark_visible`` leaves it holding); 1 where none of it is inside."""
    height, width = coverage.shape
    x0, y0 = max(int(math.floor(x - r)), 0), max(int(math.floor(y - r)), 0)
    x1, y1 = min(int(math.ceil(x + r)) + 1, width), min(int(math.ceil(y + r)) + 1, height)
    if x1 <= x0 or y1 <= y0:  # wholly outside the image: nothing there covers it
        return 1.0
    yy, xx = np.mgrid[y0:y1, x0:x1]
    disc = (xx + 0.5 - x) ** 2 + (yy + 0.5 - y) ** 2 <= r * r
    if not disc.any():
        return 1.0
    return float((coverage[y0:y1, x0:x1][disc] == 0).mean())


def draw_foreign_lamp(lamp: ForeignLamp, box: Tuple[float, float, float, float], t: float,
                      img: np.ndarray, layer: np.ndarray, light: Lighting,
                      coverage: Optional[np.ndarray] = None) -> None:
    """Draw the lamp for the vehicle box ``box`` at time ``t``: its lens into ``img`` (before
    the bodies are composited, which hide it) and, when lit, its glow onto ``layer`` in
    proportion to the share of it ``coverage`` leaves free (:func:`visible_share`; None:
    all of it), as no light of a lamp hidden behind a vehicle reaches the lens."""
    x, y, r = lamp_centre(lamp, box)
    height, width = img.shape[:2]
    if not (-4 * r < x < width + 4 * r and -4 * r < y < height + 4 * r):
        return
    emit = _COLOUR[lamp.kind]
    rx = r * lamp.aspect
    if not lamp.lit(t):
        ellipse(img, x, y, rx, r, tuple(0.2 * c * light.ambient for c in emit))
        return
    night = light.name != "day"
    k = min(1.0, lamp.level * light.lamp_gain * (1.25 if night else 1.0))
    ellipse(img, x, y, rx, r, tuple(k * c for c in emit))
    if night and k > 0.5:  # a bright lamp's centre clips towards white, as the own lamps'
        hot = 0.35 + 0.4 * k
        ellipse(img, x, y, 0.55 * rx, 0.55 * r, tuple(c + (255.0 - c) * hot for c in emit))
    seen = 1.0 if coverage is None else visible_share(x, y, r, coverage)
    if seen > 0:
        add_glow(layer, x, y, r, emit, 0.5 * k * light.glow * seen)
