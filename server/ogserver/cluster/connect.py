"""Joining the Ray cluster within a bounded time.

Given an address nothing answers at, Ray retries for a minute or more and then fails with a
traceback. The front-end first opens a TCP connection to the address itself, for at most
``cluster_connect_seconds``, and refuses to start with one line naming the address when that fails.
Needs no Ray: ``join`` is handed the call that connects.
"""

from __future__ import annotations

import socket
from collections.abc import Callable

RAY_CLIENT = "ray://"


def endpoint(address: str) -> tuple[str, int] | None:
    """The host and port a Ray address names (``HOST:PORT`` of a head node, ``ray://HOST:PORT`` of a Ray
    Client server); None for an address Ray resolves itself (``auto``)."""
    host, colon, port = address.removeprefix(RAY_CLIENT).rpartition(":")
    if not colon or not host or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def reach(address: str, seconds: float) -> None:
    """Refuse an address that takes no TCP connection within ``seconds`` (0: leave it to Ray)."""
    found = endpoint(address)
    if found is None or not seconds:
        return
    try:
        socket.create_connection(found, timeout=seconds).close()
    except OSError as error:
        raise RuntimeError(f"cannot reach the Ray cluster at {address} within {seconds:g} s "
                           f"(settings: cluster_connect_seconds): {error or type(error).__name__}") from None


def join(address: str, seconds: float, connect: Callable[[], object]) -> None:
    """``connect`` (``ray.init``) once the address answers; its failure as one line naming the address."""
    reach(address, seconds)
    try:
        connect()
    except Exception as error:  # Ray raises several kinds (ConnectionError, RuntimeError, ...), all fatal here
        first = str(error).strip().splitlines()[:1]
        raise RuntimeError(f"cannot join the Ray cluster at {address}: "
                           f"{first[0] if first else type(error).__name__}") from None
