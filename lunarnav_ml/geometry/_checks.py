"""Argument checks shared by the geometry functions: wrong shapes and NaNs raise InputError."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from lunarnav_ml.errors import InputError

LUMA = np.array([0.299, 0.587, 0.114])  # RGB -> gray (ITU-R BT.601), as OpenCV converts


def as_array(
    name: str,
    value: object,
    shape: Sequence[int | None],
    *,
    dtype: type = np.float64,
    allow_nan: bool = False,
) -> np.ndarray:
    """Convert ``value`` to an array of the given shape, or raise InputError naming ``name``.

    Args:
        name: argument name used in the error message.
        value: anything ``np.asarray`` accepts.
        shape: expected shape; ``None`` matches any length on that axis.
        dtype: dtype of the returned array.
        allow_nan: when False, NaN or inf entries raise.

    Returns:
        The converted array.
    """
    try:
        arr = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: cannot convert to a {dtype.__name__} array ({exc})") from None
    expected = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
    if arr.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, arr.shape)):
        raise InputError(f"{name}: expected shape {expected}, got {tuple(arr.shape)}")
    if not allow_nan and np.issubdtype(arr.dtype, np.floating) and not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: contains NaN or inf (shape {tuple(arr.shape)})")
    return arr


def as_points(name: str, value: object, dim: int, *, allow_nan: bool = False) -> np.ndarray:
    """Convert ``value`` to an (N, dim) float64 array; a single (dim,) point becomes (1, dim).

    Raises:
        InputError: wrong shape or non-finite values.
    """
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == dim:
        arr = arr[None, :]
    return as_array(name, arr, (None, dim), allow_nan=allow_nan)


def as_image(name: str, value: object) -> np.ndarray:
    """Check an HxW (gray) or HxWx3 RGB image and return it as an HxW uint8 gray image.

    Colour is turned to gray as ``cv2.imread(path, cv2.IMREAD_GRAYSCALE)`` turns it: the luma
    0.299 R + 0.587 G + 0.114 B (OpenCV's ``COLOR_RGB2GRAY``), so that what a learned model
    (the box and disparity refiners) reads at run time is what it was trained on; a gray image
    replicated to three channels comes back as it was. Float images are expected in [0, 1] and
    scaled to 0..255.

    Raises:
        InputError: wrong rank/channels or non-finite values.
    """
    arr = np.asarray(value)
    if arr.ndim == 3 and arr.shape[2] == 3:
        if arr.dtype == np.uint8:
            return cv2.cvtColor(np.ascontiguousarray(arr), cv2.COLOR_RGB2GRAY)
        arr = np.asarray(arr, dtype=np.float64) @ LUMA
    if arr.ndim != 2:
        raise InputError(f"{name}: expected shape (H, W) or (H, W, 3), got {tuple(np.shape(value))}")
    if arr.dtype == np.uint8:
        return arr
    arr = np.asarray(arr, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: contains NaN or inf (shape {tuple(arr.shape)})")
    if arr.size and arr.max() <= 1.0:
        arr = arr * 255.0
    return np.clip(np.rint(arr), 0, 255).astype(np.uint8)


def crater_labels_3d(path: object, coco: dict) -> list[dict]:
    """The crater labels (category 1) of a COCO object that carry a 3D centre
    (``center_cam_m``), each checked (:func:`check_crater_label`); errors name ``path``.

    Raises:
        InputError: no 'annotations' list, or a malformed crater label.
    """
    anns = coco.get("annotations")
    if not isinstance(anns, list):
        raise InputError(f"{path}: missing the 'annotations' list")
    out = []
    for k, ann in enumerate(anns):
        if isinstance(ann, dict) and ann.get("category_id") == 1 and "center_cam_m" in ann:
            check_crater_label(ann, f"{path}: annotations[{k}] (id {ann.get('id')})")
            out.append(ann)
    return out


def check_crater_label(ann: object, where: str) -> None:
    """A crater label as the geometry evaluations read it: ``bbox`` 4 finite numbers with a
    positive width and height, ``diameter_m`` finite and positive, ``center_cam_m`` 3 finite
    numbers; InputError naming ``where`` and the field otherwise."""
    if not isinstance(ann, dict):
        raise InputError(f"{where}: expected an object, got {type(ann).__name__}")
    box = as_array(f"{where}: bbox", ann.get("bbox"), (4,))
    if box[2] <= 0 or box[3] <= 0:
        raise InputError(f"{where}: bbox {ann['bbox']} has non-positive width or height")
    diam = ann.get("diameter_m")
    if isinstance(diam, bool) or not isinstance(diam, (int, float)) or not np.isfinite(diam) \
            or diam <= 0:
        raise InputError(f"{where}: diameter_m must be a positive finite number, got {diam!r}")
    as_array(f"{where}: center_cam_m", ann.get("center_cam_m"), (3,))
