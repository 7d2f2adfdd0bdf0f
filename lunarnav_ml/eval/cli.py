"""``lunarnav eval``: evaluation reports.

Tasks:
- ``detection``: COCO AP per class, crater Pd and false alarms per image at an operating
  threshold picked on a validation split, Pd vs range / diameter / sun angles, plots, overlays.
- ``geometry``: 3D crater center and diameter errors (3-sigma tables) on a stereo set.
- ``baselines-lidar`` / ``baselines-stereo``: the paper's geometric detectors on the
  paper-lidar / paper-stereo protocol sets, beside the paper's tables.
- ``transfer``: real labelled frames (``lunarnav import-real`` output): recall at 1/3/5/10
  detections per image and AP50 per class, per camera, and an overlay gallery.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.eval.predict import read_coco_results
from lunarnav_ml.eval.smallread import (
    SmallBoxReadConfig,
    SmallBoxReadPredictor,
    add_small_read_arguments,
    small_read_config,
)
from lunarnav_ml.eval.tta import TTAConfig, TTAPredictor, add_tta_arguments, tta_config

SHIPPED = "shipped"  # --refiner without a file


def add_refiner_arguments(p: argparse.ArgumentParser, prefix: str = "") -> None:
    """``--refiner [ONNX]`` (default: the shipped refiner) and ``--no-refiner``."""
    _add_tool_arguments(p, "refiner",
                        f"{prefix}correct SGBM's disparity around each crater box with this "
                        "refiner from `lunarnav train-refiner` before the lifts (default, or no "
                        "file: the shipped one; docs/geometry.md)",
                        f"{prefix}lift from SGBM's disparity as it is")


def add_box_refiner_arguments(p: argparse.ArgumentParser, prefix: str = "",
                              when: str = "before the lift",
                              off: str = "lift from the detector's boxes as they are") -> None:
    """``--box-refiner [ONNX]`` (default: the shipped box refiner) and ``--no-box-refiner``."""
    _add_tool_arguments(p, "box-refiner",
                        f"{prefix}move each detected crater box's edges onto the rim with this "
                        f"box refiner from `lunarnav train-box-refiner` {when} (default, "
                        "or no file: the shipped one; docs/geometry.md)",
                        f"{prefix}{off}")


def add_box_rescorer_arguments(p: argparse.ArgumentParser) -> None:
    """``--box-rescorer [ONNX]`` (off by default; no file: the shipped rescorer, for the model
    and box refiner it was fitted with) and ``--no-box-rescorer``."""
    p.add_argument("--box-rescorer", nargs="?", const=SHIPPED, default=None, metavar="ONNX",
                   help="score each refined crater box by this rescorer from `lunarnav "
                        "train-box-rescorer` (no file: the shipped one, fitted on the shipped "
                        "small.pt with the shipped box refiner and refused for other models; "
                        "with --small-read 640 the shipped one fitted on that read's boxes "
                        "of small.pt or of small_grid.pt; "
                        "default off; docs/geometry.md)")
    p.add_argument("--no-box-rescorer", dest="box_rescorer", action="store_const", const=None,
                   help="keep sqrt(score x quality) as the crater score (the default)")


def load_box_rescorer(args: argparse.Namespace, model: str | Path | None, refiner: Any
                      ) -> Any:
    """The :class:`~lunarnav_ml.geometry.boxrescore.BoxRescorer` of ``--box-rescorer`` for the
    model file ``model`` and the box refiner ``refiner`` (None when switched off).

    With ``--small-read`` the shipped file is one fitted on the boxes of that read: the boxes
    the second read adds change what a box's neighbours say. ``box_rescorer_small_read.onnx``
    is for ``small.pt``, ``box_rescorer_grid.onnx`` for ``small_grid.pt``; the one fitted on
    ``model`` is taken.

    Raises:
        InputError: a rescorer without a box refiner (``--no-box-refiner``); the shipped file
            asked for with a model or box refiner other than those it was fitted with, or with
            a second read other than the one it was fitted on. (A refiner without a quality
            output is refused by the :class:`~lunarnav_ml.geometry.boxrefine.BoxRefinedDetector`
            it goes into.)
    """
    from lunarnav_ml.geometry.boxrescore import SMALL_READ_BOX_RESCORERS, BoxRescorer

    choice = getattr(args, "box_rescorer", None)
    if choice is None:
        return None
    if refiner is None:
        raise InputError("--box-rescorer reads the box refiner's quality output: drop "
                         "--no-box-refiner (the shipped box refiner has one)")
    small_read = small_read_config(args)
    read = None if small_read is None else small_read.record()
    if choice != SHIPPED:
        return _open_tool(BoxRescorer, choice, args.threads)
    # the shipped file fitted on this model's boxes of this read (`small.pt` or `small_grid.pt`)
    files = [SHIPPED] if small_read is None else [str(f) for f in SMALL_READ_BOX_RESCORERS]
    first = None
    for file in files:  # opened one at a time: the first that fits is taken
        rescorer = _open_tool(BoxRescorer, file, args.threads)
        if model is not None and rescorer.fitted_for(model, refiner.path, read):
            return rescorer
        first = first or rescorer
    fitted = first.fitted_with  # named after the first: small.pt's for that read
    raise InputError(f"{first.path}: fitted on the scores of "
                     f"{(fitted['detector'] or {}).get('file')} with "
                     f"{(fitted['box_refiner'] or {}).get('file')}, fitted on the boxes of "
                     f"{_read_flags(fitted['small_read'])}; asked for {model} with "
                     f"{refiner.path} and {_read_flags(read)}; fit one for them with "
                     f"`lunarnav train-box-rescorer` and name it")


def _read_flags(read: dict[str, float] | None) -> str:
    """A rescorer's recorded read as the flags that give it."""
    return ("one read" if read is None else
            f"--small-read {read['side']} --small-read-below {read['below_px']:g}")


