"""The cross-entropy search (davis_rig.attack.search): its pure steps on hand-made vectors, the loop on scores with a
known optimum (and a control that ignores the grid), and a run against the mini RVT fixture."""

from __future__ import annotations

import json

import numpy as np
import torch
import pytest

from davis_rig.attack.search import (SearchSettings, cem_update, cross_entropy_search, mean_entropy_bits,
                                     mode_grid, sample_grids, start_probabilities)


def _cells(n: int = 4, searched: int = 12) -> np.ndarray:
    cells = np.zeros((n, n), bool)
    cells.flat[:searched] = True
    return cells


def test_sample_grids_draw_each_searched_cell_with_its_probability_and_fill_the_rest():
    cells = _cells()
    p = np.zeros((4, 4))
    p.flat[:4] = 1.0
    p.flat[4:8] = 0.25
    p.flat[12:] = 1.0  # not searched: never drawn
    grids = sample_grids(p, cells, 4000, np.random.default_rng(0), fill=0.0)
    assert grids.shape == (4000, 4, 4) and grids.dtype == np.float32
    flat = grids.reshape(4000, 16)
    assert np.all(flat[:, :4] == 1) and np.all(flat[:, 8:] == 0)
    assert np.abs(flat[:, 4:8].mean(axis=0) - 0.25).max() < 0.03


def test_cem_update_moves_each_searched_probability_towards_the_elites_share_of_white():
    cells = np.array([[True, True, True, False]])
    p = np.array([[0.5, 0.5, 0.99, 0.3]])
    elite = np.array([[[1, 0, 1, 1]], [[1, 0, 1, 0]]], np.float32)
    moved = cem_update(p, elite, cells, smoothing=0.2)
    np.testing.assert_allclose(moved, [[0.6, 0.4, 0.992, 0.3]])
    clipped = cem_update(p, elite, cells, smoothing=1.0, floor=0.05)
    np.testing.assert_allclose(clipped, [[0.95, 0.05, 0.95, 0.3]])  # the unsearched cell keeps its value


def test_mode_grid_and_entropy():
    cells = np.array([[True, True, True, False]])
    p = np.array([[0.9, 0.1, 0.5, 0.9]])
    np.testing.assert_array_equal(mode_grid(p, cells), [[1, 0, 0, 0]])
    assert mean_entropy_bits(np.full((1, 4), 0.5), cells) == pytest.approx(1.0)
    assert mean_entropy_bits(np.array([[0.0, 1.0, 0.0, 0.5]]), cells) == pytest.approx(0.0, abs=1e-9)
    assert mean_entropy_bits(p, cells) == pytest.approx((2 * 0.4689955935892812 + 1.0) / 3)


def test_start_probabilities_keep_the_start_grids_colours_with_the_given_confidence():
    cells = np.array([[True, True, False], [True, True, True]])
    grid = np.array([[1, 0, 1], [0, 1, 0]], np.float32)
    np.testing.assert_allclose(start_probabilities(grid, 0.9, cells), [[0.9, 0.1, 0.5], [0.1, 0.9, 0.1]])
    np.testing.assert_allclose(start_probabilities(grid, 0.5, cells), np.full((2, 3), 0.5))
    for confidence in (0.4, 1.0):
        with pytest.raises(ValueError, match=r"confidence must be in \[0.5, 1\)"):
            start_probabilities(grid, confidence, cells)
    with pytest.raises(ValueError, match=r"the start grid is \[2, 3\], the cells \[3, 2\]"):
        start_probabilities(grid, 0.9, cells.T)


def test_a_continued_search_draws_what_the_uninterrupted_one_draws():
    cells = _cells(6, 30)
    target = (np.arange(36).reshape(6, 6) % 3 == 0).astype(np.float32)
    settings = SearchSettings(generations=6, population=8, elite=2, smoothing=0.3)
    whole = []
    p_whole = cross_entropy_search(_distance_score(target, cells), np.full((6, 6), 0.5), cells, settings,
                                   np.random.default_rng(3), lambda record, p: whole.append(record))
    parts, rng = [], np.random.default_rng(3)
    first = cross_entropy_search(_distance_score(target, cells), np.full((6, 6), 0.5), cells,
                                 SearchSettings(generations=2, population=8, elite=2, smoothing=0.3), rng,
                                 lambda record, p: parts.append(record))
    p_parts = cross_entropy_search(_distance_score(target, cells), first, cells, settings, rng,
                                   lambda record, p: parts.append(record), first_generation=3)
    assert parts == whole and [r["generation"] for r in parts] == [1, 2, 3, 4, 5, 6]
    np.testing.assert_array_equal(p_parts, p_whole)


