"""Detection sources: on-the-fly scoring gives davis-eval's boxes; a davis-eval report's boxes load back exactly."""

from __future__ import annotations

import shutil
import threading
from pathlib import Path

import numpy as np
import pytest

from davis_rig.errors import FormatError
from davis_rig.evaluation.detections import read_detections, write_detections
from davis_rig.evaluation.physical import EvalSettings, evaluate_sessions, score_session
from davis_rig.evaluation.report import write_report
from davis_rig.models import default_detector_path
from davis_rig.models.rvt.ort_runner import RVTOnnxRunner
from davis_rig.viewer.detections import DetectionWorker, OnTheFlyDetections, StoredDetections, find_stored_detections
from davis_rig.viewer.recording import RecordingView

from tests.helpers.eval_data import person_rvt

REPO = Path(__file__).resolve().parents[2]
THRESHOLDS = (0.01, 0.1, 0.25)


def same_rows(a, b) -> bool:
    a = np.zeros((0, 7), np.float32) if a is None else a
    b = np.zeros((0, 7), np.float32) if b is None else b
    return a.shape == b.shape and np.array_equal(a, b)


def test_on_the_fly_scoring_equals_davis_eval_with_the_bundled_detector(tmp_path):
    session = shutil.copyfile(REPO / "recordings" / "sample.h5", tmp_path / "sample.h5")
    runner = RVTOnnxRunner(default_detector_path(), intra_op_threads=1)
    expected = score_session(session, runner, EvalSettings(thresholds=THRESHOLDS))
    with RecordingView(session) as view:
        np.testing.assert_array_equal(view.window_end_us, expected.window_end_us)
        source = OnTheFlyDetections(view.path, runner, view.window_end_us, view.window_us, view.crop_origin_xy,
                                    THRESHOLDS, block_windows=5)  # another block size than davis-eval's
        assert source.get(0, 0.25) is None and source.scored() == 0
        with DetectionWorker([source]):
            assert source.wait_scored(view.num_windows, timeout_s=300)
        assert source.error is None and source.describe()["scored"] == view.num_windows
        found = 0
        for threshold in THRESHOLDS:
            for k in range(view.num_windows):
                assert same_rows(source.get(k, threshold), expected.detections[threshold][k]), (threshold, k)
                found += len(source.get(k, threshold))
        assert found > 0  # the bundled detector finds the person of the sample


def test_stopping_the_worker_stops_scoring(scene):
    release = threading.Event()

    class SlowRunner:
        path = Path("slow.onnx")

        def step(self, hist, states):
            release.wait(5)
            return np.zeros((1, 10, 7), np.float32), states

    with RecordingView(scene) as view:
        source = OnTheFlyDetections(view.path, SlowRunner(), view.window_end_us, view.window_us,
                                    view.crop_origin_xy, (0.1,))
        with DetectionWorker([source]):
            release.set()
            source.wait_scored(2, timeout_s=30)
        scored = source.scored()
        assert 2 <= scored <= view.num_windows and source.get(0, 0.1).shape == (0, 7)
        assert not source.wait_scored(view.num_windows + 1, timeout_s=0.1)  # done: returns at once


def test_report_detections_round_trip_and_are_found_for_the_session(scene, tmp_path):
    session = shutil.copyfile(scene, tmp_path / "walk.h5")
    settings = EvalSettings(thresholds=(0.1, 0.25))
    results, scores = evaluate_sessions([session], person_rvt(tmp_path), settings)
    written = write_report(results, scores, settings, tmp_path / "run", plot=False, gif=False)
    path = written["detections:walk"]
    assert path == tmp_path / "run" / "walk.detections.npz"
    stored, file = find_stored_detections(tmp_path / "run", session)
    assert file == path and stored.thresholds == [0.1, 0.25] and stored.name == "walk"
    with RecordingView(session) as view:
        source = StoredDetections(stored, file, view.window_end_us, view.crop_origin_xy)
        assert source.scored() == view.num_windows and source.describe()["source"] == "report"
        for threshold in (0.1, 0.25):
            for k in range(view.num_windows):
                assert same_rows(source.get(k, threshold), scores[0].detections[threshold][k])
        assert len(source.get(12, 0.25)) == 1  # the oracle's box
        # another recording (or window length) is refused
        with pytest.raises(FormatError, match="windows"):
            StoredDetections(stored, file, view.window_end_us[:-1], view.crop_origin_xy)
        with pytest.raises(FormatError, match="crop origin"):
            StoredDetections(stored, file, view.window_end_us, (0, 0))
    # a report made elsewhere: matched by file name when the stored path does not exist here
    moved = tmp_path / "elsewhere" / "walk.h5"
    moved.parent.mkdir()
    shutil.move(session, moved)
    assert find_stored_detections(tmp_path / "run", moved)[1] == path
    assert find_stored_detections(path, moved)[1] == path  # a single file


def test_detections_file_errors(scene, tmp_path):
    with pytest.raises(FormatError, match="detections"):
        find_stored_detections(tmp_path, scene)  # an empty folder
    bad = tmp_path / "x.detections.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(FormatError, match=r"x.detections.npz: not an .npz file \(it starts with b'not '\)"):
        read_detections(bad)
    with pytest.raises(FormatError, match="cannot read"):
        read_detections(tmp_path / "missing.detections.npz")
    bad.write_bytes(b"PK\x03\x04 truncated zip")
    with pytest.raises(FormatError, match="cannot read as a detections .npz"):
        read_detections(bad)
    np.savez(bad, format=np.array("something else"))
    with pytest.raises(FormatError, match="not a davis_rig.window_detections"):
        read_detections(bad)


def test_two_files_for_one_session_are_ambiguous(scene, tmp_path):
    from davis_rig.evaluation.physical import SessionScores

    scores = SessionScores(path=Path("/elsewhere/scene.h5"), t0_us=0, window_end_us=np.array([50_000]),
                           detections={0.1: [None]}, labels=np.zeros(0), crop_origin_xy=(21, 10), num_events=0,
                           timings_s={})
    write_detections(scores, "a", 50_000, tmp_path / "a.detections.npz")
    write_detections(scores, "b", 50_000, tmp_path / "b.detections.npz")
    with pytest.raises(FormatError, match="no single detections file"):
        find_stored_detections(tmp_path, scene)
    loaded = read_detections(tmp_path / "a.detections.npz")
    assert loaded.detections == {0.1: [None]} and loaded.crop_origin_xy == (21, 10)
