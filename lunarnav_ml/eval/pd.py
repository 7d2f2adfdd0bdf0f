"""Probability of detection (Pd) the paper's way, and false alarms per image.

A non-ignored ground-truth crater is detected when a predicted crater box scoring at or above
the operating threshold has IoU >= 0.5 with it (DESIGN.md, "The paper's evaluation protocol").
Matching is greedy by score, one prediction per ground truth. A prediction that matches no
non-ignored crater but lies on an ignored one is neither a hit nor a false alarm: as in
pycocotools' crowd regions (how the AP ignores the same craters), "lies on" is the overlap
over the prediction's own area (>= 0.5), not the IoU, so a box on part of a clipped or far
crater is not counted against the detector. Every other unmatched prediction is a false alarm.
The operating threshold is picked on a validation split, never on the test set.
"""

from __future__ import annotations

import itertools
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from pycocotools import mask as mask_utils

CRATER_ID = 1
KEY_MIN_DIAMETER_M, KEY_MAX_RANGE_M = 5.0, 20.0  # the Pd set (see in_key_set)


@dataclass
class MatchResult:
    """Per-crater outcome and false alarms of one evaluation at one threshold.

    Attributes:
        gt: the non-ignored ground-truth crater annotations, in a fixed order.
        box: (len(gt), 4) xywh px of the prediction matched to each entry of ``gt`` at the
            threshold (NaN where it was missed).
        false_alarm_dets: the false-alarm predictions over all images.
        n_images: number of images evaluated.
    """

    gt: list[dict[str, Any]]
    box: np.ndarray
    false_alarm_dets: list[dict[str, Any]]
    n_images: int

    @property
    def hit(self) -> np.ndarray:
        """bool per entry of ``gt``: detected at the threshold."""
        return np.isfinite(self.box[:, 0])

    @property
    def false_alarms(self) -> int:
        """Number of false-alarm predictions over all images."""
        return len(self.false_alarm_dets)

    @property
    def pd(self) -> float:
        """Fraction of ground-truth craters detected (NaN when there is none)."""
        return float(self.hit.mean()) if self.hit.size else float("nan")

    @property
    def fa_per_image(self) -> float:
        """False alarms per image."""
        return self.false_alarms / max(self.n_images, 1)


def match_craters(
    gt: dict[str, Any],
    results: Sequence[dict[str, Any]],
    threshold: float,
    iou_thres: float = 0.5,
    category_id: int = CRATER_ID,
) -> MatchResult:
    """Match crater predictions to ground truth at a score threshold.

    Args:
        gt: COCO ground-truth dict.
        results: COCO results (``image_id``, ``category_id``, ``bbox`` xywh px, ``score``).
        threshold: operating score threshold (predictions below it are dropped).
        iou_thres: IoU needed for a hit.
        category_id: the class evaluated (1 = crater).
    """
    gt_by_img: dict[int, list[dict]] = defaultdict(list)
    for ann in gt["annotations"]:
        if ann["category_id"] == category_id:
            gt_by_img[ann["image_id"]].append(ann)
    dt_by_img: dict[int, list[dict]] = defaultdict(list)
    for det in results:
        if det["category_id"] == category_id and det["score"] >= threshold:
            dt_by_img[det["image_id"]].append(det)
    gts, boxes, false_alarms = [], [], []
    for img in gt["images"]:
        anns = gt_by_img.get(img["id"], [])
        img_boxes, img_fa = _match_image(anns, dt_by_img.get(img["id"], []), iou_thres)
        gts.extend(a for a in anns if not is_ignored(a))
        boxes.extend(img_boxes)
        false_alarms.extend(img_fa)
    return MatchResult(gts, np.asarray(boxes, dtype=float).reshape(-1, 4), false_alarms,
                       len(gt["images"]))


def is_ignored(ann: dict[str, Any]) -> bool:
    """An ignore region: neither a hit nor a miss, and a box on it is no false alarm."""
    return bool(ann.get("ignore", False)) or bool(ann.get("iscrowd", 0))


def in_key_set(ann: dict[str, Any]) -> bool:
    """The issue's headline Pd set: craters D >= 5 m whose near rim is within 20 m."""
    return (float(ann.get("diameter_m", np.nan)) >= KEY_MIN_DIAMETER_M
            and float(ann.get("near_rim_range_m", np.nan)) <= KEY_MAX_RANGE_M)


def _match_image(
    anns: list[dict], dets: list[dict], iou_thres: float
) -> tuple[list[list[float]], list[dict]]:
    """Greedy matching in one image; returns the matched prediction's box (xywh; NaN: missed)
    for each non-ignored GT, and the false alarms."""
    real = [a for a in anns if not is_ignored(a)]
    ignored = [a for a in anns if is_ignored(a)]
    dets = sorted(dets, key=lambda d: -d["score"])
    matched = np.full((len(real), 4), np.nan)
    if not dets:
        return matched.tolist(), []
    boxes = np.asarray([d["bbox"] for d in dets], dtype=float)
    iou_real = _iou(boxes, real)
    iou_ign = _iou(boxes, ignored, crowd=True)
    false_alarms = []
    for i in range(len(dets)):
        free = np.isnan(matched[:, 0])
        candidates = [j for j in range(len(real)) if free[j] and iou_real[i, j] >= iou_thres]
        if candidates:
            matched[max(candidates, key=lambda j: iou_real[i, j])] = boxes[i]
        elif not (iou_ign.shape[1] and iou_ign[i].max() >= iou_thres):
            false_alarms.append(dets[i])
    return matched.tolist(), false_alarms