def _add_tool_arguments(p: argparse.ArgumentParser, name: str, on_help: str,
                        off_help: str) -> None:
    """``--NAME [ONNX]`` (default and without a file: ``SHIPPED``) and ``--no-NAME`` (None), the
    choice :func:`_open_tool` opens."""
    dest = name.replace("-", "_")
    p.add_argument(f"--{name}", nargs="?", const=SHIPPED, default=SHIPPED, metavar="ONNX",
                   help=on_help)
    p.add_argument(f"--no-{name}", dest=dest, action="store_const", const=None, help=off_help)


def load_box_refiner(args: argparse.Namespace) -> Any:
    """The :class:`~lunarnav_ml.geometry.boxrefine.BoxRefiner` of ``--box-refiner`` (None with
    ``--no-box-refiner``), on ``--threads`` onnxruntime threads."""
    from lunarnav_ml.geometry.boxrefine import BoxRefiner

    return _open_tool(BoxRefiner, args.box_refiner, args.threads)


def with_box_refiner(predictor: Any, args: argparse.Namespace,
                     model: str | Path | None = None) -> Any:
    """``predictor`` (read from the file ``model``) with its crater boxes refined by
    ``--box-refiner`` and scored by ``--box-rescorer`` where given (a
    :class:`~lunarnav_ml.geometry.boxrefine.BoxRefinedDetector`), or as it is with
    ``--no-box-refiner``."""
    from lunarnav_ml.geometry.boxrefine import BoxRefinedDetector

    refiner = load_box_refiner(args)
    rescorer = load_box_rescorer(args, model, refiner)  # refused without a refiner
    return predictor if refiner is None else BoxRefinedDetector(predictor, refiner, rescorer)


def _open_tool(cls: Any, choice: str | None, threads: int) -> Any:
    """``cls`` (a refiner) on ``choice``: None for None (switched off), the shipped file for
    ``SHIPPED``, else that file."""
    if choice is None:
        return None
    return cls(None if choice == SHIPPED else choice, threads=threads)


def add_lifter_arguments(p: argparse.ArgumentParser, prefix: str = "") -> None:
    """``--min-flank-rise-px PX|none``: the lifter's hidden-rim test read to scale."""
    p.add_argument("--min-flank-rise-px", default=None, metavar="PX|none",
                   help=f"{prefix}reject a lift as near_rim_hidden when its crest rises over the "
                        "terrain in front by this much or less, read as disparity "
                        "(LifterConfig.min_flank_rise_px, default 0.12: higher drops more lifts "
                        "read off a brow of nearer terrain, and more good ones; 'none' turns the "
                        "test off)")


def lifter_overrides(args: argparse.Namespace, base: Any) -> Any:
    """``base`` (a :class:`~lunarnav_ml.geometry.lifter.LifterConfig`) with the lifter options
    of :func:`add_lifter_arguments` applied; ``base`` itself when none is given."""
    text = args.min_flank_rise_px
    if text is None:
        return base
    if str(text).lower() == "none":
        return dataclasses.replace(base, min_flank_rise_px=None)
    try:
        px = float(text)
    except ValueError:
        px = float("nan")
    if not math.isfinite(px) or px < 0:
        raise ConfigError(f"--min-flank-rise-px must be a finite number >= 0 or 'none', "
                          f"got {text}")
    return dataclasses.replace(base, min_flank_rise_px=px)


