"""The detection dataset: COCO records -> letterboxed (optionally augmented) tensors."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from lunarnav_ml.data.augment import Boxes, apply_augment, build_augment, clip_boxes, mosaic
from lunarnav_ml.data.coco import ImageRecord, load_coco, read_image
from lunarnav_ml.data.letterbox import letterbox, resize_long_side
from lunarnav_ml.errors import InputError

Sample = tuple[torch.Tensor, dict[str, torch.Tensor], dict[str, Any]]


class CocoDetection(Dataset):
    """Images and boxes of one COCO file, letterboxed to ``img_size`` squares.

    Args:
        ann_file: COCO ``annotations.json`` (``file_name`` relative to its folder).
        img_size: network input side, px (multiple of 32).
        augment: apply the albumentations pipeline (training).
        mosaic_prob: probability that a sample is a 4-image mosaic (training).
        cache: keep decoded, resized images in memory.
        num_classes: category ids must lie in 1..num_classes.

    Each item is ``(image, target, meta)``: image :math:`(3, S, S)` uint8 RGB; target
    ``{"boxes": (N, 4) float32 xyxy input px, "labels": (N,) int64 ids 1..K, "ignore": (N,)
    bool}``; meta ``{"image_id", "scale", "pad": (x, y), "size": (h, w) original}``.
    """

    def __init__(self, ann_file: str | Path, img_size: int = 320, augment: bool = False,
                 mosaic_prob: float = 0.0, cache: bool = True, num_classes: int = 3) -> None:
        if img_size % 32:
            raise InputError(f"img_size must be a multiple of 32, got {img_size}")
        self.ann_file = Path(ann_file)
        self.records: list[ImageRecord] = load_coco(ann_file, num_classes)
        self.img_size = img_size
        self.augment = build_augment() if augment else None
        self.mosaic_prob = mosaic_prob if augment else 0.0
        self.cache = cache
        self._cache: dict[int, tuple[np.ndarray, float]] = {}

    def __len__(self) -> int:
        return len(self.records)

    def load_resized(self, index: int) -> tuple[np.ndarray, Boxes, float]:
        """Image resized to long side ``img_size`` and its boxes scaled alike."""
        if index in self._cache:
            image, scale = self._cache[index]
        else:
            image, scale = resize_long_side(read_image(self.records[index]), self.img_size)
            if self.cache:
                self._cache[index] = (image, scale)
        rec = self.records[index]
        return image, Boxes(rec.boxes * scale, rec.labels, rec.ignore), scale

    def __getitem__(self, index: int) -> Sample:
        seed = int(torch.randint(0, 2**31 - 1, (1,)))
        rng = np.random.default_rng(seed)
        rec = self.records[index]
        if self.mosaic_prob and rng.random() < self.mosaic_prob:
            image, boxes = self._mosaic(index, rng)
            meta = {"image_id": rec.image_id, "scale": 1.0, "pad": (0.0, 0.0),
                    "size": (rec.height, rec.width)}
        else:
            image, boxes, meta = self._letterboxed(index)
        if self.augment is not None:
            image, boxes = apply_augment(self.augment, image, boxes, seed)
        target = {"boxes": torch.from_numpy(boxes.boxes.astype(np.float32)).reshape(-1, 4),
                  "labels": torch.from_numpy(boxes.labels.astype(np.int64)),
                  "ignore": torch.from_numpy(boxes.ignore.astype(bool))}
        return torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1))), target, meta

    def _letterboxed(self, index: int) -> tuple[np.ndarray, Boxes, dict[str, Any]]:
        image, boxes, scale = self.load_resized(index)
        square, info = letterbox(image, self.img_size)
        shifted = boxes.boxes + np.array([info.pad_x, info.pad_y] * 2, np.float32)
        rec = self.records[index]
        meta = {"image_id": rec.image_id, "scale": scale, "pad": (info.pad_x, info.pad_y),
                "size": (rec.height, rec.width)}
        boxes = clip_boxes(Boxes(shifted, boxes.labels, boxes.ignore), self.img_size,
                           self.img_size, min_keep=0.0)
        return square, boxes, meta

    def _mosaic(self, index: int, rng: np.random.Generator) -> tuple[np.ndarray, Boxes]:
        others = rng.integers(0, len(self), 3)
        loaded = [self.load_resized(int(i)) for i in [index, *others]]
        return mosaic([x[0] for x in loaded], [x[1] for x in loaded], self.img_size, rng)


def collate(batch: list[Sample]) -> tuple[torch.Tensor, list[dict], list[dict]]:
    """Stack images; keep targets and metas as lists.

    Shape:
        - Output images: :math:`(B, 3, S, S)` uint8.
    """
    images, targets, metas = zip(*batch)
    return torch.stack(images), list(targets), list(metas)
