"""Which of the lifter's crest lifts to keep: every candidate lift of every crater, then the
selection rules compared with the edge offsets calibrated for each, shard by shard held out.

``lift_crater`` ("tangent") lifts each crater with up to four candidates: two crest searches
(``snap_px``, then ``retry_snap_px``) and two crest rules (the largest disparity step near the
ellipse, and with ``reach_far_arc`` the lowest step up to the far arc); today it keeps, from
the first search with any lift passing every check, the mean of the two where both pass and
their ranges agree within ``LifterConfig.mean_rules_within`` (2 %, session 67), else the
farther passing lift (the rule of sessions 33-66). This study runs
SGBM once per stereo pair (cached as ``--out/<set stem>/disparity/<image id>.npz``), lifts
every evaluated crater from its labelled box's ellipse (the geometry report's default path)
with every candidate at zero edge offsets, and keeps each candidate's outcome
(``--out/<set stem>/candidates.json``). Then, per selection rule and per held-out set, it
calibrates the box edge offsets on the other sets (``calibrate_rim_offset.fit_offset``),
moves each held-out lift along its line of sight by its offset (error e -> e + offset / k0,
k0 = 1 - r / rho) and prints the 3-sigma centre error at 15-20 m per diameter, pooled over the
held-out sets, with Pd(3D). The move is the calibration's own linearisation; the lifter folds
the offset into each sample, so confirm a chosen rule with ``lunarnav eval --task geometry``.
Use development renders, never the evaluation set:

    .venv/bin/lunarnav synth /tmp/dev_ps --protocol paper-stereo --seed 1 --size 1024 --shard 0/7
    .venv/bin/python benchmarks/crest_rule_study.py <two or more annotations files> \\
        --out outputs/crest_rule_study

``--rows-only`` re-reads the candidates in ``--out``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from calibrate_rim_offset import fit_offset, needed_offsets

from lunarnav_ml.errors import LunarNavError
from lunarnav_ml.geometry._checks import crater_labels_3d
from lunarnav_ml.geometry.ellipse import Ellipse
from lunarnav_ml.geometry.frames import StereoRig, camera_to_rover
from lunarnav_ml.geometry.lifter import (
    LifterConfig,
    _crest_reach,
    _lift_tangent,
    _tries,
    ranges_agree,
    rows_needed,
)
from lunarnav_ml.geometry.report import evaluated_label, read_gray, summarize
from lunarnav_ml.geometry.stereo import SGBMStereo
from lunarnav_ml.utils.atomic import write_json
from lunarnav_ml.utils.images import read_disparity
from lunarnav_ml.utils.jsonfile import read_json_file

# the default gates and tries, as a box lift (``lift_crater(..., from_box=True)``) with every
# edge offset at 0: the offsets are fitted per rule afterwards
ZERO = replace(LifterConfig(), rim_offset=0.0, rim_offset_m=0.0, rim_offset_view=0.0,
               rim_model_sigma=LifterConfig().box_rim_model_sigma)
DIAMETERS = (5.0, 7.0, 10.0, 12.0, 15.0, 17.0, 20.0)


def _disparity(cache: Path, im: dict[str, Any], boxes: np.ndarray,
               pair: tuple[np.ndarray, np.ndarray], cfg: LifterConfig) -> np.ndarray:
    """SGBM on the band the boxes need, cached in 1/16 px steps (-1: invalid)."""
    path = cache / f"{im['id']}.npz"
    if path.is_file():
        q = np.load(path)["d16"]
        return np.where(q < 0, np.nan, q / 16.0)
    left, right = pair
    rows = rows_needed(boxes + np.array([0.5, 0.5, 0.0, 0.0]), left.shape[0], cfg)
    disp = SGBMStereo.for_width(left.shape[1])(left, right, rows).disparity
    q = np.where(np.isfinite(disp) & (disp > 0), np.round(disp * 16.0), -1).astype(np.int16)
    cache.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, d16=q)
    tmp.replace(path)
    return np.where(q < 0, np.nan, q / 16.0)


def candidates(gt: Path, out: Path, rendered: bool = False, label_ellipse: bool = False
               ) -> list[dict[str, Any]]:
    """One row per evaluated crater with every candidate lift (zero box edge offsets);
    ``rendered``: from the dataset's own disparity (no matcher, no crest match);
    ``label_ellipse``: from the labelled rim ellipse instead of the box's."""
    coco = read_json_file(gt, "annotations", expect=dict)
    root = gt.parent
    anns: dict[int, list[dict[str, Any]]] = {}
    for ann in crater_labels_3d(gt, coco):
        if evaluated_label(ann, 4.5):  # the geometry report's craters (its default min_diameter_m)
            anns.setdefault(ann["image_id"], []).append(ann)
    rows = []
    images = [im for im in coco["images"] if im.get("right_file") and anns.get(im["id"])]
    for n, im in enumerate(images):
        rig = StereoRig.from_camera_record(im["camera"])
        boxes = np.array([a["bbox"] for a in anns[im["id"]]], dtype=np.float64) - [0.5, 0.5, 0, 0]
        if rendered:
            disp, pair = read_disparity(root, im), None
        else:
            pair = (read_gray(root, im["file_name"]), read_gray(root, im["right_file"]))
            disp = _disparity(out / "disparity", im, boxes, pair, ZERO)
        for ann, box in zip(anns[im["id"]], boxes):
            ell = Ellipse.from_array(ann["ellipse"]) if label_ellipse else Ellipse.from_box(box)
            truth = camera_to_rover(ann["center_cam_m"], rig.height_m, rig.pitch_deg,
                                    rig.roll_deg)[0]
            cands, done = [], set()
            for search in _tries(ZERO):
                reach = _crest_reach(search[0][0], ell)
                if reach in done:
                    continue
                done.add(reach)
                for tried, lowest in search:
                    res = _lift_tangent(ell, disp, rig, tried, pair, lowest_step=lowest)
                    cands.append({"search": int(reach), "rule": "lowest" if lowest else "largest",
                                  "ok": bool(res.ok), "reason": res.reason,
                                  "center_m": res.center_m[:2].tolist() if res.ok else None,
                                  "diameter_m": float(res.diameter_m) if res.ok else None,
                                  "rim_residual_px": float(res.rim_residual_px),
                                  "rim_disparity_px": float(res.rim_disparity_px)})
            rows.append({"ann_id": ann["id"], "image_id": im["id"],
                         "diameter_m": float(ann["diameter_m"]),
                         "near_rim_range_m": float(ann["near_rim_range_m"]),
                         "truth_center_m": truth.tolist(), "camera_height_m": rig.height_m,
                         "candidates": cands})
        print(f"\r{gt.parent.name}: {n + 1}/{len(images)} pairs", end="", file=sys.stderr)
    print(file=sys.stderr)
    return rows


