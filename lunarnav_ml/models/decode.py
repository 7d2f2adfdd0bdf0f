"""Decode raw YOLO head maps into boxes, and NMS post-processing.

``decode`` is pure tensor arithmetic (no Python loop over boxes) so it exports to ONNX;
``postprocess`` runs torchvision's batched NMS per image.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torchvision.ops import batched_nms, box_convert

# exp(tw) is clamped here: a box at most e^4 ~ 55x its anchor (keeps early training finite).
MAX_LOG_WH = 4.0


def split_raw(raw: torch.Tensor, num_anchors: int) -> torch.Tensor:
    """Reshape one raw head map to one row of fields per anchor and cell.

    Shape:
        - raw: :math:`(B, A (5 + K), H, W)`
        - Output: :math:`(B, A, H, W, 5 + K)`
    """
    b, c, h, w = raw.shape
    if c % num_anchors:
        raise ValueError(f"raw map has {c} channels, not a multiple of {num_anchors} anchors")
    return raw.view(b, num_anchors, c // num_anchors, h, w).permute(0, 1, 3, 4, 2)


def decode_xywh(t: torch.Tensor, anchors: torch.Tensor, stride: int, scale_xy: float
                ) -> torch.Tensor:
    """Box centres and sizes in input pixels from raw ``(tx, ty, tw, th)``.

    Centre: ``((sigmoid(t) * s - (s - 1) / 2) + cell) * stride`` (YOLOv4 grid-sensitivity fix
    ``scale_x_y = s``); size: ``anchor * exp(t)``.

    Args:
        t: raw box fields, :math:`(B, A, H, W, 4)`.
        anchors: this scale's anchors (w, h) in pixels, :math:`(A, 2)`.
        stride: pixels per cell.
        scale_xy: grid-sensitivity factor (1 = original YOLOv3).

    Returns:
        :math:`(B, A, H, W, 4)` boxes ``(cx, cy, w, h)`` in pixels.
    """
    _, _, h, w, _ = t.shape
    ys = torch.arange(h, device=t.device, dtype=t.dtype)
    xs = torch.arange(w, device=t.device, dtype=t.dtype)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)  # (H, W, 2) as (x, y)
    xy = (t[..., :2].sigmoid() * scale_xy - 0.5 * (scale_xy - 1.0) + grid) * stride
    wh = torch.exp(t[..., 2:4].clamp(max=MAX_LOG_WH)) * anchors.to(t).view(1, -1, 1, 1, 2)
    return torch.cat([xy, wh], dim=-1)


def decode(raw: Sequence[torch.Tensor], anchors: torch.Tensor, strides: Sequence[int],
           scale_xy: Sequence[float]) -> torch.Tensor:
    """Decode every scale's raw map into one table of candidate boxes.

    Args:
        raw: per scale :math:`(B, A (5 + K), H_i, W_i)` raw head maps.
        anchors: :math:`(L, A, 2)` anchor (w, h) in input pixels per scale.
        strides: pixels per cell for each scale.
        scale_xy: grid-sensitivity factor per scale.

    Returns:
        :math:`(B, N, 5 + K)` rows ``(cx, cy, w, h, objectness, class probabilities...)`` in
        input pixels; probabilities after sigmoid; ``N = sum_i A H_i W_i``.
    """
    if len(raw) != len(strides) or anchors.shape[0] != len(strides):
        raise ValueError(f"{len(raw)} raw maps, {anchors.shape[0]} anchor sets and "
                         f"{len(strides)} strides must agree")
    out = []
    for level, x in enumerate(raw):
        p = split_raw(x, anchors.shape[1])
        boxes = decode_xywh(p[..., :4], anchors[level], strides[level], scale_xy[level])
        rows = torch.cat([boxes, p[..., 4:].sigmoid()], dim=-1)
        out.append(rows.reshape(rows.shape[0], -1, rows.shape[-1]))
    return torch.cat(out, dim=1)


def postprocess(decoded: torch.Tensor, conf_thres: float = 0.001, iou_thres: float = 0.6,
                max_det: int = 300) -> list[dict[str, torch.Tensor]]:
    """Score, threshold and class-wise NMS per image.

    A candidate's score for class ``k`` is ``objectness * p(k)``; each candidate keeps its
    best class (YOLOv4 inference).

    Args:
        decoded: :math:`(B, N, 5 + K)` output of :func:`decode`.
        conf_thres: minimum score kept.
        iou_thres: NMS IoU threshold (boxes of the same class).
        max_det: at most this many boxes per image, highest scores first.

    Returns:
        per image ``{"boxes": (M, 4) xyxy px, "scores": (M,), "labels": (M,) int64 category
        ids 1..K}``.
    """
    results = []
    for rows in decoded:
        scores, cls = (rows[:, 5:] * rows[:, 4:5]).max(dim=1)
        keep = scores > conf_thres
        boxes = box_convert(rows[keep, :4], "cxcywh", "xyxy")
        scores, cls = scores[keep], cls[keep]
        idx = batched_nms(boxes.float(), scores.float(), cls, iou_thres)[:max_det]
        results.append({"boxes": boxes[idx], "scores": scores[idx], "labels": cls[idx] + 1})
    return results
