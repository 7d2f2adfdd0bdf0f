"""Study of the lifter's rim-residual gate on a development stereo set.

Runs the geometry report once with the gate open (every lift kept and scored), then applies
candidate gates to the per-crater rows (``rim_residual_px``, ``rim_disparity_px``,
``crest_fraction``) and prints, per gate, the 3-sigma horizontal center error for craters
15-20 m away and over all ranges (D = 5 / 10 / 15 / 20 m), the diameter 3-sigma at 15-20 m,
Pd(3D) and the lifted count. Use a development render, never the evaluation set:

    .venv/bin/lunarnav synth /tmp/dev_ps --protocol paper-stereo --seed 1 --size 1024 --shard 0/7
    .venv/bin/python benchmarks/lifter_gate_study.py /tmp/dev_ps/annotations.shard-0-of-7.json \\
        --out outputs/dev_gate_study

Several sets pool their rows (each set's report in ``--out/<annotations file stem>``).

The lifter's retry (``LifterConfig.retry_snap_px``) is studied as it works: a second open-gate
run with the crest searched ``--retry-snap`` rows (``--out/<stem>/retry``), whose row stands in
for a crater's first row where that one fails a gate and the second passes (0: no retry). The
lifter's second crest rule (``reach_far_arc``) is off in these runs, so each row is the one
search and rule it names.

``--rows-only`` re-reads ``geometry_craters.json`` from ``--out`` instead of running again.
``--as-is`` runs the lifter with its own gates and all its tries (``--lifter`` settings
applied) and prints one row for the pooled sets: what the defaults give, nothing emulated.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any

from lunarnav_ml.errors import LunarNavError
from lunarnav_ml.geometry.lifter import LifterConfig
from lunarnav_ml.geometry.report import geometry_report, summarize
from lunarnav_ml.utils.jsonfile import read_json_file

# (absolute px, fraction of the rim disparity, least crest fraction)
GATES = [(1e9, 0.0, 0.0), (1.5, 0.0, 0.0), (1.0, 0.05, 0.0), (1.5, 0.08, 0.0), (1.5, 0.10, 0.0),
         (1.5, 0.12, 0.0), (1.5, 0.15, 0.0), (1.5, 0.20, 0.0), (1.5, 0.25, 0.0), (1.5, 0.0, 0.3),
         (1.5, 0.0, 0.5), (1.2, 0.10, 0.0), (1.0, 0.10, 0.0), (1.0, 0.12, 0.0), (0.8, 0.08, 0.0),
         (0.8, 0.10, 0.0), (0.6, 0.10, 0.0)]
DIAMETERS = ("5.0", "10.0", "15.0", "20.0")


def apply_gate(rows: list[dict[str, Any]], abs_px: float, rel: float, min_crest: float,
               retry: list[dict[str, Any]] | None = None) -> list[dict[str, Any]]:
    """Rows with ``ok`` cleared where a lift fails this gate; with ``retry`` (rows of the same
    craters in the same order), a failed row is replaced by its retry row where that passes."""
    cfg = LifterConfig(max_rim_residual_px=abs_px, max_rim_residual_rel=rel)

    def passes(r: dict[str, Any]) -> bool:
        return bool(r["ok"] and r["rim_residual_px"] <= cfg.residual_limit_px(r["rim_disparity_px"])
                    and (r["crest_fraction"] or 0.0) >= min_crest)

    out = []
    for k, r in enumerate(rows):
        if passes(r):
            out.append(r)
        elif retry is not None and passes(retry[k]):
            out.append(retry[k])
        else:
            out.append({**r, "ok": False})
    return out


def _per_d(metrics: dict[str, Any], key: str, window: str) -> str:
    per_d = metrics["per_diameter"]
    vals = [per_d.get(d, {}).get(window, {}).get(key) for d in DIAMETERS]
    return " / ".join("-" if v is None else f"{v:.2f}" for v in vals)


def _mean_all_d(metrics: dict[str, Any]) -> float:
    vals = [v["range_15_20"].get("center_3sigma_m") for v in metrics["per_diameter"].values()]
    vals = [v for v in vals if v is not None]
    return sum(vals) / len(vals) if vals else float("nan")


def _lifter_settings(items: list[str]) -> dict[str, Any]:
    fields = {f.name: f.type for f in dataclasses.fields(LifterConfig)}
    out: dict[str, Any] = {}
    for item in items:
        name, _, value = item.partition("=")
        if name not in fields or not value:
            raise LunarNavError(f"--lifter: expected FIELD=VALUE with a LifterConfig field, "
                                f"got {item!r}")
        kind = str(fields[name])
        if kind not in _PARSERS:
            raise LunarNavError(f"--lifter: {name} is a {kind}; settable here: "
                                f"{', '.join(_PARSERS)} fields")
        try:
            out[name] = _PARSERS[kind](value)
        except ValueError:
            raise LunarNavError(f"--lifter: {name} expects type {kind}, got {value!r}") from None
    return out


def _parse_bool(value: str) -> bool:
    if value not in ("true", "false"):
        raise ValueError(value)
    return value == "true"


_PARSERS = {"int": int, "float": float, "bool": _parse_bool, "str": str,
            "float | None": lambda v: None if v.lower() == "none" else float(v)}


def _report_rows(args: argparse.Namespace, gt: Path, folder: Path,
                 settings: dict[str, Any]) -> list[dict[str, Any]]:
    """The geometry report's rows of one set with these lifter settings (``--rows-only``: the
    rows already in ``folder``)."""
    if not args.rows_only:
        geometry_report(gt, folder, ellipse_source=args.ellipse_source, plots=False,
                        lifter=LifterConfig(**settings))
    return read_json_file(folder / "geometry_craters.json", "geometry report rows")


def _as_is(args: argparse.Namespace, settings: dict[str, Any]) -> int:
    rows = [r for gt in args.gt for r in _report_rows(args, gt, args.out / gt.stem, settings)]
    m = summarize(rows)
    print("3s centre 15-20 m, every D | mean | 3s centre 15-20 m, D = 5 / 10 / 15 / 20 | Pd(3D) |"
          " lifted")
    per_d = m["per_diameter"]
    every = " / ".join(f"{v['range_15_20']['center_3sigma_m'] or float('nan'):.2f}"
                       for v in per_d.values())
    print(f"{every} | {_mean_all_d(m):.2f} | {_per_d(m, 'center_3sigma_m', 'range_15_20')} | "
          f"{m['overall']['pd_3d']:.3f} | {m['overall']['n_lifted']}")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("gt", type=Path, nargs="+",
                   help="development stereo sets (annotations files); rows go to --out/<file stem>")
    p.add_argument("--out", type=Path, default=Path("outputs/dev_gate_study"))
    p.add_argument("--ellipse-source", default="fit", choices=("fit", "label", "box"))
    p.add_argument("--rows-only", action="store_true", help="reuse the rows in --out")
    p.add_argument("--lifter", nargs="*", default=[], metavar="FIELD=VALUE",
                   help="other LifterConfig settings for the run, e.g. snap_px=12")
    p.add_argument("--as-is", action="store_true",
                   help="the lifter with its own gates and tries; one pooled row")
    p.add_argument("--retry-snap", type=int, default=LifterConfig().retry_snap_px,
                   help="rows the retry searches for the crest (default: the lifter's; 0: none)")
    args = p.parse_args(argv)
    try:
        settings = _lifter_settings(args.lifter)
        if args.as_is:
            return _as_is(args, settings)
        rows, retry = [], []
        for gt in args.gt:
            part = args.out / gt.stem
            # open gate, one search and one crest rule a run: each row is the try it names
            one = {**settings, "retry_snap_px": 0, "reach_far_arc": False,
                   "max_rim_residual_px": 1e9}
            rows += _report_rows(args, gt, part, one)
            if args.retry_snap:
                retry += _report_rows(args, gt, part / "retry", {**one, "snap_px": args.retry_snap})
        if retry and [r["ann_id"] for r in retry] != [r["ann_id"] for r in rows]:
            raise LunarNavError(f"{args.out}: the retry rows are not the same craters; run "
                                f"again without --rows-only")
    except LunarNavError as err:
        print(f"lifter_gate_study: error: {err}", file=sys.stderr)
        return 2
    print("gate (abs px, rel, crest) | 3s centre 15-20 m | 3s centre all | 3s diameter 15-20 m"
          " | Pd(3D) | lifted | Pd(3D) at 5 / 6 / 7 m | 3s centre 15-20 m, mean of every D")
    for gate in GATES:
        m = summarize(apply_gate(rows, *gate, retry=retry or None))
        near = " / ".join(f"{m['pd_3d_vs_range'].get(str(k)) or 0:.2f}" for k in (5, 6, 7))
        print(f"{gate} | {_per_d(m, 'center_3sigma_m', 'range_15_20')} | "
              f"{_per_d(m, 'center_3sigma_m', 'all_ranges')} | "
              f"{_per_d(m, 'diameter_3sigma_m', 'range_15_20')} | {m['overall']['pd_3d']:.3f} | "
              f"{m['overall']['n_lifted']} | {near} | {_mean_all_d(m):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
