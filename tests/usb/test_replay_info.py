"""describe_replay: a replay's camera, transfers and decoded counts, on the bundled replay and damaged copies."""

from __future__ import annotations

from pathlib import Path

import pytest

from davis_rig.errors import FormatError
from davis_rig.session import SessionReader
from davis_rig.usb.replay_info import describe_replay

RECORDINGS = Path(__file__).resolve().parents[2] / "recordings"


def test_bundled_replay_decodes_to_the_bundled_session():
    """recordings/sample.h5 was recorded from recordings/sample.davisreplay: the counts must agree."""
    info = describe_replay(RECORDINGS / "sample.davisreplay")
    with SessionReader(RECORDINGS / "sample.h5") as reader:
        events = reader.events()
        assert (info.events, info.frames, info.specials) == (len(events), len(reader.frames), len(reader.specials()))
    assert (info.t_first_event_us, info.t_last_event_us) == (int(events["t"][0]), int(events["t"][-1]))
    assert info.serial == "SYNTH001" and info.sensor_hw == (260, 346) and not info.truncated
    assert info.transfers == 535 and info.decoder_counters == {}
    assert info.event_rate_mean_hz == pytest.approx(len(events) * 1e6 / info.duration_us)
    assert info.header_extra["tool"] == "tools/capture_replay.py"


def test_truncated_replay_is_reported_not_raised(tmp_path):
    data = (RECORDINGS / "sample.davisreplay").read_bytes()
    (tmp_path / "cut.davisreplay").write_bytes(data[: len(data) // 2])
    info = describe_replay(tmp_path / "cut.davisreplay")
    assert info.truncated and 0 < info.transfers < 535


@pytest.mark.parametrize("content", [b"", b"DAVISRPL\x01\x00\xff\xff\x00\x00{", b"not a replay at all"])
def test_damaged_replays_raise_format_error(tmp_path, content):
    (tmp_path / "bad.davisreplay").write_bytes(content)
    with pytest.raises(FormatError, match="bad.davisreplay"):
        describe_replay(tmp_path / "bad.davisreplay")


def test_missing_replay(tmp_path):
    with pytest.raises(FormatError, match="no such replay file"):
        describe_replay(tmp_path / "none.davisreplay")


@pytest.mark.parametrize("flipped", [0, 10, 19])
def test_a_damaged_host_time_does_not_make_the_host_duration_negative_or_huge(tmp_path, flipped):
    from davis_rig.usb.replay import ReplayReader, ReplayWriter

    with ReplayReader(RECORDINGS / "sample.davisreplay") as reader:
        header, head = reader.header, [record for _, record in zip(range(20), reader)]
    path = tmp_path / "flip.davisreplay"
    with ReplayWriter(path, header) as writer:
        for k, record in enumerate(head):
            t_ns = 5_000_000_000 + 1_000_000 * k  # 1 ms apart
            writer.write(record.data, t_ns ^ (1 << 63) if k == flipped else t_ns)  # one flipped top bit
    # the damaged record's steps count 0, as when pacing the replay (davis_rig.usb.replay.pacing_us)
    expected_ms = 19 - (1 if flipped in (0, 19) else 2)
    assert describe_replay(path).host_duration_us == expected_ms * 1000
