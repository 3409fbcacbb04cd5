"""The live view's parts: the tap, the tapped camera, RVT's windows on a live stream, the view with a detector."""

from __future__ import annotations

import sys
import time

import cv2
import numpy as np
import pytest

from davis_rig.errors import ModelFormatError
from davis_rig.types import make_events
from davis_rig.viewer.live import LiveApp, LiveTap, LiveView, Mailbox, TappedCamera, WindowDetector
from davis_rig.viewer.live_windows import join_events
from davis_rig.viewer.server import RequestError

from tests.helpers.eval_data import PERSON_BOX, PERSON_BOX_CROP, moving_blob_events, person_rvt
from tests.helpers.session_data import Chunk


def test_the_mailbox_keeps_only_the_newest_item_and_counts_the_replaced():
    box = Mailbox()
    assert box.get(0.01) is None
    for item in ("a", "b", "c"):
        box.put(item)
    assert box.get(0.01) == "c" and box.replaced == 2 and box.get(0.01) is None
    box.put("d")
    assert box.get(0.01) == "d" and box.replaced == 2
    box.put("e")
    box.put("f", merge=lambda replaced, item: replaced + item)  # what the replaced item carried is kept
    assert box.get(0.01) == "ef" and box.replaced == 3


def test_the_detector_carries_its_states_over_skipped_windows_and_resets_them_at_a_new_sequence():
    class Runner:
        """Records the states each step got; the new states name the step."""

        def __init__(self):
            self.given = []

        def step(self, hist, states):
            self.given.append(states)
            return np.zeros((1, 0, 7), np.float32), f"after {int(hist[0, 0, 0, 0])}"

    runner = Runner()
    detector = WindowDetector(runner, threshold=0.1)
    for window, starts in ((0, True), (1, False), (4, False), (5, True), (6, False)):  # windows 2, 3 skipped
        detector.step(np.full((20, 240, 304), window, np.uint8), starts)
    assert runner.given == [None, "after 0", "after 1", None, "after 5"]
    assert detector.boxes(np.zeros((1, 0, 7), np.float32)).shape == (0, 7)


def test_tap_drops_the_oldest_chunks_and_counts_them():
    tap = LiveTap(max_chunks=3)
    chunks = [Chunk(events=make_events([i], [0], [0], [1])) for i in range(5)]
    for chunk in chunks:
        tap.offer(chunk)
    assert tap.offered_chunks == 5 and tap.offered_events == 5 and tap.dropped_chunks == 2
    taken = tap.take()
    assert [c is chunks[i] for i, (_, c) in zip(range(2, 5), taken)] == [True, True, True]  # no copies
    assert tap.take() == [] and tap.dropped_chunks == 2


def test_each_reader_of_the_tap_gets_every_chunk_and_one_falling_behind_holds_up_no_other():
    tap = LiveTap(max_chunks=2, readers=2)
    chunks = [Chunk(events=make_events([i], [0], [0], [1])) for i in range(3)]
    tap.offer(chunks[0])
    assert [c for _, c in tap.take(0)] == [chunks[0]]
    tap.offer(chunks[1])
    tap.offer(chunks[2])
    assert [c for _, c in tap.take(0)] == chunks[1:] and tap.dropped_chunks == 1  # reader 1 lost the first
    assert [c for _, c in tap.take(1)] == chunks[1:] and tap.take(0) == []


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
        assert np.shares_memory(join_events([c for _, c in got]), got[0][1])  # one block: joined without a copy
        for i in range(10):  # 10 chunks for 8 marks: 2 marks lost, and the chunk after them has no known start
            writer.write(_events(rng, 5, 210 + 5 * i), 10.0 + i)
        got = reader.read()
        assert [t for t, _ in got] == [13.0 + i for i in range(7)] and reader.dropped_chunks == 5


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="page-fault counts from getrusage (Linux)")
def test_the_event_ring_is_allocated_before_the_recording_writes_into_it():
    import resource

    from davis_rig.viewer.live_process import EventRing

    events = _events(np.random.default_rng(8), 1 << 14, 0)
    with EventRing(capacity=1 << 16, mark_capacity=64) as ring:  # 832 KiB: 208 pages
        faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for i in range(4):  # one lap
            ring.write(events, float(i))
        assert resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults < 20


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_the_view_process_allocator_keeps_freed_blocks():
    import platform

    from davis_rig.viewer.live_process import retain_freed_memory

    assert retain_freed_memory() is (platform.libc_ver()[0] == "glibc")


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


def test_the_detector_leaves_the_recording_a_core_on_small_machines():
    from davis_rig.viewer.live import LiveView, default_detector_threads

    assert [default_detector_threads(n) for n in (1, 2, 3, 16)] == [1, 1, 2, 2]
    assert LiveView(detector=None).threads == default_detector_threads()
    assert LiveView(detector=None, threads=3).threads == 3
