"""Score a session through the server exactly as ``ogmap run`` scores a local map.

Streamed and held-out poses are rendered by the server (raw float32, so nothing is lost in
transit) and compared with the dataset frames using the engine's own metric functions.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from ogapi.convert import intrinsics_to_proto, matrix_to_list
from ogapi.images import decode_color, decode_depth
from ogapi.v1 import mapping_pb2 as pb
from ogapi.v1 import mapping_pb2_grpc as pb_grpc
from tqdm import tqdm

from ogclient.connection import SessionRef
from ogclient.frames import FrameSet
from ogmapping.camera import Intrinsics
from ogmapping.config import MapperConfig
from ogmapping.metrics import Lpips, summarise
from ogmapping.runner import PREVIEW_COUNT, ground_truth, score, side_by_side


@dataclass
class RemoteRender:
    """A server render, shaped like the engine's ``Rendered`` where scoring needs it."""

    color: np.ndarray
    depth: np.ndarray


def render(stub: pb_grpc.MappingStub, session: SessionRef, c2w: np.ndarray, camera: Intrinsics) -> RemoteRender:
    request = pb.RenderRequest(
        session_id=session.session_id, c2w=matrix_to_list(c2w), intrinsics=intrinsics_to_proto(camera),
        color_encoding=pb.COLOR_RAW_F32, depth_encoding=pb.DEPTH_RAW_F32,
    )
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
    selection = frames.selection
    previews = set(selection.streamed[:: max(1, len(selection.streamed) // PREVIEW_COUNT)][:PREVIEW_COUNT])
    previews |= set(selection.heldout[:PREVIEW_COUNT])
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    render_seconds, renders = 0.0, 0
    lpips = Lpips()
    for split, positions in (("streamed", selection.streamed), ("heldout", selection.heldout)):
        per_frame = []
        for position in tqdm(positions, desc=f"evaluating {split}", unit="frame", disable=not progress):
            truth = ground_truth(frames.load(position), config)
            tic = time.perf_counter()
            rendered = render(stub, session, truth.c2w, truth.color_intrinsics)
            render_seconds += time.perf_counter() - tic
            renders += 1
            per_frame.append(score(rendered, truth, lpips))
            if out is not None and position in previews:
                cv2.imwrite(str(out / f"{split}_{position:06d}.png"), side_by_side(rendered, truth))
        results[split] = summarise(per_frame)
    sample = frames.load(selection.streamed[0]).color_intrinsics
    results.update(
        processing_fps=stats.processing_fps,
        render_fps=renders / render_seconds if render_seconds > 0 else None,
        snapshot_bytes=len(snapshot_bytes(stub, session)),
        anchors=stats.anchors,
        gaussians=stats.gaussians,
        keyframes=stats.keyframes,
        frames_mapped=stats.frames,
        device=stats.device,
        preset=stats.preset,
        resolution=[sample.width, sample.height],
        session_id=session.session_id,
        lpips=lpips.description,
    )
    if out is not None:
        (out / "results.json").write_text(json.dumps(results, indent=2))
    return results