def load_refiner(args: argparse.Namespace) -> Any:
    """The :class:`~lunarnav_ml.geometry.refine.DisparityRefiner` of ``--refiner`` (None with
    ``--no-refiner``), on ``--threads`` onnxruntime threads."""
    from lunarnav_ml.geometry.refine import DisparityRefiner

    return _open_tool(DisparityRefiner, args.refiner, args.threads)

TASKS = ("detection", "geometry", "baselines-lidar", "baselines-stereo", "transfer")


def load_predictor(path: Path, threads: int, img_size: int | None = None,
                   tta: TTAConfig | None = None, small_read: SmallBoxReadConfig | None = None
                   ) -> Any:
    """An ONNX file runs through the torch-free runtime; anything else loads as a checkpoint.
    ``img_size``: network input side (default the model's own); ``tta``: wrap it in
    test-time augmentation; ``small_read``: in a second, larger read of the small boxes (not
    both)."""
    if tta is not None and small_read is not None:
        raise ConfigError("--small-read and --tta: choose one (both read the frame again at "
                          "other sides)")
    if Path(path).suffix == ".onnx":
        from lunarnav_ml.runtime import OnnxDetector

        predictor = OnnxDetector(path, threads=threads, img_size=img_size)
    else:
        from lunarnav_ml.training.api import load_detector

        predictor = load_detector(path, img_size)
    if small_read is not None:
        return SmallBoxReadPredictor(predictor, small_read)
    return predictor if tta is None else TTAPredictor(predictor, tta)


def predictor_from_args(args: argparse.Namespace, weights: Path) -> Any:
    """The detector of ``weights`` as the command's ``--threads``, ``--img-size``, ``--tta``,
    ``--small-read`` and box-refiner arguments ask."""
    return with_box_refiner(load_predictor(weights, args.threads, args.img_size,
                                           tta_config(args), small_read_config(args)),
                            args, weights)


def _results_for(args: argparse.Namespace, split: str, model: Callable[[], Any]
                 ) -> tuple[dict, list[dict]]:
    """Ground truth and detections of one split, from a results file or by running the model
    (``model()``: the predictor, loaded once for both splits)."""
    from lunarnav_ml.data.coco import read_coco
    from lunarnav_ml.eval.predict import predict_coco

    gt_path = Path(getattr(args, f"{split}_gt"))
    gt, _ = read_coco(gt_path)  # validated labels, every image file present
    results_path = getattr(args, f"{split}_results")
    if results_path is not None:
        return gt, read_coco_results(results_path)
    if args.model is None:
        raise InputError(f"eval: give --model or --{split}-results for the {split} split")
    return gt, predict_coco(model(), gt, gt_path.parent, desc=split, origin=str(gt_path),
                            progress=not args.no_progress)


def run_detection(args: argparse.Namespace) -> int:
    """The detection report of ``lunarnav eval --task detection``."""
    from lunarnav_ml.demo import write_overlays
    from lunarnav_ml.eval.pd import pick_operating_threshold
    from lunarnav_ml.eval.report import detection_metrics, write_report
    from lunarnav_ml.utils import atomic

    if args.threshold is None and args.val_gt is None:
        raise InputError("eval: the operating threshold comes from a validation split: give "
                         "--val-gt (with --model or --val-results), or --threshold")
    @functools.cache
    def model() -> Any:  # the predictor, loaded once when a split first runs the model
        return predictor_from_args(args, args.model)

    threshold, val = args.threshold, None
    if threshold is None:
        val = _results_for(args, "val", model)
        threshold = pick_operating_threshold(*val, args.max_fa)
    same_split = (val is not None and args.test_results is None and args.val_results is None
                  and Path(args.val_gt).resolve() == Path(args.test_gt).resolve())
    gt, results = val if same_split else _results_for(args, "test", model)  # one run per split
    metrics = detection_metrics(gt, results, threshold)
    with atomic.atomic_dir(args.out) as work:
        atomic.write_json(work / "detections.json", results, indent=None)
        reads = ((tta_config(args), small_read_config(args)) if args.test_results is None
                 else ())
        notes = [read.describe() for read in reads if read is not None]
        refiner = getattr(model(), "refiner", None) if args.test_results is None else None
        if refiner is not None:  # the test split's boxes went through it
            from lunarnav_ml.geometry.boxrefine import refined_by

            notes.append(refined_by(refiner.path, refiner.has_quality))
            if model().rescorer is not None:
                from lunarnav_ml.geometry.boxrescore import rescored_by

                notes.append(rescored_by(model().rescorer.path))
        write_report(metrics, work, f"Detection report: {args.test_gt}"
                     + (f" ({'; '.join(notes)})" if notes else ""))
        write_overlays(gt, results, threshold, Path(args.test_gt).parent, work / "overlays",
                       args.overlays)
    crater = metrics["coco"]["per_class"]["crater"]
    print(f"crater AP50 {crater['AP50']}  Pd {metrics['crater_pd_all']}  "
          f"FA/img {metrics['false_alarms_per_image']:.3f}  threshold {threshold:.3f}  -> {args.out}")
    return 0


