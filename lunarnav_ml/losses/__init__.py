"""Target assignment, CIoU, the YOLO loss and the distillation loss."""

from lunarnav_ml.losses.distill import detection_kd_loss
from lunarnav_ml.losses.iou import ciou, wh_iou
from lunarnav_ml.losses.targets import check_targets
from lunarnav_ml.losses.yolo_loss import YOLOLoss

__all__ = ["YOLOLoss", "check_targets", "ciou", "detection_kd_loss", "wh_iou"]
