"""The web view's HTTP server: an index of the maps a caller may see, a page per map, and the data the
page polls (``/api/map/ID/...``), each request checked against the caller's credential.

The page and the browser libraries are files in this package (``static/``, ``vendor/``), served as
they are: nothing is fetched from elsewhere at run time. Credentials travel in the URL's query
(``?key=`` an API key, ``?token=`` a session token) so a link or a test can carry one, or in the
``X-Api-Key`` / ``X-Session-Token`` headers; pages are sent with ``Referrer-Policy: no-referrer`` so
the query never leaves in a Referer. Connections are bounded in number, per client address and in time
(each request's head within a deadline, ``deadlines.py``), and the server
answers only requests whose Host names it (``hosts.HostPolicy``: no DNS rebinding), on every address.
"""

from __future__ import annotations

import html
import json
import logging
import mimetypes
import re
import socket
import ssl
import sys
import threading
from collections.abc import Iterable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import grpc
import numpy as np

from ogserver.errors import ServiceError
from ogserver.throttled_log import ThrottledLog
from ogserver.web.catalogue import Catalogue, Credential
from ogserver.web.deadlines import HEAD_SECONDS, AddressShares, HeadDeadline
from ogserver.web.hosts import HostPolicy, is_loopback
from ogserver.web.maps import MapView

log = logging.getLogger(__name__)
PACKAGE = Path(__file__).parent
FOLDERS = {"static": PACKAGE / "static", "vendor": PACKAGE / "vendor"}
MAX_CONNECTIONS = 64
REQUEST_SECONDS = 10.0  # each read or write; a request's head has HEAD_SECONDS in all (deadlines.py)
MAP_PATH = re.compile(r"/(map|api/map)/([A-Za-z0-9_-]{1,64})(/[a-z.]+)?")
# A file under static/ or vendor/ as the page names it: short plain segments, none hidden. Anything else
# (a NUL, a name the file system refuses as too long) is not looked up at all.
FILE_NAME = re.compile(r"(?:[A-Za-z0-9_-][A-Za-z0-9_.-]{0,99}/){0,7}[A-Za-z0-9_-][A-Za-z0-9_.-]{0,99}")
_refusals = ThrottledLog(log, 10.0)
_failures = ThrottledLog(log, 10.0)
_heads = threading.local()  # the head deadline of the connection a thread serves


class WebServer(ThreadingHTTPServer):
    """Serves ``catalogue``'s maps on ``host:port`` (0: any free port) on threads of its own, to requests that
    name ``host``, a loopback name, an IP address, or one of the ``hosts`` (``HostPolicy``)."""

    daemon_threads = True
    block_on_close = False

    def __init__(self, host: str, port: int, catalogue: Catalogue, tls: ssl.SSLContext | None = None,
                 hosts: Iterable[str] = ()) -> None:
        self.address_family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.catalogue = catalogue
        self.tls = tls
        self.loopback = is_loopback(host)
        self.hosts = HostPolicy.serving(host, hosts)
        self._slots = threading.BoundedSemaphore(MAX_CONNECTIONS)
        self._shares = AddressShares()
        self.head_seconds = HEAD_SECONDS
        super().__init__((host.strip("[]"), port), Handler)
        self.port: int = self.server_address[1]
        self._thread = threading.Thread(target=self.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="web-view", daemon=True)

    def start(self) -> WebServer:
        self._thread.start()
        return self

    def stop(self) -> None:
        self.shutdown()
        self.server_close()
        busy = self.catalogue.busy
        log.info("web view: %d decodes and renders, %.1f s; %.2f CPU seconds in all", busy.count, busy.seconds,
                 busy.cpu_seconds)

    def url(self, host: str) -> str:
        return f"{'https' if self.tls else 'http'}://{host}:{self.port}/"

    def process_request(self, request: socket.socket, client_address: tuple) -> None:  # type: ignore[override]
        if not self._shares.take(client_address[0]):
            _refusals.warning(f"web view: refused a connection from {client_address[0]}, which has "
                              f"{self._shares.limit} open")
            self.shutdown_request(request)
            return
        if not self._slots.acquire(blocking=False):
            self._shares.give_back(client_address[0])
            _refusals.warning(f"web view: refused a connection, {MAX_CONNECTIONS} are open")
            self.shutdown_request(request)
            return
        super().process_request(request, client_address)

    def handle_error(self, request: socket.socket | tuple[bytes, socket.socket], client_address: tuple) -> None:
        """What escaped a request's handler: one throttled log line, not socketserver's traceback on stderr per
        request, which any client could repeat to fill the log."""
        error = sys.exc_info()[1]
        _failures.log(logging.ERROR, f"web view: a request from {client_address[0]} failed: {error!r}")

    def process_request_thread(self, request: socket.socket, client_address: tuple) -> None:  # type: ignore[override]
        deadline = _heads.deadline = HeadDeadline(request, self.head_seconds)
        try:
            deadline.arm()  # the TLS handshake and the first request's head
            request.settimeout(REQUEST_SECONDS)
            if self.tls is not None:
                request = self.tls.wrap_socket(request, server_side=True)
            super().process_request_thread(request, client_address)
        except (OSError, ssl.SSLError):  # a client gone, or one that does not speak TLS
            self.shutdown_request(request)
        finally:
            deadline.met()
            self._slots.release()
            self._shares.give_back(client_address[0])


