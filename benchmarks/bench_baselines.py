"""Benchmark: the paper's geometric baselines (lidar, stereo) — figures and timings.

Timings (1 core): the lidar detector on one 360 deg scan with the paper's sensor (0.333 deg,
75 deg vertical FOV, 1.5 m, 23 deg tilt) and the stereo detector on one 1024 x 1024 disparity
map (after disparity), both of an analytic single-crater scene. Figures: the baseline report
(Pd vs near-rim range, 3-sigma per diameter beside the paper's) on rendered protocol sets.

    .venv/bin/python benchmarks/bench_baselines.py --timing
    .venv/bin/python benchmarks/bench_baselines.py --lidar-data /tmp/bl/lidar \
        --stereo-data /tmp/bl/stereo --disparity sgbm --out outputs/bench_baselines

``--lidar-data`` / ``--stereo-data`` take a synth folder (``lunarnav synth --protocol
paper-lidar`` / ``paper-stereo``) or one of its annotation JSON files (a shard's).
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
import numpy as np

cv2.setNumThreads(1)

from lunarnav_ml.baselines.analytic import (
    AnalyticScene,
    CraterSpec,
    render_disparity,
    simulate_lidar,
)
from lunarnav_ml.baselines.crater_model import CraterProfile
from lunarnav_ml.baselines.lidar import LidarConfig, MapCrater, detect_craters_lidar
from lunarnav_ml.baselines.report import baseline_report
from lunarnav_ml.baselines.stereo import detect_craters_stereo
from lunarnav_ml.errors import LunarNavError

TARGETS = {"lidar": "3 sigma <= 0.28/1.04/1.77/1.94 m (D 5/10/15/20); Pd >= 0.9 to 20 m; "
                    "<= 1 s per scan",
           "stereo": "3 sigma <= 1.02/3.22/4.48/4.35 m; Pd >= 0.5 for D 5 to 12 m and D >= 10 "
                     "to 15 m; <= 0.5 s per 1024^2 pair"}


def time_detectors(repeats: int = 5) -> dict[str, float]:
    """Median seconds per call of each detector on a D = 10 m crater 15 m away."""
    prof = CraterProfile(10.0, 2.0)
    scene = AnalyticScene([CraterSpec((20.0, 0.0), prof)])
    scan = simulate_lidar(scene, range_noise_m=0.01)
    prior = [MapCrater((20.5, 0.5), 10.0, 2.4)]
    disp = render_disparity(scene, noise_px=0.2, cx=511.5, cy=511.5)
    cam = {"fx": 512.0, "cx": 511.5, "cy": 511.5, "baseline_m": 0.3, "height_m": 1.5,
           "pitch_deg": 20.0}
    out = {}
    for name, fn in (("lidar_s_per_scan", lambda: detect_craters_lidar(scan, map_craters=prior)),
                     ("stereo_s_per_1024_map", lambda: detect_craters_stereo(disp, cam))):
        secs = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            secs.append(time.perf_counter() - t0)
        out[name] = float(np.median(secs))
    out["lidar_points"] = len(scan)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--timing", action="store_true", help="time the detectors (analytic scenes)")
    p.add_argument("--lidar-data", type=Path, help="paper-lidar synth folder or annotations")
    p.add_argument("--stereo-data", type=Path, help="paper-stereo synth folder or annotations")
    p.add_argument("--disparity", choices=("sgbm", "truth-noise"), default="sgbm")
    p.add_argument("--noise-px", type=float, default=0.2, help="truth-noise disparity sigma")
    p.add_argument("--max-images", type=int)
    p.add_argument("--out", type=Path, default=Path("outputs/bench_baselines"))
    p.add_argument("--lidar-model-width", type=float, default=LidarConfig.model_width,
                   help="the lidar model's diameter over the map's (default %(default)s; 1.0 "
                   "for renders of configs/synth/legacy_crest.yaml)")
    args = p.parse_args(argv)
    try:
        summary = _run(args)
    except LunarNavError as err:
        print(f"bench_baselines: error: {err}", file=sys.stderr)
        return 2
    print(json.dumps(summary, indent=1))
    return 0


def _run(args: argparse.Namespace) -> dict:
    """The timings and reports asked for, summarised (``LunarNavError`` on bad input)."""
    lidar_config = LidarConfig(model_width=args.lidar_model_width)
    summary: dict = {}
    if args.timing:
        summary["timing"] = time_detectors()
    for method, data in (("lidar", args.lidar_data), ("stereo", args.stereo_data)):
        if data is None:
            continue
        m = baseline_report(data, args.out / method, method=method, disparity=args.disparity,
                            noise_px=args.noise_px, max_images=args.max_images, progress=True,
                            lidar_config=lidar_config)
        summary[method] = {
            "target": TARGETS[method], "pd_all": m["pd_all"], "n_targets": m["n_targets"],
            "n_hidden": m["n_hidden"], "pd_including_hidden": m["pd_including_hidden"],
            "fa_per_image": m["false_alarms_per_image"],
            "three_sigma_m": {d: r["three_sigma_m"] for d, r in m["position_error"].items()},
            "three_rms_m": {d: r["three_rms_m"] for d, r in m["position_error"].items()},
            "paper_three_sigma_m": {d: r["paper_3sigma_m"] for d, r in
                                    m["position_error"].items()},
            "s_per_item": m["seconds_per_item"], "report": str(args.out / method / "report.md")}
    return summary


if __name__ == "__main__":
    sys.exit(main())
