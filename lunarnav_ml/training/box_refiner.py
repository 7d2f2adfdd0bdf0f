"""Train the crater-box refiner (:mod:`lunarnav_ml.geometry.boxrefine`):
``lunarnav train-box-refiner``.

Data: COCO sets with crater labels (category 1; non-ignored boxes at least 12 px wide and 6 px
high), each optionally with a detector's results on it (COCO results JSON, e.g. the
``detections.json`` that ``lunarnav eval --task detection --out D`` writes). Crops are cut around:
- each crater detection (score >= 0.05) whose best label overlaps it at IoU >= 0.3: the
  detection's own box and ``det_jitters`` copies with each edge moved by N(0, 0.03 x side), the
  target that label's box. These teach the detector's own errors (too narrow, low at the bottom);
- each label, ``label_jitters`` copies with each edge moved by N(0, 0.1 x side).

With a quality weight (``quality`` > 0, ``--quality W``) the net has a fifth output, trained by
binary cross-entropy (weighted W) on each crop's box's IoU with its best crater label (ignored and
small labels included); the crops of the detections that overlap no label (best IoU < 0.3, each
``repeats`` times) join the mix for that output only, so that it learns what a box off every rim
looks like. The export then has a second output, ``quality`` (the sigmoid), and detection scores
each crater sqrt(score x quality) (:class:`~lunarnav_ml.geometry.boxrefine.BoxRefinedDetector`).

The net: six 3 x 3 convolutions with batch norm and ReLU (stride 2 at four of them) to a
128 x 2 x 4 map, two dense layers, four outputs (the edges as fractions of the crop; five with
the quality output). Smooth-L1
loss (beta 0.02), AdamW under a one-cycle rate, batches of 256 with random mirroring and gain.
The loop is plain PyTorch, as for the disparity refiner: one small model, crops in memory, a
held-out error printed as it goes. The export is an ONNX file with a dynamic batch, read by
:class:`~lunarnav_ml.geometry.boxrefine.BoxRefiner`.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from lunarnav_ml import __version__
from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.geometry.boxrefine import (
    CROP_H,
    CROP_W,
    CROPS_NAME,
    EDGES_NAME,
    KIND,
    QUALITY_NAME,
    REFINED_KEY,
    crop_frames,
    cut_crops,
    encode_edges,
    normalize_crops,
)
from lunarnav_ml.geometry.report import annotations_path, read_gray
from lunarnav_ml.training.refiner import _save, optimizer_step, seeded_split
from lunarnav_ml.utils.jsonfile import read_json_file

MIN_SCORE = 0.05  # detections read
MIN_IOU = 0.3  # a detection's best label must overlap it this much


@dataclass(frozen=True)
class BoxRefinerConfig:
    """Crop and training settings (the shipped refiner's are the defaults)."""

    label_jitters: int = 2
    label_jitter: float = 0.1
    det_jitters: int = 3
    det_jitter: float = 0.03
    epochs: int = 3
    batch: int = 256
    lr: float = 2e-3
    val_fraction: float = 0.05
    seed: int = 0
    quality: float = 0.0  # weight of the IoU-quality loss; 0: edges only, no quality output

    def __post_init__(self) -> None:
        for name in ("epochs", "batch"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ConfigError(f"{name}: expected a positive integer, got {value!r}")
        for name in ("label_jitters", "det_jitters"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ConfigError(f"{name}: expected a non-negative integer, got {value!r}")
        for name in ("label_jitter", "det_jitter"):
            if not 0.0 <= getattr(self, name) < 0.5:
                raise ConfigError(f"{name}: expected a fraction of the side in [0, 0.5), got "
                                  f"{getattr(self, name)!r}")
        if not 0.0 < self.lr < 1.0:
            raise ConfigError(f"lr: expected a positive rate below 1, got {self.lr!r}")
        if not (isinstance(self.quality, int | float) and np.isfinite(self.quality)
                and 0.0 <= self.quality <= 10.0):
            raise ConfigError(f"quality: expected a loss weight in [0, 10] (0: no quality "
                              f"output), got {self.quality!r}")
        if not 0.0 < self.val_fraction < 0.5:
            raise ConfigError(f"val_fraction: expected a fraction in (0, 0.5), got "
                              f"{self.val_fraction!r}")


def _block(cin: int, cout: int, stride: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout),
                         nn.ReLU(inplace=True))


class BoxRefinerNet(nn.Module):
    """Normalized crops (B, 1, 64, 128) -> box edges (B, 4) as fractions of the crop, and with
    ``quality`` a fifth column: the logit of the box's IoU with its label."""

    def __init__(self, quality: bool = False) -> None:
        super().__init__()
        self.quality = quality
        self.features = nn.Sequential(_block(1, 16, 2), _block(16, 24, 1), _block(24, 48, 2),
                                      _block(48, 64, 2), _block(64, 96, 2), _block(96, 128, 2))
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(128 * (CROP_H // 32) * (CROP_W // 32),
                                                          128),
                                  nn.ReLU(inplace=True), nn.Linear(128, 5 if quality else 4))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))