def run_geometry(args: argparse.Namespace) -> int:
    """The 3D geometry report of ``lunarnav eval --task geometry``."""
    from lunarnav_ml.geometry.lifter import load_edge_offsets
    from lunarnav_ml.geometry.refine import default_lifter
    from lunarnav_ml.geometry.report import geometry_report

    # the rendered disparity is exact: nothing to refine
    refiner = load_refiner(args) if args.disparity == "sgbm" else None
    # the refiner's own edge offsets (if any) unless a calibration file is given
    base = load_edge_offsets(args.edge_offsets) if args.edge_offsets else default_lifter(refiner)
    lifter = lifter_overrides(args, base)
    # the box refiner moves a detector's boxes; labelled boxes are the rim's own
    box_refiner = load_box_refiner(args) if args.test_results is not None else None
    summary = geometry_report(Path(args.test_gt), args.out, detections=args.test_results,
                              ellipse_source=args.ellipse_source, disparity=args.disparity,
                              box_jitter=args.box_jitter, seed=args.seed, lifter=lifter,
                              refiner=refiner, box_refiner=box_refiner,
                              progress=not args.no_progress)
    print(json.dumps(summary.get("summary", summary), indent=1, default=str)[:2000])
    return 0


def run_baselines(args: argparse.Namespace) -> int:
    """The baseline reports of ``lunarnav eval --task baselines-lidar|baselines-stereo``."""
    from lunarnav_ml.baselines.report import baseline_report

    method = args.task.split("-", 1)[1]
    metrics = baseline_report(Path(args.test_gt), args.out, method=method,
                              prior_sigma_m=args.prior_sigma, progress=not args.no_progress)
    print(json.dumps(metrics.get("summary", metrics), indent=1, default=str)[:2000])
    print(f"-> {args.out}")
    return 0


def run_transfer(args: argparse.Namespace) -> int:
    """The real-data transfer report of ``lunarnav eval --task transfer``."""
    from lunarnav_ml.data.coco import read_coco
    from lunarnav_ml.eval.predict import predict_coco
    from lunarnav_ml.realdata.transfer import fmt_metric, write_transfer_report
    from lunarnav_ml.utils import atomic

    sources = {k: v for k, v in (("--checkpoint", args.checkpoint), ("--onnx", args.onnx),
                                 ("--model", args.model), ("--test-results", args.test_results))
               if v is not None}
    if len(sources) != 1:
        raise InputError("eval --task transfer: give exactly one of --checkpoint, --onnx, "
                         f"--model or --test-results (got {', '.join(sources) or 'none'})")
    gt_path = Path(args.test_gt)
    gt, _ = read_coco(gt_path)  # validated labels, every image file present
    title = f"Transfer report: {args.test_gt}"
    if args.test_results is not None:
        results = read_coco_results(args.test_results)
    else:  # load_predictor runs .onnx files through onnxruntime, checkpoints through torch
        weights = args.onnx or args.checkpoint or args.model
        predictor = predictor_from_args(args, weights)
        results = predict_coco(predictor, gt, gt_path.parent, desc="transfer",
                               origin=str(gt_path), progress=not args.no_progress)
        if hasattr(predictor, "describe"):
            title += f" ({predictor.describe()})"
    with atomic.atomic_dir(args.out) as work:
        atomic.write_json(work / "detections.json", results, indent=None)
        metrics = write_transfer_report(gt, results, gt_path.parent, work, title,
                                        gallery_images=args.overlays)
    crater, ks = metrics["all"]["per_class"]["crater"], metrics["budgets"]
    recalls = " / ".join(fmt_metric(crater[f"recall@{k}"]) for k in ks)
    print(f"crater recall@{'/'.join(map(str, ks))} {recalls}  "
          f"AP50 (lower bound) {fmt_metric(crater['AP50'])}  -> {args.out}")
    return 0


