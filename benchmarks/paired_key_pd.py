"""Is one read's key-crater Pd really above another's? A paired bootstrap over the frames.

Each read is a ``lunarnav eval --task detection --out D`` folder of the same labelled set: its
``detections.json`` and the operating threshold in its ``metrics.json`` (picked on validation).
The key craters (D >= 5 m, near rim within 20 m, as the report counts them) are matched at each
read's own threshold. Printed: both key Pd, the craters found by one read and not the other,
and the difference B - A with its 95 % interval from resampling the frames with replacement
(the same draw for both reads), and the share of draws in which B is not above A. A crater
counted once per frame is not independent of its neighbours in the frame; resampling frames
keeps that (docs/training.md, "How far apart two reads must be").

    python benchmarks/paired_key_pd.py --gt data/protocol8/mono_test1024/annotations.json \\
        --a outputs/s79/monotest_all_default --b outputs/s79/monotest_all_b15_rs
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np
from key_pd_bins import read_eval

from lunarnav_ml.data.coco import read_coco
from lunarnav_ml.errors import InputError, LunarNavError
from lunarnav_ml.eval.pd import in_key_set, match_craters


def key_found(gt: dict[str, Any], dets: list[dict[str, Any]], threshold: float
              ) -> tuple[np.ndarray, np.ndarray]:
    """Per key crater of ``gt`` (in :func:`match_craters`' order): its image id, and whether
    ``dets`` find it at ``threshold``."""
    match = match_craters(gt, dets, threshold)
    key = np.array([in_key_set(a) for a in match.gt], bool)
    image = np.array([a["image_id"] for a in match.gt], np.int64)
    return image[key], match.hit[key]


def paired_bootstrap(image: np.ndarray, a: np.ndarray, b: np.ndarray, draws: int = 10000,
                     seed: int = 0) -> dict[str, float]:
    """Pooled Pd of ``a`` and ``b`` (bool per crater, same craters) and B - A with its 95 %
    interval over ``draws`` resamplings of the frames (``image`` per crater); ``p_not_above``:
    the share of draws with B - A <= 0."""
    frames, idx = np.unique(image, return_inverse=True)
    n = np.bincount(idx, minlength=len(frames)).astype(np.float64)
    fa = np.bincount(idx, weights=a, minlength=len(frames))
    fb = np.bincount(idx, weights=b, minlength=len(frames))
    rng = np.random.default_rng(seed)
    diff = np.empty(draws)
    for start in range(0, draws, 500):  # 500 draws of the frames at a time
        counts = np.stack([np.bincount(rng.integers(0, len(frames), len(frames)),
                                       minlength=len(frames))
                           for _ in range(min(500, draws - start))]).astype(np.float64)
        diff[start:start + len(counts)] = (counts @ (fb - fa)) / np.maximum(counts @ n, 1)
    lo, hi = np.percentile(diff, [2.5, 97.5])
    return {"pd_a": float(a.mean()), "pd_b": float(b.mean()), "diff": float(b.mean() - a.mean()),
            "lo": float(lo), "hi": float(hi), "p_not_above": float(np.mean(diff <= 0))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gt", required=True, help="the COCO annotations both reads were made on")
    ap.add_argument("--a", required=True, type=Path, help="`lunarnav eval --out` folder A")
    ap.add_argument("--b", required=True, type=Path, help="`lunarnav eval --out` folder B")
    ap.add_argument("--draws", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    try:
        if args.draws < 1:
            raise InputError(f"--draws: expected at least 1, got {args.draws}")
        gt = read_coco(args.gt, check_files=False)[0]
        (image, a), (_, b) = (key_found(gt, *read_eval(folder)) for folder in (args.a, args.b))
        if not len(a):
            raise InputError(f"{args.gt}: no key craters (D >= 5 m, near rim <= 20 m)")
        figures = paired_bootstrap(image, a, b, args.draws, args.seed)
    except LunarNavError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"key craters {len(a)} on {len(np.unique(image))} frames: A {figures['pd_a']:.3f}, "
          f"B {figures['pd_b']:.3f}; found by B only {int((b & ~a).sum())}, by A only "
          f"{int((a & ~b).sum())}")
    print(f"B - A {figures['diff']:+.3f}, 95 % [{figures['lo']:+.3f}, {figures['hi']:+.3f}] over "
          f"{args.draws} draws of the frames; B not above A in {figures['p_not_above']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
