"""Train the disparity refiner (:mod:`lunarnav_ml.geometry.refine`): ``lunarnav train-refiner``.

Data: rendered stereo sets (``lunarnav synth --protocol paper-stereo``, which write each pair's
exact disparity). Per image, SGBM runs on the band the geometry evaluation reads
(:func:`~lunarnav_ml.geometry.lifter.rows_needed` of the evaluated craters' boxes); 64 x 64
crops are cut around the near half of each evaluated crater's box-inscribed ellipse (8 per
crater), around one point of every other crater label at least 10 px wide whose bottom lies in
the band, and at 4 random places in the band. The target is the rendered disparity minus SGBM's,
at pixels SGBM matched, the render hit and the two are within 4 px (a larger miss is a wrong
match, not a refinement).

The net: a 3 x 3 convolution to ``channels``, residual blocks (a dilated and a plain 3 x 3
convolution, leaky ReLU) and a 3 x 3 convolution to one channel; L1 loss, Adam with a cosine
rate over ``steps``. The loop is plain PyTorch rather than Lightning, as for ``distill-stem``:
one small model, crops in memory, a held-out L1 printed as it goes and no checkpoints to manage.
The export is an ONNX file with dynamic height and width, read by
:class:`~lunarnav_ml.geometry.refine.DisparityRefiner`.
"""

from __future__ import annotations

import json
import math
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
from lunarnav_ml.geometry._checks import crater_labels_3d
from lunarnav_ml.geometry.lifter import rows_needed
from lunarnav_ml.geometry.refine import (
    DELTA_NAME,
    FEATURES_NAME,
    KIND,
    N_FEATURES,
    check_settings,
    gate_metadata,
    refiner_features,
    warp_right,
)
from lunarnav_ml.geometry.report import annotations_path, evaluated_label, read_gray
from lunarnav_ml.geometry.stereo import SGBMStereo
from lunarnav_ml.utils.atomic import atomic_path
from lunarnav_ml.utils.images import read_disparity
from lunarnav_ml.utils.jsonfile import read_json_file

CROP = 64
MAX_TARGET_PX = 4.0  # larger SGBM misses are wrong matches, left out of the loss
MIN_DIAMETER_M = 4.5  # the geometry evaluation's craters


