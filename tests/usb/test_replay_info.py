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
