"""Graph rewrites: integer Range (OpenCV DNN) and inlined shared initializers keep values."""

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

from lunarnav_ml.export.graph_passes import (
    inline_shared_initializers,
    integer_ranges,
    space_to_depth_input_convs,
)


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


def _stride2_conv(k, pad, c_in=3):
    rng = np.random.default_rng(k)
    w = numpy_helper.from_array(rng.standard_normal((8, c_in, k, k)).astype(np.float32), "w")
    b = numpy_helper.from_array(rng.standard_normal(8).astype(np.float32), "b")
    node = helper.make_node("Conv", ["x", "w", "b"], ["y"], kernel_shape=[k, k], strides=[2, 2],
                            pads=[pad] * 4)
    graph = helper.make_graph(
        [node], "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, c_in, "h", "w"])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 8, None, None])], [w, b])
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def test_space_to_depth_rewrite_is_exact():
    x = {"x": np.random.default_rng(0).random((1, 3, 64, 96), dtype=np.float32)}
    for k, pad in ((6, 2), (2, 0), (10, 4)):
        model = _stride2_conv(k, pad)
        before = _run(model, x)[0]
        assert space_to_depth_input_convs(model) == 1
        onnx.checker.check_model(model)
        assert [n.op_type for n in model.graph.node] == ["SpaceToDepth", "Conv"]
        assert [i.name for i in model.graph.initializer if i.name == "w"] == []  # old weight gone
        after = _run(model, x)[0]
        assert after.shape == before.shape == (1, 8, 32, 48)
        np.testing.assert_allclose(after, before, atol=2e-5 * k * k)


def test_space_to_depth_leaves_other_convs_alone():
    # odd kernels, padding that does not halve the image: not rewritten
    for k, pad in ((3, 1), (4, 2), (6, 0), (6, 4)):
        model = _stride2_conv(k, pad)
        assert space_to_depth_input_convs(model) == 0
        assert [n.op_type for n in model.graph.node] == ["Conv"]
