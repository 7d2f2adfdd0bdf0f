"""Anchors from k-means on the training boxes (YOLOv2/v4: distance = 1 - IoU of sizes)."""

from __future__ import annotations

import numpy as np

from lunarnav_ml.data.coco import ImageRecord
from lunarnav_ml.errors import InputError


def box_sizes(records: list[ImageRecord], img_size: int) -> np.ndarray:
    """Sizes of all non-ignored boxes after letterboxing to ``img_size``.

    Returns:
        :math:`(N, 2)` float (w, h) in input pixels.
    """
    sizes = [(r.boxes[~r.ignore, 2:] - r.boxes[~r.ignore, :2]) * (img_size / max(r.width,
                                                                                r.height))
             for r in records]
    return np.concatenate(sizes + [np.zeros((0, 2), np.float32)]).astype(np.float64)


def _wh_iou(wh: np.ndarray, centers: np.ndarray) -> np.ndarray:
    inter = np.minimum(wh[:, None], centers[None]).prod(axis=2)
    return inter / (wh.prod(axis=1)[:, None] + centers.prod(axis=1)[None] - inter)


def kmeans_anchors(wh: np.ndarray, n: int, seed: int = 0, iters: int = 300) -> np.ndarray:
    """Cluster box sizes into ``n`` anchors with the 1 - IoU distance (k-means++ start).

    Args:
        wh: :math:`(N, 2)` box (w, h), px; N >= n.
        n: number of anchors.
        seed: random seed of the initialization.
        iters: maximum Lloyd iterations.

    Returns:
        :math:`(n, 2)` anchors sorted by area, px.
    """
    wh = np.asarray(wh, dtype=np.float64).reshape(-1, 2)
    wh = wh[(wh > 0).all(axis=1)]
    if len(wh) < n:
        raise InputError(f"k-means anchors: need at least {n} labelled boxes, found {len(wh)}")
    rng = np.random.default_rng(seed)
    centers = wh[[rng.integers(len(wh))]]
    while len(centers) < n:  # k-means++ with d = 1 - IoU
        d = (1 - _wh_iou(wh, centers).max(axis=1)) ** 2
        p = d / d.sum() if d.sum() > 0 else None
        centers = np.vstack([centers, wh[rng.choice(len(wh), p=p)]])
    assign = np.full(len(wh), -1)
    for _ in range(iters):
        new = _wh_iou(wh, centers).argmax(axis=1)
        if np.array_equal(new, assign):
            break
        assign = new
        centers = np.array([np.median(wh[assign == k], axis=0) if (assign == k).any()
                            else centers[k] for k in range(n)])
    return centers[np.argsort(centers.prod(axis=1))]


def anchors_for_levels(wh: np.ndarray, levels: int, per_level: int = 3, seed: int = 0
                       ) -> np.ndarray:
    """k-means anchors split by size over the scales, finest scale first.

    Returns:
        :math:`(levels, per_level, 2)` anchors, px.
    """
    return kmeans_anchors(wh, levels * per_level, seed).reshape(levels, per_level, 2)


def mean_best_iou(wh: np.ndarray, anchors: np.ndarray) -> float:
    """Mean over boxes of the best shape IoU with any anchor (anchor-fit quality)."""
    return float(_wh_iou(np.asarray(wh, float), np.asarray(anchors, float).reshape(-1, 2))
                 .max(axis=1).mean())
