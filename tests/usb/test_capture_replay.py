"""tools/capture_replay.py: capture through the real transport (virtual camera), then replay and decode identically."""

import numpy as np

from davis_rig.device.camera import Davis346
from davis_rig.protocol.decoder import DecodedChunk
from davis_rig.protocol.layout import SensorLayout
from davis_rig.types import make_events
from davis_rig.usb.replay import ReplayReader
from davis_rig.usb.sources import EncodedSource
from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend

from tests.helpers.camera_reads import read_until_drained


def test_capture_then_replay_gives_the_same_events(tmp_path, load_tool):
    tool = load_tool("capture_replay")
    rng = np.random.default_rng(5)
    n = 5000
    events = make_events(np.sort(rng.integers(0, 50_000, n)), rng.integers(0, 346, n), rng.integers(0, 260, n), rng.integers(0, 2, n))
    camera = VirtualDavis346(serial="CAP00001", source=EncodedSource(events, layout=SensorLayout.davis346()))
    path = tmp_path / "scene.davisreplay"
    counts = tool.capture_replay(
        str(path), duration_s=60.0, backend=VirtualDavis346Backend(camera), exposure_us=8000, sleep=lambda s: None,
        until=lambda: camera.drained,
    )
    assert counts["events"] == n and counts["dropped_transfers"] == 0 and counts["records"] == counts["transfers"]
    with ReplayReader(path) as reader:
        header = reader.header
        records = reader.records()
    assert header.serial == "CAP00001" and header.device_info == SensorLayout.davis346().to_dict()
    assert header.extra["exposure_us"] == 8000 and header.extra["producers"]["imu"] is False
    assert sum(len(r.data) for r in records) == counts["bytes"] == camera.bytes_served

    replay = VirtualDavis346.from_replay(path)
    with Davis346.open(backend=VirtualDavis346Backend(replay), sleep=lambda s: None, read_timeout_ms=10) as cam:
        assert cam.info.serial == "CAP00001"
        raw = []
        cam.add_raw_listener(raw.append)
        cam.start()
        got = DecodedChunk.concatenate(read_until_drained(cam, replay, raw))
    assert np.array_equal(got.events, events)


def test_main_reports_errors_with_exit_code(tmp_path, capsys, monkeypatch, load_tool):
    tool = load_tool("capture_replay")

    def fail(*args, **kwargs):
        from davis_rig.errors import DeviceNotFoundError

        raise DeviceNotFoundError("no DAVIS camera found")

    monkeypatch.setattr(tool, "capture_replay", fail)
    assert tool.main([str(tmp_path / "x.davisreplay"), "--duration-s", "0.1"]) == 3  # the camera/USB exit code
    assert "capture_replay.py: error: no DAVIS camera found" in capsys.readouterr().err