class _Exported(nn.Module):
    """A quality net's two outputs for the export: edges (B, 4) and quality (B,) in [0, 1]."""

    def __init__(self, net: BoxRefinerNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.net(x)
        return out[:, :4], torch.sigmoid(out[:, 4])


@dataclass
class BoxCrops:
    """Training crops (N, 64, 128) uint8 and their targets (N, 4) float32 (NaN rows: a crop
    for the quality output only); with a quality output, each crop's box's IoU with its best
    crater label (N,) float32."""

    crops: np.ndarray
    edges: np.ndarray
    quality: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.crops)


def _label_boxes(anns: list[dict[str, Any]], path: Path
                 ) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """Crater label boxes per image id, checked: the kept ones (not ignored, 12 x 6 px or more:
    the edges' targets) and every one (ignored and small too: the quality target's reference,
    so that a box on an ignored crater is not taught as one off every rim)."""
    kept: dict[int, list[list[float]]] = {}
    every: dict[int, list[list[float]]] = {}
    for a in anns:
        if a.get("category_id") != 1:
            continue
        box = a.get("bbox")
        if not (isinstance(box, list) and len(box) == 4
                and all(isinstance(v, int | float) and np.isfinite(v) for v in box)):
            raise InputError(f"{path}: annotation {a.get('id')}: bbox: expected 4 finite numbers, "
                             f"got {box!r}")
        every.setdefault(a["image_id"], []).append(box)
        if not (a.get("ignore") or a.get("iscrowd")) and box[2] >= 12 and box[3] >= 6:
            kept.setdefault(a["image_id"], []).append(box)
    return ({k: np.asarray(v, dtype=np.float64) for k, v in kept.items()},
            {k: np.asarray(v, dtype=np.float64) for k, v in every.items()})


def _best_iou(boxes: np.ndarray, labels: np.ndarray | None) -> np.ndarray:
    """Each box's IoU with its best label (0 without labels). Shape: (K, 4) -> (K,) float32."""
    if labels is None or not len(labels):
        return np.zeros(len(boxes), np.float32)
    return box_iou(boxes, labels).max(axis=1).astype(np.float32)


