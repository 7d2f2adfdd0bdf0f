"""Plots and overlay images a person can look at."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import cv2
import matplotlib.pyplot as plt
import numpy as np

from lunarnav_ml.utils import atomic

# BGR colours per category id: crater, rock, artifact.
CLASS_COLORS = {1: (60, 60, 255), 2: (255, 160, 40), 3: (40, 220, 255)}
GT_COLOR = (60, 220, 60)
IGNORE_COLOR = (150, 150, 150)


def plot_pd_vs_range(pd_vs_range: dict[str, list[dict[str, Any]]], path: Path) -> Path:
    """Pd vs near-rim range, one line per crater diameter group, with the KPP lines."""
    fig, ax = plt.subplots(figsize=(7, 4))
    for group, rows in pd_vs_range.items():
        x = [(r["lo"] + r["hi"]) / 2 for r in rows if r["pd"] is not None]
        y = [r["pd"] for r in rows if r["pd"] is not None]
        if x:
            ax.plot(x, y, marker="o", label=f"D {group} m")
    ax.axhline(0.5, color="r", ls="--", lw=1, label="KPP threshold (0.5)")
    ax.axhline(0.9, color="g", ls="--", lw=1, label="goal (0.9)")
    ax.set(xlabel="near-rim range (m)", ylabel="Pd (IoU >= 0.5)", ylim=(0, 1.05),
           title="Crater Pd vs range")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return atomic.write_figure(path, fig)


def plot_pd_vs_sun(zenith: Sequence[dict], azimuth: Sequence[dict], path: Path) -> Path:
    """Pd vs sun zenith and vs sun azimuth (two panels), with the paper's 0.75 bar."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, rows, label in ((axes[0], zenith, "sun zenith (deg)"),
                            (axes[1], azimuth, "sun azimuth from view direction (deg)")):
        x = [(r["lo"] + r["hi"]) / 2 for r in rows if r["pd"] is not None]
        y = [r["pd"] for r in rows if r["pd"] is not None]
        ax.plot(x, y, marker="o")
        ax.axhline(0.75, color="r", ls="--", lw=1, label="paper's bar (0.75)")
        ax.set(xlabel=label, ylabel="Pd", ylim=(0, 1.05))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Crater Pd vs illumination (D >= 5 m within 29 m)")
    return atomic.write_figure(path, fig)


def draw_overlay(
    image: np.ndarray,
    gt_anns: Sequence[dict[str, Any]],
    detections: Sequence[dict[str, Any]],
    class_names: dict[int, str],
) -> np.ndarray:
    """Draw ground truth (green, ignored grey) and detections (per class colour) on an image.

    Args:
        image: HxW or HxWx3 uint8 (BGR).
        gt_anns: COCO annotations of this image.
        detections: COCO results of this image (already thresholded).
        class_names: category id -> name.

    Returns:
        HxWx3 uint8 BGR overlay.
    """
    canvas = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    for ann in gt_anns:
        x, y, w, h = (round(v) for v in ann["bbox"])
        color = IGNORE_COLOR if ann.get("ignore") or ann.get("iscrowd") else GT_COLOR
        cv2.rectangle(canvas, (x, y), (x + w, y + h), color, 1)
    for det in detections:
        x, y, w, h = (round(v) for v in det["bbox"])
        color = CLASS_COLORS.get(det["category_id"], (255, 255, 255))
        cv2.rectangle(canvas, (x, y), (x + w, y + h), color, 2)
        label = f"{class_names.get(det['category_id'], '?')} {det['score']:.2f}"
        cv2.putText(canvas, label, (x, max(y - 3, 10)), cv2.FONT_HERSHEY_SIMPLEX, 0.4, color, 1,
                    cv2.LINE_AA)
    return canvas
