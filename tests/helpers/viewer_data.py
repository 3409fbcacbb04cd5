"""Shared data of the viewer tests: a small session with a known "person", and a headless chromium.

The scene (:func:`write_scene`): 1.2 s; a 60x150 px person box on the sensor that moves 30 px to the right every
200 ms (4 windows of 50 ms); 100 k events/s strictly inside it, ON in its left half and OFF in its right half;
full-sensor APS frames every 40 ms (grey 100 << 6, the person 1000 << 6); a label (crop px) at each frame's
exposure middle. No event lies on a window boundary, so each window shows one position of the person.

The browser (:class:`Chromium`): Debian's chromium driven over the DevTools protocol on a pipe
(``--remote-debugging-pipe``: JSON messages separated by NUL bytes on file descriptors 3 and 4), so no WebSocket
client, chromedriver or selenium is needed. Tests that need it skip with the install line when it is missing.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from davis_rig.types import BBOX_DTYPE, PEDESTRIAN_CLASS_ID, make_events

#: Scene geometry: sensor box of segment s is (X0 + DX s, Y0, X0 + DX s + W, Y0 + H), px; a segment lasts SEG_US.
X0, DX, Y0, W, H = 70, 30, 50, 60, 150
SEG_US, SEGMENTS, RATE_HZ = 200_000, 6, 100_000
CROP = (21, 10)
#: APS frames: start of frame every FRAME_US from FRAME_T0; exposure middle at start + 2100 µs.
FRAME_US, FRAME_T0 = 40_000, 5_000
BACKGROUND, PERSON = 100 << 6, 1000 << 6
#: How chromium is installed on Debian / in CI.
CHROMIUM_INSTALL = "apt-get install -y chromium"


def person_box(t_us: int) -> tuple[int, int, int, int]:
    """Sensor box (x1, y1, x2, y2; x2, y2 exclusive) of the person at time ``t_us``."""
    s = min(int(t_us) // SEG_US, SEGMENTS - 1)
    return X0 + DX * s, Y0, X0 + DX * s + W, Y0 + H


def scene_events(rng: np.random.Generator) -> np.ndarray:
    """The scene's events (time-sorted, none on a multiple of 50 ms)."""
    parts = []
    for s in range(SEGMENTS):
        n = RATE_HZ * SEG_US // 1_000_000
        t = np.sort(rng.integers(s * SEG_US, (s + 1) * SEG_US, n))
        t = t[t % 50_000 != 0]
        x1, y1, x2, y2 = person_box(s * SEG_US)
        x = rng.integers(x1 + 1, x2 - 1, len(t))
        y = rng.integers(y1 + 1, y2 - 1, len(t))
        parts.append(make_events(t, x, y, (x < (x1 + x2) // 2).astype(np.uint8)))
    return np.concatenate(parts)


def scene_frames():
    """The scene's APS frames (``ApsFrame``)."""
    from davis_rig.protocol.frames import ApsFrame
    from davis_rig.types import DAVIS346_HW

    frames = []
    for start in range(FRAME_T0, SEGMENTS * SEG_US - FRAME_US, FRAME_US):
        pixels = np.full(DAVIS346_HW, BACKGROUND, np.uint16)
        x1, y1, x2, y2 = person_box(start + 2100)
        pixels[y1:y2, x1:x2] = PERSON
        frames.append(ApsFrame(pixels, 0, 0, start, start + 100, start + 4100, start + 5100))
    return frames


def scene_labels(frames) -> np.ndarray:
    """One label per frame at its exposure middle, crop px."""
    labels = np.zeros(len(frames), BBOX_DTYPE)
    for i, frame in enumerate(frames):
        x1, y1, x2, y2 = person_box(frame.t_exposure_mid_us)
        labels[i] = (frame.t_exposure_mid_us, x1 - CROP[0], y1 - CROP[1], x2 - x1, y2 - y1, PEDESTRIAN_CLASS_ID, 1.0, 0)
    return labels


def write_scene(path: Path, *, labels: bool = True) -> Path:
    """Write the scene as a session.h5 (:class:`SessionWriter`), with labels unless ``labels=False``."""
    from davis_rig.labelers.session_labels import write_labels
    from davis_rig.session.writer import SessionWriter

    from tests.helpers.session_data import Chunk

    frames = scene_frames()
    with SessionWriter(path) as writer:
        writer.append(Chunk(events=scene_events(np.random.default_rng(5)), frames=frames))
    if labels:
        write_labels(path, scene_labels(frames), {"labeler": "tests/viewer", "crop_origin_x": CROP[0],
                                                  "crop_origin_y": CROP[1]})
    return Path(path)


# --- headless chromium over the DevTools protocol --------------------------------------------------------
#: Run in the child: put the DevTools pipe ends on fds 3 and 4 and exec the browser (argv: fd_in fd_out cmd...).
_TRAMPOLINE = ("import os, sys\n"
               "fd_in, fd_out = int(sys.argv[1]), int(sys.argv[2])\n"
               "os.dup2(fd_in, 3); os.dup2(fd_out, 4); os.close(fd_in); os.close(fd_out)\n"
               "os.execv(sys.argv[3], sys.argv[3:])\n")


def chromium_binary() -> str | None:
    """The chromium executable, or ``None``."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if path := shutil.which(name):
            return path
    return None


class Chromium:
    """A headless chromium with one page, driven over the DevTools protocol on a pipe (a context manager)."""

    def __init__(self, user_data_dir: Path, size=(1600, 1000)):
        import fcntl

        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()
        # the child gets the protocol on fds 3 (commands in) and 4 (answers out): a Python trampoline moves the
        # pipe ends there (first moved above 100 so that one cannot overwrite the other) and execs chromium
        high = [fcntl.fcntl(fd, fcntl.F_DUPFD, 100) for fd in (to_browser_r, from_browser_w)]
        for fd in (to_browser_r, from_browser_w):
            os.close(fd)
        args = [chromium_binary(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                f"--user-data-dir={user_data_dir}", "--remote-debugging-pipe", "--force-device-scale-factor=1",
                f"--window-size={size[0]},{size[1]}", "--hide-scrollbars", "about:blank"]
        self.process = subprocess.Popen(
            [sys.executable, "-c", _TRAMPOLINE, str(high[0]), str(high[1]), *args],
            pass_fds=high, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for fd in high:
            os.close(fd)
        self._buffer = b""
        self._next_id = 0
        target = self.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        self.session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        self.call("Page.enable", session=True)
        self.call("Runtime.enable", session=True)

    def call(self, method: str, params: dict | None = None, *, session: bool = False, timeout_s: float = 60.0):
        """Send one command and return its result (events in between are skipped)."""
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = self.session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout_s
        while True:
            while b"\0" in self._buffer:
                raw, self._buffer = self._buffer.split(b"\0", 1)
                answer = json.loads(raw)
                if answer.get("id") == self._next_id:
                    if "error" in answer:
                        raise RuntimeError(f"{method}: {answer['error']}")
                    return answer["result"]
            if time.monotonic() > deadline:
                raise TimeoutError(f"{method}: no answer in {timeout_s} s")
            chunk = os.read(self._from_browser, 1 << 20)
            if not chunk:
                raise RuntimeError("chromium closed the DevTools pipe")
            self._buffer += chunk

    def navigate(self, url: str) -> None:
        """Open ``url`` in the page."""
        self.call("Page.navigate", {"url": url}, session=True)

    def evaluate(self, expression: str):
        """The value of a JavaScript expression in the page (promises awaited)."""
        result = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                                "awaitPromise": True}, session=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def wait_for(self, expression: str, timeout_s: float = 30.0):
        """Poll a JavaScript expression until it is truthy; return its value."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            value = self.evaluate(expression)
            if value:
                return value
            time.sleep(0.05)
        raise TimeoutError(f"{expression} stayed falsy for {timeout_s} s")

    def screenshot(self) -> np.ndarray:
        """The page as RGB uint8 [H, W, 3]."""
        import cv2

        data = base64.b64decode(self.call("Page.captureScreenshot", {"format": "png"}, session=True)["data"])
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[..., ::-1].copy()

    def __enter__(self) -> "Chromium":
        return self

    def __exit__(self, *exc_info) -> None:
        self.process.terminate()
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        os.close(self._to_browser)
        os.close(self._from_browser)
