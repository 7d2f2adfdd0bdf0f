"""Transfer evaluation on real labelled frames: recall at detection budgets and AP50 per class,
overall and per camera, with an overlay gallery.

Real sets such as the Chang'e frames are labelled sparsely: many visible rocks and small craters
carry no box. A correct detection of an unlabelled object then counts as a false positive, so
AP is a lower bound of the true figure. Recall when each image may keep only its ``k``
top-scoring detections of a class (``k`` = 1, 3, 5, 10; IoU >= 0.5; the ``maxDets`` of COCO's
average recall) is not hurt by missing labels the same way, and says how far down the ranked
list a labelled object sits. Ground truth marked ``ignore`` is neither a hit nor a miss.
"""

from __future__ import annotations

import contextlib
import copy
import io
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from lunarnav_ml.errors import InputError
from lunarnav_ml.eval.coco_metrics import check_results, coco_ap, coco_from_dict
from lunarnav_ml.eval.plots import draw_overlay
from lunarnav_ml.realdata.sources import UNKNOWN_CAMERA
from lunarnav_ml.utils import atomic
from lunarnav_ml.utils.images import caption_tile, contact_sheet, read_rgb

BUDGETS = (1, 3, 5, 10)  # top-scoring detections kept per image and class
IOU_THRESHOLD = 0.5
AP_NOTE = ("AP50 is a lower bound: the real labels are sparse (not every visible crater or rock "
           "has a box), so correct detections of unlabelled objects count as false positives.")


def recall_at_budgets(coco_gt: COCO, results: list[dict[str, Any]],
                      budgets: Sequence[int] = BUDGETS, iou: float = IOU_THRESHOLD,
                      image_ids: Sequence[int] | None = None) -> dict[str, dict[str, Any]]:
    """Recall per class when each image keeps its ``k`` top-scoring detections of that class.

    Args:
        coco_gt: ground truth index (:func:`coco_from_dict`: ``ignore`` boxes are crowd regions).
        results: COCO results ``[{image_id, category_id, bbox [x, y, w, h] px, score}]``.
        budgets: detections per image and class, ``k``.
        iou: IoU a detection needs with a ground-truth box to find it.
        image_ids: the images evaluated (default: all).

    Returns:
        ``{class name: {"n_gt": int, "recall@k": float or None (no ground truth)}}``.
    """
    budgets = sorted(int(k) for k in budgets)
    ids = list(coco_gt.getImgIds() if image_ids is None else image_ids)
    cats = coco_gt.loadCats(coco_gt.getCatIds())
    n_gt = {c["id"]: _count_gt(coco_gt, c["id"], ids) for c in cats}
    if not results or not ids:
        return {c["name"]: {"n_gt": n_gt[c["id"]], **{f"recall@{k}": 0.0 if n_gt[c["id"]] else None
                                                      for k in budgets}} for c in cats}
    with contextlib.redirect_stdout(io.StringIO()):
        ev = COCOeval(coco_gt, coco_gt.loadRes(copy.deepcopy(results)), iouType="bbox")
        ev.params.imgIds, ev.params.iouThrs = ids, np.array([iou])
        ev.params.maxDets, ev.params.areaRng, ev.params.areaRngLbl = budgets, [[0, 1e10]], ["all"]
        ev.evaluate()
        ev.accumulate()
    recall = ev.eval["recall"][0, :, 0, :]  # [K classes, M budgets]; -1 without ground truth
    return {c["name"]: {"n_gt": n_gt[c["id"]],
                        **{f"recall@{k}": None if r < 0 else float(r)
                           for k, r in zip(budgets, recall[i])}}
            for i, c in enumerate(cats)}


def _count_gt(coco_gt: COCO, cat_id: int, image_ids: Sequence[int]) -> int:
    anns = coco_gt.loadAnns(coco_gt.getAnnIds(imgIds=list(image_ids), catIds=[cat_id]))
    return sum(1 for a in anns if not a["iscrowd"])


def camera_groups(gt: dict[str, Any]) -> dict[str, list[int]]:
    """Image ids per camera (``camera_name`` of each image; ``"unknown"`` without one)."""
    groups: dict[str, list[int]] = defaultdict(list)
    for img in gt["images"]:
        groups[str(img.get("camera_name") or UNKNOWN_CAMERA)].append(img["id"])
    return dict(sorted(groups.items()))


def transfer_metrics(gt: dict[str, Any], results: list[dict[str, Any]],
                     budgets: Sequence[int] = BUDGETS) -> dict[str, Any]:
    """Recall at each budget and AP50 per class, for all images and per camera.

    Args:
        gt: our COCO ground truth (``lunarnav import-real`` output).
        results: COCO results over the same images.

    Returns:
        ``{"budgets", "iou", "note", "all": group, "per_camera": {camera: group}}`` with
        ``group = {"n_images", "per_class": {name: {"n_gt", "AP50", "recall@k"...}}}``.
    """
    if not isinstance(results, list):
        raise InputError(f"detections must be a list of COCO results, got {type(results).__name__}")
    coco_gt = coco_from_dict(gt)
    check_results(results, coco_gt)
    groups = {"all": [img["id"] for img in gt["images"]], **camera_groups(gt)}
    out = {name: _group_metrics(gt, coco_gt, results, ids, budgets) for name, ids in groups.items()}
    return {"budgets": list(budgets), "iou": IOU_THRESHOLD, "note": AP_NOTE, "all": out.pop("all"),
            "per_camera": out}


