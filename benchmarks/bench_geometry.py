"""Benchmark: camera-only crater geometry on paper-stereo protocol scenes.

Renders (or reuses) a subset of the paper-stereo grid, runs ellipse fit + SGBM + lift on every
target crater, and prints the 3-sigma horizontal center / diameter errors per diameter for
craters 15-20 m away (beside the paper's stereo and lidar tables), Pd(3D) and the time per
crater for fit + lift on one core.

    .venv/bin/python benchmarks/bench_geometry.py --root /tmp/geo/bench --per-diameter 6
    .venv/bin/python benchmarks/bench_geometry.py --root /tmp/geo/bench --render-only ...

The subset: for each diameter, near-rim ranges 15..20 m; approach angle and sun zenith cycle
through the grid's values so that each appears about equally often. Rendering takes ~10 s
per 1024 px stereo pair on one core; items already in ``--root`` are reused.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2

cv2.setNumThreads(1)

from lunarnav_ml.geometry.report import PAPER_LIDAR_3SIGMA_M, PAPER_STEREO_3SIGMA_M, geometry_report


def select_items(diameters: list[float], ranges: list[float], per_diameter: int,
                 offset: int = 0) -> list[int]:
    """Grid indices of paper-stereo items: per diameter, ranges in turn, approach and zenith
    cycling (``offset`` shifts the cycle to draw a different subset)."""
    from lunarnav_ml.synth.protocols import DIAMETERS_M, grid

    items = grid("paper-stereo")
    approaches = sorted({it[1] for it in items})
    zeniths = sorted({it[3] for it in items})
    index = {(it[0], it[1], it[2], it[3]): i for i, it in enumerate(items)}
    chosen = []
    for d in diameters:
        d_i = DIAMETERS_M.index(d)
        for k in range(per_diameter):
            j = k + offset
            key = (d_i, approaches[j % len(approaches)], ranges[j % len(ranges)],
                   zeniths[(j // len(approaches)) % len(zeniths)])
            chosen.append(index[key])
    return chosen


def render(root: Path, indices: list[int], image_size: int, seed: int) -> Path:
    """Render the chosen items (skipping finished ones) and write annotations.json for them."""
    from lunarnav_ml.synth.config import SynthConfig
    from lunarnav_ml.synth.generate import plan_items, write_item
    from lunarnav_ml.synth.pipeline import TerrainCache, render_item

    cfg, plan = plan_items(SynthConfig(), seed, None, "paper-stereo")
    cache = TerrainCache()
    for n, i in enumerate(indices):
        if not (root / "items" / f"{i:06d}.json").exists():
            t0 = time.perf_counter()
            out = render_item(plan[i](), cfg, image_size, stereo=True, lidar=False, cache=cache)
            write_item(root, i, seed, plan[i](), out)
            print(f"rendered item {i} ({n + 1}/{len(indices)}) in {time.perf_counter() - t0:.1f} s",
                  file=sys.stderr)
    return collect(root)


def collect(root: Path) -> Path:
    """annotations.json from every finished item record under ``root/items``."""
    from lunarnav_ml.utils.atomic import write_json

    images, anns = [], []
    for path in sorted((root / "items").glob("*.json")):
        rec = json.loads(path.read_text())
        images.append(rec["image"])
        for a in rec["annotations"]:
            anns.append({"id": len(anns) + 1, "image_id": rec["image"]["id"], **a})
    cats = [{"id": 1, "name": "crater"}, {"id": 2, "name": "rock"}, {"id": 3, "name": "artifact"}]
    return write_json(root / "annotations.json",
                      {"images": images, "annotations": anns, "categories": cats}, indent=None)


def print_table(name: str, metrics: dict) -> None:
    print(f"\n== ellipse source: {name} ==")
    print(f"{'D (m)':>6} {'n':>3} {'lifted':>6} {'3s center 15-20':>16} {'3s center all':>14} "
          f"{'3s diam 15-20':>14} {'paper stereo':>12} {'paper lidar':>11}")
    for d, st in metrics["per_diameter"].items():
        near, allr = st["range_15_20"], st["all_ranges"]
        key = round(float(d))
        fmt = lambda x: "-" if x is None else f"{x:.2f}"
        print(f"{d:>6} {near['n']:>3} {near['n_lifted']:>6} {fmt(near['center_3sigma_m']):>16} "
              f"{fmt(allr['center_3sigma_m']):>14} {fmt(near['diameter_3sigma_m']):>14} "
              f"{fmt(PAPER_STEREO_3SIGMA_M.get(key)):>12} {fmt(PAPER_LIDAR_3SIGMA_M.get(key)):>11}")
    t = metrics["time_per_crater_ms"]
    print(f"Pd(3D) overall {metrics['overall']['pd_3d']:.2f}; outcomes {metrics['reasons']}")
    print(f"time per crater (1 core): fit {t['fit']:.1f} ms + lift {t['lift']:.1f} ms; "
          f"SGBM {t['stereo_per_image']:.0f} ms per image (crater rows only)")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--root", type=Path, default=Path("/tmp/lunarnav_bench_geometry"))
    p.add_argument("--diameters", type=float, nargs="+", default=[5.0, 10.0, 15.0, 20.0])
    p.add_argument("--ranges", type=float, nargs="+", default=[15.0, 16.0, 17.0, 18.0, 19.0, 20.0])
    p.add_argument("--per-diameter", type=int, default=6)
    p.add_argument("--offset", type=int, default=0, help="shift the approach/zenith cycle")
    p.add_argument("--image-size", type=int, default=1024)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--render-only", action="store_true")
    p.add_argument("--sources", nargs="+", default=["box", "fit", "label"])
    args = p.parse_args(argv)
    idx = select_items(args.diameters, args.ranges, args.per_diameter, args.offset)
    render(args.root, idx, args.image_size, args.seed)
    if args.render_only:
        return 0
    for src in args.sources:
        m = geometry_report(args.root, args.root / f"report_{src}", ellipse_source=src)
        print_table(src, m)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
