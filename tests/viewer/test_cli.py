"""``davis-view``: exports, serving until Ctrl-C, and one-line errors with the vocabulary's exit codes."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import urllib.request
from pathlib import Path

import cv2
import pytest

from davis_rig import __version__
from davis_rig.cli import view as cli
from davis_rig.evaluation.physical import EvalSettings, evaluate_sessions
from davis_rig.evaluation.report import write_report

from tests.helpers.eval_data import person_rvt

REPO = Path(__file__).resolve().parents[2]


def test_version_and_help(capsys):
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"davis-view (davis_rig {__version__})"
    assert cli.main(["--help"]) == 0
    assert "exit codes: 0 ok" in capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [
    (["--host", "0.0.0.0"], "argument --host: 0.0.0.0 is not this machine's loopback; add --allow-remote"),
    (["--session", "1"], "argument --session: only with --export"),
    (["--start", "2"], "argument --start: only with --export"),
    (["--overwrite"], "argument --overwrite: only with --export"),
    (["--export", "x.avi"], "argument --export: expected a .mp4 or .gif file"),
    (["--export", "x.gif", "--session", "3"], "argument --session: 3 is not an index of the 1 SESSION_H5 given"),
    (["--export", "x.gif", "--start", "2", "--end", "1"], "argument --end: 1 s is not after --start 2 s"),
    (["--no-detector", "--detector", "m.onnx"], "argument --no-detector: not allowed with --detector"),
    (["--no-detector", "--threshold", "0.1"], "argument --no-detector: not allowed with --detector"),
    (["--detections", "run", "--detector", "m.onnx"], "argument --detections: not allowed with --detector"),
    (["--detections", "run", "--threshold", "0.1"], "argument --threshold: with --detections the report's"),
    (["--int8", "--detector", "m.onnx"], "argument --int8: not allowed with argument --detector"),
    (["--no-detector", "--int8"], "argument --no-detector: not allowed with --detector, --int8"),
    (["--detections", "run", "--int8"], "argument --detections: not allowed with --detector or --int8"),
    (["--crop-origin", "100", "100"], "argument --crop-origin: the 304x240 crop at (100, 100) leaves"),
    (["--port", "70000"], "argument --port: expected an integer in [0, 65535]"),
    (["--layers", "events,bogus", "--export", "x.gif"], "argument --layers: unknown layer(s) bogus"),
    (["--threshold", "1.5"], "argument --threshold: expected a number in [0, 1]"),
    (["--threads", "0"], "argument --threads: expected an integer >= 1"),
])
def test_bad_arguments_exit_2_with_one_line(scene, capsys, argv, message):
    assert cli.main([str(scene), *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("davis-view: error: ") and message in err, err


def test_missing_files_exit_4(scene, tmp_path, capsys):
    assert cli.main([str(tmp_path / "nope.h5"), "--no-detector", "--port", "0"]) == 4
    assert "nope.h5: no such session file" in capsys.readouterr().err
    assert cli.main([str(scene), "--detector", str(tmp_path / "rvt.onnx"), "--port", "0"]) == 4
    assert "rvt.onnx: no such RVT step ONNX" in capsys.readouterr().err
    weights = tmp_path / "rvt.safetensors"
    weights.write_bytes(b"x")
    assert cli.main([str(scene), "--detector", str(weights), "--port", "0"]) == 4
    assert "needs an RVT step ONNX" in capsys.readouterr().err
    assert cli.main([str(scene), "--detections", str(tmp_path), "--port", "0"]) == 4
    assert "*.detections.npz" in capsys.readouterr().err


def test_export_mp4_and_gif(scene, tmp_path, capsys):
    pytest.importorskip("PIL", reason="the GIF export needs the report extra (Pillow)")
    from PIL import Image

    mp4, gif = tmp_path / "view.mp4", tmp_path / "view.gif"
    assert cli.main([str(scene), "--no-detector", "--export", str(mp4), "--start", "0.1", "--end", "0.5"]) == 0
    assert f"{mp4}: windows 2..9 of scene.h5 at 20 fps" in capsys.readouterr().out
    video = cv2.VideoCapture(str(mp4))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == 8
    ok, frame = video.read()
    assert ok and frame.shape == (260, 696, 3)
    assert cli.main([str(scene), "--no-detector", "--export", str(gif), "--fps", "10", "--layers", "events,labels",
                     "-q"]) == 0
    assert capsys.readouterr().out == ""
    with Image.open(gif) as image:
        assert image.n_frames == 25 and image.size == (696, 260) and image.info["duration"] == 100
    assert sorted(p.name for p in tmp_path.iterdir()) == ["view.gif", "view.mp4"]  # no temporary file left


def test_an_existing_video_is_kept_unless_overwrite(scene, tmp_path, capsys):
    mp4 = tmp_path / "view.mp4"
    mp4.write_bytes(b"the user's video")
    assert cli.main([str(scene), "--no-detector", "--export", str(mp4), "--end", "0.1", "-q"]) == 4
    assert "view.mp4: file exists (pass overwrite=True / --overwrite to replace it)" in capsys.readouterr().err
    assert mp4.read_bytes() == b"the user's video"
    assert cli.main([str(scene), "--no-detector", "--export", str(mp4), "--end", "0.1", "-q", "--overwrite"]) == 0
    assert cv2.VideoCapture(str(mp4)).isOpened()


def test_an_export_is_created_with_the_usual_permissions_and_a_missing_folder_is_named(scene, tmp_path, capsys):
    mp4 = tmp_path / "view.mp4"
    umask = os.umask(0o022)
    try:
        assert cli.main([str(scene), "--no-detector", "--export", str(mp4), "--end", "0.1", "-q"]) == 0
    finally:
        os.umask(umask)
    assert mp4.stat().st_mode & 0o777 == 0o644  # as any file the user creates, not a private temporary file's 0600
    missing = tmp_path / "nowhere" / "view.mp4"
    assert cli.main([str(scene), "--no-detector", "--export", str(missing), "-q"]) == 4
    assert capsys.readouterr().err == (f"davis-view: error: {missing}: the folder {missing.parent} does not "
                                       "exist\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["view.mp4"]


def test_export_with_the_boxes_of_a_davis_eval_run(scene, tmp_path):
    settings = EvalSettings(thresholds=(0.25,))
    results, scores = evaluate_sessions([scene], person_rvt(tmp_path), settings)
    write_report(results, scores, settings, tmp_path / "run", plot=False, gif=False)
    out = tmp_path / "boxes.mp4"
    assert cli.main([str(scene), "--detections", str(tmp_path / "run"), "--export", str(out), "--end", "0.2"]) == 0
    ok, frame = cv2.VideoCapture(str(out)).read()
    assert ok and frame.shape == (260, 696, 3)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_serves_until_ctrl_c_and_a_busy_port_is_a_usage_error(scene):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    port = _free_port()
    process = subprocess.Popen([sys.executable, "-c", "from davis_rig.cli.view import main; raise SystemExit(main())",
                                str(scene), "--no-detector", "--port", str(port)], env=env, cwd=REPO,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = process.stderr.readline()
        assert line.startswith(f"davis-view: 1 recording(s) at http://127.0.0.1:{port}/"), line
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/info", timeout=60) as response:
            assert json.load(response)["sessions"][0]["name"] == "scene.h5"
        busy = subprocess.run([sys.executable, "-c", "from davis_rig.cli.view import main; raise SystemExit(main())",
                               str(scene), "--no-detector", "--port", str(port)], env=env, cwd=REPO,
                              capture_output=True, text=True, timeout=120)
        assert busy.returncode == 2
        assert busy.stderr.strip().startswith(f"davis-view: error: argument --port: cannot listen on 127.0.0.1:{port}")
    finally:
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=60)
    assert process.returncode == 0 and "stopped" in err


def test_a_file_that_is_no_session_exits_4_and_nan_exits_2(tmp_path, scene, capsys):
    text = tmp_path / "text.h5"
    text.write_text("not hdf5")
    assert cli.main([str(text), "--no-detector", "--port", "0"]) == 4
    assert "text.h5: cannot open as HDF5" in capsys.readouterr().err
    assert cli.main([str(scene), "--export", str(tmp_path / "x.gif"), "--fps", "nan"]) == 2
    assert "argument --fps: expected a finite number, got 'nan'" in capsys.readouterr().err


def test_ctrl_c_during_an_export_leaves_no_file(scene, tmp_path, monkeypatch, capsys):
    from davis_rig.viewer import export

    def interrupted(frames, path, fps):
        next(frames)
        path.write_bytes(b"half a video")
        raise KeyboardInterrupt

    monkeypatch.setattr(export, "_write_mp4", interrupted)
    assert cli.main([str(scene), "--no-detector", "--export", str(tmp_path / "v.mp4")]) == 130
    assert capsys.readouterr().err.strip() == "davis-view: interrupted"
    assert list(tmp_path.iterdir()) == []


def test_int8_picks_the_bundled_int8_graph_for_the_session_and_the_live_view():
    import argparse

    from davis_rig.cli.view import _detector_path

    assert _detector_path(argparse.Namespace(detector=None, int8=True)).name == "rvt_default_int8.onnx"
    assert _detector_path(argparse.Namespace(detector=None, int8=False)).name == "rvt_default.onnx"
