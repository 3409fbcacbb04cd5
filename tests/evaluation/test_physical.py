"""The physical evaluation end to end on a session recorded through the virtual DAVIS346, with oracle RVT graphs
(known answers) and the mini RVT (consistency)."""

from __future__ import annotations

import dataclasses
import json
import math
import os

import numpy as np
import pytest

from davis_rig.errors import FormatError, ModelFormatError, SessionError
from davis_rig.evaluation.physical import (
    EvalSettings,
    SessionScores,
    compute_metrics,
    evaluate_sessions,
    labels_provenance,
    score_session,
    scoring_crop_origin,
    settings_dict,
)
from davis_rig.labelers.session_labels import label_session
from davis_rig.models.rvt.ort_runner import RVTOnnxRunner
from davis_rig.types import BBOX_DTYPE, PEDESTRIAN_CLASS_ID

from tests.helpers.eval_data import SCENE_US, person_rvt, person_yolo, scene_session, sha256

SETTINGS = EvalSettings(seq_len=5)


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    directory = tmp_path_factory.mktemp("physical")
    session = scene_session(directory, "labelled.h5")
    label_session(session, person_yolo(directory))
    return session


def evaluate(session, model, settings=SETTINGS):
    results, scores = evaluate_sessions([session], model, settings)
    return results[0].metrics, scores[0]


def test_perfect_detector_ap_one_seqasr_zero(labelled, tmp_path):
    metrics, scores = evaluate(labelled, person_rvt(tmp_path))
    assert len(scores.window_end_us) == SCENE_US // 50_000 + 1  # grid covers events (last ms) and labels
    for th in (0.001, 0.01, 0.1, 0.25):
        m = metrics[th]
        assert m["AP"] == pytest.approx(1.0) and m["AP_50"] == pytest.approx(1.0)
        assert m["seq_asr"] == 0.0 and m["seq_asr_strict"] == 0.0
    # 49 labels at 7.1 ms + 40 ms k (exposure middles); after 0.5 s: k = 13..48 -> 36 labels, in windows
    # 10 (ends 550 ms) .. 38 (ends 1950 ms) = 29 consecutive labelled windows -> 29 // 5 = 5 sequences
    assert metrics[0.25]["num_labels"] == metrics[0.25]["num_images"] == 36
    assert metrics[0.25]["num_sequences"] == 5 and metrics[0.25]["num_detected"] == 5


def test_perfect_detector_ap_is_one_at_tolerance_zero_and_a_tolerance_pools_neighbouring_windows(labelled, tmp_path):
    model = person_rvt(tmp_path)
    exact, _ = evaluate(labelled, model, EvalSettings(seq_len=5, thresholds=(0.25,), time_tol_us=0))
    assert exact[0.25]["AP"] == 1.0 and exact[0.25]["num_detections"] == exact[0.25]["num_labels"] == 36
    # 50 ms pools the copies of the neighbouring windows' detections (stamped on their label times): false positives
    pooled, _ = evaluate(labelled, model, EvalSettings(seq_len=5, thresholds=(0.25,), time_tol_us=50_000))
    assert pooled[0.25]["AP"] < 0.5 and pooled[0.25]["num_detections"] > exact[0.25]["num_detections"]


def test_no_detections_ap_zero_seqasr_one(labelled, tmp_path):
    metrics, _ = evaluate(labelled, person_rvt(tmp_path, score=0.0))
    for m in metrics.values():
        assert m["AP"] == 0.0 and m["seq_asr"] == 1.0 and m["seq_asr_strict"] == 1.0 and m["num_detections"] == 0


def test_shifted_boxes_known_ap_and_strict_seqasr(labelled, tmp_path):
    # label 80 px wide: a shift of 8 px gives IoU 72/88 = 0.818 (7 of 10 COCO thresholds), 40 px gives 1/3.
    near, _ = evaluate(labelled, person_rvt(tmp_path, shift_px=8, name="near.onnx"), EvalSettings(seq_len=5,
                                                                                                    thresholds=(0.1,)))
    assert near[0.1]["AP"] == pytest.approx(0.7) and near[0.1]["AP_75"] == pytest.approx(1.0)
    assert near[0.1]["seq_asr"] == 0.0 and near[0.1]["seq_asr_strict"] == 0.0
    far, _ = evaluate(labelled, person_rvt(tmp_path, shift_px=40, name="far.onnx"), EvalSettings(seq_len=5,
                                                                                                  thresholds=(0.1,)))
    assert far[0.1]["AP"] == 0.0
    assert far[0.1]["seq_asr"] == 0.0 and far[0.1]["seq_asr_strict"] == 1.0  # paper: any box; strict: IoU < 0.5


