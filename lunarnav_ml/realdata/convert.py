"""Shared conversion steps of the real-data importers: one split's images and boxes in our
COCO convention, with counts of what was mapped, dropped and skipped.

Bad input (a label without its image, a box outside its image, an unknown category) raises
``InputError`` naming the file and the item, unless ``skip_bad`` is set: then the item is
skipped and counted under its reason.
"""

from __future__ import annotations

import math
import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from PIL import Image, UnidentifiedImageError

from lunarnav_ml.data.coco import BOX_TOLERANCE_PX, CLASS_NAMES
from lunarnav_ml.errors import InputError
from lunarnav_ml.realdata.category_map import CategoryMap
from lunarnav_ml.realdata.sources import camera_for

MAX_EXAMPLES = 10  # skipped-item messages kept per split for the report


@dataclass
class SplitLabels:
    """One split converted to our convention, before it is written.

    Attributes:
        name: split name (the source folder's name: ``train``, ``valid``...).
        cmap: the category map in use.
        skip_bad: skip and count bad items instead of raising.
        images: our COCO image dicts plus ``path`` (absolute image file, dropped on writing).
        annotations: our COCO annotations (``image_id`` refers to ``images``), each with its
            ``source_category`` name; ``ignore`` when crowd or shorter than the map's minimum.
        images_in, annotations_in: entries read from the source.
        dropped: source name -> boxes dropped by the map.
        skipped: reason -> items skipped as bad input (``skip_bad``).
        examples: the first few skip messages.
    """

    name: str
    cmap: CategoryMap
    skip_bad: bool = False
    images: list[dict[str, Any]] = field(default_factory=list)
    annotations: list[dict[str, Any]] = field(default_factory=list)
    images_in: int = 0
    annotations_in: int = 0
    dropped: Counter = field(default_factory=Counter)
    skipped: Counter = field(default_factory=Counter)
    examples: list[str] = field(default_factory=list)

    def problem(self, reason: str, message: str) -> None:
        """Raise ``InputError(message)``, or with ``skip_bad`` count it under ``reason``."""
        if not self.skip_bad:
            raise InputError(message)
        self.skipped[reason] += 1
        if len(self.examples) < MAX_EXAMPLES:
            self.examples.append(message)

    def add_image(self, path: Path, width: int, height: int, source: str, source_file: str
                  ) -> dict[str, Any]:
        """Append an image record (ids run 1..N) and return it."""
        image = {"id": len(self.images) + 1, "path": Path(os.path.abspath(path)),
                 "width": int(width), "height": int(height), "source_name": source,
                 "source_file": source_file, "camera_name": camera_for(source)}
        self.images.append(image)
        return image

    def add_box(self, image: dict[str, Any], category: str, bbox: Any, where: str, *,
                iscrowd: bool = False, segmentation: Any = None) -> None:
        """Map, validate and append one source box ``[x, y, w, h]`` px of ``image``."""
        try:
            cat_id = self.cmap.target_id(category)
        except KeyError:
            self.problem("unmapped_category", f"{where}: category {category!r} is not in the "
                         f"category map {self.cmap.source} (its 'unmapped' policy is 'error')")
            return
        if cat_id is None:
            self.dropped[str(category)] += 1
            return
        box = self._checked_box(bbox, image, where)
        if box is None:
            return
        ignore = bool(iscrowd) or box[3] < self.cmap.ignore_height_below_px
        ann = {"id": len(self.annotations) + 1, "image_id": image["id"], "category_id": cat_id,
               "bbox": box, "area": box[2] * box[3], "iscrowd": int(ignore), "ignore": ignore,
               "source_category": str(category)}
        if segmentation:
            ann["segmentation"] = segmentation
        self.annotations.append(ann)

    def _checked_box(self, bbox: Any, image: dict[str, Any], where: str) -> list[float] | None:
        """The box clipped to its image, or ``None`` (counted) when it is bad."""
        if (not isinstance(bbox, (list, tuple)) or len(bbox) != 4
                or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in bbox)):
            self.problem("bad_box", f"{where}: bbox must be 4 finite numbers [x, y, w, h], "
                         f"got {bbox!r}")
            return None
        x, y, w, h = (float(v) for v in bbox)
        if w <= 0 or h <= 0:
            self.problem("bad_box", f"{where}: bbox {list(bbox)} has a non-positive size")
            return None
        width, height, tol = image["width"], image["height"], BOX_TOLERANCE_PX
        if x < -tol or y < -tol or x + w > width + tol or y + h > height + tol:
            self.problem("box_outside_image", f"{where}: bbox {[round(v, 3) for v in bbox]} "
                         f"lies outside its image ({width}x{height} px, {image['source_file']})")
            return None
        x0, y0, x1, y1 = max(x, 0.0), max(y, 0.0), min(x + w, width), min(y + h, height)
        return [x0, y0, x1 - x0, y1 - y0]

    def drop_images(self, image_ids: set[int], reason: str) -> None:
        """Remove images (counted under ``reason``) and their boxes; ids are renumbered."""
        self.skipped[reason] += len(image_ids)
        removed = [a for a in self.annotations if a["image_id"] in image_ids]
        self.skipped["annotation_of_skipped_image"] += len(removed)
        self.images = [i for i in self.images if i["id"] not in image_ids]
        self.annotations = [a for a in self.annotations if a["image_id"] not in image_ids]
        self._renumber()

    def _renumber(self) -> None:
        new_ids = {img["id"]: k for k, img in enumerate(self.images, start=1)}
        for img in self.images:
            img["id"] = new_ids[img["id"]]
        for k, ann in enumerate(self.annotations, start=1):
            ann["id"], ann["image_id"] = k, new_ids[ann["image_id"]]

    def to_coco(self, out_dir: Path) -> dict[str, Any]:
        """The split as a COCO dict whose ``file_name`` entries are relative to ``out_dir``
        and point at the original image files (nothing is copied)."""
        out_dir = os.path.abspath(out_dir)
        images = [{"id": img["id"], "file_name": os.path.relpath(img["path"], out_dir),
                   **{k: v for k, v in img.items() if k not in ("id", "path")}}
                  for img in self.images]
        return {"info": {"description": f"real labelled images, split {self.name}, imported by "
                         "lunarnav import-real"},
                "images": images, "annotations": self.annotations,
                "categories": [{"id": i, "name": n} for i, n in enumerate(CLASS_NAMES, start=1)]}


def image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) px read from the file's header, or ``None`` if it is not an image."""
    try:
        with Image.open(path) as im:
            return im.size
    except (UnidentifiedImageError, OSError):
        return None