# a rule maps a crater's candidate lifts (every search and crest rule) to the one kept, or None
Rule = Callable[[list[dict[str, Any]]], dict[str, Any] | None]


def _rng(c: dict[str, Any]) -> float:
    return float(np.hypot(*c["center_m"]))


def _first_search(cands: list[dict[str, Any]]) -> list[dict[str, Any]]:
    for s in sorted({c["search"] for c in cands}):
        passed = [c for c in cands if c["search"] == s and c["ok"]]
        if passed:
            return passed
    return []


def _prefer(rule: str) -> Rule:
    def pick(cands: list[dict[str, Any]]) -> dict[str, Any] | None:
        passed = _first_search(cands)
        own = [c for c in passed if c["rule"] == rule]
        return (own or passed or [None])[0]
    return pick


def _extreme(fn: Callable[..., Any], key: Callable[[dict[str, Any]], float]) -> Rule:
    def pick(cands: list[dict[str, Any]]) -> dict[str, Any] | None:
        passed = _first_search(cands)
        return fn(passed, key=key) if passed else None
    return pick


def _mean_of_both(cands: list[dict[str, Any]]) -> dict[str, Any] | None:
    passed = _first_search(cands)
    if not passed:
        return None
    return {**passed[0], "center_m": np.mean([c["center_m"] for c in passed], axis=0).tolist(),
            "diameter_m": float(np.mean([c["diameter_m"] for c in passed]))}


