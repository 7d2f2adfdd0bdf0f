"""COCO mAP@[.5:.95] and AP50 per class through pycocotools.

Ground-truth boxes marked ``"ignore": true`` (DESIGN.md) are passed to pycocotools as crowd
regions (``iscrowd = 1``), which is how COCOeval ignores them: a detection that overlaps one is
neither a hit nor a false alarm.
"""

from __future__ import annotations

import contextlib
import copy
import io
from typing import Any

import numpy as np
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from lunarnav_ml.errors import InputError

CRATER_ID = 1  # the category crater_eval and matched read (as eval.pd's)


def coco_from_dict(dataset: dict[str, Any]) -> COCO:
    """Build a pycocotools ``COCO`` index from a COCO dict, honouring ``ignore`` flags.

    Args:
        dataset: COCO detection dict with ``images``, ``annotations`` and ``categories``.
    """
    for key in ("images", "annotations", "categories"):
        if key not in dataset:
            raise InputError(f"COCO ground truth has no '{key}' list")
    data = copy.deepcopy(dataset)
    for ann in data["annotations"]:
        ann["iscrowd"] = int(bool(ann.get("ignore", False)) or bool(ann.get("iscrowd", 0)))
        ann.setdefault("area", float(ann["bbox"][2] * ann["bbox"][3]))
    coco = COCO()
    coco.dataset = data
    with contextlib.redirect_stdout(io.StringIO()):
        coco.createIndex()
    return coco


def check_results(results: list[dict[str, Any]], gt: COCO) -> None:
    """Raise ``InputError`` if a detection names an unknown image or category or holds a NaN."""
    image_ids = set(gt.getImgIds())
    cat_ids = set(gt.getCatIds())
    for i, det in enumerate(results):
        if det.get("image_id") not in image_ids:
            raise InputError(f"detection {i}: image_id {det.get('image_id')!r} is not in the ground truth")
        if det.get("category_id") not in cat_ids:
            raise InputError(f"detection {i}: unknown category_id {det.get('category_id')!r}")
        values = np.asarray(list(det["bbox"]) + [det["score"]], dtype=float)
        if values.shape != (5,) or not np.all(np.isfinite(values)):
            raise InputError(f"detection {i}: bbox/score must be 4 + 1 finite numbers, got {det}")


def coco_ap(gt: dict[str, Any] | COCO, results: list[dict[str, Any]]) -> dict[str, Any]:
    """COCO box AP per class and overall.

    Args:
        gt: ground truth (COCO dict or ``COCO`` index).
        results: COCO results, ``[{image_id, category_id, bbox [x, y, w, h] px, score}]``.

    Returns:
        ``{"mAP": float, "AP50": float, "per_class": {name: {"AP": float, "AP50": float,
        "n_gt": int}}}``; a class without ground truth gets ``None`` APs (pycocotools' -1).
    """
    coco_gt = gt if isinstance(gt, COCO) else coco_from_dict(gt)
    check_results(results, coco_gt)
    per_class = {}
    cats = coco_gt.loadCats(coco_gt.getCatIds())
    if not results:
        for cat in cats:
            n_gt = _count_gt(coco_gt, cat["id"])
            per_class[cat["name"]] = {"AP": 0.0 if n_gt else None, "AP50": 0.0 if n_gt else None,
                                      "n_gt": n_gt}
        return {"mAP": 0.0, "AP50": 0.0, "per_class": per_class}
    with contextlib.redirect_stdout(io.StringIO()):
        coco_dt = coco_gt.loadRes(copy.deepcopy(results))
        ev = COCOeval(coco_gt, coco_dt, iouType="bbox")
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    precision = ev.eval["precision"]  # [T iou thresholds, R recall, K classes, A areas, M maxdets]
    for k, cat in enumerate(cats):
        p_all = precision[:, :, k, 0, -1]
        p_50 = precision[0, :, k, 0, -1]
        per_class[cat["name"]] = {
            "AP": _mean_valid(p_all),
            "AP50": _mean_valid(p_50),
            "n_gt": _count_gt(coco_gt, cat["id"]),
        }
    return {"mAP": float(ev.stats[0]), "AP50": float(ev.stats[1]), "per_class": per_class}


def _mean_valid(precision: np.ndarray) -> float | None:
    valid = precision[precision > -1]
    return float(valid.mean()) if valid.size else None


def _count_gt(coco_gt: COCO, cat_id: int) -> int:
    anns = coco_gt.loadAnns(coco_gt.getAnnIds(catIds=[cat_id]))
    return sum(1 for a in anns if not a["iscrowd"])


def crater_eval(coco_gt: COCO, dets: list[dict[str, Any]], max_det: int) -> COCOeval:
    """pycocotools' crater evaluation at IoU 0.5, the top ``max_det`` boxes of each image."""
    with contextlib.redirect_stdout(io.StringIO()):
        ev = COCOeval(coco_gt, coco_gt.loadRes(copy.deepcopy(dets)), iouType="bbox")
        ev.params.catIds = [CRATER_ID]
        ev.params.iouThrs = np.array([0.5])
        ev.params.maxDets = [1, 10, max_det]
        ev.evaluate()
        ev.accumulate()
    return ev


def matched(coco_gt: COCO, dets: list[dict[str, Any]]) -> np.ndarray:
    """Per box of ``dets``: 1 if it matches a countable crater when every box of its image is
    read, 0 if it is an unmatched crater box, -1 otherwise (ignored, or not a crater box)."""
    status = np.full(len(dets), -1, np.int64)
    if not any(d["category_id"] == CRATER_ID for d in dets):
        return status
    per_image: dict[int, int] = {}
    for d in dets:
        per_image[d["image_id"]] = per_image.get(d["image_id"], 0) + 1
    ev = crater_eval(coco_gt, dets, max(per_image.values()))
    for e in ev.evalImgs:  # loadRes numbers the boxes 1..N in the order given
        if e is None or e["aRng"] != ev.params.areaRng[0]:
            continue
        for box_id, match, ignored in zip(e["dtIds"], e["dtMatches"][0], e["dtIgnore"][0],
                                          strict=True):
            if not ignored:
                status[box_id - 1] = int(match > 0)
    return status
