"""Picking among APS attack restarts on validation: the rule, the comparability checks, and the tool's --pick-from."""

from __future__ import annotations

import json

import numpy as np
import pytest

from davis_rig.attack_aps.restarts import RestartRow, pick_on_validation, restart_rows
from davis_rig.errors import ConfigError


def report(validation_rate, held_out_rate, final_rate, *, top=0.1, step=40, shapes=(0, 4), model="/a/yolo.onnx",
           grid_n=4, headings=(1.57, -1.57)):
    """An ``aps_control.json`` as tools/aps_attack.py writes it (only the fields the picker reads, and one row
    that must not be read: white's)."""
    n = grid_n
    return {"threshold": 0.25, "model": model,
            "rows": [{"texture": "white", "frames": 8, "rate": 1.0, "mean_top_score": 0.7},
                     {"texture": f"ours {n}x{n}", "frames": 8, "rate": final_rate, "mean_top_score": 0.2},
                     {"texture": f"ours {n}x{n}, best on validation (step {step})", "frames": 8,
                      "rate": held_out_rate, "mean_top_score": 0.1}],
            "attack": {"grid_n": n, "parts": ["torso"], "validation_shapes": list(shapes),
                       "best_on_validation": {"step": step, "rate": validation_rate, "mean_top_score": top}},
            "held_out": {"headings_rad": list(headings), "phases": [0.0], "shapes": "test split"}}


def test_rows_read_the_kept_and_the_final_textures_rows_by_name():
    rows = restart_rows([report(0.25, 0.5, 0.75, step=60)], ["s0"])
    assert rows == [RestartRow(run="s0", validation_rate=0.25, validation_step=60, validation_top_score=0.1,
                               held_out_rate=0.5, final_held_out_rate=0.75, frames=8)]


def test_the_lowest_validation_recall_is_picked_whatever_the_held_out_recall():
    # s1 validates best but is the worst on the held-out test: the rule must not look at the test.
    rows = restart_rows([report(0.25, 0.125, 0.125), report(0.125, 0.875, 0.5), report(0.5, 0.0, 0.0)],
                        ["s0", "s1", "s2"])
    assert pick_on_validation(rows) == 1


def test_a_tie_goes_to_the_lower_top_score_then_to_the_earlier_run():
    rows = restart_rows([report(0.25, 0.5, 0.5, top=0.2), report(0.25, 0.5, 0.5, top=0.1),
                         report(0.25, 0.5, 0.5, top=0.1)], ["a", "b", "c"])
    assert pick_on_validation(rows) == 1


@pytest.mark.parametrize("changed, field", [({"shapes": (1, 5)}, "validation_shapes"), ({"grid_n": 8}, "grid_n"),
                                            ({"model": "/b/other.onnx"}, "model"),
                                            ({"headings": (0.0,)}, "held_out")])
def test_runs_validated_on_other_set_ups_are_refused_naming_the_run_and_field(changed, field):
    with pytest.raises(ConfigError, match=field) as caught:
        restart_rows([report(0.25, 0.5, 0.5), report(0.125, 0.5, 0.5, **changed)], ["s0", "s1"])
    assert caught.value.field == "s1"


def test_the_labeler_file_may_sit_in_another_folder():
    rows = restart_rows([report(0.25, 0.5, 0.5), report(0.125, 0.5, 0.5, model="/elsewhere/yolo.onnx")],
                        ["s0", "s1"])
    assert pick_on_validation(rows) == 1


def test_a_run_without_validation_or_without_its_rows_is_refused():
    unvalidated = report(0.25, 0.5, 0.5)
    unvalidated["attack"]["best_on_validation"] = None
    with pytest.raises(ConfigError, match="--validate-every") as caught:
        restart_rows([report(0.25, 0.5, 0.5), unvalidated], ["s0", "s1"])
    assert caught.value.field == "s1"
    rowless = report(0.25, 0.5, 0.5)
    rowless["rows"] = rowless["rows"][:2]
    with pytest.raises(ConfigError, match="best on validation"):
        restart_rows([rowless], ["s0"])
    with pytest.raises(ConfigError):
        restart_rows([], [])
    with pytest.raises(ConfigError):
        pick_on_validation([])


def _run_folder(root, name, report_dict, texture):
    folder = root / name
    folder.mkdir()
    (folder / "aps_control.json").write_text(json.dumps(report_dict))
    np.save(folder / "best_texture.npy", texture)
    return folder


def test_the_tool_writes_the_picked_runs_texture_and_every_runs_figures(load_tool, tmp_path, capsys):
    textures = [np.eye(4, dtype=np.float32), np.ones((4, 4), np.float32), np.zeros((4, 4), np.float32)]
    runs = [_run_folder(tmp_path, f"s{i}", report(rate, 0.5, 0.5), texture)
            for i, (rate, texture) in enumerate(zip((0.375, 0.125, 0.25), textures))]
    out = tmp_path / "pick"
    assert load_tool("aps_attack").main(["--out", str(out), "--pick-from", *map(str, runs), "-q"]) == 0
    np.testing.assert_array_equal(np.load(out / "texture.npy"), textures[1])
    picked = json.loads((out / "pick.json").read_text())
    assert picked["picked"] == str(runs[1])
    assert [r["validation_rate"] for r in picked["runs"]] == [0.375, 0.125, 0.25]
    assert "| yes |" in (out / "pick.md").read_text().splitlines()[-2]  # s1's row: the second of three
    assert (out / "texture.png").is_file()


def test_the_tool_refuses_a_missing_report_or_a_kept_texture_of_the_wrong_size(load_tool, tmp_path, capsys):
    tool = load_tool("aps_attack")
    good = _run_folder(tmp_path, "good", report(0.25, 0.5, 0.5), np.zeros((4, 4), np.float32))
    out = tmp_path / "pick"
    assert tool.main(["--out", str(out), "--pick-from", str(good), str(tmp_path / "gone"), "-q"]) == 4
    assert "gone/aps_control.json: no such report" in capsys.readouterr().err
    wrong = _run_folder(tmp_path, "wrong", report(0.125, 0.5, 0.5), np.zeros((5, 5), np.float32))
    assert tool.main(["--out", str(out), "--pick-from", str(good), str(wrong), "-q"]) == 4
    assert "a 4x4 texture expected, got shape (5, 5)" in capsys.readouterr().err
    assert not out.exists()
