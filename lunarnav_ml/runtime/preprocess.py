"""Image checks, letterbox resize and normalization for the onboard runtime (numpy + OpenCV).

Letterbox (the rule of ``lunarnav_ml.data.letterbox``, which training and ``Detector.predict``
use): scale the image by ``r = min(H_in / h, W_in / w)`` (aspect kept) with area interpolation
when shrinking and bilinear when enlarging, and pad it centred to the network input size with
gray 114. A box in network pixels maps back to the original image as ``x = (x_in - pad_x) / r``.
The rule is restated here, not imported, so the runtime never loads the training packages.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from lunarnav_ml.errors import InputError


@dataclass(frozen=True)
class Letterbox:
    """Where an image of ``shape`` (h, w) went inside the network input.

    Attributes:
        scale: resize factor r (network px per image px).
        pad_x, pad_y: left and top padding, network px.
        shape: (h, w) of the original image, px.
    """

    scale: float
    pad_x: int
    pad_y: int
    shape: tuple[int, int]

    def boxes_to_image(self, boxes: np.ndarray) -> np.ndarray:
        """Map xyxy boxes from network pixels back to the original image, clipped to it.

        Shape:
            boxes: (N, 4) -> (N, 4) float32.
        """
        offset = np.array([self.pad_x, self.pad_y, self.pad_x, self.pad_y], dtype=np.float32)
        out = (np.asarray(boxes, dtype=np.float32).reshape(-1, 4) - offset) / self.scale
        h, w = self.shape
        out[:, 0::2] = out[:, 0::2].clip(0, w)
        out[:, 1::2] = out[:, 1::2].clip(0, h)
        return out


def check_image(image: object, index: int = 0) -> np.ndarray:
    """Check one input image: an HxWx3 uint8 RGB array.

    Raises:
        InputError: not an array, wrong dtype, rank or channel count, or empty; the message
            names the image's index in the list and what was expected.
    """
    if not isinstance(image, np.ndarray):
        raise InputError(f"images[{index}]: expected a numpy array HxWx3 uint8 RGB, "
                         f"got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise InputError(f"images[{index}]: expected dtype uint8 (0..255 RGB), got {image.dtype}")
    if image.ndim != 3:
        raise InputError(f"images[{index}]: expected shape (H, W, 3), got {image.shape}")
    if image.shape[2] != 3:
        raise InputError(f"images[{index}]: expected 3 channels (RGB), got {image.shape[2]} "
                         f"in shape {image.shape}")
    if image.shape[0] < 1 or image.shape[1] < 1:
        raise InputError(f"images[{index}]: empty image of shape {image.shape}")
    return image


def check_images(images: object) -> list[np.ndarray]:
    """Check a list of images (see :func:`check_image`)."""
    if isinstance(images, np.ndarray) or not isinstance(images, Sequence):
        raise InputError(f"images: expected a list of HxWx3 uint8 arrays, "
                         f"got {type(images).__name__}")
    return [check_image(im, i) for i, im in enumerate(images)]


def letterbox(image: np.ndarray, size: tuple[int, int], pad_value: int = 114
              ) -> tuple[np.ndarray, Letterbox]:
    """Resize ``image`` into a ``size`` (H, W) canvas keeping its aspect ratio.

    Args:
        image: (h, w, 3) uint8.
        size: network input (H, W) px.
        pad_value: gray level of the border.

    Returns:
        The (H, W, 3) uint8 canvas and the :class:`Letterbox` that maps boxes back.
    """
    h, w = image.shape[:2]
    out_h, out_w = size
    r = min(out_h / h, out_w / w)
    new_w, new_h = max(1, round(w * r)), max(1, round(h * r))
    if r != 1.0:
        interp = cv2.INTER_AREA if r < 1.0 else cv2.INTER_LINEAR
        image = cv2.resize(image, (new_w, new_h), interpolation=interp)
    pad_x, pad_y = (out_w - new_w) // 2, (out_h - new_h) // 2
    canvas = np.full((out_h, out_w, 3), pad_value, dtype=np.uint8)
    canvas[pad_y:pad_y + new_h, pad_x:pad_x + new_w] = image
    return canvas, Letterbox(r, pad_x, pad_y, (h, w))


def to_input(canvases: Sequence[np.ndarray], mean: Sequence[float] = (0.0, 0.0, 0.0),
             std: Sequence[float] = (1.0, 1.0, 1.0)) -> np.ndarray:
    """Stack letterboxed uint8 canvases into the network's float32 input.

    Shape:
        canvases: each (H, W, 3) uint8 RGB -> (B, 3, H, W) float32,
        ``(pixel / 255 - mean) / std``.
    """
    batch = np.stack(canvases).astype(np.float32) * np.float32(1.0 / 255.0)
    if any(mean) or any(s != 1.0 for s in std):
        batch = (batch - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
    return np.ascontiguousarray(batch.transpose(0, 3, 1, 2))


def prepare_batch(images: Sequence[np.ndarray], size: tuple[int, int], pad_value: int = 114,
                  mean: Sequence[float] = (0.0, 0.0, 0.0), std: Sequence[float] = (1.0, 1.0, 1.0)
                  ) -> tuple[np.ndarray, list[Letterbox]]:
    """Check, letterbox and normalize a list of RGB images.

    Returns:
        (B, 3, H, W) float32 input and one :class:`Letterbox` per image.
    """
    checked = check_images(images)
    boxed = [letterbox(im, size, pad_value) for im in checked]
    return to_input([c for c, _ in boxed], mean, std), [lb for _, lb in boxed]