def _distance_score(target: np.ndarray, cells: np.ndarray):
    def score(grids: np.ndarray, generation: int) -> np.ndarray:
        return np.abs(grids - target)[:, cells].sum(axis=1).astype(float)
    return score


def test_the_search_finds_a_hidden_grid_from_its_distance_alone():
    cells = _cells(6, 30)
    target = np.where(cells, np.random.default_rng(3).random((6, 6)) < 0.5, 0).astype(np.float32)
    records = []
    p = cross_entropy_search(_distance_score(target, cells), np.full((6, 6), 0.5), cells,
                             SearchSettings(generations=30, population=12, elite=3, smoothing=0.3, floor=0.02),
                             np.random.default_rng(0), lambda record, probs: records.append(record))
    np.testing.assert_array_equal(mode_grid(p, cells), target)
    assert [r["generation"] for r in records] == list(range(1, 31))
    assert records[-1]["entropy_bits"] < records[0]["entropy_bits"]
    assert records[-1]["score_mean"] < records[0]["score_mean"]
    np.testing.assert_array_equal(records[-1]["mode"], target)


def test_control_a_score_blind_to_the_grid_finds_nothing():
    cells = _cells(6, 30)
    target = np.where(cells, np.random.default_rng(3).random((6, 6)) < 0.5, 0).astype(np.float32)
    noise = np.random.default_rng(1)
    p = cross_entropy_search(lambda grids, generation: noise.random(len(grids)), np.full((6, 6), 0.5), cells,
                             SearchSettings(generations=30, population=12, elite=3, smoothing=0.3, floor=0.02),
                             np.random.default_rng(0))
    agreement = float((mode_grid(p, cells) == target)[cells].mean())
    assert 0.2 < agreement < 0.8


def test_a_score_of_the_wrong_shape_and_bad_settings_are_refused():
    cells = _cells()
    with pytest.raises(ValueError, match=r"score returned shape \(3,\), expected \(4,\)"):
        cross_entropy_search(lambda grids, generation: np.zeros(3), np.full((4, 4), 0.5), cells,
                             SearchSettings(generations=1, population=4, elite=1), np.random.default_rng(0))
    for kwargs, message in (({"elite": 5, "population": 4}, "elite must be in"), ({"smoothing": 0}, "smoothing"),
                            ({"floor": 0.5}, "floor"), ({"population": 1, "elite": 1}, "population >= 2")):
        with pytest.raises(ValueError, match=message):
            SearchSettings(**kwargs)


FIXTURE = "tests/fixtures/rvt_mini_fixture.safetensors"


def _search(tmp_path, settings: SearchSettings, validation_clips: int = 1, **kwargs) -> dict:
    """search_texture against the mini RVT on 4x4 grids, into ``tmp_path / "run"``."""
    from davis_rig.attack.config import AttackConfig
    from davis_rig.attack.optimize import load_attack_detector
    from davis_rig.attack.search import search_texture

    config = AttackConfig(grid_n=4, seed=0, num_validation_clips=validation_clips)
    return search_texture(config, load_attack_detector(FIXTURE), tmp_path / "run", settings, **kwargs)


def _log(tmp_path) -> list[dict]:
    return [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]


class _StopAfter:
    """A stop request that arrives after ``checks`` polls."""

    def __init__(self, checks: int):
        self.left = checks

    @property
    def requested(self) -> bool:
        self.left -= 1
        return self.left < 0


