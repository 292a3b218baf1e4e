"""The web view's HTTP server: an index of the maps a caller may see, a page per map, and the data the
page polls (``/api/map/ID/...``), each request checked against the caller's credential.

The page and the browser libraries are files in this package (``static/``, ``vendor/``), served as
they are: nothing is fetched from elsewhere at run time. Credentials travel in the URL's query
(``?key=`` an API key, ``?token=`` a session token) so a link or a test can carry one, or in the
``X-Api-Key`` / ``X-Session-Token`` headers; pages are sent with ``Referrer-Policy: no-referrer`` so
the query never leaves in a Referer. It is served by the listener every HTTP port of the server shares
(``ogserver.http``): connections bounded in number, per client address and in time, and only requests
whose Host names the server (``hosts.HostPolicy``: no DNS rebinding) answered, on every address. The
answers are made on the listener's worker threads (a decode waits on the mapper's lock).
"""

from __future__ import annotations

import asyncio
import html
import json
import logging
import mimetypes
import re
import ssl
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from http import HTTPStatus
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import grpc
import numpy as np
from aiohttp import web

from ogserver.access.transport import certificate_names
from ogserver.errors import ServiceError
from ogserver.http.policy import HEAD_SECONDS, PER_ADDRESS, Policy
from ogserver.http.server import HttpServer
from ogserver.throttled_log import ThrottledLog
from ogserver.web.catalogue import Catalogue, Credential
from ogserver.web.hosts import HostPolicy, is_loopback
from ogserver.web.maps import MapView

log = logging.getLogger(__name__)
PACKAGE = Path(__file__).parent
FOLDERS = {"static": PACKAGE / "static", "vendor": PACKAGE / "vendor"}
MAX_CONNECTIONS = 64
REQUEST_SECONDS = 10.0  # a response the client takes nothing of; a request's head has HEAD_SECONDS in all
MAP_PATH = re.compile(r"/(map|api/map)/([A-Za-z0-9_-]{1,64})(/[a-z.]+)?")
# A file under static/ or vendor/ as the page names it: short plain segments, none hidden. Anything else
# (a NUL, a name the file system refuses as too long) is not looked up at all.
FILE_NAME = re.compile(r"(?:[A-Za-z0-9_-][A-Za-z0-9_.-]{0,99}/){0,7}[A-Za-z0-9_-][A-Za-z0-9_.-]{0,99}")
_failures = ThrottledLog(log, 10.0)
# What a session's calls answer once it is closed, or its worker process has stopped (worker mode).
GONE = (grpc.StatusCode.NOT_FOUND, grpc.StatusCode.UNAVAILABLE)


@dataclass
class Answer:
    status: HTTPStatus
    body: bytes
    kind: str = "text/plain"
    headers: dict[str, str] = field(default_factory=dict)


class WebServer:
    """Serves ``catalogue``'s maps on ``host:port`` (0: any free port), to requests that name ``host``, a
    loopback name, an IP address, or one of the ``hosts`` (``HostPolicy``); HTTPS with ``tls``."""

    def __init__(self, host: str, port: int, catalogue: Catalogue, tls: ssl.SSLContext | None = None,
                 hosts: Iterable[str] = (), head_seconds: float = HEAD_SECONDS) -> None:
        self.catalogue = catalogue
        self.tls = tls
        self.loopback = is_loopback(host)
        self.pages = Pages(catalogue)
        app = web.Application()
        app.router.add_get("/{path:.*}", self._handle, allow_head=False)
        policy = Policy(MAX_CONNECTIONS, PER_ADDRESS, head_seconds, REQUEST_SECONDS, HostPolicy.serving(host, hosts),
                        tls)
        self.http = HttpServer("web view", host, port, app, policy)
        self.port: int = self.http.port

    def start(self) -> WebServer:
        self.http.start()
        return self

    def stop(self) -> None:
        """Stops serving and logs the view's work: its decodes and renders, and the CPU of its requests' threads
        and of its event loop's."""
        loop_cpu_seconds = self.http.loop_cpu_seconds()
        self.http.stop()
        busy = self.catalogue.busy
        log.info("web view: %d decodes and renders, %.1f s; %.2f CPU seconds in all", busy.count, busy.seconds,
                 busy.cpu_seconds + loop_cpu_seconds)

    def url(self, host: str) -> str:
        return self.http.url(host)

    async def _handle(self, request: web.Request) -> web.Response:
        transport = request.transport
        names = certificate_names(transport.get_extra_info("peercert")) if transport and self.tls else []
        answer = await asyncio.get_running_loop().run_in_executor(
            None, self.pages.answer, request.raw_path, request.headers, names, request.remote or "")
        return web.Response(status=answer.status, body=answer.body,
                            headers={"Content-Type": answer.kind, **answer.headers})


