"""tools/trigger_gradient_check.py on the mini RVT fixture: rows, their relations, the table and the JSON."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "rvt_mini_fixture.safetensors"
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_random_and_flipped_grids_against_a_trigger_file(load_tool, tmp_path, capsys):
    tool = load_tool("trigger_gradient_check")
    trigger = np.array([[1, 0, 1, 0], [0, 1, 0, 1], [1, 1, 0, 0], [0, 0, 1, 1]], np.float32)
    np.save(tmp_path / "trigger.npy", trigger)
    out = tmp_path / "check.json"
    assert tool.main(["--detector", str(FIXTURE), "--trigger", str(tmp_path / "trigger.npy"), "--cells", "4",
                      "--clips", "2", "--batch", "1", "--clip-counts", "1", "2", "--random", "2",
                      "--flipped", "0", "0.5", "1.0", "--out", str(out),
                      "--quiet"]) == 0
    assert "NaN" not in out.read_text()  # strict JSON: a grid equal to the trigger has no agreement to report
    report = json.loads(out.read_text())
    visible = report["visible_cells"]
    assert 0 < visible <= 16 and report["loss"] == "top" and report["clips"] == 2
    rows = {r["grid"]: r for r in report["rows"]}
    assert list(rows) == ["random 0", "random 1", "trigger, 0% flipped", "trigger, 50% flipped",
                          "trigger, 100% flipped"]
    unflipped = rows.pop("trigger, 0% flipped")
    assert unflipped["differing_cells"] == 0 and unflipped["descent_agreement"] is None
    assert unflipped["first_order_change"] == 0.0 and unflipped["measured_change"] == pytest.approx(0.0)
    assert rows["trigger, 50% flipped"]["differing_cells"] == round(0.5 * visible)
    assert rows["trigger, 100% flipped"]["differing_cells"] == visible
    for r in rows.values():
        assert 0.0 <= r["descent_agreement"] <= 1.0 and np.isfinite(r["first_order_change"])
        assert r["measured_change"] == pytest.approx(report["loss_at_trigger"] - r["loss"])
        assert r["agreement_by_clips"]["2"] == r["descent_agreement"]  # all the clips: the row's own gradient
        assert 0.0 <= r["agreement_by_clips"]["1"] <= 1.0 and 0.0 <= r["half_consistency"] <= 1.0
    assert capsys.readouterr().out.count("\n| ") == 5  # one table row per grid after the header


def test_gradients_at_greyed_grids_differ_from_the_hard_grids_and_are_reported(load_tool, tmp_path):
    tool = load_tool("trigger_gradient_check")
    common = ["--detector", str(FIXTURE), "--cells", "4", "--clips", "2", "--batch", "2", "--random", "1",
              "--flipped", "--quiet"]
    tool.main([*common, "--out", str(tmp_path / "hard.json")])
    assert tool.main([*common, "--contrast", "0.5", "--out", str(tmp_path / "grey.json")]) == 0
    hard, grey = (json.loads((tmp_path / name).read_text()) for name in ("hard.json", "grey.json"))
    assert hard["contrast"] == 1.0 and grey["contrast"] == 0.5 and hard["loss_at_trigger"] == grey["loss_at_trigger"]
    assert grey["rows"][0]["differing_cells"] == hard["rows"][0]["differing_cells"]  # cells of the hard grid
    assert grey["rows"][0]["loss"] != hard["rows"][0]["loss"]  # taken at the greyed grid


def test_clip_counts_that_do_not_split_into_batches_are_a_usage_error(load_tool, capsys):
    tool = load_tool("trigger_gradient_check")
    assert tool.main(["--detector", str(FIXTURE), "--clips", "8", "--batch", "4", "--clip-counts", "6"]) == 2
    assert "argument --clip-counts: 6 is not a multiple of --batch 4 within --clips 8" in capsys.readouterr().err


def test_a_trigger_of_the_wrong_size_is_refused_before_the_clips(load_tool, tmp_path, capsys):
    tool = load_tool("trigger_gradient_check")
    np.save(tmp_path / "trigger.npy", np.ones((3, 3), np.float32))
    assert tool.main(["--detector", str(FIXTURE), "--trigger", str(tmp_path / "trigger.npy"), "--cells", "4"]) == 4
    assert "trigger must be [4, 4]" in capsys.readouterr().err
