import torch

from lunarnav_ml.models.decode import decode, postprocess, split_raw


def test_decode_known_answer():
    anchors = torch.tensor([[[10.0, 20.0]]])
    raw = torch.zeros(1, 6, 2, 3)  # one anchor, one class, 2x3 cells
    raw[0, 4, 1, 2] = 3.0  # objectness logit at row 1, column 2
    out = decode([raw], anchors, strides=[8], scale_xy=[1.0])
    assert out.shape == (1, 6, 6)
    row = out[0, 1 * 3 + 2]  # cells are row-major
    # centre: (sigmoid(0) + cell) * stride; size: anchor * exp(0)
    torch.testing.assert_close(row[:4], torch.tensor([(0.5 + 2) * 8, (0.5 + 1) * 8, 10.0, 20.0]))
    torch.testing.assert_close(row[4], torch.sigmoid(torch.tensor(3.0)))


def test_grid_sensitivity_reaches_cell_borders():
    anchors = torch.tensor([[[10.0, 10.0]]])
    raw = torch.zeros(1, 6, 1, 1)
    raw[0, 0] = 30.0  # sigmoid -> 1
    x = decode([raw], anchors, [32], [1.2])[0, 0, 0]
    assert x > 32  # with scale_xy 1.2 the centre can pass the cell border (1.1 * 32)
    torch.testing.assert_close(x, torch.tensor(1.1 * 32))


def test_split_raw_layout():
    raw = torch.arange(2 * 14 * 2 * 2, dtype=torch.float32).view(2, 14, 2, 2)
    p = split_raw(raw, 2)
    assert p.shape == (2, 2, 2, 2, 7)
    assert p[1, 1, 0, 1, 3] == raw[1, 7 + 3, 0, 1]


def test_postprocess_nms_and_labels():
    # two overlapping class-2 boxes and one class-1 box
    rows = torch.tensor([[[50, 50, 20, 20, 0.9, 0.1, 0.9],
                          [51, 50, 20, 20, 0.8, 0.1, 0.9],
                          [10, 10, 8, 8, 0.9, 0.8, 0.1],
                          [90, 90, 8, 8, 0.0001, 0.9, 0.1]]])
    out = postprocess(rows, conf_thres=0.01, iou_thres=0.5)[0]
    assert out["labels"].tolist() == [2, 1]  # category ids, 1-based, highest score first
    torch.testing.assert_close(out["boxes"][1], torch.tensor([6.0, 6.0, 14.0, 14.0]))
    torch.testing.assert_close(out["scores"], torch.tensor([0.81, 0.72]))
