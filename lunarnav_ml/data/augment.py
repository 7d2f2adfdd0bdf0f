"""Box-aware augmentation: albumentations photometric + geometric transforms, and mosaic."""

from __future__ import annotations

from dataclasses import dataclass

import albumentations as A
import cv2
import numpy as np

from lunarnav_ml.data.letterbox import PAD_VALUE

MIN_BOX_PX = 2.0  # boxes thinner than this after augmentation are dropped


@dataclass
class Boxes:
    """Boxes travelling with an image through augmentation."""

    boxes: np.ndarray  # (N, 4) float32 xyxy px
    labels: np.ndarray  # (N,) int64 category ids
    ignore: np.ndarray  # (N,) bool

    def take(self, keep: np.ndarray) -> Boxes:
        """The subset selected by a boolean or index array."""
        return Boxes(self.boxes[keep], self.labels[keep], self.ignore[keep])

    @staticmethod
    def concat(parts: list[Boxes]) -> Boxes:
        """All boxes of several parts."""
        return Boxes(np.concatenate([p.boxes for p in parts]).astype(np.float32),
                     np.concatenate([p.labels for p in parts]),
                     np.concatenate([p.ignore for p in parts]))


def build_augment(flip_lr: float = 0.5, flip_ud: float = 0.0, exposure: float = 0.8,
                  noise: float = 0.3, blur: float = 0.2, affine: float = 0.5,
                  scale: tuple[float, float] = (0.7, 1.3)) -> A.Compose:
    """The training augmentation pipeline (probabilities per transform).

    Exposure covers brightness/contrast and gamma (sun elevation, camera gain); noise is
    Gaussian sensor noise; blur is defocus or motion; affine scales and shifts (boxes follow).
    Vertical flips are off by default: lunar scenes have a horizon and a sun direction.
    """
    return A.Compose(
        [
            A.HorizontalFlip(p=flip_lr),
            A.VerticalFlip(p=flip_ud),
            A.Affine(scale=scale, translate_percent=(-0.1, 0.1), border_mode=cv2.BORDER_CONSTANT,
                     fill=PAD_VALUE, p=affine),
            A.RandomBrightnessContrast(0.25, 0.3, p=exposure),
            A.RandomGamma(gamma_limit=(70, 150), p=exposure / 2),
            A.GaussNoise(std_range=(0.01, 0.06), p=noise),
            A.OneOf([A.GaussianBlur(blur_limit=(3, 5)), A.MotionBlur(blur_limit=(3, 7))], p=blur),
        ],
        bbox_params=A.BboxParams(format="pascal_voc", label_fields=["labels", "ignore"],
                                 min_visibility=0.4, clip=True, filter_invalid_bboxes=True),
    )


def apply_augment(aug: A.Compose, image: np.ndarray, boxes: Boxes, seed: int
                  ) -> tuple[np.ndarray, Boxes]:
    """Run an albumentations pipeline with a fixed seed on an image and its boxes."""
    aug.set_random_seed(seed)
    out = aug(image=image, bboxes=boxes.boxes, labels=boxes.labels, ignore=boxes.ignore)
    result = Boxes(np.asarray(out["bboxes"], dtype=np.float32).reshape(-1, 4),
                   np.asarray(out["labels"], dtype=np.int64).reshape(-1),
                   np.asarray(out["ignore"], dtype=bool).reshape(-1))
    return out["image"], drop_small(result)


def drop_small(boxes: Boxes, min_px: float = MIN_BOX_PX) -> Boxes:
    """Remove boxes narrower or shorter than ``min_px``."""
    wh = boxes.boxes[:, 2:] - boxes.boxes[:, :2]
    return boxes.take((wh >= min_px).all(axis=1))


def clip_boxes(boxes: Boxes, width: int, height: int, min_keep: float = 0.4,
               ignore_below: float = 0.0) -> Boxes:
    """Clip to the image; drop boxes keeping less than ``min_keep`` of their area, and turn
    those keeping less than ``ignore_below`` into ignore regions."""
    b = boxes.boxes.copy()
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    b[:, 0::2] = b[:, 0::2].clip(0, width)
    b[:, 1::2] = b[:, 1::2].clip(0, height)
    kept = (b[:, 2] - b[:, 0]).clip(0) * (b[:, 3] - b[:, 1]).clip(0)
    frac = kept / np.maximum(area, 1e-6)
    out = Boxes(b, boxes.labels, boxes.ignore | (frac < ignore_below)).take(frac >= min_keep)
    return drop_small(out)


def _paste(canvas: np.ndarray, img: np.ndarray, x0: int, y0: int) -> None:
    """Copy ``img`` onto ``canvas`` with its top-left corner at (x0, y0), cropping overhangs."""
    h, w = img.shape[:2]
    cx0, cy0 = max(x0, 0), max(y0, 0)
    cx1, cy1 = min(x0 + w, canvas.shape[1]), min(y0 + h, canvas.shape[0])
    if cx1 > cx0 and cy1 > cy0:
        canvas[cy0:cy1, cx0:cx1] = img[cy0 - y0:cy1 - y0, cx0 - x0:cx1 - x0]


def mosaic(images: list[np.ndarray], parts: list[Boxes], size: int, rng: np.random.Generator
           ) -> tuple[np.ndarray, Boxes]:
    """YOLOv4 mosaic: four images around a random centre of a 2x canvas, randomly rescaled and
    cropped to ``size`` x ``size``.

    Args:
        images: four HxWx3 uint8 images whose long side is at most ``size``.
        parts: their boxes (xyxy px).
        size: output side, px.
        rng: random generator.

    Returns:
        The ``size`` x ``size`` mosaic and its boxes.
    """
    canvas = np.full((2 * size, 2 * size, 3), PAD_VALUE, dtype=np.uint8)
    xc, yc = (int(v) for v in rng.uniform(0.5 * size, 1.5 * size, 2))
    placed = []
    for k, (img, part) in enumerate(zip(images, parts)):
        h, w = img.shape[:2]
        x0 = xc - w if k in (0, 2) else xc
        y0 = yc - h if k in (0, 1) else yc
        _paste(canvas, img, x0, y0)
        placed.append(Boxes(part.boxes + np.array([x0, y0, x0, y0], np.float32), part.labels,
                            part.ignore))
    zoom = rng.uniform(0.5, 1.0)
    side = max(size, round(2 * size * zoom))
    canvas = cv2.resize(canvas, (side, side), interpolation=cv2.INTER_AREA)
    ox, oy = (int(v) for v in rng.integers(0, side - size + 1, 2))
    merged = clip_boxes(Boxes.concat(placed), 2 * size, 2 * size)
    shift = np.array([ox, oy, ox, oy], np.float32)
    moved = Boxes(merged.boxes * (side / (2 * size)) - shift, merged.labels, merged.ignore)
    return canvas[oy:oy + size, ox:ox + size].copy(), clip_boxes(moved, size, size)
