"""Test-time augmentation: run a detector at several input sides and mirrored, fuse the boxes.

Each pass letterboxes the image to another network side (``scale x`` the model's own, rounded
to its stride) and optionally mirrors it left-right; its boxes are mapped back to the image and
all passes are fused class by class with weighted boxes fusion (Solovyev et al. 2021, through
the ``ensemble-boxes`` package): overlapping boxes of one class (IoU above ``fuse_iou``) become
one box, their coordinates weighted by score, scored by the sum of their scores over the
number of passes. A box that every pass finds keeps its score; one that a single pass finds is
divided by the number of passes, which is what re-ranks a frame's detections (chosen on the real `valid/`
split: see BENCHMARKS.md, issue 7).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from lunarnav_ml.errors import ConfigError

DEFAULT_SCALES = (0.8, 1.0, 1.2)
DEFAULT_FUSE_IOU = 0.55  # the ensemble-boxes default


@dataclass(frozen=True)
class TTAConfig:
    """Which passes to run and how to fuse them.

    Attributes:
        scales: input sides as multiples of the model's own side (each rounded to the stride).
        flip: also run every side on the left-right mirrored image.
        fuse_iou: IoU above which boxes of one class from different passes are fused.
    """

    scales: tuple[float, ...] = DEFAULT_SCALES
    flip: bool = True
    fuse_iou: float = DEFAULT_FUSE_IOU

    def __post_init__(self) -> None:
        scales = tuple(self.scales)
        if not scales or not all(np.isfinite(s) and s > 0 for s in scales):
            raise ConfigError(f"tta scales: expected positive numbers, got {list(self.scales)}")
        if not 0.0 < self.fuse_iou < 1.0:
            raise ConfigError(f"tta fuse_iou: expected a value in (0, 1), got {self.fuse_iou}")
        object.__setattr__(self, "scales", scales)

    def describe(self, sides: Sequence[int] | None = None) -> str:
        """One line for report titles: the scales, or the network ``sides`` (px) they gave."""
        what = (f"sides {list(sides)} px" if sides is not None
                else " / ".join(f"{s:g}" for s in self.scales) + " x the input side")
        return f"test-time augmentation: {what}{', each mirrored' if self.flip else ''}, fused"


def tta_sides(base: int, scales: Sequence[float], stride: int) -> list[int]:
    """The distinct network sides ``scale * base`` rounded to a multiple of ``stride`` (at
    least one stride), in the order of ``scales``."""
    sides: list[int] = []
    for scale in scales:
        side = max(stride, round(base * scale / stride) * stride)
        if side not in sides:
            sides.append(side)
    return sides


def square_side(predictor: Any, option: str = "tta") -> int:
    """The predictor's square network input side; ``ConfigError`` naming ``option`` (the
    wrapper that needs it) for a rectangular one."""
    size = predictor.img_size
    if isinstance(size, tuple | list):
        if size[0] != size[1]:
            raise ConfigError(f"{option}: needs a square network input, the model runs at "
                              f"{size}")
        size = size[0]
    return int(size)


def max_stride(predictor: Any) -> int:
    """The largest stride of a torch ``Detector`` (``strides``) or an ``OnnxDetector``
    (``metadata.max_stride``): what every input side must be a multiple of."""
    return (max(predictor.strides) if hasattr(predictor, "strides")
            else int(predictor.metadata.max_stride))


class TTAPredictor:
    """Wraps a predictor that has ``img_size``, ``set_img_size(side)`` and ``strides`` or
    ``metadata.max_stride`` (the torch :class:`Detector`, the onnxruntime ``OnnxDetector``);
    ``predict`` has the wrapped predictor's signature and output."""

    def __init__(self, predictor: Any, config: TTAConfig = TTAConfig()) -> None:
        self.predictor = predictor
        self.config = config
        self.base_side = square_side(predictor)
        self.sides = tta_sides(self.base_side, config.scales, max_stride(predictor))
        try:  # a model that cannot run at a side says so now, not halfway through a set
            for side in self.sides:
                predictor.set_img_size(side)
        finally:
            predictor.set_img_size(self.base_side)

    @property
    def passes(self) -> int:
        return len(self.sides) * (2 if self.config.flip else 1)

    def describe(self) -> str:
        """One line for report titles, with the sides this model runs at."""
        return self.config.describe(self.sides)

    def __getattr__(self, name: str) -> Any:  # class_names, to_coco_results, ...
        if name == "predictor":  # not set yet (copy, unpickling): no recursion
            raise AttributeError(name)
        return getattr(self.predictor, name)

    def predict(self, images: list[np.ndarray], conf_thres: float = 0.001,
                iou_thres: float = 0.6, max_det: int = 300) -> list[dict[str, np.ndarray]]:
        """Detect with every pass and fuse; per image ``{"boxes" (N, 4) xyxy px, "scores",
        "labels"}``, highest score first, at most ``max_det``."""
        if not images:
            return []
        runs = self.run_passes(images, conf_thres, iou_thres, max_det)
        return [fuse_passes([run[i] for run in runs], image.shape, self.config.fuse_iou,
                            conf_thres, max_det) for i, image in enumerate(images)]

    def run_passes(self, images: list[np.ndarray], conf_thres: float = 0.001,
                   iou_thres: float = 0.6, max_det: int = 300
                   ) -> list[list[dict[str, np.ndarray]]]:
        """Every pass's detections in image pixels, before fusion: ``[pass][image]``, the
        passes in the order side 1, side 1 mirrored, side 2, ..."""
        runs: list[list[dict[str, np.ndarray]]] = []
        mirrored = [np.ascontiguousarray(im[:, ::-1]) for im in images] if self.config.flip else []
        try:
            for side in self.sides:
                self.predictor.set_img_size(side)
                runs.append(self.predictor.predict(images, conf_thres, iou_thres, max_det))
                if self.config.flip:
                    preds = self.predictor.predict(mirrored, conf_thres, iou_thres, max_det)
                    runs.append([_unmirror(p, im.shape[1]) for p, im in zip(preds, images)])
        finally:
            self.predictor.set_img_size(self.base_side)
        return runs


