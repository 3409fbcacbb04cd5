"""The ONNX graph run in torch equals onnxruntime on every supported op, passes gradients, refuses other ops."""

from __future__ import annotations

import numpy as np
import pytest
import torch

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from onnx import TensorProto, helper, numpy_helper

from davis_rig.attack_aps.onnx_graph import OnnxGraph
from davis_rig.errors import ModelFormatError


def _init(name, array):
    return numpy_helper.from_array(np.asarray(array), name)


def _model(path, nodes, inits, out_shape, opset=13):
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 2, 8, 8])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, out_shape)], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def test_every_supported_op_matches_onnxruntime_and_passes_gradients(tmp_path):
    rng = np.random.default_rng(0)
    nodes = [
        helper.make_node("Conv", ["x", "w", "b"], ["c"], kernel_shape=[3, 3], pads=[1, 1, 1, 1], strides=[1, 1]),
        helper.make_node("Sigmoid", ["c"], ["s"]),
        helper.make_node("Mul", ["c", "s"], ["m"]),  # SiLU as Ultralytics exports it
        helper.make_node("MaxPool", ["m"], ["p"], kernel_shape=[3, 3], pads=[1, 1, 1, 1], strides=[1, 1]),
        helper.make_node("Split", ["p", "sizes"], ["p1", "p2"], axis=1),
        helper.make_node("Add", ["p1", "p2"], ["a"]),
        helper.make_node("Sub", ["a", "p2"], ["d"]),
        helper.make_node("Div", ["d", "two"], ["h"]),
        helper.make_node("Resize", ["h", "", "scales"], ["r"], mode="nearest",
                         coordinate_transformation_mode="asymmetric", nearest_mode="floor"),
        helper.make_node("Slice", ["r", "starts", "ends", "axes"], ["sl"]),
        helper.make_node("Concat", ["sl", "sl"], ["cat"], axis=1),
        helper.make_node("Reshape", ["cat", "shape"], ["rs"]),
        helper.make_node("Transpose", ["rs"], ["t"], perm=[0, 2, 1]),
        helper.make_node("Softmax", ["t"], ["y"], axis=1),
    ]
    inits = [_init("w", rng.normal(size=(4, 2, 3, 3)).astype(np.float32)),
             _init("b", rng.normal(size=4).astype(np.float32)), _init("sizes", np.array([2, 2], np.int64)),
             _init("two", np.array(2.0, np.float32)), _init("scales", np.array([1, 1, 2, 2], np.float32)),
             _init("starts", np.array([1, 2], np.int64)), _init("ends", np.array([15, -1], np.int64)),
             _init("axes", np.array([2, 3], np.int64)), _init("shape", np.array([1, 4, -1], np.int64))]
    path = _model(tmp_path / "ops.onnx", nodes, inits, [1, 182, 4])
    x = rng.normal(size=(1, 2, 8, 8)).astype(np.float32)
    expected = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"x": x})[0]
    graph = OnnxGraph(path)
    xt = torch.from_numpy(x).requires_grad_(True)
    y = graph(xt)
    assert y.shape == expected.shape
    np.testing.assert_allclose(y.detach().numpy(), expected, rtol=1e-5, atol=1e-6)
    y[:, 0].sum().backward()
    assert xt.grad is not None and xt.grad.abs().sum() > 0


def test_unsupported_op_and_bad_file_refused(tmp_path):
    path = _model(tmp_path / "relu.onnx", [helper.make_node("Relu", ["x"], ["y"])], [], [1, 2, 8, 8])
    with pytest.raises(ModelFormatError, match="Relu"):
        OnnxGraph(path)
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not onnx")
    with pytest.raises(ModelFormatError):
        OnnxGraph(bad)
