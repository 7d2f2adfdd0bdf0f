"""The detection dataset: COCO records -> letterboxed (optionally augmented) tensors."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from lunarnav_ml.data.augment import Boxes, apply_augment, build_augment, clip_boxes, mosaic
from lunarnav_ml.data.coco import ImageRecord, load_coco, read_image
from lunarnav_ml.data.letterbox import PAD_VALUE, letterbox, resize_long_side
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
        read_size: training only: frames are resized to this long side (instead of
            ``img_size``) and a random ``img_size`` square is cropped from them, centred near a
            random labelled box (:func:`crop_around_box`). The network then learns objects at
            the scale of a frame read at ``read_size`` (e.g. far craters in full-resolution
            1024 px frames) for the cost of an ``img_size`` input. None or ``img_size``:
            the whole frame is letterboxed.

    Each item is ``(image, target, meta)``: image :math:`(3, S, S)` uint8 RGB; target
    ``{"boxes": (N, 4) float32 xyxy input px, "labels": (N,) int64 ids 1..K, "ignore": (N,)
    bool}``; meta ``{"image_id", "scale", "pad": (x, y), "size": (h, w) original}``.
    """

    def __init__(self, ann_file: str | Path, img_size: int = 320, augment: bool = False,
                 mosaic_prob: float = 0.0, cache: bool = True, num_classes: int = 3,
                 read_size: int | None = None) -> None:
        if isinstance(img_size, bool) or not isinstance(img_size, int) or img_size <= 0 \
                or img_size % 32:
            raise InputError(f"img_size must be a positive multiple of 32, got {img_size!r}")
        if read_size is not None and read_size < img_size:
            raise InputError(f"read_size ({read_size}) must be at least img_size ({img_size})")
        self.ann_file = Path(ann_file)
        self.records: list[ImageRecord] = load_coco(ann_file, num_classes)
        self.img_size = img_size
        self.read_size = img_size if (read_size is None or not augment) else read_size
        self.augment = build_augment() if augment else None
        self.mosaic_prob = mosaic_prob if augment else 0.0
        self.cache = cache
        self._cache: dict[int, tuple[np.ndarray, float]] = {}

    def __len__(self) -> int:
        return len(self.records)

    def preload(self, threads: int = 4) -> None:
        """Decode and resize every image into the cache now, ``threads`` at a time.

        Loader workers forked afterwards share the decoded images; left to fill itself, each
        worker's cache holds only what that worker has drawn, so with many workers most
        samples of the first epochs are decoded again.
        """
        if not self.cache:
            return
        todo = [i for i in range(len(self)) if i not in self._cache]
        with ThreadPoolExecutor(max(1, threads)) as pool:  # cv2 releases the GIL
            for i, item in zip(todo, pool.map(self._decode, todo)):
                self._cache[i] = item

    def _decode(self, index: int) -> tuple[np.ndarray, float]:
        return resize_long_side(read_image(self.records[index]), self.read_size)

    def load_resized(self, index: int) -> tuple[np.ndarray, Boxes, float]:
        """Image resized to long side ``read_size`` (``img_size`` unless cropping) and its
        boxes scaled alike."""
        if index in self._cache:
            image, scale = self._cache[index]
        else:
            image, scale = self._decode(index)
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
        elif self.read_size > self.img_size:
            image, boxes, scale = self.load_resized(index)
            image, boxes, origin = crop_around_box(image, boxes, self.img_size, rng)
            meta = {"image_id": rec.image_id, "scale": scale, "pad": (-origin[0], -origin[1]),
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


def crop_around_box(image: np.ndarray, boxes: Boxes, size: int, rng: np.random.Generator,
                    p_box: float = 0.8, min_visible: float = 0.9
                    ) -> tuple[np.ndarray, Boxes, tuple[int, int]]:
    """A ``size`` square from a larger image: with probability ``p_box`` placed uniformly among
    the squares holding the centre of a random non-ignored box, else anywhere. Boxes the
    square cuts to less than ``min_visible`` of their area become ignore regions (a part of a
    crater is neither a crater to find nor background to learn).

    Returns:
        The crop (padded with gray where the image is smaller than ``size``), its boxes, and
        its top-left corner (x, y) in the image, px.
    """
    h, w = image.shape[:2]
    live = np.flatnonzero(~boxes.ignore)
    if len(live) and rng.random() < p_box:
        b = boxes.boxes[live[rng.integers(len(live))]]
        x0 = _origin_holding(0.5 * (b[0] + b[2]), w, size, rng)
        y0 = _origin_holding(0.5 * (b[1] + b[3]), h, size, rng)
    else:
        x0 = int(rng.integers(0, max(w - size, 0) + 1))
        y0 = int(rng.integers(0, max(h - size, 0) + 1))
    out = np.full((size, size, 3), PAD_VALUE, dtype=np.uint8)
    part = image[y0:y0 + size, x0:x0 + size]
    out[:part.shape[0], :part.shape[1]] = part
    moved = Boxes(boxes.boxes - np.array([x0, y0, x0, y0], np.float32), boxes.labels,
                  boxes.ignore)
    return out, clip_boxes(moved, part.shape[1], part.shape[0], min_keep=0.0,
                           ignore_below=min_visible), (x0, y0)


def _origin_holding(c: float, extent: int, size: int, rng: np.random.Generator) -> int:
    """A uniform start in [0, extent - size] of a ``size`` window that holds coordinate ``c``
    (the nearest start where the extent allows no such window)."""
    lo, hi = max(0.0, c - size + 1), min(c, extent - size)
    start = rng.uniform(lo, hi) if hi > lo else min(c - size / 2, extent - size)
    return max(int(start), 0)


def collate(batch: list[Sample]) -> tuple[torch.Tensor, list[dict], list[dict]]:
    """Stack images; keep targets and metas as lists.

    Shape:
        - Output images: :math:`(B, 3, S, S)` uint8.
    """
    images, targets, metas = zip(*batch)
    return torch.stack(images), list(targets), list(metas)