def test_threshold_monotonicity_with_a_low_score_detector(labelled, tmp_path):
    metrics, _ = evaluate(labelled, person_rvt(tmp_path, score=0.05))
    assert [metrics[t]["seq_asr"] for t in (0.001, 0.01, 0.1, 0.25)] == [0.0, 0.0, 1.0, 1.0]
    assert [metrics[t]["AP"] for t in (0.001, 0.01, 0.1, 0.25)] == pytest.approx([1.0, 1.0, 0.0, 0.0])


def test_skip_first_and_sliding_sequences_are_options(labelled, tmp_path):
    model = person_rvt(tmp_path)
    keep_all, _ = evaluate(labelled, model, EvalSettings(seq_len=5, skip_first_us=None, thresholds=(0.25,)))
    assert keep_all[0.25]["num_labels"] == 49
    sliding, _ = evaluate(labelled, model, EvalSettings(seq_len=5, seq_stride=1, thresholds=(0.25,)))
    assert sliding[0.25]["num_sequences"] == 29 - 5 + 1  # 29 labelled windows after 0.5 s


def test_scores_carry_states_and_match_the_runner_on_the_same_windows(labelled, tmp_path):
    pytest.importorskip("torch", reason="exporting the mini RVT needs torch")
    from davis_rig.events.crop import crop_events
    from davis_rig.models.rvt import RVTConfig, RVTDetector, export_step_onnx
    from davis_rig.session import SessionReader

    import torch

    torch.manual_seed(0)
    model = export_step_onnx(RVTDetector(RVTConfig.mini()), tmp_path / "mini.onnx")
    runner = RVTOnnxRunner(model)
    settings = EvalSettings(thresholds=(0.25, 0.001, 0.1, 0.01), chunk_windows=7)
    scores = score_session(labelled, runner, settings)
    with SessionReader(labelled) as reader:
        events = crop_events(reader.events())
    for th in (0.001, 0.25):  # per-threshold post-processing (incl. reused outputs) == the runner's own
        expected = runner.score_stream(events["x"], events["y"], events["t"], events["p"], scores.window_end_us, th)
        assert len(expected) == len(scores.detections[th])
        for got, want in zip(scores.detections[th], expected):
            assert (got is None and want is None) or np.array_equal(got, want)
    metrics = compute_metrics(scores, settings)
    for m in metrics.values():
        assert 0.0 <= m["AP"] <= 1.0 and m["seq_asr_strict"] >= m["seq_asr"]
    assert [metrics[t]["seq_asr"] for t in (0.001, 0.01, 0.1, 0.25)] == sorted(m["seq_asr"] for m in metrics.values())


def test_pipelined_parts_give_the_whole_steps_detections_bit_for_bit(labelled, tmp_path):
    pytest.importorskip("torch", reason="exporting the mini RVT needs torch")
    from davis_rig.models.rvt import RVTConfig, RVTDetector, export_step_onnx

    import torch

    torch.manual_seed(1)
    runner = RVTOnnxRunner(export_step_onnx(RVTDetector(RVTConfig.mini()), tmp_path / "mini.onnx"))
    splits = []
    split = runner.split

    def spy(*threads):
        splits.append(threads)
        return split(*threads)

    runner.split = spy
    settings = EvalSettings(thresholds=(0.001, 0.25), chunk_windows=3)
    whole = score_session(labelled, runner, dataclasses.replace(settings, pipeline=False))
    assert splits == []
    piped = score_session(labelled, runner, settings)
    assert splits == [(1, min(2, os.cpu_count()), 1)]  # the recurrent part on 2 onnxruntime threads by default
    assert piped.num_events == whole.num_events and set(piped.timings_s) == set(whole.timings_s)
    for th in settings.thresholds:
        assert len(piped.detections[th]) == len(whole.detections[th]) == len(whole.window_end_us)
        for got, want in zip(piped.detections[th], whole.detections[th]):
            assert (got is None and want is None) or np.array_equal(got, want)
    assert sum(d is not None for d in piped.detections[0.001]) > 0  # random weights: boxes to compare


class _FailingSplit:
    """Parts of a stand-in step; ``recur`` fails at its ``fail_at``-th call."""

    def __init__(self, fail_at: int):
        self.calls, self.fail_at = 0, fail_at

    def pre(self, x):
        return x

    def recur(self, x1, states):
        self.calls += 1
        if self.calls == self.fail_at:
            raise RuntimeError("recur failed")
        return states

    def head(self, states):
        return np.zeros((1, 1, 6), np.float32)


