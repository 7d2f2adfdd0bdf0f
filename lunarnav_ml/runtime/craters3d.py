"""Onboard crater localization from a rectified stereo pair: detect -> rim ellipse -> 3D.

Per frame: the detector finds crater boxes on the left image; SGBM computes the disparity
once; each crater box gets a rim ellipse (contour / convex hull fitter) and the range lifter
turns the box's inscribed ellipse (or, with ``lift_from="fit"``, the fitted one) + disparity
into a center and diameter in the rover frame (x forward, y left,
z up, m). Every stage is numpy / OpenCV / scipy (``lunarnav_ml.geometry``), never torch.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.geometry._checks import as_image
from lunarnav_ml.geometry.boxrefine import CRATER_LABEL, BoxRefinedDetector, BoxRefiner
from lunarnav_ml.geometry.ellipse import BOX_FALLBACK, Ellipse, EllipseFitter
from lunarnav_ml.geometry.frames import StereoRig
from lunarnav_ml.geometry.lifter import LifterConfig, LiftResult, lift_crater, rows_needed
from lunarnav_ml.geometry.refine import DisparityRefiner, default_lifter
from lunarnav_ml.geometry.stereo import SGBMStereo
from lunarnav_ml.runtime.preprocess import check_image

LIFT_SOURCES = ("box", "fit")


class BoxDetector(Protocol):
    """Anything with the ``predict`` contract (``OnnxDetector``, the torch ``Detector``)."""

    class_names: Sequence[str]

    def predict(self, images: list[np.ndarray], conf_thres: float = ..., iou_thres: float = ...
                ) -> list[dict[str, np.ndarray]]: ...


@dataclass(frozen=True)
class Crater3D:
    """One detected crater and what the geometry stages made of it.

    Attributes:
        box: (4,) xyxy px in the left image.
        score: detector score.
        ellipse: fitted rim ellipse (px), or None.
        ellipse_quality: 0..1 edge support of the ellipse (0 without one).
        lift: the 3D lift (rover frame), or None when it was not tried (lifting from a fitted
            ellipse that could not be fitted).
        reason: "ok", "ellipse:<why>" (``lift_from="fit"`` only) or "lift:<why>".
        refined: whether the disparity refiner corrected the disparity around this box (False
            without one, or where its gate left the box to SGBM).
    """

    box: np.ndarray
    score: float
    ellipse: Ellipse | None = None
    ellipse_quality: float = 0.0
    lift: LiftResult | None = field(default=None, repr=False)
    reason: str = "ok"
    refined: bool = False

    @property
    def ok(self) -> bool:
        """True when the crater has a 3D center and diameter."""
        return self.reason == "ok"

    @property
    def center_m(self) -> np.ndarray:
        """(3,) rim-circle center in the rover frame, m (NaN when not ok)."""
        return self.lift.center_m if self.lift is not None else np.full(3, np.nan)

    @property
    def diameter_m(self) -> float:
        """Rim diameter, m (NaN when not ok)."""
        return self.lift.diameter_m if self.lift is not None else float("nan")


class StereoCraterLocalizer:
    """Craters in 3D from a rectified stereo pair.

    Args:
        detector: box detector (normally :class:`~lunarnav_ml.runtime.OnnxDetector`).
        rig: the rectified rig and its pose on the rover.
        conf_thres: operating score threshold of crater boxes: on the detector's scores, or
            with a box refiner that has a quality output, on the refined scores
            sqrt(score x quality), as ``lunarnav detect`` and ``lunarnav eval`` apply it.
        iou_thres: NMS IoU threshold.
        stereo: disparity stage (SGBM settings); default sized to each frame's width
            (:meth:`SGBMStereo.for_width`, as the geometry evaluation runs it).
        fitter: rim ellipse stage.
        lifter: range lifter thresholds (default :class:`LifterConfig`, with the refiner's
            edge offsets when there is one).
        lift_from: the ellipse each crater is lifted from: "box" (the box's inscribed
            ellipse) or "fit" (the fitted rim ellipse, or the fitter's box fallback). The
            fitted ellipse is reported either way. "box" by default: on development renders
            of the paper-stereo grid it gave the smaller 3D errors with labelled boxes and
            with their edges moved by 1-2 % of the side, the same at 4 % and with a
            detector's boxes (BENCHMARKS.md, issue 5, "Lifting from the box").
        refiner: corrects the disparity around each crater box before the lifts
            (:class:`~lunarnav_ml.geometry.refine.DisparityRefiner`, onnxruntime); None: SGBM's
            disparity as it is.
        box_refiner: moves each detected crater box's edges onto the rim from a
            full-resolution crop before the lift
            (:class:`~lunarnav_ml.geometry.boxrefine.BoxRefiner`, onnxruntime); None: the
            detector's boxes as they are. The crater's box in the output is the refined one.
            With a quality output it also scores each crater box sqrt(score x quality), and
            NMS runs again over the refined boxes
            (:class:`~lunarnav_ml.geometry.boxrefine.BoxRefinedDetector`, the path ``lunarnav
            eval`` reads its figures on).
        box_rescorer: scores each refined crater box by a second-stage
            :class:`~lunarnav_ml.geometry.boxrescore.BoxRescorer` instead (needs a box refiner
            with a quality output); ``conf_thres`` then holds for its probabilities.
    """

    def __init__(self, detector: BoxDetector, rig: StereoRig, *, conf_thres: float = 0.25,
                 iou_thres: float = 0.6, stereo: SGBMStereo | None = None,
                 fitter: EllipseFitter | None = None, lifter: LifterConfig | None = None,
                 lift_from: str = "box", refiner: DisparityRefiner | None = None,
                 box_refiner: BoxRefiner | None = None, box_rescorer: Any = None) -> None:
        if lift_from not in LIFT_SOURCES:
            raise ConfigError(f"lift_from: expected one of {LIFT_SOURCES}, got {lift_from!r}")
        names = list(detector.class_names)
        if "crater" not in names:
            raise ConfigError(f"detector classes {names} have no 'crater'")
        self.detector, self.rig = detector, rig
        self.crater_label = names.index("crater") + 1
        self.conf_thres, self.iou_thres = conf_thres, iou_thres
        self.stereo = stereo
        self.fitter = fitter or EllipseFitter()
        self.lifter = lifter or default_lifter(refiner)  # a refined map has its own offsets
        self.lift_from = lift_from
        self.refiner = refiner
        self.box_refiner = box_refiner
        self.scorer = None  # refines and rescores the crater boxes: a refiner's quality output
        if box_rescorer is not None and not getattr(box_refiner, "has_quality", False):
            raise ConfigError("box_rescorer: reads the box refiner's quality output, and "
                              + ("there is no box refiner" if box_refiner is None
                                 else f"{box_refiner.path} has none"))
        if getattr(box_refiner, "has_quality", False):
            if self.crater_label != CRATER_LABEL:
                raise ConfigError(f"detector classes {names}: the box refiner reads crater boxes "
                                  f"as label {CRATER_LABEL}, these are label {self.crater_label}")
            self.scorer = BoxRefinedDetector(detector, box_refiner, box_rescorer)
        self.timing_ms: dict[str, float] = {}  # the last frame's, see __call__

    def detect_boxes(self, left: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Crater boxes (K, 4) xyxy px and scores (K,) on the left image, at ``conf_thres``:
        the detector's, or with a quality box refiner refined and rescored. Sets ``timing_ms``
        "detect" (the network) and, with that refiner, "box_refine"."""
        t0 = time.perf_counter()
        conf = self.conf_thres if self.scorer is None else self.scorer.raw_conf(self.conf_thres)
        det = self.detector.predict([left], conf_thres=conf, iou_thres=self.iou_thres)[0]
        t1 = time.perf_counter()
        self.timing_ms["detect"] = 1e3 * (t1 - t0)
        if self.scorer is not None:
            det = self.scorer.above(self.scorer.refine(left, det, self.iou_thres),
                                    self.conf_thres)
            self.timing_ms["box_refine"] = 1e3 * (time.perf_counter() - t1)
        mine = det["labels"] == self.crater_label
        return det["boxes"][mine], det["scores"][mine]

    def disparity(self, left: np.ndarray, right: np.ndarray,
                  rows: tuple[int, int] | None = None) -> np.ndarray:
        """Left-reference disparity (H, W) of a rectified pair (gray or RGB), px; NaN invalid
        (and outside ``rows`` [first, last) when given). Without ``stereo`` settings SGBM is
        sized to the frame (:meth:`SGBMStereo.for_width`)."""
        return (self.stereo or SGBMStereo.for_width(left.shape[1]))(left, right, rows).disparity

    def localize_box(self, left: np.ndarray, disparity: np.ndarray, box: np.ndarray,
                     score: float, pair: tuple[np.ndarray, np.ndarray] | None = None) -> Crater3D:
        """Ellipse and 3D lift of one crater box (xyxy px); with the rectified ``pair`` (gray
        or RGB) the lifter measures the rim's crest from the images (``LifterConfig.crest_match``).
        """
        xywh = np.array([box[0], box[1], box[2] - box[0], box[3] - box[1]], dtype=np.float64)
        fit = self.fitter(left, xywh)
        if self.lift_from == "box":  # the fit is reported, but the lift does not need it
            lift = lift_crater(Ellipse.from_box(xywh), disparity, self.rig, self.lifter, pair,
                               from_box=True)
        elif not fit.ok:
            return Crater3D(box, score, reason=f"ellipse:{fit.reason}")
        else:
            lift = lift_crater(fit.ellipse, disparity, self.rig, self.lifter, pair,
                               from_box=fit.reason == BOX_FALLBACK)
        return Crater3D(box, score, fit.ellipse if fit.ok else None,
                        fit.quality if fit.ok else 0.0, lift,
                        "ok" if lift.ok else f"lift:{lift.reason}")

    def __call__(self, left: np.ndarray, right: np.ndarray) -> list[Crater3D]:
        """Detect and localize the craters of one rectified stereo pair.

        Args:
            left, right: (H, W, 3) uint8 RGB rectified images of the same shape.

        Returns:
            One :class:`Crater3D` per crater box above ``conf_thres``, by decreasing score;
            check ``ok`` / ``reason`` before using ``center_m``. ``timing_ms`` then holds the
            frame's wall time per stage: "detect", "box_refine" (0 without a box refiner),
            "stereo" (gray conversion and disparity,
            with the refiner's correction; 0 without crater boxes) and "craters" (every box's
            ellipse and lift), ms.
        """
        check_image(left, 0)
        check_image(right, 1)
        if left.shape != right.shape:
            raise InputError(f"right: expected the left image's shape {left.shape}, "
                             f"got {right.shape}")
        self.timing_ms = {"detect": 0.0, "box_refine": 0.0, "stereo": 0.0, "craters": 0.0}
        boxes, scores = self.detect_boxes(left)
        t1 = time.perf_counter()
        if len(boxes) == 0:
            return []
        pair = (as_image("left", left), as_image("right", right))  # gray once a frame
        xywh = np.column_stack([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]])
        if self.box_refiner is not None and self.scorer is None:  # edges only onto the rims
            xywh = self.box_refiner(pair[0], xywh)
            boxes = np.column_stack([xywh[:, :2], xywh[:, :2] + xywh[:, 2:]])
            self.timing_ms["box_refine"] = 1e3 * (time.perf_counter() - t1)
            t1 = time.perf_counter()
        # only the rows the boxes' lifts read, as the geometry evaluation matches them
        disparity = self.disparity(*pair, rows=rows_needed(xywh, left.shape[0], self.lifter))
        refined = np.zeros(len(boxes), bool)
        if self.refiner is not None:
            disparity, refined = self.refiner.refine_boxes(*pair, disparity, xywh)
        t2 = time.perf_counter()
        craters = [replace(self.localize_box(pair[0], disparity, b, float(s), pair),
                           refined=bool(r)) for b, s, r in zip(boxes, scores, refined)]
        self.timing_ms.update(stereo=1e3 * (t2 - t1), craters=1e3 * (time.perf_counter() - t2))
        return craters
