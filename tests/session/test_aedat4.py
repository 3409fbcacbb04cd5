"""AEDAT4 import: a file written with iniVation's dv-processing is converted into an identical session."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from davis_rig.errors import FormatError
from davis_rig.session import SessionReader

from tests.helpers.session_data import random_events

dv = pytest.importorskip("dv_processing", reason="AEDAT4 import needs the optional dv-processing package")

from davis_rig.session.aedat4 import import_aedat4  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def write_aedat4(path, events, frames, triggers, imu):
    config = dv.io.MonoCameraWriter.Config("DAVIS346_00000499")
    config.addEventStream((346, 260))
    config.addFrameStream((346, 260))
    config.addTriggerStream()
    config.addImuStream()
    writer = dv.io.MonoCameraWriter(str(path), config)
    store = dv.EventStore()
    for t, x, y, p in events.tolist():
        store.push_back(t, x, y, bool(p))
    writer.writeEvents(store)
    for t_us, exposure_us, image in frames:
        writer.writeFrame(dv.Frame(t_us, exposure_us, 0, 0, image, dv.FrameSource.SENSOR))
    for t_us, trigger_type in triggers:
        writer.writeTrigger(dv.Trigger(t_us, trigger_type))
    for t_us, accel in imu:
        writer.writeImu(dv.IMU(t_us, 25.0, accel, 0.0, 1.0, 0.5, 0.0, -0.5, 0.0, 0.0, 0.0))
    del writer  # closes the file


@pytest.fixture
def aedat4_file(tmp_path, rng):
    events = random_events(rng, 3000, t0_us=1_000_000, span_us=500_000)
    image = rng.integers(0, 256, (260, 346)).astype(np.uint8)
    frames = [(1_100_000, 4000, image)]
    triggers = [(1_050_000, dv.TriggerType.EXTERNAL_SIGNAL_RISING_EDGE), (1_200_000, dv.TriggerType.TIMESTAMP_RESET)]
    imu = [(1_000_500, 0.25), (1_001_500, -1.0)]
    path = tmp_path / "rec.aedat4"
    write_aedat4(path, events, frames, triggers, imu)
    return path, events, image


def test_import_keeps_every_stream(tmp_path, aedat4_file):
    path, events, image = aedat4_file
    summary = import_aedat4(path, tmp_path / "s.h5")
    assert summary.events == len(events) and summary.frames == 1 and summary.specials == 2 and summary.imu == 2
    with SessionReader(tmp_path / "s.h5") as reader:
        np.testing.assert_array_equal(reader.events(), events)
        frame = reader.frames[0]
        np.testing.assert_array_equal(frame.pixels, image.astype(np.uint16) << 8)
        assert (frame.t_start_exposure_us, frame.t_end_exposure_us) == (1_100_000, 1_104_000)
        np.testing.assert_array_equal(reader.specials()["type"], [2, 1])  # libcaer ids
        np.testing.assert_array_equal(reader.imu()["accel_x_g"], np.array([0.25, -1.0], np.float32))
        assert reader.device_info["serial"] == "00000499"
        np.testing.assert_array_equal(reader.events_between(1_100_000, 1_200_000),
                                      events[(events["t"] >= 1_100_000) & (events["t"] < 1_200_000)])


def test_tool_script(tmp_path, aedat4_file):
    path, events, _ = aedat4_file
    out = subprocess.run([sys.executable, str(ROOT / "tools" / "aedat4_to_session.py"), str(path),
                          str(tmp_path / "t.h5")], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert f"{len(events)} events" in out.stdout
    again = subprocess.run([sys.executable, str(ROOT / "tools" / "aedat4_to_session.py"), str(path),
                            str(tmp_path / "t.h5")], capture_output=True, text=True)
    assert again.returncode == 4 and "file exists" in again.stderr


def test_not_an_aedat4_file(tmp_path):
    bad = tmp_path / "bad.aedat4"
    bad.write_bytes(b"AEDAT3 or something else")
    with pytest.raises(FormatError, match="not an AEDAT4 file"):
        import_aedat4(bad, tmp_path / "s.h5")
    with pytest.raises(FormatError, match="no such"):
        import_aedat4(tmp_path / "missing.aedat4", tmp_path / "s.h5")


def test_an_aedat4_file_under_another_name_is_a_short_error_naming_the_rule(tmp_path, aedat4_file):
    path, _, _ = aedat4_file
    renamed = tmp_path / "walk.bin"
    renamed.write_bytes(path.read_bytes())
    with pytest.raises(FormatError) as info:
        import_aedat4(renamed, tmp_path / "s.h5")
    assert str(info.value) == f"{renamed}: dv-processing reads AEDAT4 only from a file named *.aedat4; rename it"
    assert not (tmp_path / "s.h5").exists()


def test_dv_processing_errors_are_one_line_without_its_stack_trace(tmp_path, aedat4_file):
    path, _, _ = aedat4_file
    data = path.read_bytes()
    damaged = tmp_path / "damaged.aedat4"
    damaged.write_bytes(data[:20] + bytes(len(data) - 20))  # the magic, then nothing DV can parse
    with pytest.raises(FormatError, match="damaged.aedat4") as info:
        import_aedat4(damaged, tmp_path / "s.h5")
    assert "Stacktrace" not in str(info.value) and "\n" not in str(info.value)


def test_missing_dv_processing_is_a_clear_error(monkeypatch, tmp_path):
    from davis_rig.errors import MissingDependencyError

    monkeypatch.setitem(sys.modules, "dv_processing", None)
    with pytest.raises(MissingDependencyError, match=r"davis_rig\[aedat4\]"):
        import_aedat4(tmp_path / "x.aedat4", tmp_path / "s.h5")


def test_truncated_aedat4_file(tmp_path, aedat4_file):
    path, _, _ = aedat4_file
    data = path.read_bytes()
    cut = tmp_path / "cut.aedat4"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError, match="AEDAT4"):
        import_aedat4(cut, tmp_path / "s.h5")


def test_frames_are_flushed_while_importing_not_held_until_the_end(tmp_path, rng, monkeypatch):
    from davis_rig.session.writer import SessionWriter

    image = rng.integers(0, 256, (260, 346)).astype(np.uint8)
    frames = [(1_000_000 + 50_000 * i, 4000, image) for i in range(4)]
    path = tmp_path / "frames.aedat4"
    write_aedat4(path, random_events(rng, 100, t0_us=1_000_000, span_us=200_000), frames, [], [])
    frames_at_flush_checks = []
    real_maybe_flush = SessionWriter.maybe_flush

    def spy(self):
        frames_at_flush_checks.append(self.counts["frames"])
        real_maybe_flush(self)

    monkeypatch.setattr(SessionWriter, "maybe_flush", spy)
    summary = import_aedat4(path, tmp_path / "s.h5")
    assert summary.frames == len(frames)
    assert [1, 2, 3, 4] == [n for n in frames_at_flush_checks if n > 0][:4]  # checked after every frame
