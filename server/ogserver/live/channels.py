"""One Foxglove connection's view of the channels: only the topics of sessions its caller may see.

Live topics are named by session (``session_prefix``). The front passes each message of the Foxglove
WebSocket protocol through a ``ChannelFilter``: an ``advertise`` from the server keeps only the
channels whose session the caller may see (asked when the channel is advertised, so a session opened
later by another owner is never shown), ``unadvertise`` only those it passed; a client's ``subscribe``
keeps only entries for channels it passed (each dropped entry answered with the status the SDK gives
an unknown channel), ``unsubscribe`` only subscriptions it passed; a binary ``messageData`` frame
reaches the client only for a subscription it passed. Every other operation is dropped both ways
(the server offers no capability that needs one), so nothing else names a topic.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable
from dataclasses import dataclass, field

from ogserver.live.websocket import BINARY, TEXT

SESSION_TOPICS = "/session/"
SERVER_OPS = {"serverInfo", "status", "removeStatus", "advertise", "unadvertise"}
MESSAGE_DATA, TIME = 1, 2  # the server's binary opcodes it passes
UNKNOWN_CHANNEL = "Unknown channel ID: "  # the SDK's status for a subscription to no channel it has
ERROR = 2  # a status message's level


def session_prefix(session_id: str) -> str:
    """Live topics of one session: the recording's topic names under this prefix."""
    return f"{SESSION_TOPICS}{session_id}"


def topic_session(topic: str) -> str | None:
    """The session a live topic belongs to, None for a topic of no session."""
    if not topic.startswith(SESSION_TOPICS):
        return None
    session_id, slash, _ = topic.removeprefix(SESSION_TOPICS).partition("/")
    return session_id if slash and session_id else None


@dataclass
class ChannelFilter:
    """``sees``: whether the caller may see a session (None: a topic of no session)."""

    sees: Callable[[str | None], bool]
    channels: set[int] = field(default_factory=set)  # ids of the channels advertised to the client
    subscriptions: dict[int, int] = field(default_factory=dict)  # subscription id -> channel id, passed on

    def from_server(self, opcode: int, payload: bytes) -> bytes | None:
        """What of a server message reaches the client (None: nothing)."""
        if opcode == BINARY:
            if len(payload) >= 5 and payload[0] == MESSAGE_DATA:
                return payload if struct.unpack_from("<I", payload, 1)[0] in self.subscriptions else None
            return payload if payload[:1] == bytes([TIME]) else None
        message = _json(payload)
        op = message.get("op") if message is not None else None
        if op not in SERVER_OPS:
            return None
        if op == "advertise":
            shown = [channel for channel in _list(message, "channels")
                     if isinstance(channel, dict) and self.sees(topic_session(str(channel.get("topic", ""))))]
            self.channels.update(channel.get("id") for channel in shown)
            return _encode(message, channels=shown) if shown else None
        if op == "unadvertise":
            gone = [number for number in _ids(_list(message, "channelIds")) if number in self.channels]
            self.channels.difference_update(gone)
            return _encode(message, channelIds=gone) if gone else None
        return payload

    def from_client(self, opcode: int, payload: bytes) -> tuple[bytes | None, list[bytes]]:
        """What of a client message reaches the server (None: nothing), and the statuses the client is
        answered with for what was dropped."""
        message = _json(payload) if opcode == TEXT else None
        op = message.get("op") if message is not None else None
        if op == "subscribe":
            entries = [entry for entry in _list(message, "subscriptions") if isinstance(entry, dict)]
            kept = [entry for entry in entries if self._passes(entry)]
            self.subscriptions.update({entry.get("id"): entry["channelId"] for entry in kept})
            answers = [_status(f"{UNKNOWN_CHANNEL}{entry.get('channelId')}") for entry in entries if entry not in kept]
            return (_encode(message, subscriptions=kept) if kept else None), answers
        if op == "unsubscribe":
            ended = [number for number in _ids(_list(message, "subscriptionIds")) if number in self.subscriptions]
            for number in ended:
                del self.subscriptions[number]
            return (_encode(message, subscriptionIds=ended) if ended else None), []
        return None, []

    def _passes(self, subscription: dict) -> bool:
        """Whether a subscription names its id and a channel advertised to the client."""
        ids = _ids([subscription.get("id"), subscription.get("channelId")])
        return len(ids) == 2 and ids[1] in self.channels


def _json(payload: bytes) -> dict | None:
    try:
        message = json.loads(payload)
    except ValueError:  # not UTF-8 or not JSON
        return None
    return message if isinstance(message, dict) else None


def _list(message: dict, key: str) -> list:
    value = message.get(key)
    return value if isinstance(value, list) else []


def _ids(values: list) -> list[int]:
    """The integers among ``values`` (a client may send anything)."""
    return [value for value in values if isinstance(value, int) and not isinstance(value, bool)]


def _encode(message: dict, **changed: object) -> bytes:
    return json.dumps({**message, **changed}, separators=(",", ":")).encode()


def _status(text: str) -> bytes:
    return _encode({"op": "status", "level": ERROR, "message": text})
