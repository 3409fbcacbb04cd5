"""Data sources of the virtual camera: EncodedSource round trip through pyusb + decoder, slicing, pacing; Faults."""

import numpy as np
import pytest

from davis_rig.device.camera import Davis346
from davis_rig.errors import ProtocolError, ShapeError
from davis_rig.protocol.decoder import DecodedChunk
from davis_rig.protocol.frames import ApsFrame
from davis_rig.protocol.layout import SensorLayout
from davis_rig.types import make_events
from davis_rig.usb.sources import EncodedSource, Faults, _slice_edges
from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend

from tests.helpers.camera_reads import read_until_drained

LAYOUT = SensorLayout.davis346()


def scene(seed=0, n=3000, t_end_us=60_000):
    rng = np.random.default_rng(seed)
    events = make_events(
        np.sort(rng.integers(0, t_end_us, n)), rng.integers(0, 346, n), rng.integers(0, 260, n), rng.integers(0, 2, n)
    )
    frames = [
        ApsFrame(
            pixels=(rng.integers(0, 1024, (260, 346)) << 6).astype(np.uint16),
            t_start_of_frame_us=s,
            t_start_exposure_us=s + 100,
            t_end_exposure_us=s + 4100,
            t_end_of_frame_us=s + 9000,
        )
        for s in (10_500, 40_250)
    ]
    return events, frames


def test_encoded_scene_round_trips_through_the_virtual_camera():
    events, frames = scene()
    source = EncodedSource(events, frames, layout=LAYOUT, transfer_bytes=4096)
    assert source.transfers > 10 and len(source) == source.transfers
    dev = VirtualDavis346(source=source)
    with Davis346.open(backend=VirtualDavis346Backend(dev), sleep=lambda s: None, read_timeout_ms=10) as cam:
        raw = []
        cam.add_raw_listener(raw.append)
        cam.start()
        got = DecodedChunk.concatenate(read_until_drained(cam, dev, raw))
        stats = cam.stats
    assert np.array_equal(got.events, events)
    assert len(got.frames) == 2
    for a, b in zip(got.frames, frames):
        assert np.array_equal(a.pixels, b.pixels)
        assert (a.t_start_of_frame_us, a.t_start_exposure_us, a.t_end_exposure_us, a.t_end_of_frame_us) == (
            b.t_start_of_frame_us, b.t_start_exposure_us, b.t_end_exposure_us, b.t_end_of_frame_us)
    assert stats.bytes == source.total_bytes and stats.decoder.aps_frames_dropped == 0


def test_slices_never_cut_a_frame():
    edges = _slice_edges(0, 10_000, 1000, np.array([[1500, 3500], [7000, 8000]]))
    # 2000, 3000 fall inside (1500, 3500]; 8000 inside (7000, 8000]; 7000 == SOF is kept
    assert edges.tolist() == [1000, 4000, 5000, 6000, 7000, 9000, 10000]


def test_paced_release_times_follow_the_slices():
    events = make_events([0, 500, 1500, 2600], [1, 2, 3, 4], [0, 0, 0, 0], [1, 1, 1, 1])
    source = EncodedSource(events, layout=LAYOUT, slice_us=1000, paced=True)
    releases = []
    while (r := source.peek_release_us()) is not None:
        releases.append(r)
        source.pop()
    assert releases == [1000.0, 2000.0, 2601.0]  # each slice released at its end, relative to the first event


def test_encoded_source_validates_inputs():
    events, _ = scene(n=10)
    with pytest.raises(ShapeError, match="EVENT_DTYPE"):
        EncodedSource(np.zeros(3), layout=LAYOUT)
    with pytest.raises(ProtocolError, match="sorted"):
        EncodedSource(events[::-1].copy(), layout=LAYOUT)
    assert len(EncodedSource(events[:0], layout=LAYOUT)) == 0


def test_faults_validate():
    with pytest.raises(ValueError, match="stall_every must be >= 1"):
        Faults(stall_every=0)
    with pytest.raises(ValueError, match=r"garbage_rate must be in \[0, 1\]"):
        Faults(garbage_rate=1.5)
