"""COCO loading and validation, datasets, augmentation, DataModule (YOLO-txt and other real
label formats are imported by :mod:`lunarnav_ml.realdata`).

The COCO readers are torch-free; the torch ``Dataset`` (``CocoDetection``, ``collate``) loads
when first asked for, so that reading labels (``lunarnav import-real``, the ``lunarnav``
command's start-up) does not import torch."""

from typing import Any

from lunarnav_ml.data.coco import CLASS_NAMES, ImageRecord, load_coco, read_image

__all__ = ["CLASS_NAMES", "CocoDetection", "ImageRecord", "collate", "load_coco", "read_image"]


def __getattr__(name: str) -> Any:
    if name in ("CocoDetection", "collate"):
        from lunarnav_ml.data import dataset

        return getattr(dataset, name)
    raise AttributeError(f"module 'lunarnav_ml.data' has no attribute {name!r}")
