"""The live view's parts: the tap, the tapped camera, RVT's windows on a live stream, the view with a detector."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from davis_rig.errors import ModelFormatError
from davis_rig.events.crop import crop_events
from davis_rig.events.histogram import window_indices
from davis_rig.types import make_events
from davis_rig.viewer.live import LiveApp, LiveTap, LiveView, TappedCamera, WindowCutter, crop_columns
from davis_rig.viewer.server import RequestError

from tests.helpers.eval_data import PERSON_BOX, PERSON_BOX_CROP, moving_blob_events, person_rvt
from tests.helpers.session_data import Chunk


def stream(rng, n=20_000, span_us=400_000, t0_us=3_456):
    t = np.sort(rng.integers(t0_us, t0_us + span_us, n))
    t[::997] = (t[::997] // 50_000) * 50_000  # some events exactly on window boundaries
    t = np.sort(t)
    return make_events(t, rng.integers(0, 346, n), rng.integers(0, 260, n), rng.integers(0, 2, n))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), pieces=st.integers(1, 40))
def test_window_cutter_gives_rvts_windows_of_the_whole_stream(seed, pieces):
    rng = np.random.default_rng(seed)
    events = stream(rng)
    cuts = np.sort(rng.integers(0, len(events), pieces - 1))
    cutter = WindowCutter(50_000)
    windows = [w for part in np.split(events, cuts) for w in cutter.push(part)]
    t0 = int(events["t"][0]) // 1000 * 1000
    ends = t0 + 50_000 * np.arange(1, len(windows) + 1)
    assert [w[0] for w in windows] == ends.tolist()
    assert ends[-1] < events["t"][-1] <= ends[-1] + 50_000  # every window an event has passed, no more
    starts, stops = window_indices(events["t"], ends, 50_000)
    for (end, parts, restart), a, b in zip(windows, starts, stops):
        got = np.concatenate(parts) if parts else events[:0]
        np.testing.assert_array_equal(got, events[a:b])  # both ends inclusive, boundary events in both
        assert restart == (end == ends[0])


def test_window_cutter_restarts_after_a_timestamp_reset():
    rng = np.random.default_rng(1)
    cutter = WindowCutter(50_000)
    assert len(cutter.push(stream(rng, span_us=300_000, t0_us=1_000_000))) == 5
    after = cutter.push(stream(rng, span_us=120_000, t0_us=0))
    assert [w[0] for w in after] == [50_000, 100_000] and [w[2] for w in after] == [True, False]
    assert cutter.push(make_events([], [], [], [])) == []


def test_crop_columns_are_crop_events():
    rng = np.random.default_rng(4)
    events = stream(rng)
    parts = np.array_split(events, 7)
    x, y, t, p = crop_columns(parts, (21, 10))
    expected = crop_events(events, (21, 10))
    for got, name in ((x, "x"), (y, "y"), (t, "t"), (p, "p")):
        np.testing.assert_array_equal(got, expected[name])


def test_tap_drops_the_oldest_chunks_and_counts_them():
    tap = LiveTap(max_chunks=3)
    chunks = [Chunk(events=make_events([i], [0], [0], [1])) for i in range(5)]
    for chunk in chunks:
        tap.offer(chunk)
    assert tap.offered_chunks == 5 and tap.offered_events == 5 and tap.dropped_chunks == 2
    taken = tap.take()
    assert [c is chunks[i] for i, (_, c) in zip(range(2, 5), taken)] == [True, True, True]  # no copies
    assert tap.take() == [] and tap.dropped_chunks == 2


def test_tapped_camera_offers_every_chunk_read_and_forwards_the_rest():
    class Camera:
        running = True

        def __init__(self):
            self.queue = [Chunk(events=make_events([1], [2], [3], [1])), None]

        def read(self, timeout_s=None):
            return self.queue.pop(0)

    tap = LiveTap()
    camera = TappedCamera(Camera(), tap)
    first = camera.read(0.1)
    assert camera.read(0.1) is None and camera.running is True
    assert [c for _, c in tap.take()] == [first]


def test_live_view_runs_the_detector_beside_the_stream_and_draws_its_boxes(tmp_path):
    rng = np.random.default_rng(2)
    events = moving_blob_events(rng, 1_000_000, 200_000, box=PERSON_BOX)
    with LiveView(detector=person_rvt(tmp_path), threshold=0.25, threads=1, fps=50) as view:
        for part in np.array_split(events, 200):  # 5 ms chunks, in real time
            view.tap.offer(Chunk(events=part))
            time.sleep(0.005)
        deadline = time.monotonic() + 30
        while view.windows_scored + view.stats()["detector"]["windows_skipped"] < 19 and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.1)  # a frame rendered with the last boxes
        seq, jpeg = view.latest_frame(-1)
        stats = view.stats()
    assert view.windows_scored + stats["detector"]["windows_skipped"] == 19  # 20 windows, the last not complete
    assert stats["detector"]["latency_ms_median"] is not None and stats["view_dropped_chunks"] == 0
    assert stats["events"] == len(events) and seq >= 1
    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)[..., ::-1].astype(int)
    x1, y1, x2, y2 = (v + o for v, o in zip(PERSON_BOX_CROP, (21, 10, 21, 10)))
    red = (image[..., 0] > 150) & (image[..., 0] > image[..., 1] + 80) & (image[..., 0] > image[..., 2] + 80)
    assert red[y1 + 5:y2 - 5, x1].mean() > 0.8 and red[y1 + 5:y2 - 5, x2 - 1].mean() > 0.8  # the oracle's box


def test_a_bad_detector_fails_before_anything_runs(tmp_path):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not onnx")
    view = LiveView(detector=bad)
    with pytest.raises(ModelFormatError):
        view.__enter__()
    assert view._threads == []


def test_live_app_routes():
    view = LiveView(fps=10)
    app = LiveApp(view)
    assert b'"mode": "live"' in app.handle(["info"], {}).body
    assert app.handle(["live", "frame"], {"after": ["-1"]}).status == 204  # not started: no frame within 1 s
    with view:
        response = app.handle(["live", "frame"], {"after": ["-1"]})
        assert response.status == 200 and response.body[:2] == b"\xff\xd8" and response.headers[0][0] == "X-Frame-Seq"
    stats = app.handle(["live", "stats"], {})
    assert stats.status == 200 and b"render_fps" in stats.body
    with pytest.raises(RequestError):
        app.handle(["live", "nothing"], {})
    with pytest.raises(RequestError, match="after"):
        app.handle(["live", "frame"], {"after": ["x"]})


def _events(rng, n, t0):
    return make_events(np.arange(t0, t0 + n), rng.integers(0, 346, n), rng.integers(0, 260, n), np.ones(n, np.uint8))


def test_event_ring_hands_chunks_over_and_counts_what_was_overwritten():
    from davis_rig.viewer.live_process import EventRing

    rng = np.random.default_rng(5)
    with EventRing(capacity=100, mark_capacity=8) as writer, EventRing(writer.name) as reader:
        first = _events(rng, 30, 0)
        writer.write(first, 1.0)
        writer.write(_events(rng, 30, 30), 2.0)
        got = reader.read()
        assert [t for t, _ in got] == [1.0, 2.0] and reader.dropped_chunks == 0
        np.testing.assert_array_equal(got[0][1], first)
        assert reader.read() == []
        for i in range(5):  # 150 events into a ring of 100: the first two of these chunks are overwritten
            writer.write(_events(rng, 30, 60 + 30 * i), 3.0 + i)
        got = reader.read()
        assert [t for t, _ in got] == [5.0, 6.0, 7.0] and reader.dropped_chunks == 2
        assert [int(c["t"][0]) for _, c in got] == [120, 150, 180]  # wrapped around the ring's end intact
        for i in range(10):  # 10 chunks for 8 marks: 2 marks lost, and the chunk after them has no known start
            writer.write(_events(rng, 5, 210 + 5 * i), 10.0 + i)
        got = reader.read()
        assert [t for t, _ in got] == [13.0 + i for i in range(7)] and reader.dropped_chunks == 5


def test_live_view_process_serves_frames_of_the_chunks_given(tmp_path):
    import json
    import urllib.request

    from davis_rig.viewer.live_process import LiveViewProcess

    rng = np.random.default_rng(6)
    events = moving_blob_events(rng, 600_000, 200_000, box=PERSON_BOX)
    with LiveViewProcess(detector=person_rvt(tmp_path), threshold=0.25, threads=1, fps=20) as view:
        assert view.url.startswith("http://127.0.0.1:")
        for part in np.array_split(events, 60):
            view.tap.offer(Chunk(events=part))
            time.sleep(0.01)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            stats = json.load(urllib.request.urlopen(view.url + "api/live/stats", timeout=10))
            if stats["events"] == len(events) and stats["detector"]["windows_scored"] >= 1:
                break
            time.sleep(0.1)
        with urllib.request.urlopen(view.url + "api/live/frame?after=-1", timeout=10) as response:
            assert response.status == 200 and response.read()[:2] == b"\xff\xd8"
    assert stats["events"] == len(events) and stats["view_dropped_chunks"] == 0
    assert stats["detector"]["latency_ms_median"] is not None
    assert view.tap.offered_events == len(events)


def test_live_view_process_start_errors(tmp_path):
    import socket

    from davis_rig.errors import ConfigError
    from davis_rig.viewer.live_process import LiveViewProcess

    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not onnx")
    with pytest.raises(ModelFormatError, match="bad.onnx"):
        with LiveViewProcess(detector=bad):
            pass
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        with pytest.raises(ConfigError, match="cannot listen"):
            with LiveViewProcess(port=busy.getsockname()[1]):
                pass
