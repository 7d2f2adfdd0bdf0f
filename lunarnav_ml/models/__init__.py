"""The detector: CSPDarknet53 / CSP-tiny backbones, SPP + PAN necks, YOLO heads, decode + NMS."""

from lunarnav_ml.models.decode import decode, postprocess
from lunarnav_ml.models.presets import PRESETS, build_model, count_parameters, default_anchors
from lunarnav_ml.models.yolo import YOLO

__all__ = ["PRESETS", "YOLO", "build_model", "count_parameters", "decode", "default_anchors",
           "postprocess"]
