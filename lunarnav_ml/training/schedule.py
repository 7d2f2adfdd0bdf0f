"""Learning-rate schedule: linear warm-up then cosine decay, with an adjustable length."""

from __future__ import annotations

import math

import torch
from torch.optim.lr_scheduler import LRScheduler


class WarmupCosine(LRScheduler):
    """Per-step LR: linear warm-up from ``warmup_start * lr`` to ``lr`` over ``warmup_steps``,
    then cosine down to ``min_ratio * lr`` at ``total_steps``, constant afterwards.

    ``total_steps`` is an attribute saved in ``state_dict`` (so a resumed run continues the
    same curve); a time budget may shorten it, up to ``max_steps`` (see
    :class:`lunarnav_ml.training.callbacks.TimeBudgetSchedule`).
    """

    def __init__(self, optimizer: torch.optim.Optimizer, total_steps: int, warmup_steps: int = 100,
                 min_ratio: float = 0.05, warmup_start: float = 0.01, last_epoch: int = -1) -> None:
        self.total_steps = max(1, int(total_steps))
        self.max_steps = self.total_steps  # the configured length: a time budget stays under it
        self.warmup_steps = max(0, int(warmup_steps))
        self.min_ratio, self.warmup_start = min_ratio, warmup_start
        super().__init__(optimizer, last_epoch)

    def factor(self, step: int) -> float:
        """LR multiplier at optimizer step ``step``."""
        warm = min(self.warmup_steps, self.total_steps // 2)
        if step < warm:
            return self.warmup_start + (1 - self.warmup_start) * step / warm
        progress = min(1.0, (step - warm) / max(1, self.total_steps - warm))
        return self.min_ratio + (1 - self.min_ratio) * 0.5 * (1 + math.cos(math.pi * progress))

    def get_lr(self) -> list[float]:
        f = self.factor(self.last_epoch)
        return [base * f for base in self.base_lrs]
