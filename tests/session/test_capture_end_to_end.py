"""The issue's round trip: random events and frames -> StreamEncoder -> virtual DAVIS346 -> davis-record ->
session.h5 -> identical data; plus unplug and garbage on the real Davis346 driver, and kill -9 / Ctrl-C of a
`davis-record` subprocess. The in-process recordings run twice (``usb_backend``): on the virtual backend and on
pyusb's libusb1 backend over the emulated libusb-1.0, the code path of a real camera (transfer ring over ctypes)."""

from __future__ import annotations

import subprocess
import sys
import threading

import numpy as np
import pytest

from davis_rig.device.camera import Davis346
from davis_rig.protocol.decoder import StreamDecoder
from davis_rig.protocol.encoder import StreamEncoder, split_transfers
from davis_rig.protocol.frames import ApsFrame
from davis_rig.protocol.layout import SensorLayout
from davis_rig.session import SessionReader
from davis_rig.session.journal import journal_path
from davis_rig.session.record import record_session
from davis_rig.usb.replay import ReplayHeader, ReplayWriter
from davis_rig.usb.sources import EncodedSource, Faults, TransferListSource
from davis_rig.usb.virtual import VirtualDavis346

from tests.helpers.libusb_emu import EmuFaults, emulated_usb_backend, usb_backend  # noqa: F401  (fixtures)
from tests.helpers.session_data import random_events

LAYOUT = SensorLayout.davis346()


def scene(rng, n_events=60_000, n_frames=3):
    events = random_events(rng, n_events, t0_us=50_000, span_us=1_500_000)
    frames = []
    for i in range(n_frames):
        t0 = 100_000 + 400_000 * i
        pixels = (rng.integers(0, 1024, (260, 346)) << 6).astype(np.uint16)
        frames.append(ApsFrame(pixels, 0, 0, t0, t0 + 100, t0 + 4100, t0 + 9000))
    return events, frames


def record_until(camera, path, n_events, n_frames, **kwargs):
    """Record until the expected data arrived (or 60 s), then stop cleanly."""
    stop = threading.Event()

    def progress(p):
        if p.events >= n_events and p.frames >= n_frames:
            stop.set()

    return record_session(camera, path, stop_event=stop, progress=progress, progress_interval_s=0.02,
                          duration_s=60, **kwargs)


def assert_same(path, events, frames):
    with SessionReader(path) as reader:
        np.testing.assert_array_equal(reader.events(), events)
        assert len(reader.frames) == len(frames)
        for stored, frame in zip(reader.frames, frames):
            assert stored == frame
        assert reader.complete


def test_encoder_virtual_camera_record_session_round_trip(tmp_path, rng, usb_backend):
    events, frames = scene(rng)
    # Paced: served in device real time (1.5 s), like the camera; unpaced would outrun any consumer.
    device = VirtualDavis346(source=EncodedSource(events, frames, layout=LAYOUT, paced=True))
    with Davis346.open(backend=usb_backend.plug(device)) as camera:
        summary = record_until(camera, tmp_path / "s.h5", len(events), len(frames), exposure_us=4000)
    assert summary.events == len(events) and summary.frames == len(frames) and summary.dropped_transfers == 0
    assert_same(tmp_path / "s.h5", events, frames)
    with SessionReader(tmp_path / "s.h5") as reader:
        assert reader.device_info["serial"] == "VIRT0001"
        assert reader.device_info["layout"]["dvs_size_columns"] == 346
        assert reader.config["exposure_us"] == 4000
        assert reader.config["frame_interval_us"] == 40000  # the camera default in effect, not null
        assert reader.stats["camera"]["decoder"]["unknown_words"] == 0
        specials = reader.specials()
        assert 14 in specials["type"] and 15 in specials["type"]  # APS frame start / end
    assert not journal_path(tmp_path / "s.h5").exists()


