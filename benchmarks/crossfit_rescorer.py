"""Cross-fitted rescorer reads: each labelled set replayed with rescorers fitted on other sets.

Session 86 found that one validation quarter read with one rescorer fit no longer tells two
candidates apart: the reads a rescorer is fitted on move one model's key-crater Pd on the
quarter by up to 0.022 (BENCHMARKS.md, issue 4, "The fourth anchor for a full hour"). This
script reads every set once through the box refiner (the raw reads of ``lunarnav eval
--no-box-refiner``, as ``replay_candidates.py`` replays them), then, for each held-out set, fits
one rescorer per arm on the sets ``--fit-on`` names (``lunarnav train-box-rescorer``'s trees and
defaults) and replays the held-out set with it. Every held-out read goes through ``lunarnav
eval`` (threshold picked on the read itself, as the replays of sessions 77-86 did), and the arms'
key craters are pooled over the held-out sets and compared by a paired bootstrap over the frames.

Arms:

- ``base``: the rescorer's features (:data:`lunarnav_ml.geometry.boxrescore.FEATURES`).
- ``ground``: those and two read against level ground from the image's ``camera`` record
  (:func:`ground_features`): each box read as a level circle whose near edge is its bottom
  row, the diameter its width gives and its height over the height that circle would span.
- ``photo``: the base features and six read from the frame's pixels in and around the box
  (:func:`photo_features`): whether its rows hold a crater's dark and bright bands, whether
  those bands fill the box across, and whether they go on past its sides (a box on part of a
  rim). The trees otherwise see no pixel.

    python benchmarks/crossfit_rescorer.py --gt V/annotations.shard-{0,1,2,3}-of-4.json \\
        --raw raw_q{0,1,2,3}/detections.json --fit-on 1,2 2,3 3,0 0,1 --out OUT

Each set's replay through the box refiner is cached in ``OUT/set<k>.pkl`` (about 1.5 min a
quarter; with the ``photo`` arm its pixel features are added to a cache that lacks them) and
each fit takes 3-4 min on one core (``--jobs 2`` runs two at once); sets that fit on the same
others share one fit. A second model's reads of the same sets compare with ``--arms
base --against OUT/summary.json``: its pooled key craters paired with the first run's first arm.
"""

from __future__ import annotations

import argparse
import json
import math
import pickle
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from key_pd_bins import read_eval
from paired_key_pd import key_found, paired_bootstrap
from replay_candidates import raw_reads

from lunarnav_ml.data.coco import read_coco, read_image
from lunarnav_ml.errors import REPORTED_ERRORS, ConfigError, InputError
from lunarnav_ml.eval.coco_metrics import coco_from_dict, matched
from lunarnav_ml.eval.predict import to_coco_results
from lunarnav_ml.geometry.boxrefine import CRATER_LABEL, BoxRefinedDetector, BoxRefiner
from lunarnav_ml.geometry.boxrescore import FEATURES
from lunarnav_ml.utils import atomic
from lunarnav_ml.utils.jsonfile import read_json_file

ARMS = ("base", "ground", "photo")
GROUND_FEATURES = ("ground_diameter_m", "ground_aspect")
PHOTO_FEATURES = (
    "photo_contrast",  # the box's mean against the bands over and under it, in their std
    "photo_rows",  # std of the box's row means (a crater's shadow and lit wall), same unit
    "photo_dark",  # share of the box's pixels under half the bands' mean (shadow)
    "photo_sides",  # std of the row means beside the box, over the box's own (a part box)
    "photo_fill",  # share of the box's eight column strips whose rows follow the box's
    "photo_edges",  # mean |d/dy| in the box over that of the bands (rims are horizontal)
)
PHOTO_STRIPS = 8
NO_GROUND = -1.0  # a box whose bottom row is at or over the horizon


