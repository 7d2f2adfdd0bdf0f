"""Score thresholding and class-wise non-maximum suppression in numpy.

Same rules as ``lunarnav_ml.models.decode.postprocess`` (torchvision): a candidate's score is
``objectness * p(class)`` for its best class; candidates with ``score > conf_thres`` enter a
greedy NMS per class that drops boxes with IoU ``> iou_thres`` against a higher-scoring box;
at most ``max_det`` boxes per image, highest scores first.
"""

from __future__ import annotations

import numpy as np

Detections = dict[str, np.ndarray]


def cxcywh_to_xyxy(boxes: np.ndarray) -> np.ndarray:
    """Centre-size boxes to corner boxes.

    Shape:
        boxes: (..., 4) ``(cx, cy, w, h)`` -> (..., 4) ``(x0, y0, x1, y1)``.
    """
    half = boxes[..., 2:4] * 0.5
    return np.concatenate([boxes[..., :2] - half, boxes[..., :2] + half], axis=-1)


def box_iou_one(box: np.ndarray, boxes: np.ndarray, areas: np.ndarray, area: float
                ) -> np.ndarray:
    """IoU of one xyxy box (4,) with ``boxes`` (N, 4) whose areas (N,) are given."""
    w = np.minimum(box[2], boxes[:, 2]) - np.maximum(box[0], boxes[:, 0])
    h = np.minimum(box[3], boxes[:, 3]) - np.maximum(box[1], boxes[:, 1])
    inter = np.clip(w, 0, None) * np.clip(h, 0, None)
    with np.errstate(invalid="ignore", divide="ignore"):
        return inter / (area + areas - inter)


def nms(boxes: np.ndarray, scores: np.ndarray, iou_thres: float) -> np.ndarray:
    """Greedy NMS on one set of boxes.

    Args:
        boxes: (N, 4) xyxy.
        scores: (N,).
        iou_thres: a box is dropped when its IoU with a kept, higher-scoring box is above this.

    Returns:
        (K,) int64 indices of the kept boxes, by decreasing score.
    """
    boxes = np.asarray(boxes, dtype=np.float32)
    order = np.argsort(-np.asarray(scores), kind="stable")
    areas = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    keep: list[int] = []
    while order.size:
        i, rest = order[0], order[1:]
        keep.append(int(i))
        iou = box_iou_one(boxes[i], boxes[rest], areas[rest], areas[i])
        order = rest[~(iou > iou_thres)]  # NaN IoU (two empty boxes) keeps, as torchvision
    return np.asarray(keep, dtype=np.int64)


def batched_nms(boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray, iou_thres: float
                ) -> np.ndarray:
    """NMS within each label: boxes of different labels never suppress each other.

    Shape:
        boxes (N, 4) xyxy, scores (N,), labels (N,) int -> (K,) kept indices by decreasing score.
    """
    if len(boxes) == 0:
        return np.zeros(0, dtype=np.int64)
    # Shift each class to its own region so one NMS pass never mixes classes.
    offset = labels.astype(np.float32)[:, None] * (float(boxes.max()) + 1.0)
    return nms(boxes + offset, scores, iou_thres)


def select_candidates(rows: np.ndarray, conf_thres: float
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best class per candidate and the score threshold.

    Args:
        rows: (N, 5 + C) decoded rows of one image.
        conf_thres: minimum score (exclusive).

    Returns:
        boxes (M, 4) xyxy, scores (M,), class indices (M,) 0-based, for the M kept rows.
    """
    cls_scores = rows[:, 5:] * rows[:, 4:5]
    cls = cls_scores.argmax(axis=1)
    scores = np.take_along_axis(cls_scores, cls[:, None], axis=1)[:, 0]
    keep = scores > conf_thres
    return cxcywh_to_xyxy(rows[keep, :4]), scores[keep], cls[keep]


def postprocess(decoded: np.ndarray, conf_thres: float = 0.001, iou_thres: float = 0.6,
                max_det: int = 300) -> list[Detections]:
    """Threshold and class-wise NMS per image (numpy twin of the torch ``postprocess``).

    Args:
        decoded: (B, N, 5 + C) rows ``(cx, cy, w, h, objectness, class probs...)``, px.
        conf_thres: minimum score ``objectness * p(class)`` kept (exclusive).
        iou_thres: NMS IoU threshold.
        max_det: at most this many detections per image.

    Returns:
        per image ``{"boxes": (K, 4) float32 xyxy, "scores": (K,) float32, "labels": (K,)
        int64 category ids 1..C}``.
    """
    if decoded.ndim != 3 or decoded.shape[2] < 6:
        raise ValueError(f"decoded: expected shape (B, N, 5 + C), got {decoded.shape}")
    results = []
    for rows in decoded:
        boxes, scores, cls = select_candidates(rows, conf_thres)
        idx = batched_nms(boxes, scores, cls, iou_thres)[:max_det]
        results.append({"boxes": boxes[idx].astype(np.float32),
                        "scores": scores[idx].astype(np.float32),
                        "labels": cls[idx].astype(np.int64) + 1})
    return results


def split_graph_nms(indices: np.ndarray, boxes: np.ndarray, scores: np.ndarray, batch: int,
                    max_det: int = 300) -> list[Detections]:
    """Per-image detections from the outputs of an in-graph ONNX NonMaxSuppression.

    Args:
        indices: (K, 3) int64 rows ``(image, class, candidate)``.
        boxes: (K, 4) xyxy px of the selected candidates.
        scores: (K,) their scores.
        batch: number of images B.
        max_det: at most this many per image, highest scores first.

    Returns:
        B dicts as :func:`postprocess`.
    """
    results = []
    for b in range(batch):
        mine = np.flatnonzero(indices[:, 0] == b)
        mine = mine[np.argsort(-scores[mine], kind="stable")][:max_det]
        results.append({"boxes": boxes[mine].astype(np.float32),
                        "scores": scores[mine].astype(np.float32),
                        "labels": indices[mine, 1].astype(np.int64) + 1})
    return results
