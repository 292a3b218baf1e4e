"""ogclient's frame stream resumes by itself after UNAVAILABLE, against a server that drops streams on
purpose (no Ray, no mapping): the frames after the last one the session holds are sent again, each
frame ends up in the session once and in order, and a server that stays unavailable ends it with one
clear error after the bounded retries."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent import futures
from dataclasses import dataclass, field

import grpc
import pytest
from ogapi.v1 import mapping_pb2 as pb
from ogapi.v1 import mapping_pb2_grpc as pb_grpc
from ogclient.connection import ClientError, SessionRef
from ogclient.resuming import Backoff, stream_resuming

SESSION = SessionRef("a" * 32, "token")
FAST = Backoff(retries=3, first=0.01, longest=0.02)


@dataclass
class Dropping(pb_grpc.MappingServicer):
    """Holds the frames it takes; each stream call in ``cuts`` ends UNAVAILABLE after that many acks, having
    taken one frame more without acknowledging it (as a node lost while mapping it); ``down`` GetStats
    calls are UNAVAILABLE first (the session's actor being restarted)."""

    cuts: list[int]
    down: int = 0
    held: list[int] = field(default_factory=list)  # Frame.index of each frame taken, in order
    streams: int = 0

    def StreamFrames(self, requests: Iterator[pb.Frame], context: grpc.ServicerContext) -> Iterator[pb.FrameAck]:
        cut = self.cuts[self.streams] if self.streams < len(self.cuts) else None
        self.streams += 1
        for acked, frame in enumerate(requests):
            self.held.append(frame.index)
            if acked == cut:
                context.abort(grpc.StatusCode.UNAVAILABLE, "the session's node failed")
            yield pb.FrameAck(index=frame.index, sequence=len(self.held), accepted=True)

    def GetStats(self, request: pb.GetStatsRequest, context: grpc.ServicerContext) -> pb.Stats:
        if self.down:
            self.down -= 1
            context.abort(grpc.StatusCode.UNAVAILABLE, "the session's actor is restarting")
        return pb.Stats(session_id=request.session_id, last_sequence=len(self.held),
                        last_index=self.held[-1] if self.held else 0)


@pytest.fixture
def serve() -> Iterator:
    started: list[tuple[grpc.Server, grpc.Channel]] = []

    def start(servicer: Dropping) -> pb_grpc.MappingStub:
        server = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
        pb_grpc.add_MappingServicer_to_server(servicer, server)
        port = server.add_insecure_port("127.0.0.1:0")
        server.start()
        channel = grpc.insecure_channel(f"127.0.0.1:{port}")
        started.append((server, channel))
        return pb_grpc.MappingStub(channel)

    yield start
    for server, channel in started:
        channel.close()
        server.stop(0)


def frames_after(positions: list[int]):
    def source(last_index: int | None) -> Iterator[pb.Frame]:
        return (pb.Frame(index=position) for position in positions if last_index is None or position > last_index)

    return source


def test_a_cut_stream_goes_on_from_the_frame_after_the_last_one_held(serve) -> None:
    positions = [0, 1, 2, 3, 4, 6, 7, 8, 9]
    servicer = Dropping(cuts=[3, 0, 2], down=2)
    said: list[str] = []
    result = stream_resuming(serve(servicer), SESSION, frames_after(positions), progress=False,
                             backoff=Backoff(retries=4, first=0.01, longest=0.02), say=said.append)
    assert servicer.held == positions, "a frame was sent twice or lost"
    assert servicer.streams == 4
    assert [ack.sequence for ack in result.acks] == [1, 2, 3, 6, 7, 9]  # 4, 5 and 8 held but never acknowledged
    assert sum("frame stream was cut: UNAVAILABLE: the session's node failed" in line for line in said) == 3
    assert sum("GetStats: UNAVAILABLE" in line for line in said) == 2
    assert [line for line in said if line.startswith("resuming")] == [
        f"resuming: the session holds {held} frames, the last with index {index}; streaming the frames after it"
        for held, index in ((4, 3), (5, 4), (8, 8))]


def test_a_server_that_stays_unavailable_ends_the_stream_with_one_clear_error(serve) -> None:
    servicer = Dropping(cuts=[1, 0, 0, 0, 0])
    with pytest.raises(ClientError, match="stayed unavailable through 3 retries") as final:
        stream_resuming(serve(servicer), SESSION, frames_after(list(range(10))), progress=False, backoff=FAST,
                        say=lambda line: None)
    assert "ogclient stream --resume" in str(final.value)
    assert servicer.streams == 4  # the first, then three retries: the one acknowledged frame did not reset the count


def test_other_errors_end_the_stream_at_once(serve) -> None:
    class Refusing(Dropping):
        def StreamFrames(self, requests, context):
            context.abort(grpc.StatusCode.PERMISSION_DENIED, "not yours")
            yield pb.FrameAck()

    servicer = Refusing(cuts=[])
    with pytest.raises(grpc.RpcError) as refused:
        stream_resuming(serve(servicer), SESSION, frames_after([0, 1]), progress=False, backoff=FAST)
    assert refused.value.code() == grpc.StatusCode.PERMISSION_DENIED
