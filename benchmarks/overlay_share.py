"""What an overlay threshold draws: the share of labelled craters it keeps, and boxes per frame.

For each labelled crater (not ignored) the best crater detection at IoU >= 0.5 is found in a
COCO results file (e.g. the ``detections.json`` of ``lunarnav eval --task transfer``); a
threshold keeps the crater when that detection's score reaches it. Prints one line per
threshold: the share of craters kept and the crater boxes per frame at or above it (the
figures of docs/realdata.md on `lunarnav detect --overlay-conf`).

    python benchmarks/overlay_share.py --gt data/real/chandai_v5/valid/annotations.json \
        --detections outputs/real/detections.json --conf 0.25 0.1
"""
from __future__ import annotations

import argparse
import sys

import numpy as np
from pd_diagnosis import CRATER, crater_scores

from lunarnav_ml.data.coco import read_coco
from lunarnav_ml.errors import LunarNavError
from lunarnav_ml.eval.predict import check_coco_results
from lunarnav_ml.utils.jsonfile import read_json_file


def best_scores(gt: dict, dets: list[dict]) -> np.ndarray:
    """Per countable labelled crater: the best score among its IoU >= 0.5 crater detections,
    or 0 (:func:`pd_diagnosis.crater_scores`)."""
    return np.asarray([row[2] for row in crater_scores(gt, dets)], dtype=float)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gt", required=True, help="COCO annotations")
    ap.add_argument("--detections", required=True, help="COCO results JSON")
    ap.add_argument("--conf", type=float, nargs="+", default=[0.25, 0.1])
    args = ap.parse_args(argv)
    try:  # the labels and the results checked as the evaluations check them
        gt = read_coco(args.gt, check_files=False)[0]
        dets = check_coco_results(read_json_file(args.detections, "detections"), args.detections)
    except LunarNavError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    best = best_scores(gt, dets)
    scores = [d["score"] for d in dets if d["category_id"] == CRATER]
    n_images = len(gt["images"])
    for t in args.conf:
        boxes = sum(s >= t for s in scores) / n_images  # read_coco refuses a set of no images
        print(f"conf {t}: {np.mean(best >= t) if len(best) else 0.0:.2f} of {len(best)} craters"
              f" kept, {boxes:.1f} crater boxes per frame")
    return 0


if __name__ == "__main__":
    sys.exit(main())
