"""``lunarnav localize``: the craters of one rectified stereo pair in 3D (rover frame: x forward,
y left, z up, m) through the onboard pipeline (:class:`StereoCraterLocalizer`: detect, rim
ellipse, stereo lift). An ``.onnx`` model runs torch-free; a checkpoint loads through torch."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.eval.cli import (
    add_box_refiner_arguments,
    add_box_rescorer_arguments,
    add_lifter_arguments,
    add_refiner_arguments,
    add_small_read_arguments,
    lifter_overrides,
    load_box_refiner,
    load_box_rescorer,
    load_refiner,
)
from lunarnav_ml.training.cli import DEFAULT_WEIGHTS

DEFAULT_CONF = 0.3  # chosen on the 300 validation renders for sqrt(score x quality)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``lunarnav localize``."""
    p = subparsers.add_parser(
        "localize", help="craters in 3D (rover frame) from a rectified stereo pair",
        description="Detect the craters of the left image, fit each rim ellipse and lift it "
                    "with the pair's disparity to a centre and diameter in the rover frame "
                    "(x forward, y left, z up, m). Writes craters3d.json and overlay.jpg "
                    "under --out.")
    p.add_argument("left", type=Path, help="rectified left image")
    p.add_argument("right", type=Path, help="rectified right image (same size)")
    p.add_argument("--camera", type=Path, required=True,
                   help="JSON camera record: fx, fy, cx, cy (px), baseline_m, height_m, "
                        "pitch_deg, roll_deg (optional); a `lunarnav synth` image record "
                        "holding it under 'camera' also works")
    p.add_argument("--weights", type=Path, default=None,
                   help="exported .onnx model (torch-free runtime) or a checkpoint (.pt, "
                        f".ckpt); default {DEFAULT_WEIGHTS}")
    p.add_argument("--conf", type=float, default=None,
                   help="crater score threshold; with the default box refiner it holds for the "
                        "refined scores sqrt(score x quality), as in `lunarnav detect` and "
                        "`lunarnav eval` (default 0.3: on the 300 validation renders fewer false "
                        "alarms and more craters than the detector's own scores at 0.25 gave, "
                        "2.41 against 3.52 a frame, Pd 0.571 against 0.549); with "
                        "--no-box-refiner, for the detector's scores; with --box-rescorer, for "
                        "its probabilities, and then it must be given (0.79 held 0.2 false "
                        "alarms a frame on the paper-mono validation quarter with "
                        "--small-read 640)")
    p.add_argument("--iou", type=float, default=0.6, help="NMS IoU threshold")
    p.add_argument("--img-size", type=int, default=None,
                   help="network input side, px (default the model's own)")
    p.add_argument("--threads", type=int, default=2, help="onnxruntime threads")
    p.add_argument("--sgbm-mode", default="hh", choices=("hh", "hh4", "3way"),
                   help="SGBM aggregation: hh (8 paths, the evaluated default), hh4 (about half "
                        "the time), 3way (about a fifth); the faster modes lift less exactly "
                        "(BENCHMARKS.md, issue 8, 'lunarnav localize')")
    p.add_argument("--lift-from", default="box", choices=("box", "fit"),
                   help="lift each crater from the box's inscribed ellipse (default) or from "
                        "the fitted rim ellipse; the fitted one is reported either way")
    add_small_read_arguments(p, horizon=True)
    add_refiner_arguments(p)
    add_box_refiner_arguments(p)
    add_box_rescorer_arguments(p)
    add_lifter_arguments(p)
    p.add_argument("--out", type=Path, default=Path("outputs/localize"), help="output folder")
    p.set_defaults(func=run_localize)


def read_camera(path: Path) -> dict[str, float]:
    """The camera record of a JSON file (the record itself or an object with ``camera``),
    checked (:func:`~lunarnav_ml.geometry.frames.camera_values`); errors name the file."""
    from lunarnav_ml.geometry.frames import camera_values
    from lunarnav_ml.utils.jsonfile import read_json_file

    data = read_json_file(path, "camera", expect=dict)
    try:
        return camera_values(data.get("camera", data))
    except InputError as err:
        raise InputError(f"{path}: {err}") from None


