"""tools/probe_texture_sensitivity.py on the mini RVT fixture: baselines, per-clip optimisation, summary."""

import importlib.util
import json
from pathlib import Path

import pytest

pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[2]
FIXTURE = ROOT / "tests" / "fixtures" / "rvt_mini_fixture.safetensors"


def _tool():
    spec = importlib.util.spec_from_file_location("probe", ROOT / "tools" / "probe_texture_sensitivity.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.usefixtures("one_torch_thread")
def test_probe_prints_baselines_and_the_optimized_grid_per_clip(capsys):
    assert _tool().main(["--detector", str(FIXTURE), "--cells", "4", "--clips", "1", "--steps", "3"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    (row,), summary = lines[:-1], lines[-1]["summary"]
    assert row["clip"] == 0 and isinstance(row["optimized_fooled"], bool)
    for key in ("white", "black", "random", "optimized"):
        assert 0.0 <= row[key] <= 1.0
        assert summary[key] == pytest.approx(row[key], abs=1e-4)
    assert summary["clips"] == 1 and summary["cells"] == 4 and summary["steps"] == 3
    assert summary["parts"] == ["torso", "arms", "legs"] and summary["fooled"] in (0, 1)


def test_greedy_cell_flips_reaches_the_minimum_of_a_separable_score():
    import numpy as np

    target = np.random.default_rng(1).integers(0, 2, (4, 4)).astype(np.float32)
    score = lambda grid: float(np.abs(grid - target).sum())  # noqa: E731
    start = np.ones((4, 4), np.float32)
    best, best_score, evaluations = _tool().greedy_cell_flips(start, score, 3, np.random.default_rng(0))
    np.testing.assert_array_equal(best, target)
    assert best_score == 0.0
    assert evaluations == 1 + 16 * 2  # second sweep finds no gain and stops
    np.testing.assert_array_equal(start, np.ones((4, 4)))  # input untouched


def test_greedy_cell_flips_keeps_a_grid_no_flip_improves():
    import numpy as np

    grid = np.zeros((3, 3), np.float32)
    best, best_score, evaluations = _tool().greedy_cell_flips(grid, lambda g: float(g.sum()), 5,
                                                              np.random.default_rng(0))
    np.testing.assert_array_equal(best, grid)
    assert best_score == 0.0 and evaluations == 10


@pytest.mark.usefixtures("one_torch_thread")
def test_probe_greedy_pass_reports_a_score_no_worse_than_its_start(capsys):
    assert _tool().main(["--detector", str(FIXTURE), "--cells", "2", "--clips", "1", "--steps", "2",
                         "--greedy-passes", "1"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    (row,), summary = lines[:-1], lines[-1]["summary"]
    assert row["greedy_start"] in ("white", "black", "random", "optimized")
    assert row["greedy"] <= row[row["greedy_start"]] + 1e-6
    assert row["greedy_evaluations"] >= 1 + 4 and isinstance(row["greedy_fooled"], bool)
    assert summary["greedy"] == pytest.approx(row["greedy"], abs=1e-4) and summary["greedy_passes"] == 1
