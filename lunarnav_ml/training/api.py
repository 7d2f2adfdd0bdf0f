"""Training and inference entry points other stages code against (docs/ARCHITECTURE.md):
``fit_detector``, ``load_detector``, ``average_detectors`` and ``Detector``."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lunarnav_ml.data.coco import default_class_names
from lunarnav_ml.data.letterbox import LetterboxInfo, letterbox
from lunarnav_ml.errors import ConfigError, InputError, one_line
from lunarnav_ml.models import YOLO, build_model, decode, postprocess
from lunarnav_ml.training.checkpoint import read_checkpoint, save_slim


class Detector:
    """A trained detector for inference on RGB images.

    Attributes:
        model: the :class:`YOLO` module (eval mode, CPU unless moved).
        anchors: :math:`(L, A, 2)` anchors, input px.
        strides: pixels per cell of each scale.
        scale_xy: grid-sensitivity factor per scale.
        img_size: square input side, px.
        class_names: name of category id ``k`` at index ``k - 1``.
    """

    def __init__(self, model: YOLO, img_size: int, class_names: list[str], preset: str = "") -> None:
        self.model = model.eval()
        self.img_size = int(img_size)
        self.class_names = list(class_names)
        self.preset = preset

    def set_img_size(self, img_size: int | tuple[int, int]) -> None:
        """Run at another square input side, or an ``(height, width)`` input (the network is
        fully convolutional).

        Raises:
            ConfigError: not a positive multiple of the largest stride.
        """
        step = max(self.strides)
        sides = img_size if isinstance(img_size, tuple) and len(img_size) == 2 else (img_size,)
        if any(isinstance(s, bool) or not isinstance(s, int) or s <= 0 or s % step
               for s in sides):
            raise ConfigError(f"img_size: expected a positive multiple of {step} or a (height, "
                              f"width) pair of them, got {img_size!r}")
        self.img_size = img_size

    @property
    def anchors(self) -> torch.Tensor:
        return self.model.anchors

    @property
    def strides(self) -> tuple[int, ...]:
        return self.model.strides

    @property
    def scale_xy(self) -> tuple[float, ...]:
        return self.model.scale_xy

    @property
    def config(self) -> dict[str, Any]:
        """What :func:`load_detector` needs to rebuild the model."""
        return {"preset": self.preset, "num_classes": len(self.class_names),
                "class_names": self.class_names, "anchors": self.anchors.tolist(),
                "img_size": self.img_size}

    def preprocess(self, images: list[np.ndarray]) -> tuple[torch.Tensor, list[LetterboxInfo]]:
        """Letterbox RGB uint8 images into one float batch.

        Shape:
            - Output: :math:`(B, 3, S, S)` float in [0, 1], ``S = img_size`` (or
              :math:`(B, 3, H, W)` for an ``(H, W)`` img_size).
        """
        squares, infos = [], []
        for i, image in enumerate(images):
            if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3:
                raise InputError(f"images[{i}]: expected an HxWx3 uint8 RGB array, got "
                                 f"{getattr(image, 'shape', type(image))}")
            square, info = letterbox(np.ascontiguousarray(image, dtype=np.uint8), self.img_size)
            squares.append(square)
            infos.append(info)
        batch = torch.from_numpy(np.stack(squares)).permute(0, 3, 1, 2).float() / 255.0
        return batch, infos

    @torch.no_grad()
    def predict(self, images: list[np.ndarray], conf_thres: float = 0.001,
                iou_thres: float = 0.6, max_det: int = 300) -> list[dict[str, np.ndarray]]:
        """Detect objects in RGB images.

        Args:
            images: HxWx3 uint8 RGB arrays (any sizes).
            conf_thres: minimum score ``objectness * class probability``.
            iou_thres: NMS IoU threshold.

        Returns:
            per image ``{"boxes": (N, 4) float32 xyxy original px, "scores": (N,) float32,
            "labels": (N,) int64 category ids 1..K}``.
        """
        if not images:
            return []
        device = next(self.model.parameters()).device
        batch, infos = self.preprocess(images)
        # channels-last input: 1.6x eager CPU inference (small-relu, 384 px, batch 8, fp32)
        raw = self.model(batch.to(device).contiguous(memory_format=torch.channels_last))
        preds = postprocess(decode(raw, self.anchors, self.strides, self.scale_xy), conf_thres,
                            iou_thres, max_det)
        out = []
        for pred, info, image in zip(preds, infos, images):
            boxes = info.to_original(pred["boxes"].cpu().numpy(), image.shape[1], image.shape[0])
            out.append({"boxes": boxes, "scores": pred["scores"].cpu().numpy().astype(np.float32),
                        "labels": pred["labels"].cpu().numpy().astype(np.int64)})
        return out

    @staticmethod
    def to_coco_results(preds: list[dict[str, np.ndarray]], image_ids: list[int]
                        ) -> list[dict[str, Any]]:
        """Predictions of several images as COCO results (bbox as x, y, w, h)."""
        from lunarnav_ml.eval.predict import coco_results

        return coco_results(preds, image_ids)

    def save(self, path: str | Path, half: bool = False) -> Path:
        """Write a slim ``.pt`` file (weights + config) that :func:`load_detector` reads;
        ``half`` stores the weights in float16 (how the shipped checkpoints are kept)."""
        return save_slim(path, self.config, self.model, half=half)


def load_detector(path: str | Path, img_size: int | None = None) -> Detector:
    """Load a detector from a Lightning ``.ckpt`` (EMA weights) or a slim ``.pt`` file.

    Args:
        img_size: network input side to run at (:meth:`Detector.set_img_size`); default the
            size recorded in the checkpoint (the training size).

    Raises:
        InputError: the file is unreadable, its settings are impossible (unknown preset,
            class names that do not match ``num_classes``), its weights do not fit the model
            or hold NaN or infinite values.
    """
    config, state = read_checkpoint(path)
    missing = [k for k in ("preset", "num_classes", "img_size") if config.get(k) is None]
    if missing:
        raise InputError(f"{path}: checkpoint lacks model settings {missing}")
    try:
        model = build_model(config["preset"], config["num_classes"], config.get("anchors"))
    except (ConfigError, ValueError, TypeError) as err:
        raise InputError(f"{path}: {one_line(err)}") from err
    _check_weights(path, model, state, config["preset"])
    # checkpoints from before the module recorded its names trained with the defaults
    names = config.get("class_names") or default_class_names(config["num_classes"])
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise InputError(f"{path}: class_names must be a list of names, got {names!r}")
    if len(names) != config["num_classes"]:
        raise InputError(f"{path}: {len(names)} class_names {list(names)} for num_classes "
                         f"{config['num_classes']}")
    detector = Detector(model, 32, names, config["preset"])
    try:
        detector.set_img_size(config["img_size"])
    except ConfigError as err:
        raise InputError(f"{path}: checkpoint {err}") from err
    if img_size is not None:
        detector.set_img_size(img_size)
    return detector


def average_detectors(paths: list[str | Path]) -> Detector:
    """The uniform average of several detectors' weights and BatchNorm statistics (a "model
    soup"; ``torch.optim.swa_utils.AveragedModel``).

    Useful for checkpoints of one lineage (a run and the model it was fine-tuned from, or the
    last checkpoints of one run): session 55 averaged the shipped ``small.pt`` with its 60-minute
    continuation (BENCHMARKS.md, issue 4). Models trained apart from scratch do not in general
    average into a working one.

    Returns:
        a detector with the first file's preset, anchors, class names and input size.

    Raises:
        ConfigError: fewer than two files.
        InputError: a file :func:`load_detector` cannot read, or whose preset, class names or
            anchors differ from the first file's.
    """
    from torch.optim.swa_utils import AveragedModel

    if len(paths) < 2:
        raise ConfigError(f"averaging needs two or more weight files, got {len(paths)}")
    first = load_detector(paths[0])
    averaged = AveragedModel(first.model, use_buffers=True)
    averaged.update_parameters(first.model)
    for path in paths[1:]:  # one model in memory at a time besides the running mean
        other = load_detector(path)
        for what, same in (("preset differs", other.preset == first.preset),
                           ("class names differ", other.class_names == first.class_names),
                           ("anchors differ", torch.equal(other.anchors, first.anchors))):
            if not same:
                raise InputError(f"{path}: its {what} from {paths[0]}'s; only detectors of "
                                 "one architecture and lineage can be averaged")
        averaged.update_parameters(other.model)
    return Detector(averaged.module, first.img_size, first.class_names, first.preset)


def _check_weights(path: str | Path, model: YOLO, state: dict[str, torch.Tensor],
                   preset: str) -> None:
    """Load ``state`` into ``model``; one-line InputError naming the first keys that do not
    fit, or the first tensor holding NaN or infinite values."""
    odd = [k for k, v in state.items() if not isinstance(v, torch.Tensor)]
    if odd:
        raise InputError(f"{path}: weights hold a {type(state[odd[0]]).__name__} at {odd[0]}, "
                         "not a tensor")
    own = model.state_dict()
    missing = [k for k in own if k not in state]
    unexpected = [k for k in state if k not in own]
    reshaped = [f"{k} {list(state[k].shape)} in the file, {list(own[k].shape)} in the model"
                for k in own if k in state and state[k].shape != own[k].shape]
    problems = [f"{what} {', '.join(keys[:3])}"
                + (f" (and {len(keys) - 3} more)" if len(keys) > 3 else "")
                for what, keys in (("missing", missing), ("unexpected", unexpected),
                                   ("other shape:", reshaped)) if keys]
    if problems:
        raise InputError(f"{path}: weights do not match preset {preset!r}: "
                         f"{'; '.join(problems)}")
    for key, value in state.items():
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise InputError(f"{path}: weights hold NaN or infinite values (first in {key})")
    model.load_state_dict(state)


def fit_detector(train_ann: str | Path | list, val_ann: str | Path, out_dir: str | Path, *,
                 preset: str = "nano", img_size: int = 320, max_minutes: float = 7.0,
                 max_epochs: int = 100, batch_size: int = 16, seed: int = 0,
                 progress: bool = True, mosaic_prob: float = 0.0, lr: float = 2e-3,
                 num_workers: int = 0, init_from: str | Path | None = None,
                 freeze_backbone: bool = False, resume: bool = False,
                 accelerator: str = "cpu", devices: int | str = 1,
                 checkpoint_every_n_steps: int = 50, val_every_n_epochs: int = 1,
                 log_every_n_steps: int = 10,
                 **module_kwargs: Any) -> Path:
    """Train a detector on COCO data within a wall-clock budget; return the best checkpoint.

    Anchors come from k-means on the training boxes (unless ``init_from`` supplies them);
    validation computes COCO mAP each epoch and the checkpoint with the best AP50 is kept.
    ``<out_dir>/checkpoints/last.ckpt`` is refreshed every ``checkpoint_every_n_steps`` so that
    ``resume=True`` continues an interrupted run.

    Args:
        train_ann: training ``annotations.json`` (or a list of them, mixed by size).
        val_ann: validation ``annotations.json``.
        out_dir: run folder (checkpoints, CSV and TensorBoard logs).
        preset: model size; img_size: square input side (px, multiple of 32).
        max_minutes: wall-clock limit of ``trainer.fit``; max_epochs: epoch limit.
        mosaic_prob: 4-image mosaic probability; lr: peak learning rate.
        init_from: checkpoint to fine-tune from; freeze_backbone: train neck and head only.
        val_every_n_epochs: validate (COCO mAP, best checkpoint) every n training epochs.
        log_every_n_steps: how often training losses go to the CSV / TensorBoard logs.
        module_kwargs: further :class:`DetectorModule` arguments.

    Returns:
        Path of the best checkpoint (Lightning ``.ckpt``).
    """
    import lightning as L

    from lunarnav_ml.data.datamodule import DetectionDataModule
    from lunarnav_ml.training.module import DetectorModule
    from lunarnav_ml.training.trainer import build_callbacks, build_loggers

    out_dir = Path(out_dir)
    L.seed_everything(seed, workers=True)
    dm = DetectionDataModule(train_ann, str(val_ann), img_size=img_size, batch_size=batch_size,
                             num_workers=num_workers, mosaic_prob=mosaic_prob)
    module = DetectorModule(preset=preset, img_size=img_size, lr=lr,
                            init_from=str(init_from) if init_from else None,
                            freeze_backbone=freeze_backbone, **module_kwargs)
    callbacks = build_callbacks(out_dir / "checkpoints", checkpoint_every_n_steps)
    trainer = L.Trainer(
        default_root_dir=out_dir, accelerator=accelerator, devices=devices,
        max_epochs=max_epochs, max_time=timedelta(minutes=max_minutes), callbacks=callbacks,
        logger=build_loggers(out_dir), enable_progress_bar=progress, num_sanity_val_steps=0,
        log_every_n_steps=log_every_n_steps, enable_model_summary=progress,
        check_val_every_n_epoch=val_every_n_epochs,
    )
    last = out_dir / "checkpoints" / "last.ckpt"
    trainer.fit(module, dm, ckpt_path=str(last) if resume and last.is_file() else None)
    best = trainer.checkpoint_callback.best_model_path
    if not best:
        raise InputError(f"{out_dir}: training ended before any validation; raise max_minutes")
    return Path(best)
