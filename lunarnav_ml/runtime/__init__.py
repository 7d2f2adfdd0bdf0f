"""Torch-free onboard runtime: numpy, onnxruntime and OpenCV only.

``OnnxDetector`` runs an exported detector (letterbox, onnxruntime, NMS); the crater stages
(rim ellipse, stereo lift to 3D) use ``lunarnav_ml.geometry``, which is numpy/OpenCV/scipy.
"""

from lunarnav_ml.runtime.craters3d import Crater3D, StereoCraterLocalizer
from lunarnav_ml.runtime.detector import OnnxDetector
from lunarnav_ml.runtime.metadata import ModelMetadata

__all__ = ["Crater3D", "ModelMetadata", "OnnxDetector", "StereoCraterLocalizer"]
