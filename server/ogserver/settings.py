"""Server settings: defaults, overridden by a YAML/JSON file, overridden by command-line flags.

Each field declares what it accepts beside its default (``ranged``, ``formed``), as the engine's config
does, and ``Settings.validate`` checks them all with the engine's ``check``; only the rules that tie
fields together are written out.
"""

from __future__ import annotations

import dataclasses
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ogmapping.config import MIB, ConfigBounds
from ogmapping.config.fields import check, formed, ranged
from ogmapping.config.overrides import assign, read_mapping

LABEL = "settings"  # names the settings in refusals: "unknown settings key 'limits.max_sesions'"
PORT = 65535
# A colon is all the server asks of an address (gRPC parses the rest); "" turns an optional one off.
HOST_PORT = re.compile(r".*:.*", re.DOTALL)
HOST_PORT_OR_EMPTY = re.compile(r"(?:.*:.*)?", re.DOTALL)
URL_OR_EMPTY = re.compile(r"(?:.*://.*)?", re.DOTALL)


@dataclass
class Limits:
    """What one client may ask of the server; exceeding any gives RESOURCE_EXHAUSTED."""

    max_sessions: int = ranged(4, 1)
    queue_depth: int = ranged(8, 1)  # frames read ahead per session before backpressure
    realtime_queue_depth: int = ranged(1, 1)  # realtime sessions: newest frames kept waiting; older ones are skipped
    max_queued_bytes: int = ranged(256 * MIB, 1)  # access: decoded frames one session holds queued before backpressure
    max_image_pixels: int = ranged(4096 * 3072, 1)  # per colour/depth image and per render
    max_message_bytes: int = ranged(64 * MIB, 1)  # gRPC send/receive limit
    max_anchors: int = ranged(0, 0)  # frames are refused once a map holds this many anchors; 0 = no limit
    # the largest snapshot RestoreSession accepts (buffered before it is read)
    max_snapshot_bytes: int = ranged(256 * MIB, 1)
    # GetSnapshot calls of one session at once (each holds its snapshot's bytes while its client reads them)
    max_snapshots_per_session: int = ranged(2, 1)
    # --- recording: what a realtime session's skipped frames may add to its recording (mapped frames are
    # always recorded); beyond either, a skipped frame is acknowledged as not recorded. 0: none recorded.
    max_skipped_recording_bytes: int = ranged(1024 * MIB, 0)  # per session, over its life on this server
    skipped_recording_bytes_per_second: int = ranged(4 * MIB, 0)  # per session; bursts of one second's worth
    # --- CorrectPoses: entries one call may hold (more: RESOURCE_EXHAUSTED), and how far one entry may move a
    # keyframe from the pose it has (further: INVALID_ARGUMENT, a jump no SLAM correction makes)
    max_pose_corrections: int = ranged(10000, 1)
    max_correction_metres: float = ranged(5.0, 0.0, open_low=True)
    max_correction_degrees: float = ranged(30.0, 0.0, 180.0, open_low=True)


# --- access: who may call (TLS, API keys), how much one caller may hold, how long the server waits, metrics
SHA256_HEX = re.compile(r"[0-9a-f]{64}")


