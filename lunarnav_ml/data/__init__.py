"""COCO loading and validation, YOLO-txt import, datasets, augmentation, DataModule."""

from lunarnav_ml.data.coco import CLASS_NAMES, ImageRecord, load_coco, read_image
from lunarnav_ml.data.dataset import CocoDetection, collate

__all__ = ["CLASS_NAMES", "CocoDetection", "ImageRecord", "collate", "load_coco", "read_image"]
