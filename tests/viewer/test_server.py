"""The server's security rules and the sessions API: loopback by default, a token when remote, the Host check,
recordings by index only, and no request path ever reaching the file system (checked with an audit hook)."""

from __future__ import annotations

import http.client
import json
import socket
import sys
from pathlib import Path

import numpy as np
import pytest

from davis_rig.evaluation.detections import WindowDetections
from davis_rig.evaluation.physical import EvalSettings
from davis_rig.viewer.detections import StoredDetections
from davis_rig.viewer.recording import RecordingView
from davis_rig.viewer.server import ViewerServer, is_loopback
from davis_rig.viewer.sessions_app import SessionsApp

#: File-system audit events seen while ``_AUDIT["on"]`` (an audit hook cannot be removed, so it is switched).
_AUDIT = {"on": False, "events": []}
_FS_EVENTS = {"open", "os.listdir", "os.scandir", "os.remove", "os.rename", "shutil.copyfile", "glob.glob"}


def _audit(event, args):
    if _AUDIT["on"] and event in _FS_EVENTS:
        _AUDIT["events"].append((event, args[0] if args else None))


sys.addaudithook(_audit)


@pytest.fixture(scope="module")
def views(scene):
    with RecordingView(scene) as view:
        rows = [np.array([[10, 20, 50, 100, 0.9, 1.0, 1.0]], np.float32)] * view.num_windows
        stored = WindowDetections(session=str(scene), name="s", t0_us=view.t0_us, window_us=view.window_us,
                                  window_end_us=view.window_end_us, crop_origin_xy=view.crop_origin_xy,
                                  detections={0.1: rows, 0.25: rows})
        view.detections = StoredDetections(stored, Path("s.detections.npz"), view.window_end_us, view.crop_origin_xy)
        with RecordingView(scene) as bare:
            yield [view, bare]


def request(port: int, path: str, *, method: str = "GET", headers: dict | None = None):
    """``(status, headers, body)`` of one request through http.client (``Host: 127.0.0.1:port`` unless given)."""
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
    try:
        connection.putrequest(method, path, skip_host=headers is not None and "Host" in headers,
                              skip_accept_encoding=True)
        for name, value in (headers or {}).items():
            connection.putheader(name, value)
        connection.endheaders()
        response = connection.getresponse()
        return response.status, dict(response.getheaders()), response.read()
    finally:
        connection.close()


def raw_request(port: int, text: bytes) -> bytes:
    """Send raw bytes, return the raw answer (for request lines http.client would not write)."""
    with socket.create_connection(("127.0.0.1", port), timeout=60) as sock:
        sock.sendall(text)
        chunks = []
        while chunk := sock.recv(65536):
            chunks.append(chunk)
    return b"".join(chunks)


@pytest.mark.parametrize("host, loopback", [("127.0.0.1", True), ("127.5.6.7", True), ("::1", True),
                                            ("[::1]", True), ("localhost", True), ("LocalHost", True),
                                            ("0.0.0.0", False), ("192.168.1.20", False), ("example.com", False),
                                            ("", False), ("::", False)])
def test_is_loopback(host, loopback):
    assert is_loopback(host) is loopback


def test_listening_elsewhere_needs_allow_remote(views):
    app = SessionsApp(views, EvalSettings())
    with pytest.raises(ValueError, match="allow_remote"):
        ViewerServer(app, host="0.0.0.0")
    assert ViewerServer(app).token is None
    remote = ViewerServer(app, host="0.0.0.0", allow_remote=True)
    assert remote.token is not None and len(remote.token) >= 32 and f"?token={remote.token}" in remote.url
    assert ViewerServer(app, host="0.0.0.0", allow_remote=True).token != remote.token  # random each time


def test_the_page_and_its_headers(views):
    with ViewerServer(SessionsApp(views, EvalSettings())) as server:
        status, headers, body = request(server.port, "/")
        assert status == 200 and b"<script src=\"app.js\">" in body and "token" not in server.url
        assert headers["Content-Security-Policy"].startswith("default-src 'none'")
        assert headers["X-Content-Type-Options"] == "nosniff" and headers["Cache-Control"] == "no-store"
        assert headers["Referrer-Policy"] == "no-referrer" and headers["X-Frame-Options"] == "DENY"
        assert "Set-Cookie" not in headers
        status, headers, body = request(server.port, "/app.js")
        assert status == 200 and headers["Content-Type"].startswith("text/javascript") and b"davis-view" in body
        status, headers, body = request(server.port, "/", method="HEAD")
        assert status == 200 and body == b"" and int(headers["Content-Length"]) > 1000
        assert request(server.port, "/api/info", method="POST")[0] == 501
        assert request(server.port, "/api/info", method="DELETE")[0] == 501


def test_loopback_server_answers_only_loopback_host_names(views):
    with ViewerServer(SessionsApp(views, EvalSettings())) as server:
        for host in ("localhost:8346", "127.0.0.1", "[::1]:9000"):
            assert request(server.port, "/api/info", headers={"Host": host})[0] == 200, host
        for host in ("evil.example", "evil.example:8346", "127.0.0.1.evil.example", "192.168.1.2"):
            status, _, body = request(server.port, "/api/info", headers={"Host": host})
            assert status == 403 and b"localhost only" in body, host
        assert b" 403 " in raw_request(server.port, b"GET /api/info HTTP/1.0\r\n\r\n").split(b"\r\n")[0]


