"""``lunarnav train`` (the LightningCLI of train.py), ``lunarnav detect``,
``lunarnav average``, ``lunarnav distill-stem``, ``lunarnav train-refiner``,
``lunarnav train-box-refiner`` and ``lunarnav train-box-rescorer``."""

from __future__ import annotations

import argparse
from pathlib import Path

from lunarnav_ml.errors import ConfigError
from lunarnav_ml.eval.cli import add_box_refiner_arguments, add_box_rescorer_arguments
from lunarnav_ml.eval.smallread import DEFAULT_BELOW_PX, add_small_read_arguments, small_read_config
from lunarnav_ml.eval.tta import add_tta_arguments

DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "small.pt"


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``train``, ``detect``, ``average`` and ``distill-stem`` subcommands."""
    p = subparsers.add_parser(
        "train", add_help=False, help="train the detector (LightningCLI; try 'train fit --help')",
        description="Forwards its arguments to the Lightning CLI of train.py, e.g. "
                    "'lunarnav train fit --config configs/nano_cpu.yaml'.")
    p.add_argument("cli_args", nargs=argparse.REMAINDER, help="LightningCLI arguments")
    p.set_defaults(func=run_train, forwards_args=True)

    p = subparsers.add_parser(
        "detect", help="detect craters, rocks and artifacts in images and folders",
        description="Writes results.json (COCO results), images.json (image ids, files and "
                    "overlays), overlay images and a gallery.png contact sheet under --out.")
    p.add_argument("source", type=Path, nargs="+",
                   help="image files and/or folders of images (each folder's, not recursive)")
    p.add_argument("--weights", type=Path, default=None,
                   help="checkpoint (.ckpt), slim weights (.pt) or an exported ONNX model (.onnx, "
                        f"run by the torch-free onboard runtime); default {DEFAULT_WEIGHTS}")
    p.add_argument("--threads", type=int, default=2, help="onnxruntime threads (.onnx weights)")
    p.add_argument("--out", type=Path, default=Path("outputs/detect"),
                   help="output folder, replaced whole (an earlier detect output or a new folder)")
    p.add_argument("--conf", type=float, default=0.001, help="score threshold of results.json")
    p.add_argument("--iou", type=float, default=0.6, help="NMS IoU threshold")
    p.add_argument("--overlay-conf", type=float, default=0.25, help="score threshold drawn")
    p.add_argument("--batch", type=int, default=8, help="images per forward pass")
    p.add_argument("--img-size", type=int, default=None,
                   help="network input side, px (a multiple of the largest stride, 32); "
                        "default the size the model was trained at. Larger frames than the "
                        "training renders often detect better at a larger input (BENCHMARKS.md)")
    p.add_argument("--gallery", type=int, default=12,
                   help="overlays in gallery.png, spread over the images (0: no gallery)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_tta_arguments(p)
    add_small_read_arguments(p, horizon=True)
    p.add_argument("--camera", type=Path, default=None,
                   help="(--small-read-horizon) the frames' JSON camera record, as lunarnav "
                        "localize reads it; its pitch_deg, fy and cy place the band over the "
                        "horizon at each frame's height")
    add_box_refiner_arguments(p, when="(after --tta or --small-read)",
                              off="write the detector's boxes as they are")
    add_box_rescorer_arguments(p)
    p.set_defaults(func=run_detect)

    p = subparsers.add_parser(
        "average", help="average the weights of detectors of one lineage (a model soup)",
        description="Averages the weights and BatchNorm statistics of several checkpoints or "
                    "slim weight files of one architecture (a run and the model it started "
                    "from, or one run's checkpoints) into one slim weights file.")
    p.add_argument("weights", type=Path, nargs="+",
                   help="checkpoints (.ckpt) or slim weights (.pt), two or more")
    p.add_argument("--out", type=Path, required=True, help="slim weights file to write (.pt)")
    p.add_argument("--half", action="store_true",
                   help="store the weights in float16, as the shipped files are")
    p.set_defaults(func=run_average)

    p = subparsers.add_parser(
        "distill-stem", help="give a trained detector the stride-2 stem of small-relu-s2",
        description="Trains a small-relu-s2 detector from a trained small-relu one (the "
                    "teacher): every weight but the stem's is copied, and the new stem is "
                    "trained on unlabelled images to reproduce first the teacher's stage-0 "
                    "features, then its outputs; an optional third phase (--whole-steps) trains "
                    "every weight on the teacher's detections, from the new model or from "
                    "--student. Its int8 export runs 2.5-2.8x faster than "
                    "fp32 on a Xeon with AMX, small-relu's 1.8-2.0x (BENCHMARKS.md, issue 8).")
    p.add_argument("--teacher", type=Path, default=DEFAULT_WEIGHTS,
                   help="trained small-relu checkpoint or slim weights (default: the shipped)")
    p.add_argument("--images", type=Path, nargs="+", required=True,
                   help="datasets (annotations.json or its folder) or image folders; no "
                        "labels are read. Use training splits, not a set you will test on")
    p.add_argument("--out", type=Path, required=True, help="slim weights file to write (.pt)")
    p.add_argument("--max-images", type=int, default=2000,
                   help="images drawn at random from --images (all held in memory)")
    p.add_argument("--student", type=Path, default=None,
                   help="start from this small-relu-s2 checkpoint or slim weights (e.g. one "
                        "fine-tuned with labels) instead of the teacher with a fresh stem")
    p.add_argument("--feature-steps", type=int, default=1500)
    p.add_argument("--output-steps", type=int, default=400)
    p.add_argument("--whole-steps", type=int, default=0,
                   help="steps of a third phase that trains every weight on the teacher's "
                        "detections (default 0: the stem alone)")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--lr", type=float, default=2e-3, help="peak rate of the stem phases")
    p.add_argument("--whole-lr", type=float, default=1e-4, help="peak rate of the third phase")
    p.add_argument("--bf16", action="store_true",
                   help="bfloat16 autocast (faster on CPUs with AVX512-BF16 or AMX)")
    p.add_argument("--device", default="auto",
                   help="where the models run: auto (default: CUDA where there is one), cpu, "
                        "cuda or cuda:N")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: all)")
    p.add_argument("--half", action="store_true", help="store the weights in float16")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_distill_stem)

    p = subparsers.add_parser(
        "train-refiner", help="train the SGBM disparity refiner of the crater lifter",
        description="Cuts crops around crater rims from rendered stereo sets (their exact "
                    "disparity is the target), trains the small net that corrects SGBM's "
                    "disparity there and exports it as ONNX, for 'lunarnav eval --task geometry "
                    "--refiner' and 'lunarnav localize --refiner' (docs/geometry.md).")
    p.add_argument("datasets", type=Path, nargs="+",
                   help="rendered stereo sets (lunarnav synth --protocol paper-stereo): folders "
                        "with annotations.json (or one annotations*.json shard). Use "
                        "development renders, not a set you will test on")
    p.add_argument("--out", type=Path, required=True, help="ONNX file to write")
    p.add_argument("--steps", type=int, default=None, help="optimizer steps (default 4800)")
    p.add_argument("--batch", type=int, default=None, help="crops per step (default 16)")
    p.add_argument("--lr", type=float, default=None, help="peak Adam rate (default 1e-3)")
    p.add_argument("--channels", type=int, default=None, help="width of the net (default 32)")
    p.add_argument("--seed", type=int, default=None,
                   help="seed of the crops, the split and the weights (default 65)")
    p.add_argument("--max-disparity", type=float, default=None, dest="max_disparity_px",
                   help="train on the crops whose median SGBM disparity is below this (px), "
                        "and gate the refiner there (refine only boxes that read below it)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: all)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_train_refiner)

    p = subparsers.add_parser(
        "train-box-refiner", help="train the crater-box refiner of detection and the 3D lift",
        description="Cuts full-resolution crops around crater labels (jittered) and around a "
                    "detector's crater boxes, trains the small net that moves a box's edges "
                    "onto the labelled rim's box (with --quality, also estimates the box's IoU "
                    "with a crater) and exports it as ONNX, for the --box-refiner of 'lunarnav "
                    "detect', 'lunarnav eval' and 'lunarnav localize' (docs/geometry.md).")
    p.add_argument("datasets", type=Path, nargs="+",
                   help="COCO sets with crater labels: folders with annotations.json (or one "
                        "annotations*.json shard), or the files. Use development sets, not a "
                        "set you will test on")
    p.add_argument("--detections", type=Path, nargs="+", default=None,
                   help="a detector's COCO results on each set, in the same order (the "
                        "detections.json of 'lunarnav eval --task detection --no-box-refiner "
                        "--out D': the network's boxes); 'none' for a set without; default: "
                        "labels only")
    p.add_argument("--out", type=Path, required=True, help="ONNX file to write")
    p.add_argument("--epochs", type=int, default=None, help="passes over the crops (default 3)")
    p.add_argument("--batch", type=int, default=None, help="crops per step (default 256)")
    p.add_argument("--label-jitters", type=int, default=None,
                   help="jittered crops per label (default 2)")
    p.add_argument("--repeats", type=int, nargs="+", default=None,
                   help="each set's weight in the mix, in the same order (default 1 each): "
                        "that many times the crops, e.g. 8 for a few hundred real frames "
                        "beside thousands of renders")
    p.add_argument("--seed", type=int, default=None,
                   help="seed of the jitters, the split and the weights (default 0)")
    p.add_argument("--quality", type=float, default=None,
                   help="weight of a fifth output, the input box's IoU with its label, "
                        "learnt also from the detections off every label; detection then "
                        "scores each crater sqrt(score x quality) (default 0: no such output)")
    p.add_argument("--edges-from", type=Path, default=None,
                   help="with --quality: write this box refiner's edges beside the trained "
                        "quality output (one file; the lift then moves boxes as with it)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: all)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_train_box_refiner)

    p = subparsers.add_parser(
        "train-box-rescorer", help="fit the second-stage score of the refined crater boxes",
        description="Runs a detector's crater boxes through the box refiner as detection does "
                    "and fits a gradient-boosted tree ensemble on each box's score, quality, "
                    "size, place and neighbours to whether it lies on a countable crater; "
                    "exports it as ONNX, for the --box-rescorer of 'lunarnav detect' and "
                    "'lunarnav eval' (docs/geometry.md).")
    p.add_argument("datasets", type=Path, nargs="+",
                   help="COCO sets with crater labels: folders with annotations.json (or one "
                        "annotations*.json shard), or the files. Not a set you read a figure "
                        "or a threshold on")
    p.add_argument("--detections", type=Path, nargs="+", required=True,
                   help="the detector's COCO results on each set, in the same order (the "
                        "detections.json of 'lunarnav eval --task detection --no-box-refiner "
                        "--out D')")
    p.add_argument("--detector", type=Path, required=True,
                   help="the model file that wrote them (recorded with the box refiner: the "
                        "shipped rescorer refuses other models)")
    p.add_argument("--box-refiner", type=Path, default=None,
                   help="box refiner with a quality output (default: the shipped one)")
    p.add_argument("--small-read", type=int, default=None, metavar="SIDE",
                   help="the detections were made with this --small-read (recorded: the "
                        "shipped file for that read is refused for other reads)")
    p.add_argument("--small-read-below", type=float, default=DEFAULT_BELOW_PX, metavar="PX",
                   help="(--small-read) its --small-read-below; default %(default)s")
    p.add_argument("--out", type=Path, required=True, help="ONNX file to write")
    p.add_argument("--repeats", type=int, nargs="+", default=None,
                   help="each set's weight in the fit, in the same order (default 1 each), "
                        "e.g. 8 for a few hundred real frames beside thousands of renders")
    p.add_argument("--trees", type=int, default=None, help="boosting rounds (default 300)")
    p.add_argument("--seed", type=int, default=None, help="row subsampling seed (default 0)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_train_box_rescorer)


def run_train_box_refiner(args: argparse.Namespace) -> int:
    """Crops, training and ONNX export of the box refiner (``--out`` written atomically)."""
    from lunarnav_ml.training.box_refiner import BoxRefinerConfig, run
    from lunarnav_ml.utils.atomic import check_destination

    given = {k: getattr(args, k) for k in ("epochs", "batch", "label_jitters", "seed", "quality")}
    config = BoxRefinerConfig(**{k: v for k, v in given.items() if v is not None})
    detections = ([None if str(d).lower() == "none" else d for d in args.detections]
                  if args.detections is not None else [None] * len(args.datasets))
    check_destination(args.out)  # build_crops checks one results file per set
    set_torch_threads(args.threads)
    report = run(args.datasets, detections, args.out, config, progress=not args.quiet,
                 repeats=args.repeats, edges_from=args.edges_from)
    print(f"lunarnav train-box-refiner: {report.n_train} training crops, {report.steps} steps "
          f"in {report.seconds:.0f} s; held-out mean |edge error| {report.refined_l1:.4f} of "
          f"the crop (the input boxes' side edges {report.input_l1:.4f}; {report.n_val} crops)"
          + ("" if report.quality_corr is None
             else f"; quality vs IoU r = {report.quality_corr:.3f}") + f" -> {args.out}")
    return 0


def run_train_box_rescorer(args: argparse.Namespace) -> int:
    """Features, fit and ONNX export of the box rescorer (``--out`` written atomically)."""
    from lunarnav_ml.training.box_rescorer import BoxRescorerConfig, run
    from lunarnav_ml.utils.atomic import check_destination

    given = {k: getattr(args, k) for k in ("trees", "seed")}
    config = BoxRescorerConfig(**{k: v for k, v in given.items() if v is not None})
    read = small_read_config(args)  # checked before the features are computed
    check_destination(args.out)
    report = run(args.datasets, args.detections, args.out, args.detector, args.box_refiner,
                 config, progress=not args.quiet, repeats=args.repeats,
                 small_read=None if read is None else read.record())
    print(f"lunarnav train-box-rescorer: {report.n_rows} crater boxes ({report.n_positive} on "
          f"a countable crater) in {report.seconds:.0f} s -> {args.out}")
    return 0


def set_torch_threads(threads: int | None) -> None:
    """``torch.set_num_threads(threads)`` (None: torch's default), checked."""
    import torch

    if threads is not None:
        if threads < 1:
            raise ConfigError(f"--threads must be >= 1, got {threads}")
        torch.set_num_threads(threads)


def run_train_refiner(args: argparse.Namespace) -> int:
    """Crops, training and ONNX export of the disparity refiner (``--out`` written atomically)."""
    from lunarnav_ml.training.refiner import RefinerConfig, run
    from lunarnav_ml.utils.atomic import check_destination

    given = {k: getattr(args, k)
             for k in ("channels", "steps", "batch", "lr", "seed", "max_disparity_px")}
    config = RefinerConfig(**{k: v for k, v in given.items() if v is not None})
    check_destination(args.out)
    set_torch_threads(args.threads)
    report = run(args.datasets, args.out, config, progress=not args.quiet)
    print(f"lunarnav train-refiner: {report.n_train} training crops, {report.steps} steps in "
          f"{report.seconds:.0f} s; held-out L1 {report.refined_l1_px:.4f} px (SGBM "
          f"{report.sgbm_l1_px:.4f} px, {report.n_val} crops) -> {args.out}")
    return 0


def run_train(args: argparse.Namespace) -> int:
    """Run the LightningCLI with the forwarded arguments."""
    from lunarnav_ml.training.lightning_cli import run_cli

    run_cli(args.cli_args or ["--help"], prog="lunarnav train")
    return 0


def run_detect(args: argparse.Namespace) -> int:
    """Detect on the source images and write results and overlays."""
    from lunarnav_ml.eval.cli import predictor_from_args
    from lunarnav_ml.eval.smallread import small_reader
    from lunarnav_ml.runtime.cli import read_camera
    from lunarnav_ml.training.detect import detect_files, list_images

    for name in ("conf", "iou", "overlay_conf"):
        if not 0.0 <= getattr(args, name) <= 1.0:
            raise ConfigError(f"--{name.replace('_', '-')} must lie in [0, 1], "
                              f"got {getattr(args, name)}")
    if args.batch < 1:
        raise ConfigError(f"--batch must be >= 1, got {args.batch}")
    if args.threads < 1:
        raise ConfigError(f"--threads must be >= 1, got {args.threads}")
    if args.gallery < 0:
        raise ConfigError(f"--gallery must be >= 0, got {args.gallery}")
    weights = args.weights or DEFAULT_WEIGHTS
    if args.weights is None and not weights.is_file():
        raise ConfigError(f"no --weights given and no shipped weights at {weights}")
    read = small_read_config(args)
    if (read is not None and read.horizon is not None) != (args.camera is not None):
        raise ConfigError("--small-read-horizon needs --camera FILE, the frames' camera record"
                          if args.camera is None else
                          "--camera is read for --small-read-horizon only: give both")
    camera = None if args.camera is None else read_camera(args.camera)
    files = list_images(args.source)
    detector = predictor_from_args(args, weights)
    if camera is not None:
        small_reader(detector).camera = camera
    out = detect_files(detector, files, args.out, conf_thres=args.conf, iou_thres=args.iou,
                       overlay_thres=args.overlay_conf, batch=args.batch,
                       progress=not args.quiet, gallery=args.gallery)
    print(f"lunarnav detect: {len(out['results'])} detections on {len(files)} images -> "
          f"{args.out / 'results.json'}")
    return 0


def run_average(args: argparse.Namespace) -> int:
    """Average the weight files into ``--out`` (written under a temporary name, then renamed)."""
    from lunarnav_ml.training.api import average_detectors
    from lunarnav_ml.utils.atomic import check_destination

    check_destination(args.out)
    average_detectors(args.weights).save(args.out, half=args.half)
    print(f"lunarnav average: {len(args.weights)} detectors -> {args.out}")
    return 0


def run_distill_stem(args: argparse.Namespace) -> int:
    """Distil the stride-2 stem into ``--out`` (written under a temporary name, then renamed)."""
    import torch

    from lunarnav_ml.training.api import load_detector
    from lunarnav_ml.training.distill import distill_stem, load_inputs, torch_device
    from lunarnav_ml.utils.atomic import check_destination

    for name in ("max_images", "batch"):
        if getattr(args, name) < 1:
            raise ConfigError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    check_destination(args.out)
    torch_device(args.device)  # before any work
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    teacher = load_detector(args.teacher)
    start = None if args.student is None else load_detector(args.student)
    images = load_inputs(args.images, teacher.img_size, args.max_images, args.seed)
    student, report = distill_stem(teacher, images, feature_steps=args.feature_steps,
                                   output_steps=args.output_steps, batch=args.batch, lr=args.lr,
                                   held_out=min(32, max(1, len(images) // 5)), seed=args.seed,
                                   student=start, whole_steps=args.whole_steps,
                                   whole_lr=args.whole_lr, bf16=args.bf16,
                                   device=args.device, progress=not args.quiet)
    student.save(args.out, half=args.half)
    steps = " + ".join(str(n) for n in report.steps)
    print(f"lunarnav distill-stem: {len(images)} images, {steps} steps; held-out relative "
          f"error: stem features {report.feature_rel_err:.4f}, "
          f"outputs {report.output_rel_err:.4f}; detection loss {report.detection_loss:.4f} "
          f"(a fifth of the images, at most 32) -> {args.out}")
    return 0
