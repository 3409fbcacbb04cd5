"""``davis-attack search`` on the mini RVT fixture: the run folder, run.json, the printed summary, a stop and its
resume through the command line, and the mapping of the options onto the API."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from davis_rig.cli.attack import main

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "rvt_mini_fixture.safetensors"
pytestmark = pytest.mark.usefixtures("one_torch_thread")
SMALL = ["--cells", "4", "--population", "2", "--elite", "1", "--pool-clips", "2", "--clips-per-grid", "1",
         "--val-clips", "1", "--validate-every", "1", "--device", "cpu", "--quiet"]


def _log(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]


def test_a_short_search_writes_its_run_and_prints_the_kept_generation(tmp_path, capsys):
    trigger = np.array([[1, 0, 1, 0], [0, 1, 0, 1], [1, 1, 0, 0], [0, 0, 1, 1]], np.float32)
    np.save(tmp_path / "trigger.npy", trigger)
    run = tmp_path / "run"
    assert main(["search", "--out", str(run), "--detector", str(FIXTURE), "--trigger", str(tmp_path / "trigger.npy"),
                 "--generations", "2", *SMALL]) == 0
    printed = json.loads(capsys.readouterr().out)
    recorded = json.loads((run / "run.json").read_text())
    assert recorded["generations"] == printed["generations"] == 2 and recorded["stopped"] is False
    assert recorded["command"].startswith("davis-attack search --out") and recorded["detector"] == str(FIXTURE)
    assert printed["best_generation"] == recorded["best"]["generation"] in (1, 2)
    assert all("agreement" in r and "validation" in r for r in _log(run))
    assert np.load(run / "best_texture.npy").shape == (4, 4)


def test_a_stopped_search_exits_130_and_resume_finishes_it_as_one_run_would(tmp_path, monkeypatch, capsys):
    import davis_rig.stop as stop

    whole = tmp_path / "whole"
    assert main(["search", "--out", str(whole), "--detector", str(FIXTURE), "--generations", "3", *SMALL]) == 0
    polls = {"left": 4}  # generation 1 polls 2 grids + 1 validation clip; the stop arrives in generation 2

    def requested(self) -> bool:
        polls["left"] -= 1
        return polls["left"] < 0

    with monkeypatch.context() as patch:
        patch.setattr(stop.StopOnSignal, "requested", property(requested))
        parts = tmp_path / "parts"
        assert main(["search", "--out", str(parts), "--detector", str(FIXTURE), "--generations", "3", *SMALL]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"davis-attack search: interrupted after 1 finished generations, kept in {parts}; continue " \
                      "with --resume"
    assert main(["search", "--out", str(parts), "--detector", str(FIXTURE), "--generations", "3", *SMALL]) == 4
    assert "already holds a search" in capsys.readouterr().err
    assert main(["search", "--out", str(parts), "--detector", str(FIXTURE), "--generations", "3", "--resume",
                 *SMALL]) == 0
    drop = lambda records: [{k: v for k, v in r.items() if k != "seconds"} for r in records]  # noqa: E731
    assert drop(_log(parts)) == drop(_log(whole))
    np.testing.assert_array_equal(np.load(parts / "probabilities.npy"), np.load(whole / "probabilities.npy"))


def test_search_maps_its_options_onto_one_call(monkeypatch, tmp_path, capsys):
    import davis_rig.attack.optimize as opt
    import davis_rig.attack.search as search

    calls = {}
    monkeypatch.setattr(opt, "load_attack_detector", lambda path, device=None: ("detector", path, str(device)))

    def fake(config, detector, out, settings, **kwargs):
        calls.update(config=config, detector=detector, out=out, settings=settings, **kwargs)
        Path(out).mkdir()
        return {"best": None, "generations": 0, "seconds": 0.0, "cells": 12, "stopped": False}

    monkeypatch.setattr(search, "search_texture", fake)
    start = np.zeros((6, 6), np.float32)
    start[2:4] = 1
    np.save(tmp_path / "start.npy", start)
    assert main(["search", "--out", str(tmp_path / "run"), "--cells", "6", "--parts", "legs", "--generations", "7",
                 "--population", "5", "--elite", "2", "--smoothing", "0.4", "--floor", "0.01", "--pool-clips", "9",
                 "--clips-per-grid", "3", "--val-clips", "5", "--validate-every", "2", "--start",
                 str(tmp_path / "start.npy"), "--start-confidence", "0.75", "--resume", "--seed", "3",
                 "--detector", "v.safetensors", "--device", "cpu", "--quiet"]) == 0
    config, settings = calls["config"], calls["settings"]
    assert (config.grid_n, config.parts, config.seed, config.num_validation_clips) == (6, ("legs",), 3, 5)
    assert (settings.generations, settings.population, settings.elite, settings.smoothing, settings.floor) == (
        7, 5, 2, 0.4, 0.01)
    assert calls["detector"] == ("detector", "v.safetensors", "cpu") and calls["out"] == str(tmp_path / "run")
    assert (calls["pool_clips"], calls["clips_per_grid"], calls["validate_every"]) == (9, 3, 2)
    assert calls["resume"] is True and calls["start_confidence"] == 0.75 and calls["reference"] is None
    np.testing.assert_array_equal(calls["start_grid"], start)
    assert json.loads(capsys.readouterr().out)["best_generation"] is None


def test_search_draws_its_clips_from_the_distribution_optimize_would(monkeypatch, tmp_path, capsys):
    import davis_rig.attack.optimize as opt
    import davis_rig.attack.search as search
    from davis_rig.attack.config import AttackConfig
    from davis_rig.attack.eot import EoTConfig

    configs = []
    monkeypatch.setattr(opt, "load_attack_detector", lambda path, device=None: None)

    def fake(config, detector, out, settings, **kwargs):
        configs.append(config)
        Path(out).mkdir(exist_ok=True)
        return {"best": None, "generations": 0, "seconds": 0.0, "cells": 12, "stopped": False}

    monkeypatch.setattr(search, "search_texture", fake)
    out = str(tmp_path / "run")
    assert main(["search", "--out", out, "--val-clips", "64", "--quiet"]) == 0
    assert configs[-1].to_dict() == AttackConfig(grid_n=10, parts=("torso", "arms", "legs"), seed=0,
                                                 num_validation_clips=64).to_dict()  # the defaults: optimize's
    assert main(["search", "--out", out, "--walk", "bundled", "--test-sensor-probability", "0", "--select-by",
                 "score", "--events", "official_relaxed", "--playback-speed", "1.5", "--quiet"]) == 0
    config = configs[-1]
    assert (config.eot.walk, config.eot.test_sensor_probability, config.eot.playback_speed) == ("bundled", 0.0, 1.5)
    assert (config.select_by, config.events, config.v2e_mode, config.eot.threshold_sigma) == (
        "score", "official_relaxed", "official_relaxed", 0.0)
    assert main(["search", "--out", out, "--scene", "official", "--quiet"]) == 0
    assert configs[-1].eot == EoTConfig.official() != AttackConfig().eot


def test_a_real_ctrl_c_exits_130_keeping_the_finished_generations_and_resume_continues(tmp_path):
    # the command as a user runs it: SIGINT once generations are logged -> exit 130, one line; state.json at the last
    # logged generation; --resume continues after it (the library test pins the identical scores)
    import subprocess
    import sys

    from tests.helpers.interrupt import interrupt_after_log_lines, repo_env

    run = tmp_path / "run"
    argv = [sys.executable, "-m", "davis_rig.cli.attack", "search", "--out", str(run), "--cells", "2",
            "--population", "2", "--elite", "1", "--pool-clips", "1", "--clips-per-grid", "1", "--val-clips", "1",
            "--validate-every", "1000", "--detector", str(FIXTURE), "--device", "cpu", "--threads", "1", "--quiet"]
    stopped = interrupt_after_log_lines([*argv, "--generations", "1000"], run / "log.jsonl")
    assert stopped.returncode == 130, stopped.stderr
    assert "Traceback" not in stopped.stderr and stopped.last_line.startswith("davis-attack search: interrupted")
    done = json.loads((run / "state.json").read_text())["generation"]
    assert done >= 2 and [r["generation"] for r in _log(run)] == list(range(1, done + 1))
    finished = subprocess.run([*argv, "--generations", str(done + 2), "--resume"], capture_output=True, text=True,
                              env=repo_env(), timeout=240)
    assert finished.returncode == 0, finished.stderr
    assert [r["generation"] for r in _log(run)] == list(range(1, done + 3))
