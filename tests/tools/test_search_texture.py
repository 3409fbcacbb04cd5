"""tools/search_texture.py on the mini RVT fixture: the run folder, run.json and the printed summary."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "rvt_mini_fixture.safetensors"
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_a_short_search_writes_its_run_and_reports_the_kept_generation(load_tool, tmp_path, capsys):
    tool = load_tool("search_texture")
    trigger = np.array([[1, 0, 1, 0], [0, 1, 0, 1], [1, 1, 0, 0], [0, 0, 1, 1]], np.float32)
    np.save(tmp_path / "trigger.npy", trigger)
    out = tmp_path / "run"
    assert tool.main(["--out", str(out), "--detector", str(FIXTURE), "--trigger", str(tmp_path / "trigger.npy"),
                      "--cells", "4", "--generations", "2", "--population", "2", "--elite", "1", "--pool-clips", "2",
                      "--clips-per-grid", "1", "--val-clips", "1", "--validate-every", "1", "--quiet"]) == 0
    run = json.loads((out / "run.json").read_text())
    assert run["generations"] == 2 and run["stopped"] is False and run["detector"] == str(FIXTURE)
    assert run["command"].startswith("python tools/search_texture.py") and run["best"]["generation"] in (1, 2)
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert all("agreement" in r and "validation" in r for r in records)
    assert f"kept generation {run['best']['generation']}" in capsys.readouterr().out
    assert np.load(out / "best_texture.npy").shape == (4, 4)


def test_a_stopped_search_says_so_and_exits_130(load_tool, tmp_path, monkeypatch, capsys):
    import davis_rig.attack.search as search

    def stopped(config, detector, out, settings, **kwargs):
        Path(out).mkdir()
        return {"best": None, "generations": 4, "seconds": 1.0, "cells": 12, "stopped": True}

    monkeypatch.setattr(search, "search_texture", stopped)
    tool = load_tool("search_texture")
    assert tool.main(["--out", str(tmp_path / "run"), "--detector", str(FIXTURE), "--quiet"]) == 130
    err = capsys.readouterr().err.splitlines()
    assert err[-2] == f"search_texture.py: stopped after 4 finished generations, kept in {tmp_path / 'run'}"
    assert err[-1] == "search_texture.py: interrupted"
    assert json.loads((tmp_path / "run" / "run.json").read_text())["stopped"] is True
