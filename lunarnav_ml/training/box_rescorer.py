"""Fit the crater-box rescorer (:mod:`lunarnav_ml.geometry.boxrescore`):
``lunarnav train-box-rescorer``.

Data: COCO sets with crater labels, each with a detector's results on it (the
``detections.json`` of ``lunarnav eval --task detection --no-box-refiner --out D``: the
network's boxes). Each frame's results go through
:class:`~lunarnav_ml.geometry.boxrefine.BoxRefinedDetector` with the box refiner exactly as
detection runs them (refinement, sqrt(score x quality), NMS at IoU 0.6), and each crater box left
gives one row of :data:`~lunarnav_ml.geometry.boxrescore.FEATURES`; its target is whether
pycocotools matches it to a countable crater at IoU 0.5 (boxes on ignored craters are left out).

The model is scikit-learn's ``GradientBoostingClassifier`` (shallow trees, subsampled rows),
converted by skl2onnx to onnxruntime's tree-ensemble operators. (scikit-learn's faster
histogram ensemble fits as well here, but skl2onnx 1.20 fails to convert it.) Use sets that
neither the detector's threshold nor a reported figure is read on.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from lunarnav_ml import __version__
from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.eval.coco_metrics import coco_from_dict, matched
from lunarnav_ml.eval.predict import read_coco_results, to_coco_results
from lunarnav_ml.geometry.boxrefine import CRATER_LABEL, BoxRefinedDetector, BoxRefiner
from lunarnav_ml.geometry.boxrescore import (
    FEATURES,
    FEATURES_NAME,
    KIND,
    PROBABILITIES_NAME,
    file_digest,
)
from lunarnav_ml.geometry.report import annotations_path, read_gray
from lunarnav_ml.training.box_refiner import checked_repeats
from lunarnav_ml.utils.jsonfile import read_json_file

NMS_IOU = 0.6  # detection's (lunarnav eval, detect)


@dataclass(frozen=True)
class BoxRescorerConfig:
    """The tree ensemble's settings (the shipped rescorer's are the defaults)."""

    trees: int = 300
    depth: int = 4
    lr: float = 0.05
    subsample: float = 0.5
    min_leaf: int = 40
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("trees", "depth", "min_leaf"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ConfigError(f"{name}: expected a positive integer, got {value!r}")
        for name in ("lr", "subsample"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ConfigError(f"{name}: expected a value in (0, 1], got "
                                  f"{getattr(self, name)!r}")


@dataclass(frozen=True)
class BoxRescorerReport:
    """What the fit saw: rows, positives (boxes on a countable crater), seconds."""

    n_rows: int
    n_positive: int
    seconds: float


def _prediction(results: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """One frame's COCO results as a detector's output (xyxy boxes), by score."""
    results = sorted(results, key=lambda r: -r["score"])
    xywh = np.array([r["bbox"] for r in results], np.float64).reshape(-1, 4)
    return {"boxes": np.column_stack([xywh[:, :2], xywh[:, :2] + xywh[:, 2:]]),
            "scores": np.array([r["score"] for r in results], np.float32),
            "labels": np.array([r["category_id"] for r in results], np.int64)}


def collect(datasets: Sequence[str | Path], detections: Sequence[str | Path],
            refiner: BoxRefiner, progress: bool = True
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The feature rows, targets (1: matches a countable crater) and set index of every crater
    box the refiner leaves on the sets' frames.

    Raises:
        ConfigError: not one results file per set.
        InputError: a missing or malformed set, results file or image (named).
    """
    if len(detections) != len(datasets):
        raise ConfigError(f"detections: one results file per set: {len(datasets)} set(s), "
                          f"{len(detections)} file(s)")
    wrapper = BoxRefinedDetector(None, refiner)
    rows, targets, sets = [], [], []
    for k, (dataset, det_path) in enumerate(zip(datasets, detections, strict=True)):
        path = annotations_path(dataset)
        gt = read_json_file(path, "COCO annotations", dict)
        by_image: dict[int, list[dict[str, Any]]] = {}
        for r in read_coco_results(det_path):
            by_image.setdefault(r["image_id"], []).append(r)
        kept, feats = [], []
        for im in tqdm(gt.get("images", []), desc=f"features {Path(dataset).name}",
                       disable=not progress):
            results = by_image.get(im["id"])
            if not results:
                continue
            out = wrapper.refine(read_gray(path.parent, im["file_name"]), _prediction(results),
                                 NMS_IOU, features=True)
            crater = out["labels"] == CRATER_LABEL
            feats.append(out["rescore_features"][crater])
            kept += [r for r in to_coco_results(out, im["id"])
                     if r["category_id"] == CRATER_LABEL]
        if not kept:
            raise InputError(f"{det_path}: no crater detection on the frames of {path}")
        status = matched(coco_from_dict(gt), kept)
        x = np.concatenate(feats)
        good = (status >= 0) & np.isfinite(x).all(axis=1)
        rows.append(x[good])
        targets.append(status[good])
        sets.append(np.full(int(good.sum()), k, np.int64))
    return np.concatenate(rows), np.concatenate(targets), np.concatenate(sets)


