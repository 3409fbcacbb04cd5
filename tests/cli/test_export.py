"""``davis-export``: arguments map onto export_session, the summary, one-line errors with the vocabulary's codes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from davis_rig.cli import export as cli
from davis_rig.interop.summary import ExportSummary

SAMPLE = Path(__file__).resolve().parents[2] / "recordings" / "sample.h5"


def test_help_lists_the_library_formats_and_imports_nothing_heavy(fresh_python):
    code = (
        "import sys, io, contextlib\n"
        "from davis_rig.cli.export import main\n"
        "buf = io.StringIO()\n"
        "with contextlib.redirect_stdout(buf):\n"
        "    try: main(['--help'])\n"
        "    except SystemExit: pass\n"
        "assert '{aedat4,prophesee-dat,rvt,npz}' in buf.getvalue()\n"
        "print(sorted(m for m in ('h5py', 'torch', 'numpy', 'hdf5plugin') if m in sys.modules))\n"
    )
    assert fresh_python(code) == "[]"


def test_arguments_map_onto_export_session(monkeypatch, capsys):
    calls = []

    def fake(path, to, out, **kwargs):
        calls.append((path, to, out, kwargs))
        return ExportSummary(format=to, session=path, outputs=(out,), events=5, events_read=9, labels=2,
                             labels_left_out=0, frame_hw=(240, 304), origin_xy=(3, 4), t_offset_us=0,
                             not_exported={"frames": 1}, notes=("a note",))

    monkeypatch.setattr("davis_rig.interop.export_session", fake)
    assert cli.main(["s.h5", "--to", "npz", "--out", "o.npz", "--crop-origin", "3", "4", "--overwrite", "-q"]) == 0
    path, to, out, kwargs = calls[0]
    assert (path, to, out) == ("s.h5", "npz", "o.npz")
    assert kwargs == {"crop": False, "crop_origin_xy": (3, 4), "split": "test", "overwrite": True, "progress": None}
    assert capsys.readouterr().out == ("s.h5 -> o.npz (npz): 5 events, 2 boxes\n  a note\n"
                                       "  not in this format: 1 frames\n")
    assert cli.main(["s.h5", "--to", "rvt", "--out", "ds", "--split", "val", "--json", "-q"]) == 0
    assert calls[1][3]["split"] == "val" and json.loads(capsys.readouterr().out)["outputs"] == ["ds"]


def test_real_exports_of_the_bundled_sample(tmp_path, capsys):
    assert cli.main([str(SAMPLE), "--to", "prophesee-dat", "--out", str(tmp_path / "s_td.dat"), "-q"]) == 0
    text = capsys.readouterr().out
    assert "376,301 events, 120 boxes" in text and "device µs 10000" in text and "15 frames" in text
    assert (tmp_path / "s_bbox.npy").is_file()
    assert cli.main([str(SAMPLE), "--to", "rvt", "--out", str(tmp_path / "ds"), "-q", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frame_hw"] == [240, 304] and summary["extra"]["windows"] == 12
    assert (tmp_path / "ds" / "test" / "sample" / "labels_v2" / "labels.npz").is_file()


@pytest.mark.parametrize("args, code, says", [
    (["--to", "npz", "--out", "o.npz", "--split", "val"], 2, "argument --split: applies to --to rvt only"),
    (["--to", "npz", "--out", "o.npz", "--crop-origin", "0", "0"], 2,
     "argument --crop-origin: the labels were made for the crop at (21, 10), not (0, 0)"),
    (["--to", "npz", "--out", "o.npz", "--crop-origin", "-1", "0"], 2,
     "argument --crop-origin: expected an integer >= 0"),
    (["--to", "tiff", "--out", "o"], 2, "argument --to: invalid choice"),
    (["--to", "npz", "--out", "missing/o.npz"], 4, "the folder missing does not exist"),
    # dv-processing aborts the whole process (SIGABRT, no exception) on a file name without .aedat4
    (["--to", "aedat4", "--out", "o.h5"], 2,
     "argument --out: --to aedat4 writes a .aedat4 file (dv-processing aborts on any other name), got 'o.h5'"),
])
def test_usage_and_file_errors(tmp_path, monkeypatch, capsys, args, code, says):
    monkeypatch.chdir(tmp_path)
    assert cli.main([str(SAMPLE), *args, "-q"]) == code
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_a_damaged_session_in_a_fresh_process(tmp_path):
    (tmp_path / "cut.h5").write_bytes(SAMPLE.read_bytes()[:50_000])
    run = subprocess.run([sys.executable, "-c", "from davis_rig.cli.export import main; raise SystemExit(main())",
                          str(tmp_path / "cut.h5"), "--to", "rvt", "--out", str(tmp_path / "new" / "ds")],
                         capture_output=True, text=True)
    assert run.returncode == 4 and run.stderr.count("\n") == 1 and "truncated or corrupt" in run.stderr
    assert not (tmp_path / "new").exists()  # a folder the failed command would have made is not left behind


def test_help_and_version(capsys):
    assert cli.main(["--help"]) == 0
    text = capsys.readouterr().out
    assert "{aedat4,prophesee-dat,rvt,npz}" in text and "exit codes: 0 ok" in text and "validation.py" in text
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == "davis-export (davis_rig 0.1.0)"


@pytest.mark.parametrize("to, out, says", [
    ("npz", "taken", "taken: a folder, not a file that can be replaced"),
    ("prophesee-dat", "taken", "taken: a folder, not a file that can be replaced"),
    ("rvt", "taken.txt", "taken.txt: --out needs a folder, and taken.txt is a file"),
])
def test_an_out_of_the_wrong_kind_is_refused_even_with_overwrite_and_leaves_nothing(tmp_path, monkeypatch, capsys,
                                                                                     to, out, says):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "keep").write_text("mine")
    (tmp_path / "taken.txt").write_text("mine")
    assert cli.main([str(SAMPLE), "--to", to, "--out", out, "--overwrite", "-q"]) == 4
    assert capsys.readouterr().err == f"davis-export: error: {says}\n"
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["keep", "taken", "taken.txt"]  # no staging file left


@pytest.mark.parametrize("to", ["npz", "prophesee-dat", "aedat4"])
def test_the_session_itself_as_out_is_refused_even_with_overwrite(tmp_path, monkeypatch, capsys, to):
    monkeypatch.chdir(tmp_path)
    session = tmp_path / "walk.aedat4" if to == "aedat4" else tmp_path / "walk.h5"  # the name --to aedat4 needs
    session.write_bytes(SAMPLE.read_bytes())
    assert cli.main([str(session), "--to", to, "--out", f"./{session.name}", "--overwrite", "-q"]) == 2
    assert capsys.readouterr().err == (f"davis-export: error: argument --out: ./{session.name} is the session being "
                                       "exported\n")
    assert session.read_bytes() == SAMPLE.read_bytes() and [p.name for p in tmp_path.iterdir()] == [session.name]
