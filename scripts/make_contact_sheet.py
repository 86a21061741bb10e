#!/usr/bin/env python3
"""Render a contact sheet of synthetic frames: day/dusk/night scenes, every view and every
lamp design, each tile captioned with its ground truth.

Usage: python scripts/make_contact_sheet.py [--out docs/synth_contact_sheet.png] [--seed 7]
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import List

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from signal_light_node.labels import Intent, View  # noqa: E402
from signal_light_node.synth import RenderedFrame, SceneRenderer, VehicleTruth  # noqa: E402
from signal_light_node.synth.lamps import LAMP_DESIGNS  # noqa: E402

LOG = logging.getLogger("make_contact_sheet")
TILE_W, TILE_H = 256, 144
CAPTION_H = 14
SHORT = {0: "OFF", 1: "ON", 2: "UNK"}


def caption(v: VehicleTruth) -> str:
    """Short label text: view, brake, left, right, intent."""
    return (f"{v.view.name[:2]} brk:{SHORT[int(v.brake)]} L:{SHORT[int(v.left)]} R:{SHORT[int(v.right)]} "
            f"{v.intent.name} {v.kind}/{v.lamp_design}")


def put_caption(tile: np.ndarray, text: str) -> np.ndarray:
    """Append a black caption strip under a tile."""
    strip = np.zeros((CAPTION_H, tile.shape[1], 3), np.uint8)
    cv2.putText(strip, text, (3, CAPTION_H - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.32, (235, 235, 235), 1, cv2.LINE_AA)
    return np.vstack([tile, strip])


def scene_tile(frame: RenderedFrame, title: str) -> np.ndarray:
    """A whole frame, downscaled, with boxes and short labels of the listed vehicles."""
    img = frame.image.copy()
    for v in frame.vehicles:
        x0, y0, x1, y1 = (int(round(c)) for c in v.box)
        cv2.rectangle(img, (x0, y0), (x1, y1), (60, 255, 60), 1)
        txt = f"{v.view.name[0]} b{SHORT[int(v.brake)][0]} {v.intent.name[:3]}"
        cv2.putText(img, txt, (x0 + 1, max(9, y0 - 2)), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (60, 255, 60), 1, cv2.LINE_AA)
    img = cv2.resize(img, (TILE_W, TILE_H), interpolation=cv2.INTER_AREA)
    return put_caption(img, title)


def vehicle_tile(frame: RenderedFrame, v: VehicleTruth) -> np.ndarray:
    """A crop around one vehicle (with context), resized to a tile."""
    x0, y0, x1, y1 = v.box
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    half_w = max((x1 - x0) * 0.8, (y1 - y0) * 0.8 * TILE_W / TILE_H)
    half_h = half_w * TILE_H / TILE_W
    H, W = frame.image.shape[:2]
    pad = int(max(half_w, half_h)) + 2
    big = cv2.copyMakeBorder(frame.image, pad, pad, pad, pad, cv2.BORDER_CONSTANT)
    a, b = int(cx - half_w) + pad, int(cy - half_h) + pad
    crop = big[b:b + int(2 * half_h), a:a + int(2 * half_w)]
    return put_caption(cv2.resize(crop, (TILE_W, TILE_H), interpolation=cv2.INTER_AREA), caption(v))


def find_frame(renderer: SceneRenderer, n: int, pick: int) -> RenderedFrame:
    """The ``pick``-th frame of a short sequence (so blinkers are caught in their lit half)."""
    frame = None
    for frame in renderer.frames(n):
        if frame.index == pick:
            break
    return frame


def build(seed: int) -> np.ndarray:
    rows: List[np.ndarray] = []
    rng = np.random.default_rng(seed)
    # Row block 1: whole scenes per lighting.
    for lighting in ("day", "dusk", "night"):
        tiles = []
        for k in range(4):
            s = int(rng.integers(0, 1 << 30))
            r = SceneRenderer(seed=s, lighting=lighting)
            f = find_frame(r, 30, int(rng.integers(5, 30)))
            tiles.append(scene_tile(f, f"{lighting} seed={s} fps={r.fps:.0f} n={len(f.vehicles)}"))
        rows.append(np.hstack(tiles))
    # Row block 2: one lamp design per row, one view per column, blinking/braking.
    intents = [Intent.LEFT, Intent.RIGHT, Intent.HAZARD]
    for i, design in enumerate(LAMP_DESIGNS):
        tiles = []
        for j, view in enumerate((View.BEHIND, View.FRONT, View.LEFT, View.RIGHT)):
            lighting = ("day", "dusk", "night")[(i + j) % 3]
            intent = intents[(i + j) % 3]
            s = int(rng.integers(0, 1 << 30))
            spec = dict(view=view, lamp_design=design, intent=intent, brake=bool((i + j) % 2), speed=0.0, phase=0.0,
                        width_px=float(rng.uniform(120, 220)) * (2.2 if view in (View.LEFT, View.RIGHT) else 1.0),
                        center_x=320.0 + float(rng.uniform(-60, 60)))
            r = SceneRenderer(seed=s, lighting=lighting, fps=20.0, vehicles=[spec], n_vehicles=2, poles=0, respawn=False)
            f = find_frame(r, 3, 2)  # 0.1 s after switch-on: the lit half
            target = [v for v in f.vehicles if v.view == view and v.lamp_design == design]
            tiles.append(vehicle_tile(f, target[0]) if target else scene_tile(f, f"{design} {view.name}: not visible"))
        rows.append(np.hstack(tiles))
    return np.vstack(rows)


def main(argv: List[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "synth_contact_sheet.png"))
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sheet = build(args.seed)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), sheet, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    LOG.info("wrote %s (%dx%d, %.0f kB)", out, sheet.shape[1], sheet.shape[0], out.stat().st_size / 1024)
    return 0


if __name__ == "__main__":
    sys.exit(main())