def _iou(boxes: np.ndarray, anns: list[dict], crowd: bool = False) -> np.ndarray:
    """IoU of xywh ``boxes`` with the annotations' boxes; with ``crowd``, pycocotools' crowd
    overlap instead: the intersection over each box's own area."""
    if not anns:
        return np.zeros((len(boxes), 0))
    gt_boxes = np.asarray([a["bbox"] for a in anns], dtype=float)
    flags = [int(crowd)] * len(anns)
    return np.asarray(mask_utils.iou(boxes, gt_boxes, flags)).reshape(len(boxes), -1)


def pick_operating_threshold(
    gt: dict[str, Any],
    results: Sequence[dict[str, Any]],
    max_fa_per_image: float = 0.2,
    category_id: int = CRATER_ID,
) -> float:
    """Lowest score threshold whose false alarms per image stay within ``max_fa_per_image``.

    Use on a validation split. Candidates are the predicted scores themselves, so the choice
    is exact; the highest Pd under the false-alarm budget is the lowest admissible threshold.

    Returns:
        the threshold (1.0 when no prediction exists).
    """
    scores = sorted({d["score"] for d in results if d["category_id"] == category_id})
    if not scores:
        return 1.0
    lo, hi = 0, len(scores) - 1  # false alarms fall as the threshold rises: bisect
    if match_craters(gt, results, scores[hi], category_id=category_id).fa_per_image > max_fa_per_image:
        return float(np.nextafter(scores[hi], np.inf))
    while lo < hi:
        mid = (lo + hi) // 2
        if match_craters(gt, results, scores[mid], category_id=category_id).fa_per_image <= max_fa_per_image:
            hi = mid
        else:
            lo = mid + 1
    return float(scores[lo])


def pd_by(
    match: MatchResult,
    key: str,
    edges: Sequence[float],
    image_key: dict[int, float] | None = None,
) -> list[dict[str, Any]]:
    """Pd in bins of a crater (or image) property.

    Args:
        match: result of :func:`match_craters`.
        key: annotation key to bin on (``near_rim_range_m``, ``diameter_m``), or an image key
            when ``image_key`` maps image ids to that property (sun angles).
        edges: bin edges; bin i holds ``edges[i] <= value < edges[i + 1]``.
        image_key: optional image id -> value mapping.

    Returns:
        one row per bin: ``{"lo", "hi", "n", "detected", "pd"}`` (pd None when n = 0).
    """
    values = np.asarray(
        [image_key[a["image_id"]] if image_key is not None else a.get(key, np.nan) for a in match.gt],
        dtype=float,
    )
    rows = []
    for lo, hi in itertools.pairwise(edges):
        sel = (values >= lo) & (values < hi)
        n = int(sel.sum())
        det = int(match.hit[sel].sum())
        rows.append({"lo": float(lo), "hi": float(hi), "n": n, "detected": det,
                     "pd": det / n if n else None})
    return rows


def subset(match: MatchResult, keep: np.ndarray) -> MatchResult:
    """The same match restricted to the ground-truth craters selected by ``keep``."""
    keep = np.asarray(keep, dtype=bool)
    return MatchResult([g for g, k in zip(match.gt, keep) if k], match.box[keep],
                       match.false_alarm_dets, match.n_images)


def box_precision(match: MatchResult) -> dict[str, Any]:
    """How far the detected craters' boxes are from their labels, as fractions of the label's
    side: the robust sigma (1.4826 x MAD) of each edge's offset (left, right, top, bottom),
    and the median width and height ratio - 1 (negative: boxes too small). The 3D lift takes a
    crater's angular width from its box (BENCHMARKS.md, issue 5, "Lifting from the box"), so
    these figures bound the geometry a detector allows."""
    hit = match.hit
    if not hit.any():
        return {"n": 0}
    gt = np.asarray([a["bbox"] for a, h in zip(match.gt, hit) if h], dtype=float)
    det = match.box[hit]
    side = gt[:, [2, 2, 3, 3]]
    edges = np.column_stack([det[:, 0] - gt[:, 0], det[:, 0] + det[:, 2] - gt[:, 0] - gt[:, 2],
                             det[:, 1] - gt[:, 1], det[:, 1] + det[:, 3] - gt[:, 1] - gt[:, 3]])
    rel = edges / side
    sigma = 1.4826 * np.median(np.abs(rel - np.median(rel, axis=0)), axis=0)
    return {"n": len(gt),
            "edge_sigma": dict(zip(("left", "right", "top", "bottom"), map(float, sigma))),
            "width_ratio_median": float(np.median(det[:, 2] / gt[:, 2]) - 1.0),
            "height_ratio_median": float(np.median(det[:, 3] / gt[:, 3]) - 1.0)}
