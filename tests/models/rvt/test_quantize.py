"""int8 step graphs (davis_rig.models.rvt.quantize): calibration feeds, the QDQ graph, its metadata and split."""

from __future__ import annotations

import json

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from davis_rig.errors import ModelFormatError  # noqa: E402
from davis_rig.models.rvt.ort_runner import RVTOnnxRunner  # noqa: E402
from davis_rig.models.rvt.quantize import (QUANTIZED_OPS, calibration_feeds, quantization_info,  # noqa: E402
                                           quantize_step_onnx)


def _histograms(seed: int, windows: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.minimum(rng.poisson(0.3, size=(windows, 20, 240, 304)), 10).astype(np.uint8)


@pytest.fixture(scope="module")
def int8_graph(mini_onnx, tmp_path_factory):
    runner = RVTOnnxRunner(mini_onnx, intra_op_threads=1)
    feeds = calibration_feeds(runner, [_histograms(0, 4), _histograms(1, 2)], 6)
    path = tmp_path_factory.mktemp("int8") / "mini_int8.onnx"
    return quantize_step_onnx(mini_onnx, path, feeds, sources=["a", "b"]), feeds


def test_calibration_feeds_carry_the_fp32_states_of_each_sequence(mini_onnx):
    runner = RVTOnnxRunner(mini_onnx, intra_op_threads=1)
    first, second = _histograms(0, 5), _histograms(1, 3)
    feeds = calibration_feeds(runner, [first, second], 4)
    # 4 windows evenly spaced over the 8 end to end: 0, 2, 5, 7 -> windows 0, 2 of the first, 0, 2 of the second
    assert len(feeds) == 4
    np.testing.assert_array_equal(feeds[0]["histogram"], runner.prepare_histogram(first[:1]))
    np.testing.assert_array_equal(feeds[1]["histogram"], runner.prepare_histogram(first[2:3]))
    np.testing.assert_array_equal(feeds[2]["histogram"], runner.prepare_histogram(second[:1]))
    np.testing.assert_array_equal(feeds[3]["histogram"], runner.prepare_histogram(second[2:3]))
    for feed in (feeds[0], feeds[2]):  # a sequence starts from zero states
        assert all(not feed[f"{k}{s}"].any() for s in range(1, 5) for k in "hc")
    states = None
    for window in range(2):
        states = runner.step(first[window : window + 1], states)[1]
    for stage, (h_state, c_state) in enumerate(states, start=1):
        np.testing.assert_array_equal(feeds[1][f"h{stage}"], h_state)
        np.testing.assert_array_equal(feeds[1][f"c{stage}"], c_state)
    # more windows asked for than there are: every window once
    assert len(calibration_feeds(runner, [first[:2], second[:1]], 10)) == 3
    with pytest.raises(ValueError, match="max_windows"):
        calibration_feeds(runner, [first], 0)
    with pytest.raises(ValueError, match="at least one window"):
        calibration_feeds(runner, [first[:0]], 4)


def test_int8_graph_quantizes_conv_and_matmul_keeps_the_signature_and_records_itself(mini_onnx, int8_graph):
    path, feeds = int8_graph
    model = onnx.load(str(path))
    ops = {node.op_type for node in model.graph.node}
    assert {"QuantizeLinear", "DequantizeLinear"} <= ops
    # the quantized weights are the Conv and MatMul ones; no op type is added beyond the Q/DQ pairs
    initializers = {init.name for init in model.graph.initializer}
    consumers = {}
    for node in model.graph.node:
        for name in node.input:
            consumers.setdefault(name, set()).add(node.op_type)
    weights = [node.output[0] for node in model.graph.node
               if node.op_type == "DequantizeLinear" and node.input[0] in initializers]
    assert weights and set().union(*(consumers[name] for name in weights)) == set(QUANTIZED_OPS)
    assert ops - {"QuantizeLinear", "DequantizeLinear"} <= {n.op_type for n in onnx.load(str(mini_onnx)).graph.node}
    fp32_meta = {p.key: p.value for p in onnx.load(str(mini_onnx)).metadata_props}
    meta = {p.key: p.value for p in model.metadata_props}
    assert {k: meta[k] for k in fp32_meta} == fp32_meta
    info = quantization_info(path)
    assert info["ops"] == list(QUANTIZED_OPS) and info["calibration_windows"] == len(feeds) == 6
    assert info["calibration_sources"] == ["a", "b"] and info["fp32_graph"] == mini_onnx.name
    assert quantization_info(mini_onnx) is None
    int8 = RVTOnnxRunner(path, intra_op_threads=1)
    assert int8.signature == RVTOnnxRunner(mini_onnx, intra_op_threads=1).signature


def test_int8_weights_stay_within_7_bits_so_that_avx2_kernels_do_not_saturate(int8_graph):
    # uint8 x int8 pairs summed in 16 bits (VPMADDUBSW, x86 without VNNI): 255 * 63 * 2 fits, 255 * 127 * 2 does not
    model = onnx.load(str(int8_graph[0]))
    weights = [onnx.numpy_helper.to_array(init) for init in model.graph.initializer
               if init.data_type == onnx.TensorProto.INT8]
    assert weights and all(int(np.abs(w.astype(np.int16)).max()) <= 64 for w in weights)
    assert "7 bits" in quantization_info(int8_graph[0])["scheme"]


def test_int8_outputs_follow_fp32_and_its_parts_chain_to_the_whole(mini_onnx, int8_graph):
    path, _ = int8_graph
    fp32, int8 = RVTOnnxRunner(mini_onnx, intra_op_threads=1), RVTOnnxRunner(path, intra_op_threads=1)
    hist = _histograms(7, 3)
    states32 = states8 = None
    for window in range(3):
        decoded32, states32 = fp32.step(hist[window : window + 1], states32)
        decoded8, states8 = int8.step(hist[window : window + 1], states8)
    # not equal (8-bit), but close: the same boxes' scores within a few hundredths (with 8-bit weights an AVX2 CPU
    # without VNNI saturates: 0.055 on average)
    assert not np.array_equal(decoded8, decoded32)
    score32, score8 = (d[0, :, 4] * d[0, :, 5:].max(axis=1) for d in (decoded32, decoded8))
    assert float(np.abs(score8 - score32).mean()) < 0.02
    split = int8.split(1)
    x = int8.prepare_histogram(hist[:1])
    whole, _ = int8.step(x)
    np.testing.assert_array_equal(split.head(split.recur(split.pre(x), int8.initial_states(1))), whole)


def test_refuses_a_quantized_graph_no_feeds_and_a_non_graph(int8_graph, tmp_path):
    path, feeds = int8_graph
    with pytest.raises(ModelFormatError, match="already quantized"):
        quantize_step_onnx(path, tmp_path / "twice.onnx", feeds)
    with pytest.raises(ValueError, match="calibration feed"):
        quantize_step_onnx(path, tmp_path / "none.onnx", [])
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a graph")
    with pytest.raises(ModelFormatError, match="not a loadable"):
        quantize_step_onnx(bad, tmp_path / "x.onnx", feeds)
    assert not (tmp_path / "twice.onnx").exists() and not (tmp_path / "x.onnx").exists()
    assert json.loads(json.dumps(quantization_info(path)))  # plain JSON
