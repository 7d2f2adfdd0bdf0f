"""``lunarnav demo``: the whole pipeline end to end on a 2-core CPU.

Render a small synthetic stereo dataset (train / validation / held-out test, disjoint seeds),
train the smallest detector preset for a few minutes, pick the operating threshold on the
validation split, export ONNX, run the exported model through onnxruntime on the held-out test
split (its crater boxes refined and rescored by the shipped box refiner, as ``lunarnav eval``
does; the network's boxes are read too), and write one output folder: metrics JSON, a markdown
report, the Pd plots and detection overlays.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from lunarnav_ml.errors import ConfigError
from lunarnav_ml.utils import atomic

# The demo's scene distribution (fresh craters under a low side sun, see the file's header).
DEMO_SYNTH_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "synth" / "demo.yaml"


@dataclass
class DemoConfig:
    """Sizes of the demo run; the defaults fit 15 minutes on 2 CPU cores."""

    seed: int = 0  # base seed: train uses seed, validation seed + 1, test seed + 2 (x 1000003)
    n_train: int = 400  # training images
    n_val: int = 48  # validation images (operating threshold, best checkpoint)
    n_test: int = 64  # held-out test images (reported figures)
    image_size: int = 320  # rendered image side = training input side, px
    preset: str = "nano"  # detector size preset
    train_minutes: float = 12.0  # wall-clock training budget
    batch_size: int = 8  # small batches: more optimizer steps in the budget
    max_fa_per_image: float = 0.2  # false-alarm budget for the operating threshold
    n_overlays: int = 8  # overlay images written
    synth_config: str = str(DEMO_SYNTH_CONFIG)  # scene distribution of all three splits
    box_refiner: bool = True  # crater boxes through the shipped box refiner, as `lunarnav eval`

    def validate(self) -> None:
        """Reject impossible settings (before anything is rendered) with a message naming the
        field."""
        from lunarnav_ml.models.presets import PRESETS

        for name in ("n_train", "n_val", "n_test", "image_size", "batch_size"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"demo: {name} must be positive, got {getattr(self, name)}")
        if self.image_size % 32:
            raise ConfigError(f"demo: image_size must be a multiple of 32, got {self.image_size}")
        if self.n_overlays < 0:
            raise ConfigError(f"demo: n_overlays must be >= 0, got {self.n_overlays}")
        if not (math.isfinite(self.train_minutes) and self.train_minutes > 0):
            raise ConfigError(f"demo: train_minutes must be a finite number > 0, "
                              f"got {self.train_minutes}")
        if not (math.isfinite(self.max_fa_per_image) and self.max_fa_per_image >= 0):
            raise ConfigError(f"demo: max_fa_per_image must be a finite number >= 0, "
                              f"got {self.max_fa_per_image}")
        if self.preset not in PRESETS:
            raise ConfigError(f"demo: unknown preset {self.preset!r} "
                              f"(known: {', '.join(PRESETS)})")


def _split_seed(seed: int, split: int) -> int:
    return seed + 1_000_003 * split


class _Clock:
    """Wall time per stage."""

    def __init__(self) -> None:
        self.start = time.perf_counter()
        self.stages: dict[str, float] = {}
        self._t = self.start

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.stages[name] = round(now - self._t, 2)
        self._t = now
        print(f"[demo] {name}: {self.stages[name]:.1f} s", flush=True)

    @property
    def total(self) -> float:
        return round(time.perf_counter() - self.start, 2)


def peak_rss_gib() -> float:
    """Peak resident memory of this process and its waited-for children, GiB."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return round(max(own, kids) / 1024**2, 3)


def render_splits(cfg: DemoConfig, data_dir: Path, progress: bool) -> dict[str, Path]:
    """Render train / val / test with disjoint seeds; returns annotation paths. Validation and
    test are stereo pairs (right image, depth, disparity) for the 3D stages; the detector
    trains on left images, so the training split is rendered without the right view."""
    from lunarnav_ml.synth import SynthConfig, generate_dataset

    scenes = SynthConfig.from_yaml(cfg.synth_config)  # ConfigError naming a missing file
    sizes = {"train": cfg.n_train, "val": cfg.n_val, "test": cfg.n_test}
    return {
        split: generate_dataset(data_dir / split, n_images=n, seed=_split_seed(cfg.seed, i),
                                config=scenes, image_size=cfg.image_size,
                                stereo=split != "train",  # the detector trains on left images
                                progress=progress)
        for i, (split, n) in enumerate(sizes.items())
    }


def run_demo(cfg: DemoConfig, out_dir: Path, progress: bool = True) -> dict[str, Any]:
    """Run the whole demo; the output folder appears complete or not at all."""
    cfg.validate()
    with atomic.atomic_dir(out_dir) as work:  # an --out in the way is refused before rendering
        summary = _run_in(cfg, work, progress)
    print(f"[demo] wrote {out_dir}", flush=True)
    return summary


