"""Qualitative run on the other real frames in ``../shared/data/real/`` (issue 7): overlays and a
contact sheet per set, detections per image, and a coarse rock check against the Kaggle masks.

    .venv/bin/python benchmarks/qualitative_real.py --out outputs/qualitative_real \\
        [--weights lunarnav_ml/weights/small.pt] [--shared ../shared/data/real]

Sets (read in place, never copied):
- ``ce3_pcam_native``: two Chang'e 3 rover PCAM frames at the Kaggle resolution (777 x 571).
- ``ce3_kaggle_plots``: 28 Chang'e 3 PCAM / lander TCAM frames cropped from figures (423 x 310)
  with rock masks (green small rocks, blue large rocks; no crater class).
- ``apollo_surface``: two Apollo surface-photo crops (close-range regolith, reseau crosses).
- ``lro_nac_orbital``: eight LRO NAC orbital tiles near the Chang'e 4 site (nadir view: outside
  the domain the detector is trained for; shown so a user sees what it does there).

The rock check on ``ce3_kaggle_plots`` is coarse (masks resampled from plots, rocks touching each
other merge into one component): rock precision is the share of rock detections above the
overlay threshold whose box is at least 20 % rock pixels; large-rock recall is the share of
blue-mask components of >= 40 px whose centroid lies inside such a detection.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from lunarnav_ml.errors import LunarNavError
from lunarnav_ml.training.api import load_detector
from lunarnav_ml.training.cli import DEFAULT_WEIGHTS
from lunarnav_ml.training.detect import detect_files, list_images

SETS = {
    "ce3_pcam_native": "kaggle_realmoon_ce3_fragments/native",
    "ce3_kaggle_plots": "kaggle_realmoon_ce3_fragments/from_plots/images",
    "apollo_surface": "gazebo_apollo15_nac_dtm/apollo_textures",
    "lro_nac_orbital": "lro_nac_craters_ce4/test",
}
MASKS = {"ce3_kaggle_plots": "kaggle_realmoon_ce3_fragments/from_plots/masks"}
ROCK_ID = 2
MIN_ROCK_SHARE = 0.2
MIN_COMPONENT_PX = 40


def rock_masks(mask_bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(any rock, large rock) boolean masks of a Kaggle palette mask (BGR)."""
    b, g, r = (mask_bgr[..., i] > 127 for i in range(3))
    large = b & ~g & ~r
    small = g & ~b & ~r
    return large | small, large


def mask_check(images: list[dict], results: list[dict], mask_dir: Path, thres: float
               ) -> dict[str, float | int]:
    """Rock precision and large-rock recall of the detections against the Kaggle masks."""
    hits = n_dets = found = n_large = 0
    for img in images:
        mask_path = mask_dir / f"g_{Path(img['file_name']).name}"
        mask = cv2.imread(str(mask_path), cv2.IMREAD_COLOR)
        if mask is None:
            raise LunarNavError(f"{mask_path}: rock mask missing or unreadable")
        rock, large = rock_masks(mask)
        boxes = [r["bbox"] for r in results if r["image_id"] == img["id"]
                 and r["category_id"] == ROCK_ID and r["score"] >= thres]
        for x, y, w, h in boxes:
            x0, y0 = max(0, int(x)), max(0, int(y))
            x1, y1 = min(rock.shape[1], int(np.ceil(x + w))), min(rock.shape[0], int(np.ceil(y + h)))
            area = max(1, (x1 - x0) * (y1 - y0))
            hits += rock[y0:y1, x0:x1].sum() / area >= MIN_ROCK_SHARE
        n_dets += len(boxes)
        n, _, stats, centroids = cv2.connectedComponentsWithStats(large.astype(np.uint8))
        for k in range(1, n):
            if stats[k, cv2.CC_STAT_AREA] < MIN_COMPONENT_PX:
                continue
            n_large += 1
            cx, cy = centroids[k]
            found += any(x <= cx <= x + w and y <= cy <= y + h for x, y, w, h in boxes)
    return {"rock_detections": n_dets, "rock_precision": hits / n_dets if n_dets else float("nan"),
            "large_rocks": n_large, "large_rock_recall": found / n_large if n_large else float("nan")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("outputs/qualitative_real"))
    ap.add_argument("--weights", type=Path, default=DEFAULT_WEIGHTS)
    ap.add_argument("--shared", type=Path, default=Path(__file__).resolve().parents[2]
                    / "shared/data/real", help="the shared real-data folder")
    ap.add_argument("--overlay-conf", type=float, default=0.25)
    args = ap.parse_args(argv)
    try:
        detector = load_detector(args.weights)
        rows = []
        for name, rel in SETS.items():
            files = list_images(args.shared / rel)
            out = detect_files(detector, files, args.out / name, conf_thres=0.001, iou_thres=0.6,
                               overlay_thres=args.overlay_conf, progress=False, gallery=12)
            shown = Counter(detector.class_names[r["category_id"] - 1] for r in out["results"]
                            if r["score"] >= args.overlay_conf)
            row = {"set": name, "images": len(files),
                   **{f"{c}_per_image": shown[c] / len(files) for c in detector.class_names}}
            if name in MASKS:
                row.update(mask_check(out["images"], out["results"], args.shared / MASKS[name],
                                      args.overlay_conf))
            rows.append(row)
    except (LunarNavError, OSError) as err:
        print(f"qualitative_real: error: {err}", file=sys.stderr)
        return 2
    print(f"weights {args.weights}; detections drawn and counted at score >= {args.overlay_conf}")
    print("| set | images | craters / image | rocks / image | artifacts / image | contact sheet |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        print(f"| {row['set']} | {row['images']} | {row['crater_per_image']:.2f} | "
              f"{row['rock_per_image']:.2f} | {row['artifact_per_image']:.2f} | "
              f"{args.out / row['set'] / 'gallery.png'} |")
    for row in rows:
        if "rock_precision" in row:
            print(f"{row['set']} against the rock masks: rock precision {row['rock_precision']:.2f} "
                  f"({row['rock_detections']} rock detections), large-rock recall "
                  f"{row['large_rock_recall']:.2f} ({row['large_rocks']} large rocks)")
    (args.out / "summary.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
