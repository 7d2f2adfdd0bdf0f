"""Loading and validating COCO detection files (DESIGN.md "Labels").

Every problem is an ``InputError`` naming the file and the image or annotation at fault:
a missing or corrupt image, a box outside its image, an unknown category, an empty dataset.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from lunarnav_ml.errors import InputError
from lunarnav_ml.utils.jsonfile import read_json_file

CLASS_NAMES = ("crater", "rock", "artifact")  # category ids 1, 2, 3
BOX_TOLERANCE_PX = 1.0  # a box may overhang its image by this much (rounding), no more


def default_class_names(num_classes: int) -> list[str]:
    """Names of category ids 1..K when none are given: ours, then ``class<k>`` beyond them."""
    return [CLASS_NAMES[k] if k < len(CLASS_NAMES) else f"class{k + 1}"
            for k in range(num_classes)]


@dataclass
class ImageRecord:
    """One image and its boxes, validated."""

    image_id: int
    path: Path  # absolute image path
    width: int  # px
    height: int  # px
    boxes: np.ndarray  # (N, 4) float32 xyxy px, clipped to the image
    labels: np.ndarray  # (N,) int64 category ids 1..K
    ignore: np.ndarray  # (N,) bool: ignore region (``ignore: true`` or ``iscrowd: 1``)


def read_json(path: Path) -> dict[str, Any]:
    """Read a COCO JSON file, raising ``InputError`` if it is missing or not valid JSON."""
    data = read_json_file(path, "annotation", expect=dict)
    for key in ("images", "annotations", "categories"):
        if not isinstance(data.get(key), list):
            raise InputError(f"{path}: missing the '{key}' list")
    return data


def load_coco(path: Path | str, num_classes: int = 3, check_files: bool = True
              ) -> list[ImageRecord]:
    """Load a COCO detection file into validated per-image records.

    Args:
        path: ``annotations.json``; ``file_name`` entries are relative to its folder.
        num_classes: category ids must lie in 1..num_classes.
        check_files: raise if an image file does not exist.

    Returns:
        One record per image, in file order.
    """
    return read_coco(path, num_classes, check_files)[1]


def read_coco(path: Path | str, num_classes: int = 3, check_files: bool = True
              ) -> tuple[dict[str, Any], list[ImageRecord]]:
    """Read a COCO detection file once: the raw dict and its validated per-image records
    (arguments and errors as :func:`load_coco`)."""
    path = Path(path)
    data = read_json(path)
    if not data["images"]:
        raise InputError(f"{path}: the dataset has no images")
    cat_ids = _category_ids(path, data["categories"], num_classes)
    images = _image_table(path, data["images"], check_files)
    per_image: dict[int, list[tuple[list[float], int, bool]]] = {i: [] for i in images}
    for k, ann in enumerate(data["annotations"]):
        image_id, box, cat, ignore = _annotation(path, k, ann, images, cat_ids)
        per_image[image_id].append((box, cat, ignore))
    return data, [_record(images[i], per_image[i]) for i in images]


def _category_ids(path: Path, categories: list[dict], num_classes: int) -> set[int]:
    ids = set()
    for cat in categories:
        cid = cat.get("id") if isinstance(cat, dict) else None
        if not isinstance(cid, int) or not 1 <= cid <= num_classes:
            raise InputError(f"{path}: category {cat!r} must have an integer id in "
                             f"1..{num_classes} ({', '.join(CLASS_NAMES[:num_classes])})")
        ids.add(cid)
    return ids


def _image_table(path: Path, images: list[dict], check_files: bool) -> dict[int, dict]:
    table: dict[int, dict] = {}
    for k, img in enumerate(images):
        if not isinstance(img, dict) or not all(key in img for key in ("id", "file_name")):
            raise InputError(f"{path}: images[{k}] needs 'id' and 'file_name'")
        for key in ("width", "height"):
            if not isinstance(img.get(key), int) or img[key] <= 0:
                raise InputError(f"{path}: images[{k}] (id {img['id']}) needs a positive "
                                 f"integer '{key}', got {img.get(key)!r}")
        if img["id"] in table:
            raise InputError(f"{path}: images[{k}] repeats image id {img['id']}")
        file = path.parent / img["file_name"]
        if check_files and not file.is_file():
            raise InputError(f"{path}: image id {img['id']}: file {file} not found")
        table[img["id"]] = {**img, "path": file}
    return table


def _annotation(path: Path, k: int, ann: dict, images: dict[int, dict], cat_ids: set[int]
                ) -> tuple[int, list[float], int, bool]:
    where = f"{path}: annotations[{k}] (id {ann.get('id')})"
    image_id = ann.get("image_id")
    if image_id not in images:
        raise InputError(f"{where}: unknown image_id {image_id!r}")
    if ann.get("category_id") not in cat_ids:
        raise InputError(f"{where}: unknown category_id {ann.get('category_id')!r} "
                         f"(categories: {sorted(cat_ids)})")
    bbox = ann.get("bbox")
    if (not isinstance(bbox, list) or len(bbox) != 4
            or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in bbox)):
        raise InputError(f"{where}: bbox must be 4 finite numbers [x, y, w, h], got {bbox!r}")
    x, y, w, h = (float(v) for v in bbox)
    img = images[image_id]
    if w <= 0 or h <= 0:
        raise InputError(f"{where}: bbox {bbox} has non-positive width or height")
    tol = BOX_TOLERANCE_PX
    if x < -tol or y < -tol or x + w > img["width"] + tol or y + h > img["height"] + tol:
        raise InputError(f"{where}: bbox {bbox} lies outside image {image_id} "
                         f"({img['width']}x{img['height']} px, {img['file_name']})")
    ignore = bool(ann.get("ignore", False)) or bool(ann.get("iscrowd", 0))
    return image_id, [x, y, x + w, y + h], int(ann["category_id"]), ignore


def _record(img: dict, anns: list[tuple[list[float], int, bool]]) -> ImageRecord:
    boxes = np.array([a[0] for a in anns], dtype=np.float32).reshape(-1, 4)
    boxes[:, 0::2] = boxes[:, 0::2].clip(0, img["width"])
    boxes[:, 1::2] = boxes[:, 1::2].clip(0, img["height"])
    return ImageRecord(
        image_id=img["id"], path=img["path"], width=img["width"], height=img["height"],
        boxes=boxes, labels=np.array([a[1] for a in anns], dtype=np.int64),
        ignore=np.array([a[2] for a in anns], dtype=bool),
    )


def read_image(record: ImageRecord) -> np.ndarray:
    """Read a record's image as HxWx3 uint8 RGB (grayscale is replicated to three channels).

    Raises:
        InputError: the file is missing, unreadable, or not the size the annotations say.
    """
    if not record.path.is_file():
        raise InputError(f"{record.path}: image file not found (image id {record.image_id})")
    image = cv2.imread(str(record.path), cv2.IMREAD_COLOR)
    if image is None:
        raise InputError(f"{record.path}: corrupt or unreadable image (image id "
                         f"{record.image_id})")
    if image.shape[:2] != (record.height, record.width):
        raise InputError(f"{record.path}: image is {image.shape[1]}x{image.shape[0]} px but the "
                         f"annotations say {record.width}x{record.height} (image id "
                         f"{record.image_id})")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
