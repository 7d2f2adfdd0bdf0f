"""Replay a cached raw read through the box refiner (and a rescorer), with extra crater candidates.

A raw read is the ``detections.json`` of ``lunarnav eval --task detection --no-box-refiner``:
the network's boxes before the box refiner. Replaying it refines and rescores the crater boxes
as the live read does (``BoxRefinedDetector.refine``), without running the network again; on the
paper-mono validation quarter the replay without candidates gave the live read's figures to the
digit. The candidates are ways to box a crater the detector found in part (BENCHMARKS.md, issue
4: "The second read's band", session 77, and "Half-rim boxes grown to the whole crater",
session 78); none was adopted:

- ``grow-sides``: each flat crater box (width >= ``--flat`` heights) grown by ``--grow`` of its
  width to the left, and again to the right;
- ``grow-centre``: widened by ``--grow`` / 2 of its width on each side;
- ``unions``: the union of two flat crater boxes that share at least ``--rows`` of their rows,
  lie no more than ``--gap`` of the narrower width apart and together are ``--wider`` times
  wider than either;
- ``extend``: each flat crater box grown to the whole crater by a trained flat-box extender
  (``--extender E.pt``, ``benchmarks/flat_extender.py``; session 83).

``--refine twice`` runs the box refiner again on its own boxes (a crop around the refined box);
``--quality refined`` scores each box with the quality the refiner gives the once-refined box
instead of the detector's box (session 79's "The box refiner run twice"; not adopted).

A candidate takes its box's raw score (the higher of the two for a union) times ``--factor``.
Only crater boxes with a raw score of at least ``--floor`` make candidates, at most ``--top`` a
frame, the highest first. ``--join RAW2 [RAW3 ...]`` joins more raw reads of the same set first
(their boxes and the first read's, per-class NMS at ``--iou``, at most 300 a frame, as the
second read of ``--small-read`` joins its boxes; e.g. ``benchmarks/squeezed_read.py``'s);
``--join-fuse wbf`` fuses them by weighted boxes fusion instead (``benchmarks/mirrored_read.py``'s
mirrored read; session 83).
Writes COCO results for ``lunarnav eval --test-results``:

    .venv/bin/python benchmarks/replay_candidates.py --gt $MV --raw RAW/detections.json \\
        --candidates grow-sides --factor 0.3 \\
        --rescorer lunarnav_ml/weights/box_rescorer_small_read.onnx --out R/detections.json
    .venv/bin/lunarnav eval --task detection --gt $MV --test-results R/detections.json \\
        --val-gt $MV --val-results R/detections.json --out R/eval
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from pathlib import Path

import numpy as np

from lunarnav_ml.data.coco import read_coco, read_image
from lunarnav_ml.errors import REPORTED_ERRORS, ConfigError, InputError
from lunarnav_ml.eval.predict import read_coco_results, to_coco_results
from lunarnav_ml.geometry._checks import as_image
from lunarnav_ml.geometry.boxrefine import CRATER_LABEL, BoxRefinedDetector, BoxRefiner
from lunarnav_ml.utils import atomic

CANDIDATES = ("none", "grow-sides", "grow-centre", "grow-both", "unions", "extend")


def flat_boxes(pred: dict[str, np.ndarray], args: argparse.Namespace
               ) -> tuple[np.ndarray, np.ndarray]:
    """The frame's flat crater boxes (xyxy) that make candidates, and their raw scores: score >=
    ``floor``, the ``top`` highest, width >= ``flat`` heights."""
    boxes, scores = pred["boxes"], pred["scores"]
    idx = np.nonzero((pred["labels"] == CRATER_LABEL) & (scores >= args.floor))[0]
    idx = idx[np.argsort(-scores[idx], kind="stable")][:args.top]
    b = boxes[idx]
    flat = (b[:, 2] - b[:, 0]) >= args.flat * (b[:, 3] - b[:, 1])
    return b[flat], scores[idx][flat]


def grown(b: np.ndarray, s: np.ndarray, mode: str, grow: float) -> tuple[np.ndarray, np.ndarray]:
    """Flat boxes ``b`` (xyxy) grown: ``sides`` by ``grow`` widths to the left and to the right,
    ``centre`` by ``grow`` / 2 on each side, ``both``; each with its box's score."""
    w = b[:, 2] - b[:, 0]
    out = []
    if mode in ("sides", "both"):
        out += [np.column_stack([b[:, 0] - grow * w, b[:, 1:]]),
                np.column_stack([b[:, :2], b[:, 2] + grow * w, b[:, 3]])]
    if mode in ("centre", "both"):
        out += [np.column_stack([b[:, 0] - grow * w / 2, b[:, 1], b[:, 2] + grow * w / 2,
                                 b[:, 3]])]
    return np.concatenate(out).reshape(-1, 4), np.tile(s, len(out))


