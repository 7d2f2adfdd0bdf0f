"""Why craters are missed at the operating point: a validation-split diagnosis of Pd.

For one checkpoint on one labelled split (use a validation split: the threshold is picked on
it), prints one JSON line each:

1. ``summary``: crater AP50 / AP, the threshold at 0.2 false alarms per image, Pd there (all
   craters, and D >= 5 m with the near rim within 20 m, the issue's Pd set).
2. ``localised``, per group (the Pd set, the other craters) and degradation third: how many
   craters have a crater detection at IoU >= 0.5 at any score, the median score of the best such
   detection, and how many keep one at the operating threshold. A crater found at a low score
   is a ranking miss; one with no box at IoU >= 0.5 a localisation miss.
3. ``false_alarms``: what the false alarms at the threshold overlap (a crater at IoU 0.1–0.5,
   ignored or not; a second box on a crater already found; a rock or artifact; nothing).
4. ``nms``, per ``--nms`` value: the same Pd after a stricter class-wise NMS over the detections
   (a post-processing choice made on validation).
5. ``bins`` (with ``--bins``), per label attribute (box height, degradation, depth/diameter,
   visible rim fraction, surviving bowl fraction, rim ellipse minor axis, sun zenith, near-rim
   range): crater AP50 of each bin's craters alone (the others ignored: a detection on one is
   neither hit nor false alarm), and the share of them with a crater detection at IoU >= 0.5
   at any score, which bounds the bin's recall. Where crater AP50 is lost, whatever the threshold.
6. ``montage`` (with ``--montage PNG``): crops around shallow (depth/diameter < 0.08) and fresh
   (>= 0.16) craters of the same sizes, fully in view (box 14-40 px tall, >= 80 % of the rim
   visible), each box green where a detection finds it at the operating threshold, red where
   not: whether the labelled crater can be seen at all.

7. ``parts`` (with ``--parts``; runs the model, about a minute for 300 renders at 384 px): per
   group (the Pd set / the others, by degradation third), the best-scoring candidate before
   NMS among those at IoU >= 0.5 with each crater: the median of its objectness, crater class
   probability and IoU, its head (stride), how far each box edge lies from the label's (as a
   share of the label box's width or height), and the correlation of objectness with IoU.
   Whether a low score comes from the class or from the objectness, and which edge is loose.

With ``--transfer`` the split is a real one (``lunarnav import-real``, no crater geometry):
only the NMS study runs, reported as the transfer report's recall@5 and AP50 per class.

    python benchmarks/pd_diagnosis.py --gt data/d4/val300/annotations.json \\
        --checkpoint lunarnav_ml/weights/small.pt --nms 0.6 0.5 0.45
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torchvision.ops import batched_nms, box_convert, box_iou

from lunarnav_ml.errors import InputError, LunarNavError
from lunarnav_ml.eval.coco_metrics import coco_ap
from lunarnav_ml.eval.pd import (
    MatchResult,
    in_key_set,
    is_ignored,
    match_craters,
    pick_operating_threshold,
    subset,
)
from lunarnav_ml.eval.predict import iter_batches, predict_coco
from lunarnav_ml.models.decode import decode
from lunarnav_ml.training.api import Detector, load_detector
from lunarnav_ml.utils import atomic
from lunarnav_ml.utils.jsonfile import read_json_file

CRATER = 1
THIRDS = (("fresh", 0.0, 1 / 3), ("half-degraded", 1 / 3, 2 / 3), ("degraded", 2 / 3, 1.01))


def xyxy(items: list[dict[str, Any]]) -> torch.Tensor:
    """COCO ``bbox`` (x, y, w, h) of annotations or results as an (N, 4) xyxy tensor."""
    b = torch.tensor([it["bbox"] for it in items], dtype=torch.float64).reshape(-1, 4)
    return box_convert(b, "xywh", "xyxy")


def by_image(items: list[dict[str, Any]]) -> dict[int, list[dict[str, Any]]]:
    out: dict[int, list[dict[str, Any]]] = {}
    for it in items:
        out.setdefault(it["image_id"], []).append(it)
    return out


def summary(gt: dict[str, Any], results: list[dict[str, Any]]) -> tuple[dict[str, Any], MatchResult]:
    """AP, the 0.2 FA/image threshold and Pd there; and the match at that threshold."""
    ap = coco_ap(gt, results)["per_class"]["crater"]
    thr = pick_operating_threshold(gt, results)
    match = match_craters(gt, results, thr)
    keep = np.array([in_key_set(a) for a in match.gt], dtype=bool)
    return {"crater_AP50": round(ap["AP50"], 4), "crater_AP": round(ap["AP"], 4),
            "threshold": thr, "fa_per_image": round(match.fa_per_image, 3),
            "pd_all": round(match.pd, 4), "pd_set": round(subset(match, keep).pd, 4),
            "n_pd_set": int(keep.sum())}, match


def crater_scores(gt: dict[str, Any], results: list[dict[str, Any]]) -> list[tuple]:
    """Per non-ignored crater: (in the Pd set, degradation, best score among its IoU >= 0.5
    crater detections or 0, box width, box height, annotation id)."""
    dets = by_image([r for r in results if r["category_id"] == CRATER])
    rows = []
    for img_id, anns in by_image(gt["annotations"]).items():
        anns = [a for a in anns if a["category_id"] == CRATER and not is_ignored(a)]
        d = dets.get(img_id, [])
        if not anns:
            continue
        if d:
            ok = box_iou(xyxy(anns), xyxy(d)) >= 0.5
            scores = torch.tensor([x["score"] for x in d], dtype=torch.float64)
            best = torch.where(ok, scores, torch.zeros_like(scores)).max(dim=1).values.tolist()
        else:
            best = [0.0] * len(anns)
        rows += [(in_key_set(a), a.get("degradation", 0.0), s, a["bbox"][2], a["bbox"][3],
                  a["id"]) for a, s in zip(anns, best)]
    return rows


def localised(rows: list[tuple], thr: float) -> list[dict]:
    """:func:`crater_scores` grouped: Pd set / others, by degradation third."""
    out = []
    for name, group in (("pd_set", True), ("others", False)):
        wh = np.array([r[3:5] for r in rows if r[0] == group])
        out.append({"group": name, "n": len(wh), "median_box_w": round(float(np.median(wh[:, 0])), 1),
                    "median_box_h": round(float(np.median(wh[:, 1])), 1),
                    "median_aspect": round(float(np.median(wh[:, 0] / wh[:, 1])), 1)})
        for label, lo, hi in THIRDS:
            s = np.array([r[2] for r in rows if r[0] == group and lo <= r[1] < hi])
            if not len(s):
                continue
            found = s[s > 0]
            out.append({"group": name, "degradation": label, "n": len(s),
                        "any_score": round(float((s > 0).mean()), 3),
                        "median_score_found": round(float(np.median(found)), 3) if len(found) else None,
                        "at_threshold": round(float((s >= thr).mean()), 3)})
    return out


EDGES = ("left", "top", "right", "bottom")


@torch.no_grad()
def candidate_rows(detector: Detector, gt: dict[str, Any], root: Path) -> list[tuple]:
    """Per non-ignored crater: (in the Pd set, degradation, then for the best-scoring
    candidate before NMS at IoU >= 0.5, or NaN: objectness, crater probability, IoU, stride,
    and the signed offsets of its left, top, right, bottom edges from the label box's, as
    shares of the label box's width or height).

    The images are letterboxed as :meth:`Detector.predict` does; the candidates are mapped back
    to the original pixels before they are compared with the labels.
    """
    anns = by_image([a for a in gt["annotations"]
                     if a["category_id"] == CRATER and not is_ignored(a)])
    levels = None
    rows = []
    for records, images in iter_batches(gt, root, 8):
        batch, infos = detector.preprocess(images)
        raw = detector.model(batch)
        table = decode(raw, detector.anchors, detector.strides, detector.scale_xy)
        if levels is None:
            levels = torch.cat([torch.full((r.shape[2] * r.shape[3] * detector.anchors.shape[1],),
                                           s) for r, s in zip(raw, detector.strides)])
        for record, image, info, cand in zip(records, images, infos, table):
            labels = anns.get(record["id"], [])
            if not labels:
                continue
            boxes = torch.from_numpy(info.to_original(
                box_convert(cand[:, :4], "cxcywh", "xyxy").numpy(), image.shape[1],
                image.shape[0])).double()
            score = (cand[:, 4] * cand[:, 5:].max(dim=1).values).double()
            truth = xyxy(labels)
            iou = box_iou(truth, boxes)  # (G, N)
            for a, t, row in zip(labels, truth, iou):
                head = (in_key_set(a), a.get("degradation", 0.0))
                ok = row >= 0.5
                if not ok.any():
                    rows.append(head + (np.nan,) * 8)
                    continue
                i = int(torch.where(ok, score, -1.0).argmax())
                wh = (t[2:] - t[:2]).repeat(2)
                edges = ((boxes[i] - t) / wh).tolist()
                rows.append(head + (float(cand[i, 4]), float(cand[i, 5 + CRATER - 1]),
                                    float(row[i]), int(levels[i]), *edges))
    return rows


def parts(rows: list[tuple]) -> list[dict]:
    """:func:`candidate_rows` summarised per group: Pd set / others, by degradation third."""
    out = []
    arr = np.array(rows, dtype=float).reshape(-1, 10)
    for name, group in (("pd_set", True), ("others", False)):
        for label, lo, hi in THIRDS:
            sel = arr[(arr[:, 0] == group) & (arr[:, 1] >= lo) & (arr[:, 1] < hi)]
            found = sel[~np.isnan(sel[:, 2])]
            if len(found) < 2:
                continue
            med = np.median(found[:, 2:5], axis=0)
            out.append({
                "group": name, "degradation": label, "n": len(sel), "localised": len(found),
                "median_objectness": round(float(med[0]), 3),
                "median_crater_prob": round(float(med[1]), 3),
                "median_iou": round(float(med[2]), 3),
                "by_stride": {int(s): int(c) for s, c in zip(*np.unique(found[:, 5],
                                                                        return_counts=True))},
                "median_abs_edge_offset": {e: round(float(v), 3) for e, v in
                                           zip(EDGES, np.median(np.abs(found[:, 6:]), axis=0))},
                "median_edge_offset": {e: round(float(v), 3) for e, v in
                                       zip(EDGES, np.median(found[:, 6:], axis=0))},
                "corr_objectness_iou": round(float(np.corrcoef(found[:, 2], found[:, 4])[0, 1]), 3),
            })
    return out


INF = float("inf")
# label attribute -> (value of a crater annotation on its image, bin edges)
BINS: dict[str, tuple[Callable[[dict, dict], float], tuple[float, ...]]] = {
    "box_height_px": (lambda a, img: a["bbox"][3], (0, 8, 12, 20, 40, INF)),
    "degradation": (lambda a, img: a["degradation"], (0, 1 / 3, 2 / 3, INF)),
    "depth_to_diameter": (lambda a, img: a["depth_m"] / a["diameter_m"],
                          (0, 0.08, 0.12, 0.16, INF)),
    "visible_rim_fraction": (lambda a, img: a["visible_rim_fraction"], (0, 0.5, 0.8, INF)),
    "surviving_bowl_fraction": (lambda a, img: a["surviving_bowl_fraction"],
                                (0, 0.5, 0.7, 0.9, 0.99, INF)),
    "rim_minor_axis_px": (lambda a, img: 2 * min(a["ellipse"][2], a["ellipse"][3]),
                          (0, 4, 6, 8, 12, 20, INF)),
    "sun_zenith_deg": (lambda a, img: img["sun_zenith_deg"], (0, 30, 50, 70, INF)),
    "near_rim_range_m": (lambda a, img: a["near_rim_range_m"], (0, 10, 20, INF)),
}


def ap_bins(gt: dict[str, Any], results: list[dict[str, Any]], rows: list[tuple]) -> list[dict]:
    """Crater AP50 and the localised share per bin of each :data:`BINS` attribute (an
    attribute the labels lack is left out). ``rows``: :func:`crater_scores` of the same."""
    images = {i["id"]: i for i in gt["images"]}
    craters = [a for a in gt["annotations"] if a["category_id"] == CRATER and not is_ignored(a)]
    localised_ids = {r[5] for r in rows if r[2] > 0}
    crater_results = [r for r in results if r["category_id"] == CRATER]
    out = []
    for name, (value, edges) in BINS.items():
        try:
            values = {a["id"]: float(value(a, images[a["image_id"]])) for a in craters}
        except (KeyError, ZeroDivisionError):
            continue
        bins = []
        for lo, hi in itertools.pairwise(edges):
            inside = {i for i, v in values.items() if lo <= v < hi}
            if not inside:
                continue
            anns = [a if a["id"] in inside or is_ignored(a) else {**a, "ignore": True}
                    for a in gt["annotations"] if a["category_id"] == CRATER]
            ap = coco_ap({**gt, "annotations": anns}, crater_results)["per_class"]["crater"]
            bins.append({"from": round(lo, 3), "to": None if hi == INF else round(hi, 3),
                         "n": len(inside), "AP50": round(ap["AP50"], 4),
                         "localised": round(len(inside & localised_ids) / len(inside), 3)})
        out.append({"attribute": name, "bins": bins})
    return out


def montage(gt: dict[str, Any], rows: list[tuple], thr: float, root: Path, path: Path,
            per_group: int = 12, seed: int = 0) -> Path:
    """Write the shallow-against-fresh crater crops of step 6 (``rows``: :func:`crater_scores`;
    ``root``: the images' folder)."""
    images = {i["id"]: i for i in gt["images"]}
    best = {r[5]: r[2] for r in rows}  # best IoU >= 0.5 score of each crater
    live = [a for a in gt["annotations"] if a["category_id"] == CRATER and not is_ignored(a)
            and 14 <= a["bbox"][3] <= 40 and a.get("visible_rim_fraction", 1.0) >= 0.8
            and "depth_m" in a and "diameter_m" in a]
    rng = np.random.default_rng(seed)
    rows = []
    for keep in (lambda r: r < 0.08, lambda r: r >= 0.16):
        group = [a for a in live if keep(a["depth_m"] / a["diameter_m"])]
        pick = rng.choice(len(group), min(per_group, len(group)), replace=False) if group else []
        tiles = [crater_tile(group[k], images[group[k]["image_id"]], root, best[group[k]["id"]] >= thr)
                 for k in pick]
        blank = np.zeros((160, 160, 3), np.uint8)
        tiles = tiles + [blank] * (-len(tiles) % 6) if tiles else [blank] * 6
        rows += [np.hstack(tiles[i:i + 6]) for i in range(0, len(tiles), 6)]
        rows.append(np.full((6, 960, 3), 255, np.uint8))
    return atomic.write_image(path, np.vstack(rows[:-1]))


def crater_tile(ann: dict[str, Any], image: dict[str, Any], root: Path, found: bool
                ) -> np.ndarray:
    """A 160 px tile around one crater: its box (green: found at the threshold), depth/diameter
    and the sun's zenith angle (also ``key_pd_bins.py``'s montage)."""
    im = cv2.imread(str(root / image["file_name"]))
    if im is None:
        raise InputError(f"{root / image['file_name']}: cannot read the image")
    x, y, w, h = ann["bbox"]
    side = max(w, h) * 1.6 + 16
    x0, y0 = int(max(0, x + w / 2 - side / 2)), int(max(0, y + h / 2 - side / 2))
    x1 = int(min(im.shape[1], x + w / 2 + side / 2))
    y1 = int(min(im.shape[0], y + h / 2 + side / 2))
    tile = cv2.resize(im[y0:y1, x0:x1], (160, 160), interpolation=cv2.INTER_NEAREST)
    fx, fy = 160 / (x1 - x0), 160 / (y1 - y0)
    cv2.rectangle(tile, (int((x - x0) * fx), int((y - y0) * fy)),
                  (int((x + w - x0) * fx), int((y + h - y0) * fy)),
                  (0, 200, 0) if found else (0, 0, 255), 1)
    text = (f"d/D {ann['depth_m'] / ann['diameter_m']:.2f} "
            f"sun {image.get('sun_zenith_deg', float('nan')):.0f}")
    cv2.putText(tile, text, (2, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 0), 1)
    return tile


def plot_scores(rows: list[tuple], thr: float, path: Path) -> Path:
    """Histogram of the best IoU >= 0.5 score per localised crater, Pd set and others by
    degradation, with the operating threshold."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), sharex=True)
    bins = np.linspace(0, 1, 41)
    for ax, (name, group) in zip(axes, (("Pd set: D >= 5 m, near rim <= 20 m", True),
                                        ("other craters", False))):
        for label, lo, hi in THIRDS:
            s = [r[2] for r in rows if r[0] == group and lo <= r[1] < hi and r[2] > 0]
            ax.hist(s, bins=bins, histtype="step", lw=1.5, label=f"{label} (n = {len(s)})")
        ax.axvline(thr, color="r", ls="--", lw=1, label=f"threshold {thr:.3f} (0.2 FA/img)")
        ax.set(xlabel="score of the best box at IoU >= 0.5", ylabel="craters", title=name)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    return atomic.write_figure(path, fig)


def false_alarms(gt: dict[str, Any], match: MatchResult) -> dict[str, int]:
    """What each false alarm of a :func:`match_craters` result overlaps most."""
    found = {id(a) for a, h in zip(match.gt, match.hit) if h}
    anns_by = by_image(gt["annotations"])
    kinds: Counter = Counter()
    for det in match.false_alarm_dets:
        anns = anns_by.get(det["image_id"], [])
        craters = [a for a in anns if a["category_id"] == CRATER]
        others = [a for a in anns if a["category_id"] != CRATER]
        iou_c = box_iou(xyxy([det]), xyxy(craters))[0]
        iou_o = box_iou(xyxy([det]), xyxy(others))[0]
        k = int(iou_c.argmax()) if craters else -1
        if k >= 0 and iou_c[k] >= 0.1:
            a = craters[k]
            kinds["second box on a found crater" if id(a) in found else
                  "ignored crater, IoU < 0.5" if is_ignored(a) else "crater, IoU < 0.5"] += 1
        elif others and float(iou_o.max()) >= 0.3:
            kinds["rock or artifact"] += 1
        else:
            kinds["nothing labelled"] += 1
    return dict(kinds)


def stricter_nms(results: list[dict[str, Any]], iou: float) -> list[dict[str, Any]]:
    """Class-wise NMS at ``iou`` over COCO results (already NMS-ed at a looser IoU)."""
    out = []
    for dets in by_image(results).values():
        keep = batched_nms(xyxy(dets), torch.tensor([r["score"] for r in dets], dtype=torch.float64),
                           torch.tensor([r["category_id"] for r in dets]), iou)
        out += [dets[i] for i in keep.tolist()]
    return out


def transfer_nms(gt: dict[str, Any], results: list[dict[str, Any]], iou: float) -> dict:
    """recall@5 and AP50 per class of the transfer report after a stricter NMS."""
    from lunarnav_ml.realdata.transfer import transfer_metrics

    per_class = transfer_metrics(gt, stricter_nms(results, iou))["all"]["per_class"]
    return {name: {"recall@5": round(m["recall@5"], 3), "AP50": round(m["AP50"], 3)}
            for name, m in per_class.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gt", type=Path, required=True, help="validation annotations.json")
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--img-size", type=int, default=None)
    parser.add_argument("--nms", type=float, nargs="*", default=[], help="stricter NMS IoUs to try")
    parser.add_argument("--plot", type=Path, default=None,
                        help="PNG: score histograms of the localised craters")
    parser.add_argument("--transfer", action="store_true",
                        help="a real split: only the NMS study, as transfer metrics")
    parser.add_argument("--bins", action="store_true",
                        help="crater AP50 per bin of label attributes (a few minutes)")
    parser.add_argument("--montage", type=Path, default=None,
                        help="PNG: crops of shallow and fresh craters, found or not")
    parser.add_argument("--parts", action="store_true",
                        help="objectness, class probability, IoU and edge offsets of the best "
                             "candidates before NMS (runs the model)")
    parser.add_argument("--cache", type=Path, default=None,
                        help="detections JSON: read when present, else written")
    args = parser.parse_args(argv)
    try:
        gt = read_json_file(args.gt, "ground truth")
        if args.cache is not None and args.cache.exists():
            results = read_json_file(args.cache, "cached detections")
        else:
            results = predict_coco(load_detector(args.checkpoint, img_size=args.img_size), gt,
                                   args.gt.parent, progress=False)
            if args.cache is not None:
                atomic.write_json(args.cache, results, indent=None)
    except LunarNavError as err:
        print(f"pd_diagnosis: error: {err}", file=sys.stderr)
        return 2
    if args.transfer:
        for iou in args.nms:
            print(json.dumps({"nms": iou, **transfer_nms(gt, results, iou)}))
        return 0
    head, match = summary(gt, results)
    print(json.dumps({"summary": head, "checkpoint": str(args.checkpoint)}))
    rows = crater_scores(gt, results)
    for row in localised(rows, head["threshold"]):
        print(json.dumps({"localised": row}))
    if args.plot is not None:
        print(json.dumps({"plot": str(plot_scores(rows, head["threshold"], args.plot))}))
    print(json.dumps({"false_alarms": false_alarms(gt, match)}))
    for iou in args.nms:
        print(json.dumps({"nms": iou, **summary(gt, stricter_nms(results, iou))[0]}))
    if args.bins:
        for row in ap_bins(gt, results, rows):
            print(json.dumps({"bins": row}))
    if args.parts:
        try:
            detector = load_detector(args.checkpoint, img_size=args.img_size)
            detector.model.eval()
            for row in parts(candidate_rows(detector, gt, args.gt.parent)):
                print(json.dumps({"parts": row}))
        except LunarNavError as err:
            print(f"pd_diagnosis: error: {err}", file=sys.stderr)
            return 2
    if args.montage is not None:
        try:
            out = montage(gt, rows, head["threshold"], args.gt.parent, args.montage)
        except LunarNavError as err:
            print(f"pd_diagnosis: error: {err}", file=sys.stderr)
            return 2
        print(json.dumps({"montage": str(out)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
