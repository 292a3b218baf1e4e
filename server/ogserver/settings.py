"""Server settings: defaults, overridden by a YAML/JSON file, overridden by command-line flags."""

from __future__ import annotations

import dataclasses
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ogmapping.config import MIB, ConfigBounds
from ogmapping.config.overrides import assign, read_mapping

ZERO_ALLOWED = {"max_anchors", "max_skipped_recording_bytes", "skipped_recording_bytes_per_second"}


@dataclass
class Limits:
    """What one client may ask of the server; exceeding any gives RESOURCE_EXHAUSTED."""

    max_sessions: int = 4
    queue_depth: int = 8  # frames read ahead per session before backpressure
    realtime_queue_depth: int = 1  # realtime sessions: newest frames kept waiting; older ones are skipped
    max_queued_bytes: int = 256 * MIB  # access: decoded frames one session holds queued before backpressure
    max_image_pixels: int = 4096 * 3072  # per colour/depth image and per render
    max_message_bytes: int = 64 * MIB  # gRPC send/receive limit
    max_anchors: int = 0  # frames are refused once a map holds this many anchors; 0 = no limit
    max_snapshot_bytes: int = 256 * MIB  # largest snapshot RestoreSession accepts (buffered before it is read)
    # --- recording: what a realtime session's skipped frames may add to its recording (mapped frames are
    # always recorded); beyond either, a skipped frame is acknowledged as not recorded. 0: none recorded.
    max_skipped_recording_bytes: int = 1024 * MIB  # per session, over its life on this server
    skipped_recording_bytes_per_second: int = 4 * MIB  # per session; bursts of one second's worth

    def validate(self) -> None:
        for item in dataclasses.fields(self):
            value = getattr(self, item.name)
            minimum = 0 if item.name in ZERO_ALLOWED else 1
            if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
                raise ValueError(f"limits.{item.name} must be an integer >= {minimum} (got {value!r})")


# --- access: who may call (TLS, API keys), how much one caller may hold, how long the server waits, metrics
SHA256_HEX = re.compile(r"[0-9a-f]{64}")


AT_LEAST_ONE = ("max_concurrent_calls", "max_streams_per_connection", "max_metrics_connections")


@dataclass
class Access:
    """Transport security, callers and the limits that keep one caller from starving the others.

    Timeouts in seconds; 0 turns a timeout (or a per-caller limit) off.
    """

    tls_cert: str = ""  # PEM certificate chain; with tls_key the server speaks only TLS
    tls_key: str = ""
    tls_client_ca: str = ""  # PEM CA bundle: clients must present a certificate it signed (mutual TLS)
    api_keys_file: str = ""  # lines "NAME:SHA256HEX" (python -m ogserver.apikeys NAME makes one)
    api_keys: dict[str, str] = field(default_factory=dict)  # NAME -> sha256 hex of the key, as in the file
    metrics_address: str = ""  # HOST:PORT for Prometheus /metrics; empty = off
    max_sessions_per_client: int = 0  # sessions one caller identity may hold; 0 = only max_sessions
    max_label_chars: int = 256
    max_concurrent_calls: int = 32  # mapping calls at once; health checks are served beside them
    session_idle_seconds: float = 3600.0  # a session without calls, stream or queued frames this long is closed
    stream_idle_seconds: float = 300.0  # a frame stream whose client sends nothing this long is ended
    restore_idle_seconds: float = 30.0  # the longest wait for the next RestoreSession chunk
    restore_seconds: float = 600.0  # the longest a whole RestoreSession upload may take
    keepalive_seconds: float = 60.0  # HTTP/2 ping interval, so dead clients release their streams
    keepalive_timeout_seconds: float = 20.0
    max_auth_failures: int = 20  # wrong keys or tokens per client address and window, then RESOURCE_EXHAUSTED
    auth_failure_window_seconds: float = 60.0
    max_auth_failures_total: int = 200  # the same from all addresses together (a right credential always passes)
    request_seconds: float = 10.0  # the longest wait for a unary call's request message once its headers came
    max_streams_per_connection: int = 256  # HTTP/2 streams (calls) one connection may have open at once
    max_metrics_connections: int = 16  # /metrics connections served at once; more are closed at once

    def validate(self) -> None:
        if bool(self.tls_cert) != bool(self.tls_key):
            raise ValueError("access.tls_cert and access.tls_key go together")
        if self.tls_client_ca and not self.tls_cert:
            raise ValueError("access.tls_client_ca needs access.tls_cert and access.tls_key")
        if self.metrics_address and ":" not in self.metrics_address:
            raise ValueError(f"access.metrics_address must be HOST:PORT (got {self.metrics_address!r})")
        for name, digest in self.api_keys.items():
            if not isinstance(digest, str) or not SHA256_HEX.fullmatch(digest):
                raise ValueError(f"access.api_keys.{name} must be the key's sha256 as 64 lowercase hex digits")
        for item in dataclasses.fields(self):
            value = getattr(self, item.name)
            if isinstance(value, float) and not (math.isfinite(value) and value >= 0):
                raise ValueError(f"access.{item.name} must be a finite number >= 0 (got {value!r})")
            minimum = 1 if item.name in AT_LEAST_ONE else 0
            if isinstance(value, int) and value < minimum:
                raise ValueError(f"access.{item.name} must be an integer >= {minimum} (got {value!r})")

    @property
    def open(self) -> bool:
        """No API keys and no client certificates: every caller is the same anonymous one."""
        return not (self.api_keys or self.api_keys_file or self.tls_client_ca)


