"""tools/score_validation_clips.py: the baselines and given textures scored on an attack's validation clips."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "rvt_mini_fixture.safetensors"
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_scores_the_baselines_and_a_grey_texture_as_tested_and_as_trained(load_tool, tmp_path, capsys):
    tool = load_tool("score_validation_clips")
    grey = np.full((4, 4), 0.5, np.float32)
    np.save(tmp_path / "grey.npy", grey)
    out = tmp_path / "rows.json"
    assert tool.main(["--detector", str(FIXTURE), "--cells", "4", "--clips", "1", "--texture",
                      f"grey={tmp_path / 'grey.npy'}", "--out", str(out), "--quiet"]) == 0
    report = json.loads(out.read_text())
    assert [r["texture"] for r in report["rows"]] == ["white", "black", "random 4x4", "grey"]
    # the report records the command its main was given, not the process's (here pytest's)
    assert report["command"] == (f"python tools/score_validation_clips.py --detector {FIXTURE} --cells 4 --clips 1 "
                                 f"--texture grey={tmp_path / 'grey.npy'} --out {out} --quiet")
    for row in report["rows"]:
        assert row["num_sequences"] == 1 and 0.0 <= row["mean_top_score"] <= 1.0
        assert {"train_top_score", "transfer_gap"} <= set(row)
    assert capsys.readouterr().out.count("\n| ") == 4  # the rows after the header line: one per texture
    assert tool.main(["--detector", str(FIXTURE), "--cells", "4", "--clips", "1", "--random", "2", "--seed", "5",
                      "--out", str(out), "--quiet"]) == 0
    rows = {r["texture"]: r for r in json.loads(out.read_text())["rows"]}
    assert list(rows) == ["white", "black", "random 4x4, seed 5", "random 4x4, seed 6", "random 4x4, mean of 2"]
    pair = [rows["random 4x4, seed 5"], rows["random 4x4, seed 6"]]
    for key in ("SeqASR", "mean_top_score", "train_SeqASR", "train_top_score"):
        assert rows["random 4x4, mean of 2"][key] == pytest.approx((pair[0][key] + pair[1][key]) / 2)
    # a grey .npy keeps its levels; a texture outside [0, 1] is refused
    assert np.array_equal(tool.load_texture(tmp_path / "grey.npy"), grey)
    np.save(tmp_path / "bad.npy", grey + 1)
    from davis_rig.errors import FormatError

    with pytest.raises(FormatError, match=r"\[0, 1\]"):
        tool.load_texture(tmp_path / "bad.npy")
