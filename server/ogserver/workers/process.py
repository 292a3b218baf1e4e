"""One worker process as the server sees it: started, called, and lost when it dies.

Calls from any thread go out on the socket pair tagged with an id; a reader thread matches each
reply to its caller and hands each stream event to the stream it is tagged for. When the worker's
end closes (the process died, or was killed with SIGKILL), every call waiting on it, every call
after, and every stream it fed answer UNAVAILABLE naming what happened; the server's other workers
are untouched.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
from concurrent.futures import Future
from typing import Any

import grpc

from ogserver.errors import ServiceError
from ogserver.sessions.counters import FrameTotals
from ogserver.sessions.stream_events import Lost, StreamEvent
from ogserver.settings import Settings
from ogserver.workers import codec

log = logging.getLogger(__name__)
START_SECONDS = 300.0  # a worker imports torch and the engine and warms up (minutes on a busy 2-core machine)
STOP_SECONDS = 10.0  # after the server asked it to stop, then SIGKILL


def how_it_ended(code: int | None) -> str:
    if code is None:
        return "its connection to the server closed"
    if code < 0:
        return f"killed by {signal.Signals(-code).name}"
    return f"exit status {code}"


class Worker:
    def __init__(self, number: int, process: subprocess.Popen, sock: socket.socket) -> None:
        self.number = number
        self.process = process
        self.load = 0  # sessions placed on it, counting those being opened (the host's lock guards it)
        self.totals = FrameTotals()  # its frame totals when last read: what a dead worker still counts
        self._sock = sock
        self._send_lock = threading.Lock()
        self._lock = threading.Lock()
        self._calls: dict[int, Future[Any]] = {}
        self._sinks: dict[int, queue.SimpleQueue[StreamEvent]] = {}
        self._ids = itertools.count()
        self.lost: ServiceError | None = None
        self._stopping = False  # the server asked it to exit: its end is no loss
        self._reader = threading.Thread(target=self._read, name=f"worker-{number}", daemon=True)

    @property
    def alive(self) -> bool:
        return self.lost is None

    @property
    def pid(self) -> int:
        return self.process.pid

    @classmethod
    def spawn(cls, number: int, settings: Settings, threads: int) -> Worker:
        """Start the process and hand it the settings; ``ready`` waits for it to serve."""
        ours, theirs = socket.socketpair()
        # Before numba loads in the worker: its sessions run parallel kernels concurrently (as in __main__),
        # each kernel on the worker's share of the cores, as torch's calls.
        env = {**os.environ, "NUMBA_THREADING_LAYER": os.environ.get("NUMBA_THREADING_LAYER", "threadsafe"),
               "NUMBA_NUM_THREADS": str(threads)}
        process = subprocess.Popen([sys.executable, "-m", "ogserver.workers.worker", str(theirs.fileno()),
                                    str(threads)], pass_fds=(theirs.fileno(),), env=env)
        theirs.close()
        codec.send(ours, dataclasses.asdict(settings))
        return cls(number, process, ours)

    def ready(self) -> Worker:
        self._sock.settimeout(START_SECONDS)
        try:
            kind, pid = codec.receive(self._sock)
        except (EOFError, OSError) as error:
            self.process.kill()
            raise RuntimeError(f"worker process {self.number} did not start ({how_it_ended(self.process.wait())}; "
                               f"its log lines above say why): {error}") from None
        self._sock.settimeout(None)
        assert kind == "ready" and pid == self.pid
        self._reader.start()
        log.info("worker %d (pid %d) serving", self.number, self.pid)
        return self

    def call(self, method: str, *args: Any) -> Any:
        """The worker's answer; its refusal raised again as it was, a dead worker as UNAVAILABLE."""
        future: Future[Any] = Future()
        with self._lock:
            if self.lost is not None:
                raise self.lost
            call_id = next(self._ids)
            self._calls[call_id] = future
        try:
            with self._send_lock:
                codec.send(self._sock, ["call", call_id, method, list(args)])
        except OSError:
            self._lose()
        try:
            return future.result()
        except codec.RemoteFailure as failure:  # the servicer answers INTERNAL with its text
            raise RuntimeError(str(failure)) from None

    def attach(self, sink: queue.SimpleQueue[StreamEvent]) -> int:
        """A number for a stream: the worker tags that stream's events with it, and they go to ``sink``."""
        with self._lock:
            if self.lost is not None:
                raise self.lost
            number = next(self._ids)
            self._sinks[number] = sink
        return number

    def detach(self, number: int) -> None:
        with self._lock:
            self._sinks.pop(number, None)

    def _read(self) -> None:
        try:
            while True:
                message = codec.receive(self._sock)
                if message[0] == "reply":
                    _, call_id, ok, value = message
                    with self._lock:
                        future = self._calls.pop(call_id, None)
                    if future is None:  # failed already: its request could not be sent
                        continue
                    if ok:
                        future.set_result(value)
                    else:
                        future.set_exception(value)
                elif message[0] == "event":
                    with self._lock:
                        sink = self._sinks.get(message[1])
                    if sink is not None:
                        sink.put(message[2])
        except (EOFError, OSError):
            pass
        self._lose()

    def _lose(self) -> None:
        """The worker is gone: fail whatever waits on it, and everything asked of it from now on."""
        with self._lock:
            if self.lost is not None:
                return
            try:
                code = self.process.wait(STOP_SECONDS)
            except subprocess.TimeoutExpired:
                code = None
            self.lost = ServiceError(
                grpc.StatusCode.UNAVAILABLE,
                f"the worker process that held the session stopped ({how_it_ended(code)}); the server's other "
                f"sessions go on, and a server restarted with --resume brings this one back with every "
                f"acknowledged frame")
            calls, self._calls = self._calls, {}
            sinks, self._sinks = self._sinks, {}
        if self._stopping:
            log.info("worker %d (pid %d) stopped (%s)", self.number, self.pid, how_it_ended(code))
        else:
            log.error("worker %d (pid %d) stopped (%s): its sessions are unavailable until the server restarts "
                      "with --resume", self.number, self.pid, how_it_ended(code))
        for future in calls.values():
            future.set_exception(self.lost)
        for sink in sinks.values():
            sink.put(Lost(self.lost))

    def stop(self) -> None:
        """Ask the worker to exit (once its sessions are closed), SIGKILL past ``STOP_SECONDS``."""
        self._stopping = True
        if self.alive:
            try:
                with self._send_lock:
                    codec.send(self._sock, ["stop"])
            except OSError:
                pass
        try:
            self.process.wait(STOP_SECONDS)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self._sock.close()
