"""Drawing the vehicles of the evaluation generator into the radiance and id buffers: a
contact shadow, the solids' faces that look at the camera (gradient-shaded, cabins glazed
with a sky reflection and maybe a sun glint), then the lamps facing the camera: a dark
housing, the lens, its emission by the signals' state and, on a wet road, a stretched
reflection. What was drawn (``Drawn``) feeds the ground truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Tuple

import cv2
import numpy as np

from signal_light_node.evalgen.camera import NEAR_M, FrameView
from signal_light_node.evalgen.draw import Canvas, add_emission, add_glow, fill_gradient
from signal_light_node.evalgen.models import (AMBER, FACE_NORMALS, FACES, LENS, RED, WHITE, Lamp,
                                              Solid, VehicleModel, lamp_points)
from signal_light_node.evalgen.traffic import Actor
from signal_light_node.evalgen.world import Env, shade


@dataclass
class Drawn:
    """What drawing one vehicle produced, for the ground truth."""

    box: Tuple[float, float, float, float]
    hull_area: float
    lamps: List[Tuple[Lamp, np.ndarray, float]]  # (lamp, outline in pixels, cosine to the camera)


def to_world(pts: np.ndarray, x: float, z: float, yaw: float) -> np.ndarray:
    """Vehicle-frame ``(a, b, y)`` points to world ``(X, Y, Z)``."""
    a, b, y = pts[:, 0], pts[:, 1], pts[:, 2]
    s, c = math.sin(yaw), math.cos(yaw)
    return np.stack([x + a * s - b * c, y, z + a * c + b * s], axis=1)


class VehicleDrawer:
    """Draws the vehicles of one scene.

    Args:
        env: The scene's illumination.
        exposure_s: The sensor's exposure time (a flasher's lit share over it sets its level).
    """

    def __init__(self, env: Env, exposure_s: float) -> None:
        self.env = env
        self._exposure_s = exposure_s

    def draw(self, canvas: Canvas, actor: Actor, k: int, view: FrameView, t: float, obj_id: int
             ) -> Optional[Drawn]:
        """Shadow, solids and lamps of ``actor`` in frame ``k`` at time ``t``, seen through
        ``view``, with id ``obj_id`` in the id buffer; None when too near to draw."""
        x, z, yaw = float(actor.x[k]), float(actor.z[k]), float(actor.yaw[k])
        model = actor.model
        cam = view.position
        all_pts = np.concatenate([s.vertices() for s in model.solids])
        world = to_world(all_pts, x, z, yaw)
        uv, depth = view.project(world)
        if np.any(depth < NEAR_M + 1.0):
            return None
        la, hw = model.length / 2 + 0.25, model.width / 2 + 0.2
        footprint = np.array([(-la, -hw, 0.01), (la, -hw, 0.01), (la, hw, 0.01), (-la, hw, 0.01)])
        shadow = view.project(to_world(footprint, x, z, yaw))[0]
        black = (0.01, 0.01, 0.01)
        fill_gradient(canvas, shadow, black, black, alpha=0.6)
        for group in self._solid_groups(model, x, z, yaw, cam):
            for solid in group:
                self._solid(canvas, solid, actor, x, z, yaw, cam, view, obj_id)
        lamps = self._lamps(canvas, actor, x, z, yaw, cam, view, obj_id, t)
        hull = cv2.convexHull(uv.astype(np.float32))
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        box = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
        return Drawn(box, float(cv2.contourArea(hull)), lamps)

    def _solid_groups(self, model: VehicleModel, x: float, z: float, yaw: float,
                      cam: np.ndarray) -> List[List[Solid]]:
        """Solids in drawing order: tyres, then the cab/body and cargo groups far to near."""
        tyres = [s for s in model.solids if s.part == "tyre"]
        body = [s for s in model.solids if s.part not in ("cargo", "tyre")]
        cargo = [s for s in model.solids if s.part == "cargo"]

        def distance(group: List[Solid]) -> float:
            centre = np.mean([s.vertices().mean(axis=0) for s in group], axis=0)[None]
            return float(np.linalg.norm(to_world(centre, x, z, yaw)[0] - cam))

        return [tyres] + sorted([g for g in (body, cargo) if g], key=lambda g: -distance(g))

    def _solid(self, canvas: Canvas, solid: Solid, actor: Actor, x: float, z: float,
               yaw: float, cam: np.ndarray, view: FrameView, obj_id: int) -> None:
        """The faces of one solid that face the camera, gradient-shaded; cabins glazed."""
        verts = to_world(solid.vertices(), x, z, yaw)
        middle = verts.mean(axis=0)
        paint = np.asarray(actor.model.paint, np.float32)
        albedo = np.array([0.03, 0.03, 0.03]) if solid.part == "tyre" else paint
        if solid.part == "cargo":
            albedo = np.array([0.62, 0.62, 0.6])
        for name, idx in FACES.items():
            quad = verts[list(idx)]
            fc = quad.mean(axis=0)
            n = np.cross(quad[1] - quad[0], quad[3] - quad[0])
            n /= max(np.linalg.norm(n), 1e-9)
            if np.dot(n, fc - middle) < 0:
                n = -n
            to_cam = cam - fc
            if np.dot(n, to_cam) <= 0:
                continue
            dist = float(np.linalg.norm(to_cam))
            colour = shade(self.env, albedo, n, dist)
            uv = view.project(quad)[0]
            fill_gradient(canvas, uv, colour * 1.12, colour * 0.72, obj_id=obj_id)
            if solid.part == "cabin" and name != "top":
                self._glass(canvas, quad, fc, n, actor, view, obj_id)

    def _glass(self, canvas: Canvas, quad: np.ndarray, fc: np.ndarray, n: np.ndarray,
               actor: Actor, view: FrameView, obj_id: int) -> None:
        """The glazed inset of a cabin face: dark glass reflecting the sky, maybe a glint."""
        inner = fc + (quad - fc) * np.array([0.86, 0.8, 0.86])
        uv = view.project(inner)[0]
        sky = np.asarray(self.env.sky_horizon, np.float32)
        refl = 0.25 * sky * (0.5 + 0.5 * max(n[1], 0.0))
        dark = np.array([0.02, 0.02, 0.025], np.float32)
        fill_gradient(canvas, uv, dark + refl, dark + refl * 0.15, obj_id=obj_id)
        if not self.env.night and actor.glint:
            c = uv.mean(axis=0) + np.array([0.0, -0.25]) * np.ptp(uv[:, 1])
            r = max(np.ptp(uv[:, 0]) * 0.08, 1.0)
            add_glow(canvas, c, (r * 2.5, r * 0.6), (1.0, 1.0, 1.0), 0.5 * self.env.sun_level)

    def _lamps(self, canvas: Canvas, actor: Actor, x: float, z: float, yaw: float,
               cam: np.ndarray, view: FrameView, obj_id: int, t: float
               ) -> List[Tuple[Lamp, np.ndarray, float]]:
        """Housings, lenses and light of the lamps facing the camera; ``(lamp, uv, cos)``."""
        out = []
        model = actor.model
        for lamp in model.lamps:
            n_v = np.array(FACE_NORMALS[lamp.face])
            n = to_world(n_v[None], 0.0, 0.0, yaw)[0]
            pts = to_world(lamp_points(model, lamp), x, z, yaw)
            centre = pts.mean(axis=0)
            to_cam = cam - centre
            cos = float(np.dot(n, to_cam) / max(np.linalg.norm(to_cam), 1e-9))
            if cos <= 0.02:
                continue
            uv = view.project(pts)[0]
            housing = uv.mean(axis=0) + (uv - uv.mean(axis=0)) * 1.18
            fill_gradient(canvas, housing, (0.02, 0.02, 0.02), (0.01, 0.01, 0.01), obj_id=obj_id)
            lens = shade(self.env, np.asarray(LENS[lamp.lens]), n, float(np.linalg.norm(to_cam)))
            fill_gradient(canvas, uv, lens * 1.4, lens * 0.8, obj_id=obj_id)
            colour, level = self.lamp_emission(actor, lamp, t)
            if level > 0:
                add_emission(canvas, uv, colour, level * (0.35 + 0.65 * cos))
                if self.env.wet > 0.3 and level > 0.5:
                    self._reflection(canvas, pts, uv, colour, level * self.env.wet, view)
            out.append((lamp, uv, cos))
        return out

    def _reflection(self, canvas: Canvas, pts: np.ndarray, uv: np.ndarray,
                    colour: Tuple[float, float, float], level: float, view: FrameView) -> None:
        """A lamp's stretched reflection on the wet road below it."""
        mirrored = pts.mean(axis=0) * np.array([1.0, -1.0, 1.0])
        muv, depth = view.project(mirrored[None])
        if depth[0] < NEAR_M:
            return
        rx = max(np.ptp(uv[:, 0]) * 0.45, 1.0)
        add_glow(canvas, muv[0], (rx, rx * 4.0), colour, 0.08 * level)

    def lamp_emission(self, actor: Actor, lamp: Lamp, t: float
                      ) -> Tuple[Tuple[float, float, float], float]:
        """Colour and radiance of a lens at time ``t``."""
        sig, lv = actor.signals, actor.levels
        tail = lv["tail"] if sig.lights_on else 0.0
        braking = sig.braking(t)
        active = lamp.side != 0 and sig.active(lamp.side, t) is not None
        flash = sig.flash_level(lamp.side, t, self._exposure_s) if active else 0.0
        blink_colour = AMBER if lamp.blink_colour == "amber" else RED
        funcs = lamp.funcs
        if "head" in funcs:
            return WHITE, lv["head"] if sig.lights_on else 0.0
        if "drl" in funcs:
            if active:
                return AMBER, lv["blink"] * flash
            return WHITE, lv["drl"] if actor.model.drl else 0.0
        steady = max(tail if "tail" in funcs else 0.0,
                     lv["brake"] if ("brake" in funcs and braking) else 0.0)
        if "blink" in funcs and active:
            peak = max(lv["blink"], steady)
            if "tail" in funcs or "brake" in funcs:  # combined red lamp: flashes over the tail
                return RED, tail + (peak - tail) * flash
            return blink_colour, lv["blink"] * flash
        return RED, steady
