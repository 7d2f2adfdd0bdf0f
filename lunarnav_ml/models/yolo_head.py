"""YOLO detection head: per scale a 3x3 conv and a 1x1 prediction conv, raw maps out."""

from __future__ import annotations

import math

import torch
from torch import nn

from lunarnav_ml.models.blocks import ConvBNAct


class YOLOHead(nn.Module):
    """One prediction branch per scale; outputs raw (pre-sigmoid) maps.

    Each map holds, per anchor, ``(tx, ty, tw, th, objectness, class logits...)``; decoding
    lives in :mod:`lunarnav_ml.models.decode` and target assignment in :mod:`lunarnav_ml.losses`.

    Args:
        in_channels: neck widths per scale.
        num_anchors: anchors per scale.
        num_classes: number of classes.
        strides: stride of each scale in pixels (used only for the objectness bias prior).
        hidden_channels: width of each scale's 3x3 conv (default twice its input width).
        act: activation of the 3x3 conv.

    Shape:
        - Input: maps :math:`(B, C_i, H_i, W_i)`.
        - Output: maps :math:`(B, A (5 + K), H_i, W_i)`; channel ``a (5 + K) + j`` is field
          ``j`` of anchor ``a``.
    """

    def __init__(self, in_channels: tuple[int, ...], num_anchors: int, num_classes: int,
                 strides: tuple[int, ...], hidden_channels: tuple[int, ...] | None = None,
                 act: str = "leaky") -> None:
        super().__init__()
        hidden = hidden_channels or tuple(2 * c for c in in_channels)
        self.num_anchors = num_anchors
        self.num_outputs = 5 + num_classes
        self.convs = nn.ModuleList(ConvBNAct(c, h, 3, act=act) for c, h in zip(in_channels, hidden))
        self.preds = nn.ModuleList(nn.Conv2d(h, num_anchors * self.num_outputs, 1) for h in hidden)
        self._init_bias(strides, num_classes)

    def _init_bias(self, strides: tuple[int, ...], num_classes: int) -> None:
        """Prior biases: ~8 objects per 640 px image, class probability ~0.6/K (so early
        objectness and class losses start near their converged scale)."""
        for pred, stride in zip(self.preds, strides):
            bias = pred.bias.detach().view(self.num_anchors, self.num_outputs)
            bias[:, 4] = math.log(8 / (640 / stride) ** 2)
            bias[:, 5:] = math.log(0.6 / max(num_classes - 0.99, 0.01))
            pred.bias = nn.Parameter(bias.view(-1).clone())

    def add_anchors(self, sources: list[list[int]]) -> None:
        """Add anchor slots to every scale: scale ``i`` gains ``len(sources[i])`` (the same count
        at every scale), each a copy of the prediction channels (weights and biases) of the
        existing anchor ``sources[i][k]``."""
        if len({len(s) for s in sources}) != 1 or len(sources) != len(self.preds):
            raise ValueError(f"one list of source anchors per scale ({len(self.preds)}), all "
                             f"of one length; got {sources}")
        per = self.num_outputs
        for level, pred in enumerate(self.preds):
            slots = list(range(self.num_anchors)) + list(sources[level])
            index = torch.cat([torch.arange(a * per, (a + 1) * per) for a in slots])
            wide = nn.Conv2d(pred.in_channels, len(slots) * per, 1).to(pred.weight)
            with torch.no_grad():
                wide.weight.copy_(pred.weight[index.to(pred.weight.device)])
                wide.bias.copy_(pred.bias[index.to(pred.bias.device)])
            self.preds[level] = wide
        self.num_anchors += len(sources[0])

    def forward(self, feats: list[torch.Tensor]) -> list[torch.Tensor]:
        return [pred(conv(x)) for x, conv, pred in zip(feats, self.convs, self.preds)]