def unions(b: np.ndarray, s: np.ndarray, rows: float, gap: float, wider: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """The unions of pairs of flat boxes ``b`` (xyxy) side by side (see the module's doc), each
    with the higher of the two scores."""
    out_b, out_s = [], []
    w = b[:, 2] - b[:, 0]
    for i in range(len(b)):
        for j in range(i + 1, len(b)):
            shared = min(b[i, 3], b[j, 3]) - max(b[i, 1], b[j, 1])
            span = max(b[i, 3], b[j, 3]) - min(b[i, 1], b[j, 1])
            apart = max(b[i, 0], b[j, 0]) - min(b[i, 2], b[j, 2])  # > 0: a gap between them
            x0, x1 = min(b[i, 0], b[j, 0]), max(b[i, 2], b[j, 2])
            if shared >= rows * span and apart <= gap * min(w[i], w[j]) \
                    and x1 - x0 >= wider * max(w[i], w[j]):
                out_b.append([x0, min(b[i, 1], b[j, 1]), x1, max(b[i, 3], b[j, 3])])
                out_s.append(max(s[i], s[j]))
    return np.array(out_b, np.float64).reshape(-1, 4), np.array(out_s, np.float32)


def candidates(pred: dict[str, np.ndarray], shape: tuple[int, ...], args: argparse.Namespace,
               extend=None) -> dict[str, np.ndarray]:
    """One frame's raw read with ``args.candidates`` added as crater boxes (clipped to the
    frame, scores x ``factor``); ``extend`` (for ``extend``): the frame's flat boxes (x, y, w,
    h) -> the whole craters' boxes, e.g. a :class:`FlatExtender` on the frame."""
    if args.candidates == "none":
        return pred
    b, s = flat_boxes(pred, args)
    if args.candidates == "extend":
        xywh = extend(np.column_stack([b[:, :2], b[:, 2:] - b[:, :2]]))
        extra, extra_s = np.column_stack([xywh[:, :2], xywh[:, :2] + xywh[:, 2:]]), s
    elif args.candidates == "unions":
        extra, extra_s = unions(b, s, args.rows, args.gap, args.wider)
    else:
        extra, extra_s = grown(b, s, args.candidates.split("-")[1], args.grow)
    h, w = shape[:2]
    extra = np.clip(extra, 0.0, [w, h, w, h])
    return {"boxes": np.concatenate([pred["boxes"], extra]),
            "scores": np.concatenate([pred["scores"], extra_s * args.factor]).astype(np.float32),
            "labels": np.concatenate([pred["labels"],
                                      np.full(len(extra), CRATER_LABEL, np.int64)])}


def raw_reads(*paths: Path, iou: float = 0.6, max_det: int = 300, fuse: str = "nms",
              shapes: dict[int, tuple[int, int]] | None = None
              ) -> dict[int, dict[str, np.ndarray]]:
    """Results files as per-image predictions (xyxy boxes, scores, labels); two or more files
    (reads of one set) joined: per-class NMS at ``iou``, at most ``max_det`` a frame, or with
    ``fuse`` "wbf" weighted boxes fusion at ``iou`` (as ``--tta`` fuses its passes; needs each
    image's ``shapes`` (height, width))."""
    from lunarnav_ml.eval.tta import fuse_passes
    from lunarnav_ml.runtime.nms import batched_nms
    from lunarnav_ml.training.box_rescorer import _prediction as as_prediction

    per: dict[int, list[list[dict]]] = {}
    for k, path in enumerate(paths):
        for det in read_coco_results(path):
            per.setdefault(det["image_id"], [[] for _ in paths])[k].append(det)
    out = {}
    for image_id, by_file in per.items():
        preds = [as_prediction(dets) for dets in by_file]
        if len(paths) > 1 and fuse == "wbf":
            fused = fuse_passes(preds, shapes[image_id], iou, max_det=max_det)
            out[image_id] = {**fused, "boxes": fused["boxes"].astype(np.float64)}
            continue
        pred = {k: np.concatenate([p[k] for p in preds]) for k in preds[0]}
        if len(paths) > 1:  # in float32, as the second read's own merge
            keep = batched_nms(pred["boxes"].astype(np.float32), pred["scores"],
                               pred["labels"], iou)[:max_det]
            pred = {k: v[keep] for k, v in pred.items()}
        out[image_id] = pred
    return out


class TwoPassRefiner:
    """A :class:`BoxRefiner` run a second time on its own boxes: ``refine`` "twice" returns the
    second pass's edges ("once": the first's); ``quality`` "refined" scores each box with the
    quality of the once-refined box, the second pass's input ("detector": the first pass's, of
    the detector's box, as the shipped path does)."""

    def __init__(self, refiner: BoxRefiner, refine: str, quality: str) -> None:
        self.refiner, self.refine, self.quality = refiner, refine, quality
        self.has_quality = refiner.has_quality

    def refine_scored(self, gray: np.ndarray, boxes_xywh: np.ndarray, quality: bool = True
                      ) -> tuple[np.ndarray, np.ndarray | None]:
        once, q_detector = self.refiner.refine_scored(gray, boxes_xywh, quality)
        if len(once) == 0:
            return once, q_detector
        twice, q_refined = self.refiner.refine_scored(gray, once,
                                                      quality and self.quality == "refined")
        return (twice if self.refine == "twice" else once,
                q_refined if self.quality == "refined" else q_detector)


def replay(gt: Path, raw: Path, args: argparse.Namespace, log=print) -> list[dict]:
    """COCO results of the raw read ``raw`` of the images of ``gt`` (joined with
    ``args.join``, when given), candidates added, through the box refiner (and
    ``args.rescorer``), as ``lunarnav eval`` would score them."""
    _, records = read_coco(gt)
    files = [raw] + list(args.join or [])
    shapes = {r.image_id: (r.height, r.width) for r in records}
    reads = raw_reads(*files, iou=args.fuse_iou if args.join_fuse == "wbf" else args.iou,
                      fuse=args.join_fuse, shapes=shapes)
    unknown = sorted(set(reads) - {r.image_id for r in records})
    if unknown:
        raise InputError(f"{' or '.join(map(str, files))}: image_id {unknown[0]} is not an "
                         f"image of {gt}")
    rescorer = None
    if args.rescorer is not None:
        from lunarnav_ml.geometry.boxrescore import BoxRescorer

        rescorer = BoxRescorer(args.rescorer)
    refiner = BoxRefiner(args.box_refiner)
    if (args.refine, args.quality) != ("once", "detector"):
        refiner = TwoPassRefiner(refiner, args.refine, args.quality)
    detector = BoxRefinedDetector(None, refiner, rescorer)
    extender = None
    if args.candidates == "extend":
        if args.extender is None:
            raise ConfigError("--candidates extend: give --extender E.pt")
        from flat_extender import FlatExtender

        extender = FlatExtender(args.extender)
    empty = {"boxes": np.zeros((0, 4)), "scores": np.zeros(0, np.float32),
             "labels": np.zeros(0, np.int64)}
    results, added, t0 = [], 0, time.perf_counter()
    for k, record in enumerate(records):
        image = read_image(record)
        pred = reads.get(record.image_id, empty)
        extend = None
        if extender is not None:
            extend = functools.partial(extender, as_image("image", image))
        more = candidates(pred, image.shape, args, extend)
        added += len(more["scores"]) - len(pred["scores"])
        out = detector.above(detector.refine(image, more, args.iou), args.conf)
        results += to_coco_results(out, record.image_id)
        if (k + 1) % 100 == 0 or k + 1 == len(records):
            log(f"{k + 1}/{len(records)} frames, {added} candidates added, "
                f"{time.perf_counter() - t0:.0f} s")
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--gt", type=Path, required=True, help="the read set's COCO annotations")
    p.add_argument("--raw", type=Path, required=True,
                   help="its raw read: detections.json of `lunarnav eval --no-box-refiner`")
    p.add_argument("--out", type=Path, required=True, help="COCO results file to write")
    p.add_argument("--join", type=Path, nargs="+", default=None,
                   help="more raw reads of the set, joined to the first")
    p.add_argument("--join-fuse", choices=("nms", "wbf"), default="nms",
                   help="how --join joins the reads: per-class NMS at --iou, or weighted boxes "
                        "fusion at --fuse-iou")
    p.add_argument("--fuse-iou", type=float, default=0.55, help="(wbf) boxes fused above it")
    p.add_argument("--candidates", choices=CANDIDATES, default="none")
    p.add_argument("--extender", type=Path, default=None,
                   help="(extend) a flat extender, benchmarks/flat_extender.py")
    p.add_argument("--box-refiner", type=Path, default=None, help="default: the shipped one")
    p.add_argument("--rescorer", type=Path, default=None, help="a box rescorer's ONNX file")
    p.add_argument("--refine", choices=("once", "twice"), default="once",
                   help="box refiner passes over each crater box")
    p.add_argument("--quality", choices=("detector", "refined"), default="detector",
                   help="the quality that scores a box: of the detector's box, or of the "
                        "once-refined box")
    p.add_argument("--flat", type=float, default=3.0, help="flat: width >= this x height")
    p.add_argument("--grow", type=float, default=1.0, help="(grow-*) widths added")
    p.add_argument("--rows", type=float, default=0.5, help="(unions) rows shared, at least")
    p.add_argument("--gap", type=float, default=0.25, help="(unions) apart, at most")
    p.add_argument("--wider", type=float, default=1.2, help="(unions) union's width, at least")
    p.add_argument("--floor", type=float, default=0.05, help="raw score of a box that grows")
    p.add_argument("--top", type=int, default=30, help="boxes a frame that may make candidates")
    p.add_argument("--factor", type=float, default=1.0, help="a candidate's score factor")
    p.add_argument("--conf", type=float, default=0.001, help="score floor of the results")
    p.add_argument("--iou", type=float, default=0.6, help="NMS IoU after the refiner")
    args = p.parse_args(argv)
    try:
        for name in ("flat", "grow", "rows", "wider", "factor"):
            if not getattr(args, name) > 0:  # NaN fails too
                raise ConfigError(f"--{name}: expected a positive number, got "
                                  f"{getattr(args, name)}")
        if args.top < 1:
            raise ConfigError(f"--top: expected at least 1, got {args.top}")
        results = replay(args.gt, args.raw, args, log=lambda line: print(line, flush=True))
        atomic.write_json(args.out, results, indent=None)
    except REPORTED_ERRORS as err:
        print(f"replay_candidates: error: {err}", file=sys.stderr)
        return 2
    print(f"{len(results)} results -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
