"""A labelled gallery of example scenes across sun angles, for people to look at."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from lunarnav_ml.synth.config import SynthConfig
from lunarnav_ml.synth.generate import item_seed
from lunarnav_ml.synth.pipeline import render_item
from lunarnav_ml.synth.scene import sample_scene
from lunarnav_ml.utils import atomic

# (sun zenith, sun azimuth) per tile, deg
SUN_GRID = ((0.0, 0.0), (30.0, 90.0), (50.0, 45.0), (60.0, 180.0),
            (70.0, 270.0), (80.0, 90.0), (85.0, 0.0), (75.0, 135.0))
COLORS = {1: (60, 220, 60), 2: (0, 160, 255), 3: (60, 60, 255)}  # BGR per category
IGNORED = (130, 130, 130)


def draw_labels(gray: np.ndarray, annotations: list[dict[str, Any]]) -> np.ndarray:
    """BGR copy of ``gray`` (H, W) with boxes (ignored ones grey) and crater rim ellipses."""
    img = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    for a in sorted(annotations, key=lambda a: not a["ignore"]):
        if a["ignore"] and a["category_id"] != 1:
            continue
        color = IGNORED if a["ignore"] else COLORS[a["category_id"]]
        x, y, w, h = a["bbox"]
        cv2.rectangle(img, (int(x), int(y)), (int(np.ceil(x + w)) - 1, int(np.ceil(y + h)) - 1),
                      color, 1)
        if a["category_id"] == 1 and not a["ignore"]:
            cx, cy, ea, eb, ang = a["ellipse"]
            cv2.ellipse(img, ((cx, cy), (2 * ea, 2 * eb), ang), (0, 255, 255), 1)
    return img


def write_gallery(path: str | Path, *, config: SynthConfig | None = None, seed: int = 0,
                  image_size: int = 384, columns: int = 4) -> Path:
    """Render one scene per SUN_GRID entry, draw its labels, tile them into one PNG.

    Scene i uses the same random draws as dataset item i of ``seed`` except for the sun.
    Legend: green crater boxes with yellow rim ellipses, orange rocks, red artifacts,
    grey ignored craters; each tile is captioned with its sun zenith / azimuth.
    """
    cfg = config if config is not None else SynthConfig()
    tiles = []
    for i, (zen, az) in enumerate(SUN_GRID):
        spec = sample_scene(cfg, item_seed(seed, i))
        spec = dataclasses.replace(spec, sun_zenith_deg=zen, sun_azimuth_deg=az)
        out = render_item(spec, cfg, image_size, stereo=False)
        tile = draw_labels(out.left, out.annotations)
        cv2.putText(tile, f"sun zenith {zen:.0f}  azimuth {az:.0f}", (6, 18),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    rows = [np.hstack(tiles[r: r + columns]) for r in range(0, len(tiles), columns)]
    return atomic.write_image(path, np.vstack(rows))
