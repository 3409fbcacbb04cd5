"""The viewer's local web server (stdlib ``http.server``): the page, and the frames and JSON of one app.

Why a web page: it works the same on a laptop, on a headless lab machine over SSH port forwarding
(``ssh -L 8346:localhost:8346 lab``) and in a CI browser; the page is two small files shipped in the package
(``davis_rig/assets/viewer/``), nothing downloads at run time, and no GUI toolkit is needed.

Security rules (tested in ``tests/viewer/test_server.py``):

- the server binds 127.0.0.1 unless told otherwise; any other address needs ``allow_remote=True``
  (``--host 0.0.0.0 --allow-remote``), and then a random token (:func:`secrets.token_urlsafe`) is required on
  every request (``?token=...``, the ``X-Davis-Token`` header, or the ``HttpOnly`` ``SameSite=Strict`` cookie the
  page receives with the token), compared in constant time;
- on loopback, requests must name a loopback host (``Host: localhost:...``/``127.0.0.1``/``[::1]``), so a web
  page elsewhere cannot reach the viewer through DNS rebinding;
- requests name sessions by index: no part of a request ever reaches the file system (the page's two files are
  read into memory when the server is made; the API routes parse integers and fixed words only);
- GET and HEAD only; responses are ``no-store``, ``nosniff``, ``no-referrer`` (the token is in the URL), not
  framable, and the page runs under a Content-Security-Policy that allows only its own origin.
"""

from __future__ import annotations

import hmac
import ipaddress
import json
import math
import secrets
import threading
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, quote, urlsplit

from davis_rig.errors import DavisRigError

__all__ = ["RequestError", "Response", "ViewerServer", "float_param", "int_param", "is_loopback", "json_response",
           "layers_param"]

#: The page's files, read from ``davis_rig/assets/viewer/`` when a server is made: URL path -> (file, type).
ASSETS = {"/": ("index.html", "text/html; charset=utf-8"), "/app.js": ("app.js", "text/javascript; charset=utf-8")}
#: Content-Security-Policy of every response: the page may load only from its own origin.
CSP = ("default-src 'none'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' blob:; "
       "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'")
#: Query fields accepted per request (parse_qs refuses more).
MAX_QUERY_FIELDS = 32


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or an IP address, maybe in brackets) is this machine's loopback."""
    host = host.strip().strip("[]").lower()
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _host_header_name(value: str | None) -> str:
    """The host name of a ``Host`` header (without the port)."""
    if not value:
        return ""
    try:
        return urlsplit(f"//{value.strip()}").hostname or ""
    except ValueError:
        return ""


def _cookie(header: str | None, name: str) -> str:
    """The value of cookie ``name`` in a ``Cookie`` header, or ``""``."""
    from http.cookies import CookieError, SimpleCookie

    if not header:
        return ""
    try:
        morsel = SimpleCookie(header).get(name)
    except CookieError:
        return ""
    return morsel.value if morsel is not None else ""


@dataclass(frozen=True)
class Response:
    """One HTTP response: status, body bytes, content type and extra headers (name, value)."""

    status: int
    body: bytes
    content_type: str
    headers: tuple = ()


