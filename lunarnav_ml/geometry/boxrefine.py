"""A learned refinement of detected crater boxes from a full-resolution crop (torch-free).

The detector reads a 1024 px frame at its 384 px training side, and its crater boxes' edges are
off by 6-12 % of the side, too narrow on average and low at the bottom. The lift takes a crater's
angular width from the box, and with it the diameter and the centre behind the near rim, so the
box's error is the end-to-end 3D error (BENCHMARKS.md issue 5, "A learned box refiner"). A small
network (:mod:`lunarnav_ml.training.box_refiner`) reads the left image around each box at full
resolution and regresses the labelled box's four edges.

The crop (:func:`crop_frames`): centred on the box, 1.5 box widths wide and 1.5 box heights plus
0.15 widths high (craters seen from 1.5 m are flat boxes; the extra height holds the rim's
context), resampled to ``CROP_W`` x ``CROP_H``. Each crop is normalized by its own mean and
spread (:func:`normalize_crops`), and the net returns the box's left, top, right and bottom
edges as fractions of the crop (:func:`decode_edges`).

A refiner trained with a quality output (``train-box-refiner --quality W``) also returns, per
crop, its estimate of the IoU of the box the crop was cut around (the detector's) with the
best crater label (``quality``, in [0, 1]). :class:`BoxRefinedDetector` then scores each
crater sqrt(score x quality): the boxes that set the operating threshold's false alarms sit on
craters at IoU 0.2-0.5, and the detector's score does not rank them below the well-placed
ones.

The ONNX file carries ``lunarnav.kind = box_refiner`` and ``lunarnav.crop`` (``"W,H"``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from lunarnav_ml.errors import InputError
from lunarnav_ml.geometry._checks import as_image

KIND = "box_refiner"
CRATER_LABEL = 1  # the category whose boxes are refined
REFINED_KEY = "box_refined"  # marks a COCO result whose box was refined already
CROPS_NAME = "crops"
EDGES_NAME = "edges"
QUALITY_NAME = "quality"  # optional output: the input box's IoU with a label, estimated
CROP_W, CROP_H = 128, 64
DEFAULT_BOX_REFINER = Path(__file__).resolve().parents[1] / "weights" / "box_refiner.onnx"


def crop_frames(boxes_xywh: np.ndarray) -> np.ndarray:
    """Each box's crop in the image: x0, y0, width, height, px.

    Shape:
        boxes_xywh: (K, 4). Returns (K, 4) float64.
    """
    b = np.asarray(boxes_xywh, dtype=np.float64).reshape(-1, 4)
    w_c, h_c = 1.5 * b[:, 2], 1.5 * b[:, 3] + 0.15 * b[:, 2]
    return np.column_stack([b[:, 0] + b[:, 2] / 2 - w_c / 2, b[:, 1] + b[:, 3] / 2 - h_c / 2,
                            w_c, h_c])


def cut_crops(gray: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """The crops of ``frames`` (:func:`crop_frames`) resampled to ``CROP_H`` x ``CROP_W``
    (area averaging when shrinking, bilinear when enlarging; 0 outside the image).

    Shape:
        gray: (H, W) uint8; frames: (K, 4). Returns (K, CROP_H, CROP_W) uint8.
    """
    out = np.zeros((len(frames), CROP_H, CROP_W), np.uint8)
    for k, (x0, y0, w_c, h_c) in enumerate(np.asarray(frames, dtype=np.float64)):
        to_crop = np.array([[CROP_W / w_c, 0.0, -x0 * CROP_W / w_c],
                            [0.0, CROP_H / h_c, -y0 * CROP_H / h_c]], np.float32)
        flags = cv2.INTER_AREA if w_c > CROP_W else cv2.INTER_LINEAR
        out[k] = cv2.warpAffine(gray, to_crop, (CROP_W, CROP_H), flags=flags,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out


def normalize_crops(crops: np.ndarray) -> np.ndarray:
    """The net's input: each crop scaled to [0, 1], less its mean, over its spread (+ 0.02).

    Shape:
        crops: (K, CROP_H, CROP_W) uint8. Returns (K, 1, CROP_H, CROP_W) float32.
    """
    x = np.asarray(crops, dtype=np.float32)[:, None] / 255.0
    mean = x.mean(axis=(2, 3), keepdims=True)
    return ((x - mean) / (x.std(axis=(2, 3), keepdims=True) + 0.02)).astype(np.float32)


def encode_edges(boxes_xywh: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Boxes as the net's target: left, top, right, bottom as fractions of their crop.

    Shape:
        boxes_xywh, frames: (K, 4). Returns (K, 4) float32.
    """
    b = np.asarray(boxes_xywh, dtype=np.float64).reshape(-1, 4)
    f = np.asarray(frames, dtype=np.float64).reshape(-1, 4)
    return np.column_stack([(b[:, 0] - f[:, 0]) / f[:, 2], (b[:, 1] - f[:, 1]) / f[:, 3],
                            (b[:, 0] + b[:, 2] - f[:, 0]) / f[:, 2],
                            (b[:, 1] + b[:, 3] - f[:, 1]) / f[:, 3]]).astype(np.float32)