def _detection_boxes(path: Path) -> dict[int, np.ndarray]:
    """Crater detections (score >= MIN_SCORE) per image id, checked."""
    out: dict[int, list[list[float]]] = {}
    for k, d in enumerate(read_json_file(path, "COCO results", list)):
        if not isinstance(d, dict) or d.get("category_id") != 1 \
                or float(d.get("score", 1.0)) < MIN_SCORE:
            continue
        box = d.get("bbox")
        if not (isinstance(box, list) and len(box) == 4
                and all(isinstance(v, int | float) and np.isfinite(v) for v in box)
                and box[2] > 0 and box[3] > 0):
            raise InputError(f"{path}: result {k}: bbox: expected 4 finite numbers with a "
                             f"positive width and height, got {box!r}")
        if d.get(REFINED_KEY):  # a refiner learns the network's errors, not its own
            raise InputError(f"{path}: result {k}: box_refined: these boxes were refined "
                             "already; take the detections with `lunarnav eval --task detection "
                             "--no-box-refiner`")
        out.setdefault(int(d["image_id"]), []).append(box)
    return {k: np.asarray(v, dtype=np.float64) for k, v in out.items()}


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of every box in ``a`` with every box in ``b`` (x, y, w, h).

    Shape:
        a: (K, 4); b: (M, 4). Returns (K, M).
    """
    a, b = a[:, None, :], b[None, :, :]
    iw = np.clip(np.minimum(a[..., 0] + a[..., 2], b[..., 0] + b[..., 2])
                 - np.maximum(a[..., 0], b[..., 0]), 0, None)
    ih = np.clip(np.minimum(a[..., 1] + a[..., 3], b[..., 1] + b[..., 3])
                 - np.maximum(a[..., 1], b[..., 1]), 0, None)
    inter = iw * ih
    return inter / (a[..., 2] * a[..., 3] + b[..., 2] * b[..., 3] - inter)


def jitter_boxes(boxes: np.ndarray, frac: float, rng: np.random.Generator) -> np.ndarray:
    """``boxes`` with each edge moved by N(0, ``frac`` x its side); a box turned narrower than
    4 px or lower than 2 px is kept as it was.

    Shape:
        boxes: (K, 4) x, y, w, h. Returns (K, 4).
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    e = rng.normal(0.0, frac, (len(b), 4)) * b[:, [2, 2, 3, 3]]
    x0, x1 = b[:, 0] + e[:, 0], b[:, 0] + b[:, 2] + e[:, 1]
    y0, y1 = b[:, 1] + e[:, 2], b[:, 1] + b[:, 3] + e[:, 3]
    out = np.column_stack([x0, y0, x1 - x0, y1 - y0])
    bad = (out[:, 2] < 4) | (out[:, 3] < 2)
    out[bad] = b[bad]
    return out


def checked_repeats(repeats: Sequence[int] | None, n_sets: int) -> list[int]:
    """Each set's weight in a training mix: ``repeats`` as a list (None: 1 each), checked to
    be one positive integer per set."""
    repeats = [1] * n_sets if repeats is None else list(repeats)
    if len(repeats) != n_sets or any(
            not isinstance(r, int) or isinstance(r, bool) or r < 1 for r in repeats):
        raise ConfigError(f"repeats: one positive integer per set ({n_sets}), got {repeats!r}")
    return repeats


