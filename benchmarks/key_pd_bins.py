"""Where the key-crater Pd is lost: the key craters (D >= 5 m, near rim <= 20 m) of a
``lunarnav eval --task detection --out D`` read, found or missed at that read's operating
threshold, split by label attribute.

Printed: the key Pd over all key craters, over the fresh and whole ones (depth / diameter >=
0.12 and at least 0.8 of the rim visible) and over the rest; the most it could reach with the
shallow ones (d/D < 0.08) all missed and every other found; then per bin of depth / diameter,
visible rim fraction, near-rim range and the label box's width / height (a rim seen edge-on). With ``--montage``, a PNG of up to 24 key craters with
d/D < 0.08 above up to 24 fresh ones (d/D >= 0.16, rim >= 0.8 visible), drawn at random with
``--seed``: the labelled box in green where it was found, red where missed
(``pd_diagnosis.py``'s tiles).

With ``--misses``, how each missed key crater was boxed: the best-scoring crater box of the
read that overlaps it at IoU >= 0.3 (any score), counted as too narrow (under 0.8 of the
label's width), too wide (over 1.25), placed wrong at the right width, or absent; and a PNG of
up to 36 misses, the widest first, each in a tile of the frame's aspect 10:3 around it: the
label in red, that box in yellow with its IoU and score. Session 79 read it on the paper-mono
test grid: most misses are big craters boxed too narrow (BENCHMARKS.md, issue 4, "The whole
paper-mono test grid read once").

Session 75 read it on `val300`: 72 % of the key craters are shallow or part-hidden, the fresh
ones reach 0.78-0.79, those with d/D < 0.08 0.02-0.08 (BENCHMARKS.md, issue 4, "Colour frames
reach the refiner as it was trained").

    python benchmarks/key_pd_bins.py --gt data/d7/val300/annotations.json \\
        --read outputs/s75/v300_default --montage outputs/s75/key_shallow_vs_fresh.png
"""
from __future__ import annotations

import argparse
import sys
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
from pd_diagnosis import crater_tile

from lunarnav_ml.data.coco import read_coco
from lunarnav_ml.errors import InputError, LunarNavError
from lunarnav_ml.eval.pd import MatchResult, in_key_set, match_craters
from lunarnav_ml.eval.pd import _iou as box_label_iou
from lunarnav_ml.eval.predict import check_coco_results
from lunarnav_ml.utils.atomic import check_image_destination, write_image
from lunarnav_ml.utils.jsonfile import read_json_file

FRESH_DD, FRESH_RIM, SHALLOW_DD = 0.12, 0.8, 0.08
BINS = {  # label attribute: (value of an annotation, bin edges)
    "depth/diameter": (lambda a: a["depth_m"] / a["diameter_m"], (0.0, 0.08, 0.12, 0.16, np.inf)),
    "visible rim fraction": (lambda a: a.get("visible_rim_fraction", 1.0), (0.0, 0.5, 0.8, np.inf)),
    "near-rim range m": (lambda a: a["near_rim_range_m"], (0.0, 10.0, 15.0, np.inf)),
    # edge-on rims: session 82 found most of the paper-mono test grid's misses over 20
    "box width/height": (lambda a: a["bbox"][2] / max(a["bbox"][3], 1e-6),
                         (0.0, 10.0, 15.0, 20.0, 25.0, np.inf)),
}
TILE_W = TILE_H = 160  # pd_diagnosis.crater_tile's
PER_ROW = 6


def _dd(ann: dict[str, Any]) -> float:
    return float(ann["depth_m"]) / float(ann["diameter_m"])


def _is_fresh(ann: dict[str, Any], dd: float = FRESH_DD) -> bool:
    return _dd(ann) >= dd and ann.get("visible_rim_fraction", 1.0) >= FRESH_RIM


def key_bins(gt: dict[str, Any], results: list[dict[str, Any]], threshold: float
             ) -> tuple[dict[str, Any], MatchResult]:
    """The key craters' Pd at ``threshold``, overall and per bin, and the match itself.

    Raises:
        InputError: a key crater label without ``depth_m`` and a positive ``diameter_m``.
    """
    match = match_craters(gt, results, threshold)
    key = np.array([in_key_set(a) for a in match.gt], bool)
    for a in (a for a, k in zip(match.gt, key, strict=True) if k):
        if not (isinstance(a.get("depth_m"), int | float) and float(a.get("diameter_m", 0)) > 0):
            raise InputError(f"annotation {a.get('id')}: depth_m and a positive diameter_m "
                             f"needed, got {a.get('depth_m')!r}, {a.get('diameter_m')!r}")
    hit = match.hit

    def cell(mask: np.ndarray) -> dict[str, Any]:
        return {"n": int(mask.sum()), "pd": float(hit[mask].mean()) if mask.any() else None}

    fresh = np.array([k and _is_fresh(a) for a, k in zip(match.gt, key, strict=True)], bool)
    shallow = np.array([k and _dd(a) < SHALLOW_DD for a, k in zip(match.gt, key, strict=True)],
                       bool)
    out: dict[str, Any] = {"threshold": threshold, "all": cell(key), "fresh": cell(fresh),
                           "rest": cell(key & ~fresh), "shallow": cell(shallow),
                           # key Pd if every key crater were found but the shallow ones
                           "cap_without_shallow": (float((key & ~shallow).sum() / key.sum())
                                                   if key.any() else None),
                           "bins": {}}
    for name, (value, edges) in BINS.items():
        v = np.array([value(a) if k else np.nan for a, k in zip(match.gt, key, strict=True)])
        out["bins"][name] = [{"from": lo, "to": hi, **cell(key & (v >= lo) & (v < hi))}
                             for lo, hi in pairwise(edges)]
    return out, match


