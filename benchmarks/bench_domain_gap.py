"""Domain-gap study, image-level part: which adaptations of real frames raise zero-shot
transfer of a synthetic-trained detector. Measured on a real validation split only.

    .venv/bin/python benchmarks/bench_domain_gap.py \\
        --gt data/real/chandai_v5/valid/annotations.json --checkpoint lunarnav_ml/weights/nano.pt

Each adaptation is applied to the RGB frame before the detector's own letterbox; the table
gives crater / rock recall at 5 detections per image (IoU >= 0.5) and crater AP50 (a lower
bound: the real labels are sparse).

``--input-sizes 128 160 192 ...`` instead runs the detector as is at each network input side
(the frame is letterboxed to it) and plots the figures against it (``--plot``): a detector
trained on renders whose craters are smaller in the frame than a real camera's may find more
of them in a smaller input.
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
from lunarnav_ml.utils.atomic import write_figure, write_json


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


def size_rows(checkpoint: Path, gt: dict, gt_dir: Path, sizes: list[int]) -> list[dict]:
    """:func:`adaptation_rows` without adaptation, the detector run at each input side."""
    rows = []
    for size in sizes:
        row = adaptation_rows(load_detector(checkpoint, img_size=size), gt, gt_dir, ["none"])[0]
        rows.append({**row, "adaptation": f"input {size} px", "img_size": size})
        print(format_row(rows[-1]), flush=True)
    return rows


def plot_sizes(path: Path, rows: list[dict]) -> None:
    """Recall@5 and crater AP50 against the input side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = [r["img_size"] for r in rows]
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for key, style in (("crater_recall@5", "o-"), ("rock_recall@5", "s--"), ("crater_AP50", "^:")):
        ax.plot(sizes, [r[key] for r in rows], style, label=key.replace("_", " "))
    ax.set(xlabel="network input side (px)", ylabel="zero-shot figure on the real frames",
           xticks=sizes)
    ax.grid(alpha=0.3)
    ax.legend()
    write_figure(path, fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gt", type=Path, required=True, help="real validation annotations.json")
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    ap.add_argument("--input-sizes", type=int, nargs="+", default=None,
                    help="sweep the network input side (px, multiples of 32) instead")
    ap.add_argument("--plot", type=Path, default=None, help="(--input-sizes) figure to write")
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
    try:
        if args.input_sizes:
            rows = size_rows(args.checkpoint, gt, args.gt.parent, args.input_sizes)
            if args.plot:
                plot_sizes(args.plot, rows)
        else:
            for name in ADAPTATIONS:
                rows += adaptation_rows(detector, gt, args.gt.parent, [name])
                print(format_row(rows[-1]), flush=True)
    except (LunarNavError, OSError) as err:
        print(f"bench_domain_gap: error: {err}", file=sys.stderr)
        return 2
    if args.json:
        write_json(args.json, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
