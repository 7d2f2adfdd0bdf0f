"""Calibrate the lifter's rim-edge offset (``LifterConfig.rim_offset`` and ``rim_offset_m``) on
labelled development stereo renders.

The "tangent" lifter puts the near rim's visible edge ``rim_offset * r + rim_offset_m`` in front
of the rim crest (r the crater radius). Both terms depend on the rim's shape, the viewing height
and the matcher's behaviour at an occluding crest, so they are measured, not derived. This runs
the geometry report with both set to 0 on each given set, and for every lifted crater finds the
offset that would have put its center at the truth along the line of sight: with the horizontal
range of the near edge R = rho k0 - offset (k0 = 1 - sin(alpha) on the line of sight), an
along-range error e needs offset = -e k0. It then fits offset = rim_offset_m + rim_offset * r
to the per-diameter medians (weights sqrt(n)) and prints both. Use development renders, never
the evaluation set. Lifts from fitted ellipses and from box ellipses (the fitter's
"box_fallback", or ``--ellipse-source box``) are fitted apart (``box_rim_offset``,
``box_rim_offset_m``): a box's inscribed ellipse sits lower than the rim where the box also
holds the outer flank, and its lifts read nearer:

    .venv/bin/lunarnav synth /tmp/dev_ps --protocol paper-stereo --seed 1 --size 1024 --shard 0/7
    .venv/bin/python benchmarks/calibrate_rim_offset.py /tmp/dev_ps/annotations.shard-0-of-7.json \\
        --out outputs/dev_rim_offset

``--rows-only`` re-reads the rows in ``--out`` instead of running again.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from lunarnav_ml.errors import LunarNavError
from lunarnav_ml.geometry.lifter import LifterConfig
from lunarnav_ml.geometry.report import geometry_report
from lunarnav_ml.utils.atomic import write_figure, write_json
from lunarnav_ml.utils.jsonfile import read_json_file


def needed_offsets(rows: list[dict[str, Any]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(radius m, near-rim range m, offset m that zeroes the along-range error) per lifted row.

    The rows must come from a lift with both offsets at 0.
    """
    ok = [r for r in rows if r["ok"]]
    truth = np.array([r["truth_center_m"][:2] for r in ok], dtype=np.float64).reshape(-1, 2)
    err = np.array([r["center_err_xy_m"] for r in ok], dtype=np.float64).reshape(-1, 2)
    rho = np.linalg.norm(truth, axis=1)
    along = (err * truth).sum(axis=1) / np.maximum(rho, 1e-9)
    radius = np.array([r["diameter_m"] for r in ok], dtype=np.float64) / 2.0
    near = np.array([r["near_rim_range_m"] for r in ok], dtype=np.float64)
    k0 = 1.0 - radius / np.maximum(rho, 1e-9)
    return radius, near, -along * k0


def fit_offset(radius: np.ndarray, need: np.ndarray) -> tuple[float, float, dict[float, Any]]:
    """(rim_offset_m, rim_offset, per-radius (n, median)) from a line through the medians."""
    per_r = {float(r): (int((radius == r).sum()), float(np.median(need[radius == r])))
             for r in np.unique(radius)}
    if len(per_r) < 2:
        raise LunarNavError("calibration needs lifted craters of at least two diameters")
    rs = np.array(list(per_r))
    n, med = (np.array(v) for v in zip(*per_r.values()))
    slope, icpt = np.polyfit(rs, med, 1, w=np.sqrt(n))
    return float(icpt), float(slope), per_r


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("gt", type=Path, nargs="+", help="development stereo sets (annotations files)")
    p.add_argument("--out", type=Path, default=Path("outputs/dev_rim_offset"))
    p.add_argument("--ellipse-source", default="fit", choices=("fit", "label", "box"))
    p.add_argument("--rows-only", action="store_true", help="reuse the rows in --out")
    p.add_argument("--crest-match", choices=("on", "off"), default=None,
                   help="LifterConfig.crest_match (default: the lifter's default)")
    args = p.parse_args(argv)
    match = {} if args.crest_match is None else {"crest_match": args.crest_match == "on"}
    zero = LifterConfig(rim_offset=0.0, rim_offset_m=0.0, box_rim_offset=0.0,
                        box_rim_offset_m=0.0, **match)
    rows: list[dict[str, Any]] = []
    fits: dict[str, Any] = {}
    try:
        for k, gt in enumerate(args.gt):
            part = args.out / f"set{k}"
            if not args.rows_only:
                geometry_report(gt, part, ellipse_source=args.ellipse_source, lifter=zero,
                                plots=False)
            rows += read_json_file(part / "geometry_craters.json", "geometry report rows")
        # fitted ellipses and box ellipses (the fitter's fallback) get their own offsets
        for prefix, from_box in (("", False), ("box_", True)):
            group = [r for r in rows if bool(r.get("from_box")) == from_box]
            if any(r["ok"] for r in group):
                radius, near, need = needed_offsets(group)
                fits[prefix] = (radius, near, need, *fit_offset(radius, need))
    except LunarNavError as err:
        print(f"calibrate_rim_offset: error: {err}", file=sys.stderr)
        return 2
    result: dict[str, Any] = {}
    for prefix, (radius, near, need, icpt, slope, per_r) in fits.items():
        print(f"{'box' if prefix else 'fitted'} ellipses: D (m) | lifted | median offset needed "
              "(m) | as a fraction of r | fitted (m)")
        for r, (n, med) in per_r.items():
            print(f"{2 * r:g} | {n} | {med:+.3f} | {med / r:+.3f} | {icpt + slope * r:+.3f}")
        result[prefix] = {
            f"{prefix}rim_offset": slope, f"{prefix}rim_offset_m": icpt, "n_lifted": len(need),
            "per_diameter": {f"{2 * r:g}": {"n": n, "median_m": med}
                             for r, (n, med) in per_r.items()}}
        _plot(args.out / f"{prefix}rim_offset.png", radius, near, need, icpt, slope)
    settings = ", ".join(f"{k}={v:.4f}" for part in result.values() for k, v in part.items()
                         if k.endswith(("rim_offset", "rim_offset_m")))
    print(f"LifterConfig({settings})")
    write_json(args.out / "rim_offset.json", {
        "fitted_ellipses": result.get(""), "box_ellipses": result.get("box_"),
        "sets": [str(g) for g in args.gt], "ellipse_source": args.ellipse_source,
        "crest_match": zero.crest_match})
    return 0


def _plot(path: Path, radius: np.ndarray, near: np.ndarray, need: np.ndarray, icpt: float,
          slope: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    sc = ax.scatter(radius + np.random.default_rng(0).uniform(-0.15, 0.15, len(radius)), need,
                    c=near, s=8, cmap="viridis")
    rs = np.linspace(0, radius.max() * 1.05, 50)
    ax.plot(rs, icpt + slope * rs, "r-", label=f"{icpt:+.2f} m + {slope:.3f} r")
    ax.set(xlabel="crater radius r (m; jittered)", ylabel="edge offset that zeroes the error (m)",
           ylim=np.percentile(need, [2, 98]) + np.array([-0.5, 0.5]))
    fig.colorbar(sc, label="near-rim range (m)")
    ax.legend()
    ax.grid(alpha=0.3)
    write_figure(path, fig)


if __name__ == "__main__":
    raise SystemExit(main())