def _within(passed: list[dict[str, Any]], frac: float) -> bool:
    """The passing lifts lie within ``frac`` radii of each other along their ranges."""
    ranges = [_rng(c) for c in passed]
    return max(ranges) - min(ranges) <= frac * passed[0]["diameter_m"] / 2


def _mean_within(frac: float) -> Rule:
    """The mean of the passing lifts where they lie within ``frac`` radii of each other, else
    the farther."""
    def pick(cands: list[dict[str, Any]]) -> dict[str, Any] | None:
        passed = _first_search(cands)
        if not passed:
            return None
        return _mean_of_both(passed) if _within(passed, frac) else max(passed, key=_rng)
    return pick


def _agreeing(frac: float) -> Rule:
    """The farther passing lift where the passing lifts lie within ``frac`` radii of each
    other; none where they disagree by more (an ambiguous crest)."""
    def pick(cands: list[dict[str, Any]]) -> dict[str, Any] | None:
        passed = _first_search(cands)
        return max(passed, key=_rng) if passed and _within(passed, frac) else None
    return pick


def _only(rule: str) -> Rule:
    def pick(cands: list[dict[str, Any]]) -> dict[str, Any] | None:
        return (_first_search([c for c in cands if c["rule"] == rule]) or [None])[0]
    return pick


def _mean_within_range(frac: float) -> Rule:
    """The mean of the passing lifts where their ranges agree (the lifter's
    :func:`~lunarnav_ml.geometry.lifter.ranges_agree`, ``LifterConfig.mean_rules_within``), else
    the farther."""
    def pick(cands: list[dict[str, Any]]) -> dict[str, Any] | None:
        passed = _first_search(cands)
        if not passed:
            return None
        ranges = [_rng(c) for c in passed]
        agree = ranges_agree(min(ranges), max(ranges), frac)
        return _mean_of_both(passed) if agree else max(passed, key=_rng)
    return pick


TODAY = LifterConfig().mean_rules_within
RULES: dict[str, Rule] = {
    f"mean within {100 * TODAY:g} % of the range, else farther (today)": _mean_within_range(TODAY),
    "farther (sessions 33-66)": _extreme(max, _rng),
    "nearer": _extreme(min, _rng),
    "largest first": _prefer("largest"),
    "lowest first": _prefer("lowest"),
    "largest only": _only("largest"),
    "lowest only": _only("lowest"),
    "smaller relative residual": _extreme(
        min, lambda c: c["rim_residual_px"] / max(c["rim_disparity_px"], 1e-9)),
    "mean of the passing": _mean_of_both,
    "mean within 0.25 r, else farther": _mean_within(0.25),
    "mean within 0.5 r, else farther": _mean_within(0.5),
    "farther, none where they differ by > 0.05 r": _agreeing(0.05),
    "farther, none where they differ by > 0.1 r": _agreeing(0.1),
    "farther, none where they differ by > 0.2 r": _agreeing(0.2),
}


def _report_row(row: dict[str, Any], pick: dict[str, Any] | None) -> dict[str, Any]:
    base = {k: row[k] for k in ("ann_id", "diameter_m", "near_rim_range_m", "truth_center_m",
                                "camera_height_m")}
    if pick is None:
        return {**base, "ok": False, "reason": "lift", "from_box": True}
    err = np.asarray(pick["center_m"]) - np.asarray(row["truth_center_m"][:2])
    return {**base, "ok": True, "reason": "ok", "from_box": True, "center_err_xy_m": err.tolist(),
            "center_err_m": float(np.hypot(*err)),
            "diameter_err_m": pick["diameter_m"] - row["diameter_m"]}