ORIGIN = re.compile(r"[a-z][a-z0-9+.-]*://[^/\s]*")


@dataclass
class Live:
    """The live view: each session's latest render and map, in Foxglove and in the recordings."""

    foxglove_host: str = "127.0.0.1"  # the Foxglove WebSocket server's address
    foxglove_port: int = -1  # -1: no Foxglove server; 0: any free port (the log names it)
    view_seconds: float = 1.0  # at most one render and point cloud per session this often; 0: views off
    view_points: int = 50_000  # the point cloud's bound (Gaussians from anchors spread over the map)
    record_views: bool = True  # write keyframes' render and point cloud into the recordings
    # --- the Foxglove port's gate (docs/foxglove.md, "Access"): a file holding the secret the URL's token
    # carries ("" = a random one per server when the gRPC port has API keys or TLS, else none), and the
    # browser origins allowed (clients that send no Origin always are)
    foxglove_token_file: str = ""
    foxglove_origins: list[str] = field(default_factory=list)
    # --- the web view (docs/service.md, "Web view"): each session's map as Gaussians in a browser, served
    # on the address's host with the gRPC port's TLS and callers
    web_port: int = -1  # -1: off; 0: any free port (the log names it)
    web_seconds: float = 0.5  # a map's Gaussians are decoded for the web view at most this often

    def validate(self) -> None:
        for origin in self.foxglove_origins:
            if not isinstance(origin, str) or not (origin == "null" or ORIGIN.fullmatch(origin)):
                raise ValueError(f"live.foxglove_origins: {origin!r} is not an origin such as "
                                 f"https://app.foxglove.dev (scheme://host[:port], no path)")
        if not -1 <= self.foxglove_port <= 65535:
            raise ValueError(f"live.foxglove_port must be -1 (off), 0 (any free port) or a port number "
                             f"(got {self.foxglove_port})")
        if not (math.isfinite(self.view_seconds) and self.view_seconds >= 0):
            raise ValueError(f"live.view_seconds must be a finite number >= 0 (got {self.view_seconds})")
        if self.foxglove and not self.view_seconds:
            raise ValueError("live.foxglove_port needs live.view_seconds > 0 (0 turns the views off)")
        if self.view_points < 1:
            raise ValueError(f"live.view_points must be >= 1 (got {self.view_points})")
        if not -1 <= self.web_port <= 65535:
            raise ValueError(f"live.web_port must be -1 (off), 0 (any free port) or a port number "
                             f"(got {self.web_port})")
        if not (math.isfinite(self.web_seconds) and self.web_seconds > 0):
            raise ValueError(f"live.web_seconds must be a finite number > 0 (got {self.web_seconds})")

    @property
    def foxglove(self) -> bool:
        return self.foxglove_port >= 0