class _SplitRunner:
    def __init__(self, split):
        self._split = split

    def prepare_histogram(self, hist):
        return hist

    def split(self, *threads):
        return self._split

    def initial_states(self, batch):
        return []


def test_a_failing_part_stops_the_pipeline_and_its_threads(labelled):
    import threading

    before = threading.active_count()
    failing = _FailingSplit(fail_at=5)
    with pytest.raises(RuntimeError, match="recur failed"):
        score_session(labelled, _SplitRunner(failing), EvalSettings(chunk_windows=2))
    assert failing.calls == 5
    assert threading.active_count() == before  # reader, pre, recur and post-processing threads all joined
    scores = score_session(labelled, _SplitRunner(_FailingSplit(fail_at=0)), EvalSettings(chunk_windows=2))
    assert len(scores.detections[0.25]) == len(scores.window_end_us)


def test_labels_provenance_decodes_davis_label_settings_and_keeps_foreign_text():
    stored = {"labeler": "davis_rig.labelers.yolo", "settings": '{"layout": "yolov8"}', "crop_origin_x": 21}
    assert labels_provenance(stored) == {"labeler": "davis_rig.labelers.yolo", "settings": {"layout": "yolov8"},
                                         "crop_origin_x": 21}
    assert stored["settings"] == '{"layout": "yolov8"}'  # the input is not modified
    assert labels_provenance({"labeler": "hand", "settings": "drawn in CVAT"})["settings"] == "drawn in CVAT"
    assert labels_provenance({}) == {}


def test_scoring_crop_origin_reads_both_stored_spellings():
    from davis_rig.errors import ShapeError

    assert scoring_crop_origin("s.h5", None, {}) == (21, 10)  # nothing stored: centred
    assert scoring_crop_origin("s.h5", (5, 6), {}) == (5, 6)
    for attrs in ({"crop_origin_x": 0, "crop_origin_y": 3}, {"crop_origin_xy": "[0, 3]"}, {"crop_origin_xy": [0, 3]}):
        assert scoring_crop_origin("s.h5", None, attrs) == (0, 3)  # davis-label's and the synthetic recordings'
        assert scoring_crop_origin("s.h5", (0, 3), attrs) == (0, 3)
        with pytest.raises(SessionError, match=r"s.h5: the labels were made for crop origin \(0, 3\), not \(21, 10\)"):
            scoring_crop_origin("s.h5", (21, 10), attrs)
    with pytest.raises(ShapeError, match=r"s.h5: crop origin \(43, 0\): the 304x240 crop at \(43, 0\) leaves"):
        scoring_crop_origin("s.h5", (43, 0), {})  # the caller's origin
    with pytest.raises(SessionError, match=r"s.h5: the labels' stored crop origin \(43, 0\): the 304x240 crop"):
        scoring_crop_origin("s.h5", None, {"crop_origin_xy": [43, 0]})  # the file's
    with pytest.raises(SessionError, match="unreadable crop origin"):
        scoring_crop_origin("s.h5", None, {"crop_origin_xy": "[1]"})


def test_time_tolerance_matches_a_detection_of_a_neighbouring_label_time_only_when_set():
    # labels of one standing person at 40 ms (window 0) and 80 ms (window 1); RVT finds it in window 1 only
    labels = np.zeros(2, BBOX_DTYPE)
    labels["t"] = [40_000, 80_000]
    labels["x"], labels["y"], labels["w"], labels["h"] = 100, 50, 60, 120
    labels["class_id"] = PEDESTRIAN_CLASS_ID
    found = np.array([[100, 50, 160, 170, 0.9, 0.9, PEDESTRIAN_CLASS_ID]], np.float32)
    scores = SessionScores(path="synthetic.h5", t0_us=0, window_end_us=np.array([50_000, 100_000, 150_000]),
                           detections={0.25: [None, found, None]}, labels=labels, crop_origin_xy=(21, 10),
                           num_events=0, timings_s={})

    def metrics(time_tol_us):
        return compute_metrics(scores, EvalSettings(thresholds=(0.25,), seq_len=1, skip_first_us=None,
                                                    time_tol_us=time_tol_us))[0.25]

    for exact in (metrics(0), metrics(39_999)):  # the 80 ms detection is 40 ms away from the 40 ms label
        assert exact["num_images"] == 2 and exact["num_detections"] == 1
        assert exact["AP"] == pytest.approx(51 / 101)  # recall 1/2 at precision 1 (101 recall points)
    for tolerant in (metrics(40_000), metrics(50_000)):  # ±tol inclusive: the 40 ms label image gets it too
        assert tolerant["num_detections"] == 2 and tolerant["AP"] == pytest.approx(1.0)
    assert metrics(0)["seq_asr"] == metrics(50_000)["seq_asr"] == 0.5  # SeqASR does not use the tolerance
    assert settings_dict(EvalSettings(time_tol_us=50_000))["time_tol_us"] == 50_000  # stored in report.json
    with pytest.raises(ValueError, match="time_tol_us"):
        EvalSettings(time_tol_us=-1)