def build_crops(datasets: Sequence[str | Path], detections: Sequence[str | Path | None],
                config: BoxRefinerConfig = BoxRefinerConfig(), progress: bool = True,
                repeats: Sequence[int] | None = None) -> BoxCrops:
    """The training crops of ``datasets`` (each with its detector results or None).

    ``repeats`` (one per set, default 1) weighs a set in the mix: it gets ``repeats`` times as
    many jittered label crops, and each of its matched detections ``repeats`` times as many
    crops (its own box counting as one). A small set of real frames among thousands of renders
    needs it.
    """
    if len(detections) != len(datasets):
        raise ConfigError(f"detections: one results file (or None) per set: {len(datasets)} "
                          f"set(s), {len(detections)} file(s)")
    repeats = checked_repeats(repeats, len(datasets))
    rng = np.random.default_rng(config.seed)
    with_quality = config.quality > 0
    crops, edges, quality = [], [], []
    for dataset, det_path, times in zip(datasets, detections, repeats, strict=True):
        n_label, n_det = config.label_jitters * times, (1 + config.det_jitters) * times - 1
        path = annotations_path(dataset)
        coco = read_json_file(path, "COCO annotations", dict)
        labels, every = _label_boxes(coco.get("annotations", []), path)
        dets = _detection_boxes(Path(det_path)) if det_path is not None else {}
        images = [im for im in coco.get("images", []) if im.get("id") in labels
                  or (with_quality and im.get("id") in dets)]
        for im in tqdm(images, desc=f"crops {Path(dataset).name}", disable=not progress):
            lab = labels.get(im["id"], np.zeros((0, 4)))
            boxes = [jitter_boxes(lab, config.label_jitter, rng) for _ in range(n_label)]
            targets = [lab] * n_label
            det, unmatched = dets.get(im["id"]), np.zeros((0, 4))
            if det is not None and len(lab):
                iou = box_iou(det, lab)
                keep = iou.max(axis=1) >= MIN_IOU
                det, matched, unmatched = det[keep], lab[iou.argmax(axis=1)[keep]], det[~keep]
                boxes += [det] + [jitter_boxes(det, config.det_jitter, rng)
                                  for _ in range(n_det)]
                targets += [matched] * (1 + n_det)
            elif det is not None:
                unmatched = det
            box = np.concatenate(boxes) if boxes else np.zeros((0, 4))
            target = np.concatenate(targets) if targets else np.zeros((0, 4))
            if with_quality:  # the unmatched detections: quality crops (edges NaN)
                unmatched = np.repeat(unmatched, times, axis=0)
                box = np.concatenate([box, unmatched])
                quality.append(_best_iou(box, every.get(im["id"])))
            if not len(box):
                continue
            frames = crop_frames(box)
            crops.append(cut_crops(read_gray(path.parent, im["file_name"]), frames))
            edges.append(np.concatenate([encode_edges(target, frames[:len(target)]),
                                         np.full((len(box) - len(target), 4), np.nan,
                                                 np.float32)]))
    targets = np.concatenate(edges) if edges else np.zeros((0, 4), np.float32)
    if not np.isfinite(targets[:, 0]).any():
        raise InputError(f"no crater label of 12 x 6 px or more in {[str(d) for d in datasets]}")
    return BoxCrops(np.concatenate(crops), targets,
                    np.concatenate(quality) if with_quality else None)


@dataclass(frozen=True)
class BoxRefinerReport:
    """Held-out crops' mean absolute edge error as fractions of the crop, before (the box the
    crop was cut around) and after the net."""

    n_train: int
    n_val: int
    input_l1: float
    refined_l1: float
    steps: int
    seconds: float
    quality_corr: float | None = None  # held-out correlation of quality with the IoU


def _input_edges(n: int) -> np.ndarray:
    """The edges of the box a crop was cut around, in its own frame (the same for every crop
    horizontally: 1/6 and 5/6; vertically they depend on the box's aspect, so the held-out
    "before" figure is horizontal only)."""
    return np.tile(np.array([1 / 6, 5 / 6], np.float32), (n, 1))


