"""The page in a real headless browser (Debian's chromium): open a recording, play, pause, scrub, jump to a miss,
and check on screenshots that the person's box and events are where the session says; the live page too."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np

from davis_rig.evaluation.detections import WindowDetections
from davis_rig.evaluation.physical import EvalSettings
from davis_rig.viewer.detections import StoredDetections
from davis_rig.viewer.live import LiveApp, LiveView
from davis_rig.viewer.recording import RecordingView
from davis_rig.viewer.render import DETECTION_RGB, GAP_PX, LABEL_RGB, OFF_RGB, ON_RGB
from davis_rig.viewer.server import ViewerServer
from davis_rig.viewer.sessions_app import SessionsApp

from tests.helpers.viewer_data import BACKGROUND, CROP, H, PERSON, SEG_US, W, person_box

SCALE = 2
MISSED = range(8, 12)  # windows without detections: 10 and 11 are labelled (after the first 0.5 s) -> one sequence
SHIFT_PX = 4  # detections sit 4 px right of the labels, so both outlines show


def oracle_detections(view: RecordingView) -> StoredDetections:
    """Detections at the person (shifted by SHIFT_PX) in every window but MISSED, score 0.9 (threshold 0.25)."""
    rows = []
    for k, end in enumerate(view.window_end_us.tolist()):
        if k in MISSED:
            rows.append(None)
            continue
        x1, y1, x2, y2 = person_box(end - 1)
        rows.append(np.array([[x1 - CROP[0] + SHIFT_PX, y1 - CROP[1], x2 - CROP[0] + SHIFT_PX, y2 - CROP[1], 0.9, 1.0,
                               1.0]], np.float32))
    stored = WindowDetections(session=str(view.path), name="scene", t0_us=view.t0_us, window_us=view.window_us,
                              window_end_us=view.window_end_us, crop_origin_xy=CROP, detections={0.25: rows})
    return StoredDetections(stored, Path("oracle.detections.npz"), view.window_end_us, view.crop_origin_xy)


def shown_image(browser) -> np.ndarray:
    """The displayed view, from a screenshot, at 1 px per image pixel (every SCALE-th screen pixel)."""
    rect = json.loads(browser.evaluate("JSON.stringify(document.getElementById('view').getBoundingClientRect())"))
    shot = browser.screenshot()
    left, top, width, height = (int(round(rect[key])) for key in ("left", "top", "width", "height"))
    assert (width, height) == (SCALE * (2 * 346 + GAP_PX), SCALE * 260)
    return shot[top:top + height:SCALE, left:left + width:SCALE]


def wait_window(browser, k: int) -> None:
    browser.wait_for(f"(() => {{ const v = document.getElementById('view'); return v !== null && v.dataset.window === '{k}' && "
                     "v.complete && v.naturalWidth > 0; })()")


def scrub(browser, k: int) -> None:
    """Move the scrubber to window ``k`` as a user's drag does (value, then an ``input`` event)."""
    browser.evaluate(f"(() => {{ const s = document.getElementById('scrub'); s.value = {k}; "
                     "s.dispatchEvent(new Event('input')); })()")


