"""Tiny fake real-data exports drawn at test time: a Roboflow-style COCO set and a YOLO-txt set.

Every image is 64x64 px. Each Roboflow image holds the same five boxes (``BOXES``): a crater, a
boulder, a 4 px tall rock (an ignore region after import), a rocky region (dropped by the
default map) and an artifact.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np

SIZE = 64  # px
ROBOFLOW_CATEGORIES = [
    {"id": 0, "name": "objects", "supercategory": "none"},
    {"id": 1, "name": "artifact", "supercategory": "objects"},
    {"id": 2, "name": "boulder", "supercategory": "objects"},
    {"id": 3, "name": "crater", "supercategory": "objects"},
    {"id": 4, "name": "rock", "supercategory": "objects"},
    {"id": 5, "name": "rocky region", "supercategory": "objects"},
    {"id": 6, "name": "rover path", "supercategory": "objects"},
]
BOXES = [  # (Roboflow category id, [x, y, w, h] px)
    (3, [10, 10, 20, 16]),  # crater -> crater
    (2, [40, 40, 10, 8]),  # boulder -> rock
    (4, [5, 50, 6, 4]),  # rock -> rock, under 6 px tall: ignore
    (5, [0, 30, 64, 20]),  # rocky region -> dropped
    (1, [30, 5, 12, 12]),  # artifact -> artifact
]
SPLITS = {  # split -> [(original frame name, augmented copies)]
    "train": [("PCAML-C-001_SCI_A_2C.png", 3), ("chang4_20190106033410.png", 3)],
    "valid": [("C3_TCAM_1_2C_001.png", 1), ("PCAML-Q-002_SCI_A_2A.png", 1)],
}


def _image(path: Path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), rng.integers(60, 200, (SIZE, SIZE, 3), dtype=np.uint8))


def roboflow_name(original: str, copy: int) -> str:
    """``<stem>_<ext>.rf.<hash>.jpg``, the way Roboflow names an exported image."""
    stem, ext = original.rsplit(".", 1)
    digest = hashlib.md5(f"{original}/{copy}".encode()).hexdigest()
    return f"{stem}_{ext}.rf.{digest}.jpg"


def _polygon(box: list[float]) -> list[list[float]]:
    x, y, w, h = box
    return [[x, y, x + w, y, x + w, y + h, x, y + h]]


def make_roboflow(root: Path, splits: dict[str, list[tuple[str, int]]] | None = None) -> Path:
    """Write ``root/<split>/_annotations.coco.json`` and the images; returns ``root``."""
    root = Path(root)
    for split, frames in (splits or SPLITS).items():
        images, anns = [], []
        for original, copies in frames:
            for k in range(copies):
                name = roboflow_name(original, k)
                _image(root / split / name, len(images))
                images.append({"id": len(images), "license": 1, "file_name": name,
                               "height": SIZE, "width": SIZE, "extra": {"name": original}})
                anns += [{"id": len(anns) + j + 1, "image_id": images[-1]["id"],
                          "category_id": cat, "bbox": box, "area": box[2] * box[3],
                          "segmentation": _polygon(box), "iscrowd": 0}
                         for j, (cat, box) in enumerate(BOXES)]
        coco = {"info": {"description": "fake Roboflow export"}, "licenses": [],
                "categories": ROBOFLOW_CATEGORIES, "images": images, "annotations": anns}
        (root / split / "_annotations.coco.json").write_text(json.dumps(coco))
    return root


def edit_coco(path: Path, edit) -> None:
    """Load a COCO file, apply ``edit(data)`` in place, write it back."""
    data = json.loads(Path(path).read_text())
    edit(data)
    Path(path).write_text(json.dumps(data))


YOLO_NAMES = ["boulder", "crater", "rover path", "artifact"]
YOLO_LINES = [
    "1 0.5 0.5 0.25 0.25",  # crater: [24, 24, 16, 16] px
    "0 0.25 0.25 0.125 0.125",  # boulder -> rock: [12, 12, 8, 8] px
    "2 0.5 0.9 1.0 0.1",  # rover path -> dropped
    "3 0.1 0.1 0.3 0.1 0.3 0.3 0.1 0.3",  # artifact polygon: [6.4, 6.4, 12.8, 12.8] px
]


def make_yolo(root: Path) -> Path:
    """Write a Roboflow-style YOLO export: ``data.yaml`` and ``<split>/{images,labels}``.

    train: two labelled images and one without a label file (background); valid: one image.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    (root / "data.yaml").write_text("train: ../train/images\nval: ../valid/images\n"
                                    f"nc: {len(YOLO_NAMES)}\nnames: {YOLO_NAMES}\n")
    layout = {"train": ["PCAML-C-003_A_2C.png", "chang4_20190107000000.png", "C3_TCAM_2_2C_009.png"],
              "valid": ["PCAML-Q-004_A_2A.png"]}
    for split, frames in layout.items():
        (root / split / "labels").mkdir(parents=True)
        for k, original in enumerate(frames):
            name = roboflow_name(original, 0)
            _image(root / split / "images" / name, k)
            if not (split == "train" and k == 2):
                stem = name.rsplit(".", 1)[0]
                (root / split / "labels" / f"{stem}.txt").write_text("\n".join(YOLO_LINES) + "\n")
    return root