class Handler(BaseHTTPRequestHandler):
    server: WebServer
    protocol_version = "HTTP/1.1"
    timeout = REQUEST_SECONDS

    def handle_one_request(self) -> None:
        _heads.deadline.arm()  # each request of a kept-alive connection: its head in HEAD_SECONDS
        super().handle_one_request()

    def parse_request(self) -> bool:
        parsed = super().parse_request()  # the request line read before, the headers read here
        _heads.deadline.met()
        return parsed

    def log_message(self, format: str, *args: object) -> None:
        log.debug("web view: %s %s", self.address_string(), format % args)

    def do_GET(self) -> None:
        with self.server.catalogue.busy.request():
            self._answer()

    def _answer(self) -> None:
        host = self.headers.get("Host", "")
        if not self.server.hosts.allows(host):
            _refusals.warning(f"web view: refused a request for host {host[:100]!r}, not one of this server's names")
            self._send(HTTPStatus.FORBIDDEN, b"this server answers only requests that name one of its hosts\n")
            return
        path = self.path[:100]  # for the log, however the target parses
        try:
            url = urlsplit(self.path)  # a ValueError for some targets ("//[x"): a 400 as any other
            path, query = url.path[:100], parse_qs(url.query)
            folder, _, name = url.path.lstrip("/").partition("/")
            if url.path == "/favicon.ico":
                self._send(HTTPStatus.NO_CONTENT, b"")
            elif folder in FOLDERS:
                self._file(FOLDERS[folder], name)
            elif url.path == "/":
                self._index(self._credential(query))
            elif match := MAP_PATH.fullmatch(url.path):
                self._map(match.group(1), match.group(2), match.group(3) or "", self._credential(query), query)
            else:
                self._send(HTTPStatus.NOT_FOUND, b"not found\n")
        except ServiceError as refusal:
            self._refused(refusal, path.startswith("/api/"))
        except ValueError as error:  # a query or a request target that does not parse
            self._send(HTTPStatus.BAD_REQUEST, f"{str(error)[:200]}\n".encode())
        except Exception as error:  # a map that fails to decode or render: the page gets 500, the log says why
            _failures.log(logging.ERROR, f"web view: {path!r} failed: {error!r}")
            self._send(HTTPStatus.INTERNAL_SERVER_ERROR, b"the server failed; its log says why\n")

    def _credential(self, query: dict[str, list[str]]) -> Credential:
        names: list[bytes] = []
        if isinstance(self.connection, ssl.SSLSocket):
            names = certificate_names(self.connection.getpeercert())
        return Credential(key=query.get("key", [""])[0] or self.headers.get("X-Api-Key", ""),
                          token=query.get("token", [""])[0] or self.headers.get("X-Session-Token", ""),
                          certificate_names=names, address=self.client_address[0])

    def _refused(self, refusal: ServiceError, api: bool) -> None:
        status = HTTPStatus.TOO_MANY_REQUESTS if refusal.code == grpc.StatusCode.RESOURCE_EXHAUSTED \
            else HTTPStatus.UNAUTHORIZED
        if api:
            self._send(status, f"{refusal.message}\n".encode())
        else:
            self._send(status, page("OG-Mapping", LOGIN.format(reason=html.escape(refusal.message))), "text/html")

    def _index(self, credential: Credential) -> None:
        catalogue = self.server.catalogue
        if catalogue.asks_credential and not (credential.key or credential.token or credential.certificate_names):
            self._send(HTTPStatus.UNAUTHORIZED, page("OG-Mapping", LOGIN.format(reason="")), "text/html")
            return
        views = catalogue.visible(credential)
        query = html.escape(credential.query())
        rows = "".join(f'<li><a href="/map/{view.source.id}{query}">{html.escape(view.source.label or view.source.id)}'
                       f'</a> <small>{view.source.id}</small></li>' for view in views)
        body = f"<h1>Maps</h1><ul>{rows or '<li>none you may see</li>'}</ul>"
        self._send(HTTPStatus.OK, page("OG-Mapping: maps", body, refresh=5), "text/html")

    def _map(self, kind: str, map_id: str, part: str, credential: Credential, query: dict[str, list[str]]) -> None:
        view = self.server.catalogue.find(map_id, credential)
        if view is None:
            self._send(HTTPStatus.NOT_FOUND, b"no such map, or not one you may see\n")
        elif kind == "map" and not part:
            self._file(FOLDERS["static"], "map.html", cached=False)  # its URL holds the credential
        elif kind == "api/map":
            self._data(view, part, query)
        else:
            self._send(HTTPStatus.NOT_FOUND, b"not found\n")

    def _data(self, view: MapView, part: str, query: dict[str, list[str]]) -> None:
        if part == "/state":
            self._send(HTTPStatus.OK, json.dumps(view.state()).encode(), "application/json")
        elif part == "/splats.ply":
            decoded = view.splats(center(query.get("center", [""])[0]))
            self._send(HTTPStatus.OK, decoded.ply, "application/octet-stream",
                       {"X-Map-Version": str(decoded.version), "X-Gaussians": str(decoded.count)})
        elif part == "/frame":
            frame = view.source.latest()
            if frame is None:
                self._send(HTTPStatus.NOT_FOUND, b"no frame mapped yet\n")
            else:
                self._send(HTTPStatus.OK, frame.color.data, f"image/{frame.color.format or 'jpeg'}")
        elif part == "/render.jpg":
            jpeg = view.render_jpeg()
            if jpeg is None:
                self._send(HTTPStatus.NOT_FOUND, b"no frame mapped yet\n")
            else:
                self._send(HTTPStatus.OK, jpeg, "image/jpeg")
        else:
            self._send(HTTPStatus.NOT_FOUND, b"not found\n")

    def _file(self, folder: Path, name: str, cached: bool = True) -> None:
        """A file of ``folder``: 404 for a name the page never asks for, before the file system sees it. Not
        ``cached`` where the URL it answers carries a credential: no cache keeps the key beside the page."""
        if not FILE_NAME.fullmatch(name) or not (path := contained(folder, name)):
            self._send(HTTPStatus.NOT_FOUND, b"not found\n")
            return
        kind = "text/javascript" if path.suffix == ".js" else mimetypes.guess_type(path.name)[0] or "text/plain"
        self._send(HTTPStatus.OK, path.read_bytes(), kind, {"Cache-Control": "max-age=3600"} if cached else {})

    def _send(self, status: HTTPStatus, body: bytes, kind: str = "text/plain",
              headers: dict[str, str] | None = None) -> None:
        self.send_response(status)
        for name, value in {"Content-Type": kind, "Content-Length": str(len(body)), "Cache-Control": "no-store",
                            "Referrer-Policy": "no-referrer", "X-Content-Type-Options": "nosniff",
                            **(headers or {})}.items():
            self.send_header(name, value)
        self.end_headers()
        self.wfile.write(body)


