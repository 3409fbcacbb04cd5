"""davis_rig.models: paths of the bundled default detector (present, absent) and that the bundle loads."""

from __future__ import annotations

import pytest

import davis_rig.models as models
from davis_rig.errors import MissingDependencyError


@pytest.mark.parametrize(("function", "name", "hint"), [
    (models.default_detector_path, "rvt_default.onnx", "--detector RVT_STEP.onnx"),
    (models.default_detector_weights_path, "rvt_default.safetensors", "RVT checkpoint explicitly"),
])
def test_missing_bundle_raises_with_the_path_and_a_hint(monkeypatch, tmp_path, function, name, hint):
    monkeypatch.setattr(models, "DEFAULT_DETECTOR_DIR", tmp_path)
    with pytest.raises(MissingDependencyError) as info:
        function()
    assert str(tmp_path / name) in str(info.value) and hint in str(info.value)


@pytest.mark.parametrize(("function", "name"), [
    (models.default_detector_path, "rvt_default.onnx"),
    (models.default_detector_weights_path, "rvt_default.safetensors"),
])
def test_present_bundle_is_returned(monkeypatch, tmp_path, function, name):
    monkeypatch.setattr(models, "DEFAULT_DETECTOR_DIR", tmp_path)
    (tmp_path / name).write_bytes(b"x")
    assert function() == tmp_path / name


def test_weights_round_trip_through_load_detector(monkeypatch, tmp_path):
    torch = pytest.importorskip("torch")
    pytest.importorskip("safetensors")
    from davis_rig.models.rvt.checkpoint import load_detector, save_safetensors
    from davis_rig.models.rvt.config import RVTConfig
    from davis_rig.models.rvt.detector import RVTDetector

    torch.manual_seed(0)
    model = RVTDetector(RVTConfig.mini()).eval()
    monkeypatch.setattr(models, "DEFAULT_DETECTOR_DIR", tmp_path)
    save_safetensors(model.half(), tmp_path / models.DEFAULT_WEIGHTS_FILE)
    loaded = load_detector(models.default_detector_weights_path())
    assert loaded.config == RVTConfig.mini()
    for key, value in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value.float())


def test_the_shipped_bundle_loads_when_installed():
    """The real bundle (when this copy ships it): weights rebuild their architecture, the ONNX opens."""
    try:
        weights, onnx_path = models.default_detector_weights_path(), models.default_detector_path()
    except MissingDependencyError:
        pytest.skip("no bundled default detector in this copy")
    torch = pytest.importorskip("torch")
    from davis_rig.models.rvt.checkpoint import load_detector, metadata_config

    model = load_detector(weights)
    assert model.config == metadata_config(weights)
    assert weights.stat().st_size + onnx_path.stat().st_size <= 30 * 2**20  # the bundled detector stays small: <= 30 MB in all
    assert next(model.parameters()).dtype == torch.float32
    onnx = pytest.importorskip("onnx")
    onnx.checker.check_model(str(onnx_path))