def fuse_passes(preds: list[dict[str, np.ndarray]], shape: tuple[int, ...],
                fuse_iou: float = DEFAULT_FUSE_IOU, conf_thres: float = 0.001,
                max_det: int = 300) -> dict[str, np.ndarray]:
    """One image's detections from several passes (``{"boxes" xyxy px, "scores", "labels"}``
    each) fused class by class with weighted boxes fusion; highest score first."""
    from ensemble_boxes import weighted_boxes_fusion  # pulls in pandas: only when used

    h, w = shape[:2]
    scale = np.array([w, h, w, h], dtype=np.float64)
    boxes, scores, labels = [], [], []
    for p in preds:  # in [0, 1] image units; boxes wholly off the image are dropped
        b = np.clip(np.asarray(p["boxes"], np.float64).reshape(-1, 4) / scale, 0.0, 1.0)
        keep = (b[:, 2] > b[:, 0]) & (b[:, 3] > b[:, 1])
        boxes.append(b[keep])
        scores.append(np.asarray(p["scores"], np.float64)[keep])
        labels.append(np.asarray(p["labels"], np.int64)[keep])
    fused, scores, labels = weighted_boxes_fusion(boxes, scores, labels, iou_thr=fuse_iou,
                                                  skip_box_thr=conf_thres)
    order = np.argsort(-np.asarray(scores), kind="stable")[:max_det]
    return {"boxes": (np.asarray(fused).reshape(-1, 4)[order] * scale).astype(np.float32),
            "scores": np.asarray(scores, np.float32)[order],
            "labels": np.asarray(labels).astype(np.int64)[order]}


def _unmirror(pred: dict[str, np.ndarray], width: int) -> dict[str, np.ndarray]:
    """Boxes found on the mirrored image, in the original image's pixels."""
    boxes = np.asarray(pred["boxes"], np.float32).reshape(-1, 4).copy()
    boxes[:, [0, 2]] = width - boxes[:, [2, 0]]
    return {**pred, "boxes": boxes}


def add_tta_arguments(parser: argparse.ArgumentParser) -> None:
    """``--tta`` and ``--tta-scales`` for a command that runs a detector."""
    parser.add_argument("--tta", action="store_true",
                        help="test-time augmentation: run at several input sides and mirrored, "
                             "fuse with weighted boxes fusion (slower by the number of passes)")
    parser.add_argument("--tta-scales", type=float, nargs="+", default=list(DEFAULT_SCALES),
                        metavar="S", help="(--tta) input sides as multiples of the model's "
                                          "(or --img-size); default %(default)s, with mirroring")


def tta_config(args: argparse.Namespace) -> TTAConfig | None:
    """The :class:`TTAConfig` the ``--tta`` arguments ask for, or None without ``--tta``."""
    return TTAConfig(scales=tuple(args.tta_scales)) if getattr(args, "tta", False) else None
