"""Backbones: CSPDarknet53 (YOLOv4) and the CSP-tiny backbone (YOLOv4-tiny)."""

from __future__ import annotations

import torch
from torch import nn

from lunarnav_ml.models.blocks import ConvBNAct, CSPStage


class CSPDarknet(nn.Module):
    """CSPDarknet53 with Mish, scaled by channel widths and residual-block counts.

    Args:
        channels: stem width then the five stage widths (YOLOv4: 32, 64, 128, 256, 512, 1024).
        blocks: residual units per stage (YOLOv4: 1, 2, 8, 8, 4).
        act: activation name.
        stem: ``"full"``, YOLOv4's 3x3 convolution at full resolution before stage 0; or
            ``"s2"``, a 6x6 stride-2 convolution (``2 * channels[0]`` wide, YOLOv5's) and a
            3x3 convolution to ``channels[1]`` in place of that stem and all of stage 0: no
            layer at full resolution and no 12-channel layer at half, which onnxruntime's
            integer convolutions run slower than fp32 (the int8 export reads the 6x6
            convolution as a space-to-depth input: ``export.graph_passes``).

    Shape:
        - Input: :math:`(B, 3, H, W)`, H and W multiples of 32.
        - Output: three maps at strides 8, 16, 32 with ``channels[3:]`` channels.
    """

    def __init__(self, channels: tuple[int, ...], blocks: tuple[int, ...], act: str = "mish",
                 stem: str = "full"):
        super().__init__()
        if len(channels) != 6 or len(blocks) != 5:
            raise ValueError(f"CSPDarknet needs 6 widths and 5 block counts, got {channels}, {blocks}")
        if stem not in ("full", "s2"):
            raise ValueError(f"stem: expected 'full' or 's2', got {stem!r}")
        if stem == "full":
            self.stem: nn.Module = ConvBNAct(3, channels[0], 3, act=act)
            first: nn.Module = CSPStage(channels[0], channels[1], blocks[0], act)
        else:
            self.stem = nn.Sequential(ConvBNAct(3, 2 * channels[0], 6, 2, act, p=2),
                                      ConvBNAct(2 * channels[0], channels[1], 3, act=act))
            first = nn.Identity()
        self.stages = nn.ModuleList(
            [first, *(CSPStage(channels[i], channels[i + 1], blocks[i], act) for i in range(1, 5))])
        self.out_channels = tuple(channels[3:])
        self.strides = (8, 16, 32)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = self.stem(x)
        outs = []
        for i, stage in enumerate(self.stages):
            x = stage(x)
            if i >= 2:
                outs.append(x)
        return outs


class TinyCSPBlock(nn.Module):
    """YOLOv4-tiny CSP block: 3x3 conv, route the second half through two 3x3 convs, fuse.

    Returns both the block output (before the 2x2 max pool) and the fused partial map that
    YOLOv4-tiny routes to the neck.

    Shape:
        - Input: :math:`(B, C, H, W)`
        - Output: :math:`(B, 2C, H/2, W/2)` pooled map and :math:`(B, C, H, W)` route map.
    """

    def __init__(self, c: int, act: str = "leaky") -> None:
        super().__init__()
        self.conv = ConvBNAct(c, c, 3, act=act)
        self.part1 = ConvBNAct(c // 2, c // 2, 3, act=act)
        self.part2 = ConvBNAct(c // 2, c // 2, 3, act=act)
        self.fuse = ConvBNAct(c, c, 1, act=act)
        self.pool = nn.MaxPool2d(2, 2)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.conv(x)
        half = x.shape[1] // 2
        p1 = self.part1(x[:, half:])
        p2 = self.part2(p1)
        route = self.fuse(torch.cat([p2, p1], dim=1))
        return self.pool(torch.cat([x, route], dim=1)), route


class TinyDarknet(nn.Module):
    """CSP-tiny backbone in the spirit of YOLOv4-tiny (two strided stem convs, three CSP-tiny
    blocks, a 3x3 conv at stride 32).

    Args:
        width: base width (YOLOv4-tiny: 32 -> stage widths 64, 128, 256, 512).
        act: activation name (YOLOv4-tiny: leaky).

    Shape:
        - Input: :math:`(B, 3, H, W)`, H and W multiples of 32.
        - Output: maps at strides 16 (``8 * width`` ch) and 32 (``16 * width`` ch).
    """

    def __init__(self, width: int = 32, act: str = "leaky") -> None:
        super().__init__()
        w = width
        self.stem = nn.Sequential(ConvBNAct(3, w, 3, 2, act), ConvBNAct(w, 2 * w, 3, 2, act))
        self.block1 = TinyCSPBlock(2 * w, act)
        self.block2 = TinyCSPBlock(4 * w, act)
        self.block3 = TinyCSPBlock(8 * w, act)
        self.head_conv = ConvBNAct(16 * w, 16 * w, 3, act=act)
        self.out_channels = (8 * w, 16 * w)
        self.strides = (16, 32)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        x, _ = self.block1(self.stem(x))
        x, _ = self.block2(x)
        x, route16 = self.block3(x)
        return [route16, self.head_conv(x)]
