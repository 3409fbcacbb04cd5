"""Tests for RVTOnnxRunner: graph validation, padding, states, stream scoring, and the no-torch property."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from onnx import TensorProto, helper  # noqa: E402

from davis_rig.errors import FormatError, ModelFormatError, ShapeError  # noqa: E402
from davis_rig.events import stacked_histograms  # noqa: E402
from davis_rig.models.rvt.ort_runner import RVTOnnxRunner  # noqa: E402
from davis_rig.models.rvt.postprocess import postprocess  # noqa: E402

MINI_PATH = Path(__file__).resolve().parents[2] / "fixtures" / "rvt_mini_fixture.safetensors"
STATE_NAMES = [f"{k}{s}" for s in range(1, 5) for k in ("h", "c")]


@pytest.fixture(scope="module")
def runner(mini_onnx) -> RVTOnnxRunner:
    return RVTOnnxRunner(mini_onnx, intra_op_threads=1)


def _events(fx):
    return tuple(fx[f"input.events_{k}"] for k in ("x", "y", "t_us", "p"))


# --- the runner on the exported mini model ------------------------------------------------------------------------
def test_signature_and_initial_states(runner):
    sig = runner.signature
    assert sig.in_res_hw == (256, 320)
    assert sig.state_channels == (8, 8, 16, 32)
    assert sig.num_anchors == 1680 and sig.num_outputs == 7 and sig.batch is None
    assert runner.config.name == "RVT-mini"
    states = runner.initial_states(2)
    assert [h.shape for h, _ in states] == [(2, 8, 64, 80), (2, 8, 32, 40), (2, 16, 16, 20), (2, 32, 8, 10)]
    assert all(not h.any() and not c.any() and h.dtype == np.float32 for h, c in states)
    assert "RVT-mini" in repr(runner)
    decoded, new_states = runner.step(np.zeros((2, 20, 240, 304), np.uint8), states)  # dynamic batch
    assert decoded.shape == (2, 1680, 7)
    assert [h.shape for h, _ in new_states] == [h.shape for h, _ in states]


def test_uint8_unpadded_and_float_padded_inputs_agree(runner, mini_fixture):
    hist = mini_fixture["input.hist_uint8_unpadded"][:1]
    padded = np.zeros((1, 20, 256, 320), np.float32)
    padded[:, :, :240, :304] = hist
    decoded_a, states_a = runner.step(hist)
    decoded_b, states_b = runner.step(padded, runner.initial_states(1))
    np.testing.assert_array_equal(decoded_a, decoded_b)
    assert decoded_a.shape == (1, 1680, 7) and decoded_a.dtype == np.float32
    for (ha, ca), (hb, cb) in zip(states_a, states_b):
        np.testing.assert_array_equal(ha, hb)
        np.testing.assert_array_equal(ca, cb)


def test_steps_with_states_track_the_official_outputs(runner, mini_fixture):
    states = None
    for step in range(3):
        decoded, states = runner.step(mini_fixture["input.hist_uint8_unpadded"][step : step + 1], states)
        ref = mini_fixture[f"step{step}.head.decoded"]
        np.testing.assert_allclose(decoded[..., 4:], ref[..., 4:], atol=1e-4, rtol=0)
        np.testing.assert_allclose(decoded[..., :4], ref[..., :4], rtol=1e-3, atol=1e-2)
        h4 = states[3][0]
        np.testing.assert_allclose(h4, mini_fixture[f"step{step}.backbone.stage4"], atol=1e-4, rtol=0)


def test_score_stream_is_histogram_step_postprocess(runner, mini_fixture):
    x, y, t_us, p = _events(mini_fixture)
    ends = mini_fixture["input.window_end_ts_us"]
    detections = runner.score_stream(x, y, t_us, p, ends, conf_threshold=0.1)
    assert len(detections) == 3
    hists = stacked_histograms((x, y, t_us, p), ends)
    states = None
    for step in range(3):
        decoded, states = runner.step(hists[step : step + 1], states)
        (expected,) = postprocess(decoded, 0.1)
        np.testing.assert_array_equal(detections[step], expected)
        # and close to the official detections (borderline boxes could flip at 1e-6 score differences)
        official = mini_fixture[f"step{step}.post.conf0p1"]
        assert abs(detections[step].shape[0] - official.shape[0]) <= 2
        np.testing.assert_allclose(detections[step][:10, 4:], official[:10, 4:], atol=1e-4)


def test_score_stream_in_chunks_equals_one_pass(runner, mini_fixture):
    x, y, t_us, p = _events(mini_fixture)
    ends = mini_fixture["input.window_end_ts_us"]
    whole = runner.score_stream(x, y, t_us, p, ends, conf_threshold=0.1)
    first, states = runner.score_stream(x, y, t_us, p, ends[:1], conf_threshold=0.1, return_states=True)
    rest = runner.score_stream(x, y, t_us, p, ends[1:], conf_threshold=0.1, states=states)
    for a, b in zip(whole, first + rest):
        np.testing.assert_array_equal(a, b)


def test_score_stream_correct_time_scores_the_officially_corrected_stream(runner, mini_fixture):
    x, y, t_us, p = _events(mini_fixture)
    ends = mini_fixture["input.window_end_ts_us"]
    late = np.zeros(t_us.shape[0], bool)
    late[1000::997] = True  # every 997th event arrives 3 ms late, in each of the 3 windows
    t_late = t_us - np.where(late, 3_000, 0)
    assert np.any(np.diff(t_late) < 0)
    with pytest.raises(FormatError, match="non-decreasing"):
        runner.score_stream(x, y, t_late, p, ends, conf_threshold=0.1)
    corrected = runner.score_stream(x, y, t_late, p, ends, conf_threshold=0.1, correct_time=True)
    expected = runner.score_stream(x, y, np.maximum.accumulate(t_late), p, ends, conf_threshold=0.1)
    assert len(corrected) == len(expected) == 3
    for a, b in zip(corrected, expected):
        np.testing.assert_array_equal(a, b)
    # chunk by chunk, cut where the corrected time reaches window 2's start (events at that instant lie in both
    # windows): the chunk's first event is then not late, so correcting each chunk alone equals one pass
    late_after = int(np.searchsorted(t_us, ends[0], side="right")) + 5
    t_late[late_after] = t_us[late_after] - 3_000
    corrected_t = np.maximum.accumulate(t_late)
    expected = runner.score_stream(x, y, corrected_t, p, ends, conf_threshold=0.1)
    start_2 = int(np.searchsorted(corrected_t, ends[0], side="left"))
    end_1 = int(np.searchsorted(corrected_t, ends[0], side="right"))
    assert np.any(t_late[start_2:] < t_late[:start_2].max())  # late events in the second chunk
    first, states = runner.score_stream(x[:end_1], y[:end_1], t_late[:end_1], p[:end_1], ends[:1],
                                        conf_threshold=0.1, return_states=True, correct_time=True)
    rest = runner.score_stream(x[start_2:], y[start_2:], t_late[start_2:], p[start_2:], ends[1:],
                               conf_threshold=0.1, states=states, correct_time=True)
    for a, b in zip(first + rest, expected):
        np.testing.assert_array_equal(a, b)


def test_wrong_histogram_resolution_and_states_raise_shape_error(runner):
    with pytest.raises(ShapeError, match=r"240, 304\] \(padded automatically\) or \[B, 20, 256, 320\]"):
        runner.step(np.zeros((1, 20, 300, 400), np.uint8))
    with pytest.raises(ShapeError, match="expected spatial size"):
        runner.step(np.zeros((1, 20, 128, 160), np.uint8))
    with pytest.raises(ShapeError, match=r"expected \[B, 20, H, W\]"):
        runner.step(np.zeros((20, 240, 304), np.uint8))
    with pytest.raises(ShapeError, match=r"expected \[B, 20, H, W\]"):
        runner.step(np.zeros((1, 10, 240, 304), np.uint8))
    with pytest.raises(ShapeError, match="state of stage 1"):
        runner.step(np.zeros((2, 20, 240, 304), np.uint8), runner.initial_states(1))
    with pytest.raises(ShapeError, match="4 \\(h, c\\) pairs"):
        runner.step(np.zeros((1, 20, 240, 304), np.uint8), runner.initial_states(1)[:3])


# --- graph validation ---------------------------------------------------------------------------------------------
def _save(graph, path: Path, metadata: dict[str, str] | None = None) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    for key, value in (metadata or {}).items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save(model, str(path))
    return path


def test_bogus_graph_raises_model_format_error(tmp_path):
    graph = helper.make_graph(
        [helper.make_node("Identity", ["x"], ["y"])],
        "bogus",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 3])],
    )
    with pytest.raises(ModelFormatError, match="not an RVT step graph"):
        RVTOnnxRunner(_save(graph, tmp_path / "bogus.onnx"))


def _identity_step_graph(hist_hw, state_hw_scale=1, detections_shape=("B", 1680, 7), hist_channels=20,
                         state_base_hw=(256, 320)):
    """A graph with the RVT step names whose shapes can be made wrong on purpose (identity-like ops)."""
    height, width = hist_hw
    inputs = [helper.make_tensor_value_info("histogram", TensorProto.FLOAT, ["B", hist_channels, height, width])]
    outputs = [helper.make_tensor_value_info("detections", TensorProto.FLOAT, list(detections_shape))]
    nodes = [helper.make_node("Reshape", ["histogram", "detections_shape"], ["detections"])]  # never run
    target = helper.make_tensor("detections_shape", TensorProto.INT64, [3], [0, *detections_shape[1:]])
    for stage, (stride, channels) in enumerate(zip((4, 8, 16, 32), (8, 8, 16, 32)), start=1):
        state_h, state_w = (size // stride * state_hw_scale for size in state_base_hw)
        shape = ["B", channels, state_h, state_w]
        for kind in ("h", "c"):
            inputs.append(helper.make_tensor_value_info(f"{kind}{stage}", TensorProto.FLOAT, shape))
            outputs.append(helper.make_tensor_value_info(f"{kind}{stage}_out", TensorProto.FLOAT, shape))
            nodes.append(helper.make_node("Identity", [f"{kind}{stage}"], [f"{kind}{stage}_out"]))
    return helper.make_graph(nodes, "fake_step", inputs, outputs, initializer=[target])


def test_wrong_shapes_raise_model_format_error(tmp_path):
    bad_hist = _save(_identity_step_graph((128, 160)), tmp_path / "bad_hist.onnx")
    with pytest.raises(ModelFormatError, match=r"h1: expected \[B, 8, 32, 40\]"):
        RVTOnnxRunner(bad_hist)
    bad_states = _save(_identity_step_graph((256, 320), state_hw_scale=2), tmp_path / "bad_states.onnx")
    with pytest.raises(ModelFormatError, match=r"h1: expected \[B, 8, 64, 80\], got \['B', 8, 128, 160\]"):
        RVTOnnxRunner(bad_states)
    bad_out = _save(_identity_step_graph((256, 320), detections_shape=("B", 999, 7)), tmp_path / "bad_out.onnx")
    with pytest.raises(ModelFormatError, match="detections: expected"):
        RVTOnnxRunner(bad_out)
    config = json.dumps({"embed_dim": 16, "dim_head": 8})  # channels 16/32/64/128 disagree with the graph
    bad_meta = _save(_identity_step_graph((256, 320)), tmp_path / "bad_meta.onnx", {"config": config})
    with pytest.raises(ModelFormatError, match=r"h1: expected \[B, 16, 64, 80\]"):
        RVTOnnxRunner(bad_meta)


def test_self_consistent_graph_with_wrong_channels_or_too_small_input_raises_model_format_error(tmp_path):
    # consistent states and output, so only the channel count / input size can reject them, at load (not at step)
    channels = _save(_identity_step_graph((256, 320), hist_channels=10), tmp_path / "channels.onnx")
    with pytest.raises(ModelFormatError, match=r"10 input channels, expected 20 \(2 polarities x 10 time bins"):
        RVTOnnxRunner(channels)
    small_graph = _identity_step_graph((128, 160), detections_shape=("B", 420, 7), state_base_hw=(128, 160))
    small = _save(small_graph, tmp_path / "small.onnx")
    with pytest.raises(ModelFormatError, match=r"input 128x160 \(h x w\) is smaller than the 240x304 event frame"):
        RVTOnnxRunner(small)


def test_graph_with_consistent_fake_shapes_is_accepted(tmp_path):
    runner = RVTOnnxRunner(_save(_identity_step_graph((256, 320)), tmp_path / "ok.onnx"))
    assert runner.signature.state_channels == (8, 8, 16, 32)
    assert runner.config is None


def test_unloadable_file_raises_model_format_error(tmp_path):
    path = tmp_path / "garbage.onnx"
    path.write_bytes(b"not an onnx model")
    with pytest.raises(ModelFormatError, match="cannot load"):
        RVTOnnxRunner(path)


# --- scoring without torch ------------------------------------------------------------------------------------------
def test_runner_scores_a_stream_with_torch_imports_blocked(mini_onnx, runner, mini_fixture, tmp_path):
    out_path = tmp_path / "scores.npz"
    script = textwrap.dedent(
        f"""
        import sys
        sys.modules["torch"] = None  # any "import torch" now raises ImportError
        import numpy as np
        from safetensors.numpy import load_file
        from davis_rig.models.rvt.ort_runner import RVTOnnxRunner
        fx = load_file({str(MINI_PATH)!r})
        runner = RVTOnnxRunner({str(mini_onnx)!r}, intra_op_threads=1)
        dets = runner.score_stream(fx["input.events_x"], fx["input.events_y"], fx["input.events_t_us"],
                                   fx["input.events_p"], fx["input.window_end_ts_us"], conf_threshold=0.1)
        torch_modules = [m for m in sys.modules if m == "torch" or m.startswith("torch.")]
        assert sys.modules["torch"] is None and torch_modules == ["torch"], torch_modules
        np.savez({str(out_path)!r}, *dets)
        """
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    expected = runner.score_stream(*_events(mini_fixture), mini_fixture["input.window_end_ts_us"], conf_threshold=0.1)
    with np.load(out_path) as saved:
        got = [saved[f"arr_{i}"] for i in range(len(saved.files))]
    assert len(got) == 3
    for a, b in zip(got, expected):
        np.testing.assert_array_equal(a, b)
