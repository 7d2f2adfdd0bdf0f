"""Training curves of several Lightning runs side by side, from their CSV logs.

Each run is a training run's folder (its ``default_root_dir``, holding ``csv/version_*/
metrics.csv``) or one ``metrics.csv``. A run resumed after an interruption logs to a new
version folder; the versions are read in order and joined. For each metric (default the
validation AP50, all classes and crater) the script draws the value against the optimizer step
in one panel, every run a line, and prints one JSON line per run and metric: its last and best
value and the steps they were logged at.

    python benchmarks/plot_runs.py runs/s44_ft224_60_old runs/s44_ft224_60_new \\
        --labels "session 30's small.pt" "session 43's small.pt" --out outputs/runs.png
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import re
import sys
from pathlib import Path

from lunarnav_ml.errors import REPORTED_ERRORS, InputError
from lunarnav_ml.utils import atomic

DEFAULT_METRICS = ("val/AP50", "val/AP50_crater")


def _version_key(path: Path) -> int:
    match = re.fullmatch(r"version_(\d+)", path.parent.name)
    return int(match.group(1)) if match else -1


def metrics_files(run: str | Path) -> list[Path]:
    """The run's ``metrics.csv`` files, oldest version first."""
    run = Path(run)
    if run.is_file():
        return [run]
    if not run.is_dir():
        raise InputError(f"{run}: no such run folder or metrics.csv")
    files = sorted(run.glob("**/metrics.csv"), key=lambda p: (_version_key(p), str(p)))
    if not files:
        raise InputError(f"{run}: no metrics.csv under it (a Lightning CSVLogger writes "
                         "<save_dir>/<name>/version_N/metrics.csv)")
    return files


def read_curve(files: list[Path], metric: str) -> list[tuple[int, float]]:
    """(step, value) of every logged, finite value of ``metric`` across the files, in order."""
    return read_curves(files, [metric])[metric]


def read_curves(files: list[Path], metrics: list[str]) -> dict[str, list[tuple[int, float]]]:
    """Each metric's (step, value) points across the files, each file read once."""
    curves: dict[str, list[tuple[int, float]]] = {m: [] for m in metrics}
    seen: set[str] = set()
    for path in files:
        try:
            seen |= _read_file(path, curves)
        except (UnicodeDecodeError, csv.Error) as err:
            raise InputError(f"{path}: not a readable CSV file ({err})") from None
    for metric in metrics:
        if metric not in seen:
            raise InputError(f"{files[0]}: no column {metric!r}")
    return curves


def _read_file(path: Path, curves: dict[str, list[tuple[int, float]]]) -> set[str]:
    """Append ``path``'s finite values of each metric in ``curves`` to its points; return the
    metrics the file has a column for."""
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        if not reader.fieldnames or "step" not in reader.fieldnames:
            raise InputError(f"{path}: not a Lightning metrics.csv (no 'step' column)")
        present = set(curves) & set(reader.fieldnames)
        for line, row in enumerate(reader, start=2):
            for metric in present:
                if not row.get(metric):
                    continue
                try:
                    step, value = int(float(row["step"])), float(row[metric])
                except (TypeError, ValueError):
                    raise InputError(f"{path}, line {line}: step {row.get('step')!r} or "
                                     f"{metric} {row[metric]!r} is not a number") from None
                if math.isfinite(value):
                    curves[metric].append((step, value))
    return present


def summarize(points: list[tuple[int, float]]) -> dict:
    """Last and best (highest) value with their steps; Nones when nothing was logged."""
    if not points:
        return {"n": 0, "last": None, "last_step": None, "best": None, "best_step": None}
    best_step, best = max(points, key=lambda p: p[1])
    return {"n": len(points), "last": points[-1][1], "last_step": points[-1][0],
            "best": best, "best_step": best_step}


def plot_runs(runs: list[str | Path], labels: list[str], metrics: list[str],
              out: str | Path) -> list[dict]:
    """Read every run, draw one panel per metric into ``out`` (PNG, written atomically) and
    return the summary rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    atomic.check_image_destination(out)
    curves = [read_curves(metrics_files(run), metrics) for run in runs]
    fig, axes = plt.subplots(1, len(metrics), figsize=(5.5 * len(metrics), 4), squeeze=False)
    for ax, metric in zip(axes[0], metrics):
        for i, label in enumerate(labels):
            points = curves[i][metric]
            ax.plot([p[0] for p in points], [p[1] for p in points], label=label)
        ax.set_xlabel("step")
        ax.set_title(metric)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    atomic.write_figure(out, fig)
    return [{"run": str(run), "label": label, "metric": metric,
             **summarize(curves[i][metric])}
            for i, (run, label) in enumerate(zip(runs, labels)) for metric in metrics]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="run folders or metrics.csv files")
    ap.add_argument("--labels", nargs="+", help="one per run (default: the paths)")
    ap.add_argument("--metrics", nargs="+", default=list(DEFAULT_METRICS))
    ap.add_argument("--out", default="outputs/run_curves.png", help="the PNG to write")
    args = ap.parse_args(argv)
    labels = args.labels or [str(r) for r in args.runs]
    try:
        if len(labels) != len(args.runs):
            raise InputError(f"--labels: {len(labels)} labels for {len(args.runs)} runs")
        rows = plot_runs(args.runs, labels, args.metrics, args.out)
    except REPORTED_ERRORS as err:
        print(f"plot_runs: error: {err}", file=sys.stderr)
        return 2
    for row in rows:
        print(json.dumps(row))
    print(f"plot: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