@pytest.mark.usefixtures("one_torch_thread")
def test_search_texture_writes_a_run_folder_and_keeps_its_best_validated_grid(tmp_path):
    trigger = np.eye(4, dtype=np.float32)
    result = _search(tmp_path, SearchSettings(generations=3, population=3, elite=1), validation_clips=2,
                     pool_clips=3, clips_per_grid=2, validate_every=2, reference=trigger)
    run = tmp_path / "run"
    records = _log(tmp_path)
    assert [r["generation"] for r in records] == [1, 2, 3] and not result["stopped"]
    assert ["validation" in r for r in records] == [False, True, True]  # every 2nd and the last
    cells = result["cells"]
    assert 0 < cells <= 16
    for r in records:  # a share of the searched cells
        assert 0.0 <= r["agreement"] <= 1.0 and r["agreement"] * cells == pytest.approx(round(r["agreement"] * cells))
    best = json.loads((run / "best.json").read_text())
    assert best == result["best"] and best["generation"] in (2, 3)
    kept = [r for r in records if r["generation"] == best["generation"]][0]
    np.testing.assert_array_equal(np.load(run / "best_texture.npy"), kept["mode"])
    np.testing.assert_array_equal(np.load(run / "texture.npy"), records[-1]["mode"])
    p = np.load(run / "probabilities.npy")
    assert p.shape == (4, 4) and np.all((p >= 0.02) | (p == 0.5)) and np.all((p <= 0.98) | (p == 0.5))
    summary = json.loads((run / "search.json").read_text())
    assert summary["generations"] == 3 and summary["settings"]["population"] == 3 and summary["cells"] == cells
    assert (run / "best_texture.png").is_file() and (run / "texture.png").is_file()


@pytest.mark.usefixtures("one_torch_thread")
def test_a_stop_request_keeps_the_finished_generations(tmp_path):
    # generation 1 polls 3 grids x 1 clip, its validation 1 clip; the stop arrives inside generation 2
    result = _search(tmp_path, SearchSettings(generations=5, population=3, elite=1), pool_clips=2, clips_per_grid=1,
                     validate_every=1, stop=_StopAfter(5))
    assert result["stopped"] and result["generations"] == 1
    records = _log(tmp_path)
    assert len(records) == 1
    np.testing.assert_array_equal(np.load(tmp_path / "run" / "texture.npy"), records[0]["mode"])
    assert json.loads((tmp_path / "run" / "search.json").read_text())["stopped"] is True


@pytest.mark.usefixtures("one_torch_thread")
def test_a_stop_during_a_validation_keeps_the_log_and_the_texture_in_step(tmp_path):
    # generation 1: 2 grids x 1 clip (2 polls) + its validation (1 poll); generation 2: 2 more, then its validation
    result = _search(tmp_path, SearchSettings(generations=3, population=2, elite=1), pool_clips=1, clips_per_grid=1,
                     validate_every=1, stop=_StopAfter(5))
    records = _log(tmp_path)
    assert result["stopped"] and result["generations"] == len(records) == 1
    np.testing.assert_array_equal(np.load(tmp_path / "run" / "texture.npy"), records[0]["mode"])


@pytest.mark.usefixtures("one_torch_thread")
def test_a_stop_before_the_first_generation_writes_no_texture(tmp_path):
    result = _search(tmp_path, SearchSettings(generations=2, population=2, elite=1), pool_clips=1, clips_per_grid=1,
                     stop=_StopAfter(0))
    assert result["stopped"] and result["generations"] == 0 and result["best"] is None
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["log.jsonl", "search.json"]
    assert (tmp_path / "run" / "log.jsonl").read_text() == ""


def _without_seconds(records: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k != "seconds"} for r in records]


