"""Rewrites of the traced ONNX graph that keep its function and widen who can run it."""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper


def inline_shared_initializers(model: onnx.ModelProto) -> None:
    """Replace ``Identity`` nodes that alias an initializer with a copy of it, in place.

    The TorchScript exporter deduplicates equal constants (e.g. zero conv biases) through
    Identity nodes; onnxruntime's quantizer needs each conv's weight and bias as initializers.
    """
    g = model.graph
    inits = {i.name: i for i in g.initializer}
    keep = []
    for node in g.node:
        if node.op_type == "Identity" and node.input[0] in inits:
            alias = onnx.TensorProto()
            alias.CopyFrom(inits[node.input[0]])
            alias.name = node.output[0]
            g.initializer.append(alias)
        else:
            keep.append(node)
    del g.node[:]
    g.node.extend(keep)


def _constant_value(node: onnx.NodeProto | None) -> np.ndarray | None:
    if node is None or node.op_type != "Constant" or not node.attribute:
        return None
    attr = node.attribute[0]
    return numpy_helper.to_array(attr.t) if attr.name == "value" else None


def integer_ranges(model: onnx.ModelProto) -> int:
    """Rewrite ``Range(0.0, Cast<float>(n), 1.0)`` as ``Cast<float>(Range(0, n, 1))``, in place.

    The decode's grid ``arange(h, dtype=float)`` traces to a float Range whose limit is a
    Cast of an int64 shape value; OpenCV DNN rejects that mix, and the integer Range followed
    by one Cast gives the same values exactly (indices are small integers).

    Returns:
        The number of Range nodes rewritten.
    """
    g = model.graph
    producer = {out: node for node in g.node for out in node.output}
    nodes, count = [], 0
    for node in g.node:
        cast = producer.get(node.input[1]) if node.op_type == "Range" else None
        start, delta = (_constant_value(producer.get(n)) for n in (node.input[0], node.input[2])) \
            if cast is not None else (None, None)
        if cast is None or cast.op_type != "Cast" or start is None or delta is None or \
                float(start) != 0.0 or float(delta) != 1.0:
            nodes.append(node)
            continue
        p = f"int_range/{count}/"
        g.initializer.extend([numpy_helper.from_array(np.array(0, np.int64), p + "start"),
                              numpy_helper.from_array(np.array(1, np.int64), p + "delta")])
        nodes += [helper.make_node("Range", [p + "start", cast.input[0], p + "delta"],
                                   [p + "out"], name=p + "Range"),
                  helper.make_node("Cast", [p + "out"], [node.output[0]], to=TensorProto.FLOAT,
                                   name=p + "Cast")]
        count += 1
    del g.node[:]
    g.node.extend(nodes)
    remove_unused_constants(model)
    return count


def remove_unused_constants(model: onnx.ModelProto) -> int:
    """Drop Constant nodes whose output nothing reads (left behind by rewrites), in place.

    Returns:
        The number of nodes removed.
    """
    g = model.graph
    used = {name for node in g.node for name in node.input} | {o.name for o in g.output}
    keep = [n for n in g.node if n.op_type != "Constant" or n.output[0] in used]
    removed = len(g.node) - len(keep)
    del g.node[:]
    g.node.extend(keep)
    return removed


def space_to_depth_input_convs(model: onnx.ModelProto) -> int:
    """Rewrite each stride-2 convolution with an even kernel that reads a graph input as
    ``SpaceToDepth(2)`` and a convolution of half the kernel on the rearranged input, in place.

    A k x k stride-2 convolution (k = 2m, m odd, padding m - 1: 6x6 with 2, YOLOv5's stem) of
    a C-channel image of even sides equals an m x m stride-1 convolution (padding
    r = (m - 1) / 2) of its 4C-channel space-to-depth, with
    ``W'[o, (2a + b) C + c, p, q] = W[o, c, 2p + a, 2q + b]`` (ONNX's SpaceToDepth channel
    order). The int8 model wants it so: onnxruntime's integer convolution is slower than the
    float one on three input channels and fast on twelve.
    Other input convolutions (odd kernels, stride 1, groups, dilation) are left as they are.

    Returns:
        The number of convolutions rewritten.
    """
    g = model.graph
    inputs = {i.name for i in g.input}
    inits = {i.name: i for i in g.initializer}
    nodes, count = [], 0
    for node in g.node:
        attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
        weight = inits.get(node.input[1]) if node.op_type == "Conv" and len(node.input) > 1 \
            else None
        if weight is None or node.input[0] not in inputs or not _even_stride2(attrs, weight):
            nodes.append(node)
            continue
        w = numpy_helper.to_array(weight)
        o, c, k, _ = w.shape
        m = k // 2
        r = (m - 1) // 2
        # w[o, c, 2p + a, 2q + b] -> w2[o, a, b, c, p, q] -> (o, 4c, m, m)
        w2 = w.reshape(o, c, m, 2, m, 2).transpose(0, 3, 5, 1, 2, 4).reshape(o, 4 * c, m, m)
        p = f"s2d/{count}/"
        g.initializer.append(numpy_helper.from_array(np.ascontiguousarray(w2), p + "W"))
        nodes += [helper.make_node("SpaceToDepth", [node.input[0]], [p + "x"], blocksize=2,
                                   name=p + "SpaceToDepth"),
                  helper.make_node("Conv", [p + "x", p + "W", *node.input[2:]], list(node.output),
                                   kernel_shape=[m, m], strides=[1, 1],
                                   pads=[r] * 4, name=node.name or p + "Conv")]
        count += 1
    del g.node[:]
    g.node.extend(nodes)
    used = {name for node in g.node for name in node.input}
    keep = [i for i in g.initializer if i.name in used]
    del g.initializer[:]
    g.initializer.extend(keep)
    return count


def _even_stride2(attrs: dict, weight: onnx.TensorProto) -> bool:
    """A 2D convolution of stride 2 whose output is half its input: an even square kernel
    k = 2m with m odd and padding m - 1 on every side (6x6 with 2, 2x2 with 0)."""
    if len(weight.dims) != 4 or weight.dims[2] != weight.dims[3]:
        return False
    k = weight.dims[2]
    pads = list(attrs.get("pads", [0, 0, 0, 0]))
    return (k % 4 == 2 and pads == [k // 2 - 1] * 4 and list(attrs.get("strides", [1, 1])) == [2, 2]
            and attrs.get("group", 1) == 1 and set(attrs.get("dilations", [1, 1])) == {1}
            and attrs.get("auto_pad", b"NOTSET") in (b"NOTSET", "NOTSET"))