@dataclass(frozen=True)
class RefinerConfig:
    """Net and training settings (the shipped refiner's are the defaults)."""

    channels: int = 32
    dilations: tuple[int, ...] = (1, 2, 4, 8, 1)
    steps: int = 4800
    batch: int = 16
    lr: float = 1e-3
    val_fraction: float = 0.05
    seed: int = 65
    max_disparity_px: float | None = None  # keep crops whose median SGBM disparity is below

    def __post_init__(self) -> None:
        for name in ("channels", "steps", "batch"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ConfigError(f"{name}: expected a positive integer, got {value!r}")
        if not self.dilations or any(not isinstance(d, int) or d < 1 for d in self.dilations):
            raise ConfigError(f"dilations: expected positive integers, got {self.dilations!r}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ConfigError(f"lr: expected a positive number, got {self.lr!r}")
        try:  # the gate the exported file will carry
            check_settings(self.max_disparity_px, 1)
        except InputError as err:
            raise ConfigError(str(err)) from None
        if not 0.0 < self.val_fraction < 0.5:
            raise ConfigError(f"val_fraction: expected a fraction in (0, 0.5), got "
                              f"{self.val_fraction!r}")


class _Block(nn.Module):
    def __init__(self, ch: int, dilation: int) -> None:
        super().__init__()
        self.c1 = nn.Conv2d(ch, ch, 3, padding=dilation, dilation=dilation)
        self.c2 = nn.Conv2d(ch, ch, 3, padding=1)
        self.act = nn.LeakyReLU(0.1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.c2(self.act(self.c1(self.act(x))))


class RefinerNet(nn.Module):
    """Features (B, 5, H, W) -> disparity correction (B, H, W), px."""

    def __init__(self, channels: int = 32, dilations: Sequence[int] = (1, 2, 4, 8, 1)) -> None:
        super().__init__()
        self.dilations = tuple(dilations)
        self.inp = nn.Conv2d(N_FEATURES, channels, 3, padding=1)
        self.blocks = nn.Sequential(*[_Block(channels, d) for d in self.dilations])
        self.out = nn.Conv2d(channels, 1, 3, padding=1)

    @property
    def receptive_px(self) -> int:
        """Radius, px, beyond which an input cannot change an output."""
        return 2 + sum(d + 1 for d in self.dilations)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(nn.functional.leaky_relu(self.blocks(self.inp(x)), 0.1))[:, 0]


@dataclass
class Crops:
    """Training crops: left, warped right (uint8), SGBM and rendered disparity (float32, NaN
    invalid), each (N, 64, 64)."""

    left: np.ndarray
    warped: np.ndarray
    sgbm: np.ndarray
    rendered: np.ndarray

    def __len__(self) -> int:
        return len(self.left)


def _centres(targets: list[dict], others: list[dict], band: tuple[int, int], width: int,
             rng: np.random.Generator) -> list[tuple[float, float]]:
    """Crop centres: the near half of each target's box ellipse (8), one near-half point of
    each other crater whose bottom is in the band, 4 random points in the band."""
    out = []
    for anns, n in ((targets, 8), (others, 1)):
        for a in anns:
            x, y, w, h = a["bbox"]
            if n == 1 and not band[0] <= y + h <= band[1]:
                continue
            for t in rng.uniform(0, np.pi, n):
                out.append((x + w / 2 * (1 + np.cos(t)), y + h / 2 * (1 + np.sin(t))))
    out += [(rng.uniform(0, width), rng.uniform(*band)) for _ in range(4)]
    return out


def evaluated_craters(dataset: str | Path) -> tuple[Path, dict, dict[int, list[dict]]]:
    """A rendered set's annotations file, its COCO object and the craters the geometry
    evaluation scores (D >= 4.5 m, 3D labels), by image id."""
    ann_path = annotations_path(dataset)
    coco = read_json_file(ann_path, "annotations", expect=dict)
    by_image: dict[int, list[dict]] = {}
    for a in crater_labels_3d(ann_path, coco):
        if evaluated_label(a, MIN_DIAMETER_M):
            by_image.setdefault(a["image_id"], []).append(a)
    return ann_path, coco, by_image


def build_crops(datasets: Sequence[str | Path], seed: int = 65, progress: bool = True,
                stereo: Callable | None = None, max_disparity_px: float | None = None) -> Crops:
    """Cut training crops from rendered stereo sets (module docstring); with
    ``max_disparity_px`` only those whose median SGBM disparity is below it (the far craters a
    refiner gated at that disparity refines; the crops drawn are the same either way).

    Raises:
        InputError: a set without annotations, stereo pairs or rendered disparity; an image
            that cannot be read; no crop at all.
    """
    rng = np.random.default_rng(seed)
    parts: dict[str, list[np.ndarray]] = {"left": [], "warped": [], "sgbm": [], "rendered": []}
    for dataset in datasets:
        ann_path, coco, targets = evaluated_craters(dataset)
        others: dict[int, list[dict]] = {}
        for a in coco["annotations"]:
            if a.get("category_id") == 1 and a["bbox"][2] >= 10:
                others.setdefault(a["image_id"], []).append(a)
        images = [im for im in coco.get("images", []) if targets.get(im.get("id"))]
        if not images:
            raise InputError(f"{ann_path}: no image with an evaluated crater (D >= "
                             f"{MIN_DIAMETER_M} m, 3D label)")
        for im in tqdm(images, desc=f"crops {Path(dataset).name}", disable=not progress):
            if not im.get("right_file"):
                raise InputError(f"{ann_path}: images[{im['id']}] has no right_file")
            left = read_gray(ann_path.parent, im["file_name"])
            right = read_gray(ann_path.parent, im["right_file"])
            tg = targets[im["id"]]
            band = rows_needed(np.array([a["bbox"] for a in tg], float), left.shape[0])
            sgbm = (stereo or SGBMStereo.for_width(left.shape[1]))(left, right, band).disparity
            rendered = read_disparity(ann_path.parent, im).astype(np.float32)
            if rendered.shape != left.shape:
                raise InputError(f"{ann_path.parent / im['disparity_file']}: disparity of shape "
                                 f"{rendered.shape}, image {left.shape}")
            warped = warp_right(right, sgbm)
            h, w = left.shape
            for u, v in _centres(tg, others.get(im["id"], []), band, w, rng):
                u0 = int(np.clip(round(u + rng.uniform(-8, 8)) - CROP // 2, 0, w - CROP))
                v0 = int(np.clip(round(v + rng.uniform(-8, 8)) - CROP // 2, band[0],
                                 max(band[0], band[1] - CROP)))
                win = (slice(v0, v0 + CROP), slice(u0, u0 + CROP))
                if v0 + CROP > h or np.isfinite(sgbm[win]).mean() < 0.3:
                    continue
                if max_disparity_px is not None and np.nanmedian(sgbm[win]) >= max_disparity_px:
                    continue
                for key, arr in (("left", left), ("warped", warped), ("sgbm", sgbm),
                                 ("rendered", rendered)):
                    parts[key].append(arr[win])
    if not parts["left"]:
        raise InputError(f"{', '.join(map(str, datasets))}: no training crop (every crater band "
                         "too thin or unmatched)")
    return Crops(np.array(parts["left"]), np.array(parts["warped"]),
                 np.array(parts["sgbm"], dtype=np.float32),
                 np.array(parts["rendered"], dtype=np.float32))


def _loss(net: RefinerNet, crops: Crops, idx: np.ndarray) -> tuple[torch.Tensor, float]:
    """Masked L1 of the refined disparity and SGBM's own L1 on the same pixels."""
    x = torch.from_numpy(refiner_features(crops.left[idx], crops.warped[idx], crops.sgbm[idx]))
    target = torch.from_numpy(crops.rendered[idx] - crops.sgbm[idx])
    keep = (torch.isfinite(target) & (torch.from_numpy(crops.rendered[idx]) > 0)
            & (target.abs() < MAX_TARGET_PX))
    err = (net(x) - torch.nan_to_num(target)).abs()
    return err[keep].mean(), float(target[keep].abs().mean())


@dataclass(frozen=True)
class RefinerReport:
    """Held-out crops' mean absolute disparity error, px, before and after refinement."""

    n_train: int
    n_val: int
    sgbm_l1_px: float
    refined_l1_px: float
    steps: int
    seconds: float


def seeded_split(n: int, val_fraction: float, seed: int
                 ) -> tuple[np.random.Generator, np.ndarray, np.ndarray]:
    """Seed torch with ``seed`` and split ``n`` items at random: the generator (to go on
    drawing batches from), a held-out ``val_fraction`` (at least one) and the rest."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    perm = rng.permutation(n)
    n_val = max(1, int(n * val_fraction))
    return rng, perm[:n_val], perm[n_val:]


def optimizer_step(loss: torch.Tensor, opt: torch.optim.Optimizer, sched: Any, step: int
                   ) -> None:
    """Back-propagate ``loss`` and step the optimizer and its schedule; InputError for a loss
    that is not finite (the run diverged at ``step``)."""
    if not torch.isfinite(loss):
        raise InputError(f"training diverged at step {step} (loss {loss.item()})")
    opt.zero_grad()
    loss.backward()
    opt.step()
    sched.step()


def train_refiner(crops: Crops, config: RefinerConfig = RefinerConfig(),
                  log: Callable[[str], None] | None = print) -> tuple[RefinerNet, RefinerReport]:
    """Train a :class:`RefinerNet` on ``crops`` (a held-out fraction measures it)."""
    if len(crops) < 2 * config.batch:
        raise InputError(f"{len(crops)} training crops: need at least {2 * config.batch}")
    rng, val, train = seeded_split(len(crops), config.val_fraction, config.seed)
    net = RefinerNet(config.channels, config.dilations)
    opt = torch.optim.Adam(net.parameters(), config.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.5 * (1 + math.cos(math.pi * min(s / config.steps, 1.0))))
    t0 = time.perf_counter()

    def held_out() -> tuple[float, float]:
        net.eval()
        with torch.no_grad():
            parts = [_loss(net, crops, val[i:i + 64]) for i in range(0, len(val), 64)]
        net.train()
        weights = [len(val[i:i + 64]) for i in range(0, len(val), 64)]
        return (float(np.average([p[1] for p in parts], weights=weights)),
                float(np.average([p[0].item() for p in parts], weights=weights)))

    for step in range(1, config.steps + 1):
        loss, _ = _loss(net, crops, rng.choice(train, config.batch, replace=False))
        optimizer_step(loss, opt, sched, step)
        if log and (step % 500 == 0 or step == config.steps):
            base, refined = held_out()
            log(f"step {step}/{config.steps}  {time.perf_counter() - t0:.0f} s  train L1 "
                f"{loss.item():.4f} px  held-out L1 {refined:.4f} px (SGBM {base:.4f})")
    base, refined = held_out()
    net.eval()
    return net, RefinerReport(len(train), len(val), base, refined, config.steps,
                              time.perf_counter() - t0)


def export_refiner(net: RefinerNet, path: str | Path, extra: dict | None = None,
                   opset: int = 17) -> Path:
    """Write ``net`` as an ONNX refiner (dynamic batch, height and width) with its metadata,
    atomically."""
    from lunarnav_ml.export.onnx_export import trace_module

    axes = {FEATURES_NAME: {0: "batch", 2: "height", 3: "width"},
            DELTA_NAME: {0: "batch", 1: "height", 2: "width"}}
    model = trace_module(net.eval(), torch.zeros(1, N_FEATURES, CROP, CROP), FEATURES_NAME,
                         DELTA_NAME, axes, opset)
    props = {"lunarnav.kind": KIND, "lunarnav.receptive_px": str(net.receptive_px),
             "lunarnav.project_version": __version__, **(extra or {})}
    return _save(model, props, path)


def _save(model: Any, props: dict[str, str], path: str | Path) -> Path:
    """``model`` with ``props`` set in its metadata (replacing those keys), saved atomically."""
    import onnx

    keep = [(p.key, p.value) for p in model.metadata_props if p.key not in props]
    del model.metadata_props[:]
    for key, value in [*keep, *props.items()]:
        model.metadata_props.add(key=key, value=value)
    with atomic_path(path) as tmp:
        onnx.save(model, str(tmp))
    return Path(path)


def stamp_edge_offsets(path: str | Path, terms: dict[str, float],
                       max_disparity_px: float | None = None, passes: int = 1) -> Path:
    """Write ``terms`` (:class:`~lunarnav_ml.geometry.lifter.LifterConfig` edge-offset fields)
    into a refiner file's ``lunarnav.edge_offsets``, replacing any there, with the gate and
    pass count they were fitted under (``lunarnav.max_disparity_px``, ``lunarnav.passes``),
    atomically.

    Raises:
        InputError: the file is not a refiner (:class:`DisparityRefiner` checks), a term is
            not an edge-offset field or not finite, or bad settings.
    """
    import onnx

    from lunarnav_ml.geometry.refine import DisparityRefiner, _edge_offsets

    DisparityRefiner(path)  # a refiner, loadable
    text = json.dumps(terms)
    _edge_offsets(text, Path(path))
    check_settings(max_disparity_px, passes)
    props = {"lunarnav.edge_offsets": text, "lunarnav.passes": str(passes),
             **gate_metadata(max_disparity_px)}
    return _save(onnx.load(str(path)), props, path)


def run(datasets: Sequence[str | Path], out: str | Path, config: RefinerConfig,
        progress: bool = True) -> RefinerReport:
    """Crops, training and export: what ``lunarnav train-refiner`` does."""
    crops = build_crops(datasets, config.seed, progress, max_disparity_px=config.max_disparity_px)
    print(f"{len(crops)} crops from {len(datasets)} set(s)", flush=True)
    net, report = train_refiner(crops, config, log=(lambda s: print(s, flush=True)))
    meta = {"lunarnav.training": json.dumps({"datasets": [str(d) for d in datasets],
                                             **asdict(config), **asdict(report)})}
    if config.max_disparity_px is not None:  # trained for the far craters: gated likewise
        meta.update(gate_metadata(config.max_disparity_px))
    export_refiner(net, out, meta)
    return report