class Pages:
    """What the web view answers to one GET, on a worker thread: the request's CPU counted in ``busy``."""

    def __init__(self, catalogue: Catalogue) -> None:
        self.catalogue = catalogue

    def answer(self, target: str, headers: Mapping[str, str], names: list[bytes], address: str) -> Answer:
        """The answer to a GET of ``target`` (the raw request target) from ``address``, which presented
        ``headers`` and the certificate ``names``."""
        with self.catalogue.busy.request():
            return self._answer(target, headers, names, address)

    def _answer(self, target: str, headers: Mapping[str, str], names: list[bytes], address: str) -> Answer:
        path = target[:100]  # for the log, however the target parses
        try:
            url = urlsplit(target)  # a ValueError for some targets ("//[x"): a 400 as any other
            path, query = url.path[:100], parse_qs(url.query)
            folder, _, name = url.path.lstrip("/").partition("/")
            credential = Credential(key=query.get("key", [""])[0] or headers.get("X-Api-Key", ""),
                                    token=query.get("token", [""])[0] or headers.get("X-Session-Token", ""),
                                    certificate_names=names, address=address)
            if url.path == "/favicon.ico":
                return Answer(HTTPStatus.NO_CONTENT, b"")
            if folder in FOLDERS:
                return self._file(FOLDERS[folder], name)
            if url.path == "/":
                return self._index(credential)
            if match := MAP_PATH.fullmatch(url.path):
                return self._map(match.group(1), match.group(2), match.group(3) or "", credential, query)
            return Answer(HTTPStatus.NOT_FOUND, b"not found\n")
        except ServiceError as refusal:
            return self._refused(refusal, path.startswith("/api/"))
        except ValueError as error:  # a query or a request target that does not parse
            return Answer(HTTPStatus.BAD_REQUEST, f"{str(error)[:200]}\n".encode())
        except Exception as error:  # a map that fails to decode or render: the page gets 500, the log says why
            _failures.log(logging.ERROR, f"web view: {path!r} failed: {error!r}")
            return Answer(HTTPStatus.INTERNAL_SERVER_ERROR, b"the server failed; its log says why\n")

    def _refused(self, refusal: ServiceError, api: bool) -> Answer:
        if refusal.code in GONE:  # closed meanwhile, or its worker process stopped: no map any more
            return Answer(HTTPStatus.NOT_FOUND, f"the map is gone: {refusal.message}\n".encode())
        status = HTTPStatus.TOO_MANY_REQUESTS if refusal.code == grpc.StatusCode.RESOURCE_EXHAUSTED \
            else HTTPStatus.UNAUTHORIZED
        if api:
            return Answer(status, f"{refusal.message}\n".encode())
        return Answer(status, page("OG-Mapping", LOGIN.format(reason=html.escape(refusal.message))), "text/html")

    def _index(self, credential: Credential) -> Answer:
        catalogue = self.catalogue
        if catalogue.asks_credential and not (credential.key or credential.token or credential.certificate_names):
            return Answer(HTTPStatus.UNAUTHORIZED, page("OG-Mapping", LOGIN.format(reason="")), "text/html")
        views = catalogue.visible(credential)
        query = html.escape(credential.query())
        rows = "".join(f'<li><a href="/map/{view.source.id}{query}">{html.escape(view.source.label or view.source.id)}'
                       f'</a> <small>{view.source.id}</small></li>' for view in views)
        body = f"<h1>Maps</h1><ul>{rows or '<li>none you may see</li>'}</ul>"
        return Answer(HTTPStatus.OK, page("OG-Mapping: maps", body, refresh=5), "text/html")

    def _map(self, kind: str, map_id: str, part: str, credential: Credential, query: dict[str, list[str]]) -> Answer:
        view = self.catalogue.find(map_id, credential)
        if view is None:
            return Answer(HTTPStatus.NOT_FOUND, b"no such map, or not one you may see\n")
        if kind == "map" and not part:
            return self._file(FOLDERS["static"], "map.html", cached=False)  # its URL holds the credential
        if kind == "api/map":
            return self._data(view, part, query)
        return Answer(HTTPStatus.NOT_FOUND, b"not found\n")

    def _data(self, view: MapView, part: str, query: dict[str, list[str]]) -> Answer:
        if part == "/state":
            return Answer(HTTPStatus.OK, json.dumps(view.state()).encode(), "application/json")
        if part == "/splats.ply":
            decoded = view.splats(center(query.get("center", [""])[0]))
            return Answer(HTTPStatus.OK, decoded.ply, "application/octet-stream",
                          {"X-Map-Version": str(decoded.version), "X-Gaussians": str(decoded.count)})
        if part == "/frame":
            frame = view.source.shown().frame
            if frame is None:
                return Answer(HTTPStatus.NOT_FOUND, b"no frame mapped yet\n")
            return Answer(HTTPStatus.OK, frame.color.data, f"image/{frame.color.format or 'jpeg'}")
        if part == "/render.jpg":
            jpeg = view.render_jpeg()
            if jpeg is None:
                return Answer(HTTPStatus.NOT_FOUND, b"no frame mapped yet\n")
            return Answer(HTTPStatus.OK, jpeg, "image/jpeg")
        return Answer(HTTPStatus.NOT_FOUND, b"not found\n")

    def _file(self, folder: Path, name: str, cached: bool = True) -> Answer:
        """A file of ``folder``: 404 for a name the page never asks for, before the file system sees it. Not
        ``cached`` where the URL it answers carries a credential: no cache keeps the key beside the page."""
        if not FILE_NAME.fullmatch(name) or not (path := contained(folder, name)):
            return Answer(HTTPStatus.NOT_FOUND, b"not found\n")
        kind = "text/javascript" if path.suffix == ".js" else mimetypes.guess_type(path.name)[0] or "text/plain"
        return Answer(HTTPStatus.OK, path.read_bytes(), kind, {"Cache-Control": "max-age=3600"} if cached else {})


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


LOGIN = """<h1>OG-Mapping</h1><p>{reason}</p><form method="get" action="/">
<label>API key or session token <input name="key" type="password" autofocus></label>
<button>Show my maps</button></form>
<p><small>A session token shows its one session: <code>/map/SESSION_ID?token=TOKEN</code>.</small></p>"""


def page(title: str, body: str, refresh: int = 0) -> bytes:
    meta = f'<meta http-equiv="refresh" content="{refresh}">' if refresh else ""
    return (f'<!doctype html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title>{meta}'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">'
            f'<link rel="stylesheet" href="/static/style.css"></head><body class="list">{body}</body></html>').encode()
