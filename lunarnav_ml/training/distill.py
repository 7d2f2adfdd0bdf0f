"""Give a trained detector a new stem by distillation: ``lunarnav distill-stem``.

The ``small-relu-s2`` preset is ``small-relu`` with a stride-2 stem (a 6x6 stride-2 and a 3x3
convolution) in place of the full-resolution stem and stage 0; everything after stage 0 is the
same. So a trained ``small-relu`` model (the teacher) gives the new model all its weights but
the stem's, and the stem alone is trained, the rest frozen, in two phases on unlabelled images:

1. features: the student's stem output against the teacher's stage-0 output (mean squared
   error over the 24 channels at stride 2), the cheap phase;
2. outputs: the raw head maps of the student (its stem trained, the body frozen in eval mode)
   against the teacher's, so that whatever the stem still gets wrong is weighed by what the
   detector makes of it;
3. whole (optional, off by default): every weight of the student trained on the teacher's
   detections (:func:`detection_kd_loss`), at a low rate with the BatchNorm statistics held,
   so that the body can make up for what the stem still gets wrong. It can also start from a
   student trained further elsewhere (``student=``), e.g. fine-tuned with labels.

No labels are used: the teacher is the target, so the images need only look like the ones the
detector will see (renders of the training distribution, real frames of a training split).
The loop is plain PyTorch rather than Lightning: two frozen models and one small trainable
block, no validation, checkpoints or logging to manage.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.losses import detection_kd_loss
from lunarnav_ml.models import build_model
from lunarnav_ml.models.yolo import YOLO
from lunarnav_ml.training.api import Detector


@dataclass(frozen=True)
class DistillReport:
    """How close the student is to the teacher on the held-out images: relative errors (mean
    squared error over the teacher's variance) and the detection loss (0 at the teacher)."""

    feature_rel_err: float  # stem output vs the teacher's stage-0 output
    output_rel_err: float  # raw head maps
    detection_loss: float  # detection_kd_loss, the third phase's objective
    steps: tuple[int, int, int]  # (feature, output, whole) optimizer steps


def student_from(teacher: Detector, preset: str) -> YOLO:
    """A ``preset`` model holding the teacher's weights wherever the two share a tensor name and
    shape; only the stem may differ.

    Raises:
        ConfigError: the preset differs from the teacher's in more than the stem and stage 0.
    """
    model = teacher.model
    student = build_model(preset, len(teacher.class_names), model.anchors.clone())
    own, theirs = student.state_dict(), model.state_dict()
    shared = {k for k in own if k in theirs and theirs[k].shape == own[k].shape}
    outside = [k for k in own if k not in shared
               and not k.startswith(("backbone.stem.", "backbone.stages.0."))]
    if outside:
        raise ConfigError(f"preset {preset!r} differs from the teacher's "
                          f"({teacher.preset!r}) outside the stem: {outside[:3]}")
    student.load_state_dict({k: theirs[k] for k in shared}, strict=False)
    return student


def _teacher_stem(model: YOLO, x: torch.Tensor) -> torch.Tensor:
    return model.backbone.stages[0](model.backbone.stem(x))


def _rel_err(a: torch.Tensor | list, b: torch.Tensor | list) -> float:
    a, b = (list(t) if isinstance(t, (list, tuple)) else [t] for t in (a, b))
    num = sum(float(((x - y) ** 2).sum()) for x, y in zip(a, b))
    den = sum(float(((y - y.mean()) ** 2).sum()) for y in b)
    return num / max(den, 1e-12)


def distill_stem(teacher: Detector, images: np.ndarray, preset: str = "small-relu-s2", *,
                 feature_steps: int = 1000, output_steps: int = 300, batch: int = 16,
                 lr: float = 2e-3, held_out: int = 32, seed: int = 0,
                 student: Detector | None = None, whole_steps: int = 0,
                 whole_lr: float = 1e-4, bf16: bool = False, device: str = "auto",
                 progress: bool = True) -> tuple[Detector, DistillReport]:
    """Train a student's stem to reproduce the teacher (see the module docstring).

    Args:
        teacher: the trained detector (its preset differs from ``preset`` only in the stem).
        images: (N, 3, S, S) float32 network inputs (letterboxed, normalized as the model
            expects), N > ``held_out``.
        feature_steps, output_steps: optimizer steps of the two phases.
        batch: images per step (random, with horizontal flips).
        lr: AdamW peak rate, cosine to 5 % over each phase.
        held_out: the last images, kept out of training to report the errors on.
        student: start from this ``preset`` detector instead of the teacher's weights with a
            fresh stem (then ``feature_steps`` and ``output_steps`` may be 0).
        whole_steps, whole_lr: steps and AdamW peak rate of the third phase (every weight).
        bf16: run the forward passes under bfloat16 autocast (CPUs with AVX512-BF16 or AMX
            train about 1.7x faster; the losses stay in float32).
        device: where the two models run (``"auto"``: CUDA where there is one, else the CPU;
            ``"cpu"``, ``"cuda"``, ``"cuda:1"``); the images stay in host memory and go over a
            batch at a time. The student comes back on the CPU.

    Returns:
        The student as a :class:`Detector` (eval mode, the teacher's input size and classes)
        and its :class:`DistillReport`.
    """
    if images.ndim != 4 or images.shape[1] != 3 or not np.isfinite(images).all():
        raise InputError(f"images: expected finite (N, 3, S, S) inputs, got {images.shape}")
    if len(images) <= held_out or held_out < 1:
        raise ConfigError(f"images: need more than held_out={held_out} images, got {len(images)}")
    if min(feature_steps, output_steps, whole_steps) < 0 or batch < 1 or not lr > 0 \
            or not whole_lr > 0:
        raise ConfigError("feature_steps, output_steps and whole_steps must be >= 0, "
                          "batch >= 1, lr and whole_lr > 0")
    if student is not None and (student.preset != preset or student.img_size != teacher.img_size
                                or list(student.class_names) != list(teacher.class_names)):
        raise ConfigError(f"student: a {preset!r} detector at the teacher's input size and "
                          f"classes expected, got {student.preset!r} at {student.img_size} px "
                          f"with {list(student.class_names)}")
    dev = torch_device(device)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    t_model = teacher.model.float().eval().to(dev)
    student = (student_from(teacher, preset) if student is None else student.model).float()
    student.to(dev)
    for p in t_model.parameters():
        p.requires_grad_(False)
    stem = student.backbone.stem
    for name, p in student.named_parameters():
        p.requires_grad_(name.startswith("backbone.stem."))
    autocast = torch.autocast(dev.type, dtype=torch.bfloat16, enabled=bf16)
    train, test = torch.from_numpy(images[:-held_out]), torch.from_numpy(images[-held_out:]).to(dev)

    def sample() -> torch.Tensor:
        x = train[rng.integers(0, len(train), batch)]
        flip = torch.from_numpy(rng.random(batch) < 0.5)
        return torch.where(flip[:, None, None, None], x.flip(-1), x).to(dev)

    def phase(steps: int, loss_fn, desc: str, params, peak: float, warmup: int = 0) -> None:
        if steps == 0:
            return
        opt = torch.optim.AdamW(params, lr=peak, weight_decay=1e-4)
        sched = torch.optim.lr_scheduler.LambdaLR(
            opt, lambda i: min(1.0, (i + 1) / (warmup + 1))
            * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(i / steps, 1.0)))))
        bar = _progress(steps, desc, progress)
        for _ in range(steps):
            with autocast:
                loss = loss_fn(sample())
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            bar.set_postfix(loss=f"{float(loss.detach()):.4g}")
            bar.update()
        bar.close()

    def feature_loss(x: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            target = _teacher_stem(t_model, x)
        return nn.functional.mse_loss(stem(x), target)

    def against_teacher(compare):  # a loss on the raw head maps of student and teacher
        def loss(x: torch.Tensor) -> torch.Tensor:
            with torch.no_grad():
                target = t_model(x)
            return compare(student(x), target)
        return loss

    output_loss = against_teacher(lambda out, target: sum(
        nn.functional.mse_loss(s.float(), t.float()) for s, t in zip(out, target)))
    whole_loss = against_teacher(
        lambda out, target: detection_kd_loss(out, target, student.head.num_anchors))

    student.eval()
    stem.train()
    phase(feature_steps, feature_loss, "distill-stem: features", stem.parameters(), lr)
    phase(output_steps, output_loss, "distill-stem: outputs", stem.parameters(), lr)
    if feature_steps + output_steps:
        _recalibrate_batchnorm(stem, sample)
    student.eval()  # the third phase holds every BatchNorm's statistics
    for p in student.parameters():
        p.requires_grad_(True)
    phase(whole_steps, whole_loss, "distill-stem: whole", student.parameters(), whole_lr,
          warmup=min(50, whole_steps // 10))
    with torch.no_grad():
        feat = _rel_err(stem(test), _teacher_stem(t_model, test))
        s_out, t_out = student(test), t_model(test)
        out = _rel_err(s_out, t_out)
        kd = float(detection_kd_loss(s_out, t_out, student.head.num_anchors))
    t_model.cpu()
    detector = Detector(student.cpu(), teacher.img_size, teacher.class_names, preset)
    return detector, DistillReport(feat, out, kd, (feature_steps, output_steps, whole_steps))


def torch_device(name: str) -> torch.device:
    """``name`` as a torch device, checked: ``cpu``, ``cuda[:N]`` where CUDA is, or ``auto``
    (CUDA where there is one, else the CPU)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        dev = None
    if dev is None or dev.type not in ("cpu", "cuda"):
        raise ConfigError(f"device {name!r}: 'auto', 'cpu' or 'cuda[:N]' expected")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device {name!r}: no CUDA device here (use 'cpu')")
    return dev


def _recalibrate_batchnorm(module: nn.Module, sample, batches: int = 16) -> None:
    """Set the BatchNorm running statistics of ``module`` to their mean over ``batches`` fresh
    training batches under the final weights (the running averages kept during training lag
    behind weights that moved)."""
    norms = [m for m in module.modules() if isinstance(m, nn.BatchNorm2d)]
    saved = [m.momentum for m in norms]
    for m in norms:
        m.reset_running_stats()
        m.momentum = None  # cumulative average
    module.train()
    with torch.no_grad():
        for _ in range(batches):
            module(sample())
    for m, momentum in zip(norms, saved):
        m.momentum = momentum
    module.eval()


def _progress(total: int, desc: str, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, disable=not enabled, leave=False)


def load_inputs(sources: list[Path], size: int, limit: int | None = None, seed: int = 0
                ) -> np.ndarray:
    """Network inputs from image datasets or folders (``quantize.list_images``), letterboxed
    to ``size``: up to ``limit`` images drawn at random (seeded), in a fixed order."""
    from lunarnav_ml.export.quantize import list_images
    from lunarnav_ml.runtime.preprocess import prepare_batch
    from lunarnav_ml.utils.images import read_rgb

    files = [f for s in sources for f in list_images(s)]
    if not files:
        raise InputError(f"no images found in {[str(s) for s in sources]}")
    if limit is not None and limit < len(files):
        pick = np.random.default_rng(seed).choice(len(files), limit, replace=False)
        files = [files[i] for i in sorted(pick)]
    order = np.random.default_rng(seed + 1).permutation(len(files))
    out = np.empty((len(files), 3, size, size), np.float32)
    for j, i in enumerate(order):
        out[j] = prepare_batch([read_rgb(files[i])], (size, size))[0][0]
    return out
