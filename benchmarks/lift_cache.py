"""Lifter studies in seconds: cache each crater's lift inputs once, re-lift them with new settings.

A geometry report spends nearly all its time in the matcher and the refiner (a development shard
of the paper-stereo grid: about 1.5 min on 2 cores); a change to the lifter does not change
their output. ``cache`` runs the report on development sets (SGBM and the shipped gated refiner
unless ``--refiner none``; the report's ellipse source) and keeps, for every crater it lifted
within ``--range`` (near-rim range, m), what the lift read: a window of the disparity map and of
both images around the box, the label, the box and the rig, with the report's own row.
``lift`` runs the report's per-crater step (ellipse, lift, score: ``report._eval_crater``) again
on those windows, with ``LifterConfig`` fields changed by ``--lifter FIELD=VALUE`` (the same
option as ``lifter_gate_study.py``), and prints per set and pooled: the 3-sigma horizontal
centre error per diameter (15-20 m window), their mean, Pd(3D) and the lifted count over the
cached craters. Without ``--lifter`` it also checks that every row comes out as the report
wrote it (the window holds all the lift reads). Development sets only, never the evaluation
half::

    .venv/bin/python benchmarks/lift_cache.py cache data/ss/dev_s1k0 data/ss/dev_s2k0 \\
        --out outputs/lift_cache
    .venv/bin/python benchmarks/lift_cache.py lift outputs/lift_cache
    .venv/bin/python benchmarks/lift_cache.py lift outputs/lift_cache --lifter n_rim=144

The cache is a pickle per set (``<set name>.pkl``), written to a temporary name and renamed;
it holds this version's objects (``Ellipse``, ``StereoRig``, ``LifterConfig``), so rebuild it
after changing those classes (a plain ``lift`` shows it: rows no longer reproduced). Being a
pickle, load only caches this tool wrote. The report's step is reached through its module
(``report._eval_crater``), wrapped for the caching run only. A cache keeps the lifter
settings it was written with (a field added since takes its class default); ``lift --today``
starts from today's defaults instead, with the cached run's edge offsets.
"""

from __future__ import annotations

import argparse
import pickle
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from lifter_gate_study import _lifter_settings, _mean_all_d

from lunarnav_ml.errors import LunarNavError
from lunarnav_ml.geometry import report
from lunarnav_ml.geometry.lifter import EDGE_OFFSET_TERMS, LifterConfig
from lunarnav_ml.geometry.refine import DisparityRefiner
from lunarnav_ml.geometry.report import summarize

VERSION = 1
DIAMETERS = ("5.0", "7.0", "10.0", "12.0", "15.0", "17.0", "20.0")


def window(box: np.ndarray, disp: np.ndarray, half_width: int) -> tuple[int, int, int, int, int]:
    """Rows [y0, y1) and columns [x0, x1) of the disparity a lift from ``box`` reads (the crest
    search, the flank below it, the crest match), and the first column xr of the right image
    the crest match reads (x0 less the window's largest disparity and a match window)."""
    x, y, w, h = box
    rows, cols = disp.shape
    y0, y1 = max(int(y - max(h, 20) - 20), 0), min(int(y + 2 * h + 60), rows)
    x0, x1 = max(int(x - 40), 0), min(int(x + w + 40), cols)
    part = disp[y0:y1, x0:x1]
    d_max = float(np.nanmax(part)) if np.isfinite(part).any() else 0.0
    return y0, y1, x0, x1, max(int(x0 - d_max - 2 * half_width - 40), 0)


def cache_set(dataset: Path, out: Path, refiner: DisparityRefiner | None,
              ellipse_source: str, near_range: tuple[float, float], disparity: str = "sgbm"
              ) -> int:
    """Run the report on ``dataset`` and write its lifted craters' windows; their count."""
    kept: list[dict[str, Any]] = []
    step = report._eval_crater
    settings: dict[str, Any] = {}

    def capture(left, right, disp, rig, ann, box, cfg):
        row = step(left, right, disp, rig, ann, box, cfg)
        lo, hi = near_range
        if box is None or "lift_s" not in row or not lo <= row["near_rim_range_m"] <= hi:
            return row
        settings.update(source=cfg.source, disparity=cfg.disparity, lifter=cfg.lifter,
                        fitter=cfg.fitter)
        y0, y1, x0, x1, xr = window(box, disp, cfg.lifter.match_half_width)
        kept.append({"ann": ann, "box": box, "rig": rig, "shape": disp.shape,
                     "window": (y0, y1, x0, x1, xr), "disp": disp[y0:y1, x0:x1].copy(),
                     "left": left[y0:y1, xr:x1].copy(),
                     "right": None if right is None else right[y0:y1, xr:x1].copy(),
                     "row": row})
        return row

    report._eval_crater = capture
    try:
        report.geometry_report(dataset, out / dataset.name, refiner=refiner,
                               ellipse_source=ellipse_source, disparity=disparity, plots=False)
    finally:
        report._eval_crater = step
    # (the report adds each image's fields to the rows kept here after the step: same objects)
    data = {"version": VERSION, "dataset": str(dataset), "settings": settings, "craters": kept}
    dst = out / f"{dataset.name}.pkl"
    tmp = dst.with_name(dst.name + ".tmp")
    tmp.write_bytes(pickle.dumps(data))
    tmp.replace(dst)
    return len(kept)


def load(path: Path) -> dict[str, Any]:
    """One set's cache, checked."""
    try:
        data = pickle.loads(path.read_bytes())
    except (OSError, pickle.UnpicklingError, EOFError, AttributeError, ImportError) as err:
        raise LunarNavError(f"{path}: not a lift cache ({type(err).__name__}: {err})") from None
    if not isinstance(data, dict) or data.get("version") != VERSION:
        raise LunarNavError(f"{path}: not a version {VERSION} lift cache; run `cache` again")
    return data


