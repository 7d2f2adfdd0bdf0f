"""Run any detector with a ``predict(images)`` method over a COCO dataset -> COCO results."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from tqdm import tqdm

from lunarnav_ml.errors import InputError
from lunarnav_ml.utils.images import read_rgb
from lunarnav_ml.utils.jsonfile import read_json_file


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
    origin: str | None = None,
) -> list[dict[str, Any]]:
    """Detect on every image of a COCO dataset.

    A second read of a band over the camera's horizon (``--small-read-horizon``, a
    :class:`~lunarnav_ml.eval.smallread.SmallBoxReadPredictor` in ``predictor``) reads each
    image's own ``camera`` record: the images run in groups of one camera each, the results
    come back in the dataset's image order.

    Args:
        predictor: object with ``predict(images, conf_thres, iou_thres)`` returning per image
            ``{"boxes": (N, 4) xyxy px, "scores": (N,), "labels": (N,) category ids}``.
        dataset: COCO dict; ``file_name`` relative to ``root``.
        root: folder the image paths are relative to.
        origin: the dataset's file, for errors (default ``root``).

    Returns:
        COCO results ``[{image_id, category_id, bbox [x, y, w, h], score}]``.

    Raises:
        InputError: a band over the horizon and an image without a valid camera record.
    """
    from lunarnav_ml.eval.smallread import small_reader

    reader = small_reader(predictor)
    if reader is None or reader.config.horizon is None:
        groups = [(None, dataset["images"])]
    else:
        groups = camera_groups(dataset, origin or str(root))
    per_image: dict[int, list[dict[str, Any]]] = {}
    bar = tqdm(total=len(dataset["images"]), desc=desc, disable=not progress, unit="img")
    for camera, records_of_camera in groups:
        if camera is not None:
            reader.camera = camera
        for records, images in iter_batches({"images": records_of_camera}, root, batch):
            preds = predictor.predict(images, conf_thres=conf_thres, iou_thres=iou_thres)
            for record, pred in zip(records, preds):
                per_image[id(record)] = to_coco_results(pred, record["id"])
            bar.update(len(records))
    bar.close()
    return [r for record in dataset["images"] for r in per_image[id(record)]]


def camera_groups(dataset: dict[str, Any], origin: str
                  ) -> list[tuple[dict[str, float], list[dict[str, Any]]]]:
    """The dataset's image records grouped by their ``camera`` record's values
    (:func:`~lunarnav_ml.geometry.frames.camera_values`), groups in the order first seen.

    Raises:
        InputError: an image without a camera record, or with a bad one, naming ``origin`` and
            the image.
    """
    from lunarnav_ml.geometry.frames import camera_values

    groups: dict[tuple, tuple[dict[str, float], list[dict[str, Any]]]] = {}
    for record in dataset["images"]:
        where = f"{origin}: image {record.get('id')} ({record.get('file_name')})"
        if "camera" not in record:
            raise InputError(f"{where} has no camera record to read --small-read-horizon "
                             f"against: give the rows as --small-read-band TOP BOTTOM")
        try:
            values = camera_values(record["camera"])
        except InputError as err:
            raise InputError(f"{where}: {err}") from None
        groups.setdefault(tuple(sorted(values.items())), (values, []))[1].append(record)
    return list(groups.values())


def check_coco_results(results: Any, origin: str) -> list[dict[str, Any]]:
    """COCO results as the evaluations read them: a list of objects, each with an integer
    ``image_id`` and ``category_id``, a ``bbox`` of 4 finite numbers [x, y, w, h] with w, h >= 0
    and a finite ``score`` (1 when absent: a missing score is filled in as 1.0); ``InputError``
    naming ``origin``, the entry and the field otherwise.

    Returns:
        ``results``, the same list, with ``"score": 1.0`` set on the entries that had none.
    """
    if not isinstance(results, list):
        raise InputError(f"{origin}: expected a list of COCO results, got {type(results).__name__}")
    for k, det in enumerate(results):
        where = f"{origin}[{k}]"
        if not isinstance(det, dict):
            raise InputError(f"{where}: expected an object, got {type(det).__name__}")
        for key in ("image_id", "category_id"):
            if isinstance(det.get(key), bool) or not isinstance(det.get(key), int):
                raise InputError(f"{where}: {key} must be an integer, got {det.get(key)!r}")
        box = det.get("bbox")
        if not isinstance(box, list) or len(box) != 4 or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)
                for v in box):
            raise InputError(f"{where}: bbox must be 4 finite numbers [x, y, w, h], got {box!r}")
        if box[2] < 0 or box[3] < 0:
            raise InputError(f"{where}: bbox {box} has a negative width or height")
        score = det.get("score", 1.0)
        if isinstance(score, bool) or not isinstance(score, (int, float)) or not np.isfinite(score):
            raise InputError(f"{where}: score must be a finite number, got {score!r}")
        det.setdefault("score", 1.0)
    return results


def read_coco_results(path: str | Path) -> list[dict[str, Any]]:
    """A COCO results file, read and checked (:func:`check_coco_results`); one-line
    ``InputError`` naming the file when it is missing, not JSON or malformed."""
    origin = f"{path}: detections"
    return check_coco_results(read_json_file(path, "detections", expect=list), origin)


def coco_results(preds: list[dict[str, np.ndarray]], image_ids: list[int]) -> list[dict[str, Any]]:
    """Several images' predictions as COCO results (:func:`to_coco_results` each)."""
    if len(preds) != len(image_ids):
        raise InputError(f"{len(preds)} predictions for {len(image_ids)} image ids")
    return [r for pred, image_id in zip(preds, image_ids) for r in to_coco_results(pred, image_id)]


def to_coco_results(pred: dict[str, np.ndarray], image_id: int) -> list[dict[str, Any]]:
    """One image's ``{boxes xyxy, scores, labels}`` as COCO results (bbox as x, y, w, h);
    with a ``box_refined`` mask (a ``BoxRefinedDetector``'s), those results carry
    ``"box_refined": true``."""
    boxes = np.asarray(pred["boxes"], dtype=float).reshape(-1, 4)
    results = [
        {"image_id": int(image_id), "category_id": int(label),
         "bbox": [float(x0), float(y0), float(x1 - x0), float(y1 - y0)], "score": float(score)}
        for (x0, y0, x1, y1), score, label in zip(boxes, pred["scores"], pred["labels"])
    ]
    for result, refined in zip(results, pred.get("box_refined", ())):
        if refined:
            result["box_refined"] = True
    return results
