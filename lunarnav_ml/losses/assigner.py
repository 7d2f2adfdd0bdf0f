"""YOLOv4 target assignment: every anchor (of any scale) whose shape IoU with a ground-truth
box exceeds a threshold is a positive, and the best-matching anchor always is."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch

from lunarnav_ml.losses.iou import wh_iou


class TensorFields:
    """For a dataclass whose fields are all tensors: moved or pinned together."""

    def to(self, device: torch.device | str, non_blocking: bool | None = None):
        """The same on ``device`` (tensors already there are not copied); ``non_blocking``
        defaults to True towards a GPU (asynchronous from pinned memory)."""
        if non_blocking is None:
            non_blocking = torch.device(device).type == "cuda"
        return type(self)(*(getattr(self, f.name).to(device, non_blocking=non_blocking)
                            for f in fields(self)))

    def pin_memory(self):
        """A copy in page-locked host memory (asynchronous copies to a GPU)."""
        return type(self)(*(getattr(self, f.name).pin_memory() for f in fields(self)))


@dataclass
class LevelTargets(TensorFields):
    """Positives of one scale: where they sit and what they should predict."""

    batch: torch.Tensor  # (P,) image index in the batch
    anchor: torch.Tensor  # (P,) anchor index within the scale
    gy: torch.Tensor  # (P,) cell row
    gx: torch.Tensor  # (P,) cell column
    boxes: torch.Tensor  # (P, 4) target (cx, cy, w, h) in input pixels
    classes: torch.Tensor  # (P,) class index 0..K-1


def flatten_targets(targets: list[dict[str, torch.Tensor]], device: torch.device
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Stack per-image targets into rows, split into positives and ignore regions.

    Returns:
        ``gt`` :math:`(M, 6)` rows ``(image, class 0..K-1, cx, cy, w, h)`` of boxes to learn,
        and ``ign`` :math:`(Q, 5)` rows ``(image, x0, y0, x1, y1)`` of ignore regions.
    """
    # one concatenation and one boolean split for the whole batch: on a GPU a loop over the
    # images costs a synchronisation per image
    counts = [len(t["boxes"]) for t in targets]
    if sum(counts) == 0:
        return torch.zeros(0, 6, device=device), torch.zeros(0, 5, device=device)
    boxes = torch.cat([t["boxes"] for t in targets]).to(device=device, dtype=torch.float32)
    labels = torch.cat([t["labels"] for t in targets]).to(device)
    ignore = torch.cat([t["ignore"] if "ignore" in t else torch.zeros_like(t["labels"],
                                                                          dtype=torch.bool)
                        for t in targets]).to(device).bool()
    idx = torch.repeat_interleave(torch.arange(len(targets), device=device, dtype=torch.float32),
                                  torch.tensor(counts, device=device),
                                  output_size=sum(counts))[:, None]
    cxcywh = torch.cat([(boxes[:, :2] + boxes[:, 2:]) / 2, boxes[:, 2:] - boxes[:, :2]], 1)
    rows = torch.cat([idx, (labels[:, None] - 1).float(), cxcywh], dim=1)
    return rows[~ignore], torch.cat([idx, boxes], dim=1)[ignore]


def per_image(image: torch.Tensor, rows: torch.Tensor, batch: int
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows grouped by image and padded: ``(B, G, C)`` with G the most rows of one image, and
    ``(B, G)`` True where a row is real.

    Args:
        image: :math:`(M,)` image index of each row, in 0..batch-1.
        rows: :math:`(M, C)`.
    """
    counts = torch.bincount(image, minlength=batch)
    width = int(counts.max()) if len(image) else 0
    order = torch.argsort(image, stable=True)
    image = image[order]
    start = torch.cumsum(counts, 0) - counts  # first row of each image in sorted order
    slot = torch.arange(len(image), device=image.device) - start[image]
    padded = rows.new_zeros(batch, width, rows.shape[1])
    valid = torch.zeros(batch, width, dtype=torch.bool, device=rows.device)
    padded[image, slot] = rows[order]
    valid[image, slot] = True
    return padded, valid


def assign(gt: torch.Tensor, anchors: torch.Tensor, strides: tuple[int, ...],
           grid_shapes: list[tuple[int, int]], iou_thresh: float,
           neighbors: tuple[bool, ...] | None = None) -> list[LevelTargets]:
    """Assign each ground-truth box to anchors across all scales (YOLOv4 ``iou_thresh``).

    Args:
        gt: :math:`(M, 6)` rows ``(image, class, cx, cy, w, h)`` in input pixels.
        anchors: :math:`(L, A, 2)` anchor sizes in input pixels.
        strides: pixels per cell of each scale.
        grid_shapes: (H, W) cells of each scale.
        iou_thresh: shape-IoU above which an anchor is also a positive (YOLOv4: 0.213).
        neighbors: per scale, whether the two cells next to the centre cell nearest the centre
            (one in x, one in y) are positives too (YOLOv5's assignment: three times the
            positives, faster convergence). Their predictions must reach the centre, so this
            needs a grid-sensitivity factor ``scale_xy >= 2`` at that scale.

    Returns:
        One :class:`LevelTargets` per scale; a box sits in the cell holding its centre (and,
        with ``neighbors``, in two adjacent cells).
    """
    num_levels, num_anchors = anchors.shape[:2]
    ious = wh_iou(gt[:, 4:6], anchors.reshape(-1, 2))  # (M, L * A)
    positive = ious > iou_thresh
    if len(gt):
        positive[torch.arange(len(gt), device=gt.device), ious.argmax(dim=1)] = True
    out = []
    for level in range(num_levels):
        m, a = positive[:, level * num_anchors:(level + 1) * num_anchors].nonzero(as_tuple=True)
        h, w = grid_shapes[level]
        rows = gt[m]
        xy = rows[:, 2:4] / strides[level]
        gx = xy[:, 0].long().clamp(0, w - 1)
        gy = xy[:, 1].long().clamp(0, h - 1)
        if neighbors is not None and neighbors[level]:
            frac = xy - xy.floor()
            step_x = torch.where(frac[:, 0] < 0.5, -1, 1)
            step_y = torch.where(frac[:, 1] < 0.5, -1, 1)
            nx, ny = gx + step_x, gy + step_y
            in_x, in_y = (nx >= 0) & (nx < w), (ny >= 0) & (ny < h)
            a = torch.cat([a, a[in_x], a[in_y]])
            rows = torch.cat([rows, rows[in_x], rows[in_y]])
            gx, gy = torch.cat([gx, nx[in_x], gx[in_y]]), torch.cat([gy, gy[in_x], ny[in_y]])
        out.append(LevelTargets(rows[:, 0].long(), a, gy, gx, rows[:, 2:6], rows[:, 1].long()))
    return out
