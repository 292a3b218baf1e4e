"""``ogserver``: serve online mapping sessions over gRPC until SIGTERM/SIGINT."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading

from ogserver import LOG_FORMAT, view
from ogserver import settings as settings_module

READY_PREFIX = "ogserver listening on"
WEB_PREFIX = "ogserver web view on"  # printed just before READY_PREFIX, with --web-port

EPILOG = """\
settings come from defaults, then --config FILE (YAML or JSON with the same names, limits nested
under "limits:", TLS, callers, timeouts and metrics under "access:", the bounds on clients' configs under
"config_bounds:"), then flags. The server prints "ogserver listening on HOST:PORT" once it serves
(with port 0 the bound port is printed). SIGTERM or SIGINT stops it gracefully: calls in flight get
--grace seconds, then every session's recording is closed (and with --final-snapshots its map is
written as RECORD_DIR/<session>.safetensors). Nothing waits without a bound: what is still running
--stop-timeout seconds later is left behind, the recordings are closed regardless and the process
exits. After a crash or kill -9, the next server on the same record dir resumes the sessions left
open (same ids and tokens) from their checkpoints and recordings. See docs/service.md.

ogserver view MAP serves one snapshot's or recording's map in the web view on 127.0.0.1 instead, behind a
random token, and prints "ogserver map view on URL" (what ogclient view runs; ogserver view --help)."""


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="ogserver", description=__doc__, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--address", help="HOST:PORT to listen on (default 127.0.0.1:50051; port 0 = any free port)")
    p.add_argument("--record-dir", dest="record_dir", help="where session recordings (.mcap) go (default recordings/)")
    p.add_argument("--device", help="auto (default: first GPU if any, else CPU), cpu, cuda or cuda:N")
    p.add_argument("--config", help="YAML or JSON settings file")
    p.add_argument("--final-snapshots", dest="final_snapshots", action="store_true", default=None,
                   help="write each session's map into the record dir when it closes")
    p.add_argument("--torch-threads", dest="torch_threads", type=int, help="torch CPU threads (default min(cores, 8))")
    p.add_argument("--grace", dest="grace_seconds", type=float, help="shutdown grace for calls in flight, seconds (5)")
    p.add_argument("--stop-timeout", dest="stop_timeout_seconds", type=float,
                   help="how long closing a session waits for the frame being mapped, and shutdown for gRPC "
                        "after the grace, before closing the recordings regardless, seconds (10)")
    p.add_argument("--no-warm-up", dest="warm_up", action="store_false", default=None,
                   help="serve at once, without first mapping a tiny synthetic scene (which loads the compiled "
                        "kernels, ~2 s, so the first mapping session does not wait for them)")
    p.add_argument("--frame-seconds", dest="frame_seconds", type=float,
                   help="wall-clock budget of one frame's optimisation; it then stops early and its ack says "
                        "so (60; 0 = no limit)")
    crashes = p.add_argument_group("crashes: checkpoints and resume (docs/service.md, 'Checkpoints and resume')")
    crashes.add_argument("--checkpoint-interval", dest="checkpoint_interval", type=int, metavar="FRAMES",
                         help="write a checkpoint of each session's map every FRAMES recorded frames (50; 0 = only "
                              "the one each session writes when it opens, so a resume maps its whole recording again)")
    crashes.add_argument("--resume", dest="resume", action=argparse.BooleanOptionalAction, default=None,
                         help="at start, resume the sessions a crashed server left open in the record dir, with "
                              "their ids and tokens (default on)")
    p.add_argument("--workers", dest="workers", type=int, metavar="N",
                   help="map sessions in N worker processes (each new session on the least-loaded one, the "
                        "threads split between them) instead of threads of this process (0, the default); a "
                        "worker that dies takes only its own sessions, which --resume brings back")
    limits = p.add_argument_group("limits (exceeding one gives RESOURCE_EXHAUSTED)")
    limits.add_argument("--max-sessions", dest="max_sessions", type=int, help="open sessions at once (4)")
    limits.add_argument("--queue-depth", dest="queue_depth", type=int,
                        help="frames read ahead per session before backpressure (8)")
    limits.add_argument("--realtime-queue-depth", dest="realtime_queue_depth", type=int,
                        help="realtime sessions: newest frames kept waiting; older ones are skipped (1)")
    limits.add_argument("--max-image-pixels", dest="max_image_pixels", type=int,
                        help="pixels per frame image or render (12582912)")
    limits.add_argument("--max-message-bytes", dest="max_message_bytes", type=int,
                        help="largest gRPC message either way (67108864)")
    limits.add_argument("--max-anchors", dest="max_anchors", type=int,
                        help="refuse frames once a map holds this many anchors (0 = no limit)")
    limits.add_argument("--max-snapshot-bytes", dest="max_snapshot_bytes", type=int,
                        help="largest snapshot RestoreSession accepts (256 MiB)")
    limits.add_argument("--max-snapshots-per-session", dest="max_snapshots_per_session", type=int,
                        help="GetSnapshot calls of one session at once (2)")
    limits.add_argument("--max-skipped-recording-bytes", dest="max_skipped_recording_bytes", type=int,
                        help="realtime sessions: bytes of skipped frames recorded per session (1 GiB; 0 = none)")
    limits.add_argument("--skipped-recording-bytes-per-second", dest="skipped_recording_bytes_per_second", type=int,
                        help="realtime sessions: rate of skipped frames recorded per session (4 MiB/s; 0 = none)")
    access = p.add_argument_group("access: TLS, callers, per-caller limits, timeouts, metrics (more in --config)")
    access.add_argument("--tls-cert", dest="tls_cert", metavar="PEM", help="server certificate chain: serve TLS only")
    access.add_argument("--tls-key", dest="tls_key", metavar="PEM", help="the certificate's private key")
    access.add_argument("--tls-client-ca", dest="tls_client_ca", metavar="PEM",
                        help="require client certificates signed by this CA (mutual TLS; the certificate's "
                             "name is the caller)")
    access.add_argument("--api-keys-file", dest="api_keys_file", metavar="FILE",
                        help="NAME:SHA256 lines; creating, restoring and listing sessions then need a key as "
                             "metadata x-api-key (make one with python -m ogserver.apikeys NAME)")
    access.add_argument("--metrics-address", dest="metrics_address", metavar="HOST:PORT",
                        help="serve Prometheus metrics at http://HOST:PORT/metrics (default off)")
    access.add_argument("--max-sessions-per-client", dest="max_sessions_per_client", type=int,
                        help="sessions one caller may hold (0 = only --max-sessions)")
    access.add_argument("--max-concurrent-calls", dest="max_concurrent_calls", type=int,
                        help="mapping calls served at once; health checks are answered beside them (32)")
    access.add_argument("--session-idle-seconds", dest="session_idle_seconds", type=float,
                        help="close sessions unused this long (3600; 0 = never)")
    access.add_argument("--stream-idle-seconds", dest="stream_idle_seconds", type=float,
                        help="end frame streams whose client sends nothing this long (300; 0 = never)")
    cluster = p.add_argument_group("cluster mode: sessions as Ray actors across machines (docs/cluster.md; needs the "
                                   "'cluster' extra)")
    cluster.add_argument("--cluster", dest="cluster", metavar="ADDRESS",
                         help="serve sessions that live in named Ray actors of the cluster at ADDRESS (auto, "
                              "HOST:PORT or ray://HOST:PORT); any front-end serves any session")
    cluster.add_argument("--session-cpus", dest="session_cpus", type=float,
                         help="CPUs each session actor requests (1)")
    cluster.add_argument("--session-gpus", dest="session_gpus", type=float,
                         help="GPUs each session actor requests, a fraction shares one (0)")
    cluster.add_argument("--shared-storage", dest="shared_storage", metavar="URL",
                         help="an fsspec URL (s3://bucket/prefix, file:///mnt/shared, ...) where every node keeps "
                              "and finds recordings and checkpoints; --record-dir is then each node's scratch space "
                              "(default: --record-dir itself is a path every node sees)")
    live = p.add_argument_group("live view: each session's render, trajectory and map (docs/foxglove.md)")
    live.add_argument("--foxglove-port", dest="foxglove_port", type=int,
                      help="serve the live view to Foxglove over WebSocket on this port (0 = any free port; "
                           "default off; needs the foxglove-sdk package, the 'live' extra)")
    live.add_argument("--foxglove-host", dest="foxglove_host",
                      help="address the Foxglove server binds (127.0.0.1)")
    live.add_argument("--view-seconds", dest="view_seconds", type=float,
                      help="at most one render and point cloud per session this often (1; 0 = no views)")
    live.add_argument("--view-points", dest="view_points", type=int,
                      help="points in the map's point cloud at most (50000)")
    live.add_argument("--no-record-views", dest="record_views", action="store_false", default=None,
                      help="keep keyframes' render and point cloud out of the recordings")
    live.add_argument("--foxglove-token-file", dest="foxglove_token_file", metavar="FILE",
                      help="the operator's Foxglove token (?token=...), which sees every session; other clients "
                           "use the web view's credentials (?key=, ?token= a session token, a client certificate)")
    live.add_argument("--foxglove-origin", dest="foxglove_origins", action="append", metavar="ORIGIN",
                      help="a browser origin allowed on the Foxglove port, e.g. https://app.foxglove.dev "
                           "(repeatable; clients that send no Origin are always allowed)")
    web = p.add_argument_group("web view: each session's map as Gaussians in a browser (docs/service.md)")
    web.add_argument("--web-port", dest="web_port", type=int,
                     help="serve the web view over HTTP (HTTPS with --tls-cert) on the --address host and this "
                          "port (0 = any free port; default off); the same API keys and tokens as gRPC")
    web.add_argument("--web-seconds", dest="web_seconds", type=float,
                     help="decode a map's Gaussians for the web view at most this often, seconds (0.5)")
    web.add_argument("--web-host", dest="web_hosts", action="append", metavar="NAME",
                     help="a host name the web view answers for beside localhost, IP addresses and this machine's "
                          "names, e.g. maps.example.org, or .example.org for the names under it (repeatable); "
                          "requests naming any other host get 403")
    p.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING (default INFO)")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["view"]:
        return view.main(argv[1:])
    args = parser().parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format=LOG_FORMAT)
    flags = {key: value for key, value in vars(args).items() if key not in ("config", "log_level")}
    try:
        settings = settings_module.load(args.config, flags)
    except (OSError, ValueError) as error:
        print(f"ogserver: {error}", file=sys.stderr)
        return 2
    # Sessions map in parallel threads; numba's default fallback layer (workqueue) aborts the process
    # on concurrent parallel kernels, so insist on a thread-safe one (OpenMP or TBB).
    os.environ.setdefault("NUMBA_THREADING_LAYER", "threadsafe")
    logging.getLogger("ogserver").info("starting: loading torch and the mapping engine")
    from ogserver.app import build  # torch and the engine load only once the arguments are sound

    try:
        server = build(settings)
    except (RuntimeError, ValueError) as error:
        print(f"ogserver: {error}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for number in (signal.SIGTERM, signal.SIGINT):
        signal.signal(number, lambda *_: stop.set())
    host = settings.address.rsplit(":", 1)[0]
    if server.web is not None:
        print(f"{WEB_PREFIX} {server.web.url(host)}", flush=True)
    print(f"{READY_PREFIX} {host}:{server.port} (device {server.registry.device})", flush=True)
    while not stop.wait(0.5):
        pass
    log = logging.getLogger("ogserver")
    log.info("shutting down")
    stopped = server.stop(settings.grace_seconds, settings.stop_timeout_seconds)
    for closed in stopped.closed:
        print(f"closed session {closed.stats.session_id}: recording {closed.recording}"
              + (f", snapshot {closed.snapshot}" if closed.snapshot else ""), flush=True)
    if not stopped.complete:
        # Threads still running would keep the interpreter from exiting, or crash it on the way out.
        log.warning("exiting with calls or frames still running past --stop-timeout; every recording is closed")
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