def train_box_refiner(crops: BoxCrops, config: BoxRefinerConfig = BoxRefinerConfig(),
                      log: Callable[[str], None] | None = print
                      ) -> tuple[BoxRefinerNet, BoxRefinerReport]:
    """Train a :class:`BoxRefinerNet` on ``crops`` (a held-out fraction measures it)."""
    if len(crops) < 2 * config.batch:
        raise InputError(f"{len(crops)} training crops: need at least {2 * config.batch}")
    with_quality = config.quality > 0
    if with_quality and (crops.quality is None or len(crops.quality) != len(crops)):
        raise InputError("quality: these crops carry no quality targets; build them with the "
                         "same config (quality > 0)")
    rng, val, train = seeded_split(len(crops), config.val_fraction, config.seed)
    n_val = len(val)
    net = BoxRefinerNet(quality=with_quality)
    opt = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=1e-4)
    per_epoch = len(train) // config.batch
    steps = config.epochs * per_epoch
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=config.lr, total_steps=steps,
                                                pct_start=0.1)
    t0 = time.perf_counter()

    has_edges = np.isfinite(crops.edges[val][:, 0])

    def held_out() -> tuple[float, float | None]:
        """Held-out mean |edge error| (crops with edges) and the quality's correlation."""
        net.eval()
        with torch.no_grad():
            pred = torch.cat([net(torch.from_numpy(normalize_crops(crops.crops[val[i:i + 1024]])))
                              for i in range(0, len(val), 1024)]).numpy()
        net.train()
        l1 = float(np.abs(pred[has_edges, :4] - crops.edges[val][has_edges]).mean())
        if not with_quality:
            return l1, None
        q = 1.0 / (1.0 + np.exp(-pred[:, 4]))
        return l1, float(np.corrcoef(q, crops.quality[val])[0, 1])

    step = 0
    for epoch in range(config.epochs):
        order = rng.permutation(train)
        for i in range(per_epoch):
            idx = np.sort(order[i * config.batch:(i + 1) * config.batch])
            x = normalize_crops(crops.crops[idx])
            y = crops.edges[idx].copy()
            flip = rng.random(len(idx)) < 0.5
            x[flip] = x[flip, :, :, ::-1]
            y[flip] = np.column_stack([1 - y[flip, 2], y[flip, 1], 1 - y[flip, 0], y[flip, 3]])
            x *= np.exp(rng.normal(0.0, 0.2, (len(idx), 1, 1, 1))).astype(np.float32)
            out = net(torch.from_numpy(np.ascontiguousarray(x)))
            known = torch.from_numpy(np.isfinite(y[:, 0]))
            loss = nn.functional.smooth_l1_loss(out[known, :4],
                                                torch.from_numpy(y[known.numpy()]), beta=0.02)
            if with_quality:
                loss = loss + config.quality * nn.functional.binary_cross_entropy_with_logits(
                    out[:, 4], torch.from_numpy(crops.quality[idx]))
            step += 1
            optimizer_step(loss, opt, sched, step)
            if log and step % 100 == 0:
                log(f"epoch {epoch + 1}/{config.epochs}  step {step}/{steps}  "
                    f"{time.perf_counter() - t0:.0f} s  loss {loss.item():.4f}")
        if log:
            l1, corr = held_out()
            log(f"epoch {epoch + 1}/{config.epochs}: held-out mean |edge error| {l1:.4f} of the "
                "crop" + ("" if corr is None else f"; quality vs IoU r = {corr:.3f}"))
    before = float(np.abs(_input_edges(int(has_edges.sum()))
                          - crops.edges[val][has_edges][:, [0, 2]]).mean())
    after, corr = held_out()
    net.eval()
    return net, BoxRefinerReport(len(train), n_val, before, after, steps,
                                 time.perf_counter() - t0, corr)


def with_edges_from(model: Any, edges_path: str | Path) -> tuple[Any, dict[str, str]]:
    """One ONNX model whose ``edges`` are the box refiner ``edges_path``'s and whose
    ``quality`` is ``model``'s (a quality refiner's; its own edges dropped), both read from the
    same ``crops``; and the metadata that records it (``lunarnav.edges_from``: that file's
    name and training record). A lift with the result moves boxes exactly as with
    ``edges_path``.

    Raises:
        InputError: ``edges_path`` is not a box refiner; ``model`` has no quality output; the two
            were written with other ONNX opsets or IR versions.
    """
    import onnx

    from lunarnav_ml.geometry.boxrefine import BoxRefiner

    BoxRefiner(edges_path)  # a box refiner with this version's crops, or a one-line error
    base = onnx.load(str(edges_path))
    if QUALITY_NAME not in [o.name for o in model.graph.output]:
        raise InputError("edges_from: the trained net has no quality output (give --quality)")
    opsets = [sorted((o.domain, o.version) for o in m.opset_import) for m in (base, model)]
    if opsets[0] != opsets[1] or base.ir_version != model.ir_version:
        raise InputError(f"{edges_path}: written with opsets {opsets[0]} (IR {base.ir_version}); "
                         f"the trained net with {opsets[1]} (IR {model.ir_version})")
    graph = onnx.compose.add_prefix(model, "quality/").graph  # no name clashes with the base
    needed, nodes = {f"quality/{QUALITY_NAME}"}, []
    for node in reversed(graph.node):  # only what the quality output reads
        if needed.intersection(node.output):
            nodes.insert(0, node)
            needed.update(node.input)
    merged = onnx.helper.make_graph(
        [*base.graph.node, onnx.helper.make_node("Identity", [CROPS_NAME],
                                                 [f"quality/{CROPS_NAME}"]),
         *nodes, onnx.helper.make_node("Identity", [f"quality/{QUALITY_NAME}"],
                                       [QUALITY_NAME])],
        base.graph.name, list(base.graph.input),
        [*base.graph.output, next(o for o in model.graph.output if o.name == QUALITY_NAME)],
        [*base.graph.initializer, *(t for t in graph.initializer if t.name in needed)])
    out = onnx.helper.make_model(merged, opset_imports=list(base.opset_import),
                                 ir_version=base.ir_version)
    onnx.checker.check_model(out, full_check=True)
    props = {p.key: p.value for p in base.metadata_props}
    record = {"file": Path(edges_path).name,
              "training": json.loads(props.get("lunarnav.training", "null"))}
    return out, {"lunarnav.edges_from": json.dumps(record)}


