"""Detection report like the paper's monocular figures: COCO AP, Pd tables, plots, overlays."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lunarnav_ml.eval.coco_metrics import coco_ap
from lunarnav_ml.eval.pd import (
    CRATER_ID,
    MatchResult,
    box_precision,
    in_key_set,
    is_ignored,
    match_craters,
    pd_by,
    subset,
)
from lunarnav_ml.eval.plots import plot_pd_vs_range, plot_pd_vs_sun
from lunarnav_ml.utils import atomic

RANGE_EDGES = tuple(float(r) for r in range(5, 31, 2))  # near-rim range bins, m (paper: 5-29 m)
DIAMETER_GROUPS = ((2.0, 5.0), (5.0, 10.0), (10.0, 15.0), (15.0, 21.0))  # m
ZENITH_EDGES = (0.0, 10.0, 30.0, 50.0, 70.0, 90.0)  # around the paper's 0/20/40/60/80 deg
AZIMUTH_EDGES = (0.0, 30.0, 60.0, 90.0, 120.0, 150.0, 180.01)  # folded to 0-180 deg
PREDATE_NOTE = ("Note: these synthetic crater labels predate the `overprinted` rule, so craters "
                "that later impacts erased count as misses; render the set again with its seed to "
                "compare with BENCHMARKS.md (docs/synth.md).")
EDGE_ON_NOTE = ("Note: {n} countable crater labels here are seen edge-on (their rim ellipse is "
                "too thin for the default `edge_on` rule): the labels predate the rule or were "
                "rendered with it off, and such craters are almost never found; render the set "
                "again with its seed to compare with BENCHMARKS.md (docs/synth.md).")


def detection_metrics(
    gt: dict[str, Any], results: Sequence[dict[str, Any]], threshold: float
) -> dict[str, Any]:
    """All detection figures at one operating threshold.

    Args:
        gt: COCO ground truth with the crater keys of DESIGN.md (``near_rim_range_m``,
            ``diameter_m``) and image keys ``sun_zenith_deg`` / ``sun_azimuth_deg`` when known.
        results: COCO results.
        threshold: operating score threshold (picked on a validation split).
    """
    match = match_craters(gt, results, threshold)
    out: dict[str, Any] = {
        "threshold": threshold,
        "coco": coco_ap(gt, list(results)),
        "n_images": match.n_images,
        "crater_pd_all": atomic.finite_or_none(match.pd),
        "false_alarms_per_image": match.fa_per_image,
        "n_craters": int(match.hit.size),
        "box_precision": box_precision(match),
    }
    if match.gt and "near_rim_range_m" in match.gt[0]:
        out.update(_geometric_tables(gt, match))
    if labels_predate_overprint_rule(gt):
        out["labels_predate_overprint_rule"] = True
    if n_edge_on := countable_edge_on(gt):
        out["countable_edge_on_craters"] = n_edge_on
    return out


def labels_predate_overprint_rule(gt: dict[str, Any]) -> bool:
    """True for synthetic crater labels written before the ``overprinted`` ignore rule
    (2026-11-26): they have ``visible_rim_fraction`` but no ``surviving_bowl_fraction``, so
    craters that later impacts erased count as misses (docs/synth.md)."""
    craters = [a for a in gt.get("annotations", []) if a.get("category_id") == CRATER_ID]
    return (any("visible_rim_fraction" in a for a in craters)
            and not any("surviving_bowl_fraction" in a for a in craters))


def countable_edge_on(gt: dict[str, Any]) -> int:
    """How many countable synthetic crater labels the default ``edge_on`` rule (2026-11-26,
    :meth:`LabelConfig.edge_on`) would ignore."""
    from lunarnav_ml.synth.config import LabelConfig

    rule = LabelConfig()
    return sum(1 for a in gt.get("annotations", [])
               if a.get("category_id") == CRATER_ID and not is_ignored(a)
               and "visible_rim_fraction" in a and len(a.get("ellipse") or ()) == 5
               and rule.edge_on(2 * min(a["ellipse"][2], a["ellipse"][3]), a["bbox"][3]))


def _geometric_tables(gt: dict[str, Any], match: MatchResult) -> dict[str, Any]:
    diam = np.asarray([a.get("diameter_m", np.nan) for a in match.gt], dtype=float)
    rng = np.asarray([a.get("near_rim_range_m", np.nan) for a in match.gt], dtype=float)
    key_set = subset(match, np.array([in_key_set(a) for a in match.gt], dtype=bool))
    tables: dict[str, Any] = {
        "crater_pd_D5_within20m": atomic.finite_or_none(key_set.pd),
        "n_craters_D5_within20m": int(key_set.hit.size),
        "crater_pd_D5_within20m_ci95": pd_interval(int(key_set.hit.sum()), int(key_set.hit.size)),
        "box_precision_D5_within20m": box_precision(key_set),
        "pd_vs_range": {
            f"{lo:g}-{hi:g}": pd_by(subset(match, (diam >= lo) & (diam < hi)), "near_rim_range_m",
                                    RANGE_EDGES)
            for lo, hi in DIAMETER_GROUPS
        },
    }
    images = {img["id"]: img for img in gt["images"]}
    if all("sun_zenith_deg" in img for img in images.values()):
        zen = {i: float(img["sun_zenith_deg"]) for i, img in images.items()}
        az = {i: _fold_azimuth(float(img.get("sun_azimuth_deg", 0.0))) for i, img in images.items()}
        near = subset(match, (diam >= 5.0) & (rng <= 29.0))
        tables["pd_vs_sun_zenith"] = pd_by(near, "sun_zenith_deg", ZENITH_EDGES, zen)
        tables["pd_vs_sun_azimuth"] = pd_by(near, "sun_azimuth_deg", AZIMUTH_EDGES, az)
    return tables


def pd_interval(detected: int, n: int) -> list[float] | None:
    """The 95 % Wilson score interval of a Pd of ``detected`` in ``n`` (scipy's
    ``binomtest``), [low, high]; None for no craters. It counts each crater as an independent
    trial; craters of one frame share its light and terrain, so the true spread is wider."""
    if n == 0:
        return None
    from scipy.stats import binomtest

    ci = binomtest(detected, n).proportion_ci(confidence_level=0.95, method="wilson")
    return [float(ci.low), float(ci.high)]


def _fold_azimuth(az: float) -> float:
    """Sun azimuth relative to the view direction folded to 0-180 deg (0 = in front)."""
    az = az % 360.0
    return 360.0 - az if az > 180.0 else az


def write_report(metrics: dict[str, Any], out_dir: Path, title: str) -> dict[str, Path]:
    """Write metrics.json, report.md and the Pd plots into ``out_dir``."""
    out_dir = Path(out_dir)
    files = {"metrics": atomic.write_json(out_dir / "metrics.json", metrics)}
    if "pd_vs_range" in metrics:
        files["pd_vs_range"] = plot_pd_vs_range(metrics["pd_vs_range"], out_dir / "pd_vs_range.png")
    if "pd_vs_sun_zenith" in metrics:
        files["pd_vs_sun"] = plot_pd_vs_sun(metrics["pd_vs_sun_zenith"],
                                            metrics["pd_vs_sun_azimuth"], out_dir / "pd_vs_sun.png")
    files["report"] = atomic.write_text(out_dir / "report.md", render_markdown(metrics, title))
    return files


def render_markdown(metrics: dict[str, Any], title: str) -> str:
    """The report's markdown: COCO AP per class, Pd summary and the Pd tables."""
    lines = [f"# {title}", "", "## COCO (pycocotools)", "",
             "| class | AP@[.5:.95] | AP50 | ground truths |", "|---|---|---|---|"]
    for name, row in metrics["coco"]["per_class"].items():
        lines.append(f"| {name} | {_fmt(row['AP'])} | {_fmt(row['AP50'])} | {row['n_gt']} |")
    lines += ["", f"Operating threshold (picked on the validation split): {metrics['threshold']:.3f}",
              "", "## Crater Pd (IoU >= 0.5)", "",
              (f"- all non-ignored craters: Pd {_fmt(metrics['crater_pd_all'])} "
              f"(n = {metrics['n_craters']})"),
              f"- false alarms per image: {metrics['false_alarms_per_image']:.3f}"]
    if "crater_pd_D5_within20m" in metrics:
        ci = metrics.get("crater_pd_D5_within20m_ci95")
        lines.append(f"- craters D >= 5 m, near rim <= 20 m: Pd {_fmt(metrics['crater_pd_D5_within20m'])}"
                     f" (n = {metrics['n_craters_D5_within20m']}"
                     + ("" if ci is None else f"; 95 % interval {ci[0]:.3f}-{ci[1]:.3f}, Wilson, "
                        "craters counted as independent") + ")")
        lines += ["", "## Pd vs near-rim range", ""] + _range_table(metrics["pd_vs_range"])
    if metrics.get("labels_predate_overprint_rule"):
        lines += ["", PREDATE_NOTE]
    if metrics.get("countable_edge_on_craters"):
        lines += ["", EDGE_ON_NOTE.format(n=metrics["countable_edge_on_craters"])]
    lines += _box_table(metrics)
    for key, label in (("pd_vs_sun_zenith", "sun zenith"), ("pd_vs_sun_azimuth", "sun azimuth")):
        if key in metrics:
            lines += ["", f"## Pd vs {label} (craters D >= 5 m within 29 m)", "",
                      f"| {label} (deg) | n | Pd |", "|---|---|---|"]
            lines += [f"| {r['lo']:g}-{r['hi']:g} | {r['n']} | {_fmt(r['pd'])} |" for r in metrics[key]]
    return "\n".join(lines) + "\n"


