"""Onboard time of the detector with and without a second read of its small boxes.

Each design is a set of `lunarnav eval` read flags (``--small-read``, ``--small-read-band``,
``--box-rescorer``, ``--tta``) on top of the shipped box refiner. Every design reads
the same frames; a frame's time is the median over ``--repeats`` reads of it (after one warm-up
read), and the design's time the median over the frames; the designs take turns frame by frame,
round by round. Prints one row per design, in ms, and its ratio to the first design.

    .venv/bin/python benchmarks/time_small_read.py \\
        --frames data/protocol8/mono_val1024/annotations.shard-0-of-4.json --n 4 \\
        --design= --design="--small-read 640" \\
        --design="--small-read 640 --small-read-band 0.15 0.6"
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

from lunarnav_ml.data.coco import read_coco, read_image
from lunarnav_ml.eval.cli import (
    add_box_refiner_arguments,
    add_box_rescorer_arguments,
    predictor_from_args,
)
from lunarnav_ml.eval.smallread import add_small_read_arguments
from lunarnav_ml.eval.tta import add_tta_arguments
from lunarnav_ml.runtime.cli import DEFAULT_CONF


def design_parser() -> argparse.ArgumentParser:
    """The read flags a design may give, as the commands parse them."""
    p = argparse.ArgumentParser(prog="design", add_help=False)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--img-size", type=int, default=None)
    add_tta_arguments(p)
    add_small_read_arguments(p)
    add_box_refiner_arguments(p)
    add_box_rescorer_arguments(p)
    return p


def read_frames(annotations: Path, n: int) -> list:
    """``n`` frames of a COCO file spread over it (every len // n-th), RGB."""
    _, records = read_coco(annotations)
    return [read_image(r) for r in records[::max(1, len(records) // n)][:n]]


def time_designs(flags: list[str], model: Path, frames: list, conf: float, repeats: int
                 ) -> list[float]:
    """Per design, the median over the frames of the median read time of each frame, ms.

    The designs take turns: each round reads every frame once by every design, so a drift of
    the host's pace (another tenant, the clock) reaches them all alike."""
    parser = design_parser()
    predictors = [predictor_from_args(parser.parse_args(shlex.split(f)), model) for f in flags]
    for predictor in predictors:  # warm-up: allocations, onnxruntime sessions
        for image in frames:
            predictor.predict([image], conf_thres=conf)
    reads = np.zeros((len(flags), len(frames), repeats))
    for r in range(repeats):
        for d, predictor in enumerate(predictors):
            for f, image in enumerate(frames):
                t0 = time.perf_counter()
                predictor.predict([image], conf_thres=conf)
                reads[d, f, r] = time.perf_counter() - t0
    return [1e3 * float(np.median(np.median(per, axis=1))) for per in reads]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=Path, required=True, help="a COCO annotations file")
    p.add_argument("--n", type=int, default=4, help="frames to read")
    p.add_argument("--model", type=Path, default=Path("lunarnav_ml/weights/small.pt"))
    p.add_argument("--design", action="append", required=True,
                   help="read flags, as --design=\"FLAGS\"; --design= is the one read (repeatable)")
    p.add_argument("--conf", type=float, default=DEFAULT_CONF,
                   help="score floor, as `lunarnav localize` runs (default %(default)s)")
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--threads", type=int, default=1, help="torch threads")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    frames = read_frames(args.frames, args.n)
    print(f"{len(frames)} frames of {args.frames}, {args.model}, torch threads {args.threads}, "
          f"conf {args.conf}, median of {args.repeats}")
    times = time_designs(args.design, args.model, frames, args.conf, args.repeats)
    for flags, ms in zip(args.design, times, strict=True):
        print(f"{ms:8.1f} ms  x{ms / times[0]:5.2f}  {flags or '(one read)'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
