"""davis-record: arguments map onto record_session / recover_session; errors become exit codes."""

from __future__ import annotations

import contextlib
from pathlib import Path

import pytest

from davis_rig.cli import record as cli
from davis_rig.cli.common import EXIT_DATA, EXIT_DEVICE, EXIT_USAGE
from davis_rig.errors import DeviceNotFoundError, SessionError
from davis_rig.session.record import RecordingSummary


def test_help_is_fast_and_imports_nothing_heavy(fresh_python):
    code = (
        "import sys, io, contextlib\n"
        "from davis_rig.cli.record import main\n"
        "buf = io.StringIO()\n"
        "with contextlib.redirect_stdout(buf):\n"
        "    try: main(['--help'])\n"
        "    except SystemExit: pass\n"
        "assert '--out' in buf.getvalue() and '--recover' in buf.getvalue()\n"
        "print(sorted(m for m in ('h5py', 'usb', 'torch', 'numpy', 'hdf5plugin') if m in sys.modules))\n"
    )
    assert fresh_python(code) == "[]"


class FakeOpen:
    def __init__(self):
        self.calls = []
        self.camera = object()

    def __call__(self, serial, backend=None, usb_transfers=8):
        self.calls.append((serial, backend, usb_transfers))

        @contextlib.contextmanager
        def opened():
            yield self.camera

        return opened()


def _summary(path):
    return RecordingSummary(path=Path(path), duration_s=2.0, events=10, frames=1, specials=0, imu=0,
                            stopped_by="duration", camera_stats={"dropped_transfers": 0})


def test_arguments_map_onto_record_session(monkeypatch, capsys, tmp_path):
    opener = FakeOpen()
    calls = []

    def fake_record(camera, path, **kwargs):
        calls.append((camera, path, kwargs))
        return _summary(path)

    backend = object()
    fakes = []
    monkeypatch.setattr(cli, "open_camera", opener)
    monkeypatch.setattr(cli, "fake_backend",
                        lambda replay, fast: fakes.append((replay, fast)) or (backend, lambda: False))
    monkeypatch.setattr("davis_rig.session.record.record_session", fake_record)
    out = str(tmp_path / "s.h5")
    code = cli.main(["--out", out, "--duration", "2.5", "--exposure", "4000", "--frame-interval", "40000",
                     "--serial", "SN1", "--fake", "replay.bin", "--fake-fast", "--overwrite", "--quiet",
                     "--usb-transfers", "0"])
    assert code == 0
    assert fakes == [("replay.bin", True)]
    assert opener.calls == [("SN1", backend, 0)]
    assert len(calls) == 1
    camera, path, kwargs = calls[0]
    stop_event = kwargs.pop("stop_event")
    assert camera is opener.camera and path == out
    assert kwargs == dict(duration_s=2.5, exposure_us=4000, frame_interval_us=40000, overwrite=True, journal=True,
                          progress=None)
    assert not stop_event.is_set()
    assert "10 events" in capsys.readouterr().out


def test_defaults(monkeypatch, tmp_path):
    opener = FakeOpen()
    calls = []
    monkeypatch.setattr(cli, "open_camera", opener)
    monkeypatch.setattr("davis_rig.session.record.record_session",
                        lambda camera, path, **kwargs: calls.append(kwargs) or _summary(path))
    assert cli.main(["--out", str(tmp_path / "s.h5"), "--no-journal"]) == 0
    assert opener.calls == [(None, None, 8)]
    assert calls[0]["duration_s"] is None and calls[0]["exposure_us"] is None and calls[0]["journal"] is False
    assert calls[0]["progress"] is cli._progress_line


