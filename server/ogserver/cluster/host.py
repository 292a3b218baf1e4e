"""``ClusterHost``: the ``SessionHost`` of a front-end whose sessions live in named, detached Ray actors.

Creating a session reserves its place in the cluster's ``Directory`` (limits cluster-wide), starts a
``SessionActor`` named after the session id with the configured resource request (Ray places it on
a node that has them) and opens the session inside it. Any front-end finds any session by that name,
so a client may stream through one front-end and render through another. A front-end holds no map
and keeps nothing a session needs: stopping it leaves every session running in the cluster.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import grpc
import ray
from ogapi.v1 import mapping_pb2 as pb
from ray import ObjectRef
from ray.actor import ActorHandle
from ray.exceptions import GetTimeoutError, RayActorError

from ogserver import validation
from ogserver.cluster.actor import SessionActor
from ogserver.cluster.directory import Directory
from ogserver.cluster.remote import ACK_GROUP, RemoteSession, call, outcome
from ogserver.counters import FrameTotals
from ogserver.errors import ServiceError
from ogserver.hosting import Closed, HostedSession, Opened, Upload
from ogserver.registry import check_label, new_session_id, requested_config
from ogserver.settings import Settings

log = logging.getLogger(__name__)
NAMESPACE = "ogmapping"
DIRECTORY_NAME = "directory"
# A session actor that no node can take (its CPUs/GPUs are all requested) stays pending; after this
# long the CreateSession is refused instead of waiting for a node to join or a session to close.
PLACEMENT_SECONDS = 120.0
ACTOR_CONCURRENCY = 16  # a blocked frame offer, the ack poll, renders, stats and snapshots side by side
MAX_RESTARTS = 3  # Ray restarts a session's actor (on any node) this often after its process or node died


def actor_name(session_id: str) -> str:
    return f"session-{session_id}"


class ClusterHost:
    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.record_dir = Path(settings.record_dir)
        ray.init(address=settings.cluster, namespace=NAMESPACE, log_to_driver=False)
        self.device = f"ray cluster {settings.cluster}"
        self._directory = ray.remote(Directory).options(
            name=DIRECTORY_NAME, namespace=NAMESPACE, lifetime="detached", get_if_exists=True, num_cpus=0,
        ).remote()
        self._actor = ray.remote(concurrency_groups={ACK_GROUP: 1})(SessionActor)
        log.info("cluster mode: sessions are Ray actors in namespace %r of %s (%g CPUs, %g GPUs each)", NAMESPACE,
                 settings.cluster, settings.session_cpus, settings.session_gpus)

    def check_label(self, label: str) -> None:
        check_label(label, self.settings)

    def create(self, request: pb.CreateSessionRequest, owner: str) -> Opened:
        requested_config(request, self.settings)  # refuse a bad request before an actor is started for it
        return self._place(owner, lambda actor, session_id: actor.open.remote(request.SerializeToString(), owner,
                                                                              session_id))

    def restore(self, owner: str, receive: Callable[[], Upload]) -> Opened:
        """The place is reserved before ``receive`` reads the snapshot: a full cluster refuses at once."""
        return self._place(owner, lambda actor, session_id: actor.restore.remote(owner, receive(), session_id))

    def _place(self, owner: str, opening: Callable[[ActorHandle, str], ObjectRef]) -> Opened:
        limits = self.settings.limits.max_sessions, self.settings.access.max_sessions_per_client
        call(self._directory, "reserve", owner, *limits)
        committed = False
        try:
            session_id = new_session_id()
            actor = self._actor.options(
                name=actor_name(session_id), namespace=NAMESPACE, lifetime="detached",
                num_cpus=self.settings.session_cpus, num_gpus=self.settings.session_gpus,
                max_concurrency=ACTOR_CONCURRENCY, max_restarts=MAX_RESTARTS,
            ).remote(self.settings, session_id)
            try:
                config, token, recording = self._opened(actor, opening(actor, session_id))
            except BaseException:
                ray.kill(actor)
                raise
            call(self._directory, "commit", owner, session_id)
            committed = True
        finally:
            if not committed:
                call(self._directory, "release", owner)
        log.info("session %s opened for %s in a Ray actor", session_id, owner)
        return Opened(RemoteSession(actor, config, recording), token)

    def _opened(self, actor: ActorHandle, pending: ObjectRef) -> tuple[pb.SessionConfig, str, Path]:
        try:
            ray.get(actor.__ray_ready__.remote(), timeout=PLACEMENT_SECONDS)
        except GetTimeoutError:
            raise ServiceError(grpc.StatusCode.RESOURCE_EXHAUSTED,
                               f"no node of the cluster could take the session within {PLACEMENT_SECONDS:g} s "
                               f"({self.settings.session_cpus:g} CPUs, {self.settings.session_gpus:g} GPUs)") from None
        except RayActorError:
            pass  # its start failed: the opening call says why
        config, token, recording = outcome(pending, "open")
        return pb.SessionConfig.FromString(config), token, Path(recording)

    def _actor_of(self, session_id: str, field: str) -> ActorHandle:
        try:
            return ray.get_actor(actor_name(session_id), namespace=NAMESPACE)
        except ValueError:
            raise ServiceError(grpc.StatusCode.NOT_FOUND, f"{field}: no session {session_id}") from None

    @staticmethod
    def _remote(actor: ActorHandle, described: tuple[bytes, str]) -> RemoteSession:
        config, recording = described
        return RemoteSession(actor, pb.SessionConfig.FromString(config), Path(recording))

    def get(self, session_id: str, token: str, field: str = "session_id") -> HostedSession:
        session_id = validation.session_id(session_id, field)
        actor = self._actor_of(session_id, field)
        return self._remote(actor, call(actor, "authorize", token))

    def touch(self, session: HostedSession) -> None:
        assert isinstance(session, RemoteSession)
        call(session.actor, "touch")

    def sessions(self, owner: str | None = None) -> list[HostedSession]:
        found: list[HostedSession] = []
        for session_id in call(self._directory, "sessions", owner):
            try:
                actor = self._actor_of(session_id, "session_id")
                found.append(self._remote(actor, call(actor, "describe")))
            except ServiceError as error:  # closed meanwhile, or its node is gone: listed once it is back
                log.info("session %s not listed: %s", session_id, error.message)
        return found

    def frame_totals(self) -> FrameTotals:
        """Frames of the sessions open in the cluster now (closed ones are no longer counted in cluster mode)."""
        totals = FrameTotals()
        for session in self.sessions():
            totals += FrameTotals.of(session.counters())
        return totals

    def _forget(self, session: RemoteSession) -> None:
        call(self._directory, "drop", session.id)
        ray.kill(session.actor)

    def close(self, session: HostedSession) -> Closed:
        assert isinstance(session, RemoteSession)
        closed = call(session.actor, "close")
        self._forget(session)
        return closed

    def expire_idle(self) -> list[Closed]:
        """Each idle session closes itself in its actor (its registry's own expiry); its actor then goes."""
        expired = []
        for session in self.sessions():
            assert isinstance(session, RemoteSession)
            try:
                closed = call(session.actor, "expire_idle")
            except ServiceError:  # closed by another front-end meanwhile, or unavailable
                continue
            if closed:
                self._forget(session)
                expired.extend(closed)
        return expired

    def close_all(self, timeout: float) -> list[Closed]:
        """A front-end stopping closes nothing: its sessions stay in the cluster for the other front-ends."""
        ray.shutdown()
        return []