def run_localize(args: argparse.Namespace) -> int:
    """Localize the pair's craters; write ``craters3d.json`` and ``overlay.jpg``."""
    from lunarnav_ml.eval.cli import load_predictor, small_read_config
    from lunarnav_ml.geometry.frames import StereoRig
    from lunarnav_ml.geometry.refine import default_lifter
    from lunarnav_ml.geometry.stereo import SGBMStereo
    from lunarnav_ml.runtime.craters3d import StereoCraterLocalizer
    from lunarnav_ml.utils import atomic
    from lunarnav_ml.utils.images import read_rgb

    if args.conf is None:
        if getattr(args, "box_rescorer", None) is not None:
            raise ConfigError("--box-rescorer: give --conf, a threshold for the rescorer's "
                              "probabilities (the default 0.3 was chosen for sqrt(score x "
                              "quality))")
        args.conf = DEFAULT_CONF
    for name in ("conf", "iou"):
        if not 0.0 <= getattr(args, name) <= 1.0:
            raise ConfigError(f"--{name} must lie in [0, 1], got {getattr(args, name)}")
    if args.threads < 1:
        raise ConfigError(f"--threads must be >= 1, got {args.threads}")
    camera = read_camera(args.camera)
    left, right = read_rgb(args.left), read_rgb(args.right)
    if left.shape != right.shape:
        raise InputError(f"{args.right}: {right.shape[1]}x{right.shape[0]} px, but the left "
                         f"image is {left.shape[1]}x{left.shape[0]}")
    try:  # the record's values, and its principal point inside the images
        rig = StereoRig.from_camera_record(camera, image_size=(left.shape[1], left.shape[0]))
    except InputError as err:
        raise InputError(f"{args.camera}: {err}") from None
    weights = args.weights or DEFAULT_WEIGHTS
    refiner = load_refiner(args)
    box_refiner = load_box_refiner(args)
    box_rescorer = load_box_rescorer(args, weights, box_refiner)
    lifter = lifter_overrides(args, default_lifter(refiner))
    stereo = replace(SGBMStereo.for_width(left.shape[1]), mode=args.sgbm_mode)
    # an .onnx file runs through the torch-free OnnxDetector, a checkpoint through torch
    small_read = small_read_config(args)  # a band over the horizon read at this camera
    small_read = None if small_read is None else small_read.at_camera(camera, left.shape[0])
    detector = load_predictor(weights, args.threads, args.img_size, small_read=small_read)
    localizer = StereoCraterLocalizer(detector, rig,
                                      conf_thres=args.conf, iou_thres=args.iou, stereo=stereo,
                                      lift_from=args.lift_from, refiner=refiner,
                                      box_refiner=box_refiner, box_rescorer=box_rescorer,
                                      lifter=lifter)
    craters = localizer(left, right)
    record = {"left": str(args.left), "right": str(args.right), "camera": camera,
              "weights": str(weights), "conf": args.conf, "iou": args.iou,
              "small_read": None if small_read is None else {**small_read.record(),
                                                             "band": small_read.band},
              "lift_from": args.lift_from, "min_flank_rise_px": lifter.min_flank_rise_px,
              "refiner": None if refiner is None else str(refiner.path),
              "box_refiner": None if box_refiner is None else str(box_refiner.path),
              "box_rescorer": None if box_rescorer is None else str(box_rescorer.path),
              "sgbm": {"mode": stereo.mode, "num_disparities": stereo.num_disparities},
              "frame": "rover: x forward, y left, z up, m",
              "timing_ms": {k: round(v, 1) for k, v in localizer.timing_ms.items()},
              "craters": [crater_record(c) for c in craters]}
    atomic.write_json(args.out / "craters3d.json", record)
    atomic.write_image(args.out / "overlay.jpg", draw_craters(left, craters))
    for c in craters:
        where = (f"centre ({c.center_m[0]:.2f}, {c.center_m[1]:.2f}, {c.center_m[2]:.2f}) m, "
                 f"D {c.diameter_m:.2f} m" if c.ok else c.reason)
        print(f"crater score {c.score:.2f}: {where}")
    n_ok = sum(c.ok for c in craters)
    took = ", ".join(f"{k} {v:.0f} ms" for k, v in localizer.timing_ms.items())
    print(f"lunarnav localize: {len(craters)} crater boxes, {n_ok} in 3D ({took}) -> "
          f"{args.out / 'craters3d.json'}")
    return 0


def crater_record(crater: Any) -> dict[str, Any]:
    """One :class:`Crater3D` as JSON: box (xyxy px), score, ellipse (cx, cy, a, b, angle_deg),
    whether the refiner corrected its disparity, for a lifted crater its centre, diameter,
    1-sigma horizontal error and covariance, and for every lift tried (passed or rejected) what
    it read (``lift``: the crest rule, the crest's rise over the terrain in front, the rim
    disparity and its residual, the share of samples that found a crest edge, the samples
    used): what a map-matching step can weigh or filter landmarks by."""
    from lunarnav_ml.utils.atomic import finite_or_none

    out: dict[str, Any] = {
        "box": [float(v) for v in crater.box], "score": float(crater.score), "ok": crater.ok,
        "reason": crater.reason,
        "ellipse": None if crater.ellipse is None else crater.ellipse.to_array().tolist(),
        "ellipse_quality": float(crater.ellipse_quality), "refined": bool(crater.refined)}
    if crater.ok:
        out.update(center_m=crater.center_m.tolist(), diameter_m=float(crater.diameter_m),
                   sigma_horizontal_m=finite_or_none(crater.lift.horizontal_sigma_m),
                   covariance_xyzd=crater.lift.covariance.tolist())
    if crater.lift is not None:
        lift = crater.lift
        out["lift"] = {"crest_step": lift.crest_step, "n_rim": int(lift.n_rim),
                       **{k: finite_or_none(getattr(lift, k)) for k in
                          ("flank_rise_m", "rim_disparity_px", "rim_residual_px",
                           "crest_fraction")}}
    return out


def draw_craters(image: np.ndarray, craters: list[Any]) -> np.ndarray:
    """BGR overlay: each crater box (green lifted, orange not), its rim ellipse and its
    diameter and range."""
    out = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    thick = max(1, round(image.shape[1] / 640))
    for c in craters:
        color = (60, 220, 60) if c.ok else (0, 140, 255)
        x0, y0, x1, y1 = (round(float(v)) for v in c.box)
        cv2.rectangle(out, (x0, y0), (x1, y1), color, thick)
        if c.ellipse is not None:
            e = c.ellipse
            cv2.ellipse(out, ((float(e.cx), float(e.cy)), (2 * float(e.a), 2 * float(e.b)),
                              float(e.angle_deg)), (255, 200, 0), thick)
        text = (f"D {c.diameter_m:.1f} m @ {np.hypot(*c.center_m[:2]):.1f} m" if c.ok
                else c.reason.split(":")[-1])
        cv2.putText(out, text, (x0, max(12, y0 - 4)), cv2.FONT_HERSHEY_SIMPLEX,
                    0.4 * thick, color, thick, cv2.LINE_AA)
    return out
