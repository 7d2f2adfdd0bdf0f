"""A raw read of mirrored frames, its boxes mapped back: the second pass of a mirror fusion.

``lunarnav eval --task detection --no-box-refiner`` writes a raw read (the network's boxes, no
box refiner); this script writes the same read of each frame mirrored left to right, with the
same ``--small-read`` (and band) as that command, its boxes mapped back to the frame. For
``benchmarks/replay_candidates.py --join M.json --join-fuse wbf``, which fuses the two reads by
weighted boxes fusion (as ``--tta`` fuses its passes) before the box refiner: a flat box's
height, where a 3 px error costs a 12 px box a quarter of its IoU, is then the mean of two
reads (session 83, BENCHMARKS.md issue 4).

    .venv/bin/python benchmarks/mirrored_read.py --gt $MV --model lunarnav_ml/weights/small_grid.pt \\
        --small-read 640 --small-read-band 0.15 0.6 --out M.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from lunarnav_ml.data.coco import read_coco
from lunarnav_ml.errors import REPORTED_ERRORS
from lunarnav_ml.eval.predict import predict_coco
from lunarnav_ml.eval.smallread import add_small_read_arguments, small_read_config
from lunarnav_ml.eval.tta import _unmirror
from lunarnav_ml.utils import atomic

DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "lunarnav_ml" / "weights" / "small.pt"


class MirroredRead:
    """``predict`` as ``predictor``'s, on each image mirrored left to right; boxes in the
    original image's pixels. Other attributes are ``predictor``'s."""

    def __init__(self, predictor: Any) -> None:
        self.predictor = predictor

    def __getattr__(self, name: str) -> Any:
        if name == "predictor":
            raise AttributeError(name)
        return getattr(self.predictor, name)

    def predict(self, images: list[np.ndarray], conf_thres: float = 0.001,
                iou_thres: float = 0.6, max_det: int = 300) -> list[dict[str, np.ndarray]]:
        mirrored = [np.ascontiguousarray(image[:, ::-1]) for image in images]
        preds = self.predictor.predict(mirrored, conf_thres, iou_thres, max_det)
        return [_unmirror(p, image.shape[1]) for p, image in zip(preds, images, strict=True)]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--gt", type=Path, required=True, help="the set's COCO annotations")
    p.add_argument("--out", type=Path, required=True, help="COCO results file to write")
    p.add_argument("--model", type=Path, default=DEFAULT_MODEL,
                   help="detector checkpoint or ONNX file (default: the shipped small.pt)")
    p.add_argument("--threads", type=int, default=2, help="onnxruntime threads (an ONNX model)")
    p.add_argument("--no-progress", action="store_true")
    add_small_read_arguments(p)
    args = p.parse_args(argv)
    try:
        from lunarnav_ml.eval.cli import load_predictor

        gt, _ = read_coco(args.gt)
        predictor = load_predictor(args.model, args.threads,
                                   small_read=small_read_config(args))
        results = predict_coco(MirroredRead(predictor), gt, args.gt.parent, desc="mirrored",
                               origin=str(args.gt), progress=not args.no_progress)
        atomic.write_json(args.out, results, indent=None)
    except REPORTED_ERRORS as err:
        print(f"mirrored_read: error: {err}", file=sys.stderr)
        return 2
    print(f"{len(results)} results -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
