"""Training callbacks: fit the LR schedule into a wall-clock budget."""

from __future__ import annotations

import lightning as L
from lightning.pytorch.callbacks import Timer

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