def fit(x: np.ndarray, y: np.ndarray, config: BoxRescorerConfig = BoxRescorerConfig(),
        weight: np.ndarray | None = None) -> Any:
    """The fitted ``GradientBoostingClassifier`` (``weight``: each row's, default 1).

    Raises:
        InputError: the targets hold one class only.
    """
    from sklearn.ensemble import GradientBoostingClassifier

    if len(np.unique(y)) != 2:
        raise InputError(f"rescorer targets: need boxes both on and off the labelled craters, "
                         f"got {int((y == 1).sum())} on and {int((y == 0).sum())} off")
    model = GradientBoostingClassifier(n_estimators=config.trees, max_depth=config.depth,
                                       learning_rate=config.lr, subsample=config.subsample,
                                       min_samples_leaf=config.min_leaf,
                                       random_state=config.seed)
    return model.fit(np.asarray(x, np.float32), np.asarray(y, np.int64), sample_weight=weight)


def export_box_rescorer(model: Any, path: str | Path, extra: dict[str, str] | None = None
                        ) -> Path:
    """Write ``model`` as an ONNX rescorer (input ``features`` (K, F), output ``probabilities``
    (K, 2)) with its metadata, atomically."""
    import onnx
    from skl2onnx import to_onnx

    from lunarnav_ml.training.refiner import _save

    onx = to_onnx(model, np.zeros((1, len(FEATURES)), np.float32),
                  options={id(model): {"zipmap": False}},
                  target_opset={"": 17, "ai.onnx.ml": 3})
    graph = onx.graph
    old_in, old_out = graph.input[0].name, graph.output[1].name
    for node in graph.node:  # this project's names for the input and the probabilities
        node.input[:] = [FEATURES_NAME if n == old_in else n for n in node.input]
        node.output[:] = [PROBABILITIES_NAME if n == old_out else n for n in node.output]
    graph.input[0].name, graph.output[1].name = FEATURES_NAME, PROBABILITIES_NAME
    onnx.checker.check_model(onx)
    props = {"lunarnav.kind": KIND, "lunarnav.features": ",".join(FEATURES),
             "lunarnav.project_version": __version__, **(extra or {})}
    return _save(onx, props, path)


def _fingerprint(path: str | Path) -> str:
    return json.dumps({"file": Path(path).name, "sha256": file_digest(path)})


def run(datasets: Sequence[str | Path], detections: Sequence[str | Path], out: str | Path,
        detector: str | Path, box_refiner: str | Path | None = None,
        config: BoxRescorerConfig = BoxRescorerConfig(), progress: bool = True,
        repeats: Sequence[int] | None = None, small_read: dict[str, float] | None = None
        ) -> BoxRescorerReport:
    """Features, fit and export: what ``lunarnav train-box-rescorer`` does. ``detector`` is the
    model file whose results ``detections`` are (recorded by name and SHA-256, with the box
    refiner's: ``--box-rescorer`` without a file name refuses other pairs);
    ``repeats`` weighs each set's rows (default 1 each); ``small_read``: the second read the
    detections were made with (``SmallBoxReadConfig.record``), recorded likewise."""
    repeats = checked_repeats(repeats, len(datasets))
    if not Path(detector).is_file():
        raise InputError(f"{detector}: no such detector file")
    refiner = BoxRefiner(box_refiner, threads=1)
    if not refiner.has_quality:
        raise InputError(f"{refiner.path}: the rescorer reads the quality output, and this box "
                         f"refiner has none")
    t0 = time.perf_counter()
    x, y, sets = collect(datasets, detections, refiner, progress)
    print(f"{len(y)} crater boxes ({int(y.sum())} on a countable crater) from "
          f"{len(datasets)} set(s)", flush=True)
    model = fit(x, y, config, np.asarray(repeats, np.float64)[sets])
    report = BoxRescorerReport(len(y), int(y.sum()), time.perf_counter() - t0)
    meta = {"lunarnav.detector": _fingerprint(detector),
            "lunarnav.box_refiner": _fingerprint(refiner.path),
            "lunarnav.small_read": json.dumps(small_read),
            "lunarnav.training": json.dumps({
                "datasets": [str(d) for d in datasets],
                "detections": [str(d) for d in detections], "repeats": repeats,
                **asdict(config), **asdict(report)})}
    export_box_rescorer(model, out, meta)
    return report