def contained(folder: Path, name: str) -> Path | None:
    """``folder/name`` where that is a file inside ``folder`` (links followed), else None; never raises for a
    name the file system cannot take."""
    try:
        path = (folder / name).resolve()
        return path if path.is_relative_to(folder.resolve()) and path.is_file() else None
    except (OSError, ValueError):
        return None


def center(text: str) -> np.ndarray | None:
    """A viewpoint "x,y,z" from the query, None for none."""
    if not text:
        return None
    values = np.array([float(part) for part in text.split(",")]) if text.count(",") == 2 else np.array([np.nan])
    if values.shape != (3,) or not np.isfinite(values).all():
        raise ValueError(f"center: {text[:100]!r} is not three finite numbers x,y,z")
    return values


def certificate_names(certificate: dict | None) -> list[bytes]:
    """A verified client certificate's names as gRPC reports them: its DNS/URI names, else its common name."""
    if not certificate:
        return []
    alternatives = [value for kind, value in certificate.get("subjectAltName", ()) if kind in ("DNS", "URI")]
    if alternatives:
        return [name.encode() for name in alternatives]
    return [value.encode() for rdn in certificate.get("subject", ()) for key, value in rdn if key == "commonName"]


LOGIN = """<h1>OG-Mapping</h1><p>{reason}</p><form method="get" action="/">
<label>API key or session token <input name="key" type="password" autofocus></label>
<button>Show my maps</button></form>
<p><small>A session token shows its one session: <code>/map/SESSION_ID?token=TOKEN</code>.</small></p>"""


def page(title: str, body: str, refresh: int = 0) -> bytes:
    meta = f'<meta http-equiv="refresh" content="{refresh}">' if refresh else ""
    return (f'<!doctype html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title>{meta}'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">'
            f'<link rel="stylesheet" href="/static/style.css"></head><body class="list">{body}</body></html>').encode()
