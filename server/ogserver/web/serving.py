"""``ogserver --web-port``: the web view beside the gRPC port, on its host, with its TLS and callers."""

from __future__ import annotations

import logging
import ssl

from ogserver.access.callers import Callers
from ogserver.access.failed_auth import FailedAuthentications
from ogserver.sessions.registry import Registry
from ogserver.settings import Access, Settings
from ogserver.web import assets
from ogserver.web.catalogue import Sessions
from ogserver.web.http_server import WebServer

log = logging.getLogger(__name__)


def tls_context(access: Access) -> ssl.SSLContext | None:
    """The gRPC port's TLS for the web port: its certificate, and its client CA (mutual TLS) when it has one."""
    if not access.tls_cert:
        return None
    tls = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    try:
        tls.load_cert_chain(access.tls_cert, access.tls_key)
        if access.tls_client_ca:
            tls.load_verify_locations(access.tls_client_ca)
            tls.verify_mode = ssl.CERT_REQUIRED
    except (OSError, ssl.SSLError) as error:
        raise ValueError(f"live.web_port: cannot load the access.tls_* files: {error}") from None
    return tls


def start_web(settings: Settings, registry: Registry, callers: Callers) -> WebServer:
    access = settings.access
    if assets.missing():
        raise ValueError("live.web_port: the web view's browser libraries are not installed: run "
                         "python -m ogserver.web.assets (make venv does)")
    failures = FailedAuthentications(access.max_auth_failures, access.auth_failure_window_seconds,
                                     access.max_auth_failures_total)
    host = settings.address.rsplit(":", 1)[0]
    try:
        sessions = Sessions(registry, callers, failures, settings.live.web_seconds)
        server = WebServer(host, settings.live.web_port, sessions, tls_context(access), settings.live.web_hosts)
    except OSError as error:
        raise ValueError(f"live.web_port: cannot serve on {host}:{settings.live.web_port}: {error}") from None
    if callers.open:
        log.log(logging.INFO if server.loopback else logging.WARNING, "web view on %s (an open server: anyone who "
                "reaches it sees every session's map and images)", server.url(host))
    else:
        log.info("web view on %s (an API key, or a session token for its one session, in the page's ?key= or "
                 "?token=)", server.url(host))
    return server.start()
