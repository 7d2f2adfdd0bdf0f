"""Target assignment, CIoU and the YOLO loss."""

from lunarnav_ml.losses.iou import ciou, wh_iou
from lunarnav_ml.losses.targets import check_targets
from lunarnav_ml.losses.yolo_loss import YOLOLoss

__all__ = ["YOLOLoss", "check_targets", "ciou", "wh_iou"]
