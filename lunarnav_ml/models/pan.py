"""Necks: YOLOv4's SPP + PAN over three scales, and YOLOv4-tiny's two-scale FPN."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from lunarnav_ml.models.blocks import SPP, ConvBNAct, conv_stack


def _upsample(x: torch.Tensor) -> torch.Tensor:
    return F.interpolate(x, scale_factor=2.0, mode="nearest")


class YOLOv4PAN(nn.Module):
    """SPP on the stride-32 map, then a top-down FPN and a bottom-up PAN path (YOLOv4).

    Args:
        in_channels: backbone widths at strides 8, 16, 32 (YOLOv4: 256, 512, 1024).
        pairs: 1x1/3x3 pairs in each conv stack (YOLOv4: 2, i.e. five convolutions).
        act: activation name (YOLOv4 neck: leaky).

    Shape:
        - Input: three maps :math:`(B, C_i, H/s_i, W/s_i)`, s = 8, 16, 32.
        - Output: three maps with ``out_channels`` = ``in_channels // 2`` channels.
    """

    def __init__(self, in_channels: tuple[int, int, int], pairs: int = 2, act: str = "leaky"):
        super().__init__()
        c3, c4, c5 = (c // 2 for c in in_channels)
        self.pre_spp = conv_stack(in_channels[2], c5, 1, act)
        self.spp = SPP()
        self.post_spp = conv_stack(4 * c5, c5, 1, act)
        self.lat5 = ConvBNAct(c5, c4, 1, act=act)
        self.lat4_in = ConvBNAct(in_channels[1], c4, 1, act=act)
        self.td4 = conv_stack(2 * c4, c4, pairs, act)
        self.lat4 = ConvBNAct(c4, c3, 1, act=act)
        self.lat3_in = ConvBNAct(in_channels[0], c3, 1, act=act)
        self.td3 = conv_stack(2 * c3, c3, pairs, act)
        self.down3 = ConvBNAct(c3, c4, 3, 2, act=act)
        self.bu4 = conv_stack(2 * c4, c4, pairs, act)
        self.down4 = ConvBNAct(c4, c5, 3, 2, act=act)
        self.bu5 = conv_stack(2 * c5, c5, pairs, act)
        self.out_channels = (c3, c4, c5)

    def forward(self, feats: list[torch.Tensor]) -> list[torch.Tensor]:
        x3, x4, x5 = feats
        p5 = self.post_spp(self.spp(self.pre_spp(x5)))
        p4 = self.td4(torch.cat([self.lat4_in(x4), _upsample(self.lat5(p5))], dim=1))
        n3 = self.td3(torch.cat([self.lat3_in(x3), _upsample(self.lat4(p4))], dim=1))
        n4 = self.bu4(torch.cat([self.down3(n3), p4], dim=1))
        n5 = self.bu5(torch.cat([self.down4(n4), p5], dim=1))
        return [n3, n4, n5]


class TinyFPN(nn.Module):
    """YOLOv4-tiny neck: a 1x1 conv on the stride-32 map, upsampled and concatenated with the
    stride-16 route.

    Shape:
        - Input: maps :math:`(B, C_{16}, H/16, W/16)` and :math:`(B, C_{32}, H/32, W/32)`.
        - Output: maps with ``out_channels`` = ``(C_{16} + C_{32} / 4, C_{32} / 2)``.
    """

    def __init__(self, in_channels: tuple[int, int], act: str = "leaky") -> None:
        super().__init__()
        c16, c32 = in_channels
        self.reduce = ConvBNAct(c32, c32 // 2, 1, act=act)
        self.lat = ConvBNAct(c32 // 2, c32 // 4, 1, act=act)
        self.out_channels = (c16 + c32 // 4, c32 // 2)

    def forward(self, feats: list[torch.Tensor]) -> list[torch.Tensor]:
        x16, x32 = feats
        p5 = self.reduce(x32)
        p4 = torch.cat([_upsample(self.lat(p5)), x16], dim=1)
        return [p4, p5]