def ground_range(row: np.ndarray, camera: dict[str, float]) -> np.ndarray:
    """Horizontal range (m) of level ground seen at image ``row`` (NaN at or over the horizon)."""
    depression = math.radians(camera["pitch_deg"]) + np.arctan((row - camera["cy"]) / camera["fy"])
    return np.where(depression > 1e-6, camera["height_m"] / np.tan(np.maximum(depression, 1e-6)),
                    np.nan)


def ground_row(rng: np.ndarray, camera: dict[str, float]) -> np.ndarray:
    """Image row of level ground at horizontal range ``rng`` (m)."""
    depression = np.arctan(camera["height_m"] / rng)
    return camera["cy"] + camera["fy"] * np.tan(depression - math.radians(camera["pitch_deg"]))


def ground_features(xyxy: np.ndarray, camera: dict[str, float]) -> np.ndarray:
    """(N, 2): each box read as a level circle whose near edge lies at its bottom row: the
    diameter its width gives at the circle's centre, and its height over the height that circle
    would span (a whole crater on level ground reads about 1, a box on part of a rim more).
    :data:`NO_GROUND` where the bottom row is at or over the horizon."""
    w, h = xyxy[:, 2] - xyxy[:, 0], xyxy[:, 3] - xyxy[:, 1]
    near = ground_range(xyxy[:, 3], camera)
    cos_p, sin_p = math.cos(math.radians(camera["pitch_deg"])), \
        math.sin(math.radians(camera["pitch_deg"]))
    # w = fx D / z, z the centre's depth along the axis: (near + D / 2) cos p + H sin p
    denom = camera["fx"] - 0.5 * w * cos_p
    out = np.full((len(xyxy), 2), NO_GROUND, np.float32)
    ok = np.isfinite(near) & (denom > 0) & (w > 0)
    diameter = w[ok] * (near[ok] * cos_p + camera["height_m"] * sin_p) / denom[ok]
    spans = ground_row(near[ok], camera) - ground_row(near[ok] + diameter, camera)
    out[ok, 0] = diameter
    out[ok, 1] = h[ok] / np.maximum(spans, 1e-3)
    return out


def _row_std(block: np.ndarray) -> float:
    """Std of a block's row means (0 for an empty block)."""
    return float(block.mean(axis=1).std()) if block.size else 0.0


def photo_features(gray: np.ndarray, xyxy: np.ndarray) -> np.ndarray:
    """(N, len(PHOTO_FEATURES)) read from a gray frame in and around each xyxy box (px): the
    bands over and under a box are as high as it (at least 2 px), those beside it a quarter of
    its width (at least 2 px), all clipped to the frame. A box that covers no whole pixel reads
    zeros."""
    h_img, w_img = gray.shape
    out = np.zeros((len(xyxy), len(PHOTO_FEATURES)), np.float32)
    dy = np.abs(np.diff(gray, axis=0, append=gray[-1:]))
    for i, (x0, y0, x1, y1) in enumerate(np.rint(np.asarray(xyxy, np.float64)).astype(int)):
        x0, x1 = max(x0, 0), min(x1, w_img)
        y0, y1 = max(y0, 0), min(y1, h_img)
        w, h = x1 - x0, y1 - y0
        if w < 1 or h < 1:
            continue
        hb, wb = max(h, 2), max(w // 4, 2)
        inside = np.s_[y0:y1, x0:x1]
        over_under = (np.s_[max(y0 - hb, 0):y0, x0:x1], np.s_[y1:y1 + hb, x0:x1])
        box = gray[inside]
        bands = np.concatenate([gray[b].ravel() for b in over_under])
        bands_dy = np.concatenate([dy[b].ravel() for b in over_under])
        mu, sd = (float(bands.mean()), float(bands.std())) if bands.size else (
            float(box.mean()), 0.0)
        rows = box.mean(axis=1)
        own = float(rows.std())
        sides = max(_row_std(gray[y0:y1, max(x0 - wb, 0):x0]), _row_std(gray[y0:y1, x1:x1 + wb]))
        fill = 0.0
        if w >= PHOTO_STRIPS and h >= 3 and own > 0:
            profiles = [s.mean(axis=1) for s in np.array_split(box, PHOTO_STRIPS, axis=1)]
            fill = float(np.mean([p.std() > 0 and np.corrcoef(p, rows)[0, 1] > 0.5
                                  for p in profiles]))
        out[i] = ((float(box.mean()) - mu) / (sd + 1.0), own / (sd + 1.0),
                  float((box < 0.5 * mu).mean()), sides / (own + 1.0), fill,
                  float(dy[inside].mean()) / (float(bands_dy.mean()) + 1.0 if bands_dy.size
                                              else 1.0))
    return out


def frame_photo(image: np.ndarray, frame: dict[str, Any]) -> np.ndarray:
    """A read frame's :data:`PHOTO_FEATURES` rows from its RGB ``image`` (NaN for the boxes
    that are not craters)."""
    crater = frame["labels"] == CRATER_LABEL
    photo = np.full((len(crater), len(PHOTO_FEATURES)), np.nan, np.float32)
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32)
    photo[crater] = photo_features(gray, frame["boxes"][crater])
    return photo


