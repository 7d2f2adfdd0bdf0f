"""Trainer parts shared by ``fit_detector`` and ``train.py``: callbacks and loggers."""

from __future__ import annotations

from pathlib import Path

from lightning.pytorch.callbacks import Callback, LearningRateMonitor, ModelCheckpoint
from lightning.pytorch.loggers import CSVLogger, Logger, TensorBoardLogger

from lunarnav_ml.training.callbacks import TimeBudgetSchedule

MONITOR = "val/AP50"  # the best checkpoint maximises COCO AP at IoU 0.5 on validation


def build_callbacks(ckpt_dir: Path, every_n_steps: int = 50) -> list[Callback]:
    """Best-AP50 checkpoint, a ``last.ckpt`` refreshed every ``every_n_steps`` (resume), LR
    logging, and the time-budget schedule."""
    best = ModelCheckpoint(dirpath=ckpt_dir, filename="best-{epoch:03d}-{step:06d}",
                           monitor=MONITOR, mode="max", save_top_k=1, auto_insert_metric_name=False)
    last = ModelCheckpoint(dirpath=ckpt_dir, filename="last", every_n_train_steps=every_n_steps,
                           save_top_k=0, save_last=True, save_on_train_epoch_end=True)
    return [best, last, LearningRateMonitor("step"), TimeBudgetSchedule()]


def build_loggers(out_dir: Path) -> list[Logger]:
    """CSV and TensorBoard logs under ``out_dir``."""
    return [CSVLogger(out_dir, name="csv"), TensorBoardLogger(out_dir, name="tensorboard")]
