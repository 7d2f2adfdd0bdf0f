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
