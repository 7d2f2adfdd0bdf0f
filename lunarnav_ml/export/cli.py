"""``lunarnav export`` (checkpoint -> ONNX, optionally int8) and ``lunarnav bench`` (latency)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from lunarnav_ml.errors import REPORTED_ERRORS, ConfigError

# A camera frame side bench will synthesize (a 16k x 16k RGB frame is 768 MB).
MAX_FRAME_SIZE = 16384


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
    """Export, then quantize when asked; prints the written paths.

    The settings, the output paths and the calibration images are checked before anything is
    exported; with ``--int8-out`` the fp32 file appears only once the int8 file is written.
    """
    from lunarnav_ml.export.onnx_export import export_onnx

    if args.int8_out is not None and args.calib is None:
        raise ConfigError("--int8-out needs --calib (a folder of synthetic calibration images)")
    if args.n_calib < 1:
        raise ConfigError(f"--n-calib must be positive, got {args.n_calib}")
    from lunarnav_ml.utils.atomic import atomic_path, check_destination

    check_destination(args.out)  # a folder or a file in the way, found before the export
    kw = {"opset": args.opset, "nms": args.nms, "dynamic": not args.static,
          "img_size": args.img_size}
    if args.int8_out is None:
        print(f"wrote {export_onnx(args.checkpoint, args.out, **kw)}")
        return 0
    from lunarnav_ml.export.quantize import load_calibration_images, quantize_int8

    check_destination(args.int8_out)
    if args.int8_out.resolve() == args.out.resolve():
        raise ConfigError(f"--int8-out: {args.int8_out} is also --out; give another file")
    images = load_calibration_images(args.calib, args.n_calib)
    with atomic_path(args.out) as fp32:  # renamed onto --out once the int8 file is written
        export_onnx(args.checkpoint, fp32, **kw)
        q = quantize_int8(fp32, args.int8_out, images, method=args.calib_method)
    print(f"wrote {args.out}")
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
    """Print one line per (model, size, threads).

    Every setting and model is checked before the first timing: ``--sizes`` must be positive
    multiples of each model's largest stride (and the input of a fixed-size export).
    """
    from lunarnav_ml.export.bench import bench_onnx, conv_flops
    from lunarnav_ml.runtime.session import open_session

    if not args.onnx and args.checkpoint is None:
        raise ConfigError("bench: give --onnx FILE(S) and/or --checkpoint")
    for option, value, low in (("--runs", args.runs, 1), ("--warmup", args.warmup, 0),
                               ("--threads", min(args.threads), 1),
                               ("--sizes", min(args.sizes), 1)):
        if value < low:
            raise ConfigError(f"bench: {option} must be >= {low}, got {value}")
    if args.frame_size is not None:
        if not 1 <= args.frame_size <= MAX_FRAME_SIZE:
            raise ConfigError(f"bench: --frame-size must be in 1..{MAX_FRAME_SIZE} px, "
                              f"got {args.frame_size}")
        if not args.onnx:
            raise ConfigError("bench: --frame-size applies to --onnx models only")
    kw = {"runs": args.runs, "warmup": args.warmup, "conf_thres": args.conf,
          "network_only": args.network_only}
    for path in args.onnx:  # every file checked before the first timing line
        meta = open_session(path)[1]
        _check_sizes(args.sizes, meta.max_stride, path)
        if not meta.dynamic_hw and any((s, s) != meta.input_size for s in args.sizes):
            raise ConfigError(f"bench: --sizes {_join(args.sizes)}: {path} was exported with a "
                              f"fixed input {meta.input_size}")
    parts = None
    if args.checkpoint is not None:
        from lunarnav_ml.export.onnx_export import load_parts

        parts = load_parts(args.checkpoint)
        _check_sizes(args.sizes, max(parts.strides), args.checkpoint)
    for path in args.onnx:
        for size in args.sizes:
            gflop = conv_flops(path, size) / 1e9
            for threads in args.threads:
                s = bench_onnx(path, size, threads, frame_size=args.frame_size, **kw)
                print(f"{path.name:28s} {size:5d} px {threads} thr  onnxruntime  {s.row()}  "
                      f"{gflop / (s.median_ms / 1e3):6.1f} GFLOP/s ({gflop:.1f} GFLOP)",
                      flush=True)
    if parts is not None:
        _bench_checkpoint(args, parts, kw)
    return 0


def _join(sizes: list[int]) -> str:
    return " ".join(map(str, sizes))


def _check_sizes(sizes: list[int], stride: int, model: Path) -> None:
    bad = [s for s in sizes if s % stride]
    if bad:
        raise ConfigError(f"bench: --sizes {_join(bad)}: input sides must be multiples of "
                          f"{stride} (the largest stride of {model})")


def _bench_checkpoint(args: argparse.Namespace, parts: Any, kw: dict) -> None:
    from lunarnav_ml.export.bench import bench_torch

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
