"""Damaged replay files: bad host times are paced sanely, a bad header is a FormatError naming the file."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pytest

from davis_rig.errors import FormatError
from davis_rig.usb.replay import MAX_PACING_STEP_NS, ReplayReader, ReplayWriter, pacing_us
from davis_rig.usb.sources import ReplaySource

SAMPLE = Path(__file__).resolve().parents[2] / "recordings" / "sample.davisreplay"


def _copy(path: Path, records: int = 20, header=None, host_time=lambda k, t: t) -> Path:
    """The first records of the committed sample replay, with an optional header and host-time rewrite."""
    with ReplayReader(SAMPLE) as reader:
        sample_header = reader.header
        head = [record for _, record in zip(range(records), reader)]
    with ReplayWriter(path, header or sample_header) as writer:
        t0 = head[0].host_time_ns
        for k, record in enumerate(head):
            writer.write(record.data, host_time(k, t0 + 1_000_000 * k))  # 1 ms apart
    return path


def test_pacing_follows_host_times_and_ignores_damaged_steps():
    ms = 1_000_000
    releases, bad = pacing_us([5 * ms, 6 * ms, 8 * ms])
    np.testing.assert_array_equal(releases, [0.0, 1000.0, 3000.0])
    assert bad == 0
    flipped = (7 * ms) ^ (1 << 63)  # one flipped top bit: beyond int64
    releases, bad = pacing_us([5 * ms, 6 * ms, flipped, 8 * ms, 9 * ms])
    np.testing.assert_array_equal(releases, [0.0, 1000.0, 1000.0, 1000.0, 2000.0])
    assert bad == 2
    releases, bad = pacing_us([0, MAX_PACING_STEP_NS + 1, MAX_PACING_STEP_NS + 2])
    np.testing.assert_array_equal(releases, [0.0, 0.0, 0.001])
    assert bad == 1
    assert pacing_us([])[0].shape == (0,)


def test_a_flipped_host_time_bit_is_paced_with_a_warning(tmp_path):
    path = _copy(tmp_path / "flip.davisreplay", host_time=lambda k, t: t ^ (1 << 50) if k == 10 else t)
    with pytest.warns(RuntimeWarning, match="2 replay records have a host time"):
        source = ReplaySource(path, paced=True)
    assert source.bad_host_times == 2
    releases = []
    while (release := source.peek_release_us()) is not None:
        releases.append(release)
        source.pop()
    assert len(releases) == 20 and max(releases) <= 19_000.0 and releases == sorted(releases)


def test_davis_record_fake_finishes_a_replay_with_a_flipped_host_time(tmp_path, capsys):
    from davis_rig.cli.record import main

    path = _copy(tmp_path / "flip.davisreplay", host_time=lambda k, t: t ^ (1 << 50) if k == 10 else t)
    start = time.monotonic()
    with pytest.warns(RuntimeWarning, match="host time"):
        assert main(["--out", str(tmp_path / "s.h5"), "--fake", str(path), "--quiet", "--duration", "30"]) == 0
    assert time.monotonic() - start < 20  # ended with the replay, not at --duration (nor never)
    assert "stopped by end of replay" in capsys.readouterr().out


@pytest.mark.parametrize("key, value, message", [
    ("dvs_size_columns", 0, "dvs_size_columns: expected 1..4096 px, got 0"),
    ("aps_size_rows", 5000, "aps_size_rows: expected 1..4096 px, got 5000"),
    ("chip_id", "five", "invalid literal"),
])
def test_a_bad_header_layout_is_a_format_error_naming_the_file(tmp_path, key, value, message):
    with ReplayReader(SAMPLE) as reader:
        header = reader.header
    path = _copy(tmp_path / "bad.davisreplay", 2, dataclasses.replace(header, device_info={**header.device_info,
                                                                                          key: value}))
    with pytest.raises(FormatError, match=f"bad.davisreplay: replay header: .*{message}"):
        ReplayReader(path).open()


def test_davis_record_fake_with_zero_columns_exits_4_naming_the_file(tmp_path, capsys):
    from davis_rig.cli.record import main

    with ReplayReader(SAMPLE) as reader:
        header = reader.header
    path = _copy(tmp_path / "cols0.davisreplay", 2,
                 dataclasses.replace(header, device_info={**header.device_info, "dvs_size_columns": 0}))
    assert main(["--out", str(tmp_path / "s.h5"), "--fake", str(path), "--quiet"]) == 4
    assert f"{path}: replay header: dvs_size_columns" in capsys.readouterr().err
    assert not (tmp_path / "s.h5").exists()


def test_a_record_longer_than_the_file_is_a_truncation(tmp_path):
    path = _copy(tmp_path / "a.davisreplay", 3)
    raw = bytearray(path.read_bytes())
    with ReplayReader(path) as reader:
        offset = reader._data_offset
        first = next(iter(reader))
    raw[offset + 8 : offset + 12] = (len(raw)).to_bytes(4, "little")  # the first record claims the whole file
    path.write_bytes(bytes(raw))
    with ReplayReader(path) as reader, pytest.warns(RuntimeWarning, match="incomplete"):
        assert list(reader) == [] and reader.truncated
    assert first.data