def check_settings(args: argparse.Namespace) -> None:
    """Reject impossible numeric options before any model runs; ``ConfigError`` naming the
    option."""
    if args.threshold is not None and not 0.0 <= args.threshold <= 1.0:  # NaN fails both
        raise ConfigError(f"--threshold: must be a score in [0, 1], got {args.threshold}")
    if not (math.isfinite(args.max_fa) and args.max_fa >= 0):
        raise ConfigError(f"--max-fa: must be a finite number >= 0, got {args.max_fa}")
    if args.overlays < 0:
        raise ConfigError(f"--overlays: must be >= 0, got {args.overlays}")
    small_read_config(args)  # a bad second read, or rows without one, named before any work


def _dispatch(args: argparse.Namespace) -> int:
    from lunarnav_ml.utils.atomic import check_destination

    check_settings(args)
    check_destination(args.out, folder=True)  # an --out in the way is found before any work
    if args.task == "transfer":
        return run_transfer(args)
    if args.task == "geometry":
        return run_geometry(args)
    if args.task.startswith("baselines-"):
        return run_baselines(args)
    return run_detection(args)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``lunarnav eval``."""
    p = subparsers.add_parser("eval", help="evaluation reports (detection, geometry, baselines)",
                              description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", choices=TASKS, default="detection")
    p.add_argument("--test-gt", "--gt", dest="test_gt", type=Path, required=True,
                   help="COCO annotations of the evaluated split")
    p.add_argument("--test-results", type=Path, help="COCO results JSON for the evaluated split")
    p.add_argument("--model", type=Path, help="checkpoint (.ckpt/.pt) or ONNX file to run")
    p.add_argument("--checkpoint", type=Path, help="(transfer) checkpoint (.ckpt/.pt) to run")
    p.add_argument("--onnx", type=Path, help="(transfer) ONNX file to run (torch-free runtime)")
    p.add_argument("--val-gt", type=Path, help="validation annotations (operating threshold)")
    p.add_argument("--val-results", type=Path, help="COCO results JSON for the validation split")
    p.add_argument("--threshold", type=float, help="operating threshold, instead of --val-gt")
    p.add_argument("--max-fa", type=float, default=0.2,
                   help="false alarms per image allowed at the operating threshold")
    p.add_argument("--threads", type=int, default=2, help="onnxruntime threads")
    p.add_argument("--img-size", type=int, default=None,
                   help="(detection, transfer) network input side, px; default the model's")
    add_tta_arguments(p)
    add_small_read_arguments(p, horizon=True)
    p.add_argument("--overlays", type=int, default=12, help="overlay images to write")
    p.add_argument("--ellipse-source", choices=("box", "fit", "label"), default="box",
                   help="(geometry) the ellipse each crater is lifted from: the box's inscribed "
                        "one (as `lunarnav localize` lifts), the fitted one, or the labelled "
                        "one (isolates stereo + lifter)")
    p.add_argument("--box-jitter", type=float, default=0.0,
                   help="(geometry) move each edge of the labelled boxes by N(0, this x the "
                        "box's side) before the fit and lift: how the 3D figures depend on a "
                        "detector's box error")
    p.add_argument("--seed", type=int, default=0, help="(geometry) seed of --box-jitter")
    p.add_argument("--edge-offsets", type=Path, default=None,
                   help="(geometry) the lifter's edge offsets from a "
                        "benchmarks/calibrate_rim_offset.py run (its rim_offset.json), in place "
                        "of the defaults: for another rig, matcher or terrain")
    p.add_argument("--disparity", choices=("sgbm", "rendered"), default="sgbm",
                   help="(geometry) SGBM on the pair, or the dataset's rendered disparity "
                        "(isolates the lifter)")
    add_refiner_arguments(p, "(geometry) ")
    add_box_refiner_arguments(p, "", "before the detection, transfer and geometry figures "
                              "(detection and transfer when a model runs; geometry with "
                              "--test-results; boxes marked refined are not refined again)",
                              "score the detector's boxes as they are")
    add_box_rescorer_arguments(p)
    add_lifter_arguments(p, "(geometry) ")
    p.add_argument("--prior-sigma", type=float, default=1.0,
                   help="(baselines-lidar) map-prior position error per axis, m: each map "
                        "crater's prior center is offset by N(0, sigma); placements farther "
                        "than max(4 sigma, 1 m) from it are dropped")
    p.add_argument("--out", type=Path, default=Path("outputs/eval"))
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=_dispatch)