def test_bad_inputs_raise_before_scoring_and_leave_files_untouched(labelled, tmp_path):
    unlabelled = scene_session(tmp_path, "unlabelled.h5")
    before = sha256(unlabelled)
    with pytest.raises(SessionError, match="no /labels"):
        evaluate_sessions([labelled, unlabelled], person_rvt(tmp_path), SETTINGS)
    assert sha256(unlabelled) == before
    with pytest.raises(FormatError, match="no such RVT ONNX"):
        evaluate_sessions([labelled], tmp_path / "missing.onnx", SETTINGS)
    with pytest.raises(ModelFormatError, match="not an RVT step graph"):
        evaluate_sessions([labelled], person_yolo(tmp_path), SETTINGS)
    with pytest.raises(SessionError, match="no such session"):
        evaluate_sessions([tmp_path / "nothing.h5"], person_rvt(tmp_path), SETTINGS)
    with pytest.raises(ValueError):
        EvalSettings(thresholds=(1.5,))
    with pytest.raises(SessionError, match=r"crop origin \(21, 10\), not \(0, 0\)"):
        evaluate_sessions([labelled], person_rvt(tmp_path), EvalSettings(crop_origin_xy=(0, 0)))


def test_crop_origin_conflict_and_bounds_are_checked_for_every_session_before_any_scoring(labelled, tmp_path,
                                                                                           monkeypatch):
    import h5py

    from davis_rig.errors import ShapeError
    from davis_rig.evaluation import physical

    scored = []
    monkeypatch.setattr(physical, "score_session", lambda path, *a, **k: scored.append(path))
    other, outside = tmp_path / "other_origin.h5", tmp_path / "outside.h5"
    for path, origin in ((other, (0, 0)), (outside, (100, 10))):
        path.write_bytes(labelled.read_bytes())
        with h5py.File(path, "r+") as f:
            f["labels"].attrs["crop_origin_x"], f["labels"].attrs["crop_origin_y"] = origin
    model = person_rvt(tmp_path)
    with pytest.raises(SessionError, match=r"other_origin.h5: the labels were made for crop origin \(0, 0\), not "
                                           r"\(21, 10\)"):
        evaluate_sessions([labelled, other], model, EvalSettings(seq_len=5, crop_origin_xy=(21, 10)))
    with pytest.raises(SessionError, match=r"outside.h5: the labels' stored crop origin \(100, 10\): .* leaves the "
                                           r"346x260 sensor"):
        evaluate_sessions([labelled, outside], model, SETTINGS)
    unset = tmp_path / "no_stored_origin.h5"
    unset.write_bytes(labelled.read_bytes())
    with h5py.File(unset, "r+") as f:
        del f["labels"].attrs["crop_origin_x"], f["labels"].attrs["crop_origin_y"]
    with pytest.raises(ShapeError, match=r"no_stored_origin.h5: crop origin \(50, 0\)"):
        evaluate_sessions([unset, unset], model, EvalSettings(seq_len=5, crop_origin_xy=(50, 0)))
    assert scored == []


def test_empty_labels_are_refused(tmp_path):
    import h5py

    session = scene_session(tmp_path, "empty_labels.h5")
    from davis_rig.labelers.session_labels import write_labels

    write_labels(session, np.zeros(0, BBOX_DTYPE), {"labeler": "test"})
    with pytest.raises(SessionError, match="empty"):
        evaluate_sessions([session], person_rvt(tmp_path), SETTINGS)
    with h5py.File(session, "r") as f:
        assert len(f["labels/boxes"]) == 0


