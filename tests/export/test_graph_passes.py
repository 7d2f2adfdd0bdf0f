"""Graph rewrites: integer Range (OpenCV DNN) and inlined shared initializers keep values."""

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

from lunarnav_ml.export.graph_passes import inline_shared_initializers, integer_ranges


def _run(model, feeds):
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    return sess.run(None, feeds)


def test_integer_range_gives_the_same_grid():
    const = lambda name, v: helper.make_node(
        "Constant", [], [name], value=numpy_helper.from_array(np.array(v, np.float32)))
    nodes = [helper.make_node("Shape", ["x"], ["s"], start=1, end=2),
             helper.make_node("Squeeze", ["s"], ["n"]),
             helper.make_node("Cast", ["n"], ["nf"], to=TensorProto.FLOAT),
             const("zero", 0.0), const("one", 1.0),
             helper.make_node("Range", ["zero", "nf", "one"], ["grid"])]
    graph = helper.make_graph(nodes, "g",
                              [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, "n"])],
                              [helper.make_tensor_value_info("grid", TensorProto.FLOAT, ["n"])])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    x = {"x": np.zeros((1, 7), np.float32)}
    before = _run(model, x)[0]
    assert integer_ranges(model) == 1
    onnx.checker.check_model(model)
    ops = [n.op_type for n in model.graph.node]
    assert "Constant" not in ops and ops.count("Range") == 1
    np.testing.assert_array_equal(_run(model, x)[0], before)
    np.testing.assert_array_equal(before, np.arange(7, dtype=np.float32))


def test_shared_initializers_are_inlined():
    w = numpy_helper.from_array(np.arange(3, dtype=np.float32), "w")
    nodes = [helper.make_node("Identity", ["w"], ["w2"]),
             helper.make_node("Add", ["x", "w2"], ["y"])]
    graph = helper.make_graph(nodes, "g",
                              [helper.make_tensor_value_info("x", TensorProto.FLOAT, [3])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [3])], [w])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    inline_shared_initializers(model)
    assert [n.op_type for n in model.graph.node] == ["Add"]
    np.testing.assert_array_equal(_run(model, {"x": np.ones(3, np.float32)})[0], [1, 2, 3])
