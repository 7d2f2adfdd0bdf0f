"""How much crater AP50 a better score alone could give a results file: its boxes kept, ranked
perfectly.

pycocotools matches the crater boxes at IoU 0.5 as ``lunarnav eval`` does (ignored labels are
crowd regions: a box on one is neither a hit nor a false alarm). Printed:

- crater AP50 and recall as the file is scored (the top 100 boxes of each image, as COCO reads);
- the ranking ceiling: every box that matches a countable crater among all of an image's boxes
  scored above every box that does not; its AP50 is what a perfect rescoring would reach, and
  its recall what it is bounded by;
- the unmatched boxes by kind, each box's best IoU with a countable crater (>= 0.5: a second box
  on a crater another box found; 0.3-0.5: loose) or else with an ignored one (>= 0.3: near an
  ignored crater) or neither (off every crater), how many score above the median matched box,
  and the AP50 with that kind removed.

Session 73 read the shipped detector and box refiner on the 300 validation renders: AP50 0.607,
ceiling 0.822 (BENCHMARKS.md, "Where the rescored detector's crater AP50 is lost").

    python benchmarks/ranking_ceiling.py --gt data/d7/val300/annotations.json \\
        --results outputs/s72/v300_B2Q/detections.json --plot outputs/s73/ceiling_v300.png
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np
from pycocotools import mask as mask_utils
from pycocotools.coco import COCO

from lunarnav_ml.data.coco import read_coco
from lunarnav_ml.errors import LunarNavError
from lunarnav_ml.eval.coco_metrics import coco_from_dict, crater_eval, matched
from lunarnav_ml.eval.pd import CRATER_ID, is_ignored
from lunarnav_ml.eval.predict import check_coco_results
from lunarnav_ml.utils.atomic import check_image_destination, write_figure
from lunarnav_ml.utils.jsonfile import read_json_file

KINDS = ("second box", "loose", "near ignored", "off every crater")
COCO_MAX_DET = 100


def ap50_recall(coco_gt: COCO, dets: list[dict[str, Any]], max_det: int = COCO_MAX_DET
                ) -> tuple[float, float]:
    """Crater AP50 and recall (all areas, the top ``max_det`` boxes per image)."""
    if not any(d["category_id"] == CRATER_ID for d in dets):
        return 0.0, 0.0
    ev = crater_eval(coco_gt, dets, max_det)
    precision = ev.eval["precision"][0, :, 0, 0, -1]
    valid = precision[precision > -1]
    return (float(valid.mean()) if valid.size else 0.0,
            max(float(ev.eval["recall"][0, 0, 0, -1]), 0.0))


def _best_iou(box: list[float], labels: list[list[float]]) -> float:
    if not labels:
        return 0.0
    return float(mask_utils.iou([box], labels, [0] * len(labels)).max())


def unmatched_kinds(gt: dict[str, Any], dets: list[dict[str, Any]], status: np.ndarray
                    ) -> np.ndarray:
    """The kind (an index into ``KINDS``) of each unmatched crater box, -1 for the others."""
    countable: dict[int, list[list[float]]] = {}
    ignored: dict[int, list[list[float]]] = {}
    for a in gt["annotations"]:
        if a["category_id"] == CRATER_ID:
            into = ignored if is_ignored(a) else countable
            into.setdefault(a["image_id"], []).append([float(v) for v in a["bbox"]])
    kind = np.full(len(dets), -1, np.int64)
    for i in np.flatnonzero(status == 0):
        box = [float(v) for v in dets[i]["bbox"]]
        on_countable = _best_iou(box, countable.get(dets[i]["image_id"], []))
        if on_countable >= 0.5:
            kind[i] = 0
        elif on_countable >= 0.3:
            kind[i] = 1
        else:
            kind[i] = 2 if _best_iou(box, ignored.get(dets[i]["image_id"], [])) >= 0.3 else 3
    return kind


def report(gt: dict[str, Any], dets: list[dict[str, Any]]) -> dict[str, Any]:
    """The figures the script prints (module docstring)."""
    coco_gt = coco_from_dict(gt)
    ap50, recall = ap50_recall(coco_gt, dets)
    status = matched(coco_gt, dets)
    ranked = [{**d, "score": float(d["score"]) + (1.0 if s == 1 else 0.0)}
              for d, s in zip(dets, status, strict=True)]
    ceiling, ceiling_recall = ap50_recall(coco_gt, ranked)
    kind = unmatched_kinds(gt, dets, status)
    scores = np.array([float(d["score"]) for d in dets])
    median_hit = float(np.median(scores[status == 1])) if (status == 1).any() else np.inf
    kinds = []
    for k, name in enumerate(KINDS):
        idx = np.flatnonzero(kind == k)
        without = ap50_recall(coco_gt, [d for d, kd in zip(dets, kind, strict=True) if kd != k])[0]
        kinds.append({"kind": name, "n": int(idx.size),
                      "above_median_hit": int((scores[idx] > median_hit).sum()),
                      "ap50_without": without})
    return {"ap50": ap50, "recall": recall, "ceiling_ap50": ceiling,
            "ceiling_recall": ceiling_recall, "n_matched": int((status == 1).sum()),
            "n_unmatched": int((status == 0).sum()), "kinds": kinds,
            "scores": scores, "status": status, "kind": kind}


def plot(figures: dict[str, Any], path: str | Path, title: str) -> None:
    """Score histograms of the matched boxes and of each kind of unmatched box."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scores, bins = figures["scores"], np.linspace(0.0, 1.0, 41)
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.hist(scores[figures["status"] == 1], bins, histtype="step", lw=2, color="k",
            label=f"matched ({figures['n_matched']})")
    for k, name in enumerate(KINDS):
        sel = figures["kind"] == k
        ax.hist(scores[sel], bins, histtype="step", label=f"{name} ({int(sel.sum())})")
    ax.set(yscale="log", xlabel="score", ylabel="crater boxes",
           title=f"{title}: AP50 {figures['ap50']:.3f}, ceiling {figures['ceiling_ap50']:.3f}")
    ax.legend(fontsize=8)
    write_figure(path, fig)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gt", required=True, help="COCO annotations")
    ap.add_argument("--results", required=True, help="COCO results JSON on those images")
    ap.add_argument("--plot", help="PNG of the score histograms")
    args = ap.parse_args(argv)
    try:  # the labels and the results checked as the evaluations check them
        if args.plot:
            check_image_destination(args.plot)
        gt = read_coco(args.gt, check_files=False)[0]
        dets = check_coco_results(read_json_file(args.results, "detections"), args.results)
        figures = report(gt, dets)
    except LunarNavError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"crater AP50 {figures['ap50']:.4f}, recall {figures['recall']:.4f} (top "
          f"{COCO_MAX_DET} per image); ranking ceiling AP50 {figures['ceiling_ap50']:.4f}, recall "
          f"{figures['ceiling_recall']:.4f} ({figures['n_matched']} matched, "
          f"{figures['n_unmatched']} unmatched crater boxes)")
    for k in figures["kinds"]:
        print(f"  {k['kind']:17s} {k['n']:6d} unmatched, {k['above_median_hit']:5d} above the "
              f"median matched score; AP50 without them {k['ap50_without']:.4f}")
    if args.plot:
        plot(figures, args.plot, Path(args.results).parent.name)
        print(f"-> {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
