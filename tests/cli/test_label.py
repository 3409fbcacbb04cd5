"""``davis-label``: argument mapping, messages and exit codes; the session is untouched on every error."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from davis_rig.cli import label as cli
from davis_rig.session import SessionReader

from eval_data import person_yolo, scene_session, sha256


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
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["s.h5"])
    assert exit_info.value.code == 2 and "--yolo" in capsys.readouterr().err


def test_console_script_help_is_fast_and_lists_examples():
    result = subprocess.run([sys.executable, "-m", "davis_rig.cli.label", "--help"], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0 and "human-fall-detection" in result.stdout
