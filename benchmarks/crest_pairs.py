"""The same craters rendered twice, side by side: crops of two datasets rendered with the same
seeds (e.g. without and with ``craters.crest_at_rim``), each with its crater's label box.

Craters are chosen from the first dataset (countable, at least ``--min-degradation``,
``--min-diameter`` and within ``--max-near-range``; most degraded first) and found in the second
by image file name, diameter and degradation. Each pair is two tiles, first dataset left, cut
around the label box with a margin of half its width and drawn with the box in green.

    python benchmarks/crest_pairs.py data/d7/val300/annotations.json \\
        data/d8/val300/annotations.json --out outputs/crest_pairs.png
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from lunarnav_ml.data.coco import read_coco
from lunarnav_ml.errors import REPORTED_ERRORS, InputError
from lunarnav_ml.utils import atomic
from lunarnav_ml.utils.images import caption_tile, contact_sheet, read_rgb

TILE = 256


def craters_by_image(data: dict[str, Any]) -> dict[str, list[dict[str, Any]]]:
    """Crater annotations (category 1) per image file name."""
    names = {img["id"]: img["file_name"] for img in data["images"]}
    out: dict[str, list[dict[str, Any]]] = {}
    for ann in data["annotations"]:
        if ann["category_id"] == 1:
            out.setdefault(names[ann["image_id"]], []).append(ann)
    return out


def select(data: dict[str, Any], min_degradation: float, min_diameter: float,
           max_near: float) -> list[tuple[str, dict[str, Any]]]:
    """(file name, annotation) of the countable craters that pass the filters, most degraded
    first (then largest)."""
    rows = []
    for name, anns in craters_by_image(data).items():
        for ann in anns:
            if "degradation" not in ann or "diameter_m" not in ann:
                raise InputError(f"annotation {ann.get('id')} of {name}: no 'degradation' or "
                                 "'diameter_m' (a lunarnav synth dataset is needed)")
            if (not ann.get("ignore") and ann["degradation"] >= min_degradation
                    and ann["diameter_m"] >= min_diameter
                    and ann.get("near_rim_range_m", 0.0) <= max_near):
                rows.append((name, ann))
    rows.sort(key=lambda r: (-r[1]["degradation"], -r[1]["diameter_m"]))
    return rows


def match(ann: dict[str, Any], others: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The crater of ``others`` with the same diameter and degradation, nearest in centre."""
    same = [o for o in others if abs(o["diameter_m"] - ann["diameter_m"]) < 1e-3
            and abs(o["degradation"] - ann["degradation"]) < 1e-3]
    if not same:
        return None
    c = np.asarray(ann["center_cam_m"], float)
    return min(same, key=lambda o: float(np.linalg.norm(np.asarray(o["center_cam_m"]) - c)))


def crop(image: np.ndarray, box: list[float]) -> np.ndarray:
    """The label box with a margin of half its width on every side, box drawn in green."""
    x, y, w, h = box
    m = 0.5 * max(w, h)
    x0, y0 = max(0, int(x - m)), max(0, int(y - m))
    x1, y1 = min(image.shape[1], int(np.ceil(x + w + m))), min(image.shape[0],
                                                              int(np.ceil(y + h + m)))
    out = np.ascontiguousarray(image[y0:y1, x0:x1, ::-1])  # RGB -> BGR for OpenCV drawing
    cv2.rectangle(out, (round(x - x0), round(y - y0)), (round(x + w - x0), round(y + h - y0)),
                  (0, 255, 0), 1)
    return out


def crest_pairs(first: str | Path, second: str | Path, out: str | Path, n: int,
                min_degradation: float, min_diameter: float, max_near: float,
                labels: tuple[str, str]) -> int:
    """Write the contact sheet of up to ``n`` pairs; returns the number of pairs drawn."""
    atomic.check_image_destination(out)
    paths = [Path(first), Path(second)]
    data = [read_coco(p)[0] for p in paths]
    rows = select(data[0], min_degradation, min_diameter, max_near)
    if not rows:
        raise InputError(f"{first}: no countable crater passes the filters")
    second_by_image = craters_by_image(data[1])
    read = functools.lru_cache(maxsize=8)(read_rgb)  # several craters may share a frame
    tiles = []
    for name, ann in rows:
        twin = match(ann, second_by_image.get(name, []))
        if twin is None:
            continue
        for root, a, label in zip(paths, (ann, twin), labels):
            image = read(root.parent / name)
            caption = (f"{label} D {a['diameter_m']:.1f} m deg {a['degradation']:.2f} "
                       f"near {a['near_rim_range_m']:.0f} m")
            tiles.append(caption_tile(crop(image, a["bbox"]), TILE, caption))
        if len(tiles) == 2 * n:
            break
    if not tiles:
        raise InputError(f"{second}: none of the chosen craters is in it (rendered with "
                         "other seeds?)")
    atomic.write_image(out, contact_sheet(tiles, cols=4))
    return len(tiles) // 2


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("first", help="annotations.json of the first render (left tiles)")
    ap.add_argument("second", help="annotations.json of the second render, same seeds")
    ap.add_argument("--out", default="outputs/crest_pairs.png", help="the PNG to write")
    ap.add_argument("--n", type=int, default=12, help="pairs to draw")
    ap.add_argument("--min-degradation", type=float, default=0.5)
    ap.add_argument("--min-diameter", type=float, default=5.0, help="m")
    ap.add_argument("--max-near-range", type=float, default=20.0, help="near rim, m")
    ap.add_argument("--labels", nargs=2, default=["old", "crest"], help="tile captions")
    args = ap.parse_args(argv)
    try:
        if args.n < 1:
            raise InputError(f"--n must be at least 1, got {args.n}")
        drawn = crest_pairs(args.first, args.second, args.out, args.n, args.min_degradation,
                            args.min_diameter, args.max_near_range, tuple(args.labels))
    except REPORTED_ERRORS as err:
        print(f"crest_pairs: error: {err}", file=sys.stderr)
        return 2
    print(f"{drawn} pairs -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
