"""A raw read of a band of rows squeezed across: far craters seen as nearer ones.

On the paper's camera (1.5 m up) a crater's box is about range / 1.5 times wider than high: a key
crater 20 m ahead is a 13:1 box, which the detector often boxes in half (BENCHMARKS.md, issue 4,
"The second read's band", session 77). This read takes the rows ``--band`` of each frame at the
vertical scale a ``--side`` px read gives the whole frame and at ``--squeeze`` times that across
(OpenCV's area resampling), so that a far crater's box is as flat as a nearer one's. Its crater
and rock boxes, mapped back to the frame, are kept when they are under ``--below`` px high at the
model's own side (as ``--small-read`` keeps its second read's). The output is a raw read (COCO
results, no box refiner), for ``benchmarks/replay_candidates.py --join`` beside the band read of
``lunarnav eval --small-read 640 --small-read-band 0.15 0.6 --no-box-refiner``. Session 79
(issue 4, "A read squeezed across"): on the paper-mono validation quarter it gave a box at IoU >=
0.5 to 0.93 of the far key craters against the band read's 0.83, but joined it did not pass its
rule; not adopted.

    .venv/bin/python benchmarks/squeezed_read.py --gt $MV --out S.json
    .venv/bin/python benchmarks/replay_candidates.py --gt $MV --raw RAW/detections.json \\
        --join S.json --rescorer lunarnav_ml/weights/box_rescorer_small_read.onnx \\
        --out R/detections.json
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from lunarnav_ml.data.coco import read_coco
from lunarnav_ml.errors import REPORTED_ERRORS, ConfigError
from lunarnav_ml.eval.predict import predict_coco
from lunarnav_ml.eval.smallread import _up
from lunarnav_ml.eval.tta import max_stride, square_side
from lunarnav_ml.utils import atomic

DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "lunarnav_ml" / "weights" / "small.pt"


class SqueezedBandRead:
    """``predict`` reads each frame's ``band`` rows at ``side / max(H, W)`` down and ``squeeze``
    times that across; boxes in frame px, those under ``below_px`` high at the model's own
    side."""

    def __init__(self, predictor: Any, side: int, band: tuple[float, float], squeeze: float,
                 below_px: float) -> None:
        if not (0.0 <= band[0] < band[1] <= 1.0):
            raise ConfigError(f"--band: expected TOP BOTTOM with 0 <= TOP < BOTTOM <= 1, got "
                              f"{list(band)}")
        for name, value in (("side", side), ("squeeze", squeeze), ("below", below_px)):
            if not value > 0:  # NaN fails too
                raise ConfigError(f"--{name}: expected a positive number, got {value}")
        self.predictor, self.side, self.band = predictor, side, band
        self.squeeze, self.below_px = squeeze, below_px
        self.base_side = square_side(predictor, "squeezed read")
        self.stride = max_stride(predictor)

    def predict(self, images: list[np.ndarray], conf_thres: float = 0.001,
                iou_thres: float = 0.6, max_det: int = 300) -> list[dict[str, np.ndarray]]:
        try:
            return [self.read(image, conf_thres, iou_thres, max_det) for image in images]
        finally:
            self.predictor.set_img_size(self.base_side)

    def read(self, image: np.ndarray, conf_thres: float, iou_thres: float, max_det: int
             ) -> dict[str, np.ndarray]:
        h, w = image.shape[:2]
        y0 = int(np.floor(self.band[0] * h))
        y1 = max(int(np.ceil(self.band[1] * h)), y0 + 1)
        scale = self.side / max(h, w)
        rows = max(1, round((y1 - y0) * scale))
        cols = max(1, round(w * scale * self.squeeze))
        band = cv2.resize(np.ascontiguousarray(image[y0:y1]), (cols, rows),
                          interpolation=cv2.INTER_AREA)
        self.predictor.set_img_size((_up(rows, self.stride), _up(cols, self.stride)))
        (pred,) = self.predictor.predict([band], conf_thres, iou_thres, max_det)
        boxes = np.asarray(pred["boxes"], np.float32).reshape(-1, 4).copy()
        boxes[:, [0, 2]] *= w / cols
        boxes[:, [1, 3]] = boxes[:, [1, 3]] * ((y1 - y0) / rows) + y0
        keep = (boxes[:, 3] - boxes[:, 1]) * self.base_side / max(h, w) < self.below_px
        return {"boxes": boxes[keep],
                "scores": np.asarray(pred["scores"], np.float32).reshape(-1)[keep],
                "labels": np.asarray(pred["labels"], np.int64).reshape(-1)[keep]}


def add_raw_read_arguments(p: argparse.ArgumentParser) -> None:
    """The options of a script that writes a raw read of a set: ``--gt``, ``--out``,
    ``--model``, ``--threads``, ``--no-progress``."""
    p.add_argument("--gt", type=Path, required=True, help="the set's COCO annotations")
    p.add_argument("--out", type=Path, required=True, help="COCO results file to write")
    p.add_argument("--model", type=Path, default=DEFAULT_MODEL,
                   help="detector checkpoint or ONNX file (default: the shipped small.pt)")
    p.add_argument("--threads", type=int, default=2, help="onnxruntime threads (an ONNX model)")
    p.add_argument("--no-progress", action="store_true")


def write_raw_read(name: str, args: argparse.Namespace,
                   reader: Callable[[Callable[..., Any]], Any]) -> int:
    """Read the set ``args.gt`` with ``reader(load_predictor)`` (its ``predict``; it loads the
    model with the given function) and write the COCO results to ``args.out``; the exit
    status, a one-line error for bad input."""
    try:
        from lunarnav_ml.eval.cli import load_predictor

        gt, _ = read_coco(args.gt)
        results = predict_coco(reader(load_predictor), gt, args.gt.parent, desc=name,
                               origin=str(args.gt), progress=not args.no_progress)
        atomic.write_json(args.out, results, indent=None)
    except REPORTED_ERRORS as err:
        print(f"{name}_read: error: {err}", file=sys.stderr)
        return 2
    print(f"{len(results)} results -> {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_raw_read_arguments(p)
    p.add_argument("--side", type=int, default=640, help="the read's scale down the rows")
    p.add_argument("--band", type=float, nargs=2, default=(0.15, 0.6), metavar=("TOP", "BOTTOM"))
    p.add_argument("--squeeze", type=float, default=0.5, help="scale across, of --side's")
    p.add_argument("--below", type=float, default=15.0,
                   help="keep boxes under this many px high at the model's own side")
    args = p.parse_args(argv)
    return write_raw_read("squeezed", args, lambda load: SqueezedBandRead(
        load(args.model, args.threads), args.side, tuple(args.band), args.squeeze,
        args.below))


if __name__ == "__main__":
    sys.exit(main())