def _box_table(metrics: dict[str, Any]) -> list[str]:
    """The detected craters' box precision (``box_precision``), all and the key set."""
    rows = [(name, metrics[key]) for name, key in
            (("all craters", "box_precision"), ("D >= 5 m, near rim <= 20 m",
                                                "box_precision_D5_within20m"))
            if metrics.get(key, {}).get("n")]
    if not rows:
        return []
    lines = ["", "## Box precision of the detected craters (fractions of the label's side)", "",
             ("Robust sigma of each edge's offset and the median size ratio - 1; the 3D lift "
              "takes a crater's width from its box."), "",
             "| craters | n | left | right | top | bottom | width | height |",
             "|---|---|---|---|---|---|---|---|"]
    for name, b in rows:
        e = b["edge_sigma"]
        lines.append(f"| {name} | {b['n']} | {e['left']:.3f} | {e['right']:.3f} | {e['top']:.3f} | "
                     f"{e['bottom']:.3f} | {b['width_ratio_median']:+.3f} | "
                     f"{b['height_ratio_median']:+.3f} |")
    return lines


def _range_table(pd_vs_range: dict[str, list[dict[str, Any]]]) -> list[str]:
    groups = list(pd_vs_range)
    head = "| near-rim range (m) | " + " | ".join(f"D {g} m: Pd (n)" for g in groups) + " |"
    lines = [head, "|---" * (len(groups) + 1) + "|"]
    for i, row in enumerate(pd_vs_range[groups[0]]):
        cells = [f"{_fmt(pd_vs_range[g][i]['pd'])} ({pd_vs_range[g][i]['n']})" for g in groups]
        lines.append(f"| {row['lo']:g}-{row['hi']:g} | " + " | ".join(cells) + " |")
    return lines


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3f}"
