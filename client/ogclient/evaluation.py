"""Score a session through the server with the loop ``ogmap run`` scores a local map with.

Streamed and held-out poses are rendered by the server (raw float32, so nothing is lost in
transit) and ``ogmapping.quality.evaluation.evaluate_views`` scores them against the dataset frames and
picks the same previews.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
from ogapi.convert import matrix_to_list
from ogapi.images import decode_color, decode_depth
from ogapi.v1 import mapping_pb2 as pb
from ogapi.v1 import mapping_pb2_grpc as pb_grpc

from ogclient.connection import SessionRef
from ogclient.messages import intrinsics_to_proto
from ogmapping.config import MapperConfig
from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.frame import Frame
from ogmapping.quality.evaluation import FrameSet, evaluate_views
from ogmapping.runtime.host import host


@dataclass
class RemoteRender:
    """A server render, shaped like the engine's ``Rendered`` where scoring needs it."""

    color: np.ndarray
    depth: np.ndarray


def render(stub: pb_grpc.MappingStub, session: SessionRef, c2w: np.ndarray, camera: Intrinsics,
           frame: Frame | None = None) -> RemoteRender:
    """The server's render of ``c2w``: in the map's frame, or with ``frame`` as a client pose of its time (by
    its timestamp, where it has one: held-out frames were never sent, so they have no sequence), as a local
    evaluation renders it."""
    request = pb.RenderRequest(
        session_id=session.session_id, c2w=matrix_to_list(c2w), intrinsics=intrinsics_to_proto(camera),
        color_encoding=pb.COLOR_RAW_F32, depth_encoding=pb.DEPTH_RAW_F32,
    )
    if frame is not None and frame.timestamp is not None:
        request.timestamp = frame.timestamp
    response = stub.Render(request, metadata=session.metadata())
    return RemoteRender(
        color=decode_color(response.color.data, pb.COLOR_RAW_F32, camera.width, camera.height),
        depth=decode_depth(response.depth.data, pb.DEPTH_RAW_F32, 0.0, camera.width, camera.height),
    )


def snapshot_bytes(stub: pb_grpc.MappingStub, session: SessionRef) -> bytes:
    request = pb.GetSnapshotRequest(session_id=session.session_id)
    return b"".join(chunk.data for chunk in stub.GetSnapshot(request, metadata=session.metadata()))


def evaluate(
    stub: pb_grpc.MappingStub, session: SessionRef, frames: FrameSet, out: Path | None = None,
    progress: bool = True,
) -> dict:
    """results.json-shaped figures; with ``out``, also side-by-side previews and results.json there."""
    stats = stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())
    config = MapperConfig.from_dict(json.loads(stats.config_json))
    evaluation = evaluate_views(frames, config, partial(render, stub, session), out, progress)
    sample = frames.load(frames.selection.streamed[0]).color_intrinsics
    results = {
        **evaluation.splits,
        "processing_fps": stats.processing_fps,
        "render_fps": evaluation.render_fps,
        "snapshot_bytes": len(snapshot_bytes(stub, session)),
        "anchors": stats.anchors,
        "gaussians": stats.gaussians,
        "keyframes": stats.keyframes,
        "frames_mapped": stats.frames,
        "device": stats.device,
        "client_machine": host().to_dict(),
        "preset": stats.preset,
        "resolution": [sample.width, sample.height],
        "session_id": session.session_id,
        "lpips": evaluation.lpips,
    }
    if out is not None:
        (out / "results.json").write_text(json.dumps(results, indent=2))
    return results
