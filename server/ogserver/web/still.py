"""One map that no longer changes, in the web view (``ogserver view``): a snapshot, or the map at the end
of a recording.

A snapshot is loaded as it is. A recording's map is its final snapshot where the server wrote one
beside it (``--final-snapshots``: ``<session>.safetensors``), else the map a replay builds: its
recorded frames mapped here, in order, through the checks and with the config a replay's
CreateSession would get. The page is served on 127.0.0.1 behind a random token in the URL.
"""

from __future__ import annotations

import secrets
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from ogapi import recording as layout
from ogapi.v1 import mapping_pb2 as pb
from tqdm import tqdm

from ogmapping.config import pinned
from ogmapping.mapper import Mapper
from ogmapping.persist import map_io, snapshot
from ogmapping.runtime.profile import resolve_device
from ogserver.api import validation
from ogserver.errors import ServiceError
from ogserver.live.map_look import MapperLook, keyframe_path
from ogserver.live.views import Shown
from ogserver.sessions.registry import requested_config
from ogserver.settings import Settings
from ogserver.web.catalogue import OneMap
from ogserver.web.http_server import WebServer
from ogserver.web.maps import MapView

HOST = "127.0.0.1"
MIN_SECONDS = 0.2


@dataclass
class StillMap:
    """A map that no longer changes, as a ``maps.Source``: its keyframes' path as its snapshot recorded it, or
    as the replay that built it went."""

    id: str
    label: str
    mapper: Mapper
    path: np.ndarray  # the keyframes' camera-to-world poses (n, 4, 4)

    @property
    def look(self) -> MapperLook:
        return MapperLook(self.mapper)

    def shown(self) -> Shown:
        return Shown(None, None, 0)

    def keyframe_path(self) -> np.ndarray:
        return self.path

    def counters(self) -> dict[str, float]:
        return {}


def replay(path: Path, device: str, progress: Callable[[str], None], bar: bool = False) -> Mapper:
    """The map a replay of the recording at ``path`` builds; ValueError for a recording that cannot be one.
    With ``bar``, a progress bar of the frames mapped on stderr (a recording of minutes maps for minutes)."""
    recorded = layout.load(path)
    if recorded.config is None:
        raise ValueError(f"{path} holds no session config: not a session recording")
    settings = Settings()
    preset, overrides = pinned(recorded.config.preset, recorded.config.overrides, recorded.config.config_json)
    try:
        _, _, config = requested_config(pb.CreateSessionRequest(preset=preset, overrides=overrides), settings)
        mapper = Mapper(config, device=device)
        progress(f"mapping the {len(recorded.frames)} recorded frames of {path.name} here (a snapshot beside it, "
                 f"{path.stem}.safetensors, would be read instead)")
        for _, message in tqdm(recorded.frames, desc="mapping the recording", unit="frame", disable=not bar):
            mapper.process(validation.frame(message, settings.limits.max_image_pixels, config.octree))
    except ServiceError as error:
        raise ValueError(f"{path}: {error.message}") from None
    return mapper


def open_map(path: Path, device: str, progress: Callable[[str], None], bar: bool = False) -> StillMap:
    """The map at ``path``: a snapshot (.safetensors) or a recording (.mcap). A snapshot is held to a server's
    default config bounds, as RestoreSession holds one, before anything is built for it (ValueError): a shared
    file may name any model."""
    device = str(resolve_device(device))
    snapshot_path = path.with_suffix(".safetensors") if path.suffix == ".mcap" else path
    if path.suffix == ".mcap" and not snapshot_path.is_file():
        mapper = replay(path, device, progress, bar)
        poses = keyframe_path(mapper)
    else:
        bounds = Settings().config_bounds
        state = snapshot.decode(snapshot_path.read_bytes(), bounds)
        mapper, poses = Mapper.from_state(state, device, bounds=bounds), map_io.keyframe_path(state)
    return StillMap(path.stem.split(".")[0] or "map", path.name, mapper, poses)


def serve(still: StillMap, port: int = 0) -> tuple[WebServer, str]:
    """A started web server for ``still`` on 127.0.0.1 and the URL of its page (token included)."""
    token = secrets.token_urlsafe(24)
    server = WebServer(HOST, port, OneMap(MapView(still, MIN_SECONDS), token)).start()
    return server, f"{server.url(HOST)}map/{still.id}?token={token}"