def with_photo(data: dict[str, Any], gt_path: Path, log=print) -> bool:
    """Append :data:`PHOTO_FEATURES` to each crater row of a :func:`read_set` read that lacks
    them (a cache written before they were); whether it did."""
    frames = data["frames"]
    n_done = len(FEATURES) + len(GROUND_FEATURES) + len(PHOTO_FEATURES)
    if all(f["features"].shape[1] == n_done for f in frames):
        return False
    records = {r.image_id: r for r in read_coco(gt_path)[1]}
    t0 = time.perf_counter()
    for k, f in enumerate(frames):
        photo = frame_photo(read_image(records[f["image_id"]]), f)
        f["features"] = np.concatenate([f["features"], photo], axis=1)
        if (k + 1) % 100 == 0 or k + 1 == len(frames):
            log(f"  {gt_path.name}: pixel features of {k + 1}/{len(frames)} frames, "
                f"{time.perf_counter() - t0:.0f} s")
    return True


def read_set(gt_path: Path, raw_path: Path, refiner: BoxRefiner, photo: bool = False,
             log=print) -> dict[str, Any]:
    """Every frame of ``gt_path`` through the box refiner (no rescorer), with each crater box's
    rescorer and ground features (and with ``photo`` its pixel features, from the same read of
    the frame) and whether it matches a countable crater."""
    gt, records = read_coco(gt_path)
    cameras = {im["id"]: im.get("camera") for im in gt.get("images", [])}
    reads = raw_reads(raw_path)
    detector = BoxRefinedDetector(None, refiner)
    empty = {"boxes": np.zeros((0, 4)), "scores": np.zeros(0, np.float32),
             "labels": np.zeros(0, np.int64)}
    frames, t0 = [], time.perf_counter()
    for k, record in enumerate(records):
        camera = cameras.get(record.image_id)
        if not isinstance(camera, dict) or not {"fx", "fy", "cy", "pitch_deg", "height_m"} \
                <= set(camera):
            raise InputError(f"{gt_path}: image {record.image_id}: no camera record with fx, "
                             f"fy, cy, pitch_deg and height_m")
        image = read_image(record)
        out = detector.refine(image, reads.get(record.image_id, empty), 0.6, features=True)
        crater = out["labels"] == CRATER_LABEL
        ground = np.full((len(crater), 2), np.nan, np.float32)
        ground[crater] = ground_features(out["boxes"][crater].astype(np.float64), camera)
        frame = {"image_id": record.image_id, "boxes": out["boxes"], "scores": out["scores"],
                 "labels": out["labels"]}
        frame["features"] = np.concatenate([out["rescore_features"], ground]
                                           + ([frame_photo(image, frame)] if photo else []),
                                           axis=1)
        frames.append(frame)
        if (k + 1) % 100 == 0 or k + 1 == len(records):
            log(f"  {gt_path.name}: {k + 1}/{len(records)} frames, "
                f"{time.perf_counter() - t0:.0f} s")
    crater_results = [r for f in frames
                      for r in to_coco_results({k: f[k] for k in ("boxes", "scores", "labels")},
                                               f["image_id"])
                      if r["category_id"] == CRATER_LABEL]
    status = matched(coco_from_dict(gt), crater_results)
    return {"frames": frames, "status": status}