@pytest.mark.usefixtures("one_torch_thread")
def test_a_stopped_search_resumed_scores_what_the_uninterrupted_one_scores(tmp_path):
    settings = SearchSettings(generations=4, population=2, elite=1)
    kwargs = dict(pool_clips=3, clips_per_grid=1, validate_every=2)
    whole = _search(tmp_path / "whole", settings, **kwargs)
    # generation 1: 2 polls; 2: 2 + its validation's 1; the stop arrives inside generation 3
    stopped = _search(tmp_path / "parts", settings, stop=_StopAfter(6), **kwargs)
    assert stopped["stopped"] and stopped["generations"] == 2
    state = json.loads((tmp_path / "parts" / "run" / "state.json").read_text())
    assert state["generation"] == 2 and state["best"] == stopped["best"]
    resumed = _search(tmp_path / "parts", settings, resume=True, **kwargs)
    assert resumed["generations"] == 4 and not resumed["stopped"] and resumed["best"] == whole["best"]
    assert _without_seconds(_log(tmp_path / "parts")) == _without_seconds(_log(tmp_path / "whole"))
    for name in ("probabilities.npy", "texture.npy", "best_texture.npy"):
        np.testing.assert_array_equal(np.load(tmp_path / "parts" / "run" / name),
                                      np.load(tmp_path / "whole" / "run" / name))
    # a finished run continued with more generations goes on where it ended
    longer = _search(tmp_path / "parts", SearchSettings(generations=5, population=2, elite=1), resume=True,
                     **kwargs)
    assert longer["generations"] == 5 and [r["generation"] for r in _log(tmp_path / "parts")] == [1, 2, 3, 4, 5]


@pytest.mark.usefixtures("one_torch_thread")
def test_a_folder_holding_a_search_is_refused_without_resume_and_with_other_settings(tmp_path):
    from davis_rig.errors import CheckpointError

    settings = SearchSettings(generations=1, population=2, elite=1)
    _search(tmp_path, settings, pool_clips=1, clips_per_grid=1)
    run = tmp_path / "run"
    before = (run / "log.jsonl").read_text()
    with pytest.raises(CheckpointError, match=r"already holds a search .*state.json.*--resume"):
        _search(tmp_path, settings, pool_clips=1, clips_per_grid=1)
    with pytest.raises(CheckpointError, match=r"written with other settings \(settings\); only --generations"):
        _search(tmp_path, SearchSettings(generations=2, population=3, elite=1), pool_clips=1, clips_per_grid=1,
                resume=True)
    with pytest.raises(CheckpointError, match=r"\(clips_per_grid, pool_clips\)"):
        _search(tmp_path, settings, pool_clips=2, clips_per_grid=2, resume=True)
    assert (run / "log.jsonl").read_text() == before  # nothing of the run is lost
    (run / "state.json").write_text('{"generation": 1')
    with pytest.raises(CheckpointError, match=r"state.json: unreadable search state"):
        _search(tmp_path, settings, pool_clips=1, clips_per_grid=1, resume=True)
    (run / "state.json").unlink()
    with pytest.raises(CheckpointError, match=r"records generations but there is no .*state.json"):
        _search(tmp_path, settings, pool_clips=1, clips_per_grid=1, resume=True)


@pytest.mark.usefixtures("one_torch_thread")
def test_a_search_around_a_start_grid_validates_the_start_first(tmp_path):
    start = np.array([[1, 0, 1, 0], [0, 1, 0, 1], [1, 0, 1, 0], [0, 1, 0, 1]], np.float32)
    result = _search(tmp_path, SearchSettings(generations=1, population=2, elite=1, smoothing=0.5),
                     pool_clips=1, clips_per_grid=1, validate_every=1, start_grid=start, start_confidence=0.8)
    records = _log(tmp_path)
    assert [r["generation"] for r in records] == [0, 1] and records[0]["start"] is True
    seen = np.array(records[0]["mode"]) != 0  # the start's mode: the start grid on the searched cells, 0 elsewhere
    np.testing.assert_array_equal(np.array(records[0]["mode"])[seen], start[seen])
    assert 0 < seen.sum() < start.sum() <= result["cells"]
    best = result["best"]["generation"]
    np.testing.assert_array_equal(np.load(tmp_path / "run" / "best_texture.npy"), records[best]["mode"])
    p = np.load(tmp_path / "run" / "probabilities.npy")  # one step of 0.5 from 0.8 / 0.2 towards one grid
    assert set(np.round(p[p != 0.5], 6)) <= {0.1, 0.4, 0.6, 0.9}