def export_box_refiner(net: BoxRefinerNet, path: str | Path, extra: dict | None = None,
                       opset: int = 17, edges_from: str | Path | None = None) -> Path:
    """Write ``net`` as an ONNX box refiner (dynamic batch) with its metadata, atomically;
    with ``edges_from``, the edges are that file's (:func:`with_edges_from`)."""
    from lunarnav_ml.export.onnx_export import trace_module

    axes = {CROPS_NAME: {0: "batch"}, EDGES_NAME: {0: "batch"}}
    if net.quality:  # edges and quality
        axes[QUALITY_NAME] = {0: "batch"}
        model = trace_module(_Exported(net).eval(), torch.zeros(1, 1, CROP_H, CROP_W),
                             CROPS_NAME, [EDGES_NAME, QUALITY_NAME], axes, opset)
    else:
        model = trace_module(net.eval(), torch.zeros(1, 1, CROP_H, CROP_W), CROPS_NAME,
                             EDGES_NAME, axes, opset)
    props = {"lunarnav.kind": KIND, "lunarnav.crop": f"{CROP_W},{CROP_H}",
             "lunarnav.project_version": __version__, **(extra or {})}
    if edges_from is not None:
        model, more = with_edges_from(model, edges_from)
        props.update(more)
    return _save(model, props, path)


def run(datasets: Sequence[str | Path], detections: Sequence[str | Path | None],
        out: str | Path, config: BoxRefinerConfig, progress: bool = True,
        repeats: Sequence[int] | None = None, edges_from: str | Path | None = None
        ) -> BoxRefinerReport:
    """Crops, training and export: what ``lunarnav train-box-refiner`` does (``edges_from``:
    the file's edges are that refiner's, :func:`with_edges_from`)."""
    if edges_from is not None:
        if config.quality <= 0:
            raise ConfigError("edges_from: keeps another file's edges beside a quality output; "
                              "give a quality weight (--quality W)")
        from lunarnav_ml.geometry.boxrefine import BoxRefiner

        BoxRefiner(edges_from)  # checked before the crops, not after the training
    crops = build_crops(datasets, detections, config, progress, repeats)
    print(f"{len(crops)} crops from {len(datasets)} set(s)", flush=True)
    net, report = train_box_refiner(crops, config, log=(lambda s: print(s, flush=True)))
    meta = {"lunarnav.training": json.dumps({
        "datasets": [str(d) for d in datasets],
        "detections": [None if d is None else str(d) for d in detections],
        "repeats": list(repeats) if repeats is not None else [1] * len(datasets),
        **asdict(config), **asdict(report)})}
    export_box_refiner(net, out, meta, edges_from=edges_from)
    return report