@dataclass
class Access:
    """Transport security, callers and the limits that keep one caller from starving the others.

    Timeouts in seconds; 0 turns a timeout (or a per-caller limit) off.
    """

    tls_cert: str = ""  # PEM certificate chain; with tls_key the server speaks only TLS
    tls_key: str = ""
    tls_client_ca: str = ""  # PEM CA bundle: clients must present a certificate it signed (mutual TLS)
    api_keys_file: str = ""  # lines "NAME:SHA256HEX" (python -m ogserver.apikeys NAME makes one)
    # NAME -> sha256 hex of the key, as in the file
    api_keys: dict[str, str] = formed(dict, SHA256_HEX, "the key's sha256 as 64 lowercase hex digits")
    # HOST:PORT for Prometheus /metrics; empty = off
    metrics_address: str = formed("", HOST_PORT_OR_EMPTY, "HOST:PORT or empty (off)")
    max_sessions_per_client: int = ranged(0, 0)  # sessions one caller identity may hold; 0 = only max_sessions
    max_label_chars: int = ranged(256, 0)
    max_concurrent_calls: int = ranged(32, 1)  # mapping calls at once; health checks are served beside them
    # of those, the most one caller (API key, else client certificate, else address) may hold; 0 = no share
    max_calls_per_caller: int = ranged(16, 0)
    # a session without calls, stream or queued frames this long is closed
    session_idle_seconds: float = ranged(3600.0, 0)
    stream_idle_seconds: float = ranged(300.0, 0)  # a frame stream whose client sends nothing this long is ended
    restore_idle_seconds: float = ranged(30.0, 0)  # the longest wait for the next RestoreSession chunk
    restore_seconds: float = ranged(600.0, 0)  # the longest a whole RestoreSession upload may take
    keepalive_seconds: float = ranged(60.0, 0)  # HTTP/2 ping interval, so dead clients release their streams
    keepalive_timeout_seconds: float = ranged(20.0, 0)
    # wrong keys or tokens per client address and window, then RESOURCE_EXHAUSTED
    max_auth_failures: int = ranged(20, 0)
    auth_failure_window_seconds: float = ranged(60.0, 0)
    # the same from all addresses together (a right credential always passes)
    max_auth_failures_total: int = ranged(200, 0)
    # the longest wait for a unary call's request message once its headers came
    request_seconds: float = ranged(10.0, 0)
    # the longest a response message may wait for its client to take it (an unread GetSnapshot would hold its
    # call slot for as long as the connection stays open); the call then ends
    response_seconds: float = ranged(30.0, 0)
    max_streams_per_connection: int = ranged(256, 1)  # HTTP/2 streams (calls) one connection may have open at once
    max_metrics_connections: int = ranged(16, 1)  # /metrics connections served at once; more are closed at once

    @property
    def open(self) -> bool:
        """No API keys and no client certificates: every caller is the same anonymous one."""
        return not (self.api_keys or self.api_keys_file or self.tls_client_ca)


ORIGIN = re.compile(r"null|[a-z][a-z0-9+.-]*://[^/\s]*")  # what browsers send: scheme://host[:port], or null
# A DNS name: labels of letters, digits and inner hyphens; a leading dot stands for a domain and every name under it.
HOST_LABEL = r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
HOST_NAME = re.compile(rf"\.?{HOST_LABEL}(?:\.{HOST_LABEL})*\.?")


@dataclass
class Live:
    """The live view: each session's latest render and map, in Foxglove and in the recordings."""

    foxglove_host: str = "127.0.0.1"  # the Foxglove WebSocket server's address
    foxglove_port: int = ranged(-1, -1, PORT)  # -1: no Foxglove server; 0: any free port (the log names it)
    view_seconds: float = ranged(1.0, 0)  # at most one render and point cloud per session this often; 0: views off
    view_points: int = ranged(50_000, 1)  # the point cloud's bound (Gaussians from anchors spread over the map)
    record_views: bool = True  # write keyframes' render and point cloud into the recordings
    # --- the Foxglove port's gate (docs/foxglove.md, "Access"): a file holding the operator's token, which
    # sees every session ("" = none; every other client shows the web view's credentials), and the browser
    # origins allowed (clients that send no Origin always are)
    foxglove_token_file: str = ""
    foxglove_origins: list[str] = formed(list, ORIGIN, "an origin such as https://app.foxglove.dev "
                                                       "(scheme://host[:port], no path) or null")
    # --- the web view (docs/service.md, "Web view"): each session's map as Gaussians in a browser, served
    # on the address's host with the gRPC port's TLS and callers
    web_port: int = ranged(-1, -1, PORT)  # -1: off; 0: any free port (the log names it)
    # a map's Gaussians are decoded for the web view at most this often
    web_seconds: float = ranged(0.5, 0, open_low=True)
    # host names the web view answers for beside localhost, IP addresses and the machine's own names (a request
    # naming any other host is refused: DNS rebinding); ".example.org" allows that domain and the names under it
    web_hosts: list[str] = formed(list, HOST_NAME, "a host name such as maps.example.org, or .example.org for "
                                                   "a domain and the names under it")

    @property
    def foxglove(self) -> bool:
        return self.foxglove_port >= 0


