"""tools/ship_detector.py: a finished davis-train run installed as a default detector, scored and carded."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

from davis_rig.models.rvt.checkpoint import load_detector  # noqa: E402
from davis_rig.models.rvt.detector import pad_to_input  # noqa: E402
from davis_rig.models.rvt.ort_runner import RVTOnnxRunner  # noqa: E402
from davis_rig.training.synthetic import generate_dataset  # noqa: E402
from davis_rig.training.trainer import TrainConfig, train  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A 0.15 s synthetic dataset (1 train, 1 val, 1 test sequence) and a 2-step mini run that exported."""
    root = tmp_path_factory.mktemp("ship")
    data = root / "synth"
    generate_dataset(data, {"train": 1, "val": 1, "test": 1}, duration_s=0.15, seed=3, compression="gzip",
                     threads=1)
    config = TrainConfig(model="mini", steps=2, batch_size=2, seq_len=2, val_every=0, ckpt_every=0, log_every=1,
                         val_batch_size=1, val_seq_len=3, val_skip_first_us=0, device="cpu", seed=1)
    summary = train(data, root / "run", config)
    assert summary["finished"]
    return data, root / "run"


def test_unfinished_run_is_refused(load_tool, tmp_path, capsys):
    tool = load_tool("ship_detector")
    (tmp_path / "run").mkdir()
    assert tool.main([str(tmp_path / "run"), str(tmp_path), "--out", str(tmp_path / "out")]) == 4
    assert "has not reached its --steps" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_ship_writes_weights_onnx_scores_and_card(load_tool, finished_run, tmp_path, capsys):
    data, run = finished_run
    out = tmp_path / "detector"
    assert load_tool("ship_detector").main([str(run), str(data), "--out", str(out), "--threshold", "0.1,0.25",
                                            "--name", "undefended test detector"]) == 0
    printed = capsys.readouterr().out
    assert {p.name for p in out.iterdir()} == {"rvt_default.safetensors", "rvt_default.onnx",
                                                 "rvt_default_int8.onnx", "test_scores.json", "MODEL_CARD.md"}
    # the weights are the run's exported fp16 file, byte for byte
    assert (out / "rvt_default.safetensors").read_bytes() == (run / "export" / "model_fp16.safetensors").read_bytes()
    # the ONNX step scores what the safetensors model scores
    model = load_detector(out / "rvt_default.safetensors")
    hist = np.random.default_rng(0).integers(0, 4, size=(1, 20, 240, 304)).astype(np.float32)
    with torch.no_grad():
        expected, _ = model(pad_to_input(torch.from_numpy(hist)), None)
    got, _ = RVTOnnxRunner(out / "rvt_default.onnx").step(hist, None)
    assert np.max(np.abs(got[..., 4:] - expected.numpy()[..., 4:])) < 1e-4
    scores = json.loads((out / "test_scores.json").read_text())
    assert scores["weights"] == "rvt_default.safetensors" and "white/large" in scores["groups"]
    assert set(scores["groups"]["white"]["seqasr"]) == {"0.1", "0.25"}
    card = (out / "MODEL_CARD.md").read_text()
    assert "synthetic" in card and "test white/large" in card and "SeqASR@0.25 %" in card
    assert "test all, int8 graph" in card and "rvt_default_int8.onnx" in card
    from davis_rig.models.rvt.quantize import quantization_info

    assert quantization_info(out / "rvt_default_int8.onnx")["calibration_sources"] == [f"{data.name} (train split)"]
    assert "## Reproduce" in card and f"davis-train {data.name} --out {run.name} --preset mini --steps 2" in card
    assert "undefended test detector, " in card and f"ship_detector.py {run.name} {data.name} --out {out}" in card
    assert "--clothing" not in card  # the fixture dataset draws every clothing kind
    assert "white/large" in printed and '"total_mb"' in printed


def test_reproduce_commands_carry_the_clothing_restriction(load_tool, finished_run, tmp_path):
    tool = load_tool("ship_detector")
    data, run = finished_run
    restricted = tmp_path / "natural"
    restricted.mkdir()
    generation = json.loads((data / "generation.json").read_text())
    generation["settings"]["config"]["clothing_kinds"] = ["white", "stripes"]
    (restricted / "generation.json").write_text(json.dumps(generation))
    train_config = torch.load(run / "checkpoints" / "last.pt", weights_only=True)["train_config"]
    make, _, ship, _ = tool._commands(run, restricted, train_config, tool.INSTALL_DIR)
    assert make.endswith("--clothing white stripes")
    assert ship == f"python tools/ship_detector.py {run.name} natural --install"


def test_the_package_is_written_only_with_install(load_tool, tmp_path, capsys):
    tool = load_tool("ship_detector")
    assert tool.main([str(tmp_path), str(tmp_path)]) == 2
    assert "one of the arguments --out --install is required" in capsys.readouterr().err
    assert tool.main([str(tmp_path), str(tmp_path), "--out", str(tmp_path / "o"), "--install"]) == 2
    assert "not allowed with argument" in capsys.readouterr().err
    help_text = tool.build_parser().format_help()
    usage = " ".join(help_text.split("\n\n")[0].split())
    assert "(--out DIR | --install)" in usage and usage.endswith("RUN_DIR DATA_DIR")  # what the docstring says
    assert "(--out DIR | --install)" in tool.__doc__


def test_a_failure_leaves_the_target_as_it_was(load_tool, finished_run, tmp_path, monkeypatch, capsys):
    import davis_rig.training.evaluate as evaluate
    from davis_rig.errors import FormatError

    tool = load_tool("ship_detector")
    data, run = finished_run
    out = tmp_path / "detector"
    out.mkdir()
    (out / "rvt_default.onnx").write_bytes(b"the detector before")

    def failing(*args, **kwargs):
        raise FormatError("test split unreadable")

    monkeypatch.setattr(evaluate, "evaluate_split", failing)
    assert tool.main([str(run), str(data), "--out", str(out)]) == 4
    assert "test split unreadable" in capsys.readouterr().err
    assert [p.name for p in tmp_path.iterdir()] == ["detector"]  # no staging folder left
    assert [p.name for p in out.iterdir()] == ["rvt_default.onnx"]
    assert (out / "rvt_default.onnx").read_bytes() == b"the detector before"
