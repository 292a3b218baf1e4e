"""A Foxglove WebSocket server (the ``foxglove-sdk`` package, the ``live`` extra) for the live view.

Channels are advertised per topic on first use and carry protobuf messages with the schema the
recordings use, so Foxglove decodes the same bytes live and from a file. ``wants`` tells whether a
client subscribes to a topic, so nothing is rendered or decoded for a view nobody watches. The
server has its own ``foxglove.Context``: servers in one process do not see each other's channels.
Clients reach the SDK's server only through the gate in ``front.py`` (origins, credentials, TLS, and
each client's view of the channels), and the SDK's log lines, one per bad message a client sends, go
through a throttle.
"""

from __future__ import annotations

import logging
import ssl
import threading
from typing import Any

from google.protobuf.message import Message
from mcap_protobuf.schema import build_file_descriptor_set

from ogserver.live.front import Front, Gate, loopback_host
from ogserver.throttled_log import throttle_library

log = logging.getLogger(__name__)
INSTALL_HINT = "pip install 'ogmapping[live]' (the foxglove-sdk package)"
SDK_LOG_INTERVAL_SECONDS = 10.0


class FoxgloveServer:
    """The SDK's server on a loopback address of its own, behind a ``Front`` on ``host:port``."""

    def __init__(self, host: str, port: int, gate: Gate, tls: ssl.SSLContext | None = None) -> None:
        try:
            import foxglove
        except ImportError:
            raise ValueError(f"--foxglove-port needs the foxglove-sdk package: {INSTALL_HINT}") from None
        for library in ("foxglove", "tungstenite"):  # the SDK and its WebSocket library
            throttle_library(library, logging.getLogger(f"{__name__}.sdk"), SDK_LOG_INTERVAL_SECONDS)
        self._foxglove = foxglove
        self._context = foxglove.Context()
        inner_host = loopback_host()
        try:
            self._server = foxglove.start_server(name="ogserver", host=inner_host, port=0, context=self._context)
        except Exception as error:  # the SDK raises its own error types
            raise ValueError(f"cannot start the Foxglove server: {error}") from None
        try:
            self._front = Front(host, port, (inner_host, self._server.port), gate, tls)
        except OSError as error:
            self._server.stop()
            raise ValueError(f"cannot serve Foxglove on {host}:{port}: {error}") from None
        self.host = host
        self.gate = gate
        self.tls = tls is not None
        self._channels: dict[str, Any] = {}
        self._lock = threading.Lock()

    @property
    def port(self) -> int:
        return self._front.port

    def advertise(self, topic: str, message_type: type[Message]) -> None:
        """Offer ``topic`` to clients (once), so they can subscribe before anything is published on it."""
        with self._lock:
            if topic in self._channels:
                return
            schema = self._foxglove.Schema(name=message_type.DESCRIPTOR.full_name, encoding="protobuf",
                                           data=build_file_descriptor_set(message_type).SerializeToString())
            self._channels[topic] = self._foxglove.Channel(topic, schema=schema, message_encoding="protobuf",
                                                           context=self._context)

    def wants(self, topic: str) -> bool:
        with self._lock:
            channel = self._channels.get(topic)
        return channel is not None and channel.has_sinks()

    def publish(self, topic: str, message: Message, log_time: int) -> None:
        self.advertise(topic, type(message))
        with self._lock:
            channel = self._channels[topic]
        channel.log(message.SerializeToString(), log_time=log_time)

    def withdraw(self, prefix: str) -> None:
        """Stop advertising every topic under ``prefix`` (a closed session's)."""
        with self._lock:
            topics = [topic for topic in self._channels if topic.startswith(prefix)]
            channels = [self._channels.pop(topic) for topic in topics]
        for channel in channels:
            channel.close()

    def stop(self) -> None:
        self._front.stop()
        self._server.stop()
