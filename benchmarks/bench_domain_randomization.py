"""Domain-gap study, synthetic-randomization part: which render settings raise zero-shot
transfer to real frames. Measured on a real validation split only.

Every arm starts from the same synthetic detector, renders the same scenes (one master seed,
so terrain, craters and sun match item by item) under its own render settings, trains the same
number of steps on them, and is then run zero-shot on the real split, as it is and after the
best image-level adaptation of ``bench_domain_gap.py``. The ``control`` arm renders with the
default settings: it separates the effect of a randomization from that of the extra steps.

    .venv/bin/python benchmarks/bench_domain_randomization.py \\
        --gt data/real/chandai_v5/valid/annotations.json --val-synth data/d4/val/annotations.json \\
        --work /tmp/domain_rand --n 800 --steps 250

Arms: ``control`` (configs/synth/default.yaml) and every ``configs/synth/randomize/*.yaml``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from bench_domain_gap import adaptation_rows, format_row

from lunarnav_ml.errors import LunarNavError
from lunarnav_ml.training.api import load_detector
from lunarnav_ml.training.checkpoint import read_checkpoint

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def arms() -> dict[str, Path]:
    out = {"control": ROOT / "configs/synth/default.yaml"}
    out.update({p.stem: p for p in sorted((ROOT / "configs/synth/randomize").glob("*.yaml"))})
    return out


def run(cmd: list[str], log: Path) -> None:
    """Run one step of an arm; its output goes to ``log``; a failure stops the study."""
    with log.open("w") as f:
        proc = subprocess.run(cmd, check=False, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT)
    if proc.returncode:
        raise SystemExit(f"bench_domain_randomization: error: {' '.join(cmd[:3])} failed "
                         f"(exit {proc.returncode}), see {log}")


def render(arm_dir: Path, config: Path, args: argparse.Namespace) -> Path:
    ann = arm_dir / "train" / "annotations.json"
    if not ann.exists():
        run([str(BIN / "lunarnav"), "synth", str(arm_dir / "train"), "--n", str(args.n),
             "--seed", str(args.seed), "--config", str(config), "--size", str(args.size),
             "--no-stereo", "--workers", str(args.workers)], arm_dir / "render.log")
    return ann


def train(arm_dir: Path, ann: Path, args: argparse.Namespace) -> Path:
    ckpt = arm_dir / "run" / "last.ckpt"
    if ckpt.exists():
        return ckpt
    run_dir = arm_dir / "run"
    callbacks = [{"class_path": "lightning.pytorch.callbacks.ModelCheckpoint",
                  "init_args": {"dirpath": str(run_dir), "filename": "last", "save_last": True,
                                "save_top_k": 0, "every_n_train_steps": 50}}]
    logger = [{"class_path": "lightning.pytorch.loggers.CSVLogger",
               "init_args": {"save_dir": str(run_dir), "name": "csv"}}]
    run([str(BIN / "python"), "train.py", "fit", "--config", "configs/small_cpu.yaml",
         "--seed_everything", str(args.seed),
         "--data.train", str(ann), "--data.val", str(args.val_synth),
         "--model.init_from", str(args.init), "--model.preset", args.preset,
         "--model.lr", str(args.lr),
         "--model.warmup_steps", "50", "--trainer.max_steps", str(args.steps),
         "--trainer.max_time", "null", "--trainer.limit_val_batches", "0",
         "--trainer.enable_progress_bar", "false", "--trainer.default_root_dir", str(run_dir),
         "--trainer.logger", json.dumps(logger), "--trainer.callbacks", json.dumps(callbacks)],
        arm_dir / "train.log")
    return ckpt


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gt", type=Path, required=True, help="real validation annotations.json")
    ap.add_argument("--val-synth", type=Path, required=True,
                    help="a synthetic validation annotations.json (train.py needs one)")
    ap.add_argument("--work", type=Path, required=True, help="renders and runs go here")
    ap.add_argument("--init", type=Path, default=ROOT / "lunarnav_ml/weights/small.pt")
    ap.add_argument("--n", type=int, default=800, help="renders per arm")
    ap.add_argument("--steps", type=int, default=250, help="training steps per arm")
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--seed", type=int, default=3, help="render master seed, shared by all arms")
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--arms", nargs="*", default=None, help="subset of arms (default: all)")
    ap.add_argument("--adaptations", nargs="*", default=["none", "grayscale+equalize"])
    args = ap.parse_args(argv)
    try:
        gt = json.loads(args.gt.read_text())
    except (OSError, json.JSONDecodeError) as err:
        print(f"bench_domain_randomization: error: {args.gt}: {err}", file=sys.stderr)
        return 2
    try:  # train each arm as the network the start weights belong to (small.pt: small-relu)
        args.preset = read_checkpoint(args.init)[0]["preset"]
    except (LunarNavError, KeyError) as err:
        print(f"bench_domain_randomization: error: {args.init}: no preset ({err})", file=sys.stderr)
        return 2
    chosen = arms()
    if args.arms:
        unknown = sorted(set(args.arms) - set(chosen))
        if unknown:
            print(f"bench_domain_randomization: error: unknown arm {unknown[0]!r} "
                  f"(known: {', '.join(chosen)})", file=sys.stderr)
            return 2
        chosen = {k: v for k, v in chosen.items() if k in args.arms}
    rows = []
    for name, config in chosen.items():
        arm_dir = args.work / name
        arm_dir.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        ann = render(arm_dir, config, args)
        t1 = time.perf_counter()
        ckpt = train(arm_dir, ann, args)
        t2 = time.perf_counter()
        print(f"{name}: render {t1 - t0:.0f} s, train {t2 - t1:.0f} s", flush=True)
        try:
            detector = load_detector(ckpt)
        except LunarNavError as err:
            print(f"bench_domain_randomization: error: {err}", file=sys.stderr)
            return 2
        for row in adaptation_rows(detector, gt, args.gt.parent, args.adaptations):
            rows.append({"arm": name, **row})
            print(f"| {name} " + format_row(row), flush=True)
    print("\n| arm | adaptation | crater recall@5 | rock recall@5 | crater AP50 (lower bound) |")
    print("|---|---|---|---|---|")
    for row in rows:
        print(f"| {row['arm']} " + format_row(row))
    (args.work / "rows.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
