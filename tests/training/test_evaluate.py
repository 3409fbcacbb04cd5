"""Held-out split scoring: exact AP/SeqASR on hand-made detections, grouping, the davis-eval-dataset CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from davis_rig.cli import eval_dataset as cli
from davis_rig.training.evaluate import (AP_THRESHOLD, SequenceDetections, SplitScoreConfig, _groups,
                                         format_scores, score_sequences)
from davis_rig.types import BBOX_DTYPE

WINDOW_US = 50_000


def _label(t_us: int, x: float = 100.0, y: float = 60.0, w: float = 40.0, h: float = 100.0) -> np.ndarray:
    box = np.zeros(1, BBOX_DTYPE)
    box["t"], box["x"], box["y"], box["w"], box["h"], box["class_id"], box["class_confidence"] = t_us, x, y, w, h, 1, 1
    return box


def _det(label: np.ndarray, score: float, shift: float = 0.0) -> np.ndarray:
    """RVT post-processed row (x1, y1, x2, y2, obj, class_conf, class_id) for a label box, shifted in x."""
    b = label[0]
    return np.array([[b["x"] + shift, b["y"], b["x"] + shift + b["w"], b["y"] + b["h"], score, 1.0, 1]], np.float32)


def _record(hits: list[bool], subset: str = "white/large", shift: float = 0.0) -> SequenceDetections:
    """A sequence with one labelled person per window; ``hits[w]``: window w has a detection at score 0.9."""
    ends = WINDOW_US * np.arange(1, len(hits) + 1, dtype=np.int64)
    labels = [_label(int(t)) for t in ends]
    dets = [_det(lab, 0.9, shift) if hit else None for lab, hit in zip(labels, hits)]
    return SequenceDetections(name="seq", subset=subset, window_end_us=ends, labels=labels,
                              detections={AP_THRESHOLD: dets, 0.1: dets, 0.25: dets})


def test_perfect_detections_give_ap_one_and_zero_seqasr():
    result = score_sequences([_record([True] * 6)], SplitScoreConfig(skip_first_us=0, seq_len=3))
    assert result["AP"] == pytest.approx(1.0) and result["AP_50"] == pytest.approx(1.0)
    assert result["num_labels"] == 6 and result["sequences"] == 1
    assert result["seqasr"][0.25] == {"seq_asr": 0.0, "num_sequences": 2, "num_detected": 2}


def test_seqasr_counts_sequences_without_any_pedestrian_box():
    # windows 0-2 missed entirely, 3-5 hit once: one of two sequences attacked successfully
    result = score_sequences([_record([False, False, False, False, True, False])],
                             SplitScoreConfig(skip_first_us=0, seq_len=3))
    assert result["seqasr"][0.25] == {"seq_asr": 0.5, "num_sequences": 2, "num_detected": 1}
    # the remainder of a run shorter than seq_len is not evaluated: 7 windows -> 2 sequences of 3
    result = score_sequences([_record([False] * 7)], SplitScoreConfig(skip_first_us=0, seq_len=3))
    assert result["seqasr"][0.25] == {"seq_asr": 1.0, "num_sequences": 2, "num_detected": 0}
    assert result["AP"] == 0.0


def test_skip_first_drops_early_windows_from_ap_and_seqasr():
    # the first 3 windows (ends 50..150 ms) fall in the skipped 150 ms; only windows 3-5 count
    hits = [False, False, False, True, True, True]
    result = score_sequences([_record(hits)], SplitScoreConfig(skip_first_us=150_000, seq_len=3))
    assert result["num_labels"] == 3 and result["AP"] == pytest.approx(1.0)
    assert result["seqasr"][0.25] == {"seq_asr": 0.0, "num_sequences": 1, "num_detected": 1}


def test_a_box_off_by_half_its_width_counts_for_seqasr_not_for_ap50():
    # IoU of a 40 px wide box shifted by 20 px = 20 / 60 = 1/3 < 0.5: a false positive for AP, yet "detected"
    result = score_sequences([_record([True] * 3, shift=20.0)], SplitScoreConfig(skip_first_us=0, seq_len=3))
    assert result["AP_50"] == 0.0
    assert result["seqasr"][0.25]["seq_asr"] == 0.0


def test_groups_split_by_clothing_and_subset_and_table_lists_them():
    records = [_record([True] * 3, "white/large"), _record([False] * 3, "black/small"),
               _record([True] * 3, "white/small")]
    groups = _groups(records)
    assert {k: len(v) for k, v in groups.items()} == {"all": 3, "white": 2, "white/large": 1, "black": 1,
                                                      "black/small": 1, "white/small": 1}
    assert list(_groups([_record([True], "")])) == ["all"]
    result = {"config": {"seqasr_thresholds": [0.25]},
              "groups": {k: score_sequences(v, SplitScoreConfig(skip_first_us=0)) for k, v in groups.items()}}
    table = format_scores(result).splitlines()
    assert table[0] == "| group | sequences | labels | AP | AP50 | SeqASR@0.25 (%) |"
    # 6 of 9 labels found at precision 1: COCO's 101 recall points 0.00..0.66 -> AP = 67 / 101
    assert table[2] == "| all | 3 | 9 | 0.663 | 0.663 | 33.3 (1/3) |"
    assert table[5] == "| black | 1 | 3 | 0.000 | 0.000 | 100.0 (1/1) |"


def test_config_and_cli_reject_bad_values(tmp_path, capsys):
    with pytest.raises(ValueError):
        SplitScoreConfig(seq_len=0)
    with pytest.raises(ValueError):
        SplitScoreConfig(seqasr_thresholds=(1.5,))
    assert cli.main([str(tmp_path), "--threshold", "0"]) == 2
    assert ("davis-eval-dataset: error: argument --threshold: expected values in (0, 1), got (0.0,)"
            in capsys.readouterr().err)  # SplitScoreConfig's ConfigError, mapped onto the option
    assert cli.main([str(tmp_path), "--seq-len", "0"]) == 2
    assert "argument --seq-len: expected an integer >= 1, got '0'" in capsys.readouterr().err
    assert cli.main([str(tmp_path / "missing"), "--weights", str(tmp_path / "w.safetensors"), "-q"]) == 4
    assert "no such split folder" in capsys.readouterr().err


def test_cli_prints_the_table_and_writes_json(monkeypatch, tmp_path, capsys):
    import davis_rig.training.evaluate as evaluate

    calls = []

    def fake_evaluate_split(data_dir, weights, *, config, device, progress, threads=None):
        calls.append((data_dir, weights, config, device))
        groups = {"all": score_sequences([_record([True] * 3)], config)}
        return {"weights": "w.safetensors", "split": config.split, "time_s": 0.1, "groups": groups,
                "config": {"seqasr_thresholds": list(config.seqasr_thresholds)}}

    monkeypatch.setattr(evaluate, "evaluate_split", fake_evaluate_split)
    out = tmp_path / "scores.json"
    assert cli.main([str(tmp_path), "--weights", "w.safetensors", "--threshold", "0.1,0.25", "--seq-len", "3",
                     "--skip-first-ms", "0", "--json", str(out)]) == 0
    ((_, weights, config, device),) = calls
    assert weights == "w.safetensors" and device == "cpu"
    assert config == SplitScoreConfig(seqasr_thresholds=(0.1, 0.25), seq_len=3, skip_first_us=0)
    printed = capsys.readouterr().out
    assert "| all | 1 | 3 | 1.000 | 1.000 | 0.0 (0/1) | 0.0 (0/1) |" in printed
    assert json.loads(out.read_text())["groups"]["all"]["num_labels"] == 3