def _group_metrics(gt: dict[str, Any], coco_gt: COCO, results: list[dict[str, Any]],
                   ids: list[int], budgets: Sequence[int]) -> dict[str, Any]:
    keep = set(ids)
    sub_gt = {**gt, "images": [i for i in gt["images"] if i["id"] in keep],
              "annotations": [a for a in gt["annotations"] if a["image_id"] in keep]}
    ap = coco_ap(sub_gt, [r for r in results if r["image_id"] in keep])["per_class"]
    recall = recall_at_budgets(coco_gt, results, budgets, image_ids=ids)
    return {"n_images": len(ids),
            "per_class": {name: {"n_gt": row["n_gt"], "AP50": ap[name]["AP50"],
                                 **{k: v for k, v in row.items() if k != "n_gt"}}
                          for name, row in recall.items()}}


def render_markdown(metrics: dict[str, Any], title: str) -> str:
    """The transfer report: one table per image group (all, then each camera)."""
    keys = [f"recall@{k}" for k in metrics["budgets"]]
    intro = (f"Recall@k: each image keeps its k top-scoring detections per class; a labelled "
             f"box is found at IoU >= {metrics['iou']}. {metrics['note']}")
    lines = [f"# {title}", "", intro, ""]
    groups = {"all images": metrics["all"],
              **{f"camera {c}": g for c, g in metrics["per_camera"].items()}}
    for name, group in groups.items():
        lines += [f"## {name} ({group['n_images']} images)", "",
                  "| class | labelled boxes | " + " | ".join(keys) + " | AP50 (lower bound) |",
                  "|---" * (len(keys) + 3) + "|"]
        for cls, row in group["per_class"].items():
            cells = [fmt_metric(row[k]) for k in keys] + [fmt_metric(row["AP50"])]
            lines.append(f"| {cls} | {row['n_gt']} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def fmt_metric(x: float | None) -> str:
    """A metric to three decimals, ``-`` where it is undefined (no ground truth)."""
    return "-" if x is None else f"{x:.3f}"


def pick_gallery_images(gt: dict[str, Any], n: int) -> list[dict[str, Any]]:
    """``n`` images taken in turn from each camera, the most labelled first."""
    n_boxes: dict[int, int] = defaultdict(int)
    for ann in gt["annotations"]:
        n_boxes[ann["image_id"]] += not (ann.get("ignore") or ann.get("iscrowd"))
    by_id = {img["id"]: img for img in gt["images"]}
    queues = [sorted(ids, key=lambda i: (-n_boxes[i], i)) for ids in camera_groups(gt).values()]
    picked: list[dict[str, Any]] = []
    while len(picked) < n and any(queues):
        for queue in queues:
            if queue and len(picked) < n:
                picked.append(by_id[queue.pop(0)])
    return picked


def draw_gallery(gt: dict[str, Any], results: list[dict[str, Any]], root: Path, path: Path, *,
                 n: int = 12, top_k: int = 5, tile: int = 320, cols: int = 4) -> Path | None:
    """A grid of images with their labels (green; ignored grey) and top-``k`` detections.

    Args:
        gt: our COCO ground truth; ``file_name`` relative to ``root``.
        results: COCO results.
        path: PNG to write.
        n: images in the grid; top_k: detections drawn per image (all classes, by score);
        tile: side of each square tile, px; cols: tiles per row.

    Returns:
        ``path``, or ``None`` when ``n`` is 0 or there is no image.
    """
    images = pick_gallery_images(gt, n)
    if not images:
        return None
    names = {c["id"]: c["name"] for c in gt["categories"]}
    dets: dict[int, list[dict]] = defaultdict(list)
    for det in results:
        dets[det["image_id"]].append(det)
    tiles = []
    for img in images:
        anns = [a for a in gt["annotations"] if a["image_id"] == img["id"]]
        top = sorted(dets[img["id"]], key=lambda d: -d["score"])[:top_k]
        bgr = cv2.cvtColor(read_rgb(Path(root) / img["file_name"]), cv2.COLOR_RGB2BGR)
        overlay = draw_overlay(bgr, anns, top, names)
        caption = f"{img.get('camera_name', UNKNOWN_CAMERA)}  {img.get('source_name', '')}"
        tiles.append(caption_tile(overlay, tile, caption[:48]))
    return atomic.write_image(path, contact_sheet(tiles, cols))


def write_transfer_report(gt: dict[str, Any], results: list[dict[str, Any]], root: Path,
                          out_dir: Path, title: str = "Transfer to real frames", *,
                          gallery_images: int = 12, top_k: int = 5) -> dict[str, Any]:
    """Write ``transfer_metrics.json``, ``transfer_report.md`` and ``gallery.png``.

    Args:
        root: folder the ground truth's ``file_name`` entries are relative to.
        gallery_images: images in the gallery (0: none); top_k: detections drawn per image.

    Returns:
        The metrics.
    """
    metrics = transfer_metrics(gt, results)
    atomic.write_json(Path(out_dir) / "transfer_metrics.json", metrics)
    atomic.write_text(Path(out_dir) / "transfer_report.md", render_markdown(metrics, title))
    draw_gallery(gt, results, root, Path(out_dir) / "gallery.png", n=gallery_images, top_k=top_k)
    return metrics
