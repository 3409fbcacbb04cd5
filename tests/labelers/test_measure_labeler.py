"""tools/measure_labeler.py on frames with known boxes and a YOLO graph with known output."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from tests.helpers.eval_data import PERSON_BOX, person_yolo

TOOL = Path(__file__).resolve().parents[2] / "tools" / "measure_labeler.py"


def run_tool(*args):
    return subprocess.run([sys.executable, str(TOOL), *map(str, args)], capture_output=True, text=True, timeout=120)


def test_exact_labeler_scores_ap_one_and_a_wrong_box_scores_zero(tmp_path):
    frames = np.zeros((4, 260, 346), np.uint16)
    boxes = np.tile(np.array(PERSON_BOX, np.float64), (4, 1))
    boxes[3] = np.nan  # a frame without a person: the detection there is a false positive
    np.savez(tmp_path / "frames.npz", frames=frames, boxes=boxes)
    result = run_tool("--yolo", person_yolo(tmp_path), "--frames", tmp_path / "frames.npz", "--json", tmp_path / "r.json")
    assert result.returncode == 0, result.stderr
    data = json.loads((tmp_path / "r.json").read_text())
    assert data["labelled_frames"] == 3 and data["recall_at_0.25_iou_0.5"] == 1.0
    assert data["AP"]["AP_50"] == 1.0 and data["AP"]["AP"] > 0.99  # the false positive ranks after the hits (tie)
    assert data["AP"]["AP_S"] is None and data["median_best_iou"] > 0.999

    moved = boxes.copy()
    moved[:3] += [150, 0, 150, 0]
    np.savez(tmp_path / "moved.npz", frames=frames, boxes=moved)
    result = run_tool("--yolo", person_yolo(tmp_path), "--frames", tmp_path / "moved.npz")
    data = json.loads(result.stdout)
    assert data["AP"]["AP"] == 0.0 and data["recall_at_0.25_iou_0.5"] == 0.0


def test_bad_frames_file_exits_4(tmp_path):
    np.savez(tmp_path / "bad.npz", frames=np.zeros((2, 10, 10), np.uint8), boxes=np.zeros((3, 4)))
    result = run_tool("--yolo", person_yolo(tmp_path), "--frames", tmp_path / "bad.npz")
    assert result.returncode == 4 and "expected frames [N, H, W] and boxes [N, 4]" in result.stderr
