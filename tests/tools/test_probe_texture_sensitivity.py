"""tools/probe_texture_sensitivity.py on the mini RVT fixture: baselines, per-clip optimisation, summary."""

import json
from pathlib import Path

import pytest

pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[2]
FIXTURE = ROOT / "tests" / "fixtures" / "rvt_mini_fixture.safetensors"


@pytest.fixture
def tool(load_tool):
    return load_tool("probe_texture_sensitivity")


@pytest.mark.usefixtures("one_torch_thread")
def test_probe_prints_baselines_and_the_optimized_grid_per_clip(tool, capsys):
    assert tool.main(["--detector", str(FIXTURE), "--cells", "4", "--clips", "1", "--steps", "3"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    (row,), summary = lines[:-1], lines[-1]["summary"]
    assert row["clip"] == 0 and isinstance(row["optimized_fooled"], bool)
    for key in ("white", "black", "random", "optimized"):
        assert 0.0 <= row[key] <= 1.0
        assert summary[key] == pytest.approx(row[key], abs=1e-4)
    assert summary["clips"] == 1 and summary["cells"] == 4 and summary["steps"] == 3
    assert summary["parts"] == ["torso", "arms", "legs"] and summary["fooled"] in (0, 1)


@pytest.mark.usefixtures("one_torch_thread")
def test_probe_greedy_pass_reports_a_score_no_worse_than_its_start(tool, capsys):
    assert tool.main(["--detector", str(FIXTURE), "--cells", "2", "--clips", "1", "--steps", "2",
                      "--greedy-passes", "1"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    (row,), summary = lines[:-1], lines[-1]["summary"]
    assert row["greedy_start"] in ("white", "black", "random", "optimized")
    assert row["greedy"] <= row[row["greedy_start"]] + 1e-6
    assert row["greedy_evaluations"] >= 1 + 4 and isinstance(row["greedy_fooled"], bool)
    assert summary["greedy"] == pytest.approx(row["greedy"], abs=1e-4) and summary["greedy_passes"] == 1
