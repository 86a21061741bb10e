"""The static world of the evaluation generator: its illumination (sun, sky, wet road),
the road with kerbs, markings and the cross street, building fronts with windows, and
poles (street lamps, signs, the traffic signal), drawn into the radiance buffer of one
frame through the camera's ``FrameView``. Facades and poles also go into the id buffer as
``OCCLUDER``, so that they hide the vehicles' lamps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np

from signal_light_node.evalgen.camera import NEAR_M, FrameView
from signal_light_node.evalgen.draw import Canvas, add_emission, add_glow, fill_gradient
from signal_light_node.evalgen.models import RED

#: Object id of static occluders (facades, poles) in the id buffer.
OCCLUDER = -2


@dataclass
class Env:
    """Illumination of the scene."""

    night: bool
    sun: np.ndarray
    sun_level: float
    sky_level: float
    wet: float
    sky_top: Tuple[float, float, float]
    sky_horizon: Tuple[float, float, float]
    asphalt: Tuple[float, float, float]


def sample_env(rng: np.random.Generator, night: bool) -> Env:
    """Sun, sky, road wetness and colours of a day or night scene."""
    az = rng.uniform(-1.2, 1.2)
    el = rng.uniform(0.35, 1.0)
    sun = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
    if night:
        return Env(True, sun, 0.0, float(rng.uniform(0.004, 0.008)), float(rng.uniform(0.0, 1.0)),
                    (0.003, 0.0015, 0.001), (0.012, 0.01, 0.009), (0.009, 0.009, 0.01))
    haze = float(rng.uniform(0.0, 0.3))
    return Env(False, sun, float(rng.uniform(0.7, 1.0)), float(rng.uniform(0.35, 0.5)), 0.0,
                (0.75 - 0.3 * haze, 0.45, 0.25 + 0.2 * haze), (0.85, 0.8, 0.72),
                tuple(float(c) for c in rng.uniform(0.16, 0.26) * np.array([1.0, 1.0, 0.97])))


def shade(env: Env, albedo: np.ndarray, normal: np.ndarray, depth: float) -> np.ndarray:
    """Radiance of a surface: sky and sun by day; low beams and street light by night."""
    sky = env.sky_level * (0.55 + 0.45 * max(normal[1], 0.0))
    sun = env.sun_level * max(float(np.dot(normal, env.sun)), 0.0)
    light = sky + sun
    if env.night:  # the ego car's low beams on nearby rear faces, street lamps
        light += 0.05 * min(1.0, (12.0 / max(depth, 1.0)) ** 2) * max(-normal[2], 0.0) + 0.004
    return np.asarray(albedo, np.float32) * np.float32(light)


def upright_rect(x: float, z: float, half: float, y0: float, y1: float) -> np.ndarray:
    """A vertical rectangle facing the camera (constant ``z``), ``[4, 3]`` world points."""
    return np.array([(x - half, y0, z), (x + half, y0, z), (x + half, y1, z), (x - half, y1, z)])


def sample_facades(rng: np.random.Generator, ego_z0: float, z_int: Optional[float]) -> List[Dict]:
    """Building fronts along both sides of the road ahead of ``ego_z0``, with a gap for the
    cross street at ``z_int``."""
    out = []
    for x in (10.5, -13.5):
        z = float(ego_z0 - 20.0)
        while z < ego_z0 + 260.0:
            length = float(rng.uniform(12.0, 40.0))
            z0, z1 = z, z + length
            if z_int is not None and z0 < z_int + 7.0 and z1 > z_int - 7.0:
                z = z_int + 7.0
                continue
            albedo = rng.uniform(0.15, 0.55) * rng.uniform(0.8, 1.1, size=3)
            lit = rng.random(200) < 0.3
            out.append({"x": x, "z0": z0, "z1": z1, "h": float(rng.uniform(7.0, 24.0)),
                        "albedo": albedo, "lit": lit, "warm": rng.uniform(0.3, 0.9, size=200)})
            z = z1 + float(rng.uniform(0.0, 4.0))
    return out


def sample_poles(rng: np.random.Generator, ego_z0: float, z_int: Optional[float]) -> List[Dict]:
    """Street lamps and sign posts ahead of ``ego_z0``, and the traffic signal at the
    intersection ``z_int``."""
    out = []
    for x, arm in ((7.7, -1.8), (-9.4, 1.8)):
        z = float(ego_z0 + rng.uniform(4.0, 20.0))
        while z < ego_z0 + 220.0:
            if z_int is None or abs(z - z_int) > 8.0:
                out.append({"x": x, "z": z, "arm": arm, "sign": bool(rng.random() < 0.3),
                            "sodium": bool(rng.random() < 0.5), "signal": False})
            z += float(rng.uniform(22.0, 34.0))
    if z_int is not None:
        out.append({"x": 7.7, "z": z_int - 7.5, "arm": 0.0, "sign": False, "sodium": False,
                    "signal": True})
    return out


class Street:
    """Draws the static world of one scene.

    Args:
        env: The scene's illumination.
        z_int: Position of the intersection's centre, None on a road without one.
        two_way: Whether the road has oncoming lanes (double yellow line, fewer dashes).
        poles: The scene's poles (their lamps light pools on the road at night).
    """

    def __init__(self, env: Env, z_int: Optional[float], two_way: bool, poles: List[Dict]) -> None:
        self.env = env
        self.z_int = z_int
        self.two_way = two_way
        self.poles = poles

    def _ground_poly(self, view: FrameView, x0: float, x1: float, z0: float, z1: float,
                     y: float = 0.0) -> Optional[np.ndarray]:
        """A strip of ground ``x0..x1`` by ``z0..z1`` in pixels, or None if behind the camera."""
        ez = view.ego_z
        z0, z1 = max(z0, ez + 1.0), min(z1, ez + 900.0)
        if z1 <= z0:
            return None
        zs = np.linspace(z0, z1, 6)
        pts = np.array([(x0, y, z) for z in zs] + [(x1, y, z) for z in zs[::-1]])
        uv, depth = view.project(pts)
        return uv if np.all(depth > NEAR_M) else None

    def background(self, canvas: Canvas, view: FrameView) -> None:
        """Sky, ground, kerbs, road, cross street, markings and light pools."""
        env = self.env
        far_point = np.array([[0.0, view.camera.mount_height, view.ego_z + 1e5]])
        horizon = view.project(far_point)[0][0, 1]
        rows = np.clip(np.arange(canvas.height, dtype=np.float32) / max(horizon, 1.0), 0.0, 1.0)
        top, hor = np.asarray(env.sky_top, np.float32), np.asarray(env.sky_horizon, np.float32)
        canvas.rgb[:] = (top * (1 - rows[:, None]) + hor * rows[:, None])[:, None, :]
        far = 900.0 + view.ego_z
        dim = 1.0 if not env.night else 0.08
        grass = np.array([0.12, 0.2, 0.18]) * dim
        kerb_r, kerb_l = np.array([0.38, 0.39, 0.4]) * dim, np.array([0.36, 0.37, 0.38]) * dim
        for x0, x1, z0, z1, colour in ((-400.0, 400.0, 0.0, far, grass),
                                       (7.0, 10.5, 0.0, far, kerb_r),
                                       (-13.5, -8.75, 0.0, far, kerb_l),
                                       (-8.75, 7.0, 0.0, far, np.asarray(env.asphalt))):
            poly = self._ground_poly(view, x0, x1, z0, z1)
            if poly is not None:
                near = np.asarray(colour, np.float32)
                fill_gradient(canvas, poly, near * 0.9 + hor * 0.1, near * 0.8)
        if self.z_int is not None:
            poly = self._ground_poly(view, -400.0, 400.0, self.z_int - 6.0, self.z_int + 6.0)
            if poly is not None:
                a = np.asarray(env.asphalt, np.float32)
                fill_gradient(canvas, poly, a, a)
        self._markings(canvas, view)
        if env.night:
            self._light_pools(canvas, view)

    def _markings(self, canvas: Canvas, view: FrameView) -> None:
        """Lane lines (solid, dashed, double yellow) and the stop line."""
        bright = 0.7 if not self.env.night else 0.12
        white = (bright, bright, bright)
        yellow = (0.05, bright * 0.7, bright * 0.9)
        ez = view.ego_z
        stop = self.z_int - 7.0 if self.z_int is not None else np.inf
        solid = [(5.25, white), (-8.6, white)] + ([(-1.65, yellow), (-1.85, yellow)]
                                                  if self.two_way else [])
        for x, colour in solid:
            poly = self._ground_poly(view, x - 0.07, x + 0.07, ez, min(stop, ez + 400.0))
            if poly is not None:
                fill_gradient(canvas, poly, colour, colour)
        dashed = [1.75, -5.25] if self.two_way else [1.75, -1.75, -5.25]
        first = math.floor(ez / 9.0) * 9.0
        for x in dashed:
            for z in np.arange(first, min(ez + 130.0, stop), 9.0):
                poly = self._ground_poly(view, x - 0.07, x + 0.07, z, z + 3.0)
                if poly is not None:
                    fill_gradient(canvas, poly, white, white)
        if self.z_int is not None:
            poly = self._ground_poly(view, -1.6, 5.2, stop, stop + 0.5)
            if poly is not None:
                fill_gradient(canvas, poly, white, white)

    def _light_pools(self, canvas: Canvas, view: FrameView) -> None:
        """Pools of street light on the road at night."""
        for pole in self.poles:
            if pole["signal"]:
                continue
            x = pole["x"] + pole["arm"]
            uv, depth = view.project(np.array([[x, 0.0, pole["z"]]]))
            if depth[0] < 2.0 or depth[0] > 150.0:
                continue
            f = view.camera.focal
            colour = (0.25, 0.6, 1.0) if pole["sodium"] else (0.9, 0.95, 1.0)
            add_glow(canvas, uv[0], (f * 4.0 / depth[0], f * 1.2 / depth[0]), colour, 0.03)

    def facade(self, canvas: Canvas, fac: Dict, view: FrameView) -> None:
        """One building front with its windows (lit at random by night)."""
        x, h = fac["x"], fac["h"]
        z0, z1 = max(fac["z0"], view.ego_z + 1.0), fac["z1"]
        if z1 <= z0:
            return
        pts = np.array([(x, 0.0, z0), (x, 0.0, z1), (x, h, z1), (x, h, z0)])
        uv, depth = view.project(pts)
        if np.any(depth < NEAR_M):
            return
        normal = np.array([-math.copysign(1.0, x), 0.0, 0.0])
        c = shade(self.env, fac["albedo"], normal, 50.0)
        fill_gradient(canvas, uv, c * 1.05, c * 0.8, obj_id=OCCLUDER)
        nearest = float(depth.min())
        if nearest > 120.0:
            return
        glass = np.array([0.08, 0.07, 0.06]) * (1.0 if not self.env.night else 0.2)
        i = 0
        for floor_y in np.arange(3.0, h - 1.5, 3.2):
            for wz in np.arange(fac["z0"] + 1.5, fac["z1"] - 1.5, 3.0):
                i += 1
                if wz < view.ego_z + 2.0:
                    continue
                wp = np.array([(x, floor_y, wz), (x, floor_y, wz + 1.4),
                               (x, floor_y + 1.5, wz + 1.4), (x, floor_y + 1.5, wz)])
                wuv, wd = view.project(wp)
                if np.any(wd < NEAR_M) or np.ptp(wuv[:, 0]) < 1.5:
                    continue
                sky = np.asarray(self.env.sky_horizon, np.float32) * 0.5
                fill_gradient(canvas, wuv, glass + sky, glass, obj_id=OCCLUDER)
                if self.env.night and fac["lit"][i % 200]:
                    warm = 0.2 * float(fac["warm"][i % 200])
                    add_emission(canvas, wuv, (0.35, 0.65, 1.0), warm, core=0.8)

    def pole(self, canvas: Canvas, pole: Dict, view: FrameView) -> None:
        """A pole with its arm, sign, lamp head or traffic signal."""
        x, z = pole["x"], pole["z"]
        height = 6.0 if pole["signal"] else 7.5
        w = 0.09
        grey = np.array([0.25, 0.25, 0.26]) * (1.0 if not self.env.night else 0.05)
        pts = np.array([(x - w, 0.0, z), (x + w, 0.0, z), (x + w, height, z), (x - w, height, z)])
        uv, depth = view.project(pts)
        if np.any(depth < 1.5):
            return
        fill_gradient(canvas, uv, grey * 1.2, grey * 0.7, obj_id=OCCLUDER)
        ax = x + pole["arm"]
        if pole["arm"]:
            arm = np.array([(min(x, ax), height - 0.1, z), (max(x, ax), height - 0.1, z),
                            (max(x, ax), height, z), (min(x, ax), height, z)])
            fill_gradient(canvas, view.project(arm)[0], grey, grey, obj_id=OCCLUDER)
        if pole["sign"]:
            sp = upright_rect(x, z - 0.02, 0.45, 2.3, 3.0)
            blue = np.array([0.55, 0.25, 0.05]) * (1.0 if not self.env.night else 0.15)
            fill_gradient(canvas, view.project(sp)[0], blue, blue * 0.8, obj_id=OCCLUDER)
        if pole["signal"]:
            box = upright_rect(x, z - 0.05, 0.18, 4.6, 5.6)
            buv = view.project(box)[0]
            fill_gradient(canvas, buv, (0.03, 0.03, 0.03), (0.02, 0.02, 0.02), obj_id=OCCLUDER)
            t = np.linspace(0, 2 * math.pi, 12, endpoint=False)
            lens = np.stack([x + 0.11 * np.cos(t), 5.38 + 0.11 * np.sin(t),
                             np.full(12, z - 0.07)], axis=1)
            add_emission(canvas, view.project(lens)[0], RED, 6.0 if self.env.night else 2.5)
        elif self.env.night:
            t = np.linspace(0, 2 * math.pi, 10, endpoint=False)
            head = np.stack([ax + 0.35 * np.cos(t), height - 0.15 + 0.08 * np.sin(t),
                             np.full(10, z)], axis=1)
            colour = (0.25, 0.6, 1.0) if pole["sodium"] else (0.9, 0.95, 1.0)
            add_emission(canvas, view.project(head)[0], colour, 5.0)
