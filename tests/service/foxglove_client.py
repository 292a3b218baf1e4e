"""A Foxglove WebSocket protocol client over a plain websocket (``websockets``), for the live-view tests.

It speaks the protocol as the Foxglove app does: JSON ``advertise`` messages name the channels and
carry each channel's schema (a protobuf FileDescriptorSet, base64), ``subscribe`` asks for them, and
binary message-data frames (opcode 1, subscription id, log time, payload) bring the messages, decoded
here with classes built from the advertised schema, not from a package the server also uses.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import ssl
import struct
import time
from dataclasses import dataclass, field

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import Message
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 1
UNKNOWN_CHANNEL = "Unknown channel ID: "  # the server's status when a subscription names no channel it has


@dataclass(frozen=True)
class Advertised:
    id: int
    topic: str
    schema_name: str
    message_type: type[Message]


def message_type(schema_name: str, schema_base64: str) -> type[Message]:
    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(schema_base64))
    pool = descriptor_pool.DescriptorPool()
    for file in files.file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


@dataclass
class Received:
    channels: dict[str, Advertised] = field(default_factory=dict)  # by topic
    messages: dict[str, list[tuple[int, Message]]] = field(default_factory=dict)  # topic -> (log time, message)


async def _read(ws: ClientConnection, received: Received, subscribed: dict[int, Advertised]) -> int | None:
    """Read one message; return the id of a channel the server says it does not know (yet), if any."""
    message = await ws.recv()
    if isinstance(message, str):
        data = json.loads(message)
        if data["op"] == "advertise":
            for channel in data["channels"]:
                assert channel["encoding"] == "protobuf" and channel["schemaEncoding"] == "protobuf"
                received.channels[channel["topic"]] = Advertised(
                    channel["id"], channel["topic"], channel["schemaName"],
                    message_type(channel["schemaName"], channel["schema"]))
        elif data["op"] == "status" and data["message"].startswith(UNKNOWN_CHANNEL):
            return int(data["message"].removeprefix(UNKNOWN_CHANNEL))
        return None
    assert message[0] == MESSAGE_DATA, f"unexpected binary opcode {message[0]}"
    subscription, log_time = struct.unpack_from("<IQ", message, 1)
    channel = subscribed[subscription]
    received.messages.setdefault(channel.topic, []).append((log_time, channel.message_type.FromString(message[13:])))
    return None


def _connect(url: str, origin: str | None, tls: ssl.SSLContext | None) -> connect:
    return connect(url, subprotocols=[SUBPROTOCOL], max_size=None, ssl=tls, open_timeout=10,
                   additional_headers={"Origin": origin} if origin else None)


async def first_message(url: str, origin: str | None = None, tls: ssl.SSLContext | None = None) -> str | int:
    """The ``op`` of the server's first message, or the HTTP status that refused the handshake."""
    try:
        async with _connect(url, origin, tls) as ws:
            return json.loads(await asyncio.wait_for(ws.recv(), 10))["op"]
    except InvalidStatus as refused:
        return refused.response.status_code


async def subscribe_unknown(url: str, messages: int, entries: int) -> int:
    """Send ``messages`` subscribe requests of ``entries`` each, for a channel the server never had; the
    number of unknown-channel statuses answered."""
    statuses = 0
    async with _connect(url, None, None) as ws:
        await ws.recv()
        for _ in range(messages):
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": number, "channelId": 999_999} for number in range(entries)]}))
        with contextlib.suppress(TimeoutError, ConnectionClosed):
            while True:  # the server's answers (a status per bad entry), until it has none for a second
                message = await asyncio.wait_for(ws.recv(), 1.0)
                statuses += isinstance(message, str) and json.loads(message).get("message", "").startswith(
                    UNKNOWN_CHANNEL)
    return statuses


async def watch(url: str, prefix: str, topics: list[str], wanted: set[str], seconds: float,
                tls: ssl.SSLContext | None = None) -> Received:
    """Subscribe to ``prefix + topic`` for each topic once advertised; return once every ``wanted``
    topic has a message (none wanted: until the server ends the connection), or after ``seconds``."""
    received, subscribed = Received(), {}
    deadline = time.monotonic() + seconds
    async with _connect(url, None, tls) as ws:
        while time.monotonic() < deadline and not (wanted and wanted <= set(received.messages)):
            try:
                unknown = await asyncio.wait_for(_read(ws, received, subscribed),
                                                 max(deadline - time.monotonic(), 0.01))
            except (TimeoutError, ConnectionClosed):
                break
            if unknown is not None:  # advertised to the client a moment before the server took it: ask again
                await asyncio.sleep(0.1)
                subscribed = {number: channel for number, channel in subscribed.items() if channel.id != unknown}
            fresh = [received.channels[prefix + topic] for topic in topics
                     if prefix + topic in received.channels
                     and received.channels[prefix + topic] not in subscribed.values()]
            if fresh:
                for channel in fresh:
                    subscribed[max(subscribed, default=0) + 1] = channel
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": number, "channelId": channel.id} for number, channel in subscribed.items()
                    if channel in fresh]}))
    return received


async def topics(url: str, until, seconds: float = 20.0, settle: float = 1.0,
                 tls: ssl.SSLContext | None = None) -> dict[str, int]:
    """The channels advertised (and not withdrawn) to a client at ``url``, by topic: once ``until(topics)``
    holds, after a further ``settle`` seconds of listening; or after ``seconds``."""
    shown: dict[str, int] = {}
    deadline, reached = time.monotonic() + seconds, False
    async with _connect(url, None, tls) as ws:
        while time.monotonic() < deadline:
            try:
                message = await asyncio.wait_for(ws.recv(), max(deadline - time.monotonic(), 0.01))
            except (TimeoutError, ConnectionClosed):
                break
            data = json.loads(message) if isinstance(message, str) else {}
            if data.get("op") == "advertise":
                shown.update({channel["topic"]: channel["id"] for channel in data["channels"]})
            elif data.get("op") == "unadvertise":
                shown = {topic: number for topic, number in shown.items() if number not in data["channelIds"]}
            if not reached and until(set(shown)):
                deadline, reached = min(deadline, time.monotonic() + settle), True
    return shown


@dataclass
class Answers:
    statuses: list[str] = field(default_factory=list)  # the status messages' text
    data_frames: int = 0  # binary message-data frames received


async def subscribe_then(url: str, channel_ids: list[int], ready: set[int], check,
                         listen: float = 1.0) -> tuple[Answers, object]:
    """Once the channels ``ready`` are advertised, subscribe to ``channel_ids`` (subscription ids 1, 2, ...),
    run ``check()`` in a thread while connected, then listen ``listen`` seconds: what came back, and what
    ``check`` returned."""
    answers, advertised = Answers(), set()
    async with _connect(url, None, None) as ws:
        while not ready <= advertised:
            data = json.loads(await asyncio.wait_for(ws.recv(), 10))
            if data["op"] == "advertise":
                advertised.update(channel["id"] for channel in data["channels"])
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": number, "channelId": channel} for number, channel in enumerate(channel_ids, 1)]}))
        checked = await asyncio.to_thread(check)
        deadline = time.monotonic() + listen
        with contextlib.suppress(TimeoutError, ConnectionClosed):
            while (left := deadline - time.monotonic()) > 0:
                message = await asyncio.wait_for(ws.recv(), left)
                if isinstance(message, bytes):
                    answers.data_frames += message[:1] == bytes([MESSAGE_DATA])
                elif json.loads(message)["op"] == "status":
                    answers.statuses.append(json.loads(message)["message"])
    return answers, checked
