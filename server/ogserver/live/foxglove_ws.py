"""A Foxglove WebSocket server (the ``foxglove-sdk`` package, the ``live`` extra) for the live view.

Channels are advertised per topic on first use and carry protobuf messages with the schema the
recordings use, so Foxglove decodes the same bytes live and from a file. ``wants`` tells whether a
client subscribes to a topic, so nothing is rendered or decoded for a view nobody watches. The
server has its own ``foxglove.Context``: servers in one process do not see each other's channels.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from google.protobuf.message import Message
from mcap_protobuf.schema import build_file_descriptor_set

log = logging.getLogger(__name__)
INSTALL_HINT = "pip install 'ogmapping[live]' (the foxglove-sdk package)"


class FoxgloveServer:
    def __init__(self, host: str, port: int) -> None:
        try:
            import foxglove
        except ImportError:
            raise ValueError(f"--foxglove-port needs the foxglove-sdk package: {INSTALL_HINT}") from None
        self._foxglove = foxglove
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(name="ogserver", host=host, port=port, context=self._context)
        except Exception as error:  # the SDK raises its own error types for a port in use or a bad host
            raise ValueError(f"cannot serve Foxglove on {host}:{port}: {error}") from None
        self.host = host
        self._channels: dict[str, Any] = {}
        self._lock = threading.Lock()

    @property
    def port(self) -> int:
        return self._server.port

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
        self._server.stop()
