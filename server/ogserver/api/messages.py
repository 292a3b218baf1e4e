"""The ogapi messages built from the engine's and the session's results.

The session and the servicer deal in typed results (``FrameResult``, ``Rendered``, ``MapStats``,
``SessionCounters``, snapshot bytes); how they look on the wire is decided here.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator
from pathlib import Path

import grpc
from ogapi.convert import matrix_to_list
from ogapi.images import encode_color, encode_depth
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.mapper import FrameResult
from ogmapping.optim.poses import PoseReport
from ogmapping.queries import Rendered
from ogmapping.runtime.time_budget import Stop
from ogmapping.stats import MapStats, PoseSummary
from ogserver.api.validation import RenderSpec
from ogserver.errors import ServiceError
from ogserver.sessions.counters import SessionCounters

RENDER_DEPTH_SCALE = 1000.0  # PNG16 renders are millimetres


def error_ack(index: int, error: ServiceError) -> pb.FrameAck:
    return pb.FrameAck(
        index=index, accepted=False,
        error=pb.Error(code=error.code.value[0], code_name=error.code.name, message=error.message),
    )


# An accepted frame whose optimisation stopped early: its ack keeps ``accepted`` and carries why in ``error``.
STOPPED = {
    Stop.DEADLINE: (grpc.StatusCode.DEADLINE_EXCEEDED, "the frame's time budget (frame_seconds) ran out"),
    Stop.CANCELLED: (grpc.StatusCode.CANCELLED, "the session was closing"),
}


def pose_correction(report: PoseReport) -> pb.PoseCorrection:
    return pb.PoseCorrection(translation=[float(v) for v in report.translation],
                             rotation=[float(v) for v in report.rotation], clamped=report.clamped,
                             refined_c2w=matrix_to_list(report.refined_c2w))


def frame_ack(
    result: FrameResult, sequence: int, latency_seconds: float, queue_depth: int, refines: bool = False,
) -> pb.FrameAck:
    """An accepted frame's ack; with ``refines`` (the session's ``poses.refine``), its pose correction."""
    ack = pb.FrameAck(
        index=result.index, accepted=True, sequence=sequence, keyframe=result.keyframe,
        anchors=result.anchors, gaussians=result.gaussians, iterations=result.iterations,
        latency_seconds=latency_seconds, process_seconds=result.seconds, queue_depth=queue_depth,
    )
    if refines and result.pose is not None:
        ack.pose_correction.CopyFrom(pose_correction(result.pose))
    if result.stopped is not None:
        code, reason = STOPPED[result.stopped]
        ack.error.CopyFrom(pb.Error(code=code.value[0], code_name=code.name,
                                    message=f"mapped, but optimisation stopped after {result.iterations} "
                                            f"iterations: {reason}"))
    return ack


def skipped_ack(
    index: int, sequence: int, anchors: int, gaussians: int, latency_seconds: float, queue_depth: int
) -> pb.FrameAck:
    """A realtime session's frame, recorded but passed over for a newer one: the map as it was."""
    return pb.FrameAck(index=index, accepted=True, skipped=True, sequence=sequence, anchors=anchors,
                       gaussians=gaussians, latency_seconds=latency_seconds, queue_depth=queue_depth)


def render_response(spec: RenderSpec, rendered: Rendered) -> pb.RenderResponse:
    """The requested images in the requested encodings; the caller fills in ``render_seconds``."""
    response = pb.RenderResponse(width=spec.intrinsics.width, height=spec.intrinsics.height)
    if spec.color:
        response.color.encoding = spec.color_encoding
        response.color.data = encode_color(rendered.color, spec.color_encoding, spec.jpeg_quality)
    if spec.depth:
        response.depth.encoding = spec.depth_encoding
        response.depth.data = encode_depth(rendered.depth, spec.depth_encoding, RENDER_DEPTH_SCALE)
        if spec.depth_encoding == pb.DEPTH_PNG16:
            response.depth.depth_scale = RENDER_DEPTH_SCALE
    return response


def pose_summary(summary: PoseSummary) -> pb.PoseSummary:
    return pb.PoseSummary(
        refined_keyframes=summary.refined_keyframes, mean_correction_m=summary.mean_correction_m,
        max_correction_m=summary.max_correction_m, mean_correction_deg=summary.mean_correction_deg,
        max_correction_deg=summary.max_correction_deg, clamped_keyframes=summary.clamped_keyframes,
    )


def stats(config: pb.SessionConfig, engine: MapStats, counters: SessionCounters) -> pb.Stats:
    message = pb.Stats(
        session_id=config.session_id, preset=config.preset, device=engine.device,
        frames=counters.mapped, frames_received=counters.received, frames_rejected=counters.rejected,
        frames_skipped=counters.skipped,
        queue_depth=counters.pending, processing_fps=counters.processing_fps, uptime_seconds=counters.uptime_seconds,
        keyframes=engine.keyframes, anchors=engine.anchors, anchors_per_level=engine.anchors_per_level,
        gaussians=engine.gaussians, iterations=engine.iterations, timings=engine.timings,
        engine_json=json.dumps(engine.to_dict()),
        config_json=json.dumps(engine.config) if engine.config else config.config_json,
        last_sequence=counters.last_sequence, last_index=counters.last_index, mapped_sequence=counters.mapped_sequence,
    )
    if engine.poses is not None:
        message.poses.CopyFrom(pose_summary(engine.poses))
    return message


def session_info(
    config: pb.SessionConfig, counters: SessionCounters, streaming: bool, recording: Path
) -> pb.SessionInfo:
    """A session as ListSessions shows it: never its token, and the recording's file name, not its server path."""
    return pb.SessionInfo(
        session_id=config.session_id, preset=config.preset, label=config.label, device=config.device,
        created_unix=config.created_unix, frames=counters.mapped, anchors=counters.anchors,
        queue_depth=counters.pending, streaming=streaming, recording=recording.name,
        last_sequence=counters.last_sequence, last_index=counters.last_index,
    )


def snapshot_chunks(data: bytes, chunk_bytes: int) -> Iterator[pb.SnapshotChunk]:
    """Chunks of at most ``chunk_bytes``, each with its offset, the total size and the sha256; at least one."""
    digest = hashlib.sha256(data).hexdigest()
    for offset in range(0, max(len(data), 1), chunk_bytes):
        yield pb.SnapshotChunk(
            data=data[offset : offset + chunk_bytes], offset=offset, total_bytes=len(data), sha256=digest
        )


def credentials(config: pb.SessionConfig, token: str, recording: Path) -> pb.SessionCredentials:
    """A new session's id and token; its recording by file name in the record dir, never a server path."""
    return pb.SessionCredentials(
        session_id=config.session_id, token=token, config_json=config.config_json, device=config.device,
        recording=recording.name,
    )


def closed(stats: pb.Stats, recording: Path, snapshot: Path | None) -> pb.CloseSessionResponse:
    """A closed session's final stats; its recording and final snapshot by file name in the record dir."""
    return pb.CloseSessionResponse(stats=stats, recording=recording.name, snapshot=snapshot.name if snapshot else "")
