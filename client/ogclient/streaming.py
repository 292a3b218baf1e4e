"""Send frames over StreamFrames and follow the acks: progress bar, live counts, refusals."""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

from ogapi.v1 import mapping_pb2 as pb
from ogapi.v1 import mapping_pb2_grpc as pb_grpc
from tqdm import tqdm

from ogclient.connection import ClientError, SessionRef


@dataclass
class StreamResult:
    acks: list[pb.FrameAck] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def mapped(self) -> list[pb.FrameAck]:
        """Mapped (or failed while mapping): accepted and not skipped."""
        return [ack for ack in self.acks if ack.accepted and not ack.skipped]

    @property
    def skipped(self) -> list[pb.FrameAck]:
        """Realtime sessions: recorded, but passed over for a newer frame."""
        return [ack for ack in self.acks if ack.skipped]

    @property
    def rejected(self) -> list[pb.FrameAck]:
        return [ack for ack in self.acks if not ack.accepted]

    def summary(self) -> str:
        accepted = self.mapped
        last = accepted[-1] if accepted else pb.FrameAck()
        fps = len(accepted) / self.seconds if self.seconds > 0 else 0.0
        keyframes = sum(ack.keyframe for ack in accepted)
        return (
            f"{len(accepted)} frames mapped ({keyframes} keyframes), {len(self.skipped)} skipped, "
            f"{len(self.rejected)} rejected, "
            f"{self.seconds:.1f} s ({fps:.2f} frames/s); map: {last.anchors} anchors, {last.gaussians} Gaussians "
            "drawn in the last view"
        )


def paced(messages: Iterable[pb.Frame], fps: float) -> Iterator[pb.Frame]:
    """``messages`` at ``fps`` frames a second, on a fixed schedule (a late frame does not delay the
    next ones); 0: unpaced."""
    start = time.monotonic()
    for number, message in enumerate(messages):
        delay = start + number / fps - time.monotonic() if fps else 0.0
        if delay > 0:
            time.sleep(delay)
        yield message


class _Requests:
    """The frames as grpc's request iterator. One that cannot be made (a bag image refused, a file
    unreadable) ends the stream there, so the server keeps and acknowledges what came before, and is
    raised after the acks; raised inside grpc's sending thread it became `UNKNOWN: Exception iterating
    requests!`, the problem unsaid."""

    def __init__(self, messages: Iterable[pb.Frame]) -> None:
        self._messages = iter(messages)
        self.error: Exception | None = None

    def __iter__(self) -> Iterator[pb.Frame]:
        return self

    def __next__(self) -> pb.Frame:
        if self.error is not None:
            raise StopIteration
        try:
            return next(self._messages)
        except StopIteration:
            raise
        except Exception as error:  # raised again on the caller's thread
            self.error = error
            raise StopIteration from None


def stream_frames(
    stub: pb_grpc.MappingStub, session: SessionRef, messages: Iterable[pb.Frame], total: int | None = None,
    progress: bool = True, result: StreamResult | None = None,
) -> StreamResult:
    """Stream ``messages`` and collect one ack per frame (into ``result`` when given, so the acks of a stream
    that ends with an error are kept); refusals are printed, not raised, a failed call is raised."""
    result = StreamResult() if result is None else result
    start = time.perf_counter()
    bar = tqdm(total=total, desc="streaming", unit="frame", disable=not progress)
    requests = _Requests(messages)
    responses = stub.StreamFrames(requests, metadata=session.stream_metadata())
    keyframes = 0
    try:
        for ack in responses:
            result.acks.append(ack)
            bar.update(1)
            if ack.accepted and not ack.skipped:
                keyframes += ack.keyframe
                bar.set_postfix(
                    anchors=ack.anchors, drawn=ack.gaussians, keyframes=keyframes,
                    latency=f"{ack.latency_seconds:.2f}s", queue=ack.queue_depth,
                )
            elif not ack.accepted:
                bar.write(f"frame {ack.index} rejected: {ack.error.code_name}: {ack.error.message}")
        if requests.error is not None:
            raise requests.error
    except KeyboardInterrupt:
        responses.cancel()
        raise ClientError("interrupted; frames sent so far stay in the session") from None
    finally:
        bar.close()
        result.seconds += time.perf_counter() - start
    return result
