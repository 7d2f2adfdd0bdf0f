"""What the disparity refiner does to SGBM's disparity around crater rims, against the rendered
disparity: per-pixel errors in the refined regions, and a figure of example craters.

For each evaluated crater (D >= 4.5 m, not ignored) of a rendered stereo set, SGBM runs on the
geometry evaluation's band, the refiner (``--refiner``, default the shipped file) corrects the
regions around the boxes, and both are compared with the render's exact disparity where all
three are valid and SGBM is within 4 px (a larger miss is a wrong match): mean absolute error,
px, over the regions and over the pixels within 3 px of a depth step (the occluding rims). A
gated refiner's regions only (the boxes it corrects; ``n_refined_boxes`` in the output).
``--examples`` craters 15-20 m away, the smallest first, go into ``refiner_examples.png``: the
left crop, SGBM's and the refined error maps, and the disparity down the box's centre column.
Use development renders, never the evaluation set:

    .venv/bin/python benchmarks/refiner_study.py data/ss/dev_s2k0 --out outputs/refiner_study
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from lunarnav_ml.errors import REPORTED_ERRORS
from lunarnav_ml.geometry.lifter import rows_needed
from lunarnav_ml.geometry.refine import DisparityRefiner, refine_regions
from lunarnav_ml.geometry.report import read_gray
from lunarnav_ml.geometry.stereo import SGBMStereo
from lunarnav_ml.training.refiner import MAX_TARGET_PX, evaluated_craters
from lunarnav_ml.utils.atomic import write_figure, write_json
from lunarnav_ml.utils.images import read_disparity


def _edges(rendered: np.ndarray) -> np.ndarray:
    """Pixels within 3 px of a step of 5 % or more in the rendered disparity, down the rows."""
    d = np.nan_to_num(rendered)
    step = np.abs(np.diff(d, axis=0)) / np.maximum(d[1:], 1.0) > 0.05
    edge = np.zeros(d.shape, np.uint8)
    edge[1:] = step
    return cv2.dilate(edge, np.ones((7, 7), np.uint8)) > 0


def study(dataset: Path, refiner: DisparityRefiner, max_images: int | None) -> dict:
    ann_path, coco, by_image = evaluated_craters(dataset)
    images = [im for im in coco["images"] if by_image.get(im["id"])][:max_images]
    sums = {k: np.zeros(2) for k in ("sgbm", "refined", "sgbm_edge", "refined_edge")}
    examples = []
    n_boxes = n_refined = 0
    for k, im in enumerate(images):
        left = read_gray(ann_path.parent, im["file_name"])
        right = read_gray(ann_path.parent, im["right_file"])
        boxes = np.array([a["bbox"] for a in by_image[im["id"]]], float)
        band = rows_needed(boxes, left.shape[0])
        sgbm = SGBMStereo.for_width(left.shape[1])(left, right, band).disparity
        refined, gated = refiner.refine_boxes(left, right, sgbm, boxes)
        n_boxes, n_refined = n_boxes + len(boxes), n_refined + int(gated.sum())
        truth = read_disparity(ann_path.parent, im).astype(np.float32)
        inside = np.zeros(left.shape, bool)  # what the refiner corrected (its gate's boxes)
        for r0, r1, c0, c1 in refine_regions(boxes[gated], left.shape):
            inside[r0:r1, c0:c1] = True
        keep = inside & np.isfinite(sgbm) & (truth > 0) & (np.abs(sgbm - truth) < MAX_TARGET_PX)
        edge = keep & _edges(truth)
        for name, d in (("sgbm", sgbm), ("refined", refined)):
            err = np.abs(d - truth)
            sums[name] += (err[keep].sum(), keep.sum())
            sums[name + "_edge"] += (err[edge].sum(), edge.sum())
        for a, box, fixed in zip(by_image[im["id"]], boxes, gated, strict=True):
            if fixed and 15.0 <= a.get("near_rim_range_m", 0.0) <= 20.0:
                examples.append((a["diameter_m"], a["near_rim_range_m"], box, left, sgbm,
                                 refined, truth, im["id"]))
        if k % 32 == 0:
            print(f"{k + 1}/{len(images)} images", flush=True)
    out = {name: float(s[0] / max(s[1], 1)) for name, s in sums.items()}
    out.update(n_pixels=int(sums["sgbm"][1]), n_edge_pixels=int(sums["sgbm_edge"][1]),
               n_images=len(images), n_boxes=n_boxes, n_refined_boxes=n_refined,
               dataset=str(ann_path), refiner=str(refiner.path))
    return out, sorted(examples, key=lambda e: (e[0], e[1]))


def figure(examples: list, n: int):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    picks = examples[:: max(1, len(examples) // n)][:n]
    fig, axes = plt.subplots(len(picks), 4, figsize=(13, 2.6 * len(picks)), squeeze=False)
    for row, (diam, rng, box, left, sgbm, refined, truth, image_id) in zip(axes, picks,
                                                                             strict=True):
        x, y, w, h = box
        r0, r1 = max(int(y - 0.5 * h - 10), 0), min(int(y + 1.5 * h + 20), left.shape[0])
        c0, c1 = max(int(x - 0.25 * w - 10), 0), min(int(x + 1.25 * w + 10), left.shape[1])
        win = (slice(r0, r1), slice(c0, c1))
        row[0].imshow(left[win], cmap="gray", aspect="auto")
        row[0].set_title(f"image {image_id}: D {diam:.0f} m, near rim {rng:.1f} m", fontsize=8)
        for ax, d, name in ((row[1], sgbm, "SGBM"), (row[2], refined, "refined")):
            err = (d - truth)[win]
            ax.imshow(np.clip(err, -1, 1), cmap="coolwarm", vmin=-1, vmax=1, aspect="auto")
            ax.set_title(f"{name} - rendered (+-1 px)", fontsize=8)
        col = round(x + w / 2)
        rows = np.arange(r0, r1)
        for d, name, style in ((truth, "rendered", "k-"), (sgbm, "SGBM", "r-"),
                               (refined, "refined", "b-")):
            row[3].plot(rows, d[r0:r1, col], style, lw=1, label=name)
        row[3].set_title(f"disparity down column {col}, px", fontsize=8)
        row[3].legend(fontsize=7)
        for ax in row[:3]:
            ax.axis("off")
    fig.tight_layout()
    return fig


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset", type=Path, help="rendered stereo set (development renders)")
    p.add_argument("--refiner", type=Path, default=None, help="ONNX file (default: shipped)")
    p.add_argument("--max-images", type=int, default=None)
    p.add_argument("--examples", type=int, default=6)
    p.add_argument("--out", type=Path, default=Path("outputs/refiner_study"))
    args = p.parse_args(argv)
    try:
        metrics, examples = study(args.dataset, DisparityRefiner(args.refiner), args.max_images)
        write_json(args.out / "refiner_study.json", metrics)
        if examples and args.examples > 0:
            write_figure(args.out / "refiner_examples.png", figure(examples, args.examples))
    except REPORTED_ERRORS as err:
        print(f"refiner_study: error: {err}", file=sys.stderr)
        return 2
    print(f"mean |error| px in the refined regions: SGBM {metrics['sgbm']:.4f} -> refined "
          f"{metrics['refined']:.4f} ({metrics['n_pixels']} px); within 3 px of a depth step: "
          f"SGBM {metrics['sgbm_edge']:.4f} -> {metrics['refined_edge']:.4f} "
          f"({metrics['n_edge_pixels']} px) -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