def rows(data: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Crater rows' features (all columns) and status (1 on, 0 off, -1 not counted)."""
    x = np.concatenate([f["features"][f["labels"] == CRATER_LABEL] for f in data["frames"]])
    return x, data["status"]


def columns(arm: str) -> np.ndarray:
    """The feature columns an arm reads: the rescorer's, then the arm's own."""
    base, ground = len(FEATURES), len(GROUND_FEATURES)
    own = {"base": [], "ground": range(base, base + ground),
           "photo": range(base + ground, base + ground + len(PHOTO_FEATURES))}[arm]
    return np.concatenate([np.arange(base), np.asarray(own, np.int64)])


def rescored_results(data: dict[str, Any], model: Any, cols: np.ndarray, conf: float
                     ) -> list[dict[str, Any]]:
    """COCO results of a set with its crater scores replaced by ``model``'s probabilities,
    by score, those under ``conf`` dropped (as ``BoxRefinedDetector.predict`` with a rescorer)."""
    results = []
    for f in data["frames"]:
        scores = f["scores"].copy()
        crater = f["labels"] == CRATER_LABEL
        x = f["features"][crater][:, cols]
        ok = np.isfinite(x).all(axis=1)
        if ok.any():
            idx = np.flatnonzero(crater)[ok]
            scores[idx] = model.predict_proba(x[ok].astype(np.float32))[:, 1]
        order = np.lexsort((np.arange(len(scores)), -scores))
        keep = order[scores[order] >= conf]
        results += to_coco_results({"boxes": f["boxes"][keep], "scores": scores[keep],
                                    "labels": f["labels"][keep]}, f["image_id"])
    return results


def evaluate(gt: Path, results: Path, out: Path) -> dict[str, Any]:
    """``lunarnav eval`` of a results file, threshold picked on itself; its metrics.json."""
    lunarnav = Path(sys.executable).with_name("lunarnav")
    cmd = [str(lunarnav), "eval", "--task", "detection", "--gt", str(gt), "--test-results",
           str(results), "--val-gt", str(gt), "--val-results", str(results), "--out", str(out),
           "--no-progress"]
    done = subprocess.run(cmd, check=False, capture_output=True, text=True)
    if done.returncode:
        raise InputError(f"lunarnav eval of {results} failed: {done.stderr.strip()[-400:]}")
    return json.loads((out / "metrics.json").read_text())


def fit_rescorer(sets: tuple[int, ...], arm: str, data: list[dict[str, Any]],
                 seed: int) -> tuple[Any, np.ndarray, int]:
    """An ``arm`` rescorer fitted on ``sets``: the trees, the columns they read, the rows used."""
    from lunarnav_ml.training.box_rescorer import BoxRescorerConfig, fit

    train = [rows(data[s]) for s in sets]
    x = np.concatenate([t[0] for t in train])
    y = np.concatenate([t[1] for t in train])
    good = (y >= 0) & np.isfinite(x).all(axis=1)
    cols = columns(arm)
    return fit(x[good][:, cols], y[good], BoxRescorerConfig(seed=seed)), cols, int(good.sum())


def held_out(k: int, arm: str, data: list[dict[str, Any]], gts: list[dict[str, Any]],
             args: argparse.Namespace, fit_on: list[list[int]],
             fitted: tuple[Any, np.ndarray, int] | None
             ) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
    """Set ``k`` replayed with the ``fitted`` ``arm`` rescorer (None: its earlier read, reused)
    and read by ``lunarnav eval``: its figures, and its key craters' frames and found flags."""
    folder = args.out / f"set{k}_{arm}"
    t0, rows_used = time.perf_counter(), 0
    if fitted is not None:
        model, cols, rows_used = fitted
        atomic.write_json(folder / "detections.json",
                          rescored_results(data[k], model, cols, args.conf), indent=None)
        evaluate(args.gt[k], folder / "detections.json", folder / "eval")
    metrics = json.loads((folder / "eval" / "metrics.json").read_text())
    image, hit = key_found(gts[k], *read_eval(folder / "eval"))
    cell = {"ap50": metrics["coco"]["per_class"]["crater"]["AP50"],
            "key_pd": metrics["crater_pd_D5_within20m"], "found": int(hit.sum()),
            "key": len(hit), "threshold": metrics["threshold"],
            "fa_per_image": metrics["false_alarms_per_image"]}
    print(f"set {k} {arm}: fit on {fit_on[k]} ({rows_used or 'reused'} rows, read "
          f"{time.perf_counter() - t0:.0f} s): AP50 {cell['ap50']:.3f}, key Pd "
          f"{cell['key_pd']:.3f} ({cell['found']} of {cell['key']}) at "
          f"{cell['fa_per_image']:.3f} FA/img, threshold {cell['threshold']:.3f}", flush=True)
    return cell, image + 10_000_000 * k, hit


def paired_line(name_a: str, a: np.ndarray, name_b: str, b: np.ndarray, image: np.ndarray
                ) -> dict[str, float]:
    """Print and return B - A over the pooled key craters, paired over the frames."""
    figures = paired_bootstrap(image, a, b)
    print(f"{name_b} - {name_a}: {figures['diff']:+.3f}, 95 % [{figures['lo']:+.3f}, "
          f"{figures['hi']:+.3f}]; found by {name_b} only {int((b & ~a).sum())}, by {name_a} "
          f"only {int((a & ~b).sum())}")
    return figures


def parse_fit_on(specs: list[str], n: int) -> list[list[int]]:
    """``--fit-on``: per set, the indices of the other sets its rescorers fit on.

    Raises:
        ConfigError: not one per set, not indices, out of range, or a set's own index.
    """
    if len(specs) != n:
        raise ConfigError(f"--fit-on: one per --gt set ({n}), got {len(specs)}")
    fit_on = []
    for k, spec in enumerate(specs):
        try:
            sets = [int(s) for s in spec.split(",")]
        except ValueError:
            raise ConfigError(f"--fit-on: {spec!r} is not comma-separated indices") from None
        if k in sets or not all(0 <= s < n for s in sets):
            raise ConfigError(f"--fit-on: set {k} fits on {spec}: indices 0-{n - 1}, not "
                              f"its own")
        fit_on.append(sets)
    return fit_on


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--gt", type=Path, nargs="+", required=True, help="each set's annotations")
    p.add_argument("--raw", type=Path, nargs="+", required=True,
                   help="each set's raw read (lunarnav eval --no-box-refiner detections.json)")
    p.add_argument("--fit-on", nargs="+", required=True,
                   help="per set, the sets (indices, comma-separated) its rescorers fit on")
    p.add_argument("--arms", nargs="+", choices=ARMS, default=list(ARMS))
    p.add_argument("--against", type=Path, default=None,
                   help="another run's summary.json (the same sets): its first arm paired "
                        "against this run's first")
    p.add_argument("--box-refiner", type=Path, default=None, help="default: the shipped one")
    p.add_argument("--conf", type=float, default=0.001, help="score floor of the results")
    p.add_argument("--seed", type=int, default=0, help="the trees' seed")
    p.add_argument("--jobs", type=int, default=1, help="fits run at once (one core each)")
    p.add_argument("--reuse", action="store_true",
                   help="read a held-out set's eval folder again where it exists")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    try:
        n = len(args.gt)
        if len(args.raw) != n:
            raise ConfigError(f"--raw: one per --gt set ({n}), got {len(args.raw)}")
        fit_on = parse_fit_on(args.fit_on, n)
        if args.jobs < 1:
            raise ConfigError(f"--jobs: expected at least 1, got {args.jobs}")
        against = None
        if args.against is not None:
            against = read_json_file(args.against, "cross-fit summary", dict)
            if against.get("sets") != [str(g) for g in args.gt]:
                raise InputError(f"{args.against}: sets {against.get('sets')} are not this "
                                 f"run's {[str(g) for g in args.gt]}")
        args.out.mkdir(parents=True, exist_ok=True)
        refiner = BoxRefiner(args.box_refiner)
        data, photo = [], "photo" in args.arms
        log = partial(print, flush=True)
        for k, (gt, raw) in enumerate(zip(args.gt, args.raw, strict=True)):
            cache = args.out / f"set{k}.pkl"
            if cache.exists():  # one written before the pixel features gets them now
                data.append(pickle.loads(cache.read_bytes()))
                if photo and with_photo(data[-1], gt, log=log):
                    atomic.write_bytes(cache, pickle.dumps(data[-1]))
                continue
            print(f"set {k}: {gt} through the box refiner", flush=True)
            data.append(read_set(gt, raw, refiner, photo=photo, log=log))
            atomic.write_bytes(cache, pickle.dumps(data[-1]))
        gts = [read_coco(g, check_files=False)[0] for g in args.gt]
        tasks = [(k, arm) for k in range(n) for arm in args.arms]
        todo = {(k, arm) for k, arm in tasks if not (
            args.reuse and (args.out / f"set{k}_{arm}" / "eval" / "metrics.json").exists())}
        fits = sorted({(tuple(fit_on[k]), arm) for k, arm in todo})  # sets sharing a fit: once
        # the trees are grown without the GIL, the reads in a subprocess
        with ThreadPoolExecutor(args.jobs) as pool:
            t0 = time.perf_counter()
            fitted = dict(zip(fits, pool.map(lambda f: fit_rescorer(*f, data, args.seed), fits),
                              strict=True))
            print(f"{len(fits)} rescorer(s) fitted in {time.perf_counter() - t0:.0f} s",
                  flush=True)
            given = {(k, arm): fitted[(tuple(fit_on[k]), arm)] if (k, arm) in todo else None
                     for k, arm in tasks}
            done = list(pool.map(lambda t: held_out(*t, data, gts, args, fit_on, given[t]),
                                 tasks))
        summary: dict[str, Any] = {"sets": [str(g) for g in args.gt], "fit_on": fit_on,
                                   "arms": {}}
        for arm in args.arms:
            part = [d for (k, a), d in zip(tasks, done, strict=True) if a == arm]
            image = np.concatenate([d[1] for d in part])
            hits = np.concatenate([d[2] for d in part])
            summary["arms"][arm] = {"sets": [d[0] for d in part], "image": image.tolist(),
                                    "found": hits.astype(int).tolist()}
            ap = [d[0]["ap50"] for d in part]
            print(f"{arm}: pooled key Pd {hits.mean():.3f} ({int(hits.sum())} of {len(hits)}), "
                  f"mean AP50 {np.mean(ap):.3f}")
        first = summary["arms"][args.arms[0]]
        image, base = np.array(first["image"]), np.array(first["found"], bool)
        if len(args.arms) > 1:
            summary["paired"] = paired_line(args.arms[0], base, args.arms[1],
                                            np.array(summary["arms"][args.arms[1]]["found"],
                                                     bool), image)
        if against is not None:
            other_arm, other = next(iter(against["arms"].items()))
            if other["image"] != first["image"]:
                raise InputError(f"{args.against}: its key craters are not this run's")
            summary["against"] = paired_line(f"{args.against} {other_arm}",
                                             np.array(other["found"], bool),
                                             f"this run's {args.arms[0]}", base, image)
        atomic.write_json(args.out / "summary.json", summary)
    except REPORTED_ERRORS as err:
        print(f"crossfit_rescorer: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