def test_report_json_round_trip_has_every_number(labelled, tmp_path):
    from davis_rig.evaluation.report import report_dict

    results, _ = evaluate_sessions([labelled], person_rvt(tmp_path), SETTINGS)
    data = json.loads(json.dumps(report_dict(results, SETTINGS)))
    recorded = data["recordings"][0]
    assert data["settings"]["seq_len"] == 5 and data["settings"]["thresholds"] == [0.001, 0.01, 0.1, 0.25]
    assert data["settings"]["time_tol_us"] == 0
    assert recorded["metrics"]["0.25"]["AP"] == pytest.approx(1.0)
    assert recorded["metrics"]["0.25"]["AP_S"] is None  # NaN -> null
    assert set(recorded["info"]["timings_s"]) == {"read", "histogram", "inference", "postprocess", "wall", "metrics"}
    provenance = recorded["info"]["labels_provenance"]  # davis-label's /labels attributes, settings decoded
    assert provenance["labeler"] == "davis_rig.labelers.yolo" and provenance["source"] == "person_yolo.onnx"
    assert provenance["settings"]["model_name"] == "person_yolo.onnx" and provenance["settings"]["layout"] == "yolov8"
    assert provenance["settings"]["conf_threshold"] == 0.25 and provenance["settings"]["crop_origin_xy"] == [21, 10]
    assert {"labeler_version", "created_utc", "crop_origin_x", "crop_origin_y"} <= set(provenance)
    assert not any(isinstance(v, float) and math.isnan(v) for v in recorded["metrics"]["0.25"].values())


class _HistogramRecorder:
    """Stand-in for the RVT runner: keeps every window's histogram, detects nothing (one anchor, score 0); runs
    whole steps (no split)."""

    def __init__(self):
        self.hists = []

    def prepare_histogram(self, hist):
        return hist

    def split(self, *threads):
        raise ModelFormatError("a stand-in, not a graph")

    def step(self, hist, states):
        self.hists.append(hist[0].copy())
        return np.zeros((1, 1, 6), np.float32), states


def _session_with_times(path, t_us):
    """A session whose /events/t holds ``t_us`` as given, in file order (out-of-order times: a file from another
    tool, davis_rig's writer drops events that go back in time), one event per pixel, one pedestrian label."""
    import h5py

    from davis_rig.session import SessionWriter, schema
    from davis_rig.types import make_events

    n = len(t_us)
    with SessionWriter(path, device_info={"serial": "FOREIGN"}) as writer:
        writer.append_events(make_events(np.sort(t_us), 100 + np.arange(n), np.full(n, 100), np.ones(n, int)))
    boxes = np.zeros(1, BBOX_DTYPE)
    boxes["t"], boxes["w"], boxes["h"], boxes["class_id"] = 25_000, 40, 80, PEDESTRIAN_CLASS_ID
    with h5py.File(path, "r+") as f:
        f["events/t"][:] = np.asarray(t_us) - f["events"].attrs[schema.T_OFFSET_ATTR]
        f.create_group(schema.LABELS_GROUP).create_dataset(schema.LABEL_BOXES, data=boxes)
    return path


@pytest.mark.parametrize("chunk_windows", [1, 2, 3])
def test_out_of_order_times_are_corrected_across_chunks_like_rvt_over_the_whole_recording(tmp_path, chunk_windows):
    from davis_rig.events.crop import crop_events
    from davis_rig.events.histogram import stacked_histograms
    from davis_rig.session import SessionReader

    # 58 ms is followed by 20 and 50 ms in the file: RVT's running maximum lifts both to 58 ms, into window 2
    # (50..100 ms), which holds 4 events; with one window per chunk all three are read with chunk 1 (the read
    # ends at 50 ms by file time) and must be carried into chunk 2 with their corrected times
    t_us = np.array([500, 10_000, 58_000, 20_000, 50_000, 70_000, 120_000])
    session = _session_with_times(tmp_path / "foreign.h5", t_us)
    runner = _HistogramRecorder()
    scores = score_session(session, runner, EvalSettings(chunk_windows=chunk_windows, thresholds=(0.1,)))
    np.testing.assert_array_equal(scores.window_end_us, [50_000, 100_000, 150_000])
    with SessionReader(session) as reader:
        official = stacked_histograms(crop_events(reader.events()), scores.window_end_us, correct_time=True)
    np.testing.assert_array_equal(np.stack(runner.hists), official)
    assert [int(h.sum()) for h in runner.hists] == [2, 4, 1]
    assert scores.num_events == len(t_us)  # every event read once


