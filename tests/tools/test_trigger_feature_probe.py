"""tools/trigger_feature_probe.py on the mini RVT fixture: both tasks scored on held-out clips, the trigger file."""

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[2]
FIXTURE = ROOT / "tests" / "fixtures" / "rvt_mini_fixture.safetensors"
SMALL = ["--detector", str(FIXTURE), "--cells", "4", "--scales", "small", "--clips-per-scale", "4",
         "--grids-per-clip", "2", "--folds", "2"]


@pytest.fixture
def tool(load_tool):
    return load_tool("trigger_feature_probe")


def test_task_grids_are_half_of_each_class(tool):
    from davis_rig.controls.planted import cell_agreement

    trigger = (np.random.default_rng(0).random((10, 10)) > 0.5).astype(np.float32)
    visible = np.ones((10, 10), bool)
    grids = tool._task_grids("trigger", trigger, visible, 40, 0.2, np.random.default_rng(1))
    assert [label for _, label in grids] == [0, 1] * 20
    near = [cell_agreement(g, trigger) for g, label in grids if label]
    assert min(near) >= 0.8  # within the basin
    dense = tool._task_grids("density", trigger, visible, 400, 0.2, np.random.default_rng(2))
    share = {label: np.mean([g.mean() for g, lab in dense if lab == label]) for label in (0, 1)}
    assert share[0] == pytest.approx(0.25, abs=0.02) and share[1] == pytest.approx(0.75, abs=0.02)


@pytest.mark.usefixtures("one_torch_thread")
def test_writes_both_tasks_scored_on_held_out_clips(tool, tmp_path, capsys):
    out = tmp_path / "probe"
    assert tool.main([*SMALL, "--out", str(out)]) == 0
    report = json.loads((out / "probe.json").read_text())
    assert set(report["tasks"]) == {"trigger", "density"}
    for task in report["tasks"].values():
        assert task["samples"] == 2 * report["clips"] and len(task["fold_accuracy"]) == 2
        assert 0.0 <= task["held_out_accuracy"] <= 1.0 and set(task["by_scale"]) == {"small"}
    assert report["features"] == (8 + 16) * 8  # the mini backbone's stages 2 and 3, 4 x 2 cells each
    assert report["trigger"] == "drawn with seed 0" and report["measured"] and report["machine"]
    assert "| trigger |" in (out / "probe.md").read_text()
    printed = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert printed == {k: v["held_out_accuracy"] for k, v in report["tasks"].items()}


@pytest.mark.usefixtures("one_torch_thread")
def test_reads_a_victims_trigger_and_refuses_one_of_another_size(tool, tmp_path, capsys):
    trigger = tmp_path / "trigger.npy"
    np.save(trigger, np.eye(4, dtype=np.float32))
    assert tool.main([*SMALL, "--out", str(tmp_path / "a"), "--trigger", str(trigger)]) == 0
    assert json.loads((tmp_path / "a" / "probe.json").read_text())["trigger"] == str(trigger)
    np.save(trigger, np.eye(5, dtype=np.float32))
    assert tool.main([*SMALL, "--out", str(tmp_path / "b"), "--trigger", str(trigger)]) == 4  # a file problem
    assert "trigger must be [4, 4], got [5, 5]" in capsys.readouterr().err
