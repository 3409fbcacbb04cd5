"""Tests for the split RVT step (pre → recur → head): the parts chained equal the whole graph bit for bit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from onnx import TensorProto, helper  # noqa: E402

from davis_rig.errors import ModelFormatError  # noqa: E402
from davis_rig.models.rvt.onnx_split import split_step_graph  # noqa: E402
from davis_rig.models.rvt.ort_runner import RVTOnnxRunner  # noqa: E402

STATE_NAMES = [f"{k}{s}" for s in range(1, 5) for k in ("h", "c")]


def _ops(model) -> set[str]:
    return {node.op_type for node in model.graph.node}


def test_parts_have_the_step_signature_and_keep_every_node_once(mini_onnx):
    model = onnx.load(str(mini_onnx))
    parts = split_step_graph(model)
    assert [i.name for i in parts.pre.graph.input] == ["histogram"]
    assert [o.name for o in parts.pre.graph.output] == [parts.x1_name]
    assert [i.name for i in parts.recur.graph.input] == [parts.x1_name, *STATE_NAMES]
    assert [o.name for o in parts.recur.graph.output] == [f"{n}_out" for n in STATE_NAMES]
    assert [i.name for i in parts.head.graph.input] == ["h2_out", "h3_out", "h4_out"]
    assert [o.name for o in parts.head.graph.output] == ["detections"]
    names = [node.name for part in parts.__dict__.values() if not isinstance(part, str) for node in part.graph.node]
    assert len(names) == len(set(names))  # no node computed twice
    assert sorted(names) == sorted(node.name for node in model.graph.node)
    assert "Split" in _ops(parts.recur) and "Loop" not in _ops(parts.recur)  # the ConvLSTM gates: one Split each
    assert {"Conv", "MatMul"} <= _ops(parts.pre) and "Conv" in _ops(parts.head)


def test_loop_bodies_reading_the_outer_graph_are_kept(tmp_path, monkeypatch):
    # graphs exported while the ConvLSTM used tensor_split write each gate split as a Loop whose body reads tensors
    # of the outer graph: the split keeps those producers in the same part (such a graph is exported here by
    # putting tensor_split back for the export)
    torch = pytest.importorskip("torch")
    from davis_rig.models.rvt.checkpoint import load_detector
    from davis_rig.models.rvt.onnx_export import export_step_onnx

    def tensor_split_as_before(tensor, sizes, dim=0):
        if isinstance(sizes, int):
            return torch.tensor_split(tensor, tensor.shape[dim] // sizes, dim=dim)
        return torch.tensor_split(tensor, [int(sum(sizes[:k])) for k in range(1, len(sizes))], dim=dim)

    model = load_detector(Path(__file__).resolve().parents[2] / "fixtures" / "rvt_mini_fixture.safetensors")
    with monkeypatch.context() as patch:
        patch.setattr(torch, "split", tensor_split_as_before)
        path = export_step_onnx(model, tmp_path / "loop.onnx")
    parts = split_step_graph(onnx.load(str(path)))
    assert "Loop" in _ops(parts.recur)
    runner = RVTOnnxRunner(path, intra_op_threads=1)
    split = runner.split(1)
    hist = np.minimum(np.random.default_rng(4).poisson(0.5, size=(1, 20, 240, 304)), 10).astype(np.uint8)
    decoded, _ = runner.step(hist)
    got_states = split.recur(split.pre(runner.prepare_histogram(hist)), runner.initial_states(1))
    np.testing.assert_array_equal(split.head(got_states), decoded)


def test_chained_parts_equal_whole_steps_bit_for_bit_with_states_carried(mini_onnx):
    runner = RVTOnnxRunner(mini_onnx, intra_op_threads=1)
    split = runner.split(1, 2, 1)
    assert runner.split(1, 2, 1) is split and runner.split() is not split  # cached per thread counts
    rng = np.random.default_rng(3)
    states_whole, states_split = None, runner.initial_states(1)
    for _ in range(3):
        hist = np.minimum(rng.poisson(0.5, size=(1, 20, 240, 304)), 10).astype(np.uint8)
        decoded, states_whole = runner.step(hist, states_whole)
        x = runner.prepare_histogram(hist)
        states_split = split.recur(split.pre(x), states_split)
        np.testing.assert_array_equal(split.head(states_split), decoded)
        for (h_w, c_w), (h_s, c_s) in zip(states_whole, states_split):
            np.testing.assert_array_equal(h_s, h_w)
            np.testing.assert_array_equal(c_s, c_w)


def _graph_with_inputs(path: Path, head_reads_histogram: bool) -> Path:
    """A step-shaped graph: h1 is concatenated with a function of the histogram; the detections read either the
    new h-states only or (not splittable) the histogram too."""
    hw = {1: (64, 80), 2: (32, 40), 3: (16, 20), 4: (8, 10)}
    inputs = [helper.make_tensor_value_info("histogram", TensorProto.FLOAT, [1, 20, 256, 320])]
    outputs = [helper.make_tensor_value_info("detections", TensorProto.FLOAT, [1, 1])]
    nodes = [helper.make_node("MaxPool", ["histogram"], ["pooled"], kernel_shape=[4, 4], strides=[4, 4]),
             helper.make_node("ReduceMax", ["pooled"], ["x1"], keepdims=1, axes=[1]),
             helper.make_node("Concat", ["x1", "h1"], ["mix"], axis=1),
             helper.make_node("ReduceMax", ["mix"], ["h1_out"], keepdims=1, axes=[1])]
    for stage in range(1, 5):
        shape = [1, 1, *hw[stage]]
        for kind in ("h", "c"):
            inputs.append(helper.make_tensor_value_info(f"{kind}{stage}", TensorProto.FLOAT, shape))
            outputs.append(helper.make_tensor_value_info(f"{kind}{stage}_out", TensorProto.FLOAT, shape))
            if (kind, stage) != ("h", 1):
                nodes.append(helper.make_node("Identity", [f"{kind}{stage}"], [f"{kind}{stage}_out"]))
    reads = ["h2_out", "h3_out", "h4_out"] + (["histogram"] if head_reads_histogram else [])
    nodes += [helper.make_node("ReduceMax", [name], [f"m{i}"], keepdims=0) for i, name in enumerate(reads)]
    nodes.append(helper.make_node("Sum", [f"m{i}" for i in range(len(reads))], ["total"]))
    nodes.append(helper.make_node("Reshape", ["total", "one_one"], ["detections"]))
    one_one = helper.make_tensor("one_one", TensorProto.INT64, [2], [1, 1])
    model = helper.make_model(helper.make_graph(nodes, "step_like", inputs, outputs, initializer=[one_one]),
                              opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def test_a_head_reading_the_histogram_is_refused_and_a_clean_one_splits(tmp_path):
    with pytest.raises(ModelFormatError, match="'head' part .* needs the graph input 'histogram'"):
        split_step_graph(onnx.load(str(_graph_with_inputs(tmp_path / "bad.onnx", True))))
    parts = split_step_graph(onnx.load(str(_graph_with_inputs(tmp_path / "good.onnx", False))))
    assert parts.x1_name == "x1"


def test_a_graph_without_the_lstm_concat_is_refused(tmp_path):
    from tests.helpers.eval_data import oracle_rvt_onnx

    path = oracle_rvt_onnx(tmp_path / "oracle.onnx", np.zeros((1, 7), np.float32))
    with pytest.raises(ModelFormatError, match="no single two-input Concat of h1"):
        split_step_graph(onnx.load(str(path)))
    with pytest.raises(ModelFormatError, match="cannot be split"):
        RVTOnnxRunner(path).split(1)


def test_an_unreadable_file_is_a_model_format_error(tmp_path):
    from davis_rig.models.rvt.onnx_split import split_step_file

    path = tmp_path / "garbage.onnx"
    path.write_bytes(b"\x00not an onnx model")
    with pytest.raises(ModelFormatError, match="onnx cannot read the model"):
        split_step_file(path)
