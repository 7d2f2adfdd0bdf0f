"""Letterbox resizing: keep the aspect ratio, pad to a square with gray (YOLO convention)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

PAD_VALUE = 114  # gray used for padding, as in the YOLO family


@dataclass(frozen=True)
class LetterboxInfo:
    """How an image was mapped into the network input: ``input = original * scale + pad``."""

    scale: float
    pad_x: float  # px
    pad_y: float  # px

    def to_original(self, boxes: np.ndarray, width: int, height: int) -> np.ndarray:
        """Map (N, 4) xyxy boxes from input pixels back to original pixels, clipped."""
        out = np.asarray(boxes, dtype=np.float32).reshape(-1, 4).copy()
        out[:, 0::2] = ((out[:, 0::2] - self.pad_x) / self.scale).clip(0, width)
        out[:, 1::2] = ((out[:, 1::2] - self.pad_y) / self.scale).clip(0, height)
        return out


def resize_long_side(image: np.ndarray, size: int) -> tuple[np.ndarray, float]:
    """Resize so the longer side is ``size`` px (area interpolation when shrinking).

    Shape:
        - image: :math:`(H, W, 3)`; Output: :math:`(H', W', 3)` with ``max(H', W') = size``.
    """
    scale = size / max(image.shape[:2])
    return _resize(image, scale), scale


def _resize(image: np.ndarray, scale: float) -> np.ndarray:
    """``image`` scaled by ``scale`` (area interpolation when shrinking; as it is at 1)."""
    if scale == 1.0:
        return image
    h, w = image.shape[:2]
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    return cv2.resize(image, (max(1, round(w * scale)), max(1, round(h * scale))),
                      interpolation=interp)


def letterbox(image: np.ndarray, size: int | tuple[int, int]
              ) -> tuple[np.ndarray, LetterboxInfo]:
    """Fit an image into a ``size`` x ``size`` square (or a ``(height, width)`` rectangle),
    centred, padded with gray.

    Shape:
        - image: :math:`(H, W, 3)` uint8; Output: :math:`(size, size, 3)` uint8.
    """
    out_h, out_w = size if isinstance(size, tuple) else (size, size)
    scale = min(out_h / image.shape[0], out_w / image.shape[1])  # a square: the longer side
    image = _resize(image, scale)
    new_h, new_w = image.shape[:2]
    pad_x, pad_y = (out_w - new_w) // 2, (out_h - new_h) // 2
    out = np.full((out_h, out_w, 3), PAD_VALUE, dtype=np.uint8)
    out[pad_y:pad_y + new_h, pad_x:pad_x + new_w] = image
    return out, LetterboxInfo(scale, float(pad_x), float(pad_y))
