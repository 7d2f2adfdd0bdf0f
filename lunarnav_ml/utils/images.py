"""Image files: the suffixes we read, an RGB reader and a reader of a dataset image's
rendered disparity, with one-line errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from lunarnav_ml.errors import InputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def read_rgb(path: str | Path) -> np.ndarray:
    """Read an image file as HxWx3 uint8 RGB; grayscale is replicated to three channels."""
    if not Path(path).is_file():
        raise InputError(f"{path}: image file not found")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise InputError(f"{path}: not a readable image (corrupt or unknown format)")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_disparity(root: str | Path, image: dict) -> np.ndarray:
    """The rendered disparity (float64, px; 0 where nothing was hit) of a dataset image record.

    Non-finite pixels (invalid ones) are kept as they are; a map without a single finite
    value is rejected.

    Raises:
        InputError: the record has no ``disparity_file``, or the file is missing, unreadable,
            not numeric or holds no finite value.
    """
    rel = image.get("disparity_file")
    if not rel:
        raise InputError(f"images[{image.get('id')}]: no disparity_file (render with stereo)")
    path = Path(root) / rel
    try:
        disp = np.load(path).astype(np.float64)
    except (OSError, ValueError, EOFError, TypeError) as err:
        raise InputError(f"{path}: cannot read disparity ({err})") from None
    if not np.isfinite(disp).any():
        raise InputError(f"{path}: disparity has no finite value (all {disp.size} pixels are "
                         "NaN or infinite)")
    return disp


def caption_tile(image: np.ndarray, side: int, caption: str) -> np.ndarray:
    """Fit a BGR ``image`` into a ``side`` x ``side`` black tile with a caption strip on top."""
    strip = 18
    scale = min(side / image.shape[1], (side - strip) / image.shape[0])
    size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    canvas = np.zeros((side, side, 3), np.uint8)
    canvas[strip:strip + size[1], :size[0]] = small
    cv2.putText(canvas, caption, (3, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1,
                cv2.LINE_AA)
    return canvas


def contact_sheet(tiles: list[np.ndarray], cols: int = 4) -> np.ndarray:
    """Equal-sized tiles in a grid of ``cols`` columns (the last row padded with black)."""
    if not tiles:
        raise ValueError("contact_sheet needs at least one tile")
    tiles = tiles + [np.zeros_like(tiles[0])] * (-len(tiles) % cols)
    return np.vstack([np.hstack(tiles[i:i + cols]) for i in range(0, len(tiles), cols)])
