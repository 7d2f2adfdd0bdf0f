"""``lunarnav export`` (checkpoint -> ONNX, optionally int8) and ``lunarnav bench`` (latency)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lunarnav_ml.errors import REPORTED_ERRORS, ConfigError


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``lunarnav export`` and ``lunarnav bench``."""
    _add_export(subparsers)
    _add_bench(subparsers)


def _add_export(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "export", help="export a checkpoint to ONNX (fp32, optionally int8)",
        description="Export a trained detector to ONNX with decoding in the graph and the "
                    "class names, input size, normalization, strides and anchors as metadata; "
                    "optionally quantize it to int8 on calibration images.")
    p.add_argument("--checkpoint", type=Path, required=True, help="training checkpoint (.ckpt)")
    p.add_argument("--out", type=Path, required=True, help="fp32 ONNX file to write")
    p.add_argument("--opset", type=int, default=17, help="ONNX opset (default 17)")
    p.add_argument("--nms", action="store_true", help="end the graph in ONNX NonMaxSuppression")
    p.add_argument("--static", action="store_true",
                   help="fixed (1, 3, H, W) input instead of dynamic batch/height/width")
    p.add_argument("--img-size", type=int, default=None,
                   help="default input side, px (default: the training size)")
    p.add_argument("--int8-out", type=Path, default=None,
                   help="also write a statically quantized int8 model here (needs --calib)")
    p.add_argument("--calib", type=Path, default=None,
                   help="calibration images: a `lunarnav synth` dataset folder or image folder")
    p.add_argument("--n-calib", type=int, default=32, help="calibration images used")
    p.add_argument("--calib-method", default="minmax", choices=("minmax", "percentile", "entropy"))
    p.set_defaults(func=run_export)


def run_export(args: argparse.Namespace) -> int:
    """Export, then quantize when asked; prints the written paths."""
    from lunarnav_ml.export.onnx_export import export_onnx

    if args.int8_out is not None and args.calib is None:
        raise ConfigError("--int8-out needs --calib (a folder of synthetic calibration images)")
    if args.n_calib < 1:
        raise ConfigError(f"--n-calib must be positive, got {args.n_calib}")
    out = export_onnx(args.checkpoint, args.out, opset=args.opset, nms=args.nms,
                      dynamic=not args.static, img_size=args.img_size)
    print(f"wrote {out}")
    if args.int8_out is not None:
        from lunarnav_ml.export.quantize import load_calibration_images, quantize_int8

        images = load_calibration_images(args.calib, args.n_calib)
        q = quantize_int8(out, args.int8_out, images, method=args.calib_method)
        print(f"wrote {q} (int8, {len(images)} calibration images)")
    return 0


def _add_bench(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "bench", help="per-image latency (median, p90) of ONNX models and eager PyTorch",
        description="Time exported models on onnxruntime (and a checkpoint in eager PyTorch) "
                    "one image at a time; prints median and p90 latency per image in ms.")
    p.add_argument("--onnx", type=Path, nargs="*", default=[], help="lunarnav ONNX file(s)")
    p.add_argument("--checkpoint", type=Path, default=None,
                   help="also time this checkpoint in eager PyTorch")
    p.add_argument("--sizes", type=int, nargs="+", default=[512, 1024], help="input sides, px")
    p.add_argument("--threads", type=int, nargs="+", default=[1], help="thread counts")
    p.add_argument("--runs", type=int, default=10, help="timed calls per setting")
    p.add_argument("--warmup", type=int, default=2, help="untimed calls first")
    p.add_argument("--conf", type=float, default=0.25, help="score threshold of the NMS")
    p.add_argument("--network-only", action="store_true", help="time the graph alone")
    p.add_argument("--frame-size", type=int, default=None,
                   help="ONNX: time a camera frame of this side letterboxed to each input side "
                        "(e.g. 1024 px frames read at 512); default: a frame of the input side")
    p.set_defaults(func=run_bench)


def run_bench(args: argparse.Namespace) -> int:
    """Print one line per (model, size, threads)."""
    from lunarnav_ml.export.bench import bench_onnx, conv_flops
    from lunarnav_ml.runtime.session import open_session

    if not args.onnx and args.checkpoint is None:
        raise ConfigError("bench: give --onnx FILE(S) and/or --checkpoint")
    if args.runs < 1 or args.warmup < 0 or min(args.threads) < 1 or min(args.sizes) < 1:
        raise ConfigError("bench: --runs, --threads and --sizes must be positive")
    if args.frame_size is not None and args.frame_size < 1:
        raise ConfigError(f"bench: --frame-size must be positive, got {args.frame_size}")
    kw = {"runs": args.runs, "warmup": args.warmup, "conf_thres": args.conf,
          "network_only": args.network_only}
    for path in args.onnx:  # every file checked before the first timing line
        open_session(path)
    for path in args.onnx:
        for size in args.sizes:
            gflop = conv_flops(path, size) / 1e9
            for threads in args.threads:
                s = bench_onnx(path, size, threads, frame_size=args.frame_size, **kw)
                print(f"{path.name:28s} {size:5d} px {threads} thr  onnxruntime  {s.row()}  "
                      f"{gflop / (s.median_ms / 1e3):6.1f} GFLOP/s ({gflop:.1f} GFLOP)",
                      flush=True)
    if args.checkpoint is not None:
        _bench_checkpoint(args, kw)
    return 0


def _bench_checkpoint(args: argparse.Namespace, kw: dict) -> None:
    from lunarnav_ml.export.bench import bench_torch
    from lunarnav_ml.export.onnx_export import load_parts

    parts = load_parts(args.checkpoint)
    for size in args.sizes:
        for threads in args.threads:
            s = bench_torch(parts, size, threads, **kw)
            print(f"{args.checkpoint.name:28s} {size:5d} px {threads} thr  torch-eager  "
                  f"{s.row()}", flush=True)


def main(argv: list[str] | None = None) -> int:
    """``lunarnav`` restricted to ``export`` and ``bench`` (the top-level ``export/`` scripts).

    Errors are reported as in :func:`lunarnav_ml.cli.main`: one line on stderr, exit code 2.
    """
    from lunarnav_ml.cli import build_parser

    args = build_parser((__name__,)).parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except REPORTED_ERRORS as err:
        print(f"lunarnav {args.command}: error: {err}", file=sys.stderr)
        return 2