def test_remote_server_requires_the_token_on_every_request(views):
    server = ViewerServer(SessionsApp(views, EvalSettings()), host="127.0.0.1", allow_remote=True)
    token = server.token
    with server:
        for path in ("/", "/app.js", "/api/info", "/api/sessions/0/frame?k=0"):
            assert request(server.port, path)[0] == 403, path
            assert request(server.port, path + ("&" if "?" in path else "?") + "token=wrong")[0] == 403, path
        status, headers, _ = request(server.port, f"/?token={token}", headers={"Host": "lab-pc.example:8346"})
        assert status == 200
        cookie = headers["Set-Cookie"]
        assert cookie.startswith(f"davis_view_token_{server.port}={token}") and "HttpOnly" in cookie
        assert "SameSite=Strict" in cookie
        assert request(server.port, "/api/info", headers={"Cookie": cookie.split(";")[0]})[0] == 200
        assert request(server.port, "/api/info", headers={"X-Davis-Token": token})[0] == 200
        assert request(server.port, f"/api/sessions/0/frame?k=0&token={token}")[0] == 200
        assert request(server.port, "/api/info", headers={"Cookie": f"davis_view_token_{server.port}=nope"})[0] == 403


TRAVERSALS = [
    "/../../../../etc/passwd", "/%2e%2e/%2e%2e/etc/passwd", "/app.js/../../etc/passwd", "//etc/passwd",
    "/index.html", "/api/sessions/0/../../../../etc/passwd", "/api/sessions/..%2f..%2fetc%2fpasswd/frame?k=0",
    "/api/sessions/-1", "/api/sessions/2", "/api/sessions/0x0/frame?k=0", "/api/sessions/%D9%A3",
    "/api/sessions/00000000001", "/api/sessions/0/frame/../../1", "/api/sessions/0/nothing",
    "/api/sessions/0/frame?k=0&fmt=../../../etc/passwd", "/api/sessions/0/export?start=0&stop=1&format=../x",
    "/api/sessions/0/frame?k=../../etc", "/api/sessions/0/frame?k=0&layers=../../etc/passwd",
    "/api/" + "a/" * 50, "/etc/passwd",
]


def test_no_request_path_reaches_the_file_system(views, scene):
    with ViewerServer(SessionsApp(views, EvalSettings())) as server:
        for warm_up in ("/", "/api/info", "/api/sessions/0", "/api/sessions/0/frame?k=3",
                        "/api/sessions/0/misses?threshold=0.25"):  # lazy imports open module files once
            assert request(server.port, warm_up)[0] == 200, warm_up
        _AUDIT["events"].clear()
        _AUDIT["on"] = True
        try:
            answers = {path: request(server.port, path)[0] for path in TRAVERSALS}
            answers["absolute-URI"] = int(raw_request(
                server.port, b"GET http://127.0.0.1/../../etc/passwd HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                             b"Connection: close\r\n\r\n").split(b" ")[1])
            answers["frame"] = request(server.port, "/api/sessions/1/frame?k=7&layers=events,labels&fmt=jpg")[0]
        finally:
            _AUDIT["on"] = False
    assert answers.pop("frame") == 200
    assert all(status in (400, 404) for status in answers.values()), answers
    assert _AUDIT["events"] == [], _AUDIT["events"]  # nothing was opened or listed, not even the session


def test_sessions_api_answers_and_refuses_bad_parameters(views):
    with ViewerServer(SessionsApp(views, EvalSettings(seq_len=2), max_export_windows=5)) as server:
        port = server.port
        info = json.loads(request(port, "/api/info")[2])
        assert info["mode"] == "sessions" and len(info["sessions"]) == 2
        assert info["sessions"][0]["detections"]["thresholds"] == [0.1, 0.25]
        assert info["sessions"][1]["detections"] is None
        status, headers, body = request(port, "/api/sessions/0/frame?k=4&threshold=0.1")
        assert status == 200 and headers["Content-Type"] == "image/png" and body[:4] == b"\x89PNG"
        assert headers["X-Window"] == "4"
        for path, message in (("/api/sessions/0/frame", b"k: missing"),
                              ("/api/sessions/0/frame?k=25", b"k: expected 0..24"),
                              ("/api/sessions/0/frame?k=1.5", b"expected an integer"),
                              ("/api/sessions/0/frame?k=1&k=2", b"given 2 times"),
                              ("/api/sessions/0/frame?k=1&threshold=0.3", b"expected one of [0.1, 0.25]"),
                              ("/api/sessions/0/frame?k=1&threshold=nan", b"expected one of"),
                              ("/api/sessions/1/frame?k=1&threshold=0.1", b"no detections"),
                              ("/api/sessions/0/frame?k=1&layers=events,x", b"unknown"),
                              ("/api/sessions/0/frame?k=1&fmt=gif", b"fmt"),
                              ("/api/sessions/1/misses", b"need detections"),
                              ("/api/sessions/0/misses?threshold=0.1&mode=x", b"mode"),
                              ("/api/sessions/0/export?start=0&stop=9", b"at most 5 windows"),
                              ("/api/sessions/0/export?start=3&stop=3", b"stop: expected 4..25"),
                              ("/api/sessions/0/export?start=0&stop=2&format=avi", b"format"),
                              ("/api/sessions/0/frame?" + "&".join(f"f{i}=1" for i in range(40)), b"too many")):
            status, _, body = request(port, path)
            assert status == 400 and message in body, (path, body)
        misses = json.loads(request(port, "/api/sessions/0/misses?threshold=0.25")[2])
        assert misses["windows"] == [] and misses["num_scored"] == 25 and misses["threshold"] == 0.25
        status, headers, body = request(port, "/api/sessions/1/export?start=2&stop=5&format=gif&fps=10")
        assert status == 200 and body[:6] == b"GIF89a"
        assert headers["Content-Disposition"] == 'attachment; filename="scene_2-5.gif"'