@pytest.mark.usefixtures("one_torch_thread")
def test_a_search_around_a_start_grid_resumes_around_it_without_naming_it_again(tmp_path):
    from davis_rig.errors import CheckpointError

    start = np.array([[1, 0, 1, 0], [0, 1, 0, 1], [1, 0, 1, 0], [0, 1, 0, 1]], np.float32)
    kwargs = dict(pool_clips=2, clips_per_grid=1, validate_every=1)
    whole = _search(tmp_path / "whole", SearchSettings(generations=2, population=2, elite=1), start_grid=start,
                    start_confidence=0.8, **kwargs)
    _search(tmp_path / "parts", SearchSettings(generations=1, population=2, elite=1), start_grid=start,
            start_confidence=0.8, **kwargs)
    resumed = _search(tmp_path / "parts", SearchSettings(generations=2, population=2, elite=1), resume=True, **kwargs)
    assert resumed["best"] == whole["best"]
    assert _without_seconds(_log(tmp_path / "parts")) == _without_seconds(_log(tmp_path / "whole"))
    with pytest.raises(CheckpointError, match=r"other settings \(start_grid\)"):  # another start is still refused
        _search(tmp_path / "parts", SearchSettings(generations=3, population=2, elite=1), resume=True,
                start_grid=1 - start, start_confidence=0.8, **kwargs)
    # a run without a start resumes as one: nothing is taken from a state that has none
    _search(tmp_path / "plain", SearchSettings(generations=1, population=2, elite=1), **kwargs)
    plain = _search(tmp_path / "plain", SearchSettings(generations=2, population=2, elite=1), resume=True, **kwargs)
    assert plain["generations"] == 2 and [r["generation"] for r in _log(tmp_path / "plain")] == [1, 2]


def test_search_texture_refuses_bad_arguments_before_any_work(tmp_path):
    from davis_rig.attack.config import AttackConfig
    from davis_rig.attack.search import search_texture

    config = AttackConfig(grid_n=4, seed=0)
    with pytest.raises(ValueError, match=r"reference must be \[4, 4\], got \[3, 3\]"):
        search_texture(config, None, tmp_path / "run", SearchSettings(), reference=np.ones((3, 3)))
    with pytest.raises(ValueError, match=r"clips_per_grid must be in \[1, pool_clips=2\], got 3"):
        search_texture(config, None, tmp_path / "run", SearchSettings(), pool_clips=2, clips_per_grid=3)
    with pytest.raises(ValueError, match=r"start_grid must be \[4, 4\], got \[5, 5\]"):
        search_texture(config, None, tmp_path / "run", SearchSettings(), start_grid=np.ones((5, 5)))
    with pytest.raises(ValueError, match=r"start_confidence must be in \[0.5, 1\), got 1.0"):
        search_texture(config, None, tmp_path / "run", SearchSettings(), start_grid=np.ones((4, 4)),
                       start_confidence=1.0)
    assert not (tmp_path / "run").exists()


def test_a_search_or_an_optimisation_resumed_against_other_weights_is_refused_and_keeps_the_search(tmp_path):
    from davis_rig.attack.config import AttackConfig
    from davis_rig.attack.optimize import load_attack_detector, optimize_texture
    from davis_rig.attack.search import search_texture
    from davis_rig.errors import CheckpointError

    settings = SearchSettings(generations=1, population=2, elite=1)
    _search(tmp_path, settings, pool_clips=1, clips_per_grid=1)
    run = tmp_path / "run"
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    other = load_attack_detector(FIXTURE)
    with torch.no_grad():
        next(other.parameters()).mul_(1.05)
    config = AttackConfig(grid_n=4, seed=0, num_validation_clips=1)
    with pytest.raises(CheckpointError, match="written against another detector"):
        search_texture(config, other, run, settings, pool_clips=1, clips_per_grid=1, resume=True)
    # an optimisation "resumed" in the search's folder would start from step 0 and clear its outputs
    with pytest.raises(CheckpointError, match="holds log.jsonl.* of another run"):
        optimize_texture(AttackConfig(grid_n=4, iterations=1, pool_size=1, num_validation_clips=1), other, run,
                         progress=False, resume=True)
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before
