"""Greedy cell-flip refinement: exact coordinate descent on toy scores, visible cells, and the optimizer stage."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from davis_rig.attack.eot import EoTConfig
from davis_rig.attack.optimize import AttackConfig, optimize_texture
from davis_rig.attack.refine import greedy_cell_flips, refine_texture, visible_cells
from davis_rig.models.rvt.checkpoint import load_detector
from davis_rig.scene.body import BodyModel

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "rvt_mini_fixture.safetensors"
TARGET = np.array([[1, 0, 1], [0, 0, 1], [1, 1, 0]], dtype=np.float32)


def distance_to_target(grid):
    return float(np.abs(grid - TARGET).sum())


def test_greedy_flips_reach_the_optimum_of_a_separable_score_and_stop_after_a_dry_pass():
    grid, score, evaluations = greedy_cell_flips(np.ones((3, 3), np.float32), distance_to_target, 5,
                                                 np.random.default_rng(0))
    assert np.array_equal(grid, TARGET) and score == 0.0
    assert evaluations == 1 + 9 + 9  # the start, one improving pass, one pass without gain


def test_greedy_flips_only_the_allowed_cells_and_reuse_a_known_score():
    cells = np.zeros((3, 3), bool)
    cells[0] = True
    start = np.ones((3, 3), np.float32)
    grid, score, evaluations = greedy_cell_flips(start, distance_to_target, 1, np.random.default_rng(1),
                                                 cells=cells, grid_score=distance_to_target(start))
    expected = start.copy()
    expected[0] = TARGET[0]
    assert np.array_equal(grid, expected) and score == distance_to_target(expected)
    assert evaluations == 3 and np.array_equal(start, np.ones((3, 3)))  # input untouched


def test_greedy_flips_keep_a_grid_no_flip_improves():
    grid = np.zeros((3, 3), np.float32)
    best, score, evaluations = greedy_cell_flips(grid, lambda g: float(g.sum()), 5, np.random.default_rng(0))
    assert np.array_equal(best, grid) and score == 0.0 and evaluations == 10


def test_visible_cells_are_the_painted_taps_with_weight():
    lookup = SimpleNamespace(index=torch.tensor([[0], [5], [7], [8]]), painted=torch.tensor([[1.0], [1.0], [0.0], [1.0]]),
                             weight=torch.tensor([[1.0], [1.0], [1.0], [0.0]]))
    other = SimpleNamespace(index=torch.tensor([[2]]), painted=torch.tensor([[1.0]]), weight=torch.tensor([[1.0]]))
    cells = visible_cells([SimpleNamespace(lookup=lookup), SimpleNamespace(lookup=other)], 3)
    assert cells.tolist() == [[True, False, True], [False, False, True], [False, False, False]]


def test_refine_starts_from_the_best_of_gradient_white_and_black():
    clip = SimpleNamespace(lookup=SimpleNamespace(index=torch.arange(9)[:, None], painted=torch.ones(9, 1),
                                                  weight=torch.ones(9, 1)))
    far = 1.0 - TARGET
    found = refine_texture(far, [clip], distance_to_target, 2, seed=0)
    assert found["start"] == "white" and found["start_score"] == distance_to_target(np.ones((3, 3)))
    assert np.array_equal(found["texture"], TARGET) and found["score"] == 0.0 and found["cells_tried"] == 9
    close = TARGET.copy()
    close[0, 0] = 0.0
    assert refine_texture(close, [clip], distance_to_target, 1, seed=0)["start"] == "gradient"
    dark = np.zeros((3, 3), np.float32)
    dark[1, 1] = 1.0
    found = refine_texture(far, [clip], lambda g: float(np.abs(g - dark).sum()), 1, seed=0)
    assert found["start"] == "black" and found["start_score"] == 1.0 and np.array_equal(found["texture"], dark)


@pytest.mark.usefixtures("one_torch_thread")
def test_optimizer_ends_with_refinement_once(tmp_path):
    detector = load_detector(FIXTURE)
    body = BodyModel()
    cfg = AttackConfig(grid_n=3, iterations=2, pool_size=2, refresh_every=2, num_validation_clips=1,
                       validate_every=1000, checkpoint_every=2, snapshot_every=2, lr=0.05,
                       eot=EoTConfig(supersample=1), refine_passes=1, refine_clips=1)
    result = optimize_texture(cfg, detector, tmp_path, body_model=body, progress=False)
    summary = json.loads((tmp_path / "refine.json").read_text())
    records = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [r["refine"] for r in records if "refine" in r] == [summary]
    assert summary["score"] <= summary["start_score"] and 1 <= summary["cells_tried"] <= 9
    assert summary["evaluations"] >= 2 + summary["cells_tried"] - 1
    refined = np.load(tmp_path / "refined_texture.npy")
    assert set(np.unique(refined)) <= {0.0, 1.0} and refined.shape == (3, 3)
    best = json.loads((tmp_path / "best.json").read_text())
    if summary["replaced_best"]:
        assert best == summary["validation"] and best["refined"] is True
        assert np.array_equal(result.best_texture, refined)
    else:
        assert "refined" not in best
    # a finished run called again (resume) neither trains nor refines again
    again = optimize_texture(cfg, detector, tmp_path, body_model=body, progress=False, resume=True)
    assert again.steps == 0 and json.loads((tmp_path / "refine.json").read_text()) == summary
    assert np.array_equal(again.best_texture, result.best_texture)


def test_refine_settings_are_validated():
    with pytest.raises(ValueError, match="refine_passes"):
        AttackConfig(refine_passes=-1)
    with pytest.raises(ValueError, match="refine_clips"):
        AttackConfig(refine_clips=0)


def _finished_run(run_dir):
    """A finished 2-step run without refinement in ``run_dir``: returns ``(detector, body, base settings)``."""
    detector = load_detector(FIXTURE)
    body = BodyModel()
    base = dict(grid_n=3, iterations=2, pool_size=2, refresh_every=2, num_validation_clips=1, validate_every=1000,
                checkpoint_every=2, snapshot_every=2, lr=0.05, eot=EoTConfig(supersample=1))
    optimize_texture(AttackConfig(**base), detector, run_dir, body_model=body, progress=False)
    return detector, body, base


@pytest.mark.usefixtures("one_torch_thread")
def test_a_finished_run_can_be_refined_later(tmp_path):
    detector, body, base = _finished_run(tmp_path)
    assert not (tmp_path / "refine.json").exists()
    again = optimize_texture(AttackConfig(**base, refine_passes=1, refine_clips=1), detector, tmp_path,
                             body_model=body, progress=False, resume=True)
    assert again.steps == 0 and (tmp_path / "refine.json").is_file()


@pytest.mark.usefixtures("one_torch_thread")
def test_refining_a_finished_run_later_saves_the_new_best_in_the_checkpoint(tmp_path):
    detector, body, base = _finished_run(tmp_path)
    path = tmp_path / "checkpoints" / "last.pt"
    state = torch.load(path, weights_only=True)
    worst = {"SeqASR": float("nan"), "num_sequences": 1, "num_detected": 1, "mean_top_score": 2.0, "step": 2}
    state["best"] = json.dumps(worst)  # any refined texture beats it, so the refinement replaces the best
    torch.save(state, path)
    again = optimize_texture(AttackConfig(**base, refine_passes=1, refine_clips=1), detector, tmp_path,
                             body_model=body, progress=False, resume=True)
    assert json.loads((tmp_path / "refine.json").read_text())["replaced_best"]
    saved = torch.load(path, weights_only=True)
    best = json.loads((tmp_path / "best.json").read_text())
    assert json.loads(saved["best"]) == best and best["refined"] is True
    assert saved["pool"] == state["pool"] and saved["step"] == 2
    assert again.best_seq_asr == best["SeqASR"]
    later = optimize_texture(AttackConfig(**base, refine_passes=1, refine_clips=1), detector, tmp_path,
                             body_model=body, progress=False, resume=True)
    assert later.best_seq_asr == best["SeqASR"] and np.array_equal(later.best_texture, again.best_texture)
