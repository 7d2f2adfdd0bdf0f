"""A flat-box extender: a box on part of a rim seen edge-on, grown to the whole crater.

On the paper's monocular grid the key craters the detector misses are seen nearly edge-on: a
rim line 20-40 times wider than high, boxed in half or in the middle (BENCHMARKS.md, issue 4,
"Rescorers fitted on three validation quarters"). The box refiner cannot reach the rest of the
rim: its crop is 1.5 box widths wide. Growing such boxes by fixed amounts (session 78) made
candidates the quality net could not tell from boxes grown onto bare ground.

This extender reads a crop ``SPAN`` box widths wide around a flat box, at a height of 3 box
heights plus 0.06 of the crop's width, and regresses the whole crater's box (the same small
net as the box refiner, :class:`~lunarnav_ml.training.box_refiner.BoxRefinerNet`, edges as
fractions of the crop, trained by its loop). It is trained on fragments of flat labels: a random 0.35-1.0 of a flat
label's width at a random place along it, its top and bottom moved by N(0, 0.15 x height); a
quarter of them the whole label. ``benchmarks/replay_candidates.py --candidates extend
--extender E.pt`` adds each flat crater box's extension as a candidate, which the box refiner
and its quality net then judge on their own crop, now around the whole crater.

    python benchmarks/flat_extender.py data/protocol8/mono_train1024/annotations.shard-0-of-4.json \\
        data/protocol8/mono_train1024/annotations.shard-1-of-4.json --out outputs/s83/extender.pt
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from lunarnav_ml.errors import REPORTED_ERRORS, ConfigError, InputError
from lunarnav_ml.geometry.boxrefine import cut_crops, decode_edges, encode_edges, normalize_crops
from lunarnav_ml.geometry.report import annotations_path, read_gray
from lunarnav_ml.training.box_refiner import (
    BoxCrops,
    BoxRefinerConfig,
    BoxRefinerNet,
    _label_boxes,
    train_box_refiner,
)
from lunarnav_ml.training.refiner import seeded_split
from lunarnav_ml.utils import atomic
from lunarnav_ml.utils.jsonfile import read_json_file

SPAN = 4.0  # the crop's width in box widths
FLAT = 8.0  # a label this many times wider than high (or more) is trained on


def extender_frames(boxes_xywh: np.ndarray, span: float = SPAN) -> np.ndarray:
    """Each box's extender crop in the image: x0, y0, width, height, px (centred on the box,
    ``span`` widths wide, 3 heights + 0.06 of the crop's width high).

    Shape:
        boxes_xywh: (K, 4). Returns (K, 4) float64.
    """
    b = np.asarray(boxes_xywh, dtype=np.float64).reshape(-1, 4)
    w_c = span * b[:, 2]
    h_c = 3.0 * b[:, 3] + 0.06 * w_c
    return np.column_stack([b[:, 0] + b[:, 2] / 2 - w_c / 2, b[:, 1] + b[:, 3] / 2 - h_c / 2,
                            w_c, h_c])


def fragments(labels: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray,
                                                                            np.ndarray]:
    """``n`` fragments of each label (x, y, w, h): a random 0.35-1.0 of its width at a random
    place (a quarter: the whole width), top and bottom moved by N(0, 0.15 x height); and the
    label each came from.

    Shape:
        labels: (K, 4). Returns (K n, 4) fragments and (K n, 4) their labels.
    """
    lab = np.repeat(np.asarray(labels, np.float64).reshape(-1, 4), n, axis=0)
    m = len(lab)
    f = np.where(rng.random(m) < 0.25, 1.0, rng.uniform(0.35, 1.0, m))
    start = rng.uniform(0.0, 1.0, m) * (1.0 - f)
    x0 = lab[:, 0] + start * lab[:, 2]
    w = f * lab[:, 2]
    top = lab[:, 1] + rng.normal(0.0, 0.15, m) * lab[:, 3]
    bottom = lab[:, 1] + lab[:, 3] + rng.normal(0.0, 0.15, m) * lab[:, 3]
    h = np.maximum(bottom - top, 0.3 * lab[:, 3])
    return np.column_stack([x0, top, w, h]), lab


def build(datasets: list[Path], per_label: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Crops (N, 64, 128) uint8 and targets (N, 4) float32 from the flat labels of
    ``datasets``."""
    rng = np.random.default_rng(seed)
    crops, targets = [], []
    for dataset in datasets:
        path = annotations_path(dataset)
        coco = read_json_file(path, "COCO annotations", dict)
        labels, _ = _label_boxes(coco.get("annotations", []), path)
        for im in tqdm(coco.get("images", []), desc=f"crops {path.name}"):
            lab = labels.get(im["id"])
            if lab is None:
                continue
            lab = lab[lab[:, 2] >= FLAT * lab[:, 3]]
            if not len(lab):
                continue
            frag, target = fragments(lab, per_label, rng)
            frames = extender_frames(frag)
            crops.append(cut_crops(read_gray(path.parent, im["file_name"]), frames))
            targets.append(encode_edges(target, frames))
    if not crops:
        raise InputError(f"no crater label {FLAT:g} times wider than high in "
                         f"{[str(d) for d in datasets]}")
    return np.concatenate(crops), np.concatenate(targets)