@dataclass
class Settings:
    address: str = "127.0.0.1:50051"
    record_dir: str = "recordings"
    device: str = "auto"  # auto, cpu, cuda, cuda:N
    final_snapshots: bool = False  # write <session>.safetensors next to the recording on close
    torch_threads: int = 0  # 0: min(cpu count, 8)
    grace_seconds: float = 5.0  # how long shutdown waits for calls in flight
    warm_up: bool = True  # map a tiny synthetic scene before serving, so the first session pays no load costs
    limits: Limits = field(default_factory=Limits)
    # --- record: shutdown and closing never wait without a bound
    # How long closing a session waits for the frame being mapped, and shutdown (after the grace) for
    # gRPC's calls to end; then the recordings are finished regardless.
    stop_timeout_seconds: float = 10.0
    access: Access = field(default_factory=Access)
    # --- input: what one session's config and one frame may cost
    config_bounds: ConfigBounds = field(default_factory=ConfigBounds)  # on CreateSession's and snapshots' configs
    frame_seconds: float = 60.0  # a frame's optimisation stops after this long, or at once on close; 0 = no limit
    # --- crashes: a checkpoint of each session's map every this many recorded frames (0: only the one
    # written when it opens); at start, resume the sessions a crashed server left open
    checkpoint_interval: int = 50
    resume: bool = True
    live: Live = field(default_factory=Live)
    # --- cluster mode (docs/cluster.md): sessions as named Ray actors; "" = sessions in this process
    cluster: str = ""  # a Ray address: "auto", HOST:PORT of a head node, or ray://HOST:PORT (Ray Client)
    session_cpus: float = 1.0  # each session actor's Ray resource request
    session_gpus: float = 0.0  # a fraction of a GPU shares one among several sessions
    cluster_connect_seconds: float = 15.0  # the longest wait for the address to answer at start; 0: Ray decides
    # An fsspec URL (s3://bucket/prefix, file:///mnt/shared, ...) holding recordings and checkpoints for every
    # node, record_dir being each node's scratch space; "" = record_dir itself is shared (NFS, a shared volume).
    shared_storage: str = ""

    def validate(self) -> None:
        if not self.address or ":" not in self.address:
            raise ValueError(f"address must be HOST:PORT (got {self.address!r})")
        if self.torch_threads < 0 or self.grace_seconds < 0:
            raise ValueError("torch_threads and grace_seconds must not be negative")
        if not 0 <= self.stop_timeout_seconds < float("inf"):
            raise ValueError(f"stop_timeout_seconds must be a finite number >= 0 (got {self.stop_timeout_seconds})")
        self.limits.validate()
        self.access.validate()
        self.config_bounds.validate()
        self.live.validate()
        if not (math.isfinite(self.frame_seconds) and self.frame_seconds >= 0):
            raise ValueError(f"frame_seconds must be >= 0 and finite (got {self.frame_seconds})")
        if self.cluster and self.live.foxglove:
            raise ValueError("live.foxglove_port: the live view is not available in cluster mode yet")
        if self.cluster and self.live.web_port >= 0:
            raise ValueError("live.web_port: the web view is not available in cluster mode yet")
        for name in ("session_cpus", "session_gpus", "cluster_connect_seconds"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0 (got {value})")
        if self.checkpoint_interval < 0:
            raise ValueError(f"checkpoint_interval must be an integer >= 0 (got {self.checkpoint_interval})")
        if self.shared_storage and not (self.cluster and "://" in self.shared_storage):
            raise ValueError(f"shared_storage must be an fsspec URL such as s3://bucket/prefix, in cluster mode only "
                             f"(got {self.shared_storage!r}{'' if self.cluster else ' without cluster'})")

    def threads(self) -> int:
        return self.torch_threads or max(1, min(os.cpu_count() or 1, 8))


LABEL = "settings"  # names the settings in refusals: "unknown settings key 'limits.max_sesions'"
FLAG_SECTIONS = ("limits", "access", "live")  # the sections whose fields are flags of their own name


def load(path: str | Path | None = None, flags: dict[str, Any] | None = None) -> Settings:
    """Defaults, then the file (YAML or JSON, same names, sections nested), then flags not None."""
    settings = Settings()
    if path is not None:
        assign(settings, read_mapping(path, LABEL), LABEL)
    for key, value in (flags or {}).items():
        if value is None:
            continue
        section = next((name for name in FLAG_SECTIONS
                        if key in {item.name for item in dataclasses.fields(getattr(settings, name))}), "")
        assign(settings, {f"{section}.{key}" if section else key: value}, LABEL)
    settings.validate()
    return settings
