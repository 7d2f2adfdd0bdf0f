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
from typing import Any

import numpy as np
from squeezed_read import add_raw_read_arguments, write_raw_read

from lunarnav_ml.eval.smallread import add_small_read_arguments, small_read_config
from lunarnav_ml.eval.tta import _unmirror


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
    add_raw_read_arguments(p)
    add_small_read_arguments(p)
    args = p.parse_args(argv)
    return write_raw_read("mirrored", args, lambda load: MirroredRead(
        load(args.model, args.threads, small_read=small_read_config(args))))


if __name__ == "__main__":
    sys.exit(main())