def decode_edges(edges: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """The inverse of :func:`encode_edges`: boxes (x, y, w, h) in the image, px.

    Shape:
        edges, frames: (K, 4). Returns (K, 4) float64.
    """
    e = np.asarray(edges, dtype=np.float64).reshape(-1, 4)
    f = np.asarray(frames, dtype=np.float64).reshape(-1, 4)
    x0, y0 = f[:, 0] + e[:, 0] * f[:, 2], f[:, 1] + e[:, 1] * f[:, 3]
    x1, y1 = f[:, 0] + e[:, 2] * f[:, 2], f[:, 1] + e[:, 3] * f[:, 3]
    return np.column_stack([x0, y0, x1 - x0, y1 - y0])


def refined_by(path: str | os.PathLike | None, rescored: bool = False) -> str:
    """The report-title phrase for boxes refined (``rescored``: and rescored by the quality
    output) by ``path`` (None: the shipped file)."""
    shipped = path is None or Path(path).resolve() == DEFAULT_BOX_REFINER
    return ("crater boxes refined and rescored by " if rescored else "crater boxes refined by ") \
        + ("the shipped box refiner" if shipped else str(path))


class BoxRefiner:
    """Refine crater boxes with an exported box refiner (``lunarnav train-box-refiner``).

    Args:
        path: the ONNX file (default: the shipped ``lunarnav_ml/weights/box_refiner.onnx``).
        threads: onnxruntime intra-op threads.

    Raises:
        InputError: missing, corrupt or foreign file (no ``lunarnav.kind = box_refiner``), or
            inputs / outputs other than the ones the trainer exports.
    """

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 1) -> None:
        from lunarnav_ml.runtime.session import load_tool_session

        self.path = Path(path) if path is not None else DEFAULT_BOX_REFINER
        self.session, props = load_tool_session(self.path, threads, KIND, "box refiner",
                                                "`lunarnav train-box-refiner`")
        if props.get("lunarnav.crop") != f"{CROP_W},{CROP_H}":
            raise InputError(f"{self.path}: metadata lunarnav.crop is "
                             f"{props.get('lunarnav.crop')!r}; this version reads "
                             f"'{CROP_W},{CROP_H}' crops")
        ins = {i.name for i in self.session.get_inputs()}
        outs = {o.name for o in self.session.get_outputs()}
        if ins != {CROPS_NAME} or EDGES_NAME not in outs:
            raise InputError(f"{self.path}: expected input '{CROPS_NAME}' and output "
                             f"'{EDGES_NAME}', got inputs {sorted(ins)}, outputs {sorted(outs)}")
        self.has_quality = QUALITY_NAME in outs

    def __call__(self, gray: np.ndarray, boxes_xywh: np.ndarray) -> np.ndarray:
        """The boxes refined on the left image; a box the net would turn inside out (under
        2 px wide or 1 px high) is kept as it was.

        Raises:
            InputError: ``gray`` is not an (H, W) uint8 image, or boxes that are not finite
                (K, 4) with a positive width and height.

        Shape:
            gray: (H, W) uint8; boxes_xywh: (K, 4) px. Returns (K, 4) float64.
        """
        return self.refine_scored(gray, boxes_xywh, quality=False)[0]

    def refine_scored(self, gray: np.ndarray, boxes_xywh: np.ndarray, quality: bool = True
                      ) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`__call__`'s boxes and, from a file with the quality output (and ``quality``),
        each input box's estimated IoU with its best crater label (K,) float32 in [0, 1];
        otherwise None."""
        if not isinstance(gray, np.ndarray) or gray.ndim != 2 or gray.dtype != np.uint8:
            raise InputError(f"image: expected a uint8 gray image (H, W), got "
                             f"{getattr(gray, 'dtype', type(gray).__name__)} "
                             f"{getattr(gray, 'shape', '')}")
        boxes = np.asarray(boxes_xywh, dtype=np.float64)
        if boxes.size == 0:
            return boxes.reshape(0, 4), (np.zeros(0, np.float32) if quality and self.has_quality
                                         else None)
        if boxes.ndim != 2 or boxes.shape[1] != 4 or not np.isfinite(boxes).all() \
                or (boxes[:, 2:] <= 0).any():
            raise InputError(f"boxes: expected finite (K, 4) x, y, w, h with w, h > 0, got "
                             f"shape {boxes.shape}")
        frames = crop_frames(boxes)
        crops = normalize_crops(cut_crops(gray, frames))
        names = [EDGES_NAME] + ([QUALITY_NAME] if quality and self.has_quality else [])
        outputs = self.session.run(names, {CROPS_NAME: crops})
        out = decode_edges(outputs[0], frames)
        bad = ~np.isfinite(out).all(axis=1) | (out[:, 2] < 2) | (out[:, 3] < 1)
        out[bad] = boxes[bad]
        if len(outputs) == 1:
            return out, None
        q = np.asarray(outputs[1], np.float32).reshape(-1)
        return out, np.clip(np.nan_to_num(q, nan=0.0), 0.0, 1.0)

    def refine_results(self, gray: np.ndarray, results: list[dict[str, Any]]
                       ) -> list[dict[str, Any]]:
        """COCO results of one image with each crater's (``category_id`` 1) box refined and
        marked ``"box_refined": true``: copies, in the same order; other classes, and crater
        boxes already marked (a :class:`BoxRefinedDetector`'s), as they were."""
        idx = [k for k, r in enumerate(results)
               if r.get("category_id") == CRATER_LABEL and not r.get(REFINED_KEY)]
        out = list(results)
        if idx:
            boxes = self(gray, np.array([results[k]["bbox"] for k in idx], dtype=np.float64))
            for k, box in zip(idx, boxes, strict=True):
                out[k] = {**results[k], "bbox": [float(v) for v in box], REFINED_KEY: True}
        return out


class BoxRefinedDetector:
    """A detector whose crater boxes a :class:`BoxRefiner` moves onto the rims (clipped to the
    image) and, with a quality output, scores sqrt(score x quality); then per-class NMS again (two
    boxes moved onto one rim count once). Wraps anything with
    ``predict(images, conf_thres, iou_thres, max_det)`` (the torch ``Detector``, the onnxruntime
    ``OnnxDetector``, a ``TTAPredictor``); other attributes are the wrapped detector's.

    The refiner reads each box's crop at the image's own resolution, which the detector saw
    shrunk to its input side: on the issue-4 validation sets the edges alone raised crater AP50
    by 2.6-5.6 points, the shipped file's edges and quality together by 5.1-8.9 (BENCHMARKS.md,
    "The box refiner on the detector's output", "An IoU-quality score from the box refiner").
    """

    def __init__(self, predictor: Any, refiner: BoxRefiner, rescorer: Any = None) -> None:
        if rescorer is not None and not getattr(refiner, "has_quality", False):
            raise InputError(f"{refiner.path}: a box rescorer reads the quality output, and this "
                             f"box refiner has none")
        self.predictor, self.refiner, self.rescorer = predictor, refiner, rescorer

    def __getattr__(self, name: str) -> Any:  # img_size, class_names, ...
        if name in ("predictor", "refiner", "rescorer"):  # not set yet (copy, unpickling)
            raise AttributeError(name)
        return getattr(self.predictor, name)

    def describe(self) -> str:
        """One line for report titles."""
        inner = getattr(self.predictor, "describe", None)
        line = (inner() + "; " if callable(inner) else "") + refined_by(self.refiner.path,
                                                                         self.rescores)
        if self.rescorer is not None:
            from lunarnav_ml.geometry.boxrescore import rescored_by

            line += "; " + rescored_by(self.rescorer.path)
        return line

    def predict(self, images: list[np.ndarray], conf_thres: float = 0.001,
                iou_thres: float = 0.6, max_det: int = 300) -> list[dict[str, np.ndarray]]:
        """The wrapped detector's output per image (``{"boxes" (N, 4) xyxy px, "scores",
        "labels"}``, highest score first) with the crater boxes refined (and rescored, by a
        refiner with a quality output), plus ``"box_refined"`` (N,) bool.

        With a quality output ``conf_thres`` holds for the final scores: the wrapped detector
        runs at ``conf_thres`` squared (sqrt(score x quality) >= t needs score >= t^2, quality
        being at most 1), and what ends below ``conf_thres`` is dropped. With a rescorer it runs
        at most at :data:`~lunarnav_ml.geometry.boxrescore.RAW_FLOOR` (the rescorer counts the
        weak boxes around each one, as it was fitted)."""
        preds = self.predictor.predict(images, self.raw_conf(conf_thres), iou_thres, max_det)
        return [self.above(self.refine(image, pred, iou_thres), conf_thres)
                for image, pred in zip(images, preds)]

    @property
    def rescores(self) -> bool:
        """Whether the crater scores change here (a refiner with a quality output)."""
        return bool(getattr(self.refiner, "has_quality", False))

    def raw_conf(self, conf_thres: float) -> float:
        """The wrapped detector's score floor for final scores of at least ``conf_thres``:
        ``conf_thres`` squared with a quality output (sqrt(score x quality) >= t needs score >=
        t^2), at most :data:`~lunarnav_ml.geometry.boxrescore.RAW_FLOOR` with a rescorer (its
        score is not bounded by the detector's, and it counts the weak boxes around each one,
        as it was fitted), ``conf_thres`` itself otherwise."""
        raw_conf = conf_thres ** 2 if self.rescores else conf_thres
        if self.rescorer is not None:
            from lunarnav_ml.geometry.boxrescore import RAW_FLOOR

            raw_conf = min(raw_conf, RAW_FLOOR)
        return raw_conf

    def above(self, pred: dict[str, np.ndarray], conf_thres: float) -> dict[str, np.ndarray]:
        """:meth:`refine`'s output less what scores below ``conf_thres`` (when the scores were
        changed; otherwise the wrapped detector's floor did it)."""
        return ({k: v[pred["scores"] >= conf_thres] for k, v in pred.items()} if self.rescores
                else pred)

    def refine(self, image: np.ndarray, pred: dict[str, np.ndarray], iou_thres: float,
               features: bool = False) -> dict[str, np.ndarray]:
        """One image's detections with their crater boxes refined (and rescored) and NMS at
        ``iou_thres`` run again per class; by score again. An empty crater box (no width or
        height, as a clip to the frame's edge can leave) stays as it was.

        ``features`` (a refiner with a quality output): also return ``"rescore_features"``,
        (N, len(FEATURES)) float32, each crater box's
        :func:`~lunarnav_ml.geometry.boxrescore.rescore_features` (NaN rows for the other
        boxes), what ``lunarnav train-box-rescorer`` fits on."""
        boxes = np.asarray(pred["boxes"], np.float64).reshape(-1, 4).copy()
        scores = np.asarray(pred["scores"], np.float32).reshape(-1)
        labels = np.asarray(pred["labels"]).reshape(-1)
        crater = (labels == CRATER_LABEL) & np.isfinite(boxes).all(axis=1) \
            & (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])  # an empty box stays
        feats = None  # the rescorer's features, where asked for or read
        if crater.any():
            gray = as_image("image", image)
            xywh = np.column_stack([boxes[crater, :2], boxes[crater, 2:] - boxes[crater, :2]])
            raw_xywh, raw_scores = xywh, scores[crater].astype(np.float64)
            xywh, quality = self.refiner.refine_scored(gray, xywh)
            if quality is not None:
                scores = scores.copy()
                scores[crater] = np.sqrt(scores[crater] * quality)
            h, w = gray.shape  # clipped to the image, as the detector's boxes and the labels are
            boxes[crater] = np.clip(np.column_stack([xywh[:, :2], xywh[:, :2] + xywh[:, 2:]]),
                                    0.0, [w, h, w, h])
            keep = np.asarray(cv2.dnn.NMSBoxesBatched(
                np.column_stack([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]]).tolist(),
                scores.tolist(), labels.astype(int).tolist(), 0.0, float(iou_thres)),
                dtype=np.int64).reshape(-1)
            if quality is not None and (features or self.rescorer is not None):
                feats = self._features(raw_xywh, raw_scores, boxes, quality, crater, keep,
                                       gray.shape)
                if self.rescorer is not None:
                    kept = keep[crater[keep]]
                    scores = scores.copy()
                    scores[kept] = self.rescorer(feats[kept])
            keep = keep[np.lexsort((keep, -scores[keep]))]  # by score, ties in input order
            boxes, scores, labels, crater = boxes[keep], scores[keep], labels[keep], crater[keep]
            feats = None if feats is None else feats[keep]
        out = {"boxes": boxes.astype(np.float32), "scores": scores, "labels": labels,
               "box_refined": crater}
        if features:
            from lunarnav_ml.geometry.boxrescore import FEATURES

            out["rescore_features"] = (np.full((len(boxes), len(FEATURES)), np.nan, np.float32)
                                       if feats is None else feats)
        return out

    @staticmethod
    def _features(raw_xywh: np.ndarray, raw_scores: np.ndarray, boxes: np.ndarray,
                  quality: np.ndarray, crater: np.ndarray, keep: np.ndarray,
                  shape: tuple[int, ...]) -> np.ndarray:
        """(N, len(FEATURES)): the rescorer's features of the frame's crater boxes that NMS
        kept (``keep``), NaN rows for every other box; ``raw_xywh``, ``raw_scores`` and
        ``quality`` are per crater box, ``boxes`` (xyxy) and ``crater`` per box of the frame."""
        from lunarnav_ml.geometry.boxrescore import FEATURES, rescore_features

        kept = keep[crater[keep]]
        xywh = np.column_stack([boxes[crater, :2], boxes[crater, 2:] - boxes[crater, :2]])
        out = np.full((len(boxes), len(FEATURES)), np.nan, np.float32)
        out[kept] = rescore_features(raw_xywh, raw_scores, xywh, quality.astype(np.float64),
                                     (np.cumsum(crater) - 1)[kept], shape)
        return out