def _run_in(cfg: DemoConfig, work: Path, progress: bool) -> dict[str, Any]:
    from lunarnav_ml.eval.coco_metrics import coco_ap
    from lunarnav_ml.eval.pd import pick_operating_threshold
    from lunarnav_ml.eval.predict import predict_coco
    from lunarnav_ml.eval.report import detection_metrics, write_report
    from lunarnav_ml.export.onnx_export import export_onnx
    from lunarnav_ml.geometry.boxrefine import BoxRefinedDetector, BoxRefiner, refined_by
    from lunarnav_ml.runtime import OnnxDetector
    from lunarnav_ml.training.api import fit_detector, load_detector

    clock = _Clock()
    ann = render_splits(cfg, work / "data", progress)
    clock.lap("render")
    ckpt = fit_detector(ann["train"], ann["val"], work / "train", preset=cfg.preset,
                        img_size=cfg.image_size, max_minutes=cfg.train_minutes,
                        batch_size=cfg.batch_size, seed=cfg.seed, progress=progress,
                        val_every_n_epochs=2)
    clock.lap("train")
    gt = {split: json.loads(Path(p).read_text()) for split, p in ann.items()}
    detector = load_detector(ckpt)
    refiner = BoxRefiner(threads=2) if cfg.box_refiner else None

    def refined(predictor: Any) -> Any:  # the default detection path of `lunarnav eval`
        return predictor if refiner is None else BoxRefinedDetector(predictor, refiner)

    val_results = predict_coco(refined(detector), gt["val"], ann["val"].parent, progress=progress,
                               desc="val (torch)")
    threshold = pick_operating_threshold(gt["val"], val_results, cfg.max_fa_per_image)
    clock.lap("threshold")
    onnx_path = export_onnx(detector, work / "model.onnx")
    runtime = OnnxDetector(onnx_path, threads=2)
    test_results = predict_coco(refined(runtime), gt["test"], ann["test"].parent,
                                progress=progress, desc="test (onnxruntime)")
    network_results = None if refiner is None else predict_coco(
        runtime, gt["test"], ann["test"].parent, progress=progress,
        desc="test, network's boxes")
    atomic.write_json(work / "test_detections.json", test_results, indent=None)
    clock.lap("export+inference")
    metrics = detection_metrics(gt["test"], test_results, threshold)
    metrics["val_metrics"] = detection_metrics(gt["val"], val_results, threshold)["coco"]
    if network_results is not None:  # the same model without the refiner, for comparison
        metrics["network_boxes_coco"] = coco_ap(gt["test"], network_results)
    write_overlays(gt["test"], test_results, threshold, ann["test"].parent, work / "overlays",
                   cfg.n_overlays)
    clock.lap("report")
    metrics["run"] = {"config": asdict(cfg), "stage_seconds": clock.stages,
                      "wall_seconds": clock.total, "peak_rss_gib": peak_rss_gib(),
                      "checkpoint": str(Path(ckpt).resolve().relative_to(work.resolve())),
                      "onnx": "model.onnx",
                      "box_refiner": None if refiner is None else refiner.path.name}
    title = "lunarnav demo: synthetic held-out test split (onnxruntime)"
    if refiner is not None:
        title += "; " + refined_by(refiner.path, refiner.has_quality)
    write_report(metrics, work, title)
    _print_summary(metrics)
    return metrics


def write_overlays(gt: dict[str, Any], results: list[dict[str, Any]], threshold: float,
                   root: Path, out: Path, n: int) -> None:
    """Overlay ground truth and thresholded detections on the first ``n`` images.

    Raises:
        InputError: an image file is missing or unreadable (naming it).
    """
    import cv2

    from lunarnav_ml.eval.plots import draw_overlay
    from lunarnav_ml.utils.images import read_rgb

    names = {c["id"]: c["name"] for c in gt["categories"]}
    for record in gt["images"][:n]:
        image = cv2.cvtColor(read_rgb(root / record["file_name"]), cv2.COLOR_RGB2BGR)
        anns = [a for a in gt["annotations"] if a["image_id"] == record["id"]]
        dets = [d for d in results if d["image_id"] == record["id"] and d["score"] >= threshold]
        atomic.write_image(out / f"{Path(record['file_name']).stem}.png",
                           draw_overlay(image, anns, dets, names))


def _print_summary(m: dict[str, Any]) -> None:
    crater = m["coco"]["per_class"]["crater"]
    network = m.get("network_boxes_coco")
    beside = ("" if network is None else
              f" (network's boxes {network['per_class']['crater']['AP50']:.3f})")
    print(f"[demo] crater AP50 {crater['AP50']:.3f}{beside}  AP {crater['AP']:.3f}  "
          f"Pd(D>=5 m, <=20 m) {m.get('crater_pd_D5_within20m')}  "
          f"FA/img {m['false_alarms_per_image']:.3f}  threshold {m['threshold']:.3f}  "
          f"wall {m['run']['wall_seconds']:.0f} s  peak RSS {m['run']['peak_rss_gib']:.2f} GiB",
          flush=True)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``lunarnav demo``."""
    d = DemoConfig()
    p = subparsers.add_parser("demo", help="render, train, evaluate and export end to end",
                              description=__doc__)
    p.add_argument("--out", type=Path, default=Path("outputs/demo"), help="output folder")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--n-train", type=int, default=d.n_train)
    p.add_argument("--n-val", type=int, default=d.n_val)
    p.add_argument("--n-test", type=int, default=d.n_test)
    p.add_argument("--image-size", type=int, default=d.image_size, help="px, multiple of 32")
    p.add_argument("--preset", default=d.preset)
    p.add_argument("--train-minutes", type=float, default=d.train_minutes)
    p.add_argument("--batch-size", type=int, default=d.batch_size)
    p.add_argument("--synth-config", default=d.synth_config,
                   help="scene distribution (synth YAML) of the rendered splits")
    p.add_argument("--no-box-refiner", action="store_true",
                   help="report the network's boxes only (default: crater boxes refined and "
                        "rescored by the shipped box refiner, as `lunarnav eval` does)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    cfg = DemoConfig(seed=args.seed, n_train=args.n_train, n_val=args.n_val, n_test=args.n_test,
                     image_size=args.image_size, preset=args.preset,
                     train_minutes=args.train_minutes, batch_size=args.batch_size,
                     synth_config=args.synth_config, box_refiner=not args.no_box_refiner)
    run_demo(cfg, args.out, progress=not args.no_progress)
    return 0