def _with_offset(rows: list[dict[str, Any]], terms: tuple[float, float, float]
                 ) -> list[dict[str, Any]]:
    """Each lift moved along its line of sight by the edge offset these terms give."""
    icpt, slope, view = terms
    out = []
    for r in rows:
        if not r["ok"]:
            out.append(r)
            continue
        truth = np.asarray(r["truth_center_m"][:2])
        rho = float(np.linalg.norm(truth))
        radius = r["diameter_m"] / 2.0
        offset = icpt + slope * radius + view * radius * r["camera_height_m"] / r["near_rim_range_m"]
        err = np.asarray(r["center_err_xy_m"]) + truth / rho * offset / (1.0 - radius / rho)
        out.append({**r, "center_err_xy_m": err.tolist(), "center_err_m": float(np.hypot(*err))})
    return out


def compare(sets: list[list[dict[str, Any]]], held_out: int = 0) -> None:
    """Per rule, the pooled held-out figures: each set held out in turn with offsets fitted on
    the others, or (``held_out`` > 0) the last ``held_out`` sets with offsets fitted on the
    rest."""
    print("rule | 3s centre 15-20 m, D = " + " / ".join(f"{d:g}" for d in DIAMETERS)
          + " | mean | Pd(3D) | offsets per fold (m, r, r H/R)")
    for name, rule in RULES.items():
        picked = [[_report_row(r, rule(r["candidates"])) for r in rows] for rows in sets]
        held, fits = [], []
        folds = ([[k] for k in range(len(sets))] if not held_out
                 else [list(range(len(sets) - held_out, len(sets)))])
        for fold in folds:
            train = [r for j, rows in enumerate(picked) if j not in fold for r in rows]
            radius, near, need, height = needed_offsets(train)
            terms = fit_offset(radius, near, need, height)[:3]
            fits.append(terms)
            held += [r for k in fold for r in _with_offset(picked[k], terms)]
        m = summarize(held)
        vals = [m["per_diameter"].get(str(d), {}).get("range_15_20", {}).get("center_3sigma_m")
                for d in DIAMETERS]
        mean = np.mean([v for v in vals if v is not None])
        terms = "; ".join(f"{a:+.3f} {b:+.3f} {c:+.3f}" for a, b, c in fits)
        print(f"{name} | " + " / ".join("-" if v is None else f"{v:.2f}" for v in vals)
              + f" | {mean:.2f} | {m['overall']['pd_3d']:.3f} | {terms}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("gt", type=Path, nargs="+", help="two or more development annotations files")
    p.add_argument("--out", type=Path, default=Path("outputs/crest_rule_study"))
    p.add_argument("--rows-only", action="store_true", help="reuse the candidates in --out")
    p.add_argument("--ellipse", choices=("box", "label"), default="box",
                   help="label: lift from the labelled rim ellipse (isolates the box's ellipse)")
    p.add_argument("--held-out", type=int, default=0,
                   help="evaluate the last N sets with offsets fitted on the others (default: "
                        "each set held out in turn)")
    p.add_argument("--disparity", choices=("sgbm", "rendered"), default="sgbm",
                   help="rendered: the dataset's own disparity (isolates the lift from the matcher)")
    args = p.parse_args(argv)
    if len(args.gt) < 2:
        p.error("two or more sets: each is held out in turn")
    sets = []
    try:
        for gt in args.gt:
            path = args.out / gt.parent.name / "candidates.json"
            if not args.rows_only:
                write_json(path, candidates(gt, args.out / gt.parent.name,
                                             args.disparity == "rendered",
                                             args.ellipse == "label"))
            sets.append(read_json_file(path, "candidates", expect=list))
        compare(sets, args.held_out)
    except LunarNavError as err:
        print(f"crest_rule_study: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
