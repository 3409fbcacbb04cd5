"""Tests for the ONNX export of one recurrent RVT step: graph signature, metadata, ORT vs PyTorch over 3 steps.

ORT vs PyTorch is checked on the mini fixture and on RVT-T with the fixture weights from ``shared/rvt/``
(skipped when that folder is absent; export + 3 steps take ~9 s on the loaded 2-core dev box).
``benchmarks/model.py`` reports the same comparison for random RVT-T/B weights.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from davis_rig.models.rvt import RVTConfig  # noqa: E402
from davis_rig.models.rvt.checkpoint import load_detector  # noqa: E402
from davis_rig.models.rvt.detector import RVTDetector, pad_to_input  # noqa: E402
from davis_rig.models.rvt.onnx_export import (  # noqa: E402
    ONNX_FORMAT,
    export_step_onnx,
    state_input_names,
    state_output_names,
)

MINI_PATH = Path(__file__).resolve().parents[2] / "fixtures" / "rvt_mini_fixture.safetensors"


@pytest.fixture(scope="module")
def mini_model() -> RVTDetector:
    return load_detector(MINI_PATH)


@pytest.fixture(scope="module")
def mini_onnx(mini_model, tmp_path_factory) -> Path:
    return export_step_onnx(mini_model, tmp_path_factory.mktemp("onnx") / "rvt_mini_step.onnx")


def _session(path: Path):
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])


def _compare_three_steps(model: RVTDetector, onnx_path: Path, hists: np.ndarray) -> dict[str, float]:
    """Run PyTorch and ORT side by side over the steps, states carried separately; return max abs diffs."""
    session = _session(onnx_path)
    torch_states = None
    ort_states = [np.zeros(shape, np.float32) for pair in model.config.state_shapes(hists.shape[1]) for shape in pair]
    diffs = {"scores": 0.0, "boxes_rel": 0.0, "boxes_abs": 0.0, "states": 0.0}
    for step in range(hists.shape[0]):
        x = pad_to_input(torch.from_numpy(hists[step].astype(np.float32)))
        with torch.no_grad():
            decoded, torch_states = model(x, torch_states)
        outputs = session.run(None, {"histogram": x.numpy(), **dict(zip(state_input_names(), ort_states))})
        ort_decoded, ort_states = outputs[0], outputs[1:]
        ref = decoded.numpy()
        diffs["scores"] = max(diffs["scores"], float(np.abs(ort_decoded[..., 4:] - ref[..., 4:]).max()))
        box_err = np.abs(ort_decoded[..., :4] - ref[..., :4])
        diffs["boxes_abs"] = max(diffs["boxes_abs"], float(box_err.max()))
        diffs["boxes_rel"] = max(diffs["boxes_rel"], float((box_err / np.maximum(np.abs(ref[..., :4]), 1.0)).max()))
        flat_torch = [t.numpy() for pair in torch_states for t in pair]
        diffs["states"] = max(diffs["states"], max(float(np.abs(a - b).max()) for a, b in zip(ort_states, flat_torch)))
    return diffs


def test_graph_signature_checker_and_metadata(mini_model, mini_onnx):
    proto = onnx.load(str(mini_onnx))
    onnx.checker.check_model(proto, full_check=True)
    inputs = {v.name: [d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim] for v in proto.graph.input}
    outputs = {v.name: [d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim] for v in proto.graph.output}
    assert list(inputs) == ["histogram", *state_input_names()]
    assert list(outputs) == ["detections", *state_output_names()]
    assert inputs["histogram"] == ["batch", 20, 256, 320]
    assert outputs["detections"] == ["batch", 1680, 7]
    for stage, (shape, _) in enumerate(mini_model.config.state_shapes(1), start=1):
        assert inputs[f"h{stage}"] == ["batch", *shape[1:]]
        assert outputs[f"c{stage}_out"] == ["batch", *shape[1:]]
    meta = {p.key: p.value for p in proto.metadata_props}
    assert meta["format"] == ONNX_FORMAT
    assert RVTConfig.from_dict(json.loads(meta["config"])) == mini_model.config
    assert json.loads(meta["state_names"]) == list(state_input_names())


def test_ort_matches_pytorch_over_three_steps_with_states(mini_model, mini_onnx, mini_fixture):
    hists = mini_fixture["input.hist_uint8_unpadded"][:, None]  # [T, 1, 20, 240, 304]
    diffs = _compare_three_steps(mini_model, mini_onnx, hists)
    print(f"mini ORT vs PyTorch max abs diff over 3 steps: {diffs}")
    assert diffs["scores"] <= 1e-4
    assert diffs["boxes_rel"] <= 1e-3
    assert diffs["states"] <= 1e-4


def test_rvt_t_ort_matches_pytorch_over_three_steps_with_states(rvt_t_fixture, tmp_path):
    """The ≤ 1e-4 score bound on the full-size model: RVT-T with the fixture's (non-trivial) weights."""
    model = load_detector(rvt_t_fixture.path)
    assert model.config.name == "RVT-T"
    onnx_path = export_step_onnx(model, tmp_path / "rvt_t_step.onnx")
    hists = rvt_t_fixture["input.hist_uint8_unpadded"][:, None]  # [T, 1, 20, 240, 304]
    diffs = _compare_three_steps(model, onnx_path, hists)
    report = ", ".join(f"{key} {value:.2e}" for key, value in diffs.items())
    print(f"RVT-T ORT vs PyTorch max abs diff over 3 steps: {report}")
    assert diffs["scores"] <= 1e-4, report
    assert diffs["states"] <= 1e-4, report
    assert diffs["boxes_rel"] <= 1e-3, report


def test_dynamic_batch_equals_single_runs(mini_onnx, mini_fixture):
    session = _session(mini_onnx)
    hists = mini_fixture["input.hist_uint8_unpadded"].astype(np.float32)
    x = np.zeros((3, 20, 256, 320), np.float32)
    x[:, :, :240, :304] = hists
    zeros = {name: np.zeros((3, *session.get_inputs()[i + 1].shape[1:]), np.float32)
             for i, name in enumerate(state_input_names())}
    batched = session.run(["detections"], {"histogram": x, **zeros})[0]
    assert batched.shape == (3, 1680, 7)
    for b in range(3):
        single = session.run(["detections"], {"histogram": x[b : b + 1], **{k: v[:1] for k, v in zeros.items()}})[0]
        np.testing.assert_allclose(batched[b], single[0], rtol=1e-5, atol=1e-5)


def test_fixed_batch_export_and_training_flag_restored(tmp_path):
    model = RVTDetector(RVTConfig.mini())  # random weights, train mode
    assert model.training
    path = export_step_onnx(model, tmp_path / "fixed.onnx", batch_dynamic=False, example_batch=2)
    assert model.training
    proto = onnx.load(str(path))
    assert [d.dim_value for d in proto.graph.input[0].type.tensor_type.shape.dim] == [2, 20, 256, 320]
    assert [d.dim_value for d in proto.graph.output[0].type.tensor_type.shape.dim] == [2, 1680, 7]
