"""Calibrate the lifter's rim-edge offset (``LifterConfig.rim_offset``, ``rim_offset_m`` and
``rim_offset_view``) on labelled development stereo renders.

The "tangent" lifter puts the near rim's visible edge ``rim_offset * r + rim_offset_m +
rim_offset_view * r * H / R`` in front of the rim crest (r the crater radius, H the camera's
height, R the edge's horizontal range: H / R is the tangent of the sight line's depression).
The terms depend on the rim's shape, the viewing geometry and the matcher's behaviour at an
occluding crest, so they are measured, not derived. This runs the geometry report with every
offset at 0 on each given set, and for every lifted crater finds the offset that would have put
its center at the truth along the line of sight: with the horizontal range of the near edge
R = rho k0 - offset (k0 = 1 - sin(alpha) on the line of sight), an along-range error e needs
offset = -e k0. It then fits the three terms to the medians of cells of one diameter and one
2 m band of near-rim range (at least ``--min-cell`` lifts, weights sqrt(n)) and prints them.
Use development renders, never the evaluation set. Lifts from fitted ellipses and from box
ellipses (the fitter's "box_fallback", or ``--ellipse-source box``) are fitted apart
(``box_rim_offset``, ``box_rim_offset_m``, ``box_rim_offset_view``): a box's inscribed ellipse
sits lower than the rim where the box also holds the outer flank, and its lifts read nearer:

    .venv/bin/lunarnav synth /tmp/dev_ps --protocol paper-stereo --seed 1 --size 1024 --shard 0/7
    .venv/bin/python benchmarks/calibrate_rim_offset.py /tmp/dev_ps/annotations.shard-0-of-7.json \\
        --out outputs/dev_rim_offset

``--rows-only`` re-reads the rows in ``--out`` (``set0/geometry_craters.json``, ...) instead of
running again.

With ``--refiner FILE`` the lifts read SGBM's disparity corrected by that disparity refiner
(``lunarnav train-refiner``), and the fitted terms are written into the file's metadata
(``lunarnav.edge_offsets``), which the geometry evaluation and ``lunarnav localize`` then use
with it. Calibrate on development sets the refiner was not trained on:

    .venv/bin/python benchmarks/calibrate_rim_offset.py data/ss/dev_s1k3 --ellipse-source box \
        --refiner outputs/refiner.onnx --out outputs/refiner_offsets

``--max-disparity PX`` and ``--passes N`` calibrate the refiner with that gate and pass count
(:class:`~lunarnav_ml.geometry.refine.DisparityRefiner`) and write them into the file with the
terms.
"""

from __future__ import annotations

import argparse
import sys
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np

from lunarnav_ml.errors import LunarNavError
from lunarnav_ml.geometry._checks import as_array
from lunarnav_ml.geometry.lifter import EDGE_OFFSET_TERMS, LifterConfig
from lunarnav_ml.geometry.refine import DisparityRefiner
from lunarnav_ml.geometry.report import geometry_report
from lunarnav_ml.training.refiner import stamp_edge_offsets
from lunarnav_ml.utils.atomic import write_figure, write_json
from lunarnav_ml.utils.jsonfile import read_json_file

RANGE_BANDS_M = (5.0, 7.0, 9.0, 11.0, 13.0, 15.0, 17.0, 21.0)  # near-rim range cells


