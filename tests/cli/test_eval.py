"""``davis-eval``: one table column per recording, report files, messages and exit codes on bad input."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from davis_rig.cli import eval as cli
from davis_rig.labelers.session_labels import label_session

from tests.helpers.eval_data import person_rvt, person_yolo, scene_session, sha256


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    directory = tmp_path_factory.mktemp("cli_eval")
    a, b = scene_session(directory, "a.h5"), scene_session(directory, "b.h5")
    label_session(a, person_yolo(directory))
    label_session(b, person_yolo(directory))
    return directory, a, b


def test_two_recordings_one_table_and_a_full_report(sessions, tmp_path, capsys):
    pytest.importorskip("matplotlib", reason="the plot needs the report extra")
    pytest.importorskip("PIL", reason="the GIF needs the report extra")
    directory, a, b = sessions
    good, blind = person_rvt(tmp_path), person_rvt(tmp_path, score=0.0, name="blind.onnx")
    before = sha256(a), sha256(b)
    code = cli.main([str(a), str(b), "--model", str(good), "--names", "Case 1,Ours", "--seq-len", "5",
                     "--report", str(tmp_path / "rep"), "--gif-seconds", "0.5", "--quiet"])
    out = capsys.readouterr().out
    assert code == 0
    assert "| Metric | Confidence threshold | Case 1 | Ours |" in out
    assert "| AP ↓ | 0.001 | 100.0% | 100.0% |" in out and "| SeqASR ↑ | 0.25 | 0.0% | 0.0% |" in out
    rep = tmp_path / "rep"
    for name in ("report.json", "table.md", "ap_seqasr.png", "Case_1.gif", "Ours.gif"):
        assert (rep / name).stat().st_size > 0, name
    data = json.loads((rep / "report.json").read_text())
    assert [r["name"] for r in data["recordings"]] == ["Case 1", "Ours"]
    assert data["settings"]["time_tol_us"] == 0
    for recording in data["recordings"]:  # who made the ground truth, per recording
        provenance = recording["info"]["labels_provenance"]
        assert provenance["labeler"] == "davis_rig.labelers.yolo" and provenance["source"] == "person_yolo.onnx"
        assert provenance["settings"]["layout"] == "yolov8" and provenance["settings"]["classes"] == ["person"]
    assert data["recordings"][1]["metrics"]["0.1"]["seq_asr"] == 0.0
    assert (rep / "table.md").read_text() in out
    from PIL import Image

    assert Image.open(rep / "Ours.gif").n_frames == 10
    assert (sha256(a), sha256(b)) == before  # evaluation never writes to the sessions

    # the GIF draws the detections of --gif-threshold (default the highest): a detector scoring 0.1 has none at 0.25
    weak = person_rvt(tmp_path, score=0.1, name="weak.onnx")

    def gif_pixels(threshold):
        extra = [] if threshold is None else ["--gif-threshold", str(threshold)]
        out_dir = tmp_path / f"gif_{threshold}"
        assert cli.main([str(a), "--model", str(weak), "--threshold", "0.001,0.25", "--report", str(out_dir),
                         "--no-plot", "--gif-seconds", "0.5", "--quiet", *extra]) == 0
        gif = Image.open(next(out_dir.glob("*.gif")))
        return np.asarray(gif.convert("RGB"))

    default, low = gif_pixels(None), gif_pixels(0.001)
    assert np.array_equal(default, gif_pixels(0.25)) and not np.array_equal(default, low)
    capsys.readouterr()

    assert cli.main([str(a), "--model", str(blind), "--threshold", "0.25", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "| AP ↓ | 0.25 | 0.0% |" in out and "| SeqASR ↑ | 0.25 | 100.0% |" in out and "0.001" not in out


def test_gif_threshold_must_be_scored(capsys):
    assert cli.main(["x.h5", "--model", "m.onnx", "--threshold", "0.1,0.25", "--gif-threshold", "0.5"]) == 2
    assert ("davis-eval: error: argument --gif-threshold: 0.5 is not one of the scored thresholds 0.1, 0.25"
            in capsys.readouterr().err)


def test_arguments_map_onto_evaluate_sessions(monkeypatch, capsys, tmp_path):
    calls = []
    model_file = tmp_path / "m.onnx"
    model_file.write_bytes(b"onnx")

    def fake(paths, model, settings, names=None, progress=None):
        calls.append((paths, model, settings, names, progress))
        from davis_rig.evaluation.physical import RecordingResult

        metrics = {t: {"AP": 0.5, "seq_asr": 0.25, "seq_asr_strict": 0.5} for t in settings.thresholds}
        return [RecordingResult("x", "x.h5", metrics, {})], [None]

    monkeypatch.setattr("davis_rig.evaluation.physical.evaluate_sessions", fake)
    assert cli.main(["--threshold", "0.1", "x.h5", "--detector", str(model_file), "--threshold", "0.2", "--seq-len",
                     "3", "--seq-stride", "1", "--skip-first-ms", "0", "--crop-origin", "0", "0", "--coco-backend",
                     "pycocotools", "--threads", "1", "--time-tol-ms", "50", "--quiet"]) == 0
    paths, model, settings, names, progress = calls[0]
    assert (paths, model, names, progress) == (["x.h5"], model_file, None, None)
    assert settings.thresholds == (0.1, 0.2) and settings.seq_len == 3 and settings.seq_stride == 1
    assert settings.skip_first_us == 0 and settings.crop_origin_xy == (0, 0) and settings.time_tol_us == 50_000
    assert settings.coco_backend == "pycocotools" and settings.intra_op_threads == 1 and settings.gif_windows == 0
    assert "| SeqASR ↑ | 0.2 | 25.0% |" in capsys.readouterr().out


@pytest.mark.parametrize("argv_tail, message", [
    (["--names", "a,b"], "argument --names: 2 names for 1 sessions"),
    (["--seq-len", "0"], "argument --seq-len: expected an integer >= 1, got '0'"),
    (["--threshold", "2"], "argument --threshold: expected a number in [0, 1], got '2'"),
    (["--time-tol-ms", "-1"], "argument --time-tol-ms: expected a number in [0, inf), got '-1'"),
    (["--skip-first-ms", "-1"], "argument --skip-first-ms: expected a number in [0, inf), got '-1'"),
    (["--crop-origin", "500", "500"], "argument --crop-origin: the 304x240 crop at (500, 500) leaves the"),
    (["--int8", "--detector", "m.onnx"], "argument --int8: not allowed with argument --detector"),
])
def test_bad_arguments_exit_2(argv_tail, message, capsys):
    assert cli.main(["x.h5", *argv_tail]) == 2
    assert message in capsys.readouterr().err


def test_zero_sequences_warn_with_seq_len_skip_first_and_the_longest_labelled_run(sessions, tmp_path, capsys):
    import re

    _, a, _ = sessions
    model = person_rvt(tmp_path)
    assert cli.main([str(a), "--model", str(model), "--threshold", "0.25", "--seq-len", "100000", "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "| SeqASR ↑ | 0.25 | n/a |" in captured.out
    found = re.search(r"davis-eval: warning: a: SeqASR n/a \(0 sequences\): the longest run of consecutive labelled "
                      r"50 ms windows left after --skip-first-ms 500 and the box size filter is (\d+) windows, "
                      r"shorter than --seq-len 100000; lower --seq-len \(<= (\d+)\) or --skip-first-ms", captured.err)
    assert found, captured.err
    longest = int(found.group(1))
    assert longest == int(found.group(2)) and longest >= 5  # --seq-len 5 gives sequences on this recording
    assert cli.main([str(a), "--model", str(model), "--threshold", "0.25", "--seq-len", str(longest),
                     "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "warning" not in captured.err and "| SeqASR ↑ | 0.25 | 0.0% |" in captured.out


def test_skip_first_ms_help_names_ap_and_seqasr_and_tolerance_help_recommends_zero():
    text = " ".join(cli.build_parser().format_help().split())
    assert "for AP and for the SeqASR sequences" in text
    assert "default 0, the right setting here" in text and "pools the detections of neighbouring windows" in text
    assert "RVT protocol: 50" not in text and "RVT's tolerance" not in text


def test_bad_inputs_exit_nonzero_with_a_message(sessions, tmp_path, capsys):
    import h5py

    directory, a, _ = sessions
    model = person_rvt(tmp_path)
    unlabelled = scene_session(tmp_path, "unlabelled.h5")
    no_events = tmp_path / "no_events.h5"
    no_events.write_bytes(unlabelled.read_bytes())
    with h5py.File(no_events, "r+") as f:
        for name in ("t", "x", "y", "p", "ms_to_idx"):
            f["events"][name].resize((0,))
    other_sensor = tmp_path / "other_sensor.h5"
    _other_sensor_session(other_sensor)
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(a.read_bytes()[:40_000])
    zero_bytes = tmp_path / "zero_bytes.h5"
    zero_bytes.write_bytes(b"")
    cases = [
        ([str(unlabelled), "--model", str(model)], 4, "no /labels"),
        ([str(no_events), "--model", str(model)], 4, "no events"),
        ([str(truncated), "--model", str(model)], 4, "cannot open as HDF5"),
        ([str(zero_bytes), "--model", str(model)], 4, "the file is empty (0 bytes)"),
        ([str(a), "--model", str(person_yolo(tmp_path))], 4, "not an RVT step graph"),
        ([str(other_sensor), "--model", str(model)], 4, "expected a DAVIS346 recording"),
    ]
    for argv, code, message in cases:
        before = {p: sha256(p) for p in (unlabelled, no_events, truncated, zero_bytes, a, other_sensor)}
        assert cli.main([*argv, "--quiet"]) == code, argv
        err = capsys.readouterr().err
        assert err.startswith("davis-eval: error:") and message in err, err
        assert {p: sha256(p) for p in before} == before
    assert zero_bytes.stat().st_size == 0


def test_missing_bundled_detector_exits_5_and_says_how_to_pass_one(sessions, tmp_path, monkeypatch, capsys):
    import davis_rig.models

    _, a, _ = sessions
    monkeypatch.setattr(davis_rig.models, "DEFAULT_DETECTOR_DIR", tmp_path / "not_installed")
    before = sha256(a)
    assert cli.main([str(a), "--quiet"]) == 5
    err = capsys.readouterr().err
    assert err.startswith("davis-eval: error:") and "bundled default detector" in err and "--detector" in err, err
    assert sha256(a) == before


def test_int8_scores_with_the_bundled_int8_graph(sessions, monkeypatch, capsys):
    import davis_rig.evaluation.physical as physical
    from davis_rig.models import default_detector_path

    _, a, _ = sessions
    used = []
    original = physical.evaluate_sessions

    def recording(paths, model, *args, **kwargs):
        used.append(model)
        return original(paths, model, *args, **kwargs)

    monkeypatch.setattr(physical, "evaluate_sessions", recording)
    assert cli.main([str(a), "--int8", "--threshold", "0.25", "--quiet"]) == 0
    assert used == [default_detector_path(int8=True)] and used[0].name == "rvt_default_int8.onnx"
    assert "| SeqASR ↑ | 0.25 |" in capsys.readouterr().out


def _other_sensor_session(path):
    """A labelled session of a 240x180 sensor (wrong resolution for the DAVIS346 evaluation)."""
    import numpy as np

    from davis_rig.labelers.session_labels import write_labels
    from davis_rig.protocol.frames import ApsFrame
    from davis_rig.session import SessionWriter
    from davis_rig.types import BBOX_DTYPE, make_events

    info = {"layout": {"aps_size_columns": 240, "aps_size_rows": 180, "dvs_size_columns": 240, "dvs_size_rows": 180}}
    with SessionWriter(path, device_info=info) as writer:
        writer.append_events(make_events([10, 20], [1, 2], [1, 2], [0, 1]))
        writer.append_frame(ApsFrame(np.zeros((180, 240), np.uint16), 0, 0, 0, 1, 2, 3))
    labels = np.zeros(1, BBOX_DTYPE)
    labels["w"] = labels["h"] = 50
    write_labels(path, labels, {"labeler": "test"})


def test_label_and_eval_run_with_torch_imports_blocked(sessions, tmp_path):
    import subprocess
    import textwrap

    directory, a, _ = sessions
    session = tmp_path / "no_torch.h5"
    session.write_bytes(scene_session(tmp_path, "fresh.h5").read_bytes())
    script = textwrap.dedent(f"""
        import sys
        sys.modules["torch"] = None  # any "import torch" now raises ImportError
        from davis_rig.cli import eval as ev, label as lb
        assert lb.main([{str(session)!r}, "--yolo", {str(person_yolo(tmp_path))!r}, "--quiet"]) == 0
        assert ev.main([{str(session)!r}, "--model", {str(person_rvt(tmp_path))!r}, "--threshold", "0.1",
                        "--quiet"]) == 0
    """)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "| AP ↓ | 0.1 | 100.0% |" in result.stdout


def test_threshold_takes_one_value_and_never_swallows_the_session(sessions, tmp_path, capsys):
    _, a, _ = sessions
    model = person_rvt(tmp_path)
    assert cli.main(["--threshold", "0.25", str(a), "--detector", str(model), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "| AP ↓ | 0.25 | 100.0% |" in out and "0.001" not in out


def test_files_with_the_same_name_get_distinct_columns_and_gifs(sessions, tmp_path, capsys):
    pytest.importorskip("PIL", reason="the GIF needs the report extra")
    _, a, b = sessions
    for folder, source in (("d1", a), ("d2", b)):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "case.h5").write_bytes(source.read_bytes())
    report = tmp_path / "R"
    argv = [str(tmp_path / "d1" / "case.h5"), str(tmp_path / "d2" / "case.h5"), "--detector", str(person_rvt(tmp_path)),
            "--threshold", "0.25", "--out", str(report), "--no-plot", "--gif-seconds", "0.2", "--skip-first-ms", "0",
            "--seq-len", "3", "--quiet"]
    assert cli.main(argv) == 0
    assert "| Metric | Confidence threshold | d1/case | d2/case |" in capsys.readouterr().out
    data = json.loads((report / "report.json").read_text())
    assert [r["name"] for r in data["recordings"]] == ["d1/case", "d2/case"]
    assert data["settings"]["skip_first_us"] == 0  # 0 is stored as 0, not null
    assert sorted(p.name for p in report.glob("*.gif")) == ["d1_case.gif", "d2_case.gif"]
    assert cli.main([*argv[:2], "--names", "x,x", "--quiet"]) == 2
    assert "argument --names: every session needs its own non-empty name" in capsys.readouterr().err


def test_yolo_labels_an_unlabelled_session_in_the_same_run_like_davis_label(tmp_path, capsys):
    from davis_rig.cli import label as label_cli
    from davis_rig.evaluation.physical import labels_provenance
    from davis_rig.session import SessionReader

    yolo, rvt = person_yolo(tmp_path), person_rvt(tmp_path)
    fresh = scene_session(tmp_path, "fresh.h5")
    by_label = tmp_path / "by_label.h5"
    by_label.write_bytes(fresh.read_bytes())
    assert cli.main([str(fresh), "--threshold", "0.25", "--detector", str(rvt), "--quiet"]) == 4
    err = capsys.readouterr().err
    assert "has no /labels: add --yolo MODEL.onnx to label it in this run" in err and "Traceback" not in err

    assert cli.main([str(fresh), "--threshold", "0.25", "--detector", str(rvt), "--yolo", str(yolo), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "| AP ↓ | 0.25 | 100.0% |" in captured.out and "labelled with person_yolo.onnx" in captured.err
    assert label_cli.main([str(by_label), "--yolo", str(yolo), "--quiet"]) == 0
    with SessionReader(fresh) as ours, SessionReader(by_label) as theirs:
        assert np.array_equal(ours.labels(), theirs.labels())
        mine, reference = labels_provenance(ours.labels_attrs()), labels_provenance(theirs.labels_attrs())
    mine.pop("created_utc"), reference.pop("created_utc")
    assert mine == reference  # the same provenance as davis-label stores

    before = sha256(fresh)  # a labelled session is left as it is
    assert cli.main([str(fresh), "--threshold", "0.25", "--detector", str(rvt), "--yolo", str(yolo), "--quiet"]) == 0
    assert sha256(fresh) == before and "labelled with" not in capsys.readouterr().err


def test_a_missing_detector_fails_before_yolo_writes_labels(tmp_path, capsys):
    fresh = scene_session(tmp_path, "fresh.h5")
    before = sha256(fresh)
    argv = [str(fresh), "--detector", str(tmp_path / "nope.onnx"), "--yolo", str(person_yolo(tmp_path)), "--quiet"]
    assert cli.main(argv) == 4
    assert "nope.onnx: no such RVT ONNX model" in capsys.readouterr().err and sha256(fresh) == before


def test_a_failing_report_leaves_no_report_folder(sessions, tmp_path, monkeypatch, capsys):
    import davis_rig.evaluation.report as report

    _, a, _ = sessions

    def interrupted(results, settings, path):
        path.write_text("{")  # half a file, then Ctrl-C
        raise KeyboardInterrupt

    monkeypatch.setattr(report, "write_json", interrupted)
    out = tmp_path / "new" / "report"
    assert cli.main([str(a), "--detector", str(person_rvt(tmp_path)), "--threshold", "0.25", "--out", str(out),
                     "--no-plot", "--gif-seconds", "0", "--quiet"]) == 130
    assert not (tmp_path / "new").exists() and "davis-eval: interrupted" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == [tmp_path / "rvt.onnx"]  # no staging folder either


def test_no_label_left_after_the_filters_gives_ap_zero_with_a_warning(sessions, tmp_path, capsys):
    _, a, _ = sessions
    argv = [str(a), "--detector", str(person_rvt(tmp_path)), "--threshold", "0.25", "--skip-first-ms", "100000",
            "--quiet"]
    assert cli.main(argv) == 0
    captured = capsys.readouterr()
    assert "| AP ↓ | 0.25 | 0.0% |" in captured.out
    assert "a: no label left after --skip-first-ms 100000 and the box size filter: AP is 0" in captured.err


@pytest.mark.parametrize("out", ["taken.txt", "taken.txt/report"])
def test_an_out_that_cannot_be_a_folder_fails_before_scoring_and_before_yolo_writes_labels(tmp_path, capsys,
                                                                                            monkeypatch, out):
    import davis_rig.evaluation.physical as physical

    fresh = scene_session(tmp_path, "fresh.h5")
    before = sha256(fresh)
    (tmp_path / "taken.txt").write_text("mine")
    monkeypatch.setattr(physical, "evaluate_sessions", lambda *a, **k: pytest.fail("scored before --out was checked"))
    argv = [str(fresh), "--detector", str(person_rvt(tmp_path)), "--yolo", str(person_yolo(tmp_path)),
            "--threshold", "0.25", "--out", str(tmp_path / out), "--quiet"]
    assert cli.main(argv) == 4
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == (f"davis-eval: error: {tmp_path / out}: --out needs a folder, "
                                                   f"and {tmp_path / 'taken.txt'} is a file\n")
    assert sha256(fresh) == before and (tmp_path / "taken.txt").read_text() == "mine"


@pytest.mark.parametrize("name", ["rvt-b.ckpt", "model.safetensors", "weights.pt"])
def test_pytorch_weights_as_detector_say_how_to_make_the_onnx(sessions, tmp_path, capsys, name):
    _, a, _ = sessions
    weights = tmp_path / name
    weights.write_bytes(b"PK\x03\x04 not an ONNX graph")
    assert cli.main([str(a), "--detector", str(weights), "--threshold", "0.25", "--quiet"]) == 4
    err = capsys.readouterr().err
    assert err.startswith(f"davis-eval: error: {weights}: onnxruntime cannot load the model")
    assert err.rstrip().endswith("(PyTorch weights? scoring needs an RVT step ONNX: export one with "
                                 "tools/convert_checkpoint.py --onnx)")


def test_an_out_folder_that_cannot_be_written_fails_before_scoring(sessions, tmp_path, capsys, monkeypatch):
    import os

    import davis_rig.evaluation.physical as physical

    _, a, _ = sessions
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda path, mode: False if path == tmp_path else real_access(path, mode))
    monkeypatch.setattr(physical, "evaluate_sessions", lambda *a, **k: pytest.fail("scored before --out was checked"))
    argv = [str(a), "--detector", str(person_rvt(tmp_path)), "--threshold", "0.25", "--out",
            str(tmp_path / "report"), "--quiet"]
    assert cli.main(argv) == 4
    assert capsys.readouterr().err == (f"davis-eval: error: {tmp_path / 'report'}: --out cannot be created: "
                                       f"{tmp_path} is not writable\n")