def test_session_page_plays_scrubs_jumps_to_a_miss_and_shows_the_person_where_the_session_says(scene, browser):
    with RecordingView(scene) as view:
        view.detections = oracle_detections(view)
        app = SessionsApp([view], EvalSettings(seq_len=2))
        with ViewerServer(app, port=0) as server:
            browser.navigate(f"{server.url}?scale={SCALE}")
            wait_window(browser, 0)
            # play: the shown window advances by itself; pause stops it
            browser.evaluate("document.getElementById('play').click()")
            browser.wait_for("parseInt(document.getElementById('view').dataset.window, 10) >= 3", timeout_s=30)
            browser.evaluate("document.getElementById('play').click()")
            assert browser.evaluate("document.getElementById('play').textContent") == "play"
            # the misses: windows 10 and 11 (labelled, no box), one sequence of 2 = one attack success
            browser.wait_for("document.getElementById('missinfo').textContent.includes('sequences')")
            info = browser.evaluate("document.getElementById('missinfo').textContent")
            assert info.startswith("2 of 13 labelled windows missed; 1 of 6 sequences fully missed"), info
            scrub(browser, 2)
            wait_window(browser, 2)
            browser.evaluate("document.getElementById('nextmiss').click()")
            wait_window(browser, 10)
            missed = shown_image(browser)
            expected = view.render(10, threshold=0.25)
            # scrub to a detected window
            scrub(browser, 13)
            wait_window(browser, 13)
            detected = shown_image(browser)
            expected_detected = view.render(13, threshold=0.25)
    # the browser shows the server's pixels exactly (PNG, nearest-neighbour scaling)
    np.testing.assert_array_equal(missed, expected)
    np.testing.assert_array_equal(detected, expected_detected)
    # and those pixels say what the session says: window 10 = [500, 550] ms -> the person of segment 2
    x1, y1, x2, y2 = person_box(525_000)
    for offset in (0, 346 + GAP_PX):  # event panel, APS panel
        panel = missed[:, offset:offset + 346]
        assert (panel[y1:y2, x1] == LABEL_RGB).all() and (panel[y1:y2, x2 - 1] == LABEL_RGB).all()
        assert (panel[y1, x1:x2] == LABEL_RGB).all() and (panel[y2 - 1, x1:x2] == LABEL_RGB).all()
        assert not (panel == DETECTION_RGB).all(axis=2).any()  # a missed window: no RVT box
    events = missed[:, :346]
    on, off = (events == ON_RGB).all(axis=2), (events == OFF_RGB).all(axis=2)
    rows, cols = np.nonzero(on | off)
    assert len(rows) > 1000
    assert rows.min() > y1 and rows.max() < y2 - 1 and cols.min() > x1 and cols.max() < x2 - 1
    assert np.nonzero(on)[1].max() < (x1 + x2) // 2 <= np.nonzero(off)[1].min()  # ON left half, OFF right half
    aps = missed[:, 346 + GAP_PX:]
    assert (aps[y1 + 1:y2 - 1, x1 + 1:x2 - 1] == PERSON >> 8).all() and (aps[y1 - 5, x1:x2] == BACKGROUND >> 8).all()
    # window 13 = [650, 700] ms: segment 3, with the RVT box SHIFT_PX to the right of the label
    x1, y1, x2, y2 = person_box(3 * SEG_US)
    panel = detected[:, :346]
    assert (panel[y1 + 1:y2 - 1, x1] == LABEL_RGB).all()
    assert (panel[y1 + 1:y2 - 1, x2 - 1 + SHIFT_PX] == DETECTION_RGB).all()
    assert (x2 - x1, y2 - y1) == (W, H)


def test_live_page_shows_new_frames_and_stats(browser):
    from tests.helpers.session_data import Chunk

    from davis_rig.types import make_events

    rng = np.random.default_rng(3)
    x1, y1, x2, y2 = person_box(0)
    stop = threading.Event()
    with LiveView(fps=20) as live:
        def feed():
            t = 0
            while not stop.is_set():
                n = 2000
                times = np.sort(rng.integers(t, t + 10_000, n))
                live.tap.offer(Chunk(events=make_events(times, rng.integers(x1 + 1, x2 - 1, n),
                                                        rng.integers(y1 + 1, y2 - 1, n), np.ones(n, np.uint8))))
                t += 10_000
                time.sleep(0.01)

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        try:
            with ViewerServer(LiveApp(live), port=0) as server:
                browser.navigate(f"{server.url}?scale={SCALE}")
                browser.wait_for("parseInt(document.getElementById('view')?.dataset.seq || '-1', 10) >= 5")
                browser.wait_for("document.getElementById('stats').textContent.includes('Mev/s')")
                stats = browser.evaluate("document.getElementById('stats').textContent")
                image = shown_image(browser)
        finally:
            stop.set()
            feeder.join()
    assert "dropped transfers" in stats and "view skipped chunks: 0" in stats
    # JPEG: the events are bright inside the person's box and the background outside stays dark
    events = image[:, :346].astype(int).sum(axis=2)
    inside = events[y1 + 1:y2 - 1, x1 + 1:x2 - 1]
    assert (inside > 600).mean() > 0.5 and events[y1:y2, x2 + 10:x2 + 40].max() < 150
