"""``davis-record --view``: the page shows the recording while it runs, and the file is the same as without it."""

from __future__ import annotations

import json
import socket
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np

from davis_rig.cli import record
from davis_rig.session import SessionReader

REPLAY = Path(__file__).resolve().parents[2] / "recordings" / "sample.davisreplay"


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _get(url: str):
    with urllib.request.urlopen(url, timeout=5) as response:
        return response.status, dict(response.headers), response.read()


def test_record_with_the_live_view_records_the_same_file(tmp_path, capsys):
    port = _free_port()
    plain, viewed = tmp_path / "plain.h5", tmp_path / "viewed.h5"
    assert record.main(["--out", str(plain), "--fake", str(REPLAY), "-q"]) == 0
    seen = {"frames": 0, "stats": None}
    done = threading.Event()

    def poll():  # the page's requests while the recording runs (the recording runs in the main thread: SIGINT)
        after = -1
        while not done.is_set():
            try:
                status, headers, body = _get(f"http://127.0.0.1:{port}/api/live/frame?after={after}")
                if status == 200:
                    after = int(headers["X-Frame-Seq"])
                    seen["frames"] += body[:2] == b"\xff\xd8"
                seen["stats"] = json.loads(_get(f"http://127.0.0.1:{port}/api/live/stats")[2])
            except (urllib.error.URLError, ConnectionError):
                time.sleep(0.02)  # not listening yet, or already closed

    poller = threading.Thread(target=poll, daemon=True)
    poller.start()
    try:
        code = record.main(["--out", str(viewed), "--fake", str(REPLAY), "-q", "--view", "--view-port", str(port),
                            "--threads", "1"])
    finally:
        done.set()
        poller.join()
    assert code == 0
    out = capsys.readouterr().out
    assert "dropped transfers: 0" in out
    assert seen["frames"] >= 2 and seen["stats"]["detector"]["model"] == "rvt_default.onnx"
    assert seen["stats"]["events"] > 0
    with SessionReader(plain) as a, SessionReader(viewed) as b:
        assert a.num_events == b.num_events > 0 and len(a.frames) == len(b.frames)
        np.testing.assert_array_equal(a.events(), b.events())


def test_live_view_options_need_view(capsys):
    assert record.main(["--out", "x.h5", "--view-port", "9000"]) == 2
    assert "argument --view-port: only with --view" in capsys.readouterr().err
    assert record.main(["--out", "x.h5", "--view", "--view-host", "10.0.0.1"]) == 2
    assert "argument --view-host: 10.0.0.1 is not this machine's loopback" in capsys.readouterr().err
    assert record.main(["--out", "x.h5", "--view", "--no-detector", "--detector", "m.onnx"]) == 2
    assert "argument --no-detector: not allowed with --detector" in capsys.readouterr().err
    assert record.main(["--out", "x.h5", "--int8"]) == 2
    assert "argument --int8: only with --view" in capsys.readouterr().err
    assert record.main(["--out", "x.h5", "--view", "--int8", "--detector", "m.onnx"]) == 2
    assert "argument --int8: not allowed with argument --detector" in capsys.readouterr().err
