"""facesynth.onnx.passes.int32_indices: int64 index chains of GatherElements become int32,
same outputs in ONNX Runtime; chains with outside consumers are left alone."""

from __future__ import annotations

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

from facesynth.onnx.passes import int32_indices


def _model(share: bool):
    # out = GatherElements(data, Cast(x) * 2 + offset); optionally also expose the index
    nodes = [
        helper.make_node("Cast", ["x"], ["xi"], to=TensorProto.INT64),
        helper.make_node("Mul", ["xi", "two"], ["x2"]),
        helper.make_node("Add", ["x2", "offset"], ["idx"]),
        helper.make_node("GatherElements", ["data", "idx"], ["out"], axis=1),
    ]
    outputs = [helper.make_tensor_value_info("out", TensorProto.FLOAT, [1, 4])]
    if share:
        outputs.append(helper.make_tensor_value_info("idx", TensorProto.INT64, [1, 4]))
    graph = helper.make_graph(
        nodes, "g",
        [helper.make_tensor_value_info("data", TensorProto.FLOAT, [1, 10]),
         helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4])],
        outputs,
        [numpy_helper.from_array(np.array(2, np.int64), "two"),
         numpy_helper.from_array(np.array([[0, 1, 0, 1]], np.int64), "offset")],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=9)


def _run(model, data, x):
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    return sess.run(["out"], {"data": data, "x": x})[0]


def test_int32_chain_same_output():
    data = np.arange(10, dtype=np.float32)[None] * 1.5
    x = np.array([[0.0, 1.0, 2.0, 4.0]], np.float32)
    m = _model(share=False)
    want = _run(m, data, x)
    assert int32_indices(m) == 1
    onnx.checker.check_model(m)
    inits = {t.name: numpy_helper.to_array(t) for t in m.graph.initializer}
    assert inits["two"].dtype == np.int32 and inits["offset"].dtype == np.int32
    np.testing.assert_array_equal(_run(m, data, x), want)
    np.testing.assert_array_equal(want, data[0, [0, 3, 4, 9]][None])


def test_shared_chain_untouched():
    m = _model(share=True)
    before = m.SerializeToString()
    assert int32_indices(m) == 0
    assert m.SerializeToString() == before


def test_shared_chain_between_gathers_rewritten_together():
    # one index (Cast(x) * 2 + offset) read by two gathers on different data: one group
    nodes = [
        helper.make_node("Cast", ["x"], ["xi"], to=TensorProto.INT64),
        helper.make_node("Mul", ["xi", "two"], ["x2"]),
        helper.make_node("Add", ["x2", "offset"], ["idx"]),
        helper.make_node("GatherElements", ["data", "idx"], ["out"], axis=1),
        helper.make_node("GatherElements", ["data2", "idx"], ["out2"], axis=1),
    ]
    graph = helper.make_graph(
        nodes, "g",
        [helper.make_tensor_value_info("data", TensorProto.FLOAT, [1, 10]),
         helper.make_tensor_value_info("data2", TensorProto.FLOAT, [1, 10]),
         helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4])],
        [helper.make_tensor_value_info("out", TensorProto.FLOAT, [1, 4]),
         helper.make_tensor_value_info("out2", TensorProto.FLOAT, [1, 4])],
        [numpy_helper.from_array(np.array(2, np.int64), "two"),
         numpy_helper.from_array(np.array([[0, 1, 0, 1]], np.int64), "offset")],
    )
    m = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=9)
    feed = {"data": np.arange(10, dtype=np.float32)[None], "data2": -np.arange(10, dtype=np.float32)[None],
            "x": np.array([[0.0, 1.0, 2.0, 4.0]], np.float32)}

    def run(model):
        return ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, feed)

    want = run(m)
    assert int32_indices(m) == 2
    onnx.checker.check_model(m)
    assert {numpy_helper.to_array(t).dtype for t in m.graph.initializer} == {np.dtype(np.int32)}
    for got, exp in zip(run(m), want, strict=True):
        np.testing.assert_array_equal(got, exp)
    np.testing.assert_array_equal(want[1], -feed["data"][:, [0, 3, 4, 9]])
