"""``ogserver --web-port``: the web view beside the gRPC port, on its host, with its TLS and callers."""

from __future__ import annotations

import logging

from ogserver.access.transport import tls_context
from ogserver.access.viewers import Viewers
from ogserver.settings import Settings
from ogserver.web import assets
from ogserver.web.catalogue import Sessions
from ogserver.web.http_server import WebServer

log = logging.getLogger(__name__)


def start_web(settings: Settings, viewers: Viewers) -> WebServer:
    """The web view, showing each caller what ``viewers`` let its credential see."""
    if assets.missing():
        raise ValueError("live.web_port: the web view's browser libraries are not installed: run "
                         "python -m ogserver.web.assets (make venv does)")
    host = settings.address.rsplit(":", 1)[0]
    try:
        sessions = Sessions(viewers, settings.live.web_seconds)
        server = WebServer(host, settings.live.web_port, sessions, tls_context(settings.access, "live.web_port"),
                           settings.live.web_hosts)
    except OSError as error:
        raise ValueError(f"live.web_port: cannot serve on {host}:{settings.live.web_port}: {error}") from None
    if viewers.callers.open:
        log.log(logging.INFO if server.loopback else logging.WARNING, "web view on %s (an open server: anyone who "
                "reaches it sees every session's map and images)", server.url(host))
    else:
        log.info("web view on %s (an API key, or a session token for its one session, in the page's ?key= or "
                 "?token=)", server.url(host))
    return server.start()
