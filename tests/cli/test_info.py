"""``davis-info``: text and JSON on the bundled recordings, one message and exit 4 per damaged file."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from davis_rig.cli import info as cli

RECORDINGS = Path(__file__).resolve().parents[2] / "recordings"
BUNDLED = sorted(p for p in RECORDINGS.iterdir() if p.suffix in (".h5", ".davisreplay"))


@pytest.mark.parametrize("path", BUNDLED, ids=lambda p: p.name)
def test_every_bundled_recording(path, capsys):
    assert cli.main([str(path)]) == 0
    text = capsys.readouterr().out
    assert text.startswith(f"{path}: ") and "events        376,301" in text
    assert cli.main([str(path), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["events"] == 376_301 and data["kind"] == ("session" if path.suffix == ".h5" else "replay")


def test_session_text_names_what_the_issue_asks_for(capsys):
    assert cli.main([str(RECORDINGS / "sample.h5")]) == 0
    text = capsys.readouterr().out
    for needle in ("integrity     complete", "duration      0.595 s", "APS frames    15  25.0 fps", "specials      60",
                   "drops         USB 0 transfers", "serial SYNTH001", "labels        120 boxes",
                   "made by davis_rig.scene.recording", "crop origin   21, 10", "biases        28 stored", "PRBP"):
        assert needle in text, needle


def test_several_files_one_damaged(tmp_path, capsys):
    (tmp_path / "empty.h5").touch()
    code = cli.main([str(tmp_path / "empty.h5"), str(RECORDINGS / "sample.h5"), "--json"])
    captured = capsys.readouterr()
    assert code == 4
    assert captured.err.strip() == f"davis-info: error: {tmp_path / 'empty.h5'}: the file is empty (0 bytes), not a " \
                                   "recorded session"
    assert [entry["path"] for entry in json.loads(captured.out)] == [str(RECORDINGS / "sample.h5")]


@pytest.mark.parametrize("content, says", [
    (b"#!AER-DAT4.0\r\n...", "an AEDAT4 recording"),
    (b"% Data file containing CD events\n", "a Prophesee .dat event file"),
    (b"PK\x03\x04....", "numpy .npz"),
    (b"[build-system]\n", "not an HDF5 file"),
])
def test_other_kinds_of_files_are_named(tmp_path, capsys, content, says):
    (tmp_path / "f").write_bytes(content)
    assert cli.main([str(tmp_path / "f")]) == 4
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1 and "Traceback" not in err


def test_truncated_session_in_a_fresh_process(tmp_path):
    (tmp_path / "cut.h5").write_bytes((RECORDINGS / "sample.h5").read_bytes()[:100_000])
    run = subprocess.run([sys.executable, "-c", "from davis_rig.cli.info import main; raise SystemExit(main())",
                          str(tmp_path / "cut.h5")], capture_output=True, text=True)
    assert run.returncode == 4 and run.stdout == ""
    assert run.stderr.startswith("davis-info: error: ") and "truncated or corrupt" in run.stderr
    assert "Traceback" not in run.stderr


@pytest.mark.parametrize("group, missing", [("specials", "type"), ("imu", "t")])
def test_a_special_or_imu_table_without_its_columns_is_a_one_line_error(tmp_path, capsys, group, missing):
    import h5py

    path = tmp_path / "s.h5"
    path.write_bytes((RECORDINGS / "sample.h5").read_bytes())
    with h5py.File(path, "a") as f:
        table = f.require_group(group)
        table.require_dataset("ax", shape=(len(f["specials/t"]),), dtype="f4")  # a column that stays
        if missing in table:
            del table[missing]
    assert cli.main([str(path)]) == 4
    err = capsys.readouterr().err
    assert err == f"davis-info: error: {path}: missing dataset /{group}/{missing}\n"


def test_usage_and_version(capsys):
    assert cli.main([]) == 2
    assert "the following arguments are required: FILE" in capsys.readouterr().err
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == "davis-info (davis_rig 0.1.0)"
    assert cli.main(["--help"]) == 0
    assert "exit codes: 0 ok" in capsys.readouterr().out


@pytest.mark.parametrize("stats", ['{"camera": {"decoder": [1]}}', '{"writer": {"timestamp_resets": "many"}}',
                                   '{"camera": {"dropped_transfers": [2]}}'])
def test_stats_of_the_wrong_types_are_a_one_line_error(tmp_path, capsys, stats):
    import h5py

    path = tmp_path / "s.h5"
    path.write_bytes((RECORDINGS / "sample.h5").read_bytes())
    with h5py.File(path, "a") as f:
        f.attrs["stats"] = stats
    assert cli.main([str(path)]) == 4
    err = capsys.readouterr().err
    assert err.startswith(f"davis-info: error: {path}: unreadable stats attribute (") and err.count("\n") == 1


def test_an_unreadable_crop_origin_names_the_file(tmp_path, capsys):
    import h5py

    path = tmp_path / "s.h5"
    path.write_bytes((RECORDINGS / "sample.h5").read_bytes())
    with h5py.File(path, "a") as f:
        f["labels"].attrs["crop_origin_xy"] = "zz"
    assert cli.main([str(path)]) == 4
    assert capsys.readouterr().err.startswith(f"davis-info: error: {path}: /labels: unreadable crop origin attribute")
