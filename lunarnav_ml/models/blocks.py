"""Building blocks shared by the backbones and necks: conv-BN-activation, residual and CSP
blocks, SPP."""

from __future__ import annotations

import torch
from torch import nn


def make_act(name: str) -> nn.Module:
    """Activation by name: ``"mish"`` (YOLOv4 backbone), ``"leaky"`` (neck, head), ``"relu"``
    (int8-friendly: it folds into a quantized convolution) or ``"silu"``."""
    if name == "mish":
        return nn.Mish(inplace=True)
    if name == "leaky":
        return nn.LeakyReLU(0.1, inplace=True)
    if name == "relu":
        return nn.ReLU(inplace=True)
    if name == "silu":
        return nn.SiLU(inplace=True)
    raise ValueError(f"unknown activation {name!r}; expected 'mish', 'leaky', 'relu' or 'silu'")


class ConvBNAct(nn.Sequential):
    """Conv2d (no bias, 'same' padding unless ``p`` is given) -> BatchNorm2d -> activation.

    Shape:
        - Input: :math:`(B, C_{in}, H, W)`
        - Output: :math:`(B, C_{out}, H / s, W / s)` with ``s`` the stride.
    """

    def __init__(self, c_in: int, c_out: int, k: int = 1, s: int = 1, act: str = "mish",
                 p: int | None = None) -> None:
        super().__init__(
            nn.Conv2d(c_in, c_out, k, s, padding=k // 2 if p is None else p, bias=False),
            nn.BatchNorm2d(c_out, eps=1e-3, momentum=0.1),
            make_act(act),
        )


class ResBlock(nn.Module):
    """Darknet residual unit: 1x1 conv then 3x3 conv, added to the input.

    Shape:
        - Input: :math:`(B, C, H, W)`; Output: same.
    """

    def __init__(self, c: int, act: str = "mish") -> None:
        super().__init__()
        self.conv1 = ConvBNAct(c, c, 1, act=act)
        self.conv2 = ConvBNAct(c, c, 3, act=act)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(self.conv1(x))


class CSPStage(nn.Module):
    """One CSPDarknet53 stage: stride-2 3x3 conv, then a cross-stage-partial split where one
    half passes ``n`` residual units and the other half bypasses them.

    Shape:
        - Input: :math:`(B, C_{in}, H, W)`
        - Output: :math:`(B, C_{out}, H / 2, W / 2)`
    """

    def __init__(self, c_in: int, c_out: int, n: int, act: str = "mish") -> None:
        super().__init__()
        hidden = c_out // 2
        self.down = ConvBNAct(c_in, c_out, 3, 2, act=act)
        self.split_main = ConvBNAct(c_out, hidden, 1, act=act)
        self.split_skip = ConvBNAct(c_out, hidden, 1, act=act)
        self.blocks = nn.Sequential(*(ResBlock(hidden, act) for _ in range(n)))
        self.post = ConvBNAct(hidden, hidden, 1, act=act)
        self.fuse = ConvBNAct(2 * hidden, c_out, 1, act=act)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.down(x)
        main = self.post(self.blocks(self.split_main(x)))
        return self.fuse(torch.cat([main, self.split_skip(x)], dim=1))


class SPP(nn.Module):
    """Spatial pyramid pooling (YOLOv4): the input concatenated with stride-1 max pools.

    Shape:
        - Input: :math:`(B, C, H, W)`
        - Output: :math:`(B, C (1 + K), H, W)` with ``K = len(kernels)``.
    """

    def __init__(self, kernels: tuple[int, ...] = (5, 9, 13)) -> None:
        super().__init__()
        self.pools = nn.ModuleList(nn.MaxPool2d(k, 1, k // 2) for k in kernels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([x] + [pool(x) for pool in self.pools], dim=1)


def conv_stack(c_in: int, c_mid: int, pairs: int, act: str = "leaky") -> nn.Sequential:
    """YOLOv4's alternating 1x1 / 3x3 conv stack, ending on a 1x1 conv to ``c_mid`` channels.

    ``pairs`` (1x1, 3x3) pairs precede the final 1x1 (YOLOv4 uses two: five convolutions).

    Shape:
        - Input: :math:`(B, C_{in}, H, W)`; Output: :math:`(B, C_{mid}, H, W)`.
    """
    layers: list[nn.Module] = []
    c = c_in
    for _ in range(pairs):
        layers += [ConvBNAct(c, c_mid, 1, act=act), ConvBNAct(c_mid, 2 * c_mid, 3, act=act)]
        c = 2 * c_mid
    layers.append(ConvBNAct(c, c_mid, 1, act=act))
    return nn.Sequential(*layers)
