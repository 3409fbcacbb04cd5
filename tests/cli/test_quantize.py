"""davis-quantize: an int8 graph from a dataset folder and a session; bad input is refused before anything is
written; davis-eval-dataset scores the result."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from davis_rig.cli import quantize as cli  # noqa: E402
from davis_rig.models.rvt.quantize import quantization_info  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[2]
SAMPLE = REPO_ROOT / "recordings" / "sample.h5"
MINI_WEIGHTS = REPO_ROOT / "tests" / "fixtures" / "rvt_mini_fixture.safetensors"


@pytest.fixture(scope="module")
def mini_onnx(tmp_path_factory):
    """The in-repo mini RVT exported as a step graph."""
    pytest.importorskip("torch")
    from davis_rig.models.rvt.checkpoint import load_detector
    from davis_rig.models.rvt.onnx_export import export_step_onnx

    return export_step_onnx(load_detector(MINI_WEIGHTS), tmp_path_factory.mktemp("mini") / "mini.onnx")


@pytest.fixture(scope="module")
def calibration_dataset(tmp_path_factory):
    """Two train sequences of 3 windows (random histograms, one labelled box each)."""
    from davis_rig.training.dataset import DatasetWriter
    from davis_rig.types import BBOX_DTYPE

    root = tmp_path_factory.mktemp("calib") / "ds"
    rng = np.random.default_rng(0)
    with DatasetWriter(root, name="calib", description="test", compression="lzf") as writer:
        for split in ("train", "test"):
            for k in range(2):
                hist = np.minimum(rng.poisson(0.3, size=(3, 20, 240, 304)), 10).astype(np.uint8)
                box = np.zeros(1, BBOX_DTYPE)
                box["x"], box["y"], box["w"], box["h"], box["class_id"] = 100, 60, 40, 90, 1
                writer.add_sequence(hist, 50_000 * np.arange(1, 4), [box] * 3, {"k": k}, split=split)
    return root


def test_quantizes_on_a_dataset_and_a_session_and_reports_both_graphs(mini_onnx, calibration_dataset, tmp_path,
                                                                     capsys):
    out = tmp_path / "int8.onnx"
    assert cli.main(["--detector", str(mini_onnx), "--calibration", str(calibration_dataset), str(SAMPLE),
                     "--windows", "5", "--seconds", "0.2", "--out", str(out), "--threads", "1", "-q"]) == 0
    printed = capsys.readouterr().out
    assert f"wrote {out}: 5 calibration windows" in printed and "int8" in printed and "max" in printed
    info = quantization_info(out)
    assert info["calibration_sources"] == ["ds (train split)", "sample.h5"]
    assert info["calibration_windows"] == 5


def test_davis_eval_dataset_scores_an_onnx_graph_as_its_weights(mini_onnx, calibration_dataset):
    from davis_rig.training.evaluate import SplitScoreConfig, evaluate_split

    config = SplitScoreConfig(skip_first_us=0, lanes=2)
    by_graph = evaluate_split(calibration_dataset, mini_onnx, config=config, threads=1)
    by_weights = evaluate_split(calibration_dataset, MINI_WEIGHTS, config=config)
    assert by_graph["weights"] == str(mini_onnx)
    graph_all, weights_all = by_graph["groups"]["all"], by_weights["groups"]["all"]
    assert graph_all["num_labels"] == weights_all["num_labels"] == 6
    assert graph_all["AP"] == pytest.approx(weights_all["AP"], abs=1e-3, nan_ok=True)


@pytest.mark.parametrize("argv, code, message", [
    (["--calibration", "x", "--out", "int8.txt"], 2, "argument --out: must end in .onnx"),
    (["--calibration", "x", "--out", "m.onnx", "--detector", "m.onnx"], 2, "must differ from --detector"),
    (["--calibration", "x", "--out", "o.onnx", "--windows", "0"], 2, "argument --windows"),
    (["--out", "o.onnx"], 2, "--calibration"),
])
def test_bad_options_exit_2(argv, code, message, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli.main(argv) == code
    assert message in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_bad_sources_and_graphs_exit_4_and_write_nothing(mini_onnx, tmp_path, capsys):
    out = tmp_path / "int8.onnx"
    assert cli.main(["--detector", str(mini_onnx), "--calibration", str(tmp_path / "missing"), "--out",
                     str(out)]) == 4
    assert "missing: no such file or folder" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli.main(["--detector", str(mini_onnx), "--calibration", str(empty), "--out", str(out)]) == 4
    assert "no RVT-layout sequence" in capsys.readouterr().err
    not_onnx = tmp_path / "model.onnx"
    not_onnx.write_bytes(b"no graph")
    assert cli.main(["--detector", str(not_onnx), "--calibration", str(SAMPLE), "--out", str(out)]) == 4
    assert "davis-quantize: error:" in capsys.readouterr().err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["empty", "model.onnx"]


def test_a_session_is_read_window_by_window_as_davis_eval_windows_it():
    from davis_rig.cli.quantize import SessionSequence
    from davis_rig.events.crop import crop_events
    from davis_rig.events.histogram import stacked_histograms
    from davis_rig.session.reader import SessionReader

    sequence = SessionSequence(SAMPLE, 10.0)
    with SessionReader(SAMPLE) as reader:
        whole = stacked_histograms(crop_events(reader.events(), sequence.origin), sequence.window_end_us)
    assert len(sequence) == len(whole) > 2
    np.testing.assert_array_equal(np.concatenate([sequence[w : w + 1] for w in range(len(sequence))]), whole)
    np.testing.assert_array_equal(sequence[1:3], whole[1:3])
    assert len(SessionSequence(SAMPLE, 0.06)) == 2  # only the first --seconds
