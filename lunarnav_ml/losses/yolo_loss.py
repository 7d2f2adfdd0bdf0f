"""The YOLOv4 loss: CIoU box loss, objectness BCE with ignore masking, class BCE with label
smoothing."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn
from torchvision.ops import box_convert

from lunarnav_ml.errors import InputError
from lunarnav_ml.losses.assigner import (
    LevelTargets,
    TensorFields,
    assign,
    flatten_targets,
    per_image,
)
from lunarnav_ml.losses.iou import batched_box_iou, ciou
from lunarnav_ml.losses.targets import check_targets
from lunarnav_ml.models.decode import MAX_LOG_WH, decode_xywh, split_raw

# Objectness weight per scale, finest first (small objects are many cells; YOLOv5's balance).
LEVEL_BALANCE = {1: (1.0,), 2: (4.0, 1.0), 3: (4.0, 1.0, 0.4)}


class YOLOLoss(nn.Module):
    """Loss of a YOLO head's raw maps against box targets.

    Args:
        num_classes: K.
        anchor_iou_thresh: anchors with shape IoU above this are extra positives (YOLOv4 0.213).
        ignore_thresh: predictions overlapping any ground truth above this IoU get no
            objectness penalty (YOLOv4 0.7).
        label_smoothing: class targets become ``1 - eps / 2`` and ``eps / 2``.
        box_weight, obj_weight, cls_weight: weights of the three terms; ``obj_weight`` is
            scaled by ``(input size / 640)^2`` and all by ``3 / levels`` (YOLOv5 convention).
        obj_iou_ratio: objectness target of a positive is ``1 - r + r * IoU`` (0: always 1).
    """

    def __init__(self, num_classes: int, anchor_iou_thresh: float = 0.213,
                 ignore_thresh: float = 0.7, label_smoothing: float = 0.0,
                 box_weight: float = 0.05, obj_weight: float = 1.0, cls_weight: float = 0.02,
                 obj_iou_ratio: float = 1.0) -> None:
        super().__init__()
        self.num_classes = num_classes
        self.anchor_iou_thresh = anchor_iou_thresh
        self.ignore_thresh = ignore_thresh
        self.label_smoothing = label_smoothing
        self.weights = (box_weight, obj_weight, cls_weight)
        self.obj_iou_ratio = obj_iou_ratio

    def forward(self, raw: Sequence[torch.Tensor],
                targets: list[dict[str, torch.Tensor]] | PreparedTargets, anchors: torch.Tensor,
                strides: Sequence[int], scale_xy: Sequence[float]) -> dict[str, torch.Tensor]:
        """Compute the loss terms.

        Args:
            raw: per scale :math:`(B, A (5 + K), H_i, W_i)` head maps.
            targets: per image ``{"boxes": (N, 4) xyxy input px, "labels": (N,) ids 1..K,
                "ignore": (N,) bool}``, or those targets already through :meth:`prepare`
                (then nothing here waits on the device: see :meth:`prepare`).
            anchors: :math:`(L, A, 2)` px; strides, scale_xy: per scale.

        Returns:
            ``{"box", "obj", "cls", "loss"}`` scalar tensors (``loss`` is their sum).
        """
        raw = [x.float() for x in raw]  # under AMP the head maps are float16
        grids = tuple((x.shape[2], x.shape[3]) for x in raw)
        if isinstance(targets, PreparedTargets):
            if targets.grids != grids or targets.regions.gt.shape[0] != raw[0].shape[0]:
                raise InputError(f"prepared targets are for a batch of "
                                 f"{targets.regions.gt.shape[0]} on grids {targets.grids}, the "
                                 f"head maps a batch of {raw[0].shape[0]} on {grids}")
            prepared = targets.to(raw[0].device)
        else:
            prepared = self.prepare(targets, raw[0].shape[0], grids, anchors, strides, scale_xy)
        balance = LEVEL_BALANCE.get(len(raw), (1.0,) * len(raw))
        zero = raw[0].sum() * 0.0
        box, obj, cls = zero, zero, zero
        n_box = 0
        for level, x in enumerate(raw):
            p = split_raw(x, anchors.shape[1])
            pos = prepared.assigned[level]
            b_l, o_l, c_l = self._level(p, pos, prepared.regions, anchors[level],
                                        strides[level], scale_xy[level])
            box, cls = box + b_l * len(pos.batch), cls + c_l * len(pos.batch)
            n_box += len(pos.batch)
            obj = obj + o_l * balance[level]
        box, cls = box / max(n_box, 1), cls / max(n_box, 1)
        return self._weighted(box, obj, cls, raw, strides)

    def prepare(self, targets: list[dict[str, torch.Tensor]], batch_size: int,
                grids: Sequence[tuple[int, int]], anchors: torch.Tensor, strides: Sequence[int],
                scale_xy: Sequence[float]) -> PreparedTargets:
        """Check a batch's targets, assign them to anchors and cells and group them by image,
        on the device of ``targets`` and ``anchors``.

        This is the part of the loss whose sizes depend on the values (how many positives,
        how many boxes in the fullest image): on a GPU each such size is a synchronisation
        with the host. Done on the host before the batch goes to the GPU, the loss that
        follows waits on nothing, so the host can queue the next steps' kernels meanwhile.

        Args:
            grids: :math:`(H_i, W_i)` cells of each scale (the head maps' last two sides).
        """
        check_targets(targets, self.num_classes, batch_size)
        gt, ign = flatten_targets(targets, anchors.device)
        neighbors = tuple(s >= 2.0 for s in scale_xy)  # reachable neighbour cells are positives
        grids = tuple((int(h), int(w)) for h, w in grids)
        assigned = assign(gt, anchors, tuple(strides), list(grids), self.anchor_iou_thresh,
                          neighbors)
        return PreparedTargets(grids, assigned, padded_regions(gt, ign, batch_size))

    def _weighted(self, box, obj, cls, raw, strides) -> dict[str, torch.Tensor]:
        levels = len(raw)
        size = raw[0].shape[2] * strides[0]
        wb, wo, wc = self.weights
        terms = {"box": box * wb * 3 / levels, "obj": obj * wo * (size / 640) ** 2 * 3 / levels,
                 "cls": cls * wc * 3 / levels}
        terms["loss"] = terms["box"] + terms["obj"] + terms["cls"]
        return terms

    def _level(self, p: torch.Tensor, pos: LevelTargets, regions: PaddedRegions,
               anchors: torch.Tensor, stride: int, scale_xy: float
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Mean box (1 - CIoU) and class BCE over positives, and mean objectness BCE.

        Shape:
            - p: :math:`(B, A, H, W, 5 + K)` raw fields of one scale.
        """
        weight = self._negative_weight(p, regions, anchors, stride, scale_xy)
        tobj = torch.zeros_like(p[..., 4])
        box = cls = p.sum() * 0.0
        if len(pos.batch):
            t = p[pos.batch, pos.anchor, pos.gy, pos.gx]  # (P, 5 + K)
            cells = torch.stack([pos.gx, pos.gy], dim=1).to(t)
            xy = (t[:, :2].sigmoid() * scale_xy - 0.5 * (scale_xy - 1) + cells) * stride
            wh = torch.exp(t[:, 2:4].clamp(max=MAX_LOG_WH)) * anchors[pos.anchor]
            c, _ = ciou(torch.cat([xy, wh], dim=1), pos.boxes)
            box = (1.0 - c).mean()
            r = self.obj_iou_ratio
            tobj[pos.batch, pos.anchor, pos.gy, pos.gx] = (1 - r) + r * c.detach().clamp(0)
            weight[pos.batch, pos.anchor, pos.gy, pos.gx] = 1.0
            cls = F.binary_cross_entropy_with_logits(t[:, 5:], self._class_targets(pos.classes, t))
        obj = (F.binary_cross_entropy_with_logits(p[..., 4], tobj, reduction="none")
               * weight).mean()
        return box, obj, cls

    def _class_targets(self, classes: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        eps = self.label_smoothing
        target = torch.full_like(t[:, 5:], 0.5 * eps)
        target[torch.arange(len(classes), device=classes.device), classes] = 1.0 - 0.5 * eps
        return target

    @torch.no_grad()
    def _negative_weight(self, p: torch.Tensor, regions: PaddedRegions, anchors: torch.Tensor,
                         stride: int, scale_xy: float) -> torch.Tensor:
        """1 where a prediction is a plain negative, 0 where it overlaps a ground truth above
        ``ignore_thresh`` or its centre lies in an ignore region (all images at once).

        Shape:
            - Output: :math:`(B, A, H, W)`
        """
        boxes = decode_xywh(p[..., :4].float(), anchors, stride, scale_xy)  # (B, A, H, W, 4)
        flat = boxes.reshape(boxes.shape[0], -1, 4)  # (B, N, 4)
        mask = torch.zeros(flat.shape[:2], dtype=torch.bool, device=p.device)
        g, valid = regions.gt, regions.gt_valid
        if g.shape[1]:
            pred_xyxy = box_convert(flat, "cxcywh", "xyxy")
            chunk = max(1, 2**24 // (flat.shape[1] * g.shape[1]))  # bounds the memory
            for b in range(0, len(flat), chunk):
                iou = batched_box_iou(pred_xyxy[b:b + chunk], g[b:b + chunk])  # (b, N, G)
                iou = iou.masked_fill(~valid[b:b + chunk, None, :], -1.0)
                mask[b:b + chunk] |= iou.amax(dim=2) > self.ignore_thresh
        r, valid = regions.ignore, regions.ignore_valid
        if r.shape[1]:
            cx, cy = flat[..., 0:1], flat[..., 1:2]  # (B, N, 1) against (B, 1, Q)
            inside = ((cx >= r[:, None, :, 0]) & (cx <= r[:, None, :, 2])
                      & (cy >= r[:, None, :, 1]) & (cy <= r[:, None, :, 3]) & valid[:, None, :])
            mask |= inside.any(dim=2)
        return (~mask).float().reshape(boxes.shape[:-1])


@dataclass
class PreparedTargets:
    """A batch's targets through :meth:`YOLOLoss.prepare`: the positives of each scale and
    the padded regions of each image, for head maps on ``grids``."""

    grids: tuple[tuple[int, int], ...]
    assigned: list[LevelTargets]
    regions: PaddedRegions

    def to(self, device: torch.device | str, non_blocking: bool | None = None
           ) -> PreparedTargets:
        """The same on ``device`` (tensors already there are not copied); ``non_blocking``
        defaults to True towards a GPU (asynchronous from pinned memory)."""
        return PreparedTargets(self.grids, [lv.to(device, non_blocking) for lv in self.assigned],
                               self.regions.to(device, non_blocking))

    def pin_memory(self) -> PreparedTargets:
        """A copy in page-locked memory (asynchronous copies to a GPU; the DataLoader's
        ``pin_memory`` protocol)."""
        return PreparedTargets(self.grids, [lv.pin_memory() for lv in self.assigned],
                               self.regions.pin_memory())


@dataclass
class PaddedRegions(TensorFields):
    """A batch's boxes to learn and ignore regions, ``xyxy`` px, grouped by image and padded:
    :math:`(B, G, 4)` and :math:`(B, Q, 4)`, with :math:`(B, G)`, :math:`(B, Q)` masks of the
    real rows."""

    gt: torch.Tensor
    gt_valid: torch.Tensor
    ignore: torch.Tensor
    ignore_valid: torch.Tensor


def padded_regions(gt: torch.Tensor, ign: torch.Tensor, batch: int) -> PaddedRegions:
    """:class:`PaddedRegions` of :func:`flatten_targets`' ``gt`` (cxcywh) and ``ign`` rows."""
    g, g_valid = per_image(gt[:, 0].long(), box_convert(gt[:, 2:6], "cxcywh", "xyxy"), batch)
    r, r_valid = per_image(ign[:, 0].long(), ign[:, 1:5], batch)
    return PaddedRegions(g, g_valid, r, r_valid)
