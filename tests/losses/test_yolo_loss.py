import math

import pytest
import torch

from lunarnav_ml.errors import InputError
from lunarnav_ml.losses import YOLOLoss, ciou, wh_iou
from lunarnav_ml.losses.assigner import assign, flatten_targets
from lunarnav_ml.models import build_model


def _targets():
    return [{"boxes": torch.tensor([[8.0, 8.0, 40.0, 48.0], [30.0, 30.0, 60.0, 50.0]]),
             "labels": torch.tensor([1, 2]), "ignore": torch.tensor([False, True])},
            {"boxes": torch.tensor([[20.0, 10.0, 52.0, 40.0]]), "labels": torch.tensor([3])}]


def _model():
    torch.manual_seed(0)
    model = build_model("nano")
    model.set_anchors(torch.tensor([[[8, 8], [12, 16], [16, 12]], [[24, 24], [32, 40], [40, 32]],
                                    [[48, 48], [56, 56], [64, 64]]], dtype=torch.float32))
    return model


def test_ciou_known_answers():
    box = torch.tensor([[10.0, 10.0, 4.0, 4.0]])
    c, iou = ciou(box, box)
    torch.testing.assert_close(c, torch.tensor([1.0]))
    # same size, shifted by one width: IoU 0, centre term 4^2 / (8^2 + 4^2)
    c, iou = ciou(torch.tensor([[14.0, 10.0, 4.0, 4.0]]), box)
    torch.testing.assert_close(iou, torch.tensor([0.0]))
    torch.testing.assert_close(c, torch.tensor([-16 / 80]), atol=1e-5, rtol=0)
    assert wh_iou(torch.tensor([[2.0, 2.0]]), torch.tensor([[2.0, 2.0], [4.0, 4.0]])).tolist() == [
        [1.0, 0.25]]


def test_assign_best_anchor_always_and_extra_above_threshold():
    gt = torch.tensor([[0, 0, 20.0, 20.0, 12.0, 16.0]])  # image 0, class 0, exactly anchor (0, 1)
    anchors = _model().anchors
    levels = assign(gt, anchors, (8, 16, 32), [(8, 8), (4, 4), (2, 2)], iou_thresh=0.7)
    assert levels[0].anchor.tolist() == [1] and levels[0].gx.tolist() == [2]
    assert sum(len(lv.batch) for lv in levels) == 1
    loose = assign(gt, anchors, (8, 16, 32), [(8, 8), (4, 4), (2, 2)], iou_thresh=0.2)
    assert sum(len(lv.batch) for lv in loose) > 1  # several anchors per ground truth


def test_assign_neighbour_cells_nearest_the_centre():
    # centre (20, 21) at stride 8: cell (2, 2), fractions 0.5 / 0.625 -> right and lower cells
    gt = torch.tensor([[0, 0, 20.0, 21.0, 12.0, 16.0], [0, 0, 1.0, 1.0, 12.0, 16.0]])
    anchors = _model().anchors
    lv = assign(gt, anchors, (8, 16, 32), [(8, 8), (4, 4), (2, 2)], iou_thresh=0.7,
                neighbors=(True, False, False))[0]
    cells = sorted(zip(lv.gx.tolist(), lv.gy.tolist()))
    # the box at (1, 1) sits in the corner cell; its left and upper neighbours are off the grid
    assert cells == [(0, 0), (2, 2), (2, 3), (3, 2)]
    near = lv.gx > 0
    assert (lv.boxes[near, :2] == torch.tensor([20.0, 21.0])).all()  # all regress the same box


def test_flatten_separates_ignore_regions():
    gt, ign = flatten_targets(_targets(), torch.device("cpu"))
    assert gt.shape == (2, 6) and ign.shape == (1, 5)
    assert gt[:, 0].tolist() == [0, 1] and gt[:, 1].tolist() == [0, 2]  # class index = id - 1
    torch.testing.assert_close(gt[0, 2:], torch.tensor([24.0, 28.0, 32.0, 40.0]))


def test_loss_returns_named_terms():
    model = _model()
    x = torch.rand(2, 3, 64, 64)
    out = YOLOLoss(3)(model(x), _targets(), model.anchors, model.strides, model.scale_xy)
    assert set(out) == {"box", "obj", "cls", "loss"}
    assert all(torch.isfinite(v) and v.ndim == 0 for v in out.values())
    torch.testing.assert_close(out["loss"], out["box"] + out["obj"] + out["cls"])


