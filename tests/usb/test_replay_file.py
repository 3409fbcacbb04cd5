"""Replay file format: writer/reader round trip, truncation, errors, and serving a replay through pyusb."""

import json
import struct
from pathlib import Path

import pytest

from davis_rig.errors import FormatError
from davis_rig.usb.replay import REPLAY_MAGIC, ReplayHeader, ReplayReader, ReplayRecord, ReplayWriter
from davis_rig.usb.sources import ReplaySource
from davis_rig.usb.transport import UsbTransport
from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend

VECTORS = json.loads((Path(__file__).resolve().parents[1] / "fixtures" / "davis346_test_vectors.json").read_text())["vectors"]

INFO = VECTORS[0]["device_info"]
HEADER = ReplayHeader(
    device_info=INFO,
    serial="REC00001",
    firmware_version=6,
    logic_version=18,
    logic_patch=1,
    clocks={"logic_mhz": 104, "adc_mhz": 30, "usb_mhz": 80, "deviation": 1000},
    extra={"tool": "test", "features": {"aps_has_global_shutter": True}},
)
TRANSFERS = [b"\x64\x80\x0a\x10\x14\x30", b"\x01", b"", bytes(range(256)) * 40]


def _write(path):
    with ReplayWriter(path, HEADER) as w:
        for i, data in enumerate(TRANSFERS):
            w.write(data, host_time_ns=1_000_000 * i)
    return path


def test_round_trip(tmp_path):
    path = _write(tmp_path / "a.davisreplay")
    with ReplayReader(path) as r:
        assert r.header == HEADER
        assert r.records() == [ReplayRecord(1_000_000 * i, d) for i, d in enumerate(TRANSFERS)]
        assert not r.truncated
    raw = path.read_bytes()
    assert raw[:8] == REPLAY_MAGIC and struct.unpack_from("<H", raw, 8)[0] == 1


def test_truncated_last_record_is_skipped_with_warning(tmp_path):
    path = _write(tmp_path / "a.davisreplay")
    path.write_bytes(path.read_bytes()[:-10])
    with ReplayReader(path) as r, pytest.warns(RuntimeWarning, match="incomplete"):
        records = r.records()
    assert [rec.data for rec in records] == TRANSFERS[:3] and r.truncated


@pytest.mark.parametrize(
    "blob,message",
    [
        (b"NOTAFILE" + b"\x00" * 6, "not a replay file"),
        (REPLAY_MAGIC + struct.pack("<HI", 2, 0), "version 2 not supported, expected 1"),
        (REPLAY_MAGIC + struct.pack("<HI", 1, 3) + b"{x}", "not valid UTF-8 JSON"),
        (REPLAY_MAGIC + struct.pack("<HI", 1, 2) + b"[]", "'device_info'"),
        (b"DAV", "only 3 bytes"),
    ],
)
def test_malformed_files(tmp_path, blob, message):
    path = tmp_path / "bad"
    path.write_bytes(blob)
    with pytest.raises(FormatError, match=message):
        ReplayReader(path).open()


def test_virtual_camera_from_replay_serves_the_recorded_transfers(tmp_path):
    path = _write(tmp_path / "a.davisreplay")
    dev = VirtualDavis346.from_replay(path)
    assert dev.serial == "REC00001" and dev.clocks.usb_mhz == 80 and dev.features.aps_has_global_shutter
    with UsbTransport.open(backend=VirtualDavis346Backend(dev)) as t:
        for module, param in ((9, 0), (0, 0), (1, 3)):
            t.config_write(module, param, 1)
        got = []
        while (data := t.read_data(65536, 20)) is not None:
            got.append(data)
    assert got == TRANSFERS


def test_paced_replay_source_uses_host_times(tmp_path):
    path = _write(tmp_path / "a.davisreplay")
    src = ReplaySource(path, paced=True)
    releases = []
    while (r := src.peek_release_us()) is not None:
        releases.append(r)
        src.pop()
    assert releases == [0.0, 1000.0, 2000.0, 3000.0]


def test_a_replay_source_reads_transfers_when_served_so_its_memory_does_not_grow_with_the_file(tmp_path):
    import tracemalloc

    path = tmp_path / "long.davisreplay"
    payload = bytes(range(256)) * 64  # 16 KiB per transfer, 2000 transfers: 32 MiB of payload
    with ReplayWriter(path, HEADER) as w:
        for i in range(2000):
            w.write(payload[i % 256:] + payload[:i % 256], host_time_ns=1_000_000 * i)
    tracemalloc.start()
    try:
        source = ReplaySource(path, paced=True)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 2 * 2**20  # the index of 2000 records, not their 32 MiB
    assert len(source) == 2000 and source.peek_release_us() == 0.0
    with ReplayReader(path) as r:
        for k, record in enumerate(r):
            assert source.peek_release_us() == 1000.0 * k
            assert source.pop() == record.data
    assert len(source) == 0 and source.peek_release_us() is None
    with pytest.raises(IndexError):
        source.pop()


def test_a_truncated_replay_source_serves_the_complete_records_with_a_warning(tmp_path):
    path = _write(tmp_path / "a.davisreplay")
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.warns(RuntimeWarning, match="incomplete"):
        source = ReplaySource(path)
    assert source.truncated and [source.pop() for _ in range(len(source))] == TRANSFERS[:3]


def test_a_replay_cut_while_being_served_is_a_format_error_naming_the_file(tmp_path):
    path = _write(tmp_path / "a.davisreplay")
    source = ReplaySource(path)
    with open(path, "r+b") as f:
        f.truncate(path.stat().st_size - len(TRANSFERS[-1]) // 2)
    assert [source.pop() for _ in range(3)] == TRANSFERS[:3]
    with pytest.raises(FormatError, match=r"a\.davisreplay: record 3: 5120 of 10240 bytes left"):
        source.pop()
