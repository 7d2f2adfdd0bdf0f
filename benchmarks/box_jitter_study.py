"""How the 3D crater figures depend on the box: the geometry report on labelled boxes whose
edges are moved at random (``geometry_report(..., box_jitter=F)``), lifted from the box's
inscribed ellipse and from the fitted one, at several jitters.

The lift takes a crater's angular width from its ellipse, so a box edge off by a few per cent
of the side moves the centre by decimetres at 15-20 m. Compare the curve with a detector's own
box precision (the detection report's "Box precision" table) to see what 3D error it allows.
Development renders only:

    .venv/bin/python benchmarks/box_jitter_study.py /tmp/dev_ps/annotations.shard-0-of-7.json \\
        /tmp/dev2/annotations.shard-0-of-7.json --jitters 0 0.02 0.04 --out outputs/box_jitter

Prints, per source and jitter, the mean over the sets of the mean 3σ centre error at 15-20 m
(over the diameters) and of the median centre error, and writes ``box_jitter.json`` and
``box_jitter.png`` (each set's report stays in ``--out/<source>_<jitter>/set<k>``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from lunarnav_ml.errors import LunarNavError
from lunarnav_ml.geometry.report import geometry_report
from lunarnav_ml.utils.atomic import write_figure, write_json


def mean_figures(metrics: list[dict[str, Any]]) -> dict[str, float | None]:
    """Mean over the sets of (the mean over diameters of the 3σ centre error at 15-20 m), of
    the median centre error and of Pd(3D); None where no set has a value."""
    per_set = [[m["per_diameter"][d]["range_15_20"]["center_3sigma_m"]
                for d in m["per_diameter"]] for m in metrics]
    three_sigma = [np.mean(v) for v in ([x for x in s if x is not None] for s in per_set) if v]
    medians = [m["overall"]["center_median_m"] for m in metrics
               if m["overall"]["center_median_m"] is not None]
    return {"center_3sigma_15_20_m": float(np.mean(three_sigma)) if three_sigma else None,
            "center_median_m": float(np.mean(medians)) if medians else None,
            "pd_3d": float(np.mean([m["overall"]["pd_3d"] for m in metrics]))}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("gt", type=Path, nargs="+", help="development stereo sets (annotations files)")
    p.add_argument("--jitters", type=float, nargs="+", default=[0.0, 0.01, 0.02, 0.04])
    p.add_argument("--sources", nargs="+", default=["box", "fit"], choices=("box", "fit"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("outputs/box_jitter"))
    args = p.parse_args(argv)
    table: dict[str, dict[str, dict[str, float]]] = {}
    try:
        for src in args.sources:
            for jit in args.jitters:
                metrics = [geometry_report(gt, args.out / f"{src}_{jit:g}" / f"set{k}",
                                           ellipse_source=src, box_jitter=jit, seed=args.seed,
                                           plots=False)
                           for k, gt in enumerate(args.gt)]
                row = mean_figures(metrics)
                table.setdefault(src, {})[f"{jit:g}"] = row
                print(f"{src} jitter {jit:g}: mean 3σ centre 15-20 m "
                      f"{_fmt(row['center_3sigma_15_20_m'])} m, median "
                      f"{_fmt(row['center_median_m'])} m, Pd(3D) {row['pd_3d']:.3f}", flush=True)
    except LunarNavError as err:
        print(f"box_jitter_study: error: {err}", file=sys.stderr)
        return 2
    write_json(args.out / "box_jitter.json", {"sets": [str(g) for g in args.gt],
                                              "seed": args.seed, "table": table})
    _plot(args.out / "box_jitter.png", table)
    return 0


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3f}"


def _plot(path: Path, table: dict[str, dict[str, dict[str, float]]]) -> None:
    """Mean 3σ centre error at 15-20 m and median centre error against the box jitter."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for src, rows in table.items():
        jit = [100 * float(j) for j in rows]
        for ax, key in zip(axes, ("center_3sigma_15_20_m", "center_median_m")):
            ax.plot(jit, [np.nan if r[key] is None else r[key] for r in rows.values()], "o-",
                    label=src)
    axes[0].set(xlabel="box edge jitter (% of the side, 1 sigma)",
                ylabel="3σ centre error, 15-20 m (m)")
    axes[1].set(xlabel="box edge jitter (% of the side, 1 sigma)",
                ylabel="median centre error (m)")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(title="lifted from")
    fig.tight_layout()
    write_figure(path, fig)


if __name__ == "__main__":
    sys.exit(main())
