"""Training callbacks: fit the LR schedule into a wall-clock budget; the run's images/s."""

from __future__ import annotations

import time
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import Timer

from lunarnav_ml.errors import ConfigError
from lunarnav_ml.training.schedule import WarmupCosine


class TimeBudgetSchedule(L.Callback):
    """Shorten the cosine schedule so it ends when ``Trainer(max_time=...)`` stops training.

    After every training epoch (validation included), the steps that still fit in the remaining
    time are estimated from the pace so far, and the scheduler's ``total_steps`` is set to that
    (never above its configured length, ``max_steps``). The estimate may rise again when the
    pace picks up: the first epoch also decodes and caches the images, and other jobs may have
    shared the cores for a while; a plan fixed at its lowest would leave the rest of the budget
    at the schedule's floor.

    Args:
        margin: fraction of the remaining time kept free (final validation, checkpointing).
    """

    def __init__(self, margin: float = 0.05) -> None:
        self.margin = margin

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        timer = next((c for c in trainer.callbacks if isinstance(c, Timer)), None)
        if timer is None or not trainer.lr_scheduler_configs or trainer.global_step == 0:
            return
        remaining = timer.time_remaining("train")
        if remaining is None:
            return
        sched = trainer.lr_scheduler_configs[0].scheduler
        if not isinstance(sched, WarmupCosine):
            return
        pace = timer.time_elapsed("train") / trainer.global_step  # s per step, val included
        fit = trainer.global_step + int(max(0.0, remaining * (1 - self.margin)) / pace)
        sched.total_steps = max(trainer.global_step + 1, min(sched.max_steps, fit))
        pl_module.log("train/planned_steps", float(sched.total_steps))


class TrainingRate(L.Callback):
    """Log ``train/images_per_s``: training images per second of wall-clock time over the
    last ``window`` optimizer steps, everything between the steps included (waits for the
    loader, epoch ends, checkpoints) except validation. Not synchronised with a GPU, which
    runs at most a few steps behind, so windows of tens of steps read true. The first batch
    (start-up, compilation) starts the first window.

    Args:
        window: optimizer steps per figure; each figure is logged until the next replaces it.
    """

    def __init__(self, window: int = 50) -> None:
        if window < 1:
            raise ConfigError(f"TrainingRate window must be >= 1, got {window}")
        self.window = window
        self.rate: float | None = None
        self._start: float | None = None
        self._step = 0
        self._images = 0
        self._paused = 0.0
        self._val_start = 0.0

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule,
                           outputs: Any, batch: Any, batch_idx: int) -> None:
        now = time.perf_counter()
        if self._start is None:
            self._start, self._step = now, trainer.global_step
        else:
            self._images += len(batch[0])
            if trainer.global_step - self._step >= self.window:
                self.rate = self._images / max(now - self._start - self._paused, 1e-9)
                self._start, self._step, self._images, self._paused = (
                    now, trainer.global_step, 0, 0.0)
        if self.rate is not None:
            pl_module.log("train/images_per_s", self.rate)

    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._val_start = time.perf_counter()

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self._start is not None:
            self._paused += time.perf_counter() - self._val_start
