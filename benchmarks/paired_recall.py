"""Is one model's crater recall@k on the real frames really above another's? A paired bootstrap
over the frames.

Each frame's found craters (pycocotools, IoU >= 0.5, the frame's top ``k`` crater detections,
as ``lunarnav eval --task transfer`` counts them) are counted once per model; the frames are
then resampled with replacement, the same draw for both models, and the difference in pooled
recall@k read from each draw. Prints both recalls, the difference B - A with its 95 % interval,
and the share of draws in which B is not above A. With 83 craters on 99 frames one crater is
1.2 points of recall: the interval says how many craters apart two models must be before a
difference is more than the draw of frames (BENCHMARKS.md, session 59).

    python benchmarks/paired_recall.py --gt data/real/chandai_v5/valid/annotations.json \
        --a outputs/s58/ev_avg/real/detections.json --b outputs/s59/ev_avg2/real/detections.json
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from lunarnav_ml.data.coco import read_coco
from lunarnav_ml.errors import LunarNavError
from lunarnav_ml.eval.coco_metrics import coco_from_dict
from lunarnav_ml.eval.predict import check_coco_results
from lunarnav_ml.realdata.transfer import recall_at_budgets
from lunarnav_ml.utils.jsonfile import read_json_file


def found_per_frame(gt: dict, dets: list[dict], k: int, name: str = "crater"
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Per frame of ``gt``: (countable labelled ``name`` boxes, those found within the top ``k``)."""
    coco_gt = coco_from_dict(gt)
    by_image: dict[int, list[dict]] = {}
    for d in dets:
        by_image.setdefault(d["image_id"], []).append(d)
    n_gt, found = [], []
    for img in gt["images"]:
        rec = recall_at_budgets(coco_gt, by_image.get(img["id"], []), [k],
                                image_ids=[img["id"]])[name]
        n_gt.append(rec["n_gt"])
        found.append(round((rec[f"recall@{k}"] or 0.0) * rec["n_gt"]))
    return np.asarray(n_gt), np.asarray(found)


def paired_bootstrap(n_gt: np.ndarray, found_a: np.ndarray, found_b: np.ndarray,
                     n_boot: int = 10000, seed: int = 0) -> np.ndarray:
    """Pooled recall B - A over ``n_boot`` resamples of the frames (draws with no labelled
    craters left out)."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(n_gt), size=(n_boot, len(n_gt)))
    total = n_gt[idx].sum(axis=1)
    keep = total > 0
    return ((found_b[idx].sum(axis=1) - found_a[idx].sum(axis=1))[keep] / total[keep])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gt", required=True, help="COCO annotations of the frames")
    ap.add_argument("--a", required=True, help="COCO results JSON of model A (the reference)")
    ap.add_argument("--b", required=True, help="COCO results JSON of model B")
    ap.add_argument("--k", type=int, default=5, help="crater detections kept per frame")
    ap.add_argument("--n-boot", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    try:  # the labels and the results checked as the evaluations check them
        gt = read_coco(args.gt, check_files=False)[0]
        dets = [check_coco_results(read_json_file(path, "detections"), path)
                for path in (args.a, args.b)]
    except LunarNavError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    n_gt, found_a = found_per_frame(gt, dets[0], args.k)
    _, found_b = found_per_frame(gt, dets[1], args.k)
    if n_gt.sum() == 0:
        print(f"error: {args.gt}: no countable labelled craters", file=sys.stderr)
        return 2
    diff = paired_bootstrap(n_gt, found_a, found_b, args.n_boot, args.seed)
    lo, hi = np.percentile(diff, [2.5, 97.5])
    total = int(n_gt.sum())
    print(f"recall@{args.k} A {found_a.sum() / total:.3f} ({found_a.sum()} of {total}), "
          f"B {found_b.sum() / total:.3f} ({found_b.sum()}); B - A "
          f"{(found_b.sum() - found_a.sum()) / total:+.3f}, 95 % interval [{lo:+.3f}, {hi:+.3f}]"
          f" over {len(n_gt)} frames; B not above A in {np.mean(diff <= 0):.2f} of the draws")
    return 0


if __name__ == "__main__":
    sys.exit(main())