def scene_replay(tmp_path, rng):
    """A 20k-event, 2-frame scene written as ``scene.replay`` (8 KiB transfers 1 ms apart): events, frames, path."""
    events, frames = scene(rng, n_events=20_000, n_frames=2)
    data = StreamEncoder(LAYOUT).encode(events, frames)
    replay = tmp_path / "scene.replay"
    with ReplayWriter(replay, ReplayHeader(device_info=LAYOUT.to_dict(), serial="RPLY0001", firmware_version=6,
                                           logic_version=18, logic_patch=1)) as writer:
        for i, transfer in enumerate(split_transfers(data, 8192)):
            writer.write(transfer, host_time_ns=i * 1_000_000)
    return events, frames, replay


def test_davis_record_subprocess_with_a_replay_file(tmp_path, rng):
    events, frames, replay = scene_replay(tmp_path, rng)
    out = tmp_path / "s.h5"
    result = subprocess.run(
        [sys.executable, "-m", "davis_rig.cli.record", "--out", str(out), "--fake", str(replay), "--exposure", "4000"],
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert f"{len(events)} events" in result.stdout and "dropped transfers: 0" in result.stdout
    assert "stopped by end of replay" in result.stdout
    assert "Mev/s" in result.stderr  # the live progress line
    assert_same(out, events, frames)
    again = subprocess.run([sys.executable, "-m", "davis_rig.cli.record", "--out", str(out), "--fake", str(replay)],
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 4 and "file exists" in again.stderr


def test_unplug_mid_recording_keeps_the_data_before_it(tmp_path, rng, usb_backend):
    events, _ = scene(rng, n_frames=0)
    transfers = split_transfers(StreamEncoder(LAYOUT).encode(events), 4096)
    device = VirtualDavis346(source=TransferListSource(transfers),
                             faults=Faults(disconnect_after_transfers=len(transfers) // 2))
    # One transfer per read; unpaced source: a queue deep enough for the whole stream keeps it free of drops.
    with Davis346.open(backend=usb_backend.plug(device), read_bytes=4096, queue_transfers=4096) as camera:
        summary = record_session(camera, tmp_path / "s.h5", duration_s=60)
    assert summary.stopped_by == "disconnected"
    received = summary.camera_stats["bytes"]
    expected = StreamDecoder(LAYOUT).feed(b"".join(transfers)[:received]).events
    assert 0 < len(expected) < len(events)
    with SessionReader(tmp_path / "s.h5") as reader:
        assert reader.complete and reader.stats["stopped_by"] == "disconnected"
        np.testing.assert_array_equal(reader.events(), expected)


#: libusb-level faults of the emulated camera, one recording each (the virtual backend ignores them).
STOP_FAULTS = {
    "prompt": EmuFaults(),
    "late-and-racing": EmuFaults(completion_delay_us=2000, cancel_delay_us=1000, cancel_race_every=2, poll_ms=2),
}


def test_record_session_stopped_while_data_flows_keeps_every_byte_and_no_journal(tmp_path, rng, usb_backend):
    """Stopped by duration mid-stream (the camera still sends): clean end, nothing lost, in order, no journal."""
    events, _ = scene(rng, n_events=40_000, n_frames=0)
    for run, faults in enumerate(STOP_FAULTS.values()):
        device = VirtualDavis346(source=EncodedSource(events, layout=LAYOUT, paced=True))
        path = tmp_path / f"s{run}.h5"
        with Davis346.open(backend=usb_backend.plug(device, faults)) as camera:
            summary = record_session(camera, path, duration_s=0.4)
        stats = summary.camera_stats
        assert summary.stopped_by == "duration" and not journal_path(path).exists()
        assert stats["bytes"] == device.bytes_served and stats["dropped_transfers"] == 0
        assert stats["decoded_transfers"] == stats["transfers"]  # the post-stop drain wrote what arrived late
        with SessionReader(path) as reader:
            assert reader.complete and reader.stats["stopped_by"] == "duration"
            recorded = reader.events()
        assert 0 < len(recorded) < len(events)
        np.testing.assert_array_equal(recorded, events[: len(recorded)])


def test_davis_record_on_the_emulated_camera_ends_cleanly(tmp_path, rng, monkeypatch, capsys, emulated_usb_backend):
    """The README's `davis-record --out session.h5 --duration S` on a camera reached through libusb-1.0: exit 0, a
    complete file, no journal, every time."""
    from davis_rig.cli import record as cli

    events, _ = scene(rng, n_events=40_000, n_frames=0)
    faults = EmuFaults(completion_delay_us=1000, cancel_race_every=3)
    for run in range(3):
        device = VirtualDavis346(source=EncodedSource(events, layout=LAYOUT, paced=True))
        backend = emulated_usb_backend.plug(device, faults)
        monkeypatch.setattr(cli, "open_camera", lambda serial, _backend, usb_transfers: Davis346.open(
            serial=serial, backend=backend, usb_transfers=usb_transfers))
        out = tmp_path / f"session{run}.h5"
        assert cli.main(["--out", str(out), "--duration", "0.5", "--quiet"]) == 0
        assert "stopped by duration" in capsys.readouterr().out
        assert not journal_path(out).exists()
        with SessionReader(out) as reader:
            assert reader.complete
            np.testing.assert_array_equal(reader.events(), events[: reader.num_events])


def test_davis_record_fake_replay_over_the_emulated_libusb(tmp_path, rng, monkeypatch, capsys, emulated_usb_backend):
    from davis_rig.cli import record as cli

    events, frames, replay = scene_replay(tmp_path, rng)

    def fake_backend(path, fast=False):
        device = VirtualDavis346.from_replay(path, paced=not fast)
        return emulated_usb_backend.plug(device), lambda: device.drained

    monkeypatch.setattr(cli, "fake_backend", fake_backend)
    out = tmp_path / "s.h5"
    assert cli.main(["--out", str(out), "--fake", str(replay), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert f"{len(events)} events" in printed and "stopped by end of replay" in printed
    assert_same(out, events, frames)
    assert not journal_path(out).exists()


@pytest.mark.filterwarnings("ignore:.*go back in time")
def test_garbage_bytes_are_counted(tmp_path, rng, usb_backend):
    events, _ = scene(rng, n_events=20_000, n_frames=0)
    transfers = split_transfers(StreamEncoder(LAYOUT).encode(events), 4096)
    device = VirtualDavis346(source=TransferListSource(transfers), faults=Faults(garbage_rate=0.002, seed=5))
    with Davis346.open(backend=usb_backend.plug(device), read_bytes=4096, queue_transfers=4096) as camera:
        stop = threading.Event()

        def progress(p):
            if camera.stats.transfers >= len(transfers):
                stop.set()

        record_session(camera, tmp_path / "s.h5", stop_event=stop, progress=progress, progress_interval_s=0.02,
                       duration_s=60)
    with SessionReader(tmp_path / "s.h5") as reader:
        decoder = reader.stats["camera"]["decoder"]
        assert decoder["words"] == sum(len(t) for t in transfers) // 2
        assert decoder["unknown_words"] + decoder["dvs_out_of_range"] + decoder["non_monotonic_timestamps"] > 0
        assert 0 < reader.num_events


def write_paced_replay(path, events, span_us, slice_us=10_000):
    """Write ``events`` (t in [0, span_us) µs) as a replay of one transfer per ``slice_us`` µs of device time.

    Returns:
        ``path``; ``davis-record --fake path`` replays it in real time (``span_us`` µs long).
    """
    encoder = StreamEncoder(LAYOUT)
    bounds = np.searchsorted(events["t"], np.arange(0, span_us + slice_us, slice_us))
    with ReplayWriter(path, ReplayHeader(device_info=LAYOUT.to_dict(), serial="RPLY0002", firmware_version=6,
                                         logic_version=18, logic_patch=1)) as writer:
        for k, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
            writer.write(encoder.encode(events[a:b]), host_time_ns=k * slice_us * 1000)
    return path


def start_fake_recording(tmp_path, rng, n_events: int, span_us: int, stdout) -> tuple[subprocess.Popen, np.ndarray]:
    """Start `davis-record --out tmp_path/s.h5 --fake REPLAY` on a paced replay of ``n_events`` random events over
    ``span_us`` µs; returns the process (stderr piped) and the events."""
    events = random_events(rng, n_events, t0_us=0, span_us=span_us)
    replay = write_paced_replay(tmp_path / "long.replay", events, span_us)
    proc = subprocess.Popen([sys.executable, "-m", "davis_rig.cli.record", "--out", str(tmp_path / "s.h5"),
                             "--fake", str(replay)], stderr=subprocess.PIPE, stdout=stdout)
    return proc, events


def test_kill_9_of_davis_record_then_recover(tmp_path, rng):
    """kill -9 of a `davis-record --fake` subprocess, then `davis-record --recover`: at most ~1 s is lost."""
    import re
    import signal
    import time

    proc, events = start_fake_recording(tmp_path, rng, 1_000_000, 20_000_000, subprocess.DEVNULL)
    out = tmp_path / "s.h5"
    seen = []  # (wall time, events written) from the live progress line
    buffer = b""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        piece = proc.stderr.read1(4096)
        if not piece:
            break
        buffer += piece
        for match in re.finditer(rb"events\s+([\d,]+)", buffer):
            seen.append((time.monotonic(), int(match.group(1).replace(b",", b""))))
        buffer = buffer[buffer.rfind(b"\r") + 1:]
        if seen and seen[-1][0] - seen[0][0] > 2.5:
            break
    proc.send_signal(signal.SIGKILL)
    killed_at = time.monotonic()
    proc.wait(timeout=30)
    assert seen, "davis-record printed no progress"
    assert journal_path(out).exists()
    result = subprocess.run([sys.executable, "-m", "davis_rig.cli.record", "--recover", str(out)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "rebuilt from the journal" in result.stdout
    with SessionReader(out) as reader:
        recovered = reader.events()
    np.testing.assert_array_equal(recovered, events[: len(recovered)])
    written_a_second_before = max((n for t, n in seen if t <= killed_at - 1.0), default=0)
    assert len(recovered) >= written_a_second_before > 0
    assert not journal_path(out).exists()


@pytest.mark.parametrize("signal_name", ["SIGINT", "SIGTERM"])
def test_ctrl_c_of_davis_record_closes_a_complete_file(tmp_path, rng, signal_name):
    """SIGINT (Ctrl-C) or SIGTERM (``kill``, ``timeout``, a service manager) to a `davis-record --fake` subprocess
    mid-recording: exit 0, a complete file, no journal."""
    import re
    import signal
    import time

    proc, events = start_fake_recording(tmp_path, rng, 200_000, 10_000_000, subprocess.PIPE)
    out = tmp_path / "s.h5"
    stderr = b""
    deadline = time.monotonic() + 60
    while b"Mev/s" not in stderr and time.monotonic() < deadline:  # the first live progress line
        piece = proc.stderr.read1(4096)
        if not piece:
            break
        stderr += piece
    assert b"Mev/s" in stderr, f"davis-record printed no progress: {stderr.decode(errors='replace')}"
    proc.send_signal(getattr(signal, signal_name))
    stdout, rest = proc.communicate(timeout=60)
    stderr += rest
    assert proc.returncode == 0, stderr.decode(errors="replace")
    assert b"stopped by stop" in stdout
    reported = int(re.search(rb": (\d+) events", stdout).group(1))
    with SessionReader(out) as reader:
        assert reader.complete and reader.stats["stopped_by"] == "stop"
        recorded = reader.events()
    assert 0 < len(recorded) == reported < len(events)  # stopped well before the 10 s replay ended
    np.testing.assert_array_equal(recorded, events[: len(recorded)])  # everything read before the stop, in order
    assert not journal_path(out).exists()
