"""Onboard runtime figures: per-frame latency of each preset (onnxruntime fp32 / int8, eager
PyTorch), achieved GFLOP/s, and the int8 accuracy cost on a labeled test set.

Latency of presets with untrained weights (live activations) and of trained checkpoints:

    .venv/bin/python benchmarks/bench_runtime.py latency --presets nano tiny small \\
        --checkpoints lunarnav_ml/weights/small.pt --sizes 512 1024 --threads 1 2 --runs 7

Each onnxruntime cell is timed in a fresh process: timed in this one after PyTorch ran, int8
read much slower on the 2-core Xeon with AMX. The calls are end to end, NMS included, and
random weights put many boxes over the threshold, so their int8 speed-ups read low; timed on
the network alone (``--network-only``) they still read lower and wider than trained files of
the same architecture: quote trained checkpoints (BENCHMARKS.md, issue 8, sessions 63 and
64).

Accuracy (a trained checkpoint; calibration images from a split other than the test set):

    .venv/bin/python benchmarks/bench_runtime.py accuracy --checkpoint best.ckpt \\
        --test data/test/annotations.json --calib data/val

Input size on larger frames (the network is fully convolutional; which input side detects
best on, say, 1024 px frames, with its latency; choose on a split other than the test set):

    .venv/bin/python benchmarks/bench_runtime.py input-size --checkpoint small.pt \
        --test <dev set>/annotations.json --sizes 384 512 768 1024 [--calib <val split>]

The ceiling to read achieved GFLOP/s against: a large fp32 matrix product (GEMM) per thread
count, through onnxruntime and PyTorch:

    .venv/bin/python benchmarks/bench_runtime.py peak --threads 1 2

Where int8 gains and where it does not: onnxruntime's profiler per module (stem, each
backbone stage, each neck and head block), fp32 against int8, network only:

    .venv/bin/python benchmarks/bench_runtime.py stages --checkpoint lunarnav_ml/weights/small.pt \
        --sizes 1024 --calib data/val

Latency is end to end per image (letterbox + network + decoding + NMS at score 0.25), batch 1,
median and p90 over ``--runs`` calls after warm-up. GFLOP/s = conv FLOPs (2 per MAC) / median.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from lunarnav_ml.export.bench import (
    LatencyStats,
    bench_onnx,
    bench_torch,
    conv_flops,
    random_detector,
    stage_times,
    synthetic_frame,
    time_calls,
)
from lunarnav_ml.export.onnx_export import export_onnx, load_parts
from lunarnav_ml.export.quantize import load_calibration_images, quantize_int8


def export_pair(parts: Any, folder: Path, calib: list, size: int) -> tuple[Path, Path]:
    """fp32 and int8 ONNX files of one detector."""
    fp32 = export_onnx(parts, folder / f"{parts.name}.onnx", img_size=size)
    int8 = quantize_int8(fp32, folder / f"{parts.name}_int8.onnx", calib)
    return fp32, int8


DEFAULT_PRESETS = ["nano", "tiny", "small"]


def onnx_apart(path: Path, size: int, threads: int, runs: int, warmup: int,
               network_only: bool = False) -> LatencyStats:
    """``bench_onnx`` in a fresh Python process: this one has run PyTorch (export, eager
    timing), and on a 2-core host its int8 onnxruntime timings read slower than the same files
    timed alone (BENCHMARKS.md, issue 8, session 63)."""
    code = ("import dataclasses, json, sys; from lunarnav_ml.export.bench import bench_onnx; "
            "st = bench_onnx(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), "
            "runs=int(sys.argv[4]), warmup=int(sys.argv[5]), network_only=sys.argv[6] == '1'); "
            "print(json.dumps(dataclasses.asdict(st)))")
    out = subprocess.run([sys.executable, "-c", code, str(path), str(size), str(threads),
                          str(runs), str(warmup), "1" if network_only else "0"],
                         check=False, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"timing {path} at {size} px failed: {out.stderr.strip()[-500:]}")
    return LatencyStats(**json.loads(out.stdout.strip().splitlines()[-1]))


def latency_rows(parts: Any, label: str, sizes: list[int], threads: list[int], runs: int,
                 warmup: int, calib_dir: Path | None, torch_max_size: int,
                 network_only: bool = False) -> list[dict[str, Any]]:
    """One row per (size, threads, runtime) for one model (``DetectorParts``), named ``label``
    in the rows' ``preset`` field; ``network_only``: the network on a prepared input, without
    letterbox and NMS."""
    calib = (load_calibration_images(calib_dir, 16) if calib_dir
             else [synthetic_frame(min(sizes), seed=s) for s in range(16)])
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        fp32, int8 = export_pair(parts, Path(tmp), calib, min(sizes))
        for size in sizes:
            gflop = conv_flops(fp32, size) / 1e9
            for n in threads:
                runners = {"ort-fp32": lambda s=size, n=n: onnx_apart(fp32, s, n, runs, warmup,
                                                                      network_only),
                           "ort-int8": lambda s=size, n=n: onnx_apart(int8, s, n, runs, warmup,
                                                                      network_only)}
                if size <= torch_max_size:
                    runners["torch-fp32"] = lambda s=size, n=n: bench_torch(
                        parts, s, n, runs=max(3, runs // 2), warmup=1,
                        network_only=network_only)
                for runtime, run in runners.items():
                    st = run()
                    row = {"preset": label, "size": size, "threads": n, "runtime": runtime,
                           "median_ms": round(st.median_ms, 1), "p90_ms": round(st.p90_ms, 1),
                           "gflop": round(gflop, 2),
                           "gflops_per_s": round(gflop / (st.median_ms / 1e3), 1)}
                    print(json.dumps(row), flush=True)
                    rows.append(row)
    return rows


def ratios(rows: list[dict[str, Any]]) -> list[str]:
    """int8 vs fp32 and onnxruntime vs eager speed-ups per (preset, size, threads)."""
    by = {(r["preset"], r["size"], r["threads"], r["runtime"]): r["median_ms"] for r in rows}
    out = []
    for (preset, size, n, runtime), ms in by.items():
        if runtime != "ort-fp32":
            continue
        int8 = by.get((preset, size, n, "ort-int8"))
        eager = by.get((preset, size, n, "torch-fp32"))
        line = f"{preset:7s} {size:5d} px {n} thr: int8 {ms / int8:.2f}x faster than fp32"
        if eager:
            line += f"; onnxruntime {eager / ms:.2f}x faster than eager PyTorch"
        out.append(line)
    return out


def markdown(rows: list[dict[str, Any]]) -> str:
    """The rows as a markdown table."""
    lines = ["| preset | size | threads | runtime | median ms | p90 ms | GFLOP | GFLOP/s |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['preset']} | {r['size']} | {r['threads']} | {r['runtime']} | "
              f"{r['median_ms']} | {r['p90_ms']} | {r['gflop']} | {r['gflops_per_s']} |"
              for r in rows]
    return "\n".join(lines)


def run_latency(args: argparse.Namespace) -> None:
    from lunarnav_ml.training.api import load_detector

    def checkpoint(path: Path) -> tuple[Any, str]:
        detector = load_detector(path)
        return load_parts(detector), f"{path.stem} ({detector.preset})"

    presets = args.presets or ([] if args.checkpoints else DEFAULT_PRESETS)
    # each model built when its turn comes, so one at a time is held in memory
    models = [lambda p=p: (random_detector(p, img_size=min(args.sizes)), p) for p in presets]
    models += [lambda path=path: checkpoint(path) for path in args.checkpoints]
    rows = []
    for build in models:
        parts, label = build()
        rows += latency_rows(parts, label, args.sizes, args.threads, args.runs, args.warmup,
                             args.calib, args.torch_max_size, args.network_only)
    print(markdown(rows))
    print("\n".join(ratios(rows)))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


def run_accuracy(args: argparse.Namespace) -> None:
    """Crater AP50 of eager PyTorch, onnxruntime fp32 and int8 on one test set."""
    from lunarnav_ml.eval.coco_metrics import coco_ap
    from lunarnav_ml.eval.predict import predict_coco
    from lunarnav_ml.runtime import OnnxDetector
    from lunarnav_ml.training.api import load_detector

    gt = json.loads(args.test.read_text())
    root = args.test.parent
    detector = load_detector(args.checkpoint)
    calib = load_calibration_images(args.calib, args.n_calib)
    with tempfile.TemporaryDirectory() as tmp:
        parts = load_parts(detector)
        fp32, int8 = export_pair(parts, Path(tmp), calib, detector.img_size)
        for name, predictor in (("torch-fp32", detector), ("ort-fp32", OnnxDetector(fp32, 2)),
                                ("ort-int8", OnnxDetector(int8, 2))):
            t0 = time.perf_counter()
            results = predict_coco(predictor, gt, root, progress=False)
            ap = coco_ap(gt, results)
            crater = ap["per_class"]["crater"]
            print(json.dumps({"runtime": name, "crater_AP50": crater["AP50"],
                              "crater_AP": crater["AP"], "AP50_all": ap["AP50"],
                              "images": len(gt["images"]),
                              "seconds": round(time.perf_counter() - t0, 1)}), flush=True)


def run_input_size(args: argparse.Namespace) -> None:
    """AP50 per class and onnxruntime latency of one checkpoint at several input sides on a
    set of frames (letterboxed to each side; the timed call letterboxes a frame of the set's
    size), fp32 and, with ``--calib``, int8."""
    from lunarnav_ml.eval.coco_metrics import coco_ap
    from lunarnav_ml.eval.predict import predict_coco
    from lunarnav_ml.runtime import OnnxDetector

    gt = json.loads(args.test.read_text())
    frame = max(max(im["width"], im["height"]) for im in gt["images"])
    with tempfile.TemporaryDirectory() as tmp:
        models = {"fp32": export_onnx(args.checkpoint, Path(tmp) / "model.onnx")}
        if args.calib is not None:
            calib = load_calibration_images(args.calib, args.n_calib)
            models["int8"] = quantize_int8(models["fp32"], Path(tmp) / "int8.onnx", calib)
        for (precision, path), size in ((m, s) for m in models.items() for s in args.sizes):
            t0 = time.perf_counter()
            results = predict_coco(OnnxDetector(path, args.ap_threads or args.threads, img_size=size),
                                   gt, args.test.parent, progress=False)
            ap = coco_ap(gt, results)
            lat = bench_onnx(path, size, args.threads, runs=args.runs, frame_size=frame)
            print(json.dumps({"precision": precision, "img_size": size, "frame": frame,
                              "images": len(gt["images"]),
                              **{f"{k}_AP50": v["AP50"] for k, v in ap["per_class"].items()},
                              "crater_AP": ap["per_class"]["crater"]["AP"],
                              "latency_ms_median": round(lat.median_ms, 1),
                              "threads": args.threads,
                              "seconds": round(time.perf_counter() - t0, 1)}), flush=True)


def run_peak(args: argparse.Namespace) -> None:
    """GFLOP/s of an ``n`` x ``n`` fp32 GEMM (2 n^3 FLOPs), onnxruntime MatMul and torch.mm."""
    import numpy as np
    import onnxruntime as ort
    import torch
    from onnx import TensorProto, helper

    n = args.n
    rng = np.random.default_rng(0)
    a, b = (rng.random((n, n), dtype=np.float32) for _ in range(2))
    io = [helper.make_tensor_value_info(k, TensorProto.FLOAT, [n, n]) for k in "ABC"]
    graph = helper.make_graph([helper.make_node("MatMul", ["A", "B"], ["C"])], "gemm", io[:2],
                              io[2:])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    for threads in args.threads:
        opts = ort.SessionOptions()
        opts.intra_op_num_threads, opts.inter_op_num_threads = threads, 1
        sess = ort.InferenceSession(model.SerializeToString(), opts,
                                    providers=["CPUExecutionProvider"])
        torch.set_num_threads(threads)
        for runtime, call in (("onnxruntime", lambda s=sess: s.run(None, {"A": a, "B": b})),
                              ("torch", lambda: torch.mm(ta, tb))):
            gflops = 2 * n**3 / 1e9 / (time_calls(call, runs=args.runs, warmup=1).median_ms / 1e3)
            print(json.dumps({"mode": "peak", "runtime": runtime, "threads": threads, "n": n,
                              "gflops": round(gflops, 1)}), flush=True)


def run_stages(args: argparse.Namespace) -> None:
    """Kernel time per module, fp32 and int8, of a checkpoint or an untrained preset."""
    parts = (load_parts(args.checkpoint) if args.checkpoint is not None
             else random_detector(args.preset, img_size=min(args.sizes)))
    size0 = parts.img_size[0]
    calib = (load_calibration_images(args.calib, args.n_calib) if args.calib
             else [synthetic_frame(size0, seed=s) for s in range(16)])
    with tempfile.TemporaryDirectory() as tmp:
        fp32, int8 = export_pair(parts, Path(tmp), calib, size0)
        for size in args.sizes:
            (f_stage, f_op), (q_stage, q_op) = (stage_times(p, size, args.threads, runs=args.runs)
                                                for p in (fp32, int8))
            print(f"\n{parts.name}, {size} px, {args.threads} thread(s), kernel ms per run "
                  f"(mean of {args.runs})\n")
            print("| module | fp32 ms | int8 ms | int8 speed-up |\n|---|---|---|---|")
            for group in sorted(set(f_stage) | set(q_stage), key=lambda g: -f_stage.get(g, 0)):
                a, b = f_stage.get(group, 0.0), q_stage.get(group, 0.0)
                print(f"| {group} | {a:.1f} | {b:.1f} | {a / b if b else float('inf'):.2f}x |")
            a, b = sum(f_stage.values()), sum(q_stage.values())
            print(f"| **all** | {a:.1f} | {b:.1f} | {a / b:.2f}x |")
            for name, ops in (("fp32", f_op), ("int8", q_op)):
                top = sorted(ops.items(), key=lambda kv: -kv[1])[:8]
                print(f"\n{name} by operator: " + ", ".join(f"{k} {v:.1f}" for k, v in top))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="mode", required=True)
    lat = sub.add_parser("latency", help="latency per preset, size, threads and runtime")
    lat.add_argument("--presets", nargs="+", default=None,
                     help=f"untrained presets (default: {' '.join(DEFAULT_PRESETS)} when no "
                          "--checkpoints)")
    lat.add_argument("--checkpoints", type=Path, nargs="+", default=[],
                     help="trained checkpoints or slim weights")
    lat.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    lat.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    lat.add_argument("--runs", type=int, default=7)
    lat.add_argument("--warmup", type=int, default=2)
    lat.add_argument("--calib", type=Path, default=None,
                     help="calibration images (default: synthetic noise frames)")
    lat.add_argument("--torch-max-size", type=int, default=4096,
                     help="skip eager PyTorch above this input side")
    lat.add_argument("--network-only", action="store_true",
                     help="time the network alone (no letterbox, no NMS); random weights "
                          "still read int8 lower than trained files (BENCHMARKS.md, session 64)")
    lat.add_argument("--json", type=Path, default=None, help="also write the rows here")
    lat.set_defaults(func=run_latency)
    acc = sub.add_parser("accuracy", help="crater AP50: eager vs onnxruntime fp32 vs int8")
    acc.add_argument("--checkpoint", type=Path, required=True)
    acc.add_argument("--test", type=Path, required=True, help="test annotations.json")
    acc.add_argument("--calib", type=Path, required=True, help="calibration dataset folder")
    acc.add_argument("--n-calib", type=int, default=32)
    acc.set_defaults(func=run_accuracy)
    ins = sub.add_parser("input-size", help="AP50 and latency of one model at several input sides")
    ins.add_argument("--checkpoint", type=Path, required=True)
    ins.add_argument("--test", type=Path, required=True, help="annotations.json of the frames")
    ins.add_argument("--sizes", type=int, nargs="+", default=[384, 512, 768, 1024])
    ins.add_argument("--threads", type=int, default=1, help="threads of the timed runs")
    ins.add_argument("--ap-threads", type=int, default=None,
                     help="threads while detecting on the frames for AP (default --threads)")
    ins.add_argument("--runs", type=int, default=5)
    ins.add_argument("--calib", type=Path, default=None,
                     help="calibration dataset folder: also quantize and measure int8")
    ins.add_argument("--n-calib", type=int, default=32)
    ins.set_defaults(func=run_input_size)
    peak = sub.add_parser("peak", help="fp32 GEMM GFLOP/s: the ceiling for the model's rate")
    peak.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    peak.add_argument("--n", type=int, default=2048, help="matrix side")
    peak.add_argument("--runs", type=int, default=7)
    peak.set_defaults(func=run_peak)
    stg = sub.add_parser("stages", help="kernel time per module, fp32 against int8 (profiler)")
    src = stg.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", type=Path, help="a trained checkpoint")
    src.add_argument("--preset", help="an untrained preset (the arithmetic is the same)")
    stg.add_argument("--sizes", type=int, nargs="+", default=[1024])
    stg.add_argument("--threads", type=int, default=1)
    stg.add_argument("--runs", type=int, default=5)
    stg.add_argument("--calib", type=Path, default=None,
                     help="calibration dataset folder (default: synthetic noise frames)")
    stg.add_argument("--n-calib", type=int, default=16)
    stg.set_defaults(func=run_stages)
    args = parser.parse_args()
    args.func(args)


if __name__ == "__main__":
    main()