def needed_offsets(rows: list[dict[str, Any]], camera_height_m: float = 1.5
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(radius m, near-rim range m, offset m that zeroes the along-range error, camera height
    m: the row's ``camera_height_m``, else ``camera_height_m``) per lifted row.

    The rows must come from a lift with every offset at 0.
    """
    ok = [r for r in rows if r["ok"]]
    truth = np.array([r["truth_center_m"][:2] for r in ok], dtype=np.float64).reshape(-1, 2)
    err = np.array([r["center_err_xy_m"] for r in ok], dtype=np.float64).reshape(-1, 2)
    rho = np.linalg.norm(truth, axis=1)
    along = (err * truth).sum(axis=1) / np.maximum(rho, 1e-9)
    radius = np.array([r["diameter_m"] for r in ok], dtype=np.float64) / 2.0
    near = np.array([r["near_rim_range_m"] for r in ok], dtype=np.float64)
    k0 = 1.0 - radius / np.maximum(rho, 1e-9)
    height = np.array([r.get("camera_height_m", camera_height_m) for r in ok], dtype=np.float64)
    return radius, near, -along * k0, height


def _checked_rows(path: Path) -> list[dict[str, Any]]:
    """A geometry report's rows, each lifted one with the fields the calibration reads."""
    rows = read_json_file(path, "geometry report rows", expect=list)
    for i, r in enumerate(rows):
        if not isinstance(r, dict) or "ok" not in r:
            raise LunarNavError(f"{path}: row {i}: expected an object with 'ok'")
        if r["ok"]:
            for key, shape in (("truth_center_m", (3,)), ("center_err_xy_m", (2,)),
                               ("diameter_m", ()), ("near_rim_range_m", ())):
                as_array(f"{path}: row {i}: {key}", r.get(key), shape)
    return rows


def fit_offset(radius: np.ndarray, near: np.ndarray, need: np.ndarray, height_m: np.ndarray,
               min_cell: int = 5) -> tuple[float, float, float, dict[tuple[float, float], Any]]:
    """(rim_offset_m, rim_offset, rim_offset_view, cells) from a weighted least-squares fit of
    ``b + a r + c r H / R`` through the medians of the (radius, range band) cells;
    ``cells[(r, band start)]`` is (n, median H / R, median offset)."""
    cells: dict[tuple[float, float], Any] = {}
    for r in np.unique(radius):
        for lo, hi in pairwise(RANGE_BANDS_M):
            m = (radius == r) & (near >= lo) & (near < hi)
            if m.sum() >= min_cell:
                cells[(float(r), lo)] = (int(m.sum()), float(np.median(height_m[m] / near[m])),
                                         float(np.median(need[m])))
    if len({r for r, _ in cells}) < 2 or len({lo for _, lo in cells}) < 2:
        raise LunarNavError("calibration needs lifted craters of at least two diameters and "
                            f"two near-rim range bands, each cell with {min_cell}+ lifts")
    rs = np.array([r for r, _ in cells])
    n, tan_dep, med = (np.array(v) for v in zip(*cells.values()))
    design = np.column_stack([np.ones_like(rs), rs, rs * tan_dep]) * np.sqrt(n)[:, None]
    icpt, slope, view = np.linalg.lstsq(design, med * np.sqrt(n), rcond=None)[0]
    return float(icpt), float(slope), float(view), cells


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("gt", type=Path, nargs="+", help="development stereo sets (annotations files)")
    p.add_argument("--out", type=Path, default=Path("outputs/dev_rim_offset"))
    p.add_argument("--ellipse-source", default="fit", choices=("fit", "label", "box"))
    p.add_argument("--rows-only", action="store_true", help="reuse the rows in --out")
    p.add_argument("--crest-match", choices=("on", "off"), default=None,
                   help="LifterConfig.crest_match (default: the lifter's default)")
    p.add_argument("--camera-height", type=float, default=1.5,
                   help="camera height (m) for rows that do not carry theirs")
    p.add_argument("--refiner", type=Path, default=None,
                   help="lift from SGBM's disparity corrected by this refiner (ONNX) and write "
                        "the fitted terms into it")
    p.add_argument("--max-disparity", type=float, default=None,
                   help="with --refiner: refine only boxes whose SGBM median disparity over "
                        "the box's lower half is below this (px); written into the file")
    p.add_argument("--passes", type=int, default=1,
                   help="with --refiner: refinement passes; written into the file")
    p.add_argument("--min-cell", type=int, default=5,
                   help="lifts a (diameter, range band) cell needs to count")
    args = p.parse_args(argv)
    if args.refiner is None and (args.max_disparity is not None or args.passes != 1):
        p.error("--max-disparity and --passes set a refiner's gate and passes: give --refiner")
    match = {} if args.crest_match is None else {"crest_match": args.crest_match == "on"}
    zero = LifterConfig(rim_offset=0.0, rim_offset_m=0.0, rim_offset_view=0.0,
                        box_rim_offset=0.0, box_rim_offset_m=0.0, box_rim_offset_view=0.0,
                        **match)
    rows: list[dict[str, Any]] = []
    fits: dict[str, Any] = {}
    try:
        refiner = None if args.refiner is None else DisparityRefiner(
            args.refiner, max_disparity_px=args.max_disparity, passes=args.passes)
        for k, gt in enumerate(args.gt):
            part = args.out / f"set{k}"
            if not args.rows_only:
                geometry_report(gt, part, ellipse_source=args.ellipse_source, lifter=zero,
                                refiner=refiner, plots=False)
            rows += _checked_rows(part / "geometry_craters.json")
        # fitted ellipses and box ellipses (the fitter's fallback) get their own offsets
        for prefix, from_box in (("", False), ("box_", True)):
            group = [r for r in rows if bool(r.get("from_box")) == from_box]
            if any(r["ok"] for r in group):
                radius, near, need, height = needed_offsets(group, args.camera_height)
                fits[prefix] = (radius, near, need, height,
                                *fit_offset(radius, near, need, height, args.min_cell))
    except LunarNavError as err:
        print(f"calibrate_rim_offset: error: {err}", file=sys.stderr)
        return 2
    # keyed and named as load_edge_offsets reads them back (lunarnav eval --edge-offsets)
    result: dict[str, Any] = dict.fromkeys(EDGE_OFFSET_TERMS)
    settings = []
    for prefix, (radius, near, need, height, icpt, slope, view, cells) in fits.items():
        section = "box_ellipses" if prefix else "fitted_ellipses"
        print(f"{'box' if prefix else 'fitted'} ellipses: D (m) | near-rim range (m) | lifted | "
              "median offset needed (m) | fitted (m)")
        for (r, lo), (n, tan_dep, med) in cells.items():
            fitted = icpt + slope * r + view * r * tan_dep
            print(f"{2 * r:g} | {lo:g}+ | {n} | {med:+.3f} | {fitted:+.3f}")
        terms = dict(zip(EDGE_OFFSET_TERMS[section], (slope, icpt, view), strict=True))
        settings += [f"{k}={v:.4f}" for k, v in terms.items()]
        result[section] = {
            **terms, "n_lifted": len(need),
            "cells": [{"diameter_m": 2 * r, "range_from_m": lo, "n": n, "tan_depression": t,
                       "median_m": med} for (r, lo), (n, t, med) in cells.items()]}
        _plot(args.out / f"{prefix}rim_offset.png", radius, near, need, height,
              (icpt, slope, view))
    print(f"LifterConfig({', '.join(settings)})")
    write_json(args.out / "rim_offset.json", {
        **result, "sets": [str(g) for g in args.gt], "ellipse_source": args.ellipse_source,
        "crest_match": zero.crest_match,
        "refiner": None if args.refiner is None else str(args.refiner),
        "refiner_max_disparity_px": args.max_disparity, "refiner_passes": args.passes})
    if args.refiner is not None:
        terms = {k: round(float(result[section][k]), 5)
                 for section, keys in EDGE_OFFSET_TERMS.items() if result[section] for k in keys}
        stamp_edge_offsets(args.refiner, terms, args.max_disparity, args.passes)
        print(f"edge offsets written into {args.refiner}: {terms} (max_disparity_px "
              f"{args.max_disparity}, passes {args.passes})")
    return 0


def _plot(path: Path, radius: np.ndarray, near: np.ndarray, need: np.ndarray,
          height: np.ndarray, terms: tuple[float, float, float]) -> None:
    """Needed offset against the near-rim range, one panel colour per diameter, with the fit."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    icpt, slope, view = terms
    fig, ax = plt.subplots(figsize=(8, 5))
    cmap = plt.get_cmap("viridis")
    radii = np.unique(radius)
    jitter = np.random.default_rng(0).uniform(-0.3, 0.3, len(near))
    grid = np.linspace(near.min(), near.max(), 60)
    for i, r in enumerate(radii):
        m = radius == r
        color = cmap(i / max(len(radii) - 1, 1))
        ax.scatter(near[m] + jitter[m], need[m], s=5, color=color, alpha=0.4)
        ax.plot(grid, icpt + slope * r + view * r * np.median(height[m]) / grid, "-",
                color=color, lw=2, label=f"D = {2 * r:g} m")
    ax.set(xlabel="near-rim range (m; jittered)", ylabel="edge offset that zeroes the error (m)",
           ylim=np.percentile(need, [2, 98]) + np.array([-0.5, 0.5]),
           title=f"{icpt:+.3f} m + {slope:.4f} r {view:+.4f} r H / R")
    ax.legend(fontsize=8, ncol=2)
    ax.grid(alpha=0.3)
    write_figure(path, fig)


if __name__ == "__main__":
    raise SystemExit(main())
