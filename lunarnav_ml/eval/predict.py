"""Run any detector with a ``predict(images)`` method over a COCO dataset -> COCO results."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from tqdm import tqdm

from lunarnav_ml.utils.images import read_rgb


class Predictor(Protocol):
    """Anything that turns RGB images into boxes (the torch Detector, the ONNX runtime)."""

    def predict(self, images: list[np.ndarray], conf_thres: float = ..., iou_thres: float = ...
                ) -> list[dict[str, np.ndarray]]: ...


def iter_batches(dataset: dict[str, Any], root: Path, batch: int) -> Iterator[tuple[list, list]]:
    """Yield (image records, RGB arrays) in batches, in the dataset's image order."""
    images = dataset["images"]
    for start in range(0, len(images), batch):
        records = images[start:start + batch]
        yield records, [read_rgb(Path(root) / r["file_name"]) for r in records]


def predict_coco(
    predictor: Predictor,
    dataset: dict[str, Any],
    root: Path,
    *,
    conf_thres: float = 0.001,
    iou_thres: float = 0.6,
    batch: int = 8,
    progress: bool = True,
    desc: str = "detect",
) -> list[dict[str, Any]]:
    """Detect on every image of a COCO dataset.

    Args:
        predictor: object with ``predict(images, conf_thres, iou_thres)`` returning per image
            ``{"boxes": (N, 4) xyxy px, "scores": (N,), "labels": (N,) category ids}``.
        dataset: COCO dict; ``file_name`` relative to ``root``.
        root: folder the image paths are relative to.

    Returns:
        COCO results ``[{image_id, category_id, bbox [x, y, w, h], score}]``.
    """
    results: list[dict[str, Any]] = []
    bar = tqdm(total=len(dataset["images"]), desc=desc, disable=not progress, unit="img")
    for records, images in iter_batches(dataset, root, batch):
        preds = predictor.predict(images, conf_thres=conf_thres, iou_thres=iou_thres)
        for record, pred in zip(records, preds):
            results.extend(to_coco_results(pred, record["id"]))
        bar.update(len(records))
    bar.close()
    return results


def to_coco_results(pred: dict[str, np.ndarray], image_id: int) -> list[dict[str, Any]]:
    """One image's ``{boxes xyxy, scores, labels}`` as COCO results (bbox as x, y, w, h)."""
    boxes = np.asarray(pred["boxes"], dtype=float).reshape(-1, 4)
    return [
        {"image_id": int(image_id), "category_id": int(label),
         "bbox": [float(x0), float(y0), float(x1 - x0), float(y1 - y0)], "score": float(score)}
        for (x0, y0, x1, y1), score, label in zip(boxes, pred["scores"], pred["labels"])
    ]