def train(crops: np.ndarray, targets: np.ndarray, epochs: int, batch: int, lr: float,
          seed: int) -> tuple[BoxRefinerNet, float, float]:
    """The net trained on ``crops`` by the box refiner's own loop (mirroring, gain, smooth L1,
    one-cycle rate); the held-out mean |edge error| before (the fragment's own left and right
    edges) and after (all four), as fractions of the crop."""
    config = BoxRefinerConfig(epochs=epochs, batch=batch, lr=lr, seed=seed)
    net, report = train_box_refiner(BoxCrops(crops, targets), config,
                                    log=lambda line: print(line, flush=True))
    _, val, _ = seeded_split(len(crops), config.val_fraction, seed)  # the loop's held-out crops
    own = np.tile(np.array([0.5 - 0.5 / SPAN, 0.5 + 0.5 / SPAN], np.float32), (len(val), 1))
    return net, float(np.abs(own - targets[val][:, [0, 2]]).mean()), report.refined_l1


class FlatExtender:
    """A trained extender: ``__call__(gray, boxes_xywh)`` -> the whole crater's boxes."""

    def __init__(self, path: Path) -> None:
        state = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(state, dict) or "net" not in state or "span" not in state:
            raise InputError(f"{path}: not a flat extender (benchmarks/flat_extender.py)")
        self.span = float(state["span"])
        self.net = BoxRefinerNet()
        self.net.load_state_dict(state["net"])
        self.net.eval()

    def __call__(self, gray: np.ndarray, boxes_xywh: np.ndarray) -> np.ndarray:
        b = np.asarray(boxes_xywh, np.float64).reshape(-1, 4)
        if not len(b):
            return b
        frames = extender_frames(b, self.span)
        with torch.no_grad():
            edges = self.net(torch.from_numpy(normalize_crops(cut_crops(gray, frames)))).numpy()
        return decode_edges(edges, frames)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("datasets", type=Path, nargs="+")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--per-label", type=int, default=12, help="fragments per flat label")
    p.add_argument("--epochs", type=int, default=6)
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args(argv)
    try:
        if args.per_label < 1 or args.epochs < 1 or args.batch < 2:
            raise ConfigError("--per-label and --epochs: at least 1; --batch: at least 2")
        torch.set_num_threads(args.threads)
        crops, targets = build(args.datasets, args.per_label, args.seed)
        print(f"{len(crops)} crops", flush=True)
        net, before, after = train(crops, targets, args.epochs, args.batch, args.lr, args.seed)
        with atomic.atomic_path(args.out) as tmp:
            torch.save({"net": net.state_dict(), "span": SPAN,
                        "datasets": [str(d) for d in args.datasets], "seed": args.seed}, tmp)
    except REPORTED_ERRORS as err:
        print(f"flat_extender: error: {err}", file=sys.stderr)
        return 2
    print(f"held-out mean |edge error| of the crop: the fragment {before:.4f} (left and right), "
          f"extended {after:.4f} (all four) -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
