"""Element-wise box IoU and Complete-IoU (CIoU, Zheng et al. 2020) for the box loss."""

from __future__ import annotations

import math

import torch


def ciou(pred: torch.Tensor, target: torch.Tensor, eps: float = 1e-7
         ) -> tuple[torch.Tensor, torch.Tensor]:
    """Complete IoU and plain IoU of paired boxes.

    ``CIoU = IoU - rho^2 / c^2 - alpha v`` with ``rho`` the centre distance, ``c`` the
    diagonal of the enclosing box, ``v`` the aspect-ratio consistency term and
    ``alpha = v / (1 - IoU + v)`` (not differentiated through, as in the paper).

    Args:
        pred: :math:`(N, 4)` boxes ``(cx, cy, w, h)``.
        target: :math:`(N, 4)` boxes ``(cx, cy, w, h)``, same units.

    Returns:
        ``(ciou, iou)``, each :math:`(N,)`; CIoU lies in (-1.5, 1].
    """
    p1, p2 = pred[:, :2] - pred[:, 2:] / 2, pred[:, :2] + pred[:, 2:] / 2
    t1, t2 = target[:, :2] - target[:, 2:] / 2, target[:, :2] + target[:, 2:] / 2
    inter = (torch.min(p2, t2) - torch.max(p1, t1)).clamp(min=0).prod(dim=1)
    union = pred[:, 2:].prod(dim=1) + target[:, 2:].prod(dim=1) - inter + eps
    iou = inter / union
    c2 = (torch.max(p2, t2) - torch.min(p1, t1)).pow(2).sum(dim=1) + eps
    rho2 = (pred[:, :2] - target[:, :2]).pow(2).sum(dim=1)
    v = (4 / math.pi**2) * (torch.atan(target[:, 2] / (target[:, 3] + eps))
                            - torch.atan(pred[:, 2] / (pred[:, 3] + eps))).pow(2)
    with torch.no_grad():
        alpha = v / (1 - iou + v + eps)
    return iou - rho2 / c2 - alpha * v, iou


def wh_iou(wh1: torch.Tensor, wh2: torch.Tensor) -> torch.Tensor:
    """IoU of boxes sharing a centre, from their sizes only (anchor matching).

    Shape:
        - wh1: :math:`(N, 2)`, wh2: :math:`(M, 2)`
        - Output: :math:`(N, M)`
    """
    inter = torch.min(wh1[:, None], wh2[None]).prod(dim=2)
    return inter / (wh1.prod(dim=1)[:, None] + wh2.prod(dim=1)[None] - inter)


def batched_box_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """IoU of every box of ``a`` with every box of ``b``, image by image.

    Shape:
        - a: :math:`(B, N, 4)` ``(x0, y0, x1, y1)``; b: :math:`(B, G, 4)`, same units.
        - Output: :math:`(B, N, G)` (torchvision's ``box_iou`` per image).
    """
    area_a = (a[..., 2] - a[..., 0]) * (a[..., 3] - a[..., 1])
    area_b = (b[..., 2] - b[..., 0]) * (b[..., 3] - b[..., 1])
    lt = torch.max(a[:, :, None, :2], b[:, None, :, :2])
    rb = torch.min(a[:, :, None, 2:], b[:, None, :, 2:])
    wh = (rb - lt).clamp(min=0)
    inter = wh[..., 0] * wh[..., 1]
    return inter / (area_a[:, :, None] + area_b[:, None, :] - inter)
