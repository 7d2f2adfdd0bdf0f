"""The YOLO detector: backbone -> neck -> head, raw maps out."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn


class YOLO(nn.Module):
    """A YOLOv4-style detector assembled from its parts.

    The anchors are a buffer (so checkpoints carry them, and k-means anchors computed at
    training time travel with the weights); they do not change the layer shapes.

    Args:
        backbone: returns one feature map per scale (``out_channels`` attribute).
        neck: fuses the backbone maps (``out_channels`` attribute).
        head: returns one raw map per scale.
        anchors: anchor (w, h) in input pixels, :math:`(L, A, 2)`.
        strides: pixels per cell of each scale.
        scale_xy: YOLOv4 grid-sensitivity factor per scale.
        num_classes: number of classes K.

    Shape:
        - Input: :math:`(B, 3, H, W)` float RGB in [0, 1]; H, W multiples of ``max(strides)``.
        - Output: list of :math:`(B, A (5 + K), H / s_i, W / s_i)` raw maps.
    """

    def __init__(self, backbone: nn.Module, neck: nn.Module, head: nn.Module,
                 anchors: torch.Tensor, strides: Sequence[int], scale_xy: Sequence[float],
                 num_classes: int) -> None:
        super().__init__()
        anchors = torch.as_tensor(anchors, dtype=torch.float32)
        if anchors.ndim != 3 or anchors.shape[0] != len(strides) or anchors.shape[2] != 2:
            raise ValueError(f"anchors must be (levels={len(strides)}, A, 2), got "
                             f"{tuple(anchors.shape)}")
        self.backbone, self.neck, self.head = backbone, neck, head
        self.register_buffer("anchors", anchors)
        self.strides = tuple(int(s) for s in strides)
        self.scale_xy = tuple(float(s) for s in scale_xy)
        self.num_classes = num_classes

    @property
    def num_anchors(self) -> int:
        """Anchors per scale."""
        return int(self.anchors.shape[1])

    def set_anchors(self, anchors: torch.Tensor) -> None:
        """Replace the anchors (same shape), e.g. with k-means anchors of a dataset."""
        anchors = torch.as_tensor(anchors, dtype=self.anchors.dtype, device=self.anchors.device)
        if anchors.shape != self.anchors.shape:
            raise ValueError(f"anchors must have shape {tuple(self.anchors.shape)}, "
                             f"got {tuple(anchors.shape)}")
        self.anchors.copy_(anchors)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        if x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"input must be (B, 3, H, W), got {tuple(x.shape)}")
        stride = max(self.strides)
        if x.shape[2] % stride or x.shape[3] % stride:
            raise ValueError(f"input height and width must be multiples of {stride}, "
                             f"got {tuple(x.shape[2:])}")
        return self.head(self.neck(self.backbone(x)))
