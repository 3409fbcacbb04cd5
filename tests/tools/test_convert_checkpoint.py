"""Tests for tools/convert_checkpoint.py on small Lightning-like checkpoints made here."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from davis_rig.models.rvt import RVTConfig  # noqa: E402
from davis_rig.models.rvt.checkpoint import load_detector  # noqa: E402
from davis_rig.models.rvt.detector import RVTDetector  # noqa: E402

TOOL_PATH = Path(__file__).resolve().parents[2] / "tools" / "convert_checkpoint.py"


@pytest.fixture(scope="module")
def tool(load_tool):
    return load_tool("convert_checkpoint")


@pytest.fixture(scope="module")
def lightning_ckpt(tmp_path_factory) -> tuple[Path, dict]:
    """A Lightning-style checkpoint of a random mini model: ``state_dict`` with ``mdl.`` keys plus loop state."""
    torch.manual_seed(0)
    model = RVTDetector(RVTConfig.mini()).eval()
    state = {key: value.clone() for key, value in model.state_dict().items()}
    ckpt = {
        "epoch": 3,
        "global_step": 1200,
        "pytorch-lightning_version": "1.8.6",
        "state_dict": {f"mdl.{key}": value for key, value in state.items()},
        "optimizer_states": [{"state": {}, "param_groups": [{"lr": 2e-4}]}],
        "loops": {"fit_loop": {"epoch_progress": {"current": {"completed": 3}}}},
    }
    path = tmp_path_factory.mktemp("ckpt") / "rvt-mini.ckpt"
    torch.save(ckpt, path)
    return path, state


def test_convert_writes_safetensors_and_onnx_with_the_same_weights(tool, lightning_ckpt, tmp_path, capsys):
    path, state = lightning_ckpt
    code = tool.main([str(path), "--out-dir", str(tmp_path / "out"), "--config", "mini", "--onnx", "--verify"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "376 state-dict entries, all matched the RVT-mini (given) model" in printed
    assert "80,765 parameters" in printed
    assert "verify:" in printed and "scores" in printed
    safetensors_path = tmp_path / "out" / "rvt-mini.safetensors"
    onnx_path = tmp_path / "out" / "rvt-mini_step.onnx"
    assert safetensors_path.is_file() and onnx_path.is_file()

    reloaded = load_detector(safetensors_path)  # config read back from the metadata
    assert reloaded.config == RVTConfig.mini()
    for key, value in reloaded.state_dict().items():
        torch.testing.assert_close(value, state[key], rtol=0, atol=0)

    from davis_rig.models.rvt.ort_runner import RVTOnnxRunner

    runner = RVTOnnxRunner(onnx_path)
    assert runner.config == RVTConfig.mini()
    hist = np.random.default_rng(1).integers(0, 4, size=(1, 20, 240, 304)).astype(np.uint8)
    decoded, _ = runner.step(hist)
    with torch.no_grad():
        expected, _ = reloaded(torch.nn.functional.pad(torch.from_numpy(hist).float(), [0, 16, 0, 16]))
    np.testing.assert_allclose(decoded[..., 4:], expected.numpy()[..., 4:], atol=1e-4, rtol=0)


def test_convert_api_infers_the_config_and_reports(tool, lightning_ckpt, tmp_path):
    path, _ = lightning_ckpt
    report = tool.convert(path, tmp_path)
    assert report.entries == 376
    assert report.parameters == 80_765
    assert report.config_name == "RVT-mini (inferred)"
    assert report.release is None and len(report.md5) == 32
    assert report.onnx is None
    assert report.safetensors == tmp_path / "rvt-mini.safetensors"


def test_config_json_gives_the_architecture(tool, lightning_ckpt, tmp_path, capsys):
    path, state = lightning_ckpt
    config_path = tmp_path / "mini.json"
    config_path.write_text(RVTConfig.mini().to_json())
    assert tool.main([str(path), "--out-dir", str(tmp_path / "out"), "--config-json", str(config_path)]) == 0
    assert "376 state-dict entries, all matched the RVT-mini (given) model" in capsys.readouterr().out
    reloaded = load_detector(tmp_path / "out" / "rvt-mini.safetensors")
    assert reloaded.config == RVTConfig.mini()
    for key, value in reloaded.state_dict().items():
        torch.testing.assert_close(value, state[key], rtol=0, atol=0)


def test_config_json_converts_a_config_that_is_no_preset(tool, tmp_path, capsys):
    """Stage dims 8/16/16/32: the shapes match no preset, so only ``--config-json`` can convert it."""
    config = RVTConfig.mini(dim_multiplier=(1, 2, 2, 4), num_classes=3, name="mini-custom")
    model = RVTDetector(config).eval()
    path = tmp_path / "custom.ckpt"
    torch.save({"state_dict": {f"mdl.{key}": value for key, value in model.state_dict().items()}}, path)
    assert tool.main([str(path), "--out-dir", str(tmp_path / "inferred")]) == 4
    assert "cannot infer the RVT variant" in capsys.readouterr().err

    config_path = tmp_path / "custom.json"
    config_path.write_text(config.to_json())
    report = tool.convert(path, tmp_path / "out", config=tool.read_config_json(config_path), onnx=True)
    assert report.config_name == "mini-custom (given)"
    reloaded = load_detector(report.safetensors)
    assert reloaded.config == config and reloaded.config.num_outputs == 8
    for key, value in reloaded.state_dict().items():
        torch.testing.assert_close(value, model.state_dict()[key], rtol=0, atol=0)
    from davis_rig.models.rvt.ort_runner import RVTOnnxRunner

    assert RVTOnnxRunner(report.onnx).signature.num_outputs == 8


def test_config_json_errors(tool, lightning_ckpt, tmp_path, capsys):
    path, _ = lightning_ckpt
    bad = tmp_path / "bad.json"
    bad.write_text('{"embed_dim": 8}')
    assert tool.main([str(path), "--out-dir", str(tmp_path / "out"), "--config-json", str(bad)]) == 4
    err = capsys.readouterr().err
    assert "bad.json" in err and "missing required keys ['dim_head']" in err
    bad.write_text("not json")
    assert tool.main([str(path), "--out-dir", str(tmp_path / "out"), "--config-json", str(bad)]) == 4
    assert "not valid JSON" in capsys.readouterr().err
    assert tool.main([str(path), "--out-dir", str(tmp_path / "out"), "--config-json", str(tmp_path / "none.json")]) == 4
    assert "none.json" in capsys.readouterr().err
    # one architecture source at a time
    assert tool.main([str(path), "--out-dir", str(tmp_path), "--config", "mini", "--config-json", str(bad)]) == 2
    assert not (tmp_path / "out").exists()


def test_mismatching_checkpoint_prints_the_key_report_and_exits_4(tool, lightning_ckpt, tmp_path, capsys):
    path, state = lightning_ckpt
    broken = {f"mdl.{k}": v for k, v in state.items() if not k.startswith("yolox_head.obj_preds.2")}
    broken["mdl.backbone.extra.weight"] = torch.zeros(3)
    broken_path = tmp_path / "broken.ckpt"
    torch.save({"state_dict": broken}, broken_path)
    code = tool.main([str(broken_path), "--out-dir", str(tmp_path / "out"), "--config", "mini"])
    assert code == 4
    err = capsys.readouterr().err
    assert "2 missing, 1 unexpected" in err
    assert "yolox_head.obj_preds.2.weight" in err and "backbone.extra.weight" in err
    assert not (tmp_path / "out" / "broken.safetensors").exists()


def test_wrong_variant_reports_shape_mismatches(tool, lightning_ckpt, tmp_path, capsys):
    path, _ = lightning_ckpt
    assert tool.main([str(path), "--out-dir", str(tmp_path), "--config", "tiny"]) == 4
    err = capsys.readouterr().err
    assert "with a different shape" in err and "hint: the checkpoint's shapes match RVT-mini" in err


def test_verify_without_onnx_is_a_usage_error(tool, lightning_ckpt, tmp_path, capsys):
    path, _ = lightning_ckpt
    assert tool.main([str(path), "--out", str(tmp_path), "--verify"]) == 2
    assert "argument --verify: needs --onnx" in capsys.readouterr().err
    assert tool.main([str(path)]) == 2
    assert "the following arguments are required: --out" in capsys.readouterr().err
    with pytest.raises(ValueError, match="config: expected one of"):
        tool.convert(path, tmp_path, config="huge")


def test_script_runs_as_a_command(lightning_ckpt, tmp_path):
    path, _ = lightning_ckpt
    result = subprocess.run(
        [sys.executable, str(TOOL_PATH), str(path), "--out-dir", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert "safetensors: " in result.stdout
    assert (tmp_path / "rvt-mini.safetensors").is_file()
