"""Which ``Host`` headers the web view answers: its defence against DNS rebinding, on every address it binds.

A page on another site cannot read the web view's answers (the browser's same-origin rule) unless that
site's own name comes to resolve to the server's address: DNS rebinding. The browser then sends that name
in ``Host``, so the server answers only requests that name it: ``localhost`` (and names under
``.localhost``, which browsers resolve to loopback themselves), any IP address (a browser sends one only to
the address it names, so it cannot be rebound), the machine's own host names when it listens beyond
loopback, and the names the operator lists (``live.web_hosts``; ``.example.org`` for that domain and every
name under it).
"""

from __future__ import annotations

import ipaddress
import re
import socket
from collections.abc import Callable, Iterable
from dataclasses import dataclass

# What a Host header holds: a name or IPv4 address, or an IPv6 address in brackets, and maybe a port.
HEADER = re.compile(r"(?:\[(?P<v6>[0-9a-f:.]{2,45})\]|(?P<name>[a-z0-9_.-]{1,253}))(?::\d{1,5})?")


def is_loopback(host: str) -> bool:
    """Whether a bind address (``localhost``, ``127.0.0.1``, ``[::1]``) reaches only this machine."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def machine_names() -> set[str]:
    """This machine's host name and fully qualified name, as a browser on its network may name it."""
    return {socket.gethostname(), socket.getfqdn()}


def host_of(header: str) -> str | None:
    """The host a ``Host`` header names, in lower case, without its port or final dot; None for no host."""
    match = HEADER.fullmatch(header.strip().lower())
    if match is None:
        return None
    if match["v6"] is not None:
        try:
            return str(ipaddress.IPv6Address(match["v6"]))
        except ValueError:
            return None
    return match["name"].rstrip(".") or None


def is_address(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


@dataclass(frozen=True)
class HostPolicy:
    """The host names a server answers for, beside ``localhost`` and IP addresses; names in ``domains``
    stand for themselves and every name under them."""

    names: frozenset[str]
    domains: frozenset[str] = frozenset()

    @classmethod
    def serving(cls, bind: str, listed: Iterable[str] = (),
                machine: Callable[[], Iterable[str]] = machine_names) -> HostPolicy:
        """The policy of a server bound to ``bind``: that name, the ``listed`` ones, and the ``machine``'s own
        names unless it listens on loopback only (where they would not reach it, and looking them up may wait
        on DNS)."""
        names = {"localhost", bind.strip("[]")} | {name for name in listed if not name.startswith(".")}
        if not is_loopback(bind):
            names |= set(machine())
        domains = {"localhost"} | {name[1:] for name in listed if name.startswith(".")}
        return cls(frozenset(clean(names)), frozenset(clean(domains)))

    def allows(self, header: str) -> bool:
        """Whether a request with this ``Host`` header (port and all) may be answered."""
        host = host_of(header)
        if host is None:
            return False
        if host in self.names or is_address(host):
            return True
        return any(host == domain or host.endswith(f".{domain}") for domain in self.domains)


def clean(names: Iterable[str]) -> set[str]:
    return {name.lower().rstrip(".") for name in names if name.strip(".")}
