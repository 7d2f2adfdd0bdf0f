"""The teacher's detections as a training target (knowledge distillation for a detector)."""

from __future__ import annotations

import torch
from torch import nn

from lunarnav_ml.models.decode import split_raw


def detection_kd_loss(student: list[torch.Tensor], teacher: list[torch.Tensor],
                      num_anchors: int) -> torch.Tensor:
    """How far the student's raw head maps are from the teacher's, weighed by what a detection
    needs: objectness by the Kullback-Leibler divergence of the student's Bernoulli from the
    teacher's at every cell and anchor; class probabilities (the same divergence per class) and
    raw boxes (squared error) at each cell and anchor in proportion to the teacher's objectness
    there. Each scale's terms are summed over its cells and divided by its total teacher
    objectness (at least 1), so the many empty cells, where a raw-map error does not change a
    detection, do not swamp the few that hold one. The divergence is the cross-entropy against
    the teacher's probabilities less the teacher's own entropy, a constant for the student: the
    gradients are the cross-entropy's, and the value is 0 when the student matches the teacher,
    so a logged value reads as the gap that is left. Computed in float32.

    Shape:
        - student, teacher: per scale :math:`(B, A (5 + K), H, W)`
        - Output: scalar
    """
    terms = []
    bce = nn.functional.binary_cross_entropy_with_logits
    for s, t in zip(student, teacher):
        s, t = split_raw(s.float(), num_anchors), split_raw(t.float(), num_anchors)
        w = t[..., 4].sigmoid()
        mass = w.sum().clamp(min=1.0)
        obj = bce(s[..., 4], w, reduction="sum") - bce(t[..., 4], w, reduction="sum")
        p = t[..., 5:].sigmoid()
        cls = ((bce(s[..., 5:], p, reduction="none") - bce(t[..., 5:], p, reduction="none"))
               .sum(-1) * w).sum()
        box = (((s[..., :4] - t[..., :4]) ** 2).sum(-1) * w).sum()
        terms.append((obj + cls + box) / mass)
    return torch.stack(terms).sum()
