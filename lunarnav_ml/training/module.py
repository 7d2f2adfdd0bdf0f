"""The LightningModule: loss wiring, EMA, optimizer and schedule, COCO mAP validation."""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lunarnav_ml.data.coco import default_class_names
from lunarnav_ml.data.letterbox import LetterboxInfo
from lunarnav_ml.errors import ConfigError
from lunarnav_ml.losses import YOLOLoss, detection_kd_loss
from lunarnav_ml.losses.yolo_loss import PreparedTargets
from lunarnav_ml.models import build_model, decode, postprocess
from lunarnav_ml.training.checkpoint import load_weights, reanchor
from lunarnav_ml.training.ema import ModelEMA
from lunarnav_ml.training.schedule import WarmupCosine

Batch = tuple[torch.Tensor, list[dict[str, torch.Tensor]], list[dict[str, Any]]]

# the module's on_before_batch_transfer is meant to run with a DataModule beside it (it needs
# the model's anchors and strides); Lightning warns about every such pair
warnings.filterwarnings("ignore", message="You have overridden `on_before_batch_transfer` in "
                        "`LightningModule` but have passed in a `LightningDataModule`")


class DetectorModule(L.LightningModule):
    """Train and validate a YOLO detector.

    Args:
        preset: model size (``lunarnav_ml.models.PRESETS``).
        num_classes: K; category ids 1..K.
        class_names: name of each category id, in order.
        anchors: :math:`(L, 3, 2)` anchors in input px; ``None``: k-means on the DataModule's
            training boxes at setup (or the preset's reference anchors without a DataModule).
        img_size: training input side, px.
        optimizer: ``"adamw"`` or ``"sgd"`` (momentum, Nesterov).
        lr: peak learning rate.
        weight_decay: decay of conv/linear weights (not of norms and biases).
        momentum: SGD momentum, or AdamW beta1.
        warmup_steps: linear warm-up length in optimizer steps.
        min_lr_ratio: final LR as a fraction of ``lr`` (cosine end).
        ema_decay, ema_tau: weight EMA (validation and export use the EMA weights).
        label_smoothing, anchor_iou_thresh, ignore_thresh, box_weight, obj_weight, cls_weight,
            obj_iou_ratio: :class:`lunarnav_ml.losses.YOLOLoss` settings.
        multiscale: ``(min, max)`` input side in px for multi-scale training (multiples of 32),
            drawn per batch; ``None`` keeps ``img_size``.
        init_from: checkpoint (Lightning ``.ckpt`` or slim ``.pt``) whose weights start a
            fine-tuning run (anchors come with them).
        reanchor: with ``init_from``, :math:`(L, A, 2)` anchors that replace the loaded ones
            (``A`` at least the loaded count; the slots past it are added, copies of the
            nearest loaded anchor); each changed anchor's size biases move by the log of the
            old size over the new, so its boxes start where they were, and the assigner gives
            it the boxes of its new shape from the first step
            (:func:`~lunarnav_ml.training.checkpoint.reanchor`).
        freeze_backbone: keep the backbone's weights and BatchNorm statistics fixed.
        val_conf_thres, val_iou_thres: post-processing during validation.
        channels_last: model and batches in channels-last (NHWC) memory format; ``None``: on
            a GPU only (2.0-2.3x the model's training speed on an H100, where the NCHW
            BatchNorm kernels took three quarters of the step; on CPU slower in bf16).
        compile: run the training forward through ``torch.compile`` (the model compiled in
            place: same weights, same checkpoint keys); ``True`` for its default backend
            (inductor), or a backend's name. On a 2-core Xeon bf16 small-relu steps run 1.12x
            faster in a Lightning run after about a minute of compilation at the first step:
            it pays off in runs longer than about ten minutes.
        teacher: a trained detector (``.ckpt`` or ``.pt``) with the same classes, anchors and
            strides whose detections on each training batch are a second target
            (:func:`~lunarnav_ml.losses.detection_kd_loss`, logged as ``train/kd``): it keeps a
            model that differs from the teacher in a few layers (``lunarnav distill-stem``)
            close to what the teacher detects while the labels teach it. Not saved in the
            checkpoints.
        teacher_weight: the distillation term's weight in the loss.
    """

    def __init__(self, preset: str = "nano", num_classes: int = 3,
                 class_names: list[str] | None = None, anchors: list | None = None,
                 img_size: int = 320, optimizer: str = "adamw", lr: float = 2e-3,
                 weight_decay: float = 0.05, momentum: float = 0.9, warmup_steps: int = 50,
                 min_lr_ratio: float = 0.05, ema_decay: float = 0.9998, ema_tau: float = 300.0,
                 label_smoothing: float = 0.0, anchor_iou_thresh: float = 0.213,
                 ignore_thresh: float = 0.7, box_weight: float = 0.05, obj_weight: float = 1.0,
                 cls_weight: float = 0.02, obj_iou_ratio: float = 1.0,
                 multiscale: tuple[int, int] | None = None,
                 init_from: str | None = None, reanchor: list | None = None,
                 freeze_backbone: bool = False,
                 val_conf_thres: float = 0.001, val_iou_thres: float = 0.6,
                 channels_last: bool | None = None, compile: bool | str = False,
                 teacher: str | None = None, teacher_weight: float = 1.0) -> None:
        super().__init__()
        if optimizer not in ("adamw", "sgd"):
            raise ConfigError(f"optimizer must be 'adamw' or 'sgd', got {optimizer!r}")
        if not teacher_weight >= 0:
            raise ConfigError(f"teacher_weight must be >= 0, got {teacher_weight}")
        if reanchor is not None and not init_from:
            raise ConfigError("reanchor: replaces the anchors of an init_from checkpoint; "
                              "without one give anchors")
        class_names = list(class_names or default_class_names(num_classes))
        if len(class_names) != num_classes:
            raise ConfigError(f"class_names has {len(class_names)} names for {num_classes} classes")
        self.save_hyperparameters()
        # LightningCLI hands the parsed config to save_hyperparameters (class_names: null);
        # checkpoints keep the names actually used
        self.hparams.class_names = class_names
        self.model = build_model(preset, num_classes, anchors)
        self.ema = ModelEMA(self.model, ema_decay, ema_tau)
        self.loss = YOLOLoss(num_classes, anchor_iou_thresh, ignore_thresh, label_smoothing,
                             box_weight, obj_weight, cls_weight, obj_iou_ratio)
        self._val_results: list[dict[str, Any]] = []  # COCO results of this validation
        self._val_seen: set[int] = set()  # image ids validated this epoch
        self._val_gt: dict[str, Any] | None = None
        self._anchors_ready = anchors is not None
        self._channels_last = False  # decided at setup, when the device is known
        self._host_anchors = self.model.anchors.detach().clone()
        self._teacher: list[nn.Module] = []  # a list: not a submodule, kept out of checkpoints

    # ---- set-up -------------------------------------------------------------------------
    def setup(self, stage: str) -> None:
        if self.hparams.init_from:
            load_weights(self.model, self.hparams.init_from, self.hparams.preset)
            if self.hparams.get("reanchor") is not None:
                reanchor(self.model, self.hparams.reanchor)
            # a fresh average of the loaded model (reanchor may have added anchor slots)
            self.ema = ModelEMA(self.model, self.hparams.ema_decay, self.hparams.ema_tau)
            self._anchors_ready = True
        if not self._anchors_ready and stage == "fit":
            self._kmeans_anchors()
        if self.hparams.freeze_backbone:
            self.model.backbone.requires_grad_(False)
        # here, before a strategy wraps the model (DDP's gradient buckets follow its layout)
        flag = self.hparams.get("channels_last")  # absent from older checkpoints' settings
        on_gpu = self._trainer is not None and self.trainer.strategy.root_device.type == "cuda"
        self._channels_last = on_gpu if flag is None else bool(flag)
        if self._channels_last and stage == "fit":
            self.model.to(memory_format=torch.channels_last)
            self.ema.to(memory_format=torch.channels_last)
        # the host copy of the anchors for host_targets (k-means and init_from are done)
        self._host_anchors = self.model.anchors.detach().cpu()
        if self.hparams.get("teacher") and stage == "fit":
            self._load_teacher(self.hparams.teacher)
        backend = self.hparams.get("compile")
        if backend and stage == "fit":  # in place: the state_dict keeps its keys
            self.model.compile(**({"backend": backend} if isinstance(backend, str) else {}))

    def _load_teacher(self, path: str) -> None:
        from lunarnav_ml.training.api import load_detector

        teacher = load_detector(path).model
        own = self.model
        same = (teacher.anchors.shape == own.anchors.shape
                and torch.allclose(teacher.anchors.cpu(), own.anchors.detach().cpu())
                and list(teacher.strides) == list(own.strides)
                and teacher.head.num_outputs == own.head.num_outputs)
        if not same:
            raise ConfigError(f"teacher {path}: its classes, anchors or strides differ from the "
                              "model's (distillation compares the raw head maps cell by cell)")
        device = own.anchors.device if self._trainer is None else self.trainer.strategy.root_device
        teacher = teacher.to(device).eval().requires_grad_(False)
        if self._channels_last:
            teacher.to(memory_format=torch.channels_last)
        self._teacher = [teacher]

    def _kmeans_anchors(self) -> None:
        dm = getattr(self.trainer, "datamodule", None) if self._trainer else None
        if dm is None or not hasattr(dm, "kmeans_anchors"):
            return
        levels, per_level = self.model.anchors.shape[:2]
        anchors = torch.as_tensor(dm.kmeans_anchors(levels, per_level), dtype=torch.float32)
        self.model.set_anchors(anchors)
        self.ema.module.set_anchors(anchors)
        self.hparams.anchors = anchors.tolist()
        self._anchors_ready = True

    def on_train_epoch_start(self) -> None:
        if self.hparams.freeze_backbone:
            self.model.backbone.eval()  # frozen BatchNorm statistics too

    # ---- steps --------------------------------------------------------------------------
    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        return self.model(x)

    def on_train_start(self) -> None:
        # again after a resumed checkpoint's buffers are loaded (after setup)
        self._host_anchors = self.model.anchors.detach().cpu()

    def on_before_batch_transfer(self, batch: Batch, dataloader_idx: int) -> Any:
        """Training batches: draw the multi-scale side and prepare the loss's targets here,
        on the host, before the batch goes to the device (:meth:`YOLOLoss.prepare`: on a GPU
        the step then waits on nothing and the host queues work ahead)."""
        if self._trainer is None or not self.trainer.training:
            return batch
        images, targets, metas = batch
        side = self._train_side(images.shape[-1])
        targets = _scaled(targets, side / images.shape[-1])
        return (images, self.host_targets(targets, len(images), side, pin=images.is_pinned()),
                metas, side)

    def host_targets(self, targets: list[dict[str, torch.Tensor]], batch_size: int, side: int,
                     pin: bool = False) -> PreparedTargets:
        """The loss's targets of a training batch at input ``side``, prepared on the host
        (:meth:`YOLOLoss.prepare` with a host copy of the anchors), in pinned memory if
        ``pin``."""
        model = self.model
        grids = [(-(-side // s),) * 2 for s in model.strides]  # each stride-2 step rounds up
        prepared = self.loss.prepare(targets, batch_size, grids, self._host_anchors,
                                     model.strides, model.scale_xy)
        return prepared.pin_memory() if pin else prepared

    def _train_side(self, side: int) -> int:
        """The input side of a training batch: a multiple of 32 in ``multiscale``'s range,
        drawn per batch, or the loader's ``side``."""
        if not self.hparams.multiscale:
            return side
        lo, hi = (v // 32 for v in self.hparams.multiscale)
        return 32 * int(torch.randint(lo, hi + 1, (1,)))

    def _prepare(self, batch: Batch | tuple, train: bool) -> tuple[torch.Tensor, Any]:
        """Network input and targets of a batch: ``(images, targets, metas)``, or a training
        batch through :meth:`on_before_batch_transfer` (``(images, prepared targets, metas,
        side)``)."""
        if len(batch) == 4:
            images, targets, _, side = batch
        else:
            images, targets, _ = batch
            side = self._train_side(images.shape[-1]) if train else images.shape[-1]
            targets = _scaled(targets, side / images.shape[-1])
        x = images.float() / 255.0
        if self._channels_last or not train:  # inference is faster in it on a CPU too
            x = x.contiguous(memory_format=torch.channels_last)
        if side != x.shape[-1]:
            x = F.interpolate(x, size=(side, side), mode="bilinear", align_corners=False)
        return x, targets

    def _losses(self, model: nn.Module, x: torch.Tensor, targets: list[dict] | PreparedTargets
                ) -> dict[str, torch.Tensor]:
        raw = model(x)
        losses = self.loss(raw, targets, model.anchors, model.strides, model.scale_xy)
        if not self._teacher:
            return losses
        with torch.no_grad():
            target = self._teacher[0](x)
        kd = detection_kd_loss(raw, target, model.head.num_anchors)
        return {**losses, "kd": kd.detach(),
                "loss": losses["loss"] + self.hparams.teacher_weight * kd}

    def training_step(self, batch: Batch, batch_idx: int) -> torch.Tensor:
        x, targets = self._prepare(batch, train=True)
        losses = self._losses(self.model, x, targets)
        self.log_dict({f"train/{k}": v.detach() for k, v in losses.items()}, prog_bar=False,
                      batch_size=len(x))
        self.log("loss", losses["loss"].detach(), prog_bar=True, logger=False, batch_size=len(x))
        return losses["loss"]

    def optimizer_step(self, *args: Any, **kwargs: Any) -> None:
        super().optimizer_step(*args, **kwargs)
        self.ema.update(self.model)  # here, so checkpoints saved after this batch include it

    def validation_step(self, batch: Batch, batch_idx: int) -> None:
        x, targets = self._prepare(batch, train=False)
        model = self.ema.module
        raw = model(x)
        losses = self.loss(raw, targets, model.anchors, model.strides, model.scale_xy)
        self.log("val/loss", losses["loss"], batch_size=len(x), sync_dist=True)
        preds = postprocess(decode(raw, model.anchors, model.strides, model.scale_xy),
                            self.hparams.val_conf_thres, self.hparams.val_iou_thres)
        for pred, meta in zip(preds, batch[2]):
            self._val_results.extend(_coco_results(pred, meta))
        self._val_seen |= {m["image_id"] for m in batch[2]}

    def on_validation_epoch_start(self) -> None:
        self._val_results, self._val_seen = [], set()

    def on_validation_epoch_end(self) -> None:
        results, seen = _gather(self._val_results), set(_gather(sorted(self._val_seen)))
        if self.trainer.sanity_checking or not seen:
            return
        from lunarnav_ml.eval.coco_metrics import coco_ap

        gt = _subset(self._ground_truth(), seen)
        metrics = coco_ap(gt, results)
        self.log("val/mAP", metrics["mAP"], sync_dist=False, prog_bar=False)
        self.log("val/AP50", metrics["AP50"], sync_dist=False, prog_bar=True)
        for name, m in metrics["per_class"].items():
            if m["AP50"] is not None:
                self.log(f"val/AP50_{name}", m["AP50"], sync_dist=False)

    def _ground_truth(self) -> dict[str, Any]:
        if self._val_gt is None:
            dm = self.trainer.datamodule
            self._val_gt = json.loads(Path(dm.val_set.ann_file).read_text())
        return self._val_gt

    # ---- optimization -------------------------------------------------------------------
    def configure_optimizers(self) -> dict[str, Any]:
        hp = self.hparams
        decay, no_decay = [], []
        for name, p in self.model.named_parameters():
            if p.requires_grad:
                (decay if p.ndim > 1 else no_decay).append(p)
        groups = [{"params": decay, "weight_decay": hp.weight_decay},
                  {"params": no_decay, "weight_decay": 0.0}]
        if hp.optimizer == "adamw":
            opt = torch.optim.AdamW(groups, lr=hp.lr, betas=(hp.momentum, 0.999))
        else:
            opt = torch.optim.SGD(groups, lr=hp.lr, momentum=hp.momentum, nesterov=True)
        total = self.trainer.estimated_stepping_batches
        total = int(total) if np.isfinite(total) else 100_000
        sched = WarmupCosine(opt, total, hp.warmup_steps, hp.min_lr_ratio)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["hyper_parameters"]["anchors"] = self.model.anchors.tolist()


def _scaled(targets: list[dict[str, torch.Tensor]], ratio: float) -> list[dict[str, torch.Tensor]]:
    """Targets of an input resized by ``ratio``."""
    return targets if ratio == 1 else [{**t, "boxes": t["boxes"] * ratio} for t in targets]


def _coco_results(pred: dict[str, torch.Tensor], meta: dict[str, Any]) -> list[dict[str, Any]]:
    """One image's predictions in original pixels as COCO results."""
    info = LetterboxInfo(meta["scale"], *meta["pad"])
    h, w = meta["size"]
    boxes = info.to_original(pred["boxes"].detach().float().cpu().numpy(), w, h)
    return [{"image_id": meta["image_id"], "category_id": int(label),
             "bbox": [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])],
             "score": float(score)}
            for b, score, label in zip(boxes, pred["scores"].tolist(), pred["labels"].tolist())
            if b[2] > b[0] and b[3] > b[1]]


def _gather(items: list) -> list:
    """Concatenate a Python list across DDP ranks (identity in a single process)."""
    if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
        return items
    parts: list[list] = [None] * torch.distributed.get_world_size()  # type: ignore[list-item]
    torch.distributed.all_gather_object(parts, items)
    return [x for part in parts for x in part]


def _subset(gt: dict[str, Any], image_ids: set[int]) -> dict[str, Any]:
    """The ground truth restricted to some images (validation on a subset of batches)."""
    return {**gt, "images": [i for i in gt["images"] if i["id"] in image_ids],
            "annotations": [a for a in gt["annotations"] if a["image_id"] in image_ids]}
