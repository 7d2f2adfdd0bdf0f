"""Test-time augmentation on real labelled frames: which sides and mirroring, for which models.

Each model runs once per (input side, mirrored or not) over the split; every design (a set of
side scales, with or without mirroring) then fuses its passes with weighted boxes fusion
(``lunarnav_ml.eval.tta``), so the designs compare on identical passes. Prints crater recall at
1/3/5/10 detections per image and AP50 per model and design, the mean over the models, and with
``--timing`` the time per frame of one pass against the default design.

    .venv/bin/python benchmarks/bench_tta.py --gt data/real/chandai_v5/valid/annotations.json \\
        --model ft224_60=runs/ft224_60/checkpoints/best-074-010191.ckpt ...
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from lunarnav_ml.eval.predict import iter_batches
from lunarnav_ml.eval.tta import DEFAULT_SCALES, TTAConfig, TTAPredictor, fuse_passes
from lunarnav_ml.realdata.transfer import transfer_metrics
from lunarnav_ml.training.api import load_detector

# the designs compared on `valid/` when the default was chosen (BENCHMARKS.md, issue 7)
DESIGNS = ["1", "1+flip", "0.75,0.875,1,1.125,1.25", "0.75,0.875,1,1.125,1.25+flip",
           "0.6,0.8,1,1.2+flip", "0.571,0.714,0.857,1,1.143+flip", "0.8,1,1.2+flip",
           "0.6,0.8,1,1.2,1.4+flip", "0.667,0.833,1+flip", "1,1.2,1.4+flip"]
DEFAULT_DESIGN = ",".join(f"{s:g}" for s in DEFAULT_SCALES) + "+flip"


def parse_design(text: str) -> TTAConfig:
    scales, _, flip = text.partition("+")
    if flip not in ("", "flip"):
        raise SystemExit(f"design {text!r}: expected SCALES[,SCALES...][+flip]")
    return TTAConfig(scales=tuple(float(s) for s in scales.split(",")), flip=flip == "flip")


def parse_model(text: str) -> tuple[str, Path, int | None]:
    name, _, rest = text.partition("=")
    path, _, side = rest.partition("@")
    if not name or not path:
        raise SystemExit(f"--model {text!r}: expected NAME=CHECKPOINT[@SIDE]")
    return name, Path(path), int(side) if side else None


def passes_by_side(detector, gt: dict, root: Path, sides: list[int]) -> dict:
    """{(side, mirrored): {image id: detections}} for every side, each run once."""
    out: dict = {}
    for side in sides:
        tta = TTAPredictor(detector, TTAConfig(scales=(side / detector.img_size,), flip=True))
        for records, images in iter_batches(gt, root, 8):
            plain, mirrored = tta.run_passes(images)
            for record, p, m in zip(records, plain, mirrored):
                out.setdefault((side, False), {})[record["id"]] = p
                out.setdefault((side, True), {})[record["id"]] = m
    return out


def design_results(detector, design: TTAConfig, cache: dict, gt: dict) -> list[dict]:
    sides = TTAPredictor(detector, design).sides
    keys = [(s, f) for s in sides for f in ((False, True) if design.flip else (False,))]
    results = []
    for image in gt["images"]:
        preds = [cache[k][image["id"]] for k in keys]
        fused = preds[0] if len(preds) == 1 else fuse_passes(
            preds, (image["height"], image["width"]), design.fuse_iou)
        results += detector.to_coco_results([fused], [image["id"]])
    return results


def time_per_frame(predictor, gt: dict, root: Path, n: int) -> float:
    """Median ms per frame, batch 1, over the first ``n`` frames (one warm-up frame)."""
    frames = [images[0] for _, images in iter_batches({"images": gt["images"][:n + 1]}, root, 1)]
    predictor.predict(frames[:1])
    times = []
    for frame in frames[1:]:
        start = time.perf_counter()
        predictor.predict([frame])
        times.append(1e3 * (time.perf_counter() - start))
    return float(np.median(times))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gt", type=Path, required=True, help="real validation annotations.json")
    ap.add_argument("--model", action="append", required=True, metavar="NAME=CKPT[@SIDE]",
                    help="checkpoint to run (repeat); @SIDE: its network side, default its own")
    ap.add_argument("--designs", nargs="+", default=DESIGNS, metavar="SCALES[+flip]")
    ap.add_argument("--timing", type=int, default=0, metavar="N",
                    help="also time one pass and the default design on N frames")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    gt, root = json.loads(args.gt.read_text()), args.gt.parent
    designs = {d: parse_design(d) for d in args.designs}
    rows = []
    for name, path, side in map(parse_model, args.model):
        detector = load_detector(path, side)
        sides = sorted({s for d in designs.values() for s in TTAPredictor(detector, d).sides})
        cache = passes_by_side(detector, gt, root, sides)
        for text, design in designs.items():
            m = transfer_metrics(gt, design_results(detector, design, cache, gt))["all"]
            crater = m["per_class"]["crater"]
            row = {"model": name, "design": text, **{k: crater[f"recall@{k}"] for k in (1, 3, 5, 10)},
                   "AP50": crater["AP50"], "rock@5": m["per_class"]["rock"]["recall@5"],
                   "artifact@5": m["per_class"]["artifact"]["recall@5"]}
            rows.append(row)
            print(f"{name:10s} {text:32s} crater recall@1/3/5/10 " + " / ".join(
                f"{row[k]:.3f}" for k in (1, 3, 5, 10)) + f"  AP50 {row['AP50']:.3f}  rock@5 "
                f"{row['rock@5']:.3f}  artifact@5 {row['artifact@5']:.3f}", flush=True)
        if args.timing:
            one = time_per_frame(detector, gt, root, args.timing)
            tta = time_per_frame(TTAPredictor(detector, parse_design(DEFAULT_DESIGN)), gt, root,
                                 args.timing)
            print(f"{name:10s} ms per frame (batch 1, {args.threads} threads): one pass "
                  f"{one:.1f}, {DEFAULT_DESIGN} {tta:.1f}", flush=True)
    print("\nmean over the models: crater recall@5 / AP50")
    for text in designs:
        sel = [r for r in rows if r["design"] == text]
        print(f"  {text:32s} {np.mean([r[5] for r in sel]):.3f} / "
              f"{np.mean([r['AP50'] for r in sel]):.3f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