def todays_lifter(cached: LifterConfig) -> LifterConfig:
    """Today's :class:`LifterConfig` defaults with the cached run's edge offsets (those of the
    refiner it ran with): a cache keeps the lifter settings of the day it was written."""
    keys = [k for terms in EDGE_OFFSET_TERMS.values() for k in terms]
    return replace(LifterConfig(), **{k: getattr(cached, k) for k in keys})


def relift(data: dict[str, Any], overrides: dict[str, Any], today: bool = False
           ) -> list[dict[str, Any]]:
    """The report's rows of the cached craters, lifted again with ``overrides`` (on the cached
    lifter settings, or with ``today`` on :func:`todays_lifter`)."""
    s = data["settings"]
    rows = []
    if not data["craters"]:
        return rows
    base = todays_lifter(s["lifter"]) if today else s["lifter"]
    cfg = report._Settings(None, replace(base, **overrides), s["fitter"], s["source"],
                           s["disparity"])
    for c in data["craters"]:
        y0, y1, x0, x1, xr = c["window"]
        disp = np.full(c["shape"], np.nan, np.float32)
        disp[y0:y1, x0:x1] = c["disp"]
        left = np.zeros(c["shape"], np.uint8)
        left[y0:y1, xr:x1] = c["left"]
        right = None
        if c["right"] is not None:
            right = np.zeros(c["shape"], np.uint8)
            right[y0:y1, xr:x1] = c["right"]
        row = report._eval_crater(left, right, disp, c["rig"], c["ann"], c["box"], cfg)
        rows.append({**row, "image_id": c["row"].get("image_id")})
    return rows


def mismatches(cached: list[dict[str, Any]], rows: list[dict[str, Any]]) -> int:
    """Rows whose outcome (ok, reason, centre) differs from the report's."""
    def key(r: dict[str, Any]) -> tuple:
        return r["ok"], r["reason"], tuple(np.round(r.get("center_m", []), 9))
    return sum(key(a) != key(b) for a, b in zip(cached, rows, strict=True))


def line(name: str, rows: list[dict[str, Any]]) -> str:
    m = summarize(rows)
    cells = [m["per_diameter"].get(d, {}).get("range_15_20", {}).get("center_3sigma_m")
             for d in DIAMETERS]
    text = " / ".join("-" if c is None else f"{c:.2f}" for c in cells)
    pd = m["overall"]["pd_3d"]
    return (f"{name} | {text} | {_mean_all_d(m):.3f} | {'-' if pd is None else f'{pd:.3f}'} | "
            f"{m['overall']['n_lifted']}/{len(rows)}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="lift_cache", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("cache", help="run the report and cache each lifted crater's windows")
    c.add_argument("sets", type=Path, nargs="+", help="development stereo set folders")
    c.add_argument("--out", type=Path, required=True)
    c.add_argument("--refiner", default="default",
                   help="the refiner's ONNX file; 'default': the shipped one; 'none': SGBM only")
    c.add_argument("--ellipse-source", default="box", choices=report.ELLIPSE_SOURCES)
    c.add_argument("--disparity", default="sgbm", choices=report.DISPARITY_SOURCES,
                   help="'rendered': each image's own disparity file (no refiner)")
    c.add_argument("--range", type=float, nargs=2, default=(15.0, 20.0), metavar=("LO", "HI"),
                   help="near-rim ranges kept, m")
    lift = sub.add_parser("lift", help="re-lift the cached craters and print the figures")
    lift.add_argument("cache", type=Path, help="the folder `cache` wrote")
    lift.add_argument("--lifter", nargs="*", default=[], metavar="FIELD=VALUE",
                      help="LifterConfig settings changed from the cached run's")
    lift.add_argument("--today", action="store_true",
                      help="start from today's LifterConfig defaults (with the cached run's "
                           "edge offsets) instead of the settings the cache was written with")
    args = p.parse_args(argv)
    try:
        if args.command == "cache":
            if args.disparity == "rendered" and args.refiner not in ("default", "none"):
                raise LunarNavError("--refiner: refines SGBM's disparity, not the rendered one")
            refiner = (None if args.refiner == "none" or args.disparity == "rendered" else
                       DisparityRefiner(None if args.refiner == "default" else args.refiner))
            args.out.mkdir(parents=True, exist_ok=True)
            for s in args.sets:
                n = cache_set(s, args.out, refiner, args.ellipse_source, tuple(args.range),
                              args.disparity)
                print(f"{s.name}: {n} craters cached", flush=True)
            return 0
        overrides = _lifter_settings(args.lifter)
        files = sorted(args.cache.glob("*.pkl"))
        if not files:
            raise LunarNavError(f"{args.cache}: no lift cache (*.pkl) here; run `cache` first")
        print("set | 3σ centre 15-20 m, D = 5 / 7 / 10 / 12 / 15 / 17 / 20 | mean | Pd(3D) | "
              "lifted")
        pooled = []
        for f in files:
            data = load(f)
            rows = relift(data, overrides, args.today)
            pooled += rows
            check = ""
            if not overrides and not args.today:
                bad = mismatches([c["row"] for c in data["craters"]], rows)
                check = f" | reproduced {len(rows) - bad}/{len(rows)}"
            print(line(f.stem, rows) + check, flush=True)
        print(line("pooled", pooled))
        return 0
    except LunarNavError as err:
        print(f"lift_cache: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
