"""The Foxglove front's parts: WebSocket framing (RFC 6455) and one connection's channel filter."""

from __future__ import annotations

import asyncio
import json
import struct

import pytest
from ogserver.live.channels import ChannelFilter, session_prefix, topic_session
from ogserver.live.front import without_extensions
from ogserver.live.websocket import BINARY, CONTINUATION, PING, TEXT, FrameReader, Message, ProtocolError, frame


def read_all(data: bytes, masked: bool, max_bytes: int = 1 << 20) -> list[Message]:
    async def run() -> list[Message]:
        reader = asyncio.StreamReader()
        reader.feed_data(data)
        reader.feed_eof()
        frames, messages = FrameReader(reader, masked, max_bytes), []
        try:
            while True:
                messages.append(await frames.message())
        except asyncio.IncompleteReadError:
            return messages

    return asyncio.run(run())


def fragment(opcode: int, payload: bytes, final: bool, masked: bool) -> bytes:
    """A frame as ``frame`` writes it, its FIN bit cleared unless ``final``."""
    whole = frame(opcode, payload, masked)
    return bytes([whole[0] & (0xFF if final else 0x7F)]) + whole[1:]


@pytest.mark.parametrize("size", [0, 5, 125, 126, 65535, 65536, 200_000])
def test_frames_round_trip_masked_and_plain_at_every_length_form(size: int) -> None:
    payload = bytes(range(256)) * (size // 256) + bytes(size % 256)
    for masked in (True, False):
        assert read_all(frame(BINARY, payload, masked), masked) == [Message(BINARY, payload)]


def test_a_fragmented_message_is_reassembled_around_a_ping() -> None:
    data = (fragment(TEXT, b'{"op":', False, True) + frame(PING, b"hi", True)
            + fragment(CONTINUATION, b'"subscribe"}', True, True))
    assert read_all(data, masked=True) == [Message(PING, b"hi"), Message(TEXT, b'{"op":"subscribe"}')]


@pytest.mark.parametrize(("data", "problem"), [
    (frame(TEXT, b"x", False), "unmasked"),  # a client's frame must be masked
    (bytes([0xC1]) + frame(TEXT, b"x", True)[1:], "reserved bit"),  # permessage-deflate, never agreed
    (fragment(PING, b"x", False, True), "control frame"),
    (frame(CONTINUATION, b"x", True), "continuation"),
    (fragment(TEXT, b"x", False, True) + frame(TEXT, b"y", True), "new message"),
    (frame(0x3, b"x", True), "unknown opcode"),
    (frame(BINARY, bytes(2000), True), "over 1000 bytes"),
])
def test_frames_that_break_the_protocol_end_the_connection(data: bytes, problem: str) -> None:
    with pytest.raises(ProtocolError, match=problem):
        read_all(data, masked=True, max_bytes=1000)


def advertise(*channels: tuple[int, str]) -> bytes:
    return json.dumps({"op": "advertise", "channels": [{"id": number, "topic": topic, "schemaName": "x"}
                                                       for number, topic in channels]}).encode()


def message_data(subscription: int) -> bytes:
    return bytes([1]) + struct.pack("<IQ", subscription, 7) + b"payload"


def test_a_filter_shows_only_the_sessions_its_caller_sees() -> None:
    mine, theirs = session_prefix("mine"), session_prefix("theirs")
    assert topic_session(mine + "/ogmap/render") == "mine" and topic_session("/other") is None
    channels = ChannelFilter(lambda session_id: session_id == "mine")
    shown = json.loads(channels.from_server(TEXT, advertise((1, mine + "/a"), (2, theirs + "/a"), (3, "/other"))))
    assert [channel["topic"] for channel in shown["channels"]] == [mine + "/a"]
    assert channels.from_server(TEXT, advertise((4, theirs + "/b"))) is None, "an advertise of nothing it sees"

    forwarded, statuses = channels.from_client(TEXT, json.dumps({"op": "subscribe", "subscriptions": [
        {"id": 1, "channelId": 1}, {"id": 2, "channelId": 2}, {"id": 3, "channelId": [1]}]}).encode())
    assert json.loads(forwarded)["subscriptions"] == [{"id": 1, "channelId": 1}]
    assert [json.loads(status)["message"] for status in statuses] == \
        ["Unknown channel ID: 2", "Unknown channel ID: [1]"]
    assert channels.from_client(TEXT, b'{"op":"subscribe","subscriptions":[{"id":9,"channelId":4}]}')[0] is None

    assert channels.from_server(BINARY, message_data(1)) == message_data(1)
    assert channels.from_server(BINARY, message_data(2)) is None, "data for a subscription it never passed"
    unadvertise = json.dumps({"op": "unadvertise", "channelIds": [1, 2]}).encode()
    assert json.loads(channels.from_server(TEXT, unadvertise))["channelIds"] == [1]
    assert channels.from_client(TEXT, b'{"op":"unsubscribe","subscriptionIds":[1,2]}')[0] == \
        b'{"op":"unsubscribe","subscriptionIds":[1]}'


def test_a_filter_drops_what_it_does_not_know() -> None:
    channels = ChannelFilter(lambda session_id: True)
    assert channels.from_client(BINARY, b"\x01anything") == (None, [])  # publishing: no capability for it
    assert channels.from_client(TEXT, b'{"op":"subscribeConnectionGraph"}') == (None, [])
    assert channels.from_client(TEXT, b"\xff not json") == (None, [])
    assert channels.from_server(TEXT, b'{"op":"connectionGraphUpdate"}') is None
    info = b'{"op":"serverInfo","name":"ogserver"}'
    assert channels.from_server(TEXT, info) == info


def test_the_forwarded_handshake_offers_no_compression() -> None:
    head = (b"GET /?key=k HTTP/1.1\r\nHost: h\r\nSec-WebSocket-Extensions: permessage-deflate; "
            b"client_max_window_bits\r\nsec-websocket-extensions: x\r\nUpgrade: websocket\r\n\r\n")
    assert without_extensions(head) == b"GET /?key=k HTTP/1.1\r\nHost: h\r\nUpgrade: websocket\r\n\r\n"


def test_a_message_in_many_small_fragments_is_bounded_in_all() -> None:
    data = fragment(TEXT, b"x" * 100, False, True) + b"".join(
        fragment(CONTINUATION, b"x" * 100, False, True) for _ in range(20))
    with pytest.raises(ProtocolError, match="a message over 1000 bytes"):
        read_all(data, masked=True, max_bytes=1000)