def test_loss_handles_images_without_boxes():
    model = _model()
    empty = [{"boxes": torch.zeros(0, 4), "labels": torch.zeros(0, dtype=torch.long)}]
    out = YOLOLoss(3)(model(torch.rand(1, 3, 64, 64)), empty, model.anchors, model.strides,
                      model.scale_xy)
    assert out["box"] == 0 and out["cls"] == 0 and out["obj"] > 0
    out["loss"].backward()


def test_loss_falls_when_overfitting_one_batch():
    model = _model()
    loss_fn = YOLOLoss(3)
    x = torch.rand(2, 3, 64, 64)
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
    losses = []
    for _ in range(25):
        out = loss_fn(model(x), _targets(), model.anchors, model.strides, model.scale_xy)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        losses.append(float(out["loss"].detach()))
    assert losses[-1] < 0.5 * losses[0]


def test_ignore_region_removes_negative_penalty():
    model = _model()
    x = torch.rand(1, 3, 64, 64)
    raw = model(x)
    base = [{"boxes": torch.tensor([[0.0, 0.0, 64.0, 64.0]]), "labels": torch.tensor([1]),
             "ignore": torch.tensor([True])}]
    none = [{"boxes": torch.zeros(0, 4), "labels": torch.zeros(0, dtype=torch.long)}]
    loss_fn = YOLOLoss(3)
    ignored = loss_fn(raw, base, model.anchors, model.strides, model.scale_xy)
    plain = loss_fn(raw, none, model.anchors, model.strides, model.scale_xy)
    assert ignored["obj"] < 0.05 * plain["obj"]  # every prediction lies in the ignore region
    assert ignored["box"] == 0


@pytest.mark.parametrize("boxes, labels, match", [
    ([[1.0, 2.0, math.nan, 9.0]], [1], r"targets\[0\]\['boxes'\]\[0\] is not finite"),
    ([[10.0, 10.0, 5.0, 20.0]], [1], "non-positive width or height"),
    ([[1.0, 1.0, 5.0, 5.0]], [4], r"labels'\]\[0\] = 4 is not a category id in 1..3"),
    ([[1.0, 1.0, 5.0, 5.0]], [0], "is not a category id"),
    ([[1.0, 1.0, 5.0]], [1], r"boxes must be \(N, 4\)"),
])
def test_malformed_targets_raise(boxes, labels, match):
    model = _model()
    raw = model(torch.rand(1, 3, 64, 64))
    bad = [{"boxes": torch.tensor(boxes), "labels": torch.tensor(labels)}]
    with pytest.raises(InputError, match=match):
        YOLOLoss(3)(raw, bad, model.anchors, model.strides, model.scale_xy)


def test_wrong_number_of_targets_raises():
    model = _model()
    raw = model(torch.rand(2, 3, 64, 64))
    with pytest.raises(InputError, match="1 entries for a batch of 2"):
        YOLOLoss(3)(raw, _targets()[:1], model.anchors, model.strides, model.scale_xy)


def _random_targets(gen: torch.Generator, n_images: int, size: float):
    out = []
    for i in range(n_images):
        n = [0, 1, 5, 12][i % 4]  # images without boxes, and unequal counts, in one batch
        xy = torch.rand(n, 2, generator=gen) * size * 0.8
        wh = 2 + torch.rand(n, 2, generator=gen) * size * 0.3
        out.append({"boxes": torch.cat([xy, xy + wh], 1),
                    "labels": torch.randint(1, 4, (n,), generator=gen),
                    "ignore": torch.rand(n, generator=gen) < 0.3})
    return out


def _negative_weight_per_image(boxes, gt, ign, thresh):
    """The ignore mask one image at a time (torchvision's box_iou): what the batched one must
    reproduce."""
    from torchvision.ops import box_convert, box_iou
    weight = torch.ones(boxes.shape[:-1])
    for b in range(boxes.shape[0]):
        flat = boxes[b].reshape(-1, 4)
        mask = torch.zeros(len(flat), dtype=torch.bool)
        gt_b = gt[gt[:, 0] == b, 2:6]
        if len(gt_b):
            iou = box_iou(box_convert(flat, "cxcywh", "xyxy"), box_convert(gt_b, "cxcywh", "xyxy"))
            mask |= iou.max(dim=1).values > thresh
        ign_b = ign[ign[:, 0] == b, 1:5]
        if len(ign_b):
            cx, cy = flat[:, 0:1], flat[:, 1:2]
            mask |= ((cx >= ign_b[:, 0]) & (cx <= ign_b[:, 2]) & (cy >= ign_b[:, 1])
                     & (cy <= ign_b[:, 3])).any(dim=1)
        weight[b].view(-1)[mask] = 0.0
    return weight


