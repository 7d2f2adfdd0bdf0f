"""Exponential moving average of model weights (YOLOv4/v5 ``ModelEMA``)."""

from __future__ import annotations

import copy
import math

import torch
from torch import nn


class ModelEMA(nn.Module):
    """A frozen copy of a model whose weights follow the training weights.

    ``decay_t = decay * (1 - exp(-t / tau))`` after ``t`` updates, so the average follows the
    model closely early on and smooths more as training settles. Buffers (BatchNorm running
    statistics) are averaged too. Being an ``nn.Module``, it is saved in and restored from
    checkpoints with its update count.

    Args:
        model: the model being trained.
        decay: asymptotic decay.
        tau: ramp-up constant, in updates.
    """

    def __init__(self, model: nn.Module, decay: float = 0.9998, tau: float = 500.0) -> None:
        super().__init__()
        # Its forward runs only under validation, where Lightning switches it to eval mode.
        self.module = copy.deepcopy(model)
        for p in self.module.parameters():
            p.requires_grad_(False)
        self.decay, self.tau = decay, tau
        self.register_buffer("updates", torch.zeros((), dtype=torch.long))
        # the count on the host too: reading the buffer each step would wait for the device
        self._count: int | None = None
        self.register_load_state_dict_post_hook(_forget_count)

    def _updates(self) -> int:
        if self._count is None:
            self._count = int(self.updates)
        return self._count

    def current_decay(self) -> float:
        """Decay used by the next update."""
        return self.decay * (1 - math.exp(-self._updates() / self.tau))

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """Move the averaged weights towards ``model``'s."""
        self._count = self._updates() + 1
        self.updates.fill_(self._count)
        d = self.current_decay()
        src = model.state_dict()
        avg, new = [], []
        for name, value in self.module.state_dict().items():
            if value.dtype.is_floating_point:
                avg.append(value)
                new.append(src[name].detach())
            else:
                value.copy_(src[name])
        # one fused call for all tensors (a GPU step otherwise pays two launches per tensor)
        torch._foreach_lerp_(avg, new, 1 - d)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        return self.module(x)


def _forget_count(module: ModelEMA, incompatible_keys) -> None:
    """After a checkpoint is loaded, read the update count from the buffer again."""
    module._count = None