def test_recover_maps_onto_recover_session(monkeypatch, capsys):
    from davis_rig.session.recovery import RecoveryReport

    seen = []
    monkeypatch.setattr("davis_rig.session.recovery.recover_session",
                        lambda path: seen.append(path) or RecoveryReport(Path(path), True, transfers=3, events=7))
    assert cli.main(["--recover", "x.h5"]) == 0
    assert seen == ["x.h5"]
    assert "rebuilt from the journal" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, message",
    [([], "the following arguments are required: --out (or --recover SESSION_H5)"),
     (["--recover", "a.h5", "--out", "b.h5"], "argument --recover: not allowed with --out"),
     (["--recover", "a.h5", "--view"], "argument --recover: not allowed with --view"),
     (["--recover", "a.h5", "--no-imu"], "argument --recover: not allowed with --no-imu"),
     (["--out", "a.h5", "--fake-fast"], "argument --fake-fast: needs --fake REPLAY")],
)
def test_usage_errors(argv, message, capsys):
    assert cli.main(argv) == EXIT_USAGE
    assert f"davis-record: error: {message}" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, message",
    [(["--duration", "-1"], "argument --duration: expected a number in [0, inf), got '-1'"),
     (["--duration", "nan"], "argument --duration: expected a finite number, got 'nan'"),
     (["--exposure", "-1"], "argument --exposure: expected an integer in [0, 4194303], got '-1'"),
     (["--exposure", "4194304"], "argument --exposure: expected an integer in [0, 4194303]"),
     (["--frame-interval", "-5"], "argument --frame-interval: expected an integer in [0, 8388607], got '-5'"),
     (["--frame-interval", "8388608"], "argument --frame-interval: expected an integer in [0, 8388607]"),
     (["--usb-transfers", "-1"], "argument --usb-transfers: expected an integer >= 0, got '-1'"),
     (["--usb-transfers", "two"], "argument --usb-transfers: expected an integer, got 'two'")],
)
def test_out_of_range_numbers_are_usage_errors_before_the_camera_is_opened(monkeypatch, capsys, argv, message):
    def must_not_open(*args, **kwargs):
        raise AssertionError("the camera was opened")

    monkeypatch.setattr(cli, "open_camera", must_not_open)
    assert cli.main(["--out", "a.h5", "--quiet", *argv]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert f"davis-record: error: {message}" in err and "Traceback" not in err


def test_limits_of_the_numbers_are_accepted(monkeypatch, tmp_path):
    seen = {}
    monkeypatch.setattr(cli, "open_camera", FakeOpen())
    monkeypatch.setattr("davis_rig.session.record.record_session",
                        lambda camera, path, **kwargs: seen.update(kwargs) or _summary(path))
    argv = ["--out", str(tmp_path / "a.h5"), "--quiet", "--duration", "0", "--exposure", "4194303",
            "--frame-interval", "0"]
    assert cli.main(argv) == 0
    assert (seen["duration_s"], seen["exposure_us"], seen["frame_interval_us"]) == (0.0, 4194303, 0)


def test_bad_number_is_a_usage_error(capsys):
    assert cli.main(["--out", "a.h5", "--duration", "soon"]) == EXIT_USAGE
    assert "argument --duration: expected a number, got 'soon'" in capsys.readouterr().err


def test_help_names_only_files_that_exist_and_the_exit_codes(capsys):
    import re

    from davis_rig.cli.common import EXIT_CODES_TEXT

    assert cli.main(["--help"]) == 0
    text = capsys.readouterr().out
    repo = Path(__file__).resolve().parents[2]
    mentioned = re.findall(r"recordings/[\w./-]+", text)
    assert mentioned and all((repo / path).is_file() for path in mentioned), mentioned
    assert EXIT_CODES_TEXT.splitlines()[0] in text


@pytest.mark.parametrize("error, code", [(DeviceNotFoundError("no DAVIS346 attached"), EXIT_DEVICE),
                                         (SessionError("a.h5: file exists"), EXIT_DATA)])
def test_errors_become_one_message_and_an_exit_code(monkeypatch, capsys, error, code):
    def failing_open(serial, backend=None, usb_transfers=8):
        raise error

    monkeypatch.setattr(cli, "open_camera", failing_open)
    assert cli.main(["--out", "a.h5", "--quiet"]) == code
    err = capsys.readouterr().err
    assert err.startswith("davis-record: error: ") and str(error) in err and "Traceback" not in err


def test_capture_path_does_not_import_torch(fresh_python):
    code = (
        "import sys\n"
        "import davis_rig.cli.record, davis_rig.session, davis_rig.session.record, davis_rig.session.recovery\n"
        "import davis_rig.session.reader, davis_rig.session.writer\n"
        "print('torch' in sys.modules, 'dv_processing' in sys.modules)\n"
    )
    assert fresh_python(code) == "False False"


def test_no_imu_starts_the_camera_without_the_imu_and_the_default_starts_it(monkeypatch, tmp_path):
    from davis_rig.protocol.config import Imu, Module

    devices = []
    make_backend = cli.fake_backend

    def keep_device(replay, fast=False):
        backend, exhausted = make_backend(replay, fast)
        devices.append(backend.devices[0])
        return backend, exhausted

    monkeypatch.setattr(cli, "fake_backend", keep_device)
    replay = Path(__file__).resolve().parents[2] / "recordings" / "sample.davisreplay"
    assert cli.main(["--fake", str(replay), "--fake-fast", "--out", str(tmp_path / "imu.h5"), "-q"]) == 0
    assert cli.main(["--fake", str(replay), "--fake-fast", "--out", str(tmp_path / "no.h5"), "-q", "--no-imu"]) == 0
    imu_runs = [[w.value for w in device.writes if (w.module, w.param) == (Module.IMU, Imu.RUN_ACCELEROMETER)]
                for device in devices]
    assert 1 in imu_runs[0]  # started with the accelerometer on, as libcaer and DV do
    assert 1 not in imu_runs[1]


def test_the_replay_itself_as_out_is_refused_even_with_overwrite(tmp_path, monkeypatch, capsys):
    replay = Path(__file__).resolve().parents[2] / "recordings" / "sample.davisreplay"
    copy = tmp_path / "walk.davisreplay"
    copy.write_bytes(replay.read_bytes())
    monkeypatch.chdir(tmp_path)
    assert cli.main(["--fake", str(copy), "--out", "./walk.davisreplay", "--overwrite", "-q"]) == EXIT_USAGE
    assert capsys.readouterr().err.splitlines()[-1] == ("davis-record: error: argument --out: ./walk.davisreplay is "
                                                        "the --fake replay")
    assert copy.read_bytes() == replay.read_bytes() and [p.name for p in tmp_path.iterdir()] == [copy.name]


def test_the_first_signal_stops_cleanly_and_a_second_one_aborts_at_once():
    import signal
    import threading

    stop, previous = threading.Event(), {signal.SIGINT: signal.getsignal(signal.SIGINT)}
    handle = cli._stop_handler(stop, previous)
    signal.signal(signal.SIGINT, handle)
    try:
        handle(signal.SIGINT, None)
        assert stop.is_set() and signal.getsignal(signal.SIGINT) is handle  # still ours: the recording closes
        with pytest.raises(KeyboardInterrupt):
            handle(signal.SIGINT, None)
        assert signal.getsignal(signal.SIGINT) is previous[signal.SIGINT]  # restored
    finally:
        signal.signal(signal.SIGINT, previous[signal.SIGINT])
