"""COCO loading and validation, datasets, augmentation, DataModule (YOLO-txt and other real
label formats are imported by :mod:`lunarnav_ml.realdata`)."""

from lunarnav_ml.data.coco import CLASS_NAMES, ImageRecord, load_coco, read_image
from lunarnav_ml.data.dataset import CocoDetection, collate

__all__ = ["CLASS_NAMES", "CocoDetection", "ImageRecord", "collate", "load_coco", "read_image"]