@dataclass
class Settings:
    address: str = formed("127.0.0.1:50051", HOST_PORT, "HOST:PORT")
    record_dir: str = "recordings"
    device: str = "auto"  # auto, cpu, cuda, cuda:N
    final_snapshots: bool = False  # write <session>.safetensors next to the recording on close
    torch_threads: int = ranged(0, 0)  # 0: min(cpu count, 8)
    grace_seconds: float = ranged(5.0, 0)  # how long shutdown waits for calls in flight
    warm_up: bool = True  # map a tiny synthetic scene before serving, so the first session pays no load costs
    limits: Limits = field(default_factory=Limits)
    # --- record: shutdown and closing never wait without a bound
    # How long closing a session waits for the frame being mapped, and shutdown (after the grace) for
    # gRPC's calls to end; then the recordings are finished regardless.
    stop_timeout_seconds: float = ranged(10.0, 0)
    access: Access = field(default_factory=Access)
    # --- input: what one session's config and one frame may cost
    config_bounds: ConfigBounds = field(default_factory=ConfigBounds)  # on CreateSession's and snapshots' configs
    # the image size (pixels) a session's step multiple counts from (config resolution.reference_pixels, which a
    # client may not set otherwise): sqrt(frame pixels / this), rounded; 0 keeps every session at 1
    resolution_reference_pixels: int = ranged(204000, 0)
    # a frame's optimisation stops after this long, or at once on close; 0 = no limit
    frame_seconds: float = ranged(60.0, 0)
    # --- crashes: a checkpoint of each session's map every this many recorded frames (0: only the one
    # written when it opens); at start, resume the sessions a crashed server left open
    checkpoint_interval: int = ranged(50, 0)
    resume: bool = True
    # --- worker mode (docs/service.md, "Worker processes"): sessions in this many child processes of the
    # server, each mapping under its own interpreter lock, placed on the least-loaded; 0 = threads of this process
    workers: int = ranged(0, 0)
    live: Live = field(default_factory=Live)
    # --- cluster mode (docs/cluster.md): sessions as named Ray actors; "" = sessions in this process
    cluster: str = ""  # a Ray address: "auto", HOST:PORT of a head node, or ray://HOST:PORT (Ray Client)
    session_cpus: float = ranged(1.0, 0)  # each session actor's Ray resource request
    session_gpus: float = ranged(0.0, 0)  # a fraction of a GPU shares one among several sessions
    # the longest wait for the address to answer at start; 0: Ray decides
    cluster_connect_seconds: float = ranged(15.0, 0)
    # An fsspec URL (s3://bucket/prefix, file:///mnt/shared, ...) holding recordings and checkpoints for every
    # node, record_dir being each node's scratch space; "" = record_dir itself is shared (NFS, a shared volume).
    shared_storage: str = formed("", URL_OR_EMPTY, "an fsspec URL such as s3://bucket/prefix, or empty")

    def validate(self) -> None:
        """Every field against its declaration, then the rules between fields; ValueError names the key."""
        check(self, LABEL)
        problem = conflict(self)
        if problem:
            raise ValueError(f"{LABEL} {problem}")

    def threads(self) -> int:
        return self.torch_threads or max(1, min(os.cpu_count() or 1, 8))


def conflict(settings: Settings) -> str:
    """The first pair of fields whose values do not go together, in words; "" when none."""
    access, live = settings.access, settings.live
    if bool(access.tls_cert) != bool(access.tls_key):
        return "access.tls_cert and access.tls_key go together"
    if access.tls_client_ca and not access.tls_cert:
        return "access.tls_client_ca needs access.tls_cert and access.tls_key"
    if live.foxglove and not live.view_seconds:
        return "live.foxglove_port needs live.view_seconds > 0 (0 turns the views off)"
    if settings.cluster and live.foxglove:
        return "live.foxglove_port: the live view is not available in cluster mode yet"
    if settings.cluster and live.web_port >= 0:
        return "live.web_port: the web view is not available in cluster mode yet"
    if settings.workers and settings.cluster:
        return "workers and cluster do not go together (cluster mode's sessions are Ray actors already)"
    if settings.shared_storage and not settings.cluster:
        return f"shared_storage is for cluster mode only (got {settings.shared_storage!r} without cluster)"
    return ""


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
