"""A second-stage score for the refined crater boxes, from what the detector and the box refiner
already know about each box (torch-free).

:class:`~lunarnav_ml.geometry.boxrefine.BoxRefinedDetector` scores a crater sqrt(score x
quality). How often a box at that score is a countable crater depends on the box itself: its
size and aspect against where it sits in the frame (a crater on level ground seen from 1.5 m is a
flat box whose height grows with its nearness), how many other boxes the detector put around it
and how far the refiner moved it. A gradient-boosted tree ensemble (``lunarnav
train-box-rescorer``, :mod:`lunarnav_ml.training.box_rescorer`) reads these :data:`FEATURES` of
each box left after the refinement's NMS and returns the probability that it matches a
countable crater at IoU >= 0.5; that probability is the box's new score.

It is fitted on one detector's scores with one box refiner, and the file records both
(``lunarnav.detector`` and ``lunarnav.box_refiner``: name and SHA-256). It is off by default:
``--box-rescorer`` in ``lunarnav detect`` and ``lunarnav eval`` turns it on, the shipped file
for the shipped ``small.pt`` and box refiner only (:meth:`BoxRescorer.fitted_for`), a named
file for any model. The shipped file (session 74) raised crater AP50 and key-crater Pd on both
synthetic validation sets and lost one crater of 83 at recall@5 on the real ``valid/`` frames,
so it did not become the default (BENCHMARKS.md, "A second-stage score for the crater boxes").

The ONNX file (a scikit-learn ensemble converted by skl2onnx, read by onnxruntime's tree
operators) carries ``lunarnav.kind = box_rescorer`` and ``lunarnav.features``.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from lunarnav_ml.errors import InputError

KIND = "box_rescorer"
FEATURES_NAME = "features"
PROBABILITIES_NAME = "probabilities"
NEIGHBOUR_FLOOR = 0.05  # boxes under this sqrt(score x quality) are not counted as neighbours
RAW_FLOOR = NEIGHBOUR_FLOOR ** 2  # the detector must return every box that can be a neighbour
FEATURES = (
    "score",  # the detector's
    "quality",  # the box refiner's IoU estimate
    "width", "height",  # of the refined box, as fractions of the frame's width and height
    "aspect",  # width / height
    "centre_x", "centre_y",  # fractions of the frame
    "neighbours_iou30", "neighbours_iou50",  # other crater boxes overlapping it at IoU > 0.3 / 0.5
    "neighbour_max_score",  # the highest sqrt(score x quality) among those at IoU > 0.3
    "neighbour_iou_score_sum",  # sum of IoU x sqrt(score x quality) over all other boxes
    "neighbours_above",  # boxes at IoU > 0.3 scoring above it
    "shift_max", "shift_height",  # refinement move: largest |x, y, w, h| change, |h| change
)
DEFAULT_BOX_RESCORER = Path(__file__).resolve().parents[1] / "weights" / "box_rescorer.onnx"
# fitted on the boxes of `--small-read 640` (the default cut), for the paper's 1024 px frames
SMALL_READ_BOX_RESCORER = DEFAULT_BOX_RESCORER.with_name("box_rescorer_small_read.onnx")
# the same for `small_grid.pt` (trained on the paper's grid) with `--small-read 640`
GRID_BOX_RESCORER = DEFAULT_BOX_RESCORER.with_name("box_rescorer_grid.onnx")
# the shipped files for `--small-read 640`, in the order `--box-rescorer` without a file tries them
SMALL_READ_BOX_RESCORERS = (SMALL_READ_BOX_RESCORER, GRID_BOX_RESCORER)


SHIPPED_NAMES = {DEFAULT_BOX_RESCORER: "the shipped box rescorer",
                 SMALL_READ_BOX_RESCORER: "the shipped box rescorer for --small-read",
                 GRID_BOX_RESCORER: "the shipped box rescorer for small_grid.pt with --small-read"}


def rescored_by(path: str | os.PathLike | None) -> str:
    """The report-title phrase for crater scores from the rescorer ``path`` (None: shipped)."""
    resolved = DEFAULT_BOX_RESCORER if path is None else Path(path).resolve()
    return "scored by " + SHIPPED_NAMES.get(resolved, str(path))


def file_digest(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of every xywh box of ``a`` (N, 4) with every one of ``b`` (M, 4): (N, M)."""
    iw = np.minimum(a[:, None, 0] + a[:, None, 2], b[None, :, 0] + b[None, :, 2]) \
        - np.maximum(a[:, None, 0], b[None, :, 0])
    ih = np.minimum(a[:, None, 1] + a[:, None, 3], b[None, :, 1] + b[None, :, 3]) \
        - np.maximum(a[:, None, 1], b[None, :, 1])
    inter = np.clip(iw, 0, None) * np.clip(ih, 0, None)
    union = (a[:, 2] * a[:, 3])[:, None] + (b[:, 2] * b[:, 3])[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def rescore_features(raw_xywh: np.ndarray, scores: np.ndarray, xywh: np.ndarray,
                     quality: np.ndarray, keep: np.ndarray, shape: tuple[int, ...]
                     ) -> np.ndarray:
    """The :data:`FEATURES` of the crater boxes ``keep`` indexes, among all of a frame's.

    Args:
        raw_xywh: (K, 4) the detector's crater boxes, x, y, w, h px.
        scores: (K,) the detector's scores.
        xywh: (K, 4) the same boxes refined and clipped to the frame.
        quality: (K,) the refiner's quality.
        keep: indices into the K boxes (those left after NMS) to describe.
        shape: the frame's (H, W[, C]).

    Returns:
        (len(keep), len(FEATURES)) float32.
    """
    h_img, w_img = float(shape[0]), float(shape[1])
    fused = np.sqrt(scores * quality)
    keep = np.asarray(keep, np.int64).reshape(-1)
    out = np.zeros((len(keep), len(FEATURES)), np.float32)
    if not len(keep):
        return out
    w, h = xywh[keep, 2], np.maximum(xywh[keep, 3], 1e-3)
    counted = np.flatnonzero((fused >= NEIGHBOUR_FLOOR) & (xywh[:, 2] > 0) & (xywh[:, 3] > 0))
    iou = _iou_matrix(xywh[keep], xywh[counted])
    iou[keep[:, None] == counted[None, :]] = 0.0  # a box is not its own neighbour
    near30, near50 = iou > 0.3, iou > 0.5
    f_counted = fused[counted][None, :]
    shift = np.abs(xywh[keep] - raw_xywh[keep]) / np.column_stack([w, h, w, h])
    out[:, 0], out[:, 1] = scores[keep], quality[keep]
    out[:, 2], out[:, 3], out[:, 4] = w / w_img, h / h_img, w / h
    out[:, 5] = (xywh[keep, 0] + w / 2) / w_img
    out[:, 6] = (xywh[keep, 1] + xywh[keep, 3] / 2) / h_img
    out[:, 7], out[:, 8] = near30.sum(axis=1), near50.sum(axis=1)
    out[:, 9] = np.where(near30, f_counted, 0.0).max(axis=1, initial=0.0)
    out[:, 10] = (iou * f_counted).sum(axis=1)
    out[:, 11] = (near30 & (f_counted > fused[keep][:, None])).sum(axis=1)
    out[:, 12], out[:, 13] = shift.max(axis=1), shift[:, 3]
    return out


class BoxRescorer:
    """Score refined crater boxes with an exported rescorer (``lunarnav train-box-rescorer``).

    Args:
        path: the ONNX file (default: the shipped ``lunarnav_ml/weights/box_rescorer.onnx``).
        threads: onnxruntime intra-op threads.

    Raises:
        InputError: missing, corrupt or foreign file (no ``lunarnav.kind = box_rescorer``), or
            features other than this version's :data:`FEATURES`.
    """

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 1) -> None:
        from lunarnav_ml.runtime.session import load_tool_session

        self.path = Path(path) if path is not None else DEFAULT_BOX_RESCORER
        self.session, props = load_tool_session(self.path, threads, KIND, "box rescorer",
                                                "`lunarnav train-box-rescorer`")
        if props.get("lunarnav.features") != ",".join(FEATURES):
            raise InputError(f"{self.path}: metadata lunarnav.features is "
                             f"{props.get('lunarnav.features')!r}; this version computes "
                             f"{','.join(FEATURES)!r}")
        ins = [i.name for i in self.session.get_inputs()]
        outs = [o.name for o in self.session.get_outputs()]
        if ins != [FEATURES_NAME] or PROBABILITIES_NAME not in outs:
            raise InputError(f"{self.path}: expected input '{FEATURES_NAME}' and output "
                             f"'{PROBABILITIES_NAME}', got inputs {ins}, outputs {outs}")
        self.fitted_with = {key: json.loads(props.get(f"lunarnav.{key}", "null"))
                            for key in ("detector", "box_refiner", "small_read")}

    def __call__(self, features: np.ndarray) -> np.ndarray:
        """(K,) float32 in [0, 1]: each box's probability of matching a countable crater.

        Raises:
            InputError: ``features`` is not a finite (K, len(FEATURES)) array.
        """
        x = np.asarray(features, np.float32)
        if x.ndim != 2 or x.shape[1] != len(FEATURES) or not np.isfinite(x).all():
            raise InputError(f"rescorer features: expected finite (K, {len(FEATURES)}), got "
                             f"shape {x.shape}")
        if not len(x):
            return np.zeros(0, np.float32)
        prob = self.session.run([PROBABILITIES_NAME], {FEATURES_NAME: x})[0]
        return np.clip(np.asarray(prob, np.float32)[:, -1], 0.0, 1.0)

    def fitted_for(self, detector: str | os.PathLike, box_refiner: str | os.PathLike,
                   small_read: dict[str, float] | None = None) -> bool:
        """Whether this file was fitted on the scores of the file ``detector`` with the file
        ``box_refiner`` (same bytes), read as ``small_read`` says (``SmallBoxReadConfig.record``
        of ``--small-read``; None: one read, as a file that records none was fitted)."""
        want = self.fitted_with
        if want["small_read"] != small_read:
            return False
        try:
            return bool(want["detector"] and want["box_refiner"]
                        and want["detector"].get("sha256") == file_digest(detector)
                        and want["box_refiner"].get("sha256") == file_digest(box_refiner))
        except OSError:
            return False