def montage(gt: dict[str, Any], match: MatchResult, root: Path, seed: int = 0,
            per_group: int = 24) -> np.ndarray:
    """Up to ``per_group`` shallow key craters (d/D < 0.08) above as many fresh ones (d/D >=
    0.16, rim >= 0.8 visible), drawn with ``seed``; BGR uint8."""
    rng = np.random.default_rng(seed)
    images = {im["id"]: im for im in gt["images"]}
    key = [k for k, a in enumerate(match.gt) if in_key_set(a)]
    groups = ([k for k in key if _dd(match.gt[k]) < SHALLOW_DD],
              [k for k in key if _is_fresh(match.gt[k], 0.16)])
    rows = []
    for group in groups:
        pick = sorted(rng.choice(group, min(per_group, len(group)), replace=False)) if group \
            else []
        tiles = [crater_tile(match.gt[k], images[match.gt[k]["image_id"]], root,
                             bool(match.hit[k])) for k in pick]
        tiles += [np.zeros((TILE_H, TILE_W, 3), np.uint8)] * (-len(tiles) % PER_ROW)
        rows += [np.hstack(tiles[i:i + PER_ROW]) for i in range(0, len(tiles), PER_ROW)]
        rows.append(np.full((8, TILE_W * PER_ROW, 3), 255, np.uint8))
    return np.vstack(rows[:-1])


MISS_W, MISS_H, MISS_ROW = 320, 96, 4
NEAR_IOU, NARROW, WIDE = 0.3, 0.8, 1.25


