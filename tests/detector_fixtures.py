"""A tiny synthetic COCO dataset for detector tests, drawn with OpenCV at test time.

Craters: dark elliptical floors with a bright rim arc on the sunlit side; rocks: small bright
discs with a dark shadow; artifacts: bright rectangles. Backgrounds: gray with noise.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

CATEGORIES = [{"id": 1, "name": "crater"}, {"id": 2, "name": "rock"},
              {"id": 3, "name": "artifact"}]


def _draw_crater(img: np.ndarray, rng: np.random.Generator, size: int) -> list[float]:
    a = rng.uniform(0.06, 0.16) * size
    b = a * rng.uniform(0.5, 0.9)
    cx, cy = rng.uniform(a + 1, size - a - 1), rng.uniform(b + 1, size - b - 1)
    center, axes = (int(cx), int(cy)), (int(a), int(b))
    cv2.ellipse(img, center, axes, 0, 0, 360, int(rng.integers(40, 70)), -1)
    cv2.ellipse(img, center, axes, 0, 180, 360, int(rng.integers(190, 235)), max(1, int(a / 6)))
    return [center[0] - axes[0], center[1] - axes[1], 2 * axes[0], 2 * axes[1]]


def _draw_rock(img: np.ndarray, rng: np.random.Generator, size: int) -> list[float]:
    r = int(rng.uniform(0.02, 0.05) * size) + 2
    cx, cy = int(rng.uniform(r + 2, size - 2 * r - 2)), int(rng.uniform(r + 2, size - r - 2))
    cv2.ellipse(img, (cx + r // 2, cy), (r, max(1, r // 2)), 0, 0, 360, 25, -1)
    cv2.circle(img, (cx, cy), r, 215, -1)
    return [cx - r, cy - r, 2 * r + r // 2 + 1, 2 * r]


def _draw_artifact(img: np.ndarray, rng: np.random.Generator, size: int) -> list[float]:
    w, h = (int(v) for v in rng.uniform(0.08, 0.18, 2) * size)
    x, y = int(rng.uniform(1, size - w - 1)), int(rng.uniform(1, size - h - 1))
    cv2.rectangle(img, (x, y), (x + w, y + h), 250, -1)
    cv2.rectangle(img, (x + w // 4, y + h // 4), (x + 3 * w // 4, y + 3 * h // 4), 140, -1)
    return [x, y, w + 1, h + 1]


def make_coco(root: Path, n_images: int = 8, size: int = 96, seed: int = 0,
              per_image: int = 3, with_ignore: bool = True) -> Path:
    """Write ``root/annotations.json`` and ``root/images/left/*.png`` (8-bit grayscale).

    Returns:
        Path of the annotations file.
    """
    rng = np.random.default_rng(seed)
    root = Path(root)
    (root / "images" / "left").mkdir(parents=True, exist_ok=True)
    images, anns = [], []
    drawers = [(1, _draw_crater), (1, _draw_crater), (2, _draw_rock), (3, _draw_artifact)]
    for i in range(n_images):
        img = np.clip(rng.normal(120, 12, (size, size)), 0, 255).astype(np.uint8)
        for j in range(per_image):
            cat, draw = drawers[int(rng.integers(len(drawers)))]
            x, y, w, h = (float(v) for v in draw(img, rng, size))
            ignore = with_ignore and j == per_image - 1 and i % 4 == 3
            anns.append({"id": len(anns) + 1, "image_id": i + 1, "category_id": cat,
                         "bbox": [x, y, w, h], "area": w * h, "ignore": ignore,
                         "iscrowd": int(ignore)})
        name = f"images/left/{i:04d}.png"
        cv2.imwrite(str(root / name), img)
        images.append({"id": i + 1, "file_name": name, "width": size, "height": size})
    path = root / "annotations.json"
    path.write_text(json.dumps({"images": images, "annotations": anns,
                                "categories": CATEGORIES}))
    return path


class FakeSidedDetector:
    """A stand-in predictor at its own side 96 that records each side it runs at and raises at
    ``fail_at``; subclasses give ``detect(images)``, the output at ``self.img_size``."""

    strides = (8, 16, 32)
    class_names = ("crater", "rock", "artifact")

    def __init__(self, fail_at: int | None = None) -> None:
        self.img_size, self.sides_run, self.fail_at = 96, [], fail_at

    def set_img_size(self, side: int) -> None:
        self.img_size = side

    def predict(self, images, conf_thres=0.001, iou_thres=0.6, max_det=300):
        self.sides_run.append(self.img_size)
        if self.img_size == self.fail_at:
            raise RuntimeError("boom")
        return self.detect(images)

    def detect(self, images):
        raise NotImplementedError
