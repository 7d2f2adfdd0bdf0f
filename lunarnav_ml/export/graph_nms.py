"""Append ONNX NonMaxSuppression to an exported detector graph.

The tail reproduces ``lunarnav_ml.models.decode.postprocess``: each candidate keeps only its
best class (``ArgMax`` + ``OneHot`` mask on ``objectness * p(class)``), then per-class NMS with
``score > conf_thres`` and suppression at ``IoU > iou_thres`` (onnxruntime's rules match
torchvision's). The thresholds and the per-class cap are graph inputs, so one file serves any
operating point.

New inputs: ``conf_thres`` (1,) float32, ``iou_thres`` (1,) float32, ``max_per_class`` (1,)
int64. New outputs: ``det_indices`` (K, 3) int64 rows ``(image, class 0-based, candidate)``,
``det_boxes`` (K, 4) xyxy px, ``det_scores`` (K,).
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from lunarnav_ml.runtime import metadata as md

_P = "nms/"  # name prefix of every node and tensor this module adds


def _const(name: str, values: np.ndarray) -> onnx.TensorProto:
    return numpy_helper.from_array(np.asarray(values), name=_P + name)


def _slice(src: str, start: int, end: int, out: str) -> onnx.NodeProto:
    """Slice the last axis (2) of a (B, N, F) tensor: ``src[:, :, start:end]``."""
    return helper.make_node("Slice", [src, _P + f"s{start}", _P + f"e{end}", _P + "axis2"],
                            [_P + out], name=_P + out)


def _nodes(num_classes: int) -> list[onnx.NodeProto]:
    d, n = md.DECODED_NAME, helper.make_node
    return [
        _slice(d, 0, 2, "xy"), _slice(d, 2, 4, "wh"), _slice(d, 4, 5, "obj"),
        _slice(d, 5, 5 + num_classes, "cls"),
        n("Mul", [_P + "cls", _P + "obj"], [_P + "scores_all"], name=_P + "scores_all"),
        # Keep each candidate's best class only (first one on ties, as torch.max).
        n("ArgMax", [_P + "scores_all"], [_P + "best"], axis=2, keepdims=0,
          select_last_index=0, name=_P + "best"),
        n("OneHot", [_P + "best", _P + "depth", _P + "onehot_values"], [_P + "onehot"],
          axis=-1, name=_P + "onehot"),
        n("Mul", [_P + "scores_all", _P + "onehot"], [_P + "scores_best"], name=_P + "mask"),
        n("Transpose", [_P + "scores_best"], [_P + "scores_bcn"], perm=[0, 2, 1],
          name=_P + "scores_bcn"),
        n("Mul", [_P + "wh", _P + "half"], [_P + "half_wh"], name=_P + "half_wh"),
        n("Sub", [_P + "xy", _P + "half_wh"], [_P + "x0y0"], name=_P + "x0y0"),
        n("Add", [_P + "xy", _P + "half_wh"], [_P + "x1y1"], name=_P + "x1y1"),
        n("Concat", [_P + "x0y0", _P + "x1y1"], [_P + "boxes"], axis=2, name=_P + "boxes"),
        # center_point_box=0 reads (y0, x0, y1, x1); IoU is symmetric in x and y, so xyxy
        # boxes give the same suppression and the outputs stay xyxy.
        n("NonMaxSuppression", [_P + "boxes", _P + "scores_bcn", md.MAX_PER_CLASS_NAME,
                                md.IOU_NAME, md.CONF_NAME], [md.NMS_OUTPUTS[0]],
          center_point_box=0, name=_P + "NonMaxSuppression"),
        n("GatherND", [_P + "scores_bcn", md.NMS_OUTPUTS[0]], [md.NMS_OUTPUTS[2]],
          name=_P + "det_scores"),
        n("Gather", [md.NMS_OUTPUTS[0], _P + "cols_bn"], [_P + "idx_bn"], axis=1,
          name=_P + "idx_bn"),
        n("GatherND", [_P + "boxes", _P + "idx_bn"], [md.NMS_OUTPUTS[1]], name=_P + "det_boxes"),
    ]


def _initializers(num_classes: int) -> list[onnx.TensorProto]:
    i64 = np.int64
    return [
        _const("s0", np.array([0], i64)), _const("e2", np.array([2], i64)),
        _const("s2", np.array([2], i64)), _const("e4", np.array([4], i64)),
        _const("s4", np.array([4], i64)), _const("e5", np.array([5], i64)),
        _const("s5", np.array([5], i64)), _const(f"e{5 + num_classes}",
                                                 np.array([5 + num_classes], i64)),
        _const("axis2", np.array([2], i64)), _const("depth", np.array(num_classes, i64)),
        _const("onehot_values", np.array([0.0, 1.0], np.float32)),
        _const("half", np.array(0.5, np.float32)), _const("cols_bn", np.array([0, 2], i64)),
    ]


def append_nms(model: onnx.ModelProto, num_classes: int) -> onnx.ModelProto:
    """Return a copy of ``model`` with the NMS tail and its inputs/outputs added.

    Args:
        model: graph with input ``images`` and output ``decoded`` (B, N, 5 + num_classes).
        num_classes: C.

    Raises:
        ValueError: the graph has no ``decoded`` output or already has an NMS tail.
    """
    out = onnx.ModelProto()
    out.CopyFrom(model)
    g = out.graph
    if md.DECODED_NAME not in [o.name for o in g.output]:
        raise ValueError(f"graph has no output named {md.DECODED_NAME!r}")
    if any(node.name.startswith(_P) for node in g.node):
        raise ValueError("graph already has an NMS tail")
    g.node.extend(_nodes(num_classes))
    g.initializer.extend(_initializers(num_classes))
    g.input.extend([
        helper.make_tensor_value_info(md.CONF_NAME, TensorProto.FLOAT, [1]),
        helper.make_tensor_value_info(md.IOU_NAME, TensorProto.FLOAT, [1]),
        helper.make_tensor_value_info(md.MAX_PER_CLASS_NAME, TensorProto.INT64, [1]),
    ])
    g.output.extend([
        helper.make_tensor_value_info(md.NMS_OUTPUTS[0], TensorProto.INT64, ["K", 3]),
        helper.make_tensor_value_info(md.NMS_OUTPUTS[1], TensorProto.FLOAT, ["K", 4]),
        helper.make_tensor_value_info(md.NMS_OUTPUTS[2], TensorProto.FLOAT, ["K"]),
    ])
    return out