class RequestError(Exception):
    """A request the app cannot answer: ``status`` (400, 404, ...) and a message for the client."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = int(status)
        self.message = message


def json_response(obj, status: int = 200) -> Response:
    """A JSON response (NaN refused: apps send ``null``)."""
    return Response(status, json.dumps(obj, allow_nan=False).encode(), "application/json")


def _one(params: dict, name: str) -> str | None:
    values = params.get(name)
    if not values:
        return None
    if len(values) != 1:
        raise RequestError(400, f"{name}: given {len(values)} times")
    return values[0]


def int_param(params: dict, name: str, lo: int, hi: int, default: int | None = None) -> int:
    """An integer query field in ``[lo, hi]`` (``default`` when absent).

    Raises:
        RequestError: 400 when it is missing without a default, not an integer, or out of range.
    """
    text = _one(params, name)
    if text is None:
        if default is None:
            raise RequestError(400, f"{name}: missing")
        return default
    if not (text.isascii() and text.lstrip("-").isdigit() and len(text) <= 12):
        raise RequestError(400, f"{name}: expected an integer, got {text[:20]!r}")
    value = int(text)
    if not lo <= value <= hi:
        raise RequestError(400, f"{name}: expected {lo}..{hi}, got {value}")
    return value


def float_param(params: dict, name: str, choices, default: float | None = None) -> float | None:
    """A float query field that must equal one of ``choices`` (relative tolerance 1e-9); ``default`` if absent.

    Raises:
        RequestError: 400 when it is not a number or not one of the choices.
    """
    text = _one(params, name)
    if text is None:
        return default
    try:
        value = float(text[:32])
    except ValueError:
        raise RequestError(400, f"{name}: expected a number, got {text[:20]!r}") from None
    for choice in choices:
        if math.isclose(value, choice, rel_tol=1e-9, abs_tol=0.0):
            return choice
    raise RequestError(400, f"{name}: expected one of {list(choices)}, got {value}")


def layers_param(params: dict, known, default) -> frozenset:
    """A comma-separated subset of ``known`` (``default`` when absent; an empty value is no layer).

    Raises:
        RequestError: 400 on an unknown layer.
    """
    text = _one(params, "layers")
    if text is None:
        return frozenset(default)
    names = {name for name in text.split(",") if name}
    unknown = names - set(known)
    if unknown:
        raise RequestError(400, f"layers: unknown {sorted(unknown)[:4]}; expected a subset of {list(known)}")
    return frozenset(names)


class _HTTPServer(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, address, app, assets: dict, token: str | None, allow_remote: bool):
        self.app, self.assets, self.token, self.allow_remote = app, assets, token, allow_remote
        if ":" in address[0]:
            import socket

            self.address_family = socket.AF_INET6
        super().__init__(address, _Handler)


class _Handler(BaseHTTPRequestHandler):
    server_version = "davis-view"
    sys_version = ""
    protocol_version = "HTTP/1.1"

    def log_message(self, format, *args) -> None:  # noqa: A002 - the base class's signature
        """Quiet: the viewer prints nothing per request."""

    def do_GET(self) -> None:  # noqa: N802 - http.server's naming
        self._serve(head=False)

    def do_HEAD(self) -> None:  # noqa: N802
        self._serve(head=True)

    def _serve(self, head: bool) -> None:
        try:
            response = self._answer()
        except RequestError as exc:
            response = json_response({"error": exc.message}, exc.status)
        except DavisRigError as exc:  # e.g. a session file that became unreadable
            response = json_response({"error": str(exc)}, 500)
        self._send(response, head)

    def _answer(self) -> Response:
        server: _HTTPServer = self.server
        if not server.allow_remote and not is_loopback(_host_header_name(self.headers.get("Host"))):
            raise RequestError(403, "this viewer answers requests to localhost only")
        split = urlsplit(self.path)
        try:
            params = parse_qs(split.query, keep_blank_values=True, strict_parsing=False,
                              max_num_fields=MAX_QUERY_FIELDS)
        except ValueError:
            raise RequestError(400, "too many query fields") from None
        cookie_name = f"davis_view_token_{server.server_address[1]}"
        token = (params.pop("token", [""])[-1] or self.headers.get("X-Davis-Token", "")
                 or _cookie(self.headers.get("Cookie"), cookie_name))
        if server.token is not None and not hmac.compare_digest(token.encode(), server.token.encode()):
            raise RequestError(403, "missing or wrong token (the one davis-view printed)")
        if split.path in server.assets:
            body, content_type = server.assets[split.path]
            headers = [("Content-Security-Policy", CSP)]
            if server.token is not None:  # the page's own requests (script, images, fetch) carry it as a cookie
                headers.append(("Set-Cookie", f"{cookie_name}={server.token}; Path=/; HttpOnly; SameSite=Strict"))
            return Response(200, body, content_type, tuple(headers))
        if split.path.startswith("/api/"):
            return server.app.handle(split.path[len("/api/"):].split("/"), params)
        raise RequestError(404, "no such page")

    def _send(self, response: Response, head: bool) -> None:
        self.send_response(response.status)
        self.send_header("Content-Type", response.content_type)
        self.send_header("Content-Length", str(len(response.body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Referrer-Policy", "no-referrer")
        self.send_header("X-Frame-Options", "DENY")
        for name, value in response.headers:
            self.send_header(name, value)
        self.end_headers()
        if not head:
            try:
                self.wfile.write(response.body)
            except (BrokenPipeError, ConnectionResetError):
                pass  # the page moved on (e.g. a newer frame was asked for): nothing to do


def load_assets() -> dict:
    """The page's files from the package, ``{url path: (bytes, content type)}``."""
    from importlib.resources import files

    folder = files("davis_rig").joinpath("assets", "viewer")
    return {route: (folder.joinpath(name).read_bytes(), content_type) for route, (name, content_type) in ASSETS.items()}


class ViewerServer:
    """Serve an app (:class:`~davis_rig.viewer.sessions_app.SessionsApp` or the live view) on a local web page.

    Use as a context manager: entering binds and starts serving in a background thread, leaving stops.

    Args:
        app: has ``handle(parts: list[str], params: dict[str, list[str]]) -> Response`` for ``/api/...``.
        host: address to bind; loopback unless ``allow_remote``.
        port: TCP port (0 = any free one; see :attr:`port`).
        allow_remote: allow a non-loopback ``host``; a token is then required on every request.
        token: the token to require (default: a fresh random one when ``allow_remote``, none otherwise).

    Raises:
        ValueError: a non-loopback ``host`` without ``allow_remote``.
        OSError: the address cannot be bound (port in use, no such interface) — on entering.
    """

    def __init__(self, app, *, host: str = "127.0.0.1", port: int = 0, allow_remote: bool = False,
                 token: str | None = None):
        if not allow_remote and not is_loopback(host):
            raise ValueError(f"{host} is not this machine's loopback: listening there needs allow_remote "
                             "(--allow-remote), and then every request needs the printed token")
        self.app = app
        self.host = host
        self.requested_port = int(port)
        self.allow_remote = bool(allow_remote)
        self.token = token if token is not None else (secrets.token_urlsafe(24) if allow_remote else None)
        self._httpd: _HTTPServer | None = None
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        """The bound port (after entering)."""
        return self._httpd.server_address[1] if self._httpd is not None else self.requested_port

    @property
    def url(self) -> str:
        """The page's address, with the token when one is required."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        if host in ("0.0.0.0", "[::]"):
            import socket

            host = socket.gethostname()
        query = f"?token={quote(self.token)}" if self.token else ""
        return f"http://{host}:{self.port}/{query}"

    def __enter__(self) -> "ViewerServer":
        self._httpd = _HTTPServer((self.host, self.requested_port), self.app, load_assets(), self.token,
                                  self.allow_remote)
        self._thread = threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="davis-view-http", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc_info) -> None:
        if self._httpd is not None:
            self._httpd.shutdown()
            self._httpd.server_close()
            self._thread.join()
            self._httpd = None
