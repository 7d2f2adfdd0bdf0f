"""Figures like the paper's baseline evaluations: Pd and position error vs near-rim range."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from lunarnav_ml.utils import atomic

PD_GOAL = 0.5  # the paper's KPP: Pd 0.5 for 5 m craters at 15 m


def plot_baseline(metrics: dict[str, Any], out_dir: Path) -> dict[str, Path]:
    """Write pd_vs_range.png and position_error.png; returns their paths.

    Args:
        metrics: output of :func:`lunarnav_ml.baselines.report.summarize` (with ``method``).
        out_dir: destination folder.
    """
    return {"pd_vs_range": _pd_plot(metrics, out_dir / "pd_vs_range.png"),
            "position_error": _error_plot(metrics, out_dir / "position_error.png")}


def _pd_plot(metrics: dict[str, Any], path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for dm, rows in metrics["pd_vs_range"].items():
        r = [row["range_m"] for row in rows if row["pd"] is not None]
        p = [row["pd"] for row in rows if row["pd"] is not None]
        ax.plot(r, p, marker="o", ms=3, label=f"D = {dm} m")
    ax.axhline(PD_GOAL, color="green", ls="--", lw=1, label="KPP goal")
    ax.set(xlabel="near-rim range (m)", ylabel="Pd", ylim=(-0.02, 1.02),
           title=f"{metrics['method']} baseline: Pd vs near-rim range")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    return atomic.write_figure(path, fig)


def _error_plot(metrics: dict[str, Any], path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    recs = [r for r in metrics["records"] if r["hit"]]
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, dm in enumerate(metrics["pd_vs_range"]):
        sel = [r for r in recs if f"{r['diameter_m']:g}" == dm]
        if not sel:
            continue
        c = colors[i % len(colors)]
        rng = np.array([r["near_rim_range_m"] for r in sel])
        err = np.hypot([r["dx"] for r in sel], [r["dy"] for r in sel])
        ax.scatter(rng + 0.08 * (i - 3), err, s=8, color=c, label=f"D = {dm} m")
        paper = metrics["position_error"][dm].get("paper_3sigma_m")
        if paper is not None:
            ax.axhline(paper, color=c, ls=":", lw=1)
    ax.set(xlabel="near-rim range (m)", ylabel="horizontal center error (m)",
           title=f"{metrics['method']} baseline: position error (dotted: paper 3 sigma)")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    return atomic.write_figure(path, fig)