def test_events_on_chunk_boundaries_are_in_both_windows_and_counted_once(tmp_path):
    from davis_rig.session import SessionReader

    t_us = np.array([500, 50_000, 50_000, 75_000, 100_000, 120_000])  # ordered, two events on a boundary
    session = _session_with_times(tmp_path / "ordered.h5", t_us)
    runner = _HistogramRecorder()
    scores = score_session(session, runner, EvalSettings(chunk_windows=1, thresholds=(0.1,)))
    assert [int(h.sum()) for h in runner.hists] == [3, 4, 2]
    with SessionReader(session) as reader:
        assert scores.num_events == reader.num_events == 6


class _NaNRunner(_HistogramRecorder):
    """A broken model: NaN scores in every other window."""

    def step(self, hist, states):
        decoded, states = super().step(hist, states)
        return (np.full_like(decoded, np.nan) if len(self.hists) % 2 else decoded), states


def test_a_model_that_outputs_nan_is_warned_about_not_scored_in_silence(tmp_path):
    import warnings

    session = _session_with_times(tmp_path / "s.h5", np.array([500, 60_000, 120_000]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the control: a model with finite outputs raises no warning
        score_session(session, _HistogramRecorder(), EvalSettings(thresholds=(0.1,)))
    with pytest.warns(UserWarning, match=r"s\.h5: the detector's output holds NaN or inf in 2 of 3 windows"):
        scores = score_session(session, _NaNRunner(), EvalSettings(thresholds=(0.1,)))
    assert [d is None or len(d) == 0 for d in scores.detections[0.1]] == [True, True, True]


class _AllNaNRunner(_HistogramRecorder):
    """A broken model: NaN scores in every window."""

    def step(self, hist, states):
        decoded, states = super().step(hist, states)
        return np.full_like(decoded, np.nan), states


def test_a_model_that_outputs_nan_in_every_window_is_refused(tmp_path):
    session = _session_with_times(tmp_path / "s.h5", np.array([500, 60_000, 120_000]))
    with pytest.raises(ModelFormatError, match="NaN or inf in every one of the 3 windows"):
        score_session(session, _AllNaNRunner(), EvalSettings(thresholds=(0.1,)))


def _set_labels(path, times_us):
    import h5py

    with h5py.File(path, "r+") as f:
        boxes = f["labels/boxes"][:1].repeat(len(times_us))
        boxes["t"] = times_us
        del f["labels/boxes"]
        f["labels"].create_dataset("boxes", data=boxes)


def test_labels_far_outside_the_events_are_left_out_not_scored_over_empty_windows(tmp_path):
    session = _session_with_times(tmp_path / "s.h5", np.array([500, 60_000, 120_000]))
    _set_labels(session, [25_000, 3_600_000_000, np.iinfo(np.uint64).max])  # an hour late; the largest time
    with pytest.warns(UserWarning, match=r"2 of 3 labels lie outside the events' span"):
        scores = score_session(session, _HistogramRecorder(), EvalSettings(thresholds=(0.1,)))
    np.testing.assert_array_equal(scores.window_end_us, [50_000, 100_000, 150_000])  # the events' grid
    assert len(scores.labels) == 1
    _set_labels(session, [3_600_000_000])
    with pytest.raises(SessionError, match="none of the 1 labels .* lies inside the events' span"):
        score_session(session, _HistogramRecorder(), EvalSettings(thresholds=(0.1,)))


def test_a_stored_crop_origin_off_the_sensor_is_a_damaged_file(tmp_path):
    import h5py

    session = _session_with_times(tmp_path / "s.h5", np.array([500, 60_000, 120_000]))
    with h5py.File(session, "r+") as f:
        f["labels"].attrs["crop_origin_x"], f["labels"].attrs["crop_origin_y"] = 500, 10
    with pytest.raises(SessionError, match=r"stored crop origin \(500, 10\)"):
        score_session(session, _HistogramRecorder(), EvalSettings(thresholds=(0.1,)))


def test_events_outside_the_sensor_are_counted_and_a_damaged_layout_is_ignored(tmp_path):
    import h5py

    session = _session_with_times(tmp_path / "s.h5", np.array([500, 60_000, 61_000, 120_000]))
    with h5py.File(session, "r+") as f:
        f["events/x"][1] = 400  # off the 346-pixel-wide sensor
        f.attrs["device_info"] = json.dumps({"serial": "FOREIGN", "layout": "not a mapping"})
    with pytest.warns(UserWarning, match="1 events lie outside the 346x260 sensor"):
        scores = score_session(session, _HistogramRecorder(), EvalSettings(thresholds=(0.1,)))
    assert scores.num_events == 4
