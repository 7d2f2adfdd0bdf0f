"""Validation of training targets (torchvision-style list of dicts)."""

from __future__ import annotations

import torch

from lunarnav_ml.errors import InputError


def check_targets(targets: list[dict[str, torch.Tensor]], num_classes: int, batch_size: int
                  ) -> None:
    """Raise ``InputError`` naming the image and box of a malformed target.

    Each target is ``{"boxes": (N, 4) xyxy px, "labels": (N,) category ids 1..K,
    "ignore": (N,) bool (optional)}``.
    """
    if len(targets) != batch_size:
        raise InputError(f"targets: {len(targets)} entries for a batch of {batch_size} images")
    for i, t in enumerate(targets):
        boxes, labels = t.get("boxes"), t.get("labels")
        if boxes is None or labels is None:
            raise InputError(f"targets[{i}]: needs 'boxes' and 'labels', got keys {sorted(t)}")
        if boxes.ndim != 2 or boxes.shape[1] != 4 or labels.shape != boxes.shape[:1]:
            raise InputError(f"targets[{i}]: boxes must be (N, 4) and labels (N,), got "
                             f"{tuple(boxes.shape)} and {tuple(labels.shape)}")
        if "ignore" in t and t["ignore"].shape != labels.shape:
            raise InputError(f"targets[{i}]: ignore must be (N,), got {tuple(t['ignore'].shape)}")
    if not any(len(t["boxes"]) for t in targets):
        return
    # the values of the whole batch at once (one synchronisation on a GPU); per image only to
    # name the culprit
    if _bad(torch.cat([t["boxes"] for t in targets]), torch.cat([t["labels"] for t in targets]),
            num_classes).any():
        for i, t in enumerate(targets):
            _check_values(i, t["boxes"], t["labels"], num_classes)


def _bad(boxes: torch.Tensor, labels: torch.Tensor, num_classes: int) -> torch.Tensor:
    """Per box: not finite, not positive in width or height, or a label outside 1..K."""
    return (~torch.isfinite(boxes).all(dim=1) | (boxes[:, 2] <= boxes[:, 0])
            | (boxes[:, 3] <= boxes[:, 1]) | (labels < 1) | (labels > num_classes))


def _check_values(i: int, boxes: torch.Tensor, labels: torch.Tensor, num_classes: int) -> None:
    bad = _bad(boxes, labels, num_classes).nonzero()
    if not len(bad):
        return
    j = int(bad[0])
    if not torch.isfinite(boxes[j]).all():
        raise InputError(f"targets[{i}]['boxes'][{j}] is not finite: {boxes[j].tolist()}")
    if labels[j] < 1 or labels[j] > num_classes:
        raise InputError(f"targets[{i}]['labels'][{j}] = {int(labels[j])} is not a category id "
                         f"in 1..{num_classes}")
    raise InputError(f"targets[{i}]['boxes'][{j}] has non-positive width or height "
                     f"(xyxy {boxes[j].tolist()})")
