"""reproduce_table: the runs a table needs, optimize + evaluate in one call, a second call only re-reads the runs."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from davis_rig.attack.eot import EoTConfig
from davis_rig.attack.evaluate import EvalConfig
from davis_rig.attack.optimize import AttackConfig
from davis_rig.attack.reproduce import TABLE1_GRIDS, reproduce_table, run_key, table_runs
from davis_rig.models.rvt.checkpoint import load_detector

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "rvt_mini_fixture.safetensors"


def test_table_runs_keys_and_order():
    runs = table_runs(1)
    assert [n for n, _ in runs.values()] == sorted(TABLE1_GRIDS, reverse=True)
    assert all(parts == ("torso", "arms", "legs") for _, parts in runs.values())
    assert list(table_runs(1, grids=[10, 20, 10])) == ["20x20_torso+arms+legs", "10x10_torso+arms+legs"]
    two = table_runs(2)
    assert len(two) == 7 and set(n for n, _ in two.values()) == {10}
    assert "10x10_torso+arms+legs" in two  # Table 2's full-body run is Table 1's 10 x 10 run
    assert list(table_runs(2, combinations=[("legs", "torso")])) == ["10x10_torso+legs"]  # canonical order
    assert run_key(4, ("legs",)) == "4x4_legs"
    for bad in (dict(table=3), dict(table=1, grids=[]), dict(table=2, combinations=[("head",)]),
                dict(table=2, combinations=[()])):
        with pytest.raises(ValueError):
            table_runs(**bad)


def test_reproduce_table1_optimizes_then_evaluates_and_resumes(tmp_path, one_torch_thread):
    detector = load_detector(FIXTURE)
    attack = AttackConfig(iterations=2, pool_size=1, num_validation_clips=1, validate_every=1, checkpoint_every=1,
                          snapshot_every=1, lr=0.05, eot=EoTConfig(supersample=1))
    scenes = EvalConfig(scales=("middle",), shapes=(1,), headings_rad=(math.pi / 2,), phases=(0.0,),
                        thresholds=(0.25,), supersample=1)
    res = reproduce_table(1, detector, tmp_path, attack=attack, eval_config=scenes, grids=(4,),
                          detector_name="fixture", command="davis-attack reproduce --table 1")
    key = "4x4_torso+arms+legs"
    assert (tmp_path / "runs" / key / "best_texture.npy").is_file()
    assert res["runs"][key]["steps_this_call"] == 2 and res["runs"][key]["best_step"] in (1, 2)
    names = [r["texture"] for r in res["rows"] if r["scale"] == "all"]
    assert names == ["white", "black", "random 60x60", "ours 4x4"]
    text = res["markdown"].read_text()
    assert "| ours 4x4 |" in text and "2 iterations, Adam lr 0.05" in text and "`fixture`" in text
    record = json.loads(res["record"].read_text())
    assert record["attack"]["iterations"] == 2 and record["runs"][key]["grid_n"] == 4
    again = reproduce_table(1, detector, tmp_path, attack=attack, eval_config=scenes, grids=(4,))
    assert again["runs"][key]["steps_this_call"] == 0 and again["runs"][key]["seconds_per_step"] is None
    assert [r["AP"] for r in again["rows"]] == [r["AP"] for r in res["rows"]]


def test_the_budget_note_names_a_sampled_binarization():
    from davis_rig.attack.reproduce import _budget_markdown

    paper = _budget_markdown(AttackConfig(), EvalConfig(), {}, None)
    sampled = _budget_markdown(AttackConfig(binarize="sample"), EvalConfig(), {}, None)
    assert "alpha schedule linear, V2E gradient" in paper and "sampled" not in paper
    assert "alpha schedule linear (hard part sampled, Bernoulli(u) per cell and step), V2E gradient" in sampled
