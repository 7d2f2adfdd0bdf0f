"""The onboard detector: a lunarnav ONNX file run by onnxruntime, no torch.

``OnnxDetector.predict`` has the contract of ``lunarnav_ml.training.api.Detector.predict``:
HxWx3 uint8 RGB images in, per image ``{boxes xyxy, scores, labels}`` in image pixels out.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.runtime import metadata as md
from lunarnav_ml.runtime.nms import Detections, postprocess, split_graph_nms
from lunarnav_ml.runtime.preprocess import Letterbox, prepare_batch
from lunarnav_ml.runtime.session import open_session


class OnnxDetector:
    """Crater/rock/artifact detector on onnxruntime (CPU).

    Args:
        onnx_path: file written by ``lunarnav export`` (fp32 or int8); class names, input
            size, normalization and NMS placement are read from its metadata.
        threads: onnxruntime intra-op threads (1 = run in the calling thread).
        img_size: network input side (int) or (H, W), px; default the size the model was
            exported with. Must be a multiple of the largest stride; only a model exported
            with dynamic height/width accepts another size.

    Attributes:
        metadata: the file's :class:`~lunarnav_ml.runtime.metadata.ModelMetadata`.
        class_names: category names; label k is ``class_names[k - 1]``.
        img_size: (H, W) network input, px.
    """

    def __init__(self, onnx_path: str | os.PathLike, threads: int = 1,
                 img_size: int | tuple[int, int] | None = None) -> None:
        self.path = Path(onnx_path)
        self.threads = threads
        self.session, self.metadata = open_session(self.path, threads)
        self.class_names = self.metadata.class_names
        self.img_size = self._resolve_size(img_size)

    def _resolve_size(self, img_size: int | tuple[int, int] | None) -> tuple[int, int]:
        meta = self.metadata
        if img_size is None:
            return meta.input_size
        size = (img_size, img_size) if isinstance(img_size, int) else tuple(img_size)
        if len(size) != 2 or any(int(s) != s or s <= 0 or s % meta.max_stride for s in size):
            raise ConfigError(f"img_size: expected positive multiples of {meta.max_stride}, "
                              f"got {img_size!r}")
        if not meta.dynamic_hw and size != meta.input_size:
            raise ConfigError(f"img_size: {self.path} was exported with a fixed input "
                              f"{meta.input_size}; got {size}")
        return int(size[0]), int(size[1])

    def set_img_size(self, img_size: int | tuple[int, int]) -> None:
        """Run at another network input (a model exported with dynamic height/width only).

        Raises:
            ConfigError: not a multiple of the largest stride, or the model's input is fixed.
        """
        self.img_size = self._resolve_size(img_size)

    def preprocess(self, images: Sequence[np.ndarray]) -> tuple[np.ndarray, list[Letterbox]]:
        """Check, letterbox and normalize images.

        Returns:
            (B, 3, H, W) float32 network input and one :class:`Letterbox` per image.
        """
        m = self.metadata
        return prepare_batch(images, self.img_size, m.pad_value, m.mean, m.std)

    def _check_batch(self, batch: np.ndarray) -> None:
        if not isinstance(batch, np.ndarray) or batch.dtype != np.float32:
            raise InputError(f"batch: expected a float32 array (B, 3, H, W), got "
                             f"{getattr(batch, 'dtype', type(batch).__name__)}")
        stride = self.metadata.max_stride
        if batch.ndim != 4 or batch.shape[1] != 3 or batch.shape[2] % stride or \
                batch.shape[3] % stride:
            raise InputError(f"batch: expected shape (B, 3, H, W) with H and W multiples of "
                             f"{stride}, got {batch.shape}")
        if not self.metadata.dynamic_hw and tuple(batch.shape[2:]) != self.metadata.input_size:
            raise InputError(f"batch: {self.path} takes a fixed (H, W) = "
                             f"{self.metadata.input_size}, got {batch.shape[2:]}")
        if not self.metadata.dynamic_batch and batch.shape[0] != 1:
            raise InputError(f"batch: {self.path} was exported for batch 1, got {batch.shape[0]}")

    def forward(self, batch: np.ndarray) -> np.ndarray:
        """Decoded candidates before NMS.

        Shape:
            batch: (B, 3, H, W) float32 normalized -> (B, N, 5 + C) rows ``(cx, cy, w, h,
            objectness, class probs...)`` in network pixels.
        """
        self._check_batch(batch)
        feeds = {md.INPUT_NAME: batch}
        if self.metadata.nms_in_graph:
            feeds.update(self._nms_feeds(0.001, 0.6, 1))
        return self.session.run([md.DECODED_NAME], feeds)[0]

    def _nms_feeds(self, conf_thres: float, iou_thres: float, max_per_class: int
                   ) -> dict[str, np.ndarray]:
        return {md.CONF_NAME: np.array([conf_thres], np.float32),
                md.IOU_NAME: np.array([iou_thres], np.float32),
                md.MAX_PER_CLASS_NAME: np.array([max_per_class], np.int64)}

    def detect_batch(self, batch: np.ndarray, conf_thres: float = 0.001, iou_thres: float = 0.6,
                     max_det: int = 300) -> list[Detections]:
        """Detections in network pixels for a prepared batch (see :meth:`forward`)."""
        _check_thresholds(conf_thres, iou_thres, max_det)
        if not self.metadata.nms_in_graph:
            return postprocess(self.forward(batch), conf_thres, iou_thres, max_det)
        self._check_batch(batch)
        feeds = {md.INPUT_NAME: batch, **self._nms_feeds(conf_thres, iou_thres, max_det)}
        indices, boxes, scores = self.session.run(list(md.NMS_OUTPUTS), feeds)
        return split_graph_nms(indices, boxes, scores, batch.shape[0], max_det)

    def predict(self, images: Sequence[np.ndarray], conf_thres: float = 0.001,
                iou_thres: float = 0.6, max_det: int = 300) -> list[Detections]:
        """Detect objects in RGB images.

        Args:
            images: list of (h, w, 3) uint8 RGB arrays (sizes may differ).
            conf_thres: minimum score ``objectness * p(class)`` (exclusive).
            iou_thres: class-wise NMS IoU threshold.
            max_det: at most this many detections per image.

        Returns:
            per image ``{"boxes": (K, 4) float32 xyxy in image px, "scores": (K,) float32,
            "labels": (K,) int64 category ids 1..C}``, highest scores first.

        Raises:
            InputError: an image is not HxWx3 uint8 (the message names its index).
        """
        if len(images) == 0:
            return []
        batch, boxes = self.preprocess(images)
        dets = self.detect_batch(batch, conf_thres, iou_thres, max_det)
        for det, lb in zip(dets, boxes):
            det["boxes"] = lb.boxes_to_image(det["boxes"])
        return dets


def _check_thresholds(conf_thres: float, iou_thres: float, max_det: int) -> None:
    if not 0.0 <= conf_thres < 1.0:
        raise ConfigError(f"conf_thres: expected a value in [0, 1), got {conf_thres}")
    if not 0.0 < iou_thres <= 1.0:
        raise ConfigError(f"iou_thres: expected a value in (0, 1], got {iou_thres}")
    if max_det < 1:
        raise ConfigError(f"max_det: expected a positive integer, got {max_det}")
