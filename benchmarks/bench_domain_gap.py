"""Domain-gap study, image-level part: which adaptations of real frames raise zero-shot
transfer of a synthetic-trained detector. Measured on a real validation split only.

    .venv/bin/python benchmarks/bench_domain_gap.py \\
        --gt data/real/chandai_v5/valid/annotations.json --checkpoint lunarnav_ml/weights/nano.pt

Each adaptation is applied to the RGB frame before the detector's own letterbox; the table
gives crater / rock recall at 5 detections per image (IoU >= 0.5) and crater AP50 (a lower
bound: the real labels are sparse).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from lunarnav_ml.errors import LunarNavError
from lunarnav_ml.eval.predict import predict_coco
from lunarnav_ml.realdata.transfer import transfer_metrics
from lunarnav_ml.training.api import load_detector


def _luma(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def _grey3(grey: np.ndarray) -> np.ndarray:
    return np.repeat(grey[:, :, None], 3, axis=2)


def grayscale(rgb: np.ndarray) -> np.ndarray:
    """Luma replicated to three channels (the synthetic renders are grey)."""
    return _grey3(_luma(rgb))


def clahe(rgb: np.ndarray) -> np.ndarray:
    """Grayscale, then contrast-limited adaptive histogram equalization (OpenCV)."""
    return _grey3(cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)).apply(_luma(rgb)))


def equalize(rgb: np.ndarray) -> np.ndarray:
    """Grayscale, then global histogram equalization (OpenCV)."""
    return _grey3(cv2.equalizeHist(_luma(rgb)))


def gamma_dark(rgb: np.ndarray) -> np.ndarray:
    """Grayscale, then gamma 1.8: darker mid-tones, closer to the renders' hard shadows."""
    table = (255.0 * (np.arange(256) / 255.0) ** 1.8).astype(np.uint8)
    return _grey3(cv2.LUT(_luma(rgb), table))


ADAPTATIONS: dict[str, Callable[[np.ndarray], np.ndarray] | None] = {
    "none": None, "grayscale": grayscale, "grayscale+CLAHE": clahe,
    "grayscale+equalize": equalize, "grayscale+gamma 1.8": gamma_dark,
}


class Adapted:
    """A predictor that adapts each image before the wrapped detector sees it."""

    def __init__(self, detector, adapt: Callable[[np.ndarray], np.ndarray] | None) -> None:
        self.detector, self.adapt = detector, adapt

    def predict(self, images, conf_thres=0.001, iou_thres=0.6):
        if self.adapt is not None:
            images = [self.adapt(image) for image in images]
        return self.detector.predict(images, conf_thres=conf_thres, iou_thres=iou_thres)


def adaptation_rows(detector, gt: dict, gt_dir: Path, names: list[str] | None = None
                    ) -> list[dict]:
    """Zero-shot crater / rock recall@5 and crater AP50 of ``detector`` per adaptation."""
    rows = []
    for name in names or list(ADAPTATIONS):
        results = predict_coco(Adapted(detector, ADAPTATIONS[name]), gt, gt_dir, progress=False)
        per_class = transfer_metrics(gt, results, budgets=(5,))["all"]["per_class"]
        rows.append({"adaptation": name, "crater_recall@5": per_class["crater"]["recall@5"],
                     "rock_recall@5": per_class["rock"]["recall@5"],
                     "crater_AP50": per_class["crater"]["AP50"]})
    return rows


def format_row(row: dict) -> str:
    return (f"| {row['adaptation']} | {row['crater_recall@5']:.3f} | {row['rock_recall@5']:.3f} | "
            f"{row['crater_AP50']:.3f} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gt", type=Path, required=True, help="real validation annotations.json")
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = ap.parse_args(argv)
    try:
        gt = json.loads(args.gt.read_text())
        detector = load_detector(args.checkpoint)
    except (LunarNavError, OSError, json.JSONDecodeError) as err:
        print(f"bench_domain_gap: error: {err}", file=sys.stderr)
        return 2
    print("| adaptation | crater recall@5 | rock recall@5 | crater AP50 (lower bound) |")
    print("|---|---|---|---|")
    rows = []
    for name in ADAPTATIONS:
        rows += adaptation_rows(detector, gt, args.gt.parent, [name])
        print(format_row(rows[-1]), flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