def missed_key(match: MatchResult, results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each missed key crater with the best-scoring crater box of ``results`` (any score) that
    overlaps it at IoU >= 0.3: ``{"ann", "box" (xywh or None), "iou", "score", "kind"}``,
    ``kind`` one of "narrow", "wide", "placed", "none"; the widest labels first."""
    by_image: dict[int, list[dict[str, Any]]] = {}
    for det in results:
        if det["category_id"] == 1:
            by_image.setdefault(det["image_id"], []).append(det)
    out = []
    for ann, hit in zip(match.gt, match.hit, strict=True):
        if hit or not in_key_set(ann):
            continue
        dets = by_image.get(ann["image_id"], [])
        boxes = np.array([d["bbox"] for d in dets], np.float64).reshape(-1, 4)
        iou = box_label_iou(boxes, [ann])[:, 0] if dets else np.zeros(0)  # as the match's
        near = np.flatnonzero(iou >= NEAR_IOU)
        row = {"ann": ann, "box": None, "iou": 0.0, "score": 0.0, "kind": "none"}
        if near.size:
            k = near[np.argmax([dets[i]["score"] for i in near])]
            ratio = boxes[k, 2] / ann["bbox"][2]
            row.update(box=boxes[k], iou=float(iou[k]), score=float(dets[k]["score"]),
                       kind="narrow" if ratio < NARROW else "wide" if ratio > WIDE else "placed")
        out.append(row)
    return sorted(out, key=lambda r: -r["ann"]["bbox"][2])


def miss_tile(miss: dict[str, Any], image: dict[str, Any], root: Path) -> np.ndarray:
    """A ``MISS_W`` x ``MISS_H`` tile around a missed crater (1.3 of its width, at the tile's
    aspect): the label in red, the nearest box (:func:`missed_key`) in yellow; BGR uint8."""
    import cv2

    im = cv2.imread(str(root / image["file_name"]))
    if im is None:
        raise InputError(f"{root / image['file_name']}: cannot read the image")
    x, y, w, h = miss["ann"]["bbox"]
    cw = max(1.3 * w + 16, (h + 16) * MISS_W / MISS_H)
    ch = cw * MISS_H / MISS_W
    x0, y0 = x + w / 2 - cw / 2, y + h / 2 - ch / 2
    to_tile = np.array([[MISS_W / cw, 0, -x0 * MISS_W / cw], [0, MISS_H / ch, -y0 * MISS_H / ch]])
    tile = cv2.warpAffine(im, to_tile, (MISS_W, MISS_H), flags=cv2.INTER_AREA,
                          borderMode=cv2.BORDER_CONSTANT)

    def draw(box: np.ndarray, colour: tuple[int, int, int]) -> None:
        bx, by, bw, bh = box
        cv2.rectangle(tile, (int((bx - x0) * MISS_W / cw), int((by - y0) * MISS_H / ch)),
                      (int((bx + bw - x0) * MISS_W / cw), int((by + bh - y0) * MISS_H / ch)),
                      colour, 1)

    draw(np.asarray(miss["ann"]["bbox"], np.float64), (0, 0, 255))
    if miss["box"] is not None:
        draw(miss["box"], (0, 255, 255))
    ann = miss["ann"]
    text = (f"D {ann['diameter_m']:g} m at {ann['near_rim_range_m']:g} m  {miss['kind']}  "
            f"IoU {miss['iou']:.2f} s {miss['score']:.2f}")
    cv2.putText(tile, text, (2, 11), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (255, 255, 0), 1)
    return tile


def misses_sheet(gt: dict[str, Any], misses: list[dict[str, Any]], root: Path,
                 most: int = 36) -> np.ndarray:
    """Up to ``most`` of :func:`missed_key`'s tiles, ``MISS_ROW`` a row; BGR uint8."""
    images = {im["id"]: im for im in gt["images"]}
    tiles = [miss_tile(m, images[m["ann"]["image_id"]], root) for m in misses[:most]]
    if not tiles:
        return np.zeros((MISS_H, MISS_W, 3), np.uint8)
    tiles += [np.zeros((MISS_H, MISS_W, 3), np.uint8)] * (-len(tiles) % MISS_ROW)
    return np.vstack([np.hstack(tiles[i:i + MISS_ROW]) for i in range(0, len(tiles), MISS_ROW)])


def read_eval(folder: Path) -> tuple[list[dict[str, Any]], float]:
    """A ``lunarnav eval --task detection --out`` folder's detections and operating threshold
    (``paired_key_pd.py`` reads its two so).

    Raises:
        InputError: a missing or malformed file, or a threshold that is not a number.
    """
    dets = check_coco_results(read_json_file(folder / "detections.json", "detections"),
                              folder / "detections.json")
    threshold = read_json_file(folder / "metrics.json", "metrics", dict).get("threshold")
    if isinstance(threshold, bool) or not isinstance(threshold, int | float) \
            or not np.isfinite(threshold):
        raise InputError(f"{folder / 'metrics.json'}: threshold: expected a number, got "
                         f"{threshold!r}")
    return dets, float(threshold)


def _pd(cell: dict[str, Any]) -> str:
    return "-" if cell["pd"] is None else f"{cell['pd']:.3f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gt", required=True, help="COCO annotations with the crater label keys")
    ap.add_argument("--read", required=True,
                    help="a `lunarnav eval --task detection --out` folder: its detections.json "
                         "and metrics.json (the operating threshold)")
    ap.add_argument("--montage", help="PNG of shallow key craters above fresh ones")
    ap.add_argument("--seed", type=int, default=0, help="(--montage) which craters are drawn")
    ap.add_argument("--misses", help="PNG of the missed key craters with their nearest box")
    args = ap.parse_args(argv)
    try:
        for path in (args.montage, args.misses):
            if path:
                check_image_destination(path)
        gt = read_coco(args.gt, check_files=False)[0]
        dets, threshold = read_eval(Path(args.read))
        figures, match = key_bins(gt, dets, threshold)
        if args.montage:
            write_image(args.montage, montage(gt, match, Path(args.gt).parent, args.seed))
        misses = missed_key(match, dets) if args.misses else []
        if args.misses:
            write_image(args.misses, misses_sheet(gt, misses, Path(args.gt).parent))
    except LunarNavError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"threshold {threshold:.3f}: key Pd {_pd(figures['all'])} (n {figures['all']['n']}); "
          f"fresh and whole {_pd(figures['fresh'])} (n {figures['fresh']['n']}); the rest "
          f"{_pd(figures['rest'])} (n {figures['rest']['n']})")
    if figures["cap_without_shallow"] is not None:
        print(f"  with the {figures['shallow']['n']} of d/D < {SHALLOW_DD:g} all missed, key Pd "
              f"could reach at most {figures['cap_without_shallow']:.3f}")
    for name, cells in figures["bins"].items():
        print(f"  {name}: " + "; ".join(f"[{c['from']:g}, {c['to']:g}) {_pd(c)} (n {c['n']})"
                                        for c in cells))
    if args.montage:
        print(f"-> {args.montage}")
    if args.misses:
        kinds = [m["kind"] for m in misses]
        print(f"  {len(misses)} key craters missed; the best box at IoU >= {NEAR_IOU:g}: too "
              f"narrow {kinds.count('narrow')}, too wide {kinds.count('wide')}, placed wrong "
              f"{kinds.count('placed')}, none {kinds.count('none')} -> {args.misses}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
