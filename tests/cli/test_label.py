"""``davis-label``: argument mapping, messages and exit codes; the session is untouched on every error."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from davis_rig.cli import label as cli
from davis_rig.session import SessionReader

from tests.helpers.eval_data import person_yolo, scene_session, sha256


def test_label_writes_labels_and_reports(tmp_path, capsys):
    session = scene_session(tmp_path)
    code = cli.main([str(session), "--yolo", str(person_yolo(tmp_path)), "--quiet", "--crop-origin", "20", "10"])
    out = capsys.readouterr().out
    assert code == 0 and "49 boxes on 49 of 49 frames" in out and "layout yolov8" in out and "(20, 10)" in out
    with SessionReader(session) as reader:
        assert len(reader.labels()) == 49 and reader.labels_attrs()["crop_origin_x"] == 20


def test_arguments_map_onto_label_session(tmp_path, monkeypatch):
    calls = []

    def fake(path, yolo, **kwargs):
        calls.append((path, yolo, kwargs))
        from davis_rig.labelers.session_labels import LabelSummary

        return LabelSummary(Path(path), 1, 1, 1, {"model_name": "m", "layout": "yolov5", "classes": ["a", "b"],
                                                  "crop_origin_xy": [21, 10]})

    monkeypatch.setattr("davis_rig.labelers.session_labels.label_session", fake)
    assert cli.main(["s.h5", "--yolo", "m.onnx", "--classes", "Normal, Fall", "--conf", "0.4", "--iou", "0.6",
                     "--layout", "yolov5", "--overwrite", "--threads", "2", "--quiet"]) == 0
    path, yolo, kwargs = calls[0]
    assert (path, yolo) == ("s.h5", "m.onnx")
    assert kwargs == dict(classes=["Normal", "Fall"], conf_threshold=0.4, iou_threshold=0.6, layout="yolov5",
                          crop_origin_xy=None, overwrite=True, progress=None, intra_op_threads=2)


@pytest.mark.parametrize("case, message", [
    ("missing", "no such session file"),
    ("empty", "the file is empty (0 bytes), not a recorded session"),
    ("truncated", "cannot open as HDF5"),
    ("not_session", "not a session file"),
    ("missing_frames_group", "missing group /frames"),
    ("wrong_onnx", "cannot load the model"),
    ("labelled", "already has /labels"),
])
def test_bad_input_gives_a_message_exit_4_and_leaves_the_file_untouched(tmp_path, capsys, case, message):
    import h5py

    session = scene_session(tmp_path)
    model = person_yolo(tmp_path)
    if case == "missing":
        session = tmp_path / "nothing.h5"
    elif case == "empty":
        session.write_bytes(b"")
    elif case == "truncated":
        session.write_bytes(session.read_bytes()[:50_000])
    elif case == "not_session":
        with h5py.File(session, "w") as f:
            f.create_dataset("x", data=[1, 2])
    elif case == "missing_frames_group":
        with h5py.File(session, "r+") as f:
            del f["frames"]
    elif case == "wrong_onnx":
        model = tmp_path / "wrong.onnx"
        model.write_bytes(b"garbage")
    elif case == "labelled":
        assert cli.main([str(session), "--yolo", str(model), "--quiet"]) == 0
        capsys.readouterr()
    before = sha256(session) if session.exists() else None
    code = cli.main([str(session), "--yolo", str(model), "--quiet"])
    err = capsys.readouterr().err
    assert code == 4 and err.startswith("davis-label: error:") and message in err, err
    assert (sha256(session) if session.exists() else None) == before


def test_missing_required_argument_is_a_usage_error(capsys):
    assert cli.main(["s.h5"]) == 2 and "--yolo" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--conf", "1.5"], "argument --conf: expected a number in [0, 1], got '1.5'"),
    (["--conf", "nan"], "argument --conf: expected a finite number, got 'nan'"),
    (["--conf", "-1"], "argument --conf: expected a number in [0, 1], got '-1'"),
    (["--threshold", "1.5"], "argument --threshold: expected a number in [0, 1], got '1.5'"),
    (["--iou", "2"], "argument --iou: expected a number in [0, 1], got '2'"),
    (["--iou", "nan"], "argument --iou: expected a finite number, got 'nan'"),
    (["--threads", "-2"], "argument --threads: expected an integer >= 1, got '-2'"),
    (["--threads", "0"], "argument --threads: expected an integer >= 1, got '0'"),
    (["--crop-origin", "500", "500"], "argument --crop-origin: the 304x240 crop at (500, 500) leaves the 346x260"),
    (["--crop-origin", "-1", "0"], "argument --crop-origin: expected an integer >= 0, got '-1'"),
    (["--classes", " , "], "argument --classes: expected comma-separated class names"),
])
def test_bad_values_exit_2_naming_the_option_and_write_nothing(tmp_path, capsys, argv, message):
    session = scene_session(tmp_path)
    before = sha256(session)
    assert cli.main([str(session), "--yolo", str(person_yolo(tmp_path)), "--quiet", *argv]) == 2
    err = capsys.readouterr().err
    assert f"davis-label: error: {message}" in err and "Traceback" not in err, err
    assert sha256(session) == before


@pytest.mark.parametrize("kwargs, field", [
    ({"conf_threshold": float("nan")}, "conf_threshold"), ({"iou_threshold": 2.0}, "iou_threshold"),
    ({"intra_op_threads": 0}, "intra_op_threads"), ({"crop_origin_xy": (43, 0)}, "crop_origin_xy"),
])
def test_label_session_refuses_bad_settings_with_the_field_named(tmp_path, kwargs, field):
    from davis_rig.errors import ConfigError
    from davis_rig.labelers.session_labels import label_session

    session = scene_session(tmp_path)
    before = sha256(session)
    with pytest.raises(ConfigError) as info:
        label_session(session, person_yolo(tmp_path), **kwargs)
    assert info.value.field == field and sha256(session) == before


def test_console_script_help_is_fast_and_lists_examples():
    result = subprocess.run([sys.executable, "-m", "davis_rig.cli.label", "--help"], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0 and "human-fall-detection" in result.stdout