def test_batched_negative_weight_matches_the_per_image_mask():
    from lunarnav_ml.losses.yolo_loss import padded_regions
    from lunarnav_ml.models.decode import decode_xywh, split_raw
    gen = torch.Generator().manual_seed(3)
    targets = _random_targets(gen, 8, 128.0)
    gt, ign = flatten_targets(targets, torch.device("cpu"))
    assert 3 <= len(gt[:, 0].unique()) < 8 and len(ign)  # some images without boxes
    loss = YOLOLoss(3)
    anchors = torch.tensor([[8.0, 8.0], [24.0, 16.0], [48.0, 40.0]])
    raw = torch.randn(8, 3 * 8, 16, 16, generator=gen)  # one stride-8 level of a 128 px input
    p = split_raw(raw, 3)
    got = loss._negative_weight(p, padded_regions(gt, ign, 8), anchors, 8, 2.0)
    boxes = decode_xywh(p[..., :4].float(), anchors, 8, 2.0)
    want = _negative_weight_per_image(boxes, gt, ign, loss.ignore_thresh)
    assert got.shape == (8, 3, 16, 16) and 0 < (got == 0).sum() < got.numel()
    torch.testing.assert_close(got, want, rtol=0, atol=0)


def test_flatten_keeps_image_order_and_ignore_split():
    gen = torch.Generator().manual_seed(4)
    targets = _random_targets(gen, 6, 96.0)
    gt, ign = flatten_targets(targets, torch.device("cpu"))
    for i, t in enumerate(targets):
        keep = ~t["ignore"]
        rows = gt[gt[:, 0] == i]
        torch.testing.assert_close(rows[:, 1], (t["labels"][keep] - 1).float())
        b = t["boxes"][keep]
        torch.testing.assert_close(rows[:, 4:6], b[:, 2:] - b[:, :2])
        torch.testing.assert_close(ign[ign[:, 0] == i, 1:], t["boxes"][t["ignore"]])
    assert gt[:, 0].tolist() == sorted(gt[:, 0].tolist())
    empty_gt, empty_ign = flatten_targets([{"boxes": torch.zeros(0, 4),
                                            "labels": torch.zeros(0, dtype=torch.long)}],
                                          torch.device("cpu"))
    assert empty_gt.shape == (0, 6) and empty_ign.shape == (0, 5)


def test_prepared_targets_give_the_same_loss_to_the_bit():
    from lunarnav_ml.losses.yolo_loss import PreparedTargets
    model = _model()
    gen = torch.Generator().manual_seed(5)
    targets = _random_targets(gen, 8, 64.0)
    raw = model(torch.rand(8, 3, 64, 64, generator=gen))
    loss_fn = YOLOLoss(3)
    grids = [(x.shape[2], x.shape[3]) for x in raw]
    prepared = loss_fn.prepare(targets, 8, grids, model.anchors.clone(), model.strides,
                               model.scale_xy)
    assert isinstance(prepared, PreparedTargets) and sum(len(lv.batch) for lv in prepared.assigned)
    want = loss_fn(raw, targets, model.anchors, model.strides, model.scale_xy)
    got = loss_fn(raw, prepared, model.anchors, model.strides, model.scale_xy)
    for k in want:
        torch.testing.assert_close(got[k], want[k], rtol=0, atol=0)
    moved = prepared.to("cpu")  # the tensors stay where they are
    assert moved.assigned[0].boxes is prepared.assigned[0].boxes


def test_prepared_targets_for_other_grids_or_batch_raise():
    model = _model()
    raw = model(torch.rand(2, 3, 64, 64))
    loss_fn = YOLOLoss(3)
    args = (model.anchors, model.strides, model.scale_xy)
    bigger = loss_fn.prepare(_targets(), 2, [(16, 16), (8, 8), (4, 4)], *args)
    with pytest.raises(InputError, match=r"grids \(\(16, 16\).*on \(\(8, 8\)"):
        loss_fn(raw, bigger, *args)
    three = _targets() + [_targets()[1]]
    other = loss_fn.prepare(three, 3, [(8, 8), (4, 4), (2, 2)], *args)
    with pytest.raises(InputError, match="a batch of 3 .* a batch of 2"):
        loss_fn(raw, other, *args)
    with pytest.raises(InputError, match="is not finite"):  # prepare checks the values
        bad = [{"boxes": torch.tensor([[1.0, 2.0, math.nan, 9.0]]), "labels": torch.tensor([1])}]
        loss_fn.prepare(bad, 1, [(8, 8), (4, 4), (2, 2)], *args)
