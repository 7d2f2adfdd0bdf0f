"""Import YOLO-txt labels (one ``class cx cy w h`` line per box, normalised) as COCO JSON."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import cv2

from lunarnav_ml.data.coco import CLASS_NAMES
from lunarnav_ml.errors import InputError
from lunarnav_ml.utils import atomic

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def parse_yolo_line(line: str, where: str, class_map: dict[int, int]) -> tuple[int, list[float]]:
    """One label line -> (category id, normalised [cx, cy, w, h]).

    Raises:
        InputError: not five numbers, unknown class, values outside [0, 1] or a zero size.
    """
    parts = line.split()
    try:
        cls, values = int(parts[0]), [float(v) for v in parts[1:]]
    except (ValueError, IndexError) as err:
        raise InputError(f"{where}: expected 'class cx cy w h', got {line!r}") from err
    if len(values) != 4:
        raise InputError(f"{where}: expected 'class cx cy w h', got {line!r}")
    if cls not in class_map:
        raise InputError(f"{where}: unknown class {cls} (known: {sorted(class_map)})")
    cx, cy, w, h = values
    if not (0 <= cx <= 1 and 0 <= cy <= 1 and 0 < w <= 1 and 0 < h <= 1):
        raise InputError(f"{where}: normalised box {values} outside [0, 1] or of zero size")
    return class_map[cls], values


def import_yolo_txt(images_dir: str | Path, labels_dir: str | Path, out_json: str | Path,
                    class_map: dict[int, int] | None = None) -> Path:
    """Write a COCO detection file for a YOLO-txt dataset.

    Args:
        images_dir: folder of images; ``file_name`` entries are written relative to the folder
            holding ``out_json``.
        labels_dir: folder of ``<stem>.txt`` label files (a missing file: no objects).
        out_json: COCO file to write.
        class_map: YOLO class index -> category id (default ``{0: 1, 1: 2, 2: 3}``).

    Returns:
        ``out_json``.
    """
    class_map = class_map or {i: i + 1 for i in range(len(CLASS_NAMES))}
    images_dir, labels_dir, out_json = Path(images_dir), Path(labels_dir), Path(out_json)
    files = sorted(p for p in images_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) \
        if images_dir.is_dir() else []
    if not files:
        raise InputError(f"{images_dir}: no images found")
    images: list[dict[str, Any]] = []
    anns: list[dict[str, Any]] = []
    for image_id, path in enumerate(files, start=1):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise InputError(f"{path}: corrupt or unreadable image")
        h, w = image.shape[:2]
        rel = os.path.relpath(path.resolve(), out_json.parent.resolve())
        images.append({"id": image_id, "file_name": rel, "width": w, "height": h})
        anns += _image_annotations(labels_dir / f"{path.stem}.txt", image_id, w, h, class_map,
                                   len(anns))
    cats = [{"id": cid, "name": CLASS_NAMES[cid - 1] if cid <= len(CLASS_NAMES) else str(cid)}
            for cid in sorted(set(class_map.values()))]
    atomic.write_json(out_json, {"images": images, "annotations": anns, "categories": cats})
    return out_json


def _image_annotations(label_file: Path, image_id: int, w: int, h: int,
                       class_map: dict[int, int], first_id: int) -> list[dict[str, Any]]:
    if not label_file.is_file():
        return []
    anns = []
    for n, line in enumerate(label_file.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        cat, (cx, cy, bw, bh) = parse_yolo_line(line, f"{label_file}:{n}", class_map)
        x0, y0 = max(0.0, (cx - bw / 2) * w), max(0.0, (cy - bh / 2) * h)
        x1, y1 = min(float(w), (cx + bw / 2) * w), min(float(h), (cy + bh / 2) * h)
        anns.append({"id": first_id + len(anns) + 1, "image_id": image_id, "category_id": cat,
                     "bbox": [x0, y0, x1 - x0, y1 - y0], "area": (x1 - x0) * (y1 - y0),
                     "iscrowd": 0, "ignore": False})
    return anns
